"""The NumPy path's native block kernels (fwdstep/compiled/native_block.py, plugged into
fwdstep/run/program.py): the robot blocks' kernels compiled to native code equal pinocchio
called directly (aba, the joint-torque regressor, frame kinematics) at random states, every
shipped robot diagram gives the numbers of its ``implementation: pinocchio`` run, and without
llvmlite, or for a kernel the tracer refuses, the block's own method runs."""
from __future__ import annotations

import glob
import os
import sys

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio", reason="needs pinocchio (fwdstep[robots])")
pytest.importorskip("llvmlite", reason="native kernels need llvmlite (fwdstep[fast])")

import fwdstep                                                     # noqa: E402
from fwdstep.blocks.urdf import URDFArm, URDFFrame, URDFRegressor  # noqa: E402
from fwdstep.compiled.native_block import NativeKernel, native_kernel  # noqa: E402
from fwdstep.core.block import Block                               # noqa: E402
from fwdstep.run.program import native_methods                     # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ROBOT_DIAGRAMS = sorted(glob.glob(os.path.join(ROOT, "diagrams", "robots", "*.yaml")))


def _close(got, want, tol=1e-12):
    got, want = np.asarray(got), np.asarray(want)
    scale = max(1.0, float(np.abs(want).max()))
    assert np.abs(got - want).max() <= tol * scale, np.abs(got - want).max() / scale


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_the_native_plant_equals_pinocchio_aba_with_friction(robot):
    arm = URDFArm("arm", robot=robot, damping=0.3, coulomb=0.2, coulomb_velocity=0.05)
    f = native_kernel(arm, "derivative", 3)
    assert isinstance(f, NativeKernel)
    n = arm._n
    rng = np.random.default_rng(7)
    model, data = arm.model, arm.model.createData()
    for _ in range(4):
        x = rng.uniform(-2.0, 2.0, (3, 2 * n))
        tau = rng.standard_normal((3, n)) * 5.0
        tau_star = rng.standard_normal((1, n))              # one row shared by the batch
        dx = f(0.0, x, (tau, tau_star))
        assert dx.shape == (3, 2 * n)
        for b in range(3):
            q, v = x[b, :n], x[b, n:]
            torque = tau[b] + tau_star[0] - 0.3 * v - 0.2 * np.tanh(v / 0.05)
            _close(dx[b, :n], v)
            _close(dx[b, n:], pin.aba(model, data, q, v, torque))


def test_a_batch_of_payloads_reads_each_variants_parameters():
    """Parameters that differ between variants (a payload sweep) are rows of W: each row of
    the native batch equals pinocchio's aba on that variant's own model."""
    from fwdstep.structure.compiler import stack_blocks
    masses = (0.0, 1.0, 2.5)
    blocks = [[URDFArm("arm", robot="panda", payload=m, payload_frame="panda_hand",
                       implementation="pinocchio")] for m in masses]
    stacked = stack_blocks(blocks)[0]
    stacked.implementation = "auto"
    f = native_kernel(stacked, "derivative", 3)
    rng = np.random.default_rng(5)
    x, tau = rng.standard_normal((3, 14)), rng.standard_normal((3, 7))
    batch = f(0.0, x, (tau, np.zeros((1, 7))))
    for b, one in enumerate(blocks):
        _close(batch[b], one[0].derivative(0.0, x[b:b + 1], (tau[b:b + 1], np.zeros((1, 7))))[0])
    assert np.abs(batch[0] - batch[2]).max() > 1e-6        # the payloads differ


