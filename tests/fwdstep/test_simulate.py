"""The lean run program (fwdstep.run.program) against a plain reference stepper.

``reference_run`` below is procedure Step of fwdstep/run/simulate.py written the obvious way:
a walk over the schedule per stage, a signal list, fresh arrays.  ``simulate`` must give
the same numbers: bit for bit when linear blocks are called (``fuse=False``: the same
operations in the same order), and to 1e-12 (relative to the signal's size) when they are
fused into matrix products (a different summation order).  The closed loop used here has
every kind of linear block the fusion handles: a feedthrough reference dynamics, a chain of
proper transfer functions (substituted into each other), a matrix filter of the regressor,
an integrator, an unconnected optional input; and a non-feedthrough input read before its
producer ran (the arm's torque).
"""
import numpy as np
import pytest

import fwdstep
from fwdstep.core.linear import LinearBlock, linear_form_of, plan_fusion
from fwdstep.run.program import build_program
from fwdstep.run.simulate import initial_state
from fwdstep.core.solvers import TABLEAUX, step_plan

LOOP = """
parameters: {ell: 2, alpha: 4, gamma: 2}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: [0.1, -0.1]}
  ref:   {type: ReferenceDynamics, variant: eq16, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  W:     {type: StateSpace, A: [[-5, 0], [0, -5]], B: [[5, 0], [0, 5]], C: [[1, 0], [0, 1]],
          columns: 4}
  lead:  {type: TransferFunction, num: [20, 60], den: [1, 2], shape: [2]}
  lag:   {type: TransferFunction, num: [1, 10], den: [1, 10], shape: [2]}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
  ie:    {type: Integrator, shape: [2]}
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
  - s.y -> lead.u, adapt.e
  - lead.y -> lag.u
  - Yth.y -> tau.u1
  - lag.y -> tau.u2
  - tau.y -> arm.tau
  - e.y -> ie.u
simulation: {t_final: 0.3, step: 0.002, solver: rk4}
"""


@pytest.fixture
def loop(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text(LOOP)
    return str(path)


def reference_run(d):
    """Procedure Step, plainly: returns (t, {signal name: (T, B, *shape)})."""
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    stages, final = step_plan(tab, cfg.step)
    sig = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr

    def f(t, x):
        for st in d.schedule:
            xs = x[:, st.state] if st.state is not None else x[:, 0:0]
            y = st.block.output(t, xs, tuple(sig[i] for i in st.inputs))
            for idx, v in zip(st.outputs, y):
                sig[idx] = v
        dx = np.zeros_like(x)
        for st in d.stateful:
            dx[:, st.state] = st.block.derivative(t, x[:, st.state],
                                                  tuple(sig[i] for i in st.inputs))
        return dx

    def snapshot():
        return [np.broadcast_to(sig[d.signal_index[n]], (d.batch,) + sig[
            d.signal_index[n]].shape[1:]).copy() for n in d.logged]

    x = initial_state(d)
    ts, rows = [], []
    with np.errstate(all="ignore"):
        for n in range(cfg.n_steps):
            t = n * cfg.step
            k = [f(t, x)]
            if n % cfg.log_every == 0:
                ts.append(t)
                rows.append(snapshot())
            for ch, coeffs in stages:
                xi = x.copy()
                for j, a in coeffs:
                    xi += a * k[j]
                k.append(f(t + ch, xi))
            for j, b in final:
                x += b * k[j]
        f(cfg.n_steps * cfg.step, x)
        ts.append(cfg.n_steps * cfg.step)
        rows.append(snapshot())
    return np.array(ts), {n: np.array([r[i] for r in rows]) for i, n in enumerate(d.logged)}


def assert_close(actual, expected, rtol=1e-12):
    scale = max(1.0, float(np.max(np.abs(expected))))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rtol * scale)


def test_unfused_program_is_bit_identical_to_the_reference(loop):
    d = fwdstep.load_diagram(loop)
    t_ref, ref = reference_run(d)
    r = fwdstep.simulate(d, fuse=False)
    np.testing.assert_array_equal(r.t, t_ref)
    for name in d.logged:
        np.testing.assert_array_equal(r[name], ref[name][:, 0], err_msg=name)


def test_fused_program_matches_the_reference_to_1e12(loop):
    d = fwdstep.load_diagram(loop)
    t_ref, ref = reference_run(d)
    r = fwdstep.simulate(d)
    np.testing.assert_array_equal(r.t, t_ref)
    assert np.abs(ref["arm.q"]).max() < 1.0           # a sane, non-trivial closed loop
    for name in d.logged:
        assert_close(r[name], ref[name][:, 0])


