"""Linearity of recorded scans: the thesis's metrics (4.14)-(4.16).

For every experiment and each branch (trace and retrace separately) the measured
position is regressed on a nominal coordinate ``xi`` with one intercept per line
(so drift between lines is not counted as non-linearity) and one common slope
``g = dx / dxi``:

* with a ``target`` column, ``xi`` is the commanded target (um);
* without, ``xi`` is the pixel coordinate: the nominal range ``R`` spread uniformly
  in time over each line (``R * (t - t_start) / (t_end - t_start)`` on the trace,
  reversed on the retrace), lines being the half periods between the turning
  points of the voltage.

Then (4.14) ``x'_R = g * R``, (4.15) ``e_l = (x'_R - R) / R`` and (4.16) ``e_rel = sigma
/ x'_R`` with ``sigma`` the residual standard deviation (``n - lines - 1`` degrees of
freedom). Both are reported in %, per branch and as the worse of the two.

The nominal range ``R`` is ``range_um`` when given, else the recording's ``range_um``
metadata, else (with a target) the commanded span without overscan. Only complete
lines (between two turning points) are used. An overscan margin at the turning
points is excluded only when the recording declares it: metadata ``overscan`` =
extra travel at each turning point as a fraction of the range (as
:class:`piezod.scan.RasterParams`), i.e. samples whose target lies outside the
central ``1 / (1 + 2 overscan)`` of the line's span (with a target), or the first and
last ``overscan / (1 + 2 overscan)`` of each line's duration (without).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.errors import RecordingError
from piezod.recording import Experiment
from piezod.scan_inference import ScanInfo, infer_scan

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class BranchLinearity:
    """Metrics of one branch (trace or retrace) of an experiment.

    Attributes
    ----------
    direction
        +1 trace, -1 retrace.
    n, lines
        Samples and lines used.
    slope
        Measured um per nominal um (``g``).
    nominal_range_um, measured_range_um
        ``R`` and ``x'_R = g R`` (4.14).
    sigma_um
        Residual standard deviation of the regression.
    nonlinearity_pct
        ``100 sigma / x'_R`` (4.16).
    length_error_pct
        ``100 (x'_R - R) / R`` (4.15).
    pixels
        Pixels per line of the pixel figures (0: not computed).
    pixel_nonlinearity_pct
        (4.16) of the line-averaged profile at the image's pixels (:func:`pixel_profile`): the
        regression's residual averaged over the samples of each pixel and over the lines, its RMS
        over the pixels, per ``x'_R``; nan when not computed.
    pixel_noise_pct
        What noise alone leaves in that figure (:func:`pixel_profile`), per ``x'_R``; nan when it
        cannot be estimated.
    """

    direction: int
    n: int
    lines: int
    slope: float
    nominal_range_um: float
    measured_range_um: float
    sigma_um: float
    nonlinearity_pct: float
    length_error_pct: float
    pixels: int = 0
    pixel_nonlinearity_pct: float = math.nan
    pixel_noise_pct: float = math.nan

    def to_json(self) -> dict[str, Any]:
        """Plain dict for JSON output."""
        return {
            "n": self.n,
            "lines": self.lines,
            "slope": self.slope,
            "nominal_range_um": self.nominal_range_um,
            "measured_range_um": self.measured_range_um,
            "sigma_um": self.sigma_um,
            "nonlinearity_pct": self.nonlinearity_pct,
            "length_error_pct": self.length_error_pct,
            "pixels": self.pixels,
            "pixel_nonlinearity_pct": self.pixel_nonlinearity_pct,
            "pixel_noise_pct": self.pixel_noise_pct,
        }


@dataclass(frozen=True, slots=True)
class ExperimentLinearity:
    """Linearity of one experiment.

    Attributes
    ----------
    label, axis, path
        Identification.
    reference
        ``"target"`` or ``"pixel"`` (what the position was regressed on).
    frequency_hz
        Line frequency (from the target, else the voltage, waveform).
    v_min, v_max
        Voltage turning values.
    range_um
        Nominal range ``R``.
    overscan
        Overscan fraction excluded (0 when none is declared).
    trace, retrace
        Per-branch metrics.
    """

    label: str
    axis: str | None
    path: str | None
    reference: str
    frequency_hz: float
    v_min: float
    v_max: float
    range_um: float
    overscan: float
    trace: BranchLinearity
    retrace: BranchLinearity

    @property
    def offset_v(self) -> float:
        """Centre of the voltage range."""
        return 0.5 * (self.v_min + self.v_max)

    @property
    def nonlinearity_pct(self) -> float:
        """The worse branch's non-linearity."""
        return max(self.trace.nonlinearity_pct, self.retrace.nonlinearity_pct)

    @property
    def length_error_pct(self) -> float:
        """The length error of larger magnitude (signed)."""
        return max(self.trace.length_error_pct, self.retrace.length_error_pct, key=abs)

    @property
    def pixel_nonlinearity_pct(self) -> float:
        """The worse branch's line-averaged nonlinearity at the image's pixels (nan if not computed)."""
        return _worse(self.trace.pixel_nonlinearity_pct, self.retrace.pixel_nonlinearity_pct)

    @property
    def pixel_noise_pct(self) -> float:
        """The larger of the branches' noise in that figure (nan if not estimated)."""
        return _worse(self.trace.pixel_noise_pct, self.retrace.pixel_noise_pct)

    @property
    def measured_range_um(self) -> float:
        """Mean of the branches' measured ranges."""
        return 0.5 * (self.trace.measured_range_um + self.retrace.measured_range_um)

    def to_json(self) -> dict[str, Any]:
        """The experiment's entry of ``piezod linearity --json``."""
        return {
            "label": self.label,
            "axis": self.axis,
            "path": self.path,
            "reference": self.reference,
            "range_um": self.range_um,
            "measured_range_um": self.measured_range_um,
            "frequency_hz": self.frequency_hz,
            "offset_v": self.offset_v,
            "v_min": self.v_min,
            "v_max": self.v_max,
            "overscan": self.overscan,
            "nonlinearity_pct": self.nonlinearity_pct,
            "length_error_pct": self.length_error_pct,
            "pixel_nonlinearity_pct": self.pixel_nonlinearity_pct,
            "pixel_noise_pct": self.pixel_noise_pct,
            "trace": self.trace.to_json(),
            "retrace": self.retrace.to_json(),
        }


def _worse(a: float, b: float) -> float:
    finite = [v for v in (a, b) if math.isfinite(v)]
    return max(finite) if finite else math.nan


def _metadata_float(exp: Experiment, key: str) -> float | None:
    text = exp.metadata.get(key)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise RecordingError(f"metadata {key!r}: not a number: {text!r}", exp.path) from None
    if not math.isfinite(value):
        raise RecordingError(f"metadata {key!r}: not finite: {text!r}", exp.path)
    return value


#: Pixels per line of the pixel figures when a recording does not say (the scan request's default).
DEFAULT_PIXELS = 256


def experiment_linearity(
    exp: Experiment,
    *,
    range_um: float | None = None,
    overscan: float | None = None,
    pixels: int | None = None,
) -> ExperimentLinearity:
    """Metrics (4.14)-(4.16) of one experiment (see the module docstring).

    Parameters
    ----------
    exp
        The experiment: a periodic back-and-forth scan with at least one complete
        trace and retrace.
    range_um
        Nominal scan range (um); overrides the recording's metadata.
    overscan
        Overscan fraction; overrides the recording's ``overscan`` metadata.
    pixels
        Pixels per line of the pixel figures; overrides the recording's ``pixels`` metadata
        (default :data:`DEFAULT_PIXELS`).

    Raises
    ------
    RecordingError
        Not a periodic scan, no nominal range, or too few samples.
    """
    where = (exp.path, exp.first_line)
    vinfo = exp.scan()
    info: ScanInfo = vinfo if exp.target_um is None else infer_scan(exp.t_s, exp.target_um)
    src = "voltage" if exp.target_um is None else "target"
    if not info.is_periodic:
        raise NotAScanError(
            f"experiment {exp.describe()}: the {src} is not a periodic back-and-forth scan with a "
            f"complete trace and retrace ({info.kind}: {info.reason})",
            *where,
        )
    if info.kind != "triangle":
        # (4.14)-(4.16) compare the position with a straight line in time: only a linear scan
        # (a triangle of the target, or of the voltage when there is no target) has one.
        raise NotAScanError(
            f"experiment {exp.describe()}: the {src} is a {info.kind}, not a linear (triangular) scan; "
            "linearity compares the position with a straight line in time"
            + (" (record the target positions of a corrected scan)" if exp.target_um is None else ""),
            *where,
        )
    o = overscan if overscan is not None else (_metadata_float(exp, "overscan") or 0.0)
    if not 0.0 <= o < 0.5:
        raise RecordingError(f"overscan must be in [0, 0.5), got {o}", *where)
    nominal = range_um if range_um is not None else _metadata_float(exp, "range_um")
    if nominal is not None and not nominal > 0:
        raise RecordingError(f"nominal range must be > 0 um, got {nominal}", *where)

    # Every line runs from one turning sample to the next, both included (the turning samples
    # are the first and the last pixel of the two lines that meet there).
    rows, line, direction, phi, first = _lines(exp.t_s, info)
    x = exp.position_um[rows]
    m = o / (1.0 + 2.0 * o)
    if exp.target_um is not None:
        xi = exp.target_um[rows]
        tmax = np.maximum.reduceat(xi, first)
        tmin = np.minimum.reduceat(xi, first)
        if info.wraps:
            # The end and start pieces share a half period: its turning values are the record's.
            tmax[-2:], tmin[-2:] = float(xi.max()), float(xi.min())
        centre = 0.5 * (tmax + tmin)
        half = 0.5 * (tmax - tmin) / (1.0 + 2.0 * o)
        keep = np.abs(xi - centre[line]) <= half[line] * (1.0 + 1e-9)
        span = float(np.median((tmax - tmin)[: first.size - 2 if info.wraps else None])) / (1.0 + 2.0 * o)
        reference = "target"
        if nominal is None:
            nominal = span
        scale_to_nominal = nominal / span if span > 0 else math.nan
    else:
        if nominal is None:
            raise RecordingError(
                f"experiment {exp.describe()}: no nominal scan range: pass --range-um or record a "
                "'target' column or '# range_um:' metadata",
                *where,
            )
        keep = (phi >= m - 1e-12) & (phi <= 1.0 - m + 1e-12)
        frac = np.clip((phi - m) / (1.0 - 2.0 * m), 0.0, 1.0)
        xi = nominal * np.where(direction > 0, frac, 1.0 - frac)
        reference = "pixel"
        scale_to_nominal = 1.0

    px = pixels if pixels is not None else _metadata_float(exp, "pixels")
    px = DEFAULT_PIXELS if px is None else int(px)
    if px < 1:
        raise RecordingError(f"pixels must be >= 1, got {px}", *where)
    branches = []
    for d in (1, -1):
        sel = keep & (direction == d)
        branches.append(_branch(d, x[sel], xi[sel], line[sel], float(nominal), scale_to_nominal, exp, px))
    return ExperimentLinearity(
        label=exp.label,
        axis=exp.axis,
        path=exp.path,
        reference=reference,
        frequency_hz=info.frequency_hz,
        v_min=vinfo.v_min,
        v_max=vinfo.v_max,
        range_um=float(nominal),
        overscan=o,
        trace=branches[0],
        retrace=branches[1],
    )


def _lines(
    t_s: F64, info: ScanInfo
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], F64, NDArray[np.int64]]:
    """Rows, line index, direction, phase in the line and first position of every line.

    A line runs from one turning sample to the next, both included. Of a one-period record
    (:attr:`ScanInfo.wraps`) the pieces before the first and after the last turning point are
    lines too (the half period they share, each with its own offset): their phase counts from
    where the half period starts, the record's end piece continuing into its start piece.
    """
    idx = info.turning_indices
    nl = idx.size - 1
    lengths = np.diff(idx) + 1
    line = np.repeat(np.arange(nl), lengths)
    first = np.concatenate(([0], np.cumsum(lengths)[:-1]))
    rows = idx[:-1][line] + (np.arange(line.size) - first[line])
    direction = (-info.turning_kinds[:-1])[line].astype(np.int64)
    t = t_s[rows]
    t0 = t_s[idx[:-1]]
    dur = t_s[idx[1:]] - t0
    phi = (t - t0[line]) / dur[line]
    if info.wraps:
        n = t_s.size
        a, b = int(idx[0]), int(idx[-1])
        d_edge = float(t_s[a] - t_s[0] + t_s[-1] - t_s[b])
        tail = np.arange(b, n)
        head = np.arange(0, a + 1)
        rows = np.concatenate((rows, tail, head))
        line = np.concatenate((line, np.full(tail.size, nl), np.full(head.size, nl + 1)))
        first = np.concatenate((first, [first[-1] + lengths[-1], first[-1] + lengths[-1] + tail.size]))
        d = int(-info.turning_kinds[-1])
        direction = np.concatenate((direction, np.full(tail.size + head.size, d, dtype=np.int64)))
        phi = np.concatenate(
            (phi, (t_s[tail] - t_s[b]) / d_edge, (t_s[head] - t_s[0] + t_s[-1] - t_s[b]) / d_edge)
        )
    return rows.astype(np.int64), line.astype(np.int64), direction, phi, first.astype(np.int64)


