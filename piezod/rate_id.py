"""Fast creep identified from the calibration frame's harmonics at its several rates.

The frame scans each voltage range at six rates (0.2-2 Hz). A rate-independent hysteresis law
gives a triangle of a given range and offset the same shape at every rate, so the ``k``-th
harmonic of its response is the same multiple of the drive's ``k``-th harmonic at every rate. What
changes with the rate is the linear dynamics after the law: creep, lags, delays, a mode. So for
two rates ``f`` and ``f_ref`` of the same range and offset the ratio of the readback's harmonics

    rho_k(f) = (X_k(f) / V_k(f)) / (X_k(f_ref) / V_k(f_ref))

does not depend on the hysteresis at all, nor on how well the calibrated model fits it. The same
ratio of the calibrated model (its forward at the frame's voltages, times its sensor path and its
mode, :mod:`piezod.model.sensor`, :mod:`piezod.model.resonance`) says what the model expects. Their
log-ratio is what the model's rate dependence misses:

    D_k(f) = ln rho_k(f) - ln rho^model_k(f)
           ~ sum_j w_j [g_j(k f) - g_j(k f_ref)] - 2 pi i k (f - f_ref) d
             - (2 pi k)^2 (f^2 - f_ref^2) tau_p^2 / 2

with ``g_j(f) = 1 / (1 + 2 pi i f tau_j)`` (fast creep of weight ``w_j``, :mod:`piezod.model.fast_creep`),
``d`` a correction of the sensor path's delay and ``tau_p`` an unmodelled first-order lag (its gain
term; its phase is the delay's). Harmonics up to the 61st of the fastest line make this a
measurement from the frame's slowest line's fundamental to about 30 times its fastest line rate.

The weights sit on :data:`PER_DECADE` log-spaced times from a tenth of a millisecond (or two sample
intervals) to :data:`TAU_MAX_LINES` of the frame's fastest line (longer creep the frame's lines show
directly, and the calibrated model carries it). Each is at most 0.1 and at least minus the model's
own creep near its time (:func:`member_creep_share`): a family member's spectrum is fitted on the
frame's loops, which resolve a few milliseconds at best, and its smoothness prior carries the
resolved weights flat to a tenth of a millisecond; where that is more creep than the stage has, the
harmonics say so and a negative weight takes it out (docs/model-family.md 6.2aw; a member with 3-5x
the stage's creep at 3-30 ms made a 20 Hz line 1.4 % long). They are fitted by bounded linear least
squares with a ridge :data:`RIDGE` on the weights (the pole's gain and a creep element much faster
than the line are alike up to the highest harmonics; the ridge puts such a pair on the pole, which
is not adopted: the readback cannot say on which side of the stage a lag sits, docs/model-family.md
6.2aa). Rows are weighted by their noise (the readback's spectrum between the harmonics) with a
floor :data:`LOG_FLOOR` for what the linear picture leaves.

Adopted when the weights' absolute values total at least :data:`MIN_TOTAL` and, fitted on the
harmonics ``k = 1 (mod 4)``, they predict the others (``k = 3 (mod 4)``: other frequencies) better
than the delay and pole alone by :data:`MIN_GAIN` of the held-out RMS; then fitted on all harmonics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import lsq_linear

from piezod.config import AxisConfig, FastCreepConfig, ScannerConfig
from piezod.errors import ConfigError
from piezod.model.axis_model import AxisModel
from piezod.model.family import CreepSpectrum
from piezod.model.fast_creep import MAX_FAST_CREEP, FastCreep
from piezod.recording import Experiment

F64 = NDArray[np.float64]
C128 = NDArray[np.complex128]

#: Highest (odd) harmonic of a frame line used.
MAX_HARMONIC = 61
#: A harmonic is used when its amplitude is this many times the readback's noise between harmonics.
MIN_SNR = 20.0
#: Floor of a row's log-ratio uncertainty: the linear picture's own error (hysteresis and creep interact).
LOG_FLOOR = 2e-3
#: Relaxation times per decade of the fast spectrum.
PER_DECADE = 4
#: Shortest relaxation time of the fast spectrum (s), unless two sample intervals are longer.
TAU_MIN_S = 1e-4
#: The longest relaxation time is this fraction of the frame's fastest line (a line lasts ``1 / (2 f)``).
TAU_MAX_LINES = 1.0 / 14.0
#: Ridge on the weights, relative to the rows' RMS weight.
RIDGE = 0.02
#: Harmonics above this fraction of an adopted mode's frequency are left out.
MODE_FRACTION = 0.5
#: Least total weight adopted.
MIN_TOTAL = 1e-3
#: Relative fall of the held-out RMS the weights must bring.
MIN_GAIN = 0.05


@dataclass(frozen=True)
class RateFinding:
    """Fast creep fitted on the frame's harmonics, with its held-out test.

    Attributes
    ----------
    fast
        The fitted fast creep (on all harmonics).
    delay_correction_s
        The sensor path's delay correction fitted beside it (s; not adopted).
    pole_s
        The first-order lag fitted beside it (s; not adopted).
    points
        Harmonic ratios used.
    max_frequency_hz
        Highest harmonic frequency used.
    train_rms
        Weighted log-ratio RMS of the fitting harmonics with the delay and pole alone, and with the weights.
    heldout_rms
        The same on the held-out harmonics.
    adopted
        Whether the weights are material and predict the held-out harmonics better.
    note
        One line saying what was found and why it is (not) adopted.
    """

    fast: FastCreep
    delay_correction_s: float
    pole_s: float
    points: int
    max_frequency_hz: float
    train_rms: tuple[float, float]
    heldout_rms: tuple[float, float]
    adopted: bool
    note: str


@dataclass(frozen=True)
class _Harmonics:
    key: tuple[float, float]
    dt_s: float
    rate_hz: float
    k: NDArray[np.int64]
    stage: C128
    model: C128
    sigma: F64  # uncertainty of ln(stage) per harmonic


@dataclass(frozen=True)
class _Rows:
    f: F64
    f_ref: F64
    d: C128
    sigma: F64
    k: NDArray[np.int64]


def fast_taus(dt_s: float, fastest_line_rate_hz: float) -> tuple[float, ...]:
    """The fast spectrum's relaxation times for a frame sampled every ``dt_s`` whose fastest triangle
    runs at ``fastest_line_rate_hz``: :data:`PER_DECADE` per decade from :data:`TAU_MIN_S` (or two
    sample intervals) to :data:`TAU_MAX_LINES` of its line; empty when that span is empty."""
    tau_min = max(TAU_MIN_S, 2.0 * dt_s)
    tau_max = TAU_MAX_LINES / (2.0 * fastest_line_rate_hz)
    if tau_max <= tau_min:
        return ()
    return CreepSpectrum.log_spaced(tau_min, tau_max, PER_DECADE, 0.0).taus


def _period(v: F64) -> tuple[int, int]:
    """Samples per period and whole periods of a periodic drive (the strongest line of its spectrum)."""
    spectrum = np.abs(np.fft.rfft(v - v.mean()))
    loops = int(np.argmax(spectrum[1:])) + 1
    # floor: a record with a partial period at its end (a real recording: P-885's 40.13 periods)
    # must not round the period up past its last sample; a wrong period fails the periodicity check
    return v.size // loops, loops


def _detrended(y: F64, loops: int, per: int) -> F64:
    means = y.reshape(loops, per).mean(axis=1)
    out: F64 = y - (means[-1] - means[0]) / ((loops - 1) * per) * np.arange(y.size)
    return out


def _harmonics(e: Experiment, model: AxisModel) -> _Harmonics | None:
    t = np.asarray(e.t_s, dtype=np.float64)
    v = np.asarray(e.voltage_v, dtype=np.float64)
    x = np.asarray(e.position_um, dtype=np.float64)
    if t.size < 64 or not np.all(np.isfinite(x)):
        return None
    dt = float(np.median(np.diff(t)))
    per, loops = _period(v[:-1])
    if loops < 2 or per < 16:
        return None
    n = loops * per
    f = 1.0 / (per * dt)
    span = float(np.ptp(v))
    shaped = v[:n].reshape(loops, per)
    if span <= 0.0 or float(np.max(np.abs(shaped - shaped[0]))) > 1e-6 * span + 1e-9:
        return None  # not a periodic scan
    one = v[:per]
    state = model.adopt(float(one[0]), float(x[0]))
    _, state = model.forward(np.tile(one, 2), dt, state)
    m, _ = model.forward(v[:n], dt, state)
    ks = np.arange(1, MAX_HARMONIC + 1, 2)
    ks = ks[ks * loops < n // 2 - loops]
    xs = np.fft.rfft(_detrended(x[:n], loops, per))
    ms = np.fft.rfft(_detrended(np.asarray(m, dtype=np.float64), loops, per))
    vs = np.fft.rfft(v[:n])
    between = np.concatenate([xs[ks[ks >= 5] * loops + j] for j in range(1, loops)])
    noise = float(np.sqrt(np.mean(np.abs(between) ** 2))) if between.size else 0.0
    amp = np.abs(xs[ks * loops])
    keep = amp >= MIN_SNR * max(noise, 1e-12)
    ks = ks[keep]
    if ks.size == 0:
        return None
    bins = ks * loops
    centre = 0.5 * (float(v.max()) + float(v.min()))
    key = (round(span, 1), round(centre, 1))
    sigma = noise / np.abs(xs[bins])
    return _Harmonics(key, dt, f, ks, xs[bins] / vs[bins], ms[bins] / vs[bins], sigma)


def _known(config: AxisConfig, f: F64) -> C128:
    """The sensor path and the adopted mode at ``f``: what the readback adds to the model's position."""
    w = 2.0 * math.pi * f
    path = config.sensor_path()
    out: C128 = np.exp(-1j * w * path.delay_s) / (1.0 + 1j * w * path.lag_time_constant_s)
    mode = config.resonance()
    if not mode.off:
        w0 = 2.0 * math.pi * mode.f0_hz
        out = out * w0**2 / (w0**2 - w**2 + 1j * w * w0 / mode.q)
    return out


