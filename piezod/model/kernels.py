"""Compiled per-sample loops of the model family (numba): the inverses that cannot be vectorised.

With voltage-driven creep (:mod:`piezod.model.family`) every sample's voltage moves the next
sample's creep, so the inverse is a sequential loop: per sample the creep's memory term
``s sum_i w_i (a_i e_i + (1 - b0_i) V_c[n-1])`` (``O(m)``), then one monotone scalar equation
``H_state(V_c) + g V_c = y`` of the hysteresis law, then the creep update (``O(m)``). In numpy
that loop costs microseconds per sample; compiled it costs tens of nanoseconds, inside the
streaming budget (150 ns per sample and axis, ``piezod bench inverse``).

The loops are written as plain typed Python (``_pi_loop``, ``_ch_loop``: the reference; numba's
own ``NUMBA_DISABLE_JIT=1`` runs them uncompiled) and compiled by numba with ``cache=True`` (the machine
code is stored next to the module and reloaded by later processes). :func:`warm_up` compiles
or loads them; :class:`piezod.model.axis_model.FamilyAxisModel` calls it when a model with
voltage-driven creep is built, so the compilation never falls into the real-time path.

Exactness: the Prandtl-Ishlinskii solve walks the law's linear pieces from the previous
voltage (each knot is where a play engages), so it is exact for the piecewise-linear map; the
Coleman-Hodgdon solve is a bracketed Newton iteration on the exact one-sample ODE step, to
rounding. Both are bounded per sample: ``O(m + p k)`` with ``k`` knots crossed (0 or 1 at
realistic sample rates) and at most 60 Newton steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, cast

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def _mem(wa: F64, e: F64) -> float:
    """The creep's memory term ``sum_i wa_i e_i`` in four interleaved partial sums: the sum's
    additions are otherwise one dependency chain, the longest part of a sample's creep."""
    m = e.shape[0]
    s0, s1, s2, s3 = 0.0, 0.0, 0.0, 0.0
    i = 0
    while i + 4 <= m:
        s0 += wa[i] * e[i]
        s1 += wa[i + 1] * e[i + 1]
        s2 += wa[i + 2] * e[i + 2]
        s3 += wa[i + 3] * e[i + 3]
        i += 4
    while i < m:
        s0 += wa[i] * e[i]
        i += 1
    return (s0 + s1) + (s2 + s3)


def _creep_ahead(wa: F64, a: F64, ob0: F64, e: F64) -> tuple[F64, float, float]:
    """``wa_i a_i``, ``sum_i wa_i ob0_i`` and the memory term ``sum_i wa_i e_i`` before a block.

    After a sample's update ``e_i <- a_i e_i - ob0_i dV`` the memory term is
    ``sum_i wa_i a_i e_i - dV sum_i wa_i ob0_i``; its first sum does not wait for the sample's
    solve, so a sample's dependency chain holds no sum over the creep elements.
    """
    m = e.shape[0]
    waa = np.empty(m)
    pull = 0.0
    for i in range(m):
        waa[i] = wa[i] * a[i]
        pull += wa[i] * ob0[i]
    return waa, pull, _mem(wa, e)


def _pi_loop(
    xc: F64,
    b: float,
    rho0: float,
    r: F64,
    pw: F64,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    plays: F64,
    u_prev: float,
    xh: float,
    out: F64,
) -> tuple[float, float]:
    """Prandtl-Ishlinskii + voltage creep: ``out[j] = V_c`` per sample; ``e``, ``plays`` updated in place.

    Returns the last drive voltage and hysteretic position.
    """
    n = xc.shape[0]
    m = e.shape[0]
    p = plays.shape[0]
    base = b * rho0 + g
    waa, pull, mem = _creep_ahead(wa, a, ob0, e)
    for j in range(n):
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        f = xh + g * u_prev
        u = u_prev
        if y > f:
            # one pass for the slope and the next knot; another only per knot crossed
            slope = base
            knot = math.inf
            for i in range(p):
                k = plays[i] + r[i]
                if k <= u:
                    slope += b * pw[i]
                elif k < knot:
                    knot = k
            while True:
                cand = u + (y - f) / slope
                if cand <= knot:
                    u = cand
                    break
                f += slope * (knot - u)
                u = knot
                knot = math.inf
                for i in range(p):
                    k = plays[i] + r[i]
                    if k == u:
                        slope += b * pw[i]
                    elif u < k < knot:
                        knot = k
            acc = 0.0
            for i in range(p):
                lo = u - r[i]
                if plays[i] < lo:
                    plays[i] = lo
                acc += pw[i] * plays[i]
            xh = b * (rho0 * u + acc)
        elif y < f:
            slope = base
            knot = -math.inf
            for i in range(p):
                k = plays[i] - r[i]
                if k >= u:
                    slope += b * pw[i]
                elif k > knot:
                    knot = k
            while True:
                cand = u + (y - f) / slope
                if cand >= knot:
                    u = cand
                    break
                f += slope * (knot - u)
                u = knot
                knot = -math.inf
                for i in range(p):
                    k = plays[i] - r[i]
                    if k == u:
                        slope += b * pw[i]
                    elif knot < k < u:
                        knot = k
            acc = 0.0
            for i in range(p):
                hi = u + r[i]
                if plays[i] > hi:
                    plays[i] = hi
                acc += pw[i] * plays[i]
            xh = b * (rho0 * u + acc)
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    return u_prev, xh


