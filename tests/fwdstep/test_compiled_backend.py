"""The optional compiled backend (numba, fwdstep/compiled/backend_numba.py) gives the NumPy path's numbers.

Skipped when numba is not installed.  The generated code is compiled into pytest's cache
directory (``.pytest_cache``), so only the first run pays numba's compile (tens of seconds
on a slow machine); later runs load it from disk.  The diagram uses most kernels: sources,
the arm and its regressor, sums, a matrix gain, a product, the adaptation law, and fused
linear blocks (reference dynamics, transfer functions, a column-wise state-space filter).
"""
import os
import sys

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError, DivergenceError

numba = pytest.importorskip("numba")

LOOP = """
parameters: {ell: 2, alpha: 4, gamma: [2, 1, 1, 0.5]}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [[1.0, 2.0], [1.5, 0.5]],
          phase: 0.2, offset: [0.1, 0], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: [0.1, -0.1], gravity: 9.81}
  ref:   {type: ReferenceDynamics, variant: eq16, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor, gravity: 9.81}
  W:     {type: StateSpace, A: [[-5, 0], [0, -5]], B: [[5, 0], [0, 5]], C: [[1, 0], [0, 1]],
          columns: 7}
  Ks:    {type: Gain, gain: [[30, 5], [5, 20]]}
  lag:   {type: TransferFunction, num: [1, 10], den: [1, 10], shape: [2]}
  Yth:   {type: Product, a_shape: [2, 7], b_shape: [7]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 7], gamma: 1, theta0: 0.5}
  poly:  {type: Polynomial, coefficients: [0.5, -1, 0.25], derivatives: 1}
  ie:    {type: Integrator}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - qd.y_d1 -> ref.qdot_d
  - qd.y_d2 -> ref.qddot_d
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, W.u
  - W.y -> adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Ks.y -> lag.u
  - Yth.y -> tau.u1
  - lag.y -> tau.u2
  - tau.y -> arm.tau
  - poly.y_d1 -> ie.u
simulation: {t_final: 0.5, step: 0.001, solver: rk4, log_every: 3}
"""


@pytest.fixture(autouse=True)
def cache(numba_cache):
    return numba_cache


@pytest.fixture
def loop(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text(LOOP)
    return str(path)


@pytest.mark.slow          # the first run compiles (minutes); later runs load from the cache
def test_compiled_equals_numpy_path(loop):
    d = fwdstep.load_diagram(loop)
    ref = fwdstep.simulate(d)
    got = fwdstep.simulate(d, backend="compiled")
    assert set(got.names) == set(ref.names) and len(ref.names) > 15
    _agree(got, ref)


def _agree(got, ref):
    """The compiled result equals the NumPy path's: same times, every signal to 1e-12 of
    its scale."""
    np.testing.assert_array_equal(got.t, ref.t)
    for name in ref.names:
        scale = max(1.0, float(np.max(np.abs(ref[name]))))
        np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=1e-12 * scale,
                                   err_msg=name)


@pytest.mark.slow
def test_compiled_divergence_keeps_partial_results(loop, tmp_path):
    text = LOOP.replace("gain: [[30, 5], [5, 20]]", "gain: [[-20, 0], [0, -20]]")
    text = text.replace("log_every: 3}", "log_every: 3, bound: 50}")
    path = tmp_path / "unstable.yaml"
    path.write_text(text)
    d = fwdstep.load_diagram(str(path))
    with pytest.raises(DivergenceError) as ref_info:
        fwdstep.simulate(d)
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(d, backend="compiled")
    # the same step, block and state; the value itself has grown past the bound by then,
    # where round-off differences are amplified
    head = str(ref_info.value).split(" = ")[:2]
    assert str(info.value).split(" = ")[:2] == head and info.value.block == "arm"
    ref, got = ref_info.value.result, info.value.result
    assert got.status == "diverged" and len(got.t) == len(ref.t) > 20
    half = len(ref.t) // 2
    np.testing.assert_allclose(got["e.y"][:half], ref["e.y"][:half], rtol=0, atol=1e-12)


def test_a_block_without_kernel_is_refused(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\n  f: {type: FragileKernelless}\n"
                    "connections:\n  - c.y -> f.u\n")
    from fwdstep.core.block import Block
    from fwdstep.core.registry import REGISTRY, register

    @register
    class FragileKernelless(Block):
        """Test block without a compiled kernel."""
        params: dict = {}

        def setup(self):
            self.declare_input("u", ())
            self.declare_output("y", ())

        def output(self, t, x, u):
            return (u[0],)

    try:
        d = fwdstep.load_diagram(str(path))
        with pytest.raises(ConfigError, match=r"backend 'compiled' cannot run block 'f' "
                                              r"\(FragileKernelless\): it declares no kernels"):
            fwdstep.simulate(d, backend="compiled")
        assert fwdstep.simulate(d).status == "ok"
    finally:
        REGISTRY.pop("FragileKernelless", None)


