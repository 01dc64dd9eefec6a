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
0 V for a relaxed stage; a scan centred on ``c`` um runs around ``V_C = c / b``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from piezod.config import AxisConfig
from piezod.errors import SafetyError
from piezod.model.dynamic import (
    DynamicParams,
    DynamicState,
    dynamic_forward,
    dynamic_hold,
    dynamic_inverse,
    dynamic_rest_state,
)
from piezod.model.inverse import ThesisInverse
from piezod.model.ode import HysteresisState, hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.model.params import ThesisParams
from piezod.model.thesis import effective_sensitivity
from piezod.scan import slew_limit

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
    params: ThesisParams, range_um: float, frequency_hz: float, center_um: float, lo: float, hi: float
) -> PeriodicPlan:
    center_v = center_um / params.b_um_per_v
    if not lo < center_v < hi:
        raise SafetyError(
            f"centre {center_um:.6g} um needs {center_v:.6g} V, outside the voltage limits [{lo:g}, {hi:g}] V"
        )
    inv = ThesisInverse.for_scan(params, range_um, frequency_hz, v_limits=(lo, hi), center_v=center_v)
    return PeriodicPlan(
        range_um, frequency_hz, center_um, inv.v_min, inv.v_max, inv.b_hat - params.b_um_per_v
    )


