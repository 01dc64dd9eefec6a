"""The streaming engine: scan jobs -> inverse model -> voltage blocks -> board, sensor -> recordings.

The board owns the sample clock. The engine is the :class:`~piezod.link.streamer.BlockSource`
of a :class:`~piezod.link.board.Board` (today the framed-serial
:class:`~piezod.link.board.SerialBoard`, whose :class:`~piezod.link.streamer.Streamer` asks
for blocks ahead of the clock, the lead of at least 100 ms, and keeps the board FIFO filled by
credits). Scans come from a :class:`~piezod.trajectory.Trajectory` (the raster today). Every
block is computed in numpy by the current *job* (hold, move, scan, ramp to safe) through the per-axis
:class:`~piezod.service.axes.AxisDriver`, whose model state carries over from job to job.

The stream runs continuously while the board is connected (idle = hold the last voltages), so
sample indices, and the session time ``t = index / rate`` of the recordings, are continuous.
The sensor readback arrives on the link's reader thread, is paired with the targets the engine
remembers per sample index, and goes to a recorder thread that appends it to the recording
(flushed per block, so a crash loses at most the last block) and computes the linearity of the
last complete line.

Safety: every voltage is clamped to the axis limits and slew-limited before it leaves the host,
by the driver and again by :meth:`~piezod.link.board.Board.limit` for any board (clamping is
reported as a fault); ``stop()`` holds; a fault, a lost link and shutdown ramp the
outputs to the safe values (the board also ramps by itself when the host's heartbeat stops).

The jobs live in :mod:`piezod.service.jobs`, the recorder and the recording header in
:mod:`piezod.service.recorder`, the scan's line / frame events and per-frame images in
:mod:`piezod.service.scan_events`, the fault log in :mod:`piezod.service.faults`, the check of a
scan's start on copies of the axis drivers in :mod:`piezod.service.shadow`, the count of the
readback at the position sensor's full scale (per job; not a fault) in
:mod:`piezod.service.clipping`.
"""

from __future__ import annotations

import logging
import math
import stat
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.config import AxisConfig, AxisName, ScannerConfig, calibrated_axes, recorded_age_s
from piezod.errors import (
    EngineStateError,
    LinkError,
    ModelError,
    PiezodError,
    RecordingError,
    SafetyError,
)
from piezod.link.board import Board, open_board
from piezod.link.session import (
    LinkDown,
    LinkEvent,
    LinkLost,
    LinkSettings,
)
from piezod.link.streamer import MatchedBlock
from piezod.model import kernels
from piezod.readback import SENSOR_RANGE_KEY
from piezod.service import cpuwait, gcwatch
from piezod.service.axes import AxisDriver, PeriodicPlan, plan_axes
from piezod.service.clipping import SensorClips
from piezod.service.faults import FaultLog, FaultSource, link_event_fault
from piezod.service.jobs import (
    MAX_MOVE_S,
    Chunk,
    HoldJob,
    Job,
    MoveJob,
    ProgramJob,
    RampJob,
    ScanJob,
    Segment,
)
from piezod.service.recorder import Recorder, TargetRing, scan_metadata
from piezod.service.scan_events import ScanEvents
from piezod.service.schemas import (
    EngineState,
    FaultInfo,
    LineLinearity,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanEvent,
    ScanRequest,
    Status,
)
from piezod.service.shadow import check_scan_start
from piezod.service.sync import SyncSchedule
from piezod.service.tracking import SensitivityTracker
from piezod.trajectory import RasterTrajectory, Trajectory

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: A block computation slower than this (s) is logged with its cause.
SLOW_BLOCK_S = 0.05


