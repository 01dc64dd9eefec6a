"""Range-dependent sensitivity of the closed loop, (2.30)-(2.34), and the table 2.3 parameter sets.

The fitted sensitivity of (2.24) grows with the voltage range ``V_R``
(figure 2.17). The thesis compares three laws for ``b_j(V_R)``:

    b_1 = b + a_1 V_R + a_2 V_R^2            (2.30)
    b_2 = b + a_3 ln(V_R - a_4)              (2.31)
    b_3 = b - a_5 exp(-a_6 V_R)              (2.32)

and puts them into the linear term of (2.24) only (2.33); (2.34) is the final
model with ``b_3``. The thesis fitted symmetric scans only; for offset scans the
linear correction is taken around the scan centre ``V_C`` as for creep
(section 3.3): ``x = b V + (b_j - b)(V - V_C) + hysteresis``, identical to (2.33)
when ``V_C = 0``.

The 7-parameter model (3.8) cannot take ``b_3`` exactly.
:func:`thesis_params_from_table_2_3` gives the honest approximation used by
``configs/long-tube.yaml``: ``a1 = 0`` (no frequency information: the long-tube
data are all at 0.1 Hz), ``alpha, b, u`` of table 2.3 unchanged, and ``A2, A3``
fitted by linear least squares so that ``b_hat(V_R)`` of (3.7) follows ``b_3(V_R)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.model.thesis import hysteresis_loop

FloatArray = NDArray[np.float64]

#: The 48 voltage ranges (V peak-to-peak) of the long-tube experiments, section 2.1.1:
#: 2D200 5-50 V in 2.5 V steps and 55-70 V in 5 V steps, 1D3000 50-260 V in 10 V steps
#: and 275, 300, 350, 400, 440 V.
LONG_TUBE_RANGES_V: tuple[float, ...] = (
    *(5.0 + 2.5 * i for i in range(19)),
    55.0,
    60.0,
    65.0,
    70.0,
    *(50.0 + 10.0 * i for i in range(22)),
    275.0,
    300.0,
    350.0,
    400.0,
    440.0,
)


def sensitivity_quadratic(b_um_per_v: float, a1: float, a2: float, v_range: ArrayLike) -> FloatArray:
    """``b_1(V_R) = b + a_1 V_R + a_2 V_R^2`` (2.30)."""
    vr = np.asarray(v_range, dtype=np.float64)
    out: FloatArray = b_um_per_v + a1 * vr + a2 * vr**2
    return out


def sensitivity_log(b_um_per_v: float, a3: float, a4_v: float, v_range: ArrayLike) -> FloatArray:
    """``b_2(V_R) = b + a_3 ln(V_R - a_4)`` (2.31); ``V_R > a_4`` required."""
    vr = np.asarray(v_range, dtype=np.float64)
    if np.any(vr <= a4_v):
        raise ModelError(f"(2.31) needs V_R > a_4 = {a4_v} V, got min V_R = {float(np.min(vr))} V")
    out: FloatArray = b_um_per_v + a3 * np.log(vr - a4_v)
    return out


def sensitivity_exponential(
    b_um_per_v: float, a5_um_per_v: float, a6_per_v: float, v_range: ArrayLike
) -> FloatArray:
    """``b_3(V_R) = b - a_5 exp(-a_6 V_R)`` (2.32)."""
    vr = np.asarray(v_range, dtype=np.float64)
    out: FloatArray = b_um_per_v - a5_um_per_v * np.exp(-a6_per_v * vr)
    return out


@dataclass(frozen=True, slots=True)
class RangeSensitivityParams:
    """The 5 parameters of the enhanced hysteresis model (2.34), table 2.3.

    Attributes
    ----------
    alpha_per_v, b_um_per_v, u_um_per_v
        Hysteresis parameters of (2.21).
    a5_um_per_v
        Amplitude of the range-dependent sensitivity deficit (um/V).
    a6_per_v
        Its decay rate with the voltage range (1/V).
    """

    alpha_per_v: float
    b_um_per_v: float
    u_um_per_v: float
    a5_um_per_v: float
    a6_per_v: float

    def __post_init__(self) -> None:
        HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
        for name in ("a5_um_per_v", "a6_per_v"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ModelError(f"{name} must be finite, got {value!r}")

    @property
    def hysteresis(self) -> HysteresisParams:
        """The rate-independent part (2.21)."""
        return HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)

    def sensitivity(self, v_range: ArrayLike) -> FloatArray:
        """``b_3(V_R)`` (2.32) for the peak-to-peak voltage range ``V_R``."""
        return sensitivity_exponential(self.b_um_per_v, self.a5_um_per_v, self.a6_per_v, v_range)


#: Long tube scanner, table 2.3 (0.1 Hz, 5-440 V p-p, about 1-160 um).
LONG_TUBE_TABLE_2_3 = RangeSensitivityParams(
    alpha_per_v=3.44e-3, b_um_per_v=0.64, u_um_per_v=0.38, a5_um_per_v=0.18, a6_per_v=3.04e-3
)
#: Medium tube scanner, table 2.3 (0.5 Hz, 140-460 V p-p, about 12-40 um).
MEDIUM_TUBE_TABLE_2_3 = RangeSensitivityParams(
    alpha_per_v=2.55e-3, b_um_per_v=0.18, u_um_per_v=7.9e-2, a5_um_per_v=4.7e-2, a6_per_v=2.66e-3
)


def range_sensitivity_loop(
    params: HysteresisParams,
    sensitivity_um_per_v: float,
    voltage_v: ArrayLike,
    direction: ArrayLike,
    v_min: float,
    v_max: float,
) -> FloatArray:
    """Loop (2.33): the closed loop (2.24) with the sensitivity ``b_j(V_R)`` in its linear term.

    Parameters
    ----------
    params
        Hysteresis parameters (``b`` stays in ``(b - u) / alpha``).
    sensitivity_um_per_v
        ``b_j(V_R)`` for this scan's range.
    voltage_v
        Voltages inside ``[v_min, v_max]``.
    direction
        +1 trace, -1 retrace.
    v_min, v_max
        Turning points (V).
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    v_c = 0.5 * (v_min + v_max)
    out: FloatArray = hysteresis_loop(params, v, direction, v_min, v_max) + (
        sensitivity_um_per_v - params.b_um_per_v
    ) * (v - v_c)
    return out


