"""Serving the control API: Unix socket (default) or loopback TCP, in a background thread.

``--api unix:PATH`` binds a Unix socket with mode 0660 (group ``api.socket_group``);
nobody can connect before the mode and group are set, because the socket only
listens afterwards. A stale socket file (nobody listening) is removed, anything
else at the path is left alone with an error. ``--api tcp:HOST:PORT`` binds
loopback addresses only, unless ``api.allow_remote``; whenever ``api.token_file``
is required on TCP (every local user can connect to a TCP port), and every TCP request needs
``Authorization: Bearer <token>``. Every request passes
:class:`~piezod.service.guards.RequestGuardMiddleware` first (Host / Origin checks against DNS
rebinding and cross-site posts, bounded strict-JSON bodies).

uvicorn runs in a thread of its own and installs no signal handlers: the daemon
owns SIGTERM and calls :meth:`ApiServer.stop`.
"""

from __future__ import annotations

import contextlib
import grp
import ipaddress
import logging
import os
import socket
import stat
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Literal

from piezod.config import ApiConfig
from piezod.errors import ConfigError

if TYPE_CHECKING:
    import uvicorn
    from starlette.types import ASGIApp

log = logging.getLogger(__name__)

#: ``--api`` default of the daemon and of ``piezod ctl``.
DEFAULT_API_SPEC = "unix:/run/piezod/piezod.sock"

#: Longest Unix socket path (``sun_path`` holds 108 bytes with the terminating NUL on Linux).
_UNIX_PATH_MAX = 107


