"""Linearity from images of a reference of known pitch: the thesis's (4.14)-(4.16) without a sensor.

The thesis calibrated its tube scanners from SPM images of length standards (1D3000, 2D200,
chapter 2 and section 4.4): the flanks of the lines are found in every image line, identified with
their known positions ``k P`` on the sample, and regressed on their pixel position. Here, per image
(trace or retrace, on the commanded grid):

1. Every line (row) is levelled by a least-squares line; the threshold is halfway between its 10th
   and 90th percentiles; the flanks are the threshold crossings, interpolated linearly between
   pixel centres (sub-pixel). Rising and falling flanks are two families.
   A crossing counts only when the profile goes on to the other plateau (a Schmitt trigger at
   +-25 % of the step, after a 3-pixel median): spikes of the z loop make no flanks.
2. The local line width (a rising flank to the next falling one) along the line is a robust cubic
   fit of the log widths of all lines against their position (every line scans alike, so the
   stretch near the turning points is shared; particles are outliers of it). Pairs whose width
   differs from it by more than 35 % are dropped: particles and defects make narrow bumps, not
   lines. The period is the median gap in units of the local width (most gaps are one period).
3. Within a line and family, successive flanks are numbered by their gap in units of the local
   period (a missing line - the same gap in every line of a 1D pattern - is a gap of two).
4. The true position ``k P`` is regressed on the commanded position ``xi`` of the flank with one
   intercept per (line, family) - the unknown position of the sample - and one common slope; one
   pass drops flanks whose residual exceeds five robust standard deviations (dust the width test
   missed).
5. The metric weighs the line as the sensor path does. Flanks are uniform in *true* position, the
   sensor's samples of a linear scan uniform in *time* (in commanded position): on a curved
   response a straight-line fit through the flanks and one through the samples give different
   slopes (by up to a few tenths of a percent on an uncorrected scan, where both are right about
   their own points). So the flanks are not the regression's points: they give the true position
   as a function of the commanded one, ``x(xi) = k P`` (:func:`position_map`: a Legendre series of
   degree <= 6 shared by all lines, one intercept per line and family, fitted to all flanks; one
   pass drops outliers of it), which is resampled uniformly in commanded position (a quarter pixel
   apart), as the samples are, over the stretches the image sees (:func:`seen_spans`: from the
   lines' first flank to their last, less the stretches more than half a period from any flank -
   the missing line).
6. (4.14)-(4.16) of that map by :func:`piezod.linearity.branch_linearity`, the sensor path's own
   regression: ``x'_R = g R``, ``e_l = (x'_R - R) / R``, ``e_rel = sigma / x'_R`` (``sigma`` of
   the smooth map: the flanks' own scatter, the sample's edge roughness, is not the scanner's).
   The sensor figure this reproduces is the sensor path over the same stretches
   (:func:`window_linearity`); over the whole lines the sensor also sees the line ends no flank
   covers, and everywhere the position's structure finer than the flank spacing (half a period),
   which the image cannot resolve.
7. The standard uncertainty of the length error from the flank-position noise: the slope of step
   6 is linear in the map's coefficients, whose covariance is that of the fit (the flanks'
   scatter about it taken independent).

The local pitch error along the line, ``P / dxi - 1`` for successive flanks of a family, is the
picture of the nonlinearity (:func:`plot_pitch_error`): positive where the scanner moves farther
than commanded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.errors import RecordingError
from piezod.image import F64, Geometry, level
from piezod.linearity import BranchLinearity, branch_linearity

_WIDTH_TOLERANCE = 0.35
_OUTLIER_SIGMAS = 5.0
#: Schmitt-trigger band of the flank detection, a fraction of the step between the plateaus.
_HYSTERESIS = 0.25


@dataclass(frozen=True, slots=True)
class Flanks:
    """The flanks found in one image.

    Attributes
    ----------
    xi_um
        Commanded fast coordinate of each flank (um).
    k
        Period number of each flank (relative within its line and family).
    family
        +1 rising, -1 falling.
    line
        Image line (row) of each flank.
    """

    xi_um: F64
    k: NDArray[np.int64]
    family: NDArray[np.int8]
    line: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class ImageLinearity:
    """(4.14)-(4.16) of one image.

    Attributes
    ----------
    direction
        +1 trace, -1 retrace.
    pitch_um
        The reference's pitch (um).
    flanks
        Flanks used in the regression.
    dropped
        Flanks dropped as outliers.
    lines
        Image lines with flanks.
    slope
        ``g``: true um per commanded um.
    nominal_range_um, measured_range_um
        ``R`` and ``x'_R = g R``.
    sigma_um
        Residual standard deviation (um).
    nonlinearity_pct, length_error_pct
        (4.16) and (4.15) in %, of the map resampled uniformly in commanded position (as the
        sensor's samples).
    length_error_unc_pct
        Standard uncertainty of ``length_error_pct`` from the flank-position noise (the spread of
        the lines' own slopes); NaN with fewer than three lines.
    flank_length_error_pct
        (4.15) of the straight-line fit through the flanks themselves (weighted by true position;
        for comparison).
    windows
        ``(line, lo, hi)``: the commanded stretches (um) of every line the metric covers.
    flank_scatter_um
        RMS scatter of the flanks about the position map (um): the sample's edge roughness and
        the detection - the image's counterpart of a sensor's noise, which a sensor's
        non-linearity includes and this one does not.
    """

    direction: int
    pitch_um: float
    flanks: int
    dropped: int
    lines: int
    slope: float
    nominal_range_um: float
    measured_range_um: float
    sigma_um: float
    nonlinearity_pct: float
    length_error_pct: float
    length_error_unc_pct: float = math.nan
    flank_length_error_pct: float = math.nan
    windows: tuple[tuple[int, float, float], ...] = ()
    flank_scatter_um: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "direction": "trace" if self.direction > 0 else "retrace",
            "pitch_um": self.pitch_um,
            "flanks": self.flanks,
            "dropped": self.dropped,
            "lines": self.lines,
            "slope": self.slope,
            "nominal_range_um": self.nominal_range_um,
            "measured_range_um": self.measured_range_um,
            "sigma_um": self.sigma_um,
            "nonlinearity_pct": self.nonlinearity_pct,
            "length_error_pct": self.length_error_pct,
            "length_error_unc_pct": self.length_error_unc_pct,
            "flank_length_error_pct": self.flank_length_error_pct,
            "flank_scatter_um": self.flank_scatter_um,
            "windows_um": sorted({(lo, hi) for _, lo, hi in self.windows}),
        }


def _step(profile: F64) -> float:
    """The 10-90 percentile spread of a line-levelled profile (0 for too few values)."""
    ok = np.isfinite(profile)
    if ok.sum() < 8:
        return 0.0
    xs = np.arange(profile.size, dtype=np.float64)
    d = profile[ok] - np.polyval(np.polyfit(xs[ok], profile[ok], 1), xs[ok])
    lo, hi = np.percentile(d, [10, 90])
    return float(hi - lo)


def _crossings(profile: F64, xs: F64) -> tuple[F64, F64]:
    """Rising and falling crossings of the mid level of a levelled profile (sub-pixel)."""
    ok = np.isfinite(profile)
    if ok.sum() < 8:
        return np.zeros(0), np.zeros(0)
    p = profile.copy()
    # a 3-pixel median removes one-pixel spikes (z-loop overshoots) and keeps the edges
    inner = ok[:-2] & ok[1:-1] & ok[2:]
    p[1:-1][inner] = np.median(np.stack((p[:-2], p[1:-1], p[2:])), axis=0)[inner]
    coef = np.polyfit(xs[ok], p[ok], 1)
    d = p - np.polyval(coef, xs)
    lo, hi = np.nanpercentile(d, [10, 90])
    if not hi - lo > 0:
        return np.zeros(0), np.zeros(0)
    s = d - 0.5 * (lo + hi)
    # Two plateaus on one tilted line: p = a + b x + c [upper]; the mid level a + b x + c / 2 does
    # not lean with the pattern's asymmetry (a missing line) as a plain line fit does.
    step = float(hi - lo)
    for _ in range(2):
        upper = (s > 0).astype(np.float64)
        far = ok & (np.abs(s) > 0.25 * (hi - lo))
        if far.sum() < 4 or upper[far].min() == upper[far].max():
            break
        a = np.column_stack((np.ones(int(far.sum())), xs[far], upper[far]))
        c0, c1, c2 = np.linalg.lstsq(a, p[far], rcond=None)[0]
        s = p - (c0 + c1 * xs + 0.5 * c2)
        step = abs(float(c2))
        if c2 < 0:
            s = -s
    return _schmitt(s, xs, _HYSTERESIS * (hi - lo), step)


def _schmitt(s: F64, xs: F64, band: float, step: float) -> tuple[F64, F64]:
    """Zero crossings of ``s`` that complete a transition from below ``-band`` to above ``+band``
    (rising) or back (falling), at the last zero crossing before the far level is reached.

    A spike in a plateau (the z loop's overshoot where the z piezo reverses, a speck of dust) that
    does not reach the other level makes no flank; a noisy edge makes one, not several.

    Where is the flank within its pixels: a pixel is the mean over its width, so a sharp edge
    leaves one pixel at an intermediate level, and a straight line between pixel centres puts
    the crossing up to ~0.1 pixel off, by an amount that changes with the edge's phase in the
    pixel grid - along an image line, a slope error of up to ~0.1 % on a 20 um line. The
    pixels conserve the area under the profile, so the edge is found from it (:func:`_by_area`).
    """
    level = np.where(s > band, 1, np.where(s < -band, -1, 0))
    idx = np.flatnonzero(level != 0)
    if idx.size < 2:
        return np.zeros(0), np.zeros(0)
    lv = level[idx]
    change = np.flatnonzero(lv[1:] != lv[:-1]) + 1
    ends, rising = idx[change], lv[change] > 0
    # the last sign change of s before each end: the last sample on the near side of 0
    near = np.where(np.isfinite(s) & (s < 0), 1, np.where(np.isfinite(s) & (s >= 0), -1, 0))
    pos = np.arange(s.size)
    last_neg = np.maximum.accumulate(np.where(near > 0, pos, -1))
    last_pos = np.maximum.accumulate(np.where(near < 0, pos, -1))
    i = np.where(rising, last_neg[ends - 1], last_pos[ends - 1])
    ok = (i >= 0) & (i + 1 < s.size)
    i, rising = i[ok], rising[ok]
    a, b = s[i], s[i + 1]
    ok = np.isfinite(a) & np.isfinite(b) & (a != b)
    i, rising, a, b = i[ok], rising[ok], a[ok], b[ok]
    x: F64 = xs[i] + a / (a - b) * (xs[i + 1] - xs[i])
    x = _by_area(s, xs, i, rising, x, step)
    return x[rising], x[~rising]


def _by_area(s: F64, xs: F64, i: NDArray[np.intp], rising: NDArray[np.bool_], x: F64, step: float) -> F64:
    """Edge positions from the area of the profile around the crossings between ``i`` and ``i + 1``.

    In a window of ``2 m`` pixels around the crossing, each pixel's fraction on the left of the
    edge (``(v_R - v) / (v_R - v_L)``) summed, times the pixel width, from the window's left
    boundary: exact for a sharp edge and for any edge profile symmetric about its middle,
    whatever its phase in the pixel grid. ``m`` (1-3) stays below a third of the distance
    between crossings; a window that leaves the line or meets a missing value keeps ``x``.

    The levels ``v_L``, ``v_R`` are the plateaus' just outside the window (the median of up to
    three pixels on each side): a level off the line's two-level fit by ``d`` (a fraction of the
    step) would move the edge by ``2 m d`` pixels, in opposite directions for rising and falling
    edges. Heights recorded as z-piezo voltage bend along the line (the z piezo's own
    hysteresis under the sample's tilt: a few % of the step), which put rising and falling
    flanks apart by a scale of ~0.05 % on a 32 um line. Where the plateaus are too short the
    two-level fit's levels (``-+ step / 2``) stand.
    """
    if i.size == 0 or not step > 0 or xs.size < 4:
        return x
    dx = float(xs[1] - xs[0])
    gap = float(np.median(np.diff(np.sort(x)))) / abs(dx) if x.size > 1 else float(xs.size)
    m = int(np.clip(gap // 3, 1, 3))
    offs = np.arange(-m + 1, m + 1)
    j = i[:, None] + offs[None, :]
    inside = (j[:, 0] >= 0) & (j[:, -1] < s.size)
    jj = np.clip(j, 0, s.size - 1)
    v = s[jj]
    sign = np.where(rising, 1.0, -1.0)
    v_left, v_right = -0.5 * step * sign, 0.5 * step * sign
    q = int(np.clip(int(gap) - 2 * m, 0, 3))
    if q > 0:
        lj = j[:, :1] - np.arange(q, 0, -1)[None, :]
        rj = j[:, -1:] + np.arange(1, q + 1)[None, :]
        has = (lj[:, 0] >= 0) & (rj[:, -1] < s.size)
        with np.errstate(all="ignore"):
            lv = np.median(s[np.clip(lj, 0, s.size - 1)], axis=1)
            rv = np.median(s[np.clip(rj, 0, s.size - 1)], axis=1)
        # local levels only where they show the same step (a spike or the next edge does not)
        has &= np.isfinite(lv) & np.isfinite(rv) & (np.abs((rv - lv) * sign / step - 1.0) < 0.5)
        v_left, v_right = np.where(has, lv, v_left), np.where(has, rv, v_right)
    low = (v_right[:, None] - v) / (v_right - v_left)[:, None]
    ok = inside & np.isfinite(v).all(axis=1)
    area = xs[jj[:, 0]] - 0.5 * dx + dx * low.sum(axis=1)
    # the area of a pixel beyond the plateaus (noise, a spike) must not move the edge out of its pixel
    ok &= np.abs(area - x) <= abs(dx)
    out: F64 = np.where(ok, area, x)
    return out


class _Spacing:
    """A length that varies smoothly along the line (the local line width): a robust cubic in the
    commanded position.

    Every line of an image scans the same way (one nonlinearity), so all lines share it. An
    uncorrected scan stretches lengths near its turning points by up to ~2x, smoothly; a particle
    is not smooth: the fit of ``log(length)`` drops values beyond a factor 1.35 of it and refits.
    """

    def __init__(self, gaps: F64, mids: F64, lo_um: float, hi_um: float) -> None:
        self.centre = 0.5 * (lo_um + hi_um)
        self.half = max(0.5 * (hi_um - lo_um), 1e-9)
        u = (mids - self.centre) / self.half
        y = np.log(gaps)
        deg = int(min(3, max(0, np.unique(np.round(u, 2)).size - 2)))
        self.coef = np.array([float(np.median(y))])
        keep = np.abs(y - self.coef[0]) < math.log(1.9)
        for _ in range(4):
            if keep.sum() <= deg + 2:
                break
            self.coef = np.polyfit(u[keep], y[keep], deg)
            new = np.abs(y - np.polyval(self.coef, u)) < math.log(1.35)
            if np.array_equal(new, keep):
                break
            keep = new

    def __call__(self, x_um: F64) -> F64:
        u = np.clip((x_um - self.centre) / self.half, -1.0, 1.0)
        out: F64 = np.exp(np.polyval(self.coef, u))
        return out


def _number(x: F64, width_at: _Spacing, ratio: float) -> NDArray[np.int64]:
    """Period numbers of successive flanks: each gap in units of the local period
    (``ratio`` times the local line width)."""
    if x.size == 0:
        return np.zeros(0, dtype=np.int64)
    g = np.abs(np.diff(x))
    if g.size == 0:
        return np.zeros(1, dtype=np.int64)
    steps = np.maximum(np.rint(g / (ratio * width_at(0.5 * (x[1:] + x[:-1])))), 1).astype(np.int64)
    return np.concatenate(([0], np.cumsum(steps))).astype(np.int64)


def find_flanks(image: F64, geo: Geometry) -> Flanks:
    """The flanks of a line pattern in every line of ``image`` (see the module docstring)."""
    empty = Flanks(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int64))
    xs = geo.pixel_centres_um()
    lo_um, hi_um = float(xs[0]), float(xs[-1])
    pairs: list[tuple[int, F64, F64]] = []
    # profiles that miss the pattern (between the posts of a 2D grating) are flat: no flanks
    steps = np.array([_step(image[r]) for r in range(image.shape[0])])
    levelled = level(image)
    finite = levelled[np.isfinite(levelled)]
    spread = float(np.ptp(np.percentile(finite, [5, 95]))) if finite.size else 0.0
    floor = 0.3 * max(float(np.percentile(steps, 90)) if steps.size else 0.0, spread)
    for r in range(image.shape[0]):
        if not steps[r] > floor:
            continue
        up, dn = _crossings(image[r], xs)
        if up.size == 0 or dn.size == 0:
            continue
        j = np.searchsorted(dn, up)
        ok = j < dn.size
        pairs.append((r, up[ok], dn[j[ok]]))
    if not pairs:
        return empty
    widths = np.concatenate([dn - up for _, up, dn in pairs])
    centres = np.concatenate([0.5 * (up + dn) for _, up, dn in pairs])
    if widths.size < 2 or not np.all(widths > 0):
        return empty
    # the local line width: smooth along the line; a missing line does not change it
    width_at = _Spacing(widths, centres, lo_um, hi_um)
    kept: list[tuple[int, F64, F64]] = []
    period_per_width: list[F64] = []
    for r, up, dn in pairs:
        # particles and defects make bumps narrower or wider than the lines
        good = np.abs((dn - up) / width_at(0.5 * (up + dn)) - 1.0) <= _WIDTH_TOLERANCE
        # a falling flank paired twice (a rising flank missed) is one flank
        dn_k, first = np.unique(dn[good], return_index=True)
        up_k = up[good][first]
        kept.append((r, up_k, dn_k))
        for fam in (up_k, dn_k):
            if fam.size > 1:
                period_per_width.append(np.diff(fam) / width_at(0.5 * (fam[1:] + fam[:-1])))
    if not period_per_width:
        return empty
    # most gaps are one period (a missing line is one gap in a line): the period in line widths
    ratio = float(np.median(np.concatenate(period_per_width)))
    xi: list[F64] = []
    ks: list[NDArray[np.int64]] = []
    fams: list[NDArray[np.int8]] = []
    lines: list[NDArray[np.int64]] = []
    for r, up_k, dn_k in kept:
        for f, fam in ((1, up_k), (-1, dn_k)):
            if fam.size < 2:
                continue
            xi.append(fam)
            ks.append(_number(fam, width_at, ratio))
            fams.append(np.full(fam.size, f, dtype=np.int8))
            lines.append(np.full(fam.size, r, dtype=np.int64))
    if not xi:
        return empty
    return Flanks(np.concatenate(xi), np.concatenate(ks), np.concatenate(fams), np.concatenate(lines))


def _regress(x: F64, xi: F64, group: NDArray[np.int64]) -> tuple[float, F64, int]:
    ids, inv = np.unique(group, return_inverse=True)
    cnt = np.bincount(inv).astype(np.float64)
    xc = x - (np.bincount(inv, x) / cnt)[inv]
    xic = xi - (np.bincount(inv, xi) / cnt)[inv]
    sxx = float(xic @ xic)
    g = float(xic @ xc) / sxx if sxx > 0 else math.nan
    return g, xc - g * xic, int(ids.size)


@dataclass(frozen=True, slots=True)
class PositionMap:
    """The true position as a function of the commanded one along the lines of an image, from its flanks.

    ``x(xi) = c_group + sum_j a_j L_j(u)``, ``u = (xi - centre) / half`` (Legendre polynomials
    ``L_1 .. L_degree``), one intercept per (line, family), the shape shared by all lines (every
    line scans alike; what differs between lines - drift, the sample's position - is the
    intercepts').

    Attributes
    ----------
    centre, half
        Scaling of ``u`` (um).
    coef
        ``a_1 .. a_degree`` (um).
    cov
        Their covariance from the flanks' scatter about the fit (um^2).
    noise_um
        The flanks' scatter about the fit (edge roughness and detection; um rms).
    window
        ``(lo, hi)``: the commanded span the metric covers (um): from the lines' first flank to
        their last (medians over the lines).
    used, dropped
        Flanks fitted and flanks dropped as outliers of the fit.
    """

    centre: float
    half: float
    coef: F64
    cov: F64
    noise_um: float
    window: tuple[float, float]
    used: int
    dropped: int

    def basis(self, xi_um: F64) -> F64:
        """``L_1 .. L_degree`` at ``xi_um``, shape ``(n, degree)``."""
        from numpy.polynomial import legendre

        u = (np.asarray(xi_um, dtype=np.float64) - self.centre) / self.half
        out: F64 = np.asarray(legendre.legvander(u, self.coef.size)[:, 1:], dtype=np.float64)
        return out

    def __call__(self, xi_um: F64) -> F64:
        """The map (um, up to a constant)."""
        out: F64 = self.basis(xi_um) @ self.coef
        return out


def _demean(a: F64, inv: NDArray[np.intp], cnt: F64) -> F64:
    if a.ndim == 1:
        out: F64 = a - (np.bincount(inv, a) / cnt)[inv]
        return out
    return np.column_stack([_demean(a[:, j], inv, cnt) for j in range(a.shape[1])])


def position_map(fl: Flanks, pitch_um: float, pixel_um: float) -> PositionMap:
    """Fit the :class:`PositionMap` to the flanks (``k P`` at their commanded positions).

    The degree follows the flanks per line (both families): ``min(6, n - 3)``, at least 2. One pass
    drops flanks beyond five robust standard deviations of the fit (never tighter than a fifth of
    a pixel: positions are found to a fraction of a pixel) and refits.

    Raises
    ------
    RecordingError
        Too few flanks for the fit.
    """
    group = fl.line * 2 + (fl.family > 0)
    x = fl.k.astype(np.float64) * pitch_um
    per_line = float(np.median(np.bincount(np.unique(fl.line, return_inverse=True)[1])))
    degree = int(min(6, max(2, per_line - 3)))
    lo_all, hi_all = float(fl.xi_um.min()), float(fl.xi_um.max())
    centre, half = 0.5 * (lo_all + hi_all), max(0.5 * (hi_all - lo_all), 1e-9)
    firsts = [float(fl.xi_um[fl.line == r].min()) for r in np.unique(fl.line)]
    lasts = [float(fl.xi_um[fl.line == r].max()) for r in np.unique(fl.line)]
    window = (float(np.median(firsts)), float(np.median(lasts)))
    keep = np.ones(x.size, dtype=bool)
    for attempt in range(2):
        ids, inv = np.unique(group[keep], return_inverse=True)
        cnt = np.bincount(inv).astype(np.float64)
        probe = PositionMap(centre, half, np.zeros(degree), np.zeros((degree, degree)), 0.0, window, 0, 0)
        a = _demean(probe.basis(fl.xi_um[keep]), inv, cnt)
        b = _demean(x[keep], inv, cnt)
        dof = int(keep.sum()) - ids.size - degree
        if dof < 2:
            raise RecordingError(
                f"too few flanks ({int(keep.sum())}) for the position map of degree {degree}"
            )
        coef, *_ = np.linalg.lstsq(a, b, rcond=None)
        resid = b - a @ coef
        if attempt == 1:
            break
        mad = max(float(np.median(np.abs(resid - np.median(resid)))) * 1.4826, 0.2 * pixel_um)
        bad = np.abs(resid - np.median(resid)) > _OUTLIER_SIGMAS * mad
        if not bad.any() or keep.sum() - bad.sum() < ids.size + degree + 3:
            break
        keep[np.flatnonzero(keep)[bad]] = False
    noise2 = float(resid @ resid) / dof
    cov = np.asarray(noise2 * np.linalg.pinv(a.T @ a), dtype=np.float64)
    return PositionMap(
        centre=centre,
        half=half,
        coef=np.asarray(coef, dtype=np.float64),
        cov=cov,
        noise_um=math.sqrt(noise2),
        window=window,
        used=int(keep.sum()),
        dropped=int(x.size - keep.sum()),
    )


def image_linearity(image: F64, geo: Geometry, pitch_um: float, direction: int) -> ImageLinearity:
    """(4.14)-(4.16) of one image of a line pattern of pitch ``pitch_um`` (see the module docstring).

    Raises
    ------
    RecordingError
        Fewer than three usable flanks per family in the image (no line pattern, wrong pitch).
    """
    if not (math.isfinite(pitch_um) and pitch_um > 0):
        raise RecordingError(f"--pitch-um must be > 0, got {pitch_um}")
    fl = find_flanks(image, geo)
    name = "trace" if direction > 0 else "retrace"
    if fl.xi_um.size < 6:
        raise RecordingError(
            f"{name} image: found {fl.xi_um.size} flanks of a line pattern; need a reference with at least "
            f"three periods per line (pitch {pitch_um:g} um, range {geo.range_um:g} um)"
        )
    group = fl.line * 2 + (fl.family > 0)
    per_group = float(np.median(np.bincount(np.unique(group, return_inverse=True)[1])))
    if per_group < 4:
        raise RecordingError(
            f"{name} image: {per_group:g} flanks per line and family; the linearity needs at least four "
            f"(a range of several periods of the {pitch_um:g} um reference)"
        )
    # the straight line through the flanks themselves (weighted by true position), for comparison
    x = fl.k.astype(np.float64) * pitch_um
    g, r, _ = _regress(x, fl.xi_um, group)
    mad = max(float(np.median(np.abs(r - np.median(r)))) * 1.4826, 0.2 * geo.pixel_um)
    keep = np.abs(r - np.median(r)) <= _OUTLIER_SIGMAS * mad
    if keep.sum() >= 6 and not keep.all():
        g, r, _ = _regress(x[keep], fl.xi_um[keep], group[keep])
    if not 0.5 < g < 2.0:
        raise RecordingError(
            f"{name} image: the flanks do not follow a line pattern of pitch {pitch_um:g} um "
            f"(slope {g:.3g}): "
            "a wrong --pitch-um, or not a pattern of lines across this axis"
        )
    try:
        pm = position_map(fl, pitch_um, geo.pixel_um)
    except RecordingError as exc:
        raise RecordingError(f"{name} image: {exc.reason}") from None
    lo, hi = pm.window
    if not hi - lo > 2.0 * pitch_um:
        raise RecordingError(f"{name} image: the flanks span {hi - lo:.3g} um of the lines: too little")
    spans = seen_spans(fl.xi_um, pitch_um, lo, hi)
    # the map uniformly in commanded position, as the samples of a linear scan
    step = 0.25 * geo.pixel_um
    q = np.concatenate([np.linspace(a, b, max(2, math.ceil((b - a) / step) + 1)) for a, b in spans])
    br = branch_linearity(direction, pm(q), q, np.zeros(q.size, dtype=np.int64), geo.range_um)
    # the slope of that straight line is a linear function of the map's coefficients
    w = (q - q.mean()) / float((q - q.mean()) @ (q - q.mean()))
    lin = w @ pm.basis(q)
    slope_sd = math.sqrt(max(float(lin @ pm.cov @ lin), 0.0))
    lines = np.unique(fl.line)
    return ImageLinearity(
        direction=direction,
        pitch_um=pitch_um,
        flanks=pm.used,
        dropped=pm.dropped,
        lines=int(lines.size),
        slope=br.slope,
        nominal_range_um=geo.range_um,
        measured_range_um=br.measured_range_um,
        sigma_um=br.sigma_um,
        nonlinearity_pct=br.nonlinearity_pct,
        length_error_pct=br.length_error_pct,
        length_error_unc_pct=100.0 * slope_sd,
        flank_length_error_pct=100.0 * (g - 1.0),
        windows=tuple((int(r_), a, b) for r_ in lines for a, b in spans),
        flank_scatter_um=pm.noise_um,
    )


def seen_spans(xi_um: F64, pitch_um: float, lo: float, hi: float) -> list[tuple[float, float]]:
    """The commanded stretches of ``[lo, hi]`` within half a period of a flank (of any line).

    Between the flanks the map is interpolated; where the pattern shows none for longer (a missing
    line: no flank over two periods of one family, one and a half of both) the image does not see
    the position, and neither metric counts it.
    """
    x = np.unique(xi_um[(xi_um >= lo - pitch_um) & (xi_um <= hi + pitch_um)])
    spans: list[tuple[float, float]] = []
    for a, b in zip(np.maximum(x - 0.5 * pitch_um, lo), np.minimum(x + 0.5 * pitch_um, hi), strict=True):
        if b <= a:
            continue
        if spans and a <= spans[-1][1]:
            spans[-1] = (spans[-1][0], max(spans[-1][1], float(b)))
        else:
            spans.append((float(a), float(b)))
    return spans


def window_linearity(
    t_s: F64,
    target_um: F64,
    position_um: F64,
    line: NDArray[np.int64],
    direction: NDArray[np.int8],
    lin: ImageLinearity,
) -> BranchLinearity:
    """The sensor path's (4.14)-(4.16) of the same branch over the image metric's windows.

    The samples of ``lin.direction`` in every image line the image metric covers, whose commanded
    position lies inside that line's window, regressed by :func:`piezod.linearity.branch_linearity`
    - the image metric's own regression, on the same commanded span, weighted alike (uniform in
    time). ``position_um`` is the sensor (or, on the simulator, the hidden true position).

    Raises
    ------
    RecordingError
        No samples in the windows (the recording is not the image's).
    """
    sel = np.zeros(t_s.size, dtype=bool)
    for r, lo, hi in lin.windows:
        sel |= (line == r) & (direction == lin.direction) & (target_um >= lo) & (target_um <= hi)
    sel &= np.isfinite(position_um)
    name = "trace" if lin.direction > 0 else "retrace"
    if not sel.any():
        raise RecordingError(f"{name}: no position samples inside the image metric's windows")
    return branch_linearity(lin.direction, position_um[sel], target_um[sel], line[sel], lin.nominal_range_um)


def flank_sampled_linearity(
    t_s: F64,
    target_um: F64,
    position_um: F64,
    line: NDArray[np.int64],
    direction: NDArray[np.int8],
    lin: ImageLinearity,
    fl: Flanks,
) -> BranchLinearity:
    """The sensor path over the image metric's windows, of the position *as the flanks sample it*.

    The diagnosis of an image metric against a sensor (or, on the simulator, the hidden truth):
    in every image line the sensed position is taken at that line's flanks only (``fl``, as
    :func:`find_flanks` found them in the image of ``lin``) and interpolated linearly between them,
    then regressed exactly as :func:`window_linearity` regresses the sensed position itself. It is
    what a perfect flank metric - flank positions without error, the map through them - would
    read: its distance from :func:`window_linearity` is the part of the position's structure
    finer than the flank spacing, which no metric of this reference's flanks can see; its
    distance from ``lin`` is what the image metric itself adds (flank noise, the smooth map).

    Raises
    ------
    RecordingError
        No samples in the windows, or no line with two flanks in them.
    """
    xs: list[F64] = []
    ys: list[F64] = []
    ls: list[NDArray[np.int64]] = []
    for r, lo, hi in lin.windows:
        fx = np.unique(fl.xi_um[fl.line == r])
        s = (line == r) & (direction == lin.direction) & np.isfinite(position_um)
        if fx.size < 2 or s.sum() < 2:
            continue
        order = np.argsort(target_um[s], kind="stable")
        tx, px = target_um[s][order], position_um[s][order]
        at = np.interp(fx, tx, px)
        # inside the line's own flanks only: beyond them the interpolation would be a guess
        q = tx[(tx >= max(lo, fx[0])) & (tx <= min(hi, fx[-1]))]
        if q.size < 2:
            continue
        xs.append(q)
        ys.append(np.interp(q, fx, at))
        ls.append(np.full(q.size, r, dtype=np.int64))
    name = "trace" if lin.direction > 0 else "retrace"
    if not xs:
        raise RecordingError(f"{name}: no line with two flanks inside the image metric's windows")
    return branch_linearity(
        lin.direction, np.concatenate(ys), np.concatenate(xs), np.concatenate(ls), lin.nominal_range_um
    )


def slow_geometry(geo: Geometry, lines: int, row_slow_um: F64 | None = None) -> Geometry:
    """The geometry of the transposed image: the slow axis as the "fast" coordinate, one pixel per line.

    A line's slow coordinate at a given column is the commanded slow position when the tip passed
    it: a step per line plus a constant per column (the slow axis moves on during the line), which
    the regression's intercept per column absorbs. The step is that of ``row_slow_um`` (the
    commanded slow position of every line, e.g. its mean over the line) when given - a raster
    that spans the slow range in ``lines - 1`` steps differs from ``slow_range / lines`` by
    ``1 / lines`` - else ``slow_range / lines``.
    """
    span, centre = geo.slow_range_um, geo.offset_slow_um
    if row_slow_um is not None and row_slow_um.size == lines and lines > 2:
        step, first = np.polyfit(np.arange(lines, dtype=np.float64), row_slow_um, 1)
        span, centre = float(abs(step)) * lines, float(first + step * (lines - 1) / 2)
    return Geometry(
        range_um=span,
        offset_um=centre,
        slow_range_um=geo.range_um,
        offset_slow_um=geo.offset_um,
        pixels=lines,
        rotation_deg=geo.rotation_deg,
        line_rate_hz=geo.line_rate_hz,
    )


def slow_image_linearity(
    image: F64, geo: Geometry, pitch_um: float, direction: int, row_slow_um: F64 | None = None
) -> ImageLinearity:
    """(4.14)-(4.16) of the slow axis from the columns of an image of a 2D grating of pitch ``pitch_um``.

    The columns of the image are analysed as lines (:func:`image_linearity` of the transposed
    image, :func:`slow_geometry` with the lines' commanded slow positions ``row_slow_um``); a 1D
    line pattern along the slow axis has no flanks there.

    Raises
    ------
    RecordingError
        No 2D pattern across the slow axis (too few flanks).
    """
    return image_linearity(
        np.ascontiguousarray(image.T), slow_geometry(geo, image.shape[0], row_slow_um), pitch_um, direction
    )


def sensor_slow_linearity(
    t_s: F64, target_um: F64, position_um: F64, start_s: float, stop_s: float
) -> tuple[float, float]:
    """(nonlinearity %, length error %) of the slow axis from its sensor, as the images see it.

    The slow-axis samples between ``start_s`` and ``stop_s`` (the image lines): the measured
    position regressed on the commanded one, (4.14)-(4.16) over the commanded span.
    """
    s = (t_s >= start_s) & (t_s <= stop_s) & np.isfinite(position_um)
    if s.sum() < 8:
        raise RecordingError("too few slow-axis sensor samples during the image")
    x, y = target_um[s], position_um[s]
    nominal = float(np.ptp(x))
    if not nominal > 0:
        raise RecordingError("the slow axis did not move during the image")
    g, c = np.polyfit(x, y, 1)
    resid = y - (g * x + c)
    measured = float(g) * nominal
    sigma = float(np.sqrt(float(resid @ resid) / max(1, resid.size - 2)))
    return 100.0 * sigma / measured, 100.0 * (measured - nominal) / nominal


def pitch_error(image: F64, geo: Geometry, pitch_um: float) -> tuple[F64, F64]:
    """Local pitch error along the line: (midpoint xi (um), ``P / dxi - 1`` in %) per flank pair."""
    fl = find_flanks(image, geo)
    mids: list[F64] = []
    errs: list[F64] = []
    group = fl.line * 2 + (fl.family > 0)
    for gid in np.unique(group):
        s = group == gid
        xi, k = fl.xi_um[s], fl.k[s]
        dk = np.diff(k)
        ok = dk > 0
        dxi = np.diff(xi)[ok] / dk[ok]
        mids.append(0.5 * (xi[:-1] + xi[1:])[ok])
        errs.append(100.0 * (pitch_um / dxi - 1.0))
    if not mids:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(mids), np.concatenate(errs)


def plot_pitch_error(
    curves: list[tuple[str, F64, F64, F64, F64]], pitch_um: float, path: Path, title: str
) -> Path:
    """The local pitch error along the line, trace and retrace, one panel per image.

    ``curves``: (label, trace xi, trace error %, retrace xi, retrace error %).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(curves), 1, figsize=(8, 2.6 * len(curves) + 0.6), squeeze=False)
    for ax, (label, xt, et, xr, er) in zip(axes[:, 0], curves, strict=True):
        ax.plot(xt, et, ".", ms=3, label="trace")
        ax.plot(xr, er, ".", ms=3, label="retrace")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel("pitch error (%)")
        ax.set_title(label, fontsize=9)
        ax.legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("commanded fast-axis position (um)")
    fig.suptitle(
        f"{title}\nlocal pitch error P/dx - 1 along the line (P = {pitch_um:g} um; > 0: moves too far)"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


__all__ = [
    "Flanks",
    "ImageLinearity",
    "PositionMap",
    "find_flanks",
    "flank_sampled_linearity",
    "image_linearity",
    "pitch_error",
    "plot_pitch_error",
    "position_map",
    "seen_spans",
    "sensor_slow_linearity",
    "slow_geometry",
    "slow_image_linearity",
    "window_linearity",
]