def _ch_solve_py(
    b: float, alpha: float, delta: float, g: float, target: float, u0: float, y0: float
) -> float:
    """The voltage ``u`` with ``(b + g) u + y(u) = target``, ``y`` the exact ODE step from ``(u0, y0)``.

    The left side is increasing in ``u``; Newton steps kept inside a bracket (bisection when a
    step leaves it) reach rounding in a few steps.
    """
    slope = b + g
    f0 = slope * u0 + y0 - target
    if f0 == 0.0:
        return u0
    sgn = -1.0 if f0 > 0.0 else 1.0
    # the tangent at u0 (slope after the reversal, the smallest on the branch) overshoots the root,
    # so it brackets it at once on an ODE branch; the loop below widens the bracket otherwise
    der0 = slope - alpha * (sgn * y0 + delta)
    step = abs(f0) / (der0 if der0 > 0.0 else slope)
    lo = u0
    hi = u0 + sgn * step
    for _ in range(200):
        d = abs(hi - u0)
        ex = math.exp(-alpha * d)
        val = slope * hi + ex * y0 + sgn * delta * (ex - 1.0) - target
        if val * sgn >= 0.0:
            break
        lo, hi = hi, u0 + sgn * 2.0 * d
    u = hi
    for _ in range(60):
        d = abs(u - u0)
        ex = math.exp(-alpha * d)
        val = slope * u + ex * y0 + sgn * delta * (ex - 1.0) - target
        der = slope - alpha * ex * (sgn * y0 + delta)
        if val == 0.0:
            return u
        if (val > 0.0) == (sgn > 0.0):
            hi = u
        else:
            lo = u
        nxt = u - val / der if der > 0.0 else 0.5 * (lo + hi)
        if not (min(lo, hi) < nxt < max(lo, hi)):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - u) <= 1e-15 * max(1.0, abs(u)):
            return nxt
        u = nxt
    return u


def _ch_loop(
    xc: F64,
    b: float,
    alpha: float,
    delta: float,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    u_prev: float,
    xh: float,
    out: F64,
) -> tuple[float, float]:
    """Coleman-Hodgdon + voltage creep: ``out[j] = V_c`` per sample; ``e`` updated in place."""
    n = xc.shape[0]
    m = e.shape[0]
    y0 = xh - b * u_prev
    waa, pull, mem = _creep_ahead(wa, a, ob0, e)
    for j in range(n):
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        u = ch_solve(b, alpha, delta, g, y, u_prev, y0)
        xh = y - g * u
        y0 = xh - b * u
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    return u_prev, xh


def _gval(mu: F64, c: F64, row: int, q: float) -> float:
    """``G_row(q) = int_{c_0}^{q} mu_row`` (piecewise quadratic)."""
    k_last = c.shape[0] - 1
    if q <= c[0]:
        return float(mu[row, 0] * (q - c[0]))
    acc = 0.0
    for k in range(k_last):
        w = c[k + 1] - c[k]
        if q < c[k + 1]:
            t = q - c[k]
            return float(acc + mu[row, k] * t + 0.5 * (mu[row, k + 1] - mu[row, k]) / w * t * t)
        acc += 0.5 * (mu[row, k] + mu[row, k + 1]) * w
    return float(acc + mu[row, k_last] * (q - c[k_last]))


def _grow(
    mu: F64, c: F64, row: int, u: float, shift: float, sigma: float, eps: float
) -> tuple[float, float, float]:
    """One row's share of the piece starting at ``u`` (its play offset by ``shift``), in one call
    per row: the density ``mu_row(u - shift)``, ``d mu_row / dq`` on the segment the play
    moves into (just past ``u``, beyond the last node 0) and the next node it reaches beyond
    ``eps`` (``+-inf`` when none)."""
    k_last = c.shape[0] - 1
    q = u - shift
    ahead = u + sigma * 2.0 * eps
    if q <= c[0]:
        slope = float(mu[row, 0])
    elif q >= c[k_last]:
        slope = float(mu[row, k_last])
    else:
        k = 0
        while c[k + 1] <= q:
            k += 1
        t = (q - c[k]) / (c[k + 1] - c[k])
        slope = float(mu[row, k] + t * (mu[row, k + 1] - mu[row, k]))
    curv = 0.0
    knot = math.inf if sigma > 0.0 else -math.inf
    lo = c[0] + shift
    for k in range(k_last + 1):
        v = lo
        if sigma > 0.0:
            if u + eps < v < knot:
                knot = v
        elif knot < v < u - eps:
            knot = v
        if k < k_last:
            hi = c[k + 1] + shift
            inside = (lo <= ahead < hi) if sigma > 0.0 else (lo < ahead <= hi)
            if inside:
                curv = float((mu[row, k + 1] - mu[row, k]) / (c[k + 1] - c[k]))
            lo = hi
    return slope, curv, knot


def _gpiece(mu: F64, c: F64, r: F64, plays: F64, u: float, sigma: float) -> tuple[float, float, float]:
    """The piece of ``H_state`` starting at ``u`` in direction ``sigma``: slope, curvature, end (knot).

    Knots closer than ``eps`` (a few hundred rounding units) count as passed, and the curvature is
    taken just past them, so rounding at a knot (``(u - r) + r != u``) cannot stall the walk.
    """
    eps = 1e-13 * (1.0 + abs(u))
    slope, curv, knot = _grow(mu, c, 0, u, 0.0, sigma, eps)
    for i in range(plays.shape[0]):
        shift = sigma * r[i]
        edge = plays[i] + shift
        if sigma * (edge - u) <= eps:
            ds, dc, k = _grow(mu, c, i + 1, u, shift, sigma, eps)
            slope += ds
            curv += dc
            if sigma * (k - knot) < 0.0:
                knot = k
        elif sigma * (edge - knot) < 0.0:
            knot = edge
    return slope, curv, knot


def _gxh(mu: F64, c: F64, zero: F64, plays: F64, u: float) -> float:
    """``x_h`` of the state ``(u, plays)``."""
    acc = _gval(mu, c, 0, u) - zero[0]
    for i in range(plays.shape[0]):
        acc += _gval(mu, c, i + 1, plays[i]) - zero[i + 1]
    return float(acc)


def _gsettle(r: F64, plays: F64, u: float, sigma: float) -> None:
    """The plays after a monotone run in direction ``sigma`` that ended at ``u`` (in place)."""
    for i in range(plays.shape[0]):
        if sigma > 0.0:
            lo = u - r[i]
            if plays[i] < lo:
                plays[i] = lo
        else:
            hi = u + r[i]
            if plays[i] > hi:
                plays[i] = hi


def _eyring_gap(g: float, factor: float, two_g0: float) -> float:
    """A gap ``g`` after the after-effect's closed form: ``tanh(g / 2 g0)`` times ``factor``."""
    return two_g0 * math.atanh(math.tanh(g / two_g0) * factor)


