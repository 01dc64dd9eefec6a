"""Scanner configuration: one YAML file per scanner, validated by pydantic.

Every field carries its unit in its name. Unknown keys are rejected, and a bad
value is reported as ``FILE:LINE: field.path: reason``. ``piezod`` ships the
thesis scanners and the simulated stage in ``configs/``; :func:`config_dir`
finds them from a source checkout.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import difflib
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from piezod.errors import ConfigError, ModelError
from piezod.model.aftereffect import DEFAULT_INTERVAL_S, AfterEffect
from piezod.model.boucwen import BoucWenParams
from piezod.model.domainwall import DomainWallParams
from piezod.model.dynamic import DynamicParams
from piezod.model.family import CreepSpectrum, FamilyParams
from piezod.model.fast_creep import FastCreep
from piezod.model.gplay import GeneralisedPlayParams
from piezod.model.params import HysteresisParams, ThesisParams
from piezod.model.parts import Parts, part_effects
from piezod.model.play import PlayParams
from piezod.model.resonance import ResonancePart
from piezod.model.sensor import SensorPath

AxisName = Literal["x", "y", "z"]


class StrictModel(BaseModel):
    """Base for config models: frozen, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class ThesisModelConfig(StrictModel):
    """Parameters of the hysteresis + creep model (3.8), thesis table 3.3."""

    alpha_per_v: float = Field(gt=0, lt=1.0, description="hysteresis transition rate alpha (1/V)")
    b_um_per_v: float = Field(gt=0, lt=100.0, description="sensitivity b (um/V)")
    u_um_per_v: float = Field(gt=0, lt=100.0, description="virgin-curve slope u (um/V)")
    tau_s: float = Field(gt=0, lt=1e6, description="creep time constant tau (s)")
    a1: float = Field(ge=-10, le=10, description="creep frequency amplitude A1")
    a2_per_v: float = Field(ge=-1.0, le=1.0, description="creep range coefficient A2 (1/V)")
    a3: float = Field(ge=-100, le=100, description="creep constant A3")

    def params(self) -> ThesisParams:
        """The frozen model parameter object."""
        return ThesisParams(**self.model_dump())


class DynamicModelConfig(StrictModel):
    """Parameters of the time-domain model (``model: dynamic``): ODE (2.21) + log-spaced creep.

    See :mod:`piezod.model.dynamic`. The creep weights follow from ``creep_pct_per_decade``
    and ``creep_exponent`` over the fixed spread of relaxation times.
    """

    alpha_per_v: float = Field(gt=0, lt=1.0, description="hysteresis transition rate alpha (1/V)")
    b_um_per_v: float = Field(gt=0, lt=100.0, description="fast (hysteretic) sensitivity b (um/V)")
    u_um_per_v: float = Field(gt=0, lt=100.0, description="slope after a reversal u (um/V)")
    creep_pct_per_decade: float = Field(
        ge=0, le=20, description="creep per decade of time at 1 s (% of the hysteretic motion)"
    )
    creep_exponent: float = Field(
        default=0.0, ge=-0.5, le=0.5, description="creep per decade scales as (t / 1 s)^exponent"
    )
    creep_tau_min_s: float = Field(default=1e-3, gt=0, le=1e3, description="shortest relaxation time (s)")
    creep_tau_max_s: float = Field(default=1e5, gt=0, le=1e9, description="longest relaxation time (s)")
    creep_per_decade: int = Field(default=3, ge=1, le=20, description="relaxation times per decade")

    @model_validator(mode="after")
    def _check_model(self) -> DynamicModelConfig:
        if not self.creep_tau_max_s > self.creep_tau_min_s:
            raise ValueError(
                f"creep_tau_max_s ({self.creep_tau_max_s}) must exceed "
                f"creep_tau_min_s ({self.creep_tau_min_s})"
            )
        self.params()
        return self

    def params(self) -> DynamicParams:
        """The frozen model parameter object."""
        return DynamicParams(**self.model_dump())