def test_linear_blocks_are_fused_and_every_signal_is_written_once(loop):
    d = fwdstep.load_diagram(loop)
    plan = plan_fusion(d.schedule, d.signal_shapes, d.constant_signals)
    linear = {s.block.name for s in d.schedule if isinstance(s.block, LinearBlock)}
    assert plan.fused >= linear == {"ref", "W", "lead", "lag", "ie"}
    written = []
    for kind, op in plan.ops:
        written += list(op.outputs) if kind == "call" else [idx for idx, _ in op.outputs]
    produced = [idx for s in d.schedule for idx in s.outputs]
    assert sorted(written) == sorted(produced)
    groups = [op for kind, op in plan.ops if kind == "group"]
    assert sum(g.derivative for g in groups) == 1      # all fused states: one product
    # the fused states are one slice of the flat state, after the called blocks' states
    assert plan.state.stop == d.n_states
    for s in d.stateful:
        inside = plan.state.start <= s.state.start < plan.state.stop
        assert inside == (s.block.name in plan.fused)


def _count_calls(d):
    counts = {}
    for st in d.schedule:
        blk = st.block
        for method in ("output", "derivative"):
            fn = getattr(blk, method)
            key = (blk.name, method)
            counts[key] = 0

            def counted(t, x, u, fn=fn, key=key):
                counts[key] += 1
                return fn(t, x, u)

            setattr(blk, method, counted)
    return counts


@pytest.mark.parametrize("fuse", [False, True])
def test_each_block_is_evaluated_exactly_once_per_stage(loop, fuse):
    d = fwdstep.load_diagram(loop)
    x0 = initial_state(d)
    counts = _count_calls(d)
    fwdstep.simulate(d, x0=x0, fuse=fuse)
    n, stages = d.spec.simulation.n_steps, TABLEAUX["rk4"].stages
    fused = plan_fusion(d.schedule, d.signal_shapes, d.constant_signals).fused if fuse else set()
    # + 1: every block is evaluated once more, block by block, at the initial state, where
    # the shapes of its results are checked (fwdstep.run.evaluate.check_shapes)
    for st in d.schedule:
        name = st.block.name
        expected = 0 if name in fused else stages * n + 1      # + the final-time outputs
        assert counts[(name, "output")] == expected + 1, name
        if st.state is not None:
            assert counts[(name, "derivative")] == (
                0 if name in fused else stages * n) + 1, name


def test_linear_form_describes_the_block(loop):
    """The fused form evaluates exactly what the block's own methods do."""
    d = fwdstep.load_diagram(loop)
    rng = np.random.default_rng(1)
    for st in d.schedule:
        form = linear_form_of(st.block)
        if form is None:
            continue
        blk = st.block
        x = rng.normal(size=(1, blk.n_states))
        u = tuple(rng.normal(size=(1,) + p.shape) for p in blk.inputs.values())
        for k, y in enumerate(blk.output(0.0, x, u)):
            expect = form.C[k][0] @ x[0] + sum(
                (form.D[(k, j)][0] @ u[j][0].ravel() for j in range(len(u)) if (k, j) in
                 form.D), np.zeros(form.C[k].shape[1]))
            np.testing.assert_allclose(np.ravel(y), expect, rtol=1e-13, atol=1e-13)
        if blk.n_states:
            dx = form.A[0] @ x[0] + sum((form.B[j][0] @ u[j][0].ravel() for j in form.B),
                                        np.zeros(blk.n_states))
            np.testing.assert_allclose(blk.derivative(0.0, x, u)[0], dx, rtol=1e-13,
                                       atol=1e-13)


def test_a_subclass_that_overrides_output_is_called_not_fused():
    from fwdstep.blocks.linear import Integrator

    class Clipped(Integrator):
        def output(self, t, x, u):
            return (np.clip(x, -1, 1),)

    assert linear_form_of(Integrator("i", shape=[2])) is not None
    assert linear_form_of(Clipped("c", shape=[2])) is None


def test_a_run_twice_gives_the_same_result_and_keeps_nothing(loop):
    d = fwdstep.load_diagram(loop)
    a = fwdstep.simulate(d)
    b = fwdstep.simulate(d)
    for name in d.logged:
        np.testing.assert_array_equal(a[name], b[name])
    assert not any(hasattr(s, "_names") for s in d.schedule)


@pytest.mark.parametrize("solver", ["euler", "heun"])
def test_other_solvers_match_the_reference(loop, solver):
    d = fwdstep.load_diagram(loop)
    d.spec.simulation.solver = solver
    d.spec.simulation.log_every = 3
    t_ref, ref = reference_run(d)
    r = fwdstep.simulate(d)
    np.testing.assert_array_equal(r.t, t_ref)
    for name in d.logged:
        assert_close(r[name], ref[name][:, 0])


def test_program_source_is_straight_line(loop):
    """No loops or signal lookups in the generated stage code: one line per operation."""
    d = fwdstep.load_diagram(loop)
    prog = build_program(d, n_rows=2)
    body = prog.source
    assert "for " not in body and "while " not in body and "sig[" not in body


