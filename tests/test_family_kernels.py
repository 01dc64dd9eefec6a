"""The compiled per-sample loops of the family (piezod.model.kernels) against their Python reference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod.model import kernels
from piezod.model.axis_model import FamilyAxisModel
from piezod.model.dynamic import discretise
from piezod.model.family import CreepSpectrum, FamilyParams, family_forward, family_rest_state
from piezod.model.params import HysteresisParams
from piezod.model.play import PlayParams

W = np.exp(-np.arange(16) / 6.0)
PI = PlayParams.uniform(0.11, 0.45, 320.0, 16, 0.55 * W / W.sum())
CH = HysteresisParams(3e-3, 0.115, 0.072)
SPEC = CreepSpectrum.log_spaced(1e-4, 1e5, 2, 0.015 / 2)


def _args(p: FamilyParams, dt: float) -> tuple[float, np.ndarray, float, np.ndarray, np.ndarray]:
    disc = discretise(p.creep, dt)
    w, s, ob0 = p.creep.weights, p.law_slope_um_per_v, disc.one_minus_b0
    return s * float(w @ (1.0 - ob0)), s * (w * disc.a), s * float(w @ ob0), disc.a, ob0


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.05, 30.0), ch=st.booleans())
def test_the_compiled_loops_equal_the_python_reference(seed: int, scale: float, ch: bool) -> None:
    """Same targets (a random walk's forward positions) through both: identical voltages and states."""
    rng = np.random.default_rng(seed)
    p = FamilyParams(CH if ch else PI, SPEC, 0.0, 0.0, "voltage")
    dt = 1e-5
    s0 = family_rest_state(p, 10.0)
    v = 10.0 + np.cumsum(rng.normal(0, scale, 500) * (rng.random(500) < 0.9))
    x, _ = family_forward(p, v, dt, s0)
    g, wa, wb, a, ob0 = _args(p, dt)
    results = []
    for compiled in (True, False):
        e = s0.creep_um.copy()
        out = np.empty(x.size)
        if ch:
            fn = kernels.ch_loop if compiled else kernels._ch_loop
            end = fn(
                x,
                CH.b_um_per_v,
                CH.alpha_per_v,
                CH.delta_um,
                g,
                wa,
                wb,
                a,
                ob0,
                e,
                10.0,
                s0.law.position_um,
                out,
            )
            plays = np.zeros(0)
        else:
            fn = kernels.pi_loop if compiled else kernels._pi_loop
            plays = s0.law.plays_v.copy()  # type: ignore[union-attr]
            end = fn(
                x,
                PI.b_um_per_v,
                PI.rho0,
                PI.r,
                PI.w,
                g,
                wa,
                wb,
                a,
                ob0,
                e,
                plays,
                10.0,
                s0.law.position_um,
                out,
            )
        results.append((out, e, plays, end))
    (o1, e1, p1, end1), (o2, e2, p2, end2) = results
    np.testing.assert_allclose(o1, o2, rtol=0, atol=1e-10)
    np.testing.assert_allclose(o1, v, rtol=0, atol=1e-9 * max(1.0, float(np.ptp(v))))
    np.testing.assert_allclose(e1, e2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(p1, p2, rtol=0, atol=1e-10)
    assert end1 == pytest.approx(end2, abs=1e-10)


def test_a_voltage_creep_model_compiles_its_loop_when_it_is_loaded() -> None:
    FamilyAxisModel(FamilyParams(PI, SPEC, 2e-4, 0.05, "voltage"))
    assert kernels._warm


_NO_COMPILE_AFTER_WARM_UP = """
import numpy as np
from piezod.bench import bench_models
from piezod.model import kernels

kernels.warm_up()
loops = [n for n in kernels.__all__ if hasattr(getattr(kernels, n), "signatures")]
known = {n: set(getattr(kernels, n).signatures) for n in loops}
for name, m in bench_models().items():
    st = m.rest(0.0)
    v, after = m.inverse(np.linspace(0.0, 1.0, 50), 2e-5, st)
    m.forward(v, 2e-5, st)
    m.hold(10, 2e-5, after)
    for n in loops:
        new = set(getattr(kernels, n).signatures) - known[n]
        assert not new, f"{name}: {n} compiled {sorted(map(str, new))} after warm_up"
print("ok", len(loops))
"""


def test_warm_up_compiles_every_signature_the_models_stream_with() -> None:
    """A compilation after ``warm_up`` would fall into the first streamed block (4 s on a cold cache).

    In a fresh process (this one's loops may have been compiled by other tests): every model of
    ``piezod bench`` (each family member, the richest with voltage creep and every part) runs its
    inverse, forward and hold after ``warm_up`` without a new signature.
    """
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", _NO_COMPILE_AFTER_WARM_UP], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("ok"), done.stdout
