"""The host's one entry point to the simulator (:mod:`hil_sim`), used only when the user asks for it.

``--sim`` (``scan``, ``serve``, ``calibrate``, ``probe``, the benches), ``piezod sim`` and the
``simsock:`` USB backend reach the simulated board through these functions, which import
:mod:`hil_sim` lazily: without them the host never loads the simulator. :mod:`hil_sim` itself
imports nothing from :mod:`piezod` (checked by ``tests/test_import_rules.py``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from piezod.errors import ConfigError, LinkError, LinkTimeoutError

if TYPE_CHECKING:
    from hil_sim.server import SimProcess


def spawn_sim(
    config_path: str | Path | None = None,
    effects: Sequence[str] = (),
    seed: int = 0,
    extra_args: Sequence[str] = (),
    link: str | Path | None = None,
    *,
    timeout_s: float = 30.0,
) -> SimProcess:
    """Start the simulated board on a pty (:func:`hil_sim.server.spawn_sim`); a context manager.

    Its ``path`` is the pty (or ``link``) the host opens; the parameters are those of
    :func:`hil_sim.server.spawn_sim`.
    """
    from hil_sim.errors import SimError, SimLinkTimeoutError
    from hil_sim.server import spawn_sim as _spawn

    try:
        return _spawn(config_path, effects, seed, extra_args, link, timeout_s=timeout_s)
    except SimLinkTimeoutError as exc:
        raise LinkTimeoutError(str(exc)) from exc
    except SimError as exc:
        raise LinkError(str(exc)) from exc


def usb_sim_backend(socket_path: str) -> Any:
    """The pyusb backend forwarding to the simulator's USB socket (``hil_sim.usb_backend``)."""
    from hil_sim.usb_backend import SimSocketBackend

    return SimSocketBackend(socket_path)


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulator's command-line options (``piezod sim``)."""
    from hil_sim.server import add_sim_arguments as _add

    _add(parser)


def run_sim(args: argparse.Namespace) -> int:
    """Run the simulator until killed (``piezod sim``); its errors become a one-line ConfigError."""
    from hil_sim.errors import SimError
    from hil_sim.server import run_from_args

    try:
        return int(run_from_args(args))
    except SimError as exc:
        raise ConfigError(str(exc)) from exc


def simulated_session(
    stage: str | Path,
    plan: Sequence[tuple[Any, ...]],
    *,
    effects: Sequence[str] = (),
    sample_rate_hz: float = 1000.0,
    seed: int = 0,
    axis: str = "x",
) -> list[tuple[str, Any, Any, Any]]:
    """Run ``plan`` on a preset (or scanner YAML) stage of the simulator, in process, without a board.

    Parameters
    ----------
    stage
        Preset name (``pi-stage``, ``p885-stage``, ...: ``configs/sim-NAME.yaml``) or a scanner
        YAML with a ``simulation:`` section.
    plan
        Experiments in order: ``("triangle", range_v, frequency_hz, offset_v, cycles, settle_cycles)``,
        ``("sine", range_v, frequency_hz, offset_v, cycles, settle_cycles)`` or
        ``("hold", voltage_v, duration_s)``.
    effects
        ``NAME=VALUE`` effects added to the stage (``piezod sim --effect``).
    sample_rate_hz, seed, axis
        Sampling, sensor-noise seed and the driven axis.

    Returns
    -------
    list
        Per recorded experiment ``(label, t_s, voltage_v, position_um)`` (numpy arrays).
    """
    from hil_sim.errors import SimError
    from hil_sim.session import Hold, PlanItem, Sine, Triangle, run_session
    from hil_sim.stage import StageConfig, resolve_stage

    items: list[PlanItem] = []
    for p in plan:
        kind, *args = p
        if kind in ("triangle", "sine"):
            r, f, o, cycles, settle = args
            cls = Triangle if kind == "triangle" else Sine
            items.append(cls(float(r), float(f), float(o), cycles=int(cycles), settle_cycles=int(settle)))
        elif kind == "hold":
            items.append(Hold(float(args[0]), float(args[1])))
        else:
            raise ConfigError(f"unknown plan item {kind!r} (triangle, sine or hold)")
    try:
        path = resolve_stage(stage)
        if path is None:
            raise ConfigError(f"no stage {stage!r}")
        cfg = StageConfig.from_file(path).with_effects(*effects)
        res = run_session(cfg, items, sample_rate_hz=sample_rate_hz, seed=seed, axis=axis)  # type: ignore[arg-type]
    except SimError as exc:
        raise ConfigError(str(exc)) from exc
    return [(e.label, e.t_s, e.voltage_v, e.position_um) for e in res.experiments]
