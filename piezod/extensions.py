"""The audit's findings into the scanner's model: ``piezod audit ... --out F.yaml`` and calibrate's adoption.

The audit (:mod:`piezod.audit`) names effects with their parameters in the names of the effect
registry (:mod:`piezod.model.registry`). Those with a runtime part (:mod:`piezod.model.parts`:
polarity, thermal, stiffness, saturation, drift) go into the axis's ``extensions:`` section, which
the daemon's inverse applies; a ``delay`` goes there as the axis's sensor path
(:mod:`piezod.model.sensor`: the readback's delay and lag, which the analysis undoes, the drive
unchanged); the others are reported as not (yet) correctable at run time, with
the reason. The written YAML says in a comment which finding became which parameter.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from piezod.config import ScannerConfig, dump_config, load_config
from piezod.errors import ConfigError, ModelError
from piezod.model.parts import PART_EFFECTS, Parts
from piezod.model.sensor import SENSOR_EFFECTS, SensorPath
from piezod.recording import Experiment

#: Why a registry effect has no runtime part.
NO_PART_REASON: dict[str, str] = {
    "resonance": "no runtime part (the scan's turning points ring; lower the line rate)",
    "creep": "the creep spectrum is the calibration's (piezod calibrate fits it)",
    "asymmetry": "no runtime part yet",
}


@dataclass(frozen=True)
class Adoption:
    """What of the findings reaches the scanner.

    Attributes
    ----------
    effects
        ``{effect id: {parameter: value}}`` for the ``extensions:`` section.
    skipped
        One line per finding left out, with the reason.
    """

    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    skipped: tuple[str, ...] = ()

    @property
    def adopted(self) -> tuple[str, ...]:
        """One line per adopted finding (``stiffness: sensitivity_pct_per_um = -0.16``)."""
        lines = []
        for effect, values in self.effects.items():
            line = f"{effect}: " + ", ".join(f"{k} = {v:.6g}" for k, v in values.items())
            if effect in SENSOR_EFFECTS:
                line += " (sensor path: the readback is aligned, the drive unchanged)"
            lines.append(line)
        return tuple(lines)

    def summary(self) -> str:
        """Human-readable, one line per finding."""
        lines = [f"adopted {a}" for a in self.adopted] + [f"not adopted {s}" for s in self.skipped]
        return "\n".join(lines) if lines else "no material finding: the model is kept as it is"


def adopt_findings(findings: Sequence[Mapping[str, Any]]) -> Adoption:
    """Map the audit's findings (``result_json(...)["findings"]``) to runtime parts.

    Parameters
    ----------
    findings
        Each with ``effect`` and ``params`` (registry names, public units).
    """
    effects: dict[str, dict[str, float]] = {}
    skipped: list[str] = []
    for f in findings:
        effect = str(f["effect"])
        params = {str(k): v for k, v in dict(f.get("params") or {}).items()}
        if effect in SENSOR_EFFECTS:
            names = SENSOR_EFFECTS[effect]
            vals = {n: float(params.get(n) or 0.0) for n in names}
            try:
                SensorPath.from_effects({effect: vals})
            except ModelError as exc:
                skipped.append(f"{effect}: {exc}")
                continue
            effects[effect] = vals
            continue
        if effect not in PART_EFFECTS:
            skipped.append(f"{effect}: {NO_PART_REASON.get(effect, 'no runtime part')}")
            continue
        values: dict[str, float] = {}
        for name in PART_EFFECTS[effect]:
            value = params.get(name)
            if value is None or not math.isfinite(float(value)):
                break
            values[name] = float(value)
        else:
            try:
                Parts.from_effects({**effects, effect: values})
            except ModelError as exc:
                skipped.append(f"{effect}: {exc}")
                continue
            effects[effect] = values
            continue
        skipped.append(f"{effect}: no finite value for {', '.join(PART_EFFECTS[effect])}")
    return Adoption(effects, tuple(skipped))


def extended_config(config: ScannerConfig, axis: str, adoption: Adoption) -> ScannerConfig:
    """``config`` whose ``axis`` carries the adopted parts (merged over the parts it has)."""
    if axis not in config.axes:
        raise ConfigError(f"the scanner config has no axis {axis!r} (axes: {', '.join(config.axes)})")
    name = next(a for a in config.axes if a == axis)
    ax = config.axes[name]
    merged: dict[str, dict[str, float]] = {str(k): v for k, v in (ax.extensions or {}).items()}
    merged.update(adoption.effects)
    new_ax = ax.model_validate({**ax.model_dump(), "extensions": merged})
    axes = dict(config.axes)
    axes[name] = new_ax
    return config.model_copy(update={"axes": axes})


def experiments_through_parts(experiments: Sequence[Experiment], parts: Parts) -> list[Experiment]:
    """The experiments as the model inside the parts sees them: voltages and positions through the
    parts' exact inverse (times from the recording: the stage's clock)."""
    return [
        dataclasses.replace(
            e,
            voltage_v=parts.voltage_in(np.asarray(e.voltage_v, dtype=np.float64)),
            position_um=parts.position_in(np.asarray(e.position_um, dtype=np.float64), np.asarray(e.t_s)),
        )
        for e in experiments
    ]


def experiments_through_sensor(experiments: Sequence[Experiment], path: SensorPath) -> list[Experiment]:
    """The experiments with the stage's position in place of the readback (:meth:`SensorPath.align`;
    the rows whose ``t + d`` is past an experiment's end are dropped)."""
    if path.identity:
        return list(experiments)
    out = []
    for e in experiments:
        t, x = path.align(np.asarray(e.t_s, dtype=np.float64), np.asarray(e.position_um, dtype=np.float64))
        n = t.size
        if n < 2:
            raise ModelError(f"experiment {e.describe()}: shorter than the sensor delay {path.delay_s:g} s")
        out.append(
            dataclasses.replace(
                e,
                t_s=t,
                voltage_v=np.asarray(e.voltage_v, dtype=np.float64)[:n],
                position_um=x,
                target_um=None if e.target_um is None else e.target_um[:n],
                line_numbers=None if e.line_numbers is None else e.line_numbers[:n],
            )
        )
    return out


