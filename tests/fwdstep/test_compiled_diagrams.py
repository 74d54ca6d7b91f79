"""Every shipped diagram runs on both paths with equal results (issue 10): the NumPy path and
the compiled backend (numba), over a short horizon (``STEPS`` solver steps).

``diagrams/*.yaml`` and ``diagrams/robots/*.yaml`` are covered.  The compiled backend refuses
exactly the diagrams of ``REFUSED`` (block type -> why), in one line naming the block; the
fast test checks that list against every shipped diagram (a new refusal, or a diagram that
became compilable, fails it), without compiling anything.

``test_shipped_diagram_on_both_paths`` compiles each diagram's structure and compares every
logged signal to 1e-12 of its scale: in the default suite for every diagram that traces to a
scalar stage (about 30 s in all on a cold cache), with ``pytest -m slow`` for the few that run
the array code (``ARRAY_CODE``: tens of seconds each).
"""
import glob
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.structure.compiler import compile_spec
from fwdstep.core.errors import ConfigError
from fwdstep.core.solvers import IVP_METHODS
from fwdstep.structure.spec import load_spec

pytest.importorskip("numba")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SHIPPED = sorted(glob.glob(os.path.join(ROOT, "diagrams", "*.yaml"))
                 + glob.glob(os.path.join(ROOT, "diagrams", "robots", "*.yaml")))
STEPS = 40
#: diagrams the scalar stage cannot trace (complex numbers in the n-link kernels, integer
#: hashing in WhiteNoise, Theorem 6's 900-state filter bank on the robots): the compiled
#: backend runs them with the array code, which jits every kernel (minutes on a cold cache),
#: so they stay in the slow tier
ARRAY_CODE = ("computed_torque_nlink", "pd_gravity_nlink", "theorem3_measurement_noise",
              "robots/panda_theorem6", "robots/ur5_theorem6")


def _tier(path):
    """The quick tier (default suite) for every diagram that traces; the rest is slow."""
    slow = any(part in _name(path) for part in ARRAY_CODE)
    return pytest.param(path, marks=pytest.mark.slow, id=_name(path)) if slow else \
        pytest.param(path, id=_name(path))

#: block types the compiled backend refuses, and why (the diagrams holding one are refused)
REFUSED = {
    # (URDFArm and URDFRegressor, which call pinocchio, run compiled in numba's object mode:
    # compile_with = "objmode", tests/fwdstep/test_python_blocks.py; so does a linear block
    # too large to fuse, e.g. Theorem 6's filter bank on the robots)
}


def _name(path):
    return os.path.relpath(path, os.path.join(ROOT, "diagrams"))


def _short(path):
    try:
        spec = load_spec(path)
    except ConfigError as exc:
        if "install fwdstep[" in str(exc):
            pytest.skip(str(exc))
        raise
    spec.simulation.t_final = STEPS * spec.simulation.step
    return spec


def _refused_types(d):
    return sorted({st.block.type_name for st in d.schedule if st.block.type_name in REFUSED})


@pytest.fixture(autouse=True)
def cache(numba_cache):
    return numba_cache


@pytest.mark.parametrize("path", SHIPPED, ids=_name)
def test_compiled_backend_refuses_exactly_the_listed_blocks(path):
    """No compiling: the refusal (or its absence) is decided before any code is generated."""
    from fwdstep.compiled import backend_numba
    spec = _short(path)
    if spec.simulation.solver in IVP_METHODS:
        pytest.skip("scipy solve_ivp solver: NumPy path only")
    d = compile_spec(spec)
    refused = _refused_types(d)
    if not refused:
        backend_numba.check_compilable(d)          # raises if any block is refused
        return
    with pytest.raises(ConfigError) as info:
        fwdstep.simulate(d, backend="compiled")
    text = str(info.value)
    assert "\n" not in text and "backend 'compiled'" in text, text
    blamed = [t for t in refused if REFUSED[t] in text]
    assert blamed, f"{_name(path)}: {text}"
    names = [st.block.name for st in d.schedule if st.block.type_name in blamed]
    assert any(f"'{n}'" in text for n in names), text


