"""Stacked-filter blocks (blocks/stacked.py) against their transfer functions.

Each realisation is checked by its frequency response, C (jw I - A)^-1 B + D, against the
polynomial ratio it claims, at several frequencies; derivative outputs against (jw)^k times
the base response; LinearCombination against numpy.einsum; FrequencyParameters against the
expansion of prod_i (p^2 + omega_i^2) and the paper's n* = 3 formulas.
"""
import numpy as np
import pytest

import fwdstep.blocks  # noqa: F401  registers the library
from fwdstep.blocks.stacked import (FilterDerivatives, FrequencyParameters, LinearCombination,
                            TransferFunctionSum)

W_GRID = np.array([0.05, 0.3, 1.0, 2.7, 9.0, 40.0])


def matrices(blk):
    """(A, B by input, C by output, D by (output, input)) from the generic linear form."""
    p = blk.p
    A = p.A_T[0].T
    names_in, names_out = blk._in_names, blk._out_names
    B = {names_in[j]: getattr(p, f"B_T_{j}")[0].T for j in blk._b_used}
    C = {o: getattr(p, f"C_T_{k}")[0].T for k, o in enumerate(names_out)}
    D = {(o, names_in[j]): getattr(p, f"D_T_{k}_{j}")[0].T
         for k, o in enumerate(names_out) for j in blk._d_used[k]}
    return A, B, C, D


def response(blk, out, inp, w):
    A, B, C, D = matrices(blk)
    n = A.shape[0]
    Bj = B.get(inp, np.zeros((n, blk.inputs[inp].size)))
    G = C[out] @ np.linalg.solve(1j * w * np.eye(n) - A, Bj.astype(complex))
    return G + D.get((out, inp), 0.0)


def ratio(num, den, w, power=0):
    s = 1j * w
    return s ** power * np.polyval(num, s) / np.polyval(den, s)


@pytest.mark.parametrize("first,step,count", [(0, 2, 3), (1, 1, 2), (0, 1, 1)])
def test_filter_derivatives_matches_each_stacked_transfer_function(first, step, count):
    num = [1.0, 6.0, 9.0]                                # N_H = (p + 3)^2
    den = np.poly([-3.0] * 6 + [-4.0])                   # A*(p) D(p), degree 7
    blk = FilterDerivatives("W", num=num, den=den, first=first, step=step, count=count,
                            shape=[2])
    for w in W_GRID:
        G = response(blk, "y", "u", w)                   # (2*count, 2)
        for k in range(count):
            expected = ratio(num, den, w, first + k * step)
            for e in range(2):
                assert abs(G[e * count + k, e] - expected) <= 1e-9 * max(1, abs(expected))
                assert abs(G[e * count + k, 1 - e]) <= 1e-12   # channels do not mix


def test_filter_derivatives_biproper_last_output_has_feedthrough_and_improper_refused():
    num, den = [1.0, 4.0, 4.0], np.poly([-2.0] * 4)
    blk = FilterDerivatives("W", num=num, den=den, first=0, step=2, count=2)
    assert blk.feedthrough("y") == ("u",)
    with pytest.raises(Exception, match="improper"):
        FilterDerivatives("W", num=num, den=den, first=0, step=2, count=3)


def test_transfer_function_sum_outputs_and_derivatives_match_transfer_functions():
    den = np.polymul([1.0, 6.0, 9.0], [1.0, 0.0, 0.0, 0.0, 0.0])   # N_H p^4 (n* = 2)
    A_star = np.poly([-3.0] * 4)
    p4 = np.array([1.0, 0, 0, 0, 0])
    num1 = -np.polymul(np.polysub(A_star, p4), [1.0, 6.0, 9.0])   # relative degree 1
    num2 = A_star                                                 # relative degree 2
    blk = TransferFunctionSum("e2", den=den, nums=[num1, num2], derivatives=2,
                              input_derivatives=[1, 0], shape=[])
    assert blk.relative_degrees == [1, 2]
    for w in W_GRID:
        for k, out in enumerate(["y", "y_d1", "y_d2"]):
            # the u1 path: u1 and its derivative u1_d1 = jw u1 both carry the same signal
            g1 = response(blk, out, "u1", w) + 1j * w * response(blk, out, "u1_d1", w)
            g2 = response(blk, out, "u2", w)
            for g, num in ((g1, num1), (g2, num2)):
                expected = ratio(num, den, w, k)
                assert abs(g.item() - expected) <= 1e-8 * max(1, abs(expected))
    assert blk.feedthrough("y") == ()
    assert set(blk.feedthrough("y_d1")) == {"u1"}
    assert set(blk.feedthrough("y_d2")) == {"u1", "u1_d1", "u2"}


