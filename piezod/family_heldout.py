"""Every member of the model family scored on held-out data of measured recordings.

The question a lab asks of its own recordings (or of someone else's): *which model predicts what
it was not fitted to, and how close to the sensor noise does it get?* :func:`compare_family` fits
every law of the family (:data:`piezod.calibrate_family.LAWS`) with every creep driver on the
training recordings (:func:`piezod.calibrate_family.fit_family`: hysteresis law, creep spectrum,
stiffness, drive lag) and scores each on held-out data, split the way the audit splits it:

* ``--validate`` recordings: the members are fitted on all training recordings and run through
  the validation session from rest; per experiment a position offset and per validation file one
  sensor gain are nuisance parameters (a separate session, as
  :func:`piezod.audit.fitting.heldout_validate`);
* several experiments: every :data:`HOLDOUT_EVERY`-th experiment is held out (the last one when
  there are fewer), the others fitted, the model run through the whole session;
* one recording: it is cut into ``blocks`` contiguous time blocks (the model still runs through
  all of them without a break) and every :data:`HOLDOUT_EVERY`-th block is held out.

The first :data:`SKIP_S` seconds of every experiment (at most :data:`SKIP_FRACTION` of it) are
left out of the fits and the scores: the stage's state before a recording is unknown.

A readback delay the recordings document (``sensor_delay_s`` metadata) is aligned first
(:func:`piezod.readback.align_known_delay`).

The best member is then refitted without each of its parts (:data:`PARTS`: the static stiffness
map, the creep spectrum, the drive lag) and each part's held-out gain measured
(:class:`PartGain`). :func:`check_findings` holds the audit's findings against those parts, and
:func:`audit_with_family` runs the audit, the family and the check together, dropping a
candidate the better model contradicts (what ``piezod audit`` does).

Used by ``piezod audit`` (the family table, the part gains, ``best_model``) and by ``piezod
calibrate`` on recordings (``--model family``).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.audit import AuditOptions, AuditResult, run_audit
from piezod.audit.fitting import HeldOut, gain_with_se
from piezod.audit.residuals import pooled_noise_floor
from piezod.calibrate_data import DynamicCalibrationData, prepare_dynamic
from piezod.calibrate_family import (
    AFTER_EFFECT_LAWS,
    CHOICE_TIE_FRACTION,
    CREEP_DRIVERS,
    DEFAULT_PLAYS,
    LAWS,
    FamilyFit,
    fit_family,
    holdout_mask,
    member_name,
    session_positions,
    settled_rows,
)
from piezod.errors import CalibrationError
from piezod.model.aftereffect import AfterEffect
from piezod.model.family import FamilyParams
from piezod.model.params import ThesisParams
from piezod.readback import align_known_delay
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: The laws ``piezod audit`` scores by default: the Bouc-Wen law's rate search takes minutes on a
#: full calibration frame (over 4 min of CPU on a 34-experiment frame of 1.9 M samples, where the
#: play law took 6 s and the generalised play law 45 s) and is there with ``--family-laws``.
AUDIT_LAWS: tuple[str, ...] = ("prandtl-ishlinskii", "generalised-play", "coleman-hodgdon")
#: Every this-many-th experiment (or time block) is held out.
HOLDOUT_EVERY = 4
#: Start-up time left out of every experiment's fit and score (s) ...
SKIP_S = 1.0
#: ... but never more than this fraction of the experiment.
SKIP_FRACTION = 0.1
#: Time blocks of a single recording (the audit's default folds).
DEFAULT_BLOCKS = 5
#: Grid density of the family's session (samples per loop / per non-periodic experiment, at most).
MAX_SAMPLES_PER_LOOP = 512
MAX_SAMPLES_PER_EXPERIMENT = 1 << 14


@dataclass(frozen=True)
class MemberScore:
    """One member of the family on the held-out data.

    Attributes
    ----------
    name
        ``family/<law>`` (position-driven creep) or ``family/<law>/voltage-creep``.
    law, creep_driver
        The member.
    train_rms_um, heldout_rms_um
        RMS of the training fit and of the held-out prediction (nan when the fit failed).
    params
        The fitted model (None when the fit failed).
    error
        Why the fit failed (None when it did not).
    """

    name: str
    law: str
    creep_driver: str
    train_rms_um: float
    heldout_rms_um: float
    params: FamilyParams | None = None
    error: str | None = None

    def to_json(self, floor_um: float) -> dict[str, Any]:
        """JSON of the member (``ratio_to_noise_floor``: held-out RMS over ``floor_um``)."""
        p = self.params
        return {
            "name": self.name,
            "law": self.law,
            "creep_driver": self.creep_driver,
            "train_rms_um": _num(self.train_rms_um),
            "heldout_rms_um": _num(self.heldout_rms_um),
            "ratio_to_noise_floor": _num(self.heldout_rms_um / floor_um) if floor_um > 0 else None,
            "lag_ms": None if p is None else 1e3 * p.lag_time_constant_s,
            "stiffness_pct_per_um": None if p is None else p.stiffness_pct_per_um,
            "creep_total_pct": None if p is None else 100.0 * p.creep.total_creep,
            "error": self.error,
        }


#: The parts of a member whose worth :func:`compare_family` measures on the held-out data (audit
#: effect ids): the static stiffness map, the creep spectrum, the drive lag, each left out in turn
#: (:func:`~piezod.calibrate_family.fit_family`'s ``fit_stiffness``, ``fit_creep``, ``fit_lag``).
PARTS: tuple[str, ...] = ("stiffness", "creep", "delay")


@dataclass(frozen=True)
class PartGain:
    """What one part of the best member is worth on the held-out data.

    Attributes
    ----------
    effect
        The audit's effect id of the part: ``stiffness`` (the static map), ``creep`` (the creep
        spectrum), ``delay`` (the drive lag).
    heldout_rms_without_um
        Held-out RMS of the member refitted without the part.
    gain, gain_se
        ``RMS without / RMS with`` and its standard error (block jackknife of the held-out
        residuals, :func:`piezod.audit.fitting.gain_with_se`).
    material
        The gain passes the audit's rule (at least ``gain_min`` and more than ``gain_sigmas``
        standard errors above 1, :class:`piezod.audit.AuditOptions`).
    error
        Why the member could not be refitted without the part (None when it could); such a part
        checks no finding.
    """

    effect: str
    heldout_rms_without_um: float
    gain: float
    gain_se: float
    material: bool
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON of the part's gain."""
        return {
            "effect": self.effect,
            "heldout_rms_without_um": _num(self.heldout_rms_without_um),
            "gain": _num(self.gain),
            "gain_se": _num(self.gain_se),
            "material": self.material,
            "error": self.error,
        }


