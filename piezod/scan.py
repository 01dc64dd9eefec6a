"""Scan trajectories: what position each axis should be at, sample by sample.

A :class:`RasterGenerator` turns :class:`RasterParams` into blocks of target
positions (um) for the fast and slow axes at the board's sample rate: the fast
axis scans trace and retrace (both are image lines, as in the thesis), the slow
axis steps once per line (a short slew-limited step at the start of the trace)
or ramps continuously; a rotation turns the (fast, slow) frame onto the (x, y)
axes. New parameters take effect at the next line boundary. Moves between
points (to the scan start, between scans) are slew-limited raised-cosine
profiles (:func:`move_profile`), never jumps.

Everything here is pure numpy and per block; the engine maps the targets to
voltages through the inverse model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from piezod.errors import SafetyError

SlowMode = Literal["step", "ramp"]


@dataclass(frozen=True, slots=True)
class RasterParams:
    """One raster scan.

    Attributes
    ----------
    range_um
        Fast-axis scan range (um), the image width.
    line_rate_hz
        Lines per second; one line is a trace and a retrace.
    lines
        Lines per frame (slow-axis steps).
    slow_range_um
        Slow-axis range (um); None = square image (``range_um``).
    offset_x_um, offset_y_um
        Centre of the image in stage coordinates (um).
    rotation_deg
        Rotation of the image frame against the stage axes (counter-clockwise).
    overscan
        Extra fast-axis travel at each turning point, as a fraction of ``range_um``;
        the image lies inside, the turning points outside.
    slow_mode
        ``"step"``: the slow axis steps at the start of each trace; ``"ramp"``: it moves
        continuously (the lines are slightly skewed, as in most SPMs).
    slow_step_fraction
        Fraction of a line period over which a slow-axis step is spread (slew limit).
    frames
        Number of frames; 0 means scan until stopped.
    bidirectional_slow
        After a frame, scan the next one back (up/down) instead of returning to the start.
    """

    range_um: float
    line_rate_hz: float
    lines: int = 256
    slow_range_um: float | None = None
    offset_x_um: float = 0.0
    offset_y_um: float = 0.0
    rotation_deg: float = 0.0
    overscan: float = 0.0
    slow_mode: SlowMode = "step"
    slow_step_fraction: float = 0.02
    frames: int = 1
    bidirectional_slow: bool = True

    def __post_init__(self) -> None:
        checks = [
            (
                self.range_um > 0 and math.isfinite(self.range_um),
                f"range_um must be > 0, got {self.range_um}",
            ),
            (
                self.line_rate_hz > 0 and math.isfinite(self.line_rate_hz),
                f"line_rate_hz must be > 0, got {self.line_rate_hz}",
            ),
            (self.lines >= 1, f"lines must be >= 1, got {self.lines}"),
            (self.slow_range_um is None or self.slow_range_um >= 0, "slow_range_um must be >= 0"),
            (0.0 <= self.overscan <= 0.5, f"overscan must be in [0, 0.5], got {self.overscan}"),
            (0.0 < self.slow_step_fraction <= 0.5, "slow_step_fraction must be in (0, 0.5]"),
            (self.frames >= 0, "frames must be >= 0 (0 = until stopped)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise SafetyError(msg)

    @property
    def slow_range(self) -> float:
        """The slow-axis range (um)."""
        return self.range_um if self.slow_range_um is None else self.slow_range_um

    @property
    def fast_travel_um(self) -> float:
        """Fast-axis peak-to-peak travel including the overscan (um)."""
        return self.range_um * (1.0 + 2.0 * self.overscan)

    def extent_um(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((x_min, x_max), (y_min, y_max)) the scan visits in stage coordinates."""
        hf, hs = 0.5 * self.fast_travel_um, 0.5 * self.slow_range
        corners = np.array([[-hf, -hs], [hf, -hs], [hf, hs], [-hf, hs]])
        xy = corners @ _rotation(self.rotation_deg).T
        return (
            (float(xy[:, 0].min() + self.offset_x_um), float(xy[:, 0].max() + self.offset_x_um)),
            (float(xy[:, 1].min() + self.offset_y_um), float(xy[:, 1].max() + self.offset_y_um)),
        )


def _rotation(deg: float) -> NDArray[np.float64]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s], [s, c]])


