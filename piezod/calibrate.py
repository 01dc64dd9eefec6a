"""Offline calibration: least-squares fit of the 7-parameter model (3.8) to recorded loops.

Model
-----
Experiment ``i`` is a steady triangular scan between ``V_m,i`` and ``V_M,i`` at line
frequency ``f_i`` (all inferred from the voltage waveform). Its samples are modelled as

    x_ij = thesis_loop(p, V_ij, s_ij, V_m,i, V_M,i, f_i) + c_i + noise

with the 7 parameters ``p = (alpha, b, u, tau, A1, A2, A3)`` shared by all experiments
and one position offset ``c_i`` per experiment (sensor zero, drift between experiments;
it also absorbs the ``-(b_hat - b) V_C`` term of offset scans).

Offsets
-------
With the default squared loss the offsets are eliminated analytically (variable
projection): residuals and Jacobian are centred per experiment, which is exactly the
least-squares optimum over ``c_i`` for every ``p``, and the marginal covariance of
``p`` follows from the projected Jacobian. With a robust loss (``soft_l1``, ``huber``,
``cauchy``, ``arctan``) the mean is not the optimal offset, so the offsets are fitted
as explicit parameters; ``f_scale`` defaults to twice the robust noise estimate of a
first squared-loss fit.

Parametrisation, bounds, start
------------------------------
The solver works on ``z = (ln alpha, ln b, ln u, ln tau, A1, A2 * S, A3)`` with
``S`` the mean half range of the frame, so that all components are O(1)
(``x_scale = 1``) and ``alpha, b, u, tau`` stay positive. Bounds keep the model
physical and inside the config schema: ``1e-6 < alpha < 0.999 /V``,
``1e-6 < b, u < 99 um/V``, ``1e-3 s < tau < 1e5 s``, ``0 <= A1 <= 0.999`` (creep
decreases with frequency and the creep factor stays positive), ``|A2| <= 0.999 /V``,
``|A3| <= 99``. The Jacobian is analytic.

The automatic start needs no prior: (1) for ``alpha`` on a grid refined by a scalar
search, the model with one free sensitivity ``b_hat_i`` per experiment (the thesis's
"unrestricted k_i" fit (3.4)) is linear in ``delta = (b - u)/alpha``, ``b_hat_i`` and
``c_i``; (2) for ``(tau, A1)`` on a grid, ``b_hat_i = b + delta D_i (1 - A1 E_i)(A2 V_h,i +
A3)`` is linear in ``(b, A2, A3)``. The best of this start and, when given, the config's
parameters starts the full fit.

Identifiability
---------------
Only ``alpha``, ``delta`` and the function ``b_hat(f, V_h)`` are observable. ``tau`` and
``A1`` need frequencies around ``1/tau``; ``A2`` needs three or more ranges; ``b`` and
``A3`` are separated only by the curvature of ``tanh(alpha V_h) / V_h`` over the
ranges and are strongly correlated for small ``alpha V_h``. Parameters the frame
cannot determine (fewer than 3 distinct frequencies: ``tau``; fewer than 2: also
``A1``; fewer than 3 ranges: ``A2``) are held at their start values and listed in
:attr:`CalibrationResult.fixed`; the correlation matrix and the condition number of
the scaled Jacobian are reported as they are.

Fit error
---------
Per experiment (2.26)-(2.27): ``sigma_i = sqrt(LSF_i / (n_i - nu))`` with ``nu`` the
number of fitted model parameters (the per-experiment offset is not counted; it
changes sigma by ~1/(2 n_i)), relative to the distance ``Delta x_i`` covered by the
fitted loop (``max - min`` of the model), in %.

The recordings -> arrays step (:func:`prepare`, :class:`CalibrationData`) lives in
:mod:`piezod.calibrate_data` (re-exported here); the model, its start, the fit and its outputs
stay together here (a little over 800 lines: one model's calibration, end to end); the
statistics every fit returns are :class:`piezod.fitstats.FitResult`.
"""

from __future__ import annotations

import datetime as _dt
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, minimize_scalar

