"""The audit's baselines: the thesis model (3.8) for triangular scans, the hysteresis ODE (2.21) otherwise.

Thesis baseline
---------------
Every experiment is a steady triangular scan; the model is (3.8) with the 7 parameters of
:mod:`piezod.calibrate` and one position offset per experiment. The start comes from
:func:`piezod.calibrate.auto_start` (no prior needed); the audit then fits and evaluates the
same model as :mod:`piezod.calibrate`, vectorised, with the hooks its candidates need (voltage
and turning points replaced, an extra term in the creep factor). Internal parameters: see
:class:`ThesisBase`.

ODE baseline
------------
Any waveform: the exact per-sample hysteresis step (:func:`piezod.model.ode.hysteresis_step`)
with shared ``alpha, b, u`` run through every experiment from a relaxed start; the unknown
initial state enters linearly (``y_0 exp(-L)``, ``L`` the scaled voltage travel) and is a
nuisance parameter of the experiment, like its position offset. Internally
``z = (ln alpha, u, kappa)`` with ``kappa = alpha (b - u)``: when ``alpha V`` is small the
branches are parabolas whose curvature is ``kappa``, so this stays well conditioned where
``b`` alone would run away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from piezod.audit.data import AuditData
from piezod.audit.projection import Projector
from piezod.calibrate import PARAM_NAMES, auto_start, prepare
from piezod.errors import CalibrationError
from piezod.fitstats import solve_linear
from piezod.model.ode import HysteresisState, hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.recording import Experiment

F64 = NDArray[np.float64]

THESIS = "thesis"
ODE = "ode"

_T_LOWER = np.array([math.log(1e-6), 1e-9, 1e-12, math.log(1e-3), 0.0, -np.inf, -np.inf])
_T_UPPER = np.array([math.log(0.999), 99.0, np.inf, math.log(1e5), 0.999, np.inf, np.inf])


def at_bound(value: float, bound: float) -> bool:
    """Whether an internal parameter ``value`` sits on ``bound`` (a relative tolerance of 1e-6).

    One tolerance for every reading of "on a bound" in the audit: a term left out
    (:meth:`ThesisBase.absent`) and a parameter the degeneracy check reports on a bound.
    """
    return math.isfinite(bound) and abs(value - bound) <= 1e-6 * max(1.0, abs(bound))


@dataclass(frozen=True, eq=False)
class Geometry:
    """Per-sample and per-experiment arrays of one :class:`AuditData` that the models reuse.

    Attributes
    ----------
    data
        The data.
    exp
        Experiment index per sample.
    counts
        Samples per experiment.
    v_min, v_max, frequency_hz, dt_s
        Per experiment.
    slices
        Sample slice of every experiment.
    v_from_turn
        ``s (V - V_turn)`` per sample: voltage travelled since the turning point the branch starts at.
    v_from_centre
        ``V - V_C`` per sample.
    rest_index
        The sample whose voltage is nearest to 0 V (the rest position of the stage).
    cache
        Precomputed arrays of the candidates that depend only on the data (e.g. creep weights).
    period
        Samples per period per experiment (0 = not periodic).
    t_rel_s
        Session time relative to the model's reference time, per sample.
    log_f
        ``ln(f_ref / f)`` per experiment (0 where not periodic).
    """

    data: AuditData
    exp: NDArray[np.intp]
    counts: NDArray[np.intp]
    v_min: F64
    v_max: F64
    frequency_hz: F64
    dt_s: F64
    period: NDArray[np.intp]
    t_rel_s: F64
    log_f: F64
    slices: tuple[slice, ...]
    v_from_turn: F64
    v_from_centre: F64
    rest_index: int
    cache: dict[object, object] = field(default_factory=dict)


def geometry(data: AuditData, t_ref_s: float, f_ref_hz: float) -> Geometry:
    """Precompute the arrays of ``data`` for models referenced to ``t_ref_s`` and ``f_ref_hz``."""
    f = data.per_experiment("frequency_hz")
    log_f = np.where(np.isfinite(f) & (f > 0), np.log(f_ref_hz / np.where(f > 0, f, 1.0)), 0.0)
    counts = data.counts
    v_min = data.per_experiment("v_min")
    v_max = data.per_experiment("v_max")
    s = data.direction
    v = data.voltage_v
    v_turn = np.where(s > 0, np.repeat(v_min, counts), np.repeat(v_max, counts))
    return Geometry(
        data=data,
        exp=data.experiment,
        counts=counts,
        v_min=v_min,
        v_max=v_max,
        frequency_hz=f,
        dt_s=data.per_experiment("dt_s"),
        period=np.array([e.period_samples for e in data.info], dtype=np.intp),
        t_rel_s=data.t_s - t_ref_s,
        log_f=log_f,
        slices=tuple(data.slice(i) for i in range(data.n_experiments)),
        v_from_turn=s * (v - v_turn),
        v_from_centre=v - np.repeat(0.5 * (v_min + v_max), counts),
        rest_index=int(np.argmin(np.abs(v))),
    )


@dataclass(frozen=True, eq=False)
class ThesisBase:
    """The 7-parameter model (3.8) with per-experiment offsets.

    Internally ``z = (ln alpha, b, delta, ln tau, A1, C2, C3)`` with ``delta = (b - u) / alpha``,
    ``C2 = delta A2 S`` and ``C3 = delta A3``: for fixed ``(alpha, tau, A1)`` the model is linear
    in ``(b, delta, C2, C3)``, which removes the curved valley that ``(b, u, A3)`` form (``u`` is a
    small difference of large numbers) and lets Gauss-Newton converge in a few steps.

    Attributes
    ----------
    a2_scale
        ``S``, the mean half range of the training frame.
    fixed
        Parameters held at their start (the frame cannot determine them).
    """

    a2_scale: float
    fixed: tuple[str, ...] = ()
    kind: str = THESIS

    @property
    def names(self) -> tuple[str, ...]:
        """Public parameter names."""
        return PARAM_NAMES

    @property
    def free(self) -> NDArray[np.bool_]:
        """Mask of the fitted internal parameters (``a2_per_v`` fixed holds ``C2``, ``a3`` never is)."""
        internal = ("alpha_per_v", "b_um_per_v", "u_um_per_v", "tau_s", "a1", "a2_per_v", "a3")
        return np.array([k not in self.fixed for k in internal])

    def bounds(self) -> tuple[F64, F64]:
        """Internal bounds."""
        return _T_LOWER.copy(), _T_UPPER.copy()

    def absent(self, z: F64) -> tuple[int, ...]:
        """Internal parameters of a term the fit at ``z`` left out: ``(tau, A1)`` when the
        frequency factor (3.5) ``1 - A1 exp(-1/(f tau))`` is constant over the line rates: ``A1``
        at 0 (``tau`` has no effect), or ``tau`` on a bound (at 1 ms the exponential is 0 below
        100 Hz; at 1e5 s it is 1 above 1e-3 Hz, and ``1 - A1`` trades with the loop's scale).

        The model at ``z`` is then (3.8) without its creep factor, a model of its own whose
        determination the degeneracy check (:mod:`piezod.audit.degenerate`) judges on the rest.
        """
        on_bound = (
            at_bound(float(z[4]), float(_T_LOWER[4]))
            or at_bound(float(z[3]), float(_T_LOWER[3]))
            or at_bound(float(z[3]), float(_T_UPPER[3]))
        )
        return (3, 4) if on_bound else ()

    def to_internal(self, p: ThesisParams) -> F64:
        """Internal vector of ``p``."""
        delta = (p.b_um_per_v - p.u_um_per_v) / p.alpha_per_v
        return np.array(
            [
                math.log(p.alpha_per_v),
                p.b_um_per_v,
                delta,
                math.log(p.tau_s),
                p.a1,
                delta * p.a2_per_v * self.a2_scale,
                delta * p.a3,
            ]
        )

    def public(self, z: F64) -> dict[str, float]:
        """Parameter name -> value."""
        alpha = math.exp(float(z[0]))
        b, delta = float(z[1]), float(z[2])
        return {
            "alpha_per_v": alpha,
            "b_um_per_v": b,
            "u_um_per_v": b - alpha * delta,
            "tau_s": math.exp(float(z[3])),
            "a1": float(z[4]),
            "a2_per_v": float(z[5]) / (delta * self.a2_scale),
            "a3": float(z[6]) / delta,
        }

    def evaluate(
        self,
        z: F64,
        geo: Geometry,
        voltage_v: F64 | None = None,
        v_min: F64 | None = None,
        v_max: F64 | None = None,
        k_extra: F64 | None = None,
    ) -> F64:
        """Positions of (3.8) without offsets.

        Parameters
        ----------
        z
            Internal parameters.
        geo
            The data's geometry (experiment index, frequencies).
        voltage_v, v_min, v_max
            Voltage per sample and turning voltages per experiment when a candidate transforms
            them (default: the data's).
        k_extra
            Added to the frequency factor ``1 - A1 exp(-1/(f tau))`` of (3.5), per experiment.
        """
        alpha = math.exp(float(z[0]))
        b, delta = float(z[1]), float(z[2])
        tau = math.exp(float(z[3]))
        a1, c2, c3 = float(z[4]), float(z[5]) / self.a2_scale, float(z[6])
        s = geo.data.direction
        counts = geo.counts
        if voltage_v is None or v_min is None or v_max is None:
            voltage_v, v_min, v_max = geo.data.voltage_v, geo.v_min, geo.v_max
            from_turn, from_centre = geo.v_from_turn, geo.v_from_centre
        else:
            v_turn = np.where(s > 0, np.repeat(v_min, counts), np.repeat(v_max, counts))
            from_turn = s * (voltage_v - v_turn)
            from_centre = voltage_v - np.repeat(0.5 * (v_min + v_max), counts)
        vr = np.maximum(v_max - v_min, 1e-12)
        vh = 0.5 * vr
        c_rel = 2.0 / (1.0 + np.exp(-alpha * vr))
        dd = np.tanh(alpha * vh) / vh
        ff = 1.0 - a1 * np.exp(-1.0 / (geo.frequency_hz * tau))
        if k_extra is not None:
            ff = ff + k_extra
        beta = ff * (c2 * vh + c3) * dd  # = k delta tanh(alpha V_h) / V_h = b_hat - b
        w = np.repeat(c_rel, counts) * np.exp(-alpha * from_turn)
        x: F64 = b * voltage_v - delta * s * (1.0 - w) + np.repeat(beta, counts) * from_centre
        return x


def _distinct(values: F64, rel: float = 0.05) -> int:
    """Number of distinct values (relative spacing above ``rel``)."""
    lv = np.sort(np.log(np.abs(values[values != 0])))
    return int(1 + np.count_nonzero(np.diff(lv) > rel)) if lv.size else 0


def thesis_start(experiments: list[Experiment]) -> tuple[ThesisBase, F64, tuple[str, ...]]:
    """Start of the thesis baseline from :func:`piezod.calibrate.auto_start` (no prior needed).

    Parameters the frame cannot determine are held, as calibrate does: ``tau_s`` with fewer than
    3 distinct frequencies (at 1 s), ``a1`` with one frequency (at 0), ``a2_per_v`` with fewer than
    3 distinct ranges (at 0).

    Returns
    -------
    base, z, notes
        The baseline, its internal start vector and notes on held parameters.

    Raises
    ------
    CalibrationError
        The frame cannot determine the model (fewer than 2 ranges, no hysteresis).
    """
    cdata = prepare(experiments)
    n_f = _distinct(cdata.frequency_hz)
    n_r = _distinct(cdata.v_max - cdata.v_min)
    if n_r < 2:
        raise CalibrationError(
            f"the frame has {n_r} distinct voltage range(s); the thesis model needs 2 or more"
        )
    held: dict[str, float] = {}
    notes: list[str] = []
    if n_f < 3:
        held["tau_s"] = 1.0
        notes.append(f"only {n_f} distinct frequencies: tau_s held at 1 s")
    if n_f < 2:
        held["a1"] = 0.0
        notes.append("one frequency only: a1 held at 0")
    if n_r < 3:
        held["a2_per_v"] = 0.0
        notes.append(f"only {n_r} distinct ranges: a2_per_v held at 0")
    start = auto_start(cdata, fixed=held)
    a2_scale = float(np.mean(0.5 * (cdata.v_max - cdata.v_min)))
    base = ThesisBase(a2_scale=a2_scale, fixed=tuple(k for k in PARAM_NAMES if k in held))
    lo, hi = base.bounds()
    z = np.clip(base.to_internal(start), lo, hi)
    return base, z, tuple(notes)


@dataclass(frozen=True, eq=False)
class OdeBase:
    """The hysteresis ODE (2.21) with shared ``alpha, b, u``, per-experiment offset and initial state.

    Attributes
    ----------
    alpha_bounds
        Bounds of ``alpha`` (1/V).
    """

    alpha_bounds: tuple[float, float]
    kind: str = ODE

    @property
    def names(self) -> tuple[str, ...]:
        """Public parameter names."""
        return ("alpha_per_v", "b_um_per_v", "u_um_per_v")

    @property
    def free(self) -> NDArray[np.bool_]:
        """All three are fitted."""
        return np.ones(3, dtype=bool)

    def absent(self, z: F64) -> tuple[int, ...]:
        """None: ``alpha`` without a loop opening (``b = u``) is a collapse, not a term left out."""
        return ()

    def bounds(self) -> tuple[F64, F64]:
        """Internal bounds of ``(ln alpha, u, kappa)``."""
        lo = np.array([math.log(self.alpha_bounds[0]), 1e-12, 0.0])
        hi = np.array([math.log(self.alpha_bounds[1]), np.inf, np.inf])
        return lo, hi

    def params(self, z: F64) -> HysteresisParams:
        """The ODE parameters of ``z``."""
        alpha = math.exp(float(z[0]))
        u = max(float(z[1]), 1e-12)
        kappa = max(float(z[2]), 0.0)
        return HysteresisParams(alpha, u + kappa / alpha, u)

    def public(self, z: F64) -> dict[str, float]:
        """Parameter name -> value."""
        p = self.params(z)
        return {"alpha_per_v": p.alpha_per_v, "b_um_per_v": p.b_um_per_v, "u_um_per_v": p.u_um_per_v}

    def evaluate(self, z: F64, geo: Geometry, voltage_v: F64) -> tuple[F64, F64]:
        """Hysteretic positions (0 at the rest position) and the initial-state basis ``exp(-L)``.

        The ODE starts in the periodic steady state of a periodic experiment (the fixed point of
        one period, exact because a period maps the state linearly), else in the state the
        experiment's own voltage history leaves (a first pass over the experiment). The
        initial-state nuisance ``y0 exp(-L)`` corrects what remains.
        """
        p = self.params(z)
        x, decay = ode_positions(p, voltage_v, geo.data.starts, geo.counts, geo.period)
        # Positions relative to the model's position nearest to 0 V (the stage's rest position):
        # the effects that act on the absolute position (thermal, stiffness, saturation, creep)
        # refer to it; the offsets absorb the constant.
        x -= x[geo.rest_index]
        return x, decay


#: Largest scaled voltage travel of one experiment for the one-pass closed form (exp(600) is finite).
_MAX_TRAVEL = 600.0


def ode_positions(
    p: HysteresisParams,
    voltage_v: F64,
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    periods: NDArray[np.intp],
) -> tuple[F64, F64]:
    """The exact ODE step (:func:`piezod.model.ode.hysteresis_step`) through all experiments at once.

    With ``y = x - b V`` the step is linear in ``y``; from ``y = 0`` at the first sample the
    response is ``Y_n = exp(-L_n) delta sum_k s_k (exp(L_{k-1}) - exp(L_k))`` (``L`` the scaled
    voltage travel since the experiment's start) and any initial state adds ``y_0 exp(-L_n)``.
    The initial state is the periodic steady state of a periodic experiment (the fixed point
    ``y_0 = Y_P / (1 - exp(-L_P))`` of one period ``P``), else the state the experiment's own
    history leaves (a first pass from rest, then the step back to the first voltage).
    Experiments whose scaled travel exceeds 600 are run through ``hysteresis_step`` in chunks.

    Returns
    -------
    x, decay
        Positions and ``exp(-L)`` per sample.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    alpha, b, delta = p.alpha_per_v, p.b_um_per_v, p.delta_um
    dv = np.diff(v, prepend=v[0])
    dv[starts] = 0.0
    step = alpha * np.abs(dv)
    big_l = np.cumsum(step)
    big_l -= np.repeat(big_l[starts], counts)
    ends = starts + counts - 1
    too_long = big_l[ends] > _MAX_TRAVEL
    big_l = np.minimum(big_l, _MAX_TRAVEL)
    e_l = np.exp(big_l)
    terms = np.sign(dv) * (np.exp(big_l - step) - e_l)
    cs = np.cumsum(terms)
    cs -= np.repeat(cs[starts], counts)
    decay = 1.0 / e_l
    y_free = decay * delta * cs
    y0 = np.empty(starts.size)
    for i, (s0, n, per) in enumerate(zip(starts.tolist(), counts.tolist(), periods.tolist(), strict=True)):
        if 0 < per < n:
            a = float(decay[s0 + per])
            c = float(y_free[s0 + per])
            y0[i] = c / (1.0 - a) if a < 1.0 - 1e-12 else c
        else:
            d0 = float(v[s0] - v[s0 + n - 1])
            a0 = math.exp(-alpha * abs(d0))
            y0[i] = (
                a0 * float(y_free[s0 + n - 1]) + math.copysign(1.0, d0) * delta * (a0 - 1.0)
                if d0
                else float(y_free[s0 + n - 1])
            )
    x: F64 = b * v + y_free + decay * np.repeat(y0, counts)
    for i in np.flatnonzero(too_long).tolist():
        sl = slice(int(starts[i]), int(starts[i] + counts[i]))
        x[sl], decay[sl] = _ode_experiment(p, v[sl], int(periods[i]))
    return x, decay


def _ode_experiment(p: HysteresisParams, v: F64, period: int) -> tuple[F64, F64]:
    """One experiment through ``hysteresis_step`` (long experiments; same initial state rule)."""
    travel = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(v)))))
    decay = np.exp(-p.alpha_per_v * travel)
    if 0 < period < v.size:
        x1, _ = hysteresis_step(
            p, v[1 : period + 1], HysteresisState(float(v[0]), p.b_um_per_v * float(v[0]))
        )
        c = float(x1[-1]) - p.b_um_per_v * float(v[period])
        a = float(decay[period])
        y_end = c / (1.0 - a) if a < 1.0 - 1e-12 else c
        start = HysteresisState(float(v[0]), p.b_um_per_v * float(v[0]) + y_end)
    else:
        _, start = hysteresis_step(p, v, relaxed_state(p, float(v[0])))
    x, _ = hysteresis_step(p, v, start)
    return x, decay


