"""The simulated piezo stage: a forward time-domain model per axis, state carried across blocks.

Per channel (axis) and block, in this order:

1. ``delay`` at the drive (if configured so): first-order lag and pure delay of the voltage.
2. ``polarity``: the ceramic sees ``V (1 + p / 100)`` for ``V < 0``.
3. ``asymmetry_pct``: static curvature, the ceramic sees ``V + c V^2``.
   Hysteresis: the axis's law (:mod:`hil_sim.hysteresis`): the exact step of the
   Coleman-Hodgdon ODE (2.21) (the controller's default law: self-consistency) or a
   Prandtl-Ishlinskii sum of play operators whose minor loops close (other physics).
4. Creep: ``x = x_h + sum_i w_i z_i``, a bank of first-order relaxations with log-spaced time
   constants (:mod:`hil_sim.creep`) driven by the hysteretic position ``x_h`` (default) or by
   ``b V``, with equal weights (log creep) or weights ``~ tau^beta`` (power-law creep,
   ``creep.spectrum_exponent``). The hysteresis is the fast response (faster than
   ``tau_min``); the creep adds ``gamma`` of it per decade of time on top, as thesis chapter 3
   superimposes creep on (2.24).
   Driving by the position follows the cascade "hysteresis, then linear viscoelastic creep" of
   Croft, Shed and Devasia (2001): the slow domain relaxation follows the strain set by the
   (hysteretic) polarisation, so creep is a fraction of the *motion*, as the empirical log law
   states. ``drive: voltage`` makes the creep term exactly linear in ``V`` (the thesis's
   assumption behind (3.3)).
5. ``thermal``: the displacement is scaled by the slowly changing sensitivity.
6. ``stiffness``: ``x + k x^2 / 200``.
7. ``saturation``: ``x_sat tanh(x / x_sat)``.
8. ``resonance``: exact second-order mechanical filter.
9. ``drift``: ``+ rate t``.
10. ``delay`` at the sensor (default): first-order lag and pure delay of the position.

The result is the position the sensor sees, before sensor noise and ADC quantisation
(:meth:`Stage.sense` / :func:`sensor` add those). ``t`` counts from the last reset. Positions
are in um relative to the rest position at 0 V.

The true hysteresis parameters satisfy ``b / 2 < u < b``: with the ODE, ``b > 2 u`` makes the
start of every branch after a reversal at large ranges run backwards (``dx/dV = 2u - b < 0``),
which a real piezo does not do; the thesis's own medium-tube fit (``b = 0.081``,
``u = 0.016``) violates it, so the simulated stage uses different, monotone parameters.

A little over 800 lines because the stage's per-block pipeline (drive effects, hysteresis,
creep, output effects, sensor) and its configuration (validated from the scanner YAML's
``simulation:`` section, with line numbers) change together; the laws themselves live in
:mod:`hil_sim.hysteresis`, :mod:`hil_sim.creep` and :mod:`hil_sim.effects`.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hil_sim.creep import CreepBank, CreepState, creep_rest_state, creep_step, lowpass_block
from hil_sim.effects import (
    CreepLawOverride,
    DelayEffect,
    DelayState,
    DriftEffect,
    EffectConfig,
    PolarityEffect,
    ResonanceEffect,
    ResonanceState,
    SaturationEffect,
    StiffnessEffect,
    ThermalEffect,
    build_effect,
    delay_rest_state,
    delay_step,
    parse_effect_spec,
    resonance_rest_state,
    resonance_step,
)
from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.errors import SimModelError as ModelError
from hil_sim.hysteresis import (
    BoucWenParams,
    BoucWenState,
    CHParams,
    CHState,
    PIParams,
    PIState,
    PreisachParams,
    PreisachState,
    boucwen_rest_state,
    boucwen_step,
    ch_rest_state,
    ch_step,
    pi_rest_state,
    pi_step,
    preisach_position,
    preisach_rest_state,
    preisach_step,
)

#: Axis names of a scanner.
AxisName = Literal["x", "y", "z"]
#: Hysteresis laws of an axis.
HysteresisLaw = Literal["coleman-hodgdon", "prandtl-ishlinskii", "preisach", "bouc-wen"]
HysteresisParams = CHParams | PIParams | PreisachParams | BoucWenParams
HysteresisState = CHState | PIState | PreisachState | BoucWenState


class ScannerLike(Protocol):
    """What :meth:`StageConfig.from_scanner` reads of a scanner configuration object."""

    @property
    def name(self) -> str: ...

    @property
    def axes(self) -> Mapping[Any, Any]: ...

    @property
    def simulation(self) -> Mapping[str, Any] | None: ...


def _yaml_line(root: yaml.Node | None, loc: Sequence[int | str]) -> int | None:
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


# ---------------------------------------------------------------------------------------------
# Configuration (the ``simulation:`` section of a scanner YAML)


class _SimModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StageAxisConfig(_SimModel):
    """True physics of one axis of the simulated stage.

    ``law: coleman-hodgdon`` (default) needs ``alpha_per_v`` and ``u_um_per_v``;
    ``law: prandtl-ishlinskii`` needs ``pi_rho0`` and ``pi_span_v`` (see
    :meth:`hil_sim.hysteresis.PIParams.from_shape`). ``asymmetry_pct`` bends the static curve
    asymmetrically: the ceramic sees ``V + (a / 100) V^2 / (2 V_r)``, so the local sensitivity is
    ``1 + a / 100`` times nominal at ``+V_r`` and ``1 - a / 100`` at ``-V_r``.
    """

    law: HysteresisLaw = Field(default="coleman-hodgdon", description="hysteresis law")
    b_um_per_v: float = Field(gt=0, lt=100.0, description="sensitivity b (um/V)")
    alpha_per_v: float | None = Field(
        default=None, gt=0, lt=1.0, description="coleman-hodgdon: transition rate alpha (1/V)"
    )
    u_um_per_v: float | None = Field(
        default=None, gt=0, lt=100.0, description="coleman-hodgdon: slope after a reversal u (um/V)"
    )
    pi_rho0: float | None = Field(
        default=None, gt=0, le=1.0, description="prandtl-ishlinskii, preisach: slope after a reversal / b"
    )
    pi_span_v: float | None = Field(
        default=None, gt=0, le=1e4, description="prandtl-ishlinskii: voltage change engaging every play (V)"
    )
    pi_operators: int = Field(default=16, ge=1, le=256, description="prandtl-ishlinskii: play operators")
    pi_decay_v: float | None = Field(
        default=None, gt=0, le=1e5, description="prandtl-ishlinskii: decay of the weights (V); none = uniform"
    )
    preisach_width_v: float | None = Field(
        default=None,
        gt=0,
        le=1e4,
        description="preisach: decay of the relay density over the relay width (V)",
    )
    preisach_asymmetry: float = Field(
        default=0.0, gt=-0.5, lt=0.5, description="preisach: centre dependence of the relay density"
    )
    preisach_saturation_v: float = Field(
        default=300.0, gt=0, le=1e4, description="preisach: voltage beyond which no relay switches (V)"
    )
    bw_a: float | None = Field(default=None, gt=0, lt=1.0, description="bouc-wen: A (fraction of dV into h)")
    bw_beta_per_v: float | None = Field(default=None, gt=0, lt=1.0, description="bouc-wen: beta (1/V^n)")
    bw_gamma_per_v: float = Field(default=0.0, gt=-1.0, lt=1.0, description="bouc-wen: gamma (1/V^n)")
    bw_exponent: Literal[1, 2] = Field(default=1, description="bouc-wen: exponent n")
    creep_pct_per_decade: float = Field(
        default=1.5, ge=0, le=20, description="creep per decade of time (% of the motion)"
    )
    asymmetry_pct: float = Field(
        default=0.0, ge=-20, le=20, description="static curvature: sensitivity change at +V_r (%)"
    )
    asymmetry_range_v: float = Field(default=230.0, gt=0, le=1e4, description="V_r of asymmetry_pct (V)")

    @model_validator(mode="after")
    def _law_fields(self) -> StageAxisConfig:
        if self.law == "coleman-hodgdon":
            if self.alpha_per_v is None or self.u_um_per_v is None:
                raise ValueError("law coleman-hodgdon needs alpha_per_v and u_um_per_v")
            if not self.u_um_per_v < self.b_um_per_v:
                raise ValueError(
                    f"u_um_per_v ({self.u_um_per_v}) must be below b_um_per_v ({self.b_um_per_v})"
                )
            if not self.u_um_per_v > 0.5 * self.b_um_per_v:
                raise ValueError(
                    f"u_um_per_v ({self.u_um_per_v}) must exceed b_um_per_v / 2 ({0.5 * self.b_um_per_v:g}):"
                    " otherwise branches run backwards after a reversal (dx/dV = 2u - b < 0)"
                )
        elif self.law == "preisach":
            if self.pi_rho0 is None or self.preisach_width_v is None:
                raise ValueError("law preisach needs pi_rho0 and preisach_width_v")
        elif self.law == "bouc-wen":
            if self.bw_a is None or self.bw_beta_per_v is None:
                raise ValueError("law bouc-wen needs bw_a and bw_beta_per_v")
            if not self.bw_beta_per_v > abs(self.bw_gamma_per_v):
                raise ValueError("law bouc-wen needs bw_beta_per_v > |bw_gamma_per_v|")
            if not 2.0 * self.bw_a * self.bw_beta_per_v / (self.bw_beta_per_v + self.bw_gamma_per_v) < 1.0:
                raise ValueError(
                    "law bouc-wen needs 2 bw_a beta / (beta + gamma) < 1 (else branches run backwards)"
                )
        elif self.pi_rho0 is None or self.pi_span_v is None:
            raise ValueError("law prandtl-ishlinskii needs pi_rho0 and pi_span_v")
        return self

    @property
    def hysteresis(self) -> HysteresisParams:
        """The hysteresis law's frozen parameters."""
        if self.law == "coleman-hodgdon":
            assert self.alpha_per_v is not None and self.u_um_per_v is not None
            return CHParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
        if self.law == "preisach":
            assert self.pi_rho0 is not None and self.preisach_width_v is not None
            return PreisachParams(
                self.b_um_per_v,
                self.pi_rho0,
                self.preisach_width_v,
                self.preisach_asymmetry,
                self.preisach_saturation_v,
            )
        if self.law == "bouc-wen":
            assert self.bw_a is not None and self.bw_beta_per_v is not None
            return BoucWenParams(
                self.b_um_per_v, self.bw_a, self.bw_beta_per_v, self.bw_gamma_per_v, self.bw_exponent
            )
        assert self.pi_rho0 is not None and self.pi_span_v is not None
        return PIParams.from_shape(
            self.b_um_per_v, self.pi_rho0, self.pi_span_v, self.pi_operators, self.pi_decay_v
        )


