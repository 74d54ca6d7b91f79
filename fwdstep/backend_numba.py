"""Optional compiled backend: the whole fixed-step run as numba-compiled code.

Chosen with ``simulation: {backend: compiled}`` (or ``simulate(d, backend="compiled")``);
needs ``pip install fwdstep[fast]`` (numba).  Only this module imports numba, and only the
compiled backend imports this module.

From the compiled schedule (with linear blocks fused, ``fwdstep.linear.plan_fusion``) it
generates one Python module: ``outputs(t, x, ...)`` and ``derivatives(t, x, k, ...)`` are
straight-line calls into the numba kernels below (one per block type) over preallocated
flat float64 buffers, one per signal; ``run(n0, n1, ...)`` is the jitted fixed-step loop
(procedure Step of ``fwdstep.simulate``, the same operations in the same order, logging at
stage 1 and the divergence test after each step).  No parameter value is written into the
source (they are arguments), so the generated module depends on the diagram's structure
only: it is written to a cache directory (``$FWDSTEP_CACHE_DIR``, default
``~/.cache/fwdstep``) under a hash of its text and compiled with numba's on-disk cache, so
only the first process that runs a structure pays the compile.

Each block type needs a kernel here; a diagram with a block this backend does not know is
refused with the list of supported types (run it with ``backend: numpy``).  Single runs only
(batch 1); ``fwdstep sweep`` batches with the NumPy path.  Ctrl-C is honoured between chunks
of steps; a block cannot raise inside compiled code, so a failure shows as a divergence.
"""
from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import sys
import tempfile

import numpy as np
from numba import njit

from .errors import ConfigError
from .linear import plan_fusion
from .solvers import TABLEAUX, step_plan

#: Steps per call of the compiled loop (Ctrl-C and progress are handled between calls).
CHUNK = 2000


# ---------------------------------------------------------------------------- kernels
@njit(cache=True)
def k_copy(src, dst):
    for i in range(dst.shape[0]):
        dst[i] = src[i]


@njit(cache=True)
def k_sinusoids(t, w, phi, offset, has_offset, coef, Y):
    """Y[j, i] = sum_k coef[j, i, k] * (sin if j even else cos)(w[i, k] t + phi[i, k])."""
    m1, n, terms = coef.shape
    for i in range(n):
        for k in range(terms):
            a = w[i, k] * t + phi[i, k]
            s = math.sin(a)
            c = math.cos(a)
            for j in range(m1):
                v = coef[j, i, k] * (c if j % 2 else s)
                Y[j, i] = v if k == 0 else Y[j, i] + v
        if has_offset:
            Y[0, i] = Y[0, i] + offset[i]


@njit(cache=True)
def k_polynomial(t, coef, Y):
    """Y[j, i] = sum_k coef[j, i, k] t^k."""
    m1, n, d1 = coef.shape
    for j in range(m1):
        for i in range(n):
            v = 0.0
            for k in range(d1):
                v += coef[j, i, k] * t ** k
            Y[j, i] = v


@njit(cache=True)
def k_two_link(x, tau, tau_star, a, gravity, dx):
    """The two-link arm's derivative, as TwoLinkArm._derivative_single."""
    q1, q2, qd1, qd2 = x[0], x[1], x[2], x[3]
    c2 = math.cos(q2)
    s2 = math.sin(q2)
    h12 = a[1] + a[2] * c2 + a[3] * s2
    h11 = a[0] + 2.0 * a[2] * c2 + 2.0 * a[3] * s2
    hh = a[2] * s2 - a[3] * c2
    r1 = (tau[0] + tau_star[0]) + hh * (2.0 * qd1 + qd2) * qd2
    r2 = (tau[1] + tau_star[1]) - hh * qd1 * qd1
    if gravity:
        q12 = q1 + q2
        g2 = a[5] * math.cos(q12) + a[6] * math.sin(q12)
        r1 = r1 - a[4] * math.cos(q1) - g2
        r2 = r2 - g2
    inv_det = 1.0 / (h11 * a[1] - h12 * h12)
    dx[0] = qd1
    dx[1] = qd2
    dx[2] = (a[1] * r1 - h12 * r2) * inv_det
    dx[3] = (h11 * r2 - h12 * r1) * inv_det


