"""The sensorless frame's law fit from the flanks beside the same fit with the hidden truth.

For the frame recordings of a ``piezod calibrate --sim --from-images`` run (its recordings
directory holds ``truth.f64``, the simulator's truth log, and ``frame/*.csv``): the session
compared at the flanks (:func:`piezod.imagecal.flank_session`), and the same session with the
true position at every compared sample in place of the flank positions. One law of the family
(default Prandtl-Ishlinskii with voltage-driven creep) is fitted on both, trained on the choice's
training scans: the truth fit shows what the session layout allows, the flank fit what the flanks
add. ``--settle-lines N`` lays the gaps out as the daemon runs rasters (what ``piezod calibrate``
does); ``--settle-lines -1`` the default reconstruction (up to eight settling loops after a hold
at the next start), for comparison.

Usage::

    python tools/flank_fit_check.py RECORDINGS_DIR [--config F] [--law L] [--driver D] [--settle-lines N]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from piezod import calibrate_family as cf
from piezod import imagecal as ic
from piezod.config import load_config
from piezod.recording import read_recording
from piezod.trajectory import SETTLE_LINES


def main(argv: list[str] | None = None) -> int:
    """Print the flank and truth fits."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("recordings_dir", type=Path)
    p.add_argument("--config", default="configs/sim-pi-microscope.yaml", help="the scanner YAML of the run")
    p.add_argument("--pitch-um", type=float, default=3.0)
    p.add_argument("--law", default="prandtl-ishlinskii")
    p.add_argument("--driver", default="voltage", help="creep driver")
    p.add_argument("--settle-lines", type=int, default=SETTLE_LINES, help="-1: the default reconstruction")
    args = p.parse_args(argv)
    base = load_config(args.config)
    frame = args.recordings_dir / "frame"
    paths = [frame / f"{s.name()}.csv" for s in ic.default_image_frame()]
    recs = [read_recording(q) for q in paths]
    events = [ic.flank_events(r, args.pitch_um, label=q.stem) for r, q in zip(recs, paths, strict=True)]
    th = ic.fit_thesis_from_flanks(recs, events, start=base.axes["x"].thesis.params())
    settle = None if args.settle_lines < 0 else args.settle_lines
    ramp = base.service.ramp_rate_v_per_s
    session = ic.flank_session(
        recs, events, th.line_width_um, slew_rate_v_per_s=ramp, rest_voltage_v=0.0, settle_lines=settle
    )
    # the compared samples' times: the same layout with the time in place of the position
    truths = []
    idx, tx = ic.read_truth_log(args.recordings_dir / "truth.f64")
    for rec in recs:
        sel = ic._x_rows(rec)
        truths.append((rec.t_s[sel], ic.with_truth(rec, (idx, tx), base.sample_rate_hz).position_um[sel]))
    timed = ic.timed_layout(recs, events, slew_rate_v_per_s=ramp, rest_voltage_v=0.0, settle_lines=settle)
    grid_t = np.full(timed.grid_index.size, np.nan)
    grid_t[timed.compared] = timed.position_um
    true_pos = np.empty(session.compared.size)
    for i in range(session.n_experiments):
        a, c = int(session.starts[i]), int(session.counts[i])
        t, x = truths[i]
        true_pos[a : a + c] = np.interp(grid_t[session.compared[a : a + c]], t, x)
    train = cf.holdout_mask(session.n_experiments)
    name = f"{args.law}/{args.driver}-creep"
    gaps = "default reconstruction" if settle is None else f"{settle} settling lines after a hold"
    print(
        f"{len(events)} scans, {sum(len(e) for e in events)} flanks; gaps: {gaps}; held out: "
        + ", ".join(session.experiments[i].label for i in np.flatnonzero(~train))
    )
    for label, data in (("flanks", session), ("truth", dataclasses.replace(session, position_um=true_pos))):
        fit = cf.fit_family(data, args.law, creep_driver=args.driver, train=train)
        print(
            f"{label:7s} {name}: train {fit.rms_um * 1e3:.2f} nm, held out {fit.heldout_rms_um * 1e3:.2f} nm"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
