"""What the refit on a frame played again needs to know of the stage's past.

Usage::

    piezod calibrate --sim --config configs/sim-pi-stage.yaml --frame reduced --no-audit \\
        --no-verify --refresh-after 0 --out F.yaml --json F.json
    python tools/refresh_history.py F.yaml F.json

On that run's recordings (``F-recordings/frame.csv`` and ``frame-again.csv``, one clock) the
chosen member is refitted as :func:`piezod.stagecal.refresh_member` does, and as it would with
less of the stage's past: the held-out RMS of each (docs/model-family.md 6.2br). With
``--rule-only``, the rule alone from the first frame's model (``first-frame.yaml``), beside that
model kept unchanged on the same held-out scans, with an offset per scan and with one sensor's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from piezod import calibrate_family as cf
from piezod.config import load_config
from piezod.recording import Experiment, read_experiments
from piezod.stagecal import refit_at_drive_lag, refresh_member


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="the YAML `piezod calibrate --refresh-after` wrote")
    ap.add_argument("report", help="its --json report")
    ap.add_argument("--axis", default="x")
    ap.add_argument(
        "--rule-only",
        action="store_true",
        help="only the rule's refit beside the first frame's member kept, with an offset per scan and "
        "with one sensor's",
    )
    args = ap.parse_args()
    cfg, doc = load_config(args.config), json.loads(Path(args.report).read_text())
    # the audit's redone choice when it adopted parts
    choice = doc.get("audit", {}).get("model_choice", doc["model_choice"])
    chosen = choice["chosen"]
    member = cf.parse_member(chosen)
    if member is None or "recording" not in doc.get("refresh", {}):
        raise SystemExit(f"{args.report}: no family member refitted on a frame played again")
    placement = doc["frame"].get("lag_placement_recording")
    first = read_experiments([Path(doc["frame"]["recording"])], axis=args.axis)
    lead = read_experiments([Path(placement)], axis=args.axis) if placement else []
    again = read_experiments([Path(doc["refresh"]["recording"])], axis=args.axis)
    ramp, rest = cfg.service.ramp_rate_v_per_s, cfg.axes[args.axis].safe_voltage_v

    def refit(exps: list[Experiment], history: list[Experiment], one_sensor: bool = False) -> float:
        _, rms = refit_at_drive_lag(
            exps, cfg, args.axis, member[2], ramp, rest, one_sensor=one_sensor, history=history
        )
        return rms

    print(f"{chosen}: the choice's held-out RMS {choice['heldout_rms_um'][chosen] * 1e3:.2f} nm")
    if args.rule_only:
        # the rule as refresh_member runs it from the first frame's model, beside that model kept
        # kept beside the recordings when the refit was written; otherwise it is the written one
        first_cfg = load_config(doc["refresh"].get("first_frame_config", args.config))
        print("| offsets | the refit | the first frame's member kept |\n|---|---|---|")
        for one in (False, True):
            got = refresh_member(
                again, args.axis, first_cfg, chosen, ramp, rest, one, history=[*first, *lead]
            )
            offsets = "the offsets of one sensor" if one else "an offset per scan"
            print(f"| {offsets} | {got.heldout_rms_um * 1e3:.2f} nm | {got.kept_rms_um * 1e3:.2f} nm |")
        return 0
    print("| refit of the chosen member | held out |\n|---|---|")
    rows = [
        ("the first frame (refitted so)", refit(first, [])),
        ("the frame played again, as if the stage had rested until it", refit(again, [])),
        ("after the first frame, the new frame's first scan fitted", refit(again, [*first, *lead])),
        ("the new frame's first scan only run through", refit(again[1:], again[:1])),
        (
            "the first frame and the first scan run through (refresh_member)",
            refit(again[1:], [*first, *lead, again[0]]),
        ),
    ]
    for what, rms in rows:
        print(f"| {what} | {rms * 1e3:.2f} nm |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
