"""fwdstep.compiled.scalarize: kernels traced into scalar expressions (the compiled backend's scalar
stages).  The traced graph is checked against the kernel itself run by NumPy, for every
registered block whose kernels trace; the folds against IEEE arithmetic."""
import math
import os

import numpy as np
import pytest

pytest.importorskip("numba")             # the tracer runs fwdstep.compiled.compiled_ops' loops

import fwdstep  # noqa: E402
from fwdstep.compiled import scalarize as sz  # noqa: E402
from fwdstep.core.registry import REGISTRY
from fwdstep.structure.library import load_library  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _leaves(tr, name, values, invariant=False):
    """An object array of leaves carrying ``values`` (one variant); ``invariant``: a
    parameter (branches on it take its value)."""
    values = np.asarray(values, dtype=float)
    out = np.empty(values.shape, dtype=object)
    for idx in np.ndindex(*values.shape):
        out[idx] = tr.leaf(f"{name}{'_'.join(map(str, idx))}", invariant, [values[idx]])
    return out


def _value(tr, node):
    return float(np.asarray(tr.evaluate(tr.lift(node))).reshape(-1)[0])


# ------------------------------------------------------------------------------- folds
@pytest.mark.parametrize("a", [2.5, -0.0, 0.0, math.inf, -3e300])
def test_folds_are_exact_where_the_docstring_says(a):
    tr = sz.Trace()
    x = tr.leaf("x", False, [a])
    y = tr.leaf("y", False, [7.25])
    for expr, want in ((x + 0.0, a + 0.0), (x - 0.0, a - 0.0), (x * 1.0, a * 1.0),
                       (1.0 * x, 1.0 * a), (x / 1.0, a / 1.0), (x * -1.0, a * -1.0),
                       (y + (-x), 7.25 + (-a)), (y - (-x), 7.25 - (-a))):
        got = _value(tr, expr)
        assert got == want or (math.isnan(got) and math.isnan(want))
    assert (x * 0.0).op == "const"          # the one inexact fold: 0 * a = 0 (a finite)
    assert (x * 1.0) is x and (x + 0.0) is x


def test_common_subexpressions_are_one_node():
    tr = sz.Trace()
    x, y = tr.leaf("x", False), tr.leaf("y", False)
    a = (x * y).sin()
    b = (x * y).sin()
    assert a is b and len(tr.nodes) == 4


def test_a_branch_on_a_parameter_takes_its_value_and_a_branch_on_a_signal_is_refused():
    tr = sz.Trace()
    flag = tr.leaf("p0", True, [1.0, 1.0])
    assert bool(flag != 0.0) is True
    mixed = tr.leaf("p1", True, [0.0, 1.0])
    with pytest.raises(sz.Untraceable, match="a branch depends on a parameter that differs "
                                             "between variants"):
        bool(mixed != 0.0)
    x = tr.leaf("x", False)
    with pytest.raises(sz.Untraceable, match="a branch depends on a signal or the state"):
        bool(x > 0.0)


def test_where_is_a_selection_and_writes_as_one():
    tr = sz.Trace()
    rb = sz.Rebinder(tr)

    def kernel(t, u):
        return np.where(u > 1.0, 2.0 * u, -u)

    u = _leaves(tr, "u", [[0.5, 3.0]])
    y = sz.run_traced(rb, kernel, 0.0, u)
    assert [_value(tr, v) for v in y.reshape(-1)] == [-0.5, 6.0]
    assert tr.expr(y[0, 0]).startswith("(") and " if " in tr.expr(y[0, 0])


# ---------------------------------------------------------------- every block, traced
load_library()
from tests.blocks.test_contract import _compiled_kernel_names, _inputs, _make, _state  # noqa


