"""Transient loops after an offset or range change, (5.1)-(5.9).

The piezo sits at ``(V_0, x_0)`` and moves in the trace direction when the scan
changes to the new turning points ``[V'_m, V'_M]``. Its first trace (5.2) runs
from ``V_0`` up to ``V'_M``, its first retrace (5.3) back to ``V'_m``; after that
it scans ``[V'_m, V'_M]`` and converges to the closed loop (2.24). With
``eta = x - b V`` and ``a = exp(-alpha V'_R)``, one full loop maps the retrace
end state by ``eta -> q eta + delta (1 - a)^2``, ``q = a^2`` (5.5), so successive
loops differ by the factor ``q`` (5.7), (5.8).

The thesis's (5.4) has two typos (its ``V'_0`` stands for ``V'_m`` in the bracket
and for ``V_0`` in the exponent); the functions below implement the corrected
form, checked against the exact ODE (:func:`~piezod.model.ode.hysteresis_step`)
in ``tests/test_transient.py``.

Only the rate-independent hysteresis (2.21) enters: the transients do not depend
on the scan frequency (creep adds a time-dependent relaxation on top, which is
why the thesis observes more curvature than (5.9) predicts).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.ode import HysteresisState
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.model.thesis import RETRACE, TRACE, hysteresis_loop

FloatArray = NDArray[np.float64]


def _hyst(params: HysteresisParams | ThesisParams) -> HysteresisParams:
    return params.hysteresis if isinstance(params, ThesisParams) else params


def _check_new_range(v_min: float, v_max: float) -> None:
    if not (math.isfinite(v_min) and math.isfinite(v_max) and v_max > v_min):
        raise ModelError(f"new scan range must have finite v_max > v_min, got [{v_min}, {v_max}]")


def _check_start(start: HysteresisState, v_max: float) -> None:
    if not start.voltage_v <= v_max:
        raise ModelError(
            f"start voltage {start.voltage_v} V lies above the new upper turning point {v_max} V: "
            "the first trace (5.2) cannot reach it"
        )


def steady_state(
    params: HysteresisParams | ThesisParams, v_min: float, v_max: float, voltage_v: float, direction: int
) -> HysteresisState:
    """State on the closed loop (2.24) of the scan ``[v_min, v_max]``, e.g. where a scan is left.

    Parameters
    ----------
    params
        Hysteresis parameters (the creep part of :class:`ThesisParams` is ignored).
    v_min, v_max
        Turning points of the old scan (V).
    voltage_v
        Voltage at which the scan is left (V).
    direction
        Branch the stage is on (+1 trace, -1 retrace).
    """
    p = _hyst(params)
    x = float(hysteresis_loop(p, voltage_v, direction, v_min, v_max))
    return HysteresisState(float(voltage_v), x)


def first_trace(
    params: HysteresisParams | ThesisParams, start: HysteresisState, voltage_v: ArrayLike
) -> FloatArray:
    """Position on the first trace after the change (5.2), ``V_0 <= V <= V'_M``."""
    p = _hyst(params)
    v = np.asarray(voltage_v, dtype=np.float64)
    a, b, d = p.alpha_per_v, p.b_um_per_v, p.delta_um
    e = np.exp(-a * (v - start.voltage_v))
    out: FloatArray = b * v - d * (1.0 - e) + (start.position_um - b * start.voltage_v) * e
    return out


def first_retrace(
    params: HysteresisParams | ThesisParams, start: HysteresisState, v_max: float, voltage_v: ArrayLike
) -> FloatArray:
    """Position on the first retrace after the change (5.3), from ``V'_M = v_max`` down."""
    p = _hyst(params)
    _check_start(start, v_max)
    v = np.asarray(voltage_v, dtype=np.float64)
    a, b, d = p.alpha_per_v, p.b_um_per_v, p.delta_um
    eta0 = start.position_um - b * start.voltage_v
    out: FloatArray = (
        b * v
        + d * (1.0 - 2.0 * np.exp(-a * (v_max - v)))
        + (eta0 + d) * np.exp(-a * (2.0 * v_max - v - start.voltage_v))
    )
    return out


def convergence_ratio(params: HysteresisParams | ThesisParams, v_min: float, v_max: float) -> float:
    """Ratio ``q = exp(-2 alpha (V'_M - V'_m))`` (5.5) by which successive loops approach the closed loop."""
    _check_new_range(v_min, v_max)
    return math.exp(-2.0 * _hyst(params).alpha_per_v * (v_max - v_min))


def steady_fraction(params: HysteresisParams | ThesisParams, v_min: float, v_max: float) -> float:
    """``(1 - sqrt q)^2 / (1 - q)`` of (5.4), equal to ``1 - 2 e^{a V'_m} / (e^{a V'_m} + e^{a V'_M})`` (5.6).

    ``b V'_m + (b - u)/alpha`` times this is the closed loop's lower turning point.
    """
    q = convergence_ratio(params, v_min, v_max)
    sq = math.sqrt(q)
    return (1.0 - sq) / (1.0 + sq)


def _top_state_first(p: HysteresisParams, start: HysteresisState, v_max: float) -> float:
    """``eta`` at ``V'_M`` at the end of the first trace."""
    eta0 = start.position_um - p.b_um_per_v * start.voltage_v
    return (eta0 + p.delta_um) * math.exp(-p.alpha_per_v * (v_max - start.voltage_v)) - p.delta_um


