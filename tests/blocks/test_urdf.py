"""URDFArm and URDFRegressor against pinocchio's own algorithms (an independently loaded model)
and against the shipped planar NLinkArm / NLinkRegressor on a planar chain written as URDF."""
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

from fwdstep.blocks.robot import NLinkArm, NLinkRegressor  # noqa: E402
from fwdstep.blocks.urdf import NAMED_ROBOTS, URDFArm, URDFRegressor, _robots_folder  # noqa: E402
from fwdstep.core.errors import ParameterError  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ("panda", "ur5")
IMPLEMENTATIONS = ("pinocchio", "kernels")


def reference_model(robot, gravity=9.81):
    """The robot loaded directly with pinocchio (not through blocks/urdf.py)."""
    relative, locked = NAMED_ROBOTS[robot]
    model = pin.buildModelFromUrdf(str(_robots_folder("test") / relative))
    if locked:
        model = pin.buildReducedModel(model, [model.getJointId(j) for j in locked],
                                      pin.neutral(model))
    model.gravity.linear = np.array([0.0, 0.0, -gravity])
    return model, model.createData()


def dynamics(model, data, q, v):
    """H (symmetrised from crba's upper triangle), C (computeCoriolisMatrix), g."""
    H = pin.crba(model, data, q).copy()
    H = np.triu(H) + np.triu(H, 1).T
    C = pin.computeCoriolisMatrix(model, data, q, v).copy()
    g = pin.computeGeneralizedGravity(model, data, q).copy()
    return H, C, g


def points(n, count, seed):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        yield rng.uniform(-2, 2, n), *rng.standard_normal((3, n))


def regress(block, q, qdot, zeta, zetad):
    return block.output(0.0, None, (q[None], qdot[None], zeta[None], zetad[None]))[0][0]


# ------------------------------------------------------------------------------ plant
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("robot", ROBOTS)
def test_plant_accelerations_are_pinocchio_aba_with_friction(robot, implementation):
    model, data = reference_model(robot)
    n = model.nv
    arm = URDFArm("arm", robot=robot, damping=0.3, coulomb=[0.5] * n, coulomb_velocity=0.1,
                  implementation=implementation)
    assert arm.outputs["q"].shape == (n,) and n == {"panda": 7, "ur5": 6}[robot]
    for q, v, tau, tau_star in points(n, 5, 1):
        dx = arm.derivative(0.0, np.concatenate([q, v])[None], (tau[None], tau_star[None]))[0]
        friction = 0.3 * v + 0.5 * np.tanh(v / 0.1)
        expected = pin.aba(model, data, q, v, tau + tau_star - friction)
        np.testing.assert_allclose(dx[:n], v, rtol=0, atol=0)
        np.testing.assert_allclose(dx[n:], expected, rtol=1e-12, atol=1e-12)
        # and H qddot + C qdot + g = torque (crba, Coriolis matrix, gravity: not aba)
        H, C, g = dynamics(model, data, q, v)
        np.testing.assert_allclose(H @ dx[n:] + C @ v + g, tau + tau_star - friction,
                                   rtol=0, atol=1e-9)


def test_plant_batch_equals_single_runs_and_theta_is_the_inertias():
    arm = URDFArm("arm", robot="ur5")
    model, _ = reference_model("ur5")
    rng = np.random.default_rng(2)
    x, tau = rng.standard_normal((3, 12)), rng.standard_normal((3, 6))
    batch = arm.derivative(0.0, x, (tau, np.zeros((1, 6))))
    for b in range(3):
        np.testing.assert_array_equal(
            batch[b], arm.derivative(0.0, x[b:b + 1], (tau[b:b + 1], np.zeros((1, 6))))[0])
    q, qdot, theta = arm.output(0.0, x[:1], (tau[:1], np.zeros((1, 6))))[:3]
    np.testing.assert_array_equal(q, x[:1, :6])
    masses = theta[0].reshape(6, 10)[:, 0]
    np.testing.assert_allclose(masses, [model.inertias[j].mass for j in range(1, 7)])
    assert masses.sum() == pytest.approx(3.7 + 8.393 + 2.275 + 1.219 + 1.219 + 0.1879)


