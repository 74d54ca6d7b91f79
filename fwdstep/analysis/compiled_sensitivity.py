"""Forward sensitivities on the compiled backend: the variational equations compiled into
the stage, integrated by the compiled loop as a bigger state.

The compiled backend traces the whole stage into one scalar expression graph
(``fwdstep.compiled.scalarize``, ``backend_numba._ScalarStage``).  ``VariationalStage`` is
that stage with, added to the same graph, the derivative of every state derivative and of
every logged entry along P directions (``fwdstep.analysis.jacobian.directional_tangents``,
the forward mode the block Jacobians use): the state x_i's tangent in direction c is a new
state entry S[i, c], a moved parameter entry's tangent is its dp/dtheta (found by the
loader, ``sensitivity.loader_derivative``), so the tangent of the state derivative f is
A S + B.  The stage integrates (x, S), N (1 + P) entries; the Runge-Kutta map applied to
that state *is* the variational equation of the RK map (same tableau, same stage times,
same sub-steps at declared discontinuities), which the NumPy path integrates block by
block (``sensitivity._integrate``): both differentiate the numbers fwdstep computes.

Where a parameter reaches the code:

* a kernel's argument ``block.p.NAME`` moved by the parameter: its entries are leaves of
  their own (not folded into 0, 1, -1 nor shared with an unmoved entry, as the diagram's
  stage does; shared only with an equal moving entry of equal seeds), seeded with their
  column of dp (entries of W as well: another value of the parameter with the same pattern
  of zeros runs the same machine code);
* a fused linear group's matrix M (``fwdstep.core.linear.plan_fusion``): M is a product of
  the blocks' matrices, so dM/dtheta is the Richardson central difference of the fusion of
  the moved blocks (exact to round-off for the polynomials of degree <= 4 a fusion makes);
  the entries that move are leaves of their own, seeded with dM.

The sensitivities of logged signals are extra columns of the compiled log (``LL``), written
at the same record as the signals.  Only x is checked against ``simulation.bound``.

The traced stage is memoised (``variational_stage``) by everything the trace reads except
the values of the moving entries and their seeds; a call with new values (a tuning's next
evaluation) reuses the graph and the machine code with those W columns rebound
(``VariationalStage.rebound``), unless a number a kernel's branch was written for moves
(``Trace.decisions``): then it is traced again.

Not compiled (``run_compiled`` returns the reason, and ``fwdstep.sensitivities`` takes the
NumPy path with a one-line note in ``Result.notes``): discrete updates at sample instants,
zero crossings, stages that do not trace (object-mode blocks, kernels the tracer refuses),
a parameter that reaches a kernel other than as one of its arguments.
"""
from __future__ import annotations

import copy
import dataclasses
import time as _time

import numpy as np

from fwdstep.analysis.jacobian import DIFFERENCE_STEP, OFFSETS, directional_tangents, \
    moved_block, moved_variants, richardson
from fwdstep.compiled import backend_numba
from fwdstep.compiled import scalarize as sz
from fwdstep.compiled.driver import CompiledBackend, numpy_instead
from fwdstep.core.solvers import TABLEAUX

#: the variational stage's graph may hold this many nodes (the diagram's stage: 20 000)
MAX_NODES = 200_000