def _rows(found: Sequence[_Harmonics], config: AxisConfig, cap_hz: float) -> _Rows | None:
    groups: dict[tuple[float, float], list[_Harmonics]] = {}
    for h in found:
        groups.setdefault(h.key, []).append(h)
    f, f_ref, stages, models, sigma, kk = [], [], [], [], [], []
    for members in groups.values():
        members = sorted(members, key=lambda h: h.rate_hz)
        ref = members[0]
        for h in members[1:]:
            if h.rate_hz < 1.2 * ref.rate_hz:
                continue
            common, i_h, i_r = np.intersect1d(h.k, ref.k, return_indices=True)
            for k, a, b in zip(common, i_h, i_r, strict=True):
                fk, fr = k * h.rate_hz, k * ref.rate_hz
                if fk > cap_hz:
                    continue
                stage = h.stage[a] / ref.stage[b]
                model = h.model[a] / ref.model[b]
                if stage == 0 or model == 0:
                    continue
                f.append(fk)
                f_ref.append(fr)
                stages.append(stage)
                models.append(model)
                sigma.append(math.hypot(h.sigma[a], ref.sigma[b]))
                kk.append(k)
    if not f:
        return None
    fa, fr_a = np.array(f), np.array(f_ref)
    model_ratio = np.array(models) * _known(config, fa) / _known(config, fr_a)
    d = np.log(np.array(stages) / model_ratio)
    return _Rows(fa, fr_a, d, np.array(sigma), np.array(kk))


