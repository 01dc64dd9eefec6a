"""How much of each verified scan's nonlinearity (4.16) is the sensor's white noise.

    python tools/verification_noise.py RUN/rec/verify-family-*.csv [--config F.yaml]

For each recording of a verification point (``piezod calibrate --sim/--port --recordings-dir``):
(4.14)-(4.16) as the verification computes them from the readback (aligned through the sensor path
of ``--config``, the calibrated YAML, as the verification does), and
:func:`piezod.linearity.noise_pct`, the readback's third-difference noise floor over the measured
range (docs/model-family.md 6.2ao).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from piezod.config import load_config
from piezod.extensions import experiments_through_sensor
from piezod.linearity import linearity, noise_pct
from piezod.recording import read_experiments


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--axis", default="x")
    ap.add_argument("--config", type=Path, default=None, help="the calibrated YAML (its sensor path)")
    args = ap.parse_args()
    sensor = None if args.config is None else load_config(args.config).axes[args.axis].sensor_path()
    print(f"{'recording':<24} {'range um':>9} {'nonlin %':>9} {'length %':>9} {'noise %':>9}")
    for path in args.recordings:
        exp = read_experiments([path], axis=args.axis)[0]
        if sensor is not None:
            exp = experiments_through_sensor([exp], sensor)[0]
        e = linearity([exp]).experiments[0]
        measured = e.trace.measured_range_um
        print(
            f"{path.name:<24} {e.trace.nominal_range_um:9.3g} {e.nonlinearity_pct:9.3f} "
            f"{e.length_error_pct:+9.3f} {noise_pct(exp.position_um, measured):9.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