class FamilyModelConfig(StrictModel):
    """Parameters of the model family (``model: family``), see :mod:`piezod.model.family`.

    ``law: coleman-hodgdon`` needs ``alpha_per_v`` and ``u_um_per_v``; ``law: prandtl-ishlinskii``
    needs ``pi_rho0``, ``pi_thresholds_v`` and ``pi_weights``; ``law: generalised-play`` (a
    Preisach law, :mod:`piezod.model.gplay`) needs ``gp_thresholds_v``, ``gp_nodes_v`` and
    ``gp_density`` (its ``b_um_per_v`` is the rest slope at 0 V, for information); ``law: bouc-wen``
    (a Duhem law with direction- and sign-dependent rates, :mod:`piezod.model.boucwen`) needs
    ``bw_c_um_per_v``, ``bw_rates_per_v`` and ``bw_amp_down`` (and ``bw_exponent``, default 1); ``law:
    domain-wall`` (pinned walls relaxing towards an anhysteretic curve, :mod:`piezod.model.domainwall`)
    needs ``dw_w_um_per_v``, ``dw_pinning_v``, ``dw_centre_v`` and ``dw_width_v`` (and
    ``dw_interaction``, default 0). The creep
    spectrum is a list of non-negative weights on relaxation times. ``piezod calibrate`` writes this section.
    """

    law: Literal["coleman-hodgdon", "prandtl-ishlinskii", "generalised-play", "bouc-wen", "domain-wall"] = (
        Field(description="hysteresis law")
    )
    b_um_per_v: float = Field(gt=0, lt=100.0, description="sensitivity b of the hysteresis law (um/V)")
    alpha_per_v: float | None = Field(default=None, gt=0, lt=1.0, description="coleman-hodgdon: alpha (1/V)")
    u_um_per_v: float | None = Field(default=None, gt=0, lt=100.0, description="coleman-hodgdon: u (um/V)")
    pi_rho0: float | None = Field(default=None, gt=0, le=2.0, description="prandtl-ishlinskii: slope / b")
    pi_thresholds_v: list[float] = Field(default=[], description="prandtl-ishlinskii: play half-widths (V)")
    pi_weights: list[float] = Field(
        default=[], description="prandtl-ishlinskii: play weights (fractions of b)"
    )
    gp_thresholds_v: list[float] = Field(default=[], description="generalised-play: play half-widths (V)")
    gp_nodes_v: list[float] = Field(default=[], description="generalised-play: relay-centre nodes (V)")
    gp_density: list[list[float]] = Field(
        default=[],
        description="generalised-play: density (um/V) per row (reversible part, then one per play) and node",
    )
    bw_c_um_per_v: float | None = Field(
        default=None, description="bouc-wen: weight c of the hysteretic variable, x_h = b V + c h (um/V)"
    )
    bw_rates_per_v: list[float] = Field(
        default=[],
        description="bouc-wen: relaxation rates of h (1/V): rising with h > 0, rising with h < 0, "
        "falling with h < 0, falling with h > 0",
    )
    bw_amp_down: float | None = Field(default=None, gt=0, description="bouc-wen: A_down / A_up")
    bw_exponent: float = Field(
        default=1.0, ge=1, le=4, description="bouc-wen: exponent n of the knee (1: exponential, 2: tanh)"
    )
    dw_w_um_per_v: float | None = Field(
        default=None, ge=0, lt=100.0, description="domain-wall: weight w of the walls, x_h = b V + w P (um/V)"
    )
    dw_pinning_v: float | None = Field(default=None, gt=0, le=1e6, description="domain-wall: pinning k (V)")
    dw_centre_v: float | None = Field(
        default=None, ge=-1e4, le=1e4, description="domain-wall: centre h_b of the anhysteretic curve (V)"
    )
    dw_width_v: float | None = Field(
        default=None, gt=0, le=1e6, description="domain-wall: width a of the anhysteretic curve (V)"
    )
    dw_interaction: float = Field(
        default=0.0, ge=0, le=0.9, description="domain-wall: interaction alpha, field h = V + alpha P"
    )
    creep_taus_s: list[float] = Field(description="creep relaxation times (s), ascending")
    creep_weights: list[float] = Field(description="creep weights (fractions of the hysteretic motion)")
    lag_time_constant_s: float = Field(default=0.0, ge=0, le=1.0, description="drive pole (s)")
    stiffness_pct_per_um: float = Field(
        default=0.0, ge=-5, le=5, description="static map x + k x^2/200 (%/um)"
    )
    creep_driver: Literal["position", "voltage"] = Field(
        default="position", description="what the creep follows: the hysteretic position or the drive voltage"
    )
    offset_um: float = Field(
        default=0.0,
        ge=-1e4,
        le=1e4,
        description="where the position sensor reads the model's zero (um), added after the static map",
    )
    ae_fluctuation_v: float | None = Field(
        default=None,
        gt=0,
        le=1e6,
        description="after-effect (generalised-play, domain-wall): fluctuation voltage g0 (V)",
    )
    ae_time_s: float | None = Field(
        default=None,
        gt=0,
        le=1e9,
        description="after-effect (generalised-play, domain-wall): relaxation time tau (s)",
    )
    ae_interval_s: float = Field(
        default=DEFAULT_INTERVAL_S,
        gt=0,
        le=1.0,
        description="after-effect (generalised-play, domain-wall): relaxation interval (s)",
    )

    @model_validator(mode="after")
    def _check_model(self) -> FamilyModelConfig:
        if (self.ae_fluctuation_v is None) != (self.ae_time_s is None):
            raise ValueError("an after-effect needs both ae_fluctuation_v and ae_time_s")
        if self.law == "coleman-hodgdon" and (self.alpha_per_v is None or self.u_um_per_v is None):
            raise ValueError("law coleman-hodgdon needs alpha_per_v and u_um_per_v")
        if self.law == "prandtl-ishlinskii" and self.pi_rho0 is None:
            raise ValueError("law prandtl-ishlinskii needs pi_rho0, pi_thresholds_v and pi_weights")
        if self.law == "bouc-wen" and (
            self.bw_c_um_per_v is None or len(self.bw_rates_per_v) != 4 or self.bw_amp_down is None
        ):
            raise ValueError("law bouc-wen needs bw_c_um_per_v, bw_rates_per_v (4 rates) and bw_amp_down")
        dw = (self.dw_w_um_per_v, self.dw_pinning_v, self.dw_centre_v, self.dw_width_v)
        if self.law == "domain-wall" and any(v is None for v in dw):
            raise ValueError("law domain-wall needs dw_w_um_per_v, dw_pinning_v, dw_centre_v and dw_width_v")
        if self.law == "generalised-play" and not (self.gp_nodes_v and self.gp_density):
            raise ValueError("law generalised-play needs gp_thresholds_v, gp_nodes_v and gp_density")
        try:
            self.params()
        except ModelError as exc:
            raise ValueError(str(exc)) from exc
        return self

    def params(self) -> FamilyParams:
        """The frozen model parameter object."""
        hyst: HysteresisParams | PlayParams | GeneralisedPlayParams | BoucWenParams | DomainWallParams
        if self.law == "domain-wall":
            w, pin, hb, a = self.dw_w_um_per_v, self.dw_pinning_v, self.dw_centre_v, self.dw_width_v
            assert w is not None and pin is not None and hb is not None and a is not None
            hyst = DomainWallParams(self.b_um_per_v, w, pin, hb, a, self.dw_interaction)
        elif self.law == "bouc-wen":
            assert self.bw_c_um_per_v is not None and self.bw_amp_down is not None
            k = self.bw_rates_per_v
            c, amp, n = self.bw_c_um_per_v, self.bw_amp_down, self.bw_exponent
            hyst = BoucWenParams(self.b_um_per_v, c, k[0], k[1], k[2], k[3], amp, n)
        elif self.law == "generalised-play":
            hyst = GeneralisedPlayParams(
                tuple(self.gp_thresholds_v),
                tuple(self.gp_nodes_v),
                tuple(tuple(row) for row in self.gp_density),
            )
        elif self.law == "coleman-hodgdon":
            assert self.alpha_per_v is not None and self.u_um_per_v is not None
            hyst = HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
        else:
            assert self.pi_rho0 is not None
            hyst = PlayParams(
                self.b_um_per_v, self.pi_rho0, tuple(self.pi_thresholds_v), tuple(self.pi_weights)
            )
        return FamilyParams(
            hyst,
            CreepSpectrum(tuple(self.creep_taus_s), tuple(self.creep_weights)),
            self.lag_time_constant_s,
            self.stiffness_pct_per_um,
            self.creep_driver,
            self.offset_um,
            None
            if self.ae_fluctuation_v is None or self.ae_time_s is None
            else AfterEffect(self.ae_fluctuation_v, self.ae_time_s, self.ae_interval_s),
        )


