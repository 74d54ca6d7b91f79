"""Batched runs (fwdstep.compile_batch): B variants in one pass give each variant's own numbers.

Each variant is also run alone; the batched numbers must agree to 1e-12 (relative to the
signal's size) although the blocks take their batched code paths and the fused linear
matrices carry a batch axis.  A variant whose gain makes the loop unstable diverges: it is
frozen and marked (NaN after its divergence time) while the others go on.
"""
import numpy as np
import pytest

import fwdstep
from fwdstep.structure.compiler import compile_batch, compile_spec, instantiate_variants
from fwdstep.core.errors import ConfigError, DivergenceError
from fwdstep.structure.spec import load_spec

LOOP = """
parameters: {ell: 2, alpha: 4, gamma: 2, K: 20*eye(2), q0: [0.1, -0.1], amp: [0.3, 0.2]}
blocks:
  qd:    {type: Sine, amplitude: amp, frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: q0}
  ref:   {type: ReferenceDynamics, variant: eq2, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  Ks:    {type: Gain, gain: K}
  lag:   {type: TransferFunction, num: [1, 10], den: [1, 10], shape: [2]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Ks.y -> lag.u
  - Yth.y -> tau.u1
  - lag.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.6, step: 0.002, solver: rk4, log_every: 2, bound: 1e3}
log: [e.y, tau.y, adapt.theta_hat, ref.z]
metrics: {error: e.y}
"""

VARIANTS = [
    {"K": "20*eye(2)"},
    {"K": "-120*eye(2)"},                      # positive feedback: diverges at t = 0.4
    {"K": "50*eye(2)", "alpha": 2, "q0": [0.3, 0.2]},
    {"gamma": 0.5, "amp": [0.5, -0.1]},
]


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "loop.yaml"
    p.write_text(LOOP)
    return str(p)


def run_alone(spec):
    try:
        return fwdstep.simulate(compile_spec(spec))
    except DivergenceError as exc:
        return exc.result


def test_batched_run_equals_variants_run_one_by_one(path):
    specs = [load_spec(path, v) for v in VARIANTS]
    batch = fwdstep.simulate(compile_batch(specs))
    assert batch.status == "partially diverged"
    assert batch.batch == len(VARIANTS)
    for b, spec in enumerate(specs):
        alone = run_alone(spec)
        rows = len(alone.t)
        if b == 1:
            assert alone.status == "diverged" and 0.3 < alone.diverged_at[0] < 0.5
            assert batch.diverged_at[1] == pytest.approx(alone.diverged_at[0])
            assert rows < len(batch.t)
            # after its divergence the frozen variant is NaN, and stays so
            for name in alone.names:
                assert np.all(np.isnan(batch[name][rows:, b]))
        else:
            assert alone.status == "ok" and np.isnan(batch.diverged_at[b])
            assert rows == len(batch.t)
        np.testing.assert_array_equal(batch.t[:rows], alone.t)
        for name in alone.names:
            ref = alone[name]
            scale = max(1.0, float(np.max(np.abs(ref))))
            np.testing.assert_allclose(batch[name][:rows, b], ref, rtol=0, atol=1e-12 * scale,
                                       err_msg=f"variant {b}, {name}")
    # the survivors' metrics are those of their own runs
    metrics = batch.metrics()
    for b in (0, 2, 3):
        alone = run_alone(specs[b]).metrics()
        for key, value in alone.items():
            assert metrics[b][key] == pytest.approx(value, rel=1e-10, abs=1e-14)


def test_all_variants_diverging_raises_with_the_partial_batch(path):
    specs = [load_spec(path, {"K": f"-{k}*eye(2)"}) for k in (300, 400)]
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(compile_batch(specs))
    result = info.value.result
    assert result.status == "diverged" and result.batch == 2 and len(result.t) > 1


def test_identical_blocks_are_built_once(path):
    specs = [load_spec(path, {"gamma": g}) for g in (1, 2, 3)]
    variants = instantiate_variants(specs)
    names = [b.name for b in variants[0]]
    for k, name in enumerate(names):
        same = all(v[k] is variants[0][k] for v in variants)
        assert same == (name != "adapt"), name


def test_stacking_leaves_shared_blocks_alone(path):
    """One arm instance serves two batches of different sizes; each gets its own x0."""
    specs = [load_spec(path, {"gamma": g}) for g in (1, 2, 3)]
    a = compile_batch(specs)
    b = compile_batch(specs[:2])
    assert a.x0.shape[0] == 3 and b.x0.shape[0] == 2
    ra, rb = fwdstep.simulate(a), fwdstep.simulate(b)
    np.testing.assert_array_equal(ra["e.y"][:, :2], rb["e.y"])


