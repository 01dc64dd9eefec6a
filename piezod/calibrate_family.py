"""Calibration of the model family (:mod:`piezod.model.family`) and the choice of model by held-out data.

The session is laid out exactly as for the dynamic model (:func:`piezod.calibrate_dynamic.prepare_dynamic`:
every recorded experiment in time order, the unrecorded moves, holds and settling loops
reconstructed, the rate-independent hysteresis run on a subsequence that keeps every turning
point). On it the family's position is

    x = x_c + kappa x_c^2,    x_c = (1 + W) x_h + E[x_h] w,    x_h = F theta

with ``F`` the hysteresis features at the compared samples -- ``[V, P_r1[V], ..., P_rm[V]]`` for
Prandtl-Ishlinskii (plays with thresholds spread over the recorded voltage span), ``[V, Y_alpha]``
for Coleman-Hodgdon -- and ``E[.]`` the creep element deviations (linear in the drive, one column
per relaxation time). Given the creep weights ``w`` the position is linear in ``theta`` and
``kappa``; given ``theta`` it is linear in ``w``. The fit alternates the two bounded linear
least-squares problems (:func:`solve_linear`: non-negative ``theta`` and ``w``, Tikhonov
regularisation of the creep spectrum, one position offset per experiment eliminated by
projection) until the residual stops falling; Coleman-Hodgdon's ``alpha`` is an outer bounded
scalar search. The relaxation times are log-spaced, ``per_decade`` per decade, from 0.1 ms
(well below the shortest loop time) to the session length: the data decide the spectrum.

Choosing the model
------------------
:func:`choose_model` fits every candidate (the laws; and any further candidates the caller
evaluates, such as the dynamic model) on the *training* experiments and compares the RMS of the
predictions on the *held-out* experiments (every ``holdout_every``-th experiment, spread over
ranges, rates and offsets), which the fit never saw. The best one is refitted on all
experiments. There is no default model.

Over 800 lines (about 900) because the features, the alternating and joint fits and the held-out
choice all work on one private layout of the session (``_Session``: compared rows, centring,
creep deviations); the next split is the choice (:class:`ModelChoice`, :func:`choose_model`) into
its own module once that layout is public.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, minimize, minimize_scalar

from piezod.calibrate_dynamic import (
    DynamicCalibrationData,
    _centre,
    _Deviations,
    _hysteresis_unit,
)
from piezod.config import FamilyModelConfig
from piezod.errors import CalibrationError, ModelError
from piezod.fitstats import FitResult, solve_linear
from piezod.model import kernels
from piezod.model.aftereffect import AfterEffect
from piezod.model.boucwen import (
    MIN_SLOPE_FRACTION,
    BoucWenParams,
    boucwen_forward,
    boucwen_rest_state,
    unit_hysteresis,
)
from piezod.model.domainwall import DomainWallParams, domainwall_rest_state, session_walls
from piezod.model.dynamic import MAX_TOTAL_CREEP
from piezod.model.family import CREEP_DRIVERS, MAX_STIFFNESS_PCT_PER_UM, CreepSpectrum, FamilyParams
from piezod.model.gplay import (
    GeneralisedPlayParams,
    basis_features,
    gplay_forward,
    gplay_rest_state,
    play_outputs,
)
from piezod.model.params import HysteresisParams
from piezod.model.play import PlayParams, PlayState, play_forward

F64 = NDArray[np.float64]

LAWS: tuple[str, ...] = (
    "prandtl-ishlinskii",
    "generalised-play",
    "coleman-hodgdon",
    "bouc-wen",
    "domain-wall",
)
#: Relay-centre nodes of the generalised play law's density (its centre dependence is piecewise
#: linear between them: 3 nodes allow a density that bends once over the recorded span).
GP_NODES = 3
#: Finest centre grid the choice tries (:func:`choose_model`). On a Krasnosel'skii-Pokrovskii
#: stage 5 nodes predicted 3x better than 3 and took the 0.2 Hz line's length error from -0.113 %
#: to -0.020 %; the law's per-sample inverse costs 1.33x at 5 nodes and 1.80x at 9 (about 167 ns
#: of the 150 ns budget; docs/model-family.md 6.2bo).
MAX_GP_NODES = 5
#: Weight of the generalised play law's penalty on its centre dependence (:func:`_centre_smoothing`).
GP_CENTRE_SMOOTHING = 0.0
#: Family members whose held-out RMS is within this fraction of the best one's are a tie, and the
#: one with the fewest coefficients is chosen: on three stages whose law is Prandtl-Ishlinskii the
#: generalised play law (its generalisation, three times the coefficients) predicted 0.9-1.4 % better
#: and verified no better or worse (the sensorless images: -0.22 % against -0.13 % inside).
CHOICE_TIE_FRACTION = 0.02
#: Play operators of the play laws unless the choice refines them.
DEFAULT_PLAYS = 32
#: Laws built from play operators, whose resolution (the number of plays) the choice refines.
PLAY_LAWS: tuple[str, ...] = ("prandtl-ishlinskii", "generalised-play")
#: Laws that may carry an after-effect (:mod:`piezod.model.aftereffect`), with voltage-driven creep.
AFTER_EFFECT_LAWS: tuple[str, ...] = ("generalised-play", "domain-wall")
#: Finest play grid the choice tries: the per-sample inverse of a play law grows with its plays
#: (Prandtl-Ishlinskii with voltage creep and every runtime part: ~100 ns at 64, ~170 ns at 128).
MAX_PLAYS = 64


def member_name(
    law: str, driver: str, plays: int | None = None, nodes: int | None = None, after_effect: bool = False
) -> str:
    """The choice's name of a family member:
    ``family/<law>[/<n>-plays][/<k>-nodes][/after-effect][/voltage-creep]`` (the play count and
    the generalised play law's centre nodes only when they are not the choice's defaults)."""
    return (
        f"family/{law}"
        + (f"/{plays}-plays" if plays else "")
        + (f"/{nodes}-nodes" if nodes else "")
        + ("/after-effect" if after_effect else "")
        + ("/voltage-creep" if driver == "voltage" else "")
    )


def member_after_effect(name: str) -> bool:
    """Whether a :func:`member_name` has the generalised play law's after-effect."""
    return "after-effect" in name.split("/")


def _named_count(parts: Sequence[str], suffix: str) -> int | None:
    """The ``<n>`` of a :func:`member_name`'s ``<n><suffix>`` part, None when it has none."""
    return next((int(p.removesuffix(suffix)) for p in parts if p.endswith(suffix)), None)


def member_nodes(name: str) -> int:
    """Centre nodes of a :func:`member_name`'s generalised play law (:data:`GP_NODES` unless named)."""
    return _named_count(name.split("/"), "-nodes") or GP_NODES


def parse_member(name: str) -> tuple[str, str, int | None] | None:
    """``(law, creep driver, plays or None)`` of a :func:`member_name`; None for another candidate."""
    parts = name.split("/")
    if len(parts) < 2 or parts[0] != "family" or parts[1] not in LAWS:
        return None
    driver = "voltage" if parts[-1] == "voltage-creep" else "position"
    return parts[1], driver, _named_count(parts[2:], "-plays")


#: Longest drive lag the fit considers (s).
_MAX_LAG_S = 0.05
#: Bound on the static map's ``kappa`` in the fits (the model's own limit). Unbounded, a law whose
#: features include a static map of the voltage (the generalised play law's reversible part) trades
#: ``kappa x_c^2`` against them without limit: the alternation then diverged on a unipolar stack.
_MAX_KAPPA = MAX_STIFFNESS_PCT_PER_UM / 200.0


# ------------------------------------------------------------------------------ the shared linear path


# solve_linear: the one linear least-squares path, in piezod.fitstats beside the fit-result type


# ------------------------------------------------------------------------------------------ features


def _play_features(data: DynamicCalibrationData, thresholds: F64) -> F64:
    """``[V, P_r1[V], ...]`` at the grid samples, from rest at the rest voltage."""
    v = data.hysteresis_voltage_v
    unit = PlayParams(1.0, 1.0, tuple(map(float, thresholds)), tuple(0.0 for _ in thresholds))
    r = unit.r
    state = PlayState(data.rest_voltage_v, np.full(r.size, data.rest_voltage_v), 0.0)
    # play outputs: run the forward law per play (weights one-hot) through the vectorised runs
    out = np.empty((data.grid_index.size, r.size + 1))
    out[:, 0] = v[data.grid_index]
    p = state.plays_v
    from piezod.model.play import _runs

    starts, dirs = _runs(v, state.voltage_v)
    bounds = np.append(starts, v.size)
    plays = np.empty((r.size, v.size))
    for k, direction in enumerate(dirs):
        seg = v[bounds[k] : bounds[k + 1]]
        if direction > 0:
            blk = np.maximum(p[:, None], seg[None, :] - r[:, None])
        elif direction < 0:
            blk = np.minimum(p[:, None], seg[None, :] + r[:, None])
        else:
            blk = np.repeat(p[:, None], seg.size, axis=1)
        plays[:, bounds[k] : bounds[k + 1]] = blk
        p = blk[:, -1]
    out[:, 1:] = plays[:, data.grid_index].T
    return out


def default_nodes(data: DynamicCalibrationData, count: int = GP_NODES) -> F64:
    """Relay-centre nodes evenly over the recorded voltage span (generalised play law)."""
    v = data.grid_voltage_v[data.compared]
    lo, hi = float(np.min(v)), float(np.max(v))
    if not hi > lo:
        raise CalibrationError("the recordings span no voltage: nothing to fit a hysteresis law to")
    return np.linspace(lo, hi, max(2, count))


def hysteresis_times_s(data: DynamicCalibrationData) -> F64:
    """The time (s, from the session's start) of every sample of ``data.hysteresis_voltage_v``:
    the grid samples' from the pieces' intervals, the turning points between them interpolated."""
    step = np.empty(data.grid_index.size)
    for dt_s, start, stop in data.pieces:
        step[start:stop] = dt_s
    out: F64 = np.interp(
        np.arange(data.hysteresis_voltage_v.size, dtype=np.float64), data.grid_index, np.cumsum(step)
    )
    return out


#: Most relaxation steps between two samples of a session (:func:`session_play_outputs`): a slow
#: ramp's steps then grow beyond the after-effect's interval.
AE_MAX_STEPS = 256


def session_play_outputs(
    data: DynamicCalibrationData, thresholds: F64, after_effect: AfterEffect | None = None
) -> F64:
    """Play outputs at every sample of ``data.hysteresis_voltage_v`` from rest, shape ``(p, n)``;
    with ``after_effect`` the memory relaxes between the samples as the runtime model's does."""
    v = data.hysteresis_voltage_v
    rest = data.rest_voltage_v
    start = PlayState(rest, np.full(thresholds.size, rest), 0.0)
    if after_effect is None:
        plays, _ = play_outputs(thresholds, v, start)
        return plays
    out = np.empty((thresholds.size, v.size))
    kernels.timed_relax_outputs(
        hysteresis_times_s(data),
        v,
        np.ascontiguousarray(thresholds, dtype=np.float64),
        start.plays_v.copy(),
        rest,
        0.0,
        after_effect.interval_s,
        after_effect.time_s,
        after_effect.fluctuation_v,
        AE_MAX_STEPS,
        out,
    )
    return out


