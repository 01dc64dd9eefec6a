#!/usr/bin/env python3
"""foreign49's stage in process, parts of its physics switched off, under a written scanner YAML.

    OMP_NUM_THREADS=1 python tools/heldout/foreign49/take_apart.py F.yaml [noenv] [noacc] [nota] [nocreep]
    OMP_NUM_THREADS=1 python tools/heldout/foreign49/take_apart.py --calibrate OUT.yaml [noenv] ...
    (either with --json RUN.json: the verification's rows as model_family_verify.py writes them)

Plays ``piezod calibrate``'s frame and verification points (``tools/model_family_verify.py
--skip-dynamic --verify F.yaml``) on :class:`stage_server.ForeignStage`'s x axis (y and z held at
0 V) instead of a hil_sim stage, with the named parts off: ``noenv`` the warm-up and the HVAC cycle,
``noacc`` the accommodation, ``nota`` the thermally activated loop widths, ``nocreep`` the creep.
``F.yaml`` is what ``piezod calibrate --port`` wrote on the stage (docs/model-family.md 6.2bm).
With ``--calibrate OUT.yaml`` the stage (with those parts off) is calibrated in process as ``piezod
calibrate`` does (``--audit --resonance --fast-creep``), the result written to ``OUT.yaml`` and
verified: what the calibration makes of the stage without a part, to say whether that part is
what the member misses.
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(HERE))

import stage_server as fs  # noqa: E402

SWITCHES = {
    "noenv": ("env_warm_k", "env_hvac_k"),
    "noacc": ("acc_sigma_m", "acc_sigma_a"),
    "nota": ("ta_kappa",),
    "nocreep": ("creep_gamma",),
}


class OneAxis:
    """The foreign stage's x axis as the one-axis stage :class:`piezod.effects_bench.StageBench` drives."""

    def __init__(self, seed: int) -> None:
        self.stage = fs.ForeignStage(seed=seed)

    def step(self, voltage_v: Any, dt_s: float) -> np.ndarray:
        v = np.asarray(voltage_v, dtype=np.float64)
        return np.asarray(self.stage.step(np.stack([v, np.zeros_like(v), np.zeros_like(v)]), dt_s)[0])

    def sense(self, position_um: Any, lsb_um: float | None = None) -> np.ndarray:
        return self.stage.sense(position_um)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(usage="\n".join(__doc__.strip().splitlines()[2:5]))
    ap.add_argument("yaml", help="the written scanner YAML to verify (with --calibrate: the one to write)")
    ap.add_argument("parts", nargs="*", help=f"parts of the physics to switch off: {', '.join(SWITCHES)}")
    ap.add_argument(
        "--calibrate", action="store_true", help="calibrate in process first, as piezod calibrate does"
    )
    ap.add_argument("--json", metavar="RUN.json", help="the verification tool's rows")
    args = ap.parse_args(argv)
    unknown = [name for name in args.parts if name not in SWITCHES]
    if unknown:  # not argparse's choices: it checks an empty list of parts against them too
        ap.error(f"no part {', '.join(unknown)} (parts: {', '.join(SWITCHES)})")
    params = copy.deepcopy(fs.PARAMS)
    for name in args.parts:
        for key in SWITCHES[name]:
            params[key] = params[key] * 0.0
    fs.PARAMS.clear()
    fs.PARAMS.update(params)
    # the verification tool reads the base config (limits, rate) and a simulation section from one
    # YAML; the section is a placeholder: the stage below replaces whatever it describes
    scanner = yaml.safe_load((HERE / "scanner.yaml").read_text())
    scanner["simulation"] = yaml.safe_load((ROOT / "configs" / "sim-stage.yaml").read_text())["simulation"]
    with tempfile.TemporaryDirectory() as tmp:
        stage_yaml = Path(tmp) / "foreign49-stage.yaml"
        stage_yaml.write_text(yaml.safe_dump(scanner, sort_keys=False))
        tool = ROOT / "tools" / "model_family_verify.py"
        spec = importlib.util.spec_from_file_location("model_family_verify", tool)
        assert spec is not None and spec.loader is not None
        mfv = importlib.util.module_from_spec(spec)
        sys.modules["model_family_verify"] = mfv
        spec.loader.exec_module(mfv)
        mfv.__dict__["Stage"] = lambda cfg, axes=None: OneAxis(7)
        what = ["--audit", "--resonance", "--fast-creep", "--config-out"] if args.calibrate else ["--verify"]
        json_out = ["--json", args.json] if args.json else []
        sys.argv = [tool.name, "--stage", str(stage_yaml), "--skip-dynamic", *json_out, *what, args.yaml]
        return int(mfv.main())


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
