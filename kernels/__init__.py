"""Warp kernels of tawarp (installed as ``tawarp.kernels``).

Building blocks are small ``@wp.func``: complex arithmetic (:mod:`.cmath`), pore
functions (:mod:`.pore`), gas laws (:mod:`.gas`), the steady heat model
(:mod:`.heat`); they compose into the few kernels of :mod:`.forward`.
Everything is float64.
"""