@dataclass(frozen=True)
class FamilyComparison:
    """The outcome of :func:`compare_family`.

    Attributes
    ----------
    method
        How the held-out data were chosen (one line).
    members
        Every member, in the order fitted.
    noise_floor_um
        Sensor noise floor of the held-out data (third differences,
        :func:`piezod.audit.residuals.noise_floor`, pooled over experiments).
    skip_s
        Start-up time left out of every experiment.
    heldout
        Labels of the held-out experiments or blocks.
    gains
        Per validation file, the best member's fitted sensor gain (validation only).
    parts
        What each part of the best member (:data:`PARTS`) is worth on the held-out data.
    others
        Held-out RMS of the models passed as ``others`` to :func:`compare_family` (or scored on
        its split afterwards, e.g. :func:`thesis_heldout_rms`).
    fitted_on
        What each of ``others`` was fitted on, when not all the training data.
    """

    method: str
    members: tuple[MemberScore, ...]
    noise_floor_um: float
    skip_s: float
    heldout: tuple[str, ...]
    gains: dict[str, float] = field(default_factory=dict)
    parts: tuple[PartGain, ...] = ()
    others: dict[str, float] = field(default_factory=dict)
    fitted_on: dict[str, str] = field(default_factory=dict)

    def part(self, effect: str) -> PartGain | None:
        """The best member's part for ``effect`` (None when not measured)."""
        return next((p for p in self.parts if p.effect == effect), None)

    @property
    def best(self) -> MemberScore | None:
        """The member with the smallest held-out RMS; within :data:`CHOICE_TIE_FRACTION` of it, the
        simpler law (earlier in :data:`~piezod.calibrate_family.LAWS`) and position-driven creep."""
        ok = [m for m in self.members if math.isfinite(m.heldout_rms_um)]
        if not ok:
            return None
        limit = min(m.heldout_rms_um for m in ok) * (1.0 + CHOICE_TIE_FRACTION)
        return next(m for m in ok if m.heldout_rms_um <= limit)

    def table(self) -> str:
        """One line per member: training and held-out RMS, the ratio to the noise floor, the best marked."""
        best = self.best
        floor = self.noise_floor_um
        lines = [
            f"{'member':<42} {'train RMS um':>13} {'held-out RMS um':>16} {'/ noise':>8} {'lag ms':>7}"
            f" {'k %/um':>7}"
        ]
        for m in self.members:
            if m.params is None:
                lines.append(f"{m.name:<42} {'failed':>13} {'-':>16}  ({m.error})")
                continue
            mark = "  <- best" if best is not None and m.name == best.name else ""
            ratio = m.heldout_rms_um / floor if floor > 0 else math.inf
            lines.append(
                f"{m.name:<42} {m.train_rms_um:>13.4f} {m.heldout_rms_um:>16.4f} {ratio:>8.2f}"
                f" {1e3 * m.params.lag_time_constant_s:>7.2f} {m.params.stiffness_pct_per_um:>7.3f}{mark}"
            )
        for name, rms in self.others.items():
            ratio = rms / floor if floor > 0 else math.inf
            label = f"{name} (fitted on {self.fitted_on.get(name, 'all')})"
            lines.append(f"{label:<42} {'':>13} {rms:>16.4f} {ratio:>8.2f}")
        lines.append(f"{'noise floor of the held-out data':<42} {'':>13} {floor:>16.4f}")
        for p in self.parts:
            if p.error is not None:
                lines.append(f"  without its {p.effect:<9} not measured ({p.error})")
                continue
            mark = "material" if p.material else "not material"
            lines.append(
                f"  without its {p.effect:<9} held-out RMS {p.heldout_rms_without_um:.4f} um: gain "
                f"{p.gain:.3g} +- {p.gain_se:.2g} ({mark})"
            )
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        """JSON of the comparison (``best``: the best member's name, or None)."""
        best = self.best
        return {
            "method": self.method,
            "noise_floor_um": _num(self.noise_floor_um),
            "skip_s": self.skip_s,
            "heldout": list(self.heldout),
            "members": [m.to_json(self.noise_floor_um) for m in self.members],
            "best": None if best is None else best.name,
            "gains": self.gains,
            "parts": [p.to_json() for p in self.parts],
            "others": {k: _num(v) for k, v in self.others.items()},
            "others_fitted_on": {k: self.fitted_on.get(k, "all") for k in self.others},
        }


