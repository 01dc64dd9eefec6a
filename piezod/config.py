"""Scanner configuration: one YAML file per scanner, validated by pydantic.

Every field carries its unit in its name. Unknown keys are rejected, and a bad
value is reported as ``FILE:LINE: field.path: reason``. ``piezod`` ships the
thesis scanners and the simulated stage in ``configs/``; :func:`config_dir`
finds them from a source checkout.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from piezod.errors import ConfigError
from piezod.model.dynamic import DynamicParams
from piezod.model.params import ThesisParams

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


class AxisConfig(StrictModel):
    """One scanner axis: its voltage limits, safety settings and model."""

    voltage_min_v: float = Field(ge=-2000, le=2000, description="lowest voltage ever applied (V)")
    voltage_max_v: float = Field(ge=-2000, le=2000, description="highest voltage ever applied (V)")
    safe_voltage_v: float = Field(default=0.0, description="voltage ramped to on stop / fault (V)")
    slew_rate_v_per_s: float = Field(
        default=2000.0, gt=0, description="largest |dV/dt| the host commands (V/s)"
    )
    model: Literal["thesis", "dynamic"] = "thesis"
    thesis: ThesisModelConfig
    dynamic: DynamicModelConfig | None = Field(
        default=None, description="time-domain model parameters (required by model: dynamic)"
    )

    @model_validator(mode="after")
    def _check_limits(self) -> AxisConfig:
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

    @model_validator(mode="after")
    def _check_axes(self) -> ScannerConfig:
        if "x" not in self.axes:
            raise ValueError("axes must contain at least the fast axis 'x'")
        return self


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


def parse_yaml_model(path: Path, model: type[StrictModel]) -> Any:
    """Load YAML at ``path`` and validate it with ``model``.

    Raises
    ------
    ConfigError
        With ``path:line: field.path: reason`` for the first problem found.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{where}: invalid YAML: {problem}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        field = ".".join(str(p) for p in loc) or "(top level)"
        line = _yaml_line(root, loc)
        where = f"{path}:{line}" if line is not None else str(path)
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise ConfigError(f"{where}: {field}: {msg}{more}") from exc


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
    """Write ``cfg`` as YAML (round-trips through :func:`load_config`)."""
    data = cfg.model_dump(mode="json", exclude_none=True)
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    Path(path).write_text(text, encoding="utf-8")


def config_dir() -> Path:
    """The directory holding the shipped scanner configs (``configs/`` of the checkout)."""
    here = Path(__file__).resolve().parent
    for candidate in (here.parent / "configs", here / "data" / "configs"):
        if candidate.is_dir():
            return candidate
    raise ConfigError("cannot find the shipped configs directory")


def default_sim_config_path() -> Path:
    """``configs/sim-stage.yaml``, the simulated stage used by ``--sim``."""
    return config_dir() / "sim-stage.yaml"


def json_schema() -> str:
    """JSON schema of the scanner YAML, for editors."""
    return json.dumps(ScannerConfig.model_json_schema(), indent=2)