def _trace_block(blk, t, x, u):
    """(outputs, derivative) of blk's kernels traced on leaves holding these values, each
    evaluated from the graph; Untraceable when a kernel does not trace."""
    tr = sz.Trace()
    rb = sz.Rebinder(tr)
    k = blk.kernels
    xs = _leaves(tr, "x", x)
    us = [_leaves(tr, f"u{j}_", a) for j, a in enumerate(u)]
    args = []
    for n in k.params:
        args.append(_leaves(tr, f"p{n}_", np.asarray(getattr(blk.p, n), dtype=float)[:1],
                            invariant=True))
    args += list(k.static)
    ins = (tuple(us),) if k.tuple_inputs else tuple(us)
    ts = tr.leaf("ts", False, [t])
    outs = der = None
    if k.output is not None:
        r = sz.run_traced(rb, k.output, ts, xs, *ins, *args)
        if k.packed:
            flat = sz.as_nodes(tr, r, (1, sum(p.size for p in blk.outputs.values())))
            r = [flat[:, a:b].reshape((1,) + (p.shape if shape is not None else (b - a,)))
                 for (a, b, shape), p in zip(blk._unpack, blk.outputs.values())]
        outs = [np.vectorize(lambda s: _value(tr, s), otypes=[float])(
            sz.as_nodes(tr, y, (1,) + port.shape)) for y, port in zip(r, blk.outputs.values())]
    if blk.n_states and k.derivative is not None:
        r = sz.run_traced(rb, k.derivative, ts, xs, *ins, *args)
        der = np.vectorize(lambda s: _value(tr, s), otypes=[float])(
            sz.as_nodes(tr, r, (1, blk.n_states)))
    return outs, der


TRACED: list = []


@pytest.mark.parametrize("name", _compiled_kernel_names())
def test_traced_kernels_equal_the_numpy_kernels(name):
    """One definition, derived: the scalar code's graph, evaluated, gives the block's NumPy
    outputs and derivative at random points (1e-12), or the kernel says it cannot be traced
    (the compiled backend then runs its array code)."""
    rng = np.random.default_rng(5)
    blk = _make(name)
    blk.finalize(1)
    u = tuple(np.ascontiguousarray(a) for a in _inputs(blk, 1, rng))
    x = _state(blk, 1, rng)
    t = float(rng.uniform(0.0, 2.0))
    try:
        outs, der = _trace_block(blk, t, x, u)
    except sz.Untraceable:
        return
    TRACED.append(name)
    if outs is not None:
        for got, ref in zip(outs, blk.output(t, x, u)):
            ref = np.broadcast_to(ref, got.shape)
            scale = max(1.0, float(np.max(np.abs(ref)))) if ref.size else 1.0
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * scale, err_msg=name)
    if der is not None:
        ref = blk.derivative(t, x, u)
        scale = max(1.0, float(np.max(np.abs(ref))))
        np.testing.assert_allclose(der, ref, rtol=0, atol=1e-12 * scale, err_msg=name)


SPEED_CRITICAL = ["slotine_li", "theorem1", "theorem2", "theorem3", "theorem4", "theorem5",
                  "theorem6", "theorem7", "theorem8", "theorem9", "pid_reformulated",
                  "computed_torque"]


@pytest.mark.parametrize("name", SPEED_CRITICAL)
def test_the_theorem_diagrams_trace_to_scalar_stages(name):
    """A change that made one of these untraceable would silently run it with the array
    code (10x slower compiled): they must trace."""
    from fwdstep.compiled import backend_numba as bn
    from fwdstep.run.finite import unlogged_signals
    d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", f"{name}.yaml"))
    shapes = [tuple(s) for s in d.signal_shapes]
    ops, fused = bn._ops_for(d.schedule, shapes, d.constant_signals)
    st = bn._ScalarStage(d, shapes, ops, fused, d.constant_signals,
                         [d.signal_index[n] for n in d.logged], unlogged_signals(d), 4)
    assert st.n_nodes > 20
    import llvmlite.binding as llvm
    from fwdstep.compiled.llvm_stage import stage_ir
    llvm.parse_assembly(stage_ir(st)).verify()   # valid LLVM IR