class CreepConfig(_SimModel):
    """Relaxation times of the creep bank (shared by all axes)."""

    tau_min_s: float = Field(default=1e-3, gt=0, le=1e3, description="shortest relaxation time (s)")
    tau_max_s: float = Field(default=1e5, gt=0, le=1e9, description="longest relaxation time (s)")
    per_decade: int = Field(default=3, ge=1, le=20, description="relaxation times per decade")
    drive: Literal["position", "voltage"] = Field(
        default="position", description="what creeps: the hysteretic position or b V"
    )
    spectrum_exponent: float = Field(
        default=0.0,
        ge=-0.5,
        le=0.5,
        description="weights proportional to tau^beta (power-law creep); 0 = logarithmic creep",
    )

    @model_validator(mode="after")
    def _span(self) -> CreepConfig:
        if not self.tau_max_s > self.tau_min_s:
            raise ValueError(f"tau_max_s ({self.tau_max_s}) must exceed tau_min_s ({self.tau_min_s})")
        return self


class EffectsConfig(_SimModel):
    """The optional effects, each off unless given."""

    drift: DriftEffect | None = None
    thermal: ThermalEffect | None = None
    stiffness: StiffnessEffect | None = None
    polarity: PolarityEffect | None = None
    resonance: ResonanceEffect | None = None
    delay: DelayEffect | None = None
    saturation: SaturationEffect | None = None

    def enabled(self) -> list[str]:
        """Ids of the configured effects."""
        return [name for name in type(self).model_fields if getattr(self, name) is not None]


