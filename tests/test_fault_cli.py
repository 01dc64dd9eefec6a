"""Bad command-line input: one line on stderr naming the argument, exit 2, never a traceback (#13 item 6).

Every case runs the real ``piezod`` command in a subprocess.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from orphans import children, ended_within, piezod_process, sigterm

from piezod.recording import read_recording


def piezod(*args: str, timeout: float = 180.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "piezod", *args], capture_output=True, text=True, timeout=timeout
    )


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr
    err = proc.stderr.strip()
    assert err.count("\n") == 0, err
    for needle in needles:
        assert needle in err, err


SCAN = ["scan", "--sim", "--out", "x.csv"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        ([*SCAN, "--range-um", "-5", "--line-rate-hz", "1"], "--range-um"),
        ([*SCAN, "--range-um", "nan", "--line-rate-hz", "1"], "--range-um"),
        ([*SCAN, "--range-um", "0", "--line-rate-hz", "1"], "--range-um"),
        ([*SCAN, "--range-um", "inf", "--line-rate-hz", "1"], "--range-um"),
        ([*SCAN, "--range-um", "5", "--line-rate-hz", "NaN"], "--line-rate-hz"),
        ([*SCAN, "--range-um", "5", "--line-rate-hz", "-1"], "--line-rate-hz"),
        ([*SCAN, "--range-um", "5", "--line-rate-hz", "1", "--lines", "0"], "--lines"),
        ([*SCAN, "--range-um", "5", "--line-rate-hz", "1", "--lines", "2.5"], "--lines"),
        ([*SCAN, "--range-um", "5", "--line-rate-hz", "1", "--offset-um", "inf"], "--offset-um"),
        (["ctl", "--timeout", "nan", "status"], "--timeout"),
        (["ctl", "--timeout", "-1", "status"], "--timeout"),
        (
            ["ctl", "--api", "unix:/nonexistent/x.sock", "scan", "--range-um", "nan", "--line-rate-hz", "1"],
            "nan",
        ),
        (["linearity", "/dev/zero"], "not a regular file"),
        (["linearity", "/nonexistent.csv"], "No such file"),
        (["calibrate", "--config", "/dev/zero", "x.csv"], "not a regular file"),
        (["audit", "/dev/zero"], "not a regular file"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else v,
)
def test_bad_arguments_are_one_line_errors(tmp_path: Path, args: list[str], needle: str) -> None:
    """Tried: piezod scan with negative/NaN/zero/inf range, NaN/negative rate, --lines 0 or 2.5, --offset-
    um inf; ctl --timeout nan/-1; ctl scan --range-um nan; linearity/calibrate/audit of /dev/zero or a
    missing file. Held: one line naming the argument, exit 2, no traceback.
    """
    assert_one_line_error(piezod(*args), needle)


def test_unwritable_output_is_a_one_line_error(tmp_path: Path) -> None:
    """Tried: piezod scan --out into a path whose parent is a file. Held: one line naming the path, exit 2."""
    (tmp_path / "a-file").write_text("not a directory")
    proc = piezod(
        "scan",
        "--sim",
        "--range-um",
        "5",
        "--line-rate-hz",
        "4",
        "--lines",
        "1",
        "--out",
        str(tmp_path / "a-file" / "x.csv"),
    )
    assert_one_line_error(proc, "a-file")


def test_an_output_path_with_spaces_simply_works(tmp_path: Path) -> None:
    """Tried: piezod scan --out 'my scan (1).csv'. Held: the scan runs and the recording parses."""
    out = tmp_path / "my scan (1).csv"
    proc = piezod(
        "scan", "--sim", "--range-um", "5", "--line-rate-hz", "4", "--lines", "2", "--out", str(out)
    )
    assert proc.returncode == 0, proc.stderr
    rec = read_recording(out)
    assert rec.t_s.size > 100


def test_sigterm_ends_a_command_as_ctrl_c_does(tmp_path: Path) -> None:
    """Tried: SIGTERM (a plain ``kill``) to piezod scan --sim while it records. Held: one line, exit
    143, no traceback; the recording so far is complete to its last row; the simulator it started is
    gone."""
    # before, SIGTERM ended the process on the spot and left the simulator running
    import time

    out = tmp_path / "long.csv"
    args = ["scan", "--sim", "--range-um", "5", "--line-rate-hz", "1", "--lines", "200", "--out", str(out)]
    with piezod_process(args) as proc:
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and proc.poll() is None:
            if out.exists() and out.stat().st_size > 50_000:
                break
            time.sleep(0.1)
        assert proc.poll() is None, proc.communicate()
        sims = children(proc.pid)
        assert sims, "no simulator process under piezod scan --sim"
        err = sigterm(proc, 120.0)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "piezod scan: terminated (SIGTERM)"
    assert out.read_bytes().endswith(b"\n")
    assert read_recording(out).t_s.size > 1000
    assert ended_within(sims, 30.0)
