"""Optional compiled backend: the whole fixed-step run as one numba-compiled loop.

Chosen with ``simulation: {backend: compiled}``, ``--backend compiled`` or
``simulate(d, backend="compiled")``; needs ``pip install fwdstep[fast]`` (numba).  Only this
module (and ``fwdstep.compiled.compiled_ops`` / ``fwdstep.compiled.compiled_cache``) import numba, and only
the compiled backend imports them.

Nothing here restates a block's equations.  Each block declares its numerics once as
kernels (``Block.set_kernels``, docs/writing-blocks.md).  Two ways to compile them:

* **Scalar stages** (the default when every kernel traces): ``fwdstep.compiled.scalarize`` runs each
  kernel once on symbols and ``_ScalarStage`` holds the stage as straight-line scalar
  code (no array, no call inside), which ``fwdstep.compiled.llvm_stage`` compiles with LLVM in a
  fraction of a second; the fixed-step loop is a text shared by every structure (numba,
  compiled once per machine and solver, cached), which calls the stage through a function
  pointer.  A never-seen structure compiles only its stage.  The code is written for the
  sizes and for the pattern of the parameter values (which entries are 0, 1, -1 or
  equal), so another size or pattern is another stage.
* **Array code** (``_Stage``), for kernels that cannot be traced (a branch on a signal,
  complex numbers, a table lookup), object-mode blocks, and sweeps whose batches differ in
  sizes (``CompiledDiagram.sizes_at_run_time``: one program for all their sizes).

For the array code, this module jits *those functions*
(``jit_kernel``: the helpers of ``fwdstep.core.kernelops`` they call are bound to their loops in
``fwdstep.compiled.compiled_ops``) and generates one Python module whose ``run_one`` is the
fixed-step loop of ``fwdstep.simulate`` (procedure Step: outputs in schedule order, a
record at stage 1, derivatives, the RK sums, the bound test) for one variant, with every
kernel call written out in it.  Linear blocks are fused as on the NumPy path
(``fwdstep.core.linear.plan_fusion``), from their ``linear_form``.

The generated text depends on the diagram's *structure* only (which kernels, how they are
wired, the ranks of the signals): every number — parameters, sizes, state offsets — is an
argument, so a sweep over ell or n compiles once.  It is stored in the compiled-code cache
(``fwdstep.compiled.compiled_cache``: private directory, content-hash checked) under a hash that
includes the digest of every function it compiles (bytecode and frozen globals, as loaded),
so an edited block never reuses stale machine code.  The kernels themselves (and the
helpers they call) are cached by numba in ``<cache>/kernels/<key>``, the key hashing the
digests of every function they depend on, so a
never-seen structure built from known blocks compiles only its own loop.

Batches (``fwdstep sweep --backend compiled``): ``run_all`` runs the variants with numba's
``prange`` over the machine's cores, each variant exactly as a single run would be.

Declared discontinuity times: the loop reads the NumPy path's plan (``fwdstep.run.events``) as
arrays (``event_arrays``) and runs a split step's sub-steps as ``fwdstep.run.program``'s
``rest_h`` does; before a sub-step whose discrete blocks update it returns (status 3) and
the caller applies ``fwdstep.run.events.apply_updates`` (docs/discrete-time.md).

Zero crossings (scalar stages): the stage evaluates the blocks' guards at every stage 1 and
compares their signs with the previous step's; the loop returns a step where one changed
(status 4, the state back at its start) and ``fwdstep.compiled.driver`` takes it with
``fwdstep.run.crossings`` (``_guard_check``).
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import importlib
import math
import os
import sys
import types
import warnings
import weakref

import numpy as np
from numba import njit

from fwdstep.compiled import compiled_cache
from fwdstep.compiled import scalarize as sz

from fwdstep.compiled import compiled_ops

from fwdstep.core import kernelops
from fwdstep.core.errors import ConfigError
from fwdstep.core.linear import plan_fusion
from fwdstep.core.solvers import TABLEAUX, step_plan
from fwdstep.run.crossings import crossing_steps

#: Steps per call of the compiled loop (Ctrl-C and progress are handled between calls).
CHUNK = 2000


# ---------------------------------------------------------------------------- kernels
_jitted: dict = {}


def jit_kernel(fn):
    """The numba dispatcher of kernel ``fn`` and the digests of the code it compiles.

    ``fn``'s globals are copied with ``fwdstep.core.kernelops`` (the module or its functions)
    replaced by ``fwdstep.compiled.compiled_ops`` and every other plain Python function replaced by
    its own jitted version (recursively), so a kernel may call helpers of its module.

    The digests (``_function_digest``: "module.qualname sha") are of the functions *in
    memory* — the bytecode numba compiles and the global values it freezes — not of their
    files: a file edited after it was imported must not label machine code compiled from
    the old text as the new text's."""
    key = fn
    if key in _jitted:
        return _jitted[key]
    files = {_function_digest(fn)}
    g = dict(fn.__globals__)
    for name in sz.global_names(fn.__code__):
        value = g.get(name)
        if value is kernelops:
            g[name] = _OpsNamespace()
            files |= _ops_digests()
        elif isinstance(value, types.FunctionType):
            if getattr(value, "__module__", "") == kernelops.__name__:
                value = getattr(compiled_ops, value.__name__).py_func
            sub, sub_files = jit_kernel(value)
            g[name] = sub
            files |= sub_files
        elif isinstance(getattr(value, "py_func", None), types.FunctionType):
            files |= _dispatcher_digests(value.py_func)     # a user's own @njit helper
    clone = types.FunctionType(fn.__code__, g, fn.__name__, fn.__defaults__, fn.__closure__)
    clone.__module__ = fn.__module__
    clone.__qualname__ = fn.__qualname__
    dispatcher = njit(cache=False)(clone)
    _cache_on_disk(dispatcher, files)
    _jitted[key] = (dispatcher, files)
    return _jitted[key]


_ops_namespace: list = []


def _OpsNamespace():
    """``fwdstep.core.kernelops`` as kernels see it in compiled code: a module whose functions
    are the cached jitted twins of ``fwdstep.compiled.compiled_ops``."""
    if not _ops_namespace:
        ops = types.ModuleType("fwdstep._compiled_kernelops")
        for name in dir(compiled_ops):
            value = getattr(compiled_ops, name)
            if hasattr(value, "py_func"):
                setattr(ops, name, jit_kernel(value.py_func)[0])
        _ops_namespace.append(ops)
    return _ops_namespace[0]


_kernel_folders: set = set()
_key_folders: dict = {}


def _cache_on_disk(dispatcher, files: set) -> None:
    """Let numba cache ``dispatcher``'s machine code in a private folder of the compiled-code
    cache keyed by the digests ``files`` of every function it compiles (and the numba and
    Python versions), so a new structure compiles only its generated loop and an edited
    kernel never reuses stale code (numba's own key ignores the functions a kernel calls)."""
    import numba
    from numba.core import config
    key = hashlib.sha256("\n".join(
        [numba.__version__, sys.version] + sorted(files)).encode()).hexdigest()[:24]
    if key not in _key_folders:            # checked once per process (hashes every file)
        _key_folders[key] = compiled_cache.kernel_folder(key)
    folder = _key_folders[key]
    if folder is None:
        return
    old = config.CACHE_DIR
    config.CACHE_DIR = folder
    try:
        dispatcher.enable_caching()
    except Exception as exc:  # noqa: BLE001 - a cache fault never stops a run
        compiled_cache.warn(f"kernel cache unusable ({type(exc).__name__}: {exc}"[:200] + ")")
    finally:
        config.CACHE_DIR = old
    _kernel_folders.add(folder)


def seal_kernels() -> None:
    """Record the hashes of the kernel cache files written so far (see compiled_cache)."""
    for folder in sorted(_kernel_folders):
        compiled_cache.seal_folder(folder)


def kernel(module: str, qualname: str):
    """The jitted kernel ``module.qualname`` (used by the generated module)."""
    mod = sys.modules.get(module) or importlib.import_module(module)
    return jit_kernel(getattr(mod, qualname))[0]


def _function_digest(fn) -> str:
    """"module.qualname sha": the SHA-256 of what numba compiles of ``fn`` — its bytecode,
    constants and names (line numbers excluded: an edited comment changes nothing) and the
    values of the plain globals it reads, which numba freezes into the machine code."""
    h = hashlib.sha256()
    _hash_code(h, fn.__code__)
    h.update(repr(fn.__defaults__).encode())
    for name in sorted(sz.global_names(fn.__code__)):
        value = fn.__globals__.get(name, _MISSING)
        if isinstance(value, (types.FunctionType, types.ModuleType)) or hasattr(
                value, "py_func"):
            continue                      # functions: their own digests; modules: by name
        h.update(f"\0{name}=".encode())
        if value is _MISSING:             # a builtin or an attribute name: the name alone
            h.update(b"?")                # (repr(_MISSING) holds an address: another key in
        elif isinstance(value, np.ndarray):     # every process, so no cache hit ever)
            h.update(f"{value.dtype.str}{value.shape}".encode() + value.tobytes())
        elif isinstance(value, (bool, int, float, complex, str, bytes, tuple, type(None),
                                np.generic)):
            h.update(repr(value).encode())
        else:
            h.update(type(value).__qualname__.encode())
    return f"{fn.__module__}.{fn.__qualname__} {h.hexdigest()[:16]}"


