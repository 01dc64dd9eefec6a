"""The scan's line and frame events and the per-frame images (called from the recorder thread).

:class:`ScanEvents` follows every open scan recording: the recorder reports each finished trace
or retrace line (:meth:`ScanEvents.line_done`) and the closing of a recording
(:meth:`ScanEvents.closed`); it publishes ``line`` and ``frame`` events
(:class:`~piezod.service.schemas.ScanEvent`) to a listener (the API's event hub). For recordings
with a height channel it writes the trace / retrace images of every finished frame by ``piezod
image`` in a child process (image assembly must not hold the GIL of the streaming threads; a
plain child is simple to wait for or end at shutdown), with the heights of the scanner's z axis
(``--config``: a copy of the scanner config in force at the scan's start) when it has one, and
publishes the frame event once they are written, naming them. One child at a time, in the order
the frames finished (a thread takes them from a queue): frame events come in frame order. When
frames finish faster than their images are written (fast lines, small frames), a frame still
waiting for its turn when the next one finishes is skipped - its frame event, in its turn, says
so and names the command that writes it - rather than piling up processes on the controller PC or falling
ever further behind the scan.

* a scan of one frame: ``NAME.gwy`` and ``NAME-CHANNEL-GRID.png``, of the whole recording, when
  it closes;
* a scan of several frames (or until stopped): ``NAME-fK.gwy`` and ``NAME-fK-CHANNEL-GRID.png``
  for frame ``K`` (``piezod image --frame K``), written while the scan goes on - once the next
  frame's first trace is done (the frame's last retrace ends at a turning point the recording
  must show) - and for the last frame when the recording closes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import tempfile
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from piezod.config import ScannerConfig, dump_config
from piezod.errors import PiezodError
from piezod.service.schemas import ScanEvent

log = logging.getLogger("piezod.service.engine")


@dataclass(eq=False)
class _RecordingScan:
    """What the line / frame events of one recording need."""

    path: Path
    lines: int
    frames: int
    height: bool
    config: ScannerConfig | None = None
    last_line: int = -1
    #: a finished frame whose images wait for the next frame's first trace
    pending: int | None = None


class ScanEvents:
    """Line / frame events and images of the scan recordings (thread-safe).

    Parameters
    ----------
    listener
        Called with every event (None: events are not published).
    write_images
        Write the trace / retrace images of every finished frame of recordings with a height channel.
    """

    def __init__(self, listener: Callable[[ScanEvent], None] | None, write_images: bool) -> None:
        self.listener = listener
        self.write_images = write_images
        self._lock = threading.Lock()
        self._scans: dict[int, _RecordingScan] = {}
        #: (recording, frame or None for the whole recording, skipped)
        self._jobs: deque[tuple[_RecordingScan, int | None, bool]] = deque()
        self._worker: threading.Thread | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._idle = threading.Event()
        self._idle.set()

    def begin(
        self,
        ident: int,
        path: Path,
        lines: int,
        frames: int,
        height: bool,
        config: ScannerConfig | None = None,
    ) -> None:
        """Recording ``ident`` (written to ``path``) is a scan of ``lines`` per frame, ``frames`` frames
        (0: until stopped); ``height``: it has a height channel; ``config``: the scanner config in
        force (its ``z`` axis converts the z voltage to heights; None or no z axis: ``z_voltage``
        images only)."""
        usable = config if config is not None and "z" in config.axes else None
        with self._lock:
            self._scans[ident] = _RecordingScan(path, lines, frames, height, usable)

    def _publish(self, event: ScanEvent) -> None:
        if self.listener is not None:
            try:
                self.listener(event)
            except Exception:  # a listener must not stop the recorder
                log.exception("scan event listener failed")

    def _images(self, scan: _RecordingScan) -> bool:
        return self.write_images and scan.height

    def line_done(self, ident: int, line: int, direction: int) -> None:
        """The recorder finished trace (``direction`` +1) or retrace (-1) ``line`` of recording ``ident``."""
        with self._lock:
            scan = self._scans.get(ident)
        if scan is None or line < 0:
            return
        frame, in_frame = divmod(line, scan.lines)
        scan.last_line = line
        name = scan.path.name
        self._publish(
            ScanEvent(
                kind="line",
                recording=name,
                frame=frame,
                lines=scan.lines,
                line=in_frame,
                direction="trace" if direction > 0 else "retrace",
            )
        )
        if direction > 0 and scan.pending is not None and frame > scan.pending:
            self._launch(scan, scan.pending)
            scan.pending = None
        last_frame = scan.frames > 0 and frame == scan.frames - 1
        if direction < 0 and in_frame == scan.lines - 1 and not last_frame:
            if self._images(scan):
                scan.pending = frame
            else:
                self._publish(ScanEvent(kind="frame", recording=name, frame=frame, lines=scan.lines))

    def closed(self, ident: int) -> None:
        """The recorder closed recording ``ident``: its last frame is done; its images are written
        (in a worker process: image assembly must not hold the GIL of the streaming threads)."""
        with self._lock:
            scan = self._scans.pop(ident, None)
        if scan is None or scan.last_line < 0:
            return
        frame = scan.last_line // scan.lines
        if not self._images(scan):
            self._publish(ScanEvent(kind="frame", recording=scan.path.name, frame=frame, lines=scan.lines))
            return
        if scan.frames == 1:
            self._launch(scan, None)
            return
        if scan.pending is not None and scan.pending != frame:
            self._launch(scan, scan.pending)
        scan.pending = None
        self._launch(scan, frame)

    def _launch(self, scan: _RecordingScan, frame: int | None) -> None:
        """Queue ``piezod image`` of the recording (``frame`` None) or of one frame.

        A frame of the same recording still waiting for its turn is skipped (its frame event, in
        its turn, says so): the images keep up with the newest frame instead of falling ever
        further behind.
        """
        with self._lock:
            self._jobs = deque((sc, f, skip or (sc is scan and f is not None)) for sc, f, skip in self._jobs)
            self._jobs.append((scan, frame, False))
            if self._worker is None or not self._worker.is_alive():
                self._worker = threading.Thread(target=self._work, name="piezod-images", daemon=True)
                self._worker.start()
            self._idle.clear()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._jobs:
                    self._worker = None
                    self._idle.set()
                    return
                scan, frame, skip = self._jobs.popleft()
            if skip and frame is not None:
                self._publish(
                    ScanEvent(
                        kind="frame",
                        recording=scan.path.name,
                        frame=frame,
                        lines=scan.lines,
                        image_error=(
                            "images skipped: the frames finish faster than their images are written "
                            f"(piezod image {scan.path.name} --frame {frame} writes them)"
                        ),
                    )
                )
            else:
                self._write(scan, frame)

    def _write(self, scan: _RecordingScan, only: int | None) -> None:
        """Run ``piezod image`` of the recording or frame ``only`` in a child; publish the frame event."""
        cmd = [sys.executable, "-m", "piezod", "image", str(scan.path), "--out", str(scan.path.parent)]
        if only is not None:
            cmd += ["--frame", str(only)]
        config_file: str | None = None
        if scan.config is not None:
            fd, config_file = tempfile.mkstemp(prefix=f"{scan.path.stem}-", suffix=".yaml")
            os.close(fd)
            try:
                dump_config(scan.config, config_file)
            except (OSError, PiezodError) as exc:  # no heights then, but the images
                log.warning("images of %s without heights: %s", scan.path.name, exc)
                Path(config_file).unlink(missing_ok=True)
                config_file = None
            else:
                cmd += ["--config", config_file]
        try:
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            with self._lock:
                self._proc = proc
            _, err = proc.communicate()
        except OSError as exc:  # cannot start a process: the frame event says so
            log.warning("images of %s: %s", scan.path.name, exc)
            err, proc = str(exc).encode(), None
        finally:
            with self._lock:
                self._proc = None
            if config_file is not None:
                with contextlib.suppress(OSError):
                    os.unlink(config_file)
        files: list[str] = []
        error = None
        if proc is not None and proc.returncode == 0:
            stem = scan.path.stem if only is None else f"{scan.path.stem}-f{only}"
            files = sorted(
                f.name
                for f in scan.path.parent.iterdir()
                if f.name == f"{stem}.gwy" or (f.name.startswith(f"{stem}-") and f.suffix == ".png")
            )
        else:
            lines = err.decode(errors="replace").strip().splitlines()
            code = proc.returncode if proc is not None else None
            error = lines[-1] if lines else f"piezod image exited with {code}"
            if proc is not None:
                log.warning("images of %s: %s", scan.path.name, error)
        self._publish(
            ScanEvent(
                kind="frame",
                recording=scan.path.name,
                frame=scan.last_line // scan.lines if only is None else only,
                lines=scan.lines,
                images=files,
                image_error=error,
            )
        )

    def finish(self, timeout_s: float = 30.0) -> None:
        """Wait for the queued images to be written (a writer still running after ``timeout_s`` is
        ended, the frames still queued then are not written)."""
        if not self._idle.wait(timeout_s):
            with self._lock:
                self._jobs.clear()
                proc = self._proc
            if proc is not None:
                proc.kill()
            self._idle.wait(10.0)


__all__ = ["ScanEvents"]
