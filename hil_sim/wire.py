"""A simulated board on the wall clock over a socket pair: the board the link tests talk to.

:class:`WireBoard` runs a :class:`hil_sim.board.Board` in a thread of its own, feeding it the
host's bytes as they arrive and writing what it sends, like the pty server
(:mod:`hil_sim.server`) but in the calling process and over a ``socket.socketpair`` (or a Unix
stream socket), so a test can reach into the board (its counters, :attr:`Board.faults`) while
the host streams. Every :meth:`connect` plugs a fresh wire in (the previous one is cut);
:meth:`unplug` cuts it and refuses new ones for a while; :attr:`silent` makes the board deaf
and mute (a hung firmware). The board keeps running through all of it, as hardware would.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from types import TracebackType

from hil_sim.board import Board
from hil_sim.errors import SimLinkClosedError

_POLL_S = 0.0005


class WireBoard:
    """See the module docstring.

    Parameters
    ----------
    board
        The simulated board (its clock is reset to ``time.monotonic()``).
    """

    def __init__(self, board: Board) -> None:
        self.board = board
        self.lock = threading.RLock()
        #: Deaf and mute while True (bytes from the host are discarded, nothing is sent).
        self.silent = False
        self._sock: socket.socket | None = None
        self._listener: socket.socket | None = None
        self._unplugged_until = 0.0
        self._running = True
        self._t0 = time.monotonic() - board.time
        self._thread = threading.Thread(target=self._run, name="hil-sim-wire", daemon=True)
        self._thread.start()

    def _now(self) -> float:
        return time.monotonic() - self._t0

    # -- wiring -------------------------------------------------------------------------------

    def connect(self) -> socket.socket:
        """Plug a fresh wire in; return the host's end (a connected stream socket).

        Raises
        ------
        SimLinkClosedError
            While unplugged.
        """
        with self.lock:
            if time.monotonic() < self._unplugged_until:
                raise SimLinkClosedError("hil_sim wire: unplugged")
            host, dev = socket.socketpair()
            self._attach(dev)
        return host

    def serve_unix(self, path: str) -> None:
        """Also accept connections on a Unix stream socket at ``path`` (the latest one is wired)."""
        lst = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        lst.bind(path)
        lst.listen(1)
        self._listener = lst

        def accept() -> None:
            while self._running:
                try:
                    conn, _ = lst.accept()
                except OSError:
                    return
                with self.lock:
                    self._attach(conn)

        threading.Thread(target=accept, name="hil-sim-wire-accept", daemon=True).start()

    def _attach(self, sock: socket.socket) -> None:
        self._cut()
        sock.setblocking(False)
        self._sock = sock

    def _cut(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
            self._sock = None

    def unplug(self, seconds: float) -> None:
        """Cut the wire; :meth:`connect` fails for ``seconds``. The board keeps running."""
        with self.lock:
            self._unplugged_until = time.monotonic() + seconds
            self._cut()

    def close(self) -> None:
        """Stop the board's thread and cut every wire."""
        self._running = False
        self._thread.join(timeout=5.0)
        with self.lock:
            self._cut()
            if self._listener is not None:
                self._listener.close()

    def __enter__(self) -> WireBoard:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- the board's loop ---------------------------------------------------------------------

    def _run(self) -> None:
        while self._running:
            with self.lock:
                sock = self._sock
            data = b""
            if sock is None:
                time.sleep(_POLL_S)
            else:
                try:
                    ready, _, _ = select.select([sock], [], [], _POLL_S)
                    if ready:
                        data = sock.recv(65536)
                        if not data:
                            self._drop(sock)
                except OSError:
                    self._drop(sock)
            with self.lock:
                if data and not self.silent:
                    self.board.feed(data, self._now())
                self.board.advance(self._now())
                out = self.board.data_to_send()
                sock = self._sock
            if out and sock is not None and not self.silent:
                try:
                    sock.setblocking(True)
                    sock.settimeout(1.0)
                    sock.sendall(out)
                    sock.setblocking(False)
                except OSError:
                    self._drop(sock)

    def _drop(self, sock: socket.socket) -> None:
        with self.lock:
            if self._sock is sock:
                sock.close()
                self._sock = None


__all__ = ["WireBoard"]