from piezod import __version__
from piezod.calibrate_data import CalibrationData, prepare
from piezod.config import AxisConfig, ScannerConfig, ThesisModelConfig, calibrated_notes
from piezod.errors import CalibrationError, ModelError
from piezod.fitstats import CalibrationFit, fit_warnings, parameter_statistics, solve_linear
from piezod.model.params import ThesisParams
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: Names of the 7 model parameters, in the order of (3.8) / table 3.3.
PARAM_NAMES: tuple[str, ...] = ("alpha_per_v", "b_um_per_v", "u_um_per_v", "tau_s", "a1", "a2_per_v", "a3")
LOSSES: tuple[str, ...] = ("linear", "soft_l1", "huber", "cauchy", "arctan")

_LOG = np.array([True, True, True, True, False, False, False])
_LOWER = np.array([1e-6, 1e-6, 1e-6, 1e-3, 0.0, -0.999, -99.0])
_UPPER = np.array([0.999, 99.0, 99.0, 1e5, 0.999, 0.999, 99.0])
_DEFAULT_TAU_S = 1.0


# ------------------------------------------------------------------------------------------------ model


def _to_z(p: ThesisParams, a2_scale: float) -> F64:
    v = np.array([getattr(p, k) for k in PARAM_NAMES], dtype=np.float64)
    v[5] *= a2_scale
    v[:4] = np.log(v[:4])
    return v


def _from_z(z: F64, a2_scale: float) -> ThesisParams:
    v = np.asarray(z, dtype=np.float64).copy()
    v[:4] = np.exp(v[:4])
    v[5] /= a2_scale
    return ThesisParams(**dict(zip(PARAM_NAMES, v.tolist(), strict=True)))


def _z_bounds(a2_scale: float) -> tuple[F64, F64]:
    lo, hi = _LOWER.copy(), _UPPER.copy()
    lo[5] *= a2_scale
    hi[5] *= a2_scale
    lo[:4] = np.log(lo[:4])
    hi[:4] = np.log(hi[:4])
    return lo, hi


def _model(data: CalibrationData, z: F64, a2_scale: float, jac: bool) -> tuple[F64, F64 | None]:
    """Model positions (without offsets) and, optionally, the Jacobian d x / d z (n x 7)."""
    alpha, b, u, tau = np.exp(z[:4])
    a1, a2, a3 = z[4], z[5] / a2_scale, z[6]
    idx = data.index
    v, s = data.voltage_v, data.direction
    sdv = data.distance_from_start_v
    pc = data.from_centre_v
    vr = data.v_max - data.v_min
    vh = 0.5 * vr
    e_r = np.exp(-alpha * vr)
    c_rel = 2.0 / (1.0 + e_r)
    th = np.tanh(alpha * vh)
    dd = th / vh
    ee = np.exp(-1.0 / (data.frequency_hz * tau))
    gg = a2 * vh + a3
    ff = 1.0 - a1 * ee
    kk = ff * gg
    delta = (b - u) / alpha
    w = c_rel[idx] * np.exp(-alpha * sdv)
    one_w = 1.0 - w
    beta = kk * delta * dd  # b_hat - b per experiment
    x = b * v - s * delta * one_w + beta[idx] * pc
    if not jac:
        return x, None
    dlnc = vr * e_r / (1.0 + e_r)  # d ln(C_rel) / d alpha
    J = np.empty((v.size, 7))
    J[:, 0] = (
        s * delta * (one_w + alpha * w * (dlnc[idx] - sdv))
        + (kk * delta * (alpha * (1.0 - th**2) - dd))[idx] * pc
    )
    creep = (kk * dd / alpha)[idx] * pc
    J[:, 1] = b * (v - s * one_w / alpha + creep)
    J[:, 2] = u * (s * one_w / alpha - creep)
    per_exp = np.column_stack(
        [
            -delta * dd * gg * a1 * ee / (data.frequency_hz * tau),
            -delta * dd * gg * ee,
            delta * dd * ff * vh / a2_scale,
            delta * dd * ff,
        ]
    )
    J[:, 3:] = per_exp[idx] * pc[:, None]
    return x, J


