"""One interface for every axis model: forward, per-sample inverse, holds, adopted states.

The engine's axis driver (:mod:`piezod.service.axes`), the calibrations and the benchmarks use
an :class:`AxisModel` without knowing which model it is. A model is a frozen parameter object;
its state is an immutable value the caller keeps and passes back (so blocks, pauses, offset and
range changes and a switch of model all carry the state explicitly):

``rest(V)``
    The state of a stage that has rested at ``V`` for ever.
``forward(volts, dt, state)``
    Positions for a block of voltages, and the state after it.
``inverse(targets, dt, state)``
    Voltages whose forward model reaches the targets at every sample, and the state after it.
``hold(n, dt, state)``
    The state after holding the last voltage for ``n`` samples (creep runs on).
``adopt(V, x)``
    A state at voltage ``V`` and position ``x`` (a model switched in on a stage that is there).
``position(state)`` / ``voltage(state)``
    What the state says.
``with_plan(kappa, V_C)``
    The model for a periodic scan whose creep term is ``kappa (V - V_C)`` (only the thesis
    model (3.8) needs one; the time-domain models return themselves).
``loop_voltages(c, r, f, state)``
    The turning voltages of the model's own periodic scan of range ``r`` centred on ``c``: where
    the scan planner places it (the thesis model is planned by its closed form (4.12) instead).

Implementations: :class:`ThesisAxisModel` (ODE (2.21) + the creep term of (3.8)),
:class:`DynamicAxisModel` (:mod:`piezod.model.dynamic`), :class:`FamilyAxisModel`
(:mod:`piezod.model.family`: lag, Coleman-Hodgdon or Prandtl-Ishlinskii, creep spectrum, static map).
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.model import kernels
from piezod.model.dynamic import (
    DynamicParams,
    DynamicState,
    dynamic_forward,
    dynamic_hold,
    dynamic_inverse,
    dynamic_rest_state,
)
from piezod.model.family import (
    FamilyParams,
    family_adopt_state,
    family_forward,
    family_hold,
    family_inverse,
    family_rest_state,
)
from piezod.model.ode import HysteresisState, hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.model.params import ThesisParams

F64 = NDArray[np.float64]
#: Samples per cycle of the periodic scan :meth:`AxisModel.loop_voltages` runs the inverse over.
LOOP_SAMPLES = 512


class AxisModel(ABC):
    """A scanner axis model (frozen); states are opaque immutable values with ``voltage_v``."""

    #: The ``model:`` name in the scanner YAML.
    kind: ClassVar[str] = ""

    @abstractmethod
    def rest(self, voltage_v: float = 0.0) -> Any:
        """Rested at ``voltage_v`` for ever."""

    @abstractmethod
    def forward(self, voltage_v: ArrayLike, dt_s: float, state: Any) -> tuple[F64, Any]:
        """Positions (um) for a block of voltages, and the state after it."""

    @abstractmethod
    def inverse(self, target_um: ArrayLike, dt_s: float, state: Any) -> tuple[F64, Any]:
        """Voltages reaching the targets at every sample, and the state after them."""

    @abstractmethod
    def hold(self, samples: int, dt_s: float, state: Any) -> Any:
        """The state after holding the last voltage for ``samples`` samples."""

    @abstractmethod
    def adopt(self, voltage_v: float, position_um: float) -> Any:
        """A state at ``voltage_v`` whose position is ``position_um`` (creep relaxed)."""

    @abstractmethod
    def position(self, state: Any) -> float:
        """The position (um) a state stands for."""

    def voltage(self, state: Any) -> float:
        """The last voltage (V) of a state."""
        return float(state.voltage_v)

    def with_plan(self, kappa_um_per_v: float, center_v: float) -> AxisModel:
        """The model for a periodic scan with creep term ``kappa (V - V_C)`` (default: unchanged)."""
        return self

    #: The scan planner places this model's periodic scans with the thesis law (4.12) (only the
    #: thesis model; the others by :meth:`loop_voltages`).
    plans_by_thesis: ClassVar[bool] = False

    def loop_voltages(
        self, center_um: float, range_um: float, frequency_hz: float, state: Any
    ) -> tuple[float, float]:
        """Turning voltages ``(v_min, v_max)`` of the model's own periodic scan, from ``state``.

        The model's inverse runs the move to the scan's start and two triangle cycles
        (:data:`LOOP_SAMPLES` per cycle, creep at the scan's rate; the state is not changed); the
        second cycle's extremes are returned. The positions of a fitted law are defined along the
        histories it was fitted on, so a voltage read off its rest curve (a stage rested at ``V``
        for ever, a state no calibration frame visits) or the thesis law's ``c / b`` can be far
        from where its inverse really drives the stage: on a unipolar stack the generalised play
        law and the thesis parameters disagreed by 2x at the frame's centre.
        """
        per = LOOP_SAMPLES
        dt = 1.0 / (float(frequency_hz) * per)
        lo = float(center_um) - 0.5 * float(range_um)
        move = np.linspace(self.position(state), lo, per // 4 + 1)[1:]
        phase = (np.arange(1, 2 * per + 1) % per) / per
        loop = lo + float(range_um) * np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
        volts, _ = self.inverse(np.concatenate([move, loop]), dt, state)
        last = volts[-per:]
        return float(np.min(last)), float(np.max(last))


@dataclass(frozen=True)
class ThesisAxisModel(AxisModel):
    """ODE (2.21) plus the creep term ``kappa (V - V_C)`` of (3.8) for the scan in progress."""

    params: ThesisParams
    kappa_um_per_v: float
    center_v: float
    kind: ClassVar[str] = "thesis"
    plans_by_thesis: ClassVar[bool] = True

    def rest(self, voltage_v: float = 0.0) -> HysteresisState:
        return relaxed_state(self.params.hysteresis, voltage_v)

    def forward(
        self, voltage_v: ArrayLike, dt_s: float, state: HysteresisState
    ) -> tuple[F64, HysteresisState]:
        v = np.asarray(voltage_v, dtype=np.float64)
        xh, new = hysteresis_step(self.params.hysteresis, v, state)
        return xh + self.kappa_um_per_v * (v - self.center_v), new

    def inverse(
        self, target_um: ArrayLike, dt_s: float, state: HysteresisState
    ) -> tuple[F64, HysteresisState]:
        shifted = np.asarray(target_um, dtype=np.float64) + self.kappa_um_per_v * self.center_v
        return hysteresis_inverse_step(
            self.params.hysteresis, shifted, state, kappa_um_per_v=self.kappa_um_per_v
        )

    def hold(self, samples: int, dt_s: float, state: HysteresisState) -> HysteresisState:
        return state

    def adopt(self, voltage_v: float, position_um: float) -> HysteresisState:
        v = float(voltage_v)
        return HysteresisState(v, float(position_um) - self.kappa_um_per_v * (v - self.center_v))

    def position(self, state: HysteresisState) -> float:
        return state.position_um + self.kappa_um_per_v * (state.voltage_v - self.center_v)

    def with_plan(self, kappa_um_per_v: float, center_v: float) -> ThesisAxisModel:
        return dataclasses.replace(self, kappa_um_per_v=kappa_um_per_v, center_v=center_v)


@dataclass(frozen=True)
class DynamicAxisModel(AxisModel):
    """The time-domain model: ODE (2.21) + creep operator (:mod:`piezod.model.dynamic`)."""

    params: DynamicParams
    kind: ClassVar[str] = "dynamic"

    def rest(self, voltage_v: float = 0.0) -> DynamicState:
        return dynamic_rest_state(self.params, voltage_v)

    def forward(self, voltage_v: ArrayLike, dt_s: float, state: DynamicState) -> tuple[F64, DynamicState]:
        return dynamic_forward(self.params, voltage_v, dt_s, state)

    def inverse(self, target_um: ArrayLike, dt_s: float, state: DynamicState) -> tuple[F64, DynamicState]:
        return dynamic_inverse(self.params, target_um, dt_s, state)

    def hold(self, samples: int, dt_s: float, state: DynamicState) -> DynamicState:
        return dynamic_hold(self.params, samples, dt_s, state)

    def adopt(self, voltage_v: float, position_um: float) -> DynamicState:
        v, x = float(voltage_v), float(position_um)
        xh = x / (1.0 + self.params.total_creep)
        return DynamicState(HysteresisState(v, xh), x, np.zeros(self.params.taus_s.size))

    def position(self, state: DynamicState) -> float:
        return state.position_um


@dataclass(frozen=True)
class FamilyAxisModel(AxisModel):
    """The model family (:mod:`piezod.model.family`)."""

    params: FamilyParams
    kind: ClassVar[str] = "family"

    def __post_init__(self) -> None:
        # a model is loaded before it streams: compile its per-sample loop now, not in the first block
        if self.params.creep_driver == "voltage" or self.params.law in (
            "generalised-play",
            "bouc-wen",
            "domain-wall",
        ):
            kernels.warm_up()

    def rest(self, voltage_v: float = 0.0) -> Any:
        return family_rest_state(self.params, voltage_v)

    def forward(self, voltage_v: ArrayLike, dt_s: float, state: Any) -> tuple[F64, Any]:
        return family_forward(self.params, voltage_v, dt_s, state)

    def inverse(self, target_um: ArrayLike, dt_s: float, state: Any) -> tuple[F64, Any]:
        return family_inverse(self.params, target_um, dt_s, state)

    def hold(self, samples: int, dt_s: float, state: Any) -> Any:
        return family_hold(self.params, samples, dt_s, state)

    def adopt(self, voltage_v: float, position_um: float) -> Any:
        return family_adopt_state(self.params, voltage_v, position_um)

    def position(self, state: Any) -> float:
        return float(state.position_um)


__all__ = ["AxisModel", "DynamicAxisModel", "FamilyAxisModel", "ThesisAxisModel"]