class FastCreepConfig(StrictModel):
    """Fast creep around the axis model (:mod:`piezod.model.fast_creep`): ``weights[j]`` of the motion
    arrive with the relaxation time ``taus_s[j]``; the static gain is unchanged."""

    taus_s: list[float] = Field(description="relaxation times (s), ascending, > 0")
    weights: list[float] = Field(
        description="fractions of the motion, one per relaxation time (negative: less creep than the model's)"
    )

    def part(self) -> FastCreep:
        """The frozen part."""
        return FastCreep(tuple(self.taus_s), tuple(self.weights))

    @model_validator(mode="after")
    def _check(self) -> FastCreepConfig:
        try:
            self.part()
        except ModelError as exc:
            raise ValueError(str(exc)) from exc
        return self


PartEffect = Literal["polarity", "thermal", "stiffness", "saturation", "drift", "delay", "resonance"]


class AxisConfig(StrictModel):
    """One scanner axis: its voltage limits, safety settings and model."""

    voltage_min_v: float = Field(ge=-2000, le=2000, description="lowest voltage ever applied (V)")
    voltage_max_v: float = Field(ge=-2000, le=2000, description="highest voltage ever applied (V)")
    safe_voltage_v: float = Field(default=0.0, description="voltage ramped to on stop / fault (V)")
    slew_rate_v_per_s: float = Field(
        default=2000.0, gt=0, description="largest |dV/dt| the host commands (V/s)"
    )
    model: Literal["thesis", "dynamic", "family"] = "thesis"
    thesis: ThesisModelConfig
    dynamic: DynamicModelConfig | None = Field(
        default=None, description="time-domain model parameters (required by model: dynamic)"
    )
    family: FamilyModelConfig | None = Field(
        default=None, description="model-family parameters (required by model: family)"
    )
    extensions: dict[PartEffect, dict[str, float]] | None = Field(
        default=None,
        description="runtime parts around the model (the audit's findings, piezod.model.parts): "
        "{effect id: {parameter: value}} with the names of piezod.model.registry; delay is the "
        "sensor path (the readback's delay and lag, piezod.model.sensor): the analysis aligns the "
        "readback with it, the drive is unchanged; resonance shapes the targets ahead so the mode does not "
        "ring (piezod.model.resonance)",
    )
    fast_creep: FastCreepConfig | None = Field(
        default=None,
        description="creep faster than the calibration frame's lines, which the frame shows only as "
        "sensitivity (piezod.model.fast_creep): piezod calibrate identifies it from the frame's "
        "harmonics at its several rates (piezod.rate_id); none: off",
    )
    sensor_full_scale_um: float | None = Field(
        default=None,
        gt=0,
        le=1e5,
        description="the position sensor's range on the board's ADC: code +-32768 reads +-this many um "
        "(none: the link's default, 100 um). A stage that moves beyond it reads the full scale: piezod "
        "calibrate leaves such scans out of its fits and says so",
    )
    tracking_min_line_s: float | None = Field(
        default=None,
        gt=0,
        description="the sensitivity tracker learns only from lines of this axis at least this long (s); "
        "piezod calibrate writes the calibration frame's shortest line: a faster line's length error is "
        "the model's rate error beyond what the frame measured, not a change of sensitivity "
        "(none: every line)",
    )

    def parts(self) -> Parts:
        """The runtime parts of :attr:`extensions` (the drive side)."""
        return Parts.from_effects(part_effects(self.extensions or {}))

    def sensor_path(self) -> SensorPath:
        """The sensor path of :attr:`extensions` (identity when none)."""
        return SensorPath.from_effects({str(k): v for k, v in (self.extensions or {}).items()})

    def resonance(self) -> ResonancePart:
        """The resonance part of :attr:`extensions` (off when none)."""
        return ResonancePart.from_effects({str(k): v for k, v in (self.extensions or {}).items()})

    def fast_creep_part(self) -> FastCreep:
        """The fast creep around the model (the identity when none)."""
        return FastCreep() if self.fast_creep is None else self.fast_creep.part()

    @model_validator(mode="after")
    def _check_limits(self) -> AxisConfig:
        try:
            self.parts()
            self.sensor_path()
            self.resonance()
        except ModelError as exc:
            raise ValueError(f"extensions: {exc}") from exc
        if not self.voltage_min_v < self.voltage_max_v:
            raise ValueError(
                f"voltage_min_v ({self.voltage_min_v}) must be below voltage_max_v ({self.voltage_max_v})"
            )
        if not self.voltage_min_v <= self.safe_voltage_v <= self.voltage_max_v:
            raise ValueError(
                f"safe_voltage_v ({self.safe_voltage_v}) must lie inside "
                f"[{self.voltage_min_v}, {self.voltage_max_v}]"
            )
        if self.model == "dynamic" and self.dynamic is None:
            raise ValueError("model: dynamic needs a dynamic: section (piezod calibrate writes it)")
        if self.model == "family" and self.family is None:
            raise ValueError("model: family needs a family: section (piezod calibrate writes it)")
        return self


