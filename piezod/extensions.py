"""The audit's findings into the scanner's model: ``piezod audit ... --out F.yaml`` and calibrate's adoption.

The audit (:mod:`piezod.audit`) names effects with their parameters in the names of the effect
registry (:mod:`piezod.model.registry`). Those with a runtime part (:mod:`piezod.model.parts`:
polarity, thermal, stiffness, saturation, drift; :mod:`piezod.model.resonance`: the resonance) go
into the axis's ``extensions:`` section, which the daemon's inverse applies; a ``delay`` goes there
as the axis's sensor path (:mod:`piezod.model.sensor`: the readback's delay and lag, which the
analysis undoes, the drive unchanged); the others are reported as not (yet) correctable at run time, with
the reason. The written YAML says in a comment which finding became which parameter.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from piezod.config import ScannerConfig, dump_config, load_config
from piezod.errors import ConfigError, ModelError, RecordingError
from piezod.fitstats import lowers
from piezod.model.parts import PART_EFFECTS, TIME_PARTS, Parts, part_effects
from piezod.model.resonance import RESONANCE_PARAMS, ResonancePart
from piezod.model.sensor import SENSOR_EFFECTS, SensorPath
from piezod.readback import SENSOR_DELAY_KEY, align_known_delay, experiments_through_sensor
from piezod.recording import Experiment

if TYPE_CHECKING:
    from piezod.audit import AuditOptions

#: Why a registry effect has no runtime part.
NO_PART_REASON: dict[str, str] = {
    "creep": "the creep spectrum is the calibration's (piezod calibrate fits it)",
    "asymmetry": "no runtime part yet",
}


@dataclass(frozen=True)
class Adoption:
    """What of the findings reaches the scanner.

    Attributes
    ----------
    effects
        ``{effect id: {parameter: value}}`` for the ``extensions:`` section.
    skipped
        One line per finding left out, with the reason.
    """

    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    skipped: tuple[str, ...] = ()

    @property
    def adopted(self) -> tuple[str, ...]:
        """One line per adopted finding (``stiffness: sensitivity_pct_per_um = -0.16``)."""
        lines = []
        for effect, values in self.effects.items():
            line = f"{effect}: " + ", ".join(f"{k} = {v:.6g}" for k, v in values.items())
            if effect in SENSOR_EFFECTS:
                line += " (sensor path: the readback is aligned, the drive unchanged)"
            lines.append(line)
        return tuple(lines)

    def summary(self) -> str:
        """Human-readable, one line per finding."""
        lines = [f"adopted {a}" for a in self.adopted] + [f"not adopted {s}" for s in self.skipped]
        return "\n".join(lines) if lines else "no material finding: the model is kept as it is"


#: Effects the adoption audit fits into its baseline: every runtime model creeps, so a baseline
#: without creep leaves the creep's structure to the candidates (on the full calibration frame of
#: the built-in stage the hysteresis ODE alone left 36 nm against a 2 nm floor, and the thermal
#: candidate took it as -17 %/h where +1.2 %/h was injected; with the creep in the baseline the
#: audit names +1.25 %/h).
ADOPTION_BASE_EFFECTS: tuple[str, ...] = ("creep",)


def adoption_audit_options(folds: int = 4) -> AuditOptions:
    """The audit settings of ``piezod calibrate``'s adoption (and the effects bench's).

    Only the effects a runtime part or the sensor path can take are candidates (the others could
    not be adopted; ``piezod audit`` tries all); the creep is part of the baseline
    (:data:`ADOPTION_BASE_EFFECTS`); the folds are refitted by a few Gauss-Newton steps.
    """
    from piezod.audit import AuditOptions

    return AuditOptions(
        folds=folds,
        refit_cv=False,
        effects=(*PART_EFFECTS, *SENSOR_EFFECTS),
        base_effects=ADOPTION_BASE_EFFECTS,
    )


#: The time-dependent parts (thermal, drift) follow the time for this many times the length of
#: the session they were found on, then hold (:class:`~piezod.model.parts.Parts`): a trend seen
#: over minutes says nothing about a week of scanning, and unbounded it would grow without limit
#: (0.3 nm/s is 180 um a week; 1.2 %/h is 200 % of the sensitivity).
TREND_HORIZON_FACTOR = 3.0


def trend_horizon_s(experiments: Sequence[Experiment]) -> float:
    """How long the adopted time-dependent parts follow the time: :data:`TREND_HORIZON_FACTOR`
    times the session's length (first to last sample of ``experiments``; ``inf`` for none)."""
    if not experiments:
        return math.inf
    t0 = min(float(e.t_s[0]) for e in experiments)
    t1 = max(float(e.t_s[-1]) for e in experiments)
    return TREND_HORIZON_FACTOR * max(t1 - t0, 1.0)


