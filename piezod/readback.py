"""The readback aligned to the drive: a known sensor delay, or the sensor path's inverse.

A position sensor's readback may trail the drive sample it belongs to (the sensor's and the
acquisition's delay, a first-order lag of its electronics). :func:`experiments_through_sensor`
undoes a :class:`~piezod.model.sensor.SensorPath` on recorded experiments;
:func:`align_known_delay` does it for the delay a recording documents in its metadata
(``sensor_delay_s``, docs/formats.md). Used by the audit, the model family and the offline
calibration (no dependency on either).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from piezod.errors import ModelError, RecordingError
from piezod.model.sensor import SensorPath
from piezod.recording import Experiment


def experiments_through_sensor(experiments: Sequence[Experiment], path: SensorPath) -> list[Experiment]:
    """The experiments with the stage's position in place of the readback (:meth:`SensorPath.align`;
    the rows whose ``t + d`` is past an experiment's end are dropped)."""
    if path.identity:
        return list(experiments)
    out = []
    for e in experiments:
        t, x = path.align(np.asarray(e.t_s, dtype=np.float64), np.asarray(e.position_um, dtype=np.float64))
        n = t.size
        if n < 2:
            raise ModelError(f"experiment {e.describe()}: shorter than the sensor delay {path.delay_s:g} s")
        out.append(e.rows(slice(0, n), t_s=t, position_um=x))
    return out


#: Recording metadata key: the readback's known delay behind the drive (s), e.g. from the
#: instrument's documentation (docs/formats.md).
SENSOR_DELAY_KEY = "sensor_delay_s"


def align_known_delay(experiments: Sequence[Experiment]) -> tuple[list[Experiment], str | None]:
    """The experiments with the readback aligned by their recordings' ``sensor_delay_s`` metadata.

    A delay the recording documents is not something to estimate: the analysis (audit, family
    fits, calibration) sees the stage's position at the time of the drive
    (:meth:`~piezod.model.sensor.SensorPath.align`; the last ``d`` of every experiment is lost).

    Returns
    -------
    experiments, note
        The aligned experiments and one line saying what was aligned (None when no recording
        has the key).

    Raises
    ------
    RecordingError
        The value is not a number inside the delay effect's physical range (names the file).
    """
    out: list[Experiment] = []
    seen: dict[str, float] = {}
    for e in experiments:
        raw = e.metadata.get(SENSOR_DELAY_KEY)
        if raw is None:
            out.append(e)
            continue
        try:
            path = SensorPath(delay_s=float(raw))
        except (ValueError, ModelError) as exc:
            raise RecordingError(
                f"metadata {SENSOR_DELAY_KEY}: {raw!r} is not a valid delay ({exc})", e.path
            ) from exc
        seen[e.path or e.label] = path.delay_s
        # the key moves to sensor_delay_aligned_s: aligning twice would shift the readback twice
        meta = {k: v for k, v in e.metadata.items() if k != SENSOR_DELAY_KEY}
        meta[f"{SENSOR_DELAY_KEY.removesuffix('_s')}_aligned_s"] = raw
        out.extend(experiments_through_sensor([dataclasses.replace(e, metadata=meta)], path))
    if not seen:
        return out, None
    where = ", ".join(f"{Path(k).name} {v * 1e3:g} ms" for k, v in seen.items())
    return out, f"readback aligned by the recordings' documented sensor delay ({SENSOR_DELAY_KEY}: {where})"


#: Metadata key of a recording's sensor range (um; ``.<axis>`` appended in multi-axis recordings).
SENSOR_RANGE_KEY = "sensor_full_scale_um"

#: A readback within this share of the sensor's full scale sits at the ADC's end code (a 12-bit
#: converter's last step is 1/2048 of the range): the stage is beyond what the sensor reads.
FULL_SCALE_MARGIN = 1.0 / 2048.0


