"""Where a written family member sits against the sensor on a stage's calibration frame.

Usage::

    python tools/member_offsets.py --stage configs/sim-birch35-holdout-stage.yaml F.yaml [G.yaml ...]

The default frame is played on the stage in this process (as ``tools/model_family_verify.py``
does), seen through each YAML's sensor path and runtime parts (as the calibration fits it), and
each experiment's offset is printed: its mean residual, the readback minus the member's position
(:func:`piezod.calibrate_family.experiment_offsets`). A member whose offsets are not ~0 sits
off the sensor's zero; one whose offsets spread has no one absolute position. The parts that act
on the absolute position then compress or stiffen in the wrong place (docs/model-family.md 6.2bp).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_family_verify import play_default_frame

from piezod.calibrate_family import experiment_offsets, session_positions
from piezod.config import load_config
from piezod.extensions import experiments_through
from piezod.stagecal import _frame_session


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", required=True, help="preset name or scanner YAML with simulation:")
    ap.add_argument("--axis", default="x")
    ap.add_argument("yaml", nargs="+", help="written scanner YAMLs whose family member to place")
    args = ap.parse_args()
    played = play_default_frame(args.stage, axis=args.axis)
    for name in args.yaml:
        ax = load_config(Path(name)).axes[args.axis]
        if ax.model != "family" or ax.family is None:
            print(f"{name}: axis {args.axis} is not a family member ({ax.model})")
            continue
        effects = {str(k): dict(v) for k, v in (ax.extensions or {}).items()}
        data = _frame_session(
            experiments_through(played.experiments, effects), played.ramp_v_per_s, played.rest_voltage_v
        )
        off = experiment_offsets(data, session_positions(data, ax.family.params()))
        print(
            f"{name}: offset_um {ax.family.offset_um:+.3f}; readback - member per experiment: "
            f"mean {np.mean(off):+.3f} um, {np.min(off):+.3f} ... {np.max(off):+.3f} um"
        )
        print("  " + " ".join(f"{o:+.2f}" for o in off))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
