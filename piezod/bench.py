"""Benchmarks of the model core: ``piezod bench inverse``.

The full inverse (:class:`~piezod.model.inverse.ThesisInverse`) is timed on
blocks of a triangular scan (both branches; the half line is not a multiple of
the block, so some blocks hold a turning point), against the same inverse with
W taken from :func:`scipy.special.lambertw` (the literal (4.11)), measured in the
same run, alternating block by block; every block counts with its best time over
the repeats (robust against other load on a shared machine). The round-trip error is
``max |x(V(x)) - x|`` over the run relative to the scan range.
"""

from __future__ import annotations

import math
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import lambertw as scipy_lambertw

from piezod.errors import ModelError
from piezod.model.inverse import BranchConstants, ThesisInverse
from piezod.model.ode import hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.model.params import ThesisParams
from piezod.model.thesis import MEDIUM_TUBE_TABLE_3_3, TRACE
from piezod.progress import progress

FloatArray = NDArray[np.float64]

#: Per-sample inverse of the richest runtime model (issue 9), ns per sample and axis.
TARGET_MODEL_NS_PER_SAMPLE = 150.0
#: The richest runtime model of :func:`bench_models` (the one the 150 ns target is about).
RICHEST_MODEL = "family/generalised-play/64-plays/5-nodes/after-effect/voltage-creep+parts"
#: The targets of docs/formats.md, section 5.
TARGET_NS_PER_SAMPLE = 50.0
TARGET_RATIO = 0.3
TARGET_ROUNDTRIP_REL = 1e-9


def _scipy_branch(br: BranchConstants, x: FloatArray) -> FloatArray:
    """(4.11) literally, with scipy's W."""
    c1, c2, c3, c4 = br.c1, br.c2, br.c3, br.c4
    u = (x - c4) / c1
    z = (c2 * c3 / c1) * np.exp(c3 * u)
    out: FloatArray = u - scipy_lambertw(z).real / c3
    return out


def scipy_voltage(inv: ThesisInverse, x: FloatArray, direction: NDArray[np.int8]) -> FloatArray:
    """Baseline inverse: the same constants, checks and clipping as ``inv.voltage``, W from scipy."""
    lo, hi = float(x.min()), float(x.max())
    if not (lo >= inv.x_min - 1e-9 * inv.range_um and hi <= inv.x_max + 1e-9 * inv.range_um):
        raise ModelError("target outside the scan")
    trace = direction == TRACE
    out = np.empty_like(x)
    out[trace] = _scipy_branch(inv.trace, x[trace])
    out[~trace] = _scipy_branch(inv.retrace, x[~trace])
    np.clip(out, inv.v_min, inv.v_max, out=out)
    return out


def triangular_targets(
    inv: ThesisInverse, n_samples: int, half_line: int
) -> tuple[FloatArray, NDArray[np.int8]]:
    """Absolute targets and directions of a linear triangular scan over the full range."""
    k = np.arange(n_samples)
    phase = k % (2 * half_line)
    up = phase < half_line
    frac = np.where(up, phase / half_line, 2.0 - phase / half_line)
    x = inv.to_absolute(frac * inv.range_um)
    return x, np.where(up, 1, -1).astype(np.int8)


def _time_interleaved(
    fns: list[Callable[[FloatArray, NDArray[np.int8]], FloatArray]],
    blocks: list[tuple[FloatArray, NDArray[np.int8]]],
    repeats: int,
) -> tuple[list[float], list[list[FloatArray]]]:
    """Best time of every block over the repeats, summed, per function; the implementations
    alternate block by block so that both see the same machine load."""
    best = np.full((len(fns), len(blocks)), math.inf)
    outputs: list[list[FloatArray]] = [[] for _ in fns]
    clock = time.perf_counter
    for rep in progress(range(repeats), desc="bench inverse"):
        for j, (xb, db) in enumerate(blocks):
            for i, fn in enumerate(fns):
                t0 = clock()
                out = fn(xb, db)
                best[i, j] = min(best[i, j], clock() - t0)
                if rep == 0:
                    outputs[i].append(out)
    return [float(t) for t in best.sum(axis=1)], outputs


