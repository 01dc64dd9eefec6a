"""Runtime parts around any axis model: the audit's extensions, each with an exact per-sample inverse.

The audit (:mod:`piezod.audit`) names effects the calibrated model misses (ids and parameters
of :mod:`piezod.model.registry`); these parts put them into the scanner's inverse. Per sample
``n`` at time ``t_n`` (counted from the state's rest or adoption), in the order of the simulated
stage (:mod:`hil_sim.stage`)::

    V'  = V (1 + p / 100) for V < 0, else V              polarity (partially depoled ceramic)
    x_m = M(V')                                           the wrapped axis model (lag, hysteresis, creep, ...)
    x_t = x_m (1 + r_T t / 360000)                        thermal: sensitivity drifting over the session
    x_s = x_t + k x_t^2 / 200                             stiffness (k in %/um)
    x_q = x_sat tanh(x_s / x_sat)                         saturation
    x   = x_q + r_D t / 1000                              drift (r_D in nm/s)

The time-dependent parts (thermal, drift) follow ``t`` up to their ``horizon_s`` and hold there: a
linear trend measured over a calibration session of minutes is not extrapolated over a week of
scanning (``piezod calibrate`` adopts them with :data:`~piezod.extensions.TREND_HORIZON_FACTOR`
times the session's length; without a horizon they follow ``t`` for ever). Their clock reads
``t`` plus the time since the session the trend was measured in began (``since_unix_s``: the
calibration's sensitivity is the one at that session's start, so a part adopted ten minutes later
starts ten minutes into its trend; the daemon sets it when it builds the model,
:meth:`Parts.anchored`); without ``since_unix_s`` the clock starts at the rest or adoption.

Every part is a monotone static map or a known function of time, so the inverse runs the chain
backwards exactly, ``O(1)`` per sample and vectorised: subtract the drift, ``x_sat atanh``, the
quadratic formula, divide by the thermal scale, the model's own inverse, divide negative
voltages by ``1 + p / 100``. A target the saturation cannot reach (``|x_q| >= x_sat``) is
clipped just inside it; the axis's voltage limits then clamp as for any unreachable target.

Not a part: the audit's ``delay``, which the readback shows alike wherever it sits, is the axis's
*sensor path* (:mod:`piezod.model.sensor`: undone in the analysis, the drive unchanged); a pure
delay at the drive would need targets ahead of the sample being computed (the drive *lag* is a
part of the family model). Not a part either: ``resonance``, which needs the targets ahead of
the one it shapes (:mod:`piezod.model.resonance`, applied by the axis driver before the model's
inverse); ``creep`` is the calibration's (the family's spectrum). The fast creep
(:mod:`piezod.model.fast_creep`, the axis's ``fast_creep:``, not an audit effect) has state of its
own and wraps the model inside these parts: ``x_m`` above is its output.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.axis_model import AxisModel
from piezod.model.registry import spec

F64 = NDArray[np.float64]

#: Effect ids (and their parameters) the runtime parts implement, in chain order.
PART_EFFECTS: dict[str, tuple[str, ...]] = {
    "polarity": ("negative_sensitivity_pct",),
    "thermal": ("rate_pct_per_hour",),
    "stiffness": ("sensitivity_pct_per_um",),
    "saturation": ("x_sat_um",),
    "drift": ("rate_nm_per_s",),
}
#: Parts that are functions of time: they take an optional ``horizon_s`` besides their parameters.
TIME_PARTS: tuple[str, ...] = ("thermal", "drift")


def part_effects(effects: Mapping[Any, Mapping[str, float]]) -> dict[Any, Mapping[str, float]]:
    """The effects of ``effects`` that are runtime parts (an axis's extensions also hold its sensor
    path, :mod:`piezod.model.sensor`), for :meth:`Parts.from_effects`."""
    return {k: v for k, v in effects.items() if k in PART_EFFECTS}


#: A saturated target is clipped to this fraction of ``x_sat``.
_SATURATION_REACH = 1.0 - 1e-9


@dataclass(frozen=True)
class Parts:
    """Frozen parameters of the runtime parts (0 or ``inf``: the part is off).

    Attributes
    ----------
    negative_sensitivity_pct
        Polarity: sensitivity change for ``V < 0`` (%), > -90.
    rate_pct_per_hour
        Thermal: sensitivity change per hour (%/h).
    sensitivity_pct_per_um
        Stiffness: relative sensitivity change per um of position (%/um).
    x_sat_um
        Saturation scale (um), > 0; ``inf`` for none.
    rate_nm_per_s
        Drift velocity (nm/s).
    thermal_horizon_s, drift_horizon_s
        Time (s, on the part's clock) after which the thermal / drift part holds its value instead
        of following ``t``; ``inf`` for never.
    thermal_since_unix_s, drift_since_unix_s
        The wall-clock instant (Unix time, s) at which the part's clock reads 0: the start of the
        session the trend was measured in (``nan``: the clock starts at the rest or adoption).
        Pure data here: :meth:`anchored`, called where the clock is read, turns it into
        ``*_t0_s``.
    thermal_t0_s, drift_t0_s
        The part's clock at the rest or adoption (s, >= 0).
    """

    negative_sensitivity_pct: float = 0.0
    rate_pct_per_hour: float = 0.0
    sensitivity_pct_per_um: float = 0.0
    x_sat_um: float = math.inf
    rate_nm_per_s: float = 0.0
    thermal_horizon_s: float = math.inf
    drift_horizon_s: float = math.inf
    thermal_since_unix_s: float = math.nan
    drift_since_unix_s: float = math.nan
    thermal_t0_s: float = 0.0
    drift_t0_s: float = 0.0

    def __post_init__(self) -> None:
        for effect in TIME_PARTS:
            h = getattr(self, f"{effect}_horizon_s")
            if not h > 0.0:
                raise ModelError(f"{effect}.horizon_s = {h!r} must be > 0 (s)")
            since = getattr(self, f"{effect}_since_unix_s")
            if not (math.isnan(since) or (math.isfinite(since) and since >= 0.0)):
                raise ModelError(f"{effect}.since_unix_s = {since!r} must be a Unix time (s)")
            t0 = getattr(self, f"{effect}_t0_s")
            if not (math.isfinite(t0) and t0 >= 0.0):
                raise ModelError(f"{effect} clock at adoption {t0!r} must be finite and >= 0 (s)")
        for effect, names in PART_EFFECTS.items():
            for name in names:
                value = getattr(self, name)
                if name == "x_sat_um" and value == math.inf:
                    continue
                low, high = spec(effect).param(name).physical
                if not (math.isfinite(value) and low <= value <= high):
                    raise ModelError(
                        f"{effect}.{name} = {value!r} outside its physical range [{low}, {high}]"
                    )

    @classmethod
    def from_effects(cls, effects: Mapping[Any, Mapping[str, float]]) -> Parts:
        """From ``{effect id: {parameter: value}}`` (registry names); effects without a part are refused."""
        fields: dict[str, float] = {}
        for effect, params in effects.items():
            if effect not in PART_EFFECTS:
                raise ModelError(f"effect {effect!r} has no runtime part (parts: {', '.join(PART_EFFECTS)})")
            for name, value in params.items():
                if name in ("horizon_s", "since_unix_s") and effect in TIME_PARTS:
                    fields[f"{effect}_{name}"] = float(value)
                    continue
                if name not in PART_EFFECTS[effect]:
                    raise ModelError(f"effect {effect!r} has no runtime parameter {name!r}")
                fields[name] = float(value)
        return cls(**fields)

    def effects(self) -> dict[str, dict[str, float]]:
        """The parts that are on, as ``{effect id: {parameter: value}}``."""
        off = {"x_sat_um": math.inf}
        out = {
            effect: {n: float(getattr(self, n)) for n in names}
            for effect, names in PART_EFFECTS.items()
            if any(getattr(self, n) != off.get(n, 0.0) for n in names)
        }
        for effect in TIME_PARTS:
            for key in ("horizon_s", "since_unix_s"):
                value = float(getattr(self, f"{effect}_{key}"))
                if effect in out and math.isfinite(value):
                    out[effect][key] = value
        return out

    def anchored(self, now_unix_s: float) -> Parts:
        """The parts with each time part's clock at ``now_unix_s`` set from its ``since_unix_s``
        (a trend measured from the start of a calibration session goes on from where it is now,
        not from 0 at the adoption; parts without ``since_unix_s`` are unchanged)."""
        fields: dict[str, float] = {}
        for effect in TIME_PARTS:
            since = float(getattr(self, f"{effect}_since_unix_s"))
            if math.isfinite(since):
                fields[f"{effect}_t0_s"] = max(float(now_unix_s) - since, 0.0)
        return dataclasses.replace(self, **fields) if fields else self

    @property
    def identity(self) -> bool:
        """No part is on."""
        return not self.effects()

    # -- the maps ---------------------------------------------------------------------------------

    def voltage_in(self, v: F64) -> F64:
        """``V'``: the voltage the wrapped model sees."""
        if self.negative_sensitivity_pct == 0.0:
            return v
        out: F64 = np.where(v < 0.0, v * (1.0 + self.negative_sensitivity_pct / 100.0), v)
        return out

    def voltage_out(self, u: F64) -> F64:
        """The commanded voltage whose ``V'`` is ``u`` (inverse of :meth:`voltage_in`)."""
        if self.negative_sensitivity_pct == 0.0:
            return u
        out: F64 = np.where(u < 0.0, u / (1.0 + self.negative_sensitivity_pct / 100.0), u)
        return out

    def position_out(self, xm: F64, t: F64) -> F64:
        """``x`` from the wrapped model's position ``x_m`` at times ``t``."""
        x = xm
        if self.rate_pct_per_hour != 0.0:
            x = x * self._thermal_scale(t)
        k = self.sensitivity_pct_per_um / 200.0
        if k != 0.0:
            x = x + k * x * x
        if self.x_sat_um != math.inf:
            x = self.x_sat_um * np.tanh(x / self.x_sat_um)
        if self.rate_nm_per_s != 0.0:
            x = x + self._drift_um(t)
        return x

    def _thermal_scale(self, t: F64) -> F64:
        clock = np.minimum(t + self.thermal_t0_s, self.thermal_horizon_s)
        out: F64 = 1.0 + self.rate_pct_per_hour * clock / 360000.0
        return out

    def _drift_um(self, t: F64) -> F64:
        out: F64 = self.rate_nm_per_s * 1e-3 * np.minimum(t + self.drift_t0_s, self.drift_horizon_s)
        return out

    def position_in(self, x: F64, t: F64) -> F64:
        """The wrapped model's target ``x_m`` for the position ``x`` at times ``t`` (exact inverse)."""
        y = x
        if self.rate_nm_per_s != 0.0:
            y = y - self._drift_um(t)
        if self.x_sat_um != math.inf:
            xs = self.x_sat_um
            y = xs * np.arctanh(np.clip(y / xs, -_SATURATION_REACH, _SATURATION_REACH))
        k = self.sensitivity_pct_per_um / 200.0
        if k != 0.0:
            y = 2.0 * y / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * k * y, 0.0)))
        if self.rate_pct_per_hour != 0.0:
            y = y / self._thermal_scale(t)
        return y