class VariationalStage(backend_numba._ScalarStage):
    """The diagram's scalar stage and its tangents along P directions (module docstring).
    ``dp[(block, name)]``: d block.p.name / d columns, (size, P); ``dM[id(group op)]``:
    d M / d columns, (P, rows, columns).  State layout: x (N), then S[i, c] at
    N + i P + c.  ``sens_columns``: the first log column of each logged signal's
    sensitivities, (size, P) in C order."""

    def __init__(self, d, dp: dict, dM: dict, P: int, shapes, ops, fused, logged, unlogged,
                 n_stages: int):
        self.dp, self.dM, self.P, self.N = dp, dM, P, d.n_states
        self.seeds: dict = {}             # leaf node number -> {direction: node}
        self._moving: dict = {}           # (id(group op), i, j) -> its leaf
        self.sens_columns: list = []
        #: (column of W, its leaf's node number, where its value comes from): the entries
        #: that move and their seeds (a column shared by equal entries: one row each),
        #: ("p", block, name, entry) / ("dp", block, name, entry, direction) / ("M", op,
        #: i, j) / ("dM", op, i, j, direction), op the group's position in the ops
        #: (``rebound``)
        self.bindings: list = []
        self._seeds_by_value: dict = {}
        self._moving_by_value: dict = {}
        self._column_of: dict = {}        # leaf node number -> its column of W
        self._position = {id(op): k for k, (_, op, _) in enumerate(ops)}
        super().__init__(d, shapes, ops, fused, d.constant_signals, logged, unlogged,
                         n_stages)

    def _column(self, values, source):
        """A run-time value of its own: a column of W (never folded into a constant nor
        shared with an equal entry), whose value comes from ``source`` (``bindings``)."""
        values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if len(self.columns) >= backend_numba.MAX_SCALAR_PARAMS:
            raise sz.Untraceable(f"more than {backend_numba.MAX_SCALAR_PARAMS} parameter "
                                 "entries")
        j = len(self.columns)
        self.columns.append(values)
        node = self.tr.leaf(f"p{j}", True, values)
        self._column_of[node.n] = j
        self.bindings.append((j, node.n, source))
        return node

    def _bind(self, node, source) -> None:
        """Another entry whose value is that of the column ``node`` (``rebound`` checks
        that it still is)."""
        self.bindings.append((self._column_of[node.n], node.n, source))

    def _seed(self, value: float, source):
        """A seed (an entry of dp or dM): a run-time value too (not a constant written
        into the code), so another value of the parameter runs the same machine code;
        seeds equal to each other are one column (as ``_leaf`` shares equal entries: their
        products are then one node), ``rebound`` checks that they still are."""
        values = np.array([value], dtype=np.float64)
        node = self._seeds_by_value.get(values.tobytes())
        if node is None:
            node = self._seeds_by_value[values.tobytes()] = self._column(values, source)
        else:
            self._bind(node, source)
        return node

    def _moving_leaf(self, values, tangent, source):
        """A parameter entry that moves: a column of W, seeded; entries equal to each other
        with equal seeds are one column (as ``_leaf`` shares equal entries: a fused matrix
        repeats a coefficient per joint, and its products are then shared too)."""
        values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        tangent = np.ascontiguousarray(tangent, dtype=np.float64)
        key = values.tobytes() + tangent.tobytes()
        seeds = [(c, ("d" + source[0],) + source[1:] + (c,)) for c in range(self.P)
                 if tangent[c] != 0.0]
        node = self._moving_by_value.get(key)
        if node is not None and not np.isnan(values).any():
            self._bind(node, source)
            for c, src in seeds:
                self._bind(self.seeds[node.n][c], src)
            return node
        node = self._moving_by_value[key] = self._column(values, source)
        self.seeds[node.n] = {c: self._seed(tangent[c], src) for c, src in seeds}
        return node

    def _kernel_param(self, blk, name: str):
        g = self.dp.get((blk.name, name))
        if g is None:
            return super()._kernel_param(blk, name)
        arr = np.asarray(getattr(blk.p, name), dtype=np.float64)
        out = np.empty((1,) + arr.shape[1:], dtype=object)
        for k, idx in enumerate(np.ndindex(*arr.shape[1:])):
            values = arr[(slice(None),) + idx]
            out[(0,) + idx] = (self._moving_leaf(values, g[k], ("p", blk.name, name, k))
                               if g[k].any() else self._leaf(values))
        return out

    def _group_mask(self, op, M):
        mask = super()._group_mask(op, M)
        dm = self.dM.get(id(op))
        return mask if dm is None else mask | np.any(dm != 0.0, axis=0)

    def _group_entry(self, op, M, i: int, j: int):
        dm = self.dM.get(id(op))
        if dm is None or not dm[:, i, j].any():
            return super()._group_entry(op, M, i, j)
        key = (id(op), i, j)
        if key not in self._moving:
            self._moving[key] = self._moving_leaf(M[:, i, j], dm[:, i, j],
                                                  ("M", self._position[id(op)], i, j))
        return self._moving[key]

    def rebound(self, d, dp: dict, ops, dM: dict):
        """This stage for other values of the moving entries and their seeds (the same
        structure, unmoved values and zero patterns: ``variational_stage``'s key): a copy
        sharing the graph and the machine code, with W's columns of ``bindings`` taken from
        ``d``'s blocks, ``ops``' fused matrices, ``dp`` and ``dM``; None when a number
        the code was written for changes with them (``Trace.decisions``: trace again)."""
        blocks = {blk.name: blk for blk in d.blocks}
        W = self.W.copy()
        leaves = {}
        for j, n, src in self.bindings:
            kind = src[0]
            if kind == "p":
                arr = np.asarray(getattr(blocks[src[1]].p, src[2]), dtype=np.float64)
                v = arr.reshape(arr.shape[0], -1)[:, src[3]]
            elif kind == "dp":
                v = np.array([dp[(src[1], src[2])][src[3], src[4]]])
            elif kind == "M":
                v = np.asarray(ops[src[1]][1].M, dtype=np.float64)[:, src[2], src[3]]
            else:
                v = np.array([dM[id(ops[src[1]][1])][src[4], src[2], src[3]]])
            if v.size != len(self.columns[j]):
                return None
            if n in leaves:               # a column shared by equal entries: still equal?
                if not np.array_equal(v, leaves[n]):
                    return None
                continue
            W[:v.size, j] = v
            leaves[n] = v
        if not self.tr.decisions_hold(leaves):
            return None
        new = copy.copy(self)
        new.W, new.dp, new.dM = W, dp, dM
        new.columns = [W[:len(c), j] for j, c in enumerate(self.columns)]
        return new

    def _extend(self, x, sig, logs, shapes, roots) -> None:
        tr, N, P = self.tr, self.N, self.P
        # every node made from here on is a tangent's (the diagram's own are all made):
        # their products and sums may be fused multiply-adds (fwdstep.compiled.llvm_ir)
        self.contract_from = len(tr.nodes)
        tr.max_nodes = max(tr.max_nodes, MAX_NODES)
        for i in range(N):
            self.seeds[x[0, i].n] = {c: tr.leaf(f"x{N + i * P + c}", False)
                                     for c in range(P)}
        logged = [sig[idx].reshape(-1) for idx in logs]
        primal = list(self.der)
        tangents = directional_tangents(
            tr, [node for _, node in primal] + [n for nodes in logged for n in nodes],
            self.seeds)
        zero = tr.const(0.0)
        self.der = primal + [(N + i * P + c, t.get(c, zero))
                             for (i, _), t in zip(primal, tangents) for c in range(P)]
        col, k = self.log_width, len(primal)
        for nodes in logged:
            self.sens_columns.append(col)
            for _ in nodes:
                t = tangents[k]
                k += 1
                for c in range(P):
                    node = t.get(c, zero)
                    self.records.append((col, node))
                    roots.append(node)
                    col += 1
        self.log_width = col
        self.contract_to = len(tr.nodes)      # (the guards, if any, come after: not fused)

    def _total_states(self, d) -> int:
        return d.n_states * (1 + self.P)


