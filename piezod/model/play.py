"""Prandtl-Ishlinskii hysteresis (a weighted sum of play operators) and its exact per-sample inverse.

``x_h = b (rho0 V + sum_i w_i P_{r_i}[V])`` with play (backlash) operators of half-width ``r_i``:
on a rising voltage ``p_i = max(p_i, V - r_i)``, on a falling one ``p_i = min(p_i, V + r_i)``.
The law is rate independent, has wiping-out memory, and its minor loops close (unlike the
Coleman-Hodgdon ODE, whose repeated minor loops drift). With ``rho0 > 0`` and ``w_i >= 0`` it is
strictly increasing along every monotone voltage run, so it has an exact inverse.

Inverse
-------
Along a monotone run starting at ``V_0`` with plays ``p^0`` the position is a piecewise linear,
increasing function of ``V`` whose knots are where the plays engage (``p^0_i + r_i`` on a rising
run). Per run the knots and their positions are computed once (``O(m^2)`` for ``m`` plays), then
every target of the run is an independent ``searchsorted`` + linear interpolation: exact (to
rounding) for any targets, cost ``O(log m)`` per sample, vectorised. Runs of the targets are
runs of the voltage (the map is increasing), so a scan line costs one pass.

All positions are hysteretic positions (um) before creep and static maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.params import readonly_array

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=False)
class PlayParams:
    """Frozen parameters of a Prandtl-Ishlinskii law.

    Attributes
    ----------
    b_um_per_v
        Slope once every play moves (um/V), > 0.
    rho0
        Slope right after a reversal as a fraction of ``b``, in (0, 1].
    thresholds_v
        Play half-widths ``r_i`` (V), ascending, > 0.
    weights
        Play weights ``w_i`` (fractions of ``b``), >= 0.
    """

    b_um_per_v: float
    rho0: float
    thresholds_v: tuple[float, ...]
    weights: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.b_um_per_v) and self.b_um_per_v > 0.0):
            raise ModelError(f"b_um_per_v must be finite and > 0, got {self.b_um_per_v!r}")
        if not (math.isfinite(self.rho0) and self.rho0 > 0.0):
            raise ModelError(f"rho0 must be finite and > 0, got {self.rho0!r}")
        r, w = self.thresholds_v, self.weights
        if len(r) != len(w):
            raise ModelError(f"{len(r)} thresholds but {len(w)} weights")
        if not all(math.isfinite(x) and x > 0.0 for x in r) or list(r) != sorted(r):
            raise ModelError("thresholds_v must be finite, > 0 and ascending")
        if not all(math.isfinite(x) and x >= 0.0 for x in w):
            raise ModelError("play weights must be finite and >= 0")

    @cached_property
    def r(self) -> F64:
        """Thresholds as an array (V)."""
        return readonly_array(self.thresholds_v)

    @cached_property
    def w(self) -> F64:
        """Weights as an array."""
        return readonly_array(self.weights)

    @property
    def total_weight(self) -> float:
        """``rho0 + sum w``: the major-loop slope over ``b``."""
        return self.rho0 + float(self.w.sum())

    @classmethod
    def uniform(
        cls, b_um_per_v: float, rho0: float, span_v: float, count: int, weights: ArrayLike
    ) -> PlayParams:
        """Plays with thresholds ``(i / count) span_v / 2``, ``i = 1..count``, and the given weights."""
        r = 0.5 * span_v * np.arange(1, count + 1) / count
        return cls(
            float(b_um_per_v), float(rho0), tuple(map(float, r)), tuple(map(float, np.asarray(weights)))
        )


@dataclass(frozen=True, slots=True, eq=False)
class PlayState:
    """State after a sample: the voltage (V), every play's output (V), the position (um)."""

    voltage_v: float
    plays_v: F64
    position_um: float


def play_rest_state(params: PlayParams, voltage_v: float = 0.0) -> PlayState:
    """Relaxed at ``voltage_v``: every play centred, ``x_h = b total V``."""
    v = float(voltage_v)
    plays = np.full(params.r.size, v)
    return PlayState(v, plays, params.b_um_per_v * params.total_weight * v)


def _position(params: PlayParams, v: F64, plays: F64) -> F64:
    out: F64 = params.b_um_per_v * (params.rho0 * v + params.w @ plays)
    return out


def play_state_at(params: PlayParams, voltage_v: float, plays_v: ArrayLike) -> PlayState:
    """The state with the given voltage and play outputs (plays clipped into ``V -+ r``)."""
    v = float(voltage_v)
    p = np.clip(np.asarray(plays_v, dtype=np.float64), v - params.r, v + params.r)
    return PlayState(v, p, float(_position(params, np.array([v]), p[:, None])[0]))


