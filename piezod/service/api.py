"""The daemon's control API: a FastAPI app over an :class:`~piezod.service.schemas.EngineControl`.

Endpoints (all JSON unless noted)::

    GET   /v1/status              a Status snapshot
    POST  /v1/scan                start a scan (ScanRequest)            202, 409 busy/fault, 422 refused
    PATCH /v1/scan                change the running scan (ScanChange)  200, 409 not scanning, 422 refused
    POST  /v1/stop                stop and hold (always allowed)        200
    POST  /v1/move                move, then hold (MoveRequest)         202, 409 busy/fault, 422 refused
    GET   /v1/recordings          the recordings (RecordingInfo[])
    GET   /v1/recordings/{name}   one recording as CSV (text/csv)       404 unknown
    GET   /v1/events              server-sent events: ``status`` snapshots at a rate, ``fault`` at once;
                                  with ``scans=true`` also ``line`` / ``frame`` (ScanEvent)
    GET   /openapi.json, /docs    the API description

Engine calls run in the threadpool, so a briefly blocking engine never stalls
the event loop. Engine errors become one-line JSON answers
``{"detail": reason, "error": exception name}``; unexpected ones are logged
with their traceback and answered with 500 without it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import stat
import threading
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Annotated, Any, TypeVar

from fastapi import FastAPI, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from piezod import __version__
from piezod.errors import (
    BoardFaultError,
    ConfigError,
    EngineStateError,
    LinkError,
    ModelError,
    PiezodError,
    RecordingError,
    SafetyError,
)
from piezod.service.guards import (
    API_THREADS,
    MAX_EVENT_STREAMS,
    BearerTokenMiddleware,
    ErrorBody,
)
from piezod.service.schemas import (
    EngineControl,
    FaultInfo,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanEvent,
    ScanRequest,
    Status,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Recording names the API serves: no separators, no leading dot (same rule as ScanRequest.name).
RECORDING_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")

_CHUNK = 64 * 1024

#: Highest status rate an event stream may ask for (Hz).
MAX_EVENT_RATE_HZ = 50.0


class _RefusedError(Exception):
    """Answered as ``{"detail": ..., "error": ...}`` with ``status_code``."""

    def __init__(
        self, status_code: int, detail: str, error: str | None = None, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.error = error
        self.headers = headers


def http_status_for(exc: PiezodError) -> int:
    """The HTTP status a piezod error is answered with.

    ``SafetyError``, ``ModelError`` (``RangeUnreachableError``...), ``ConfigError`` and
    ``RecordingError``: 422 (the request cannot be done); ``EngineStateError`` and
    ``BoardFaultError``: 409 (not now); ``LinkError``: 503 (the board is unavailable);
    anything else: 500.
    """
    if isinstance(exc, SafetyError | ModelError | ConfigError | RecordingError):
        return 422
    if isinstance(exc, EngineStateError | BoardFaultError):
        return 409
    if isinstance(exc, LinkError):
        return 503
    return 500


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _refusal_for(what: str, exc: Exception) -> _RefusedError:
    """The answer to an engine error, logged: client errors at info, server errors with the traceback."""
    if isinstance(exc, PiezodError):
        code = http_status_for(exc)
        reason = _one_line(str(exc)) or type(exc).__name__
        if code >= 500:
            log.error("%s failed: %s: %s", what, type(exc).__name__, reason, exc_info=exc)
        else:
            log.info("%s refused (%d): %s", what, code, reason)
        return _RefusedError(code, reason, type(exc).__name__)
    log.error("%s failed unexpectedly", what, exc_info=exc)
    return _RefusedError(
        500, f"internal error in {what} ({type(exc).__name__}); see the daemon log", "InternalError"
    )


def _engine_call(what: str, fn: Callable[..., T], *args: Any) -> T:
    """Call the engine; translate its errors into answers."""
    try:
        return fn(*args)
    except Exception as exc:
        raise _refusal_for(what, exc) from exc


# --------------------------------------------------------------------------------------------- events


@dataclass(eq=False)
class _Subscriber:
    loop: asyncio.AbstractEventLoop
    queue: asyncio.Queue[FaultInfo | ScanEvent | None] = field(
        default_factory=lambda: asyncio.Queue(maxsize=256)
    )
    dropped: int = 0
    scans: bool = False

    def offer(self, item: FaultInfo | ScanEvent | None) -> None:
        """Runs in the subscriber's loop."""
        if isinstance(item, ScanEvent) and not self.scans:
            return
        if item is None:
            while self.queue.full():  # the end marker must get through
                self.queue.get_nowait()
        if self.queue.full():
            self.dropped += 1
            if self.dropped == 1:
                log.warning("event stream too slow: dropping events")
            return
        self.queue.put_nowait(item)


