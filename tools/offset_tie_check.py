"""What tying the frame's offsets to one sensor does to a family member (docs/model-family.md 6.2ar).

    OMP_NUM_THREADS=1 python tools/offset_tie_check.py STAGE [LAW ...]

Plays :func:`piezod.stagecal.default_frame` on the simulated stage ``STAGE`` (preset name or YAML
with ``simulation:``, in process), fits each law (default ``generalised-play``) with both creep
drivers on the training experiments (every 4th held out), once with an unknown offset per
experiment (the fits' default) and once with one offset and drift for the session
(:func:`piezod.stagecal.one_sensor_offsets`), and prints each fit's training and held-out RMS and
how far the model's per-experiment offsets spread against the sensor.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_family_verify import play_default_frame

from piezod.calibrate_family import fit_family, holdout_mask
from piezod.stagecal import _frame_session, offset_spread


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage")
    ap.add_argument("laws", nargs="*", default=["generalised-play"])
    args = ap.parse_args()
    t0 = time.perf_counter()
    played = play_default_frame(args.stage)
    sessions = {
        "per experiment": _frame_session(played.experiments, played.ramp_v_per_s, played.rest_voltage_v),
        "one sensor": _frame_session(
            played.experiments, played.ramp_v_per_s, played.rest_voltage_v, one_sensor=True
        ),
    }
    data = sessions["per experiment"]
    train = holdout_mask(data.n_experiments)
    print(f"{args.stage}: {data.n_experiments} experiments, {np.ptp(data.position_um):.3g} um of travel")
    for law in args.laws:
        for driver in ("position", "voltage"):
            parts = []
            for name, session in sessions.items():
                fit = fit_family(session, law, creep_driver=driver, train=train)
                spread, _ = offset_spread(data, fit.params)
                parts.append(
                    f"{name}: train {1e3 * fit.rms_um:.2f} held out {1e3 * fit.heldout_rms_um:.2f} nm, "
                    f"offsets spread {1e3 * spread:.0f} nm"
                )
            print(f"{law}, {driver} creep | " + " | ".join(parts), flush=True)
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
