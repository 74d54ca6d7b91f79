"""The two-link arm and its regressor as native code on the NumPy path
(``TwoLinkArm.native_kernels``, ``Regressor.native_kernels``; fwdstep/compiled/native_block.py):
the native derivative and regressor equal the arm written from its physical parameters
(Slotine & Li, Example 9.2: ``reference_terms`` of tests/blocks/test_robot.py), variant by
variant in a batch whose variants have their own parameters, and the paper's two-link
diagrams give the numbers of their runs without native code."""
from __future__ import annotations

import os

import numpy as np
import pytest

pytest.importorskip("llvmlite", reason="native kernels need llvmlite (fwdstep[fast])")

import fwdstep                                                     # noqa: E402
from fwdstep.blocks.robot import Regressor, TwoLinkArm            # noqa: E402
from fwdstep.compiled.native_block import NativeKernel, native_kernel  # noqa: E402
from fwdstep.run import program                                    # noqa: E402
from fwdstep.run.program import native_methods                     # noqa: E402
from tests.blocks.test_robot import (OTHER_ARM, SLOTINE_LI, random_states,  # noqa: E402
                                     reference_terms, stacked)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_the_native_arm_is_the_arm_of_each_variant(gravity):
    """A batch of two arms with different physical parameters (a sweep's stacked p): each
    row of the native derivative is that arm's qddot = H^-1 (tau + tau* - C qdot - g)."""
    arms = [TwoLinkArm("arm", **prm, gravity=gravity) for prm in (SLOTINE_LI, OTHER_ARM)]
    batch = stacked(arms)
    f = native_kernel(batch, "derivative", 2)
    assert isinstance(f, NativeKernel)
    rng = np.random.default_rng(11)
    for _ in range(20):
        q, qdot, _, _ = random_states(rng, 2)
        tau = rng.normal(0.0, 10.0, (2, 2))
        tau_star = rng.normal(0.0, 3.0, (1, 2))              # one row shared by the batch
        dx = f(0.0, np.hstack([q, qdot]), (tau, tau_star))
        for k, prm in enumerate((SLOTINE_LI, OTHER_ARM)):
            H, C, g, _ = reference_terms(prm, gravity, q[k], qdot[k])
            want = np.linalg.solve(H, tau[k] + tau_star[0] - C @ qdot[k] - g)
            np.testing.assert_array_equal(dx[k, :2], qdot[k])
            np.testing.assert_allclose(dx[k, 2:], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("batch", [1, 5])
@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_the_native_regressor_satisfies_property3(gravity, batch):
    """Y(q, qdot, zeta, zetad) theta = H zetad + C zeta + g (Property 3)."""
    reg = Regressor("Y", gravity=gravity)
    reg.finalize(batch)
    f = native_kernel(reg, "output", batch)
    assert isinstance(f, NativeKernel)
    theta = TwoLinkArm.parameter_vector(**SLOTINE_LI, gravity=gravity)
    rng = np.random.default_rng(12)
    for _ in range(10):
        q, qdot, zeta, zetad = random_states(rng, batch)
        (Y,) = f(0.0, np.zeros((batch, 0)), (q, qdot, zeta, zetad))
        assert Y.shape == (batch, 2, theta.size)
        for k in range(batch):
            H, C, g, _ = reference_terms(SLOTINE_LI, gravity, q[k], qdot[k])
            np.testing.assert_allclose(Y[k] @ theta, H @ zetad[k] + C @ zeta[k] + g,
                                       rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["slotine_li.yaml", "theorem1.yaml", "theorem4.yaml"])
def test_the_two_link_diagrams_give_the_numbers_of_their_runs_without_native_code(
        name, monkeypatch):
    """A batch of three variants (a sweep) runs the arm and its regressor natively and gives
    the numbers of the same batch without native code; a single run keeps the NumPy
    kernels (``_native_in_batches``: one run does not win back llvmlite's import)."""
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    path = os.path.join(ROOT, "diagrams", name)
    values = [{"t_final": 0.2, "K": [[k, 0.0], [0.0, k]]} for k in (20.0, 50.0, 90.0)]

    def batch():
        return compile_batch([load_spec(path, v) for v in values])

    single = fwdstep.load_diagram(path, overrides=values[0])
    assert not any(type(s.block) in (TwoLinkArm, Regressor) and id(s.block) in native
                   for native in [native_methods(single)] for s in single.schedule)
    d = batch()
    native = native_methods(d)
    arms = [s.block for s in d.schedule if type(s.block) in (TwoLinkArm, Regressor)]
    assert arms and all(id(b) in native for b in arms)
    got = fwdstep.simulate(d)
    monkeypatch.setattr(program, "PLUGGED_NATIVE", "fwdstep.no_such_module")
    reference = batch()
    assert native_methods(reference) == {}
    want = fwdstep.simulate(reference)
    for signal in want.names:
        scale = max(1.0, float(np.abs(want[signal]).max()))
        assert np.abs(got[signal] - want[signal]).max() <= 1e-12 * scale, signal
