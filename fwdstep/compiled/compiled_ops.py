"""The numba twins of ``fwdstep.core.kernelops`` (same names, same results), bound in place of the
NumPy versions when the compiled backend jits a block's kernels.  Without numba (the optional
``fast`` extra) they stay plain Python loops: the tracer (``fwdstep.compiled.scalarize``), which
the linear analysis also uses, reads them as such."""
from __future__ import annotations

import numpy as np

try:
    from numba import njit
except ImportError:
    def njit(*args, **kwargs):
        """Without numba: the function itself (the decorator's arguments are ignored)."""
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda fn: fn


@njit(cache=False)
def bvecmat(v, M):
    B = max(v.shape[0], M.shape[0])
    n, m = M.shape[1], M.shape[2]
    y = np.zeros((B, m))
    for b in range(B):
        bv = b if v.shape[0] > 1 else 0
        bm = b if M.shape[0] > 1 else 0
        for i in range(n):
            vi = v[bv, i]
            for j in range(m):
                y[b, j] += vi * M[bm, i, j]
    return y


@njit(cache=False)
def bmatvec(M, v):
    B = max(v.shape[0], M.shape[0])
    n, m = M.shape[1], M.shape[2]
    y = np.zeros((B, n))
    for b in range(B):
        bv = b if v.shape[0] > 1 else 0
        bm = b if M.shape[0] > 1 else 0
        for i in range(n):
            acc = 0.0
            for j in range(m):
                acc += M[bm, i, j] * v[bv, j]
            y[b, i] = acc
    return y


@njit(cache=False)
def bmatmul(A, C):
    B = max(A.shape[0], C.shape[0])
    n, k, m = A.shape[1], A.shape[2], C.shape[2]
    y = np.zeros((B, n, m))
    for b in range(B):
        ba = b if A.shape[0] > 1 else 0
        bc = b if C.shape[0] > 1 else 0
        for i in range(n):
            for j in range(m):
                acc = 0.0
                for r in range(k):
                    acc += A[ba, i, r] * C[bc, r, j]
                y[b, i, j] = acc
    return y


@njit(cache=False)
def bsolve(M, v):
    """Gaussian elimination with partial pivoting (LAPACK getrf/getrs order of pivots), in
    loops: numba compiles np.linalg.solve in ~10 s, these loops in well under 1 s."""
    B = max(v.shape[0], M.shape[0])
    n = M.shape[1]
    y = np.empty((B, n))
    A = np.empty((n, n))
    r = np.empty(n)
    for b in range(B):
        bv = b if v.shape[0] > 1 else 0
        bm = b if M.shape[0] > 1 else 0
        for i in range(n):
            r[i] = v[bv, i]
            for j in range(n):
                A[i, j] = M[bm, i, j]
        for k in range(n):
            p = k
            big = abs(A[k, k])
            for i in range(k + 1, n):
                if abs(A[i, k]) > big:
                    big = abs(A[i, k])
                    p = i
            if p != k:
                for j in range(n):
                    A[k, j], A[p, j] = A[p, j], A[k, j]
                r[k], r[p] = r[p], r[k]
            piv = A[k, k]
            for i in range(k + 1, n):
                f = A[i, k] / piv
                if f != 0.0:
                    for j in range(k + 1, n):
                        A[i, j] -= f * A[k, j]
                    r[i] -= f * r[k]
        for i in range(n - 1, -1, -1):
            acc = r[i]
            for j in range(i + 1, n):
                acc -= A[i, j] * y[b, j]
            y[b, i] = acc / A[i, i]
    return y


@njit(cache=False)
def symupper(M):
    B, n = M.shape[0], M.shape[1]
    y = np.empty((B, n, n))
    for b in range(B):
        for i in range(n):
            for j in range(i, n):
                y[b, i, j] = M[b, i, j]
                y[b, j, i] = M[b, i, j]
    return y


@njit(cache=False)
def cumsum1(a):
    out = np.empty_like(a)
    for b in range(a.shape[0]):
        acc = a[b, 0] * 0
        for i in range(a.shape[1]):
            acc += a[b, i]
            out[b, i] = acc
    return out


@njit(cache=False)
def take1(u, index):
    B = max(u.shape[0], index.shape[0])
    m = index.shape[1]
    y = np.empty((B, m))
    for b in range(B):
        bu = b if u.shape[0] > 1 else 0
        bi = b if index.shape[0] > 1 else 0
        for j in range(m):
            y[b, j] = u[bu, int(index[bi, j])]
    return y
