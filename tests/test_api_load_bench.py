"""The daemon streams without underruns while its API is polled and a fit runs (short run)."""

from __future__ import annotations

import argparse

from piezod.service.bench import run_api_load_bench


def test_streaming_survives_api_polling_and_a_fit() -> None:
    args = argparse.Namespace(
        axes=3, rate_hz=20_000.0, seconds=6.0, api_clients=2, with_fit=True, config=None
    )
    result = run_api_load_bench(args)
    print(result)  # the numbers, for the log
    assert result["underruns"] == 0, result["faults"]
    assert result["crc_errors"] == 0
    assert result["engine_state"] == "scanning"
    assert result["api_requests"] > 50
    assert result["samples_read"] > 0.5 * result["samples_sent"]
