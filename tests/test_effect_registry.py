"""The effect registry (piezod.model.registry) and the simulator's own implementations agree."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.effects import EFFECTS, SPEC_MODELS, random_effect
from hil_sim.stage import StageAxisConfig
from piezod.model.registry import EFFECT_IDS, REGISTRY, is_physical, spec


def test_every_simulated_effect_is_registered_with_the_same_parameter_names() -> None:
    for name, model in SPEC_MODELS.items():
        entry = spec(name)
        assert entry.primary.name == model.primary
        numeric = {f for f, info in model.model_fields.items() if info.annotation not in (str,) and f != "at"}
        numeric -= {"tau_min_s", "tau_max_s", "per_decade", "drive", "time_constant_s"}
        assert numeric <= set(entry.names), (name, numeric - set(entry.names))
    assert set(EFFECTS) <= set(EFFECT_IDS)
    assert "asymmetry_pct" in StageAxisConfig.model_fields
    assert spec("asymmetry").primary.name == "asymmetry_pct"


@pytest.mark.parametrize("name", list(SPEC_MODELS))
def test_realistic_draws_of_the_simulator_lie_in_the_registry(name: str) -> None:
    rng = np.random.default_rng(3)
    entry = REGISTRY[name]
    for _ in range(50):
        effect = random_effect(name, rng)
        for field, value in effect.model_dump(exclude_none=True).items():
            if not isinstance(value, float) or field not in entry.names or value == 0.0:
                continue
            p = entry.param(field)
            lo, hi = p.realistic
            assert lo <= abs(value) <= hi * (1 + 1e-12), (name, field, value, p.realistic)
            assert is_physical(name, field, value)


def test_bounds_are_ordered_and_realistic_inside_physical() -> None:
    for entry in REGISTRY.values():
        assert entry.sources
        for p in entry.params:
            lo, hi = p.physical
            assert lo < hi
            rlo, rhi = p.realistic
            assert 0 <= rlo < rhi
            assert rhi <= max(abs(lo), abs(hi))
    with pytest.raises(KeyError, match="unknown effect"):
        spec("bogus")
    with pytest.raises(KeyError, match="no parameter"):
        spec("drift").param("bogus")
