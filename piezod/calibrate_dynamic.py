"""Calibration of the dynamic model (:mod:`piezod.model.dynamic`) from recordings of any waveform.

What is simulated: the whole session, in time order
---------------------------------------------------
The creep elements remember the past for up to ``creep_tau_max_s`` (a day), far longer than
one experiment: a scan at +50 V still relaxes from the scan at -50 V before it. Simulating
each experiment from a guessed state would leave that relaxation unexplained (or need one
free state per slow element and experiment), so the model is run through the *session*:
from rest at ``rest_voltage_v`` at ``t = 0`` through every recorded experiment in the order
of ``t`` (the recording format's ``t`` is continuous over a session), with the unrecorded
stretches between experiments reconstructed the way a calibration frame produces them
(:func:`hil_sim.session.run_session`, the daemon's programs): a move at ``slew_rate_v_per_s``
to the next start voltage, a hold there, then -- for a periodic experiment -- as many settling
loops (the periodic extension of its first recorded loop) as fit into the rest of the gap (at
most ``max_preroll_loops``). Before the first experiment the stage rests at ``rest_voltage_v``
until the move. The start voltage of an experiment is one sample before its first, on the same
slope (or the periodic predecessor after settling loops), so that its turning point is kept.
Per experiment a position offset ``c_e`` (sensor zero, drift) is a nuisance parameter,
eliminated by projection (residuals and Jacobian centred per experiment).

Decimation without changing the hysteresis
------------------------------------------
The hysteresis ODE is rate independent, and along a monotone voltage path its state at the
end depends only on the end points. The fit therefore runs the ODE on a subsequence that
keeps every ``k``-th sample *and* every turning point of the voltage: exact at the kept
samples for any waveform. The creep elements run on the uniform ``k``-sample grid (first-order
hold, exact for a drive linear between grid points; ``k`` gives about
``max_samples_per_loop`` samples per loop of a periodic experiment and at most
``max_samples_per_experiment`` samples otherwise). Holds are one step of their full length,
moves a few dozen steps.

Structure of the fit
--------------------
With ``y = x_h - b V`` the ODE state at rest is 0, so ``x_h = b V + delta Y_alpha`` with
``delta = (b - u) / alpha`` and ``Y_alpha`` the solution for ``delta = 1``; the creep deviations
are linear in the drive, so ``x = (1 + W)(b V + delta Y) + (b E[V] + delta E[Y]) w`` where
``E[.]`` (one column per creep element) does not depend on any parameter but ``alpha``.
``E[V]`` is computed once, ``E[Y]`` once per ``alpha``; the Jacobian is analytic except for
``d/d alpha`` (one extra simulation). Parameters: ``alpha, b, u`` (fitted in logs),
``creep_pct_per_decade`` and ``creep_exponent``; the spread of relaxation times
(``creep_tau_min_s``, ``creep_tau_max_s``, ``creep_per_decade``) is structure, not fitted.
``creep_exponent`` is held at 0 (the logarithmic law) unless the frame spans at least
``min_decades_for_exponent`` decades of time scales, or when asked (``fix``).

Fit error per experiment (2.26)-(2.27): ``sigma_e = sqrt(LSF_e / (n_e - nu))`` relative to the
distance ``Delta x_e`` covered by the fitted positions, in %.

The session layout (:func:`prepare_dynamic`, :class:`DynamicCalibrationData`) lives in
:mod:`piezod.calibrate_data` (re-exported here); the model, its start, the fit and its outputs
stay together here (a little over 800 lines: one model's calibration, end to end); the
statistics every fit returns are :class:`piezod.fitstats.FitResult`.
"""

from __future__ import annotations

import datetime as _dt
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, minimize_scalar
from scipy.special import digamma

