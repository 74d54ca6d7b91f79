"""Compile once, run lean: a compiled diagram as straight-line step functions.

``build_program`` turns the schedule into Python source with one line per block call, in
evaluation order, and ``exec``s it once per run.  The source is made only of names this
module invents (``s12``, ``out3``, ``k1_7``) and of the objects bound to them; no diagram
text ever reaches it (the same technique as ``collections.namedtuple`` and
``dataclasses``).  What the generic loop did on every stage is done here once:

* every signal is a local variable (no signal list, no index lookups, no tuple building
  beyond the block's input tuple);
* each block's slice of the stage state and of each stage's derivative buffer is a view
  made once (the stage state is one preallocated buffer, written in place; stage 1 reads
  x_n itself);
* the bound methods ``block.output`` / ``block.derivative`` are looked up once;
* linear blocks are fused (``fwdstep.core.linear.plan_fusion``): every group of linear signals
  that becomes computable at the same point is one matrix product into a preallocated
  buffer whose column views *are* the signals, and all fused states' derivatives are more
  columns of such a product (or one product at the end of the stage);
* the RK stage sums are in-place NumPy operations on preallocated buffers, in the same
  order as the reference stepper (so the unfused program is bit-identical to it);
* a large batch's two-column signals are copied into wider buffers as one 16-byte item per
  pair (``_put_pairs``), which NumPy does in one loop instead of one per row.

The procedure is the one documented in ``fwdstep.simulate``: each block output evaluated
exactly once per stage, derivatives after all outputs, logging at stage 1.
"""
from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass

import numpy as np

from fwdstep.core.block import Block
from fwdstep.core.linear import FusionPlan, LinearGroup, plan_fusion
from fwdstep.core.solvers import TABLEAUX, step_plan


_F8 = np.dtype(np.float64)
_PAIR = np.dtype((np.void, 16))
#: below this many rows the plain copy is as fast (measured: equal at 64, 2x at 256)
PAIR_COPY_MIN_ROWS = 64


def _put_pairs(pairs: np.ndarray, dst: np.ndarray, value) -> None:
    """``dst[...] = value`` where ``dst``'s last axis holds two float64 and ``pairs`` is the
    same memory seen as one 16-byte item per pair.  NumPy copies an array row by row along
    the destination's last axis, so (B, 2) into columns of a wider buffer costs B calls of
    its inner loop; as items it is one strided loop of B.  Any other value (another dtype
    or layout, broadcasting along that axis, a wrong shape) takes the plain assignment,
    which also raises the plain error."""
    try:
        if value.dtype is _F8 and value.ndim == pairs.ndim and value.shape[-1] == 2:
            pairs[...] = value.view(_PAIR)
            return
    except (AttributeError, ValueError):
        pass
    dst[...] = value


@dataclass
class Program:
    """Per-run buffers and the generated functions.

    ``first(t)`` / ``first_record(t, row)``: stage 1 at (t, xn) (the latter also records the
    logged signals in row ``row``); ``rest(t)``: stages 2..s and the update of ``xn``;
    ``final(t, row)``: outputs at (t, xn) and a record (the final time).
    ``first_ts``, ``first_record_ts``, ``final_ts``: the same with the stage time ``ts``
    given apart from the recorded time ``t``; ``rest_h(t, h, lo, hi)``: stages 2..s of a
    step of size h with stage times clamped to [lo, hi] (steps at discontinuities)."""
    xn: np.ndarray
    logs: list
    t_log: np.ndarray
    first: object
    first_record: object
    rest: object
    final: object
    plan: FusionPlan | None
    source: str
    first_ts: object = None
    first_record_ts: object = None
    final_ts: object = None
    rest_h: object = None
    sample_signals: object = None
    k: np.ndarray | None = None    # the stage derivatives k_i, (s, B, N); first_ts fills k[0]
    G: np.ndarray | None = None    # zero-crossing guards at the last stage 1 (``crossings``)


class _Source:
    """The generated lines and the namespace binding every name they use."""

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

    def copy(self, prefix: str, dst: np.ndarray, value: str) -> str:
        """The line ``dst[...] = value`` (``value`` an expression of the generated code).
        A batch's two-column destinations (a joint pair, the commonest signal) are copied
        through ``_put_pairs`` instead: 2x faster at B = 256, the same numbers (a copy)."""
        name = self.const(prefix, dst)
        if (dst.ndim >= 2 and dst.shape[-1] == 2 and dst.strides[-1] == 8
                and dst.dtype == _F8 and dst.size >= 2 * PAIR_COPY_MIN_ROWS):
            pairs = self.const(prefix + "p", dst.view(_PAIR))
            return f"put_pairs({pairs}, {name}, {value})"
        return f"{name}[...] = {value}"


