"""A readback at the sensor's full scale is the ADC's end code, not a position (piezod.readback).

The daemon writes the sensor range into every recording's header; the offline analyses (``piezod
calibrate FILE.csv``, ``piezod audit``) leave out the experiments whose readback reached it and say
so. On the stage, ``piezod calibrate`` does the same with its frame (tests/test_stagecal.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from piezod.audit import run_audit
from piezod.cli import main
from piezod.errors import RecordingError
from piezod.readback import SENSOR_RANGE_KEY, within_sensor_range
from piezod.recording import Experiment, Recording, read_experiments, write_recording
from piezod.synth import MEDIUM_TUBE, random_plan, synth_session


def _exp(label: str, peak_um: float, meta: dict[str, str], axis: str = "x") -> Experiment:
    t = np.arange(200) / 100.0
    x = np.clip(peak_um * np.sin(2 * np.pi * t), -50.0, 50.0 * 32767 / 32768)
    return Experiment(label, axis, t, 2.0 * x, x, metadata=meta)


def test_experiments_that_read_the_full_scale_their_recording_documents_are_left_out() -> None:
    meta = {SENSOR_RANGE_KEY: "50"}
    kept, note = within_sensor_range([_exp("a", 30.0, meta), _exp("b", 60.0, meta), _exp("c", 70.0, {})])
    # "c" documents no range: kept as it is
    assert [e.label for e in kept] == ["a", "c"]
    assert note is not None and note.startswith("left out, the readback at the sensor's full scale: b (")
    assert "at +-50 um" in note
    # a multi-axis recording documents one range per axis
    per_axis = {f"{SENSOR_RANGE_KEY}.y": "50", f"{SENSOR_RANGE_KEY}.x": "200"}
    kept, note = within_sensor_range(
        [_exp("d", 60.0, per_axis, axis="x"), _exp("e", 60.0, per_axis, axis="y")]
    )
    assert [e.label for e in kept] == ["d"] and note is not None and "e (" in note
    kept, note = within_sensor_range([_exp("a", 30.0, meta)])
    assert [e.label for e in kept] == ["a"] and note is None


def test_a_bad_sensor_range_or_nothing_left_is_a_clear_error() -> None:
    with pytest.raises(RecordingError, match=r"metadata sensor_full_scale_um: 'wide' is not a positive"):
        within_sensor_range([_exp("a", 30.0, {SENSOR_RANGE_KEY: "wide"})])
    with pytest.raises(RecordingError, match="every experiment's readback reached the sensor's full scale"):
        within_sensor_range([_exp("b", 60.0, {SENSOR_RANGE_KEY: "50"})])


@pytest.fixture(scope="module")
def clipped_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, float]:
    """Six triangles whose largest ones the sensor read clipped (its documented range below their peak)."""
    s = synth_session(MEDIUM_TUBE, random_plan(3, 6, range_v=(80.0, 300.0)), samples_per_loop=512, seed=3)
    rec = s.recording
    assert rec.experiment is not None
    peaks = sorted(float(np.max(np.abs(rec.position_um[rec.experiment == p.label]))) for p in s.plan)
    full_scale = 0.5 * (peaks[-3] + peaks[-2])  # the two largest reach it
    read = np.clip(rec.position_um, -full_scale, full_scale * 32767 / 32768)
    path = tmp_path_factory.mktemp("clip") / "frame.csv"
    clipped = Recording(rec.t_s, rec.voltage_v, read, axis=rec.axis, experiment=rec.experiment)
    write_recording(path, clipped, metadata={SENSOR_RANGE_KEY: f"{full_scale:.6f}"})
    return path, 2, full_scale


def test_offline_calibrate_leaves_the_clipped_experiments_out_and_says_so(
    clipped_file: tuple[Path, int, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, n_clipped, _ = clipped_file
    js = tmp_path / "cal.json"
    out = tmp_path / "c.yaml"
    assert main(["calibrate", str(path), "--model", "thesis", "--out", str(out), "--json", str(js)]) == 0
    said = capsys.readouterr()
    assert "WARNING: left out, the readback at the sensor's full scale:" in said.out + said.err
    assert len(json.loads(js.read_text())["experiments"]) == 6 - n_clipped


def test_the_audit_leaves_the_clipped_experiments_out_and_notes_it(
    clipped_file: tuple[Path, int, float],
) -> None:
    path, n_clipped, full_scale = clipped_file
    result = run_audit(read_experiments([path]), [])
    (note,) = [n for n in result.notes if n.startswith("left out, the readback at the sensor's full scale")]
    assert note.count(f"at +-{full_scale:g} um") == n_clipped
    assert result.data.n_experiments == 6 - n_clipped


def _triangles(peak_um: float, clip_um: float | None, step_um: float = 0.0, seed: int = 0) -> Experiment:
    """Three 1 Hz triangles at 2 kS/s, read with 3 nm noise, quantised to ``step_um``, clipped."""
    rng = np.random.default_rng(seed)
    t = np.arange(6000) / 2000.0
    phase = t % 1.0
    v = 100.0 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    x = peak_um * v / 100.0 + 0.003 * rng.standard_normal(t.size)
    if step_um:
        x = np.round(x / step_um) * step_um
    if clip_um is not None:
        x = np.minimum(x, clip_um)
    return Experiment("tri", "x", t, v, x)


def test_a_readback_stuck_at_its_extreme_while_the_drive_sweeps_reads_as_a_clipped_sensor() -> None:
    """A recording that does not document its sensor's range: an ADC at its end code holds one value
    while the drive sweeps the part of the loop beyond it; a live sensor, even quantised to 1.5 nm
    steps, changes at the turning points, and a hold at the top (the drive still) is not a sweep."""
    from piezod.readback import PLATEAU_MIN_SAMPLES, plateau_mask

    clipped = _triangles(60.0, 50.0)
    stuck = plateau_mask(clipped.position_um, clipped.voltage_v)
    # the top sixth of every 2000-sample triangle, three times
    assert 3 * 300 < np.count_nonzero(stuck) < 3 * 360
    assert np.all(clipped.position_um[stuck] == 50.0)
    for step in (0.0, 0.0015, 0.005):
        live = _triangles(60.0, None, step_um=step, seed=1)
        assert not plateau_mask(live.position_um, live.voltage_v).any(), step
    # a hold at the top: the reading repeats, the drive does not move
    held = np.r_[np.linspace(0.0, 100.0, 500), np.full(400, 100.0)]
    assert not plateau_mask(0.5 * held, held).any()
    short = np.arange(PLATEAU_MIN_SAMPLES - 1.0)
    assert not plateau_mask(np.full(short.size, 50.0), short).any()

    kept, note = within_sensor_range([clipped, _triangles(40.0, None, seed=2)])
    assert len(kept) == 1 and kept[0].position_um.max() < 45.0
    assert note is not None and "samples stuck at +50 um while the drive moved" in note


def test_offline_calibrate_leaves_a_clipped_experiment_out_of_a_recording_that_documents_no_range(
    clipped_file: tuple[Path, int, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, n_clipped, _ = clipped_file
    rec = read_experiments([path])
    bare = tmp_path / "bare.csv"
    lines = [ln for ln in path.read_text().splitlines(keepends=True) if SENSOR_RANGE_KEY not in ln]
    bare.write_text("".join(lines))
    assert len(rec) == 6
    js = tmp_path / "cal.json"
    assert (
        main(
            [
                "calibrate",
                str(bare),
                "--model",
                "thesis",
                "--out",
                str(tmp_path / "c.yaml"),
                "--json",
                str(js),
            ]
        )
        == 0
    )
    said = capsys.readouterr()
    assert "while the drive moved: a sensor at its end code" in said.out + said.err
    assert len(json.loads(js.read_text())["experiments"]) == 6 - n_clipped
