"""The mechanical resonance as a runtime part: the targets shaped ahead so the mode does not ring.

The audit's ``resonance`` (:mod:`piezod.model.registry`) is a unit-gain second-order filter of the
quasi-static position ``x_q`` (the model's output, after the static parts):

    x'' + (w0 / Q) x' + w0^2 x = w0^2 x_q

A triangular scan excites it at every turning point (the velocity jumps), and the stage rings
there for ``Q / (pi f0)``; on a slow, long line that ringing is the line's nonlinearity. Its
inverse asks for the quasi-static position

    x_q = s + s' / (Q w0) + s'' / w0^2

where ``s`` is the target. At a turning point ``s''`` is an impulse of area ``2 v``, which the
slew limit would cut; so the target is first smoothed, over a quarter of the resonance period
each side (:data:`SMOOTHING_PERIOD_FRACTION`: ``K`` samples), by the symmetric kernel

    k = a T_K + b T_2K,    a = 4 (K + 1) / (3 K + 2),    b = -(K + 2) / (3 K + 2)

with ``T_K`` the triangular kernel of half-width ``K`` (a box of ``K + 1`` samples applied twice).
Its weights sum to 1 and its second moment is 0, so it keeps every polynomial up to the third
degree: a straight stretch of the scan stays exactly as it was, and at a turning point the smoothed
target leaves the apex (by about ``2 v dt K / 9``, a third less than ``T_K`` alone) with a
deviation of zero area, so a line's regression slope -- its length -- is kept to first order. The
triangular kernel alone rounds the apex by ``v dt K (K + 2) / (3 (K + 1))`` to one side only: on
moss23's 135 Hz mode a 20 Hz line read 0.55 % short from the rounding alone (docs/model-family.md
6.2aa). The derivatives are centred differences of the smoothed target, so the part needs the
targets ``2 K + 1`` samples ahead of the one it shapes (:meth:`ResonancePart.lookahead`): the
driver is handed them by the job, which knows its trajectory ahead
(:meth:`piezod.trajectory.Trajectory.peek`); without them the last target is taken to hold.

The shaping is linear, so where it sits in the inverse chain does not matter up to the drift,
which moves by nm per second: the driver shapes the targets, then the model's own inverse
(with its parts) turns the shaped targets into voltages. Cost: ``O(1)`` per sample (four moving
sums), vectorised; ``K <= MAX_HALF_WIDTH``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.registry import spec

F64 = NDArray[np.float64]

#: Parameters of the effect ``resonance`` the part takes.
RESONANCE_PARAMS: tuple[str, ...] = ("f0_hz", "q")
#: Half-width of the smoothing kernel, as a fraction of the resonance period: a trade between the
#: slew limit, which cuts a narrow pulse, and the rounding of the apex, which shortens a fast line's
#: regression. Measured on a 290 Hz, Q 28 stage slew-limited at 12 kV/s (lark22), 31 um at 20 Hz:
#: |length error| 1.1 % at 1/8, 0.19 % at 1/4, 0.51 % at 1/2 with the triangle alone (6.2y); with
#: the kernel of zero second moment, on lark22 / moss23 / fern21's 20 Hz lines, 1.63 / 2.31 / 0.70 %
#: at 1/8, 0.08 / 1.36 / 0.38 % at 1/4, 0.03 / 1.39 / 0.28 % at 3/8 (docs/model-family.md 6.2aa).
SMOOTHING_PERIOD_FRACTION = 0.25
#: Largest ``K`` (samples): bounds the targets needed ahead of a block (``2 K + 1``).
MAX_HALF_WIDTH = 64


@dataclass(frozen=True)
class ResonancePart:
    """Frozen parameters of the resonance part (``f0_hz`` infinite: off).

    Attributes
    ----------
    f0_hz
        Undamped resonance frequency (Hz), inside the registry's physical bounds, or ``inf``.
    q
        Quality factor, inside the registry's physical bounds.
    """

    f0_hz: float = math.inf
    q: float = 10.0

    def __post_init__(self) -> None:
        if self.off:
            return
        for name in RESONANCE_PARAMS:
            value = float(getattr(self, name))
            low, high = spec("resonance").param(name).physical
            if not (math.isfinite(value) and low <= value <= high):
                raise ModelError(f"resonance.{name} = {value!r} outside its physical range [{low}, {high}]")

    @classmethod
    def from_effects(cls, effects: Mapping[str, Mapping[str, float]]) -> ResonancePart:
        """From ``{effect id: {parameter: value}}``: the ``resonance`` entry (off without one)."""
        given = dict(effects.get("resonance") or {})
        if not given:
            return cls()
        unknown = sorted(set(given) - set(RESONANCE_PARAMS))
        if unknown:
            names = ", ".join(RESONANCE_PARAMS)
            raise ModelError(f"effect 'resonance' has no parameter {unknown[0]!r} ({names})")
        if "f0_hz" not in given:
            raise ModelError("effect 'resonance' needs f0_hz")
        return cls(**{k: float(v) for k, v in given.items()})

    @property
    def off(self) -> bool:
        """No resonance: the targets pass unchanged."""
        return math.isinf(self.f0_hz)

    def half_width(self, dt_s: float) -> int:
        """``K`` at the sample interval ``dt_s``: the inner triangle's half-width (samples; the
        kernel spans ``+-2 K``)."""
        if self.off:
            return 0
        k = round(SMOOTHING_PERIOD_FRACTION / (self.f0_hz * dt_s))
        return int(min(max(k, 1), MAX_HALF_WIDTH))

    def lookahead(self, dt_s: float) -> int:
        """Targets needed after (and before) the one shaped: ``2 K + 1`` (0 when off)."""
        return 0 if self.off else 2 * self.half_width(dt_s) + 1

    def window(self, before_um: ArrayLike, targets_um: ArrayLike, dt_s: float) -> F64:
        """The targets the next block's :meth:`shape` takes as ``before_um``: the last
        :meth:`lookahead` of ``before_um`` followed by ``targets_um``."""
        kept = np.concatenate([np.asarray(before_um, np.float64), np.asarray(targets_um, np.float64)])
        return kept[max(0, kept.size - self.lookahead(dt_s)) :].copy()

    def shape(self, targets_um: ArrayLike, before_um: ArrayLike, ahead_um: ArrayLike, dt_s: float) -> F64:
        """The quasi-static positions that bring the resonant stage to the (smoothed) targets.

        Parameters
        ----------
        targets_um
            The block's targets (um).
        before_um
            The targets before the block (at least :meth:`lookahead`; fewer: the first held).
        ahead_um
            The targets after the block (fewer than :meth:`lookahead`: the last one held).
        dt_s
            Sample interval (s).

        Returns
        -------
        ndarray
            ``x_q`` per target, same length as ``targets_um``.
        """
        x = np.asarray(targets_um, dtype=np.float64)
        if self.off or x.size == 0:
            return x.copy()
        m = self.lookahead(dt_s)
        before = np.asarray(before_um, dtype=np.float64)[-m:]
        ahead = np.asarray(ahead_um, dtype=np.float64)[:m]
        first = before[0] if before.size else x[0]
        last = ahead[-1] if ahead.size else x[-1]
        e = np.concatenate([np.full(m - before.size, first), before, x, ahead, np.full(m - ahead.size, last)])
        # a triangle of half-width w - 1 is a box of w samples applied twice (O(1) per sample);
        # e[j] for the block's sample n sits at j = n + m, and s covers n - 1 ... n + size (the
        # inner triangle, K samples narrower each side, needs e without its K outermost samples)
        k = m // 2
        w1, w2 = k + 1, m
        inner = _box_sum(_box_sum(e[k : e.size - k], w1), w1)
        outer = _box_sum(_box_sum(e, w2), w2)
        a = 4.0 * (k + 1) / (3.0 * k + 2.0)
        s = (a / (w1 * w1)) * inner + ((1.0 - a) / (w2 * w2)) * outer
        w0 = 2.0 * math.pi * self.f0_hz
        lead = 1.0 / (2.0 * dt_s * self.q * w0)
        accel = 1.0 / (dt_s * dt_s * w0 * w0)
        out: F64 = (1.0 - 2.0 * accel) * s[1:-1]
        out += (accel + lead) * s[2:]
        out += (accel - lead) * s[:-2]
        return out


def _box_sum(x: F64, width: int) -> F64:
    """Moving sum over ``width`` samples, only where the window is inside ``x``."""
    c = np.cumsum(x)
    out: F64 = c[width - 1 :].copy()
    out[1:] -= c[:-width]
    return out


__all__ = ["MAX_HALF_WIDTH", "RESONANCE_PARAMS", "SMOOTHING_PERIOD_FRACTION", "ResonancePart"]
