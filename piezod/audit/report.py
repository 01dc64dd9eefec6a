"""The audit report: a text summary for the scientist and the JSON document (keys: docs/formats.md)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import IO, Any

import numpy as np

from piezod.audit.decide import AuditOptions, AuditResult, CandidateResult
from piezod.audit.evidence import Structure

_MEANING = {
    "none": "the model explains the data to the noise",
    "unexplained": "structure above the noise that no candidate explains",
    "drift": "position drifts linearly in time",
    "thermal": "sensitivity changes slowly over the session",
    "stiffness": "position-dependent stiffness (length error depends on offset)",
    "polarity": "sensitivity differs for the two voltage polarities",
    "resonance": "mechanical ringing after turning points",
    "delay": "sensor or amplifier lag: the loop opens with speed",
    "saturation": "response compresses at large excursions",
    "creep": "creep law wrong: frequency dependence not as modelled",
    "switching": "polarization switching: the actuator model does not apply (butterfly response, even in V)",
    "sensitivity_loss": "sensitivity lost after a large excursion (depoling)",
    "sensitivity_gain": "the validation session is more sensitive than the training session",
    "undetermined": "the data do not determine the baseline model; no cause can be named",
}


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _candidate_json(c: CandidateResult) -> dict[str, Any]:
    return {
        "effect": c.effect,
        "round": c.round,
        "tested": c.fit is not None,
        "note": c.testable,
        "params": {k: _num(v) for k, v in c.params.items()},
        "gain": _num(c.gain),
        "gain_se": _num(c.gain_se),
        "heldout_rms_before_um": _num(c.heldout_rms_before_um),
        "heldout_rms_after_um": _num(c.heldout_rms_after_um),
        "rms_um": _num(c.rms_um),
        "bic_delta": _num(c.bic_delta),
        "eligible": c.eligible,
        "plausible": not c.implausible,
        "implausible": c.implausible,
    }


def _structure_json(s: Structure) -> dict[str, Any]:
    return {
        "rms_um": s.rms_um,
        "noise_ratio": s.noise_ratio,
        "correlations": s.correlations,
        "negative_minus_positive_um": s.negative_minus_positive_um,
        "spectral_peak_hz": s.spectral_peak_hz,
        "loop_closure_um": s.loop_closure_um,
        "bins": s.bins,
        "experiments": s.per_experiment,
    }


def _finding_json(f: CandidateResult) -> dict[str, Any]:
    return {
        "effect": f.effect,
        "evidence": f.evidence,
        "gain": _num(f.gain),
        "gain_se": _num(f.gain_se),
        "heldout_rms_before_um": _num(f.heldout_rms_before_um),
        "heldout_rms_after_um": _num(f.heldout_rms_after_um),
        "params": {k: _num(v) for k, v in f.params.items()},
        "bic_delta": _num(f.bic_delta),
        "rms_um": _num(f.rms_um),
        "round": f.round,
    }


def result_json(
    result: AuditResult, *, inputs: Sequence[str] = (), validate: Sequence[str] = ()
) -> dict[str, Any]:
    """The JSON document of ``piezod audit --json`` (keys: docs/formats.md, more keys welcome).

    Keys the checks read: ``cause``, ``findings[]`` (``effect, evidence, gain,
    heldout_rms_before_um, heldout_rms_after_um``) and ``baseline`` (``rms_um, heldout_rms_um``).
    """
    base_params, _ = result.base_fit.model.public(result.base_fit.p)
    final_base, final_ext = result.final_fit.model.public(result.final_fit.p)
    opts = result.options
    return {
        "cause": result.cause,
        "cause_meaning": _MEANING.get(result.cause, ""),
        "findings": [_finding_json(f) for f in result.findings],
        "withheld": [_finding_json(f) for f in result.withheld],
        "baseline": {
            "model": result.baseline_name,
            "params": base_params,
            "rms_um": result.base_fit.rms_um,
            "heldout_rms_um": result.base_heldout.rms_um,
            "noise_floor_um": _num(result.noise_floor_um),
            "structure_ratio": _num(result.structure_ratio),
            "bic": result.base_fit.bic,
            "n_samples": result.base_fit.n,
            "n_parameters": result.base_fit.k,
        },
        "final": {
            "effects": list(result.final_fit.model.effects),
            "params": final_base,
            "extension_params": final_ext,
            "rms_um": result.final_fit.rms_um,
            "heldout_rms_um": result.final_heldout.rms_um,
            "gain": result.base_heldout.rms_um / result.final_heldout.rms_um,
            "structure_ratio": _num(result.final_structure_ratio),
        },
        "candidates": [_candidate_json(c) for c in result.candidates],
        "rounds": [[_candidate_json(c) for c in rnd] for rnd in result.rounds],
        "heldout": {
            "method": result.heldout_method,
            "validation_gain": result.base_heldout.gains,
        },
        "residuals": {
            "baseline": _structure_json(result.base_structure),
            "final": _structure_json(result.final_structure),
            "noise_floor_per_experiment_um": [_num(v) for v in result.noise_per_experiment_um],
        },
        "decision": {
            "bic_min": opts.bic_min,
            "gain_min": opts.gain_min,
            "structure_max": opts.structure_max,
            "explain_min": opts.explain_min,
            "gain_sigmas": opts.gain_sigmas,
            "heldout_refit": opts.refit_cv,
            "rule": legend(opts),
        },
        "outside_model": _outside_json(result),
        "degeneracy": None
        if result.degeneracy is None
        else {
            "degenerate": result.degeneracy.degenerate,
            "undetermined": list(result.degeneracy.undetermined),
            "on_bounds": list(result.degeneracy.on_bounds),
            "absent": list(result.degeneracy.absent),
            "condition_number": _num(result.degeneracy.condition_number),
            "max_correlation": _num(result.degeneracy.max_correlation),
            "text": result.degeneracy.text,
        },
        "n_experiments": result.data.n_experiments,
        "n_samples": result.data.n,
        "notes": list(result.notes),
        "seconds": result.seconds,
        "inputs": list(inputs),
        "validate": list(validate),
    }


def _outside_json(result: AuditResult) -> dict[str, Any]:
    o = result.outside
    return {
        "switching": None
        if o.switching is None
        else {
            "onset_v": o.switching.onset_v,
            "turn_fraction": o.switching.turn_fraction,
            "experiments": list(o.switching.experiments),
            "text": o.switching.text,
        },
        "hold_drift": None
        if o.drift is None
        else {
            "rate_nm_per_s": o.drift.rate_nm_per_s,
            "rate_se_nm_per_s": o.drift.rate_se_nm_per_s,
            "gain": _num(o.drift.gain),
            "gain_se": _num(o.drift.gain_se),
            "bic_delta": o.drift.bic_delta,
            "n_holds": o.drift.n_holds,
            "seconds": o.drift.seconds,
            "significant": o.drift.significant,
            "text": o.drift.text,
        },
        "sensitivity_loss": None
        if o.loss is None
        else {
            "loss_pct": o.loss.loss_pct,
            "after": o.loss.after,
            "peak_v": o.loss.peak_v,
            "text": o.loss.text,
        },
        "holds": [{"experiment": lab, "first_sample": a, "stop_sample": b} for lab, a, b in o.holds],
    }


def legend(opts: AuditOptions) -> str:
    """The eligibility rule as the code applies it (:func:`piezod.audit.decide._try`)."""
    return (
        f"(* eligible: BIC falls by more than {opts.bic_min:g}, held-out gain >= {opts.gain_min:g} and "
        f"more than {opts.gain_sigmas:g} standard errors above 1, explains >= {100 * opts.explain_min:g} % "
        "of the held-out variance above the noise, parameters physically plausible; > the eligible "
        "candidate with the largest gain: finding 1, the cause)"
    )


def print_summary(result: AuditResult, out: IO[str]) -> None:
    """The human-readable report."""
    b = result.base_fit
    kind = "thesis model (3.8)" if result.base_kind == "thesis" else "hysteresis ODE (2.21)"
    pr = print
    pr(
        f"audit: {result.data.n_experiments} experiments, {result.data.n} samples, baseline {kind}; "
        f"held-out: {result.heldout_method}; {result.seconds:.1f} s",
        file=out,
    )
    params, extra = b.model.public(b.p)
    within = [f"{k} = {v:.5g} ({effect})" for effect, values in extra.items() for k, v in values.items()]
    shown = [f"{k} = {v:.5g}" for k, v in params.items()] + within
    pr("baseline parameters: " + ", ".join(shown), file=out)
    pr(
        f"baseline: rms {b.rms_um:.4g} um, held-out {result.base_heldout.rms_um:.4g} um, noise floor "
        f"{result.noise_floor_um:.4g} um (ratio {result.structure_ratio:.2f})",
        file=out,
    )
    _print_structure(result.base_structure, out)
    pr("", file=out)
    pr(
        f"{'candidate':<11} {'gain':>7} {'+-':>6} {'held-out um':>12} {'BIC delta':>11}  parameters",
        file=out,
    )
    first = result.findings[0].effect if result.findings else None
    for c in result.candidates:
        if c.fit is None:
            pr(f"{c.effect:<11} {'-':>7} {'':>6} {'-':>12} {'-':>11}  not tested: {c.testable}", file=out)
            continue
        ptxt = ", ".join(f"{k} {v:.4g}" for k, v in c.params.items())
        mark = " >" if c.effect == first and c.eligible else (" *" if c.eligible else "  ")
        note = f" [{c.testable}]" if c.testable else ""
        nums = f"{c.gain:7.3f} {c.gain_se:6.3f} {c.heldout_rms_after_um:12.4g} {c.bic_delta:11.4g}"
        pr(f"{c.effect:<11} {nums}{mark}{ptxt}{note}", file=out)
    pr(legend(result.options), file=out)
    pr("", file=out)
    for k, f in enumerate(result.findings, start=1):
        pr(f"finding {k}: {f.effect} ({_MEANING.get(f.effect, '')})", file=out)
        pr(f"  {f.evidence}", file=out)
    if result.findings:
        fin = result.final_fit
        pr(
            f"final model (baseline + {' + '.join(fin.model.effects)}): rms {fin.rms_um:.4g} um, held-out "
            f"{result.final_heldout.rms_um:.4g} um (overall gain "
            f"{result.base_heldout.rms_um / result.final_heldout.rms_um:.3g}), ratio to noise "
            f"{result.final_structure_ratio:.2f}",
            file=out,
        )
    for note in result.notes[1:]:
        pr(f"note: {note}", file=out)
    pr(f"cause: {result.cause} ({_MEANING.get(result.cause, '')})", file=out)


def _print_structure(s: Structure, out: IO[str]) -> None:
    c = s.correlations
    if len(s.per_experiment) < 3:
        _print_extra(s, out)
        return

    def f(v: float) -> str:
        return "  nan" if not math.isfinite(v) else f"{v:+.2f}"

    print(
        "residual structure: per-experiment sensitivity error vs session time "
        f"{f(c['gain_error_vs_time'])}, offset {f(c['gain_error_vs_offset'])}, range "
        f"{f(c['gain_error_vs_range'])}, log f {f(c['gain_error_vs_log_frequency'])}; loop opening vs f "
        f"{f(c['opening_error_vs_frequency'])}; trend vs time {f(c['slope_vs_time'])}",
        file=out,
    )
    _print_extra(s, out)


def _print_extra(s: Structure, out: IO[str]) -> None:
    extra = []
    if math.isfinite(s.negative_minus_positive_um):
        extra.append(f"mean residual V<0 minus V>0 {s.negative_minus_positive_um:+.3g} um")
    if s.spectral_peak_hz:
        extra.append(f"spectral peak at {s.spectral_peak_hz:.4g} Hz")
    if s.loop_closure_um:
        extra.append(f"loop-to-loop change (model-free) median {float(np.median(s.loop_closure_um)):.3g} um")
    if extra:
        print("  " + "; ".join(extra), file=out)