def group_derivatives(d, ops, shapes, dp: dict, P: int, fused=None) -> dict:
    """d M / d column for every fused group whose blocks move: id(op) -> (P, rows, cols),
    Richardson central differences of the fusion of the moved blocks (module docstring).
    ``fused``: the names of the blocks in groups (``_ops_for``'s); a column that moves
    none of them is not differenced (its dM is 0)."""
    groups = [(k, op) for k, (kind, op, _) in enumerate(ops) if kind == "group"]
    by_block: dict = {}
    for (blk, name), g in dp.items():
        if fused is None or blk in fused:
            by_block.setdefault(blk, {})[name] = g
    if not groups or not by_block:
        return {}
    out = {id(op): np.zeros((P,) + np.shape(op.M)[1:]) for _, op in groups}
    moves, steps = [], []     # every (column, offset) is a variant of one batched fusion
    for c in range(P):
        scale = max(float(np.max(np.abs(g[:, c]))) for m in by_block.values()
                    for g in m.values())
        if scale == 0.0:
            continue
        size = max([float(np.max(np.abs(getattr(st.block.p, n)))) for st in d.schedule
                    if st.block.name in by_block for n in by_block[st.block.name]] + [1.0])
        h = DIFFERENCE_STEP * size / scale
        moves += [(c, off * h) for off in OFFSETS]
        steps.append((c, h))
    if not moves:
        return {}

    def fused(variants):
        """The groups' M with the moved blocks' variants ``variants`` (a batch), or None
        when the fusion is not the diagram's (a batch too large to fuse, say)."""
        schedule = [dataclasses.replace(st, block=moved_variants(
            st.block, by_block[st.block.name], variants))
            if st.block.name in by_block else st for st in d.schedule]
        moved, _ = backend_numba._ops_for(schedule, shapes, d.constant_signals)
        if [kind for kind, _, _ in moved] != [kind for kind, _, _ in ops] or any(
                np.shape(moved[k][1].M)[1:] != np.shape(op.M)[1:] for k, op in groups):
            return None
        return [np.broadcast_to(np.asarray(moved[k][1].M, dtype=float),
                                (len(variants),) + np.shape(op.M)[1:]) for k, op in groups]

    Ms = fused(moves)
    if Ms is None:                    # one move at a time
        each = [fused([m]) for m in moves]
        if any(m is None for m in each):
            raise sz.Untraceable("the fusion of the linear blocks changes with the parameter")
        Ms = [np.concatenate([m[g] for m in each]) for g in range(len(groups))]
    n = len(OFFSETS)
    for (_, op), M in zip(groups, Ms):
        for q, (c, h) in enumerate(steps):
            out[id(op)][c] = richardson(M[q * n:(q + 1) * n], h)
    return {key: dm for key, dm in out.items() if dm.any()}