def _relax_plays(plays: F64, u: float, factor: float, g0: float) -> None:
    """The after-effect's relaxation of the play outputs towards ``u`` (in place; ``g0 = inf``:
    linear), :func:`piezod.model.aftereffect.relax`."""
    if math.isinf(g0):
        for i in range(plays.shape[0]):
            plays[i] = u + (plays[i] - u) * factor
        return
    if factor >= 1.0:
        return
    two = 2.0 * g0
    for i in range(plays.shape[0]):
        # a gap beyond ~37 g0 saturates tanh at 1.0: the closed form then gives the gap it has
        # after the step to rounding (such a gap closes almost at once), never atanh(1)
        plays[i] = u + _eyring_gap(plays[i] - u, factor, two)


def _clip_plays(r: F64, plays: F64, v: float) -> None:
    """The play update at the voltage ``v`` (in place)."""
    for i in range(plays.shape[0]):
        lo = v - r[i]
        hi = v + r[i]
        if plays[i] < lo:
            plays[i] = lo
        elif plays[i] > hi:
            plays[i] = hi


def _relax_outputs(
    v: F64, r: F64, plays: F64, u_prev: float, pending: int, every: int, factor: float, g0: float, out: F64
) -> int:
    """Play outputs ``out[i, j]`` through a block with the after-effect every ``every`` samples
    (``pending`` samples since the last one); ``plays`` updated in place; returns the new count."""
    cnt = pending
    for j in range(v.shape[0]):
        cnt += 1
        if cnt >= every:
            cnt = 0
            _relax_plays(plays, u_prev, factor, g0)
        _clip_plays(r, plays, v[j])
        for i in range(plays.shape[0]):
            out[i, j] = plays[i]
        u_prev = v[j]
    return cnt


def _timed_relax_outputs(
    t: F64,
    v: F64,
    r: F64,
    plays: F64,
    u_prev: float,
    t_prev: float,
    interval: float,
    tau: float,
    g0: float,
    max_steps: int,
    out: F64,
) -> None:
    """Play outputs with the after-effect at samples of any spacing (a calibration session's
    voltages at the times ``t``): between two samples the voltage moves linearly in steps of
    about ``interval`` (at most ``max_steps``), the memory relaxing before each as the runtime
    model does every interval; a held voltage relaxes in one exact step."""
    for j in range(v.shape[0]):
        span = t[j] - t_prev
        if span > 0.0:
            if v[j] == u_prev:
                _relax_plays(plays, u_prev, math.exp(-span / tau), g0)
            else:
                m = min(max_steps, max(1, math.ceil(span / interval)))
                factor = math.exp(-span / m / tau)
                step = (v[j] - u_prev) / m
                u = u_prev
                for k in range(1, m + 1):
                    _relax_plays(plays, u, factor, g0)
                    u = u_prev + step * k
                    _clip_plays(r, plays, u)
        _clip_plays(r, plays, v[j])
        for i in range(plays.shape[0]):
            out[i, j] = plays[i]
        u_prev = v[j]
        t_prev = t[j]


def _gpi_loop(
    xc: F64,
    r: F64,
    c: F64,
    mu: F64,
    zero: F64,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    plays: F64,
    u_prev: float,
    xh: float,
    out: F64,
    every: int,
    pending: int,
    factor: float,
    g0: float,
) -> tuple[float, float]:
    """Generalised play (Preisach) law + voltage creep: ``out[j] = V_c``; ``e``, ``plays`` updated in place.

    The left side ``H_state(u) + g u`` is piecewise quadratic in ``u`` along a monotone run (a
    piece ends where a play engages or a moving play crosses a density node). The current piece
    (its start, value, slope, curvature and end) is kept from sample to sample, so a sample that
    stays on it costs ``O(1)`` besides the creep: one quadratic, solved from the piece's start in
    its stable form (no accumulation of rounding along the piece). Crossing a knot or reversing
    settles the plays and computes the next piece (``O(p K)``, one pass over the nodes per moving
    play); across a knot the left side is continuous, so the next piece starts from the last one's
    end value, and the state's ``x_h`` is summed afresh only at a reversal (rounding does not build
    up beyond one monotone run). With no creep elements and ``g = 0`` it is the law's own exact
    inverse.

    With ``every > 0`` the after-effect relaxes the plays every ``every`` samples (``pending``
    since the last time, :mod:`piezod.model.aftereffect`): the plays are settled, relaxed
    towards the last voltage and the left side summed afresh; the next sample starts a new piece.
    """
    n = xc.shape[0]
    m = e.shape[0]
    max_pieces = 4 * (plays.shape[0] + 1) * (c.shape[0] + 1) + 8
    have = False
    dirty = False
    cnt = pending
    ps, u0, f0, b0, cv, kn = 0.0, u_prev, 0.0, 0.0, 0.0, 0.0
    f_cur = xh + g * u_prev
    waa, pull, mem = _creep_ahead(wa, a, ob0, e)
    for j in range(n):
        if every > 0:
            cnt += 1
            if cnt >= every:
                cnt = 0
                if have:
                    _gsettle(r, plays, u_prev, ps)
                    have = False
                _relax_plays(plays, u_prev, factor, g0)
                f_cur = _gxh(mu, c, zero, plays, u_prev) + g * u_prev
                dirty = True
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        u = u_prev
        if y != f_cur:
            sigma = 1.0 if y > f_cur else -1.0
            if not have or sigma != ps:
                if have:
                    _gsettle(r, plays, u_prev, ps)
                u0 = u_prev
                f0 = _gxh(mu, c, zero, plays, u0) + g * u0
                b0, cv, kn = _gpiece(mu, c, r, plays, u0, sigma)
                b0 += g
                ps = sigma
                have = True
            for _ in range(max_pieces):
                t = sigma * (y - f0)
                q = 0.5 * sigma * cv
                disc = b0 * b0 + 4.0 * q * t
                d = 2.0 * t / (b0 + math.sqrt(disc)) if disc >= 0.0 else math.inf
                to_knot = sigma * (kn - u0)
                if d <= to_knot:
                    u = u0 + sigma * d
                    break
                f0 += sigma * (b0 + q * to_knot) * to_knot
                u0 = kn
                _gsettle(r, plays, u0, sigma)
                b0, cv, kn = _gpiece(mu, c, r, plays, u0, sigma)
                b0 += g
                u = u0
            f_cur = y
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    if have:
        _gsettle(r, plays, u_prev, ps)
    if have or dirty:
        xh = _gxh(mu, c, zero, plays, u_prev)
    return u_prev, xh


