"""The model family on the real PI P-885 stack: identify on one run, predict the other.

Usage::

    python tools/model_family_p885.py [--plays 32] [--json out.json]

Fits every law of the family (:func:`piezod.calibrate_family.fit_family`: hysteresis law, creep
spectrum, stiffness, first-order drive lag) to ``piezod/data/real/pi-p885/identification.csv``
and predicts ``validation.csv`` from rest with the fitted parameters (per experiment a position
offset, and -- as the audit does -- one sensor gain for the validation session, are nuisance
parameters; the first ``--skip-s`` seconds of each run, the start-up transient from an unknown
state, are left out of fit and scores). Reports RMS and the ratio to the sensor noise floor (third
differences of the
measured positions, :func:`piezod.audit.residuals.noise_floor`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from piezod.audit.residuals import noise_floor
from piezod.calibrate_dynamic import prepare_dynamic
from piezod.calibrate_family import (
    AFTER_EFFECT_LAWS,
    CREEP_DRIVERS,
    LAWS,
    fit_family,
    session_positions,
    settled_rows,
)
from piezod.heights import lagged_experiments
from piezod.recording import read_experiments

DATA = Path(__file__).resolve().parent.parent / "piezod" / "data" / "real" / "pi-p885"


def _prepare(  # type: ignore[no-untyped-def]
    name: str, delay_samples: int = 0, lag_samples: float = 0.0, rest_voltage_v: float | None = None
):
    exps = read_experiments([DATA / name])
    if lag_samples > 0.0:
        dt = float(np.median(np.diff(exps[0].t_s)))
        exps = lagged_experiments(exps, lag_samples * dt)
    if delay_samples > 0:
        # the readback aligned to the drive: the position recorded n samples later is the stage's now
        n = delay_samples
        exps = [
            dataclasses.replace(
                e,
                t_s=e.t_s[:-n],
                voltage_v=e.voltage_v[:-n],
                position_um=e.position_um[n:],
                target_um=None if e.target_um is None else e.target_um[:-n],
                line_numbers=None if e.line_numbers is None else e.line_numbers[:-n],
            )
            for e in exps
        ]
    v0 = float(exps[0].voltage_v[0]) if rest_voltage_v is None else rest_voltage_v
    return exps, prepare_dynamic(
        exps, max_samples_per_loop=4096, max_samples_per_experiment=1 << 16, rest_voltage_v=v0
    )


def prediction_error(data: Any, params: Any, rows: Any) -> tuple[Any, float]:
    """Prediction minus measurement on ``rows`` of a session, with one offset per experiment and
    one sensor gain for the session fitted (the nuisance parameters), and that gain."""
    x = data.centred(session_positions(data, params))[rows]
    y = data.centred(data.position_um)[rows]
    gain = float(x @ y / (x @ x))
    return gain * x - y, gain


def _plot(path: Path, valid: Any, law: str, driver: str, keep: Any, resid: Any, floor: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.concatenate(
        [
            e.t_start_s + np.linspace(0, e.duration_s, int(c))
            for e, c in zip(valid.experiments, valid.counts, strict=True)
        ]
    )[keep]
    v = valid.grid_voltage_v[valid.compared][keep]
    fig, ax = plt.subplots(2, 1, figsize=(9, 6.5))
    ax[0].plot(t, 1e3 * resid, lw=0.5)
    ax[0].axhline(1e3 * floor, color="k", ls=":", label=f"noise floor {1e3 * floor:.0f} nm rms")
    ax[0].axhline(-1e3 * floor, color="k", ls=":")
    ax[0].set_xlabel("time in the validation run (s)")
    ax[0].set_ylabel("predicted - measured (nm)")
    ax[0].legend(loc="upper right")
    ax[1].plot(v, 1e3 * resid, ",", alpha=0.5)
    ax[1].set_xlabel("drive voltage (V)")
    ax[1].set_ylabel("predicted - measured (nm)")
    fig.suptitle(
        f"Real P-885 validation run predicted by the family ({law}, {driver}-driven creep)\n"
        "fitted on identification.csv: residual over time and over the drive voltage"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--plays", type=int, default=32)
    ap.add_argument("--json", default=None)
    ap.add_argument("--skip-s", type=float, default=1.0, help="start-up transient left out (s)")
    ap.add_argument("--laws", nargs="+", default=list(LAWS), choices=LAWS, help="laws to fit")
    ap.add_argument(
        "--after-effect",
        action="store_true",
        help="also fit the generalised play and domain-wall laws with voltage creep and the after-effect "
        "of their memory (searched)",
    )
    ap.add_argument(
        "--centre-smoothing",
        type=float,
        default=None,
        help="generalised play law: penalty on its centre dependence (default: the calibration's)",
    )
    ap.add_argument(
        "--sensor-delay-samples",
        type=int,
        default=0,
        help="align the readback by this many samples first (SOURCE.md: the sensor lags by one)",
    )
    ap.add_argument(
        "--drive-lag-samples",
        type=float,
        default=0.0,
        help="run the drive voltage through an exact first-order lag of this many sample intervals and"
        " hold the fit's own (first-order form) lag at 0",
    )
    ap.add_argument("--plot", default=None, metavar="F.png", help="validation residual of the best member")
    args = ap.parse_args()
    ident_exps, ident = _prepare("identification.csv", args.sensor_delay_samples, args.drive_lag_samples)
    valid_exps, valid = _prepare("validation.csv", args.sensor_delay_samples, args.drive_lag_samples)
    floor_id = float(np.sqrt(np.mean([noise_floor(np.asarray(e.position_um)) ** 2 for e in ident_exps])))
    floor_va = float(np.sqrt(np.mean([noise_floor(np.asarray(e.position_um)) ** 2 for e in valid_exps])))
    rows = []
    best: tuple[float, tuple[str, str, Any, Any]] | None = None
    members = [(law, d, False) for law in args.laws for d in CREEP_DRIVERS]
    if args.after_effect:
        members += [(law, "voltage", True) for law in AFTER_EFFECT_LAWS if law in args.laws]
    for law, driver, after_effect in members:
        t0 = time.perf_counter()
        extra: dict[str, Any] = (
            {} if args.centre_smoothing is None else {"centre_smoothing": args.centre_smoothing}
        )
        if args.drive_lag_samples > 0.0:
            extra["fit_lag"] = False
        if after_effect:
            extra["after_effect"] = True
        fit = fit_family(ident, law, plays=args.plays, skip_s=args.skip_s, creep_driver=driver, **extra)
        keep = settled_rows(valid, args.skip_s)
        err, gain = prediction_error(valid, fit.params, keep)
        rms_valid = float(np.sqrt(np.mean(err**2)))
        if best is None or rms_valid < best[0]:
            best = (rms_valid, (law, driver, keep, err))
        p = fit.params
        rows.append(
            {
                "law": law + ("+after-effect" if after_effect else ""),
                "creep_driver": driver,
                "identification_rms_um": fit.rms_um,
                "validation_rms_um": rms_valid,
                "validation_gain": gain,
                "ratio_to_noise_floor": rms_valid / floor_va,
                "lag_ms": 1e3 * p.lag_time_constant_s,
                "stiffness_pct_per_um": p.stiffness_pct_per_um,
                "creep_total_pct": 100.0 * p.creep.total_creep,
                "seconds": time.perf_counter() - t0,
            }
        )
    print(f"noise floor: identification {floor_id:.4f} um, validation {floor_va:.4f} um")
    print(
        f"{'law':<20} {'creep driver':<13} {'ident RMS um':>13} {'valid RMS um':>13} {'valid/floor':>12}"
        f" {'lag ms':>7} {'k %/um':>8}"
    )
    for r in rows:
        print(
            f"{r['law']:<20} {r['creep_driver']:<13}"
            f" {r['identification_rms_um']:>13.4f} {r['validation_rms_um']:>13.4f}"
            f" {r['ratio_to_noise_floor']:>12.2f} {r['lag_ms']:>7.2f} {r['stiffness_pct_per_um']:>8.3f}"
        )
    if args.plot and best is not None:
        _plot(Path(args.plot), valid, *best[1], floor_va)
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {"noise_floor_um": {"identification": floor_id, "validation": floor_va}, "rows": rows},
                indent=2,
            )
        )
    return 0 if all(math.isfinite(r["validation_rms_um"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
