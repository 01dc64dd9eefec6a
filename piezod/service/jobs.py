"""The engine's jobs: what the stream plays now (hold, ramp, move, scan along a trajectory, a
voltage program). Each renders the next block of voltages (and targets) through the engine's
per-axis drivers; :class:`~piezod.service.engine.Engine` switches between them.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from piezod.errors import (
    SafetyError,
)
from piezod.service.schemas import (
    EngineState,
    ScanChange,
    ScanRequest,
)
from piezod.service.sync import SyncPlanner
from piezod.trajectory import RasterTrajectory, Trajectory

if TYPE_CHECKING:
    from piezod.service.axes import PeriodicPlan
    from piezod.service.engine import Engine

log = logging.getLogger("piezod.service.engine")

FloatArray = NDArray[np.float64]


#: Speed of the moves to the start of a scan, as a multiple of the scan's own speed (at most).
MOVE_SPEED_FACTOR = 1.0
#: Longest move a request may ask for (s): a slower one is refused with the speed it needs.
MAX_MOVE_S = 600.0
#: Most samples :meth:`Engine.check_scan` renders to check the start of a scan.
MAX_CHECK_SAMPLES = 200_000


@dataclass(slots=True)
class Chunk:
    """What a job produced for some samples.

    Attributes
    ----------
    volts
        ``(axes, n)`` voltages.
    targets
        ``(axes, n)`` target positions (um), NaN where the axis has no target.
    line
        Line number per sample (-1 outside scan lines).
    direction
        +1 trace / -1 retrace / 0 (per sample).
    record
        Whether the sample is recorded.
    label
        Experiment label id of the chunk (:meth:`Engine.label_id`), -1 for none.
    corrected
        Whether the chunk is the model's correction (its lines feed the sensitivity tracker).
    scale
        The tracked sensitivity scale the fast axis's travel was divided by.
    """

    volts: FloatArray
    targets: FloatArray
    line: NDArray[np.int64]
    direction: NDArray[np.int8]
    record: NDArray[np.bool_]
    label: int = -1
    corrected: bool = False
    scale: float = 1.0

    @classmethod
    def unlined(cls, volts: FloatArray, targets: FloatArray | None) -> Chunk:
        """A chunk without scan lines (hold, move, ramp): no line, no direction, ``record`` false."""
        n = volts.shape[1]
        return cls(
            volts,
            np.full(volts.shape, np.nan) if targets is None else targets,
            np.full(n, -1, dtype=np.int64),
            np.zeros(n, dtype=np.int8),
            np.zeros(n, dtype=bool),
        )


class Job(ABC):
    """Something the engine streams: produces chunks until :attr:`done`."""

    state: EngineState = "idle"
    done = False
    #: The engine's id of a client's job (scan, program, move; its readback is counted per job,
    #: :mod:`piezod.service.clipping`); -1 for the engine's own (hold, ramp).
    ident = -1

    @abstractmethod
    def render(self, engine: Engine, n: int) -> Chunk:
        """The next ``n`` samples (fewer when the job ends inside them)."""


class HoldJob(Job):
    """Hold the last voltages (idle)."""

    def __init__(self, state: EngineState = "idle") -> None:
        self.state = state

    def render(self, engine: Engine, n: int) -> Chunk:
        volts = np.stack([d.hold(n).voltage_v for d in engine.drivers.values()])
        return engine.chunk(volts, None)


class RampJob(Job):
    """Ramp every axis linearly to a voltage (the safe values by default), then hold."""

    def __init__(
        self, engine: Engine, target_v: dict[str, float] | None, rate_v_per_s: float, state: EngineState
    ):
        self.state = state
        volts = []
        for name, d in engine.drivers.items():
            goal = d.config.safe_voltage_v if target_v is None else target_v.get(name, d.voltage_v)
            volts.append(d.ramp_to(goal, rate_v_per_s, engine.rate_hz))
        length = max(v.size for v in volts)
        self._volts = np.stack([np.concatenate([v, np.full(length - v.size, v[-1])]) for v in volts])
        self._pos = 0

    def render(self, engine: Engine, n: int) -> Chunk:
        take = min(n, self._volts.shape[1] - self._pos)
        out = self._volts[:, self._pos : self._pos + take]
        self._pos += take
        self.done = self._pos >= self._volts.shape[1]
        return engine.chunk(out, None)


class MoveJob(Job):
    """A slew-limited move in position (through the inverse model), then done.

    The raised-cosine profile is computed block by block from where the axes are when the move
    begins, so a long move costs no memory and no time up front (and none under the engine lock).
    """

    state: EngineState = "moving"

    def __init__(self, engine: Engine, goal_um: dict[str, float], speed_um_per_s: float) -> None:
        self._goal = dict(goal_um)
        self._speed = float(speed_um_per_s)
        self._a: FloatArray | None = None
        self._b = np.empty(0)
        self._n = 0
        self._pos = 0
        self._moving = np.zeros(0, dtype=bool)

    def _begin(self, engine: Engine) -> None:
        a = np.array([d.position_um for d in engine.drivers.values()])
        b = np.array([self._goal.get(name, a[i]) for i, name in enumerate(engine.drivers)])
        self._a, self._b = a, b
        self._n = move_samples(float(np.max(np.abs(b - a))), self._speed, engine.rate_hz)
        self._moving = np.abs(b - a) > 0

    def render(self, engine: Engine, n: int) -> Chunk:
        if self._a is None:
            self._begin(engine)
        assert self._a is not None
        take = min(n, self._n - self._pos)
        need = max(d.lookahead for d in engine.drivers.values())
        # the block and the targets after it, which hold at the end of the move
        u = np.minimum(np.arange(self._pos + 1, self._pos + take + need + 1) / self._n, 1.0)
        w = 0.5 - 0.5 * np.cos(np.pi * u)
        path = self._a[:, None] + (self._b - self._a)[:, None] * w[None, :]
        targets, ahead = path[:, :take], path[:, take:]
        self._pos += take
        self.done = self._pos >= self._n
        volts = np.empty_like(targets)
        for i, d in enumerate(engine.drivers.values()):
            if self._moving[i]:
                volts[i] = engine.drive(d, d.corrected(targets[i], ahead[i]))
            else:
                volts[i] = d.hold(take).voltage_v
        return engine.chunk(volts, targets)


def move_samples(distance_um: float, speed_um_per_s: float, rate_hz: float) -> int:
    """Samples of a raised-cosine move of ``distance_um`` with peak speed ``speed_um_per_s`` (>= 1)."""
    duration = 0.5 * math.pi * abs(distance_um) / speed_um_per_s
    return max(1, math.ceil(duration * rate_hz))


class ScanJob(Job):
    """A scan along a :class:`~piezod.trajectory.Trajectory`: move to its start, settle, scan
    (recorded), then hold at the end."""

    state: EngineState = "scanning"

    def __init__(
        self,
        engine: Engine,
        request: ScanRequest,
        trajectory: Trajectory,
        plans: dict[str, PeriodicPlan | None] | None = None,
    ) -> None:
        self.request = request
        self._traj = trajectory
        # Settling: the trajectory's unrecorded lead-in (a raster: SETTLE_LINES on the first row).
        self._settle: Trajectory | None = trajectory.settling()
        self._name = request.name or "scan"
        self.label = engine.label_id(self._name)
        engine.set_label_note(self.label, None)
        # Changes (ctl change) start a new experiment "<name>.<part>" at the line where they apply.
        self._part = 1
        self._scanned = False
        self._change_text: list[str] = []
        self._plans = plans if plans is not None else engine.plans_for(trajectory)
        self._plan_key: object = trajectory.key
        for name, plan in self._plans.items():
            engine.drivers[name].use_plan(plan)
        speed = max(trajectory.speed_um_per_s() * MOVE_SPEED_FACTOR, 1.0)
        self._move: MoveJob | None = MoveJob(engine, trajectory.start_um(), speed)
        self._sync = SyncPlanner(engine.sync_schedule, request.pixels)

    def change(self, engine: Engine, change: ScanChange) -> None:
        updates = change.model_dump(exclude_none=True)
        engine.plans_for(self._traj.changed(**updates))  # refuse before it takes effect
        self._traj.change(**updates)
        self._change_text.append(" ".join(f"{k}={v:g}" for k, v in updates.items()))

    def _new_experiment(self, engine: Engine, start_index: int) -> None:
        """New parameters took effect at ``start_index``: a new experiment, noted in the recording."""
        if self._scanned:
            self._part += 1
            self.label = engine.label_id(f"{self._name}.{self._part}")
        engine.set_label_note(
            self.label,
            f"change: experiment {engine.label_names(np.array([self.label]))[0]} from "
            f"t = {start_index / engine.rate_hz:.6f} s: {'; '.join(self._change_text)} "
            f"(now {self._traj.describe()})",
        )
        self._change_text = []

    def _ahead(self, n: int) -> tuple[FloatArray, FloatArray]:
        """The ``n`` targets (x, y) after the block just taken, as far as the trajectory knows them
        (a settling lead-in is followed by the scan)."""
        if n <= 0:
            return np.empty(0), np.empty(0)
        x: list[FloatArray] = [np.empty(0)]
        y: list[FloatArray] = [np.empty(0)]
        left = n
        for traj in (self._settle, self._traj):
            if traj is not None and not traj.done and left > 0:
                block = traj.peek(left)
                x.append(block.x_um)
                y.append(block.y_um)
                left -= block.x_um.size
        return np.concatenate(x), np.concatenate(y)

    def render(self, engine: Engine, n: int) -> Chunk:
        if self._move is not None:
            chunk = self._move.render(engine, n)
            if self._move.done:
                self._move = None
            return chunk
        settling = self._settle is not None
        traj = self._settle if self._settle is not None else self._traj
        change_at = None if settling else self._traj.pending_index
        if change_at is not None and change_at > self._traj.next_index:
            n = min(n, change_at - self._traj.next_index)  # a block never spans a change
        block = traj.next_block(n)
        if self._settle is not None and self._settle.done:
            self._settle = None
        m = block.x_um.size
        if m == 0:
            self.done = self._settle is None and self._traj.done
            return engine.chunk(np.empty((len(engine.drivers), 0)), None)
        ahead = self._ahead(max(d.lookahead for d in engine.drivers.values()))
        if self._plan_key is not self._traj.key:
            self._plan_key = self._traj.key
            self._plans = engine.plans_for(self._traj)
            for name, plan in self._plans.items():
                engine.drivers[name].use_plan(plan)
            if not settling:
                self._new_experiment(engine, engine.render_index)
        targets = np.full((len(engine.drivers), m), np.nan)
        volts = np.empty((len(engine.drivers), m))
        x_scale = 1.0
        for i, (name, d) in enumerate(engine.drivers.items()):
            if name in ("x", "y"):
                tgt = block.x_um if name == "x" else block.y_um
                targets[i] = tgt
                plan = self._plans.get(name)
                scale = engine.tracked_scale(name) if self.request.correction else 1.0
                if name == "x":
                    x_scale = scale
                nxt = ahead[0] if name == "x" else ahead[1]
                if scale != 1.0 and plan is not None:
                    # the stage is `scale` times as sensitive as the model: shorten the travel
                    tgt = plan.center_um + (tgt - plan.center_um) / scale
                    nxt = plan.center_um + (nxt - plan.center_um) / scale
                if self.request.correction or plan is None:
                    volts[i] = engine.drive(d, d.corrected(tgt, nxt))
                else:
                    volts[i] = engine.drive(d, d.linear(tgt, plan))
            else:
                volts[i] = d.hold(m).voltage_v
        self.done = self._settle is None and self._traj.done
        if settling:
            return Chunk(
                volts, targets, np.full(m, -1, dtype=np.int64), block.fast_direction, np.zeros(m, bool)
            )
        if isinstance(self._traj, RasterTrajectory):
            p = self._traj.params
            spl = engine.rate_hz / p.line_rate_hz
            self._sync.add_block(engine.render_index, block, p.range_um, spl, p.overscan)
        record = np.full(m, self.request.record)
        self._scanned = True
        return Chunk(
            volts,
            targets,
            block.line,
            block.fast_direction,
            record,
            self.label,
            self.request.correction,
            x_scale,
        )

    @property
    def trajectory(self) -> Trajectory:
        return self._traj

    @property
    def line(self) -> int:
        return max(0, self._traj.line)


@dataclass(frozen=True, slots=True)
class Segment:
    """One piece of a voltage program: samples for one axis, labelled, recorded or not."""

    volts: FloatArray
    label: str
    record: bool = True


class ProgramJob(Job):
    """Play voltage segments on one axis (others hold), each preceded by a ramp to its start.

    This is how a calibration frame runs: the thesis's uncorrected triangles, settling loops
    unrecorded, then the recorded loops, each experiment labelled.
    """

    state: EngineState = "scanning"

    def __init__(self, engine: Engine, axis: str, segments: list[Segment], ramp_v_per_s: float) -> None:
        if axis not in engine.drivers:
            raise SafetyError(f"the scanner has no axis {axis!r}")
        lo, hi = engine.drivers[axis].limits
        for seg in segments:
            if seg.volts.size == 0 or not (np.all(seg.volts >= lo) and np.all(seg.volts <= hi)):
                raise SafetyError(f"segment {seg.label!r}: voltages outside [{lo:g}, {hi:g}] V or empty")
        self.axis = axis
        self._axis_index = list(engine.drivers).index(axis)
        self._segments = list(segments)
        self._ramp = ramp_v_per_s
        self._current: FloatArray | None = None
        self._current_seg: Segment | None = None
        self._pos = 0
        self._label = -1

    def _advance(self, engine: Engine) -> bool:
        if not self._segments:
            return False
        seg = self._segments.pop(0)
        driver = engine.drivers[self.axis]
        start = float(seg.volts[0])
        n_ramp = math.ceil(abs(start - driver.voltage_v) / self._ramp * engine.rate_hz)
        ramp = driver.voltage_v + (start - driver.voltage_v) * np.arange(1, n_ramp + 1) / max(n_ramp, 1)
        self._ramp_len = n_ramp
        self._current = np.concatenate([ramp, seg.volts])
        self._current_seg = seg
        self._pos = 0
        self._label = engine.label_id(seg.label)
        return True

    def render(self, engine: Engine, n: int) -> Chunk:
        if (self._current is None or self._pos >= self._current.size) and not self._advance(engine):
            self.done = True
            return engine.chunk(np.empty((len(engine.drivers), 0)), None)
        assert self._current is not None and self._current_seg is not None
        take = min(n, self._current.size - self._pos)
        piece = self._current[self._pos : self._pos + take]
        in_seg = np.arange(self._pos, self._pos + take) >= self._ramp_len
        self._pos += take
        volts = np.empty((len(engine.drivers), take))
        for i, d in enumerate(engine.drivers.values()):
            volts[i] = engine.drive(d, d.direct(piece)) if i == self._axis_index else d.hold(take).voltage_v
        chunk = engine.chunk(volts, None)
        chunk.record = in_seg & self._current_seg.record
        chunk.label = self._label
        if self._pos >= self._current.size and not self._segments:
            self.done = True
        return chunk