def test_locked_joints_and_urdf_file():
    panda_8 = URDFArm("arm", robot="panda", locked_joints=["panda_finger_joint2"])
    assert panda_8.outputs["q"].shape == (8,)
    with pytest.raises(ParameterError, match=r"^block 'arm': the robot's joint "
                       r"'panda_finger_joint2' mimics 'panda_finger_joint1' \(<mimic>\), which "
                       r"is not supported: lock it \(locked_joints\)$"):
        URDFArm("arm", robot="panda", locked_joints=[])
    relative = NAMED_ROBOTS["ur5"][0]
    by_file = URDFArm("arm", urdf=str(_robots_folder("t") / relative))
    by_name = URDFArm("arm", robot="ur5")
    np.testing.assert_array_equal(by_file.p.theta, by_name.p.theta)


@pytest.mark.parametrize("params, message", [
    ({}, "block 'arm' needs exactly one of 'robot' (one of panda, ur5) and 'urdf' (a file)"),
    ({"robot": "iiwa"}, "block 'arm' parameter 'robot' must be one of panda, ur5, got 'iiwa'"),
    ({"urdf": "/nonexistent.urdf"}, "block 'arm' parameter 'urdf': no file '/nonexistent.urdf'"),
    ({"robot": "ur5", "locked_joints": ["elbow"]},
     "block 'arm': the robot has no joint 'elbow' to lock; joints are: shoulder_pan_joint, "
     "shoulder_lift_joint, elbow_joint, wrist_1_joint, wrist_2_joint, wrist_3_joint"),
    ({"robot": "ur5", "damping": [1, 2]},
     "block 'arm' parameter 'damping' must be a number or a list of 6 numbers, got shape (2,)"),
])
def test_bad_parameters_give_one_line_messages(params, message):
    with pytest.raises(ParameterError) as info:
        URDFArm("arm", **params)
    assert str(info.value) == message


# ------------------------------------------------------------------------------ regressor
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("robot", ROBOTS)
def test_regressor_is_H_zetad_plus_C_zeta_plus_g(robot, implementation):
    model, data = reference_model(robot)
    n = model.nv
    Y = URDFRegressor("Y", robot=robot, implementation=implementation)
    theta = URDFArm("arm", robot=robot).p.theta[0]
    assert Y.outputs["Y"].shape == (n, 10 * n)
    for q, qdot, zeta, zetad in points(n, 5, 3):
        H, C, g = dynamics(model, data, q, qdot)
        expected = H @ zetad + C @ zeta + g
        np.testing.assert_allclose(regress(Y, q, qdot, zeta, zetad) @ theta, expected,
                                   rtol=0, atol=1e-10 * max(1.0, np.abs(expected).max()))


@pytest.mark.parametrize("robot", ROBOTS)
def test_regressor_with_zeta_qdot_is_rnea(robot):
    model, data = reference_model(robot)
    Y = URDFRegressor("Y", robot=robot)
    theta = URDFArm("arm", robot=robot).p.theta[0]
    for q, qdot, _, qddot in points(model.nv, 5, 4):
        expected = pin.rnea(model, data, q, qdot, qddot)
        np.testing.assert_allclose(regress(Y, q, qdot, qdot, qddot) @ theta, expected,
                                   rtol=0, atol=1e-10 * max(1.0, np.abs(expected).max()))