_MISSING = object()


def _hash_code(h, code) -> None:
    h.update(code.co_code)
    h.update(repr((code.co_names, code.co_varnames, code.co_freevars, code.co_cellvars,
                   code.co_argcount, code.co_kwonlyargcount, code.co_flags)).encode())
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            _hash_code(h, const)
        else:
            h.update(repr(const).encode())


def _ops_digests() -> set:
    """The digests of every numba twin of ``fwdstep.compiled.compiled_ops`` (what kernelops is bound to)."""
    out: set = set()
    for name in dir(compiled_ops):
        value = getattr(compiled_ops, name)
        if hasattr(value, "py_func"):
            out |= jit_kernel(value.py_func)[1]
    return out


def _dispatcher_digests(fn, seen=None) -> set:
    """Digests of an already-jitted helper's Python function and the functions it calls."""
    seen = set() if seen is None else seen
    if fn in seen:
        return set()
    seen.add(fn)
    out = {_function_digest(fn)}
    for name in sz.global_names(fn.__code__):
        value = fn.__globals__.get(name)
        value = getattr(value, "py_func", value)
        if isinstance(value, types.FunctionType):
            out |= _dispatcher_digests(value, seen)
    return out


def refusal(block) -> str | None:
    """Why ``block`` cannot run compiled, or None."""
    if type(block).cannot_compile:
        return type(block).cannot_compile
    if python_block(block):
        return None
    k = block.kernels
    if getattr(block, "linear_form", None) is not None and _fusable_alone(block):
        return None
    if k is None or (k.output is None and block.outputs) or (
            block.n_states and k.derivative is None):
        return "it declares no kernels (docs/writing-blocks.md)"
    for fn in (k.output, k.derivative):
        if fn is not None and (not isinstance(fn, types.FunctionType) or "<locals>"
                               in fn.__qualname__ or fn.__name__ == "<lambda>"):
            return (f"its kernel {getattr(fn, '__qualname__', fn)!r} is not a module-level "
                    "function")
    return None


def python_block(block) -> bool:
    """Whether the compiled loop calls ``block``'s methods through object mode
    (``compile_with = "objmode"``, fwdstep/core/block.py) instead of jitting its kernels; a
    ``"traced"`` block's kernels are traced into the scalar stage, and only the array code
    (a stage that does not trace) calls its methods through object mode."""
    how = type(block).compile_with
    if how not in ("numba", "objmode", "traced"):
        raise ConfigError(f"block '{block.name}' ({block.type_name}): compile_with must be "
                          f"'numba', 'objmode' or 'traced', not {how!r}", block=block.name)
    return how in ("objmode", "traced")


def _traced_only(block) -> bool:
    """A ``compile_with = "traced"`` block with kernels: the scalar stage traces them."""
    return type(block).compile_with == "traced" and block.kernels is not None


def _in_python(block) -> bool:
    """Whether the loop calls ``block``'s methods in object mode: it asks to
    (``python_block``), or it is a linear block without kernels that the fusion left alone
    (too large: Theorem 6's filter bank on the robots, 903 states); its NumPy-path methods
    (scipy.sparse products) are then its one definition, as on the NumPy path."""
    return python_block(block) or block.kernels is None or (
        block.kernels.output is None and bool(block.outputs))


def _fusable_alone(block) -> bool:
    from fwdstep.core.linear import fusable
    return fusable(block)


# ---------------------------------------------------------------------------- code generation
class _Gen:
    """Names, arguments and lines of one generated module."""

    def __init__(self):
        self.args: list = []        # (name, value) run-time arguments after the fixed ones
        self.ints: list = []        # layout integers, the array I
        self.imports: list = []     # header lines binding kernels
        self.files: set = set()
        self.kernels: dict = {}     # id(fn) -> name
        self.python: list = []      # blocks called through object mode, by number

    def arg(self, prefix: str, value) -> str:
        name = f"{prefix}{len(self.args)}"
        self.args.append((name, value))
        return name

    def i(self, value: int) -> str:
        self.ints.append(int(value))
        return f"I[{len(self.ints) - 1}]"

    def kern(self, fn) -> str:
        if id(fn) not in self.kernels:
            _, files = jit_kernel(fn)
            self.files |= files
            name = f"k{len(self.kernels)}"
            self.kernels[id(fn)] = name
            self.imports.append(f"{name} = _kernel({fn.__module__!r}, {fn.__qualname__!r})")
        return self.kernels[id(fn)]


def _unflat(buf: str, a: int, b: int, shape: tuple, gen: _Gen) -> str:
    """Columns a:b of row 0 of the (1, n) array ``buf`` as a (1, *shape) signal: a view when
    ``buf`` is C-contiguous (no copy, no allocation)."""
    if shape == ():
        return f"_view0({buf}, {gen.i(a)})"
    if len(shape) == 1:
        return f"_view1({buf}, {gen.i(a)}, {gen.i(b - a)})"
    if len(shape) == 2:
        return f"_view2({buf}, {gen.i(a)}, {gen.i(shape[0])}, {gen.i(shape[1])})"
    dims = ", ".join(gen.i(s) for s in shape)
    return f"_viewn({buf}, {gen.i(a)}, {gen.i(b - a)}, ({dims},))"


