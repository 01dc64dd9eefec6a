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
    for j in range(n):
        mem = 0.0
        for i in range(m):
            mem += wa[i] * e[i]
        y = xc[j] - mem - wb * u_prev
        f = xh + g * u_prev
        u = u_prev
        if y > f:
            slope = base
            for i in range(p):
                if plays[i] + r[i] <= u:
                    slope += b * pw[i]
            while True:
                knot = math.inf
                for i in range(p):
                    k = plays[i] + r[i]
                    if u < k < knot:
                        knot = k
                cand = u + (y - f) / slope
                if cand <= knot:
                    u = cand
                    break
                f += slope * (knot - u)
                u = knot
                for i in range(p):
                    if plays[i] + r[i] == knot:
                        slope += b * pw[i]
            acc = 0.0
            for i in range(p):
                lo = u - r[i]
                if plays[i] < lo:
                    plays[i] = lo
                acc += pw[i] * plays[i]
            xh = b * (rho0 * u + acc)
        elif y < f:
            slope = base
            for i in range(p):
                if plays[i] - r[i] >= u:
                    slope += b * pw[i]
            while True:
                knot = -math.inf
                for i in range(p):
                    k = plays[i] - r[i]
                    if knot < k < u:
                        knot = k
                cand = u + (y - f) / slope
                if cand >= knot:
                    u = cand
                    break
                f += slope * (knot - u)
                u = knot
                for i in range(p):
                    if plays[i] - r[i] == knot:
                        slope += b * pw[i]
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
    for j in range(n):
        mem = 0.0
        for i in range(m):
            mem += wa[i] * e[i]
        y = xc[j] - mem - wb * u_prev
        u = ch_solve(b, alpha, delta, g, y, u_prev, y0)
        xh = y - g * u
        y0 = xh - b * u
        du = u - u_prev
        for i in range(m):
            e[i] = a[i] * e[i] - ob0[i] * du
        out[j] = u
        u_prev = u
    return u_prev, xh


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
ch_solve = cast(Callable[..., float], _jit(_ch_solve_py))
pi_loop = cast(Loop, _jit(_pi_loop))
ch_loop = cast(Loop, _jit(_ch_loop))

_warm = False


def warm_up() -> None:
    """Compile (or load from the cache) the loops: call it when a model is loaded, not per block."""
    global _warm
    if _warm:
        return
    one = np.zeros(1)
    pi_loop(one, 1.0, 0.5, one, one, 0.1, one, 0.0, one, one, np.zeros(1), np.zeros(1), 0.0, 0.0, np.empty(1))
    ch_loop(one, 1.0, 1e-3, 0.5, 0.1, one, 0.0, one, one, np.zeros(1), 0.0, 0.0, np.empty(1))
    _warm = True


__all__ = ["ch_loop", "ch_solve", "pi_loop", "warm_up"]
