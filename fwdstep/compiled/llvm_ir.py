"""LLVM IR of traced scalar graphs (``fwdstep.compiled.scalarize``) and its machine code, with
llvmlite only (no numba: ``fwdstep.compiled.native_block`` uses it without importing numba).

Every node is one LLVM instruction (``fadd``, ``fmul``, ``fcmp``, ``select``, a call of the
math intrinsic numba's own code calls), in the graph's order, with no fast-math flag, so the
machine code does the operations of the kernels with the same IEEE results.  The one
exception: an ``Emitter`` may be given a range of nodes whose products and sums carry LLVM's
``contract`` flag (the tangent nodes of a variational stage,
``fwdstep.analysis.compiled_sensitivity``, which nothing of the diagram's own state reads),
so that a product and the sum using it may be one fused multiply-add where the machine has
one: those numbers then differ from unfused ones in the last bits (another, equally exact
order of rounding).  Shared by the
compiled backend's stage (``fwdstep.compiled.llvm_stage``) and the NumPy path's native block
kernels (``fwdstep.compiled.native_block``).
"""
from __future__ import annotations

import struct

import llvmlite.binding as llvm

_UNARY = {"sin": "llvm.sin.f64", "cos": "llvm.cos.f64", "exp": "llvm.exp.f64",
          "log": "llvm.log.f64", "sqrt": "llvm.sqrt.f64", "abs": "llvm.fabs.f64",
          "tan": "tan", "tanh": "tanh", "sinh": "sinh", "cosh": "cosh", "atan": "atan",
          "asin": "asin", "acos": "acos", "floor": "llvm.floor.f64"}
_ARITH = {"+": "fadd", "-": "fsub", "*": "fmul", "/": "fdiv"}
_CMP = {"<": "olt", "<=": "ole", ">": "ogt", ">=": "oge", "==": "oeq", "!=": "une"}
INF = "0x7FF0000000000000"


def literal(v: float) -> str:
    """An exact LLVM literal of the double v."""
    return "0x" + struct.pack(">d", float(v)).hex().upper()


class BasicBlock:
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
            return literal(v)
        name, kind = self.names[node.n]
        if kind == want:
            return name
        if want == "double":
            return self.emit(f"uitofp i1 {name} to double")
        return self.emit(f"fcmp une double {name}, {literal(0.0)}")

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
            flag = " contract" if self.em.contract_from <= node.n < self.em.contract_to \
                else ""
            out = self.emit(f"{_ARITH[op]}{flag} double {self.value(a[0])}, "
                            f"{self.value(a[1])}")
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


class Emitter:
    """The counter of instruction names and the functions to declare, over a function."""

    def __init__(self, tr, contract=None):
        self.tr, self.count, self.declare = tr, 0, set()
        # nodes numbered in [from, to) may fuse a product into a sum (``contract``)
        self.contract_from, self.contract_to = contract or (0, 0)


_TARGET = []


def target_machine():
    """A new target machine for one engine: ``llvm.create_mcjit_compiler`` makes
    the engine its owner, so it is deleted with the engine (one machine shared by every
    stage dangled once the first engine was freed: a segfault in the next compile)."""
    if not _TARGET:
        llvm.initialize_native_target()
        llvm.initialize_native_asmprinter()
        _TARGET.append((llvm.Target.from_default_triple(), llvm.get_host_cpu_name(),
                        llvm.get_host_cpu_features().flatten()))
    target, cpu, features = _TARGET[0]
    return target.create_target_machine(cpu=cpu, features=features, opt=2,
                                        codemodel="jitdefault")


def target_identity() -> str:
    """What machine code depends on besides the IR: LLVM, the host triple and CPU."""
    target_machine()
    target, cpu, features = _TARGET[0]
    return f"{llvm.llvm_version_info} {target.triple} {cpu} {features}"


def engine_of(text: str, object_code: bytes | None = None, on_object=None):
    """An MCJIT engine holding the machine code of the IR ``text`` (verified, optimised at
    level 2 for the host CPU, finalised); keep it alive as long as its functions are used.
    ``object_code``: that machine code as made before (``on_object(bytes)`` receives it when
    it is made here): the optimisation and code generation are skipped."""
    tm = target_machine()
    mod = llvm.parse_assembly(text)
    mod.verify()
    mod.triple = tm.triple
    mod.data_layout = str(tm.target_data)
    if object_code is None:
        pto = llvm.create_pipeline_tuning_options(speed_level=2)
        pb = llvm.create_pass_builder(tm, pto)
        pb.getModulePassManager().run(mod, pb)
    engine = llvm.create_mcjit_compiler(mod, tm)
    if object_code is not None or on_object is not None:
        engine.set_object_cache(
            notify_func=None if on_object is None else (lambda _, data: on_object(bytes(data))),
            getbuffer_func=lambda _: object_code)
    engine.finalize_object()
    return engine