def build_program(d, n_rows: int, fuse: bool = True, alloc=None, sampled: tuple = (),
                  solver: str | None = None, probe=None, crossings: tuple = ()) -> Program:
    """Generate the run functions of compiled diagram ``d`` with ``n_rows`` log rows.
    ``alloc(shape)`` makes each log array (default: in memory, NaN-filled;
    ``fwdstep.core.budgets.disk_allocator`` streams the log to disk).  ``sampled``: the signal
    indices ``sample_signals(ts)`` returns (inputs of discrete blocks, fwdstep.run.events).
    ``solver``: the tableau, if not ``simulation.solver`` (fwdstep.run.ivp uses stage 1 only).
    ``probe``: (signal indices, (B, total size) buffer): every record also copies those
    signals into the buffer (``fwdstep.run.finite`` checks the unrecorded outputs there).
    ``crossings``: compiled steps of blocks with zero-crossing functions; every stage 1 (and
    final pass) writes their guards into ``Program.G`` (``fwdstep.run.crossings``)."""
    cfg = d.spec.simulation
    tab = TABLEAUX[solver or cfg.solver]
    stages, final_coeffs = step_plan(tab, cfg.step)
    B, N = d.batch, d.n_states
    S = tab.stages

    xn = np.zeros((B, N))         # x_n, updated in place at the end of each step
    X = np.zeros((B, N))          # the stage state x_i, i >= 2 (stage 1 reads x_n itself)
    T = np.zeros((B, N))          # scratch for a * k_j
    K = np.zeros((S, B, N))
    src = _Source()
    ns = src.ns
    ns.update(xn=xn, X=X, T=T, multiply=np.multiply, add=np.add, dot=np.dot, matmul=np.matmul,
              put_pairs=_put_pairs)
    for s in range(S):
        ns[f"K{s}"] = K[s]

    # the signals a stage needs when it records nothing: what the derivatives, the guards
    # and the discrete blocks read, and what those are computed from.  The blocks producing
    # none of them (stateless blocks whose outputs are only logged, e.g. an error signal
    # for a plot) run at the recorded stage 1 only: after the others, unfused, every
    # ``log_every`` steps instead of every stage.
    needed, live = _needed_signals(d, sampled, crossings)
    stage_schedule = [st for st in d.schedule if id(st) in live]
    plan = (plan_fusion(stage_schedule, d.signal_shapes, d.constant_signals) if fuse
            else None)
    if plan is None:
        ops = [("call", step) for step in stage_schedule]
        called_stateful = list(d.stateful)
    else:
        ops = plan.ops
        called_stateful = [s for s in d.stateful if s.block.name not in plan.fused]
    record_ops = ops + [("call", st) for st in d.schedule if id(st) not in live]

    def state_view(buffer, sl):
        """Name of the constant view of a block's state in ``buffer`` (made once)."""
        key = (id(buffer), None if sl is None else (sl.start, sl.stop))
        if key not in views:
            views[key] = src.const("xv", buffer[:, sl] if sl is not None else buffer[:, 0:0])
        return views[key]

    views: dict = {}
    # ---------------------------------------------------------------- signal names
    shapes = [tuple(sh) for sh in d.signal_shapes]
    name: dict = {}
    for idx, arr in d.constant_signals.items():
        name[idx] = src.const("zero", arr)
    producer_call: dict = {}
    for kind, op in record_ops:
        if kind == "call":
            for idx in op.outputs:
                producer_call[idx] = op
                name[idx] = f"s{idx}"
    groups = {}                    # id(LinearGroup) -> _GroupBuffers
    derivative_group = None
    for kind, op in ops:
        if kind == "group":
            groups[id(op)] = _GroupBuffers(src, op, B, shapes, name)
            if op.derivative:
                derivative_group = op
    # signals read before their producer ran in this stage (inputs that are not
    # feedthrough): kept in a cell that holds the previous stage's value
    stale: set = set()
    done: set = set(d.constant_signals)
    for kind, op in record_ops:
        if kind == "call":
            stale.update(u for u in op.inputs if u not in done and u in producer_call)
            done.update(op.outputs)
        else:
            done.update(idx for idx, _ in op.outputs)
    ns["S"] = [None] * len(d.signal_names)

    def read(u):
        return f"S[{u}]" if u in stale else name[u]

    def args(inputs) -> str:
        text = ", ".join(read(u) for u in inputs)
        return f"({text},)" if len(inputs) == 1 else f"({text})"

    # ---------------------------------------------------------------- one stage
    kargs: dict = {}

    def kernel_call(block, fn, xview: str, inputs) -> str:
        """A direct call of kernel ``fn`` of ``block``: what ``Block.output`` /
        ``Block.derivative`` do, with the parameter arguments bound once per run (they
        are fixed during a run) instead of gathered on every call."""
        k = block.kernels
        if id(block) not in kargs:
            kargs[id(block)] = "".join(", " + src.const("p", a) for a in block.kernel_args())
        ins = args(inputs) if k.tuple_inputs else "".join(", " + read(u) for u in inputs)
        if k.tuple_inputs:
            ins = ", " + ins
        return f"{src.const('kern', fn)}(ts, {xview}{ins}{kargs[id(block)]})"

    native = native_methods(d)

    def method(block, name: str):
        """The callable of ``block.<name>``: its native kernel when there is one."""
        return native.get(id(block), {}).get(name) or getattr(block, name)

    def direct(block, method: str) -> bool:
        """True when ``block``'s ``method`` is the base class's kernel call (not overridden
        by its class or wrapped on the instance, not run natively)."""
        k = block.kernels
        return (getattr(type(block), method) is getattr(Block, method) and k is not None
                and method not in native.get(id(block), {})
                and method not in block.__dict__ and getattr(k, method) is not None)

    cells: dict = {}

    def held() -> dict:
        """Input signal -> memo cell of the time-only block producing it, for the blocks
        whose cell exists (their value is reused while the stage time is unchanged)."""
        return {idx: cells[id(op.block)] for idx, op in producer_call.items()
                if id(op.block) in cells}

    def time_only(block) -> bool:
        """No inputs, no states: the outputs are a function of t alone (kernels are pure)."""
        return not block.inputs and not block.n_states

    def memo(block, target: str, call: str) -> list:
        """``target = call``, reusing the last value when the stage time has not changed
        (RK4's stages 2 and 3 share t + h/2): a time-only block is evaluated twice per
        step instead of four times, with the same numbers."""
        if not time_only(block):
            return [f"{target} = {call}"]
        if id(block) not in cells:            # one cell per block: every stage function
            cells[id(block)] = src.const("memo", [math.nan, None])
        cell = cells[id(block)]
        return [f"if {cell}[0] != ts:", f"    {cell}[1] = {call}", f"    {cell}[0] = ts",
                f"{target} = {cell}[1]"]

    def output_pass(buffer, record: bool = False) -> list:
        """Every block output at the stage (``record``: for the log and the probe too; else
        the needed ones only, see ``_needed_signals``)."""
        bound = None if record else needed | stale

        def binds(idx) -> bool:
            return bound is None or idx in bound

        lines = []
        for kind, op in (record_ops if record else ops):
            if kind == "group":
                g = groups[id(op)]
                if op.outputs:
                    lines.extend(g.code(src, buffer, plan, read, g.Y, held()))
                continue
            blk = op.block
            if direct(blk, "output") and blk.kernels.packed:
                call = kernel_call(blk, blk.kernels.output, state_view(buffer, op.state),
                                   op.inputs)
                unpack = [f"r[:, {a}:{b}]" if shape is None else
                          f"r[:, {a}:{b}].reshape((r.shape[0],) + "
                          f"{src.const('shape', shape)})" for a, b, shape in blk._unpack]
                if time_only(blk):
                    # the outputs sliced once per new stage time, with the packed value
                    if id(blk) not in cells:
                        cells[id(blk)] = src.const("memo", [math.nan, None, None])
                    cell = cells[id(blk)]
                    lines += [f"if {cell}[0] != ts:", f"    r = {call}", f"    {cell}[1] = r",
                              f"    {cell}[2] = ({', '.join(unpack)},)", f"    {cell}[0] = ts",
                              f"{', '.join(name[idx] for idx in op.outputs)}, = {cell}[2]"]
                else:
                    lines.append(f"r = {call}")
                    lines.extend(f"{name[idx]} = {value}" for idx, value in
                                 zip(op.outputs, unpack) if binds(idx))
                lines.extend(f"S[{idx}] = {name[idx]}" for idx in op.outputs if idx in stale)
                continue
            if direct(blk, "output"):
                call = kernel_call(blk, blk.kernels.output, state_view(buffer, op.state),
                                   op.inputs)
            else:
                call = (f"{src.const('out', method(blk, 'output'))}(ts, "
                        f"{state_view(buffer, op.state)}, {args(op.inputs)})")
            if time_only(blk) and direct(blk, "output"):
                lines.extend(memo(blk, "r", call))
                call = "r"
            if len(op.outputs) == 1 and binds(op.outputs[0]):
                lines.append(f"{name[op.outputs[0]]} = {call}[0]")
            else:
                if call != "r":
                    lines.append(f"r = {call}")
                lines.extend(f"{name[idx]} = r[{k}]" for k, idx in enumerate(op.outputs)
                             if binds(idx))
            lines.extend(f"S[{idx}] = {name[idx]}" for idx in op.outputs if idx in stale)
        return lines

    def derivative_pass(buffer, s: int) -> list:
        lines = []
        for step in called_stateful:
            kv = K[s][:, step.state]
            blk = step.block
            if direct(blk, "derivative"):
                lines.append(src.copy(f"k{s}_", kv, kernel_call(
                    blk, blk.kernels.derivative, state_view(buffer, step.state), step.inputs)))
                continue
            fn = src.const("der", method(blk, "derivative"))
            lines.append(src.copy(f"k{s}_", kv, f"{fn}(ts, {state_view(buffer, step.state)}, "
                                                f"{args(step.inputs)})"))
        if derivative_group is not None:
            g = groups[id(derivative_group)]
            kv = K[s][:, plan.state]
            if derivative_group.outputs:          # dx came with the group's outputs
                lines.append(src.copy("klin", kv, src.const('dx', g.dx)))
            else:                                 # a product straight into k_i
                lines.extend(g.code(src, buffer, plan, read, kv, held()))
        return lines

    # ---------------------------------------------------------------- logging
    logs = []
    t_log = np.empty(n_rows)
    ns["t_log"] = t_log
    record = ["t_log[row] = t"]
    for sig_name in d.logged:
        idx = d.signal_index[sig_name]
        arr = (alloc((n_rows, B) + shapes[idx]) if alloc is not None else
               np.full((n_rows, B) + shapes[idx], np.nan))
        logs.append(arr)
        record.append(f"{src.const('log', arr)}[row] = {read(idx)}")
    if probe is not None:
        c = 0
        for idx in probe[0]:
            n = int(np.prod(shapes[idx], dtype=np.int64))
            view = _view(probe[1][:, c:c + n], (B,) + shapes[idx])
            record.append(src.copy("probe", view, read(idx)))
            c += n

    # ---------------------------------------------------------------- functions
    def function(header: str, body: list) -> None:
        src.emit(0, header)
        for line in body or ["pass"]:
            src.emit(1, line)
        src.emit(0, "")

    G = np.zeros((B, sum(st.block.n_crossings for st in crossings)))
    guards, c = [], 0
    for st in crossings:
        blk = st.block
        m = blk.n_crossings
        ck = getattr(blk, "crossing_kernel", None)
        if ck is not None and "zero_crossings" not in vars(type(blk)) \
                and "zero_crossings" not in blk.__dict__:
            # the guard kernel, straight into its columns of G
            pars = "".join(", " + src.const("p", getattr(blk.p, n)) for n in ck[1])
            ins = "".join(", " + read(u) for u in st.inputs)
            guards.append(f"{src.const('zck', ck[0])}({src.const('g', G[:, c:c + m])}, ts, "
                          f"{state_view(xn, st.state)}{ins}{pars})")
        else:
            fn = src.const("zc", blk.zero_crossings)
            guards.append(src.copy("g", G[:, c:c + m], f"{fn}(ts, {state_view(xn, st.state)}, "
                                                        f"{args(st.inputs)})"))
        c += m
    stage1 = ["ts = t"] + output_pass(xn) + guards
    stage1_record = ["ts = t"] + output_pass(xn, record=True) + guards
    function("def first(t):", stage1 + derivative_pass(xn, 0))
    function("def first_record(t, row):", stage1_record + record + derivative_pass(xn, 0))
    def stage_state(coeffs, scale: str) -> list:
        """x_i = x_n + sum_j (scale a_ij) k_j, summed in the reference stepper's order."""
        if not coeffs:
            return ["X[...] = xn"]
        j, a = coeffs[0]
        lines = [f"multiply(K{j}, {scale}{src.const('a', a)}, out=X)", "add(X, xn, out=X)"]
        for j, a in coeffs[1:]:
            lines += [f"multiply(K{j}, {scale}{src.const('a', a)}, out=T)", "add(X, T, out=X)"]
        return lines

    def update(coeffs, scale: str) -> list:
        """x_n += sum_j (scale b_j) k_j."""
        lines = []
        for j, b in coeffs:
            lines += [f"multiply(K{j}, {scale}{src.const('b', b)}, out=T)", "add(xn, T, out=xn)"]
        return lines

    rest = []
    stage = output_pass(X)
    for s, (ch, coeffs) in enumerate(stages, start=1):
        rest.extend(stage_state(coeffs, ""))       # coefficients already times h
        rest.append(f"ts = t + {src.const('c', ch)}")
        rest.extend(stage)
        rest.extend(derivative_pass(X, s))
    rest.extend(update(final_coeffs, ""))
    function("def rest(t):", rest)
    function("def final(t, row):", stage1_record + record)
    # the same stage 1 at an explicit stage time, and a step of any size h whose stage
    # times are clamped to [lo, hi]: for steps that start or end at a discontinuity
    # (fwdstep.run.events); the steps above are untouched, so runs without events stay the same
    stage1_ts, stage1_record_ts = stage1[1:], stage1_record[1:]
    function("def first_ts(ts):", stage1_ts + derivative_pass(xn, 0))
    function("def first_record_ts(t, ts, row):", stage1_record_ts + record
             + derivative_pass(xn, 0))
    function("def final_ts(t, ts, row):", stage1_record_ts + record)
    rest_h = []
    for s, (c, row_a) in enumerate(zip(tab.c[1:], tab.a[1:]), start=1):
        rest_h.extend(stage_state([(j, a) for j, a in enumerate(row_a) if a != 0.0], "h * "))
        rest_h.append(f"ts = min(max(t + {src.const('c', c)} * h, lo), hi)")
        rest_h.extend(stage)
        rest_h.extend(derivative_pass(X, s))
    rest_h.extend(update([(j, b) for j, b in enumerate(tab.b) if b != 0.0], "h * "))
    function("def rest_h(t, h, lo, hi):", rest_h)
    # every output at (ts, xn), returning the signals discrete blocks read: {index: value}
    if sampled:
        function("def sample_signals(ts):", stage1_ts + [
            "return {" + ", ".join(f"{i}: {read(i)}" for i in sampled) + "}"])

    source = "\n".join(src.lines)
    exec(_compiled(source, f"<fwdstep program for {d.file}>"), ns)  # noqa: S102
    return Program(xn=xn, logs=logs, t_log=t_log, first=ns["first"],
                   first_record=ns["first_record"], rest=ns["rest"], final=ns["final"],
                   plan=plan, source=source, first_ts=ns["first_ts"],
                   first_record_ts=ns["first_record_ts"], final_ts=ns["final_ts"],
                   rest_h=ns["rest_h"], sample_signals=ns.get("sample_signals"), k=K, G=G)