def bench_models() -> dict[str, Any]:
    """The axis models timed by :func:`axis_model_costs` (the family members at realistic sizes).

    The family members carry a drive lag, 16 play operators (or Coleman-Hodgdon, or the generalised
    play law with 32 plays over 3 relay-centre nodes, or the Bouc-Wen/Duhem law of exponent 1 or 2),
    a creep spectrum
    of 19 relaxation times from 0.1 ms to 1e5 s and the stiffness map; :data:`RICHEST_MODEL` (the
    generalised play law) adds voltage-driven creep, the fast creep of a 2 Hz frame
    (:mod:`piezod.model.fast_creep`, 10 relaxation times) and every other runtime part
    (:mod:`piezod.model.parts`: polarity, thermal,
    stiffness, saturation, drift) at the finest play and centre grids the calibration's choice
    writes (64 plays over 5 relay-centre nodes) with the after-effect of its memory
    (:mod:`piezod.model.aftereffect`; the same without it, the Prandtl-Ishlinskii law with voltage
    creep and every part at 64 plays, and the generalised play law over 3 nodes, beside it).
    """
    from piezod.model.aftereffect import AfterEffect
    from piezod.model.axis_model import DynamicAxisModel, FamilyAxisModel, ThesisAxisModel
    from piezod.model.boucwen import BoucWenParams
    from piezod.model.domainwall import DomainWallParams
    from piezod.model.dynamic import DynamicParams
    from piezod.model.family import CreepSpectrum, FamilyParams
    from piezod.model.fast_creep import FastCreep, FastCreepAxisModel
    from piezod.model.gplay import GeneralisedPlayParams
    from piezod.model.params import HysteresisParams
    from piezod.model.parts import Parts, PartsAxisModel
    from piezod.model.play import PlayParams
    from piezod.rate_id import fast_taus

    creep = CreepSpectrum.log_spaced(1e-4, 1e5, 2, 0.015 / 2)
    shape = np.exp(-np.arange(16) / 6.0)
    pi = PlayParams.uniform(0.115, 0.45, 320.0, 16, 0.55 * shape / shape.sum())
    ch = HysteresisParams(3e-3, 0.115, 0.072)

    def generalised_play(n: int, decay: float, nodes: int = 3) -> GeneralisedPlayParams:
        """``n`` plays with weights decaying over ``decay`` plays, density over ``nodes`` relay-centre
        nodes (rising by a quarter from the lowest to the highest)."""
        shape = np.exp(-np.arange(n) / decay)
        w = 0.115 * 0.55 * shape / shape.sum()
        bend = np.linspace(0.9, 1.15, nodes)
        return GeneralisedPlayParams(
            tuple(float(x) for x in 160.0 * np.arange(1, n + 1) / (n + 1)),
            tuple(float(c) for c in np.linspace(-230.0, 230.0, nodes)),
            tuple(tuple(float(v * b) for b in bend) for v in [0.052, *map(float, w)]),
        )

    # generalised play law at a fitted size: 32 plays
    gp = generalised_play(32, 12.0)
    # the finest play grid the calibration's choice writes (calibrate_family.MAX_PLAYS)
    fine = 64
    fshape = np.exp(-np.arange(fine) / (fine / 2.7))
    pi_fine = PlayParams.uniform(0.115, 0.45, 320.0, fine, 0.55 * fshape / fshape.sum())
    gp_fine = generalised_play(fine, fine / 2.7)
    # and the finest centre grid (calibrate_family.MAX_GP_NODES)
    gp_finest = generalised_play(fine, fine / 2.7, 5)
    # the Duhem law with direction- and sign-dependent rates at a fitted size (asymmetric)
    bw = BoucWenParams(0.098, -0.037, 0.0159, 0.0097, 0.0155, 0.0081, 1.2)
    # exponent 2 (a sharp knee): the law is its per-sample Runge-Kutta step, inverted by Newton
    bw2 = BoucWenParams(0.2, -0.07, 0.0234, 0.015, 0.0234, 0.015, 1.0, 2.0)
    # the fast creep's largest spectrum (piezod.rate_id): its times up to a fourteenth of a 2 Hz line
    taus = fast_taus(1e-5, 2.0)
    fast = FastCreep(taus, tuple(0.003 for _ in taus))
    # the memory's after-effect (piezod.model.aftereffect) as foreign51's frame placed it
    after_effect = AfterEffect(2.16, 5.0e3)
    # the domain-wall law as foreign51's frame placed it, its interaction raised to the stage's
    dw = DomainWallParams(0.42, 0.22, 36.7, 36.8, 96.8, 0.3)
    dw_after_effect = AfterEffect(1.38, 5.4e4)
    return {
        "thesis": ThesisAxisModel(MEDIUM_TUBE_TABLE_3_3, 0.01, 0.0),
        "dynamic": DynamicAxisModel(DynamicParams(3e-3, 0.115, 0.072, 1.5)),
        "family/coleman-hodgdon": FamilyAxisModel(FamilyParams(ch, creep, 2e-4, 0.05)),
        "family/prandtl-ishlinskii": FamilyAxisModel(FamilyParams(pi, creep, 2e-4, 0.05)),
        "family/coleman-hodgdon/voltage-creep": FamilyAxisModel(
            FamilyParams(ch, creep, 2e-4, 0.05, "voltage")
        ),
        "family/prandtl-ishlinskii/voltage-creep": FamilyAxisModel(
            FamilyParams(pi, creep, 2e-4, 0.05, "voltage")
        ),
        "family/generalised-play": FamilyAxisModel(FamilyParams(gp, creep, 2e-4, 0.05)),
        "family/generalised-play/voltage-creep": FamilyAxisModel(
            FamilyParams(gp, creep, 2e-4, 0.05, "voltage")
        ),
        "family/bouc-wen": FamilyAxisModel(FamilyParams(bw, creep, 2e-4, 0.05)),
        "family/bouc-wen/voltage-creep": FamilyAxisModel(FamilyParams(bw, creep, 2e-4, 0.05, "voltage")),
        "family/bouc-wen-n2": FamilyAxisModel(FamilyParams(bw2, creep, 2e-4, 0.05)),
        "family/bouc-wen-n2/voltage-creep": FamilyAxisModel(FamilyParams(bw2, creep, 2e-4, 0.05, "voltage")),
        "family/domain-wall": FamilyAxisModel(FamilyParams(dw, creep, 2e-4, 0.05)),
        "family/domain-wall/voltage-creep": FamilyAxisModel(FamilyParams(dw, creep, 2e-4, 0.05, "voltage")),
        "family/domain-wall/after-effect/voltage-creep+parts": PartsAxisModel(
            FastCreepAxisModel(
                FamilyAxisModel(FamilyParams(dw, creep, 2e-4, 0.05, "voltage", 0.0, dw_after_effect)), fast
            ),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/bouc-wen/voltage-creep+parts": PartsAxisModel(
            FamilyAxisModel(FamilyParams(bw, creep, 2e-4, 0.05, "voltage")),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/prandtl-ishlinskii/voltage-creep+parts": PartsAxisModel(
            FamilyAxisModel(FamilyParams(pi, creep, 2e-4, 0.05, "voltage")),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/generalised-play/voltage-creep+parts": PartsAxisModel(
            FamilyAxisModel(FamilyParams(gp, creep, 2e-4, 0.05, "voltage")),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/prandtl-ishlinskii/64-plays/voltage-creep+parts": PartsAxisModel(
            FamilyAxisModel(FamilyParams(pi_fine, creep, 2e-4, 0.05, "voltage")),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/generalised-play/64-plays/voltage-creep+parts": PartsAxisModel(
            FastCreepAxisModel(FamilyAxisModel(FamilyParams(gp_fine, creep, 2e-4, 0.05, "voltage")), fast),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        "family/generalised-play/64-plays/5-nodes/voltage-creep+parts": PartsAxisModel(
            FastCreepAxisModel(FamilyAxisModel(FamilyParams(gp_finest, creep, 2e-4, 0.05, "voltage")), fast),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
        RICHEST_MODEL: PartsAxisModel(
            FastCreepAxisModel(
                FamilyAxisModel(FamilyParams(gp_finest, creep, 2e-4, 0.05, "voltage", 0.0, after_effect)),
                fast,
            ),
            Parts(-5.0, 1.0, 0.05, 120.0, 0.5),
        ),
    }


def axis_model_costs(
    targets_um: FloatArray, block_samples: int, repeats: int, range_um: float, dt_s: float
) -> dict[str, dict[str, float]]:
    """ns per sample of every :func:`bench_models` inverse through the axis-model interface.

    The targets are streamed block by block with the state carried (as the engine does); every
    block counts with its best time over the repeats; the round trip runs the forward model
    over the voltages and compares with the targets (relative to the scan range).
    """
    out: dict[str, dict[str, float]] = {}
    n = targets_um.size
    for name, model in bench_models().items():
        state0 = model.rest(0.0)
        x = targets_um - float(targets_um[0]) + model.position(state0)
        states, volts, st = [], [], state0
        for i in range(0, n, block_samples):
            states.append(st)
            vb, st = model.inverse(x[i : i + block_samples], dt_s, st)
            volts.append(vb)
        best = np.full(len(states), math.inf)
        for _ in range(max(1, repeats // 2)):
            for j, st in enumerate(states):
                i = j * block_samples
                t0 = time.perf_counter()
                model.inverse(x[i : i + block_samples], dt_s, st)
                best[j] = min(best[j], time.perf_counter() - t0)
        x_back, _ = model.forward(np.concatenate(volts), dt_s, state0)
        out[name] = {
            "ns_per_sample": float(best.sum()) / n * 1e9,
            "max_roundtrip_error_rel": float(np.max(np.abs(x_back - x)) / range_um),
        }
    return out


#: The resonance part timed by :func:`resonance_cost`: the nPoint AFM stage's mode (issue #9) at
#: 100 kS/s, ``K`` = 38 samples (the smoothing kernel spans 76 each side).
BENCH_RESONANCE = (665.0, 8.0)


def resonance_cost(targets_um: FloatArray, block_samples: int, repeats: int, dt_s: float) -> float:
    """ns per sample of the resonance part's shaping (:mod:`piezod.model.resonance`), which the axis
    driver runs before any model's inverse, block by block with the targets before and ahead."""
    from piezod.model.resonance import ResonancePart

    part = ResonancePart(*BENCH_RESONANCE)
    m = part.lookahead(dt_s)
    n = targets_um.size
    best = math.inf
    for _ in range(max(1, repeats // 2)):
        t0 = time.perf_counter()
        for i in range(0, n, block_samples):
            part.shape(
                targets_um[i : i + block_samples],
                targets_um[max(0, i - m) : i],
                targets_um[i + block_samples : i + block_samples + m],
                dt_s,
            )
        best = min(best, time.perf_counter() - t0)
    return best / n * 1e9


def run_inverse_bench(
    *,
    block_samples: int = 4096,
    blocks: int = 128,
    repeats: int = 5,
    params: ThesisParams = MEDIUM_TUBE_TABLE_3_3,
    range_um: float = 30.0,
    frequency_hz: float = 1.0,
    half_line_samples: int = 5000,
    v_limits: tuple[float, float] = (-230.0, 230.0),
) -> dict[str, Any]:
    """Time the full inverse against a scipy-based inverse and measure its round trip.

    Parameters
    ----------
    block_samples
        Samples per call (one axis).
    blocks
        Blocks per repeat.
    repeats
        Interleaved repeats; the best time of each implementation counts.
    params, range_um, frequency_hz, v_limits
        The scan (default: medium tube, table 3.3, 30 um at 1 Hz).
    half_line_samples
        Samples per trace (and per retrace).

    Returns
    -------
    dict
        ``ns_per_sample``, ``scipy_ns_per_sample``, ``ratio``, ``max_roundtrip_error_rel``,
        ``max_voltage_difference_v`` (vs scipy), ``ode_ns_per_sample`` and
        ``ode_max_roundtrip_error_rel`` (per-sample ODE inverse on the same targets),
        ``models`` (:func:`axis_model_costs`: every axis model's per-sample inverse at 100 kS/s),
        the settings, the targets and ``meets_targets``.
    """
    if block_samples < 1 or blocks < 1 or repeats < 1 or half_line_samples < 2:
        raise ModelError("block_samples, blocks, repeats must be >= 1 and half_line_samples >= 2")
    inv = ThesisInverse.for_scan(params, range_um, frequency_hz, v_limits=v_limits)
    n = block_samples * blocks
    x, d = triangular_targets(inv, n, half_line_samples)
    chunks = [(x[i : i + block_samples], d[i : i + block_samples]) for i in range(0, n, block_samples)]
    (best_ours, best_scipy), (v_ours, v_scipy) = _time_interleaved(
        [inv.voltage, lambda xb, db: scipy_voltage(inv, xb, db)], chunks, repeats
    )
    v = np.concatenate(v_ours)
    x_back = inv.position(v, d)
    roundtrip = float(np.max(np.abs(x_back - x)) / inv.range_um)
    dv = float(np.max(np.abs(v - np.concatenate(v_scipy))))

    hyst = params.hysteresis
    state0 = relaxed_state(hyst, inv.v_min)
    ode_x = x - inv.x_min + state0.position_um
    starts, v_ode, state = [], [], state0
    for i in range(0, n, block_samples):
        starts.append(state)
        vb, state = hysteresis_inverse_step(hyst, ode_x[i : i + block_samples], state)
        v_ode.append(vb)
    ode_blocks = list(zip(range(0, n, block_samples), starts, strict=True))
    best_ode = np.full(len(ode_blocks), math.inf)
    for _ in range(max(1, repeats // 2)):
        for j, (i, st) in enumerate(ode_blocks):
            t0 = time.perf_counter()
            hysteresis_inverse_step(hyst, ode_x[i : i + block_samples], st)
            best_ode[j] = min(best_ode[j], time.perf_counter() - t0)
    x_ode, _ = hysteresis_step(hyst, np.concatenate(v_ode), state0)
    ode_roundtrip = float(np.max(np.abs(x_ode - ode_x)) / inv.range_um)

    ns = best_ours / n * 1e9
    ns_scipy = best_scipy / n * 1e9
    ratio = ns / ns_scipy
    models = axis_model_costs(ode_x, block_samples, repeats, range_um, dt_s=1e-5)
    richest = models[RICHEST_MODEL]
    shaping = resonance_cost(ode_x, block_samples, repeats, dt_s=1e-5)
    richest_ns = richest["ns_per_sample"] + shaping
    return {
        "models": models,
        "target_model_ns_per_sample": TARGET_MODEL_NS_PER_SAMPLE,
        "richest_model": RICHEST_MODEL,
        "richest_model_ns_per_sample": richest["ns_per_sample"],
        "resonance_ns_per_sample": shaping,
        "richest_ns_per_sample": richest_ns,
        "richest_ratio": richest_ns / ns_scipy,
        "richest_meets_target": bool(
            richest_ns <= TARGET_MODEL_NS_PER_SAMPLE
            and richest["max_roundtrip_error_rel"] <= TARGET_ROUNDTRIP_REL
        ),
        "ns_per_sample": ns,
        "scipy_ns_per_sample": ns_scipy,
        "ratio": ratio,
        "max_roundtrip_error_rel": roundtrip,
        "max_voltage_difference_v": dv,
        "ode_ns_per_sample": float(best_ode.sum()) / n * 1e9,
        "ode_max_roundtrip_error_rel": ode_roundtrip,
        "block_samples": block_samples,
        "blocks": blocks,
        "repeats": repeats,
        "samples": n,
        "half_line_samples": half_line_samples,
        "range_um": range_um,
        "frequency_hz": frequency_hz,
        "v_min": inv.v_min,
        "v_max": inv.v_max,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "targets": {
            "ns_per_sample": TARGET_NS_PER_SAMPLE,
            "ratio": TARGET_RATIO,
            "max_roundtrip_error_rel": TARGET_ROUNDTRIP_REL,
        },
        "meets_targets": bool(
            ns <= TARGET_NS_PER_SAMPLE and ratio <= TARGET_RATIO and roundtrip <= TARGET_ROUNDTRIP_REL
        ),
    }
