"""Image metric vs the hidden truth per branch, and the truth as the reference's flanks sample it.

For the verification recordings of a ``piezod calibrate --sim --from-images`` run (its recordings
directory holds ``truth.f64``, the simulator's truth log, and ``verify-*/*.csv``), per branch
(trace / retrace) the length error (4.15):

* ``image``: the image metric (``piezod.image_linearity.image_linearity``);
* ``truth``: the true position over the image metric's windows, regressed alike
  (``window_linearity``: what the image measures);
* ``at flanks``: the true position taken at the image's flanks only and interpolated linearly
  between them (``flank_sampled_linearity``): what a perfect flank metric would read.

``truth - at flanks`` is the position structure finer than the flank spacing (no metric of this
reference can see it); ``image - at flanks`` what the image metric itself adds.

Usage::

    python tools/image_flank_limit.py RECORDINGS_DIR [--pitch-um 3] [--json F]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from piezod.cli.calibrate_images import _verify_here
from piezod.recording import read_recording


def main(argv: list[str] | None = None) -> int:
    """Print the table (and write it as JSON with ``--json``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("recordings_dir", type=Path)
    p.add_argument("--pitch-um", type=float, default=3.0)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    truth = args.recordings_dir / "truth.f64"
    paths = sorted(args.recordings_dir.glob("verify-*/*.csv"))
    if not truth.is_file() or not paths:
        print(
            f"{args.recordings_dir}: no truth.f64 and verify-*/*.csv (a --sim --from-images run)",
            file=sys.stderr,
        )
        return 2
    rate = float(read_recording(paths[0]).metadata.get("sample_rate_hz", "5000"))
    rows: list[dict[str, Any]] = []
    print(
        f"{'model':<8} {'scan':<20} {'branch':<8} {'image %':>8} {'truth %':>8} {'at flanks %':>11} "
        f"{'image-truth':>11} {'truth-at flanks':>15}"
    )
    for path in paths:
        out = _verify_here(path, args.pitch_um, truth, rate)
        model = path.parent.name.removeprefix("verify-")
        for b in ("trace", "retrace"):
            try:
                im = out["image"]["branches"][b]["length_error_pct"]
                tr = out["truth"]["branches"][b]["length_error_pct"]
                fl = out["truth_at_flanks"]["branches"][b]["length_error_pct"]
            except KeyError:
                print(f"{model:<8} {path.stem:<20} {b:<8} {out.get('image_error', 'no image metric')}")
                continue
            rows.append(
                {
                    "model": model,
                    "scan": path.stem,
                    "branch": b,
                    "image_pct": im,
                    "truth_pct": tr,
                    "truth_at_flanks_pct": fl,
                }
            )
            print(
                f"{model:<8} {path.stem:<20} {b:<8} {im:+8.3f} {tr:+8.3f} {fl:+11.3f} {im - tr:+11.3f} "
                f"{tr - fl:+15.3f}"
            )
    n = len(rows)
    within = sum(abs(r["image_pct"] - r["truth_pct"]) <= 0.05 for r in rows)
    perfect = sum(abs(r["truth_at_flanks_pct"] - r["truth_pct"]) <= 0.05 for r in rows)
    print(
        f"image vs truth within 0.05 %: {within} of {n}; "
        f"a perfect flank metric (at flanks) would be: {perfect} of {n}"
    )
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