class _Stage:
    """Emits one stage's output pass and derivative pass for the ops of a schedule."""

    def __init__(self, gen: _Gen, d_shapes, ops, fused, consts):
        self.gen, self.shapes, self.ops, self.fused = gen, d_shapes, ops, fused
        self.sig = {}
        self.params = {}
        for idx, arr in consts.items():
            self.sig[idx] = gen.arg("C", np.ascontiguousarray(arr, dtype=np.float64))
        self.zeros = {}
        self.group_y = {}
        self.group_no = {}
        self.block_args = {}
        for kind, op, _ in ops:
            if kind == "call" and _in_python(op.block):
                gen.python.append(op.block)
                self.block_args[id(op)] = len(gen.python) - 1
            elif kind == "call":
                blk = op.block
                names = [gen.arg("P", np.ascontiguousarray(getattr(blk.p, n), dtype=np.float64))
                         for n in blk.kernels.params]
                names += [gen.arg("S", v) for v in blk.kernels.static]
                self.block_args[id(op)] = names
                for n in names:
                    if n.startswith("P"):
                        self.params[n] = True
        # the program's entry in the table of object-mode blocks (set by build_program)
        self.handle = gen.arg("H", np.zeros(1, dtype=np.int64)) if gen.python else None
        self.groups = {}
        self.group_plan = {}
        self.prologue = {}          # group number -> lines allocating its buffers
        for kind, op, owner in ops:
            if kind == "group":
                self.group_plan[id(op)] = owner
                self.group_no[id(op)] = len(self.group_no)
                M = np.ascontiguousarray(op.M, dtype=np.float64)
                self.groups[id(op)] = gen.arg("P", M)
                self.params[self.groups[id(op)]] = True

    def _zero(self, idx):
        if idx not in self.zeros:
            self.zeros[idx] = self.gen.arg("Z", np.zeros((1,) + tuple(self.shapes[idx])))
        return self.zeros[idx]

    def _read(self, u, done):
        """Signal u, or (read before its producer ran this stage: only by an output that
        does not depend on it, by the feedthrough contract) a zero array of its shape."""
        return f"s{u}" if u in done else self._zero(u)

    @staticmethod
    def _inputs(names, k) -> list:
        """The input arguments: one by one, or (``tuple_inputs``) one tuple of contiguous
        arrays (a homogeneous tuple numba can index with a loop variable)."""
        if not k.tuple_inputs:
            return names
        return ["(" + "".join(f"np.ascontiguousarray({n}), " for n in names) + ")"]

    def _xs(self, buf, step):
        gen = self.gen
        if step.state is None:
            return f"{buf}[:, 0:0]"
        return f"{buf}[:, {gen.i(step.state.start)}:{gen.i(step.state.stop)}]"

    def outputs(self, buf: str, ts: str) -> list:
        gen, lines, done = self.gen, [], set(self.sig)
        for idx, name in self.sig.items():
            lines.append(f"s{idx} = {name}")
        for kind, op, _ in self.ops:
            if kind == "group":
                if op.outputs:
                    lines += self._group(op, buf, done)
                    done.update(idx for idx, _ in op.outputs)
                continue
            blk = op.block
            if _in_python(blk):
                if blk.outputs:
                    lines += self._python_call(op, "_pyout", buf, ts, [
                        (f"s{idx}", len(self.shapes[idx])) for idx in op.outputs],
                        [self._read(u, done) for u in op.inputs])
                    done.update(op.outputs)
                continue
            k = blk.kernels
            if k.output is None:
                continue
            args = self._inputs([self._read(u, done) for u in op.inputs], k)
            args += self.block_args[id(op)]
            call = f"{gen.kern(k.output)}({ts}, {self._xs(buf, op)}{''.join(', ' + a for a in args)})"
            if k.packed:
                lines.append(f"r = {call}")
                c = 0
                for idx in op.outputs:
                    shape = tuple(self.shapes[idx])
                    size = int(np.prod(shape, dtype=np.int64)) if shape else 1
                    lines.append(f"s{idx} = " + _unflat("r", c, c + size, shape, gen))
                    c += size
            else:
                lines.append(f"r = {call}")
                for j, idx in enumerate(op.outputs):
                    lines.append(f"s{idx} = r[{j}]")
            done.update(op.outputs)
        return lines

    def _python_call(self, op, fn, buf, ts, results, inputs) -> list:
        """Block number j's method called in object mode: ``results`` are (variable, rank of
        the signal); each comes back as a C-contiguous float64 array (1, *shape), the type
        numba is told from the declared port's rank (the sizes stay run-time values)."""
        j = self.block_args[id(op)]
        types_ = ", ".join(f'{name}="float64[{", ".join([":"] * rank + ["::1"])}]"'
                           for name, rank in results)
        targets = "".join(f"{name}, " for name, _ in results)
        return [f"xo{j} = {self._xs(buf, op)}",
                f"with _objmode({types_}):",
                f"    {targets}= {fn}({self.handle}[0], {j}, v, {ts}, xo{j}"
                f"{''.join(', ' + a for a in inputs)})"]

    def _group(self, op, buf, done) -> list:
        """The fused product [inputs] @ M into the group's buffers V, Y (allocated once per
        call of run_one, before the loop); its output signals are views of Y."""
        gen = self.gen
        no = self.group_no[id(op)]
        v, y, M = f"V{no}", f"Y{no}", self.groups[id(op)]
        if no not in self.prologue:
            n_in = sum(n for _, n in op.inputs)
            self.prologue[no] = [f"{v} = _zeros({gen.i(n_in)})",
                                 f"{y} = _zeros({M}.shape[2])"]
        lines = []
        c = 0
        for term, n in op.inputs:
            if term == "x":
                sl = self.group_plan[id(op)].state
                lines.append(f"_copy({v}, {gen.i(c)}, {buf}, {gen.i(sl.start)}, {gen.i(n)})")
            else:
                rank = len(self.shapes[term])
                put = "_put0" if rank == 0 else "_put1" if rank == 1 else "_put2" \
                    if rank == 2 else "_putn"
                lines.append(f"{put}({v}, {gen.i(c)}, {self._read(term, done)})")
            c += n
        lines.append(f"_vecmat_into({v}, {M}, {y})")
        c = 0
        for idx, n in op.outputs:
            lines.append(f"s{idx} = " + _unflat(y, c, c + n, tuple(self.shapes[idx]), gen))
            c += n
        self.group_y[id(op)] = (y, c)
        return lines

    def derivatives(self, buf: str, ts: str, kbuf: str) -> list:
        gen, lines = self.gen, []
        done = set(range(len(self.shapes)))
        fused = self.fused
        for kind, op, owner in self.ops:
            if kind == "group":
                if not op.derivative:
                    continue
                plan = owner
                sl = plan.state
                dst = f"{kbuf}, {gen.i(sl.start)}, {gen.i(sl.stop - sl.start)}"
                if op.outputs:
                    y, c = self.group_y[id(op)]
                    lines.append(f"_store({dst}, {y}, {gen.i(c)})")
                else:
                    lines += self._group(op, buf, done)
                    y, _ = self.group_y[id(op)]
                    lines.append(f"_store({dst}, {y}, {gen.i(0)})")
                continue
            blk = op.block
            if op.state is None or blk.name in fused:
                continue
            if _in_python(blk):
                d = f"dx{self.block_args[id(op)]}"
                lines += self._python_call(op, "_pyder", buf, ts, [(d, 1)],
                                           [f"s{u}" for u in op.inputs])
                lines.append(f"_store({kbuf}, {gen.i(op.state.start)}, "
                             f"{gen.i(op.state.stop - op.state.start)}, {d}, {gen.i(0)})")
                continue
            args = self._inputs([f"s{u}" for u in op.inputs], blk.kernels)
            args += self.block_args[id(op)]
            call = (f"{gen.kern(blk.kernels.derivative)}({ts}, {self._xs(buf, op)}"
                    f"{''.join(', ' + a for a in args)})")
            lines.append(f"_store({kbuf}, {gen.i(op.state.start)}, "
                         f"{gen.i(op.state.stop - op.state.start)}, {call}, {gen.i(0)})")
        return lines


