"""Block Jacobians (fwdstep.analysis.jacobian) against central differences, for every registered block.

The reference is computed here, independently: central differences of the block's own
``output`` and ``derivative`` (the NumPy path) extrapolated to step zero (Ridders' method);
the Jacobian must agree within 1e-7 of the larger of 1 and its largest entry.
"""
import math
import zlib

import numpy as np
import pytest

from fwdstep.compiled import scalarize as sz
from fwdstep.analysis.jacobian import BlockJacobian, GraphProgram, forward_tangents
from fwdstep.structure.library import load_library

REGISTRY = load_library()
NAMES = sorted(REGISTRY)
TOLERANCE = 1e-7


def _make(name):
    cls = REGISTRY[name]
    if "[install fwdstep[" in cls.summary():
        pytest.skip(f"{name}: {cls.summary()}")
    return cls("example", **cls.example)


def _evaluate(blk, t, v):
    """Outputs (vectorised, declared order) then derivative at the points v (B, n + inputs)."""
    n = blk.n_states
    us, c = [], n
    for port in blk.inputs.values():
        us.append(v[:, c:c + port.size].reshape((-1,) + port.shape))
        c += port.size
    B = v.shape[0]
    parts = [np.broadcast_to(np.asarray(y, dtype=float), (B,) + p.shape).reshape(B, -1)
             for y, p in zip(blk.output(t, v[:, :n], tuple(us)), blk.outputs.values())]
    if n:
        parts.append(np.asarray(blk.derivative(t, v[:, :n], tuple(us))).reshape(B, n))
    return np.concatenate(parts, axis=1) if parts else np.zeros((B, 0))


def _central(blk, t, base):
    """Central differences extrapolated to step 0 (Ridders' method: a tableau of central
    differences at steps h0 / 1.4^i, Richardson-extrapolated; the entry with the smallest
    error estimate), column by column: accurate also where a block is steep (Friction's
    tanh(qdot / 0.01)), where one fixed step is either too coarse or too noisy."""
    C = base.shape[1]
    rows = _evaluate(blk, t, base).shape[1]
    J = np.zeros((rows, C))
    for k in range(C):
        h = 1e-2 * max(1.0, abs(base[0, k]))
        best, err = None, np.full(rows, np.inf)
        table = []
        for i in range(10):
            e = np.zeros_like(base)
            e[0, k] = h
            row = [((_evaluate(blk, t, base + e) - _evaluate(blk, t, base - e)) / (2 * h))[0]]
            fac = 1.4 ** 2
            for j in range(1, i + 1):
                row.append((row[j - 1] * fac - table[i - 1][j - 1]) / (fac - 1.0))
                fac *= 1.4 ** 2
                estimate = np.maximum(np.abs(row[j] - row[j - 1]),
                                      np.abs(row[j] - table[i - 1][j - 1]))
                better = estimate <= err
                best = np.where(better, row[j], best if best is not None else row[j])
                err = np.where(better, estimate, err)
            table.append(row)
            h /= 1.4
        J[:, k] = best
    return J


@pytest.mark.parametrize("name", NAMES)
def test_block_jacobian_matches_central_differences(name):
    """d output/d x, d output/d u, d derivative/d x, d derivative/d u at 3 random points."""
    blk = _make(name)
    bj = BlockJacobian(blk)
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    for trial in range(3):
        t = float(rng.uniform(0.05, 2.0))
        x = rng.standard_normal((1, blk.n_states)) * 0.3
        u = tuple(rng.standard_normal((1,) + p.shape) * 0.5 for p in blk.inputs.values())
        jac = bj.at(t, x, u)
        base = np.concatenate([x] + [a.reshape(1, -1) for a in u], axis=1)
        ref = _central(blk, t, base)
        J = jac.J[0]
        assert J.shape == ref.shape
        scale = max(1.0, float(np.abs(ref).max(initial=0.0)))
        err = float(np.abs(J - ref).max(initial=0.0))
        assert err <= TOLERANCE * scale, (name, bj.method, err, scale)