@dataclass(frozen=True, slots=True)
class ScanBlock:
    """Targets for one block of samples.

    Attributes
    ----------
    start_index
        Sample index of the first sample (board clock).
    fast_um, slow_um
        Positions in the image frame (um, relative to the image centre).
    x_um, y_um
        Positions in stage coordinates (um): rotated and offset.
    fast_direction
        +1 on the trace, -1 on the retrace (per sample).
    line
        Line number within the frame (per sample).
    frame
        Frame number (per sample).
    params
        The parameters in force for each line of the block (one entry per line touched).
    in_image
        True where the fast axis is inside the image (not in the overscan).
    """

    start_index: int
    fast_um: NDArray[np.float64]
    slow_um: NDArray[np.float64]
    x_um: NDArray[np.float64]
    y_um: NDArray[np.float64]
    fast_direction: NDArray[np.int8]
    line: NDArray[np.int64]
    frame: NDArray[np.int64]
    in_image: NDArray[np.bool_]


class RasterGenerator:
    """Produce a raster scan block by block; parameter changes apply at the next line.

    Lines are laid out on the sample clock: line ``k`` of the current parameters
    starts at sample ``round(k * fs / f)`` after the parameter change, so the line
    period is exact on average even when ``fs / f`` is not an integer.

    Parameters
    ----------
    params
        The scan.
    sample_rate_hz
        The board's sample clock.
    start_index
        Board sample index of the first sample.
    """

    def __init__(self, params: RasterParams, sample_rate_hz: float, start_index: int = 0) -> None:
        if not sample_rate_hz > 0:
            raise SafetyError(f"sample_rate_hz must be > 0, got {sample_rate_hz}")
        self.sample_rate_hz = float(sample_rate_hz)
        self._params = params
        self._pending: RasterParams | None = None
        self._segment_start = start_index  # sample index where the current params began
        self._segment_line0 = 0  # line counter (across frames) at the segment start
        self._next = start_index
        self._check_line_samples(params)

    def _check_line_samples(self, p: RasterParams) -> None:
        per_line = self.sample_rate_hz / p.line_rate_hz
        if per_line < 8:
            raise SafetyError(
                f"line rate {p.line_rate_hz} Hz leaves {per_line:.1f} samples per line at "
                f"{self.sample_rate_hz:g} S/s; at least 8 are needed"
            )

    @property
    def params(self) -> RasterParams:
        """The parameters in force now."""
        return self._params

    @property
    def next_index(self) -> int:
        """Sample index of the next sample :meth:`next_block` produces."""
        return self._next

    @property
    def pending_index(self) -> int | None:
        """Sample index where requested new parameters take effect (the next line boundary), or None."""
        if self._pending is None:
            return None
        line = self._line_at(self._next)
        start = self._line_start(line)
        return start if start == self._next else self._line_start(line + 1)

    @property
    def done(self) -> bool:
        """True when a finite number of frames has been produced."""
        p = self._params
        return p.frames > 0 and self._next >= self._line_start(p.frames * p.lines)

    def total_samples(self) -> int:
        """Samples of the whole scan with the current parameters (finite ``frames`` only)."""
        p = self._params
        if p.frames == 0:
            raise SafetyError("an endless scan (frames = 0) has no total length")
        lines = p.frames * p.lines - self._segment_line0
        return self._segment_start + round(lines * self.sample_rate_hz / p.line_rate_hz) - self._next

    def change(self, **changes: object) -> RasterParams:
        """Request new parameters (e.g. ``range_um=20``); they apply at the next line boundary.

        Returns
        -------
        RasterParams
            The validated new parameters.
        """
        new = replace(self._params, **changes)  # type: ignore[arg-type]
        self._check_line_samples(new)
        self._pending = new
        return new

    def _lines_at(self, index: NDArray[np.int64]) -> NDArray[np.int64]:
        """Line of each sample index: line k holds ``[_line_start(k), _line_start(k + 1))``."""
        p = self._params
        spl = self.sample_rate_hz / p.line_rate_hz
        rel = index - self._segment_start
        k = np.floor(rel / spl).astype(np.int64)
        # the boundaries are integers (rounded); floating point may put k one off either way
        k += (np.round((k + 1) * spl) <= rel).astype(np.int64)
        k -= (np.round(k * spl) > rel).astype(np.int64)
        out: NDArray[np.int64] = self._segment_line0 + k
        return out

    def _line_at(self, index: int) -> int:
        return int(self._lines_at(np.array([index], dtype=np.int64))[0])

    def _line_start(self, line: int) -> int:
        p = self._params
        spl = self.sample_rate_hz / p.line_rate_hz
        return self._segment_start + round((line - self._segment_line0) * spl)

    def next_block(self, n: int) -> ScanBlock:
        """The next ``n`` samples (fewer when a finite scan ends inside the block)."""
        if n <= 0:
            raise ValueError(f"block size must be > 0, got {n}")
        parts: list[ScanBlock] = []
        remaining = n
        while remaining > 0 and not self.done:
            if self._pending is not None:
                line = self._line_at(self._next)
                boundary = self._line_start(line) if self._line_start(line) == self._next else None
                if boundary is None:
                    boundary = self._line_start(line + 1)
                if boundary == self._next:
                    self._segment_line0 = line
                    self._segment_start = self._next
                    self._params = self._pending
                    self._pending = None
                    continue
                take = min(remaining, boundary - self._next)
            else:
                take = remaining
            p = self._params
            if p.frames > 0:
                end = self._line_start(p.frames * p.lines)
                take = min(take, end - self._next)
            if take <= 0:
                raise SafetyError(f"scan generator made no progress at sample {self._next} (internal error)")
            part = self._render(self._next, take)
            parts.append(part)
            self._next += take
            remaining -= take
        if not parts:
            empty_f = np.empty(0)
            return ScanBlock(
                self._next,
                empty_f,
                empty_f,
                empty_f,
                empty_f,
                np.empty(0, np.int8),
                np.empty(0, np.int64),
                np.empty(0, np.int64),
                np.empty(0, bool),
            )
        if len(parts) == 1:
            return parts[0]
        return ScanBlock(
            parts[0].start_index,
            *(np.concatenate([getattr(q, f) for q in parts]) for f in _ARRAY_FIELDS),
        )

    def _render(self, start: int, n: int) -> ScanBlock:
        p = self._params
        spl = self.sample_rate_hz / p.line_rate_hz
        idx = np.arange(start, start + n, dtype=np.int64)
        line = self._lines_at(idx)
        # Line phase in [0, 1) over the line's own (integer) samples: trace on [0, 0.5), retrace on [0.5, 1).
        k = line - self._segment_line0
        first = np.round(k * spl)
        length = np.round((k + 1) * spl) - first
        phase = (idx - self._segment_start - first) / length
        tri = np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)  # 0 -> 1 -> 0
        half = 0.5 * p.fast_travel_um
        fast = -half + 2.0 * half * tri
        direction = np.where(phase < 0.5, 1, -1).astype(np.int8)
        frame = line // p.lines
        line_in_frame = line % p.lines
        backwards = p.bidirectional_slow & (frame % 2 == 1)
        row = np.where(backwards, p.lines - 1 - line_in_frame, line_in_frame).astype(np.float64)
        slow_step = p.slow_range / max(p.lines - 1, 1) if p.lines > 1 else 0.0
        sign = np.where(backwards, -1.0, 1.0)
        if p.slow_mode == "ramp":
            slow_rel = row + sign * phase  # continuous, one step per line
            slow_rel = np.clip(slow_rel, 0.0, max(p.lines - 1, 0))
        else:
            # Step over the first slow_step_fraction of the trace with a raised cosine.
            prev_row = np.clip(row - sign, 0, max(p.lines - 1, 0))
            first_line = line_in_frame == 0
            prev_row = np.where(first_line, row, prev_row)
            u = np.clip(phase / p.slow_step_fraction, 0.0, 1.0)
            w = 0.5 - 0.5 * np.cos(np.pi * u)
            slow_rel = prev_row + (row - prev_row) * w
        slow = -0.5 * p.slow_range + slow_rel * slow_step if p.lines > 1 else np.zeros(n)
        rot = _rotation(p.rotation_deg)
        x = rot[0, 0] * fast + rot[0, 1] * slow + p.offset_x_um
        y = rot[1, 0] * fast + rot[1, 1] * slow + p.offset_y_um
        in_image = np.abs(fast) <= 0.5 * p.range_um + 1e-12
        return ScanBlock(
            start, fast, np.asarray(slow, dtype=np.float64), x, y, direction, line, frame, in_image
        )


