"""blocks/rigid_body.py (fwdstep's own rigid-body algorithms) against pinocchio's, on the
shipped robots (Panda, UR5) and on generated URDFs with revolute and prismatic joints about
unaligned axes (a chain and a branching tree); batches against single evaluations; and the
kernels traced by fwdstep.compiled.scalarize against the kernels run by NumPy."""
import textwrap

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio", reason="pinocchio is the reference (fwdstep[robots])")

from fwdstep.blocks import rigid_body as rb  # noqa: E402
from fwdstep.blocks.urdf import NAMED_ROBOTS, _base_reduction, _robots_folder  # noqa: E402

TOL = 1e-12


def _link(name, mass, com, rpy, inertia):
    ixx, ixy, ixz, iyy, iyz, izz = inertia
    return f"""
      <link name="{name}">
        <inertial>
          <origin xyz="{com}" rpy="{rpy}"/>
          <mass value="{mass}"/>
          <inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/>
        </inertial>
      </link>"""


def _joint(name, kind, parent, child, xyz, rpy, axis):
    limit = '<limit lower="-1" upper="1" effort="10" velocity="2"/>'
    return f"""
      <joint name="{name}" type="{kind}">
        <parent link="{parent}"/><child link="{child}"/>
        <origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>{limit}
      </joint>"""


def generated_urdf(path, tree: bool) -> str:
    """A small robot: revolute and prismatic joints, aligned and unaligned axes, rotated
    placements and inertia frames; ``tree``: joint j4 branches off link 1."""
    links = [_link("base", 1.0, "0 0 0", "0 0 0", (1, 0, 0, 1, 0, 1))]
    links += [_link(f"l{i}", 0.5 + 0.3 * i, f"0.0{i} -0.02 0.1{i}", f"0.{i} -0.2 0.3",
                    (0.02 * i, 0.001, -0.002, 0.03, 0.0015, 0.01 * i + 0.01))
              for i in range(1, 6)]
    joints = [
        _joint("j1", "revolute", "base", "l1", "0 0 0.3", "0 0 0", "0 0 1"),
        _joint("j2", "prismatic", "l1", "l2", "0.1 0.2 0", "0.3 -0.2 0.5", "0.6 0 0.8"),
        _joint("j3", "revolute", "l2", "l3", "0 0 0.4", "1.5707963267948966 0 0", "0 1 0"),
        _joint("j4", "revolute", "l1" if tree else "l3", "l4", "-0.1 0 0.2", "0 0 0",
               "0.2 0.3 -0.9"),
        _joint("j5", "prismatic", "l4", "l5", "0 0.1 0.1", "0 0.4 0", "1 0 0"),
    ]
    text = textwrap.dedent(f"""\
        <?xml version="1.0"?>
        <robot name="generated">{''.join(links)}{''.join(joints)}
        </robot>
        """)
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module", params=["panda", "ur5", "chain", "tree"])
def robot(request, tmp_path_factory):
    """(pinocchio model with gravity 9.81, its data, structure (1, n, 17), theta (1, 10 n),
    path, locked joints)."""
    if request.param in NAMED_ROBOTS:
        relative, locked = NAMED_ROBOTS[request.param]
        path = str(_robots_folder("test") / relative)
    else:
        path = generated_urdf(tmp_path_factory.mktemp("urdf") / "robot.urdf",
                              request.param == "tree")
        locked = ()
    model = pin.buildModelFromUrdf(path)
    if locked:
        model = pin.buildReducedModel(model, [model.getJointId(j) for j in locked],
                                      pin.neutral(model))
    model.gravity.linear = np.array([0.0, 0.0, -9.81])
    return (model, model.createData(), rb.tree_from_pinocchio(model)[None],
            rb.theta_from_pinocchio(model)[None], path, tuple(locked))


G = np.array([[9.81]])


def states(n, count=4, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        yield rng.uniform(-1.0, 1.0, n), *(2.0 * rng.standard_normal((4, n)))


def close(got, want):
    scale = max(1.0, float(np.max(np.abs(want))))
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL * scale)


def pinocchio_regressor(model, q, v, zeta, zetad):
    """Y theta = H zetad + C zeta + g by polarisation of pinocchio's joint-torque regressor
    (docs/urdf-regressor.md)."""
    model0 = model.copy()
    model0.gravity.linear = np.zeros(3)
    plus = pin.computeJointTorqueRegressor(model, model.createData(), q, 0.5 * (v + zeta),
                                           zetad)
    minus = pin.computeJointTorqueRegressor(model0, model0.createData(), q, 0.5 * (v - zeta),
                                            np.zeros_like(q))
    return plus - minus


