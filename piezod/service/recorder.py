"""The recorder: sensor readback paired with the engine's targets, appended to the open
recording (flushed per block), and the linearity of the last complete line of the fast axis.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from piezod.config import ScannerConfig, calibrated_axes
from piezod.errors import (
    PiezodError,
    RecordingError,
)
from piezod.link.streamer import MatchedBlock
from piezod.readback import full_scale_mask
from piezod.recording import RecordingWriter
from piezod.service.jobs import Chunk
from piezod.service.schemas import (
    LineLinearity,
    ScanRequest,
)

if TYPE_CHECKING:
    from piezod.service.engine import Engine

log = logging.getLogger("piezod.service.engine")

FloatArray = NDArray[np.float64]


def scan_metadata(
    config: ScannerConfig,
    request: ScanRequest,
    rate_hz: float,
    position_sensor: bool,
    axes: tuple[str, ...],
    correction: str,
) -> dict[str, object]:
    """The header of a scan recording (docs/formats.md): the request, the scanner, the model.

    Parameters
    ----------
    config
        The scanner.
    request
        The scan.
    rate_hz
        The sample rate.
    position_sensor
        Whether positions are measured.
    axes
        The recorded (scanned) axes.
    correction
        What corrects them (:meth:`piezod.service.engine.Engine.correction_label`, ``none``).
    """
    meta: dict[str, object] = {
        "scanner": config.name,
        "range_um": request.range_um,
        "line_rate_hz": request.line_rate_hz,
        "lines": request.lines,
        "offset_x_um": request.offset_x_um,
        "offset_y_um": request.offset_y_um,
        "rotation_deg": request.rotation_deg,
        "overscan": request.overscan,
        "sample_rate_hz": rate_hz,
        "pixels": request.pixels,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "config_sha256": hashlib.sha256(config.model_dump_json().encode()).hexdigest(),
    }
    fast = config.axes["x"]
    if request.correction:
        section = getattr(fast, fast.model)
        meta["model"] = fast.model
        meta["model_params"] = json.dumps(section.model_dump(mode="json"), sort_keys=True)
    else:
        meta["model"] = "none"
    mic = config.microscope
    if mic is not None or not position_sensor:
        meta["position_sensor"] = "yes" if position_sensor else "no"
    if mic is not None:
        meta["z_monitor_ratio"] = mic.z_monitor_ratio
    meta["correction"] = correction
    uncal = [a for a in axes if a not in calibrated_axes(config)]
    meta["calibrated"] = "no (axes " + ", ".join(uncal) + ")" if uncal else "yes"
    return meta


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
        self.scale = np.ones(capacity)
        self.job = np.full(capacity, -1, dtype=np.int64)
        self.hi = 0
        self.lock = threading.Lock()

    def put(self, first: int, chunk: Chunk, recording_id: int, job_id: int = -1) -> None:
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
            self.scale[slots] = chunk.scale
            self.job[slots] = job_id
            self.hi = max(self.hi, first + n)

    def get(self, idx: NDArray[np.int64]) -> tuple[Any, ...]:
        """(targets, line, direction, record, recording id, label id, corrected, the fast axis's
        tracked scale rendered, job id) at the sample indices."""
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
                self.scale[slots].copy(),
                np.where(known, self.job[slots], -1),
            )


@dataclass
class _OpenRecording:
    ident: int
    path: Path
    writer: RecordingWriter
    axes: tuple[str, ...]
    targets: bool
    rows: int = 0
    last_t: float = 0.0
    done: bool = False
    labels_seen: set[int] = field(default_factory=set)
    z_monitor_ratio: float | None = None
    every: int = 1


@dataclass
class _LineAccumulator:
    line: int = -1
    direction: int = 0
    corrected: bool = False
    recording: int = -1
    target: list[FloatArray] = field(default_factory=list)
    position: list[FloatArray] = field(default_factory=list)
    scale: list[FloatArray] = field(default_factory=list)
    clipped: int = 0
    full_scale_um: float = math.nan


class Recorder(threading.Thread):
    """Appends matched sensor blocks to the open recording; line linearity of the fast axis."""

    def __init__(self, engine: Engine) -> None:
        super().__init__(name="piezod-recorder", daemon=True)
        self.engine = engine
        self.queue: queue.Queue[tuple[MatchedBlock | None, tuple[Any, ...]] | None] = queue.Queue()
        self.recordings: dict[int, _OpenRecording] = {}
        self.lock = threading.Lock()
        self.failed = 0
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
        every: int = 1,
    ) -> None:
        """Create the recording ``path`` (exclusively: an existing file is never reused or truncated).

        With ``z_monitor_ratio`` (a microscope) every row also carries ``z_voltage``: the z channel's
        reading (the z-piezo voltage monitor) times the ratio. With ``every`` > 1 only the samples
        whose index is a multiple of it are written.

        Raises
        ------
        RecordingError
            If ``path`` exists or cannot be created (a full disk): nothing is left behind.
        """
        height = ("z_voltage",) if z_monitor_ratio is not None else ()
        target = ("target",) if targets else ()
        columns = ("t", "voltage", "position", *target, *height, "axis", "experiment")
        try:
            writer = RecordingWriter(path, columns, metadata=metadata, exclusive=True)
        except FileExistsError as exc:
            raise RecordingError(
                "exists; recordings are never overwritten or reused: choose another name", str(path)
            ) from exc
        except OSError as exc:
            raise RecordingError(f"cannot create the recording: {exc.strerror or exc}", str(path)) from exc
        with self.lock:
            self.recordings[ident] = _OpenRecording(
                ident, path, writer, axes, targets, z_monitor_ratio=z_monitor_ratio, every=every
            )

    def open_names(self) -> set[str]:
        """File names of the recordings still open (a stopped scan's stays open until its readback,
        up to a FIFO's lead behind, is written)."""
        with self.lock:
            return {rec.path.name for rec in self.recordings.values()}

    def discard(self, ident: int) -> None:
        """Close and delete a recording that never started (its scan was refused)."""
        with self.lock:
            rec = self.recordings.pop(ident, None)
        if rec is not None:
            rec.writer.close()
            with contextlib.suppress(OSError):
                rec.path.unlink()

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
                    at_end = self.engine.sensor_clips.add(block.axes, block.position_um, meta[8])
                    self._write(block, meta, at_end.get("x"))
                    last = int(block.indices[-1]) if block.indices.size else -1
                    for ident, end in list(self._pending_close.items()):
                        if last >= end - 1:
                            del self._pending_close[ident]
                            self._close(ident)
            except (OSError, PiezodError, ValueError) as exc:
                # not one recording's disk error (handled in _write): stop every open recording
                log.exception("recorder failed")
                with self.lock:
                    idents = list(self.recordings)
                for ident in idents:
                    self._fail(ident, exc)
            finally:
                self.queue.task_done()
        self.engine.sensor_clips.finish()
        with self.lock:
            for rec in self.recordings.values():
                rec.writer.close()

    def _fail(self, ident: int, exc: BaseException) -> None:
        """A recording cannot be written: keep what it holds, close it, stop its scan, report it."""
        with self.lock:
            rec = self.recordings.pop(ident, None)
        if rec is None:
            return
        rec.writer.close()
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        self.failed += 1
        if rec.rows == 0:  # created by us, holding no data: leave no empty recording behind
            with contextlib.suppress(OSError):
                rec.path.unlink()
            kept = "nothing was recorded (the empty file is removed)"
        else:
            kept = (
                f"its {rec.rows} rows up to t = {rec.last_t:.3f} s are kept (the file ends with a "
                "complete line)"
            )
        self.engine.recording_failed(
            ident, f"recording {rec.path.name} stopped: {reason}; {kept}; the scan was stopped"
        )

    def _close(self, ident: int) -> None:
        with self.lock:
            rec = self.recordings.pop(ident, None)
        if rec is not None:
            try:
                self._write_trailer(rec)
            finally:
                rec.writer.close()
            log.info("recording %s closed (%d rows)", rec.path, rec.rows)
            self._finish_line()  # the last retrace ends with the recording
            self._acc.line = -1
            self.engine.scan_events.closed(ident)

    def _write_trailer(self, rec: _OpenRecording) -> None:
        """The last line of a recording whose job's readback reached the sensor's full scale:
        ``# sensor_clipped: x=<samples> y=<samples>`` (docs/formats.md)."""
        counts = self.engine.sensor_clips.for_recording(rec.ident)
        if not counts or not any(counts.values()):
            return
        try:
            rec.writer.comment("sensor_clipped: " + " ".join(f"{a}={n}" for a, n in counts.items()))
        except OSError as exc:  # the rows are all written: the file lacks only its trailer
            log.error("recording %s: cannot write its sensor_clipped trailer: %s", rec.path, exc)

    def _write(
        self, block: MatchedBlock, meta: tuple[Any, ...], x_at_end: NDArray[np.bool_] | None = None
    ) -> None:
        targets, line, direction, record, rec_id, label, corrected, scale, _ = meta
        rate = self.engine.rate_hz
        t = block.indices / rate
        self._line_stats(
            block, targets, line, direction, corrected, np.where(record, rec_id, -1), scale, x_at_end
        )
        if not record.any():
            return
        for ident in np.unique(rec_id[record]):
            with self.lock:
                rec = self.recordings.get(int(ident))
            if rec is None:
                continue
            rows = np.flatnonzero(record & (rec_id == ident))
            if rec.every > 1:
                rows = rows[block.indices[rows] % rec.every == 0]
                if rows.size == 0:
                    continue
            try:
                self._write_rows(rec, block, rows, t, targets, label)
            except OSError as exc:  # a full disk, an I/O error: this recording ends here
                self._fail(int(ident), exc)

    def _write_rows(
        self,
        rec: _OpenRecording,
        block: MatchedBlock,
        rows: NDArray[np.intp],
        t: FloatArray,
        targets: FloatArray,
        label: NDArray[np.int64],
    ) -> None:
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
                rec.last_t = float(t[run][-1])

    def _line_stats(
        self,
        block: MatchedBlock,
        targets: FloatArray,
        line: NDArray[np.int64],
        direction: NDArray[np.int8],
        corrected: NDArray[np.bool_],
        recording: NDArray[np.int64],
        scale: FloatArray,
        at_end: NDArray[np.bool_] | None = None,
    ) -> None:
        """Accumulate the fast axis's lines; ``at_end``: which x samples sit at the sensor's full
        scale (from :meth:`SensorClips.add`, which has tested the block; tested here if not given)."""
        if "x" not in block.axes:
            return
        ix = block.axes.index("x")
        acc = self._acc
        full_scale = self.engine.sensor_clips.full_scale_um("x")
        if at_end is None and full_scale is not None:
            at_end = full_scale_mask(block.position_um[ix], full_scale)
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
                acc.target, acc.position, acc.scale = [], [], []
                acc.clipped = 0
                acc.corrected = bool(corrected[seg[0]])
                acc.recording = int(recording[seg[0]])
            if ln >= 0:
                acc.target.append(targets[ix, seg])
                acc.position.append(block.position_um[ix, seg])
                acc.scale.append(scale[seg])
                if at_end is not None and full_scale is not None:
                    acc.clipped += int(np.count_nonzero(at_end[seg]))
                    acc.full_scale_um = full_scale

    def _finish_line(self) -> None:
        acc = self._acc
        if acc.line < 0 or not acc.target:
            return
        if acc.recording >= 0:
            self.engine.scan_events.line_done(acc.recording, acc.line, acc.direction)
        tgt = np.concatenate(acc.target)
        pos = np.concatenate(acc.position)
        rendered = float(np.mean(np.concatenate(acc.scale)))
        duration_s = tgt.size / self.engine.rate_hz
        if acc.clipped:
            # the ADC's end code is not a position: a figure from it would teach the tracker a length
            self.engine.set_line_linearity(
                LineLinearity(
                    line=acc.line,
                    direction="trace" if acc.direction > 0 else "retrace",
                    nonlinearity_pct=None,
                    length_error_pct=None,
                    duration_s=duration_s,
                    skipped=f"readback at the sensor's full scale (+-{acc.full_scale_um:g} um) in "
                    f"{acc.clipped} samples",
                ),
                acc.corrected,
                rendered,
            )
            return
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
                duration_s=duration_s,
            ),
            acc.corrected,
            rendered,
        )
