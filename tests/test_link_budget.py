"""The link budget: cadences derived from the link's capacity and the sample rate (piezod.link.budget)."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_proto import Samples, encode
from piezod.config import default_sim_config_path, load_config
from piezod.errors import ConfigError
from piezod.link.budget import USABLE_FRACTION, host_bytes_per_s, plan_link_budget, wire_bytes
from piezod.link.plan import LinkSettings


def test_wire_size_is_the_codecs() -> None:
    for n in (1, 7, 100, 500):
        frame = encode(Samples(0, np.full((n, 3), 0x0101, dtype=np.int16)), 1)
        assert len(frame) <= wire_bytes(12 + 6 * n) <= len(frame) + 1


def test_a_fast_link_keeps_the_defaults() -> None:
    b = plan_link_budget(None, 20_000.0, 3, lead_s=0.15)
    assert (b.status_period_ms, b.frame_samples) == (10, 100) and b.usable_bytes_per_s is None


@pytest.mark.parametrize(("capacity", "shared", "rate"), [(11_520, False, 1000.0), (6000, True, 100.0)])
def test_a_slow_link_is_never_asked_for_more_than_it_can(capacity: float, shared: bool, rate: float) -> None:
    b = plan_link_budget(capacity, rate, 3, lead_s=0.5, shared=shared)
    usable = USABLE_FRACTION * capacity / (2 if shared else 1)
    assert b.host_to_board_bytes_per_s <= usable and b.board_to_host_bytes_per_s <= usable
    assert b.status_period_ms > 10 and b.frame_samples > round(rate * 0.005)
    assert host_bytes_per_s(rate, 3, max(1, round(rate * 0.005))) > b.host_to_board_bytes_per_s
    assert "B/s" in b.describe()


def test_a_stream_the_link_cannot_carry_is_refused_with_the_figures() -> None:
    with pytest.raises(ConfigError, match=r"11,520 B/s .* 5000 S/s on 3 channels needs host->board"):
        plan_link_budget(11_520, 5000.0, 3, lead_s=0.15)


def test_the_scanner_yaml_sets_the_capacity() -> None:
    cfg = load_config(default_sim_config_path())
    svc = cfg.service.model_copy(update={"link_bytes_per_s": 11_520.0})
    s = LinkSettings.from_config(cfg.model_copy(update={"sample_rate_hz": 1000.0, "service": svc}))
    assert s.budget is not None and s.status_period_ms == s.budget.status_period_ms > 10
    assert s.frame_samples == s.budget.frame_samples
    assert LinkSettings.from_config(cfg).budget is None
