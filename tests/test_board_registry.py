"""Boards looked up by URL scheme (piezod.link.board.open_board): the framed serial board for
transport URLs, the simulated board for sim://, and a registered second implementation."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from piezod.config import ScannerConfig, default_sim_config_path, load_config
from piezod.errors import ConfigError
from piezod.link import board as board_mod
from piezod.link.board import Board, BoardSnapshot, SerialBoard, open_board
from piezod.link.events import LinkEvent
from piezod.link.plan import LinkSettings
from piezod.link.streamer import BlockSource, MatchedBlock
from piezod.service.engine import Engine
from piezod.service.schemas import MoveRequest
from piezod.simulator import SimBoard, parse_sim_url


@pytest.fixture(scope="module")
def config() -> ScannerConfig:
    return load_config(default_sim_config_path()).model_copy(update={"sample_rate_hz": 10_000.0})


def _ignore(_: LinkEvent) -> None:
    pass


@pytest.mark.parametrize(
    "url",
    ["/dev/ttyACM0", "socket://localhost:7777", "loop://", "rfc2217://h:1", "unix:///s", "usb://1209:0001"],
)
def test_transport_urls_get_the_serial_board(config: ScannerConfig, url: str) -> None:
    board = open_board(url, config, _ignore)
    assert type(board) is SerialBoard and board.url == url


def test_sim_urls_name_the_stage_effects_and_seed(config: ScannerConfig) -> None:
    assert parse_sim_url("sim://") == (default_sim_config_path(), (), 0)
    path, effects, seed = parse_sim_url("sim://configs/x.yaml?effect=drift=2.0&effect=delay=1e-4&seed=3")
    assert (path, effects, seed) == (Path("configs/x.yaml"), ("drift=2.0", "delay=1e-4"), 3)
    assert isinstance(open_board("sim://", config, _ignore), SimBoard)
    with pytest.raises(ConfigError, match="unknown option 'speed'"):
        parse_sim_url("sim://?speed=2")
    with pytest.raises(ConfigError, match="seed must be"):
        parse_sim_url("sim://?seed=-1")


class _MemoryBoard(Board):
    """A second Board implementation (what an NI-DAQ card would be): it plays into memory."""

    def __init__(
        self,
        url: str,
        config: ScannerConfig,
        on_event: Callable[[LinkEvent], None],
        settings: LinkSettings | None = None,
    ) -> None:
        super().__init__(config, on_event)
        self.url = url
        self.played: list[np.ndarray] = []

    def _do_open(self, timeout_s: float) -> tuple[str, ...]:
        return self.axes

    def _do_start(
        self,
        source: BlockSource,
        start_index: int,
        *,
        lead_s: float,
        block_samples: int,
        on_block: Callable[[MatchedBlock], None],
    ) -> None:
        self.played.append(source.next_block(block_samples))

    next_index = 0
    running = False
    connected = True

    def wait_ended(self, timeout_s: float) -> bool:
        return True

    def ended_by(self) -> str | None:
        return None

    def check(self) -> None:
        pass

    def restart(self, timeout_s: float) -> None:
        pass

    def finish(self, timeout_s: float) -> None:
        pass

    def snapshot(self) -> BoardSnapshot:
        return BoardSnapshot()

    def close(self, *, ramp_to_safe: bool = True) -> None:
        pass


class _Wild:
    def next_block(self, n: int) -> np.ndarray:
        return np.full((3, n), 1e4)  # far outside every limit


def test_a_registered_board_plugs_in_by_scheme_and_the_base_keeps_it_safe(
    config: ScannerConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(board_mod.BOARDS, "memdaq", f"{__name__}:_MemoryBoard")
    events: list[LinkEvent] = []
    board = open_board("memdaq://Dev1", config, events.append)
    assert isinstance(board, _MemoryBoard) and board.url == "memdaq://Dev1"
    board.open()
    board.start(_Wild(), 0, lead_s=0.1, block_samples=50, on_block=lambda _: None)
    (block,) = board.played
    for i, name in enumerate(board.axes):  # Board.limit ran before the implementation saw the block
        ax = config.axes[name]  # type: ignore[index]
        assert ax.voltage_min_v <= block[i].min() and block[i].max() <= ax.voltage_max_v
    assert events  # the clamping was reported


def test_a_board_that_cannot_be_loaded_is_a_one_line_config_error(
    config: ScannerConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(board_mod.BOARDS, "nidaq", "piezod.link.no_such_module:NidaqBoard")
    with pytest.raises(ConfigError, match=r"nidaq:// board cannot be loaded"):
        open_board("nidaq://Dev1", config, _ignore)


def test_the_engine_runs_on_the_sim_url_and_stops_the_simulator(
    config: ScannerConfig, tmp_path: Path
) -> None:
    engine = Engine(config, "sim://", recording_dir=tmp_path)
    board = engine._board
    assert isinstance(board, SimBoard)
    engine.open()
    try:
        sim = board.sim
        assert sim is not None and sim.poll() is None
        engine.move(MoveRequest(x_um=2.0, speed_um_per_s=50.0))
        assert engine.wait_idle(20.0) == "idle"
        assert engine.status().position_um["x"] == pytest.approx(2.0, abs=1e-6)
    finally:
        engine.close()
    assert board.sim is None and sim.poll() is not None


def test_probe_takes_sim_urls_and_names_other_boards(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from piezod.cli import main

    out = tmp_path / "caps.json"
    assert main(["probe", "sim://?seed=1", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["n_channels"] == 3
    monkeypatch.setitem(board_mod.BOARDS, "memdaq", f"{__name__}:_MemoryBoard")
    assert main(["probe", "memdaq://Dev1"]) == 2
    assert "names a memdaq:// board" in capsys.readouterr().err
