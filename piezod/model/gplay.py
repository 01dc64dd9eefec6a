"""A generalised play law: a Preisach law whose density depends on the relay's width *and* centre.

A Preisach law sums relays (switching up at ``alpha``, down at ``beta``) with a non-negative
density ``mu``. Writing a relay by its half-width ``r = (alpha - beta) / 2`` and centre
``c = (alpha + beta) / 2``, the relays of one half-width that are "up" after any input history
are exactly those with centre below the output of the play operator ``P_r[V]``, so *any*
Preisach law is a sum over widths of monotone functions of the play outputs (Brokate and
Sprekels, *Hysteresis and Phase Transitions*, 1996, ch. 2)::

    x_h = H_0(V) + sum_i H_i(P_{r_i}[V]),     H_i'(c) = mu_i(c) >= 0

``H_0`` (width zero) is the reversible part, a monotone static map of the voltage (the static
input map before the hysteresis). A Prandtl-Ishlinskii law is the special case of a density
that does not depend on the centre (every ``H_i`` linear). Here each density ``mu_i`` is
piecewise linear in the centre over shared nodes ``c_0 < ... < c_{K-1}`` (constant beyond the
end nodes), so ``H_i`` is piecewise quadratic, increasing, with a continuous slope; loops are
asymmetric and minor loops at different offsets differ, while the law keeps wiping-out memory
(minor loops close). The densities enter linearly, so the calibration fits them by
non-negative least squares (:mod:`piezod.calibrate_family`).

Inverse
-------
Along a monotone voltage run every play is either held or moves with the voltage, and a
moving play's ``H_i`` is quadratic between the nodes: the position is piecewise quadratic in
the voltage with knots where a play engages (``p_i +- r_i``) or a moving play crosses a node
(``c_j +- r_i``). The exact inverse walks these pieces from the previous voltage and solves one
quadratic on the last (:func:`piezod.model.kernels.gpi_loop`, a compiled per-sample loop of
bounded cost ``O(p K)`` per piece, one piece at realistic sample rates).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.params import readonly_array
from piezod.model.play import PlayState, _runs

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GeneralisedPlayParams:
    """Frozen parameters of a generalised play (Preisach) law.

    Attributes
    ----------
    thresholds_v
        Play half-widths ``r_i`` (V), ascending, > 0.
    nodes_v
        Centre nodes ``c_j`` (V), ascending, at least two.
    density
        ``mu_i(c_j)`` (um/V), shape ``(len(thresholds) + 1) x len(nodes)`` as nested tuples, >= 0;
        row 0 is the reversible part ``H_0``, row ``i`` the play of half-width ``r_i``. The
        reversible row must be > 0 at every node (the law's slope right after a reversal).
    """

    thresholds_v: tuple[float, ...]
    nodes_v: tuple[float, ...]
    density: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        r, c = self.thresholds_v, self.nodes_v
        if not all(math.isfinite(x) and x > 0.0 for x in r) or list(r) != sorted(r):
            raise ModelError("thresholds_v must be finite, > 0 and ascending")
        ascending = all(b > a for a, b in itertools.pairwise(c))
        if len(c) < 2 or not all(math.isfinite(x) for x in c) or not ascending:
            raise ModelError("nodes_v must be at least two finite, strictly ascending voltages")
        if len(self.density) != len(r) + 1 or any(len(row) != len(c) for row in self.density):
            raise ModelError(f"density must have {len(r) + 1} rows of {len(c)} values (one per node)")
        if not all(math.isfinite(x) and x >= 0.0 for row in self.density for x in row):
            raise ModelError("the density must be finite and >= 0")
        if not all(x > 0.0 for x in self.density[0]):
            raise ModelError("the reversible density (row 0) must be > 0 at every node")

    @cached_property
    def r(self) -> F64:
        """Half-widths (V)."""
        return readonly_array(self.thresholds_v)

    @cached_property
    def c(self) -> F64:
        """Centre nodes (V)."""
        return readonly_array(self.nodes_v)

    @cached_property
    def mu(self) -> F64:
        """Density, shape ``(p + 1, K)`` (um/V)."""
        return readonly_array(self.density)

    @cached_property
    def zero(self) -> F64:
        """``G_i(0)`` per row: the antiderivatives are referred to 0 V, so ``H_i(0) = 0``."""
        g = _antiderivative(self.mu, self.c, np.zeros((self.mu.shape[0], 1)))[:, 0]
        g.setflags(write=False)
        return g

    def slope_at(self, voltage_v: float) -> float:
        """Slope of the relaxed (all plays centred) position over the voltage at ``voltage_v`` (um/V)."""
        return float(np.sum(_interp_rows(self.mu, self.c, float(voltage_v))))

    @property
    def b_um_per_v(self) -> float:
        """The rest slope at 0 V (um/V): the scale the family's voltage-driven creep uses."""
        return self.slope_at(0.0)

    def positions(self, voltage_v: F64, plays_v: F64) -> F64:
        """``x_h`` for voltages ``(n,)`` and play outputs ``(p, n)``."""
        q = np.vstack([voltage_v[None, :], plays_v])
        g = _antiderivative(self.mu, self.c, q) - self.zero[:, None]
        out: F64 = g.sum(axis=0)
        return out


def _interp_rows(mu: F64, c: F64, q: float) -> F64:
    """``mu_i(q)`` for every row (constant beyond the end nodes)."""
    k = int(np.clip(np.searchsorted(c, q, side="right") - 1, 0, c.size - 2))
    t = float(np.clip((q - c[k]) / (c[k + 1] - c[k]), 0.0, 1.0))
    out: F64 = mu[:, k] + t * (mu[:, k + 1] - mu[:, k])
    return out


def _antiderivative(mu: F64, c: F64, q: F64) -> F64:
    """``G_i(q) = int_{c_0}^{q} mu_i``, rows of ``q`` matched to rows of ``mu`` (shape ``(p + 1, n)``)."""
    width = np.diff(c)
    # integral up to every node, per row
    steps = np.cumsum(0.5 * (mu[:, :-1] + mu[:, 1:]) * width, axis=1)
    cum = np.concatenate([np.zeros((mu.shape[0], 1)), steps], axis=1)
    qc = np.clip(q, c[0], c[-1])
    k = np.clip(np.searchsorted(c, qc, side="right") - 1, 0, c.size - 2)
    t = qc - c[k]
    rows = np.arange(mu.shape[0])[:, None]
    m0, m1 = mu[rows, k], mu[rows, k + 1]
    g = cum[rows, k] + m0 * t + 0.5 * (m1 - m0) / width[k] * t * t
    g += mu[:, :1] * np.minimum(q - c[0], 0.0) + mu[:, -1:] * np.maximum(q - c[-1], 0.0)
    out: F64 = g
    return out


def basis_features(voltage_v: F64, plays_v: F64, nodes_v: F64) -> F64:
    """Columns ``H_{i,j}`` of the unit densities (row ``i``, node ``j``) per sample, shape ``(n, (p + 1) K)``.

    The position of a law with density ``mu`` is ``features @ mu.ravel()``: linear in the density.
    """
    q = np.vstack([voltage_v[None, :], plays_v])
    rows, k = q.shape[0], nodes_v.size
    out = np.empty((q.shape[1], rows * k))
    for j in range(k):
        unit = np.zeros((rows, k))
        unit[:, j] = 1.0
        g = _antiderivative(unit, nodes_v, q) - _antiderivative(unit, nodes_v, np.zeros((rows, 1)))
        out[:, j::k] = g.T
    return out


def gplay_rest_state(params: GeneralisedPlayParams, voltage_v: float = 0.0) -> PlayState:
    """Relaxed at ``voltage_v``: every play centred on it."""
    v = float(voltage_v)
    plays = np.full(params.r.size, v)
    return PlayState(v, plays, float(params.positions(np.array([v]), plays[:, None])[0]))


def gplay_state_at(params: GeneralisedPlayParams, voltage_v: float, plays_v: ArrayLike) -> PlayState:
    """The state with the given voltage and play outputs (plays clipped into ``V -+ r``)."""
    v = float(voltage_v)
    p = np.clip(np.asarray(plays_v, dtype=np.float64), v - params.r, v + params.r)
    return PlayState(v, p, float(params.positions(np.array([v]), p[:, None])[0]))


def play_outputs(thresholds_v: F64, voltage_v: F64, state: PlayState) -> tuple[F64, F64]:
    """Play outputs through a block, shape ``(p, n)``, and the plays after it."""
    r = thresholds_v[:, None]
    p = state.plays_v
    out = np.empty((thresholds_v.size, voltage_v.size))
    starts, dirs = _runs(voltage_v, state.voltage_v)
    bounds = np.append(starts, voltage_v.size)
    for k, direction in enumerate(dirs):
        seg = voltage_v[bounds[k] : bounds[k + 1]]
        if direction > 0:
            block = np.maximum(p[:, None], seg[None, :] - r)
        elif direction < 0:
            block = np.minimum(p[:, None], seg[None, :] + r)
        else:
            block = np.repeat(p[:, None], seg.size, axis=1)
        out[:, bounds[k] : bounds[k + 1]] = block
        p = block[:, -1].copy()
    return out, p


def gplay_forward(
    params: GeneralisedPlayParams, voltage_v: ArrayLike, state: PlayState
) -> tuple[F64, PlayState]:
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
    plays, p_end = play_outputs(params.r, v, state)
    x = params.positions(v, plays)
    return x, PlayState(float(v[-1]), p_end, float(x[-1]))


__all__ = [
    "GeneralisedPlayParams",
    "basis_features",
    "gplay_forward",
    "gplay_rest_state",
    "gplay_state_at",
    "play_outputs",
]
