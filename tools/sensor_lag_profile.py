"""The dynamic model's fit error against the readback lag the frame is aligned for.

The effects bench's ``delay`` case (``piezod bench effects``): the built-in stage with hil_sim's
realistic readback delay (0.32 ms delay + 0.32 ms lag), the full calibration frame stepped in
process; the dynamic model refitted on the frame seen through a sensor path of lag ``tau`` (no
pure delay) for each ``tau``: the profile :func:`piezod.extensions.refine_sensor_lag` searches.

Usage::

    python tools/sensor_lag_profile.py [--lags-ms 0 0.3 0.5 0.63 0.8 0.935] [--reduced]
"""

from __future__ import annotations

import argparse
import sys

from piezod import calibrate_dynamic as cd
from piezod.config import default_sim_config_path, load_config
from piezod.effects_bench import StageBench, realistic_specs
from piezod.extensions import experiments_through
from piezod.simulator import load_stage
from piezod.stagecal import default_frame


def main(argv: list[str] | None = None) -> int:
    """Print the fit error per lag."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lags-ms", type=float, nargs="+", default=[0.0, 0.3, 0.5, 0.63, 0.8, 0.935])
    p.add_argument("--reduced", action="store_true", help="the reduced frame")
    args = p.parse_args(argv)
    path = default_sim_config_path()
    base = load_config(path)
    specs = realistic_specs("delay")
    frame = default_frame(base, "x", reduced=args.reduced)
    bench = StageBench(load_stage(path, specs, "x", 1), base.sample_rate_hz)
    exps = bench.play_frame(frame, "x", base.service.ramp_rate_v_per_s)
    which = "reduced" if args.reduced else "full"
    print(f"injected: {', '.join(specs)}; {which} frame, {len(exps)} experiments")
    for lag_ms in args.lags_ms:
        seen = experiments_through(exps, {"delay": {"delay_s": 0.0, "lag_time_constant_s": lag_ms * 1e-3}})
        dyn = cd.calibrate_dynamic(
            seen if lag_ms > 0 else exps,
            slew_rate_v_per_s=base.service.ramp_rate_v_per_s,
            rest_voltage_v=base.axes["x"].safe_voltage_v,
        )
        rms_nm = dyn.residual_rms_um * 1e3
        print(f"lag {lag_ms:6.3f} ms: fit error {dyn.fit_error_pct:.3f} %, RMS {rms_nm:.2f} nm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
