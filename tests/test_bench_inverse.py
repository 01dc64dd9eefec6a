"""``piezod bench``: the inverse benchmark (numbers, no wall-clock assertions) and the CLI."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from piezod.bench import run_inverse_bench, scipy_voltage, triangular_targets
from piezod.cli import main
from piezod.model.inverse import ThesisInverse
from piezod.model.thesis import MEDIUM_TUBE_TABLE_3_3

KEYS = {"ns_per_sample", "scipy_ns_per_sample", "ratio", "max_roundtrip_error_rel"}


def test_bench_reports_keys_and_accuracy() -> None:
    r = run_inverse_bench(block_samples=1024, blocks=12, repeats=1, half_line_samples=1500)
    assert set(r) >= KEYS
    assert r["samples"] == 12 * 1024
    assert r["ns_per_sample"] > 0 and r["scipy_ns_per_sample"] > 0
    assert r["ratio"] == pytest.approx(r["ns_per_sample"] / r["scipy_ns_per_sample"])
    assert r["max_roundtrip_error_rel"] <= 1e-9
    assert r["max_voltage_difference_v"] <= 1e-9
    assert r["ode_max_roundtrip_error_rel"] <= 1e-9
    # the richest runtime model (voltage creep + every part) is timed and exact; its ns are the bench's
    assert r["richest_model"] in r["models"] and r["richest_ns_per_sample"] > 0
    assert r["richest_ns_per_sample"] == pytest.approx(
        r["models"][r["richest_model"]]["ns_per_sample"] + r["resonance_ns_per_sample"]
    )
    assert r["richest_ratio"] == pytest.approx(r["richest_ns_per_sample"] / r["scipy_ns_per_sample"])
    assert all(m["max_roundtrip_error_rel"] <= 1e-9 for m in r["models"].values())


def test_scipy_baseline_is_the_same_inverse() -> None:
    inv = ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, 20.0, 0.5, v_limits=(-230.0, 230.0))
    x, d = triangular_targets(inv, 3000, 700)
    assert set(np.unique(d)) == {-1, 1}
    np.testing.assert_allclose(scipy_voltage(inv, x, d), inv.voltage(x, d), atol=1e-9)


def test_cli_bench_inverse_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    assert main(["bench", "inverse", "--blocks", "2", "--repeats", "1", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert set(data) >= KEYS
    text = capsys.readouterr().out
    assert "ns/sample" in text and "richest runtime model" in text


def test_cli_bench_stream_not_available_yet(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "piezod.link.bench", None)
    assert main(["bench", "stream"]) == 2
    assert "stream bench is not available yet" in capsys.readouterr().err


def test_cli_bench_stream_calls_the_link_bench(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen: dict[str, Any] = {}

    def run_stream_bench(args: Any) -> dict[str, Any]:
        seen.update(axes=args.axes, rate_hz=args.rate_hz, seconds=args.seconds)
        return {**seen, "samples_sent": 10, "samples_read": 10, "underruns": 0, "crc_errors": 0}

    fake = types.ModuleType("piezod.link.bench")
    fake.run_stream_bench = run_stream_bench  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "piezod.link.bench", fake)
    out = tmp_path / "s.json"
    argv = ["bench", "stream", "--axes", "2", "--rate-hz", "5000", "--seconds", "0.5", "--json", str(out)]
    assert main(argv) == 0
    assert seen == {"axes": 2, "rate_hz": 5000.0, "seconds": 0.5}
    assert json.loads(out.read_text())["underruns"] == 0


def test_benchmark_inverse_block(benchmark: Any) -> None:
    """pytest-benchmark: one 4096-sample block of the full inverse (disabled by default)."""
    inv = ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, 30.0, 1.0, v_limits=(-230.0, 230.0))
    x = inv.to_absolute(np.linspace(0.0, inv.range_um, 4096))
    v = benchmark(inv.voltage, x, 1)
    assert np.max(np.abs(inv.position(v, 1) - x)) <= 1e-9 * inv.range_um
