"""Batched helpers for block kernels: the operations numba does not compile on arrays with a
leading batch axis (matrix products and solves over a batch, cumulative sums along an axis,
per-variant gathers).

A kernel calls them as ``ko.bmatvec(M, v)`` (``from fwdstep import kernelops as ko``).  On the
NumPy path they are these vectorised NumPy functions; in compiled code the backend binds
the loops of ``fwdstep.compiled.compiled_ops`` (same names, same results) in their place.  The batch
axis broadcasts: an operand of leading length 1 is shared by every variant.
"""
from __future__ import annotations

import functools

import numpy as np

try:              # np.einsum's C core, without the wrapper that only picks the optimize path
    from numpy._core.multiarray import c_einsum as _einsum
except ImportError:                                                    # pragma: no cover
    _einsum = np.einsum


#: Matrices of at most this many entries are multiplied by einsum, 2-3x faster than the
#: stacked ``np.matmul`` over a batch (256 variants of a 2x4 regressor: 10 vs 27 us) and
#: faster for one variant too (2.5 vs 3.3 us); larger ones by ``np.matmul``.  The choice
#: depends on the matrix size only, never on the batch size, so a variant in a batch gets the
#: same bits as its run alone (tested).
SMALL = 32


def bvecmat(v, M):
    """y[b] = v[b] @ M[b]: v (B, n), M (B, n, m) -> (B, m).  Above ``SMALL`` entries one
    variant is one ``np.dot`` (BLAS gemv, as np.matmul calls per variant: the same bits,
    tested) without the stacked product's set-up (7x43: 0.9 instead of 1.3 us)."""
    if M.shape[1] * M.shape[2] <= SMALL:
        return _einsum("bi,bij->bj", v, M)
    if M.shape[0] == 1 and v.shape[0] == 1:
        return np.dot(v[0], M[0])[None]
    return np.matmul(v[:, None, :], M)[:, 0, :]


def bmatvec(M, v):
    """y[b] = M[b] @ v[b]: M (B, n, m), v (B, m) -> (B, n) (one variant: ``np.dot``, as
    ``bvecmat``)."""
    if M.shape[1] * M.shape[2] <= SMALL:
        return _einsum("bij,bj->bi", M, v)
    if M.shape[0] == 1 and v.shape[0] == 1:
        return np.dot(M[0], v[0])[None]
    return np.matmul(M, v[:, :, None])[:, :, 0]


def bmatmul(A, B):
    """C[b] = A[b] @ B[b]: A (B, n, k), B (B, k, m) -> (B, n, m)."""
    return np.matmul(A, B)


def bsolve(M, v):
    """x[b] = M[b]^-1 v[b]: M (B, n, n), v (B, n) -> (B, n).  A 2x2 system is solved by
    Cramer's rule (256 variants: 8 us instead of np.linalg.solve's 90 us)."""
    if M.shape[1] == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        inv_det = 1.0 / (a * d - b * c)
        x = np.empty((max(M.shape[0], v.shape[0]), 2))
        x[:, 0] = (d * v[:, 0] - b * v[:, 1]) * inv_det
        x[:, 1] = (a * v[:, 1] - c * v[:, 0]) * inv_det
        return x
    return np.linalg.solve(M, v[:, :, None])[:, :, 0]


def symupper(M):
    """S[b] symmetric with S[b, i, j] = M[b, min(i, j), max(i, j)] (M's upper triangle
    mirrored): M (B, n, n) -> (B, n, n)."""
    i, j = _strict_lower(M.shape[1])
    S = M.copy()
    S[:, i, j] = M[:, j, i]
    return S


@functools.lru_cache(maxsize=128)
def _strict_lower(n):
    return np.tril_indices(n, -1)


def cumsum1(a):
    """Cumulative sum along axis 1 of a 2-d array (real or complex)."""
    return np.add.accumulate(a, axis=1)


def take1(u, index):
    """y[b, j] = u[b, index[b, j]]: u (B, n), index (B, m) of whole numbers stored as floats."""
    B = max(u.shape[0], index.shape[0])
    idx = np.broadcast_to(index.astype(np.intp), (B, index.shape[1]))
    return np.take_along_axis(np.broadcast_to(u, (B, u.shape[1])), idx, axis=1)
