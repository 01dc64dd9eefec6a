"""Calibration without a position sensor: the scanner model fitted from images of a reference.

The thesis calibrated its sensorless tube scanners from trace / retrace images of length
standards recorded while the voltage range and line rate changed (chapter 2, section 3.2). This
module does that, through the model helper's public fitters (:mod:`piezod.calibrate`,
:mod:`piezod.calibrate_dynamic`), with the flanks of a line pattern of known pitch ``P`` in place
of the sensor:

1. **Frame** (:func:`default_image_frame`, :func:`run_image_frame`): uncorrected raster scans of
   the reference (plain voltage triangles) at several ranges, line rates and offsets, one
   recording each, in one session; the first ``skip_lines`` lines of every scan settle.
2. **Flanks** (:func:`flank_events`): in the trace and retrace images on the commanded grid, the
   flanks (:func:`piezod.image_linearity.find_flanks`); each flank's commanded coordinate gives
   its time in its line and so the voltage at which the tip crossed it. Its true position is
   ``k P`` plus unknowns: the sample's position (one per scan) and the line width (the falling
   flanks sit ``w`` after the rising ones). The period numbers ``k`` are made consistent across
   the half lines of a scan by continuity at every turning point: both half lines' flank
   positions, extrapolated linearly in time to the turn, must meet (to within ``P / 2``).
3. **Thesis model (3.8)** (:func:`fit_thesis_from_flanks`): the flanks of each scan and family are
   one experiment of :class:`piezod.calibrate.CalibrationData` (the steady loop is a function of
   ``V``, so sparse points fit it as dense ones do); the per-experiment offsets absorb the unknowns
   and give the line width ``w``.
4. **Dynamic model** (:func:`fit_dynamic_from_flanks`): the session is laid out by
   :func:`piezod.calibrate_dynamic.prepare_dynamic` from the recorded voltages; the compared
   samples are replaced by the grid samples nearest to the flanks, their positions the flank
   positions (falling flanks moved by ``w``) shifted by the local velocity times the time
   difference (a fraction of a grid step).

5. **Polarity** (:func:`search_polarity`): a partially depoled ceramic moves less per volt below
   0 V; no hysteresis law bends at a fixed voltage, so after the choice of model the runtime
   part's value is profiled on the flanks (the images pin the kink: it sits at 0 V of the drive),
   the choice redone through it and the value refined on the new member. The position-side parts
   are not searched: the family's static map takes a stiffness, and the flank positions are known
   only up to an offset per scan.

The position column of the recordings is never read. On the simulator the hidden truth (the
board's ``--truth-log``) checks the result: :func:`with_truth` puts the true positions into a
recording, whose sensor-path linearity (:mod:`piezod.linearity`) stands beside the image metrics.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from piezod.calibrate import CalibrationData, CalibrationResult, fit, model_positions
from piezod.calibrate_data import MAX_PREROLL_LOOPS
from piezod.calibrate_dynamic import (
    DynamicCalibrationData,
    DynamicCalibrationResult,
    fit_dynamic,
    prepare_dynamic,
)
from piezod.errors import CalibrationError, ModelError, RecordingError
from piezod.image import F64, Geometry, assemble, geometry, raster_samples
from piezod.image_linearity import find_flanks
from piezod.model.params import ThesisParams
from piezod.recording import Experiment, Recording, infer_scan

if TYPE_CHECKING:
    from piezod.calibrate_family import FamilyFit, ModelChoice
    from piezod.config import ScannerConfig

_CONTINUITY_FLANKS = 4
#: Faults that mean the stream broke during a scan (the scan is repeated).
_STREAM_FAULTS = frozenset(
    {"STREAM", "STREAM_END", "UNDERRUN", "WATCHDOG", "LINKDOWN", "LINKLOST", "RESTART"}
)
#: A frame scan's recording is far larger than its header alone.
_MIN_RECORDING_BYTES = 4096


@dataclass(frozen=True, slots=True)
class FlankEvents:
    """The flanks of one raster scan of a line pattern, as (time, voltage, position) events.

    Attributes
    ----------
    label
        The scan (recording) label.
    t_s, voltage_v
        When the tip crossed the flank and the fast-axis voltage then.
    direction
        +1 trace, -1 retrace.
    position_um
        ``k P``: the flank's position on the sample up to the scan's offset (and ``w`` for the
        falling family).
    velocity_um_per_s
        Local scan velocity (from the neighbouring flanks of the family in the half line).
    family
        +1 rising, -1 falling flank.
    line
        Image line.
    """

    label: str
    t_s: F64
    voltage_v: F64
    direction: NDArray[np.int8]
    position_um: F64
    velocity_um_per_s: F64
    family: NDArray[np.int8]
    line: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.t_s.size)

    def select(self, keep: NDArray[np.bool_]) -> FlankEvents:
        """The events where ``keep``."""
        return FlankEvents(
            self.label,
            self.t_s[keep],
            self.voltage_v[keep],
            self.direction[keep],
            self.position_um[keep],
            self.velocity_um_per_s[keep],
            self.family[keep],
            self.line[keep],
        )


def _extrapolate(t: F64, x: F64, t0: float) -> float:
    """Position at ``t0`` from the flanks nearest to it: a parabola in time (a line for fewer)."""
    if t.size == 1:
        return float(x[0])
    deg = 2 if t.size >= 4 else 1
    c = np.polyfit(t - t0, x, deg)
    return float(c[-1])


_Half = tuple[F64, NDArray[np.int64], F64, F64, F64]


def _align_lines(halves: dict[tuple[int, int], _Half]) -> dict[tuple[int, int], _Half]:
    """Period numbers made consistent across the lines of one scan direction.

    Every line of a direction scans alike, so a flank of the sample lies at nearly the same
    commanded position in every line: each line's numbers are shifted onto those of the line with
    most flanks (the median of the matched differences); flanks matching no flank of that line
    (a particle, a misread edge) are dropped, and so are period numbers that fewer than half the
    lines of the direction show (the line with most flanks may be the one that crosses a
    particle: on the simulated microscope's 14 um scans its bump became a flank 2 um off).
    """
    out = _align_onto_reference(halves)
    for d in (1, -1):
        keys = [key for key in out if key[1] == d]
        seen: dict[int, int] = {}
        for key in keys:
            for k in np.unique(out[key][1]):
                seen[int(k)] = seen.get(int(k), 0) + 1
        need = max(2, math.ceil(0.5 * len(keys)))
        for key in keys:
            ts, ks, vs, xi, t_l = out[key]
            keep = np.array([seen[int(k)] >= need for k in ks], dtype=bool)
            if keep.sum() < 2:
                del out[key]
            elif not keep.all():
                out[key] = (ts[keep], ks[keep], vs[keep], xi[keep], t_l)
    return out


def _align_onto_reference(halves: dict[tuple[int, int], _Half]) -> dict[tuple[int, int], _Half]:
    out: dict[tuple[int, int], _Half] = {}
    for d in (1, -1):
        keys = [key for key in halves if key[1] == d]
        if not keys:
            continue
        ref_key = max(keys, key=lambda key: (halves[key][0].size, key[0]))
        r_xi, r_k = halves[ref_key][3], halves[ref_key][1]
        order = np.argsort(r_xi)
        r_xi, r_k = r_xi[order], r_k[order]
        tol = 0.3 * float(np.median(np.abs(np.diff(r_xi)))) if r_xi.size > 1 else np.inf
        for key in keys:
            ts, ks, vs, xi, t_l = halves[key]
            j = np.clip(np.searchsorted(r_xi, xi), 1, max(1, r_xi.size - 1))
            j = np.where(
                (j - 1 >= 0) & (np.abs(r_xi[j - 1] - xi) < np.abs(r_xi[np.minimum(j, r_xi.size - 1)] - xi)),
                j - 1,
                np.minimum(j, r_xi.size - 1),
            )
            match = np.abs(r_xi[j] - xi) < tol
            if match.sum() < 2:
                continue
            diff = r_k[j[match]] - ks[match]
            shift = int(np.round(np.median(diff)))
            keep = match & (ks + shift == r_k[j])
            if keep.sum() < 2:
                continue
            out[key] = (ts[keep], ks[keep] + shift, vs[keep], xi[keep], t_l)
    return out


def _turn_shift(aligned: dict[tuple[int, int], _Half], pitch_um: float) -> int:
    """The retraces' period-number shift onto the traces: continuity at every turning point.

    At each turn both half lines' flank positions, extrapolated in time to the turn, must meet;
    every turn votes and the most common shift wins.
    """
    votes: list[int] = []
    for (ln, d), (ts, ks, _v, _xi, t_l) in aligned.items():
        if d > 0 and (ln, -1) in aligned:  # trace ln -> retrace ln
            nxt = aligned[(ln, -1)]
            t_turn = float(t_l[-1])
            first, second = (ts, ks), (nxt[0], nxt[1])
            sign = 1
        elif d < 0 and (ln + 1, 1) in aligned:  # retrace ln -> trace ln + 1
            nxt = aligned[(ln + 1, 1)]
            t_turn = float(t_l[-1])
            first, second = (nxt[0], nxt[1]), (ts, ks)
            sign = -1
        else:
            continue
        trace_t, trace_k = first
        re_t, re_k = second
        n = _CONTINUITY_FLANKS
        if sign > 0:
            x_tr = _extrapolate(trace_t[-n:], pitch_um * trace_k[-n:].astype(np.float64), t_turn)
            x_re = _extrapolate(re_t[:n], pitch_um * re_k[:n].astype(np.float64), t_turn)
        else:
            x_tr = _extrapolate(trace_t[:n], pitch_um * trace_k[:n].astype(np.float64), t_turn)
            x_re = _extrapolate(re_t[-n:], pitch_um * re_k[-n:].astype(np.float64), t_turn)
        votes.append(round((x_tr - x_re) / pitch_um))
    if not votes:
        return 0
    values, counts = np.unique(votes, return_counts=True)
    return int(values[np.argmax(counts)])


def flank_events(
    rec: Recording, pitch_um: float, *, skip_lines: int = 2, label: str | None = None
) -> FlankEvents:
    """The flank events of one raster recording of a line pattern (see the module docstring).

    Raises
    ------
    RecordingError
        Not a raster recording with a height channel, or too few flanks.
    """
    geo = geometry(rec)
    rs = raster_samples(rec)
    if rs.z_voltage_v is None:
        raise RecordingError("no 'z_voltage' column: the recording carries no height channel", rec.path)
    tr, re = assemble(rs.target_um, rs.z_voltage_v, rs.line, rs.direction, rs.lines, geo, profile=True)
    # (half-line order, direction) -> flanks; half lines in time order: trace 0, retrace 0, trace 1, ...
    groups: list[tuple[int, int, F64, NDArray[np.int64], NDArray[np.int8], F64, F64, F64]] = []
    for d, img in ((1, tr), (-1, re)):
        fl = find_flanks(img, geo)
        for ln in np.unique(fl.line):
            s = (rs.line == ln) & (rs.direction == d)
            if s.sum() < 4:
                continue
            t_l, x_l, v_l = rs.t_s[s], rs.target_um[s], rs.voltage_v[s]
            order = np.argsort(x_l, kind="stable")
            sel = fl.line == ln
            xi = fl.xi_um[sel]
            t_f = np.interp(xi, x_l[order], t_l[order])
            v_f = np.interp(t_f, t_l, v_l)
            groups.append((int(ln), d, t_f, fl.k[sel], fl.family[sel], v_f, t_l, xi))
    if not groups:
        raise RecordingError(f"no flanks of a line pattern of pitch {pitch_um:g} um found", rec.path)
    groups.sort(key=lambda g: (g[0], -g[1]))
    out_t, out_v, out_d, out_x, out_vel, out_f, out_l = [], [], [], [], [], [], []
    for fam in (1, -1):
        # (line, direction) -> (t, k, v, xi, t_line) of this family, time-ordered
        halves: dict[tuple[int, int], tuple[F64, NDArray[np.int64], F64, F64, F64]] = {}
        for ln, d, t_f, k, f, v_f, t_l, xi in groups:
            s = f == fam
            if s.sum() < 2:
                continue
            order = np.argsort(t_f[s])
            halves[(ln, d)] = (t_f[s][order], k[s][order], v_f[s][order], xi[s][order], t_l)
        aligned = _align_lines(halves)
        shift = _turn_shift(aligned, pitch_um)
        for (ln, d), (ts, ks, vs, _xi, _t_l) in sorted(aligned.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
            if ln < skip_lines or ts.size < 2:
                continue
            x = pitch_um * (ks + (shift if d < 0 else 0)).astype(np.float64)
            out_t.append(ts)
            out_v.append(vs)
            out_d.append(np.full(ts.size, d, dtype=np.int8))
            out_x.append(x)
            out_vel.append(np.gradient(x, ts))
            out_f.append(np.full(ts.size, fam, dtype=np.int8))
            out_l.append(np.full(ts.size, ln, dtype=np.int64))
    if not out_t:
        raise RecordingError(
            f"no flanks after the {skip_lines} settling line(s): record more lines", rec.path
        )
    return FlankEvents(
        label=label or (Path(rec.path).stem if rec.path else "scan"),
        t_s=np.concatenate(out_t),
        voltage_v=np.concatenate(out_v),
        direction=np.concatenate(out_d),
        position_um=np.concatenate(out_x),
        velocity_um_per_s=np.concatenate(out_vel),
        family=np.concatenate(out_f),
        line=np.concatenate(out_l),
    )


def _x_rows(rec: Recording) -> NDArray[np.bool_]:
    return np.ones(len(rec), dtype=bool) if rec.axis is None else rec.axis == "x"


def thesis_data(recs: Sequence[Recording], events: Sequence[FlankEvents]) -> CalibrationData:
    """:class:`piezod.calibrate.CalibrationData` of the flanks: one experiment per scan and family."""
    vs, ds, xs, starts, vmin, vmax, freq, labels, paths, loops = [], [], [], [], [], [], [], [], [], []
    n = 0
    for rec, ev in zip(recs, events, strict=True):
        sel = _x_rows(rec)
        info = infer_scan(rec.t_s[sel], rec.voltage_v[sel])
        if not info.is_scan:
            raise RecordingError(f"the voltage is not a periodic triangular scan ({info.reason})", rec.path)
        for fam in (1, -1):
            s = ev.family == fam
            if s.sum() < 8:
                continue
            starts.append(n)
            vs.append(ev.voltage_v[s])
            ds.append(ev.direction[s].astype(np.float64))
            xs.append(ev.position_um[s])
            n += int(s.sum())
            vmin.append(info.v_min)
            vmax.append(info.v_max)
            freq.append(info.frequency_hz)
            labels.append(f"{ev.label}:{'rising' if fam > 0 else 'falling'}")
            paths.append(rec.path)
            loops.append(int(info.n_loops))
    if not starts:
        raise CalibrationError("too few flanks in the calibration frame")
    return CalibrationData(
        voltage_v=np.concatenate(vs),
        direction=np.concatenate(ds),
        position_um=np.concatenate(xs),
        starts=np.asarray(starts, dtype=np.intp),
        v_min=np.asarray(vmin),
        v_max=np.asarray(vmax),
        frequency_hz=np.asarray(freq),
        labels=tuple(labels),
        axes=tuple("x" for _ in labels),
        paths=tuple(paths),
        n_loops=tuple(loops),
    )


@dataclass(frozen=True, slots=True)
class ThesisFromFlanks:
    """The thesis model fitted to the flanks, and the line width it implies per scan (um)."""

    result: CalibrationResult
    line_width_um: dict[str, float]


def fit_thesis_from_flanks(
    recs: Sequence[Recording], events: Sequence[FlankEvents], *, start: ThesisParams | None = None
) -> ThesisFromFlanks:
    """Fit (3.8) to the flanks of the frame (one offset per scan and flank family)."""
    data = thesis_data(recs, events)
    result = fit(data, start=start)
    model = model_positions(data, result.params)
    widths: dict[str, float] = {}
    offsets: dict[str, float] = {}
    for i, label in enumerate(data.labels):
        a = int(data.starts[i])
        b = int(data.starts[i + 1]) if i + 1 < data.n_experiments else data.voltage_v.size
        offsets[label] = float(np.mean(data.position_um[a:b] - model[a:b]))
    for ev in events:
        r, f = offsets.get(f"{ev.label}:rising"), offsets.get(f"{ev.label}:falling")
        if r is not None and f is not None:
            widths[ev.label] = r - f
    return ThesisFromFlanks(result, widths)


def merged_positions(ev: FlankEvents, line_width_um: float) -> F64:
    """Flank positions with the falling family moved onto the rising family's offset."""
    out: F64 = np.where(ev.family < 0, ev.position_um + line_width_um, ev.position_um)
    return out


def timed_layout(
    recs: Sequence[Recording],
    events: Sequence[FlankEvents],
    *,
    slew_rate_v_per_s: float = 2000.0,
    rest_voltage_v: float = 0.0,
    max_samples_per_loop: int = 2048,
    settle_lines: int | None = None,
) -> DynamicCalibrationData:
    """The frame's layout for :func:`flank_session` (same arguments) with every compared grid
    sample's recorded time in place of its position."""
    exps = []
    for rec, ev in zip(recs, events, strict=True):
        sel = _x_rows(rec)
        t = rec.t_s[sel]
        exps.append(
            Experiment(label=ev.label, axis="x", t_s=t, voltage_v=rec.voltage_v[sel], position_um=t.copy())
        )
    return prepare_dynamic(
        exps,
        max_samples_per_loop=max_samples_per_loop,
        max_samples_per_experiment=1 << 16,
        slew_rate_v_per_s=slew_rate_v_per_s,
        rest_voltage_v=rest_voltage_v,
        max_preroll_loops=MAX_PREROLL_LOOPS if settle_lines is None else settle_lines,
        hold_before_move=settle_lines is not None,
    )


def flank_session(
    recs: Sequence[Recording],
    events: Sequence[FlankEvents],
    line_width_um: dict[str, float],
    *,
    slew_rate_v_per_s: float = 2000.0,
    rest_voltage_v: float = 0.0,
    max_samples_per_loop: int = 2048,
    settle_lines: int | None = None,
) -> DynamicCalibrationData:
    """The session of a frame recorded in one session, compared at the flanks (module docstring, 4).

    The layout is :func:`piezod.calibrate_dynamic.prepare_dynamic`'s (so every fitter of the
    session works on it: the dynamic model, the model family of :mod:`piezod.calibrate_family`);
    the compared samples are the grid samples nearest the flanks, their positions the flank
    positions. ``settle_lines``: the recordings are the daemon's raster scans, which hold where
    the previous scan ended, move to the start and scan that many unrecorded lines first
    (:data:`piezod.trajectory.SETTLE_LINES`); the gaps are reconstructed so (on the simulated
    Prandtl-Ishlinskii microscope the fit with the truth in place of the flanks left 10 nm with
    the default reconstruction, up to eight settling loops after a hold at the next start, and
    2.6 nm with this one: voltage-driven creep remembers where the stage held). ``None``: the
    default reconstruction of :func:`~piezod.calibrate_data.prepare_dynamic`. Each scan's rising
    and falling flanks are two offset groups
    (:attr:`~piezod.calibrate_data.DynamicCalibrationData.offset_group`): the fits eliminate the
    sample's position per family, so an error of the thesis fit's line width (``line_width_um``
    only moves the falling family) does not enter them.
    """
    data = timed_layout(
        recs,
        events,
        slew_rate_v_per_s=slew_rate_v_per_s,
        rest_voltage_v=rest_voltage_v,
        max_samples_per_loop=max_samples_per_loop,
        settle_lines=settle_lines,
    )
    by_label = {ev.label: ev for ev in events}
    compared, positions, starts, counts, groups = [], [], [], [], []
    n = 0
    for i, layout in enumerate(data.experiments):
        ev = by_label[layout.label]
        a, c = int(data.starts[i]), int(data.counts[i])
        t_cmp = data.position_um[a : a + c]  # the placeholder: each compared sample's recorded time
        j = np.clip(np.searchsorted(t_cmp, ev.t_s), 1, c - 1)
        j = np.where(np.abs(t_cmp[j - 1] - ev.t_s) < np.abs(t_cmp[j] - ev.t_s), j - 1, j)
        x = merged_positions(ev, line_width_um.get(ev.label, 0.0))
        x = x + ev.velocity_um_per_s * (t_cmp[j] - ev.t_s)
        j, first = np.unique(j, return_index=True)
        compared.append(data.compared[a + j])
        positions.append(x[first])
        groups.append(2 * i + (ev.family[first] < 0).astype(np.intp))
        starts.append(n)
        counts.append(int(j.size))
        n += int(j.size)
    return dataclasses.replace(
        data,
        compared=np.concatenate(compared),
        position_um=np.concatenate(positions),
        starts=np.asarray(starts, dtype=np.intp),
        counts=np.asarray(counts, dtype=np.intp),
        offset_group=np.concatenate(groups),
    )


def drop_outlier_flanks(
    data: DynamicCalibrationData, model_um: F64, *, sigmas: float = 5.0
) -> tuple[DynamicCalibrationData, int]:
    """The session without the flanks a first model misses by more than ``sigmas`` robust
    standard deviations (dust, a misread edge), and how many were dropped.

    ``model_um`` are a model's positions at the compared samples; the residuals are taken with
    the offsets of the session's offset groups removed (the sample's unknown position).
    """
    from piezod.calibrate_dynamic import _centre

    resid = _centre(data, model_um) - _centre(data, data.position_um)
    mad = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    keep = np.abs(resid) <= sigmas * max(mad, 1e-6)
    if keep.all():
        return data, 0
    exp_of_row = np.repeat(np.arange(data.n_experiments), data.counts)
    counts = np.bincount(exp_of_row[keep], minlength=data.n_experiments).astype(np.intp)
    if (counts < 2).any():
        return data, 0
    starts = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.intp)
    out = dataclasses.replace(
        data,
        compared=data.compared[keep],
        position_um=data.position_um[keep],
        starts=starts,
        counts=counts,
        offset_group=None if data.offset_group is None else data.offset_group[keep],
    )
    return out, int((~keep).sum())


