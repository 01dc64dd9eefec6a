"""The audit finds what was hidden, and only that (seeded sessions; the sweeps are ``slow``)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_audit_sessions import EFFECT_IDS, sim_session, thesis_session

from piezod.audit import result_json, run_audit
from piezod.audit.standins import preset_session
from piezod.audit.synthetic import frame_plan, hidden_session
from piezod.extensions import adoption_audit_options
from piezod.recording import Experiment, read_experiments, split_experiments
from piezod.synth import random_params

DATA = Path(__file__).resolve().parents[1] / "piezod" / "data" / "real" / "pi-p885"

#: Mid-range magnitudes (random_effect's ranges) for the fast, deterministic tests.
MID: dict[str, dict[str, Any]] = {
    "drift": {"rate_nm_per_s": 1.5},
    "thermal": {"rate_pct_per_hour": 2.5},
    "stiffness": {"sensitivity_pct_per_um": 0.08},
    "polarity": {"negative_sensitivity_pct": -6.0},
    "resonance": {"f0_hz": 150.0, "q": 12.0},  # resolved by the small frame (fastest ~700 samples/s)
    "delay": {"delay_s": 4e-4},
    "saturation": {"x_sat_um": 100.0},
    "creep": {"pct_per_decade": 4.0, "law": "k"},
}


def small_session(effects: dict[str, dict[str, Any]], seed: int) -> list[Experiment]:
    """A small thesis-model frame: 3 ranges x 3 frequencies (0.05-5 Hz) + 3 references, 512 samples/loop."""
    rng = np.random.default_rng(seed)
    params = random_params(rng)
    plan = frame_plan(
        rng, ranges_v=(120.0, 260.0, 400.0), n_frequencies=3, frequency_hz=(0.05, 5.0), n_references=3
    )
    return split_experiments(hidden_session(params, plan, effects, samples_per_loop=512, seed=rng).recording)


def test_clean_thesis_stage_gives_none() -> None:
    result = run_audit(small_session({}, 0))
    assert result.cause == "none"
    assert result.findings == ()
    assert result.structure_ratio < 1.1
    assert all(not c.eligible for c in result.candidates)


@pytest.mark.parametrize("effect", EFFECT_IDS)
def test_a_hidden_effect_is_named(effect: str) -> None:
    result = run_audit(small_session({effect: MID[effect]}, 3))
    assert result.cause == effect
    assert [f.effect for f in result.findings] == [effect]
    finding = result.findings[0]
    assert finding.gain > 1.01 and finding.heldout_rms_after_um < finding.heldout_rms_before_um
    assert finding.evidence


def test_two_hidden_effects_are_both_found_with_their_magnitudes() -> None:
    result = run_audit(small_session({"drift": MID["drift"], "stiffness": MID["stiffness"]}, 4))
    assert result.cause == "stiffness"  # the stronger one
    assert sorted(f.effect for f in result.findings) == ["drift", "stiffness"]
    got = {f.effect: f.params for f in result.findings}
    assert got["stiffness"]["sensitivity_pct_per_um"] == pytest.approx(0.08, rel=0.05)
    assert got["drift"]["rate_nm_per_s"] == pytest.approx(1.5, rel=0.2)


def test_a_creep_factor_fitted_to_zero_leaves_the_baseline_determined() -> None:
    # A stage whose loops grow with the line rate (less motion the slower it scans: not the
    # creep factor (3.5)'s direction) puts A1 at 0, where tau has no effect. That is (3.8)
    # without its creep term, a determined model: the polarity is named and sized. Before, the
    # zero column of tau read as a collapsed baseline and the audit named nothing
    # (the fifteenth held-out stage, docs/model-family.md 6.2n).
    rng = np.random.default_rng(41)
    params = dataclasses.replace(random_params(rng), a1=0.0)
    plan = frame_plan(
        rng, ranges_v=(120.0, 260.0, 400.0), n_frequencies=3, frequency_hz=(0.05, 5.0), n_references=3
    )
    hidden = {
        "polarity": {"negative_sensitivity_pct": 4.0},
        "creep": {"pct_per_decade": -1.0, "law": "motion"},
    }
    session = hidden_session(params, plan, hidden, samples_per_loop=512, seed=rng)
    result = run_audit(split_experiments(session.recording))
    assert result.degeneracy is not None and not result.degeneracy.degenerate
    assert result.degeneracy.absent == ("tau_s", "a1")
    assert any("tau_s, a1 left out" in n for n in result.notes)
    assert result_json(result)["degeneracy"]["absent"] == ["tau_s", "a1"]
    assert result.cause == "polarity"
    found = {f.effect: f.params for f in result.findings}
    assert found["polarity"]["negative_sensitivity_pct"] == pytest.approx(4.0, rel=0.1)
    assert "creep" in found


def test_a_term_left_out_and_a_parameter_on_a_bound_read_the_bound_alike() -> None:
    # One tolerance for both: an A1 the degeneracy check would call "on its bound" (a residue of
    # the bounded solver, 1e-7) is a creep term left out, not a bound that undetermines the model.
    from piezod.audit.baseline import ThesisBase, at_bound

    base = ThesisBase(a2_scale=1.0)
    z = base.to_internal(dataclasses.replace(random_params(np.random.default_rng(3)), a1=0.2, tau_s=0.5))
    assert base.absent(z) == ()
    for k, value in ((4, 1e-7), (3, math.log(1e-3) + 1e-7), (3, math.log(1e5) - 1e-6)):
        near = z.copy()
        near[k] = value
        assert base.absent(near) == (3, 4)
    assert at_bound(1e-7, 0.0) and not at_bound(1e-5, 0.0)
    assert at_bound(math.log(1e5) - 1e-5, math.log(1e5)) and not at_bound(math.log(1e5) - 1e-4, math.log(1e5))


def test_findings_on_an_undetermined_baseline_are_withheld_for_the_adoption_to_try() -> None:
    # No loop opening (alpha and b on bounds: undetermined), a sensor ripple, and a ceramic 5 %
    # more sensitive below 0 V. The polarity is eligible on held-out data but not named on the
    # undetermined model; it is kept as withheld, in a form the adoption takes.
    from piezod.extensions import adopt_findings

    rng = np.random.default_rng(5)
    t = np.arange(0.0, 20.0, 0.005)
    v = 60.0 * np.sin(2 * np.pi * 0.5 * t) * (0.5 + 0.5 * t / 20.0)
    seen = np.where(v < 0, 1.05 * v, v)
    x = 0.1 * seen + 0.05 * np.sin(2 * np.pi * 0.1 * seen) + rng.normal(0.0, 0.002, t.size)
    result = run_audit([Experiment("no loop", None, t, v, x)])
    assert result.cause == "undetermined" and result.findings == ()
    assert [f.effect for f in result.withheld] == ["polarity"]
    assert "not named on the undetermined model: polarity" in result.notes
    doc = result_json(result)
    assert doc["findings"] == [] and [f["effect"] for f in doc["withheld"]] == ["polarity"]
    adoption = adopt_findings(doc["withheld"])
    assert adoption.effects["polarity"]["negative_sensitivity_pct"] == pytest.approx(5.0, rel=0.05)


def test_structure_that_no_candidate_explains_is_unexplained() -> None:
    # A sensor nonlinearity none of the candidates has: a ripple with the position (4 um period).
    exps = small_session({}, 6)
    bent = [
        Experiment(
            e.label,
            e.axis,
            e.t_s,
            e.voltage_v,
            e.position_um + 0.03 * np.sin(2 * np.pi * e.position_um / 4.0),
        )
        for e in exps
    ]
    result = run_audit(bent)
    assert result.cause == "unexplained"
    assert result.structure_ratio > 1.15


def test_p885_real_stack_names_a_cause_with_a_held_out_gain() -> None:
    ident = read_experiments([DATA / "identification.csv"])
    val = read_experiments([DATA / "validation.csv"])
    result = run_audit(ident, val)
    assert result.base_kind == "ode"
    assert result.cause == "delay"
    first = result.findings[0]
    assert first.gain >= 1.2
    lag = first.params["delay_s"] + first.params["lag_time_constant_s"]
    # The documented one-sample (5 ms) sensor delay is aligned from the recordings' metadata; the
    # ODE baseline still needs a lag to widen its loop, which the model family does not confirm
    # (piezod audit drops it: tests/test_audit_realdata.py).
    assert 0.005 <= lag <= 0.03
    assert any("documented sensor delay" in n for n in result.notes)


def test_a_single_recording_is_split_in_time() -> None:
    rng = np.random.default_rng(7)
    params = random_params(rng)
    plan = frame_plan(rng, ranges_v=(200.0,), n_frequencies=1, frequency_hz=(1.0, 2.0), n_references=0)
    (exp,) = split_experiments(hidden_session(params, plan, {}, samples_per_loop=512, seed=rng).recording)
    many = Experiment(exp.label, None, exp.t_s, exp.voltage_v, exp.position_um)
    result = run_audit([many])
    assert "blocked split" in result.heldout_method
    assert result.cause in ("none", "unexplained")


# --------------------------------------------------------------------------------------------- sweeps


def _sweep(
    kind: str, n: int, base_seed: int, log: Path | None = None
) -> tuple[dict[str, Counter[str]], list[float], list[dict[str, Any]]]:
    matrix: dict[str, Counter[str]] = {}
    seconds: list[float] = []
    rows: list[dict[str, Any]] = []
    for hidden in ("none", *EFFECT_IDS):
        matrix[hidden] = Counter()
        for k in range(n):
            seed = base_seed + 100 * (EFFECT_IDS.index(hidden) + 1 if hidden != "none" else 0) + k
            effects = [] if hidden == "none" else [hidden]
            make = thesis_session if kind == "thesis" else sim_session
            exps, fx = make(effects, seed)
            t0 = time.process_time()
            result = run_audit(exps)
            seconds.append(time.process_time() - t0)
            matrix[hidden][result.cause] += 1
            rows.append(
                {
                    "hidden": hidden,
                    "seed": seed,
                    "effects": fx,
                    "cause": result.cause,
                    "findings": [f.effect for f in result.findings],
                    "cpu_s": seconds[-1],
                }
            )
            if log is not None:
                with log.open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps(rows[-1]) + "\n")
    return matrix, seconds, rows


def _print_matrix(title: str, matrix: dict[str, Counter[str]], seconds: list[float]) -> None:
    causes = ["none", *EFFECT_IDS, "unexplained"]
    print(f"\n{title}: rows hidden, columns cause")
    print(f"{'':>11} " + " ".join(f"{c[:6]:>6}" for c in causes))
    for hidden, row in matrix.items():
        print(f"{hidden:>11} " + " ".join(f"{row.get(c, 0):6d}" for c in causes))
    print(f"cpu seconds per audit: median {np.median(seconds):.1f}, max {np.max(seconds):.1f}")


def _log_path(name: str) -> Path | None:
    """``AUDIT_SWEEP_LOG`` (a directory): one JSON line per audit is appended to ``<dir>/<name>.jsonl``."""
    d = os.environ.get("AUDIT_SWEEP_LOG")
    return Path(d) / f"{name}.jsonl" if d else None


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_thesis_stage_confusion_matrix() -> None:
    """10 thesis-model sessions per hidden effect (random magnitude and sign) and 10 clean ones."""
    n = int(os.environ.get("AUDIT_SWEEP_N", "10"))
    matrix, seconds, _ = _sweep("thesis", n, 5000, _log_path("thesis"))
    _print_matrix("thesis-model stage", matrix, seconds)
    for hidden, row in matrix.items():
        assert row[hidden] >= 0.9 * n, (hidden, dict(row))
    assert max(seconds) <= 60.0


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_simulated_stage_finds_the_hidden_effect() -> None:
    """Sessions of hil_sim's stage (ODE + log creep): the hidden effect is among the findings.

    The simulated stage creeps with a spread of relaxation times that (3.8) does not describe,
    so ``creep`` is part of its clean state: a clean session gives ``creep`` (or ``none``), and
    a hidden effect must be found as well (``creep`` and ``drift`` may accompany it: the creep
    operator of the audit approximates the stage's).
    """
    n = int(os.environ.get("AUDIT_SIM_N", "3"))
    matrix, seconds, rows = _sweep("sim", n, 7000, _log_path("sim"))
    _print_matrix("simulated stage (hil_sim)", matrix, seconds)
    for row in rows:
        allowed = {"creep", "drift"}
        if row["hidden"] == "none":
            assert row["cause"] in ("none", "creep"), row
            assert set(row["findings"]) <= allowed, row
        else:
            assert row["hidden"] in row["findings"], row
            assert set(row["findings"]) <= allowed | {row["hidden"]}, row


def test_candidates_that_change_nothing_gain_one_within_their_error() -> None:
    # Clean data: every candidate's best fit is (nearly) the baseline itself, so its honest
    # held-out gain must be 1 within its standard error, and none may be eligible.
    result = run_audit(small_session({}, 11))
    assert result.options.refit_cv  # the honest estimate is the default
    tested = [c for c in result.candidates if c.fit is not None]
    assert len(tested) >= 6
    for c in tested:
        assert np.isfinite(c.gain_se) and c.gain_se >= 0.0, c.effect
        assert abs(c.gain - 1.0) <= 3.0 * c.gain_se + 2e-3, (c.effect, c.gain, c.gain_se)
        assert not c.eligible


def test_gain_standard_error_is_a_block_jackknife() -> None:
    from piezod.audit.fitting import HeldOut, gain_with_se

    rng = np.random.default_rng(1)
    before = rng.normal(0.0, 2.0, 5000)
    rows = np.ones(5000, dtype=bool)
    same = HeldOut(float(np.sqrt(np.mean(before**2))), before, rows)
    g, se = gain_with_se(same, same)
    assert g == pytest.approx(1.0) and se == pytest.approx(0.0, abs=1e-12)
    after = before / 2.0 + rng.normal(0.0, 0.1, 5000)
    half = HeldOut(float(np.sqrt(np.mean(after**2))), after, rows)
    g, se = gain_with_se(same, half)
    assert g == pytest.approx(2.0, rel=0.02)
    assert 0.0 < se < 0.05


def test_creep_in_the_baseline_lets_the_audit_size_a_thermal_drift() -> None:
    """The adoption audit's ODE baseline carries the creep (``base_effects``): on a preset frame of
    the built-in stage with a 3 %/h sensitivity drift the ODE alone leaves the creep's structure
    (20x the noise) and names nothing; with the creep in the baseline the drift is named, sized
    within 25 %, and the creep itself is never a finding."""
    exps = preset_session("stage", ("thermal=3",), seed=2)
    ode = dataclasses.replace(adoption_audit_options(), base="ode")
    without = run_audit(exps, options=dataclasses.replace(ode, base_effects=()))
    assert without.cause == "unexplained"
    result = run_audit(exps, options=ode)
    assert result.base_fit.model.effects == ("creep",)
    assert any("baseline: + creep" in n for n in result.notes)
    assert result.cause == "thermal"
    assert "creep" not in [f.effect for f in result.findings]
    assert result.findings[0].params["rate_pct_per_hour"] == pytest.approx(3.0, rel=0.25)
