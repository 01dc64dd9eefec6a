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

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]

import stage_server as fs  # noqa: E402
from take_apart_driver import run  # noqa: E402

#: Each part's parameters and the factor that switches it off.
SWITCHES: dict[str, dict[str, float]] = {
    "noenv": {"env_warm_k": 0.0, "env_hvac_k": 0.0},
    "noacc": {"acc_sigma_m": 0.0, "acc_sigma_a": 0.0},
    "nota": {"ta_kappa": 0.0},
    "nocreep": {"creep_gamma": 0.0},
}


def main(argv: list[str]) -> int:
    return run(argv, __doc__ or "", HERE, lambda: fs.ForeignStage(seed=7), fs.PARAMS, SWITCHES)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