def _bw_phi(k: float, d: float) -> float:
    """``(1 - exp(-k d)) / k`` (``d`` for ``k = 0``): the relaxed fraction over a run ``d``.

    Below ``k d = 1e-8`` by its series ``d (1 - k d / 2)`` (error ``(k d)^2 / 6``, below rounding):
    dividing by a subnormal ``k`` (a rate of 1e-312 1/V) loses most of the quotient's digits.
    """
    y = k * d
    if y < 1e-8:
        return d * (1.0 - 0.5 * y)
    return -math.expm1(-y) / k


def _bw_to_zero(h0: float, sigma: float, amp: float, k_back: float) -> float:
    """The run from ``h0`` (``sigma h0 < 0``) to ``h = 0``: ``log1p(k |h0| / amp) / k``, written as
    ``|h0| / amp`` times ``log1p(x) / x`` (series below ``x = 1e-8``: ``k`` may be subnormal)."""
    ratio = -sigma * h0 / amp
    x = ratio * k_back
    return ratio * (math.log1p(x) / x if x > 1e-8 else 1.0 - 0.5 * x)


def _bw_h(h0: float, d: float, sigma: float, amp: float, k_same: float, k_back: float) -> float:
    """``h`` after a monotone run of length ``d >= 0`` in direction ``sigma`` from ``h0``.

    ``dh/dd = sigma amp - k h`` with ``k = k_back`` while ``sigma h < 0`` (``h`` recovering after a
    reversal) and ``k = k_same`` once ``h`` has the run's sign: exponential relaxation, one sign
    change of ``h`` at most (at ``h = 0`` it moves in direction ``sigma``).
    """
    if sigma * h0 < 0.0:
        d0 = _bw_to_zero(h0, sigma, amp, k_back)
        if d <= d0:
            return h0 + (sigma * amp - k_back * h0) * _bw_phi(k_back, d)
        d -= d0
        h0 = 0.0
    return h0 + (sigma * amp - k_same * h0) * _bw_phi(k_same, d)


def _bw_forward(
    v: F64,
    b: float,
    c: float,
    amp_down: float,
    k_us: float,
    k_ub: float,
    k_ds: float,
    k_db: float,
    u_prev: float,
    h: float,
    out: F64,
) -> float:
    """The Bouc-Wen (Duhem) law forward, exact per sample: ``out[j] = x_h``; returns the last ``h``."""
    for j in range(v.shape[0]):
        u = v[j]
        if u > u_prev:
            h = _bw_h(h, u - u_prev, 1.0, 1.0, k_us, k_ub)
        elif u < u_prev:
            h = _bw_h(h, u_prev - u, -1.0, amp_down, k_ds, k_db)
        out[j] = b * u + c * h
        u_prev = u
    return h


def _bw_run_solve(big: float, q: float, k: float, target: float, cap: float) -> float:
    """``d`` in ``[0, cap]`` with ``big d + q phi(k, d) = target`` (increasing in ``d``; ``target > 0``).

    Newton from ``d = 0`` (its first step, ``target / (big + q)``, taken in closed form): the left
    side is convex (``q < 0``) or concave (``q > 0``), so the iterates then approach the root from
    one side, quadratically; kept inside the bracket, at most 60 steps (2-4 in practice). A step
    below ``1e-9`` of ``d`` leaves an error of order ``k d 1e-18``: below rounding.
    """
    lo, hi = 0.0, cap
    slope0 = big + q
    d = target / slope0 if slope0 > 0.0 else 0.5 * cap
    if not d <= cap:
        d = cap
    for _ in range(60):
        em = math.expm1(-k * d)
        val = big * d + q * _bw_phi(k, d) - target
        if val == 0.0:
            return d
        if val > 0.0:
            hi = d
        else:
            lo = d
        der = big + q * (1.0 + em)
        nxt = d - val / der if der > 0.0 else 0.5 * (lo + hi)
        if not (lo <= nxt <= hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - d) <= 1e-9 * abs(nxt):
            return nxt
        d = nxt
    return d


def _bw_loop(
    xc: F64,
    b: float,
    c: float,
    amp_down: float,
    k_us: float,
    k_ub: float,
    k_ds: float,
    k_db: float,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    u_prev: float,
    h: float,
    out: F64,
) -> tuple[float, float]:
    """Bouc-Wen (Duhem) law + voltage creep: ``out[j] = V_c``; ``e`` updated in place; returns ``(V_c, h)``.

    Per sample the left side ``F(u) = (b + g) u + c h(u)`` is increasing along the run from the
    previous voltage; ``h`` has the closed form of :func:`_bw_h`, so ``F`` has at most two pieces
    (before and after ``h`` changes sign), each ``big d + q phi(k, d)``: the piece holding the
    target is found by one evaluation and solved by :func:`_bw_run_solve`. Bounded cost
    ``O(m)`` + at most 2 x 60 Newton steps. With no creep elements and ``g = 0`` it is the law's
    own exact inverse.
    """
    n = xc.shape[0]
    m = e.shape[0]
    big = b + g
    waa, pull, mem = _creep_ahead(wa, a, ob0, e)
    for j in range(n):
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        f0 = big * u_prev + c * h
        u = u_prev
        if y != f0:
            sigma = 1.0 if y > f0 else -1.0
            amp = 1.0 if sigma > 0.0 else amp_down
            k_same = k_us if sigma > 0.0 else k_ds
            k_back = k_ub if sigma > 0.0 else k_db
            t = sigma * (y - f0)
            u0, h0 = u_prev, h
            if sigma * h0 < 0.0:
                q = c * (amp - sigma * k_back * h0)
                # the recovering piece extended beyond h = 0 is still increasing: solve on it and
                # look for the sign change (a log1p) only when the solution crosses it
                low = big + min(q, 0.0)
                d = _bw_run_solve(big, q, k_back, t, (t / low if low > 0.0 else t / big) * (1.0 + 1e-9))
                h1 = h0 + (sigma * amp - k_back * h0) * _bw_phi(k_back, d)
                if sigma * h1 <= 0.0:
                    u = u0 + sigma * d
                    h = h1
                    t = 0.0
                else:
                    d0 = _bw_to_zero(h0, sigma, amp, k_back)
                    g0 = big * d0 + q * _bw_phi(k_back, d0)
                    t -= g0
                    u0 += sigma * d0
                    h0 = 0.0
                    if t <= 0.0:
                        u, h, t = u0, 0.0, 0.0
            if t > 0.0:
                q = c * (amp - sigma * k_same * h0)
                cap = t / (big + min(q, 0.0)) if big + min(q, 0.0) > 0.0 else t / big
                d = _bw_run_solve(big, q, k_same, t, cap * (1.0 + 1e-9))
                u = u0 + sigma * d
                h = h0 + (sigma * amp - k_same * h0) * _bw_phi(k_same, d)
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    return u_prev, h