@pytest.mark.parametrize("path", [_tier(p) for p in SHIPPED])
def test_shipped_diagram_on_both_paths(path):
    spec = _short(path)
    if spec.simulation.solver in IVP_METHODS:
        pytest.skip("scipy solve_ivp solver: NumPy path only")
    d = compile_spec(spec)
    if _refused_types(d):
        pytest.skip(f"refused: {', '.join(_refused_types(d))} (see the fast test)")
    ref = fwdstep.simulate(d, backend="numpy")
    got = fwdstep.simulate(d, backend="compiled")
    np.testing.assert_array_equal(got.t, ref.t)
    assert sorted(got.names) == sorted(ref.names)
    for name in ref.names:
        scale = max(1.0, float(np.nanmax(np.abs(ref[name])))) if np.size(ref[name]) else 1.0
        np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=1e-12 * scale,
                                   err_msg=name)


#: jumps off the step grid (h = 1 ms): a Step at T, pulse edges, noise held over 0.7 ms, into
#: a saturated second-order loop; the steps they fall in are split (fwdstep.run.events)
JUMPS = """
parameters: {T: 0.0123, A: 1.0, seed: 1}
blocks:
  src:   {type: Step, after: A, time: T}
  i:     {type: Integrator}
  pulse: {type: Pulse, high: [2.0, -1.0], period: 0.0113, width: 0.0041, delay: 0.0017}
  w:     {type: WhiteNoise, n: 2, psd: 1.0e-2, sample_time: 0.0007, seed: seed}
  e:     {type: Sum, signs: "++-", shape: [2]}
  sat:   {type: Saturation, lower: -0.5, upper: 0.5, shape: [2]}
  plant: {type: TransferFunction, num: [100], den: [1, 8, 100], shape: [2]}
connections:
  - src.y -> i.u
  - w.y -> e.u1
  - pulse.y -> e.u2
  - plant.y -> e.u3
  - e.y -> sat.u
  - sat.y -> plant.u
simulation: {t_final: 0.05, step: 0.001, solver: rk4, log_every: 3}
metrics: {error: e.y}
"""


def _same(got, ref, column=None):
    """Every signal of ``got`` within 1e-12 of its scale of ``ref`` (``column``: the
    variant of the batch ``got`` to compare)."""
    np.testing.assert_array_equal(got.t, ref.t)
    assert sorted(got.names) == sorted(ref.names)
    for name in ref.names:
        a = got[name] if column is None else got[name][:, column]
        scale = max(1.0, float(np.nanmax(np.abs(ref[name]))))
        np.testing.assert_allclose(a, ref[name], rtol=0, atol=1e-12 * scale, err_msg=name)


@pytest.fixture
def jumps(tmp_path):
    path = tmp_path / "jumps.yaml"
    path.write_text(JUMPS)
    return str(path)


