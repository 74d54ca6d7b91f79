"""One block's kernel as native code, for the NumPy path (``fwdstep.run.program``).

A block that declares ``native_kernels`` (``fwdstep.core.block.Block``; the robot blocks of
blocks/urdf.py: ``URDFArm``'s derivative, ``URDFRegressor``'s and ``URDFFrame``'s output) and
wants them for a
batch (``Block.native_wanted``) has that kernel traced on symbols (``fwdstep.compiled.scalarize``,
the tracer of the compiled backend) and compiled with LLVM (``fwdstep.compiled.llvm_ir``, the
emitter the compiled stage uses), without numba.  The NumPy path's generated program calls
the result (``NativeKernel``) in place of the block's ``output`` / ``derivative``, with the
same arguments and results: the same equations (the block's own kernel), the kernel's order
of operations (IEEE results equal to the kernel run by NumPy up to the last bit of the math
functions), a few microseconds per call instead of the block's Python and C++ calls.

The code is written for the block's structure: the parameters are read at run time from a
matrix W (one column per entry, one row per variant: ``scalarize.ParameterColumns``), except
entries that are 0, 1 or -1 (folded) and those a branch of the kernel reads (a joint type, a
parent index: written into the code).  One function runs every variant of the batch:

    kernel(ts, table)        table = [B, &slot_0, stride_0, ..., &W, stride_W, &out, stride_out]

(addresses and row strides, in doubles, of the state, the inputs, W and the output rows; a
stride 0 shares one row between the variants).  An input that is the same array object at
two calls in a row (a state view, a fused group's column view) is read in place; any other
is first copied into the kernel's own buffer (a NumPy copy of ~0.1 us; reading an array's
address from Python costs ~1 us).  The output is returned as new arrays, as the block's
method does.

Tracing costs 0.02-0.06 s per robot kernel, once per process (memoised by everything the
trace reads); compiling 0.1-0.2 s, once per machine: the object code is kept in the
compiled-code cache (``fwdstep.compiled.compiled_cache``: private folder, SHA-256 checked)
under the hash of the IR and the target, and loaded from there by later processes.  Without
llvmlite this module does not import and the blocks run their Python methods; a kernel the
tracer refuses (``Untraceable``) does the same.
"""
from __future__ import annotations

import ctypes
import hashlib

import numpy as np

from fwdstep.compiled import compiled_cache, llvm_ir
from fwdstep.compiled import scalarize as sz

_F8 = np.dtype(np.float64)
_CALL = ctypes.CFUNCTYPE(None, ctypes.c_double, ctypes.c_int64)


