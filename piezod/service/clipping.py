"""Readback at the position sensor's full scale, counted as it arrives: per job and in total.

A reading at the ADC's end code is not a position: the stage travelled beyond what the sensor
reads (``axes.<axis>.sensor_full_scale_um``). It is not a fault (the voltages stay inside their
limits, the stage is safe), but the positions there are not measured. The test is the one the
offline analyses use (:func:`piezod.readback.full_scale_mask`), so the daemon and ``piezod audit``
or ``calibrate`` agree on what is clipped.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from piezod.readback import full_scale_mask

log = logging.getLogger("piezod.service.engine")

#: Ended jobs kept for their recording's trailer (the recorder closes a recording at most a few
#: jobs after it ended: when the readback of its last sample is in).
_KEEP_ENDED = 8


@dataclass
class _Job:
    name: str
    recording: int
    counts: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class ClipSnapshot:
    """The counts at one moment.

    Attributes
    ----------
    job
        The client's job (scan, program, move) whose readback arrived last, current or ended;
        None before any.
    job_counts
        Its samples at the full scale per axis reading a position (empty before any job).
    total
        Every readback sample since the engine started (holds and ramps too), per such axis.
    """

    job: str | None
    job_counts: dict[str, int]
    total: dict[str, int]


class SensorClips:
    """Per-axis counts of readback samples at the position sensor's full scale.

    The engine names the client's jobs (:meth:`register`) and tags their samples with the job's
    id; the recorder thread feeds every matched readback block in sample order (:meth:`add`).
    A job's count is final once the readback of a later sample (the next job's, or the hold after
    it) arrives: then a job with any clipped sample is reported in one ``WARNING`` line naming
    the job, the axes, the counts and the setting to change. Thread-safe.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._full_scale: dict[str, float] = {}
        self._named: dict[int, tuple[str, int]] = {}
        self._current_id = -1
        self._last_id = -1
        self._current: _Job | None = None
        self._shown: _Job | None = None
        self._ended: dict[int, _Job] = {}
        self._total: dict[str, int] = {}

    def set_full_scale(self, full_scale_um: Mapping[str, float]) -> None:
        """The axes that read a position sensor and the sensor's range of each (um)."""
        with self._lock:
            self._full_scale = dict(full_scale_um)
            self._total = {a: self._total.get(a, 0) for a in self._full_scale}

    def full_scale_um(self, axis: str) -> float | None:
        """The sensor's range of ``axis`` (um; None: the axis reads no position)."""
        with self._lock:
            return self._full_scale.get(axis)

    def register(self, ident: int, name: str, recording: int = -1) -> None:
        """Name job ``ident`` (> 0; its samples are tagged with it) and its recording's id (-1: none)."""
        with self._lock:
            self._named[ident] = (name, recording)

    def add(
        self, axes: tuple[str, ...], position_um: NDArray[np.float64], job: NDArray[np.int64]
    ) -> dict[str, NDArray[np.bool_]]:
        """Count a readback block: ``position_um`` ``(axes, n)``, the job id of every sample (-1: the
        engine's own hold or ramp, counted in the total only). Returns which samples of each
        counted axis sit at the full scale (for the recorder's line figures)."""
        with self._lock:
            full_scale = self._full_scale
        rows = [i for i, a in enumerate(axes) if a in full_scale]
        if not rows or job.size == 0:
            return {}
        names = [axes[i] for i in rows]
        limits = np.array([full_scale[a] for a in names])[:, None]
        mask = full_scale_mask(position_um[rows], limits)
        starts = np.concatenate(([0], np.flatnonzero(np.diff(job)) + 1))
        per_run = np.add.reduceat(mask, starts, axis=1, dtype=np.int64)
        ended: list[_Job] = []
        with self._lock:
            for k, start in enumerate(starts):
                ident = int(job[start])
                if ident != self._current_id:
                    ended.extend(self._switch(ident))
                for a, n in zip(names, per_run[:, k].tolist(), strict=True):
                    self._total[a] = self._total.get(a, 0) + n
                    if self._current is not None:
                        self._current.counts[a] = self._current.counts.get(a, 0) + n
        for done in ended:
            self._report(done)
        return dict(zip(names, mask, strict=True))

    def _switch(self, ident: int) -> list[_Job]:
        ended = []
        if self._current is not None:
            ended.append(self._current)
            if self._current.recording >= 0:
                self._ended[self._current.recording] = self._current
                while len(self._ended) > _KEEP_ENDED:
                    del self._ended[next(iter(self._ended))]
        self._current_id = ident
        self._current = None
        if ident > self._last_id:  # an id seen before (a stale tag after a gap) starts nothing
            self._last_id = ident
            name, recording = self._named.pop(ident, (f"job {ident}", -1))
            self._current = _Job(name, recording, dict.fromkeys(self._full_scale, 0))
            self._shown = self._current
        return ended

    def finish(self) -> None:
        """End the current job (the readback stops: the engine closes)."""
        with self._lock:
            ended = self._switch(-1)
        for done in ended:
            self._report(done)

    def for_recording(self, recording: int) -> dict[str, int] | None:
        """The counts of the job recorded as ``recording`` (None: no such job seen); its count is
        final once the readback of the job's last sample is in."""
        with self._lock:
            if self._current is not None and self._current.recording == recording:
                return dict(self._current.counts)
            done = self._ended.pop(recording, None)
            return None if done is None else dict(done.counts)

    def snapshot(self) -> ClipSnapshot:
        """The counts now (:class:`ClipSnapshot`)."""
        with self._lock:
            shown = self._shown
            return ClipSnapshot(
                None if shown is None else shown.name,
                {} if shown is None else dict(shown.counts),
                dict(self._total),
            )

    def _report(self, job: _Job) -> None:
        clipped = {a: n for a, n in job.counts.items() if n}
        if not clipped:
            return
        with self._lock:
            full_scale = dict(self._full_scale)
        where = ", ".join(
            f"{a} ({n} samples at +-{full_scale.get(a, float('nan')):g} um)" for a, n in clipped.items()
        )
        settings = ", ".join(f"axes.{a}.sensor_full_scale_um" for a in clipped)
        log.warning(
            "%s: the readback reached the position sensor's full scale on %s: positions there are "
            "not measured (the stage travelled beyond the sensor's range; if the sensor reads "
            "farther, set %s)",
            job.name,
            where,
            settings,
        )


__all__ = ["ClipSnapshot", "SensorClips"]
