"""The simulated microscope, images from recordings, .gwy files and image-based linearity."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil_sim.microscope import Microscope, MicroscopeConfig
from hil_sim.sample import SAMPLES, get_sample
from hil_sim.stage import StageConfig
from piezod.config import config_dir, default_sim_config_path
from piezod.errors import RecordingError
from piezod.image import images, raster_samples
from piezod.image_linearity import find_flanks, flank_sampled_linearity, image_linearity, window_linearity
from piezod.linearity import experiment_linearity
from piezod.recording import Recording, read_recording, split_experiments

# ------------------------------------------------------------------------------------ samples


def test_line_pattern_has_its_pitch_a_missing_line_and_a_particle() -> None:
    s = get_sample("line-3um")
    x = np.linspace(-15.0, 15.0, 30001)
    h = s.height(x, 0.0) - s.tilt_x * x
    up = x[1:][(h[:-1] < 0.05) & (h[1:] >= 0.05)]
    gaps = np.diff(up)
    assert np.median(gaps) == pytest.approx(3.0, abs=0.01)
    assert np.isclose(gaps, 6.0, atol=0.05).sum() == 1  # the missing line
    d = s.defects[0]
    assert s.height(d.x_um, d.y_um) - s.height(d.x_um, d.y_um + 2.0) > 0.1
    with pytest.raises(ValueError, match="known: line-3um"):
        get_sample("nope")


def test_every_sample_is_deterministic_and_bounded() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-20, 20, 500), rng.uniform(-20, 20, 500)
    for s in SAMPLES.values():
        a, b = s.height(x, y), s.height(x, y)
        assert np.array_equal(a, b) and np.isfinite(a).all()
        assert np.ptp(a) < 0.5


def test_z_feedback_follows_the_surface_with_its_bandwidth() -> None:
    stage = StageConfig.from_file(default_sim_config_path())
    cfg = MicroscopeConfig(sample="steps-100nm", height_noise_nm_rms=0.0, feedback_bandwidth_hz=200.0)
    mic = Microscope(cfg, stage)
    fs = 20000.0
    x = np.linspace(-5.0, 7.0, 12000)  # 12 um in 0.6 s: steps up at -2 um and down at +2 um
    vz, ez = [], []
    for i in range(0, x.size, 200):
        v, e = mic.step(x[i : i + 200], np.zeros(200), 1.0 / fs)
        vz.append(v)
        ez.append(e)
        assert mic.last_error_nm_rms < 0.5  # the passes find the voltage of the extension
    v, e = np.concatenate(vz), np.concatenate(ez)
    h = mic.sample.height(x, 0.0)
    settled = np.convolve(np.abs(np.diff(h, prepend=h[0])) > 1e-6, np.ones(160), "full")[: h.size] == 0
    assert settled.sum() > 10000
    assert np.abs(e - h)[settled].max() < 1e-3  # on the terraces the tip follows within 1 nm
    assert np.abs(e - h)[~settled].max() > 0.01  # at the steps the loop lags (finite bandwidth)
    # the z voltage needed for it is not proportional: hysteresis + creep of the z piezo
    assert np.ptp(v) > 0.1 / 0.024


# ---------------------------------------------------------------------- images (synthetic, offline)


def _synthetic(nonlinear: float, *, lines: int = 6, pixels: int = 200, cubic: float = 0.0) -> Recording:
    """A raster recording of the line pattern with a known fast-axis distortion and a sensor."""
    fs, f, r = 5000.0, 2.0, 20.0
    n_half = int(fs / f / 2)
    ramp = np.linspace(-r / 2, r / 2, n_half, endpoint=False)
    tgt = np.concatenate([np.concatenate((ramp, -ramp)) for _ in range(lines)] + [np.array([-r / 2])])
    t = np.arange(tgt.size) / fs
    u = tgt / (r / 2)
    pos = tgt * 1.01 + nonlinear * (r / 2) * (1 - u**2) + cubic * (r / 2) * u**3  # +1 % length, a bow
    line = np.repeat(np.arange(lines), 2 * n_half)
    y = np.concatenate((-r / 2 + r * line / max(lines - 1, 1), [r / 2]))
    h = get_sample("line-3um").height(pos, y)
    meta = {"range_um": "20", "pixels": str(pixels), "line_rate_hz": "2", "sample_rate_hz": str(fs)}
    return Recording(
        t_s=t,
        voltage_v=tgt * 10,
        position_um=pos,
        target_um=tgt,
        z_voltage_v=h / 0.024,
        axis=np.full(t.size, "x"),
        metadata=meta,
    )


@pytest.mark.parametrize(("bow", "cubic"), [(0.0, 0.0), (0.002, 0.0), (0.05, 0.02)])
def test_image_metrics_reproduce_the_sensor_metrics(bow: float, cubic: float) -> None:
    # (0.05, 0.02): 0.5 um of bow and 0.2 um of S (0.7 % non-linearity, an uncorrected scan's order):
    # flanks are uniform in true position, the sensor's samples in time; a straight line through
    # the flanks reads +2.43 % where the samples give +2.19 %. The image metric resamples the
    # flanks' position map uniformly in commanded position and regresses it as the sensor path does.
    rec = _synthetic(bow, cubic=cubic)
    pair = next(p for p in images(rec) if p.grid == "commanded")
    assert pair.trace.shape == (6, 200) and np.isfinite(pair.trace).all()
    sensor = experiment_linearity(split_experiments(rec)[0])
    rs = raster_samples(rec)
    for d, img, br in ((1, pair.trace, sensor.trace), (-1, pair.retrace, sensor.retrace)):
        im = image_linearity(img, pair.geometry, 3.0, d)
        same = window_linearity(rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, im)
        assert im.length_error_pct == pytest.approx(same.length_error_pct, abs=0.05)
        assert im.nonlinearity_pct == pytest.approx(same.nonlinearity_pct, abs=0.05)
        # the stretches the image sees cover most of the line
        assert same.n > 0.7 * br.n
        assert im.length_error_pct == pytest.approx(br.length_error_pct, abs=0.05 if bow < 0.01 else 0.1)
        if cubic:  # the flanks' own straight line weighs the curvature otherwise
            assert abs(im.flank_length_error_pct - same.length_error_pct) > 0.15
        # the edge roughness (3 nm rms) is the uncertainty's noise
        assert 0.002 < im.length_error_unc_pct < 0.05
    assert sensor.trace.length_error_pct == pytest.approx(1.0 + 60 * cubic, abs=0.01)  # u^3: slope 3/5


@pytest.mark.parametrize(("amp_um", "wavelength_um"), [(0.0, 1.0), (0.02, 1.3)])
def test_structure_finer_than_the_flanks_is_what_the_flank_sampled_truth_shows(
    amp_um: float, wavelength_um: float
) -> None:
    # A true position with a 20 nm wiggle of 1.3 um wavelength (finer than the flank spacing of a
    # 3 um pattern, ~1.5 um): the flanks alias it, so the image metric reads 0.08 % off the truth
    # over the same stretches - as the truth sampled at the flanks does (a perfect flank metric);
    # without the wiggle all three agree.
    rec = _synthetic(0.002)
    pos = rec.position_um + amp_um * np.sin(2 * np.pi * rec.target_um / wavelength_um)
    rows = np.arange(rec.t_s.size) // (rec.t_s.size // 6)
    z = get_sample("line-3um").height(pos, -10.0 + 4.0 * rows) / 0.024
    rec = dataclasses.replace(rec, position_um=pos, z_voltage_v=z)
    pair = next(p for p in images(rec) if p.grid == "commanded")
    rs = raster_samples(rec)
    for d, img in ((1, pair.trace), (-1, pair.retrace)):
        im = image_linearity(img, pair.geometry, 3.0, d)
        truth = window_linearity(rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, im)
        at = flank_sampled_linearity(
            rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, im, find_flanks(img, pair.geometry)
        )
        assert im.length_error_pct == pytest.approx(at.length_error_pct, abs=0.02)
        if amp_um:
            assert abs(at.length_error_pct - truth.length_error_pct) > 0.05
        else:
            assert at.length_error_pct == pytest.approx(truth.length_error_pct, abs=0.01)


def test_flanks_are_found_to_a_fraction_of_the_sample_spacing() -> None:
    # a sample every 16 nm, pixels of 100 nm: wherever an edge falls in its pixel, the pixel's
    # area places it (a straight line between pixel centres was up to 8 nm off)
    import dataclasses

    smooth = dataclasses.replace(get_sample("line-3um"), roughness_nm_rms=0.0)
    rec = _synthetic(0.0)
    rec = dataclasses.replace(rec, z_voltage_v=smooth.height(rec.position_um, _rows_y(rec)) / 0.024)
    pair = next(p for p in images(rec) if p.grid == "commanded")
    fl = find_flanks(pair.trace, pair.geometry)
    true = fl.xi_um * 1.01 - 0.75  # edges at k P +- P / 4 on the stretched scan
    err = true - np.round(true / 1.5) * 1.5
    assert np.abs(err[fl.line != 4]).max() < 0.002  # um (line 4 passes the particle's flank)


def test_flanks_follow_plateau_levels_that_bend_along_the_line() -> None:
    """Heights recorded as z-piezo voltage bend along the line (the z piezo's hysteresis under
    the sample's tilt): the levels of each edge are the plateaus' beside it, so rising and
    falling flanks are not pushed apart by a level the line's two-level fit misses."""
    import dataclasses

    smooth = dataclasses.replace(get_sample("line-3um"), roughness_nm_rms=0.0)
    rec = _synthetic(0.0)
    x = rec.position_um
    # 8 % of the step at the ends of a 20 um line, curved
    bend = 0.008 * (x / 10.0) ** 2 + 0.004 * (x / 10.0) ** 3
    h = smooth.height(x, _rows_y(rec)) + bend
    rec = dataclasses.replace(rec, z_voltage_v=h / 0.024)
    pair = next(p for p in images(rec) if p.grid == "commanded")
    fl = find_flanks(pair.trace, pair.geometry)
    true = fl.xi_um * 1.01 - 0.75
    err = true - np.round(true / 1.5) * 1.5
    # the two-level fit's levels put them up to 18 nm off, rising and falling in opposite
    # directions; a flank within a window of the line's end keeps its crossing (~30 nm here)
    inner = (fl.line != 4) & (np.abs(fl.xi_um) < 9.5)
    assert np.abs(err[inner]).max() < 0.0015


def _rows_y(rec: Recording) -> np.ndarray:
    lines = 6
    n_half = (rec.t_s.size - 1) // (2 * lines)
    line = np.repeat(np.arange(lines), 2 * n_half)
    return np.concatenate((-10.0 + 20.0 * line / (lines - 1), [10.0]))


def test_flanks_skip_the_particle_and_number_across_the_missing_line() -> None:
    rec = _synthetic(0.0, lines=12)
    pair = next(p for p in images(rec) if p.grid == "commanded")
    fl = find_flanks(pair.trace, pair.geometry)
    for r in np.unique(fl.line):
        s = (fl.line == r) & (fl.family > 0)
        assert np.diff(fl.k[s]).max() <= 2
    # no flank pair narrower than a line survives (the particle at x = -7.3 um, y = 4.1 um)
    assert np.abs(fl.xi_um[(fl.line == 8)] + 7.3).min() > 0.3


def test_images_refuse_recordings_that_are_not_rasters() -> None:
    rec = _synthetic(0.0)
    bare = Recording(t_s=rec.t_s, voltage_v=rec.voltage_v, position_um=rec.position_um, metadata=rec.metadata)
    with pytest.raises(RecordingError, match="no 'target' column"):
        raster_samples(bare)
    no_z = Recording(
        t_s=rec.t_s,
        voltage_v=rec.voltage_v,
        position_um=rec.position_um,
        target_um=rec.target_um,
        metadata={},
    )
    with pytest.raises(RecordingError, match="range_um"):
        images(no_z)


# ----------------------------------------------------------------- through the real simulated board


def _piezod(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "piezod", *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("img")
    # the sensorless calibration's result at 5 kS/s (light enough for a busy machine), with its sensor on
    text = (config_dir() / "sim-microscope-calibrated.yaml").read_text()
    with_sensor = d / "with-sensor.yaml"
    with_sensor.write_text(text.replace("position_sensor: false", "position_sensor: true"))
    common = ["--sim", "--sample", "line-3um", "--range-um", "20", "--line-rate-hz", "2", "--lines", "6"]
    out = {}
    for name, extra in (
        ("corrected", ["--config", str(with_sensor), "--pixels", "256"]),
        (
            "nosensor",
            ["--config", str(config_dir() / "sim-microscope.yaml"), "--no-correction", "--pixels", "128"],
        ),
    ):
        p = _piezod("scan", *common, *extra, "--out", str(d / f"{name}.csv"), cwd=d)
        assert p.returncode == 0, p.stderr
        out[name] = d / f"{name}.csv"
    return out


def test_scan_records_the_height_channel_and_the_metadata(scans: dict[str, Path]) -> None:
    rec = read_recording(scans["corrected"])
    assert rec.z_voltage_v is not None and np.ptp(rec.z_voltage_v) > 1.0
    for key in ("pixels", "started_utc", "config_sha256", "model", "model_params", "position_sensor"):
        assert key in rec.metadata
    assert rec.metadata["position_sensor"] == "yes"
    bare = read_recording(scans["nosensor"])
    assert bare.metadata["position_sensor"] == "no"
    assert np.all(bare.position_um[bare.axis == "x"] == 0.0)  # no sensor: the ADC reads nothing


def test_piezod_image_writes_gwy_files_that_gwyfile_opens(scans: dict[str, Path], tmp_path: Path) -> None:
    import gwyfile

    p = _piezod(
        "image",
        str(scans["corrected"]),
        str(scans["nosensor"]),
        "--config",
        str(default_sim_config_path()),
        "--out",
        str(tmp_path),
        "--pitch-um",
        "3",
        "--json",
        "-",
        cwd=tmp_path,
    )
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout)["recordings"]
    obj = gwyfile.load(str(tmp_path / "corrected.gwy"))
    titles = sorted(str(obj[k]) for k in obj if k.endswith("/data/title"))
    assert (
        "height_model trace (commanded grid)" in titles and "height_model retrace (measured grid)" in titles
    )
    meta = dict(obj["/0/meta"])
    assert meta["range_um"] == "20" and meta["pixels"] == "256" and meta["lines"] == "6"
    assert len(meta["config_sha256"]) == 64 and meta["model"] in ("thesis", "dynamic")
    assert obj["/0/data"].data.shape == (6, 256)
    bare = gwyfile.load(str(tmp_path / "nosensor.gwy"))
    assert not any("measured" in str(bare[k]) for k in bare if k.endswith("/data/title"))
    assert (tmp_path / "corrected-pitch-error.png").stat().st_size > 1000
    # where a sensor exists, the image reproduces the sensor's figures of the same scan: over the
    # same commanded span by the same regression, and (a corrected, straight scan) over the whole lines
    img, sen = res[0]["image_linearity"], res[0]["sensor_window_linearity"]
    whole = res[0]["sensor_linearity"]
    for b in ("trace", "retrace"):
        assert abs(img[b]["length_error_pct"] - sen[b]["length_error_pct"]) <= 0.05
        assert abs(img[b]["nonlinearity_pct"] - sen[b]["nonlinearity_pct"]) <= 0.05
        assert abs(img[b]["length_error_pct"] - whole[b]["length_error_pct"]) <= 0.05
    # the uncorrected scan without a sensor: its distortion from the image alone
    assert res[1]["image_linearity"]["trace"]["length_error_pct"] > 2.0
    assert "sensor_linearity" not in res[1]


def test_piezod_image_names_a_file_that_is_not_a_raster(tmp_path: Path) -> None:
    f = tmp_path / "plain.csv"
    f.write_text("t,voltage,position\n0,0,0\n0.1,1,0.1\n")
    p = _piezod("image", str(f), "--out", str(tmp_path), cwd=tmp_path)
    assert p.returncode == 2
    assert "plain.csv" in p.stderr and "range_um" in p.stderr and "Traceback" not in p.stderr


def _posts(x: np.ndarray, y: np.ndarray, pitch: float, rows: bool = True) -> np.ndarray:
    """Square posts (half the pitch) averaged over each pixel (8 x 8 sub-samples) and blurred, as a scan
    sees them."""
    sub = (np.arange(8) + 0.5) / 8 - 0.5

    def fine(c: np.ndarray) -> np.ndarray:
        step = np.gradient(c)
        return (c[:, None] + sub[None, :] * step[:, None]).ravel()

    xf, yf = fine(x), fine(y)
    on_x = (np.mod(xf + 0.3, pitch) < 0.5).astype(float)
    on_y = (np.mod(yf + 0.2, pitch) < 0.5).astype(float) if rows else np.ones(yf.size)
    img = np.outer(on_y, on_x).reshape(y.size, 8, x.size, 8).mean(axis=(1, 3))
    from scipy.ndimage import gaussian_filter

    out: np.ndarray = gaussian_filter(img, 1.0)  # the tip and the z loop blur edges over ~a pixel
    return out


def test_slow_axis_linearity_from_the_columns_of_a_2d_grating() -> None:
    from piezod.image import Geometry
    from piezod.image_linearity import slow_image_linearity

    pitch, rng = 1.0, np.random.default_rng(4)
    geo = Geometry(
        range_um=12.0,
        offset_um=0.0,
        slow_range_um=12.0,
        offset_slow_um=0.0,
        pixels=240,
        rotation_deg=0.0,
        line_rate_hz=1.0,
    )
    lines = 240
    xc = geo.pixel_centres_um()
    yc = -6.0 + (np.arange(lines) + 0.5) * 12.0 / lines
    for gain in (1.0, 1.012):
        x_true = 0.995 * xc
        y_true = gain * yc + 0.002 * yc**2  # the slow axis stretched, slightly bowed
        img = _posts(x_true, y_true, pitch) + 0.01 * rng.standard_normal((lines, geo.pixels))
        slow = slow_image_linearity(img, geo, pitch, 1)
        # the sensor's view of the same slow axis: true vs commanded over the frame
        g = np.polyfit(yc, y_true, 1)[0]
        assert slow.length_error_pct == pytest.approx(100.0 * (g - 1.0), abs=0.05)
        assert slow.nonlinearity_pct < 0.3
        fast = image_linearity(img, geo, pitch, 1)
        assert fast.length_error_pct == pytest.approx(-0.5, abs=0.05)
    # a 1D line pattern along the slow axis has no flanks across it
    lines_only = _posts(xc, yc, pitch, rows=False) + 0.01 * rng.standard_normal(img.shape)
    with pytest.raises(RecordingError):
        slow_image_linearity(lines_only, geo, pitch, 1)


def test_images_of_one_frame_are_its_lines_of_the_whole_image() -> None:
    rec = _synthetic(0.0)
    rec = dataclasses.replace(rec, metadata={**rec.metadata, "lines": "3"})  # 6 lines: two frames
    whole = next(p for p in images(rec) if p.grid == "commanded")
    second = next(p for p in images(rec, frame=1) if p.grid == "commanded")
    np.testing.assert_array_equal(second.trace, whole.trace[3:])
    np.testing.assert_array_equal(second.retrace, whole.retrace[3:])
    with pytest.raises(RecordingError, match=r"frame 2: the recording holds 2 frame\(s\) of 3 lines"):
        images(rec, frame=2)
    with pytest.raises(RecordingError, match="lines per frame"):
        images(
            dataclasses.replace(rec, metadata={k: v for k, v in rec.metadata.items() if k != "lines"}),
            frame=0,
        )
