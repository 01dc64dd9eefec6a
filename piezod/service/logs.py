"""Logging to stderr with journald priority prefixes when running under systemd."""

from __future__ import annotations

import logging
import os
import sys

#: syslog priorities of sd-daemon(3) (``<3>`` = error ...), keyed by logging level.
_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


class JournalPrefixFormatter(logging.Formatter):
    """Prefix each line with ``<N>`` so journald files it under the right priority."""

    def format(self, record: logging.LogRecord) -> str:
        level = max((lvl for lvl in _PRIORITY if lvl <= record.levelno), default=logging.DEBUG)
        prio = _PRIORITY[level]
        text = super().format(record)
        return "\n".join(f"<{prio}>{line}" for line in text.splitlines())


def setup_logging(level: int = logging.INFO, *, journal: bool | None = None) -> None:
    """Log to stderr; with journald priority prefixes when stderr is the journal.

    Parameters
    ----------
    level
        Root log level.
    journal
        Force the prefixes on or off; by default on when ``$JOURNAL_STREAM`` is set.
    """
    if journal is None:
        journal = bool(os.environ.get("JOURNAL_STREAM"))
    handler = logging.StreamHandler(sys.stderr)
    if journal:
        handler.setFormatter(JournalPrefixFormatter("%(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
