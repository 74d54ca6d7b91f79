"""A scalar stage (``backend_numba._ScalarStage``) compiled straight to machine code with
LLVM (llvmlite, which numba brings), in tens of milliseconds.

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
import struct

import llvmlite.binding as llvm
from numba.core import types
from numba.core.types import WrapperAddressProtocol
from numba.experimental import function_type  # noqa: F401  (registers the typeof above)

SIGNATURE = types.int64(types.int64, types.float64, types.int64, types.int64, types.uintp,
                        types.uintp)

_UNARY = {"sin": "llvm.sin.f64", "cos": "llvm.cos.f64", "exp": "llvm.exp.f64",
          "log": "llvm.log.f64", "sqrt": "llvm.sqrt.f64", "abs": "llvm.fabs.f64",
          "tan": "tan", "tanh": "tanh", "sinh": "sinh", "cosh": "cosh", "atan": "atan",
          "asin": "asin", "acos": "acos", "floor": "llvm.floor.f64"}
_ARITH = {"+": "fadd", "-": "fsub", "*": "fmul", "/": "fdiv"}
_CMP = {"<": "olt", "<=": "ole", ">": "ogt", ">=": "oge", "==": "oeq", "!=": "une"}
_INF = "0x7FF0000000000000"


def _double(v: float) -> str:
    """An exact LLVM literal of the double v."""
    return "0x" + struct.pack(">d", float(v)).hex().upper()


class _Block:
    """The instructions of one basic block and the names of the nodes defined so far on
    the way to it (its dominators')."""

    def __init__(self, em, label, names):
        self.em, self.label, self.names = em, label, dict(names)
        self.lines = [f"{label}:"]

    def emit(self, text) -> str:
        name = f"%t{self.em.count}"
        self.em.count += 1
        self.lines.append(f"  {name} = {text}")
        return name

    def load(self, base, offset) -> str:
        ptr = self.emit(f"getelementptr inbounds double, double* {base}, i64 {offset}")
        return self.emit(f"load double, double* {ptr}")

    def store(self, base, offset, value) -> None:
        ptr = self.emit(f"getelementptr inbounds double, double* {base}, i64 {offset}")
        self.lines.append(f"  store double {value}, double* {ptr}")

    def value(self, node, want="double") -> str:
        if node.op == "const":
            v = self.em.tr.value(node)
            if want == "i1":
                return "true" if v != 0.0 else "false"
            return _double(v)
        name, kind = self.names[node.n]
        if kind == want:
            return name
        if want == "double":
            return self.emit(f"uitofp i1 {name} to double")
        return self.emit(f"fcmp une double {name}, {_double(0.0)}")

    def define(self, node) -> None:
        """Emit node (its arguments are defined)."""
        op, a = node.op, node.args
        if op in _CMP:
            self.names[node.n] = (self.emit(f"fcmp {_CMP[op]} double {self.value(a[0])}, "
                                            f"{self.value(a[1])}"), "i1")
            return
        if op in ("&", "|"):
            self.names[node.n] = (self.emit(f"{'and' if op == '&' else 'or'} i1 "
                                            f"{self.value(a[0], 'i1')}, "
                                            f"{self.value(a[1], 'i1')}"), "i1")
            return
        if op == "!":
            self.names[node.n] = (self.emit(f"xor i1 {self.value(a[0], 'i1')}, true"), "i1")
            return
        if op == "?":
            c, x, y = self.value(a[0], "i1"), self.value(a[1]), self.value(a[2])
            out = self.emit(f"select i1 {c}, double {x}, double {y}")
        elif op == "-" and len(a) == 1:
            out = self.emit(f"fneg double {self.value(a[0])}")
        elif op in _ARITH:
            out = self.emit(f"{_ARITH[op]} double {self.value(a[0])}, {self.value(a[1])}")
        elif op == "**":
            out = self.call("llvm.pow.f64", self.value(a[0]), self.value(a[1]))
        elif op == "atan2":
            out = self.call("atan2", self.value(a[0]), self.value(a[1]))
        else:
            out = self.call(_UNARY[op], self.value(a[0]))
        self.names[node.n] = (out, "double")

    def call(self, fn, *args) -> str:
        self.em.declare.add((fn, len(args)))
        return self.emit(f"call double @{fn}({', '.join('double ' + x for x in args)})")


class _Emitter:
    def __init__(self, tr):
        self.tr, self.count, self.declare = tr, 0, set()


def stage_ir(st) -> str:
    """The LLVM IR of ``_ScalarStage`` st's stage function."""
    tr = st.tr
    em = _Emitter(tr)
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
_target = []


def _target_machine():
    """A new target machine for one stage's engine: ``llvm.create_mcjit_compiler`` makes
    the engine its owner, so it is deleted with the engine (one machine shared by every
    stage dangled once the first engine was freed: a segfault in the next compile)."""
    if not _target:
        llvm.initialize_native_target()
        llvm.initialize_native_asmprinter()
        _target.append((llvm.Target.from_default_triple(), llvm.get_host_cpu_name(),
                        llvm.get_host_cpu_features().flatten()))
    target, cpu, features = _target[0]
    return target.create_target_machine(cpu=cpu, features=features, opt=2,
                                        codemodel="jitdefault")


def compile_stage(st, before=None) -> CompiledStage:
    """The machine code of ``_ScalarStage`` st (memoised in the process by its IR);
    ``before()`` is called first when it must be compiled (not memoised)."""
    text = stage_ir(st)
    key = hashlib.sha256(text.encode()).digest()
    if key not in _compiled:
        if before is not None:
            before()
        tm = _target_machine()
        mod = llvm.parse_assembly(text)
        mod.verify()
        mod.triple = tm.triple
        mod.data_layout = str(tm.target_data)
        pto = llvm.create_pipeline_tuning_options(speed_level=2)
        pb = llvm.create_pass_builder(tm, pto)
        pb.getModulePassManager().run(mod, pb)
        engine = llvm.create_mcjit_compiler(mod, tm)
        engine.finalize_object()
        _compiled[key] = CompiledStage(engine, engine.get_function_address("stage"))
        while len(_compiled) > 256:     # a program holds its own stage (and its engine)
            _compiled.pop(next(iter(_compiled)))
    return _compiled[key]
