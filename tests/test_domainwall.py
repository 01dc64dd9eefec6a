"""The domain-wall law: walls relaxing towards an anhysteretic curve, its after-effect, exact inverse, fit."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from family_sessions import loop_session
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod import calibrate_family as cf
from piezod.config import FamilyModelConfig
from piezod.errors import ModelError
from piezod.model import kernels
from piezod.model.aftereffect import AfterEffect
from piezod.model.domainwall import (
    DomainWallParams,
    DomainWallState,
    domainwall_forward,
    domainwall_rest_state,
    domainwall_state_at,
    session_walls,
)
from piezod.model.family import (
    CreepSpectrum,
    FamilyParams,
    family_adopt_state,
    family_forward,
    family_hold,
    family_inverse,
    family_rest_state,
)

DT = 1e-4
LAW = DomainWallParams(0.42, 0.22, 30.0, 38.0, 90.0, 0.3)
RELAXING = AfterEffect(1.5, 20.0)


def _params(ae: AfterEffect | None = RELAXING, driver: str = "voltage") -> FamilyParams:
    spec = CreepSpectrum.log_spaced(1e-3, 1e3, 2, 0.006)
    return FamilyParams(LAW, spec, 50e-6, 0.01, driver, 0.2, ae)


def _step(p: float, h0: float, h1: float) -> tuple[float, float]:
    k, hb, a = LAW.pinning_v, LAW.centre_v, LAW.width_v
    p1, der, _ = kernels._dw_step(p, h0, kernels._dw_pan(h0, hb, a), h1, 1.0 / k, hb, a)
    return p1, der


def test_the_step_is_the_ode_and_its_derivative() -> None:
    """One step is the linear ODE ``dP/d|h| = (P_an - P) / k`` with ``P_an`` linear over it (to
    ``O(step^2)`` of the true curve: a fine run of steps converges to the same end), the walls stay
    pinned until the curve passes them, and the returned derivative is the step's own."""
    coarse, _ = _step(-20.0, 0.0, 40.0)
    fine, h = -20.0, 0.0
    for h1 in np.linspace(0.0, 40.0, 4001)[1:]:
        fine, _ = _step(fine, h, float(h1))
        h = float(h1)
    assert coarse == pytest.approx(fine, abs=0.05)
    # pinned: the curve at 10 V lies below walls at +20 V, so rising there does not move them
    assert _step(20.0, 0.0, 10.0) == (20.0, 0.0)
    for p0, h0, h1 in (
        (-20.0, 0.0, 40.0),
        (-25.0, 0.0, 30.0),
        (30.0, 60.0, 20.0),
        (0.0, 10.0, 80.0),
        (-9.0, 9.0, 9.01),
    ):
        _, der = _step(p0, h0, h1)
        eps = 1e-6
        num = (_step(p0, h0, h1 + eps)[0] - _step(p0, h0, h1 - eps)[0]) / (2 * eps)
        assert der == pytest.approx(num, rel=1e-5, abs=1e-8)
        assert 0.0 <= der <= 1.0