def frame_flank_session(
    paths: Sequence[Path], pitch_um: float, base: ScannerConfig
) -> tuple[list[Recording], list[FlankEvents], ThesisFromFlanks, DynamicCalibrationData]:
    """A recorded image frame as ``piezod calibrate --from-images`` fits it: the recordings, their
    flanks (labelled by file stem), the thesis fit from the flanks (its line widths) and the flank
    session of the daemon's rasters (:func:`flank_session` with the settling lines)."""
    from piezod.recording import read_recording
    from piezod.trajectory import SETTLE_LINES

    recs = [read_recording(p) for p in paths]
    events = [flank_events(r, pitch_um, label=Path(p).stem) for r, p in zip(recs, paths, strict=True)]
    ax = base.axes["x"]
    th = fit_thesis_from_flanks(recs, events, start=ax.thesis.params())
    session = flank_session(
        recs,
        events,
        th.line_width_um,
        slew_rate_v_per_s=base.service.ramp_rate_v_per_s,
        rest_voltage_v=ax.safe_voltage_v,
        settle_lines=SETTLE_LINES,
    )
    return recs, events, th, session


def session_through_polarity(data: DynamicCalibrationData, pct: float) -> DynamicCalibrationData:
    """The session as a model inside a polarity part of ``pct`` sees it (drive voltages below 0 V
    times ``1 + pct / 100``, :meth:`piezod.model.parts.Parts.voltage_in`)."""
    from piezod.model.parts import Parts

    if pct == 0.0:
        return data
    parts = Parts.from_effects({"polarity": {"negative_sensitivity_pct": float(pct)}})
    return dataclasses.replace(data, hysteresis_voltage_v=parts.voltage_in(data.hysteresis_voltage_v))