def session_origin_unix_s(path: str | Path) -> float:
    """The wall-clock instant (Unix time, s) at which a recording's clock read 0: its header's
    ``started_utc`` minus its first sample's ``t`` (the board's clock counts from the start of the
    session). ``nan`` when the header has no ``started_utc`` (recordings of other tools) or no
    sample follows it.

    Raises
    ------
    RecordingError
        ``started_utc`` is not ``YYYY-MM-DDTHH:MM:SSZ`` (names the file).
    """
    import calendar
    import time

    started: str | None = None
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.startswith("#"):
                key, _, value = line[1:].partition(":")
                if key.strip() == "started_utc":
                    started = value.strip()
                continue
            if line.startswith("t,") or not line.strip():
                continue
            first = line.split(",", 1)[0]
            break
        else:
            return math.nan
    if started is None:
        return math.nan
    try:
        wall = float(calendar.timegm(time.strptime(started, "%Y-%m-%dT%H:%M:%SZ")))
        t0 = float(first)
    except ValueError as exc:
        raise RecordingError(
            f"{path}: started_utc {started!r} or first t {first!r} unreadable: {exc}"
        ) from exc
    return wall - t0 if math.isfinite(t0) else math.nan


#: Findings adopted with all their parameters (the value a missing one takes) and the check they
#: must pass: the sensor path (a missing delay or lag is none) and the resonance part.
_EffectCheck = Callable[[Mapping[str, Mapping[str, float]]], object]
_WHOLE_EFFECTS: dict[str, tuple[tuple[str, ...], float, _EffectCheck]] = {
    **{effect: (names, 0.0, SensorPath.from_effects) for effect, names in SENSOR_EFFECTS.items()},
    "resonance": (RESONANCE_PARAMS, math.nan, ResonancePart.from_effects),
}


def adopt_findings(
    findings: Sequence[Mapping[str, Any]], *, horizon_s: float = math.inf, since_unix_s: float = math.nan
) -> Adoption:
    """Map the audit's findings (``result_json(...)["findings"]``) to runtime parts.

    Parameters
    ----------
    findings
        Each with ``effect`` and ``params`` (registry names, public units).
    horizon_s
        The time-dependent parts' horizon (:func:`trend_horizon_s`; ``inf``: none).
    since_unix_s
        When the clock of the audited recordings read 0 (:func:`session_origin_unix_s`): the
        time parts go on from there (:meth:`~piezod.model.parts.Parts.anchored`); ``nan``: from
        the adoption.
    """
    effects: dict[str, dict[str, float]] = {}
    skipped: list[str] = []
    for f in findings:
        effect = str(f["effect"])
        params = {str(k): v for k, v in dict(f.get("params") or {}).items()}
        if effect in _WHOLE_EFFECTS:
            names, missing, check = _WHOLE_EFFECTS[effect]
            vals = {n: float(params.get(n) or missing) for n in names}
            try:
                check({effect: vals})
            except ModelError as exc:
                skipped.append(f"{effect}: {exc}")
                continue
            effects[effect] = vals
            continue
        if effect not in PART_EFFECTS:
            skipped.append(f"{effect}: {NO_PART_REASON.get(effect, 'no runtime part')}")
            continue
        values: dict[str, float] = {}
        for name in PART_EFFECTS[effect]:
            value = params.get(name)
            if value is None or not math.isfinite(float(value)):
                break
            values[name] = float(value)
        else:
            if effect in TIME_PARTS and math.isfinite(horizon_s):
                values["horizon_s"] = float(horizon_s)
            if effect in TIME_PARTS and math.isfinite(since_unix_s):
                values["since_unix_s"] = float(since_unix_s)
            try:
                Parts.from_effects(part_effects(effects) | {effect: values})
            except ModelError as exc:
                skipped.append(f"{effect}: {exc}")
                continue
            effects[effect] = values
            continue
        skipped.append(f"{effect}: no finite value for {', '.join(PART_EFFECTS[effect])}")
    return Adoption(effects, tuple(skipped))


def extended_config(config: ScannerConfig, axis: str, adoption: Adoption) -> ScannerConfig:
    """``config`` whose ``axis`` carries the adopted parts (merged over the parts it has)."""
    if axis not in config.axes:
        raise ConfigError(f"the scanner config has no axis {axis!r} (axes: {', '.join(config.axes)})")
    name = next(a for a in config.axes if a == axis)
    ax = config.axes[name]
    merged: dict[str, dict[str, float]] = {str(k): v for k, v in (ax.extensions or {}).items()}
    merged.update(adoption.effects)
    new_ax = ax.model_validate({**ax.model_dump(), "extensions": merged})
    axes = dict(config.axes)
    axes[name] = new_ax
    return config.model_copy(update={"axes": axes})


