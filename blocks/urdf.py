"""Serial manipulators from URDF (pinocchio): the plant of eq. (1) and its regressor (Property 3).

Both blocks describe the robot the same way, through ``robot`` (an example-robot-data name:
``panda``, ``ur5``) or ``urdf`` (a file), ``locked_joints`` and ``gravity``; ``load_model`` turns
that description into a pinocchio model, once (cached).  The parameter vector theta holds, per
moving body, pinocchio's 10 dynamic parameters [m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz,
I_yz, I_zz] (inertia about the joint frame's origin), or the base parameters (an identifiable
reduction; ``parameters: base``).  The derivation of the regressor is in docs/urdf-regressor.md.

pinocchio (PyPI ``pin``) and ``example-robot-data`` are the optional extra ``fwdstep[robots]``:
without them this module still imports and registers its blocks (``fwdstep blocks`` lists them
with an install hint), and building one raises a one-line ParameterError.  pinocchio's calls
cannot run inside numba-compiled code: the compiled backend calls these blocks' methods through
numba's object mode (``compile_with = "objmode"``, fwdstep/core/block.py).
"""
from __future__ import annotations

import functools
import os

import numpy as np

from fwdstep.core.block import Block, Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register

from .robot import MechanicalPlant

INSTALL_HINT = "install fwdstep[robots]"

#: example-robot-data models: URDF path under the package's ``robots`` folder and the joints
#: locked by default (the Panda's gripper fingers: the arm has 7 joints).
NAMED_ROBOTS = {
    "panda": ("panda_description/urdf/panda.urdf",
              ("panda_finger_joint1", "panda_finger_joint2")),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", ()),
}

#: parameters per body, in pinocchio's ``Inertia.toDynamicParameters`` order
BODY_PARAMETERS = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


def _pinocchio(block_name: str, type_name: str):
    try:
        import pinocchio
    except ImportError:
        raise ParameterError(f"block {block_name!r} ({type_name}) needs pinocchio: "
                             f"{INSTALL_HINT}", block=block_name) from None
    return pinocchio


def available() -> bool:
    """True when pinocchio can be imported."""
    try:
        import pinocchio  # noqa: F401
    except ImportError:
        return False
    return True


def _robots_folder(block_name: str):
    from importlib import metadata
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        raise ParameterError(f"block {block_name!r}: named robots need example-robot-data: "
                             f"{INSTALL_HINT}", block=block_name) from None
    return dist.locate_file("cmeel.prefix/share/example-robot-data/robots")


def _description(block, robot: str, urdf: str, locked_joints):
    """(urdf path, locked joint names) from the block parameters, checked."""
    name = block.name
    if bool(robot) == bool(urdf):
        raise ParameterError(f"block {name!r} needs exactly one of 'robot' (one of "
                             f"{', '.join(NAMED_ROBOTS)}) and 'urdf' (a file)", block=name)
    if robot:
        if robot not in NAMED_ROBOTS:
            raise ParameterError(f"block {name!r} parameter 'robot' must be one of "
                                 f"{', '.join(NAMED_ROBOTS)}, got {robot!r}", block=name)
        relative, default_locked = NAMED_ROBOTS[robot]
        path = str(_robots_folder(name) / relative)
    else:
        path, default_locked = os.path.abspath(os.path.expanduser(urdf)), ()
        if not os.path.isfile(path):
            raise ParameterError(f"block {name!r} parameter 'urdf': no file {urdf!r}",
                                 block=name)
    if locked_joints is None:
        locked = tuple(default_locked)
    elif isinstance(locked_joints, (list, tuple)) and all(isinstance(j, str)
                                                            for j in locked_joints):
        locked = tuple(locked_joints)
    else:
        raise ParameterError(f"block {name!r} parameter 'locked_joints' must be a list of "
                             f"joint names, got {locked_joints!r}", block=name)
    return path, locked


