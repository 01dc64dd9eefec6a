"""The streaming engine against the real simulator process over a real pty."""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from piezod.cli.ctl import status_text
from piezod.config import ScannerConfig, default_sim_config_path, load_config
from piezod.errors import EngineStateError, RangeUnreachableError, SafetyError
from piezod.model import kernels
from piezod.recording import read_recording
from piezod.service import engine as engine_module
from piezod.service.engine import Engine
from piezod.service.jobs import Segment
from piezod.service.schemas import MoveRequest, ScanChange, ScanRequest
from piezod.stagecal import frame_record_every

RATE_HZ = 10_000.0


@pytest.fixture(scope="module")
def sim_config() -> ScannerConfig:
    return load_config(default_sim_config_path()).model_copy(update={"sample_rate_hz": RATE_HZ})


@pytest.fixture
def engine(sim_config: ScannerConfig, tmp_path: Path, spawn_board: Callable[..., Any]) -> Iterator[Engine]:
    with spawn_board(default_sim_config_path()) as sim:
        eng = Engine(sim_config, sim.path, recording_dir=tmp_path)
        eng.open()
        try:
            yield eng
        finally:
            eng.close()


def test_scan_is_streamed_recorded_and_measured(engine: Engine, tmp_path: Path) -> None:
    engine.start_scan(ScanRequest(range_um=15.0, line_rate_hz=2.0, lines=4, name="s1"))
    assert engine.wait_idle(20.0) == "idle"
    engine.wait_recorded()
    st = engine.status()
    assert st.underruns == 0 and not [f for f in st.faults if f.source != "link"]
    assert st.last_line is not None and st.last_line.line == 3
    # configs/sim-stage.yaml is the first guess: the status (and the API's) says so
    assert not st.calibrated and st.uncalibrated_axes == ["x", "y", "z"]
    assert "warning: uncalibrated model on axes x, y, z" in status_text(st)
    rec = read_recording(tmp_path / "s1.csv")
    assert rec.metadata["range_um"] == "15.0"
    assert rec.metadata["sensor_full_scale_um.x"] == rec.metadata["sensor_full_scale_um.y"] == "100.0"
    x = rec.axis == "x"
    # 4 recorded lines of 5000 samples on x (settling lines are not recorded)
    assert int(np.count_nonzero(x)) == 4 * 5000
    assert np.all(np.diff(rec.t_s[x]) > 0)
    assert rec.target_um is not None
    assert np.nanmax(rec.target_um[x]) - np.nanmin(rec.target_um[x]) == pytest.approx(15.0, rel=1e-3)
    # the stage followed: the readback spans about the commanded range (uncalibrated model: within 10 %)
    span = np.ptp(rec.position_um[x])
    assert 13.5 < span < 16.5


