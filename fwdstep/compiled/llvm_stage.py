"""A scalar stage (``backend_numba._ScalarStage``) compiled straight to machine code with
LLVM (llvmlite, which numba brings), in tens of milliseconds (the IR of each node and the
compile: ``fwdstep.compiled.llvm_ir``, shared with the NumPy path's native block kernels).

The traced graph (``fwdstep.compiled.scalarize``) is straight-line floating-point code: every node
is one LLVM instruction (``fadd``, ``fmul``, ``fcmp``, ``select``, a call of the math
intrinsic numba's own code calls), in the graph's order, with no fast-math flag, so the
machine code does the operations numba would do with the same IEEE results.  Running it
through numba instead costs 1-2 s of typing and lowering per structure.  The compiled
function is handed to the numba loop as a first-class function (``WrapperAddressProtocol``)
of the one signature ``SIGNATURE``:

    stage(mode, ts, stg, rb, ws, L) -> status

``ws`` and ``L`` are the addresses of the variant's workspace and of the log array (see
``_ScalarStage``); modes 0 derivative, 1 record and derivative, 2 record only, 3 the
parameter-only nodes into the workspace; status 2 when an unrecorded output is not finite.
A stage 1 (stg 0) that makes derivatives also compares the zero-crossing guards' signs
with the ones it left in the workspace (``_ScalarStage.og``), writes the new ones there and
returns 4 when one changed sign and is finite (when the diagram has guards).
"""
from __future__ import annotations

import hashlib

from numba.core import types
from numba.core.types import WrapperAddressProtocol
from numba.experimental import function_type  # noqa: F401  (registers the typeof above)

from fwdstep.compiled.llvm_ir import INF as _INF, BasicBlock as _Block, Emitter as _Emitter, \
    engine_of, literal as _double

SIGNATURE = types.int64(types.int64, types.float64, types.int64, types.int64, types.uintp,
                        types.uintp)