@pytest.mark.parametrize(
    ("ae", "driver"), [(AfterEffect(1.5, 20.0), "voltage"), (None, "voltage"), (None, "position")]
)
def test_the_inverse_is_exact_across_blocks(ae: AfterEffect | None, driver: str) -> None:
    """The compiled inverse reproduces the voltages that drove the forward model, in blocks of any
    length, with and without the after-effect (the count of samples carries over)."""
    params = _params(ae, driver)
    t = np.arange(40_000) * DT
    v = 50.0 + 60.0 * np.sin(2 * np.pi * 0.7 * t) * np.exp(-t / 3.0)
    rest = family_rest_state(params, 0.0)
    x, end = family_forward(params, v, DT, rest)
    state, out = rest, []
    for block in np.array_split(x, 17):
        u, state = family_inverse(params, block, DT, state)
        out.append(u)
    np.testing.assert_allclose(np.concatenate(out), v, atol=1e-9)
    assert state.relax_pending == end.relax_pending
    assert state.position_um == pytest.approx(end.position_um, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    step_v=st.floats(0.01, 8.0),
    g0=st.sampled_from([0.3, 3.0, math.inf]),
    tau_s=st.floats(1e-3, 1e3),
    alpha=st.floats(0.0, 0.85),
    pinning_v=st.floats(0.5, 200.0),
    splits=st.integers(1, 9),
)
def test_random_walks_through_the_inverse_are_exact(
    seed: int, step_v: float, g0: float, tau_s: float, alpha: float, pinning_v: float, splits: int
) -> None:
    """Random walks (steps up to 8 V a sample, reversals anywhere, any interaction and pinning, gaps
    far below and above ``g0``) through the forward model come back through the compiled inverse
    to 1e-8 V over blocks split anywhere, and the position rises with the voltage along every run."""
    law = DomainWallParams(0.4, 0.3, pinning_v, 30.0, 70.0, alpha)
    spec = CreepSpectrum.log_spaced(1e-3, 1e2, 1, 0.01)
    params = FamilyParams(law, spec, 0.0, 0.02, "voltage", 0.0, AfterEffect(g0, tau_s, 5e-4))
    rng = np.random.default_rng(seed)
    v = np.clip(40.0 + np.cumsum(rng.normal(0.0, step_v, 3000)), -20.0, 120.0)
    rest = family_rest_state(params, 40.0)
    x, _ = family_forward(params, v, DT, rest)
    state, out = rest, []
    for block in np.array_split(x, splits):
        u, state = family_inverse(params, block, DT, state)
        out.append(u)
    np.testing.assert_allclose(np.concatenate(out), v, atol=1e-8)
    xh, _, _ = domainwall_forward(law, v, domainwall_rest_state(law, 40.0))
    assert np.all(np.diff(xh) * np.diff(v) >= -1e-12)


def test_a_hold_is_the_forward_model_at_the_held_voltage() -> None:
    """The hold takes the relaxations that end in it as the forward model does: the same state."""
    params = _params()
    t = np.arange(20_000) * DT
    _, state = family_forward(params, 40.0 + 50.0 * np.sin(2 * np.pi * t), DT, family_rest_state(params))
    held = family_hold(params, 123_457, DT, state)
    _, stepped = family_forward(params, np.full(123_457, state.voltage_v), DT, state)
    assert held.position_um == pytest.approx(stepped.position_um, abs=1e-9)
    assert held.relax_pending == stepped.relax_pending
    assert isinstance(held.law, DomainWallState) and isinstance(stepped.law, DomainWallState)
    assert held.law.walls_v == pytest.approx(stepped.law.walls_v, abs=1e-9)
    # the walls relaxed towards the curve: the position crept
    assert abs(held.position_um - state.position_um) > 1e-3


def test_minor_loops_take_the_curves_local_slope_and_the_rest_state_sits_on_it() -> None:
    """Unlike a Duhem law of fixed saturation the branches bend towards a curve of the voltage:
    the same 20 V minor loop is steeper where the curve is (its centre) than in its tail; the rest
    state lies on the curve and an adopted state reaches its position."""
    law = DomainWallParams(0.1, 0.5, 10.0, 40.0, 40.0, 0.2)

    def minor_rise(centre: float) -> float:
        v = np.concatenate(
            [
                np.linspace(0.0, centre + 10.0, 500),
                np.tile(
                    np.r_[
                        np.linspace(centre + 10, centre - 10, 200), np.linspace(centre - 10, centre + 10, 200)
                    ],
                    3,
                ),
            ]
        )
        x, _, _ = domainwall_forward(law, v, domainwall_rest_state(law, 0.0))
        return float(x[-1] - x[-201])

    assert minor_rise(40.0) > 1.5 * minor_rise(100.0)
    rest = domainwall_rest_state(law, 25.0)
    assert rest.walls_v == pytest.approx(float(law.anhysteretic(rest.field_v)), abs=1e-9)
    at = domainwall_state_at(law, 25.0, rest.position_um + 1.0)
    assert at.position_um == pytest.approx(rest.position_um + 1.0, abs=1e-9)
    far = domainwall_state_at(law, 25.0, 1e3)  # beyond any branch: the nearest the walls can be
    assert float(law.anhysteretic(far.field_v)) - far.walls_v == pytest.approx(-law.pinning_v, abs=1e-6)
    params = FamilyParams(law, CreepSpectrum((1.0,), (0.02,)), 0.0, 0.0, "voltage", 0.3)
    target = family_rest_state(params, 25.0).position_um + 1.0
    assert family_adopt_state(params, 25.0, target).position_um == pytest.approx(target, abs=1e-9)