def model_positions(data: CalibrationData, params: ThesisParams) -> F64:
    """Positions of (3.8) for every sample of the frame, without offsets."""
    x, _ = _model(data, _to_z(params, 1.0), 1.0, jac=False)
    return x


def _centre(data: CalibrationData, a: NDArray[np.float64]) -> NDArray[np.float64]:
    sums = np.add.reduceat(a, data.starts, axis=0)
    means = sums / (data.counts if a.ndim == 1 else data.counts[:, None])
    out: NDArray[np.float64] = a - np.repeat(means, data.counts, axis=0)
    return out


def fit_errors(data: CalibrationData, params: ThesisParams, *, nu: int = 7) -> tuple[F64, F64, F64]:
    """Per-experiment fit error (2.26)-(2.27) of ``params`` with least-squares offsets.

    Returns
    -------
    fit_error_pct, sigma_um, range_um
        Per experiment.
    """
    x = model_positions(data, params)
    r = _centre(data, data.position_um - x)
    return _errors(data, x, r, nu)


def _errors(data: CalibrationData, x: F64, r: F64, nu: int) -> tuple[F64, F64, F64]:
    lsf = np.add.reduceat(r**2, data.starts)
    sigma = np.sqrt(lsf / np.maximum(data.counts - nu, 1))
    rng = np.maximum.reduceat(x, data.starts) - np.minimum.reduceat(x, data.starts)
    return 100.0 * sigma / rng, sigma, rng


# ------------------------------------------------------------------------------------------------ start


def _distinct(values: F64, rel: float = 0.05) -> int:
    lv = np.sort(np.log(np.abs(values)))
    return int(1 + np.count_nonzero(np.diff(lv) > rel)) if lv.size else 0


def _hysteresis_stage(data: CalibrationData, log_alpha: float) -> tuple[float, float, F64]:
    """Free-sensitivity fit (3.4) at fixed alpha: returns (rss, delta, b_hat per experiment)."""
    alpha = math.exp(log_alpha)
    counts = data.counts
    s, v = data.direction, data.voltage_v
    c_rel = 2.0 / (1.0 + np.exp(-alpha * (data.v_max - data.v_min)))
    g = -s * (1.0 - c_rel[data.index] * np.exp(-alpha * data.distance_from_start_v))
    vc = _centre(data, v)
    svv = np.add.reduceat(vc * vc, data.starts)
    gc = _centre(data, g)
    xc = _centre(data, data.position_um)
    gp = gc - np.repeat(np.add.reduceat(gc * vc, data.starts) / svv, counts) * vc
    xp = xc - np.repeat(np.add.reduceat(xc * vc, data.starts) / svv, counts) * vc
    sgg = float(gp @ gp)
    sgx = float(gp @ xp)
    delta = sgx / sgg if sgg > 0 else 0.0
    rss = float(xp @ xp) - (sgx * delta)
    b_hat = np.add.reduceat((xc - delta * gc) * vc, data.starts) / svv
    return rss, delta, b_hat