from piezod import __version__
from piezod.calibrate_data import MAX_PREROLL_LOOPS, DynamicCalibrationData, ExperimentLayout, prepare_dynamic
from piezod.config import (
    AxisConfig,
    DynamicModelConfig,
    ScannerConfig,
    ThesisModelConfig,
    calibrated_notes,
)
from piezod.errors import CalibrationError, ModelError
from piezod.fitstats import CalibrationFit, fit_warnings, parameter_statistics, solve_linear
from piezod.model.dynamic import (
    MAX_TOTAL_CREEP,
    DynamicParams,
    creep_element_deviations,
    creep_taus,
    creep_weights,
    foh_coefficients,
)
from piezod.model.ode import HysteresisState, hysteresis_step
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: Fitted parameters, in this order.
PARAM_NAMES: tuple[str, ...] = (
    "alpha_per_v",
    "b_um_per_v",
    "u_um_per_v",
    "creep_pct_per_decade",
    "creep_exponent",
)
_LOWER = np.array([math.log(1e-6), math.log(1e-6), math.log(1e-6), 0.0, -0.5])
_UPPER = np.array([math.log(0.5), math.log(99.0), math.log(99.0), 20.0, 0.5])


# ------------------------------------------------------------------------------------------- the model


@dataclass(frozen=True, slots=True)
class CreepStructure:
    """The fixed spread of relaxation times (not fitted)."""

    tau_min_s: float = 1e-3
    tau_max_s: float = 1e5
    per_decade: int = 3

    @property
    def taus_s(self) -> F64:
        """The relaxation times (s)."""
        return creep_taus(self.tau_min_s, self.tau_max_s, self.per_decade)


def _hysteresis_unit(data: DynamicCalibrationData, alpha: float) -> F64:
    """``Y_alpha`` at the grid samples: ``x_h - b V`` of the ODE with ``delta = 1``, from rest.

    ``h = x_h - b V`` obeys ``dh = -alpha (|dV| h + delta dV)``: it depends on ``alpha`` and
    ``delta = (b - u) / alpha`` only, so ``b = 1 + alpha, u = 1`` gives it for any ``alpha > 0``
    (``u = 1 - alpha`` with ``b = 1`` was not a law for ``alpha >= 1`` 1/V, which a session
    spanning a few volts searches).
    """
    v = data.hysteresis_voltage_v
    v0 = data.rest_voltage_v
    b = 1.0 + alpha
    xh, _ = hysteresis_step(HysteresisParams(alpha, b, 1.0), v, HysteresisState(v0, b * v0))
    y: F64 = (xh - b * v)[data.grid_index]
    return y


#: Elements with ``n dt / tau`` up to this are evaluated in closed form (one cumulative sum).
_CLOSED_FORM_SPAN = 400.0


class _Deviations:
    """The creep deviations operator of a session: drive on the grid -> ``E`` at the compared samples.

    Linear in the drive, from rest. Per stretch of uniform ``dt`` the slow elements (``n h <= 400``)
    use the closed form ``e[j] = a^j (a e[-1] + g sum_{l<=j} a^-l dd[l])`` with cached growth
    tables; the fast ones the recursion (:func:`piezod.model.dynamic.creep_element_deviations`).
    The session is simulated once per ``alpha`` in the fit, so the tables pay off.
    """

    def __init__(self, data: DynamicCalibrationData, taus: F64) -> None:
        self.data = data
        self.taus = taus
        self.plans: list[tuple[float, int, int, F64, F64, NDArray[np.bool_], F64 | None]] = []
        for dt_s, start, stop in data.pieces:
            n = stop - start
            a, _, b0 = foh_coefficients(taus, dt_s)
            h = dt_s / taus
            slow = (h * n <= _CLOSED_FORM_SPAN) if n > 1 else np.zeros(taus.size, dtype=bool)
            grow = np.exp(np.outer(np.arange(n, dtype=np.float64), h[slow])) if slow.any() else None
            self.plans.append((dt_s, start, stop, a, -(1.0 - b0), slow, grow))

    def __call__(self, drive: F64, drive_rest: float) -> F64:
        cmp = self.data.compared
        m = self.taus.size
        out = np.empty((cmp.size, m))
        e = np.zeros(m)
        d_prev = drive_rest
        for dt_s, start, stop, a, g, slow, grow in self.plans:
            d = drive[start:stop]
            if stop - start == 1:
                blk = (a * e + g * (float(d[0]) - d_prev))[None, :]
            else:
                blk = np.empty((stop - start, m))
                dd = np.diff(d, prepend=d_prev)
                if grow is not None:
                    acc = np.cumsum(dd[:, None] * grow, axis=0)
                    acc *= g[slow]
                    acc += (a * e)[slow]
                    acc /= grow
                    blk[:, slow] = acc
                fast = ~slow
                if fast.any():
                    blk[:, fast] = creep_element_deviations(self.taus[fast], dt_s, d, d_prev, e[fast])
            lo, hi = np.searchsorted(cmp, [start, stop])
            if hi > lo:
                out[lo:hi] = blk[cmp[lo:hi] - start]
            e = blk[-1]
            d_prev = float(d[-1])
        return out


