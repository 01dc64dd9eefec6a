"""The API's request guards, pure ASGI middlewares in front of the app (:mod:`piezod.service.api`):
bounded bodies and JSON, Host / Origin checks against DNS rebinding, a request rate limit
(429), and the bearer token of TCP listeners; their answers are the API's one-line
:class:`ErrorBody`.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import time
from typing import Any

from pydantic import BaseModel
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from piezod.errors import (
    ConfigError,
)

log = logging.getLogger(__name__)


class ErrorBody(BaseModel):
    """An error answer."""

    detail: str
    error: str | None = None


# --------------------------------------------------------------------------------------------- auth


#: Largest request body accepted (bytes); the biggest valid body is a few hundred bytes.
MAX_BODY_BYTES = 16 * 1024
#: Most members of a JSON object / items of an array in a body, and deepest nesting.
MAX_JSON_MEMBERS = 64
MAX_JSON_DEPTH = 4
#: Requests per second the API serves (a burst of as many is allowed); beyond, 429 after a delay.
MAX_REQUESTS_PER_S = 50.0
THROTTLE_DELAY_S = 0.1
#: Open event streams at most (503 beyond).
MAX_EVENT_STREAMS = 8
#: Threads running engine calls at most (the stream's threads share the interpreter with them).
API_THREADS = 4
#: Host names every listener answers to (the client's ``http://piezod`` over the Unix socket, loopback).
LOOPBACK_HOSTS = frozenset({"piezod", "localhost", "127.0.0.1", "::1"})


async def _answer(
    send: Send, status: int, detail: str, error: str, headers: dict[str, str] | None = None
) -> None:
    """A JSON error answer sent straight from a middleware (connection closed afterwards)."""
    body = ErrorBody(detail=detail, error=error).model_dump_json().encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class _BodyError(ValueError):
    pass


def _reject_constant(name: str) -> Any:
    raise _BodyError(f"{name} is not allowed in JSON (numbers must be finite)")


def _bounded_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    if len(pairs) > MAX_JSON_MEMBERS:
        raise _BodyError(f"an object with {len(pairs)} members (at most {MAX_JSON_MEMBERS})")
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _BodyError(f"duplicate key {key!r}")
        out[key] = value
    return out


def check_json_body(body: bytes) -> None:
    """Refuse a body that is not small, strict JSON: NaN / Infinity, duplicate keys, many members, depth.

    Raises
    ------
    ValueError
        One line saying what is wrong.
    """
    depth = 0
    for byte in body:
        if byte in b"[{":
            depth += 1
            if depth > MAX_JSON_DEPTH:
                raise _BodyError(f"nested deeper than {MAX_JSON_DEPTH} levels")
        elif byte in b"]}":
            depth -= 1
    try:
        value = json.loads(body, parse_constant=_reject_constant, object_pairs_hook=_bounded_object)
    except _BodyError:
        raise
    except (ValueError, RecursionError) as exc:
        raise _BodyError(f"not valid JSON: {exc}") from None

    def walk(v: Any) -> None:
        if isinstance(v, list):
            if len(v) > MAX_JSON_MEMBERS:
                raise _BodyError(f"an array with {len(v)} items (at most {MAX_JSON_MEMBERS})")
            for item in v:
                walk(item)
        elif isinstance(v, dict):
            for item in v.values():
                walk(item)

    walk(value)


def _host_name(value: str) -> str:
    """The host part of a Host header or an Origin's authority (no port, no brackets, lower case)."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class RequestGuardMiddleware:
    """What every request must pass before the app sees it (a pure ASGI middleware).

    - ``Host`` must name this listener (``allowed_hosts``), so a web page on another name that
      resolves to 127.0.0.1 (DNS rebinding) is refused (403);
    - a request with an ``Origin`` (a browser on a web page) must come from an allowed host (403);
    - a body must be ``application/json`` (415; a cross-site ``text/plain`` or form POST is refused),
      at most :data:`MAX_BODY_BYTES` (413, read no further) and strict, small JSON (422: no NaN /
      Infinity, no duplicate keys, at most :data:`MAX_JSON_MEMBERS` members, depth
      :data:`MAX_JSON_DEPTH`). All of it is checked without the engine, in microseconds.

    Parameters
    ----------
    app
        The app.
    allowed_hosts
        Host names accepted in ``Host`` and ``Origin``; None accepts any ``Host`` (remote
        listeners, where the token protects) but still refuses any ``Origin``.
    max_body_bytes
        Body size limit.
    """

    def __init__(
        self,
        app: ASGIApp,
        allowed_hosts: frozenset[str] | None = LOOPBACK_HOSTS,
        max_body_bytes: int = MAX_BODY_BYTES,
        max_requests_per_s: float = MAX_REQUESTS_PER_S,
    ) -> None:
        self.app = app
        self.allowed_hosts = allowed_hosts
        self.max_body_bytes = max_body_bytes
        self.max_requests_per_s = max_requests_per_s
        self._bucket = max_requests_per_s
        self._bucket_t = time.monotonic()
        self.throttled = 0

    def _admit(self) -> bool:
        now = time.monotonic()
        rate = self.max_requests_per_s
        self._bucket = min(rate, self._bucket + (now - self._bucket_t) * rate)
        self._bucket_t = now
        if self._bucket < 1.0:
            return False
        self._bucket -= 1.0
        return True

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if not self._admit():
            # the stream shares this process: the API's share of it is bounded, whoever asks
            self.throttled += 1
            _throttled_log("rate", "API requests throttled: more than %g per second", self.max_requests_per_s)
            await asyncio.sleep(THROTTLE_DELAY_S)
            await _answer(
                send, 429, "too many requests; retry later", "TooManyRequests", {"retry-after": "1"}
            )
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        what = f"{scope.get('method')} {scope.get('path')}"
        host = _host_name(headers.get("host", ""))
        if self.allowed_hosts is not None and host not in self.allowed_hosts:
            _throttled_log("host", "API request refused: Host %r is not served here (%s)", host[:100], what)
            await _answer(send, 403, f"Host {host[:100]!r} is not served here", "Forbidden")
            return
        origin = headers.get("origin")
        if origin is not None:
            o_host = _host_name(origin.split("://", 1)[-1].split("/", 1)[0])
            allowed = self.allowed_hosts if self.allowed_hosts is not None else frozenset({host})
            if origin == "null" or o_host not in allowed:
                _throttled_log("origin", "API request refused: cross-site Origin %r (%s)", origin[:100], what)
                await _answer(
                    send, 403, f"cross-site request from Origin {origin[:100]!r} refused", "Forbidden"
                )
                return
        method = scope.get("method", "GET")
        length_text = headers.get("content-length")
        ctype = headers.get("content-type")
        chunked = "chunked" in headers.get("transfer-encoding", "").lower()
        has_body = chunked or (length_text is not None and length_text.strip() != "0")
        if method in ("GET", "HEAD", "OPTIONS", "DELETE") and not has_body:
            await self.app(scope, receive, send)
            return
        if ctype is not None and ctype.split(";", 1)[0].strip().lower() != "application/json":
            await _answer(
                send, 415, f"request bodies must be application/json, not {ctype[:60]!r}", "ValidationError"
            )
            return
        if has_body and ctype is None:
            await _answer(send, 415, "request bodies must be application/json", "ValidationError")
            return
        if length_text is not None:
            try:
                length = int(length_text)
            except ValueError:
                await _answer(send, 400, "invalid Content-Length", "ValidationError")
                return
            if length > self.max_body_bytes:
                await _answer(
                    send, 413, f"body of {length} bytes; at most {self.max_body_bytes}", "ValidationError"
                )
                return
        chunks: list[bytes] = []
        size = 0
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body_bytes:
                await _answer(send, 413, f"body larger than {self.max_body_bytes} bytes", "ValidationError")
                return
            chunks.append(chunk)
            more = bool(message.get("more_body", False))
        body = b"".join(chunks)
        if body:
            try:
                check_json_body(body)
            except _BodyError as exc:
                log.info("%s refused (422): body %s", what, exc)
                await _answer(send, 422, f"body: {exc}", "ValidationError")
                return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class _LogThrottle:
    """At most one log line per kind per :attr:`period_s`; the next one says how many were held back."""

    period_s = 10.0

    def __init__(self) -> None:
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def __call__(self, kind: str, msg: str, *args: object) -> None:
        now = time.monotonic()
        last = self._last.get(kind)
        if last is not None and now - last < self.period_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            return
        held = self._held.pop(kind, 0)
        self._last[kind] = now
        suffix = (
            f" (and {held} more like it in the last {now - last:.0f} s)" if held and last is not None else ""
        )
        log.warning(msg + suffix, *args)