@pytest.mark.parametrize("name", ["theorem1", "theorem3", "theorem6", "theorem8", "pid_classic",
                                  "slotine_li_disturbed"])
def test_shipped_diagrams_without_events_run_the_plain_procedure(name):
    """Diagrams that declare no discontinuity times (fwdstep.run.events) take the unchanged
    path: bit for bit the reference stepper.  (Their fused runs were also compared with
    arrays saved before events existed: equal, docs/discrete-time.md.)"""
    from fwdstep.run.events import plan_events
    d = fwdstep.load_diagram(f"diagrams/{name}.yaml", overrides={"simulation.t_final": 0.04})
    assert plan_events(d, d.spec.simulation.step, d.spec.simulation.n_steps) is None
    t_ref, ref = reference_run(d)
    r = fwdstep.simulate(d, fuse=False)
    np.testing.assert_array_equal(r.t, t_ref)
    for sig in d.logged:
        np.testing.assert_array_equal(r[sig], ref[sig][:, 0], err_msg=sig)


def test_a_time_only_block_is_evaluated_once_per_stage_time(loop):
    """The Sine has no inputs and no states: RK4's stages 2 and 3 share t + h/2, so the
    program reuses its outputs there (the numbers are those of the reference stepper, bit
    for bit: test above); the plant, which has a state, is evaluated at every stage."""
    import dataclasses
    d = fwdstep.load_diagram(loop)
    calls = {"qd": [], "arm": []}
    for st in d.schedule:
        if st.block.name in calls:
            k, seen = st.block.kernels, calls[st.block.name]
            st.block.kernels = dataclasses.replace(
                k, output=lambda t, *a, _f=k.output, _s=seen: _s.append(t) or _f(t, *a))
    fwdstep.simulate(d)
    n = d.spec.simulation.n_steps
    assert len(calls["arm"]) >= 4 * n                     # every stage
    assert 2 * n < len(calls["qd"]) <= 3 * n + 3          # stages 1, 2 and 4 (and the start)


def test_a_time_only_block_with_several_unpacked_outputs(tmp_path):
    """Each output of a reused (memoised) call is still named: a user's source returning a
    tuple of two outputs (not packed) feeds two integrators, which give its integrals."""
    plugin = tmp_path / "clock.py"
    plugin.write_text('''
import numpy as np
from fwdstep.core.block import Block
from fwdstep.core.registry import register


def clock_output(t, x):
    return (np.full((1, 1), t), np.full((1, 1), 2.0))


@register
class Clock(Block):
    """Clock: a = t, b = 2.

    Equation: a = t, b = 2.
    """
    params = {}

    def setup(self):
        self.declare_output("a", (1,))
        self.declare_output("b", (1,))
        self.set_kernels(output=clock_output)
''')
    path = tmp_path / "d.yaml"
    path.write_text("blocks:\n  c: {type: Clock}\n  i: {type: Integrator, shape: [1]}\n"
                    "  j: {type: Integrator, shape: [1]}\nconnections:\n  - c.a -> i.u\n"
                    "  - c.b -> j.u\nsimulation: {t_final: 1.0, step: 0.01, solver: rk4}\n"
                    "log: [i.y, j.y]\n")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path), plugins=[str(plugin)]))
    np.testing.assert_allclose(r["i.y"][-1], [0.5], rtol=1e-12)
    np.testing.assert_allclose(r["j.y"][-1], [2.0], rtol=1e-12)


def test_a_reused_time_only_output_in_a_fused_product_is_the_current_one(tmp_path):
    """A Sine feeding fused linear blocks is copied into the product's input buffer only when
    it was evaluated again (RK4's stage 3 reuses stage 2's time); every stage must still see
    the Sine at its own time: the logged gain output is 2 sin(3t) and the integral of it
    matches the closed form to RK4's accuracy (a stale stage input would leave an O(h) error)."""
    path = tmp_path / "d.yaml"
    path.write_text("blocks:\n  w: {type: Sine, amplitude: [1.0], frequency: [3.0]}\n"
                    "  g: {type: Gain, gain: 2}\n  i: {type: Integrator, shape: [1]}\n"
                    "connections:\n  - w.y -> g.u\n  - g.y -> i.u\n"
                    "simulation: {t_final: 2.0, step: 0.01, solver: rk4}\nlog: [g.y, i.y]\n")
    d = fwdstep.load_diagram(str(path))
    assert " is not memo" in build_program(d, n_rows=2).source     # the guarded copy is used
    r = fwdstep.simulate(d)
    np.testing.assert_allclose(r["g.y"][:, 0], 2 * np.sin(3 * r.t), rtol=0, atol=1e-14)
    np.testing.assert_allclose(r["i.y"][:, 0], 2 / 3 * (1 - np.cos(3 * r.t)), rtol=0, atol=1e-8)