def _bwn_pow(x: float, n: float) -> float:
    """``x^n`` for ``x >= 0``, multiplied out for the integer exponents (a ``pow`` call costs ~20 ns)."""
    if n == 2.0:
        return x * x
    if n == 3.0:
        return x * x * x
    return math.pow(x, n)


def _bwn_rate(u: float, amp: float, k_same: float, k_back: float, n: float) -> float:
    """``du/dd = amp - sign(u) |k u|^n`` (``u = sigma h``: ``k_same`` for ``u >= 0``, else ``k_back``)."""
    if u >= 0.0:
        return amp - _bwn_pow(k_same * u, n)
    return amp + _bwn_pow(-k_back * u, n)


def _bwn_u(u: float, d: float, amp: float, k_same: float, k_back: float, n: float) -> float:
    """``u`` after a run of length ``d >= 0``: classic Runge-Kutta, steps of ``k d <= 0.25`` at most.

    The law's own discretisation: forward and inverse take the same steps, so the inverse is exact
    for it; against the ODE the error is of order ``(k d)^5`` per step (below 1e-6 of ``h``).
    """
    k = max(k_same, k_back)
    steps = 1 + int(4.0 * k * d)
    dd = d / steps
    for _ in range(steps):
        r1 = _bwn_rate(u, amp, k_same, k_back, n)
        r2 = _bwn_rate(u + 0.5 * dd * r1, amp, k_same, k_back, n)
        r3 = _bwn_rate(u + 0.5 * dd * r2, amp, k_same, k_back, n)
        r4 = _bwn_rate(u + dd * r3, amp, k_same, k_back, n)
        u += dd * (r1 + 2.0 * r2 + 2.0 * r3 + r4) / 6.0
    return u


def _bwn_forward(
    v: F64,
    b: float,
    c: float,
    amp_down: float,
    k_us: float,
    k_ub: float,
    k_ds: float,
    k_db: float,
    n: float,
    u_prev: float,
    h: float,
    out: F64,
) -> float:
    """The Bouc-Wen (Duhem) law of exponent ``n`` forward: ``out[j] = x_h``; returns the last ``h``."""
    for j in range(v.shape[0]):
        u = v[j]
        if u > u_prev:
            h = _bwn_u(h, u - u_prev, 1.0, k_us, k_ub, n)
        elif u < u_prev:
            h = -_bwn_u(-h, u_prev - u, amp_down, k_ds, k_db, n)
        out[j] = b * u + c * h
        u_prev = u
    return h


def _bwn_loop(
    xc: F64,
    b: float,
    c: float,
    amp_down: float,
    k_us: float,
    k_ub: float,
    k_ds: float,
    k_db: float,
    n: float,
    slope_min: float,
    g: float,
    wa: F64,
    wb: float,
    a: F64,
    ob0: F64,
    e: F64,
    u_prev: float,
    h: float,
    out: F64,
) -> tuple[float, float]:
    """Bouc-Wen law of exponent ``n`` + voltage creep: ``out[j] = V_c``; ``e`` updated in place.

    Per sample, along the run in direction ``sigma`` from the previous voltage, the run length
    ``d`` solves ``G(d) = (b + g) d + c (u(d) - u0) = sigma (y - f0)`` with ``u = sigma h`` stepped
    by :func:`_bwn_u`; ``G`` increases at least at ``slope_min + g`` (the law's smallest slope),
    so the root lies in ``[0, t / (slope_min + g)]``: a bracketed Newton iteration with the ODE's
    own derivative ``G' = b + g + c du/dd``, at most 60 steps (2-4 in practice), each one run of
    the stepper. Bounded cost ``O(m)`` + that. With no creep elements and ``g = 0`` it is the
    law's own exact inverse.
    """
    n_s = xc.shape[0]
    m = e.shape[0]
    big = b + g
    waa, pull, mem = _creep_ahead(wa, a, ob0, e)
    for j in range(n_s):
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        f0 = big * u_prev + c * h
        u = u_prev
        if y != f0:
            sigma = 1.0 if y > f0 else -1.0
            amp = 1.0 if sigma > 0.0 else amp_down
            k_same = k_us if sigma > 0.0 else k_ds
            k_back = k_ub if sigma > 0.0 else k_db
            t = sigma * (y - f0)
            u0 = sigma * h
            lo, hi = 0.0, t / (slope_min + g)
            der0 = big + c * _bwn_rate(u0, amp, k_same, k_back, n)
            d = t / der0 if der0 > 0.0 else 0.5 * hi
            if not d <= hi:
                d = hi
            u1 = u0
            for _ in range(60):
                u1 = _bwn_u(u0, d, amp, k_same, k_back, n)
                val = big * d + c * (u1 - u0) - t
                if val == 0.0:
                    break
                if val > 0.0:
                    hi = d
                else:
                    lo = d
                rate = _bwn_rate(u1, amp, k_same, k_back, n)
                der = big + c * rate
                nxt = d - val / der if der > 0.0 else 0.5 * (lo + hi)
                if not (lo <= nxt <= hi):
                    nxt = 0.5 * (lo + hi)
                if abs(nxt - d) <= 1e-10 * abs(nxt):
                    # a last step below 1e-10 of d: u moves with it at its rate (error ~ k (1e-10 d)^2)
                    u1 += (nxt - d) * rate
                    d = nxt
                    break
                d = nxt
            u = u_prev + sigma * d
            h = sigma * u1
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    return u_prev, h


