"""Arithmetic blocks: outputs against independent numpy computations, batch behaviour
(batched inputs and stacked parameters), feedthrough, and parameter errors."""
import re

import numpy as np
import pytest

from fwdstep.blocks.arithmetic import Demux, Gain, Mux, Product, ScalarProduct, Selector, Sum
from fwdstep.structure.compiler import stack_blocks
from fwdstep.core.errors import ParameterError

RNG = np.random.default_rng(20240611)
NO_STATE = np.zeros((1, 0))
B = 5


def call(block, *inputs):
    return block.output(0.0, NO_STATE, tuple(inputs))


def random_inputs(block, batch):
    return [RNG.standard_normal((batch,) + port.shape) for port in block.inputs.values()]


def assert_batched_inputs_match_separate_calls(block):
    """(B, ...) inputs, and a mix of (1, ...) and (B, ...) inputs, give per-row results equal
    to B separate calls with (1, ...) inputs."""
    batched = random_inputs(block, B)
    mixes = [batched]
    if len(batched) > 1:
        mixes.append([batched[0][:1]] + batched[1:])
    for inputs in mixes:
        ys = call(block, *inputs)
        for i in range(B):
            row = [v[min(i, v.shape[0] - 1)][None] for v in inputs]
            for yb, ys_i in zip(ys, call(block, *row)):
                assert yb.shape[0] == B
                np.testing.assert_allclose(yb[i], ys_i[0], rtol=1e-15, atol=1e-15)


def assert_stacked_params_match_separate_calls(cls, variants):
    """Parameters stacked by the engine's batched-sweep code, with (B, ...) inputs and with
    (1, ...) inputs, give per-variant results equal to separate blocks."""
    singles = [cls("b", **v) for v in variants]
    big = stack_blocks([[cls("b", **v)] for v in variants])[0]
    n = len(variants)
    batched = random_inputs(big, n)
    for inputs in (batched, [v[:1] for v in batched]):
        ys = call(big, *inputs)
        for i, single in enumerate(singles):
            row = [v[min(i, v.shape[0] - 1)][None] for v in inputs]
            for yb, ys_i in zip(ys, call(single, *row)):
                assert yb.shape[0] == n
                np.testing.assert_allclose(yb[i], ys_i[0], rtol=1e-15, atol=1e-15)


def table_ports(cls):
    rows = re.findall(r"^\s*\|\s*(\w+)\s*\|\s*(in|out)\s*\|", cls.__doc__, re.M)
    return [name for name, _ in rows]


ALL = [Gain, Sum, Product, ScalarProduct, Selector, Mux, Demux]


@pytest.mark.parametrize("cls", ALL)
def test_example_matches_docstring_and_feeds_through(cls):
    blk = cls("ex", **cls.example)
    assert table_ports(cls) == list(blk.inputs) + list(blk.outputs)
    ys = call(blk, *random_inputs(blk, 1))
    for y, port in zip(ys, blk.outputs.values()):
        assert y.shape == (1,) + port.shape
        assert blk.feedthrough(port.name) == tuple(blk.inputs)


@pytest.mark.parametrize("cls", ALL)
def test_example_batched_inputs(cls):
    assert_batched_inputs_match_separate_calls(cls("ex", **cls.example))


# --------------------------------------------------------------------------- Gain
def test_gain_matrix_scalar_and_stacked():
    K = RNG.standard_normal((3, 2))
    u = RNG.standard_normal((B, 2))
    np.testing.assert_allclose(call(Gain("g", gain=K), u)[0], u @ K.T, rtol=1e-14)
    m = RNG.standard_normal((B, 2, 4))
    np.testing.assert_array_equal(call(Gain("g", gain=-3.0, shape=[2, 4]), m)[0], -3.0 * m)
    gains = [RNG.standard_normal((3, 2)) for _ in range(B)]
    assert_stacked_params_match_separate_calls(Gain, [{"gain": k} for k in gains])
    assert_stacked_params_match_separate_calls(Gain, [{"gain": g, "shape": [2]}
                                                      for g in (1.0, -2.0, 0.5)])


