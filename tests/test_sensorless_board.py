"""A board that reports no position sensor (CAPABILITIES revision 2) is a supported configuration."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from firmware_proto import NO_POSITION_SENSOR_BIT, Capabilities, ProtocolError
from firmware_proto.codec import Frame, decode_frame, encode
from piezod.config import config_dir, load_config
from piezod.errors import RecordingError
from piezod.recording import parse_recording, read_experiments, read_recording
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest
from piezod.simulator import spawn_sim


def _caps(**kw: object) -> Capabilities:
    base: dict[str, object] = dict(
        reply_to_seq=0,
        protocol_version=1,
        firmware_version=(1, 0, 0),
        dac_bits=16,
        adc_bits=16,
        max_samples_per_frame=100,
        sample_rate_min_hz=1,
        sample_rate_max_hz=100_000,
        sample_clock_hz=0,
        fifo_depth_samples=4096,
        board_serial=7,
        amplifier_ranges_v=((-10.0, 10.0),),
    )
    base.update(kw)
    return Capabilities(**base)  # type: ignore[arg-type]


def test_the_flag_is_bit_7_beside_the_sync_outputs_and_round_trips() -> None:
    for sync, sensor in ((0, True), (3, True), (3, False), (8, False)):
        caps = _caps(sync_outputs=sync, position_sensor=sensor)
        payload = caps.pack_payload()
        assert payload[13] == sync | (0 if sensor else NO_POSITION_SENSOR_BIT)
        back = decode_frame(encode(caps, seq=1)[:-1])
        assert isinstance(back, Frame) and isinstance(back.msg, Capabilities)
        assert (back.msg.sync_outputs, back.msg.position_sensor) == (sync, sensor)
    # a revision-0/1 board sends the bit clear: a position sensor, as before
    old = bytearray(_caps(sync_outputs=3).pack_payload())
    assert Capabilities.unpack_payload(bytes(old)).position_sensor is True
    with pytest.raises(ProtocolError, match="position_sensor"):
        _caps(position_sensor=1)


def test_recordings_without_a_position_column_are_read_when_marked_sensorless() -> None:
    body = "t,voltage,target,z_voltage\n0,0,0,1\n0.001,1,0.1,1.1\n"
    rec = parse_recording("# position_sensor: no\n" + body, path="a.csv")
    assert np.isnan(rec.position_um).all()
    with pytest.raises(RecordingError, match="missing required column 'position'"):
        parse_recording(body, path="a.csv")


def _piezod(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "piezod", *args], cwd=cwd, capture_output=True, text=True, timeout=120
    )


def test_a_board_without_a_sensor_is_driven_and_sensor_features_refuse(tmp_path: Path) -> None:
    # the scanner config claims a sensor: the board's CAPABILITIES say otherwise and win
    text = (config_dir() / "sim-microscope.yaml").read_text()
    text = text.replace("position_sensor: false", "position_sensor: true")
    cfg_path = tmp_path / "claims-a-sensor.yaml"
    cfg_path.write_text(text)
    config = load_config(cfg_path)
    config = config.model_copy(
        update={"service": config.service.model_copy(update={"sensitivity_tracking": True})}
    )
    with spawn_sim(cfg_path, extra_args=("--sample", "line-3um", "--no-position-sensor")) as sim:
        engine = Engine(config, sim.path, recording_dir=tmp_path)
        engine.open()
        try:
            assert engine.position_sensor is False
            assert engine.status().sensitivity_scale == {}  # the tracker is off
            request = ScanRequest(range_um=10.0, line_rate_hz=5.0, lines=3, pixels=64, name="nosensor")
            engine.start_scan(request)
            limit = time.monotonic() + 60.0
            while engine.status().state == "scanning" and time.monotonic() < limit:
                time.sleep(0.05)
            assert engine.wait_idle(timeout_s=10.0) == "idle"
            engine.wait_recorded()
            assert engine.status().last_line is None  # no sensor: no line linearity
        finally:
            engine.close()
    path = tmp_path / "nosensor.csv"
    rec = read_recording(path)
    assert rec.metadata["position_sensor"] == "no"
    with pytest.raises(RecordingError, match="without a position sensor"):
        read_experiments([path])
    p = _piezod("linearity", str(path), cwd=tmp_path)
    assert p.returncode == 2
    assert "without a position sensor" in p.stderr and "Traceback" not in p.stderr
    p = _piezod("image", str(path), "--out", str(tmp_path / "img"), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "img" / "nosensor.gwy").exists()


def test_the_sensor_calibration_refuses_a_scanner_without_a_sensor(tmp_path: Path) -> None:
    p = _piezod(
        "calibrate",
        "--sim",
        "--config",
        str(config_dir() / "sim-microscope.yaml"),
        "--frame",
        "reduced",
        "--out",
        str(tmp_path / "cal.yaml"),
        cwd=tmp_path,
    )
    assert p.returncode == 2, p.stderr
    assert "no position sensor" in p.stderr and "--from-images" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "cal.yaml").exists()
