"""Offline measurement sessions on the simulated stage (no board, no pty).

:func:`run_session` runs a plan of experiments (triangular scans over ranges x frequencies x
offsets, settling loops, a repeated reference experiment, sines, ramps, steps, nested minor
loops) through a :class:`~hil_sim.stage.Stage` at a given sample rate and returns, per
experiment, the time, the voltage, the sensed position (with sensor noise and optional
quantisation) and the label: the data the pty simulator would deliver, minus the board.

The stage starts at rest; between experiments the voltage moves to the next start voltage at
the slew rate (these moves, and the settle cycles of a scan unless ``record_settle``, are
simulated but not recorded). Time is continuous over the session (``t = k / sample_rate``).
:func:`piezod.simulator.session_recording` gives the session as the host's recording (this
package imports nothing of the host: its errors are :mod:`hil_sim.errors`, a scanner config is
read through the :class:`ScannerAxesLike` protocol).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.errors import SimSafetyError as SafetyError
from hil_sim.stage import ScannerLike, Stage, StageConfig

F64 = NDArray[np.float64]
AxisName = Literal["x", "y", "z"]


class AxisLimitsLike(Protocol):
    """What :func:`run_scanner_session` reads of one axis of a scanner config."""

    @property
    def voltage_min_v(self) -> float: ...

    @property
    def voltage_max_v(self) -> float: ...

    @property
    def slew_rate_v_per_s(self) -> float: ...

    @property
    def safe_voltage_v(self) -> float: ...


class ScannerAxesLike(ScannerLike, Protocol):
    """What :func:`run_scanner_session` reads of a scanner config (``piezod.config.ScannerConfig``)."""

    @property
    def sample_rate_hz(self) -> float: ...


def _num(value: float) -> str:
    return f"{value:g}".replace("+", "")


def _check_positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(f"{name} must be finite and > 0, got {value!r}")


def _check_finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value!r}")


def _piecewise_linear(points_v: Sequence[float], rate_v_per_s: float, fs: float) -> F64:
    """Samples ``k / fs`` (k >= 1) of the path through ``points_v`` at ``rate_v_per_s``, to its end."""
    v = np.asarray(points_v, dtype=np.float64)
    times = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(v)) / rate_v_per_s)))
    n = max(1, math.ceil(times[-1] * fs - 1e-9))
    t = np.arange(1, n + 1) / fs
    out: F64 = np.interp(t, times, v)
    return out


class PlanItem(Protocol):
    """What :func:`run_session` needs from an experiment of a plan."""

    @property
    def kind(self) -> str:
        """Kind of experiment (``triangle``, ``sine``, ...)."""
        ...

    def start_voltage_v(self) -> float:
        """Voltage the experiment starts from (reached by a slew-limited move)."""
        ...

    def name(self) -> str:
        """The experiment label."""
        ...

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """Voltage samples after the start (first at ``1 / fs``) and the number of unrecorded lead samples."""
        ...

    def params(self) -> dict[str, float | str]:
        """Nominal parameters, for the record."""
        ...


@dataclass(frozen=True, slots=True)
class Triangle:
    """Periodic triangular scan from ``offset - range/2`` up to ``offset + range/2`` and back.

    Attributes
    ----------
    range_v
        Peak-to-peak voltage (V).
    frequency_hz
        Line (trace + retrace) frequency (Hz).
    offset_v
        Centre voltage (V).
    cycles
        Recorded loops.
    settle_cycles
        Loops run before the recorded ones (thesis: 4 before recording).
    record_settle
        Record the settle loops too, as a separate experiment ``<label>_settle``.
    label
        Experiment label (default ``tri_r<range>V_f<freq>Hz_o<offset>V``).
    """

    range_v: float
    frequency_hz: float
    offset_v: float = 0.0
    cycles: int = 4
    settle_cycles: int = 2
    record_settle: bool = False
    label: str | None = None

    def __post_init__(self) -> None:
        _check_positive("range_v", self.range_v)
        _check_positive("frequency_hz", self.frequency_hz)
        _check_finite("offset_v", self.offset_v)
        if self.cycles < 1 or self.settle_cycles < 0:
            raise ConfigError(
                f"need cycles >= 1 and settle_cycles >= 0, got {self.cycles}, {self.settle_cycles}"
            )

    @property
    def kind(self) -> str:
        """``triangle``."""
        return "triangle"

    def start_voltage_v(self) -> float:
        """The lower turning point."""
        return self.offset_v - 0.5 * self.range_v

    def name(self) -> str:
        """The label."""
        return (
            self.label or f"tri_r{_num(self.range_v)}V_f{_num(self.frequency_hz)}Hz_o{_num(self.offset_v)}V"
        )

    def _phase_wave(self, sample_rate_hz: float) -> tuple[F64, F64, int]:
        total = round((self.settle_cycles + self.cycles) * sample_rate_hz / self.frequency_hz)
        lead = round(self.settle_cycles * sample_rate_hz / self.frequency_hz)
        t = np.arange(1, total + 1) / sample_rate_hz
        return t, np.mod(t * self.frequency_hz, 1.0), lead

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """The scan samples and the number of settle samples."""
        _, phase, lead = self._phase_wave(sample_rate_hz)
        tri = np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
        v: F64 = self.start_voltage_v() + self.range_v * tri
        return v, lead

    def params(self) -> dict[str, float | str]:
        """Range, frequency and offset."""
        return {"range_v": self.range_v, "frequency_hz": self.frequency_hz, "offset_v": self.offset_v}


@dataclass(frozen=True, slots=True)
class Sine(Triangle):
    """Periodic sine ``offset - range/2 cos(2 pi f t)`` (same attributes as :class:`Triangle`)."""

    @property
    def kind(self) -> str:
        """``sine``."""
        return "sine"

    def name(self) -> str:
        """The label."""
        return (
            self.label or f"sin_r{_num(self.range_v)}V_f{_num(self.frequency_hz)}Hz_o{_num(self.offset_v)}V"
        )

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """The sine samples and the number of settle samples."""
        t, _, lead = self._phase_wave(sample_rate_hz)
        v: F64 = self.offset_v - 0.5 * self.range_v * np.cos(2.0 * np.pi * self.frequency_hz * t)
        return v, lead


@dataclass(frozen=True, slots=True)
class Ramp:
    """A single linear ramp from ``start_v`` to ``stop_v`` in ``duration_s``."""

    start_v: float
    stop_v: float
    duration_s: float
    label: str | None = None

    def __post_init__(self) -> None:
        _check_finite("start_v", self.start_v)
        _check_finite("stop_v", self.stop_v)
        _check_positive("duration_s", self.duration_s)

    @property
    def kind(self) -> str:
        """``ramp``."""
        return "ramp"

    def start_voltage_v(self) -> float:
        """``start_v``."""
        return self.start_v

    def name(self) -> str:
        """The label."""
        return self.label or f"ramp_{_num(self.start_v)}V_to_{_num(self.stop_v)}V_{_num(self.duration_s)}s"

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """The ramp samples."""
        n = max(1, round(self.duration_s * sample_rate_hz))
        v: F64 = self.start_v + (self.stop_v - self.start_v) * np.arange(1, n + 1) / n
        return v, 0

    def params(self) -> dict[str, float | str]:
        """Start, stop, duration."""
        return {"start_v": self.start_v, "stop_v": self.stop_v, "duration_s": self.duration_s}


@dataclass(frozen=True, slots=True)
class Step:
    """Hold ``from_v`` for ``before_s``, jump to ``to_v`` within one sample and hold it for ``after_s``."""

    from_v: float
    to_v: float
    after_s: float
    before_s: float = 0.0
    label: str | None = None

    def __post_init__(self) -> None:
        _check_finite("from_v", self.from_v)
        _check_finite("to_v", self.to_v)
        _check_positive("after_s", self.after_s)
        if not (math.isfinite(self.before_s) and self.before_s >= 0.0):
            raise ConfigError(f"before_s must be finite and >= 0, got {self.before_s!r}")

    @property
    def kind(self) -> str:
        """``step``."""
        return "step"

    def start_voltage_v(self) -> float:
        """``from_v``."""
        return self.from_v

    def name(self) -> str:
        """The label."""
        return self.label or f"step_{_num(self.from_v)}V_to_{_num(self.to_v)}V"

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """Hold, then the step."""
        n_before = round(self.before_s * sample_rate_hz)
        n_after = max(1, round(self.after_s * sample_rate_hz))
        v: F64 = np.concatenate([np.full(n_before, self.from_v), np.full(n_after, self.to_v)])
        return v, 0

    def params(self) -> dict[str, float | str]:
        """Levels and durations."""
        return {"from_v": self.from_v, "to_v": self.to_v, "before_s": self.before_s, "after_s": self.after_s}


@dataclass(frozen=True, slots=True)
class Hold:
    """Constant voltage for ``duration_s`` (rest, creep and drift observation)."""

    voltage_v: float
    duration_s: float
    label: str | None = None

    def __post_init__(self) -> None:
        _check_finite("voltage_v", self.voltage_v)
        _check_positive("duration_s", self.duration_s)

    @property
    def kind(self) -> str:
        """``hold``."""
        return "hold"

    def start_voltage_v(self) -> float:
        """``voltage_v``."""
        return self.voltage_v

    def name(self) -> str:
        """The label."""
        return self.label or f"hold_{_num(self.voltage_v)}V_{_num(self.duration_s)}s"

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """Constant samples."""
        return np.full(max(1, round(self.duration_s * sample_rate_hz)), self.voltage_v), 0

    def params(self) -> dict[str, float | str]:
        """Voltage and duration."""
        return {"voltage_v": self.voltage_v, "duration_s": self.duration_s}


@dataclass(frozen=True, slots=True)
class Waypoints:
    """Piecewise-linear path through ``voltages_v`` at constant ``|dV/dt| = rate_v_per_s``."""

    voltages_v: tuple[float, ...]
    rate_v_per_s: float
    label: str | None = None

    def __post_init__(self) -> None:
        if len(self.voltages_v) < 2 or not all(math.isfinite(v) for v in self.voltages_v):
            raise ConfigError("voltages_v needs at least two finite voltages")
        _check_positive("rate_v_per_s", self.rate_v_per_s)

    @property
    def kind(self) -> str:
        """``waypoints``."""
        return "waypoints"

    def start_voltage_v(self) -> float:
        """The first waypoint."""
        return float(self.voltages_v[0])

    def name(self) -> str:
        """The label."""
        return self.label or f"path_{len(self.voltages_v)}pts_{_num(self.rate_v_per_s)}Vps"

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """The path samples."""
        return _piecewise_linear(self.voltages_v, self.rate_v_per_s, sample_rate_hz), 0

    def params(self) -> dict[str, float | str]:
        """Rate and number of waypoints."""
        return {"rate_v_per_s": self.rate_v_per_s, "waypoints": float(len(self.voltages_v))}


@dataclass(frozen=True, slots=True)
class MinorLoops:
    """Nested minor loops: from ``center - A_0`` through ``center +/- A_k`` for decreasing ``A_k``.

    Each loop of amplitude ``A_k`` is run ``repeats`` times; every loop lies inside the previous
    one (first-order reversal curves, the test of the hysteresis memory).
    """

    center_v: float
    amplitudes_v: tuple[float, ...]
    rate_v_per_s: float
    repeats: int = 1
    label: str | None = None

    def __post_init__(self) -> None:
        _check_finite("center_v", self.center_v)
        amps = self.amplitudes_v
        if not amps or not all(math.isfinite(a) and a > 0 for a in amps):
            raise ConfigError("amplitudes_v needs positive finite amplitudes")
        if any(b > a for a, b in itertools.pairwise(amps)):
            raise ConfigError(f"amplitudes_v must not increase (nested loops), got {amps}")
        _check_positive("rate_v_per_s", self.rate_v_per_s)
        if self.repeats < 1:
            raise ConfigError(f"repeats must be >= 1, got {self.repeats}")

    @property
    def kind(self) -> str:
        """``minor_loops``."""
        return "minor_loops"

    def start_voltage_v(self) -> float:
        """``center - A_0``."""
        return self.center_v - self.amplitudes_v[0]

    def name(self) -> str:
        """The label."""
        return self.label or f"minor_{len(self.amplitudes_v)}loops_c{_num(self.center_v)}V"

    def waypoints(self) -> list[float]:
        """The turning points, start included."""
        pts = [self.start_voltage_v()]
        for amp in self.amplitudes_v:
            for _ in range(self.repeats):
                pts += [self.center_v + amp, self.center_v - amp]
        return pts

    def waveform(self, sample_rate_hz: float) -> tuple[F64, int]:
        """The loop samples."""
        return _piecewise_linear(self.waypoints(), self.rate_v_per_s, sample_rate_hz), 0

    def params(self) -> dict[str, float | str]:
        """Centre, largest amplitude, rate."""
        return {
            "center_v": self.center_v,
            "max_amplitude_v": self.amplitudes_v[0],
            "rate_v_per_s": self.rate_v_per_s,
        }


def calibration_plan(
    ranges_v: Iterable[float],
    frequencies_hz: Iterable[float],
    offsets_v: Iterable[float] = (0.0,),
    *,
    cycles: int = 4,
    settle_cycles: int = 2,
    record_settle: bool = False,
    reference: Triangle | None = None,
    reference_every: int = 0,
) -> list[PlanItem]:
    """Triangular scans over ranges x frequencies x offsets, with an optional repeated reference.

    Parameters
    ----------
    ranges_v, frequencies_hz, offsets_v
        The grid (peak-to-peak V, Hz, V); offsets vary slowest, frequencies fastest.
    cycles, settle_cycles, record_settle
        Per scan, see :class:`Triangle`.
    reference
        A scan repeated first, after every ``reference_every`` grid scans and last, labelled
        ``reference_01``, ``reference_02``, ... (to see the session's slow changes).
    reference_every
        Grid scans between references (0: reference only first and last).
    """
    grid: list[PlanItem] = [
        Triangle(r, f, o, cycles=cycles, settle_cycles=settle_cycles, record_settle=record_settle)
        for o in offsets_v
        for r in ranges_v
        for f in frequencies_hz
    ]
    if reference is None:
        return grid
    plan: list[PlanItem] = []
    count = 0

    def add_reference() -> None:
        nonlocal count
        count += 1
        plan.append(
            Triangle(
                reference.range_v,
                reference.frequency_hz,
                reference.offset_v,
                cycles=reference.cycles,
                settle_cycles=reference.settle_cycles,
                label=f"reference_{count:02d}",
            )
        )

    add_reference()
    for i, item in enumerate(grid, start=1):
        plan.append(item)
        if reference_every > 0 and i % reference_every == 0 and i < len(grid):
            add_reference()
    add_reference()
    return plan


@dataclass(frozen=True, eq=False)
class ExperimentRecord:
    """The recorded samples of one experiment.

    Attributes
    ----------
    label, kind, axis
        Experiment label, kind (``triangle``, ``settle``, ...), axis.
    t_s
        Time since the session start (s).
    voltage_v
        Voltage at the piezo (V).
    position_um
        Sensor reading (um): true position plus sensor noise (and quantisation).
    true_position_um
        The stage position before the sensor noise (um), for tests.
    params
        Nominal experiment parameters (range_v, frequency_hz, offset_v, ...).
    """

    label: str
    kind: str
    axis: AxisName
    t_s: F64
    voltage_v: F64
    position_um: F64
    true_position_um: F64
    params: Mapping[str, float | str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.size)


@dataclass(frozen=True, eq=False)
class SessionResult:
    """The recorded experiments of a session, in order.

    Attributes
    ----------
    experiments
        One record per recorded experiment.
    sample_rate_hz
        Sample rate (Hz).
    axis
        The driven axis.
    config
        The stage that produced the data (with its effects).
    """

    experiments: tuple[ExperimentRecord, ...]
    sample_rate_hz: float
    axis: AxisName
    config: StageConfig

    def __getitem__(self, label: str) -> ExperimentRecord:
        for rec in self.experiments:
            if rec.label == label:
                return rec
        raise KeyError(label)

    def labels(self) -> list[str]:
        """Labels in order."""
        return [rec.label for rec in self.experiments]


def _run(stage: Stage, v: F64, dt_s: float, block: int) -> F64:
    parts = [stage.step(v[i : i + block], dt_s) for i in range(0, v.size, block)]
    out: F64 = np.concatenate(parts) if parts else np.empty(0)
    return out


def run_session(
    config: StageConfig,
    plan: Sequence[PlanItem],
    *,
    sample_rate_hz: float,
    axis: AxisName = "x",
    seed: int | None = None,
    slew_rate_v_per_s: float = 2000.0,
    voltage_limits_v: tuple[float, float] | None = None,
    rest_voltage_v: float = 0.0,
    pause_s: float = 0.0,
    lsb_um: float | None = None,
    block_samples: int = 1 << 16,
) -> SessionResult:
    """Run ``plan`` on one axis of the simulated stage (pure function: same inputs, same data).

    Parameters
    ----------
    config
        The true stage (effects included).
    plan
        Experiments, run in order.
    sample_rate_hz
        Sample rate (Hz).
    axis
        The driven axis (the other axes are independent and not simulated).
    seed
        Seed of the sensor noise (default ``config.seed``).
    slew_rate_v_per_s
        Rate of the unrecorded moves between experiments (V/s).
    voltage_limits_v
        ``(min, max)``: a plan leaving them raises :class:`~hil_sim.errors.SimSafetyError`.
    rest_voltage_v
        Voltage the stage rested at before the session.
    pause_s
        Unrecorded hold at each experiment's start voltage before it runs (s).
    lsb_um
        Sensor quantisation step (um), None for none.
    block_samples
        Samples per :meth:`Stage.step` call (the result does not depend on it beyond rounding).

    Returns
    -------
    SessionResult
        The recorded experiments.
    """
    _check_positive("sample_rate_hz", sample_rate_hz)
    _check_positive("slew_rate_v_per_s", slew_rate_v_per_s)
    if not (math.isfinite(pause_s) and pause_s >= 0.0):
        raise ConfigError(f"pause_s must be finite and >= 0, got {pause_s!r}")
    if block_samples < 1:
        raise ConfigError(f"block_samples must be >= 1, got {block_samples}")
    labels = [item.name() for item in plan]
    dup = sorted({lab for lab in labels if labels.count(lab) > 1})
    if dup:
        raise ConfigError(f"plan has repeated experiment label {dup[0]!r} (labels must be unique)")
    stage = Stage(config, axes=(axis,), seed=seed, rest_voltage_v=rest_voltage_v)
    dt = 1.0 / sample_rate_hz
    k = 0
    v_now = float(rest_voltage_v)
    out: list[ExperimentRecord] = []

    def check(v: F64, what: str) -> None:
        if voltage_limits_v is None or v.size == 0:
            return
        lo, hi = voltage_limits_v
        if v.min() < lo or v.max() > hi:
            raise SafetyError(
                f"{what}: voltage {v.min():g}..{v.max():g} V leaves the limits {lo:g}..{hi:g} V"
            )

    def record(label: str, kind: str, item_params: dict[str, Any], t: F64, v: F64, x: F64) -> None:
        out.append(
            ExperimentRecord(
                label=label,
                kind=kind,
                axis=axis,
                t_s=t,
                voltage_v=v,
                position_um=stage.sense(x, lsb_um),
                true_position_um=x,
                params=item_params,
            )
        )

    for item, label in zip(plan, labels, strict=True):
        start = item.start_voltage_v()
        wave, lead = item.waveform(sample_rate_hz)
        check(np.concatenate(([start], wave)), f"experiment {label!r}")
        moves = []
        if start != v_now:
            moves.append(_piecewise_linear([v_now, start], slew_rate_v_per_s, sample_rate_hz))
        if pause_s > 0.0:
            moves.append(np.full(round(pause_s * sample_rate_hz), start))
        for move in moves:
            _run(stage, move, dt, block_samples)
            k += move.size
        x = _run(stage, wave, dt, block_samples)
        t = (k + np.arange(1, wave.size + 1)) / sample_rate_hz
        k += wave.size
        v_now = float(wave[-1])
        params = item.params()
        if isinstance(item, Triangle) and item.record_settle and lead > 0:
            record(f"{label}_settle", "settle", params, t[:lead], wave[:lead], x[:lead])
        if lead < wave.size:
            record(label, item.kind, params, t[lead:], wave[lead:], x[lead:])
    return SessionResult(experiments=tuple(out), sample_rate_hz=sample_rate_hz, axis=axis, config=config)


def run_scanner_session(
    scanner: ScannerAxesLike,
    plan: Sequence[PlanItem],
    *,
    sample_rate_hz: float | None = None,
    axis: AxisName = "x",
    effects: Sequence[str] = (),
    **kwargs: Any,
) -> SessionResult:
    """:func:`run_session` with the stage, limits, slew rate and safe voltage of a scanner config.

    Parameters
    ----------
    scanner
        A scanner config with a ``simulation:`` section (e.g. ``configs/sim-stage.yaml``).
    plan
        Experiments.
    sample_rate_hz
        Default: the scanner's ``sample_rate_hz``.
    axis
        The driven axis.
    effects
        ``NAME=VALUE`` strings added to the stage (:meth:`StageConfig.with_effects`).
    **kwargs
        Passed on to :func:`run_session`.
    """
    if axis not in scanner.axes:
        raise ConfigError(f"scanner {scanner.name!r} has no axis {axis!r}")
    ax: AxisLimitsLike = scanner.axes[axis]
    stage = StageConfig.from_scanner(scanner).with_effects(*effects)
    kwargs.setdefault("voltage_limits_v", (ax.voltage_min_v, ax.voltage_max_v))
    kwargs.setdefault("slew_rate_v_per_s", ax.slew_rate_v_per_s)
    kwargs.setdefault("rest_voltage_v", ax.safe_voltage_v)
    return run_session(
        stage, plan, sample_rate_hz=sample_rate_hz or scanner.sample_rate_hz, axis=axis, **kwargs
    )


__all__ = [
    "ExperimentRecord",
    "Hold",
    "MinorLoops",
    "PlanItem",
    "Ramp",
    "SessionResult",
    "Sine",
    "Step",
    "Triangle",
    "Waypoints",
    "calibration_plan",
    "run_scanner_session",
    "run_session",
]
