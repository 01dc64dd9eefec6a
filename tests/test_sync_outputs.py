"""The scan's pixel, line and frame clocks reach the board's sync outputs at the right sample indices.

End to end: the engine (inverse model, streamer, session) over a real pty to hil_sim's board,
which applies the SYNC events on its sample clock and logs every change of its outputs. The
expected edges are derived here from the recording (the index of every recorded sample and its
line) and the raster's definition, not from the engine's sync code.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hil_sim.board import Board
from hil_sim.server import SimServer
from piezod.config import default_sim_config_path, load_config
from piezod.recording import read_recording
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest
from piezod.service.sync import FRAME, LINE, PIXEL, SyncPlanner, SyncSchedule

RATE_HZ = 2000.0
LINE_RATE_HZ = 5.0  # 400 samples per line: trace 200, retrace 200
PIXELS = 7  # 28.57 samples per pixel: pixel boundaries fall between samples
LINES = 3


@pytest.fixture
def sim_board() -> Iterator[tuple[Board, str]]:
    """hil_sim's board served on a pty from a thread of this process (its sync log is readable)."""
    import time

    board = Board.from_scanner_file(default_sim_config_path(), now=time.monotonic())
    server = SimServer(board)
    server.open()
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            server.step()

    thread = threading.Thread(target=serve, name="sim-board", daemon=True)
    thread.start()
    try:
        yield board, server.public_path
    finally:
        stop.set()
        thread.join(timeout=10.0)
        server.close()


def expected_events(line_starts: list[int], samples_per_line: int) -> list[tuple[int, int, int]]:
    """(index, lines, mask) of the raster's clocks as PROTOCOL.md 4.14 / piezod.service.sync define them."""
    half = samples_per_line // 2
    per_pixel = half / PIXELS
    fall = math.floor(0.5 * per_pixel + 0.5)
    ev: list[tuple[int, int, int]] = []
    for k, start in enumerate(line_starts):
        bits = LINE | (FRAME if k == 0 else 0)
        ev.append((start, bits, bits))
        ev.append((start + half, 0, LINE | FRAME))
        # trace: pixel p spans fractional samples [p, p + 1) * per_pixel from the line start
        for p in range(PIXELS):
            first = start + math.ceil(p * per_pixel)
            ev += [(first, PIXEL, PIXEL), (first + fall, 0, PIXEL)]
        # retrace: pixel q (from the right) begins just after the boundary (the right edge is outside)
        for q in range(PIXELS - 1, -1, -1):
            first = start + math.floor(half * (2 * PIXELS - 1 - q) / PIXELS) + 1
            ev += [(first, PIXEL, PIXEL), (first + fall, 0, PIXEL)]
    return ev


def levels_of(events: list[tuple[int, int, int]]) -> list[tuple[int, int]]:
    """The output changes ``(index, levels)`` the events make (merged per index, in the order given)."""
    merged: dict[int, tuple[int, int]] = {}
    for i, lines, mask in events:
        ol, om = merged.get(i, (0, 0))
        merged[i] = ((ol & ~mask) | (lines & mask), om | mask)
    level, out = 0, []
    for i in sorted(merged):
        lines, mask = merged[i]
        new = (level & ~mask) | (lines & mask)
        if new != level:
            out.append((i, new))
            level = new
    return out


def test_schedule_merges_per_index_and_resends_the_same_events() -> None:
    s = SyncSchedule(history=100)
    s.add(10, PIXEL, PIXEL)
    s.add(12, 0, PIXEL)
    s.add(12, PIXEL, PIXEL)  # the next pixel rises where the last one falls: it stays high
    s.add(12, LINE, LINE)
    assert s.between(10, 3) == [(0, PIXEL, PIXEL), (2, PIXEL | LINE, PIXEL | LINE)]
    assert s.between(11, 1) == [] and s.between(10, 3) == s.between(10, 3)
    s.add(500, 0, LINE)  # events more than `history` samples behind are forgotten
    assert s.between(0, 400) == [] and len(s) == 1
    with pytest.raises(ValueError, match="pixels"):
        SyncPlanner(s, 0)


def test_engine_drives_pixel_line_and_frame_clocks_on_the_board(
    sim_board: tuple[Board, str], tmp_path: Path
) -> None:
    board, path = sim_board
    config = load_config(default_sim_config_path()).model_copy(update={"sample_rate_hz": RATE_HZ})
    eng = Engine(config, path, recording_dir=tmp_path)
    eng.open()
    try:
        assert board.capabilities.sync_outputs == 3
        eng.start_scan(
            ScanRequest(range_um=10.0, line_rate_hz=LINE_RATE_HZ, lines=LINES, pixels=PIXELS, name="sync")
        )
        assert eng.wait_idle(60.0) == "idle"
        eng.wait_recorded()
        st = eng.status()
        assert st.underruns == 0, st.faults
    finally:
        eng.close()
    rec = read_recording(tmp_path / "sync.csv")
    x = rec.axis == "x"
    index = np.rint(rec.t_s[x] * RATE_HZ).astype(np.int64)
    per_line = int(RATE_HZ / LINE_RATE_HZ)
    assert index.size == LINES * per_line and np.all(np.diff(index) == 1)
    starts = [int(index[0]) + k * per_line for k in range(LINES)]
    # the recorded targets confirm the line layout: each line turns at its middle sample (x = +range / 2)
    assert rec.target_um is not None
    target = rec.target_um[x].reshape(LINES, per_line)
    assert np.all(np.argmax(target, axis=1) == per_line // 2)
    want = levels_of(expected_events(starts, per_line))
    got = [(i, lv) for i, lv in board.sync_transitions if starts[0] - per_line <= i]
    assert got == want
    # 2 * PIXELS pixel pulses, one line pulse per line, one frame pulse; everything low at the end
    prev = [0] + [lv for _, lv in got[:-1]]
    rises = [i for (i, lv), before in zip(got, prev, strict=True) if lv & PIXEL and not before & PIXEL]
    assert len(rises) == 2 * PIXELS * LINES
    assert got[-1][1] == 0 and board.counters.overflows == 0
