"""The audit: baseline, candidates, held-out gains and the decision rule.

Decision rule
-------------
Greedy forward selection. In every round each remaining candidate is added to the current
model (baseline plus the findings so far) and everything is refitted jointly. A candidate is
*eligible* when

* the Bayesian information criterion of the training fit drops by more than ``bic_min``
  (``n ln(RSS/n) + k ln n``, the nuisance terms counted),
* the held-out RMS drops by the factor ``gain_min`` or more (k-fold over experiments, a blocked
  split in time for one long recording, or the ``--validate`` recordings),
* it explains at least ``explain_min`` of the held-out variance above the noise floor (a real
  stage whose baseline misfit is large must not collect every candidate that shaves a percent
  off it), and
* its parameters describe the effect (e.g. a resonance must ring: resolvable ``f0``, ``Q > 1/sqrt 2``).

The eligible candidate with the largest held-out gain becomes a finding and joins the model;
the next round starts from there, so two effects at once are both found, and an effect that
only mimics part of another one loses its gain once the true one is in the model. The *cause*
is the first (strongest) finding; ``none`` when nothing is eligible and the baseline residual
is at the noise floor; ``unexplained`` when nothing is eligible but the residual stays above
the noise floor by more than ``structure_max``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from piezod.audit import data as audit_data
from piezod.audit.baseline import (
    ODE,
    THESIS,
    Geometry,
    OdeBase,
    ThesisBase,
    geometry,
    ode_start,
    thesis_start,
)
from piezod.audit.bounds import implausible as physically_implausible
from piezod.audit.candidates import (
    EFFECTS,
    AuditModel,
    Candidate,
    Resonance,
    Scales,
    make_candidate,
    spectral_peak,
)
from piezod.audit.degenerate import Degeneracy, rayleigh_note
from piezod.audit.degenerate import check as check_degeneracy
from piezod.audit.evidence import Structure, evidence, structure
from piezod.audit.fitting import (
    Fit,
    HeldOut,
    Problem,
    fit_candidate,
    folds_of,
    gain_with_se,
    heldout_cv,
    heldout_validate,
)
from piezod.audit.outside import Outside
from piezod.audit.outside import check as check_outside
from piezod.audit.residuals import noise_floor_data
from piezod.errors import CalibrationError, PiezodError
from piezod.readback import align_known_delay, within_sensor_range
from piezod.recording import Experiment
from piezod.scan_inference import ScanInfo

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class AuditOptions:
    """Settings of the audit.

    Attributes
    ----------
    folds
        Folds of the cross-validation over experiments (or time blocks).
    bic_min
        BIC decrease a candidate needs.
    gain_min
        Held-out gain a candidate needs.
    explain_min
        Fraction of the held-out variance above the noise floor a candidate must explain.
    structure_max
        Largest ratio of the residual RMS to the noise floor that counts as "at the noise".
    max_findings
        Rounds of the forward selection.
    effects
        Candidates to try.
    base
        Force the baseline (``thesis`` / ``ode``; default: thesis when every experiment is a
        triangular scan and the frame determines it).
    refit_cv
        Refit every fold with the solver, warm-started at the full fit (the default: an honest
        estimate); ``False`` takes a few damped Gauss-Newton steps from the full fit instead
        (faster, biased toward the full fit).
    cv_nfev
        Evaluation budget of every cross-validation refit.
    gain_sigmas
        A candidate's held-out gain must exceed 1 by this many standard errors.
    base_effects
        Effects fitted into the baseline before the search (``creep`` when the model the findings
        will extend has creep anyway, as every runtime model does): never candidates, never named.
    """

    folds: int = 5
    bic_min: float = 10.0
    gain_min: float = 1.003
    explain_min: float = 0.1
    structure_max: float = 1.15
    max_findings: int = 3
    effects: tuple[str, ...] = EFFECTS
    base: str | None = None
    refit_cv: bool = True
    cv_nfev: int = 60
    gain_sigmas: float = 2.0
    base_effects: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class CandidateResult:
    """One candidate in one round.

    Attributes
    ----------
    effect
        Audit id.
    round
        Round of the forward selection (1 = added to the bare baseline).
    testable
        Empty, or why the data cannot show the effect (then nothing was fitted).
    params
        Fitted parameters (public units).
    rms_um
        Training RMS with the candidate.
    bic_delta
        BIC change against the round's starting model (negative = better).
    heldout_rms_before_um, heldout_rms_after_um
        Held-out RMS without and with the candidate.
    gain_se
        Standard error of the held-out gain (block jackknife of the held-out data).
    implausible
        Empty, or why the fitted magnitude lies outside physical bounds (:mod:`piezod.audit.bounds`).
    eligible
        Passes both thresholds.
    fit
        The training fit (None when not testable).
    heldout
        Held-out residuals with the candidate.
    evidence
        What the residual shows and what the term explains (findings only).
    """

    effect: str
    round: int
    testable: str
    params: dict[str, float]
    rms_um: float
    bic_delta: float
    heldout_rms_before_um: float
    heldout_rms_after_um: float
    eligible: bool
    fit: Fit | None = None
    heldout: HeldOut | None = None
    evidence: str = ""
    gain_se: float = math.nan
    implausible: str = ""
    gain_override: float = math.nan

    @property
    def gain(self) -> float:
        """Held-out RMS before / after."""
        if math.isfinite(self.gain_override):
            return self.gain_override
        if not (self.heldout_rms_after_um > 0):
            return math.nan
        return self.heldout_rms_before_um / self.heldout_rms_after_um


@dataclass(frozen=True, eq=False)
class AuditResult:
    """Everything the audit found.

    Attributes
    ----------
    cause
        ``none``, an effect id, or ``unexplained``.
    findings
        Accepted candidates in the order found (the first is the cause).
    rounds
        Every candidate's numbers, per round.
    base_kind
        ``thesis`` or ``ode``.
    base_fit, base_heldout
        The baseline's training fit and held-out residuals.
    final_fit, final_heldout
        The model with all findings.
    noise_floor_um, noise_per_experiment_um
        From high-order differences of the measured positions.
    heldout_method
        How the held-out error was measured.
    data, geo, val_geo
        The data (training and, with ``--validate``, validation).
    base_structure, final_structure
        Residual structure of the baseline and of the final model (training data).
    notes
        Warnings and remarks.
    seconds
        Wall time.
    outside
        The model-free checks (switching, drift in voltage holds, lost sensitivity).
    degeneracy
        What the data cannot determine about the baseline.
    withheld
        Findings of the forward selection not named because the baseline is undetermined
        (eligible on held-out data, but on a model that cannot carry a cause). ``piezod
        calibrate``'s adoption still tries them on its own model, which judges them on held-out
        data (:func:`piezod.stagecal.audit_and_extend`).
    """

    cause: str
    findings: tuple[CandidateResult, ...]
    rounds: tuple[tuple[CandidateResult, ...], ...]
    base_kind: str
    base_fit: Fit
    base_heldout: HeldOut
    final_fit: Fit
    final_heldout: HeldOut
    noise_floor_um: float
    noise_per_experiment_um: F64
    heldout_method: str
    data: audit_data.AuditData
    geo: Geometry
    val_geo: Geometry | None
    options: AuditOptions
    base_structure: Structure
    final_structure: Structure
    notes: tuple[str, ...] = field(default=())
    seconds: float = 0.0
    outside: Outside = field(default_factory=Outside)
    degeneracy: Degeneracy | None = None
    withheld: tuple[CandidateResult, ...] = ()

    @property
    def baseline_name(self) -> str:
        """``thesis (3.8)`` or ``hysteresis ODE (2.21)``."""
        return "thesis (3.8)" if self.base_kind == THESIS else "hysteresis ODE (2.21)"

    @property
    def structure_ratio(self) -> float:
        """Baseline training RMS over the noise floor."""
        return self.base_fit.rms_um / self.noise_floor_um if self.noise_floor_um > 0 else math.inf

    @property
    def final_structure_ratio(self) -> float:
        """Training RMS of the final model over the noise floor."""
        return self.final_fit.rms_um / self.noise_floor_um if self.noise_floor_um > 0 else math.inf

    @property
    def candidates(self) -> tuple[CandidateResult, ...]:
        """First-round numbers of every candidate (each added alone to the baseline)."""
        return self.rounds[0] if self.rounds else ()


#: Baseline RMS over the noise floor above which the ODE baseline is tried for triangular scans.
_TRY_ODE_RATIO = 3.0


def _distinct(values: F64, rel: float = 0.05) -> int:
    """Number of distinct values (relative spacing above ``rel`` in log)."""
    lv = np.sort(np.log(np.abs(values[values != 0])))
    return int(1 + np.count_nonzero(np.diff(lv) > rel)) if lv.size else 0


def _choose_base(train: Sequence[ScanInfo], val: Sequence[ScanInfo], forced: str | None) -> str:
    if forced is not None:
        if forced not in (THESIS, ODE):
            raise CalibrationError(f"unknown baseline {forced!r}; choose thesis or ode")
        return forced
    if not all(i.is_scan for i in (*train, *val)):
        return ODE
    ranges = np.array([i.v_max - i.v_min for i in train])
    return THESIS if _distinct(ranges) >= 2 else ODE


def _scales(data: audit_data.AuditData, x_model: F64) -> Scales:
    t0, t1 = float(data.t_s.min()), float(data.t_s.max())
    f = data.per_experiment("frequency_hz")
    fp = f[np.isfinite(f) & (f > 0)]
    f_ref = float(np.exp(np.mean(np.log(fp)))) if fp.size else 1.0
    dt = data.per_experiment("dt_s")
    periods = 1.0 / fp if fp.size else np.array([200.0 * float(dt.max())])
    span = max(t1 - t0, float(dt.max()))
    # Log creep: relaxation times from a few samples to far beyond the session (the slowest ones
    # show as a slow drift after the stage left its rest at the start of the recording).
    tau_lo = max(2.0 * float(dt.min()), 1e-3)
    taus = 10.0 ** np.arange(
        math.ceil(3 * math.log10(tau_lo)) / 3, math.log10(100.0 * span) + 1e-9, 1.0 / 3.0
    )
    return Scales(
        t_ref_s=0.5 * (t0 + t1),
        session_s=span,
        f_ref_hz=f_ref,
        x_scale_um=max(float(np.max(np.abs(x_model))), 1e-9),
        min_period_s=float(np.min(periods)),
        max_rate_hz=float(1.0 / dt.min()),
        max_line_hz=float(fp.max()) if fp.size else 0.0,
        has_negative_voltage=bool(np.any(data.voltage_v < 0)),
        creep_taus_s=taus,
    )


def run_audit(
    experiments: Sequence[Experiment],
    validate: Sequence[Experiment] = (),
    *,
    options: AuditOptions | None = None,
    on_step: Callable[[str], None] | None = None,
) -> AuditResult:
    """Audit the model against measured experiments.

    Parameters
    ----------
    experiments
        Training experiments (one axis).
    validate
        Held-out experiments (``--validate``); without them the held-out error comes from a
        k-fold split over experiments, or a blocked split in time of a single recording.
    options
        Thresholds and settings.
    on_step
        Called with a short label after every fit (progress display).

    Raises
    ------
    PiezodError
        Unusable data (no experiments, a baseline that cannot be fitted).
    """
    t_start = time.perf_counter()
    opts = options or AuditOptions()
    unknown = [e for e in (*opts.effects, *opts.base_effects) if e not in EFFECTS]
    if unknown:
        raise PiezodError(f"unknown effect(s) {', '.join(unknown)}; choose from {', '.join(EFFECTS)}")
    step = on_step or (lambda _s: None)
    notes: list[str] = []
    experiments, clipped = within_sensor_range(experiments)
    validate, clipped_val = within_sensor_range(validate) if validate else ([], None)
    experiments, aligned = align_known_delay(experiments)
    validate, aligned_val = align_known_delay(validate)
    notes.extend(n for n in (clipped, clipped_val, aligned, aligned_val) if n)
    outside = check_outside(experiments)
    for e in experiments:
        gap = e.metadata.get("gap_before_s")
        if gap is not None:
            where = f" ({e.path}:{e.first_line})" if e.path and e.first_line else ""
            notes.append(
                f"gap of {gap} s in t before {e.label}{where}: {e.metadata.get('split_from', '')} was split "
                "there into separate experiments (nothing interpolated across the gap)"
            )
    scans = [e.scan() for e in experiments]
    val_scans = [e.scan() for e in validate]
    kind = _choose_base(scans, val_scans, opts.base)
    # Triangular scans start at a turning point after settling: no prefix to drop (a one-period
    # record starts inside a half period, maybe on the initial curve: it settles).
    settle = not all(i.is_scan and not i.wraps for i in (*scans, *val_scans))
    blocks = opts.folds if (len(experiments) == 1 and not validate) else 1
    data = audit_data.build(experiments, blocks=blocks, settle=settle, scans=scans)
    val = audit_data.build(validate, settle=settle, scans=val_scans) if validate else None
    rows = data.fit_mask

    def start_fit(which: str) -> tuple[Fit, Scales]:
        if which == ODE:
            base: ThesisBase | OdeBase
            try:
                base, z0 = ode_start(data)
            except CalibrationError as exc:
                span = float(np.ptp(data.voltage_v))
                if not span > 0:
                    raise
                # No actuator loop to start from (a butterfly, a loop without opening): fit from
                # a nearly linear one; the degeneracy check says what the data do not determine.
                notes.append(f"baseline start: {exc}; fitted from a nearly linear start")
                base = OdeBase(alpha_bounds=(1e-4 / span, 60.0 / span))
                slope = abs(float(np.polyfit(data.voltage_v, data.position_um, 1)[0])) + 1e-9
                z0 = np.array([math.log(1e-2 / span), slope, 1e-6 * slope / span])
        else:
            base, z0, warns = thesis_start(list(experiments))
            notes.extend(warns)
        sc = _scales(data, np.ones(1))
        geo_fit = geometry(data, sc.t_ref_s, sc.f_ref_hz)
        fit = Problem(AuditModel(base, (), sc), geo_fit, rows).fit(z0)
        # The candidates' scales refer to the fitted baseline (its largest excursion).
        x_fit, _ = fit.model.evaluate(fit.p, geo_fit)
        sc = _scales(data, x_fit)
        return replace(fit, model=AuditModel(base, (), sc)), sc

    base_fit, scales = start_fit(kind)
    step("baseline")
    floor, per_exp = noise_floor_data(data)
    if kind == THESIS and opts.base is None and base_fit.rms_um > _TRY_ODE_RATIO * floor:
        # Far above the noise: a stage with memory (transients after range or offset changes)
        # may be described better by the ODE through every experiment.
        ode_fit, ode_scales = start_fit(ODE)
        step("ODE baseline")
        if ode_fit.bic < base_fit.bic:
            notes.append(
                "baseline: the hysteresis ODE (2.21) fits better than (3.8) "
                f"(BIC {ode_fit.bic - base_fit.bic:+.4g}): the loops carry memory of earlier scans"
            )
            kind, base_fit, scales = ODE, ode_fit, ode_scales
    if kind == ODE:
        notes.insert(
            0, "baseline: hysteresis ODE (2.21), shared alpha, b, u; per-experiment offset and initial state"
        )
    else:
        notes.insert(0, "baseline: thesis model (3.8), 7 parameters; per-experiment offset")
    geo = geometry(data, scales.t_ref_s, scales.f_ref_hz)
    for effect in opts.base_effects:
        if effect == "creep" and kind == THESIS:
            continue  # (3.8) has its creep factor (3.5)
        cand = make_candidate(effect, kind)
        why = cand.testable(scales)
        if why:
            notes.append(f"baseline: without {effect} ({why})")
            continue
        base_fit = fit_candidate(Problem(base_fit.model.with_candidate(cand), geo, rows), base_fit, cand)
        _, public = base_fit.model.public(base_fit.p)
        values = ", ".join(f"{k} {v:.4g}" for k, v in public[effect].items())
        notes.append(f"baseline: + {effect} ({values}), part of the model the findings extend")
        step(f"baseline + {effect}")
    val_geo = geometry(val, scales.t_ref_s, scales.f_ref_hz) if val is not None else None
    if val_geo is not None:
        method = f"validation recordings ({val_geo.data.n_experiments} experiments)"
    elif data.blocked:
        method = f"blocked split in time ({data.n_segments} blocks of one recording)"
    else:
        method = f"{min(opts.folds, data.n_segments)}-fold cross-validation over experiments"
    folds = folds_of(data.n_segments, opts.folds)
    if data.n_segments < 2 and val_geo is None:
        raise CalibrationError("the held-out test needs at least two experiments or time blocks")

    def heldout(fit: Fit) -> HeldOut:
        if val_geo is not None:
            return heldout_validate(fit.model, val_geo, fit)
        return heldout_cv(fit.model, geo, fit, folds, refit=opts.refit_cv, max_nfev=opts.cv_nfev)

    base_ho = heldout(base_fit)
    step("baseline held-out")
    degeneracy = check_degeneracy(base_fit, geo, rows)
    if isinstance(base_fit.model.base, OdeBase):
        rayleigh = rayleigh_note(
            base_fit.model.public(base_fit.p)[0], float(np.max(geo.v_max) - np.min(geo.v_min))
        )
        if rayleigh:
            notes.append(rayleigh)
    if degeneracy.absent:
        notes.append(
            f"baseline: {', '.join(degeneracy.absent)} left out (the fit made their term constant "
            "over the data): the baseline's determination is judged without them"
        )
    current, current_ho = base_fit, base_ho
    rounds: list[tuple[CandidateResult, ...]] = []
    findings: list[CandidateResult] = []
    pre: list[CandidateResult] = []
    remaining = [e for e in opts.effects if e not in opts.base_effects]
    stop = ""
    if outside.switching is not None:
        stop = "switching"
        notes.append(f"switching: {outside.switching.text}")
    drift = outside.drift
    if drift is not None:
        bad = physically_implausible("drift", {"rate_nm_per_s": drift.rate_nm_per_s}, scales)
        if drift.significant and not bad and "drift" in remaining:
            pre.append(
                CandidateResult(
                    effect="drift",
                    round=0,
                    testable="",
                    params={"rate_nm_per_s": drift.rate_nm_per_s, "rate_se_nm_per_s": drift.rate_se_nm_per_s},
                    rms_um=math.nan,
                    bic_delta=drift.bic_delta,
                    heldout_rms_before_um=math.nan,
                    heldout_rms_after_um=math.nan,
                    eligible=True,
                    evidence=drift.text,
                    gain_se=drift.gain_se,
                    implausible=bad,
                    gain_override=drift.gain,
                )
            )
            remaining.remove("drift")
        else:
            notes.append(f"voltage holds: {drift.text}" + (f"; {bad}" if bad else "; not significant"))
            held = sum(b - a for _, a, b in outside.holds)
            total = sum(len(e) for e in experiments)
            if "drift" in remaining and held >= 0.5 * total:
                # Mostly holds: the hold analysis (log creep of the step + a line, per hold) is
                # the measurement of drift; a drift term on the actuator model would take the
                # creep's departure from a log law for a drift.
                remaining.remove("drift")
                notes.append(
                    f"drift is judged in the voltage holds ({100.0 * held / total:.0f} % of the samples), "
                    "not by a drift term on the actuator model"
                )
    for rnd in range(1, 0 if stop else opts.max_findings + 1):
        results: list[CandidateResult] = []
        for effect in remaining:
            cand = make_candidate(effect, kind)
            why = cand.testable(scales)
            if why:
                results.append(
                    CandidateResult(
                        effect, rnd, why, {}, math.nan, math.nan, current_ho.rms_um, math.nan, False
                    )
                )
                continue
            res = _try(cand, current, current_ho, geo, rows, heldout, opts, rnd, floor)
            results.append(res)
            step(f"round {rnd}: {effect}")
        rounds.append(tuple(results))
        eligible = [r for r in results if r.eligible]
        if not eligible:
            break
        ringing = None
        if any(r.effect == "resonance" for r in eligible):
            rc = make_candidate("resonance", kind)
            assert isinstance(rc, Resonance)
            lo, hi = rc._f_range(scales)
            ringing = spectral_peak(geo, rows, current.residual, lo, hi)
        best = _best(eligible, ringing)
        findings.append(best)
        assert best.fit is not None and best.heldout is not None
        current, current_ho = best.fit, best.heldout
        remaining.remove(best.effect)
        if not remaining:
            break

    ratio = base_fit.rms_um / floor if floor > 0 else math.inf
    f_hi = 0.45 * scales.max_rate_hz

    def struct(fit: Fit) -> Structure:
        x, _ = fit.model.evaluate(fit.p, geo)
        return structure(geo, rows, fit.residual, x, floor, f_hi)

    base_struct = struct(base_fit)
    before = base_struct
    explained: list[CandidateResult] = []
    for k, f in enumerate(findings):
        others = [
            r for r in rounds[k] if r.effect != f.effect and r.fit is not None and math.isfinite(r.gain)
        ]
        runner = max(others, key=lambda r: r.gain) if others else None
        assert f.fit is not None
        text = evidence(
            f.effect,
            f.params,
            before,
            f.gain,
            f.bic_delta,
            f.heldout_rms_before_um,
            f.heldout_rms_after_um,
            None if runner is None else (runner.effect, runner.gain, runner.testable),
            data,
        )
        explained.append(replace(f, evidence=text))
        before = struct(f.fit)
    findings = pre + explained
    loss = outside.loss
    if loss is not None:
        findings.append(
            CandidateResult(
                effect="sensitivity_loss",
                round=0,
                testable="",
                params={"loss_pct": loss.loss_pct, "after_peak_v": loss.peak_v},
                rms_um=math.nan,
                bic_delta=math.nan,
                heldout_rms_before_um=math.nan,
                heldout_rms_after_um=math.nan,
                eligible=True,
                evidence=loss.text,
            )
        )
    for path, g in base_ho.gains.items():
        if abs(g - 1.0) > 0.1:
            findings.append(
                CandidateResult(
                    effect="sensitivity_loss" if g < 1.0 else "sensitivity_gain",
                    round=0,
                    testable="",
                    params={"change_pct": 100.0 * (g - 1.0)},
                    rms_um=math.nan,
                    bic_delta=math.nan,
                    heldout_rms_before_um=math.nan,
                    heldout_rms_after_um=math.nan,
                    eligible=True,
                    evidence=(
                        f"the validation session {path} has {100.0 * (g - 1.0):+.3g} % of the training "
                        "session's sensitivity (fitted as its sensor gain)"
                    ),
                )
            )
    final_struct = before
    withheld: tuple[CandidateResult, ...] = ()
    if not stop and degeneracy.degenerate and (findings or ratio > opts.structure_max):
        # The baseline alone is undetermined; a model with findings may be determined (an
        # effect the baseline tried to absorb). No cause is named on an undetermined model.
        final_deg = check_degeneracy(current, geo, rows) if current is not base_fit else degeneracy
        if final_deg.degenerate and (final_deg.blocks_a_cause or not findings):
            degeneracy = final_deg
            # Model-free findings (round 0: drift in the voltage holds, a sensitivity loss)
            # are measured without the actuator model and stand on an undetermined one.
            free = [f for f in findings if f.round == 0]
            withheld = tuple(f for f in findings if f.round != 0)
            if free:
                notes.append(
                    final_deg.text.split(". No cause")[0]
                    + ". The model-free findings ("
                    + ", ".join(f.effect for f in free)
                    + ") do not use it"
                )
            else:
                stop = "undetermined"
                notes.append(final_deg.text)
            if withheld:
                notes.append("not named on the undetermined model: " + ", ".join(f.effect for f in withheld))
            findings = free
        else:
            told = (final_deg if final_deg.degenerate else degeneracy).text.split(". No cause")[0]
            notes.append(
                f"{told}. The findings do not depend on it (their parameters correlate with the "
                f"baseline's by at most {final_deg.extension_correlation:.3g})"
            )
            degeneracy = final_deg
    elif not stop and degeneracy.degenerate:
        notes.append(degeneracy.text.split(". No cause")[0] + ". Nothing above the noise needs a cause.")
    if stop:
        cause = stop
    elif findings:
        cause = findings[0].effect
        final_ratio = current.rms_um / floor if floor > 0 else math.inf
        if final_ratio > opts.structure_max:
            notes.append(
                f"structure remains after the findings: residual {current.rms_um:.4g} um is "
                f"{final_ratio:.2f} x the noise floor {floor:.4g} um"
            )
    elif ratio > opts.structure_max:
        cause = "unexplained"
    else:
        cause = "none"
    return AuditResult(
        cause=cause,
        findings=tuple(findings),
        rounds=tuple(rounds),
        base_kind=kind,
        base_fit=base_fit,
        base_heldout=base_ho,
        final_fit=current,
        final_heldout=current_ho,
        noise_floor_um=floor,
        noise_per_experiment_um=per_exp,
        heldout_method=method,
        data=data,
        geo=geo,
        val_geo=val_geo,
        options=opts,
        base_structure=base_struct,
        final_structure=final_struct,
        notes=tuple(notes),
        seconds=time.perf_counter() - t_start,
        outside=outside,
        degeneracy=degeneracy,
        withheld=withheld,
    )


def _best(eligible: Sequence[CandidateResult], ringing_hz: float | None) -> CandidateResult:
    """The eligible candidate with the largest held-out gain; a lag before an unproven resonance.

    A resonance is proven by ringing: a peak of the residual spectrum right after the voltage
    reversals (``ringing_hz``) within 20 % of its ``f0``. Without it, a resonance acts as a lag
    (far below ``f0`` the two have the same phase): when a ``delay`` is eligible with a gain
    within the resonance's standard error, the lag is named.
    """
    best = max(eligible, key=lambda r: (r.gain, -r.bic_delta))
    if best.effect == "resonance":
        f0 = best.params.get("f0_hz", math.nan)
        rings = ringing_hz is not None and abs(f0 / ringing_hz - 1.0) < 0.2
        lag = [r for r in eligible if r.effect == "delay"]
        se = best.gain_se if math.isfinite(best.gain_se) else 0.0
        if lag and not rings and best.gain - lag[0].gain <= se:
            return lag[0]
    return best


def _try(
    cand: Candidate,
    current: Fit,
    current_ho: HeldOut,
    geo: Geometry,
    rows: NDArray[np.bool_],
    heldout: Callable[[Fit], HeldOut],
    opts: AuditOptions,
    rnd: int,
    floor: float,
) -> CandidateResult:
    model = current.model.with_candidate(cand)
    fit = fit_candidate(Problem(model, geo, rows), current, cand)
    bic_delta = fit.bic - current.bic
    ho = heldout(fit)
    _, params = model.public(fit.p)
    gain, se = gain_with_se(current_ho, ho)
    bad = physically_implausible(cand.effect, params[cand.effect], model.scales)
    why = bad or cand.implausible(fit.p[model.slices()[cand.effect]], model.scales)
    excess = current_ho.rms_um**2 - (floor**2 if math.isfinite(floor) else 0.0)
    explained = (current_ho.rms_um**2 - ho.rms_um**2) / excess if excess > 0 else math.inf
    if not why and explained < opts.explain_min:
        why = f"explains only {100.0 * explained:.2g} % of the held-out variance above the noise"
    if not why and math.isfinite(se) and gain - 1.0 <= opts.gain_sigmas * se:
        why = f"gain {gain:.4g} +- {se:.2g} not {opts.gain_sigmas:g} standard errors above 1"
    eligible = bic_delta < -opts.bic_min and gain >= opts.gain_min and not why
    return CandidateResult(
        effect=cand.effect,
        round=rnd,
        testable=why,
        params=params[cand.effect],
        rms_um=fit.rms_um,
        bic_delta=bic_delta,
        heldout_rms_before_um=current_ho.rms_um,
        heldout_rms_after_um=ho.rms_um,
        eligible=eligible,
        fit=fit,
        heldout=ho,
        gain_se=se,
        implausible=bad,
    )
