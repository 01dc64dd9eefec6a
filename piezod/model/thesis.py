"""The closed-loop thesis model: hysteresis (2.22)-(2.24), tilt (2.29) and creep (3.1)-(3.8).

All functions are vectorised over voltage samples and describe the *steady*
periodic loop of a triangular scan between ``V_m`` and ``V_M`` at line frequency
``f`` (Hz). Offset scans follow section 3.3: the creep term is linear in
``V - V_C`` around the centre ``V_C = (V_M + V_m) / 2`` and depends on the range
through the half range ``V_h = (V_M - V_m) / 2`` only, so a symmetric scan
(``V_C = 0``) reduces exactly to (3.8).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.params import HysteresisParams, ThesisParams

#: Branch direction: +1 trace (``dV/dt > 0``), -1 retrace.
TRACE = 1
RETRACE = -1


def _check_range(v_min: float, v_max: float) -> None:
    if not v_max > v_min:
        raise ModelError(f"voltage range must have v_max > v_min, got [{v_min}, {v_max}]")


def loop_constant(alpha_per_v: float, v_min: float, v_max: float, direction: int) -> float:
    """Integration constant ``C_{t/r}`` of the closed loop (2.24).

    ``C_t = 2 / (exp(-a V_m) + exp(-a V_M))`` and ``C_r = 2 / (exp(a V_m) + exp(a V_M))``.
    """
    s = float(direction)
    return float(2.0 / (np.exp(-s * alpha_per_v * v_min) + np.exp(-s * alpha_per_v * v_max)))


def hysteresis_loop(
    params: HysteresisParams, voltage_v: ArrayLike, direction: ArrayLike, v_min: float, v_max: float
) -> NDArray[np.float64]:
    """Position on the closed rate-independent loop (2.24).

    Parameters
    ----------
    params
        Hysteresis parameters.
    voltage_v
        Voltages inside ``[v_min, v_max]``.
    direction
        +1 (trace) or -1 (retrace), scalar or per sample.
    v_min, v_max
        Turning points of the periodic scan (V).

    Returns
    -------
    ndarray
        Position (um) on the branch of the given direction.
    """
    _check_range(v_min, v_max)
    v = np.asarray(voltage_v, dtype=np.float64)
    s = np.asarray(direction, dtype=np.float64)
    a, b, d = params.alpha_per_v, params.b_um_per_v, params.delta_um
    # exp(-s a (V - V_turn)) written relative to the turning point the branch starts from,
    # so that large |alpha V| never overflows.
    v_start = np.where(s > 0, v_min, v_max)
    e_r = np.exp(-a * (v_max - v_min))
    c_rel = 2.0 / (1.0 + e_r)  # C * exp(-s a V_start)
    out: NDArray[np.float64] = b * v - s * d * (1.0 - c_rel * np.exp(-s * a * (v - v_start)))
    return out


def tilt(params: HysteresisParams, v_half: ArrayLike) -> NDArray[np.float64]:
    """Tilt ``s(V_M)`` of a symmetric closed loop (2.29): slope of the line joining its turning points.

    Tends to ``u`` for small ranges and to ``b`` for large ranges.
    """
    vm = np.asarray(v_half, dtype=np.float64)
    a, b, u = params.alpha_per_v, params.b_um_per_v, params.u_um_per_v
    x = a * vm
    ratio = np.where(x < 1e-8, 1.0 - x**2 / 3.0, np.tanh(x) / np.where(x == 0, 1.0, x))
    out: NDArray[np.float64] = b - (b - u) * ratio
    return out


def max_creep_um(params: HysteresisParams, v_min: float, v_max: float) -> float:
    """Maximum creep ``d(V_M)`` (3.1): distance from the upper turning point to ``b V``.

    ``d = (b - u) / alpha * (1 - C_t exp(-alpha V_M)) = delta * (1 - 2 / (1 + exp(alpha V_R)))``.
    """
    _check_range(v_min, v_max)
    e = np.exp(-params.alpha_per_v * (v_max - v_min))
    return float(params.delta_um * (1.0 - 2.0 * e / (1.0 + e)))


def creep_factor(params: ThesisParams, frequency_hz: float, v_half: float) -> float:
    """Creep factor ``k(f, V_M) = (1 - A1 exp(-1 / (f tau))) (A2 V_M + A3)`` (3.5)."""
    if not frequency_hz > 0:
        raise ModelError(f"scan frequency must be > 0 Hz, got {frequency_hz}")
    return float(
        (1.0 - params.a1 * np.exp(-1.0 / (frequency_hz * params.tau_s)))
        * (params.a2_per_v * v_half + params.a3)
    )


def effective_sensitivity(params: ThesisParams, frequency_hz: float, v_min: float, v_max: float) -> float:
    """Creep-enhanced sensitivity ``b_hat(f, V_M)`` (3.7) of a scan between ``v_min`` and ``v_max``."""
    v_half = 0.5 * (v_max - v_min)
    d = max_creep_um(params.hysteresis, v_min, v_max)
    return float(params.b_um_per_v + creep_factor(params, frequency_hz, v_half) * d / v_half)


def thesis_loop(
    params: ThesisParams,
    voltage_v: ArrayLike,
    direction: ArrayLike,
    v_min: float,
    v_max: float,
    frequency_hz: float,
) -> NDArray[np.float64]:
    """Position of the hysteresis + creep model (3.8) for a steady triangular scan.

    ``x = b V + (b_hat - b)(V - V_C) -/+ (b - u)/alpha (1 - C_{t/r} exp(-/+ alpha V))``

    Parameters
    ----------
    params
        The 7 model parameters.
    voltage_v
        Voltages inside ``[v_min, v_max]``.
    direction
        +1 trace, -1 retrace (scalar or per sample).
    v_min, v_max
        Turning points (V).
    frequency_hz
        Line (trace + retrace) frequency (Hz).

    Returns
    -------
    ndarray
        Position (um).
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    b_hat = effective_sensitivity(params, frequency_hz, v_min, v_max)
    v_c = 0.5 * (v_min + v_max)
    hyst = hysteresis_loop(params.hysteresis, v, direction, v_min, v_max)
    out: NDArray[np.float64] = hyst + (b_hat - params.b_um_per_v) * (v - v_c)
    return out


