"""Blocks that call Python libraries run inside compiled runs (``compile_with = "objmode"``,
fwdstep/run/python_blocks.py): the compiled loop calls their NumPy-path methods through numba's
object mode, one variant per call.

Fast tests call the callbacks directly (no compiling): variant v of a stacked block gives what
a block built with variant v's parameters gives, and failures are reported as on the NumPy
path.  Slow tests (``pytest -m slow``) compile: a user block calling scipy (outputs of rank 0,
1 and 2, a state) agrees with the NumPy path, a batch equals one-by-one compiled runs, a
failure inside the compiled batch loop names block, time and variant; and the same for the
pinocchio blocks (panda, ur5), skipped without the ``robots`` extra.
"""
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.run import python_blocks
from fwdstep.core.block import Block, Param
from fwdstep.core.errors import BlockRuntimeError, ConfigError
from fwdstep.core.registry import REGISTRY, register

pytest.importorskip("numba")
scipy_special = pytest.importorskip("scipy.special")
scipy_linalg = pytest.importorskip("scipy.linalg")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(autouse=True)
def object_mode_in_the_loop(monkeypatch):
    """These tests are about the compiled loop calling object-mode blocks: keep it from
    picking the NumPy path (fwdstep.compiled.driver.PICK_NUMPY_FOR_OBJECT_MODE)."""
    from fwdstep.compiled import driver
    monkeypatch.setattr(driver, "PICK_NUMPY_FOR_OBJECT_MODE", False)


class ScipyLeak(Block):
    """Leaky integrator driven through scipy: dx/dt = -k x + expit(u), with a rotation.

    Equation: dx/dt = -k x + expit(u); y = x; R = expm([[0, x_1], [-x_1, 0]]); n = j0(u_1).

    Ports:
        | port | direction | shape  | feedthrough |
        | u    | in        | (2,)   | -           |
        | y    | out       | (2,)   | -           |
        | R    | out       | (2, 2) | -           |
        | n    | out       | ()     | u           |

    Parameters:
        k: leak rate (per second).
        fail_at: the derivative raises from this time on (default 1e9: never).
    """

    params = {"k": Param("float", 1.0, "leak rate"),
              "fail_at": Param("float", 1e9, "raise from this time on")}
    example = {"k": 2.0}
    compile_with = "objmode"

    def setup(self, k, fail_at):
        self.declare_input("u", (2,))
        self.declare_output("y", (2,), feedthrough=())
        self.declare_output("R", (2, 2), feedthrough=())
        self.declare_output("n", (), feedthrough=("u",))
        self.declare_state(2, [0.5, -0.2])
        self.set_param("k", k)
        self.set_param("fail_at", fail_at)

    def output(self, t, x, u):
        R = np.stack([scipy_linalg.expm(np.array([[0.0, a], [-a, 0.0]])) for a in x[:, 0]])
        return x, R, scipy_special.j0(u[0][:, 0])

    def derivative(self, t, x, u):
        if np.any(t >= self.p.fail_at):
            raise RuntimeError("fail_at reached")
        return -self.p.k[:, None] * x + scipy_special.expit(u[0])


DIAGRAM = """
parameters: {k: 2.0, fail_at: 1.0e9}
blocks:
  src: {type: Sine, amplitude: [1.0, 0.5], frequency: [2.0, 3.0]}
  f:   {type: ScipyLeak, k: k, fail_at: fail_at}
  P:   {type: Product, a_shape: [2, 2], b_shape: [2]}
  I:   {type: Integrator, shape: [2]}
connections:
  - src.y -> f.u
  - f.R -> P.a
  - f.y -> P.b
  - P.y -> I.u
simulation: {t_final: 0.2, step: 0.01, solver: rk4}
"""


@pytest.fixture
def leak(tmp_path):
    register(ScipyLeak)
    path = tmp_path / "leak.yaml"
    path.write_text(DIAGRAM)
    try:
        yield str(path)
    finally:
        REGISTRY.pop("ScipyLeak", None)


@pytest.fixture(autouse=True)
def cache(numba_cache):
    return numba_cache


def _batch(path, overrides):
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    return compile_batch([load_spec(path, o) for o in overrides])


def _block(d, name):
    return next(st.block for st in d.schedule if st.block.name == name)


# ---------------------------------------------------------------- fast: the callbacks
def test_each_variant_is_called_as_its_own_single_block(leak):
    """Variant v of a stacked block = the block built with variant v's parameters."""
    ks = (0.5, 2.0, 7.0)
    stacked = _block(_batch(leak, [{"k": k} for k in ks]), "f")
    owner = type("Owner", (), {})()
    handle, entry = python_blocks.register(owner, [stacked], len(ks))
    x = np.array([[0.3, -0.4]])
    u = np.array([[0.2, -0.7]])
    for v, k in enumerate(ks):
        alone = _block(fwdstep.load_diagram(leak, {"k": k}), "f")
        got = python_blocks.derivative(handle, 0, v, 0.1, x, u)
        np.testing.assert_array_equal(got, alone.derivative(0.1, x, (u,)))
        assert got.flags.c_contiguous and got.shape == (1, 2)
        y, R, n = python_blocks.output(handle, 0, v, 0.1, x, u)
        assert (y.shape, R.shape, n.shape) == ((1, 2), (1, 2, 2), (1,))
        np.testing.assert_array_equal(R[0], scipy_linalg.expm([[0, 0.3], [-0.3, 0]]))
        np.testing.assert_array_equal(n, scipy_special.j0([0.2]))
    assert np.ptp([python_blocks.derivative(handle, 0, v, 0.1, x, u)[0, 0]
                   for v in range(3)]) > 1.0          # the variants really differ
    del owner
    assert handle not in python_blocks._programs    # the table entry goes with its program