def best_model(
    comparison: FamilyComparison | None, audit_name: str, audit_heldout_rms_um: float, audit_floor_um: float
) -> dict[str, Any]:
    """The model that predicts the held-out data best: the audit's own (baseline and findings) or
    the family's best member. Keys ``name``, ``heldout_rms_um``, ``noise_floor_um`` (of the data
    the RMS is on) and ``ratio_to_noise_floor``; ``source`` is ``audit`` or ``family``."""
    rows = [("audit", audit_name, audit_heldout_rms_um, audit_floor_um)]
    best = None if comparison is None else comparison.best
    if comparison is not None and best is not None:
        rows.append(("family", best.name, best.heldout_rms_um, comparison.noise_floor_um))
    finite = [r for r in rows if math.isfinite(r[2])] or rows
    source, name, rms, floor = min(finite, key=lambda r: r[2] if math.isfinite(r[2]) else math.inf)
    return {
        "source": source,
        "name": name,
        "heldout_rms_um": _num(rms),
        "noise_floor_um": _num(floor),
        "ratio_to_noise_floor": _num(rms / floor) if floor > 0 else None,
    }


#: A finding the family's best member contains is confirmed when the member's own value is at
#: least this fraction of the finding's (same sign).
CONFIRM_FRACTION = 1.0 / 3.0