@functools.lru_cache(maxsize=32)
def _load(path: str, locked: tuple, gravity: float):
    """(model, data, model without gravity, its data): joints in ``locked`` fixed at the
    neutral configuration; or a message saying why not.  The data objects are scratch space
    every pinocchio call fills anew, shared by all blocks of one robot (so variants of a sweep
    that differ only in numbers batch together)."""
    import pinocchio as pin
    try:
        full = pin.buildModelFromUrdf(path)
    except (RuntimeError, ValueError) as exc:
        return f"cannot read URDF {path!r}: {str(exc).splitlines()[0] if str(exc) else exc}"
    unknown = [j for j in locked if not full.existJointName(j)]
    if unknown:
        names = ", ".join(full.names[1:])
        return f"has no joint {unknown[0]!r} to lock; joints are: {names}"
    if locked:
        ids = [full.getJointId(j) for j in locked]
        model = pin.buildReducedModel(full, ids, pin.neutral(full))
    else:
        model = full
    if model.nq != model.nv or model.nv != model.njoints - 1:
        return ("is not a chain of 1-degree-of-freedom joints (revolute or prismatic; "
                "continuous and floating joints are not supported)")
    if model.nv < 1:
        return "has no moving joint"
    data = model.createData()
    H = pin.crba(model, data, pin.neutral(model))
    try:
        np.linalg.cholesky(np.triu(H) + np.triu(H, 1).T)
    except np.linalg.LinAlgError:
        return ("has an inertia matrix that is not positive definite (massless links? check "
                "the URDF's <inertial> elements)")
    model.gravity.linear = np.array([0.0, 0.0, -gravity])
    model_no_gravity = model.copy()
    model_no_gravity.gravity.linear = np.zeros(3)
    return model, data, model_no_gravity, model_no_gravity.createData()


def load_model(block, robot: str, urdf: str, locked_joints, gravity: float):
    """(model, data, model without gravity, its data) for a block's robot description, which
    is kept in ``block.robot_description`` (compared between plant and regressor)."""
    _pinocchio(block.name, block.type_name)
    path, locked = _description(block, robot, urdf, locked_joints)
    block.robot_description = (path, locked, float(gravity))
    loaded = _load(path, locked, float(gravity))
    if isinstance(loaded, str):
        raise ParameterError(f"block {block.name!r}: the robot {loaded}", block=block.name)
    return loaded


def true_parameters(model) -> np.ndarray:
    """theta (10 per moving body): pinocchio's dynamic parameters of each body's inertia."""
    return np.concatenate([model.inertias[j].toDynamicParameters()
                           for j in range(1, model.njoints)])


def regressor(pin, model, data, model0, data0, q, qdot, zeta, zetad) -> np.ndarray:
    """Y (n, 10 n) with Y theta = H zetad + C(q, qdot) zeta + g, C the Christoffel matrix:

        Y = R_g(q, (qdot + zeta)/2, zetad) - R_0(q, (qdot - zeta)/2, 0)

    where R_g(q, v, a) is pinocchio's joint-torque regressor (R_g theta = H a + C(q, v) v + g)
    and R_0 the same without gravity (docs/urdf-regressor.md, eq. (R))."""
    half_sum = qdot + zeta
    half_sum *= 0.5
    half_difference = qdot - zeta
    half_difference *= 0.5
    plus = pin.computeJointTorqueRegressor(model, data, q, half_sum, zetad)
    minus = pin.computeJointTorqueRegressor(model0, data0, q, half_difference, 0.0 * zetad)
    return plus - minus