def _gplay_features(
    data: DynamicCalibrationData, thresholds: F64, nodes: F64, after_effect: AfterEffect | None = None
) -> tuple[F64, F64, F64]:
    """``[V, H_{0,0}, ..., H_{p,K-1}]`` at the grid samples from rest, their rest values, and the
    voltage-creep scale per column (the rest slope at 0 V each column contributes)."""
    v = data.hysteresis_voltage_v
    rest = data.rest_voltage_v
    plays = session_play_outputs(data, thresholds, after_effect)
    idx = data.grid_index
    f = np.column_stack([v[idx], basis_features(v[idx], plays[:, idx], nodes)])
    f_rest = np.concatenate(
        [[rest], basis_features(np.array([rest]), np.full((thresholds.size, 1), rest), nodes)[0]]
    )
    hat0 = np.array([np.interp(0.0, nodes, np.eye(nodes.size)[k]) for k in range(nodes.size)])
    slope = np.concatenate([[1.0], np.tile(hat0, thresholds.size + 1)])
    return f, f_rest, slope


def _centre_smoothing(s: _Session, f_grid: F64, rows: int, nodes: int, weight: float) -> F64 | None:
    """Penalty rows on ``mu_{i,k+1} - mu_{i,k}`` (the generalised play law's centre dependence).

    Each row is scaled by the RMS norm of its features on the training data, so ``weight = 1``
    makes a density change cost about what the fit gains from that feature: the law stays a
    Prandtl-Ishlinskii law unless the data show a centre dependence clearly (a record with one
    excitation, such as the P-885 identification run, cannot tell the two apart and a free
    density then extrapolates badly to other loops).
    """
    if weight <= 0.0:
        return None
    fc = _centre(s.data, f_grid[s.data.compared])[s.train_rows]
    norms = np.linalg.norm(fc, axis=0)
    out = np.zeros((rows * (nodes - 1), f_grid.shape[1]))
    for i in range(rows):
        cols = 1 + i * nodes + np.arange(nodes)
        scale = math.sqrt(weight) * float(np.sqrt(np.mean(norms[cols] ** 2)))
        for k in range(nodes - 1):
            out[i * (nodes - 1) + k, cols[k]] = -scale
            out[i * (nodes - 1) + k, cols[k + 1]] = scale
    return out


