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


def sim_effect_names() -> tuple[str, ...]:
    """The effect ids the simulated stage can inject (``hil_sim.effects.EFFECT_NAMES``)."""
    from hil_sim.effects import EFFECT_NAMES

    return tuple(EFFECT_NAMES)


def load_stage(config_path: str | Path, effects: Sequence[str], axis: str, seed: int) -> Any:
    """The simulated stage of ``config_path`` (its ``simulation:`` section) with ``effects``
    (``NAME=VALUE`` / ``NAME.FIELD=VALUE``), one axis, stepped in this process (``hil_sim.stage.Stage``:
    ``step(volts, dt)``, ``sense(positions)``)."""
    from hil_sim.errors import SimError
    from hil_sim.stage import Stage, StageConfig

    try:
        config = StageConfig.from_file(config_path).with_effects(*effects)
        return Stage(config, axes=(axis,), seed=seed)  # type: ignore[arg-type]
    except SimError as exc:
        raise ConfigError(str(exc)) from exc


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