@functools.lru_cache(maxsize=32)
def _base_reduction(path: str, locked: tuple, gravity: float):
    """(independent columns, K) such that Y theta = Y[:, cols] (theta[cols] + K theta[rest])
    for every (q, qdot, zeta, zetad): the base parameters beta = theta[cols] + K theta[rest].
    Found numerically from regressor samples at seeded random points (column-pivoted
    Gram-Schmidt with a relative tolerance)."""
    import pinocchio as pin
    model, data, model0, data0 = _load(path, locked, gravity)
    n = model.nv
    rng = np.random.default_rng(12345)
    lower = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.pi)
    upper = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.pi)
    rows = []
    for _ in range(max(20, 4 * n)):
        q = rng.uniform(np.maximum(lower, -np.pi), np.minimum(upper, np.pi))
        qdot, zeta, zetad = rng.standard_normal((3, n))
        rows.append(regressor(pin, model, data, model0, data0, q, qdot, zeta, zetad))
    W = np.vstack(rows)
    scale = np.linalg.norm(W, axis=0)
    tol = 1e-9 * max(scale.max(), 1.0)
    cols = []
    basis = np.zeros((W.shape[0], 0))
    for j in np.argsort(-scale, kind="stable"):
        if scale[j] <= tol:
            continue
        w = W[:, j] - basis @ (basis.T @ W[:, j])
        w = w - basis @ (basis.T @ w)
        norm = np.linalg.norm(w)
        if norm > 1e-8 * scale[j]:
            cols.append(j)
            basis = np.column_stack([basis, w / norm])
    cols = np.array(sorted(cols))
    rest = np.setdiff1d(np.arange(W.shape[1]), cols)
    K = np.linalg.lstsq(W[:, cols], W[:, rest], rcond=None)[0]
    K[np.abs(K) < 1e-10] = 0.0
    return cols, rest, K


def _robot_params():
    return {
        "robot": Param("str", "", "example-robot-data model: " + ", ".join(NAMED_ROBOTS)),
        "urdf": Param("str", "", "URDF file (absolute, or relative to the working directory); "
                                 "instead of 'robot'"),
        "locked_joints": Param("any", None, "joint names fixed at the neutral configuration "
                                            "(default: the named robot's, e.g. the Panda's "
                                            "fingers; [] for none)"),
        "gravity": Param("float", 9.81, "gravitational acceleration along -z of the base "
                                        "frame (m/s^2); 0: no gravity"),
        "parameters": Param("choice", "full", "theta: 'full' (10 per body) or 'base' (the "
                                              "identifiable reduction)",
                            choices=("full", "base")),
    }


def _parameter_form(block, model, robot, urdf, locked_joints, gravity, parameters):
    """theta in the block's form and the reduction (None for 'full')."""
    theta = true_parameters(model)
    if parameters == "full":
        return theta, None
    path, locked = _description(block, robot, urdf, locked_joints)
    cols, rest, K = _base_reduction(path, locked, float(gravity))
    return theta[cols] + K @ theta[rest], cols


def _summary_with_hint(cls) -> str:
    summary = Block.summary.__func__(cls)
    return summary if available() else f"{summary} [{INSTALL_HINT}]"