_ARRAY_FIELDS = ("fast_um", "slow_um", "x_um", "y_um", "fast_direction", "line", "frame", "in_image")


def move_profile(
    start: NDArray[np.float64] | float,
    end: NDArray[np.float64] | float,
    max_speed: NDArray[np.float64] | float,
    sample_rate_hz: float,
) -> NDArray[np.float64]:
    """A raised-cosine move from ``start`` to ``end`` whose peak speed is ``max_speed``.

    Works for positions (um, um/s) or voltages (V, V/s), one axis or several
    (then all axes arrive together, the slowest one setting the duration).

    Parameters
    ----------
    start, end
        Start and end value per axis.
    max_speed
        Largest allowed |d/dt| per axis (units per second), > 0.
    sample_rate_hz
        Sample clock.

    Returns
    -------
    ndarray
        Shape ``(axes, n)`` (``(1, n)`` for scalars); the last sample equals ``end``;
        at least one sample.
    """
    a = np.atleast_1d(np.asarray(start, dtype=np.float64))
    b = np.atleast_1d(np.asarray(end, dtype=np.float64))
    vmax = np.broadcast_to(np.atleast_1d(np.asarray(max_speed, dtype=np.float64)), a.shape)
    if np.any(vmax <= 0) or not np.all(np.isfinite(vmax)):
        raise SafetyError(f"max_speed must be finite and > 0, got {max_speed}")
    # Raised cosine: peak speed = pi/2 * distance / duration.
    duration = float(np.max(0.5 * np.pi * np.abs(b - a) / vmax))
    n = max(1, math.ceil(duration * sample_rate_hz))
    u = np.arange(1, n + 1) / n
    w = 0.5 - 0.5 * np.cos(np.pi * u)
    out: NDArray[np.float64] = a[:, None] + (b - a)[:, None] * w[None, :]
    return out