def auto_start(data: CalibrationData, *, fixed: Mapping[str, float] | None = None) -> ThesisParams:
    """A start for the fit from the data alone (see the module docstring).

    Parameters
    ----------
    data
        The frame.
    fixed
        Values to use for parameters held fixed (``tau_s``, ``a1``, ``a2_per_v``).

    Raises
    ------
    CalibrationError
        The loops show no hysteresis of the modelled orientation (``b <= u``).
    """
    fixed = dict(fixed or {})
    vr = data.v_max - data.v_min
    grid = np.linspace(math.log(0.02 / vr.max()), math.log(min(20.0 / vr.min(), 0.9)), 48)
    rss = np.array([_hysteresis_stage(data, la)[0] for la in grid])
    k = int(np.argmin(rss))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    best = minimize_scalar(
        lambda la: _hysteresis_stage(data, la)[0], bounds=(lo, hi), method="bounded", options={"xatol": 1e-6}
    )
    log_alpha = float(best.x) if best.fun <= rss[k] else float(grid[k])
    _, delta, b_hat = _hysteresis_stage(data, log_alpha)
    alpha = math.exp(log_alpha)
    if not delta > 0:
        raise CalibrationError(
            "the loops show no hysteresis of the modelled orientation (trace below retrace): "
            f"fitted (b - u)/alpha = {delta:.4g} um"
        )

    vh = 0.5 * vr
    dd = np.tanh(alpha * vh) / vh
    f = data.frequency_hz
    taus = (
        np.array([fixed["tau_s"]])
        if "tau_s" in fixed
        else np.exp(np.linspace(math.log(0.01 / f.max()), math.log(100.0 / f.min()), 40))
    )
    a1s = np.array([fixed["a1"]]) if "a1" in fixed else np.linspace(0.0, 0.95, 20)
    best_rss, best_sol = math.inf, (float(np.median(b_hat)), 0.0, 0.0, _DEFAULT_TAU_S, 0.0)
    for tau in taus:
        ee = np.exp(-1.0 / (f * tau))
        for a1 in a1s:
            ff = 1.0 - a1 * ee
            cols = [np.ones_like(vh), delta * dd * ff]
            target = b_hat.copy()
            if "a2_per_v" in fixed:
                target -= delta * dd * ff * vh * fixed["a2_per_v"]
            else:
                cols.append(delta * dd * ff * vh)
            A = np.column_stack(cols)
            sol, _ = solve_linear(A, target)
            r = float(np.sum((A @ sol - target) ** 2))
            if r < best_rss:
                a2 = fixed.get("a2_per_v", float(sol[2]) if sol.size > 2 else 0.0)
                best_rss, best_sol = r, (float(sol[0]), float(sol[1]), a2, float(tau), float(a1))
    b, a3, a2, tau, a1 = best_sol
    b = float(np.clip(b, 1.01 * alpha * delta, 98.0))  # keep u = b - alpha delta > 0
    u = max(b - alpha * delta, 1e-3 * b)
    return ThesisParams(
        alpha_per_v=float(np.clip(alpha, 2e-6, 0.99)),
        b_um_per_v=b,
        u_um_per_v=u,
        tau_s=float(np.clip(tau, 2e-3, 5e4)),
        a1=float(np.clip(a1, 0.0, 0.99)),
        a2_per_v=float(np.clip(a2, -0.99, 0.99)),
        a3=float(np.clip(a3, -98.0, 98.0)),
    )


# -------------------------------------------------------------------------------------------------- fit


@dataclass(frozen=True, eq=False)
class ExperimentFit:
    """Fit summary of one experiment.

    Attributes
    ----------
    label, axis, path
        Identification.
    v_min, v_max, frequency_hz, n_loops
        The scan inferred from the voltage.
    n
        Samples used.
    position_offset_um
        Fitted position offset ``c_i``.
    range_um
        Distance covered by the fitted loop (``Delta x_i`` of (2.27)).
    sigma_um
        ``sigma_i`` of (2.26).
    fit_error_pct
        ``100 sigma_i / Delta x_i`` (2.27).
    rms_um
        RMS residual.
    """

    label: str
    axis: str | None
    path: str | None
    v_min: float
    v_max: float
    frequency_hz: float
    n_loops: int
    n: int
    position_offset_um: float
    range_um: float
    sigma_um: float
    fit_error_pct: float
    rms_um: float

    @property
    def range_v(self) -> float:
        """Peak-to-peak voltage range."""
        return self.v_max - self.v_min

    @property
    def offset_v(self) -> float:
        """Centre voltage of the scan."""
        return 0.5 * (self.v_max + self.v_min)


@dataclass(frozen=True, eq=False, kw_only=True)
class CalibrationResult(CalibrationFit[ExperimentFit]):
    """Result of :func:`fit`: the shared :class:`~piezod.fitstats.FitResult` (standard errors,
    covariance, correlations, residuals, condition, bounds, ``n``, ``dof``, solver status) and
    the thesis model's parameters.

    Attributes
    ----------
    params
        Fitted parameters.
    experiments
        Per-experiment summaries.
    loss
        Loss function used.
    """

    param_names: ClassVar[tuple[str, ...]] = PARAM_NAMES

    params: ThesisParams
    loss: str