def retrace_end_position(
    params: HysteresisParams | ThesisParams,
    start: HysteresisState,
    v_min: float,
    v_max: float,
    loops: ArrayLike,
) -> FloatArray:
    """Position ``x_r^n(V'_m)`` at the end of the ``n``-th retrace (5.4), ``n >= 1``.

    Parameters
    ----------
    params
        Hysteresis parameters.
    start
        State ``(V_0, x_0)`` when the change happens; the stage moves up from there.
    v_min, v_max
        New turning points ``V'_m``, ``V'_M`` (V).
    loops
        Loop numbers ``n >= 1`` (integers, any shape).
    """
    p = _hyst(params)
    _check_new_range(v_min, v_max)
    _check_start(start, v_max)
    n = np.asarray(loops, dtype=np.float64)
    if np.any(n < 1):
        raise ModelError("loop numbers must be >= 1")
    a, b, d = p.alpha_per_v, p.b_um_per_v, p.delta_um
    q = convergence_ratio(p, v_min, v_max)
    frac = steady_fraction(p, v_min, v_max)
    eta0 = start.position_um - b * start.voltage_v
    first = d * (1.0 - 2.0 * math.exp(-a * (v_max - v_min)) - frac) + math.exp(
        -a * (2.0 * v_max - v_min - start.voltage_v)
    ) * (eta0 + d)
    out: FloatArray = b * v_min + d * frac + q ** (n - 1.0) * first
    return out


def retrace_difference(
    params: HysteresisParams | ThesisParams,
    start: HysteresisState,
    v_min: float,
    v_max: float,
    voltage_v: ArrayLike,
    loops: ArrayLike,
) -> FloatArray:
    """``x_r^{n+1}(V) - x_r^n(V)`` on the retrace, ``= q^{n-1} (x_r^2(V) - x_r^1(V))`` (5.7), (5.8)."""
    p = _hyst(params)
    _check_new_range(v_min, v_max)
    _check_start(start, v_max)
    n = np.asarray(loops, dtype=np.float64)
    if np.any(n < 1):
        raise ModelError("loop numbers must be >= 1")
    a_r = math.exp(-p.alpha_per_v * (v_max - v_min))
    q = a_r * a_r
    eta_top = _top_state_first(p, start, v_max)
    # one loop maps the top state by eta -> q eta - delta (1 - a)^2
    d_top = (q - 1.0) * eta_top - p.delta_um * (1.0 - a_r) ** 2
    v = np.asarray(voltage_v, dtype=np.float64)
    out: FloatArray = d_top * q ** (n - 1.0) * np.exp(-p.alpha_per_v * (v_max - v))
    return out


def loops_to_settle(
    params: HysteresisParams | ThesisParams,
    v_min: float,
    v_max: float,
    *,
    start: HysteresisState,
    pixel_um: float,
    lines: int = 512,
    direction: int = TRACE,
    voltage_v: float | None = None,
) -> int:
    """Smallest number of loops ``n`` after which the next ``lines`` loops move by less than a pixel (5.9).

    Solves ``|x_r^{n+lines}(V) - x_r^n(V)| < pixel_um`` with (5.7):
    ``|D_1| e^{-alpha (V'_M - V)} q^{n-1} (1 - q^lines) / (1 - q) < pixel``.

    Parameters
    ----------
    params
        Hysteresis parameters.
    v_min, v_max
        New turning points (V).
    start
        State when the change happens (e.g. :func:`steady_state` of the old scan).
    pixel_um
        Pixel width ``lambda`` (um), e.g. the new range / 512.
    lines
        Number of following loops (image lines) that must be free of the transient.
    direction
        Direction the stage moves in at ``start``; for -1 the mirrored problem
        (``V -> -V``, ``x -> -x``) is solved, so the loops end at ``V'_M``.
    voltage_v
        Where on the retrace to measure; None takes the worst point of the loop
        (the retrace start ``V'_M``, factor 1).

    Returns
    -------
    int
        ``n >= 1``.
    """
    p = _hyst(params)
    if not (math.isfinite(pixel_um) and pixel_um > 0.0):
        raise ModelError(f"pixel width must be > 0 um, got {pixel_um!r}")
    if lines < 1:
        raise ModelError(f"lines must be >= 1, got {lines}")
    if direction == RETRACE:
        start = HysteresisState(-start.voltage_v, -start.position_um)
        v_min, v_max = -v_max, -v_min
        voltage_v = None if voltage_v is None else -voltage_v
    elif direction != TRACE:
        raise ModelError(f"direction must be +1 or -1, got {direction!r}")
    v_at = v_max if voltage_v is None else float(voltage_v)
    d1 = abs(float(retrace_difference(p, start, v_min, v_max, v_at, 1)))
    q = convergence_ratio(p, v_min, v_max)
    total = d1 * (1.0 - q**lines) / (1.0 - q)
    if total < pixel_um:
        return 1
    # q^(n-1) total < pixel  <=>  n - 1 > ln(pixel / total) / ln(q)
    return math.floor(math.log(pixel_um / total) / math.log(q)) + 2