class ApiConfig(StrictModel):
    """Control API access (``piezod serve --api``)."""

    socket_group: str | None = Field(
        default=None, description="group owning the Unix socket (mode 0660); None = the daemon's group"
    )
    allow_remote: bool = Field(
        default=False, description="allow --api tcp: on non-loopback addresses (then a token is required)"
    )
    token_file: str | None = Field(
        default=None, description="file holding the bearer token required on TCP (required when allow_remote)"
    )

    @model_validator(mode="after")
    def _remote_needs_token(self) -> ApiConfig:
        if self.allow_remote and not self.token_file:
            raise ValueError("allow_remote needs token_file: a non-loopback API must require a token")
        return self


class ServiceConfig(StrictModel):
    """How the daemon streams and records."""

    recording_dir: str = Field(default="recordings", description="where recordings are written")
    lead_ms: float = Field(
        default=150.0, ge=100.0, le=5000.0, description="samples kept ahead in the FIFO (ms)"
    )
    block_ms: float = Field(default=20.0, ge=1.0, le=500.0, description="samples computed per block (ms)")
    heartbeat_timeout_ms: int = Field(
        default=500, ge=50, le=60_000, description="board watchdog timeout (ms)"
    )
    ramp_rate_v_per_s: float = Field(default=200.0, gt=0, le=1e5, description="ramp-to-safe rate (V/s)")
    link_bytes_per_s: float | None = Field(
        default=None,
        gt=0,
        le=1e9,
        description=(
            "bytes/s the board link carries each way (a UART: baud / 10); the status period and "
            "frame size are derived from it and the sample rate (docs/hardware.md); null = a fast link"
        ),
    )
    link_shared: bool = Field(
        default=False, description="both directions share link_bytes_per_s (QEMU's emulated UART on a pty)"
    )
    sensitivity_tracking: bool = Field(
        default=True, description="correct slow sensitivity drift from the sensor readback of corrected scans"
    )
    sensitivity_gain: float = Field(
        default=0.25, gt=0, le=1, description="fraction of a line's measured length error corrected per line"
    )
    sensitivity_max_step_pct: float = Field(
        default=0.05, gt=0, le=1, description="largest change of the tracked sensitivity per line (%)"
    )
    sensitivity_limit_pct: float = Field(
        default=3.0, gt=0, le=20, description="largest total correction of the tracked sensitivity (%)"
    )
    sensitivity_drift_pct_per_hour: float = Field(
        default=2.0,
        ge=0,
        le=100,
        description=(
            "fastest sensitivity drift expected (%/h; warm-up): after a pause, or with a model fitted "
            "long ago, the tracker weighs the next lines by what such a drift could have moved "
            "meanwhile (0: always the bounded slow update)"
        ),
    )
    sensitivity_line_scatter_pct: float = Field(
        default=0.05,
        gt=0,
        le=5,
        description="line-to-line scatter of a corrected line's measured length error (%: noise, model)",
    )

    def block_samples(self, rate_hz: float) -> int:
        """Samples the engine computes per block at a ``rate_hz`` sample clock (at least 1)."""
        return max(1, round(rate_hz * self.block_ms / 1000.0))