class _Traced(sz.ParameterColumns):
    """The graph of ``block``'s kernel ``which`` ("output" or "derivative") for one variant:
    leaves for the state, each input and the parameter columns; ``outs``, the nodes of the
    result in the order of the output rows; ``slots``, the shape of each array read."""

    def __init__(self, block, which: str):
        self.columns, self._by_values = [], {}
        tr = self.tr = sz.Trace()
        rb = sz.Rebinder(tr)
        k = block.kernels
        fn = getattr(k, which)
        self.leaves = {}                         # leaf name -> (slot, offset in its row)
        self.slots = []                          # (port) shapes of the arrays read

        def slot(shape):
            j = len(self.slots)
            self.slots.append(shape)
            size = int(np.prod(shape, dtype=np.int64))

            def name(idx):
                flat = int(np.ravel_multi_index(idx[1:], shape)) if shape else 0
                nm = f"s{j}_{flat}"
                self.leaves[nm] = (j, flat)
                return nm, False
            return sz.sym_array(tr, (1,) + shape, name) if size else \
                np.empty((1,) + shape, dtype=object).view(sz.SymArray)

        n = block.n_states
        self.has_state = n > 0
        x = slot((n,)) if n else np.empty((1, 0), dtype=object).view(sz.SymArray)
        inputs = [slot(tuple(port.shape)) for port in block.inputs.values()]
        if k.tuple_inputs:
            inputs = [tuple(inputs)]
        ts = tr.leaf("ts", False)
        args = [self._param(getattr(block.p, name)) for name in k.params] + list(k.static)
        r = sz.run_traced(rb, fn, ts, x, *inputs, *args)
        if which == "derivative":
            self.shapes = [(n,)]
            outs = [sz.as_nodes(tr, r, (1, n))]
        else:
            self.shapes = [tuple(port.shape) for port in block.outputs.values()]
            sizes = [int(np.prod(s, dtype=np.int64)) for s in self.shapes]
            if k.packed:
                outs = [sz.as_nodes(tr, r, (1, sum(sizes)))]
            else:
                if len(r) != len(self.shapes):
                    raise sz.Untraceable(f"{len(r)} outputs where {len(self.shapes)} "
                                         f"declared")
                outs = [sz.as_nodes(tr, v, (1,) + s) for v, s in zip(r, self.shapes)]
        self.outs = [node for o in outs for node in o.reshape(-1)]
        self.W = self.column_matrix()

    def ir(self) -> str:
        """The LLVM IR of ``kernel(ts, table)``: a loop over the B variants whose body is
        the graph, straight-line."""
        tr = self.tr
        em = llvm_ir.Emitter(tr)
        n_slots = len(self.slots) + 2                        # the arrays read, W, out
        entry = ["entry:", "  %tab = inttoptr i64 %tabi to i64*",
                 "  %B = load i64, i64* %tab"]
        for k in range(n_slots):
            entry += [f"  %ap{k} = getelementptr inbounds i64, i64* %tab, i64 {1 + 2 * k}",
                      f"  %a{k} = load i64, i64* %ap{k}",
                      f"  %p{k} = inttoptr i64 %a{k} to double*",
                      f"  %sp{k} = getelementptr inbounds i64, i64* %tab, i64 {2 + 2 * k}",
                      f"  %s{k} = load i64, i64* %sp{k}"]
        entry += ["  %any = icmp sgt i64 %B, 0", "  br i1 %any, label %loop, label %exit"]
        body = llvm_ir.BasicBlock(em, "loop", {})
        body.lines.append("  %b = phi i64 [0, %entry], [%next, %loop]")
        base = []
        for k in range(n_slots):
            off = body.emit(f"mul i64 %b, %s{k}")
            base.append(body.emit(f"getelementptr inbounds double, double* %p{k}, i64 {off}"))
        w_slot, out_slot = n_slots - 2, n_slots - 1
        for node in tr.nodes:
            if node.op != "leaf":
                continue
            name = node.value
            if name == "ts":
                body.names[node.n] = ("%ts", "double")
            elif name in self.leaves:
                j, flat = self.leaves[name]
                body.names[node.n] = (body.load(base[j], flat), "double")
            else:                                            # p{j}: a column of W
                body.names[node.n] = (body.load(base[w_slot], int(name[1:])), "double")
        for n in sorted(tr.needed(self.outs)):
            body.define(tr.nodes[n])
        for i, node in enumerate(self.outs):
            body.store(base[out_slot], i, body.value(node))
        body.lines += ["  %next = add i64 %b, 1", "  %more = icmp slt i64 %next, %B",
                       "  br i1 %more, label %loop, label %exit"]
        decl = [f"declare double @{fn}({', '.join(['double'] * k)})"
                for fn, k in sorted(em.declare)]
        return "\n".join(decl + ["define void @kernel(double %ts, i64 %tabi) {", *entry,
                                 *body.lines, "exit:", "  ret void", "}", ""])


#: the compiled kernels of this process: key -> (_Traced, engine, address)
_compiled: dict = {}


def _key(block, which: str) -> bytes:
    """Everything the trace reads: the kernel (its code and what it calls are those of the
    function object, held by the memo), its static values, the shapes, the parameters."""
    k = block.kernels
    fn = getattr(k, which)
    h = hashlib.sha256(repr((type(block).__qualname__, which, id(fn), k.params, k.static,
                             k.packed, k.tuple_inputs, block.n_states,
                             [tuple(p.shape) for p in block.inputs.values()],
                             [tuple(p.shape) for p in block.outputs.values()])).encode())
    for name in k.params:
        arr = np.ascontiguousarray(getattr(block.p, name), dtype=float)
        h.update(repr(arr.shape).encode() + arr.data)
    return h.digest()


def _compile(block, which: str):
    key = _key(block, which)
    got = _compiled.get(key)
    if got is None:
        traced = _Traced(block, which)
        text = traced.ir()
        code = hashlib.sha256(f"{text}\n{llvm_ir.target_identity()}".encode()).hexdigest()
        cached = compiled_cache.native_object(code)
        engine = llvm_ir.engine_of(text, cached, None if cached is not None else (
            lambda data: compiled_cache.store_native_object(code, data)))
        got = _compiled[key] = (traced, engine, engine.get_function_address("kernel"),
                                getattr(block.kernels, which))
        while len(_compiled) > 64:
            _compiled.pop(next(iter(_compiled)))
    return got