def test_the_compiled_loops_are_loaded_before_the_stream_starts(
    sim_config: ScannerConfig,
    tmp_path: Path,
    spawn_board: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a model switched in while streaming (the calibrated family model at `piezod calibrate`'s
    # verification) loaded the loops in the daemon's process then: 0.26 s from numba's cache,
    # 7.8 s cold, the streaming thread stalled ("slow block", session 40's held-out runs)
    calls: list[bool] = []
    with spawn_board(default_sim_config_path()) as sim:
        eng = Engine(sim_config, sim.path, recording_dir=tmp_path)
        assert type(eng.drivers["x"].model).__name__ == "ThesisAxisModel"  # needs no compiled loop
        monkeypatch.setattr(kernels, "warm_up", lambda: calls.append(eng.status().state == "starting"))
        eng.open()
        try:
            assert calls == [True]
        finally:
            eng.close()


def test_a_slow_block_says_where_its_time_went(
    engine: Engine, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # every block reported: the warning splits its time into the lock, the thread's own CPU, the
    # wait for a core, the rest (another thread holding the interpreter lock) and the process's
    # garbage collections
    monkeypatch.setattr(engine_module, "SLOW_BLOCK_S", -1.0)
    with caplog.at_level(logging.WARNING, logger="piezod.service.engine"):
        time.sleep(0.3)
    lines = [r.getMessage() for r in caplog.records if "slow block" in r.getMessage()]
    assert lines, "no block reported"
    assert re.search(
        r"slow block: \d+ samples took \d+ ms \(\d+ ms waiting for the engine lock, \d+ ms of this "
        r"thread's CPU, \d+ ms waiting for a core, \d+ ms blocked otherwise \(the interpreter lock held by "
        r"another thread, or I/O\); \d+ ms of garbage collection in the process\), job \w+",
        lines[-1],
    ), lines[-1]


def test_a_program_recorded_every_nth_sample_keeps_the_clocks_samples(engine: Engine, tmp_path: Path) -> None:
    """A calibration frame on a fast clock is played at the full rate and recorded every n-th sample:
    the rows are the board's own samples (their times on the clock's grid, n apart), and the
    header says how they were taken."""
    t = np.arange(6000) / RATE_HZ
    volts = 20.0 * np.abs(((4.0 * t) % 2.0) - 1.0) - 10.0  # a 2 Hz triangle over +-10 V
    path = tmp_path / "p.csv"
    engine.start_program("x", [Segment(volts, "tri")], path, {"content": "test"}, record_every=3)
    assert engine.wait_idle(20.0) == "idle"
    engine.wait_recorded()
    rec = read_recording(path)
    assert rec.metadata["recorded_every"] == "3"
    assert rec.metadata["sample_rate_hz"] == f"{RATE_HZ}"
    steps = np.round(rec.t_s * RATE_HZ).astype(np.int64)
    assert np.all(steps % 3 == 0) and np.all(np.diff(steps) == 3)
    assert abs(len(rec) - 6000 / 3) <= 1
    assert np.ptp(rec.voltage_v) == pytest.approx(20.0, abs=0.1)
    # the frame's policy: the full rate up to 20 kS/s, else the smallest n that gets below it
    assert [frame_record_every(r) for r in (10e3, 20e3, 25e3, 50e3, 100e3)] == [1, 1, 2, 3, 5]


def test_the_reading_at_rest_is_the_sensors_mean_while_the_voltage_holds(engine: Engine) -> None:
    """What ``piezod calibrate`` starts its verification from after a fault moved the stage: the
    held voltage and the sensor's mean reading there; nothing while the voltage changes."""
    deadline = time.monotonic() + 20.0
    while (rest := engine.measured_at_rest("x")) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert rest is not None
    held = engine.status().voltage_v["x"]
    assert rest[0] == held
    assert abs(rest[1] - engine.status().position_um["x"]) < 0.5  # the model's idea of it, uncalibrated
    engine.start_scan(ScanRequest(range_um=15.0, line_rate_hz=2.0, lines=20, record=False))
    deadline = time.monotonic() + 5.0
    moving = False
    while time.monotonic() < deadline and not moving:
        moving = engine.measured_at_rest("x") is None
        time.sleep(0.01)
    engine.stop()
    assert moving


def test_change_mid_scan_and_stop(engine: Engine) -> None:
    engine.start_scan(ScanRequest(range_um=10.0, line_rate_hz=5.0, lines=0 + 100, frames=0, record=False))
    time.sleep(1.0)
    engine.change_scan(ScanChange(range_um=5.0, offset_x_um=2.0))
    time.sleep(1.0)
    st = engine.status()
    assert st.state == "scanning"
    # the x voltages of the new lines: around the new centre
    engine.stop()
    assert engine.status().state == "idle"
    with pytest.raises(EngineStateError):
        engine.change_scan(ScanChange(range_um=3.0))


def test_requests_outside_the_limits_are_refused_with_the_reason(engine: Engine) -> None:
    with pytest.raises(RangeUnreachableError, match="largest reachable"):
        engine.check_scan(ScanRequest(range_um=200.0, line_rate_hz=1.0))
    with pytest.raises(SafetyError, match="slew limit"):
        engine.check_scan(ScanRequest(range_um=30.0, line_rate_hz=40.0))
    with pytest.raises(SafetyError, match="outside the reach"):
        engine.check_move(MoveRequest(x_um=500.0))


def test_move_reaches_the_position(engine: Engine) -> None:
    engine.move(MoveRequest(x_um=5.0, y_um=-3.0, speed_um_per_s=50.0))
    assert engine.wait_idle(10.0) == "idle"
    st = engine.status()
    assert st.position_um["x"] == pytest.approx(5.0, abs=1e-6)
    assert st.position_um["y"] == pytest.approx(-3.0, abs=1e-6)


def test_a_restart_whose_start_fails_is_tried_again(engine: Engine, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in the block source ends the run; the supervisor reports it and restarts the stream.
    When that restart's START fails (a board still ramping refuses it, or no reply), it tries again
    instead of waiting for the end of a run that never began. Before, the first killed the
    supervisor thread and the second left it waiting: either way the daemon answered but never
    streamed again (test_board_side_fuzz_short stayed 'scanning' once).
    """
    from piezod.errors import LinkTimeoutError

    board: Any = engine._board
    session = board.session
    real_start = session.start
    calls: list[int] = []

    def start_once_refused(start_index: int, prefill_samples: int, **kw: Any) -> int:
        calls.append(start_index)
        if len(calls) == 1:
            raise LinkTimeoutError(f"{session.url}: no reply to START within 1 s")
        return int(real_start(start_index, prefill_samples, **kw))

    monkeypatch.setattr(session, "start", start_once_refused)
    real_next_block = engine.next_block
    failed: list[bool] = []

    def fail_once(n: int) -> Any:
        if not failed:
            failed.append(True)
            raise RuntimeError("the block source failed once")  # ends the run: the supervisor restarts
        return real_next_block(n)

    monkeypatch.setattr(engine, "next_block", fail_once)
    deadline = time.monotonic() + 30.0
    while len(calls) < 2 or not board.running:
        assert time.monotonic() < deadline, (calls, engine.status().faults[-3:])
        time.sleep(0.05)
    codes = [f.code for f in engine.status().faults]
    assert "STREAM" in codes and "RESTART" in codes, codes
    assert any("RuntimeError: the block source failed once" in f.message for f in engine.status().faults)
    engine.stop()
    engine.start_scan(ScanRequest(range_um=5.0, line_rate_hz=4.0, lines=1, name="after-restart"))
    assert engine.wait_idle(20.0) == "idle", engine.status().faults[-3:]


def test_the_sensor_range_of_an_axis_reaches_the_board_and_its_end_reads_as_clipped(
    sim_config: ScannerConfig, tmp_path: Path, spawn_board: Callable[..., Any]
) -> None:
    """``axes.x.sensor_full_scale_um`` sets the ADC's scale on the board; a stage driven beyond it
    reads the end code, which :func:`piezod.stagecal.readback_clipped` finds."""
    from piezod.errors import RecordingError
    from piezod.readback import within_sensor_range
    from piezod.recording import split_experiments
    from piezod.stagecal import readback_clipped

    axes = dict(sim_config.axes)
    axes["x"] = axes["x"].model_copy(update={"sensor_full_scale_um": 0.5})
    cfg = sim_config.model_copy(update={"axes": axes})
    with spawn_board(default_sim_config_path()) as sim:
        eng = Engine(cfg, sim.path, recording_dir=tmp_path)
        eng.open()
        try:
            assert eng.settings.full_scale_um("x") == 0.5 and eng.settings.full_scale_um("y") == 100.0
            t = np.arange(4000) / RATE_HZ
            volts = 20.0 * np.abs(((4.0 * t) % 2.0) - 1.0) - 10.0
            path = tmp_path / "p.csv"
            eng.start_program("x", [Segment(volts, "wide")], path, {"content": "test"})
            assert eng.wait_idle(20.0) == "idle"
            eng.wait_recorded()
        finally:
            eng.close()
    rec = read_recording(path)
    # the header says what the sensor read: offline analyses leave out what it could not
    assert rec.metadata["sensor_full_scale_um"] == "0.5"
    (exp,) = split_experiments(rec)
    with pytest.raises(RecordingError, match="every experiment's readback reached the sensor's full scale"):
        within_sensor_range([exp])
    assert exp.position_um.max() == pytest.approx(0.5 * 32767 / 32768, abs=1e-9)
    assert exp.position_um.min() == pytest.approx(-0.5, abs=1e-9)
    clipped = readback_clipped([exp], 0.5)
    assert 0 < clipped["wide"] < len(exp)
    assert readback_clipped([exp], 100.0) == {}


def _ringing_after_turns(rec: Any, f0_hz: float) -> float:
    """RMS of x's readback minus its moving average over one period of the mode, in the first
    ten periods after each turning point (the mode rings there; the rest of the line is smooth)."""
    x = rec.axis == "x"
    pos, tgt = rec.position_um[x], rec.target_um[x]
    per = round(RATE_HZ / f0_hz)
    smooth = np.convolve(pos, np.ones(per) / per, mode="same")
    turns = np.flatnonzero(np.diff(np.sign(np.diff(tgt))) != 0) + 1
    rows = np.zeros(pos.size, dtype=bool)
    for k in turns:
        rows[k + per : k + 10 * per] = True
    rows[:per] = rows[-per:] = False
    return float(np.sqrt(np.mean((pos - smooth)[rows] ** 2)))


def test_a_resonance_extension_shapes_the_scan_so_the_stage_does_not_ring(
    sim_config: ScannerConfig, tmp_path: Path, spawn_board: Callable[..., Any]
) -> None:
    """The stage rings at 300 Hz (Q 20) after every turning point; the axis's ``resonance``
    extension (handed the targets ahead by the scan job, across blocks) takes most of it away."""
    effects = ["resonance=300", "resonance.q=20"]
    ax = sim_config.axes["x"]
    shaped = ax.model_validate({**ax.model_dump(), "extensions": {"resonance": {"f0_hz": 300.0, "q": 20.0}}})
    ringing = {}
    with_shaping = sim_config.model_copy(update={"axes": {**sim_config.axes, "x": shaped}})
    for name, cfg in (("plain", sim_config), ("shaped", with_shaping)):
        with spawn_board(default_sim_config_path(), effects=effects) as sim:
            eng = Engine(cfg, sim.path, recording_dir=tmp_path)
            eng.open()
            try:
                eng.start_scan(ScanRequest(range_um=15.0, line_rate_hz=4.0, lines=3, name=name))
                assert eng.wait_idle(30.0) == "idle"
                eng.wait_recorded()
                st = eng.status()
                assert st.underruns == 0 and not [f for f in st.faults if f.source != "link"]
            finally:
                eng.close()
        ringing[name] = _ringing_after_turns(read_recording(tmp_path / f"{name}.csv"), 300.0)
    assert ringing["plain"] > 0.02  # ~60 nm at 120 um/s
    assert ringing["shaped"] < 0.3 * ringing["plain"]
