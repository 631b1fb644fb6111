"""Many callers' fits as one batch: :func:`run_together` runs functions (a loop per data
set, say) in threads that take turns, and each call of :func:`tawarp.fit.problems.fit_batch`
or :func:`tawarp.fit.problems.predict_sets` they make (:meth:`Together.call`) waits until
every other thread waits on one too or has ended; then all the calls run as one batch
(this module knows nothing of fits, only of requests and the functions that batch them):
one LM over all their fits
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

import functools
import threading
from collections import deque
from collections.abc import Callable

_LOCAL = threading.local()


def current() -> "Together | None":
    """The :class:`Together` whose turns this thread takes (None outside
    :func:`run_together`)."""
    return getattr(_LOCAL, "together", None)


class Together:
    """Turns among the threads of :func:`run_together` and the requests they wait on.
    ``state``: what the batches share (:class:`tawarp.fit.problems.Families`, the kinds by
    family), passed to every batch."""

    def __init__(self, state=None):
        self.state = state
        self._lock = threading.Lock()
        # one condition per thread, on the one lock: a turn wakes its thread alone (64
        # threads of 50 trivial calls each took 2.1 s of CPU when each turn woke them all,
        # 0.05 s so)
        self._woken: dict[int, threading.Condition] = {}
        self._turn: int | None = None
        self._ready: deque[int] = deque()
        # thread -> (its request, the function that runs a batch of such, whether it is eager)
        self._waiting: dict = {}
        self._results: dict = {}  # thread -> its result, or the exception its batch raised
        #: batches run, and the requests in them (how far the callers kept in step)
        self.batches = 0
        self.calls = 0
        #: a batch is running (the work it does is done at once, not waited for)
        self.running = False

    def call(self, request, batch: Callable[[list, object], list], eager: bool = False):
        """``request``'s result, from ``batch(requests, state)`` (results in the requests'
        order) run once every other thread waits too, on every waiting request of that
        ``batch``; from the thread that holds the turn. ``eager``: the batch is cheap beside
        the others (host arithmetic, no launch): once every thread waits, the eager batches
        run first and alone, and their callers go on to their next request before the
        others run, so that they join the same batches as if they had not waited (the fits
        of loops that compute their evidence at different steps stay in one batch)."""
        me = _LOCAL.index
        with self._lock:
            self._waiting[me] = (request, batch, eager)
            self._hand_on()
            self._wait_turn(me)
        got = self._results.pop(me)
        if isinstance(got, BaseException):
            raise got
        return got

    def _wait_turn(self, me: int) -> None:
        while self._turn != me:
            self._woken[me].wait()

    def _hand_on(self) -> None:
        """Give the turn to the next ready thread; where none is, run the waiting requests,
        each batch function's in one call (in this thread, which holds the turn), and make
        their threads ready: the eager ones alone where any waits (:meth:`call`)."""
        if not self._ready and self._waiting:
            eager = [owner for owner, (_, _, first) in self._waiting.items() if first]
            owners_now = eager or list(self._waiting)
            by_batch: dict = {}
            for owner in owners_now:
                request, batch, _ = self._waiting[owner]
                by_batch.setdefault(batch, []).append((owner, request))
            self.running = True
            try:
                for batch, waiting in by_batch.items():
                    owners, requests = zip(*waiting)
                    self._settle(list(owners), functools.partial(batch, list(requests), self.state))
            finally:
                self.running = False
            self.batches += 1
            self.calls += len(owners_now)
            self._ready.extend(owners_now)
            for owner in owners_now:
                del self._waiting[owner]
        self._give_turn()

    def _give_turn(self) -> None:
        """The turn to the first ready thread (none where none is), and wake it."""
        self._turn = self._ready.popleft() if self._ready else None
        if self._turn is not None:
            self._woken[self._turn].notify()

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
            with self._lock:
                self._wait_turn(i)
            try:
                out[i] = f()
            except Exception as e:
                out[i] = e
            finally:
                with self._lock:
                    self._hand_on()

        self._woken = {i: threading.Condition(self._lock) for i in range(len(functions))}
        threads = [threading.Thread(target=one, args=(i, f), daemon=True) for i, f in enumerate(functions)]
        for t in threads:
            t.start()
        with self._lock:
            self._ready.extend(range(len(functions)))
            self._give_turn()
        for t in threads:
            t.join()
        return out


def run_together(functions: list[Callable[[], object]], state=None) -> list:
    """[f() for f in functions], the requests they make of :meth:`Together.call` batched
    (module doc; ``state``: what the batches share, :class:`tawarp.fit.problems.Families` for
    the fits and predictions). A function that raised gives its exception in its place."""
    return Together(state).run(functions)
