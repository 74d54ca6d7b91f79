"""Linear time-invariant blocks in one generic form.

Every linear block (transfer functions, state-space systems, reference dynamics, regressor
filters) is described by flat matrices over the *vectorised* (C-order flattened) ports::

    xdot    = A x + sum_j B_j vec(u_j)
    vec(y_k) = C_k x + sum_j D_kj vec(u_j)

The block's constructor only builds these matrices; the run-time code is shared here.  The
per-output feedthrough is read off the non-zero ``D_kj`` blocks, so it is exact.

Because the engine knows this form, it fuses the linear blocks of a diagram (``plan_fusion``):
their states sit side by side in one block-diagonal system whose derivative is one matrix
product per stage, and chains of linear outputs (y = C x + D u feeding another linear block)
are substituted into each other at compile time, so every group of linear signals that
becomes computable at the same point of the schedule costs one matrix product.  Any block
may take part by offering ``linear_form()`` (see ``LinearForm``); ``LinearBlock`` offers it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fwdstep.core.block import Block


class LinearBlock(Block):
    """Base class: subclasses declare ports and call ``set_linear`` in ``setup``."""

    finalize_attributes = Block.finalize_attributes + ("_batched", "_AT", "_BT", "_CT", "_DT")

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
        pick = (lambda a: a) if self._batched else (lambda a: a[0])
        op = (lambda a: _operator(pick(a), self._batched))
        self._AT = op(p.A_T)
        self._BT = [(j, op(getattr(p, f"B_T_{j}"))) for j in self._b_used]
        self._CT = [op(getattr(p, f"C_T_{k}")) for k in range(len(self._out_names))]
        self._DT = [[(j, op(getattr(p, f"D_T_{k}_{j}"))) for j in used]
                    for k, used in enumerate(self._d_used)]

    @staticmethod
    def _flat(u: np.ndarray) -> np.ndarray:
        return u.reshape(u.shape[0], -1)

    def output(self, t, x, u):
        outs = []
        for k, CT in enumerate(self._CT):
            y = CT(x) if CT is not None else np.zeros((x.shape[0],) + self._out_shapes[k])
            y = y.reshape(x.shape[0], -1)
            for j, DT in self._DT[k]:
                if DT is not None:
                    y = y + DT(self._flat(u[j]))
            outs.append(y.reshape((y.shape[0],) + self._out_shapes[k]))
        return tuple(outs)

    def derivative(self, t, x, u):
        dx = self._AT(x) if self._AT is not None else None
        for j, BT in self._BT:
            if BT is not None:
                term = BT(self._flat(u[j]))
                dx = term if dx is None else dx + term
        return dx if dx is not None else np.zeros_like(x)


#: a matrix with at least this many entries and at most SPARSE_DENSITY of them nonzero is
#: applied as a scipy.sparse matrix (an Integrator of 2000 states has A = 0 and C = I: dense,
#: every call would read 32 MB to compute x)
SPARSE_MIN_SIZE = 1 << 16
SPARSE_DENSITY = 0.05


def _operator(MT: np.ndarray, batched: bool):
    """``v -> v @ MT`` (v is (B, n)) in the cheapest exact structure: None for a zero
    matrix, a copy for the identity, a scaling for a diagonal, scipy.sparse for a large
    sparse matrix, else the dense product.  Batched matrices (B, n, m) stay dense."""
    if batched:
        return lambda v: np.matmul(v[:, None, :], MT)[:, 0, :]
    if not MT.any():
        return None
    n, m = MT.shape
    if n == m and n > 1:
        diag = np.diagonal(MT)
        if np.count_nonzero(MT) == np.count_nonzero(diag):
            if (diag == 1).all():
                return lambda v: np.array(v, dtype=float)
            d = diag.copy()
            return lambda v: v * d
    if MT.size >= SPARSE_MIN_SIZE and np.count_nonzero(MT) <= SPARSE_DENSITY * MT.size:
        from scipy import sparse
        S = sparse.csr_matrix(MT.T)
        return lambda v: np.asarray((S @ v.T).T)
    return lambda v: v @ MT


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
    with np.errstate(all="ignore"):
        den = den / lead
        scaled = [np.asarray(num, dtype=float) / lead for num in nums]
    if not (np.isfinite(den).all() and all(np.isfinite(num).all() for num in scaled)):
        from fwdstep.core.errors import ParameterError
        raise ParameterError(f"parameter 'den': the leading coefficient {lead:g} is too small "
                             "(dividing the other coefficients by it overflows); drop it or "
                             "rescale the transfer function")
    n = den.size - 1
    A = np.zeros((n, n))
    if n:
        A[:, 0] = -den[1:]
        A[:-1, 1:] = np.eye(n - 1)
    B = np.zeros((n, len(nums)))
    D = np.zeros(len(nums))
    for j, num in enumerate(scaled):
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


# ---------------------------------------------------------------------------- fusion
@dataclass
class LinearForm:
    """A block's exact linear description, every matrix with a leading batch axis (1 or B)
    and in (out, in) orientation over the vectorised ports::

        xdot = A x + sum_j B[j] vec(u_j),    vec(y_k) = C[k] x + sum_j D[(k, j)] vec(u_j)

    ``A`` (Bp, N, N); ``B`` maps input index j -> (Bp, N, size_j); ``C`` lists one
    (Bp, size_k, N) per output; ``D`` maps (k, j) -> (Bp, size_k, size_j).  Missing = zero.
    A block's ``linear_form()`` may return None (e.g. too large to hold densely); the block is
    then simply called.  It must describe ``output`` and ``derivative`` exactly."""
    A: np.ndarray
    B: dict
    C: list
    D: dict


def _linear_form(self) -> LinearForm:
    """This block's ``LinearForm``, read from the (possibly stacked) parameters in ``p``."""
    p = self.p

    def t(a):
        return np.swapaxes(a, -1, -2)

    return LinearForm(
        A=t(p.A_T),
        B={j: t(getattr(p, f"B_T_{j}")) for j in self._b_used},
        C=[t(getattr(p, f"C_T_{k}")) for k in range(len(self._out_names))],
        D={(k, j): t(getattr(p, f"D_T_{k}_{j}"))
           for k, used in enumerate(self._d_used) for j in used})


