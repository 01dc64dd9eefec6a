"""Is the baseline determined by the data? Parameters on bounds, collapsed directions, correlations.

A baseline the data cannot determine (``alpha`` collapsing to its bound with ``b`` running away,
a condition number of 1e10, two parameters correlated to 0.99999) fits any residual structure
with an arbitrary mix of its parameters: no cause can be named on top of it. The audit states
what the data cannot determine and which measurement would determine it, and names no cause.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from piezod.audit.baseline import Geometry, OdeBase, at_bound
from piezod.audit.fitting import Fit, Problem, jacobian
from piezod.fitstats import jacobian_covariance

F64 = NDArray[np.float64]

#: Condition number (column-normalised Jacobian) above which the baseline counts as undetermined.
MAX_CONDITION = 1e7
#: Largest |correlation| of two baseline parameters that is still determined.
MAX_CORRELATION = 0.99999
#: A condition number above this is a collapse (a direction the data do not see at all).
COLLAPSED_CONDITION = 1e10
#: Largest |correlation| of a candidate's parameter with a baseline parameter on an undetermined baseline.
MAX_EXTENSION_CORRELATION = 0.99

#: ``alpha`` times the voltage span below which the ODE's branches are parabolic over the whole
#: record (:func:`rayleigh_note`): ``exp(-0.1)`` is 0.90, the branch has gone a tenth of its way
#: towards the anhysteretic line.
RAYLEIGH_LIMIT = 0.1

#: Which measurement determines each (public) baseline parameter.
_MEASUREMENT = {
    "alpha_per_v": "loops of several amplitudes (nested minor loops, or a larger voltage span)",
    "b_um_per_v": "loops of several amplitudes with a larger voltage span",
    "u_um_per_v": "loops of several amplitudes with a larger voltage span",
    "tau_s": "triangular scans at line rates a decade or more apart",
    "a1": "triangular scans at line rates a decade or more apart",
    "a2_per_v": "scans of several ranges and offsets",
    "a3": "scans of several ranges and offsets",
}


@dataclass(frozen=True)
class Degeneracy:
    """What the baseline fit cannot determine.

    Attributes
    ----------
    undetermined
        Public baseline parameters the data do not determine.
    condition_number
        Of the column-normalised baseline Jacobian.
    max_correlation
        Largest |correlation| between two baseline parameters.
    on_bounds
        Parameters that sit on a bound.
    text
        The plain statement for the report (empty when determined).
    collapsed
        Parameters on bounds or a condition number above :data:`COLLAPSED_CONDITION` (not only
        a strong correlation between two baseline parameters).
    extension_correlation
        Largest |correlation| of a candidate parameter with a baseline parameter (0 without
        candidates): above :data:`MAX_EXTENSION_CORRELATION` the extension is entangled with
        what the data do not determine.
    absent
        Baseline parameters of a term the fit left out (the creep factor's ``tau_s`` and ``a1``,
        with ``a1`` at 0 or ``tau_s`` on a bound): the model without that term is analysed, these
        are not.
    """

    undetermined: tuple[str, ...]
    condition_number: float
    max_correlation: float
    on_bounds: tuple[str, ...]
    text: str
    collapsed: bool = False
    extension_correlation: float = 0.0
    absent: tuple[str, ...] = ()

    @property
    def blocks_a_cause(self) -> bool:
        """No cause may be named: collapsed, or the extension entangled with the undetermined part."""
        return self.degenerate and (self.collapsed or self.extension_correlation > MAX_EXTENSION_CORRELATION)

    @property
    def degenerate(self) -> bool:
        """The data do not determine the baseline."""
        return bool(self.text)


def check(fit: Fit, geo: Geometry, rows: NDArray[np.bool_]) -> Degeneracy:
    """Conditioning, correlations and bounds of the fitted baseline ``fit`` (no candidates)."""
    model = fit.model
    # Public name of every internal baseline parameter (ODE: (ln alpha, u, alpha (b - u))).
    names = (
        ("alpha_per_v", "u_um_per_v", "b_um_per_v") if isinstance(model.base, OdeBase) else model.base.names
    )
    p = fit.p
    # A term the fit made constant over the data (its amplitude at 0, its time constant on a
    # bound) leaves its parameters without effect or trading with the rest: the model is the one
    # without the term, determined or not by the rest (a zero column is not a direction the data
    # fail to see, it is no direction at all).
    free = model.free()
    gone = [k for k in model.base.absent(p[: model.n_base]) if free[k]]
    free[gone] = False
    absent = tuple(names[k] for k in gone)
    lo, hi = model.bounds()
    on: list[str] = []
    for k in np.flatnonzero(free[: model.n_base]).tolist():
        for b in (lo[k], hi[k]):
            if at_bound(float(p[k]), float(b)):
                on.append(names[k])
    if isinstance(model.base, OdeBase) and (p[2] <= 1e-12 or "b_um_per_v" in on):
        # b = u (the loop opening alpha (b - u) at 0, to the bounds' tolerance): alpha has no effect
        on.append("alpha_per_v")
    prob = Problem(model, geo, rows)
    jac = jacobian(prob, p, free, central=True)
    cov = jacobian_covariance(jac, fit.rss, max(fit.dof, 1))
    corr = np.nan_to_num(np.abs(cov.corr - np.eye(cov.corr.shape[0])), nan=1.0)
    max_corr = float(corr.max()) if corr.size else 0.0
    bad = list(dict.fromkeys(on))
    fidx = np.flatnonzero(free).tolist()
    if cov.condition_number > MAX_CONDITION:
        # The parameters in the direction the data do not see (smallest singular vector).
        norms = np.linalg.norm(jac, axis=0)
        norms[norms == 0] = 1.0
        _, _, vt = np.linalg.svd(jac / norms, full_matrices=False)
        weak = np.flatnonzero(np.abs(vt[-1]) > 0.3).tolist()
        bad += [names[fidx[j]] for j in weak if fidx[j] < model.n_base]
    if max_corr > MAX_CORRELATION:
        i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)
        bad += [names[fidx[k]] for k in (int(i), int(j)) if fidx[k] < model.n_base]
    bad = list(dict.fromkeys(bad))
    nb = sum(1 for k in fidx if k < model.n_base)
    ext = float(corr[:nb, nb:].max()) if corr.shape[0] > nb and nb > 0 else 0.0
    collapsed = bool(on) or cov.condition_number > COLLAPSED_CONDITION
    if not bad:
        return Degeneracy((), cov.condition_number, max_corr, tuple(on), "", collapsed, ext, absent)
    public = model.base.public(p[: model.n_base])
    vals = ", ".join(f"{k} = {public[k]:.4g}" for k in bad if k in public)
    need = list(dict.fromkeys(_MEASUREMENT.get(k, "more varied scans") for k in bad))
    text = (
        f"the data do not determine the baseline: {vals}"
        + (f" (on a bound: {', '.join(on)})" if on else "")
        + f"; condition number {cov.condition_number:.3g}, largest correlation {max_corr:.6f}. "
        f"What would determine it: {'; '.join(need)}. No cause is named on an undetermined baseline."
    )
    return Degeneracy(tuple(bad), cov.condition_number, max_corr, tuple(on), text, collapsed, ext, absent)


def rayleigh_note(public: dict[str, float], span_v: float) -> str | None:
    """What the ODE baseline's parameters mean when its loop is in the Rayleigh limit, else None.

    With ``alpha`` times the voltage span far below 1 the exponential approach (2.22) never gets
    far: every branch is the parabola ``u dV + s alpha (b - u) dV^2 / 2`` (``dV`` from the
    reversal), the Rayleigh law of weak-field piezo and ferro hysteresis. The fit then sets
    ``alpha`` and ``b`` by the branches' small cubic term only, and ``b`` is the slope of an
    anhysteretic line the data never approach -- on real stacks many times the stage's own
    sensitivity. The sizes the data show are ``u`` and the product ``alpha (b - u)``.

    Parameters
    ----------
    public
        The baseline's ``alpha_per_v``, ``b_um_per_v``, ``u_um_per_v``.
    span_v
        The voltage span of the data.
    """
    alpha, b, u = public["alpha_per_v"], public["b_um_per_v"], public["u_um_per_v"]
    reach = alpha * span_v
    if not (span_v > 0 and reach < RAYLEIGH_LIMIT):
        return None
    return (
        f"baseline: alpha x the voltage span = {reach:.2g} (far below 1): the ODE's branches are "
        f"parabolic over the whole record (its Rayleigh limit), so alpha = {alpha:.3g} 1/V and "
        f"b = {b:.4g} um/V are not sizes of the stage (b is the slope of an anhysteretic line the "
        f"branches never approach); the data determine the slope after a reversal, u = {u:.4g} um/V, "
        f"and the branches' curvature, alpha (b - u) = {alpha * (b - u):.3g} um/V^2"
    )