class NativeKernel:
    """``block.output`` or ``block.derivative`` (``which``) for batches of ``batch``
    variants, run by the native code of the block's kernel: call it as the method,
    ``f(t, x, u)``."""

    def __init__(self, block, which: str, batch: int):
        traced, self._engine, address, _ = _compile(block, which)
        self._fn = _CALL(address)
        self.block, self.which = block, which
        B = self.batch = max(int(batch), traced.W.shape[0])
        if traced.W.shape[0] not in (1, B):
            raise sz.Untraceable("parameter rows differ from the batch")
        self.slots = traced.slots
        self.has_state = traced.has_state
        self.W = np.ascontiguousarray(traced.W)
        self.shapes = traced.shapes
        self.sizes = [int(np.prod(s, dtype=np.int64)) for s in self.shapes]
        self.width = sum(self.sizes)
        self.out = np.zeros((B, self.width))
        self.buffers = [np.zeros((B,) + s) for s in self.slots]
        n_slots = len(self.slots) + 2
        self.table = np.zeros(1 + 2 * n_slots, dtype=np.int64)
        self.table[0] = B
        for k, buf in enumerate(self.buffers):
            self._point(k, buf)
        self._point(n_slots - 2, self.W)
        self._point(n_slots - 1, self.out)
        self._table = int(self.table.__array_interface__["data"][0])
        self.held = [None] * len(self.slots)     # the array read in place, per slot
        self.seen = [None] * len(self.slots)     # the array copied at the last call

    def _point(self, k: int, arr: np.ndarray) -> None:
        self.table[1 + 2 * k] = arr.__array_interface__["data"][0]
        self.table[2 + 2 * k] = arr.strides[0] // 8 if arr.shape[0] > 1 else 0

    def _in_place(self, k: int, a) -> bool:
        """Read ``a`` in place at slot k from now on, if its layout allows."""
        shape = self.slots[k]
        if not (isinstance(a, np.ndarray) and a.dtype == _F8 and a.shape[1:] == shape
                and a.shape[0] in (1, self.batch) and a.strides[0] % 8 == 0):
            return False
        step = 8
        for n, s in zip(reversed(shape), reversed(a.strides[1:])):
            if n > 1 and s != step:
                return False
            step *= n
        if a.__array_interface__["data"][0] % 8:
            return False
        self._point(k, a)
        self.held[k] = a
        return True

    def __call__(self, t, x, u):
        arrays = ((x,) if self.has_state else ()) + tuple(u)
        try:
            for k, a in enumerate(arrays):
                if a is self.held[k]:
                    continue
                if a is self.seen[k] and self._in_place(k, a):
                    continue
                if self.held[k] is not None:          # back to the copy
                    self.held[k] = None
                    self._point(k, self.buffers[k])
                self.seen[k] = a
                self.buffers[k][...] = a
        except ValueError:              # not an array of the declared shape: the method
            return getattr(type(self.block), self.which)(self.block, t, x, u)
        self._fn(float(t), self._table)
        r = self.out.copy()
        if self.which == "derivative":
            return r
        if len(self.shapes) == 1:
            return (r.reshape((self.batch,) + self.shapes[0]),)
        out, c = [], 0
        for shape, size in zip(self.shapes, self.sizes):
            out.append(r[:, c:c + size].reshape((self.batch,) + shape))
            c += size
        return tuple(out)


def native_kernel(block, which: str, batch: int):
    """A ``NativeKernel`` of ``block``'s kernel ``which`` for ``batch`` variants, or None
    when the tracer refuses it, or LLVM fails (one warning line: a fault of fwdstep's, not
    the diagram's); the block's method runs then, with the same numbers."""
    if block.kernels is None or getattr(block.kernels, which, None) is None:
        return None
    try:
        return NativeKernel(block, which, batch)
    except sz.Untraceable:
        return None
    except RuntimeError as exc:                       # llvmlite's parse, verify, compile
        reason = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        compiled_cache.warn(f"block {block.name!r}: its native {which} kernel did not "
                            f"compile ({reason}); running its method")
        return None
