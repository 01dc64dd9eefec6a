"""Least-squares fits of an :class:`~piezod.audit.candidates.AuditModel` and its held-out error.

The residual of a fit is the measured position minus the model, projected per segment onto the
complement of the nuisance columns (offset, initial states): the exact optimum over the
nuisance parameters for every model parameter vector. The solver is a bounded
Levenberg-Marquardt on the column-scaled normal equations with a forward-difference Jacobian
(:func:`levenberg_marquardt`). Held-out errors come from fits without the held-out segments,
evaluated on the held-out segments with only their nuisance parameters fitted there.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from piezod.audit.baseline import Geometry
from piezod.audit.candidates import AuditModel, Candidate
from piezod.audit.projection import Projector
from piezod.errors import ModelError
from piezod.fitstats import FitResult

F64 = NDArray[np.float64]

#: Contiguous blocks of the held-out data of the jackknife of a gain.
JACKKNIFE_BLOCKS = 10


@dataclass(frozen=True, eq=False, kw_only=True)
class Fit(FitResult):
    """A fitted model: the shared :class:`~piezod.fitstats.FitResult` (the projected residual,
    ``n``, ``dof`` = ``n`` minus the free parameters and the nuisance terms, BIC) and the model.

    The audit's fits compute no standard errors at the solution (the degeneracy check does,
    :mod:`piezod.audit.degenerate`); ``cost`` is half the residual sum of squares.

    Attributes
    ----------
    model
        The model.
    p
        Internal parameters.
    """

    model: AuditModel
    p: F64

    @property
    def rms_um(self) -> float:
        """RMS residual."""
        return self.residual_rms_um

    @property
    def k(self) -> int:
        """Free parameters, nuisance terms included (for the BIC)."""
        return self.n_coefficients

    @property
    def residual(self) -> F64:
        """Projected residual (measured minus model) of the fitted rows."""
        return self.residuals_um


class Problem:
    """A model on the rows ``rows`` of a geometry.

    Parameters
    ----------
    model
        The model.
    geo
        The data.
    rows
        Samples that enter (boolean, per sample).
    """

    def __init__(self, model: AuditModel, geo: Geometry, rows: NDArray[np.bool_]) -> None:
        self.model = model
        self.geo = geo
        self.rows = rows
        self.y = geo.data.position_um[rows]
        self.seg = geo.data.segment[rows]
        self._const_proj: Projector | None = None
        self.nfev = 0

    def projector(self, extra: F64 | None) -> Projector:
        """Projector of the nuisance terms (cached when there are only offsets)."""
        if extra is None:
            if self._const_proj is None:
                self._const_proj = Projector(self.seg)
            return self._const_proj
        return Projector(self.seg, extra[self.rows])

    def residual(self, p: F64) -> F64:
        """Projected residual at ``p``."""
        self.nfev += 1
        x, extra = self.model.evaluate(p, self.geo)
        r = self.y - x[self.rows]
        out: F64 = self.projector(extra)(r)
        return out

    def n_nuisance(self, p: F64) -> int:
        """Active nuisance terms at ``p``."""
        _, extra = self.model.evaluate(p, self.geo)
        return self.projector(extra).n_nuisance

    def fit(
        self,
        p0: F64,
        *,
        max_nfev: int | None = None,
        free: NDArray[np.bool_] | None = None,
    ) -> Fit:
        """Least-squares fit from ``p0`` (parameters outside ``free`` held), see :func:`levenberg_marquardt`.

        Raises
        ------
        ModelError
            The model cannot be evaluated (non-finite values).
        """
        mask = self.model.free() if free is None else free
        lo, hi = self.model.bounds()
        start_nfev = self.nfev
        t0 = time.perf_counter()
        p_fit, r, success = levenberg_marquardt(
            self, np.asarray(p0, dtype=np.float64), mask, lo, hi, max_nfev
        )
        if not np.all(np.isfinite(r)):
            raise ModelError(f"the model {'+'.join(('baseline', *self.model.effects))} is not finite")
        k = int(mask.sum()) + self.n_nuisance(p_fit)
        rss = float(r @ r)
        return Fit(
            model=self.model,
            p=p_fit,
            residuals_um=r,
            cost=0.5 * rss,
            n=int(r.size),
            dof=int(r.size) - k,
            nfev=self.nfev - start_nfev,
            success=success,
            message="converged" if success else "stopped: iteration or evaluation budget spent",
            seconds=time.perf_counter() - t0,
        )


def levenberg_marquardt(
    problem: Problem,
    p0: F64,
    free: NDArray[np.bool_],
    lo: F64,
    hi: F64,
    max_nfev: int | None = None,
    *,
    max_iter: int = 60,
    rtol: float = 1e-10,
) -> tuple[F64, F64, bool]:
    """Bounded Levenberg-Marquardt on the normal equations with a forward-difference Jacobian.

    The problems here have many rows (~1e5) and few parameters (<= ~12): the normal equations
    (column-scaled, p x p) are cheap where an SVD of the Jacobian is not. Bounds are kept by
    clipping the step and freezing parameters on a bound whose gradient points outwards.

    Returns
    -------
    p, residual, converged
    """
    p = np.clip(p0.copy(), lo, hi)
    r = problem.residual(p)
    if not np.all(np.isfinite(r)):
        return p, r, False
    cost = float(r @ r)
    if not free.any():
        return p, r, True
    budget = math.inf if max_nfev is None else max_nfev
    used = 0
    lam = 1e-3
    converged = False
    for _ in range(max_iter):
        jac = jacobian(problem, p, free, r)
        used += jac.shape[1] + 1
        g = jac.T @ r
        h = jac.T @ jac
        d = np.sqrt(np.diag(h))
        d[d == 0] = 1.0
        hs = h / np.outer(d, d)
        gs = g / d
        idx = np.flatnonzero(free)
        at_lo = np.isfinite(lo[idx]) & (p[idx] <= lo[idx] + 1e-12 * np.maximum(1.0, np.abs(p[idx])))
        at_hi = np.isfinite(hi[idx]) & (p[idx] >= hi[idx] - 1e-12 * np.maximum(1.0, np.abs(p[idx])))
        # Gradient of the cost 0.5 |r|^2 is J^T r with J = d r / d p; descent moves along -g.
        act = (at_lo & (gs > 0)) | (at_hi & (gs < 0))
        keep = ~act
        if not keep.any():
            converged = True
            break
        improved = False
        while lam < 1e12:
            a = hs[np.ix_(keep, keep)] + lam * np.eye(int(keep.sum()))
            try:
                step_s = np.linalg.solve(a, -gs[keep])
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            q = p.copy()
            q[idx[keep]] += step_s / d[keep]
            q = np.clip(q, lo, hi)
            r_new = problem.residual(q)
            used += 1
            c_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else math.inf
            if c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                p, r, cost = q, r_new, c_new
                lam = max(lam / 5.0, 1e-9)
                improved = True
                if rel < rtol:
                    converged = True
                break
            lam *= 8.0
            if used >= budget:
                break
        if not improved:
            converged = True
            break
        if converged or used >= budget:
            break
    return p, r, converged


def _gauss_newton_step(jac: F64, r: F64) -> F64:
    """Step ``delta`` minimising ``|r + J delta|`` (column-scaled normal equations)."""
    h = jac.T @ jac
    d = np.sqrt(np.diag(h))
    d[d == 0] = 1.0
    hs = h / np.outer(d, d) + 1e-12 * np.eye(d.size)
    step: F64 = np.linalg.solve(hs, -(jac.T @ r) / d) / d
    return step


def linear_start(problem: Problem, p: F64, cand_slice: slice, step: float = 1e-4) -> F64:
    """Candidate parameters from one Gauss-Newton step at ``p`` with the baseline frozen."""
    lo, hi = problem.model.bounds()
    r0 = problem.residual(p)
    k = cand_slice.stop - cand_slice.start
    cols = np.empty((r0.size, k))
    for j in range(k):
        q = p.copy()
        idx = cand_slice.start + j
        h = step * max(1.0, abs(q[idx]))
        if q[idx] + h > hi[idx]:
            h = -h
        q[idx] += h
        cols[:, j] = (r0 - problem.residual(q)) / h
    out = p[cand_slice] + _gauss_newton_step(-cols, r0)
    lo_c, hi_c = lo[cand_slice], hi[cand_slice]
    clipped: F64 = np.clip(out, lo_c, hi_c)
    return clipped


def _cost(problem: Problem, p: F64) -> float:
    r = problem.residual(p)
    return float(r @ r) if np.all(np.isfinite(r)) else math.inf


def fit_candidate(
    problem: Problem,
    parent: Fit,
    cand: Candidate,
    *,
    max_nfev: int | None = None,
) -> Fit:
    """Fit ``parent.model + cand`` on ``problem``'s rows: best start, the candidate alone, a joint fit.

    The start is the best of the neutral parameters, a linearised (Gauss-Newton) step and the
    candidate's grids; then the candidate's parameters are fitted with the rest held, then all
    parameters jointly from there (Levenberg-Marquardt to convergence: at most 60 iterations or
    ``max_nfev`` evaluations).

    ``problem.model`` must already be the extended model.
    """
    model = problem.model
    sl = model.slices()[cand.effect]
    neutral = cand.neutral(model.scales)
    p_neutral = np.concatenate((parent.p, neutral))
    starts = [p_neutral]
    lin = linear_start(problem, p_neutral, sl)
    starts.append(np.concatenate((parent.p, lin)))
    for g in cand.grid(model.scales):
        starts.append(np.concatenate((parent.p, g)))
    suggested = cand.grid_from_residual(model.scales, problem.geo, problem.rows, parent.residual)
    first_suggested = len(starts)
    for g in suggested:
        starts.append(np.concatenate((parent.p, g)))
    costs = np.array([_cost(problem, s) for s in starts])
    # Candidate alone from the best start and from the best start the residual suggests (a
    # mistuned resonance can cost more than a lag-like one before it is tuned), then jointly.
    picks = [int(np.argmin(costs))]
    if suggested:
        picks.append(first_suggested + int(np.argmin(costs[first_suggested:])))
    only = np.zeros(model.size, dtype=bool)
    only[sl] = True
    stage1 = min(
        (problem.fit(starts[k], free=only, max_nfev=40 * cand.size) for k in dict.fromkeys(picks)),
        key=lambda f: f.rss,
    )
    # Baseline at its optimum, candidate fitted: the joint fit moves everything together.
    return problem.fit(stage1.p, max_nfev=max_nfev)


@dataclass(frozen=True, eq=False)
class HeldOut:
    """Held-out prediction error of a model.

    Attributes
    ----------
    rms_um
        Pooled RMS of the held-out residuals.
    residual
        Held-out residual per held-out row (in row order of ``rows``).
    rows
        Held-out samples (boolean, per sample of the held-out geometry).
    gains
        Sensor gain fitted per validation recording (validation only).
    """

    rms_um: float
    residual: F64
    rows: NDArray[np.bool_]
    gains: dict[str, float] = field(default_factory=dict)

    def block_ss(self, blocks: int = JACKKNIFE_BLOCKS) -> F64:
        """Sum of squared held-out residuals in ``blocks`` contiguous blocks (sample order)."""
        n = self.residual.size
        k = max(1, min(blocks, n))
        edges = (np.arange(k + 1) * n) // k
        csum = np.concatenate(([0.0], np.cumsum(self.residual**2)))
        out: F64 = csum[edges[1:]] - csum[edges[:-1]]
        return out


def gain_with_se(before: HeldOut, after: HeldOut, blocks: int = JACKKNIFE_BLOCKS) -> tuple[float, float]:
    """Held-out gain ``RMS before / RMS after`` and its standard error.

    The standard error is a delete-one block jackknife over ``blocks`` contiguous blocks of the
    held-out samples (the same samples before and after, so the scatter of the data common to
    both cancels; contiguous blocks keep the residuals' correlation in time inside a block).
    """
    if before.residual.size != after.residual.size or after.residual.size == 0:
        return math.nan, math.nan
    sb, sa = before.block_ss(blocks), after.block_ss(blocks)
    tb, ta = float(sb.sum()), float(sa.sum())
    if not ta > 0:
        return math.inf, math.nan
    gain = math.sqrt(tb / ta)
    k = sb.size
    if k < 2:
        return gain, math.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        loo = np.sqrt((tb - sb) / (ta - sa))
    loo = loo[np.isfinite(loo)]
    if loo.size < 2:
        return gain, math.nan
    se = math.sqrt((loo.size - 1) / loo.size * float(np.sum((loo - loo.mean()) ** 2)))
    return gain, se


def folds_of(n_segments: int, k: int) -> list[NDArray[np.bool_]]:
    """Interleaved folds over segments (segment ``s`` is in fold ``s % k``)."""
    k = max(2, min(k, n_segments))
    idx = np.arange(n_segments)
    return [idx % k == g for g in range(k)]


def jacobian(
    problem: Problem, p: F64, free: NDArray[np.bool_], r0: F64 | None = None, *, central: bool = False
) -> F64:
    """Finite-difference Jacobian (forward, or central) of the projected residual over the free parameters."""
    lo, hi = problem.model.bounds()
    r0 = problem.residual(p) if r0 is None else r0
    idx = np.flatnonzero(free)
    out = np.empty((r0.size, idx.size))
    for j, k in enumerate(idx):
        h = (1e-5 if central else 1e-7) * max(1.0, abs(float(p[k])))
        up = p.copy()
        dn = p.copy()
        if central and p[k] - h >= lo[k] and p[k] + h <= hi[k]:
            up[k] += h
            dn[k] -= h
            out[:, j] = (problem.residual(up) - problem.residual(dn)) / (2.0 * h)
            continue
        if p[k] + h > hi[k]:
            h = -h
        up[k] += h
        out[:, j] = (problem.residual(up) - r0) / h
    return out


def heldout_cv(
    model: AuditModel,
    geo: Geometry,
    full: Fit,
    folds: Sequence[NDArray[np.bool_]],
    *,
    refit: bool = False,
    max_nfev: int | None = None,
    chord_steps: int = 2,
) -> HeldOut:
    """K-fold cross-validation over segments.

    Without ``refit`` every fold is refitted by a few damped Gauss-Newton (chord) steps from the
    full fit that reuse the Jacobian of the full fit restricted to the fold's training rows:
    each step re-evaluates the residual, is damped until the fold's training cost decreases,
    and so follows the leave-fold-out optimum without a new Jacobian per fold. With ``refit``
    every fold is refitted by the solver, warm-started at the full fit.
    """
    data = geo.data
    seg = data.segment
    rows = data.fit_mask
    free = model.free()
    lo, hi = model.bounds()
    resid = np.empty(data.n)
    test_all = np.zeros(data.n, dtype=bool)
    prob = Problem(model, geo, rows)
    r_full = prob.residual(full.p)
    jac = None if refit else jacobian(prob, full.p, free, r_full)
    h_full = None if jac is None else jac.T @ jac
    idx = np.flatnonzero(free)
    for fold in folds:
        test_seg = fold[seg]
        test = rows & test_seg
        keep = ~test_seg[rows]
        if refit:
            p_fold = Problem(model, geo, rows & ~test_seg).fit(full.p, max_nfev=max_nfev).p
            r_fold = prob.residual(p_fold)
        else:
            assert jac is not None and h_full is not None
            p_fold, r_fold = full.p, r_full
            j_te = jac[~keep]
            h = h_full - j_te.T @ j_te
            d = np.sqrt(np.maximum(np.diag(h), 0.0))
            d[d == 0] = 1.0
            hs = h / np.outer(d, d)
            cost = float(r_fold[keep] @ r_fold[keep])
            lam = 1e-6
            for _ in range(chord_steps):
                g = (jac.T @ np.where(keep, r_fold, 0.0)) / d
                moved = False
                while lam < 1e8:
                    step = np.linalg.solve(hs + lam * np.eye(d.size), -g) / d
                    q = p_fold.copy()
                    q[idx] += step
                    q = np.clip(q, lo, hi)
                    r_q = prob.residual(q)
                    c_q = float(r_q[keep] @ r_q[keep]) if np.all(np.isfinite(r_q)) else math.inf
                    if c_q < cost:
                        p_fold, r_fold, cost = q, r_q, c_q
                        lam = max(lam / 10.0, 1e-9)
                        moved = True
                        break
                    lam *= 10.0
                if not moved:
                    break
        resid[test] = r_fold[~keep]
        test_all |= test
    r_all = resid[test_all]
    return HeldOut(rms_um=math.sqrt(float(np.mean(r_all**2))), residual=r_all, rows=test_all)


def heldout_validate(model: AuditModel, geo_val: Geometry, full: Fit) -> HeldOut:
    """Prediction error on separate validation recordings.

    Only nuisance terms are fitted on the validation data: per experiment the offset (and the
    ODE's initial state), and per recording file one sensor gain (a separate session: the
    sensor and amplifier gains need not be those of the training session).

    Returns
    -------
    HeldOut
        With the fitted gains in ``gains`` (file -> gain).
    """
    data = geo_val.data
    rows = data.fit_mask
    x, extra = model.evaluate(full.p, geo_val)
    proj = Projector(data.segment[rows], None if extra is None else extra[rows])
    r = proj(data.position_um[rows] - x[rows])
    xp = proj(x[rows])
    paths = np.array([data.info[i].path or "" for i in data.experiment[rows]])
    gains: dict[str, float] = {}
    for path in dict.fromkeys(paths.tolist()):
        sel = paths == path
        den = float(xp[sel] @ xp[sel])
        g = float(xp[sel] @ r[sel]) / den if den > 0 else 0.0
        r[sel] -= g * xp[sel]
        gains[path] = 1.0 + g
    return HeldOut(rms_um=math.sqrt(float(np.mean(r**2))), residual=r, rows=rows, gains=gains)
