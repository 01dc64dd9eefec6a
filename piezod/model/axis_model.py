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
``centre_voltage(c, dt, state)``
    The voltage at which the model, moved from ``state``, stands at position ``c``: where the
    scan planner centres a periodic scan on ``c`` (the thesis model: ``c / b``).

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
#: Samples of the straight move :meth:`AxisModel.centre_voltage` runs the inverse over.
CENTRE_MOVE_SAMPLES = 256


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

    def centre_voltage(self, center_um: float, dt_s: float, state: Any) -> float:
        """The voltage at which the model stands at ``center_um`` when moved there from ``state``.

        The default runs the model's own inverse over a straight move (the state is not
        changed): the positions of a fitted law are defined along the histories it was fitted
        on, so a voltage read off its rest curve (a stage rested at ``V`` for ever, a state no
        calibration frame visits) can be far from where its inverse really drives the stage.
        """
        start = self.position(state)
        targets = np.linspace(start, float(center_um), CENTRE_MOVE_SAMPLES + 1)[1:]
        volts, _ = self.inverse(targets, dt_s, state)
        return float(volts[-1])


@dataclass(frozen=True)
class ThesisAxisModel(AxisModel):
    """ODE (2.21) plus the creep term ``kappa (V - V_C)`` of (3.8) for the scan in progress."""

    params: ThesisParams
    kappa_um_per_v: float
    center_v: float
    kind: ClassVar[str] = "thesis"

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

    def centre_voltage(self, center_um: float, dt_s: float, state: Any) -> float:
        # the planner's own coordinates (4.12): positions b V around a relaxed loop
        return float(center_um) / self.params.b_um_per_v


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
        if self.params.creep_driver == "voltage" or self.params.law in ("generalised-play", "bouc-wen"):
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
