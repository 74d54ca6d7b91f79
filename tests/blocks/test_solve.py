"""The Solve block (y = A^-1 b, least squares, minimum norm, damped) against numpy.linalg,
on the NumPy path (LAPACK) and through its kernel (what compiled runs trace)."""
import numpy as np
import pytest

from fwdstep.blocks.arithmetic import Solve, solve_output
from fwdstep.core.errors import ParameterError


def reference(A, b, d):
    """numpy.linalg per variant: solve, lstsq (minimum norm for a wide A), or the damped
    normal equations."""
    out = []
    for Ab, bb in zip(A, b):
        m, k = Ab.shape
        if d == 0.0:
            out.append(np.linalg.solve(Ab, bb) if m == k else
                       np.linalg.lstsq(Ab, bb, rcond=None)[0])
        elif m >= k:
            out.append(np.linalg.solve(Ab.T @ Ab + d * np.eye(k), Ab.T @ bb))
        else:
            out.append(Ab.T @ np.linalg.solve(Ab @ Ab.T + d * np.eye(m), bb))
    return np.array(out)


@pytest.mark.parametrize("shape", [(6, 6), (9, 4), (3, 6), (1, 1)])
@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_solve_is_numpy_linalg(shape, damping):
    rng = np.random.default_rng(sum(shape))
    A = rng.standard_normal((5,) + shape) + 2 * np.eye(*shape)
    b = rng.standard_normal((5, shape[0]))
    block = Solve("s", shape=list(shape), damping=damping)
    expected = reference(A, b, damping)
    # the normal equations square the condition number (documented)
    tolerance = 1e-15 * max(np.linalg.cond(a) for a in A) ** 2 * np.abs(expected).max()
    for y in (block.output(0.0, None, (A, b))[0],                         # NumPy path
              solve_output(0.0, None, A, b, block.p.damping)[0]):          # the kernel
        assert y.shape == (5, shape[1])
        np.testing.assert_allclose(y, expected, rtol=0, atol=tolerance)


def test_a_batch_broadcasts_a_shared_matrix_and_is_its_variants():
    rng = np.random.default_rng(1)
    A, b = rng.standard_normal((1, 4, 4)) + 3 * np.eye(4), rng.standard_normal((3, 4))
    block = Solve("s", shape=[4, 4])
    y = block.output(0.0, None, (A, b))[0]
    for k in range(3):
        np.testing.assert_allclose(y[k], np.linalg.solve(A[0], b[k]), rtol=1e-13)


def test_bad_parameters():
    with pytest.raises(ParameterError, match="'damping' must be >= 0"):
        Solve("s", shape=[2, 2], damping=-1.0)
    with pytest.raises(ParameterError, match="shape"):
        Solve("s", shape=[2])
