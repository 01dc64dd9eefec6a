"""Recordings -> the arrays the calibration fits read (the data side of :mod:`piezod.calibrate`
and :mod:`piezod.calibrate_dynamic`).

:func:`prepare` (the thesis model, :class:`CalibrationData`): the complete loops of each
periodic triangular experiment, strided to at most ``max_samples_per_loop`` samples.

:func:`prepare_dynamic` puts every experiment at its place in time, reconstructs the unrecorded
stretches between them (a move at the slew rate, a hold, settling loops of a periodic
experiment) and decimates the voltage so that the hysteresis ODE stays exact (every turning
point kept) and the creep elements run on a uniform grid; see the docstring of
:mod:`piezod.calibrate_dynamic` for the reasoning. The result, :class:`DynamicCalibrationData`,
is what the dynamic and the family fits (:mod:`piezod.calibrate_family`) read.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from piezod.errors import CalibrationError
from piezod.recording import Experiment

F64 = NDArray[np.float64]

_MOVE_STEPS = 32


# ------------------------------------------------------------------------------------- thesis model


@dataclass(frozen=True, eq=False)
class CalibrationData:
    """The experiments of a calibration frame, concatenated for the fit.

    Attributes
    ----------
    voltage_v, direction, position_um
        Per sample (direction +1 trace / -1 retrace, as float).
    starts
        Index of the first sample of every experiment (experiments are contiguous).
    v_min, v_max, frequency_hz
        Per experiment, inferred from the voltage waveform.
    labels, axes, paths, n_loops
        Per experiment, for reports.
    """

    voltage_v: F64
    direction: F64
    position_um: F64
    starts: NDArray[np.intp]
    v_min: F64
    v_max: F64
    frequency_hz: F64
    labels: tuple[str, ...]
    axes: tuple[str | None, ...]
    paths: tuple[str | None, ...]
    n_loops: tuple[int, ...]

    @property
    def n_experiments(self) -> int:
        """Number of experiments."""
        return len(self.labels)

    @cached_property
    def counts(self) -> NDArray[np.intp]:
        """Samples per experiment."""
        return np.diff(np.append(self.starts, self.voltage_v.size))

    @cached_property
    def index(self) -> NDArray[np.intp]:
        """Experiment index of every sample."""
        return np.repeat(np.arange(self.n_experiments), self.counts)

    @cached_property
    def distance_from_start_v(self) -> F64:
        """``s (V - V_start)`` >= 0: voltage travelled since the branch's turning point."""
        v_start = np.where(self.direction > 0, self.v_min[self.index], self.v_max[self.index])
        out: F64 = self.direction * (self.voltage_v - v_start)
        return out

    @cached_property
    def from_centre_v(self) -> F64:
        """``V - V_C`` with ``V_C`` the centre of the experiment's scan."""
        out: F64 = self.voltage_v - (0.5 * (self.v_max + self.v_min))[self.index]
        return out


