"""Where ``piezod ctl`` looks for a running daemon's API socket.

``piezod serve`` (:func:`piezod.service.daemon.default_api_spec`) listens on
``unix:<dir>/<scanner>.sock`` in the first usable of ``/run/piezod`` (the systemd unit's
``RuntimeDirectory``; the unit passes ``--api unix:/run/piezod/%i.sock``, the same path),
``$XDG_RUNTIME_DIR`` (as ``piezod-<scanner>.sock``) and ``/tmp/piezod-<euid>``.
``piezod ctl`` without ``--api`` and without ``$PIEZOD_API`` looks in the same places and
uses the one socket it finds.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from piezod.errors import ConfigError

#: The systemd unit's RuntimeDirectory.
RUN_DIR = Path("/run/piezod")
#: Where the per-user fallback directory ``piezod-<euid>`` lives.
TMP_ROOT = Path("/tmp")


def _user_tmp_dir() -> Path:
    return TMP_ROOT / f"piezod-{os.geteuid()}"


def _is_socket(p: Path) -> bool:
    try:
        return stat.S_ISSOCK(p.stat().st_mode)
    except OSError:
        return False


def running_api_sockets() -> list[Path]:
    """API sockets of daemons in the places ``serve`` puts them (see the module docstring)."""
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
