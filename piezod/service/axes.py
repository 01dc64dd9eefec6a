"""Per-axis mapping of target positions to voltages through the axis model.

Every axis keeps the state of its hysteresis ODE (2.21) across blocks, so what
the stage did before (a previous scan, an offset or range change, a move) shapes
the voltages that follow: the transients of thesis chapter 5 are handled, not
ignored. For a periodic scan the creep term of (3.8) enters as the extra
sensitivity ``kappa = b_hat(f, V_h) - b`` around the scan centre ``V_C``; in steady
state the per-sample inverse then *is* the closed-form inverse (4.11) of (3.8)
(see :func:`piezod.model.ode.hysteresis_inverse_step`), and after a change the
ODE state carries the transient.

Positions are in stage coordinates: the model's absolute position, 0 um at
0 V for a relaxed stage; the thesis model runs a scan centred on ``c`` um around ``V_C = c / b``,
the time-domain models between the turning voltages of their own steady loop from the present
state (:meth:`~piezod.model.axis_model.AxisModel.loop_voltages`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.config import AxisConfig
from piezod.errors import ModelError, RangeUnreachableError, SafetyError
from piezod.model.axis_model import AxisModel, DynamicAxisModel, FamilyAxisModel, ThesisAxisModel
from piezod.model.fast_creep import with_fast_creep
from piezod.model.inverse import ThesisInverse
from piezod.model.params import ThesisParams
from piezod.model.parts import with_parts
from piezod.model.thesis import effective_sensitivity
from piezod.scan import slew_limit
from piezod.trajectory import Trajectory

#: Frequency (Hz) whose creep term moves and holds use before any scan sets one.
QUASI_STATIC_HZ = 0.1


@dataclass(frozen=True, slots=True)
class PeriodicPlan:
    """The steady loop of a periodic scan on one axis.

    Attributes
    ----------
    range_um
        Peak-to-peak travel (um).
    frequency_hz
        Loop frequency (Hz).
    center_um
        Centre of the travel in stage coordinates (um).
    v_min, v_max
        Turning voltages of the steady loop (4.12) (V).
    kappa_um_per_v
        Creep sensitivity ``b_hat - b`` (um/V).
    """

    range_um: float
    frequency_hz: float
    center_um: float
    v_min: float
    v_max: float
    kappa_um_per_v: float

    @property
    def v_center(self) -> float:
        """Scan centre ``V_C`` (V)."""
        return 0.5 * (self.v_min + self.v_max)


@lru_cache(maxsize=256)
def _plan(
    params: ThesisParams,
    range_um: float,
    frequency_hz: float,
    center_um: float,
    lo: float,
    hi: float,
    center_v: float | None = None,
) -> PeriodicPlan:
    if center_v is None:
        center_v = center_um / params.b_um_per_v
    if not lo < center_v < hi:
        raise SafetyError(
            f"centre {center_um:.6g} um needs {center_v:.6g} V, outside the voltage limits [{lo:g}, {hi:g}] V"
        )
    inv = ThesisInverse.for_scan(params, range_um, frequency_hz, v_limits=(lo, hi), center_v=center_v)
    return PeriodicPlan(
        range_um, frequency_hz, center_um, inv.v_min, inv.v_max, inv.b_hat - params.b_um_per_v
    )


def axis_model(config: AxisConfig) -> AxisModel:
    """The model an axis's configuration selects (``model: thesis | dynamic | family``).

    The thesis model starts with the creep term of a slow scan over the whole voltage range (moves
    and holds then use the stage's quasi-static sensitivity, not the bare ``b``) until a scan sets
    its own (:meth:`AxisModel.with_plan`). The axis's ``extensions:`` (runtime parts, the audit's
    findings) wrap the model (:mod:`piezod.model.parts`); a time part measured in an earlier
    session goes on from where its trend is now (:meth:`~piezod.model.parts.Parts.anchored` at
    the wall clock).
    """
    inner = with_fast_creep(_bare_model(config), config.fast_creep_part())
    return with_parts(inner, config.parts().anchored(time.time()))


def _bare_model(config: AxisConfig) -> AxisModel:
    if config.model == "dynamic" and config.dynamic is not None:
        return DynamicAxisModel(config.dynamic.params())
    if config.model == "family" and config.family is not None:
        return FamilyAxisModel(config.family.params())
    params = config.thesis.params()
    lo, hi = config.voltage_min_v, config.voltage_max_v
    kappa = effective_sensitivity(params, QUASI_STATIC_HZ, lo, hi) - params.b_um_per_v
    return ThesisAxisModel(params, kappa, 0.5 * (lo + hi))


@dataclass(frozen=True, slots=True)
class AxisOutput:
    """Voltages for one block of one axis.

    Attributes
    ----------
    voltage_v
        The voltages, inside the limits and the slew limit.
    clamped
        Samples that had to be clamped to the voltage limits (a fault when > 0).
    slew_limited
        Samples the slew limit changed.
    """

    voltage_v: NDArray[np.float64]
    clamped: int
    slew_limited: int


class AxisDriver:
    """Turns target positions of one axis into voltages, keeping the model's state.

    The model is any :class:`~piezod.model.axis_model.AxisModel` (chosen by the axis's
    ``model:``); the driver adds the voltage limits, the slew limit and the bookkeeping, and never
    asks which model it drives.

    Parameters
    ----------
    name
        Axis name (``x``, ``y``, ``z``).
    config
        The axis's configuration (limits, slew rate, model parameters).
    sample_rate_hz
        The board's sample clock.
    model
        The model to drive (default: the one ``config`` selects, :func:`axis_model`).
    """

    def __init__(
        self, name: str, config: AxisConfig, sample_rate_hz: float, model: AxisModel | None = None
    ) -> None:
        self.name = name
        self.config = config
        #: The thesis parameters: the scan planner's model (turning voltages, reach, slew).
        self.params = config.thesis.params()
        self.limits = (config.voltage_min_v, config.voltage_max_v)
        self.max_step_v = config.slew_rate_v_per_s / sample_rate_hz
        self._dt_s = 1.0 / sample_rate_hz
        self.model: AxisModel = axis_model(config) if model is None else model
        #: The resonance part (the audit's ``resonance``): shapes the targets ahead of the model.
        self.resonance = config.resonance()
        self._state: Any = self.model.rest(config.safe_voltage_v)
        # the last targets corrected, for the resonance part's window (None: the drive was not
        # corrected since: the next block starts as if its first target had held)
        self._before: NDArray[np.float64] | None = None
        self._prime()

    def _prime(self) -> None:
        """Run every model call the stream makes once, on scratch states, before the model streams.

        A model may prepare itself lazily on its first call with given argument types: the
        compiled per-sample loops of the family (numba) compile one machine-code version per
        argument signature (:func:`piezod.model.kernels.warm_up` compiles those the family's
        models pass; a model of another kind may have its own). Left to the first block, such a
        compilation (seconds on a loaded machine) runs in the streaming thread under the engine
        lock, and the board's FIFO underran at the hand-over from the hold to the first
        corrected scan. Here it runs where the driver is built (outside the engine lock).
        """
        dt = self._dt_s
        rest = self.model.rest(self.config.safe_voltage_v)
        x0 = self.model.position(rest)
        targets = x0 + np.linspace(0.0, 1e-3, 4)
        volts, after = self.model.inverse(targets, dt, rest)
        self.model.forward(volts, dt, rest)
        held = self.model.hold(4, dt, after)
        adopted = self.model.adopt(self.model.voltage(held), self.model.position(held))
        self.model.inverse(targets, dt, adopted)

    @property
    def state(self) -> Any:
        """The model's state after the last sample."""
        return self._state

    @property
    def voltage_v(self) -> float:
        """The last voltage."""
        return self.model.voltage(self._state)

    @property
    def position_um(self) -> float:
        """The model's position after the last sample."""
        return self.model.position(self._state)

    @property
    def lookahead(self) -> int:
        """Targets :meth:`corrected` wants ahead of each block (the resonance part's; 0: none)."""
        return self.resonance.lookahead(self._dt_s)

    def reset(self, voltage_v: float | None = None) -> None:
        """Forget the history: the stage rests at ``voltage_v`` (default: the safe value)."""
        v = self.config.safe_voltage_v if voltage_v is None else voltage_v
        self._state = self.model.rest(v)
        self._before = None

    def plan(self, range_um: float, frequency_hz: float, center_um: float) -> PeriodicPlan:
        """The steady loop of a periodic scan (cached).

        Raises
        ------
        RangeUnreachableError
            If the range needs voltages beyond the limits.
        SafetyError
            If the centre lies outside the limits.
        """
        r, f, c = float(range_um), float(frequency_hz), float(center_um)
        if self.model.plans_by_thesis:
            return _plan(self.params, r, f, c, *self.limits)
        if not (math.isfinite(r) and r > 0.0 and math.isfinite(f) and f > 0.0 and math.isfinite(c)):
            raise ModelError(f"scan range {r!r} um, frequency {f!r} Hz, centre {c!r} um: finite, > 0 needed")
        v_min, v_max = self.model.loop_voltages(c, r, f, self._state)
        lo, hi = self.limits
        if not (math.isfinite(v_min) and math.isfinite(v_max)):
            raise SafetyError(f"centre {c:.6g} um: the model gives no finite voltage there")
        if v_min < lo or v_max > hi:
            centre = 0.5 * (v_min + v_max)
            if not lo < centre < hi:
                raise SafetyError(
                    f"centre {c:.6g} um needs {centre:.6g} V, outside the voltage limits [{lo:g}, {hi:g}] V"
                )
            up, down = (hi - centre) / max(v_max - centre, 1e-12), (centre - lo) / max(centre - v_min, 1e-12)
            raise RangeUnreachableError(
                f"scan range {r:.6g} um at {f:.6g} Hz centred on {c:.6g} um needs {v_min:.6g} ... "
                f"{v_max:.6g} V with the axis's model (limits [{lo:g}, {hi:g}] V); the largest reachable "
                f"range there is about {r * min(up, down):.6g} um"
            )
        # the thesis model's creep term (kappa) is not used by the time-domain models
        return PeriodicPlan(r, f, c, v_min, v_max, 0.0)

    def peak_slew_v_per_s(self, plan: PeriodicPlan) -> float:
        """Largest |dV/dt| of the corrected steady loop of ``plan`` (inf if a branch is not monotone).

        The target moves at ``2 range f``; the voltage is fastest where the branch is flattest,
        at its start right after a turning point.
        """
        inv = ThesisInverse.for_voltages(
            self.params, plan.v_min, plan.v_max, plan.frequency_hz, allow_nonmonotone=True
        )
        slope = min(inv.trace.slope_start_um_per_v, inv.retrace.slope_start_um_per_v)
        if slope <= 0.0:
            return math.inf
        return 2.0 * plan.range_um * plan.frequency_hz / slope

    def use_plan(self, plan: PeriodicPlan | None) -> None:
        """Switch the model to ``plan``'s periodic scan (None: keep the current one)."""
        if plan is not None:
            self.model = self.model.with_plan(plan.kappa_um_per_v, plan.v_center)

    def corrected(
        self, targets_um: NDArray[np.float64], ahead_um: NDArray[np.float64] | None = None
    ) -> AxisOutput:
        """Voltages that bring the modelled stage to ``targets_um`` (um), sample by sample.

        Parameters
        ----------
        targets_um
            The block's targets.
        ahead_um
            The targets after the block, as far as known (:attr:`lookahead` of them are used;
            fewer or None: the last target is taken to hold). Only the resonance part needs them.
        """
        targets = np.asarray(targets_um, dtype=np.float64)
        prior = self._before
        shaped = targets
        if not self.resonance.off and targets.size:
            before = np.empty(0) if prior is None else prior
            ahead = np.empty(0) if ahead_um is None else np.asarray(ahead_um, dtype=np.float64)
            shaped = self.resonance.shape(targets, before, ahead, self._dt_s)
        volts, state = self.model.inverse(shaped, self._dt_s, self._state)
        # the inverse of a drive lag asks for a step at every turning point; cut to the slew
        # limit after the step alone, the ramp rounds each turning point late and the scan reads long
        out = self._finish(volts, state, centred=True)
        if not self.resonance.off and targets.size:
            self._before = self.resonance.window(np.empty(0) if prior is None else prior, targets, self._dt_s)
        return out

    def linear(self, targets_um: NDArray[np.float64], plan: PeriodicPlan) -> AxisOutput:
        """The uncorrected drive: voltage linear in the target over the plan's voltage range."""
        scale = (plan.v_max - plan.v_min) / plan.range_um
        volts = plan.v_center + (np.asarray(targets_um, dtype=np.float64) - plan.center_um) * scale
        return self._finish(volts)

    def direct(self, volts: NDArray[np.float64]) -> AxisOutput:
        """Voltages given directly (no model), clamped and slew-limited; the model state follows."""
        return self._finish(np.asarray(volts, dtype=np.float64))

    def adopt_state(self, other: AxisDriver) -> None:
        """Continue from another driver's last voltage and position (new model, same stage)."""
        self.adopt(other.voltage_v, other.position_um)

    def adopt(self, voltage_v: float, position_um: float) -> None:
        """Continue from a stage at ``voltage_v`` and ``position_um`` (e.g. as its sensor reads it)."""
        self._state = self.model.adopt(float(voltage_v), float(position_um))
        self._before = None

    def hold(self, n: int) -> AxisOutput:
        """Keep the last voltage for ``n`` samples (the model's creep runs on)."""
        self._state = self.model.hold(n, self._dt_s, self._state)
        self._before = None
        return AxisOutput(np.full(n, self.voltage_v), 0, 0)

    def ramp_to(self, voltage_v: float, rate_v_per_s: float, sample_rate_hz: float) -> NDArray[np.float64]:
        """A linear voltage ramp from the last voltage to ``voltage_v`` (model state advanced)."""
        start = self.voltage_v
        n = max(1, math.ceil(abs(voltage_v - start) / rate_v_per_s * sample_rate_hz))
        volts = start + (voltage_v - start) * np.arange(1, n + 1) / n
        return self._finish(volts).voltage_v

    def _finish(
        self, volts: NDArray[np.float64], state_after: Any = None, *, centred: bool = False
    ) -> AxisOutput:
        self._before = None
        lo, hi = self.limits
        last = self.voltage_v
        bad = (volts < lo) | (volts > hi) | ~np.isfinite(volts)
        clamped = int(np.count_nonzero(bad))
        if clamped:
            volts = np.clip(np.nan_to_num(volts, nan=last), lo, hi)
        volts, slewed = slew_limit(volts, last, self.max_step_v, centred=centred)
        if state_after is None or clamped or slewed:
            _, state_after = self.model.forward(volts, self._dt_s, self._state)
        self._state = state_after
        return AxisOutput(volts, clamped, slewed)


def plan_axes(drivers: Mapping[str, AxisDriver], trajectory: Trajectory) -> dict[str, PeriodicPlan | None]:
    """The steady loop of each axis the trajectory moves; refuses what the stage cannot do.

    Raises
    ------
    RangeUnreachableError, SafetyError
        With the reason (range beyond the limits, slew rate exceeded, missing axis).
    """
    plans: dict[str, PeriodicPlan | None] = {}
    for name, motion in trajectory.motion().items():
        if name not in drivers:
            if motion is not None:
                raise SafetyError(f"the scan needs axis {name!r}, which the scanner config does not have")
            continue
        if motion is None:
            plans[name] = None
            continue
        travel, f = motion.travel_um, motion.frequency_hz
        d = drivers[name]
        plan = d.plan(travel, f, motion.center_um)
        need = d.peak_slew_v_per_s(plan)
        if need > d.config.slew_rate_v_per_s:
            raise SafetyError(
                f"axis {name}: {travel:.4g} um at {f:.4g} Hz needs up to {need:.4g} V/s, above the "
                f"slew limit {d.config.slew_rate_v_per_s:g} V/s; scan slower or smaller"
            )
        plans[name] = plan
    return plans
