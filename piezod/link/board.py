"""The board at the level the engine uses: open, start streaming at an index, finish, status,
sensor blocks. :class:`SerialBoard` (the framed serial/USB protocol of ``firmware_proto``) is one
implementation; a DAQ card (NI-DAQmx, ...) would be a second one, a subclass providing the
``_do_*`` hooks, not a fork of :mod:`piezod.link`.

The public methods of :class:`Board` enforce the safety rules whatever the implementation
(python-microscope style): every block the engine produces passes :meth:`Board.limit`, which
clamps it to the axes' voltage limits and slew rates and reports what it had to change as a
:class:`~piezod.link.session.HostLimitFault`, before a ``_do_*`` hook sees it.

Boards are looked up by the URL's scheme (python-can's ``interface=`` style), by
:func:`open_board`:

``sim://[SCANNER.yaml][?effect=NAME=VALUE&seed=N]``
    The simulated board (:class:`piezod.simulator.SimBoard`: ``hil_sim`` on a pty of its own).
any other scheme registered in :data:`BOARDS` or as a ``piezod.boards`` entry point
    That board class (e.g. ``nidaq://Dev1`` -> an NI-DAQ :class:`Board` subclass in
    ``piezod/link/daq.py``, registered as ``BOARDS["nidaq"] = "piezod.link.daq:NidaqBoard"``).
everything else (device paths, ``socket://``, ``loop://``, ``rfc2217://``, ``unix://``, ``usb://``)
    :class:`SerialBoard`: the framed protocol over the transport the URL names
    (:func:`piezod.link.transport.open_transport`).
"""

from __future__ import annotations

import importlib
import logging
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points

import numpy as np
from numpy.typing import NDArray

from firmware_proto import NO_INDEX
from piezod.config import ScannerConfig
from piezod.errors import ConfigError
from piezod.link.session import BoardSession, HostLimitFault, LinkEvent, LinkSettings
from piezod.link.streamer import BlockSource, MatchedBlock, Streamer

FloatArray = NDArray[np.float64]


log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BoardSnapshot:
    """What the engine reports of the board (all zero before it reported anything)."""

    fifo_level_ms: float = 0.0
    last_played_index: int | None = None
    underruns: int = 0
    crc_errors: int = 0
    frames_dropped: int = 0