class EventHub:
    """Live events for ``GET /v1/events``: status rate, pushed faults, shutdown.

    Give the same hub to the engine (it calls :meth:`publish_fault` from any thread
    so that faults reach the streams at once) and to :func:`create_app`. Faults
    that only show up in ``Status.faults`` are found by comparing snapshots, at
    the status rate. :meth:`close` ends every stream (server shutdown).

    Parameters
    ----------
    rate_hz
        Status snapshots per second on a stream, unless the client asks otherwise
        (at most :data:`MAX_EVENT_RATE_HZ`).
    """

    def __init__(self, rate_hz: float = 5.0) -> None:
        if not 0 < rate_hz <= MAX_EVENT_RATE_HZ:
            raise ConfigError(f"event rate {rate_hz} Hz must lie in (0, {MAX_EVENT_RATE_HZ}]")
        self.rate_hz = rate_hz
        self._lock = threading.Lock()
        self._subscribers: set[_Subscriber] = set()
        self._closed = False

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed

    @property
    def subscribers(self) -> int:
        """Number of open event streams."""
        with self._lock:
            return len(self._subscribers)

    def publish_fault(self, fault: FaultInfo) -> None:
        """Send a fault event to every open stream now (thread-safe, never blocks)."""
        self._broadcast(fault)

    def publish_scan(self, event: ScanEvent) -> None:
        """Send a line / frame event to every stream that asked for them (thread-safe, never blocks)."""
        self._broadcast(event)

    def close(self) -> None:
        """End every stream and refuse new ones (thread-safe, idempotent)."""
        with self._lock:
            self._closed = True
        self._broadcast(None)

    def _broadcast(self, item: FaultInfo | ScanEvent | None) -> None:
        with self._lock:
            subscribers = list(self._subscribers)
        for sub in subscribers:
            try:
                sub.loop.call_soon_threadsafe(sub.offer, item)
            except RuntimeError:  # its loop is closed: the server is gone
                self._unsubscribe(sub)

    def _subscribe(self, scans: bool = False) -> _Subscriber:
        sub = _Subscriber(asyncio.get_running_loop(), scans=scans)
        with self._lock:
            if self._closed:
                raise _RefusedError(503, "the daemon is shutting down", "ShuttingDown")
            if len(self._subscribers) >= MAX_EVENT_STREAMS:
                raise _RefusedError(503, f"{MAX_EVENT_STREAMS} event streams are open already", "Busy")
            self._subscribers.add(sub)
        return sub

    def _unsubscribe(self, sub: _Subscriber) -> None:
        with self._lock:
            self._subscribers.discard(sub)


def _fault_key(fault: FaultInfo) -> tuple[float, str, str, int | None]:
    return (fault.time_s, fault.source, fault.code, fault.index)


def _sse(event: str, data: str, event_id: int) -> bytes:
    return f"event: {event}\nid: {event_id}\ndata: {data}\n\n".encode()


