"""Calibrate-and-verify on a simulated stage, in process (deterministic, independent of machine load).

Usage::

    python tools/model_family_verify.py --stage pi-stage [--json out.json]
    python tools/model_family_verify.py --markdown out.json    # the docs tables of a saved run
    python tools/model_family_verify.py --stage pi-stage --offline   # calibrated from the frame's CSV

The same steps as ``piezod calibrate --sim --config configs/sim-NAME.yaml`` with the full frame,
but the stage (:class:`hil_sim.stage.Stage`, the preset's ``simulation:`` section) is stepped in
this process instead of behind the pty, so a loaded machine cannot spoil the run with underruns:

1. the frame of :func:`piezod.stagecal.default_frame` (uncorrected triangles: 5 ranges x 6 rates
   + offsets, settling loops unrecorded, ramps between scans at the service ramp rate);
2. the thesis fit, the dynamic fit, the family fit and the held-out choice
   (:func:`piezod.stagecal.choose_for_experiments`, the function ``piezod calibrate`` runs);
3. the verification points of :func:`piezod.stagecal.verification_points` (inside the frame;
   10x slower, 10x faster, offsets beyond it), each driven through
   :class:`piezod.service.axes.AxisDriver` with the chosen model and with the dynamic model
   in the daemon's blocks and under the axis's slew limit (one unrecorded warm-up loop, then 4
   recorded loops; the stage keeps its whole history),
   scored by :func:`piezod.linearity.experiment_linearity`.

The board's ADC is not modelled: the readback here is not clipped at the sensor's range, as the
simulated board behind the pty clips it at ``axes.<axis>.sensor_full_scale_um`` (default 100 um; a
stage that travels further reads differently over the pty, docs/model-family.md 6.2q).

``--offline`` replaces step 2 by what a lab with recordings does: the frame written to one CSV and
``piezod calibrate FRAME.csv --config STAGE`` (its held-out choice among (3.8) and the family,
docs/model-family.md 3.1) writes the config that is verified.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.stage import Stage, StageConfig, resolve_stage
from piezod import calibrate_dynamic as cd
from piezod.calibrate import calibrate, calibrated_config
from piezod.cli import main as cli_main
from piezod.config import AxisName, ScannerConfig, dump_config, load_config
from piezod.effects_bench import StageBench
from piezod.errors import RangeUnreachableError, SafetyError
from piezod.extensions import experiments_through_sensor
from piezod.lag_placement import PLACEMENT_LABEL, program_for
from piezod.linearity import experiment_linearity
from piezod.rate_id import adopt_fast_creep
from piezod.recording import Experiment, Recording, write_recording
from piezod.resonance_id import adopt_resonance
from piezod.service.axes import AxisDriver
from piezod.stagecal import (
    FRAME_END_SAMPLES,
    Frame,
    ThesisFit,
    audit_and_extend,
    check_points,
    choose_for_experiments,
    default_frame,
    placement_segments,
    verification_points,
    with_lag_placed,
)


def markdown(result: dict[str, Any]) -> str:
    """The model-choice and verification tables of a run (its ``--json`` output) as markdown."""
    rep = result["choice"]
    lines = ["| model | train RMS (nm) | held-out RMS (nm) |", "|---|---|---|"]
    for name, held in sorted(rep["heldout_rms_um"].items(), key=lambda kv: kv[1]):
        mark = " (chosen)" if name == rep["chosen"] else ""
        lines.append(f"| {name}{mark} | {1e3 * rep['train_rms_um'][name]:.2f} | {1e3 * held:.2f} |")
    lines += [
        "",
        "| model | point | range um | f Hz | offset um | nonlin % | length err % |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        why = r["why"] + (" (clamped: not the model's)" if r.get("clamped") else "")
        why += " (moved/shrunk to avoid clamping)" if r.get("placement", "").startswith("moved") else ""
        lines.append(
            f"| {r['model']} | {why} | {r['range_um']:.1f} | {r['frequency_hz']:g} |"
            f" {r['offset_um']:+.2f} | {r['nonlinearity_pct']:.3f} | {r['length_error_pct']:+.3f} |"
        )
    for key, s in result["summary"].items():
        lines.append(
            f"| **{key.split('/')[0]}** | **max {', '.join(key.split('/')[1:])}** | | | |"
            f" **{s['max_nonlinearity_pct']:.3f}** | **{s['max_abs_length_error_pct']:.3f}** |"
        )
    return "\n".join(lines)


def summary_table(paths: list[str]) -> str:
    """One markdown row per saved run: the chosen model, its held-out RMS, the worst figures."""
    lines = [
        "| stage | chosen | held-out RMS (nm) | inside: max nonlin. / max abs length err. (%)"
        " | outside: max abs length err. (%) |",
        "|---|---|---|---|---|",
    ]
    for p in paths:
        r = json.loads(Path(p).read_text())
        rep = r["choice"]
        kind = rep["chosen"].split("/")[0]
        inside, outside = r["summary"][f"{kind}/inside"], r["summary"][f"{kind}/outside"]
        lines.append(
            f"| `{Path(r['stage']).stem.removeprefix('sim-')}` | {rep['chosen']} |"
            f" {1e3 * rep['heldout_rms_um'][rep['chosen']]:.2f} |"
            f" {inside['max_nonlinearity_pct']:.3f} / {inside['max_abs_length_error_pct']:.3f} |"
            f" {outside['max_abs_length_error_pct']:.3f} |"
        )
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class PlayedFrame:
    """The default frame played on a preset's stage in this process, and what the calibration
    starts from (shared with ``tools/audit_step_cost.py``)."""

    path: Path
    base: ScannerConfig
    axis: AxisName
    bench: StageBench
    frame: Frame
    experiments: list[Experiment]
    ramp_v_per_s: float
    rest_voltage_v: float


def truth_config(cfg: StageConfig) -> StageConfig:
    """``cfg`` without what lies between the stage's position and its readback: the sensor's noise
    and a delay or lag placed at the sensor. Stepped beside the stage it gives where the stage is."""
    fx = cfg.effects
    if fx.delay is not None and fx.delay.at == "sensor":
        fx = fx.model_copy(update={"delay": None})
    return cfg.model_copy(update={"sensor_noise_nm_rms": 0.0, "effects": fx})


def play_default_frame(stage: str, axis: AxisName = "x", truth: bool = False) -> PlayedFrame:
    """:func:`piezod.stagecal.default_frame` played on the preset ``stage`` (name or YAML path);
    with ``truth`` the stage's true position is stepped beside it (:func:`truth_config`)."""
    path = resolve_stage(stage)
    if path is None:
        raise SystemExit(f"no stage {stage!r}")
    base = load_config(path)
    cfg = StageConfig.from_file(path)
    bench = StageBench(
        Stage(cfg, axes=(axis,)),
        base.sample_rate_hz,
        keep_history=False,
        truth=Stage(truth_config(cfg), axes=(axis,)) if truth else None,
    )
    ramp = base.service.ramp_rate_v_per_s
    frame = default_frame(base, axis)
    exps = bench.play_frame(frame, axis, ramp)
    return PlayedFrame(path, base, axis, bench, frame, exps, ramp, base.axes[axis].safe_voltage_v)


