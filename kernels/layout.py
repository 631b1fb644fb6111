"""Layout of the per-parameter-set table the kernels read.

``params`` is a float64 array of shape (N_GLOBAL + n_segments * N_FIELDS, n_sets): one
column per parameter set, so that neighbouring threads read neighbouring addresses.
Rows: the globals below, then for each segment its fields at the rows below;
``tawarp.model.fields`` binds each field name to its row. ``flags`` is an int32 array (n_segments, N_FLAGS) of
what is fixed for a whole batch: the structure of the core.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

# global rows
T_COLD, P_MEAN, RADIUS, HEAT_INPUT = range(4)
N_GLOBAL = 4
# segment fields (tawarp.model.fields binds names, bounds and scaling to these rows)
LENGTH, POROSITY, PORE_RADIUS, TORTUOSITY, SOLID_CONDUCTIVITY, H = range(6)
# optional effects, each "off" at its neutral value (tawarp.model.fields):
# thermal_radius_ratio (1: r_k = r), conductivity_exponent (0), radiative_conductivity (0),
# h_convection (0), wall_conductance (0), frame_mobility (0: rigid frame), viscous_shape_factor (1),
# end_conductance (0: adiabatic ends of the heat model)
(
    THERMAL_RADIUS_RATIO,
    CONDUCTIVITY_EXPONENT,
    RADIATIVE_CONDUCTIVITY,
    H_CONVECTION,
    WALL_CONDUCTANCE,
    FRAME_MOBILITY,
    VISCOUS_SHAPE_FACTOR,
    END_CONDUCTANCE,
) = range(6, 14)
# imposed temperatures [K] at the segment's start and end (read where F_IMPOSED is set)
T_START, T_END = range(14, 16)
# thermal contact resistance [m^2 K/W] at the segment's start, against the previous thermal
# segment (0: none)
CONTACT_RESISTANCE = 16
# width [m] of an annular gap between a porous segment and the tube wall (0: none)
BYPASS_GAP = 17
# lateral thermal resistance [m^2 K/W] between the segment's gas/solid and its tube wall, 1/h_w
# (0: perfect contact, the wall at the gas temperature; > 0 with a wall_conductance: the wall
# a temperature field of its own, kernels/heat.py)
WALL_RESISTANCE = 18
N_FIELDS = 19
# structure flags per segment: F_THERMAL a segment of the heat model, F_IMPOSED one whose
# temperature profile is imposed (linear from T_START to T_END)
F_POROUS, F_PORE_MODEL, F_THERMAL, F_HEATER, F_IMPOSED = range(5)
N_FLAGS = 5

_NG = wp.constant(N_GLOBAL)
_NF = wp.constant(N_FIELDS)


@wp.func
def seg_value(params: wp.array2d(dtype=wp.float64), i: int, s: int, field: int):
    """Field ``field`` of segment ``s`` for parameter set ``i``."""
    return params[_NG + s * _NF + field, i]
