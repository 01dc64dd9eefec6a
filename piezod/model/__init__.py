"""Scanner models: pure numpy, no I/O, frozen parameters, vectorised over blocks."""

from piezod.model.inverse import ThesisInverse, solve_half_range
from piezod.model.lambertw import lambertw0, lambertw0_exp
from piezod.model.ode import HysteresisState, hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.model.thesis import (
    MEDIUM_TUBE_TABLE_3_3,
    RETRACE,
    TRACE,
    creep_factor,
    effective_sensitivity,
    hysteresis_loop,
    max_creep_um,
    scan_range_um,
    thesis_loop,
    tilt,
)
from piezod.model.transient import loops_to_settle

__all__ = [
    "MEDIUM_TUBE_TABLE_3_3",
    "RETRACE",
    "TRACE",
    "HysteresisParams",
    "HysteresisState",
    "ThesisInverse",
    "ThesisParams",
    "creep_factor",
    "effective_sensitivity",
    "hysteresis_inverse_step",
    "hysteresis_loop",
    "hysteresis_step",
    "lambertw0",
    "lambertw0_exp",
    "loops_to_settle",
    "max_creep_um",
    "relaxed_state",
    "scan_range_um",
    "solve_half_range",
    "thesis_loop",
    "tilt",
]