def test_exact_methods_are_used_where_possible():
    """Every block with kernels written in real arithmetic is traced (exact); linear blocks
    use their LinearForm; only the blocks the tracer refuses fall back to differences."""
    numeric = set()
    for name in NAMES:
        cls = REGISTRY[name]
        if "[install fwdstep[" in cls.summary():
            continue
        bj = BlockJacobian(cls("example", **cls.example))
        if bj.method == "central differences":
            numeric.add(name)
    assert numeric <= {"Lookup1D", "NLinkArm", "NLinkRegressor", "URDFArm", "URDFRegressor",
                       "WhiteNoise"}, numeric
    assert BlockJacobian(_make("TwoLinkArm")).method == "traced"
    assert BlockJacobian(_make("TransferFunction")).method == "linear form"


def test_parts_are_named_by_port():
    blk = _make("TwoLinkArm")
    jac = BlockJacobian(blk).at(0.0, np.zeros((1, 4)), (np.zeros((1, 2)), np.zeros((1, 2))))
    assert jac.part("y.q", "x").tolist() == [[[1, 0, 0, 0], [0, 1, 0, 0]]]
    assert jac.part("dx", "u.tau").shape == (1, 4, 2)
    assert not jac.part("y.q", "u.tau").any()          # no feedthrough


def test_parameter_columns_for_sensitivities():
    """d/d gain of a Gain block is the input, arranged per entry of the gain matrix."""
    from fwdstep.structure.library import lookup
    blk = lookup("Gain")("g", gain=[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    bj = BlockJacobian(blk, params=tuple(vars(blk.p)))
    u = np.array([[0.7, -1.3]])
    jac = bj.at(0.0, np.zeros((1, 0)), (u,))
    name = next(iter(vars(blk.p)))
    dp = jac.part("y.y", f"p.{name}")[0]
    # y = G u whatever the stored layout of G: check against differences of the block itself
    arr = getattr(blk.p, name)
    for c in range(arr[0].size):
        moved = arr.copy().reshape(1, -1)
        moved[0, c] += 1e-6
        probe = lookup("Gain")("g", gain=[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
        setattr(probe.p, name, moved.reshape(arr.shape))
        probe.__dict__.pop("_kargs", None)
        d = (probe.output(0.0, np.zeros((1, 0)), (u,))[0] - blk.output(
            0.0, np.zeros((1, 0)), (u,))[0]) / 1e-6
        np.testing.assert_allclose(dp[:, c], d[0], atol=1e-8)


def _traced_function(fn, n):
    tr = sz.Trace()
    rb = sz.Rebinder(tr)
    x = sz.sym_array(tr, (1, n), lambda i: (f"x{i[1]}", False))
    y = sz.as_nodes(tr, sz.run_traced(rb, fn, x), (1,))
    return tr, list(x[0]), y[0]


def _every_operation(x):
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    r = (np.sin(a) * np.cos(b) + np.tan(c) + np.exp(a) / (1.0 + b * b) + np.log(2.0 + a)
         + np.sqrt(3.0 + c) + np.tanh(a * b) + np.sinh(c) - np.cosh(b) + np.arctan(a)
         + np.arcsin(0.3 * c) + np.arccos(0.2 * b) + np.abs(a - b) + np.arctan2(a, 1.5 + c)
         + (2.0 + a) ** 1.5 + (1.5 + b) ** (1.0 + 0.1 * c) + np.where(a > b, a * c, b - c)
         + np.maximum(a, c) + math.pi * np.floor(4.0) * a)
    return r


def test_forward_mode_rules_against_differences():
    """Every differentiation rule of forward_tangents, on a function using each operation."""
    tr, leaves, root = _traced_function(_every_operation, 3)
    (tangent,) = forward_tangents(tr, [root], leaves)
    prog = GraphProgram(tr, [tangent[k] for k in range(3)])
    rng = np.random.default_rng(5)
    for _ in range(5):
        v = rng.uniform(-0.8, 0.8, 3)
        got = [float(np.asarray(g).reshape(-1)[0])
               for g in prog({f"x{i}": np.array([v[i]]) for i in range(3)})]
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-6
            ref = (_every_operation((v + e)[None]) - _every_operation((v - e)[None])) / 2e-6
            assert abs(got[k] - ref[0]) <= 1e-7 * max(1.0, abs(ref[0])), (k, got[k], ref)
