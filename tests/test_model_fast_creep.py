"""The fast-creep part (piezod.model.fast_creep): unit static gain, exact inverse, states across blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod.config import AxisConfig, ThesisModelConfig, load_config
from piezod.errors import ConfigError, ModelError
from piezod.model.fast_creep import MAX_FAST_CREEP, FastCreep, FastCreepAxisModel
from piezod.service.axes import axis_model

THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)
FAST = {"taus_s": [3e-4, 0.002, 0.012], "weights": [0.004, 0.012, 0.01]}
DT = 1.0 / 20_000.0


def _axis(model: str = "thesis") -> AxisConfig:
    cfg = AxisConfig(voltage_min_v=-30.0, voltage_max_v=150.0, thesis=THESIS, fast_creep=FAST)  # type: ignore[arg-type]
    if model == "thesis":
        return cfg
    sim = load_config("configs/sim-stage-calibrated.yaml").axes["x"]
    return sim.model_copy(update={"fast_creep": cfg.fast_creep})


@pytest.mark.parametrize("kind", ["thesis", "dynamic"])
def test_the_inverse_is_exact_across_blocks(kind: str) -> None:
    model = axis_model(_axis(kind))
    assert isinstance(model, FastCreepAxisModel)
    rng = np.random.default_rng(2)
    state = model.rest(40.0)
    targets = model.position(state) + np.cumsum(rng.normal(0.0, 0.02, 6000))
    volts, states = [], state
    for chunk in np.split(targets, [1, 700, 701, 4000]):
        v, states = model.inverse(chunk, DT, states)
        volts.append(v)
    x, after = model.forward(np.concatenate(volts), DT, state)
    assert np.max(np.abs(x - targets)) < 1e-9
    assert model.position(after) == pytest.approx(model.position(states), abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    w=st.lists(st.floats(-0.09, 0.09), min_size=1, max_size=5),
    dt=st.floats(1e-5, 1e-2),
)
def test_the_part_alone_inverts_any_weights(w: list[float], dt: float) -> None:
    """Any weights the part accepts, negative ones too (less creep than the wrapped model's)."""
    taus = tuple(np.geomspace(1e-4, 0.05, len(w)))
    fast = FastCreep(taus, tuple(w))
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.normal(0.0, 0.1, 500))
    c0 = np.full(len(w), 0.3)
    xm, c1 = fast.inverse(y, dt, c0)
    back, c2 = fast.forward(xm, dt, c0)
    assert np.allclose(back, y, atol=1e-9 * (1.0 + np.abs(y).max()))
    assert np.allclose(c1, c2, atol=1e-9 * (1.0 + np.abs(y).max()))


@pytest.mark.parametrize("weights", [(0.02, 0.01), (0.02, -0.03)])
def test_the_static_gain_is_one_and_a_sine_follows_the_response(weights: tuple[float, float]) -> None:
    """Also with a negative weight (the wrapped model creeps too much at 10 ms): a lead, not a lag."""
    fast = FastCreep((0.002, 0.01), weights)
    assert abs(fast.response(np.array([0.0]))[0]) == pytest.approx(1.0)
    f = 40.0
    t = np.arange(round(2.0 / DT)) * DT
    x = np.sin(2 * math.pi * f * t)
    y, _ = fast.forward(x, DT, np.zeros(2))
    tail = t >= 1.0
    gain = np.sqrt(2.0 * np.mean(y[tail] ** 2))
    assert gain == pytest.approx(abs(fast.response(np.array([f]))[0]), rel=2e-3)
    held, _ = fast.forward(np.ones(4000), DT, np.zeros(2))
    assert held[-1] == pytest.approx(1.0, abs=1e-6)


def test_a_hold_lets_the_late_motion_arrive() -> None:
    model = axis_model(_axis())
    state = model.rest(0.0)
    v, state = model.inverse(np.linspace(0.0, 5.0, 200), DT, state)
    assert model.position(state) == pytest.approx(5.0, abs=1e-9)
    assert isinstance(model, FastCreepAxisModel)
    held = model.hold(round(1.0 / DT), DT, state)
    # after a second every element has arrived: the position is the wrapped model's own
    arrived = model.inner.position(held.inner)
    assert model.position(held) > model.position(state)
    assert np.allclose(np.asarray(held.c), arrived, atol=1e-9)
    assert model.position(held) == pytest.approx(arrived, abs=1e-9)
    assert model.voltage(held) == pytest.approx(float(v[-1]))


@pytest.mark.parametrize(
    ("taus", "weights", "match"),
    [
        ((0.01, 0.001), (0.01, 0.01), "ascending"),
        ((0.001,), (float("nan"),), "finite"),
        ((0.001, 0.01), (0.3, -0.2), "absolute values"),
        ((0.001, 0.01), (0.01,), "one weight"),
        ((0.001,), (MAX_FAST_CREEP,), "below"),
    ],
)
def test_bad_parameters_are_refused(taus: tuple[float, ...], weights: tuple[float, ...], match: str) -> None:
    with pytest.raises(ModelError, match=match):
        FastCreep(taus, weights)


def test_a_bad_fast_creep_in_the_yaml_names_the_field(tmp_path: object) -> None:
    from pathlib import Path

    doc = yaml.safe_load(Path("configs/sim-stage-calibrated.yaml").read_text())
    doc["axes"]["x"]["fast_creep"] = {"taus_s": [0.01, 0.001], "weights": [0.01, 0.01]}
    path = Path(str(tmp_path)) / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="fast_creep"):
        load_config(path)
