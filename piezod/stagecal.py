"""Calibration on the stage: the thesis's "calibration button", and its verification.

``piezod calibrate (--sim | --port URL) --config F --out F.yaml`` runs a *calibration frame*
(thesis section 3.1, tables 3.1-3.2) on the stage through the daemon's engine: uncorrected
triangular voltage scans over a grid of voltage ranges x line rates (x offsets), each with
settling loops first (not recorded) and then the recorded loops. It keeps the recording, fits
the model(s) to it, writes the scanner YAML, and verifies: it scans online-corrected inside the
frame and outside it (10x slower, 10x faster, offsets beyond it) and tabulates nonlinearity and
length error per range, rate and offset for each model, like thesis tables 4.3 / 4.4.
"""

from __future__ import annotations

import concurrent.futures
import math
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from piezod import calibrate_any
from piezod.calibrate import calibrate, calibrated_config, result_json
from piezod.config import AxisName, FamilyModelConfig, ScannerConfig
from piezod.errors import CalibrationError, ModelError, PiezodError
from piezod.fitstats import excess_rms, lowers
from piezod.linearity import linearity, noise_pct
from piezod.model.aftereffect import AfterEffect
from piezod.model.boucwen import BoucWenParams
from piezod.model.domainwall import DomainWallParams
from piezod.model.sensor import SensorPath
from piezod.model.thesis import scan_range_um
from piezod.readback import at_full_scale
from piezod.recording import Experiment, Recording, read_experiments, read_recording, split_experiments
from piezod.service.engine import Engine, Segment
from piezod.service.schemas import ScanRequest

if TYPE_CHECKING:
    from piezod.calibrate_dynamic import DynamicCalibrationData
    from piezod.extensions import Adoption
    from piezod.lag_placement import PlacementProgram

Progress = Callable[[str, float], None]


@dataclass(frozen=True, slots=True)
class FrameScan:
    """One experiment of the calibration frame: an uncorrected triangular voltage scan."""

    range_v: float
    frequency_hz: float
    offset_v: float = 0.0
    settle_loops: int = 2
    loops: int = 3

    @property
    def label(self) -> str:
        """Experiment label in the recording."""
        return f"R{self.range_v:g}V_f{self.frequency_hz:g}Hz_o{self.offset_v:+g}V"

    @property
    def duration_s(self) -> float:
        """Time on the stage (s)."""
        return (self.settle_loops + self.loops) / self.frequency_hz

    def segments(self, rate_hz: float) -> list[Segment]:
        """Settling loops (unrecorded) then recorded loops, each starting at the lower turning point."""
        n = max(8, round(rate_hz / self.frequency_hz))
        phase = np.arange(n) / n
        tri = np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
        one = self.offset_v + (tri - 0.5) * self.range_v
        out = []
        if self.settle_loops:
            out.append(Segment(np.tile(one, self.settle_loops), self.label, record=False))
        out.append(Segment(np.concatenate([np.tile(one, self.loops), one[:1]]), self.label, record=True))
        return out


@dataclass(frozen=True, slots=True)
class Frame:
    """A calibration frame on one axis."""

    axis: AxisName
    scans: tuple[FrameScan, ...]

    @property
    def duration_s(self) -> float:
        """Total time on the stage (s), without the ramps between scans."""
        return sum(s.duration_s for s in self.scans)

    @property
    def frequencies_hz(self) -> tuple[float, float]:
        """Lowest and highest line rate."""
        f = [s.frequency_hz for s in self.scans]
        return min(f), max(f)

    @property
    def ranges_v(self) -> tuple[float, float]:
        """Smallest and largest voltage range."""
        r = [s.range_v for s in self.scans]
        return min(r), max(r)

    @property
    def offsets_v(self) -> tuple[float, float]:
        """Lowest and highest offset."""
        o = [s.offset_v for s in self.scans]
        return min(o), max(o)


def without_extensions(config: ScannerConfig, axis: AxisName) -> tuple[ScannerConfig, list[str]]:
    """``config`` without ``axis``'s extensions, and their names: a calibration measures them again.

    They were measured with another model, on another day. The frame is uncorrected, so it does not
    need them, and its audit finds them again. A part kept from before would sit beside a model
    fitted without it.
    """
    ax = config.axes[axis]
    names = [str(k) for k in (ax.extensions or {})]
    if not names:
        return config, []
    return config.with_axis(axis, extensions=None), names


def with_tracking_bound(config: ScannerConfig, frame: Frame) -> ScannerConfig:
    """``config`` with the frame axis's ``tracking_min_line_s`` set to the frame's shortest line.

    The sensitivity tracker (:mod:`piezod.service.tracking`) then learns only from lines the
    calibration measured the rate dependence for; a line of a triangle at ``f`` lasts ``1 / (2 f)``.
    """
    return calibrate_any.with_tracking_bound(config, frame.axis, 0.5 / frame.frequencies_hz[1])


def default_frame(config: ScannerConfig, axis: AxisName = "x", *, reduced: bool = False) -> Frame:
    """A frame like thesis table 3.1 scaled to the axis: ranges 1/3..full x 0.2-2 Hz, +- offsets.

    ``reduced`` is a quick frame (2 ranges x 3 rates, one offset) for tests and demos.
    """
    ax = config.axes[axis]
    span = ax.voltage_max_v - ax.voltage_min_v
    centre = 0.5 * (ax.voltage_max_v + ax.voltage_min_v)
    full = 0.98 * span
    if reduced:
        ranges = [0.45 * full, 0.9 * full]
        freqs = [0.5, 1.0, 2.0]
        scans = [FrameScan(r, f, centre, settle_loops=1, loops=2) for r in ranges for f in freqs]
    else:
        ranges = list(np.linspace(full / 3.0, full, 5))
        freqs = [0.2, 0.4, 0.7, 1.0, 1.4, 2.0]
        scans = [FrameScan(r, f, centre) for r in ranges for f in freqs]
        off = 0.15 * span
        scans += [FrameScan(full / 2.0, 1.0, centre + o) for o in (-off, off)]
        scans += [FrameScan(full / 3.0, 0.4, centre + o) for o in (-off, off)]
    for s in scans:
        needed = 2.0 * s.range_v * s.frequency_hz
        if needed > ax.slew_rate_v_per_s:
            raise CalibrationError(
                f"frame scan {s.label} needs {needed:g} V/s, "
                f"above the slew limit {ax.slew_rate_v_per_s:g} V/s"
            )
    return Frame(axis, tuple(round_frame(s) for s in scans))


def round_frame(scan: FrameScan) -> FrameScan:
    """Round the ranges / offsets to 0.1 V (readable labels)."""
    return FrameScan(
        round(scan.range_v, 1), scan.frequency_hz, round(scan.offset_v, 1), scan.settle_loops, scan.loops
    )


#: Highest rate the calibration frame is recorded at (S/s). On a faster sample clock the frame is
#: played at the full rate and every n-th sample recorded: the analysis needs no more (its fits
#: decimate further, lags are resolved to a fraction of a sample), and a full frame at 100 kS/s
#: would be 31 M rows (1.6 GB of CSV, several GB in memory on the analysis worker).
FRAME_RECORD_RATE_HZ = 20000.0


def frame_record_every(rate_hz: float) -> int:
    """Every how many samples of a ``rate_hz`` clock the frame is recorded (1 up to
    :data:`FRAME_RECORD_RATE_HZ`)."""
    return max(1, math.ceil(rate_hz / FRAME_RECORD_RATE_HZ - 1e-9))


def run_frame(
    engine: Engine,
    frame: Frame,
    path: Path,
    *,
    progress: Progress | None = None,
    timeout_s: float | None = None,
) -> Path:
    """Play the frame on the stage, recorded to ``path`` (one experiment per scan)."""
    segments = [seg for scan in frame.scans for seg in scan.segments(engine.rate_hz)]
    meta = {
        "content": "calibration frame (uncorrected triangles)",
        "axis": frame.axis,
        "experiments": len(frame.scans),
    }
    return _play_program(
        engine, frame.axis, segments, path, meta, frame.duration_s, "calibration frame", progress, timeout_s
    )


def run_placement(
    engine: Engine,
    config: ScannerConfig,
    axis: AxisName,
    path: Path,
    frame: Frame | None = None,
    *,
    progress: Progress | None = None,
    timeout_s: float | None = None,
) -> Path:
    """Play the lag placement experiment (:func:`piezod.lag_placement.placement_program`) on the
    stage, recorded to ``path`` (experiment :data:`piezod.lag_placement.PLACEMENT_LABEL`).

    With the ``frame``, its last :data:`FRAME_END_SCANS` scans are played again after it (experiment
    :data:`FRAME_END_LABEL`):
    the stage is then left as the frame left it, on the same branch at the same voltage, and the
    verification starts from the end of this recording (:func:`frame_end`) as it would have from
    the frame's.
    """
    segments, total = placement_segments(config, axis, engine.rate_hz, frame)
    meta = {
        "content": "lag placement (uncorrected ramps with short spikes), then the frame's last scans",
        "axis": axis,
        "experiments": len({seg.label for seg in segments}),
    }
    what = "lag placement experiment"
    return _play_program(engine, axis, segments, path, meta, total, what, progress, timeout_s)


def placement_segments(
    config: ScannerConfig, axis: AxisName, rate_hz: float, frame: Frame | None = None
) -> tuple[list[Segment], float]:
    """The segments :func:`run_placement` plays (the experiment, then the ``frame``'s last
    :data:`FRAME_END_SCANS` scans) and their time on the stage (s), without the ramps between them."""
    from piezod.lag_placement import PLACEMENT_LABEL, program_for

    program = program_for(config, axis, rate_hz)
    segments = [Segment(program.volts, PLACEMENT_LABEL, record=True)]
    total = program.duration_s
    for last in frame.scans[-FRAME_END_SCANS:] if frame is not None else ():
        segments += [Segment(seg.volts, FRAME_END_LABEL, seg.record) for seg in last.segments(rate_hz)]
        total += last.duration_s
    return segments, total


#: Label of the frame's last scans played again after the lag placement experiment.
FRAME_END_LABEL = "frame-end"
#: How many of the frame's last scans are played again after it (the default frame's four offset
#: scans, 35 s): the creep the experiment's full-range loops leave then relaxes as the frame's did.
FRAME_END_SCANS = 4


def _play_program(
    engine: Engine,
    axis: AxisName,
    segments: list[Segment],
    path: Path,
    meta: dict[str, Any],
    total_s: float,
    what: str,
    progress: Progress | None,
    timeout_s: float | None,
) -> Path:
    engine.start_program(axis, segments, path, meta, record_every=frame_record_every(engine.rate_hz))
    t0 = time.monotonic()
    deadline = None if timeout_s is None else t0 + timeout_s
    while engine.status().state == "scanning":
        if progress is not None:
            progress(what, min(time.monotonic() - t0, total_s))
        if deadline is not None and time.monotonic() > deadline:
            engine.stop()
            raise CalibrationError(f"the {what} did not finish within {timeout_s:g} s")
        time.sleep(0.1)
    state = engine.wait_idle(10.0)
    engine.wait_recorded()
    if state != "idle":
        faults = "; ".join(f"{f.code}: {f.message}" for f in engine.status().faults[-3:])
        raise CalibrationError(f"the {what} ended in state {state}: {faults}")
    return path


def readback_clipped(experiments: Sequence[Experiment], full_scale_um: float) -> dict[str, int]:
    """Samples per experiment whose readback sits at the sensor's full scale (``+-full_scale_um``).

    Such a sample is the ADC's end code, not a position: the stage moved beyond the sensor's range
    and its true position is unknown. Experiments without one are left out of the result.
    """
    out: dict[str, int] = {}
    for e in experiments:
        n = at_full_scale(e.position_um, full_scale_um)
        if n:
            out[e.label] = out.get(e.label, 0) + n
    return out


