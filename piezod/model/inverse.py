"""Inverse of the closed-loop hysteresis + creep model (3.8) by Lambert W, (4.2)-(4.12).

Each branch of the steady loop has the form (4.2)

    x(V) = c1 V + c2 exp(c3 V) + c4

with (4.3)-(4.6), extended to offset scans with the creep term linear in
``V - V_C`` (section 3.3, :mod:`piezod.model.thesis`):

    c1 = b_hat(f, V_h),  c2 = ±(b - u)/alpha C_{t/r},  c3 = ∓alpha,
    c4 = ∓(b - u)/alpha - (b_hat - b) V_C

(upper sign trace, lower sign retrace; the thesis writes ``b_hat(omega, V_m)`` in
(4.3), which is ``V_M``). Its inverse is (4.11)

    V(x) = (x - c4)/c1 - W(c2 c3 / c1 exp(c3 (x - c4) / c1)) / c3.

``c2 exp(c3 V)`` overflows float64 for large ``|alpha V|``; here it is written
relative to the branch start ``V_s`` (``V_m`` for the trace, ``V_M`` for the
retrace), ``c2 exp(c3 V) = c2s exp(c3 (V - V_s))`` with the bounded
``c2s = ±(b - u)/alpha * 2 / (1 + exp(-alpha V_R))``, and W is evaluated in the
log form (:func:`~piezod.model.lambertw.lambertw0_exp`), so no parameter set
overflows. With ``w = W(z)`` the slope is ``dx/dV = c1 (1 + w)``: the rising part
of a branch is the principal branch ``W0``.

The voltage range belonging to a requested scan range comes from (4.12) solved
for the half range by a bracketed, safeguarded Newton iteration with a fixed
maximum number of steps (per scan, not per sample).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError, RangeUnreachableError
from piezod.model.lambertw import lambertw0_exp_bounded
from piezod.model.params import ThesisParams
from piezod.model.thesis import RETRACE, TRACE, effective_sensitivity, scan_range_um

FloatArray = NDArray[np.float64]

#: Upper bound of safeguarded Newton / bisection steps of the range solve (4.12);
#: 60 halvings alone shrink the bracket to 1e-18 of its width.
RANGE_SOLVE_MAX_STEPS = 60
#: Targets may leave the branch by this fraction of the scan range (rounding only).
TARGET_TOLERANCE_REL = 1e-9
#: Above this many direction changes in one block the branches are evaluated by masks.
_MAX_DIRECTION_RUNS = 16


@dataclass(frozen=True, slots=True)
class BranchConstants:
    """Constants (4.3)-(4.6) of one loop branch ``x(V) = c1 V + c2 exp(c3 V) + c4``.

    Attributes
    ----------
    direction
        +1 trace (rising voltage), -1 retrace.
    c1
        Linear slope ``b_hat`` (um/V).
    c3
        Exponential rate ``-direction * alpha`` (1/V).
    c4
        Offset (um).
    v_start
        Voltage where the branch starts (``V_m`` trace, ``V_M`` retrace).
    c2_start
        ``c2 exp(c3 v_start)`` (um), the bounded form of (4.4) used for evaluation.
    """

    direction: int
    c1: float
    c3: float
    c4: float
    v_start: float
    c2_start: float

    @property
    def c2(self) -> float:
        """The thesis constant (4.4), ``c2_start exp(-c3 v_start)`` (inf if it overflows)."""
        with np.errstate(over="ignore"):
            return float(self.c2_start * np.exp(-self.c3 * self.v_start))

    @property
    def slope_start_um_per_v(self) -> float:
        """``dx/dV`` at the branch start, ``c1 + c2_start c3``: the smallest slope of the branch."""
        return self.c1 + self.c2_start * self.c3

    @property
    def monotone(self) -> bool:
        """Whether ``x`` increases with the voltage along the whole branch."""
        return self.slope_start_um_per_v > 0.0

    def position(self, voltage_v: FloatArray) -> FloatArray:
        """Forward model (4.2) on this branch."""
        out: FloatArray = self.c1 * voltage_v + self.c2_start * np.exp(self.c3 * (voltage_v - self.v_start))
        out += self.c4
        return out


@dataclass(frozen=True, slots=True)
class _Fast:
    """Per-branch coefficients of the hot path: ``y = ya x + yb``, ``V = va x + vb + vw W``."""

    ya: float
    yb: float
    va: float
    vb: float
    vw: float
    negative: bool


def _fast(br: BranchConstants) -> _Fast:
    k = br.c2_start * br.c3 / br.c1
    x0 = br.c4 + br.c1 * br.v_start
    log_k = math.log(abs(k)) if k != 0.0 else -math.inf
    return _Fast(
        ya=br.c3 / br.c1,
        yb=log_k - br.c3 * x0 / br.c1,
        va=1.0 / br.c1,
        vb=br.v_start - x0 / br.c1,
        vw=-1.0 / br.c3,
        negative=k < 0.0,
    )


def _direction_sign(direction: int) -> int:
    if direction == TRACE:
        return TRACE
    if direction == RETRACE:
        return RETRACE
    raise ModelError(f"direction must be +1 (trace) or -1 (retrace), got {direction!r}")


@dataclass(frozen=True, slots=True)
class ThesisInverse:
    """Frozen inverse of one steady triangular scan of the (3.8) model.

    Build it with :meth:`for_scan` (from a requested scan range, solving (4.12))
    or :meth:`for_voltages` (from the turning points). Positions are the model's
    absolute ``x`` (as :func:`~piezod.model.thesis.thesis_loop`); both branches
    run between ``x_min = x(v_min)`` and ``x_max = x(v_max)``.

    Attributes
    ----------
    params
        The 7 model parameters.
    frequency_hz
        Line frequency (Hz).
    v_min, v_max
        Turning points (V).
    allow_nonmonotone
        Accept a branch whose slope is negative near its start (see :meth:`voltage`).
    b_hat
        Creep-enhanced sensitivity (3.7), ``c1`` of both branches (um/V).
    trace, retrace
        The branch constants (4.3)-(4.6).
    x_min, x_max
        Positions at the turning points (um).

    Raises
    ------
    ModelError
        If ``v_max <= v_min``, the frequency is not positive, or a branch is not
        monotone and ``allow_nonmonotone`` is False.
    """

    params: ThesisParams
    frequency_hz: float
    v_min: float
    v_max: float
    allow_nonmonotone: bool = False
    b_hat: float = field(init=False)
    trace: BranchConstants = field(init=False)
    retrace: BranchConstants = field(init=False)
    x_min: float = field(init=False)
    x_max: float = field(init=False)
    _fast_t: _Fast = field(init=False, repr=False)
    _fast_r: _Fast = field(init=False, repr=False)

    def __post_init__(self) -> None:
        v_min, v_max = float(self.v_min), float(self.v_max)
        if not (math.isfinite(v_min) and math.isfinite(v_max) and v_max > v_min):
            raise ModelError(f"voltage range must have finite v_max > v_min, got [{v_min}, {v_max}]")
        p = self.params
        b_hat = effective_sensitivity(p, self.frequency_hz, v_min, v_max)
        if not b_hat > 0.0:
            raise ModelError(
                f"effective sensitivity b_hat = {b_hat:.6g} um/V <= 0 for [{v_min}, {v_max}] V at "
                f"{self.frequency_hz} Hz: the creep parameters give no invertible loop"
            )
        a, b, delta = p.alpha_per_v, p.b_um_per_v, p.hysteresis.delta_um
        v_c = 0.5 * (v_min + v_max)
        c2s = delta * 2.0 / (1.0 + math.exp(-a * (v_max - v_min)))
        creep = (b_hat - b) * v_c
        trace = BranchConstants(TRACE, b_hat, -a, -delta - creep, v_min, c2s)
        retrace = BranchConstants(RETRACE, b_hat, a, delta - creep, v_max, -c2s)
        for br, name in ((trace, "trace"), (retrace, "retrace")):
            if not br.monotone and not self.allow_nonmonotone:
                raise ModelError(
                    f"{name} branch of the (3.8) loop on [{v_min}, {v_max}] V at {self.frequency_hz} Hz is "
                    f"not monotone: dx/dV = {br.slope_start_um_per_v:.6g} um/V at its start "
                    f"{br.v_start} V (b_hat = {b_hat:.6g} um/V < (b - u) * 2/(1 + exp(-alpha V_R)) = "
                    f"{abs(br.c2_start * br.c3):.6g} um/V); the stage would first move backwards"
                )
        setattr_ = object.__setattr__
        setattr_(self, "v_min", v_min)
        setattr_(self, "v_max", v_max)
        setattr_(self, "b_hat", b_hat)
        setattr_(self, "trace", trace)
        setattr_(self, "retrace", retrace)
        setattr_(self, "x_min", float(trace.position(np.array([v_min]))[0]))
        setattr_(self, "x_max", float(trace.position(np.array([v_max]))[0]))
        setattr_(self, "_fast_t", _fast(trace))
        setattr_(self, "_fast_r", _fast(retrace))

    @classmethod
    def for_voltages(
        cls,
        params: ThesisParams,
        v_min: float,
        v_max: float,
        frequency_hz: float,
        *,
        allow_nonmonotone: bool = False,
    ) -> ThesisInverse:
        """Inverse of the scan between the turning points ``v_min`` and ``v_max``."""
        return cls(params, frequency_hz, v_min, v_max, allow_nonmonotone)

    @classmethod
    def for_scan(
        cls,
        params: ThesisParams,
        range_um: float,
        frequency_hz: float,
        *,
        v_limits: tuple[float, float],
        center_v: float = 0.0,
        allow_nonmonotone: bool = False,
    ) -> ThesisInverse:
        """Inverse of the scan of ``range_um`` around the voltage ``center_v``, solving (4.12).

        Parameters
        ----------
        params
            The 7 model parameters.
        range_um
            Requested scan range ``x(V_M) - x(V_m)`` (um), > 0.
        frequency_hz
            Line frequency (Hz).
        v_limits
            ``(lowest, highest)`` voltage the axis may see (V).
        center_v
            Scan centre ``V_C`` (V); the position of the range centre is ``b V_C``.
        allow_nonmonotone
            See :class:`ThesisInverse`.

        Raises
        ------
        RangeUnreachableError
            If the range needs voltages beyond ``v_limits`` (the message gives the
            largest reachable range).
        ModelError
            For a non-positive range or frequency, or a centre outside the limits.
        """
        v_half = solve_half_range(params, range_um, frequency_hz, v_limits=v_limits, center_v=center_v)
        return cls(params, frequency_hz, center_v - v_half, center_v + v_half, allow_nonmonotone)

    @property
    def range_um(self) -> float:
        """Scan range ``x_max - x_min`` (um)."""
        return self.x_max - self.x_min

    @property
    def center_v(self) -> float:
        """Scan centre ``V_C`` (V)."""
        return 0.5 * (self.v_min + self.v_max)

    @property
    def v_half(self) -> float:
        """Half voltage range ``V_h`` (V)."""
        return 0.5 * (self.v_max - self.v_min)

    def branch(self, direction: int) -> BranchConstants:
        """The constants of the trace (+1) or retrace (-1) branch."""
        return self.trace if _direction_sign(direction) == TRACE else self.retrace

    def to_absolute(self, target_um: ArrayLike, *, centred: bool = False) -> FloatArray:
        """Map a linear scan target onto the model's absolute position.

        Parameters
        ----------
        target_um
            Target in ``[0, range_um]`` measured from ``x_min``, or with
            ``centred=True`` in ``[-range_um / 2, range_um / 2]`` around the centre.
        centred
            Whether the target is centred.
        """
        t = np.asarray(target_um, dtype=np.float64)
        origin = 0.5 * (self.x_min + self.x_max) if centred else self.x_min
        out: FloatArray = t + origin
        return out

    def _check_targets(self, x: FloatArray) -> tuple[float, float]:
        lo = float(x.min())
        hi = float(x.max())
        tol = TARGET_TOLERANCE_REL * self.range_um
        if not (lo >= self.x_min - tol and hi <= self.x_max + tol):
            bad = lo if not lo >= self.x_min - tol else hi
            raise ModelError(
                f"target position {bad!r} um is outside the scan branch "
                f"[{self.x_min:.9g}, {self.x_max:.9g}] um of the loop on [{self.v_min}, {self.v_max}] V"
            )
        return lo, hi

    def _evaluate(
        self,
        x: FloatArray,
        c: tuple[float | FloatArray, ...],
        negative: bool,
        y_bounds: tuple[float, float] | None,
    ) -> FloatArray:
        """``V = va x + vb + vw W0(±exp(ya x + yb))`` with coefficients ``c = (ya, yb, va, vb, vw)``."""
        ya, yb, va, vb, vw = c
        y = x * ya
        y += yb
        if y_bounds is None:
            y_bounds = (float(y.min()), float(y.max()))
        w = lambertw0_exp_bounded(y, y_bounds[0], y_bounds[1], negative=negative)
        w *= vw
        v = x * va
        v += vb
        v += w
        np.maximum(v, self.v_min, out=v)
        np.minimum(v, self.v_max, out=v)
        return v

    def voltage(self, position_um: ArrayLike, direction: int | ArrayLike) -> FloatArray:
        """Voltage that puts the stage at ``position_um`` on the given branch (4.11).

        Parameters
        ----------
        position_um
            Absolute model positions inside ``[x_min, x_max]`` (um).
        direction
            +1 (trace) or -1 (retrace), scalar or one per sample.

        Returns
        -------
        ndarray
            Voltages inside ``[v_min, v_max]`` (V). On a non-monotone branch
            (``allow_nonmonotone``) the voltage of the rising part is returned,
            which jumps at the branch start.

        Raises
        ------
        ModelError
            If a target lies outside ``[x_min, x_max]`` (beyond rounding) or is NaN,
            or a direction is not ±1.
        """
        x = np.asarray(position_um, dtype=np.float64)
        shape = x.shape
        x = np.ascontiguousarray(x.reshape(-1))
        if x.size == 0:
            return np.empty(shape)
        lo, hi = self._check_targets(x)
        # both branches share the sign of the W argument (-sign(b - u))
        negative = self._fast_t.negative
        d = np.asarray(direction)
        if d.ndim == 0:
            f = self._fast_t if _direction_sign(int(d)) == TRACE else self._fast_r
            y_bounds = (lo * f.ya + f.yb, hi * f.ya + f.yb)
            y_bounds = (min(y_bounds), max(y_bounds))
            return self._evaluate(x, (f.ya, f.yb, f.va, f.vb, f.vw), negative, y_bounds).reshape(shape)
        d = d.reshape(-1)
        if d.shape != x.shape:
            raise ModelError(f"direction has {d.size} entries for {x.size} positions")
        t, r = self._fast_t, self._fast_r
        cuts = np.flatnonzero(d[1:] != d[:-1]) + 1
        if cuts.size <= _MAX_DIRECTION_RUNS:
            coeffs = [np.empty_like(x) for _ in range(5)]
            edges = [0, *cuts.tolist(), x.size]
            for start, stop in itertools.pairwise(edges):
                f = t if _direction_sign(int(d[start])) == TRACE else r
                for arr, value in zip(coeffs, (f.ya, f.yb, f.va, f.vb, f.vw), strict=True):
                    arr[start:stop] = value
        else:
            trace = d == TRACE
            if int(np.count_nonzero(trace)) + int(np.count_nonzero(d == RETRACE)) != d.size:
                raise ModelError("direction entries must be +1 (trace) or -1 (retrace)")
            coeffs = [
                np.where(trace, a, b)
                for a, b in zip((t.ya, t.yb, t.va, t.vb, t.vw), (r.ya, r.yb, r.va, r.vb, r.vw), strict=True)
            ]
        return self._evaluate(x, tuple(coeffs), negative, None).reshape(shape)

    def position(self, voltage_v: ArrayLike, direction: int | ArrayLike) -> FloatArray:
        """Forward model (3.8) on the given branch, the same as :func:`~piezod.model.thesis.thesis_loop`.

        Raises
        ------
        ModelError
            If a voltage lies outside ``[v_min, v_max]`` (beyond rounding) or is NaN.
        """
        v = np.asarray(voltage_v, dtype=np.float64)
        if v.size:
            lo, hi = float(v.min()), float(v.max())
            tol = 1e-12 * (self.v_max - self.v_min)
            if not (lo >= self.v_min - tol and hi <= self.v_max + tol):
                raise ModelError(
                    f"voltage {lo if not lo >= self.v_min - tol else hi!r} V is outside the scan "
                    f"[{self.v_min}, {self.v_max}] V"
                )
        d = np.asarray(direction)
        if d.ndim == 0:
            return self.branch(int(d)).position(v)
        if d.shape != v.shape or not np.all((d == TRACE) | (d == RETRACE)):
            raise ModelError("direction must be ±1, scalar or one entry per voltage")
        return np.where(d == TRACE, self.trace.position(v), self.retrace.position(v))


def _range_and_slope(params: ThesisParams, frequency_hz: float, v_half: float) -> tuple[float, float]:
    a, b, delta = params.alpha_per_v, params.b_um_per_v, params.hysteresis.delta_um
    f_factor = 1.0 - params.a1 * math.exp(-1.0 / (frequency_hz * params.tau_s))
    th = math.tanh(a * v_half)
    k = f_factor * (params.a2_per_v * v_half + params.a3)
    r = 2.0 * b * v_half + 2.0 * delta * th * (k - 1.0)
    dr = 2.0 * b + 2.0 * delta * (a * (1.0 - th * th) * (k - 1.0) + th * f_factor * params.a2_per_v)
    return r, dr


def solve_half_range(
    params: ThesisParams,
    range_um: float,
    frequency_hz: float,
    *,
    v_limits: tuple[float, float],
    center_v: float = 0.0,
) -> float:
    """Half voltage range ``V_h`` whose loop spans ``range_um`` (4.12).

    Bracketed Newton iteration on ``scan_range_um(V_h) - range_um`` in
    ``(0, V_h,max]``, started at the thesis's ``x_R / (2 b)``, bisecting whenever
    Newton leaves the bracket; at most :data:`RANGE_SOLVE_MAX_STEPS` steps.

    Parameters
    ----------
    params
        The 7 model parameters.
    range_um
        Requested scan range (um), > 0.
    frequency_hz
        Line frequency (Hz), > 0.
    v_limits
        ``(lowest, highest)`` allowed voltage (V).
    center_v
        Scan centre (V), inside the limits.

    Returns
    -------
    float
        ``V_h`` (V).

    Raises
    ------
    RangeUnreachableError
        If ``range_um`` exceeds the range reachable inside the limits.
    ModelError
        For invalid arguments.
    """
    lo_lim, hi_lim = (float(v) for v in v_limits)
    if not (math.isfinite(range_um) and range_um > 0.0):
        raise ModelError(f"scan range must be finite and > 0 um, got {range_um!r}")
    if not (math.isfinite(frequency_hz) and frequency_hz > 0.0):
        raise ModelError(f"scan frequency must be finite and > 0 Hz, got {frequency_hz!r}")
    if not (math.isfinite(lo_lim) and math.isfinite(hi_lim) and lo_lim < hi_lim):
        raise ModelError(f"voltage limits must be finite with lowest < highest, got {v_limits!r}")
    if not lo_lim < center_v < hi_lim:
        raise ModelError(
            f"scan centre {center_v!r} V is not inside the voltage limits [{lo_lim}, {hi_lim}] V"
        )
    vh_max = min(hi_lim - center_v, center_v - lo_lim)
    r_max, _ = _range_and_slope(params, frequency_hz, vh_max)
    if r_max < range_um * (1.0 - 1e-12):
        raise RangeUnreachableError(
            f"scan range {range_um:.6g} um at {frequency_hz:.6g} Hz needs more than ±{vh_max:.6g} V around "
            f"{center_v:.6g} V (limits [{lo_lim:.6g}, {hi_lim:.6g}] V); the largest reachable range there "
            f"is {r_max:.6g} um"
        )
    lo, hi = 0.0, vh_max
    v = min(max(range_um / (2.0 * params.b_um_per_v), 0.0), vh_max)
    if not 0.0 < v < vh_max:
        v = 0.5 * vh_max
    for _ in range(RANGE_SOLVE_MAX_STEPS):
        r, dr = _range_and_slope(params, frequency_hz, v)
        f = r - range_um
        if f < 0.0:
            lo = v
        else:
            hi = v
        step_ok = dr > 0.0 and lo < v - f / dr < hi
        v_new = v - f / dr if step_ok else 0.5 * (lo + hi)
        if abs(v_new - v) <= 4.0 * np.finfo(np.float64).eps * v_new or hi - lo <= 0.0:
            v = v_new
            break
        v = v_new
    if r_max <= range_um:
        v = vh_max  # the full range, within rounding
    r_final = float(scan_range_um(params, frequency_hz, v))
    if not abs(r_final - range_um) <= 1e-9 * range_um:
        raise ModelError(
            f"range solve (4.12) did not converge: {r_final!r} um for {range_um!r} um at V_h = {v!r} V"
        )
    return v
