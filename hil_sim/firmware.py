"""The reference C firmware (``firmware_proto/c``) as a board process, like :func:`hil_sim.server.spawn_sim`.

:func:`build_firmware` compiles the host build with ``make`` (the system C compiler);
:func:`spawn_firmware` starts it on a pty with hil_sim's stage behind its DAC/ADC
(:mod:`hil_sim.stage_pipe`) and returns a :class:`~hil_sim.server.SimProcess`, so tests and
benchmarks drive the C firmware exactly as they drive the Python board.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Sequence
from pathlib import Path

from hil_sim.errors import SimLinkError
from hil_sim.server import SimProcess, _read_path_line

FIRMWARE_DIR = Path(__file__).resolve().parent.parent / "firmware_proto" / "c"
"""The firmware sources (a Makefile and C11 code)."""


def missing_tools(*tools: str) -> list[str]:
    """The programs of ``tools`` not on PATH (``make``, ``cc``, ``arm-none-eabi-gcc``, ...)."""
    return [t for t in tools if shutil.which(t) is None]


def build_firmware(out_dir: str | Path, target: str = "host") -> Path:
    """Build ``target`` of ``firmware_proto/c/Makefile`` into ``out_dir``; returns ``out_dir``.

    Raises
    ------
    SimLinkError
        ``make`` failed (the message carries the compiler's last lines).
    """
    out = Path(out_dir)
    done = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE_DIR), f"O={out}", target],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-15:])
        raise SimLinkError(f"make {target} in {FIRMWARE_DIR} failed:\n{tail}")
    return out


def spawn_firmware(
    binary: str | Path,
    config_path: str | Path | None = None,
    effects: Sequence[str] = (),
    seed: int = 0,
    extra_args: Sequence[str] = (),
    link: str | Path | None = None,
    *,
    timeout_s: float = 30.0,
) -> SimProcess:
    """Start the host build of the firmware with hil_sim's stage and wait for its pty path.

    Parameters
    ----------
    binary
        ``piezod-fw-host`` from :func:`build_firmware`.
    config_path, effects, seed
        The stage, as for :func:`hil_sim.server.spawn_sim`.
    extra_args
        More options of the firmware (``--unplug-s S``, ``--rate-max HZ``, ...).
    link
        Keep a stable symlink at this path.
    timeout_s
        How long to wait for the path line (s).
    """
    stage = [sys.executable, "-m", "hil_sim.stage_pipe", "--seed", str(seed)]
    if config_path is not None:
        stage += ["--config", str(config_path)]
    for effect in effects:
        stage += ["--effect", effect]
    cmd = [str(binary), "--stage-cmd", shlex.join(stage)]
    if link is not None:
        cmd += ["--link", str(link)]
    cmd += [str(a) for a in extra_args]
    fd, name = tempfile.mkstemp(prefix="fw_host-", suffix=".log")
    stderr_path = Path(name)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    with os.fdopen(fd, "wb") as err:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err, env=env)
    board = SimProcess(proc, "", stderr_path, Path(link) if link is not None else None)
    try:
        board.path = _read_path_line(proc, timeout_s, stderr_path)
    except BaseException:
        board.close()
        raise
    return board


_QEMU_PTY = re.compile(r"char device redirected to (/dev/pts/\d+)")


def spawn_qemu(elf: str | Path, machine: str = "mps2-an385", *, timeout_s: float = 30.0) -> SimProcess:
    """Run the Cortex-M build under ``qemu-system-arm`` with its UART on a pty.

    Parameters
    ----------
    elf
        ``piezod-fw-mps2.elf`` from ``build_firmware(out, "mps2")``.
    machine
        The QEMU machine (the build's memory map and UART are mps2-an385's).
    timeout_s
        How long to wait for QEMU to name its pty (s).

    Returns
    -------
    SimProcess
        ``path`` is the pty of the emulated UART; QEMU's output goes to ``stderr_path``.

    Raises
    ------
    SimLinkError
        QEMU exited or named no pty in time.
    """
    fd, name = tempfile.mkstemp(prefix="fw_qemu-", suffix=".log")
    log_path = Path(name)
    cmd = ["qemu-system-arm", "-M", machine, "-display", "none", "-monitor", "none", "-serial", "pty"]
    cmd += ["-kernel", str(elf)]
    with os.fdopen(fd, "wb") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    board = SimProcess(proc, "", log_path)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = _QEMU_PTY.search(log_path.read_text(encoding="utf-8", errors="replace"))
        if found:
            board.path = found.group(1)
            # QEMU's pty backend polls for a reader about once a second and discards the guest's
            # output until it sees one: keep the slave open (never read) so the first reply counts
            keep = os.open(board.path, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(keep)
            board.keepalive_fd = keep  # type: ignore[attr-defined]
            time.sleep(1.2)
            return board
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    text = log_path.read_text(encoding="utf-8", errors="replace").strip()
    board.close()
    raise SimLinkError(f"qemu-system-arm named no pty within {timeout_s} s: {text[-300:]}")


__all__ = ["FIRMWARE_DIR", "build_firmware", "missing_tools", "spawn_firmware", "spawn_qemu"]
