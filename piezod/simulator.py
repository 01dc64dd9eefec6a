"""The host's one entry point to the simulator (:mod:`hil_sim`), used only when the user asks for it.

``--sim`` (``scan``, ``serve``, ``calibrate``, ``probe``, the benches), ``piezod sim`` and the
``simsock:`` USB backend reach the simulated board through these functions, which import
:mod:`hil_sim` lazily: without them the host never loads the simulator. An offline session of
:mod:`hil_sim.session` becomes the host's recording through :func:`session_recording`. :mod:`hil_sim` itself
imports nothing from :mod:`piezod` (checked by ``tests/test_import_rules.py``).
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from piezod.errors import ConfigError, LinkError, LinkTimeoutError

if TYPE_CHECKING:
    from hil_sim.server import SimProcess
    from hil_sim.session import SessionResult
    from piezod.recording import Experiment, Recording


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


def session_recording(result: SessionResult, metadata: Mapping[str, str] | None = None) -> Recording:
    """All experiments of an offline :mod:`hil_sim.session` run as one :class:`~piezod.recording.Recording`.

    Columns t, voltage, position, axis, experiment; the metadata names the source and the effects.
    """
    import numpy as np

    from piezod.recording import Recording

    recs = result.experiments
    meta = {
        "source": "hil_sim offline session (simulated)",
        "sample_rate_hz": f"{result.sample_rate_hz:g}".replace("+", ""),
        "effects": ",".join(result.config.effects.enabled()) or "none",
        **(metadata or {}),
    }
    return Recording(
        t_s=np.concatenate([r.t_s for r in recs]),
        voltage_v=np.concatenate([r.voltage_v for r in recs]),
        position_um=np.concatenate([r.position_um for r in recs]),
        axis=np.concatenate([np.full(len(r), r.axis) for r in recs]),
        experiment=np.concatenate([np.full(len(r), r.label) for r in recs]),
        metadata=meta,
    )


def session_experiments(result: SessionResult) -> list[Experiment]:
    """An offline session as :class:`piezod.recording.Experiment` objects (what calibrate reads)."""
    from piezod.recording import split_experiments

    return split_experiments(session_recording(result))
