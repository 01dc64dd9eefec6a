"""Calibration of the model family on a simulated stage of other physics, and the held-out choice of model."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from hil_sim.session import calibration_plan, run_session
from hil_sim.stage import EffectsConfig, StageConfig, resolve_stage
from piezod.calibrate_dynamic import DynamicCalibrationData, prepare_dynamic
from piezod.calibrate_family import (
    CHOICE_TIE_FRACTION,
    GP_NODES,
    MAX_GP_NODES,
    MAX_PLAYS,
    choose_model,
    family_model_config,
    fit_family,
    heldout_rms,
    holdout_mask,
    member_name,
    member_nodes,
    parse_member,
    session_positions,
    solve_linear,
)
from piezod.model.boucwen import BoucWenParams
from piezod.model.gplay import GeneralisedPlayParams
from piezod.model.play import PlayParams
from piezod.simulator import session_experiments


@cache
def _preset_session(
    preset: str,
    ranges_v: tuple[float, ...],
    frequencies_hz: tuple[float, ...],
    offsets_v: tuple[float, ...],
    rate_hz: float,
    limits_v: tuple[float, float],
) -> DynamicCalibrationData:
    """A short session (2 ranges x 2 rates x 2 offsets, 2 loops each) on a preset's ``x`` axis."""
    path = resolve_stage(preset)
    assert path is not None
    stage = StageConfig.from_file(path)
    plan = calibration_plan(ranges_v, frequencies_hz, offsets_v, cycles=2, settle_cycles=1)
    sess = run_session(stage, plan, sample_rate_hz=rate_hz, axis="x", voltage_limits_v=limits_v)
    return prepare_dynamic(session_experiments(sess), max_samples_per_loop=128, slew_rate_v_per_s=2000.0)


def _pi_session() -> DynamicCalibrationData:
    return _preset_session("pi-stage", (150.0, 300.0), (0.5, 2.0), (-20.0, 20.0), 1000.0, (-230.0, 230.0))


def test_a_play_law_is_chosen_on_a_prandtl_ishlinskii_stage_by_held_out_data() -> None:
    """pi-stage (play hysteresis): the held-out data pick a play law, predicted to a few nm.

    The generalised play law contains the Prandtl-Ishlinskii law (a density that does not depend
    on the relay centre), so either may win by a nm; Coleman-Hodgdon may not.

    On this short session (8 experiments of 2 loops at 1 kS/s) the two creep drivers are within
    a few nm of each other once the fit converges (joint Gauss-Newton); the full frame separates
    them (docs/model-family.md, section 6.1).
    """
    data = _pi_session()
    choice = choose_model(data, alpha_per_v=3e-3, holdout_every=3)
    assert choice.chosen.startswith(("family/prandtl-ishlinskii", "family/generalised-play")), choice.table()
    assert choice.holdout and all(i % 3 == 2 for i in choice.holdout)
    held = choice.heldout_rms_um
    assert held["family/prandtl-ishlinskii"] < 0.1 * held["family/coleman-hodgdon"]
    assert held["family/generalised-play"] < 0.1 * held["family/coleman-hodgdon"]
    # the sensor noise is 2 nm rms; the fitted law leaves a few nm over ~35 um loops
    assert held[choice.chosen] < 0.01
    fit = choice.fit
    assert fit is not None and isinstance(fit.params.hysteresis, PlayParams | GeneralisedPlayParams)
    section = family_model_config(fit.params)
    assert section.creep_driver == fit.params.creep_driver
    again = section.params()
    np.testing.assert_allclose(session_positions(data, again), session_positions(data, fit.params), atol=1e-4)
    assert "<- chosen" in choice.table()


def test_solve_linear_bounds_fixed_columns_and_ridge() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 3))
    y = a @ np.array([1.0, -2.0, 0.5]) + rng.normal(0, 1e-3, 200)
    c, rms = solve_linear(a, y)
    np.testing.assert_allclose(c, [1.0, -2.0, 0.5], atol=1e-3)
    assert rms < 2e-3
    c, _ = solve_linear(a, y, lower=np.zeros(3))
    assert np.all(c >= 0) and c[1] == pytest.approx(0.0, abs=1e-9)
    c, _ = solve_linear(a, y, lower=np.array([-np.inf, 0.0, -np.inf]), upper=np.array([np.inf, 0.0, np.inf]))
    assert c[1] == 0.0
    c_ridge, _ = solve_linear(a, y, ridge=100.0 * np.eye(3))
    assert np.linalg.norm(c_ridge) < np.linalg.norm([1.0, -2.0, 0.5])