def scan_range_um(params: ThesisParams, frequency_hz: float, v_half: ArrayLike) -> NDArray[np.float64]:
    """Scan range ``x(V_M) - x(V_m)`` of the (3.8) loop for a half voltage range ``V_h``.

    ``2 b V_h + 2 d(V_h) (k(f, V_h) - 1)`` with ``d = (b - u)/alpha tanh(alpha V_h)`` (3.1):
    the left-hand side of the range equation (4.12). It does not depend on the
    scan centre (offset scans, section 3.3).

    Parameters
    ----------
    params
        The 7 model parameters.
    frequency_hz
        Line frequency (Hz).
    v_half
        Half the voltage range ``(V_M - V_m) / 2`` (V), >= 0.

    Returns
    -------
    ndarray
        Scan range (um).
    """
    if not frequency_hz > 0:
        raise ModelError(f"scan frequency must be > 0 Hz, got {frequency_hz}")
    vh = np.asarray(v_half, dtype=np.float64)
    f_factor = 1.0 - params.a1 * np.exp(-1.0 / (frequency_hz * params.tau_s))
    d = params.hysteresis.delta_um * np.tanh(params.alpha_per_v * vh)
    out: NDArray[np.float64] = 2.0 * params.b_um_per_v * vh + 2.0 * d * (
        f_factor * (params.a2_per_v * vh + params.a3) - 1.0
    )
    return out


#: Medium tube scanner, thesis table 3.3 (calibration frame 172.5-402.5 V p-p, 0.1-1.4 Hz), with the
#: table's A3 = 0.872 (the text of section 3.3.1 prints 0.681; see ``configs/medium-tube.yaml``).
MEDIUM_TUBE_TABLE_3_3 = ThesisParams(
    alpha_per_v=3.23e-3, b_um_per_v=0.081, u_um_per_v=0.016, tau_s=2.666, a1=0.081, a2_per_v=2.78e-3, a3=0.872
)
