"""Structure of the residuals: noise floor, binned residuals, per-experiment regressions, spectra.

Everything here is model-free bookkeeping on a residual vector and the data it belongs to; the
numbers serve as evidence in the report and as the axes of the plots.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from piezod.audit.data import AuditData
from piezod.fitstats import solve_linear

if TYPE_CHECKING:
    from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: Order of the differences of the noise-floor estimate.
_DIFF_ORDER = 3


def noise_floor(x: F64, order: int = _DIFF_ORDER) -> float:
    """White-noise level of a smooth signal from its high-order differences (um rms).

    The ``order``-th difference of white noise of variance ``s^2`` has variance
    ``C(2 order, order) s^2``; a smooth signal contributes little, sparse kinks (turning points)
    are outliers that the median absolute deviation ignores. When the signal is quantised so
    coarsely that most differences vanish, the trimmed RMS of the differences is used instead.

    Parameters
    ----------
    x
        Samples of one experiment.
    order
        Difference order.
    """
    if x.size <= order + 4:
        return math.nan
    d = np.diff(x, order)
    scale = math.sqrt(math.comb(2 * order, order))
    mad = float(np.median(np.abs(d - np.median(d))))
    if mad > 0.0:
        return 1.4826 * mad / scale
    q = np.sort(np.abs(d))[: max(1, int(0.98 * d.size))]
    return float(np.sqrt(np.mean(q**2))) / scale


def pooled_noise_floor(segments: Sequence[F64]) -> tuple[float, F64]:
    """Noise floor of every segment (an experiment's positions) and the pooled value (RMS over the
    segments, weighted by their samples; nan when none has one)."""
    per = np.array([noise_floor(np.asarray(x, dtype=np.float64)) for x in segments])
    w = np.array([len(x) for x in segments], dtype=np.float64)
    ok = np.isfinite(per)
    pooled = math.sqrt(float(np.sum(w[ok] * per[ok] ** 2) / np.sum(w[ok]))) if ok.any() else math.nan
    return pooled, per


def experiments_noise_floor(experiments: Sequence[Experiment]) -> float:
    """The readback's noise over ``experiments`` (um rms; :func:`pooled_noise_floor` of their
    positions, 0 when none has one): what no model's residual RMS on them goes below, taken out of
    the calibration's adoption gains (:func:`piezod.fitstats.lowers`)."""
    floor, _ = pooled_noise_floor([np.asarray(e.position_um, dtype=np.float64) for e in experiments])
    return floor if math.isfinite(floor) else 0.0


def noise_floor_data(data: AuditData) -> tuple[float, F64]:
    """Noise floor of every experiment and the pooled value (:func:`pooled_noise_floor`)."""
    return pooled_noise_floor([data.position_um[data.slice(i)] for i in range(data.n_experiments)])


@dataclass(frozen=True, eq=False)
class ExperimentStructure:
    """Per experiment: a regression of the residual on simple shapes.

    Attributes
    ----------
    rms_um
        RMS residual.
    slope_nm_per_s
        Residual trend in time.
    gain_error
        Relative sensitivity error: residual regressed on the centred model position.
    opening_um
        Loop-opening error: residual regressed on the direction (trace +1 / retrace -1).
    """

    rms_um: F64
    slope_nm_per_s: F64
    gain_error: F64
    opening_um: F64


def experiment_structure(
    data: AuditData, rows: NDArray[np.bool_], r: F64, model_x: F64
) -> ExperimentStructure:
    """Regress the residual of every experiment on ``[1, t, x - mean x, direction]``.

    Parameters
    ----------
    data
        The data.
    rows
        Samples the residual belongs to.
    r
        Residual on ``rows``.
    model_x
        Model position per sample (all samples).
    """
    full = np.full(data.n, np.nan)
    full[rows] = r
    ne = data.n_experiments
    rms, slope, gain, opening = (np.full(ne, np.nan) for _ in range(4))
    for i in range(ne):
        sl = data.slice(i)
        ri = full[sl]
        ok = np.isfinite(ri)
        if ok.sum() < 8:
            continue
        t = data.t_s[sl][ok]
        xm = model_x[sl][ok]
        s = data.direction[sl][ok]
        cols = [np.ones(t.size), t - t.mean(), xm - xm.mean()]
        has_dir = np.ptp(s) > 0
        if has_dir:
            cols.append(s - s.mean())
        a = np.column_stack(cols)
        coef, _ = solve_linear(a, ri[ok])
        rms[i] = math.sqrt(float(np.mean(ri[ok] ** 2)))
        slope[i] = coef[1] * 1e3
        gain[i] = coef[2]
        opening[i] = coef[3] if has_dir else math.nan
    return ExperimentStructure(rms_um=rms, slope_nm_per_s=slope, gain_error=gain, opening_um=opening)