def check_findings(
    comparison: FamilyComparison | None, findings: Sequence[Any], audit_heldout_rms_um: float
) -> list[dict[str, Any]]:
    """The audit's findings that the family's best member also has a part for, checked against it.

    The audit names effects against its own baseline (the thesis model or the hysteresis ODE);
    when that baseline's law is not the stage's, a candidate may take the misfit (on the real
    P-885 stack the ODE's loop is narrower than the stack's and a first-order lag of 11 ms widens
    it). When the family's best member predicts the held-out data better than the audit's model,
    the findings it has a part for (:data:`PARTS`: ``delay`` its drive lag, ``stiffness`` its
    static map, ``creep`` its creep spectrum) are ``confirmed`` when that part is material on the
    held-out data (:attr:`PartGain.material`) and, for ``delay`` and ``stiffness``, the member's
    own value has the finding's sign and at least :data:`CONFIRM_FRACTION` of its size.

    Parameters
    ----------
    comparison
        :func:`compare_family`'s result.
    findings
        The audit's findings (:class:`piezod.audit.CandidateResult`).
    audit_heldout_rms_um
        The audit's final model's held-out RMS.

    Returns
    -------
    list of dict
        Per checked finding: ``effect``, ``finding`` and ``member`` values (``unit``), the part's
        held-out ``gain`` and ``gain_se``, ``confirmed`` and a one-line ``text``.
    """
    best = None if comparison is None else comparison.best
    if comparison is None or best is None or best.params is None:
        return []
    if not best.heldout_rms_um < audit_heldout_rms_um:
        return []
    out: list[dict[str, Any]] = []
    for f in findings:
        part = comparison.part(f.effect)
        if part is None or part.error is not None:
            continue
        if f.effect == "delay":
            value = 1e3 * (
                float(f.params.get("delay_s", 0.0)) + float(f.params.get("lag_time_constant_s", 0.0))
            )
            member, unit, what = 1e3 * best.params.lag_time_constant_s, "ms", "drive lag"
            sized = value != 0.0 and member / value >= CONFIRM_FRACTION
        elif f.effect == "stiffness":
            value = float(f.params.get("sensitivity_pct_per_um", 0.0))
            member, unit, what = best.params.stiffness_pct_per_um, "%/um", "static stiffness map"
            sized = value != 0.0 and member / value >= CONFIRM_FRACTION
        else:
            value = float(f.params.get("creep_pct_per_decade", math.nan))
            member, unit, what = 100.0 * best.params.creep.total_creep, "%", "creep spectrum"
            sized = True
        confirmed = part.material and sized
        if confirmed:
            verdict = "confirmed"
        elif not part.material:
            verdict = "not confirmed: the better model does not need it"
        else:
            verdict = "not confirmed: the better model needs far less of it"
        size = f"{member:.3g} {unit}" if f.effect != "creep" else f"{member:.3g} % in all"
        found = f"{value:.3g} {unit}" if f.effect != "creep" else f"{value:.3g} %/decade"
        text = (
            f"{f.effect} {found}: {verdict} ({best.name} predicts the held-out data "
            f"{audit_heldout_rms_um / best.heldout_rms_um:.2f} x better; its {what}, {size}, is worth a "
            f"held-out gain of {part.gain:.3g} +- {part.gain_se:.2g})"
        )
        out.append(
            {
                "effect": f.effect,
                "finding": _num(value),
                "member": _num(member),
                "unit": unit,
                "gain": _num(part.gain),
                "gain_se": _num(part.gain_se),
                "confirmed": confirmed,
                "text": text,
            }
        )
    return out


#: Most audits :func:`audit_with_family` runs (each rerun drops the candidates the family contradicted).
MAX_AUDIT_RUNS = 3


@dataclass(frozen=True)
class FamilyAudit:
    """The audit checked against the model family (:func:`audit_with_family`).

    Attributes
    ----------
    result
        The audit (rerun without the candidates the family contradicted, if any).
    family
        The family on the same held-out data (None when not scored).
    family_error
        Why the family was not scored ("" when it was, or was not asked for).
    checks
        :func:`check_findings` of every run, the rejected ones first.
    rejected
        Effects dropped from the candidates because a better-predicting member contradicted them.
    best
        :func:`best_model` of the final audit and the family.
    """

    result: AuditResult
    family: FamilyComparison | None
    family_error: str
    checks: tuple[dict[str, Any], ...]
    rejected: tuple[str, ...]
    best: dict[str, Any]