def frame_in_sensor_range(
    frame_path: Path, frame: Frame, full_scale_um: float, out_path: Path
) -> tuple[Path, Frame, dict[str, int]]:
    """The recorded frame without the scans whose readback reached the sensor's full scale.

    Returns the recording the fits use (``frame_path`` itself when nothing clipped, else
    ``out_path``: the same file without those scans' rows; the recording as made is kept), the
    frame of the scans kept (the verification is placed within it) and the clipped sample count
    per scan left out.

    Raises
    ------
    CalibrationError
        Fewer than two ranges of the frame read within the sensor's range.
    """
    rec = read_recording(frame_path)
    clipped = readback_clipped(split_experiments(rec), full_scale_um)
    if not clipped:
        return frame_path, frame, {}
    kept = tuple(s for s in frame.scans if s.label not in clipped)
    fix = (
        f"set axes.{frame.axis}.sensor_full_scale_um to the sensor's range, or lower "
        f"axes.{frame.axis}.voltage_max_v / raise voltage_min_v"
    )
    if len({s.range_v for s in kept}) < 2:
        raise CalibrationError(
            f"{frame_path}: the readback reached the sensor's full scale (+-{full_scale_um:g} um) in "
            f"{len(clipped)} of {len(frame.scans)} scans of the frame: too few left to fit; {fix}"
        )
    if rec.experiment is None:
        raise CalibrationError(f"{frame_path}: the frame recording has no experiment column")
    rows = ~np.isin(rec.experiment, list(clipped))

    def cut(col: NDArray[Any] | None) -> NDArray[Any] | None:
        return None if col is None else col[rows]

    from piezod.recording_writer import write_recording

    note = f"{frame_path.name} without {len(clipped)} scans whose readback reached the sensor's full scale"
    write_recording(
        out_path,
        Recording(
            t_s=rec.t_s[rows],
            voltage_v=rec.voltage_v[rows],
            position_um=rec.position_um[rows],
            target_um=cut(rec.target_um),
            axis=cut(rec.axis),
            experiment=rec.experiment[rows],
            metadata=rec.metadata,
            z_voltage_v=cut(rec.z_voltage_v),
        ),
        metadata={
            "content": f"calibration frame within the sensor's range ({note})",
            "experiments": len(kept),
        },
    )
    return out_path, Frame(frame.axis, kept), clipped


@dataclass(frozen=True, slots=True)
class VerifyPoint:
    """One verification scan."""

    range_um: float
    frequency_hz: float
    offset_um: float
    inside_frame: bool
    why: str
    #: How :func:`check_points` moved or shrank the point (empty: placed as planned).
    note: str = ""


#: Share of the voltage span the checked verification scans keep from the limits.
CHECK_MARGIN = 0.03

#: Samples at the end of the frame whose readback is averaged for the position the run starts from.
FRAME_END_SAMPLES = 50


def frame_end(rec: Recording, axis: AxisName = "x") -> tuple[float, float]:
    """Where the calibration frame left the stage: the last voltage of ``axis`` and its measured
    position (the mean readback of the last :data:`FRAME_END_SAMPLES` samples: the sensor noise
    averaged).

    A fitted law's positions are defined along the histories it was fitted on, not absolutely
    (its rest curve is not identified), so the run adopts the new model at this voltage and
    measured position (:meth:`piezod.service.engine.Engine.set_axis_model`) and the verification
    is placed and checked from there (:func:`verification_points`, :func:`check_points`): the
    scan centres are the sensor's coordinates.

    Raises
    ------
    CalibrationError
        The recording has no finite readback of ``axis``.
    """
    of_axis = np.ones(len(rec.t_s), dtype=bool) if rec.axis is None else rec.axis == axis
    rows = np.flatnonzero(of_axis & np.isfinite(rec.position_um) & np.isfinite(rec.voltage_v))
    if rows.size == 0:
        where = rec.path or "the frame"
        raise CalibrationError(f"{where}: no readback of axis {axis} to start the verification from")
    last = rows[-FRAME_END_SAMPLES:]
    return float(rec.voltage_v[rows[-1]]), float(np.mean(rec.position_um[last]))


def check_points(
    config: ScannerConfig,
    points: Sequence[VerifyPoint],
    *,
    axis: AxisName = "x",
    lines: int = 4,
    start_v: float | None = None,
    start_um: float | None = None,
) -> list[VerifyPoint]:
    """Check every verification point with the verified model's own inverse over the whole scan.

    The points are played in order as :func:`verify` plays them (one warm-up scan at the first
    point, then each point: the move to its start, the settling lines and every line at its line
    rate, the model's creep and loop carried from one scan to the next), rendered by the engine's
    own scan job on copies of an axis driver of ``config``'s model
    (:func:`piezod.service.shadow.render_whole_scan`). A point that would clamp a sample to the
    voltage limits (or that the scan planner refuses) is moved towards the centre (an offset
    point: 10 % steps, never inside the frame) or shrunk (its range, 10 % steps), and says so in
    :attr:`VerifyPoint.note`; one that cannot be placed keeps its setting with a note saying it
    clamps (its figures are then not the model's). The check starts where the run starts: the
    model adopted at ``start_v`` and the measured ``start_um`` (:func:`frame_end`: the model is
    switched in from the stage's voltage and sensor position), or, without ``start_um``, resting
    at ``start_v`` (default: the axis's safe voltage). The scans are placed :data:`CHECK_MARGIN`
    of the voltage span inside the limits (never past the safe voltage), so a point the check
    placed is not refused or clamped for a state it could not know exactly.
    """
    import copy
    import dataclasses

    from piezod.errors import RangeUnreachableError, SafetyError
    from piezod.service.axes import AxisDriver, plan_axes
    from piezod.service.shadow import ShadowEngine, render_whole_scan
    from piezod.trajectory import RasterTrajectory

    ax = config.axes[axis]
    start = None if start_um is None else (ax.safe_voltage_v if start_v is None else start_v, start_um)
    home = _home_um(config, axis, 0.5 * (ax.voltage_max_v + ax.voltage_min_v), start)
    margin = CHECK_MARGIN * (ax.voltage_max_v - ax.voltage_min_v)
    ax = ax.model_copy(
        update={
            "voltage_min_v": min(ax.voltage_min_v + margin, ax.safe_voltage_v),
            "voltage_max_v": max(ax.voltage_max_v - margin, ax.safe_voltage_v),
        }
    )
    rate = float(config.sample_rate_hz)
    driver = AxisDriver(axis, ax, rate)
    if start is not None:
        driver.adopt(*start)
    else:
        driver.reset(ax.safe_voltage_v if start_v is None else start_v)
    drivers: dict[str, AxisDriver] = {axis: driver}
    block = 4096

    def clamps(pt: VerifyPoint, n_lines: int) -> tuple[int, dict[str, AxisDriver]]:
        trial = copy.deepcopy(drivers)
        req = ScanRequest(
            range_um=pt.range_um,
            line_rate_hz=pt.frequency_hz,
            lines=n_lines,
            slow_range_um=0.0,
            offset_x_um=pt.offset_um,
            record=False,
        )
        traj = RasterTrajectory.from_request(req, rate)
        try:
            plans = plan_axes(trial, traj)
        except (RangeUnreachableError, SafetyError):
            return -1, trial
        shadow = ShadowEngine(None, drivers=trial, rate_hz=rate)
        bad = render_whole_scan(shadow, req, traj, plans, block)[axis]
        return bad, shadow.drivers

    out: list[VerifyPoint] = []
    for k, pt in enumerate([*points[:1], *points]):
        warm = k == 0
        n_lines = 4 if warm else (1 if pt.frequency_hz < 0.1 else lines)
        cand, notes = pt, []
        for _ in range(40):
            bad, after = clamps(cand, n_lines)
            if bad == 0:
                break
            what = "refused by the scan planner" if bad < 0 else f"{bad} samples clamped"
            off, off0 = cand.offset_um - home, pt.offset_um - home
            if round(off, 2) != 0.0 and abs(off) * 0.9 >= abs(off0) * 0.5:
                nxt = dataclasses.replace(cand, offset_um=round(home + off * 0.9, 2))
                notes.append(f"offset {cand.offset_um:+.2f} um: {what}")
            else:
                nxt = dataclasses.replace(cand, range_um=round(cand.range_um * 0.9, 2))
                notes.append(f"range {cand.range_um:g} um: {what}")
            cand = nxt
        else:
            bad = -2
        if bad == 0:
            drivers = after
        if warm:
            continue
        note = ""
        if bad != 0:
            note = (
                f"clamps with the verified model even when moved/shrunk ({notes[-1]}): "
                "its figures are not the model's"
            )
            cand = pt
        elif notes:
            note = (
                f"moved/shrunk by the check with the verified model: was range {pt.range_um:g} um, offset "
                f"{pt.offset_um:+.2f} um ({notes[0]})"
            )
        out.append(dataclasses.replace(cand, note=note))
    return out


def verification_points(
    config: ScannerConfig,
    frame: Frame,
    *,
    reduced: bool = False,
    axis: AxisName = "x",
    start: tuple[float, float] | None = None,
) -> list[VerifyPoint]:
    """Scans inside the frame and outside it (10x slower, 10x faster, offsets beyond).

    Scan centres are positions: with ``start`` (the voltage and the measured position the run
    starts from, :func:`frame_end`) they are the verified model's, adopted there and ramped to
    the frame's centre voltage (the sensor's coordinates, as the daemon's driver has them once
    the model is switched in); without it, ramped from rest at 0 V.
    """
    ax = config.axes[axis]
    p = ax.thesis.params()
    f_lo, f_hi = frame.frequencies_hz
    r_lo, r_hi = frame.ranges_v
    o_lo, o_hi = frame.offsets_v
    centre = 0.5 * (ax.voltage_max_v + ax.voltage_min_v)

    def um(range_v: float, f: float) -> float:
        return round(float(scan_range_um(p, f, 0.5 * range_v)), 1)

    f_mid = float(np.sqrt(f_lo * f_hi))
    b = p.b_um_per_v
    # Scan centres are positions, and position 0 is where the stage rests at 0 V: on a unipolar
    # stage (-30 ... +150 V) the frame's centre lies elsewhere, and a scan centred on 0 clamps.
    home = _home_um(config, axis, centre, start)
    pts = [
        VerifyPoint(um(r_lo * 1.1, f_mid), round(f_mid, 2), home, True, "inside: small range"),
        VerifyPoint(um(0.5 * (r_lo + r_hi), f_mid), round(f_mid, 2), home, True, "inside: mid range"),
        VerifyPoint(um(r_hi * 0.92, f_hi), f_hi, home, True, "inside: large range, fastest rate"),
    ]
    if reduced:
        return pts
    pts += [
        VerifyPoint(um(r_lo * 1.1, f_lo), f_lo, home, True, "inside: slowest rate"),
        VerifyPoint(um(0.5 * (r_lo + r_hi), f_lo / 10.0), round(f_lo / 10.0, 4), home, False, "10x slower"),
    ]
    # 10x faster: as large as the slew limit allows.
    f_fast = 10.0 * f_hi
    r_fast = min(0.5 * (r_lo + r_hi), 0.8 * ax.slew_rate_v_per_s / (2.0 * f_fast) / 2.0)
    pts.append(VerifyPoint(um(r_fast, f_fast), f_fast, home, False, "10x faster"))
    # Offsets beyond the frame's: half-range scans pushed out to 1.8x the largest offset.
    frame_off = max(abs(o_hi - centre), abs(o_lo - centre), 0.1 * (ax.voltage_max_v - ax.voltage_min_v))
    off_v = 1.8 * frame_off
    r_off = min(r_lo, 2.0 * (0.5 * (ax.voltage_max_v - ax.voltage_min_v) - off_v) * 0.9)
    if r_off > 0:
        for sign in (-1.0, 1.0):
            off_um, at_v = _offset_um(
                config, axis, centre, sign * off_v, um(r_off, 1.0), b, 1.2 * frame_off, start
            )
            pts.append(VerifyPoint(um(r_off, 1.0), 1.0, off_um, False, f"offset {at_v:+.0f} V beyond frame"))
    return pts


def _home_um(
    config: ScannerConfig, axis: AxisName, centre_v: float, start: tuple[float, float] | None = None
) -> float:
    """Where the model stands at the frame's centre voltage (um): ramped from ``start`` (voltage,
    measured position), or from rest at 0 V (0 if symmetric)."""
    from piezod.service.axes import axis_model

    if centre_v == 0.0 and start is None:
        return 0.0
    model = axis_model(config.axes[axis])
    return round(_ramped_um(model, centre_v, float(config.sample_rate_hz), start=start), 2)


def _ramped_um(
    model: Any, to_v: float, rate_hz: float, samples: int = 2000, start: tuple[float, float] | None = None
) -> float:
    """The model's position after a straight ramp to ``to_v``: from rest at 0 V, relative to its
    rest at 0 V; or, with ``start``, from the model adopted at that voltage and measured position
    (absolute: the measurement's coordinates).

    The fitted laws are identified along the histories of the calibration frame, which starts
    with the stage resting at its safe voltage and ramping to the first scan; a state "rested at
    ``V`` for ever" is one no frame visits, and a law whose density depends on the relay centre
    can put it far off (on a unipolar stack fitted by the generalised play law, twice the
    stage's position at its centre voltage).
    """
    if start is None:
        from_v, here = 0.0, model.rest(0.0)
        origin = float(model.position(here))
    else:
        from_v, here, origin = float(start[0]), model.adopt(float(start[0]), float(start[1])), 0.0
    volts = np.linspace(from_v, float(to_v), samples + 1)[1:]
    _, after = model.forward(volts, 1.0 / rate_hz, here)
    return float(model.position(after)) - origin