async def _event_stream(
    engine: EngineControl, hub: EventHub, rate_hz: float, limit: int | None, scans: bool = False
) -> AsyncIterator[bytes]:
    """Status snapshots every ``1/rate_hz`` s, faults as they come, until the limit, close or disconnect.

    A client disconnect cancels this generator (Starlette listens for it); the
    ``finally`` then unsubscribes.
    """
    loop = asyncio.get_running_loop()
    period = 1.0 / rate_hz
    seen: dict[tuple[float, str, str, int | None], None] = {}
    sent_status = 0
    event_id = 0
    next_tick = loop.time()
    try:
        sub = hub._subscribe(scans)
    except _RefusedError:
        return
    try:
        yield f"retry: {max(1000, int(2000 * period))}\n\n".encode()
        while True:
            now = loop.time()
            if now >= next_tick:
                try:
                    status = await run_in_threadpool(engine.status)
                except Exception as exc:
                    log.exception("event stream: engine status failed")
                    body = ErrorBody(
                        detail=f"engine status failed ({type(exc).__name__})", error="InternalError"
                    )
                    yield _sse("error", body.model_dump_json(), event_id + 1)
                    return
                for fault in status.faults:
                    key = _fault_key(fault)
                    if key not in seen:
                        seen[key] = None
                        if event_id > 0:  # faults older than the stream are in the first status
                            event_id += 1
                            yield _sse("fault", fault.model_dump_json(), event_id)
                event_id += 1
                yield _sse("status", status.model_dump_json(), event_id)
                sent_status += 1
                if limit is not None and sent_status >= limit:
                    return
                next_tick += period
                if next_tick < now:  # fell behind (slow engine, slow client): no burst
                    next_tick = now + period
                while len(seen) > 1024:
                    del seen[next(iter(seen))]
                continue
            try:
                item = await asyncio.wait_for(sub.queue.get(), timeout=next_tick - now)
            except TimeoutError:
                continue
            if item is None:
                return
            if isinstance(item, ScanEvent):
                event_id += 1
                yield _sse(item.kind, item.model_dump_json(), event_id)
                continue
            key = _fault_key(item)
            if key not in seen:
                seen[key] = None
                event_id += 1
                yield _sse("fault", item.model_dump_json(), event_id)
    finally:
        hub._unsubscribe(sub)


_DESCRIPTION = """\
Control a running **piezod** daemon: start, change and stop raster scans, move the
stage, follow its state live, and download the recordings it wrote.

Connect over the daemon's Unix socket (default `/run/piezod/piezod.sock`, mode 0660), e.g.
`curl --unix-socket /run/piezod/piezod.sock http://piezod/v1/status`, or use `piezod ctl`.
A TCP listener off the loopback interface requires `Authorization: Bearer <token>` on every request.

Every request is validated twice: by its schema (422 naming the field) and by the engine against
the scanner's voltage limits and model (422 with the reason, e.g. a range the stage cannot reach).
Requests that do not fit the engine's state (a scan already running, a fault) get 409.
Errors are `{"detail": "<one line>", "error": "<name>"}`.
"""

_TAGS = [
    {"name": "status", "description": "What the daemon is doing, as a snapshot or a live event stream."},
    {"name": "scan", "description": "Raster scans and moves."},
    {"name": "recordings", "description": "Sensor recordings the daemon wrote (CSV, docs/formats.md)."},
]

_E409: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorBody, "description": "the engine's state does not allow it (busy, fault)"}
}
_E429: dict[int | str, dict[str, Any]] = {
    429: {"model": ErrorBody, "description": "another scan is being checked: nothing changed; retry"}
}
_E422_ENGINE = "invalid body (naming the field), or refused by the engine's limits or model (with the reason)"
_E503: dict[int | str, dict[str, Any]] = {
    503: {"model": ErrorBody, "description": "the board is unavailable"}
}
_E500: dict[int | str, dict[str, Any]] = {
    500: {"model": ErrorBody, "description": "internal error (details in the daemon log)"}
}

