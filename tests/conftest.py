"""Shared pytest configuration."""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from hypothesis import HealthCheck, settings  # noqa: E402

settings.register_profile(
    "default", deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "thorough", deadline=None, max_examples=2000, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


# --- the board backends of the loopback tests: the Python board (hil_sim) and the C firmware ---

import shutil  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import pytest  # noqa: E402

BOARD_BACKENDS = ("hil_sim", "firmware")
"""``hil_sim``: ``python -m hil_sim``; ``firmware``: the host build of ``firmware_proto/c``."""


@pytest.fixture(autouse=True)
def _logger_state() -> Any:
    """Undo what an in-process entry point (``piezod sim`` via ``main``) does to logging.

    ``hil_sim``'s entry point gives its logger a handler on the process's stderr and stops
    propagation: run in a test, that handler writes to pytest's captured stream after it is closed,
    and later tests' ``caplog`` (on the root logger) no longer sees ``hil_sim``'s records.
    """
    import logging

    saved = {}
    for name in ("hil_sim", "piezod"):
        lg = logging.getLogger(name)
        saved[name] = (list(lg.handlers), lg.propagate, lg.level)
    yield
    for name, (handlers, propagate, level) in saved.items():
        lg = logging.getLogger(name)
        lg.handlers[:] = handlers
        lg.propagate = propagate
        lg.setLevel(level)


@pytest.fixture(scope="session")
def firmware_host_binary(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The host build of the C reference firmware, built once per session with ``make`` into a temp dir."""
    from hil_sim.firmware import build_firmware, missing_tools

    missing = missing_tools("make", "cc")
    if missing:
        pytest.skip(f"C firmware host build needs {', '.join(missing)} (apt-get install build-essential)")
    out = build_firmware(tmp_path_factory.mktemp("fw-build"), "host")
    return out / "host" / "piezod-fw-host"


@pytest.fixture(scope="session", params=BOARD_BACKENDS)
def board_backend(request: pytest.FixtureRequest) -> str:
    """The backend a loopback test runs against (each such test runs once per backend)."""
    return str(request.param)


@pytest.fixture(scope="session")
def spawn_board(board_backend: str, request: pytest.FixtureRequest) -> Callable[..., Any]:
    """``spawn_sim``-compatible factory of the board process of :func:`board_backend`."""
    if board_backend == "hil_sim":
        from hil_sim.server import spawn_sim

        return spawn_sim
    binary: Path = request.getfixturevalue("firmware_host_binary")
    from hil_sim.firmware import spawn_firmware

    def spawn(
        config_path: str | Path | None = None,
        effects: Sequence[str] = (),
        seed: int = 0,
        extra_args: Sequence[str] = (),
        link: str | Path | None = None,
    ) -> Any:
        return spawn_firmware(binary, config_path, effects, seed, extra_args, link)

    return spawn


def have(tool: str) -> bool:
    """The program ``tool`` is on PATH."""
    return shutil.which(tool) is not None
