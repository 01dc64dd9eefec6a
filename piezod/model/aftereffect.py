"""The after-effect of a play (Preisach) law: thermally activated relaxation of its memory.

A Preisach law's memory is the staircase of relays left "up" or "down" by the voltage's
history. At a finite temperature relays near their switching field flip spontaneously, and the
staircase drifts towards the anhysteretic state, the one the voltage would leave if it had shaken
the ceramic's domains into equilibrium (Neel's after-effect, the Preisach-Neel model; in
ferroelectric stacks the thermally activated motion of pinned domain walls). In play-operator
form the drift moves every play's output ``p_i`` towards the voltage ``V``; with the gap
``g_i = p_i - V`` (``|g_i| <= r_i``) and an Eyring (``sinh``) rate::

    dg_i/dt = -(g0 / tau) sinh(g_i / g0)

whose solution at a held voltage is closed-form::

    tanh(g_i(t) / (2 g0)) = tanh(g_i(0) / (2 g0)) exp(-t / tau)

``g0`` (V) is the fluctuation voltage: a gap much larger than it closes logarithmically,
``g(t) ~ -g0 ln(exp(-g(0) / g0) + t / (2 tau))``, by ``g0 ln 10`` per decade of time, so the
position creeps by ``g0 ln 10`` times the slope of the plays that were moving (a log-time creep
whose amount is set by how far the history left the memory from equilibrium, not by the size of
the last step); a gap much smaller than ``g0`` decays with the time constant ``tau``. With
``g0 = inf`` the decay is linear, ``g(t) = g(0) exp(-t / tau)``. The drift also narrows the
loops of a slowly driven stage: the law is no longer rate independent.

Discretisation: the memory relaxes every ``interval`` (a whole number of samples, at least one)
by the closed form over that interval, towards the voltage of the last sample, before the next
sample's play update; at a held voltage this is exact for any interval. The per-sample
inverse therefore stays the play law's own (:func:`piezod.model.kernels.gpi_loop`), the
relaxation a separate ``O(p)`` step every interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from piezod.errors import ModelError
from piezod.model import kernels

F64 = NDArray[np.float64]

#: Default relaxation interval (s): relaxation is a slow process against the sample clock, and
#: the interval keeps its ``O(p)`` cost (two transcendental functions per play) off most samples.
DEFAULT_INTERVAL_S = 1e-3


@dataclass(frozen=True)
class AfterEffect:
    """Frozen parameters of a play law's after-effect.

    Attributes
    ----------
    fluctuation_v
        ``g0`` (V), > 0; ``inf`` for a linear relaxation.
    time_s
        ``tau`` (s), > 0.
    interval_s
        How often the memory relaxes (s), > 0 (rounded to whole samples, at least one).
    """

    fluctuation_v: float
    time_s: float
    interval_s: float = DEFAULT_INTERVAL_S

    def __post_init__(self) -> None:
        if math.isnan(self.fluctuation_v) or not self.fluctuation_v > 0.0:
            raise ModelError(f"fluctuation_v must be > 0 (inf: linear), got {self.fluctuation_v!r}")
        if not (math.isfinite(self.time_s) and self.time_s > 0.0):
            raise ModelError(f"time_s must be finite and > 0, got {self.time_s!r}")
        if not (math.isfinite(self.interval_s) and 0.0 < self.interval_s <= 1.0):
            raise ModelError(f"interval_s must lie in (0, 1] s, got {self.interval_s!r}")

    def every(self, dt_s: float) -> int:
        """Samples per relaxation at the sample interval ``dt_s``."""
        return max(1, round(self.interval_s / dt_s))

    def factor(self, seconds: float) -> float:
        """``exp(-seconds / tau)``: the relaxation over ``seconds`` at a held voltage."""
        return math.exp(-seconds / self.time_s)

    def loop_args(self, dt_s: float) -> tuple[int, float, float]:
        """The compiled loops' arguments at the sample interval ``dt_s``: samples per relaxation,
        the factor of one relaxation, ``g0``."""
        every = self.every(dt_s)
        return every, self.factor(every * dt_s), float(self.fluctuation_v)


def relax(plays_v: F64, voltage_v: float, factor: float, fluctuation_v: float) -> F64:
    """Play outputs after relaxing towards ``voltage_v`` by ``factor`` (:meth:`AfterEffect.factor`):
    a copy through the compiled step the runtime model takes every interval."""
    out = np.array(plays_v, dtype=np.float64)
    kernels.relax_plays(out, float(voltage_v), float(factor), float(fluctuation_v))
    return out


__all__ = ["DEFAULT_INTERVAL_S", "AfterEffect", "relax"]
