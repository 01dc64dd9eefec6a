"""``piezod image``: trace / retrace images of raster recordings (.gwy + PNG), image-based linearity."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from piezod.cli._common import (
    add_json_option,
    finite_float,
    human_stream,
    positive_float,
    positive_int,
    write_json,
)
from piezod.config import load_config
from piezod.errors import RecordingError
from piezod.image import ImagePair, has_position_sensor, images, raster_samples
from piezod.image_io import write_gwy, write_pair_png, write_png
from piezod.image_linearity import (
    image_linearity,
    pitch_error,
    plot_pitch_error,
    sensor_slow_linearity,
    slow_image_linearity,
    window_linearity,
)
from piezod.linearity import linearity
from piezod.recording import read_experiments, read_recording


def register(sub: Any) -> None:
    """Add the ``image`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "image",
        help="trace/retrace images of raster recordings: Gwyddion .gwy + PNG; image-based linearity",
        description=(
            "Assemble the trace and retrace images of every height channel of a raster recording "
            "(z_voltage as recorded; with --config also height_model, the z axis's forward model, and "
            "height_linear, one constant sensitivity) on the commanded grid and, when the board had a "
            "position sensor, on the measured positions. Writes DIR/NAME.gwy (all images, with the scan's "
            "metadata) and PNGs. With --pitch-um, the non-linearity and length error (4.14)-(4.16) from "
            "the flanks of a line pattern of that pitch, beside the sensor's figures when there is one "
            "(over the image metric's windows by the same regression, and over the whole lines)."
        ),
    )
    p.add_argument("recordings", nargs="+", metavar="REC.csv", help="raster recordings (piezod scan)")
    p.add_argument("--out", metavar="DIR", default=".", help="output directory (default: .)")
    p.add_argument("--config", metavar="F", help="scanner YAML whose z axis converts z voltage to height")
    p.add_argument(
        "--pixels", type=positive_int, metavar="N", help="pixels per line (default: the recording's)"
    )
    p.add_argument(
        "--z-sensitivity-um-per-v",
        type=finite_float,
        metavar="S",
        help="constant z sensitivity of height_linear (default: best fit to the model heights)",
    )
    p.add_argument(
        "--pitch-um", type=positive_float, metavar="P", help="pitch of the reference: image linearity"
    )
    p.add_argument(
        "--frame",
        type=int,
        metavar="K",
        help="only frame K (0, 1, ...) of a multi-frame scan (the recording's 'lines' per frame); "
        "files NAME-fK.gwy / NAME-fK-*.png",
    )
    p.add_argument("--no-png", action="store_true", help="write the .gwy files only")
    p.add_argument(
        "--pair",
        metavar="F.png",
        help="also one picture of the first two recordings' trace images side by side "
        "(uncorrected, corrected), with the --pitch-um grid",
    )
    add_json_option(p)
    p.set_defaults(func=run)


def _headline(pairs: list[ImagePair]) -> ImagePair:
    order = ("height_model", "height_linear", "z_voltage")
    cmd = [q for q in pairs if q.grid == "commanded"]
    return sorted(cmd, key=lambda q: order.index(q.channel) if q.channel in order else 9)[0]


def _slow_axis(entry: dict[str, Any], rec: Any, head: ImagePair, pitch_um: float, say: Any) -> None:
    """The slow axis's (4.14)-(4.16) from the columns of a 2D grating image (and its sensor's)."""
    rows: dict[int, Any] = {1: None, -1: None}
    y = None if rec.axis is None or rec.target_um is None else rec.axis == "y"
    rs = raster_samples(rec)
    if y is not None and y.any():
        for d in (1, -1):  # the commanded slow position of every line: its mean over the line
            rows[d] = np.array(
                [
                    float(
                        np.mean(
                            np.interp(
                                rs.t_s[(rs.line == k) & (rs.direction == d)], rec.t_s[y], rec.target_um[y]
                            )
                        )
                    )
                    for k in range(rs.lines)
                ]
            )
    try:
        slow = {
            name: slow_image_linearity(img, head.geometry, pitch_um, d, rows[d])
            for name, img, d in (("trace", head.trace, 1), ("retrace", head.retrace, -1))
        }
    except RecordingError:
        return  # a 1D pattern along the slow axis: no flanks across it
    entry["slow_image_linearity"] = {k: v.as_dict() for k, v in slow.items()}
    print(
        "  slow axis, image (flanks):  "
        + "  ".join(
            f"{k} nonlin {v.nonlinearity_pct:.4f} % length {v.length_error_pct:+.4f} %"
            for k, v in slow.items()
        ),
        file=say,
    )
    if entry["position_sensor"] and y is not None and y.any():
        t_img = rs.t_s[rs.line >= 0]
        nl, le = sensor_slow_linearity(
            rec.t_s[y], rec.target_um[y], rec.position_um[y], float(t_img.min()), float(t_img.max())
        )
        entry["slow_sensor_linearity"] = {"nonlinearity_pct": nl, "length_error_pct": le}
        print(f"  slow axis, sensor (samples): nonlin {nl:.4f} % length {le:+.4f} %", file=say)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod image``."""
    out_dir = Path(args.out)
    z_axis = None
    if args.config:
        cfg = load_config(args.config)
        z_axis = cfg.axes.get("z")
        if z_axis is None:
            raise RecordingError(f"{args.config}: the scanner has no z axis (needed for heights)")
    say = human_stream(args)
    results: list[dict[str, Any]] = []
    headlines: list[ImagePair] = []
    for path in args.recordings:
        rec = read_recording(path)
        pairs = images(
            rec,
            z_axis=z_axis,
            pixels=args.pixels,
            sensitivity_um_per_v=args.z_sensitivity_um_per_v,
            frame=args.frame,
        )
        stem = Path(path).stem if args.frame is None else f"{Path(path).stem}-f{args.frame}"
        headlines.append(_headline(pairs))
        meta = rec.metadata if args.frame is None else {**rec.metadata, "frame": str(args.frame)}
        files = [str(write_gwy(out_dir / f"{stem}.gwy", pairs, meta, str(path)))]
        if not args.no_png:
            for q in pairs:
                title = f"{stem}: {q.channel} ({q.grid} grid), {q.geometry.range_um:g} um"
                files.append(str(write_png(out_dir / f"{stem}-{q.channel}-{q.grid}.png", q, title)))
        entry: dict[str, Any] = {
            "path": str(path),
            "files": files,
            "position_sensor": has_position_sensor(rec),
        }
        print(f"{path}: {len(pairs)} image pairs -> {files[0]}", file=say)
        if args.pitch_um is not None:
            head = _headline(pairs)
            try:
                branches = {
                    name: image_linearity(img, head.geometry, args.pitch_um, d)
                    for name, img, d in (("trace", head.trace, 1), ("retrace", head.retrace, -1))
                }
            except RecordingError as exc:
                if args.pair:  # the pair's grid needs the pitch, the metrics more periods than it shows
                    print(f"  no image linearity: {exc}", file=say)
                    results.append(entry)
                    continue
                raise
            entry["image_linearity"] = {k: v.as_dict() for k, v in branches.items()}
            line = "  image (flanks):           " + "  ".join(
                f"{k} nonlin {v.nonlinearity_pct:.4f} % length {v.length_error_pct:+.4f} "
                f"+- {v.length_error_unc_pct:.4f} %"
                for k, v in branches.items()
            )
            print(line, file=say)
            if entry["position_sensor"]:
                exp = linearity(read_experiments([path], axis="x")).experiments[0]
                entry["sensor_linearity"] = {
                    "trace": {
                        "nonlinearity_pct": exp.trace.nonlinearity_pct,
                        "length_error_pct": exp.trace.length_error_pct,
                    },
                    "retrace": {
                        "nonlinearity_pct": exp.retrace.nonlinearity_pct,
                        "length_error_pct": exp.retrace.length_error_pct,
                    },
                }
                tr, rt = exp.trace, exp.retrace
                rs = raster_samples(rec)
                same = {
                    k: window_linearity(rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, v)
                    for k, v in branches.items()
                }
                entry["sensor_window_linearity"] = {
                    k: {"nonlinearity_pct": b.nonlinearity_pct, "length_error_pct": b.length_error_pct}
                    for k, b in same.items()
                }
                print(
                    "  sensor (image's windows): "
                    + "  ".join(
                        f"{k} nonlin {b.nonlinearity_pct:.4f} % length {b.length_error_pct:+.4f} %"
                        for k, b in same.items()
                    ),
                    file=say,
                )
                print(
                    f"  sensor (whole lines):     trace nonlin {tr.nonlinearity_pct:.4f} % length "
                    f"{tr.length_error_pct:+.4f} %  retrace nonlin {rt.nonlinearity_pct:.4f} % "
                    f"length {rt.length_error_pct:+.4f} %",
                    file=say,
                )
            _slow_axis(entry, rec, head, args.pitch_um, say)
            if not args.no_png:
                xt, et = pitch_error(head.trace, head.geometry, args.pitch_um)
                xr, er = pitch_error(head.retrace, head.geometry, args.pitch_um)
                png = plot_pitch_error(
                    [(f"{stem} ({head.channel}, commanded grid)", xt, et, xr, er)],
                    args.pitch_um,
                    out_dir / f"{stem}-pitch-error.png",
                    f"{stem}: image-based linearity",
                )
                files.append(str(png))
        results.append(entry)
    if args.pair:
        if len(headlines) < 2:
            raise RecordingError("--pair needs two recordings (uncorrected, corrected)")
        left, right = headlines[0], headlines[1]
        write_pair_png(
            left,
            right,
            Path(args.pair),
            titles=(
                f"uncorrected: {Path(args.recordings[0]).stem}",
                f"corrected: {Path(args.recordings[1]).stem}",
            ),
            pitch_um=args.pitch_um,
            suptitle=f"trace images, {left.channel}"
            + (
                f"; dotted: the reference's {args.pitch_um:g} um pitch on a linear scan"
                if args.pitch_um
                else ""
            ),
        )
        print(f"pair: {args.pair}", file=say)
    write_json(args.json, {"recordings": results})
    return 0
