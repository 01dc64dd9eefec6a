"""The stage's mechanical resonance, identified on the residual of the model calibration chose.

The audit's resonance candidate is fitted against the audit's own baseline (the thesis model),
whose misfit is tens of times the ringing; there it is never material, or it fits an overdamped
filter that acts as a lag (docs/model-family.md 6.2x). The ringing decides a slow scan's
nonlinearity all the same. So once calibration has chosen and extended its model, the frame is
replayed through that model at the recording's full rate (the family fit decimates the loops
far below a mode's frequency) and the resonance is fitted to what the model leaves:

    r = y - M(V)               the readback (aligned by the sensor path) minus the model
    d = R(M(V)) - M(V)         what a resonance (f0, Q) would add to the model's output

both high-passed alike (a centred moving average of :data:`HIGH_PASS_S` subtracted: the slow
misfit and the offsets go, a mode above 50 Hz stays), the first third of every experiment left
out (the model's hysteresis memory starts from a guess). ``(f0, Q)`` minimise ``|r - d + l x'|``
on the training experiments, with ``l`` the lag that best explains the rest (a lag the model
and its sensor path leave, which an overdamped resonance would otherwise take: the held-out tube
stage's 0.3 ms sensor delay made the fit an overdamped 1.4 kHz filter); a grid in ``f0`` and ``Q``,
then ``scipy.optimize.least_squares`` in ``(ln f0, ln Q)``. The comparison is with the same lag
term alone. The resonance is adopted when

* it rings: ``Q >= MIN_Q`` and ``f0`` inside the registry's bounds, at least
  :data:`MIN_HARMONIC` times the fastest line rate and below 0.4 times the sample rate;
* it predicts the held-out experiments (every fourth, as the model choice holds out) better: their
  high-passed residual RMS falls by at least :data:`MIN_GAIN` of what it has above the readback's
  noise floor (:func:`piezod.fitstats.lowers`; the high pass keeps white noise nearly whole), the
  floor as the readback aligned by the sensor path carries it
  (:meth:`piezod.model.sensor.SensorPath.noise_gain`: interpolating a fractional delay smooths the
  noise, and the raw floor could exceed the whole residual).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d
from scipy.optimize import least_squares

from piezod.audit.dynamics import resonance
from piezod.audit.residuals import experiments_noise_floor
from piezod.config import AxisConfig, ScannerConfig
from piezod.errors import ConfigError, ModelError
from piezod.fitstats import lowers
from piezod.model.registry import spec
from piezod.readback import experiments_through_sensor
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: Width of the moving average the residuals are high-passed with (s).
HIGH_PASS_S = 0.05
#: Least quality factor of a resonance that rings (below it, it acts as a lag or as a rate misfit's
#: stand-in). The first modes of the simulated stages have Q 4-80 and nPoint's measured one rings
#: sharply; every fit with Q 1-2 on them stood in for something else: a sensor delay (909 Hz, Q 1.4,
#: docs/model-family.md 6.2y) or a member's excess millisecond creep (birch35's 255 Hz, Q 1.66, whose
#: stage rings at 1020 Hz, Q 22; 6.2aw).
MIN_Q = 2.0
#: The resonance must lie at least this many times above the fastest line rate.
MIN_HARMONIC = 5.0
#: Relative fall of the held-out high-passed residual RMS a resonance must bring.
MIN_GAIN = 0.05
#: Frequencies of the coarse grid, and the quality factors tried at each.
GRID_F0 = 48
GRID_Q = (2.0, 8.0, 30.0)


@dataclass(frozen=True)
class ResonanceFinding:
    """A resonance fitted on a model's residual, with its held-out test.

    Attributes
    ----------
    f0_hz, q
        The fitted resonance.
    train_rms_um
        High-passed training residual RMS without and with it.
    heldout_rms_um
        The same on the held-out experiments.
    adopted
        Whether it rings and predicts the held-out experiments better.
    note
        One line saying what was found and why it is (not) adopted.
    """

    f0_hz: float
    q: float
    train_rms_um: tuple[float, float]
    heldout_rms_um: tuple[float, float]
    adopted: bool
    note: str

    @property
    def effect(self) -> dict[str, float]:
        """``{f0_hz, q}`` for the axis's ``extensions: resonance``."""
        return {"f0_hz": self.f0_hz, "q": self.q}