def _branch(
    d: int,
    x: F64,
    xi: F64,
    line: NDArray[np.intp],
    nominal: float,
    scale: float,
    exp: Experiment,
    pixels: int,
) -> BranchLinearity:
    try:
        return branch_linearity(d, x, xi, line, nominal, scale, pixels=pixels)
    except RecordingError as exc:
        raise RecordingError(f"experiment {exp.describe()}: {exc.reason}", exp.path, exp.first_line) from None


def branch_linearity(
    direction: int,
    x: F64,
    xi: F64,
    line: NDArray[np.integer[Any]],
    nominal: float,
    scale: float = 1.0,
    *,
    pixels: int = 0,
) -> BranchLinearity:
    """(4.14)-(4.16) of one branch: ``x`` regressed on ``xi`` with one intercept per ``line``.

    The one regression of the sensor path (:func:`experiment_linearity`) and of the image path
    (:func:`piezod.image_linearity.image_linearity`, on the position map it reconstructs from the
    flanks): both weigh the points as given - the samples of a linear scan, uniform in time.

    Parameters
    ----------
    direction
        +1 trace, -1 retrace.
    x
        Position (um).
    xi
        Nominal coordinate (um): the commanded position or the pixel coordinate.
    line
        Line of every point (one intercept each).
    nominal
        Nominal range ``R`` (um).
    scale
        ``R`` per commanded um (``x'_R = g R / scale``).
    pixels
        Pixels per line of the pixel figures (:func:`pixel_profile`); 0: not computed.

    Raises
    ------
    RecordingError
        Too few points for the regression.
    """
    ids, inv = np.unique(line, return_inverse=True)
    n_lines = ids.size
    n = x.size
    if n < n_lines + 3:
        name = "trace" if direction > 0 else "retrace"
        raise RecordingError(f"too few {name} samples ({n}) for the linearity regression")
    cnt = np.bincount(inv).astype(np.float64)
    xc = x - (np.bincount(inv, x) / cnt)[inv]
    xic = xi - (np.bincount(inv, xi) / cnt)[inv]
    sxx = float(xic @ xic)
    if not sxx > 0:
        raise RecordingError("the nominal coordinate does not vary within the lines")
    g = float(xic @ xc) / sxx
    r = xc - g * xic
    sigma = math.sqrt(float(r @ r) / (n - n_lines - 1))
    # g is measured um per target um; x'_R of (4.14) is g times the commanded span, compared with R.
    measured = g * nominal / scale
    px_sigma, px_noise = pixel_profile(r, xi, inv, pixels) if pixels > 0 else (math.nan, math.nan)
    return BranchLinearity(
        direction=direction,
        n=n,
        lines=n_lines,
        slope=g,
        nominal_range_um=nominal,
        measured_range_um=measured,
        sigma_um=sigma,
        nonlinearity_pct=100.0 * sigma / measured,
        length_error_pct=100.0 * (measured - nominal) / nominal,
        pixels=pixels,
        pixel_nonlinearity_pct=100.0 * px_sigma / measured,
        pixel_noise_pct=100.0 * px_noise / measured,
    )