def enhanced_loop(
    params: RangeSensitivityParams, voltage_v: ArrayLike, direction: ArrayLike, v_min: float, v_max: float
) -> FloatArray:
    """The final enhanced hysteresis model (2.34) with ``b_3(V_R)``."""
    b3 = float(params.sensitivity(v_max - v_min))
    return range_sensitivity_loop(params.hysteresis, b3, voltage_v, direction, v_min, v_max)


def enhanced_scan_range_um(params: RangeSensitivityParams, v_range: ArrayLike) -> FloatArray:
    """Scan range of (2.34): ``b_3(V_R) V_R - 2 (b - u)/alpha tanh(alpha V_R / 2)``."""
    vr = np.asarray(v_range, dtype=np.float64)
    out: FloatArray = params.sensitivity(vr) * vr - 2.0 * params.hysteresis.delta_um * np.tanh(
        0.5 * params.alpha_per_v * vr
    )
    return out


@dataclass(frozen=True, slots=True)
class CreepApproximation:
    """(3.8) parameters approximating (2.34), with the size of the approximation error.

    Attributes
    ----------
    params
        The 7-parameter set (``a1 = 0``).
    max_error_rel
        Largest loop difference ``|x_(3.8) - x_(2.34)|`` over all fitted ranges,
        relative to that range's scan range.
    rms_error_rel
        Root mean square of the same over the ranges (loop ends).
    """

    params: ThesisParams
    max_error_rel: float
    rms_error_rel: float


def thesis_params_from_table_2_3(
    params: RangeSensitivityParams,
    v_ranges: ArrayLike = LONG_TUBE_RANGES_V,
    *,
    tau_s: float = 1.0,
) -> CreepApproximation:
    """(3.8) parameters (``a1 = 0``) whose range dependence best follows (2.34).

    For a symmetric scan the two models differ by ``(b_hat - b_3) V`` only, largest at
    the turning points; ``A2, A3`` minimise that difference relative to the scan
    range over ``v_ranges`` (linear least squares: ``b_hat - b`` is linear in them).

    Parameters
    ----------
    params
        The (2.34) parameters.
    v_ranges
        Peak-to-peak voltage ranges to fit over (V).
    tau_s
        Creep time constant to store; irrelevant because ``a1 = 0``.
    """
    vr = np.asarray(v_ranges, dtype=np.float64)
    if vr.ndim != 1 or vr.size < 2 or np.any(vr <= 0):
        raise ModelError("need at least two positive voltage ranges")
    vh = 0.5 * vr
    shape = params.hysteresis.delta_um * np.tanh(params.alpha_per_v * vh) / vh  # d(V_h) / V_h
    x_range = enhanced_scan_range_um(params, vr)
    # relative loop-end difference: ((A2 vh + A3) shape - (b3 - b)) vh / x_range
    scale = vh / x_range
    design = np.stack([shape * vh * scale, shape * scale], axis=1)
    rhs = (params.sensitivity(vr) - params.b_um_per_v) * scale
    (a2, a3), *_ = np.linalg.lstsq(design, rhs, rcond=None)
    resid = design @ np.array([a2, a3]) - rhs
    thesis = ThesisParams(
        alpha_per_v=params.alpha_per_v,
        b_um_per_v=params.b_um_per_v,
        u_um_per_v=params.u_um_per_v,
        tau_s=tau_s,
        a1=0.0,
        a2_per_v=float(a2),
        a3=float(a3),
    )
    return CreepApproximation(thesis, float(np.max(np.abs(resid))), float(np.sqrt(np.mean(resid**2))))
