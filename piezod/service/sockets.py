"""Where a daemon's API socket lives, for ``serve`` (where to listen) and ``ctl`` (where to look).

``piezod serve`` listens on ``unix:<dir>/<scanner>.sock`` in the first usable of
``/run/piezod`` (the systemd unit's ``RuntimeDirectory``; the unit passes
``--api unix:/run/piezod/%i.sock``, the same path), ``$XDG_RUNTIME_DIR`` (as
``piezod-<scanner>.sock``) and ``/tmp/piezod-<uid>``. ``piezod ctl`` without ``--api`` and
without ``$PIEZOD_API`` looks in the same places and uses the one socket it finds.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from piezod.errors import ConfigError

#: The systemd unit's RuntimeDirectory.
RUN_DIR = Path("/run/piezod")


def _user_tmp_dir() -> Path:
    return Path(f"/tmp/piezod-{os.getuid()}")


def default_api_spec(scanner: str) -> str:
    """``unix:/run/piezod/<scanner>.sock`` when that directory is writable, else a per-user socket."""
    run = RUN_DIR
    if run.is_dir() and os.access(run, os.W_OK):
        return f"unix:{run / (scanner + '.sock')}"
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and os.access(base, os.W_OK):
        return f"unix:{Path(base) / f'piezod-{scanner}.sock'}"
    d = _user_tmp_dir()
    d.mkdir(mode=0o700, exist_ok=True)
    return f"unix:{d / (scanner + '.sock')}"


def _is_socket(p: Path) -> bool:
    try:
        return stat.S_ISSOCK(p.stat().st_mode)
    except OSError:
        return False


def running_api_sockets() -> list[Path]:
    """API sockets of daemons in the places :func:`default_api_spec` puts them."""
    found: list[Path] = []
    places: list[tuple[Path, str]] = [(RUN_DIR, "*.sock")]
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base:
        places.append((Path(base), "piezod-*.sock"))
    places.append((_user_tmp_dir(), "*.sock"))
    for d, pattern in places:
        try:
            found.extend(p for p in sorted(d.glob(pattern)) if _is_socket(p))
        except OSError:
            continue
    return found


def discover_api_spec() -> str:
    """The API of the one running daemon found by :func:`running_api_sockets`.

    Raises
    ------
    ConfigError
        If none or several are found (naming where it looked, or what it found).
    """
    found = running_api_sockets()
    if len(found) == 1:
        return f"unix:{found[0]}"
    if not found:
        where = [f"{RUN_DIR}/*.sock"]
        if os.environ.get("XDG_RUNTIME_DIR"):
            where.append(f"{os.environ['XDG_RUNTIME_DIR']}/piezod-*.sock")
        where.append(f"{_user_tmp_dir()}/*.sock")
        raise ConfigError(
            f"no running piezod found (looked for {', '.join(where)}); start one (piezod serve) "
            "or pass --api unix:PATH / set PIEZOD_API"
        )
    raise ConfigError(
        f"{len(found)} piezod daemons are running ({', '.join(map(str, found))}): "
        "choose one with --api unix:PATH"
    )
