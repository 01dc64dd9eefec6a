"""The streaming engine: scan jobs -> inverse model -> voltage blocks -> board, sensor -> recordings.

The board owns the sample clock. The engine is the :class:`~piezod.link.streamer.BlockSource`
of a :class:`~piezod.link.streamer.Streamer`, which asks for blocks ahead of the clock (the lead,
at least 100 ms) and keeps the board FIFO filled by credits. Every block is computed in numpy
by the current *job* (hold, move, scan, ramp to safe) through the per-axis
:class:`~piezod.service.axes.AxisDriver`, whose model state carries over from job to job.

The stream runs continuously while the board is connected (idle = hold the last voltages), so
sample indices, and the session time ``t = index / rate`` of the recordings, are continuous.
The sensor readback arrives on the link's reader thread, is paired with the targets the engine
remembers per sample index, and goes to a recorder thread that appends it to the recording
(flushed per block, so a crash loses at most the last block) and computes the linearity of the
last complete line.

Safety: every voltage is clamped to the axis limits and slew-limited before it leaves the host
(clamping is reported as a fault); ``stop()`` holds; a fault, a lost link and shutdown ramp the
outputs to the safe values (the board also ramps by itself when the host's heartbeat stops).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import queue
import stat
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from firmware_proto import NO_INDEX
from piezod.config import AxisConfig, AxisName, ScannerConfig, calibrated_axes
from piezod.errors import (
    EngineStateError,
    LinkError,
    ModelError,
    PiezodError,
    SafetyError,
)
from piezod.link.session import (
    BoardFault,
    BoardSession,
    HostLimitFault,
    LinkDown,
    LinkEvent,
    LinkLost,
    LinkSettings,
    Reconnected,
    SensorGap,
)
from piezod.link.streamer import MatchedBlock, Streamer
from piezod.recording import RecordingWriter
from piezod.scan import move_profile
from piezod.service.axes import AxisDriver, PeriodicPlan
from piezod.service.schemas import (
    EngineState,
    FaultInfo,
    LineLinearity,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanRequest,
    Status,
)
from piezod.service.tracking import SensitivityTracker
from piezod.trajectory import RasterTrajectory, Trajectory

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
FaultSource = Literal["board", "host", "link"]

#: A block computation slower than this (s) is logged with its cause.
SLOW_BLOCK_S = 0.05
#: Faults of one (source, code) closer together than this (s) are counted, not listed again.
FAULT_REPEAT_S = 1.0
#: Speed of the moves to the start of a scan, as a multiple of the scan's own speed (at most).
MOVE_SPEED_FACTOR = 1.0


@dataclass(slots=True)
class Chunk:
    """What a job produced for some samples.

    Attributes
    ----------
    volts
        ``(axes, n)`` voltages.
    targets
        ``(axes, n)`` target positions (um), NaN where the axis has no target.
    line
        Line number per sample (-1 outside scan lines).
    direction
        +1 trace / -1 retrace / 0 (per sample).
    record
        Whether the sample is recorded.
    label
        Experiment label id of the chunk (:meth:`Engine.label_id`), -1 for none.
    """

    volts: FloatArray
    targets: FloatArray
    line: NDArray[np.int64]
    direction: NDArray[np.int8]
    record: NDArray[np.bool_]
    label: int = -1
    corrected: bool = False


class Job(ABC):
    """Something the engine streams: produces chunks until :attr:`done`."""

    state: EngineState = "idle"
    done = False

    @abstractmethod
    def render(self, engine: Engine, n: int) -> Chunk:
        """The next ``n`` samples (fewer when the job ends inside them)."""


class HoldJob(Job):
    """Hold the last voltages (idle)."""

    def __init__(self, state: EngineState = "idle") -> None:
        self.state = state

    def render(self, engine: Engine, n: int) -> Chunk:
        volts = np.stack([d.hold(n).voltage_v for d in engine.drivers.values()])
        return engine.chunk(volts, None)


class RampJob(Job):
    """Ramp every axis linearly to a voltage (the safe values by default), then hold."""

    def __init__(
        self, engine: Engine, target_v: dict[str, float] | None, rate_v_per_s: float, state: EngineState
    ):
        self.state = state
        volts = []
        for name, d in engine.drivers.items():
            goal = d.config.safe_voltage_v if target_v is None else target_v.get(name, d.voltage_v)
            volts.append(d.ramp_to(goal, rate_v_per_s, engine.rate_hz))
        length = max(v.size for v in volts)
        self._volts = np.stack([np.concatenate([v, np.full(length - v.size, v[-1])]) for v in volts])
        self._pos = 0

    def render(self, engine: Engine, n: int) -> Chunk:
        take = min(n, self._volts.shape[1] - self._pos)
        out = self._volts[:, self._pos : self._pos + take]
        self._pos += take
        self.done = self._pos >= self._volts.shape[1]
        return engine.chunk(out, None)


class MoveJob(Job):
    """A slew-limited move in position (through the inverse model), then done."""

    state: EngineState = "moving"

    def __init__(self, engine: Engine, goal_um: dict[str, float], speed_um_per_s: float) -> None:
        start = np.array([d.position_um for d in engine.drivers.values()])
        end = np.array([goal_um.get(name, start[i]) for i, name in enumerate(engine.drivers)])
        self._path = move_profile(start, end, speed_um_per_s, engine.rate_hz)
        self._moving = np.abs(end - start) > 0
        self._pos = 0

    def render(self, engine: Engine, n: int) -> Chunk:
        take = min(n, self._path.shape[1] - self._pos)
        targets = self._path[:, self._pos : self._pos + take]
        self._pos += take
        self.done = self._pos >= self._path.shape[1]
        volts = np.empty_like(targets)
        for i, d in enumerate(engine.drivers.values()):
            if self._moving[i]:
                volts[i] = engine.drive(d, d.corrected(targets[i]))
            else:
                volts[i] = d.hold(take).voltage_v
        return engine.chunk(volts, targets)


class ScanJob(Job):
    """A scan along a :class:`~piezod.trajectory.Trajectory`: move to its start, settle, scan
    (recorded), then hold at the end."""

    state: EngineState = "scanning"

    def __init__(self, engine: Engine, request: ScanRequest, trajectory: Trajectory) -> None:
        self.request = request
        self._traj = trajectory
        # Settling: the trajectory's unrecorded lead-in (a raster: SETTLE_LINES on the first row).
        self._settle: Trajectory | None = trajectory.settling()
        self._name = request.name or "scan"
        self.label = engine.label_id(self._name)
        engine.set_label_note(self.label, None)
        # Changes (ctl change) start a new experiment "<name>.<part>" at the line where they apply.
        self._part = 1
        self._scanned = False
        self._change_text: list[str] = []
        self._plans = engine.plans_for(trajectory)
        self._plan_key: object = trajectory.key
        for name, plan in self._plans.items():
            engine.drivers[name].use_plan(plan)
        speed = max(trajectory.speed_um_per_s() * MOVE_SPEED_FACTOR, 1.0)
        self._move: MoveJob | None = MoveJob(engine, trajectory.start_um(), speed)

    def change(self, engine: Engine, change: ScanChange) -> None:
        updates = change.model_dump(exclude_none=True)
        engine.plans_for(self._traj.changed(**updates))  # refuse before it takes effect
        self._traj.change(**updates)
        self._change_text.append(" ".join(f"{k}={v:g}" for k, v in updates.items()))

    def _new_experiment(self, engine: Engine, start_index: int) -> None:
        """New parameters took effect at ``start_index``: a new experiment, noted in the recording."""
        if self._scanned:
            self._part += 1
            self.label = engine.label_id(f"{self._name}.{self._part}")
        engine.set_label_note(
            self.label,
            f"change: experiment {engine.label_names(np.array([self.label]))[0]} from "
            f"t = {start_index / engine.rate_hz:.6f} s: {'; '.join(self._change_text)} "
            f"(now {self._traj.describe()})",
        )
        self._change_text = []

    def render(self, engine: Engine, n: int) -> Chunk:
        if self._move is not None:
            chunk = self._move.render(engine, n)
            if self._move.done:
                self._move = None
            return chunk
        settling = self._settle is not None
        traj = self._settle if self._settle is not None else self._traj
        change_at = None if settling else self._traj.pending_index
        if change_at is not None and change_at > self._traj.next_index:
            n = min(n, change_at - self._traj.next_index)  # a block never spans a change
        block = traj.next_block(n)
        if self._settle is not None and self._settle.done:
            self._settle = None
        m = block.x_um.size
        if m == 0:
            self.done = self._settle is None and self._traj.done
            return engine.chunk(np.empty((len(engine.drivers), 0)), None)
        if self._plan_key is not self._traj.key:
            self._plan_key = self._traj.key
            self._plans = engine.plans_for(self._traj)
            for name, plan in self._plans.items():
                engine.drivers[name].use_plan(plan)
            if not settling:
                self._new_experiment(engine, engine.render_index)
        targets = np.full((len(engine.drivers), m), np.nan)
        volts = np.empty((len(engine.drivers), m))
        for i, (name, d) in enumerate(engine.drivers.items()):
            if name in ("x", "y"):
                tgt = block.x_um if name == "x" else block.y_um
                targets[i] = tgt
                plan = self._plans.get(name)
                scale = engine.tracked_scale(name) if self.request.correction else 1.0
                if scale != 1.0 and plan is not None:
                    # the stage is `scale` times as sensitive as the model: shorten the travel
                    tgt = plan.center_um + (tgt - plan.center_um) / scale
                if self.request.correction or plan is None:
                    volts[i] = engine.drive(d, d.corrected(tgt))
                else:
                    volts[i] = engine.drive(d, d.linear(tgt, plan))
            else:
                volts[i] = d.hold(m).voltage_v
        self.done = self._settle is None and self._traj.done
        if settling:
            return Chunk(
                volts, targets, np.full(m, -1, dtype=np.int64), block.fast_direction, np.zeros(m, bool)
            )
        record = np.full(m, self.request.record)
        self._scanned = True
        return Chunk(
            volts, targets, block.line, block.fast_direction, record, self.label, self.request.correction
        )

    @property
    def trajectory(self) -> Trajectory:
        return self._traj

    @property
    def line(self) -> int:
        return max(0, self._traj.line)


@dataclass(frozen=True, slots=True)
class Segment:
    """One piece of a voltage program: samples for one axis, labelled, recorded or not."""

    volts: FloatArray
    label: str
    record: bool = True


class ProgramJob(Job):
    """Play voltage segments on one axis (others hold), each preceded by a ramp to its start.

    This is how a calibration frame runs: the thesis's uncorrected triangles, settling loops
    unrecorded, then the recorded loops, each experiment labelled.
    """

    state: EngineState = "scanning"

    def __init__(self, engine: Engine, axis: str, segments: list[Segment], ramp_v_per_s: float) -> None:
        if axis not in engine.drivers:
            raise SafetyError(f"the scanner has no axis {axis!r}")
        lo, hi = engine.drivers[axis].limits
        for seg in segments:
            if seg.volts.size == 0 or not (np.all(seg.volts >= lo) and np.all(seg.volts <= hi)):
                raise SafetyError(f"segment {seg.label!r}: voltages outside [{lo:g}, {hi:g}] V or empty")
        self.axis = axis
        self._axis_index = list(engine.drivers).index(axis)
        self._segments = list(segments)
        self._ramp = ramp_v_per_s
        self._current: FloatArray | None = None
        self._current_seg: Segment | None = None
        self._pos = 0
        self._label = -1

    def _advance(self, engine: Engine) -> bool:
        if not self._segments:
            return False
        seg = self._segments.pop(0)
        driver = engine.drivers[self.axis]
        start = float(seg.volts[0])
        n_ramp = math.ceil(abs(start - driver.voltage_v) / self._ramp * engine.rate_hz)
        ramp = driver.voltage_v + (start - driver.voltage_v) * np.arange(1, n_ramp + 1) / max(n_ramp, 1)
        self._ramp_len = n_ramp
        self._current = np.concatenate([ramp, seg.volts])
        self._current_seg = seg
        self._pos = 0
        self._label = engine.label_id(seg.label)
        return True

    def render(self, engine: Engine, n: int) -> Chunk:
        if (self._current is None or self._pos >= self._current.size) and not self._advance(engine):
            self.done = True
            return engine.chunk(np.empty((len(engine.drivers), 0)), None)
        assert self._current is not None and self._current_seg is not None
        take = min(n, self._current.size - self._pos)
        piece = self._current[self._pos : self._pos + take]
        in_seg = np.arange(self._pos, self._pos + take) >= self._ramp_len
        self._pos += take
        volts = np.empty((len(engine.drivers), take))
        for i, d in enumerate(engine.drivers.values()):
            volts[i] = engine.drive(d, d.direct(piece)) if i == self._axis_index else d.hold(take).voltage_v
        chunk = engine.chunk(volts, None)
        chunk.record = in_seg & self._current_seg.record
        chunk.label = self._label
        if self._pos >= self._current.size and not self._segments:
            self.done = True
        return chunk


class TargetRing:
    """What the engine commanded per sample index, for matching the sensor readback."""

    def __init__(self, axes: int, capacity: int) -> None:
        self.capacity = capacity
        self.targets = np.full((axes, capacity), np.nan)
        self.line = np.full(capacity, -1, dtype=np.int64)
        self.direction = np.zeros(capacity, dtype=np.int8)
        self.record = np.zeros(capacity, dtype=bool)
        self.recording = np.full(capacity, -1, dtype=np.int64)
        self.label = np.full(capacity, -1, dtype=np.int64)
        self.corrected = np.zeros(capacity, dtype=bool)
        self.hi = 0
        self.lock = threading.Lock()

    def put(self, first: int, chunk: Chunk, recording_id: int) -> None:
        n = chunk.volts.shape[1]
        slots = np.arange(first, first + n) % self.capacity
        with self.lock:
            self.targets[:, slots] = chunk.targets
            self.line[slots] = chunk.line
            self.direction[slots] = chunk.direction
            self.record[slots] = chunk.record
            self.recording[slots] = recording_id if chunk.record.any() else -1
            self.label[slots] = chunk.label
            self.corrected[slots] = chunk.corrected
            self.hi = max(self.hi, first + n)

    def get(self, idx: NDArray[np.int64]) -> tuple[Any, ...]:
        """(targets, line, direction, record, recording id, label id) at the sample indices."""
        slots = idx % self.capacity
        with self.lock:
            known = (idx < self.hi) & (idx >= self.hi - self.capacity)
            return (
                self.targets[:, slots].copy(),
                self.line[slots].copy(),
                self.direction[slots].copy(),
                self.record[slots] & known,
                np.where(known, self.recording[slots], -1),
                self.label[slots].copy(),
                self.corrected[slots].copy(),
            )


@dataclass
class _OpenRecording:
    ident: int
    path: Path
    writer: RecordingWriter
    axes: tuple[str, ...]
    targets: bool
    rows: int = 0
    done: bool = False
    z_monitor_ratio: float | None = None
    labels_seen: set[int] = field(default_factory=set)


@dataclass
class _LineAccumulator:
    line: int = -1
    direction: int = 0
    corrected: bool = False
    target: list[FloatArray] = field(default_factory=list)
    position: list[FloatArray] = field(default_factory=list)


class Recorder(threading.Thread):
    """Appends matched sensor blocks to the open recording; line linearity of the fast axis."""

    def __init__(self, engine: Engine) -> None:
        super().__init__(name="piezod-recorder", daemon=True)
        self.engine = engine
        self.queue: queue.Queue[tuple[MatchedBlock | None, tuple[Any, ...]] | None] = queue.Queue()
        self.recordings: dict[int, _OpenRecording] = {}
        self.lock = threading.Lock()
        self.error: BaseException | None = None
        self._acc = _LineAccumulator()
        self._pending_close: dict[int, int] = {}

    def open(
        self,
        ident: int,
        path: Path,
        metadata: dict[str, object],
        axes: tuple[str, ...],
        *,
        targets: bool = True,
        z_monitor_ratio: float | None = None,
    ) -> None:
        height = ("z_voltage",) if z_monitor_ratio is not None else ()
        target = ("target",) if targets else ()
        columns = ("t", "voltage", "position", *target, *height, "axis", "experiment")
        writer = RecordingWriter(path, columns, metadata=metadata, append=False)
        with self.lock:
            self.recordings[ident] = _OpenRecording(
                ident, path, writer, axes, targets, z_monitor_ratio=z_monitor_ratio
            )

    def run(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                self.queue.task_done()
                break
            block, meta = item
            try:
                if block is None:
                    self._pending_close[int(meta[1])] = int(meta[2])
                else:
                    if self.error is None:
                        self._write(block, meta)
                    last = int(block.indices[-1]) if block.indices.size else -1
                    for ident, end in list(self._pending_close.items()):
                        if last >= end - 1:
                            del self._pending_close[ident]
                            self._close(ident)
            except (OSError, PiezodError, ValueError) as exc:
                log.exception("recorder failed")
                self.error = exc
                self.engine.fault("host", "RECORDING", f"recording failed, recording stopped: {exc}")
            finally:
                self.queue.task_done()
        with self.lock:
            for rec in self.recordings.values():
                rec.writer.close()

    def _close(self, ident: int) -> None:
        with self.lock:
            rec = self.recordings.pop(ident, None)
        if rec is not None:
            rec.writer.close()
            log.info("recording %s closed (%d rows)", rec.path, rec.rows)

    def _write(self, block: MatchedBlock, meta: tuple[Any, ...]) -> None:
        targets, line, direction, record, rec_id, label, corrected = meta
        rate = self.engine.rate_hz
        t = block.indices / rate
        self._line_stats(block, targets, line, direction, corrected)
        if not record.any():
            return
        for ident in np.unique(rec_id[record]):
            with self.lock:
                rec = self.recordings.get(int(ident))
            if rec is None:
                continue
            rows = np.flatnonzero(record & (rec_id == ident))
            z_all = None
            if rec.z_monitor_ratio is not None and "z" in block.axes:
                z_all = block.position_um[block.axes.index("z")] * rec.z_monitor_ratio
            # one run per experiment, so that a change's note precedes its experiment's rows
            for run in np.split(rows, np.flatnonzero(np.diff(label[rows])) + 1):
                lab = int(label[run[0]])
                if lab not in rec.labels_seen:
                    rec.labels_seen.add(lab)
                    note = self.engine.label_note(lab)
                    if note is not None:
                        rec.writer.comment(note)
                names = self.engine.label_names(label[run])
                z_voltage = None
                if rec.z_monitor_ratio is not None:
                    z_voltage = z_all[run] if z_all is not None else np.full(run.size, np.nan)
                for i, axis in enumerate(block.axes):
                    if axis not in rec.axes:
                        continue
                    rec.writer.write(
                        t[run],
                        block.commanded_v[i, run],
                        block.position_um[i, run],
                        target_um=targets[i, run] if rec.targets else None,
                        axis=axis,
                        experiment=names,
                        z_voltage_v=z_voltage,
                    )
                    rec.rows += int(run.size)

    def _line_stats(
        self,
        block: MatchedBlock,
        targets: FloatArray,
        line: NDArray[np.int64],
        direction: NDArray[np.int8],
        corrected: NDArray[np.bool_],
    ) -> None:
        if "x" not in block.axes:
            return
        ix = block.axes.index("x")
        acc = self._acc
        # Split at changes of (line, direction); finish a trace/retrace when it ends.
        key = line * 4 + (direction + 1)
        cuts = np.flatnonzero(np.diff(key)) + 1
        for seg in np.split(np.arange(key.size), cuts):
            if seg.size == 0:
                continue
            ln, dr = int(line[seg[0]]), int(direction[seg[0]])
            if (ln, dr) != (acc.line, acc.direction):
                self._finish_line()
                acc.line, acc.direction = ln, dr
                acc.target, acc.position = [], []
                acc.corrected = bool(corrected[seg[0]])
            if ln >= 0:
                acc.target.append(targets[ix, seg])
                acc.position.append(block.position_um[ix, seg])

    def _finish_line(self) -> None:
        acc = self._acc
        if acc.line < 0 or not acc.target:
            return
        tgt = np.concatenate(acc.target)
        pos = np.concatenate(acc.position)
        ok = np.isfinite(tgt) & np.isfinite(pos)
        if ok.sum() < 8:
            return
        tgt, pos = tgt[ok], pos[ok]
        nominal = float(tgt.max() - tgt.min())
        if nominal <= 0:
            return
        slope, intercept = np.polyfit(tgt, pos, 1)
        resid = pos - (slope * tgt + intercept)
        measured = slope * nominal
        self.engine.set_line_linearity(
            LineLinearity(
                line=acc.line,
                direction="trace" if acc.direction > 0 else "retrace",
                nonlinearity_pct=float(100.0 * np.std(resid) / measured) if measured else math.inf,
                length_error_pct=float(100.0 * (measured - nominal) / nominal),
            ),
            acc.corrected,
        )


def capped_lead_s(lead_s: float, session: BoardSession, rate_hz: float) -> float:
    """The lead, capped at 60 % of the board FIFO (at high sample rates a long lead does not fit)."""
    caps = session.capabilities
    if caps is None:
        return lead_s
    fit = 0.6 * caps.fifo_depth_samples / rate_hz
    if lead_s > fit:
        log.info(
            "lead %.0f ms capped at %.0f ms: the board FIFO holds %d samples",
            1e3 * lead_s,
            1e3 * fit,
            caps.fifo_depth_samples,
        )
        return fit
    return lead_s


class Engine:
    """The daemon's streaming engine (implements :class:`~piezod.service.schemas.EngineControl`).

    Parameters
    ----------
    config
        The scanner.
    url
        The board (pyserial URL / device / ``usb://``).
    recording_dir
        Where recordings are written (created if needed).
    settings
        Link settings (default from the config).
    on_fault
        Called with every new fault (e.g. the API's event hub).
    """

    def __init__(
        self,
        config: ScannerConfig,
        url: str,
        *,
        recording_dir: Path | None = None,
        settings: LinkSettings | None = None,
        on_fault: Callable[[FaultInfo], None] | None = None,
    ) -> None:
        self.config = config
        self.url = url
        self.rate_hz = float(config.sample_rate_hz)
        self.recording_dir = Path(
            recording_dir if recording_dir is not None else config.service.recording_dir
        )
        self.recording_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings or LinkSettings.from_config(config)
        self.on_fault = on_fault
        self.drivers: dict[str, AxisDriver] = {
            name: AxisDriver(name, axis, self.rate_hz) for name, axis in config.axes.items()
        }
        self._lock = threading.RLock()
        self._job: Job = HoldJob("starting")
        self._queue: deque[Job] = deque()
        self._state: EngineState = "starting"
        self._t0 = time.monotonic()
        self._faults: deque[FaultInfo] = deque(maxlen=200)
        self._fault_last: dict[tuple[str, str], float] = {}
        self._fault_counts: dict[tuple[str, str], int] = {}
        self._fault_latched = False
        self._index = 0
        self._ring = TargetRing(len(self.drivers), max(1 << 16, int(self.rate_hz * 8)))
        self._recorder = Recorder(self)
        self._recording_id = -1
        self._recording_name: str | None = None
        self._next_recording = 0
        self._last_line: LineLinearity | None = None
        self._session: BoardSession | None = None
        self._streamer: Streamer | None = None
        self._clamped = 0
        self._closing = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._idle_cb: list[Callable[[], None]] = []
        svc = config.service
        self._trackers: dict[str, SensitivityTracker] = (
            {
                "x": SensitivityTracker(
                    gain=svc.sensitivity_gain,
                    max_step=svc.sensitivity_max_step_pct / 100.0,
                    limit=svc.sensitivity_limit_pct / 100.0,
                )
            }
            if svc.sensitivity_tracking and "x" in config.axes
            else {}
        )
        self._labels: list[str] = []
        self._label_ids: dict[str, int] = {}
        self._label_notes: dict[int, str] = {}
        #: Board sample index of the first sample the current job's render() produces.
        self.render_index = 0

    # -- lifecycle ------------------------------------------------------------------------------

    def open(self, timeout_s: float = 10.0) -> None:
        """Connect to the board, configure it, start streaming (hold), start the recorder."""
        self._recorder.start()
        self._session = BoardSession.open(
            self.url,
            config=self.config,
            settings=self.settings,
            on_event=self._on_link_event,
            timeout_s=timeout_s,
        )
        plan = self._session.plan
        assert plan is not None
        order = list(plan.axes)
        if order != list(self.drivers):
            self.drivers = {name: self.drivers[name] for name in order}
            self._ring = TargetRing(len(self.drivers), self._ring.capacity)
        self._start_stream()
        self._supervisor = threading.Thread(target=self._supervise, name="piezod-supervisor", daemon=True)
        self._supervisor.start()

    def _start_stream(self) -> None:
        assert self._session is not None
        lead = capped_lead_s(self.config.service.lead_ms / 1000.0, self._session, self.rate_hz)
        block = max(1, round(self.rate_hz * self.config.service.block_ms / 1000.0))
        self._streamer = Streamer(
            self._session, self, lead_s=lead, block_samples=block, on_block=self._on_block
        )
        with self._lock:
            self._job = HoldJob("idle")
            self._queue.clear()
            if self._state in ("starting", "disconnected"):
                self._state = "idle" if not self._fault_latched else "fault"
        self._streamer.start(self._index)

    def _supervise(self) -> None:
        """Restart the stream after an underrun or a reconnect; report the reason."""
        while not self._closing.is_set():
            streamer = self._streamer
            if streamer is None or not streamer.wait(0.2):
                continue
            if self._closing.is_set():
                return
            run = streamer.stats.runs[-1] if streamer.stats.runs else None
            how = run.ended_by if run is not None else None
            try:
                streamer.check()
            except PiezodError as exc:
                self.fault("host", "STREAM", f"streaming ended: {exc}")
            if how not in (None, "stop"):
                self.fault("host", "STREAM_END", f"streaming run ended by {how}")
            self._end_recording()
            with self._lock:
                self._state = "disconnected" if how == "link" else "fault"
                self._fault_latched = True
            # Wait for the session to be usable again, then stream (hold) again.
            session = self._session
            if session is None:
                return
            while not self._closing.is_set() and not session.connected:
                time.sleep(0.1)
            if self._closing.is_set():
                return
            self._index = max(self._index, streamer.next_index) + int(self.rate_hz)
            try:
                # After any abnormal end the outputs go to the safe values (the board's ramp after a
                # watchdog, or the reconfiguration here), and the model forgets the history.
                session.prepare_restart(timeout_s=10.0)
                for d in self.drivers.values():
                    d.reset(d.config.safe_voltage_v)
                self._start_stream()
            except (LinkError, PiezodError) as exc:
                self.fault("link", "RESTART", f"cannot restart streaming: {exc}")
                time.sleep(0.5)

    def close(self, *, ramp: bool = True, timeout_s: float = 20.0) -> None:
        """Ramp the outputs to the safe values, stop streaming, close recordings and the link."""
        streamer, session = self._streamer, self._session
        if ramp and streamer is not None and streamer.running:
            done = threading.Event()
            with self._lock:
                self._queue.clear()
                ramp_job = RampJob(self, None, self.config.service.ramp_rate_v_per_s, "stopping")
                self._job = ramp_job
                self._state = "stopping"
                self._idle_cb.append(done.set)
            done.wait(timeout_s)
        self._closing.set()
        try:
            if streamer is not None and streamer.running:
                streamer.finish(timeout_s=timeout_s)
        finally:
            self._end_recording()
            self._recorder.queue.put(None)
            self._recorder.join(timeout=10.0)
            if session is not None:
                session.close(ramp_to_safe=True)

    # -- the block source (streamer thread) ------------------------------------------------------

    def next_block(self, n: int) -> FloatArray:
        """The next ``n`` samples for the board: volts ``(axes, n)``."""
        out = np.empty((len(self.drivers), n))
        filled = 0
        t_call = time.monotonic()
        with self._lock:
            t_locked = time.monotonic()
            while filled < n:
                job = self._job
                self.render_index = self._index + filled
                try:
                    chunk = job.render(self, n - filled)
                except (ModelError, SafetyError) as exc:
                    self.fault("host", "MODEL", f"{type(job).__name__}: {exc}")
                    self._job = RampJob(self, None, self.config.service.ramp_rate_v_per_s, "fault")
                    self._fault_latched = True
                    continue
                m = chunk.volts.shape[1]
                if m:
                    out[:, filled : filled + m] = chunk.volts
                    self._ring.put(self._index + filled, chunk, self._recording_id)
                    filled += m
                if job.done:
                    self._job_finished(job, self._index + filled)
        t_done = time.monotonic()
        if t_done - t_call > SLOW_BLOCK_S:
            # a block must be computed in a fraction of the lead; say where the time went
            log.warning(
                "slow block: %d samples took %.0f ms (%.0f ms waiting for the engine lock), job %s",
                n,
                1e3 * (t_done - t_call),
                1e3 * (t_locked - t_call),
                type(self._job).__name__,
            )
        self._index += n
        return out

    def _job_finished(self, job: Job, end_index: int) -> None:
        if isinstance(job, ScanJob | ProgramJob):
            self._end_recording(end_index)
        if self._queue:
            self._job = self._queue.popleft()
        else:
            state: EngineState = "fault" if self._fault_latched else "idle"
            self._job = HoldJob(state)
            for cb in self._idle_cb:
                cb()
            self._idle_cb.clear()
        self._state = self._job.state

    def chunk(self, volts: FloatArray, targets: FloatArray | None) -> Chunk:
        """A chunk without scan lines (hold, move, ramp)."""
        n = volts.shape[1]
        return Chunk(
            volts,
            np.full(volts.shape, np.nan) if targets is None else targets,
            np.full(n, -1, dtype=np.int64),
            np.zeros(n, dtype=np.int8),
            np.zeros(n, dtype=bool),
        )

    def drive(self, driver: AxisDriver, out: Any) -> FloatArray:
        """Account for clamping (a fault) and return the voltages."""
        if out.clamped:
            self._clamped += out.clamped
            self.fault(
                "host", "LIMIT", f"axis {driver.name}: {out.clamped} samples clamped to the voltage limits"
            )
        volts: FloatArray = out.voltage_v
        return volts

    # -- scan planning ---------------------------------------------------------------------------

    def plans_for(self, trajectory: Trajectory) -> dict[str, PeriodicPlan | None]:
        """The steady loop of each axis the trajectory moves; refuses what the stage cannot do.

        Raises
        ------
        RangeUnreachableError, SafetyError
            With the reason (range beyond the limits, slew rate exceeded, missing axis).
        """
        plans: dict[str, PeriodicPlan | None] = {}
        for name, motion in trajectory.motion().items():
            if name not in self.drivers:
                if motion is not None:
                    raise SafetyError(f"the scan needs axis {name!r}, which the scanner config does not have")
                continue
            if motion is None:
                plans[name] = None
                continue
            travel, f = motion.travel_um, motion.frequency_hz
            d = self.drivers[name]
            plan = d.plan(travel, f, motion.center_um)
            need = d.peak_slew_v_per_s(plan)
            if need > d.config.slew_rate_v_per_s:
                raise SafetyError(
                    f"axis {name}: {travel:.4g} um at {f:.4g} Hz needs up to {need:.4g} V/s, above the "
                    f"slew limit {d.config.slew_rate_v_per_s:g} V/s; scan slower or smaller"
                )
            plans[name] = plan
        return plans

    # -- EngineControl ---------------------------------------------------------------------------

    def status(self) -> Status:
        """A snapshot (cheap, thread-safe)."""
        with self._lock:
            job = self._job
            state = self._state
            scan = job.request if isinstance(job, ScanJob) else None
            line = job.line if isinstance(job, ScanJob) else None
        session = self._session
        fifo_ms = 0.0
        underruns = crc = dropped = 0
        if session is not None:
            st = session.status
            if st is not None and st.last_played_index != NO_INDEX:
                fifo_ms = 1000.0 * max(0, st.write_index - st.last_played_index - 1) / self.rate_hz
            c = session.counters()
            underruns, crc, dropped = c.underruns, c.crc_errors, c.frames_dropped_board
        return Status(
            state=state,
            scanner=self.config.name,
            uptime_s=time.monotonic() - self._t0,
            sample_rate_hz=self.rate_hz,
            sample_index=self._index,
            scan=scan,
            line=line,
            fifo_level_ms=fifo_ms,
            lead_target_ms=self.config.service.lead_ms,
            underruns=underruns,
            crc_errors=crc,
            frames_dropped=dropped,
            faults=list(self._faults)[-20:],
            last_line=self._last_line,
            position_um={n: d.position_um for n, d in self.drivers.items()},
            voltage_v={n: d.voltage_v for n, d in self.drivers.items()},
            recording=self._recording_name,
            sensitivity_scale={a: t.scale for a, t in self._trackers.items()},
        )

    def check_scan(self, request: ScanRequest) -> None:
        """Refuse a scan the stage cannot do (with the reason)."""
        self.plans_for(RasterTrajectory.from_request(request, self.rate_hz))

    def start_scan(self, request: ScanRequest, *, path: Path | None = None) -> Status:
        """Start a scan; recorded to ``path`` or to the recording directory."""
        trajectory = RasterTrajectory.from_request(request, self.rate_hz)
        self.plans_for(trajectory)
        with self._lock:
            if self._state not in ("idle",):
                raise EngineStateError(f"cannot start a scan while {self._state}")
            job = ScanJob(self, request, trajectory)
            if request.record:
                self._begin_recording(request, trajectory, path)
            self._job = job
            self._state = "scanning"
        return self.status()

    def change_scan(self, change: ScanChange) -> Status:
        """Change the running scan at the next line."""
        with self._lock:
            job = self._job
            if not isinstance(job, ScanJob):
                raise EngineStateError(f"no scan is running (state {self._state})")
            job.change(self, change)
        return self.status()

    def stop(self) -> Status:
        """Stop scanning / moving and hold; clears a latched fault."""
        with self._lock:
            self._queue.clear()
            if isinstance(self._job, ScanJob):
                self._end_recording()
            self._fault_latched = False
            self._job = HoldJob("idle")
            self._state = "idle"
        return self.status()

    def check_move(self, request: MoveRequest) -> None:
        """Refuse a move outside the axes' reach."""
        for name, value in (("x", request.x_um), ("y", request.y_um), ("z", request.z_um)):
            if value is None:
                continue
            if name not in self.drivers:
                raise SafetyError(f"the scanner has no axis {name!r}")
            d = self.drivers[name]
            lo, hi = d.limits
            reach = (d.params.b_um_per_v * lo * 0.98, d.params.b_um_per_v * hi * 0.98)
            if not reach[0] <= value <= reach[1]:
                raise SafetyError(
                    f"{name} = {value:g} um is outside the reach of axis {name} "
                    f"(about {reach[0]:.4g} .. {reach[1]:.4g} um inside [{lo:g}, {hi:g}] V)"
                )

    def move(self, request: MoveRequest) -> Status:
        """Move to a position (slew-limited), then hold."""
        self.check_move(request)
        goal = {
            k: v for k, v in (("x", request.x_um), ("y", request.y_um), ("z", request.z_um)) if v is not None
        }
        with self._lock:
            if self._state not in ("idle", "moving"):
                raise EngineStateError(f"cannot move while {self._state}")
            self._job = MoveJob(self, goal, request.speed_um_per_s)
            self._state = "moving"
        return self.status()

    def recordings(self) -> list[RecordingInfo]:
        """The recordings in the recording directory."""
        out = []
        for p in sorted(self.recording_dir.glob("*.csv")):
            try:
                st = p.lstat()
            except FileNotFoundError:  # removed since the listing
                continue
            if not stat.S_ISREG(st.st_mode):  # symlinks (dangling or not), directories: not served
                continue
            out.append(
                RecordingInfo(
                    name=p.name,
                    size_bytes=st.st_size,
                    modified_unix=st.st_mtime,
                    complete=p.name != self._recording_name,
                )
            )
        return out

    def recording_path(self, name: str) -> Path:
        """Path of a recording by name."""
        p = self.recording_dir / name
        if "/" in name or name.startswith(".") or not p.is_file():
            raise FileNotFoundError(name)
        return p

    def start_program(
        self, axis: AxisName, segments: list[Segment], path: Path, metadata: Mapping[str, object]
    ) -> Status:
        """Play a voltage program on ``axis`` (e.g. a calibration frame), recorded to ``path``."""
        job = ProgramJob(self, axis, segments, self.config.service.ramp_rate_v_per_s)
        with self._lock:
            if self._state != "idle":
                raise EngineStateError(f"cannot start a program while {self._state}")
            self._next_recording += 1
            ident = self._next_recording
            meta = {"scanner": self.config.name, "sample_rate_hz": self.rate_hz, **metadata}
            self._recorder.open(ident, path, meta, (axis,), targets=False)
            self._recording_id = ident
            self._recording_name = path.name
            self._job = job
            self._state = "scanning"
        return self.status()

    def set_axis_model(self, axis: AxisName, config: AxisConfig) -> None:
        """Use new model parameters on ``axis`` from now on (the model state carries over)."""
        with self._lock:
            old = self.drivers[axis]
            new = AxisDriver(axis, config, self.rate_hz)
            new.adopt_state(old)
            self.drivers[axis] = new

    def healthy(self) -> bool:
        """Streaming runs and the board reports in time (the systemd watchdog is pinged only then)."""
        streamer, session = self._streamer, self._session
        if streamer is None or session is None or not streamer.running or not session.connected:
            return False
        with self._lock:
            return self._state not in ("disconnected", "starting")

    def wait_healthy(self, timeout_s: float = 15.0) -> bool:
        """Wait until streaming runs again (e.g. after the supervisor's restart following a fault)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.healthy():
                return True
            time.sleep(0.05)
        return False

    # -- waiting (piezod scan) -------------------------------------------------------------------

    def wait_idle(self, timeout_s: float | None = None, poll_s: float = 0.05) -> EngineState:
        """Block until the engine is idle / fault / disconnected (or the timeout)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            with self._lock:
                state = self._state
            if state in ("idle", "fault", "disconnected"):
                return state
            if deadline is not None and time.monotonic() > deadline:
                return state
            time.sleep(poll_s)

    def wait_recorded(self, timeout_s: float = 5.0) -> None:
        """Wait until the board played everything computed so far and its readback is written."""
        target = self._index
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self._session.status if self._session is not None else None
            if st is not None and st.last_played_index != NO_INDEX and st.last_played_index + 1 >= target:
                break
            time.sleep(0.02)
        # SENSOR frames follow the played samples within a few status periods.
        time.sleep(5 * self.settings.status_period_ms / 1000.0 + 0.05)
        self._recorder.queue.join()

    # -- recordings ------------------------------------------------------------------------------

    def _begin_recording(self, request: ScanRequest, trajectory: Trajectory, path: Path | None) -> None:
        name = request.name or time.strftime("scan-%Y%m%d-%H%M%S")
        if path is None:
            path = self.recording_dir / (name if name.endswith(".csv") else name + ".csv")
        self._next_recording += 1
        ident = self._next_recording
        meta: dict[str, object] = {
            "scanner": self.config.name,
            "range_um": request.range_um,
            "line_rate_hz": request.line_rate_hz,
            "lines": request.lines,
            "offset_x_um": request.offset_x_um,
            "offset_y_um": request.offset_y_um,
            "rotation_deg": request.rotation_deg,
            "overscan": request.overscan,
            "sample_rate_hz": self.rate_hz,
            "pixels": request.pixels,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "config_sha256": hashlib.sha256(self.config.model_dump_json().encode()).hexdigest(),
        }
        fast = self.config.axes["x"]
        if request.correction:
            section = fast.dynamic if fast.model == "dynamic" and fast.dynamic is not None else fast.thesis
            meta["model"] = fast.model
            meta["model_params"] = json.dumps(section.model_dump(mode="json"), sort_keys=True)
        else:
            meta["model"] = "none"
        mic = self.config.microscope
        if mic is not None:
            meta["position_sensor"] = "yes" if mic.position_sensor else "no"
            meta["z_monitor_ratio"] = mic.z_monitor_ratio
        axes = tuple(a for a, plan in self.plans_for(trajectory).items() if plan is not None) or ("x",)
        axes = tuple(a for a in axes if mic is None or a != "z")
        meta["correction"] = self.correction_label(axes) if request.correction else "none"
        uncal = [a for a in axes if a not in calibrated_axes(self.config)]
        meta["calibrated"] = "no (axes " + ", ".join(uncal) + ")" if uncal else "yes"
        self._recorder.open(
            ident, path, meta, axes, z_monitor_ratio=None if mic is None else mic.z_monitor_ratio
        )
        self._recording_id = ident
        self._recording_name = path.name

    def correction_label(self, axes: tuple[str, ...]) -> str:
        """The model correcting ``axes`` now: ``dynamic``, ``thesis``, or per axis ``x=dynamic y=thesis``."""
        with self._lock:
            models = {a: self.drivers[a].model.kind for a in axes if a in self.drivers}
        if len(set(models.values())) == 1:
            return next(iter(models.values()))
        return " ".join(f"{a}={m}" for a, m in models.items())

    def _end_recording(self, end_index: int | None = None) -> None:
        """Close the recording once the readback up to ``end_index`` (default: all computed) is in."""
        if self._recording_id >= 0:
            end = self._index if end_index is None else end_index
            self._recorder.queue.put((None, ("close", self._recording_id, end)))
            self._recording_id = -1
            self._recording_name = None

    # -- readback and events (link reader thread) ------------------------------------------------

    def _on_block(self, block: MatchedBlock) -> None:
        self._recorder.queue.put((block, self._ring.get(block.indices)))

    def label_id(self, name: str) -> int:
        """The id of an experiment label (registered on first use)."""
        with self._lock:
            if name not in self._label_ids:
                self._label_ids[name] = len(self._labels)
                self._labels.append(name)
            return self._label_ids[name]

    def set_label_note(self, ident: int, note: str | None) -> None:
        """A comment the recorder writes before the first row of experiment ``ident`` (None: none)."""
        with self._lock:
            if note is None:
                self._label_notes.pop(ident, None)
            else:
                self._label_notes[ident] = note

    def label_note(self, ident: int) -> str | None:
        """The comment for experiment ``ident`` (see :meth:`set_label_note`)."""
        with self._lock:
            return self._label_notes.get(ident)

    def label_names(self, ids: NDArray[np.int64]) -> NDArray[np.str_]:
        """Label strings of label ids (``""`` for none)."""
        with self._lock:
            names = np.array([*self._labels, ""], dtype=str)
        return names[np.where(ids >= 0, ids, len(names) - 1)]

    def set_line_linearity(self, value: LineLinearity, corrected: bool) -> None:
        """Called by the recorder when a line of the fast axis completes (feeds the tracker)."""
        self._last_line = value
        tracker = self._trackers.get("x")
        if corrected and tracker is not None:
            # the line was scanned with the scale in force then: its error is what remains
            tracker.update(1.0 + value.length_error_pct / 100.0)

    def tracked_scale(self, axis: str) -> float:
        """The tracked sensitivity of ``axis`` relative to its model (1 without tracking)."""
        tracker = self._trackers.get(axis)
        return 1.0 if tracker is None else tracker.scale

    def fault(self, source: FaultSource, code: str, message: str, index: int | None = None) -> None:
        """Record a fault (and tell the listener); repeats of one kind within a second are counted only."""
        now = time.monotonic() - self._t0
        key = (source, code)
        self._fault_counts[key] = self._fault_counts.get(key, 0) + 1
        last = self._fault_last.get(key)
        if last is not None and now - last < FAULT_REPEAT_S:
            return
        self._fault_last[key] = now
        info = FaultInfo(time_s=now, source=source, code=code, message=message, index=index)
        self._faults.append(info)
        log.warning("fault %s/%s: %s", source, code, message)
        if self.on_fault is not None:
            self.on_fault(info)

    def _on_link_event(self, ev: LinkEvent) -> None:
        if isinstance(ev, BoardFault):
            index = None if ev.fault.index == NO_INDEX else int(ev.fault.index)
            self.fault("board", ev.code.name, str(ev.fault), index)
        elif isinstance(ev, HostLimitFault):
            self.fault(
                "host",
                "LIMIT",
                f"{ev.count} samples of axis {ev.axis} clamped (worst {ev.worst_v:.4g} V)",
                ev.first_index,
            )
        elif isinstance(ev, LinkDown | LinkLost):
            with self._lock:
                self._state = "disconnected"
            self.fault("link", type(ev).__name__.upper(), str(ev.error))
        elif isinstance(ev, Reconnected):
            self.fault(
                "link",
                "RECONNECTED",
                f"board back after {ev.downtime_s:.1f} s (watchdog fired: {ev.watchdog_fired})",
            )
        elif isinstance(ev, SensorGap) and not ev.explained:
            self.fault(
                "link",
                "SENSOR_GAP",
                f"{ev.missing_rows} sensor rows missing at {ev.expected_index}",
                ev.expected_index,
            )