def _design(rows: _Rows, taus: F64) -> tuple[F64, F64]:
    """Weighted real design matrix and right-hand side: creep columns, delay (ms), pole gain (ms^2)."""
    g = [1.0 / (1.0 + 2j * math.pi * rows.f * t) - 1.0 / (1.0 + 2j * math.pi * rows.f_ref * t) for t in taus]
    delay = -2j * math.pi * (rows.f - rows.f_ref) * 1e-3
    pole = -0.5 * (2.0 * math.pi) ** 2 * (rows.f**2 - rows.f_ref**2) * 1e-6 + 0j
    m = np.column_stack([*g, delay, pole])
    wt = 1.0 / np.sqrt(rows.sigma**2 + LOG_FLOOR**2)
    wt = wt / math.sqrt(float(np.mean(wt**2)))
    a = np.vstack([m.real * wt[:, None], m.imag * wt[:, None]])
    b = np.concatenate([rows.d.real * wt, rows.d.imag * wt])
    return a, b


def member_creep_share(config: AxisConfig, taus: F64) -> F64:
    """How much of the motion the wrapped model's own creep spectrum puts near each of ``taus``.

    Parameters
    ----------
    config
        The axis config whose model the fast creep wraps.
    taus
        The fast spectrum's relaxation times (s), log-spaced, ascending.

    Returns
    -------
    numpy.ndarray
        Per element the member's creep weight density at ``tau_j`` (interpolated in ``ln tau``,
        zero outside the member's span) times one fast element's width, as a fraction of the
        model's motion (a weight ``w_i`` of the hysteretic motion is ``w_i / (1 + W)`` of it, for
        either creep driver to first order). Zero for a model that is not a family member: only a
        family member's spectrum reaches below the times its frame resolves (module docstring).
    """
    fam = config.family
    out: F64 = np.zeros(taus.size)
    if config.model != "family" or fam is None or len(fam.creep_taus_s) < 2 or taus.size == 0:
        return out
    log_member = np.log(np.asarray(fam.creep_taus_s, dtype=np.float64))
    weights = np.asarray(fam.creep_weights, dtype=np.float64)
    # per unit of ln tau, each element over its own width (a YAML's times need not be evenly spaced)
    density = weights / (1.0 + float(weights.sum())) / np.gradient(log_member)
    log_fast = np.log(taus)
    width = np.gradient(log_fast) if log_fast.size > 1 else np.ones(1)
    out = np.interp(log_fast, log_member, density, left=0.0, right=0.0) * width
    return out


