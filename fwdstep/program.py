"""Compile once, run lean: a compiled diagram as straight-line step functions.

``build_program`` turns the schedule into Python source with one line per block call, in
evaluation order, and ``exec``s it once per run.  The source is made only of names this
module invents (``s12``, ``out_3``, ``kv1_3``) and of the objects bound to them; no diagram
text ever reaches it (the same technique as ``collections.namedtuple`` and
``dataclasses``).  What the generic loop did on every stage is done here once:

* every signal is a local variable (no signal list, no index lookups, no tuple building
  beyond the block's input tuple);
* each block's slice of the stage state and of each stage's derivative buffer is a view
  made once (the stage state is one preallocated buffer, written in place);
* the bound methods ``block.output`` / ``block.derivative`` are looked up once;
* linear blocks are fused (``fwdstep.linear.plan_fusion``): every group of linear signals
  that becomes computable at the same point is one matrix product into a preallocated
  buffer whose column views *are* the signals, and all fused states' derivatives are one
  product at the end of the stage;
* the RK stage sums are in-place NumPy operations on preallocated buffers, in the same
  order as the reference stepper (so the unfused program is bit-identical to it).

The procedure is the one documented in ``fwdstep.simulate``: each block output evaluated
exactly once per stage, derivatives after all outputs, logging at stage 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .linear import FusionPlan, LinearGroup, plan_fusion
from .solvers import TABLEAUX, step_plan


@dataclass
class Program:
    """Per-run buffers and the generated functions.

    ``first(t)`` / ``first_record(t, row)``: stage 1 at (t, xn) (the latter also records the
    logged signals in row ``row``); ``rest(t)``: stages 2..s and the update of ``xn``;
    ``final(t, row)``: outputs at (t, xn) and a record (the final time)."""
    xn: np.ndarray
    logs: list
    t_log: np.ndarray
    first: object
    first_record: object
    rest: object
    final: object
    plan: FusionPlan | None
    source: str


class _Source:
    def __init__(self):
        self.lines: list = []
        self.ns: dict = {}
        self._n = 0

    def const(self, prefix: str, value) -> str:
        self._n += 1
        name = f"{prefix}{self._n}"
        self.ns[name] = value
        return name

    def emit(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)


def build_program(d, n_rows: int, fuse: bool = True) -> Program:
    """Generate the run functions of compiled diagram ``d`` with ``n_rows`` log rows."""
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    stages, final_coeffs = step_plan(tab, cfg.step)
    B, N = d.batch, d.n_states
    S = tab.stages

    xn = np.zeros((B, N))
    X = np.zeros((B, N))          # the stage state x_i
    T = np.zeros((B, N))          # scratch for a * k_j
    K = np.zeros((S, B, N))
    src = _Source()
    ns = src.ns
    ns.update(xn=xn, X=X, T=T, multiply=np.multiply, add=np.add, dot=np.dot, matmul=np.matmul)
    for s in range(S):
        ns[f"K{s}"] = K[s]
    empty = X[:, 0:0]

    plan = plan_fusion(d.schedule, d.signal_shapes, d.constant_signals) if fuse else None
    if plan is None:
        ops = [("call", step) for step in d.schedule]
        called_stateful = list(d.stateful)
    else:
        ops = plan.ops
        called_stateful = [s for s in d.stateful if s.block.name not in plan.fused]

    # ---------------------------------------------------------------- names of signals
    shapes = [tuple(sh) for sh in d.signal_shapes]
    name: dict = {}
    for idx, arr in d.constant_signals.items():
        name[idx] = src.const("zero", arr)
    producer_call: dict = {}
    call_names: dict = {}          # id(step) -> (output method, state view) names
    for kind, op in ops:
        if kind == "call":
            for idx in op.outputs:
                producer_call[idx] = op
                name[idx] = f"s{idx}"
            call_names[id(op)] = (src.const("out_", op.block.output),
                                  src.const("xv_", X[:, op.state] if op.state is not None
                                            else empty))
    group_code: list = []
    derivative_group = None        # (LinearGroup, its buffer's dx view or None)
    for kind, op in ops:
        if kind != "group":
            continue
        if op.derivative and not op.outputs:      # product straight into each k_i
            derivative_group = (op, None)
            continue
        lines, dx_view = _group(src, op, B, X, name, shapes, plan)
        group_code.append(lines)
        if op.derivative:
            derivative_group = (op, dx_view)
    # signals read before their producer ran in this stage (inputs that are not
    # feedthrough): keep them in a cell that holds the previous stage's value
    stale: set = set()
    done: set = set(d.constant_signals)
    for kind, op in ops:
        if kind == "call":
            for u in op.inputs:
                if u not in done and u in producer_call:
                    stale.add(u)
            done.update(op.outputs)
        else:
            done.update(idx for idx, _ in op.outputs)
    cell = [None] * len(d.signal_names)
    ns["S"] = cell

    def read(u):
        return f"S[{u}]" if u in stale else name[u]

    # ---------------------------------------------------------------- output pass
    out_lines: list = []
    groups = iter(group_code)
    for kind, op in ops:
        if kind == "group":
            if op.outputs:
                out_lines.extend(next(groups))
            continue
        fn, xv = call_names[id(op)]
        args = ", ".join(read(u) for u in op.inputs)
        args = f"({args},)" if len(op.inputs) == 1 else f"({args})"
        call = f"{fn}(ts, {xv}, {args})"
        if len(op.outputs) == 1:
            out_lines.append(f"{name[op.outputs[0]]} = {call}[0]")
        else:
            out_lines.append(f"r = {call}")
            for k, idx in enumerate(op.outputs):
                out_lines.append(f"{name[idx]} = r[{k}]")
        for idx in op.outputs:
            if idx in stale:
                out_lines.append(f"S[{idx}] = {name[idx]}")

    # ---------------------------------------------------------------- derivative pass
    def derivative_lines(s: int) -> list:
        lines = []
        for step in called_stateful:
            kv = src.const(f"kv{s}_", K[s][:, step.state])
            fn = src.const("der_", step.block.derivative)
            args = ", ".join(read(u) for u in step.inputs)
            args = f"({args},)" if len(step.inputs) == 1 else f"({args})"
            xv = src.const("xv_", X[:, step.state])
            lines.append(f"{kv}[...] = {fn}(ts, {xv}, {args})")
        if derivative_group is not None:
            group, dx_view = derivative_group
            kv = K[s][:, plan.state]
            if dx_view is None:
                lines.extend(_product(src, group, B, X, name, shapes, plan, kv))
            else:
                lines.append(f"{src.const('kvlin', kv)}[...] = {src.const('dx', dx_view)}")
        return lines

    # ---------------------------------------------------------------- logging
    logs, record_lines = [], []
    t_log = np.empty(n_rows)
    ns["t_log"] = t_log
    for sig_name in d.logged:
        idx = d.signal_index[sig_name]
        arr = np.full((n_rows, B) + tuple(d.signal_shapes[idx]), np.nan)
        logs.append(arr)
        record_lines.append(f"{src.const('log_', arr)}[row] = {read(idx)}")
    record_lines.insert(0, "t_log[row] = t")

    # ---------------------------------------------------------------- functions
    def function(header: str, body: list) -> None:
        src.emit(0, header)
        for line in body or ["pass"]:
            src.emit(1, line)
        src.emit(0, "")

    stage1 = ["X[...] = xn", "ts = t"] + out_lines
    function("def first(t):", stage1 + derivative_lines(0))
    function("def first_record(t, row):", stage1 + record_lines + derivative_lines(0))
    rest = []
    for s, (ch, coeffs) in enumerate(stages, start=1):
        # x_i = x_n + sum_j a_ij k_j, summed in the reference stepper's order
        if coeffs:
            j, a = coeffs[0]
            rest.append(f"multiply(K{j}, {src.const('a', a)}, out=X)")
            rest.append("add(X, xn, out=X)")
        else:
            rest.append("X[...] = xn")
        for j, a in coeffs[1:]:
            rest.append(f"multiply(K{j}, {src.const('a', a)}, out=T)")
            rest.append("add(X, T, out=X)")
        rest.append(f"ts = t + {src.const('c', ch)}")
        rest.extend(out_lines)
        rest.extend(derivative_lines(s))
    for j, b in final_coeffs:
        rest.append(f"multiply(K{j}, {src.const('b', b)}, out=T)")
        rest.append("add(xn, T, out=xn)")
    function("def rest(t):", rest)
    function("def final(t, row):", ["X[...] = xn", "ts = t"] + out_lines + record_lines)

    source = "\n".join(src.lines)
    exec(compile(source, f"<fwdstep program for {d.file}>", "exec"), ns)  # noqa: S102
    return Program(xn=xn, logs=logs, t_log=t_log, first=ns["first"],
                   first_record=ns["first_record"], rest=ns["rest"], final=ns["final"],
                   plan=plan, source=source)


def _group(src: _Source, group: LinearGroup, B: int, X, name: dict, shapes: list,
           plan) -> list:
    """Code of one fused output group; its outputs become fixed views of its buffer."""
    n_out = group.M.shape[2]
    Y = np.zeros((B, n_out))
    lines = _product(src, group, B, X, name, shapes, plan, Y)
    c = 0
    for idx, n in group.outputs:
        name[idx] = src.const(f"y{idx}_", _view(Y[:, c:c + n], (B,) + shapes[idx]))
        c += n
    return lines, (Y[:, c:] if group.derivative else None)


def _product(src: _Source, group: LinearGroup, B: int, X, name: dict, shapes: list, plan,
             out) -> list:
    """Lines filling the group's input buffer and writing ``[inputs] @ M`` into ``out``."""
    n_in = sum(n for _, n in group.inputs)
    lines = []
    if n_in == 0:                      # every output is identically zero
        return lines
    V = np.zeros((B, n_in))
    c = 0
    for term, n in group.inputs:
        if term == "x":
            xv = src.const("xlin", X[:, plan.state])
            lines.append(f"{src.const('v', V[:, c:c + n])}[...] = {xv}")
        else:
            view = _view(V[:, c:c + n], (B,) + shapes[term])
            lines.append(f"{src.const('v', view)}[...] = {name[term]}")
        c += n
    M = group.M
    if M.shape[0] == 1 and out.flags.c_contiguous:
        lines.append(f"dot({src.const('V', V)}, {src.const('M', M[0])}, "
                     f"out={src.const('Y', out)})")
    elif M.shape[0] == 1:
        lines.append(f"matmul({src.const('V', V)}, {src.const('M', M[0])}, "
                     f"out={src.const('Y', out)})")
    else:
        lines.append(f"matmul({src.const('V', V[:, None, :])}, {src.const('M', M)}, "
                     f"out={src.const('Y', out[:, None, :])})")
    return lines


def _view(arr: np.ndarray, shape: tuple) -> np.ndarray:
    """``arr`` reshaped without copying (raises if that is impossible)."""
    v = arr.view()
    v.shape = shape
    return v
