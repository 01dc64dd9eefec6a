"""The reference firmware cross-compiled for a Cortex-M3 (QEMU's mps2-an385), its UART on a pty,
streamed by the real host link and by the real daemon.

The emulated CMSDK UART has a one-byte receive buffer that QEMU's pty backend refills once per
main-loop wakeup: it carries about 8 kB/s host -> board, which with the host's 5 ms SAMPLES
frames (27 bytes of framing each) is a few hundred samples/s on three channels
(``piezod bench stream --port`` against it reports the figure, docs/hardware.md the sweep). On a
busy machine QEMU's main loop wakes less often and the figure drops, so the first test queues
a whole run before the clock starts (no timing pressure). The real daemon (``piezod serve``) streams
a scan on it when the scanner YAML gives the link's capacity (``service.link_bytes_per_s``): it
then derives a status period and frame size the emulated UART carries (piezod.link.budget). Skipped, with
the install command, where the cross toolchain or QEMU is missing."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial
import yaml

from firmware_proto import (
    Ack,
    BoardState,
    Capabilities,
    ChannelConfig,
    Configure,
    Fault,
    FaultCode,
    Frame,
    FrameDecoder,
    Hello,
    Message,
    Samples,
    Sensor,
    Start,
    Status,
    encode,
)
from hil_sim.firmware import build_firmware, missing_tools, spawn_qemu
from piezod.client import PiezodClient
from piezod.config import default_sim_config_path, load_config
from piezod.link.bench import bench_config, stream_bench
from piezod.link.session import LinkSettings
from piezod.recording import read_recording

INSTALL = "apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
QEMU_RATE_HZ = 100

_missing = missing_tools("make", "arm-none-eabi-gcc", "qemu-system-arm")
pytestmark = pytest.mark.skipif(
    bool(_missing), reason=f"Cortex-M build under QEMU needs {', '.join(_missing)} ({INSTALL})"
)


@pytest.fixture(scope="module")
def elf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = build_firmware(tmp_path_factory.mktemp("fw-mps2"), "mps2")
    return out / "mps2" / "piezod-fw-mps2.elf"


@pytest.fixture
def qemu(elf: Path) -> Iterator[Any]:
    with spawn_qemu(elf) as board:
        yield board


class _Reader:
    """Everything the board sent, in order, and a cursor past the last message handed out.

    One read can complete several frames (a FAULT and the SENSOR rows after it arrive together
    on a busy machine), so nothing decoded is dropped when the wanted one is found."""

    def __init__(self, port: Any) -> None:
        self.port, self.dec, self.got, self._next = port, FrameDecoder(), [], 0

    def next(self, want: type, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            while self._next < len(self.got):
                item = self.got[self._next]
                self._next += 1
                if isinstance(item, want):
                    return item
            if time.monotonic() >= deadline:
                names = [type(m).__name__ for m in self.got]
                raise AssertionError(f"no {want.__name__} within {timeout_s} s: {names}")
            # a decode error is kept too, so a missing frame says whether bytes were spoilt
            self.got.extend(i.msg if isinstance(i, Frame) else i for i in self.dec.feed(self.port.read(4096)))


def test_emulated_mcu_plays_a_queued_run_clamps_and_reports_the_underrun(qemu: Any) -> None:
    n = 200
    with serial.Serial(qemu.path, timeout=0.05) as port:
        link = _Reader(port)
        port.write(b"\x00" + encode(Hello(session_id=7), seq=0))
        caps = link.next(Capabilities, 10.0)
        assert caps.n_channels == 3 and caps.sample_clock_hz % QEMU_RATE_HZ == 0
        lo, hi = caps.amplifier_ranges_v[0]
        scale = float(np.float32((hi - lo) / 65536.0))
        channel = ChannelConfig.from_volts(
            v_min=-100.0,
            v_max=100.0,
            safe_v=0.0,
            dac_v_per_code=scale,
            dac_offset_v=0.0,
            ramp_v_per_s=1000.0,
            adc_um_per_code=0.001,
            adc_offset_um=0.0,
        )
        conf = Configure(QEMU_RATE_HZ, 60_000, 50, 1, (channel,) * 3)
        assert conf.check(caps) is None
        port.write(encode(conf, seq=1))
        assert link.next(Ack, 10.0).acked_seq == 1
        while link.next(Status, 10.0).state != BoardState.IDLE:
            pass
        port.write(encode(Start(start_index=1000, prefill_samples=n), seq=2))
        assert link.next(Ack, 10.0).acked_seq == 2
        ch = conf.channels
        codes = np.zeros((n, 3), dtype=np.int16)
        codes[:, 0] = np.linspace(ch[0].code_min // 2, ch[0].code_max // 2, n).astype(np.int16)
        codes[150, 1] = ch[1].code_max + 1
        port.write(encode(Samples(first_index=1000, codes=codes), seq=3))
        fault = link.next(Fault, 10.0)
        assert fault.code == FaultCode.LIMIT_VIOLATION and (fault.channel, fault.index) == (1, 1150)
        underrun = link.next(Fault, 20.0)
        assert underrun.code == FaultCode.UNDERRUN and underrun.index == 1000 + n - 1
        link.next(Status, 5.0)
    got = link.got
    rows = [m for m in got if isinstance(m, Sensor)]
    indices = np.concatenate([m.first_index + m.stride * np.arange(m.n_samples) for m in rows])
    spoilt = [m for m in got if not isinstance(m, Message)]
    np.testing.assert_array_equal(indices, 1000 + np.arange(n), err_msg=f"decode errors: {spoilt}")
    sensed = np.concatenate([np.asarray(m.codes) for m in rows])
    assert np.corrcoef(codes[:, 0], sensed[:, 0])[0, 1] > 0.99  # the simulated stage follows the DAC
    last = [m for m in got if isinstance(m, Status)][-1]
    assert last.state == BoardState.IDLE and last.last_played_index == 1000 + n - 1
    assert last.underruns == 1 and last.clamped_samples == 1


@pytest.mark.slow
def test_host_link_streams_to_the_emulated_mcu_without_loss(qemu: Any) -> None:
    config = bench_config(load_config(default_sim_config_path()), 3, QEMU_RATE_HZ)
    settings = LinkSettings(status_period_ms=50)
    r = stream_bench(qemu.path, config, rate_hz=QEMU_RATE_HZ, seconds=3.0, lead_s=0.5, settings=settings)
    assert r["underruns"] == 0 and r["run_ends"] == ["stop"], r
    assert r["samples_sent"] == r["samples_played"] == r["samples_read"] >= 2.5 * QEMU_RATE_HZ
    assert r["unexplained_loss"] == 0 and r["crc_errors"] == 0
    assert r["index_gaps"] == r["overflows"] == 0


SYSCLK_STM32F405_HZ = 168_000_000
"""The real-board target's clock; its sample rates go up to 70 kS/s (caps in stm32f4/main.c)."""


