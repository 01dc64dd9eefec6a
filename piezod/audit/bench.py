"""``piezod bench audit``: the audit over a corpus generated in process, and its numbers.

The corpus (nothing is read from disk except the shipped P-885 recordings):

* **hidden effects** (own-model self-consistency): thesis-model sessions
  (:func:`piezod.audit.synthetic.hidden_session`, random stage parameters, a small calibration
  frame) with one effect each at a random realistic magnitude and sign (the ranges of
  :data:`MAGNITUDES`), and clean sessions;
* **variants** (stable verdicts): every hidden-effect session decimated by 2 and re-split (the
  even and the odd experiments alone); the verdict must not change;
* **stand-ins for real data** (other physics, :mod:`piezod.audit.standins`): a PNZT disc with a
  voltage hold and a known linear drift, a 5 kHz actuator and its 200 Hz decimation, a
  ferroelectric switching above its coercive voltage, loops below it;
* **stages of other physics** (hil_sim presets ``pi-stage``, ``p885-stage``, run in process): a
  small frame, its decimation by 2 and its even / odd experiments (the verdict must not change),
  and the frame with a 600 s voltage hold (at 100 samples/s) with and without a hidden linear
  drift of 1 nm/s (the verdict changes on these stages are listed apart from the invariance
  failures of the own-model sessions and the stand-ins);
* **real recordings**: the P-885 stack (validation file, blocked split in time, decimated by 2).

Printed: the confusion matrix (rows: what is hidden, columns: the cause named), the false-alarm
rate (clean sessions with a cause other than ``none``), invariance failures, findings outside
the physical bounds, and the CPU time per audit.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from piezod.audit import CAUSES, EFFECTS
from piezod.audit.bounds import implausible
from piezod.audit.decide import AuditResult, run_audit
from piezod.audit.standins import (
    actuator_5khz,
    butterfly_session,
    decimate,
    one_period_triangles,
    pnzt_hold_session,
    preset_session,
)
from piezod.audit.synthetic import frame_plan, hidden_session
from piezod.recording import Experiment, read_experiments, split_experiments
from piezod.synth import random_params

#: Realistic magnitude ranges of the hidden effects (signed ones get a random sign), the ranges
#: of ``hil_sim.effects.random_effect``: drift 0.2-2 nm/s, thermal 0.5-3 %/h, stiffness
#: 0.03-0.15 %/um, polarity 3-10 %, delay 0.1-1 ms, saturation 60-150 um, creep 3-5 %/decade;
#: resonance 150-300 Hz (Q 5-30), below the small frame's highest resolvable frequency (~1.1 kHz
#: at 2560 samples/s) where random_effect's 300-1500 Hz would often be invisible.
MAGNITUDES: dict[str, dict[str, tuple[float, float, bool]]] = {
    "drift": {"rate_nm_per_s": (0.2, 2.0, True)},
    "thermal": {"rate_pct_per_hour": (0.5, 3.0, True)},
    "stiffness": {"sensitivity_pct_per_um": (0.03, 0.15, True)},
    "polarity": {"negative_sensitivity_pct": (3.0, 10.0, True)},
    "resonance": {"f0_hz": (150.0, 300.0, False), "q": (5.0, 30.0, False)},
    "delay": {"delay_s": (1e-4, 1e-3, False)},
    "saturation": {"x_sat_um": (60.0, 150.0, False)},
    "creep": {"pct_per_decade": (3.0, 5.0, False)},
}

P885 = Path(__file__).resolve().parents[1] / "data" / "real" / "pi-p885"


def draw(effect: str, rng: np.random.Generator) -> dict[str, Any]:
    """A random realistic magnitude of ``effect`` (:data:`MAGNITUDES`)."""
    out: dict[str, Any] = {}
    for name, (lo, hi, signed) in MAGNITUDES[effect].items():
        v = float(rng.uniform(lo, hi))
        out[name] = v * float(rng.choice((-1.0, 1.0))) if signed else v
    if effect == "creep":
        out["law"] = str(rng.choice(["motion", "k"]))
    return out


def hidden(effect: str | None, seed: int) -> list[Experiment]:
    """A small thesis-model frame (3 ranges x 3 frequencies 0.05-5 Hz, 3 references, 512 samples/loop)."""
    rng = np.random.default_rng(seed)
    fx = {} if effect is None else {effect: draw(effect, rng)}
    params = random_params(rng)
    plan = frame_plan(
        rng, ranges_v=(120.0, 260.0, 400.0), n_frequencies=3, frequency_hz=(0.05, 5.0), n_references=3
    )
    return split_experiments(hidden_session(params, plan, fx, samples_per_loop=512, seed=rng).recording)


def _decimated(exps: Sequence[Experiment], k: int) -> list[Experiment]:
    return [decimate(e, k) for e in exps]


def _audit(
    exps: Sequence[Experiment], val: Sequence[Experiment] = (), family_laws: Sequence[str] = ()
) -> tuple[AuditResult, float]:
    """The audit and its CPU time; with ``family_laws``, checked against those laws of the family
    as ``piezod audit`` does (:func:`piezod.family_heldout.audit_with_family`)."""
    t0 = time.process_time()
    if family_laws:
        from piezod.family_heldout import audit_with_family

        r = audit_with_family(exps, val, laws=family_laws).result
    else:
        r = run_audit(exps, val)
    return r, time.process_time() - t0


def _outside_bounds(r: AuditResult) -> list[str]:
    sc = r.final_fit.model.scales
    return [
        f"{f.effect}: {why}"
        for f in r.findings
        if f.effect in EFFECTS and (why := f.implausible or implausible(f.effect, f.params, sc))
    ]


#: The other-physics presets of the corpus (``configs/sim-NAME.yaml``).
PRESETS: tuple[str, ...] = ("pi-stage", "p885-stage")


def run_corpus(
    n: int = 2,
    *,
    seed: int = 9000,
    effects: Sequence[str] = EFFECTS,
    presets: Sequence[str] = PRESETS,
    with_standins: bool = True,
    on_audit: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Audit the corpus; ``n`` sessions per hidden effect (and clean). Returns the numbers.

    ``effects``, ``presets`` and ``with_standins=False`` select a part (the short test of the default
    test run); the full corpus is the default.
    """
    tick = on_audit or (lambda _s: None)
    matrix: dict[str, Counter[str]] = {}
    seconds: list[float] = []
    invariance: list[str] = []
    lost: list[str] = []
    bounds: list[str] = []
    rows: list[dict[str, Any]] = []

    def record(name: str, r: AuditResult, s: float) -> None:
        seconds.append(s)
        bounds.extend(f"{name}: {b}" for b in _outside_bounds(r))
        rows.append(
            {
                "name": name,
                "cause": r.cause,
                "findings": [f.effect for f in r.findings],
                "cpu_s": round(s, 2),
            }
        )
        tick(name)

    for h in ("none", *effects):
        matrix[h] = Counter()
        for k in range(n):
            s_ = seed + 100 * (EFFECTS.index(h) + 1 if h != "none" else 0) + k
            exps = hidden(None if h == "none" else h, s_)
            r, s = _audit(exps)
            record(f"{h}#{k}", r, s)
            matrix[h][r.cause] += 1
            if h == "none" or k > 0:
                continue
            # Variants of the first session of each effect: decimated by 2, and re-split.
            for vname, vexps in (
                ("decimated x2", _decimated(exps, 2)),
                ("even experiments", exps[::2]),
                ("odd experiments", exps[1::2]),
            ):
                rv, sv = _audit(vexps)
                record(f"{h}#{k} {vname}", rv, sv)
                if rv.cause != r.cause:
                    # A variant with less data may lose a weak effect ("none"): a loss of power,
                    # listed apart from a verdict that changes to another cause.
                    (lost if rv.cause == "none" else invariance).append(
                        f"{h}#{k}: {r.cause} -> {vname}: {rv.cause}"
                    )
    standins: list[dict[str, Any]] = []

    def stand(
        name: str,
        expect: str | tuple[str, ...],
        exps: Sequence[Experiment],
        val: Sequence[Experiment] = (),
        family_laws: Sequence[str] = (),
    ) -> str:
        r, s = _audit(exps, val, family_laws)
        expected = (expect,) if isinstance(expect, str) else expect
        record(name, r, s)
        f0 = r.findings[0] if r.findings else None
        standins.append(
            {
                "name": name,
                "expected": " or ".join(expected),
                "cause": r.cause,
                "params": {} if f0 is None else {k: _round(v) for k, v in f0.params.items()},
                "gain": None if f0 is None else _round(f0.gain),
                "gain_se": None if f0 is None else _round(f0.gain_se),
                "ok": r.cause in expected,
            }
        )
        return r.cause

    if with_standins:
        stand("PNZT hold, drift +0.63 nm/s", "drift", pnzt_hold_session(0.63))
        stand("one-period triangles 1-0.01 Hz, log creep", "creep", one_period_triangles())
        act = actuator_5khz(seconds=6.0)
        c5 = stand("actuator 5 kHz, lag 2 ms", "delay", [act])
        c2 = stand("same, decimated to 200 Hz", "delay", [decimate(act, 25)])
        if c5 != c2:
            invariance.append(f"actuator: 5 kHz {c5} -> 200 Hz {c2}")
        stand("butterfly above the coercive voltage", "switching", butterfly_session())
        if P885.is_dir():
            ident = read_experiments([P885 / "identification.csv"])
            val = read_experiments([P885 / "validation.csv"])
            # Real data, no hidden truth: a cause is right when the model family's best member,
            # which predicts the held-out data 2.7 x better than the audit's baseline, carries it
            # (a stiffness of -0.2 to -0.37 %/um in every law, a creep spectrum; SOURCE.md
            # documents the creep). The lag the ODE baseline needs (11-16 ms) it does not: the
            # audits are checked against the family as `piezod audit` does.
            p885 = ("creep", "stiffness")
            laws = ("prandtl-ishlinskii",)
            a = stand("P-885, validation file", p885, ident, val, laws)
            b = stand("P-885, blocked split", p885, ident, family_laws=laws)
            c = stand("P-885, decimated to 100 Hz", p885, _decimated(ident, 2), family_laws=laws)
            if len({a, b, c}) > 1:
                invariance.append(f"P-885: validation {a}, blocked {b}, decimated {c}")
    other: list[dict[str, Any]] = []
    other_changes: list[str] = []
    for name in presets:
        exps = preset_session(name)
        r, s = _audit(exps)
        record(f"{name} frame", r, s)
        causes = {"frame": r.cause}
        for vname, vexps in (
            ("decimated x2", _decimated(exps, 2)),
            ("even experiments", exps[::2]),
            ("odd experiments", exps[1::2]),
        ):
            rv, sv = _audit(vexps)
            record(f"{name} {vname}", rv, sv)
            causes[vname] = rv.cause
            if rv.cause != r.cause:
                other_changes.append(f"{name}: {r.cause} -> {vname}: {rv.cause}")
        other.append({"name": f"{name} frame", "causes": causes, "findings": _findings(r)})
        for rate in (0.0, 1.0):
            fx = (f"drift={rate:g}",) if rate else ()
            rh, sh = _audit(preset_session(name, fx, hold_s=600.0, rate_hz=100.0))
            label = f"{name} + 600 s hold" + (f", drift {rate:g} nm/s" if rate else ", no drift")
            record(label, rh, sh)
            found = [f for f in rh.findings if f.effect == "drift"]
            hold = {
                "name": label,
                "causes": {"frame + hold": rh.cause},
                "findings": _findings(rh),
                "drift_expected_nm_per_s": rate,
            }
            if rate:
                hold["drift_ok"] = bool(found) and abs(found[0].params["rate_nm_per_s"] - rate) <= 0.3 * rate
            else:
                hold["drift_ok"] = not found
            other.append(hold)
    clean = matrix["none"]
    n_clean = sum(clean.values())
    right = sum(matrix[h][h] for h in effects)
    n_eff = sum(sum(matrix[h].values()) for h in effects)
    return {
        "matrix": {h: dict(c) for h, c in matrix.items()},
        "hidden_right": right,
        "hidden_total": n_eff,
        "false_alarm_rate": (n_clean - clean["none"]) / n_clean if n_clean else math.nan,
        "invariance_failures": invariance,
        "power_losses": lost,
        "outside_bounds": bounds,
        "standins": standins,
        "other_physics": other,
        "other_physics_changes": other_changes,
        "cpu_s_median": float(np.median(seconds)),
        "cpu_s_max": float(np.max(seconds)),
        "audits": len(seconds),
        "rows": rows,
    }