@register
class URDFArm(MechanicalPlant):
    """Serial manipulator from URDF: H(q) qddot + C(q, qdot) qdot + g(q) = tau + tau_star - tau_f.

    Equation (1) of the paper for any fixed-base chain of revolute/prismatic joints, computed by
    pinocchio's articulated-body algorithm: qddot = aba(q, qdot, tau + tau_star - tau_f), with
    joint friction tau_f = damping qdot + coulomb tanh(qdot / coulomb_velocity) (zero by
    default; not part of the regressor).  The joints in ``locked_joints`` are fixed at the
    neutral configuration and their bodies merged into their parents.  Output ``theta`` is the
    robot's true parameter vector (constant), in the form of ``URDFRegressor`` with the same
    ``parameters``, so a diagram can plot theta_hat against it.  ``tau_star`` is optional:
    unconnected, it is zero.  State order: q (n), then qdot (n).  Compiled runs call it in
    numba's object mode (pinocchio).

    Equation: (1), qddot = H^-1 (tau + tau_star - tau_f - C qdot - g) by pinocchio.aba.

    Ports:
        | port     | direction | shape | feedthrough |
        | tau      | in        | (n,)  | -           |
        | tau_star | in        | (n,)  | -           |
        | q        | out       | (n,)  | -           |
        | qdot     | out       | (n,)  | -           |
        | theta    | out       | (p,)  | -           |

    Parameters:
        robot: example-robot-data model (panda: 7 joints, fingers locked; ur5: 6 joints), or
        urdf: a URDF file.
        locked_joints: joints to fix (default: the named robot's; [] for none).
        gravity: gravitational acceleration along -z of the base frame (default 9.81).
        parameters: 'full' (p = 10 n) or 'base' (identifiable reduction) for ``theta``.
        damping, coulomb: viscous (N m s/rad) and Coulomb (N m) friction, one number or n.
        coulomb_velocity: velocity scale of the smoothed Coulomb term (rad/s, default 0.01).
        q0, qdot0: initial joint positions and velocities (one number or n numbers).
    """

    params = {
        **_robot_params(),
        "damping": Param("array", 0.0, "viscous joint friction (N m s/rad): scalar or (n,)"),
        "coulomb": Param("array", 0.0, "Coulomb joint friction (N m): scalar or (n,)"),
        "coulomb_velocity": Param("float", 0.01, "velocity scale of tanh in the Coulomb term"),
        "q0": Param("array", 0.0, "initial joint positions, scalar or (n,)"),
        "qdot0": Param("array", 0.0, "initial joint velocities, scalar or (n,)"),
    }
    example = {"robot": "ur5", "q0": [0.1, -1.0, 1.2, 0.0, 0.5, 0.0], "damping": 0.1}
    summary = classmethod(_summary_with_hint)
    compile_with = "objmode"        # pinocchio: the compiled loop calls output/derivative

    def setup(self, robot, urdf, locked_joints, gravity, parameters, damping, coulomb,
              coulomb_velocity, q0, qdot0):
        from .robot import _vector_param
        self._pin = _pinocchio(self.name, self.type_name)
        self.model, self._data, _, _ = load_model(self, robot, urdf, locked_joints, gravity)
        n = self.model.nv
        self.declare_plant(n, q0, qdot0)
        self.kernels = None          # output/derivative below (pinocchio), not the base's
        self.state_labels = [f"q_{j}" for j in self.model.names[1:]] + \
                            [f"qdot_{j}" for j in self.model.names[1:]]
        theta, _ = _parameter_form(self, self.model, robot, urdf, locked_joints, gravity,
                                   parameters)
        self.declare_output("theta", theta.shape, feedthrough=(), label=r"$\theta$")
        self.parameter_form = parameters
        self.set_param("theta", theta)
        if coulomb_velocity <= 0.0:
            raise ParameterError(f"block {self.name!r} parameter 'coulomb_velocity' must be "
                                 f"positive, got {coulomb_velocity}", block=self.name)
        damping = _vector_param(self, "damping", damping, n)
        coulomb = _vector_param(self, "coulomb", coulomb, n)
        if np.any(damping < 0.0) or np.any(coulomb < 0.0):
            raise ParameterError(f"block {self.name!r} parameters 'damping' and 'coulomb' must "
                                 f"not be negative", block=self.name)
        self._damping, self._coulomb = damping, coulomb
        self._friction = bool(np.any(damping) or np.any(coulomb))
        self._coulomb_velocity = coulomb_velocity

    def output(self, t, x, u):
        n = self._n
        return x[:, :n], x[:, n:], self.p.theta

    def friction(self, qdot: np.ndarray) -> np.ndarray:
        """tau_f = damping qdot + coulomb tanh(qdot / coulomb_velocity)."""
        return self._damping * qdot + self._coulomb * np.tanh(qdot / self._coulomb_velocity)

    def derivative(self, t, x, u):
        n = self._n
        torque = u[0] + u[1]
        B = max(x.shape[0], torque.shape[0])
        if B > 1:
            x = np.broadcast_to(x, (B, 2 * n))
            torque = np.broadcast_to(torque, (B, n))
        if self._friction:
            torque = torque - self.friction(x[:, n:])
        dx = np.empty((B, 2 * n))
        dx[:, :n] = x[:, n:]
        aba, model, data = self._pin.aba, self.model, self._data
        for b in range(B):
            dx[b, n:] = aba(model, data, x[b, :n], x[b, n:], torque[b])
        return dx


