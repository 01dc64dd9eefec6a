"""The take-apart tools' shared driver: a foreign stage's x axis in process, parts of its physics
switched off, calibrated and verified by ``tools/model_family_verify.py`` as on a hil_sim stage.

Used by ``tools/heldout/*/take_apart.py``; each names its stage and the parts it can switch off.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[2]


class OneAxis:
    """A three-channel foreign stage's x axis as the one-axis stage
    :class:`piezod.effects_bench.StageBench` drives (y and z held at 0 V)."""

    def __init__(self, stage: Any) -> None:
        self.stage = stage

    def step(self, voltage_v: Any, dt_s: float) -> np.ndarray:
        v = np.asarray(voltage_v, dtype=np.float64)
        return np.asarray(self.stage.step(np.stack([v, np.zeros_like(v), np.zeros_like(v)]), dt_s)[0])

    def sense(self, position_um: Any, lsb_um: float | None = None) -> np.ndarray:
        return np.asarray(self.stage.sense(position_um))


def run(
    argv: Sequence[str],
    doc: str,
    stage_dir: Path,
    make_stage: Callable[[], Any],
    params: MutableMapping[str, Any],
    switches: Mapping[str, Mapping[str, float]],
) -> int:
    """Parse a take-apart tool's command line (usage from the first lines of its ``doc``), scale
    the stage's ``params`` in place by the factors of the named ``switches``, and verify (or, with
    ``--calibrate``, calibrate and verify) on ``make_stage()``'s x axis under ``stage_dir``'s
    ``scanner.yaml``; returns the verification tool's exit status."""
    ap = argparse.ArgumentParser(usage="\n".join(doc.strip().splitlines()[2:5]))
    ap.add_argument("yaml", help="the written scanner YAML to verify (with --calibrate: the one to write)")
    ap.add_argument("parts", nargs="*", help=f"parts of the physics to switch off: {', '.join(switches)}")
    ap.add_argument(
        "--calibrate", action="store_true", help="calibrate in process first, as piezod calibrate does"
    )
    ap.add_argument("--json", metavar="RUN.json", help="the verification tool's rows")
    args = ap.parse_args(list(argv))
    unknown = [name for name in args.parts if name not in switches]
    if unknown:  # not argparse's choices: it checks an empty list of parts against them too
        ap.error(f"no part {', '.join(unknown)} (parts: {', '.join(switches)})")
    for name in args.parts:
        for key, factor in switches[name].items():
            params[key] = params[key] * factor
    # the verification tool reads the base config (limits, rate) and a simulation section from one
    # YAML; the section is a placeholder: the stage below replaces whatever it describes
    scanner = yaml.safe_load((stage_dir / "scanner.yaml").read_text())
    scanner["simulation"] = yaml.safe_load((ROOT / "configs" / "sim-stage.yaml").read_text())["simulation"]
    with tempfile.TemporaryDirectory() as tmp:
        stage_yaml = Path(tmp) / f"{stage_dir.name}-stage.yaml"
        stage_yaml.write_text(yaml.safe_dump(scanner, sort_keys=False))
        tool = ROOT / "tools" / "model_family_verify.py"
        spec = importlib.util.spec_from_file_location("model_family_verify", tool)
        assert spec is not None and spec.loader is not None
        mfv = importlib.util.module_from_spec(spec)
        sys.modules["model_family_verify"] = mfv
        spec.loader.exec_module(mfv)
        mfv.__dict__["Stage"] = lambda cfg, axes=None: OneAxis(make_stage())
        what = ["--audit", "--resonance", "--fast-creep", "--config-out"] if args.calibrate else ["--verify"]
        json_out = ["--json", args.json] if args.json else []
        sys.argv = [tool.name, "--stage", str(stage_yaml), "--skip-dynamic", *json_out, *what, args.yaml]
        return int(mfv.main())