def audit_model_name(result: AuditResult) -> str:
    """``audit: <baseline> + <finding> + ...`` (the audit's final model)."""
    named = [f.effect for f in result.findings if f.round > 0]
    return " + ".join([f"audit: {result.baseline_name}", *named])


def audit_with_family(
    experiments: Sequence[Experiment],
    validate: Sequence[Experiment] = (),
    *,
    options: AuditOptions | None = None,
    family: bool = True,
    laws: Sequence[str] = AUDIT_LAWS,
    on_step: Callable[[str], None] | None = None,
) -> FamilyAudit:
    """The audit, the family on the same held-out data, and the findings checked against it.

    The audit (:func:`piezod.audit.run_audit`) names effects against its own baseline. The family
    (:func:`compare_family`) is scored on the same held-out split (``options.folds`` time blocks
    for a single recording). A finding that a member predicting the held-out data better
    contradicts (:func:`check_findings`: on the real P-885 stack a first-order lag of 11 ms that the
    play law, 2.7 x better, does not need) is not a cause: the audit is rerun without that candidate
    (at most :data:`MAX_AUDIT_RUNS` runs), and a note says why.

    Parameters
    ----------
    experiments, validate
        As for :func:`piezod.audit.run_audit`.
    options
        The audit's options.
    family
        Score the family (False: the audit alone, as :func:`~piezod.audit.run_audit`).
    laws
        The family's laws to score (both creep drivers each; default :data:`AUDIT_LAWS`).
    on_step
        Progress callback.
    """
    opts = options or AuditOptions()
    result = run_audit(experiments, validate, options=opts, on_step=on_step)
    comparison: FamilyComparison | None = None
    error = ""
    if family:
        try:
            comparison = compare_family(experiments, validate, blocks=opts.folds, laws=laws, on_step=on_step)
        except CalibrationError as exc:
            error = str(exc)
    dropped: list[dict[str, Any]] = []
    rejected: list[str] = []
    found: list[dict[str, Any]] = []
    for run in range(MAX_AUDIT_RUNS):
        named = [f for f in result.findings if f.round > 0]
        found = check_findings(comparison, named, result.final_heldout.rms_um)
        bad = [c for c in found if not c["confirmed"]]
        if not bad or run == MAX_AUDIT_RUNS - 1:
            break
        dropped.extend(bad)
        rejected.extend(c["effect"] for c in bad)
        opts = dataclasses.replace(opts, effects=tuple(e for e in opts.effects if e not in rejected))
        result = run_audit(experiments, validate, options=opts, on_step=on_step)
        result = dataclasses.replace(
            result, notes=(*result.notes, *(f"not a candidate: {c['text']}" for c in dropped))
        )
    checks = [*dropped, *found]
    name = audit_model_name(result)
    best = best_model(comparison, name, result.final_heldout.rms_um, result.noise_floor_um)
    return FamilyAudit(result, comparison, error, tuple(checks), tuple(rejected), best)


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _rms(resid: F64) -> float:
    return float(np.sqrt(np.mean(resid**2))) if resid.size else math.nan


def skip_for(experiments: Sequence[Experiment]) -> float:
    """Start-up time left out of every experiment: :data:`SKIP_S`, at most :data:`SKIP_FRACTION` of
    the shortest experiment."""
    shortest = min(float(e.t_s[-1] - e.t_s[0]) for e in experiments)
    return min(SKIP_S, SKIP_FRACTION * shortest)


def session(experiments: Sequence[Experiment]) -> DynamicCalibrationData:
    """The experiments laid out for the family fit, the stage at rest at the first voltage before."""
    first = min(experiments, key=lambda e: float(e.t_s[0]))
    return prepare_dynamic(
        experiments,
        max_samples_per_loop=MAX_SAMPLES_PER_LOOP,
        max_samples_per_experiment=MAX_SAMPLES_PER_EXPERIMENT,
        rest_voltage_v=float(first.voltage_v[0]),
    )


def time_blocks(experiment: Experiment, blocks: int) -> list[Experiment]:
    """``experiment`` cut into ``blocks`` contiguous experiments (labels ``<label>[i/blocks]``)."""
    edges = np.linspace(0, len(experiment), blocks + 1).round().astype(int)
    return [
        experiment.rows(slice(int(a), int(b)), label=f"{experiment.label}[{i + 1}/{blocks}]")
        for i, (a, b) in enumerate(itertools.pairwise(edges))
    ]