def test_holdout_mask_spreads_the_held_out_experiments() -> None:
    assert holdout_mask(8, 4).tolist() == [True, True, True, False, True, True, True, False]
    assert holdout_mask(1, 4).tolist() == [True]


def test_the_streaming_choice_adopts_either_creep_driver_and_can_still_block_one() -> None:
    """The daemon's calibration adopts whichever creep driver predicts the held-out data best (the
    voltage-driven inverse is compiled, within the streaming budget of ``piezod bench inverse``); a
    driver left out of the adoptable ones is scored, shown and marked not adopted."""
    from piezod.model.family import CREEP_DRIVERS, REALTIME_CREEP_DRIVERS

    assert set(REALTIME_CREEP_DRIVERS) == set(CREEP_DRIVERS)
    data = _pi_session()
    choice = choose_model(data, alpha_per_v=3e-3, holdout_every=3, adoptable_drivers=REALTIME_CREEP_DRIVERS)
    held = choice.heldout_rms_um
    base = {k: v for k, v in held.items() if "-plays" not in k and "-nodes" not in k}
    # among the members at the default resolution: the best held-out RMS, or a member with fewer
    # coefficients within CHOICE_TIE_FRACTION of it (here Prandtl-Ishlinskii, the stage's own law,
    # within 1 % of the generalised play law)
    law, driver, plays = parse_member(choice.chosen) or ("", "", None)
    picked = member_name(law, driver)
    best = min(base.values())
    assert base[picked] <= best * (1.0 + CHOICE_TIE_FRACTION), choice.table()
    size = {k: f.n - f.dof for k, f in choice.fits.items() if k in base}
    assert all(size[k] >= size[picked] for k in size if base[k] <= best * (1.0 + CHOICE_TIE_FRACTION))
    # a finer play or centre grid replaces it only by predicting better by more than the tie fraction
    if plays is not None or member_nodes(choice.chosen) != GP_NODES:
        assert held[choice.chosen] < base[picked] * (1.0 - CHOICE_TIE_FRACTION)
    assert "not adopted" not in choice.table()
    assert choice.fit is not None
    driver = choice.fit.params.creep_driver
    other = next(d for d in CREEP_DRIVERS if d != driver)
    blocked = choose_model(data, alpha_per_v=3e-3, holdout_every=3, adoptable_drivers=(other,))
    assert {k for k in blocked.heldout_rms_um if "-plays" not in k and "-nodes" not in k} == set(base)
    assert blocked.fit is None or blocked.fit.params.creep_driver == other
    assert blocked.chosen != choice.chosen and "not adopted" in blocked.table()


def test_preisach_stage_picks_the_generalised_play_law() -> None:
    """preisach-stage (a relay density that depends on the relay centre; held out until the
    generalised play law was developed against it): the held-out data pick the generalised play
    law, which represents such a density, over the Prandtl-Ishlinskii law, which cannot."""
    data = _preset_session(
        "preisach-stage", (150.0, 300.0), (0.5, 2.0), (-20.0, 20.0), 1000.0, (-230.0, 230.0)
    )
    choice = choose_model(data, alpha_per_v=3e-3, holdout_every=3, creep_drivers=("position",))
    member = parse_member(choice.chosen)
    assert member is not None and member[:2] == ("generalised-play", "position"), choice.table()
    fit = choice.fit
    assert fit is not None and isinstance(fit.params.hysteresis, GeneralisedPlayParams)
    # plays the fit leaves at zero density are dropped
    h = fit.params.hysteresis
    assert 0 < len(h.thresholds_v) <= MAX_PLAYS and all(max(row) > 0 for row in h.density)
    held = choice.heldout_rms_um
    assert held["family/generalised-play"] < 0.5 * held["family/prandtl-ishlinskii"]
    assert held["family/prandtl-ishlinskii"] < 0.5 * held["family/coleman-hodgdon"]
    # the centre grid was refined once, and kept only when it predicts better by the tie fraction
    plays = member[2]
    coarse = member_name("generalised-play", "position", plays)
    finer = member_name("generalised-play", "position", plays, 2 * GP_NODES - 1)
    assert coarse in held and finer in held, choice.table()
    nodes = member_nodes(choice.chosen)
    assert len(h.nodes_v) == nodes <= MAX_GP_NODES
    if nodes == GP_NODES:
        assert not held[finer] < held[coarse] * (1.0 - CHOICE_TIE_FRACTION)
    else:
        assert held[finer] < held[coarse] * (1.0 - CHOICE_TIE_FRACTION)