@pytest.mark.parametrize("robot,parameters", [("panda", "base"), ("ur5", "full")])
def test_the_native_regressor_equals_pinocchios_polarized_regressor(robot, parameters):
    Y = URDFRegressor("Y", robot=robot, parameters=parameters)
    f = native_kernel(Y, "output", 2)
    n, cols = Y._n, Y._columns
    model, model0 = Y.model, Y.model0
    data, data0 = model.createData(), model0.createData()
    rng = np.random.default_rng(11)
    for _ in range(3):
        q, qdot, zeta, zetad = rng.uniform(-2.0, 2.0, (4, 2, n))
        (got,) = f(0.0, None, (q, qdot, zeta, zetad))
        for b in range(2):
            full = (pin.computeJointTorqueRegressor(model, data, q[b], (qdot[b] + zeta[b]) / 2,
                                                    zetad[b])
                    - pin.computeJointTorqueRegressor(model0, data0, q[b],
                                                      (qdot[b] - zeta[b]) / 2, np.zeros(n)))
            _close(got[b], full if cols is None else full[:, cols])


def test_the_native_frame_equals_pinocchios_frame_kinematics():
    block = URDFFrame("ee", robot="ur5", frame="tool0")
    f = native_kernel(block, "output", 1)
    model = block.model
    data = model.createData()
    fid = model.getFrameId("tool0")
    world = pin.LOCAL_WORLD_ALIGNED
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, qdot = rng.uniform(-2.0, 2.0, (2, 1, 6))
        position, rotation, J, bias = f(0.0, None, (q, qdot))
        pin.forwardKinematics(model, data, q[0], qdot[0], np.zeros(6))
        placement = pin.updateFramePlacement(model, data, fid)
        pin.computeJointJacobians(model, data, q[0])
        acc = pin.getFrameClassicalAcceleration(model, data, fid, world)
        _close(position[0], placement.translation)
        _close(rotation[0], placement.rotation)
        _close(J[0], pin.getFrameJacobian(model, data, fid, world))
        _close(bias[0], np.concatenate([acc.linear, acc.angular]))


def _pinocchio_overrides(d) -> dict:
    return {f"{s.block.name}.implementation": "pinocchio" for s in d.schedule
            if s.block.type_name.startswith("URDF")}


@pytest.mark.parametrize("path", ROBOT_DIAGRAMS, ids=os.path.basename)
def test_every_robot_diagram_gives_the_pinocchio_runs_numbers(path):
    short = {"t_final": 0.03}
    d = fwdstep.load_diagram(path, overrides=short)
    native = native_methods(d)
    urdf = [s.block for s in d.schedule if s.block.type_name.startswith("URDF")]
    assert urdf and all(id(b) in native for b in urdf)       # every robot block natively
    reference = fwdstep.load_diagram(path, overrides={**short, **_pinocchio_overrides(d)})
    assert native_methods(reference) == {}
    got, want = fwdstep.simulate(d), fwdstep.simulate(reference)
    assert got.names == want.names
    for name in want.names:
        _close(got[name], want[name])


def test_without_llvmlite_the_blocks_run_pinocchio(monkeypatch):
    path = os.path.join(ROOT, "diagrams", "robots", "ur5_slotine_li.yaml")
    short = {"t_final": 0.02}
    d = fwdstep.load_diagram(path, overrides=short)
    reference = fwdstep.simulate(fwdstep.load_diagram(
        path, overrides={**short, **_pinocchio_overrides(d)}))
    for name in ("llvmlite", "llvmlite.binding", "numba"):
        monkeypatch.setitem(sys.modules, name, None)             # import -> ImportError
    package = sys.modules["fwdstep.compiled"]
    for name in ("native_block", "llvm_ir"):             # imported afresh: they fail
        monkeypatch.delitem(sys.modules, f"fwdstep.compiled.{name}", raising=False)
        monkeypatch.delattr(package, name, raising=False)
    assert native_methods(d) == {}
    got = fwdstep.simulate(d)
    for name in reference.names:
        np.testing.assert_array_equal(got[name], reference[name])


def _solve_kernel(t, x, u):
    return (np.linalg.solve(np.eye(2), u[:, :, None])[:, :, 0],)


class _Refused(Block):
    """A block whose kernel the tracer refuses (np.linalg)."""

    native_kernels = ("output",)

    def setup(self):
        self.declare_input("u", (2,))
        self.declare_output("y", (2,))
        self.set_kernels(output=_solve_kernel, params=())


