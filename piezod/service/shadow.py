"""Trying a job without effect: the scan-start check on copies of the engine's axis drivers.

:class:`ShadowEngine` is what a job needs of the :class:`~piezod.service.engine.Engine`, on deep
copies of its axis drivers (labels, sync events and recordings go nowhere);
:func:`check_scan_start` renders the start of a scan on it and refuses a scan that would clamp.
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray

from piezod.errors import SafetyError
from piezod.service.axes import AxisDriver, PeriodicPlan, plan_axes
from piezod.service.jobs import MAX_CHECK_SAMPLES, Chunk, ScanJob
from piezod.service.schemas import ScanRequest
from piezod.service.sync import SyncSchedule
from piezod.trajectory import SETTLE_LINES, Trajectory

if TYPE_CHECKING:
    from piezod.service.engine import Engine

FloatArray = NDArray[np.float64]


class ShadowEngine:
    """What a job needs of the engine, on copies of its axis drivers: to try a job without effect."""

    def __init__(
        self,
        engine: Engine | None,
        *,
        drivers: dict[str, AxisDriver] | None = None,
        rate_hz: float | None = None,
    ) -> None:
        self._engine = engine
        if engine is not None:
            self.rate_hz = engine.rate_hz
            with engine._lock:
                self.drivers = {name: copy.deepcopy(d) for name, d in engine.drivers.items()}
        else:
            # no engine: the given drivers (copied), e.g. to check a scan before any board is there
            assert drivers is not None and rate_hz is not None
            self.rate_hz = float(rate_hz)
            self.drivers = {name: copy.deepcopy(d) for name, d in drivers.items()}
        self.render_index = 0
        self.clamped = dict.fromkeys(self.drivers, 0)
        self.sync_schedule = SyncSchedule(history=0)  # a trial's sync events go nowhere
        #: Lowest and highest voltage asked of each axis (before clamping).
        self.asked_v = {name: (math.inf, -math.inf) for name in self.drivers}

    def label_id(self, name: str) -> int:
        return -1

    def set_label_note(self, ident: int, note: str | None) -> None:
        pass

    def label_names(self, ids: NDArray[np.int64]) -> NDArray[np.str_]:
        return np.full(ids.shape, "", dtype=str)

    def plans_for(self, trajectory: Trajectory) -> dict[str, PeriodicPlan | None]:
        if self._engine is not None:
            return self._engine.plans_for(trajectory)
        return plan_axes(self.drivers, trajectory)

    def tracked_scale(self, axis: str) -> float:
        return 1.0 if self._engine is None else self._engine.tracked_scale(axis)

    def drive(self, driver: AxisDriver, out: Any) -> FloatArray:
        if out.clamped:
            self.clamped[driver.name] += int(out.clamped)
        volts: FloatArray = out.voltage_v
        return volts

    def chunk(self, volts: FloatArray, targets: FloatArray | None) -> Chunk:
        return Chunk.unlined(volts, targets)


def check_scan_start(
    engine: Engine, request: ScanRequest, trajectory: Trajectory, plans: dict[str, PeriodicPlan | None]
) -> None:
    """Render the start of a scan (the move to its first point, the settling lines, the first lines)
    on a :class:`ShadowEngine` of ``engine``; refuse it when any sample would be clamped.

    Raises
    ------
    SafetyError
        With the axis, the number of samples and the limits.
    """
    shadow = ShadowEngine(engine)
    job = ScanJob(cast("Engine", shadow), request, trajectory.restarted(), plans)
    lines_s = (SETTLE_LINES + 2 + 1) / max(request.line_rate_hz, 1e-9)
    budget = min(int(engine.rate_hz * lines_s) + 1, MAX_CHECK_SAMPLES)
    block = engine.config.service.block_samples(engine.rate_hz)
    total = rendered = 0
    while not job.done and (job._move is not None or rendered < budget) and total < MAX_CHECK_SAMPLES:
        in_move = job._move is not None
        m = job.render(cast("Engine", shadow), block).volts.shape[1]
        total += m
        if not in_move:
            rendered += m
        if m == 0 and not job.done:
            break
    bad = {axis: n for axis, n in shadow.clamped.items() if n}
    if bad:
        axis, n = next(iter(bad.items()))
        lo, hi = engine.drivers[axis].limits
        raise SafetyError(
            f"axis {axis}: the start of this scan (range {request.range_um:g} um, offset "
            f"({request.offset_x_um:g}, {request.offset_y_um:g}) um) would drive {n} samples beyond the "
            f"voltage limits [{lo:g}, {hi:g}] V while the stage settles; reduce the offset or the range"
        )


def render_whole_scan(
    shadow: ShadowEngine,
    request: ScanRequest,
    trajectory: Trajectory,
    plans: dict[str, PeriodicPlan | None],
    block: int,
) -> dict[str, int]:
    """Render a whole (finite) scan on ``shadow``: the move to its start, the settling lines and
    every line, as the engine plays it. Returns the samples clamped per axis; the drivers of
    ``shadow`` end where the stage would."""
    job = ScanJob(cast("Engine", shadow), request, trajectory.restarted(), plans)
    total = 0
    while not job.done:
        m = job.render(cast("Engine", shadow), block).volts.shape[1]
        total += m
        if m == 0 and not job.done:
            break
    return dict(shadow.clamped)


__all__ = ["ShadowEngine", "check_scan_start", "render_whole_scan"]
