"""``python -m hil_sim.stage_pipe``: hil_sim's stage behind a pipe, for the C firmware's host build.

The reference firmware (``firmware_proto/c``, host build) runs this as its ``--stage-cmd`` so that
the same simulated stage stands behind its DAC and ADC as behind :class:`hil_sim.board.Board`.
Binary protocol on stdin / stdout, little-endian:

- at start the helper writes ``b"PZST"``, ``u32 C`` and per channel ``f32 v_min, f32 v_max``
  (the amplifier range: the scanner's axis voltage limits, rounded outwards to float32);
- per request the firmware writes ``u32 n``, ``f64 dt_s`` and ``n * C`` ``f32`` volts (row by
  row: one tick, then the next); the helper steps the stage and answers ``n * C`` ``f32`` sensed
  positions (um, sensor noise included).

EOF on stdin ends the helper (exit 0).
"""

from __future__ import annotations

import argparse
import struct
import sys
from collections.abc import Sequence
from typing import BinaryIO

import numpy as np

from hil_sim.board import Board


def serve(board: Board, inp: BinaryIO, out: BinaryIO) -> int:
    """Answer step requests for ``board``'s stage until EOF on ``inp``; returns the requests served."""
    stage = board.stage
    C = stage.channels
    head = b"PZST" + struct.pack("<I", C)
    for lo, hi in board.capabilities.amplifier_ranges_v:
        head += struct.pack("<ff", lo, hi)
    out.write(head)
    out.flush()
    served = 0
    while True:
        req = inp.read(12)
        if len(req) < 12:
            return served
        n, dt = struct.unpack("<Id", req)
        raw = inp.read(4 * n * C)
        if len(raw) < 4 * n * C:
            return served
        volts = np.frombuffer(raw, dtype="<f4").reshape(n, C).T.astype(np.float64)
        sensed = stage.sense(stage.step(volts, dt))
        out.write(np.ascontiguousarray(sensed.T, dtype="<f4").tobytes())
        out.flush()
        served += 1


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: ``--config YAML``, ``--seed N``, ``--effect NAME=VALUE`` (repeatable)."""
    parser = argparse.ArgumentParser(prog="python -m hil_sim.stage_pipe", description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=None, help="scanner YAML (default: configs/sim-stage.yaml)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--effect", action="append", default=[])
    args = parser.parse_args(argv)
    board = Board.from_scanner_file(args.config, effects=args.effect, seed=args.seed)
    serve(board, sys.stdin.buffer, sys.stdout.buffer)
    return 0


if __name__ == "__main__":
    sys.exit(main())
