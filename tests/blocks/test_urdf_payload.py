"""URDFArm's payload (a point mass held by a frame) against pinocchio's own appendBodyToJoint,
and a batched Panda sweep over payload and gains: every variant equals its own run, on the
NumPy path and on the compiled backend."""
import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

from fwdstep.blocks.urdf import NAMED_ROBOTS, URDFArm, _robots_folder  # noqa: E402
from fwdstep.core.errors import ParameterError  # noqa: E402

SLOTINE_LI = "diagrams/robots/panda_slotine_li.yaml"


def reference_with_payload(robot, frame, mass, position, gravity=9.81):
    """The robot loaded by pinocchio directly, the payload appended to the frame's joint by
    pinocchio (``appendBodyToJoint`` of a point Inertia at the frame's placement)."""
    relative, locked = NAMED_ROBOTS[robot]
    model = pin.buildModelFromUrdf(str(_robots_folder("test") / relative))
    if locked:
        model = pin.buildReducedModel(model, [model.getJointId(j) for j in locked],
                                      pin.neutral(model))
    model.gravity.linear = np.array([0.0, 0.0, -gravity])
    if frame:
        fr = model.frames[model.getFrameId(frame)]
        joint, placement = fr.parentJoint, fr.placement
    else:
        joint, placement = model.njoints - 1, pin.SE3.Identity()
    model.appendBodyToJoint(joint, pin.Inertia(mass, np.asarray(position, float),
                                               np.zeros((3, 3))), placement)
    return model, model.createData()


@pytest.mark.parametrize("implementation", ["pinocchio", "kernels"])
@pytest.mark.parametrize("robot, frame", [("panda", "panda_hand"), ("ur5", "tool0"),
                                          ("ur5", "")])
def test_payload_dynamics_equal_pinocchio_with_the_body_appended(robot, frame, implementation):
    mass, position = 1.7, [0.02, -0.03, 0.1]
    arm = URDFArm("arm", robot=robot, payload=mass, payload_frame=frame,
                  payload_position=position, implementation=implementation, damping=0.0)
    model, data = reference_with_payload(robot, frame, mass, position)
    n = model.nv
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, v, tau = rng.uniform(-1, 1, n), rng.standard_normal(n), 5 * rng.standard_normal(n)
        dx = arm.derivative(0.0, np.concatenate([q, v])[None], (tau[None], np.zeros((1, n))))
        reference = pin.aba(model, data, q, v, tau)
        assert np.abs(dx[0, n:] - reference).max() <= 1e-12 * max(1.0, np.abs(reference).max())
    # theta (full form) is pinocchio's parameters of the loaded bodies
    full = URDFArm("arm", robot=robot, payload=mass, payload_frame=frame,
                   payload_position=position)
    expected = np.concatenate([model.inertias[j].toDynamicParameters()
                               for j in range(1, model.njoints)])
    np.testing.assert_allclose(full.p.theta[0], expected, rtol=0, atol=1e-12)


def test_batched_payloads_each_take_their_own_model():
    """One batch of three payloads on the pinocchio path: each row equals its own block."""
    from fwdstep.structure.compiler import stack_blocks
    masses = (0.0, 1.0, 2.5)
    blocks = [[URDFArm("arm", robot="panda", payload=m, payload_frame="panda_hand",
                       implementation="pinocchio")] for m in masses]
    stacked = stack_blocks(blocks)[0]
    rng = np.random.default_rng(0)
    x, tau = rng.standard_normal((3, 14)), rng.standard_normal((3, 7))
    batch = stacked.derivative(0.0, x, (tau, np.zeros((1, 7))))
    for b, one in enumerate(blocks):
        alone = one[0].derivative(0.0, x[b:b + 1], (tau[b:b + 1], np.zeros((1, 7))))
        np.testing.assert_array_equal(batch[b], alone[0])


def test_payload_messages():
    with pytest.raises(ParameterError, match="'payload' must be a mass >= 0"):
        URDFArm("arm", robot="ur5", payload=-1.0)
    with pytest.raises(ParameterError, match="'payload_position' 3 finite numbers"):
        URDFArm("arm", robot="ur5", payload=1.0, payload_position=[0, 1])
    with pytest.raises(ParameterError, match="no frame 'nowhere' on a moving body"):
        URDFArm("arm", robot="ur5", payload=1.0, payload_frame="nowhere")


@pytest.mark.parametrize("backend", ["numpy", pytest.param("compiled", marks=pytest.mark.slow)])
def test_panda_sweep_over_payload_and_gains_is_one_batch_of_own_runs(backend):
    """Issue 25 item 4: payload mass and gains on the Panda, one batch; each variant's logged
    error equals its own run (1e-12)."""
    if backend == "compiled":
        pytest.importorskip("numba")
    from fwdstep.run.simulate import simulate
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.structure.spec import load_spec
    from fwdstep.sweeps.sweep import run_sweep
    variants = [{"payload": 0.0, "Lambda": 5.0, "Gamma": 1.0},
                {"payload": 1.0, "Lambda": 3.0, "Gamma": 0.5},
                {"payload": 2.5, "Lambda": 8.0, "Gamma": 2.0}]
    fixed = {"t_final": 0.05}
    result = run_sweep(SLOTINE_LI, variants=variants, overrides=fixed, workers=1,
                       backend=backend)
    assert len(result.batches) == 1 and result.counts() == {"ok": 3}
    signals = {int(i): part["e"][:, k] for part in result.parts
               for k, i in enumerate(part["indices"])}
    for v in result.variants:
        alone = simulate(compile_spec(load_spec(SLOTINE_LI, {**fixed, **v.values,
                                                             "simulation.backend": backend})))
        np.testing.assert_allclose(signals[v.index], alone["e.y"], rtol=0, atol=1e-12,
                                   err_msg=str(v.values))
    # the payload changes the motion (so the test would see another variant's numbers)
    assert np.abs(signals[0] - signals[2]).max() > 1e-6


def test_sweep_over_friction_from_zero_gives_each_variant_its_own_friction():
    """URDFArm writes its kernels with or without joint friction (a static flag from the
    numbers): a sweep over arm.damping = 0, 5 ran both without friction in one batch (the
    second off by 8e-3 rad in 0.05 s); now the flag splits the batch."""
    from fwdstep.run.simulate import simulate
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.structure.spec import load_spec
    from fwdstep.sweeps.sweep import run_sweep
    fixed = {"t_final": 0.05}
    result = run_sweep(SLOTINE_LI, variants=[{"arm.damping": 0.0}, {"arm.damping": 5.0}],
                       overrides=fixed, workers=1)
    signals = {int(i): part["e"][:, k] for part in result.parts
               for k, i in enumerate(part["indices"])}
    for v in result.variants:
        alone = simulate(compile_spec(load_spec(SLOTINE_LI, {**fixed, **v.values})))
        np.testing.assert_allclose(signals[v.index], alone["e.y"], rtol=0, atol=1e-12)