class _Model:
    """The session model ``x(theta)`` at the compared samples, with cached per-alpha simulations."""

    def __init__(self, data: DynamicCalibrationData, creep: CreepStructure) -> None:
        self.data = data
        self.taus = creep.taus_s
        self.log_taus = np.log(self.taus)
        self.unit_weights = creep_weights(self.taus, 1.0, 0.0)
        v = data.grid_voltage_v
        self.v = v[data.compared]
        self.deviations = _Deviations(data, self.taus)
        self.e_v = self.deviations(v, data.rest_voltage_v)
        self._alpha: float | None = None
        self._y: F64 = np.empty(0)
        self._e_y: F64 = np.empty((0, 0))
        self.simulations = 0

    def hysteresis_parts(self, alpha: float) -> tuple[F64, F64]:
        """``Y_alpha`` and ``E[Y_alpha]`` at the compared samples (cached for the last alpha)."""
        if self._alpha != alpha:
            y = _hysteresis_unit(self.data, alpha)
            self._e_y = self.deviations(y, 0.0)
            self._y = y[self.data.compared]
            self._alpha = alpha
            self.simulations += 1
        return self._y, self._e_y

    def shape(self, beta: float) -> F64:
        """Weights per unit ``gamma`` (``creep_weights`` with ``gamma = 1``)."""
        out: F64 = self.unit_weights * np.exp(beta * self.log_taus) / math.gamma(1.0 - beta)
        return out

    def weights(self, gamma: float, beta: float) -> F64:
        return gamma * self.shape(beta)

    def positions(self, z: F64) -> F64:
        alpha, b, u = np.exp(z[:3])
        w = self.weights(z[3], z[4])
        y, e_y = self.hysteresis_parts(float(alpha))
        delta = (b - u) / alpha
        total = float(w.sum())
        out: F64 = (1.0 + total) * (b * self.v + delta * y) + (b * self.e_v + delta * e_y) @ w
        return out

    def jacobian(self, z: F64) -> F64:
        alpha, b, u = (float(c) for c in np.exp(z[:3]))
        gamma, beta = float(z[3]), float(z[4])
        w = self.weights(gamma, beta)
        total = float(w.sum())
        y, e_y = self.hysteresis_parts(alpha)
        delta = (b - u) / alpha
        hyst_y = (1.0 + total) * y + e_y @ w
        hyst_v = (1.0 + total) * self.v + self.e_v @ w
        # d/d ln(alpha): delta = (b - u) / alpha and Y_alpha change
        step = 1e-6
        y2, e_y2 = self.hysteresis_parts(alpha * math.exp(step))
        dy = ((1.0 + total) * y2 + e_y2 @ w - hyst_y) / step
        J = np.empty((y.size, 5))
        J[:, 0] = -delta * hyst_y + delta * dy
        J[:, 1] = b * (hyst_v + hyst_y / alpha)
        J[:, 2] = -u * hyst_y / alpha
        d_lin = b * self.v + delta * y
        e_lin = b * self.e_v + delta * e_y
        dw_g = self.shape(beta)
        J[:, 3] = float(dw_g.sum()) * d_lin + e_lin @ dw_g
        dw_b = w * (self.log_taus + float(digamma(1.0 - beta)))
        J[:, 4] = float(dw_b.sum()) * d_lin + e_lin @ dw_b
        return J


