"""Hardware-in-the-loop simulation: the simulated piezo stage (and, later, the simulated board).

:mod:`hil_sim.stage` is the forward time-domain model of the scanner (hysteresis ODE, creep
bank, optional effects); :mod:`hil_sim.session` runs offline measurement plans through it.
"""

from hil_sim.effects import EFFECT_NAMES, random_effect
from hil_sim.stage import Stage, StageConfig, sensor

__all__ = ["EFFECT_NAMES", "Stage", "StageConfig", "random_effect", "sensor"]