def _check_calls(ops, dp: dict) -> None:
    """A moved p array a kernel does not take as an argument must not change what it
    computes (its static values): else the stage cannot be differentiated here."""
    for kind, op, _ in ops:
        if kind != "call" or op.block.kernels is None:
            continue
        blk = op.block
        others = {name: g for (b, name), g in dp.items()
                  if b == blk.name and name not in blk.kernels.params}
        if not others:
            continue
        for c in range(next(iter(others.values())).shape[1]):
            probe = moved_block(blk, others, c, 1e-3)
            same = len(probe.kernels.static) == len(blk.kernels.static) and all(
                np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                zip(probe.kernels.static, blk.kernels.static))
            if not same:
                raise sz.Untraceable(f"parameter '{next(iter(others))}' of block "
                                     f"'{blk.name}' reaches its kernels other than as an "
                                     "argument")


#: traced variational stages by ``variational_stage``'s key: (the kernels the key names
#: by id, held so that their ids are not reused; the stage)
_STAGES: dict = {}
#: how many the memo keeps (a stage holds its graph: a few MB for the Panda)
MAX_STAGES = 16


def variational_stage(d, dp: dict, P: int) -> VariationalStage:
    """The compiled-backend stage of ``d`` with its tangents; ``Untraceable`` when not.
    Memoised in the process by everything the trace reads EXCEPT the values of the entries
    that move and of their seeds (run-time values of their own: ``VariationalStage._column``):
    the structure, the kernels and their statics, the unmoved values, which entries move
    and the zero patterns of dp and dM.  A tuning's next evaluation (another value) then
    reuses the graph and the machine code with W's moving columns rebound
    (``VariationalStage.rebound``), unless a number the code was written for moves with
    them (then it is traced again)."""
    # (kept for build_program's next call, which runs this stage)
    shapes, ops, fused = backend_numba._diagram_ops(d, keep=True)
    _check_calls(ops, dp)
    dM = group_derivatives(d, ops, shapes, dp, P, fused)
    from fwdstep.run.finite import unlogged_signals
    logged = [d.signal_index[name] for name in d.logged]
    unlogged = unlogged_signals(d)
    S = TABLEAUX[d.spec.simulation.solver].stages
    moving_p = {key: np.any(g != 0.0, axis=1) for key, g in dp.items()}
    moving_M = {key: np.any(dm != 0.0, axis=0) for key, dm in dM.items()}
    h, held = backend_numba.stage_key(d, shapes, ops, fused, logged, unlogged, S, moving_p,
                                      moving_M)
    h.update(repr(("variational", P)).encode())
    for (blk, name), g in sorted(dp.items()):
        h.update(repr((blk, name, g.shape)).encode() + np.ascontiguousarray(g != 0.0).data)
    for k, (_, op, _) in enumerate(ops):
        if id(op) in dM:
            h.update(repr(("dM", k)).encode() + np.ascontiguousarray(dM[id(op)] != 0.0).data)
    key = h.digest()
    got = _STAGES.get(key)
    if got is not None:
        st = got[1].rebound(d, dp, ops, dM)
        if st is not None:
            return st
    st = VariationalStage(d, dp, dM, P, shapes, ops, fused, logged, unlogged, S)
    _STAGES.pop(key, None)
    _STAGES[key] = (held, st)
    while len(_STAGES) > MAX_STAGES:
        _STAGES.pop(next(iter(_STAGES)))
    return st


