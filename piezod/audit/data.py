"""The measured data of an audit: experiments concatenated, scans inferred, segments for held-out tests.

Every experiment is a contiguous block of the concatenated arrays. A *segment* is the unit
that owns nuisance parameters (a position offset, and for the ODE baseline the unknown
initial state) and the unit held out by cross-validation: one segment per experiment, or,
for a single long recording, ``blocks`` contiguous blocks in time (a blocked split).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from piezod.errors import RecordingError
from piezod.recording import Experiment
from piezod.scan_inference import ScanInfo

F64 = NDArray[np.float64]
I64 = NDArray[np.intp]

#: Fewest samples an experiment needs to enter an audit.
MIN_SAMPLES = 16
#: Relative jitter of the sample interval above which an experiment counts as non-uniformly sampled.
_UNIFORM_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class ExperimentInfo:
    """What the audit knows about one experiment.

    Attributes
    ----------
    label, path, first_line
        Identification (for reports and errors).
    kind
        Waveform kind inferred from the voltage (``triangle``, ``sine``, ``periodic``, ``ramp``,
        ``constant``, ``arbitrary``).
    triangle
        A periodic triangular scan with at least one complete loop (the thesis model applies).
    periodic
        Regular back-and-forth motion with at least one complete loop.
    frequency_hz
        Line frequency (nan when not periodic).
    v_min, v_max
        Turning voltages (or the extreme voltages).
    n_loops
        Complete loops.
    dt_s
        Median sample interval (s).
    uniform
        The sample interval is constant to 0.1 %.
    period_samples
        Samples per period (0 when not periodic or shorter than a period).
    t_start_s, t_end_s
        First and last sample time (session clock).
    """

    label: str
    path: str | None
    first_line: int | None
    kind: str
    triangle: bool
    periodic: bool
    frequency_hz: float
    v_min: float
    v_max: float
    n_loops: int
    dt_s: float
    uniform: bool
    period_samples: int
    t_start_s: float
    t_end_s: float

    @property
    def range_v(self) -> float:
        """Peak-to-peak voltage."""
        return self.v_max - self.v_min

    @property
    def offset_v(self) -> float:
        """Centre voltage."""
        return 0.5 * (self.v_max + self.v_min)

    @property
    def duration_s(self) -> float:
        """Duration of the experiment."""
        return self.t_end_s - self.t_start_s


@dataclass(frozen=True, eq=False)
class AuditData:
    """Experiments concatenated for the fits.

    Attributes
    ----------
    t_s, voltage_v, position_um, direction
        Per sample (direction +1 rising / -1 falling voltage, as float).
    starts
        First sample of every experiment.
    info
        Per experiment.
    fit_mask
        Samples that enter fits and residual statistics (False in a settling prefix).
    segment
        Segment index of every sample (0 ... n_segments - 1, ascending in sample order).
    segment_experiment
        Experiment of every segment.
    first_segment
        Per segment: it is the first segment of its experiment (owns the initial-state nuisance).
    blocked
        True when the segments are time blocks of one experiment (blocked split).
    """

    t_s: F64
    voltage_v: F64
    position_um: F64
    direction: F64
    starts: I64
    info: tuple[ExperimentInfo, ...]
    fit_mask: NDArray[np.bool_]
    segment: I64
    segment_experiment: I64
    first_segment: NDArray[np.bool_]
    blocked: bool

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t_s.size)

    @property
    def n_experiments(self) -> int:
        """Number of experiments."""
        return len(self.info)

    @property
    def n_segments(self) -> int:
        """Number of segments."""
        return int(self.segment_experiment.size)

    @property
    def counts(self) -> I64:
        """Samples per experiment."""
        out: I64 = np.diff(np.append(self.starts, self.n))
        return out

    @property
    def experiment(self) -> I64:
        """Experiment index of every sample."""
        out: I64 = np.repeat(np.arange(self.n_experiments), self.counts)
        return out

    def slice(self, i: int) -> slice:
        """Sample slice of experiment ``i``."""
        return slice(int(self.starts[i]), int(self.starts[i]) + int(self.counts[i]))

    @property
    def all_triangles(self) -> bool:
        """Every experiment is a periodic triangular scan."""
        return all(e.triangle for e in self.info)

    def per_experiment(self, name: str) -> F64:
        """An :class:`ExperimentInfo` attribute as an array over experiments."""
        return np.array([float(getattr(e, name)) for e in self.info])

    def per_sample(self, values: F64) -> F64:
        """Repeat per-experiment ``values`` over the samples."""
        out: F64 = np.repeat(values, self.counts)
        return out


def _settling_prefix(v: F64) -> int:
    """Samples until the voltage has travelled a quarter of its span (at most 5 % of the experiment)."""
    span = float(np.ptp(v))
    if span <= 0.0 or v.size < 2:
        return 0
    travel = np.cumsum(np.abs(np.diff(v)))
    k = int(np.searchsorted(travel, 0.25 * span)) + 1
    return min(k, int(0.05 * v.size))


def build(
    experiments: Sequence[Experiment],
    *,
    blocks: int = 1,
    settle: bool = False,
    scans: Sequence[ScanInfo] | None = None,
) -> AuditData:
    """Infer the scans and concatenate the experiments.

    Parameters
    ----------
    experiments
        The experiments of one axis.
    blocks
        Split a single experiment into this many time blocks (segments); ignored when there are
        several experiments.
    settle
        Exclude a settling prefix of every experiment from fits (used with the ODE baseline,
        whose start-up transients the steady models do not describe).
    scans
        The experiments' :meth:`~piezod.recording.Experiment.scan` results, when already known.

    Raises
    ------
    RecordingError
        An experiment too short to audit (names the file and line).
    """
    if not experiments:
        raise RecordingError("no experiments to audit")
    ts, vs, xs, ds, masks = [], [], [], [], []
    infos: list[ExperimentInfo] = []
    starts: list[int] = []
    n = 0
    for k, e in enumerate(experiments):
        if len(e) < MIN_SAMPLES:
            raise RecordingError(
                f"experiment {e.describe()} has {len(e)} samples; the audit needs at least {MIN_SAMPLES}",
                e.path,
                e.first_line,
            )
        info = e.scan() if scans is None else scans[k]
        t = np.asarray(e.t_s, dtype=np.float64)
        dts = np.diff(t)
        dt = float(np.median(dts))
        uniform = bool(np.all(np.abs(dts - dt) <= _UNIFORM_TOL * dt))
        f = float(info.frequency_hz)
        periodic = bool(info.is_periodic) and math.isfinite(f) and f > 0
        period = round(1.0 / (f * dt)) if periodic else 0
        if period > len(e):
            period = 0
        infos.append(
            ExperimentInfo(
                label=e.label,
                path=e.path,
                first_line=e.first_line,
                kind=info.kind,
                triangle=bool(info.is_scan),
                periodic=periodic,
                frequency_hz=f if periodic else math.nan,
                v_min=float(info.v_min),
                v_max=float(info.v_max),
                n_loops=int(info.n_loops),
                dt_s=dt,
                uniform=uniform,
                period_samples=int(period),
                t_start_s=float(t[0]),
                t_end_s=float(t[-1]),
            )
        )
        v = np.asarray(e.voltage_v, dtype=np.float64)
        mask = np.ones(v.size, dtype=bool)
        if settle:
            mask[: _settling_prefix(v)] = False
        starts.append(n)
        ts.append(t)
        vs.append(v)
        xs.append(np.asarray(e.position_um, dtype=np.float64))
        ds.append(np.asarray(info.direction, dtype=np.float64))
        masks.append(mask)
        n += v.size
    starts_arr = np.asarray(starts, dtype=np.intp)
    counts = np.diff(np.append(starts_arr, n))
    blocked = len(experiments) == 1 and blocks > 1
    if blocked:
        edges = np.linspace(0, n, blocks + 1).round().astype(np.intp)
        segment = np.searchsorted(edges, np.arange(n), side="right") - 1
        seg_exp = np.zeros(blocks, dtype=np.intp)
        first = np.zeros(blocks, dtype=bool)
        first[0] = True
    else:
        segment = np.repeat(np.arange(len(experiments)), counts).astype(np.intp)
        seg_exp = np.arange(len(experiments), dtype=np.intp)
        first = np.ones(len(experiments), dtype=bool)
    return AuditData(
        t_s=np.concatenate(ts),
        voltage_v=np.concatenate(vs),
        position_um=np.concatenate(xs),
        direction=np.concatenate(ds),
        starts=starts_arr,
        info=tuple(infos),
        fit_mask=np.concatenate(masks),
        segment=segment.astype(np.intp),
        segment_experiment=seg_exp,
        first_segment=first,
        blocked=blocked,
    )
