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

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]

import stage_server as fs  # noqa: E402
from take_apart_driver import run  # noqa: E402

SWITCHES: dict[str, dict[str, float]] = {
    "noae": {"ae_tau_s": 1e30},
    "notemp": {"amb_ramp_k_per_s": 0.0, "amb_step_k": 0.0, "self_tan_delta": 0.0},
    "noslew": {"amp_i_max_a": 1e6},
    "nomode2": {"mode2_weight": 0.0},
}


def main(argv: list[str]) -> int:
    return run(argv, __doc__ or "", HERE, lambda: fs.ForeignStage(seed=7), fs.PARAMS, SWITCHES)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