@pytest.mark.parametrize("robot", ROBOTS)
def test_implied_C_makes_Hdot_minus_2C_skew_and_is_the_christoffel_matrix(robot):
    model, data = reference_model(robot)
    n = model.nv
    Y = URDFRegressor("Y", robot=robot)
    theta = URDFArm("arm", robot=robot).p.theta[0]
    zero = np.zeros(n)
    for q, qdot, w, _ in points(n, 3, 5):
        g = regress(Y, q, qdot, zero, zero) @ theta
        C = np.column_stack([regress(Y, q, qdot, e, zero) @ theta - g for e in np.eye(n)])
        # Hdot along qdot by a 4th-order central difference of crba (independent of C)
        def H(s):
            M = pin.crba(model, data, q + s * qdot).copy()
            return np.triu(M) + np.triu(M, 1).T
        h = 1e-3
        Hdot = (8 * (H(h) - H(-h)) - (H(2 * h) - H(-2 * h))) / (12 * h)
        S = Hdot - 2 * C
        assert np.abs(S + S.T).max() < 1e-8 * max(1.0, np.abs(Hdot).max())
        # Christoffel symmetry C(q, v) w = C(q, w) v, also of pinocchio's C (docs: our finding)
        Cw = np.column_stack([regress(Y, q, w, e, zero) @ theta - g for e in np.eye(n)])
        np.testing.assert_allclose(C @ w, Cw @ qdot, rtol=0, atol=1e-11)
        Cp_v = pin.computeCoriolisMatrix(model, data, q, qdot).copy()
        Cp_w = pin.computeCoriolisMatrix(model, data, q, w).copy()
        np.testing.assert_allclose(Cp_v @ w, Cp_w @ qdot, rtol=0, atol=1e-11)


@pytest.mark.parametrize("robot", ROBOTS)
def test_base_parameters_reproduce_the_full_regressor(robot):
    full = URDFRegressor("Y", robot=robot)
    base = URDFRegressor("Yb", robot=robot, parameters="base")
    theta = URDFArm("arm", robot=robot).p.theta[0]
    beta = URDFArm("arm", robot=robot, parameters="base").p.theta[0]
    n, p = base.outputs["Y"].shape
    assert p < 10 * n and beta.shape == (p,)
    rows = []
    for q, qdot, zeta, zetad in points(n, 12, 6):
        Yb = regress(base, q, qdot, zeta, zetad)
        expected = regress(full, q, qdot, zeta, zetad) @ theta
        np.testing.assert_allclose(Yb @ beta, expected, rtol=0,
                                   atol=1e-9 * max(1.0, np.abs(expected).max()))
        rows.append(Yb)
    assert np.linalg.matrix_rank(np.vstack(rows)) == p      # identifiable: full column rank


# ------------------------------------------------------------------------------ planar chain
def planar_chain_urdf(lengths, masses, com, angle_deg, inertias):
    """NLinkArm's chain as URDF: the plane of motion is the base x-z plane (gravity along -z is
    the in-plane gravity), joints about -y so that positive angles turn x towards +z."""
    links, joints = [], []
    for i, (l, m, c, a, inertia) in enumerate(zip(lengths, masses, com, np.radians(angle_deg),
                                                  inertias)):
        links.append(f"""<link name="link{i}"><inertial>
          <origin xyz="{c * np.cos(a):.17g} 0 {c * np.sin(a):.17g}"/><mass value="{m:.17g}"/>
          <inertia ixx="0.01" ixy="0" ixz="0" iyy="{inertia:.17g}" iyz="0" izz="0.02"/>
          </inertial></link>""")
        parent = "base" if i == 0 else f"link{i - 1}"
        offset = 0.0 if i == 0 else lengths[i - 1]
        joints.append(f"""<joint name="j{i}" type="revolute"><parent link="{parent}"/>
          <child link="link{i}"/><origin xyz="{offset:.17g} 0 0"/><axis xyz="0 -1 0"/>
          <limit effort="100" velocity="10" lower="-10" upper="10"/></joint>""")
    return ('<robot name="chain"><link name="base"/>' + "".join(links) + "".join(joints)
            + "</robot>")