def _dw_tanh(z: float) -> float:
    """``tanh(z)`` as ``m / (m + 2)``, ``m = expm1(2 z)`` (to rounding; one ``expm1``, cheaper than
    the library's ``tanh``), saturated beyond ``|z| = 20``."""
    if z > 20.0:
        return 1.0
    if z < -20.0:
        return -1.0
    m = math.expm1(2.0 * z)
    return m / (m + 2.0)


def _dw_pan(h: float, hb: float, a: float) -> float:
    """The domain-wall law's anhysteretic curve ``a tanh((h - hb) / a)`` (slope 1 at ``hb``)."""
    return a * _dw_tanh((h - hb) / a)


def _dw_step(
    p: float, h0: float, pa0: float, h1: float, ik: float, hb: float, a: float
) -> tuple[float, float, float]:
    """``P_i`` after the field runs from ``h0`` (where the curve is at ``pa0``) to ``h1``, its
    derivative in ``h1``, and how far the walls moved along the run (0: pinned throughout).

    Along the run (distance ``d``) ``dP/dd = (P_an - P) / k`` while ``P_an`` lies ahead of ``P`` in
    the run's direction, else ``P`` stays (the walls are pinned until the curve passes them). With
    ``P_an`` linear between the run's start (or the crossing, ``P_an = P``) and ``h1`` the step is
    the linear ODE's exact solution: ``P1 = P_an1 (1 - phi) + P_a0 (phi - e) + P e`` with
    ``e = exp(-d / k)``, ``phi = (1 - e) / (d / k)`` (its series below ``d / k = 1e-3``); ``ik`` is
    ``1 / k`` (multiplications: a division costs several).
    """
    if h1 == h0:
        return p, 0.0, 0.0
    sigma = 1.0 if h1 > h0 else -1.0
    t = _dw_tanh((h1 - hb) / a)
    pa1 = a * t
    if sigma * (pa1 - p) <= 0.0:
        return p, 0.0, 0.0
    hs = h0
    if sigma * (pa0 - p) <= 0.0:
        # pinned until the curve reaches P: the run starts there
        r = p / a
        if r >= 1.0:
            r = 1.0 - 1e-16
        elif r <= -1.0:
            r = -1.0 + 1e-16
        hs = hb + a * math.atanh(r)
        pa0 = p
    d = sigma * (h1 - hs)
    if d <= 0.0:
        return p, 0.0, 0.0
    x = d * ik
    e = math.exp(-x)
    if x < 1e-3:
        phi = 1.0 - x * (0.5 - x * (1.0 / 6.0 - x / 24.0))
        q = -0.5 + x * (1.0 / 3.0 - x * 0.125)
    else:
        ix = 1.0 / x
        phi = (1.0 - e) * ix
        q = (e - phi) * ix
    p1 = pa1 * (1.0 - phi) + pa0 * (phi - e) + p * e
    der = (1.0 - t * t) * (1.0 - phi) + sigma * ((pa0 - pa1) * q - (p - pa0) * e) * ik
    return p1, der, d


#: Newton's last step on the field (relative): below it, and inside the piece the walls moved on
#: (the law has a kink where they start to move), they follow the step to first order
#: (``P += dP/dh dh``: an error of ``dh^2 / k``, below 1e-12 V at the steps of a scan) and the
#: iteration stops; along a scan the first iterate from the last sample's slope is that close.
_DW_TOL = 1e-7


def _dw_move(
    p: float, h0: float, v1: float, ik: float, hb: float, a: float, al: float
) -> tuple[float, float]:
    """The field ``h1`` at the drive voltage ``v1`` (``h1 = v1 + al P(h1)``) from the state
    ``(p, h0)``, and ``P`` there: a bracketed Newton iteration on the increasing
    ``F(h) = h - al P(h) - v1`` (``F' = 1 - al dP/dh >= 1 - al``), at most 60 steps; ``ik`` is
    ``1 / k``."""
    dv = v1 - (h0 - al * p)
    if dv == 0.0:
        return h0, p
    near = h0 + dv
    far = h0 + 2.0 * dv / (1.0 - al)
    lo, hi = (near, far) if dv > 0.0 else (far, near)
    h, p1, _ = _dw_solve(p, h0, _dw_pan(h0, hb, a), near, lo, hi, 1.0, -al, v1, ik, hb, a)
    return h, p1


def _dw_solve(
    p: float,
    h0: float,
    pa0: float,
    x: float,
    lo: float,
    hi: float,
    c1: float,
    c2: float,
    y: float,
    ik: float,
    hb: float,
    a: float,
) -> tuple[float, float, float]:
    """The field ``x`` in ``[lo, hi]`` where ``c1 x + c2 P(x) = y`` along the run from the state
    ``(p, h0)`` (the caller's ``c1 + c2 dP/dh`` stays > 0 there), from ``x``: a bracketed Newton
    iteration, at most 60 steps; returns ``(x, P(x), dP/dh)``."""
    p1, der = p, 0.0
    for _ in range(60):
        p1, der, moved = _dw_step(p, h0, pa0, x, ik, hb, a)
        f = c1 * x + c2 * p1 - y
        if f == 0.0:
            break
        if f > 0.0:
            hi = x
        else:
            lo = x
        nxt = x - f / (c1 + c2 * der)
        if not (lo <= nxt <= hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - x) <= _DW_TOL * (1.0 + abs(nxt)) and moved > abs(nxt - x):
            p1 += der * (nxt - x)
            x = nxt
            break
        if abs(nxt - x) <= 1e-15 * (1.0 + abs(nxt)):
            break
        x = nxt
    return x, p1, der


def _dw_relax(
    p: float, h: float, v: float, factor: float, g0: float, hb: float, a: float, al: float
) -> tuple[float, float]:
    """The after-effect over one relaxation at the held drive voltage ``v``: the gap
    ``g = P_an(h) - P`` closes by the Eyring closed form (linear for ``g0 = inf``), then the field
    settles at ``h = v + al P``."""
    pa = _dw_pan(h, hb, a)
    g = pa - p
    if math.isinf(g0):
        p = pa - g * factor
    elif factor < 1.0:
        p = pa - _eyring_gap(g, factor, 2.0 * g0)
    return p, v + al * p