@pytest.mark.slow
@pytest.mark.parametrize("T", [0.0123, 0.02, 0.05])      # inside a step, on the grid, t_final
def test_split_steps_agree_on_both_paths(jumps, T):
    """Steps split at jumps off the grid, clamped stage times, an event at t_final: the
    compiled loop runs the NumPy path's step grid (the same numbers), and the integral of
    the Step is exact, A (t - T) (RK4 integrates each constant piece exactly)."""
    from fwdstep.run.events import plan_events
    d = fwdstep.load_diagram(jumps, {"T": T})
    plan = plan_events(d, 0.001, 50)
    assert any(abs(sub.a / 0.001 - round(sub.a / 0.001)) > 1e-6
               for subs in plan.steps.values() for sub in subs)        # split steps
    got = fwdstep.simulate(d, backend="compiled")
    _same(got, fwdstep.simulate(d, backend="numpy"))
    np.testing.assert_allclose(got["i.y"], np.maximum(got.t - T, 0.0), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(got["src.y"], np.where(got.t >= T, 1.0, 0.0))


@pytest.mark.slow
def test_batch_with_jumps_equals_one_by_one_compiled_runs(jumps):
    """A batch (run_all, prange) of variants with other seeds and heights: each variant is
    its own compiled run; the batch equals the NumPy path's batch."""
    from fwdstep.structure.compiler import compile_batch
    values = [{"A": 1.0, "seed": 1}, {"A": -2.0, "seed": 2}, {"A": 0.5, "seed": 7}]
    d = compile_batch([load_spec(jumps, v) for v in values])
    batch = fwdstep.simulate(d, backend="compiled")
    _same(batch, fwdstep.simulate(d, backend="numpy"))
    for b, v in enumerate(values):
        _same(batch, fwdstep.simulate(fwdstep.load_diagram(jumps, v), backend="compiled"), b)
    assert not np.array_equal(batch["w.y"][:, 0], batch["w.y"][:, 1])      # other seeds


@pytest.mark.slow
def test_compiled_sweep_over_jump_times_and_seeds(jumps):
    """``fwdstep sweep --backend compiled`` over jump times (separate batches: one step
    grid per batch) and seeds: each variant's recorded signal is its own compiled run."""
    from fwdstep.sweeps.sweep import run_sweep
    result = run_sweep(jumps, grid={"T": [0.0123, 0.05], "seed": [1, 2]}, backend="compiled")
    assert result.counts() == {"ok": 4} and len(result.batches) == 2
    recorded = {int(i): (part["t"], part["e"][:, k]) for part in result.parts
                for k, i in enumerate(part["indices"])}
    for v in result.variants:
        alone = fwdstep.simulate(fwdstep.load_diagram(jumps, v.values), backend="compiled")
        t, e = recorded[v.index]
        np.testing.assert_array_equal(t, alone.t)
        np.testing.assert_allclose(e, alone["e.y"], rtol=0, atol=1e-12,
                                   err_msg=str(v.values))


#: a sampled loop: period 3.7 ms (not a multiple of the 1 ms step), first sample at 1.1 ms
#: (off the grid); a hold feeding a state space with D != 0 (two levels of updates at one
#: instant) and a unit delay
SAMPLED = """
parameters: {T: 0.0037, t0: 0.0011, a: 0.9}
blocks:
  w:     {type: Sine, amplitude: [1.0, 0.5], frequency: [30.0, 50.0]}
  plant: {type: TransferFunction, num: [100], den: [1, 8, 100], shape: [2]}
  e:     {type: Sum, signs: "+-", shape: [2]}
  zoh:   {type: ZeroOrderHold, period: T, offset: t0, shape: [2]}
  ctrl:  {type: DiscreteStateSpace, A: [[a, 0.05], [0, 0.8]], B: [[0.1, 0], [0, 0.2]],
          C: [[2, 0], [0, 3]], D: [[1, 0], [0, 1]], period: T, offset: t0}
  dly:   {type: UnitDelay, period: T, offset: t0, shape: [2]}
connections:
  - w.y -> e.u1
  - plant.y -> e.u2
  - e.y -> zoh.u
  - zoh.y -> ctrl.u
  - ctrl.y -> dly.u
  - dly.y -> plant.u
simulation: {t_final: 0.05, step: 0.001, solver: rk4, log_every: 3}
"""


@pytest.mark.slow
def test_discrete_blocks_agree_on_both_paths(tmp_path):
    """Discrete updates between (sub-)steps (the loop pauses, fwdstep.run.events.apply_updates
    updates, the loop resumes at that sub-step): the NumPy path's numbers, one run and a
    batch of variants with other matrices, each equal to its own compiled run."""
    from fwdstep.structure.compiler import compile_batch
    path = tmp_path / "sampled.yaml"
    path.write_text(SAMPLED)
    d = fwdstep.load_diagram(str(path))
    got = fwdstep.simulate(d, backend="compiled")
    _same(got, fwdstep.simulate(d, backend="numpy"))
    k = np.searchsorted(got.t, 0.0011 + 0.0037)          # held between samples
    last = {"t0": 0.0021, "simulation.t_final": 0.028}     # a sample at t_final: recorded
    _same(fwdstep.simulate(fwdstep.load_diagram(str(path), last), backend="compiled"),
          fwdstep.simulate(fwdstep.load_diagram(str(path), last), backend="numpy"))
    assert got["dly.y"][k - 1, 0] == 0.0 and got["dly.y"][k + 1, 0] != 0.0
    values = [{"a": 0.9}, {"a": 0.5}, {"a": -0.3}]
    batch = fwdstep.simulate(compile_batch([load_spec(str(path), v) for v in values]),
                             backend="compiled")
    for b, v in enumerate(values):
        _same(batch, fwdstep.simulate(fwdstep.load_diagram(str(path), v), backend="compiled"),
              b)


def test_event_arrays_are_the_numpy_paths_plan(tmp_path):
    """No compiling: the rows the compiled loop reads are plan_events' sub-steps, in order,
    with the discrete updates flagged, and an event at t_final gives the final record its
    right limit."""
    from fwdstep.compiled import backend_numba
    from fwdstep.run.events import plan_events
    path = tmp_path / "sampled.yaml"
    path.write_text(SAMPLED.replace("t0: 0.0011", "t0: 0.0021"))   # 0.0021 + 7 T = 0.028
    d = fwdstep.load_diagram(str(path), {"simulation.t_final": 0.028})
    plan = plan_events(d, 0.001, 28)
    (ev_n, ev_off, ev_t, ev_r), events = backend_numba.event_arrays(plan, 28, 0.001, 3)
    subs = [s for n in sorted(plan.steps) for s in plan.steps[n]]
    assert ev_n.tolist() == sorted(plan.steps) + [28] and ev_off[-1] == len(subs) + 1
    assert [tuple(r) for r in ev_t[:-1]] == [(s.a, s.b, s.lo, s.hi, float(s.event is not None))
                                             for s in subs]
    assert events[:-1] == [s.event for s in subs] and sum(e is not None for e in events) == 7
    assert plan.final.updates and ev_t[-1, 4] == 0       # applied by the caller
    assert ev_t[-1, 0] == 28 * 0.001 and ev_t[-1, 2] == plan.final.hi
    assert ev_r.tolist() == [-1, -1, -1]


#: the arm's payload grows at P = 23.7 ms, inside a 1 ms step
PAYLOAD = """
parameters: {P: 0.0237, kp: -40}
blocks:
  arm: {type: TwoLinkArm, q0: [0.3, -0.2], gravity: 9.81, payload: 0.5, payload_time: P}
  kp:  {type: Gain, gain: kp, shape: [2]}
  kd:  {type: Gain, gain: -8, shape: [2]}
  tau: {type: Sum, signs: "++", shape: [2]}
connections:
  - arm.q -> kp.u
  - arm.qdot -> kd.u
  - kp.y -> tau.u1
  - kd.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.05, step: 0.001, solver: rk4, log_every: 3}
"""


@pytest.mark.slow
def test_payload_jump_inside_a_step_agrees_on_both_paths(tmp_path):
    """A plant whose parameters jump at a declared time off the grid (the split step): the
    NumPy path's numbers, one run and a batch of other gains (each its own compiled run)."""
    from fwdstep.structure.compiler import compile_batch
    path = tmp_path / "payload.yaml"
    path.write_text(PAYLOAD)
    d = fwdstep.load_diagram(str(path))
    assert 23 in _plan_steps(d) and len(_plan_steps(d)[23]) == 2
    got = fwdstep.simulate(d, backend="compiled")
    _same(got, fwdstep.simulate(d, backend="numpy"))
    values = [{"kp": -40}, {"kp": -10}]
    batch = fwdstep.simulate(compile_batch([load_spec(str(path), v) for v in values]),
                             backend="compiled")
    for b, v in enumerate(values):
        _same(batch, fwdstep.simulate(fwdstep.load_diagram(str(path), v), backend="compiled"),
              b)


def _plan_steps(d):
    from fwdstep.run.events import plan_events
    cfg = d.spec.simulation
    return plan_events(d, cfg.step, cfg.n_steps).steps