#: Samples at the end of the latest readback averaged by :meth:`Engine.measured_at_rest`.
REST_READ_SAMPLES = 50


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
        on_scan_event: Callable[[ScanEvent], None] | None = None,
        write_images: bool = False,
    ) -> None:
        self.config = config
        self._uncalibrated: list[str] = sorted(set(config.axes) - calibrated_axes(config))
        self.url = url
        self.rate_hz = float(config.sample_rate_hz)
        self.recording_dir = Path(
            recording_dir if recording_dir is not None else config.service.recording_dir
        )
        self.recording_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings or LinkSettings.from_config(config)
        #: The scan's line / frame events (to ``on_scan_event``) and per-frame images.
        self.scan_events = ScanEvents(on_scan_event, write_images)
        self.drivers: dict[str, AxisDriver] = {
            name: AxisDriver(name, axis, self.rate_hz) for name, axis in config.axes.items()
        }
        self._lock = threading.RLock()
        gcwatch.install()
        self._job: Job = HoldJob("starting")
        self._queue: deque[Job] = deque()
        self._state: EngineState = "starting"
        self._t0 = time.monotonic()
        #: The last faults (to ``on_fault``).
        self.faults = FaultLog(self._t0, on_fault)
        self._fault_latched = False
        self._index = 0
        self._ring = TargetRing(len(self.drivers), max(1 << 16, int(self.rate_hz * 8)))
        #: The sync-output events of the scans (sent when the board has pixel, line and frame outputs).
        self.sync_schedule = SyncSchedule(self._ring.capacity)
        self._recorder = Recorder(self)
        self._recording_id = -1
        self._recording_name: str | None = None
        self._next_recording = 0
        self._last_line: LineLinearity | None = None
        self._board: Board = open_board(url, config, self._on_link_event, self.settings)
        self._clamped = 0
        #: Readback at the position sensor's full scale, per client job and in total.
        self.sensor_clips = SensorClips()
        self._next_job = 0
        self._closing = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._idle_cb: list[Callable[[], None]] = []
        self._last_block: MatchedBlock | None = None
        svc = config.service
        self._trackers: dict[str, SensitivityTracker] = (
            {
                "x": SensitivityTracker(
                    gain=svc.sensitivity_gain,
                    max_step=svc.sensitivity_max_step_pct / 100.0,
                    limit=svc.sensitivity_limit_pct / 100.0,
                    drift_per_s=svc.sensitivity_drift_pct_per_hour / 100.0 / 3600.0,
                    scatter=svc.sensitivity_line_scatter_pct / 100.0,
                ).restarted(recorded_age_s(config, time.time()), 0.0)
            }
            if svc.sensitivity_tracking and "x" in config.axes
            else {}
        )
        self._labels: list[str] = []
        self._label_ids: dict[str, int] = {}
        self._label_notes: dict[int, str] = {}
        #: Board sample index of the first sample the current job's render() produces.
        self.render_index = 0

    @property
    def board(self) -> Board:
        """The board the engine streams to."""
        return self._board

    # -- lifecycle ------------------------------------------------------------------------------

    def _reads_position(self, axis: str) -> bool:
        """Whether the ADC channel of ``axis`` reads a position (a microscope's z reads the monitor)."""
        return self.position_sensor and not (self.config.microscope is not None and axis == "z")

    @property
    def position_sensor(self) -> bool:
        """Whether positions are measured: the scanner config's ``microscope.position_sensor``
        and the board's CAPABILITIES (a board may report that it has no sensor) both say so."""
        mic = self.config.microscope
        if mic is not None and not mic.position_sensor:
            return False
        return self._board.position_sensor

    def open(self, timeout_s: float = 10.0) -> None:
        """Connect to the board, configure it, start streaming (hold), start the recorder."""
        # The family's compiled loops are loaded (or compiled) with the first model that needs
        # them, holding the interpreter throughout: 0.26 s from the cache, 7.8 s cold. Left to a
        # model switched in while streaming (the calibrated model at `piezod calibrate`'s
        # verification, a daemon's calibration job), that stalled the streaming thread.
        kernels.warm_up()
        self._recorder.start()
        self._board.open(timeout_s)
        if not self.position_sensor and self._trackers:
            # the sensitivity tracker follows measured positions: without a sensor it stays off
            log.info("no position sensor: sensitivity tracking off")
            self._trackers = {}
        order = list(self._board.axes)
        if order != list(self.drivers):
            self.drivers = {name: self.drivers[name] for name in order}
            self._ring = TargetRing(len(self.drivers), self._ring.capacity)
        self.sensor_clips.set_full_scale(
            {a: self.settings.full_scale_um(a) for a in self.drivers if self._reads_position(a)}
        )
        self._start_stream()
        self._supervisor = threading.Thread(target=self._supervise, name="piezod-supervisor", daemon=True)
        self._supervisor.start()

    def _start_stream(self) -> None:
        lead = self.config.service.lead_ms / 1000.0
        capped = self._board.capped_lead_s(lead)
        if capped < lead:
            log.info("lead %.0f ms capped at %.0f ms by the board FIFO", 1e3 * lead, 1e3 * capped)
        lead = capped
        block = self.config.service.block_samples(self.rate_hz)
        with self._lock:
            self._job = HoldJob("idle")
            self._queue.clear()
            if self._state in ("starting", "disconnected"):
                self._state = "idle" if not self._fault_latched else "fault"
        self._board.start(self, self._index, lead_s=lead, block_samples=block, on_block=self._on_block)

    def _supervise(self) -> None:
        """Restart the stream after an underrun or a reconnect; report the reason."""
        board = self._board
        while not self._closing.is_set():
            if not board.wait_ended(0.2):
                continue
            if self._closing.is_set():
                return
            how = board.ended_by()
            try:
                board.check()
            except PiezodError as exc:
                self.fault("host", "STREAM", f"streaming ended: {exc}")
            except Exception as exc:
                # a bug in a block source (a model, a job): reported with its traceback, and the
                # stream restarted at the safe values like after any abnormal end; the supervisor
                # must outlive it, or the daemon answers but never streams again
                log.error("streaming ended by an unexpected error", exc_info=exc)
                self.fault("host", "STREAM", f"streaming ended: {type(exc).__name__}: {exc}")
            if how not in (None, "stop"):
                self.fault("host", "STREAM_END", f"streaming run ended by {how}")
            self._end_recording()
            with self._lock:
                self._state = "disconnected" if how == "link" else "fault"
                self._fault_latched = True
            # Wait for the board to be usable again, then stream (hold) again.
            while not self._closing.is_set() and not board.connected:
                time.sleep(0.1)
            if self._closing.is_set():
                return
            self._index = max(self._index, board.next_index) + int(self.rate_hz)
            try:
                # After any abnormal end the outputs go to the safe values (the board's ramp after a
                # watchdog, or the reconfiguration here), and the model forgets the history.
                board.restart(timeout_s=10.0)
                for d in self.drivers.values():
                    d.reset(d.config.safe_voltage_v)
                self._start_stream()
            except (LinkError, PiezodError) as exc:
                self.fault("link", "RESTART", f"cannot restart streaming: {exc}")
                time.sleep(0.5)
            except Exception as exc:
                log.error("restarting the stream failed unexpectedly", exc_info=exc)
                self.fault("link", "RESTART", f"cannot restart streaming: {type(exc).__name__}: {exc}")
                time.sleep(0.5)

    def close(self, *, ramp: bool = True, timeout_s: float = 20.0) -> None:
        """Ramp the outputs to the safe values, stop streaming, close recordings and the link."""
        board = self._board
        if ramp and board.running:
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
            board.finish(timeout_s=timeout_s)
        finally:
            try:
                self._end_recording()
                self._recorder.queue.put(None)
                self._recorder.join(timeout=10.0)
                board.close(ramp_to_safe=True)
            finally:
                self.scan_events.finish(timeout_s=30.0)

    # -- the block source (streamer thread) ------------------------------------------------------

    def next_block(self, n: int) -> FloatArray:
        """The next ``n`` samples for the board: volts ``(axes, n)``."""
        out = np.empty((len(self.drivers), n))
        filled = 0
        t_call = time.monotonic()
        cpu_call = time.thread_time()
        gc_call = gcwatch.collection_seconds()
        queued_call = cpuwait.run_delay_s()
        with self._lock:
            t_locked = time.monotonic()
            while filled < n:
                job = self._job
                self.render_index = self._index + filled
                try:
                    chunk = job.render(self, n - filled)
                except (ModelError, SafetyError) as exc:
                    self.fault("host", "MODEL", f"{type(job).__name__}: {exc}")
                    if isinstance(job, ScanJob | ProgramJob):
                        self._end_recording(self._index + filled)  # closed, not leaked
                    self._queue.clear()
                    self._job = RampJob(self, None, self.config.service.ramp_rate_v_per_s, "fault")
                    self._fault_latched = True
                    continue
                m = chunk.volts.shape[1]
                if m:
                    out[:, filled : filled + m] = chunk.volts
                    self._ring.put(self._index + filled, chunk, self._recording_id, job.ident)
                    filled += m
                if job.done:
                    self._job_finished(job, self._index + filled)
        t_done = time.monotonic()
        if t_done - t_call > SLOW_BLOCK_S:
            # a block must be computed in a fraction of the lead; say where the time went
            queued = cpuwait.run_delay_s() - queued_call
            took, locked, cpu = t_done - t_call, t_locked - t_call, time.thread_time() - cpu_call
            if math.isnan(queued):
                where = "waiting for a core: unknown"
            else:
                rest = max(0.0, took - locked - cpu - queued)
                where = (
                    f"{1e3 * queued:.0f} ms waiting for a core, {1e3 * rest:.0f} ms blocked otherwise "
                    "(the interpreter lock held by another thread, or I/O)"
                )
            log.warning(
                "slow block: %d samples took %.0f ms (%.0f ms waiting for the engine lock, %.0f ms of "
                "this thread's CPU, %s; %.0f ms of garbage collection in the process), job %s",
                n,
                1e3 * took,
                1e3 * locked,
                1e3 * cpu,
                where,
                1e3 * (gcwatch.collection_seconds() - gc_call),
                type(self._job).__name__,
            )
        self._index += n
        return out

    def sync_events(self, first_index: int, n: int) -> list[tuple[int, int, int]]:
        """The scans' sync events at ``[first, first + n)`` (:class:`~piezod.link.streamer.SyncSource`)."""
        with self._lock:
            return self.sync_schedule.between(first_index, n)

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

    def _name_job(self, job: Job, name: str) -> None:
        """Give a client's job its id (its readback is counted as its own: ``sensor_clips``)."""
        self._next_job += 1
        job.ident = self._next_job
        self.sensor_clips.register(job.ident, name, self._recording_id)

    def chunk(self, volts: FloatArray, targets: FloatArray | None) -> Chunk:
        """A chunk without scan lines (hold, move, ramp)."""
        return Chunk.unlined(volts, targets)

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
        return plan_axes(self.drivers, trajectory)

    # -- EngineControl ---------------------------------------------------------------------------

    def status(self) -> Status:
        """A snapshot (cheap, thread-safe).

        While the board is disconnected no position or voltage is reported: what the board applies
        then is not known to the host (it ramps to its safe values when the heartbeat stops).
        """
        with self._lock:
            return self._status_locked()

    def _status_locked(self) -> Status:
        job = self._job
        state = self._state
        scan = job.request if isinstance(job, ScanJob) else None
        line = job.line if isinstance(job, ScanJob) else None
        known = state not in ("disconnected", "starting")
        snap = self._board.snapshot()
        fifo_ms, underruns, crc, dropped = (
            snap.fifo_level_ms,
            snap.underruns,
            snap.crc_errors,
            snap.frames_dropped,
        )
        clips = self.sensor_clips.snapshot()
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
            faults=self.faults.recent(20),
            last_line=self._last_line,
            position_um={n: d.position_um for n, d in self.drivers.items()} if known else {},
            voltage_v={n: d.voltage_v for n, d in self.drivers.items()} if known else {},
            recording=self._recording_name,
            sensitivity_scale={a: t.scale for a, t in self._trackers.items()},
            calibrated=not self._uncalibrated,
            uncalibrated_axes=self._uncalibrated,
            sensor_clipped=clips.job_counts,
            sensor_clipped_job=clips.job,
            sensor_clipped_total=clips.total,
        )

    def trajectory_for(self, request: ScanRequest) -> Trajectory:
        """The scan path a request asks for (the raster today; a new path is selected here)."""
        return RasterTrajectory.from_request(request, self.rate_hz)

    def check_scan(self, request: ScanRequest) -> None:
        """Refuse a scan the stage cannot do (with the reason).

        Besides the steady loop (:meth:`plans_for`), the start of the scan (the move to its first
        point, the settling lines and the first lines of the frame) is rendered on copies of the
        axis drivers, outside the engine lock: a scan that would clamp any sample to the voltage
        limits there (an offset that drives an axis into its limits while the creep settles) is
        refused with the numbers instead of being clamped while it runs.
        """
        trajectory = self.trajectory_for(request)
        check_scan_start(self, request, trajectory, self.plans_for(trajectory))

    def start_scan(self, request: ScanRequest, *, path: Path | None = None) -> Status:
        """Start a scan; recorded to ``path`` or to the recording directory."""
        trajectory = self.trajectory_for(request)
        plans = self.plans_for(trajectory)  # the heavy parts, outside the lock
        check_scan_start(self, request, trajectory, plans)
        with self._lock:
            if self._state not in ("idle",):
                raise EngineStateError(f"cannot start a scan while {self._state}")
            if request.record:
                self._begin_recording(request, trajectory, path, plans)
            try:
                job = ScanJob(self, request, trajectory, plans)
            except BaseException:
                self._discard_recording()
                raise
            self._name_job(job, f"scan {self._recording_name or '(not recorded)'}")
            self._job = job
            self._state = "scanning"
        return self.status()

    def change_scan(self, change: ScanChange) -> Status:
        """Change the running scan at the next line; a refused change has no effect at all."""
        updates = change.model_dump(exclude_none=True)
        with self._lock:
            job = self._job
            if not isinstance(job, ScanJob):
                raise EngineStateError(f"no scan is running (state {self._state})")
            candidate = job.trajectory.changed(**updates)
        self.plans_for(candidate)  # the heavy check, outside the lock (its plans are cached)
        with self._lock:
            if self._job is not job:
                raise EngineStateError("the scan ended meanwhile; nothing was changed")
            job.change(self, change)
        return self.status()

    def stop(self) -> Status:
        """Stop scanning / moving and hold; clears a latched fault.

        While the board is disconnected there is nothing to stop here (the board ramps to its safe
        values by itself when the heartbeat stops, and is reconfigured when it is back): the answer
        says ``disconnected``.
        """
        with self._lock:
            self._queue.clear()
            if isinstance(self._job, ScanJob | ProgramJob):
                self._end_recording()
            self._fault_latched = False
            if self._state in ("disconnected", "starting"):
                self._job = HoldJob(self._state)
                return self._status_locked()
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
        self._check_move_duration(request)
        goal = {
            k: v for k, v in (("x", request.x_um), ("y", request.y_um), ("z", request.z_um)) if v is not None
        }
        with self._lock:
            if self._state not in ("idle", "moving"):
                raise EngineStateError(f"cannot move while {self._state}")
            job = MoveJob(self, goal, request.speed_um_per_s)
            self._name_job(job, "move to " + " ".join(f"{a}={v:g} um" for a, v in goal.items()))
            self._job = job
            self._state = "moving"
        return self.status()

    def _check_move_duration(self, request: MoveRequest) -> None:
        """Refuse a move that would take longer than :data:`MAX_MOVE_S` (with the speed it needs)."""
        with self._lock:
            here = {n: d.position_um for n, d in self.drivers.items()}
        goal = {"x": request.x_um, "y": request.y_um, "z": request.z_um}
        dist = max((abs(v - here[k]) for k, v in goal.items() if v is not None and k in here), default=0.0)
        duration = 0.5 * math.pi * dist / request.speed_um_per_s
        if duration > MAX_MOVE_S:
            need = 0.5 * math.pi * dist / MAX_MOVE_S
            raise SafetyError(
                f"a move of {dist:.4g} um at {request.speed_um_per_s:g} um/s takes {duration:.4g} s, longer "
                f"than the {MAX_MOVE_S:g} s a move may take; use at least {need:.3g} um/s"
            )

    def recordings(self) -> list[RecordingInfo]:
        """The recordings in the recording directory (``complete`` once the recorder has closed it)."""
        writing = self._recorder.open_names()
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
                    complete=p.name != self._recording_name and p.name not in writing,
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
        self,
        axis: AxisName,
        segments: list[Segment],
        path: Path,
        metadata: Mapping[str, object],
        *,
        record_every: int = 1,
    ) -> Status:
        """Play a voltage program on ``axis`` (e.g. a calibration frame), recorded to ``path``.

        ``record_every`` > 1 records every that many samples of the sample clock (the header says
        so: ``recorded_every``); the program itself is played at the full rate.
        """
        if record_every < 1:
            raise ValueError(f"record_every must be >= 1, got {record_every}")
        job = ProgramJob(self, axis, segments, self.config.service.ramp_rate_v_per_s)
        with self._lock:
            if self._state != "idle":
                raise EngineStateError(f"cannot start a program while {self._state}")
            self._next_recording += 1
            ident = self._next_recording
            meta = {
                "scanner": self.config.name,
                "sample_rate_hz": self.rate_hz,
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                **(
                    {SENSOR_RANGE_KEY: self.settings.full_scale_um(axis)}
                    if self._reads_position(axis)
                    else {}
                ),
                **metadata,
            }
            if record_every > 1:
                meta["recorded_every"] = record_every
            self._recorder.open(ident, path, meta, (axis,), targets=False, every=record_every)  # exclusive
            self._recording_id = ident
            self._recording_name = path.name
            self._name_job(job, f"program {path.name}")
            self._job = job
            self._state = "scanning"
        return self.status()

    def set_axis_model(
        self,
        axis: AxisName,
        config: AxisConfig,
        *,
        position_um: float | None = None,
        data_age_s: float | None = 0.0,
    ) -> None:
        """Use new model parameters on ``axis`` from now on.

        The new model continues from the present voltage and the old model's position, or, with
        ``position_um``, from that position (the sensor's reading: a freshly fitted law's
        positions are defined only relative to the histories it was fitted on, and the old model's
        may be an uncalibrated guess).

        ``data_age_s`` is how long ago the data the model was fitted on were measured (``None``:
        unknown): the sensitivity tracker starts from scale 1 as uncertain as the expected drift
        makes it over that time, so the first corrected lines count as much as it could have moved.
        """
        # Built outside the lock: building a model may compile its per-sample loop (seconds), and
        # the block producer needs the lock to keep the board's FIFO fed meanwhile.
        new = AxisDriver(axis, config, self.rate_hz)
        with self._lock:
            old = self.drivers[axis]
            if position_um is None:
                new.adopt_state(old)
            else:
                new.adopt(old.voltage_v, position_um)
            self.drivers[axis] = new
            if axis in self._trackers:
                # the tracked sensitivity is relative to the model it was learnt under
                self._trackers[axis] = self._trackers[axis].restarted(data_age_s, self.uptime_s)
            # the recordings' headers state the model in force (model, parameters, config hash)
            self.config = self.config.model_copy(update={"axes": {**self.config.axes, axis: config}})

    def healthy(self) -> bool:
        """Streaming runs and the board reports in time (the systemd watchdog is pinged only then)."""
        if not self._board.running or not self._board.connected:
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

    @property
    def uptime_s(self) -> float:
        """Seconds since the engine was created (the ``time_s`` of its faults)."""
        return time.monotonic() - self._t0

    def acknowledge_fault(self, timeout_s: float = 15.0, *, since_s: float = 0.0) -> list[FaultInfo]:
        """After a fault: wait until the supervisor has handled it and streams (hold) again, then clear
        it (:meth:`stop`). Returns the faults logged since ``since_s`` (:attr:`uptime_s`), for the
        caller to report.

        A fault that ends the streaming run (an underrun) is reported by the link before the
        supervisor sees the run end and latches the state; clearing it in between was undone by
        the supervisor a moment later (the next scan was refused: ``cannot start a scan while
        fault``). This waits for the latched state and the restarted stream first.

        Raises
        ------
        EngineStateError
            If streaming does not run again within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                latched = self._fault_latched and self._state == "fault"
                settled = latched or self._state in ("idle", "scanning", "moving")
            if settled and self._board.running and self._board.connected and not self._board.wait_ended(0.0):
                break
            if time.monotonic() > deadline:
                state = self.status().state
                raise EngineStateError(
                    f"streaming did not resume within {timeout_s:g} s after the fault (state {state})"
                )
            time.sleep(0.05)
        faults = [f for f in self.faults.recent(200) if f.time_s >= since_s]
        self.stop()
        return faults

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
            played = self._board.snapshot().last_played_index
            if played is not None and played + 1 >= target:
                break
            time.sleep(0.02)
        # SENSOR frames follow the played samples within a few status periods.
        time.sleep(5 * self.settings.status_period_ms / 1000.0 + 0.05)
        self._recorder.queue.join()

    # -- recordings ------------------------------------------------------------------------------

    def _begin_recording(
        self,
        request: ScanRequest,
        trajectory: Trajectory,
        path: Path | None,
        plans: dict[str, PeriodicPlan | None],
    ) -> None:
        self._next_recording += 1
        ident = self._next_recording
        mic = self.config.microscope
        z_ratio = None if mic is None else mic.z_monitor_ratio
        axes = tuple(a for a, plan in plans.items() if plan is not None) or ("x",)
        axes = tuple(a for a in axes if mic is None or a != "z")
        correction = self.correction_label(axes) if request.correction else "none"
        meta = scan_metadata(self.config, request, self.rate_hz, self.position_sensor, axes, correction)
        # offline analyses leave out what the sensor could not read (piezod.readback)
        meta.update(
            {
                f"{SENSOR_RANGE_KEY}.{a}": self.settings.full_scale_um(a)
                for a in axes
                if self._reads_position(a)
            }
        )
        if path is not None or request.name:
            if path is None:
                name = request.name or ""
                path = self.recording_dir / (name if name.endswith(".csv") else name + ".csv")
            self._recorder.open(ident, path, meta, axes, z_monitor_ratio=z_ratio)
        else:
            # unnamed: scan-<time>, then -2, -3 ... for scans started within the same second
            stem = time.strftime("scan-%Y%m%d-%H%M%S")
            for n in range(1, 1000):
                path = self.recording_dir / (f"{stem}.csv" if n == 1 else f"{stem}-{n}.csv")
                try:
                    self._recorder.open(ident, path, meta, axes, z_monitor_ratio=z_ratio)
                    break
                except RecordingError as exc:
                    if not isinstance(exc.__cause__, FileExistsError):
                        raise
            else:
                raise RecordingError(f"no free recording name {stem}-N.csv", str(self.recording_dir))
        assert path is not None
        self._recording_id = ident
        self._recording_name = path.name
        # the heights of the per-frame images: the z axis in force now
        cfg = self.config
        if "z" in self.drivers:
            cfg = cfg.model_copy(update={"axes": {**cfg.axes, "z": self.drivers["z"].config}})
        self.scan_events.begin(ident, path, request.lines, request.frames, z_ratio is not None, cfg)

    def _discard_recording(self) -> None:
        if self._recording_id >= 0:
            self._recorder.discard(self._recording_id)
            self._recording_id = -1
            self._recording_name = None

    def recording_failed(self, ident: int, message: str) -> None:
        """The recorder lost recording ``ident`` (a full disk): stop its scan and hold; a fault.

        The stage holds where it is (no jump, no ramp that might move a probe near a surface);
        the fault stays until ``stop()``. The next scan opens a new recording, so recording
        resumes by itself once space returns (or is refused with the reason if it has not).
        """
        with self._lock:
            if ident == self._recording_id:
                self._recording_id = -1
                self._recording_name = None
                if isinstance(self._job, ScanJob | ProgramJob):
                    self._queue.clear()
                    self._job = HoldJob("fault")
                    self._state = "fault"
                    self._fault_latched = True
        self.fault("host", "RECORDING", message)

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
        self._last_block = block  # kept for measured_at_rest: the readback path does no more
        self._recorder.queue.put((block, self._ring.get(block.indices)))

    def measured_at_rest(self, axis: AxisName) -> tuple[float, float] | None:
        """The voltage ``axis`` holds and the sensor's mean reading there (um), from the last
        :data:`REST_READ_SAMPLES` samples of the latest readback; None while the voltage changes
        (by more than 1e-4 of the axis's span over those samples), without a position sensor, or
        before any readback."""
        block = self._last_block
        if not self.position_sensor or block is None or axis not in block.axes or axis not in self.drivers:
            return None
        i = block.axes.index(axis)
        v, p = block.commanded_v[i, -REST_READ_SAMPLES:], block.position_um[i, -REST_READ_SAMPLES:]
        lo, hi = self.drivers[axis].limits
        # a held voltage may still move by a runtime part's slow correction (drift, warming)
        finite = v.size > 0 and bool(np.all(np.isfinite(v)) and np.all(np.isfinite(p)))
        if not finite or np.ptp(v) > 1e-4 * (hi - lo):
            return None
        return float(v[-1]), float(np.mean(p))

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

    def set_line_linearity(self, value: LineLinearity, corrected: bool, rendered_scale: float = 1.0) -> None:
        """Called by the recorder when a line of the fast axis completes (feeds the tracker);
        ``rendered_scale`` is the tracked scale the line was scanned with. A line without figures
        (``value.skipped``: its readback reached the sensor's full scale) leaves the tracker as it is."""
        if not self.position_sensor:
            return
        self._last_line = value
        tracker = self._trackers.get("x")
        if corrected and tracker is not None and value.length_error_pct is not None:
            tracker.update(
                1.0 + value.length_error_pct / 100.0,
                math.inf if value.duration_s is None else value.duration_s,
                self.config.axes["x"].tracking_min_line_s,
                rendered=rendered_scale,
                t_s=self.uptime_s,
            )

    def tracked_scale(self, axis: str) -> float:
        """The tracked sensitivity of ``axis`` relative to its model (1 without tracking)."""
        tracker = self._trackers.get(axis)
        return 1.0 if tracker is None else tracker.scale

    def tracker_lines(self, axis: str) -> dict[str, int] | None:
        """How many lines the tracker of ``axis`` took (``used``), set aside as too far off to be a
        drift (``far_off``) or as faster than the calibration measured (``too_fast``) since its
        model was switched in; None without tracking."""
        tracker = self._trackers.get(axis)
        if tracker is None:
            return None
        return {
            "used": tracker.lines_used,
            "far_off": tracker.lines_ignored,
            "too_fast": tracker.lines_too_fast,
        }

    def fault(self, source: FaultSource, code: str, message: str, index: int | None = None) -> None:
        """Record a fault (and tell ``on_fault``); repeats of one kind within a second are counted only."""
        self.faults.add(source, code, message, index)

    def _on_link_event(self, ev: LinkEvent) -> None:
        if isinstance(ev, LinkDown | LinkLost):
            with self._lock:
                self._state = "disconnected"
        fault = link_event_fault(ev)
        if fault is not None:
            self.fault(*fault)


__all__ = ["Engine", "FaultSource", "Segment"]