class SensitivityBackend(CompiledBackend):
    """The compiled backend integrating (x, S) (``VariationalStage``); ``x`` is the view of
    the diagram's state, S starts at ``S0`` (N, P)."""

    def __init__(self, d, plan, stage: VariationalStage, S0, on_compile=None):
        super().__init__(d, plan, on_compile, stage=stage)
        self.stage, self.S0 = stage, np.asarray(S0, dtype=float)

    def start(self, x0) -> None:
        super().start(x0)
        self.prog.xn[:, self.d.n_states:] = self.S0.reshape(1, -1)

    def sensitivities(self, rows: int) -> dict:
        """Logged signal -> its sensitivities (rows, size, P) from the compiled log."""
        st, P = self.stage, self.stage.P
        LL = self.prog.call_logs[0].reshape(-1, self.d.batch, max(st.log_width, 1))
        out = {}
        for name, col in zip(self.d.logged, st.sens_columns):
            size = int(np.prod(self.d.signal_shapes[self.d.signal_index[name]],
                               dtype=np.int64))
            out[name] = LL[:rows, 0, col:col + size * P].reshape(rows, size, P).copy()
        return out


def not_compiled(d) -> str | None:
    """Why the compiled backend cannot integrate ``d``'s sensitivities (before tracing; a
    block the compiled backend refuses is refused here)."""
    from fwdstep.run.crossings import crossing_steps
    from fwdstep.run.events import plan_events
    located = crossing_steps(d)
    if located:
        blk = located[0].block
        return f"block '{blk.name}' ({blk.type_name}) has zero crossings"
    cfg = d.spec.simulation
    plan = plan_events(d, cfg.step, cfg.n_steps)
    if plan is not None and (plan.discrete or (plan.final is not None and plan.final.updates)):
        return "discrete blocks update at sample instants"
    backend_numba.check_compilable(d)
    return None


def run_compiled(d, dp: dict, P: int, S0, progress=None, on_compile=None,
                 max_log_bytes=None):
    """Run ``d`` and its sensitivities on the compiled backend: (Result, signal ->
    (rows, size, P)), or the reason (one line) why they are not compiled."""
    from fwdstep.core.budgets import check_log
    from fwdstep.run.events import plan_events
    from fwdstep.run.simulate import run
    check_log(d, max_log_bytes, api=True)
    wall0 = _time.perf_counter()
    reason = not_compiled(d)
    if reason is not None:
        return reason
    cfg = d.spec.simulation
    try:
        stage = variational_stage(d, dp, P)
        backend = SensitivityBackend(d, plan_events(d, cfg.step, cfg.n_steps), stage, S0,
                                     on_compile)
    except sz.Untraceable as exc:
        # (asked only now: whether the diagram's own stage traces costs a trace)
        return numpy_instead(d) or f"its variational stage is not compiled ({exc})"
    r = run(d, backend, progress, None, wall0)
    r.backend = "compiled"
    return r, backend.sensitivities(len(r.t))


__all__ = ["VariationalStage", "SensitivityBackend", "variational_stage", "run_compiled",
           "group_derivatives", "not_compiled"]