#: The polarity profile's first pass: a grid over the registry's realistic magnitudes and beyond
#: (a fit's training RMS is not unimodal in the value far from it), then a bounded search between
#: the best grid point's neighbours.
POLARITY_GRID_PCT: tuple[float, ...] = (-20.0, -15.0, -10.0, -6.0, -3.0, 0.0, 3.0, 6.0, 10.0, 15.0, 20.0)
#: Evaluations of the bounded search after the grid.
POLARITY_EVALUATIONS = 8
#: The smallest polarity adopted (%): a kink of ``p`` % at the middle of a centred scan bends it by
#: about ``p / 8`` % of its range, so below a quarter percent it is under the image metrics'
#: resolution (0.01-0.03 %); on a stage without depoling the profile finds ~0.1 % that shaves a
#: few percent off the held-out RMS of a law that misses something else.
POLARITY_MIN_PCT = 0.25


@dataclass(frozen=True)
class PartSearch:
    """What a search for one runtime part on the flanks leaves (:func:`search_polarity`,
    :func:`search_saturation`).

    Attributes
    ----------
    choice
        The model choice to use: redone on the session through the part when adopted, else the
        one passed in.
    heldout_rms_um
        Held-out flank RMS of the chosen member without the part, and with it (the final member
        at the refined value; ``nan`` when not adopted).
    notes
        One line per step, for the report.
    """

    choice: ModelChoice
    heldout_rms_um: tuple[float, float]
    notes: tuple[str, ...]