def test_the_after_effect_makes_the_loops_depend_on_the_rate() -> None:
    """With the walls' after-effect a slow loop is narrower than a fast one."""
    no_creep = CreepSpectrum((1.0,), (0.0,))

    def width(params: FamilyParams, freq_hz: float) -> float:
        per = round(1.0 / (freq_hz * DT))
        v = 50.0 - 50.0 * np.cos(2 * np.pi * freq_hz * np.arange(3 * per) * DT)
        x, _ = family_forward(params, v, DT, family_rest_state(params))
        grid = np.linspace(10.0, 90.0, 41)
        half = per // 2
        up = np.interp(grid, v[-per:][:half], x[-per:][:half])
        down = np.interp(grid, v[-per:][half:][::-1], x[-per:][half:][::-1])
        return float(np.max(down - up))

    relaxing = FamilyParams(LAW, no_creep, 0.0, 0.0, "voltage", 0.0, AfterEffect(1.5, 20.0))
    assert width(relaxing, 0.05) < 0.8 * width(relaxing, 5.0)
    plain = FamilyParams(LAW, no_creep, 0.0, 0.0, "voltage")
    assert width(plain, 0.05) == pytest.approx(width(plain, 5.0), rel=1e-3)


def test_the_fit_discretisation_follows_the_runtime_model() -> None:
    """The calibration's walls at a session's sparse samples (the voltage moving linearly in steps
    of the interval between them) match the runtime model's at every sample."""
    ae = AfterEffect(1.5, 3.0)
    t = np.arange(40_000) * DT
    v = 45.0 * np.sin(2 * np.pi * 0.5 * t) + 5.0 * np.sin(2 * np.pi * 3.1 * t)
    x_full, _, _ = domainwall_forward(LAW, v, domainwall_rest_state(LAW, 0.0), ae, DT, 0)
    idx = np.arange(4, v.size, 5)
    walls = session_walls(LAW, np.asarray(t[idx] + DT, np.float64), v[idx], 0.0, ae)
    x_sparse = LAW.b_um_per_v * v[idx] + LAW.w_um_per_v * walls
    assert float(np.max(np.abs(x_full[idx] - x_sparse))) < 2e-3 * float(np.ptp(x_full))


def test_the_law_is_written_and_read_back_and_bad_values_are_refused() -> None:
    """The config section carries the law and its after-effect; a missing or bad field is refused."""
    params = _params()
    section = cf.family_model_config(params)
    assert section.law == "domain-wall"
    back = section.params()
    assert (back.hysteresis, back.after_effect, back.creep_driver) == (LAW, params.after_effect, "voltage")
    fields = section.model_dump()
    with pytest.raises(ValueError, match="law domain-wall needs"):
        FamilyModelConfig(**{**fields, "dw_pinning_v": None})
    with pytest.raises(ValueError, match="interaction"):
        FamilyModelConfig(**{**fields, "dw_interaction": 0.95})
    with pytest.raises(ModelError, match="w_um_per_v"):
        DomainWallParams(0.4, -0.1, 30.0, 0.0, 50.0)
    with pytest.raises(ModelError, match="finite"):
        DomainWallParams(0.4, 0.1, math.nan, 0.0, 50.0)
    with pytest.raises(ModelError, match="voltage-driven creep"):
        FamilyParams(LAW, params.creep, creep_driver="position", after_effect=AfterEffect(1.0, 1.0))


