"""The batched helpers of block kernels (fwdstep.kernelops) against per-variant NumPy written
out here, including the broadcast of a batch axis of length 1; and (slow: numba compiles
them) their numba twins in fwdstep.compiled_ops against the NumPy versions, to 1e-12."""
import numpy as np
import pytest

from fwdstep import kernelops as ko

RNG = np.random.default_rng(7)


def _cases():
    """(name, args, reference) with a shared operand (batch 1) on one side."""
    B, n, k, m = 3, 4, 5, 2
    M = RNG.standard_normal((B, n, k))
    v = RNG.standard_normal((1, k))
    w = RNG.standard_normal((B, n))
    C = RNG.standard_normal((1, k, m))
    S = RNG.standard_normal((B, n, n)) + 4.0 * np.eye(n)
    r = RNG.standard_normal((1, n))
    a = RNG.standard_normal((B, n)) + 1j * RNG.standard_normal((B, n))
    u = RNG.standard_normal((B, 6))
    idx = np.array([[5.0, 0.0, 2.0]])
    return [
        ("bmatvec", (M, v), [M[b] @ v[0] for b in range(B)]),
        ("bvecmat", (w, M), [w[b] @ M[b] for b in range(B)]),
        ("bmatmul", (M, C), [M[b] @ C[0] for b in range(B)]),
        ("bsolve", (S, r), [np.linalg.solve(S[b], r[0]) for b in range(B)]),
        ("symupper", (S,), [np.triu(S[b]) + np.triu(S[b], 1).T for b in range(B)]),
        ("cumsum1", (a,), [[a[b, :i + 1].sum() for i in range(n)] for b in range(B)]),
        ("take1", (u, idx), [u[b, [5, 0, 2]] for b in range(B)]),
    ]


CASES = _cases()


@pytest.mark.parametrize("name,args,ref", CASES, ids=[c[0] for c in CASES])
def test_numpy_helpers_equal_per_variant_numpy(name, args, ref):
    got = getattr(ko, name)(*args)
    np.testing.assert_allclose(got, np.array(ref), rtol=0, atol=1e-12)


def test_symupper_is_symmetric_and_keeps_the_upper_triangle():
    M = RNG.standard_normal((2, 5, 5))
    before = M.copy()
    S = ko.symupper(M)
    assert np.array_equal(S, S.transpose((0, 2, 1)))
    iu = np.triu_indices(5)
    assert np.array_equal(S[:, iu[0], iu[1]], M[:, iu[0], iu[1]])
    assert np.array_equal(M, before)           # the argument is not modified


@pytest.mark.slow            # numba compiles every twin (seconds each on a loaded machine)
@pytest.mark.parametrize("name,args,ref", CASES, ids=[c[0] for c in CASES])
def test_numba_twins_equal_the_numpy_helpers(name, args, ref):
    pytest.importorskip("numba")
    from fwdstep import compiled_ops
    got = getattr(compiled_ops, name)(*args)
    np.testing.assert_allclose(got, getattr(ko, name)(*args), rtol=0, atol=1e-12)