def prepare(
    experiments: Sequence[Experiment], *, skip_loops: int = 0, max_samples_per_loop: int | None = 2048
) -> CalibrationData:
    """Infer every experiment's scan and concatenate the frame.

    Parameters
    ----------
    experiments
        The experiments (one axis).
    skip_loops
        Complete loops to drop at the start of every experiment (settling).
    max_samples_per_loop
        Keep every k-th sample so that a loop has at most this many (None: all). The
        steady loop is smooth, so a few thousand samples determine it; plain striding
        (no averaging) keeps the per-sample noise and hence the fit errors (2.26)
        comparable with the undecimated data.

    Raises
    ------
    RecordingError
        An experiment's voltage is not a periodic triangular scan (file:line).
    CalibrationError
        Too little data left.
    """
    if not experiments:
        raise CalibrationError("no experiments to calibrate")
    if max_samples_per_loop is not None and max_samples_per_loop < 16:
        raise CalibrationError(f"max_samples_per_loop must be >= 16, got {max_samples_per_loop}")
    vs, ds, xs, starts = [], [], [], []
    v_min, v_max, freq, n_loops = [], [], [], []
    n = 0
    for e in experiments:
        info = e.require_scan()
        lo = 0
        if skip_loops:
            if info.n_loops <= skip_loops:
                raise CalibrationError(
                    f"experiment {e.describe()} has {info.n_loops} complete loop(s), cannot skip {skip_loops}"
                )
            lo = int(info.turning_indices[2 * skip_loops])
        step = 1
        if max_samples_per_loop is not None:
            per_loop = 1.0 / (info.frequency_hz * float(np.median(np.diff(e.t_s))))
            step = max(1, math.ceil(per_loop / max_samples_per_loop - 1e-6))
        starts.append(n)
        vs.append(e.voltage_v[lo::step])
        ds.append(info.direction[lo::step].astype(np.float64))
        xs.append(e.position_um[lo::step])
        n += vs[-1].size
        v_min.append(info.v_min)
        v_max.append(info.v_max)
        freq.append(info.frequency_hz)
        n_loops.append(info.n_loops - skip_loops)
    return CalibrationData(
        voltage_v=np.concatenate(vs),
        direction=np.concatenate(ds),
        position_um=np.concatenate(xs),
        starts=np.asarray(starts, dtype=np.intp),
        v_min=np.asarray(v_min),
        v_max=np.asarray(v_max),
        frequency_hz=np.asarray(freq),
        labels=tuple(e.label for e in experiments),
        axes=tuple(e.axis for e in experiments),
        paths=tuple(e.path for e in experiments),
        n_loops=tuple(n_loops),
    )


# ------------------------------------------------------------------------------------- session layout


@dataclass(frozen=True, slots=True)
class ExperimentLayout:
    """How one experiment enters the session simulation.

    Attributes
    ----------
    label, axis, path, kind
        Identification; ``kind`` from :func:`piezod.scan_inference.infer_scan`.
    t_start_s, duration_s
        Time of the first recorded sample and the recorded duration (s).
    frequency_hz, v_min, v_max
        Loop frequency (nan when not periodic) and the voltage span.
    stride
        Recorded samples per grid step.
    gap_s
        Unrecorded time before the experiment (s).
    move_s, hold_s, preroll_loops
        The gap's reconstruction: move at the slew rate, hold, settling loops.
    """

    label: str
    axis: str | None
    path: str | None
    kind: str
    t_start_s: float
    duration_s: float
    frequency_hz: float
    v_min: float
    v_max: float
    stride: int
    gap_s: float
    move_s: float
    hold_s: float
    preroll_loops: int