_BUSY_REASONS = {
    "scanning": "a scan is running; change it with PATCH /v1/scan or stop it first",
    "moving": "a move is in progress; wait for it or stop it first",
    "starting": "the engine is starting; retry in a moment",
    "stopping": "the engine is stopping; retry in a moment",
    "disconnected": "the board is disconnected",
}


class _LoggedRoute(APIRoute):
    """Answers an unexpected exception with a JSON 500 and logs its traceback.

    Catching it here, not in an ``Exception`` handler, keeps the connection open:
    Starlette re-raises from such a handler and the server then drops the
    keep-alive connection, failing the client's next request.
    """

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def run(request: Request) -> Response:
            try:
                return await handler(request)
            except (StarletteHTTPException, RequestValidationError, _RefusedError):
                raise
            except Exception:
                log.exception("%s %s failed", request.method, request.url.path)
                body = ErrorBody(detail="internal error; see the daemon log", error="InternalError")
                return JSONResponse(body.model_dump(), 500)

        return run


def _require_state(status: Status, allowed: frozenset[str], action: str) -> None:
    if status.state in allowed:
        return
    if status.state == "fault":
        last = status.faults[-1] if status.faults else None
        why = f" ({last.source} {last.code}: {last.message})" if last else ""
        reason = f"cannot {action}: the engine is in fault{why}; POST /v1/stop to clear it"
    else:
        reason = f"cannot {action}: {_BUSY_REASONS.get(status.state, f'the engine is {status.state}')}"
    log.info("%s refused (409): %s", action, reason)
    raise _RefusedError(409, reason, "EngineStateError")


async def _file_chunks(fd: int, size: int) -> AsyncIterator[bytes]:
    """``size`` bytes of ``fd`` in chunks read in the threadpool; closes ``fd`` even when cancelled."""
    try:
        left = size
        while left > 0:
            chunk = await run_in_threadpool(os.read, fd, min(_CHUNK, left))
            if not chunk:
                raise RecordingError(f"recording shrank while being sent ({left} bytes missing)")
            left -= len(chunk)
            yield chunk
    finally:
        os.close(fd)


def _complete_lines_size(fd: int, size: int) -> int:
    """The size up to the last newline: a recording being written is served as whole lines."""
    end = size
    while end > 0:
        start = max(0, end - _CHUNK)
        block = os.pread(fd, end - start, start)
        cut = block.rfind(b"\n")
        if cut >= 0:
            return start + cut + 1
        end = start
    return 0


@contextlib.asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    from anyio import to_thread

    to_thread.current_default_thread_limiter().total_tokens = API_THREADS
    yield