def stage_ir(st) -> str:
    """The LLVM IR of ``_ScalarStage`` st's stage function."""
    tr = st.tr
    # (a variational stage's tangent nodes may be fused multiply-adds: llvm_ir)
    em = _Emitter(tr, (st.contract_from, st.contract_to) if hasattr(st, "contract_to")
                  else None)
    nodes = tr.nodes
    leaves = {}                       # leaf name -> node number
    for node in nodes:
        if node.op == "leaf":
            leaves[node.value] = node.n

    def load_params(block):
        for j in range(st.n_columns):
            n = leaves.get(f"p{j}")
            if n is not None:
                block.names[n] = (block.load("%ws", st.ow + j), "double")

    entry = _Block(em, "entry", {})
    entry.lines += ["  %ws = inttoptr i64 %wsi to double*", "  %L = inttoptr i64 %Li to double*",
                    "  %is3 = icmp eq i64 %mode, 3",
                    "  br i1 %is3, label %inv, label %main"]
    inv = _Block(em, "inv", {})
    load_params(inv)
    for n in st.inv:
        inv.define(nodes[n])
    for k, n in enumerate(st.inv):
        inv.store("%ws", st.oz + k, inv.value(nodes[n]))
    inv.lines.append("  ret i64 0")
    main = _Block(em, "main", {})
    load_params(main)
    if "ts" in leaves:
        main.names[leaves["ts"]] = ("%ts", "double")
    for k, n in enumerate(st.inv):
        main.names[n] = (main.load("%ws", st.oz + k), "double")
    for i in range(st.n_states):
        n = leaves.get(f"x{i}")
        if n is not None:
            main.names[n] = (main.load("%ws", i), "double")
    for n in st.need_d:
        main.define(nodes[n])
    main.lines += ["  %isrec = icmp ne i64 %mode, 0",
                   "  br i1 %isrec, label %record, label %der"]
    rec = _Block(em, "record", main.names)
    for n in st.need_r:
        rec.define(nodes[n])
    for col, node in st.records:
        off = rec.emit(f"add i64 %rb, {col}")
        rec.store("%L", off, rec.value(node))
    ok = "true"
    for node in st.checked:
        a = rec.call("llvm.fabs.f64", rec.value(node))
        f = rec.emit(f"fcmp olt double {a}, {_INF}")
        ok = rec.emit(f"and i1 {ok}, {f}")
    rec.lines.append(f"  br i1 {ok}, label %recok, label %bad")
    tail = ["bad:", "  ret i64 2", "recok:", "  %is2 = icmp eq i64 %mode, 2",
            "  br i1 %is2, label %done, label %der", "done:", "  ret i64 0"]
    der = _Block(em, "der", main.names)
    kb0 = der.emit(f"mul i64 %stg, {st.n_states}")
    kb = der.emit(f"add i64 {kb0}, {st.n_states}")
    for i, node in st.der:
        off = der.emit(f"add i64 {kb}, {i}")
        der.store("%ws", off, der.value(node))
    guards = []
    if getattr(st, "n_guards", 0):     # stage 1: the guards, compared and kept
        der.lines += ["  %isg = icmp eq i64 %stg, 0",
                      "  br i1 %isg, label %guards, label %dret", "dret:"]
        g = _Block(em, "guards", main.names)
        for n in st.need_g:
            g.define(nodes[n])
        changed = "false"
        for k, node in enumerate(st.guards):
            new = g.value(node)
            old = g.load("%ws", st.og + k)
            flip = g.emit(f"xor i1 {g.emit(f'fcmp oge double {new}, {_double(0.0)}')}, "
                          f"{g.emit(f'fcmp oge double {old}, {_double(0.0)}')}")
            finite = g.emit(f"fcmp olt double {g.call('llvm.fabs.f64', new)}, {_INF}")
            changed = g.emit(f"or i1 {changed}, {g.emit(f'and i1 {flip}, {finite}')}")
            g.store("%ws", st.og + k, new)
        g.lines.append(f"  %gst = select i1 {changed}, i64 4, i64 0")
        g.lines.append("  ret i64 %gst")
        guards = g.lines
    der.lines.append("  ret i64 0")
    decl = [f"declare double @{fn}({', '.join(['double'] * k)})"
            for fn, k in sorted(em.declare)]
    return "\n".join(decl + [
        "define i64 @stage(i64 %mode, double %ts, i64 %stg, i64 %rb, i64 %wsi, i64 %Li) {",
        *entry.lines, *inv.lines, *main.lines, *rec.lines, *tail, *der.lines, *guards, "}", ""])


class CompiledStage(WrapperAddressProtocol):
    """A stage's machine code as a first-class function of numba (type
    ``FunctionType(SIGNATURE)``); holds the engine that owns the code."""

    def __init__(self, engine, address: int):
        self.engine, self.address = engine, address

    def __wrapper_address__(self) -> int:
        return self.address

    def signature(self):
        return SIGNATURE


_compiled: dict = {}


def compile_stage(st, before=None) -> CompiledStage:
    """The machine code of ``_ScalarStage`` st (memoised in the process by its IR, whose
    hash is kept on st: a stage never changes once built, and a copy rebound to other
    values of W, ``compiled_sensitivity.VariationalStage.rebound``, has the same IR);
    ``before()`` is called first when it must be compiled (not memoised)."""
    key, text = getattr(st, "_ir_key", None), None
    if key is None:
        text = stage_ir(st)
        key = st._ir_key = hashlib.sha256(text.encode()).digest()
    if key not in _compiled:
        if text is None:
            text = stage_ir(st)
        if before is not None:
            before()
        engine = engine_of(text)
        _compiled[key] = CompiledStage(engine, engine.get_function_address("stage"))
        while len(_compiled) > 256:     # a program holds its own stage (and its engine)
            _compiled.pop(next(iter(_compiled)))
    return _compiled[key]
