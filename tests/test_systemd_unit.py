"""The systemd unit: `systemd-analyze verify` passes, and the README's install steps fit it."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from piezod.cli import build_parser
from piezod.config import load_config

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "piezod" / "service" / "systemd" / "piezod@.service"


def _install_steps() -> list[list[str]]:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Installing the service for a scanner", 1)[1]
    block = section.split("```sh", 1)[1].split("```", 1)[0]
    return [shlex.split(line, comments=True) for line in block.strip().splitlines() if line.strip()]


def _unit_value(key: str) -> str:
    (value,) = re.findall(rf"^{key}=(.*)$", UNIT.read_text(encoding="utf-8"), re.M)
    return value


def test_systemd_analyze_verify(tmp_path: Path) -> None:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        if os.environ.get("PIEZOD_CI_SYSTEMD"):
            pytest.fail("systemd-analyze is missing (CI installs Debian's systemd package)")
        pytest.skip("systemd-analyze not installed (Debian package systemd)")
    # As installed by the README (pip puts the entry point next to the interpreter here).
    exe = Path(sys.executable).parent / "piezod"
    assert exe.is_file(), exe
    text = UNIT.read_text(encoding="utf-8").replace("/usr/local/bin/piezod", str(exe))
    unit = tmp_path / "piezod@afm1.service"
    unit.write_text(text, encoding="utf-8")
    res = subprocess.run(
        [tool, "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=120, check=False
    )
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr


def test_readme_install_steps_match_the_unit() -> None:
    steps = _install_steps()
    copies = [s for s in steps if s[:2] == ["sudo", "cp"]]
    sources = {Path(s[2]).name: ROOT / s[2] for s in copies}
    for src in sources.values():
        assert src.is_file(), src
    assert load_config(sources["medium-tube.yaml"]).name == "medium-tube"
    (unit_dst,) = [s[3] for s in copies if s[2].endswith("piezod@.service")]
    assert unit_dst == "/etc/systemd/system/"
    # the env file the README writes is the unit's EnvironmentFile, with the variable ExecStart uses
    (echo,) = [s for s in steps if s[0] == "echo"]
    key = echo[1].split("=", 1)[0]
    tee = next(s for s in steps if "tee" in s)
    assert _unit_value("EnvironmentFile").replace("%i", "afm1") == tee[-1]
    exec_start = shlex.split(
        _unit_value("ExecStart").replace("%i", "afm1").replace(f"${{{key}}}", "/dev/ttyACM0")
    )
    assert exec_start[0] == "/usr/local/bin/piezod"  # where `sudo python -m pip install .` puts it
    args = build_parser().parse_args(exec_start[1:])
    assert args.config == "/etc/piezod/afm1.yaml" and args.port == "/dev/ttyACM0"
    # the README's own check talks to the socket the unit listens on
    ctl = next(s for s in steps if s[:2] == ["piezod", "ctl"])
    assert ctl[ctl.index("--api") + 1] == args.api
    build_parser().parse_args(ctl[1:])