def pixel_profile(
    residual_um: F64, xi: F64, line: NDArray[np.integer[Any]], pixels: int
) -> tuple[float, float]:
    """The regression's residual as the image sees it: averaged over the samples of each pixel and
    over the lines, and what noise alone leaves in that average.

    (4.16) is the residual's standard deviation over the samples, so the sensor's noise counts in
    full (3 nm on a 0.6 um line is 0.5 %). An image pixel averages the samples it holds, and a
    grating's profile is read on the average of its lines: the residual's mean per pixel and line,
    averaged over the lines, keeps what every line has in common (the scanner's nonlinearity) and
    divides the noise by the square root of the samples behind each pixel.

    Parameters
    ----------
    residual_um
        The regression's residual (one intercept per line removed), um.
    xi
        Nominal coordinate of every sample: pixel ``j`` of a line holds the samples whose ``xi``
        lies in the ``j``-th of ``pixels`` equal parts of that line's span.
    line
        Line of every sample.
    pixels
        Pixels per line (>= 1).

    Returns
    -------
    tuple of float
        ``(sigma, noise)`` in um: the RMS over the pixels of the line-averaged residual, and the
        RMS that noise alone gives it: the lines' scatter about their average as it enters the
        average (noise, and whatever else differs from line to line), or with one line the
        samples' scatter within each pixel (white noise). ``noise`` is nan when neither can be
        estimated; the figure's square is about the scanner's squared nonlinearity plus
        ``noise**2``.
    """
    if pixels < 1:
        raise ValueError(f"pixels must be >= 1, got {pixels}")
    r = np.asarray(residual_um, dtype=np.float64)
    q = np.asarray(xi, dtype=np.float64)
    ids, inv = np.unique(np.asarray(line), return_inverse=True)
    n_lines = ids.size
    lo = np.full(n_lines, np.inf)
    hi = np.full(n_lines, -np.inf)
    np.minimum.at(lo, inv, q)
    np.maximum.at(hi, inv, q)
    span = hi - lo
    ok = span[inv] > 0
    if not ok.any():
        return math.nan, math.nan
    u = (q[ok] - lo[inv[ok]]) / span[inv[ok]]
    cell = inv[ok] * pixels + np.minimum((u * pixels).astype(np.int64), pixels - 1)
    size = n_lines * pixels
    cnt = np.bincount(cell, minlength=size).reshape(n_lines, pixels).astype(np.float64)
    s1 = np.bincount(cell, r[ok], minlength=size).reshape(n_lines, pixels)
    s2 = np.bincount(cell, r[ok] * r[ok], minlength=size).reshape(n_lines, pixels)
    have = cnt > 0
    m_lp = np.where(have, s1 / np.where(have, cnt, 1.0), 0.0)
    per_pixel = have.sum(axis=0)
    seen = per_pixel > 0
    m_p = m_lp.sum(axis=0)[seen] / per_pixel[seen]
    sigma = math.sqrt(float(np.mean(m_p * m_p)))
    several = per_pixel >= 2
    if several.any():
        dev = np.where(have, m_lp - (m_lp.sum(axis=0) / np.maximum(per_pixel, 1))[None, :], 0.0)
        var = (dev * dev).sum(axis=0)[several] / (per_pixel[several] - 1)
        noise2 = float(np.mean(var / per_pixel[several]))
    else:
        within = cnt >= 2
        if not within.any():
            return sigma, math.nan
        c = cnt[within]
        var_w = np.maximum(s2[within] - s1[within] ** 2 / c, 0.0) / (c - 1.0)
        noise2 = float(np.mean(var_w / c))
    return sigma, math.sqrt(noise2)


