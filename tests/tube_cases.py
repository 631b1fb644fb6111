"""The synthetic tube, its microphones, terminations and specimens that the tube tests
measure (tests/test_tube_methods.py on exact transfer functions, tests/test_tube_synthetic.py
on noisy signals), in exp(+i omega t) as :mod:`tawarp.tube.synthetic` writes them."""

import numpy as np

from tawarp.tube import e2611, synthetic

TUBE = synthetic.Tube()
MICS = e2611.FourMics(l1=0.15, s1=0.08, l2=0.2, s2=0.08, thickness=0.03)
LOAD_A = synthetic.Setup(length_up=0.6, length_down=0.4, reflection_up=0.3, reflection_down=0.05)  # near anechoic
LOAD_B = synthetic.Setup(length_up=0.6, length_down=0.25, reflection_up=0.3, reflection_down=1.0)  # rigid end
SOURCE_DOWN = synthetic.Setup(length_up=0.6, length_down=0.4, reflection_up=0.3, reflection_down=0.05, source="down")
#: a rigid backing right behind the specimen (the surface-impedance method)
BACKED = synthetic.Setup(length_up=0.6, length_down=0.0, reflection_up=0.3, reflection_down=1.0)


def layer(f):
    """A symmetric, reciprocal specimen: 30 mm of a 20 kPa s/m^2 porous layer."""
    return synthetic.porous_layer(f, MICS.thickness, 2e4, TUBE)


def nonreciprocal(f):
    """A passive non-reciprocal specimen: the layer followed by a 20 % volume-velocity sink."""
    return layer(f) @ np.diag([1.0, 0.8])


def core(f):
    """A heated-core-like two-port: 0.2 m of a slower, lossier gas and a volume-velocity gain,
    det T = 1.6 + 0.2i (not reciprocal)."""
    k, z0 = TUBE.wavenumber(f) * 1.05, TUBE.impedance(f) * 1.2
    c, s = np.cos(k * 0.2), np.sin(k * 0.2)
    duct = np.conj(np.stack([np.stack([c, -1j * z0 * s], -1), np.stack([-1j * s / z0, c], -1)], -2))
    return duct @ np.array([[1.0, 0.0], [0.0, 1.6 + 0.2j]])