_throttled_log = _LogThrottle()


class BearerTokenMiddleware:
    """Refuse every HTTP request without ``Authorization: Bearer <token>`` (401).

    A pure ASGI middleware (streaming answers pass untouched); the token is compared in
    constant time. Refusals are logged at most once per 10 s (with the count held back); each
    is answered after a short delay, and beyond :attr:`max_failures_per_s` failures per second
    after 1 s with 429, so guessing is slow and cannot flood the journal or the event loop.
    The right token is never delayed.
    """

    max_failures_per_s = 10.0
    failure_delay_s = 0.05

    def __init__(self, app: ASGIApp, token: str) -> None:
        token = token.strip()
        if not token:
            raise ConfigError("the API token is empty")
        self.app = app
        self._expected = f"Bearer {token}".encode()
        self._bucket = self.max_failures_per_s
        self._bucket_t = time.monotonic()
        self.refused = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = b""
        for name, value in scope.get("headers", []):
            if name == b"authorization":
                given = value
                break
        if hmac.compare_digest(given, self._expected):
            await self.app(scope, receive, send)
            return
        now = time.monotonic()
        self._bucket = min(
            self.max_failures_per_s, self._bucket + (now - self._bucket_t) * self.max_failures_per_s
        )
        self._bucket_t = now
        self._bucket -= 1.0
        self.refused += 1
        reason = "missing bearer token" if not given else "invalid bearer token"
        _throttled_log(
            "token", "API request refused: %s (%s %s)", reason, scope.get("method"), scope.get("path")
        )
        if self._bucket < 0:  # a burst of failures: guessing, not a typo
            self._bucket = max(self._bucket, -self.max_failures_per_s)
            await asyncio.sleep(1.0)
            await _answer(
                send,
                429,
                "too many failed authentications; retry later",
                "Unauthorized",
                {"retry-after": "1"},
            )
            return
        await asyncio.sleep(self.failure_delay_s)
        await _answer(send, 401, reason, "Unauthorized", {"www-authenticate": "Bearer"})


# --------------------------------------------------------------------------------------------- app
