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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

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


__all__ = ["SENSOR_DELAY_KEY", "align_known_delay", "experiments_through_sensor"]