def experiments_through_parts(experiments: Sequence[Experiment], parts: Parts) -> list[Experiment]:
    """The experiments as the model inside the parts sees them: voltages and positions through the
    parts' exact inverse (times from the recording: the stage's clock)."""
    return [
        dataclasses.replace(
            e,
            voltage_v=parts.voltage_in(np.asarray(e.voltage_v, dtype=np.float64)),
            position_um=parts.position_in(np.asarray(e.position_um, dtype=np.float64), np.asarray(e.t_s)),
        )
        for e in experiments
    ]


def experiments_through(
    experiments: Sequence[Experiment], effects: Mapping[str, Mapping[str, float]]
) -> list[Experiment]:
    """The experiments as the model inside the adopted ``effects`` sees them: the readback aligned
    through the sensor path (the last link of the chain), then through the parts' exact inverse."""
    aligned = experiments_through_sensor(experiments, SensorPath.from_effects(effects))
    return experiments_through_parts(aligned, Parts.from_effects(part_effects(effects)))


#: Evaluations of the profile search per adopted part (:func:`refine_parts`).
REFINE_EVALUATIONS = 12
#: Times the profile search moves on when its optimum lies on its window's edge.
REFINE_EXPANSIONS = 2


def refine_parts(
    effects: Mapping[str, Mapping[str, float]],
    train_rms: Callable[[dict[str, dict[str, float]]], float],
    model: str = "the refitted model",
    only: Sequence[str] | None = None,
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Profile each adopted runtime part's primary parameter on a refitted model's training RMS.

    The audit estimates a part against its own baseline model, which absorbs some of the effect
    (a law whose density depends on the relay centre takes part of a polarity kink at 0 V: on a
    tube with 5 % depoling the audit found 3.98 %; on the built-in stage a saturation of 105 um
    came out as 89.7 um). Each part's primary parameter is searched (bounded scalar search over
    half to one and a half times the audit's value, inside the registry's physical bounds;
    :data:`REFINE_EVALUATIONS` evaluations) for the smallest ``train_rms``: the *training* RMS of
    the model refitted on the frame seen through the parts (:func:`experiments_through`). An
    optimum on the window's edge is searched on beyond it, up to twice its distance from 0 (at most
    :data:`REFINE_EXPANSIONS` times): on a held-out stage with a -4 % depoling, a profile started
    at -1 % stopped on its window's edge, -1.5 % (docs/model-family.md 6.2q). ``only`` restricts
    the search to those parts (default all).

    Returns
    -------
    effects, notes
        The effects with the refined values, and one line per refined part.
    """
    from scipy.optimize import minimize_scalar

    from piezod.model.registry import spec

    out = {k: dict(v) for k, v in effects.items()}
    notes: list[str] = []
    for effect in [e for e in out if e in PART_EFFECTS and (only is None or e in only)]:
        name = PART_EFFECTS[effect][0]
        p0 = float(out[effect][name])
        if p0 == 0.0:
            continue
        lo_phys, hi_phys = next(p.physical for p in spec(effect).params if p.name == name)
        lo, hi = max(lo_phys, p0 - 0.5 * abs(p0)), min(hi_phys, p0 + 0.5 * abs(p0))

        def rms(value: float, effect: str = effect, name: str = name) -> float:
            trial = {k: dict(v) for k, v in out.items()}
            trial[effect][name] = float(value)
            return train_rms(trial)

        start = rms(p0)
        x_best, f_best = p0, start
        for _ in range(1 + REFINE_EXPANSIONS):
            best = minimize_scalar(
                rms,
                bounds=(lo, hi),
                method="bounded",
                options={"xatol": 0.01 * abs(p0), "maxiter": REFINE_EVALUATIONS},
            )
            if not (math.isfinite(float(best.fun)) and float(best.fun) < f_best):
                break
            x_best, f_best = float(best.x), float(best.fun)
            # an optimum on the window's edge lies beyond it: search on from there
            edge = 0.02 * abs(p0)
            at_low = x_best < lo + edge and lo > lo_phys + edge
            at_high = x_best > hi - edge and hi < hi_phys - edge
            if not (at_low or at_high):
                break
            lo, hi = (
                (max(lo_phys, x_best - abs(x_best)), x_best)
                if at_low
                else (x_best, min(hi_phys, x_best + abs(x_best)))
            )
        if f_best < start:
            out[effect][name] = x_best
            notes.append(
                f"{effect}: {name} {p0:.6g} -> {x_best:.6g} (training RMS of {model} "
                f"{start * 1e3:.2f} -> {f_best * 1e3:.2f} nm)"
            )
    return out, notes


#: Static parts tried on the chosen member whether or not the audit named them (:func:`probe_parts`).
PROBE_EFFECTS: tuple[str, ...] = ("polarity", "saturation")
#: The polarity probe's step (%): a depoling of this size either way.
PROBE_POLARITY_STEP_PCT = 5.0
#: The saturation probe's step in ``(x_max / x_sat)^2``: ``x_sat tanh(x / x_sat)`` compresses the
#: frame's largest position ``x_max`` by a third of it (1 %).
PROBE_SATURATION_STEP = 0.03
#: The polarity is probed only on a frame with at least this share of its samples below 0 V.
PROBE_MIN_NEGATIVE_SHARE = 0.01
#: A probed part is added when it lowers the training RMS by at least this fraction.
PROBE_GAIN = 0.05


@dataclass(frozen=True)
class _ProbeAxis:
    """How one part is probed: its primary parameter as a function of the probe variable ``q``
    (0: the part off), the two probe points and the range the vertex may take."""

    value: Callable[[float], float]
    points: tuple[float, float]
    domain: tuple[float, float]


def _probe_axis(effect: str, experiments: Sequence[Experiment]) -> _ProbeAxis | None:
    from piezod.model.registry import spec

    lo, hi = spec(effect).primary.physical
    if effect == "polarity":
        volts = np.concatenate([np.asarray(e.voltage_v, dtype=np.float64) for e in experiments])
        if not volts.size or float(np.mean(volts < 0.0)) < PROBE_MIN_NEGATIVE_SHARE:
            return None
        step = PROBE_POLARITY_STEP_PCT
        return _ProbeAxis(float, (-step, step), (max(lo, -3.0 * step), min(hi, 3.0 * step)))
    if effect == "saturation":
        x_max = _largest_position(experiments)
        if not x_max > 0.0:
            return None
        q_lo, q_hi = _saturation_domain(x_max)
        if q_hi <= q_lo:
            return None
        # on a small stage the registry's least x_sat can compress less than the probe's steps
        step = min(PROBE_SATURATION_STEP, 0.5 * q_hi)
        return _ProbeAxis(lambda q: x_max / math.sqrt(q), (step, 2.0 * step), (q_lo, q_hi))
    return None


def _largest_position(experiments: Sequence[Experiment]) -> float:
    """The frame's largest |position| (um; 0 without finite readings): the scale of a saturation's
    coordinate ``(x_max / x_sat)^2``."""
    finite = [p[np.isfinite(p)] for p in (np.asarray(e.position_um, dtype=np.float64) for e in experiments)]
    return max((float(np.max(np.abs(p))) for p in finite if p.size), default=0.0)


def _saturation_domain(x_max: float) -> tuple[float, float]:
    """The range of ``(x_max / x_sat)^2`` inside the registry's physical bounds, where the inverse
    (``atanh``) keeps every position well inside ``x_sat`` (``x_sat >= 1.4 x_max``)."""
    from piezod.model.registry import spec

    lo, hi = spec("saturation").primary.physical
    return (x_max / hi) ** 2, min(0.5, (x_max / lo) ** 2)


def probe_parts(
    effects: Mapping[str, Mapping[str, float]],
    train_rms: Callable[[dict[str, dict[str, float]]], float],
    experiments: Sequence[Experiment],
    model: str = "the refitted model",
    floor_um: float = 0.0,
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Try the static parts the audit did not name on a refitted model's training RMS.

    The audit names effects against its own baseline (the thesis model), whose misfit of another
    hysteresis law can hide an effect or give it the wrong sign: on a held-out stage with a -4 %
    depoling below 0 V the audit fitted +0.76 % with no held-out gain, while the chosen member
    (Bouc-Wen) refitted through a -4 % polarity went from 42 to 7 nm training RMS
    (docs/model-family.md 6.2q). So each part of :data:`PROBE_EFFECTS` not among ``effects`` is
    probed: ``train_rms`` at two points (a polarity of -/+ :data:`PROBE_POLARITY_STEP_PCT`; a
    saturation compressing the frame's largest position by 1 % and 2 %), a parabola in the mean
    square through them and the part left off, and one more fit at its vertex (inside the
    registry's physical bounds). The best point is added when it lowers the training RMS by
    :data:`PROBE_GAIN` of what the RMS has above the frame's noise ``floor_um``
    (:func:`piezod.fitstats.lowers`); the next part is probed with it. A polarity is probed only on a frame
    reaching below 0 V (:data:`PROBE_MIN_NEGATIVE_SHARE`). The held-out data decide later
    (:func:`prune_parts`).

    Returns
    -------
    effects, notes
        The effects with the parts added, and one line per part added.
    """
    out = {k: dict(v) for k, v in effects.items()}
    notes: list[str] = []
    if not experiments:
        return out, notes
    current: float | None = None
    for effect in PROBE_EFFECTS:
        if effect in out:
            continue
        probe = _probe_axis(effect, experiments)
        if probe is None:
            continue
        name = PART_EFFECTS[effect][0]

        def rms(q: float, effect: str = effect, name: str = name, probe: _ProbeAxis = probe) -> float:
            return train_rms({**out, effect: {name: probe.value(q)}})

        if current is None:
            current = train_rms(out)
        tried = {q: rms(q) for q in probe.points}
        qs = np.array([0.0, *tried])
        ms = np.array([current, *tried.values()]) ** 2
        if np.all(np.isfinite(ms)):
            a, b, _ = np.polyfit(qs, ms, 2)
            if a > 0.0:
                vertex = float(np.clip(-b / (2.0 * a), *probe.domain))
                if vertex != 0.0 and vertex not in tried:
                    tried[vertex] = rms(vertex)
        q_best = min(tried, key=lambda q: tried[q])
        if lowers(tried[q_best], current, PROBE_GAIN, floor_um):
            out[effect] = {name: probe.value(q_best)}
            notes.append(
                f"{effect}: probed, {name} = {probe.value(q_best):.6g} (training RMS of {model} "
                f"{current * 1e3:.2f} -> {tried[q_best] * 1e3:.2f} nm)"
            )
            current = tried[q_best]
    return out, notes


