"""Python client of a running daemon's control API (``piezod serve``).

::

    from piezod.client import PiezodClient

    with PiezodClient("unix:/run/piezod/sim-stage.sock") as daemon:
        daemon.scan(range_um=10, line_rate_hz=2, lines=128, name="sample-a")
        for event in daemon.events(limit=10):
            print(event)
        daemon.stop()
        daemon.fetch_recording("sample-a.csv", "data/")

Errors: an HTTP error answer raises :class:`~piezod.errors.ApiError` (status code,
the server's reason in one line); no answer at all raises
:class:`~piezod.errors.ApiUnreachableError`.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import tempfile
import time
from collections.abc import Generator, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any
from urllib.parse import quote

import httpx

from piezod.errors import ApiError, ApiUnreachableError
from piezod.service.schemas import (
    FaultInfo,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanEvent,
    ScanRequest,
    Status,
)
from piezod.service.server import parse_api_spec
from piezod.service.sockets import discover_api_spec

#: Environment variable naming the API of ``piezod ctl`` and of a client without a spec.
API_ENV = "PIEZOD_API"


def default_api_spec() -> str:
    """``$PIEZOD_API``, else the one running daemon's socket.

    See :func:`~piezod.service.sockets.discover_api_spec`.
    """
    return os.environ.get(API_ENV) or discover_api_spec()


def _format_detail(body: Any) -> str:
    """One line from an error body: a string detail, or FastAPI's validation list."""
    detail = body.get("detail") if isinstance(body, dict) else None
    if isinstance(detail, str):
        return " ".join(detail.split())
    if isinstance(detail, list):
        parts = []
        for err in detail:
            if not isinstance(err, dict):
                parts.append(str(err))
                continue
            loc = [str(p) for p in err.get("loc", [])]
            if len(loc) > 1 and loc[0] in ("body", "query", "path"):
                loc = loc[1:]
            field = ".".join(loc)
            msg = str(err.get("msg", "invalid"))
            parts.append(f"{field}: {msg}" if field else msg)
        return "; ".join(parts)
    return ""


