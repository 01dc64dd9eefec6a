"""A fake streaming engine implementing :class:`~piezod.service.schemas.EngineControl` for API tests.

It keeps the state machine of the real engine (idle / scanning / fault ...),
refuses ranges above ``max_range_um`` with a :class:`RangeUnreachableError`
naming the voltage it would need, refuses moves outside ``limits_um`` with a
:class:`SafetyError`, and lists the ``*.csv`` files of a directory as its
recordings. Every call is recorded in :attr:`FakeEngine.calls`.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from piezod.config import ApiConfig
from piezod.errors import EngineStateError, RangeUnreachableError, SafetyError
from piezod.service.api import EventHub, create_app
from piezod.service.schemas import (
    EngineState,
    FaultInfo,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanRequest,
    Status,
)
from piezod.service.server import ApiServer

UM_PER_V = 0.2
VOLTAGE_MAX_V = 150.0


class FakeEngine:
    """An engine without a board: state, limits and recordings only."""

    def __init__(
        self,
        recording_dir: Path,
        *,
        hub: EventHub | None = None,
        max_range_um: float = 2 * UM_PER_V * VOLTAGE_MAX_V,
        limits_um: tuple[float, float] = (-30.0, 30.0),
        sample_rate_hz: float = 10_000.0,
    ) -> None:
        self.recording_dir = recording_dir
        self.hub = hub
        self.max_range_um = max_range_um
        self.limits_um = limits_um
        self.sample_rate_hz = sample_rate_hz
        self.calls: list[tuple[str, Any]] = []
        #: set to make ``start_scan`` wait until the event is set (a briefly blocking engine)
        self.block_start: threading.Event | None = None
        #: set to make ``status`` raise this exception
        self.status_error: Exception | None = None
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self.reset()

    def reset(self) -> None:
        """Back to idle, no faults, no calls."""
        with self._lock:
            self.state: EngineState = "idle"
            self.scan: ScanRequest | None = None
            self.faults: list[FaultInfo] = []
            self.position_um = {"x": 0.0, "y": 0.0, "z": 0.0}
            self.calls.clear()
            self.block_start = None
            self.status_error = None

    # ---------------------------------------------------------------------- EngineControl

    def status(self) -> Status:
        """A snapshot."""
        if self.status_error is not None:
            raise self.status_error
        with self._lock:
            uptime = time.monotonic() - self._t0
            return Status(
                state=self.state,
                scanner="fake-stage",
                uptime_s=uptime,
                sample_rate_hz=self.sample_rate_hz,
                sample_index=int(uptime * self.sample_rate_hz),
                scan=self.scan,
                line=3 if self.scan else None,
                frame=0 if self.scan else None,
                fifo_level_ms=150.0 if self.scan else 0.0,
                lead_target_ms=150.0,
                faults=list(self.faults),
                position_um=dict(self.position_um),
                voltage_v={k: v / UM_PER_V for k, v in self.position_um.items()},
                recording=self.scan.name if self.scan and self.scan.record else None,
            )

    def check_scan(self, request: ScanRequest) -> None:
        """Refuse a range the voltage limits cannot reach."""
        self.calls.append(("check_scan", request))
        travel = request.range_um * (1 + 2 * request.overscan)
        if travel > self.max_range_um:
            need = travel / (2 * UM_PER_V)
            raise RangeUnreachableError(
                f"range {travel:g} um needs +/-{need:g} V on x, beyond voltage_max_v {VOLTAGE_MAX_V:g} V"
            )

    def start_scan(self, request: ScanRequest) -> Status:
        """Start scanning (idle only)."""
        self.calls.append(("start_scan", request))
        self.check_scan(request)
        if self.block_start is not None:
            self.block_start.wait(10.0)
        with self._lock:
            if self.state != "idle":
                raise EngineStateError(f"cannot start a scan while {self.state}")
            self.state = "scanning"
            self.scan = request
        return self.status()

    def change_scan(self, change: ScanChange) -> Status:
        """Change the running scan."""
        self.calls.append(("change_scan", change))
        with self._lock:
            if self.state != "scanning" or self.scan is None:
                raise EngineStateError("no scan is running")
            update = change.model_dump(exclude_none=True)
            if update.get("range_um", self.scan.range_um) > self.max_range_um:
                raise RangeUnreachableError(f"range {update['range_um']:g} um is beyond the stage")
            self.scan = self.scan.model_copy(update=update)
        return self.status()

    def stop(self) -> Status:
        """Stop, clear faults."""
        self.calls.append(("stop", None))
        with self._lock:
            self.state = "idle"
            self.scan = None
            self.faults.clear()
        return self.status()

    def check_move(self, request: MoveRequest) -> None:
        """Refuse targets outside the limits."""
        self.calls.append(("check_move", request))
        lo, hi = self.limits_um
        for axis in ("x", "y", "z"):
            value = getattr(request, f"{axis}_um")
            if value is not None and not lo <= value <= hi:
                raise SafetyError(f"{axis}_um = {value:g} is outside the limits [{lo:g}, {hi:g}] um")

    def move(self, request: MoveRequest) -> Status:
        """Jump there at once."""
        self.calls.append(("move", request))
        with self._lock:
            if self.state not in ("idle", "moving"):
                raise EngineStateError(f"cannot move while {self.state}")
            for axis in ("x", "y", "z"):
                value = getattr(request, f"{axis}_um")
                if value is not None:
                    self.position_um[axis] = value
        return self.status()

    def recordings(self) -> list[RecordingInfo]:
        """The CSV files of the recording directory."""
        out = []
        for path in sorted(self.recording_dir.glob("*.csv")):
            st = path.stat()
            out.append(
                RecordingInfo(name=path.name, size_bytes=st.st_size, modified_unix=st.st_mtime, complete=True)
            )
        return out

    def recording_path(self, name: str) -> Path:
        """``recording_dir / name`` (the API must have refused traversal before)."""
        path = self.recording_dir / name
        if not path.exists() and not path.is_symlink():
            raise FileNotFoundError(name)
        return path

    # ---------------------------------------------------------------------- test helpers

    def inject_fault(
        self, code: str = "underrun", message: str = "FIFO ran empty", push: bool = True
    ) -> None:
        """Enter the fault state; publish the fault on the hub when ``push``."""
        with self._lock:
            fault = FaultInfo(
                time_s=time.monotonic() - self._t0, source="board", code=code, message=message, index=1234
            )
            self.faults.append(fault)
            self.state = "fault"
        if push and self.hub is not None:
            self.hub.publish_fault(fault)


@contextlib.contextmanager
def running_api(
    recording_dir: Path,
    spec: str | None = None,
    api_config: ApiConfig | None = None,
    *,
    rate_hz: float = 20.0,
) -> Iterator[tuple[FakeEngine, ApiServer]]:
    """A FakeEngine behind a started ApiServer (default: ``unix:<recording_dir>/api.sock``)."""
    hub = EventHub(rate_hz=rate_hz)
    engine = FakeEngine(recording_dir, hub=hub)
    server = ApiServer(
        create_app(engine, events=hub), spec or f"unix:{recording_dir / 'api.sock'}", api_config
    )
    server.start()
    try:
        yield engine, server
    finally:
        server.stop()