def heldout_mask(n: int, every: int = HOLDOUT_EVERY) -> NDArray[np.bool_]:
    """Training mask of ``n`` experiments: :func:`~piezod.calibrate_family.holdout_mask`, and the last
    one held out when ``n < every`` (that one holds out none)."""
    if n < 2:
        raise CalibrationError("the held-out test needs at least two experiments, time blocks or --validate")
    train = holdout_mask(n, every)
    if train.all():
        train[-1] = False
    return train


def prediction_error(
    data: DynamicCalibrationData, params: FamilyParams, rows: NDArray[np.bool_], group: NDArray[np.intp]
) -> tuple[F64, list[float]]:
    """Prediction minus measurement on ``rows`` of a session the model was not fitted to.

    One offset per experiment (centring) and one sensor gain per ``group`` (of the experiments:
    the validation file) are fitted; returns the residual on ``rows`` and the gains."""
    x = data.centred(session_positions(data, params))
    y = data.centred(data.position_um)
    g_row = group[np.repeat(np.arange(data.n_experiments), data.counts)]
    resid = np.empty(int(rows.sum()))
    gains: list[float] = []
    r_rows = np.flatnonzero(rows)
    for g in range(int(group.max()) + 1):
        sel = g_row[r_rows] == g
        idx = r_rows[sel]
        den = float(x[idx] @ x[idx])
        gain = float(x[idx] @ y[idx]) / den if den > 0 else 1.0
        resid[sel] = gain * x[idx] - y[idx]
        gains.append(gain)
    return resid, gains