@dataclass(frozen=True)
class PolaritySearch(PartSearch):
    """The outcome of :func:`search_polarity`: ``pct``, the adopted ``negative_sensitivity_pct``
    (0: none adopted)."""

    pct: float = 0.0


def _profile(
    rms: Callable[[float], float], lo: float, hi: float, grid: Sequence[float]
) -> tuple[float, float]:
    from scipy.optimize import minimize_scalar

    pts = sorted({min(max(float(g), lo), hi) for g in grid})
    vals = [rms(g) for g in pts]
    k = int(np.argmin(vals))
    a, b = pts[max(k - 1, 0)], pts[min(k + 1, len(pts) - 1)]
    best_p, best_v = pts[k], vals[k]
    if b > a:
        res = minimize_scalar(rms, bounds=(a, b), method="bounded", options={"maxiter": POLARITY_EVALUATIONS})
        if math.isfinite(float(res.fun)) and float(res.fun) < best_v:
            best_p, best_v = float(res.x), float(res.fun)
    return best_p, best_v


def _fitted(
    data: DynamicCalibrationData,
    which: str,
    mask: NDArray[np.bool_] | None,
    alpha_per_v: float | None,
) -> FamilyFit | None:
    """The family member named ``which`` (:func:`piezod.calibrate_family.member_name`) fitted."""
    from piezod import calibrate_family as cf

    member = cf.parse_member(which)
    if member is None:
        raise CalibrationError(f"{which!r} is not a family member")
    law, driver, plays = member
    try:
        return cf.fit_family(
            data,
            law,
            train=mask,
            plays=plays or cf.DEFAULT_PLAYS,
            n_nodes=cf.member_nodes(which),
            alpha_per_v=alpha_per_v,
            creep_driver=driver,
            after_effect=cf.member_after_effect(which),
        )
    except (CalibrationError, ModelError):
        return None


@dataclass(frozen=True)
class _Part:
    """One runtime part the image path searches: how the session looks through it."""

    effect: str
    name: str
    unit: str
    #: The profiled variable's grid, bounds, and its map to the part's value.
    grid: tuple[float, ...]
    bounds: tuple[float, float]
    value: Callable[[float], float]
    variable: Callable[[float], float]
    through: Callable[[DynamicCalibrationData, float], DynamicCalibrationData]
    #: Why a profiled value is not material (None: it is).
    immaterial: Callable[[float], str | None]
    #: Told the member fitted through the profiled value (a part that places the session by a
    #: fitted model takes the better one), which is then refitted.
    settle: Callable[[FamilyFit], None] | None = None


