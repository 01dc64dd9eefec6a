"""The garbage collector's time, which the engine's slow-block warning reports."""

from __future__ import annotations

import gc

from piezod.service import gcwatch


def test_collections_are_timed_from_any_thread() -> None:
    gcwatch.install()
    gcwatch.install()  # idempotent: one callback, not two
    assert gc.callbacks.count(gcwatch._callback) == 1
    before = gcwatch.collection_seconds()
    junk = [[i] for i in range(100_000)]
    gc.collect()
    del junk
    assert gcwatch.collection_seconds() > before
