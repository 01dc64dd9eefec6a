"""Where a lag sits: at the drive (the amplifier's pole) or at the sensor, measured on the stage.

The frame's loops cannot place a lag. A first-order lag commutes with a linear stage, and on a
hysteretic one the difference between ``H(L v)`` (the amplifier's pole before the ceramic) and
``L(H v)`` (a sensor's filter after it) is a branch shift proportional to the line rate, which
the fitted creep takes (docs/model-family.md 6.2af: on ``heath27`` the frame's held-out RMS
preferred the sensor side, 12.06 against 12.62 nm, for a 1 ms pole at the drive). So the
calibration puts a lag it cannot place at the sensor (the tie rule of 6.2c), and a drive pole
then goes uncompensated: ``-6 tau^2 / L^2`` of a fast line's length.

Hysteresis remembers where the voltage turned, which a filter after the stage cannot change. A
short excursion (*spike*) beyond the turning point of a slow ramp leaves the stage on the branch
of the turning point the ceramic saw: the commanded one when the lag is at the sensor, one
``(1 - g) dV`` short of it when it is at the drive (``g`` the lagged excursion's peak gain).
After the spike the slow branch is offset for good (the memory), while the sensor's lag and the
stage's mode have died out. Each spike is paired with a control, the same ramp without it; the
model's error along the ramp cancels in the difference:

    J = sign [(post - pre)_spike - (post - pre)_control]

of the readback's residual from the written model's prediction (``post`` after the spike has
died out, ``pre`` just before it). A drive lag the model leaves out gives ``J < 0``, one it has
too much of ``J > 0``; ``J`` is close to linear in the time moved between the sensor path and the
drive, so the time to move is its zero. The calibration moves time from the sensor path to the
drive (``J < 0``) or from the member's own drive lag to the sensor path (``J > 0``), which keeps
the lags' sum the frame's loops pin. A drive lag left too long drives every line with a lead the
stage does not need: on held-out stages whose sensor lag the member took at the drive, the
frame's fast lines came out long against its slow ones (by up to 0.15 %; docs/model-family.md
6.2bj). The zero is also measured where it asks for more drive lag than the sensor path holds
(the frame pins the sum loosely: the member's creep can take part of a drive lag's rate
dependence; :data:`ADDED_MAX`), and reported, not made: on the stage where it acted it made the
fastest verified line worse (docs/model-family.md 6.2an).

This module is pure numpy (the model's forward and a first-order filter); the stage side plays
:func:`placement_program` as one recorded segment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from piezod.audit.dynamics import pure_delay
from piezod.config import AxisName, ScannerConfig
from piezod.errors import CalibrationError
from piezod.model.sensor import SensorPath
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: The recorded experiment's label.
PLACEMENT_LABEL = "lag-placement"
#: Ramp rate of the slow parts, in spans (voltage range) per second: well below the frame's
#: fastest lines (2 Hz over 0.98 of the span: 3.9 spans/s), so the turning point the ramp sets
#: is the commanded one on either placement.
RAMP_SPANS_PER_S = 0.8
#: Shortest spike half (s): long against the lags placed (up to a few ms), short against the creep.
SPIKE_S = 0.01
#: Spike patterns: (turning point as a fraction of the span, spike as a fraction, direction).
PATTERNS: tuple[tuple[float, float, int], ...] = (
    (0.6, 0.15, 1),
    (0.75, 0.12, 1),
    (0.4, 0.15, -1),
    (0.25, 0.12, -1),
)
#: Windows of the residual before and after each turning point (s). The one after starts when the
#: spike, the sensor's lag and the stage's ringing have died out.
PRE_S = (0.15, 0.005)
POST_AFTER_S = 0.05
POST_S = 0.15
#: A move (either way) is adopted when the jumps at it are at most this
#: fraction of the jumps at none moved (RMS over the patterns).
ADOPT_FRACTION = 0.5
#: ... and the time is at least this much (s): less is below what a 20 Hz line feels.
MIN_MOVED_S = 5e-5
#: The zero is sought up to this fraction of the written lags' sum of drive lag beyond the sensor
#: path, or :data:`ADDED_MIN_S` when that is more (the frame fits a drive lag short when its creep
#: takes part of it, not by more than that; a tenth of :data:`SPIKE_S` keeps the spike's peak on
#: the lagged drive).
ADDED_MAX = 1.0
ADDED_MIN_S = 1e-3


@dataclass(frozen=True, slots=True)
class PlacementProgram:
    """The placement experiment's voltages on one axis.

    Attributes
    ----------
    volts
        The voltages at ``rate_hz`` (one recorded segment).
    rate_hz
        The sample rate.
    marks_s
        Per spike or control: when the ramp reaches its turning point (s from the first sample).
    spike_s
        Duration of one spike half (s).
    signs
        Per pair: +1 for a turning point on the way up, -1 on the way down.
    """

    volts: F64
    rate_hz: float
    marks_s: tuple[float, ...]
    spike_s: float
    signs: tuple[int, ...]

    @property
    def duration_s(self) -> float:
        """Time on the stage (s)."""
        return self.volts.size / self.rate_hz


def placement_program(
    voltage_min_v: float, voltage_max_v: float, slew_rate_v_per_s: float, rate_hz: float
) -> PlacementProgram:
    """The placement experiment: two slow full-range loops (they wipe the hysteresis memory the
    frame left), then per pattern of :data:`PATTERNS` a spike and its control.

    Every voltage stays 1 % of the span inside the limits; the spikes keep to half the slew limit.
    """
    span = voltage_max_v - voltage_min_v
    if not (span > 0.0 and rate_hz > 0.0 and slew_rate_v_per_s > 0.0):
        raise CalibrationError("placement experiment: empty voltage range, or no sample rate or slew limit")
    edge = 0.01 * span
    low, high = voltage_min_v + edge, voltage_max_v - edge
    rate = RAMP_SPANS_PER_S * span

    def ramp(a: float, b: float, v_per_s: float) -> F64:
        n = max(2, round(abs(b - a) / v_per_s * rate_hz))
        return np.linspace(a, b, n + 1)[1:]

    parts: list[F64] = [np.array([low])]
    for _ in range(2):
        parts += [ramp(low, high, rate), ramp(high, low, rate)]
    longest = max(abs(dv) for _, dv, _ in PATTERNS) * span
    spike_s = max(SPIKE_S, longest / (0.5 * slew_rate_v_per_s), 20.0 / rate_hz)
    marks: list[float] = []
    at = low
    for top_frac, dv_frac, sign in PATTERNS:
        start = low if sign > 0 else high
        top = voltage_min_v + top_frac * span
        dv = sign * dv_frac * span
        for spike in (True, False):
            parts += [ramp(at, start, rate), np.full(round(0.2 * rate_hz), start), ramp(start, top, rate)]
            marks.append(sum(p.size for p in parts) / rate_hz)
            if spike:
                parts += [ramp(top, top + dv, abs(dv) / spike_s), ramp(top + dv, top, abs(dv) / spike_s)]
            else:
                parts.append(np.full(2 * round(spike_s * rate_hz), top))
            parts.append(ramp(top, start, rate))
            at = start
    return PlacementProgram(
        np.concatenate(parts), float(rate_hz), tuple(marks), spike_s, tuple(s for _, _, s in PATTERNS)
    )


def program_for(config: ScannerConfig, axis: AxisName, rate_hz: float) -> PlacementProgram:
    """:func:`placement_program` on ``axis``'s voltage and slew limits."""
    ax = config.axes[axis]
    return placement_program(ax.voltage_min_v, ax.voltage_max_v, ax.slew_rate_v_per_s, rate_hz)


