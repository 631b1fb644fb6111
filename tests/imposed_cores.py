"""Cores with imposed temperatures shared by the tests (docs/formats.md, "Imposed temperatures")."""

from tawarp.model.core import core_from_dict, load_core


def imposed_ceramic(hot: float = 650.0):
    """The bundled ceramic core with its temperatures imposed instead of solved: T_cold ->
    ``hot`` [K] along the stack, ``hot`` in the hot exchanger, back to T_cold along the buffer
    tube."""
    d = load_core("ceramic").to_dict()
    cold = d["gas"]["T_cold"]
    for seg, (t0, t1) in zip(d["segment"][1:4], [(cold, hot), (hot, hot), (hot, cold)]):
        for k in ("thermal", "heater", "h"):
            seg.pop(k, None)
        seg.update(T_start=t0, T_end=t1)
    return core_from_dict(d, "<imposed ceramic>")