def test_transfer_function_sum_derivatives_are_exact_for_any_state():
    """y_dk = C A^k x + (input terms): d/dt of the state part of y_d(k-1) is C A^k x."""
    den = np.poly([-1.0, -2.0, -5.0])
    blk = TransferFunctionSum("f", den=den, nums=[[1.0, 0.5], [2.0, 1.0, 3.0]],
                              derivatives=2, input_derivatives=[1, 1], shape=[])
    A, B, C, D = matrices(blk)
    assert np.allclose(C["y_d1"], C["y"] @ A, atol=1e-12)
    assert np.allclose(C["y_d2"], C["y_d1"] @ A, atol=1e-12)


def test_transfer_function_sum_omit_direct_drops_exactly_the_direct_term():
    den = np.polymul([1.0, 6.0, 9.0], [1.0, 0.0, 0.0])
    num2 = np.poly([-3.0, -3.0])
    full = TransferFunctionSum("a", den=den, nums=[[1.0], num2], derivatives=2)
    cut = TransferFunctionSum("b", den=den, nums=[[1.0], num2], derivatives=2,
                              omit_direct=[2])
    assert full.direct_terms[2][1] == pytest.approx(1.0)
    assert cut.feedthrough("y_d2") == ()
    for w in W_GRID:
        diff = response(full, "y_d2", "u2", w) - response(cut, "y_d2", "u2", w)
        assert abs(diff.item() - 1.0) <= 1e-12


def test_transfer_function_sum_refuses_a_missing_input_derivative():
    with pytest.raises(Exception, match="u1_d1"):
        TransferFunctionSum("f", den=[1.0, 1.0], nums=[[1.0]], derivatives=2)


def test_linear_combination_matches_einsum_with_batches_and_fixed_weights():
    rng = np.random.default_rng(0)
    blk = LinearCombination("c", weights=[3], fixed=[1.0, -2.0], shape=[2, 4])
    c = rng.normal(size=(5, 3))
    u = rng.normal(size=(1, 2, 4, 5))
    (y,) = blk.output(0.0, np.zeros((1, 0)), (c, u))
    w = np.concatenate([c, np.tile([1.0, -2.0], (5, 1))], axis=1)
    assert np.allclose(y, np.einsum("bijk,bk->bij", np.broadcast_to(u, (5, 2, 4, 5)), w),
                       atol=1e-13)
    scalar = LinearCombination("s", weights=[], fixed=[1.0], shape=[2])
    (y,) = scalar.output(0.0, np.zeros((1, 0)), (np.array([2.5]), np.array([[[1.0, 3.0],
                                                                             [4.0, 5.0]]])))
    assert np.allclose(y, [[2.5 + 3.0, 10.0 + 5.0]])


@pytest.mark.parametrize("omegas", [[3.0], [2.0, 4.0], [2.0, 3.0, 4.5]])
def test_frequency_parameters_expand_the_product_of_binomials(omegas):
    (theta,) = FrequencyParameters("t", omegas=omegas).output(0.0, None, ())
    product = np.array([1.0])
    for w in omegas:
        product = np.polymul(product, [1.0, 0.0, w * w])       # p^2 + omega^2
    # product = p^(2n*) + theta_n* p^(2n*-2) + ... + theta_1: every other coefficient
    expected = product[2::2][::-1]
    assert np.allclose(theta[0], expected, rtol=1e-14)
    assert np.allclose(product[1::2], 0.0)


def test_frequency_parameters_n3_matches_the_paper_formulas():
    w1, w2, w3 = 2.0, 3.0, 4.5
    (theta,) = FrequencyParameters("t", omegas=[w1, w2, w3]).output(0.0, None, ())
    s1, s2, s3 = w1 ** 2, w2 ** 2, w3 ** 2
    assert np.allclose(theta[0], [s1 * s2 * s3, s1 * s2 + s1 * s3 + s2 * s3, s1 + s2 + s3],
                       rtol=1e-14)