#: the module that compiles a block's kernel to native code (``Block.native_kernels``),
#: loaded by name: the run layer never imports ``fwdstep.compiled``.  Without llvmlite it
#: does not import and every block runs its method.
PLUGGED_NATIVE = "fwdstep.compiled.native_block"


def native_methods(d) -> dict:
    """id(block) -> {"output" or "derivative": its native kernel} for the blocks of ``d``
    that want native kernels at its batch size (``Block.native_wanted``) and whose kernels
    compile; {} without the plugged module.  A method replaced on the block instance (a
    wrapper that counts or traces calls) is called as it is, never bypassed."""
    wanted, seen = [], set()
    for st in list(d.schedule) + list(d.stateful):
        blk = st.block
        if id(blk) not in seen:
            seen.add(id(blk))
            wanted += [(blk, which) for which in blk.native_wanted(d.batch)
                       if which not in blk.__dict__]   # (a method wrapped on the instance runs)
    if not wanted:
        return {}
    try:
        provider = importlib.import_module(PLUGGED_NATIVE)
    except ImportError:
        return {}
    out: dict = {}
    for blk, which in wanted:
        fn = provider.native_kernel(blk, which, d.batch)
        if fn is not None:
            out.setdefault(id(blk), {})[which] = fn
    return out


class _GroupBuffers:
    """The preallocated buffers of one fused product ``[inputs] @ M``: the input buffer V
    (one view per input term), M, the product buffer Y whose column views are the group's
    output signals (bound in ``name``), and the view of its derivative columns."""

    def __init__(self, src: _Source, group: LinearGroup, B: int, shapes: list, name: dict):
        self.group = group
        n_in = sum(n for _, n in group.inputs)
        self.V = np.zeros((B, n_in))
        self.inputs = []
        c = 0
        for term, n in group.inputs:
            view = self.V[:, c:c + n]
            self.inputs.append((term, view if term == "x" else _view(view, (B,) + shapes[term])))
            c += n
        self.Y = np.zeros((B, group.M.shape[2]))
        c = 0
        for idx, n in group.outputs:
            name[idx] = src.const(f"y{idx}_", _view(self.Y[:, c:c + n], (B,) + shapes[idx]))
            c += n
        self.dx = self.Y[:, c:] if group.derivative else None
        self.seen: dict = {}

    def code(self, src: _Source, buffer, plan, read, out, held=None) -> list:
        """Lines filling V (states from ``buffer``) and writing the product into ``out``.
        ``held``: input signal -> memo cell of the time-only block producing it; those
        inputs are copied into V only when the cell holds a new value (RK4's stage 3 and the
        next step's stage 1 reuse stage 2's and stage 4's: the copy would write the same
        numbers again).  Only this group writes its V, so V still holds the last copy."""
        if not self.V.shape[1]:                     # every output is identically zero
            return []
        lines, by_cell = [], {}
        for term, view in self.inputs:
            value = src.const("xlin", buffer[:, plan.state]) if term == "x" else read(term)
            line = src.copy("v", view, value)
            cell = (held or {}).get(term)
            if cell is None:
                lines.append(line)
            else:
                by_cell.setdefault(cell, []).append(line)
        for cell, copies in by_cell.items():
            if cell not in self.seen:           # the cell's value last copied into V
                self.seen[cell] = src.const("seen", [None])
            seen = self.seen[cell]
            lines += [f"if {seen}[0] is not {cell}[1]:"] + ["    " + c for c in copies] + [
                f"    {seen}[0] = {cell}[1]"]
        M = self.group.M
        if M.shape[0] == 1 and out.flags.c_contiguous:
            lines.append(f"dot({src.const('V', self.V)}, {src.const('M', M[0])}, "
                         f"out={src.const('Y', out)})")
        elif M.shape[0] == 1:
            lines.append(f"matmul({src.const('V', self.V)}, {src.const('M', M[0])}, "
                         f"out={src.const('Y', out)})")
        else:
            lines.append(f"matmul({src.const('V', self.V[:, None, :])}, {src.const('M', M)}, "
                         f"out={src.const('Y', out[:, None, :])})")
        return lines