def _search_part(
    part: _Part,
    data: DynamicCalibrationData,
    choice: ModelChoice,
    *,
    alpha_per_v: float | None,
    adoptable_drivers: Sequence[str] | None,
    laws: Sequence[str] | None,
    creep_drivers: Sequence[str] | None,
) -> tuple[float | None, ModelChoice, tuple[float, float], tuple[str, ...]]:
    """Profile ``part`` on the chosen member, keep it when material and better on the held-out
    scans, redo the choice through it and refine the value (see :func:`search_polarity`).
    Returns the profiled variable (None: not adopted), the choice, the held-out RMS before and
    after, and the notes."""
    from piezod import calibrate_family as cf
    from piezod.extensions import refine_parts
    from piezod.model.family import CREEP_DRIVERS

    drivers = tuple(adoptable_drivers) if adoptable_drivers is not None else CREEP_DRIVERS
    member = cf.parse_member(choice.chosen)
    before = float(choice.heldout_rms_um.get(choice.chosen, math.nan))
    if member is None:
        note = f"{part.effect}: not searched (not a family member)"
        return None, choice, (before, math.nan), (note,)
    train = cf.holdout_mask(data.n_experiments)

    def train_rms(which: str) -> Callable[[float], float]:
        def rms(u: float) -> float:
            f = _fitted(part.through(data, float(u)), which, train, alpha_per_v)
            return math.inf if f is None else float(f.rms_um)

        return rms

    u1, _ = _profile(train_rms(choice.chosen), *part.bounds, part.grid)
    f1 = _fitted(part.through(data, u1), choice.chosen, train, alpha_per_v)
    if f1 is not None and part.settle is not None:
        part.settle(f1)
        f1 = _fitted(part.through(data, u1), choice.chosen, train, alpha_per_v)
    held1 = math.inf if f1 is None else float(f1.heldout_rms_um)
    notes = [
        f"{part.effect} profiled on {choice.chosen}: {part.name} {part.value(u1):.4g} {part.unit},"
        f" held-out {1e3 * before:.2f} -> {1e3 * held1:.2f} nm"
    ]
    why = part.immaterial(u1)
    if why is not None:
        notes.append(f"{part.effect}: not adopted ({why})")
        return None, choice, (before, math.nan), tuple(notes)
    if not held1 < before * (1.0 - cf.CHOICE_TIE_FRACTION):
        notes.append(f"{part.effect}: not adopted (held-out not better by the tie fraction)")
        return None, choice, (before, math.nan), tuple(notes)
    seen = part.through(data, u1)
    redone = cf.choose_model(
        seen,
        laws=tuple(laws) if laws is not None else cf.LAWS,
        alpha_per_v=alpha_per_v,
        creep_drivers=tuple(creep_drivers) if creep_drivers is not None else CREEP_DRIVERS,
        adoptable_drivers=drivers,
    )
    if cf.parse_member(redone.chosen) is None:
        raise CalibrationError(
            f"the choice through the {part.effect} part chose {redone.chosen!r}, not a family member"
        )
    refined, _ = refine_parts(
        {part.effect: {part.name: part.value(u1)}},
        lambda trial: train_rms(redone.chosen)(part.variable(trial[part.effect][part.name])),
        model=redone.chosen,
    )
    u2 = part.variable(float(refined[part.effect][part.name]))
    f2 = _fitted(part.through(data, u2), redone.chosen, train, alpha_per_v)
    final = _fitted(part.through(data, u2), redone.chosen, None, alpha_per_v)
    if f2 is None or final is None:
        raise CalibrationError(
            f"{redone.chosen} through a {part.effect} part of {part.value(u2):.4g} {part.unit} failed to fit"
        )
    held2 = float(f2.heldout_rms_um)
    notes.append(
        f"choice redone through it: {redone.chosen}; {part.name} refined on it: "
        f"{part.value(u2):.4g} {part.unit}, held-out {1e3 * held2:.2f} nm"
    )
    heldout = dict(redone.heldout_rms_um)
    trains = dict(redone.train_rms_um)
    heldout[redone.chosen], trains[redone.chosen] = held2, float(f2.rms_um)
    out = dataclasses.replace(redone, fit=final, heldout_rms_um=heldout, train_rms_um=trains)
    return u2, out, (before, held2), tuple(notes)


def search_polarity(
    data: DynamicCalibrationData,
    choice: ModelChoice,
    *,
    alpha_per_v: float | None = None,
    adoptable_drivers: Sequence[str] | None = None,
    laws: Sequence[str] | None = None,
    creep_drivers: Sequence[str] | None = None,
) -> PolaritySearch:
    """Search the flanks for a polarity part (a partially depoled ceramic) and redo the choice.

    1. The chosen family member's training RMS on the session through a polarity part is
       profiled (:data:`POLARITY_GRID_PCT`, then a bounded search; registry bounds).
    2. The part is kept only when it is at least :data:`POLARITY_MIN_PCT` and the member, fitted
       through it on the training scans, predicts the held-out scans better by more than
       :data:`~piezod.calibrate_family.CHOICE_TIE_FRACTION`.
    3. The model choice is redone on the session through the part (the best law can change: a
       law that took part of the kink loses it), and the value refined on the new member
       (:func:`piezod.extensions.refine_parts`, as the sensor path refines the audit's value).

    Parameters
    ----------
    data
        The flank session (:func:`flank_session`).
    choice
        :func:`piezod.calibrate_family.choose_model` on it.
    alpha_per_v, adoptable_drivers, laws, creep_drivers
        As for the choice (None: :func:`~piezod.calibrate_family.choose_model`'s defaults).
    """
    from piezod.model.registry import spec

    lo, hi = next(p.physical for p in spec("polarity").params if p.name == "negative_sensitivity_pct")
    part = _Part(
        "polarity",
        "negative_sensitivity_pct",
        "%",
        POLARITY_GRID_PCT,
        (max(lo, min(POLARITY_GRID_PCT)), min(hi, max(POLARITY_GRID_PCT))),
        float,
        float,
        session_through_polarity,
        lambda u: None if abs(u) >= POLARITY_MIN_PCT else f"below {POLARITY_MIN_PCT:g} %",
    )
    u, out, held, notes = _search_part(
        part,
        data,
        choice,
        alpha_per_v=alpha_per_v,
        adoptable_drivers=adoptable_drivers,
        laws=laws,
        creep_drivers=creep_drivers,
    )
    return PolaritySearch(out, held, notes, pct=0.0 if u is None else u)


#: The saturation profile's variable is ``1000 / x_sat`` (0: none; 1/mm): a grid from none to
#: the registry's strongest realistic part, then a bounded search between the best's neighbours.
SATURATION_GRID_PER_MM: tuple[float, ...] = (0.0, 2.5, 5.0, 8.0, 12.0, 17.0, 24.0, 32.0)
#: The smallest saturation adopted: it must compress the frame's farthest position by at least
#: this much (%), ``1 - tanh(u) / u`` at ``u = max |x| / x_sat`` (as :data:`POLARITY_MIN_PCT`).
SATURATION_MIN_PCT = 0.25


@dataclass(frozen=True)
class SaturationSearch(PartSearch):
    """The outcome of :func:`search_saturation`: ``x_sat_um``, the adopted saturation scale
    (``inf``: none adopted)."""

    x_sat_um: float = math.inf


def session_through_saturation(
    data: DynamicCalibrationData, x_sat_um: float, model_um: F64
) -> DynamicCalibrationData:
    """The session as a model inside a saturation part of ``x_sat_um`` sees it.

    The flank positions are known up to an offset per scan and flank family; the part acts on
    absolute positions, so each group is first placed where ``model_um`` (a fitted model's
    positions at the compared samples, before the part) puts it through the part, then taken
    through the part's inverse, ``x_sat atanh(x / x_sat)`` (:meth:`piezod.model.parts.Parts.position_in`).
    """
    if not math.isfinite(x_sat_um):
        return data
    p = data.position_um
    _, inv = np.unique(data.groups(), return_inverse=True)
    cnt = np.bincount(inv).astype(np.float64)
    offsets = np.bincount(inv, x_sat_um * np.tanh(model_um / x_sat_um) - p) / cnt
    a = np.clip((p + offsets[inv]) / x_sat_um, -1.0 + 1e-9, 1.0 - 1e-9)
    return dataclasses.replace(data, position_um=x_sat_um * np.arctanh(a))