#: Quadratic steps of the joint profile of the runtime parts (:func:`refine_jointly`).
JOINT_ITERATIONS = 3
#: The joint profile's design step, as a fraction of each coordinate (at least its floor below).
JOINT_STEP_FRACTION = 0.25
#: Floor of the design step per part, in the probe's coordinate (polarity %, saturation's
#: ``(x_max / x_sat)^2``; the others in their primary parameter's unit, as a fraction of the
#: physical bound's magnitude).
JOINT_STEP_FLOOR = {"polarity": 0.5, "saturation": 0.005}
JOINT_STEP_FLOOR_OF_BOUND = 0.01
#: The joint profile stops after a step that lowers the training RMS by less than this fraction.
JOINT_MIN_GAIN = 0.01
#: The quadratic's vertex is taken at most this many design steps from the centre.
JOINT_TRUST_STEPS = 4.0


def refine_jointly(
    effects: Mapping[str, Mapping[str, float]],
    train_rms: Callable[[dict[str, dict[str, float]]], float],
    experiments: Sequence[Experiment],
    model: str = "the refitted model",
    floor_um: float = 0.0,
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Profile the runtime parts' primary parameters together on a refitted model's training RMS.

    :func:`refine_parts` searches one part at a time, each with the others held, and a part the
    probe adds later (:func:`probe_parts`) is searched with the earlier ones fixed where they
    ended without it. Parts that act alike over the frame trade: on a held-out flexure stage
    (-3 % depoling below 0 V, ``x_sat`` 500 um) the saturation profiled alone went to 346 um, the
    polarity probed beside it to -1.5 %, and the member refitted there left 22.8 nm in training
    where the stage's own values leave 13.0 nm; the scans corrected with it were 0.13 % short on
    small ranges and 0.12 % long on large ones (docs/model-family.md 6.2v). So with two parts or
    more the mean square training RMS is modelled as a full quadratic in the parts' coordinates
    (saturation in ``(x_max / x_sat)^2``, the probe's axis; the others in their primary
    parameter) from the fewest points that determine it (the centre, a step either way along
    each coordinate, a step along both of every pair) and the fit at its vertex, kept within
    :data:`JOINT_TRUST_STEPS` steps and the registry's physical bounds, is taken when it is the
    best point so far; :data:`JOINT_ITERATIONS` such steps at most, each from the best point, until
    one lowers the training RMS by less than :data:`JOINT_MIN_GAIN` of what it has above the
    frame's noise ``floor_um`` (:func:`piezod.fitstats.lowers`).

    Returns
    -------
    effects, notes
        The effects with the jointly profiled values, and one line per changed part.
    """
    from piezod.model.registry import spec

    out = {k: dict(v) for k, v in effects.items()}
    parts = [e for e in out if e in PART_EFFECTS and float(out[e][PART_EFFECTS[e][0]]) not in (0.0, math.inf)]
    if len(parts) < 2:
        return out, []
    x_max = _largest_position(experiments) if "saturation" in parts else 0.0
    if "saturation" in parts and not x_max > 0.0:
        parts.remove("saturation")
        if len(parts) < 2:
            return out, []
    names = [PART_EFFECTS[e][0] for e in parts]

    def coord(effect: str, value: float) -> float:
        return (x_max / value) ** 2 if effect == "saturation" else value

    def value_of(effect: str, q: float) -> float:
        return x_max / math.sqrt(q) if effect == "saturation" else q

    bounds = []
    floors = []
    for effect, name in zip(parts, names, strict=True):
        lo, hi = spec(effect).param(name).physical
        bounds.append(_saturation_domain(x_max) if effect == "saturation" else (lo, hi))
        floors.append(JOINT_STEP_FLOOR.get(effect, JOINT_STEP_FLOOR_OF_BOUND * max(abs(lo), abs(hi))))
    lo_b = np.array([b[0] for b in bounds])
    hi_b = np.array([b[1] for b in bounds])

    def ms(q: np.ndarray) -> float:
        trial = {k: dict(v) for k, v in out.items()}
        for effect, name, qi in zip(parts, names, q, strict=True):
            trial[effect][name] = float(value_of(effect, float(qi)))
        r = train_rms(trial)
        return r * r if math.isfinite(r) else math.inf

    start = np.array([coord(e, float(out[e][n])) for e, n in zip(parts, names, strict=True)])
    best_q, best = start, ms(start)
    first = best
    n = len(parts)
    eye = np.eye(n)
    # the centre, a step either way along each coordinate, a step along both of every pair
    offsets = [np.zeros(n), *(sgn * eye[i] for i in range(n) for sgn in (1.0, -1.0))]
    offsets += [eye[i] + eye[j] for i in range(n) for j in range(i + 1, n)]
    for _ in range(JOINT_ITERATIONS):
        h = np.maximum(JOINT_STEP_FRACTION * np.abs(best_q), floors)
        pts = [np.clip(best_q + o * h, lo_b, hi_b) for o in offsets]
        vals = [best if np.array_equal(p, best_q) else ms(p) for p in pts]
        ok = [k for k, v in enumerate(vals) if math.isfinite(v)]
        k_best = min(ok, key=lambda k: vals[k])
        step_best, val_best = pts[k_best], vals[k_best]
        z = _quadratic_vertex(np.array([(pts[k] - best_q) / h for k in ok]), np.array([vals[k] for k in ok]))
        if z is not None:
            vertex = np.clip(best_q + np.clip(z, -JOINT_TRUST_STEPS, JOINT_TRUST_STEPS) * h, lo_b, hi_b)
            v = ms(vertex)
            if v < val_best:
                step_best, val_best = vertex, v
        if not val_best < best:
            break
        gained = lowers(math.sqrt(val_best), math.sqrt(best), JOINT_MIN_GAIN, floor_um)
        best_q, best = step_best, val_best
        if not gained:
            break
    if not best < first:
        return out, []
    notes = []
    for effect, name, qi in zip(parts, names, best_q, strict=True):
        old = float(out[effect][name])
        out[effect][name] = float(value_of(effect, float(qi)))
        notes.append(
            f"{effect}: {name} {old:.6g} -> {out[effect][name]:.6g} (profiled jointly with "
            f"{', '.join(e for e in parts if e != effect)}; training RMS of {model} "
            f"{math.sqrt(first) * 1e3:.2f} -> {math.sqrt(best) * 1e3:.2f} nm)"
        )
    return out, notes


def _quadratic_vertex(d: np.ndarray, values: np.ndarray) -> np.ndarray | None:
    """The vertex of the full quadratic through ``values`` at the points ``d`` (rows), or None when
    the points do not determine it or it has no minimum."""
    n = d.shape[1]
    iu = np.triu_indices(n)
    design = np.column_stack([np.ones(len(d)), d, *(d[:, a] * d[:, b] for a, b in zip(*iu, strict=True))])
    if len(d) < design.shape[1]:
        return None
    coef = np.linalg.lstsq(design, values, rcond=None)[0]
    upper = np.zeros((n, n))
    upper[iu] = coef[1 + n :]
    hess = upper + upper.T  # 2 c_aa on the diagonal, c_ab off it
    if not np.all(np.linalg.eigvalsh(hess) > 0.0):
        return None
    vertex: np.ndarray = -np.linalg.solve(hess, coef[1 : 1 + n])
    return vertex


#: Bounds of the sensor-path lag profile, as factors on the audit's values (:func:`refine_sensor_lag`).
SENSOR_LAG_FACTORS = (0.2, 1.6)
#: Evaluations of the sensor-path lag profile.
SENSOR_LAG_EVALUATIONS = 12


def refine_sensor_lag(
    effects: Mapping[str, Mapping[str, float]], train_rms: Callable[[dict[str, dict[str, float]]], float]
) -> tuple[dict[str, dict[str, float]], str | None]:
    """Profile the sensor path's lag on a refitted model's training RMS.

    The audit estimates a readback delay against its own baseline, whose misfit of the rate
    dependence the delay candidate partly takes: on the built-in stage with 0.32 ms delay +
    0.32 ms lag at the sensor (0.63 ms in all) it found a 0.94 ms lag, and the model refitted
    through that path left 0.074 % length error where the injected path leaves none. The
    refitted model's training RMS is sharp at the true total (the dynamic model's fit error on
    the full frame, ``tools/sensor_lag_profile.py``: 0.094 / 0.032 / 0.020 / 0.040 / 0.069 % at
    0 / 0.5 / 0.63 / 0.8 / 0.94 ms).
    So the audit's delay and lag are scaled by one factor in :data:`SENSOR_LAG_FACTORS` (their
    split is kept: the frame's rates do not separate a delay from a lag of the same total), by a
    bounded scalar search of :data:`SENSOR_LAG_EVALUATIONS` evaluations of ``train_rms``.

    Parameters
    ----------
    effects
        The adoption's ``{effect: {parameter: value}}``; only the sensor-path effects change.
    train_rms
        Training RMS of the model refitted on the frame seen through the given effects (a
        failed fit returns ``inf``). Its lag must not stand in for the sensor's (a model with a
        drive lag of its own is fitted without it here).

    Returns
    -------
    effects, note
        The effects with the refined sensor path, and a line saying what changed (``None`` when
        the audit's values stand).
    """
    from scipy.optimize import minimize_scalar

    base = {k: dict(v) for k, v in effects.items()}
    sensor = [e for e in base if e in SENSOR_EFFECTS and any(float(x) > 0 for x in base[e].values())]
    if not sensor:
        return base, None

    def scaled(c: float) -> dict[str, dict[str, float]]:
        out = {k: dict(v) for k, v in base.items()}
        for e in sensor:
            out[e] = {k: float(v) * c for k, v in base[e].items()}
        return out

    start = train_rms(base)
    best = minimize_scalar(
        lambda c: train_rms(scaled(float(c))),
        bounds=SENSOR_LAG_FACTORS,
        method="bounded",
        options={"xatol": 0.01, "maxiter": SENSOR_LAG_EVALUATIONS},
    )
    if not (math.isfinite(float(best.fun)) and float(best.fun) < start):
        return base, None
    c = float(best.x)
    out = scaled(c)
    total = {e: sum(base[e].values()) for e in sensor}
    note = (
        "; ".join(f"{e}: total {total[e] * 1e3:.3f} ms -> {total[e] * c * 1e3:.3f} ms" for e in sensor)
        + f" (training RMS {start * 1e3:.2f} -> {float(best.fun) * 1e3:.2f} nm)"
    )
    return out, note


def refine_findings(
    effects: Mapping[str, Mapping[str, float]],
    train_rms: Callable[[dict[str, dict[str, float]]], float],
    sensor_rms: Callable[[dict[str, dict[str, float]]], float] | None = None,
    model: str = "the refitted model",
    sensor_model: str | None = None,
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """:func:`refine_sensor_lag` on ``sensor_rms`` (default ``train_rms``: a model without a drive
    lag of its own, described by ``sensor_model`` in the note), then :func:`refine_parts` on
    ``train_rms`` through the refined sensor path; the refined effects and one line per change.

    The sensor path goes first: the audit's lag is the estimate furthest off (its baseline's misfit
    of the rate dependence goes into it), and a part profiled through a wrong lag takes some of the
    lag's misfit. On a held-out nPoint-like stage the audit's 1.22 ms sensor lag (0.34 ms once
    profiled) left the member 15.5 nm in training, and the stiffness profiled through it went to
    the search's bound (+0.094 %/um; the stage's is -0.025 %/um); the scans corrected with it were
    0.12 % short (docs/model-family.md 6.2g).
    """
    out = {k: dict(v) for k, v in effects.items()}
    notes: list[str] = []
    if any(e in SENSOR_EFFECTS for e in out):
        out, note = refine_sensor_lag(out, sensor_rms or train_rms)
        if note:
            notes.append(f"sensor path {note}" + (f", of {sensor_model}" if sensor_model else ""))
    out, part_notes = refine_parts(out, train_rms, model)
    return out, notes + part_notes


def prune_parts(
    effects: Mapping[str, Mapping[str, float]],
    heldout_rms: Callable[[dict[str, dict[str, float]]], float],
    model: str = "the refitted model",
    tie_fraction: float | None = None,
    floor_um: float = 0.0,
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Leave out the runtime parts that do not lower a refitted model's held-out RMS.

    The audit names effects against its own baseline; the model they are adopted into may have
    the effect already (a family member fits its own static stiffness map), and a part the model
    does not need still lowers its *training* RMS a little. So each runtime part (the sensor path
    is not one: where a lag sits is decided by :func:`piezod.stagecal.audit_and_extend`) must earn
    its place: while the model refitted through all the parts but one predicts the held-out
    experiments no worse than through all of them (within ``tie_fraction``, default the model
    choice's :data:`piezod.calibrate_family.CHOICE_TIE_FRACTION`, of what the RMS has above the
    frame's noise ``floor_um``: :func:`piezod.fitstats.lowers`), the part whose removal costs least
    is left out.

    Parameters
    ----------
    effects
        ``{effect id: {parameter: value}}`` (refined, :func:`refine_findings`).
    heldout_rms
        Held-out RMS of the model refitted on the frame seen through the given effects (a
        failed fit returns ``inf``).
    model
        The refitted model, for the notes.
    tie_fraction
        Relative held-out gain a part must bring.
    floor_um
        The frame's noise floor (um; 0: the gain is taken on the RMS itself).

    Returns
    -------
    effects, left_out
        The effects kept, and one line per part left out, with the held-out RMS with and without it.
    """
    if tie_fraction is None:
        from piezod.calibrate_family import CHOICE_TIE_FRACTION

        tie_fraction = CHOICE_TIE_FRACTION
    out = {k: dict(v) for k, v in effects.items()}
    left_out: list[str] = []
    with_all = heldout_rms(out)
    while parts := [e for e in out if e in PART_EFFECTS]:
        without = {e: heldout_rms({k: v for k, v in out.items() if k != e}) for e in parts}
        effect = min(without, key=lambda e: without[e])
        if lowers(with_all, without[effect], tie_fraction, floor_um):
            break
        left_out.append(
            f"{effect}: held-out RMS of {model} {with_all * 1e3:.2f} nm with it, "
            f"{without[effect] * 1e3:.2f} nm without"
        )
        del out[effect]
        with_all = without[effect]
    return out, left_out


