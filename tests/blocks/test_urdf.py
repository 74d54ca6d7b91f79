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
from fwdstep.errors import ParameterError  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ("panda", "ur5")


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
@pytest.mark.parametrize("robot", ROBOTS)
def test_plant_accelerations_are_pinocchio_aba_with_friction(robot):
    model, data = reference_model(robot)
    n = model.nv
    arm = URDFArm("arm", robot=robot, damping=0.3, coulomb=[0.5] * n, coulomb_velocity=0.1)
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
    q, qdot, theta = arm.output(0.0, x[:1], (tau[:1], np.zeros((1, 6))))
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
@pytest.mark.parametrize("robot", ROBOTS)
def test_regressor_is_H_zetad_plus_C_zeta_plus_g(robot):
    model, data = reference_model(robot)
    n = model.nv
    Y = URDFRegressor("Y", robot=robot)
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
    from fwdstep.errors import WiringError
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
