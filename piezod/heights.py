"""Heights from the z voltage: the forward model against the linear conversion (thesis chapter 5).

SPM controllers record the height as the z-piezo voltage of the z feedback and convert it with
one sensitivity. The z piezo has its own hysteresis and creep: after every step the voltage
overshoots and relaxes while the piezo (and the tip) stay on the terrace - the overshoots of
thesis figs 5.3-5.4 that a capacitive z sensor does not show. The forward model
(:func:`piezod.image.forward_heights`) runs the recorded z-voltage waveform, exact for any
waveform, with its state, and removes them.

:func:`compare_heights` measures both conversions against the true heights (the simulator's truth
log, or a z sensor), after levelling each image line by its median difference (the reference
height of a line is arbitrary in an image).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from piezod.config import AxisConfig, ScannerConfig
from piezod.errors import CalibrationError
from piezod.image import F64, RasterSamples, linear_sensitivity
from piezod.recording import Experiment

_SETTLE_LINES = 1
_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class HeightComparison:
    """Worst deviation of each conversion from the true heights, in % of the step height.

    Attributes
    ----------
    step_um
        The step height (um), from the truth (its 1st-99th percentile span).
    model_max_pct, linear_max_pct
        Largest |converted - true| over the compared samples (after per-line levelling), % of the step.
    model_rms_pct, linear_rms_pct
        RMS of the same.
    sensitivity_um_per_v
        The linear conversion's sensitivity (best fit to the true heights: the most favourable one).
    samples
        Compared samples.
    model_plateau_max_pct, linear_plateau_max_pct
        Largest |converted - true| on the plateaus only (% of the step): the compared samples
        farther than :data:`EDGE_SAMPLES` truth samples from any where the true height moves by
        more than 5 % of the step. At an edge the tip is on the step and the height changes by the
        step within a few samples, so a fraction of a sample of timing between drive and extension
        (an amplifier pole) is a large error there; the thesis's overshoots are on the plateaus.
    """

    step_um: float
    model_max_pct: float
    linear_max_pct: float
    model_rms_pct: float
    linear_rms_pct: float
    sensitivity_um_per_v: float
    samples: int
    model_plateau_max_pct: float = math.nan
    linear_plateau_max_pct: float = math.nan


#: Truth samples on either side of an edge left out of the plateau figures.
EDGE_SAMPLES = 3


def _level_per_line(err: F64, line: NDArray[np.int64]) -> F64:
    out = err.copy()
    for ln in np.unique(line):
        s = line == ln
        out[s] -= np.median(err[s])
    return out


def compare_heights(
    rs: RasterSamples, model_um: F64, true_um: F64, *, settle_lines: int = _SETTLE_LINES
) -> tuple[HeightComparison, F64, F64]:
    """Both conversions against the true heights, per sample (NaN where there is no truth).

    Returns
    -------
    comparison, model_error_um, linear_error_um
        The figures and the per-sample errors (NaN outside the compared samples).
    """
    if rs.z_voltage_v is None:
        raise ValueError("no z_voltage")
    z = rs.z_voltage_v
    ok = np.isfinite(true_um) & (rs.line >= settle_lines)
    s = linear_sensitivity(z[ok], true_um[ok])
    lin = s * z
    e_m = np.full(z.size, np.nan)
    e_l = np.full(z.size, np.nan)
    e_m[ok] = _level_per_line(model_um[ok] - true_um[ok], rs.line[ok])
    e_l[ok] = _level_per_line(lin[ok] - true_um[ok], rs.line[ok])
    lo, hi = np.percentile(true_um[ok], [1, 99])
    step = float(hi - lo)
    pct = 100.0 / step
    idx = np.flatnonzero(ok)
    edge = np.zeros(idx.size, dtype=bool)
    for k in np.flatnonzero(np.abs(np.diff(true_um[idx])) > 0.05 * step):
        edge[max(0, k - EDGE_SAMPLES) : k + 1 + EDGE_SAMPLES + 1] = True
    plateau = idx[~edge]
    return (
        HeightComparison(
            step_um=step,
            model_max_pct=float(np.nanmax(np.abs(e_m))) * pct,
            linear_max_pct=float(np.nanmax(np.abs(e_l))) * pct,
            model_rms_pct=float(np.sqrt(np.nanmean(e_m**2))) * pct,
            linear_rms_pct=float(np.sqrt(np.nanmean(e_l**2))) * pct,
            sensitivity_um_per_v=s,
            samples=int(ok.sum()),
            model_plateau_max_pct=float(np.max(np.abs(e_m[plateau]), initial=0.0)) * pct,
            linear_plateau_max_pct=float(np.max(np.abs(e_l[plateau]), initial=0.0)) * pct,
        ),
        e_m,
        e_l,
    )


def plot_height_profiles(
    rs: RasterSamples, true_um: F64, model_err_um: F64, linear_err_um: F64, path: Path, title: str
) -> Path:
    """One trace line: true height, and the error of both conversions along it (as thesis fig. 5.4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    line = int(np.max(rs.line))
    s = (rs.line == line) & (rs.direction > 0) & np.isfinite(true_um)
    x = rs.target_um[s]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5.2), sharex=True)
    a1.plot(x, (true_um[s] - np.median(true_um[s])) * 1e3, "k-", lw=1)
    a1.set_ylabel("true height (nm)")
    a1.set_title("true surface under the tip (trace)", fontsize=9)
    a2.plot(x, linear_err_um[s] * 1e3, "-", lw=1, label="linear conversion (one sensitivity)")
    a2.plot(x, model_err_um[s] * 1e3, "-", lw=1, label="forward model (hysteresis + creep)")
    a2.axhline(0.0, color="k", lw=0.5)
    a2.set_xlabel("commanded fast-axis position (um)")
    a2.set_ylabel("height error (nm)")
    a2.set_title("converted minus true height", fontsize=9)
    a2.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def z_experiments(rs: RasterSamples, true_um: F64, label: str) -> list[Experiment]:
    """The z axis's calibration data of a raster recording: one experiment per image line, the
    recorded z voltage against a measured z extension (a z sensor; on the simulator its truth log),
    at the samples where the extension is known."""
    if rs.z_voltage_v is None:
        raise CalibrationError(f"{label}: no z_voltage column")
    out = []
    for ln in range(rs.lines):
        s = (rs.line == ln) & np.isfinite(true_um)
        if s.sum() < 32:
            continue
        out.append(
            Experiment(
                label=f"{label}#{ln}",
                axis="z",
                t_s=rs.t_s[s],
                voltage_v=rs.z_voltage_v[s],
                position_um=true_um[s],
            )
        )
    if not out:
        raise CalibrationError(f"{label}: no image line with known z extensions")
    return out