def start_config(played: PlayedFrame) -> ScannerConfig:
    """The thesis and dynamic fits on the frame: the config the model choice starts from."""
    exps, axis = played.experiments, played.axis
    thesis = calibrated_config(calibrate(exps), axis=axis, base=played.base)
    dyn = cd.calibrate_dynamic(
        exps, slew_rate_v_per_s=played.ramp_v_per_s, rest_voltage_v=played.rest_voltage_v
    )
    return cd.calibrated_config(dyn, axis=axis, base=thesis)


def _offline(exps: list[Experiment], stage_path: Path, axis: AxisName) -> ThesisFit:
    """The frame written as one recording and calibrated by ``piezod calibrate`` on it (offline)."""
    with tempfile.TemporaryDirectory() as tmp:
        rec, out, js = Path(tmp) / "frame.csv", Path(tmp) / "cal.yaml", Path(tmp) / "cal.json"
        write_recording(rec, Recording.of_experiments(exps))
        argv = ["calibrate", str(rec), "--config", str(stage_path), "--axis", axis]
        if cli_main([*argv, "--out", str(out), "--json", str(js)]) != 0:
            raise SystemExit("piezod calibrate failed on the frame")
        doc = json.loads(js.read_text())
        config = load_config(out)
    fam = doc.get("family", {})
    others = fam.get("others", {})
    held = {m["name"]: m["heldout_rms_um"] for m in fam.get("members", []) if m["heldout_rms_um"] is not None}
    train = {m["name"]: m["train_rms_um"] for m in fam.get("members", []) if m["heldout_rms_um"] is not None}
    held.update(others)
    train.update({k: float("nan") for k in others})
    chosen = doc.get("chosen") or next(iter(others), "thesis (3.8)")
    report = {"chosen": chosen, "heldout_rms_um": held, "train_rms_um": train, "offline": doc["model_reason"]}
    return ThesisFit(report, config, float(held.get(chosen, float("nan"))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", default="pi-stage", help="preset name or scanner YAML with simulation:")
    ap.add_argument("--json", default=None)
    ap.add_argument("--loops", type=int, default=4)
    ap.add_argument(
        "--audit",
        action="store_true",
        help="audit the frame and adopt its findings, as piezod calibrate does",
    )
    ap.add_argument("--skip-dynamic", action="store_true", help="verify the chosen model only")
    ap.add_argument(
        "--truth",
        action="store_true",
        help="also measure every verified scan on the stage's true position (no sensor noise, "
        "no sensor lag or delay), stepped beside it",
    )
    ap.add_argument(
        "--offline",
        action="store_true",
        help="calibrate as a lab does from recordings: the frame written to a CSV and the config from "
        "`piezod calibrate FRAME.csv --config STAGE --out F.yaml` (its held-out choice), then verified",
    )
    ap.add_argument(
        "--choice-only", action="store_true", help="stop after the held-out model choice (no verification)"
    )
    ap.add_argument(
        "--config-out", default=None, metavar="F.yaml", help="write the calibrated config (before verifying)"
    )
    ap.add_argument(
        "--verify",
        default=None,
        metavar="F.yaml",
        help="skip the calibration: verify this scanner config (e.g. an edited --config-out) after the frame",
    )
    ap.add_argument(
        "--lag-placement",
        action="store_true",
        help="with --verify: play the lag placement experiment after the frame and move as much of that "
        "config's sensor path to the drive as it places there, as piezod calibrate does (with --audit "
        "it is always played)",
    )
    ap.add_argument(
        "--member",
        default=None,
        metavar="NAME",
        help="with --verify --lag-placement: the family member the config holds (e.g. "
        "family/generalised-play/64-plays/voltage-creep, its calibration's `chosen`), refitted with the "
        "drive lag held where the experiment places it",
    )
    ap.add_argument(
        "--resonance",
        action="store_true",
        help="with --verify: fit the stage's resonance on the frame's residual of that config, as piezod "
        "calibrate does, and verify the config with it when adopted",
    )
    ap.add_argument(
        "--fast-creep",
        action="store_true",
        help="with --verify: fit the fast creep that config misses on the frame's harmonics (after "
        "--resonance), as piezod calibrate does, and verify the config with it when adopted",
    )
    ap.add_argument(
        "--redo-dynamics",
        action="store_true",
        help="with --verify: drop that config's resonance and fast creep and identify both again "
        "(--resonance --fast-creep) on this code, e.g. on a written YAML to compare two versions",
    )
    ap.add_argument(
        "--hold-s",
        type=float,
        default=0.0,
        metavar="S",
        help="hold the frame's last voltage this long before verifying, as the stage does over the pty "
        "while piezod calibrate fits (an hour on a 2-core machine)",
    )
    ap.add_argument(
        "--hold-v",
        type=float,
        default=None,
        metavar="V",
        help="with --hold-s: ramp to this voltage and hold it (default: the frame's last); the "
        "verification then starts from the sensor's reading there (--start now)",
    )
    ap.add_argument(
        "--start",
        choices=("frame-end", "now"),
        default="frame-end",
        help="the position the verification adopts: the frame's last reading (as piezod calibrate "
        "does) or the sensor's reading after --hold-s",
    )
    ap.add_argument(
        "--markdown", default=None, metavar="F.json", help="print the tables of a saved --json run"
    )
    ap.add_argument(
        "--summary", nargs="+", default=None, metavar="F.json", help="one row per saved --json run"
    )
    args = ap.parse_args()
    if args.summary:
        print(summary_table(args.summary))
        return 0
    if args.markdown:
        print(markdown(json.loads(Path(args.markdown).read_text())))
        return 0
    t0 = time.perf_counter()
    played = play_default_frame(args.stage, truth=args.truth)
    path, base, axis = played.path, played.base, played.axis
    bench, frame, exps = played.bench, played.frame, played.experiments
    rate, ramp, rest = base.sample_rate_hz, played.ramp_v_per_s, played.rest_voltage_v
    # where the frame left the stage: its last voltage and readback (noise averaged, as frame_end)
    last_x = float(np.mean(exps[-1].position_um[-FRAME_END_SAMPLES:]))
    print(f"frame: {len(exps)} experiments, {bench.t:.0f} s simulated")
    placement = None
    if args.lag_placement or (args.audit and not (args.offline or args.verify)):
        # as piezod calibrate plays it after the frame (each segment ramped to, as the daemon does):
        # the experiment, then the frame's last scans again
        segments, _ = placement_segments(base, axis, rate, frame)
        for seg in segments:
            seg_v = np.asarray(seg.volts, dtype=np.float64)
            bench.ramp(float(seg_v[0]), ramp)
            t, x = bench.play(seg_v)
            if seg.label == PLACEMENT_LABEL:
                placement = (Experiment(PLACEMENT_LABEL, axis, t, seg_v, x), program_for(base, axis, rate))
        last_x = float(np.mean(x[-FRAME_END_SAMPLES:]))
    if args.verify or args.offline:
        choice = (
            ThesisFit({"chosen": f"given: {args.verify}"}, load_config(args.verify), float("nan"))
            if args.verify
            else _offline(exps, path, axis)
        )
        args.skip_dynamic = args.skip_dynamic or choice.config.axes[axis].dynamic is None
    else:
        with_dyn = start_config(played)
        choice = choose_for_experiments(exps, axis, with_dyn, ramp, rest)
        print(choice.report["table"])
    if args.audit and not (args.offline or args.verify):
        # as piezod calibrate does by default: the frame audited, the findings with a runtime part
        # adopted when the extended model predicts the held-out experiments better
        audited = audit_and_extend(exps, axis, choice, with_dyn, ramp, rest, placement=placement)
        print(f"audit of the frame: findings {', '.join(audited.report['findings']) or 'none'}")
        print(audited.report["text"])
        choice = dataclasses.replace(audited, report={**choice.report, "audit": audited.report})
    if args.choice_only:
        if args.json:
            Path(args.json).write_text(json.dumps({"stage": str(path), "choice": choice.report}, indent=2))
        return 0
    calibrated = choice.config
    if args.hold_s > 0:
        if args.hold_v is not None:
            bench.ramp(args.hold_v, ramp)
            args.start = "now"
        chunk = int(60 * rate)
        for k in range(0, round(args.hold_s * rate), chunk):
            _, x = bench.play(np.full(min(chunk, round(args.hold_s * rate) - k), bench.v))
        now_x = float(np.mean(x[-FRAME_END_SAMPLES:]))
        print(f"held {bench.v:.4g} V for {args.hold_s:.0f} s: the reading moved {now_x - last_x:+.4f} um")
        if args.start == "now":
            last_x = now_x
    if args.verify and placement is not None:
        named = {**choice.report, "model_choice": {"chosen": args.member}} if args.member else choice.report
        placed = with_lag_placed(placement, axis, dataclasses.replace(choice, report=named), exps, ramp, rest)
        calibrated = placed.config
        print("\n".join(placed.report.get("adopted", []) + placed.report.get("skipped", [])))
    if args.redo_dynamics:
        kept = {k: v for k, v in (calibrated.axes[axis].extensions or {}).items() if k != "resonance"}
        calibrated = calibrated.with_axis(axis, extensions=kept or None, fast_creep=None)
        args.resonance = args.fast_creep = True
    if args.resonance:
        calibrated, found = adopt_resonance(exps, axis, calibrated)
        print(found.note if found is not None else "resonance: the frame cannot resolve one")
    if args.fast_creep:
        calibrated, fast = adopt_fast_creep(exps, axis, calibrated)
        print(fast.note if fast is not None else "fast creep: the frame cannot measure it")
    if args.config_out:
        dump_config(calibrated, args.config_out, header=f"calibrated in process on {path}")
    chosen_kind = calibrated.axes[axis].model
    rows: list[dict[str, Any]] = []
    # placed, then checked with the verified model's own inverse over each whole scan (as piezod
    # calibrate does): a point that would clamp is moved or shrunk, and says so
    start = (bench.v, last_x)
    planned = verification_points(calibrated, frame, axis=axis, start=start)
    points = check_points(calibrated, planned, axis=axis, start_v=start[0], start_um=start[1])
    for pt in points:
        if pt.note:
            print(f"verification point '{pt.why}': {pt.note}")
    # the daemon's block: the slew limit spreads a step only inside one block
    block = calibrated.service.block_samples(rate)
    kinds = [chosen_kind] + (["dynamic"] if chosen_kind != "dynamic" and not args.skip_dynamic else [])
    for kind in kinds:
        # the amplifier's slew limit as the daemon applies it: a fast point's turning points may
        # ask for more (docs/model-family.md 6.2w)
        cfg = calibrated.axes[axis].model_copy(update={"model": kind})
        driver = AxisDriver(axis, cfg, rate)
        # scored where the stage is, as piezod calibrate scores it: a readback lag the model puts
        # in the sensor path is not a position error
        sensor = cfg.sensor_path()
        # as the daemon switches a model in: from the stage's voltage and position (here the sensor's
        # last reading), not from a rest state at that voltage (one the frame never visits)
        driver.adopt(bench.v, last_x)
        # as piezod calibrate's verification: one unrecorded warm-up scan at the first point
        # after a model is switched in (its creep memory starts from rest, the stage's does not)
        for k, pt in enumerate([points[0], *points]):
            warm_up = k == 0
            try:
                plan = driver.plan(pt.range_um, pt.frequency_hz, pt.offset_um)
            except (SafetyError, RangeUnreachableError) as exc:
                print(f"{kind:<8} {pt.why}: refused by the scan planner ({exc}): no figures")
                continue
            driver.use_plan(plan)
            lo = pt.offset_um - 0.5 * pt.range_um
            per = max(8, round(rate / pt.frequency_hz))
            n_move = max(
                1, round(abs(lo - driver.position_um) / (0.5 * pt.range_um * pt.frequency_hz) * rate)
            )
            move = np.linspace(driver.position_um, lo, n_move + 1)[1:]
            phase = (np.arange(1, per * (1 + args.loops) + 1) % per) / per
            scan = lo + pt.range_um * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
            target = np.concatenate([move, scan])
            volts = []
            faults = slewed = 0
            for i in range(0, target.size, block):
                ahead = target[i + block : i + block + driver.lookahead]
                out = driver.corrected(target[i : i + block], ahead)
                faults += out.clamped
                slewed += out.slew_limited
                volts.append(out.voltage_v)
            v = np.concatenate(volts)
            t, x = bench.play(v)
            if warm_up:
                continue
            k0 = n_move + per
            exp = Experiment("verify", axis, t[k0:], v[k0:], x[k0:], target_um=target[k0:])
            if not sensor.identity:
                exp = experiments_through_sensor([exp], sensor)[0]
            lin = experiment_linearity(exp)
            true_lin = None
            if bench.truth is not None and bench.last_truth is not None:
                true_exp = Experiment("verify", axis, t[k0:], v[k0:], bench.last_truth[k0:])
                true_lin = experiment_linearity(dataclasses.replace(true_exp, target_um=target[k0:]))
            rows.append(
                {
                    "model": kind,
                    "why": pt.why,
                    "inside_frame": pt.inside_frame,
                    "range_um": pt.range_um,
                    "frequency_hz": pt.frequency_hz,
                    "offset_um": pt.offset_um,
                    "nonlinearity_pct": float(lin.nonlinearity_pct),
                    "length_error_pct": float(lin.length_error_pct),
                    "pixel_nonlinearity_pct": float(lin.pixel_nonlinearity_pct),
                    "pixel_noise_pct": float(lin.pixel_noise_pct),
                    "clamped": faults,
                    "slew_limited": slewed,
                    "placement": pt.note,
                }
            )
            if true_lin is not None:
                rows[-1]["true_nonlinearity_pct"] = float(true_lin.nonlinearity_pct)
                rows[-1]["true_length_error_pct"] = float(true_lin.length_error_pct)
            r = rows[-1]
            print(
                f"{kind:<8} {pt.why:<34} {pt.range_um:6.1f} um {pt.frequency_hz:7.3f} Hz "
                f"offset {pt.offset_um:+6.2f} um: nonlinearity {r['nonlinearity_pct']:.3f} %, "
                f"length error {r['length_error_pct']:+.3f} %, "
                f"at the pixels {r['pixel_nonlinearity_pct']:.3f} % (noise {r['pixel_noise_pct']:.3f} %)"
                + (f" ({faults} clamped)" if faults else "")
                + (f" ({slewed} samples slew-limited)" if slewed else "")
                + (
                    f"; true position {true_lin.nonlinearity_pct:.3f} %, {true_lin.length_error_pct:+.3f} %"
                    if true_lin is not None
                    else ""
                )
            )
    summary: dict[str, dict[str, float]] = {}
    for kind in kinds:
        for inside in (True, False):
            # a clamped scan measures the amplifier's limit, not the model: left out of the summary
            sel = [r for r in rows if r["model"] == kind and r["inside_frame"] == inside and not r["clamped"]]
            if sel:
                summary[f"{kind}/{'inside' if inside else 'outside'}"] = {
                    "max_nonlinearity_pct": max(r["nonlinearity_pct"] for r in sel),
                    "max_pixel_nonlinearity_pct": max(r["pixel_nonlinearity_pct"] for r in sel),
                    "max_abs_length_error_pct": max(abs(r["length_error_pct"]) for r in sel),
                }
                if all("true_nonlinearity_pct" in r for r in sel):
                    summary[f"{kind}/{'inside' if inside else 'outside'}/true position"] = {
                        "max_nonlinearity_pct": max(r["true_nonlinearity_pct"] for r in sel),
                        "max_abs_length_error_pct": max(abs(r["true_length_error_pct"]) for r in sel),
                    }
    for name, line in summary.items():
        print(
            f"{name:<20} max nonlinearity {line['max_nonlinearity_pct']:.3f} %, max |length error| "
            f"{line['max_abs_length_error_pct']:.3f} %"
            + (
                f", at the pixels {line['max_pixel_nonlinearity_pct']:.3f} %"
                if "max_pixel_nonlinearity_pct" in line
                else ""
            )
        )
    print(f"{time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {"stage": str(path), "choice": choice.report, "rows": rows, "summary": summary}, indent=2
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