def _free_names(data: CalibrationData, fix: Iterable[str]) -> tuple[tuple[str, ...], set[str], list[str]]:
    """(held parameters, those held because the frame cannot determine them, notes)."""
    fixed = set(fix)
    asked = set(fixed)
    unknown = fixed - set(PARAM_NAMES)
    if unknown:
        raise CalibrationError(f"unknown parameter(s) to fix: {', '.join(sorted(unknown))}")
    notes: list[str] = []
    n_f = _distinct(data.frequency_hz)
    n_r = _distinct(data.v_max - data.v_min)
    if n_r < 2:
        raise CalibrationError(
            f"the frame has {n_r} distinct voltage range(s); at least 2 (better 4 or more) are needed"
        )
    if n_f < 3 and "tau_s" not in fixed:
        fixed.add("tau_s")
        notes.append(f"only {n_f} distinct frequencies: tau_s held at its start value")
    if n_f < 2 and "a1" not in fixed:
        fixed.add("a1")
        notes.append("one frequency only: a1 held at its start value")
    if n_r < 3 and "a2_per_v" not in fixed:
        fixed.add("a2_per_v")
        notes.append(f"only {n_r} distinct ranges: a2_per_v held at its start value")
    return tuple(k for k in PARAM_NAMES if k in fixed), fixed - asked, notes


