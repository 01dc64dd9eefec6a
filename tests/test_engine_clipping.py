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