class MicroscopeSection(StrictModel):
    """The microscope around the scanner: where the height signal comes from (``piezod image``)."""

    z_monitor_ratio: float = Field(
        default=100.0, gt=0, le=1e4, description="the z channel's ADC reads the z-piezo voltage / this"
    )
    z_monitor_full_scale: float = Field(
        default=2.56, gt=0, le=1e3, description="ADC full scale of the z monitor input (monitor volts)"
    )
    position_sensor: bool = Field(default=True, description="false: the x / y ADC channels carry no sensor")
    pixels: int = Field(default=256, ge=2, le=16_384, description="default pixels per image line")


class ScannerConfig(StrictModel):
    """A scanner: its axes, and optional sections used by the simulator and the service."""

    name: str = Field(min_length=1)
    description: str = ""
    notes: list[str] = Field(default_factory=list)
    sample_rate_hz: float = Field(default=10_000.0, gt=0, le=1e6, description="board sample clock (Hz)")
    axes: dict[AxisName, AxisConfig]
    api: ApiConfig = Field(default_factory=ApiConfig)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    simulation: dict[str, Any] | None = Field(
        default=None, description="the simulated stage's physics (hil_sim validates it)"
    )
    calibration: dict[str, Any] | None = Field(
        default=None, description="provenance of the model parameters (written by piezod calibrate)"
    )
    microscope: MicroscopeSection | None = Field(
        default=None, description="a microscope records height on the z channel (z-piezo voltage monitor)"
    )

    def with_axis(self, axis: AxisName, **update: Any) -> ScannerConfig:
        """A copy with ``axis``'s fields replaced by ``update`` (the others shared, not revalidated,
        as :meth:`pydantic.BaseModel.model_copy`)."""
        changed = self.axes[axis].model_copy(update=update)
        return self.model_copy(update={"axes": {**self.axes, axis: changed}})

    @model_validator(mode="after")
    def _check_axes(self) -> ScannerConfig:
        if "x" not in self.axes:
            raise ValueError("axes must contain at least the fast axis 'x'")
        return self


#: Largest scanner YAML read (bytes); real configs are a few kB.
MAX_CONFIG_BYTES = 1 << 20
#: Deepest nesting of mappings / sequences in a config.
MAX_CONFIG_DEPTH = 32
#: Most YAML nodes after expanding aliases (a billion-laughs file is refused long before memory fills).
MAX_CONFIG_NODES = 100_000