def _solve(a: F64, b: F64, n_creep: int, floor: F64 | None) -> F64:
    """Creep weights in ``[-floor, 0.1]`` (none if ``floor`` is None), the delay (ms), pole gain (ms^2)."""
    cols = a.shape[1]
    creep = floor is not None
    lower = np.r_[-floor if floor is not None else np.zeros(n_creep), -10.0, 0.0]
    upper = np.r_[np.full(n_creep, 0.1 if creep else 1e-12), 10.0, 25.0]
    ridge = RIDGE * math.sqrt(a.shape[0] / 2.0)
    pen = np.zeros((n_creep, cols))
    pen[:, :n_creep] = ridge * np.eye(n_creep)
    sol = lsq_linear(np.vstack([a, pen]), np.r_[b, np.zeros(n_creep)], bounds=(lower, upper))
    x: F64 = sol.x
    if not creep:
        x[:n_creep] = 0.0
    return x


def _rms(a: F64, b: F64, x: F64) -> float:
    return float(np.sqrt(np.mean((a @ x - b) ** 2)))


def identify_fast_creep(experiments: Sequence[Experiment], config: AxisConfig) -> RateFinding | None:
    """The fast creep ``config``'s model misses, from the frame's periodic scans (None: fewer than
    two rates of one range and offset, or no harmonic above the noise)."""
    from piezod.service.axes import axis_model

    bare = config.model_copy(update={"fast_creep": None})
    model = axis_model(bare)
    found = [h for h in (_harmonics(e, model) for e in experiments) if h is not None]
    if not found:
        return None
    dt = min(h.dt_s for h in found)
    cap = 0.1 / dt
    mode = bare.resonance()
    if not mode.off:
        cap = min(cap, MODE_FRACTION * mode.f0_hz)
    rows = _rows(found, bare, cap)
    if rows is None or rows.f.size < 8:
        return None
    taus = np.array(fast_taus(dt, max(h.rate_hz for h in found)))
    if taus.size == 0:
        return None
    tau_min, tau_max = float(taus[0]), float(taus[-1])
    n = taus.size
    train = rows.k % 4 == 1
    a, b = _design(rows, taus)
    tr = np.concatenate([train, train])
    floor = member_creep_share(bare, taus)
    lag_only = _solve(a[tr], b[tr], n, None)
    with_creep = _solve(a[tr], b[tr], n, floor)
    train_rms = (_rms(a[tr], b[tr], lag_only), _rms(a[tr], b[tr], with_creep))
    held = (_rms(a[~tr], b[~tr], lag_only), _rms(a[~tr], b[~tr], with_creep))
    final = _solve(a, b, n, floor)
    w = final[:n]
    w[np.abs(w) < 1e-6] = 0.0
    spread = float(np.sum(np.abs(w)))
    beyond = spread >= MAX_FAST_CREEP
    if beyond:
        w *= 0.99 * MAX_FAST_CREEP / spread  # reported, never adopted
    fast = FastCreep(tuple(map(float, taus)), tuple(map(float, w)))
    material = fast.spread >= MIN_TOTAL
    better = held[1] <= (1.0 - MIN_GAIN) * held[0]
    adopted = material and better and not beyond
    peak = float(taus[int(np.argmax(np.abs(w)))]) if np.any(w) else float("nan")
    if adopted:
        why = "adopted"
    elif beyond:
        why = f"not adopted: the weights' absolute sum {spread:.3g} is beyond any stage"
    elif not material:
        why = "not adopted: below the least total"
    else:
        why = "not adopted: no better on the held-out harmonics"
    less = " (negative: the model's own creep there is too much)" if fast.total < 0.0 else ""
    span = f"{1e3 * tau_min:.2g}-{1e3 * tau_max:.3g} ms"
    note = (
        f"fast creep {100 * fast.total:.2f} % of the motion{less} ({span}, "
        f"largest at {1e3 * peak:.3g} ms) from {rows.f.size} harmonic ratios up to {rows.f.max():.0f} Hz "
        f"(held-out log-ratio RMS {held[0]:.4f} -> {held[1]:.4f}): {why}"
    )
    return RateFinding(
        fast=fast,
        delay_correction_s=float(final[n]) * 1e-3,
        pole_s=math.sqrt(max(float(final[n + 1]), 0.0)) * 1e-3,
        points=int(rows.f.size),
        max_frequency_hz=float(rows.f.max()),
        train_rms=train_rms,
        heldout_rms=held,
        adopted=adopted,
        note=note,
    )


def adopt_fast_creep(
    experiments: Sequence[Experiment], axis: str, config: ScannerConfig
) -> tuple[ScannerConfig, RateFinding | None]:
    """``config`` with ``axis``'s fast creep when :func:`identify_fast_creep` adopts it (else
    ``config`` unchanged), and the finding (None: the frame cannot measure it)."""
    if axis not in config.axes:
        raise ConfigError(f"the scanner config has no axis {axis!r} (axes: {', '.join(config.axes)})")
    found = identify_fast_creep(experiments, config.axes[axis])
    if found is None or not found.adopted:
        return config, found
    keep = [(t, w) for t, w in zip(found.fast.taus_s, found.fast.weights, strict=True) if w != 0.0]
    part = FastCreepConfig(taus_s=[t for t, _ in keep], weights=[w for _, w in keep])
    return config.with_axis(axis, fast_creep=part), found


__all__ = ["RateFinding", "adopt_fast_creep", "fast_taus", "identify_fast_creep", "member_creep_share"]
