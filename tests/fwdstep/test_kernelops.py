"""The batched helpers of block kernels (fwdstep.core.kernelops) against per-variant NumPy written
out here, including the broadcast of a batch axis of length 1; and (slow: numba compiles
them) their numba twins in fwdstep.compiled.compiled_ops against the NumPy versions, to 1e-12."""
import numpy as np
import pytest

from fwdstep.core import kernelops as ko

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
    ] + _paths(B)


def _paths(B):
    """The other branches of the helpers: one matrix shared by every variant (a 2-d product),
    matrices above ``ko.SMALL`` entries (np.matmul), and the 2x2 solve (Cramer's rule)."""
    big = RNG.standard_normal((B, 6, 7))
    shared = RNG.standard_normal((1, 3, 4))
    x7, x6 = RNG.standard_normal((B, 7)), RNG.standard_normal((B, 6))
    x4, x3 = RNG.standard_normal((B, 4)), RNG.standard_normal((B, 3))
    S2 = RNG.standard_normal((B, 2, 2)) + 3.0 * np.eye(2)
    r2 = RNG.standard_normal((1, 2))
    S1 = RNG.standard_normal((1, 2, 2)) + 3.0 * np.eye(2)
    v2 = RNG.standard_normal((B, 2))
    assert big.shape[1] * big.shape[2] > ko.SMALL
    return [
        ("bmatvec", (big, x7), [big[b] @ x7[b] for b in range(B)]),
        ("bvecmat", (x6, big), [x6[b] @ big[b] for b in range(B)]),
        ("bmatvec", (shared, x4), [shared[0] @ x4[b] for b in range(B)]),
        ("bvecmat", (x3, shared), [x3[b] @ shared[0] for b in range(B)]),
        ("bsolve", (S2, r2), [np.linalg.solve(S2[b], r2[0]) for b in range(B)]),
        ("bsolve", (S1, v2), [np.linalg.solve(S1[0], v2[b]) for b in range(B)]),
    ]


CASES = _cases()


IDS = [f"{c[0]}-{k}" for k, c in enumerate(CASES)]


@pytest.mark.parametrize("name,args,ref", CASES, ids=IDS)
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
@pytest.mark.parametrize("name,args,ref", CASES, ids=IDS)
def test_numba_twins_equal_the_numpy_helpers(name, args, ref):
    pytest.importorskip("numba")
    from fwdstep.compiled import compiled_ops
    got = getattr(compiled_ops, name)(*args)
    np.testing.assert_allclose(got, getattr(ko, name)(*args), rtol=0, atol=1e-12)


@pytest.mark.parametrize("n,m", [(2, 4), (2, 2), (3, 3), (1, 32), (6, 7), (7, 43),
                                 (43, 7), (12, 60)])
def test_a_variant_in_a_batch_gets_the_bits_of_its_run_alone(n, m):
    """Sweeps promise each variant equals its own run; a diverging variant amplifies any
    rounding difference, so the products must not depend on the batch size."""
    B = 7
    M, v, s = (RNG.standard_normal(shape) for shape in ((B, n, m), (B, m), (B, n)))
    S = RNG.standard_normal((B, 2, 2)) + 3.0 * np.eye(2)
    for name, args in (("bmatvec", (M, v)), ("bvecmat", (s, M)), ("bmatvec", (M[:1], v)),
                       ("bvecmat", (s, M[:1])), ("bsolve", (S, v[:, :2]))):
        batch = getattr(ko, name)(*args)
        alone = [getattr(ko, name)(*(a[k:k + 1] if a.shape[0] == B else a for a in args))[0]
                 for k in range(B)]
        assert np.array_equal(batch, np.array(alone)), (name, n, m)
