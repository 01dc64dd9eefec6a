"""``piezod bench effects``: per hil_sim effect, online correction by the baseline and the extended model.

For every effect the simulated stage can inject (``hil_sim.effects.EFFECT_NAMES``), at the
middle of its realistic magnitude (:mod:`piezod.model.registry`), on the built-in stage
(``configs/sim-stage.yaml``: the stage built from the controller's default model, so the
baseline alone is at its self-consistency floor and what remains is the effect's):

1. the calibration frame of :func:`piezod.stagecal.default_frame` (uncorrected triangles) is
   stepped on the stage in process (deterministic, independent of machine load);
2. **baseline**: the dynamic model calibrated on the frame (what ``piezod calibrate`` writes on
   this stage);
3. **extended**: the audit (:func:`piezod.audit.run_audit`) of the same frame for the candidates
   ``piezod calibrate`` audits (those a runtime part or the sensor path can take), its material
   findings mapped to runtime parts and the sensor path (:func:`piezod.extensions.adopt_findings`),
   each part's primary parameter and the sensor path's lag profiled on the refitted dynamic
   model's training RMS (:func:`piezod.extensions.refine_parts`,
   :func:`piezod.extensions.refine_sensor_lag`: what ``piezod calibrate``'s
   :func:`piezod.stagecal.refine_adoption` does with the chosen family member), the dynamic model
   refitted with them fixed (the frame's readback aligned through the sensor path, then seen
   through the parts' exact inverse), the parts around it
   (:class:`piezod.model.parts.PartsAxisModel`);
4. both verified by online-corrected triangles at the frame's verification points
   (:func:`piezod.stagecal.verification_points`; one warm-up loop, then ``loops`` recorded),
   scored by :func:`piezod.linearity.experiment_linearity` on where the stage is: the readback,
   or for an effect of the readback only (hil_sim's ``delay`` at the sensor) the same stage
   without it stepped alongside (a readback delay is not an error of the position);
5. the floor: the baseline calibrated and verified the same way on the stage without the effect.

What is left of an effect's error with a model is its worst metric over the points minus the
floor's (never below 0). A third model, the parts with the *injected* values (refitted the same
way), separates what the runtime parts can correct from what the audit finds. The target is
``left(extended) <= left(baseline) / 3`` for both the
nonlinearity and the length error. An effect whose error stays within ``resolution_pct`` of the
floor with the baseline already is reported as "below resolution" (nothing to remove).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod import calibrate_dynamic as cd
from piezod.config import (
    AxisName,
    ScannerConfig,
    atomic_write_text,
    default_sim_config_path,
    load_config,
)
from piezod.errors import CalibrationError, ConfigError
from piezod.extensions import (
    Adoption,
    adopt_findings,
    adoption_audit_options,
    experiments_through,
    extended_config,
    refine_findings,
    trend_horizon_s,
)
from piezod.linearity import experiment_linearity
from piezod.model.parts import PART_EFFECTS
from piezod.model.registry import REGISTRY
from piezod.model.resonance import RESONANCE_PARAMS
from piezod.model.sensor import SENSOR_EFFECTS
from piezod.recording import Experiment
from piezod.resonance_id import adopt_resonance
from piezod.service.axes import axis_model
from piezod.stagecal import Frame, VerifyPoint, default_frame, verification_points

F64 = NDArray[np.float64]
#: Metrics of a verification: the worst nonlinearity and |length error| over the points (%).
METRICS = ("nonlinearity_pct", "length_error_pct")
#: The target: what the extended model leaves of the effect's error, as a fraction of the baseline's.
TARGET_FRACTION = 1.0 / 3.0


def realistic_specs(effect: str) -> list[str]:
    """``NAME.FIELD=VALUE`` for the middle of every realistic range of ``effect`` (registry)."""
    out = []
    for p in REGISTRY[effect].params:
        lo, hi = p.realistic
        mid = math.sqrt(lo * hi) if lo > 0 and hi / lo > 5 else 0.5 * (lo + hi)
        out.append(f"{effect}.{p.name}={mid:.6g}")
    return out


#: Samples per block when the bench steps the stage and when a model replays the stage's history
#: (:func:`_verify`): whole recordings at once take per-sample state for all of them.
HISTORY_BLOCK = 1 << 16


class StageBench:
    """A hil_sim stage and its clock, stepped in process: voltages in, sensed positions out.

    Parameters
    ----------
    stage
        The stage (:func:`piezod.simulator.load_stage`).
    rate_hz
        Sample rate.
    keep_history
        Keep every voltage played (:attr:`history`), to replay the stage's past through a model.
    truth
        The same stage without its sensor-side effects, stepped alongside: where the stage really
        is (:attr:`last_truth`, the last block's), when the readback is delayed.
    """

    def __init__(
        self, stage: Any, rate_hz: float, *, keep_history: bool = True, truth: Any | None = None
    ) -> None:
        self.stage = stage
        self.truth = truth
        self.last_truth: F64 | None = None
        self.rate_hz = rate_hz
        self.dt = 1.0 / rate_hz
        self.t = 0.0
        self.v = 0.0
        self.keep_history = keep_history
        self.history: list[F64] = []

    def play(self, volts: F64) -> tuple[F64, F64]:
        chunks = range(0, volts.size, HISTORY_BLOCK)
        xs = [self.stage.sense(self.stage.step(volts[i : i + HISTORY_BLOCK], self.dt)) for i in chunks]
        if self.truth is not None:
            true = [self.truth.sense(self.truth.step(volts[i : i + HISTORY_BLOCK], self.dt)) for i in chunks]
            self.last_truth = np.concatenate(true).astype(np.float64)
        t: F64 = self.t + self.dt * np.arange(1, volts.size + 1, dtype=np.float64)
        self.t = float(t[-1])
        self.v = float(volts[-1])
        x: F64 = np.concatenate(xs).astype(np.float64)
        if self.keep_history:
            self.history.append(np.asarray(volts, dtype=np.float64))
        return t, x

    def ramp(self, to_v: float, rate: float) -> None:
        n = max(1, math.ceil(abs(to_v - self.v) / rate / self.dt))
        self.play(self.v + (to_v - self.v) * np.arange(1, n + 1) / n)

    def play_frame(self, frame: Frame, axis: AxisName, ramp_v_per_s: float) -> list[Experiment]:
        """Play a calibration frame (ramping to each scan's start); the recorded experiments."""
        exps: list[Experiment] = []
        for scan in frame.scans:
            segs = scan.segments(self.rate_hz)
            self.ramp(float(segs[0].volts[0]), ramp_v_per_s)
            for seg in segs:
                volts = np.asarray(seg.volts, dtype=np.float64)
                t, x = self.play(volts)
                if seg.record:
                    exps.append(Experiment(scan.label, axis, t, volts, x))
        return exps


def _stage(path: Path, specs: Sequence[str], axis: AxisName, seed: int) -> Any:
    from piezod.simulator import load_stage

    return load_stage(path, specs, axis, seed)


class _Refits:
    """The dynamic model fitted on the frame seen through given effects, each fit done once (the
    profile searches evaluate the values they settle on, the extended model is the fit there)."""

    def __init__(self, exps: Sequence[Experiment], base: ScannerConfig, axis: AxisName) -> None:
        self.exps, self.base, self.axis = list(exps), base, axis
        self._fits: dict[tuple[tuple[str, tuple[tuple[str, float], ...]], ...], Any] = {}

    def fit(self, effects: Mapping[str, Mapping[str, float]]) -> Any:
        """The fit (``DynamicCalibrationResult``); raises :class:`CalibrationError`."""
        key = tuple(sorted((e, tuple(sorted(v.items()))) for e, v in effects.items()))
        if key not in self._fits:
            seen = experiments_through(self.exps, effects) if effects else self.exps
            self._fits[key] = cd.calibrate_dynamic(
                seen,
                slew_rate_v_per_s=self.base.service.ramp_rate_v_per_s,
                rest_voltage_v=self.base.axes[self.axis].safe_voltage_v,
            )
        return self._fits[key]

    def rms(self, effects: dict[str, dict[str, float]]) -> float:
        """Training RMS (um) of the fit (``inf`` when it fails)."""
        try:
            return float(self.fit(effects).residual_rms_um)
        except CalibrationError:
            return math.inf

    def config(self, effects: Mapping[str, Mapping[str, float]]) -> ScannerConfig:
        """The base config with the fitted dynamic model in force on the axis."""
        cfg = cd.calibrated_config(self.fit(effects), axis=self.axis, base=self.base)
        return cfg.with_axis(self.axis, model="dynamic")


def _verify(
    bench: StageBench, config: ScannerConfig, axis: AxisName, points: Sequence[VerifyPoint], loops: int
) -> list[dict[str, Any]]:
    ax = config.axes[axis]
    model = axis_model(ax)
    rate = 1.0 / bench.dt
    lo_v, hi_v = ax.voltage_min_v, ax.voltage_max_v
    # the model has seen every voltage the stage has (as the daemon's driver carries its state
    # through frames, moves and holds): its creep memory is the stage's, its clock the stage's.
    # Block by block, as the driver does: the whole history at once (a full frame and the
    # verifications before, tens of millions of samples) took several GB of per-sample state.
    state = model.rest(0.0)
    for played in bench.history:
        for i in range(0, played.size, HISTORY_BLOCK):
            _, state = model.forward(played[i : i + HISTORY_BLOCK], bench.dt, state)
    rows = []
    for k, pt in enumerate([points[0], *points]):
        lo = pt.offset_um - 0.5 * pt.range_um
        per = max(8, round(rate / pt.frequency_hz))
        here = model.position(state)
        n_move = max(1, round(abs(lo - here) / (0.5 * pt.range_um * pt.frequency_hz) * rate))
        move = np.linspace(here, lo, n_move + 1)[1:]
        phase = (np.arange(1, per * (1 + loops) + 1) % per) / per
        target = np.concatenate([move, lo + pt.range_um * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)])
        v, state = model.inverse(target, bench.dt, state)
        clamped = int(np.count_nonzero((v < lo_v) | (v > hi_v)))
        v = np.clip(v, lo_v, hi_v)
        t, x = bench.play(v)
        if bench.last_truth is not None:
            x = bench.last_truth  # a sensor delay is not an error of the position: score where the stage is
        if k == 0:
            continue  # one unrecorded warm-up scan after the model is switched in
        k0 = n_move + per
        lin = experiment_linearity(Experiment("verify", axis, t[k0:], v[k0:], x[k0:], target_um=target[k0:]))
        rows.append(
            {
                "why": pt.why,
                "inside_frame": pt.inside_frame,
                "range_um": pt.range_um,
                "frequency_hz": pt.frequency_hz,
                "offset_um": pt.offset_um,
                "nonlinearity_pct": float(lin.nonlinearity_pct),
                "length_error_pct": float(lin.length_error_pct),
                "position_offset_um": float(np.mean(x[k0:] - target[k0:])),
                "clamped": clamped,
            }
        )
    return rows


def _worst(rows: Sequence[dict[str, Any]], inside_only: bool = True) -> dict[str, float]:
    sel = [r for r in rows if r["inside_frame"] or not inside_only]
    return {m: max(abs(float(r[m])) for r in sel) for m in METRICS}


def _injected_parts(specs: Sequence[str]) -> dict[str, dict[str, float]]:
    """``{effect: {parameter: value}}`` of the injected specs that have a runtime part or are the
    sensor path."""
    out: dict[str, dict[str, float]] = {}
    known = {**PART_EFFECTS, **SENSOR_EFFECTS, "resonance": RESONANCE_PARAMS}
    for text in specs:
        head, value = text.split("=", 1)
        effect, _, name = head.partition(".")
        sensor_ok = effect not in SENSOR_EFFECTS or _is_sensor_side(text, specs)
        if effect in known and name in known[effect] and sensor_ok:
            out.setdefault(effect, {})[name] = float(value)
    return out


def _is_sensor_side(text: str, specs: Sequence[str]) -> bool:
    """Whether the spec ``text`` is an effect of the readback only (hil_sim's delay ``at: sensor``,
    its default)."""
    effect = text.split("=", 1)[0].partition(".")[0]
    return effect in SENSOR_EFFECTS and f"{effect}.at=drive" not in specs


def run_case(
    specs: Sequence[str],
    *,
    stage_path: Path | None = None,
    axis: AxisName = "x",
    reduced: bool = True,
    loops: int = 3,
    seed: int = 1,
    audit_effects: Sequence[str] | None = None,
    folds: int = 4,
    on_step: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Frame, baseline, audit, extended model and their verification on the stage with ``specs``.

    Returns
    -------
    dict
        ``specs``, ``findings`` (audit ids), ``adoption`` (adopted / skipped lines), ``baseline`` and
        ``extended`` (``rows`` per point and ``worst`` inside the frame), ``injected`` (the same
        refit with the injected values of the effects that have a runtime part), ``seconds``.
    """
    from piezod.audit import result_json, run_audit

    t0 = time.perf_counter()
    path = stage_path or default_sim_config_path()
    base = load_config(path)
    rate = base.sample_rate_hz
    frame = default_frame(base, axis, reduced=reduced)
    sensor_side = [x for x in specs if _is_sensor_side(x, specs)]
    truth = _stage(path, [x for x in specs if x not in sensor_side], axis, seed) if sensor_side else None
    bench = StageBench(_stage(path, specs, axis, seed), rate, truth=truth)
    exps = bench.play_frame(frame, axis, base.service.ramp_rate_v_per_s)
    step = on_step or (lambda _s: None)
    step("frame")
    refits = _Refits(exps, base, axis)
    baseline = refits.config({})
    step("baseline")
    points = verification_points(baseline, frame, reduced=reduced, axis=axis)
    out: dict[str, Any] = {"specs": list(specs)}
    out["baseline"] = {"rows": _verify(bench, baseline, axis, points, loops)}
    step("baseline verified")
    if not specs:
        out["findings"], out["adoption"] = [], {"adopted": [], "skipped": []}
        out["extended"] = out["baseline"]
    else:
        # the candidates piezod calibrate audits its frame for: those a runtime part or the sensor
        # path can take (the others could not be adopted)
        options = adoption_audit_options(folds)
        if audit_effects:
            options = dataclasses.replace(options, effects=tuple(audit_effects))
        doc = result_json(run_audit(exps, [], options=options))
        step("audit")
        adoption: Adoption = adopt_findings(doc["findings"], horizon_s=trend_horizon_s(exps))
        out["findings"] = [f["effect"] for f in doc["findings"]]
        out["adoption"] = {"adopted": list(adoption.adopted), "skipped": list(adoption.skipped)}
        if adoption.effects:
            # as piezod calibrate's refine_adoption, on the bench's model (the dynamic model)
            refined, notes = refine_findings(adoption.effects, refits.rms)
            if notes:
                adoption = dataclasses.replace(adoption, effects=refined)
                out["refined"] = notes
                out["adoption"]["adopted"] = list(adoption.adopted)
            extended = extended_config(refits.config(adoption.effects), axis, adoption)
        else:
            extended = baseline
        # as piezod calibrate: the resonance fitted on what the extended model leaves
        extended, found = adopt_resonance(exps, axis, extended)
        if found is not None:
            key = "adopted" if found.adopted else "skipped"
            out["adoption"][key] = [*out["adoption"][key], found.note]
        out["extended"] = {"rows": _verify(bench, extended, axis, points, loops)}
        step("extended verified")
        injected = _injected_parts(specs)
        if injected:
            # the same refit with the injected values: what the runtime parts do when the finding is right
            oracle = extended_config(refits.config(injected), axis, Adoption(injected))
            out["injected"] = {"rows": _verify(bench, oracle, axis, points, loops)}
            step("injected verified")
    for key in ("baseline", "extended", "injected"):
        if key not in out:
            continue
        out[key]["worst"] = _worst(out[key]["rows"])
    out["seconds"] = time.perf_counter() - t0
    return out


def score(case: dict[str, Any], floor: dict[str, float], resolution_pct: float) -> dict[str, Any]:
    """What the baseline and the extended model leave of the effect's error, and whether the target is met."""
    left: dict[str, dict[str, float]] = {}
    met = True
    below = True
    for m in METRICS:
        lb = max(0.0, case["baseline"]["worst"][m] - floor[m])
        le = max(0.0, case["extended"]["worst"][m] - floor[m])
        left[m] = {"baseline": lb, "extended": le, "fraction": le / lb if lb > 0 else math.nan}
        if lb > resolution_pct:
            below = False
            met = met and le <= TARGET_FRACTION * lb
    if "injected" in case:
        for m in METRICS:
            left[m]["injected"] = max(0.0, case["injected"]["worst"][m] - floor[m])
    return {"left": left, "below_resolution": below, "met": met and not below}


def _case_key(specs: Sequence[str], reduced: bool, loops: int, seed: int) -> dict[str, Any]:
    return {"specs": list(specs), "frame": "reduced" if reduced else "full", "loops": loops, "seed": seed}


def _load_case(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
    """A case saved by an earlier run with the same ``key``, None when there is none."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}:{exc.lineno}: not a saved effects case: {exc.msg}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("case"), dict):
        raise ConfigError(f"{path}: not a saved effects case (no 'case')")
    if doc.get("key") != key:
        raise ConfigError(
            f"{path}: saved for {doc.get('key')!r}, this run is {key!r} (another directory, or remove it)"
        )
    case: dict[str, Any] = doc["case"]
    return case


def _save_case(path: Path, key: dict[str, Any], case: dict[str, Any]) -> None:
    atomic_write_text(path, json.dumps({"key": key, "case": case}, indent=1) + "\n")


def run_effects_bench(
    effects: Sequence[str] | None = None,
    *,
    reduced: bool = True,
    loops: int = 3,
    seed: int = 1,
    resolution_pct: float = 0.01,
    on_step: Callable[[str], None] | None = None,
    jobs: int = 1,
    cases_dir: Path | None = None,
) -> dict[str, Any]:
    """The table of the module docstring for ``effects`` (default: every hil_sim effect).

    ``jobs > 1`` runs the cases (the floor and one per effect: each independent, deterministic
    for its seed) in that many worker processes; ``on_step`` then hears one ``"case"`` per
    finished case instead of every step.

    ``cases_dir`` keeps every case as it ends (``floor.json``, ``<effect>.json``), so that a run
    stopped half way loses only the cases still running: a later run with the same directory
    and settings takes the saved cases instead of running them again.

    Raises
    ------
    ConfigError
        A file in ``cases_dir`` is not a saved case, or was saved with other specs, frame,
        loops or seed.
    """
    from piezod.simulator import sim_effect_names

    names = list(effects) if effects else list(sim_effect_names())
    labels = ["floor", *names]
    specs = [[], *(realistic_specs(name) for name in names)]
    keys = [_case_key(sp, reduced, loops, seed) for sp in specs]
    paths = [cases_dir / f"{label}.json" if cases_dir is not None else None for label in labels]
    cases: list[dict[str, Any] | None] = [
        _load_case(path, key) if path is not None else None for path, key in zip(paths, keys, strict=True)
    ]
    if cases_dir is not None:
        cases_dir.mkdir(parents=True, exist_ok=True)
    todo = [i for i, c in enumerate(cases) if c is None]

    def done(i: int, case: dict[str, Any]) -> None:
        cases[i] = case
        path = paths[i]
        if path is not None:
            _save_case(path, keys[i], case)

    if jobs > 1 and len(todo) > 1:
        import multiprocessing
        import queue

        step = on_step or (lambda _s: None)
        ended: queue.Queue[tuple[int, dict[str, Any] | None, BaseException | None]] = queue.Queue()
        # a Pool, not a ProcessPoolExecutor: stopped (Ctrl-C, SIGTERM) it terminates the cases
        # still running at once; the executor's exit waited for them (half an hour a case)
        pool = multiprocessing.get_context("spawn").Pool(processes=min(jobs, len(todo)))
        try:

            def report(i: int) -> tuple[Callable[[dict[str, Any]], None], Callable[[BaseException], None]]:
                def ok(case: dict[str, Any]) -> None:
                    ended.put((i, case, None))

                def bad(exc: BaseException) -> None:
                    ended.put((i, None, exc))

                return ok, bad

            for i in todo:
                ok, bad = report(i)
                pool.apply_async(
                    run_case,
                    (specs[i],),
                    {"reduced": reduced, "loops": loops, "seed": seed},
                    callback=ok,
                    error_callback=bad,
                )
            pool.close()
            failed: BaseException | None = None
            for _ in todo:
                i, case, exc = ended.get()
                # one failed case must not lose the others still running: they are saved as they end
                if exc is not None or case is None:
                    failed = failed or exc
                    continue
                done(i, case)
                step("case")
            pool.join()
        finally:
            pool.terminate()
        if failed is not None:
            raise failed
    else:
        for i in todo:
            done(i, run_case(specs[i], reduced=reduced, loops=loops, seed=seed, on_step=on_step))
    ready = [c for c in cases if c is not None]
    floor = ready[0]["baseline"]["worst"]
    rows = []
    for name, case in zip(names, ready[1:], strict=True):
        rows.append({"effect": name, **case, **score(case, floor, resolution_pct)})
    return {
        "stage": "built-in stage (configs/sim-stage.yaml) + one hil_sim effect: the baseline is the "
        "stage's own model family (self-consistency), the effect is hil_sim's implementation",
        "frame": "reduced" if reduced else "full",
        "loops": loops,
        "floor": floor,
        "resolution_pct": resolution_pct,
        "target_fraction": TARGET_FRACTION,
        "rows": rows,
    }


def format_table(result: dict[str, Any]) -> str:
    """Markdown table: per effect the injected magnitude, the findings, and what each model leaves."""
    fl = result["floor"]
    lines = [
        f"floor (baseline, no effect): nonlinearity {fl['nonlinearity_pct']:.3f} %, "
        f"|length error| {fl['length_error_pct']:.3f} % (worst inside the frame)",
        "",
        "| effect (injected) | audit finds | adopted | nonlin. left: baseline / extended (%) | "
        "length err. left: baseline / extended (%) | extended <= 1/3 baseline | "
        "parts with the injected value: nonlin. / length err. left (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        left = r["left"]
        verdict = "below resolution" if r["below_resolution"] else ("**yes**" if r["met"] else "no")
        injected = ", ".join(s.split(".", 1)[1] for s in r["specs"])
        adopted = "; ".join(a.split(" (")[0] for a in r["adoption"]["adopted"]) or "-"
        oracle = (
            f"{left['nonlinearity_pct']['injected']:.3f} / {left['length_error_pct']['injected']:.3f}"
            if "injected" in left["nonlinearity_pct"]
            else "no runtime part"
        )
        lines.append(
            f"| {r['effect']} ({injected}) | {', '.join(r['findings']) or 'none'} | {adopted} | "
            f"{left['nonlinearity_pct']['baseline']:.3f} / {left['nonlinearity_pct']['extended']:.3f} | "
            f"{left['length_error_pct']['baseline']:.3f} / {left['length_error_pct']['extended']:.3f} | "
            f"{verdict} | {oracle} |"
        )
    return "\n".join(lines)


def plot_effects(result: dict[str, Any], path: str | Path) -> Path:
    """Bar chart: per effect, the error left by the baseline and the extended model (both metrics)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    names = [r["effect"] for r in rows]
    xs = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    for ax, m, label in zip(axes, METRICS, ("nonlinearity", "|length error|"), strict=True):
        base = [r["left"][m]["baseline"] for r in rows]
        ext = [r["left"][m]["extended"] for r in rows]
        inj = [r["left"][m].get("injected", np.nan) for r in rows]
        ax.bar(xs - 0.27, base, 0.27, label="baseline (dynamic model)")
        ax.bar(xs, ext, 0.27, label="extended (audit findings as runtime parts / sensor path)")
        ax.bar(xs + 0.27, inj, 0.27, label="parts / sensor path with the injected value")
        ax.set_xticks(xs, names, rotation=30, ha="right")
        ax.set_ylabel(f"{label} left above the no-effect floor (%)")
        ax.set_title(f"{label}: worst online-corrected scan inside the frame", fontsize=10)
        ax.legend(fontsize=8)
    fig.suptitle(
        "Error each hil_sim effect leaves after online correction (built-in stage + one effect, "
        "realistic magnitude)"
    )
    out = Path(path)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


__all__ = [
    "StageBench",
    "format_table",
    "plot_effects",
    "realistic_specs",
    "run_case",
    "run_effects_bench",
    "score",
]