LinearBlock.linear_form = _linear_form


def _defining_index(cls: type, name: str) -> int | None:
    for i, klass in enumerate(cls.__mro__):
        if name in vars(klass):
            return i
    return None


def linear_form_of(block: Block) -> LinearForm | None:
    """The block's ``LinearForm`` if it offers one that describes its run-time methods.

    A subclass that overrides ``output`` or ``derivative`` below the class defining
    ``linear_form`` is not trusted to be linear and is called like any other block."""
    cls = type(block)
    where = _defining_index(cls, "linear_form")
    if where is None:
        return None
    for method in ("output", "derivative"):
        defined = _defining_index(cls, method)
        if defined is not None and defined < where:
            return None
    return block.linear_form()


def matrix_eigenvalues(A: np.ndarray) -> np.ndarray:
    """The eigenvalues of every variant's (N, N) matrix in ``A`` (Bp, N, N): (Bp, N) complex.
    A large matrix is split into its decoupled diagonal blocks (the connected components of
    its nonzero pattern, e.g. ``kron(I, A_filter)`` of a filter bank on a robot's signals),
    and equal blocks are solved once: a 900-state bank costs microseconds, not a dense
    900 x 900 eigenproblem."""
    A = np.asarray(A, dtype=float)
    Bp, N = A.shape[0], A.shape[-1]
    if N <= 32:
        return np.linalg.eigvals(A)
    from scipy.sparse import csgraph, csr_matrix
    pattern = (A != 0).any(axis=0)
    n_parts, label = csgraph.connected_components(csr_matrix(pattern | pattern.T),
                                                  directed=False)
    out = np.empty((Bp, N), dtype=complex)
    seen: dict = {}
    col = 0
    for part in range(n_parts):
        idx = np.flatnonzero(label == part)
        sub = A[:, idx[:, None], idx[None, :]]
        key = (sub.shape, sub.tobytes())
        if key not in seen:
            seen[key] = np.linalg.eigvals(sub)
        out[:, col:col + idx.size] = seen[key]
        col += idx.size
    return out


def fusable(block: Block) -> bool:
    """Cheap class-level test used to lay fusable states out side by side."""
    cls = type(block)
    where = _defining_index(cls, "linear_form")
    return where is not None and all(
        (_defining_index(cls, m) is None or _defining_index(cls, m) >= where)
        for m in ("output", "derivative"))


#: Fusion is skipped when one fused matrix would hold more numbers than this (dense
#: matrices of large filtered signals would cost more than the calls they replace).  At
#: 1360 fused states (Theorem 6 on the Panda, diagrams/robots/) the dense product cost 14x
#: the unfused calls; the shipped two-link diagrams have at most 175 states.
MAX_FUSED_ELEMENTS = 250_000


