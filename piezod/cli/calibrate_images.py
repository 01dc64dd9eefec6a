"""``piezod calibrate (--sim | --port URL) --from-images --pitch-um P``: calibration without a sensor.

Records a frame of uncorrected trace / retrace images of a line pattern of pitch ``P`` (several
ranges, line rates, offsets), fits the thesis model (3.8) and the dynamic model to the flanks
(:mod:`piezod.imagecal`), writes the YAML, and verifies corrected images inside and outside the
frame by the image metrics - on the simulator also by the hidden truth (the board's truth log),
side by side.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from piezod.calibrate import calibrated_config as thesis_config
from piezod.calibrate_dynamic import calibrated_config as dynamic_config
from piezod.calibrate_dynamic import fit_dynamic
from piezod.cli._common import board_url, human_stream, scanner_config_path, with_microscope, write_json
from piezod.config import MicroscopeSection, ScannerConfig, dump_config, load_config
from piezod.errors import CalibrationError, PiezodError, SafetyError
from piezod.image import images, raster_samples
from piezod.image_linearity import find_flanks, flank_sampled_linearity, image_linearity, window_linearity
from piezod.imagecal import (
    RECHECK_MIN_INTERVAL_S,
    default_image_frame,
    drop_outlier_flanks,
    frame_flank_session,
    read_truth_log,
    recheck_scan,
    recording_span_unix_s,
    run_image_scans,
    search_polarity,
    search_saturation,
    sensitivity_recheck,
    session_through_polarity,
    verification_scans,
    with_truth,
)
from piezod.linearity import experiment_linearity
from piezod.recording import read_recording, split_experiments


def _worse(d: dict[str, dict[str, float]]) -> dict[str, float]:
    """The worse of trace and retrace: the larger non-linearity, the length error of larger magnitude
    (with its uncertainty when it has one)."""
    tr, rt = d["trace"], d["retrace"]
    le = max((tr, rt), key=lambda b: abs(b["length_error_pct"]))
    out = {
        "nonlinearity_pct": max(tr["nonlinearity_pct"], rt["nonlinearity_pct"]),
        "length_error_pct": le["length_error_pct"],
    }
    if "length_error_unc_pct" in le:
        out["length_error_unc_pct"] = le["length_error_unc_pct"]
    return out


def _verify_here(path: Path, pitch_um: float, truth: Path | None, rate_hz: float) -> dict[str, Any]:
    """Image metrics of a verification scan and, on the simulator, the hidden truth's: over the image
    metric's windows by the same regression (:func:`piezod.image_linearity.window_linearity`), and
    over the whole lines by the sensor path (:func:`piezod.linearity.experiment_linearity`)."""
    out: dict[str, Any] = {}
    rec = read_recording(path)
    pair = next(p for p in images(rec) if p.grid == "commanded" and p.channel == "z_voltage")
    lins = {}
    try:
        for name, img, d in (("trace", pair.trace, 1), ("retrace", pair.retrace, -1)):
            lins[name] = image_linearity(img, pair.geometry, pitch_um, d)
    except PiezodError as exc:
        out["image_error"] = str(exc)
        lins = {}
    if lins:
        per = {
            k: {
                "nonlinearity_pct": v.nonlinearity_pct,
                "length_error_pct": v.length_error_pct,
                "length_error_unc_pct": v.length_error_unc_pct,
            }
            for k, v in lins.items()
        }
        out["image"] = {**_worse(per), "branches": per}
    if truth is None:
        return out
    true_rec = with_truth(rec, read_truth_log(truth), rate_hz)
    if lins:
        rs = raster_samples(true_rec)
        per, at_flanks = {}, {}
        for k, v in lins.items():
            b = window_linearity(rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, v)
            per[k] = {"nonlinearity_pct": b.nonlinearity_pct, "length_error_pct": b.length_error_pct}
            # the truth as the flanks sample it: what a perfect flank metric would read
            img = pair.trace if v.direction > 0 else pair.retrace
            fl = find_flanks(img, pair.geometry)
            try:
                f = flank_sampled_linearity(
                    rs.t_s, rs.target_um, rs.position_um, rs.line, rs.direction, v, fl
                )
            except PiezodError as exc:
                out["truth_at_flanks_error"] = str(exc)
                continue
            at_flanks[k] = {"nonlinearity_pct": f.nonlinearity_pct, "length_error_pct": f.length_error_pct}
        out["truth"] = {**_worse(per), "branches": per}
        if len(at_flanks) == 2:
            out["truth_at_flanks"] = {**_worse(at_flanks), "branches": at_flanks}
    # a recording with a gap (samples lost on a loaded machine) splits into experiments: the longest
    exp = max((e for e in split_experiments(true_rec) if e.axis in (None, "x")), key=lambda e: e.t_s.size)
    try:
        lin = experiment_linearity(exp)
    except PiezodError as exc:
        out["truth_whole_lines_error"] = str(exc)
        return out
    per = {
        k: {"nonlinearity_pct": b.nonlinearity_pct, "length_error_pct": b.length_error_pct}
        for k, b in (("trace", lin.trace), ("retrace", lin.retrace))
    }
    out["truth_whole_lines"] = {**_worse(per), "branches": per}
    return out


def _fit_here(
    paths: list[Path], pitch_um: float, base: ScannerConfig
) -> tuple[ScannerConfig, dict[str, Any]]:
    """Flanks, the fits, the choice of model by held-out images and the calibrated config (in the
    worker process: results are plain data)."""
    from piezod import calibrate_family as cf
    from piezod.extensions import Adoption, extended_config
    from piezod.model.family import REALTIME_CREEP_DRIVERS, CreepSpectrum, FamilyParams

    _, events, th, session = frame_flank_session(paths, pitch_um, base)
    dyn = fit_dynamic(session)
    # flanks the first fit misses by far (dust, a misread edge) are dropped, then everything refitted
    dp = dyn.params
    spectrum = CreepSpectrum(tuple(map(float, dp.taus_s)), tuple(map(float, dp.weights)))
    dropped = 0
    for _ in range(2):
        session, n = drop_outlier_flanks(
            session, cf.session_positions(session, FamilyParams(dp.hysteresis, spectrum)), sigmas=4.0
        )
        if not n:
            break
        dropped += n
        dyn = fit_dynamic(session)
        dp = dyn.params
        spectrum = CreepSpectrum(tuple(map(float, dp.taus_s)), tuple(map(float, dp.weights)))
    inputs = [str(p) for p in paths]
    thesis_cfg = thesis_config(th.result, axis="x", base=base, inputs=inputs)
    calibrated = dynamic_config(dyn, axis="x", base=thesis_cfg, inputs=inputs)
    # the model family (piezod.calibrate_family), the dynamic model beside it: the one that predicts
    # the held-out scans' images best is adopted
    dp = dyn.params
    spectrum = CreepSpectrum(tuple(map(float, dp.taus_s)), tuple(map(float, dp.weights)))
    choice = cf.choose_model(
        session,
        others={"dynamic": FamilyParams(dp.hysteresis, spectrum)},
        alpha_per_v=dp.alpha_per_v,
        adoptable_drivers=REALTIME_CREEP_DRIVERS,
    )
    polarity = search_polarity(
        session, choice, alpha_per_v=dp.alpha_per_v, adoptable_drivers=REALTIME_CREEP_DRIVERS
    )
    saturation = search_saturation(
        session_through_polarity(session, polarity.pct),
        polarity.choice,
        alpha_per_v=dp.alpha_per_v,
        adoptable_drivers=REALTIME_CREEP_DRIVERS,
    )
    choice = saturation.choice
    cal_ax = calibrated.axes["x"]
    if choice.fit is not None:
        section = cf.family_model_config(choice.fit.params)
        cal_ax = cal_ax.model_copy(update={"model": "family", "family": section})
    else:
        cal_ax = cal_ax.model_copy(update={"model": "dynamic"})
    calibrated = calibrated.model_copy(
        update={"microscope": base.microscope, "axes": {**calibrated.axes, "x": cal_ax}}
    )
    parts: dict[str, dict[str, float]] = {}
    if polarity.pct != 0.0:
        parts["polarity"] = {"negative_sensitivity_pct": polarity.pct}
    if np.isfinite(saturation.x_sat_um):
        parts["saturation"] = {"x_sat_um": saturation.x_sat_um}
    if parts:
        calibrated = extended_config(calibrated, "x", Adoption(parts))
    summary = {
        "flanks": sum(len(e) for e in events),
        "flanks_dropped": dropped,
        "line_width_um": th.line_width_um,
        "thesis": {"params": dataclasses.asdict(th.result.params), "fit_error_pct": th.result.fit_error_pct},
        "dynamic": {"params": dataclasses.asdict(dyn.params), "fit_error_pct": dyn.fit_error_pct},
        "choice": {
            "chosen": choice.chosen,
            "model": cal_ax.model,
            "held_out_scans": [session.experiments[i].label for i in choice.holdout],
            "heldout_rms_um": choice.heldout_rms_um,
            "train_rms_um": choice.train_rms_um,
            "table": choice.table(),
        },
        "polarity": {
            "negative_sensitivity_pct": polarity.pct,
            "heldout_rms_um": list(polarity.heldout_rms_um),
            "notes": list(polarity.notes),
        },
        "saturation": {
            "x_sat_um": saturation.x_sat_um if np.isfinite(saturation.x_sat_um) else None,
            "heldout_rms_um": list(saturation.heldout_rms_um),
            "notes": list(saturation.notes),
        },
    }
    return calibrated, summary


def _scan_with_retry(engine: Any, scans: list[Any], out_dir: Path, say: Any, **kw: Any) -> list[Path]:
    """Scan each image; one ended by a fault (an underrun or a lost link on a loaded machine: the
    board ramped to safe) is repeated, at most twice, after clearing the fault; one the safety
    check refuses (voltages beyond the limits) is not. The repeat is a new
    measurement under a new name (the faulted recording is kept, never overwritten)."""
    paths = []
    for sc in scans:
        for attempt in range(3):
            if engine.status().state in ("fault", "disconnected"):
                print("  clearing a latched fault", file=say)
                engine.wait_healthy(timeout_s=15.0)
                engine.stop()
            try:
                paths += run_image_scans(engine, [sc], out_dir, **kw)
                break
            except SafetyError:
                raise  # the scan's check refused it: the same scan would be refused again
            except PiezodError as exc:
                if attempt == 2:
                    raise
                print(f"  {exc}; repeating the scan", file=say)
    return paths


def _recheck(
    engine: Any,
    worker: ProcessPoolExecutor,
    frame: list[Any],
    paths: list[Path],
    out_dir: Path,
    pitch_um: float,
    calibrated: ScannerConfig,
    say: Any,
) -> tuple[ScannerConfig, dict[str, Any]]:
    """Repeat one frame scan, uncorrected, after the fits; a material change of the sensitivity
    becomes the thermal part of the calibrated config (:class:`piezod.imagecal.SensitivityRecheck`).
    Without a sensor nothing else sees a scanner that warms between the frame and the scans."""
    from piezod.extensions import Adoption, extended_config

    sc = recheck_scan(frame)
    first = paths[frame.index(sc)]
    wait = RECHECK_MIN_INTERVAL_S - (time.time() - recording_span_unix_s(first)[1])
    if wait > 0:
        print(f"  the re-check waits {wait:.0f} s (a trend needs time to show)", file=say)
        time.sleep(wait)
    repeat = _scan_with_retry(engine, [sc], out_dir, say)[0]
    rc = worker.submit(sensitivity_recheck, paths, first, repeat, pitch_um).result()
    print(rc.note(), file=say)
    summary: dict[str, Any] = {
        **dataclasses.asdict(rc),
        "rate_pct_per_hour": rc.rate_pct_per_hour,
        "recording": str(repeat),
    }
    thermal = rc.thermal()
    if thermal is not None:
        calibrated = extended_config(calibrated, "x", Adoption({"thermal": thermal}))
    return calibrated, summary


def run_from_images(args: argparse.Namespace) -> int:
    """Run the sensorless calibration on the stage."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not args.out:
        raise CalibrationError("--out F.yaml is required: where the calibrated scanner config goes")
    if args.pitch_um is None or not args.pitch_um > 0:
        raise CalibrationError("--from-images needs --pitch-um P > 0 (the reference's certified pitch)")
    if args.recordings:
        raise CalibrationError("--from-images records its own frame: give no recordings")
    config_path = scanner_config_path(args)
    out = Path(args.out)
    recdir = Path(args.recordings_dir) if args.recordings_dir else out.parent / f"{out.stem}-recordings"
    recdir.mkdir(parents=True, exist_ok=True)
    truth: Path | None = None
    if args.sim:
        args.sample = args.sample or "line-3um"
        args.no_position_sensor = True
        truth = recdir / "truth.f64"
        truth.unlink(missing_ok=True)
        args.truth_log = str(truth)
    base = with_microscope(args, load_config(config_path))
    if base.microscope is None:
        base = base.model_copy(update={"microscope": MicroscopeSection(position_sensor=False)})
    reduced = args.frame == "reduced"
    frame = default_image_frame(reduced=reduced)
    say = human_stream(args)
    print(
        f"image calibration frame: {len(frame)} uncorrected scans of the {args.pitch_um:g} um reference, "
        f"ranges {sorted({s.range_um for s in frame})} um, "
        f"rates {sorted({s.line_rate_hz for s in frame})} Hz, "
        f"offsets {sorted({s.offset_um for s in frame})} um",
        file=say,
    )
    t0 = time.monotonic()
    report: dict[str, Any] = {"pitch_um": args.pitch_um}
    ctx = multiprocessing.get_context("spawn")
    with board_url(args, config_path) as url, ProcessPoolExecutor(max_workers=1, mp_context=ctx) as worker:
        from piezod.link.session import LinkSettings
        from piezod.service.engine import Engine

        # the simulator is a Python process on a possibly busy machine: allow it longer silences
        settings = LinkSettings.from_config(base, silence_timeout_s=5.0) if args.sim else None
        engine = Engine(base, url, recording_dir=recdir, settings=settings)
        engine.open()
        try:
            paths = _scan_with_retry(
                engine, frame, recdir / "frame", say, progress=lambda n: print(f"  scan {n}", file=say)
            )
            calibrated, summary = worker.submit(_fit_here, paths, args.pitch_um, base).result()
            n_flanks = int(summary["flanks"])
            print(f"flanks: {n_flanks} in {len(paths)} scans", file=say)
            print(
                f"thesis model (3.8) from images: worst fit error {summary['thesis']['fit_error_pct']:.3f} %",
                file=say,
            )
            print(
                f"dynamic model from images: worst fit error {summary['dynamic']['fit_error_pct']:.3f} %",
                file=say,
            )
            print("model chosen by held-out images (flank positions):", file=say)
            print(summary["choice"]["table"], file=say)
            for note in (*summary["polarity"]["notes"], *summary["saturation"]["notes"]):
                print(note, file=say)
            if not args.no_recheck:
                try:
                    calibrated, summary["recheck"] = _recheck(
                        engine, worker, frame, paths, recdir / "recheck", args.pitch_um, calibrated, say
                    )
                except PiezodError as exc:
                    # the fitted model is kept: a re-check that cannot be made adopts nothing
                    print(f"sensitivity re-check failed, no trend adopted: {exc}", file=say)
                    summary["recheck"] = {"error": str(exc)}
            dump_config(
                calibrated,
                out,
                header=(
                    f"calibrated without a position sensor by piezod calibrate --from-images "
                    f"(pitch {args.pitch_um:g} um, {len(frame)} image pairs, {n_flanks} flanks)"
                ),
            )
            print(f"-> {out}", file=say)
            report.update(summary)
            rows: list[dict[str, Any]] = []
            if not args.no_verify:
                scans = verification_scans(reduced=reduced)
                chosen_model = calibrated.axes["x"].model
                for model in dict.fromkeys(("thesis", chosen_model)):
                    # the thesis row is the baseline as fitted: without the parts found for the chosen model
                    update: dict[str, Any] = {"model": model}
                    if model != chosen_model:
                        update["extensions"] = None
                    engine.set_axis_model("x", calibrated.axes["x"].model_copy(update=update))
                    _scan_with_retry(engine, scans[:1], recdir / f"warmup-{model}", say, correction=True)
                    vpaths: list[Path | None] = []
                    for sc in scans:
                        try:
                            vpaths += _scan_with_retry(
                                engine,
                                [sc],
                                recdir / f"verify-{model}",
                                say,
                                correction=True,
                                progress=lambda n, m=model: print(f"  verify {m}: {n}", file=say),
                            )
                        except PiezodError as exc:
                            print(f"  verification scan {sc.name()} failed: {exc}", file=say)
                            vpaths.append(None)
                    engine.wait_recorded()
                    for sc, vp in zip(scans, vpaths, strict=True):
                        row: dict[str, Any] = {
                            "model": model,
                            "range_um": sc.range_um,
                            "line_rate_hz": sc.line_rate_hz,
                            "offset_um": sc.offset_um,
                            "frame": "inside" if sc.where == "inside" else "outside",
                            "what": sc.where,
                            "recording": str(vp) if vp is not None else None,
                        }
                        if vp is None:
                            row["error"] = "the scan failed"
                        else:
                            row.update(
                                worker.submit(
                                    _verify_here, vp, args.pitch_um, truth, base.sample_rate_hz
                                ).result()
                            )
                        rows.append(row)
                print(format_rows(rows), file=say)
                report["verification"] = rows
        finally:
            engine.close()
    report["seconds"] = time.monotonic() - t0
    write_json(args.json, report)
    return 0