# ------------------------------------------------------------------ LLVM machine code
def _stage(exprs, checked=(), records=()):
    """A stage object with ``exprs`` as the derivative of len(exprs) states (x0 = 0.3,
    x1 = 0.9 the first two), compiled by fwdstep.compiled.llvm_stage, and a ctypes caller."""
    import ctypes
    import types
    from fwdstep.compiled import llvm_stage
    tr = exprs[0].trace
    n = len(exprs)
    st = types.SimpleNamespace(
        tr=tr, n_columns=1, ow=n + 4 * n, oz=n + 4 * n + 1, inv=[],
        need_d=sorted(tr.needed(exprs)),
        need_r=sorted(tr.needed([e for e in checked] + [e for _, e in records])
                      - tr.needed(exprs)),
        records=list(records), checked=list(checked), der=list(enumerate(exprs)), n_states=n)
    fn = llvm_stage.compile_stage(st)
    f = ctypes.CFUNCTYPE(ctypes.c_int64, ctypes.c_int64, ctypes.c_double, ctypes.c_int64,
                         ctypes.c_int64, ctypes.c_uint64, ctypes.c_uint64)(fn.address)
    return st, f


def test_the_llvm_stage_computes_every_operation_as_python_does():
    """Each node kind, compiled to machine code, against Python's math on the same numbers
    (bit for bit: the same IEEE operations and libm functions)."""
    tr = sz.Trace()
    x0, x1 = tr.leaf("x0", False), tr.leaf("x1", False)
    p0 = tr.leaf("p0", True, [0.7])
    exprs = [x0.tan(), x0.tanh(), tr.binary("atan2", x0, x1), x0.sinh(), x0.cosh(),
             x0.arctan(), (x0 * 0.5).arcsin(), (x0 * 0.5).arccos(), x0 ** p0,
             tr.select(x0 > x1, x0, x1), abs(-x1), x0.exp(), x0.log(), x0.sqrt(),
             x0.sin() + x1.cos(), x0 / x1 - x1 * p0, (x0 < x1) * p0, -x0,
             (x1 * 7.0).floor(), (-x1).sign(), tr.select((x0 < x1) & (x1 < p0), 1.0, 2.0),
             tr.select((x0 > x1) | (x1 > p0), 1.0, 2.0), tr.select(~(x0 < x1), 1.0, 2.0)]
    st, f = _stage(exprs)
    a, b, p = 0.3, 0.9, 0.7
    want = [math.tan(a), math.tanh(a), math.atan2(a, b), math.sinh(a), math.cosh(a),
            math.atan(a), math.asin(a * 0.5), math.acos(a * 0.5), a ** p, max(a, b), b,
            math.exp(a), math.log(a), math.sqrt(a), math.sin(a) + math.cos(b),
            a / b - b * p, p, -a, math.floor(b * 7.0), -1.0, 2.0, 1.0, 2.0]
    n = len(exprs)
    ws = np.zeros(st.oz + 1)
    ws[0], ws[1], ws[st.ow] = a, b, p
    L = np.zeros(1)
    assert f(0, 0.0, 2, 0, ws.ctypes.data, L.ctypes.data) == 0
    assert ws[n + 2 * n:n + 3 * n].tolist() == want            # stage 2's derivative slot


def test_the_llvm_stage_records_and_reports_a_non_finite_output():
    tr = sz.Trace()
    x0, x1 = tr.leaf("x0", False), tr.leaf("x1", False)
    ratio = x0 / x1
    st, f = _stage([x0 + x1, x1], checked=[ratio], records=[(1, x0 * 2.0)])
    ws = np.zeros(st.oz + 1)
    L = np.zeros(4)
    ws[0], ws[1] = 3.0, 2.0
    assert f(1, 0.0, 0, 2, ws.ctypes.data, L.ctypes.data) == 0   # record at L[2 + 1]
    assert L.tolist() == [0.0, 0.0, 0.0, 6.0] and ws[2:4].tolist() == [5.0, 2.0]
    assert f(2, 0.0, 1, 0, ws.ctypes.data, L.ctypes.data) == 0   # record only (final)
    assert L[1] == 6.0 and ws[4:6].tolist() == [0.0, 0.0]
    ws[1] = 0.0                                                   # 3 / 0: not finite
    assert f(1, 0.0, 0, 0, ws.ctypes.data, L.ctypes.data) == 2
    assert f(0, 0.0, 0, 0, ws.ctypes.data, L.ctypes.data) == 0    # no record, no check