def fit(
    data: CalibrationData,
    *,
    start: ThesisParams | None = None,
    loss: str = "linear",
    f_scale: float | None = None,
    fix: Iterable[str] = (),
    max_nfev: int = 500,
    on_eval: Callable[[int], None] | None = None,
) -> CalibrationResult:
    """Fit the 7-parameter model (3.8) with per-experiment offsets.

    Parameters
    ----------
    data
        The frame (:func:`prepare`).
    start
        Parameters to start from (e.g. a scanner config's); the automatic start is
        computed as well and the better one is used.
    loss
        ``linear`` (least squares) or a robust loss of :func:`scipy.optimize.least_squares`.
    f_scale
        Residual scale of a robust loss (um); default twice the robust noise estimate.
    fix
        Parameter names to hold at their start values.
    max_nfev
        Evaluation budget of the solver.
    on_eval
        Called with the running number of model evaluations (progress display).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Unknown loss / parameter, a frame that cannot determine the model, or a
        solver failure.
    """
    t0 = time.perf_counter()
    if loss not in LOSSES:
        raise CalibrationError(f"unknown loss {loss!r}; choose one of {', '.join(LOSSES)}")
    fixed, undetermined, notes = _free_names(data, fix)
    free = tuple(k for k in PARAM_NAMES if k not in fixed)
    mask = np.array([k in free for k in PARAM_NAMES])
    a2_scale = float(np.mean(0.5 * (data.v_max - data.v_min)))
    lo, hi = _z_bounds(a2_scale)
    nfev = [0]

    def count() -> None:
        nfev[0] += 1
        if on_eval is not None:
            on_eval(nfev[0])

    # Held values: the given start's; else, for what the frame cannot determine, neutral
    # defaults (no frequency / range dependence, tau 1 s); else the automatic start's.
    if start is not None:
        held = {k: float(getattr(start, k)) for k in fixed}
    else:
        defaults = {"tau_s": _DEFAULT_TAU_S, "a1": 0.0, "a2_per_v": 0.0}
        held = {k: defaults[k] for k in undetermined}
    auto = auto_start(data, fixed=held)
    for k in fixed:
        held.setdefault(k, float(getattr(auto, k)))
    candidates = [auto]
    if start is not None:
        candidates.append(start)
    best_z, best_cost = None, math.inf
    for cand in candidates:
        z = np.clip(_to_z(cand, a2_scale), lo + 1e-9, hi - 1e-9)
        for k, val in held.items():
            j = PARAM_NAMES.index(k)
            z[j] = _to_z(ThesisParams(**{**_as_dict(cand), k: val}), a2_scale)[j]
        x, _ = _model(data, z, a2_scale, jac=False)
        count()
        c = float(np.sum(_centre(data, data.position_um - x) ** 2))
        if c < best_cost:
            best_z, best_cost = z, c
    assert best_z is not None
    z_full = best_z.copy()

    def full(zf: F64) -> F64:
        out = z_full.copy()
        out[mask] = zf
        return out

    def resid(zf: F64) -> F64:
        count()
        x, _ = _model(data, full(zf), a2_scale, jac=False)
        return _centre(data, x - data.position_um)

    def jac(zf: F64) -> F64:
        _, J = _model(data, full(zf), a2_scale, jac=True)
        assert J is not None
        return _centre(data, J[:, mask])

    kw: dict[str, Any] = {"method": "trf", "x_scale": 1.0, "ftol": 1e-10, "xtol": 1e-10, "gtol": 1e-10}
    try:
        res = least_squares(
            resid, best_z[mask], jac=jac, bounds=(lo[mask], hi[mask]), max_nfev=max_nfev, **kw
        )
    except (ValueError, ModelError, FloatingPointError) as exc:
        raise CalibrationError(f"the fit failed: {exc}") from exc
    z_sol = full(res.x)
    n_exp = data.n_experiments
    jac_for_cov = res.jac
    resid_for_dof = res.fun
    cost = float(res.cost)
    success, message = bool(res.success), str(res.message)
    if loss != "linear":
        x, _ = _model(data, z_sol, a2_scale, jac=False)
        r0 = _centre(data, data.position_um - x)
        scale = f_scale if f_scale is not None else 2.0 * 1.4826 * float(np.median(np.abs(r0)))
        if not scale > 0:
            raise CalibrationError(f"the robust loss needs a residual scale > 0 um, got {scale}")
        starts, counts = data.starts, data.counts
        offs0 = np.add.reduceat(data.position_um - x, starts) / counts

        def resid_r(zc: F64) -> F64:
            count()
            xm, _ = _model(data, full(zc[: mask.sum()]), a2_scale, jac=False)
            return xm + np.repeat(zc[mask.sum() :], counts) - data.position_um

        def jac_r(zc: F64) -> F64:
            _, J = _model(data, full(zc[: mask.sum()]), a2_scale, jac=True)
            assert J is not None
            ind = np.zeros((data.voltage_v.size, n_exp))
            ind[np.arange(data.voltage_v.size), data.index] = 1.0
            return np.hstack([J[:, mask], ind])

        big = np.full(n_exp, np.inf)
        try:
            res = least_squares(
                resid_r,
                np.concatenate([res.x, offs0]),
                jac=jac_r,
                bounds=(np.concatenate([lo[mask], -big]), np.concatenate([hi[mask], big])),
                loss=loss,
                f_scale=scale,
                max_nfev=max_nfev,
                **kw,
            )
        except (ValueError, ModelError, FloatingPointError) as exc:
            raise CalibrationError(f"the robust fit failed: {exc}") from exc
        z_sol = full(res.x[: mask.sum()])
        # Standard errors as if the outliers (beyond 3 robust sigma) had been left out.
        r_fin = np.asarray(res.fun, dtype=np.float64)
        sigma_rob = 1.4826 * float(np.median(np.abs(r_fin)))
        inl = np.abs(r_fin) <= 3.0 * sigma_rob
        jac_for_cov = jac_r(res.x)[inl]
        resid_for_dof = r_fin[inl]
        cost = float(res.cost)
        success, message = bool(res.success), str(res.message)
        notes.append(
            f"robust loss {loss} with f_scale {scale:.4g} um; {int((~inl).sum())} samples "
            f"({100.0 * float((~inl).mean()):.2g} %) beyond 3 robust sigma"
        )

    params = _from_z(z_sol, a2_scale)
    x, _ = _model(data, z_sol, a2_scale, jac=False)
    offsets = np.add.reduceat(data.position_um - x, data.starts) / data.counts
    if loss != "linear":
        offsets = np.asarray(res.x[mask.sum() :], dtype=np.float64)
    resid_um = data.position_um - x - np.repeat(offsets, data.counts)
    err_pct, sigma, rng = _errors(data, x + np.repeat(offsets, data.counts), resid_um, int(mask.sum()))

    # Covariance from the (projected) Jacobian and the residual variance.
    p_free = int(mask.sum())
    dof = max(np.size(resid_for_dof) - p_free - n_exp, 1)
    vals = np.array([getattr(params, k) for k in PARAM_NAMES])
    dz = np.where(_LOG, vals, 1.0)
    dz[5] = 1.0 / a2_scale
    stats = parameter_statistics(
        jac_for_cov,
        float(np.sum(np.asarray(resid_for_dof) ** 2)),
        dof,
        names=PARAM_NAMES,
        free=free,
        z=z_sol,
        lo=lo,
        hi=hi,
        dvalue_dz=dz,
    )
    cond, bounded = stats.condition_number, stats.at_bounds
    warnings = list(notes) + fit_warnings(bounded, cond, params.u_um_per_v, params.b_um_per_v)
    vh = 0.5 * (data.v_max - data.v_min)
    kk = (1.0 - params.a1 * np.exp(-1.0 / (data.frequency_hz * params.tau_s))) * (
        params.a2_per_v * vh + params.a3
    )
    if np.any(kk < 0):
        warnings.append("the creep factor k(f, V) of (3.5) is negative for some experiments")
    if not success:
        warnings.append(f"solver did not converge: {message}")

    exps = tuple(
        ExperimentFit(
            label=data.labels[i],
            axis=data.axes[i],
            path=data.paths[i],
            v_min=float(data.v_min[i]),
            v_max=float(data.v_max[i]),
            frequency_hz=float(data.frequency_hz[i]),
            n_loops=data.n_loops[i],
            n=int(data.counts[i]),
            position_offset_um=float(offsets[i]),
            range_um=float(rng[i]),
            sigma_um=float(sigma[i]),
            fit_error_pct=float(err_pct[i]),
            rms_um=float(np.sqrt(np.mean(resid_um[data.starts[i] : data.starts[i] + data.counts[i]] ** 2))),
        )
        for i in range(n_exp)
    )
    resid_um.setflags(write=False)
    return CalibrationResult(
        params=params,
        stderr=stats.stderr,
        covariance=stats.covariance,
        correlations=stats.correlations,
        free=free,
        fixed=fixed,
        at_bounds=bounded,
        condition_number=cond,
        experiments=exps,
        residuals_um=resid_um,
        cost=cost,
        n=int(resid_um.size),
        dof=stats.dof,
        loss=loss,
        nfev=nfev[0],
        success=success,
        message=message,
        seconds=time.perf_counter() - t0,
        warnings=tuple(warnings),
    )