def _adopted_dynamic_state(params: DynamicParams, other: AxisDriver) -> DynamicState:
    """``model: dynamic`` taking over from ``other``: its voltage, its hysteretic distance from the
    centre line rescaled to the new loop width, its creep deviations if it had the same elements."""
    v = other.voltage_v
    old = other.dynamic.hysteresis if other.dynamic is not None else other.params.hysteresis
    eta = (other.state.position_um - old.b_um_per_v * v) * params.hysteresis.delta_um / old.delta_um
    xh = params.b_um_per_v * v + eta
    dyn = other.dynamic_state
    e = np.zeros(params.taus_s.size)
    if dyn is not None and other.dynamic is not None and np.array_equal(other.dynamic.taus_s, params.taus_s):
        e = np.array(dyn.creep_um)
    return DynamicState(
        HysteresisState(v, xh), (1.0 + params.total_creep) * xh + float(params.weights @ e), e
    )


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

    Parameters
    ----------
    name
        Axis name (``x``, ``y``, ``z``).
    config
        The axis's configuration (limits, slew rate, model parameters).
    sample_rate_hz
        The board's sample clock.
    """

    def __init__(self, name: str, config: AxisConfig, sample_rate_hz: float) -> None:
        self.name = name
        self.config = config
        self.params = config.thesis.params()
        self.limits = (config.voltage_min_v, config.voltage_max_v)
        self.max_step_v = config.slew_rate_v_per_s / sample_rate_hz
        self._state = relaxed_state(self.params.hysteresis, config.safe_voltage_v)
        # Until a scan sets its own, the creep term of a slow scan over the whole voltage range
        # (moves and holds then use the stage's quasi-static sensitivity, not the bare b).
        lo, hi = self.limits
        self._kappa = effective_sensitivity(self.params, QUASI_STATIC_HZ, lo, hi) - self.params.b_um_per_v
        self._v_center = 0.5 * (lo + hi)
        # model: dynamic -- the time-domain model (piezod.model.dynamic) drives corrected(); its
        # state is kept next to (and in step with) the hysteresis state.
        self._dt_s = 1.0 / sample_rate_hz
        self.dynamic: DynamicParams | None = None
        self._dyn: DynamicState | None = None
        if config.model == "dynamic" and config.dynamic is not None:
            self.dynamic = config.dynamic.params()
            self._dyn = dynamic_rest_state(self.dynamic, config.safe_voltage_v)
            self._state = self._dyn.hysteresis

    @property
    def state(self) -> HysteresisState:
        """The hysteresis ODE state after the last sample."""
        return self._state

    @property
    def dynamic_state(self) -> DynamicState | None:
        """The dynamic model's state (``model: dynamic``), else None."""
        return None if self.dynamic is None else self._dynamic_state()

    @property
    def voltage_v(self) -> float:
        """The last voltage."""
        return self._state.voltage_v

    @property
    def position_um(self) -> float:
        """The model's position after the last sample (hysteresis + current creep term)."""
        if self.dynamic is not None:
            return self._dynamic_state().position_um
        return self._state.position_um + self._kappa * (self._state.voltage_v - self._v_center)

    def reset(self, voltage_v: float | None = None) -> None:
        """Forget the history: the stage rests at ``voltage_v`` (default: the safe value)."""
        v = self.config.safe_voltage_v if voltage_v is None else voltage_v
        self._state = relaxed_state(self.params.hysteresis, v)
        if self.dynamic is not None:
            self._dyn = dynamic_rest_state(self.dynamic, v)
            self._state = self._dyn.hysteresis

    def plan(self, range_um: float, frequency_hz: float, center_um: float) -> PeriodicPlan:
        """The steady loop of a periodic scan (cached).

        Raises
        ------
        RangeUnreachableError
            If the range needs voltages beyond the limits.
        SafetyError
            If the centre lies outside the limits.
        """
        return _plan(self.params, float(range_um), float(frequency_hz), float(center_um), *self.limits)

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
        """Switch the creep term to that of ``plan`` (None: keep the current one)."""
        if plan is not None:
            self._kappa, self._v_center = plan.kappa_um_per_v, plan.v_center

    def corrected(self, targets_um: NDArray[np.float64]) -> AxisOutput:
        """Voltages that bring the modelled stage to ``targets_um`` (um), sample by sample."""
        if self.dynamic is not None:
            volts, dyn = dynamic_inverse(self.dynamic, targets_um, self._dt_s, self._dynamic_state())
            return self._finish(volts, dyn)
        shifted = np.asarray(targets_um, dtype=np.float64) + self._kappa * self._v_center
        volts, state = hysteresis_inverse_step(
            self.params.hysteresis, shifted, self._state, kappa_um_per_v=self._kappa
        )
        return self._finish(volts, state)

    def linear(self, targets_um: NDArray[np.float64], plan: PeriodicPlan) -> AxisOutput:
        """The uncorrected drive: voltage linear in the target over the plan's voltage range."""
        scale = (plan.v_max - plan.v_min) / plan.range_um
        volts = plan.v_center + (np.asarray(targets_um, dtype=np.float64) - plan.center_um) * scale
        return self._finish(volts)

    def direct(self, volts: NDArray[np.float64]) -> AxisOutput:
        """Voltages given directly (no model), clamped and slew-limited; the model state follows."""
        return self._finish(np.asarray(volts, dtype=np.float64))

    def adopt_state(self, other: AxisDriver) -> None:
        """Continue from another driver's last voltage and position (new parameters, same stage)."""
        if self.dynamic is not None:
            self._dyn = _adopted_dynamic_state(self.dynamic, other)
            self._state = self._dyn.hysteresis
            return
        v = other.voltage_v
        eta = other.state.position_um - other.params.b_um_per_v * v
        # keep the distance from the branch centre line b V, rescaled to the new loop width
        scale = self.params.hysteresis.delta_um / other.params.hysteresis.delta_um
        self._state = HysteresisState(v, self.params.b_um_per_v * v + eta * scale)

    def hold(self, n: int) -> AxisOutput:
        """Keep the last voltage for ``n`` samples."""
        if self.dynamic is not None:
            self._dyn = dynamic_hold(self.dynamic, n, self._dt_s, self._dynamic_state())
            self._state = self._dyn.hysteresis
        return AxisOutput(np.full(n, self._state.voltage_v), 0, 0)

    def ramp_to(self, voltage_v: float, rate_v_per_s: float, sample_rate_hz: float) -> NDArray[np.float64]:
        """A linear voltage ramp from the last voltage to ``voltage_v`` (model state advanced)."""
        start = self._state.voltage_v
        n = max(1, math.ceil(abs(voltage_v - start) / rate_v_per_s * sample_rate_hz))
        volts = start + (voltage_v - start) * np.arange(1, n + 1) / n
        return self._finish(volts).voltage_v

    def _dynamic_state(self) -> DynamicState:
        """The dynamic model's state; rebuilt (creep relaxed) if the hysteresis state was replaced."""
        assert self.dynamic is not None and self._dyn is not None
        if self._dyn.hysteresis is not self._state:
            self._dyn = DynamicState(
                self._state,
                (1.0 + self.dynamic.total_creep) * self._state.position_um,
                np.zeros(self.dynamic.taus_s.size),
            )
        return self._dyn

    def _finish(
        self, volts: NDArray[np.float64], state_after: HysteresisState | DynamicState | None = None
    ) -> AxisOutput:
        lo, hi = self.limits
        bad = (volts < lo) | (volts > hi) | ~np.isfinite(volts)
        clamped = int(np.count_nonzero(bad))
        if clamped:
            volts = np.clip(np.nan_to_num(volts, nan=self._state.voltage_v), lo, hi)
        volts, slewed = slew_limit(volts, self._state.voltage_v, self.max_step_v)
        if self.dynamic is not None:
            dyn = state_after if isinstance(state_after, DynamicState) else None
            if dyn is None or clamped or slewed:
                _, dyn = dynamic_forward(self.dynamic, volts, self._dt_s, self._dynamic_state())
            self._dyn = dyn
            self._state = dyn.hysteresis
            return AxisOutput(volts, clamped, slewed)
        if not isinstance(state_after, HysteresisState) or clamped or slewed:
            _, state_after = hysteresis_step(self.params.hysteresis, volts, self._state)
        self._state = state_after
        return AxisOutput(volts, clamped, slewed)