def test_the_fit_finds_the_law_and_its_after_effect() -> None:
    """Self-consistency: on a session of the law with its after-effect the fit predicts the held-out
    loops as well as the truth does and far better than without the after-effect, and the choice
    tries the domain-wall law with it once a play law's after-effect is adopted."""
    truth = FamilyParams(
        LAW, CreepSpectrum((1.0, 100.0), (0.01, 0.02)), 0.0, 0.0, "voltage", 0.0, AfterEffect(1.5, 20.0)
    )
    data = loop_session(truth)
    train = cf.holdout_mask(data.n_experiments, 3)
    without = cf.fit_family(data, "domain-wall", train=train, creep_driver="voltage")
    fitted = cf.fit_family(data, "domain-wall", train=train, creep_driver="voltage", after_effect=True)
    assert fitted.params.after_effect is not None
    # the session's reconstruction (128 samples a loop, the pauses between the loops) is not the
    # stream the loops were simulated on: the truth itself predicts the held-out loops to this
    assert fitted.heldout_rms_um < 1.1 * cf.heldout_rms(data, truth, train)
    assert fitted.heldout_rms_um < 0.3 * without.heldout_rms_um
    choice = cf.choose_model(
        data, laws=("generalised-play", "domain-wall"), creep_drivers=("voltage",), holdout_every=3, plays=8
    )
    assert choice.chosen == "family/domain-wall/after-effect/voltage-creep", choice.table()
    assert choice.fit is not None and choice.fit.params.law == "domain-wall"


def test_the_compiled_loop_equals_the_python_reference() -> None:
    """The inverse with voltage creep and the after-effect, compiled and as plain Python: the same
    voltages, creep elements and state."""
    from piezod.model.dynamic import discretise

    params = _params()
    dt = 1e-4
    t = np.arange(3000) * dt
    v = 40.0 + 50.0 * np.sin(2 * np.pi * 3.0 * t)
    rest = family_rest_state(params, 0.0)
    x, _ = family_forward(params, v, dt, rest)
    disc = discretise(params.creep, dt)
    w, s = params.creep.weights, params.law_slope_um_per_v
    ob0 = disc.one_minus_b0
    creep = (s * float(w @ (1.0 - ob0)), s * (w * disc.a), s * float(w @ ob0), disc.a, ob0)
    ae = params.after_effect
    assert ae is not None and isinstance(rest.law, DomainWallState)
    xc = x - params.offset_um  # the stiffness map is small: the loops only need the same input
    results = []
    loops: tuple[Callable[..., Any], ...] = (kernels.dw_loop, kernels._dw_loop)
    for fn in loops:
        e = rest.creep_um.copy()
        out = np.empty(xc.size)
        end = fn(
            xc,
            LAW.b_um_per_v,
            LAW.w_um_per_v,
            *LAW.shape,
            *creep,
            e,
            rest.law.walls_v,
            rest.law.field_v,
            out,
            ae.every(dt),
            0,
            ae.factor(ae.every(dt) * dt),
            ae.fluctuation_v,
        )
        results.append((out, e, end))
    (o1, e1, end1), (o2, e2, end2) = results
    np.testing.assert_allclose(o1, o2, rtol=0, atol=1e-10)
    np.testing.assert_allclose(e1, e2, rtol=0, atol=1e-12)
    assert end1 == pytest.approx(end2, abs=1e-10)


def test_the_recordings_path_tries_the_law_with_its_after_effect_and_writes_it() -> None:
    """``piezod calibrate FILES`` (the held-out comparison of recordings): once the after-effect is
    adopted on the generalised play law, the domain-wall law with its after-effect is tried, named
    best when it predicts better, and the written refit holds it."""
    from family_sessions import loop_experiments

    from piezod.cli.calibrate import _written
    from piezod.family_heldout import compare_family

    truth = FamilyParams(LAW, CreepSpectrum((1.0, 100.0), (0.01, 0.02)), 0.0, 0.0, "voltage", 0.0, RELAXING)
    exps = loop_experiments(truth)
    family = compare_family(
        exps,
        laws=("generalised-play", "domain-wall"),
        creep_drivers=("voltage",),
        plays=8,
        parts=False,
        after_effect=True,
    )
    best = family.best
    assert best is not None and best.name == "family/domain-wall/after-effect/voltage-creep", family.table()
    written = _written(exps, best, family.skip_s, refit=True)
    assert best.params is not None and written.after_effect == best.params.after_effect
    assert written.law == "domain-wall"