#: Drive lags the z fit profiles, in sample intervals (then refined between the best's neighbours).
Z_LAG_GRID_SAMPLES = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)


def lagged_experiments(experiments: list[Experiment], tau_s: float) -> list[Experiment]:
    """The experiments with their voltages run through the drive lag ``tau_s`` exactly.

    The lag is the runtime model's (:func:`piezod.model.family.family_forward`): ``V_c[n] =
    a V_c[n-1] + (1 - a) V[n]``, ``a = exp(-dt / tau)`` with the experiment's (uniform) sample
    interval; it carries its state from one experiment to the next when they are contiguous (one
    sample apart) and starts settled at the first voltage otherwise.
    """
    if tau_s < 0.0 or not math.isfinite(tau_s):
        raise CalibrationError(f"drive lag must be >= 0 s, got {tau_s!r}")
    if tau_s == 0.0:
        return list(experiments)
    out: list[Experiment] = []
    y = 0.0
    last_t: float | None = None
    for e in sorted(experiments, key=lambda e: float(e.t_s[0])):
        step = float(np.median(np.diff(e.t_s))) if e.t_s.size > 1 else 0.0
        a = math.exp(-step / tau_s)
        contiguous = last_t is not None and float(e.t_s[0]) - last_t <= 1.5 * step
        y0 = y if contiguous else float(e.voltage_v[0])
        v = lfilter([1.0 - a], [1.0, -a], e.voltage_v, zi=[a * y0])[0]
        y, last_t = float(v[-1]), float(e.t_s[-1])
        out.append(dataclasses.replace(e, voltage_v=v))
    return out


