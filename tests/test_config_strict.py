"""Strict scanner-config loading: what a config file must not be able to do (issue #13 item 7, #6).

Each hostile file is refused with one ``FILE:LINE: field: reason`` line per problem, in process
and through the real ``piezod serve`` command (exit 2, no traceback), and nothing is expanded
or allocated beyond the limits.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from piezod.config import (
    MAX_CONFIG_BYTES,
    ScannerConfig,
    config_dir,
    dump_config,
    load_config,
)
from piezod.errors import ConfigError

BASE = (config_dir() / "medium-tube.yaml").read_text(encoding="utf-8")


def _write(tmp_path: Path, text: str | bytes, name: str = "scanner.yaml") -> Path:
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text, encoding="utf-8")
    return p


def _refused(path: Path) -> str:
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert str(path) in msg
    return msg


def test_the_base_config_loads_and_round_trips(tmp_path: Path) -> None:
    cfg = load_config(_write(tmp_path, BASE))
    out = tmp_path / "again.yaml"
    dump_config(cfg, out, header="round trip")
    assert load_config(out) == cfg


def test_duplicate_key_is_refused_with_both_lines(tmp_path: Path) -> None:
    """Tried: a YAML with voltage_max_v twice (230, then 2000). Held: refused naming both lines."""
    text = BASE.replace("voltage_max_v: 230.0", "voltage_max_v: 230.0\n    voltage_max_v: 2000", 1)
    assert text != BASE
    msg = _refused(_write(tmp_path, text))
    assert "duplicate key 'voltage_max_v'" in msg
    line = next(i for i, t in enumerate(text.splitlines(), 1) if "2000" in t)
    assert f":{line}:" in msg and f"first on line {line - 1}" in msg


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("slew_rate_v_per_s: 2000.0", "slew_rate_v_per_s: .inf", "slew_rate_v_per_s"),
        ("tau_s:", "tau_s: .nan #", "tau_s"),
    ],
)
def test_non_finite_numbers_are_refused(tmp_path: Path, old: str, new: str, field: str) -> None:
    """Tried: slew_rate_v_per_s: .inf, tau_s: .nan. Held: refused, FILE:LINE: field."""
    assert old in BASE
    text = BASE.replace(old, new, 1)
    msg = _refused(_write(tmp_path, text))
    assert field in msg and "finite" in msg


def test_a_bool_is_not_a_number(tmp_path: Path) -> None:
    """Tried: sample_rate_hz: true. Held: refused (not read as 1 Hz)."""
    text = BASE.replace("sample_rate_hz: 10000.0", "sample_rate_hz: true")
    msg = _refused(_write(tmp_path, text))
    assert "sample_rate_hz" in msg and ":28:" in msg


def test_scientific_notation_without_a_dot_is_a_number(tmp_path: Path) -> None:
    cfg = load_config(_write(tmp_path, BASE.replace("sample_rate_hz: 10000.0", "sample_rate_hz: 2e4")))
    assert cfg.sample_rate_hz == 20_000.0


def test_billion_laughs_is_refused_without_expanding(tmp_path: Path) -> None:
    """Tried: a billion-laughs YAML (9 levels of 9 aliases). Held: refused after 100k values, nothing
    expanded.
    """
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 10):
        refs = ",".join([f"*a{i - 1}"] * 9)
        lines.append(f"a{i}: &a{i} [{refs}]")
    text = "simulation:\n" + "".join(f"  {line}\n" for line in lines) + BASE
    msg = _refused(_write(tmp_path, text))
    assert "alias expansion" in msg


def test_deep_nesting_is_refused(tmp_path: Path) -> None:
    """Tried: 20,000 nested [. Held: refused (32 levels), no RecursionError."""
    msg = _refused(_write(tmp_path, "notes: " + "[" * 20_000 + "]" * 20_000 + "\n"))
    assert "nested" in msg


def test_a_latin1_byte_names_its_line(tmp_path: Path) -> None:
    """Tried: a Latin-1 byte (0xb5). Held: refused naming the line and the byte."""
    raw = BASE.encode() + b"description: \xb5m scanner\n"
    msg = _refused(_write(tmp_path, raw))
    line = raw.count(b"\n")
    assert f":{line}:" in msg and "0xb5" in msg and "UTF-8" in msg


def test_huge_files_and_devices_are_not_read(tmp_path: Path) -> None:
    """Tried: a 1 MiB+ file; /dev/zero as a config. Held: refused after reading at most 1 MiB."""
    big = _write(tmp_path, b"# " + b"x" * MAX_CONFIG_BYTES + b"\n")
    assert "larger than" in _refused(big)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config("/dev/zero")


def test_typo_is_an_unknown_key_with_a_suggestion_not_a_missing_field(tmp_path: Path) -> None:
    """Tried: voltage_mn_v (a typo). Held: 'unknown key (did you mean voltage_min_v?)', no 'Field
    required'.
    """
    text = BASE.replace("voltage_min_v:", "voltage_mn_v:", 1)
    msg = _refused(_write(tmp_path, text))
    assert "voltage_mn_v: unknown key (did you mean voltage_min_v?)" in msg
    assert "Field required" not in msg


def test_every_problem_is_listed(tmp_path: Path) -> None:
    """Tried: a config with four problems. Held: four lines, one per problem (no 'and 3 more')."""
    text = BASE.replace("voltage_min_v:", "voltage_mn_v:", 1)
    text = text.replace("tau_s:", "tau_s: -1 #", 1)
    text = "bogus_key: 1\n" + text.replace("sample_rate_hz: 10000.0", "sample_rate_hz: -5")
    msg = _refused(_write(tmp_path, text))
    lines = msg.splitlines()
    assert len(lines) == 4, msg
    assert "more)" not in msg
    assert all(line.startswith(f"{tmp_path / 'scanner.yaml'}:") for line in lines)


def test_config_errors_through_the_real_cli_are_one_line_per_problem(tmp_path: Path) -> None:
    """Tried: piezod serve --config with bad files, and /dev/zero. Held: exit 2, no traceback."""
    text = BASE.replace("sample_rate_hz: 10000.0", "sample_rate_hz: true").replace(
        "voltage_max_v: 230.0", "voltage_max_v: 230.0\n    voltage_max_v: 2000", 1
    )
    bad = _write(tmp_path, text)
    for args in (
        ["serve", "--config", str(bad), "--sim", "--api", f"unix:{tmp_path / 's.sock'}"],
        ["serve", "--config", "/dev/zero", "--sim", "--api", f"unix:{tmp_path / 's.sock'}"],
    ):
        proc = subprocess.run(
            [sys.executable, "-m", "piezod", *args], capture_output=True, text=True, timeout=120
        )
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        assert proc.stderr.strip().count("\n") == 0, proc.stderr


def test_schema_is_unchanged_by_strictness() -> None:
    assert "sample_rate_hz" in ScannerConfig.model_json_schema()["properties"]
    yaml.safe_load(BASE)  # the base text itself is plain YAML