@dataclass(frozen=True, eq=False)
class DynamicCalibrationData:
    """A session prepared for the dynamic fit (:func:`prepare_dynamic`).

    Attributes
    ----------
    hysteresis_voltage_v
        The voltage subsequence the ODE runs on (grid samples and every turning point).
    grid_index
        Positions of the creep-grid samples in ``hysteresis_voltage_v``.
    pieces
        ``(dt_s, start, stop)`` over the grid: stretches of uniform sample interval.
    compared
        Grid positions of the compared (recorded) samples, experiments contiguous.
    position_um
        Measured positions there.
    starts, counts
        First compared sample and number of compared samples per experiment.
    rest_voltage_v
        Voltage the stage rested at before ``t = 0``.
    experiments
        Per-experiment layout.
    offset_group
        ``None`` (one unknown position offset per experiment), or the offset group of every
        compared sample: a group is a set of samples of one experiment that share an unknown
        position offset (a line pattern's rising and falling flanks, whose positions differ by
        the line width the fit need not know).
    offset_time_s
        ``None``, or the time (s) of every compared sample: each offset group's offset is then a
        straight line in time (an offset and a drift rate) instead of a constant.
    """

    hysteresis_voltage_v: F64
    grid_index: NDArray[np.intp]
    pieces: tuple[tuple[float, int, int], ...]
    compared: NDArray[np.intp]
    position_um: F64
    starts: NDArray[np.intp]
    counts: NDArray[np.intp]
    rest_voltage_v: float
    experiments: tuple[ExperimentLayout, ...]
    offset_group: NDArray[np.intp] | None = None
    offset_time_s: F64 | None = None

    @property
    def n_experiments(self) -> int:
        """Number of experiments."""
        return len(self.experiments)

    @property
    def grid_voltage_v(self) -> F64:
        """Voltage at the grid samples."""
        out: F64 = self.hysteresis_voltage_v[self.grid_index]
        return out

    def groups(self) -> NDArray[np.intp]:
        """The offset group of every compared sample (the experiment's index by default)."""
        if self.offset_group is not None:
            return self.offset_group
        out: NDArray[np.intp] = np.repeat(np.arange(self.n_experiments, dtype=np.intp), self.counts)
        return out

    def n_offset_parameters(self, rows: NDArray[np.bool_]) -> int:
        """The unknown offsets' parameters on ``rows`` (2 per group with :attr:`offset_time_s`)."""
        groups = int(np.unique(self.groups()[rows]).size)
        return groups * (1 if self.offset_time_s is None else 2)

    def centred(self, a: F64) -> F64:
        """``a`` (compared samples along axis 0) less its mean per offset group (per experiment
        unless :attr:`offset_group` says otherwise), and with :attr:`offset_time_s` less its
        straight line in time per group too: what is left once the unknown offsets are
        eliminated."""
        if self.offset_time_s is not None:
            return _detrended(a, self.groups(), self.offset_time_s)
        if self.offset_group is None:
            sums = np.add.reduceat(a, self.starts, axis=0)
            means = sums / (self.counts if a.ndim == 1 else self.counts[:, None])
            out: F64 = a - np.repeat(means, self.counts, axis=0)
            return out
        g = self.offset_group
        cols = a.reshape(a.shape[0], -1)
        n = np.maximum(np.bincount(g), 1).astype(np.float64)
        centred: F64 = (cols - (_group_sums(cols, g, n.size) / n[:, None])[g]).reshape(a.shape)
        return centred

    def time_scales_s(self) -> tuple[float, float]:
        """Shortest and longest time scale the frame shows: a quarter loop / a ramp; the session."""
        short = [
            0.25 / e.frequency_hz if math.isfinite(e.frequency_hz) else e.duration_s for e in self.experiments
        ]
        last = self.experiments[-1]
        return min(short), last.t_start_s + last.duration_s


class _Builder:
    def __init__(self, rest_v: float) -> None:
        self.v: list[F64] = []
        self.grid: list[NDArray[np.intp]] = []
        self.n_v = 0
        self.n_grid = 0
        self.pieces: list[tuple[float, int, int]] = []
        self.compared: list[NDArray[np.intp]] = []
        self.positions: list[F64] = []
        self.v_last = rest_v

    def piece(
        self,
        v: F64,
        grid_local: NDArray[np.intp],
        dt_s: float,
        compare_local: NDArray[np.intp] | None = None,
        positions: F64 | None = None,
    ) -> None:
        """Append ODE samples ``v``, of which ``grid_local`` are on a uniform grid of ``dt_s``."""
        if grid_local.size == 0:
            return
        self.v.append(v)
        self.grid.append(self.n_v + grid_local)
        self.pieces.append((dt_s, self.n_grid, self.n_grid + grid_local.size))
        if compare_local is not None and positions is not None:
            self.compared.append(self.n_grid + compare_local)
            self.positions.append(positions)
        self.n_v += v.size
        self.n_grid += grid_local.size
        self.v_last = float(v[-1])