def test_different_structures_are_refused(path):
    specs = [load_spec(path, {"ell": 1}), load_spec(path, {"ell": 2})]
    with pytest.raises(ConfigError, match="differ in structure"):
        compile_batch(specs)


def test_variants_differing_in_a_flag_are_not_stacked():
    """A str/bool/choice/int parameter may select a code path: never stack across it unless
    the block declares it in ``stacked_params`` (keeps it in ``p`` per variant)."""
    from fwdstep.core.block import Block, Param
    from fwdstep.structure.compiler import structure_signature
    from fwdstep.structure.library import load_library

    class Switch(Block):
        """Test-only: y = u or y = -u by a choice that is NOT stored in p."""
        params = {"mode": Param("choice", choices=("plus", "minus")), "k": Param("float")}

        def setup(self, mode, k):
            self.declare_input("u", (2,))
            self.declare_output("y", (2,))
            self.set_param("k", k)

    a, b, c = Switch("s", mode="plus", k=1.0), Switch("s", mode="minus", k=1.0), \
        Switch("s", mode="plus", k=2.0)
    assert structure_signature([a]) != structure_signature([b])
    assert structure_signature([a]) == structure_signature([c])
    prod = load_library()["Product"]
    assert "transpose_a" in prod.stacked_params
    assert (structure_signature([prod("p", a_shape=[2, 2], b_shape=[2], transpose_a=True)])
            == structure_signature([prod("p", a_shape=[2, 2], b_shape=[2])]))


def test_a_number_kept_outside_p_splits_the_batch():
    """A block that keeps a parameter in a private attribute (not in ``p``) must not be
    stacked with a variant whose attribute differs: ``stack_blocks`` would give it the first
    variant's number.  What ``finalize`` recomputes from the stacked ``p`` does not split."""
    from fwdstep.core.block import Block, Param
    from fwdstep.structure.compiler import stack_blocks, structure_signature

    class Hidden(Block):
        """Test-only: y = k u with k kept outside p (a block written carelessly)."""
        params = {"k": Param("float"), "g": Param("float", 1.0)}
        finalize_attributes = Block.finalize_attributes + ("_g_first",)   # declared, not probed

        def setup(self, k, g):
            self.declare_input("u", (2,))
            self.declare_output("y", (2,))
            self._k = k                          # not stacked: must split
            self.set_param("g", g)
            self.finalize(1)

        def finalize(self, batch):
            self._g_first = self.p.g[0]          # recomputed after stacking: must not split

    a, b, c = Hidden("h", k=1.0), Hidden("h", k=2.0), Hidden("h", k=1.0, g=3.0)
    assert structure_signature([a]) != structure_signature([b])
    assert structure_signature([a]) == structure_signature([c])
    with pytest.raises(ConfigError, match="differ in structure"):
        stack_blocks([[a], [b]])
    stacked = stack_blocks([[a], [c]])[0]
    np.testing.assert_array_equal(stacked.p.g, [1.0, 3.0])


def test_variants_whose_kernels_are_written_for_other_statics_are_not_stacked():
    """A kernel's static value (``set_kernels(static=...)``) may be derived from a number
    (URDFArm: whether there is joint friction at all): variants with other statics run other
    code, so they must not share a batch (before, a sweep over arm.damping = 0, 5 ran both
    without friction)."""
    from fwdstep.core.block import Block, Param
    from fwdstep.structure.compiler import stack_blocks, structure_signature

    class Scaled(Block):
        """Test-only: y = k u, the multiplication left out (static flag) when k == 1."""
        params = {"k": Param("float")}

        def setup(self, k):
            self.declare_input("u", (2,))
            self.declare_output("y", (2,))
            self.set_param("k", [k])
            self.set_kernels(output=_scaled_output, params=("k",), static=(k != 1.0,))

    a, b, c = Scaled("s", k=1.0), Scaled("s", k=2.0), Scaled("s", k=3.0)
    assert structure_signature([a]) != structure_signature([b])
    assert structure_signature([b]) == structure_signature([c])
    with pytest.raises(ConfigError, match="differ in structure"):
        stack_blocks([[a], [b]])
    stacked = stack_blocks([[b], [c]])[0]
    y = stacked.output(0.0, None, (np.ones((2, 2)),))[0]
    np.testing.assert_array_equal(y, [[2.0, 2.0], [3.0, 3.0]])


def _scaled_output(t, x, u, k, scaled):
    return ((k * u) if scaled else u.copy(),)
