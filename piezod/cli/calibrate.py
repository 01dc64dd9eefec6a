"""``piezod calibrate``: fit the hysteresis + creep model to recordings (offline).

The thesis model (3.8) for periodic triangular scans, the dynamic model (ODE (2.21) + log creep)
for any other waveform (:mod:`piezod.calibrate_any` chooses and says which); with ``--model auto``
the model family's members are scored beside that model on the same held-out data
(:func:`piezod.family_heldout.compare_family`; (3.8) refitted on the training part,
:func:`piezod.family_heldout.thesis_heldout_rms`) and the one that predicts best is written.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from typing import Any, cast

import numpy as np

from piezod import calibrate_any
from piezod.calibrate import LOSSES, PARAM_NAMES, CalibrationResult
from piezod.calibrate_dynamic import PARAM_NAMES as DYNAMIC_PARAM_NAMES
from piezod.calibrate_dynamic import DynamicCalibrationResult
from piezod.calibrate_family import CHOICE_TIE_FRACTION, family_model_config, fit_family
from piezod.cli._common import (
    add_family_laws_option,
    add_json_option,
    add_port_options,
    add_reading_options,
    human_stream,
    input_file,
    nonneg_float,
    nonneg_int,
    positive_float,
    write_json,
)
from piezod.config import AxisName, ScannerConfig, dump_config, load_config, with_recorded_utc
from piezod.errors import CalibrationError, RecordingError
from piezod.family_heldout import (
    AUDIT_LAWS,
    FamilyComparison,
    MemberScore,
    compare_family,
    session,
    thesis_heldout_rms,
)
from piezod.model.domainwall import DomainWallParams
from piezod.model.dynamic import DynamicParams
from piezod.model.family import CreepSpectrum, FamilyParams
from piezod.progress import progress_bar
from piezod.readback import align_known_delay, within_sensor_range
from piezod.recording import AXES, Experiment, read_experiments

#: ``piezod calibrate --sim/--port``: the frame is played again when the fits end more than this
#: many seconds after its middle (the full frame's audit takes 45-95 min over the pty; birch35's
#: stage warmed by 4 %/h meanwhile, docs/model-family.md 6.2br).
REFRESH_AFTER_S = 600.0


def register(sub: Any) -> None:
    """Add the ``calibrate`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "calibrate",
        help="fit the model to recordings (any waveform) and write the scanner config",
        description=(
            "Least-squares fit with one position offset per experiment: the 7-parameter hysteresis + "
            "creep model (3.8) when every experiment is a periodic triangular scan (one-period "
            "triangles included; range, offset and frequency inferred from the voltage), else the "
            "dynamic model (hysteresis ODE (2.21) + log creep), which takes any waveform; with --model "
            "auto (default) the model family's members are scored beside it on held-out data and the "
            "one that predicts them best is written. The report says which model and why. Writes the "
            "scanner YAML (--out) and a JSON report (--json)."
        ),
    )
    p.add_argument(
        "recordings", nargs="*", type=input_file, metavar="REC.csv", help="recording files (docs/formats.md)"
    )
    p.add_argument(
        "--config",
        type=input_file,
        metavar="F",
        help="base scanner YAML: limits kept, start parameters taken",
    )
    p.add_argument("--out", metavar="F.yaml", help="write the calibrated scanner config here")
    add_json_option(p)
    p.add_argument(
        "--axis", choices=AXES, help="axis to calibrate (default: the recordings' only axis, else x)"
    )
    p.add_argument(
        "--model",
        choices=(*calibrate_any.MODEL_CHOICES, "family"),
        default="auto",
        help="auto (default): the model family's best member or the incumbent -- (3.8) on triangular "
        "scans, else the dynamic model -- whichever predicts held-out data better; thesis / dynamic: "
        "that model, no held-out scoring; family: the member that predicts held-out data best "
        "(docs/model-family.md 3.1)",
    )
    p.add_argument(
        "--validate",
        nargs="+",
        default=[],
        type=input_file,
        metavar="REC.csv",
        help="--model family / auto: held-out recordings the models are "
        "scored on (default: every 4th experiment, or every 4th of 5 time blocks of a single recording)",
    )
    # Bouc-Wen's rate search takes minutes per creep driver on a calibration frame: asked for only.
    add_family_laws_option(p, AUDIT_LAWS, "--model family / auto: the family's laws to fit")
    p.add_argument("--loss", choices=LOSSES, default="linear", help="loss function (default: linear)")
    p.add_argument(
        "--f-scale", type=positive_float, metavar="UM", help="residual scale of a robust loss (um)"
    )
    p.add_argument(
        "--fix",
        nargs="+",
        default=[],
        choices=tuple(dict.fromkeys((*PARAM_NAMES, *DYNAMIC_PARAM_NAMES))),
        metavar="NAME",
        help="hold parameters at start",
    )
    p.add_argument(
        "--skip-loops", type=nonneg_int, default=0, metavar="N", help="drop N settling loops per experiment"
    )
    p.add_argument(
        "--max-samples-per-loop",
        type=nonneg_int,
        default=2048,
        metavar="N",
        help="keep every k-th sample so that a loop has at most N (0 = all; default 2048)",
    )
    p.add_argument(
        "--no-dynamics",
        action="store_true",
        help="with --out: do not fit the stage's mode and the fast creep on the written model's residual "
        "(by default each is adopted when it predicts held-out data better, as on the stage)",
    )
    add_reading_options(p)
    add_port_options(p)
    stage = p.add_argument_group("on the stage (--sim / --port)")
    stage.add_argument(
        "--frame", choices=("full", "reduced"), default="full", help="calibration frame (default: full)"
    )
    stage.add_argument("--no-verify", action="store_true", help="skip the verification scans")
    stage.add_argument(
        "--no-audit",
        action="store_true",
        help="do not audit the frame (by default its material findings with a runtime part are adopted "
        "when they predict the held-out experiments better)",
    )
    stage.add_argument(
        "--no-lag-placement",
        action="store_true",
        help="do not play the lag placement experiment after the frame (~20 s of ramps with short "
        "spikes; by default it measures how much of the audit's sensor lag is the amplifier's pole at "
        "the drive, docs/model-family.md 6.2ak)",
    )
    refresh = stage.add_mutually_exclusive_group()
    refresh.add_argument(
        "--refresh-after",
        type=nonneg_float,
        metavar="S",
        default=REFRESH_AFTER_S,
        help="when the fits end more than S s after the frame's middle, play the frame again, refit the "
        "chosen family member on it (its parts held) and write the refit when it predicts that frame "
        "better than the first frame's member: a warming stage drifts while the fits run "
        f"(default {REFRESH_AFTER_S:g}; docs/model-family.md 6.2br)",
    )
    refresh.add_argument(
        "--no-refresh", action="store_true", help="never play the frame again after the fits"
    )
    stage.add_argument(
        "--recordings-dir", metavar="DIR", help="where the frame and verification recordings go"
    )
    stage.add_argument("--plot", metavar="F.png", help="plot of the verification (matplotlib)")
    stage.add_argument(
        "--effect", action="append", metavar="NAME=VALUE", help="simulator effect (with --sim)"
    )
    images = p.add_argument_group("without a position sensor (--from-images, docs/images.md)")
    images.add_argument(
        "--from-images",
        action="store_true",
        help="calibrate from trace/retrace images of a line pattern of known pitch (no position sensor)",
    )
    images.add_argument(
        "--pitch-um", type=positive_float, metavar="P", help="the reference's certified pitch (um)"
    )
    images.add_argument(
        "--sample", metavar="NAME", help="with --sim: the simulated reference (default line-3um)"
    )
    images.add_argument(
        "--no-recheck",
        action="store_true",
        help="do not repeat a frame scan after the fits (by default a material change of the "
        "sensitivity since the frame - a scanner that warms - is adopted as a thermal trend)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod calibrate``."""
    if args.from_images:
        from piezod.cli.calibrate_images import run_from_images

        if not (args.sim or args.port):
            raise CalibrationError("--from-images runs on the stage: give --sim or --port URL")
        return run_from_images(args)
    if args.sim or args.port:
        from piezod.cli.calibrate_stage import run_on_stage

        return run_on_stage(args)
    if not args.recordings:
        raise CalibrationError("no recordings given (piezod calibrate REC.csv...)")
    if args.skip_loops < 0:
        raise CalibrationError(f"--skip-loops must be >= 0, got {args.skip_loops}")
    base = load_config(args.config) if args.config else None
    exps = read_experiments(
        args.recordings,
        axis=args.axis,
        allow_truncated_tail=args.allow_truncated_tail,
        encoding=args.encoding,
    )
    axes = sorted({e.axis for e in exps if e.axis is not None})
    if args.axis is None and len(axes) > 1:
        raise CalibrationError(f"the recordings contain axes {', '.join(axes)}: choose one with --axis")
    axis = args.axis or (axes[0] if axes else "x")
    exps, clipped = within_sensor_range(exps)
    exps, aligned = align_known_delay(exps)
    start = base.axes[axis].thesis.params() if base is not None and axis in base.axes else None
    if args.validate and args.model in ("thesis", "dynamic"):
        raise CalibrationError(
            "--validate scores the models on held-out recordings: use it with --model auto or family"
        )

    family: FamilyComparison | None = None
    family_note = ""
    with progress_bar(desc="calibrate", total=None, unit="eval") as bar:

        def tick(_n: int) -> None:
            bar.update(1)

        result = calibrate_any.calibrate_any(
            exps,
            model="dynamic" if args.model == "family" else args.model,
            start=start,
            loss=args.loss,
            f_scale=args.f_scale,
            fix=args.fix,
            skip_loops=args.skip_loops,
            max_samples_per_loop=args.max_samples_per_loop or None,
            on_eval=tick,
        )
        dyn = result.dynamic
        val: list[Experiment] = []
        if args.validate:
            val = read_experiments(
                args.validate,
                axis=axis,
                allow_truncated_tail=args.allow_truncated_tail,
                encoding=args.encoding,
            )
            val, clipped_val = within_sensor_range(val)
            clipped = "; ".join(n for n in (clipped, clipped_val) if n) or None
        incumbent_name = "dynamic" if dyn is not None else "thesis (3.8)"
        if args.model in ("family", "auto"):
            # The dynamic model is a candidate too (fitted on all the data, so it wins ties); the
            # thesis model is refitted on the training part of the split below.
            incumbent = (
                {} if dyn is None else {"dynamic": FamilyParams(dyn.params.hysteresis, _spectrum(dyn.params))}
            )
            try:
                family = compare_family(
                    exps,
                    val,
                    laws=args.family_laws,
                    on_step=lambda _name: tick(1),
                    others=incumbent,
                    parts=False,
                    after_effect=True,
                )
            except CalibrationError as exc:
                if args.model == "family":
                    raise
                family_note = (
                    f"the model family was not scored ({exc}): the {incumbent_name} model is written"
                )
        if family is not None and result.thesis is not None and args.model == "auto":
            try:
                thesis_rms = thesis_heldout_rms(
                    exps, val, family, start=start, max_samples_per_loop=args.max_samples_per_loop or None
                )
            except (CalibrationError, RecordingError) as exc:
                family_note = (
                    f"the thesis model (3.8) was not scored on the held-out data ({exc}): it is written"
                )
                family = None
            else:
                family = dataclasses.replace(
                    family,
                    others={**family.others, incumbent_name: thesis_rms},
                    fitted_on={**family.fitted_on, incumbent_name: "all" if val else "the training part"},
                )
    out = human_stream(args)
    if clipped:
        print(f"WARNING: {clipped}", file=out)
    if aligned:
        print(f"note: {aligned}", file=out)
    chosen = None if family is None else _chosen_member(family)
    if family is not None and chosen is not None and args.model == "auto":
        incumbent_rms = family.others.get(incumbent_name, math.inf)
        if not chosen.heldout_rms_um < incumbent_rms * (1.0 - CHOICE_TIE_FRACTION):
            family_note = (
                f"the {incumbent_name} model predicts the held-out data ({incumbent_rms:.4g} um) at least "
                f"as well as the family's best member {chosen.name} ({chosen.heldout_rms_um:.4g} um): the "
                f"{incumbent_name} model is written"
            )
            chosen = None
    if family is not None and chosen is not None:
        why = (
            "requested"
            if args.model == "family"
            else f"auto: it predicts the held-out data better than the {incumbent_name} model "
            f"({family.others.get(incumbent_name, math.nan):.4g} um)"
        )
        print(
            f"model: family ({chosen.name}: the member that predicts the held-out data best; {why})", file=out
        )
        print(f"held out: {family.method}", file=out)
        print(family.table(), file=out)
        print(
            f"{incumbent_name} model (the config's thesis section and provenance): fit error "
            f"{result.fit.fit_error_pct:.4f} %",
            file=out,
        )
    else:
        print(f"model: {result.choice.model} ({result.choice.reason})", file=out)
        if result.thesis is not None:
            _print_summary(result.thesis, axis, out)
        elif result.dynamic is not None:
            _print_dynamic(result.dynamic, axis, out)
        if family is not None:
            print(f"the model family on held-out data ({family.method}):", file=out)
            print(family.table(), file=out)
        if family_note:
            print(f"note: {family_note}", file=out)
    doc = calibrate_any.result_json(result, inputs=list(args.recordings))
    if family is not None:
        doc["family"] = family.to_json()
    if family_note:
        doc["model_reason"] = f"{doc['model_reason']}; {family_note}"
    if family is not None and chosen is not None:
        section = family_model_config(_written(exps, chosen, family.skip_s, refit=not args.validate))
        doc.update(
            model="family",
            model_reason=f"{chosen.name} predicts the held-out data best ({family.method})",
            chosen=chosen.name,
            family_params=section.model_dump(),
        )
    if args.out:
        span = (
            float(min(np.min(e.voltage_v) for e in exps)),
            float(max(np.max(e.voltage_v) for e in exps)),
        )
        cfg = calibrate_any.calibrated_config(
            result, axis=axis, base=base, inputs=list(args.recordings), voltage_span_v=span
        )
        model_name: str = result.choice.model
        if family is not None and chosen is not None:
            cfg = cfg.with_axis(cast(AxisName, axis), model="family", family=section)
            model_name = f"family ({chosen.name}, held out: {family.method})"
        dynamics: list[str] = []
        if not args.no_dynamics:
            cfg, dynamics = _with_dynamics(exps, cast(AxisName, axis), cfg, doc)
            for line in dynamics:
                print(line, file=out)
        line_s = calibrate_any.shortest_line_s(exps)
        if line_s is not None:
            cfg = calibrate_any.with_tracking_bound(cfg, axis, line_s)
            print(
                f"the sensitivity tracker learns from lines of axis {axis} about as long as the recordings' "
                f"shortest or longer (tracking_min_line_s: {line_s:.3g} s)",
                file=out,
            )
        measured = calibrate_any.recorded_mid_unix_s(exps)
        if math.isfinite(measured):
            cfg = with_recorded_utc(cfg, measured)
        else:
            print(
                "the recordings do not say when they were measured (no started_utc): the daemon's "
                "sensitivity tracker will take the model's age as unknown",
                file=out,
            )
        header = (
            f"scanner config written by piezod calibrate (axis {axis}, {model_name} model) "
            f"from {', '.join(args.recordings)}"
        )
        if args.config:
            header += f"\nbase: {args.config} (limits and other axes kept)"
        header += "".join(f"\n{line}" for line in dynamics)
        dump_config(cfg, args.out, header=header)
        load_config(args.out)
        print(f"wrote {args.out}", file=out)
    write_json(args.json, doc)
    if not result.success:
        print(f"piezod calibrate: the fit did not converge: {result.message}", file=out)
        return 1
    return 0


def _with_dynamics(
    exps: Sequence[Experiment], axis: AxisName, cfg: ScannerConfig, doc: dict[str, Any]
) -> tuple[ScannerConfig, list[str]]:
    """``cfg`` with the mode and the fast creep the recordings show on its axis model's residual
    (:func:`piezod.stagecal.with_dynamics`, as ``piezod calibrate --sim/--port`` does); their
    summaries go to ``doc`` (``resonance``, ``fast_creep``), and one line per step is returned."""
    from piezod.stagecal import ThesisFit, with_dynamics

    stepped = with_dynamics(exps, axis, ThesisFit({}, cfg, math.nan))
    for key in ("resonance", "fast_creep"):
        if key in stepped.report:
            doc[key] = stepped.report[key]
    lines = [line for line in str(stepped.report.get("text") or "").splitlines() if line]
    doc["dynamics"] = lines
    return stepped.config, lines


def _chosen_member(family: FamilyComparison) -> MemberScore:
    """The member that predicts the held-out data best (both creep drivers stream in real time)."""
    best = family.best
    if best is None:
        reasons = "; ".join(f"{m.name}: {m.error}" for m in family.members if m.error)
        raise CalibrationError(f"no member of the model family could be fitted: {reasons}")
    return best


def _spectrum(params: DynamicParams) -> CreepSpectrum:
    """The dynamic model's creep as a family creep spectrum (the same modal bank)."""
    return CreepSpectrum(tuple(map(float, params.taus_s)), tuple(map(float, params.weights)))


def _written(exps: Sequence[Experiment], chosen: MemberScore, skip_s: float, *, refit: bool) -> FamilyParams:
    """The chosen member as fitted on every training experiment: its scored fit when that already
    was (``--validate``), else refitted on all of them (the held-out ones included)."""
    if not refit and chosen.params is not None:
        return chosen.params
    # an after-effect is held where the scored fit placed it (the search is the costly part), and a
    # domain-wall law's search starts from its shape
    held = None if chosen.params is None else chosen.params.after_effect
    law = None if chosen.params is None else chosen.params.hysteresis
    return fit_family(
        session(exps),
        chosen.law,
        creep_driver=chosen.creep_driver,
        skip_s=skip_s,
        after_effect=held,
        start=law if isinstance(law, DomainWallParams) else None,
    ).params


def _print_dynamic(result: DynamicCalibrationResult, axis: str, out: Any) -> None:
    print(
        f"axis {axis}: {len(result.experiments)} experiments, {result.n} samples, "
        f"{result.nfev} evaluations, {result.seconds:.2f} s",
        file=out,
    )
    _print_parameters(result, DYNAMIC_PARAM_NAMES, 20, out)
    print(f"  {'experiment':<28} {'kind':>9} {'range V':>8} {'range um':>9} {'fit err %':>9}", file=out)
    for e in result.experiments:
        lay = e.layout
        print(
            f"  {e.label[-28:]:<28} {lay.kind:>9} {lay.v_max - lay.v_min:8.1f} {e.range_um:9.3f} "
            f"{e.fit_error_pct:9.4f}",
            file=out,
        )
    _print_footer(result, out, strong_correlations=False)


def _print_parameters(
    result: CalibrationResult | DynamicCalibrationResult, names: Sequence[str], width: int, out: Any
) -> None:
    """One line per parameter: value, standard error, held or not."""
    for k in names:
        tag = "  (fixed)" if k in result.fixed else ""
        print(f"  {k:<{width}} = {getattr(result.params, k):<12.6g} +- {result.stderr[k]:.3g}{tag}", file=out)


def _print_footer(
    result: CalibrationResult | DynamicCalibrationResult, out: Any, *, strong_correlations: bool
) -> None:
    """The worst experiment, the condition number, (strong correlations,) the fit's warnings."""
    w = result.worst
    print(
        f"worst fit error {w.fit_error_pct:.4f} % ({w.label}); "
        f"condition number {result.condition_number:.3g}",
        file=out,
    )
    if strong_correlations:
        strong = [
            f"{a}/{b} {result.correlations[i, j]:+.3f}"
            for i, a in enumerate(result.free)
            for j, b in enumerate(result.free)
            if j > i and abs(result.correlations[i, j]) > 0.95
        ]
        if strong:
            print("strong correlations: " + ", ".join(strong), file=out)
    for msg in result.warnings:
        print(f"note: {msg}", file=out)


def _print_summary(result: CalibrationResult, axis: str, out: Any) -> None:
    print(
        f"axis {axis}: {len(result.experiments)} experiments, {result.n} samples, loss {result.loss}, "
        f"{result.nfev} evaluations, {result.seconds:.2f} s",
        file=out,
    )
    _print_parameters(result, PARAM_NAMES, 12, out)
    print(
        f"  {'experiment':<28} {'range V':>8} {'offs V':>7} {'f Hz':>7} {'range um':>9} {'fit err %':>9}",
        file=out,
    )
    for e in result.experiments:
        print(
            f"  {e.label[-28:]:<28} {e.range_v:8.1f} {e.offset_v:7.1f} {e.frequency_hz:7.3g} "
            f"{e.range_um:9.3f} {e.fit_error_pct:9.4f}",
            file=out,
        )
    _print_footer(result, out, strong_correlations=True)