def _as_dict(p: ThesisParams) -> dict[str, float]:
    return {k: float(getattr(p, k)) for k in PARAM_NAMES}


def calibrate(
    experiments: Sequence[Experiment],
    *,
    start: ThesisParams | None = None,
    loss: str = "linear",
    f_scale: float | None = None,
    fix: Iterable[str] = (),
    skip_loops: int = 0,
    max_samples_per_loop: int | None = 2048,
    on_eval: Callable[[int], None] | None = None,
) -> CalibrationResult:
    """:func:`prepare` the experiments and :func:`fit` them (see there)."""
    data = prepare(experiments, skip_loops=skip_loops, max_samples_per_loop=max_samples_per_loop)
    return fit(data, start=start, loss=loss, f_scale=f_scale, fix=fix, on_eval=on_eval)


# ----------------------------------------------------------------------------------------------- output


def result_json(result: CalibrationResult, *, inputs: Sequence[str] = ()) -> dict[str, Any]:
    """The JSON document of ``piezod calibrate --json`` (keys: docs/formats.md)."""
    return {
        "params": result.values,
        "stderr": dict(result.stderr),
        "fit_error_pct": result.fit_error_pct,
        "experiments": [
            {
                "label": e.label,
                "axis": e.axis,
                "path": e.path,
                "range_v": e.range_v,
                "offset_v": e.offset_v,
                "v_min": e.v_min,
                "v_max": e.v_max,
                "frequency_hz": e.frequency_hz,
                "n_loops": e.n_loops,
                "range_um": e.range_um,
                "position_offset_um": e.position_offset_um,
                "sigma_um": e.sigma_um,
                "rms_um": e.rms_um,
                "fit_error_pct": e.fit_error_pct,
                "n": e.n,
            }
            for e in result.experiments
        ],
        **result.statistics_json(),
        "n_experiments": len(result.experiments),
        "loss": result.loss,
        "inputs": list(inputs),
    }