def test_a_single_run_raises_the_numpy_paths_error_at_once(leak):
    blk = _block(fwdstep.load_diagram(leak, {"fail_at": 0.0}), "f")
    owner = type("Owner", (), {})()
    handle, _ = python_blocks.register(owner, [blk], 1)
    with pytest.raises(BlockRuntimeError) as info:
        python_blocks.derivative(handle, 0, 0, 0.25, np.zeros((1, 2)), np.ones((1, 2)))
    assert str(info.value) == ("block 'f' (ScipyLeak) raised RuntimeError: fail_at reached at "
                               "t = 0.25; inputs: u=[1. 1.]")
    assert isinstance(info.value.__cause__, RuntimeError)


def test_a_batch_records_the_failure_answers_nan_and_raises_it_after_the_call(leak):
    stacked = _block(_batch(leak, [{"fail_at": 9.0}, {"fail_at": 0.0}]), "f")
    owner = type("Owner", (), {})()
    handle, entry = python_blocks.register(owner, [stacked], 2)
    x, u = np.zeros((1, 2)), np.ones((1, 2))
    assert np.isfinite(python_blocks.derivative(handle, 0, 0, 0.5, x, u)).all()
    assert np.isnan(python_blocks.derivative(handle, 0, 1, 0.5, x, u)).all()
    # once a call failed, every later call answers NaN at once (the batch stops)
    assert np.isnan(python_blocks.derivative(handle, 0, 0, 0.5, x, u)).all()
    assert all(np.isnan(y).all() for y in python_blocks.output(handle, 0, 0, 0.5, x, u))
    with pytest.raises(BlockRuntimeError, match=r"^block 'f' \(ScipyLeak\) raised RuntimeError: "
                       r"fail_at reached at t = 0\.5; inputs: u=\[1\. 1\.\] \(variant 1\)$"):
        entry.check()
    entry.check()                                      # reported once


def test_an_interruption_inside_a_batch_call_is_raised_as_it_came(leak):
    stacked = _block(_batch(leak, [{"k": 1.0}, {"k": 2.0}]), "f")
    owner = type("Owner", (), {})()
    handle, entry = python_blocks.register(owner, [stacked], 2)

    def interrupted(t, x, u):
        raise KeyboardInterrupt
    entry.blocks[0][1].derivative = interrupted
    assert np.isnan(python_blocks.derivative(handle, 0, 1, 0.0, np.zeros((1, 2)),
                                             np.ones((1, 2)))).all()
    with pytest.raises(KeyboardInterrupt):
        entry.check()


def test_a_signal_inside_a_c_call_stays_a_signal(leak):
    """A signal handler that raises while C code runs (a lock's acquire) comes out as
    SystemError caused by the KeyboardInterrupt: the run must end 'interrupted'."""
    blk = _block(fwdstep.load_diagram(leak), "f")

    def signalled(t, x, u):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("returned a result with an exception set") from exc
    blk.derivative = signalled
    owner = type("Owner", (), {})()
    handle, _ = python_blocks.register(owner, [blk], 1)
    with pytest.raises(KeyboardInterrupt):
        python_blocks.derivative(handle, 0, 0, 0.0, np.zeros((1, 2)), np.ones((1, 2)))


def test_a_wrong_output_shape_names_block_port_and_shapes(leak):
    blk = _block(fwdstep.load_diagram(leak), "f")
    blk.output = lambda t, x, u: (x, np.zeros((1, 3, 2)), np.zeros(1))
    owner = type("Owner", (), {})()
    handle, _ = python_blocks.register(owner, [blk], 1)
    with pytest.raises(BlockRuntimeError) as info:
        python_blocks.output(handle, 0, 0, 0.0, np.zeros((1, 2)), np.ones((1, 2)))
    assert str(info.value) == ("block 'f' (ScipyLeak) output 'R' has shape (3, 2) at t = 0, "
                               "but declares (2, 2)")


def test_compile_with_accepts_numba_objmode_or_traced_only(leak):
    from fwdstep.compiled import backend_numba
    d = fwdstep.load_diagram(leak)
    blk = _block(d, "f")
    assert backend_numba.refusal(blk) is None
    type(blk).compile_with = "python"
    try:
        with pytest.raises(ConfigError, match=r"^block 'f' \(ScipyLeak\): compile_with must be "
                                              r"'numba', 'objmode' or 'traced', not "
                                              r"'python'$"):
            backend_numba.refusal(blk)
    finally:
        type(blk).compile_with = "objmode"