class Board(ABC):
    """A DAC/ADC board streaming one voltage per axis and sample, reading the sensor back.

    Parameters
    ----------
    config
        The scanner: axes, voltage limits, slew rates, sample rate.
    on_event
        Called with every :class:`~piezod.link.session.LinkEvent` (faults, link loss, clamping).
    """

    def __init__(self, config: ScannerConfig, on_event: Callable[[LinkEvent], None]) -> None:
        self.config = config
        self.on_event = on_event
        self.rate_hz = float(config.sample_rate_hz)
        self.axes: tuple[str, ...] = tuple(config.axes)
        self._last_v: dict[str, float] = {}

    # -- the public methods: safety here, the work in the hooks ---------------------------------

    def open(self, timeout_s: float = 10.0) -> None:
        """Connect and configure the board (outputs at their safe values); sets :attr:`axes`."""
        self.axes = self._do_open(timeout_s)
        self._last_v = {}

    def start(
        self,
        source: BlockSource,
        start_index: int,
        *,
        lead_s: float,
        block_samples: int,
        on_block: Callable[[MatchedBlock], None],
    ) -> None:
        """Stream ``source``'s blocks from sample ``start_index``, each through :meth:`limit`."""
        board = self

        sync = getattr(source, "sync_events", None)

        class _Limited:
            def next_block(self, n: int) -> FloatArray:
                return board.limit(source.next_block(n), board.next_index)

            def sync_events(self, first_index: int, n: int) -> list[tuple[int, int, int]]:
                return sync(first_index, n) if callable(sync) else []

        self._do_start(_Limited(), start_index, lead_s=lead_s, block_samples=block_samples, on_block=on_block)

    def capped_lead_s(self, lead_s: float) -> float:
        """The streaming lead the board can hold (s); default: ``lead_s`` unchanged."""
        return lead_s

    @property
    def position_sensor(self) -> bool:
        """Whether the board reads back a position sensor; default: it does."""
        return True

    def limit(self, volts: FloatArray, first_index: int) -> FloatArray:
        """``volts`` ``(axes, n)`` clamped to the voltage limits and slew rates (reported if changed)."""
        out = np.array(volts, dtype=np.float64, copy=True)
        for i, name in enumerate(self.axes):
            ax = self.config.axes[name]  # type: ignore[index]
            row = out[i]
            lo, hi = ax.voltage_min_v, ax.voltage_max_v
            step = ax.slew_rate_v_per_s / self.rate_hz * (1.0 + 1e-9) + 1e-9
            bad = ~np.isfinite(row) | (row < lo) | (row > hi)
            prev = self._last_v.get(name)
            steps = np.abs(np.diff(row if prev is None else np.concatenate(([prev], row))))
            if bad.any() or (steps.size and float(np.nanmax(steps, initial=0.0)) > step):
                worst = float(row[np.flatnonzero(bad)[0]]) if bad.any() else float(row[0])
                fixed = np.where(np.isfinite(row), np.clip(row, lo, hi), ax.safe_voltage_v)
                last = fixed[0] if prev is None else prev
                for k in range(fixed.size):  # the fault path only: sequential slew limiting
                    last = fixed[k] = min(max(fixed[k], last - step), last + step)
                count = int(np.count_nonzero(np.abs(fixed - np.nan_to_num(row, nan=np.inf)) > 1e-12))
                out[i] = fixed
                self.on_event(HostLimitFault(time.monotonic(), i, name, first_index, count, worst))
            if out.shape[1]:
                self._last_v[name] = float(out[i, -1])
        return out

    @property
    @abstractmethod
    def next_index(self) -> int:
        """Sample index of the next sample the stream asks for."""

    @property
    @abstractmethod
    def running(self) -> bool:
        """Streaming runs."""

    @property
    @abstractmethod
    def connected(self) -> bool:
        """The board is reachable now."""

    @abstractmethod
    def wait_ended(self, timeout_s: float) -> bool:
        """Wait until streaming ended (True) or the timeout passed (False)."""

    @abstractmethod
    def ended_by(self) -> str | None:
        """Why the last streaming run ended (``stop``, ``underrun``, ``link``, ...; None: unknown)."""

    @abstractmethod
    def check(self) -> None:
        """Raise the error that ended streaming, if any."""

    @abstractmethod
    def restart(self, timeout_s: float) -> None:
        """After a fault or reconnection: back to idle with the outputs at their safe values."""

    @abstractmethod
    def finish(self, timeout_s: float) -> None:
        """Play what was sent, then stop streaming."""

    @abstractmethod
    def snapshot(self) -> BoardSnapshot:
        """FIFO level, last played sample and error counters (cheap)."""

    @abstractmethod
    def close(self, *, ramp_to_safe: bool = True) -> None:
        """Disconnect (after ramping every output to its safe value)."""

    @abstractmethod
    def _do_open(self, timeout_s: float) -> tuple[str, ...]:
        """Connect and configure; return the axes in the order of the blocks' rows."""

    @abstractmethod
    def _do_start(
        self,
        source: BlockSource,
        start_index: int,
        *,
        lead_s: float,
        block_samples: int,
        on_block: Callable[[MatchedBlock], None],
    ) -> None:
        """Start streaming ``source`` (already limited) at ``start_index``."""


