"""Pixel, line and frame clocks of a scan for the board's sync outputs (PROTOCOL.md 4.14).

An existing SPM controller acquires in step with piezod's raster from three digital outputs
(bit 0 pixel, bit 1 line, bit 2 frame clock):

- the frame and line clocks rise at the first sample of each frame / line (a line is a trace
  and its retrace) and fall half a line later, at the first sample of the retrace;
- the pixel clock rises at the first sample of each pixel and falls half a pixel later
  (``max(1, round(samples per pixel / 2))`` samples). A line holds ``pixels`` pixels on the
  trace and again on the retrace (the scan request's ``pixels``, the image width ``piezod image``
  uses); the pixels tile the image width (``range_um``) in the image
  frame, so the overscan at the turning points has no pixel clock. A pixel shorter than two
  samples has no visible pixel clock (its fall and the next rise share a tick).

:class:`SyncPlanner` turns the blocks of a scan into events as they are rendered (it carries
the last sample's line, frame, direction and pixel across blocks); :class:`SyncSchedule` keeps
them by absolute sample index for the streamer, which sends them as SYNC frames with the
SAMPLES of the same indices (and again after a go-back-N rewind).
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numpy.typing import NDArray

from piezod.scan import ScanBlock

PIXEL, LINE, FRAME = 0b001, 0b010, 0b100


class SyncSchedule:
    """Sync events by absolute sample index, merged per index (a later event wins its bits).

    Parameters
    ----------
    history
        Events this many samples behind the newest added are forgotten (a rewind never goes
        further back than the board FIFO).
    """

    def __init__(self, history: int) -> None:
        self.history = int(history)
        self._index: list[int] = []
        self._ev: dict[int, tuple[int, int]] = {}

    def add(self, index: int, lines: int, mask: int) -> None:
        """Set the outputs of ``mask`` to the bits of ``lines`` at sample ``index``."""
        old = self._ev.get(index)
        if old is None:
            bisect.insort(self._index, index)
            self._ev[index] = (lines & mask, mask)
        else:
            o_lines, o_mask = old
            self._ev[index] = ((o_lines & ~mask) | (lines & mask), o_mask | mask)
        horizon = self._index[-1] - self.history
        if self._index[0] < horizon:
            cut = bisect.bisect_left(self._index, horizon)
            for i in self._index[:cut]:
                del self._ev[i]
            del self._index[:cut]

    def between(self, first: int, n: int) -> list[tuple[int, int, int]]:
        """``(offset from first, lines, mask)`` of the events at indices ``[first, first + n)``."""
        lo = bisect.bisect_left(self._index, first)
        hi = bisect.bisect_left(self._index, first + n)
        return [(i - first, *self._ev[i]) for i in self._index[lo:hi]]

    def __len__(self) -> int:
        return len(self._index)


class SyncPlanner:
    """The sync events of one scan, block by block (see the module docstring).

    Parameters
    ----------
    schedule
        Where the events go.
    pixels
        Pixels per trace (and per retrace).
    """

    def __init__(self, schedule: SyncSchedule, pixels: int) -> None:
        if pixels < 1:
            raise ValueError(f"pixels must be >= 1, got {pixels}")
        self.schedule = schedule
        self.pixels = int(pixels)
        self._line = -1
        self._frame = -1
        self._dir = 0
        self._pix = -1

    def add_block(
        self, start_index: int, block: ScanBlock, range_um: float, samples_per_line: float, overscan: float
    ) -> None:
        """Add the events of ``block`` (its first sample at board index ``start_index``).

        ``range_um``, ``samples_per_line`` and ``overscan`` are the raster's in force for the
        block (a change applies at a line boundary, where no pixel is open).
        """
        m = block.fast_um.size
        if m == 0:
            return
        idx = start_index + np.arange(m, dtype=np.int64)
        line, frame, direction = block.line, block.frame, block.fast_direction.astype(np.int64)
        u = (block.fast_um / range_um + 0.5) * self.pixels
        pix = np.where((u >= 0) & (u < self.pixels), np.floor(u), -1).astype(np.int64)
        prev_line = np.concatenate(([self._line], line[:-1]))
        prev_frame = np.concatenate(([self._frame], frame[:-1]))
        prev_dir = np.concatenate(([self._dir], direction[:-1]))
        prev_pix = np.concatenate(([self._pix], pix[:-1]))
        new_line = line != prev_line
        new_frame = frame != prev_frame
        to_retrace = (direction < 0) & (prev_dir > 0) & ~new_line
        new_pix = (pix >= 0) & ((pix != prev_pix) | new_line | (direction != prev_dir))
        # samples per pixel: half a line spans the travel (range + overscan on both sides)
        per_pixel = 0.5 * samples_per_line / (1.0 + 2.0 * overscan) / self.pixels
        half_pixel = max(1, math.floor(0.5 * per_pixel + 0.5))
        sched = self.schedule
        for i in np.flatnonzero(to_retrace):
            sched.add(int(idx[i]), 0, LINE | FRAME)
        for i in np.flatnonzero(new_line):
            bits = LINE | (FRAME if new_frame[i] else 0)
            sched.add(int(idx[i]), bits, bits)
        ends: NDArray[np.int64] = idx[new_pix] + half_pixel
        for i, end in zip(np.flatnonzero(new_pix), ends, strict=True):
            sched.add(int(idx[i]), PIXEL, PIXEL)
            sched.add(int(end), 0, PIXEL)
        self._line, self._frame = int(line[-1]), int(frame[-1])
        self._dir, self._pix = int(direction[-1]), int(pix[-1])


__all__ = ["FRAME", "LINE", "PIXEL", "SyncPlanner", "SyncSchedule"]
