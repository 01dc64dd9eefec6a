"""``piezod bench inverse | stream``: speed and accuracy benchmarks with numbers against a baseline."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Any

from piezod.cli._common import add_json_option, human_stream, positive_float, positive_int, write_json
from piezod.errors import PiezodError

#: Module providing ``run_stream_bench(args) -> dict`` (the link's streaming benchmark).
STREAM_BENCH_MODULE = "piezod.link.bench"


def register(sub: Any) -> None:
    """Add the ``bench`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "bench",
        help="benchmarks: the inverse model (ns/sample vs scipy) or streaming over the link",
        description=(
            "inverse: time the full Lambert-W inverse on blocks of a triangular scan against the same "
            "inverse built on scipy.special.lambertw, in the same run, and report the worst round-trip "
            "error relative to the range. stream: stream samples to the simulated board and count "
            "underruns and CRC errors. audit: run the audit over a corpus generated in process "
            "(hidden-effect sessions, decimated and re-split variants, stand-ins for real data, the "
            "P-885 recordings) and print the confusion matrix, false-alarm rate, invariance failures, "
            "findings outside physical bounds and the time per audit."
        ),
    )
    p.add_argument("which", choices=("inverse", "stream", "audit", "effects"), help="what to benchmark")
    add_json_option(p)
    inv = p.add_argument_group("inverse")
    inv.add_argument(
        "--block-samples", type=positive_int, default=4096, metavar="N", help="samples per block"
    )
    inv.add_argument("--blocks", type=positive_int, default=128, metavar="N", help="blocks per repeat")
    inv.add_argument(
        "--repeats", type=positive_int, default=7, metavar="N", help="interleaved repeats (best counts)"
    )
    stream = p.add_argument_group("stream")
    stream.add_argument("--axes", type=positive_int, default=3, metavar="N", help="number of axes streamed")
    stream.add_argument(
        "--rate-hz", type=positive_float, default=100_000.0, metavar="R", help="samples/s per axis"
    )
    stream.add_argument("--seconds", type=positive_float, default=60.0, metavar="S", help="duration (s)")
    stream.add_argument(
        "--port",
        default=None,
        metavar="URL",
        help="stream to this board (a pty, serial port or pyserial URL, e.g. the C firmware's host "
        "build) instead of a fresh hil_sim",
    )
    stream.add_argument(
        "--model",
        default=None,
        metavar="NAME",
        help="run this axis model's inverse on every axis in the streaming path (triangle targets), "
        "e.g. family/prandtl-ishlinskii/voltage-creep (the richest; names as in 'bench inverse')",
    )
    stream.add_argument(
        "--api-load", action="store_true", help="stream with the daemon while its API is polled"
    )
    stream.add_argument(
        "--api-clients", type=positive_int, default=2, metavar="N", help="polling clients (--api-load)"
    )
    stream.add_argument("--with-fit", action="store_true", help="also run calibration fits (--api-load)")
    aud = p.add_argument_group("audit")
    aud.add_argument(
        "--sessions", type=int, default=2, metavar="N", help="hidden-effect sessions per effect (audit)"
    )
    eff = p.add_argument_group("effects")
    eff.add_argument(
        "--effects",
        nargs="+",
        default=None,
        metavar="ID",
        help="effects (default: every effect hil_sim can inject): online correction with the baseline "
        "and the audit's extended model on the built-in stage + the effect",
    )
    eff.add_argument("--plot", metavar="F.png", help="bar chart of what each model leaves (effects)")
    eff.add_argument("--full-frame", action="store_true", help="the full calibration frame (effects)")
    eff.add_argument(
        "--jobs",
        type=positive_int,
        default=1,
        metavar="N",
        help="run the cases in N worker processes (effects; a full-frame case took up to 7 GB in session 22)",
    )
    eff.add_argument(
        "--cases-dir",
        metavar="DIR",
        help="keep every case in DIR as it ends (effects); a later run with the same DIR and settings "
        "takes the saved cases instead of running them again",
    )
    p.set_defaults(func=run)


def _run_inverse(args: argparse.Namespace) -> dict[str, Any]:
    from piezod.bench import run_inverse_bench

    if args.block_samples < 1 or args.blocks < 1 or args.repeats < 1:
        raise PiezodError("--block-samples, --blocks and --repeats must be >= 1")
    result = run_inverse_bench(block_samples=args.block_samples, blocks=args.blocks, repeats=args.repeats)
    out = human_stream(args)
    print(
        f"inverse: {result['ns_per_sample']:.1f} ns/sample, scipy-based: {result['scipy_ns_per_sample']:.1f} "
        f"ns/sample, ratio {result['ratio']:.3f} (target <= 0.3)",
        file=out,
    )
    print(
        f"round trip: max error {result['max_roundtrip_error_rel']:.2e} of range (target <= 1e-9); "
        f"ODE per-sample inverse {result['ode_ns_per_sample']:.1f} ns/sample, "
        f"round trip {result['ode_max_roundtrip_error_rel']:.2e}",
        file=out,
    )
    for name, m in result["models"].items():
        print(
            f"axis model {name:<45} {m['ns_per_sample']:7.1f} ns/sample/axis "
            f"(x{m['ns_per_sample'] / result['scipy_ns_per_sample']:.2f} of the scipy-based inverse), "
            f"round trip {m['max_roundtrip_error_rel']:.1e} of range",
            file=out,
        )
    print(
        f"richest runtime model ({result['richest_model']} {result['richest_model_ns_per_sample']:.1f} ns "
        f"+ the resonance part's shaping {result['resonance_ns_per_sample']:.1f} ns): "
        f"{result['richest_ns_per_sample']:.1f} "
        f"ns/sample/axis, x{result['richest_ratio']:.2f} of the scipy-based inverse (target <= "
        f"{result['target_model_ns_per_sample']:.0f} ns): "
        f"{'met' if result['richest_meets_target'] else 'NOT met'}",
        file=out,
    )
    print(
        f"{result['samples']} samples in blocks of {result['block_samples']}, best of {result['repeats']}; "
        f"targets {'met' if result['meets_targets'] else 'NOT met'}",
        file=out,
    )
    return result


def _run_stream(args: argparse.Namespace) -> dict[str, Any]:
    if getattr(args, "api_load", False):
        from piezod.service.bench import run_api_load_bench

        result = run_api_load_bench(args)
        keys = (
            "underruns",
            "crc_errors",
            "samples_sent",
            "samples_read",
            "api_requests_per_s",
            "fits_completed",
        )
        print(", ".join(f"{k} {result[k]}" for k in keys if k in result), file=human_stream(args))
        return result
    return _run_link_stream(args)


def _run_link_stream(args: argparse.Namespace) -> dict[str, Any]:
    try:
        module = importlib.import_module(STREAM_BENCH_MODULE)
    except ModuleNotFoundError as exc:
        if exc.name is not None and STREAM_BENCH_MODULE.startswith(exc.name):
            raise PiezodError(
                f"the stream bench is not available yet ({STREAM_BENCH_MODULE} does not exist)"
            ) from exc
        raise
    result: dict[str, Any] = module.run_stream_bench(args)
    keys = (
        "axes",
        "rate_hz",
        "seconds",
        "samples_sent",
        "samples_read",
        "underruns",
        "crc_errors",
        "model",
        "model_ns_per_sample",
        "host_clamped_samples",
    )
    print(", ".join(f"{k} {result[k]}" for k in keys if k in result), file=human_stream(args))
    return result


def _run_audit(args: argparse.Namespace) -> dict[str, Any]:
    from piezod.audit.bench import format_report, run_corpus
    from piezod.progress import progress_bar

    if args.sessions < 1:
        raise PiezodError("--sessions must be >= 1")
    with progress_bar(desc="audits", total=None, unit="audit") as bar:

        def tick(_name: str) -> None:
            bar.update(1)

        result = run_corpus(args.sessions, on_audit=tick)
    print(format_report(result), file=human_stream(args))
    return result


def _run_effects(args: argparse.Namespace) -> dict[str, Any]:
    from piezod.effects_bench import format_table, plot_effects, run_effects_bench
    from piezod.progress import progress_bar
    from piezod.simulator import sim_effect_names

    known = sim_effect_names()
    names = args.effects or list(known)
    unknown = [n for n in names if n not in known]
    if unknown:
        raise PiezodError(f"--effects: unknown effect {unknown[0]!r} (one of {', '.join(known)})")
    with progress_bar(desc="effects", total=None, unit="step") as bar:

        def tick(_step: str) -> None:
            bar.update(1)

        result = run_effects_bench(
            names,
            reduced=not args.full_frame,
            on_step=tick,
            jobs=args.jobs,
            cases_dir=Path(args.cases_dir) if args.cases_dir else None,
        )
    print(format_table(result), file=human_stream(args))
    if args.plot:
        print(f"plot: {plot_effects(result, args.plot)}", file=human_stream(args))
    return result


def run(args: argparse.Namespace) -> int:
    """Run ``piezod bench``."""
    runners = {"inverse": _run_inverse, "stream": _run_stream, "audit": _run_audit, "effects": _run_effects}
    result = runners[args.which](args)
    write_json(args.json, result)
    return 0