@pytest.mark.slow
def test_generated_module_is_cached_by_structure(loop):
    """Parameters are arguments: another gain reuses the same generated module."""
    from fwdstep.compiled import backend_numba
    from fwdstep.compiled.llvm_stage import stage_ir
    loaded_before = {getattr(m, "__file__", None) for m in list(sys.modules.values())}
    a = backend_numba.build_program(fwdstep.load_diagram(loop, {"alpha": 4}), 10)
    b = backend_numba.build_program(fwdstep.load_diagram(loop, {"alpha": 7}), 10)
    # the loop is one cached module; the stage's code is the same text (alpha is in W)
    assert a.module.loop is b.module.loop and stage_ir(a.module.st) == stage_ir(b.module.st)
    assert not np.array_equal(a.args[0], b.args[0])
    # kept on disk: in this test's cache folder, unless an earlier test of the process already
    # loaded the same module from another folder (generated modules are cached in-process)
    assert os.path.isfile(a.module.__file__)
    if a.module.__file__ not in loaded_before:
        assert os.path.dirname(a.module.__file__) == os.environ["FWDSTEP_CACHE_DIR"]
    # the array code (sizes at run time): one generated module for both
    da, db = (fwdstep.load_diagram(loop, {"alpha": v}) for v in (4, 7))
    da.sizes_at_run_time = db.sizes_at_run_time = True
    a, b = backend_numba.build_program(da, 10), backend_numba.build_program(db, 10)
    assert a.module is b.module


def test_a_block_may_declare_why_it_cannot_run_compiled(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\n  f: {type: PinocchioLike}\n"
                    "connections:\n  - c.y -> f.u\n")
    from fwdstep.core.block import Block
    from fwdstep.core.registry import REGISTRY, register

    @register
    class PinocchioLike(Block):
        """Test block calling a library numba cannot compile."""
        params: dict = {}
        cannot_compile = "it calls pinocchio, which numba cannot compile"

        def setup(self):
            self.declare_input("u", ())
            self.declare_output("y", ())

        def output(self, t, x, u):
            return (u[0],)

    try:
        d = fwdstep.load_diagram(str(path))
        with pytest.raises(ConfigError, match=r"cannot run block 'f' \(PinocchioLike\): it "
                                              r"calls pinocchio, which numba cannot compile; "
                                              r"use --backend numpy"):
            fwdstep.simulate(d, backend="compiled")
    finally:
        REGISTRY.pop("PinocchioLike", None)


@pytest.mark.slow
def test_batched_compiled_run_equals_one_by_one_runs(loop):
    """A batch runs its variants in parallel (prange), each exactly as a single run."""
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    alphas = (3.0, 4.0, 6.0)
    batch = fwdstep.simulate(compile_batch([load_spec(loop, {"alpha": a}) for a in alphas]),
                             backend="compiled")
    for b, a in enumerate(alphas):
        one = fwdstep.simulate(fwdstep.load_diagram(loop, {"alpha": a}), backend="compiled")
        for name in one.names:
            np.testing.assert_allclose(batch[name][:, b], one[name], rtol=0, atol=1e-12,
                                       err_msg=name)


def test_a_sweep_over_ell_generates_one_program(monkeypatch):
    """Sizes are run-time values: ell = 1..10 of Theorem 1 is one generated module (one
    compile), not ten, when the diagram asks for it (a sweep whose batches differ in
    structure does: see the next test); a single run gets scalar code for its sizes."""
    import hashlib
    from fwdstep.compiled import backend_numba
    seen = []
    monkeypatch.setattr(backend_numba.compiled_cache, "load",
                        lambda source: seen.append(hashlib.sha256(source.encode()).digest()))
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    for ell in range(1, 11):
        d = fwdstep.load_diagram(os.path.join(root, "diagrams", "theorem1.yaml"), {"ell": ell})
        d.sizes_at_run_time = True
        backend_numba.build_program(d, 5)
    assert len(seen) == 10 and len(set(seen)) == 1


def test_a_compiled_sweep_over_sizes_asks_for_run_time_sizes(monkeypatch):
    """A compiled sweep whose batches differ in structure (ell = 1, 2, 3) runs them all with
    the one program of run-time sizes; a sweep over numbers only (one structure) keeps the
    scalar code.  (The runs here are NumPy-path runs: only the request is checked.)"""
    from fwdstep.sweeps import sweep as sw
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    path = os.path.join(root, "diagrams", "theorem1.yaml")
    seen = []
    real = sw.simulate

    def spy(d, **kw):
        seen.append((d.n_states, d.sizes_at_run_time))
        return real(d, backend="numpy", **kw)

    monkeypatch.setattr(sw, "simulate", spy)
    sw.run_sweep(path, grid={"ell": [1, 2, 3]}, overrides={"t_final": 0.05},
                 backend="compiled")
    assert len({n for n, _ in seen}) == 3 and all(flag for _, flag in seen)
    seen.clear()
    sw.run_sweep(path, grid={"alpha": [3.0, 4.0]}, overrides={"t_final": 0.05},
                 backend="compiled")
    assert seen and not any(flag for _, flag in seen)