@pytest.mark.parametrize("a,b", [(0.3, 0.9), (0.9, 0.3), (0.6, 0.6)])
def test_the_llvm_stage_computes_reflected_operators_and_every_comparison(a, b):
    """Reflected operators (a constant on the left) and each comparison, at points below,
    above and ON the boundary, where a '>=' compiled as '>' (or '<=' as '<') would differ."""
    tr = sz.Trace()
    x0, x1 = tr.leaf("x0", False), tr.leaf("x1", False)
    exprs = [1.0 - x0, 2.0 / x0, 3.0 + x0, 4.0 * x0, 2.0 ** x0, 1.5 - x0 / x1,
             tr.select(x0 >= x1, 1.0, 2.0), tr.select(x0 <= x1, 1.0, 2.0),
             tr.select(x0 > x1, 1.0, 2.0), tr.select(x0 < x1, 1.0, 2.0),
             tr.select(x0 == x1, 1.0, 2.0), tr.select(x0 != x1, 1.0, 2.0),
             (x0 >= x1) * 3.0, (x0 <= x1) * 3.0]
    st, f = _stage(exprs)
    want = [1.0 - a, 2.0 / a, 3.0 + a, 4.0 * a, 2.0 ** a, 1.5 - a / b,
            1.0 if a >= b else 2.0, 1.0 if a <= b else 2.0, 1.0 if a > b else 2.0,
            1.0 if a < b else 2.0, 1.0 if a == b else 2.0, 1.0 if a != b else 2.0,
            3.0 * (a >= b), 3.0 * (a <= b)]
    n = len(exprs)
    ws = np.zeros(st.oz + 1)
    ws[0], ws[1] = a, b
    L = np.zeros(1)
    assert f(0, 0.0, 2, 0, ws.ctypes.data, L.ctypes.data) == 0
    assert ws[n + 2 * n:n + 3 * n].tolist() == want


def test_a_freed_stage_leaves_the_next_compile_working(tmp_path):
    """llvmlite's MCJIT engine owns the target machine it is made with: a machine shared by
    every stage was deleted with the first engine freed, and the next compile crashed the
    process (std::bad_alloc or a segfault).  In a child process, so a regression fails
    this test instead of killing the run."""
    pytest.importorskip("numba")
    import subprocess
    import sys
    script = f"""
import gc, fwdstep
from fwdstep.compiled import llvm_stage
def run(g):
    path = {str(tmp_path / "d.yaml")!r}
    open(path, "w").write('''
blocks:
  k: {{type: Gain, gain: %s}}
  i: {{type: Integrator, initial: 1.0}}
connections:
  - i.y -> k.u
  - k.y -> i.u
simulation: {{t_final: 0.1, step: 0.01, solver: rk4}}
''' % g)
    return fwdstep.simulate(fwdstep.load_diagram(path), backend="compiled")
run(-1.5)
llvm_stage._compiled.clear()
gc.collect()
r = run(-2.5)
print(r.backend, repr(float(r["i.y"][-1])))
"""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-500:]
    backend, value = out.stdout.split()
    assert backend == "compiled"
    assert abs(float(value) - math.exp(-0.25)) < 1e-8          # x' = -2.5 x to t = 0.1


def test_the_numbers_a_branch_was_written_for_are_checked_for_other_values():
    """A kernel's branch on a parameter fixes the code for that value (``Trace.fixed``):
    a stage reused with other values (compiled_sensitivity's memo) asks
    ``decisions_hold``, which is False once the branch would go the other way."""
    tr = sz.Trace()
    k = tr.leaf("p0", True, np.array([2.0]))
    x = tr.leaf("x0", False)
    y = x * 3.0 if k > 1.0 else x * 5.0
    assert y.op == "*" and len(tr.decisions) == 1
    assert tr.decisions_hold({k.n: np.array([1.5])})
    assert not tr.decisions_hold({k.n: np.array([0.5])})
    assert tr.decisions_hold({})                  # the traced value itself