@dataclass(frozen=True, slots=True, eq=False)
class PartsState:
    """State of a model with parts.

    Attributes
    ----------
    inner
        The wrapped model's state.
    time_s
        Time of the last sample since the rest or adoption (s).
    position_um, voltage_v
        Position and commanded voltage of the last sample.
    """

    inner: Any
    time_s: float
    position_um: float
    voltage_v: float


@dataclass(frozen=True)
class PartsAxisModel(AxisModel):
    """An axis model with runtime parts around it (the audit's extensions): see the module docstring.

    Attributes
    ----------
    inner
        The wrapped model (thesis, dynamic or family).
    parts
        The parts.
    """

    inner: AxisModel
    parts: Parts

    @property
    def kind(self) -> str:  # type: ignore[override]
        """The wrapped model's ``model:`` name."""
        return self.inner.kind

    def _state(self, inner: Any, t: float) -> PartsState:
        xm = np.array([self.inner.position(inner)])
        x = float(self.parts.position_out(xm, np.array([t]))[0])
        v = float(self.parts.voltage_out(np.array([self.inner.voltage(inner)]))[0])
        return PartsState(inner, t, x, v)

    def rest(self, voltage_v: float = 0.0) -> PartsState:
        u = float(self.parts.voltage_in(np.array([float(voltage_v)]))[0])
        return self._state(self.inner.rest(u), 0.0)

    def forward(self, voltage_v: ArrayLike, dt_s: float, state: Any) -> tuple[F64, PartsState]:
        v = np.asarray(voltage_v, dtype=np.float64)
        if v.size == 0:
            return np.empty(0), state
        t = _times(state, v.size, dt_s)
        xm, inner = self.inner.forward(self.parts.voltage_in(v), dt_s, state.inner)
        x = self.parts.position_out(xm, t)
        return x, PartsState(inner, float(t[-1]), float(x[-1]), float(v[-1]))

    def inverse(self, target_um: ArrayLike, dt_s: float, state: Any) -> tuple[F64, PartsState]:
        x = np.asarray(target_um, dtype=np.float64)
        if x.size == 0:
            return np.empty(0), state
        t = _times(state, x.size, dt_s)
        u, inner = self.inner.inverse(self.parts.position_in(x, t), dt_s, state.inner)
        return self.parts.voltage_out(u), self._state(inner, float(t[-1]))

    def hold(self, samples: int, dt_s: float, state: Any) -> PartsState:
        inner = self.inner.hold(samples, dt_s, state.inner)
        return self._state(inner, state.time_s + samples * dt_s)

    def adopt(self, voltage_v: float, position_um: float) -> PartsState:
        u = float(self.parts.voltage_in(np.array([float(voltage_v)]))[0])
        xm = float(self.parts.position_in(np.array([float(position_um)]), np.zeros(1))[0])
        return self._state(self.inner.adopt(u, xm), 0.0)

    def position(self, state: Any) -> float:
        return float(state.position_um)

    def voltage(self, state: Any) -> float:
        return float(state.voltage_v)

    def with_plan(self, kappa_um_per_v: float, center_v: float) -> AxisModel:
        return PartsAxisModel(self.inner.with_plan(kappa_um_per_v, center_v), self.parts)

    @property
    def plans_by_thesis(self) -> bool:  # type: ignore[override]
        """The wrapped model's planner."""
        return self.inner.plans_by_thesis


def with_parts(model: AxisModel, parts: Parts) -> AxisModel:
    """``model`` with ``parts`` around it (``model`` itself when no part is on)."""
    return model if parts.identity else PartsAxisModel(model, parts)


def _times(state: PartsState, n: int, dt_s: float) -> F64:
    if not (math.isfinite(dt_s) and dt_s > 0.0):
        raise ModelError(f"dt_s must be finite and > 0, got {dt_s!r}")
    out: F64 = state.time_s + dt_s * np.arange(1, n + 1, dtype=np.float64)
    return out


__all__ = [
    "PART_EFFECTS",
    "TIME_PARTS",
    "Parts",
    "PartsAxisModel",
    "PartsState",
    "part_effects",
    "with_parts",
]
