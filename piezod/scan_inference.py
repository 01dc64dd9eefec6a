"""Scan inference: what a voltage (or target) waveform is, and where it turns.

:func:`infer_scan` finds the turning points of a waveform with a Schmitt trigger at
30 % / 70 % of its span, fits a straight line and a half cosine to every half period,
and classifies the waveform as ``triangle``, ``sine``, ``periodic`` (regular
back-and-forth motion of another shape, e.g. a corrected scan), ``ramp``, ``constant``
or ``arbitrary``. It returns the line frequency, the turning voltages, the per-sample
direction (+1 trace, -1 retrace) and the number of complete loops (:class:`ScanInfo`).

The steps, each a function below: the robust span (:func:`_robust_span`), turning-point
candidates from the Schmitt trigger (:func:`_schmitt_turns`), the white-noise level
from second differences (:func:`_noise_d2`), dropping record-edge candidates cut short
by the record's start or end (:func:`_drop_cut_edges`), per-half-period shape fits
(:func:`_fit_halves`), refined turning times of a triangle (:func:`_refine_triangle`),
the period and duty (:func:`_period_and_duty`), the per-sample direction, the
regularity checks (:func:`_irregularities`) and the classification.

Pure numpy, no I/O; the recording reader (:mod:`piezod.recording`) uses it for
:meth:`piezod.recording.Experiment.scan`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
I8 = NDArray[np.int8]

ScanKind = Literal["triangle", "sine", "periodic", "ramp", "constant", "arbitrary"]

#: Largest straight-line (or half-cosine) shape error of a triangle (or sine), relative to the span.
_SHAPE_TOL = 0.01
#: The better shape must fit at least this much better than the other one.
_SHAPE_RATIO = 0.4
#: Largest relative spread of turning values and half-period durations of a periodic waveform.
_REGULAR_TOL = 0.05
#: Below this sample noise / span the extreme samples are the turning values.
_CLEAN_TOL = 1e-4


def _frozen(a: ArrayLike, dtype: type | np.dtype[np.generic]) -> NDArray[np.generic]:
    arr = np.array(a, dtype=dtype)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class ScanInfo:
    """What the voltage (or target) waveform of an experiment is.

    Attributes
    ----------
    kind
        ``triangle`` (periodic, straight half periods), ``sine``, ``periodic`` (regular
        back-and-forth of another shape), ``ramp``, ``constant`` or ``arbitrary``.
    reason
        Why the waveform is not a periodic triangle (empty when it is).
    frequency_hz
        Line (trace + retrace) frequency; nan when there is no complete half period.
    v_min, v_max
        Turning values: the median lower / upper turning point (extreme samples for a
        clean waveform, intersections of the fitted half-period lines for a noisy
        triangle); the sample minimum / maximum when there are no turning points.
    turning_indices
        Sample indices of the turning points, in time order.
    turning_kinds
        +1 for an upper (maximum), -1 for a lower (minimum) turning point.
    direction
        Per sample: +1 trace (rising), -1 retrace (falling). A turning sample belongs to
        the half period that starts there.
    n_loops
        Number of complete periods between the first and the last turning point.
    shape_error
        RMS deviation of the half periods from straight lines, relative to the span.
    noise
        RMS deviation from the best fitting shape (line or half cosine), in waveform units.
    duty
        Fraction of the period spent rising (0.5 for a symmetric triangle; nan if unknown).
    wraps
        The record is one period that starts and ends inside a half period, e.g. a one-period
        triangle ``0 -> +V -> 0 -> -V -> 0`` as instruments export one loop per block: its
        first and last pieces together are one half period (``n_loops`` is 1; the record does
        not start at a turning point, so the first piece may hold the initial curve).
    """

    kind: ScanKind
    reason: str
    frequency_hz: float
    v_min: float
    v_max: float
    turning_indices: NDArray[np.int64]
    turning_kinds: NDArray[np.int8]
    direction: NDArray[np.int8]
    n_loops: int
    shape_error: float
    noise: float
    duty: float
    wraps: bool = False

    @property
    def range_v(self) -> float:
        """Peak-to-peak range ``v_max - v_min``."""
        return self.v_max - self.v_min

    @property
    def offset_v(self) -> float:
        """Centre ``(v_max + v_min) / 2``."""
        return 0.5 * (self.v_max + self.v_min)

    @property
    def period_s(self) -> float:
        """``1 / frequency_hz``."""
        return 1.0 / self.frequency_hz

    @property
    def is_scan(self) -> bool:
        """A periodic triangular scan with at least one complete loop."""
        return self.kind == "triangle" and self.n_loops >= 1

    @property
    def is_periodic(self) -> bool:
        """Regular back-and-forth motion (triangle, sine or another periodic shape), >= 1 loop."""
        return self.kind in ("triangle", "sine", "periodic") and self.n_loops >= 1


def infer_scan(t_s: ArrayLike, voltage: ArrayLike) -> ScanInfo:
    """Infer scan frequency, range, offset, direction and turning points of a waveform.

    Parameters
    ----------
    t_s
        Sample times (s), strictly increasing.
    voltage
        The waveform (V; any unit works, e.g. a target position in um).

    Returns
    -------
    ScanInfo
        The classification and the inferred scan (see :class:`ScanInfo`).
    """
    t = np.asarray(t_s, dtype=np.float64)
    v = np.asarray(voltage, dtype=np.float64)
    n = v.size
    if n < 4:
        return _nonscan("arbitrary", f"only {n} samples", v)
    vmin_all, vmax_all = float(v.min()), float(v.max())
    scale = max(abs(vmin_all), abs(vmax_all), 1e-300)
    if vmax_all - vmin_all <= 1e-9 * scale:
        return _nonscan("constant", "the waveform is constant", v)
    lo, span = _robust_span(v, vmin_all, vmax_all)
    idx, kinds = _schmitt_turns(v, lo, span)
    noise_d2 = _noise_d2(v)
    idx, kinds = _drop_cut_edges(
        v, idx, kinds, 0.005 * span + 4.0 * noise_d2, _REGULAR_TOL * span + 6.0 * noise_d2
    )

    if idx.size < 2:
        direction = _direction_from_slope(v)
        if idx.size == 0 and abs(v[-1] - v[0]) >= 0.8 * (vmax_all - vmin_all):
            return _nonscan("ramp", "monotonic ramp, no turning point", v, direction)
        return _nonscan("arbitrary", f"{idx.size} turning point(s): not a back-and-forth scan", v, direction)

    halves = _fit_halves(t, v, idx, span, noise_d2)
    t_turn = t[idx].copy()
    v_turn = v[idx].copy()
    clean = noise_d2 <= _CLEAN_TOL * span
    if halves.triangle:
        idx = _refine_triangle(t, v_turn, t_turn, idx, kinds, halves, clean)
    vmaxs = v_turn[kinds > 0]
    vmins = v_turn[kinds < 0]
    v_max = float(np.median(vmaxs)) if vmaxs.size else vmax_all
    v_min = float(np.median(vmins)) if vmins.size else vmin_all
    frequency, duty = _period_and_duty(t_turn, kinds)
    direction = _direction_from_turns(n, idx, kinds)
    n_loops = (idx.size - 1) // 2

    problems = _irregularities(t, v, idx, kinds, direction, t_turn, vmaxs, vmins, span, noise_d2, halves)
    kind, reason = _classify(problems, halves, idx.size, n_loops)
    wraps = False
    if kind == "triangle" and n_loops == 0 and idx.size == 2:
        why_not = _one_period(t, v, idx, span, noise_d2)
        if why_not:
            reason += f" ({why_not})"
        else:
            wraps, n_loops, reason = True, 1, ""
            frequency = 1.0 / float(t[-1] - t[0])
            duty = float(t[idx[0]] - t[0] + t[-1] - t[idx[1]]) * frequency
            if kinds[0] < 0:
                duty = 1.0 - duty
    return ScanInfo(
        kind=kind,
        reason=reason,
        frequency_hz=float(frequency),
        v_min=v_min,
        v_max=v_max,
        turning_indices=_frozen(idx, np.int64),  # type: ignore[arg-type]
        turning_kinds=_frozen(kinds, np.int8),  # type: ignore[arg-type]
        direction=_frozen(direction, np.int8),  # type: ignore[arg-type]
        n_loops=int(n_loops),
        shape_error=float(halves.shape_line),
        noise=float(halves.noise),
        duty=duty,
        wraps=wraps,
    )


def _one_period(t: F64, v: F64, idx: I64, span: float, noise_d2: float) -> str:
    """Empty when a record with two turning points is one whole triangle period, else why not.

    The pieces before the first and after the last turning point must be straight, with the
    same slope, and join into the missing half period: the record starts and ends at the same
    level, and the two pieces together cross the whole span.
    """
    a, b = int(idx[0]), int(idx[-1])
    n = v.size
    if a < 2 or n - b < 3:
        return "the record starts or ends at a turning point"
    tol = _REGULAR_TOL * span + 6.0 * noise_d2
    if abs(v[-1] - v[0]) > tol:
        return f"it starts at {v[0]:.4g} and ends at {v[-1]:.4g}: not one whole period"
    travel = abs(v[a] - v[0]) + abs(v[-1] - v[b])
    if abs(travel - abs(v[b] - v[a])) > tol:
        return "the first and last pieces do not join into a half period"
    slopes, sq = [], 0.0
    for sl in (slice(0, a + 1), slice(b, n)):
        tt, vv = t[sl], v[sl]
        coef = np.polyfit(tt - tt[0], vv, 1)
        slopes.append(float(coef[0]))
        sq += float(np.sum((vv - np.polyval(coef, tt - tt[0])) ** 2))
    rms = math.sqrt(max(0.0, sq / (a + 1 + n - b) - noise_d2**2)) / span
    if rms > _SHAPE_TOL or abs(slopes[0] - slopes[1]) > _REGULAR_TOL * max(abs(slopes[0]), abs(slopes[1])):
        return "the first and last pieces are not one straight half period"
    return ""


def _robust_span(v: F64, vmin_all: float, vmax_all: float) -> tuple[float, float]:
    """Lower level and span from the 1 / 99 % percentiles (the full range if they collapse)."""
    lo, hi = (float(q) for q in np.percentile(v, [1.0, 99.0]))
    span = hi - lo
    if span <= 1e-6 * (vmax_all - vmin_all):
        lo, span = vmin_all, vmax_all - vmin_all
    return lo, span


def _schmitt_turns(v: F64, lo: float, span: float) -> tuple[I64, I8]:
    """Turning-point candidates: the extreme sample of every run above 70 % / below 30 % of the span."""
    n = v.size
    band = np.zeros(n, dtype=np.int8)
    band[v >= lo + 0.7 * span] = 1
    band[v <= lo + 0.3 * span] = -1
    nz = np.flatnonzero(band)
    # Forward-filled band state: the last band the waveform was in (0 before the first).
    fill = np.maximum.accumulate(np.where(band != 0, np.arange(n), 0))
    state = band[fill]
    state[: nz[0]] = 0
    change = np.flatnonzero(np.diff(state)) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [n]))
    cand_idx: list[int] = []
    cand_kind: list[int] = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        k = int(state[s])
        if k == 0:
            continue
        run_v = v[s:e]
        cand_idx.append(s + int(np.argmax(run_v) if k > 0 else np.argmin(run_v)))
        cand_kind.append(k)
    return np.asarray(cand_idx, dtype=np.int64), np.asarray(cand_kind, dtype=np.int8)


def _noise_d2(v: F64) -> float:
    """White sample noise (RMS) estimated robustly from second differences."""
    if v.size <= 2:
        return 0.0
    d2 = np.diff(v, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _drop_cut_edges(v: F64, idx: I64, kinds: I8, tol: float, turn: float) -> tuple[I64, I8]:
    """Drop first / last candidates not at the level of the other turning points of their kind.

    The first and last band runs may be cut by the record's start or end and then hold no
    turning point at all: they count only next to real ones and at their level, or where the
    waveform turns back on both sides of them by more than ``turn`` (a record that starts or
    ends anywhere in the period, e.g. one period from the middle of a branch).
    """
    if not idx.size:
        return idx, kinds
    interior = np.ones(idx.size, dtype=bool)
    interior[[0, -1]] = False
    keep = interior.copy()
    if not interior.any():
        # One or two candidates (a one-period triangle, a half loop): a candidate is a turning
        # point when the waveform turns back on both sides of it, i.e. when its band run is
        # not cut by the record's start or end.
        for j, (k, kind) in enumerate(zip(idx.tolist(), kinds.tolist(), strict=True)):
            drop = kind * (v[k] - v)
            keep[j] = bool(np.any(drop[: k + 1] >= turn) and np.any(drop[k:] >= turn))
        return idx[keep], kinds[keep]
    for edge in np.flatnonzero(~interior):
        same = kinds == kinds[edge]
        ref_pool = v[idx[same & interior]] if np.any(same & interior) else v[idx[same]]
        k, kind = int(idx[edge]), int(kinds[edge])
        back = kind * (v[k] - v)
        turns = bool(np.any(back[: k + 1] >= turn) and np.any(back[k:] >= turn))
        keep[edge] = turns or abs(v[k] - float(np.median(ref_pool))) <= tol
    return idx[keep], kinds[keep]


@dataclass(frozen=True)
class _Halves:
    """Straight-line and half-cosine fits of every half period (between turning points)."""

    seg: NDArray[np.intp]  # half-period index of every row between the first and last turn
    t_start: F64  # start time of every half period
    dur: F64  # duration of every half period
    line_a: F64  # line fit v = a + b u, u in [0, 1] over the half period
    line_b: F64
    shape_line: float  # RMS straight-line error / span
    noise: float  # RMS error of the better shape
    triangle: bool
    sine: bool


def _half_period_rows(idx: I64, nseg: int) -> tuple[NDArray[np.int64], NDArray[np.intp]]:
    rows = np.arange(int(idx[0]), int(idx[-1]) + 1)
    seg = np.clip(np.searchsorted(idx, rows, side="right") - 1, 0, nseg - 1).astype(np.intp)
    return rows, seg


def _fit_halves(t: F64, v: F64, idx: I64, span: float, noise_d2: float) -> _Halves:
    """Per half period: line and half-cosine least-squares fits (vectorised over segments)."""
    nseg = idx.size - 1
    rows, seg = _half_period_rows(idx, nseg)
    t_start = t[idx[:-1]]
    dur = t[idx[1:]] - t_start
    u = (t[rows] - t_start[seg]) / dur[seg]
    vv = v[rows]
    r_line, line_a, line_b = _segment_fit(u, vv, seg, nseg)
    r_cos, _, _ = _segment_fit(np.cos(np.pi * u), vv, seg, nseg)
    npts = rows.size
    line_rms = math.sqrt(float(np.sum(r_line**2)) / npts)
    cos_rms = math.sqrt(float(np.sum(r_cos**2)) / npts)
    # Shape errors in excess of white sample noise (estimated from second differences).
    ex_line = math.sqrt(max(0.0, line_rms**2 - noise_d2**2)) / span
    ex_cos = math.sqrt(max(0.0, cos_rms**2 - noise_d2**2)) / span
    triangle = ex_line <= _SHAPE_TOL and ex_line <= _SHAPE_RATIO * ex_cos
    sine = not triangle and ex_cos <= _SHAPE_TOL and ex_cos <= _SHAPE_RATIO * ex_line
    return _Halves(
        seg=seg,
        t_start=t_start,
        dur=dur,
        line_a=line_a,
        line_b=line_b,
        shape_line=line_rms / span,
        noise=min(line_rms, cos_rms),
        triangle=triangle,
        sine=sine,
    )


def _refine_triangle(
    t: F64, v_turn: F64, t_turn: F64, idx: I64, kinds: I8, halves: _Halves, clean: bool
) -> I64:
    """Turning times (and, for a noisy triangle, values) where adjacent fitted lines meet.

    Updates ``t_turn`` and ``v_turn`` in place; returns the turning indices re-anchored
    at the refined times (nearest sample) for a noisy triangle, else ``idx`` unchanged.
    """
    n = t.size
    nseg = idx.size - 1
    # line k: v = icpt_k + slope_k t
    slope = halves.line_b / halves.dur
    icpt = halves.line_a - slope * halves.t_start
    if nseg >= 2:
        ds = slope[:-1] - slope[1:]
        ok = np.abs(ds) > 0
        tx = np.where(ok, (icpt[1:] - icpt[:-1]) / np.where(ok, ds, 1.0), t_turn[1:-1])
        t_turn[1:-1] = tx
        if not clean:
            v_turn[1:-1] = np.where(ok, icpt[:-1] + slope[:-1] * tx, v_turn[1:-1])
    # An extreme sample at a record edge is a poor turning time (the vertex may lie just
    # outside, or noise moved it): where the edge's line reaches the level of the other
    # turning points of that kind is a better one.
    pos = np.arange(idx.size)
    for end, sg in ((0, 0), (idx.size - 1, nseg - 1)):
        others = (kinds == kinds[end]) & (pos > 0) & (pos < idx.size - 1)
        if not others.any():
            others = (kinds == kinds[end]) & (pos != end)
        level = float(np.median(v_turn[others])) if others.any() else float(v_turn[end])
        if slope[sg] != 0:
            t_turn[end] = (level - icpt[sg]) / slope[sg]
            if not clean:
                v_turn[end] = level
    if clean:
        return idx
    j = np.clip(np.searchsorted(t, t_turn), 1, n - 1)
    near = np.where(t_turn - t[j - 1] <= t[j] - t_turn, j - 1, j)
    if np.all(np.diff(near) > 0):
        return near.astype(np.int64)
    return idx


def _period_and_duty(t_turn: F64, kinds: I8) -> tuple[float, float]:
    """Line frequency (same-kind turning times regressed on their count) and rising duty."""
    slopes: list[tuple[float, int]] = []
    for k in (1, -1):
        tk = t_turn[kinds == k]
        if tk.size >= 2:
            j = np.arange(tk.size, dtype=np.float64)
            slopes.append((float(np.polyfit(j, tk, 1)[0]), tk.size - 1))
    if slopes:
        period = sum(s * w for s, w in slopes) / sum(w for _, w in slopes)
    else:
        period = 2.0 * float(t_turn[1] - t_turn[0])
    frequency = 1.0 / period if period > 0 else math.nan
    rising = -kinds[:-1] > 0
    if not (np.any(rising) and np.any(~rising)):
        return frequency, 0.5
    return frequency, float(np.mean(np.diff(t_turn)[rising]) * frequency)


def _direction_from_turns(n: int, idx: I64, kinds: I8) -> I8:
    """+1 rising / -1 falling per sample; a turning sample starts the next half period."""
    lo_i, hi_i = int(idx[0]), int(idx[-1])
    _, seg = _half_period_rows(idx, idx.size - 1)
    direction = np.empty(n, dtype=np.int8)
    direction[:lo_i] = kinds[0]
    direction[lo_i : hi_i + 1] = (-kinds[:-1])[seg]
    direction[hi_i:] = -kinds[-1]
    return direction


def _irregularities(
    t: F64,
    v: F64,
    idx: I64,
    kinds: I8,
    direction: I8,
    t_turn: F64,
    vmaxs: F64,
    vmins: F64,
    span: float,
    noise_d2: float,
    halves: _Halves,
) -> list[str]:
    """Why the motion is not regular back-and-forth (empty list when it is)."""
    problems: list[str] = []
    vmin_all, vmax_all = float(v.min()), float(v.max())
    # Back-and-forth, not wandering: between turning points the motion may not turn back by much.
    part = np.searchsorted(idx, np.arange(v.size), side="right")
    w = direction * (v - 0.5 * (vmax_all + vmin_all)) + part * (2.0 * (vmax_all - vmin_all))
    backtrack = float(np.max(np.maximum.accumulate(w) - w))
    if backtrack > _REGULAR_TOL * span + 6.0 * noise_d2:
        problems.append(f"the motion turns back by {backtrack:.4g} between turning points (span {span:.4g})")
    for name, vals in (("upper", vmaxs), ("lower", vmins)):
        if vals.size >= 2 and np.ptp(vals) > _REGULAR_TOL * span + 6.0 * halves.noise:
            problems.append(f"{name} turning points vary by {np.ptp(vals):.4g} of span {span:.4g}")
    seg_dur = np.diff(t_turn)
    rising = -kinds[:-1] > 0
    for name, sel in (("rising", rising), ("falling", ~rising)):
        d = seg_dur[sel]
        if d.size < 2:
            continue  # one half period (or none) cannot vary
        # Turning times of a rounded waveform jitter with the noise (flat tops); a triangle's do not.
        jitter = (
            0.0
            if halves.triangle
            else 4.0 * float(np.mean(d)) / math.pi * math.sqrt(2.0 * halves.noise / span)
        )
        if np.ptp(d) > _REGULAR_TOL * np.mean(d) + 4.0 * float(np.median(np.diff(t))) + jitter:
            problems.append(f"{name} half periods last {d.min():.4g} s to {d.max():.4g} s")
    return problems


def _classify(problems: list[str], halves: _Halves, n_turns: int, n_loops: int) -> tuple[ScanKind, str]:
    if problems:
        return "arbitrary", "not periodic: " + "; ".join(problems)
    if halves.triangle:
        return "triangle", ("" if n_loops >= 1 else f"only {n_turns} turning points, no complete loop")
    if halves.sine:
        return "sine", f"sinusoidal (straight-line error {halves.shape_line:.2%} of the span)"
    return "periodic", f"half periods are not straight (error {halves.shape_line:.2%} of the span)"


def _segment_fit(basis: F64, v: F64, seg: NDArray[np.intp], nseg: int) -> tuple[F64, F64, F64]:
    """Per-segment least squares ``v = a + b * basis``; returns residuals, a, b."""
    cnt = np.bincount(seg, minlength=nseg).astype(np.float64)
    mb = np.bincount(seg, basis, nseg) / cnt
    mv = np.bincount(seg, v, nseg) / cnt
    bc = basis - mb[seg]
    vc = v - mv[seg]
    sbb = np.bincount(seg, bc * bc, nseg)
    sbv = np.bincount(seg, bc * vc, nseg)
    b = np.divide(sbv, sbb, out=np.zeros(nseg), where=sbb > 0)
    a = mv - b * mb
    return vc - b[seg] * bc, a, b


def _direction_from_slope(v: F64) -> I8:
    d = np.sign(np.diff(v)).astype(np.int8)
    nz = d != 0
    if not nz.any():
        return np.ones(v.size, dtype=np.int8)
    fill = np.maximum.accumulate(np.where(nz, np.arange(d.size), 0))
    d = d[fill]
    first = int(np.flatnonzero(nz)[0])
    d[:first] = d[first]
    return np.concatenate((d, d[-1:]))


def _nonscan(kind: ScanKind, reason: str, v: F64, direction: I8 | None = None) -> ScanInfo:
    if direction is None:
        direction = _direction_from_slope(v) if v.size else np.zeros(0, dtype=np.int8)
    return ScanInfo(
        kind=kind,
        reason=reason,
        frequency_hz=math.nan,
        v_min=float(v.min()) if v.size else math.nan,
        v_max=float(v.max()) if v.size else math.nan,
        turning_indices=_frozen(np.zeros(0), np.int64),  # type: ignore[arg-type]
        turning_kinds=_frozen(np.zeros(0), np.int8),  # type: ignore[arg-type]
        direction=_frozen(direction, np.int8),  # type: ignore[arg-type]
        n_loops=0,
        shape_error=math.nan,
        noise=math.nan,
        duty=math.nan,
    )