def test_a_batch_compiles_the_kernels_of_one_variant_and_restores_the_batch_ones():
    """run_one runs each variant alone: a block that picks vectorised kernels for a batch
    (TwoLinkArm, Regressor: finalize(batch)) is compiled with its one-variant kernels, which
    numba turns into scalar code (the vectorised ones allocate an array per operation); the
    NumPy path of the same diagram keeps its batch kernels.  No compiling here."""
    from fwdstep.compiled import backend_numba
    from fwdstep.blocks import robot
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    path = os.path.join(os.path.dirname(__file__), "..", "..", "diagrams", "slotine_li.yaml")
    d = compile_batch([load_spec(path, {"Lambda": lam}) for lam in (2.0, 5.0, 8.0)])
    arm = next(st.block for st in d.schedule if st.block.name == "arm")
    Y = next(st.block for st in d.schedule if st.block.name == "Y")
    assert arm.kernels.derivative is robot.two_link_derivative_batch
    assert Y.kernels.output is robot.regressor_output_batch
    with backend_numba._per_variant_kernels(d):
        assert arm.kernels.derivative is robot.two_link_derivative
        assert Y.kernels.output is robot.regressor_output
    assert arm.kernels.derivative is robot.two_link_derivative_batch
    assert Y.kernels.output is robot.regressor_output_batch


NONLINEAR = """
parameters: {Fc: [0.5, 0.3]}
blocks:
  pulse: {type: Pulse, high: [1.0, 2.0], low: -0.5, period: 0.2, width: 0.05, delay: 0.1}
  step:  {type: Step, after: [1.0, 2.0], before: 0.5, time: [0.1, 0.2]}
  arm:   {type: TwoLinkArm, q0: [0.1, -0.2]}
  fr:    {type: Friction, n: 2, coulomb: Fc, viscous: 0.2, velocity_scale: 0.0}
  sat:   {type: Saturation, lower: [-1.0, -2.0], upper: [1.0, 0.5]}
  dz:    {type: DeadZone, lower: -0.5, upper: [0.5, 1.0]}
  sum:   {type: Sum, signs: "+++-"}
  K:     {type: Gain, gain: 5}
connections:
  - pulse.y -> sum.u1
  - step.y -> sum.u2
  - fr.tau_f -> sum.u3
  - arm.qdot -> fr.qdot
  - arm.q -> K.u
  - K.y -> dz.u
  - dz.y -> sum.u4
  - sum.y -> sat.u
  - sat.y -> arm.tau
simulation: {t_final: 1, step: 0.001, solver: rk4}
log: [sat.y, arm.q, fr.tau_f, pulse.y, step.y]
"""


@pytest.mark.slow
def test_switching_blocks_run_as_scalar_stages_with_the_numpy_paths_numbers(tmp_path):
    """Pulse (floor, and of comparisons), Step, Friction (sign), Saturation and DeadZone
    (selections) trace to scalar code, and the run gives the NumPy path's numbers."""
    from fwdstep.compiled import backend_numba
    path = tmp_path / "switching.yaml"
    path.write_text(NONLINEAR)
    d = fwdstep.load_diagram(str(path))
    assert type(backend_numba.build_program(d, 3).module).__name__ == "_ScalarModule"
    ref = fwdstep.simulate(d)
    got = fwdstep.simulate(d, backend="compiled")
    assert float(np.max(np.abs(np.diff(ref["sat.y"], axis=0)))) > 0.5     # it switches
    _agree(got, ref)


@pytest.mark.slow
def test_an_llvm_fault_warns_once_and_runs_the_array_code(loop, monkeypatch, capsys):
    from fwdstep.compiled import backend_numba
    from fwdstep.compiled import llvm_stage

    def broken(st, before=None):
        raise RuntimeError("LLVM ERROR: no target")

    monkeypatch.setattr(llvm_stage, "compile_stage", broken)
    d = fwdstep.load_diagram(loop)
    got = fwdstep.simulate(d, backend="compiled")
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fwdstep: warning: scalar stage not compiled (RuntimeError: LLVM ERROR: no "
                   "target); running the array code"]
    assert type(backend_numba.build_program(d, 3).module).__name__ != "_ScalarModule"
    _agree(got, fwdstep.simulate(d))