def _dw_forward(
    v: F64,
    k: float,
    hb: float,
    a: float,
    al: float,
    p: float,
    h: float,
    every: int,
    pending: int,
    factor: float,
    g0: float,
    out: F64,
) -> tuple[float, float, int]:
    """The domain-wall law forward: ``out[j] = P`` at the drive voltages ``v`` (the after-effect
    every ``every`` samples, ``pending`` since the last; ``every = 0``: none); returns ``(P, h,
    count)``."""
    cnt = pending
    ik = 1.0 / k
    for j in range(v.shape[0]):
        if every > 0:
            cnt += 1
            if cnt >= every:
                cnt = 0
                p, h = _dw_relax(p, h, h - al * p, factor, g0, hb, a, al)
        h, p = _dw_move(p, h, v[j], ik, hb, a, al)
        out[j] = p
    return p, h, cnt


def _dw_timed_forward(
    t: F64,
    v: F64,
    k: float,
    hb: float,
    a: float,
    al: float,
    p: float,
    h: float,
    t_prev: float,
    interval: float,
    tau: float,
    g0: float,
    max_steps: int,
    out: F64,
) -> None:
    """``P`` at samples of any spacing (a calibration session's voltages at the times ``t``): between
    two samples the voltage moves linearly in steps of about ``interval`` (at most ``max_steps``),
    the gap relaxing before each as the runtime model does every interval (``tau = inf``: none)."""
    ik = 1.0 / k
    for j in range(v.shape[0]):
        span = t[j] - t_prev
        if span > 0.0 and math.isfinite(tau):
            u_prev = h - al * p
            m = min(max_steps, max(1, math.ceil(span / interval)))
            factor = math.exp(-span / m / tau)
            step = (v[j] - u_prev) / m
            for i in range(1, m + 1):
                p, h = _dw_relax(p, h, h - al * p, factor, g0, hb, a, al)
                # the last step ends at the sample's own voltage (not at its rounded sum)
                h, p = _dw_move(p, h, v[j] if i == m else u_prev + step * i, ik, hb, a, al)
        else:
            h, p = _dw_move(p, h, v[j], ik, hb, a, al)
        out[j] = p
        t_prev = t[j]


def _dw_hold(
    p: float, h: float, times: int, factor: float, g0: float, hb: float, a: float, al: float
) -> tuple[float, float]:
    """``times`` relaxations at the held drive voltage (each over one interval)."""
    v = h - al * p
    for _ in range(times):
        p, h = _dw_relax(p, h, v, factor, g0, hb, a, al)
    return p, h


def _dw_loop(
    xc: F64,
    b: float,
    w: float,
    k: float,
    hb: float,
    a: float,
    al: float,
    g: float,
    wa: F64,
    wb: float,
    ca: F64,
    ob0: F64,
    e: F64,
    p: float,
    h: float,
    out: F64,
    every: int,
    pending: int,
    factor: float,
    g0: float,
) -> tuple[float, float, int]:
    """Domain-wall law + voltage creep: ``out[j] = V_c``; ``e`` updated in place; returns
    ``(P, h, count)``.

    Per sample the position ``(b + g) V + w P - y`` is, in the field ``h`` (``V = h - al P``),
    ``G(h) = (b + g) h + beta P(h) - y`` with ``beta = w - (b + g) al``; ``dP/dh`` lies in
    ``[0, 1]`` on every reachable state, so ``G`` increases at least at ``min(b + g, b + g + beta)``
    > 0: a bracketed Newton iteration on ``h`` (at most 60 steps), then ``V = h - al P``
    explicitly. With no creep elements and ``g = 0`` it is the law's own exact inverse.
    """
    n_s = xc.shape[0]
    m = e.shape[0]
    big = b + g
    beta = w - big * al
    g_lo = min(big, big + beta)
    g_hi = max(big, big + beta)
    waa, pull, mem = _creep_ahead(wa, ca, ob0, e)
    u_prev = h - al * p
    cnt = pending
    slope = 0.5
    ik = 1.0 / k
    for j in range(n_s):
        if every > 0:
            cnt += 1
            if cnt >= every:
                cnt = 0
                p, h = _dw_relax(p, h, u_prev, factor, g0, hb, a, al)
        y = xc[j] - mem - wb * u_prev
        ahead = _mem(waa, e)
        t = y - (big * h + beta * p)
        if t != 0.0:
            pa0 = _dw_pan(h, hb, a)
            near = h + t / g_hi
            far = h + 2.0 * t / g_lo
            lo, hi = (near, far) if t > 0.0 else (far, near)
            # the last sample's slope: along a scan the first iterate is then all but the root
            x = h + t / (big + beta * slope)
            if not (lo <= x <= hi):
                x = near
            h, p, slope = _dw_solve(p, h, pa0, x, lo, hi, big, beta, y, ik, hb, a)
        u = h - al * p
        du = u - u_prev
        for i in range(m):
            e[i] = ca[i] * e[i] - ob0[i] * du
        mem = ahead - pull * du
        out[j] = u
        u_prev = u
    return p, h, cnt


def _fast_creep_loop(y: F64, a: F64, w: F64, scale: float, g: float, c: F64, out: F64) -> None:
    """The fast-creep part's inverse (:mod:`piezod.model.fast_creep`), ``c`` updated in place:
    per sample ``x = (scale y - sum_j w_j a_j c_j) / g``, then ``c_j = a_j c_j + (1 - a_j) x``.

    The next sample's sum is ``sum_j w_j a_j^2 c_j + x sum_j w_j a_j (1 - a_j)``: its first term
    does not wait for ``x``, so a sample's dependency chain is one division and one multiply-add.
    """
    m = a.size
    waa, q, s = _creep_ahead(w * a, a, 1.0 - a, c)
    for n in range(y.size):
        x = (scale * y[n] - s) / g
        p = _mem(waa, c)
        for j in range(m):
            c[j] = a[j] * c[j] + (1.0 - a[j]) * x
        s = p + q * x
        out[n] = x


Loop = Callable[..., tuple[float, float]]