@njit(cache=True)
def k_regressor(q, qdot, z, zd, gravity, Y):
    """Y (flat, 2 x p) of the two-link arm, as Regressor._output_single."""
    p = 7 if gravity else 4
    c2 = math.cos(q[1])
    s2 = math.sin(q[1])
    v1 = qdot[1] * z[0] + (qdot[0] + qdot[1]) * z[1]
    v2 = qdot[0] * z[0]
    w1 = 2.0 * zd[0] + zd[1]
    Y[0] = zd[0]
    Y[1] = zd[1]
    Y[2] = c2 * w1 - s2 * v1
    Y[3] = s2 * w1 + c2 * v1
    Y[p + 0] = 0.0
    Y[p + 1] = zd[0] + zd[1]
    Y[p + 2] = c2 * zd[0] + s2 * v2
    Y[p + 3] = s2 * zd[0] - c2 * v2
    if gravity:
        c12 = math.cos(q[0] + q[1])
        s12 = math.sin(q[0] + q[1])
        Y[4] = math.cos(q[0])
        Y[5] = c12
        Y[6] = s12
        Y[p + 4] = 0.0
        Y[p + 5] = c12
        Y[p + 6] = s12


@njit(cache=True)
def k_vecmat(v, M, y):
    """y = v @ M (v (n,), M (n, m))."""
    n, m = M.shape
    for j in range(m):
        y[j] = 0.0
    for i in range(n):
        vi = v[i]
        for j in range(m):
            y[j] += vi * M[i, j]


@njit(cache=True)
def k_matvec(M, v, y, transpose):
    """y = op(M) @ v with M (r, c) flat-indexed as given, op = transpose or not."""
    r, c = M.shape
    if transpose:
        for j in range(c):
            acc = 0.0
            for i in range(r):
                acc += M[i, j] * v[i]
            y[j] = acc
    else:
        for i in range(r):
            acc = 0.0
            for j in range(c):
                acc += M[i, j] * v[j]
            y[i] = acc


@njit(cache=True)
def k_matmat(A, B, C, ta, tb):
    """C = op(A) op(B)."""
    n = A.shape[1] if ta else A.shape[0]
    inner = A.shape[0] if ta else A.shape[1]
    m = B.shape[0] if tb else B.shape[1]
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for k in range(inner):
                a = A[k, i] if ta else A[i, k]
                b = B[j, k] if tb else B[k, j]
                acc += a * b
            C[i, j] = acc


# ---------------------------------------------------------------------------- emitters
class _Context:
    """Names of buffers and parameter arrays for the generated source."""

    def __init__(self):
        self.arrays: dict = {}          # argument name -> array

    def arr(self, prefix: str, value) -> str:
        name = f"{prefix}{len(self.arrays)}"
        self.arrays[name] = np.ascontiguousarray(value, dtype=np.float64)
        return name

    def keep(self, prefix: str, value: np.ndarray) -> str:
        """An existing buffer, passed as it is (views of it stay live)."""
        name = f"{prefix}{len(self.arrays)}"
        self.arrays[name] = value
        return name


def _mro_names(block) -> set:
    return {c.__name__ for c in type(block).__mro__}


