"""Synthetic measurement sessions from the thesis model, like a calibration frame.

A session is a sequence of experiments (triangular voltage scans of given range,
offset and line frequency). Each records ``n_loops`` loops after ``settle_loops``
loops that are run but not recorded (their time still passes, so ``t`` stays the
session clock). The position is

* ``model="loop"`` (default): the steady loop of (3.8) (:func:`thesis_loop`), i.e. the
  data the calibration model describes exactly, or
* ``model="ode"``: the rate-independent hysteresis ODE (2.21) integrated exactly
  through the whole session from a relaxed stage (:func:`hysteresis_step`), so that
  offset and range changes leave transients (chapter 5), plus the steady creep term
  ``(b_hat - b)(V - V_C)`` of (3.8) of each experiment;

plus a per-experiment position offset (sensor zero / drift between experiments) and
white Gaussian sensor noise. Everything here is pure and seeded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from piezod.errors import ModelError
from piezod.model.ode import hysteresis_step, relaxed_state
from piezod.model.params import ThesisParams
from piezod.model.thesis import effective_sensitivity, thesis_loop
from piezod.recording import Recording

#: Medium tube scanner, thesis table 3.3 (A3 = 0.872 from the table; the text says 0.681).
MEDIUM_TUBE = ThesisParams(
    alpha_per_v=3.23e-3, b_um_per_v=0.081, u_um_per_v=0.016, tau_s=2.666, a1=0.081, a2_per_v=2.78e-3, a3=0.872
)

#: Default calibration frame: voltage ranges (V peak-to-peak) and line frequencies (Hz).
DEFAULT_RANGES_V: tuple[float, ...] = (80.0, 160.0, 240.0, 320.0, 400.0)
DEFAULT_FREQUENCIES_HZ: tuple[float, ...] = (0.02, 0.1, 0.3, 1.0, 2.0, 5.0)


@dataclass(frozen=True, slots=True)
class PlannedExperiment:
    """One experiment of a session plan.

    Attributes
    ----------
    label
        Experiment label (written to the ``experiment`` column).
    v_min, v_max
        Turning voltages (V).
    frequency_hz
        Line (trace + retrace) frequency (Hz).
    n_loops
        Recorded loops.
    settle_loops
        Loops run before recording starts.
    """

    label: str
    v_min: float
    v_max: float
    frequency_hz: float
    n_loops: int = 1
    settle_loops: int = 1

    def __post_init__(self) -> None:
        if not self.v_max > self.v_min:
            raise ModelError(f"{self.label}: v_max must exceed v_min, got [{self.v_min}, {self.v_max}]")
        if not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise ModelError(f"{self.label}: frequency must be > 0 Hz, got {self.frequency_hz}")
        if self.n_loops < 1 or self.settle_loops < 0:
            raise ModelError(f"{self.label}: need n_loops >= 1 and settle_loops >= 0")

    @property
    def range_v(self) -> float:
        """Peak-to-peak voltage range."""
        return self.v_max - self.v_min

    @property
    def offset_v(self) -> float:
        """Centre voltage."""
        return 0.5 * (self.v_max + self.v_min)


def calibration_plan(
    ranges_v: Sequence[float] = DEFAULT_RANGES_V,
    frequencies_hz: Sequence[float] = DEFAULT_FREQUENCIES_HZ,
    offsets_v: Sequence[float] = (0.0,),
    *,
    n_loops: int = 1,
    settle_loops: int = 1,
) -> tuple[PlannedExperiment, ...]:
    """The full grid ranges x frequencies x offsets, ranges outermost.

    Labels read ``r{range}_f{frequency}`` (plus ``_o{offset}`` when several offsets).
    """
    out: list[PlannedExperiment] = []
    for r in ranges_v:
        for o in offsets_v:
            for f in frequencies_hz:
                label = f"r{r:g}_f{f:g}" + (f"_o{o:g}" if len(offsets_v) > 1 else "")
                out.append(PlannedExperiment(label, o - r / 2, o + r / 2, f, n_loops, settle_loops))
    return tuple(out)


def random_plan(
    rng: np.random.Generator | int,
    n_experiments: int = 35,
    *,
    range_v: tuple[float, float] = (80.0, 400.0),
    frequency_hz: tuple[float, float] = (0.02, 5.0),
    offset_v: tuple[float, float] = (0.0, 0.0),
    n_loops: int = 1,
    settle_loops: int = 1,
) -> tuple[PlannedExperiment, ...]:
    """A stratified random frame: ranges uniform, frequencies log-uniform, offsets uniform.

    Ranges and frequencies are drawn from ``n_experiments`` equal strata each (Latin
    hypercube), so that every frame spans both intervals.
    """
    g = np.random.default_rng(rng)
    n = n_experiments
    strata = (np.arange(n) + g.random((2, n))) / n
    ranges = range_v[0] + (range_v[1] - range_v[0]) * g.permutation(strata[0])
    lf = np.log(frequency_hz)
    freqs = np.exp(lf[0] + (lf[1] - lf[0]) * g.permutation(strata[1]))
    offs = g.uniform(offset_v[0], offset_v[1], n) if offset_v[1] > offset_v[0] else np.full(n, offset_v[0])
    return tuple(
        PlannedExperiment(
            f"e{i:02d}_r{r:.0f}_f{f:.3g}", o - r / 2, o + r / 2, float(f), n_loops, settle_loops
        )
        for i, (r, f, o) in enumerate(zip(ranges.tolist(), freqs.tolist(), offs.tolist(), strict=True))
    )


def random_params(
    rng: np.random.Generator | int, around: ThesisParams = MEDIUM_TUBE, spread: float = 0.25
) -> ThesisParams:
    """Plausible random parameters: each of ``around``'s multiplied by ``exp(U(-spread, spread))``.

    ``u`` is kept below ``0.6 b`` and ``A1`` inside (0, 0.5) so that the result stays physical.
    """
    g = np.random.default_rng(rng)
    f = np.exp(g.uniform(-spread, spread, 7))
    b = around.b_um_per_v * f[1]
    return ThesisParams(
        alpha_per_v=around.alpha_per_v * f[0],
        b_um_per_v=b,
        u_um_per_v=min(around.u_um_per_v * f[2], 0.6 * b),
        tau_s=around.tau_s * f[3],
        a1=min(around.a1 * f[4], 0.5),
        a2_per_v=around.a2_per_v * f[5],
        a3=around.a3 * f[6],
    )


@dataclass(frozen=True, eq=False)
class SynthSession:
    """A synthetic session and the truth behind it.

    Attributes
    ----------
    recording
        The data (columns ``t, voltage, position, axis, experiment``), ready for
        :func:`piezod.recording.write_recording`.
    params
        The true model parameters.
    plan
        The experiments, in recording order.
    position_offsets_um
        The true per-experiment position offset added to the model.
    noise_um
        Standard deviation of the white sensor noise.
    model
        ``"loop"`` or ``"ode"`` (see the module docstring).
    """

    recording: Recording
    params: ThesisParams
    plan: tuple[PlannedExperiment, ...]
    position_offsets_um: NDArray[np.float64]
    noise_um: float
    model: str


def triangle_voltage(exp: PlannedExperiment, samples_per_loop: int, loops: int) -> NDArray[np.float64]:
    """``loops`` triangular loops starting at ``v_min`` rising, plus the closing sample at ``v_min``."""
    k = np.arange(loops * samples_per_loop + 1)
    phase = (k % samples_per_loop) / samples_per_loop
    tri = np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
    return np.asarray(exp.v_min + exp.range_v * tri, dtype=np.float64)


def synth_session(
    params: ThesisParams,
    plan: Sequence[PlannedExperiment],
    *,
    samples_per_loop: int = 2048,
    noise_um: float = 0.005,
    offset_spread_um: float = 2.0,
    position_offsets_um: Sequence[float] | None = None,
    seed: np.random.Generator | int = 0,
    axis: str = "x",
    model: Literal["loop", "ode"] = "loop",
    record_settling: bool = False,
    gap_s: float = 0.0,
    t0_s: float = 0.0,
) -> SynthSession:
    """Generate a measurement session from the thesis model.

    Parameters
    ----------
    params
        True model parameters.
    plan
        The experiments (:func:`calibration_plan`, :func:`random_plan`).
    samples_per_loop
        Samples per loop (even); the sample rate of each experiment is
        ``samples_per_loop * frequency``.
    noise_um
        White Gaussian sensor noise (um, standard deviation).
    offset_spread_um
        Per-experiment position offsets are uniform in +-this (ignored when
        ``position_offsets_um`` is given).
    position_offsets_um
        Explicit per-experiment offsets.
    seed
        Random generator or seed.
    axis
        Axis name written to the ``axis`` column.
    model
        ``"loop"`` (steady (3.8)) or ``"ode"`` (hysteresis ODE through the session).
    record_settling
        Also record the settling loops (as part of the experiment).
    gap_s
        Pause between experiments (s; the voltage jumps at its end).
    t0_s
        Session time of the first sample.

    Returns
    -------
    SynthSession
        The recording and the truth.
    """
    if samples_per_loop < 8 or samples_per_loop % 2:
        raise ModelError(f"samples_per_loop must be even and >= 8, got {samples_per_loop}")
    g = np.random.default_rng(seed)
    plan = tuple(plan)
    if position_offsets_um is None:
        offsets = g.uniform(-offset_spread_um, offset_spread_um, len(plan))
    else:
        offsets = np.asarray(position_offsets_um, dtype=np.float64)
        if offsets.shape != (len(plan),):
            raise ModelError(f"need {len(plan)} position offsets, got {offsets.shape}")
    ts: list[NDArray[np.float64]] = []
    vs: list[NDArray[np.float64]] = []
    xs: list[NDArray[np.float64]] = []
    labels: list[NDArray[np.str_]] = []
    t_next = t0_s
    state = relaxed_state(params.hysteresis, 0.0)
    for exp, off in zip(plan, offsets.tolist(), strict=True):
        loops = exp.settle_loops + exp.n_loops
        v = triangle_voltage(exp, samples_per_loop, loops)
        dt = 1.0 / (exp.frequency_hz * samples_per_loop)
        t = np.asarray(t_next + dt * np.arange(v.size), dtype=np.float64)
        if model == "ode":
            hyst, state = hysteresis_step(params.hysteresis, v, state)
            b_hat = effective_sensitivity(params, exp.frequency_hz, exp.v_min, exp.v_max)
            x = hyst + (b_hat - params.b_um_per_v) * (v - exp.offset_v)
        elif model == "loop":
            direction = np.where((np.arange(v.size) % samples_per_loop) < samples_per_loop // 2, 1, -1)
            x = thesis_loop(params, v, direction, exp.v_min, exp.v_max, exp.frequency_hz)
        else:
            raise ModelError(f"unknown synth model {model!r}")
        start = 0 if record_settling else exp.settle_loops * samples_per_loop
        ts.append(t[start:])
        vs.append(v[start:])
        xs.append(np.asarray(x[start:] + off + g.normal(0.0, noise_um, v.size - start), dtype=np.float64))
        labels.append(np.full(v.size - start, exp.label))
        t_next = float(t[-1]) + dt + gap_s
    n = sum(a.size for a in ts)
    rec = Recording(
        t_s=np.concatenate(ts),
        voltage_v=np.concatenate(vs),
        position_um=np.concatenate(xs),
        axis=np.full(n, axis),
        experiment=np.concatenate(labels),
        metadata={"source": f"piezod.synth ({model})", "noise_um": f"{noise_um:g}"},
    )
    return SynthSession(
        recording=rec,
        params=params,
        plan=plan,
        position_offsets_um=offsets,
        noise_um=noise_um,
        model=model,
    )