class StageConfig(_SimModel):
    """The ``simulation:`` section of a scanner YAML: the true simulated stage.

    Examples
    --------
    >>> stage_cfg = StageConfig.from_file("configs/sim-stage.yaml")
    >>> stage_cfg = stage_cfg.with_effects("drift=0.4", "resonance=800", "resonance.q=20")
    """

    axes: dict[AxisName, StageAxisConfig]
    creep: CreepConfig = CreepConfig()
    effects: EffectsConfig = EffectsConfig()
    amplifier_lag_s: float = Field(
        default=0.0,
        ge=0,
        le=1.0,
        description="first-order pole of the HV amplifier at the drive (s); 0 = none",
    )
    sensor_noise_nm_rms: float = Field(default=0.0, ge=0, le=1e5, description="sensor noise (nm rms)")
    seed: int = Field(default=0, ge=0, description="seed of the sensor noise")

    @classmethod
    def from_scanner(cls, cfg: ScannerLike) -> StageConfig:
        """Validate ``cfg.simulation`` against the scanner's axes.

        Raises
        ------
        SimConfigError
            ``simulation.<field.path>: <reason>`` for the first problem, also when the section
            is missing or lacks an axis the scanner has.
        """
        return _validate_simulation(cfg.name, list(cfg.axes), cfg.simulation)

    @classmethod
    def from_file(cls, path: str | Path) -> StageConfig:
        """Load a scanner YAML and validate its ``simulation:`` section (nothing else of it).

        Raises
        ------
        SimConfigError
            ``FILE:LINE: simulation.<field.path>: <reason>``, or ``FILE: <reason>`` when the
            file cannot be read or is no YAML mapping.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
            data = yaml.safe_load(text)
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
            raise ConfigError(f"{where}: invalid YAML: {getattr(exc, 'problem', None) or exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
        axes = data.get("axes")
        if not isinstance(axes, dict) or not axes:
            raise ConfigError(f"{path}: axes: missing or not a mapping")
        try:
            return _validate_simulation(str(data.get("name", path.stem)), list(axes), data.get("simulation"))
        except _LocatedConfigError as exc:
            root = yaml.compose(text, Loader=yaml.SafeLoader)
            line = _yaml_line(root, exc.loc)
            raise ConfigError(f"{path}:{line}: {exc}") from exc

    def with_effects(self, *specs: str | EffectConfig) -> StageConfig:
        """A copy with effects set from ``NAME=VALUE`` / ``NAME.FIELD=VALUE`` strings or effect models.

        Strings for the same effect combine, starting from the effect already configured
        (``resonance.q=30`` alone changes Q of a configured resonance). ``creep=VALUE`` sets
        the creep percent per decade of every axis; ``creep.FIELD=VALUE`` the creep bank.

        Raises
        ------
        ConfigError
            Naming the string at fault.
        """
        effects = self.effects.model_dump()
        creep_fields: dict[str, Any] = {}
        pending: dict[str, dict[str, Any]] = {}
        sources: dict[str, str] = {}
        for spec in specs:
            if isinstance(spec, EffectConfig):
                if isinstance(spec, CreepLawOverride):
                    creep_fields.update(spec.model_dump(exclude_none=True))
                else:
                    pending[spec.name] = spec.model_dump()
                    sources[spec.name] = spec.name
                continue
            name, field, value = parse_effect_spec(spec)
            if name == CreepLawOverride.name:
                creep_fields[field] = build_effect(name, {field: value}, repr(spec)).model_dump()[field]
                continue
            if name not in pending:
                pending[name] = dict(effects.get(name) or {})
            pending[name][field] = value
            sources[name] = repr(spec)
        for name, fields in pending.items():
            effects[name] = build_effect(name, fields, sources[name]).model_dump()
        data = self.model_dump()
        data["effects"] = effects
        pct = creep_fields.pop("pct_per_decade", None)
        if pct is not None:
            for axis in data["axes"].values():
                axis["creep_pct_per_decade"] = pct
        data["creep"].update(creep_fields)
        try:
            return StageConfig.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            raise ConfigError(
                f"effects {list(map(str, specs))}: {_loc_text(err['loc'])}: {err['msg']}"
            ) from exc

    def without_effects(self) -> StageConfig:
        """A copy with every effect off."""
        return self.model_copy(update={"effects": EffectsConfig()})


def _loc_text(loc: Sequence[int | str]) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


class _LocatedConfigError(ConfigError):
    """ConfigError carrying the YAML location of the field at fault (for :meth:`StageConfig.from_file`)."""

    def __init__(self, message: str, loc: tuple[int | str, ...]) -> None:
        super().__init__(message)
        self.loc = loc


def _validate_simulation(name: str, scanner_axes: Sequence[str], section: Any) -> StageConfig:
    if section is None:
        raise _LocatedConfigError(
            f"scanner {name!r}: simulation: missing (the simulated stage needs the true physics)", ()
        )
    try:
        # simulation.microscope is the simulated microscope's (hil_sim.microscope), not the stage's
        stage = StageConfig.model_validate(
            {k: v for k, v in section.items() if k != "microscope"} if isinstance(section, dict) else section
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ("simulation", *err["loc"])
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise _LocatedConfigError(f"{_loc_text(loc)}: {msg}{more}", loc) from exc
    missing = [axis for axis in scanner_axes if axis not in stage.axes]
    if missing:
        raise _LocatedConfigError(
            f"simulation.axes: missing axis {missing[0]!r} (the scanner has axes {', '.join(scanner_axes)})",
            ("simulation", "axes"),
        )
    extra = [axis for axis in stage.axes if axis not in scanner_axes]
    if extra:
        raise _LocatedConfigError(
            f"simulation.axes.{extra[0]}: axis not in the scanner's axes ({', '.join(scanner_axes)})",
            ("simulation", "axes", extra[0]),
        )
    return stage


#: Directory of the preset stages (``configs/sim-<name>.yaml``).
PRESET_DIR = Path(__file__).resolve().parent.parent / "configs"


def preset_names() -> list[str]:
    """Names of the preset stages: ``NAME`` of every ``configs/sim-NAME.yaml``."""
    return sorted(p.stem.removeprefix("sim-") for p in PRESET_DIR.glob("sim-*.yaml"))


def resolve_stage(spec: str | Path | None) -> Path | None:
    """The scanner YAML of ``spec``: a preset name (``pi-stage``) or a path (returned as is).

    Raises
    ------
    SimConfigError
        ``spec`` looks like a name (no ``/``, no ``.yaml``) but no such preset exists.
    """
    if spec is None:
        return None
    text = str(spec)
    if "/" in text or text.endswith((".yaml", ".yml")) or Path(text).exists():
        return Path(text)
    path = PRESET_DIR / f"sim-{text}.yaml"
    if not path.is_file():
        raise ConfigError(f"--stage {text}: no such preset (one of {', '.join(preset_names())})")
    return path


# ---------------------------------------------------------------------------------------------
# The sensor


def sensor(
    position_um: ArrayLike,
    rng: np.random.Generator,
    noise_nm_rms: float,
    lsb_um: float | None = None,
) -> NDArray[np.float64]:
    """The sensor reading of ``position_um``: white Gaussian noise and optional quantisation.

    Parameters
    ----------
    position_um
        True (sensor-side) position (um).
    rng
        Random generator of the noise.
    noise_nm_rms
        Noise (nm rms), >= 0.
    lsb_um
        Quantisation step (um), or None for none (the board's ADC does it).
    """
    x = np.array(position_um, dtype=np.float64)
    if not noise_nm_rms >= 0.0:
        raise ModelError(f"noise_nm_rms must be >= 0, got {noise_nm_rms!r}")
    if noise_nm_rms > 0.0:
        x = x + rng.normal(0.0, noise_nm_rms * 1e-3, size=x.shape)
    if lsb_um is not None:
        if not lsb_um > 0.0:
            raise ModelError(f"lsb_um must be > 0, got {lsb_um!r}")
        x = np.round(x / lsb_um) * lsb_um
    return x


# ---------------------------------------------------------------------------------------------
# The model: frozen parameters, frozen state, a pure step function


@dataclass(frozen=True, slots=True, eq=False)
class StageModel:
    """Frozen, precomputed parameters of a stage for a set of axes.

    Attributes
    ----------
    axes
        Axis names, one per channel.
    hysteresis
        ODE parameters per channel.
    creep
        The creep bank (weights per channel).
    creep_drive
        ``"position"`` or ``"voltage"``.
    effects
        The configured effects.
    curvature_per_v
        ``c`` per channel of the static curvature ``V + c V^2`` at the ceramic (1/V); empty = none.
    """

    axes: tuple[AxisName, ...]
    hysteresis: tuple[HysteresisParams, ...]
    creep: CreepBank
    creep_drive: Literal["position", "voltage"]
    effects: EffectsConfig
    curvature_per_v: tuple[float, ...] = ()
    amplifier_lag_s: float = 0.0

    @classmethod
    def from_config(cls, config: StageConfig, axes: Sequence[AxisName] | None = None) -> StageModel:
        """Build the model for ``axes`` (default: all axes of ``config``, in its order)."""
        names: tuple[AxisName, ...] = tuple(config.axes) if axes is None else tuple(axes)
        if not names:
            raise ConfigError("a stage needs at least one axis")
        unknown = [a for a in names if a not in config.axes]
        if unknown:
            raise ConfigError(f"simulation.axes: no axis {unknown[0]!r} (have {', '.join(config.axes)})")
        ax = [config.axes[a] for a in names]
        bank = CreepBank.from_law(
            [a.creep_pct_per_decade for a in ax],
            config.creep.tau_min_s,
            config.creep.tau_max_s,
            config.creep.per_decade,
            config.creep.spectrum_exponent,
        )
        curvature = tuple(a.asymmetry_pct / 100.0 / (2.0 * a.asymmetry_range_v) for a in ax)
        return cls(
            axes=names,
            hysteresis=tuple(a.hysteresis for a in ax),
            creep=bank,
            creep_drive=config.creep.drive,
            effects=config.effects,
            curvature_per_v=curvature if any(curvature) else (),
            amplifier_lag_s=config.amplifier_lag_s,
        )

    @property
    def channels(self) -> int:
        """Number of channels."""
        return len(self.axes)

    @property
    def b_um_per_v(self) -> NDArray[np.float64]:
        """True ODE sensitivity per channel (um/V)."""
        return np.array([h.b_um_per_v for h in self.hysteresis])


@dataclass(frozen=True, slots=True, eq=False)
class StageState:
    """Complete state of a stage after a sample (a snapshot; arrays are copies).

    Attributes
    ----------
    time_s
        Time of the last sample since the reset (s).
    hysteresis
        ODE state per channel.
    creep
        Creep bank state.
    drive_lag, sensor_lag
        ``(output, input)`` of the first-order lag at the drive / sensor, or None.
    drive_delay, sensor_delay
        Delay-line history at the drive / sensor, or None.
    resonance
        Resonator state, or None.
    """

    time_s: float
    hysteresis: tuple[HysteresisState, ...]
    creep: CreepState
    drive_lag: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    drive_delay: DelayState | None
    resonance: ResonanceState | None
    sensor_lag: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    sensor_delay: DelayState | None
    amplifier: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None


def _static_chain(model: StageModel, x: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Steps 5-7: thermal, stiffness, saturation (memoryless)."""
    fx = model.effects
    if fx.thermal is not None:
        rate = fx.thermal.rate_pct_per_hour / 100.0 / 3600.0
        tau = fx.thermal.time_constant_s
        grown = t if tau is None else -tau * np.expm1(-t / tau)
        x = x * (1.0 + rate * grown)
    if fx.stiffness is not None:
        x = x + (fx.stiffness.sensitivity_pct_per_um / 200.0) * x * x
    if fx.saturation is not None:
        xs = fx.saturation.x_sat_um
        x = xs * np.tanh(x / xs)
    return x


def _polarity(model: StageModel, v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Polarity effect, then the axis's static curvature: the voltage the ceramic acts on."""
    if model.effects.polarity is not None:
        factor = 1.0 + model.effects.polarity.negative_sensitivity_pct / 100.0
        v = np.where(v < 0.0, v * factor, v)
    if model.curvature_per_v:
        c = np.asarray(model.curvature_per_v)[:, None]
        v = v + c * v * v
    return v


def _relaxed(params: HysteresisParams, voltage_v: float) -> HysteresisState:
    if isinstance(params, CHParams):
        return ch_rest_state(params, voltage_v)
    if isinstance(params, PreisachParams):
        return preisach_rest_state(params, voltage_v)
    if isinstance(params, BoucWenParams):
        return boucwen_rest_state(params, voltage_v)
    return pi_rest_state(params, voltage_v)


def _rest_position(params: HysteresisParams, voltage_v: float, state: HysteresisState) -> float:
    if isinstance(params, PreisachParams):
        assert isinstance(state, PreisachState)
        return preisach_position(params, voltage_v, state)
    return params.b_um_per_v * voltage_v


def _hysteresis_block(
    params: HysteresisParams, v: NDArray[np.float64], state: HysteresisState
) -> tuple[NDArray[np.float64], HysteresisState]:
    if isinstance(params, CHParams):
        assert isinstance(state, CHState)
        return ch_step(params, v, state)
    if isinstance(params, PreisachParams):
        assert isinstance(state, PreisachState)
        return preisach_step(params, v, state)
    if isinstance(params, BoucWenParams):
        assert isinstance(state, BoucWenState)
        return boucwen_step(params, v, state)
    assert isinstance(state, PIState)
    return pi_step(params, v, state)


def rest_state(model: StageModel, voltage_v: ArrayLike = 0.0) -> StageState:
    """The state of a stage that has rested at ``voltage_v`` (per channel) for ever, at ``t = 0``.

    The creep has fully relaxed, so the rest position is ``b V (1 + sum w)`` (plus effects).
    """
    v0 = np.broadcast_to(np.asarray(voltage_v, dtype=np.float64), (model.channels,)).astype(np.float64)
    fx = model.effects
    v_eff = _polarity(model, v0[:, None])[:, 0]
    hyst = tuple(_relaxed(p, float(v)) for p, v in zip(model.hysteresis, v_eff, strict=True))
    x_h = np.array(
        [_rest_position(p, float(v), s) for p, v, s in zip(model.hysteresis, v_eff, hyst, strict=True)]
    )
    drive = x_h if model.creep_drive == "position" else model.b_um_per_v * v_eff
    creep = creep_rest_state(model.creep, drive)
    x = x_h + model.creep.total_weight * drive
    x = _static_chain(model, x[:, None], np.zeros(1))[:, 0]
    delay = fx.delay
    at_drive = delay is not None and delay.at == "drive"
    at_sensor = delay is not None and delay.at == "sensor"
    return StageState(
        time_s=0.0,
        hysteresis=hyst,
        creep=creep,
        drive_lag=(v0.copy(), v0.copy()) if at_drive else None,
        drive_delay=delay_rest_state(v0, 0.0, delay.delay_s) if delay is not None and at_drive else None,
        resonance=resonance_rest_state(x) if fx.resonance is not None else None,
        sensor_lag=(x.copy(), x.copy()) if at_sensor else None,
        sensor_delay=delay_rest_state(x, 0.0, delay.delay_s) if delay is not None and at_sensor else None,
        amplifier=(v0.copy(), v0.copy()) if model.amplifier_lag_s > 0.0 else None,
    )


def _lag_and_delay(
    effect: DelayEffect,
    x: NDArray[np.float64],
    t: NDArray[np.float64],
    dt_s: float,
    lag: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    line: DelayState | None,
) -> tuple[NDArray[np.float64], tuple[NDArray[np.float64], NDArray[np.float64]] | None, DelayState | None]:
    if lag is not None and effect.lag_time_constant_s > 0.0:
        z_last, in_last = lag
        y = lowpass_block(effect.lag_time_constant_s, x, dt_s, z_last, in_last)
        lag = (y[:, -1].copy(), x[:, -1].copy())
        x = y
    elif lag is not None:
        lag = (x[:, -1].copy(), x[:, -1].copy())
    if line is not None and effect.delay_s > 0.0:
        x, line = delay_step(effect.delay_s, x, t, line)
    return x, lag, line


def stage_step(
    model: StageModel, voltage_v: ArrayLike, dt_s: float, state: StageState
) -> tuple[NDArray[np.float64], StageState]:
    """Advance the stage through a block of voltage samples (pure function).

    Parameters
    ----------
    model
        The stage parameters.
    voltage_v
        Voltage at the ceramic (V), shape ``(channels, n)``; the first sample is ``dt_s`` after
        the state's last one, and the voltage is taken as linear between samples.
    dt_s
        Sample interval (s), > 0; may change between blocks.
    state
        State before the block.

    Returns
    -------
    position_um : ndarray
        Position the sensor sees (before its noise), shape ``(channels, n)`` (um).
    state : StageState
        State after the block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 2 or v.shape[0] != model.channels:
        raise ModelError(f"voltage_v must have shape ({model.channels}, n), got {v.shape}")
    if not (np.isfinite(dt_s) and dt_s > 0.0):
        raise ModelError(f"dt_s must be finite and > 0, got {dt_s!r}")
    if not np.all(np.isfinite(v)):
        raise ModelError("voltage_v contains non-finite samples")
    n = v.shape[1]
    if n == 0:
        return np.empty_like(v), state
    fx = model.effects
    t = state.time_s + dt_s * np.arange(1, n + 1, dtype=np.float64)
    amplifier = state.amplifier
    if amplifier is not None:
        v_amp = lowpass_block(model.amplifier_lag_s, v, dt_s, amplifier[0], amplifier[1])
        amplifier = (v_amp[:, -1].copy(), v[:, -1].copy())
        v = v_amp
    drive_lag, drive_delay = state.drive_lag, state.drive_delay
    if fx.delay is not None and fx.delay.at == "drive":
        v, drive_lag, drive_delay = _lag_and_delay(fx.delay, v, t, dt_s, drive_lag, drive_delay)
    v = _polarity(model, v)
    x_h = np.empty_like(v)
    hyst = []
    for ch, params in enumerate(model.hysteresis):
        x_h[ch], h_state = _hysteresis_block(params, v[ch], state.hysteresis[ch])
        hyst.append(h_state)
    drive = x_h if model.creep_drive == "position" else model.b_um_per_v[:, None] * v
    creep, creep_state = creep_step(model.creep, drive, dt_s, state.creep)
    x = _static_chain(model, x_h + creep, t)
    res_state = state.resonance
    if fx.resonance is not None and res_state is not None:
        x, res_state = resonance_step(fx.resonance, x, dt_s, res_state)
    if fx.drift is not None:
        x = x + (fx.drift.rate_nm_per_s * 1e-3) * t
    sensor_lag, sensor_delay = state.sensor_lag, state.sensor_delay
    if fx.delay is not None and fx.delay.at == "sensor":
        x, sensor_lag, sensor_delay = _lag_and_delay(fx.delay, x, t, dt_s, sensor_lag, sensor_delay)
    new = StageState(
        time_s=float(t[-1]),
        hysteresis=tuple(hyst),
        creep=creep_state,
        drive_lag=drive_lag,
        drive_delay=drive_delay,
        resonance=res_state,
        sensor_lag=sensor_lag,
        sensor_delay=sensor_delay,
        amplifier=amplifier,
    )
    return x, new


# ---------------------------------------------------------------------------------------------
# The stateful wrapper the board calls once per block


class Stage:
    """A simulated piezo stage (all or some axes of a :class:`StageConfig`).

    Deterministic: the physics has no randomness, and the sensor noise of :meth:`sense` comes
    from a generator seeded with ``seed`` (default ``config.seed``), reseeded by :meth:`reset`.

    Parameters
    ----------
    config
        The true stage.
    axes
        The axes to simulate, one channel each (default: all, in config order).
    seed
        Seed of the sensor noise.
    rest_voltage_v
        Voltage (per channel) the stage has rested at before ``t = 0``.
    """

    def __init__(
        self,
        config: StageConfig,
        axes: Sequence[AxisName] | None = None,
        *,
        seed: int | None = None,
        rest_voltage_v: ArrayLike = 0.0,
    ) -> None:
        self._config = config
        self._model = StageModel.from_config(config, axes)
        self._seed = config.seed if seed is None else seed
        self._rest_voltage = np.broadcast_to(
            np.asarray(rest_voltage_v, dtype=np.float64), (self._model.channels,)
        ).copy()
        self._state = rest_state(self._model, self._rest_voltage)
        self._rng = np.random.default_rng(self._seed)

    @property
    def config(self) -> StageConfig:
        """The stage configuration."""
        return self._config

    @property
    def model(self) -> StageModel:
        """The frozen model parameters."""
        return self._model

    @property
    def axes(self) -> tuple[AxisName, ...]:
        """Axis of each channel."""
        return self._model.axes

    @property
    def channels(self) -> int:
        """Number of channels."""
        return self._model.channels

    @property
    def time_s(self) -> float:
        """Time of the last simulated sample since the reset (s)."""
        return self._state.time_s

    def reset(self, rest_voltage_v: ArrayLike | None = None) -> None:
        """Back to rest at ``t = 0`` (at ``rest_voltage_v``, default the constructor's); reseed the noise."""
        if rest_voltage_v is not None:
            self._rest_voltage = np.broadcast_to(
                np.asarray(rest_voltage_v, dtype=np.float64), (self.channels,)
            ).copy()
        self._state = rest_state(self._model, self._rest_voltage)
        self._rng = np.random.default_rng(self._seed)

    def step(self, voltage_v: ArrayLike | Mapping[str, ArrayLike], dt_s: float) -> NDArray[np.float64]:
        """Simulate a block.

        Parameters
        ----------
        voltage_v
            Voltage at the ceramic (V), shape ``(channels, n)``, or ``(n,)`` for a one-channel
            stage, or a mapping axis -> samples covering every channel.
        dt_s
            Sample interval (s).

        Returns
        -------
        ndarray
            Position the sensor sees (um), same shape as the input (``(channels, n)`` for a mapping).
        """
        if isinstance(voltage_v, Mapping):
            missing = [a for a in self.axes if a not in voltage_v]
            if missing:
                raise ModelError(f"voltage for axis {missing[0]!r} missing")
            v = np.stack([np.asarray(voltage_v[a], dtype=np.float64) for a in self.axes])
        else:
            v = np.asarray(voltage_v, dtype=np.float64)
        one_d = v.ndim == 1
        if one_d:
            if self.channels != 1:
                raise ModelError(
                    f"a {self.channels}-channel stage needs voltage_v of shape ({self.channels}, n)"
                )
            v = v[None, :]
        x, self._state = stage_step(self._model, v, dt_s, self._state)
        return x[0] if one_d else x

    def sense(self, position_um: ArrayLike, lsb_um: float | None = None) -> NDArray[np.float64]:
        """Sensor reading of ``position_um``: the configured noise from the stage's generator."""
        return sensor(position_um, self._rng, self._config.sensor_noise_nm_rms, lsb_um)

    def snapshot(self) -> StageSnapshot:
        """The complete state (physics and noise generator), for :meth:`restore`."""
        return StageSnapshot(state=self._state, rng_state=copy.deepcopy(dict(self._rng.bit_generator.state)))

    def restore(self, snapshot: StageSnapshot) -> None:
        """Return to a :meth:`snapshot` (the stage continues bit-for-bit as from there)."""
        if len(snapshot.state.hysteresis) != self.channels:
            raise ModelError(
                f"snapshot has {len(snapshot.state.hysteresis)} channels, the stage {self.channels}"
            )
        self._state = snapshot.state
        self._rng = np.random.default_rng()
        self._rng.bit_generator.state = copy.deepcopy(snapshot.rng_state)


@dataclass(frozen=True, slots=True, eq=False)
class StageSnapshot:
    """A :class:`Stage`'s complete state: the physics (never mutated in place) and the noise generator."""

    state: StageState
    rng_state: dict[str, Any]


__all__ = [
    "CreepConfig",
    "EffectsConfig",
    "Stage",
    "StageAxisConfig",
    "StageConfig",
    "StageModel",
    "StageSnapshot",
    "StageState",
    "preset_names",
    "resolve_stage",
    "rest_state",
    "sensor",
    "stage_step",
]