def compare_family(
    experiments: Sequence[Experiment],
    validate: Sequence[Experiment] = (),
    *,
    blocks: int = DEFAULT_BLOCKS,
    laws: Sequence[str] = LAWS,
    creep_drivers: Sequence[str] = CREEP_DRIVERS,
    plays: int = DEFAULT_PLAYS,
    on_step: Callable[[str], None] | None = None,
    others: dict[str, FamilyParams] | None = None,
    parts: bool = True,
    after_effect: bool = False,
) -> FamilyComparison:
    """Fit every member of the family and score it on held-out data (module docstring).

    Parameters
    ----------
    experiments
        Training recordings (one axis).
    validate
        Held-out recordings; without them, held-out experiments or time blocks.
    blocks
        Time blocks of a single training recording (without ``validate``).
    laws, creep_drivers
        The members to fit.
    plays
        Play operators of the play laws.
    on_step
        Called with the member's name after every fit.
    others
        Models fitted elsewhere (e.g. the dynamic model, on all the training data), scored on the
        same held-out data as :attr:`FamilyComparison.others` (name -> held-out RMS); they take
        no part in :attr:`FamilyComparison.best`.
    parts
        Measure the best member's parts (:attr:`FamilyComparison.parts`: one refit per part; the
        audit's check needs them, the choice of a model does not).
    after_effect
        When the best member is the generalised play law with voltage-driven creep, also fit it
        with its memory's after-effect (:mod:`piezod.model.aftereffect`, searched; listed last, so
        it is best only by more than the tie fraction), as the model choice on the stage does.

    Raises
    ------
    CalibrationError
        Nothing to hold out (one experiment, ``blocks < 2``, no ``validate``).
    """
    step = on_step or (lambda _s: None)
    train_exps, _ = align_known_delay(experiments)
    validate, _ = align_known_delay(validate)
    if validate:
        skip = skip_for([*train_exps, *validate])
        train_data = session(train_exps)
        val_data = session(list(validate))
        train_mask = np.ones(train_data.n_experiments, dtype=bool)
        paths = [e.path or "" for e in val_data.experiments]
        keys = list(dict.fromkeys(paths))
        group = np.array([keys.index(p) for p in paths], dtype=np.intp)
        val_rows = settled_rows(val_data, skip)
        floor_exps = list(validate)
        method = f"validation recordings ({len(validate)} experiments)"
        heldout = tuple(e.label for e in validate)
    else:
        if len(train_exps) == 1:
            if blocks < 2:
                raise CalibrationError(
                    "the held-out test needs at least two experiments, time blocks or --validate"
                )
            train_exps = time_blocks(train_exps[0], blocks)
            method = (
                f"blocked split in time ({blocks} blocks of one recording, every {HOLDOUT_EVERY}th held out)"
            )
        else:
            method = f"held-out experiments (every {HOLDOUT_EVERY}th)"
        skip = skip_for(train_exps)
        train_data = session(train_exps)
        train_mask = heldout_mask(train_data.n_experiments)
        ordered = sorted(train_exps, key=lambda e: float(e.t_s[0]))
        floor_exps = [e for e, t in zip(ordered, train_mask, strict=True) if not t]
        heldout = tuple(e.label for e in floor_exps)
    floor, _ = pooled_noise_floor([e.position_um for e in floor_exps])
    if validate:

        def heldout_residual(params: FamilyParams) -> tuple[F64, list[float]]:
            return prediction_error(val_data, params, val_rows, group)

    else:
        exp_of_row = np.repeat(np.arange(train_data.n_experiments), train_data.counts)
        test_rows = ~train_mask[exp_of_row] & settled_rows(train_data, skip)
        y_centred = train_data.centred(train_data.position_um)

        def heldout_residual(params: FamilyParams) -> tuple[F64, list[float]]:
            # a model fitted elsewhere (``others``); a member's fit carries its own residuals
            x = train_data.centred(session_positions(train_data, params))
            out: F64 = (x - y_centred)[test_rows]
            return out, []

    def fitted(
        law: str, driver: str, without: str = "", relaxing: AfterEffect | bool | None = None
    ) -> tuple[FamilyFit, F64, list[float]]:
        fit = fit_family(
            train_data,
            law,
            train=train_mask,
            plays=plays,
            skip_s=skip,
            creep_driver=driver,
            fit_stiffness=without != "stiffness",
            fit_creep=without != "creep",
            fit_lag=without != "delay",
            after_effect=relaxing,
        )
        if not validate:
            return fit, fit.heldout_residuals_um, []
        resid, gains = heldout_residual(fit.params)
        return fit, resid, gains

    members: list[MemberScore] = []
    gains_by: dict[str, dict[str, float]] = {}
    resid_by: dict[str, F64] = {}

    def score(law: str, driver: str, relaxing: bool = False) -> None:
        """Fit and score one member (with the after-effect searched when ``relaxing``)."""
        name = member_name(law, driver, after_effect=relaxing)
        try:
            fit, resid, gains = fitted(law, driver, relaxing=relaxing)
        except (CalibrationError, np.linalg.LinAlgError) as exc:
            members.append(MemberScore(name, law, driver, math.nan, math.nan, None, str(exc)))
        else:
            resid_by[name] = resid
            if validate:
                gains_by[name] = dict(zip(keys, gains, strict=True))
            members.append(MemberScore(name, law, driver, fit.rms_um, _rms(resid), fit.params))
        step(name)

    for law in laws:
        for driver in creep_drivers:
            score(law, driver)
    first = FamilyComparison(method, tuple(members), floor, skip, heldout).best
    if (
        after_effect
        and first is not None
        and first.creep_driver == "voltage"
        and first.law in AFTER_EFFECT_LAWS
    ):
        score(first.law, first.creep_driver, relaxing=True)
        relaxed = FamilyComparison(method, tuple(members), floor, skip, heldout).best
        # loops that depend on the rate: the domain-wall law with its walls' after-effect too
        found = None if relaxed is None or relaxed.params is None else relaxed.params.after_effect
        if (
            found is not None
            and relaxed is not None
            and relaxed.law != "domain-wall"
            and "domain-wall" in laws
        ):
            score("domain-wall", "voltage", relaxing=True)
    scored_others: dict[str, float] = {}
    for name, params in (others or {}).items():
        scored_others[name] = _rms(heldout_residual(params)[0])
    result = FamilyComparison(method, tuple(members), floor, skip, heldout, others=scored_others)
    best = result.best
    if best is None:
        return result
    result = dataclasses.replace(result, gains=gains_by.get(best.name, {}))
    if not parts:
        return result
    part_gains: list[PartGain] = []
    opts = AuditOptions()
    with_part = HeldOut(best.heldout_rms_um, resid_by[best.name], np.ones(1, dtype=bool))
    held = None if best.params is None else best.params.after_effect
    for effect in PARTS:
        try:
            _, resid, _ = fitted(best.law, best.creep_driver, without=effect, relaxing=held)
        except (CalibrationError, np.linalg.LinAlgError) as exc:
            part_gains.append(PartGain(effect, math.nan, math.nan, math.nan, False, str(exc)))
            continue
        rms = _rms(resid)
        gain, se = gain_with_se(HeldOut(rms, resid, np.ones(1, dtype=bool)), with_part)
        material = bool(
            gain >= opts.gain_min and gain - opts.gain_sigmas * (se if math.isfinite(se) else 0.0) > 1.0
        )
        part_gains.append(PartGain(effect, rms, gain, se, material))
        step(f"{best.name} without {effect}")
    return dataclasses.replace(result, parts=tuple(part_gains))