def default_thresholds(data: DynamicCalibrationData, count: int, spacing: str = "uniform") -> F64:
    """Play half-widths up to half the recorded voltage span.

    ``uniform`` (default): evenly spaced; ``geometric``: log-spaced from 1/200 of the span, dense
    near zero; ``mixed``: a quarter log-spaced from 1/200 of the span up to the first even step,
    the rest evenly spaced. (``mixed`` fitted ``pi-stage`` as well as ``uniform`` but made the
    alternation on the real P-885 data stall after one step: 0.35 um against 0.20 um.)
    """
    v = data.grid_voltage_v[data.compared]
    span = float(np.max(v) - np.min(v))
    if not span > 0.0:
        raise CalibrationError("the recordings span no voltage: nothing to fit a hysteresis law to")
    top = 0.5 * span * count / (count + 1)
    if spacing == "geometric":
        return np.geomspace(span / 200.0, top, count)
    if spacing == "mixed":
        n_even = count - count // 4
        small = np.geomspace(span / 200.0, top / n_even, count // 4, endpoint=False)
        return np.concatenate([small, top * np.arange(1, n_even + 1) / n_even])
    if spacing != "uniform":
        raise CalibrationError(f"unknown threshold spacing {spacing!r} (uniform, geometric, mixed)")
    return 0.5 * span * np.arange(1, count + 1) / (count + 1)


def default_taus(data: DynamicCalibrationData, per_decade: int = 2, tau_min_s: float = 1e-4) -> F64:
    """Log-spaced relaxation times from ``tau_min_s`` to the session length."""
    _, session = data.time_scales_s()
    tau_max = max(10.0 * tau_min_s, session)
    count = max(2, round(math.log10(tau_max / tau_min_s) * per_decade) + 1)
    return np.logspace(math.log10(tau_min_s), math.log10(tau_max), count)


# ---------------------------------------------------------------------------------------------- fit


@dataclass(frozen=True, eq=False, kw_only=True)
class FamilyFit(FitResult):
    """A fitted member of the family: the shared :class:`~piezod.fitstats.FitResult` (training
    residuals, ``n``, ``dof``, AIC/BIC, the held-out RMS) and the model's parameters.

    The family's fit is an alternation of regularised linear problems, not one Jacobian at a
    solution: it computes no parameter standard errors (:attr:`has_errors` is false); ``cost``
    is half the training sum of squares (the creep spectrum's regularisation not included),
    ``nfev`` counts alternations and joint Gauss-Newton steps.

    Attributes
    ----------
    params
        The frozen model parameters.
    heldout_residuals_um
        Measured minus fitted position on the held-out rows (offsets removed per experiment;
        empty without held-out experiments): what :attr:`heldout_rms_um` is the RMS of.
    """

    params: FamilyParams
    heldout_residuals_um: F64 = field(default_factory=lambda: np.zeros(0))

    @property
    def law(self) -> str:
        """The hysteresis law."""
        return self.params.law

    @property
    def rms_um(self) -> float:
        """RMS residual on the experiments it was fitted to (um, offsets removed per experiment)."""
        return self.residual_rms_um

    @property
    def iterations(self) -> int:
        """Alternations and joint Gauss-Newton steps until convergence."""
        return self.nfev


class _Session:
    """Cached pieces of a session for repeated fits (features, deviations operator, centring)."""

    def __init__(
        self,
        data: DynamicCalibrationData,
        taus: F64,
        train: NDArray[np.bool_],
        skip_s: float = 0.0,
        max_lag_s: float = _MAX_LAG_S,
        max_kappa: float = _MAX_KAPPA,
        max_creep: float = MAX_TOTAL_CREEP,
        history: NDArray[np.bool_] | None = None,
    ) -> None:
        self.data = data
        self.max_lag_s = max_lag_s
        self.max_kappa = max_kappa
        self.max_creep = max_creep
        self.taus = taus
        self.dev = _Deviations(data, taus)
        self.y = data.position_um
        exp_of_row = np.repeat(np.arange(data.n_experiments), data.counts)
        keep = settled_rows(data, skip_s)
        if history is not None:
            keep &= ~history[exp_of_row]
        self.train_rows = train[exp_of_row] & keep
        self.test_rows = ~train[exp_of_row] & keep
        self.yc = _centre(data, self.y)
        # Tikhonov on the creep weights: second differences over log tau plus a small ridge
        m = taus.size
        d2 = np.diff(np.eye(m), n=2, axis=0) if m > 2 else np.zeros((0, m))
        self.creep_reg = np.vstack([d2, 0.1 * np.eye(m)])

    def creep_columns(self, features: F64) -> list[F64]:
        """``E[F_j]`` at the compared samples for every feature column (shape ``(n_cmp, m)`` each)."""
        rest = self.data.rest_voltage_v
        return [
            self.dev(features[:, j], rest if j < features.shape[1] else 0.0) for j in range(features.shape[1])
        ]


def _dead(columns: F64) -> NDArray[np.bool_]:
    """Columns (centred, training rows) the training data never move -- a play wider than any
    loop: their coefficients stay at 0."""
    norms = np.linalg.norm(columns, axis=0)
    dead: NDArray[np.bool_] = norms <= 1e-9 * float(np.max(norms))
    return dead


def _rate(data: DynamicCalibrationData, grid_values: F64) -> F64:
    """Time derivative of a grid signal at the compared samples (per uniform piece)."""
    out = np.zeros(grid_values.size)
    for dt_s, start, stop in data.pieces:
        if stop - start > 1:
            out[start:stop] = np.gradient(grid_values[start:stop], dt_s)
    rate: F64 = out[data.compared]
    return rate


def settled_rows(data: DynamicCalibrationData, skip_s: float) -> NDArray[np.bool_]:
    """Compared samples at least ``skip_s`` after the start of their experiment (start-up transients out)."""
    keep = np.ones(data.compared.size, dtype=bool)
    if skip_s <= 0.0:
        return keep
    for e, start, count in zip(data.experiments, data.starts, data.counts, strict=True):
        step = e.duration_s / max(1, int(count) - 1)
        n_skip = min(int(count), math.ceil(skip_s / step)) if step > 0 else 0
        keep[int(start) : int(start) + n_skip] = False
    return keep


def _alternate(
    s: _Session,
    f_grid: F64,
    f_rest: F64,
    lam: float,
    max_iter: int = 15,
    tol: float = 1e-5,
    *,
    slope_of_theta: F64 | None = None,
    refine: bool = True,
    theta_reg: F64 | None = None,
    keep: list[F64] | None = None,
) -> tuple[F64, F64, float, float, float, int]:
    """Alternating bounded least squares: ``(theta, w, kappa, tau_lag, rms_train, iterations)``.

    ``keep`` receives the training residuals of the returned coefficients.

    The alternation finds the basin; it converges slowly along the valley where the hysteresis
    coefficients and the creep weights trade off (their product is what the data pin), so
    ``refine`` continues with joint Gauss-Newton steps (:func:`_joint_refine`).

    The drive lag enters to first order: ``x(V lagged by tau) = x(V) - tau dx/dt``.
    The creep regressors are the filtered hysteretic positions. ``slope_of_theta`` selects
    voltage-driven creep instead (the law's rest slope is ``slope_of_theta @ theta`` and column 0
    of ``f_grid`` is the drive voltage): that fit is linear in the law and the creep per volt and
    is solved by :func:`_voltage_fit` (``max_iter`` Gauss-Newton steps, at least 40 with
    ``refine``).
    """
    if slope_of_theta is not None:
        return _voltage_fit(
            s,
            f_grid,
            f_rest,
            lam,
            slope_of_theta,
            theta_reg=theta_reg,
            keep=keep,
            max_iter=max(max_iter, 40) if refine else max_iter,
        )
    data = s.data
    f = f_grid[data.compared]
    e_f = [s.dev(f_grid[:, j], float(f_rest[j])) for j in range(f_grid.shape[1])]
    n_f, m = f.shape[1], s.taus.size
    w = np.zeros(m)
    kappa = 0.0
    xc = f @ np.ones(n_f) * 0.0
    tr = s.train_rows
    yc = s.yc[tr]
    last = math.inf
    rms = math.inf
    stall = 0
    best: tuple[F64, F64, float, float, float, int] = (
        np.zeros(f.shape[1]),
        np.zeros(s.taus.size),
        0.0,
        0.0,
        rms,
        0,
    )
    theta = np.zeros(n_f)
    rate = np.zeros(f.shape[0])
    tau = 0.0
    it = 0
    while it < max_iter:
        it += 1
        total = float(w.sum())
        a = np.column_stack([(1.0 + total) * f[:, j] + e_f[j] @ w for j in range(n_f)] + [xc * xc])
        ac = _centre(data, a)[tr]
        lower = np.concatenate([np.full(n_f, 0.0), [-s.max_kappa]])
        upper = np.concatenate([np.full(n_f, np.inf), [s.max_kappa]])
        lower[0] = 1e-9
        dead = _dead(ac)
        lower[dead] = 0.0
        upper[dead] = 0.0
        t_ridge = None if theta_reg is None else np.column_stack([theta_reg, np.zeros(theta_reg.shape[0])])
        coef, _ = solve_linear(
            ac, yc + _centre(data, tau * rate)[tr], lower=lower, upper=upper, ridge=t_ridge, method="bvls"
        )
        theta, kappa = coef[:n_f], float(coef[-1])
        xh = f @ theta
        e_x = sum(theta[j] * e_f[j] for j in range(n_f))
        assert isinstance(e_x, np.ndarray)
        xc_new = (1.0 + total) * xh + e_x @ w
        b_cols = xh[:, None] + e_x
        rate = (1.0 + total) * _rate(data, f_grid @ theta)
        target = s.yc - _centre(data, xh + kappa * xc_new * xc_new - tau * rate)
        bc = _centre(data, b_cols)
        scale = float(np.linalg.norm(bc[tr])) / math.sqrt(m)
        w, _ = solve_linear(
            bc[tr],
            target[tr],
            lower=np.zeros(m),
            upper=np.full(m, s.max_creep / m),
            ridge=math.sqrt(lam) * scale * s.creep_reg,
            method="bvls",
        )
        xc = (1.0 + float(w.sum())) * xh + e_x @ w
        # the lag to first order, x(V lagged by tau) = x(V) - tau dx/dt: a 1-D least squares
        without = _centre(data, xc + kappa * xc * xc) - s.yc
        rate_c = _centre(data, rate)
        denom = float(rate_c[tr] @ rate_c[tr])
        tau = 0.0 if denom <= 0.0 else float(np.clip((without[tr] @ rate_c[tr]) / denom, 0.0, s.max_lag_s))
        resid = without - tau * rate_c
        rms = float(np.sqrt(np.mean(resid[tr] ** 2)))
        if rms < last * (1.0 - tol):
            best = (theta.copy(), w.copy(), kappa, tau, rms, it)
            last, stall = rms, 0
            if keep is not None:
                keep[:] = [resid[tr].copy()]
        else:
            stall += 1
            if stall >= 2:
                break
    if refine:
        return _joint_refine(s, f_grid, lam, best, e_f, theta_reg=theta_reg, keep=keep)
    return best


def _voltage_fit(
    s: _Session,
    f_grid: F64,
    f_rest: F64,
    lam: float,
    slope_of_theta: F64,
    *,
    theta_reg: F64 | None = None,
    keep: list[F64] | None = None,
    max_iter: int = 40,
    tol: float = 1e-7,
) -> tuple[F64, F64, float, float, float, int]:
    """Voltage-driven creep: ``(theta, w, kappa, tau_lag, rms_train, iterations)`` by Gauss-Newton.

    With the creep driven by the voltage the position is ``x_c = F theta + s (W V + E[V] w)``
    with ``s = slope_of_theta @ theta`` the law's rest slope: bilinear in ``theta`` and ``w``, but
    *linear* in ``theta`` and ``c = s w`` (the creep per volt of each element). The fit solves
    for ``(theta, c)`` jointly, so it never alternates along the valley where ``s`` and ``w``
    trade off (an alternation there let the slope of a law with local densities -- the
    generalised play law's at 0 V -- run away: 0.74 -> 2.9 -> 0.46 um/V in three steps and a
    diverged fit); the static map ``kappa`` and the drive lag ``tau`` are the only nonlinear
    parts, taken by Gauss-Newton steps on all coefficients (each a bounded, regularised
    :func:`solve_linear`, accepted with step halving when the regularised training cost falls).
    ``w = c / s`` at the end. ``keep`` receives the training residuals of the result.
    """
    data = s.data
    f = f_grid[data.compared]
    n_f, m = f.shape[1], s.taus.size
    # x_creep = sum_k c_k (V + e_k[V]): column k is what c_k multiplies
    cc = f[:, :1] + s.dev(f_grid[:, 0], float(f_rest[0]))
    r_f = np.column_stack([_rate(data, f_grid[:, j]) for j in range(n_f)])
    tr = s.train_rows
    yc = s.yc[tr]
    reg = s.creep_reg
    ridge_scale = float(np.linalg.norm(_centre(data, cc)[tr])) / math.sqrt(m)
    ridge = np.zeros((reg.shape[0], n_f + m + 2))
    ridge[:, n_f : n_f + m] = math.sqrt(lam) * ridge_scale * reg
    if theta_reg is not None:
        extra = np.zeros((theta_reg.shape[0], n_f + m + 2))
        extra[:, :n_f] = theta_reg
        ridge = np.vstack([ridge, extra])
    lower = np.concatenate([np.zeros(n_f + m), [-s.max_kappa, 0.0]])
    upper = np.concatenate([np.full(n_f + m, np.inf), [s.max_kappa, s.max_lag_s]])
    lower[0] = 1e-9
    dead = _dead(_centre(data, f)[tr])
    lower[:n_f][dead] = 0.0
    upper[:n_f][dead] = 0.0

    def evaluate(p: F64) -> tuple[F64, F64, F64]:
        theta, c, kappa, tau = p[:n_f], p[n_f : n_f + m], float(p[-2]), float(p[-1])
        xc = f @ theta + cc @ c
        rate = r_f @ theta + float(c.sum()) * r_f[:, 0]
        return xc + kappa * xc * xc - tau * rate, xc, rate

    def feasible(p: F64) -> F64:
        # w_k = c_k / s <= MAX_TOTAL_CREEP / m with the slope s of this very point
        out = p.copy()
        cap = s.max_creep / m * max(float(slope_of_theta @ p[:n_f]), 0.0)
        out[n_f : n_f + m] = np.minimum(out[n_f : n_f + m], cap)
        return out

    def cost(p: F64) -> tuple[float, F64]:
        resid = (_centre(data, evaluate(p)[0]) - s.yc)[tr]
        return float(resid @ resid) + float(np.sum((ridge @ p) ** 2)), resid

    p = np.zeros(n_f + m + 2)
    # the creep per volt is bounded through the slope (w_k = c_k / s <= MAX_TOTAL_CREEP / m): start
    # from the law alone so the first joint step has a slope to bound by
    first, _ = solve_linear(_centre(data, f)[tr], yc, lower=lower[:n_f], upper=upper[:n_f], method="bvls")
    p[:n_f] = first
    current, resid = cost(p)
    it = 0
    for it in range(1, max_iter + 1):
        x0, xc, rate = evaluate(p)
        kappa, tau = float(p[-2]), float(p[-1])
        chain = 1.0 + 2.0 * kappa * xc
        jac = np.column_stack(
            [
                chain[:, None] * f - tau * r_f,
                chain[:, None] * cc - tau * r_f[:, :1],
                xc * xc,
                -rate,
            ]
        )
        jc = _centre(data, jac)[tr]
        target = (s.yc - _centre(data, x0))[tr] + jc @ p
        slope = float(slope_of_theta @ p[:n_f])
        if slope > 0.0:
            upper[n_f : n_f + m] = s.max_creep / m * slope
        lo, hi = lower.copy(), upper.copy()
        if it == 1:
            # without creep the static map and the lag have no column yet: they start at zero
            lo[-2:] = hi[-2:] = 0.0
        q, _ = solve_linear(jc, target, lower=lo, upper=hi, ridge=ridge, method="bvls")
        step, accepted = 1.0, False
        while step >= 1.0 / 1024.0:
            trial = feasible(p + step * (q - p))
            new, new_resid = cost(trial)
            if new < current:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            it -= 1
            break
        gain = (current - new) / new
        p, current, resid = trial, new, new_resid
        if gain < tol:
            break
    theta, c, kappa, tau = p[:n_f], p[n_f : n_f + m], float(p[-2]), float(p[-1])
    slope = float(slope_of_theta @ theta)
    w = np.minimum(c / slope, s.max_creep / m) if slope > 0.0 else np.zeros(m)
    if keep is not None:
        keep[:] = [resid.copy()]
    rms = float(np.sqrt(np.mean(resid**2)))
    return theta.copy(), w, kappa, tau, rms, max(it, 1)


def _joint_refine(
    s: _Session,
    f_grid: F64,
    lam: float,
    start: tuple[F64, F64, float, float, float, int],
    e_f: list[F64],
    *,
    theta_reg: F64 | None = None,
    max_iter: int = 40,
    tol: float = 1e-6,
    keep: list[F64] | None = None,
) -> tuple[F64, F64, float, float, float, int]:
    """Joint Gauss-Newton refinement of ``(theta, w, kappa, tau)`` from the alternation's result.

    ``keep`` receives the training residuals of the returned coefficients.

    The position is bilinear in ``theta`` and ``w``, ``x_c = A(w) theta = x_h + B(theta) w``, so
    its linearisation at ``(theta0, w0)`` is ``A(w0) theta + B(theta0) (w - w0)``; with the
    stiffness and the lag (chain rule through ``x_c + kappa x_c^2 - tau dx/dt``) every step is one
    bounded, regularised linear least-squares problem in all coefficients at once
    (:func:`solve_linear`), accepted with step halving only when the regularised training cost
    falls. ``e_f`` are the creep deviations of every feature column (position-driven creep).
    """
    data = s.data
    f = f_grid[data.compared]
    n_f, m = f.shape[1], s.taus.size
    stacked = np.stack(e_f)
    rates = np.column_stack([_rate(data, f_grid[:, j]) for j in range(n_f)])
    tr = s.train_rows
    reg = s.creep_reg

    def parts(theta: F64, w: F64, kappa: float, tau: float) -> tuple[F64, F64, F64, F64, F64, F64]:
        total = float(w.sum())
        xh = f @ theta
        e_x = np.tensordot(theta, stacked, axes=1)
        xc = (1.0 + total) * xh + e_x @ w
        a = (1.0 + total) * f + (stacked @ w).T
        b = xh[:, None] + e_x
        rate_cols = (1.0 + total) * rates
        rate = rate_cols @ theta
        x = xc + kappa * xc * xc - tau * rate
        return x, xc, a, b, rate, rate_cols

    def cost(theta: F64, w: F64, kappa: float, tau: float, ridge_scale: float) -> tuple[float, float, F64]:
        x = parts(theta, w, kappa, tau)[0]
        resid = (_centre(data, x) - s.yc)[tr]
        fit = float(resid @ resid)
        penalty = lam * ridge_scale**2 * float(np.sum((reg @ w) ** 2))
        if theta_reg is not None:
            penalty += float(np.sum((theta_reg @ theta) ** 2))
        return fit + penalty, math.sqrt(fit / max(1, resid.size)), resid

    theta, w, kappa, tau, rms, it = start
    theta, w = theta.copy(), w.copy()
    if not math.isfinite(rms):
        return start
    lower = np.concatenate([np.zeros(n_f), np.zeros(m), [-s.max_kappa, 0.0]])
    upper = np.concatenate([np.full(n_f, np.inf), np.full(m, s.max_creep / m), [s.max_kappa, s.max_lag_s]])
    lower[0] = 1e-9
    b = parts(theta, w, kappa, tau)[3]
    ridge_scale = float(np.linalg.norm(_centre(data, b)[tr])) / math.sqrt(m)
    current, rms, resid = cost(theta, w, kappa, tau, ridge_scale)
    dead = _dead(_centre(data, f)[tr])
    lower[:n_f][dead] = 0.0
    upper[:n_f][dead] = 0.0
    for _ in range(max_iter):
        x, xc, a, b, rate, rate_cols = parts(theta, w, kappa, tau)
        chain = 1.0 + 2.0 * kappa * xc
        # d rate / d w_i: the creep's instantaneous share scales the rate of the position
        rate_w = rates @ theta
        jac = np.column_stack(
            [chain[:, None] * a - tau * rate_cols, chain[:, None] * b - tau * rate_w[:, None], xc * xc, -rate]
        )
        p0 = np.concatenate([theta, w, [kappa, tau]])
        jc = _centre(data, jac)[tr]
        target = (s.yc - _centre(data, x))[tr] + jc @ p0
        ridge = np.zeros((reg.shape[0], p0.size))
        ridge[:, n_f : n_f + m] = math.sqrt(lam) * ridge_scale * reg
        if theta_reg is not None:
            extra = np.zeros((theta_reg.shape[0], p0.size))
            extra[:, :n_f] = theta_reg
            ridge = np.vstack([ridge, extra])
        p, _ = solve_linear(jc, target, lower=lower, upper=upper, ridge=ridge, method="bvls")
        step = 1.0
        accepted = False
        while step >= 1.0 / 16.0:
            q = p0 + step * (p - p0)
            th, wq, kq, tq = q[:n_f], q[n_f : n_f + m], float(q[-2]), float(q[-1])
            if float(wq.sum()) < MAX_TOTAL_CREEP:
                new, new_rms, new_resid = cost(th, wq, kq, tq, ridge_scale)
                if new < current:
                    accepted = True
                    break
            step *= 0.5
        if not accepted:
            break
        gain = (current - new) / current
        theta, w, kappa, tau, current, rms, resid = th.copy(), wq.copy(), kq, tq, new, new_rms, new_resid
        it += 1
        if gain < tol:
            break
    if keep is not None:
        keep[:] = [resid]
    return theta, w, kappa, tau, rms, it


def _result(s: _Session, params: FamilyParams, iterations: int, n_coefficients: int, t0: float) -> FamilyFit:
    """The fit's result: residuals on the training rows, RMS on the held-out ones; ``params``
    carry where the sensor reads their zero (:attr:`~piezod.model.family.FamilyParams.offset_um`).

    The fits leave an offset per experiment (or one for the sensor) free, so the member's own zero
    need not be the sensor's: on birch35 the generalised play law on 5 centre nodes sat 1.01 um
    below it with the offsets tied. The runtime parts around the model (a saturation, a
    stiffness) are fitted in the sensor's frame; placed 1.01 um off, the saturation made every
    verified line 2.3-2.4 % long (docs/model-family.md 6.2bp). The mean of the experiments'
    offsets places the model there.
    """
    x = session_positions(s.data, params, s.dev)
    offset = float(np.mean(experiment_offsets(s.data, x)))
    params = dataclasses.replace(params, offset_um=params.offset_um + offset)
    # the offsets are centred out of the residual: x need not move with them
    resid = s.yc - _centre(s.data, x)
    train = resid[s.train_rows]
    held = resid[s.test_rows]
    n = int(train.size)
    n_offsets = s.data.n_offset_parameters(s.train_rows)
    return FamilyFit(
        params=params,
        residuals_um=train,
        cost=0.5 * float(train @ train),
        n=n,
        dof=n - n_coefficients - n_offsets,
        nfev=iterations,
        success=True,
        message="converged",
        seconds=time.perf_counter() - t0,
        heldout_rms_um=float(np.sqrt(np.mean(held**2))) if held.size else math.nan,
        heldout_residuals_um=held,
    )


def session_positions(
    data: DynamicCalibrationData, params: FamilyParams, dev: _Deviations | None = None
) -> F64:
    """The model's positions at the compared samples of a session (the lag to first order).

    Parameters
    ----------
    data
        The session.
    params
        The model.
    dev
        A deviations operator on ``params.creep.taus_s`` (built when not given).
    """
    if dev is None or not np.array_equal(dev.taus, params.creep.taus_s):
        dev = _Deviations(data, np.asarray(params.creep.taus_s))
    h = params.hysteresis
    v = data.hysteresis_voltage_v
    if isinstance(h, DomainWallParams):
        walls = session_walls(
            h, hysteresis_times_s(data), v, data.rest_voltage_v, params.after_effect, AE_MAX_STEPS
        )
        xh_all = h.b_um_per_v * v + h.w_um_per_v * walls
    elif isinstance(h, BoucWenParams):
        xh_all, _ = boucwen_forward(h, v, boucwen_rest_state(h, data.rest_voltage_v))
    elif isinstance(h, GeneralisedPlayParams):
        if params.after_effect is None:
            xh_all, _ = gplay_forward(h, v, gplay_rest_state(h, data.rest_voltage_v))
        else:
            xh_all = h.positions(v, session_play_outputs(data, np.asarray(h.r), params.after_effect))
    elif isinstance(h, PlayParams):
        state = PlayState(data.rest_voltage_v, np.full(h.r.size, data.rest_voltage_v), 0.0)
        xh_all, _ = play_forward(h, v, state)
    else:
        from piezod.model.ode import HysteresisState, hysteresis_step

        xh_all, _ = hysteresis_step(
            h, v, HysteresisState(data.rest_voltage_v, h.b_um_per_v * data.rest_voltage_v)
        )
    xh_grid = xh_all[data.grid_index]
    total = params.creep.total_creep
    kappa = params.stiffness_pct_per_um / 200.0
    if params.creep_driver == "voltage":
        played = isinstance(h, PlayParams | GeneralisedPlayParams)
        v_grid = v[data.grid_index] if played else data.grid_voltage_v
        slope = params.law_slope_um_per_v
        e = dev(v_grid, data.rest_voltage_v)
        xc = xh_grid[data.compared] + slope * (total * v_grid[data.compared] + e @ params.creep.weights)
        rate = _rate(data, xh_grid) + slope * total * _rate(data, v_grid)
    else:
        e = dev(xh_grid, _rest_position(h, data.rest_voltage_v))
        xc = (1.0 + total) * xh_grid[data.compared] + e @ params.creep.weights
        rate = (1.0 + total) * _rate(data, xh_grid)
    out: F64 = xc + kappa * xc * xc - params.lag_time_constant_s * rate + params.offset_um
    return out


def heldout_rms(
    data: DynamicCalibrationData,
    params: FamilyParams,
    train: NDArray[np.bool_],
    history: NDArray[np.bool_] | None = None,
    skip_s: float = 0.0,
) -> float:
    """RMS (um) of a member with given ``params`` (fitted elsewhere) on a session's held-out
    experiments, scored as :func:`fit_family` scores its own fit on the same ``train``,
    ``history`` and ``skip_s``: the offsets (per experiment or of one sensor, as ``data`` says)
    are the only thing fitted. NaN when no experiment is held out.
    """
    train = np.asarray(train, dtype=bool)
    exp_of_row = np.repeat(np.arange(data.n_experiments), data.counts)
    keep = settled_rows(data, skip_s)
    if history is not None:
        keep &= ~np.asarray(history, dtype=bool)[exp_of_row]
    test_rows = ~train[exp_of_row] & keep
    if not test_rows.any():
        return math.nan
    resid = _centre(data, data.position_um) - _centre(data, session_positions(data, params))
    return float(np.sqrt(np.mean(resid[test_rows] ** 2)))


def experiment_offsets(data: DynamicCalibrationData, positions_um: F64) -> F64:
    """Each experiment's mean residual, sensor minus ``positions_um`` (:func:`session_positions`):
    its offset as the fit leaves it."""
    out: F64 = np.add.reduceat(data.position_um - positions_um, data.starts) / data.counts
    return out


def _rest_position(
    h: HysteresisParams | PlayParams | GeneralisedPlayParams | BoucWenParams | DomainWallParams, v: float
) -> float:
    if isinstance(h, DomainWallParams):
        return domainwall_rest_state(h, v).position_um
    if isinstance(h, BoucWenParams):
        return boucwen_rest_state(h, v).position_um
    if isinstance(h, GeneralisedPlayParams):
        return gplay_rest_state(h, v).position_um
    if isinstance(h, PlayParams):
        return h.b_um_per_v * h.total_weight * v
    return h.b_um_per_v * v


#: Bounds of the Bouc-Wen (Duhem) law's searched rates: relaxation rates (1/V), the ratio of the
#: recovery rate after a reversal to the saturating rate, and ``amp_down``.
BW_RATE_BOUNDS = (1e-4, 0.3)
#: Bounds of the Coleman-Hodgdon law's searched ``alpha`` (1/V), scaled like the Bouc-Wen rates.
CH_ALPHA_BOUNDS = (1e-4, 0.1)
#: The rate bounds are for sessions spanning at least this many volts; a narrower session's are
#: scaled up by ``BW_SPAN_REF_V / span`` (``k x span``, how far a branch bends over the session's
#: voltages, is what the data pin: a rate below ``1e-4 x 100 V / span`` cannot bend within them).
BW_SPAN_REF_V = 100.0
BW_RATIO_BOUNDS = (0.0, 3.0)
BW_AMP_BOUNDS = (0.5, 2.0)
#: The Bouc-Wen rate search: exponents and recovery ratios profiled (a scalar search of the rate,
#: at most ``BW_PROFILE_EVALUATIONS`` each), then evaluations of the polish of all five.
BW_EXPONENTS = (1.0, 2.0, 3.0)
BW_PROFILE_RATIOS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
BW_PROFILE_EVALUATIONS = 14
BW_POLISH_EVALUATIONS = 80
#: A rejected Bouc-Wen candidate scores this many times :func:`_train_scale_um` (worse than any
#: admissible one: a fit is at most as bad as a constant per experiment).
BW_REJECT_FACTOR = 10.0


def _train_scale_um(s: _Session) -> float:
    """RMS of the centred training positions (um): what a constant per experiment leaves."""
    return float(np.sqrt(np.mean(s.yc[s.train_rows] ** 2)))


def _bw_c_floor(b: float, rates: tuple[float, float, float, float], amp: float, exponent: float) -> float:
    """Lowest ``c`` that keeps the slope after a reversal, ``b + c M``
    (:attr:`BoucWenParams.reversal_rate`), >= 2 :data:`~piezod.model.boucwen.MIN_SLOPE_FRACTION` ``b``."""
    return -(1.0 - 2.0 * MIN_SLOPE_FRACTION) * b / BoucWenParams(b, 0.0, *rates, amp, exponent).reversal_rate


def _bw_admissible(theta: F64, rates: tuple[float, float, float, float], amp: float, exponent: float) -> bool:
    """Whether the linear fit ``theta = (b, -c)`` is a law the slope limit leaves as it is.

    The slope after a reversal, ``b + c M`` (:attr:`BoucWenParams.reversal_rate`), must stay >= 2
    :data:`~piezod.model.boucwen.MIN_SLOPE_FRACTION` ``b`` (where :func:`_fit_bouc_wen` limits
    ``c``). A fit beyond it is one the limit would change, by ``(c_fit - c_limit) h``: when ``b``
    and ``-c`` nearly cancel (a rate so low the law cannot bend within the session's voltages,
    ``h`` almost ``V``), that is the whole position many times over.
    """
    b, c = float(theta[0]), -float(theta[1])
    if not (math.isfinite(b) and math.isfinite(c) and b > 0.0):
        return False
    return c >= _bw_c_floor(b, rates, amp, exponent)


def _span_scale(data: DynamicCalibrationData) -> float:
    """``BW_SPAN_REF_V / span`` on a session spanning fewer volts, else 1: the factor on the
    searched rates (1/V) of the Bouc-Wen and Coleman-Hodgdon laws."""
    v = data.hysteresis_voltage_v
    span = float(np.max(v) - np.min(v)) if v.size else 0.0
    return BW_SPAN_REF_V / span if 0.0 < span < BW_SPAN_REF_V else 1.0


def _bw_rate_bounds(data: DynamicCalibrationData) -> tuple[float, float]:
    """The searched rates (1/V): :data:`BW_RATE_BOUNDS`, scaled up on a session narrower than
    :data:`BW_SPAN_REF_V`."""
    scale = _span_scale(data)
    return (BW_RATE_BOUNDS[0] * scale, BW_RATE_BOUNDS[1] * scale)


def _bw_unpack(z: F64) -> tuple[tuple[float, float, float, float], float]:
    """``(rates, amp_down)`` of the search vector ``(log k_up, log k_down, rho_up, rho_down, log amp)``."""
    k_up, k_down = math.exp(float(z[0])), math.exp(float(z[1]))
    return (k_up, float(z[2]) * k_up, k_down, float(z[3]) * k_down), math.exp(float(z[4]))


def _bw_pack(law: BoucWenParams) -> F64:
    """The search vector of a law's rates (the inverse of :func:`_bw_unpack`)."""
    return np.array(
        [
            math.log(law.k_up_same),
            math.log(law.k_down_same),
            law.k_up_back / law.k_up_same,
            law.k_down_back / law.k_down_same,
            math.log(law.amp_down),
        ]
    )


def _fit_bouc_wen(
    s: _Session, lam: float, voltage: bool, start: BoucWenParams | None = None
) -> tuple[F64, F64, float, float, int, BoucWenParams, int]:
    """The Bouc-Wen (Duhem) law by variable projection.

    For given rates the position is linear in ``theta = (b, -c)`` and the creep weights (the
    features are ``[V, -h]`` with ``h`` the law's hysteretic variable for ``A_up = 1``), so the
    five nonlinear parameters (the saturating rate per direction, the recovery-to-saturating
    ratio per direction, ``amp_down``) and the exponent are searched on the training residuals of
    the linear fit (:func:`_alternate`, 4 alternations). The residual is a narrow valley in the
    rate (the knee's voltage scale: 25 % off the rate costs 30x the RMS on a sharp knee) and has
    several in the ratio, so the search first profiles the symmetric law (one rate, one ratio:
    Coleman-Hodgdon is ratio 1): for the exponents of :data:`BW_EXPONENTS` in turn (stopping at
    one that fits worse than the last) and every ratio of :data:`BW_PROFILE_RATIOS` a bounded
    scalar search of the rate; then a bounded Gauss-Newton
    (trust-region, :func:`scipy.optimize.least_squares`) polish of all five at the best exponent,
    on the residual vector; then the full alternation and joint refinement at the best rates.
    ``c`` is then limited so the slope after a reversal stays >=
    :data:`~piezod.model.boucwen.MIN_SLOPE_FRACTION` of ``b``.

    With ``start`` (a law fitted on nearly the same data) the profile is skipped: the polish
    starts from its rates at its exponent (unless the start is rejected here).

    The rates are searched in :func:`_bw_rate_bounds` (scaled up on a session spanning less than
    :data:`BW_SPAN_REF_V`). A candidate whose linear fit is not finite or is one that limit would
    change (:func:`_bw_admissible`) is rejected: it scores a flat residual of
    :data:`BW_REJECT_FACTOR` times the centred data, above every admissible one, so neither the
    profile nor the polish can pick it.

    Returns ``(theta, w, kappa, tau, iterations, law, searched parameters)``.

    Raises
    ------
    CalibrationError
        Every profiled candidate was rejected.
    """
    data = s.data
    rest = data.rest_voltage_v
    f_rest = np.array([rest, 0.0])
    slope = np.array([1.0, 0.0]) if voltage else None
    n_train = int(np.count_nonzero(s.train_rows))
    reject = np.full(n_train, BW_REJECT_FACTOR * _train_scale_um(s))
    exponent = 1.0
    evaluations = 0

    def features(z: F64) -> F64:
        rates, amp = _bw_unpack(z)
        h = unit_hysteresis(rates, amp, data.hysteresis_voltage_v, rest, exponent)
        return np.column_stack([data.grid_voltage_v, -h[data.grid_index]])

    def residuals(z: F64) -> F64:
        nonlocal evaluations
        evaluations += 1
        keep: list[F64] = []
        f = features(z)
        if not np.all(np.isfinite(f)):
            return reject  # the law's variable overflowed along this session (a rate far too high)
        # position-driven creep is bilinear in the law and the creep weights: 4 alternations are
        # far from converged there (28 nm at the true rates of a stage the converged fit leaves at
        # its 2 nm noise), and such a score ranks the rates wrongly; the joint refinement converges
        # at about the same cost. The voltage-driven fit's Gauss-Newton steps converge in 4.
        theta = _alternate(
            s, f, f_rest, lam, max_iter=4, slope_of_theta=slope, refine=slope is None, keep=keep
        )[0]
        rates, amp = _bw_unpack(z)
        if keep and np.all(np.isfinite(keep[0])) and _bw_admissible(theta, rates, amp, exponent):
            return keep[0]
        # no finite step, or a law the slope limit would have to change (its score is not the
        # returned law's): rejected, a flat residual above any admissible one
        return reject

    def cost(z: F64) -> float:
        r = residuals(z)
        return float(np.sqrt(np.mean(r * r)))

    lo, hi = (math.log(b) for b in _bw_rate_bounds(data))
    amp_lo, amp_hi = (math.log(b) for b in BW_AMP_BOUNDS)
    lower = np.array([lo, lo, BW_RATIO_BOUNDS[0], BW_RATIO_BOUNDS[0], amp_lo])
    upper = np.array([hi, hi, BW_RATIO_BOUNDS[1], BW_RATIO_BOUNDS[1], amp_hi])
    best_z, best, best_n = np.zeros(5), math.inf, 1.0
    last = math.inf
    if start is not None:
        exponent = best_n = start.exponent
        best_z = _bw_pack(start).clip(lower, upper)
        best = cost(best_z)
    warm = best < float(reject[0])  # else the start is not admissible here: searched as without
    if not warm:
        best, best_n = math.inf, 1.0
    for exponent in () if warm else BW_EXPONENTS:
        here = math.inf
        for rho in BW_PROFILE_RATIOS:
            prof = minimize_scalar(
                lambda lk, rho=rho: cost(np.array([lk, lk, rho, rho, 0.0])),
                bounds=(lo + 0.1 * (hi - lo), hi - 0.05 * (hi - lo)),
                method="bounded",
                options={"xatol": 0.02, "maxiter": BW_PROFILE_EVALUATIONS},
            )
            here = min(here, float(prof.fun))
            if float(prof.fun) < best:
                best, best_n = float(prof.fun), exponent
                best_z = np.array([float(prof.x)] * 2 + [rho, rho, 0.0])
        if here >= last:
            break  # sharper than the last exponent fits worse: the next, sharper still, is not tried
        last = here
    if best >= float(reject[0]):
        raise CalibrationError(
            "family fit (bouc-wen): no searched rates give an admissible law (every candidate's "
            "fit diverged or needs a slope after a reversal below the limit)"
        )
    exponent = best_n
    res = least_squares(
        residuals,
        np.clip(best_z, lower, upper),
        bounds=(lower, upper),
        method="trf",
        diff_step=1e-3,
        max_nfev=BW_POLISH_EVALUATIONS,
    )
    polished = float(np.sqrt(np.mean(res.fun**2)))
    z = np.asarray(res.x) if polished < best else best_z
    rates, amp = _bw_unpack(z)
    theta, w, kappa, tau, _, it = _alternate(s, features(z), f_rest, lam, slope_of_theta=slope)
    b, c = float(theta[0]), -float(theta[1])
    # the slope after a reversal is b + c M (BoucWenParams.min_slope_um_per_v): keep it positive
    c = max(c, _bw_c_floor(b, rates, amp, exponent))
    law = BoucWenParams(b, c, *rates, amp, exponent)
    return theta, w, kappa, tau, it + evaluations, law, 6


#: The domain-wall law's search (:func:`_fit_domain_wall`): starting pinnings (fractions of the
#: session's span) and interactions on a grid, the curve centred on the span and as wide; then a
#: polish of the four (and of the after-effect's two, searched from its own grid at the polished law).
DW_PINNING_FRACTIONS = (0.05, 0.2, 0.5)
DW_INTERACTIONS = (0.0, 0.4)
DW_POLISH_EVALUATIONS = 60
#: Bounds of the searched shape: pinning and width as fractions of the span, the centre within a
#: span of the session's voltages, the interaction below the law's limit.
DW_PINNING_BOUNDS = (1e-3, 3.0)
DW_WIDTH_BOUNDS = (0.05, 30.0)
DW_MAX_INTERACTION = 0.85
#: The after-effect's times (s) on the domain-wall law's grid (its ``g0`` on
#: :data:`AE_FLUCTUATION_FRACTIONS` of the span, as the generalised play law's).
DW_AE_TIMES_S = (1.0, 1e2, 1e4)


def _fit_domain_wall(
    s: _Session,
    lam: float,
    voltage: bool,
    after_effect: AfterEffect | bool | None,
    start: DomainWallParams | None = None,
) -> tuple[F64, F64, float, float, int, DomainWallParams, AfterEffect | None, int]:
    """The domain-wall law by variable projection.

    For a given shape ``(k, h_b, a, alpha)`` (and after-effect) the position is linear in
    ``theta = (b, w)`` and the creep weights (features ``[V, P]``, ``P`` the walls' displacement
    along the session, :func:`piezod.model.domainwall.session_walls`), so the shape is searched on
    the training residuals of the linear fit (:func:`_alternate`, 4 steps): a grid of pinnings and
    interactions (:data:`DW_PINNING_FRACTIONS`, :data:`DW_INTERACTIONS`; the curve centred on the
    session's span and as wide), then a bounded Gauss-Newton polish
    (:func:`scipy.optimize.least_squares`) of the four. With ``after_effect=True`` its ``(g0,
    tau)`` are then searched at the polished shape on a grid (:data:`AE_FLUCTUATION_FRACTIONS`
    x :data:`DW_AE_TIMES_S`) and all six polished together; an :class:`AfterEffect` is held. A
    candidate whose linear fit is not finite or has ``w < 0`` or ``b <= 0`` is rejected (a flat
    residual of :data:`BW_REJECT_FACTOR` times the centred data). ``start``: a law fitted on nearly
    the same session, whose shape starts the polish (the grid is skipped).

    Returns ``(theta, w, kappa, tau, iterations, law, after-effect, searched parameters)``.

    Raises
    ------
    CalibrationError
        Every candidate was rejected.
    """
    data = s.data
    v = data.hysteresis_voltage_v
    times = hysteresis_times_s(data)
    rest = data.rest_voltage_v
    lo_v, hi_v = (float(np.min(v)), float(np.max(v))) if v.size else (rest - 1.0, rest + 1.0)
    span = max(hi_v - lo_v, 1e-3)
    slope = np.array([1.0, 0.0]) if voltage else None
    n_train = int(np.count_nonzero(s.train_rows))
    reject = np.full(n_train, BW_REJECT_FACTOR * _train_scale_um(s))
    evaluations = 0

    def law_of(z: F64) -> DomainWallParams:
        return DomainWallParams(
            1.0, 1.0, math.exp(float(z[0])), float(z[1]), math.exp(float(z[2])), float(z[3])
        )

    def ae_of(z: F64) -> AfterEffect | None:
        if isinstance(after_effect, AfterEffect):
            return after_effect
        if z.size < 6:
            return None
        return AfterEffect(math.exp(float(z[4])), math.exp(float(z[5])))

    def features(z: F64) -> tuple[F64, F64]:
        law = law_of(z)
        walls = session_walls(law, times, v, rest, ae_of(z), AE_MAX_STEPS)
        f_rest = np.array([rest, domainwall_rest_state(law, rest).walls_v])
        return np.column_stack([data.grid_voltage_v, walls[data.grid_index]]), f_rest

    def residuals(z: F64) -> F64:
        nonlocal evaluations
        evaluations += 1
        try:
            f, f_rest = features(z)
        except ModelError:
            return reject
        if not np.all(np.isfinite(f)):
            return reject
        keep: list[F64] = []
        theta = _alternate(
            s, f, f_rest, lam, max_iter=4, slope_of_theta=slope, refine=slope is None, keep=keep
        )[0]
        if keep and np.all(np.isfinite(keep[0])) and float(theta[0]) > 0.0 and float(theta[1]) >= 0.0:
            return keep[0]
        return reject

    def cost(z: F64) -> float:
        r = residuals(z)
        return float(np.sqrt(np.mean(r * r)))

    lower = np.array(
        [math.log(DW_PINNING_BOUNDS[0] * span), lo_v - span, math.log(DW_WIDTH_BOUNDS[0] * span), 0.0]
    )
    upper = np.array(
        [
            math.log(DW_PINNING_BOUNDS[1] * span),
            hi_v + span,
            math.log(DW_WIDTH_BOUNDS[1] * span),
            DW_MAX_INTERACTION,
        ]
    )
    if start is not None:
        best_z = np.array(
            [math.log(start.pinning_v), start.centre_v, math.log(start.width_v), start.interaction]
        )
        best_z = best_z.clip(lower, upper)
        best = cost(best_z)
    else:
        best_z, best = np.zeros(4), math.inf
        for frac in DW_PINNING_FRACTIONS:
            for alpha in DW_INTERACTIONS:
                z = np.array([math.log(frac * span), 0.5 * (lo_v + hi_v), math.log(span), alpha])
                c = cost(z)
                if c < best:
                    best_z, best = z, c
    if best >= float(reject[0]):
        raise CalibrationError(
            "family fit (domain-wall): no searched shape gives an admissible law (every candidate's fit "
            "diverged or weighs the walls negatively)"
        )

    def polish(z0: F64, c0: float, lo: F64, hi: F64) -> F64:
        """The polished ``z`` from ``z0`` (whose cost is ``c0``), or ``z0`` when it is no better."""
        res = least_squares(
            residuals,
            z0.clip(lo, hi),
            bounds=(lo, hi),
            method="trf",
            diff_step=1e-3,
            max_nfev=DW_POLISH_EVALUATIONS,
        )
        return np.asarray(res.x) if float(np.sqrt(np.mean(res.fun**2))) < c0 else z0

    z = polish(best_z, best, lower, upper)
    searched = 4
    if after_effect is True:
        base, best = z, math.inf
        for frac in AE_FLUCTUATION_FRACTIONS:
            for tau_s in DW_AE_TIMES_S:
                trial = np.concatenate([base, [math.log(frac * span), math.log(tau_s)]])
                c = cost(trial)
                if c < best:
                    z, best = trial, c
        ae_lo = [math.log(AE_MIN_FLUCTUATION_FRACTION * span), math.log(AE_TIME_BOUNDS_S[0])]
        ae_hi = [math.log(AE_MAX_FLUCTUATION_V), math.log(AE_TIME_BOUNDS_S[1])]
        z = polish(z, best, np.concatenate([lower, ae_lo]), np.concatenate([upper, ae_hi]))
        searched = 6
    f, f_rest = features(z)
    theta, w, kappa, tau, _, it = _alternate(s, f, f_rest, lam, slope_of_theta=slope)
    shape = law_of(z)
    law = DomainWallParams(
        float(theta[0]),
        max(float(theta[1]), 0.0),
        shape.pinning_v,
        shape.centre_v,
        shape.width_v,
        shape.interaction,
    )
    return theta, w, kappa, tau, it + evaluations, law, ae_of(z), searched


def fit_family(
    data: DynamicCalibrationData,
    law: str,
    *,
    alpha_per_v: float | None = None,
    train: NDArray[np.bool_] | None = None,
    plays: int = DEFAULT_PLAYS,
    taus: F64 | None = None,
    regularisation: float = 1e-4,
    skip_s: float = 0.0,
    creep_driver: str = "position",
    thresholds: F64 | None = None,
    nodes: F64 | None = None,
    n_nodes: int = GP_NODES,
    centre_smoothing: float = GP_CENTRE_SMOOTHING,
    fit_lag: bool = True,
    fit_stiffness: bool = True,
    fit_creep: bool = True,
    start: BoucWenParams | DomainWallParams | None = None,
    history: NDArray[np.bool_] | None = None,
    after_effect: AfterEffect | bool | None = None,
) -> FamilyFit:
    """Fit one law of the family to a session.

    Parameters
    ----------
    data
        The session (:func:`piezod.calibrate_dynamic.prepare_dynamic`).
    law
        ``prandtl-ishlinskii`` or ``coleman-hodgdon``.
    alpha_per_v
        Coleman-Hodgdon: hold ``alpha`` here (e.g. from the dynamic fit) instead of searching it.
    train
        Experiments to fit (default all); the others give :attr:`FamilyFit.heldout_rms_um`.
    plays
        Number of play operators (Prandtl-Ishlinskii).
    taus
        Relaxation times (default :func:`default_taus`).
    regularisation
        Tikhonov weight of the creep spectrum (relative to the data scale).
    skip_s
        Leave the first ``skip_s`` seconds of every experiment out of the fit and the scores
        (start-up transients the session reconstruction cannot know).
    creep_driver
        ``position`` or ``voltage``: what the fitted creep spectrum follows.
    thresholds
        Play half-widths (V) of the Prandtl-Ishlinskii and generalised play laws (default
        :func:`default_thresholds` with ``plays`` plays).
    nodes
        Relay-centre nodes (V) of the generalised play law (default :func:`default_nodes` with
        ``n_nodes`` nodes).
    n_nodes
        How many centre nodes the default grid has.
    centre_smoothing
        Generalised play law: weight of the penalty on density changes between neighbouring
        centre nodes (:func:`_centre_smoothing`); 0 leaves the centre dependence free.
    fit_lag
        Fit the drive lag (in its first-order form ``x - tau_lag dx/dt``, good while the drive
        changes slowly against ``tau_lag``); False holds it at 0, for a caller that runs the exact
        lag over the voltages itself (steps: :func:`piezod.heights.fit_z_model`).
    fit_stiffness
        Fit the static stiffness map; False holds it at 0 (what the held-out data lose without
        it: :func:`piezod.family_heldout.part_gains`).
    fit_creep
        Fit the creep spectrum; False holds its weights at 0.
    start
        Bouc-Wen: a law fitted on nearly the same session (the profiles of the runtime parts
        refit one member many times through slightly different parts). Its rates start the
        polish and its exponent is kept; the profile over exponents and ratios is skipped
        (the same fit to 0.001 nm at a seventh to a fourteenth of the time on fern21's frame,
        docs/model-family.md 6.2w).
    history
        Experiments the model runs through but neither fits nor scores (default none): what the
        stage did before the fitted ones (a first frame, before the frame played again).
    after_effect
        Generalised play law with voltage-driven creep: the after-effect of its memory
        (:mod:`piezod.model.aftereffect`), held at the given one, or searched with True
        (:func:`_search_after_effect`); False or None: none (what a member's
        :attr:`~piezod.model.family.FamilyParams.after_effect` holds when it has none).

    Raises
    ------
    CalibrationError
        Unknown law, or the fit gives parameters the model refuses; the Bouc-Wen law's search
        finds no admissible rates, or its law fits the training rows worse than a constant per
        experiment.
    """
    if law not in LAWS:
        raise CalibrationError(f"unknown hysteresis law {law!r} (one of {', '.join(LAWS)})")
    if creep_driver not in CREEP_DRIVERS:
        raise CalibrationError(f"unknown creep driver {creep_driver!r} (one of {', '.join(CREEP_DRIVERS)})")
    voltage = creep_driver == "voltage"
    if after_effect and not (law in AFTER_EFFECT_LAWS and voltage):
        raise CalibrationError(
            f"family fit ({law}, {creep_driver} creep): an after-effect needs the generalised play or "
            "domain-wall law with voltage-driven creep"
        )
    ae: AfterEffect | None = None
    taus = default_taus(data) if taus is None else np.asarray(taus, dtype=np.float64)
    mask = np.ones(data.n_experiments, dtype=bool) if train is None else np.asarray(train, dtype=bool)
    before = None if history is None else np.asarray(history, dtype=bool)
    if before is not None:
        mask = mask & ~before
    if not mask.any():
        raise CalibrationError("no experiment left to fit")
    t0 = time.perf_counter()
    s = _Session(
        data,
        taus,
        mask,
        skip_s,
        _MAX_LAG_S if fit_lag else 0.0,
        _MAX_KAPPA if fit_stiffness else 0.0,
        MAX_TOTAL_CREEP if fit_creep else 0.0,
        before,
    )
    rest_v = data.rest_voltage_v
    hyst: HysteresisParams | PlayParams | GeneralisedPlayParams | BoucWenParams | DomainWallParams
    searched = 0
    try:
        if law == "domain-wall":
            theta, w, kappa, tau, it, hyst, ae, searched = _fit_domain_wall(
                s,
                regularisation,
                voltage,
                after_effect,
                start if isinstance(start, DomainWallParams) else None,
            )
        elif law == "bouc-wen":
            bw_start = start if isinstance(start, BoucWenParams) else None
            theta, w, kappa, tau, it, hyst, searched = _fit_bouc_wen(s, regularisation, voltage, bw_start)
        elif law == "generalised-play":
            r = default_thresholds(data, plays) if thresholds is None else np.asarray(thresholds, np.float64)
            c = default_nodes(data, n_nodes) if nodes is None else np.asarray(nodes, np.float64)
            if after_effect is True:
                ae = _search_after_effect(s, r, c, regularisation, centre_smoothing)
                searched = 2
            elif isinstance(after_effect, AfterEffect):
                ae = after_effect
            f_grid, f_rest, slope = _gplay_features(data, r, c, ae)
            theta, w, kappa, tau, _, it = _alternate(
                s,
                f_grid,
                f_rest,
                regularisation,
                slope_of_theta=slope if voltage else None,
                theta_reg=_centre_smoothing(s, f_grid, r.size + 1, c.size, centre_smoothing),
            )
            mu = theta[1:].reshape(r.size + 1, c.size).copy()
            mu[0] += theta[0]
            used = np.flatnonzero(mu[1:].max(axis=1) > 0.0)
            used = used if used.size else np.array([0])
            hyst = GeneralisedPlayParams(
                tuple(map(float, r[used])),
                tuple(map(float, c)),
                tuple(tuple(map(float, row)) for row in np.vstack([mu[:1], mu[1:][used]])),
            )
        elif law == "prandtl-ishlinskii":
            r = default_thresholds(data, plays) if thresholds is None else np.asarray(thresholds, np.float64)
            plays = r.size
            f_grid = _play_features(data, r)
            theta, w, kappa, tau, _, it = _alternate(
                s,
                f_grid,
                np.full(plays + 1, rest_v),
                regularisation,
                slope_of_theta=np.ones(plays + 1) if voltage else None,
            )
            b = float(theta.sum())
            # plays the fit left at zero weight only cost inverse time: dropped (one kept)
            used = np.flatnonzero(theta[1:] > 0.0)
            used = used if used.size else np.array([0])
            weights = theta[1:][used] / b
            hyst = PlayParams(b, float(theta[0] / b), tuple(map(float, r[used])), tuple(map(float, weights)))
        else:
            ch_slope = np.array([1.0, 0.0]) if voltage else None

            def run(log_alpha: float) -> tuple[float, F64, F64, float, int]:
                alpha = math.exp(log_alpha)
                y = _hysteresis_unit(data, alpha)
                f_grid = np.column_stack([data.grid_voltage_v, y])
                res = _alternate(
                    s,
                    f_grid,
                    np.array([rest_v, 0.0]),
                    regularisation,
                    max_iter=4,
                    slope_of_theta=ch_slope,
                    # bilinear with position-driven creep: scored converged (see _fit_bouc_wen)
                    refine=ch_slope is None,
                )
                b_fit, delta_fit = float(res[0][0]), float(res[0][1])
                if not (math.isfinite(res[4]) and b_fit > 0.0 and b_fit - alpha * delta_fit > 1e-6 * b_fit):
                    # the slope after a reversal u = b - alpha delta would have to be clamped: the
                    # score is not the returned law's (b and delta cancel where the law cannot bend)
                    return reject, res[0], res[1], res[2], res[5]
                return res[4], res[0], res[1], res[2], res[5]

            reject = BW_REJECT_FACTOR * _train_scale_um(s)
            if alpha_per_v is None:
                scale = _span_scale(data)
                best = minimize_scalar(
                    lambda la: run(la)[0],
                    bounds=(math.log(CH_ALPHA_BOUNDS[0] * scale), math.log(CH_ALPHA_BOUNDS[1] * scale)),
                    method="bounded",
                    options={"xatol": 0.05, "maxiter": 14},
                )
                alpha = math.exp(float(best.x))
            else:
                alpha = float(alpha_per_v)
            y = _hysteresis_unit(data, alpha)
            f_grid = np.column_stack([data.grid_voltage_v, y])
            theta, w, kappa, tau, _, it = _alternate(
                s, f_grid, np.array([rest_v, 0.0]), regularisation, slope_of_theta=ch_slope
            )
            b, delta = float(theta[0]), float(theta[1])
            if not b - alpha * delta > 1e-6 * b:
                raise CalibrationError(
                    f"family fit (coleman-hodgdon): at alpha = {alpha:.3g} 1/V the slope after a reversal, "
                    f"b - alpha delta = {b - alpha * delta:.3g} um/V, is not positive (no admissible law)"
                )
            u = b - alpha * delta
            hyst = HysteresisParams(alpha, b, u)
        params = FamilyParams(
            hyst,
            CreepSpectrum(tuple(map(float, taus)), tuple(map(float, w))),
            tau,
            200.0 * kappa,
            creep_driver,
            after_effect=ae,
        )
    except ModelError as exc:
        raise CalibrationError(f"family fit ({law}): {exc}") from exc
    # theta, the creep weights, kappa and the lag (and Coleman-Hodgdon's alpha when searched)
    n_coefficients = theta.size + taus.size + 2 + int(law == "coleman-hodgdon" and alpha_per_v is None)
    n_coefficients += searched
    fit = _result(s, params, it, n_coefficients, t0)
    if law in ("bouc-wen", "domain-wall") and not fit.rms_um <= (constant := _train_scale_um(s)):
        # the returned law, not the search's linear fit, is what is scored: never hand back a law
        # that fits worse than a constant per experiment
        raise CalibrationError(
            f"family fit ({law}) failed: training RMS {fit.rms_um:.3g} um, worse than a constant "
            f"per experiment ({constant:.3g} um)"
        )
    return fit


#: The after-effect's search (:func:`_search_after_effect`): fluctuation voltages as fractions of
#: the session's voltage span, and relaxation times (s), on a grid; then a polish of both.
AE_FLUCTUATION_FRACTIONS = (0.003, 0.015, 0.075)
AE_TIMES_S = (1e-2, 1.0, 1e2, 1e4)
AE_POLISH_EVALUATIONS = 16
#: Gauss-Newton steps and play operators of a searched candidate's fit (the final fit runs on
#: the member's own plays to convergence).
AE_SEARCH_STEPS = 5
AE_SEARCH_PLAYS = 8
#: Bounds of the searched after-effect: ``g0`` from this fraction of the span (below it every
#: gap closes logarithmically from the start) to ``AE_MAX_FLUCTUATION_V`` (linear), ``tau`` (s).
AE_MIN_FLUCTUATION_FRACTION = 1e-4
AE_MAX_FLUCTUATION_V = 1e6
AE_TIME_BOUNDS_S = (1e-4, 1e9)


def _search_after_effect(s: _Session, r: F64, c: F64, lam: float, centre_smoothing: float) -> AfterEffect:
    """The after-effect whose fit leaves the least training RMS: a grid over ``g0`` (fractions of
    the span, :data:`AE_FLUCTUATION_FRACTIONS`) and ``tau`` (:data:`AE_TIMES_S`), each candidate
    fitted with :data:`AE_SEARCH_STEPS` steps, then a Nelder-Mead polish of both (log scale)."""
    data = s.data
    v = data.grid_voltage_v[data.compared]
    span = float(np.max(v) - np.min(v))
    r = default_thresholds(data, min(AE_SEARCH_PLAYS, r.size))
    lo = np.log([AE_MIN_FLUCTUATION_FRACTION * span, AE_TIME_BOUNDS_S[0]])
    hi = np.log([AE_MAX_FLUCTUATION_V, AE_TIME_BOUNDS_S[1]])
    scores: dict[tuple[float, float], float] = {}

    def candidate(z: F64) -> AfterEffect:
        g0, tau = np.exp(np.clip(z, lo, hi))
        return AfterEffect(float(g0), float(tau))

    def score(z: F64) -> float:
        ae = candidate(z)
        key = (ae.fluctuation_v, ae.time_s)
        if key not in scores:
            f_grid, f_rest, slope = _gplay_features(data, r, c, ae)
            theta_reg = _centre_smoothing(s, f_grid, r.size + 1, c.size, centre_smoothing)
            fit = _alternate(
                s,
                f_grid,
                f_rest,
                lam,
                max_iter=AE_SEARCH_STEPS,
                slope_of_theta=slope,
                refine=False,
                theta_reg=theta_reg,
            )
            scores[key] = fit[4] if math.isfinite(fit[4]) else math.inf
        return scores[key]

    grid = [np.log([f * span, t]) for f in AE_FLUCTUATION_FRACTIONS for t in AE_TIMES_S]
    best = min(grid, key=score)
    # the simplex's first steps: a factor e in g0 and e^1.5 in tau, about half a grid step
    simplex = np.vstack([best, best + np.array([1.0, 0.0]), best + np.array([0.0, 1.5])])
    polish = minimize(
        score,
        best,
        method="Nelder-Mead",
        options={"maxfev": AE_POLISH_EVALUATIONS, "xatol": 0.05, "fatol": 0.0, "initial_simplex": simplex},
    )
    z = polish.x if float(polish.fun) < score(best) else best
    return candidate(np.asarray(z, dtype=np.float64))


@dataclass(frozen=True, eq=False)
class ModelChoice:
    """The outcome of :func:`choose_model`.

    Attributes
    ----------
    chosen
        Name of the chosen candidate.
    fit
        The chosen family member refitted on all experiments (None when a non-family
        candidate won).
    heldout_rms_um
        Held-out prediction RMS per candidate (um).
    train_rms_um
        Training RMS per candidate (um).
    holdout
        Indices of the held-out experiments.
    fits
        The family members' fits on the training experiments, by candidate name.
    not_adoptable
        Candidates fitted and scored but never chosen (creep driver not adoptable).
    failed
        Candidates whose fit failed (:class:`~piezod.errors.CalibrationError`), with its message:
        skipped by the choice.
    """

    chosen: str
    fit: FamilyFit | None
    heldout_rms_um: dict[str, float]
    train_rms_um: dict[str, float]
    holdout: tuple[int, ...]
    fits: dict[str, FamilyFit] = field(default_factory=dict)
    not_adoptable: tuple[str, ...] = ()
    failed: dict[str, str] = field(default_factory=dict)

    def table(self) -> str:
        """One line per candidate: training and held-out RMS, the chosen one marked; failed fits last."""
        w = max([40, *map(len, self.heldout_rms_um), *map(len, self.failed)])
        lines = [f"{'model':<{w}} {'train RMS (nm)':>15} {'held-out RMS (nm)':>18}"]
        for name in self.heldout_rms_um:
            mark = "  <- chosen" if name == self.chosen else ""
            if name in self.not_adoptable:
                mark = "  (not adopted: its inverse is too slow for streaming)"
            train, held = 1e3 * self.train_rms_um[name], 1e3 * self.heldout_rms_um[name]
            lines.append(f"{name:<{w}} {train:>15.2f} {held:>18.2f}{mark}")
        for name, reason in self.failed.items():
            lines.append(f"{name:<{w}} {'failed':>15} {'-':>18}  ({reason})")
        return "\n".join(lines)


def holdout_mask(n_experiments: int, every: int = 4) -> NDArray[np.bool_]:
    """Training mask holding out experiments ``every - 1, 2 every - 1, ...`` (at least one trains)."""
    train = np.ones(n_experiments, dtype=bool)
    if n_experiments >= 2:
        train[every - 1 :: every] = False
        if not train.any():
            train[0] = True
    return train


def choose_model(
    data: DynamicCalibrationData,
    *,
    laws: Sequence[str] = LAWS,
    holdout_every: int = 4,
    others: dict[str, FamilyParams] | None = None,
    plays: int = DEFAULT_PLAYS,
    alpha_per_v: float | None = None,
    creep_drivers: Sequence[str] = CREEP_DRIVERS,
    adoptable_drivers: Sequence[str] = CREEP_DRIVERS,
    members: Sequence[tuple[str, str]] | None = None,
) -> ModelChoice:
    """Fit every law on the training experiments, compare held-out prediction RMS, refit the best.

    Family members within :data:`CHOICE_TIE_FRACTION` of the best held-out RMS are a tie, won by
    the one with the fewest coefficients (a candidate from ``others`` wins only outright). A play
    law's resolution is then refined: the same member with twice the plays (up to
    :data:`MAX_PLAYS`) replaces it when it predicts the held-out experiments better by more than
    the tie fraction (a stage whose loops have a few sharp kinks needs a finer grid than a smooth
    one; the finer member is named ``.../<n>-plays``). So is the generalised play law's centre
    grid, from :data:`GP_NODES` nodes to ``2 n - 1`` up to :data:`MAX_GP_NODES` (``.../<k>-nodes``):
    its density then bends more than once over the span (a Krasnosel'skii-Pokrovskii stage's
    loops, docs/model-family.md 6.2bo). A finer grid can also bend the slope the way a part on the
    absolute position does; :func:`piezod.stagecal.needs_one_sensor` ties such a member's offsets
    when they would place the part wrongly. A generalised play law with voltage-driven creep is
    last tried with its memory's after-effect (:mod:`piezod.model.aftereffect`, searched once;
    ``.../after-effect/voltage-creep``), adopted on the same terms (a stage whose loops depend on
    the rate), and then its grids are refined again with the after-effect held; so is the
    domain-wall law with voltage-driven creep. When an after-effect was adopted on another law,
    the domain-wall law with its walls' after-effect (searched) is tried last
    (``family/domain-wall/after-effect/voltage-creep``), on the same terms.

    Parameters
    ----------
    data
        The session.
    laws
        Family laws to try.
    holdout_every
        Every ``holdout_every``-th experiment is held out.
    others
        Further candidates, already fitted (e.g. the dynamic model as a family member), scored on
        the same held-out experiments; they win only by predicting better.
    plays
        Play operators of the Prandtl-Ishlinskii law.
    alpha_per_v
        Coleman-Hodgdon's ``alpha`` (searched when None).
    creep_drivers
        Creep drivers to try for every law (``position``, ``voltage``): candidates are named
        ``family/<law>`` (position-driven creep) and ``family/<law>/voltage-creep``.
    adoptable_drivers
        Creep drivers the choice may adopt; the others are fitted and scored but never chosen
        (the daemon passes :data:`piezod.model.family.REALTIME_CREEP_DRIVERS`).
    members
        ``(law, creep driver)`` pairs to fit instead of every one of ``laws`` x ``creep_drivers``
        (a choice redone on a shortlist, :func:`piezod.stagecal.audit_and_extend`).

    Raises
    ------
    CalibrationError
        No candidate is left to choose (every fit failed, or every one left is not adoptable),
        or the refit of the chosen one fails. A candidate whose fit fails is skipped and listed in
        :attr:`ModelChoice.failed` (shown by :meth:`ModelChoice.table`).
    """
    train = holdout_mask(data.n_experiments, holdout_every)
    heldout: dict[str, float] = {}
    train_rms: dict[str, float] = {}
    fits: dict[str, FamilyFit] = {}
    failed: dict[str, str] = {}
    pairs = [(law, driver) for law in laws for driver in creep_drivers] if members is None else members
    for law, driver in pairs:
        name = member_name(law, driver)
        try:
            fit = fit_family(
                data, law, train=train, plays=plays, alpha_per_v=alpha_per_v, creep_driver=driver
            )
        except CalibrationError as exc:
            failed[name] = str(exc)
            continue
        fits[name] = fit
        heldout[name] = fit.heldout_rms_um
        train_rms[name] = fit.rms_um
    for name, params in (others or {}).items():
        s = _Session(data, np.asarray(params.creep.taus_s), train)
        x = session_positions(data, params, s.dev)
        resid = _centre(data, x) - s.yc
        train_rms[name] = float(np.sqrt(np.mean(resid[s.train_rows] ** 2)))
        heldout[name] = float(np.sqrt(np.mean(resid[s.test_rows] ** 2))) if s.test_rows.any() else math.nan
    blocked = tuple(k for k, f in fits.items() if f.params.creep_driver not in adoptable_drivers)
    scores = {k: (v if math.isfinite(v) else train_rms[k]) for k, v in heldout.items() if k not in blocked}
    if not scores:
        reasons = "; ".join(f"{k}: {v}" for k, v in failed.items()) or "every candidate is not adoptable"
        raise CalibrationError(f"no model to choose: {reasons}")
    chosen = min(scores, key=lambda k: scores[k])
    final = None
    if chosen in fits:
        # ties within the held-out data's resolution go to the member with fewer coefficients
        limit = scores[chosen] * (1.0 + CHOICE_TIE_FRACTION)
        tied = [k for k in scores if k in fits and scores[k] <= limit]
        chosen = min(tied, key=lambda k: (fits[k].n - fits[k].dof, scores[k]))
        law, driver = fits[chosen].law, fits[chosen].params.creep_driver

        def finer(n_p: int, n_n: int, relaxing: AfterEffect | bool | None, trial: str | None = None) -> bool:
            """The chosen member on ``n_p`` plays and ``n_n`` centre nodes (and with ``relaxing``,
            :func:`fit_family`'s ``after_effect``; with ``trial`` another law), chosen when it
            predicts better by the tie fraction."""
            nonlocal chosen
            which = trial or law
            name = member_name(
                which, driver, n_p if n_p != plays else None, n_n if n_n != GP_NODES else None, bool(relaxing)
            )
            try:
                fit = fit_family(
                    data,
                    which,
                    train=train,
                    plays=n_p,
                    n_nodes=n_n,
                    alpha_per_v=alpha_per_v,
                    creep_driver=driver,
                    after_effect=relaxing,
                )
            except CalibrationError as exc:
                failed[name] = str(exc)
                return False
            fits[name] = fit
            heldout[name], train_rms[name] = fit.heldout_rms_um, fit.rms_um
            if not fit.heldout_rms_um < scores[chosen] * (1.0 - CHOICE_TIE_FRACTION):
                return False
            chosen = name
            scores[chosen] = fit.heldout_rms_um
            return True

        n_plays, n_nodes = plays, GP_NODES
        after_effect: AfterEffect | None = None

        def refine() -> None:
            nonlocal n_plays, n_nodes
            while law in PLAY_LAWS and 2 * n_plays <= MAX_PLAYS and finer(2 * n_plays, n_nodes, after_effect):
                n_plays *= 2
            gp = law == "generalised-play"
            while gp and 2 * n_nodes - 1 <= MAX_GP_NODES and finer(n_plays, 2 * n_nodes - 1, after_effect):
                n_nodes = 2 * n_nodes - 1

        refine()
        # the memory's relaxation (a stage whose loops depend on the rate), searched once; the grids
        # are refined again with it held: what the finer grids fit may have been its misfit
        if law in AFTER_EFFECT_LAWS and driver == "voltage" and finer(n_plays, n_nodes, True):
            after_effect = fits[chosen].params.after_effect
            refine()
        # loops that depend on the rate: the walls' after-effect on the domain-wall law, whose
        # branches bend towards a curve of the voltage (a Preisach law's relaxed memory cannot)
        if after_effect is not None and law != "domain-wall" and finer(plays, GP_NODES, True, "domain-wall"):
            law, n_plays, n_nodes = "domain-wall", plays, GP_NODES
            after_effect = fits[chosen].params.after_effect
        chosen_law = fits[chosen].params.hysteresis
        final = fit_family(
            data,
            law,
            plays=n_plays,
            n_nodes=n_nodes,
            alpha_per_v=alpha_per_v,
            creep_driver=driver,
            after_effect=after_effect,
            start=chosen_law if isinstance(chosen_law, DomainWallParams) else None,
        )
    holdout = tuple(int(i) for i in np.flatnonzero(~train))
    return ModelChoice(chosen, final, heldout, train_rms, holdout, fits, blocked, failed)


def family_model_config(params: FamilyParams) -> FamilyModelConfig:
    """The ``family:`` config section of ``params``.

    Raises
    ------
    CalibrationError
        The values do not fit the config schema.
    """
    h = params.hysteresis
    fields: dict[str, Any] = {
        "law": params.law,
        "b_um_per_v": h.b_um_per_v,
        "creep_taus_s": [float(f"{t:.6g}") for t in params.creep.taus],
        "creep_weights": [float(f"{w:.6g}") for w in params.creep.w],
        "lag_time_constant_s": params.lag_time_constant_s,
        "stiffness_pct_per_um": params.stiffness_pct_per_um,
        "creep_driver": params.creep_driver,
        "offset_um": params.offset_um,
    }
    if (ae := params.after_effect) is not None:
        fields.update(ae_fluctuation_v=ae.fluctuation_v, ae_time_s=ae.time_s, ae_interval_s=ae.interval_s)
    if isinstance(h, DomainWallParams):
        fields.update(
            dw_w_um_per_v=h.w_um_per_v,
            dw_pinning_v=h.pinning_v,
            dw_centre_v=h.centre_v,
            dw_width_v=h.width_v,
            dw_interaction=h.interaction,
        )
    elif isinstance(h, BoucWenParams):
        fields.update(
            bw_c_um_per_v=h.c_um_per_v,
            bw_rates_per_v=list(h.rates),
            bw_amp_down=h.amp_down,
            bw_exponent=h.exponent,
        )
    elif isinstance(h, GeneralisedPlayParams):
        fields.update(
            # full precision: a rounded node moves every play's density (6 digits cost 0.3 nm)
            gp_thresholds_v=list(h.thresholds_v),
            gp_nodes_v=list(h.nodes_v),
            gp_density=[list(row) for row in h.density],
        )
    elif isinstance(h, PlayParams):
        fields.update(
            pi_rho0=h.rho0,
            pi_thresholds_v=[float(f"{r:.6g}") for r in h.thresholds_v],
            pi_weights=[float(f"{w:.6g}") for w in h.weights],
        )
    else:
        fields.update(alpha_per_v=h.alpha_per_v, u_um_per_v=h.u_um_per_v)
    try:
        return FamilyModelConfig(**fields)
    except ValueError as exc:
        raise CalibrationError(f"fitted family parameters are outside the config limits: {exc}") from exc


__all__ = [
    "AFTER_EFFECT_LAWS",
    "CREEP_DRIVERS",
    "DEFAULT_PLAYS",
    "LAWS",
    "MAX_PLAYS",
    "PLAY_LAWS",
    "FamilyFit",
    "ModelChoice",
    "choose_model",
    "default_taus",
    "default_thresholds",
    "family_model_config",
    "fit_family",
    "holdout_mask",
    "member_after_effect",
    "member_name",
    "member_nodes",
    "parse_member",
    "session_positions",
    "solve_linear",
]