def experiments_through(
    experiments: Sequence[Experiment], effects: Mapping[str, Mapping[str, float]]
) -> list[Experiment]:
    """The experiments as the model inside the adopted ``effects`` sees them: the readback aligned
    through the sensor path (the last link of the chain), then through the parts' exact inverse."""
    aligned = experiments_through_sensor(experiments, SensorPath.from_effects(effects))
    return experiments_through_parts(
        aligned, Parts.from_effects({k: v for k, v in effects.items() if k in PART_EFFECTS})
    )


def write_extended_config(
    base: str | Path, axis: str, findings: Sequence[Mapping[str, Any]], out: str | Path, source: str
) -> Adoption:
    """Write ``base`` with the findings' runtime parts on ``axis`` to ``out`` (a comment says which).

    Parameters
    ----------
    base
        The scanner YAML the recordings were taken with.
    axis
        The audited axis.
    findings
        The audit's findings (``result_json(...)["findings"]``).
    out
        The extended scanner YAML (written atomically; loads with ``piezod serve``/``scan``).
    source
        What the findings come from (named in the comment).
    """
    config = load_config(base)
    adoption = adopt_findings(findings)
    extended = extended_config(config, axis, adoption)
    header = "\n".join(
        [
            f"Extended by {source}: the audit's material findings on axis {axis} as runtime parts",
            "(axes.<axis>.extensions, piezod.model.parts; parameter names of piezod.model.registry).",
            *adoption.summary().splitlines(),
            f"Base: {Path(base).name}",
        ]
    )
    dump_config(extended, out, header=header)
    load_config(out)
    return adoption


__all__ = [
    "NO_PART_REASON",
    "Adoption",
    "adopt_findings",
    "experiments_through",
    "experiments_through_parts",
    "experiments_through_sensor",
    "extended_config",
    "write_extended_config",
]
