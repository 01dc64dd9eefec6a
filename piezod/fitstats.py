"""Statistics of a least-squares fit shared by the calibrations: covariance, correlations, bounds."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

#: Singular values below this fraction of the largest count as zero (infinite variance).
_SV_FLOOR = 1e-13
#: A condition number above this is reported as ill-conditioned.
ILL_CONDITIONED = 1e8


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
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    inv_sv2 = np.where(sv > sv[0] * _SV_FLOOR, 1.0 / np.maximum(sv, 1e-300) ** 2, np.inf)
    s2 = sum_sq / max(dof, 1)
    cov = (vt.T * inv_sv2) @ vt / np.outer(norms, norms) * s2
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
