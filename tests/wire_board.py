"""The link tests' board: hil_sim's simulated board on a socket pair (:class:`hil_sim.wire.WireBoard`).

The board side of the protocol exists once, in :mod:`hil_sim.board`; this module only builds it
for the tests (CAPABILITIES the tests expect, the ADC wired to the DAC so that the sensor reads
back the played codes, played codes kept) and turns its wire into a host transport. Faults are
the board's own options (:class:`hil_sim.board.BoardConfig`) and run-time hooks
(:attr:`hil_sim.board.Board.faults`). Not a test module.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np

from firmware_proto import Capabilities, Configure, Endpoint, Hello, MessageType, NakReason
from hil_sim.board import Board, BoardConfig
from hil_sim.errors import SimLinkClosedError
from hil_sim.wire import WireBoard
from piezod.config import default_sim_config_path
from piezod.errors import LinkClosedError
from piezod.link.transport import Transport, socket_transport

URL = "sim-wire://board"


@dataclass(frozen=True)
class Stats:
    """The board's counters and the injected faults, as the tests read them."""

    crc_errors: int
    frames_dropped: int
    underruns: int
    clamped_samples: int
    index_gaps: int
    overflows: int
    max_fifo_level: int
    samples_accepted: int
    bytes_corrupted_tx: int
    bytes_corrupted_rx: int
    frames_dropped_tx: int
    watchdogs: int
    requests: dict[str, int] = field(default_factory=dict)


class TestBoard:
    """A :class:`WireBoard` with the tests' defaults; ``**options`` are :class:`BoardConfig` fields.

    ``fifo_depth_samples`` 16384, ``board_serial`` 0xB0A4D, rates 100 Hz .. 200 kHz, amplifiers
    +-250 V by default.
    """

    __test__ = False

    def __init__(self, **options: Any) -> None:
        opts: dict[str, Any] = {
            "fifo_depth_samples": 16384,
            "board_serial": 0xB0A4D,
            "firmware_version": (0, 9, 1),
            "sample_rate_min_hz": 100,
            "sample_rate_max_hz": 200_000,
            "amplifier_ranges_v": ((-250.0, 250.0),) * 3,
            "adc_loopback": True,
            "record_played": True,
        }
        opts.update(options)
        seed = int(opts.pop("seed", 0))
        board = Board.from_scanner_file(default_sim_config_path(), seed=seed, config=BoardConfig(**opts))
        self.wire = WireBoard(board)
        self.board = board

    # -- wiring -------------------------------------------------------------------------------

    def connect(self) -> Transport:
        """A transport factory: a fresh wire to the board."""
        try:
            sock = self.wire.connect()
        except SimLinkClosedError as exc:
            raise LinkClosedError(f"{URL}: {exc}") from exc
        return socket_transport(sock, URL, read_timeout_s=0.01)

    def serve_unix(self, path: str) -> None:
        self.wire.serve_unix(path)

    def unplug(self, seconds: float) -> None:
        self.wire.unplug(seconds)

    @property
    def silent(self) -> bool:
        return self.wire.silent

    @silent.setter
    def silent(self, value: bool) -> None:
        self.wire.silent = value

    def close(self) -> None:
        self.wire.close()

    def __enter__(self) -> TestBoard:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- the board's state --------------------------------------------------------------------

    @property
    def drop_replies(self) -> dict[MessageType, int]:
        return self.board.faults.drop_replies

    @property
    def force_nak(self) -> dict[MessageType, tuple[NakReason, int]]:
        return self.board.faults.force_nak

    @property
    def hellos(self) -> list[Hello]:
        with self.wire.lock:
            return list(self.board.hellos)

    @property
    def config(self) -> Configure | None:
        with self.wire.lock:
            return self.board.configuration

    def capabilities(self) -> Capabilities:
        return self.board.capabilities

    @property
    def endpoint(self) -> Endpoint:
        return self.board.endpoint

    @property
    def last_played(self) -> int:
        with self.wire.lock:
            return int(self.board.status().last_played_index)

    @property
    def stats(self) -> Stats:
        with self.wire.lock:
            b = self.board
            c = b.counters
            return Stats(
                crc_errors=c.crc_errors,
                frames_dropped=c.frames_dropped,
                underruns=c.underruns,
                clamped_samples=c.clamped_samples,
                index_gaps=c.index_gaps,
                overflows=c.overflows,
                max_fifo_level=b.max_fifo_level,
                samples_accepted=b.samples_accepted,
                bytes_corrupted_tx=b.injected["bytes_out"],
                bytes_corrupted_rx=b.injected["bytes_in"],
                frames_dropped_tx=b.injected["frames_dropped"],
                watchdogs=c.watchdog_trips,
                requests=dict(b.requests),
            )

    def played_codes(self) -> tuple[int, np.ndarray]:
        """First index and all codes played (rows), assuming one contiguous run."""
        with self.wire.lock:
            played = list(self.board.played)
        if not played:
            return 0, np.zeros((0, self.board.capabilities.n_channels), dtype=np.int16)
        return played[0][0], np.concatenate([r for _, r in played])


def unix_socket_path(tmpdir: str, name: str = "board.sock") -> str:
    path = os.path.join(tmpdir, name)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    return path
