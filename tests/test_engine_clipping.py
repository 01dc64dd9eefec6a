"""Readback at the sensor's full scale, counted by the engine as it arrives (the real board over a pty).

Not a fault: the job runs to its end; the status counts the samples per axis, the end of the job
logs one WARNING naming the setting, and the recording ends with a ``# sensor_clipped:`` line.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from piezod.cli.ctl import status_text
from piezod.client import PiezodClient
from piezod.config import ScannerConfig, default_sim_config_path, load_config
from piezod.readback import at_full_scale
from piezod.recording import read_recording
from piezod.service.api import create_app
from piezod.service.engine import Engine
from piezod.service.jobs import Segment
from piezod.service.schemas import ScanRequest
from piezod.service.server import ApiServer

RATE_HZ = 10_000.0

#: Warnings about the sensor's full scale (the engine's logger).
CLIP_WARNING = "reached the position sensor's full scale"


@pytest.fixture(scope="module")
def sim_config() -> ScannerConfig:
    return load_config(default_sim_config_path()).model_copy(update={"sample_rate_hz": RATE_HZ})


def _narrow_x(config: ScannerConfig, full_scale_um: float) -> ScannerConfig:
    axes = dict(config.axes)
    axes["x"] = axes["x"].model_copy(update={"sensor_full_scale_um": full_scale_um})
    return config.model_copy(update={"axes": axes})


def _triangle(n: int, amplitude_v: float) -> Any:
    t = np.arange(n) / RATE_HZ
    return 2.0 * amplitude_v * np.abs(((4.0 * t) % 2.0) - 1.0) - amplitude_v


@pytest.fixture
def open_engine(
    tmp_path: Path, spawn_board: Callable[..., Any]
) -> Iterator[Callable[[ScannerConfig], Engine]]:
    with spawn_board(default_sim_config_path()) as sim:
        opened: list[Engine] = []

        def start(config: ScannerConfig) -> Engine:
            eng = Engine(config, sim.path, recording_dir=tmp_path)
            eng.open()
            opened.append(eng)
            return eng

        try:
            yield start
        finally:
            for eng in opened:
                eng.close()


def _clip_warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and CLIP_WARNING in r.getMessage()
    ]


def test_a_program_beyond_the_sensors_range_is_counted_reported_and_not_stopped(
    sim_config: ScannerConfig,
    tmp_path: Path,
    open_engine: Callable[[ScannerConfig], Engine],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="piezod")
    eng = open_engine(_narrow_x(sim_config, 0.5))
    path = tmp_path / "wide.csv"
    volts = _triangle(4000, 10.0)  # about +-1 um on x: twice the sensor's range
    eng.start_program("x", [Segment(volts, "wide")], path, {"content": "test"})
    assert eng.wait_idle(20.0) == "idle"  # ran to its end: no fault, no ramp
    eng.wait_recorded()
    st = eng.status()
    assert not [f for f in st.faults if f.source != "link"], st.faults
    assert st.sensor_clipped_job == "program wide.csv"
    assert set(st.sensor_clipped) == {"x", "y", "z"}
    assert st.sensor_clipped["y"] == st.sensor_clipped["z"] == 0
    rec = read_recording(path)
    offline = at_full_scale(rec.position_um, 0.5)
    # the job's count holds every sample of its readback: the recorded ones and the ramp to the start
    assert 0 < offline <= st.sensor_clipped["x"] < len(volts) + RATE_HZ
    assert st.sensor_clipped_total["x"] >= st.sensor_clipped["x"]
    assert (
        f"warning: program wide.csv: readback at the sensor's full scale on x ({st.sensor_clipped['x']} "
        "samples)" in status_text(st)
    )
    (warning,) = _clip_warnings(caplog)
    assert warning.startswith("program wide.csv: ")
    assert f"x ({st.sensor_clipped['x']} samples at +-0.5 um)" in warning
    assert "axes.x.sensor_full_scale_um" in warning and "axes.y." not in warning
    # the recording's trailer says it too (a comment: the columns and the header are unchanged)
    last = path.read_text().rstrip("\n").rsplit("\n", 1)[-1]
    assert last == f"# sensor_clipped: x={st.sensor_clipped['x']} y=0 z=0"
    assert rec.metadata["sensor_full_scale_um"] == "0.5"


def test_a_program_inside_the_sensors_range_counts_nothing(
    sim_config: ScannerConfig,
    tmp_path: Path,
    open_engine: Callable[[ScannerConfig], Engine],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="piezod")
    eng = open_engine(sim_config)
    path = tmp_path / "narrow.csv"
    eng.start_program("x", [Segment(_triangle(2000, 10.0), "narrow")], path, {"content": "test"})
    assert eng.wait_idle(20.0) == "idle"
    eng.wait_recorded()
    st = eng.status()
    assert st.sensor_clipped_job == "program narrow.csv"
    assert st.sensor_clipped == {"x": 0, "y": 0, "z": 0}
    assert st.sensor_clipped_total == {"x": 0, "y": 0, "z": 0}
    assert not _clip_warnings(caplog)
    assert "sensor_clipped" not in path.read_text() and "full scale" not in status_text(st)


def test_the_served_status_counts_a_scan_beyond_the_sensors_range(
    sim_config: ScannerConfig, tmp_path: Path, open_engine: Callable[[ScannerConfig], Engine]
) -> None:
    eng = open_engine(_narrow_x(sim_config, 0.5))
    server = ApiServer(create_app(eng), f"unix:{tmp_path / 'api.sock'}")
    server.start()
    try:
        with PiezodClient(server.address, timeout=10.0) as client:
            before = client.status()
            assert before.sensor_clipped_job is None and before.sensor_clipped == {}
            client.scan(range_um=15.0, line_rate_hz=4.0, lines=2, name="api")
            assert eng.wait_idle(20.0) == "idle"
            eng.wait_recorded()
            st = client.status()
    finally:
        server.stop()
    assert st.sensor_clipped_job == "scan api.csv"
    assert st.sensor_clipped["x"] > 0 and st.sensor_clipped["y"] == 0
    assert st.sensor_clipped_total["x"] >= st.sensor_clipped["x"]


def test_the_count_follows_the_jobs_tagged_samples_across_blocks(caplog: pytest.LogCaptureFixture) -> None:
    """Blocks that hold the end of one job and the start of the next; a job's count is final (and
    reported once) when a later sample's readback arrives; a stale tag starts no job."""
    from piezod.service.clipping import SensorClips

    clips = SensorClips()
    clips.set_full_scale({"x": 1.0, "y": 10.0})
    clips.register(1, "scan a.csv", recording=7)
    clips.register(2, "move to x=0 um")
    axes = ("x", "y", "z")  # z reads no position here: not counted
    pos = np.zeros((3, 8))
    pos[0, [0, 1, 5]] = [1.0, -0.9999, 1.0]  # the second is within 1/2048 of -1 um
    pos[1, 2] = np.nan
    pos[2, :] = 99.0
    with caplog.at_level(logging.WARNING, logger="piezod"):
        clips.add(axes, pos, np.array([-1, 1, 1, 1, 1, 1, 2, 2]))
        assert clips.snapshot().job == "move to x=0 um"
        assert clips.for_recording(7) == {"x": 2, "y": 0}
        clips.add(axes, pos, np.array([2, 2, -1, -1, 1, 1, -1, -1]))
        snap = clips.snapshot()
    assert snap.job == "move to x=0 um" and snap.job_counts == {"x": 2, "y": 0}
    assert snap.total == {"x": 6, "y": 0}
    assert _clip_warnings(caplog) == [
        "scan a.csv: the readback reached the position sensor's full scale on x (2 samples at +-1 um): "
        "positions there are not measured (the stage travelled beyond the sensor's range; if the sensor "
        "reads farther, set axes.x.sensor_full_scale_um)",
        "move to x=0 um: the readback reached the position sensor's full scale on x (2 samples at +-1 um): "
        "positions there are not measured (the stage travelled beyond the sensor's range; if the sensor "
        "reads farther, set axes.x.sensor_full_scale_um)",
    ]


