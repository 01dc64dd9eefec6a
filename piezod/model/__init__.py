"""Scanner models: pure numpy, no I/O, frozen parameters, vectorised over blocks."""

from piezod.model.ode import HysteresisState, hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.model.thesis import (
    RETRACE,
    TRACE,
    creep_factor,
    effective_sensitivity,
    hysteresis_loop,
    max_creep_um,
    thesis_loop,
    tilt,
)

__all__ = [
    "RETRACE",
    "TRACE",
    "HysteresisParams",
    "HysteresisState",
    "ThesisParams",
    "creep_factor",
    "effective_sensitivity",
    "hysteresis_loop",
    "hysteresis_step",
    "max_creep_um",
    "relaxed_state",
    "thesis_loop",
    "tilt",
]