def _runs(values: F64, last: float) -> tuple[NDArray[np.intp], F64]:
    sign = np.sign(np.diff(values, prepend=last))
    moving = np.flatnonzero(sign)
    if moving.size == 0:
        return np.zeros(1, dtype=np.intp), np.zeros(1)
    sm = sign[moving]
    change = np.concatenate(([0], np.flatnonzero(sm[1:] != sm[:-1]) + 1))
    starts = moving[change].astype(np.intp)
    starts[0] = 0
    return starts, sm[change]


def play_forward(params: PlayParams, voltage_v: ArrayLike, state: PlayState) -> tuple[F64, PlayState]:
    """Hysteretic positions for a block of voltages (exact at the samples).

    Parameters
    ----------
    params
        The law.
    voltage_v
        Voltages (V), shape ``(n,)``.
    state
        State before the block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise ModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    r = params.r[:, None]
    p = state.plays_v
    x = np.empty_like(v)
    starts, dirs = _runs(v, state.voltage_v)
    bounds = np.append(starts, v.size)
    for k, direction in enumerate(dirs):
        seg = v[bounds[k] : bounds[k + 1]]
        if direction > 0:
            block = np.maximum(p[:, None], seg[None, :] - r)
        elif direction < 0:
            block = np.minimum(p[:, None], seg[None, :] + r)
        else:
            block = np.repeat(p[:, None], seg.size, axis=1)
        x[bounds[k] : bounds[k + 1]] = _position(params, seg, block)
        p = block[:, -1].copy()
    return x, PlayState(float(v[-1]), p, float(x[-1]))


def _rising_inverse(params: PlayParams, targets: F64, v0: float, p0: F64, x0: float) -> tuple[F64, F64]:
    """Voltages reaching ``targets`` (ascending run, all >= ``x0``) from ``(v0, p0)``; plays at the end."""
    b, r, w = params.b_um_per_v, params.r, params.w
    knots = np.sort(p0 + r)  # where each play engages; all >= v0 for a consistent state
    knots = np.concatenate(([v0], np.maximum(knots, v0)))
    plays_at = np.maximum(p0[None, :], knots[:, None] - r[None, :])
    x_knots = b * (params.rho0 * knots + plays_at @ w)
    x_knots[0] = x0
    engaged = knots[None, 1:] <= knots[:, None]  # play j (sorted) moving after knot k
    order = np.argsort(p0 + r)
    slope = b * (params.rho0 + engaged.astype(np.float64) @ w[order])
    k = np.clip(np.searchsorted(x_knots, targets, side="right") - 1, 0, knots.size - 1)
    v = knots[k] + (targets - x_knots[k]) / slope[k]
    p_end = np.maximum(p0, v[-1] - r)
    return v, p_end


def play_inverse(params: PlayParams, position_um: ArrayLike, state: PlayState) -> tuple[F64, PlayState]:
    """Voltages whose forward law (:func:`play_forward`) reaches the hysteretic positions exactly.

    Parameters
    ----------
    params
        The law.
    position_um
        Hysteretic target positions (um), shape ``(n,)``; the first step goes from
        ``state.position_um``.
    state
        State before the block.

    Returns
    -------
    voltage_v : ndarray
        Voltages (V).
    state : PlayState
        State after the block.
    """
    x = np.asarray(position_um, dtype=np.float64)
    if x.ndim != 1:
        raise ModelError(f"position_um must be 1-D, got shape {x.shape}")
    if x.size == 0:
        return np.empty(0), state
    v_out = np.empty_like(x)
    v0, p0, x0 = state.voltage_v, state.plays_v, state.position_um
    starts, dirs = _runs(x, x0)
    bounds = np.append(starts, x.size)
    for k, direction in enumerate(dirs):
        seg = x[bounds[k] : bounds[k + 1]]
        if direction > 0:
            v, p0 = _rising_inverse(params, seg, v0, p0, x0)
        elif direction < 0:
            vn, pn = _rising_inverse(params, -seg, -v0, -p0, -x0)
            v, p0 = -vn, -pn
        else:
            v = np.full(seg.size, v0)
        v_out[bounds[k] : bounds[k + 1]] = v
        v0, x0 = float(v[-1]), float(seg[-1])
    return v_out, PlayState(v0, p0, x0)


__all__ = [
    "PlayParams",
    "PlayState",
    "play_forward",
    "play_inverse",
    "play_rest_state",
    "play_state_at",
]