class PiezodClient:
    """Talk to ``piezod serve`` over its Unix socket or TCP.

    Parameters
    ----------
    spec
        ``unix:PATH`` or ``tcp:HOST:PORT``; default ``$PIEZOD_API`` or the socket of the one
        running daemon (:func:`~piezod.service.sockets.discover_api_spec`).
    token
        Bearer token, for a TCP API with a token file.
    timeout
        Seconds to wait for connecting and for each answer.
    """

    def __init__(self, spec: str | None = None, token: str | None = None, timeout: float = 10.0) -> None:
        self.spec = parse_api_spec(spec if spec is not None else default_api_spec())
        self.timeout = timeout
        headers = {"accept": "application/json", "user-agent": "piezod-client"}
        if token is not None:
            headers["authorization"] = f"Bearer {token.strip()}"
        if self.spec.kind == "unix":
            transport = httpx.HTTPTransport(uds=self.spec.path)
            base_url = "http://piezod"
        else:
            transport = httpx.HTTPTransport()
            host = f"[{self.spec.host}]" if ":" in self.spec.host else self.spec.host
            base_url = f"http://{host}:{self.spec.port}"
        self._http = httpx.Client(
            transport=transport, base_url=base_url, headers=headers, timeout=timeout, trust_env=False
        )

    # ---------------------------------------------------------------------- plumbing

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> PiezodClient:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _unreachable(self, method: str, path: str, exc: httpx.TransportError) -> ApiUnreachableError:
        if isinstance(exc, httpx.TimeoutException):
            why = f"no answer within {self.timeout:g} s"
        else:
            why = str(exc) or type(exc).__name__
            cause: BaseException | None = exc
            while cause is not None:  # the OSError deep inside httpcore names the real reason
                if isinstance(cause, OSError) and cause.strerror:
                    why = cause.strerror
                    break
                cause = cause.__cause__ or cause.__context__
        hint = " (is piezod serve running?)" if isinstance(exc, httpx.ConnectError) else ""
        return ApiUnreachableError(f"{method} {path}: cannot reach {self.spec}: {why}{hint}")

    @staticmethod
    def _check(response: httpx.Response) -> None:
        if response.is_success:
            return
        try:
            body = json.loads(response.read())
        except (ValueError, httpx.StreamError):
            body = None
        detail = _format_detail(body) or response.reason_phrase or "error"
        error = body.get("error") if isinstance(body, dict) else None
        method = response.request.method
        path = response.request.url.path
        raise ApiError(
            f"{method} {path}: {detail} (HTTP {response.status_code})",
            status_code=response.status_code,
            detail=detail,
            error=error if isinstance(error, str) else None,
        )

    def _retry_after(self, response: httpx.Response, deadline: float) -> bool:
        """True (after waiting) if a 429 may be retried before ``deadline``.

        The daemon answers 429 before a request reaches the engine, so any request may be sent again.
        """
        if response.status_code != 429:
            return False
        try:
            wait = min(max(float(response.headers.get("retry-after", "1")), 0.05), 5.0)
        except ValueError:
            wait = 1.0
        wait *= 0.5 + random.random()  # spread the retries of many clients
        if time.monotonic() + wait > deadline:
            return False
        time.sleep(wait)
        return True

    def _request(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        try:
            content = None if body is None else json.dumps(body, allow_nan=False).encode()
        except ValueError as exc:
            raise ApiError(f"{method} {path}: {exc} (numbers must be finite)", status_code=None) from exc
        headers = {"content-type": "application/json"} if content is not None else None
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                response = self._http.request(method, path, content=content, headers=headers)
            except httpx.TransportError as exc:
                raise self._unreachable(method, path, exc) from exc
            if not self._retry_after(response, deadline):
                break
        self._check(response)
        return response.json()

    # ---------------------------------------------------------------------- API

    def status(self) -> Status:
        """A status snapshot (``GET /v1/status``)."""
        return Status.model_validate(self._request("GET", "/v1/status"))

    def scan(self, request: ScanRequest | None = None, **fields: Any) -> Status:
        """Start a scan (``POST /v1/scan``).

        Give a :class:`ScanRequest` or its fields (``range_um=10, line_rate_hz=2, ...``);
        the fields are checked by the server, so a bad one comes back as an
        :class:`ApiError` with status 422 naming it.
        """
        body = request.model_dump(exclude_unset=True) if request is not None else {}
        body.update(fields)
        return Status.model_validate(self._request("POST", "/v1/scan", body))

    def change(self, change: ScanChange | None = None, **fields: Any) -> Status:
        """Change the running scan at its next line (``PATCH /v1/scan``)."""
        body = change.model_dump(exclude_unset=True) if change is not None else {}
        body.update(fields)
        return Status.model_validate(self._request("PATCH", "/v1/scan", body))

    def stop(self) -> Status:
        """Stop scanning or moving and hold; clears a fault (``POST /v1/stop``)."""
        return Status.model_validate(self._request("POST", "/v1/stop"))

    def move(self, request: MoveRequest | None = None, **fields: Any) -> Status:
        """Move to a position and hold it (``POST /v1/move``), e.g. ``move(x_um=1.5, y_um=-2)``."""
        body = request.model_dump(exclude_unset=True) if request is not None else {}
        body.update(fields)
        return Status.model_validate(self._request("POST", "/v1/move", body))

    def recordings(self) -> list[RecordingInfo]:
        """The daemon's recordings (``GET /v1/recordings``)."""
        return [RecordingInfo.model_validate(r) for r in self._request("GET", "/v1/recordings")]

    def openapi(self) -> dict[str, Any]:
        """The OpenAPI document."""
        doc: dict[str, Any] = self._request("GET", "/openapi.json")
        return doc

    @contextlib.contextmanager
    def _stream(
        self, path: str, params: dict[str, Any] | None = None, read_timeout: float | None = None
    ) -> Iterator[httpx.Response]:
        timeout = httpx.Timeout(self.timeout, read=read_timeout if read_timeout else self.timeout)
        deadline = time.monotonic() + self.timeout
        try:
            while True:
                with self._http.stream("GET", path, params=params, timeout=timeout) as response:
                    if response.status_code == 429:
                        response.read()
                    if self._retry_after(response, deadline):
                        continue
                    self._check(response)
                    yield response
                    return
        except httpx.TransportError as exc:
            raise self._unreachable("GET", path, exc) from exc

    def iter_recording(self, name: str) -> Iterator[bytes]:
        """The bytes of a recording, in chunks (``GET /v1/recordings/{name}``)."""
        path = f"/v1/recordings/{quote(name, safe='')}"
        with self._stream(path) as response:
            expected = response.headers.get("content-length")
            got = 0
            for chunk in response.iter_bytes():
                got += len(chunk)
                yield chunk
            if expected is not None and got != int(expected):
                raise ApiError(f"GET {path}: got {got} of {expected} bytes", status_code=response.status_code)

    def fetch_recording(self, name: str, dest: str | Path | None = None) -> Path:
        """Download a recording; returns the file written.

        Parameters
        ----------
        name
            As listed by :meth:`recordings`.
        dest
            A file, or a directory to put ``name`` in: an existing one, or one named
            with a trailing ``/`` (created); default ``./name``. Missing parent
            directories are created. Written to a temporary file first and renamed,
            so an interrupted download leaves nothing behind.
        """
        target = Path(dest) if dest is not None else Path(name)
        if target.is_dir() or str(dest).endswith(("/", os.sep)):
            target = target / name
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as out:
                for chunk in self.iter_recording(name):
                    out.write(chunk)
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        return target

    def events(
        self, *, rate_hz: float | None = None, limit: int | None = None, scans: bool = False
    ) -> Generator[Status | FaultInfo | ScanEvent, None, None]:
        """Follow the daemon live (``GET /v1/events``, server-sent events).

        Yields a :class:`Status` per snapshot (at ``rate_hz``, default the
        daemon's 5 Hz) and a :class:`FaultInfo` as soon as a fault happens. Ends
        after ``limit`` snapshots, when the daemon shuts down, or when the
        caller stops iterating (the connection is then closed). With ``scans`` also a
        :class:`ScanEvent` per finished line and frame of a scan.

        Raises
        ------
        ApiError
            If the daemon reports an error on the stream.
        """
        params: dict[str, Any] = {}
        if rate_hz is not None:
            params["rate_hz"] = rate_hz
        if limit is not None:
            params["limit"] = limit
        if scans:
            params["scans"] = "true"
        period = 1.0 / rate_hz if rate_hz else 1.0
        with self._stream("/v1/events", params, read_timeout=max(self.timeout, 5 * period)) as response:
            event = "message"
            data: list[str] = []
            for line in response.iter_lines():
                if line == "":
                    if data:
                        yield _parse_event(event, "\n".join(data))
                    event, data = "message", []
                elif line.startswith(":"):
                    continue
                else:
                    key, _, value = line.partition(":")
                    value = value.removeprefix(" ")
                    if key == "event":
                        event = value
                    elif key == "data":
                        data.append(value)


def _parse_event(event: str, data: str) -> Status | FaultInfo | ScanEvent:
    if event == "status":
        return Status.model_validate_json(data)
    if event in ("line", "frame"):
        return ScanEvent.model_validate_json(data)
    if event == "fault":
        return FaultInfo.model_validate_json(data)
    if event == "error":
        try:
            detail = _format_detail(json.loads(data)) or data
        except ValueError:
            detail = data
        raise ApiError(f"GET /v1/events: {detail}", status_code=None, detail=detail)
    raise ApiError(f"GET /v1/events: unknown event type {event!r}")
