"""The one fit-result type and the statistics every least-squares fit of piezod shares.

:class:`FitResult` is what every least-squares fit returns: the calibrations
(``piezod.calibrate.CalibrationResult``, ``piezod.calibrate_dynamic.DynamicCalibrationResult``,
``piezod.calibrate_family.FamilyFit``) and the audit (``piezod.audit.fitting.Fit``) are
subclasses adding their model's parameters and summaries (the thesis and dynamic calibrations
through :class:`CalibrationFit`: named parameters, a summary per experiment). Every result has
residuals and their RMS, cost, ``n``, ``dof``, AIC and BIC; where the fit computes them,
parameter standard errors, covariance and correlations, the condition number, the parameters
on a bound; where it held data out, the held-out RMS. :func:`parameter_statistics` computes
the statistics from the Jacobian at the solution (the nonlinear fits, and the audit through
:func:`jacobian_covariance`), :func:`solve_linear` is the linear least-squares path (bounded,
optionally regularised).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar, Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import lsq_linear

from piezod.errors import CalibrationError

F64 = NDArray[np.float64]

#: Singular values below this fraction of the largest count as zero (infinite variance).
_SV_FLOOR = 1e-13
#: A parameter whose unit vector has a component larger than this outside the directions the data
#: determine is itself undetermined (infinite variance).
_UNDETERMINED_COMPONENT = 1e-6
#: A condition number above this is reported as ill-conditioned.
ILL_CONDITIONED = 1e8


def excess_rms(rms: float, floor: float) -> float:
    """The part of a residual RMS above the sensor's noise floor: ``sqrt(rms^2 - floor^2)`` (0
    below the floor; ``rms`` itself when ``floor`` is not a positive number).

    Parameters
    ----------
    rms
        A residual RMS (any unit).
    floor
        The white noise of the data it is on, in the same unit
        (:func:`piezod.audit.residuals.pooled_noise_floor`).
    """
    if not (math.isfinite(floor) and floor > 0.0) or not math.isfinite(rms):
        return rms
    return math.sqrt(max(rms * rms - floor * floor, 0.0))


def lowers(new: float, old: float, fraction: float, floor: float = 0.0) -> bool:
    """Whether the residual RMS ``new`` is below ``old`` by ``fraction`` of what ``old`` leaves
    above the noise ``floor`` (:func:`excess_rms`).

    A relative gain of the RMS itself cannot tell a model error from the sensor's noise: on a
    2.2 um stage read through 3 nm of noise, a polarity part that took the chosen member's model
    error from 0.9 to 0.3 nm moved the RMS 3.14 -> 3.02 nm, 4 %, below a 5 % threshold
    (docs/model-family.md 6.2ap). With ``floor`` 0 this is ``new < (1 - fraction) old``.

    Parameters
    ----------
    new, old
        Residual RMS with and without the change (``inf`` for a failed fit).
    fraction
        The relative gain the change must bring.
    floor
        The noise floor of the data both are on (0: none taken out).
    """
    if not math.isfinite(new):
        return False
    if not math.isfinite(old):
        return True
    return excess_rms(new, floor) < (1.0 - fraction) * excess_rms(old, floor)


@dataclass(frozen=True, slots=True)
class Covariance:
    """Covariance of the fitted (internal) parameters from the Jacobian at the solution.

    Attributes
    ----------
    cov
        Covariance of all Jacobian columns (internal parameters).
    sd
        Standard deviations (square root of the diagonal).
    corr
        Correlation matrix.
    condition_number
        Of the column-normalised Jacobian.
    """

    cov: F64
    sd: F64
    corr: F64
    condition_number: float


def jacobian_covariance(jac: ArrayLike, sum_sq: float, dof: int) -> Covariance:
    """``s^2 (J^T J)^-1`` with ``s^2 = sum_sq / dof``, by an SVD of the column-normalised Jacobian.

    Directions the data do not determine get an infinite variance instead of a wrong number.
    """
    Jc = np.asarray(jac, dtype=np.float64)
    norms = np.linalg.norm(Jc, axis=0)
    norms[norms == 0] = 1.0
    _, sv, vt = np.linalg.svd(Jc / norms, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 and sv.size == Jc.shape[1] else math.inf
    determined = sv > sv[0] * _SV_FLOOR
    s2 = sum_sq / max(dof, 1)
    cov = (vt[determined].T / sv[determined] ** 2) @ vt[determined]
    # a parameter with a component along a direction the data do not determine has an infinite
    # variance and no defined covariance; the others keep theirs (a product inf * 0 gave nan)
    outside = 1.0 - np.sum(vt[determined] ** 2, axis=0)  # of each unit parameter vector, squared
    touched = outside > _UNDETERMINED_COMPONENT**2
    cov[touched, :] = np.nan
    cov[:, touched] = np.nan
    cov[touched, touched] = np.inf
    cov = cov / np.outer(norms, norms) * s2
    sd = np.sqrt(np.abs(np.diag(cov)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    return Covariance(cov, sd, corr, cond)


def at_bounds(
    names: Sequence[str], free: Sequence[str], z: ArrayLike, lo: ArrayLike, hi: ArrayLike, rel: float = 1e-6
) -> tuple[str, ...]:
    """The free parameters whose internal value sits on a bound (within ``rel`` of the span)."""
    zz, ll, hh = (np.asarray(a, dtype=np.float64) for a in (z, lo, hi))
    span = hh - ll
    out = []
    for k in free:
        i = list(names).index(k)
        if min(zz[i] - ll[i], hh[i] - zz[i]) < rel * span[i]:
            out.append(k)
    return tuple(out)


def fit_warnings(
    bounded: Sequence[str], condition_number: float, u_um_per_v: float, b_um_per_v: float
) -> list[str]:
    """The warnings every calibration gives (parameters on bounds, conditioning, loop shape)."""
    warnings = []
    if bounded:
        warnings.append(f"on a bound (standard errors not meaningful): {', '.join(bounded)}")
    if condition_number > ILL_CONDITIONED:
        warnings.append(f"ill-conditioned: condition number {condition_number:.3g}; see the correlations")
    if not u_um_per_v < b_um_per_v:
        warnings.append("u >= b: the loop shape is not that of a piezo (check the data)")
    return warnings


@dataclass(frozen=True, slots=True)
class ParameterStatistics:
    """Uncertainty of the free parameters of a fit, in their own units (see :func:`parameter_statistics`).

    Attributes
    ----------
    stderr
        Standard error per parameter name (0 for held ones; inf when the data do not determine it).
    covariance
        Covariance of the free parameters (order of ``free``).
    correlations
        Their correlation matrix.
    condition_number
        Of the column-normalised Jacobian.
    at_bounds
        Free parameters whose internal value sits on a bound.
    dof
        Degrees of freedom of the residual variance.
    """

    stderr: Mapping[str, float]
    covariance: F64
    correlations: F64
    condition_number: float
    at_bounds: tuple[str, ...]
    dof: int


def parameter_statistics(
    jac: ArrayLike,
    sum_sq: float,
    dof: int,
    *,
    names: Sequence[str],
    free: Sequence[str],
    z: ArrayLike,
    lo: ArrayLike,
    hi: ArrayLike,
    dvalue_dz: ArrayLike,
) -> ParameterStatistics:
    """Standard errors, covariance and correlations of a fit solved in internal coordinates ``z``.

    Parameters
    ----------
    jac
        Jacobian of the residuals at the solution; its first ``len(free)`` columns are the free
        parameters (further columns, e.g. per-experiment offsets, take part in the covariance).
    sum_sq, dof
        Residual sum of squares and its degrees of freedom.
    names
        Every parameter name, in the order of ``z``, ``lo``, ``hi`` and ``dvalue_dz``.
    free
        The fitted ones.
    z, lo, hi
        The solution and the bounds, internal coordinates (all parameters).
    dvalue_dz
        ``d value / d z`` per parameter (e.g. the value itself for a log-parametrised one).
    """
    cov = jacobian_covariance(jac, sum_sq, dof)
    p = len(free)
    d = np.asarray(dvalue_dz, dtype=np.float64)[[list(names).index(k) for k in free]]
    stderr = dict.fromkeys(names, 0.0)
    for j, k in enumerate(free):
        stderr[k] = float(abs(d[j]) * cov.sd[j])
    with np.errstate(invalid="ignore"):
        covariance = cov.cov[:p, :p] * np.outer(d, d)
    return ParameterStatistics(
        stderr=MappingProxyType(stderr),
        covariance=covariance,
        correlations=cov.corr[:p, :p],
        condition_number=cov.condition_number,
        at_bounds=at_bounds(names, free, z, lo, hi),
        dof=max(dof, 1),
    )


_NO_MATRIX: F64 = np.zeros((0, 0))


@dataclass(frozen=True, eq=False, kw_only=True)
class FitResult:
    """What every least-squares fit of piezod returns, the calibrations' and the audit's alike.

    Like :class:`scipy.optimize.OptimizeResult` or lmfit's ``MinimizerResult``: the residuals
    and the solver's status always, the parameter statistics where the fit computes them (a
    fit that does not has an empty :attr:`stderr` and :attr:`has_errors` false), held-out
    figures where the fit held data out. Subclasses add the fitted model (``params``;
    ``values``: name -> fitted value where the parameters are named) and their summaries:
    ``piezod.calibrate.CalibrationResult``, ``piezod.calibrate_dynamic.DynamicCalibrationResult``,
    ``piezod.calibrate_family.FamilyFit``, ``piezod.audit.fitting.Fit``.

    Attributes
    ----------
    residuals_um
        Measured minus fitted position per compared sample (um; for the audit after projecting
        out the nuisance terms).
    cost
        The solver's cost at the solution (scipy's convention: half the sum of squares it
        minimised, robust loss applied where the fit uses one).
    n
        Number of compared samples.
    dof
        Degrees of freedom of the residual variance (``n`` minus every fitted coefficient,
        nuisance terms such as per-experiment offsets included).
    nfev
        Model evaluations (or solver iterations, for fits that say so).
    success, message
        Solver status.
    seconds
        Wall time of the fit.
    warnings
        Things the user should know (undetermined or bounded parameters, ...).
    stderr
        Standard error per parameter name (0 for held ones; inf when undetermined; empty when
        the fit does not compute them).
    covariance
        Covariance matrix of the free parameters (order of ``free``; shape ``(0, 0)`` when not
        computed).
    correlations
        Correlation matrix of the free parameters (same order and shape).
    free, fixed
        Names of the fitted and of the held parameters.
    at_bounds
        Free parameters that ended on a bound (their standard errors are not meaningful).
    condition_number
        Condition number of the column-normalised Jacobian of the free parameters (nan when not
        computed).
    heldout_rms_um
        RMS prediction error on data the fit did not see (um), nan when none was held out.
    """

    residuals_um: F64
    cost: float
    n: int
    dof: int
    nfev: int
    success: bool
    message: str
    seconds: float = 0.0
    warnings: tuple[str, ...] = field(default=())
    stderr: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    covariance: F64 = field(default_factory=lambda: _NO_MATRIX)
    correlations: F64 = field(default_factory=lambda: _NO_MATRIX)
    free: tuple[str, ...] = ()
    fixed: tuple[str, ...] = ()
    at_bounds: tuple[str, ...] = ()
    condition_number: float = math.nan
    heldout_rms_um: float = math.nan

    def statistics_json(self) -> dict[str, Any]:
        """The shared part of a fit's JSON document (keys of docs/formats.md): the parameter
        statistics, ``n``, ``cost`` and the solver status."""
        return {
            "correlations": {
                a: {b: float(self.correlations[i, j]) for j, b in enumerate(self.free)}
                for i, a in enumerate(self.free)
            },
            "condition_number": self.condition_number,
            "free": list(self.free),
            "fixed": list(self.fixed),
            "at_bounds": list(self.at_bounds),
            "n": self.n,
            "cost": self.cost,
            "nfev": self.nfev,
            "success": self.success,
            "message": self.message,
            "seconds": self.seconds,
            "warnings": list(self.warnings),
        }

    @property
    def has_errors(self) -> bool:
        """Whether the fit computed parameter standard errors."""
        return bool(self.stderr)

    @property
    def rss(self) -> float:
        """Residual sum of squares (um^2)."""
        r = self.residuals_um
        return float(r @ r)

    @property
    def residual_rms_um(self) -> float:
        """RMS of :attr:`residuals_um` (um)."""
        return math.sqrt(self.rss / self.n) if self.n else math.nan

    @property
    def n_coefficients(self) -> int:
        """Fitted coefficients, nuisance terms included (``n - dof``)."""
        return self.n - self.dof

    @property
    def aic(self) -> float:
        """Akaike information criterion ``n ln(RSS / n) + 2 k``, ``k`` = :attr:`n_coefficients`."""
        return self.n * math.log(max(self.rss, 1e-300) / self.n) + 2.0 * self.n_coefficients

    @property
    def bic(self) -> float:
        """Bayesian information criterion ``n ln(RSS / n) + k ln n``, ``k`` = :attr:`n_coefficients`."""
        return self.n * math.log(max(self.rss, 1e-300) / self.n) + self.n_coefficients * math.log(self.n)


class ExperimentSummary(Protocol):
    """What :class:`CalibrationFit` needs of a per-experiment summary."""

    @property
    def label(self) -> str: ...

    @property
    def fit_error_pct(self) -> float: ...


ExperimentT = TypeVar("ExperimentT", bound=ExperimentSummary)


@dataclass(frozen=True, eq=False, kw_only=True)
class CalibrationFit(FitResult, Generic[ExperimentT]):
    """A calibration of named parameters with a summary per experiment (the thesis and the
    dynamic model's fits).

    Subclasses set :attr:`param_names` and hold the fitted model in ``params`` (one attribute
    per name).

    Attributes
    ----------
    experiments
        Per-experiment summaries.
    """

    #: The model's parameter names (attributes of ``params``), in order.
    param_names: ClassVar[tuple[str, ...]] = ()

    experiments: tuple[ExperimentT, ...]

    @property
    def values(self) -> dict[str, float]:
        """Parameter name -> fitted value."""
        params = getattr(self, "params")  # noqa: B009 - the subclass's model, typed there
        return {k: float(getattr(params, k)) for k in self.param_names}

    @property
    def fit_error_pct(self) -> float:
        """Worst experiment's fit error (2.27), in %."""
        return max(e.fit_error_pct for e in self.experiments)

    @property
    def worst(self) -> ExperimentT:
        """The experiment with the largest fit error."""
        return max(self.experiments, key=lambda e: e.fit_error_pct)


#: :func:`scipy.optimize.lsq_linear`'s options per method of :func:`solve_linear`.
_LSQ_OPTIONS: dict[str, dict[str, str]] = {
    "trf": {"method": "trf", "lsmr_tol": "auto"},
    "bvls": {"method": "bvls"},
}


def solve_linear(
    a: F64,
    y: F64,
    *,
    lower: F64 | None = None,
    upper: F64 | None = None,
    ridge: F64 | None = None,
    method: str = "trf",
) -> tuple[F64, float]:
    """Bounded, optionally Tikhonov-regularised linear least squares ``min |A c - y|^2 + |R c|^2``.

    The one linear least-squares path of the calibrations and of the audit:
    :func:`scipy.optimize.lsq_linear` (trust-region reflective) on the stacked, column-scaled
    system; without bounds and regularisation the column-scaled :func:`numpy.linalg.lstsq` that
    ``lsq_linear`` starts from (and returns) in that case.

    Parameters
    ----------
    a
        Design matrix, shape ``(n, p)``.
    y
        Data, shape ``(n,)``.
    lower, upper
        Bounds per coefficient (default unbounded).
    ridge
        Regularisation matrix ``R``, shape ``(k, p)`` (default none).
    method
        ``trf`` (trust-region reflective: any size) or ``bvls`` (an active-set method, exact to
        rounding: for up to a few hundred coefficients whose columns are nearly collinear, where
        ``trf`` stops short of the minimum).

    Returns
    -------
    coefficients : ndarray
        The solution.
    rms : float
        RMS of ``A c - y`` (without the regularisation rows).

    Raises
    ------
    CalibrationError
        ``A`` or ``y`` is not finite, ``method`` is unknown, or the solver does not converge
        (``bvls`` whose SVD fails is solved by ``trf`` first).
    """
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(y))):
        raise CalibrationError("linear least squares: the design matrix or the data is not finite")
    p = a.shape[1]
    lo = np.full(p, -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
    hi = np.full(p, np.inf) if upper is None else np.asarray(upper, dtype=np.float64)
    fixed = lo >= hi
    if fixed.any():
        c: F64 = np.where(fixed, lo, 0.0)
        free = ~fixed
        if not free.any():
            return c, float(np.sqrt(np.mean((a @ c - y) ** 2)))
        sub, _ = solve_linear(
            a[:, free],
            y - a[:, fixed] @ lo[fixed],
            lower=lo[free],
            upper=hi[free],
            ridge=None if ridge is None else ridge[:, free],
            method=method,
        )
        c[free] = sub
        return c, float(np.sqrt(np.mean((a @ c - y) ** 2)))
    if lower is None and upper is None and ridge is None:
        # what lsq_linear does first (and returns) for an unbounded problem, without its overhead
        scale = np.linalg.norm(a, axis=0)
        scale[scale == 0.0] = 1.0
        try:
            sol_u: F64 = np.linalg.lstsq(a / scale, y, rcond=-1)[0] / scale
        except np.linalg.LinAlgError as exc:
            raise CalibrationError(f"linear least squares did not converge: {exc}") from exc
        return sol_u, float(np.sqrt(np.mean((a @ sol_u - y) ** 2)))
    if ridge is not None:
        a_full = np.vstack([a, ridge])
        y_full = np.concatenate([y, np.zeros(ridge.shape[0])])
    else:
        a_full, y_full = a, y
    scale = np.linalg.norm(a_full, axis=0)
    scale[scale == 0.0] = 1.0
    if method not in ("trf", "bvls"):
        raise CalibrationError(f"unknown linear least-squares method {method!r} (trf, bvls)")
    # the active set's SVD can fail to converge on nearly collinear columns (the generalised play
    # law on 5 centre nodes did on tansy30's frame); the trust-region method takes none
    tries = [method, "trf"] if method == "bvls" else [method]
    for i, m in enumerate(tries):
        try:
            res = lsq_linear(a_full / scale, y_full, bounds=(lo * scale, hi * scale), **_LSQ_OPTIONS[m])
            break
        except np.linalg.LinAlgError as exc:
            if i == len(tries) - 1:
                raise CalibrationError(f"linear least squares did not converge: {exc}") from exc
    # the active-set solution may sit a rounding error outside its bounds
    sol: F64 = np.clip(res.x / scale, lo, hi)
    return sol, float(np.sqrt(np.mean((a @ sol - y) ** 2)))