def test_real_board_target_builds_and_fits(tmp_path: Path) -> None:
    out = build_firmware(tmp_path, "stm32f4") / "stm32f4" / "piezod-fw-stm32f4.elf"
    done = subprocess.run(["arm-none-eabi-size", str(out)], capture_output=True, text=True, check=True)
    text, data, bss = (int(v) for v in done.stdout.splitlines()[1].split()[:3])
    print(f"stm32f4: flash {text + data} B of 1 MiB, RAM {data + bss} B of 128 KiB")
    assert text + data <= 1024 * 1024
    assert data + bss <= 128 * 1024 - 8 * 1024  # 8 KiB left for the stack


def test_cycle_budget_per_sample_at_70k(tmp_path: Path) -> None:
    """Instructions per sample of the core (QEMU -icount: one instruction per ns) within the budget.

    Budget at 70 kS/s on 168 MHz: 2400 cycles per sample. Spent outside the core: the SPI
    transfers the tick waits for (3 x 24 DAC bits + 3 x 16 ADC bits at 21 MHz = 960 cycles).
    The core's instructions count at an assumed 1.5 cycles each (Cortex-M4, flash wait states
    hidden by the ART accelerator for this loop-heavy code)."""
    elf = build_firmware(tmp_path, "tickbench") / "mps2" / "tickbench.elf"
    log = tmp_path / "tickbench.out"
    cmd = ["qemu-system-arm", "-M", "mps2-an385", "-display", "none", "-monitor", "none"]
    cmd += ["-serial", f"file:{log}", "-icount", "shift=0", "-kernel", str(elf)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and "\n" not in (log.read_text() if log.exists() else ""):
            time.sleep(0.2)
    finally:
        proc.kill()
        proc.wait()
    words = log.read_text().split()
    fields = dict(zip(words[::2], map(int, words[1::2]), strict=True))
    assert fields["ticks"] == 15600 and fields["state"] == 3
    core = fields["insns_per_tick"] + fields["insns_per_sample_received"] + fields["insns_per_sample_polled"]
    cycles = 1.5 * core + 960
    budget = SYSCLK_STM32F405_HZ / 70_000
    print(f"per sample: {fields} -> ~{cycles:.0f} cycles of {budget:.0f} at 70 kS/s")
    assert cycles < budget


QEMU_LINK_BYTES_PER_S = 6000
"""What the emulated UART on a pty carries, both directions together (docs/hardware.md): the
daemon derives its status period and frame size from it (piezod.link.budget)."""


def _qemu_scanner_yaml(tmp_path: Path, rate_hz: float) -> Path:
    raw = yaml.safe_load(default_sim_config_path().read_text())
    raw["sample_rate_hz"] = rate_hz
    service = raw.setdefault("service", {})
    service.update(link_bytes_per_s=QEMU_LINK_BYTES_PER_S, link_shared=True, lead_ms=500.0)
    out = tmp_path / "qemu-stage.yaml"
    out.write_text(yaml.safe_dump(raw))
    return out


def _serve_scan_on_qemu(qemu: Any, tmp_path: Path, rate_hz: float, lines: int) -> None:
    """``piezod serve`` on the emulated MCU's pty: a scan of ``lines`` lines at ``rate_hz``, no loss."""
    config = _qemu_scanner_yaml(tmp_path, rate_hz)
    api = tmp_path / "api.sock"
    log_path = tmp_path / "daemon.log"
    cmd = [sys.executable, "-m", "piezod", "serve", "--config", str(config), "--port", qemu.path]
    cmd += ["--api", f"unix:{api}", "--recordings", str(tmp_path / "rec")]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log)
    try:
        deadline = time.monotonic() + 90.0
        while not api.exists():
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.2)
        with PiezodClient(f"unix:{api}", timeout=30.0) as client:
            while client.status().state != "idle":
                assert time.monotonic() < deadline, client.status()
                time.sleep(0.2)
            per_line = round(rate_hz / 1.0)
            client.scan(range_um=5.0, line_rate_hz=1.0, lines=lines, pixels=8, name="qemu")
            end = time.monotonic() + 60.0 + 3 * lines
            while (st := client.status()).state == "scanning":
                assert time.monotonic() < end, st
                time.sleep(0.5)
            assert st.state == "idle", st.faults
            assert st.underruns == 0 and st.crc_errors == 0 and st.frames_dropped == 0, st
            assert not [f for f in st.faults if f.code != "LINK"], st.faults
            time.sleep(2.0)  # the last sensor rows reach the recording
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log_path.read_text()
    budget = [line for line in text.splitlines() if "link budget" in line]
    assert budget, text
    print(f"\n{budget[0].split('link budget', 1)[1].strip()}")
    rec = read_recording(tmp_path / "rec" / "qemu.csv")
    x = rec.axis == "x"
    index = np.rint(rec.t_s[x] * rate_hz).astype(np.int64)
    # every scan sample was played and read back, in order, once
    assert index.size == lines * per_line and np.all(np.diff(index) == 1), (index.size, lines * per_line)
    assert np.all(np.isfinite(rec.position_um[x]))
    print(f"QEMU mps2-an385 + piezod serve: {lines * per_line} samples at {rate_hz:g} S/s, no loss")


def test_real_daemon_streams_a_scan_on_the_emulated_mcu(qemu: Any, tmp_path: Path) -> None:
    _serve_scan_on_qemu(qemu, tmp_path, QEMU_RATE_HZ, lines=2)


@pytest.mark.slow
def test_real_daemon_streams_a_longer_scan_on_the_emulated_mcu(qemu: Any, tmp_path: Path) -> None:
    _serve_scan_on_qemu(qemu, tmp_path, 2 * QEMU_RATE_HZ, lines=10)
