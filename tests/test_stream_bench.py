"""``piezod bench stream``: the streaming benchmark against a fresh simulator over a pty."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from piezod.bench import RICHEST_MODEL
from piezod.cli import main
from piezod.config import default_sim_config_path, load_config
from piezod.errors import ConfigError
from piezod.link.bench import bench_config, run_stream_bench, triangle_for

pytest.importorskip("hil_sim.server", reason="hil_sim.server (the simulator process) is missing")

REQUIRED = ("axes", "rate_hz", "seconds", "samples_sent", "samples_read", "underruns", "crc_errors")


def test_bench_config_and_waveform_stay_inside_the_limits() -> None:
    config = load_config(default_sim_config_path())
    two = bench_config(config, 2, 50_000)
    assert list(two.axes) == ["x", "y"] and two.sample_rate_hz == 50_000
    with pytest.raises(ConfigError, match="only 3 axes"):
        bench_config(config, 4, 1000)
    src = triangle_for(two, 50_000)
    v = src.next_block(100_000)  # two seconds: whole periods
    for row, name in zip(v, ("x", "y"), strict=True):
        ax = two.axes[name]  # type: ignore[index]
        assert ax.voltage_min_v < row.min() < row.max() < ax.voltage_max_v
        assert np.max(np.abs(np.diff(row))) * 50_000 <= ax.slew_rate_v_per_s
        assert row.max() - row.min() > 0.75 * (ax.voltage_max_v - ax.voltage_min_v)


def test_bench_stream_cli_writes_the_contract_keys(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    status = main(
        ["bench", "stream", "--axes", "3", "--rate-hz", "50000", "--seconds", "0.8", "--json", str(out)]
    )
    assert status == 0
    result = json.loads(out.read_text())
    assert set(REQUIRED) <= set(result)
    assert (result["axes"], result["rate_hz"], result["seconds"]) == (3, 50_000.0, 0.8)
    assert result["underruns"] == 0 and result["crc_errors"] == 0 and result["unexplained_loss"] == 0
    assert result["samples_sent"] == result["samples_read"] >= 0.6 * 50_000
    assert result["min_lead_ms"] > 0 and result["lead_target_ms"] > 0
    assert result["samples_frames_sent"] > 0 and result["host_cpu_pct"] > 0


def test_bench_stream_against_the_c_firmware(tmp_path: Path, firmware_host_binary: Path) -> None:
    from hil_sim.firmware import spawn_firmware

    out = tmp_path / "bench.json"
    with spawn_firmware(firmware_host_binary) as fw:
        args = ["bench", "stream", "--port", fw.path, "--rate-hz", "50000", "--seconds", "0.8"]
        assert main([*args, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["simulator"] == f"the board at {fw.path}"
    assert result["underruns"] == 0 and result["crc_errors"] == 0 and result["unexplained_loss"] == 0
    assert result["samples_sent"] == result["samples_played"] == result["samples_read"] >= 0.6 * 50_000


def test_bench_stream_rejects_bad_arguments() -> None:
    with pytest.raises(ConfigError, match="--axes"):
        run_stream_bench(argparse.Namespace(axes=5, rate_hz=1000.0, seconds=1.0))
    with pytest.raises(ConfigError, match="--seconds"):
        run_stream_bench(argparse.Namespace(axes=1, rate_hz=1000.0, seconds=0.0))


@pytest.mark.soak
def test_bench_stream_target_3_axes_100k_20s() -> None:
    """The target: ``piezod bench stream --axes 3 --rate-hz 100000 --seconds 20`` loses nothing."""
    result = run_stream_bench(argparse.Namespace(axes=3, rate_hz=100_000.0, seconds=20.0))
    print(json.dumps(result, indent=2))
    assert result["underruns"] == 0 and result["unexplained_loss"] == 0
    assert result["samples_sent"] == result["samples_read"] >= 19 * 100_000


def test_the_richest_model_runs_in_the_streaming_path_without_loss(tmp_path: Path) -> None:
    """Short version of the soak target below: every axis's voltages come from the model's inverse."""
    out = tmp_path / "bench.json"
    model = RICHEST_MODEL
    args = ["bench", "stream", "--axes", "3", "--rate-hz", "50000", "--seconds", "0.8", "--model", model]
    assert main([*args, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["model"] == model and result["model_ns_per_sample"] > 0
    assert result["underruns"] == 0 and result["unexplained_loss"] == 0
    assert result["samples_sent"] == result["samples_read"] >= 0.6 * 50_000
    with pytest.raises(ConfigError, match="--model 'nope'"):
        run_stream_bench(argparse.Namespace(axes=1, rate_hz=1000.0, seconds=0.5, model="nope"))


@pytest.mark.soak
def test_bench_stream_target_3_axes_100k_20s_with_the_richest_model() -> None:
    """``piezod bench stream --axes 3 --rate-hz 100000 --seconds 20 --model <richest>`` loses nothing."""
    model = RICHEST_MODEL
    result = run_stream_bench(argparse.Namespace(axes=3, rate_hz=100_000.0, seconds=20.0, model=model))
    print(json.dumps(result, indent=2))
    assert result["underruns"] == 0 and result["unexplained_loss"] == 0
    assert result["samples_sent"] == result["samples_read"] >= 19 * 100_000