class NotAScanError(RecordingError):
    """The experiment's voltage / target is not a periodic back-and-forth scan."""


@dataclass(frozen=True, slots=True)
class LinearityReport:
    """Linearity of several experiments.

    Attributes
    ----------
    experiments
        Per experiment.
    """

    experiments: tuple[ExperimentLinearity, ...]
    skipped: tuple[tuple[str, str, str], ...] = ()

    @property
    def max_nonlinearity_pct(self) -> float:
        """Worst non-linearity over all experiments."""
        return max(e.nonlinearity_pct for e in self.experiments)

    @property
    def max_abs_length_error_pct(self) -> float:
        """Largest |length error| over all experiments."""
        return max(abs(e.length_error_pct) for e in self.experiments)

    def to_json(self) -> dict[str, Any]:
        """The document of ``piezod linearity --json`` (keys: docs/formats.md)."""
        return {
            "experiments": [e.to_json() for e in self.experiments],
            "max_nonlinearity_pct": self.max_nonlinearity_pct,
            "max_abs_length_error_pct": self.max_abs_length_error_pct,
            "skipped": [{"experiment": e, "axis": a, "reason": r} for e, a, r in self.skipped],
        }


def noise_pct(position_um: NDArray[np.float64], measured_range_um: float) -> float:
    """The sensor's white noise as a nonlinearity (4.16): ``100 s / x'_R``.

    (4.16) divides the regression's residual standard deviation by the range, so the sensor's noise
    counts as nonlinearity: 3 nm on a 0.6 um line is 0.5 % whatever the scanner does (a 2.2 um
    buzzer-disc stage, docs/model-family.md 6.2ao). ``s`` is the readback's third-difference floor
    (:func:`piezod.audit.residuals.noise_floor`: white noise, the smooth scan ignored). Taking it
    out of (4.16) in quadrature is not done: a 1 % error of the floor leaves 0.07 % of a 0.5 %
    figure.

    Parameters
    ----------
    position_um
        The scan's readback.
    measured_range_um
        ``x'_R`` (4.14).

    Returns
    -------
    float
        nan when the floor cannot be estimated.
    """
    from piezod.audit.residuals import noise_floor

    x = np.asarray(position_um, dtype=np.float64)
    floor = noise_floor(x[np.isfinite(x)])
    if not (math.isfinite(floor) and measured_range_um > 0.0):
        return math.nan
    return 100.0 * floor / measured_range_um


def linearity(
    experiments: Sequence[Experiment],
    *,
    range_um: float | None = None,
    overscan: float | None = None,
    skip_non_scans: bool = False,
) -> LinearityReport:
    """:func:`experiment_linearity` of every experiment.

    With ``skip_non_scans`` an experiment that is not a periodic scan (e.g. the slow axis
    of a raster recording) is listed in ``skipped`` instead of failing the analysis.

    Raises
    ------
    RecordingError
        For the first experiment that cannot be analysed, or when none is left.
    """
    if not experiments:
        raise RecordingError("no experiments to analyse")
    done: list[ExperimentLinearity] = []
    skipped: list[tuple[str, str, str]] = []
    first_error: NotAScanError | None = None
    for e in experiments:
        try:
            done.append(experiment_linearity(e, range_um=range_um, overscan=overscan))
        except NotAScanError as exc:
            if not skip_non_scans:
                raise
            first_error = first_error or exc
            skipped.append((e.label, e.axis or "-", exc.reason))
    if not done:
        assert first_error is not None
        raise first_error
    return LinearityReport(tuple(done), tuple(skipped))