class _OneAtATime:
    """Admits one scan check at a time; a request arriving meanwhile is answered 429 at once.

    Checking a scan renders its start (seconds of samples) on copies of the axis drivers. Under
    the GIL those renders share the CPU with the streamer's, so concurrent checks from several
    clients could starve the stream into an underrun; refused, they change nothing and the
    client may send them again (``Retry-After``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def __call__(self, action: str) -> Iterator[None]:
        if not self._lock.acquire(blocking=False):
            raise _RefusedError(
                429,
                f"cannot {action} now: another scan is being checked; retry in a moment",
                "Busy",
                {"retry-after": "1"},
            )
        try:
            yield
        finally:
            self._lock.release()


def create_app(
    engine: EngineControl,
    *,
    token: str | None = None,
    events: EventHub | None = None,
) -> FastAPI:
    """Build the control API around an engine.

    Parameters
    ----------
    engine
        The streaming engine (or a fake).
    token
        If given, every request needs ``Authorization: Bearer <token>`` (401 otherwise).
        :class:`~piezod.service.server.ApiServer` adds it itself on TCP listeners with a
        configured ``api.token_file``.
    events
        The hub feeding ``GET /v1/events``; give the engine the same hub for
        immediate fault events. A 5 Hz hub is created when omitted. It is
        ``app.state.events``.

    Returns
    -------
    FastAPI
        The ASGI app.
    """
    hub = events if events is not None else EventHub()
    app = FastAPI(
        title="piezod control API",
        version=__version__,
        description=_DESCRIPTION,
        openapi_tags=_TAGS,
        responses=_E500,
        lifespan=_lifespan,
    )
    app.router.route_class = _LoggedRoute
    app.state.engine = engine
    app.state.events = hub
    heavy = _OneAtATime()

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        # the default handler echoes the input (unbounded, maybe not JSON-safe): name the fields only
        errors = exc.errors()
        detail = [
            {
                "loc": list(e.get("loc", ())),
                "msg": _one_line(str(e.get("msg", "invalid")))[:200],
                "type": e.get("type"),
            }
            for e in errors[:20]
        ]
        log.info("%s %s refused (422): %d invalid field(s)", request.method, request.url.path, len(errors))
        return JSONResponse({"detail": detail, "error": "ValidationError"}, 422)

    @app.exception_handler(_RefusedError)
    async def _refusal(request: Request, exc: _RefusedError) -> JSONResponse:
        body = ErrorBody(detail=exc.detail, error=exc.error).model_dump()
        return JSONResponse(body, exc.status_code, headers=exc.headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # Last resort (errors outside the routes): Starlette re-raises, so the server logs it.
        return JSONResponse(
            ErrorBody(detail="internal error; see the daemon log", error="InternalError").model_dump(), 500
        )

    @app.get("/v1/status", tags=["status"], summary="Status snapshot", response_description="the status")
    def get_status() -> Status:
        """What the daemon is doing now: state, scan, FIFO level, faults, last line's linearity."""
        return _engine_call("status", engine.status)

    @app.post(
        "/v1/scan",
        tags=["scan"],
        status_code=202,
        summary="Start a scan",
        response_description="accepted: the status with the scan starting",
        responses={**_E409, **_E429, **_E503, 422: {"description": _E422_ENGINE}},
    )
    def post_scan(request: ScanRequest) -> Status:
        """Check the scan against the limits and the model, then start it (the engine must be idle)."""
        _require_state(_engine_call("status", engine.status), frozenset({"idle"}), "start a scan")
        with heavy("start a scan"):
            return _engine_call("scan start", engine.start_scan, request)

    @app.patch(
        "/v1/scan",
        tags=["scan"],
        summary="Change the running scan",
        response_description="the status with the changed scan",
        responses={**_E409, **_E429, **_E503, 422: {"description": _E422_ENGINE}},
    )
    def patch_scan(change: ScanChange) -> Status:
        """Change range, line rate, offsets or rotation of the running scan at its next line."""
        if not change.model_fields_set:
            raise _RefusedError(422, "nothing to change: give at least one field", "ValidationError")
        _require_state(_engine_call("status", engine.status), frozenset({"scanning"}), "change the scan")
        with heavy("change the scan"):
            return _engine_call("scan change", engine.change_scan, change)

    @app.post(
        "/v1/stop",
        tags=["scan"],
        summary="Stop",
        response_description="the status after stopping",
        responses=_E503,
    )
    def post_stop() -> Status:
        """Stop scanning or moving and hold; ramp to the safe value when nothing runs. Clears a fault."""
        return _engine_call("stop", engine.stop)

    @app.post(
        "/v1/move",
        tags=["scan"],
        status_code=202,
        summary="Move and hold",
        response_description="accepted: the status with the move starting",
        responses={**_E409, **_E503, 422: {"description": _E422_ENGINE}},
    )
    def post_move(request: MoveRequest) -> Status:
        """Move to a position at a limited speed, then hold it (not while scanning)."""
        if request.x_um is None and request.y_um is None and request.z_um is None:
            raise _RefusedError(
                422, "nothing to move: give at least one of x_um, y_um, z_um", "ValidationError"
            )
        _engine_call("move check", engine.check_move, request)
        _require_state(_engine_call("status", engine.status), frozenset({"idle", "moving"}), "move")
        return _engine_call("move", engine.move, request)

    @app.get(
        "/v1/recordings",
        tags=["recordings"],
        summary="List recordings",
        response_description="the recordings",
    )
    def get_recordings() -> list[RecordingInfo]:
        """The recordings in the daemon's recording directory."""
        return _engine_call("recordings", engine.recordings)

    @app.get(
        "/v1/recordings/{name}",
        tags=["recordings"],
        summary="Download a recording",
        response_class=StreamingResponse,
        responses={
            200: {"content": {"text/csv": {}}, "description": "the recording (CSV)"},
            404: {"model": ErrorBody, "description": "no recording of that name"},
        },
    )
    async def get_recording(
        name: Annotated[str, Path(description="recording name, as listed by GET /v1/recordings")],
    ) -> StreamingResponse:
        """The recording as CSV. One still being written is served up to its last complete line."""
        if not RECORDING_NAME.match(name):
            log.info("recording %r refused: not a plain name", name)
            raise _RefusedError(404, f"no recording named {name!r}", "FileNotFoundError")
        fd = await run_in_threadpool(_open_recording, engine, name)
        try:
            size = await run_in_threadpool(_complete_lines_size, fd, os.fstat(fd).st_size)
        except BaseException:
            os.close(fd)
            raise
        headers = {
            "content-length": str(size),
            "content-disposition": f'attachment; filename="{name}"',
            "cache-control": "no-store",
        }
        return StreamingResponse(
            _file_chunks(fd, size), media_type="text/csv; charset=utf-8", headers=headers
        )

    @app.get(
        "/v1/events",
        tags=["status"],
        summary="Live status (server-sent events)",
        response_class=StreamingResponse,
        responses={
            200: {
                "content": {"text/event-stream": {}},
                "description": "`event: status` (a Status, at the rate) and `event: fault` (a FaultInfo, "
                "as it happens); with `scans=true` also `event: line` and `event: frame` (a ScanEvent: a "
                "trace or retrace, a frame finished; a frame's images written); `event: error` ends the "
                "stream after an engine failure",
            },
            503: {"model": ErrorBody, "description": "the daemon is shutting down"},
        },
    )
    async def get_events(
        rate_hz: Annotated[
            float | None, Query(gt=0, le=MAX_EVENT_RATE_HZ, description="status events per second")
        ] = None,
        limit: Annotated[
            int | None, Query(ge=1, description="end the stream after this many status events")
        ] = None,
        scans: Annotated[bool, Query(description="also line and frame events of scans")] = False,
    ) -> StreamingResponse:
        """Server-sent events: status snapshots at ``rate_hz`` (default 5 Hz), faults at once."""
        if hub.closed:
            raise _RefusedError(503, "the daemon is shutting down", "ShuttingDown")
        if hub.subscribers >= MAX_EVENT_STREAMS:
            raise _RefusedError(
                503, f"{MAX_EVENT_STREAMS} event streams are open already; retry later", "Busy"
            )
        return StreamingResponse(
            _event_stream(engine, hub, rate_hz or hub.rate_hz, limit, scans),
            media_type="text/event-stream",
            headers={"cache-control": "no-cache", "x-accel-buffering": "no"},
        )

    if token is not None:
        app.add_middleware(BearerTokenMiddleware, token=token)
    return app


def _open_recording(engine: EngineControl, name: str) -> int:
    """Open a recording read-only; 404 for unknown names, symlinks and non-files."""
    try:
        path = engine.recording_path(name)
    except FileNotFoundError as exc:
        log.info("recording %r: not found", name)
        raise _RefusedError(404, f"no recording named {name!r}", "FileNotFoundError") from exc
    except Exception as exc:
        raise _refusal_for("recording lookup", exc) from exc
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        log.info("recording %r: cannot open %s: %s", name, path, exc.strerror or exc)
        raise _RefusedError(404, f"no recording named {name!r}", "FileNotFoundError") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        log.info("recording %r: %s is not a regular file", name, path)
        raise _RefusedError(404, f"no recording named {name!r}", "FileNotFoundError")
    return fd
