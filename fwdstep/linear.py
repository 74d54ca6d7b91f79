"""Linear time-invariant blocks in one generic form.

Every linear block (transfer functions, state-space systems, reference dynamics, regressor
filters) is described by flat matrices over the *vectorised* (C-order flattened) ports::

    xdot    = A x + sum_j B_j vec(u_j)
    vec(y_k) = C_k x + sum_j D_kj vec(u_j)

The block's constructor only builds these matrices; the run-time code is shared here.  The
per-output feedthrough is read off the non-zero ``D_kj`` blocks, so it is exact.  Because the
engine knows this form, it can later fuse all linear blocks of a diagram into one system.
"""
from __future__ import annotations

import numpy as np

from .block import Block


class LinearBlock(Block):
    """Base class: subclasses declare ports and call ``set_linear`` in ``setup``."""

    def set_linear(self, A, B: dict, C: dict, D: dict | None = None, x0=None) -> None:
        """``A`` (N, N); ``B`` maps input name -> (N, size_in); ``C`` maps output name ->
        (size_out, N); ``D`` maps (output, input) -> (size_out, size_in) (missing = 0).
        Ports must already be declared (outputs with any feedthrough; it is recomputed)."""
        A = np.asarray(A, dtype=float)
        n = A.shape[0]
        self.declare_state(n, x0)
        D = D or {}
        self._in_names = list(self.inputs)
        self._out_names = list(self.outputs)
        self.set_param("A_T", A.T)
        self._b_used = []
        for j, name in enumerate(self._in_names):
            Bj = np.asarray(B.get(name, np.zeros((n, self.inputs[name].size))), dtype=float)
            if Bj.shape != (n, self.inputs[name].size):
                raise ValueError(f"B[{name}] has shape {Bj.shape}")
            if np.any(Bj != 0):
                self.set_param(f"B_T_{j}", Bj.T)
                self._b_used.append(j)
        self._d_used = []
        for k, out in enumerate(self._out_names):
            Ck = np.asarray(C[out], dtype=float)
            if Ck.shape != (self.outputs[out].size, n):
                raise ValueError(f"C[{out}] has shape {Ck.shape}")
            self.set_param(f"C_T_{k}", Ck.T)
            used = []
            for j, name in enumerate(self._in_names):
                Dkj = D.get((out, name))
                if Dkj is not None and np.any(np.asarray(Dkj) != 0):
                    Dkj = np.asarray(Dkj, dtype=float)
                    if Dkj.shape != (self.outputs[out].size, self.inputs[name].size):
                        raise ValueError(f"D[{out},{name}] has shape {Dkj.shape}")
                    self.set_param(f"D_T_{k}_{j}", Dkj.T)
                    used.append(j)
            self._d_used.append(used)
            self._feedthrough[out] = tuple(self._in_names[j] for j in used)
        self._out_shapes = [self.outputs[o].shape for o in self._out_names]
        self.finalize(1)

    def finalize(self, batch: int) -> None:
        p = self.p
        self._batched = p.A_T.shape[0] > 1
        self._AT = p.A_T if self._batched else p.A_T[0]
        pick = (lambda a: a) if self._batched else (lambda a: a[0])
        self._BT = [(j, pick(getattr(p, f"B_T_{j}"))) for j in self._b_used]
        self._CT = [pick(getattr(p, f"C_T_{k}")) for k in range(len(self._out_names))]
        self._DT = [[(j, pick(getattr(p, f"D_T_{k}_{j}"))) for j in used]
                    for k, used in enumerate(self._d_used)]

    @staticmethod
    def _flat(u: np.ndarray) -> np.ndarray:
        return u.reshape(u.shape[0], -1)

    def _mul(self, v: np.ndarray, MT: np.ndarray) -> np.ndarray:
        if self._batched:
            return np.matmul(v[:, None, :], MT)[:, 0, :]
        return v @ MT

    def output(self, t, x, u):
        outs = []
        for k, CT in enumerate(self._CT):
            y = self._mul(x, CT)
            for j, DT in self._DT[k]:
                y = y + self._mul(self._flat(u[j]), DT)
            outs.append(y.reshape((y.shape[0],) + self._out_shapes[k]))
        return tuple(outs)

    def derivative(self, t, x, u):
        dx = self._mul(x, self._AT)
        for j, BT in self._BT:
            dx = dx + self._mul(self._flat(u[j]), BT)
        return dx


def observer_form(den, nums):
    """Observer-canonical realisation of ``y = sum_j nums[j](p) / den(p) u_j`` (SISO, one
    shared monic-normalised denominator, each numerator of degree <= deg den).

    Coefficients are highest power first (numpy.polyval order).  Returns ``(A, B, C, D)``
    with ``B`` of shape (n, m) and ``D`` of shape (m,).  This *is* the paper's degree
    reduction: the state is z, then z' + ..., and so on (Sec. 3.2).
    """
    den = np.trim_zeros(np.asarray(den, dtype=float), "f")
    if den.size == 0:
        raise ValueError("denominator is zero")
    lead = den[0]
    den = den / lead
    n = den.size - 1
    A = np.zeros((n, n))
    if n:
        A[:, 0] = -den[1:]
        A[:-1, 1:] = np.eye(n - 1)
    B = np.zeros((n, len(nums)))
    D = np.zeros(len(nums))
    for j, num in enumerate(nums):
        num = np.asarray(num, dtype=float) / lead
        num = np.trim_zeros(num, "f") if np.any(num) else np.zeros(1)
        if num.size - 1 > n:
            raise ValueError("improper")
        num = np.concatenate([np.zeros(n + 1 - num.size), num])
        D[j] = num[0]
        B[:, j] = num[1:] - num[0] * den[1:]
    C = np.zeros((1, n))
    if n:
        C[0, 0] = 1.0
    return A, B, C, D
