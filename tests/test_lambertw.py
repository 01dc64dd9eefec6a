"""Lambert W0 with a fixed number of Halley steps, against scipy as the oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.special import lambertw as scipy_lambertw
from scipy.special import wrightomega

from piezod.errors import LambertWDomainError, ModelError
from piezod.model.lambertw import (
    BRANCH_POINT,
    lambertw0,
    lambertw0_exp,
    lambertw0_exp_bounded,
    lambertw0_exp_scalar,
)

EPS = np.finfo(np.float64).eps


def _tolerance(w_ref: np.ndarray) -> np.ndarray:
    """Rounding-level tolerance, widened by W's condition number ``1 / (1 + w)`` near the branch point."""
    tol: np.ndarray = 8 * EPS * np.abs(w_ref) * np.maximum(1.0, 1.0 / (1.0 + w_ref)) + 1e-300
    return tol


def test_negative_arguments_match_scipy() -> None:
    rng = np.random.default_rng(1)
    z = BRANCH_POINT * np.concatenate([rng.uniform(0, 1, 20000), 10.0 ** rng.uniform(-300, 0, 5000)])
    w = lambertw0(z)
    ref = scipy_lambertw(z).real
    assert np.all(np.abs(w - ref) <= _tolerance(ref) + 4 * EPS * np.abs(ref))


def test_positive_arguments_match_scipy() -> None:
    rng = np.random.default_rng(2)
    z = np.concatenate([rng.uniform(0, 10, 20000), 10.0 ** rng.uniform(-300, 300, 20000)])
    w = lambertw0(z)
    ref = scipy_lambertw(z).real
    np.testing.assert_allclose(w, ref, rtol=4 * EPS, atol=0)


def test_log_form_matches_wright_omega_without_overflow() -> None:
    rng = np.random.default_rng(3)
    y = np.concatenate([rng.uniform(-60, 60, 20000), rng.uniform(700, 1e6, 2000), [1e300]])
    w = lambertw0_exp(y)
    # scipy's wrightomega itself is off by up to ~16 eps (e.g. near y = -33)
    np.testing.assert_allclose(w, wrightomega(y), rtol=32 * EPS, atol=0)
    assert np.all(np.isfinite(w))


def test_log_form_negative_branch_matches_scipy() -> None:
    rng = np.random.default_rng(4)
    y = np.concatenate([rng.uniform(-60, -1, 20000), -1.0 - 10.0 ** rng.uniform(-15, -2, 5000)])
    w = lambertw0_exp(y, negative=True)
    ref = scipy_lambertw(-np.exp(y)).real
    assert np.all(np.abs(w - ref) <= _tolerance(ref) + 4 * EPS * np.abs(ref))


@given(st.floats(-700.0, -1.0))
def test_negative_log_form_solves_its_equation(y: float) -> None:
    w = float(lambertw0_exp(np.array([y]), negative=True)[0])
    assert -1.0 <= w < 0.0
    assert abs((w + math.log(-w)) - y) <= 8 * EPS * (abs(y) + 1.0)


@given(st.floats(-700.0, 1e300))
def test_positive_log_form_solves_its_equation(y: float) -> None:
    w = float(lambertw0_exp(np.array([y]))[0])
    assert w > 0.0
    assert abs((w + math.log(w)) - y) <= 8 * EPS * max(abs(y), 1.0)


@given(st.floats(-700.0, 1e5), st.booleans())
def test_scalar_version_agrees(y: float, negative: bool) -> None:
    if negative:
        y = min(y, -1.0)
    w_vec = float(lambertw0_exp(np.array([y]), negative=negative)[0])
    w_sca = lambertw0_exp_scalar(y, negative=negative)
    assert w_sca == pytest.approx(w_vec, rel=8 * EPS, abs=1e-300)


def test_blocks_spanning_all_regions_equal_elementwise_evaluation() -> None:
    y_pos = np.array([-800.0, -41.0, -39.0, -3.0, 0.0, 0.5, 3.9, 4.1, 50.0, 1e6])
    y_neg = np.array([-800.0, -41.0, -39.0, -3.0, -1.01, -1.0 - 1e-4, -1.0 - 1e-12, -1.0])
    for y, neg in ((y_pos, False), (y_neg, True)):
        whole = lambertw0_exp(y, negative=neg)
        single = np.array([lambertw0_exp(np.array([v]), negative=neg)[0] for v in y])
        np.testing.assert_array_equal(whole, single)
        bounded = lambertw0_exp_bounded(y, float(y.min()), float(y.max()), negative=neg)
        np.testing.assert_array_equal(bounded, whole)


def test_special_values() -> None:
    assert lambertw0(np.array([0.0]))[0] == 0.0
    assert lambertw0(np.array([-0.0]))[0] == 0.0
    assert lambertw0(np.array([BRANCH_POINT]))[0] == pytest.approx(-1.0, abs=1e-7)
    assert lambertw0(np.array([math.e]))[0] == pytest.approx(1.0, rel=2 * EPS)
    assert lambertw0_exp(np.array([-math.inf]))[0] == 0.0
    assert lambertw0_exp(np.array([-math.inf]), negative=True)[0] == 0.0
    assert lambertw0_exp(np.array([-1.0]), negative=True)[0] == -1.0


def test_shape_is_kept_and_scalars_work() -> None:
    z = np.linspace(-0.3, 5.0, 12).reshape(3, 4)
    assert lambertw0(z).shape == (3, 4)
    assert lambertw0(0.5).shape == ()
    assert lambertw0_exp(np.empty((0, 2))).shape == (0, 2)


def test_below_branch_point_raises_naming_the_value() -> None:
    with pytest.raises(LambertWDomainError, match=r"-0\.37"):
        lambertw0(np.array([0.1, -0.37]))
    with pytest.raises(LambertWDomainError, match="below the branch point"):
        lambertw0_exp(np.array([-3.0, -0.99]), negative=True)
    with pytest.raises(LambertWDomainError):
        lambertw0_exp_scalar(-0.5, negative=True)
    # the domain error is a ModelError (and a ValueError) for callers
    with pytest.raises(ModelError):
        lambertw0(-1.0)
    with pytest.raises(ValueError, match="branch point"):
        lambertw0(-1.0)


def test_rounding_below_branch_point_is_accepted() -> None:
    z = np.nextafter(BRANCH_POINT, -1.0)
    assert lambertw0(np.array([z]))[0] == pytest.approx(-1.0, abs=1e-7)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_nan_and_inf_raise(bad: float) -> None:
    with pytest.raises(LambertWDomainError):
        lambertw0(np.array([1.0, bad]))
    with pytest.raises(LambertWDomainError):
        lambertw0_exp(np.array([bad]))
    with pytest.raises(LambertWDomainError):
        lambertw0_exp_scalar(bad)


@given(st.lists(st.floats(BRANCH_POINT, 1e300), min_size=1, max_size=50))
def test_never_nan_inside_the_domain(zs: list[float]) -> None:
    w = lambertw0(np.array(zs))
    assert np.all(np.isfinite(w))
    assert np.all(w >= -1.0)
