"""Progress display for long runs: a bar on a terminal, silence otherwise."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

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


def progress_bar(*, desc: str, total: float | None, unit: str = "it") -> tqdm:  # type: ignore[type-arg]
    """A manually updated progress bar (``bar.update(n)``), shown only on a terminal."""
    return tqdm(desc=desc, total=total, unit=unit, disable=not sys.stderr.isatty(), leave=False)