class _ScalarStage(sz.ParameterColumns):
    """One stage as straight-line scalar code: every kernel traced once on symbols
    (``fwdstep.compiled.scalarize``), every fused group written out entry by entry (the entries of M
    that are zero in every variant left out).  Raises ``Untraceable`` when a kernel cannot
    be traced or an object-mode block is present (the array code of ``_Stage`` is used then).

    ``fwdstep.compiled.llvm_stage`` compiles it to a function that the loop (``_module_source``
    without a ``_Stage``: one text for every structure, compiled once per machine and
    solver and cached) calls through a function pointer.  The function works in a variant's
    workspace ``ws`` = [x_i (N), k_1..k_S (S N), the variant's row of ``W`` (every parameter
    entry is a column of W), Z (the nodes that depend on parameters only, computed once per
    call of the loop: mode 3), G (the zero-crossing guards, ``Block.zero_crossings``, written
    by every stage 1 that makes derivatives)]; logged signals are columns of one array ``LL``
    (rows, variants, columns) whose slices are the logs.  The guards are traced like every
    kernel, from the blocks' own ``zero_crossings`` (or their declared guard kernel), so
    the compiled loop compares the same numbers as ``fwdstep.run.crossings``."""

    def __init__(self, d, shapes, ops, fused, consts, logs, unlogged, n_stages):
        self.columns: list = []         # the values of W's columns over the variants
        self._by_values: dict = {}
        tr = self.tr = sz.Trace()
        rb = sz.Rebinder(tr)
        x = sz.sym_array(tr, (1, d.n_states), lambda idx: (f"x{idx[1]}", False))
        ts = tr.leaf("ts", False)
        sig = {idx: self._param(arr) for idx, arr in consts.items()}

        def zeros(idx):
            return sz.as_nodes(tr, 0.0, (1,) + shapes[idx])

        def state(op):
            if op.state is None:
                return x[:, 0:0]
            return x[:, op.state.start:op.state.stop]

        block_args, group_y = {}, {}
        for kind, op, _ in ops:
            if kind == "call":
                if _in_python(op.block) and not _traced_only(op.block):
                    raise sz.Untraceable(f"block {op.block.name!r} runs in object mode")
                k = op.block.kernels
                block_args[id(op)] = [self._kernel_param(op.block, n)
                                      for n in k.params] + list(k.static)

        def call(fn, op, inputs):
            if op.block.kernels.tuple_inputs:
                inputs = [tuple(inputs)]
            return sz.run_traced(rb, fn, ts, state(op), *inputs, *block_args[id(op)])

        def group(op, owner, done):
            v = []
            for term, n in op.inputs:
                if term == "x":
                    v.extend(x[0, owner.state.start:owner.state.stop])
                else:
                    v.extend((sig[term] if term in done else zeros(term)).reshape(-1))
            M = np.asarray(op.M, dtype=np.float64)
            nz = self._group_mask(op, M)
            y = []
            for j in range(M.shape[2]):
                acc = None
                for i in range(M.shape[1]):
                    if nz[i, j]:
                        term = v[i] * self._group_entry(op, M, i, j)
                        acc = term if acc is None else acc + term
                y.append(tr.const(0.0) if acc is None else acc)
            return y

        # the output pass (a signal read before its producer ran is zero, as in _Stage)
        done = set(sig)
        for kind, op, owner in ops:
            if kind == "group":
                if op.outputs:
                    y = group_y[id(op)] = group(op, owner, done)
                    c = 0
                    for idx, n in op.outputs:
                        sig[idx] = np.array(y[c:c + n], dtype=object).reshape(
                            (1,) + shapes[idx])
                        c += n
                    done.update(idx for idx, _ in op.outputs)
                continue
            k = op.block.kernels
            if k.output is None:
                continue
            r = call(k.output, op, [sig[u] if u in done else zeros(u) for u in op.inputs])
            if k.packed:
                sizes = [int(np.prod(shapes[i], dtype=np.int64)) for i in op.outputs]
                flat = sz.as_nodes(tr, r, (1, sum(sizes)))
                c = 0
                for idx, n in zip(op.outputs, sizes):
                    sig[idx] = flat[:, c:c + n].reshape((1,) + shapes[idx])
                    c += n
            else:
                if len(r) != len(op.outputs):
                    raise sz.Untraceable(f"{len(r)} outputs where {len(op.outputs)} declared")
                for j, idx in enumerate(op.outputs):
                    sig[idx] = sz.as_nodes(tr, r[j], (1,) + shapes[idx])
            done.update(op.outputs)
        # the derivative pass: (state index, node)
        der = []
        everything = set(range(len(shapes)))
        for kind, op, owner in ops:
            if kind == "group":
                if not op.derivative:
                    continue
                sl = owner.state
                if op.outputs:
                    y, c = group_y[id(op)], sum(n for _, n in op.outputs)
                else:
                    y, c = group(op, owner, everything), 0
                der += [(sl.start + i, y[c + i]) for i in range(sl.stop - sl.start)]
                continue
            blk = op.block
            if op.state is None or blk.name in fused:
                continue
            r = call(blk.kernels.derivative, op, [sig[u] for u in op.inputs])
            n = op.state.stop - op.state.start
            dx = sz.as_nodes(tr, r, (1, n))
            der += [(op.state.start + i, dx[0, i]) for i in range(n)]
        # records: logged signals (columns of LL) and the finite checks of the others
        self.records, self.checked, roots = [], [], []
        self.log_columns = []
        col = 0
        for idx in logs:
            self.log_columns.append(col)
            for pos in np.ndindex(*shapes[idx]):
                node = sig[idx][(0,) + pos]
                roots.append(node)
                self.records.append((col, node))
                col += 1
        self.log_width = col
        for idx in unlogged:
            nodes = [n for n in sig[idx].reshape(-1) if n.op != "const"]
            roots += nodes
            self.checked += nodes
        self.der = der
        self._extend(x, sig, logs, shapes, roots)
        der = self.der
        # the guards at stage 1, from the signals of the output pass
        self.guards = []
        for step in crossing_steps(d):
            self.guards += list(self._guards(rb, step, ts, state(step), [
                sig[u] for u in step.inputs]).reshape(-1))
        need_d = tr.needed([node for _, node in der])
        need_r = tr.needed(roots) - need_d
        need_g = tr.needed(self.guards) - need_d
        inv = sorted(n for n in need_d | need_r | need_g if tr.nodes[n].invariant)
        self.inv, self.n_invariants = inv, len(inv)
        self.need_d = sorted(need_d - set(inv))
        self.need_r = sorted(need_r - set(inv))
        self.need_g = sorted(need_g - set(inv))
        self.n_nodes = len(need_d | need_r | need_g)
        self.W = self.column_matrix()
        # the workspace ws of a variant: x_i (N), k_1..k_S (S N), W's row, Z
        self.n_states = self._total_states(d)
        self.n_columns = len(self.columns)
        self.ow = self.n_states + n_stages * self.n_states
        self.oz = self.ow + self.n_columns
        self.og = self.oz + self.n_invariants
        self.n_guards = len(self.guards)

    def _guards(self, rb, step, ts, x, inputs) -> np.ndarray:
        """Block ``step.block``'s guards (1, n_crossings) as nodes: its declared guard
        kernel, or its ``zero_crossings`` method run with ``self.p`` read as parameter
        leaves (each variant's values, as the kernels' parameters are)."""
        blk = step.block
        m = blk.n_crossings
        ck = getattr(blk, "crossing_kernel", None)
        if ck is not None and "zero_crossings" not in vars(type(blk)) \
                and "zero_crossings" not in blk.__dict__:      # (as fwdstep.run.program)
            out = sz.as_nodes(self.tr, 0.0, (1, m)).copy().view(sz.SymArray)
            sz.run_traced(rb, ck[0], out, ts, x, *inputs,
                          *(self._param(getattr(blk.p, n)) for n in ck[1]))
            return out
        if "zero_crossings" in blk.__dict__:
            raise sz.Untraceable(f"block {blk.name!r}: zero_crossings set on the instance")
        proxy = _TracedParams(blk, self._param, rb)
        r = sz.run_traced(rb, type(blk).zero_crossings, proxy, ts, x, tuple(inputs))
        r = np.asarray(r, dtype=object)
        while r.ndim > 2 and r.shape[0] == 1:   # leading ones: dropped, as the NumPy
            r = r[0]                            # path's assignment into its G drops them
        return sz.as_nodes(self.tr, r, (1, m))

    # hooks of a stage that integrates more than the diagram's state (the variational
    # equations of fwdstep.analysis.compiled_sensitivity); here: the diagram's stage
    def _kernel_param(self, blk, name: str):
        """The kernel argument ``blk.p.<name>`` as leaves."""
        return self._param(getattr(blk.p, name))

    @staticmethod
    def _group_mask(op, M):
        """The entries of a fused group's matrix written into the code."""
        return np.any(M != 0.0, axis=0)

    def _group_entry(self, op, M, i: int, j: int):
        """Entry (i, j) of a fused group's matrix as a node."""
        return self._leaf(M[:, i, j])

    def _extend(self, x, sig, logs, shapes, roots) -> None:
        """Add derivative entries (``self.der``), records (``self.records``, widening
        ``self.log_width``) and their roots, after the diagram's own."""

    def _total_states(self, d) -> int:
        """The entries of the integrated state (x first)."""
        return d.n_states


class _TracedParams:
    """A block seen by its traced ``zero_crossings``: ``p.<name>`` are parameter leaves
    (``_ScalarStage._param``), its methods traced on this view too, every other attribute
    the block's own (a constant of the structure)."""

    def __init__(self, block, param, rebinder):
        self._block, self._rebinder = block, rebinder
        self.p = _LazyParams(block.p, param)

    def __getattr__(self, name):
        fn = getattr(type(self._block), name, None)
        if isinstance(fn, types.FunctionType):
            return types.MethodType(self._rebinder.function(fn), self)
        return getattr(self._block, name)


class _LazyParams:
    """``block.p`` with each array read as leaves on first use (unused ones add no column)."""

    def __init__(self, p, param):
        self._p, self._param, self._done = p, param, {}

    def __getattr__(self, name):
        if name not in self._done:
            value = getattr(self._p, name)
            self._done[name] = self._param(value) if isinstance(value, np.ndarray) else value
        return self._done[name]


#: Diagrams with more parameter entries than this keep the array code (their scalar code
#: would be long to compile).
MAX_SCALAR_PARAMS = sz.MAX_SCALAR_PARAMS


def _ops_for(schedule, shapes, consts):
    """The evaluation ops: the fusion plan's, with linear blocks the plan left alone (too
    large to fuse together) as groups of their own."""
    plan = plan_fusion(schedule, shapes, consts)
    ops = plan.ops if plan is not None else [("call", s) for s in schedule]
    out, fused = [], set(plan.fused) if plan is not None else set()
    for kind, op in ops:
        if kind == "call" and (op.block.kernels is None or (
                op.block.kernels.output is None and op.block.outputs)):
            single = plan_fusion([op], shapes, consts)
            if single is not None:
                fused |= single.fused
                out += [(k, o, single) for k, o in single.ops]
                continue
        out.append((kind, op, plan))
    return out, fused


_last_ops: dict = {}


def _diagram_ops(d, keep: bool = False) -> tuple:
    """(shapes, ops, fused) of diagram ``d``.  ``keep``: for the next call, which takes it
    (``simulate`` asks twice per run: whether the guards trace, then to build the program;
    nothing changes the diagram in between, while a later run may have changed its
    parameters, hence its fused matrices)."""
    got = _last_ops.pop("last", None)
    if got is not None and got[0]() is d:
        return got[1]
    shapes = [tuple(s) for s in d.signal_shapes]
    ops, fused = _ops_for(d.schedule, shapes, d.constant_signals)
    if keep:
        _last_ops["last"] = (weakref.ref(d), (shapes, ops, fused))
    return shapes, ops, fused


def check_compilable(d) -> None:
    """Refuse, in one line naming the block, a diagram the compiled backend cannot run."""
    for step in d.schedule:
        reason = refusal(step.block)
        if reason is not None:
            blk = step.block
            raise ConfigError(f"backend 'compiled' cannot run block '{blk.name}' "
                              f"({blk.type_name}): {reason}; use --backend numpy",
                              file=d.file)