def _centre(data: DynamicCalibrationData, a: NDArray[np.float64]) -> NDArray[np.float64]:
    return data.centred(a)


# --------------------------------------------------------------------------------------------- start


def _linear_b_delta(data: DynamicCalibrationData, col_b: F64, col_d: F64) -> tuple[float, float, float]:
    """Least squares of ``x = b col_b + delta col_d + c_e``: (rss, b, delta)."""
    A = _centre(data, np.column_stack([col_b, col_d]))
    x = _centre(data, data.position_um)
    sol, _ = solve_linear(A, x)
    r = A @ sol - x
    return float(r @ r), float(sol[0]), float(sol[1])


def auto_start(
    data: DynamicCalibrationData, model: _Model, *, creep_pct: float | None = None, exponent: float = 0.0
) -> F64:
    """A start ``(ln alpha, ln b, ln u, gamma, beta)`` from the data alone.

    ``alpha`` by a grid and a scalar search with the creep of the hysteretic part neglected
    (then the model is linear in ``b`` and ``delta``), then ``gamma`` on a grid (unless
    given) with ``b`` and ``delta`` solved linearly.
    """
    v_span = max(e.v_max - e.v_min for e in data.experiments)
    v_small = min(max(e.v_max - e.v_min, 1e-3) for e in data.experiments)
    gamma0 = 1.0 if creep_pct is None else creep_pct
    w0 = model.weights(gamma0, exponent)
    hyst_v = (1.0 + float(w0.sum())) * model.v + model.e_v @ w0

    def rss_alpha(log_alpha: float) -> float:
        alpha = math.exp(log_alpha)
        y = _hysteresis_unit(data, alpha)[data.compared]
        return _linear_b_delta(data, hyst_v, (1.0 + float(w0.sum())) * y)[0]

    grid = np.linspace(math.log(0.02 / v_span), math.log(min(20.0 / v_small, 0.45)), 32)
    rss = np.array([rss_alpha(float(g)) for g in grid])
    k = int(np.argmin(rss))
    best = minimize_scalar(
        rss_alpha,
        bounds=(float(grid[max(k - 1, 0)]), float(grid[min(k + 1, grid.size - 1)])),
        method="bounded",
        options={"xatol": 1e-4},
    )
    log_alpha = float(best.x) if best.fun <= rss[k] else float(grid[k])
    alpha = math.exp(log_alpha)
    y, e_y = model.hysteresis_parts(alpha)
    gammas = [gamma0] if creep_pct is not None else [0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0]
    best_fit = (math.inf, 0.0, 0.0, gamma0)
    for g in gammas:
        w = model.weights(g, exponent)
        tot = 1.0 + float(w.sum())
        fit = _linear_b_delta(data, tot * model.v + model.e_v @ w, tot * y + e_y @ w)
        if fit[0] < best_fit[0]:
            best_fit = (fit[0], fit[1], fit[2], g)
    _, b, delta, gamma = best_fit
    if not (b > 0 and delta > 0):
        raise CalibrationError(
            "the data show no hysteresis of the modelled orientation (trace below retrace): "
            f"b = {b:.4g} um/V, (b - u)/alpha = {delta:.4g} um"
        )
    u = max(b - alpha * delta, 1e-3 * b)
    return np.array([log_alpha, math.log(b), math.log(u), gamma, exponent])


# ----------------------------------------------------------------------------------------------- fit


@dataclass(frozen=True, eq=False)
class DynamicExperimentFit:
    """Fit summary of one experiment.

    Attributes
    ----------
    layout
        How it entered the session (kind, time, stride, reconstructed gap).
    n
        Compared samples.
    position_offset_um
        Fitted position offset ``c_e``.
    range_um
        Distance covered by the fitted positions (``Delta x_e`` of (2.27)).
    sigma_um
        ``sigma_e`` of (2.26).
    fit_error_pct
        ``100 sigma_e / Delta x_e`` (2.27).
    rms_um
        RMS residual.
    """

    layout: ExperimentLayout
    n: int
    position_offset_um: float
    range_um: float
    sigma_um: float
    fit_error_pct: float
    rms_um: float

    @property
    def label(self) -> str:
        """Experiment label."""
        return self.layout.label