def first_order_lag(values: F64, dt_s: float, tau_s: float) -> F64:
    """``values`` through the exact discrete first-order lag ``tau_s`` (settled at the first one)."""
    x = np.asarray(values, dtype=np.float64)
    if x.size == 0 or tau_s <= 0.0:
        return x
    a = math.exp(-dt_s / tau_s)
    out: F64 = np.asarray(lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])[0], dtype=np.float64)
    return out


def through_sensor(position_um: F64, dt_s: float, path: SensorPath) -> F64:
    """What the sensor path makes of positions: the first-order lag, then the delay (as
    :mod:`piezod.model.sensor` describes it); the first sample is taken as settled."""
    x = first_order_lag(np.asarray(position_um, dtype=np.float64), dt_s, path.lag_time_constant_s)
    if x.size == 0:
        return x
    return pure_delay(x, dt_s, path.delay_s, 0)


def movable_s(config: ScannerConfig, axis: AxisName) -> float:
    """The sensor path's time that can move to the drive (its lag plus its delay; 0 when the axis
    model has no drive lag of its own, i.e. is not a family member)."""
    ax = config.axes[axis]
    if ax.model != "family" or ax.family is None:
        return 0.0
    path = ax.sensor_path()
    return path.lag_time_constant_s + path.delay_s


def drive_lag_s(config: ScannerConfig, axis: AxisName) -> float:
    """The family member's own drive lag, which can move to the sensor path (0 when the axis model
    is not a family member)."""
    ax = config.axes[axis]
    if ax.model != "family" or ax.family is None:
        return 0.0
    return float(ax.family.lag_time_constant_s)