def _jit(fn: Any) -> Any:
    """``numba.njit`` with the on-disk cache, or without it where no cache directory is writable
    (numba refuses ``cache=True`` then, e.g. in a hardened service without ``NUMBA_CACHE_DIR``):
    the loops then compile once per process, still at model load."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError:
        return numba.njit(nogil=True)(fn)


# _ch_loop calls ch_solve by its global name, resolved when _ch_loop compiles
_mem = _jit(_mem)
_creep_ahead = _jit(_creep_ahead)
ch_solve = cast(Callable[..., float], _jit(_ch_solve_py))
pi_loop = cast(Loop, _jit(_pi_loop))
ch_loop = cast(Loop, _jit(_ch_loop))
# _gpi_loop calls these by their global names, resolved when it compiles
_grow = _jit(_grow)
_gval = _jit(_gval)
_gpiece = _jit(_gpiece)
_gxh = _jit(_gxh)
_gsettle = _jit(_gsettle)
_eyring_gap = _jit(_eyring_gap)
_relax_plays = _jit(_relax_plays)
relax_plays = cast(Callable[..., None], _relax_plays)
_clip_plays = _jit(_clip_plays)
gpi_loop = cast(Loop, _jit(_gpi_loop))
relax_outputs = cast(Callable[..., int], _jit(_relax_outputs))
timed_relax_outputs = cast(Callable[..., None], _jit(_timed_relax_outputs))
# _bw_forward and _bw_loop call these by their global names, resolved when they compile
_bw_phi = _jit(_bw_phi)
_bw_to_zero = _jit(_bw_to_zero)
_bw_h = _jit(_bw_h)
_bw_run_solve = _jit(_bw_run_solve)
bw_forward = cast(Callable[..., float], _jit(_bw_forward))
bw_loop = cast(Loop, _jit(_bw_loop))
# _bwn_forward and _bwn_loop call these by their global names, resolved when they compile
_bwn_pow = _jit(_bwn_pow)
_bwn_rate = _jit(_bwn_rate)
_bwn_u = _jit(_bwn_u)
bwn_forward = cast(Callable[..., float], _jit(_bwn_forward))
bwn_loop = cast(Loop, _jit(_bwn_loop))
# the domain-wall loops call these by their global names, resolved when they compile
_dw_tanh = _jit(_dw_tanh)
_dw_pan = _jit(_dw_pan)
_dw_step = _jit(_dw_step)
_dw_solve = _jit(_dw_solve)
_dw_move = _jit(_dw_move)
_dw_relax = _jit(_dw_relax)
dw_forward = cast(Callable[..., tuple[float, float, int]], _jit(_dw_forward))
dw_timed_forward = cast(Callable[..., None], _jit(_dw_timed_forward))
dw_hold = cast(Callable[..., tuple[float, float]], _jit(_dw_hold))
dw_loop = cast(Callable[..., tuple[float, float, int]], _jit(_dw_loop))
fast_creep_loop = cast(Callable[..., None], _jit(_fast_creep_loop))

_warm = False


def warm_up() -> None:
    """Compile (or load from the cache) the loops: call it when a model is loaded, not per block.

    Each loop is compiled once per argument signature, and the frozen parameter objects hold
    read-only arrays: a signature of its own. Both the read-only version (what the models pass)
    and the writable one (fits that build arrays on the fly) are compiled here; left to the first
    block, a cold compilation takes seconds.
    """
    global _warm
    if _warm:
        return
    for frozen in (True, False):
        _compile_all(frozen)
    _warm = True


def _compile_all(frozen: bool) -> None:
    """Call every loop once, the parameter arrays read-only when ``frozen`` (as the models pass them)."""

    def param(a: F64) -> F64:
        a = a.copy()
        a.flags.writeable = not frozen
        return a

    one = np.zeros(1)
    creep = (0.1, one, 0.0, one, one, np.zeros(1))  # g, wa, wb, a, ob0, e
    start = (0.0, 0.0, np.empty(1))  # previous voltage, previous state, out
    bw = (1.0, -0.5, 1.0, 0.01, 0.005, 0.01, 0.005)  # b, c, amp_down, rates
    pi_loop(one, 1.0, 0.5, param(one), param(one), *creep, np.zeros(1), *start)
    ch_loop(one, 1.0, 1e-3, 0.5, *creep, *start)
    nodes, dens = np.array([-1.0, 1.0]), np.ones((2, 2))
    gpi_loop(
        one,
        param(one),
        param(nodes),
        param(dens),
        param(np.zeros(2)),
        *creep,
        np.zeros(1),
        *start,
        1,
        0,
        0.5,
        1.0,
    )
    relax_plays(np.zeros(1), 0.0, 0.5, 1.0)
    relax_outputs(one, param(one), np.zeros(1), 0.0, 0, 1, 0.5, 1.0, np.empty((1, 1)))
    timed_relax_outputs(one, one, param(one), np.zeros(1), 0.0, 0.0, 1e-3, 1.0, 1.0, 8, np.empty((1, 1)))
    bw_forward(one, *bw, *start)
    bw_loop(one, *bw, *creep, *start)
    bwn_forward(one, *bw, 2.0, *start)
    bwn_loop(one, *bw, 2.0, 0.5, *creep, *start)
    fast_creep_loop(one, param(one), param(one), 1.0, 1.0, np.zeros(1), np.empty(1))
    dw = (30.0, 40.0, 100.0, 0.3)  # k, hb, a, al
    dw_forward(one, *dw, 0.0, 0.0, 1, 0, 0.5, 1.0, np.empty(1))
    dw_timed_forward(one, one, *dw, 0.0, 0.0, 0.0, 1e-3, 1.0, 1.0, 8, np.empty(1))
    dw_hold(0.0, 0.0, 2, 0.5, 1.0, 40.0, 100.0, 0.3)
    dw_loop(one, 0.4, 0.2, *dw, *creep, 0.0, 0.0, np.empty(1), 1, 0, 0.5, 1.0)


__all__ = [
    "bw_forward",
    "bw_loop",
    "bwn_forward",
    "bwn_loop",
    "ch_loop",
    "ch_solve",
    "dw_forward",
    "dw_hold",
    "dw_loop",
    "dw_timed_forward",
    "fast_creep_loop",
    "gpi_loop",
    "pi_loop",
    "relax_outputs",
    "relax_plays",
    "timed_relax_outputs",
    "warm_up",
]