# --------------------------------------------------------------------------- Sum
def test_sum_signs():
    blk = Sum("s", signs="+-+", shape=[2, 3])
    assert list(blk.inputs) == ["u1", "u2", "u3"]
    u1, u2, u3 = (RNG.standard_normal((B, 2, 3)) for _ in range(3))
    np.testing.assert_allclose(call(blk, u1, u2, u3)[0], u1 - u2 + u3, rtol=1e-15)
    neg = Sum("s", signs="--")
    assert neg.outputs["y"].shape == ()
    a, b = np.array([1.5, 2.0]), np.array([0.25, -1.0])
    np.testing.assert_array_equal(call(neg, a, b)[0], [-1.75, -1.0])
    assert call(Sum("s", signs="+"), a)[0].tolist() == a.tolist()


def test_sum_batched_inputs():
    assert_batched_inputs_match_separate_calls(Sum("s", signs="-+-+", shape=[3]))


# --------------------------------------------------------------------------- Product
@pytest.mark.parametrize("a_shape, b_shape, ta, tb, y_shape", [
    ((4, 3), (3,), False, False, (4,)),        # Y theta_hat
    ((4, 3), (4,), True, False, (3,)),         # Y^T s
    ((4, 3), (4, 3), False, True, (4, 4)),     # W W^T
    ((4, 3), (4, 2), True, False, (3, 2)),
    ((3, 4), (2, 3), True, True, (4, 2)),
    ((3,), (3, 2), False, False, (2,)),        # row vector times matrix
    ((2,), (3, 2), False, True, (3,)),
    ((3,), (3,), False, False, ()),            # dot product
])
def test_product_against_numpy(a_shape, b_shape, ta, tb, y_shape):
    blk = Product("p", a_shape=list(a_shape), b_shape=list(b_shape), transpose_a=ta,
                  transpose_b=tb)
    assert blk.outputs["y"].shape == y_shape
    a = RNG.standard_normal((B,) + a_shape)
    b = RNG.standard_normal((B,) + b_shape)
    y = call(blk, a, b)[0]
    assert y.shape == (B,) + y_shape
    for i in range(B):
        ref = np.dot(a[i].T if ta else a[i], b[i].T if tb else b[i])
        np.testing.assert_allclose(y[i], ref, rtol=1e-13, atol=1e-14)
    assert_batched_inputs_match_separate_calls(blk)


# --------------------------------------------------------------------------- ScalarProduct
def test_scalar_product():
    blk = ScalarProduct("k", shape=[2, 3])
    k = RNG.standard_normal(B)
    u = RNG.standard_normal((B, 2, 3))
    y = call(blk, k, u)[0]
    for i in range(B):
        np.testing.assert_array_equal(y[i], k[i] * u[i])
    np.testing.assert_array_equal(call(blk, k[:1], u)[0], k[0] * u)   # one k for all rows
    scalar = ScalarProduct("k")
    assert call(scalar, np.array([2.0, 3.0]), np.array([4.0, 5.0]))[0].tolist() == [8.0, 15.0]
    assert_batched_inputs_match_separate_calls(ScalarProduct("k", shape=[4]))


# --------------------------------------------------------------------------- Selector, Mux, Demux
def test_selector_mux_demux():
    u = RNG.standard_normal((B, 5))
    np.testing.assert_array_equal(call(Selector("s", n=5, indices=[4, 0, 0]), u)[0],
                                  u[:, [4, 0, 0]])
    np.testing.assert_array_equal(call(Selector("s", n=5, indices=[1, 2, 3]), u)[0], u[:, 1:4])
    parts = call(Demux("d", sizes=[2, 1, 2]), u)
    assert [p.shape for p in parts] == [(B, 2), (B, 1), (B, 2)]
    np.testing.assert_array_equal(np.concatenate(parts, axis=1), u)
    np.testing.assert_array_equal(call(Mux("m", sizes=[2, 1, 2]), *parts)[0], u)
    # inputs with different batch lengths broadcast
    y = call(Mux("m", sizes=[1, 2]), np.array([[7.0]]), u[:, :2])[0]
    np.testing.assert_array_equal(y, np.concatenate([np.full((B, 1), 7.0), u[:, :2]], axis=1))


