"""SPM images from recordings: trace and retrace on the commanded grid and on the measured positions.

A raster recording (``piezod scan``, the daemon) holds, per sample of the fast axis ``x``: the
commanded ``target`` (um), the sensor ``position`` (um; absent physically when the board has no
position sensor, metadata ``position_sensor: no``) and, from a microscope, the height channel
``z_voltage`` (V, the z-piezo voltage of the z feedback). The fast-axis target is a triangle; its
turning points cut it into half periods: the *traces* (target increasing) and the *retraces*.
Trace ``k`` and the retrace after it are image line ``k`` (the slow axis steps at the start of each
trace). Pixel ``j`` of a line of ``N`` pixels covers ``[x0 + j R / N, x0 + (j + 1) R / N)`` of the
fast coordinate, ``x0 = offset - R / 2``; on the commanded grid its value is the mean over the
pixel of the line's profile interpolated linearly between its samples (where in the pixel an edge
lies stays in the image at any sample rate), on the measured grid the mean of the samples inside
(empty pixels, at most a few at very high pixel counts, are interpolated along the line). Both
images are stored left to right in x.

* ``grid="commanded"``: the fast coordinate is the commanded target: the image the microscope
  shows (distorted where the scanner is not linear).
* ``grid="measured"``: the fast coordinate is the sensor position: the image on the positions the
  tip really had (needs a position sensor).

Height channels (:func:`height_channels`): ``z_voltage`` (V) as recorded; ``height_linear`` (um):
one constant z sensitivity times the voltage (what SPM software does; the sensitivity is the best
linear fit to the model heights of the same recording unless given); ``height_model`` (um): the z
axis's forward model (the hysteresis ODE (2.21), with the creep operator of the dynamic model when
the z axis has one) run through the whole recorded z-voltage waveform from rest at its first
sample - exact for any waveform, with its state.

Everything here is pure numpy on in-memory recordings; files are written by :mod:`piezod.image_io`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from piezod.config import AxisConfig
from piezod.errors import RecordingError
from piezod.model.dynamic import dynamic_forward, dynamic_rest_state
from piezod.model.family import family_forward, family_rest_state
from piezod.model.ode import hysteresis_step, relaxed_state
from piezod.recording import Recording, infer_scan

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class RasterSamples:
    """The fast-axis samples of a raster recording, each with its image line and direction.

    Attributes
    ----------
    t_s, target_um, position_um, voltage_v
        Time, commanded and sensed fast-axis position, and voltage of every sample.
    z_voltage_v
        The height channel (V) or None.
    line
        Image line of every sample (-1: not part of a complete trace / retrace).
    direction
        +1 on traces, -1 on retraces.
    lines
        Number of image lines.
    """

    t_s: F64
    target_um: F64
    position_um: F64
    voltage_v: F64
    z_voltage_v: F64 | None
    line: NDArray[np.int64]
    direction: NDArray[np.int8]
    lines: int


@dataclass(frozen=True, slots=True)
class Geometry:
    """Where the image lies: fast-axis range and offset, slow range, pixels, rotation (metadata)."""

    range_um: float
    offset_um: float
    slow_range_um: float
    offset_slow_um: float
    pixels: int
    rotation_deg: float
    line_rate_hz: float | None

    @property
    def x0_um(self) -> float:
        """Fast coordinate of the left edge of the first pixel (um)."""
        return self.offset_um - 0.5 * self.range_um

    @property
    def pixel_um(self) -> float:
        """Pixel width (um)."""
        return self.range_um / self.pixels

    def pixel_centres_um(self) -> F64:
        """Fast coordinate of every pixel centre (um)."""
        out: F64 = self.x0_um + (np.arange(self.pixels, dtype=np.float64) + 0.5) * self.pixel_um
        return out


@dataclass(frozen=True, slots=True)
class ImagePair:
    """Trace and retrace image of one channel on one grid.

    Attributes
    ----------
    channel
        ``z_voltage``, ``height_linear``, ``height_model`` (or any other name).
    unit
        SI unit string of the values (``V``, ``m`` ...) as used in the files; values are in
        ``V`` or ``um`` (see ``scale_to_si``).
    scale_to_si
        Factor from the stored values to ``unit`` (1e-6 for um -> m).
    grid
        ``commanded`` or ``measured``.
    trace, retrace
        ``(lines, pixels)`` arrays, row 0 = first line.
    geometry
        Where the image lies.
    """

    channel: str
    unit: str
    scale_to_si: float
    grid: str
    trace: F64
    retrace: F64
    geometry: Geometry
    notes: Mapping[str, str] = field(default_factory=dict)


def _meta_float(rec: Recording, key: str, default: float | None = None) -> float | None:
    raw = rec.metadata.get(key)
    if raw is None or raw in ("", "None", "none"):
        return default
    try:
        return float(raw)
    except ValueError:
        raise RecordingError(f"metadata {key!r}: not a number: {raw!r}", rec.path) from None


def geometry(rec: Recording, *, pixels: int | None = None) -> Geometry:
    """The image geometry from the recording's metadata (``range_um``, ``offset_x_um``, ``pixels``, ...).

    Raises
    ------
    RecordingError
        No ``range_um`` metadata, or an invalid value.
    """
    r = _meta_float(rec, "range_um")
    if r is None or not r > 0:
        raise RecordingError("no '# range_um:' metadata (the image width): not a raster recording", rec.path)
    n = pixels if pixels is not None else int(_meta_float(rec, "pixels", 256) or 256)
    if not 2 <= n <= 16384:
        raise RecordingError(f"pixels must lie in [2, 16384], got {n}", rec.path)
    slow = _meta_float(rec, "slow_range_um", None)
    return Geometry(
        range_um=float(r),
        offset_um=float(_meta_float(rec, "offset_x_um", 0.0) or 0.0),
        slow_range_um=float(slow if slow is not None and slow > 0 else r),
        offset_slow_um=float(_meta_float(rec, "offset_y_um", 0.0) or 0.0),
        pixels=n,
        rotation_deg=float(_meta_float(rec, "rotation_deg", 0.0) or 0.0),
        line_rate_hz=_meta_float(rec, "line_rate_hz", None),
    )


def has_position_sensor(rec: Recording) -> bool:
    """False when the recording says its board had no position sensor (``# position_sensor: no``)."""
    return rec.metadata.get("position_sensor", "yes").strip().lower() not in ("no", "false", "0")


def raster_samples(rec: Recording) -> RasterSamples:
    """Split the fast-axis (``x``) rows of a raster recording into image lines.

    Raises
    ------
    RecordingError
        No ``target`` column, no x rows, a rotated scan, or no complete trace and retrace.
    """
    if rec.target_um is None:
        raise RecordingError("no 'target' column: images need the commanded positions", rec.path)
    rot = _meta_float(rec, "rotation_deg", 0.0) or 0.0
    if abs(rot) > 1e-9:
        raise RecordingError(f"rotation_deg {rot:g}: images of rotated scans are not supported yet", rec.path)
    sel = np.ones(len(rec), dtype=bool) if rec.axis is None else rec.axis == "x"
    if not sel.any():
        raise RecordingError("no rows of the fast axis x", rec.path)
    t = rec.t_s[sel]
    target = rec.target_um[sel]
    info = infer_scan(t, target)
    idx = info.turning_indices
    if not info.is_periodic or idx.size < 3:
        raise RecordingError(
            f"the fast-axis target is not a back-and-forth scan with a complete trace and retrace "
            f"({info.kind}: {info.reason})",
            rec.path,
        )
    n = t.size
    half = np.full(n, -1, dtype=np.int64)
    direction = np.zeros(n, dtype=np.int8)
    trace_count = 0
    line_of_half: list[int] = []
    for h in range(idx.size - 1):
        d = int(-info.turning_kinds[h])
        if d > 0:
            line_of_half.append(trace_count)
            trace_count += 1
        else:
            line_of_half.append(trace_count - 1)
        lo, hi = int(idx[h]), int(idx[h + 1])
        half[lo:hi] = line_of_half[-1]
        direction[lo:hi] = d
    line = np.where(half >= 0, half, -1)
    z = rec.z_voltage_v[sel] if rec.z_voltage_v is not None else None
    return RasterSamples(
        t_s=t,
        target_um=target,
        position_um=rec.position_um[sel],
        voltage_v=rec.voltage_v[sel],
        z_voltage_v=z,
        line=line,
        direction=direction,
        lines=trace_count,
    )


def _box_means(x: F64, v: F64, edges: F64) -> F64:
    """Mean over each ``[edges[j], edges[j + 1])`` of the profile interpolated linearly between the
    points ``(x, v)`` (``x`` increasing); NaN where a box holds no part of ``[x[0], x[-1]]``."""
    dx = np.diff(x)
    cum = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dx)))

    def integral(b: F64) -> F64:
        b = np.clip(b, x[0], x[-1])
        i = np.clip(np.searchsorted(x, b, side="right") - 1, 0, x.size - 2)
        h = b - x[i]
        slope = (v[i + 1] - v[i]) / np.where(dx[i] > 0, dx[i], 1.0)
        out: F64 = cum[i] + v[i] * h + 0.5 * slope * h * h
        return out

    lo, hi = np.clip(edges[:-1], x[0], x[-1]), np.clip(edges[1:], x[0], x[-1])
    width = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        means: F64 = np.where(width > 0, (integral(edges[1:]) - integral(edges[:-1])) / width, np.nan)
    return means