def test_structure_is_read_from_the_model(robot):
    model, _, tree, theta, _, _ = robot
    assert tree.shape == (1, model.nv, rb.STRUCTURE_WIDTH)
    assert theta.shape == (1, 10 * model.nv)
    assert tree[0, :, 0].tolist() == [float(model.parents[i] - 1)
                                      for i in range(1, model.njoints)]


def test_forward_kinematics_is_pinocchio_s(robot):
    model, data, tree, _, _, _ = robot
    for q, *_ in states(model.nv):
        pin.forwardKinematics(model, data, q)
        pos, rot = rb.frame_placements(tree, q[None])
        for i in range(model.nv):
            close(pos[0, i], data.oMi[i + 1].translation)
            close(rot[0, i], data.oMi[i + 1].rotation)


def test_inverse_dynamics_mass_matrix_and_gravity_are_pinocchio_s(robot):
    model, data, tree, theta, _, _ = robot
    for q, v, a, _, _ in states(model.nv):
        close(rb.rnea(tree, G, theta, q[None], v[None], a[None])[0],
              pin.rnea(model, data, q, v, a))
        H = pin.crba(model, data, q)
        close(rb.mass_matrix(tree, theta, q[None])[0], np.triu(H) + np.triu(H, 1).T)
        close(rb.gravity_torque(tree, G, theta, q[None])[0],
              pin.computeGeneralizedGravity(model, data, q))


def test_forward_dynamics_is_pinocchio_aba(robot):
    model, data, tree, theta, _, _ = robot
    for q, v, tau, _, _ in states(model.nv):
        close(rb.forward_dynamics(tree, G, theta, q[None], v[None], tau[None])[0],
              pin.aba(model, data, q, v, tau))


def test_regressor_is_pinocchio_s_and_gives_H_C_g(robot):
    """Y (all columns) equals pinocchio's polarised regressor, and Y theta equals
    H zetad + C zeta + g with pinocchio's crba, computeCoriolisMatrix (the Christoffel C)
    and gravity; C from Y alone, column by column, equals pinocchio's C."""
    model, data, tree, theta, _, _ = robot
    n = model.nv
    cols = np.arange(10 * n, dtype=float)[None]
    for q, v, zeta, zetad, _ in states(n):
        Y = rb.regressor(tree, G, cols, q[None], v[None], zeta[None], zetad[None])[0]
        close(Y, pinocchio_regressor(model, q, v, zeta, zetad))
        H = pin.crba(model, data, q)
        H = np.triu(H) + np.triu(H, 1).T
        C = pin.computeCoriolisMatrix(model, data, q, v).copy()
        g = pin.computeGeneralizedGravity(model, data, q)
        close(Y @ theta[0], H @ zetad + C @ zeta + g)
        eye = np.eye(n)
        YC = rb.regressor(tree, G, cols, np.repeat(q[None], n, 0), np.repeat(v[None], n, 0),
                          eye, np.zeros((n, n)))
        close((YC @ theta[0]).T - g[:, None], C)


def test_base_regressor_is_the_independent_columns(robot):
    """Y_base (the kernel given the base columns) equals pinocchio's regressor's columns, and
    Y_base beta = Y theta with the base parameters beta."""
    model, _, tree, theta, path, locked = robot
    n = model.nv
    base, rest, K = _base_reduction(path, locked, 9.81)
    beta = theta[0, base] + K @ theta[0, rest]
    for q, v, zeta, zetad, _ in states(n):
        Yb = rb.regressor(tree, G, base[None].astype(float), q[None], v[None], zeta[None],
                          zetad[None])[0]
        Y = pinocchio_regressor(model, q, v, zeta, zetad)
        close(Yb, Y[:, base])
        close(Yb @ beta, Y @ theta[0])