def calibrated_config(
    result: CalibrationResult,
    *,
    axis: str = "x",
    base: ScannerConfig | None = None,
    inputs: Sequence[str] = (),
    voltage_span_v: tuple[float, float] | None = None,
    name: str = "calibrated",
) -> ScannerConfig:
    """The scanner config with the fitted parameters on ``axis``.

    Parameters
    ----------
    result
        The fit.
    axis
        The calibrated axis.
    base
        Scanner to start from: its limits and other axes are kept, ``axis``'s thesis
        parameters are replaced. Without a base a minimal scanner is written whose
        voltage limits cover ``voltage_span_v`` (only the x axis).
    inputs
        Recording files, for the provenance section.
    voltage_span_v
        Lowest and highest recorded voltage (needed without ``base``).
    name
        Scanner name without ``base``.

    Raises
    ------
    CalibrationError
        The parameters do not fit the config schema, or no base for a non-x axis.
    """
    try:
        thesis = ThesisModelConfig(**result.values)
    except ValueError as exc:
        raise CalibrationError(f"fitted parameters are outside the config limits: {exc}") from exc
    prov: dict[str, Any] = {
        "tool": f"piezod calibrate {__version__}",
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "axis": axis,
        "recordings": list(inputs),
        "n_experiments": len(result.experiments),
        "n_samples": result.n,
        "loss": result.loss,
        "fit_error_pct": round(result.fit_error_pct, 6),
        "stderr": {k: float(f"{v:.6g}") for k, v in result.stderr.items()},
        "fixed": list(result.fixed),
        "condition_number": float(f"{result.condition_number:.4g}"),
        "voltage_range_v": [
            min(e.range_v for e in result.experiments),
            max(e.range_v for e in result.experiments),
        ],
        "frequency_range_hz": [
            min(e.frequency_hz for e in result.experiments),
            max(e.frequency_hz for e in result.experiments),
        ],
    }
    if base is not None:
        if axis not in base.axes:
            raise CalibrationError(f"the base config has no axis {axis!r} (axes: {', '.join(base.axes)})")
        axes = dict(base.axes)
        axes[axis] = base.axes[axis].model_copy(update={"thesis": thesis})
        data = base.model_dump()
        data["axes"] = {k: a.model_dump() for k, a in axes.items()}
        data["calibration"] = prov
        data["notes"] = calibrated_notes(base.notes)
        try:
            return ScannerConfig.model_validate(data)
        except ValueError as exc:
            raise CalibrationError(f"cannot build the calibrated config: {exc}") from exc
    if axis != "x":
        raise CalibrationError(f"calibrating axis {axis!r} needs --config (a scanner with an x axis)")
    if voltage_span_v is None:
        raise CalibrationError("without a base config the recorded voltage span is needed")
    vlo = math.floor(voltage_span_v[0])
    vhi = math.ceil(voltage_span_v[1])
    if vhi <= vlo:
        vhi = vlo + 1
    try:
        ax = AxisConfig(
            voltage_min_v=vlo,
            voltage_max_v=vhi,
            safe_voltage_v=float(min(max(0.0, vlo), vhi)),
            thesis=thesis,
        )
        return ScannerConfig(
            name=name,
            description="written by piezod calibrate from recordings (voltage limits = recorded span)",
            axes={"x": ax},
            calibration=prov,
        )
    except ValueError as exc:
        raise CalibrationError(f"cannot build the calibrated config: {exc}") from exc


__all__ = [
    "LOSSES",
    "PARAM_NAMES",
    "CalibrationData",
    "CalibrationResult",
    "ExperimentFit",
    "auto_start",
    "calibrate",
    "calibrated_config",
    "fit",
    "fit_errors",
    "model_positions",
    "prepare",
    "result_json",
]
