"""Physical plausibility bounds: a fit outside them is reported as implausible, never as the cause."""

from __future__ import annotations

import pytest

from piezod.audit.bounds import BOUNDS, implausible
from piezod.audit.candidates import EFFECTS, Scales, make_candidate

SC = Scales(
    t_ref_s=50.0,
    session_s=100.0,
    f_ref_hz=1.0,
    x_scale_um=40.0,
    min_period_s=0.2,
    max_rate_hz=2000.0,
    max_line_hz=5.0,
    has_negative_voltage=True,
)


def test_every_effect_has_bounds_on_its_public_parameters() -> None:
    for effect in EFFECTS:
        names = set(make_candidate(effect, "ode").names) | set(make_candidate(effect, "thesis").names)
        for b in BOUNDS[effect]:
            assert b.param in names, (effect, b.param)
            assert b.lo < b.hi and b.source


@pytest.mark.parametrize(
    ("effect", "params"),
    [
        ("drift", {"rate_nm_per_s": 1.5}),
        ("thermal", {"rate_pct_per_hour": -2.5}),
        ("stiffness", {"sensitivity_pct_per_um": 0.15}),
        ("polarity", {"negative_sensitivity_pct": -10.0}),
        ("resonance", {"f0_hz": 300.0, "q": 30.0}),
        ("delay", {"delay_s": 1e-3, "lag_time_constant_s": 0.0}),
        ("saturation", {"x_sat_um": 60.0}),
        ("creep", {"creep_pct_per_decade": 5.0}),
    ],
)
def test_realistic_magnitudes_are_plausible(effect: str, params: dict[str, float]) -> None:
    assert implausible(effect, params, SC) == ""


@pytest.mark.parametrize(
    ("effect", "params"),
    [
        ("drift", {"rate_nm_per_s": -1.4e4}),
        ("thermal", {"rate_pct_per_hour": -973.0}),
        ("stiffness", {"sensitivity_pct_per_um": -6.9e10}),
        ("resonance", {"f0_hz": 0.22, "q": 3.0}),
        ("resonance", {"f0_hz": 20.0, "q": 3.0}),  # 4th harmonic of the 5 Hz scan
        ("creep", {"creep_pct_per_decade": 35.0}),
        ("saturation", {"x_sat_um": 10.0}),
        ("delay", {"delay_s": 0.0, "lag_time_constant_s": 0.05}),
        ("drift", {"rate_nm_per_s": float("nan")}),
    ],
)
def test_impossible_magnitudes_are_implausible(effect: str, params: dict[str, float]) -> None:
    why = implausible(effect, params, SC)
    assert why.startswith("implausible:"), why


def test_audit_and_effect_registry_agree_where_they_name_the_same_parameter() -> None:
    from piezod.audit.bounds import REGISTRY_SHARED
    from piezod.model.registry import REGISTRY

    # Bounded relative to the data's excursion, where the registry's absolute interval
    # presupposes a lab stage's stroke (docstring of piezod.audit.bounds).
    relative = {("stiffness", "sensitivity_pct_per_um"), ("saturation", "x_sat_um")}
    for effect in EFFECTS:
        if effect not in REGISTRY:
            continue
        names = set(make_candidate(effect, "ode").names) | set(make_candidate(effect, "thesis").names)
        for p in REGISTRY[effect].params:
            if p.name not in names or (effect, p.name) in relative:
                continue
            assert (effect, p.name) in REGISTRY_SHARED, (effect, p.name)
            (b,) = [b for b in BOUNDS[effect] if b.param == p.name]
            assert (b.lo, b.hi) == p.physical
            assert implausible(effect, {p.name: p.physical[1] * 1.01 + 1e-9}, SC).startswith("implausible")
