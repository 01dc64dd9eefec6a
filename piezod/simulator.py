"""The host's one entry point to the simulator (:mod:`hil_sim`), used only when the user asks for it.

``--sim`` (``scan``, ``serve``, ``calibrate``, ``probe``, the benches), ``piezod sim``, the
``sim://`` board URL (:class:`SimBoard`, looked up by :func:`piezod.link.board.open_board`) and
the ``simsock:`` USB backend reach the simulated board through these functions, which import
:mod:`hil_sim` lazily: without them the host never loads the simulator. An offline session of
:mod:`hil_sim.session` becomes the host's recording through :func:`session_recording`. :mod:`hil_sim` itself
imports nothing from :mod:`piezod` (checked by ``tests/test_import_rules.py``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qsl

from piezod.config import ScannerConfig, default_sim_config_path
from piezod.errors import ConfigError, LinkError, LinkTimeoutError
from piezod.link.board import SerialBoard
from piezod.link.events import LinkEvent
from piezod.link.plan import LinkSettings

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


def parse_sim_url(url: str) -> tuple[Path, tuple[str, ...], int]:
    """``sim://[SCANNER.yaml][?effect=NAME=VALUE&...&seed=N]`` -> (scanner YAML, effects, seed).

    Without a path: ``configs/sim-stage.yaml`` (the built-in stage).

    Raises
    ------
    ConfigError
        Not a ``sim://`` URL, an unknown option or a seed that is not a non-negative integer.
    """
    if not url.lower().startswith("sim://"):
        raise ConfigError(f"board URL {url!r}: not a sim:// URL")
    path, _, query = url[len("sim://") :].partition("?")
    effects: list[str] = []
    seed = 0
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=True) if query else []
    except ValueError:
        raise ConfigError(f"board URL {url!r}: malformed query {query!r}") from None
    for key, value in pairs:
        if key == "effect":
            effects.append(value)
        elif key == "seed" and value.isdigit():
            seed = int(value)
        elif key == "seed":
            raise ConfigError(f"board URL {url!r}: seed must be a non-negative integer, got {value!r}")
        else:
            raise ConfigError(f"board URL {url!r}: unknown option {key!r} (effect, seed)")
    return (Path(path) if path else default_sim_config_path()), tuple(effects), seed


class SimBoard(SerialBoard):
    """The ``sim://`` board: ``hil_sim`` started on a pty of its own, then a :class:`SerialBoard`
    on that pty (the real protocol over a real pty); the simulator stops when the board closes.

    Parameters
    ----------
    url
        ``sim://[SCANNER.yaml][?effect=NAME=VALUE&seed=N]`` (:func:`parse_sim_url`).
    config, on_event, settings
        As for :class:`SerialBoard`.
    """

    def __init__(
        self,
        url: str,
        config: ScannerConfig,
        on_event: Callable[[LinkEvent], None],
        settings: LinkSettings | None = None,
    ) -> None:
        self.sim_config_path, self.effects, self.seed = parse_sim_url(url)
        super().__init__(url, config, on_event, settings)
        self.sim: SimProcess | None = None

    def _do_open(self, timeout_s: float) -> tuple[str, ...]:
        if self.sim is None:
            self.sim = spawn_sim(self.sim_config_path, effects=self.effects, seed=self.seed)
            self.url = self.sim.path
        try:
            return super()._do_open(timeout_s)
        except BaseException:
            self._stop_sim()
            raise

    def _stop_sim(self) -> None:
        sim, self.sim = self.sim, None
        if sim is not None:
            sim.close()

    def close(self, *, ramp_to_safe: bool = True) -> None:
        try:
            super().close(ramp_to_safe=ramp_to_safe)
        finally:
            self._stop_sim()


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