def _offset_um(
    config: ScannerConfig,
    axis: AxisName,
    centre_v: float,
    off_v: float,
    range_um: float,
    b: float,
    least_v: float,
    start: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """The centre (um) of a scan ``off_v`` from the voltage centre, and that offset (V).

    The offset is a *voltage*: the axis's own model (the one being verified) says where the stage
    stands there when ramped from rest at 0 V or from ``start`` (:func:`_ramped_um`) -- the
    thesis model's ``b`` says it wrongly for a loop much wider or narrower than the thesis law's
    (its centre then needs more voltage than the amplifier has, and the scan clamps). The
    periodic plan checks the thesis loop's reach around that voltage, so the offset shrinks (down
    to ``least_v``, still beyond the frame) until that check passes; where it never does, the
    thesis model places it as before.
    """
    from piezod.errors import RangeUnreachableError, SafetyError
    from piezod.service.axes import _plan, axis_model

    ax = config.axes[axis]
    model = axis_model(ax)
    thesis = ax.thesis.params()
    rate = float(config.sample_rate_hz)
    v = off_v
    while abs(v) >= least_v:
        off_um = round(_ramped_um(model, centre_v + v, rate, start=start), 2)
        try:
            _plan(thesis, range_um, 1.0, off_um, ax.voltage_min_v, ax.voltage_max_v, center_v=centre_v + v)
        except (RangeUnreachableError, SafetyError):
            v *= 0.9
            continue
        return off_um, v
    return round((centre_v + off_v) * b, 2), off_v


def verify(
    engine: Engine,
    points: Sequence[VerifyPoint],
    directory: Path,
    model: str,
    worker: AnalysisWorker,
    *,
    lines: int = 4,
    progress: Progress | None = None,
    sensor: SensorPath | None = None,
) -> list[dict[str, Any]]:
    """Scan each point online-corrected; nonlinearity and length error from the sensor readback
    (aligned through the axis's sensor path ``sensor``: a readback delay is not a position error).

    A model that was just switched in starts from a state adopted from the previous one (the
    dynamic model's creep memory spans decades), so one unrecorded warm-up scan at the first
    point's setting precedes the measurements.
    """
    rows: list[dict[str, Any]] = []
    warm_faults: list[str] = []
    if points and engine.status().state in ("fault", "disconnected"):
        # an underrun while the stage held (the fits, the check of the points) on a loaded machine
        # must not end the run: reported with the first point, cleared before the warm-up
        warm_faults = _fault_texts(engine.acknowledge_fault())
    if points:
        first = points[0]
        warm = ScanRequest(
            range_um=first.range_um,
            line_rate_hz=first.frequency_hz,
            lines=4,
            slow_range_um=0.0,
            offset_x_um=first.offset_um,
            record=False,
        )
        engine.check_scan(warm)
        mark = engine.uptime_s
        engine.start_scan(warm)
        if engine.wait_idle((4 + 3) / first.frequency_hz + 10.0) != "idle":
            # the warm-up is not measured, but its fault is reported with the first point
            warm_faults += _fault_texts(engine.acknowledge_fault(since_s=mark))
    for i, pt in enumerate(points):
        name = f"verify-{model}-{i:02d}"
        n_lines = 1 if pt.frequency_hz < 0.1 else lines  # a 0.02 Hz line takes 50 s
        path = directory / f"{name}.csv"
        req = ScanRequest(
            range_um=pt.range_um,
            line_rate_hz=pt.frequency_hz,
            lines=n_lines,
            slow_range_um=0.0,
            offset_x_um=pt.offset_um,
            name=name,
        )
        row: dict[str, Any] = {
            "model": model,
            "range_um": pt.range_um,
            "frequency_hz": pt.frequency_hz,
            "offset_um": pt.offset_um,
            "inside_frame": pt.inside_frame,
            "what": pt.why,
            "recording": str(path),
        }
        if pt.note:
            row["placement"] = pt.note
        if warm_faults:
            row["faults_before"], warm_faults = warm_faults, []
        if engine.status().state in ("fault", "disconnected"):
            # An earlier fault (e.g. an underrun while the fit ran) must not silently end the run:
            # it is reported with the next point, cleared, and the verification goes on.
            row["faults_before"] = row.get("faults_before", []) + _fault_texts(engine.acknowledge_fault())
        mark = engine.uptime_s
        lines_before = engine.tracker_lines("x")
        try:
            engine.check_scan(req)
        except PiezodError as exc:
            row.update(nonlinearity_pct=None, length_error_pct=None, skipped=str(exc))
            rows.append(row)
            continue
        state = _scan_once(engine, req, path, pt, i, len(points), n_lines, progress)
        if state != "idle":
            # A fault (an underrun on a loaded machine, a link hiccup) spoils the measurement, not
            # the correction: report it and measure the point once more.
            # The stage ramped down (the fault's own handling); the table says the point was retried.
            row["retried_after"] = _fault_texts(engine.acknowledge_fault(since_s=mark))
            # recordings are never overwritten: the spoilt one stays, the retry gets its own
            path = directory / f"{name}-retry.csv"
            req = req.model_copy(update={"name": f"{name}-retry"})
            row["recording"] = str(path)
            state = _scan_once(engine, req, path, pt, i, len(points), n_lines, progress)
        if state != "idle":
            row.update(
                nonlinearity_pct=None, length_error_pct=None, skipped=f"the scan ended in state {state}"
            )
            rows.append(row)
            continue
        full_scale = engine.settings.full_scale_um("x")
        figures = worker.linearity(path, "x", sensor, full_scale)
        nl, le, clipped = figures.nonlinearity_pct, figures.length_error_pct, figures.clipped
        limited = [f for f in engine.faults.recent(200) if f.time_s >= mark and f.code == "LIMIT"]
        # figures that are not the model's are never reported, only kept aside with the reason: a
        # readback at the sensor's full scale scores the ADC's end code, a clamped scan the amplifier
        aside: tuple[str, str] | None = None
        if clipped:
            aside = (
                "clipped_figures",
                f"readback at the sensor's full scale (+-{full_scale:g} um) in {clipped} samples",
            )
        elif limited:
            aside = "clamped_figures", f"clamped ({limited[-1].message})"
        if aside is None:
            row.update(nonlinearity_pct=nl, length_error_pct=le)
            for key in ("noise_pct", "pixel_nonlinearity_pct", "pixel_noise_pct"):
                if math.isfinite(value := getattr(figures, key)):
                    row[key] = value
        else:
            row.update(nonlinearity_pct=None, length_error_pct=None, skipped=aside[1])
            row[aside[0]] = {"nonlinearity_pct": nl, "length_error_pct": le}
        # the sensitivity the daemon's tracker had learnt by the end of the point, relative to the model
        row["tracked_scale"] = engine.tracked_scale("x")
        lines_after = engine.tracker_lines("x")
        if lines_before is not None and lines_after is not None:
            row["tracker_lines"] = {k: lines_after[k] - lines_before[k] for k in lines_after}
        rows.append(row)
    return rows


def _fault_texts(faults: Sequence[Any]) -> list[str]:
    """The last faults of the engine's log as ``source/CODE: message`` lines."""
    return [f"{f.source}/{f.code}: {f.message}" for f in faults[-3:]]


@dataclass(frozen=True, slots=True)
class ThesisFit:
    """What the fit process returns: the JSON report, the calibrated config, the worst fit error."""

    report: dict[str, Any]
    config: ScannerConfig
    fit_error_pct: float


def _scan_once(
    engine: Engine,
    req: ScanRequest,
    path: Path,
    pt: VerifyPoint,
    i: int,
    n: int,
    n_lines: int,
    progress: Progress | None,
) -> str:
    """Scan one verification point; return the engine state afterwards."""
    engine.start_scan(req, path=path)
    total = (n_lines + 2) / pt.frequency_hz
    t0 = time.monotonic()
    while engine.status().state == "scanning":
        if progress is not None:
            progress(f"verify {i + 1}/{n}", min(time.monotonic() - t0, total))
        time.sleep(0.1)
    state = engine.wait_idle(10.0)
    engine.wait_recorded()
    return state


def _fit_thesis_here(frame_path: Path, axis: AxisName, base: ScannerConfig) -> ThesisFit:
    result = calibrate(read_experiments([frame_path], axis=axis))
    config = calibrated_config(result, axis=axis, base=base, inputs=[str(frame_path)])
    return ThesisFit(result_json(result, inputs=[str(frame_path)]), config, float(result.fit_error_pct))


def _fit_dynamic_here(
    frame_path: Path, axis: AxisName, base: ScannerConfig, ramp_v_per_s: float, rest_voltage_v: float
) -> ThesisFit:
    from piezod import calibrate_dynamic as cd

    result = cd.calibrate_dynamic(
        read_experiments([frame_path], axis=axis),
        slew_rate_v_per_s=ramp_v_per_s,
        rest_voltage_v=rest_voltage_v,
    )
    config = cd.calibrated_config(result, axis=axis, base=base, inputs=[str(frame_path)])
    return ThesisFit(cd.result_json(result, inputs=[str(frame_path)]), config, float(result.fit_error_pct))


def _choose_here(
    frame_path: Path, axis: AxisName, base: ScannerConfig, ramp_v_per_s: float, rest_voltage_v: float
) -> ThesisFit:
    return choose_for_experiments(
        read_experiments([frame_path], axis=axis), axis, base, ramp_v_per_s, rest_voltage_v
    )


def _frame_session(
    experiments: Sequence[Experiment],
    ramp_v_per_s: float,
    rest_voltage_v: float,
    one_sensor: bool = False,
    hold_before_move: bool = False,
) -> DynamicCalibrationData:
    """The frame laid out for the family fit (:func:`piezod.calibrate_dynamic.prepare_dynamic`):
    one unknown offset per experiment, or with ``one_sensor`` those of one sensor
    (:func:`one_sensor_offsets`); ``hold_before_move``: between experiments the stage held where
    the previous one ended (the daemon between programs)."""
    from piezod import calibrate_dynamic as cd

    data = cd.prepare_dynamic(
        experiments,
        max_samples_per_loop=256,
        slew_rate_v_per_s=ramp_v_per_s,
        rest_voltage_v=rest_voltage_v,
        hold_before_move=hold_before_move,
    )
    return one_sensor_offsets(data) if one_sensor else data


def one_sensor_offsets(data: DynamicCalibrationData) -> DynamicCalibrationData:
    """``data`` with one unknown offset and drift rate for the whole session instead of an offset
    per experiment.

    The calibration frame is one session read by one sensor: its zero is the same in every scan,
    up to the sensor's slow drift. An offset per experiment leaves the model's absolute position
    free between scans (the session's reconstruction between them need not be exact), and what
    only moves it there goes unseen; :func:`audit_and_extend` ties the offsets to one sensor
    when a part acts on that position (:func:`needs_one_sensor`, docs/model-family.md 6.2ar).
    """
    import dataclasses

    times = [
        np.linspace(e.t_start_s, e.t_start_s + e.duration_s, int(n))
        for e, n in zip(data.experiments, data.counts, strict=True)
    ]
    return dataclasses.replace(
        data,
        offset_group=np.zeros(data.position_um.size, dtype=np.intp),
        offset_time_s=np.concatenate(times),
    )


#: How far the chosen member's per-experiment offsets may move a verified line's length (%) through
#: the parts that act on the absolute position (:func:`needs_one_sensor`). An offset per
#: experiment leaves the member's absolute position free between the scans; where a part bends
#: the stage's slope with the position, a member placed ``d`` um off scans at a slope off by ``d``
#: times the slope's relative change per um (:func:`absolute_slope_gradient`). On birch35 (a PMN
#: stage, saturation and a +2 %/um stiffness) the generalised play law on 5 centre nodes spread its
#: offsets by 0.62 um with the range (3 % of the 19 um travel, inside the 5 % this rule used to
#: allow), its saturation part was profiled at 28.4 um (the stage's 26.0) and every verified
#: line came out 0.6-1.9 % long; 0.62 um times the 0.044 /um of that part is 2.7 %. The tie is not
#: the default: where the reconstruction between the scans is not exact it costs held-out RMS
#: (preisach-stage's play member 4.05 -> 7.06 nm with 20 nm of spread), and without such a part a
#: member's offsets do not reach the scans (tansy30's play member spreads by 31 um over 71 um and
#: verified within the targets; the daemon adopts the measured position).
OFFSET_LENGTH_LIMIT_PCT = 0.1


#: Runtime parts that act on the absolute position (:mod:`piezod.model.parts`): the model's
#: position decides where they compress or stiffen, so a member whose offsets spread between the
#: frame's scans puts them in the wrong place (:func:`needs_one_sensor`).
ABSOLUTE_PARTS = ("saturation", "stiffness")


def absolute_slope_gradient(
    effects: Mapping[str, Any], member_stiffness_pct_per_um: float, travel_um: float
) -> float:
    """The largest relative change of the stage's slope per um of absolute position (1/um) over
    ``travel_um`` on either side of the model's zero: the stiffness part's ``k / 100`` and the
    member's own static map's, and the saturation part's ``2 tanh(travel / x_sat) / x_sat``
    (:mod:`piezod.model.parts`)."""
    gradient = abs(member_stiffness_pct_per_um) / 100.0
    stiffness = effects.get("stiffness") or {}
    gradient += abs(float(stiffness.get("sensitivity_pct_per_um", 0.0))) / 100.0
    x_sat = float((effects.get("saturation") or {}).get("x_sat_um", math.inf))
    if math.isfinite(x_sat) and x_sat > 0.0:
        gradient += 2.0 * math.tanh(travel_um / x_sat) / x_sat
    return gradient


def needs_one_sensor(choice_report: Mapping[str, Any], effects: Mapping[str, Any]) -> str | None:
    """Why the parts ``effects`` need the model choice fitted with one sensor's offsets
    (:func:`one_sensor_offsets`), or None: a part that acts on the absolute position
    (:data:`ABSOLUTE_PARTS`) with a chosen member whose per-experiment offsets spread so far that,
    through the slope those parts bend (:func:`absolute_slope_gradient`), they could move a line's
    length by more than :data:`OFFSET_LENGTH_LIMIT_PCT`."""
    offsets = choice_report.get("offsets", {})
    absolute = sorted(set(effects) & set(ABSOLUTE_PARTS))
    spread, travel = offsets.get("spread_um", 0.0), offsets.get("travel_um", 0.0)
    if offsets.get("one_sensor") or not absolute:
        return None
    member_k = float((choice_report.get("family") or {}).get("stiffness_pct_per_um", 0.0))
    length_pct = 100.0 * spread * absolute_slope_gradient(effects, member_k, travel)
    if length_pct <= OFFSET_LENGTH_LIMIT_PCT:
        return None
    return (
        f"{choice_report.get('chosen')}'s offsets spread by {spread:.3g} um over a {travel:.3g} um frame "
        f"under {', '.join(absolute)}, which act on the absolute position: a line placed that far off "
        f"would be up to {length_pct:.2g} % off in length (more than {OFFSET_LENGTH_LIMIT_PCT:g} %); the "
        "parts and the choice fitted again with the offsets of one sensor"
    )


def tied_to_one_sensor(choice_report: Mapping[str, Any]) -> bool:
    """Whether a model choice's report (:func:`choose_for_experiments`) fitted with the offsets of
    one sensor."""
    return bool(choice_report.get("offsets", {}).get("one_sensor", False))


def offset_spread(data: DynamicCalibrationData, params: Any) -> tuple[float, float]:
    """How far a family member's per-experiment offsets spread (um: the largest minus the
    smallest of the experiments' mean residual) and the frame's travel (um)."""
    from piezod.calibrate_family import experiment_offsets, session_positions

    off = experiment_offsets(data, session_positions(data, params))
    return float(np.ptp(off)), float(np.ptp(data.position_um))


def choose_for_experiments(
    experiments: Sequence[Experiment],
    axis: AxisName,
    base: ScannerConfig,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    members: Sequence[tuple[str, str]] | None = None,
    one_sensor: bool = False,
) -> ThesisFit:
    """Fit the family's laws, score them and the dynamic model of ``base`` on held-out experiments.

    Returns the config using the model that predicts the held-out experiments best
    (``model: family`` with its section, or ``model: dynamic``), the report (``table``,
    ``chosen``, RMS per candidate, ``offsets``: whether the fits took the offsets of one sensor,
    and the chosen member's offset spread and the frame's travel) and, as ``fit_error_pct``, the
    chosen model's held-out RMS in um. ``members`` (``(law, creep driver)`` pairs) restricts the
    family members fitted (:func:`piezod.calibrate_family.choose_model`); default every one.
    ``one_sensor``: the offsets of one sensor (:func:`one_sensor_offsets`), not one per
    experiment.
    """
    from piezod import calibrate_family as cf
    from piezod.model.family import REALTIME_CREEP_DRIVERS, CreepSpectrum, FamilyParams

    data = _frame_session(experiments, ramp_v_per_s, rest_voltage_v, one_sensor=one_sensor)
    ax = base.axes[axis]
    others: dict[str, FamilyParams] = {}
    alpha = None
    if ax.dynamic is not None:
        dyn = ax.dynamic.params()
        alpha = dyn.alpha_per_v
        spectrum = CreepSpectrum(tuple(map(float, dyn.taus_s)), tuple(map(float, dyn.weights)))
        others["dynamic"] = FamilyParams(dyn.hysteresis, spectrum)
    choice = cf.choose_model(
        data, others=others, alpha_per_v=alpha, adoptable_drivers=REALTIME_CREEP_DRIVERS, members=members
    )
    report: dict[str, Any] = {
        "chosen": choice.chosen,
        "held_out_experiments": list(choice.holdout),
        "heldout_rms_um": choice.heldout_rms_um,
        "train_rms_um": choice.train_rms_um,
        "table": choice.table(),
    }
    config = base
    report["offsets"] = {"one_sensor": one_sensor}
    if choice.fit is not None:
        section = cf.family_model_config(choice.fit.params)
        config = base.with_axis(axis, model="family", family=section)
        report["family"] = section.model_dump()
        report["family_rms_um"] = choice.fit.rms_um
        spread, travel = offset_spread(data, choice.fit.params)
        report["offsets"].update(spread_um=spread, travel_um=travel)
    elif ax.dynamic is not None:
        config = base.with_axis(axis, model="dynamic")
    return ThesisFit(report, config, float(choice.heldout_rms_um[choice.chosen]))


def audit_and_extend(
    experiments: Sequence[Experiment],
    axis: AxisName,
    chosen: ThesisFit,
    base: ScannerConfig,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    *,
    folds: int = 4,
    since_unix_s: float = math.nan,
    placement: tuple[Experiment, PlacementProgram] | None = None,
) -> ThesisFit:
    """Audit the frame, adopt the material findings that have a runtime part if they predict better.

    The audit (:func:`piezod.audit.run_audit`) names the effects (and, on a baseline it finds
    undetermined, withholds them: they are tried all the same); those with a runtime part
    (:func:`piezod.extensions.adopt_findings`) are profiled on the chosen member, the static parts
    it did not name are probed there, those the member's held-out RMS does not need are left out
    (:func:`profile_member`); when the chosen member leaves out a runtime part the audit named
    (not one it fits itself), the same is done on the best member of each other law
    (:func:`other_laws`), and the parts profiled on the member that predicts best through them
    are taken. The model choice is redone on the
    frame seen through their exact inverse (:func:`choose_for_experiments`). When a part acts on the
    absolute position and the member chosen through the parts has offsets that spread between the
    scans (:func:`needs_one_sensor`), the profile and the choice are done again with the offsets of
    one sensor (:func:`one_sensor_offsets`), and the chosen member is refitted that way to compare
    with. The extended model is adopted when its held-out RMS is below the chosen model's, else the
    findings are reported as not adopted.

    Parameters
    ----------
    experiments
        The frame.
    axis
        The calibrated axis.
    chosen
        :func:`choose_for_experiments` on the frame (its ``fit_error_pct`` is the held-out RMS).
    base
        The config the choice started from (thesis and dynamic sections).
    ramp_v_per_s, rest_voltage_v
        As for the choice.
    folds
        The audit's held-out folds.
    since_unix_s
        When the frame's clock read 0 (:func:`piezod.extensions.session_origin_unix_s`): adopted
        time parts go on from there.
    placement
        The lag placement experiment and its program: the written model's sensor path is then
        placed by it (:func:`with_lag_placed`) before the dynamics are identified.

    Returns
    -------
    ThesisFit
        The config to write (``chosen.config`` or the extended one), ``report`` with ``findings``,
        ``withheld``, ``adopted``, ``skipped``, ``heldout_rms_um`` (chosen / extended) and ``text``.
    """
    from piezod import calibrate_family as cf
    from piezod.audit import result_json as audit_json
    from piezod.audit import run_audit
    from piezod.audit.residuals import experiments_noise_floor
    from piezod.calibrate_family import CHOICE_TIE_FRACTION
    from piezod.extensions import (
        adopt_findings,
        adoption_audit_options,
        experiments_through,
        extended_config,
        trend_horizon_s,
    )
    from piezod.model.parts import PART_EFFECTS
    from piezod.model.sensor import SENSOR_EFFECTS

    def finish(fit: ThesisFit) -> ThesisFit:
        placed = with_lag_placed(placement, axis, fit, experiments, ramp_v_per_s, rest_voltage_v)
        return with_dynamics(experiments, axis, placed)

    doc = audit_json(run_audit(experiments, [], options=adoption_audit_options(folds)))
    # Findings withheld on an undetermined audit baseline are tried all the same: each part is
    # profiled on the chosen member and kept only if that member's held-out RMS needs it.
    adoption = adopt_findings(
        [*doc["findings"], *doc["withheld"]],
        horizon_s=trend_horizon_s(experiments),
        since_unix_s=since_unix_s,
    )
    report: dict[str, Any] = {
        "findings": [f["effect"] for f in doc["findings"]],
        "withheld": [f["effect"] for f in doc["withheld"]],
        "cause": doc["cause"],
        "adopted": [],
        "skipped": list(adoption.skipped),
        "heldout_rms_um": {"chosen": chosen.fit_error_pct},
    }
    first = str(chosen.report.get("chosen", ""))
    # the family fits keep every k-th sample (_frame_session): their residuals carry the
    # readback's noise per sample unchanged
    floor = experiments_noise_floor(experiments)
    named = adoption

    def profile_and_redo(tied: bool) -> tuple[Adoption, list[str], ThesisFit | None]:
        """The parts profiled on the chosen member (and on the other laws when it drops one), and
        the choice redone through those kept (None when none is)."""
        profiled, refined, heldout = profile_member(
            experiments, named, first, ramp_v_per_s, rest_voltage_v, floor_um=floor, one_sensor=tied
        )
        best = first, heldout if profiled.effects and math.isfinite(heldout) else chosen.fit_error_pct
        report["profiled"] = {first: best[1]}
        # a named static part the chosen member does without: its law may absorb the effect in a
        # misfit of the loops (or the audit was wrong); another law may fit through the part
        dropped = (set(named.effects) & set(PART_EFFECTS)) - set(MEMBER_OWN_PARTS) - set(profiled.effects)
        for name in other_laws(chosen.report) if dropped else []:
            trial, notes, rms = profile_member(
                experiments, named, name, ramp_v_per_s, rest_voltage_v, floor_um=floor, one_sensor=tied
            )
            report["profiled"][name] = rms
            if trial.effects and lowers(rms, best[1], CHOICE_TIE_FRACTION, floor):
                best, profiled, refined = (name, rms), trial, notes
        if best[0] != first:
            refined = [
                f"parts profiled on {best[0]} ({best[1] * 1e3:.2f} nm held out through them; "
                f"{first}: {report['profiled'][first] * 1e3:.2f} nm)",
                *refined,
            ]
        report["refined"] = refined
        report["skipped"] = list(profiled.skipped)
        if not profiled.effects:
            return profiled, refined, None
        members = redo_shortlist(chosen.report)
        profiled_member = cf.parse_member(best[0])
        if members is not None and profiled_member is not None and profiled_member[:2] not in members:
            members.append(profiled_member[:2])
        redone = choose_for_experiments(
            experiments_through(experiments, profiled.effects),
            axis,
            base,
            ramp_v_per_s,
            rest_voltage_v,
            members=members,
            one_sensor=tied,
        )
        return profiled, refined, redone

    tied = tied_to_one_sensor(chosen.report)
    # what the extended model is compared with: the chosen model under the same offsets
    chosen_rms = chosen.fit_error_pct
    adoption, refined, redone = profile_and_redo(tied)
    if redone is not None and (reason := needs_one_sensor(redone.report, adoption.effects)) is not None:
        # the parts act on the absolute position the offsets per experiment left free
        tied = True
        report["offsets"] = {"one_sensor": True, "reason": reason}
        again = cf.parse_member(first)
        if again is not None:
            chosen_rms = choose_for_experiments(
                experiments, axis, base, ramp_v_per_s, rest_voltage_v, members=[again[:2]], one_sensor=True
            ).fit_error_pct
            report["heldout_rms_um"]["chosen_one_sensor"] = chosen_rms
        adoption, refined, redone = profile_and_redo(tied)
    if redone is None:
        report["text"] = adoption.summary()
        return finish(ThesisFit(report, chosen.config, chosen.fit_error_pct))
    report["heldout_rms_um"]["extended"] = redone.fit_error_pct
    # A lag the held-out data cannot place (the sensor path predicts as well as the drive lag the
    # fit takes instead) is put at the sensor: a sensor lag compensated at the drive makes the
    # voltage overshoot every reversal, which moves a hysteretic stage's branch; a drive lag left
    # uncompensated only delays the stage.
    sensor_only = set(adoption.effects) <= set(SENSOR_EFFECTS)
    limit = excess_rms(chosen_rms, floor) * (1.0 + CHOICE_TIE_FRACTION)
    tie = sensor_only and excess_rms(redone.fit_error_pct, floor) <= limit
    if redone.fit_error_pct < chosen_rms or tie:
        report["adopted"] = list(adoption.adopted)
        report["model_choice"] = redone.report
        report["text"] = (
            f"held-out RMS {chosen_rms * 1e3:.2f} nm -> {redone.fit_error_pct * 1e3:.2f} nm with "
            f"the findings as runtime parts"
            + (" (both with the offsets of one sensor)" if tied else "")
            + (f"\noffsets: {report['offsets']['reason']}" if "offsets" in report else "")
            + f"\n{adoption.summary()}"
            + "".join(f"\nrefined {r}" for r in refined)
        )
        extended = ThesisFit(report, extended_config(redone.config, axis, adoption), redone.fit_error_pct)
        return finish(extended)
    worse = f"held-out RMS {redone.fit_error_pct * 1e3:.2f} nm, not below {chosen_rms * 1e3:.2f} nm"
    report["skipped"] = [f"{a} ({worse})" for a in adoption.adopted] + report["skipped"]
    report["text"] = "\n".join(f"not adopted {s}" for s in report["skipped"])
    return finish(ThesisFit(report, chosen.config, chosen.fit_error_pct))


def with_dynamics(experiments: Sequence[Experiment], axis: AxisName, fit: ThesisFit) -> ThesisFit:
    """``fit`` with the stage's mode, then with the fast creep its model misses (measured through
    the mode), each identified on the frame and adopted when it predicts held-out data better.

    Parameters
    ----------
    experiments
        The frame (periodic triangular scans at several rates; other scans give no finding).
    axis
        The calibrated axis of ``fit.config``.
    fit
        The config to extend (its axis model is the one the steps measure against), a report and
        the held-out RMS (passed through).

    Returns
    -------
    ThesisFit
        The config with the parts adopted; the report with ``resonance`` and ``fast_creep`` (when
        the frame shows them), each step's note appended to ``adopted`` or ``skipped`` and to
        ``text``.
    """
    return _with_fast_creep(experiments, axis, _with_resonance(experiments, axis, fit))


def with_lag_placed(
    placement: tuple[Experiment, PlacementProgram] | None,
    axis: AxisName,
    fit: ThesisFit,
    experiments: Sequence[Experiment] = (),
    ramp_v_per_s: float = 0.0,
    rest_voltage_v: float = 0.0,
) -> ThesisFit:
    """``fit`` with its lags where the lag placement experiment places them
    (:func:`piezod.lag_placement.place_lag`): as much of its sensor path at the drive as it places
    there, or as much of the family member's own drive lag at the sensor (more drive lag than the
    sensor path holds is reported, not made); unchanged without the experiment or a lag to move.

    When time moves to the drive, with the frame's ``experiments`` the family member is then
    refitted with its drive lag held there (:func:`refit_at_drive_lag`): fitted with the lag at the
    sensor, its creep took the rate dependence the lag gives the loops, and a moved lag beside it
    would count that twice. When the member's drive lag moves to the sensor the member is kept:
    refitted there, the verified lines inside the frame spread further apart on three of eight
    held-out stages (to 0.103 % from 0.021 %), kept on none by more than 0.006 %
    (docs/model-family.md 6.2bj).
    The report gets ``lag_placement`` and the step's note under ``adopted`` or ``skipped``.
    """
    from piezod import calibrate_family as cf
    from piezod.lag_placement import LagPlacement, moved_config, place_lag

    if placement is None:
        return fit
    experiment, program = placement
    member = cf.parse_member(str(fit.report.get("model_choice", {}).get("chosen", "")))
    refit: dict[str, float] = {}

    def adopt(
        _: Sequence[Experiment], __: str, config: ScannerConfig
    ) -> tuple[ScannerConfig, LagPlacement | None]:
        found = place_lag(experiment, program, config, axis)
        if found is None or not found.adopted:
            return config, found
        moved = moved_config(config, axis, found.moved_s)
        # a member's drive lag moved to the sensor keeps the member: the refit moved the verified
        # lines by more than the move did (docs/model-family.md 6.2bj)
        if found.moved_s < 0.0 or not experiments or member is None:
            return moved, found
        moved, refit["heldout_rms_um"] = refit_at_drive_lag(
            experiments,
            moved,
            axis,
            member[2],
            ramp_v_per_s,
            rest_voltage_v,
            one_sensor=tied_to_one_sensor(fit.report.get("model_choice", {})),
        )
        return moved, found

    def summary(found: LagPlacement) -> dict[str, Any]:
        return {
            "movable_s": found.movable_s,
            "drive_lag_s": found.drive_lag_s,
            "placed_s": found.placed_s,
            "moved_s": found.moved_s,
            "jumps_um": list(found.jumps_um),
            "jumps_moved_um": list(found.jumps_moved_um),
            "adopted": found.adopted,
            **refit,
        }

    placed = _with_step([experiment], axis, fit, "lag_placement", adopt, summary)
    if "heldout_rms_um" in refit:
        # a config given as written (tools/model_family_verify.py --verify) has no held-out figure
        before = (
            f" (with the lag at the sensor: {fit.fit_error_pct * 1e3:.2f} nm)"
            if math.isfinite(fit.fit_error_pct)
            else ""
        )
        placed = _noted(
            placed,
            dict(placed.report),
            f"refitted with the drive lag held there: {refit['heldout_rms_um'] * 1e3:.2f} nm held out"
            + before,
            "adopted",
            placed.config,
        )
    return placed


def drive_lagged(experiments: Sequence[Experiment], tau_s: float) -> list[Experiment]:
    """The experiments with their voltages through a first-order lag ``tau_s`` (the amplifier's
    pole: what the ceramic sees), each settled at its first voltage."""
    import dataclasses

    from piezod.lag_placement import first_order_lag

    if tau_s <= 0.0:
        return list(experiments)
    out = []
    for e in experiments:
        t = np.asarray(e.t_s, dtype=np.float64)
        if t.size < 2:
            out.append(e)
            continue
        dt = float(np.median(np.diff(t)))
        out.append(dataclasses.replace(e, voltage_v=first_order_lag(np.asarray(e.voltage_v), dt, tau_s)))
    return out


def _drive_lag_session(
    experiments: Sequence[Experiment],
    config: ScannerConfig,
    axis: AxisName,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    one_sensor: bool,
    history: Sequence[Experiment],
) -> tuple[FamilyModelConfig, DynamicCalibrationData, NDArray[np.bool_], NDArray[np.bool_]]:
    """The family section of ``config``'s ``axis``, and :func:`refit_at_drive_lag`'s session with
    its training and history masks (the model choice's split of ``experiments``)."""
    from piezod import calibrate_family as cf
    from piezod.extensions import experiments_through

    ax = config.axes[axis]
    if ax.model != "family" or ax.family is None:
        raise CalibrationError(f"axis {axis}: the drive lag is refitted on a family member only")
    section = ax.family
    # experiments_through takes the sensor path and the runtime parts and ignores the rest
    effects = {str(k): v for k, v in (ax.extensions or {}).items()}
    seen = drive_lagged(experiments_through([*history, *experiments], effects), section.lag_time_constant_s)
    data = _frame_session(
        seen, ramp_v_per_s, rest_voltage_v, one_sensor=one_sensor, hold_before_move=bool(history)
    )
    # the session is sorted by time
    first_t = min(float(e.t_s[0]) for e in experiments)
    before = np.array([lay.t_start_s < first_t for lay in data.experiments], dtype=bool)
    if np.count_nonzero(before) != len(history):
        raise CalibrationError("the history must come before the frame, on the same clock")
    train = np.concatenate([np.zeros(len(history), dtype=bool), cf.holdout_mask(len(experiments))])
    return section, data, train, before


def refit_at_drive_lag(
    experiments: Sequence[Experiment],
    config: ScannerConfig,
    axis: AxisName,
    plays: int | None,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    one_sensor: bool = False,
    history: Sequence[Experiment] = (),
) -> tuple[ScannerConfig, float]:
    """``config``'s family member refitted on the frame seen through its runtime parts and sensor
    path, with its drive lag held at ``lag_time_constant_s`` (the frame's voltages through that
    pole, :func:`drive_lagged`, and no lag fitted), with the offsets the model choice used
    (``one_sensor``: :func:`one_sensor_offsets`). The model runs through the ``history``
    experiments (what the stage did before the frame, on the same clock; the stage held where each
    program ended) without fitting or scoring them.

    Returns
    -------
    config, heldout_rms_um
        The config with the refitted member (fitted on every experiment, as the model choice's
        final fit), and its held-out RMS (fitted on the choice's training experiments).

    Raises
    ------
    CalibrationError
        The axis model is not a family member, or a fit fails.
    """
    session = _drive_lag_session(experiments, config, axis, ramp_v_per_s, rest_voltage_v, one_sensor, history)
    return _refit_on_session(config, axis, plays, *session)


def _refit_on_session(
    config: ScannerConfig,
    axis: AxisName,
    plays: int | None,
    section: FamilyModelConfig,
    data: DynamicCalibrationData,
    train: NDArray[np.bool_],
    before: NDArray[np.bool_],
) -> tuple[ScannerConfig, float]:
    """:func:`refit_at_drive_lag` on the session :func:`_drive_lag_session` built."""
    from piezod import calibrate_family as cf

    tau = section.lag_time_constant_s
    law = section.params()
    options: dict[str, Any] = {
        "plays": plays or cf.DEFAULT_PLAYS,
        "n_nodes": len(section.gp_nodes_v) or cf.GP_NODES,
        "creep_driver": section.creep_driver,
        "alpha_per_v": section.alpha_per_v,
        "fit_lag": False,
        "start": law.hysteresis if isinstance(law.hysteresis, BoucWenParams | DomainWallParams) else None,
        # held where the first frame placed it (a search per refit costs a minute)
        "after_effect": law.after_effect,
    }
    heldout = cf.fit_family(data, section.law, train=train, history=before, **options)
    final = cf.fit_family(data, section.law, history=before, **options)
    refitted = cf.family_model_config(final.params).model_copy(update={"lag_time_constant_s": tau})
    return config.with_axis(axis, family=refitted), heldout.heldout_rms_um


def refresh_blocker(config: ScannerConfig, axis: AxisName, chosen: str) -> str | None:
    """Why ``config``'s ``axis`` model cannot be refitted on a frame played again
    (:func:`refresh_member`), or None when it can."""
    from piezod import calibrate_family as cf
    from piezod.model.parts import TIME_PARTS

    ax = config.axes[axis]
    if ax.model != "family" or ax.family is None or cf.parse_member(chosen) is None:
        return f"the written model ({ax.model}) is not a family member"
    timed = sorted(set(map(str, ax.extensions or {})) & set(TIME_PARTS))
    if timed:
        return f"its time parts ({', '.join(timed)}) run from the first frame"
    return None


@dataclass(frozen=True)
class Refresh:
    """A family member refitted on a frame played again (:func:`refresh_member`).

    Attributes
    ----------
    config
        The config with the member refitted on the new frame.
    heldout_rms_um
        The refit's held-out RMS on the new frame (fitted on the model choice's training scans).
    kept_rms_um
        The first frame's member, unchanged, on the same held-out scans (only the offsets fitted,
        by the same rule).
    """

    config: ScannerConfig
    heldout_rms_um: float
    kept_rms_um: float

    @property
    def better(self) -> bool:
        """Whether the refit predicts the new frame's held-out scans better than the first frame's
        member does (true when there was nothing to compare)."""
        return not self.heldout_rms_um >= self.kept_rms_um


def refresh_member(
    experiments: Sequence[Experiment],
    axis: AxisName,
    config: ScannerConfig,
    chosen: str,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    one_sensor: bool = False,
    history: Sequence[Experiment] = (),
) -> Refresh:
    """``config``'s family member (``chosen``, the model choice's name for it) refitted on a frame
    played again after the fits: the member's laws, play grid, centre grid and drive lag stay, its
    weights and offsets are fitted again (:func:`refit_at_drive_lag`) on the frame seen through the
    adopted parts and the sensor path, which are held as the first frame's fits left them (as are
    the mode and the fast creep). The model runs through the ``history`` first: what the stage
    did since it rested at ``rest_voltage_v`` (the first frame, the lag placement), on the same
    clock, and through the frame's first scan; neither is fitted or scored. The first frame's
    member is scored on the same held-out scans, so a caller keeps whichever predicts the stage
    as it is now (:attr:`Refresh.better`).

    Raises
    ------
    CalibrationError
        The model cannot be refitted so (:func:`refresh_blocker`), or a fit fails.
    """
    from piezod import calibrate_family as cf

    if (why := refresh_blocker(config, axis, chosen)) is not None:
        raise CalibrationError(f"not refitted: {why}")
    member = cf.parse_member(chosen)
    assert member is not None
    experiments = sorted(experiments, key=lambda e: float(e.t_s[0]))
    if len(experiments) < 2:
        raise CalibrationError("not refitted: the frame played again has fewer than two scans")
    # its first scan only runs the model: the creep from the hold relaxes through it, which the
    # member's spectrum, fitted on a frame that began at rest, does not follow (pi-stage: 26.0 nm
    # held out with it fitted, 3.5 nm without; the first frame 2.9 nm; docs/model-family.md 6.2br)
    scans, ran = experiments[1:], [*history, experiments[0]]
    session = _drive_lag_session(scans, config, axis, ramp_v_per_s, rest_voltage_v, one_sensor, ran)
    section, data, train, before = session
    # the section's lag is the drive pole the session's voltages went through already
    first = replace(section.params(), lag_time_constant_s=0.0)
    kept = cf.heldout_rms(data, first, train, history=before)
    refitted, heldout = _refit_on_session(config, axis, member[2], *session)
    return Refresh(refitted, heldout, kept)


def _refresh_here(
    frame_path: Path,
    history_paths: Sequence[Path],
    axis: AxisName,
    config: ScannerConfig,
    chosen: str,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    one_sensor: bool,
) -> Refresh:
    exps = read_experiments([frame_path], axis=axis)
    before = read_experiments(list(history_paths), axis=axis) if history_paths else []
    return refresh_member(
        exps, axis, config, chosen, ramp_v_per_s, rest_voltage_v, one_sensor, history=before
    )


def _noted(fit: ThesisFit, report: dict[str, Any], note: str, key: str, config: ScannerConfig) -> ThesisFit:
    report["text"] = "\n".join(t for t in (str(report.get("text") or ""), note) if t)
    report[key] = [*report.get(key, []), note]
    return ThesisFit(report, config, fit.fit_error_pct)


def _with_step(
    experiments: Sequence[Experiment],
    axis: AxisName,
    fit: ThesisFit,
    what: str,
    adopt: Callable[[Sequence[Experiment], str, ScannerConfig], tuple[ScannerConfig, Any]],
    summary: Callable[[Any], dict[str, Any]],
) -> ThesisFit:
    """``fit`` through one identification step on the frame (``adopt`` returns the config and a
    finding with ``note`` and ``adopted``, or None when the frame cannot show it); the report gets
    the finding's ``summary`` under ``what`` and its note under ``adopted`` or ``skipped``."""
    report = dict(fit.report)
    try:
        config, found = adopt(experiments, axis, fit.config)
    except (ModelError, CalibrationError) as exc:
        # the model is written without it; the run says why rather than losing the frame's fit
        return _noted(fit, report, f"{what.replace('_', ' ')}: not fitted ({exc})", "skipped", fit.config)
    if found is None:
        return fit
    report[what] = summary(found)
    return _noted(fit, report, found.note, "adopted" if found.adopted else "skipped", config)


def _with_fast_creep(experiments: Sequence[Experiment], axis: AxisName, fit: ThesisFit) -> ThesisFit:
    """``fit`` with the fast creep its model misses when the frame's harmonics at its several rates
    show it and predict the held-out harmonics better (:func:`piezod.rate_id.adopt_fast_creep`)."""
    from piezod.rate_id import RateFinding, adopt_fast_creep

    def summary(found: RateFinding) -> dict[str, Any]:
        return {
            "taus_s": list(found.fast.taus_s),
            "weights": list(found.fast.weights),
            "total": found.fast.total,
            "delay_correction_s": found.delay_correction_s,
            "pole_s": found.pole_s,
            "points": found.points,
            "max_frequency_hz": found.max_frequency_hz,
            "train_rms": list(found.train_rms),
            "heldout_rms": list(found.heldout_rms),
            "adopted": found.adopted,
        }

    return _with_step(experiments, axis, fit, "fast_creep", adopt_fast_creep, summary)


def _with_resonance(experiments: Sequence[Experiment], axis: AxisName, fit: ThesisFit) -> ThesisFit:
    """``fit`` with the stage's resonance when its model's residual shows one that rings and
    predicts the held-out experiments better (:func:`piezod.resonance_id.adopt_resonance`).

    The audit's own resonance candidate is fitted against the audit's baseline, whose misfit
    hides the ringing; the model chosen and extended leaves little else at the mode's frequency.
    """
    from piezod.resonance_id import ResonanceFinding, adopt_resonance

    def summary(found: ResonanceFinding) -> dict[str, Any]:
        return {
            "f0_hz": found.f0_hz,
            "q": found.q,
            "train_rms_um": list(found.train_rms_um),
            "heldout_rms_um": list(found.heldout_rms_um),
            "adopted": found.adopted,
        }

    return _with_step(experiments, axis, fit, "resonance", adopt_resonance, summary)


#: The choice redone through adopted parts refits the family members whose held-out RMS was
#: within this factor of the chosen one's (:func:`redo_shortlist`).
REDO_SHORTLIST_FACTOR = 1.5


def redo_shortlist(report: Mapping[str, Any]) -> list[tuple[str, str]] | None:
    """The ``(law, creep driver)`` pairs worth refitting when the choice is redone through the
    audit's adopted parts: those whose held-out RMS in the first choice's ``report`` was within
    :data:`REDO_SHORTLIST_FACTOR` of the chosen candidate's, the chosen member always; None (every
    member) for a report without the choice's table.

    The parts (a sensor lag, a thermal drift, a stiffening) change every member's residual alike;
    a member predicting half again worse is not overtaken by them (a part the chosen member does
    without can be another law's: :func:`other_laws`, whose member joins), and refitting every law (the
    position-creep fits of a fine play grid take minutes each) made the audit step the longest
    part of a calibration.
    """

    if str(report.get("chosen", "")) not in _choice_rms(report):
        return None
    pairs: list[tuple[str, str]] = []
    for _, member, _ in _members_within(report, REDO_SHORTLIST_FACTOR):
        if member[:2] not in pairs:
            pairs.append(member[:2])
    return pairs


def _choice_rms(report: Mapping[str, Any]) -> dict[str, float]:
    """Held-out RMS per candidate of a model choice's ``report``."""
    return {str(k): float(v) for k, v in dict(report.get("heldout_rms_um") or {}).items()}


def _members_within(
    report: Mapping[str, Any], factor: float
) -> list[tuple[str, tuple[str, str, int | None], float]]:
    """``(name, (law, creep driver, plays), held-out RMS)`` of the family members in a choice's
    ``report`` within ``factor`` of the chosen candidate's held-out RMS (the chosen one always; every
    member when the report has no RMS for it), in the report's order."""
    from piezod import calibrate_family as cf

    rms = _choice_rms(report)
    chosen = str(report.get("chosen", ""))
    limit = factor * rms.get(chosen, math.inf)
    return [
        (name, member, value)
        for name, value in rms.items()
        if (member := cf.parse_member(name)) is not None and (value <= limit or name == chosen)
    ]


#: The audit's runtime parts are also profiled on the best member of each other law whose held-out
#: RMS in the first choice was within this factor of the chosen one's (:func:`other_laws`).
OTHER_LAW_FACTOR = 2.5


def other_laws(report: Mapping[str, Any], factor: float = OTHER_LAW_FACTOR) -> list[str]:
    """The best member of each law other than the chosen member's in the first choice's
    ``report``, within ``factor`` of the chosen one's held-out RMS, best first.

    A static part can change which law fits: a law whose loops are right but whose static map
    cannot bend the way the stage's does (a compression symmetric in position against the
    member's quadratic map) misfits the frame more than a law that absorbs the bend in its
    shape functions but not the loops. On a short-travel held-out stage with a hardening
    Bouc-Wen law and compression the chosen generalised play member left 6.3 nm held out with
    or without a saturation part, the Bouc-Wen member 10.9 nm without it and 0.9 nm through it
    (docs/model-family.md 6.2ah). The factor bounds the cost (each profile refits the member
    a few dozen times, minutes for a play law with position creep); so does
    :func:`audit_and_extend`, which asks only when the chosen member leaves out a part the audit
    named.
    """
    from piezod import calibrate_family as cf

    chosen = cf.parse_member(str(report.get("chosen", "")))
    best: dict[str, tuple[float, str]] = {}
    for name, member, value in _members_within(report, factor):
        if chosen is not None and member[0] == chosen[0]:
            continue
        if member[0] not in best or value < best[member[0]][0]:
            best[member[0]] = (value, name)
    return [name for _, name in sorted(best.values())]


#: Runtime parts a family member fits itself, with why the adoption leaves them out: the member's
#: static map ``x = x_c + k x_c^2 / 200`` is the stiffness part's map, so the two in series are
#: one map with a cubic term the pair trades between them. On a held-out stage the part was
#: profiled to +0.31 %/um with the member's own map at -0.17 %/um beside it, and the corrected
#: scans came out 0.4 % short before the sensitivity tracker (docs/model-family.md 6.2s).
MEMBER_OWN_PARTS: dict[str, str] = {
    "stiffness": "fits its own static stiffness map, the same map as the part",
}


def refine_adoption(
    experiments: Sequence[Experiment],
    adoption: Adoption,
    chosen: str,
    ramp_v_per_s: float,
    rest_voltage_v: float,
) -> tuple[Adoption, list[str]]:
    """:func:`profile_member` without the held-out RMS: the refined adoption and its notes."""
    adopted, notes, _ = profile_member(experiments, adoption, chosen, ramp_v_per_s, rest_voltage_v)
    return adopted, notes


def profile_member(
    experiments: Sequence[Experiment],
    adoption: Adoption,
    chosen: str,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    floor_um: float | None = None,
    one_sensor: bool = False,
) -> tuple[Adoption, list[str], float]:
    """Profile the adopted runtime parts and the sensor path on the chosen member's fit, and keep
    the parts that predict held-out data better.

    The audit estimates them against its own baseline model, which absorbs part of an effect, or
    all of it. A part the member fits itself (:data:`MEMBER_OWN_PARTS`) is left out first. The
    sensor path's lag (:func:`piezod.extensions.refine_sensor_lag`), then each
    runtime part's primary parameter (:func:`piezod.extensions.refine_parts`) are searched for the
    smallest *training* RMS of the chosen family member refitted on the frame seen through them;
    the held-out experiments stay out of it. The static parts the audit did not name are probed
    the same way (:func:`piezod.extensions.probe_parts`) and those added are refined; then the
    parts are profiled together (:func:`piezod.extensions.refine_jointly`: parts that act alike
    trade, and one searched at a time with the others held stops short). For the
    sensor path the member is fitted without a drive lag of its own, which would otherwise take
    any part of the lag the sensor path leaves.
    Then a runtime part the member's held-out RMS does not need is left out
    (:func:`piezod.extensions.prune_parts`; it goes to the adoption's ``skipped``). The probe,
    the joint profile and the pruning take their gains on what the RMS has above the frame's
    noise floor (``floor_um``, by default
    :func:`piezod.audit.residuals.experiments_noise_floor` of the frame;
    :func:`piezod.fitstats.lowers`).
    A member refined to a finer play grid is profiled at the default grid
    (:data:`piezod.calibrate_family.DEFAULT_PLAYS`), on its own centre grid. A chosen model that is
    not a family member leaves the findings as the audit found them.

    Returns
    -------
    adoption, notes, heldout_rms_um
        The adoption with the refined values, the probed parts and without the parts left out,
        one line per refined or probed part, and the member's held-out RMS through the parts kept
        (``nan`` for a chosen model that is not a family member).
    """
    import dataclasses
    import json

    from piezod import calibrate_family as cf
    from piezod.audit.residuals import experiments_noise_floor
    from piezod.extensions import (
        experiments_through,
        probe_parts,
        prune_parts,
        refine_findings,
        refine_jointly,
        refine_parts,
    )

    member = cf.parse_member(chosen)
    if member is None:
        return adoption, [], math.nan
    law, driver, plays = member
    twice = [e for e in MEMBER_OWN_PARTS if e in adoption.effects]
    if twice:
        adoption = dataclasses.replace(
            adoption,
            effects={k: v for k, v in adoption.effects.items() if k not in twice},
            skipped=(*adoption.skipped, *(f"{e}: {chosen} {MEMBER_OWN_PARTS[e]} (left out)" for e in twice)),
        )
    # the profile refits the member a dozen times per part; a finer play grid moves the kinks of
    # the loops, not a part's rate or lag, and costs several times as much per fit
    plays = min(plays or cf.DEFAULT_PLAYS, cf.DEFAULT_PLAYS)
    # the centre grid is kept: it bends the slope as a part on the absolute position does, and a
    # part profiled on another grid is another part (birch35's saturation: 26.0 um on 3 nodes,
    # 28.4 um on 5; docs/model-family.md 6.2bo)
    nodes = cf.member_nodes(chosen)
    fitted = cf.member_name(
        law,
        driver,
        None if plays == cf.DEFAULT_PLAYS else plays,
        None if nodes == cf.GP_NODES else nodes,
        cf.member_after_effect(chosen),
    )
    fits: dict[str, tuple[float, float]] = {}
    # the profiles refit the member through slightly different parts: a Bouc-Wen law starts from
    # the first fit's rates instead of searching them again (the costliest part of its fit), and
    # an after-effect is searched on the first fit and held there
    first_law: BoucWenParams | DomainWallParams | None = None
    after_effect: AfterEffect | bool = cf.member_after_effect(chosen)

    def fit(trial: dict[str, dict[str, float]], fit_lag: bool = True) -> tuple[float, float]:
        nonlocal first_law, after_effect
        key = json.dumps([trial, fit_lag], sort_keys=True)
        if key not in fits:
            data = _frame_session(
                experiments_through(experiments, trial), ramp_v_per_s, rest_voltage_v, one_sensor=one_sensor
            )
            train = cf.holdout_mask(data.n_experiments)
            try:
                f = cf.fit_family(
                    data,
                    law,
                    train=train,
                    plays=plays,
                    n_nodes=nodes,
                    creep_driver=driver,
                    fit_lag=fit_lag,
                    start=first_law,
                    after_effect=after_effect,
                )
                fits[key] = (f.rms_um, f.heldout_rms_um)
                if first_law is None and isinstance(f.params.hysteresis, BoucWenParams | DomainWallParams):
                    first_law = f.params.hysteresis
                if after_effect is True and f.params.after_effect is not None:
                    after_effect = f.params.after_effect
            except (CalibrationError, ModelError):
                fits[key] = (math.inf, math.inf)
        return fits[key]

    def train_rms(trial: dict[str, dict[str, float]]) -> float:
        return fit(trial)[0]

    effects, notes = refine_findings(
        adoption.effects,
        train_rms,
        lambda trial: fit(trial, fit_lag=False)[0],
        model=fitted,
        sensor_model=f"{fitted} without a drive lag of its own",
    )
    floor = experiments_noise_floor(experiments) if floor_um is None else floor_um
    probed, probe_notes = probe_parts(effects, train_rms, experiments, model=fitted, floor_um=floor)
    if probe_notes:
        added = [e for e in probed if e not in effects]
        effects, refined_notes = refine_parts(probed, train_rms, fitted, only=added)
        notes += probe_notes + refined_notes
    effects, joint_notes = refine_jointly(effects, train_rms, experiments, model=fitted, floor_um=floor)
    notes += joint_notes
    kept, left_out = prune_parts(effects, lambda trial: fit(trial)[1], model=fitted, floor_um=floor)
    heldout = fit(kept)[1]
    if not notes and not left_out:
        return adoption, [], heldout
    gone = set(effects) - set(kept)
    notes = [n for n in notes if n.split(":", 1)[0] not in gone]
    effects = kept
    skipped = adoption.skipped + tuple(f"{line} (left out)" for line in left_out)
    return dataclasses.replace(adoption, effects=effects, skipped=skipped), notes, heldout


def _audit_here(
    frame_path: Path,
    axis: AxisName,
    chosen: ThesisFit,
    base: ScannerConfig,
    ramp_v_per_s: float,
    rest_voltage_v: float,
    placement_path: Path | None = None,
    rate_hz: float | None = None,
) -> ThesisFit:
    from piezod.extensions import session_origin_unix_s

    exps = read_experiments([frame_path], axis=axis)
    placement = None if placement_path is None else read_placement(placement_path, base, axis, rate_hz)
    return audit_and_extend(
        exps,
        axis,
        chosen,
        base,
        ramp_v_per_s,
        rest_voltage_v,
        since_unix_s=session_origin_unix_s(frame_path),
        placement=placement,
    )


def read_placement(
    path: Path, config: ScannerConfig, axis: AxisName, rate_hz: float | None = None
) -> tuple[Experiment, PlacementProgram]:
    """The lag placement experiment recorded in ``path`` (:func:`run_placement`) and its program
    on ``config``'s limits at ``rate_hz`` (default the config's sample rate).

    Raises
    ------
    CalibrationError
        The recording holds no experiment labelled :data:`piezod.lag_placement.PLACEMENT_LABEL`.
    """
    from piezod.lag_placement import PLACEMENT_LABEL, program_for

    found = [e for e in read_experiments([path], axis=axis) if e.label == PLACEMENT_LABEL]
    if not found:
        raise CalibrationError(f"{path}: no experiment {PLACEMENT_LABEL!r} of axis {axis}")
    return found[0], program_for(config, axis, rate_hz or config.sample_rate_hz)


@dataclass(frozen=True, slots=True)
class VerifiedFigures:
    """What the verification reads from one scan's readback (all in %, nan when not estimated).

    Attributes
    ----------
    nonlinearity_pct, length_error_pct
        (4.16) and (4.15).
    noise_pct
        The sensor's white noise alone as a nonlinearity (:func:`piezod.linearity.noise_pct`).
    pixel_nonlinearity_pct, pixel_noise_pct
        (4.16) of the line-averaged profile at the image's pixels and what noise alone leaves in
        it (:func:`piezod.linearity.pixel_profile`): the scan's nonlinearity as an image reads it,
        below a noisy sensor's (4.16).
    clipped
        The axis's readings at the sensor's full scale in the recording (0 when none was given).
    """

    nonlinearity_pct: float
    length_error_pct: float
    noise_pct: float
    pixel_nonlinearity_pct: float
    pixel_noise_pct: float
    clipped: int = 0


def verified_linearity(
    path: Path, axis: AxisName, sensor: SensorPath | None = None, full_scale_um: float | None = None
) -> VerifiedFigures:
    """The figures of the first experiment of ``axis`` in ``path`` (:class:`VerifiedFigures`), the
    readback aligned through ``sensor`` (the axis's sensor path) when given, and with
    ``full_scale_um`` the count of the axis's readings at the sensor's full scale (one parse of
    the recording for both)."""
    exps = read_experiments([path], axis=axis)
    clipped = 0 if full_scale_um is None else sum(readback_clipped(exps, full_scale_um).values())
    if sensor is not None:
        from piezod.extensions import experiments_through_sensor

        exps = experiments_through_sensor(exps, sensor)
    e = linearity(exps).experiments[0]
    nl, le = float(e.nonlinearity_pct), float(e.length_error_pct)
    return VerifiedFigures(
        nonlinearity_pct=nl,
        length_error_pct=le,
        noise_pct=noise_pct(exps[0].position_um, e.trace.nominal_range_um * (1.0 + le / 100.0)),
        pixel_nonlinearity_pct=float(e.pixel_nonlinearity_pct),
        pixel_noise_pct=float(e.pixel_noise_pct),
        clipped=clipped,
    )


def _frame_end_here(path: Path, axis: AxisName) -> tuple[float, float]:
    return frame_end(read_recording(path), axis)


def _check_points_here(
    config: ScannerConfig, points: list[VerifyPoint], axis: AxisName, start: tuple[float, float] | None
) -> list[VerifyPoint]:
    start_v, start_um = (None, None) if start is None else start
    return check_points(config, points, axis=axis, start_v=start_v, start_um=start_um)


def _synth_here(path: Path) -> None:
    from piezod.recording import write_recording
    from piezod.synth import MEDIUM_TUBE, calibration_plan, synth_session

    plan = calibration_plan([180.0, 280.0, 380.0], [0.2, 0.5, 1.0, 2.0], [0.0])
    session = synth_session(MEDIUM_TUBE, plan, samples_per_loop=1024, seed=0)
    write_recording(path, session.recording)


#: Niceness added to the analysis worker: on a machine short of cores the streaming threads of the
#: daemon's process (and a simulator beside it) get the CPU first, the fits wait.
WORKER_NICENESS = 5


def _worker_init(parent_pid: int) -> None:
    if hasattr(os, "nice"):
        os.nice(WORKER_NICENESS)
    threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), name="orphan-watch", daemon=True).start()