def _needed_signals(d, sampled: tuple, crossings: tuple) -> tuple:
    """(the signals a stage that records nothing needs, ids of the Steps that compute them):
    the inputs of every stateful block (its derivative reads them), of the zero-crossing
    guards and the ``sampled`` signals, and, transitively, the inputs of the blocks producing
    any of those.  Stateful blocks and blocks without outputs always run (their output call
    is where a block may stop a run); a stateless block producing none of these is needed
    only for a record (the log and ``fwdstep.run.finite``'s probe read every output)."""
    needed = set(sampled)
    for st in list(d.stateful) + list(crossings):
        needed.update(st.inputs)
    live: set = set()
    changed = True
    while changed:                  # a non-feedthrough input may come from later in the order
        changed = False
        for st in reversed(d.schedule):
            if id(st) in live:
                continue
            if st.state is not None or not st.outputs or needed.intersection(st.outputs):
                live.add(id(st))
                needed.update(st.inputs)
                changed = True
    return needed, live


@functools.lru_cache(maxsize=64)
def _compiled(source: str, filename: str):
    """The code object of a generated source (the batches of a sweep share one text: the
    names in it are counters, the values are bound in each run's namespace)."""
    return compile(source, filename, "exec")


def _view(arr: np.ndarray, shape: tuple) -> np.ndarray:
    """``arr`` reshaped without copying (raises if that is impossible)."""
    v = arr.view()
    v.shape = shape
    return v