def binned(values: F64, r: F64, bins: int = 12) -> tuple[F64, F64, F64]:
    """Mean and RMS of ``r`` in quantile bins of ``values``: (bin centres, mean, rms)."""
    ok = np.isfinite(values) & np.isfinite(r)
    v, rr = values[ok], r[ok]
    if v.size < bins or np.ptp(v) == 0:
        return np.empty(0), np.empty(0), np.empty(0)
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(idx, minlength=edges.size - 1).astype(np.float64)
    good = cnt > 0
    mean = np.bincount(idx, rr, edges.size - 1)[good] / cnt[good]
    rms = np.sqrt(np.bincount(idx, rr * rr, edges.size - 1)[good] / cnt[good])
    centre = (np.bincount(idx, v, edges.size - 1)[good]) / cnt[good]
    return centre, mean, rms


def since_turn(data: AuditData) -> F64:
    """Voltage travelled since the last reversal of the voltage, per sample (V)."""
    out = np.zeros(data.n)
    for i in range(data.n_experiments):
        sl = data.slice(i)
        v = data.voltage_v[sl]
        s = data.direction[sl]
        turn = np.concatenate(([True], s[1:] != s[:-1]))
        idx = np.maximum.accumulate(np.where(turn, np.arange(v.size), 0))
        out[sl] = np.abs(v - v[idx])
    return out


def velocity(data: AuditData) -> F64:
    """Voltage rate per sample (V/s), central differences within experiments."""
    out = np.zeros(data.n)
    for i in range(data.n_experiments):
        sl = data.slice(i)
        out[sl] = np.gradient(data.voltage_v[sl], data.t_s[sl])
    return out


def loop_closure(data: AuditData) -> F64:
    """Per periodic experiment: RMS change of the measured position from one loop to the next (um).

    Model-free: a steady, noise-free loop repeats exactly, so this is ``sqrt(2)`` times the noise
    plus drift, creep settling and other slow changes. NaN for experiments with fewer than two loops.
    """
    out = np.full(data.n_experiments, np.nan)
    for i, e in enumerate(data.info):
        p = e.period_samples
        sl = data.slice(i)
        x = data.position_um[sl]
        if p <= 0 or x.size < 2 * p:
            continue
        d = x[p:] - x[:-p]
        out[i] = math.sqrt(float(np.mean((d - d.mean()) ** 2)))
    return out


def spectrum(data: AuditData, rows: NDArray[np.bool_], r: F64) -> tuple[F64, F64]:
    """Amplitude spectrum of the residual (um per sqrt(Hz)), averaged over experiments on a common grid.

    Experiments are resampled onto log-spaced frequency bins from their periodograms.
    """
    full = np.zeros(data.n)
    full[rows] = r
    fmin = math.inf
    fmax = 0.0
    for e in data.info:
        fmin = min(fmin, 1.0 / max(e.duration_s, 1e-12))
        fmax = max(fmax, 0.5 / e.dt_s)
    if not (math.isfinite(fmin) and fmax > fmin):
        return np.empty(0), np.empty(0)
    grid = np.exp(np.linspace(math.log(fmin), math.log(fmax), 120))
    acc = np.zeros(grid.size)
    cnt = np.zeros(grid.size)
    for i, e in enumerate(data.info):
        sl = data.slice(i)
        y = full[sl]
        n = y.size
        if n < 16:
            continue
        win = np.hanning(n)
        spec = np.abs(np.fft.rfft((y - y.mean()) * win)) ** 2 * 2.0 * e.dt_s / np.sum(win**2)
        f = np.fft.rfftfreq(n, e.dt_s)
        idx = np.searchsorted(grid, f[1:])
        ok = idx < grid.size
        np.add.at(acc, idx[ok], spec[1:][ok])
        np.add.at(cnt, idx[ok], 1.0)
    good = cnt > 0
    return grid[good], np.sqrt(acc[good] / cnt[good])


def correlation(a: F64, b: F64) -> float:
    """Pearson correlation of the finite pairs (nan when undefined)."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return math.nan
    return float(np.corrcoef(a[ok], b[ok])[0, 1])