def search_saturation(
    data: DynamicCalibrationData,
    choice: ModelChoice,
    *,
    alpha_per_v: float | None = None,
    adoptable_drivers: Sequence[str] | None = None,
    laws: Sequence[str] | None = None,
    creep_drivers: Sequence[str] | None = None,
) -> SaturationSearch:
    """Search the flanks for a saturation part (a response that flattens towards the ends of the
    range, odd in the position) and redo the choice, as :func:`search_polarity` does.

    No law of the family flattens its static curve symmetrically (the static map is quadratic),
    and the play laws' envelopes take only part of it. The profile's fits see the session through
    :func:`session_through_saturation`, the offsets placed by the chosen member's fit.
    """
    from piezod import calibrate_family as cf
    from piezod.model.registry import spec

    if choice.fit is None:
        before = float(choice.heldout_rms_um.get(choice.chosen, math.nan))
        note = "saturation: not searched (not a family member)"
        return SaturationSearch(choice, (before, math.nan), (note,))
    placed = {"model_um": cf.session_positions(data, choice.fit.params)}
    reach = float(np.max(np.abs(placed["model_um"])))
    lo_um, _ = next(p.physical for p in spec("saturation").params if p.name == "x_sat_um")

    def x_sat(u: float) -> float:
        return 1000.0 / u if u > 0.0 else math.inf

    def immaterial(u: float) -> str | None:
        r = reach / x_sat(u)
        squeeze = 100.0 * (1.0 - math.tanh(r) / r) if r > 0.0 else 0.0
        if squeeze >= SATURATION_MIN_PCT:
            return None
        return f"compresses the farthest position, {reach:.3g} um, by {squeeze:.3g} %"

    grid = SATURATION_GRID_PER_MM
    part = _Part(
        "saturation",
        "x_sat_um",
        "um",
        grid,
        (0.0, min(max(grid), 1000.0 / lo_um)),
        x_sat,
        lambda x: 1000.0 / x if math.isfinite(x) and x > 0.0 else 0.0,
        lambda d, u: session_through_saturation(d, x_sat(u), placed["model_um"]),
        immaterial,
        lambda f: placed.update(model_um=cf.session_positions(data, f.params)),
    )
    u, out, held, notes = _search_part(
        part,
        data,
        choice,
        alpha_per_v=alpha_per_v,
        adoptable_drivers=adoptable_drivers,
        laws=laws,
        creep_drivers=creep_drivers,
    )
    return SaturationSearch(out, held, notes, x_sat_um=math.inf if u is None else x_sat(u))


def fit_dynamic_from_flanks(
    recs: Sequence[Recording],
    events: Sequence[FlankEvents],
    line_width_um: dict[str, float],
    *,
    slew_rate_v_per_s: float = 2000.0,
    rest_voltage_v: float = 0.0,
    max_samples_per_loop: int = 2048,
    **fit_kwargs: object,
) -> DynamicCalibrationResult:
    """Fit the dynamic model to the flanks of a frame recorded in one session (:func:`flank_session`)."""
    data = flank_session(
        recs,
        events,
        line_width_um,
        slew_rate_v_per_s=slew_rate_v_per_s,
        rest_voltage_v=rest_voltage_v,
        max_samples_per_loop=max_samples_per_loop,
    )
    return fit_dynamic(data, **fit_kwargs)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ hidden truth


TRUTH_COLUMNS = ("index", "x_um", "y_um", "z_voltage_v", "z_um")
"""Columns of the simulator's truth log (``hil_sim.board.BoardConfig.truth_log``)."""


def read_truth_rows(path: str | Path) -> F64:
    """All rows of the simulator's truth log, ``(n, 5)`` in :data:`TRUTH_COLUMNS` order, by index."""
    raw = np.fromfile(str(path), dtype=np.float64)
    if raw.size % 5:
        raw = raw[: raw.size - raw.size % 5]
    rows = raw.reshape(-1, 5)
    out: F64 = rows[np.argsort(rows[:, 0], kind="stable")]
    return out


def read_truth_log(path: str | Path, column: str = "x_um") -> tuple[NDArray[np.int64], F64]:
    """The simulator's truth log: sample indices and one column (default the true x position, um)."""
    rows = read_truth_rows(path)
    return rows[:, 0].astype(np.int64), rows[:, TRUTH_COLUMNS.index(column)]


def with_truth(rec: Recording, truth: tuple[NDArray[np.int64], F64], sample_rate_hz: float) -> Recording:
    """The recording with its position column replaced by the hidden true position (x rows)."""
    idx, x = truth
    pos = rec.position_um.copy()
    sel = _x_rows(rec)
    k = rec.t_s[sel] * sample_rate_hz
    if idx.size < 2 or k.min() < idx[0] or k.max() > idx[-1]:
        raise CalibrationError("the truth log does not cover the recording")
    pos[sel] = np.interp(k, idx.astype(np.float64), x)
    return dataclasses.replace(rec, position_um=pos)


# --------------------------------------------------------------------------------------- the frame


@dataclass(frozen=True, slots=True)
class ImageScan:
    """One scan of the image calibration frame (or of its verification)."""

    range_um: float
    line_rate_hz: float
    offset_um: float = 0.0
    lines: int = 6
    label: str = ""
    where: str = "inside"

    def name(self) -> str:
        """A recording name."""
        return self.label or f"r{self.range_um:g}_f{self.line_rate_hz:g}_o{self.offset_um:g}"


def default_image_frame(*, reduced: bool = False) -> list[ImageScan]:
    """The calibration frame: ranges x line rates on the reference, plus two offsets.

    Ranges are nominal (um of the uncorrected triangle); the thesis used 15-35 um at 0.1-1.4 Hz.
    """
    ranges = (14.0, 24.0, 32.0) if not reduced else (14.0, 30.0)
    rates = (0.5, 1.0, 2.0) if not reduced else (0.5, 2.0)
    scans = [ImageScan(r, f, lines=6) for r in ranges for f in rates]
    scans += [ImageScan(18.0, 1.0, o, lines=6) for o in (-6.0, 6.0)]
    return scans


def verification_scans(*, reduced: bool = False) -> list[ImageScan]:
    """Corrected scans inside and outside the frame (10x slower / faster, offset beyond it).

    ``reduced``: one scan inside, the offset beyond the frame and 5x faster (no slow scan).
    """
    if reduced:
        return [
            ImageScan(20.0, 1.0, 0.0, 5, "in-20um-1Hz", "inside"),
            ImageScan(20.0, 10.0, 0.0, 20, "out-20um-10Hz", "outside: 5x faster"),
            ImageScan(14.0, 1.0, -10.5, 5, "out-14um-off-10.5", "outside: offset beyond the frame"),
        ]
    return [
        ImageScan(20.0, 1.0, 0.0, 6, "in-20um-1Hz", "inside"),
        ImageScan(30.0, 2.0, 0.0, 6, "in-30um-2Hz", "inside"),
        ImageScan(18.0, 0.5, 3.0, 5, "in-18um-0.5Hz-off3", "inside"),
        ImageScan(20.0, 0.05, 0.0, 2, "out-20um-0.05Hz", "outside: 10x slower"),
        ImageScan(20.0, 10.0, 0.0, 30, "out-20um-10Hz", "outside: 5x faster"),
        ImageScan(14.0, 1.0, -10.5, 6, "out-14um-off-10.5", "outside: offset beyond the frame"),
    ]


