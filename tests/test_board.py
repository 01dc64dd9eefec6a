"""The simulated board core (hil_sim.board) against an in-memory host built from firmware_proto.Endpoint.

Everything runs on a fake clock: the host advances ``now`` and hands bytes back and forth.
"""

from __future__ import annotations

import struct
import time
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest
from cobs import cobs
from numpy.typing import ArrayLike, NDArray

from firmware_proto import (
    Ack,
    Acked,
    BoardState,
    Capabilities,
    ChannelConfig,
    Configure,
    Endpoint,
    Event,
    Fault,
    FaultCode,
    FaultFlags,
    Frame,
    Heartbeat,
    Hello,
    Message,
    Nacked,
    Nak,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    Sync,
    VersionMismatchError,
    encode,
)
from hil_sim.board import Board, BoardConfig, slew_limit
from hil_sim.stage import Stage, StageConfig
from piezod.config import default_sim_config_path, load_config

DAC_V_PER_CODE = 250.0 / 32768
ADC_UM_PER_CODE = 1e-3
RANGES = ((-230.0, 230.0),) * 3


@pytest.fixture(scope="module")
def stage_config() -> StageConfig:
    cfg = StageConfig.from_file(default_sim_config_path())
    return cfg.model_copy(update={"sensor_noise_nm_rms": 0.0})


class SpyStage(Stage):
    """A stage that records every voltage block it is driven with."""

    def __init__(self, config: StageConfig) -> None:
        super().__init__(config)
        self.blocks: list[tuple[NDArray[np.float64], float]] = []

    def step(self, voltage_v: Any, dt_s: float) -> NDArray[np.float64]:
        self.blocks.append((np.array(voltage_v, dtype=np.float64), dt_s))
        return super().step(voltage_v, dt_s)

    def voltages(self) -> NDArray[np.float64]:
        return np.concatenate([b for b, _ in self.blocks], axis=1)

    def times(self, t_start: float) -> NDArray[np.float64]:
        dts = np.concatenate([np.full(b.shape[1], dt) for b, dt in self.blocks])
        return t_start + np.cumsum(dts)


def make_board(stage_config: StageConfig, **cfg: Any) -> tuple[Board, SpyStage]:
    stage = SpyStage(stage_config)
    board = Board(stage, BoardConfig(amplifier_ranges_v=RANGES, **cfg), now=0.0)
    return board, stage


def chan(
    v_min: float = -230.0, v_max: float = 230.0, safe_v: float = 0.0, ramp_v_per_s: float = 1000.0
) -> ChannelConfig:
    return ChannelConfig.from_volts(
        v_min=v_min,
        v_max=v_max,
        safe_v=safe_v,
        dac_v_per_code=DAC_V_PER_CODE,
        dac_offset_v=0.0,
        ramp_v_per_s=ramp_v_per_s,
        adc_um_per_code=ADC_UM_PER_CODE,
        adc_offset_um=0.0,
    )


def configure(
    rate_hz: int = 10_000,
    heartbeat_ms: int = 60_000,
    status_ms: int = 10,
    decimation: int = 1,
    channels: Sequence[ChannelConfig] | None = None,
) -> Configure:
    chans = tuple(channels) if channels is not None else (chan(), chan(), chan())
    return Configure(rate_hz, heartbeat_ms, status_ms, decimation, chans)


