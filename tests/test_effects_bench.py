"""Per hil_sim effect: online correction by the baseline and the extended model (piezod bench effects)."""

from __future__ import annotations

import math
from functools import cache
from typing import Any

import pytest

from piezod.effects_bench import (
    TARGET_FRACTION,
    format_table,
    realistic_specs,
    run_case,
    run_effects_bench,
    score,
)
from piezod.model.parts import PART_EFFECTS
from piezod.model.registry import REGISTRY


def test_realistic_specs_sit_inside_the_registry_ranges() -> None:
    for effect in ("stiffness", "resonance", "delay"):
        for text in realistic_specs(effect):
            head, value = text.split("=")
            name = head.split(".", 1)[1]
            lo, hi = REGISTRY[effect].param(name).realistic
            assert lo <= float(value) <= hi


def test_score_compares_what_is_left_above_the_floor() -> None:
    floor = {"nonlinearity_pct": 0.01, "length_error_pct": 0.002}
    case: dict[str, Any] = {
        "baseline": {"worst": {"nonlinearity_pct": 0.1, "length_error_pct": 0.05}},
        "extended": {"worst": {"nonlinearity_pct": 0.02, "length_error_pct": 0.01}},
    }
    s = score(case, floor, resolution_pct=0.01)
    assert s["left"]["nonlinearity_pct"]["baseline"] == pytest.approx(0.09)
    assert s["left"]["length_error_pct"]["fraction"] == pytest.approx(0.008 / 0.048)
    assert s["met"] and not s["below_resolution"]
    case["extended"]["worst"]["length_error_pct"] = 0.04
    assert not score(case, floor, resolution_pct=0.01)["met"]
    quiet: dict[str, Any] = {"baseline": {"worst": floor}, "extended": {"worst": floor}}
    s = score(quiet, floor, resolution_pct=0.01)
    assert s["below_resolution"] and not s["met"] and math.isnan(s["left"]["nonlinearity_pct"]["fraction"])


@cache
def _floor() -> dict[str, Any]:
    return run_case([], loops=2)


def test_stiffness_is_found_adopted_and_corrected_online() -> None:
    """Short version of the table: stiffness (realistic) on the built-in stage, reduced frame."""
    case = run_case(realistic_specs("stiffness"), loops=2, audit_effects=("drift", "stiffness"))
    assert "stiffness" in case["findings"]
    assert any(a.startswith("stiffness:") for a in case["adoption"]["adopted"])
    s = score(case, _floor()["baseline"]["worst"], resolution_pct=0.01)
    left = s["left"]["nonlinearity_pct"]
    assert left["baseline"] > 0.05  # the effect's curvature, uncorrected
    assert left["extended"] <= TARGET_FRACTION * left["baseline"], s
    assert s["met"], s


@pytest.mark.slow
def test_every_effect_with_a_runtime_part_is_corrected() -> None:
    """The full table (docs/model-family.md, section 8): ``piezod bench effects``."""
    result = run_effects_bench()
    print(format_table(result))
    for row in result["rows"]:
        if row["effect"] in PART_EFFECTS:
            assert row["met"] or row["below_resolution"], row["effect"]
