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
   intercept per (line, family) - the unknown position of the sample - and one common slope ``g``
   (as :mod:`piezod.linearity` regresses the sensor position on the target). One pass drops flanks
   whose residual exceeds five robust standard deviations (dust the width test missed).
5. (4.14) ``x'_R = g R``, (4.15) ``e_l = (x'_R - R) / R``, (4.16) ``e_rel = sigma / x'_R``, ``sigma``
   the residual standard deviation (``n - groups - 1`` degrees of freedom).

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
        (4.16) and (4.15) in %.
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
    for _ in range(2):
        upper = (s > 0).astype(np.float64)
        far = ok & (np.abs(s) > 0.25 * (hi - lo))
        if far.sum() < 4 or upper[far].min() == upper[far].max():
            break
        a = np.column_stack((np.ones(int(far.sum())), xs[far], upper[far]))
        c0, c1, c2 = np.linalg.lstsq(a, p[far], rcond=None)[0]
        s = p - (c0 + c1 * xs + 0.5 * c2)
        if c2 < 0:
            s = -s
    return _schmitt(s, xs, _HYSTERESIS * (hi - lo))


def _schmitt(s: F64, xs: F64, band: float) -> tuple[F64, F64]:
    """Zero crossings of ``s`` that complete a transition from below ``-band`` to above ``+band``
    (rising) or back (falling), at the last zero crossing before the far level is reached.

    A spike in a plateau (the z loop's overshoot where the z piezo reverses, a speck of dust) that
    does not reach the other level makes no flank; a noisy edge makes one, not several.
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
    return x[rising], x[~rising]


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


def image_linearity(image: F64, geo: Geometry, pitch_um: float, direction: int) -> ImageLinearity:
    """(4.14)-(4.16) of one image of a line pattern of pitch ``pitch_um``.

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
    x = fl.k.astype(np.float64) * pitch_um
    g, r, ng = _regress(x, fl.xi_um, group)
    keep = np.ones(x.size, dtype=bool)
    # flank positions are quantised to a fraction of a pixel: no tighter outlier band than that
    mad = max(float(np.median(np.abs(r - np.median(r)))) * 1.4826, 0.2 * geo.pixel_um)
    if mad > 0:
        keep = np.abs(r - np.median(r)) <= _OUTLIER_SIGMAS * mad
        if keep.sum() >= 6 and not keep.all():
            g, r, ng = _regress(x[keep], fl.xi_um[keep], group[keep])
    n = int(keep.sum())
    dof = n - ng - 1
    if dof < 1:
        raise RecordingError(f"{name} image: too few flanks ({n}) for the linearity regression")
    sigma = math.sqrt(float(r @ r) / dof)
    measured = g * geo.range_um
    if not 0.5 < g < 2.0:
        raise RecordingError(
            f"{name} image: the flanks do not follow a line pattern of pitch {pitch_um:g} um "
            f"(slope {g:.3g}): "
            "a wrong --pitch-um, or not a pattern of lines across this axis"
        )
    return ImageLinearity(
        direction=direction,
        pitch_um=pitch_um,
        flanks=n,
        dropped=int(x.size - n),
        lines=int(np.unique(fl.line).size),
        slope=g,
        nominal_range_um=geo.range_um,
        measured_range_um=measured,
        sigma_um=sigma,
        nonlinearity_pct=100.0 * sigma / measured,
        length_error_pct=100.0 * (measured - geo.range_um) / geo.range_um,
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
    "find_flanks",
    "image_linearity",
    "pitch_error",
    "plot_pitch_error",
    "sensor_slow_linearity",
    "slow_geometry",
    "slow_image_linearity",
]
