"""Play the lag placement experiment on a simulated stage in process and place a config's lags.

    python tools/lag_placement_check.py --stage configs/sim-heath27-holdout-stage.yaml \
        --config F.yaml [--out placed.yaml]

``F.yaml`` is a scanner config calibrated on that stage (``piezod calibrate --sim ... --out
F.yaml``); the experiment (:mod:`piezod.lag_placement`) is played from rest after a ramp, read
through the stage's sensor, and :func:`piezod.lag_placement.place_lag` says how much of the
config's sensor path it places at the drive, and where the jumps' zero lies when it asks for
another move (docs/model-family.md 6.2ak, 6.2an). ``--out`` writes the config with the move the
calibration would make; with ``--placed``, at the jumps' zero (the member kept as written).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hil_sim.stage import Stage, StageConfig, resolve_stage
from piezod.config import AxisName, dump_config, load_config
from piezod.lag_placement import PLACEMENT_LABEL, moved_config, place_lag, program_for
from piezod.recording import Experiment


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", required=True, help="preset name or scanner YAML with simulation:")
    ap.add_argument("--config", required=True, metavar="F.yaml", help="the config calibrated on it")
    ap.add_argument("--axis", default="x")
    ap.add_argument("--out", default=None, metavar="F.yaml", help="the config with the lag placed")
    ap.add_argument(
        "--placed",
        action="store_true",
        help="with --out: the config at the jumps' zero (placed_s), a move the calibration may not make",
    )
    args = ap.parse_args()
    axis: AxisName = args.axis
    path = resolve_stage(args.stage)
    if path is None:
        raise SystemExit(f"no stage {args.stage!r}")
    base = load_config(path)
    config = load_config(args.config)
    rate = base.sample_rate_hz
    program = program_for(config, axis, rate)
    stage = Stage(StageConfig.from_file(path), axes=(axis,))
    dt = 1.0 / rate
    stage.sense(stage.step(np.linspace(0.0, float(program.volts[0]), round(0.5 * rate)), dt))
    readback = stage.sense(stage.step(program.volts, dt))
    t = dt * np.arange(readback.size, dtype=np.float64)
    exp = Experiment(PLACEMENT_LABEL, axis, t, program.volts, np.asarray(readback, dtype=np.float64))
    t0 = time.perf_counter()
    found = place_lag(exp, program, config, axis)
    took = time.perf_counter() - t0
    name = path.stem
    if found is None:
        print(f"{name}: no lag to place ({program.duration_s:.1f} s program)")
        return 0
    print(f"{name}: {found.note} ({program.duration_s:.1f} s program, analysis {took:.1f} s)")
    fmt = " ".join
    print(f"  jumps, written model: {fmt(f'{1e3 * j:+7.1f}' for j in found.jumps_um)} nm")
    print(f"  jumps, placed:        {fmt(f'{1e3 * j:+7.1f}' for j in found.jumps_moved_um)} nm")
    if args.out and (found.adopted or args.placed):
        moved_s = found.placed_s if args.placed else found.moved_s
        dump_config(moved_config(config, axis, moved_s), args.out, header=f"{found.note} ({name})")
        print(f"-> {args.out} ({moved_s * 1e3:+.3f} ms moved to the drive)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