_SCI_FLOAT = re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader refusing duplicate keys, deep nesting and alias expansion beyond the limits.

    ``1e-3`` (no dot) is a float, as in YAML 1.2.
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0
        self._sizes: dict[int, int] = {}

    def _count(self, n: int, mark: yaml.Mark | None) -> None:
        self._nodes += n
        if self._nodes > MAX_CONFIG_NODES:
            raise yaml.YAMLError(_Problem(f"more than {MAX_CONFIG_NODES} values (alias expansion?)", mark))

    def _size(self, node: yaml.Node) -> int:
        known = self._sizes.get(id(node))
        if known is not None:
            return known
        if isinstance(node, yaml.MappingNode):
            size = 1 + sum(self._size(k) + self._size(v) for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            size = 1 + sum(self._size(v) for v in node.value)
        else:
            size = 1
        self._sizes[id(node)] = size
        return size

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark  # type: ignore[no-untyped-call]
            node = super().compose_node(parent, index)
            if node is not None:
                self._count(self._size(node), mark)
            return node
        mark = self.peek_event().start_mark  # type: ignore[no-untyped-call]
        self._depth += 1
        try:
            if self._depth > MAX_CONFIG_DEPTH:
                raise yaml.YAMLError(_Problem(f"nested deeper than {MAX_CONFIG_DEPTH} levels", mark))
            self._count(1, mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.get(key)
            except TypeError:
                continue  # unhashable key: the base class reports it
            if first is not None:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"duplicate key {key!r} (first on line {first})",
                    key_node.start_mark,
                )
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _SCI_FLOAT, list("-+0123456789"))


@dataclass
class _Problem:
    """A YAMLError payload with a mark (like PyYAML's MarkedYAMLError)."""

    problem: str
    problem_mark: yaml.Mark | None

    def __str__(self) -> str:
        return self.problem


def _yaml_line(root: yaml.Node | None, loc: tuple[int | str, ...]) -> int | None:
    """1-based line of the YAML node at the pydantic location ``loc`` (deepest found)."""
    node = root
    line = node.start_mark.line + 1 if node is not None else None
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            for k_node, v_node in node.value:
                if k_node.value == str(key):
                    node = v_node
                    line = k_node.start_mark.line + 1
                    break
            else:
                return line
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def read_config_text(path: Path, what: str = "config") -> str:
    """The text of a small config file: a regular file, at most :data:`MAX_CONFIG_BYTES`, UTF-8.

    Raises
    ------
    ConfigError
        ``path: reason`` (``path:line: ...`` for a byte that is not UTF-8).
    """
    try:
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{path}: not a regular file; a {what} must be a file")
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: larger than {MAX_CONFIG_BYTES // 1024} KiB; not a {what}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{path}:{line}: byte 0x{raw[exc.start]:02x} is not UTF-8 (save the file as UTF-8)"
        ) from exc


