"""Residual structure in numbers, and the evidence text of every finding.

For a residual (measured minus model) the structure is summarised per experiment (trend in
time, sensitivity error, loop-opening error) and correlated with what distinguishes the
candidate effects: session time (drift, thermal), scan offset (stiffness), range (saturation),
line rate (delay, creep), the voltage sign (polarity) and the spectrum (resonance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.audit.baseline import Geometry
from piezod.audit.candidates import spectral_peak
from piezod.audit.data import AuditData
from piezod.audit.residuals import (
    binned,
    correlation,
    experiment_structure,
    loop_closure,
    since_turn,
    velocity,
)

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Structure:
    """Structure of one residual.

    Attributes
    ----------
    rms_um
        RMS residual.
    noise_ratio
        RMS over the noise floor.
    per_experiment
        One dict per experiment (label, scan, rms, slope, gain error, opening error).
    correlations
        Named correlations of the per-experiment numbers with the scan parameters.
    bins
        Residual mean / RMS in bins of voltage, voltage rate, travel since the last reversal.
    negative_minus_positive_um
        Mean residual at ``V < 0`` minus at ``V > 0`` (nan without both).
    spectral_peak_hz
        Strongest narrow excess of the residual spectrum above the line frequencies (or None).
    loop_closure_um
        Per periodic experiment with two or more loops: loop-to-loop RMS change of the measurement.
    """

    rms_um: float
    noise_ratio: float
    per_experiment: list[dict[str, Any]]
    correlations: dict[str, float]
    bins: dict[str, dict[str, list[float]]]
    negative_minus_positive_um: float
    spectral_peak_hz: float | None
    loop_closure_um: list[float]


def structure(
    geo: Geometry, rows: NDArray[np.bool_], r: F64, model_x: F64, noise_um: float, f_hi_hz: float
) -> Structure:
    """Summarise the residual ``r`` (on ``rows``) of a model with positions ``model_x``."""
    data = geo.data
    es = experiment_structure(data, rows, r, model_x)
    t_mid = np.array([0.5 * (e.t_start_s + e.t_end_s) for e in data.info])
    offs = np.array([e.offset_v for e in data.info])
    rng = np.array([e.range_v for e in data.info])
    f = np.array([e.frequency_hz for e in data.info])
    logf = np.log(np.where(np.isfinite(f) & (f > 0), f, np.nan))
    per = [
        {
            "label": e.label,
            "kind": e.kind,
            "frequency_hz": e.frequency_hz,
            "range_v": e.range_v,
            "offset_v": e.offset_v,
            "t_mid_s": float(t_mid[i]),
            "rms_um": float(es.rms_um[i]),
            "slope_nm_per_s": float(es.slope_nm_per_s[i]),
            "gain_error_pct": float(100.0 * es.gain_error[i]),
            "opening_error_um": float(es.opening_um[i]),
        }
        for i, e in enumerate(data.info)
    ]
    corr = {
        "gain_error_vs_time": correlation(es.gain_error, t_mid),
        "gain_error_vs_offset": correlation(es.gain_error, offs),
        "gain_error_vs_range": correlation(es.gain_error, rng),
        "gain_error_vs_log_frequency": correlation(es.gain_error, logf),
        "opening_error_vs_frequency": correlation(es.opening_um, f),
        "slope_vs_time": correlation(es.slope_nm_per_s, t_mid),
    }
    full_r = np.full(data.n, np.nan)
    full_r[rows] = r
    bins: dict[str, dict[str, list[float]]] = {}
    for name, values in (
        ("voltage_v", data.voltage_v),
        ("voltage_rate_v_per_s", velocity(data)),
        ("since_reversal_v", since_turn(data)),
    ):
        c, m, q = binned(values, full_r)
        bins[name] = {"centre": c.tolist(), "mean_um": m.tolist(), "rms_um": q.tolist()}
    neg = rows & (data.voltage_v < 0)
    pos = rows & (data.voltage_v > 0)
    npd = float(np.mean(full_r[neg]) - np.mean(full_r[pos])) if neg.any() and pos.any() else math.nan
    fl = np.array([e.frequency_hz for e in data.info if e.periodic])
    f_lo = 5.0 * float(fl.max()) if fl.size else 2.0 / max(min(e.duration_s for e in data.info), 1e-9)
    peak = spectral_peak(geo, rows, r, f_lo, f_hi_hz) if f_hi_hz > 2.0 * f_lo else None
    rms = math.sqrt(float(np.mean(r**2)))
    return Structure(
        rms_um=rms,
        noise_ratio=rms / noise_um if noise_um > 0 else math.inf,
        per_experiment=per,
        correlations=corr,
        bins=bins,
        negative_minus_positive_um=npd,
        spectral_peak_hz=peak,
        loop_closure_um=[float(v) for v in loop_closure(data) if np.isfinite(v)],
    )


def _fmt(v: float, digits: int = 3) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.{digits}g}"


def _r(name: str, v: float) -> str:
    """``, <name> (r = v)`` or nothing when the correlation is undefined (one experiment)."""
    return f", {name} (r = {v:.2f})" if math.isfinite(v) else ""


def evidence(
    effect: str,
    params: dict[str, float],
    before: Structure,
    gain: float,
    bic_delta: float,
    heldout_before: float,
    heldout_after: float,
    runner_up: tuple[str, float, str] | None,
    data: AuditData,
) -> str:
    """A sentence or two a scientist can check: what the residual shows and what the term explains.

    Parameters
    ----------
    effect
        The finding.
    params
        Its fitted parameters.
    before
        Structure of the residual before the finding was added.
    gain, bic_delta, heldout_before, heldout_after
        Its numbers.
    runner_up
        The best other candidate of the round, its held-out gain and why it was not eligible.
    data
        The training data.
    """
    c = before.correlations
    per = before.per_experiment
    parts: list[str] = []
    if effect == "drift":
        slopes = np.array([p["slope_nm_per_s"] for p in per], dtype=float)
        ok = np.isfinite(slopes)
        sign = np.sign(params["rate_nm_per_s"])
        same = int(np.sum(np.sign(slopes[ok]) == sign))
        parts.append(
            f"position drifts {params['rate_nm_per_s']:+.3g} nm/s; the residual trends the same way "
            f"within {same}/{int(ok.sum())} experiments (median {_fmt(float(np.median(slopes[ok])))} nm/s), "
            "independent of the position (an offset change in time, not a sensitivity change)"
        )
    elif effect == "thermal":
        refs = [p for p in per if str(p["label"]).split(":")[-1].startswith("reference")]
        txt = f"sensitivity changes {params['rate_pct_per_hour']:+.3g} %/h" + _r(
            "the per-experiment sensitivity error correlates with session time", c["gain_error_vs_time"]
        )
        if len(refs) >= 2:
            g0, g1 = refs[0]["gain_error_pct"], refs[-1]["gain_error_pct"]
            txt += (
                f"; the repeated reference scan changes its sensitivity by {g1 - g0:+.3g} % between "
                f"t = {refs[0]['t_mid_s']:.0f} s and {refs[-1]['t_mid_s']:.0f} s"
            )
        parts.append(txt + " (a change of scale, not of offset)")
    elif effect == "stiffness":
        parts.append(
            f"sensitivity changes {params['sensitivity_pct_per_um']:+.3g} %/um of position (preload "
            "spring), an error even in the position"
            + _r("the per-experiment sensitivity error follows the scan offset", c["gain_error_vs_offset"])
        )
    elif effect == "polarity":
        parts.append(
            f"the ceramic is {params['negative_sensitivity_pct']:+.3g} % more sensitive below 0 V; the "
            f"residual at V < 0 differs from V > 0 by {_fmt(before.negative_minus_positive_um)} um "
            "with a kink at 0 V"
        )
    elif effect == "saturation":
        parts.append(
            f"response compresses at large excursions (x_sat = {_fmt(params['x_sat_um'])} um), an error odd "
            "in the position"
            + _r("the per-experiment sensitivity error falls with the range", c["gain_error_vs_range"])
        )
    elif effect == "resonance":
        peak = before.spectral_peak_hz
        ptxt = f"the residual spectrum peaks at {peak:.4g} Hz" if peak else "no single spectral peak"
        decay = params["q"] / (math.pi * params["f0_hz"])
        parts.append(
            f"mechanical resonance f0 = {params['f0_hz']:.4g} Hz, Q = {params['q']:.3g} (ringing decays "
            f"in {decay * 1e3:.3g} ms after every turning point); {ptxt}"
        )
    elif effect == "delay":
        d, tau = params["delay_s"], params["lag_time_constant_s"]
        f = np.array([p["frequency_hz"] for p in per], dtype=float)
        fmax = float(np.nanmax(f)) if np.isfinite(f).any() else math.nan
        lag = d + tau
        txt = (
            f"the position lags by {lag * 1e3:.3g} ms (pure delay {d * 1e3:.3g} ms, "
            f"first-order lag {tau * 1e3:.3g} ms)"
        )
        if math.isfinite(fmax):
            txt += f", {360.0 * fmax * lag:.3g} deg of phase at {fmax:.3g} Hz"
        txt += "; the loop opens with the speed" + _r(
            "the loop-opening error grows with the line rate", c["opening_error_vs_frequency"]
        )
        parts.append(txt)
    elif effect == "creep":
        if "creep_pct_per_decade" in params:
            parts.append(
                f"slow creep of {params['creep_pct_per_decade']:.3g} % of the motion per decade of time, "
                "driven by the position since the start of the recording"
            )
        else:
            parts.append(
                f"creep law not as (3.5): the sensitivity varies with log frequency "
                f"(k {params['k_log_per_decade']:+.3g} per decade, motion "
                f"{params['motion_pct_per_decade']:+.3g} % per decade of time)"
                + _r("the per-experiment sensitivity error follows log f", c["gain_error_vs_log_frequency"])
            )
    parts.append(
        f"held-out RMS {heldout_before:.4g} -> {heldout_after:.4g} um (gain {gain:.3g}), BIC {bic_delta:+.4g}"
    )
    if runner_up is not None:
        why = f": {runner_up[2]}" if runner_up[2] else ""
        parts.append(f"next best candidate {runner_up[0]} (gain {runner_up[1]:.3g}{why})")
    return "; ".join(parts)
