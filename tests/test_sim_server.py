"""The simulator process on a real pty (hil_sim.server, spawn_sim), talked to through pyserial.

hil_sim.server is imported lazily: the SIGKILL test runs :func:`stream_forever` of this module in
a subprocess, which should start quickly.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import serial
from orphans import ended_within, kill_parent_of

from firmware_proto import (
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
    Hello,
    Message,
    Nacked,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
)
from hil_sim.usb_bridge import connect
from piezod.errors import LinkError

if TYPE_CHECKING:
    from hil_sim.server import SimProcess

HERE = Path(__file__).resolve().parent
DAC_V_PER_CODE = 250.0 / 32768


def configure(rate_hz: int = 10_000, heartbeat_ms: int = 2000, ramp_v_per_s: float = 2000.0) -> Configure:
    ch = ChannelConfig.from_volts(
        v_min=-230.0,
        v_max=230.0,
        safe_v=0.0,
        dac_v_per_code=DAC_V_PER_CODE,
        dac_offset_v=0.0,
        ramp_v_per_s=ramp_v_per_s,
        adc_um_per_code=1e-3,
        adc_offset_um=0.0,
    )
    return Configure(rate_hz, heartbeat_ms, 10, 1, (ch, ch, ch))


class Host:
    """A minimal host on any byte stream (pyserial port or socket): Endpoint + wall clock."""

    def __init__(self, read: Callable[[], bytes], write: Callable[[bytes], Any], fileno: int) -> None:
        self._read = read
        self._write = write
        self._fd = fileno
        self.ep = Endpoint()
        self.events: list[Event] = []

    @classmethod
    def on_pty(cls, path: str) -> tuple[Host, serial.Serial]:
        port = serial.serial_for_url(path, baudrate=12_000_000, timeout=0)
        return cls(lambda: port.read(port.in_waiting or 1), port.write, port.fileno()), port

    def pump(self, duration: float = 0.0) -> list[Event]:
        out: list[Event] = []
        deadline = time.monotonic() + duration
        while True:
            now = time.monotonic()
            out += self.ep.poll(now)
            data = self.ep.data_to_send()
            if data:
                self._write(data)
            ready, _, _ = select.select([self._fd], [], [], max(0.0, min(deadline - now, 0.005)))
            if ready:
                out += self.ep.receive(self._read(), time.monotonic())
            if time.monotonic() >= deadline:
                break
        self.events += out
        return out

    def request(self, msg: Message, timeout_s: float = 3.0) -> Acked | Nacked:
        seq = self.ep.send(msg, time.monotonic())
        return self.wait_for(lambda e: isinstance(e, Acked | Nacked) and e.seq == seq, timeout_s)

    def wait_for(self, pred: Callable[[Event], bool], timeout_s: float = 3.0) -> Any:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for event in self.pump(0.005):
                if pred(event):
                    return event
        raise AssertionError(f"nothing matching within {timeout_s} s")

    def msgs(self, kind: type[Message]) -> list[Any]:
        return [e.msg for e in self.events if isinstance(e, Frame) and isinstance(e.msg, kind)]

    def status_in(self, *states: BoardState, timeout_s: float = 3.0) -> Status:
        event = self.wait_for(
            lambda e: isinstance(e, Frame) and isinstance(e.msg, Status) and e.msg.state in states, timeout_s
        )
        status: Status = event.msg
        return status

    def setup(self, conf: Configure) -> Capabilities:
        """HELLO, STOP (whatever the board was doing), CONFIGURE, wait for IDLE."""
        caps = self.request(Hello(session_id=os.getpid()))
        assert isinstance(caps, Acked) and isinstance(caps.reply, Capabilities), caps
        self.request(Stop())
        reply = self.request(conf)
        assert isinstance(reply, Acked), reply
        self.status_in(BoardState.IDLE)
        return caps.reply


def sine(n: int, first: int, rate_hz: float) -> np.ndarray[Any, np.dtype[np.int16]]:
    t = (first + np.arange(n)) / rate_hz
    v = np.stack([100 * np.sin(2 * np.pi * 20 * t), 50 * np.cos(2 * np.pi * 20 * t), 10 + 0 * t], axis=1)
    return np.asarray(np.rint(v / DAC_V_PER_CODE), dtype=np.int16)


def stream_forever(path: str) -> None:
    """Host body of the SIGKILL test (run in a subprocess): stream 3 x 10 kS/s until killed."""
    host, _ = Host.on_pty(path)
    rate = 10_000
    host.setup(configure(rate_hz=rate, heartbeat_ms=200, ramp_v_per_s=2000.0))
    assert isinstance(host.request(Start(0, 1000)), Acked)
    sent = 0
    announced = False
    while True:
        statuses = [e.msg for e in host.pump(0.005) if isinstance(e, Frame) and isinstance(e.msg, Status)]
        played = statuses[-1].last_played_index if statuses else None
        played = -1 if played is None or played >= 2**63 else played
        # half a second ahead, over twice the 200 ms watchdog: a stall of this process on a busy
        # machine trips the watchdog (what the test checks), never an underrun first
        while sent < played + 1 + rate // 2:
            host.ep.send(Samples(sent, sine(500, sent, rate)), time.monotonic())
            sent += 500
        if not announced and played > 2000:
            print("streaming", flush=True)
            announced = True


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    from hil_sim.server import spawn_sim

    tmp = tmp_path_factory.mktemp("sim")
    with spawn_sim(
        link=tmp / "board",
        extra_args=("--usb-socket", str(tmp / "usb.sock"), "--unplug-s", "0.5"),
        seed=1,
    ) as proc:
        yield proc


def test_stream_and_read_the_sensor_back(sim: SimProcess) -> None:
    assert os.path.islink(sim.path) and os.readlink(sim.path).startswith("/dev/pts/")
    host, port = Host.on_pty(sim.path)
    try:
        caps = host.setup(configure())
        assert caps.n_channels == 3 and caps.fifo_depth_samples == 65536
        codes = sine(3000, 0, 10_000)
        assert isinstance(host.request(Start(0, 1000)), Acked)
        for lo in range(0, 3000, 500):
            host.ep.send(Samples(lo, codes[lo : lo + 500]), time.monotonic())
        assert isinstance(host.request(Stop(2999)), Acked)
        status = host.wait_for(
            lambda e: isinstance(e, Frame) and isinstance(e.msg, Status) and e.msg.last_played_index == 2999,
            timeout_s=5.0,
        ).msg
        host.pump(0.05)
        assert status.underruns == 0 and status.crc_errors == 0
        sensors = host.msgs(Sensor)
        idx = np.concatenate([s.indices for s in sensors])
        rows = np.concatenate([s.codes for s in sensors])
        np.testing.assert_array_equal(idx, np.arange(3000))
        # x follows the 20 Hz drive: about 0.1 um/V x 100 V = 10 um = 10000 codes of amplitude
        assert 5000 < rows[:, 0].max() < 20000 and -20000 < rows[:, 0].min() < -5000
        assert host.ep.decoder_stats.errors == 0
    finally:
        port.close()


def test_killed_host_watchdog_ramps_to_safe(sim: SimProcess) -> None:
    code = (
        f"import sys; sys.path.insert(0, {str(HERE)!r}); "
        f"import test_sim_server as t; t.stream_forever({sim.path!r})"
    )
    host_proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert host_proc.stdout is not None
        ready, _, _ = select.select([host_proc.stdout], [], [], 30.0)
        line = host_proc.stdout.readline() if ready else b""
        assert line == b"streaming\n", (
            host_proc.stderr.read().decode() if host_proc.poll() is not None else line
        )
        time.sleep(0.1)
    finally:
        host_proc.send_signal(signal.SIGKILL)
        host_proc.wait()
        killed_at = time.monotonic()
    # watchdog 200 ms + ramp of <= 100 V at 2000 V/s (50 ms), with scheduling margin
    time.sleep(max(0.0, killed_at + 0.6 - time.monotonic()))
    host, port = Host.on_pty(sim.path)
    try:
        assert isinstance(host.request(Hello(session_id=99)), Acked)
        status = host.status_in(BoardState.IDLE)
        assert status.fault_flags & FaultFlags.WATCHDOG
        assert status.underruns == 0
        fault = host.wait_for(lambda e: isinstance(e, Frame) and isinstance(e.msg, Fault)).msg
        assert fault.code is FaultCode.WATCHDOG
        assert 2000 < fault.index == status.last_played_index
    finally:
        port.close()
    assert "watchdog" in sim.stderr_text()


def test_usb_socket_serves_the_same_board(sim: SimProcess) -> None:
    sock_path = Path(sim.path).parent / "usb.sock"
    sock = connect(sock_path, timeout_s=5.0)
    sock.setblocking(False)
    try:
        host = Host(lambda: sock.recv(65536), sock.sendall, sock.fileno())
        reply = host.request(Hello(session_id=5))
        assert isinstance(reply, Acked) and isinstance(reply.reply, Capabilities)
        assert reply.reply.n_channels == 3
        host.status_in(BoardState.IDLE, BoardState.RAMPING)  # configured by the earlier tests
    finally:
        sock.close()


def test_unplug_and_replug(sim: SimProcess) -> None:
    host, port = Host.on_pty(sim.path)
    try:
        host.setup(configure())
        sim.unplug()
        with pytest.raises(OSError):  # EIO (serial.SerialException is an OSError too)
            host.pump(2.0)
    finally:
        port.close()
    deadline = time.monotonic() + 5.0
    gone = False
    while time.monotonic() < deadline:
        if not os.path.lexists(sim.path):
            gone = True
        elif gone:
            break
        time.sleep(0.01)
    assert gone and os.path.lexists(sim.path), "the link must vanish and come back"
    host, port = Host.on_pty(sim.path)
    try:
        assert isinstance(host.request(Hello(session_id=7)), Acked)
        assert host.status_in(BoardState.IDLE).state is BoardState.IDLE  # still configured
    finally:
        port.close()
    assert "plugged in again" in sim.stderr_text()


def test_sigterm_exits_cleanly(sim: SimProcess) -> None:
    link = sim.path
    assert sim.terminate() == 0
    assert not os.path.lexists(link)
    assert not (Path(link).parent / "usb.sock").exists()
    assert "stopped by SIGTERM" in sim.stderr_text()


def test_a_simulator_never_outlives_the_process_that_spawned_it(tmp_path: Path) -> None:
    """A parent killed outright (SIGKILL: no handler, no context manager runs) must not leave its
    simulator running: the simulator sees the end of file of the pipe on its stdin and stops."""
    link = tmp_path / "pty"
    sim_pid = kill_parent_of(
        "import sys, time; from hil_sim.server import spawn_sim; "
        f"sim = spawn_sim(link={str(link)!r}); print(sim.pid, flush=True); time.sleep(600)"
    )
    assert ended_within([sim_pid], 60.0), "the simulator outlived its parent"
    assert not os.path.lexists(link)


def test_piezod_sim_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``piezod sim`` in this process: prints the link, SIGINT ends it with status 0."""
    from piezod.cli import main

    link = tmp_path / "pty"

    def interrupt_when_serving() -> None:
        deadline = time.monotonic() + 60.0
        while not os.path.lexists(link) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=interrupt_when_serving, daemon=True)
    thread.start()
    status = main(["sim", "--link", str(link), "--seed", "2"])
    thread.join()
    assert status == 0
    assert capsys.readouterr().out == f"{link}\n"
    assert not os.path.lexists(link)


