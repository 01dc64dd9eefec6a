"""`piezod calibrate --from-images` repeats a scan a fault broke, never one the safety check refused."""

from __future__ import annotations

import io
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from piezod.cli import calibrate_images as ci
from piezod.errors import CalibrationError, SafetyError
from piezod.imagecal import ImageScan


class _Engine:
    def status(self) -> Any:
        return SimpleNamespace(state="idle")


def test_a_refused_scan_is_not_repeated_a_broken_one_is(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls: list[str] = []
    outcomes: dict[str, list[Exception | None]] = {
        "refused": [SafetyError("would drive 207 samples beyond the voltage limits")],
        "broken": [CalibrationError("scan broken was interrupted (UNDERRUN)"), None],
    }

    def fake(engine: Any, scans: list[ImageScan], out_dir: Path, **kw: Any) -> list[Path]:
        name = scans[0].label
        calls.append(name)
        exc = outcomes[name].pop(0)
        if exc is not None:
            raise exc
        return [out_dir / f"{name}.csv"]

    monkeypatch.setattr(ci, "run_image_scans", fake)
    say = io.StringIO()
    with pytest.raises(SafetyError):
        ci._scan_with_retry(_Engine(), [ImageScan(14.0, 1.0, -10.5, label="refused")], tmp_path, say)
    assert calls == ["refused"]
    paths = ci._scan_with_retry(_Engine(), [ImageScan(20.0, 1.0, label="broken")], tmp_path, say)
    assert calls == ["refused", "broken", "broken"] and paths == [tmp_path / "broken.csv"]
    assert "repeating the scan" in say.getvalue()
