"""Fast creep: the rate dependence above the calibration frame's rates, around any axis model.

A calibration frame scans at 0.2-2 Hz. Creep whose relaxation times are much shorter than its
lines (milliseconds) has settled within every line there: the frame shows it as sensitivity,
the fitted model carries it in its gain, and a line ten times faster than the frame then comes
out short, because that creep has no time to follow (docs/model-family.md 6.2ae). This part puts
it back as a linear filter on the wrapped model's position ``x_m`` with unit static gain::

    y[n] = (x_m[n] + sum_j w_j c_j[n]) / (1 + W),   W = sum_j w_j
    c_j[n] = a_j c_j[n-1] + (1 - a_j) x_m[n],       a_j = exp(-dt / tau_j)

``w_j`` of the motion arrive with the relaxation time ``tau_j``; at rest every ``c_j = x_m``
and ``y = x_m``, so the wrapped model's calibration (its slow response) is unchanged. In the
frequency domain ``F(f) = (1 + sum_j w_j / (1 + 2 pi i f tau_j)) / (1 + W)`` (:meth:`FastCreep.response`).

A weight may be negative: it takes out creep the wrapped model has too much of at ``tau_j``. A
family member's creep spectrum is fitted on the frame's loops, which resolve a few milliseconds
at best; its weights below that are carried there by the fit's smoothness prior, not measured,
and can be several times the stage's (docs/model-family.md 6.2aw). :mod:`piezod.rate_id` bounds
a negative weight by the wrapped model's own creep near ``tau_j``.

The inverse is exact per sample: ``x_m[n] = ((1 + W) y[n] - sum_j w_j a_j c_j[n-1]) / G`` with
``G = 1 + sum_j w_j (1 - a_j)``, then the element updates. With ``sum_j |w_j| < 1`` (the part
allows less than :data:`MAX_FAST_CREEP`) ``G > 0`` and the inverse is stable: every element's
discrete response ``(1 - a_j) / (1 - a_j / z)`` has magnitude at most 1 for ``|z| >= 1``, so
``1 + sum_j w_j (1 - a_j) / (1 - a_j / z)`` has no zero there. Each sample's ``x_m`` moves the
next sample's elements, so it is a sequential loop, ``O(J)`` per sample for ``J`` elements,
compiled (:func:`piezod.model.kernels.fast_creep_loop`; a few ns per sample). The forward runs
one first-order filter per element (``scipy.signal.lfilter``), vectorised over a block.
:mod:`piezod.rate_id` identifies the weights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import lfilter

from piezod.errors import ModelError
from piezod.model import kernels
from piezod.model.axis_model import AxisModel

F64 = NDArray[np.float64]
#: Bound on the fast creep's weights, ``sum_j |w_j|`` (fractions of the motion): a real stage's creep
#: below a second is a few percent, so half the motion is far beyond any stage (and below 1 the
#: inverse is stable, see the module docstring).
MAX_FAST_CREEP = 0.5


@dataclass(frozen=True)
class FastCreep:
    """Frozen weights ``w_j`` (fractions of the motion; negative: less creep than the wrapped model's)
    on relaxation times ``tau_j`` (s).

    Attributes
    ----------
    taus_s
        Relaxation times (s), strictly ascending, finite, > 0.
    weights
        Weights, finite, their absolute values summing below :data:`MAX_FAST_CREEP`. Empty: the
        part is off.
    """

    taus_s: tuple[float, ...] = ()
    weights: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if len(self.taus_s) != len(self.weights):
            raise ModelError("fast creep needs one weight per relaxation time")
        finite = all(math.isfinite(t) and t > 0.0 for t in self.taus_s)
        if not finite or any(b <= a for a, b in zip(self.taus_s, self.taus_s[1:], strict=False)):
            raise ModelError("fast creep relaxation times must be finite, > 0 and ascending")
        if not all(math.isfinite(w) for w in self.weights):
            raise ModelError("fast creep weights must be finite")
        if self.spread >= MAX_FAST_CREEP:
            raise ModelError(
                f"fast creep weights' absolute values sum to {self.spread:.4g}; "
                f"they must stay below {MAX_FAST_CREEP}"
            )

    @cached_property
    def total(self) -> float:
        """``W``, the fraction of the motion that arrives late (negative: less than the wrapped model's)."""
        return float(sum(self.weights))

    @cached_property
    def spread(self) -> float:
        """``sum_j |w_j|``, what :data:`MAX_FAST_CREEP` bounds."""
        return float(sum(abs(w) for w in self.weights))

    @property
    def identity(self) -> bool:
        """No weight: the part is off."""
        return self.spread == 0.0

    def response(self, frequency_hz: ArrayLike) -> NDArray[np.complex128]:
        """``F(f)``: the part's complex gain at ``frequency_hz`` (1 at 0 Hz)."""
        f = np.asarray(frequency_hz, dtype=np.float64)
        out = np.ones(f.shape, dtype=np.complex128)
        for tau, w in zip(self.taus_s, self.weights, strict=True):
            out += w / (1.0 + 2j * math.pi * f * tau)
        result: NDArray[np.complex128] = out / (1.0 + self.total)
        return result

    def forward(self, xm: F64, dt_s: float, c: F64) -> tuple[F64, F64]:
        """``y`` for the wrapped model's positions ``xm`` from element states ``c``; the states after."""
        a, w, _ = _coefficients(self.taus_s, self.weights, float(dt_s))
        y = xm.copy()
        c_out = np.empty_like(c)
        for j in range(a.size):
            cj, _ = lfilter([1.0 - a[j]], [1.0, -a[j]], xm, zi=[a[j] * c[j]])
            y += w[j] * cj
            c_out[j] = cj[-1]
        out: F64 = y / (1.0 + self.total)
        return out, c_out

    def inverse(self, y: F64, dt_s: float, c: F64) -> tuple[F64, F64]:
        """The wrapped model's positions ``xm`` whose :meth:`forward` is ``y``; the states after."""
        a, w, g = _coefficients(self.taus_s, self.weights, float(dt_s))
        state = np.array(c, dtype=np.float64)
        xm = np.empty(y.size)
        y = np.ascontiguousarray(y, dtype=np.float64)
        kernels.fast_creep_loop(y, a, w, 1.0 + self.total, g, state, xm)
        return xm, state


@lru_cache(maxsize=64)
def _coefficients(taus: tuple[float, ...], weights: tuple[float, ...], dt_s: float) -> tuple[F64, F64, float]:
    """``a_j = exp(-dt / tau_j)``, the weights and the inverse's ``G`` at one sample interval (read-only;
    computed once per part and interval, not per block)."""
    if not (math.isfinite(dt_s) and dt_s > 0.0):
        raise ModelError(f"dt_s must be finite and > 0, got {dt_s!r}")
    a = np.exp(-dt_s / np.asarray(taus, dtype=np.float64))
    w = np.asarray(weights, dtype=np.float64)
    g = 1.0 + float(np.sum(w * (1.0 - a)))
    a.flags.writeable = False
    w.flags.writeable = False
    return a, w, g


@dataclass(frozen=True, slots=True, eq=False)
class FastCreepState:
    """State of a model with fast creep.

    Attributes
    ----------
    inner
        The wrapped model's state.
    c
        The elements' states (um), read-only.
    position_um
        Position of the last sample (um).
    """

    inner: Any
    c: F64
    position_um: float


@dataclass(frozen=True)
class FastCreepAxisModel(AxisModel):
    """An axis model whose position arrives partly late (:class:`FastCreep`; see the module docstring).

    Attributes
    ----------
    inner
        The wrapped model.
    fast
        The fast creep (not the identity).
    """

    inner: AxisModel
    fast: FastCreep

    def __post_init__(self) -> None:
        kernels.warm_up()

    @property
    def kind(self) -> str:  # type: ignore[override]
        """The wrapped model's ``model:`` name."""
        return self.inner.kind

    @property
    def plans_by_thesis(self) -> bool:  # type: ignore[override]
        """The wrapped model's planner."""
        return self.inner.plans_by_thesis

    def _settled(self, inner: Any) -> FastCreepState:
        xm = float(self.inner.position(inner))
        return FastCreepState(inner, _frozen(np.full(len(self.fast.taus_s), xm)), xm)

    def rest(self, voltage_v: float = 0.0) -> FastCreepState:
        return self._settled(self.inner.rest(voltage_v))

    def adopt(self, voltage_v: float, position_um: float) -> FastCreepState:
        return self._settled(self.inner.adopt(voltage_v, position_um))

    def forward(self, voltage_v: ArrayLike, dt_s: float, state: Any) -> tuple[F64, FastCreepState]:
        v = np.asarray(voltage_v, dtype=np.float64)
        if v.size == 0:
            return np.empty(0), state
        xm, inner = self.inner.forward(v, dt_s, state.inner)
        y, c = self.fast.forward(np.asarray(xm, dtype=np.float64), dt_s, state.c)
        return y, FastCreepState(inner, _frozen(c), float(y[-1]))

    def inverse(self, target_um: ArrayLike, dt_s: float, state: Any) -> tuple[F64, FastCreepState]:
        y = np.asarray(target_um, dtype=np.float64)
        if y.size == 0:
            return np.empty(0), state
        xm, c = self.fast.inverse(y, dt_s, state.c)
        v, inner = self.inner.inverse(xm, dt_s, state.inner)
        return v, FastCreepState(inner, _frozen(c), float(y[-1]))

    def hold(self, samples: int, dt_s: float, state: Any) -> FastCreepState:
        inner = self.inner.hold(samples, dt_s, state.inner)
        if samples <= 0:
            return FastCreepState(inner, state.c, state.position_um)
        xm = float(self.inner.position(inner))
        # the wrapped position moves slowly during a hold; the elements relax towards where it ends
        a, _, _ = _coefficients(self.fast.taus_s, self.fast.weights, float(dt_s))
        c = xm + (state.c - xm) * a**samples
        y = (xm + float(np.dot(self.fast.weights, c))) / (1.0 + self.fast.total)
        return FastCreepState(inner, _frozen(c), y)

    def position(self, state: Any) -> float:
        return float(state.position_um)

    def voltage(self, state: Any) -> float:
        return float(self.inner.voltage(state.inner))

    def with_plan(self, kappa_um_per_v: float, center_v: float) -> AxisModel:
        return FastCreepAxisModel(self.inner.with_plan(kappa_um_per_v, center_v), self.fast)


def with_fast_creep(model: AxisModel, fast: FastCreep) -> AxisModel:
    """``model`` with ``fast`` after it (``model`` itself when the part is off)."""
    return model if fast.identity else FastCreepAxisModel(model, fast)


def _frozen(c: F64) -> F64:
    out = np.array(c, dtype=np.float64)
    out.flags.writeable = False
    return out


__all__ = ["MAX_FAST_CREEP", "FastCreep", "FastCreepAxisModel", "FastCreepState", "with_fast_creep"]
