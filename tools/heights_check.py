"""Heights from the z voltage on a simulated microscope: forward model vs linear conversion.

Scans the ``steps-100nm`` sample twice on the simulated microscope of a scanner YAML (a calibration
scan and a different verification scan), and converts the verification scan's z voltage to
heights, against the hidden true z extension (the simulator's truth log), per image line levelled:

* ``linear``: one constant sensitivity (the best fit to the true heights: the most favourable);
* ``model (config)``: the z axis's model as the scanner YAML states it (nominal parameters);
* ``model (z fitted)``: the model family fitted to the calibration scan's z voltage against its
  true z extension - the truth standing in for a z sensor used once (:func:`piezod.heights.fit_z_model`).

Usage::

    python tools/heights_check.py [--config configs/sim-pi-microscope.yaml] [--json F]

``configs/sim-pi-microscope.yaml``: a z piezo of other physics (Prandtl-Ishlinskii, voltage-driven
power-law creep); ``configs/sim-microscope.yaml``: the controller's own model (self-consistency).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.server import spawn_sim
from piezod.config import MicroscopeSection, load_config
from piezod.errors import CalibrationError
from piezod.heights import compare_heights, fit_z_model, z_experiments
from piezod.image import forward_heights, raster_samples
from piezod.imagecal import read_truth_log
from piezod.recording import read_recording
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest

SCANS = {
    "calibration": ScanRequest(range_um=20.0, line_rate_hz=2.0, lines=8, pixels=256, name="zcal"),
    "calibration-slow": ScanRequest(range_um=20.0, line_rate_hz=0.5, lines=4, pixels=256, name="zcal-slow"),
    "verification": ScanRequest(range_um=16.0, line_rate_hz=1.0, lines=4, pixels=256, name="zver"),
}
#: The verification is compared at every 10th sample (the truth log's default density), so that
#: the plateau figures' edge margin (piezod.heights.EDGE_SAMPLES compared samples) keeps its meaning.
COMPARE_EVERY = 10


def _scan(engine: Engine, request: ScanRequest, path: Path) -> None:
    engine.start_scan(request, path=path)
    limit = time.monotonic() + 600.0
    while engine.status().state == "scanning" and time.monotonic() < limit:
        time.sleep(0.1)
    if engine.wait_idle(timeout_s=60.0) != "idle":
        raise SystemExit(f"scan {request.name} did not end cleanly: {engine.status().state}")
    engine.wait_recorded()


def _true_z(
    rs_t: np.ndarray, truth: tuple[np.ndarray, np.ndarray], rate: float, every: int = 1
) -> np.ndarray:
    """The true z extension (``truth``: the log's sample indices and z column) at every
    ``every``-th sample the log holds, NaN elsewhere: at a step the extension moves within a
    sample or two, which no interpolation between logged samples follows."""
    idx, z = truth
    k = np.rint(rs_t * rate).astype(np.int64)
    pos = np.clip(np.searchsorted(idx, k), 0, idx.size - 1)
    return np.where((idx[pos] == k) & (k % every == 0), z[pos], np.nan)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/sim-pi-microscope.yaml")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--keep", metavar="DIR", help="scan into DIR (kept); reuse its scans when there")
    args = ap.parse_args(argv)
    cfg_path = Path(args.config)
    base = load_config(cfg_path)
    config = (
        base if base.microscope is not None else base.model_copy(update={"microscope": MicroscopeSection()})
    )
    rate = base.sample_rate_hz
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(args.keep or tmp)
        d.mkdir(parents=True, exist_ok=True)
        truth = d / "truth.f64"
        recs = {name: d / f"{req.name}.csv" for name, req in SCANS.items()}
        if not (truth.exists() and all(p.exists() for p in recs.values())):
            _record(cfg_path, config, d, truth, recs)
        rs = {k: raster_samples(read_recording(p)) for k, p in recs.items()}
        log = read_truth_log(truth, "z_um")
        # the verification compared at every COMPARE_EVERY-th sample: the published figures' definition
        every = {k: COMPARE_EVERY if k == "verification" else 1 for k in rs}
        true = {k: _true_z(r.t_s, log, rate, every[k]) for k, r in rs.items()}
    _report(args, cfg_path, base, rs, true)
    return 0


def _record(cfg_path: Path, config: Any, d: Path, truth: Path, recs: dict[str, Path]) -> None:
    truth.unlink(missing_ok=True)
    args = ("--sample", "steps-100nm", "--truth-log", str(truth), "--truth-every", "1")
    with spawn_sim(cfg_path, extra_args=args) as sim:
        engine = Engine(config, sim.path, recording_dir=d)
        engine.open()
        try:
            for name, req in SCANS.items():
                _scan(engine, req, recs[name])
        finally:
            engine.close()


def _report(args: Any, cfg_path: Path, base: Any, rs: dict[str, Any], true: dict[str, Any]) -> None:
    rate = base.sample_rate_hz
    z_axis = base.axes["z"]
    axes = {"model (config)": z_axis}
    heldout: dict[str, float] = {}
    try:
        fitted, chosen, heldout = fit_z_model(
            z_experiments(rs["calibration"], true["calibration"], "zcal")
            + z_experiments(rs["calibration-slow"], true["calibration-slow"], "zcal-slow"),
            base,
        )
        axes["model (z fitted)"] = fitted
        if fitted.family is not None:
            chosen += f" (drive lag {fitted.family.lag_time_constant_s * 1e3:.3f} ms)"
    except CalibrationError as exc:
        chosen = f"none: {exc}"
    v = rs["verification"]
    assert v.z_voltage_v is not None
    rows = {}
    for name, axis in axes.items():
        heights = forward_heights(axis, v.z_voltage_v, 1.0 / rate)
        cmp, _, _ = compare_heights(v, heights, true["verification"])
        rows[name] = cmp
    first = next(iter(rows.values()))
    print(
        f"{cfg_path.name}: steps {first.step_um * 1e3:.1f} nm, verification scan "
        f"{SCANS['verification'].range_um:g} um at {SCANS['verification'].line_rate_hz:g} Hz "
        f"({first.samples} samples); z model fitted on the calibration scan: {chosen}"
    )
    print(f"{'conversion':<34} {'max % of step':>14} {'rms % of step':>14} {'plateau max %':>14}")
    print(
        f"{'linear (' + format(first.sensitivity_um_per_v, '.4f') + ' um/V)':<34} "
        f"{first.linear_max_pct:14.2f} {first.linear_rms_pct:14.2f} {first.linear_plateau_max_pct:14.2f}"
    )
    for name, cmp in rows.items():
        print(
            f"{name:<34} {cmp.model_max_pct:14.2f} {cmp.model_rms_pct:14.2f}"
            f" {cmp.model_plateau_max_pct:14.2f}"
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "config": str(cfg_path),
                    "step_um": first.step_um,
                    "linear": {
                        "max_pct": first.linear_max_pct,
                        "rms_pct": first.linear_rms_pct,
                        "sensitivity_um_per_v": first.sensitivity_um_per_v,
                        "plateau_max_pct": first.linear_plateau_max_pct,
                    },
                    **{
                        k: {
                            "max_pct": c.model_max_pct,
                            "rms_pct": c.model_rms_pct,
                            "plateau_max_pct": c.model_plateau_max_pct,
                        }
                        for k, c in rows.items()
                    },
                    "z_fit": {"chosen": chosen, "heldout_rms_um": heldout},
                },
                indent=2,
            )
        )


if __name__ == "__main__":
    sys.exit(main())
