"""``piezod audit``: what the model gets wrong on measured data, the physical cause, the held-out gain."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from piezod.audit import EFFECTS, AuditOptions, print_summary, result_json
from piezod.cli._common import (
    add_family_laws_option,
    add_json_option,
    add_reading_options,
    human_stream,
    input_file,
    positive_int,
    write_json,
)
from piezod.errors import PiezodError
from piezod.family_heldout import AUDIT_LAWS, audit_with_family
from piezod.progress import progress_bar
from piezod.recording import AXES, Experiment, read_experiments


def register(sub: Any) -> None:
    """Add the ``audit`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "audit",
        help="where the model and the measured stage disagree, why, and the held-out gain of a fix",
        description=(
            "Fit the baseline (the thesis model (3.8) for triangular scans, the hysteresis ODE (2.21) "
            "for any other waveform), analyse the residual structure, fit one physical extension per "
            "effect (drift, thermal, stiffness, polarity, resonance, delay, saturation, creep), measure "
            "each one's gain on held-out data (k-fold over experiments, a blocked split in time of a "
            "single recording, or --validate recordings) and name the cause."
        ),
    )
    p.add_argument(
        "recordings",
        nargs="+",
        type=input_file,
        metavar="REC.csv",
        help="recordings to fit (docs/formats.md)",
    )
    p.add_argument(
        "--validate", nargs="+", default=[], metavar="REC.csv", help="held-out recordings (not fitted)"
    )
    add_json_option(p)
    p.add_argument("--plots", metavar="DIR", help="write PNG plots into DIR (needs matplotlib)")
    p.add_argument(
        "--out",
        metavar="F.yaml",
        help="write the extended scanner YAML: --config with the material findings as runtime parts "
        "of the audited axis (piezod serve/scan load it; a comment says which finding became what)",
    )
    p.add_argument("--config", metavar="F", help="the scanner YAML the recordings were taken with (--out)")
    p.add_argument("--axis", choices=AXES, help="audit this axis (default: the recordings' only axis)")
    p.add_argument(
        "--folds", type=positive_int, default=5, metavar="K", help="folds of the held-out split (default 5)"
    )
    p.add_argument(
        "--baseline", choices=("thesis", "ode"), help="force the baseline (default: thesis for triangles)"
    )
    p.add_argument(
        "--effects",
        nargs="+",
        choices=EFFECTS,
        metavar="ID",
        help=f"candidates to try ({', '.join(EFFECTS)})",
    )
    p.add_argument(
        "--base-effects",
        nargs="+",
        choices=EFFECTS,
        default=(),
        metavar="ID",
        help="effects fitted into the baseline first, never named (e.g. creep: what piezod calibrate's"
        " adoption audit does)",
    )
    cv = p.add_mutually_exclusive_group()
    cv.add_argument(
        "--refit-cv",
        dest="fast_cv",
        action="store_false",
        help="refit every training fold with the solver (the default, an honest held-out estimate)",
    )
    cv.add_argument(
        "--fast-cv",
        action="store_true",
        help="a few Gauss-Newton steps from the full fit per fold instead of a refit (faster, optimistic)",
    )
    fam = p.add_argument_group("the model family (docs/model-family.md)")
    fam.add_argument(
        "--no-family",
        action="store_true",
        help="do not fit and score the model family's members on the held-out data (by default the"
        " --family-laws are, each with both creep drivers; the best model is the one of them or the"
        " audit's that predicts best, and a finding the better model contradicts is not named)",
    )
    add_family_laws_option(
        fam,
        AUDIT_LAWS,
        "the family's laws to score (the Bouc-Wen law's search takes minutes on a large frame)",
    )
    add_reading_options(p)
    p.set_defaults(func=run)


def _read(
    paths: list[str], axis: str | None, truncated: bool, encoding: str | None
) -> tuple[list[Experiment], str | None]:
    exps = read_experiments(paths, axis=axis, allow_truncated_tail=truncated, encoding=encoding)
    axes = sorted({e.axis for e in exps if e.axis is not None})
    if axis is None and len(axes) > 1:
        raise PiezodError(f"the recordings contain axes {', '.join(axes)}: choose one with --axis")
    return exps, axis or (axes[0] if axes else None)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod audit``."""
    if args.folds < 2:
        raise PiezodError(f"--folds must be >= 2, got {args.folds}")
    if args.out and not args.config:
        raise PiezodError("--out needs --config F (the scanner YAML the recordings were taken with)")
    exps, axis = _read(list(args.recordings), args.axis, args.allow_truncated_tail, args.encoding)
    val: list[Experiment] = []
    if args.validate:
        val, _ = _read(list(args.validate), axis, args.allow_truncated_tail, args.encoding)
    options = AuditOptions(
        folds=args.folds,
        base=args.baseline,
        effects=tuple(args.effects) if args.effects else EFFECTS,
        refit_cv=not args.fast_cv,
        base_effects=tuple(args.base_effects),
    )
    with progress_bar(desc="audit", total=None, unit="fit") as bar:

        def tick(_label: str) -> None:
            bar.update(1)

        checked = audit_with_family(
            exps, val, options=options, family=not args.no_family, laws=args.family_laws, on_step=tick
        )
    result, family, best = checked.result, checked.family, checked.best
    out = human_stream(args)
    print_summary(result, out)
    if family is not None:
        print(f"\nthe model family on held-out data ({family.method}):", file=out)
        print(family.table(), file=out)
    elif checked.family_error:
        print(f"\nthe model family: not scored ({checked.family_error})", file=out)
    for c in checked.checks:
        print(f"finding {c['text']}", file=out)
    print(
        f"best model on the held-out data: {best['name']} ({best['source']}), "
        f"{best['heldout_rms_um']:.4g} um = {best['ratio_to_noise_floor']:.2f} x the noise floor",
        file=out,
    )
    if args.plots:
        from piezod.audit.plots import write_plots

        files = write_plots(result, args.plots)
        print(f"plots: {', '.join(str(f) for f in files)}", file=out)
    doc = result_json(result, inputs=list(args.recordings), validate=list(args.validate))
    if family is not None:
        doc["family"] = family.to_json()
    else:
        doc["family"] = {"error": checked.family_error} if checked.family_error else None
    doc["best_model"] = best
    doc["finding_checks"] = list(checked.checks)
    doc["rejected_candidates"] = list(checked.rejected)
    write_json(args.json, doc)
    if args.out:
        from piezod.extensions import session_origin_unix_s, trend_horizon_s, write_extended_config

        source = "piezod audit " + " ".join(Path(r).name for r in args.recordings)
        adoption = write_extended_config(
            args.config,
            axis or "x",
            doc["findings"],
            args.out,
            source,
            horizon_s=trend_horizon_s(exps),
            since_unix_s=session_origin_unix_s(args.recordings[0]),
        )
        print(f"extended scanner YAML: {args.out}\n{adoption.summary()}", file=out)
    return 0