def _exit_when_orphaned(parent_pid: int) -> None:
    # A parent killed outright (SIGKILL, an OOM kill) cannot stop its worker, which would go on
    # fitting for minutes on a core the restarted daemon's streaming needs; nothing it computes
    # has anywhere to go.
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    os._exit(1)


def _niceness() -> int:
    return os.nice(0) if hasattr(os, "nice") else 0


class AnalysisWorker:
    """A persistent worker process for the CPU-heavy analysis a daemon process must not run.

    Fits and the reading of long recordings hold the GIL for hundreds of ms at a time (a
    341 ms stall was measured reading a 320k-row recording), enough to starve the streaming
    and heartbeat threads (the board's watchdog fired). They run in one ``spawn``-ed process
    (no fork of a threaded process) that lives as long as this object.
    """

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=1, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
        )

    def niceness(self) -> int:
        """The worker process's scheduling niceness (POSIX; 0 elsewhere)."""
        return self._pool.submit(_niceness).result()

    def fit_thesis(self, frame_path: Path, base: ScannerConfig, axis: AxisName = "x") -> ThesisFit:
        """Fit the thesis model (3.8) to the frame recording."""
        return self._pool.submit(_fit_thesis_here, frame_path, axis, base).result()

    def fit_dynamic(
        self,
        frame_path: Path,
        base: ScannerConfig,
        axis: AxisName,
        *,
        ramp_v_per_s: float,
        rest_voltage_v: float,
    ) -> ThesisFit:
        """Fit the time-domain model (``model: dynamic``) to the frame recording of a session.

        ``base`` should already hold the fitted thesis parameters (they are kept); the ramp
        rate and the rest voltage let the fit rebuild the unrecorded stretches of the session.
        """
        return self._pool.submit(
            _fit_dynamic_here, frame_path, axis, base, ramp_v_per_s, rest_voltage_v
        ).result()

    def choose_model(
        self,
        frame_path: Path,
        base: ScannerConfig,
        axis: AxisName,
        *,
        ramp_v_per_s: float,
        rest_voltage_v: float,
    ) -> ThesisFit:
        """Fit the model family and choose the model (family laws, ``base``'s dynamic model) that
        predicts held-out experiments of the frame best; the returned config uses it.

        ``fit_error_pct`` of the result holds the chosen model's held-out RMS in um.
        """
        return self._pool.submit(_choose_here, frame_path, axis, base, ramp_v_per_s, rest_voltage_v).result()

    def audit_and_extend(
        self,
        frame_path: Path,
        chosen: ThesisFit,
        base: ScannerConfig,
        axis: AxisName,
        *,
        ramp_v_per_s: float,
        rest_voltage_v: float,
        placement_path: Path | None = None,
        rate_hz: float | None = None,
    ) -> ThesisFit:
        """:func:`audit_and_extend` on the frame recording (in the worker process), with the lag
        placement experiment in ``placement_path`` (played at ``rate_hz``) when given."""
        return self._pool.submit(
            _audit_here, frame_path, axis, chosen, base, ramp_v_per_s, rest_voltage_v, placement_path, rate_hz
        ).result()

    def refresh(
        self,
        frame_path: Path,
        config: ScannerConfig,
        axis: AxisName,
        chosen: str,
        *,
        history: Sequence[Path] = (),
        ramp_v_per_s: float,
        rest_voltage_v: float,
        one_sensor: bool = False,
    ) -> Refresh:
        """:func:`refresh_member` on the frame played again, after the recordings in ``history``
        (in the worker process)."""
        return self._pool.submit(
            _refresh_here,
            frame_path,
            list(history),
            axis,
            config,
            chosen,
            ramp_v_per_s,
            rest_voltage_v,
            one_sensor,
        ).result()

    def linearity(
        self,
        path: Path,
        axis: AxisName = "x",
        sensor: SensorPath | None = None,
        full_scale_um: float | None = None,
    ) -> VerifiedFigures:
        """:func:`verified_linearity` in the worker process: parsing a verification scan's recording
        holds the interpreter (a 0.02 Hz line of 20 MB: 1.1 s, with other threads stalled for up to
        270 ms, beyond the daemon's 150 ms lead)."""
        return self._pool.submit(verified_linearity, path, axis, sensor, full_scale_um).result()

    def frame_in_sensor_range(
        self, frame_path: Path, frame: Frame, full_scale_um: float, out_path: Path
    ) -> tuple[Path, Frame, dict[str, int]]:
        """:func:`frame_in_sensor_range` in the worker process (it parses the whole frame recording:
        3.2 s for 66 MB, other threads stalled for up to 250 ms at a time)."""
        return self._pool.submit(frame_in_sensor_range, frame_path, frame, full_scale_um, out_path).result()

    def check_points(
        self,
        config: ScannerConfig,
        points: Sequence[VerifyPoint],
        axis: AxisName = "x",
        start: tuple[float, float] | None = None,
    ) -> list[VerifyPoint]:
        """:func:`check_points` in the worker process (a whole-scan rendering must not hold the
        daemon's GIL), from ``start`` (voltage, measured position: :func:`frame_end`) when given."""
        return self._pool.submit(_check_points_here, config, list(points), axis, start).result()

    def frame_end(self, frame_path: Path, axis: AxisName = "x") -> tuple[float, float]:
        """:func:`frame_end` of the frame recording, read in the worker process: parsing a frame of
        a few hundred MB holds the interpreter for seconds, which starved the engine's streaming
        thread past its lead (an underrun at the built-in stage's 1 s lead, twice)."""
        return self._pool.submit(_frame_end_here, frame_path, axis).result()

    def synth_frame(self, path: Path) -> None:
        """Write a synthetic 12-experiment calibration session (for benchmarks) to ``path``."""
        self._pool.submit(_synth_here, path).result()

    def close(self) -> None:
        """Stop the worker process."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> AnalysisWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """A table like thesis tables 4.3 / 4.4; ``pixels %``: (4.16) of the line-averaged profile at
    the image's pixels (:class:`VerifiedFigures`); ``tracked %``: the sensitivity the daemon's
    tracker had learnt by the end of the point, relative to the model (the stage's drift since the
    frame)."""
    head = (
        f"{'model':<8} {'range um':>9} {'f Hz':>7} {'offset um':>9} {'frame':>7} "
        f"{'nonlin %':>9} {'pixels %':>9} {'length %':>9} {'tracked %':>9}  what"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        nl = "-" if r.get("nonlinearity_pct") is None else f"{r['nonlinearity_pct']:.3f}"
        px = "-" if r.get("pixel_nonlinearity_pct") is None else f"{r['pixel_nonlinearity_pct']:.3f}"
        le = "-" if r.get("length_error_pct") is None else f"{r['length_error_pct']:+.3f}"
        tr = "-" if r.get("tracked_scale") is None else f"{100.0 * (r['tracked_scale'] - 1.0):+.3f}"
        inside = "inside" if r["inside_frame"] else "outside"
        what = r["what"] + (f" (skipped: {r['skipped']})" if r.get("skipped") else "")
        if r.get("retried_after"):
            what += f" (measured again after a fault: {'; '.join(r['retried_after'])})"
        if r.get("faults_before"):
            what += f" (fault before this point, cleared: {'; '.join(r['faults_before'])})"
        if r.get("placement"):
            what += f" ({r['placement']})"
        noise = r.get("noise_pct")
        if noise is not None and r.get("nonlinearity_pct") and noise >= 0.5 * r["nonlinearity_pct"]:
            what += f" (the sensor's noise alone: {noise:.3f} %"
            px_noise = r.get("pixel_noise_pct")
            if px_noise is not None and r.get("pixel_nonlinearity_pct"):
                what += f"; at the pixels {px_noise:.3f} %"
            what += ")"
        lines.append(
            f"{r['model']:<8} {r['range_um']:9.3g} {r['frequency_hz']:7.3g} {r['offset_um']:9.3g} "
            f"{inside:>7} {nl:>9} {px:>9} {le:>9} {tr:>9}  {what}"
        )
    return "\n".join(lines)


#: The tracker's share (%) beyond which the verification says how much of the gain it took.
TRACKER_NOTE_PCT = 0.1


def tracker_note(rows: Sequence[dict[str, Any]], model: str) -> str | None:
    """One line when the daemon's sensitivity tracker moved ``model``'s sensitivity by more than
    :data:`TRACKER_NOTE_PCT` during the verification (else None).

    The verification's figures are the online correction's, tracker included: a calibration whose
    gain is 0.4 % off can verify inside 0.1 % once the tracker has learnt it (crest18, session 25,
    docs/model-family.md 6.2s). The tracker's share is the sum of that error and of the stage's
    drift since the frame (a warming stage, the time the fits took); the verification cannot tell
    them apart, so the line says both.
    """
    scales = [
        float(r["tracked_scale"]) for r in rows if r["model"] == model and r.get("tracked_scale") is not None
    ]
    if not scales:
        return None
    worst = max((100.0 * (s - 1.0) for s in scales), key=abs)
    if abs(worst) <= TRACKER_NOTE_PCT:
        return None
    return (
        f"the sensitivity tracker moved {model}'s sensitivity by up to {worst:+.3f} % during the "
        "verification; the figures include that correction: the calibrated gain is off by about "
        "as much, or the stage drifted since the frame (warming, the time the fits took)"
    )


def tracker_far_off_note(rows: Sequence[dict[str, Any]], model: str) -> str | None:
    """One line when the daemon's sensitivity tracker set aside lines of ``model``'s verification
    as too far off to be a drift (else None).

    The tracker follows a drift of the sensitivity, a few per cent at most; a line whose length is
    off by more than its ``outlier`` bound (5 %) is taken for a fault and not followed. When a
    verification's lines are that far off, the model is wrong (birch35's first run, session 36:
    every line 6-25 % long, the tracker at +0.000), and the table's tracked 0 must not read as "no
    drift".
    """
    counts = [r["tracker_lines"] for r in rows if r["model"] == model and r.get("tracker_lines")]
    far = sum(c["far_off"] for c in counts)
    if far == 0:
        return None
    seen = sum(c["far_off"] + c["used"] for c in counts)
    return (
        f"the sensitivity tracker set aside {far} of the {seen} lines of {model}'s verification it "
        "was given as too far off to be a drift of the sensitivity; it corrected none of that error"
    )


#: Inside its own frame, a written model whose verified lines are off by more than this much in
#: length (%) or (4.16) is wrong, not merely short of a target: the calibration says so loudly.
WRONG_LENGTH_PCT = 1.0
WRONG_NONLINEARITY_PCT = 0.5


def wrong_model_warning(rows: Sequence[dict[str, Any]], model: str) -> str | None:
    """A warning when ``model`` verified grossly off inside the frame it was calibrated on (more
    than :data:`WRONG_LENGTH_PCT` in length or :data:`WRONG_NONLINEARITY_PCT` in (4.16)), else
    None. The figures are what the lab's images would show."""
    inside = [
        r for r in rows if r["model"] == model and r["inside_frame"] and r.get("length_error_pct") is not None
    ]
    worse = []
    length = max((float(r["length_error_pct"]) for r in inside), key=abs, default=0.0)
    if abs(length) > WRONG_LENGTH_PCT:
        worse.append(f"length error {length:+.3f} %")
    nonlin = max((float(r["nonlinearity_pct"]) for r in inside), default=0.0)
    if nonlin > WRONG_NONLINEARITY_PCT:
        worse.append(f"nonlinearity {nonlin:.3f} %")
    if not worse:
        return None
    return (
        f"the written model ({model}) scans inside its own calibration frame with up to "
        f"{' and '.join(worse)}: the model is wrong for this stage (its images would be that far "
        "off); do not use it unchecked: look at the audit above, measure the frame again"
    )


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Worst figures per model, inside and outside the frame: (4.16) as read, (4.16) of the
    line-averaged profile at the image's pixels (:class:`VerifiedFigures`), |(4.15)|."""
    out: dict[str, dict[str, float | None]] = {}
    for model in sorted({r["model"] for r in rows}):
        for inside in (True, False):
            sel = [
                r
                for r in rows
                if r["model"] == model
                and r["inside_frame"] == inside
                and r.get("nonlinearity_pct") is not None
            ]
            key = f"{model}_{'inside' if inside else 'outside'}"
            px = [r["pixel_nonlinearity_pct"] for r in sel if r.get("pixel_nonlinearity_pct") is not None]
            out[key] = {
                "max_nonlinearity_pct": max((r["nonlinearity_pct"] for r in sel), default=None),
                "max_pixel_nonlinearity_pct": max(px, default=None),
                "max_abs_length_error_pct": max((abs(r["length_error_pct"]) for r in sel), default=None),
            }
    return out