def test_member_names_carry_a_refined_play_and_centre_grid() -> None:
    """A member's name says its play count and centre nodes when the choice refined them."""
    name = member_name("generalised-play", "voltage", 64, 5)
    assert name == "family/generalised-play/64-plays/5-nodes/voltage-creep"
    assert parse_member(name) == ("generalised-play", "voltage", 64)
    assert member_nodes(name) == 5
    assert member_nodes("family/generalised-play") == GP_NODES
    assert member_name("prandtl-ishlinskii", "position") == "family/prandtl-ishlinskii"


def test_joint_gauss_newton_finishes_what_the_alternation_leaves(monkeypatch: pytest.MonkeyPatch) -> None:
    """The alternation alone stalls in the valley where play weights and creep weights trade off."""
    import functools

    import piezod.calibrate_family as cf

    data = _pi_session()
    train = holdout_mask(data.n_experiments, 3)
    r = cf.default_thresholds(data, 16, "uniform")
    refined = cf.fit_family(data, "prandtl-ishlinskii", train=train, thresholds=r)
    monkeypatch.setattr(cf, "_alternate", functools.partial(cf._alternate, refine=False))
    alternated = cf.fit_family(data, "prandtl-ishlinskii", train=train, thresholds=r)
    assert refined.rms_um < 0.3 * alternated.rms_um
    assert refined.heldout_rms_um < 0.3 * alternated.heldout_rms_um
    assert refined.heldout_rms_um < 0.006


def _boucwen_session() -> DynamicCalibrationData:
    return _preset_session(
        "boucwen-stage", (150.0, 300.0), (0.5, 2.0), (-20.0, 20.0), 1000.0, (-200.0, 200.0)
    )


def test_the_duhem_law_is_chosen_on_a_bouc_wen_stage_by_held_out_data() -> None:
    """boucwen-stage (developed against): the fitted Bouc-Wen/Duhem law predicts held-out
    experiments far better than any play law or Coleman-Hodgdon, and is chosen."""
    data = _boucwen_session()
    choice = choose_model(data, laws=("prandtl-ishlinskii", "coleman-hodgdon", "bouc-wen"), holdout_every=3)
    assert choice.chosen.startswith("family/bouc-wen"), choice.table()
    held = choice.heldout_rms_um
    best_other = min(v for k, v in held.items() if not k.startswith("family/bouc-wen"))
    assert held[choice.chosen] < 0.5 * best_other, choice.table()
    fit = choice.fit
    assert fit is not None
    section = family_model_config(fit.params)
    assert section.law == "bouc-wen"
    np.testing.assert_allclose(
        session_positions(data, section.params()), session_positions(data, fit.params), atol=1e-6
    )


def _knee_session() -> DynamicCalibrationData:
    return _preset_session(
        "knee-holdout-stage", (80.0, 160.0), (0.5, 2.0), (50.0, 70.0), 5000.0, (-30.0, 150.0)
    )


def test_the_bouc_wen_fit_finds_a_sharp_knee_exponent() -> None:
    """knee-holdout-stage (held out until session 6, developed against since): a Bouc-Wen law of
    exponent 2 on a unipolar stack. The fit's exponent search finds n = 2 and predicts the held-out
    experiments several times better than the law of exponent 1 (its rate search alone found a
    valley 25 % off in the rate, which costs 30x the RMS on this knee)."""
    data = _knee_session()
    train = holdout_mask(data.n_experiments, 3)
    fit = fit_family(data, "bouc-wen", train=train)
    h = fit.params.hysteresis
    assert isinstance(h, BoucWenParams)
    assert h.exponent == 2.0
    held = fit.heldout_rms_um
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("piezod.calibrate_family.BW_EXPONENTS", (1.0,))
        first = fit_family(data, "bouc-wen", train=train).heldout_rms_um
    assert held < 0.25 * first, (held, first)
    assert held < 0.010