def test_the_robot_blocks_are_traced_and_fall_back_to_object_mode():
    """URDFArm and URDFRegressor (blocks/urdf.py): their kernels are traced into the scalar
    stage; the array code (a stage that does not trace) calls their methods in object mode."""
    pytest.importorskip("pinocchio")
    from fwdstep.compiled import backend_numba
    d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", "robots", "ur5_theorem1.yaml"))
    for name in ("arm", "Y"):
        blk = _block(d, name)
        assert blk.compile_with == "traced" and backend_numba.refusal(blk) is None
        assert backend_numba._in_python(blk) and backend_numba._traced_only(blk)


# ---------------------------------------------------------------- slow: compiled runs
def _assert_close(got, ref, columns=None):
    np.testing.assert_array_equal(got.t, ref.t)
    for name in ref.names:
        want = ref[name] if columns is None else ref[name]
        have = got[name] if columns is None else got[name][:, columns]
        scale = max(1.0, float(np.nanmax(np.abs(want))))
        np.testing.assert_allclose(have, want, rtol=0, atol=1e-12 * scale, err_msg=name)


@pytest.mark.slow
def test_a_scipy_block_runs_compiled_single_and_batched(leak):
    """Ranks 0, 1, 2 and a state through object mode, feeding jitted blocks: the NumPy
    path's numbers; a batch equals one-by-one compiled runs."""
    ref = fwdstep.simulate(fwdstep.load_diagram(leak), backend="numpy")
    got = fwdstep.simulate(fwdstep.load_diagram(leak), backend="compiled")
    assert float(np.abs(ref["f.R"][:, 0, 1]).max()) > 0.1     # the signals are not trivial
    _assert_close(got, ref)
    ks = (0.5, 2.0, 7.0)
    batch = fwdstep.simulate(_batch(leak, [{"k": k} for k in ks]), backend="compiled")
    for b, k in enumerate(ks):
        one = fwdstep.simulate(fwdstep.load_diagram(leak, {"k": k}), backend="compiled")
        _assert_close(batch, one, b)


@pytest.mark.slow
def test_a_failure_inside_the_compiled_batch_names_block_time_and_variant(leak):
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(_batch(leak, [{"fail_at": 9.0}, {"fail_at": 0.05}]),
                         backend="compiled")
    text = str(info.value)
    assert text.startswith("block 'f' (ScipyLeak) raised RuntimeError: fail_at reached at "
                           "t = 0.05; inputs: u=") and text.endswith("(variant 1)"), text
    assert info.value.result is not None and info.value.result.status == "error"
    with pytest.raises(BlockRuntimeError, match=r"^block 'f' \(ScipyLeak\) raised "
                                                r"RuntimeError: fail_at reached at t = 0\.05;"):
        fwdstep.simulate(fwdstep.load_diagram(leak, {"fail_at": 0.05}), backend="compiled")


@pytest.mark.slow
def test_the_rows_before_an_object_mode_failure_are_kept(leak):
    """The failing chunk's rows (t = 0 .. 0.05 here, all in one chunk) are in the result, as
    on the NumPy path: the loop could not return its row count when the block raised."""
    results = {}
    for backend in ("numpy", "compiled"):
        with pytest.raises(BlockRuntimeError) as info:
            fwdstep.simulate(fwdstep.load_diagram(leak, {"fail_at": 0.05}), backend=backend)
        results[backend] = info.value.result
    ref, got = results["numpy"], results["compiled"]
    assert len(ref.t) >= 5 and np.array_equal(got.t, ref.t), (got.t, ref.t)
    _assert_close(got, ref)


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_a_robot_batch_equals_one_by_one_compiled_runs(robot):
    """The pinocchio blocks in a compiled batch (variants in sequence): each variant of
    a batch gives its single compiled run (which test_compiled_diagrams compares with the
    NumPy path), and the first variant the NumPy path's."""
    pytest.importorskip("pinocchio")
    from fwdstep.structure.compiler import compile_batch, compile_spec
    from fwdstep.structure.spec import load_spec
    path = os.path.join(ROOT, "diagrams", "robots", f"{robot}_theorem1.yaml")
    overrides = [{"alpha": 3.0}, {"alpha": 4.0, "Gamma": 2.0}, {"alpha": 6.0}]

    def spec(o):
        s = load_spec(path, o)
        s.simulation.t_final = 30 * s.simulation.step
        return s
    batch = fwdstep.simulate(compile_batch([spec(o) for o in overrides]), backend="compiled")
    for b, o in enumerate(overrides):
        one = fwdstep.simulate(compile_spec(spec(o)), backend="compiled")
        _assert_close(batch, one, b)
    _assert_close(fwdstep.simulate(compile_spec(spec(overrides[0])), backend="numpy"),
                  fwdstep.simulate(compile_spec(spec(overrides[0])), backend="compiled"))