def thesis_heldout_rms(
    experiments: Sequence[Experiment],
    validate: Sequence[Experiment],
    comparison: FamilyComparison,
    *,
    blocks: int = DEFAULT_BLOCKS,
    start: ThesisParams | None = None,
    max_samples_per_loop: int | None = 2048,
) -> float:
    """Held-out prediction RMS of the thesis model (3.8) on the split of ``comparison`` (um).

    The model is fitted (:func:`piezod.calibrate.calibrate`) on the training experiments only --
    all of ``experiments`` with ``validate``, else those whose labels are not in
    ``comparison.heldout`` (time blocks of a single recording as :func:`compare_family` cuts them)
    -- and predicts the held-out experiments' loops after their first: (3.8) is a model of steady
    loops, so the start-up loop the family's fits skip by time is skipped by loop (when an
    experiment has only one, it is scored whole). As for the family, each held-out experiment has
    its own position offset and each validation file one sensor gain.

    Raises
    ------
    CalibrationError
        No training or no held-out experiment, or the fit failed.
    RecordingError
        A held-out or training experiment is not a periodic triangular scan (file:line).
    """
    from piezod.calibrate import _centre as centre_per_experiment
    from piezod.calibrate import calibrate, model_positions
    from piezod.calibrate_data import prepare

    train_exps, _ = align_known_delay(experiments)
    if validate:
        held, _ = align_known_delay(validate)
        train = list(train_exps)
    else:
        pool = time_blocks(train_exps[0], blocks) if len(train_exps) == 1 else list(train_exps)
        names = set(comparison.heldout)
        held = [e for e in pool if e.label in names]
        train = [e for e in pool if e.label not in names]
    if not held or not train:
        raise CalibrationError("the thesis model needs training and held-out experiments to be scored")
    fit = calibrate(train, start=start, max_samples_per_loop=max_samples_per_loop)
    try:
        data = prepare(held, skip_loops=1, max_samples_per_loop=max_samples_per_loop)
    except CalibrationError:
        data = prepare(held, skip_loops=0, max_samples_per_loop=max_samples_per_loop)
    exp_of = np.repeat(np.arange(data.n_experiments), data.counts)
    x = centre_per_experiment(data, model_positions(data, fit.params))
    y = centre_per_experiment(data, data.position_um)
    files: list[str | None] = list(dict.fromkeys(data.paths)) if validate else [None]
    group = np.array([files.index(p) if validate else 0 for p in data.paths], dtype=np.intp)[exp_of]
    resid = np.empty_like(y)
    for g in range(len(files)):
        sel = group == g
        den = float(x[sel] @ x[sel])
        gain = float(x[sel] @ y[sel]) / den if validate and den > 0 else 1.0
        resid[sel] = gain * x[sel] - y[sel]
    return _rms(resid)


__all__ = [
    "AUDIT_LAWS",
    "CONFIRM_FRACTION",
    "DEFAULT_BLOCKS",
    "HOLDOUT_EVERY",
    "MAX_AUDIT_RUNS",
    "PARTS",
    "SKIP_FRACTION",
    "SKIP_S",
    "FamilyAudit",
    "FamilyComparison",
    "MemberScore",
    "PartGain",
    "audit_model_name",
    "audit_with_family",
    "best_model",
    "check_findings",
    "compare_family",
    "heldout_mask",
    "prediction_error",
    "session",
    "skip_for",
    "thesis_heldout_rms",
    "time_blocks",
]