# --- lines whose readback reached the full scale: not scored, not learnt by the tracker ---

CALIBRATED = Path(__file__).resolve().parent.parent / "configs" / "sim-stage-calibrated.yaml"


class _LineEngine:
    """What the recorder's line statistics need of the engine; keeps the lines it is given."""

    rate_hz = RATE_HZ

    def __init__(self, full_scale_um: dict[str, float]) -> None:
        from piezod.service.clipping import SensorClips

        self.sensor_clips = SensorClips()
        self.sensor_clips.set_full_scale(full_scale_um)
        self.scan_events = self
        self.lines: list[Any] = []

    def line_done(self, ident: int, line: int, direction: int) -> None:
        pass

    def set_line_linearity(self, value: Any, corrected: bool, rendered_scale: float = 1.0) -> None:
        self.lines.append(value)


def _feed_lines(engine: _LineEngine, position_x: Any, line: Any, direction: Any, block: int) -> list[Any]:
    """Feed the x readback ``position_x`` (target: a 10 um ramp per line) in blocks of ``block``."""
    from piezod.link.streamer import MatchedBlock
    from piezod.service.recorder import Recorder

    rec = Recorder(engine)  # type: ignore[arg-type]
    n = position_x.size
    target = np.tile(np.linspace(-5.0, 5.0, 50), n // 50)
    for s in range(0, n, block):
        sl = slice(s, min(n, s + block))
        m = sl.stop - sl.start
        pos = np.vstack([position_x[sl], np.zeros(m)])
        matched = MatchedBlock(np.arange(sl.start, sl.stop), np.zeros((2, m)), pos, ("x", "y"))
        rec._line_stats(
            matched,
            np.vstack([target[sl], np.zeros(m)]),
            line[sl],
            direction[sl],
            np.ones(m, dtype=bool),
            np.full(m, -1, dtype=np.int64),
            np.ones(m),
        )
    rec._finish_line()
    return engine.lines


def test_a_line_with_one_sample_at_the_full_scale_is_not_scored_whatever_the_blocks() -> None:
    """Four lines of 50 samples, fed in blocks that split them anywhere: the second has one
    reading at the full scale (within 1/2048 of it), the third a NaN (not clipped), the fourth a
    clipped reading before it starts (a settling sample, line -1, counts for no line)."""
    pos = np.tile(np.linspace(-5.0, 5.0, 50) * 1.01, 4)
    line = np.repeat(np.arange(4, dtype=np.int64), 50)
    direction = np.tile(np.int8(1), 200)
    pos[50 + 17] = -7.9999
    pos[100 + 3] = np.nan
    line[150:152] = -1
    pos[150] = 8.0
    for block in (7, 50, 64, 200):
        lines = _feed_lines(_LineEngine({"x": 8.0, "y": 100.0}), pos, line, direction, block)
        assert [ll.line for ll in lines] == [0, 1, 2, 3], block
        clipped = lines[1]
        assert clipped.nonlinearity_pct is None and clipped.length_error_pct is None
        assert clipped.skipped == "readback at the sensor's full scale (+-8 um) in 1 samples"
        assert clipped.duration_s == pytest.approx(50 / RATE_HZ)
        for ll in (lines[0], lines[2], lines[3]):
            assert ll.skipped is None and ll.length_error_pct is not None, (block, ll)
        assert lines[0].length_error_pct == pytest.approx(1.0)
        assert clipped.figures().startswith("not scored (readback at the sensor's full scale")


def test_without_a_position_sensor_range_no_line_is_marked() -> None:
    """An axis that reads no position (no range known) has nothing to test: the lines are scored."""
    pos = np.tile(np.linspace(-5.0, 5.0, 50), 2)
    lines = _feed_lines(
        _LineEngine({"y": 1.0}),
        pos,
        np.repeat(np.arange(2, dtype=np.int64), 50),
        np.tile(np.int8(-1), 100),
        32,
    )
    assert [ll.skipped for ll in lines] == [None, None]
    assert lines[0].length_error_pct == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("full_scale_um", [4.0, 100.0], ids=["beyond", "inside"])
def test_a_scan_beyond_the_sensors_range_leaves_the_tracker_as_it_was(
    full_scale_um: float,
    tmp_path: Path,
    spawn_board: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A corrected 12 um scan, the calibrated stage over the pty: with the x sensor reading +-4 um
    every line reaches the full scale, is reported without figures and the tracker keeps its
    state; inside the sensor's range (+-100 um) the lines are scored and the tracker learns."""
    import copy

    base = load_config(CALIBRATED).model_copy(update={"sample_rate_hz": RATE_HZ})
    config = _narrow_x(base, full_scale_um)
    with spawn_board(CALIBRATED) as sim:
        eng = Engine(config, sim.path, recording_dir=tmp_path)
        eng.open()
        try:
            seen: list[Any] = []
            original = eng.set_line_linearity

            def keep(value: Any, corrected: bool, rendered_scale: float = 1.0) -> None:
                seen.append(value)
                original(value, corrected, rendered_scale)

            monkeypatch.setattr(eng, "set_line_linearity", keep)
            before = copy.deepcopy(eng._trackers["x"])
            eng.start_scan(ScanRequest(range_um=12.0, line_rate_hz=5.0, lines=3, name="t"))
            assert eng.wait_idle(20.0) == "idle"
            eng.wait_recorded()
            after = copy.deepcopy(eng._trackers["x"])
            st = eng.status()
        finally:
            eng.close()
    assert [(ll.line, ll.direction) for ll in seen] == [
        (k, d) for k in range(3) for d in ("trace", "retrace")
    ]
    assert st.last_line == seen[-1]
    if full_scale_um < 6.0:
        assert st.sensor_clipped["x"] > 0
        for ll in seen:
            assert ll.nonlinearity_pct is None and ll.length_error_pct is None, ll
            assert ll.skipped is not None and ll.skipped.startswith(
                "readback at the sensor's full scale (+-4 um)"
            )
        assert after == before and after.lines_used == after.lines_ignored == 0
        assert st.sensitivity_scale == {"x": 1.0}
        assert "last line 2 (retrace): not scored (readback at the sensor's full scale" in status_text(st)
    else:
        assert st.sensor_clipped["x"] == 0
        assert all(ll.skipped is None and ll.length_error_pct is not None for ll in seen), seen
        assert after.lines_used > 0 and after.scale != before.scale
        assert st.sensitivity_scale == {"x": after.scale}
