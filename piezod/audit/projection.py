"""Per-segment nuisance parameters eliminated by projection (variable projection).

Every segment owns a position offset and, optionally, a few more linear nuisance terms (the
unknown initial state of the ODE baseline and of the creep operator). For any model
parameters the least-squares optimum over the nuisance terms is the projection of the residual
onto the orthogonal complement of the nuisance columns, segment by segment.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class Projector:
    """Removes the per-segment least-squares fit of nuisance columns from vectors or matrices.

    Parameters
    ----------
    segment
        Segment id per row, non-decreasing.
    columns
        Extra nuisance columns (rows x m, m >= 0) besides the per-segment constant; a column that
        is zero on a segment does not act there.
    """

    def __init__(self, segment: NDArray[np.intp], columns: F64 | None = None) -> None:
        self.segment = np.asarray(segment, dtype=np.intp)
        n = self.segment.size
        change = np.flatnonzero(np.diff(self.segment)) + 1
        self.bounds = np.concatenate(([0], change)).astype(np.intp)
        self.counts = np.diff(np.append(self.bounds, n))
        self.index = np.repeat(np.arange(self.bounds.size), self.counts)
        if columns is None or columns.size == 0:
            self.basis: F64 | None = None
            self.n_nuisance = int(self.bounds.size)
            return
        b = np.column_stack((np.ones(n), columns))
        self.basis = b
        m = b.shape[1]
        iu, ju = np.triu_indices(m)
        sums = np.add.reduceat(b[:, iu] * b[:, ju], self.bounds, axis=0)
        gram = np.empty((self.bounds.size, m, m))
        gram[:, iu, ju] = sums
        gram[:, ju, iu] = sums
        self.pinv = np.linalg.pinv(gram, rcond=1e-11, hermitian=True)
        # Active nuisance terms: the rank of every segment's Gram matrix.
        self.n_nuisance = int(np.sum(np.linalg.matrix_rank(gram, tol=None, hermitian=True)))

    @property
    def n_segments(self) -> int:
        """Number of segments."""
        return int(self.bounds.size)

    def __call__(self, y: F64) -> F64:
        """``y`` (rows or rows x k) minus its per-segment nuisance fit."""
        if self.basis is None:
            sums = np.add.reduceat(y, self.bounds, axis=0)
            means = sums / (self.counts if y.ndim == 1 else self.counts[:, None])
            out: F64 = y - means[self.index]
            return out
        b = self.basis
        if y.ndim == 1:
            g = np.add.reduceat(b * y[:, None], self.bounds, axis=0)
            coef = np.einsum("sij,sj->si", self.pinv, g)
            c = coef[self.index]
            out = y - c[:, 0]
            for j in range(1, b.shape[1]):
                out -= b[:, j] * c[:, j]
            return out
        g2 = np.add.reduceat(b[:, :, None] * y[:, None, :], self.bounds, axis=0)
        coef2 = np.einsum("sij,sjk->sik", self.pinv, g2)
        out = y - np.einsum("ri,rik->rk", b, coef2[self.index])
        return out