def run_image_scans(
    engine: object,
    scans: Sequence[ImageScan],
    out_dir: Path,
    *,
    pixels: int = 512,
    correction: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[Path]:
    """Scan each image on the stage (one recording each, one session) through the engine."""
    from piezod.service.engine import Engine
    from piezod.service.schemas import ScanRequest

    assert isinstance(engine, Engine)
    paths = []
    out_dir.mkdir(parents=True, exist_ok=True)
    for sc in scans:
        path = out_dir / f"{sc.name()}.csv"
        n = 2
        while path.exists():  # recordings are never overwritten: a repeated scan gets a new name
            path = out_dir / f"{sc.name()}-r{n}.csv"
            n += 1
        # at least two samples per pixel (fast lines at a low sample rate get fewer pixels)
        per_half_line = engine.rate_hz / (2.0 * sc.line_rate_hz)
        request = ScanRequest(
            range_um=sc.range_um,
            line_rate_hz=sc.line_rate_hz,
            lines=sc.lines,
            offset_x_um=sc.offset_um,
            pixels=max(64, min(pixels, int(per_half_line // 2))),
            correction=correction,
            name=path.stem,
        )
        if progress is not None:
            progress(sc.name())
        engine.check_scan(request)
        scan_start_s = engine.status().uptime_s
        engine.start_scan(request, path=path)
        limit = time.monotonic() + 60.0 + 4.0 * (sc.lines + 2) / sc.line_rate_hz
        while engine.status().state == "scanning":
            if time.monotonic() > limit:
                raise CalibrationError(f"scan {sc.name()} did not finish in time")
            time.sleep(0.1)
        state = engine.wait_idle(timeout_s=10.0)
        engine.wait_recorded()
        if state != "idle":
            faults = "; ".join(f"{f.code}: {f.message}" for f in engine.status().faults[-3:])
            raise CalibrationError(f"scan {sc.name()} ended in state {state}: {faults}")
        # a stream that broke and restarted during the scan leaves the engine idle with a short or
        # empty recording: the scan is not a measurement of the frame
        broken = [f for f in engine.status().faults if f.time_s >= scan_start_s and f.code in _STREAM_FAULTS]
        if broken or not path.exists() or path.stat().st_size < _MIN_RECORDING_BYTES:
            why = "; ".join(f"{f.code}: {f.message}" for f in broken[-3:]) or "the recording is empty"
            raise CalibrationError(f"scan {sc.name()} was interrupted ({why})")
        paths.append(path)
    return paths


#: A repeated image's sensitivity change is adopted as a warming trend when it is at least this
#: large (%) - below it a trend over the minutes of a calibration is not worth extrapolating -
#: and :data:`RECHECK_SIGMAS` times its standard uncertainty.
RECHECK_MIN_PCT = 0.03
#: See :data:`RECHECK_MIN_PCT`.
RECHECK_SIGMAS = 3.0
#: The repeat is scanned at least this long after the first image (s): without any warming the
#: two images' ratio is off by ~0.015 % (their histories differ: the frame's scans before one, a
#: hold before the other; the built-in microscope: -0.014 % 70 s later, -0.015 % 306 s later),
#: which read as a trend over a minute is ~0.7 %/h, over five minutes ~0.2 %/h.
RECHECK_MIN_INTERVAL_S = 300.0


def recheck_scan(frame: Sequence[ImageScan]) -> ImageScan:
    """The frame scan the sensitivity re-check repeats: the largest range without an offset (the
    most flanks, so the most precise length), at its median line rate."""
    centred = [s for s in frame if s.offset_um == 0.0] or list(frame)
    if not centred:
        raise CalibrationError("the image frame has no scans to re-check")
    top = max(s.range_um for s in centred)
    widest = sorted((s for s in centred if s.range_um == top), key=lambda s: s.line_rate_hz)
    return widest[(len(widest) - 1) // 2]


def recording_span_unix_s(path: str | Path) -> tuple[float, float]:
    """Wall-clock instants (Unix time, s) of a recording's first and last sample: its header's
    ``started_utc`` (:func:`piezod.extensions.session_origin_unix_s`) and the first column of its
    last row, read from the file's end (a frame recording may be hundreds of MB).

    Raises
    ------
    RecordingError
        No ``started_utc`` in the header, or an unreadable last row (names the file).
    """
    from piezod.extensions import session_origin_unix_s

    origin = session_origin_unix_s(path)
    if not math.isfinite(origin):
        raise RecordingError(f"{path}: no started_utc in the header: the time of the scan is unknown")
    first = last = math.nan
    with open(path, "rb") as f:
        for raw in f:
            if raw.startswith(b"#") or raw.startswith(b"t,") or not raw.strip():
                continue
            first = float(raw.split(b",", 1)[0])
            break
        f.seek(0, 2)
        f.seek(max(0, f.tell() - 65536))
        rows = [r for r in f.read().splitlines() if r.strip() and not r.startswith(b"#")]
    try:
        last = float(rows[-1].split(b",", 1)[0])
    except (IndexError, ValueError) as exc:
        raise RecordingError(f"{path}: the last row has no time: {exc}") from None
    return origin + first, origin + last


#: Degree of the Chebyshev series of the uncorrected branch the two images of a re-check share.
RECHECK_DEGREE = 9


def _height_pair(path: str | Path) -> tuple[F64, F64, Geometry]:
    from piezod.image import images
    from piezod.recording import read_recording

    rec = read_recording(path)
    try:
        pair = next(p for p in images(rec) if p.grid == "commanded" and p.channel == "z_voltage")
    except StopIteration:
        raise RecordingError(f"{path}: no height image on the commanded grid") from None
    return pair.trace, pair.retrace, pair.geometry


def image_scale_change(first: str | Path, repeat: str | Path, pitch_um: float) -> tuple[float, float]:
    """How much more the stage moves per commanded um in ``repeat`` than in ``first``, two
    recorded images of the reference with the same drive: ``s - 1`` and its standard uncertainty.

    The flank at commanded ``c`` of line ``l`` sits at ``k P = s_i F(c) + o_l`` (image ``i``;
    ``s_1 = 1``): the uncorrected branch ``F`` (a Chebyshev series per scan direction) is the same
    function of the commanded position in both images because the drive is; the offsets ``o_l``
    per line and flank family take the sample's position, the line width and the slow creep of
    each line. Dividing the repeat's equations by ``s`` makes the problem linear in ``1 / s``.
    Unlike the images' length errors (4.15), this does not depend on which flanks each image
    happens to see on a strongly curved uncorrected branch.

    Raises
    ------
    RecordingError
        No image, or too few flanks (names the file).
    """
    from piezod.image_linearity import find_flanks

    imgs = [_height_pair(first), _height_pair(repeat)]
    geo = imgs[0][2]
    rows: list[F64] = []
    rhs: list[F64] = []
    blocks = []
    for d in (0, 1):
        per: list[tuple[F64, F64, NDArray[np.int64]]] = []
        for (tr, rt, geo_i), path in zip(imgs, (first, repeat), strict=True):
            fl = find_flanks(tr if d == 0 else rt, geo_i)
            if fl.xi_um.size < 12:
                raise RecordingError(f"{path}: {fl.xi_um.size} flanks in the image: too few to compare")
            grp = np.unique(fl.line * 2 + (fl.family > 0), return_inverse=True)[1]
            per.append((fl.xi_um, fl.k.astype(np.float64) * pitch_um, grp))
        blocks.append(per)
    n_poly = RECHECK_DEGREE
    n_grp = [int(b[i][2].max()) + 1 for b in blocks for i in (0, 1)]
    cols = 1 + 2 * n_poly + sum(n_grp)
    col = 1
    for (c1, x1, g1), (c2, x2, g2) in blocks:
        base = col
        col_o1 = base + n_poly
        col_o2 = col_o1 + int(g1.max()) + 1
        for img, (c, x, grp) in enumerate(((c1, x1, g1), (c2, x2, g2))):
            u = 2.0 * (c - geo.x0_um) / geo.range_um - 1.0
            a = np.zeros((c.size, cols))
            a[:, base : base + n_poly] = np.polynomial.chebyshev.chebvander(u, n_poly)[:, 1:]
            a[np.arange(c.size), (col_o1 if img == 0 else col_o2) + grp] = 1.0
            if img == 0:
                rows.append(a)
                rhs.append(x)
            else:
                a[:, 0] = -x
                rows.append(a)
                rhs.append(np.zeros(c.size))
        col = col_o2 + int(g2.max()) + 1
    a_all = np.vstack(rows)
    b_all = np.concatenate(rhs)
    keep = np.ones(b_all.size, dtype=bool)
    for _ in range(2):
        sol, *_ = np.linalg.lstsq(a_all[keep], b_all[keep], rcond=None)
        r = b_all - a_all @ sol
        mad = 1.4826 * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        keep = np.abs(r - np.median(r[keep])) <= 5.0 * max(mad, 1e-6)
    sol, *_ = np.linalg.lstsq(a_all[keep], b_all[keep], rcond=None)
    r = (b_all - a_all @ sol)[keep]
    dof = max(int(keep.sum()) - cols, 1)
    cov = np.linalg.pinv(a_all[keep].T @ a_all[keep]) * float(r @ r) / dof
    inv_s = float(sol[0])
    if not inv_s > 0:
        raise RecordingError(f"{repeat}: the repeated image does not follow {first}")
    sd = math.sqrt(max(float(cov[0, 0]), 0.0)) / inv_s**2
    return 1.0 / inv_s - 1.0, sd


@dataclass(frozen=True)
class SensitivityRecheck:
    """One frame scan of the reference repeated, uncorrected, minutes later: how much more the
    stage moves per volt now (a scanner that warms; thesis section 4.4).

    The two images share the drive, the range, the line rate and the settling lines, so what the
    model gets wrong cancels and the ratio of their lengths is the change of the sensitivity; what
    changed it is taken to grow linearly in time (a thermal part, :class:`piezod.model.parts.Parts`)
    from the frame's middle, where the fitted sensitivity is.

    Attributes
    ----------
    scan
        The repeated scan's name.
    change_pct, unc_pct
        Sensitivity of the repeat over the first, minus 1 (%), and its standard uncertainty.
    first_unix_s, repeat_unix_s
        Middle of each image (Unix time, s).
    frame_mid_unix_s, frame_start_unix_s
        Middle and start of the calibration frame (Unix time, s).
    adopted
        Whether the change is material (:data:`RECHECK_MIN_PCT`, :data:`RECHECK_SIGMAS`).
    """

    scan: str
    change_pct: float
    unc_pct: float
    first_unix_s: float
    repeat_unix_s: float
    frame_mid_unix_s: float
    frame_start_unix_s: float
    adopted: bool

    @property
    def rate_pct_per_hour(self) -> float:
        """The sensitivity's change per hour between the two images (%/h)."""
        return self.change_pct * 3600.0 / max(self.repeat_unix_s - self.first_unix_s, 1.0)

    @property
    def horizon_s(self) -> float:
        """How long the trend is followed (:data:`piezod.extensions.TREND_HORIZON_FACTOR` times the
        session from the frame's start to the repeat)."""
        from piezod.extensions import TREND_HORIZON_FACTOR

        return TREND_HORIZON_FACTOR * max(self.repeat_unix_s - self.frame_start_unix_s, 1.0)

    def thermal(self) -> dict[str, float] | None:
        """The thermal part's values (``extensions: thermal:``), or None when not adopted."""
        if not self.adopted:
            return None
        return {
            "rate_pct_per_hour": self.rate_pct_per_hour,
            "horizon_s": self.horizon_s,
            "since_unix_s": self.frame_mid_unix_s,
        }

    def note(self) -> str:
        """One line for the user."""
        dt = self.repeat_unix_s - self.first_unix_s
        head = (
            f"sensitivity re-check: {self.scan} repeated {dt:.0f} s later moves "
            f"{self.change_pct:+.3f} +-{self.unc_pct:.3f} % more per volt"
        )
        if self.adopted:
            return (
                f"{head}: a trend of {self.rate_pct_per_hour:+.3f} %/h adopted (thermal part, from "
                f"the frame's middle, followed for {self.horizon_s:.0f} s)"
            )
        return (
            f"{head}: not material (< {RECHECK_MIN_PCT:g} % or < {RECHECK_SIGMAS:g} sigma), no trend adopted"
        )


def sensitivity_recheck(
    frame: Sequence[str | Path], first: str | Path, repeat: str | Path, pitch_um: float
) -> SensitivityRecheck:
    """Compare a frame scan (``first``, one of ``frame``) with its uncorrected repeat.

    Raises
    ------
    RecordingError
        A recording without time or image (names the file).
    """
    spans = [recording_span_unix_s(p) for p in frame]
    a0, a1 = recording_span_unix_s(first)
    b0, b1 = recording_span_unix_s(repeat)
    ds, sd = image_scale_change(first, repeat, pitch_um)
    change, unc = 100.0 * ds, 100.0 * sd
    starts = [s for s, _ in spans]
    ends = [e for _, e in spans]
    return SensitivityRecheck(
        scan=Path(first).stem,
        change_pct=change,
        unc_pct=unc,
        first_unix_s=0.5 * (a0 + a1),
        repeat_unix_s=0.5 * (b0 + b1),
        frame_mid_unix_s=0.5 * (min(starts) + max(ends)),
        frame_start_unix_s=min(starts),
        adopted=abs(change) >= max(RECHECK_MIN_PCT, RECHECK_SIGMAS * unc),
    )


__all__ = [
    "RECHECK_MIN_INTERVAL_S",
    "RECHECK_MIN_PCT",
    "RECHECK_SIGMAS",
    "FlankEvents",
    "ImageScan",
    "SensitivityRecheck",
    "ThesisFromFlanks",
    "default_image_frame",
    "drop_outlier_flanks",
    "fit_dynamic_from_flanks",
    "fit_thesis_from_flanks",
    "flank_events",
    "flank_session",
    "image_scale_change",
    "merged_positions",
    "read_truth_log",
    "recheck_scan",
    "recording_span_unix_s",
    "run_image_scans",
    "sensitivity_recheck",
    "thesis_data",
    "timed_layout",
    "verification_scans",
    "with_truth",
]