# ---------------------------------------------------------------------------- the program
class CompiledProgram:
    """The run functions of one diagram (any batch size), with their buffers."""

    def __init__(self, module, args, xn, X, K, logs, t_log, consts, batch, events,
                 call_logs=None):
        self.module, self.args, self.xn, self.X, self.K = module, args, xn, X, K
        self.logs, self.t_log, self.consts, self.batch = logs, t_log, consts, batch
        # the log arrays the loop writes (scalar stages: one array whose slices are logs)
        self.call_logs = logs if call_logs is None else call_logs
        self.I = consts["I"]
        # (ev_n, ev_off, ev_t, ev_r) and the Event of each row of ev_t: see event_arrays
        self.events, self.row_events = events
        self._sealed = False
        self.python = None          # fwdstep.run.python_blocks entry of object-mode blocks
        self.guards = None          # (GP, XS, GI): the zero-crossing check's (_guard_check)

    def _first_call_sealed(self) -> None:
        """Seal right after the call that compiled (not only at the end of the run), so
        another process starting meanwhile finds the cache files already recorded."""
        if not self._sealed:
            self._sealed = True
            self.seal()

    def _fixed(self):
        c = self.consts
        return (c["h"], c["every"], c["bound"], c["a"], c["c"], c["b"], self.xn, self.X,
                self.K, self.t_log, self.I, c["A"], c["C"], c["B"], *self.events)

    def run(self, n0: int, n1: int, row: int) -> tuple:
        """Variant 0, steps n0..n1-1: (status 0 ok / 1 diverged / 2 an output not finite /
        3 paused for discrete updates (``event_arrays``) / 4 a step to take on the NumPy
        path (a zero crossing in it, or it touches a declared time: ``_guard_check``), next
        step, next row)."""
        out = self.module.run_one(0, n0, n1, row, False, *self._fixed(), *self.args,
                                  *self.call_logs)
        self._first_call_sealed()
        self._check_python()
        return out

    def run_batch(self, n0: int, n1: int, rows, status, n_next, alive) -> None:
        """Every alive variant, steps n0..n1-1, in parallel; updates rows/status/n_next."""
        self.module.run_all(n0, n1, rows, status, n_next, alive, *self._fixed(), *self.args,
                            *self.call_logs)
        self._first_call_sealed()
        self._check_python()

    def _check_python(self) -> None:
        """Raise what an object-mode block raised inside the batch loop."""
        if self.python is not None:
            self.python.check()

    def compile(self) -> None:
        """Compile the run functions now, running no step (numba compiles on first call).
        ``simulate`` calls it with signals deferred: an exception raised by a signal handler
        inside numba's compiler callbacks is swallowed there and leaves a broken function.
        numba's note that first-class function types are experimental (printed, with its
        terminal colour codes, when a batch's parallel loop taking the stage is compiled) is
        not shown: the stage is always called through that one signature (``llvm_stage``),
        which the tests of every backend check."""
        from numba.core.errors import NumbaExperimentalFeatureWarning
        B = self.batch
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NumbaExperimentalFeatureWarning)
            if B == 1:
                self.run(0, 0, 0)
            else:
                z = np.zeros(B, dtype=np.int64)
                self.run_batch(0, 0, z, z.copy(), z.copy(), np.ones(B, dtype=bool))

    def seal(self) -> None:
        """Record the hashes of the machine code numba just cached (see compiled_cache).
        A scalar stage and its loop have one signature each: sealed once per process."""
        if isinstance(self.module, _ScalarModule):
            loop = self.module.loop
            if loop.__name__ not in _sealed_loops:
                _sealed_loops.add(loop.__name__)
                compiled_cache.seal(loop)
            return
        compiled_cache.seal(self.module)
        seal_kernels()

    def final(self, t: float, row: int, v: int = 0) -> int:
        """Outputs at the final time (t = n_steps h) and their record, for variant v: the
        first stage of run_one's loop, stopped after the record (no second copy of it).
        Returns 2 if an unrecorded output is not finite there, else 0."""
        n = int(round(t / self.consts["h"]))
        out = self.module.run_one(v, n, n + 1, row, True, *self._fixed(), *self.args,
                                  *self.call_logs)[0]
        self._check_python()
        return out


_traced: dict = {}


def _scalar_stage(d, shapes, ops, fused, logged, unlogged, S):
    """The ``_ScalarStage`` of a diagram, or None when it cannot be traced; memoised in
    the process by everything the trace reads (kernels, static values, parameter values,
    wiring, shapes), so running a diagram again does not trace it again."""
    from fwdstep.compiled.scalarize import Untraceable
    h, fns = stage_key(d, shapes, ops, fused, logged, unlogged, S)
    key = h.digest()
    if key not in _traced:
        try:
            st = _ScalarStage(d, shapes, ops, fused, d.constant_signals, logged, unlogged, S)
        except Untraceable:
            st = None
        _traced[key] = (fns, st)
        while len(_traced) > 64:
            _traced.pop(next(iter(_traced)))
    return _traced[key][1]


def _update_value(h, v) -> None:
    """Hash a static value exactly (an array by its bytes: ``repr`` rounds to 8 digits and
    elides long arrays)."""
    if isinstance(v, np.ndarray) and v.dtype != object:
        h.update(repr(("a", v.dtype.str, v.shape)).encode() + np.ascontiguousarray(v).data)
    elif isinstance(v, (tuple, list)):
        h.update(repr((type(v).__name__, len(v))).encode())
        for item in v:
            _update_value(h, item)
    else:
        h.update(repr(v).encode())


def stage_key(d, shapes, ops, fused, logged, unlogged, S, moving_p=None,
              moving_M=None) -> tuple:
    """(sha256 hasher, kernels): everything the trace of a diagram's scalar stage reads
    (kernels, static values, parameter values, wiring, shapes, guards); the kernels are to
    be held by the memo using the key (their ids are in it: not reused meanwhile).
    ``moving_p[(block, name)]`` / ``moving_M[id(group op)]``: boolean masks of parameter
    entries (of ``p.name``'s entry axes, flat) / fused-matrix entries (rows, columns)
    whose values are left out (only which entries they are is in the key): entries a
    stage keeps as run-time values of their own (``fwdstep.analysis.compiled_sensitivity``)."""
    moving_p, moving_M = moving_p or {}, moving_M or {}
    h = hashlib.sha256(repr((d.n_states, S, logged, unlogged, sorted(fused), shapes,
                             sorted(d.constant_signals))).encode())
    for arr in d.constant_signals.values():
        h.update(repr(np.shape(arr)).encode() + np.ascontiguousarray(arr, dtype=float).data)
    fns = []                # held by the memo: their ids are not reused meanwhile
    for kind, op, owner in ops:
        if kind == "group":
            h.update(repr(("g", op.inputs, op.outputs, op.derivative, op.M.shape,
                           owner.state)).encode())
            M = np.array(op.M, dtype=float, order="C", ndmin=1)
            mask = moving_M.get(id(op))
            if mask is not None:
                M[:, mask] = np.nan
                h.update(np.ascontiguousarray(mask).data)
            h.update(M.data)
            continue
        blk, k = op.block, op.block.kernels
        fns.append(k)
        h.update(repr(("c", blk.name, type(blk).__qualname__, _in_python(blk),
                       None if k is None else (id(k.output), id(k.derivative), k.params,
                                               k.packed, k.tuple_inputs),
                       op.inputs, op.outputs, op.state)).encode())
        if k is not None:
            _update_value(h, tuple(k.static))
        for name in (k.params if k is not None else ()):
            arr = np.array(getattr(blk.p, name), dtype=float, order="C", ndmin=1)  # a copy
            mask = moving_p.get((blk.name, name))
            if mask is not None:
                arr.reshape(arr.shape[0], -1)[:, mask] = np.nan
                h.update(np.ascontiguousarray(mask).data)
            h.update(repr(arr.shape).encode() + arr.data)
    for step in crossing_steps(d):       # the guards: their functions and parameters
        blk = step.block
        ck = getattr(blk, "crossing_kernel", None)
        h.update(repr(("z", blk.name, type(blk).__qualname__, blk.n_crossings,
                       None if ck is None else (id(ck[0]), ck[1]), step.inputs,
                       step.state)).encode())
        for name, arr in sorted(vars(blk.p).items()):
            if isinstance(arr, np.ndarray):
                a = np.ascontiguousarray(arr, dtype=float)
                h.update(repr((name, a.shape)).encode() + a.data)
    return h, fns


class _ScalarModule:
    """The run functions of a scalar stage: the cached loop module's ``run_one`` and
    ``run_all`` (numba compiles or loads them on the first call: ``CompiledProgram.compile``
    runs under deferred signals) with the stage's machine code (``fwdstep.compiled.llvm_stage``) as
    first argument."""

    def __init__(self, loop, st, fn):
        self.loop, self.st, self._fn = loop, st, fn
        self.__file__ = getattr(loop, "__file__", None)

    def run_one(self, *args):
        return self.loop.run_one(self._fn, *args)

    def run_all(self, *args):
        return self.loop.run_all(self._fn, *args)


#: names of the loop modules whose numba files were sealed in this process (one signature
#: each: nothing new is written after their first call)
_sealed_loops: set = set()


#: CPU seconds to compile, measured on the 2-core development machine (docs/performance.md,
#: "Compiling"): a scalar stage costs about STAGE_SECONDS + STAGE_SECONDS_PER_OP per scalar
#: operation (LLVM; two-link Slotine-Li, 147 operations: 0.03 s; Panda Slotine-Li, 4890:
#: 0.7 s), the loop around it LOOP_SECONDS once per machine and solver (then numba's cache:
#: 2.0 s cold), array code about ARRAY_SECONDS + ARRAY_SECONDS_PER_OP per block call
#: (two-link Slotine-Li, 7 block calls, every kernel cold: 24 s)
STAGE_SECONDS, STAGE_SECONDS_PER_OP = 0.03, 1.6e-4
LOOP_SECONDS, LOOP_LOAD_SECONDS = 2.0, 1.0
#: compiling expected to take less than this is not announced (a small stage, every run)
ANNOUNCE_FROM_SECONDS = 0.5
ARRAY_SECONDS, ARRAY_SECONDS_PER_OP = 10.0, 2.0