def _emit(ctx, step, sig, xs):
    """(output lines, derivative lines) of one called block.  ``sig[idx]`` is the flat
    buffer name of a signal; ``xs`` the state slice expression; derivative lines write
    ``dk`` (the block's slice of k)."""
    blk, p = step.block, step.block.p
    ins = [sig[u] for u in step.inputs]
    outs = [sig[o] for o in step.outputs]
    kind = type(blk).__name__
    names = _mro_names(blk)
    if "_SinusoidSum" in names:
        coef = np.empty((blk._m + 1,) + p.frequency.shape[1:])
        for j in range(blk._m + 1):
            coef[j] = (p.even_coef if j % 2 == 0 else p.odd_coef)[0, j // 2]
        Y = ctx.arr("Ys", np.zeros((blk._m + 1, coef.shape[1])))
        has = bool(np.any(p.offset))
        lines = [f"k_sinusoids(ts, {ctx.arr('w', p.frequency[0])}, "
                 f"{ctx.arr('phi', p.phase[0])}, {ctx.arr('off', p.offset[0])}, {has}, "
                 f"{ctx.arr('coef', coef)}, {Y})"]
        lines += [f"k_copy({Y}[{j}], {o})" for j, o in enumerate(outs)]
        return lines, []
    if kind == "Polynomial":
        coef = p.coef[0]
        Y = ctx.arr("Yp", np.zeros(coef.shape[:2]))
        lines = [f"k_polynomial(ts, {ctx.arr('pc', coef)}, {Y})"]
        return lines + [f"k_copy({Y}[{j}], {o})" for j, o in enumerate(outs)], []
    if kind == "Constant":
        return [f"k_copy({ctx.arr('cv', np.ravel(p.value[0]))}, {outs[0]})"], []
    if kind == "Step":
        tm, af, bf = (ctx.arr(k, np.ravel(getattr(p, k)[0])) for k in ("time", "after",
                                                                      "before"))
        return [f"for i in range({outs[0]}.shape[0]):",
                f"    {outs[0]}[i] = {af}[i] if ts >= {tm}[i] else {bf}[i]"], []
    if kind == "TwoLinkArm":
        theta = p.theta[0]
        gravity = bool(np.any(theta[4:] != 0.0))
        return ([f"k_copy({xs}[0:2], {outs[0]})", f"k_copy({xs}[2:4], {outs[1]})"],
                [f"k_two_link({xs}, {ins[0]}, {ins[1]}, {ctx.arr('th', theta)}, {gravity}, dk)"])
    if kind == "Regressor":
        return [f"k_regressor({ins[0]}, {ins[1]}, {ins[2]}, {ins[3]}, {blk._gravity}, "
                f"{outs[0]})"], []
    if kind == "PointMass":
        n = blk._n
        im = ctx.arr("im", np.broadcast_to(p.inv_mass[0], (n,)))
        return ([f"k_copy({xs}[0:{n}], {outs[0]})", f"k_copy({xs}[{n}:{2 * n}], {outs[1]})"],
                [f"for i in range({n}):",
                 f"    dk[i] = {xs}[{n} + i]",
                 f"    dk[{n} + i] = ({ins[0]}[i] + {ins[1]}[i]) * {im}[i]"])
    if kind == "Sum":
        row = p.signs[0]
        plus = [j for j in range(1, row.size) if row[j] > 0]
        minus = [j for j in range(1, row.size) if row[j] < 0]
        expr = f"-{ins[0]}[i]" if row[0] < 0 else f"{ins[0]}[i]"
        for j in plus:
            expr = f"({expr} + {ins[j]}[i])"
        for j in minus:
            expr = f"({expr} - {ins[j]}[i])"
        return [f"for i in range({outs[0]}.shape[0]):", f"    {outs[0]}[i] = {expr}"], []
    if kind == "Gain":
        if blk._matrix:
            return [f"k_vecmat({ins[0]}, {ctx.arr('KT', p.K_T[0])}, {outs[0]})"], []
        K = ctx.arr("K", np.reshape(p.K_T[0], (1,)))
        return [f"for i in range({outs[0]}.shape[0]):",
                f"    {outs[0]}[i] = {K}[0] * {ins[0]}[i]"], []
    if kind == "ScalarProduct":
        return [f"for i in range({outs[0]}.shape[0]):",
                f"    {outs[0]}[i] = {ins[0]}[0] * {ins[1]}[i]"], []
    if kind == "Product":
        a_shape, b_shape = blk.inputs["a"].shape, blk.inputs["b"].shape
        ta, tb = (bool(f) for f in blk._flags)
        A = f"{ins[0]}.reshape({a_shape})" if len(a_shape) == 2 else ins[0]
        Bm = f"{ins[1]}.reshape({b_shape})" if len(b_shape) == 2 else ins[1]
        kindab = (len(a_shape), len(b_shape))
        if kindab == (2, 2):
            shape = blk.outputs["y"].shape
            return [f"k_matmat({A}, {Bm}, {outs[0]}.reshape({shape}), {ta}, {tb})"], []
        if kindab == (2, 1):
            return [f"k_matvec({A}, {Bm}, {outs[0]}, {ta})"], []
        if kindab == (1, 2):
            return [f"k_matvec({Bm}, {A}, {outs[0]}, {not tb})"], []
        return [f"{outs[0]}[0] = np.dot({A}, {Bm})"], []
    if kind == "Selector" and blk._per_variant is None:
        idx = np.arange(blk.inputs["u"].shape[0])[blk._pick]
        return [f"{outs[0]}[{k}] = {ins[0]}[{int(i)}]" for k, i in enumerate(idx)], []
    if kind == "Mux":
        lines, c = [], 0
        for name, j in zip(ins, range(len(ins))):
            size = blk.inputs[f"u{j + 1}"].size
            lines.append(f"{outs[0]}[{c}:{c + size}] = {name}")
            c += size
        return lines, []
    if kind == "Demux":
        return [f"{o}[:] = {ins[0]}[{s.start}:{s.stop}]" for o, s in zip(outs, blk._slices)], []
    if kind == "PointMassRegressor":
        n = blk._n
        return [f"for i in range({n * n}):", f"    {outs[0]}[i] = 0.0",
                f"for i in range({n}):", f"    {outs[0]}[i * {n} + i] = {ins[3]}[i]"], []
    if kind == "AdaptationLaw":
        out = [f"k_copy({xs}, {outs[0]})"]
        if blk._vector:
            g = ctx.arr("g", np.reshape(p.gamma[0], (1,)))
            return out, ["acc = 0.0", f"for i in range({ins[1]}.shape[0]):",
                         f"    acc += {ins[0]}[i] * {ins[1]}[i]", f"dk[0] = -{g}[0] * acc"]
        n, q = blk.inputs["W"].shape
        v = ctx.arr("v", np.zeros(q))
        lines = [f"k_vecmat({ins[1]}, {ins[0]}.reshape(({n}, {q})), {v})"]
        if blk._matrix_gain:
            lines += [f"k_vecmat({v}, {ctx.arr('gT', p.gamma_T[0])}, dk)",
                      f"for i in range({q}):", "    dk[i] = -dk[i]"]
        else:
            g = ctx.arr("g", np.broadcast_to(np.ravel(p.gamma[0]), (q,)))
            lines += [f"for i in range({q}):", f"    dk[i] = -{g}[i] * {v}[i]"]
        return out, lines
    return None


SUPPORTED = ("Sine", "MultiSine", "RandomDisturbance", "Polynomial", "Constant", "Step",
             "TwoLinkArm", "Regressor", "PointMass", "PointMassRegressor", "Sum", "Gain",
             "ScalarProduct", "Product", "Selector", "Mux", "Demux", "AdaptationLaw",
             "and every LinearBlock (Integrator, TransferFunction, StateSpace, "
             "ReferenceDynamics, ...)")


# ---------------------------------------------------------------------------- program
class CompiledProgram:
    """The run functions of one diagram, with their buffers (see ``build_program``)."""

    def __init__(self, module, args, xn, K, X, logs, log_views, t_log, consts):
        self.module, self.args, self.xn, self.K, self.X = module, args, xn, K, X
        self.logs, self.log_views, self.t_log, self.consts = logs, log_views, t_log, consts

    def run(self, n0: int, n1: int, row: int) -> tuple:
        """Steps n0..n1-1; returns (status 0 ok / 1 diverged, next step, next row)."""
        c = self.consts
        return self.module.run(n0, n1, row, c["h"], c["every"], c["bound"], c["a"], c["c"],
                               c["b"], self.xn, self.X, self.K, self.t_log, *self.args,
                               *self.log_views)

    def final(self, t: float, row: int) -> None:
        self.module.final(t, row, self.xn, self.t_log, *self.args, *self.log_views)


def build_program(d, n_rows: int) -> CompiledProgram:
    if d.batch != 1:
        raise ConfigError("backend 'compiled' runs single diagrams; batches and sweeps use "
                          "backend 'numpy'", file=d.file)
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    stages, final_coeffs = step_plan(tab, cfg.step)
    N, S = d.n_states, tab.stages
    ctx = _Context()
    plan = plan_fusion(d.schedule, d.signal_shapes, d.constant_signals)
    fused = plan.fused if plan is not None else set()
    ops = plan.ops if plan is not None else [("call", s) for s in d.schedule]
    sizes = [int(np.prod(s, dtype=np.int64)) for s in d.signal_shapes]
    sig = {idx: ctx.arr("g", np.zeros(sizes[idx])) for idx in range(len(sizes))}
    for idx, arr in d.constant_signals.items():
        ctx.arrays[sig[idx]][:] = np.ravel(arr)
    out_lines: list = []
    der_lines: list = []
    unsupported = []
    for kind, op in ops:
        if kind == "group":
            out_lines += _group_lines(ctx, op, plan, sig, sizes, der_lines)
            continue
        xs = f"x[{op.state.start}:{op.state.stop}]" if op.state is not None else "x[0:0]"
        emitted = _emit(ctx, op, sig, xs)
        if emitted is None:
            unsupported.append(f"{op.block.name} ({op.block.type_name})")
            continue
        out_lines += emitted[0]
        if op.state is not None and op.block.name not in fused:
            der_lines += [f"dk = k[{op.state.start}:{op.state.stop}]"] + emitted[1]
    if unsupported:
        plural = "s" if len(unsupported) > 1 else ""
        raise ConfigError(f"backend 'compiled' has no kernel for block{plural} "
                          f"{', '.join(unsupported)}; it supports {', '.join(SUPPORTED)}; use "
                          "'backend: numpy'", file=d.file)
    args = list(ctx.arrays)
    xn, X = np.zeros(N), np.zeros(N)
    K = np.zeros((S, N))
    t_log = np.empty(n_rows)
    logs, log_views, log_names, record = [], [], [], []
    for k, name in enumerate(d.logged):
        idx = d.signal_index[name]
        arr = np.full((n_rows, 1) + tuple(d.signal_shapes[idx]), np.nan)
        logs.append(arr)
        log_views.append(arr.reshape(n_rows, sizes[idx]))
        log_names.append(f"L{k}")
        record.append(f"L{k}[row, :] = {sig[idx]}")
    a = np.zeros((S, S))
    for s, (_, coeffs) in enumerate(stages, start=1):
        for j, val in coeffs:
            a[s, j] = val
    consts = {"h": cfg.step, "every": cfg.log_every, "bound": cfg.bound, "a": a,
              "c": np.array([0.0] + [ch for ch, _ in stages]),
              "b": np.array([b for _, b in final_coeffs])}
    source = _module_source(args, log_names, out_lines, der_lines, record, stages,
                            final_coeffs, N)
    module = _load(source)
    return CompiledProgram(module, [ctx.arrays[n] for n in args], xn, K, X, logs, log_views,
                           t_log, consts)


def _group_lines(ctx, group, plan, sig, sizes, der_lines) -> list:
    """A fused linear product: fill V, y = V @ M, copy the outputs (and dx)."""
    n_in = sum(n for _, n in group.inputs)
    V = ctx.arr("V", np.zeros(n_in))
    M = ctx.arr("M", group.M[0])
    Y = ctx.arr("Y", np.zeros(group.M.shape[2]))
    lines, c = [], 0
    for term, n in group.inputs:
        src = f"x[{plan.state.start}:{plan.state.stop}]" if term == "x" else sig[term]
        lines.append(f"{V}[{c}:{c + n}] = {src}")
        c += n
    lines.append(f"k_vecmat({V}, {M}, {Y})")
    c = 0
    for idx, n in group.outputs:
        lines.append(f"{sig[idx]}[:] = {Y}[{c}:{c + n}]")
        c += n
    if group.derivative:
        der_lines.append(f"k[{plan.state.start}:{plan.state.stop}] = {Y}[{c}:]")
    return lines


def _module_source(args, log_names, out_lines, der_lines, record, stages, final_coeffs,
                   N) -> str:
    a_list = ", ".join(args)
    logs = ", ".join(log_names)
    ind = "\n    "
    lines = [f"# fwdstep compiled program; kernels {_kernel_version()}",
             "import math", "import numpy as np", "from numba import njit",
             "from fwdstep.backend_numba import (k_copy, k_sinusoids, k_polynomial, "
             "k_two_link, k_regressor, k_vecmat, k_matvec, k_matmat)", "", "",
             "@njit(cache=True)", f"def outputs(ts, x, {a_list}):",
             "    " + ind.join(out_lines or ["pass"]), "", "",
             "@njit(cache=True)", f"def derivatives(ts, x, k, {a_list}):",
             "    " + ind.join(der_lines or ["pass"]), "", "",
             "@njit(cache=True)",
             f"def run(n0, n1, row, h, every, bound, a, c, b, xn, X, K, t_log, {a_list}"
             f"{', ' + logs if logs else ''}):",
             f"    N = {N}",
             "    for n in range(n0, n1):",
             "        t = n * h",
             f"        outputs(t, xn, {a_list})",
             "        if n % every == 0:",
             "            t_log[row] = t"]
    lines += [f"            {r}" for r in record]
    lines += ["            row += 1",
              f"        derivatives(t, xn, K[0], {a_list})"]
    for s, (_, coeffs) in enumerate(stages, start=1):
        lines.append("        for i in range(N):")
        if coeffs:
            j0 = coeffs[0][0]
            expr = f"a[{s}, {j0}] * K[{j0}, i] + xn[i]"
            for j, _ in coeffs[1:]:
                expr = f"({expr}) + a[{s}, {j}] * K[{j}, i]"
        else:
            expr = "xn[i]"
        lines.append(f"            X[i] = {expr}")
        lines.append(f"        outputs(t + c[{s}], X, {a_list})")
        lines.append(f"        derivatives(t + c[{s}], X, K[{s}], {a_list})")
    lines.append("        bad = False")
    lines.append("        for i in range(N):")
    expr = "xn[i]"
    for m, (j, _) in enumerate(final_coeffs):
        expr = f"({expr} + b[{m}] * K[{j}, i])"
    lines.append(f"            v = {expr}")
    lines.append("            xn[i] = v")
    lines.append("            if not (abs(v) <= bound):")
    lines.append("                bad = True")
    lines.append("        if bad:")
    lines.append("            return 1, n + 1, row")
    lines.append("    return 0, n1, row")
    lines += ["", "", "@njit(cache=True)",
              f"def final(t, row, xn, t_log, {a_list}{', ' + logs if logs else ''}):",
              f"    outputs(t, xn, {a_list})", "    t_log[row] = t"]
    lines += [f"    {r}" for r in record]
    return "\n".join(lines) + "\n"


def _kernel_version() -> str:
    """Hash of this file and the numba version: numba's disk cache of the generated module
    does not notice changes of the kernels it calls, so they are part of its text."""
    import numba
    with open(__file__, "rb") as fh:
        return f"{hashlib.sha256(fh.read()).hexdigest()[:16]}, numba {numba.__version__}"


def cache_dir() -> str:
    return os.environ.get("FWDSTEP_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "fwdstep")


def _load(source: str):
    """Write ``source`` under its hash in the cache directory (once) and import it."""
    digest = hashlib.sha256(source.encode()).hexdigest()[:20]
    name = f"fwdstep_compiled_{digest}"
    if name in sys.modules:
        return sys.modules[name]
    folder = cache_dir()
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, f"{name}.py")
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".py", dir=folder)
        with os.fdopen(fd, "w") as fh:
            fh.write(source)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules[name] = module
    return module
