"""The one fit-result type: every calibration fit returns a piezod.fitstats.FitResult whose
standard errors, covariance and correlations agree, with n, dof and the residual RMS."""

from __future__ import annotations

import numpy as np
import pytest

from piezod.calibrate import fit, prepare
from piezod.calibrate_dynamic import DynamicCalibrationResult, fit_dynamic, prepare_dynamic
from piezod.fitstats import FitResult, parameter_statistics, solve_linear
from piezod.recording import split_experiments
from piezod.synth import random_params, random_plan, synth_session


def _check(res: FitResult, n_coefficients_besides: int) -> None:
    assert isinstance(res, FitResult)
    p = len(res.free)
    assert res.covariance.shape == res.correlations.shape == (p, p)
    sd = np.sqrt(np.diag(res.covariance))
    np.testing.assert_allclose(sd, [res.stderr[k] for k in res.free], rtol=1e-9)
    np.testing.assert_allclose(res.covariance / np.outer(sd, sd), res.correlations, rtol=1e-9, atol=1e-12)
    assert all(res.stderr[k] == 0.0 for k in res.fixed)
    assert res.n == res.residuals_um.size and res.dof == res.n - p - n_coefficients_besides
    assert res.residual_rms_um == pytest.approx(float(np.sqrt(np.mean(res.residuals_um**2))))
    assert set(res.values) >= set(res.free)
    js = res.statistics_json()
    assert js["n"] == res.n and js["free"] == list(res.free) and set(js["correlations"]) == set(res.free)


def test_thesis_fit_returns_the_shared_result() -> None:
    truth = random_params(3)
    session = synth_session(truth, random_plan(3, 8), samples_per_loop=256, noise_um=0.005, seed=3)
    data = prepare(split_experiments(session.recording))
    _check(fit(data), data.n_experiments)  # one position offset per experiment


def test_dynamic_fit_returns_the_shared_result() -> None:
    from hil_sim.session import Triangle, calibration_plan, run_session
    from hil_sim.stage import StageConfig
    from piezod.config import default_sim_config_path
    from piezod.simulator import session_experiments

    stage = StageConfig.from_file(default_sim_config_path())
    plan = calibration_plan(
        [200.0, 400.0], [2.0, 8.0], reference=Triangle(300.0, 4.0, cycles=2), reference_every=2
    )
    sess = run_session(stage, plan, sample_rate_hz=500.0, axis="x", voltage_limits_v=(-230.0, 230.0))
    res = fit_dynamic(prepare_dynamic(session_experiments(sess), max_samples_per_loop=128))
    assert isinstance(res, DynamicCalibrationResult)
    _check(res, len(res.experiments))


def test_parameter_statistics_in_physical_units() -> None:
    # y = exp(z0) * t + z1 fitted in (z0 = log slope, z1): the slope's standard error is slope * sd(z0)
    t = np.linspace(0.0, 1.0, 50)
    slope = 2.0
    jac = np.column_stack([slope * t, np.ones_like(t)])
    st = parameter_statistics(
        jac,
        0.49,
        48,
        names=("slope", "c"),
        free=("slope", "c"),
        z=[np.log(slope), 0.0],
        lo=[-10.0, -10.0],
        hi=[10.0, 10.0],
        dvalue_dz=[slope, 1.0],
    )
    cov = np.linalg.inv(np.column_stack([t, np.ones_like(t)]).T @ np.column_stack([t, np.ones_like(t)]))
    np.testing.assert_allclose(st.covariance, cov * 0.49 / 48, rtol=1e-9)
    assert st.at_bounds == () and st.dof == 48


def test_solve_linear_honours_bounds() -> None:
    a = np.column_stack([np.ones(10), np.arange(10.0)])
    y = 1.0 - 0.5 * np.arange(10.0)
    c, rms = solve_linear(a, y, lower=np.array([-np.inf, 0.0]), upper=np.array([np.inf, np.inf]))
    assert c[1] == pytest.approx(0.0, abs=1e-9) and rms > 0
    c, rms = solve_linear(a, y)
    np.testing.assert_allclose(c, [1.0, -0.5], atol=1e-9)
    assert rms == pytest.approx(0.0, abs=1e-9)