def test_a_batch_equals_its_variants_one_by_one(robot):
    """Batches of 5 states, parameters shared or per variant: every variant bit for bit its
    own single evaluation."""
    model, _, tree, theta, _, _ = robot
    n = model.nv
    rng = np.random.default_rng(4)
    q, v, z, zd, tau = rng.standard_normal((5, 5, n))
    thetas = theta * rng.uniform(0.5, 1.5, (5, 1))
    cols = np.arange(10 * n, dtype=float)[None]
    batch = [rb.forward_dynamics(tree, G, thetas, q, v, tau),
             rb.regressor(tree, G, cols, q, v, z, zd),
             rb.mass_matrix(tree, theta, q)]
    for b in range(5):
        s = slice(b, b + 1)
        one = [rb.forward_dynamics(tree, G, thetas[s], q[s], v[s], tau[s]),
               rb.regressor(tree, G, cols, q[s], v[s], z[s], zd[s]),
               rb.mass_matrix(tree, theta, q[s])]
        for got, want in zip(batch, one):
            np.testing.assert_array_equal(got[b], want[0])


FRAMES = {"panda": "panda_hand", "ur5": "tool0"}


def test_frame_pose_jacobian_and_jdot_qdot_are_pinocchio_s(robot):
    """A frame of the last body (the Panda's hand, the UR5's tool0, link l5): position,
    rotation, LOCAL_WORLD_ALIGNED Jacobian and classical acceleration at qddot = 0."""
    model, data, tree, _, path, _ = robot
    n = model.nv
    name = next((f for r, f in FRAMES.items() if r in path), "l5")
    frame = rb.frame_from_pinocchio(model, name)[None]
    fid = model.getFrameId(name)
    for q, v, *_ in states(n):
        pin.forwardKinematics(model, data, q, v, np.zeros(n))
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, q)
        pos, rot, J, bias = rb.frame_kinematics(tree, frame, q[None], v[None])
        close(pos[0], data.oMf[fid].translation)
        close(rot[0], data.oMf[fid].rotation)
        close(J[0], pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED))
        acc = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        close(bias[0], np.concatenate([acc.linear, acc.angular]))


# ------------------------------------------------------------------------------ tracing
frame_placements = rb.frame_placements


def fk_positions(tree, q):
    return frame_placements(tree, q)[0]


def fk_rotations(tree, q):
    return frame_placements(tree, q)[1]


def _traced(fn, args, invariant):
    """fn run by fwdstep.compiled.scalarize on leaves holding args' values (parameters invariant),
    its graph evaluated at those values."""
    sz = pytest.importorskip("fwdstep.compiled.scalarize")
    tr = sz.Trace(max_nodes=50000)
    leaves = []
    for k, a in enumerate(args):
        out = np.empty(a.shape, dtype=object)
        for idx in np.ndindex(*a.shape):
            out[idx] = tr.leaf(f"a{k}_{'_'.join(map(str, idx))}", invariant[k], [a[idx]])
        leaves.append(out)
    result = sz.run_traced(sz.Rebinder(tr), fn, *leaves)
    nodes = sz.as_nodes(tr, result, np.shape(fn(*args)))
    return np.vectorize(lambda s: float(np.asarray(tr.evaluate(s)).reshape(-1)[0]),
                        otypes=[float])(nodes), len(tr.nodes)


def test_the_kernels_trace_and_the_graph_is_the_kernel(robot):
    """The scalar stage's view of the kernels (fwdstep.compiled.scalarize: the structure folded in,
    the joint loops unrolled) computes what NumPy computes, in a few thousand nodes."""
    pytest.importorskip("numba")             # the tracer imports fwdstep.compiled.compiled_ops
    model, _, tree, theta, _, _ = robot
    n = model.nv
    q, v, z, zd, _ = next(states(n, seed=7))
    cols = np.arange(10 * n, dtype=float)[None]
    cases = [(rb.regressor, (tree, G, cols, q[None], v[None], z[None], zd[None]),
              (True, True, True, False, False, False, False)),
             (rb.forward_dynamics, (tree, G, theta, q[None], v[None], z[None]),
              (True, True, True, False, False, False)),
             (fk_positions, (tree, q[None]), (True, False)),
             (fk_rotations, (tree, q[None]), (True, False))]
    for fn, args, invariant in cases:
        got, nodes = _traced(fn, args, invariant)
        close(got, fn(*args))
        assert nodes < 6000, (fn.__name__, nodes)


def test_non_revolute_or_prismatic_joints_are_refused_by_name():
    model = pin.Model()
    model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    with pytest.raises(ValueError, match="joint 'ball' is a JointModelSpherical: only "
                                         "revolute and prismatic joints are supported"):
        rb.tree_from_pinocchio(model)