@dataclass
class LinearGroup:
    """One fused matrix product ``[outputs | dx] = [inputs] @ M``.

    ``inputs``: list of (term, size) in column order; term is ``"x"`` (the fused states) or a
    signal index.  ``outputs``: list of (signal index, size) in column order.  With
    ``derivative`` true, the last ``n_states`` product columns are the fused states'
    derivative.  ``M`` is (Bp, n_in, n_out) with Bp = 1 or the batch size."""
    inputs: list
    outputs: list
    M: np.ndarray
    derivative: bool = False


@dataclass
class FusionPlan:
    """The evaluation order with linear blocks fused.

    ``ops``: ("call", step) or ("group", LinearGroup) in evaluation order; every signal is
    written by exactly one op.  ``state``: slice of the flat state holding the fused states;
    their derivative is computed by the one group with ``derivative`` set (with the last
    output group whose inputs suffice, or a group of its own at the end).  ``fused``: names
    of the blocks that are no longer called."""
    ops: list
    state: slice
    fused: set = field(default_factory=set)


class _TooLarge(Exception):
    pass


def _accumulate(terms: dict, key, mat: np.ndarray) -> None:
    terms[key] = terms[key] + mat if key in terms else mat


def plan_fusion(schedule: list, signal_shapes: list, constants: dict) -> FusionPlan | None:
    """Fuse every block offering a ``LinearForm``; None when there is nothing to fuse or the
    fused matrices would be too large.  ``schedule`` lists the compiler's Steps."""
    forms = {i: f for i, f in ((i, linear_form_of(st.block)) for i, st in enumerate(schedule))
             if f is not None}
    n_fused_states = sum(schedule[i].state.stop - schedule[i].state.start for i in forms
                         if schedule[i].state is not None)
    batch = max([f.A.shape[0] for f in forms.values() if f.A is not None] + [1])
    if batch * n_fused_states ** 2 > MAX_FUSED_ELEMENTS:
        # one dense (B, N, N) state matrix would be wasteful (12 GiB for 40 000 integrator
        # states): fuse the stateless blocks only; the others keep their own, block-sized
        # derivative calls
        forms = {i: f for i, f in forms.items() if schedule[i].state is None}
    if not forms:
        return None
    # the fused states must form one slice (the compiler lays them out so)
    slices = sorted((schedule[i].state for i in forms if schedule[i].state is not None),
                    key=lambda sl: sl.start)
    start = stop = slices[0].start if slices else 0
    for sl in slices:
        if sl.start != stop:
            return None
        stop = sl.stop
    width = stop - start
    try:
        with np.errstate(all="ignore"):        # huge gains multiply to inf, as they would
            return _Planner(schedule, forms, signal_shapes, constants, start, width).run()
    except _TooLarge:
        return None