def compile_estimate(kind: str, operations: int) -> float:
    """About how many seconds compiling takes: kind "stage" (LLVM, scalar operations),
    "loop" (the loop around a scalar stage) or "array" (block calls)."""
    if kind == "stage":
        return STAGE_SECONDS + STAGE_SECONDS_PER_OP * operations
    if kind == "loop":
        return LOOP_SECONDS
    return ARRAY_SECONDS + ARRAY_SECONDS_PER_OP * operations


def object_mode_only(d) -> str | None:
    """Why compiling cannot make ``d`` faster, or None: its stage does not trace into scalar
    code and the array code would call blocks through numba's object mode (a Python call
    per block and stage, as the NumPy path makes, plus object mode's own cost)."""
    python = [s.block.name for s in d.schedule if _in_python(s.block)]
    if not python:
        return None
    shapes = [tuple(s) for s in d.signal_shapes]
    ops, fused = _ops_for(d.schedule, shapes, d.constant_signals)
    from fwdstep.run.finite import unlogged_signals
    logged = [d.signal_index[name] for name in d.logged]
    S = TABLEAUX[d.spec.simulation.solver].stages
    with _per_variant_kernels(d):
        if (not d.sizes_at_run_time and
                _scalar_stage(d, shapes, ops, fused, logged, unlogged_signals(d), S) is not None):
            return None
    names = ", ".join(python[:3]) + (", ..." if len(python) > 3 else "")
    return (f"its stage does not trace into scalar code and the compiled loop would call "
            f"{names} through numba's object mode")


def guards_unwatched(d) -> str | None:
    """Why the compiled loop cannot watch the zero crossings of ``d`` (they are watched in
    scalar stages only: ``_ScalarStage`` traces the guards), or None."""
    if d.sizes_at_run_time:
        return ("its zero crossings are watched in scalar code only, and its variants "
                "differ in sizes")
    shapes, ops, fused = _diagram_ops(d, keep=True)
    from fwdstep.run.finite import unlogged_signals
    logged = [d.signal_index[name] for name in d.logged]
    S = TABLEAUX[d.spec.simulation.solver].stages
    with _per_variant_kernels(d):
        if _scalar_stage(d, shapes, ops, fused, logged, unlogged_signals(d), S) is not None:
            return None
    return ("its zero crossings are watched in scalar code only, and its stage (or a "
            "block's zero_crossings) does not trace into it")


def build_program(d, n_rows: int, plan=None, scalar: bool | None = None,
                  notify=None, stage=None) -> CompiledProgram:
    """Generate, load (from the cache when possible) and bind the compiled run of ``d``;
    ``plan``: its ``fwdstep.run.events.plan_events`` (None: no declared times), whose split
    steps the loop runs as the NumPy path does (``event_arrays``).  ``scalar``: trace the
    kernels into scalar code (``_ScalarStage``; the default unless ``d.sizes_at_run_time``)
    when every kernel can be traced, else (or False) the array code of ``_Stage``, whose
    sizes are run-time values.  ``notify(what, operations, estimate)`` is called before
    anything never compiled before is compiled (what: "scalar stage" or "array code"; the
    number of scalar operations or block calls; about how many seconds it takes); the
    caller times ``CompiledProgram.compile`` after it.  ``stage``: a ``_ScalarStage`` to run
    instead of the diagram's own (one integrating more than the diagram's state, whose first
    ``d.n_states`` entries are x: only those are checked against the bound); an LLVM fault
    then raises ``Untraceable`` instead of taking the array code."""
    check_compilable(d)
    if scalar is None:
        scalar = not d.sizes_at_run_time
    with _per_variant_kernels(d):
        return _build_program(d, n_rows, plan, scalar, notify, stage)


@contextlib.contextmanager
def _per_variant_kernels(d):
    """The compiled loop runs each variant of a batch alone (``run_one``), so its blocks'
    kernels are the ones they pick for one variant (``finalize(1)``: scalar loops), not the
    vectorised ones a batch picks for the NumPy path, which numba compiles into an array
    allocation per operation (a 256-variant compiled sweep ran 40x slower per variant)."""
    swapped = []
    if d.batch > 1:
        for step in d.schedule:
            blk = step.block
            if blk.kernels is None:
                continue
            probe = copy.copy(blk)
            probe.finalize(1)
            if probe.kernels != blk.kernels:
                swapped.append((blk, blk.kernels))
                blk.kernels = probe.kernels
    try:
        yield
    finally:
        for blk, kernels in swapped:
            blk.kernels = kernels


def _build_program(d, n_rows: int, plan, scalar: bool, notify=None,
                   stage=None) -> CompiledProgram:
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    stages, final_coeffs = step_plan(tab, cfg.step)
    B, N, S = d.batch, d.n_states, tab.stages
    shapes, ops, fused = _diagram_ops(d)
    from fwdstep.run.finite import unlogged_signals      # every other output: finite, or status 2
    logged = [d.signal_index[name] for name in d.logged]
    if stage is not None:
        st, N = stage, stage.n_states
    else:
        st = _scalar_stage(d, shapes, ops, fused, logged, unlogged_signals(d), S) if scalar \
            else None
    stage_fn = None
    guard_arrays = None
    final = "xv[i]"
    for m, (j, _) in enumerate(final_coeffs):
        final = f"({final} + bw[{m}] * K2[{j}, i])"
    call = "stage({}, ts, stg, (row * B_ + vi) * width, wsp, Lp)"
    if st is not None:
        from fwdstep.compiled.llvm_stage import compile_stage
        # the loop (fixed text: compiled once per machine and solver, then cached) calls
        # the stage (compiled per structure) through a function pointer
        if st.n_guards:     # the stage's status: 4 when a guard changed sign (_guard_check)
            record = [f"cs = {call.format('2 if final else 1')}",
                      "if cs == 2: return 2, n, row + 1"]
            stage_der = ["if not (stg == 0 and q == q0 and (n % every == 0 or final)):",
                         "    cs = " + call.format("0")]
        else:
            record = [f"if {call.format('2 if final else 1')} != 0: return 2, n, row + 1"]
            stage_der = ["if not (stg == 0 and q == q0 and (n % every == 0 or final)):",
                         "    " + call.format("0")]
        gen = _Gen()
        skeleton = compiled_cache.load(_module_source(gen, None, [], record, [], stage_der,
                                                      final, stage is not None,
                                                      guards=bool(st.n_guards)))
        loop_new = not compiled_cache.compiled_before(skeleton)

        def announce():
            estimate = compile_estimate("stage", st.n_nodes) + (
                compile_estimate("loop", 0) if loop_new else LOOP_LOAD_SECONDS)
            if notify is not None and estimate >= ANNOUNCE_FROM_SECONDS:
                notify("scalar stage", st.n_nodes, estimate)
            announce.done = True
        announce.done = False
        try:
            stage_fn = compile_stage(st, before=announce)
        except Exception as exc:  # noqa: BLE001 - an LLVM fault falls back, never stops a run
            if stage is not None:
                raise sz.Untraceable(f"the stage was not compiled ({type(exc).__name__}: "
                                     f"{exc}"[:200] + ")") from None
            compiled_cache.warn(f"scalar stage not compiled ({type(exc).__name__}: "
                                f"{exc}"[:200] + "); running the array code")
            st = None
        if st is not None and loop_new and not announce.done:
            announce()
    if st is not None:
        module = _ScalarModule(skeleton, st, stage_fn)
        LL = np.full((n_rows, B, max(st.log_width, 1)), np.nan)
        logs = []
        for idx, col in zip(logged, st.log_columns):
            size = int(np.prod(shapes[idx], dtype=np.int64))
            view = LL[:, :, col:col + size].reshape((n_rows, B) + shapes[idx])
            assert np.shares_memory(view, LL)
            logs.append(view)
        args, call_logs = [st.W, st.n_invariants, LL.shape[2]], [LL.reshape(-1)]
        if st.n_guards:                 # the guards' reference values (_guard_check)
            guard_arrays = (np.zeros((B, st.n_guards)), np.zeros((B, N)),
                            np.zeros((B, 2), dtype=np.int64))
            call_logs += list(guard_arrays)
    else:
        logs = [np.full((n_rows, B) + shapes[idx], np.nan) for idx in logged]
        log_names = [f"L{k}" for k in range(len(logs))]
        gen = _Gen()
        st = _Stage(gen, shapes, ops, fused, d.constant_signals)
        record = [f"_rec(L{k}, row, v, s{idx})" for k, idx in enumerate(logged)]
        record += [f"if not _finite(s{idx}): return 2, n, row + 1"
                   for idx in unlogged_signals(d)]
        # one stage, written once, inside a loop over the stages (stage 1 reads a copy of
        # x_n): a quarter of the code numba must type and optimise for RK4
        stage_out = st.outputs("X2", "ts")
        stage_der = st.derivatives("X2", "ts", "K2, stg")
        source = _module_source(gen, st, log_names, record, stage_out, stage_der, final)
        module = compiled_cache.load(source)
        if notify is not None and not compiled_cache.compiled_before(module):
            notify("array code", len(ops), compile_estimate("array", len(ops)))
        args, call_logs = [v for _, v in gen.args], logs
    a = np.zeros((S, S))
    for s, (_, coeffs) in enumerate(stages, start=1):
        for j, val in coeffs:
            a[s, j] = val
    consts = {"h": cfg.step, "every": cfg.log_every, "bound": cfg.bound, "a": a,
              "c": np.array([0.0] + [ch for ch, _ in stages]),
              "b": np.array([b for _, b in final_coeffs]),
              # (the loop of a stage given to build_program reads I[0]: the entries of its
              # state checked against the bound, the diagram's x)
              "I": np.array(gen.ints + [d.n_states if stage is not None else 0],
                            dtype=np.int64),
              # the tableau itself, for (sub-)steps of another size (times hs in the loop)
              "A": np.array([list(row) + [0.0] * (S - len(row)) for row in tab.a]),
              "C": np.array(tab.c, dtype=float),
              "B": np.array([b for b in tab.b if b != 0.0])}
    xn, X = np.zeros((B, N)), np.zeros((B, N))
    K = np.zeros((B, S, N))
    prog = CompiledProgram(module, args, xn, X, K, logs, np.full(n_rows, np.nan), consts, B,
                           event_arrays(plan, cfg.n_steps, cfg.step, B), call_logs)
    # (GP, XS, GI) of _guard_check when the loop watches zero crossings, else None
    prog.guards = guard_arrays
    if gen.python:                  # blocks called in object mode: the program's handle
        from fwdstep.run import python_blocks
        handle, prog.python = python_blocks.register(prog, gen.python, B)
        args[[n for n, _ in gen.args].index(st.handle)][0] = handle
    return prog


