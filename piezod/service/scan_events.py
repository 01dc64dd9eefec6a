"""The scan's line and frame events and the per-frame images (called from the recorder thread).

:class:`ScanEvents` follows every open scan recording: the recorder reports each finished trace
or retrace line (:meth:`ScanEvents.line_done`) and the closing of a recording
(:meth:`ScanEvents.closed`); it publishes ``line`` and ``frame`` events
(:class:`~piezod.service.schemas.ScanEvent`) to a listener (the API's event hub) and, for
recordings with a height channel, writes the trace / retrace images of the last frame by
``piezod image`` in a child process (image assembly must not hold the GIL of the streaming
threads; a plain child is simple to wait for or end at shutdown).
"""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from piezod.service.schemas import ScanEvent

log = logging.getLogger("piezod.service.engine")


@dataclass(eq=False)
class _RecordingScan:
    """What the line / frame events of one recording need."""

    path: Path
    lines: int
    frames: int
    height: bool
    last_line: int = -1


class ScanEvents:
    """Line / frame events and images of the scan recordings (thread-safe).

    Parameters
    ----------
    listener
        Called with every event (None: events are not published).
    write_images
        Write the trace / retrace images beside every finished recording with a height channel.
    """

    def __init__(self, listener: Callable[[ScanEvent], None] | None, write_images: bool) -> None:
        self.listener = listener
        self.write_images = write_images
        self._lock = threading.Lock()
        self._scans: dict[int, _RecordingScan] = {}
        self._procs: list[subprocess.Popen[bytes]] = []

    def begin(self, ident: int, path: Path, lines: int, frames: int, height: bool) -> None:
        """Recording ``ident`` (written to ``path``) is a scan of ``lines`` per frame, ``frames`` frames
        (0: until stopped); ``height``: it has a height channel."""
        with self._lock:
            self._scans[ident] = _RecordingScan(path, lines, frames, height)

    def _publish(self, event: ScanEvent) -> None:
        if self.listener is not None:
            try:
                self.listener(event)
            except Exception:  # a listener must not stop the recorder
                log.exception("scan event listener failed")

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
        last_frame = scan.frames > 0 and frame == scan.frames - 1
        if direction < 0 and in_frame == scan.lines - 1 and not last_frame:
            self._publish(ScanEvent(kind="frame", recording=name, frame=frame, lines=scan.lines))

    def closed(self, ident: int) -> None:
        """The recorder closed recording ``ident``: its last frame is done; its images are written
        (in a worker process: image assembly must not hold the GIL of the streaming threads)."""
        with self._lock:
            scan = self._scans.pop(ident, None)
        if scan is None or scan.last_line < 0:
            return
        frame = scan.last_line // scan.lines
        if not (self.write_images and scan.height):
            self._publish(ScanEvent(kind="frame", recording=scan.path.name, frame=frame, lines=scan.lines))
            return
        cmd = [sys.executable, "-m", "piezod", "image", str(scan.path), "--out", str(scan.path.parent)]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        with self._lock:
            self._procs.append(proc)
        threading.Thread(
            target=self._wait_images, args=(proc, scan, frame), name="piezod-images", daemon=True
        ).start()

    def _wait_images(self, proc: subprocess.Popen[bytes], scan: _RecordingScan, frame: int) -> None:
        _, err = proc.communicate()
        with self._lock:
            if proc in self._procs:
                self._procs.remove(proc)
        files: list[str] = []
        error = None
        if proc.returncode == 0:
            stem = scan.path.stem
            files = sorted(
                f.name
                for f in scan.path.parent.iterdir()
                if f.name == f"{stem}.gwy" or (f.name.startswith(f"{stem}-") and f.suffix == ".png")
            )
        else:
            lines = err.decode(errors="replace").strip().splitlines()
            error = lines[-1] if lines else f"piezod image exited with {proc.returncode}"
            log.warning("images of %s: %s", scan.path.name, error)
        self._publish(
            ScanEvent(
                kind="frame",
                recording=scan.path.name,
                frame=frame,
                lines=scan.lines,
                images=files,
                image_error=error,
            )
        )

    def finish(self, timeout_s: float = 30.0) -> None:
        """Wait for the images being written (a writer still running after ``timeout_s`` is ended)."""
        with self._lock:
            procs, self._procs = list(self._procs), []
        for proc in procs:
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


__all__ = ["ScanEvents"]
