"""Progress display for long runs: a bar on a terminal, silence otherwise."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TextIO, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], *, desc: str, total: int | None = None) -> Iterator[T]:
    """Iterate with a progress bar on stderr when stderr is a terminal.

    Parameters
    ----------
    iterable
        What to iterate over.
    desc
        Short label shown before the bar.
    total
        Number of items, when ``iterable`` has no ``len``.
    """
    yield from tqdm(iterable, desc=desc, total=total, disable=not sys.stderr.isatty(), leave=False)


#: A bar counting seconds: "4.2/10.0 s", no rate (tqdm's rate would read "1.01s/s").
SECONDS_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}]"


def progress_bar(*, desc: str, total: float | None, unit: str = "it", file: TextIO | None = None) -> tqdm:  # type: ignore[type-arg]
    """A manually updated progress bar (``bar.update(n)``), shown only on a terminal (stderr by default).

    With ``unit="s"`` and a total the bar counts seconds of a run of known length.
    """
    out = sys.stderr if file is None else file
    fmt = SECONDS_FORMAT if unit == "s" and total is not None else None
    return tqdm(
        desc=desc, total=total, unit=unit, bar_format=fmt, file=out, disable=not out.isatty(), leave=False
    )