def _bouc_wen_position_creep_session() -> DynamicCalibrationData:
    """The x axis of bwtube-holdout-stage without its effects and amplifier pole: a Bouc-Wen law
    (softening loops) with position-driven power-law creep -- the family's own structure -- and
    2 nm of sensor noise."""
    path = resolve_stage("bwtube-holdout-stage")
    assert path is not None
    stage = StageConfig.from_file(path).model_copy(
        update={"effects": EffectsConfig(), "amplifier_lag_s": 0.0}
    )
    plan = calibration_plan((100.0, 300.0), (0.5, 2.0), (-40.0, 40.0), cycles=2, settle_cycles=1)
    sess = run_session(stage, plan, sample_rate_hz=2000.0, axis="x", voltage_limits_v=(-200.0, 200.0))
    return prepare_dynamic(session_experiments(sess), max_samples_per_loop=128, slew_rate_v_per_s=2000.0)


def test_a_bouc_wen_law_with_position_creep_is_fitted_to_the_noise(monkeypatch: pytest.MonkeyPatch) -> None:
    """The rate search scores every candidate by the converged fit when the creep follows the
    position (bilinear in the law and the weights). Scored after 4 alternations, the search
    settled 2.5 % off the true rates at 3x the noise (on the full frame of this stage 6.2 nm
    against 2.0 nm at the true rates), and the voltage-creep member won on a position-creep stage."""
    data = _bouc_wen_position_creep_session()
    train = holdout_mask(data.n_experiments, 4)
    position = fit_family(data, "bouc-wen", train=train)
    voltage = fit_family(data, "bouc-wen", train=train, creep_driver="voltage")
    h = position.params.hysteresis
    assert isinstance(h, BoucWenParams)
    # the true law: k_same = beta + gamma = 0.006, k_back = beta - gamma = 0.014 (1/V)
    np.testing.assert_allclose(
        [h.k_up_same, h.k_up_back, h.k_down_same, h.k_down_back], [0.006, 0.014, 0.006, 0.014], rtol=0.05
    )
    assert position.heldout_rms_um < 0.003, position.heldout_rms_um  # the noise: 0.002 um
    assert position.heldout_rms_um < voltage.heldout_rms_um
    # scored unconverged (as before), the same search leaves the rates and the fit worse
    import piezod.calibrate_family as cf

    plain = cf._alternate

    def unconverged(*args: object, **kwargs: object) -> object:
        if kwargs.get("max_iter") == 4:
            kwargs["refine"] = False
        return plain(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(cf, "_alternate", unconverged)
    old = fit_family(data, "bouc-wen", train=train)
    assert old.heldout_rms_um > 1.2 * position.heldout_rms_um
    print(
        f"held-out RMS: converged scores {position.heldout_rms_um * 1e3:.2f} nm, "
        f"4-alternation scores {old.heldout_rms_um * 1e3:.2f} nm, "
        f"voltage creep {voltage.heldout_rms_um * 1e3:.2f} nm"
    )


def _stack_session() -> DynamicCalibrationData:
    return _preset_session(
        "stack-holdout-stage", (60.0, 120.0), (0.5, 2.0), (40.0, 55.0), 1000.0, (-20.0, 120.0)
    )


@pytest.mark.parametrize("driver", ["position", "voltage"])
def test_the_generalised_play_law_fits_at_least_as_well_as_its_special_case(driver: str) -> None:
    """stack-holdout-stage (a unipolar Preisach stack with narrow relays; developed against since
    session 7): the generalised play law contains the Prandtl-Ishlinskii law, so it may not train
    worse. Until session 7 it did (31 against 19.6 nm on the full frame): with voltage-driven creep
    the alternation let the law's slope at 0 V run away and diverged, and ``lsq_linear``'s
    trust-region method stopped short of the minimum on its near-collinear columns."""
    data = _stack_session()
    train = holdout_mask(data.n_experiments, 3)
    pi = fit_family(data, "prandtl-ishlinskii", train=train, creep_driver=driver)
    gp = fit_family(data, "generalised-play", train=train, creep_driver=driver)
    assert gp.rms_um <= 1.02 * pi.rms_um
    assert gp.heldout_rms_um < 0.5 * pi.heldout_rms_um
    # sensor noise 2 nm rms; the law the stage follows is in the fitted family
    assert gp.heldout_rms_um < 0.008


def test_one_sensors_offsets_are_an_offset_and_a_drift_of_the_whole_session() -> None:
    """The calibration frame is read by one sensor: its fits eliminate one offset and one drift
    rate for the session (``offset_time_s``), not an offset per experiment, so a model position
    that is off in one scan and not in another is a misfit, not a free offset."""
    import dataclasses

    from piezod.stagecal import one_sensor_offsets

    data = _pi_session()
    one = one_sensor_offsets(data)
    assert np.all(one.groups() == 0)
    t = one.offset_time_s
    assert t is not None and t.size == data.position_um.size
    # the experiments' times follow the session's clock
    firsts = t[data.starts]
    assert np.all(np.diff(firsts) > 0)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(t.size, 3))
    # an offset and a drift are eliminated, nothing else
    trend = 0.7 - 0.02 * t
    np.testing.assert_allclose(one.centred(a + trend[:, None]), one.centred(a), atol=1e-9)
    np.testing.assert_allclose(one.centred(one.centred(a)), one.centred(a), atol=1e-9)
    np.testing.assert_allclose(one.centred(a[:, 1]), one.centred(a)[:, 1], atol=1e-12)
    step = np.where(np.arange(t.size) >= data.starts[1], 0.5, 0.0)
    assert np.linalg.norm(one.centred(step)) > 0.1 * np.linalg.norm(step - step.mean())
    # per experiment (the default) a step between experiments is an offset, eliminated
    np.testing.assert_allclose(data.centred(step), 0.0, atol=1e-12)
    # the fit's degrees of freedom count the two
    rows = np.ones(t.size, dtype=bool)
    assert one.n_offset_parameters(rows) == 2
    assert data.n_offset_parameters(rows) == data.n_experiments
    assert dataclasses.replace(one, offset_time_s=None).n_offset_parameters(rows) == 1


