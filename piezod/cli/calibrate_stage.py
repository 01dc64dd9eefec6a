"""``piezod calibrate (--sim | --port URL) --config F --out F.yaml``: the calibration button."""

from __future__ import annotations

import argparse
import logging
import math
import time
from pathlib import Path
from typing import Any

from piezod.cli._common import board_url, fresh_dir, human_stream, scanner_config_path, write_json
from piezod.config import AxisName, dump_config, load_config, with_recorded_utc
from piezod.errors import CalibrationError, ModelError, PiezodError
from piezod.progress import progress_bar
from piezod.service.engine import Engine
from piezod.stagecal import (
    AnalysisWorker,
    Frame,
    default_frame,
    format_table,
    frame_summary,
    plot_verification,
    refresh_blocker,
    run_frame,
    run_placement,
    summary,
    tied_to_one_sensor,
    tracker_far_off_note,
    tracker_note,
    verification_points,
    verify,
    with_tracking_bound,
    without_extensions,
    wrong_model_warning,
)


def run_on_stage(args: argparse.Namespace) -> int:
    """Record the frame on the stage, fit, write the YAML, verify inside and outside the frame."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not args.out:
        raise CalibrationError("--out F.yaml is required: where the calibrated scanner config goes")
    if args.recordings:
        raise CalibrationError("give recordings (offline fit) or --sim/--port (on the stage), not both")
    config_path = scanner_config_path(args, first_guess=True)
    base = load_config(config_path)
    axis: AxisName = args.axis or "x"
    reduced = args.frame == "reduced"
    frame = default_frame(base, axis, reduced=reduced)
    out = Path(args.out)
    if args.recordings_dir:
        recdir = Path(args.recordings_dir)
        recdir.mkdir(parents=True, exist_ok=True)
    else:
        recdir = fresh_dir(out.parent / f"{out.stem}-recordings")
    say = human_stream(args)
    base, old_parts = without_extensions(base, axis)
    if old_parts:
        print(
            f"the config's extensions on {axis} ({', '.join(old_parts)}) are measured again, not kept",
            file=say,
        )
    print(f"calibration frame: {frame_summary(frame)}", file=say)
    t_start = time.monotonic()
    report: dict[str, Any] = {}
    # where the run's time goes (a lab waits for it; the stage may drift meanwhile)
    phases: dict[str, float] = {}
    last = [t_start]

    def took(phase: str) -> str:
        now = time.monotonic()
        phases[phase] = round(now - last[0], 1)
        last[0] = now
        return f"{phases[phase]:.0f} s"

    with board_url(args, config_path) as url, AnalysisWorker() as worker:
        from piezod.link.session import LinkSettings

        # --sim: the board is a Python process on the same, possibly overloaded machine; at load 14
        # it once sent nothing for over 1 s (the hardware silence limit) in the 314 s frame and the
        # link dropped mid-frame. The same allowance as `calibrate --from-images --sim`.
        settings = LinkSettings.from_config(base, silence_timeout_s=5.0) if args.sim else None
        engine = Engine(base, url, recording_dir=recdir, settings=settings)
        engine.open()
        try:
            if not engine.position_sensor:
                raise CalibrationError(
                    "the board (or the scanner config's microscope section) has no position sensor: "
                    "calibrate from images of a reference instead (--from-images --pitch-um P)"
                )
            frame_path, frame_mid_unix_s = _play_frame(
                engine, frame, recdir / "frame.csv", "calibration frame"
            )
            took("frame")
            # a scan that drove the stage beyond the sensor's range has no positions there: the fits
            # and the verification's placement use the scans within it (the recording is kept whole)
            full_scale = engine.settings.full_scale_um(axis)
            recorded_path = frame_path
            frame_path, frame, clipped = worker.frame_in_sensor_range(
                recorded_path, frame, full_scale, recdir / "frame-in-sensor-range.csv"
            )
            if clipped:
                print(
                    f"WARNING: the readback reached the sensor's full scale (+-{full_scale:g} um) in "
                    f"{len(clipped)} scans ({', '.join(clipped)}): left out of the fits and the "
                    f"verification's placement; if the sensor reads further, set "
                    f"axes.{axis}.sensor_full_scale_um to its range",
                    file=say,
                )
            placement_path: Path | None = None
            if not (getattr(args, "no_audit", False) or getattr(args, "no_lag_placement", False)):
                placement_path = run_placement(engine, base, axis, recdir / "lag-placement.csv", frame)
                print(f"lag placement experiment recorded ({took('lag_placement')})", file=say)
            # the recording whose end is where the stage is left for the verification
            start_path = placement_path or recorded_path
            rest_v = base.axes[axis].safe_voltage_v
            fitted = worker.fit_thesis(frame_path, base, axis)
            print(
                f"thesis model (3.8) fitted: worst fit error {fitted.fit_error_pct:.3f} % "
                f"({took('thesis_fit')})",
                file=say,
            )
            dynamic = worker.fit_dynamic(
                frame_path,
                fitted.config,
                axis,
                ramp_v_per_s=base.service.ramp_rate_v_per_s,
                rest_voltage_v=rest_v,
            )
            print(
                f"dynamic model fitted: worst fit error {dynamic.fit_error_pct:.3f} % "
                f"({took('dynamic_fit')})",
                file=say,
            )
            choice = worker.choose_model(
                frame_path,
                dynamic.config,
                axis,
                ramp_v_per_s=base.service.ramp_rate_v_per_s,
                rest_voltage_v=rest_v,
            )
            chosen = str(choice.report["chosen"])
            print(
                f"model choice by held-out experiments of the frame ({took('model_choice')}):\n"
                f"{choice.report['table']}",
                file=say,
            )
            calibrated = choice.config
            audit_report: dict[str, Any] | None = None
            extra = ""
            audited = None
            if not getattr(args, "no_audit", False):
                try:
                    audited = worker.audit_and_extend(
                        frame_path,
                        choice,
                        dynamic.config,
                        axis,
                        ramp_v_per_s=base.service.ramp_rate_v_per_s,
                        rest_voltage_v=rest_v,
                        placement_path=placement_path,
                        rate_hz=engine.rate_hz,
                    )
                except (ModelError, CalibrationError) as exc:
                    # the frame's model choice stands on its own; a step after it that fails
                    # must not throw the recorded frame and its fits away
                    print(
                        f"WARNING: the audit step failed ({took('audit')}): {exc}; the chosen model "
                        "is written without the audit's parts",
                        file=say,
                    )
                    audit_report = {"error": str(exc)}
            if audited is not None:
                found = ", ".join(audited.report["findings"]) or "none"
                if audited.report.get("withheld"):
                    found += (
                        f"; withheld on its undetermined baseline, tried on the chosen model: "
                        f"{', '.join(audited.report['withheld'])}"
                    )
                print(
                    f"audit of the frame: findings {found} ({took('audit')})\n{audited.report['text']}",
                    file=say,
                )
                calibrated = audited.config
                audit_report = audited.report
                if audited.report["adopted"]:
                    names = ", ".join(a.split(":")[0] for a in audited.report["adopted"])
                    extra = f"; the audit's findings adopted as runtime parts: {names}"
            # the choice the written member comes from (the audit's redone choice when it adopted)
            final_choice = (audit_report or {}).get("model_choice", choice.report)
            faults_while_fitting: list[str] = []

            def acknowledged(when: str) -> None:
                if engine.status().state in ("fault", "disconnected"):
                    # the frame is recorded; a fault while the stage only held during the fits (an
                    # underrun on a loaded machine) does not spoil it: say so, acknowledge, go on
                    faults = [f"{f.source}/{f.code}: {f.message}" for f in engine.acknowledge_fault()]
                    print(f"faults while the stage held {when} (acknowledged): {'; '.join(faults)}", file=say)
                    faults_while_fitting.extend(faults)

            after_s = getattr(args, "refresh_after", None)
            if getattr(args, "no_refresh", False) or after_s is None:
                after_s = math.inf
            refresh: dict[str, Any] = {"after_s": after_s if math.isfinite(after_s) else None}
            age_s = time.time() - frame_mid_unix_s
            if age_s > after_s:
                chosen_now = str(final_choice.get("chosen", ""))
                refresh["age_s"] = round(age_s, 1)
                why_not = refresh_blocker(calibrated, axis, chosen_now)
                if why_not is not None:
                    refresh["skipped"] = why_not
                    print(f"the frame is {age_s:.0f} s old; not played again: {why_not}", file=say)
                else:
                    acknowledged("during the fits")
                    print(
                        f"the frame is {age_s:.0f} s old (the stage may have drifted while the fits ran): "
                        f"played again to refit {chosen_now} on it",
                        file=say,
                    )
                    try:
                        again, again_mid_unix_s = _play_frame(
                            engine, frame, recdir / "frame-again.csv", "frame again"
                        )
                        refresh["recording"] = str(again)
                        again_fitted, _, _ = worker.frame_in_sensor_range(
                            again, frame, full_scale, recdir / "frame-again-in-sensor-range.csv"
                        )
                        got = worker.refresh(
                            again_fitted,
                            calibrated,
                            axis,
                            chosen_now,
                            # the stage's creep still relaxes from the first frame: the model runs
                            # through it (and the lag placement) on the daemon's clock
                            history=[p for p in (recorded_path, placement_path) if p is not None],
                            ramp_v_per_s=base.service.ramp_rate_v_per_s,
                            rest_voltage_v=rest_v,
                            one_sensor=tied_to_one_sensor(final_choice),
                        )
                    except PiezodError as exc:
                        # the first frame's model stands (a fault while the frame played again, a
                        # failed fit); what was recorded is kept for a look
                        refresh["error"] = str(exc)
                        print(
                            f"WARNING: the refit on the frame played again failed ({took('refresh')}): "
                            f"{exc}; the model fitted on the first frame is written",
                            file=say,
                        )
                    else:
                        # the verification starts where the frame played again left the stage
                        start_path = again
                        refresh["heldout_rms_um"] = got.heldout_rms_um
                        refresh["kept_rms_um"] = got.kept_rms_um
                        refresh["adopted"] = got.better
                        first_nm = (audited or choice).fit_error_pct * 1e3
                        compared = (
                            f"{got.heldout_rms_um * 1e3:.2f} nm held out on it, the first frame's member "
                            f"{got.kept_rms_um * 1e3:.2f} nm on the same scans (on its own frame "
                            f"{first_nm:.2f} nm)"
                        )
                        if got.better:
                            # the model fitted on the first frame is kept beside the recordings
                            first_yaml = recdir / "first-frame.yaml"
                            dump_config(
                                with_recorded_utc(with_tracking_bound(calibrated, frame), frame_mid_unix_s),
                                first_yaml,
                                header="fitted on the first frame, before the frame was played again",
                            )
                            refresh["first_frame_config"] = str(first_yaml)
                            calibrated, frame_mid_unix_s = got.config, again_mid_unix_s
                            extra += f"; the member refitted on the frame played again {age_s:.0f} s later"
                            print(
                                f"{chosen_now} refitted on the frame played again: {compared} "
                                f"({took('refresh')})",
                                file=say,
                            )
                        else:
                            extra += (
                                f"; kept over its refit on the frame played again {age_s:.0f} s later "
                                "(which predicted that frame no better)"
                            )
                            print(
                                f"{chosen_now} refitted on the frame played again: {compared}; "
                                f"the first frame's model is kept ({took('refresh')})",
                                file=say,
                            )
            calibrated = with_recorded_utc(with_tracking_bound(calibrated, frame), frame_mid_unix_s)
            dump_config(
                calibrated,
                out,
                header=(
                    f"calibrated on the stage by piezod calibrate ({frame_summary(frame)}); "
                    f"model: {calibrated.axes[axis].model} ({chosen}: best held-out prediction), "
                    "the thesis and dynamic parameters kept beside it" + extra
                ),
            )
            print(f"-> {out}", file=say)
            report = dict(fitted.report)
            report["dynamic"] = dynamic.report
            report["model_choice"] = choice.report
            if audit_report is not None:
                report["audit"] = audit_report
            report["frame"] = {"summary": frame_summary(frame), "recording": str(recorded_path)}
            if placement_path is not None:
                report["frame"]["lag_placement_recording"] = str(placement_path)
            if clipped:
                report["frame"]["clipped"] = {
                    "sensor_full_scale_um": full_scale,
                    "samples_by_scan": clipped,
                    "fitted_recording": str(frame_path),
                }
            report["refresh"] = refresh
            rows: list[dict[str, Any]] = []
            acknowledged("during the fits")
            if faults_while_fitting:
                report["faults_while_fitting"] = faults_while_fitting
            if not args.no_verify:
                # the run starts where the frame left the stage, in the sensor's coordinates (if the
                # stage still holds the frame's last voltage: a position read at another is not the state)
                v_end, x_end = worker.frame_end(start_path, axis)
                held = engine.status().voltage_v.get(axis)
                span_v = base.axes[axis].voltage_max_v - base.axes[axis].voltage_min_v

                def at_held(v: float) -> bool:
                    return held is not None and abs(held - v) <= 1e-3 * span_v

                holds = at_held(v_end)
                start = (v_end, x_end) if holds else None
                if not holds:
                    # a fault while the stage held ramped the outputs to the safe values: the run
                    # starts from the sensor's reading where the stage rests now, not from the
                    # fitted law's rest curve (unidentified: 10 um off on a unipolar stack)
                    now = engine.measured_at_rest(axis)
                    start = now if now is not None and at_held(now[0]) else None
                    report["verification_start"] = (
                        f"the stage left the frame's last voltage ({v_end:.4g} V): "
                        + (
                            f"from the sensor's reading now, {start[1]:.4g} um at {start[0]:.4g} V"
                            if start is not None
                            else "from rest at 0 V in the model's coordinates (no reading at rest)"
                        )
                    )
                    print(f"verification start: {report['verification_start']}", file=say)
                planned = verification_points(calibrated, frame, reduced=reduced, axis=axis, start=start)
                points = worker.check_points(calibrated, planned, axis, start)
                for pt in points:
                    if pt.note:
                        print(f"verification point '{pt.why}': {pt.note}", file=say)
                models = [calibrated.axes[axis].model] + (
                    ["dynamic"] if calibrated.axes[axis].model != "dynamic" else []
                )
                for k, model in enumerate(models):
                    engine.set_axis_model(
                        axis,
                        calibrated.axes[axis].model_copy(update={"model": model}),
                        position_um=start[1] if k == 0 and start is not None else None,
                        # the fits took a while: the stage's sensitivity may have drifted since the frame
                        data_age_s=time.time() - frame_mid_unix_s,
                    )
                    sensor = calibrated.axes[axis].sensor_path()
                    rows += verify(engine, points, recdir, model, worker, sensor=sensor)
                print(f"verification ({took('verification')}):\n{format_table(rows)}", file=say)
                if (note := tracker_note(rows, models[0])) is not None:
                    print(f"note: {note}", file=say)
                    report["tracker_note"] = note
                if (note := tracker_far_off_note(rows, models[0])) is not None:
                    print(f"note: {note}", file=say)
                    report["tracker_far_off_note"] = note
                if (warning := wrong_model_warning(rows, models[0])) is not None:
                    print(f"WARNING: {warning}", file=say)
                    report["verification_warning"] = warning
                report["verification"] = rows
                report["verification_summary"] = summary(rows)
                if args.plot:
                    plot_verification(rows, Path(args.plot))
                    print(f"plot: {args.plot}", file=say)
        finally:
            engine.close()
    report["seconds"] = time.monotonic() - t_start
    report["phase_seconds"] = phases
    write_json(args.json, report)
    return 0


def _play_frame(engine: Engine, frame: Frame, path: Path, what: str) -> tuple[Path, float]:
    """Play the frame from where the stage holds, recorded to ``path``, with a progress bar: the
    path and the Unix time of the frame's middle."""
    with progress_bar(desc=what, total=round(frame.duration_s, 1), unit="s") as bar:
        shown = [0.0]

        def tick(_: str, t: float) -> None:
            bar.update(round(t, 1) - shown[0])
            shown[0] = round(t, 1)

        t0 = time.time()
        played = run_frame(engine, frame, path, progress=tick)
    return played, 0.5 * (t0 + time.time())