def test_bad_input_fails_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from hil_sim.errors import SimLinkError
    from hil_sim.server import main, spawn_sim
    from piezod import simulator

    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\naxes: {}\n", encoding="utf-8")
    with pytest.raises(SimLinkError, match=r"status 2 .*bad\.yaml"):
        spawn_sim(bad)
    with pytest.raises(LinkError, match=r"status 2 .*bad\.yaml"):  # the host's entry point
        simulator.spawn_sim(bad)
    assert main(["--corrupt-rate", "2"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and "corrupt_rate" in out.err


def stream(host: Host, rate_hz: int, seconds: float, lead_s: float = 0.2, frame: int = 500) -> dict[str, int]:
    """Stream a sine on every channel with credits, lead and go-back-N; returns counters."""
    assert isinstance(host.request(Start(0, int(lead_s * rate_hz))), Acked)
    n_total = int(rate_hz * seconds)
    table = sine(rate_hz, 0, rate_hz)  # one second, repeated
    next_index = 0
    credit = int(lead_s * rate_hz) + frame
    played = -1
    gaps = 0
    rewinds = 0
    sensor_rows = 0
    stop_sent = False
    last_status_t = time.monotonic()
    while played < n_total - 1:
        for event in host.pump(0.002):
            if not isinstance(event, Frame):
                continue
            msg = event.msg
            if isinstance(msg, Sensor):
                sensor_rows += msg.n_samples
            elif isinstance(msg, Status):
                last_status_t = time.monotonic()
                credit = msg.credit_limit
                if msg.last_played_index < 2**63:
                    played = msg.last_played_index
                if msg.index_gaps > gaps:
                    gaps = msg.index_gaps
                    if msg.write_index < next_index:
                        next_index = msg.write_index
                        rewinds += 1
                if msg.state is BoardState.RUNNING and not stop_sent:
                    host.ep.send(Stop(n_total - 1), time.monotonic())  # the end is no underrun
                    stop_sent = True
                assert msg.state in (BoardState.ARMED, BoardState.RUNNING) or played == n_total - 1, msg
        assert time.monotonic() - last_status_t < 2.0, "no STATUS for 2 s"
        limit = min(credit, played + 1 + int(lead_s * rate_hz), n_total)
        while next_index < limit:
            n = min(frame, limit - next_index)
            rows = table[(next_index + np.arange(n)) % rate_hz]
            host.ep.send(Samples(next_index, rows), time.monotonic())
            next_index += n
        host.pump(0.0)
    return {"played": played + 1, "rewinds": rewinds, "sensor_rows": sensor_rows}


@pytest.mark.soak
def test_soak_60s_with_byte_errors(tmp_path: Path) -> None:
    """3 x 100 kS/s for 60 s; 1e-3 bit errors per byte board -> host, 1e-5 host -> board."""
    from hil_sim.server import spawn_sim

    rate, seconds = 100_000, 60.0
    args = ("--corrupt-rate", "1e-3", "--corrupt-in-rate", "1e-5")
    with spawn_sim(link=tmp_path / "board", extra_args=args, seed=3) as sim:
        host, port = Host.on_pty(sim.path)
        try:
            host.setup(configure(rate_hz=rate, heartbeat_ms=500))
            result = stream(host, rate, seconds)
            status = host.status_in(BoardState.IDLE)
        finally:
            port.close()
        exit_status = sim.terminate()
        log = sim.stderr_text()
    dec = host.ep.decoder_stats
    print(
        f"\nsoak: {result['played']} samples x 3 ch in {seconds:g} s, underruns {status.underruns}, "
        f"board crc errors {status.crc_errors}, index gaps {status.index_gaps} "
        f"({result['rewinds']} rewinds), "
        f"host decode errors {dec.errors} of {dec.frames_ok + dec.errors} frames, "
        f"sensor rows {result['sensor_rows']}"
    )
    assert exit_status == 0, log[-2000:]
    assert status.underruns == 0 and status.last_played_index >= rate * seconds - 1
    assert dec.errors > 0 and result["sensor_rows"] > 0
