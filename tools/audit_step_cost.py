"""Where ``piezod calibrate``'s time goes on a simulated stage: the model choice and the steps of
the adoption audit, in process (docs/model-family.md section 3, "The audit step's cost").

Usage::

    OMP_NUM_THREADS=1 python tools/audit_step_cost.py --stage preisach-stage

The frame of :func:`piezod.stagecal.default_frame` is played on the preset's stage in this
process (as ``tools/model_family_verify.py`` does), then :func:`piezod.stagecal.choose_for_experiments`
and :func:`piezod.stagecal.audit_and_extend` run with their parts timed: every family fit (law,
creep driver, plays), the audit (:func:`piezod.audit.run_audit`), the profile of the adopted parts
(:func:`piezod.stagecal.refine_adoption`) and the choice redone through them. Wall-clock
seconds: run it on a quiet machine, one BLAS thread, and compare runs made side by side.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from collections.abc import Callable
from typing import Any

from model_family_verify import play_default_frame, start_config

from piezod import audit, stagecal
from piezod import calibrate_family as cf

_TIMES: dict[str, list[float]] = {}


def _timed(module: Any, name: str, label: Callable[..., str]) -> None:
    inner = getattr(module, name)

    @functools.wraps(inner)
    def run(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            dt = time.perf_counter() - t0
            _TIMES.setdefault(name, []).append(dt)
            print(f"  {name} {label(*args, **kwargs)}: {dt:.1f} s", flush=True)

    setattr(module, name, run)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", default="preisach-stage", help="preset name or scanner YAML with simulation:")
    ap.add_argument("--json", default=None, help="write the phase times here")
    args = ap.parse_args()
    played = play_default_frame(args.stage)
    exps, axis, ramp, rest = played.experiments, played.axis, played.ramp_v_per_s, played.rest_voltage_v

    def member(data: Any, law: str, **k: Any) -> str:
        return f"{law} {k.get('creep_driver', 'position')} {k.get('plays', cf.DEFAULT_PLAYS)} plays"

    _timed(cf, "fit_family", member)
    _timed(audit, "run_audit", lambda *a, **k: "")
    _timed(stagecal, "refine_adoption", lambda *a, **k: "")
    with_dyn = start_config(played)
    t0 = time.perf_counter()
    choice = stagecal.choose_for_experiments(exps, axis, with_dyn, ramp, rest)
    t_choice = time.perf_counter() - t0
    print(choice.report["table"])
    fits_in_choice = sum(_TIMES.pop("fit_family", []))
    t0 = time.perf_counter()
    audited = stagecal.audit_and_extend(exps, axis, choice, with_dyn, ramp, rest)
    t_audit = time.perf_counter() - t0
    print(audited.report["text"])
    t_run_audit = sum(_TIMES.get("run_audit", []))
    t_refine = sum(_TIMES.get("refine_adoption", []))
    phases = {
        "choice_s": round(t_choice, 1),
        "choice_fits_s": round(fits_in_choice, 1),
        "audit_step_s": round(t_audit, 1),
        "run_audit_s": round(t_run_audit, 1),
        "refine_s": round(t_refine, 1),
        "redone_choice_s": round(t_audit - t_run_audit - t_refine, 1),
        "adopted": audited.report["adopted"],
        "heldout_rms_nm": {k: round(1e3 * float(v), 2) for k, v in audited.report["heldout_rms_um"].items()},
    }
    print(json.dumps(phases, indent=1))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(phases, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