def assemble(
    coord_um: F64,
    values: F64,
    line: NDArray[np.int64],
    direction: NDArray[np.int8],
    lines: int,
    geo: Geometry,
    *,
    profile: bool = False,
) -> tuple[F64, F64]:
    """Trace and retrace images: the mean of ``values`` in every (line, pixel) bin of ``coord_um``.

    With ``profile`` (a coordinate monotonic within every half line: the commanded grid) a pixel
    is the mean over its width of the profile interpolated linearly between the samples: a sharp
    edge then leaves the pixel it falls in at the level that says where in the pixel it lies,
    whatever the samples' phase in the pixel (the plain mean of the samples inside a pixel of a
    few samples puts it up to half a sample spacing off). Without, the mean of the samples inside.

    Returns
    -------
    trace, retrace
        ``(lines, pixels)``; pixels no sample fell into are interpolated along their line (NaN when
        a line has no sample at all).
    """
    n_px = geo.pixels
    p = np.floor((coord_um - geo.x0_um) / geo.pixel_um).astype(np.int64)
    ok = (line >= 0) & (p >= 0) & (p < n_px) & np.isfinite(values)
    edges = geo.x0_um + geo.pixel_um * np.arange(n_px + 1, dtype=np.float64)
    out = []
    for d in (1, -1):
        s = ok & (direction == d)
        flat = line[s] * n_px + p[s]
        size = lines * n_px
        cnt = np.bincount(flat, minlength=size).astype(np.float64)
        tot = np.bincount(flat, weights=values[s], minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            img = (tot / cnt).reshape(lines, n_px)
        if profile:
            whole = (line >= 0) & (direction == d) & np.isfinite(values)
            for r in range(lines):
                k = np.flatnonzero(whole & (line == r))
                if k.size < 2:
                    continue
                order = np.argsort(coord_um[k], kind="stable")
                xs, vs = coord_um[k][order], values[k][order]
                if np.any(np.diff(xs) <= 0):
                    continue  # not monotonic: keep the sample means
                box = _box_means(xs, vs, edges)
                img[r] = np.where(np.isfinite(box), box, img[r])
        cols = np.arange(n_px)
        for r in range(lines):
            row = img[r]
            good = np.isfinite(row)
            if good.any() and not good.all():
                row[~good] = np.interp(cols[~good], cols[good], row[good])
        out.append(img)
    return out[0], out[1]


def forward_heights(axis: AxisConfig, z_voltage_v: F64, dt_s: float) -> F64:
    """Heights (um) of a recorded z-voltage waveform through the z axis's forward model, from rest.

    The model family's forward model when the axis's model is ``family`` (e.g. a z calibrated by
    :func:`piezod.heights.fit_z_model`), the dynamic model (hysteresis ODE + creep operator) when
    the axis has a ``dynamic`` section, else the hysteresis ODE (2.21) of its thesis parameters
    (no creep: the thesis's creep law (3.8) holds for periodic scans only, which z is not). The
    height is relative to the position before the first sample.

    A family model starts at rest at the axis's safe voltage and ramps to the first sample at the
    axis's slew rate: a fitted law's states are defined along the histories it was fitted on,
    which start that way (:func:`piezod.calibrate_data.prepare_dynamic`); "rested at the first
    voltage for ever" is a state no calibration visits (a Bouc-Wen law fitted to 0.05 nm put its
    slope 7 % off there). The other models start at rest at the first sample's voltage.
    """
    v = np.asarray(z_voltage_v, dtype=np.float64)
    if v.size == 0:
        return np.zeros(0)
    if axis.model == "family" and axis.family is not None:
        fp = axis.family.params()
        fs = family_rest_state(fp, axis.safe_voltage_v)
        n = math.ceil(abs(float(v[0]) - axis.safe_voltage_v) / axis.slew_rate_v_per_s / dt_s)
        if n > 0:
            _, fs = family_forward(fp, np.linspace(axis.safe_voltage_v, float(v[0]), n + 1)[1:], dt_s, fs)
        xf, _ = family_forward(fp, v, dt_s, fs)
        out_f: F64 = xf - fs.position_um
        return out_f
    if axis.dynamic is not None:
        params = axis.dynamic.params()
        st = dynamic_rest_state(params, float(v[0]))
        x0 = st.position_um
        x, _ = dynamic_forward(params, v, dt_s, st)
        out: F64 = x - x0
        return out
    hp = axis.thesis.params().hysteresis
    hs = relaxed_state(hp, float(v[0]))
    x, _ = hysteresis_step(hp, v, hs)
    x0 = float(x[0]) if v.size else 0.0
    res: F64 = x - x0
    return res


def linear_sensitivity(z_voltage_v: F64, heights_um: F64) -> float:
    """The best constant z sensitivity (um/V): least-squares slope of heights on voltage."""
    v = z_voltage_v - z_voltage_v.mean()
    h = heights_um - heights_um.mean()
    vv = float(v @ v)
    return float(v @ h) / vv if vv > 0 else math.nan


def height_channels(
    samples: RasterSamples,
    z_axis: AxisConfig | None,
    sample_rate_hz: float,
    sensitivity_um_per_v: float | None,
) -> dict[str, tuple[F64, str, float]]:
    """The height channels of a raster recording: name -> (values per sample, SI unit, scale to SI)."""
    z = samples.z_voltage_v
    if z is None:
        return {}
    out: dict[str, tuple[F64, str, float]] = {"z_voltage": (z, "V", 1.0)}
    model_h: F64 | None = None
    if z_axis is not None and np.isfinite(z).all():
        model_h = forward_heights(z_axis, z, 1.0 / sample_rate_hz)
        out["height_model"] = (model_h, "m", 1e-6)
    s = sensitivity_um_per_v
    if s is None and model_h is not None:
        s = linear_sensitivity(z, model_h)
    if s is not None and math.isfinite(s):
        out["height_linear"] = ((z - z[0]) * s, "m", 1e-6)
    return out


def images(
    rec: Recording,
    *,
    z_axis: AxisConfig | None = None,
    pixels: int | None = None,
    sensitivity_um_per_v: float | None = None,
    frame: int | None = None,
) -> list[ImagePair]:
    """Every image of a raster recording: each height channel on the commanded grid, and on the
    measured grid when the board had a position sensor.

    Parameters
    ----------
    rec
        A raster recording with ``target`` and ``z_voltage`` columns.
    z_axis
        The z axis of the scanner config (for ``height_model`` / ``height_linear``); None: only the
        recorded ``z_voltage``.
    pixels
        Pixels per line (default: the recording's ``pixels`` metadata, else 256).
    sensitivity_um_per_v
        Constant z sensitivity of ``height_linear`` (default: the best fit to the model heights).
    frame
        Only this frame of a multi-frame scan (frame ``k``: image lines ``k L .. k L + L - 1``,
        ``L`` the recording's ``lines`` metadata); a frame still being recorded gives its lines
        so far. The heights still run through the whole z-voltage waveform from the recording's
        first sample (the z model's state carries over from frame to frame). None: every line.

    Raises
    ------
    RecordingError
        Not a raster recording, no height channel, or no line of ``frame``.
    """
    geo = geometry(rec, pixels=pixels)
    rs = raster_samples(rec)
    rate = _meta_float(rec, "sample_rate_hz", None)
    if rate is None:
        dt = np.diff(rs.t_s)
        rate = 1.0 / float(np.median(dt)) if dt.size else 1.0
    chans = height_channels(rs, z_axis, rate, sensitivity_um_per_v)
    if not chans:
        raise RecordingError("no 'z_voltage' column: the recording carries no height channel", rec.path)
    line, lines = rs.line, rs.lines
    if frame is not None:
        line, lines = frame_lines(rec, rs, frame)
    grids = {"commanded": rs.target_um}
    if has_position_sensor(rec):
        grids["measured"] = rs.position_um
    out = []
    for grid, coord in grids.items():
        for name, (values, unit, scale) in chans.items():
            tr, re = assemble(coord, values, line, rs.direction, lines, geo, profile=grid == "commanded")
            out.append(ImagePair(name, unit, scale, grid, tr, re, geo))
    return out


def frame_lines(rec: Recording, rs: RasterSamples, frame: int) -> tuple[NDArray[np.int64], int]:
    """The image line of every sample within frame ``frame`` (-1 outside it) and the lines per frame.

    Raises
    ------
    RecordingError
        No ``lines`` metadata, or no line of ``frame`` in the recording.
    """
    per = _meta_float(rec, "lines", None)
    if per is None or not per >= 1 or per != int(per):
        raise RecordingError("no valid '# lines:' metadata (lines per frame): cannot cut frames", rec.path)
    n = int(per)
    frames = -(-rs.lines // n)
    if frame < 0 or frame * n >= rs.lines:
        raise RecordingError(
            f"frame {frame}: the recording holds {frames} frame(s) of {n} lines (0 .. {frames - 1})", rec.path
        )
    inside = (rs.line >= frame * n) & (rs.line < (frame + 1) * n)
    out: NDArray[np.int64] = np.where(inside, rs.line - frame * n, -1).astype(np.int64)
    return out, n


def level(img: F64) -> F64:
    """The image minus its least-squares plane (for display; NaN-safe)."""
    grid = np.indices(img.shape).astype(np.float64)
    rows, cols = grid[0], grid[1]
    ok = np.isfinite(img)
    if ok.sum() < 3:
        flat: F64 = img - np.nanmean(img)
        return flat
    a = np.column_stack((np.ones(int(ok.sum())), rows[ok], cols[ok]))
    coef = np.asarray(np.linalg.lstsq(a, img[ok], rcond=None)[0], dtype=np.float64)
    out: F64 = img - (coef[0] + coef[1] * rows + coef[2] * cols)
    return out


__all__ = [
    "Geometry",
    "ImagePair",
    "RasterSamples",
    "assemble",
    "forward_heights",
    "frame_lines",
    "geometry",
    "has_position_sensor",
    "height_channels",
    "images",
    "level",
    "linear_sensitivity",
    "raster_samples",
]