def slew_limit(
    values: NDArray[np.float64], previous: float, max_step: float, *, centred: bool = False
) -> tuple[NDArray[np.float64], int]:
    """Limit sample-to-sample steps to ``max_step`` (a last line of defence, not a trajectory).

    Parameters
    ----------
    values
        The samples of one block.
    previous
        The last sample sent before the block.
    max_step
        Largest step between two samples.
    centred
        Spread a step the limit cuts over the samples on both sides of it, not only after it:
        the mean of the block limited forwards (the ramp starts at the step) and backwards (the
        ramp ends there), limited forwards once more from ``previous``. The mean of two
        sequences within the limit is within it; for an isolated step the ramp is centred on the
        step. Only inside the block: a step at its first sample is limited forwards.

    Returns
    -------
    samples, changed
        The limited samples (each between the block's values and ``previous``) and how many of
        them differ from ``values``.

    Notes
    -----
    Sequential by nature, so it walks the samples only when some step violates the limit
    (trajectories are slew-limited by construction; a model's inverse may ask for more at a
    scan's turning points, docs/model-family.md 6.2w).
    """
    v = np.asarray(values, dtype=np.float64)
    d = np.diff(v, prepend=previous)
    if not np.any(np.abs(d) > max_step * (1 + 1e-9)):
        return v, 0
    if centred:
        both = 0.5 * (_limited_forwards(v, previous, max_step) + _limited_backwards(v, max_step))
        out = _limited_forwards(both, previous, max_step)
    else:
        out = _limited_forwards(v, previous, max_step)
    return out, int(np.count_nonzero(out != v))


def _limited_forwards(v: NDArray[np.float64], previous: float, max_step: float) -> NDArray[np.float64]:
    """``v`` limited sample by sample from ``previous``, walking only from each step the limit
    cuts until the samples are their own again (the steps in between are within the limit)."""
    src = v.tolist()
    out = list(src)
    bad = np.flatnonzero(np.abs(np.diff(v, prepend=previous)) > max_step)
    n = len(src)
    k = 0
    while k < bad.size:
        i = int(bad[k])
        prev = previous if i == 0 else out[i - 1]
        while i < n:
            prev = min(max(src[i], prev - max_step), prev + max_step)
            out[i] = prev
            i += 1
            if prev == src[i - 1] and i > bad[k]:
                break
        k = int(np.searchsorted(bad, i))
    return np.asarray(out, dtype=np.float64)


def _limited_backwards(v: NDArray[np.float64], max_step: float) -> NDArray[np.float64]:
    """``v`` limited from its last sample backwards (each ramp ends where the step was)."""
    return _limited_forwards(v[::-1], float(v[-1]), max_step)[::-1]
