"""hil_sim's select loop when its own process was not scheduled (or busy): a board's clock and its
receiver run together and never starve, so the simulated clock runs one tick over the stall, the
bytes that waited in the pty are taken in then, and simulated time lags the wall clock from then on."""

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
def test_the_simulated_clock_runs_one_tick_over_a_stall(
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
    assert board.advanced[-1] == pytest.approx(expected)
    assert server.lag_s == pytest.approx(gap_s - server.tick_s if stalled else 0.0)
    assert ("stalled" in caplog.text) == stalled


def test_after_a_stall_simulated_time_runs_at_the_wall_clock_rate_again() -> None:
    clock = _Clock()
    board = _Board()
    server = SimServer(board, clock=clock)  # type: ignore[arg-type]
    server.open()
    try:
        server.step()
        clock.t += 0.5
        server.step()
        behind = server.lag_s
        for _ in range(5):
            clock.t += 0.01
            server.step()
    finally:
        server.close()
    assert behind == pytest.approx(0.5 - server.tick_s)
    assert server.lag_s == behind  # short iterations are simulated in full
    assert board.advanced[-1] == pytest.approx(clock.t - behind)
    assert all(b > a for a, b in zip(board.advanced, board.advanced[1:], strict=False))
