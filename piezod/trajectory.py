"""Trajectories: what the engine pulls target blocks from (the raster today).

A :class:`Trajectory` yields the commanded stage positions block by block on the board's sample
clock (:class:`~piezod.scan.ScanBlock`: ``x_um``, ``y_um``, the fast direction and the line of
every sample) and says which steady periodic motion each axis performs
(:meth:`Trajectory.motion`), which is all the engine needs to plan the model's periodic loop and
to refuse what the stage cannot do. Planning the path is the trajectory's business; turning
targets into voltages is the engine's (:class:`~piezod.service.axes.AxisDriver`).

:class:`RasterTrajectory` is the raster scan (:class:`~piezod.scan.RasterGenerator`). A new
kind (a spiral, a Lissajous figure, a list of points) is a new subclass here plus a way to ask
for it (a request field), see ``docs/architecture.md``.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from piezod.errors import EngineStateError
from piezod.scan import RasterGenerator, RasterParams, ScanBlock

if TYPE_CHECKING:
    from piezod.service.schemas import ScanRequest


@dataclass(frozen=True, slots=True)
class PeriodicMotion:
    """The steady back-and-forth of one axis: ``travel_um`` peak to peak around ``center_um``."""

    travel_um: float
    frequency_hz: float
    center_um: float


class Trajectory(ABC):
    """Target positions block by block (stage coordinates, um) on the board's sample clock.

    Parameters
    ----------
    sample_rate_hz
        The board's sample clock.
    """

    def __init__(self, sample_rate_hz: float) -> None:
        self.sample_rate_hz = float(sample_rate_hz)

    @abstractmethod
    def next_block(self, n: int) -> ScanBlock:
        """The next (at most) ``n`` samples; fewer when the trajectory ends inside the block."""

    def peek(self, n: int) -> ScanBlock:
        """The next (at most) ``n`` samples without taking them (a pending change included).

        The runtime resonance part shapes each block with the targets after it (the host
        computes ahead of the board). A trajectory is a small state machine, so a copy runs ahead.
        """
        return copy.deepcopy(self).next_block(n)

    @property
    @abstractmethod
    def done(self) -> bool:
        """True when a finite trajectory has produced all its samples."""

    @property
    @abstractmethod
    def next_index(self) -> int:
        """Trajectory sample index of the next sample :meth:`next_block` produces."""

    @property
    @abstractmethod
    def key(self) -> object:
        """Identifies the parameters in force: a new object when a change has taken effect."""

    @abstractmethod
    def motion(self) -> dict[str, PeriodicMotion | None]:
        """Per scanned axis its periodic motion now (None: the axis stands still)."""

    def start_um(self) -> dict[str, float]:
        """The first target of every scanned axis (where the engine moves before starting)."""
        probe = self.restarted().next_block(1)
        return {"x": float(probe.x_um[0]), "y": float(probe.y_um[0])}

    @abstractmethod
    def restarted(self) -> Trajectory:
        """A fresh copy from the first sample, with the parameters in force now."""

    def speed_um_per_s(self) -> float:
        """The typical speed along the trajectory (the engine moves to its start at most this fast)."""
        moving = [m for m in self.motion().values() if m is not None]
        return max((2.0 * m.travel_um * m.frequency_hz for m in moving), default=0.0)

    @property
    def line(self) -> int:
        """The line (or other progress count) the next sample belongs to; 0 if none."""
        return 0

    def settling(self) -> Trajectory | None:
        """The unrecorded lead-in that lets the model's loop settle (None: none)."""
        return None

    @property
    def pending_index(self) -> int | None:
        """Sample index where a requested change takes effect (None: no change pending)."""
        return None

    def changed(self, **changes: Any) -> Trajectory:
        """A fresh trajectory with ``changes`` applied, to check them before :meth:`change`."""
        raise EngineStateError(f"a {type(self).__name__} cannot be changed while it runs")

    def change(self, **changes: Any) -> None:
        """Apply ``changes`` at the trajectory's next opportunity (the next line of a raster)."""
        raise EngineStateError(f"a {type(self).__name__} cannot be changed while it runs")

    def describe(self) -> str:
        """The parameters in force, ``key=value`` words (for the recording's change notes)."""
        return ""