def format_rows(rows: list[dict[str, Any]]) -> str:
    """The verification table: image metrics beside the hidden truth.

    Each figure is the worse of trace and retrace. ``truth`` is the true position over the image
    metric's windows by the same regression (what the image measures); ``truth whole`` the sensor
    path over the whole lines (the ends no flank covers included); ``truth@flanks`` the true
    position taken at the image's flanks only, linear between them, regressed alike (what a
    perfect flank metric would read: its distance from ``truth`` is structure finer than the flank
    spacing); ``+-`` the image's standard uncertainty from the flank-position noise.
    """
    head = (
        f"{'model':<8} {'range um':>8} {'f Hz':>6} {'off um':>6} {'frame':>7}  "
        f"{'image nonlin %':>14} {'image len %':>16}  {'truth nonlin %':>14} {'truth len %':>11}  "
        f"{'truth@flanks len %':>18}  {'truth whole len %':>17}  what"
    )
    lines = [head]
    for r in rows:
        im = r.get("image", {})
        tr = r.get("truth", {})
        tw = r.get("truth_whole_lines", {})
        tf = r.get("truth_at_flanks", {})

        def f(d: dict[str, float], k: str, fmt: str) -> str:
            v = d.get(k)
            return format(v, fmt) if v is not None and np.isfinite(v) else "-"

        le = f(im, "length_error_pct", "+.3f")
        unc = im.get("length_error_unc_pct")
        if le != "-" and unc is not None and np.isfinite(unc):
            le += f" +-{unc:.3f}"
        lines.append(
            f"{r['model']:<8} {r['range_um']:8.4g} {r['line_rate_hz']:6.3g} {r['offset_um']:6.3g} "
            f"{r['frame']:>7}  "
            f"{f(im, 'nonlinearity_pct', '14.3f')} {le:>16}  "
            f"{f(tr, 'nonlinearity_pct', '14.3f')} {f(tr, 'length_error_pct', '+11.3f')}  "
            f"{f(tf, 'length_error_pct', '+18.3f')}  {f(tw, 'length_error_pct', '+17.3f')}  {r['what']}"
        )
    return "\n".join(lines)


__all__ = ["format_rows", "run_from_images"]
