"""hil_sim's select loop when its own process was not scheduled: the board's receiver runs beside
its clock, so bytes that waited in the pty are taken in before the clock catches up."""

from __future__ import annotations

import logging
import os
import select

import pytest

from hil_sim.server import STALL_WARN_S, SimServer


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class _Board:
    """Records when the loop feeds bytes and advances time (the loop's contract with a board)."""

    def __init__(self) -> None:
        self.fed: list[tuple[bytes, float]] = []
        self.advanced: list[float] = []

    def feed(self, data: bytes, now: float) -> None:
        self.fed.append((bytes(data), now))

    def advance(self, now: float) -> None:
        self.advanced.append(now)

    def data_to_send(self) -> bytes:
        return b""


@pytest.mark.parametrize("gap_s", [0.001, 0.4])
def test_input_after_a_stall_is_taken_in_as_of_the_stall_start(
    gap_s: float, caplog: pytest.LogCaptureFixture
) -> None:
    clock = _Clock()
    board = _Board()
    server = SimServer(board, clock=clock)  # type: ignore[arg-type]
    server.open()
    try:
        fd = os.open(server.public_path, os.O_RDWR | os.O_NOCTTY)
        try:
            server.step()  # sees the host open the slave
            last = clock.t
            os.write(fd, b"\x00frame\x00")
            assert server.pty is not None
            ready, _, _ = select.select(server.pty.read_fds(), [], [], 30.0)  # in the pty before the step
            assert ready
            clock.t += gap_s
            with caplog.at_level(logging.WARNING, logger="hil_sim"):
                server.step()
        finally:
            os.close(fd)
    finally:
        server.close()
    assert board.fed and board.fed[0][0] == b"\x00frame\x00"
    stalled = gap_s > STALL_WARN_S
    expected = last + server.tick_s if stalled else clock.t
    assert board.fed[0][1] == pytest.approx(expected)
    assert board.advanced[-1] == clock.t  # the clock still catches up to the present
    assert ("stalled" in caplog.text) == stalled
