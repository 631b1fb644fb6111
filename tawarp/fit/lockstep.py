"""Many callers' fits as one batch: :func:`run_together` runs functions (a loop per data
set, say) in threads that take turns, and each call of :func:`tawarp.fit.problems.fit_batch`
or :func:`tawarp.fit.problems.predict_sets` they make waits until every other thread waits
on one too or has ended; then all the calls run as one batch: one LM over all their fits
(:func:`tawarp.fit.problems.fit_calls`), and one forward launch per structure and family
of kinds (:class:`tawarp.fit.problems.Families`) for all their parameter sets.

Why threads: a loop (:func:`tawarp.loop.run_loop`) decides what to fit next from what its
fits gave, and its host work per launch is the same for a batch of one data set's fits as
for a hundred's: on a GPU host that work, not the device, bounds how many loops a second
one process closes. The threads never run at once (one holds the turn, and hands it on at
a fit or when it ends), so the code they run needs no locks and its numbers are those of
one thread; they are threads only to keep each caller's own control flow.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

_LOCAL = threading.local()


def current() -> "Together | None":
    """The :class:`Together` whose turns this thread takes (None outside
    :func:`run_together`)."""
    return getattr(_LOCAL, "together", None)


class Together:
    """Turns among the threads of :func:`run_together` and the fits and predictions they
    wait on."""

    def __init__(self, families=None):
        from .problems import Families

        #: the kinds the threads fit, by family (each joins when first met)
        self.families = families if families is not None else Families()
        self._cond = threading.Condition()
        self._turn: int | None = None
        self._ready: deque[int] = deque()
        self._waiting: dict = {}  # thread -> its FitCall, or its list of prediction jobs
        self._results: dict = {}  # thread -> its fits, or the exception the batch raised
        #: batches run, and the calls in them (how far the callers kept in step)
        self.batches = 0
        self.calls = 0
        #: a batch is running (its fits' predictions are made at once, not waited for)
        self.running = False

    def fit(self, call):
        """``call``'s fits (:class:`tawarp.fit.problems.FitCall`), run in the batch of every
        thread's next call; from the thread that holds the turn."""
        return self._wait_for(call)

    def predict(self, jobs: list) -> list:
        """The model values of ``jobs`` (:class:`tawarp.fit.problems.Sets`), predicted in the
        batch of every thread's next call (:func:`tawarp.fit.problems.run_sets`)."""
        return self._wait_for(jobs)

    def _wait_for(self, request):
        me = _LOCAL.index
        with self._cond:
            self._waiting[me] = request
            self._hand_on()
            self._wait_turn(me)
        got = self._results.pop(me)
        if isinstance(got, BaseException):
            raise got
        return got

    def _wait_turn(self, me: int) -> None:
        while self._turn != me:
            self._cond.wait()

    def _hand_on(self) -> None:
        """Give the turn to the next ready thread; where none is, run the waiting calls as one
        batch (in this thread, which holds the turn) and make their threads ready."""
        if not self._ready and self._waiting:
            owners = list(self._waiting)
            self._run_batch([self._waiting[k] for k in owners], owners)
            self._waiting.clear()
            self._ready.extend(owners)
        self._turn = self._ready.popleft() if self._ready else None
        self._cond.notify_all()

    def _run_batch(self, requests: list, owners: list) -> None:
        """The fit calls among ``requests`` in one batch, and the lists of prediction jobs in
        one (their threads' results set)."""
        from .problems import FitCall, fit_calls

        self.running = True
        try:
            fits = [k for k, r in enumerate(requests) if isinstance(r, FitCall)]
            jobs = [k for k, r in enumerate(requests) if not isinstance(r, FitCall)]
            if fits:
                self._settle([owners[k] for k in fits], lambda: fit_calls([requests[k] for k in fits], self.families))
            if jobs:
                self._settle([owners[k] for k in jobs], lambda: self._predict([requests[k] for k in jobs]))
            self.batches += 1
            self.calls += len(requests)
        finally:
            self.running = False

    def _predict(self, lists: list[list]) -> list[list]:
        """The model values of each list of prediction jobs, all in one
        :func:`tawarp.fit.problems.run_sets`."""
        from .problems import run_sets

        flat = run_sets([j for jobs in lists for j in jobs], self.families)
        out, k = [], 0
        for jobs in lists:
            out.append(flat[k : k + len(jobs)])
            k += len(jobs)
        return out

    def _settle(self, owners: list, run: Callable[[], list]) -> None:
        """Each owner's result of ``run()``; where it raised, every owner gets the exception."""
        try:
            got = run()
        except Exception as e:
            got = [e] * len(owners)
        self._results.update(zip(owners, got))

    def run(self, functions: list[Callable[[], object]]) -> list:
        """[f() for f in functions], each in a thread of its own taking turns; a function that
        raised gives its exception in its place."""
        out: list = [None] * len(functions)

        def one(i: int, f: Callable[[], object]) -> None:
            _LOCAL.together, _LOCAL.index = self, i
            with self._cond:
                self._wait_turn(i)
            try:
                out[i] = f()
            except Exception as e:
                out[i] = e
            finally:
                with self._cond:
                    self._hand_on()

        threads = [threading.Thread(target=one, args=(i, f), daemon=True) for i, f in enumerate(functions)]
        for t in threads:
            t.start()
        with self._cond:
            self._ready.extend(range(len(functions)))
            self._turn = self._ready.popleft() if self._ready else None
            self._cond.notify_all()
        for t in threads:
            t.join()
        return out


def run_together(functions: list[Callable[[], object]], kinds: list = ()) -> list:
    """[f() for f in functions], their :func:`tawarp.fit.problems.fit_batch` calls and
    predictions batched (module doc), the kinds of one family sharing launches
    (:class:`tawarp.fit.problems.Families`; ``kinds``: those the functions fit, each family's
    first the one whose core the launches take; any other kind joins its family when first
    met). A function that raised gives its exception in its place."""
    from .problems import Families

    return Together(Families(kinds)).run(functions)