def _load_yaml(path: Path, text: str) -> tuple[yaml.Node | None, Any]:
    """Compose and construct ``text`` with the strict loader."""
    loader = _StrictLoader(text)
    try:
        root = loader.get_single_node()
        data = loader.construct_document(root) if root is not None else None
    except yaml.YAMLError as exc:
        payload = exc.args[0] if exc.args and isinstance(exc.args[0], _Problem) else exc
        mark = getattr(payload, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(payload, "problem", None) or str(payload)
        raise ConfigError(f"{where}: invalid YAML: {_one_line(problem)}") from exc
    except RecursionError as exc:  # deeper than the interpreter allows, before our limit
        raise ConfigError(f"{path}: invalid YAML: nested too deeply") from exc
    finally:
        loader.dispose()
    return root, data


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _non_finite(data: Any, loc: tuple[int | str, ...] = ()) -> Iterator[tuple[int | str, ...]]:
    """Locations of NaN / infinite numbers in loaded YAML."""
    if isinstance(data, float) and not math.isfinite(data):
        yield loc
    elif isinstance(data, dict):
        for k, v in data.items():
            yield from _non_finite(v, (*loc, k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from _non_finite(v, (*loc, i))


def _model_at(model: type[BaseModel], loc: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model class reached by following ``loc`` from ``model`` (dict values, optionals)."""
    current: Any = model
    keys = list(loc)
    while keys:
        if isinstance(current, type) and issubclass(current, BaseModel):
            info = current.model_fields.get(str(keys.pop(0)))
            if info is None:
                return None
            current = info.annotation
            continue
        origin = get_origin(current)
        args = get_args(current)
        if origin is dict and len(args) == 2:
            keys.pop(0)
            current = args[1]
        elif args:
            models = [a for a in args if isinstance(a, type) and issubclass(a, BaseModel)]
            if not models:
                return None
            current = models[0]
        else:
            return None
    while not (isinstance(current, type) and issubclass(current, BaseModel)):
        models = [a for a in get_args(current) if isinstance(a, type) and issubclass(a, BaseModel)]
        if not models:
            return None
        current = models[0]
    return current


def _problems(exc: ValidationError, model: type[BaseModel]) -> list[tuple[tuple[int | str, ...], str]]:
    """(location, reason) of every error; a typo is one "unknown key (did you mean ...)" error.

    A misspelt required key shows up twice in pydantic (the unknown key, the missing field): the
    missing field it most likely meant is dropped from the list.
    """
    errs = []
    for err in exc.errors():
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        errs.append((loc, err["type"], err["msg"]))
    missing = {loc for loc, kind, _ in errs if kind == "missing"}
    dropped: set[tuple[int | str, ...]] = set()
    out: list[tuple[tuple[int | str, ...], str]] = []
    for loc, kind, _msg in errs:
        if kind != "extra_forbidden":
            continue
        parent, key = loc[:-1], str(loc[-1])
        sib_missing = [str(m[-1]) for m in missing if m[:-1] == parent and m not in dropped]
        guess = difflib.get_close_matches(key, sib_missing, n=1, cutoff=0.6)
        if guess:
            dropped.add((*parent, guess[0]))
        else:
            owner = _model_at(model, parent)
            names = list(owner.model_fields) if owner is not None else []
            guess = difflib.get_close_matches(key, names, n=1, cutoff=0.6)
        hint = f" (did you mean {guess[0]}?)" if guess else ""
        out.append((loc, f"unknown key{hint}"))
    for loc, kind, msg in errs:
        if kind == "extra_forbidden" or loc in dropped:
            continue
        out.append((loc, msg))
    return out


def parse_yaml_model(path: Path, model: type[StrictModel]) -> Any:
    """Load YAML at ``path`` strictly and validate it with ``model``.

    Strict means: a regular UTF-8 file of at most :data:`MAX_CONFIG_BYTES`; no duplicate keys;
    nesting and alias expansion bounded; no NaN / infinity; no ``true`` where a number belongs
    (pydantic strict mode); unknown keys refused with a did-you-mean.

    Raises
    ------
    ConfigError
        One line ``path:line: field.path: reason`` per problem found (all of them).
    """
    text = read_config_text(path)
    root, data = _load_yaml(path, text)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    problems: list[tuple[tuple[int | str, ...], str]] = [
        (loc, "must be a finite number (no .inf / .nan)") for loc in _non_finite(data)
    ]
    result: Any = None
    try:
        result = model.model_validate(data, strict=True)
    except ValidationError as exc:
        bad = {loc for loc, _ in problems}
        problems += [(loc, msg) for loc, msg in _problems(exc, model) if loc not in bad]
    if not problems:
        return result
    lines = []
    for loc, msg in problems:
        field = ".".join(str(p) for p in loc) or "(top level)"
        line = _yaml_line(root, loc)
        where = f"{path}:{line}" if line is not None else str(path)
        lines.append(f"{where}: {field}: {_one_line(msg)}")
    raise ConfigError("\n".join(lines))


def load_config(path: str | Path) -> ScannerConfig:
    """Load and validate one scanner YAML file.

    Parameters
    ----------
    path
        The YAML file.

    Returns
    -------
    ScannerConfig
        The validated, frozen configuration.
    """
    cfg: ScannerConfig = parse_yaml_model(Path(path), ScannerConfig)
    return cfg


def dump_config(cfg: ScannerConfig, path: str | Path, header: str | None = None) -> None:
    """Write ``cfg`` as YAML (round-trips through :func:`load_config`), atomically.

    The text goes to a temporary file beside ``path``, is fsynced and renamed over ``path``:
    on any failure (a full disk) ``path`` keeps its previous content and the temporary file
    is removed.

    Raises
    ------
    ConfigError
        ``path: cannot write: reason`` (the original untouched).
    """
    data = cfg.model_dump(mode="json", exclude_none=True)
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    atomic_write_text(Path(path), text)


def atomic_write_text(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` atomically (temp file + fsync + rename + directory fsync).

    An existing file's permission bits are kept.

    Raises
    ------
    ConfigError
        ``path: cannot write: reason``; ``path`` is unchanged.
    """
    directory = path.parent if str(path.parent) else Path(".")
    tmp: str | None = None
    try:
        try:
            mode: int | None = stat.S_IMODE(os.stat(path).st_mode)
        except FileNotFoundError:
            mode = None
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
        with os.fdopen(fd, "wb") as fh:
            fh.write(text.encode("utf-8"))
            fh.flush()
            os.fsync(fh.fileno())
            if mode is not None:
                os.fchmod(fh.fileno(), mode)
        os.replace(tmp, path)
        tmp = None
        dfd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write: {exc.strerror or exc} (the file is unchanged)") from exc
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def config_dir() -> Path:
    """The directory holding the shipped scanner configs (``configs/`` of the checkout)."""
    here = Path(__file__).resolve().parent
    for candidate in (here.parent / "configs", here / "data" / "configs"):
        if candidate.is_dir():
            return candidate
    raise ConfigError("cannot find the shipped configs directory")


def default_sim_config_path() -> Path:
    """``configs/sim-stage.yaml``: the simulated stage (``simulation:``) with an uncalibrated host model."""
    return config_dir() / "sim-stage.yaml"


def default_sim_scan_config_path() -> Path:
    """``configs/sim-stage-calibrated.yaml``: the simulated stage with its shipped calibration.

    ``scan --sim`` and ``serve --sim`` use it by default, so that a corrected scan on the
    built-in stage is corrected by a calibrated model; ``calibrate --sim`` starts from
    :func:`default_sim_config_path` (the first guess).
    """
    return config_dir() / "sim-stage-calibrated.yaml"


def calibrated_notes(notes: list[str]) -> list[str]:
    """A base config's notes for its calibrated copy: those saying it is uncalibrated dropped."""
    return [n for n in notes if "uncalibrated" not in n.lower()]


def calibrated_axes(config: ScannerConfig) -> frozenset[str]:
    """The axes whose model the ``calibration:`` provenance covers.

    ``piezod calibrate`` writes ``axis:`` (and ``dynamic: {axis: ...}``); a per-axis entry
    (``calibration: {y: {...}}``) covers that axis; ``source:`` (parameters taken from a
    publication, e.g. the thesis's tables) covers every axis.
    """
    cal = config.calibration or {}
    if "source" in cal:
        return frozenset(config.axes)
    found = {str(cal["axis"])} if "axis" in cal else set()
    dyn = cal.get("dynamic")
    if isinstance(dyn, dict) and "axis" in dyn:
        found.add(str(dyn["axis"]))
    found.update(k for k in cal if k in config.axes)
    return frozenset(found & set(config.axes))


def with_recorded_utc(config: ScannerConfig, unix_s: float) -> ScannerConfig:
    """``config`` with ``calibration.recorded_utc``: when the data its model was fitted on were
    measured (the middle of the calibration frame; the sensitivity tracker's starting
    uncertainty grows with the time since, :class:`piezod.service.tracking.SensitivityTracker`)."""
    stamp = _dt.datetime.fromtimestamp(unix_s, _dt.UTC).isoformat(timespec="seconds")
    return config.model_copy(update={"calibration": {**(config.calibration or {}), "recorded_utc": stamp}})


def recorded_age_s(config: ScannerConfig, now_unix_s: float) -> float | None:
    """Seconds from ``calibration.recorded_utc`` to ``now_unix_s``; ``None`` when the config does
    not say when its data were measured.

    Raises
    ------
    ConfigError
        ``recorded_utc`` is not an ISO 8601 time (names the field).
    """
    stamp = (config.calibration or {}).get("recorded_utc")
    if stamp is None:
        return None
    try:
        when = _dt.datetime.fromisoformat(str(stamp))
    except ValueError as exc:
        raise ConfigError(
            f"scanner {config.name!r}: calibration.recorded_utc {stamp!r} is not an ISO 8601 time"
        ) from exc
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.UTC)
    return max(0.0, now_unix_s - when.timestamp())


def uncalibrated_warning(
    config: ScannerConfig,
    path: str | os.PathLike[str] | None = None,
    axes: Iterable[str] | None = None,
) -> str | None:
    """A one-line warning when an axis of ``axes`` (default: all) has an uncalibrated model, else None.

    A config without ``calibration:`` provenance for an axis holds a first guess of its model
    (e.g. ``configs/sim-stage.yaml``): a corrected scan with it is not linear.
    ``piezod calibrate`` writes the provenance.
    """
    wanted = [a for a in (config.axes if axes is None else axes) if a in config.axes]
    missing = [a for a in wanted if a not in calibrated_axes(config)]
    if not missing:
        return None
    where = f"{os.fspath(path)}: " if path is not None else ""
    which = "axis " + missing[0] if len(missing) == 1 else "axes " + ", ".join(missing)
    return (
        f"{where}scanner {config.name!r}, {which}: uncalibrated model (no calibration provenance), "
        "a first guess: corrected scans will not be linear; run piezod calibrate"
    )


def json_schema() -> str:
    """JSON schema of the scanner YAML, for editors."""
    return json.dumps(ScannerConfig.model_json_schema(), indent=2)