@dataclass(frozen=True, eq=False, kw_only=True)
class DynamicCalibrationResult(CalibrationFit[DynamicExperimentFit]):
    """Result of :func:`fit_dynamic`: the shared :class:`~piezod.fitstats.FitResult` (standard
    errors, covariance, correlations, residuals, condition, bounds, ``n``, ``dof``, solver
    status) and the dynamic model's parameters.

    Attributes
    ----------
    params
        The fitted model (with the creep structure used).
    experiments
        Per-experiment summaries, in time order.
    simulations
        Runs of the session's ODE + creep for new ``alpha``.
    """

    param_names: ClassVar[tuple[str, ...]] = PARAM_NAMES

    params: DynamicParams
    simulations: int


def _to_z(p: DynamicParams) -> F64:
    return np.array(
        [
            math.log(p.alpha_per_v),
            math.log(p.b_um_per_v),
            math.log(p.u_um_per_v),
            p.creep_pct_per_decade,
            p.creep_exponent,
        ]
    )


def fit_dynamic(
    data: DynamicCalibrationData,
    *,
    creep: CreepStructure | None = None,
    start: DynamicParams | None = None,
    fix: Iterable[str] = (),
    min_decades_for_exponent: float = 2.0,
    max_nfev: int = 200,
    on_eval: Callable[[int], None] | None = None,
) -> DynamicCalibrationResult:
    """Fit the dynamic model to a prepared session by least squares with per-experiment offsets.

    Parameters
    ----------
    data
        The session (:func:`prepare_dynamic`).
    creep
        Spread of the relaxation times (default: that of ``start``, else 1 ms ... 1e5 s, 3 per decade).
    start
        Parameters to start from (e.g. a config's); the automatic start is computed as well
        and the better one is used. Held parameters take its values (else the automatic start's;
        ``creep_exponent`` 0).
    fix
        Names of :data:`PARAM_NAMES` to hold.
    min_decades_for_exponent
        ``creep_exponent`` is held at its start value unless the frame's time scales (a quarter
        of the fastest loop to the session length) span at least this many decades.
    max_nfev
        Evaluation budget of the solver.
    on_eval
        Called with the running number of model evaluations (progress display).

    Raises
    ------
    CalibrationError
        Unknown names, data without hysteresis, a solver failure or parameters outside the
        model's domain.
    """
    t0 = time.perf_counter()
    fixed = set(fix)
    unknown = fixed - set(PARAM_NAMES)
    if unknown:
        raise CalibrationError(f"unknown parameter(s) to fix: {', '.join(sorted(unknown))}")
    warnings: list[str] = []
    short_s, long_s = data.time_scales_s()
    decades = math.log10(long_s / short_s) if short_s > 0 else 0.0
    if "creep_exponent" not in fixed and decades < min_decades_for_exponent:
        fixed.add("creep_exponent")
        warnings.append(
            f"the frame spans {decades:.1f} decades of time: creep_exponent held at its start value"
        )
    if creep is None:
        creep = (
            CreepStructure(start.creep_tau_min_s, start.creep_tau_max_s, start.creep_per_decade)
            if start is not None
            else CreepStructure()
        )
    model = _Model(data, creep)
    nfev = [0]

    def count() -> None:
        nfev[0] += 1
        if on_eval is not None:
            on_eval(nfev[0])

    exponent0 = start.creep_exponent if start is not None else 0.0
    gamma_held = (
        start.creep_pct_per_decade if (start is not None and "creep_pct_per_decade" in fixed) else None
    )
    try:
        z_auto = auto_start(data, model, creep_pct=gamma_held, exponent=exponent0)
    except (ModelError, FloatingPointError) as exc:
        raise CalibrationError(f"the automatic start failed: {exc}") from exc
    candidates = [z_auto]
    if start is not None:
        z_start = _to_z(start)
        for k in fixed:
            j = PARAM_NAMES.index(k)
            z_auto[j] = z_start[j]
        candidates.append(z_start)
    lo, hi = _LOWER, _UPPER
    best_z, best_cost = candidates[0], math.inf
    for cand in candidates:
        z = np.clip(cand, lo + 1e-9, hi - 1e-9)
        count()
        c = float(np.sum(_centre(data, model.positions(z) - data.position_um) ** 2))
        if c < best_cost:
            best_z, best_cost = z, c
    free = tuple(k for k in PARAM_NAMES if k not in fixed)
    mask = np.array([k in free for k in PARAM_NAMES])
    z_full = best_z.copy()

    def full(zf: F64) -> F64:
        out = z_full.copy()
        out[mask] = zf
        return out

    def resid(zf: F64) -> F64:
        count()
        return _centre(data, model.positions(full(zf)) - data.position_um)

    def jac(zf: F64) -> F64:
        return _centre(data, model.jacobian(full(zf))[:, mask])

    try:
        res = least_squares(
            resid,
            best_z[mask],
            jac=jac,
            bounds=(lo[mask], hi[mask]),
            method="trf",
            x_scale="jac",
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-12,
            max_nfev=max_nfev,
        )
    except (ValueError, ModelError, FloatingPointError) as exc:
        raise CalibrationError(f"the fit failed: {exc}") from exc
    z_sol = full(res.x)
    alpha, b, u = (float(c) for c in np.exp(z_sol[:3]))
    try:
        params = DynamicParams(
            alpha,
            b,
            u,
            float(z_sol[3]),
            float(z_sol[4]),
            creep.tau_min_s,
            creep.tau_max_s,
            creep.per_decade,
        )
    except ModelError as exc:
        raise CalibrationError(f"the fitted parameters leave the model's domain: {exc}") from exc
    if params.total_creep >= MAX_TOTAL_CREEP:  # pragma: no cover - DynamicParams checks it
        raise CalibrationError("fitted creep too large")

    x = model.positions(z_sol)
    # the experiment's mean offset is reported; its groups' offsets are eliminated
    offsets = np.add.reduceat(data.position_um - x, data.starts) / data.counts
    resid_um = _centre(data, data.position_um - x)
    fitted = data.position_um - resid_um
    p_free = int(mask.sum())
    lsf = np.add.reduceat(resid_um**2, data.starts)
    sigma = np.sqrt(lsf / np.maximum(data.counts - p_free, 1))
    rng = np.maximum.reduceat(fitted, data.starts) - np.minimum.reduceat(fitted, data.starts)
    err_pct = 100.0 * sigma / np.where(rng > 0, rng, np.nan)
    rms = np.sqrt(lsf / data.counts)

    n_exp = data.n_experiments
    dof = max(resid_um.size - p_free - int(np.unique(data.groups()).size), 1)
    stats = parameter_statistics(
        res.jac,
        float(resid_um @ resid_um),
        dof,
        names=PARAM_NAMES,
        free=free,
        z=z_sol,
        lo=lo,
        hi=hi,
        dvalue_dz=np.array([alpha, b, u, 1.0, 1.0]),  # d value / d z
    )
    cond, bounded = stats.condition_number, stats.at_bounds
    warnings += fit_warnings(bounded, cond, u, b)
    if not res.success:
        warnings.append(f"solver did not converge: {res.message}")
    exps = tuple(
        DynamicExperimentFit(
            layout=data.experiments[i],
            n=int(data.counts[i]),
            position_offset_um=float(offsets[i]),
            range_um=float(rng[i]),
            sigma_um=float(sigma[i]),
            fit_error_pct=float(err_pct[i]),
            rms_um=float(rms[i]),
        )
        for i in range(n_exp)
    )
    resid_um.setflags(write=False)
    return DynamicCalibrationResult(
        params=params,
        stderr=stats.stderr,
        covariance=stats.covariance,
        correlations=stats.correlations,
        free=free,
        fixed=tuple(k for k in PARAM_NAMES if k in fixed),
        at_bounds=bounded,
        condition_number=cond,
        experiments=exps,
        residuals_um=resid_um,
        cost=float(res.cost),
        n=int(resid_um.size),
        dof=stats.dof,
        nfev=nfev[0],
        simulations=model.simulations,
        success=bool(res.success),
        message=str(res.message),
        seconds=time.perf_counter() - t0,
        warnings=tuple(warnings),
    )