def ode_start(data: AuditData) -> tuple[OdeBase, F64]:
    """A start for the ODE baseline: ``alpha`` on a log grid, the rest by linear least squares.

    For fixed ``alpha`` the model ``b V + delta G(alpha) + y0_i exp(-L) + c_i`` is linear; the
    nuisance terms are projected out per segment.

    Raises
    ------
    CalibrationError
        The voltage does not move, or no ``alpha`` gives loops of the modelled orientation.
    """
    v = data.voltage_v
    span = float(np.ptp(v))
    if not span > 0:
        raise CalibrationError("the voltage is constant: the audit needs a moving voltage")
    base = OdeBase(alpha_bounds=(1e-4 / span, 60.0 / span))
    geo = geometry(data, 0.0, 1.0)
    rows = data.fit_mask
    first = data.first_segment[data.segment][rows]
    y = data.position_um[rows]
    best: tuple[float, F64] | None = None
    for la in np.linspace(math.log(2e-3 / span), math.log(30.0 / span), 25):
        alpha = math.exp(la)
        # Unit delta response: b = 2, u = 1 gives delta = 1 / alpha.
        x, decay = ode_positions(HysteresisParams(alpha, 2.0, 1.0), v, data.starts, geo.counts, geo.period)
        g = (x - 2.0 * v) * alpha
        proj = Projector(data.segment[rows], (decay[rows] * first)[:, None])
        a = proj(np.column_stack((v[rows], g[rows])))
        yp = proj(y)
        coef, _ = solve_linear(a, yp)
        r = float(np.sum((a @ coef - yp) ** 2))
        b, delta = float(coef[0]), float(coef[1])
        u = b - alpha * delta
        if delta > 0 and u > 0 and (best is None or r < best[0]):
            best = (r, np.array([la, u, alpha * delta]))
    if best is None:
        raise CalibrationError(
            "the hysteresis ODE (2.21) does not fit: no alpha gives loops of the modelled orientation "
            "(position rising with the voltage, trace below retrace)"
        )
    return base, best[1]
