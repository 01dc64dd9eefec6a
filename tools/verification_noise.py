"""How much of each verified scan's nonlinearity (4.16) is the sensor's white noise.

    python tools/verification_noise.py RUN/rec/verify-family-*.csv [--config F.yaml]

For each recording of a verification point (``piezod calibrate --sim/--port --recordings-dir``):
what the verification computes from it (:func:`piezod.stagecal.verified_linearity`: (4.16), (4.15)
and the sensor's noise alone as a nonlinearity; (4.16) of the line-averaged profile at the image's
pixels and the noise left in it; on the readback aligned through the sensor path of ``--config``,
the calibrated YAML; docs/model-family.md 6.2ao).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from piezod.config import load_config
from piezod.stagecal import verified_linearity


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--axis", default="x")
    ap.add_argument("--config", type=Path, default=None, help="the calibrated YAML (its sensor path)")
    args = ap.parse_args()
    sensor = None if args.config is None else load_config(args.config).axes[args.axis].sensor_path()
    print(
        f"{'recording':<24} {'nonlin %':>9} {'length %':>9} {'noise %':>9} {'pixels %':>9} {'px noise %':>10}"
    )
    for path in args.recordings:
        f = verified_linearity(path, args.axis, sensor)
        print(
            f"{path.name:<24} {f.nonlinearity_pct:9.3f} {f.length_error_pct:+9.3f} {f.noise_pct:9.3f} "
            f"{f.pixel_nonlinearity_pct:9.3f} {f.pixel_noise_pct:10.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