class _Planner:
    """Walks the schedule once; see ``plan_fusion``.  Expressions are dicts term -> matrix
    (Bp, rows, cols) in (out, in) orientation; term "x" is the fused state vector."""

    def __init__(self, schedule, forms, shapes, constants, start, width):
        self.schedule, self.forms, self.constants = schedule, forms, constants
        self.start, self.width = start, width
        self.size = [int(np.prod(sh, dtype=np.int64)) for sh in shapes]
        self.pending: dict = {}        # signal index -> (schedule position, output number)
        self.taken: set = set()        # schedule positions of fused blocks already placed
        self.available: set = set(constants)
        self.ops: list = []
        self.derivative = self._derivative_terms() if width else None

    def _place_cols(self, i, mat):
        """(Bp, rows, n_i) -> (Bp, rows, width), at block i's columns of the fused state."""
        sl = self.schedule[i].state
        full = np.zeros(mat.shape[:-1] + (self.width,))
        full[..., sl.start - self.start:sl.stop - self.start] = mat
        return full

    def _place_rows(self, i, mat):
        sl = self.schedule[i].state
        full = np.zeros(mat.shape[:-2] + (self.width, mat.shape[-1]))
        full[..., sl.start - self.start:sl.stop - self.start, :] = mat
        return full

    def _derivative_terms(self) -> dict:
        terms: dict = {}
        for i, form in self.forms.items():
            step = self.schedule[i]
            if step.state is None:
                continue
            _accumulate(terms, "x", self._place_rows(i, self._place_cols(i, form.A)))
            for j, Bj in form.B.items():
                u = step.inputs[j]
                if u not in self.constants:         # unconnected optional input: zero
                    _accumulate(terms, u, self._place_rows(i, Bj))
        return terms

    def _substitute(self, terms: dict, memo: dict) -> dict:
        """Replace pending linear signals in ``terms`` by their expressions."""
        out: dict = {}
        for term, mat in terms.items():
            if term in self.pending:
                for sub, smat in self._expression(term, memo).items():
                    _accumulate(out, sub, np.matmul(mat, smat))
            else:
                _accumulate(out, term, mat)
        return out

    def _expression(self, idx: int, memo: dict) -> dict:
        if idx not in memo:
            i, k = self.pending[idx]
            form, step = self.forms[i], self.schedule[i]
            terms: dict = {}
            if step.state is not None and np.any(form.C[k]):
                terms["x"] = self._place_cols(i, form.C[k])
            for (kk, j), Dkj in form.D.items():
                if kk == k and step.inputs[j] not in self.constants:
                    _accumulate(terms, step.inputs[j], Dkj)
            memo[idx] = self._substitute(terms, memo)
        return memo[idx]

    def _hoist(self) -> None:
        """Add to the pending group every later fused block whose outputs can already be
        computed (its feedthrough inputs are available or pending): a tracking error that
        is only logged then joins the first product instead of widening a later one."""
        changed = True
        while changed:
            changed = False
            for i, form in self.forms.items():
                if i in self.taken:
                    continue
                step = self.schedule[i]
                needed = {step.inputs[j] for (_, j) in form.D} - set(self.constants)
                if all(u in self.available or u in self.pending for u in needed):
                    self._take(i)
                    changed = True

    def _take(self, i: int) -> None:
        self.taken.add(i)
        for k, idx in enumerate(self.schedule[i].outputs):
            self.pending[idx] = (i, k)

    def _flush(self) -> None:
        if not self.pending:
            return
        self._hoist()
        memo: dict = {}
        rows = [(idx, self.size[idx]) for idx in self.pending]
        row_terms = [self._expression(idx, memo) for idx in self.pending]
        with_derivative = self.derivative is not None and all(
            t == "x" or t in self.available or t in self.pending for t in self.derivative)
        if with_derivative:
            rows.append((None, self.width))
            row_terms.append(self._substitute(self.derivative, memo))
            self.derivative = None
        self.ops.append(("group", self._group(rows, row_terms, with_derivative)))
        self.available.update(self.pending)
        self.pending.clear()

    def _group(self, rows: list, row_terms: list, derivative: bool) -> LinearGroup:
        columns: list = []
        for terms in row_terms:
            columns.extend(t for t in terms if t not in columns)
        columns.sort(key=lambda c: c != "x")
        col_size = {c: (self.width if c == "x" else self.size[c]) for c in columns}
        n_in = sum(col_size.values())
        n_out = sum(n for _, n in rows)
        batch = max([m.shape[0] for terms in row_terms for m in terms.values()] + [1])
        if batch * n_in * n_out > MAX_FUSED_ELEMENTS:
            raise _TooLarge
        M = np.zeros((batch, n_in, n_out))
        col0, c = {}, 0
        for term in columns:
            col0[term], c = c, c + col_size[term]
        r = 0
        for (_, n), terms in zip(rows, row_terms):
            for term, mat in terms.items():
                M[:, col0[term]:col0[term] + col_size[term], r:r + n] = np.swapaxes(mat, -1, -2)
            r += n
        outputs = [(idx, n) for idx, n in rows if idx is not None]
        return LinearGroup(inputs=[(t, col_size[t]) for t in columns], outputs=outputs, M=M,
                           derivative=derivative)

    def run(self) -> FusionPlan:
        for i, step in enumerate(self.schedule):
            if i in self.forms:
                if i not in self.taken:
                    self._take(i)
                continue
            if any(u in self.pending for u in step.inputs):
                self._flush()
            self.ops.append(("call", step))
            self.available.update(step.outputs)
        self._flush()
        if self.derivative is not None:         # its inputs come after every output group
            self.ops.append(("group", self._group([(None, self.width)], [self.derivative],
                                                  True)))
        return FusionPlan(ops=self.ops, state=slice(self.start, self.start + self.width),
                          fused={self.schedule[i].block.name for i in self.forms})
