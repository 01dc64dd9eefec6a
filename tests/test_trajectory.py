"""The Trajectory interface the engine pulls from, and the raster as its implementation."""

from __future__ import annotations

import numpy as np
import pytest

from piezod.errors import EngineStateError, SafetyError
from piezod.scan import RasterParams, ScanBlock
from piezod.service.schemas import ScanRequest
from piezod.trajectory import SETTLE_LINES, PeriodicMotion, RasterTrajectory, Trajectory

FS = 10_000.0


def test_raster_motion_fast_axis_at_line_rate_slow_at_frame_rate() -> None:
    t = RasterTrajectory(RasterParams(range_um=10.0, line_rate_hz=2.0, lines=8, offset_x_um=1.0), FS)
    m = t.motion()
    assert m["x"] == PeriodicMotion(10.0, 2.0, 1.0)
    assert m["y"] is not None and m["y"].frequency_hz == pytest.approx(2.0 / 16) and m["y"].travel_um == 10.0
    rotated = RasterTrajectory(RasterParams(range_um=10.0, line_rate_hz=2.0, lines=8, rotation_deg=90.0), FS)
    ry = rotated.motion()["y"]
    assert ry is not None and ry.frequency_hz == 2.0  # the fast axis is y now
    flat = RasterTrajectory(RasterParams(range_um=10.0, line_rate_hz=2.0, lines=1, slow_range_um=0.0), FS)
    assert flat.motion()["y"] is None


def test_raster_from_request_start_settling_and_change() -> None:
    t = RasterTrajectory.from_request(ScanRequest(range_um=6.0, line_rate_hz=5.0, lines=4), FS)
    assert t.start_um() == pytest.approx({"x": -3.0, "y": -3.0})
    settle = t.settling()
    assert settle.params.frames == SETTLE_LINES and settle.params.lines == 1
    with pytest.raises(SafetyError):
        t.changed(line_rate_hz=5000.0)  # too few samples per line: refused before it applies
    key = t.key
    t.next_block(100)
    t.change(range_um=3.0)
    assert t.pending_index == 2000  # the next line
    t.next_block(1900)
    assert t.key is key
    t.next_block(10)
    assert t.key is not key and t.params.range_um == 3.0 and "range_um=3" in t.describe()


class _Hold(Trajectory):
    """A minimal trajectory: stand still at one point for ``n`` samples."""

    def __init__(self, n: int) -> None:
        super().__init__(FS)
        self._n, self._i = n, 0

    def next_block(self, n: int) -> ScanBlock:
        k = min(n, self._n - self._i)
        self._i += k
        z = np.zeros(k)
        return ScanBlock(
            self._i - k,
            z,
            z,
            z + 1.0,
            z,
            np.ones(k, np.int8),
            np.zeros(k, np.int64),
            np.zeros(k, np.int64),
            np.ones(k, bool),
        )

    @property
    def done(self) -> bool:
        return self._i >= self._n

    @property
    def next_index(self) -> int:
        return self._i

    @property
    def key(self) -> object:
        return None

    def motion(self) -> dict[str, PeriodicMotion | None]:
        return {"x": None, "y": None}

    def restarted(self) -> _Hold:
        return _Hold(self._n)


def test_a_new_trajectory_needs_only_the_abstract_methods() -> None:
    t = _Hold(5)
    assert t.start_um() == {"x": 1.0, "y": 0.0} and t.settling() is None and t.pending_index is None
    assert t.next_block(3).x_um.size == 3 and t.next_block(3).x_um.size == 2 and t.done
    with pytest.raises(EngineStateError, match="cannot be changed"):
        t.change(range_um=1.0)


def test_peek_shows_the_next_samples_with_a_pending_change_and_takes_none() -> None:
    t = RasterTrajectory.from_request(ScanRequest(range_um=6.0, line_rate_hz=5.0, lines=4), FS)
    t.next_block(1950)
    unchanged = t.peek(100)
    t.change(range_um=3.0)  # from the next line, sample 2000
    ahead = t.peek(100)
    assert t.next_index == 1950 and t.pending_index == 2000
    taken = t.next_block(50)
    taken2 = t.next_block(50)
    np.testing.assert_array_equal(ahead.x_um, np.concatenate([taken.x_um, taken2.x_um]))
    np.testing.assert_array_equal(ahead.x_um[:50], unchanged.x_um[:50])
    assert not np.allclose(ahead.x_um[50:], unchanged.x_um[50:])  # the new range from sample 2000