def test_planar_chain_agrees_with_the_shipped_n_link_blocks(tmp_path):
    lengths, masses, com = [1.0, 0.8, 0.5], [2.0, 1.0, 0.5], [0.4, 0.3, 0.2]
    angle, inertias = [0.0, 20.0, -10.0], [0.15, 0.08, 0.03]
    path = tmp_path / "chain.urdf"
    path.write_text(planar_chain_urdf(lengths, masses, com, angle, inertias))
    physical = dict(lengths=lengths, masses=masses, com=com, com_angle=angle,
                    inertias=inertias, gravity=9.81)
    arm_n = NLinkArm("n", **physical)
    reg_n = NLinkRegressor("rn", lengths=lengths, gravity=9.81)
    arm_u = URDFArm("u", urdf=str(path))
    reg_u = URDFRegressor("ru", urdf=str(path))
    theta_n, theta_u = arm_n.p.theta[0], arm_u.p.theta[0]
    for q, qdot, zeta, zetad in points(3, 5, 7):
        expected = regress(reg_n, q, qdot, zeta, zetad) @ theta_n
        np.testing.assert_allclose(regress(reg_u, q, qdot, zeta, zetad) @ theta_u, expected,
                                   rtol=0, atol=1e-10 * max(1.0, np.abs(expected).max()))
        x, tau = np.concatenate([q, qdot])[None], zetad[None]
        np.testing.assert_allclose(arm_u.derivative(0, x, (tau, 0 * tau)),
                                   arm_n.derivative(0, x, (tau, 0 * tau)), rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------ without pinocchio
def test_without_pinocchio_blocks_are_listed_with_a_hint_and_refused_in_one_line(tmp_path):
    diagram = tmp_path / "d.yaml"
    diagram.write_text(textwrap.dedent("""\
        blocks:
          arm: {type: URDFArm, robot: panda}
          tau: {type: Constant, value: [0, 0, 0, 0, 0, 0, 0]}
        connections:
          - tau.y -> arm.tau
        simulation: {t_final: 0.01, step: 0.001}
        """))
    code = ("import sys; sys.modules['pinocchio'] = None; import cli; "
            "sys.exit(cli.main(sys.argv[1:]))")
    listing = subprocess.run([sys.executable, "-c", code, "blocks"], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
    assert listing.returncode == 0
    lines = [ln for ln in listing.stdout.splitlines() if ln.startswith(("URDFArm ", "URDFReg"))]
    assert len(lines) == 2 and all(ln.endswith("[install fwdstep[robots]]") for ln in lines)
    run = subprocess.run([sys.executable, "-c", code, "run", str(diagram), "-o",
                          str(tmp_path / "out")], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2
    assert run.stderr.strip().count("\n") == 0
    assert "block 'arm' (URDFArm) needs pinocchio: install fwdstep[robots]" in run.stderr
    assert f"{diagram}:2" in run.stderr


def test_a_regressor_that_does_not_match_its_plant_is_refused_at_load_time(tmp_path):
    import fwdstep
    from fwdstep.core.errors import WiringError
    diagram = tmp_path / "mismatch.yaml"
    diagram.write_text(textwrap.dedent("""\
        blocks:
          arm: {type: URDFArm, robot: ur5, parameters: base}
          Y: {type: URDFRegressor, robot: ur5, parameters: base, gravity: 0}
          tau: {type: Constant, value: [0, 0, 0, 0, 0, 0]}
        connections:
          - tau.y -> arm.tau
          - arm.q -> Y.q
          - arm.qdot -> Y.qdot, Y.zeta, Y.zetad
        simulation: {t_final: 0.01, step: 0.001}
        """))
    with pytest.raises(WiringError) as info:
        fwdstep.load_diagram(str(diagram))
    assert str(info.value) == (
        f"{diagram}:7: connection arm.q -> Y.q: the regressor's gravity (0.0) differs from "
        "the plant's (9.81); give both blocks the same robot, locked_joints, gravity and "
        "parameters")


# ------------------------------------------------------- implementations, URDF dynamics, YAML
ROBOT_DIAGRAMS = [pytest.param(p, id=p.stem, marks=() if p.stem == "panda_slotine_li"
                               else pytest.mark.slow)
                  for p in sorted((ROOT / "diagrams" / "robots").glob("*.yaml"))]


@pytest.mark.parametrize("path", ROBOT_DIAGRAMS)
def test_robot_diagrams_give_the_same_numbers_with_kernels_and_with_pinocchio(path):
    """Every robot diagram, 20 steps on the NumPy path: fwdstep's kernels (blocks/rigid_body.py)
    and pinocchio give the same logged signals to 1e-12 of their scale."""
    import fwdstep
    results = []
    for impl in IMPLEMENTATIONS:
        overrides = {"t_final": 0.02, "arm.implementation": impl, "Y.implementation": impl}
        if path.stem == "ur5_task_space":
            overrides["tool.implementation"] = impl
        d = fwdstep.load_diagram(str(path), overrides=overrides)
        results.append(fwdstep.simulate(d))
    ref, got = results
    for name in ref.names:
        scale = max(1.0, float(np.nanmax(np.abs(ref[name]))))
        np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=1e-12 * scale,
                                   err_msg=name)


def test_auto_runs_pinocchio_for_small_batches_and_the_kernels_for_large_ones(monkeypatch):
    from fwdstep.blocks import urdf
    arm = URDFArm("arm", robot="ur5")
    assert arm.implementation == "auto"
    assert not urdf._uses_kernels("auto", urdf.KERNELS_FROM_BATCH - 1)
    assert urdf._uses_kernels("auto", urdf.KERNELS_FROM_BATCH)
    assert urdf._uses_kernels("kernels", 1) and not urdf._uses_kernels("pinocchio", 10 ** 6)


def _urdf_with_dynamics(path, damping, friction):
    path.write_text(textwrap.dedent(f"""\
        <?xml version="1.0"?>
        <robot name="pendulum2">
          <link name="base"/>
          <link name="l1"><inertial><origin xyz="0.3 0 0"/><mass value="1.5"/>
            <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.03"/></inertial></link>
          <link name="l2"><inertial><origin xyz="0.2 0.01 0"/><mass value="0.7"/>
            <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
          <joint name="a" type="revolute"><parent link="base"/><child link="l1"/>
            <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="5" velocity="3"/>
            <dynamics damping="{damping[0]}" friction="{friction[0]}"/></joint>
          <joint name="b" type="revolute"><parent link="l1"/><child link="l2"/>
            <origin xyz="0.6 0 0"/><axis xyz="0 1 0"/>
            <limit lower="-3" upper="3" effort="5" velocity="3"/>
            <dynamics damping="{damping[1]}" friction="{friction[1]}"/></joint>
        </robot>
        """))
    return str(path)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_urdf_damping_and_friction_act_through_the_friction_law(tmp_path, implementation):
    """<dynamics damping= friction=> are the plant's viscous and Coulomb friction (the law
    of the Friction block: tau_f = -(F_c tanh(qdot / v_s) + F_v qdot)) unless given."""
    from fwdstep.blocks.nonlinear import Friction
    path = _urdf_with_dynamics(tmp_path / "p.urdf", (0.2, 0.05), (0.4, 0.1))
    model = pin.buildModelFromUrdf(path)
    model.gravity.linear = np.array([0.0, 0.0, -9.81])
    data = model.createData()
    arm = URDFArm("arm", urdf=path, coulomb_velocity=0.05, implementation=implementation)
    law = Friction("f", n=2, coulomb=[0.4, 0.1], viscous=[0.2, 0.05], velocity_scale=0.05)
    for q, v, tau, _ in points(2, 4, 9):
        dx = arm.derivative(0.0, np.concatenate([q, v])[None], (tau[None], np.zeros((1, 2))))
        tau_f = law.output(0.0, np.zeros((1, 2)), (v[None],))[0][0]
        np.testing.assert_allclose(tau_f, -(np.array([0.4, 0.1]) * np.tanh(v / 0.05)
                                            + np.array([0.2, 0.05]) * v), rtol=1e-15)
        np.testing.assert_allclose(dx[0, 2:], pin.aba(model, data, q, v, tau + tau_f),
                                   rtol=0, atol=1e-12)
    none = URDFArm("arm", urdf=path, damping=0, coulomb=0, implementation=implementation)
    q, v, tau, _ = next(points(2, 1, 9))
    np.testing.assert_allclose(none.derivative(0.0, np.concatenate([q, v])[None],
                                               (tau[None], np.zeros((1, 2))))[0, 2:],
                               pin.aba(model, data, q, v, tau), rtol=0, atol=1e-12)


def test_the_panda_urdf_damping_is_honoured():
    arm = URDFArm("arm", robot="panda")
    np.testing.assert_array_equal(arm.p.viscous[0], [0.003] * 7)
    np.testing.assert_array_equal(arm.p.coulomb[0], [0.0] * 7)


def test_locked_joints_are_written_in_yaml(tmp_path):
    """``locked_joints: [name]`` and ``locked_joints: []`` are lists of names, not
    expressions; the Panda's mimic finger must stay locked (one line)."""
    import fwdstep
    from fwdstep.core.errors import DiagramError

    def diagram(locked):
        path = tmp_path / "d.yaml"
        n = 9 if locked == "[]" else 8
        path.write_text(textwrap.dedent(f"""\
            blocks:
              arm: {{type: URDFArm, robot: panda, locked_joints: {locked}}}
              tau: {{type: Constant, value: "zeros({n})"}}
            connections:
              - tau.y -> arm.tau
            simulation: {{t_final: 0.002, step: 0.001}}
            """))
        return str(path)
    d = fwdstep.load_diagram(diagram("[panda_finger_joint2]"))
    arm = next(s.block for s in d.schedule if s.block.name == "arm")
    assert arm.outputs["q"].shape == (8,)
    with pytest.raises(DiagramError, match="block 'arm': the robot's joint 'panda_finger_joint2' "
                                           "mimics 'panda_finger_joint1'"):
        fwdstep.load_diagram(diagram("[]"))


@pytest.mark.parametrize("name", ["panda_slotine_li", "ur5_theorem1"])
def test_robot_diagrams_trace_to_a_scalar_stage(name):
    """Compiled runs of the robot diagrams are straight-line code (the kernels traced, the
    robot's structure folded in), not calls of pinocchio in object mode."""
    pytest.importorskip("numba")
    import llvmlite.binding as llvm

    import fwdstep
    from fwdstep.compiled import backend_numba as bn
    from fwdstep.run.finite import unlogged_signals
    from fwdstep.compiled.llvm_stage import stage_ir
    d = fwdstep.load_diagram(str(ROOT / "diagrams" / "robots" / f"{name}.yaml"))
    shapes = [tuple(s) for s in d.signal_shapes]
    ops, fused = bn._ops_for(d.schedule, shapes, d.constant_signals)
    st = bn._ScalarStage(d, shapes, ops, fused, d.constant_signals,
                         [d.signal_index[n] for n in d.logged], unlogged_signals(d), 4)
    assert 1000 < st.n_nodes < 8000
    llvm.parse_assembly(stage_ir(st)).verify()


def test_urdf_frame_block_is_pinocchio_s_task_space_kinematics():
    from fwdstep.blocks.urdf import URDFFrame
    model, data = reference_model("ur5")
    fid = model.getFrameId("tool0")
    blk = URDFFrame("ee", robot="ur5", frame="tool0", implementation="kernels")
    assert blk.outputs["J"].shape == (6, 6)
    assert blk.feedthrough("position") == ("q",)
    for q, v, _, _ in points(6, 3, 11):
        pos, rot, J, bias = (y[0] for y in blk.output(0.0, None, (q[None], v[None])))
        pin.forwardKinematics(model, data, q, v, np.zeros(6))
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, q)
        np.testing.assert_allclose(pos, data.oMf[fid].translation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rot, data.oMf[fid].rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(J, pin.getFrameJacobian(model, data, fid,
                                                           pin.LOCAL_WORLD_ALIGNED),
                                   rtol=0, atol=1e-12)
        acc = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(bias, np.concatenate([acc.linear, acc.angular]), rtol=0,
                                   atol=1e-12 * max(1.0, np.abs(bias).max()))
    with pytest.raises(ParameterError, match="^block 'ee' parameter 'frame': the robot has "
                                             "no frame 'hand' on a moving body; frames are: "):
        URDFFrame("ee", robot="ur5", frame="hand")