def test_solve_linear_falls_back_when_the_active_set_svd_does_not_converge(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """BVLS's SVD can fail to converge on nearly collinear columns (the generalised play law on 5
    centre nodes on tansy30's frame): the trust-region method solves it instead; a solver that
    fails outright is a CalibrationError naming it, never numpy's LinAlgError."""
    import piezod.fitstats as fs
    from piezod.errors import CalibrationError

    real = fs.lsq_linear

    def flaky(*args: object, method: str = "trf", **kwargs: object) -> object:
        if method == "bvls":
            raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
        return real(*args, method=method, **kwargs)

    a = np.column_stack([np.ones(10), np.arange(10.0)])
    y = 1.0 - 0.5 * np.arange(10.0)
    lower, upper = np.array([-np.inf, -1.0]), np.array([np.inf, 0.0])
    want, _ = solve_linear(a, y, lower=lower, upper=upper, method="bvls")
    monkeypatch.setattr(fs, "lsq_linear", flaky)
    got, _ = solve_linear(a, y, lower=lower, upper=upper, method="bvls")
    np.testing.assert_allclose(got, want, atol=1e-6)

    def broken(*args: object, **kwargs: object) -> object:
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(fs, "lsq_linear", broken)
    with pytest.raises(CalibrationError, match="did not converge"):
        solve_linear(a, y, lower=lower, upper=upper, method="bvls")


def _check_common(res: FitResult) -> None:
    """The part every fit fills: residuals, n, dof, cost and the information criteria agree."""
    assert isinstance(res, FitResult)
    r = res.residuals_um
    assert res.n == r.size and 0 < res.n_coefficients < res.n
    assert res.rss == pytest.approx(float(r @ r)) and res.residual_rms_um == pytest.approx(
        np.sqrt(np.mean(r**2))
    )
    k, n = res.n_coefficients, res.n
    assert res.bic == pytest.approx(n * np.log(res.rss / n) + k * np.log(n))
    assert res.aic == pytest.approx(n * np.log(res.rss / n) + 2 * k)


def test_family_fit_returns_the_shared_result() -> None:
    """FamilyFit: training residuals of the returned parameters, held-out RMS, no standard errors."""
    from hil_sim.session import calibration_plan, run_session
    from hil_sim.stage import StageConfig, resolve_stage
    from piezod.calibrate_family import (
        FamilyFit,
        _centre,
        _Session,
        default_taus,
        fit_family,
        holdout_mask,
        session_positions,
    )
    from piezod.simulator import session_experiments

    path = resolve_stage("pi-stage")
    assert path is not None
    plan = calibration_plan((150.0, 300.0), (0.5, 2.0), (-20.0, 20.0), cycles=1, settle_cycles=1)
    sess = run_session(
        StageConfig.from_file(path), plan, sample_rate_hz=500.0, axis="x", voltage_limits_v=(-230.0, 230.0)
    )
    data = prepare_dynamic(session_experiments(sess), max_samples_per_loop=64, slew_rate_v_per_s=2000.0)
    train = holdout_mask(data.n_experiments, 3)
    res = fit_family(data, "coleman-hodgdon", alpha_per_v=3e-3, train=train)
    assert isinstance(res, FamilyFit)
    _check_common(res)
    assert not res.has_errors and res.covariance.shape == (0, 0)
    assert res.cost == pytest.approx(0.5 * res.rss) and res.rms_um == res.residual_rms_um
    s = _Session(data, np.asarray(res.params.creep.taus_s), train)
    resid = s.yc - _centre(data, session_positions(data, res.params, s.dev))
    np.testing.assert_allclose(res.residuals_um, resid[s.train_rows], atol=1e-12)
    assert res.heldout_rms_um == pytest.approx(float(np.sqrt(np.mean(resid[s.test_rows] ** 2))))
    # theta (V, hysteresis unit), a weight per relaxation time, kappa, the lag; an offset per experiment
    assert res.dof == res.n - (2 + default_taus(data).size + 2) - int(train.sum())
    assert np.isnan(fit_family(data, "coleman-hodgdon", alpha_per_v=3e-3).heldout_rms_um)


@pytest.mark.filterwarnings("error")
def test_an_undetermined_parameter_leaves_the_others_their_variance() -> None:
    """A column the data do not determine (here all zero) has an infinite variance; the others
    keep theirs, and no invalid-value warning reaches the user (its inf * 0 used to make every
    variance nan, with a RuntimeWarning printed in the middle of a calibration)."""
    from piezod.fitstats import jacobian_covariance

    rng = np.random.default_rng(1)
    good = rng.normal(size=(40, 2))
    jac = np.column_stack([good, np.zeros(40)])
    cov = jacobian_covariance(jac, 1.0, 38)
    expected = np.sqrt(np.diag(np.linalg.inv(good.T @ good)) / 38)
    assert cov.sd[:2] == pytest.approx(expected)
    assert cov.sd[2] == np.inf and cov.condition_number == np.inf
    # two columns the data cannot tell apart: both undetermined
    twin = jacobian_covariance(np.column_stack([good[:, 0], good[:, 0], good[:, 1]]), 1.0, 37)
    assert np.isinf(twin.sd[:2]).all() and np.isfinite(twin.sd[2])