def _turning_points(v: F64) -> NDArray[np.intp]:
    """Samples where the direction of ``v`` changes (held samples belong to their run)."""
    s = np.sign(np.diff(v))
    moving = np.flatnonzero(s)
    if moving.size < 2:
        return np.empty(0, dtype=np.intp)
    flips: NDArray[np.intp] = moving[1:][s[moving[1:]] != s[moving[:-1]]].astype(np.intp)
    return flips


def _sample_interval(e: Experiment) -> float:
    if len(e) < 2:
        raise CalibrationError(f"experiment {e.describe()}: needs at least 2 samples, has {len(e)}")
    steps = np.diff(e.t_s)
    dt = float(np.median(steps))
    bad = np.flatnonzero(np.abs(steps - dt) > 0.01 * dt)
    if bad.size:
        j = int(bad[0])
        line = None if e.line_numbers is None else int(e.line_numbers[j + 1])
        where = f" (line {line})" if line is not None else ""
        raise CalibrationError(
            f"experiment {e.describe()}: sample times are not uniform: step {steps[j]:.6g} s at "
            f"t = {e.t_s[j + 1]:.6g} s{where}, median {dt:.6g} s"
        )
    return dt


def _sample_period(v: F64, per_loop: float, *, rel: float = 0.03, probes: int = 4096) -> int:
    """The whole number of samples after which the voltage ``v`` repeats, near ``per_loop``.

    The waveform inference refines a triangle's turning times by straight lines through its
    halves; a periodic waveform whose halves are not straight (a triangle seen through a static
    map with a kink, as the runtime polarity part maps the commanded voltage) comes out with a
    period off by a fraction of a percent, which puts the reconstructed settling loops out of
    phase with the recorded ones. The lag ``L`` within ``rel`` of ``per_loop`` at which
    ``v[i + L]`` matches ``v[i]`` best (over at most ``probes`` samples ``i``) is the period the
    waveform was generated with; ``round(per_loop)`` wins ties.
    """
    n = v.size
    centre = round(per_loop)
    width = max(2, math.ceil(rel * per_loop))
    lags = [lag for lag in range(centre - width, centre + width + 1) if 2 <= lag < n]
    if not lags or centre >= n:
        return centre
    lags.sort(key=lambda lag: abs(lag - centre))
    m = n - max(lags)
    idx = np.arange(0, m, max(1, m // probes))
    cost = [float(np.mean((v[idx + lag] - v[idx]) ** 2)) for lag in lags]
    return lags[int(np.argmin(cost))]


#: Most settling loops :func:`prepare_dynamic` assumes before a periodic experiment (by default).
MAX_PREROLL_LOOPS = 8


def prepare_dynamic(
    experiments: Sequence[Experiment],
    *,
    max_samples_per_loop: int = 512,
    max_samples_per_experiment: int = 8192,
    slew_rate_v_per_s: float = 2000.0,
    rest_voltage_v: float = 0.0,
    max_preroll_loops: int = MAX_PREROLL_LOOPS,
    hold_before_move: bool = False,
) -> DynamicCalibrationData:
    """Lay out a session of experiments (any waveforms, one axis) for the dynamic fit.

    Parameters
    ----------
    experiments
        The recorded experiments; sorted by time here, they must not overlap in ``t``.
    max_samples_per_loop
        Grid density of periodic experiments (samples per loop, at most).
    max_samples_per_experiment
        Grid samples of a non-periodic experiment, at most.
    slew_rate_v_per_s
        Rate of the unrecorded moves between experiments (the axis's slew rate).
    rest_voltage_v
        Voltage the stage rested at before ``t = 0`` (the safe voltage).
    max_preroll_loops
        Most settling loops assumed before a periodic experiment.
    hold_before_move
        Between experiments the stage holds where the previous one ended, then moves to the next
        start (the daemon's scan jobs: a scan holds at its end until the next one moves); by
        default it moves first and holds at the next start (``hil_sim.session``'s pause).

    Raises
    ------
    CalibrationError
        No experiments, several axes, overlapping or non-uniform sample times, or too few samples.
    """
    if not experiments:
        raise CalibrationError("no experiments to calibrate")
    if max_samples_per_loop < 16 or max_samples_per_experiment < 16:
        raise CalibrationError("max_samples_per_loop and max_samples_per_experiment must be >= 16")
    if not (math.isfinite(slew_rate_v_per_s) and slew_rate_v_per_s > 0):
        raise CalibrationError(f"slew_rate_v_per_s must be > 0, got {slew_rate_v_per_s!r}")
    axes = {e.axis for e in experiments if e.axis is not None}
    if len(axes) > 1:
        raise CalibrationError(f"experiments of several axes ({', '.join(sorted(axes))}): calibrate one axis")
    order = sorted(experiments, key=lambda e: float(e.t_s[0]))
    builder = _Builder(float(rest_voltage_v))
    layouts: list[ExperimentLayout] = []
    starts: list[int] = []
    counts: list[int] = []
    t_prev = 0.0
    prev: Experiment | None = None
    n_compared = 0
    for e in order:
        dt = _sample_interval(e)
        t0 = float(e.t_s[0])
        if prev is not None and t0 <= t_prev:
            raise CalibrationError(
                f"experiments {prev.describe()} and {e.describe()} overlap in time "
                f"(t = {t0:.6g} s <= {t_prev:.6g} s): one session, continuous t, is needed"
            )
        v = np.asarray(e.voltage_v, dtype=np.float64)
        n = v.size
        info = e.scan()
        periodic = bool(info.is_periodic)
        freq = float(info.frequency_hz) if periodic else math.nan
        if periodic:
            per_loop = 1.0 / (freq * dt)
            loop = _sample_period(v, per_loop)
            if loop != round(per_loop):
                per_loop, freq = float(loop), 1.0 / (loop * dt)
            stride = max(1, math.floor(per_loop / max_samples_per_loop))
        else:
            per_loop = math.nan
            stride = max(1, math.ceil(n / max_samples_per_experiment))
            loop = 0
        gap = max(0, round((t0 - t_prev) / dt) - 1) if prev is not None or t0 > 0.0 else 0
        v_from = builder.v_last
        # where the experiment started: one sample before its first, on the same slope
        v_start = 2.0 * float(v[0]) - float(v[1])
        move = math.ceil(abs(v_start - v_from) / slew_rate_v_per_s / dt - 1e-6)
        n_pre = 0
        pre = 0
        if periodic and 0 < loop <= n:
            # whole loops that fit after the move (a sample or two of the move may be short)
            n_pre = max(0, min(max_preroll_loops, math.floor((gap - move) / per_loop + 0.05)))
            pre = min(gap, round(n_pre * per_loop))
            v_start = float(v[(-pre - 1) % loop])
        move = min(move, gap - pre)
        hold = gap - pre - move
        if move + hold == 0:
            v_start = v_from  # no room: the first sample follows the previous one directly
        # the move (monotone: exact for the ODE) and the hold (one step): before the first
        # experiment the stage rests at the rest voltage until it moves (the daemon idles, then
        # ramps to a program's start); between experiments it holds at the next start voltage
        # (hil_sim.session's pause)
        steps = min(move, _MOVE_STEPS)
        frac = np.arange(1, steps + 1) / max(steps, 1)
        hold_first = prev is None or hold_before_move
        v_hold = v_from if hold_first else v_start
        if hold > 0 and hold_first:
            builder.piece(np.array([v_hold]), np.zeros(1, dtype=np.intp), hold * dt)
        if move > 0:
            mv = v_from + (v_start - v_from) * frac
            builder.piece(mv, np.arange(steps, dtype=np.intp), move * dt / steps)
        if hold > 0 and not hold_first:
            builder.piece(np.array([v_hold]), np.zeros(1, dtype=np.intp), hold * dt)
        # settling loops (the periodic extension of the first recorded loop backwards in time),
        # then the recorded samples: grid every `stride` samples, ending on the last one
        full = np.concatenate([v[np.arange(-pre, 0) % loop], v]) if pre else v
        offset = pre
        length = full.size
        grid = np.arange((length - 1) % stride, length, stride, dtype=np.intp)
        keep = np.union1d(grid, _turning_points(np.concatenate(([builder.v_last], full)))[:] - 1)
        keep = keep[keep >= 0]
        first = int(grid[0])
        pos = np.asarray(e.position_um, dtype=np.float64)
        for lo_i, hi_i, dt_piece in ((-1, first, (first + 1) * dt), (first, length - 1, stride * dt)):
            sel = keep[(keep > lo_i) & (keep <= hi_i)]
            gl = np.flatnonzero(np.isin(sel, grid)).astype(np.intp)
            on_grid = sel[gl]
            rec = on_grid >= offset
            builder.piece(
                full[sel], gl, dt_piece, np.flatnonzero(rec).astype(np.intp), pos[on_grid[rec] - offset]
            )
        m = int(sum(c.size for c in builder.compared)) - n_compared
        starts.append(n_compared)
        counts.append(m)
        n_compared += m
        layouts.append(
            ExperimentLayout(
                label=e.label,
                axis=e.axis,
                path=e.path,
                kind=str(info.kind),
                t_start_s=t0,
                duration_s=float(e.t_s[-1] - t0),
                frequency_hz=freq,
                v_min=float(v.min()),
                v_max=float(v.max()),
                stride=stride,
                gap_s=gap * dt,
                move_s=move * dt,
                hold_s=hold * dt,
                preroll_loops=n_pre,
            )
        )
        t_prev = float(e.t_s[-1])
        prev = e
    if min(counts) < 8:
        bad = layouts[int(np.argmin(counts))]
        raise CalibrationError(f"experiment {bad.label!r}: too few samples for the fit ({min(counts)})")
    return DynamicCalibrationData(
        hysteresis_voltage_v=np.concatenate(builder.v),
        grid_index=np.concatenate(builder.grid),
        pieces=tuple(builder.pieces),
        compared=np.concatenate(builder.compared),
        position_um=np.concatenate(builder.positions),
        starts=np.asarray(starts, dtype=np.intp),
        counts=np.asarray(counts, dtype=np.intp),
        rest_voltage_v=float(rest_voltage_v),
        experiments=tuple(layouts),
    )


def _detrended(a: F64, group: NDArray[np.intp], t: F64) -> F64:
    """``a`` less its least-squares straight line in ``t`` within every group (a linear projection:
    it commutes with the fits' linear combinations of columns)."""
    cols = a.reshape(a.shape[0], -1)
    n = np.bincount(group).astype(np.float64)
    safe = np.maximum(n, 1.0)
    tc = t - (np.bincount(group, weights=t, minlength=n.size) / safe)[group]
    stt = np.bincount(group, weights=tc * tc, minlength=n.size)
    inv = np.where(stt > 0, 1.0 / np.where(stt > 0, stt, 1.0), 0.0)
    centred = cols - (_group_sums(cols, group, n.size) / safe[:, None])[group]
    cross = _group_sums(centred * tc[:, None], group, n.size)
    out: F64 = (centred - (cross * inv[:, None])[group] * tc[:, None]).reshape(a.shape)
    return out


def _group_sums(cols: F64, group: NDArray[np.intp], size: int) -> F64:
    """Sums of the columns of ``cols`` (samples along axis 0) per group, shape ``(size, columns)``
    (a bincount per column: faster than ``np.add.at`` for one column and for a hundred)."""
    out: F64 = np.stack([np.bincount(group, weights=c, minlength=size) for c in cols.T], axis=1)
    return out


__all__ = [
    "MAX_PREROLL_LOOPS",
    "CalibrationData",
    "DynamicCalibrationData",
    "ExperimentLayout",
    "prepare",
    "prepare_dynamic",
]