@register
class URDFRegressor(Block):
    """URDF-arm regressor Y(q, qdot, zeta, zetad) with H zetad + C(q, qdot) zeta + g = Y theta.

    Property 3 of the paper for ``URDFArm`` (same ``robot``/``urdf``, ``locked_joints``,
    ``gravity``), with C the Christoffel-symbol Coriolis matrix (so Hdot - 2C is
    skew-symmetric, Property 2; it equals pinocchio's computeCoriolisMatrix).  Built from
    pinocchio's joint-torque regressor R(q, v, a) (R theta = H a + C(q, v) v + g) by
    polarization (docs/urdf-regressor.md, eq. (R)):

        Y = R_g(q, (qdot + zeta)/2, zetad) - R_0(q, (qdot - zeta)/2, 0),

    R_0 without gravity.  theta holds 10 parameters per moving body ([m, m c, inertia about
    the joint origin], ``URDFArm``'s ``theta`` output); many are not identifiable (columns of Y
    that vanish or are combinations of others): ``parameters: base`` keeps the independent
    columns and the plant's ``theta`` becomes the base parameters beta with Y_base beta = Y theta.
    Compiled runs call it in object mode (pinocchio).

    Equation: Property 3, Y theta = H zetad + C zeta + g (docs/urdf-regressor.md, eq. (R)).

    Ports:
        | port  | direction | shape  | feedthrough          |
        | q     | in        | (n,)   | -                    |
        | qdot  | in        | (n,)   | -                    |
        | zeta  | in        | (n,)   | -                    |
        | zetad | in        | (n,)   | -                    |
        | Y     | out       | (n, p) | q, qdot, zeta, zetad |

    Parameters:
        robot / urdf, locked_joints, gravity: the plant's (see ``URDFArm``).
        parameters: 'full' (p = 10 n) or 'base' (p = number of base parameters).
    """

    params = _robot_params()
    example = {"robot": "ur5"}
    summary = classmethod(_summary_with_hint)
    compile_with = "objmode"        # pinocchio: the compiled loop calls output/derivative

    def setup(self, robot, urdf, locked_joints, gravity, parameters):
        self._pin = _pinocchio(self.name, self.type_name)
        self.model, self._data, self.model0, self._data0 = load_model(self, robot, urdf,
                                                                      locked_joints, gravity)
        n = self._n = self.model.nv
        theta, self._columns = _parameter_form(self, self.model, robot, urdf, locked_joints,
                                               gravity, parameters)
        for name in ("q", "qdot", "zeta", "zetad"):
            self.declare_input(name, (n,))
        self.declare_output("Y", (n, theta.size), feedthrough=("q", "qdot", "zeta", "zetad"))
        self.parameter_form = parameters

    def check_source(self, port, source, source_port):
        """At load time: the plant driving ``q`` must be the same robot, with the same locked
        joints, gravity and parameter form (else Y theta is not that plant's torque)."""
        if port != "q" or not isinstance(source, URDFArm):
            return None
        mine = (*self.robot_description, self.parameter_form)
        theirs = (*source.robot_description, source.parameter_form)
        names = ("URDF file", "locked joints", "gravity", "parameters")
        for name, a, b in zip(names, mine, theirs):
            if a != b:
                return (f"the regressor's {name} ({a!r}) differs from the plant's "
                        f"({b!r}); give both blocks the same robot, locked_joints, gravity and "
                        f"parameters")
        return None

    def output(self, t, x, u):
        q, qdot, zeta, zetad = u
        cols = self._columns
        args = (self._pin, self.model, self._data, self.model0, self._data0)
        if len(q) == len(qdot) == len(zeta) == len(zetad) == 1:
            Y = regressor(*args, q[0], qdot[0], zeta[0], zetad[0])
            return ((Y if cols is None else Y[:, cols])[None],)
        B = max(q.shape[0], qdot.shape[0], zeta.shape[0], zetad.shape[0])
        q, qdot, zeta, zetad = (np.broadcast_to(v, (B, self._n)) for v in u)
        p = self.outputs["Y"].shape[1]
        out = np.empty((B, self._n, p))
        for b in range(B):
            Y = regressor(*args, q[b], qdot[b], zeta[b], zetad[b])
            out[b] = Y if cols is None else Y[:, cols]
        return (out,)