def calibrate_dynamic(
    experiments: Sequence[Experiment],
    *,
    creep: CreepStructure | None = None,
    start: DynamicParams | None = None,
    fix: Iterable[str] = (),
    max_samples_per_loop: int = 512,
    max_samples_per_experiment: int = 8192,
    slew_rate_v_per_s: float = 2000.0,
    rest_voltage_v: float = 0.0,
    max_preroll_loops: int = MAX_PREROLL_LOOPS,
    on_eval: Callable[[int], None] | None = None,
) -> DynamicCalibrationResult:
    """:func:`prepare_dynamic` the experiments and :func:`fit_dynamic` them (see there)."""
    data = prepare_dynamic(
        experiments,
        max_samples_per_loop=max_samples_per_loop,
        max_samples_per_experiment=max_samples_per_experiment,
        slew_rate_v_per_s=slew_rate_v_per_s,
        rest_voltage_v=rest_voltage_v,
        max_preroll_loops=max_preroll_loops,
    )
    return fit_dynamic(data, creep=creep, start=start, fix=fix, on_eval=on_eval)


# -------------------------------------------------------------------------------------------- output


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def result_json(result: DynamicCalibrationResult, *, inputs: Sequence[str] = ()) -> dict[str, Any]:
    """The JSON document of a dynamic calibration (keys of docs/formats.md, plus more)."""
    p = result.params
    return {
        "model": "dynamic",
        "params": result.values,
        "creep_structure": {
            "creep_tau_min_s": p.creep_tau_min_s,
            "creep_tau_max_s": p.creep_tau_max_s,
            "creep_per_decade": p.creep_per_decade,
            "elements": int(p.taus_s.size),
            "total_creep": p.total_creep,
        },
        "stderr": dict(result.stderr),
        "fit_error_pct": result.fit_error_pct,
        "experiments": [
            {
                "label": e.label,
                "axis": e.layout.axis,
                "path": e.layout.path,
                "kind": e.layout.kind,
                "t_start_s": e.layout.t_start_s,
                "duration_s": e.layout.duration_s,
                "range_v": e.layout.v_max - e.layout.v_min,
                "offset_v": 0.5 * (e.layout.v_max + e.layout.v_min),
                "v_min": e.layout.v_min,
                "v_max": e.layout.v_max,
                "frequency_hz": _finite(e.layout.frequency_hz),
                "stride": e.layout.stride,
                "gap_s": e.layout.gap_s,
                "preroll_loops": e.layout.preroll_loops,
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
        "simulations": result.simulations,
        "inputs": list(inputs),
    }


def dynamic_model_config(params: DynamicParams) -> DynamicModelConfig:
    """The ``dynamic:`` config section of ``params``.

    Raises
    ------
    CalibrationError
        The values do not fit the config schema.
    """
    try:
        return DynamicModelConfig(
            alpha_per_v=params.alpha_per_v,
            b_um_per_v=params.b_um_per_v,
            u_um_per_v=params.u_um_per_v,
            creep_pct_per_decade=params.creep_pct_per_decade,
            creep_exponent=params.creep_exponent,
            creep_tau_min_s=params.creep_tau_min_s,
            creep_tau_max_s=params.creep_tau_max_s,
            creep_per_decade=params.creep_per_decade,
        )
    except ValueError as exc:
        raise CalibrationError(f"fitted dynamic parameters are outside the config limits: {exc}") from exc


def calibrated_config(
    result: DynamicCalibrationResult,
    *,
    axis: str = "x",
    base: ScannerConfig | None = None,
    thesis: ThesisParams | None = None,
    inputs: Sequence[str] = (),
    voltage_span_v: tuple[float, float] | None = None,
    name: str = "calibrated",
) -> ScannerConfig:
    """The scanner config with ``model: dynamic`` and the fitted ``dynamic:`` section on ``axis``.

    The ``thesis:`` section is kept (from ``base``, or ``thesis`` when given, which replaces
    it): the engine still plans periodic scans with it. Provenance goes to
    ``calibration.dynamic`` (other keys of ``calibration`` are kept).

    Parameters
    ----------
    result
        The dynamic fit.
    axis
        The calibrated axis.
    base
        Scanner to start from (limits, other axes, thesis parameters kept).
    thesis
        Thesis parameters for the axis (required without ``base``).
    inputs
        Recording files, for the provenance.
    voltage_span_v
        Lowest and highest recorded voltage (needed without ``base``).
    name
        Scanner name without ``base``.

    Raises
    ------
    CalibrationError
        The parameters do not fit the config schema, or the base / thesis parameters are missing.
    """
    section = dynamic_model_config(result.params)
    prov: dict[str, Any] = {
        "tool": f"piezod calibrate {__version__} (dynamic model)",
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "axis": axis,
        "recordings": list(inputs),
        "n_experiments": len(result.experiments),
        "n_samples": result.n,
        "fit_error_pct": round(result.fit_error_pct, 6),
        "stderr": {k: float(f"{v:.6g}") for k, v in result.stderr.items()},
        "fixed": list(result.fixed),
        "condition_number": float(f"{result.condition_number:.4g}"),
    }
    thesis_cfg = None
    if thesis is not None:
        try:
            thesis_cfg = ThesisModelConfig(**{k: getattr(thesis, k) for k in ThesisModelConfig.model_fields})
        except ValueError as exc:
            raise CalibrationError(f"thesis parameters are outside the config limits: {exc}") from exc
    if base is not None:
        if axis not in base.axes:
            raise CalibrationError(f"the base config has no axis {axis!r} (axes: {', '.join(base.axes)})")
        update: dict[str, Any] = {"model": "dynamic", "dynamic": section}
        if thesis_cfg is not None:
            update["thesis"] = thesis_cfg
        data = base.model_dump()
        data["axes"][axis] = base.axes[axis].model_copy(update=update).model_dump()
        data["calibration"] = {**(base.calibration or {}), "dynamic": prov}
        data["notes"] = calibrated_notes(base.notes)
        try:
            return ScannerConfig.model_validate(data)
        except ValueError as exc:
            raise CalibrationError(f"cannot build the calibrated config: {exc}") from exc
    if thesis_cfg is None:
        raise CalibrationError("without a base config the thesis parameters are needed (thesis=...)")
    if axis != "x":
        raise CalibrationError(f"calibrating axis {axis!r} needs a base config (a scanner with an x axis)")
    if voltage_span_v is None:
        raise CalibrationError("without a base config the recorded voltage span is needed")
    vlo = math.floor(voltage_span_v[0])
    vhi = max(math.ceil(voltage_span_v[1]), vlo + 1)
    try:
        ax = AxisConfig(
            voltage_min_v=vlo,
            voltage_max_v=vhi,
            safe_voltage_v=float(min(max(0.0, vlo), vhi)),
            model="dynamic",
            thesis=thesis_cfg,
            dynamic=section,
        )
        return ScannerConfig(
            name=name,
            description="written by piezod calibrate from recordings (voltage limits = recorded span)",
            axes={"x": ax},
            calibration={"dynamic": prov},
        )
    except ValueError as exc:
        raise CalibrationError(f"cannot build the calibrated config: {exc}") from exc


__all__ = [
    "PARAM_NAMES",
    "CreepStructure",
    "DynamicCalibrationData",
    "DynamicCalibrationResult",
    "DynamicExperimentFit",
    "ExperimentLayout",
    "auto_start",
    "calibrate_dynamic",
    "calibrated_config",
    "dynamic_model_config",
    "fit_dynamic",
    "prepare_dynamic",
    "result_json",
]
