"""Candidate extensions of the baseline, one per physical effect (audit effect ids of docs/formats.md).

Each candidate adds a physically motivated term with one or two parameters to the baseline.
The extended model is evaluated as a pipeline in the order in which a real stage produces
the effects (the same order as the simulated stage):

1. ``polarity``  the ceramic sees ``V (1 + p/100)`` for ``V < 0`` (turning points too): a kink at 0 V.
2. baseline      (3.8) or the ODE (2.21);
   ``creep``     (3.8): ``k(f)`` of (3.5) gets ``+ gamma ln(f_ref/f)`` (log law of the tilt) and the
                 whole motion is scaled by ``1 + lambda ln(f_ref/f)`` (a spread of relaxation times
                 lets the whole loop grow ``lambda`` per e-fold of time); ODE: a log creep operator,
                 ``gamma`` per decade of time, a bank of first-order relaxations with log-spaced time
                 constants (two sample intervals to 100 x the session) driven by the hysteretic
                 position, starting at rest at 0 V at the start of every recording.
3. ``thermal``   sensitivity ``1 + kappa t`` changing linearly in session time.
4. ``stiffness`` ``x + k x^2 / 200`` (sensitivity ``1 + k x / 100``, preload spring): length error
                 linear in the scan offset.
5. ``saturation`` ``x_sat tanh(x / x_sat)``: compression at large excursions.
6. ``resonance`` unit-gain second-order mechanical resonance ``(f0, Q)``: ringing after turning points.
7. ``drift``     ``+ r t``: position drifting linearly in session time.
8. ``delay``     pure delay ``d`` and first-order lag ``tau`` of the sensed position: the loop opens
                 with the scan speed.

Parameters live in an internal O(1) scaling (see each candidate's ``public``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from piezod.audit.baseline import Geometry, OdeBase, ThesisBase
from piezod.audit.dynamics import first_order_lag, lag_coefficients, pure_delay, resonance

F64 = NDArray[np.float64]

#: Effect ids in the order of docs/formats.md (the candidates).
EFFECTS: tuple[str, ...] = (
    "drift",
    "thermal",
    "stiffness",
    "polarity",
    "resonance",
    "delay",
    "saturation",
    "creep",
)


@dataclass(frozen=True, eq=False)
class Scales:
    """Scales of the training data that make the candidates' internal parameters O(1).

    Attributes
    ----------
    t_ref_s
        Reference time (middle of the training session).
    session_s
        Duration of the training session.
    f_ref_hz
        Geometric mean of the line frequencies (1 Hz when none).
    x_scale_um
        Largest excursion of the baseline model from 0.
    min_period_s
        Shortest line period (or 200 sample intervals when nothing is periodic).
    max_rate_hz
        Highest sample rate.
    max_line_hz
        Highest line frequency (0 when nothing is periodic).
    has_negative_voltage
        Some samples have ``V < 0``.
    creep_taus_s
        Relaxation times of the ODE creep operator (3 per decade over the session's time scales).
    """

    t_ref_s: float
    session_s: float
    f_ref_hz: float
    x_scale_um: float
    min_period_s: float
    max_rate_hz: float
    max_line_hz: float
    has_negative_voltage: bool
    creep_taus_s: F64 = field(default_factory=lambda: np.empty(0))


@dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate extension.

    Attributes
    ----------
    effect
        Audit id.
    names
        Public parameter names (with units).
    description
        The physical term, for reports.
    """

    effect: str
    names: tuple[str, ...]
    description: str

    @property
    def size(self) -> int:
        """Number of internal parameters."""
        return len(self.names)

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        """Internal bounds."""
        raise NotImplementedError

    def neutral(self, sc: Scales) -> F64:
        """Internal parameters with no effect."""
        return np.zeros(self.size)

    def grid(self, sc: Scales) -> list[F64]:
        """Starting points to try besides the linearised start."""
        return []

    def grid_from_residual(self, sc: Scales, geo: Geometry, rows: NDArray[np.bool_], r: F64) -> list[F64]:
        """Starting points suggested by the current residual."""
        return []

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        """Public parameter values."""
        raise NotImplementedError

    def testable(self, sc: Scales) -> str:
        """Empty when the data can show the effect, else why not."""
        return ""

    def implausible(self, phi: F64, sc: Scales) -> str:
        """Empty when the fitted parameters describe the effect, else why they do not."""
        return ""


class Drift(Candidate):
    """``x + r (t - t_ref)``; internal: the drift over the session in um."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([-np.inf]), np.array([np.inf])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"rate_nm_per_s": float(phi[0]) / sc.session_s * 1e3}

    def testable(self, sc: Scales) -> str:
        return "" if sc.session_s > 0 else "a single instant"


class Thermal(Candidate):
    """``x (1 + kappa (t - t_ref))``; internal: the relative sensitivity change over the session."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([-0.5]), np.array([0.5])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"rate_pct_per_hour": float(phi[0]) / sc.session_s * 3600.0 * 100.0}

    def testable(self, sc: Scales) -> str:
        return "" if sc.session_s > 0 else "a single instant"


class Stiffness(Candidate):
    """``x + k x^2 / 200``; internal: ``k X / 100`` (relative sensitivity change at the largest excursion)."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([-1.0]), np.array([1.0])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"sensitivity_pct_per_um": float(phi[0]) * 100.0 / sc.x_scale_um}


class Polarity(Candidate):
    """``V -> V (1 + p)`` for ``V < 0``; internal: ``p``."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([-0.9]), np.array([1.0])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"negative_sensitivity_pct": float(phi[0]) * 100.0}

    def testable(self, sc: Scales) -> str:
        return "" if sc.has_negative_voltage else "no sample has a negative voltage"


class Saturation(Candidate):
    """``x_sat tanh(x / x_sat)``; internal: ``(X / x_sat)^2`` >= 0."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([0.0]), np.array([25.0])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        w = float(phi[0])
        return {"x_sat_um": sc.x_scale_um / math.sqrt(w) if w > 0 else math.inf}


class Resonance(Candidate):
    """Unit-gain second-order resonance; internal: ``(ln f0, ln Q)``."""

    def _f_range(self, sc: Scales) -> tuple[float, float]:
        lo = max(5.0 * sc.max_line_hz, 2.0 / sc.min_period_s if sc.max_line_hz == 0 else 0.0, 1e-3)
        # Up to the Nyquist frequency of the fastest sampled experiment (a hair below it, where
        # the discrete filter still rings): a stricter cut made a resonance found the same in
        # the data and in their decimation "unresolvable" in the latter (an invariance failure).
        hi = 0.49 * sc.max_rate_hz
        return lo, max(hi, 1.5 * lo)

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        lo, _ = self._f_range(sc)
        # Far above the Nyquist frequency the filter is the identity: the baseline is nested.
        return np.array([math.log(lo), math.log(0.5)]), np.array(
            [math.log(1e3 * sc.max_rate_hz), math.log(300.0)]
        )

    def neutral(self, sc: Scales) -> F64:
        return np.array([math.log(1e3 * sc.max_rate_hz), math.log(300.0)])

    def grid_from_residual(self, sc: Scales, geo: Geometry, rows: NDArray[np.bool_], r: F64) -> list[F64]:
        lo, hi = self._f_range(sc)
        peak = spectral_peak(geo, rows, r, lo, hi)
        if peak is None:
            return []
        return [
            np.array([math.log(peak * k), math.log(q)])
            for k in (0.94, 0.97, 1.0, 1.03, 1.06)
            for q in (3.0, 10.0, 30.0)
        ]

    def implausible(self, phi: F64, sc: Scales) -> str:
        _, hi = self._f_range(sc)
        f0 = math.exp(float(phi[0]))
        q = math.exp(float(phi[1]))
        if f0 > hi:
            return f"f0 = {f0:.4g} Hz is above the resolvable {hi:.4g} Hz: no ringing seen, it acts as a lag"
        if q <= 1.0 / math.sqrt(2.0):
            return f"Q = {q:.3g} <= 1/sqrt(2): overdamped, no ringing; it acts as a lag"
        return ""

    def grid(self, sc: Scales) -> list[F64]:
        lo, hi = self._f_range(sc)
        out = []
        for f0 in np.exp(np.linspace(math.log(lo), math.log(hi), 24)):
            for q in (2.0, 10.0):
                out.append(np.array([math.log(f0), math.log(q)]))
        return out

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"f0_hz": math.exp(float(phi[0])), "q": math.exp(float(phi[1]))}

    def testable(self, sc: Scales) -> str:
        lo, hi = self._f_range(sc)
        return "" if hi > 2.0 * lo else "the sample rate is too low to resolve a resonance above the scan"


class Delay(Candidate):
    """Pure delay ``d`` and first-order lag ``tau`` of the sensed position; internal: both in s."""

    def _max(self, sc: Scales) -> float:
        return 0.1 * sc.min_period_s

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        m = self._max(sc)
        return np.zeros(2), np.array([m, m])

    def grid(self, sc: Scales) -> list[F64]:
        m = self._max(sc)
        return [np.array([d, 0.0]) for d in m * np.array([1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3])]

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"delay_s": float(phi[0]), "lag_time_constant_s": float(phi[1])}


class CreepThesis(Candidate):
    """(3.8): ``k += gamma ln(f_ref/f)``, motion ``x (1 + lambda ln(f_ref/f))``.

    Internal parameters ``(gamma, lambda)``.
    """

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([-2.0, 0.0]), np.array([2.0, 0.5])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {
            "k_log_per_decade": float(phi[0]) * math.log(10.0),
            "motion_pct_per_decade": float(phi[1]) * math.log(10.0) * 100.0,
            "f_ref_hz": sc.f_ref_hz,
        }

    def testable(self, sc: Scales) -> str:
        return "" if sc.max_line_hz > 0 else "no periodic scan"


class CreepOde(Candidate):
    """ODE: log creep operator, ``gamma`` of the motion per decade of time; internal ``gamma``."""

    def bounds(self, sc: Scales) -> tuple[F64, F64]:
        return np.array([0.0]), np.array([1.0])

    def public(self, phi: F64, sc: Scales) -> dict[str, float]:
        return {"creep_pct_per_decade": float(phi[0]) * 100.0}

    def testable(self, sc: Scales) -> str:
        return "" if sc.creep_taus_s.size else "the session spans too short a time"


_DESCRIPTIONS = {
    "drift": "position drifting linearly in session time: x + r t",
    "thermal": "sensitivity changing linearly in session time: x (1 + kappa t)",
    "stiffness": "position-dependent sensitivity (preload spring): x + k x^2 / 200",
    "polarity": "different sensitivity for V < 0: V -> V (1 + p) below 0 V",
    "resonance": "second-order mechanical resonance (f0, Q) applied to the model output",
    "delay": "sensor / amplifier lag: pure delay d and first-order lag tau of the position",
    "saturation": "compression at large excursions: x_sat tanh(x / x_sat)",
    "creep_thesis": "creep law with a spread of relaxation times: log-frequency terms in k(f) and the motion",
    "creep_ode": "log creep operator: relaxations with log-spaced time constants, gamma per decade",
}


def make_candidate(effect: str, base_kind: str) -> Candidate:
    """The candidate for ``effect`` on a baseline of ``base_kind`` (``thesis`` / ``ode``)."""
    table: dict[str, tuple[type[Candidate], tuple[str, ...]]] = {
        "drift": (Drift, ("rate_nm_per_s",)),
        "thermal": (Thermal, ("rate_pct_per_hour",)),
        "stiffness": (Stiffness, ("sensitivity_pct_per_um",)),
        "polarity": (Polarity, ("negative_sensitivity_pct",)),
        "resonance": (Resonance, ("f0_hz", "q")),
        "delay": (Delay, ("delay_s", "lag_time_constant_s")),
        "saturation": (Saturation, ("x_sat_um",)),
    }
    if effect == "creep":
        if base_kind == "thesis":
            return CreepThesis(
                "creep", ("k_log_per_decade", "motion_pct_per_decade"), _DESCRIPTIONS["creep_thesis"]
            )
        return CreepOde("creep", ("creep_pct_per_decade",), _DESCRIPTIONS["creep_ode"])
    cls, names = table[effect]
    return cls(effect, names, _DESCRIPTIONS[effect])


# ------------------------------------------------------------------------------------------ the pipeline


@dataclass(frozen=True, eq=False)
class AuditModel:
    """The baseline with a set of candidate extensions.

    Attributes
    ----------
    base
        The baseline.
    candidates
        Active extensions (at most one per effect).
    scales
        Training-data scales.
    memo
        The last few baseline-stage results (a cache; the arrays are not modified).
    """

    base: ThesisBase | OdeBase
    candidates: tuple[Candidate, ...]
    scales: Scales
    memo: dict[object, tuple[F64, tuple[F64, ...]]] = field(default_factory=dict, repr=False)

    @property
    def n_base(self) -> int:
        """Internal baseline parameters."""
        return 3 if isinstance(self.base, OdeBase) else 7

    @property
    def size(self) -> int:
        """All internal parameters."""
        return self.n_base + sum(c.size for c in self.candidates)

    @property
    def effects(self) -> tuple[str, ...]:
        """Active effect ids."""
        return tuple(c.effect for c in self.candidates)

    def slices(self) -> dict[str, slice]:
        """Internal parameter slice of every active candidate."""
        out: dict[str, slice] = {}
        k = self.n_base
        for c in self.candidates:
            out[c.effect] = slice(k, k + c.size)
            k += c.size
        return out

    def with_candidate(self, cand: Candidate) -> AuditModel:
        """This model plus ``cand``."""
        return AuditModel(self.base, (*self.candidates, cand), self.scales)

    def bounds(self) -> tuple[F64, F64]:
        """Internal bounds."""
        lo, hi = self.base.bounds()
        los, his = [lo], [hi]
        for c in self.candidates:
            a, b = c.bounds(self.scales)
            los.append(a)
            his.append(b)
        return np.concatenate(los), np.concatenate(his)

    def free(self) -> NDArray[np.bool_]:
        """Mask of fitted internal parameters."""
        return np.concatenate([self.base.free, *[np.ones(c.size, dtype=bool) for c in self.candidates]])

    def public(self, p: F64) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
        """Baseline parameters and per-candidate parameters, public units."""
        base = self.base.public(p[: self.n_base])
        sl = self.slices()
        return base, {c.effect: c.public(p[sl[c.effect]], self.scales) for c in self.candidates}

    def evaluate(self, p: F64, geo: Geometry) -> tuple[F64, F64 | None]:
        """Model positions (without offsets) and the extra nuisance columns (first segments only).

        Returns
        -------
        x : ndarray
            Per sample.
        nuisance : ndarray or None
            Columns (n x m) of linear per-experiment nuisance terms besides the offsets, non-zero
            only on the first segment of their experiment.
        """
        sl = self.slices()
        phi = {k: p[s] for k, s in sl.items()}
        data = geo.data
        v = data.voltage_v
        vmin, vmax = geo.v_min, geo.v_max
        if "polarity" in phi:
            fac = 1.0 + float(phi["polarity"][0])
            v = np.where(v < 0.0, v * fac, v)
            vmin = np.where(vmin < 0.0, vmin * fac, vmin)
            vmax = np.where(vmax < 0.0, vmax * fac, vmax)
        zb = p[: self.n_base]
        # The baseline stage depends only on the baseline parameters and the voltage / creep
        # hooks: remembered, so that varying a candidate's parameters does not recompute it.
        hooks = tuple(float(v) for k in ("polarity", "creep") if k in phi for v in phi[k])
        key = (id(geo), zb.tobytes(), hooks)
        hit = self.memo.get(key)
        if hit is not None:
            x, nuis = hit[0], list(hit[1])
        else:
            nuis = []
            if isinstance(self.base, ThesisBase):
                k_extra = None
                if "creep" in phi:
                    k_extra = float(phi["creep"][0]) * geo.log_f
                if "polarity" in phi:
                    x = self.base.evaluate(zb, geo, v, vmin, vmax, k_extra)
                else:
                    x = self.base.evaluate(zb, geo, k_extra=k_extra)
                if "creep" in phi:
                    x = x * (1.0 + float(phi["creep"][1]) * geo.log_f[geo.exp])
            else:
                x, decay = self.base.evaluate(zb, geo, v)
                nuis.append(decay)
                if "creep" in phi:
                    x = x + float(phi["creep"][0]) * _creep_bank(x, geo, self.scales.creep_taus_s)
            if len(self.memo) >= 4:
                self.memo.pop(next(iter(self.memo)))
            self.memo[key] = (x, tuple(nuis))
        if "thermal" in phi:
            x = x * (1.0 + float(phi["thermal"][0]) / self.scales.session_s * geo.t_rel_s)
        if "stiffness" in phi:
            x = x + float(phi["stiffness"][0]) / (2.0 * self.scales.x_scale_um) * x * x
        if "saturation" in phi:
            w = float(phi["saturation"][0])
            if w > 0.0:
                xs = self.scales.x_scale_um / math.sqrt(w)
                x = xs * np.tanh(x / xs)
        if "resonance" in phi:
            f0, q = math.exp(float(phi["resonance"][0])), math.exp(float(phi["resonance"][1]))
            x = _per_experiment(x, geo, lambda xe, dt, per: resonance(xe, dt, f0, q, per))
        if "drift" in phi:
            x = x + float(phi["drift"][0]) / self.scales.session_s * geo.t_rel_s
        if "delay" in phi:
            d, tau = float(phi["delay"][0]), float(phi["delay"][1])
            if d > 0.0:
                x = _per_experiment(x, geo, lambda xe, dt, per: pure_delay(xe, dt, d, per))
            if tau > 0.0:
                x = _per_experiment(x, geo, lambda xe, dt, per: first_order_lag(xe, dt, tau, per))
        extra = None
        if nuis:
            first = geo.data.first_segment[geo.data.segment]
            extra = np.column_stack(nuis) * first[:, None]
        return x, extra


def spectral_peak(geo: Geometry, rows: NDArray[np.bool_], r: F64, f_lo: float, f_hi: float) -> float | None:
    """Frequency of the strongest narrow excess of the residual spectrum in ``[f_lo, f_hi]`` (Hz).

    Ringing follows the reversals of the voltage and decays, so the spectra are taken from the
    residual right after every reversal (the first sample of a periodic experiment included),
    tapered by ``exp(-k / K)`` for a few decay lengths ``K``, in the experiments that resolve
    ``f_lo``. They are normalised by their median, pooled on log-spaced bins and divided by a
    running median (the background); the decay length with the clearest peak wins.
    """
    full = np.zeros(geo.data.n)
    full[rows] = r
    edges = np.exp(np.linspace(math.log(f_lo), math.log(f_hi), 301))
    centres = np.sqrt(edges[:-1] * edges[1:])
    data = geo.data
    best: tuple[float, float] | None = None
    for decay in (12, 48, 192):
        length = 4 * decay
        taper = np.exp(-np.arange(length) / decay)
        acc = np.zeros(edges.size - 1)
        cnt = np.zeros(edges.size - 1)
        for i, sl in enumerate(geo.slices):
            dt = float(geo.dt_s[i])
            y = full[sl]
            if 0.5 / dt <= 2.0 * f_lo or y.size < length:
                continue
            turns = np.flatnonzero(np.diff(data.direction[sl]) != 0) + 1
            if geo.period[i] > 0:
                turns = np.concatenate(([0], turns))
            starts = turns[turns + length <= y.size]
            if starts.size == 0:
                continue
            seg = y[starts[:, None] + np.arange(length)[None, :]]
            seg = seg - seg.mean(axis=1, keepdims=True)
            pw = np.mean(np.abs(np.fft.rfft(seg * taper, n=2 * length, axis=1)) ** 2, axis=0)
            f = np.fft.rfftfreq(2 * length, dt)
            med = float(np.median(pw[1:])) or 1.0
            k = np.searchsorted(edges, f[1:]) - 1
            ok = (k >= 0) & (k < acc.size)
            np.add.at(acc, k[ok], pw[1:][ok] / med)
            np.add.at(cnt, k[ok], 1.0)
        good = cnt > 0
        if good.sum() < 8:
            continue
        level = acc[good] / cnt[good]
        half = 15
        pad = np.pad(level, half, mode="edge")
        background = np.array([np.median(pad[j : j + 2 * half + 1]) for j in range(level.size)])
        excess = level / np.maximum(background, 1e-300)
        j = int(np.argmax(excess))
        if excess[j] > 2.0 and (best is None or excess[j] > best[1]):
            best = (float(centres[good][j]), float(excess[j]))
    return None if best is None else best[0]


def _per_experiment(x: F64, geo: Geometry, fn: object) -> F64:
    out = np.empty_like(x)
    for i, sl in enumerate(geo.slices):
        out[sl] = fn(x[sl], float(geo.dt_s[i]), int(geo.period[i]))  # type: ignore[operator]
    return out


def _creep_bank(x: F64, geo: Geometry, taus: F64) -> F64:
    """Log creep operator: first-order relaxations of ``x`` with log-spaced time constants, per decade.

    Every recording file is one session that starts at rest at ``t = 0`` (relaxations at the rest
    position 0, the model position nearest to 0 V). Between the end of one experiment and the
    start of the next (the first one included) the stage is taken to run the next scan: every
    relaxation moves from its last state toward the periodic steady state of the next
    experiment (or toward its first position when it is not periodic) with its own time
    constant, ``z = z_ss + (z_prev - z_ss) exp(-gap / tau)``.
    """
    per_decade = 3.0
    bank = np.zeros_like(x)
    data = geo.data
    state: dict[str | None, tuple[F64, float]] = {}
    for i, sl in enumerate(geo.slices):
        info = data.info[i]
        xe = x[sl]
        dt = float(geo.dt_s[i])
        z_prev, t_prev = state.get(info.path, (np.zeros(taus.size), 0.0))
        gap = max(info.t_start_s - t_prev, 0.0)
        key = ("creep", i, taus.size, float(taus[0]))
        weights = geo.cache.get(key)
        if weights is None:
            weights = geo.cache[key] = _relaxation_weights(xe.size, dt, taus)
        total, z_end = _relaxations(xe, taus, z_prev, gap, int(geo.period[i]), weights)  # type: ignore[arg-type]
        bank[sl] = total
        state[info.path] = (z_end, info.t_end_s)
    out: F64 = bank / per_decade
    return out


@dataclass(frozen=True, eq=False)
class _Weights:
    """Precomputed closed-form weights of the relaxations of one experiment."""

    inst: NDArray[np.bool_]
    slow: NDArray[np.bool_]
    fast: tuple[tuple[int, F64, F64, F64], ...]
    decay: F64
    grow: F64
    w_now: F64
    w_prev: F64
    dt: float


def _relaxation_weights(n: int, dt: float, taus: F64) -> _Weights:
    span = n * dt
    inst = taus < 0.5 * dt
    slow = ~inst & (span / taus <= 500.0)
    fast = ~inst & ~slow
    tau = taus[slow][:, None]
    a = np.exp(-dt / tau)
    r = tau / dt * (1.0 - a)
    decay = np.exp(-np.arange(n)[None, :] * dt / tau)
    steps = np.arange(1, n + 1) * dt
    return _Weights(
        inst=inst,
        slow=slow,
        fast=tuple(
            (j, *lag_coefficients(float(taus[j]), dt), np.exp(-steps / float(taus[j])))
            for j in np.flatnonzero(fast).tolist()
        ),
        decay=decay,
        grow=decay * a,
        w_now=(1.0 - r) / decay,
        w_prev=(r - a) / decay,
        dt=dt,
    )


def _relaxations(xe: F64, taus: F64, z_prev: F64, gap: float, period: int, w: _Weights) -> tuple[F64, F64]:
    """Sum over ``taus`` of first-order lags of ``xe`` (exact for linear segments), and their end states.

    Each lag is its zero-state response plus ``a^(k+1) z_start`` (``a = exp(-dt/tau)``), with
    ``z_start`` relaxed over ``gap`` from ``z_prev`` toward the periodic steady state (the fixed
    point of one period, ``Y_{P-1} / (1 - a^P)``) or toward ``x_0``. The zero-state response of
    ``y_k = a y_{k-1} + b0 x_k + b1 x_{k-1}`` (``x_{-1} = x_0``) is ``a^k sum_{i<=k} a^-i u_i``,
    evaluated for all slow time constants at once (``a^-n`` stays finite); the few fast ones run
    through :func:`scipy.signal.lfilter`; those shorter than half a sample follow ``x``.
    """
    n = xe.size
    total = np.zeros(n)
    z_end = np.empty(taus.size)
    relax = np.exp(-gap / taus)
    per = period if 0 < period <= n else 0
    if w.inst.any():
        total += xe * float(w.inst.sum())
        z_end[w.inst] = xe[-1]
    if w.slow.any():
        x_prev = np.concatenate(([xe[0]], xe[:-1]))
        zero = w.decay * np.cumsum(w.w_now * xe[None, :] + w.w_prev * x_prev[None, :], axis=1)
        tau = taus[w.slow]
        target = zero[:, per - 1] / -np.expm1(-per * w.dt / tau) if per else np.full(tau.size, xe[0])
        z0 = target + (z_prev[w.slow] - target) * relax[w.slow]
        y = zero + w.grow * z0[:, None]
        total += y.sum(axis=0)
        z_end[w.slow] = y[:, -1]
    for j, b, a1, grow1 in w.fast:
        zero1, _ = lfilter(b, a1, xe, zi=[b[1] * xe[0]])
        tau1 = float(taus[j])
        target1 = float(zero1[per - 1]) / -math.expm1(-per * w.dt / tau1) if per else float(xe[0])
        z01 = target1 + (float(z_prev[j]) - target1) * float(relax[j])
        y1 = zero1 + grow1 * z01
        total += y1
        z_end[j] = y1[-1]
    return total, z_end