def full_scale_mask(
    position_um: NDArray[np.float64], full_scale_um: float | NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Which readings of ``position_um`` sit at the sensor's full scale (``+-full_scale_um``).

    Parameters
    ----------
    position_um
        Sensor readings (um); NaN reads as not at the full scale.
    full_scale_um
        The sensor's range (um), or one per row of a 2-D ``position_um`` (shape ``(rows, 1)``).

    Returns
    -------
    NDArray[np.bool_]
        True where the reading is the ADC's end code (within :data:`FULL_SCALE_MARGIN`).
    """
    return np.abs(position_um) >= np.multiply(full_scale_um, 1.0 - FULL_SCALE_MARGIN)


def at_full_scale(position_um: NDArray[np.float64], full_scale_um: float) -> int:
    """How many readings of ``position_um`` sit at the sensor's full scale (``+-full_scale_um``)."""
    return int(np.count_nonzero(full_scale_mask(position_um, full_scale_um)))


#: A readback held at one value, the experiment's largest or smallest, for at least this many
#: consecutive samples ...
PLATEAU_MIN_SAMPLES = 8
#: ... while the drive moved by at least this share of the experiment's voltage span reads as a
#: sensor at its end code (:func:`plateau_mask`). At a scan's turning point the drive barely moves
#: while a quantised reading repeats; behind a clipped sensor it sweeps the part of the loop the
#: sensor cannot read.
PLATEAU_MIN_SPAN_SHARE = 0.02


def plateau_mask(position_um: NDArray[np.float64], voltage_v: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Readings stuck at the experiment's extreme value while the drive moves: a clipped sensor.

    For recordings that do not document their sensor's range: a run of at least
    :data:`PLATEAU_MIN_SAMPLES` identical readings at the experiment's largest (or smallest) value,
    over which the voltage moves by at least :data:`PLATEAU_MIN_SPAN_SHARE` of its span. A moving
    stage read by a live sensor never repeats its extreme reading that long while the drive sweeps
    (noise and quantisation steps make it change); an ADC at its end code does.

    Returns
    -------
    NDArray[np.bool_]
        True on the stuck readings.
    """
    x = np.asarray(position_um, dtype=np.float64)
    v = np.asarray(voltage_v, dtype=np.float64)
    mask = np.zeros(x.size, dtype=bool)
    finite = np.isfinite(x)
    if x.size < PLATEAU_MIN_SAMPLES or not finite.any():
        return mask
    span = float(np.nanmax(v) - np.nanmin(v))
    if not span > 0:
        return mask
    for extreme in (float(np.max(x[finite])), float(np.min(x[finite]))):
        at = np.r_[False, x == extreme, False]
        edges = np.flatnonzero(np.diff(at.astype(np.int8)))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if b - a >= PLATEAU_MIN_SAMPLES and np.ptp(v[a:b]) >= PLATEAU_MIN_SPAN_SHARE * span:
                mask[a:b] = True
    return mask


def within_sensor_range(experiments: Sequence[Experiment]) -> tuple[list[Experiment], str | None]:
    """The experiments without those whose readback reached the sensor range their recording
    documents (``sensor_full_scale_um`` or ``sensor_full_scale_um.<axis>``, written by the daemon).

    Such a reading is the ADC's end code, not a position (the stage moved beyond what the sensor
    reads): an experiment with one is left out of the analysis. Of a recording that does not
    document its range, an experiment whose readback sticks at its extreme value while the drive
    sweeps (:func:`plateau_mask`) is left out the same way.

    Returns
    -------
    experiments, note
        The experiments kept and one line naming those left out (None when none was).

    Raises
    ------
    RecordingError
        The value is not a positive number (names the file), or no experiment is left.
    """
    out: list[Experiment] = []
    dropped: list[str] = []
    for e in experiments:
        per_axis = f"{SENSOR_RANGE_KEY}.{e.axis}"
        key = per_axis if per_axis in e.metadata else SENSOR_RANGE_KEY
        raw = e.metadata.get(key)
        if raw is None:
            stuck = plateau_mask(e.position_um, e.voltage_v)
            if stuck.any():
                value = float(e.position_um[np.flatnonzero(stuck)[0]])
                dropped.append(
                    f"{e.label} ({int(np.count_nonzero(stuck))} samples stuck at {value:+g} um while the "
                    "drive moved: a sensor at its end code)"
                )
            else:
                out.append(e)
            continue
        try:
            full_scale = float(raw)
        except ValueError:
            full_scale = math.nan
        if not full_scale > 0 or not math.isfinite(full_scale):
            raise RecordingError(f"metadata {key}: {raw!r} is not a positive sensor range in um", e.path)
        n = at_full_scale(e.position_um, full_scale)
        if n:
            dropped.append(f"{e.label} ({n} samples at +-{full_scale:g} um)")
        else:
            out.append(e)
    if not dropped:
        return out, None
    if not out:
        raise RecordingError(
            f"every experiment's readback reached the sensor's full scale: {', '.join(dropped)}",
            experiments[0].path,
        )
    return out, f"left out, the readback at the sensor's full scale: {', '.join(dropped)}"


__all__ = [
    "FULL_SCALE_MARGIN",
    "PLATEAU_MIN_SAMPLES",
    "PLATEAU_MIN_SPAN_SHARE",
    "SENSOR_DELAY_KEY",
    "SENSOR_RANGE_KEY",
    "align_known_delay",
    "at_full_scale",
    "experiments_through_sensor",
    "full_scale_mask",
    "plateau_mask",
    "within_sensor_range",
]