def added_limit_s(config: ScannerConfig, axis: AxisName) -> float:
    """How far the drive lag may grow beyond the sensor path's time (:data:`ADDED_MAX`); 0 when
    the axis model is not a family member."""
    ax = config.axes[axis]
    if ax.model != "family" or ax.family is None:
        return 0.0
    return max(ADDED_MAX * (movable_s(config, axis) + drive_lag_s(config, axis)), ADDED_MIN_S)


def moved_config(config: ScannerConfig, axis: AxisName, moved_s: float) -> ScannerConfig:
    """``config`` with ``moved_s`` of ``axis``'s sensor path (its lag first, then its delay) moved
    to the family member's drive lag (a first-order pole, ``lag_time_constant_s``), and what
    exceeds the sensor path added to the drive lag; a negative ``moved_s`` moves that much of the
    drive lag to the sensor path's lag instead."""
    ax = config.axes[axis]
    if moved_s == 0.0:
        return config
    if ax.family is None or moved_s < -drive_lag_s(config, axis) * (1.0 + 1e-9):
        raise CalibrationError(
            f"axis {axis}: cannot move {abs(moved_s) * 1e3:.3f} ms of its drive lag to the sensor"
        )
    path = ax.sensor_path()
    if moved_s > 0.0:
        lag = max(path.lag_time_constant_s - moved_s, 0.0)
        delay = max(path.delay_s - max(moved_s - path.lag_time_constant_s, 0.0), 0.0)
    else:
        lag, delay = path.lag_time_constant_s - moved_s, path.delay_s
    extensions = {str(k): dict(v) for k, v in (ax.extensions or {}).items() if k != "delay"}
    if lag > 0.0 or delay > 0.0:
        extensions["delay"] = {"delay_s": delay, "lag_time_constant_s": lag}
    drive = max(ax.family.lag_time_constant_s + moved_s, 0.0)
    family = ax.family.model_copy(update={"lag_time_constant_s": drive})
    return config.with_axis(axis, family=family, extensions=extensions or None)


def predicted_readback(experiment: Experiment, config: ScannerConfig, axis: AxisName) -> F64:
    """The readback ``config`` predicts for the experiment's voltages: its axis model from rest at
    the first voltage, then its sensor path."""
    from piezod.service.axes import axis_model

    ax = config.axes[axis]
    model = axis_model(ax)
    v = np.asarray(experiment.voltage_v, dtype=np.float64)
    dt = _dt(experiment)
    x, _ = model.forward(v, dt, model.rest(float(v[0])))
    return through_sensor(np.asarray(x, dtype=np.float64), dt, ax.sensor_path())


def _dt(experiment: Experiment) -> float:
    t = np.asarray(experiment.t_s, dtype=np.float64)
    if t.size < 2:
        raise CalibrationError(f"{experiment.label}: fewer than two samples")
    return float(np.median(np.diff(t)))


def jumps_um(experiment: Experiment, program: PlacementProgram, predicted_um: F64) -> F64:
    """Per pattern, the spike's jump minus its control's (``J`` of the module's docstring), um.

    A pattern whose windows hold a non-finite readback (the sensor's range) gives ``nan``.
    """
    t = np.asarray(experiment.t_s, dtype=np.float64)
    t = t - t[0]
    resid = np.asarray(experiment.position_um, dtype=np.float64) - predicted_um

    def mean(lo_s: float, hi_s: float) -> float:
        i, j = np.searchsorted(t, [lo_s, hi_s])
        part = resid[i:j]
        if part.size == 0 or not np.all(np.isfinite(part)):
            return math.nan
        return float(np.mean(part))

    steps = []
    for mark in program.marks_s:
        pre = mean(mark - PRE_S[0], mark - PRE_S[1])
        after = mark + 2.0 * program.spike_s + POST_AFTER_S
        steps.append(mean(after, after + POST_S) - pre)
    out = [sign * (steps[2 * k] - steps[2 * k + 1]) for k, sign in enumerate(program.signs)]
    return np.asarray(out, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class LagPlacement:
    """What the placement experiment says of the written model's lags.

    Attributes
    ----------
    movable_s
        The sensor path's time (lag plus delay) that could move to the drive.
    drive_lag_s
        The member's own drive lag, which could move to the sensor path.
    placed_s
        Where the jumps' zero lies, as time moved to the drive: from ``-drive_lag_s`` (the member's
        drive lag moved to the sensor path) to ``movable_s`` plus :func:`added_limit_s` (drive lag
        added beyond the sensor path's).
    moved_s
        The move the calibration makes: ``placed_s`` within ``[-drive_lag_s, movable_s]`` (more
        drive lag than the sensor path holds is reported, not made: docs/model-family.md 6.2an).
    jumps_um
        Per pattern, ``J`` of the written model (um).
    jumps_moved_um
        The same with ``moved_s`` moved.
    adopted
        Whether the move is adopted (:data:`ADOPT_FRACTION`, :data:`MIN_MOVED_S`).
    note
        One line for the calibration's report.
    """

    movable_s: float
    drive_lag_s: float
    placed_s: float
    moved_s: float
    jumps_um: tuple[float, ...]
    jumps_moved_um: tuple[float, ...]
    adopted: bool
    note: str


def _rms(values: F64) -> float:
    good = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(good * good))) if good.size else math.nan