def test_structural_parameters_may_vary_within_a_batch():
    """Sweeps over signs, indices or the transposes of square operands stay exact."""
    assert_stacked_params_match_separate_calls(
        Sum, [{"signs": s, "shape": [2]} for s in ("+-+", "-++", "+-+", "---")])
    assert_stacked_params_match_separate_calls(
        Selector, [{"n": 4, "indices": i} for i in ([0, 1], [3, 1], [2, 2])])
    assert_stacked_params_match_separate_calls(
        Product, [{"a_shape": [3, 3], "b_shape": [3, 3], "transpose_a": ta, "transpose_b": tb}
                  for ta, tb in ((False, False), (True, False), (True, True), (False, True))])
    assert_stacked_params_match_separate_calls(
        Product, [{"a_shape": [3, 3], "b_shape": [3], "transpose_a": ta} for ta in (True, False)])


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize("cls, params, message", [
    (Product, {"a_shape": [4, 3], "b_shape": [4]},
     "block 'b': cannot multiply a by b: a_shape [4, 3] gives op(a) of shape [4, 3], b_shape "
     "[4] gives op(b) of shape [4], and the inner sizes 3 and 4 differ"),
    (Product, {"a_shape": [4, 3], "b_shape": [4, 2], "transpose_b": True},
     "block 'b': cannot multiply a by b^T: a_shape [4, 3] gives op(a) of shape [4, 3], b_shape "
     "[4, 2] gives op(b) of shape [2, 4], and the inner sizes 3 and 2 differ"),
    (Product, {"a_shape": [3], "b_shape": [3], "transpose_a": True},
     "block 'b' parameter 'transpose_a' needs a matrix a, but a_shape is [3]"),
    (Product, {"a_shape": [2, 2, 2], "b_shape": [2]},
     "block 'b' parameter 'a_shape' must be a vector [n] or a matrix [n, m], got [2, 2, 2]"),
    (Sum, {"signs": "+*"},
     "block 'b' parameter 'signs' must be a non-empty string of '+' and '-' such as \"+-\", "
     "got '+*'"),
    (Sum, {"signs": "+-", "shape": [2.5]},
     "block 'b' parameter 'shape' must be a list of positive whole numbers such as [3] or "
     "[2, 3] ([] for a scalar), got [2.5]"),
    (Selector, {"n": 3, "indices": [0, 3]},
     "block 'b' parameter 'indices' must be a non-empty list of whole numbers from 0 to 2, got "
     "[0, 3]"),
    (Mux, {"sizes": [2, 0]},
     "block 'b' parameter 'sizes' must be a non-empty list of positive whole numbers such as "
     "[2, 1], got [2, 0]"),
    (Gain, {"gain": 1.0, "bias": 2.0},
     "block 'b' (Gain) has no parameter 'bias'; valid parameters are: gain, shape"),
])
def test_bad_parameters_raise_with_exact_message(cls, params, message):
    with pytest.raises(ParameterError) as err:
        cls("b", **params)
    assert str(err.value) == message


def test_absurd_port_counts_are_refused():
    with pytest.raises(ParameterError, match="number of inputs = 5000 is larger than the limit"):
        Sum("b", signs="+" * 5000)


@pytest.mark.parametrize("signs", ["+", "-", "+-", "-+", "--", "++", "+-+-", "-+--"])
def test_sum_of_a_batch_with_shared_signs_gives_the_same_bits(signs):
    """A batch whose variants share the signs runs ``sum_signed_output`` (u1 - u2 instead
    of 1 u1 + (-1) u2): the same numbers as the general kernel and as the plain
    expression, bit for bit, signed zeros, infinities and NaN included."""
    from fwdstep.blocks.arithmetic import sum_output, sum_signed_output
    from fwdstep.structure.compiler import stack_blocks
    blocks = [[Sum("s", signs=signs, shape=[3])] for _ in range(2)]
    stacked = stack_blocks(blocks)[0]
    assert stacked.kernels.output is sum_signed_output
    rng = np.random.default_rng(7)
    u = [rng.standard_normal((5, 3)) for _ in signs]
    u[0][0] = [0.0, -0.0, np.inf]
    if len(u) > 1:
        u[1][0] = [-0.0, -0.0, np.inf]
        u[1][1, 0] = np.nan
    with np.errstate(invalid="ignore"):                  # inf - inf: NaN on both sides
        y = stacked.output(0.0, None, tuple(u))[0]
        general = sum_output(0.0, None, tuple(u), stacked.p.signs)[0]
    np.testing.assert_array_equal(np.signbit(y), np.signbit(general))
    np.testing.assert_array_equal(y, general)
    plain = -u[0] if signs[0] == "-" else +u[0]
    with np.errstate(invalid="ignore"):
        for s, v in zip(signs[1:], u[1:]):
            plain = plain - v if s == "-" else plain + v
    np.testing.assert_array_equal(y, plain)
    assert y is not u[0]