def plot_verification(rows: Sequence[dict[str, Any]], path: Path) -> Path:
    """Bar plot of nonlinearity and length error per verification scan and model (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = verification_figure(rows)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def verification_figure(rows: Sequence[dict[str, Any]]) -> Any:
    """The figure of :func:`plot_verification` (a matplotlib ``Figure``)."""
    import matplotlib.pyplot as plt

    models = sorted({r["model"] for r in rows})
    pts = [r for r in rows if r["model"] == models[0]]
    labels = [f"{r['range_um']:g} um\n{r['frequency_hz']:g} Hz\n{r['offset_um']:+g} um" for r in pts]
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 1.1 * len(pts)), 6.5), sharex=True)
    width = 0.8 / len(models)
    x = np.arange(len(pts))
    for k, model in enumerate(models):
        sel = [r for r in rows if r["model"] == model]
        nl = [math.nan if r.get("nonlinearity_pct") is None else r["nonlinearity_pct"] for r in sel]
        le = [math.nan if r.get("length_error_pct") is None else r["length_error_pct"] for r in sel]
        px = [r.get("pixel_nonlinearity_pct") for r in sel]
        px = [math.nan if v is None else v for v in px]
        axes[0].bar(x + k * width, nl, width, label=model)
        axes[0].plot(
            x + k * width, px, "k_", ms=12, mew=2, label="line-averaged at the pixels" if k == 0 else None
        )
        axes[1].bar(x + k * width, le, width, label=model)
    outside = [i for i, r in enumerate(pts) if not r["inside_frame"]]
    for i in outside:
        for a in axes:
            a.axvspan(i - 0.45, i + 0.45 + width * (len(models) - 1), color="0.9", zorder=0)
    # Axis limits follow the data; a reference line is drawn only where it lies inside them.
    nl_all = [r["nonlinearity_pct"] for r in rows if r.get("nonlinearity_pct") is not None]
    le_all = [abs(r["length_error_pct"]) for r in rows if r.get("length_error_pct") is not None]
    nl_top = 1.25 * max([*nl_all, 0.05])
    le_lim = 1.25 * max([*le_all, 0.05])
    axes[0].set_ylabel("nonlinearity (% of range)")
    axes[0].set_ylim(0.0, nl_top)
    if nl_top > 0.2:
        axes[0].axhline(0.2, color="k", ls=":", lw=0.8, label="one pixel of 512 (0.2 %)")
    axes[0].axhline(0.05, color="g", ls="--", lw=0.8, label="target in frame (0.05 %)")
    axes[1].set_ylabel("length error (% of range)")
    axes[1].set_ylim(-le_lim, le_lim)
    axes[1].axhline(0.0, color="k", lw=0.8)
    if le_lim > 1.0:
        for y in (-1.0, 1.0):
            axes[1].axhline(y, color="r", ls=":", lw=0.8, label="+-1 %" if y > 0 else None)
    axes[1].set_xticks(x + width * (len(models) - 1) / 2, labels, fontsize=7)
    axes[1].set_xlabel("verification scan: range, line rate, offset")
    axes[0].legend()
    title = "Online correction on the stage: linearity of verification scans per model"
    if outside:
        title += "\n(grey: outside the calibration frame)"
    axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def frame_summary(frame: Frame) -> str:
    """One line describing the frame."""
    (r0, r1), (f0, f1), (o0, o1) = frame.ranges_v, frame.frequencies_hz, frame.offsets_v
    offsets = f"offset {o0:+g} V" if o0 == o1 else f"offsets {o0:+g}..{o1:+g} V"
    return (
        f"{len(frame.scans)} scans on {frame.axis}: {r0:g}-{r1:g} V p-p, {f0:g}-{f1:g} Hz, "
        f"{offsets}, ~{frame.duration_s:.0f} s"
    )