def event_arrays(plan, n_steps: int, h: float, batch: int = 1) -> tuple:
    """``fwdstep.run.events.plan_events``'s plan as arrays the compiled loop reads, and the
    event of each sub-step: ``((ev_n, ev_off, ev_t, ev_r), events)``.  ``ev_n``: the grid
    steps it splits (ascending); ``ev_off`` (len(ev_n) + 1): step ``ev_n[p]`` is the
    sub-steps ``ev_t[ev_off[p]:ev_off[p + 1]]``, rows (a, b, lo, hi, update): update = 1
    when discrete blocks update at a, before the sub-step; the loop then returns status 3
    with ``ev_r[v]`` = the row, the caller applies ``events[row]``
    (``fwdstep.run.events.apply_updates``) and runs on from that step, and the loop resumes at
    that row.  An event at t_final adds step n_steps, one row (t_final, t_final, hi of the
    event, inf, 0): the final record's time is then max(t_final, hi), as on the NumPy path
    (its updates are the caller's, before the final record)."""
    ns, off, rows, events = [], [0], [], []
    if plan is not None:
        for n in sorted(plan.steps):
            ns.append(n)
            for sub in plan.steps[n]:
                rows.append((sub.a, sub.b, sub.lo, sub.hi, float(sub.event is not None)))
                events.append(sub.event)
            off.append(len(rows))
        if plan.final is not None:
            t = n_steps * h
            ns.append(n_steps)
            rows.append((t, t, plan.final.hi, math.inf, 0.0))
            events.append(None)
            off.append(len(rows))
    return ((np.array(ns, dtype=np.int64), np.array(off, dtype=np.int64),
             np.array(rows, dtype=np.float64).reshape(-1, 5),
             np.full(batch, -1, dtype=np.int64)), events)


_HELPERS = ("_pick", "_put0", "_put1", "_put2", "_putn", "_vecmat_into", "_view0", "_view1",
            "_view2", "_viewn", "_zeros", "_copy", "_store", "_rec", "_finite")


_PYTHON_HEADER = ("from numba import objmode as _objmode",
                  "from fwdstep.run.python_blocks import output as _pyout, derivative as _pyder")


def _module_source(gen, st, log_names, record, stage_out, stage_der, final,
                   bound_first: bool = False, guards: bool = False) -> str:
    """The text of the generated loop module; ``bound_first``: only the first I[0] entries
    of the state are checked against the bound (a stage given to ``build_program``);
    ``guards`` (scalar stages only): the loop of a diagram with zero crossings
    (``_guard_check``)."""
    arg_names = [n for n, _ in gen.args]
    a_list = "".join(", " + n for n in arg_names + log_names)
    fixed = "h, every, bound, a, c, b, xn, X, K, t_log, I, A, C, B, ev_n, ev_off, ev_t, ev_r"
    import numba
    fn_arg = ""
    if st is None:
        # the loop of scalar stages (_ScalarStage): the same text for every structure; the
        # stage comes in as a function pointer, its numbers in W (variant v's row), its
        # parameter-only nodes in Z, its records in LL
        fn_arg = "stage, "
        a_list = ", W, nZ, width, LL" + (", GP, XS, GI" if guards else "")
        prologue = ["S = a.shape[0]", "NW = W.shape[1]",
                    *(["og = N + S * N + NW + nZ", "nG = GP.shape[1]", "GPv = GP[v]",
                       "XSv = XS[v]", "gok = GI[v, 0]", "rsave = GI[v, 1]", "cs = 0",
                       "ws = np.empty(og + nG)"] if guards else
                      ["ws = np.empty(N + S * N + NW + nZ)"]),
                    # (not W[v if ... else 0]: prange's v is unsigned, and numba unifies
                    # uint64 with int64 to float64)
                    "Wv = W[0] if W.shape[0] == 1 else W[v]",
                    "for i in range(NW):", "    ws[N + S * N + i] = Wv[i]",
                    "vi = np.int64(v)", "B_ = np.int64(xn.shape[0])",
                    "wsp = ws.ctypes.data", "Lp = LL.ctypes.data",
                    "stage(3, 0.0, 0, 0, wsp, Lp)",
                    "Xv = ws[0:N]", "K2 = ws[N:N + S * N].reshape((S, N))",
                    *(["for j in range(nG):", "    ws[og + j] = GPv[j]"] if guards else [])]
        out = ["# fwdstep compiled loop of scalar stages (generated; see "
               "fwdstep/compiled/backend_numba.py)", f"# numba {numba.__version__}",
               "import math", "import numpy as np", "from numba import njit, prange",
               "CACHE = True", "", ""]
        one = "@njit(cache=CACHE)"
    else:
        picks = [f"{n} = _pick({n}, v)" for n in arg_names if n.startswith("P")]
        prologue = picks + [line for lines in st.prologue.values() for line in lines]
        helpers = set().union(*(jit_kernel(globals()[h])[1] for h in _HELPERS),
                              _ops_digests())
        digests = [f"# {part}" for part in sorted(gen.files | helpers)]
        out = ["# fwdstep compiled program (generated; see fwdstep/compiled/backend_numba.py)",
               f"# numba {numba.__version__}", *digests,
               "import math", "import numpy as np", "from numba import njit, prange",
               "from fwdstep.compiled.backend_numba import kernel as _kernel",
               *[f"{h} = _kernel('fwdstep.compiled.backend_numba', {h!r})" for h in _HELPERS],
               *gen.imports, *_PYTHON_HEADER * bool(gen.python), "CACHE = True", "", ""]
        one = "@njit(cache=CACHE)"

    def fn(header, body, decorator="@njit(cache=CACHE)"):
        out.append(decorator)
        out.append(header)
        out.extend("    " + line for line in body)
        out.extend(["", ""])

    views = [] if st is None else ["X2 = X[v:v + 1]", "Xv = X[v]", "K2 = K[v]"]
    # (a loop, not np.searchsorted, and np.empty, not np.empty_like: their implementations
    # cost numba ~1 s to compile, once per machine)
    run_body = ["N = xn.shape[1]", "xv = xn[v]"] + views + prologue + [
        "AW = np.empty((a.shape[0], a.shape[1]))", "BW = np.empty(b.shape[0])",
        "p = 0",
        "while p < ev_n.shape[0] and ev_n[p] < n0:",
        "    p += 1",
        "for n in range(n0, n1):",
        "    t = n * h",
        # a grid step split at declared discontinuity times (fwdstep.run.events): sub-steps
        # q0..q1-1 of ev_t; any other step is one sub-step with the precomputed a, c, b
        "    q0, q1, split = 0, 1, False",
        "    if p < ev_n.shape[0] and ev_n[p] == n:",
        "        q0, q1, split = ev_off[p], ev_off[p + 1], True",
        "        p += 1",
        "    ta, hs, lo, hi = t, h, -math.inf, math.inf",
        "    bad = False",
        *(["    r0 = row",
           # a step at a declared time: the Python driver's (fwdstep.run.crossings), after
           # it retook the step before (its end checks jumps there)
           "    if split and not final:",
           "        GI[v, 0] = 0",
           "        if gok == 1:",
           "            for i in range(N):", "                xv[i] = XSv[i]",
           "            return 4, n - 1, rsave",
           "        return 4, n, row"] if guards else []),
        "    qs = q0",                    # resuming at the row whose updates were applied
        "    if split and ev_r[v] >= q0 and ev_r[v] < q1:",
        "        qs = ev_r[v]",
    ]
    # a sub-step [ta, ta + hs] runs as fwdstep.run.program's rest_h: coefficients hs a_ij and
    # hs b_j, stage times clamped to [lo, hi], stage 1 at max(ta, lo)
    sub = ["if split and ev_t[q, 4] != 0.0:",      # discrete updates at ta: the caller's
           "    if ev_r[v] == q:", "        ev_r[v] = -1",
           "    else:", "        ev_r[v] = q", "        return 3, n, row",
           "aw, bw = a, b", "if split:",
           "    ta, hs, lo, hi = ev_t[q, 0], ev_t[q, 1] - ev_t[q, 0], ev_t[q, 2], ev_t[q, 3]",
           "    for i in range(A.shape[0]):", "        for j in range(A.shape[1]):",
           "            AW[i, j] = hs * A[i, j]",
           "    for m in range(B.shape[0]):", "        BW[m] = hs * B[m]",
           "    aw, bw = AW, BW"]
    # x_i = x_n + sum_j a_ij k_j over the nonzero a_ij, in the NumPy path's order
    stage = ["if not split:", "    ts = t + c[stg]",
             "elif stg == 0:", "    ts = max(ta, lo)",
             "else:", "    ts = min(max(ta + C[stg] * hs, lo), hi)",
             "for i in range(N):", "    Xv[i] = xv[i]",
             "for j in range(stg):", "    aij = aw[stg, j]",
             "    if aij != 0.0:", "        for i in range(N):",
             "            Xv[i] = Xv[i] + aij * K2[j, i]"] + stage_out
    stage += ["if stg == 0 and q == q0 and (n % every == 0 or final):", "    t_log[row] = t"]
    stage += ["    " + r for r in record] + ["    row += 1", "    if final:",
                                                "        return 0, n, row"] + stage_der
    if guards:                  # stage 1 compared the guards with the last step's start
        stage += ["if stg == 0:"] + ["    " + line for line in _guard_check("n", "r0")]
    inner = sub + ["for stg in range(a.shape[0]):"] + ["    " + line for line in stage]
    inner += ["bad = False", "for i in range(N):", f"    w = {final}", "    xv[i] = w",
              "    if " + ("i < I[0] and " if bound_first else "") + "not (abs(w) <= bound):",
              "        bad = True"]
    run_body += ["    for q in range(qs, q1):"] + ["        " + line for line in inner]
    run_body += ["    if bad:", "        return 1, n + 1, row"]
    if guards:                  # the last step's end: stage 1 at n1 (made again next call)
        run_body += ["if not final and n1 > n0 and gok == 1:",
                     "    for i in range(N):", "        Xv[i] = xv[i]",
                     "    cs = stage(0, n1 * h, 0, 0, wsp, Lp)"]
        run_body += ["    " + line for line in _guard_check("n1", None)]
        run_body += ["if not final:", "    GI[v, 0] = gok", "    GI[v, 1] = rsave",
                     "    for j in range(nG):", "        GPv[j] = ws[og + j]"]
    run_body.append("return 0, n1, row")
    fn(f"def run_one({fn_arg}v, n0, n1, row, final, {fixed}{a_list}):", run_body, one)
    # with object-mode blocks the variants run one after another: their calls hold the GIL,
    # and prange threads contending for it made 8 Panda variants 4.7x the NumPy batch's
    # time, against 2.0x in sequence (fwdstep/run/python_blocks.py)
    loop = "range" if gen.python else "prange"
    fn(f"def run_all({fn_arg}n0, n1, rows, status, n_next, alive, {fixed}{a_list}):",
       [f"for v in {loop}(rows.shape[0]):",
        "    if alive[v]:",
        f"        st, nn, r = run_one({fn_arg}v, n0, n1, rows[v], False, {fixed}{a_list})",
        "        status[v] = st", "        n_next[v] = nn", "        rows[v] = r",
        "        if st:", "            alive[v] = False"],
       "@njit(cache=CACHE)" if gen.python else "@njit(cache=CACHE, parallel=True)")
    return "\n".join(out) + "\n"