def test_history_experiments_run_the_model_but_are_neither_fitted_nor_scored() -> None:
    """The refit on a frame played again (piezod.stagecal.refresh_member) runs the model through
    the first frame without fitting or scoring it: readings there, however wrong, change nothing;
    the same readings fitted do."""
    import dataclasses

    data = _pi_session()
    n = data.n_experiments
    before = np.arange(n) < 2
    train = holdout_mask(n) & ~before
    spoilt_y = data.position_um.copy()
    rows = slice(int(data.starts[0]), int(data.starts[1] + data.counts[1]))
    spoilt_y[rows] += np.linspace(0.0, 5.0, spoilt_y[rows].size)
    spoilt = dataclasses.replace(data, position_um=spoilt_y)
    options = {"plays": 16, "creep_driver": "voltage", "train": train}
    clean = fit_family(data, "prandtl-ishlinskii", history=before, **options)
    same = fit_family(spoilt, "prandtl-ishlinskii", history=before, **options)
    assert same.heldout_rms_um == pytest.approx(clean.heldout_rms_um, rel=1e-9)
    assert same.rms_um == pytest.approx(clean.rms_um, rel=1e-9)
    # without the history mask the experiments left out of the training are scored
    scored = fit_family(data, "prandtl-ishlinskii", **options).heldout_residuals_um.size
    assert same.heldout_residuals_um.size == clean.heldout_residuals_um.size < scored
    fitted = fit_family(spoilt, "prandtl-ishlinskii", **{**options, "train": holdout_mask(n)})
    assert fitted.rms_um > 3.0 * clean.rms_um


def test_a_member_fitted_elsewhere_is_scored_as_a_fit_scores_its_own() -> None:
    """heldout_rms scores given parameters on a session's held-out experiments as fit_family
    scores its own (the refit on a frame played again is set against the first frame's member
    so): the fit's own parameters score its held-out RMS; a member 2 % more sensitive, as a stage
    that warmed would be seen by the model fitted before, scores worse."""
    import dataclasses

    data = _pi_session()
    n = data.n_experiments
    before = np.arange(n) < 2
    train = holdout_mask(n) & ~before
    fit = fit_family(
        data, "prandtl-ishlinskii", plays=16, creep_driver="voltage", train=train, history=before
    )
    assert heldout_rms(data, fit.params, train, history=before) == pytest.approx(fit.heldout_rms_um, rel=1e-9)
    law = fit.params.hysteresis
    assert isinstance(law, PlayParams)
    warmed = dataclasses.replace(
        fit.params, hysteresis=dataclasses.replace(law, b_um_per_v=1.02 * law.b_um_per_v)
    )
    assert heldout_rms(data, warmed, train, history=before) > 3.0 * fit.heldout_rms_um
    # nothing held out: nothing to score
    assert np.isnan(heldout_rms(data, fit.params, np.ones(n, dtype=bool)))