class SerialBoard(Board):
    """The framed serial / USB board (``firmware_proto``): a :class:`BoardSession` and a
    :class:`Streamer` keeping its FIFO filled by credits."""

    def __init__(
        self,
        url: str,
        config: ScannerConfig,
        on_event: Callable[[LinkEvent], None],
        settings: LinkSettings | None = None,
    ) -> None:
        super().__init__(config, on_event)
        self.url = url
        self.settings = settings or LinkSettings.from_config(config)
        self.session: BoardSession | None = None
        self.streamer: Streamer | None = None

    def _do_open(self, timeout_s: float) -> tuple[str, ...]:
        self.session = BoardSession.open(
            self.url, config=self.config, settings=self.settings, on_event=self.on_event, timeout_s=timeout_s
        )
        assert self.session.plan is not None
        if self.settings.budget is not None:
            log.info("%s", self.settings.budget.describe())
        return tuple(self.session.plan.axes)

    @property
    def position_sensor(self) -> bool:
        """False when the board's CAPABILITIES say it has no position sensor."""
        caps = self.session.capabilities if self.session is not None else None
        return caps is None or caps.position_sensor

    def capped_lead_s(self, lead_s: float) -> float:
        """The lead, capped at 60 % of the board FIFO (at high sample rates a long lead does not fit)."""
        caps = self.session.capabilities if self.session is not None else None
        if caps is None:
            return lead_s
        return min(lead_s, 0.6 * caps.fifo_depth_samples / self.rate_hz)

    def _do_start(
        self,
        source: BlockSource,
        start_index: int,
        *,
        lead_s: float,
        block_samples: int,
        on_block: Callable[[MatchedBlock], None],
    ) -> None:
        assert self.session is not None
        self.streamer = Streamer(
            self.session,
            source,
            lead_s=lead_s,
            block_samples=block_samples,
            on_block=on_block,
            frame_samples=self.session.settings.frame_samples,
        )
        self.streamer.start(start_index)

    @property
    def next_index(self) -> int:
        return self.streamer.next_index if self.streamer is not None else 0

    @property
    def running(self) -> bool:
        return self.streamer is not None and self.streamer.running

    @property
    def connected(self) -> bool:
        return self.session is not None and self.session.connected

    def wait_ended(self, timeout_s: float) -> bool:
        return self.streamer is not None and self.streamer.wait(timeout_s)

    def ended_by(self) -> str | None:
        runs = self.streamer.stats.runs if self.streamer is not None else []
        return runs[-1].ended_by if runs else None

    def check(self) -> None:
        if self.streamer is not None:
            self.streamer.check()

    def restart(self, timeout_s: float) -> None:
        assert self.session is not None
        self.session.prepare_restart(timeout_s=timeout_s)
        self._last_v = {}

    def finish(self, timeout_s: float) -> None:
        if self.streamer is not None and self.streamer.running:
            self.streamer.finish(timeout_s=timeout_s)

    def snapshot(self) -> BoardSnapshot:
        session = self.session
        if session is None:
            return BoardSnapshot()
        st = session.status
        fifo_ms, played = 0.0, None
        if st is not None and st.last_played_index != NO_INDEX:
            fifo_ms = 1000.0 * max(0, st.write_index - st.last_played_index - 1) / self.rate_hz
            played = int(st.last_played_index)
        c = session.counters()
        return BoardSnapshot(fifo_ms, played, c.underruns, c.crc_errors, c.frames_dropped_board)

    def close(self, *, ramp_to_safe: bool = True) -> None:
        if self.session is not None:
            self.session.close(ramp_to_safe=ramp_to_safe)


BoardFactory = Callable[[str, ScannerConfig, Callable[[LinkEvent], None], LinkSettings | None], Board]
"""What a board class is called with: ``(url, config, on_event, settings)``."""

#: Board implementations by URL scheme (``"module:Class"``, imported on first use). Third-party
#: packages add theirs as entry points of the group ``piezod.boards`` (name: the scheme).
BOARDS: dict[str, str] = {"sim": "piezod.simulator:SimBoard"}
BOARD_ENTRY_POINT_GROUP = "piezod.boards"


def board_scheme(url: str) -> str | None:
    """The URL's scheme when a board other than :class:`SerialBoard` is registered for it."""
    scheme = url.partition("://")[0].lower() if "://" in url else ""
    if scheme in BOARDS or any(ep.name == scheme for ep in entry_points(group=BOARD_ENTRY_POINT_GROUP)):
        return scheme
    return None


def board_class(url: str) -> BoardFactory:
    """The board implementation for ``url`` (see the module docstring): a registered one, else
    :class:`SerialBoard`.

    Raises
    ------
    ConfigError
        The registered implementation cannot be imported (names the scheme and the module).
    """
    scheme = board_scheme(url)
    if scheme is None:
        return SerialBoard
    target = BOARDS.get(scheme)
    try:
        if target is None:
            (ep,) = [e for e in entry_points(group=BOARD_ENTRY_POINT_GROUP) if e.name == scheme]
            factory: BoardFactory = ep.load()
            return factory
        module, _, name = target.partition(":")
        loaded: BoardFactory = getattr(importlib.import_module(module), name)
        return loaded
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"board URL {url!r}: the {scheme}:// board cannot be loaded ({exc})") from exc


def open_board(
    url: str,
    config: ScannerConfig,
    on_event: Callable[[LinkEvent], None],
    settings: LinkSettings | None = None,
) -> Board:
    """The :class:`Board` for ``url`` (not opened yet: call :meth:`Board.open`)."""
    return board_class(url)(url, config, on_event, settings)


__all__ = [
    "BOARDS",
    "BOARD_ENTRY_POINT_GROUP",
    "Board",
    "BoardFactory",
    "BoardSnapshot",
    "SerialBoard",
    "board_class",
    "board_scheme",
    "open_board",
]