@dataclass(frozen=True)
class ApiSpec:
    """A parsed ``--api`` value."""

    kind: Literal["unix", "tcp"]
    path: str = ""
    host: str = ""
    port: int = 0

    def __str__(self) -> str:
        if self.kind == "unix":
            return f"unix:{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp:{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """True for Unix sockets and for TCP hosts that only resolve to loopback addresses."""
        if self.kind == "unix":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            pass
        try:
            infos = socket.getaddrinfo(self.host, None, type=socket.SOCK_STREAM)
        except socket.gaierror:
            return False
        return bool(infos) and all(ipaddress.ip_address(info[4][0]).is_loopback for info in infos)


def parse_api_spec(spec: str) -> ApiSpec:
    """Parse ``unix:PATH`` or ``tcp:HOST:PORT`` (IPv6 hosts in brackets: ``tcp:[::1]:8765``).

    Raises
    ------
    ConfigError
        One line naming the spec and what is wrong with it.
    """
    where = f"--api {spec!r}"
    kind, sep, rest = spec.partition(":")
    if not sep or kind not in ("unix", "tcp"):
        raise ConfigError(f"{where}: expected unix:PATH or tcp:HOST:PORT")
    if kind == "unix":
        if not rest:
            raise ConfigError(f"{where}: empty socket path")
        if "\0" in rest:
            raise ConfigError(f"{where}: NUL in socket path")
        if len(os.fsencode(rest)) > _UNIX_PATH_MAX:
            raise ConfigError(f"{where}: socket path longer than {_UNIX_PATH_MAX} bytes")
        return ApiSpec("unix", path=rest)
    if rest.startswith("["):
        host, bracket, tail = rest[1:].partition("]")
        if not bracket or not tail.startswith(":"):
            raise ConfigError(f"{where}: expected tcp:[IPV6]:PORT")
        port_text = tail[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ConfigError(f"{where}: {host!r} is not an IPv6 address") from None
    else:
        host, colon, port_text = rest.rpartition(":")
        if not colon or not host:
            raise ConfigError(f"{where}: expected tcp:HOST:PORT")
        if ":" in host:
            raise ConfigError(f"{where}: put IPv6 addresses in brackets: tcp:[{host}]:{port_text}")
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ConfigError(f"{where}: port {port_text!r} is not a number in 0..65535")
    return ApiSpec("tcp", host=host, port=int(port_text))


def read_token(path: str | Path) -> str:
    """The bearer token in ``path`` (surrounding whitespace stripped; the file at most 1 MiB).

    Raises
    ------
    ConfigError
        If the file cannot be read or holds no token.
    """
    from piezod.config import read_config_text

    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the API token: {exc.strerror or exc}") from exc
    text = read_config_text(Path(path), "token file")
    token = text.strip()
    if not token or any(c.isspace() for c in token):
        raise ConfigError(f"{path}: the API token must be one non-empty word")
    if st.st_mode & stat.S_IROTH:
        log.warning("%s: API token file is readable by everyone; chmod o-r it", path)
    return token


def private_dir(path: Path) -> Path:
    """Create ``path`` (mode 0700) or verify that it is a directory this user owns that nobody else can write.

    A per-user socket directory under a shared ``/tmp`` can be created first by another user
    (to replace the socket with an impostor's); it is then refused, not used.

    Raises
    ------
    ConfigError
        Naming the directory, its owner and mode, and what to do.
    """
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"{path}: cannot create the socket directory: {exc.strerror or exc}") from exc
    st = os.lstat(path)
    uid = os.geteuid()
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"{path}: is not a directory (a symlink?); refusing to put the API socket there")
    if st.st_uid != uid:
        raise ConfigError(
            f"{path}: owned by uid {st.st_uid}, not by this user (uid {uid}); refusing to put the API "
            "socket there (someone else created it): remove it or use --api unix:PATH"
        )
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise ConfigError(
            f"{path}: mode {stat.S_IMODE(st.st_mode):04o} lets other users in; refusing to put the API "
            f"socket there (chmod 700 {path}, or use --api unix:PATH)"
        )
    return path


def _group_id(group: str) -> int:
    if group.isdigit():
        return int(group)
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise ConfigError(f"api.socket_group: no group named {group!r}") from None


def _remove_stale_socket(path: Path) -> None:
    """Remove ``path`` if it is a socket nobody listens on; refuse anything else."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ConfigError(f"{path}: cannot inspect: {exc.strerror or exc}") from exc
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigError(f"{path}: exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(str(path))
    except (ConnectionRefusedError, FileNotFoundError):
        pass  # stale: nobody listening
    except OSError as exc:
        raise ConfigError(f"{path}: cannot probe the existing socket: {exc.strerror or exc}") from exc
    else:
        raise ConfigError(f"{path}: another server is listening on this socket")
    finally:
        probe.close()
    log.info("removing stale API socket %s", path)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def _bind_unix(path: Path, gid: int | None, backlog: int) -> tuple[socket.socket, tuple[int, int]]:
    """Bind and listen on a Unix socket with mode 0660; returns the socket and its (dev, inode)."""
    if not path.parent.is_dir():
        raise ConfigError(f"{path}: directory {path.parent} does not exist")
    _remove_stale_socket(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    bound = False
    try:
        sock.bind(str(path))
        bound = True
        os.chmod(path, 0o660)
        if gid is not None:
            os.chown(path, -1, gid)
        st = os.stat(path)
        sock.listen(backlog)
    except OSError as exc:
        sock.close()
        if bound:
            with contextlib.suppress(OSError):
                os.unlink(path)
        raise ConfigError(f"{path}: cannot serve the API here: {exc.strerror or exc}") from exc
    return sock, (st.st_dev, st.st_ino)


def _bind_tcp(host: str, port: int, backlog: int) -> socket.socket:
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ConfigError(f"tcp:{host}:{port}: cannot resolve {host!r}: {exc.strerror}") from exc
    family, socktype, proto, _, address = infos[0]
    sock = socket.socket(family, socktype, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(backlog)
    except OSError as exc:
        sock.close()
        raise ConfigError(f"tcp:{host}:{port}: cannot listen: {exc.strerror or exc}") from exc
    return sock


def _uvicorn_server(config: uvicorn.Config) -> uvicorn.Server:
    import uvicorn

    class _ThreadServer(uvicorn.Server):
        """uvicorn without signal handlers: the daemon owns SIGTERM/SIGINT."""

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            yield

    return _ThreadServer(config)


class ApiServer:
    """Serve an ASGI app on ``unix:PATH`` or ``tcp:HOST:PORT`` from a background thread.

    Parameters
    ----------
    app
        The app, usually from :func:`piezod.service.api.create_app`. Its
        ``app.state.events`` hub (if any) is closed on :meth:`stop` so that open
        event streams end.
    spec
        ``unix:PATH`` (default :data:`DEFAULT_API_SPEC`) or ``tcp:HOST:PORT``; port 0
        picks a free port (see :attr:`address`).
    api_config
        ``ScannerConfig.api``: socket group, remote access, token file.
    access_log
        Log every request (off: the event streams would flood the journal).
    graceful_timeout_s
        How long :meth:`stop` lets requests finish before cancelling them.
    backlog
        Listen backlog.

    Raises
    ------
    ConfigError
        For a bad spec, a non-loopback TCP host without ``allow_remote``, an
        unreadable token file or an unknown socket group.
    """

    def __init__(
        self,
        app: ASGIApp,
        spec: str = DEFAULT_API_SPEC,
        api_config: ApiConfig | None = None,
        *,
        access_log: bool = False,
        graceful_timeout_s: int = 5,
        backlog: int = 64,
    ) -> None:
        self.api_config = api_config if api_config is not None else ApiConfig()
        self.spec = parse_api_spec(spec)
        self._app = app
        self._access_log = access_log
        self._graceful_timeout_s = graceful_timeout_s
        self._backlog = backlog
        self._token: str | None = None
        self._gid: int | None = None
        if self.spec.kind == "tcp":
            if not self.spec.is_loopback and not self.api_config.allow_remote:
                raise ConfigError(
                    f"--api {self.spec}: {self.spec.host} is not a loopback address; "
                    "set api.allow_remote (with api.token_file) to serve it"
                )
            if not self.api_config.token_file:
                raise ConfigError(
                    f"--api {self.spec}: a TCP listener needs api.token_file (every local user can "
                    "connect to a TCP port); use the Unix socket for access by file permissions"
                )
            self._token = read_token(self.api_config.token_file)
        elif self.api_config.socket_group is not None:
            self._gid = _group_id(self.api_config.socket_group)
        self._sock: socket.socket | None = None
        self._sock_id: tuple[int, int] | None = None
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.address = str(self.spec)

    @property
    def requires_token(self) -> bool:
        """True when every request needs the bearer token."""
        return self._token is not None

    @property
    def running(self) -> bool:
        """True between a successful :meth:`start` and :meth:`stop`."""
        return self._thread is not None and self._thread.is_alive()

    def start(self, timeout_s: float = 10.0) -> None:
        """Bind, start serving in a thread, return once the socket accepts connections.

        Raises
        ------
        ConfigError
            If the socket cannot be bound.
        RuntimeError
            If the server does not come up within ``timeout_s``.
        """
        import uvicorn

        from piezod.service.guards import LOOPBACK_HOSTS, BearerTokenMiddleware, RequestGuardMiddleware

        if self._thread is not None:
            raise RuntimeError("ApiServer already started")
        if self.spec.kind == "unix":
            self._sock, self._sock_id = _bind_unix(Path(self.spec.path), self._gid, self._backlog)
        else:
            self._sock = _bind_tcp(self.spec.host, self.spec.port, self._backlog)
            host, port = self._sock.getsockname()[:2]
            self.address = str(ApiSpec("tcp", host=host, port=port))
        app: ASGIApp = self._app
        if self._token is not None:
            app = BearerTokenMiddleware(app, self._token)
        hosts: frozenset[str] | None = LOOPBACK_HOSTS
        if self.spec.kind == "tcp":
            hosts = LOOPBACK_HOSTS | {self.spec.host.lower()} if self.spec.is_loopback else None
        app = RequestGuardMiddleware(app, hosts)
        config = uvicorn.Config(
            app,
            log_config=None,
            access_log=self._access_log,
            lifespan="auto",
            ws="none",
            server_header=False,
            proxy_headers=False,
            timeout_graceful_shutdown=self._graceful_timeout_s,
        )
        self._server = _uvicorn_server(config)
        sock = self._sock
        self._thread = threading.Thread(target=self._run, args=(sock,), name="piezod-api", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive():
                self._cleanup()
                raise RuntimeError(f"API server on {self.address} failed to start: {self._error!r}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"API server on {self.address} did not start within {timeout_s} s")
            time.sleep(0.005)
        log.info("control API listening on %s%s", self.address, " (token required)" if self._token else "")

    def _run(self, sock: socket.socket) -> None:
        assert self._server is not None
        try:
            self._server.run(sockets=[sock])
        except BaseException as exc:  # SystemExit on a failed lifespan startup, too
            self._error = exc
            log.error("control API server failed: %r", exc, exc_info=exc)

    def stop(self, timeout_s: float = 10.0) -> None:
        """End the event streams, let running requests finish, close and remove the socket.

        Idempotent. Requests still running after the graceful timeout are cancelled.
        """
        from piezod.service.api import EventHub

        hub = getattr(getattr(self._app, "state", None), "events", None)
        if isinstance(hub, EventHub):
            hub.close()
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive() and self._server is not None:
                log.error("control API did not stop within %s s; forcing", timeout_s)
                self._server.force_exit = True
                self._thread.join(timeout_s)
        self._cleanup()

    def _cleanup(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self.spec.kind == "unix" and self._sock_id is not None:
            path = self.spec.path
            with contextlib.suppress(FileNotFoundError):
                st = os.lstat(path)
                if (st.st_dev, st.st_ino) == self._sock_id:  # still ours, not a successor's
                    os.unlink(path)
            self._sock_id = None

    def __enter__(self) -> ApiServer:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
