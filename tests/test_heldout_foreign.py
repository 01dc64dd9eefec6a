"""The held-out stages of foreign physics (tools/heldout/foreign49, tools/heldout/foreign51) still
serve the real protocol, and their take-apart tools still parse their command lines.

docs/model-family.md 6.2bm gives the commands that calibrate piezod on foreign49 over ``--port``
(foreign51's scanner YAML gives its own); this keeps them runnable: each stage server starts on a
real pty, ``piezod probe`` completes the handshake over it, and SIGTERM ends it cleanly.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "tools" / "heldout"


@pytest.mark.parametrize("stage", ["foreign49", "foreign51"])
def test_the_foreign_stage_serves_the_protocol_on_a_pty(stage: str, tmp_path: Path) -> None:
    link = tmp_path / "link"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    server = subprocess.Popen(
        [sys.executable, str(HELDOUT / stage / "stage_server.py"), "--link", str(link)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )
    try:
        assert server.stdout is not None
        printed = server.stdout.readline().strip()  # once ready (after compiling its loops)
        assert printed == str(link), server.stderr.read() if server.stderr else ""
        probe = subprocess.run(
            [sys.executable, "-m", "piezod", "probe", str(link), "--timeout", "20", "--json", "-"],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert probe.returncode == 0, probe.stderr
        assert json.loads(probe.stdout)
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            rc = server.wait(timeout=30)
        finally:
            if server.poll() is None:
                server.kill()
    assert rc == 0
    assert not link.exists()


@pytest.mark.parametrize(("stage", "part"), [("foreign49", "noenv"), ("foreign51", "noae")])
def test_take_apart_names_its_usage_on_a_wrong_command_line(stage: str, part: str) -> None:
    tool = ROOT / "tools" / "heldout" / stage / "take_apart.py"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    wrong: list[list[str]] = [
        [],
        ["--calibrate"],
        ["F.yaml", "nothere"],
        ["--calibrate", "OUT.yaml", part, "nothere"],
        ["F.yaml", "--json"],
    ]
    for args in wrong:
        run = subprocess.run(
            [sys.executable, str(tool), *args], capture_output=True, text=True, env=env, timeout=300
        )
        assert run.returncode == 2, (args, run.stderr)
        assert "take_apart.py F.yaml" in run.stderr and "--calibrate OUT.yaml" in run.stderr
        assert "Traceback" not in run.stderr
