"""Scanner models: pure numpy, no I/O, frozen parameters, vectorised over blocks."""

from piezod.model.ode import HysteresisState, hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams, ThesisParams

__all__ = [
    "HysteresisParams",
    "HysteresisState",
    "ThesisParams",
    "hysteresis_step",
    "relaxed_state",
]