def write_extended_config(
    base: str | Path,
    axis: str,
    findings: Sequence[Mapping[str, Any]],
    out: str | Path,
    source: str,
    *,
    horizon_s: float = math.inf,
    since_unix_s: float = math.nan,
) -> Adoption:
    """Write ``base`` with the findings' runtime parts on ``axis`` to ``out`` (a comment says which).

    Parameters
    ----------
    base
        The scanner YAML the recordings were taken with.
    axis
        The audited axis.
    findings
        The audit's findings (``result_json(...)["findings"]``).
    out
        The extended scanner YAML (written atomically; loads with ``piezod serve``/``scan``).
    source
        What the findings come from (named in the comment).
    horizon_s
        The time-dependent parts' horizon (:func:`trend_horizon_s` of the audited recordings).
    since_unix_s
        When the audited recordings' clock read 0 (:func:`session_origin_unix_s`).
    """
    config = load_config(base)
    adoption = adopt_findings(findings, horizon_s=horizon_s, since_unix_s=since_unix_s)
    extended = extended_config(config, axis, adoption)
    header = "\n".join(
        [
            f"Extended by {source}: the audit's material findings on axis {axis} as runtime parts",
            "(axes.<axis>.extensions, piezod.model.parts; parameter names of piezod.model.registry).",
            *adoption.summary().splitlines(),
            f"Base: {Path(base).name}",
        ]
    )
    dump_config(extended, out, header=header)
    load_config(out)
    return adoption


__all__ = [
    "NO_PART_REASON",
    "PROBE_EFFECTS",
    "PROBE_GAIN",
    "PROBE_MIN_NEGATIVE_SHARE",
    "PROBE_POLARITY_STEP_PCT",
    "PROBE_SATURATION_STEP",
    "REFINE_EVALUATIONS",
    "REFINE_EXPANSIONS",
    "SENSOR_DELAY_KEY",
    "SENSOR_LAG_EVALUATIONS",
    "SENSOR_LAG_FACTORS",
    "TREND_HORIZON_FACTOR",
    "Adoption",
    "adopt_findings",
    "align_known_delay",
    "experiments_through",
    "experiments_through_parts",
    "experiments_through_sensor",
    "extended_config",
    "probe_parts",
    "prune_parts",
    "refine_findings",
    "refine_parts",
    "refine_sensor_lag",
    "session_origin_unix_s",
    "trend_horizon_s",
    "write_extended_config",
]
