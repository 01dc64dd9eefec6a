"""The recording format: reader, writer, experiments and scan inference."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.errors import RecordingError
from piezod.recording import (
    Experiment,
    Recording,
    RecordingWriter,
    parse_recording,
    read_experiments,
    read_recording,
    split_experiments,
    write_recording,
)
from piezod.scan_inference import infer_scan

HEADER = "t,voltage,position"


def _triangle(
    n_loops: float, spl: int, v_min: float, v_max: float, f: float, phase: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(round(n_loops * spl) + 1) + phase * spl
    ph = (k / spl) % 1.0
    tri = np.where(ph < 0.5, 2 * ph, 2 - 2 * ph)
    return k / (f * spl), v_min + (v_max - v_min) * tri


def _write(tmp_path: Path, text: str, name: str = "rec.csv") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode("utf-8"))
    return p


def _err(tmp_path: Path, text: str, **kw: bool) -> RecordingError:
    p = _write(tmp_path, text)
    with pytest.raises(RecordingError) as info:
        read_recording(p, **kw)
    err = info.value
    assert err.path == str(p)
    assert str(err).startswith(f"{p}:{err.line}: " if err.line is not None else f"{p}: ")
    return err


# ------------------------------------------------------------------------------------------- round trip


def test_round_trip_all_columns(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 1000
    t = np.cumsum(rng.uniform(1e-4, 1e-3, n)) + 1234.5
    rec = Recording(
        t_s=t,
        voltage_v=rng.uniform(-400, 400, n),
        position_um=rng.normal(0, 20, n),
        target_um=rng.normal(0, 20, n),
        axis=np.where(np.arange(n) < 600, "x", "x"),
        experiment=np.where(np.arange(n) < 600, "first run", "second-run_2"),
        metadata={"sample_rate_hz": "10000", "note": "a: b"},
    )
    p = tmp_path / "a.csv"
    write_recording(p, rec, metadata={"extra": 1})
    back = read_recording(p)
    np.testing.assert_allclose(back.t_s, rec.t_s, rtol=1e-14)
    np.testing.assert_allclose(back.voltage_v, rec.voltage_v, rtol=1e-9)
    np.testing.assert_allclose(back.position_um, rec.position_um, rtol=1e-9, atol=1e-12)
    assert back.target_um is not None and rec.target_um is not None
    np.testing.assert_allclose(back.target_um, rec.target_um, rtol=1e-9, atol=1e-12)
    assert back.experiment is not None and back.experiment.tolist() == rec.experiment.tolist()  # type: ignore[union-attr]
    assert back.columns == ("t", "voltage", "position", "target", "axis", "experiment")
    assert dict(back.metadata) == {"sample_rate_hz": "10000", "note": "a: b", "extra": "1"}
    assert back.line_numbers is not None and back.line_numbers[0] == 5  # 3 metadata lines + header
    exps = split_experiments(back)
    assert [e.label for e in exps] == ["first run", "second-run_2"]
    assert [len(e) for e in exps] == [600, 400]
    assert exps[1].first_line == 5 + 600


def test_streaming_writer_blocks_and_append(tmp_path: Path) -> None:
    p = tmp_path / "s.csv"
    cols = ("t", "voltage", "position", "experiment")
    with RecordingWriter(p, cols, metadata={"axis_note": "x"}) as w:
        w.write([0.0, 0.1], [1.0, 2.0], [0.5, 0.6], experiment="a")
        w.write([0.2], [3.0], [0.7], experiment=["a"])
    with p.open("a", encoding="utf-8") as fh:  # a crash mid-line
        fh.write("0.3,4.0,0.")
    with RecordingWriter(p, cols, append=True) as w:
        assert w.dropped_tail_bytes == len("0.3,4.0,0.")
        w.write(np.array([0.3, 0.4]), np.array([4.0, 5.0]), np.array([0.8, 0.9]), experiment="b")
    rec = read_recording(p)
    np.testing.assert_array_equal(rec.t_s, [0.0, 0.1, 0.2, 0.3, 0.4])
    assert [e.label for e in split_experiments(rec)] == ["a", "b"]
    with pytest.raises(RecordingError, match="header"):
        RecordingWriter(p, ("t", "voltage", "position"), append=True)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"experiment": "a,b"}, "invalid experiment"),
        ({"experiment": ""}, "invalid experiment"),
        ({"axis": "w"}, "not one of x, y, z"),
        ({}, "'experiment' missing"),
    ],
)
def test_writer_rejects_bad_rows(tmp_path: Path, kwargs: dict[str, str], match: str) -> None:
    cols = (
        ("t", "voltage", "position", "experiment")
        if "axis" not in kwargs
        else ("t", "voltage", "position", "axis")
    )
    with RecordingWriter(tmp_path / "w.csv", cols) as w, pytest.raises(RecordingError, match=match):
        w.write([0.0], [1.0], [2.0], **kwargs)


def test_writer_rejects_non_finite(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "w.csv") as w, pytest.raises(RecordingError, match="non-finite"):
        w.write([0.0, 1.0], [1.0, math.nan], [2.0, 3.0])


def test_comments_blank_lines_crlf_bom_and_unknown_columns(tmp_path: Path) -> None:
    text = "\ufeff# k: v\r\n\r\nt, voltage ,position,sensor_raw\r\n0,1,2,abc\r\n# paused\r\n\r\n1,2,3,d\r\n"
    rec = read_recording(_write(tmp_path, text))
    np.testing.assert_array_equal(rec.t_s, [0, 1])
    assert rec.line_numbers is not None and rec.line_numbers.tolist() == [4, 7]
    assert rec.ignored_columns == ("sensor_raw",)
    assert rec.metadata["k"] == "v"


def test_interleaved_axes_t_increases_per_axis(tmp_path: Path) -> None:
    text = "t,voltage,position,axis\n0,1,2,x\n0,5,6,y\n1,2,3,x\n1,6,7,y\n"
    exps = split_experiments(read_recording(_write(tmp_path, text)))
    assert [(e.axis, e.t_s.tolist()) for e in exps] == [("x", [0.0, 1.0]), ("y", [0.0, 1.0])]
    err = _err(tmp_path, "t,voltage,position,axis\n0,1,2,x\n0,5,6,y\n0,2,3,x\n")
    assert err.line == 4 and "on axis x" in err.reason


# ------------------------------------------------------------------------------------ malformed files


@pytest.mark.parametrize(
    ("text", "line", "reason"),
    [
        ("", 1, "empty file"),
        ("# only\n# comments\n", 2, "no header"),
        ("t,voltage\n0,1\n", 1, "missing required column 'position'"),
        ("t,voltage,position,t\n0,1,2,3\n", 1, "duplicate column 't'"),
        ("t,,position\n", 1, "empty column name"),
        (f"{HEADER}\n", 1, "no data rows"),
        (f"# m\n{HEADER}\n0,1,2\n0.1,abc,2\n", 4, "column 'voltage': not a number: 'abc'"),
        (f"{HEADER}\n0,1,2\n0.1,,2\n", 3, "column 'voltage': not a number: ''"),
        (f"{HEADER}\n0,1,2\n0.1,1_0,2\n", 3, "not a number: '1_0'"),
        (f"{HEADER}\n0,1,2\n0.1,1\n", 3, "wrong number of cells: 2, expected 3"),
        (f"{HEADER}\n0,1,2\n0.1,1,2,3\n", 3, "wrong number of cells: 4, expected 3"),
        (f"{HEADER}\n0,1,2\n0.1,1,nan\n", 3, "column 'position': non-finite value nan"),
        (f"{HEADER}\n0,1,2\n0.2,1,2\n\n0.1,1,2\n", 5, "column 't': not strictly increasing: 0.1 after 0.2"),
        (f"{HEADER}\n0,1,2\n0,1,2\n", 3, "not strictly increasing"),
        (f"{HEADER},axis\n0,1,2,x\n1,1,2,q\n", 3, "column 'axis': 'q' is not one of x, y, z"),
        (f"{HEADER},experiment\n0,1,2,a\n1,1,2, \n", 3, "column 'experiment': empty label"),
        (f"{HEADER},experiment\n0,1,2,a\n1,1,2,b\n2,1,2,a\n", 4, "experiment 'a' resumes"),
    ],
)
def test_malformed_file_gives_file_line_and_reason(tmp_path: Path, text: str, line: int, reason: str) -> None:
    err = _err(tmp_path, text)
    assert err.line == line
    assert reason in err.reason


@pytest.mark.parametrize("chunk", [1, 5, 13])
def test_a_body_parsed_in_chunks_gives_the_same_rows_and_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, chunk: int
) -> None:
    """The body is parsed a few MB at a time (a 100 kS/s recording is millions of rows): chunks of
    a few characters give the same columns, labels, line numbers and first error as one chunk."""
    import piezod.recording as recording

    rows = [f"{k},{k % 7 - 3},{0.5 * k},{'xy'[k % 2]},{'abc'[k // 10]}" for k in range(30)]
    rows[4:4] = ["# change: a note", ""]
    rows[17:17] = ["#", "", "# another"]
    text = f"# k: v\n{HEADER},axis,experiment\n" + "\n".join(rows) + "\n"
    whole = parse_recording(text, path="w.csv")
    monkeypatch.setattr(recording, "PARSE_CHUNK_CHARS", chunk)
    part = parse_recording(text, path="w.csv")
    for name in ("t_s", "voltage_v", "position_um", "axis", "experiment", "line_numbers"):
        np.testing.assert_array_equal(getattr(part, name), getattr(whole, name))
    assert part.metadata == whole.metadata and len(part) == 30
    for bad, line, reason in [
        (f"{HEADER},experiment\n0,1,2,a\n1,1,2,a\n# c\n2,1,2,b\n3,1,2, \n", 6, "empty label"),
        (f"{HEADER},axis\n0,1,2,x\n1,1,2,x\n\n2,1,2,q\n", 5, "'q' is not one of"),
        (f"{HEADER}\n0,1,2\n0.2,1,2\n\n0.1,1,2\n", 5, "not strictly increasing"),
        (f"{HEADER}\n0,1,2\n1,2,3\n2,3", 4, "crash"),
        (f"{HEADER},experiment\n0,1,2,a\n1,1,2,b\n2,1,2,a\n", 4, "experiment 'a' resumes"),
        ("# only\n# comments\n", 2, "no header"),
    ]:
        with pytest.raises(RecordingError) as info:
            parse_recording(bad, path="b.csv")
        assert info.value.line == line and reason in info.value.reason, (bad, info.value)
    tail = parse_recording(f"{HEADER}\n0,1,2\n1,2,3\n2,3", allow_truncated_tail=True)
    assert tail.dropped_tail and tail.t_s.tolist() == [0, 1]


def test_bytes_outside_the_given_encoding_name_the_line(tmp_path: Path) -> None:
    p = tmp_path / "bin.csv"
    p.write_bytes(b"t,voltage,position\n0,1,2\n1,\xff,2\n")
    with pytest.raises(RecordingError, match=r"bin\.csv:3: not utf-8") as info:
        read_recording(p, encoding="utf-8")
    assert info.value.line == 3
    # Detected as a single-byte encoding, the bad cell is then named as a bad number.
    with pytest.raises(RecordingError, match=r"bin\.csv:3:") as info:
        read_recording(p)
    assert info.value.line == 3


def test_latin1_and_utf16_instrument_exports_are_read(tmp_path: Path) -> None:
    text = "# instrument: Interferometer \u00b5m, 23 \u00b0C\nt,voltage,position\n0,1,2\n1,2,3\n"
    latin = tmp_path / "latin.csv"
    latin.write_bytes(text.encode("latin-1"))
    rec = read_recording(latin)
    assert rec.metadata["instrument"] == "Interferometer \u00b5m, 23 \u00b0C"
    assert rec.metadata["encoding"] == "cp1252"
    assert list(rec.position_um) == [2.0, 3.0]
    assert read_recording(latin, encoding="latin-1").metadata["encoding"] == "latin-1"
    wide = tmp_path / "wide.csv"
    wide.write_bytes(text.encode("utf-16"))
    assert list(read_recording(wide).voltage_v) == [1.0, 2.0]
    with pytest.raises(RecordingError, match="unknown encoding"):
        read_recording(latin, encoding="no-such-codec")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "nope.csv")


def test_truncated_tail(tmp_path: Path) -> None:
    text = f"{HEADER}\n0,1,2\n1,2,3\n2,3"
    err = _err(tmp_path, text)
    assert err.line == 4 and "wrong number of cells" in err.reason and "crash" in err.reason
    rec = read_recording(tmp_path / "rec.csv", allow_truncated_tail=True)
    assert rec.dropped_tail and rec.t_s.tolist() == [0, 1]
    # a complete but unterminated last line is accepted by default
    rec = read_recording(_write(tmp_path, f"{HEADER}\n0,1,2\n1,2,3"))
    assert rec.t_s.tolist() == [0, 1] and not rec.dropped_tail


def test_non_scan_is_rejected_when_a_scan_is_required(tmp_path: Path) -> None:
    t = np.linspace(0, 4, 801)
    rec = Recording(t_s=t, voltage_v=100 * np.sin(2 * np.pi * t), position_um=t)
    write_recording(tmp_path / "sine.csv", rec)
    (exp,) = read_experiments([tmp_path / "sine.csv"])
    with pytest.raises(RecordingError, match=r"sine\.csv:2: .*not a periodic triangular scan.*sine"):
        exp.require_scan()


def test_read_experiments_prefixes_labels_and_filters_axis(tmp_path: Path) -> None:
    for name in ("a.csv", "b.csv"):
        _write(tmp_path, "t,voltage,position,axis\n0,1,2,x\n0,1,2,y\n", name)
    exps = read_experiments([tmp_path / "a.csv", tmp_path / "b.csv"], axis="y")
    assert [(e.label, e.axis) for e in exps] == [("a.csv:a", "y"), ("b.csv:b", "y")]
    with pytest.raises(RecordingError, match="no experiments for axis z"):
        read_experiments([tmp_path / "a.csv"], axis="z")


# --------------------------------------------------------------------------------------- scan inference


@given(
    f=st.floats(0.01, 50.0),
    v_min=st.floats(-300, 100),
    v_range=st.floats(10, 400),
    phase=st.floats(0.0, 0.999),
    spl=st.sampled_from([64, 250, 1000, 2048]),
    loops=st.integers(2, 6),
    noise_frac=st.sampled_from([0.0, 1e-3, 5e-3]),
    seed=st.integers(0, 2**16),
)
def test_inference_on_triangles(
    f: float, v_min: float, v_range: float, phase: float, spl: int, loops: int, noise_frac: float, seed: int
) -> None:
    t, v = _triangle(loops, spl, v_min, v_min + v_range, f, phase)
    noisy = v + np.random.default_rng(seed).normal(0, noise_frac * v_range, v.size)
    info = infer_scan(t, noisy)
    assert info.kind == "triangle", info.reason
    assert info.is_scan
    # one sample of timing per turning point, plus noise
    assert info.frequency_hz == pytest.approx(f, rel=2.0 / (spl * (loops - 1)) + 20 * noise_frac / spl)
    tol = 1e-9 * v_range if noise_frac == 0 else 4 * noise_frac * v_range
    step = 2 * v_range / spl  # the sampled extreme can miss a vertex by up to one step
    assert info.v_min == pytest.approx(v_min, abs=tol + step)
    assert info.v_max == pytest.approx(v_min + v_range, abs=tol + step)
    assert info.offset_v == pytest.approx(v_min + v_range / 2, abs=tol + step)
    assert info.n_loops in (loops - 1, loops)
    assert info.duty == pytest.approx(0.5, abs=0.02)
    # direction: the true slope sign, except within a couple of samples of a turning point
    true_dir = np.where(((np.arange(v.size) + phase * spl) / spl) % 1.0 < 0.5, 1, -1)
    near = np.zeros(v.size, dtype=bool)
    for i in info.turning_indices:
        near[max(0, i - 3) : i + 4] = True
    assert np.all(info.direction[~near] == true_dir[~near])


def test_exact_triangle_turning_points_and_loops() -> None:
    t, v = _triangle(3, 2048, -40, 120, 0.5)
    info = infer_scan(t, v)
    assert info.turning_indices.tolist() == [0, 1024, 2048, 3072, 4096, 5120, 6144]
    assert info.turning_kinds.tolist() == [-1, 1, -1, 1, -1, 1, -1]
    assert (info.v_min, info.v_max, info.n_loops) == (-40.0, 120.0, 3)
    assert info.frequency_hz == pytest.approx(0.5, rel=1e-12)
    assert info.direction[0] == 1 and info.direction[1024] == -1 and info.direction[1023] == 1
    assert info.range_v == 160.0 and info.offset_v == 40.0


def test_asymmetric_triangle_duty() -> None:
    k = np.arange(4 * 1000 + 1)
    ph = (k / 1000) % 1
    v = 100 * np.where(ph < 0.8, ph / 0.8, (1 - ph) / 0.2)
    info = infer_scan(k / 1000.0, v)
    assert info.kind == "triangle" and info.duty == pytest.approx(0.8, abs=1e-3)
    assert info.frequency_hz == pytest.approx(1.0, rel=1e-9)


@pytest.mark.parametrize(
    ("make", "kind"),
    [
        (lambda t: 40 + 80 * np.sin(2 * np.pi * 0.5 * t), "sine"),
        (lambda t: 3.0 * t, "ramp"),
        (lambda t: np.full(t.size, 7.0), "constant"),
        (lambda t: np.cumsum(np.random.default_rng(1).normal(size=t.size)), "arbitrary"),
        (lambda t: np.tanh(2 * (_triangle(3, 1000, -40, 120, 0.5)[1][: t.size] - 40) / 80), "periodic"),
        (lambda t: _triangle(3, 1000, -40, 120, 0.5)[1][: t.size] * np.where(t > 4, 0.5, 1.0), "arbitrary"),
        (lambda t: _triangle(3, 1000, -40, 120, 0.5)[1][: t.size] + np.where(t > 4, 30.0, 0.0), "arbitrary"),
    ],
)
def test_non_triangles_are_classified(make: object, kind: str) -> None:
    t = np.arange(3001) / 500.0
    info = infer_scan(t, make(t))  # type: ignore[operator]
    assert info.kind == kind, info.reason
    assert not info.is_scan
    assert info.reason


def test_real_sine_recording_is_a_sine() -> None:
    path = Path(__file__).resolve().parents[1] / "piezod/data/real/pi-p885/identification.csv"
    if not path.exists():
        pytest.skip("vendored PI P-885 data not present")
    (exp,) = read_experiments([path])
    info = exp.scan()
    assert info.kind == "sine" and info.frequency_hz == pytest.approx(1.0, rel=1e-3)
    assert isinstance(exp, Experiment)


def test_parse_speed_is_vectorised() -> None:
    """100k rows parse through the numpy path (no per-row Python work beyond a comma count)."""
    n = 100_000
    t = np.arange(n) * 1e-4
    body = "\n".join(f"{a:.4f},{a * 3:.4f},{a * 0.2:.4f}" for a in t.tolist())
    rec = parse_recording(f"{HEADER}\n{body}\n", path="mem.csv")
    assert len(rec) == n and rec.line_numbers is not None and rec.line_numbers[-1] == n + 1


@pytest.mark.slow
def test_read_write_speed_against_loadtxt(tmp_path: Path) -> None:
    """Benchmark: reading / writing 200k rows, as a ratio to plain ``np.loadtxt`` / ``np.savetxt``."""
    import time

    n = 200_000
    rng = np.random.default_rng(0)
    rec = Recording(
        t_s=np.arange(n, dtype=np.float64) * 1e-4,
        voltage_v=rng.uniform(-200, 200, n),
        position_um=rng.normal(0, 10, n),
        axis=np.full(n, "x"),
        experiment=np.repeat(["a", "b"], n // 2),
    )
    p = tmp_path / "big.csv"
    t0 = time.perf_counter()
    write_recording(p, rec)
    t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    back = read_recording(p)
    t_read = time.perf_counter() - t0
    plain = tmp_path / "plain.csv"
    t0 = time.perf_counter()
    np.savetxt(plain, np.column_stack([rec.t_s, rec.voltage_v, rec.position_um]), delimiter=",")
    t_savetxt = time.perf_counter() - t0
    t0 = time.perf_counter()
    np.loadtxt(plain, delimiter=",")
    t_loadtxt = time.perf_counter() - t0
    print(
        f"\n200k rows x 5 columns: read {t_read:.3f} s ({t_read / t_loadtxt:.2f} x np.loadtxt of 3 numeric "
        f"columns, {t_loadtxt:.3f} s), write {t_write:.3f} s ({t_write / t_savetxt:.2f} x np.savetxt, "
        f"{t_savetxt:.3f} s)"
    )
    assert len(back) == n


def test_a_gap_in_t_splits_the_experiment_and_is_not_interpolated(tmp_path: Path) -> None:
    from piezod.recording import split_experiments

    t = np.concatenate((np.arange(0.0, 1.0, 0.01), 2.0 + np.arange(0.0, 1.0, 0.01)))
    v = np.sin(2 * np.pi * t)
    rec = Recording(t_s=t, voltage_v=v, position_um=0.1 * v, path=str(tmp_path / "gap.csv"))
    parts = split_experiments(rec)
    assert [e.label for e in parts] == ["gap#1", "gap#2"]
    assert [len(e) for e in parts] == [100, 100]
    assert parts[1].t_s[0] == pytest.approx(2.0)
    assert float(parts[1].metadata["gap_before_s"]) == pytest.approx(1.01)
    assert parts[1].metadata["split_from"] == "gap"
    # Jitter of the sample clock is not a gap.
    jitter = np.cumsum(np.random.default_rng(0).uniform(0.009, 0.011, 300))
    assert len(split_experiments(Recording(t_s=jitter, voltage_v=np.sin(jitter), position_um=jitter))) == 1