#: Lines scanned before the recording of a raster starts (the loop settles, thesis section 3.1.2).
SETTLE_LINES = 2


class RasterTrajectory(Trajectory):
    """The raster scan (:class:`~piezod.scan.RasterGenerator`); changes apply at the next line."""

    def __init__(self, params: RasterParams, sample_rate_hz: float) -> None:
        super().__init__(sample_rate_hz)
        self._gen = RasterGenerator(params, sample_rate_hz)

    @classmethod
    def from_request(cls, request: ScanRequest, sample_rate_hz: float) -> RasterTrajectory:
        """The raster of a scan request."""
        return cls(
            RasterParams(
                range_um=request.range_um,
                line_rate_hz=request.line_rate_hz,
                lines=request.lines,
                slow_range_um=request.slow_range_um,
                offset_x_um=request.offset_x_um,
                offset_y_um=request.offset_y_um,
                rotation_deg=request.rotation_deg,
                overscan=request.overscan,
                slow_mode=request.slow_mode,
                frames=request.frames,
            ),
            sample_rate_hz,
        )

    @property
    def params(self) -> RasterParams:
        """The raster parameters in force."""
        return self._gen.params

    def next_block(self, n: int) -> ScanBlock:
        return self._gen.next_block(n)

    @property
    def done(self) -> bool:
        return self._gen.done

    @property
    def next_index(self) -> int:
        return self._gen.next_index

    @property
    def key(self) -> object:
        return self._gen.params

    @property
    def pending_index(self) -> int | None:
        return self._gen.pending_index

    @property
    def line(self) -> int:
        """The line (counted over frames) of the next sample."""
        return self._gen._line_at(self._gen.next_index)

    def speed_um_per_s(self) -> float:
        """The image-frame speed of the fast axis: ``2 * range * line rate``."""
        p = self._gen.params
        return 2.0 * p.range_um * p.line_rate_hz

    def motion(self) -> dict[str, PeriodicMotion | None]:
        """The fast axis at the line rate, the slow one at the frame rate (swapped past 45 deg)."""
        p = self._gen.params
        (x0, x1), (y0, y1) = p.extent_um()
        c, s = abs(math.cos(math.radians(p.rotation_deg))), abs(math.sin(math.radians(p.rotation_deg)))
        frame_rate = p.line_rate_hz / (2.0 * max(p.lines, 1))
        f_x = p.line_rate_hz if c >= s else frame_rate
        f_y = frame_rate if c >= s else p.line_rate_hz
        out: dict[str, PeriodicMotion | None] = {}
        for name, (lo, hi), f in (("x", (x0, x1), f_x), ("y", (y0, y1), f_y)):
            travel = hi - lo
            out[name] = PeriodicMotion(travel, f, 0.5 * (lo + hi)) if travel > 1e-9 else None
        return out

    def restarted(self) -> RasterTrajectory:
        return RasterTrajectory(self._gen.params, self.sample_rate_hz)

    def settling(self) -> RasterTrajectory:
        """:data:`SETTLE_LINES` lines on the first row (one way), not recorded."""
        settle = replace(self._gen.params, lines=1, frames=SETTLE_LINES, bidirectional_slow=False)
        return RasterTrajectory(settle, self.sample_rate_hz)

    def changed(self, **changes: Any) -> RasterTrajectory:
        return RasterTrajectory(replace(self._gen.params, **changes), self.sample_rate_hz)

    def change(self, **changes: Any) -> None:
        self._gen.change(**changes)

    def describe(self) -> str:
        p = self._gen.params
        return (
            f"range_um={p.range_um:g} line_rate_hz={p.line_rate_hz:g} offset_x_um={p.offset_x_um:g} "
            f"offset_y_um={p.offset_y_um:g} rotation_deg={p.rotation_deg:g}"
        )


__all__ = ["SETTLE_LINES", "PeriodicMotion", "RasterTrajectory", "Trajectory"]