def test_a_kernel_the_tracer_refuses_keeps_the_method():
    assert native_kernel(_Refused("r"), "output", 1) is None


def test_the_object_code_is_cached_on_disk_and_checked(tmp_path, monkeypatch, capsys):
    """A second process (here: the memo emptied) loads the machine code from the private
    cache instead of compiling; an entry that does not match its hash is compiled afresh,
    with one warning line."""
    import glob as globbing

    from fwdstep.compiled import llvm_ir, native_block
    monkeypatch.setenv("FWDSTEP_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(native_block, "_compiled", {})
    Y = URDFRegressor("Y", robot="ur5")
    rng = np.random.default_rng(2)
    u = tuple(rng.uniform(-1.0, 1.0, (4, 1, 6)))
    want = Y.output(0.0, None, u)[0]                 # pinocchio
    _close(native_kernel(Y, "output", 1)(0.0, None, u)[0], want)
    (obj,) = globbing.glob(str(tmp_path / "native" / "*.o"))

    def no_compile(*args, **kwargs):
        raise AssertionError("compiled although cached")

    monkeypatch.setattr(native_block, "_compiled", {})
    with monkeypatch.context() as m:
        m.setattr(llvm_ir.llvm, "create_pass_builder", no_compile)
        _close(native_kernel(Y, "output", 1)(0.0, None, u)[0], want)
    with open(obj, "r+b") as fh:                       # a changed entry
        fh.seek(100)
        fh.write(b"\xff\xff\xff\xff")
    monkeypatch.setattr(native_block, "_compiled", {})
    capsys.readouterr()
    _close(native_kernel(Y, "output", 1)(0.0, None, u)[0], want)
    assert "does not match its recorded hash" in capsys.readouterr().err


def test_an_llvm_failure_warns_once_and_keeps_the_method(monkeypatch, capsys):
    from fwdstep.compiled import llvm_ir, native_block

    def broken(*args, **kwargs):
        raise RuntimeError("LLVM ERROR: out of registers\nmore")

    monkeypatch.setattr(native_block, "_compiled", {})
    monkeypatch.setattr(llvm_ir, "engine_of", broken)
    monkeypatch.setattr(native_block.compiled_cache, "native_object", lambda key: None)
    assert native_kernel(URDFRegressor("Y", robot="ur5"), "output", 1) is None
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fwdstep: warning: block 'Y': its native output kernel did not compile "
                   "(LLVM ERROR: out of registers); running its method"]


def test_a_refused_cache_folder_is_said_once_and_the_kernel_still_runs(tmp_path, monkeypatch,
                                                                        capsys):
    """A file where the cache folder should be: the NumPy path's native kernels compile in
    memory and the user is told why once per process (the numba path says it too), not
    never (every later process would silently pay the compile again)."""
    from fwdstep.compiled import compiled_cache, native_block
    where = tmp_path / "cache"
    where.write_text("not a directory")
    monkeypatch.setenv("FWDSTEP_CACHE_DIR", str(where))
    monkeypatch.setattr(compiled_cache, "_REFUSALS_TOLD", set(), raising=False)
    Y = URDFRegressor("Y", robot="ur5")
    u = tuple(np.random.default_rng(3).uniform(-1.0, 1.0, (4, 1, 6)))
    want = Y.output(0.0, None, u)[0]                 # pinocchio
    capsys.readouterr()
    for _ in range(2):                               # a second process's first call, twice
        monkeypatch.setattr(native_block, "_compiled", {})
        _close(native_kernel(Y, "output", 1)(0.0, None, u)[0], want)
    err = capsys.readouterr().err.splitlines()
    assert err == [f"fwdstep: warning: compiled-code cache refused: {where} exists and is not "
                   "a directory; native kernels compiled in memory"]
    assert where.read_text() == "not a directory"