class Link:
    """An in-memory host: an Endpoint wired to the board, on a fake clock."""

    def __init__(self, board: Board, now: float = 0.0, session_id: int = 1) -> None:
        self.board = board
        self.host = Endpoint()
        self.now = now
        self.session_id = session_id
        self.events: list[Event] = []

    def pump(self, dt: float = 0.0, raw: bytes = b"") -> list[Event]:
        self.now += dt
        self.board.feed(self.host.data_to_send() + raw, self.now)
        events = self.host.receive(self.board.data_to_send(), self.now)
        self.events += events
        return events

    def run(self, seconds: float, step: float = 1e-3) -> list[Event]:
        """Let time pass in steps without the host sending anything."""
        out: list[Event] = []
        for _ in range(round(seconds / step)):
            out += self.pump(step)
        return out

    def request(self, msg: Message, dt: float = 1e-3) -> Acked | Nacked:
        seq = self.host.send(msg, self.now)
        for event in self.pump(dt):
            if isinstance(event, Acked | Nacked) and event.seq == seq:
                return event
        raise AssertionError(f"no reply to {msg}")

    def send(self, msg: Message) -> None:
        self.host.send(msg, self.now)

    def hello(self) -> Capabilities:
        reply = self.request(Hello(session_id=self.session_id))
        assert isinstance(reply, Acked), reply
        assert isinstance(reply.reply, Capabilities)
        return reply.reply

    def setup(self, conf: Configure | None = None) -> None:
        """HELLO + CONFIGURE, then wait for IDLE."""
        self.hello()
        reply = self.request(conf if conf is not None else configure())
        assert isinstance(reply, Acked), reply
        for _ in range(2000):
            if self.board.state is BoardState.IDLE:
                return
            self.pump(1e-3)
        raise AssertionError("board never reached IDLE after CONFIGURE")

    def msgs(self, kind: type[Message], events: Sequence[Event] | None = None) -> list[Any]:
        src = self.events if events is None else events
        return [e.msg for e in src if isinstance(e, Frame) and isinstance(e.msg, kind)]

    def settle(self) -> None:
        """Deliver what the host queued, then wait one status period for a fresh STATUS."""
        self.pump(1e-3)
        self.pump(0.011)

    def last_status(self) -> Status:
        statuses = self.msgs(Status)
        assert statuses, "no STATUS received"
        status: Status = statuses[-1]
        return status


def codes_for(volts: ArrayLike) -> NDArray[np.int16]:
    return np.asarray(np.rint(np.asarray(volts) / DAC_V_PER_CODE), dtype=np.int16)


def sine_codes(n: int, first: int = 0, rate_hz: float = 10_000.0, amp_v: float = 100.0) -> NDArray[np.int16]:
    t = (first + np.arange(n)) / rate_hz
    v = np.stack(
        [amp_v * np.sin(2 * np.pi * 5 * t), 0.5 * amp_v * np.sin(2 * np.pi * 3 * t), 0.2 * amp_v * t], 1
    )
    return codes_for(v)


def send_samples(link: Link, first: int, codes: NDArray[np.int16], frame: int = 1000) -> None:
    for lo in range(0, codes.shape[0], frame):
        link.send(Samples(first + lo, codes[lo : lo + frame]))


def raw_frame(version: int, typ: int, flags: int, seq: int, payload: bytes) -> bytes:
    body = struct.pack("<BBBBI", version, typ, flags, 0, seq) + payload
    stuffed: bytes = cobs.encode(body + struct.pack("<I", zlib.crc32(body)))
    return stuffed + b"\x00"


# ---------------------------------------------------------------------------------------------
# handshake and configuration


