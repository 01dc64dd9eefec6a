"""Can a sensorless calibration frame pin a sensitivity trend? Profile a thermal scale on its flanks.

Usage::

    python tools/image_thermal_profile.py CONFIG FRAME_DIR [--law generalised-play] [--driver position]
        [--plays 64] [--rates 0 0.5 1 1.5 2]

Builds the flank session of a recorded image frame as ``piezod calibrate --from-images`` does
(:func:`piezod.imagecal.frame_flank_session`), divides the flank positions by ``1 + r t / 360000`` (the
runtime thermal part's scale, ``t`` from the frame's first compared sample) and fits one family
member on the training scans for each rate ``r`` (%/h): training and held-out flank RMS per rate.
A trend the frame pins lowers the held-out RMS by more than the model choice's tie fraction.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from piezod import calibrate_family as cf
from piezod.config import load_config
from piezod.imagecal import frame_flank_session


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config")
    ap.add_argument("frame_dir")
    ap.add_argument("--pitch-um", type=float, default=3.0)
    ap.add_argument("--law", default="generalised-play")
    ap.add_argument("--driver", default="position")
    ap.add_argument("--plays", type=int, default=64)
    ap.add_argument("--rates", type=float, nargs="+", default=[0.0, 0.5, 1.0, 1.5, 2.0])
    args = ap.parse_args()
    base = load_config(args.config)
    paths = sorted(Path(args.frame_dir).glob("*.csv"))
    _, _, _, session = frame_flank_session(paths, args.pitch_um, base)
    t_grid = np.zeros(session.hysteresis_voltage_v.size)
    for dt, a, b in session.pieces:
        t_grid[a:b] = (t_grid[a - 1] if a else 0.0) + dt * np.arange(1, b - a + 1)
    t = t_grid[session.compared]
    print(f"frame: {len(paths)} scans, {t.size} flanks over {t.max() - t.min():.0f} s of the session")
    train = cf.holdout_mask(session.n_experiments)
    name = cf.member_name(args.law, args.driver, args.plays)
    for r in args.rates:
        s = dataclasses.replace(
            session, position_um=session.position_um / (1.0 + r * (t - t.min()) / 360000.0)
        )
        f = cf.fit_family(s, args.law, train=train, plays=args.plays, creep_driver=args.driver)
        print(
            f"thermal {r:+.2f} %/h: {name} train {1e3 * f.rms_um:.3f} nm,"
            f" held-out {1e3 * f.heldout_rms_um:.3f} nm"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
