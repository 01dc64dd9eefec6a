"""Unit tests of the audit's building blocks: filters, ODE, baselines, projection, fits, held-out error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter, lsim
from test_audit_sessions import thesis_session

from piezod.audit import data as audit_data
from piezod.audit.baseline import (
    OdeBase,
    _ode_experiment,
    geometry,
    ode_positions,
    thesis_start,
)
from piezod.audit.candidates import (
    EFFECTS,
    AuditModel,
    _relaxation_weights,
    _relaxations,
    make_candidate,
)
from piezod.audit.decide import _scales
from piezod.audit.dynamics import (
    _resonance_tf,
    _resonance_tf_expm,
    first_order_lag,
    lag_coefficients,
    pure_delay,
    resonance,
)
from piezod.audit.fitting import Problem, folds_of, heldout_cv
from piezod.audit.projection import Projector
from piezod.audit.residuals import noise_floor
from piezod.calibrate import model_positions, prepare
from piezod.fitstats import FitResult
from piezod.model.ode import HysteresisState, hysteresis_step
from piezod.model.params import HysteresisParams, ThesisParams


@pytest.mark.parametrize(
    ("f0", "q", "dt"), [(500.0, 10.0, 1e-4), (500.0, 0.5, 1e-4), (300.0, 30.0, 0.02), (1e4, 0.7, 1e-4)]
)
def test_resonance_closed_form_matches_the_matrix_exponential(f0: float, q: float, dt: float) -> None:
    b1, a1 = _resonance_tf(f0, q, dt)
    b2, a2 = _resonance_tf_expm(f0, q, dt)
    np.testing.assert_allclose(b1, b2, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(a1, a2, rtol=1e-9, atol=1e-13)
    assert sum(b1) / sum(a1) == pytest.approx(1.0, abs=1e-9)


def test_resonance_and_lag_are_exact_for_piecewise_linear_inputs() -> None:
    dt = 1e-4
    t = np.arange(4000) * dt
    x = np.interp(t, [0.0, 0.1, 0.25, 0.4], [0.0, 3.0, -1.0, 2.0])
    w0 = 2 * math.pi * 700.0
    q = 8.0
    ref_res = lsim(([w0**2], [1.0, w0 / q, w0**2]), x, t, interp=True)[1]
    np.testing.assert_allclose(resonance(x, dt, 700.0, q, 0), ref_res, atol=1e-9)
    tau = 3e-3
    ref_lag = lsim(([1.0], [tau, 1.0]), x, t, interp=True)[1]
    np.testing.assert_allclose(first_order_lag(x, dt, tau, 0), ref_lag, atol=1e-9)


def test_pure_delay_of_a_periodic_signal_wraps_around() -> None:
    x = np.tile(np.array([0.0, 1.0, 2.0, 3.0]), 3)
    out = pure_delay(x, 1.0, 1.5, 4)
    np.testing.assert_allclose(out[:4], [2.5, 1.5, 0.5, 1.5])
    ramp = np.arange(20.0)
    np.testing.assert_allclose(pure_delay(ramp, 0.5, 1.25, 0)[5:], ramp[5:] - 2.5)


def test_vectorised_ode_matches_the_exact_step() -> None:
    p = HysteresisParams(0.01, 0.1, 0.06)
    rng = np.random.default_rng(0)
    v1 = 100.0 * np.sin(2 * np.pi * np.arange(301) / 100.0)
    v2 = np.cumsum(rng.normal(0.0, 3.0, 250))
    v3 = np.concatenate([np.linspace(0, 50, 50), np.linspace(50, -20, 80)])
    v4 = 400.0 * np.sin(2 * np.pi * np.arange(2000) / 50.0)  # scaled travel > 600: chunked fallback
    parts = [v1, v2, v3, v4]
    v = np.concatenate(parts)
    counts = np.array([a.size for a in parts])
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    periods = np.array([100, 0, 0, 50])
    x, decay = ode_positions(p, v, starts, counts, periods)
    for i, part in enumerate(parts):
        sl = slice(int(starts[i]), int(starts[i] + counts[i]))
        xr, dr = _ode_experiment(p, part, int(periods[i]))
        np.testing.assert_allclose(x[sl], xr, atol=1e-8)
        np.testing.assert_allclose(decay[sl], dr, atol=1e-12)
    # The periodic start is the steady state: one more period changes nothing.
    x_next, _ = hysteresis_step(p, v1[1:101], HysteresisState(float(v1[0]), float(x[0])))
    assert x_next[-1] == pytest.approx(x[0], abs=1e-9)


def test_thesis_baseline_is_the_calibrate_model() -> None:
    exps, _ = thesis_session([], 1, small=True)
    base, z, _ = thesis_start(exps)
    data = audit_data.build(exps)
    geo = geometry(data, 0.0, 1.0)
    p = ThesisParams(**base.public(z))
    np.testing.assert_allclose(base.evaluate(z, geo), model_positions(prepare(exps), p), atol=1e-9)
    np.testing.assert_allclose(base.to_internal(p), z, rtol=1e-9, atol=1e-12)


def test_projector_is_the_per_segment_least_squares_fit() -> None:
    rng = np.random.default_rng(2)
    seg = np.repeat(np.arange(4), [30, 50, 20, 40])
    col = rng.normal(size=seg.size) * (seg != 2)  # absent on segment 2
    y = rng.normal(size=seg.size)
    out = Projector(seg, col[:, None])(y)
    for s in range(4):
        m = seg == s
        a = np.column_stack([np.ones(m.sum()), col[m]])
        coef, *_ = np.linalg.lstsq(a, y[m], rcond=None)
        np.testing.assert_allclose(out[m], y[m] - a @ coef, atol=1e-10)
    assert Projector(seg, col[:, None]).n_nuisance == 7
    np.testing.assert_allclose(Projector(seg)(y)[seg == 1], y[seg == 1] - y[seg == 1].mean())


def test_noise_floor_of_a_noisy_triangle_scan() -> None:
    rng = np.random.default_rng(3)
    k = np.arange(4096)
    tri = 20.0 * np.abs(((k / 512.0) % 2.0) - 1.0)
    est = noise_floor(tri + np.tanh(tri / 5.0) + rng.normal(0.0, 0.005, k.size))
    assert est == pytest.approx(0.005, rel=0.08)


def test_creep_relaxations_match_a_bank_of_filters() -> None:
    rng = np.random.default_rng(4)
    period = 500
    x = np.tile(5.0 * np.sin(2 * np.pi * np.arange(period) / period), 6) + 1.0
    dt = 1e-3
    taus = 10.0 ** np.arange(-3.5, 2.1, 0.5)
    z_prev = rng.normal(size=taus.size)
    for gap, per in ((0.0, 0), (0.3, period), (0.2, 0)):
        total, z_end = _relaxations(x, taus, z_prev, gap, per, _relaxation_weights(x.size, dt, taus))
        ref = np.zeros_like(x)
        for j, tau in enumerate(taus):
            if tau < 0.5 * dt:
                ref += x
                continue
            b, a = lag_coefficients(float(tau), dt)
            target = float(x[0])
            if per:
                # The periodic steady state: the fixed point of one period.
                y0, _ = lfilter(b, a, x[:per], zi=[b[1] * x[0]])
                target = float(y0[-1]) / -math.expm1(-per * dt / tau)
            z0 = target + (z_prev[j] - target) * math.exp(-gap / tau)
            y, _ = lfilter(b, a, x, zi=[z0 * (-a[1]) + b[1] * x[0]])
            ref += y
            assert z_end[j] == pytest.approx(y[-1], abs=1e-9)
        np.testing.assert_allclose(total, ref, atol=1e-8)


@pytest.fixture(scope="module")
def small_frame() -> tuple[AuditModel, object, object]:
    exps, _ = thesis_session([], 11, small=True)
    data = audit_data.build(exps)
    base, z, _ = thesis_start(exps)
    x0, _ = AuditModel(base, (), _scales(data, np.zeros(1))).evaluate(z, geometry(data, 0.0, 1.0))
    sc = _scales(data, x0)
    geo = geometry(data, sc.t_ref_s, sc.f_ref_hz)
    model = AuditModel(base, (), sc)
    fit = Problem(model, geo, data.fit_mask).fit(z)
    return model, geo, fit


@pytest.mark.parametrize("effect", EFFECTS)
def test_every_candidate_contains_the_baseline(effect: str, small_frame: tuple) -> None:  # type: ignore[type-arg]
    model, geo, fit = small_frame
    cand = make_candidate(effect, "thesis")
    ext = model.with_candidate(cand)
    x0, _ = model.evaluate(fit.p, geo)
    x1, _ = ext.evaluate(np.concatenate((fit.p, cand.neutral(model.scales))), geo)
    assert np.max(np.abs(x1 - x0)) < 1e-6


def test_baseline_fit_reaches_the_noise_on_clean_data(small_frame: tuple) -> None:  # type: ignore[type-arg]
    _, _, fit = small_frame
    assert fit.rms_um == pytest.approx(0.005, rel=0.1)


def test_the_audit_fit_is_the_shared_fit_result(small_frame: tuple) -> None:  # type: ignore[type-arg]
    """Projected residual, dof = n - (free parameters + nuisance terms), BIC from the shared type."""
    model, geo, fit = small_frame
    assert isinstance(fit, FitResult) and not fit.has_errors
    k = int(model.free().sum()) + Problem(model, geo, geo.data.fit_mask).n_nuisance(fit.p)
    assert fit.k == k == fit.n - fit.dof and fit.n == fit.residual.size
    assert fit.rss == pytest.approx(float(fit.residual @ fit.residual))
    assert fit.cost == pytest.approx(0.5 * fit.rss)
    assert fit.bic == pytest.approx(fit.n * math.log(fit.rss / fit.n) + k * math.log(fit.n))


def test_chord_cross_validation_agrees_with_refits() -> None:
    exps, _ = thesis_session(["stiffness"], 12, small=True)
    data = audit_data.build(exps)
    base, z, _ = thesis_start(exps)
    x0, _ = AuditModel(base, (), _scales(data, np.zeros(1))).evaluate(z, geometry(data, 0.0, 1.0))
    sc = _scales(data, x0)
    geo = geometry(data, sc.t_ref_s, sc.f_ref_hz)
    model = AuditModel(base, (), sc).with_candidate(make_candidate("stiffness", "thesis"))
    full = Problem(model, geo, data.fit_mask).fit(np.concatenate((z, [0.0])))
    folds = folds_of(data.n_segments, 4)
    fast = heldout_cv(model, geo, full, folds)
    exact = heldout_cv(model, geo, full, folds, refit=True)
    assert fast.rms_um == pytest.approx(exact.rms_um, rel=0.02)
    assert exact.rms_um >= full.rms_um * 0.98


def test_ode_baseline_start_and_fit_on_sines() -> None:
    p = HysteresisParams(0.004, 0.11, 0.07)
    rng = np.random.default_rng(5)
    from piezod.recording import Experiment

    exps = []
    t0 = 0.0
    for k, (amp, f) in enumerate([(150.0, 1.0), (80.0, 2.0), (200.0, 0.5)]):
        t = t0 + np.arange(2000) / 1000.0
        v = amp * np.sin(2 * np.pi * f * (t - t0))
        x, _ = hysteresis_step(p, v, HysteresisState(0.0, 0.0))
        exps.append(Experiment(f"sine{k}", None, t, v, x + rng.normal(0.0, 0.002, v.size) + k, path="mem"))
        t0 = float(t[-1]) + 1.0
    from piezod.audit.baseline import ode_start

    data = audit_data.build(exps, settle=True)
    base, z = ode_start(data)
    assert isinstance(base, OdeBase)
    sc = _scales(data, np.ones(1))
    geo = geometry(data, sc.t_ref_s, sc.f_ref_hz)
    fit = Problem(AuditModel(base, (), sc), geo, data.fit_mask).fit(z)
    assert fit.rms_um < 0.0025
    got = base.public(fit.p)
    assert got["alpha_per_v"] == pytest.approx(0.004, rel=0.05)
    assert got["b_um_per_v"] == pytest.approx(0.11, rel=0.05)


def test_the_rayleigh_note_speaks_only_when_the_branches_never_bend_over() -> None:
    from piezod.audit.degenerate import rayleigh_note

    bent = {"alpha_per_v": 0.01, "b_um_per_v": 0.2, "u_um_per_v": 0.1}
    assert rayleigh_note(bent, 300.0) is None
    parabolic = {"alpha_per_v": 1e-5, "b_um_per_v": 27.7, "u_um_per_v": 0.129}
    note = rayleigh_note(parabolic, 300.0)
    assert note is not None and "u = 0.129 um/V" in note and "alpha (b - u) = 0.000276 um/V^2" in note
    assert rayleigh_note(parabolic, 0.0) is None