#: The zero-crossing part of the loop (``_module_source(guards=True)``).  Every stage 1
#: that makes derivatives compares the guards' signs with those it wrote at the previous
#: step's stage 1 (``ws[og:og + nG]``; ``GP`` keeps them between calls), writes the new
#: ones there and returns 4 when one changed sign and is finite (``fwdstep.run.crossings``'s
#: test; ``fwdstep.compiled.llvm_stage``).  The loop keeps the state ``XS`` and the row
#: count ``rsave`` at the start of the last step; ``gok``: they and the guards are valid
#: (``GI`` between calls; the driver sets 0 when it changed the state).  Status 4 from
#: stage 1 means the last step crossed: the state goes back to that step's start and the
#: loop returns status 4 with that step and row; ``fwdstep.compiled.driver`` takes it with
#: the NumPy path's crossing machinery and resumes the loop after it.
def _guard_check(n: str, row) -> list:
    """Lines acting on the status ``cs`` of stage 1 of step ``n`` (4: step n - 1 crossed);
    then, with ``row`` (this step's first row), this step's start kept."""
    lines = ["if cs == 4 and gok == 1:",
             "    for i in range(N):", "        xv[i] = XSv[i]",
             "    GI[v, 0] = 0",
             f"    return 4, {n} - 1, rsave"]
    if row is not None:
        lines += ["for i in range(N):", "    XSv[i] = xv[i]",
                  "gok = 1", f"rsave = {row}"]
    return lines


# ---------------------------------------------------------------------------- helpers
# Plain functions, jitted (and cached) like kernels by the generated module.
def _pick(P, v):
    """Variant v's slice of a parameter array (shared when its batch axis is 1)."""
    if P.shape[0] > 1:
        return P[v:v + 1]
    return P[0:1]


def _put0(V, c, s):
    """V[0, c] = the scalar signal s (1,)."""
    V[0, c] = s[0]


def _put1(V, c, s):
    """V[0, c:c + n] = the vector signal s (1, n), of any layout, without a copy."""
    for i in range(s.shape[1]):
        V[0, c + i] = s[0, i]


def _put2(V, c, s):
    """V[0, c:c + n p] = the matrix signal s (1, n, p) in row-major order."""
    n, p = s.shape[1], s.shape[2]
    for i in range(n):
        for j in range(p):
            V[0, c + i * p + j] = s[0, i, j]


def _putn(V, c, s):
    """The same for a signal of any rank (one copy)."""
    flat = np.ascontiguousarray(s).ravel()
    for i in range(flat.size):
        V[0, c + i] = flat[i]


def _finite(a):
    """Whether every element of a signal is finite (run_one returns status 2 otherwise)."""
    for w in a.flat:
        if not math.isfinite(w):
            return False
    return True


def _view0(Y, a):
    """Element a of row 0 of Y as a scalar signal (1,) (a view when Y is C-contiguous).
    These helpers keep reshapes and slice assignments (whose error paths cost numba
    seconds to compile) out of the generated loop: they are compiled once, then cached."""
    return np.ascontiguousarray(Y[0, a:a + 1])


def _view1(Y, a, n):
    """Y[0, a:a + n] as a vector signal (1, n)."""
    return np.ascontiguousarray(Y[0, a:a + n]).reshape((1, n))


def _view2(Y, a, n, p):
    """Y[0, a:a + n p] as a matrix signal (1, n, p)."""
    return np.ascontiguousarray(Y[0, a:a + n * p]).reshape((1, n, p))


def _viewn(Y, a, size, shape):
    """Y[0, a:a + size] as a signal (1, *shape)."""
    return np.ascontiguousarray(Y[0, a:a + size]).reshape((1,) + shape)


def _zeros(n):
    """A (1, n) buffer."""
    return np.zeros((1, n))


def _copy(V, c, X, a, n):
    """V[0, c:c + n] = X[0, a:a + n]."""
    for i in range(n):
        V[0, c + i] = X[0, a + i]


def _store(K, s, a, n, y, c):
    """K[s, a:a + n] = y[0, c:c + n] (a stage derivative)."""
    for i in range(n):
        K[s, a + i] = y[0, c + i]


def _rec(L, row, v, s):
    """L[row, v] = s[0] (a record of a logged signal)."""
    L[row, v] = s[0]


def _vecmat_into(V, M, Y):
    """Y (1, m) = V (1, n) @ M (1, n, m), in place."""
    n, m = M.shape[1], M.shape[2]
    for j in range(m):
        Y[0, j] = 0.0
    for i in range(n):
        vi = V[0, i]
        for j in range(m):
            Y[0, j] += vi * M[0, i, j]