def _findings(r: AuditResult) -> list[str]:
    return [
        f.effect + " (" + ", ".join(f"{k} {v:.4g}" for k, v in f.params.items() if math.isfinite(v)) + ")"
        for f in r.findings
    ]


def _round(v: float) -> float | None:
    return float(f"{v:.4g}") if math.isfinite(v) else None


def format_report(res: dict[str, Any]) -> str:
    """The numbers as text (also the generated block of ``docs/audit.md``)."""
    causes = [c for c in CAUSES if c != "sensitivity_gain"]
    short = {c: c[:6] for c in causes}
    short.update({"sensitivity_loss": "s.loss", "undetermined": "undet", "unexplained": "unexpl"})
    lines = ["hidden effect (rows) -> cause named (columns), small thesis-model frames:"]
    lines.append(f"{'':>11} " + " ".join(f"{short[c]:>6}" for c in causes))
    for h, row in res["matrix"].items():
        lines.append(f"{h:>11} " + " ".join(f"{row.get(c, 0):6d}" for c in causes))
    lines.append(
        f"hidden effects named right: {res['hidden_right']}/{res['hidden_total']}; false-alarm rate on "
        f"clean sessions: {res['false_alarm_rate']:.2f}"
    )
    lines.append("stand-ins for real data and the real P-885 recordings:")
    for s in res["standins"]:
        par = ", ".join(f"{k} {v:.4g}" for k, v in s["params"].items() if v is not None)
        gain = "" if s["gain"] is None else f", gain {s['gain']:.3g} +- {s['gain_se'] or 0:.2g}"
        lines.append(
            f"  {s['name']}: {s['cause']} ({'ok' if s['ok'] else 'expected ' + s['expected']}){gain}"
            + (f"; {par}" if par else "")
        )
    other = res.get("other_physics", [])
    if other:
        lines.append("stages of other physics (hil_sim presets, no hidden effect unless named):")
    for o in other:
        named = ", ".join(f"{k}: {v}" for k, v in o["causes"].items())
        ok = "" if "drift_ok" not in o else f" [drift {'ok' if o['drift_ok'] else 'WRONG'}]"
        lines.append(
            f"  {o['name']}: {named}{ok}"
            + (f"; findings {'; '.join(o['findings'])}" if o["findings"] else "")
        )
    oc = res.get("other_physics_changes", [])
    if other:
        lines.append(f"  verdicts that change on a stage of other physics (decimated / re-split): {len(oc)}")
        lines.extend(f"    {x}" for x in oc)
    inv = res["invariance_failures"]
    lines.append(
        f"invariance failures (another cause when decimated / re-split / held out otherwise): {len(inv)}"
    )
    lines.extend(f"  {x}" for x in inv)
    lost = res.get("power_losses", [])
    lines.append(f"weak effects lost with half the data (cause none): {len(lost)}")
    lines.extend(f"  {x}" for x in lost)
    ob = res["outside_bounds"]
    lines.append(f"findings outside the physical bounds: {len(ob)}")
    lines.extend(f"  {x}" for x in ob)
    lines.append(
        f"CPU time per audit: median {res['cpu_s_median']:.1f} s, max {res['cpu_s_max']:.1f} s "
        f"({res['audits']} audits)"
    )
    return "\n".join(lines)
