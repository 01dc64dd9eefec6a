"""Principal branch ``W0`` of the Lambert W function, real and vectorised, with a fixed cost.

``W(z) exp(W(z)) = z`` (4.1). The inverse of the hysteresis model (4.11) and the
per-sample inverse of the ODE step need ``W0`` of an argument ``z = ±exp(y)``
whose exponent ``y`` is linear in the target position. Forming ``z`` can overflow
(or underflow) float64 for large ``|alpha V|``, so the work is done in the *log
form*: :func:`lambertw0_exp` solves ``w + ln|w| = y`` (for ``z > 0`` this is the
Wright omega function) and never forms ``exp(y)`` where it could overflow.

Algorithm (no open-ended tolerance loop, the same work for every sample of a region):

* first guess by region of ``y``:

  - ``|z| < 4e-18``: ``W = z (1 - z)``, exact in double precision, no iteration;
  - ``z`` near the branch point ``-1/e`` (``p = sqrt(2 (1 + e z)) < 0.05``): the
    branch-point series ``W = sum mu_k p^k`` to ``p^13`` (Corless et al. 1996),
    exact in double precision, no iteration;
  - ``-1/e < z < 0`` and ``0 < z <= 1``: ``W = z g(p)`` with ``g = W / z = exp(-W)``
    a polynomial in ``p`` (degree 9 and 7, relative error < 2e-7);
  - ``1 < z <= e^4``: a polynomial in ``y`` (degree 8, relative error < 5e-7);
  - ``z > e^4``: the asymptotic series in ``L1 = y``, ``L2 = ln y`` (error < 2e-4);

* then one Halley step of ``w + ln|w| - y = 0`` (two in the asymptotic region);
  Halley converges cubically, so the guesses above end at rounding level
  (about 1e-16 relative away from the branch point, see ``tests/test_lambertw.py``).

The polynomials are least-squares Chebyshev fits to ``W0`` evaluated with mpmath
at 50 digits (600 Chebyshev nodes), converted to monomials in ``t = (v - c) / h``.

A block is evaluated region by region: when all samples fall into one region (the
normal case for a scan line) the region's formula runs on the whole block without
indexing. Arguments below the branch point ``z < -1/e`` raise
:class:`~piezod.errors.LambertWDomainError`; NaN input raises too. No NaN is produced.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import LambertWDomainError

FloatArray = NDArray[np.float64]

#: The branch point ``-1/e`` of the real Lambert W function.
BRANCH_POINT = -math.exp(-1.0)

_E = math.e
#: Below this ``y`` (|z| < 4.2e-18) ``W = z - z^2`` is exact in double precision.
_Y_TINY = -40.0
#: Above this ``y`` (negative z) ``p < 0.05`` and the branch-point series is exact.
_Y_BRANCH = -1.0 + math.log1p(-(0.05**2) / 2.0)
#: Tolerance for ``y`` above -1 (``z`` below ``-1/e`` by rounding only).
_Y_DOMAIN_TOL = 4.0 * np.finfo(np.float64).eps
_Y_POS_MID = 0.0
_Y_POS_ASYM = 4.0

# NEG: g(p) = W/z on p in [0, sqrt 2] (z in [-1/e, 0]), degree 9 in p, max rel err 1.64e-07
_NEG_COEFFS = (
    -0.006349001597478738,
    0.053113019706144765,
    -0.20435052473551996,
    0.49390761671998895,
    -0.88045088957786,
    1.3069026238160322,
    -1.7661176030834256,
    2.264380832689633,
    -2.718247233097841,
    2.71828159449184,
)
# POS: g(p) = W/z on p in [sqrt 2, sqrt(2 (1 + e))] (z in [0, 1]), degree 7, max rel err 4.42e-08
_POS_CENTER, _POS_HALF = 2.070609958384724, 0.6563963960116291
_POS_COEFFS = (
    -1.7859029162090375e-05,
    8.983268342116495e-05,
    -0.0004164459234308871,
    0.002066885258461478,
    -0.010062411189126689,
    0.047181094734430155,
    -0.2059316359211507,
    0.7342338047106443,
)
# MID: W(e^y) on y in [0, 4], degree 8, max rel err 4.13e-07
_MID_CENTER, _MID_HALF = 2.0, 2.0
_MID_COEFFS = (
    1.634540018504053e-05,
    0.00028870961526863194,
    -0.001206836191981121,
    0.0015647370007186197,
    0.004505638927794518,
    -0.04016895737442045,
    0.18624634386550223,
    1.2178795891663567,
    1.55714564242219,
)
# Branch-point series W0 = sum_k mu_k p^k, k = 0..13 (highest power first).
_BRANCH_COEFFS = (
    0.0010262633205076076,
    -0.001576930344686784,
    0.002440877991143983,
    -0.003811298034892,
    0.0060145432529561185,
    -0.009616892024299429,
    0.015635632532333927,
    -0.025984714873603758,
    0.04450231481481483,
    -0.07962962962962962,
    0.1527777777777778,
    -0.3333333333333333,
    1.0,
    -1.0,
)


def _horner(coeffs: Sequence[float], t: FloatArray) -> FloatArray:
    acc = t * coeffs[0]
    acc += coeffs[1]
    for c in coeffs[2:]:
        acc *= t
        acc += c
    return acc


def _halley_g(w: FloatArray, g: FloatArray) -> FloatArray:
    """One Halley step of ``w + ln|w| = y`` for a guess ``w = z g`` (``g = w / z``), in place on ``w``.

    With ``ln|w| = y + ln g`` the residual is ``r = y - w - ln|w| = -(w + ln g)``: no
    cancellation against a large ``|y|``. The step is ``w (1 + r / (a - r / (2 a)))``
    with ``a = 1 + w``. ``g`` is overwritten.
    """
    m = np.log(g, out=g)
    m += w  # -r
    a = w + 1.0
    t = m / a
    t *= 0.5
    t += a  # a - r / (2 a)
    m /= t
    m *= w
    w -= m
    return w


def _halley_y(w: FloatArray, y: FloatArray) -> FloatArray:
    """One Halley step of ``w + ln w = y`` (``w > 0``), in place on ``w``."""
    r = np.log(w)
    r += w
    np.subtract(y, r, out=r)
    a = w + 1.0
    t = r / a
    t *= -0.5
    t += a  # a - r / (2 a)
    r /= t
    r *= w
    w += r
    return w


def _neg_z(y: FloatArray, z: FloatArray | None) -> FloatArray:
    if z is not None:
        return z
    z = np.exp(y)
    return np.negative(z, out=z)


def _pos_z(y: FloatArray, z: FloatArray | None) -> FloatArray:
    return np.exp(y) if z is None else z


def _neg_tiny(y: FloatArray, z: FloatArray | None) -> FloatArray:
    z = _neg_z(y, z)
    return z - z * z


def _pos_tiny(y: FloatArray, z: FloatArray | None) -> FloatArray:
    z = _pos_z(y, z)
    return z - z * z


def _neg_main(y: FloatArray, z: FloatArray | None) -> FloatArray:
    z = _neg_z(y, z)
    p = z * (2.0 * _E)
    p += 2.0  # > 2.5e-3 in this region
    np.sqrt(p, out=p)
    g = _horner(_NEG_COEFFS, p)
    w = z * g
    return _halley_g(w, g)


def _neg_branch(y: FloatArray, z: FloatArray | None) -> FloatArray:
    p = np.expm1(y + 1.0)
    p *= -2.0
    np.maximum(p, 0.0, out=p)
    np.sqrt(p, out=p)
    return _horner(_BRANCH_COEFFS, p)


def _pos_small(y: FloatArray, z: FloatArray | None) -> FloatArray:
    z = _pos_z(y, z)
    p = z * (2.0 * _E)
    p += 2.0
    np.sqrt(p, out=p)
    p -= _POS_CENTER
    p *= 1.0 / _POS_HALF
    g = _horner(_POS_COEFFS, p)
    w = z * g
    return _halley_g(w, g)


def _pos_mid(y: FloatArray, z: FloatArray | None) -> FloatArray:
    t = y - _MID_CENTER
    t *= 1.0 / _MID_HALF
    w = _horner(_MID_COEFFS, t)
    return _halley_y(w, y)


def _asymptotic(y: float | FloatArray, l2: float | FloatArray) -> float | FloatArray:
    inv = 1.0 / y
    return y - l2 + l2 * inv * (1.0 + inv * (0.5 * (l2 - 2.0) + inv * ((6.0 + l2 * (-9.0 + 2.0 * l2)) / 6.0)))


def _pos_large(y: FloatArray, z: FloatArray | None) -> FloatArray:
    w = np.asarray(_asymptotic(y, np.log(y)), dtype=np.float64)
    _halley_y(w, y)
    return _halley_y(w, y)


_Kernel = Callable[[FloatArray, FloatArray | None], FloatArray]

_NEG_BOUNDS = (_Y_TINY, _Y_BRANCH)
_NEG_KERNELS: tuple[_Kernel, ...] = (_neg_tiny, _neg_main, _neg_branch)
_POS_BOUNDS = (_Y_TINY, _Y_POS_MID, _Y_POS_ASYM)
_POS_KERNELS: tuple[_Kernel, ...] = (_pos_tiny, _pos_small, _pos_mid, _pos_large)


def _dispatch(
    y: FloatArray,
    z: FloatArray | None,
    lo: float,
    hi: float,
    bounds: tuple[float, ...],
    kernels: tuple[_Kernel, ...],
) -> FloatArray:
    i_lo = bisect.bisect_right(bounds, lo)
    i_hi = bisect.bisect_right(bounds, hi)
    if i_lo == i_hi:
        return kernels[i_lo](y, z)
    region = np.searchsorted(bounds, y, side="right")
    out = np.empty_like(y)
    for i in range(i_lo, i_hi + 1):
        idx = np.flatnonzero(region == i)
        if idx.size:
            out[idx] = kernels[i](y[idx], None if z is None else z[idx])
    return out


def _w0(
    y: FloatArray, z: FloatArray | None, negative: bool, bounds: tuple[float, float] | None = None
) -> FloatArray:
    """Checked evaluation on a contiguous 1-D ``y`` (and optionally ``z = ±exp(y)``)."""
    if bounds is None:
        lo = float(y.min())
        hi = float(y.max())
    else:
        lo, hi = bounds
    if math.isnan(lo) or math.isnan(hi):
        raise LambertWDomainError("Lambert W argument is NaN")
    if hi == math.inf:
        raise LambertWDomainError("Lambert W argument exponent is +inf (z overflows to infinity)")
    if negative:
        if hi > -1.0 + _Y_DOMAIN_TOL:
            z_bad = -math.exp(min(hi, 709.0))
            raise LambertWDomainError(
                f"Lambert W argument z = -exp({hi!r}) = {z_bad!r} is below the branch point "
                f"-1/e = {BRANCH_POINT!r}: no real solution"
            )
        return _dispatch(y, z, lo, hi, _NEG_BOUNDS, _NEG_KERNELS)
    return _dispatch(y, z, lo, hi, _POS_BOUNDS, _POS_KERNELS)


def _as_1d(values: ArrayLike) -> tuple[FloatArray, tuple[int, ...]]:
    arr = np.asarray(values, dtype=np.float64)
    return np.ascontiguousarray(arr.reshape(-1)), arr.shape


def lambertw0_exp(y: ArrayLike, *, negative: bool = False) -> FloatArray:
    """``W0(exp(y))`` (or ``W0(-exp(y))``) without overflow for large ``y``.

    For ``negative=False`` this is the Wright omega function, the solution of
    ``w + ln w = y``, defined for every real ``y``. For ``negative=True`` it is
    ``W0(-exp(y))``, the solution in ``[-1, 0)`` of ``w + ln(-w) = y``, defined for
    ``y <= -1``.

    Parameters
    ----------
    y
        Natural logarithm of ``|z|``; ``-inf`` gives ``W0(0) = 0``.
    negative
        Whether ``z = -exp(y)`` (True) or ``z = exp(y)`` (False).

    Returns
    -------
    ndarray
        ``W0(±exp(y))``, same shape as ``y``.

    Raises
    ------
    LambertWDomainError
        If ``negative`` and ``y > -1`` (``z < -1/e``), or any ``y`` is NaN or ``+inf``.
    """
    flat, shape = _as_1d(y)
    if flat.size == 0:
        return np.empty(shape)
    return _w0(flat, None, negative).reshape(shape)


def lambertw0_exp_bounded(y: FloatArray, y_min: float, y_max: float, *, negative: bool) -> FloatArray:
    """:func:`lambertw0_exp` for a contiguous 1-D block whose bounds the caller already knows.

    Saves the two reductions over the block when ``y`` is a monotone map of inputs
    that were checked (the inverses derive the bounds of ``y`` from those of the
    targets). The bounds select the regions and do the domain check; they must
    bound ``y`` (a bound off by rounding is harmless: every region's formula stays
    accurate slightly beyond its edges).

    Raises
    ------
    LambertWDomainError
        As :func:`lambertw0_exp`, judged on the bounds.
    """
    if y.size == 0:
        return np.empty(0)
    return _w0(y, None, negative, (y_min, y_max))


def lambertw0(z: ArrayLike) -> FloatArray:
    """Principal branch ``W0(z)`` for real ``z >= -1/e``.

    Parameters
    ----------
    z
        Real arguments. Values below ``-1/e`` by rounding only (``ln(-z) + 1 <= 4 eps``)
        are treated as the branch point (``W = -1``).

    Returns
    -------
    ndarray
        ``W0(z)``, same shape as ``z``, ``W0(z) >= -1``.

    Raises
    ------
    LambertWDomainError
        If any ``z < -1/e`` (the message names the smallest such value), any ``z``
        is NaN, or ``z = +inf``.
    """
    flat, shape = _as_1d(z)
    if flat.size == 0:
        return np.empty(shape)
    lo = float(flat.min())
    hi = float(flat.max())
    if math.isnan(lo) or math.isnan(hi):
        raise LambertWDomainError("Lambert W argument is NaN")
    if hi == math.inf:
        raise LambertWDomainError("Lambert W argument is +inf")
    if lo < BRANCH_POINT and math.log(-lo) > -1.0 + _Y_DOMAIN_TOL:
        raise LambertWDomainError(
            f"Lambert W argument z = {lo!r} is below the branch point -1/e = {BRANCH_POINT!r}: "
            "no real solution"
        )
    with np.errstate(divide="ignore"):
        if lo >= 0.0:
            return _w0(np.log(flat), flat, False).reshape(shape)
        if hi < 0.0:
            return _w0(np.log(np.negative(flat)), flat, True).reshape(shape)
        out = np.zeros_like(flat)
        for mask, negative in ((flat < 0.0, True), (flat > 0.0, False)):
            part = np.ascontiguousarray(flat[mask])
            if part.size:
                out[mask] = _w0(np.log(np.abs(part)), part, negative)
    return out.reshape(shape)


def lambertw0_exp_scalar(y: float, *, negative: bool = False) -> float:
    """Scalar :func:`lambertw0_exp` in plain Python, for per-run solves inside a Python loop.

    Same first guesses and Halley steps as the vectorised version.

    Raises
    ------
    LambertWDomainError
        As :func:`lambertw0_exp`.
    """
    if math.isnan(y) or y == math.inf:
        raise LambertWDomainError(f"Lambert W argument exponent is {y!r}")
    if negative and y > -1.0 + _Y_DOMAIN_TOL:
        raise LambertWDomainError(
            f"Lambert W argument z = -exp({y!r}) is below the branch point -1/e = {BRANCH_POINT!r}: "
            "no real solution"
        )
    if y < _Y_TINY:
        z = -math.exp(y) if negative else math.exp(y)
        return z - z * z
    if negative and y > _Y_BRANCH:
        return _horner_scalar(_BRANCH_COEFFS, math.sqrt(max(-2.0 * math.expm1(y + 1.0), 0.0)))
    if negative or y <= _Y_POS_MID:
        if negative:
            z = -math.exp(y)
            g = _horner_scalar(_NEG_COEFFS, math.sqrt(2.0 + 2.0 * _E * z))
        else:
            z = math.exp(y)
            g = _horner_scalar(_POS_COEFFS, (math.sqrt(2.0 + 2.0 * _E * z) - _POS_CENTER) / _POS_HALF)
        w = z * g
        r = -(w + math.log(g))
        a = 1.0 + w
        return w + w * r / (a - 0.5 * r / a)
    if y <= _Y_POS_ASYM:
        w = _horner_scalar(_MID_COEFFS, (y - _MID_CENTER) / _MID_HALF)
        steps = 1
    else:
        w = float(_asymptotic(y, math.log(y)))
        steps = 2
    for _ in range(steps):
        r = y - w - math.log(w)
        a = 1.0 + w
        w += w * r / (a - 0.5 * r / a)
    return w


def _horner_scalar(coeffs: Sequence[float], t: float) -> float:
    acc = coeffs[0]
    for c in coeffs[1:]:
        acc = acc * t + c
    return acc
