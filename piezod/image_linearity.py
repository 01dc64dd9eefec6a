"""Linearity from images of a reference of known pitch: the thesis's (4.14)-(4.16) without a sensor.

The thesis calibrated its tube scanners from SPM images of length standards (1D3000, 2D200,
chapter 2 and section 4.4): the flanks of the lines are found in every image line, identified with
their known positions ``k P`` on the sample, and regressed on their pixel position. Here, per image
(trace or retrace, on the commanded grid):

1. Every line (row) is levelled by a least-squares line; the threshold is halfway between its 10th
   and 90th percentiles; the flanks are the threshold crossings, interpolated linearly between
   pixel centres (sub-pixel). Rising and falling flanks are two families.
2. Flank pairs (a rising flank and the next falling one) whose width differs from the median width
   of their neighbours (two pairs either side) by more than 35 % are dropped: particles and defects
   make narrow bumps, not lines.
3. Within a line and family, successive flanks are numbered by their spacing in units of the
   shorter neighbouring spacing (a missing line is a gap of two).
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
from piezod.image import F64, Geometry

_WIDTH_TOLERANCE = 0.35
_OUTLIER_SIGMAS = 5.0


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


def _crossings(profile: F64, xs: F64) -> tuple[F64, F64]:
    """Rising and falling crossings of the mid level of a levelled profile (sub-pixel)."""
    ok = np.isfinite(profile)
    if ok.sum() < 8:
        return np.zeros(0), np.zeros(0)
    p = profile.copy()
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
    a, b = s[:-1], s[1:]
    valid = np.isfinite(a) & np.isfinite(b)
    up = np.flatnonzero(valid & (a < 0) & (b >= 0))
    dn = np.flatnonzero(valid & (a >= 0) & (b < 0))

    def interp(i: NDArray[np.intp]) -> F64:
        f = a[i] / (a[i] - b[i])
        out: F64 = xs[i] + f * (xs[i + 1] - xs[i])
        return out

    return interp(up), interp(dn)


def _number(x: F64, spacing: float) -> NDArray[np.int64]:
    """Period numbers of successive flanks: each gap in units of its shorter neighbouring gap.

    Against the neighbours rather than the median spacing: an uncorrected scan stretches the
    periods near its turning points by up to ~2x, as much as a missing line does; neighbouring
    gaps stretch alike, a missing line doubles one gap.
    """
    if x.size == 0:
        return np.zeros(0, dtype=np.int64)
    g = np.abs(np.diff(x))
    if g.size == 0:
        return np.zeros(1, dtype=np.int64)
    left = np.concatenate(([np.inf], g[:-1]))
    right = np.concatenate((g[1:], [np.inf]))
    ref = np.minimum(left, right)
    ref = np.where(np.isfinite(ref), ref, spacing)
    ref = np.clip(ref, 0.4 * spacing, 2.5 * spacing)
    steps = np.maximum(np.rint(g / ref), 1).astype(np.int64)
    return np.concatenate(([0], np.cumsum(steps))).astype(np.int64)


def find_flanks(image: F64, geo: Geometry) -> Flanks:
    """The flanks of a line pattern in every line of ``image`` (see the module docstring)."""
    xs = geo.pixel_centres_um()
    per_line: list[tuple[int, F64, F64]] = []
    widths: list[F64] = []
    spacings: list[F64] = []
    for r in range(image.shape[0]):
        up, dn = _crossings(image[r], xs)
        per_line.append((r, up, dn))
        if up.size and dn.size:
            j = np.searchsorted(dn, up)
            ok = j < dn.size
            widths.append(dn[j[ok]] - up[ok])
        for fam in (up, dn):
            if fam.size > 1:
                spacings.append(np.diff(fam))
    if not widths or not spacings:
        return Flanks(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int64))
    w_med = float(np.median(np.concatenate(widths)))
    xi: list[F64] = []
    ks: list[NDArray[np.int64]] = []
    fams: list[NDArray[np.int8]] = []
    lines: list[NDArray[np.int64]] = []
    good_spacings: list[F64] = []
    kept: list[tuple[int, F64, F64]] = []
    for r, up, dn in per_line:
        if up.size == 0 or dn.size == 0:
            continue
        j = np.searchsorted(dn, up)
        ok = j < dn.size
        width = np.full(up.size, np.nan)
        width[ok] = dn[j[ok]] - up[ok]
        # against the neighbours' widths: an uncorrected scan stretches lines near the turning points
        local = np.array(
            [
                np.nanmedian(width[max(0, i - 2) : i + 3])
                if np.isfinite(width[max(0, i - 2) : i + 3]).any()
                else w_med
                for i in range(width.size)
            ]
        )
        ref = np.where(np.abs(local - w_med) <= 0.6 * w_med, local, w_med)
        good = np.abs(width - ref) <= _WIDTH_TOLERANCE * ref
        up_k = up[good]
        dn_k = dn[j[good]]
        kept.append((r, up_k, dn_k))
        for fam in (up_k, dn_k):
            if fam.size > 1:
                good_spacings.append(np.diff(fam))
    if not good_spacings:
        return Flanks(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int64))
    spacing = float(np.median(np.concatenate(good_spacings)))
    for r, up_k, dn_k in kept:
        for f, fam in ((1, up_k), (-1, dn_k)):
            if fam.size < 2:
                continue
            xi.append(fam)
            ks.append(_number(fam, spacing))
            fams.append(np.full(fam.size, f, dtype=np.int8))
            lines.append(np.full(fam.size, r, dtype=np.int64))
    if not xi:
        return Flanks(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int64))
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
    mad = float(np.median(np.abs(r - np.median(r)))) * 1.4826
    if mad > 0:
        keep = np.abs(r) <= _OUTLIER_SIGMAS * max(mad, 1e-6)
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
            "a wrong --pitch-um, or not a 1D line pattern across the fast axis"
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


__all__ = ["Flanks", "ImageLinearity", "find_flanks", "image_linearity", "pitch_error", "plot_pitch_error"]