def place_lag(
    experiment: Experiment, program: PlacementProgram, config: ScannerConfig, axis: AxisName
) -> LagPlacement | None:
    """Measure where ``config``'s lags belong from the placement experiment.

    The jumps are computed as written and with a move in their sign's direction (the whole
    sensor path to the drive when they are negative, or :func:`added_limit_s` at the drive when
    there is none; the member's whole drive lag to the sensor path when positive), the zero of
    their mean taken by the secant (they are close to linear in it). The part of it that moves
    the sensor path to the drive, or the member's drive lag to the sensor path, is the move,
    checked there; more drive lag than the sensor path holds is reported.

    Returns
    -------
    LagPlacement or None
        None when the axis model has no drive lag to place (not a family member).

    Raises
    ------
    CalibrationError
        The recording does not hold the program (another length), or no pattern was read.
    """
    dt = _dt(experiment)
    got = np.asarray(experiment.voltage_v).size
    if abs(got * dt - program.duration_s) > 2.0 * dt:
        raise CalibrationError(
            f"{experiment.label}: {got * dt:.3f} s recorded, not the placement program's "
            f"{program.duration_s:.3f} s"
        )
    forward, back, added = movable_s(config, axis), drive_lag_s(config, axis), added_limit_s(config, axis)
    if added <= 0.0:
        return None
    hi = forward + added

    seen: dict[float, F64] = {}

    def jumps_at(moved_s: float) -> F64:
        # the move made and the one reported are often the secant's end: one forward pass each
        if moved_s not in seen:
            placed = moved_config(config, axis, moved_s)
            seen[moved_s] = jumps_um(experiment, program, predicted_readback(experiment, placed, axis))
        return seen[moved_s]

    at_none = jumps_at(0.0)
    if not np.any(np.isfinite(at_none)):
        raise CalibrationError(f"{experiment.label}: no pattern inside the sensor's range")
    j0 = float(np.nanmean(at_none))
    end = (forward if forward > 0.0 else hi) if j0 < 0.0 else -back
    placed = 0.0
    if end != 0.0:
        j1 = float(np.nanmean(jumps_at(end)))
        placed = end * j0 / (j0 - j1) if j0 != j1 else 0.0
        placed = float(np.clip(placed, -back, hi) if placed * end > 0.0 else 0.0)
    moved = float(np.clip(placed, -back, forward))
    at_moved = jumps_at(moved)
    before, after = _rms(at_none), _rms(at_moved)
    adopted = abs(moved) >= MIN_MOVED_S and after <= ADOPT_FRACTION * before
    n = int(np.isfinite(at_none).sum())
    if moved < 0.0 or forward > 0.0:
        if moved < 0.0:
            what = f"{-moved * 1e3:.3f} of the member's {back * 1e3:.3f} ms drive lag at the sensor"
            made, left = "sensor", "drive"
        else:
            what = f"{moved * 1e3:.3f} of the sensor path's {forward * 1e3:.3f} ms at the drive"
            made, left = "drive", "sensor"
        verdict = f"moved to the {made}" if adopted else f"left at the {left}"
        note = (
            f"lag placement: {what} "
            f"(spike jumps {before * 1e3:.1f} -> {after * 1e3:.1f} nm RMS over {n} patterns): {verdict}"
        )
    else:
        note = (
            f"lag placement: no sensor path to move to the drive "
            f"(spike jumps {before * 1e3:.1f} nm RMS over {n} patterns)"
        )
    if placed - moved >= MIN_MOVED_S:
        there = _rms(jumps_at(placed))
        asked = f"{(placed - forward) * 1e3:.3f} ms more drive lag than written"
        note += f"; the jumps' zero asks for {asked} ({there * 1e3:.1f} nm there): reported, not made"
    return LagPlacement(
        forward,
        back,
        placed,
        moved,
        tuple(float(j) for j in at_none),
        tuple(float(j) for j in at_moved),
        adopted,
        note,
    )