def test_handshake_capabilities(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    caps = link.hello()
    assert caps.n_channels == 3
    assert (caps.dac_bits, caps.adc_bits) == (16, 16)
    assert caps.fifo_depth_samples == 65536
    assert caps.amplifier_ranges_v == RANGES
    assert caps.firmware_version == (1, 0, 0)
    assert caps.sample_rate_min_hz <= 100_000 <= caps.sample_rate_max_hz
    assert caps.max_samples_per_frame >= 1000
    assert board.session_id == 1
    assert not link.msgs(Status), "an unconfigured board sends no STATUS"


def test_from_scanner_file_uses_the_scanner_limits() -> None:
    board = Board.from_scanner_file(None, effects=("drift=0.4",), seed=3)
    scanner = load_config(default_sim_config_path())
    assert board.capabilities.amplifier_ranges_v == tuple(
        (scanner.axes[a].voltage_min_v, scanner.axes[a].voltage_max_v) for a in ("x", "y", "z")
    )
    assert board.stage.config.effects.drift is not None
    with pytest.raises(ValueError, match="bogus"):
        Board.from_scanner_file(None, effects=("bogus=1",))


def test_requests_before_hello_get_bad_state(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    reply = link.request(configure())
    assert isinstance(reply, Nacked)
    assert reply.reply.reason is NakReason.BAD_STATE
    assert board.configuration is None
    link.hello()
    reply = link.request(Start(0))
    assert isinstance(reply, Nacked) and reply.reply.reason is NakReason.BAD_STATE
    assert reply.reply.detail == BoardState.UNCONFIGURED


def test_version_mismatch(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    reply = link.request(Hello(protocol_version=2, session_id=9))
    assert isinstance(reply, Nacked)
    assert reply.reply.reason is NakReason.VERSION_MISMATCH and reply.reply.detail == 1
    assert isinstance(reply.error(), VersionMismatchError)
    # a frame of a foreign version other than HELLO / NAK: dropped, NAKed with the board's version
    naks_before = len(link.msgs(Nak))
    link.pump(1e-3, raw=raw_frame(2, 0x06, 0x01, 77, struct.pack("<QII", 0, 0, 0)))
    naks = link.msgs(Nak)
    assert len(naks) == naks_before + 1
    assert naks[-1].reason is NakReason.VERSION_MISMATCH and naks[-1].nacked_seq == 77
    assert board.endpoint.decoder_stats.bad_version == 1


def test_unknown_type_is_nacked_and_counted(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    link.pump(1e-3, raw=raw_frame(1, 0x30, 0x01, 5, b"xyz"))
    link.pump(0.011)
    naks = link.msgs(Nak)
    assert naks and naks[-1].reason is NakReason.UNKNOWN_TYPE and naks[-1].nacked_type == 0x30
    assert link.last_status().frames_dropped == 1


@pytest.mark.parametrize(
    ("conf", "reason", "offset"),
    [
        (configure(channels=(chan(), chan(v_max=240.0), chan())), NakReason.BAD_VALUE, 8 + 16 + 32 + 10),
        (configure(channels=(chan(v_min=-231.0), chan(), chan())), NakReason.BAD_VALUE, 8 + 16 + 8),
        (configure(rate_hz=300_000), NakReason.UNSUPPORTED, 8),
        (configure(heartbeat_ms=5), NakReason.BAD_VALUE, 12),
        (configure(channels=(chan(), chan())), NakReason.BAD_VALUE, 20),
    ],
)
def test_configure_out_of_limits_is_refused_and_never_applied(
    stage_config: StageConfig, conf: Configure, reason: NakReason, offset: int
) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    good = configure(rate_hz=20_000)
    link.setup(good)
    reply = link.request(conf)
    assert isinstance(reply, Nacked)
    assert (reply.reply.reason, reply.reply.detail) == (reason, offset)
    faults = link.msgs(Fault)
    assert faults[-1].code is FaultCode.CONFIG_REJECTED and faults[-1].detail == offset
    assert board.configuration == good
    link.pump(0.011)
    assert link.last_status().fault_flags & FaultFlags.CONFIG_REJECTED


def test_configure_refused_on_a_board_clock_that_cannot_make_the_rate(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config, sample_clock_hz=1_000_000)
    link = Link(board)
    link.hello()
    reply = link.request(configure(rate_hz=3_000))
    assert isinstance(reply, Nacked) and reply.reply.reason is NakReason.UNSUPPORTED
    assert board.state is BoardState.UNCONFIGURED
    assert isinstance(link.request(configure(rate_hz=4_000)), Acked)


def test_configure_ramps_to_the_new_safe_value(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.hello()
    conf = configure(channels=(chan(safe_v=50.0, ramp_v_per_s=500.0), chan(), chan(safe_v=-20.0)))
    assert isinstance(link.request(conf), Acked)
    assert board.state is BoardState.RAMPING
    link.run(0.09)
    assert board.state is BoardState.RAMPING
    link.run(0.02)
    assert board.state is BoardState.IDLE
    np.testing.assert_allclose(board.output_voltages_v, [50.0, 0.0, -20.0], atol=DAC_V_PER_CODE)
    states = [s.state for s in link.msgs(Status)]
    assert states[0] is BoardState.RAMPING and BoardState.IDLE in states


# ---------------------------------------------------------------------------------------------
# playing samples


def start_running(link: Link, n: int, start: int = 1000, prefill: int = 500) -> NDArray[np.int16]:
    assert isinstance(link.request(Start(start, prefill)), Acked)
    codes = sine_codes(n, start)
    send_samples(link, start, codes)
    link.pump(0.0)
    assert link.board.state is BoardState.RUNNING
    return codes


def test_plays_at_the_configured_rate_and_reports_credits(stage_config: StageConfig) -> None:
    board, stage = make_board(stage_config)
    link = Link(board)
    link.setup()
    start = 1000
    codes = start_running(link, 3000, start)
    t_fill = link.now
    link.pump(0.1)  # 0.1 s after the fill: ticks at t_fill + k * 100 us, k = 1..1000
    st = board.status()
    assert st.last_played_index == start + 999
    assert st.write_index == start + 3000
    assert st.fifo_free_samples == 65536 - 2000
    assert st.credit_limit == start + 3000 + 65536 - 2000
    assert link.now < board.next_deadline() <= link.now + 1e-4 + 1e-9  # the next tick
    link.run(0.05)
    assert board.status().last_played_index == start + 1499
    assert link.last_status().state is BoardState.RUNNING
    link.run(0.02)  # the stage is stepped in blocks of up to a status period
    # the voltages reaching the stage after the fill are exactly the DAC codes, one per tick
    v = stage.voltages()
    t = stage.times(0.0)
    run = t > t_fill + 1e-9
    assert np.count_nonzero(run) >= 1500
    np.testing.assert_allclose(v[:, run][:, :1500].T, codes[:1500] * DAC_V_PER_CODE, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.diff(t[run]), 1e-4, rtol=1e-9)
    assert t[run][0] == pytest.approx(t_fill + 1e-4)


def test_sensor_is_the_stage_position_through_the_adc(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    codes = start_running(link, 3000, start=0)
    link.run(0.25)
    sensors = link.msgs(Sensor)
    assert sensors
    got = np.concatenate([s.codes for s in sensors])
    idx = np.concatenate([s.indices for s in sensors])
    np.testing.assert_array_equal(idx, np.arange(got.shape[0]))
    assert all(s.stride == 1 for s in sensors)
    assert got.shape[0] >= 2400  # flushed at least every status period
    # an independent stage, from rest, driven by the same voltages
    ref = Stage(stage_config).step(codes[: got.shape[0]].T * DAC_V_PER_CODE, 1e-4)
    expect = np.rint(ref / ADC_UM_PER_CODE).T
    assert np.max(np.abs(got - expect)) <= 1
    assert np.ptp(got[:, 0]) > 5000  # the stage really moved (tens of um)


def test_sensor_decimation(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup(configure(decimation=4))
    start_running(link, 2000, start=10)
    link.run(0.15)
    sensors = link.msgs(Sensor)
    idx = np.concatenate([s.indices for s in sensors])
    assert all(s.stride == 4 for s in sensors)
    np.testing.assert_array_equal(idx, 10 + 4 * np.arange(idx.size))
    assert idx[-1] >= 10 + 1400


def test_underrun_reports_the_last_valid_index_and_holds(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    codes = start_running(link, 300, start=5000, prefill=300)
    link.run(0.05)
    faults = link.msgs(Fault)
    assert [f.code for f in faults] == [FaultCode.UNDERRUN]
    assert faults[0].index == 5299
    st = link.last_status()
    assert st.state is BoardState.IDLE
    assert st.underruns == 1 and st.last_played_index == 5299
    assert st.fault_flags & FaultFlags.UNDERRUN
    np.testing.assert_allclose(board.output_voltages_v, codes[-1] * DAC_V_PER_CODE)
    # a new START clears the latched flags
    assert isinstance(link.request(Start(6000, 10)), Acked)
    link.pump(0.011)
    assert link.last_status().fault_flags == FaultFlags.NONE


def test_stop_after_index_is_not_an_underrun(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    start_running(link, 3000, start=0)
    assert isinstance(link.request(Stop(1499)), Acked)
    link.run(0.3)
    st = link.last_status()
    assert st.state is BoardState.IDLE and st.last_played_index == 1499
    assert st.underruns == 0 and not link.msgs(Fault)
    assert st.fifo_free_samples == 65536


def test_stop_now_and_ramp_to_safe(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup(configure(channels=(chan(ramp_v_per_s=200.0),) * 3))
    assert isinstance(link.request(Start(0, 1)), Acked)
    send_samples(link, 0, np.tile(codes_for([100.0, -50.0, 20.0]), (5000, 1)))
    link.run(0.1)
    assert isinstance(link.request(RampToSafe()), Acked)
    assert board.state is BoardState.RAMPING
    link.run(0.1)  # ramp at 200 V/s: 100 V -> 80 V
    assert isinstance(link.request(Stop()), Acked)
    held = board.output_voltages_v
    assert held[0] == pytest.approx(80.0, abs=0.3) and held[2] == pytest.approx(0.0, abs=1e-9)
    link.run(0.1)
    assert board.state is BoardState.IDLE
    np.testing.assert_allclose(board.output_voltages_v, held)


# ---------------------------------------------------------------------------------------------
# limits, watchdog


def test_out_of_limit_codes_are_clamped_and_reported(stage_config: StageConfig) -> None:
    board, stage = make_board(stage_config)
    link = Link(board)
    limits = (chan(v_min=-100.0, v_max=100.0), chan(), chan())
    link.setup(configure(channels=limits))
    assert isinstance(link.request(Start(0, 1)), Acked)
    codes = np.zeros((1000, 3), dtype=np.int16)
    codes[:, 0] = codes_for(np.linspace(0.0, 200.0, 1000))
    codes[10, 1] = -32768
    send_samples(link, 0, codes)
    link.run(0.2)
    fault = [f for f in link.msgs(Fault) if f.code is FaultCode.LIMIT_VIOLATION]
    assert len(fault) == 1
    assert (fault[0].channel, fault[0].index, fault[0].detail) == (1, 10, 0x8000)
    n_over = int(np.count_nonzero(codes[:, 0] > limits[0].code_max))
    st = link.last_status()
    assert st.clamped_samples == n_over + 1
    assert st.fault_flags & FaultFlags.LIMIT_VIOLATION
    v = stage.voltages()
    assert v[0].max() <= limits[0].v_max + 1e-9 and v[0].max() == pytest.approx(limits[0].v_max)
    assert v[1].min() >= -230.0


def test_watchdog_ramps_to_safe_and_is_reported_on_the_next_hello(stage_config: StageConfig) -> None:
    board, stage = make_board(stage_config)
    link = Link(board)
    link.setup(configure(heartbeat_ms=100, channels=(chan(ramp_v_per_s=1000.0),) * 3))
    assert isinstance(link.request(Start(0, 1)), Acked)
    send_samples(link, 0, np.tile(codes_for([100.0, -50.0, 0.0]), (20_000, 1)))
    link.pump(1e-3)
    t_last = link.now  # the host falls silent
    fired_at = None
    for _ in range(300):
        events = link.pump(1e-3)
        if any(f.code is FaultCode.WATCHDOG for f in link.msgs(Fault, events)):
            fired_at = link.now
            break
    assert fired_at is not None
    assert t_last + 0.1 <= fired_at <= t_last + 0.1 + 1.001e-3
    wd = link.msgs(Fault)[-1]
    last_played = wd.index
    assert last_played == board.status().last_played_index
    assert link.last_status().state is BoardState.RAMPING
    link.run(0.1)  # 100 V at 1000 V/s
    assert board.state is BoardState.IDLE
    np.testing.assert_allclose(board.output_voltages_v, 0.0, atol=1e-9)
    # the ramp: monotonic, never faster than the configured rate
    v = stage.voltages()
    t = stage.times(0.0)
    ramp = t >= fired_at - 1e-3
    slope = np.abs(np.diff(v[:, ramp], axis=1)) / np.diff(t[ramp])
    assert slope.max() <= 1000.0 * (1 + 1e-9)
    assert np.all(np.diff(v[0, ramp]) <= 1e-12) and np.all(np.diff(v[1, ramp]) >= -1e-12)
    trips = board.counters.watchdog_trips
    link.run(0.5)
    assert board.counters.watchdog_trips == trips == 1, "fires once per silence"
    # a new host: HELLO -> CAPABILITIES, STATUS with WATCHDOG latched, FAULT WATCHDOG again
    new = Link(board, now=link.now, session_id=2)
    new.hello()
    st = new.last_status()
    assert st.state is BoardState.IDLE and st.fault_flags & FaultFlags.WATCHDOG
    faults = new.msgs(Fault)
    assert faults and faults[-1].code is FaultCode.WATCHDOG and faults[-1].index == last_played
    assert board.session_id == 2


# ---------------------------------------------------------------------------------------------
# SAMPLES acceptance, corruption, retransmission


def test_index_gap_duplicate_overlap_overflow(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config, fifo_depth_samples=1024)
    link = Link(board)
    link.setup()
    assert isinstance(link.request(Start(0, 1024)), Acked)  # stays ARMED: prefill never reached
    block = sine_codes(100)
    link.send(Samples(0, block))
    link.send(Samples(200, block))  # a frame before it was lost
    link.pump(1e-3)
    assert board.status().write_index == 100
    gap = link.msgs(Fault)[-1]
    assert gap.code is FaultCode.INDEX_GAP and gap.index == 100
    link.send(Samples(0, block))  # duplicate
    link.send(Samples(50, block))  # partial overlap: rows 50..99 dropped, 100..149 stored
    link.settle()
    st = link.last_status()
    assert (st.write_index, st.index_gaps, st.frames_dropped) == (150, 1, 2)
    assert st.fifo_free_samples == 1024 - 150
    link.send(Samples(150, sine_codes(1000)))  # beyond the credit limit 150 + 874
    link.settle()
    over = link.msgs(Fault)[-1]
    assert over.code is FaultCode.OVERFLOW and over.index == 150
    st = link.last_status()
    assert (st.write_index, st.overflows, st.frames_dropped) == (150, 1, 3)
    assert st.fault_flags & FaultFlags.INDEX_GAP and st.fault_flags & FaultFlags.OVERFLOW
    assert board.state is BoardState.ARMED


def test_samples_with_wrong_channel_count_or_in_idle_are_dropped(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    link.send(Samples(0, sine_codes(10)))  # IDLE
    assert isinstance(link.request(Start(0, 5)), Acked)
    link.send(Samples(0, np.zeros((10, 2), dtype=np.int16)))
    link.settle()
    st = link.last_status()
    assert st.frames_dropped == 2 and st.write_index == 0


def test_corrupted_frames_are_counted(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    wire = bytearray(encode(Heartbeat(123456789), seq=50))
    i = len(wire) // 2
    wire[i] = wire[i] ^ 0x40 if wire[i] ^ 0x40 else wire[i] ^ 0x20
    link.pump(1e-3, raw=bytes(wire))
    link.pump(0.011)
    st = link.last_status()
    assert (st.crc_errors, st.frames_dropped) == (1, 1)
    assert st.fault_flags & FaultFlags.CRC_ERRORS
    fault = link.msgs(Fault)[-1]
    assert fault.code is FaultCode.CRC_ERRORS and fault.detail == 1


def test_injected_corruption_in_both_directions(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config, corrupt_rate=0.02, corrupt_in_rate=0.02, seed=4)
    link = Link(board)
    for _ in range(200):
        link.send(Heartbeat(1))
        link.pump(1e-3)
    dec = board.endpoint.decoder_stats
    assert 0 < dec.errors < 200 and dec.frames_ok + dec.errors >= 150
    assert board.counters.frames_dropped == dec.errors
    assert board.counters.crc_errors == dec.bad_crc > 0
    # outgoing: the host's decoder sees damaged frames (the requests are retried until answered)
    board2, _ = make_board(stage_config, corrupt_rate=0.01, seed=5)
    link2 = Link(board2)
    link2.send(Hello(session_id=3))
    link2.send(configure())
    for _ in range(1000):
        link2.pump(1e-3)
        link2.host.poll(link2.now)
    assert board2.configuration is not None
    host_dec = link2.host.decoder_stats
    assert host_dec.errors > 20 and host_dec.frames_ok > 20


def test_dropped_frames(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config, drop_rate=0.5, seed=1)
    link = Link(board)
    link.send(Hello(session_id=1))
    link.send(configure())
    for _ in range(1000):
        link.pump(1e-3)
        link.host.poll(link.now)
    assert board.configuration is not None
    sent = board.endpoint.stats.frames_sent
    received = link.host.decoder_stats.frames_ok
    assert 0.3 * sent < received < 0.7 * sent
    assert link.host.decoder_stats.errors == 0  # whole frames vanish, none arrive damaged


def test_retransmitted_request_is_answered_from_the_cache(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    link.setup()
    link.host.send(Start(0, 100), link.now)
    wire = link.host.data_to_send()
    link.pump(1e-3, raw=wire)
    link.pump(1e-3, raw=wire)  # the same request again (its ACK was lost)
    acks = [e for e in link.events if isinstance(e, Frame) and isinstance(e.msg, Ack)]
    acked = [e for e in link.events if isinstance(e, Acked) and isinstance(e.request, Start)]
    assert len(acked) == 1 and len(acks) == 1  # the second ACK is a stray reply for the host
    assert board.endpoint.stats.duplicate_requests == 1
    assert board.state is BoardState.ARMED


# ---------------------------------------------------------------------------------------------
# helpers and speed


def test_slew_limit_matches_the_sequential_recursion() -> None:
    rng = np.random.default_rng(0)
    v = np.cumsum(rng.normal(0, 1, (3, 500)), axis=1)
    v[1, 200] += 40.0  # a step
    prev = np.array([0.0, 5.0, -30.0])
    out = slew_limit(v, prev, 2.0)
    ref = np.empty_like(v)
    for c in range(3):
        y = prev[c]
        for j in range(v.shape[1]):
            y += np.clip(v[c, j] - y, -2.0, 2.0)
            ref[c, j] = y
    np.testing.assert_allclose(out, ref, atol=1e-12)
    assert np.max(np.abs(np.diff(out, axis=1))) <= 2.0 + 1e-12
    smooth = np.linspace(0, 1, 50)[None, :].repeat(3, 0)
    assert slew_limit(smooth, np.zeros(3), 1.0) is smooth


@pytest.mark.slow
def test_throughput_3_channels_100k(stage_config: StageConfig) -> None:
    """Board + stage + codec at 3 x 100 kS/s on a fake clock; prints samples/s per core."""
    board = Board(
        Stage(StageConfig.from_file(default_sim_config_path())), BoardConfig(amplifier_ranges_v=RANGES)
    )
    link = Link(board)
    link.setup(configure(rate_hz=100_000, status_ms=10))
    rate, seconds, frame = 100_000, 5.0, 500
    n_total = int(rate * seconds)
    codes = sine_codes(n_total + 20_000, rate_hz=rate)
    wires = [
        encode(Samples(lo, codes[lo : lo + frame]), seq=1000 + k)
        for k, lo in enumerate(range(0, n_total + 20_000, frame))
    ]
    assert isinstance(link.request(Start(0, 10_000)), Acked)
    sent = 0
    t0 = time.process_time()
    now = link.now
    out_bytes = 0
    for _ in range(int(seconds / 0.002)):
        now += 0.002
        target = min(len(wires), (int((now - link.now) * rate) + 20_000) // frame + 1)
        data = b"".join(wires[sent:target])
        sent = max(sent, target)
        board.feed(data, now)
        out_bytes += len(board.data_to_send())
    cpu = time.process_time() - t0
    played = board.counters.samples_played
    print(
        f"\nboard+stage: {played} samples x 3 ch in {cpu:.2f} s CPU = {played / cpu:,.0f} samples/s per core "
        f"({played / cpu / rate:.1f}x real time at {rate} S/s), {out_bytes / seconds:,.0f} B/s out"
    )
    assert board.counters.underruns == 0
    assert played >= n_total - rate * 0.01


def test_sync_outputs_follow_their_events_and_drop_when_the_clock_stops(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config)
    link = Link(board)
    assert link.hello().sync_outputs == 3
    link.request(configure())
    for _ in range(2000):
        if board.state is BoardState.IDLE:
            break
        link.pump(1e-3)
    assert isinstance(link.request(Start(20_000, 100)), Acked)
    # frame + line + pixel at the first sample, pixel clock every 10 samples (high for 5)
    events = [(0, 0b111, 0b111), (5, 0b000, 0b111)]
    for k in range(1, 10):
        events += [(10 * k, 0b001, 0b001), (10 * k + 5, 0b000, 0b001)]
    link.send(Sync(20_000, tuple(events)))
    link.send(Sync(20_000, tuple(events[:4])))  # a resend (go-back-N): skipped, not doubled
    # index 20001 lies behind the queue (skipped), 20500 past the run (queued, cleared at the stop)
    link.send(Sync(20_000, ((1, 0b100, 0b100), (500, 0b010, 0b110))))
    send_samples(link, 20_000, np.zeros((100, 3), dtype=np.int16))
    link.run(0.05)  # 100 samples at 10 kS/s, then an underrun
    got = board.sync_transitions
    want = [(20_000, 0b111), (20_005, 0b000)]
    for k in range(1, 10):
        want += [(20_000 + 10 * k, 0b001), (20_005 + 10 * k, 0b000)]
    assert got == want
    assert link.msgs(Fault)[-1].code is FaultCode.UNDERRUN
    # events past the end were never applied; outputs low while stopped; a frame in IDLE is dropped
    before = link.last_status().frames_dropped
    link.send(Sync(30_000, ((0, 0b111, 0b111),)))
    link.settle()
    assert board.sync_transitions == want and link.last_status().frames_dropped == before + 1


def test_a_board_without_sync_outputs_drops_sync(stage_config: StageConfig) -> None:
    board, _ = make_board(stage_config, sync_outputs=0)
    link = Link(board)
    link.setup()
    assert isinstance(link.request(Start(0, 10)), Acked)
    link.send(Sync(0, ((0, 1, 1),)))
    send_samples(link, 0, np.zeros((10, 3), dtype=np.int16))
    link.run(0.01)
    assert board.sync_transitions == [] and board.capabilities.sync_outputs == 0