@dataclass(frozen=True)
class _Piece:
    dt_s: float
    width: int
    model_um: F64
    residual_um: F64
    rate_um_per_s: F64
    keep: NDArray[np.bool_]
    train: bool


def _high_pass(x: F64, width: int) -> F64:
    if width < 3 or x.size <= width:
        return x - float(np.mean(x))
    out: F64 = x - uniform_filter1d(x, width, mode="nearest")
    return out


def _line_rate_hz(e: Experiment) -> float:
    v = np.asarray(e.voltage_v, dtype=np.float64)
    dv = np.diff(v)
    dv = dv[dv != 0.0]
    turns = int(np.count_nonzero(np.diff(np.sign(dv)) != 0))
    duration = float(e.t_s[-1] - e.t_s[0])
    return 0.5 * turns / duration if duration > 0 else 0.0


def _held_out(i: int, every: int) -> bool:
    """Experiment ``i`` is held out (every ``every``-th, as the model choice holds out)."""
    return i % every == every - 1


def _pieces(experiments: Sequence[Experiment], config: AxisConfig, every: int) -> list[_Piece]:
    from piezod.service.axes import axis_model

    model = axis_model(config)
    aligned = experiments_through_sensor(experiments, config.sensor_path())
    out = []
    for i, e in enumerate(aligned):
        t = np.asarray(e.t_s, dtype=np.float64)
        if t.size < 64:
            continue
        dt = float(np.median(np.diff(t)))
        v = np.asarray(e.voltage_v, dtype=np.float64)
        y = np.asarray(e.position_um, dtype=np.float64)
        state = model.adopt(float(v[0]), float(y[0]))
        m, _ = model.forward(v, dt, state)
        width = max(3, round(HIGH_PASS_S / dt))
        keep = np.zeros(t.size, dtype=bool)
        keep[t.size // 3 : t.size - width // 2] = True
        rate = _high_pass(np.gradient(m, dt), width)
        out.append(_Piece(dt, width, m, _high_pass(y - m, width), rate, keep, not _held_out(i, every)))
    return out


def _lefts(pieces: Sequence[_Piece], f0: float | None, q: float) -> list[F64]:
    """What a resonance ``(f0, Q)`` (None: none) leaves of each piece's residual, on its kept rows."""
    out = []
    for p in pieces:
        r = p.residual_um
        if f0 is not None:
            r = r - _high_pass(resonance(p.model_um, p.dt_s, f0, q, 0) - p.model_um, p.width)
        out.append(r[p.keep])
    return out


def _lag(pieces: Sequence[_Piece], lefts: Sequence[F64]) -> float:
    """The lag (s) that best explains what the resonance leaves of the residual, ``r ~ -lag x'``."""
    num = den = 0.0
    for p, r in zip(pieces, lefts, strict=True):
        g = p.rate_um_per_s[p.keep]
        num += float(r @ g)
        den += float(g @ g)
    return -num / den if den > 0.0 else 0.0


def _misfits(pieces: Sequence[_Piece], lefts: Sequence[F64], lag_s: float) -> F64:
    return np.concatenate([r + lag_s * p.rate_um_per_s[p.keep] for p, r in zip(pieces, lefts, strict=True)])


def _rms(pieces: Sequence[_Piece], lefts: Sequence[F64], lag_s: float) -> float:
    r = _misfits(pieces, lefts, lag_s)
    return math.sqrt(float(r @ r) / r.size) if r.size else math.nan


def _train_rms(pieces: Sequence[_Piece], f0: float | None, q: float) -> float:
    lefts = _lefts(pieces, f0, q)
    return _rms(pieces, lefts, _lag(pieces, lefts))


def identify_resonance(
    experiments: Sequence[Experiment], config: AxisConfig, *, every: int = 4
) -> ResonanceFinding | None:
    """Fit a resonance to what ``config``'s model (with its parts and sensor path) leaves of the frame.

    Parameters
    ----------
    experiments
        The calibration frame (one axis), at the rate it was recorded.
    config
        The axis's calibrated configuration.
    every
        Every ``every``-th experiment is held out.

    Returns
    -------
    ResonanceFinding or None
        None when the frame cannot resolve a resonance (too slow a recording, too few experiments).
    """
    pieces = _pieces(experiments, config, every)
    train = [p for p in pieces if p.train]
    held = [p for p in pieces if not p.train]
    if not train or not held:
        return None
    f_line = max(_line_rate_hz(e) for e in experiments)
    dt = max(p.dt_s for p in pieces)
    f_lo_reg, f_hi_reg = spec("resonance").param("f0_hz").physical
    q_lo, q_hi = spec("resonance").param("q").physical
    f_lo = max(f_lo_reg, MIN_HARMONIC * f_line)
    f_hi = min(f_hi_reg, 0.4 / dt)
    if not f_lo < f_hi:
        return None
    grid = np.geomspace(f_lo, f_hi, GRID_F0)
    scores = sorted((_train_rms(train, float(f), q), float(f), q) for f in grid for q in GRID_Q)

    def residuals(z: F64) -> F64:
        lefts = _lefts(train, math.exp(float(z[0])), math.exp(float(z[1])))
        return _misfits(train, lefts, _lag(train, lefts))

    best: tuple[float, float, float] | None = None
    lo = np.array([math.log(f_lo), math.log(q_lo)])
    hi = np.array([math.log(f_hi), math.log(q_hi)])
    for _, f0, q in scores[:2]:
        try:
            sol = least_squares(residuals, np.clip([math.log(f0), math.log(q)], lo, hi), bounds=(lo, hi))
        except (ValueError, ModelError):
            continue
        cand = (math.sqrt(2.0 * float(sol.cost) / sol.fun.size), math.exp(sol.x[0]), math.exp(sol.x[1]))
        if best is None or cand[0] < best[0]:
            best = cand
    if best is None:
        return None
    _, f0, q = best
    without, with_mode = _lefts(train, None, q), _lefts(train, f0, q)
    lag0, lag1 = _lag(train, without), _lag(train, with_mode)
    tr = (_rms(train, without, lag0), _rms(train, with_mode, lag1))
    ho = (_rms(held, _lefts(held, None, q), lag0), _rms(held, _lefts(held, f0, q), lag1))
    why = []
    if q < MIN_Q:
        why.append(f"Q {q:.3g} < {MIN_Q:g}: it does not ring")
    if not f_lo * 1.0001 < f0 < f_hi * 0.9999:
        why.append(f"f0 on the search's bound [{f_lo:.4g}, {f_hi:.4g}] Hz")
    held_raw = [e for i, e in enumerate(experiments) if _held_out(i, every)]
    floor = experiments_noise_floor(held_raw) * config.sensor_path().noise_gain(dt)
    if not (ho[1] == ho[0] == 0.0 or lowers(ho[1], ho[0], MIN_GAIN, floor)):
        why.append(f"held-out gain below {100 * MIN_GAIN:g} %")
    adopted = not why
    note = (
        f"resonance f0 {f0:.4g} Hz, Q {q:.3g} on the calibrated model's residual (high-passed RMS "
        f"{tr[0] * 1e3:.2f} -> {tr[1] * 1e3:.2f} nm training, {ho[0] * 1e3:.2f} -> {ho[1] * 1e3:.2f} nm "
        f"held out): " + ("adopted" if adopted else "not adopted (" + "; ".join(why) + ")")
    )
    return ResonanceFinding(f0, q, tr, ho, adopted, note)


def adopt_resonance(
    experiments: Sequence[Experiment], axis: str, config: ScannerConfig
) -> tuple[ScannerConfig, ResonanceFinding | None]:
    """``config`` with ``axis``'s resonance part when :func:`identify_resonance` adopts one (else
    ``config`` unchanged), and the finding (None: the frame cannot resolve one)."""
    from piezod.extensions import Adoption, extended_config

    if axis not in config.axes:
        raise ConfigError(f"the scanner config has no axis {axis!r} (axes: {', '.join(config.axes)})")
    found = identify_resonance(experiments, config.axes[axis])
    if found is None or not found.adopted:
        return config, found
    return extended_config(config, axis, Adoption({"resonance": found.effect})), found


__all__ = ["ResonanceFinding", "adopt_resonance", "identify_resonance"]
