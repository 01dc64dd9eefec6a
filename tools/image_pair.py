"""Regenerate docs/image-pair.png: the README's uncorrected vs corrected image pair.

Usage: ``python tools/image_pair.py [--out docs/image-pair.png] [--stage pi|own]``

Two scans of the simulated 10 um grating (30 um at 2 Hz, 48 lines, 256 pixels) on the simulated
tube scanner without a position sensor - the plain voltage triangle, then corrected online by the
model ``piezod calibrate --from-images`` fitted from images of the 3 um line pattern - and
``piezod image --pair`` of the two. ``--stage pi`` (default) is the scanner of other physics
(``configs/sim-pi-microscope*.yaml``: Prandtl-Ishlinskii hysteresis, voltage-driven creep),
``own`` the one built from the controller's own model (``configs/sim-microscope*.yaml``).
About 3 minutes.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {
    "pi": ("sim-pi-microscope.yaml", "sim-pi-microscope-calibrated.yaml"),
    "own": ("sim-microscope.yaml", "sim-microscope-calibrated.yaml"),
}
SCAN = [
    "--sample",
    "grating-10um",
    "--range-um",
    "30",
    "--line-rate-hz",
    "2",
    "--lines",
    "48",
    "--pixels",
    "256",
]


def _piezod(*args: str, cwd: Path) -> None:
    cmd = [sys.executable, "-m", "piezod", *args]
    print("+ piezod " + " ".join(args), flush=True)
    subprocess.run(cmd, cwd=cwd, check=True)


def main(argv: list[str] | None = None) -> int:
    """Scan both images and write the pair."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "image-pair.png"), help="the picture")
    parser.add_argument("--stage", choices=sorted(CONFIGS), default="pi", help="which simulated scanner")
    args = parser.parse_args(argv)
    raw_cfg, cal_cfg = (str(ROOT / "configs" / name) for name in CONFIGS[args.stage])
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        _piezod(
            "scan",
            "--sim",
            "--config",
            raw_cfg,
            *SCAN,
            "--no-correction",
            "--out",
            "plain-triangle.csv",
            cwd=d,
        )
        _piezod("scan", "--sim", "--config", cal_cfg, *SCAN, "--out", "sensorless-calibrated.csv", cwd=d)
        out = str(Path(args.out).resolve())
        _piezod(
            "image",
            "plain-triangle.csv",
            "sensorless-calibrated.csv",
            "--config",
            cal_cfg,
            "--pitch-um",
            "10",
            "--pair",
            out,
            "--out",
            "img",
            cwd=d,
        )
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