def fit_z_model(
    experiments: list[Experiment], base: ScannerConfig, *, axis: Literal["x", "y", "z"] = "z"
) -> tuple[AxisConfig, str, dict[str, float]]:
    """The z axis's model from z voltage vs measured extension.

    A height image's z voltage steps at every edge within a sample or two, so the drive lag (an
    amplifier pole) is applied exactly to the voltages, not in the family fit's first-order form
    (good for slow drives only): it is profiled by the held-out RMS of one law
    (Prandtl-Ishlinskii, voltage-driven creep) on :data:`Z_LAG_GRID_SAMPLES` and refined between
    the best point's neighbours. At that lag every law and creep driver of
    :mod:`piezod.calibrate_family` is scored by held-out data and the best is refitted on all (as
    :func:`piezod.calibrate_family.choose_model` calibrates the lateral axes): with several scans
    (an experiment's label up to ``#``, as :func:`z_experiments` writes it) each scan is held out
    in turn and predicted from the others (the RMS over the folds), so a model that fits the lines
    of its own scans but not another rate or range loses; with one scan every fourth line is held
    out. A member whose fit
    fails is left out; when every one fails the dynamic model
    (:func:`piezod.calibrate_dynamic.fit_dynamic`, fitted on all lines) is the model.

    Parameters
    ----------
    experiments
        The z calibration data (:func:`z_experiments`), at the sample rate: a lag of a fraction of
        a sample is not determined by data sampled more sparsely.
    base
        The scanner configuration (the axis's safe voltage, the ramp rate).
    axis
        The axis to calibrate.

    Returns
    -------
    axis_config, chosen, heldout_rms_um
        The calibrated z axis, the chosen candidate's name, and every family candidate's held-out
        RMS (um; over the folds; NaN: its fit failed, the reason in the log) at the chosen lag.

    Raises
    ------
    CalibrationError
        Too little data, or no model could be fitted.
    """
    from scipy.optimize import minimize_scalar

    from piezod.calibrate_data import DynamicCalibrationData, prepare_dynamic
    from piezod.calibrate_dynamic import CreepStructure, calibrated_config, fit_dynamic
    from piezod.calibrate_family import (
        LAWS,
        family_model_config,
        fit_family,
        holdout_mask,
        member_name,
    )
    from piezod.model.family import CREEP_DRIVERS

    ax = base.axes[axis]
    prepared: dict[float, DynamicCalibrationData] = {}

    def prepare(tau_s: float) -> DynamicCalibrationData:
        if tau_s not in prepared:
            prepared[tau_s] = prepare_dynamic(
                lagged_experiments(experiments, tau_s),
                rest_voltage_v=ax.safe_voltage_v,
                slew_rate_v_per_s=base.service.ramp_rate_v_per_s,
                max_samples_per_experiment=4096,
            )
        return prepared[tau_s]

    train = holdout_mask(prepare(0.0).n_experiments, 4)
    dt = min(float(np.median(np.diff(e.t_s))) for e in experiments if e.t_s.size > 1)
    profiled: dict[float, float] = {}

    def profile(tau_s: float) -> float:
        if tau_s not in profiled:
            try:
                fit = fit_family(
                    prepare(tau_s), "prandtl-ishlinskii", train=train, creep_driver="voltage", fit_lag=False
                )
                profiled[tau_s] = fit.heldout_rms_um
            except CalibrationError as exc:
                _log.warning("z lag %.3g s not profiled: %s", tau_s, exc)
                profiled[tau_s] = math.inf
        return profiled[tau_s]

    grid = [k * dt for k in Z_LAG_GRID_SAMPLES]
    scores = [profile(t) for t in grid]
    best = int(np.argmin(scores))
    lag_s = grid[best]
    if math.isfinite(scores[best]):
        lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
        if hi > lo:
            res = minimize_scalar(
                profile, bounds=(lo, hi), method="bounded", options={"xatol": 0.05 * dt, "maxiter": 8}
            )
            if float(res.fun) < scores[best]:
                lag_s = float(res.x)
    data = prepare(lag_s)
    heldout: dict[str, float] = {}
    members: dict[str, tuple[str, str]] = {}
    for law in LAWS:
        for driver in CREEP_DRIVERS:
            name = member_name(law, driver)
            members[name] = (law, driver)
            try:
                heldout[name] = fit_family(
                    data, law, train=train, creep_driver=driver, fit_lag=False
                ).heldout_rms_um
            except CalibrationError as exc:
                heldout[name] = math.nan
                _log.warning("z model %s not fitted: %s", name, exc)
    scored = {k: v for k, v in heldout.items() if math.isfinite(v)}
    if scored:
        chosen = min(scored, key=lambda k: scored[k])
        law, driver = members[chosen]
        final = fit_family(data, law, creep_driver=driver, fit_lag=False)
        params = dataclasses.replace(final.params, lag_time_constant_s=lag_s)
        return (
            ax.model_copy(update={"model": "family", "family": family_model_config(params)}),
            chosen,
            heldout,
        )
    # relaxation times beyond ten times what the data spans are not determined by it
    span_s = float(max(e.t_s[-1] for e in experiments) - min(e.t_s[0] for e in experiments))
    dyn = fit_dynamic(prepare(0.0), creep=CreepStructure(tau_min_s=1e-3, tau_max_s=max(10.0, 10.0 * span_s)))
    return calibrated_config(dyn, axis=axis, base=base).axes[axis], "dynamic", heldout


__all__ = [
    "HeightComparison",
    "compare_heights",
    "fit_z_model",
    "lagged_experiments",
    "plot_height_profiles",
    "z_experiments",
]
