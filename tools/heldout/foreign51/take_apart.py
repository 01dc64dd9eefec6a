#!/usr/bin/env python3
"""foreign51's stage in process, parts of its physics switched off, under a written scanner YAML.

    OMP_NUM_THREADS=1 python tools/heldout/foreign51/take_apart.py F.yaml [noae] [notemp] [noslew] [nomode2]
    OMP_NUM_THREADS=1 python tools/heldout/foreign51/take_apart.py --calibrate OUT.yaml [noae] ...
    (either with --json RUN.json: the verification's rows as model_family_verify.py writes them)

Plays ``piezod calibrate``'s frame and verification points (``tools/model_family_verify.py
--skip-dynamic --verify F.yaml``) on :class:`stage_server.ForeignStage`'s x axis (y and z held at
0 V) instead of a hil_sim stage, with the named parts off: ``noae`` the walls' thermally activated
after-effect (the creep), ``notemp`` the room's warming, the heater step and the self-heating,
``noslew`` the amplifier's current limit, ``nomode2`` the second mode. ``F.yaml`` is what
``piezod calibrate --port`` wrote on the stage (docs/model-family.md 6.2bt). With ``--calibrate
OUT.yaml`` the stage (with those parts off) is calibrated in process as ``piezod calibrate`` does
(``--audit --resonance --fast-creep``), the result written to ``OUT.yaml`` and verified: what the
calibration makes of the stage without a part, to say whether that part is what the member misses.
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

#: Each part's parameters and the value that switches it off (a factor on the parameter).
SWITCHES: dict[str, dict[str, float]] = {
    "noae": {"ae_tau_s": 1e30},
    "notemp": {"amb_ramp_k_per_s": 0.0, "amb_step_k": 0.0, "self_tan_delta": 0.0},
    "noslew": {"amp_i_max_a": 1e6},
    "nomode2": {"mode2_weight": 0.0},
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
        for key, factor in SWITCHES[name].items():
            params[key] = params[key] * factor
    fs.PARAMS.clear()
    fs.PARAMS.update(params)
    # the verification tool reads the base config (limits, rate) and a simulation section from one
    # YAML; the section is a placeholder: the stage below replaces whatever it describes
    scanner = yaml.safe_load((HERE / "scanner.yaml").read_text())
    scanner["simulation"] = yaml.safe_load((ROOT / "configs" / "sim-stage.yaml").read_text())["simulation"]
    with tempfile.TemporaryDirectory() as tmp:
        stage_yaml = Path(tmp) / "foreign51-stage.yaml"
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
