"""A Duhem hysteresis law with direction- and sign-dependent rates (generalised Bouc-Wen, exponent n).

The hysteretic position is ``x_h = b V + c h`` with the hysteretic variable ``h`` (V) obeying,
along a monotone voltage run in direction ``sigma`` (``d = |V - V_run start|``, ``u = sigma h``)::

    du/dd = A_sigma - sign(u) |k u|^n,   k = k_same(sigma)  if u >= 0  (h heads to its saturation)
                                         k = k_back(sigma)  if u <  0  (h recovers after a reversal)

with ``A_up = 1`` (the scale of ``h`` is absorbed in ``c``) and ``A_down = amp_down``. The
exponent ``n`` (Bouc's and Wen's, 1 <= n <= 4) sets how sharp the knee is where a branch bends
into saturation: ``n = 1`` relaxes exponentially, ``n = 2`` along ``tanh`` / ``tan``, larger
``n`` more abruptly. For ``n = 1`` (``du/dd = A - k u``) special cases are:

* the Coleman-Hodgdon ODE (2.21): every rate ``alpha``, ``amp_down = 1``, ``c = -alpha delta``;
* the symmetric rate-independent Bouc-Wen law with exponent 1, ``x = b (V - h')``,
  ``dh' = A dV - beta |dV| h' - gamma dV |h'|``: ``k_same = beta + gamma``,
  ``k_back = beta - gamma`` in both directions, ``amp_down = 1``, ``c = -b A`` (``h' = A h``).

The four rates and ``amp_down`` let the loop's two branches and its recovery after a reversal
differ (an asymmetric or direction-dependent Duhem law). Repeated minor loops drift (no
wiping-out memory), as for any Duhem law.

With ``n = 1`` ``h`` has a closed form along a monotone run (exponential relaxation, one sign
change at most), so the forward law is exact per sample for a voltage monotone between samples,
and the inverse per sample is a scalar increasing equation with at most two pieces, each solved
by a bracketed Newton iteration (:func:`piezod.model.kernels.bw_loop`, compiled, bounded cost).
For other ``n`` the law *is* its per-sample Runge-Kutta discretisation (steps of ``k d <= 0.25``,
error of order ``(k d)^5`` against the ODE): the inverse solves that same step by a bracketed
Newton iteration (:func:`piezod.model.kernels.bwn_loop`), so the round trip is exact.

Invertibility: ``h`` stays in ``[-amp_down^(1/n) / k_same_down, 1 / k_same_up]`` once there (the
rest state ``h = 0`` is), and the slope ``dx_h/dV`` along a run is smallest right after a
reversal at the far end of that interval; the parameters are refused unless it stays positive
there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model import kernels

F64 = NDArray[np.float64]

#: Smallest slope right after a reversal, as a fraction of ``b`` (the inverse's gain stays bounded).
MIN_SLOPE_FRACTION = 1e-3


@dataclass(frozen=True)
class BoucWenParams:
    """Frozen parameters of the Duhem law with direction- and sign-dependent rates.

    Attributes
    ----------
    b_um_per_v
        Reversible slope ``b`` (um/V), > 0.
    c_um_per_v
        Weight of the hysteretic variable ``c`` (um/V; negative for a counter-clockwise loop, as a
        piezo's).
    k_up_same, k_up_back, k_down_same, k_down_back
        Relaxation rates (1/V), >= 0: rising (``up``) or falling, with ``h`` of the run's sign
        (``same``, > 0) or of the other sign (``back``).
    amp_down
        ``A_down / A_up`` (> 0).
    exponent
        ``n`` in ``[1, 4]`` (the knee's sharpness; 1: exponential relaxation).
    """

    b_um_per_v: float
    c_um_per_v: float
    k_up_same: float
    k_up_back: float
    k_down_same: float
    k_down_back: float
    amp_down: float = 1.0
    exponent: float = 1.0

    def __post_init__(self) -> None:
        values = (self.b_um_per_v, self.c_um_per_v, *self.rates, self.amp_down, self.exponent)
        if not all(math.isfinite(v) for v in values):
            raise ModelError("bouc-wen parameters must be finite")
        if self.b_um_per_v <= 0.0:
            raise ModelError(f"bouc-wen b_um_per_v must be > 0, got {self.b_um_per_v!r}")
        if not (self.k_up_same > 0.0 and self.k_down_same > 0.0):
            raise ModelError("bouc-wen k_up_same and k_down_same must be > 0 (h stays bounded)")
        if min(self.k_up_back, self.k_down_back) < 0.0:
            raise ModelError("bouc-wen k_up_back and k_down_back must be >= 0")
        if not self.amp_down > 0.0:
            raise ModelError(f"bouc-wen amp_down must be > 0, got {self.amp_down!r}")
        if not 1.0 <= self.exponent <= 4.0:
            raise ModelError(f"bouc-wen exponent must lie in [1, 4], got {self.exponent!r}")
        if self.min_slope_um_per_v < MIN_SLOPE_FRACTION * self.b_um_per_v:
            raise ModelError(
                f"bouc-wen branch would flatten or run backwards: the slope after a reversal "
                f"{self.min_slope_um_per_v:.4g} um/V must stay >= {MIN_SLOPE_FRACTION:g} b"
            )

    @property
    def rates(self) -> tuple[float, float, float, float]:
        """``(k_up_same, k_up_back, k_down_same, k_down_back)`` (1/V)."""
        return (self.k_up_same, self.k_up_back, self.k_down_same, self.k_down_back)

    @property
    def h_range_v(self) -> tuple[float, float]:
        """The interval ``h`` stays in: ``[-amp_down^(1/n) / k_down_same, 1 / k_up_same]``."""
        return (-(self.amp_down ** (1.0 / self.exponent)) / self.k_down_same, 1.0 / self.k_up_same)

    @property
    def min_slope_um_per_v(self) -> float:
        """Smallest ``dx_h/dV`` along any run from a state inside :attr:`h_range_v` (um/V)."""
        c = self.c_um_per_v
        if c >= 0.0:
            # the slope b + c du/dd is smallest where h reaches its saturation: b
            return self.b_um_per_v
        return self.b_um_per_v + c * self.reversal_rate

    @property
    def reversal_rate(self) -> float:
        """Largest ``du/dd`` ``M``: right after a reversal at the far end of :attr:`h_range_v`.

        The slope of ``x_h`` along a run is ``b + c du/dd``, so for ``c < 0`` it is smallest,
        ``b + c M``, there.
        """
        lo, hi = self.h_range_v
        n = self.exponent
        up = 1.0 + math.pow(self.k_up_back * -lo, n)
        return max(up, self.amp_down + math.pow(self.k_down_back * hi, n))

    @classmethod
    def from_bouc_wen(
        cls, b_um_per_v: float, a: float, beta_per_v: float, gamma_per_v: float
    ) -> BoucWenParams:
        """The symmetric Bouc-Wen law ``x = b (V - h')``, ``dh' = A dV - beta |dV| h' - gamma dV |h'|``."""
        k_same, k_back = beta_per_v + gamma_per_v, beta_per_v - gamma_per_v
        return cls(b_um_per_v, -b_um_per_v * a, k_same, k_back, k_same, k_back, 1.0)

    @classmethod
    def from_coleman_hodgdon(cls, alpha_per_v: float, b_um_per_v: float, u_um_per_v: float) -> BoucWenParams:
        """The Coleman-Hodgdon ODE (2.21) with ``delta = (b - u) / alpha``."""
        delta = (b_um_per_v - u_um_per_v) / alpha_per_v
        a = alpha_per_v
        return cls(b_um_per_v, -a * delta, a, a, a, a, 1.0)


@dataclass(frozen=True, slots=True)
class BoucWenState:
    """State after a sample: voltage (V), hysteretic variable ``h`` (V), position ``x_h`` (um)."""

    voltage_v: float
    h_v: float
    position_um: float


def boucwen_rest_state(params: BoucWenParams, voltage_v: float = 0.0) -> BoucWenState:
    """Rested at ``voltage_v``: ``h = 0`` (the centre line ``x_h = b V``)."""
    v = float(voltage_v)
    return BoucWenState(v, 0.0, params.b_um_per_v * v)


def boucwen_state_at(params: BoucWenParams, voltage_v: float, position_um: float) -> BoucWenState:
    """The state at ``voltage_v`` nearest to ``position_um`` (``h`` clipped to its range)."""
    v = float(voltage_v)
    lo, hi = params.h_range_v
    c = params.c_um_per_v
    h = 0.0 if c == 0.0 else float(np.clip((float(position_um) - params.b_um_per_v * v) / c, lo, hi))
    return BoucWenState(v, h, params.b_um_per_v * v + c * h)


def _args(p: BoucWenParams) -> tuple[float, ...]:
    return (p.b_um_per_v, p.c_um_per_v, p.amp_down, *p.rates)


def _forward_kernel(v: F64, args: tuple[float, ...], n: float, u0: float, h0: float, out: F64) -> float:
    """``b V + c h`` into ``out`` (``args`` as :func:`_args`) by exponent ``n``'s kernel; the last ``h``."""
    if n == 1.0:
        return float(kernels.bw_forward(v, *args, u0, h0, out))
    return float(kernels.bwn_forward(v, *args, n, u0, h0, out))


def creep_loop(
    p: BoucWenParams,
    xc: F64,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    u_prev: float,
    h: float,
    out: F64,
) -> tuple[float, float]:
    """The compiled inverse of the law plus voltage creep (:func:`piezod.model.kernels.bw_loop` or,
    for ``n != 1``, :func:`~piezod.model.kernels.bwn_loop`): ``(last V_c, last h)``."""
    if p.exponent == 1.0:
        return kernels.bw_loop(xc, *_args(p), g, wa, wb, a, ob0, e, u_prev, h, out)
    return kernels.bwn_loop(
        xc, *_args(p), p.exponent, p.min_slope_um_per_v, g, wa, wb, a, ob0, e, u_prev, h, out
    )


def boucwen_forward(
    params: BoucWenParams, voltage_v: ArrayLike, state: BoucWenState
) -> tuple[F64, BoucWenState]:
    """``x_h`` for a block of voltages (exact for a voltage monotone between samples), and the state after."""
    v = np.ascontiguousarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise ModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    out = np.empty(v.size)
    h = _forward_kernel(v, _args(params), params.exponent, state.voltage_v, state.h_v, out)
    return out, BoucWenState(float(v[-1]), float(h), float(out[-1]))


def boucwen_inverse(
    params: BoucWenParams, position_um: ArrayLike, state: BoucWenState
) -> tuple[F64, BoucWenState]:
    """Voltages whose forward law reaches ``position_um`` at every sample (exact), and the state after."""
    x = np.ascontiguousarray(position_um, dtype=np.float64)
    if x.ndim != 1:
        raise ModelError(f"position_um must be 1-D, got shape {x.shape}")
    if x.size == 0:
        return np.empty(0), state
    out = np.empty(x.size)
    none = np.empty(0)
    u, h = creep_loop(params, x, 0.0, none, 0.0, none, none, np.empty(0), state.voltage_v, state.h_v, out)
    x_end = params.b_um_per_v * float(u) + params.c_um_per_v * float(h)
    return out, BoucWenState(float(u), float(h), x_end)


def unit_hysteresis(
    rates: tuple[float, float, float, float],
    amp_down: float,
    voltage_v: ArrayLike,
    rest_voltage_v: float,
    exponent: float = 1.0,
) -> F64:
    """``h`` along ``voltage_v`` from rest at ``rest_voltage_v`` (a calibration feature)."""
    v = np.ascontiguousarray(voltage_v, dtype=np.float64)
    out = np.empty(v.size)
    _forward_kernel(v, (0.0, 1.0, amp_down, *rates), float(exponent), float(rest_voltage_v), 0.0, out)
    return out


__all__ = [
    "BoucWenParams",
    "BoucWenState",
    "boucwen_forward",
    "boucwen_inverse",
    "boucwen_rest_state",
    "boucwen_state_at",
    "creep_loop",
    "unit_hysteresis",
]
