"""Frozen parameter objects of the scanner models (units in the field names)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError


def readonly_array(values: ArrayLike) -> NDArray[np.float64]:
    """A float64 copy of ``values`` that cannot be written: the array view of a frozen parameter."""
    a = np.array(values, dtype=np.float64)
    a.setflags(write=False)
    return a


def _require(cond: bool, what: str) -> None:
    if not cond:
        raise ModelError(what)


@dataclass(frozen=True, slots=True)
class HysteresisParams:
    """Parameters of the rate-independent Coleman-Hodgdon hysteresis ODE (2.21).

    ``dx/dV = alpha * sgn(dV) * (b V - x) + u``

    Attributes
    ----------
    alpha_per_v
        Rate of transition of the slope from ``u`` to ``b`` (1/V), > 0.
    b_um_per_v
        Sensitivity, slope of the asymptote ``b V`` (um/V), > 0.
    u_um_per_v
        Slope of the virgin curve / slope right after a reversal (um/V), > 0.
    """

    alpha_per_v: float
    b_um_per_v: float
    u_um_per_v: float

    def __post_init__(self) -> None:
        for name in ("alpha_per_v", "b_um_per_v", "u_um_per_v"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value > 0.0, f"{name} must be finite and > 0, got {value!r}")

    @property
    def delta_um(self) -> float:
        """Half the vertical distance between the two branch asymptotes, ``(b - u) / alpha``."""
        return (self.b_um_per_v - self.u_um_per_v) / self.alpha_per_v


@dataclass(frozen=True, slots=True)
class ThesisParams:
    """The 7 parameters of the hysteresis + creep model (3.8), table 3.3.

    The creep factor is ``k(f, V_M) = (1 - a1 exp(-1 / (f tau))) (a2 V_M + a3)`` (3.5)
    with ``f`` the line (scan) frequency in Hz and ``V_M`` half the voltage range.

    Attributes
    ----------
    alpha_per_v, b_um_per_v, u_um_per_v
        Hysteresis parameters of (2.21).
    tau_s
        Creep time constant (s).
    a1
        Creep frequency amplitude (dimensionless).
    a2_per_v
        Range dependence of the creep factor (1/V).
    a3
        Range-independent part of the creep factor (dimensionless).
    """

    alpha_per_v: float
    b_um_per_v: float
    u_um_per_v: float
    tau_s: float
    a1: float
    a2_per_v: float
    a3: float

    def __post_init__(self) -> None:
        HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
        _require(math.isfinite(self.tau_s) and self.tau_s > 0.0, f"tau_s must be > 0, got {self.tau_s!r}")
        for name in ("a1", "a2_per_v", "a3"):
            value = getattr(self, name)
            _require(math.isfinite(value), f"{name} must be finite, got {value!r}")

    @property
    def hysteresis(self) -> HysteresisParams:
        """The rate-independent part (2.21)."""
        return HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
