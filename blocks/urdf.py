"""Serial manipulators from URDF (pinocchio): the plant of eq. (1) and its regressor (Property 3).

Both blocks describe the robot the same way, through ``robot`` (an example-robot-data name:
``panda``, ``ur5``) or ``urdf`` (a file), ``locked_joints`` and ``gravity``; ``load_model`` turns
that description into a pinocchio model, once (cached).  The parameter vector theta holds, per
moving body, pinocchio's 10 dynamic parameters [m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz,
I_yz, I_zz] (inertia about the joint frame's origin), or the base parameters (an identifiable
reduction; ``parameters: base``).  The derivation of the regressor is in docs/urdf-regressor.md.

pinocchio (PyPI ``pin``) and ``example-robot-data`` are the optional extra ``fwdstep[robots]``:
without them this module still imports and registers its blocks (``fwdstep blocks`` lists them
with an install hint), and building one raises a one-line ParameterError.

Two implementations of the same equations, chosen per block and batch (``implementation``):
pinocchio reads the URDF (always) and can compute aba and the regressor one variant at a time
in C++; fwdstep's own kernels (blocks/rigid_body.py) are what the compiled backend traces
into straight-line code for the robot (``compile_with = "traced"``).  On the NumPy path,
``implementation: auto`` runs the same traced code compiled natively for the block alone
(``native_kernels``: fwdstep/compiled/native_block.py, when llvmlite is installed; 0.4-2 us
per variant, 3-10x faster than pinocchio's calls from Python); without llvmlite it runs
pinocchio below KERNELS_FROM_BATCH variants and the kernels as NumPy arrays from there
(every variant in one pass).  All equal each other to ~1e-15 relative
(tests/blocks/test_rigid_body.py, tests/fwdstep/test_native_block.py).
"""
from __future__ import annotations

import functools
import os

import numpy as np

from fwdstep.core.block import Block, Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.native import captured_stderr
from fwdstep.core.registry import register

from . import rigid_body as rb
from .rigid_body import forward_dynamics, frame_kinematics, regressor as christoffel_regressor
from .nonlinear import friction_law
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


#: budgets of a robot description: its file and its links (rigid-body algorithms, the
#: base-parameter identification and its samples grow with them; a 200-link URDF took
#: 2.8 GB before this limit).  The shipped robots have 12 (UR5) and 13 (Panda) links.
MAX_URDF_BYTES = 64 * 2**20
MAX_URDF_LINKS = 128


def _over_budget(path: str) -> str | None:
    """Why the URDF at ``path`` is too large to build, checked before parsing; or None."""
    size = os.path.getsize(path)
    if size > MAX_URDF_BYTES:
        return (f"is {size / 2**20:.0f} MiB; the limit of a robot description is "
                f"{MAX_URDF_BYTES >> 20} MiB")
    with open(path, "rb") as fh:
        links = fh.read().count(b"<link")
    if links > MAX_URDF_LINKS:
        return f"has {links} links; the limit is {MAX_URDF_LINKS}"
    return None


@functools.lru_cache(maxsize=32)
def _load(path: str, locked: tuple, gravity: float):
    """(model, data, model without gravity, its data): joints in ``locked`` fixed at the
    neutral configuration; or a message saying why not.  The data objects are scratch space
    every pinocchio call fills anew, shared by all blocks of one robot (so variants of a sweep
    that differ only in numbers batch together)."""
    import pinocchio as pin
    too_large = _over_budget(path)
    if too_large is not None:
        return too_large
    try:
        with captured_stderr() as log:        # urdfdom's C++ log lines, with build paths
            full = pin.buildModelFromUrdf(path)
    except (RuntimeError, ValueError) as exc:
        return (f"cannot read URDF {path!r}: "
                f"{log.reason or (str(exc).splitlines()[0] if str(exc) else exc)}")
    unknown = [j for j in locked if not full.existJointName(j)]
    if unknown:
        names = ", ".join(full.names[1:])
        return f"has no joint {unknown[0]!r} to lock; joints are: {names}"
    mimic = _mimic_joints(path)
    free = [(j, m) for j, m in mimic if j not in locked]
    if free:
        return (f"'s joint {free[0][0]!r} mimics {free[0][1]!r} (<mimic>), which is not "
                f"supported: lock it (locked_joints)")
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


def _mimic_joints(path: str) -> list:
    """[(joint, mimicked joint)] of the URDF's <mimic> elements."""
    import xml.etree.ElementTree as ElementTree      # only when a URDF is read
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError):
        return []
    return [(j.get("name"), m.get("joint")) for j in root.iter("joint")
            for m in j.findall("mimic")]


@functools.lru_cache(maxsize=32)
def rigid_body_model(path: str, locked: tuple, gravity: float):
    """(structure (n, 17), theta (10 n), URDF damping (n), URDF friction (n)) of a loaded
    robot, for the kernels of blocks/rigid_body.py."""
    model = _load(path, locked, gravity)[0]
    return (rb.tree_from_pinocchio(model), rb.theta_from_pinocchio(model),
            np.array(model.damping, dtype=float), np.array(model.friction, dtype=float))


def load_model(block, robot: str, urdf: str, locked_joints, gravity: float):
    """(model, data, model without gravity, its data) for a block's robot description, which
    is kept in ``block.robot_description`` (compared between plant and regressor)."""
    _pinocchio(block.name, block.type_name)
    path, locked = _description(block, robot, urdf, locked_joints)
    block.robot_description = (path, locked, float(gravity))
    loaded = _load(path, locked, float(gravity))
    if isinstance(loaded, str):
        sep = "" if loaded.startswith("'s ") else " "
        raise ParameterError(f"block {block.name!r}: the robot{sep}{loaded}", block=block.name)
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


def regressor_rows(pin, model, data, model0, data0, q, qdot, zeta, zetad, columns, B):
    """Y (B, n, p) of ``regressor`` for every variant (rows of q, ... or one shared row),
    the wanted columns only (all: None): the half sums and differences formed for the batch
    at once, pinocchio's two regressors subtracted into one array, the columns taken once."""
    n = model.nv
    half_sum = qdot + zeta
    half_sum *= 0.5
    half_difference = qdot - zeta
    half_difference *= 0.5
    zeros = np.zeros(n)
    R = pin.computeJointTorqueRegressor
    if B == 1:
        full = R(model, data, q[0], half_sum[0], zetad[0])
        np.subtract(full, R(model0, data0, q[0], half_difference[0], zeros), out=full)
        return (full if columns is None else full.take(columns, axis=1))[None]
    q, zetad, half_sum, half_difference = (np.broadcast_to(v, (B, n)) for v in (
        q, zetad, half_sum, half_difference))
    full = np.empty((B, n, 10 * n))
    for qb, sb, db, ab, out in zip(q, half_sum, half_difference, zetad, full):
        np.subtract(R(model, data, qb, sb, ab), R(model0, data0, qb, db, zeros), out=out)
    return full if columns is None else full.take(columns, axis=2)


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
        "urdf": Param("file", "", "URDF file (absolute, or relative to the diagram file that "
                                  "names it, like a subsystem's file:); instead of 'robot'"),
        "locked_joints": Param("names", None, "joint names fixed at the neutral configuration "
                                              "(default: the named robot's, e.g. the Panda's "
                                              "fingers; [] for none)"),
        "gravity": Param("float", 9.81, "gravitational acceleration along -z of the base "
                                        "frame (m/s^2); 0: no gravity"),
        "parameters": Param("choice", "full", "theta: 'full' (10 per body) or 'base' (the "
                                              "identifiable reduction)",
                            choices=("full", "base")),
        "implementation": Param("choice", "auto", "who computes the dynamics on the NumPy "
                                                  "path: 'auto' (fwdstep's kernels compiled "
                                                  "to native code; without llvmlite "
                                                  "pinocchio below "
                                                  f"{KERNELS_FROM_BATCH} variants, the "
                                                  "kernels from there), 'pinocchio' or "
                                                  "'kernels'; compiled runs trace the kernels",
                                choices=("auto", "pinocchio", "kernels")),
    }


#: On the NumPy path without native kernels (no llvmlite, or the tracer refused),
#: ``implementation: auto`` runs fwdstep's kernels for batches of at least this many variants
#: and pinocchio (one C++ call per variant) below (measured:
#: benchmarks/robots_benchmark.py --kernels).
KERNELS_FROM_BATCH = 512


def _uses_kernels(implementation: str, batch: int) -> bool:
    return implementation == "kernels" or (implementation == "auto"
                                           and batch >= KERNELS_FROM_BATCH)


def _native_wanted(self, batch: int) -> tuple:
    """``implementation: auto``: the kernel as native code at every batch size, when
    llvmlite is installed (the NumPy path runs the method otherwise: pinocchio, or the
    kernels from KERNELS_FROM_BATCH variants).  Measured on the Panda (benchmarks/
    robots_benchmark.py --kernels): aba 2.2 us per call at one variant, 0.4 us per variant
    in a batch, against pinocchio's 6.7 and 3.4-4.5 and the NumPy kernels' 1.8 at 4096;
    the Slotine-Li regressor 2.2 and 0.5-1.0 against 11-22 and 5.5."""
    return self.native_kernels if self.implementation == "auto" else ()


def _parameter_form(block, model, robot, urdf, locked_joints, gravity, parameters,
                    theta=None):
    """theta (default: the URDF's, ``true_parameters``) in the block's form and the reduction
    (None for 'full')."""
    theta = true_parameters(model) if theta is None else theta
    if parameters == "full":
        return theta, None
    path, locked = _description(block, robot, urdf, locked_joints)
    cols, rest, K = _base_reduction(path, locked, float(gravity))
    return theta[cols] + K @ theta[rest], cols


def point_mass_parameters(model, frame: str, mass: float, position) -> tuple:
    """(joint index (0-based), the ten dynamic parameters) of a point mass ``mass`` at
    ``position`` (3, m) in the frame ``frame`` (a URDF link or joint; "": the last joint's
    frame), about the origin of the frame of the joint that carries it:
    [m, m c, m (|c|^2 1 - c c^T)] in pinocchio's order (c the position in that joint's
    frame); KeyError when the robot has no such frame on a moving body."""
    if frame:
        placement = rb.frame_from_pinocchio(model, frame)
        joint, R, p = int(placement[0]), placement[1:10].reshape(3, 3), placement[10:13]
    else:
        joint, R, p = model.nv - 1, np.eye(3), np.zeros(3)
    c = R @ np.asarray(position, dtype=float) + p
    m = float(mass)
    x, y, z = c
    return joint, np.array([m, m * x, m * y, m * z, m * (y * y + z * z), -m * x * y,
                            m * (x * x + z * z), -m * x * z, -m * y * z, m * (x * x + y * y)])


def _summary_with_hint(cls) -> str:
    summary = Block.summary.__func__(cls)
    return summary if available() else f"{summary} [{INSTALL_HINT}]"


# ------------------------------------------------------------------------------ kernels
def arm_output(t, x, tau, tau_star, tree, gravity, inertia, coulomb, viscous,
               velocity_scale, theta, effort, velocity, lower, upper, viscous_friction,
               coulomb_friction):
    """q, qdot, theta (the parameter vector in the block's form) and the URDF's limits
    (constant)."""
    n = x.shape[1] // 2
    return x[:, :n], x[:, n:], theta, effort, velocity, lower, upper


def arm_torque(t, x, qdot, tau, tau_star, coulomb, viscous, velocity_scale,
               viscous_friction, coulomb_friction):
    """tau + tau_star + tau_f: tau_f of the Friction block's law (blocks/nonlinear.py, the
    stateless ``friction_law``) when there is Coulomb friction, its viscous part alone when
    there is only that (the same numbers: 0 tanh(.) + F_v qdot is F_v qdot), none without
    friction."""
    torque = tau + tau_star
    if coulomb_friction:
        return torque + friction_law(t, x, qdot, coulomb, viscous, velocity_scale)[0]
    if viscous_friction:
        return torque - viscous * qdot
    return torque


def arm_derivative(t, x, tau, tau_star, tree, gravity, inertia, coulomb, viscous,
                   velocity_scale, theta, effort, velocity, lower, upper, viscous_friction,
                   coulomb_friction):
    """dx = [qdot, qddot], qddot = H^-1 (tau + tau_star + tau_f - C qdot - g) (``arm_torque``:
    the flags say which friction terms are there)."""
    n = x.shape[1] // 2
    q = x[:, :n]
    qdot = x[:, n:]
    torque = arm_torque(t, x, qdot, tau, tau_star, coulomb, viscous, velocity_scale,
                        viscous_friction, coulomb_friction)
    qddot = forward_dynamics(tree, gravity, inertia, q, qdot, torque)
    dx = np.empty((qddot.shape[0], 2 * n))
    dx[:, :n] = qdot
    dx[:, n:] = qddot
    return dx


#: what a limit output holds for a joint whose URDF gives none (a finite number: every output
#: of a run must be finite)
NO_LIMIT = float(np.finfo(float).max)


def urdf_limits(model) -> tuple:
    """(effort, velocity, lower, upper) of the model's joints as the URDF's <limit> gives
    them (pinocchio's effortLimit, velocityLimit, lower/upperPositionLimit); inf where it
    gives none (an effort or velocity <= 0, or lower >= upper)."""
    effort = np.array(model.effortLimit, dtype=float)
    velocity = np.array(model.velocityLimit, dtype=float)
    lower = np.array(model.lowerPositionLimit, dtype=float)
    upper = np.array(model.upperPositionLimit, dtype=float)
    effort[~(effort > 0.0)] = np.inf
    velocity[~(velocity > 0.0)] = np.inf
    none = ~(lower < upper) | ~np.isfinite(lower) | ~np.isfinite(upper)
    lower[none], upper[none] = -np.inf, np.inf
    return effort, velocity, lower, upper


def _joint_units(tree) -> tuple:
    """(effort, velocity, position) units: of revolute joints, prismatic ones, or both."""
    kinds = set(tree[:, 1].astype(int).tolist())
    if kinds == {rb.REVOLUTE}:
        return "N m", "rad/s", "rad"
    if kinds == {rb.PRISMATIC}:
        return "N", "m/s", "m"
    return "N m or N", "rad/s or m/s", "rad or m"


# (the kernels call rigid_body's functions by name: the tracer rebinds a kernel's global
# functions, not a module's attributes)
def regressor_output(t, x, q, qdot, zeta, zetad, tree, gravity, columns):
    """Y (B, n, p) of the wanted columns of the Christoffel regressor."""
    return (christoffel_regressor(tree, gravity, columns, q, qdot, zeta, zetad),)


@register
class URDFArm(MechanicalPlant):
    """Serial manipulator from URDF: H(q) qddot + C(q, qdot) qdot + g(q) = tau + tau_star + tau_f.

    Equation (1) of the paper for any fixed-base chain (or tree) of revolute/prismatic
    joints: qddot = H^-1 (tau + tau_star + tau_f - C qdot - g), computed by fwdstep's kernels
    (blocks/rigid_body.py: composite rigid-body H, Newton-Euler bias, LDL^T solve; traced to
    straight-line code by the compiled backend) or by pinocchio's aba (``implementation``).
    Joint friction tau_f = -(coulomb tanh(qdot / coulomb_velocity) + damping qdot), the law of
    the ``Friction`` block, is not part of the regressor; ``damping`` and ``coulomb`` default
    to the URDF's ``<dynamics damping= friction=>``.  The joints in ``locked_joints`` are
    fixed at the neutral configuration and their bodies merged into their parents; a
    ``<mimic>`` joint must be locked.  Output ``theta`` is the robot's true parameter vector
    (constant), in the form of ``URDFRegressor`` with the same ``parameters``, so a diagram
    can plot theta_hat against it.  ``tau_star`` is optional: unconnected, it is zero.  State
    order: q (n), then qdot (n).

    Equation: (1), qddot = H^-1 (tau + tau_star + tau_f - C qdot - g).

    Ports:
        | port     | direction | shape | feedthrough |
        | tau      | in        | (n,)  | -           |
        | tau_star | in        | (n,)  | -           |
        | q        | out       | (n,)  | -           |
        | qdot     | out       | (n,)  | -           |
        | theta    | out       | (p,)  | -           |
        | effort_limit   | out | (n,) | -           |
        | velocity_limit | out | (n,) | -           |
        | position_lower | out | (n,) | -           |
        | position_upper | out | (n,) | -           |

    The four ``*_limit``/``position_*`` outputs are the URDF's joint limits (<limit effort=
    velocity= lower= upper=>; constant; 1.8e308 where the URDF gives none), for a
    ``Saturation`` with limit inputs (``Clip``) or a reference that respects them.  The run
    also reports, in summary.json's ``limits`` and the report, max_t |tau_i| / effort_i,
    max_t |qdot_i| / velocity_i and the position's max |q_i - centre_i| / half-range_i
    (fwdstep.run.limits); above 1 the joint left its limit.  The run goes on unless
    ``stop_on_limits``.

    Parameters:
        robot: example-robot-data model (panda: 7 joints, fingers locked; ur5: 6 joints), or
        urdf: a URDF file.
        locked_joints: joints to fix (default: the named robot's; [] for none).
        gravity: gravitational acceleration along -z of the base frame (default 9.81).
        parameters: 'full' (p = 10 n) or 'base' (identifiable reduction) for ``theta``.
        implementation: 'auto' (native code of the kernels), 'pinocchio' or 'kernels' (the
        NumPy path's choice; see the module docstring).
        damping, coulomb: viscous (N m s/rad) and Coulomb (N m) friction, one number or n
        (default: the URDF's damping and friction).
        coulomb_velocity: velocity scale of the smoothed Coulomb term (rad/s, default 0.01).
        payload: a mass held for the whole run (kg, default 0): a point mass at
        payload_position (m, default [0, 0, 0]) in payload_frame (a URDF link or joint,
        default the last joint's frame), added to the ten parameters of the body that
        holds it (so ``theta`` includes it; the regressor does not depend on it).  A sweep
        over it batches: every variant's dynamics take its own parameters.
        q0, qdot0: initial joint positions and velocities (one number or n numbers).
        stop_on_limits: end the run at the first recorded sample beyond a URDF limit
        (effort on tau, velocity, position), results kept (default false: report only).
    """

    params = {
        **_robot_params(),
        "damping": Param("array", None, "viscous joint friction (N m s/rad): scalar or (n,); "
                                        "default: the URDF's <dynamics damping=>"),
        "coulomb": Param("array", None, "Coulomb joint friction (N m): scalar or (n,); "
                                        "default: the URDF's <dynamics friction=>"),
        "coulomb_velocity": Param("float", 0.01, "velocity scale of tanh in the Coulomb term"),
        "payload": Param("float", 0.0, "mass held by the robot (kg): a point mass at "
                                       "payload_position in payload_frame, the whole run"),
        "payload_frame": Param("str", "", "the URDF frame (link or joint) holding the payload; "
                                          "default: the last joint's frame"),
        "payload_position": Param("array", [0.0, 0.0, 0.0], "the payload's position in "
                                                            "payload_frame (m, 3 numbers)"),
        "q0": Param("array", 0.0, "initial joint positions, scalar or (n,)"),
        "qdot0": Param("array", 0.0, "initial joint velocities, scalar or (n,)"),
        "stop_on_limits": Param("bool", False, "end the run at the first recorded sample "
                                               "beyond a URDF joint limit (effort, velocity, "
                                               "position); default: report only"),
    }
    example = {"robot": "ur5", "q0": [0.1, -1.0, 1.2, 0.0, 0.5, 0.0], "damping": 0.1}
    summary = classmethod(_summary_with_hint)
    compile_with = "traced"         # compiled: the kernels traced; NumPy: see derivative
    native_kernels = ("derivative",)   # NumPy path, ``auto``: natively compiled (_native_wanted)
    native_wanted = _native_wanted

    #: ``_models``: the pinocchio models of the stacked ``inertia`` rows (built when first
    #: needed for a parameter namespace, as ``_kargs``)
    finalize_attributes = Block.finalize_attributes + ("_models",)

    def setup(self, robot, urdf, locked_joints, gravity, parameters, implementation, damping,
              coulomb, coulomb_velocity, payload, payload_frame, payload_position, q0, qdot0,
              stop_on_limits):
        from .robot import _vector_param
        self._pin = _pinocchio(self.name, self.type_name)
        self.model, self._data, _, _ = load_model(self, robot, urdf, locked_joints, gravity)
        n = self.model.nv
        self.declare_plant(n, q0, qdot0)
        self.state_labels = [f"q_{j}" for j in self.model.names[1:]] + \
                            [f"qdot_{j}" for j in self.model.names[1:]]
        inertia = self._with_payload(payload, payload_frame, payload_position)
        theta, _ = _parameter_form(self, self.model, robot, urdf, locked_joints, gravity,
                                   parameters, inertia)
        self.declare_output("theta", theta.shape, feedthrough=(), label=r"$\theta$")
        tree = rigid_body_model(*self.robot_description)[0]
        joints = list(self.model.names[1:])
        effort_unit, velocity_unit, position_unit = _joint_units(tree)
        limits = urdf_limits(self.model)
        for name, unit, label in (("effort_limit", effort_unit, r"$\tau_{max}$"),
                                  ("velocity_limit", velocity_unit, r"$\dot q_{max}$"),
                                  ("position_lower", position_unit, r"$q_{min}$"),
                                  ("position_upper", position_unit, r"$q_{max}$")):
            self.declare_output(name, (n,), feedthrough=(), label=label, unit=unit,
                                components=joints)
        effort, velocity, lower, upper = limits
        self.declare_limit("tau", "effort", effort, unit=effort_unit, components=joints,
                           stop=stop_on_limits)
        self.declare_limit("qdot", "velocity", velocity, unit=velocity_unit, components=joints,
                           stop=stop_on_limits)
        self.declare_limit("q", "position", upper, lower, unit=position_unit,
                           components=joints, stop=stop_on_limits)
        self.parameter_form = parameters
        if coulomb_velocity <= 0.0:
            raise ParameterError(f"block {self.name!r} parameter 'coulomb_velocity' must be "
                                 f"positive, got {coulomb_velocity}", block=self.name)
        tree, _, urdf_damping, urdf_friction = rigid_body_model(*self.robot_description)
        damping = urdf_damping if damping is None else _vector_param(self, "damping", damping, n)
        coulomb = urdf_friction if coulomb is None else _vector_param(self, "coulomb", coulomb,
                                                                      n)
        if np.any(damping < 0.0) or np.any(coulomb < 0.0):
            raise ParameterError(f"block {self.name!r} parameters 'damping' and 'coulomb' must "
                                 f"not be negative", block=self.name)
        self.implementation = implementation
        self.set_param("tree", tree)
        self.set_param("gravity", [float(gravity)])
        self.set_param("inertia", inertia)
        self.set_param("coulomb", coulomb)
        self.set_param("viscous", damping)
        self.set_param("velocity_scale", [coulomb_velocity])
        self.set_param("theta", theta)
        for name, value in zip(("effort", "velocity", "lower", "upper"), limits):
            self.set_param(name, np.clip(value, -NO_LIMIT, NO_LIMIT))
        self.set_kernels(output=arm_output, derivative=arm_derivative,
                         params=("tree", "gravity", "inertia", "coulomb", "viscous",
                                 "velocity_scale", "theta", "effort", "velocity", "lower",
                                 "upper"),
                         static=(bool(np.any(damping)), bool(np.any(coulomb))))

    def _with_payload(self, payload, frame, position):
        """The ten parameters of every body (the kernels' ``inertia``), the payload's
        point mass added to the body that holds it."""
        inertia = rigid_body_model(*self.robot_description)[1]
        position = np.asarray(position, dtype=float)
        if not payload >= 0.0 or position.shape != (3,) or not np.all(np.isfinite(position)):
            raise ParameterError(f"block {self.name!r}: 'payload' must be a mass >= 0 (kg) and "
                                 f"'payload_position' 3 finite numbers (m), got {payload} and "
                                 f"{position.tolist()}", block=self.name)
        try:
            joint, added = point_mass_parameters(self.model, frame, payload, position)
        except KeyError:
            names = ", ".join(f.name for f in self.model.frames if f.name != "universe")
            raise ParameterError(f"block {self.name!r} parameter 'payload_frame': the robot has "
                                 f"no frame {frame!r} on a moving body; frames are: "
                                 f"{names}"[:400], block=self.name) from None
        if payload == 0.0:
            return inertia
        inertia = inertia.copy()
        inertia[10 * joint:10 * joint + 10] += added
        return inertia

    def _pinocchio_models(self):
        """[(model, data)] for the rows of ``p.inertia`` (one row, or one per variant): the
        URDF's model where a row is the URDF's parameters, else a copy holding that row's
        inertias (a payload)."""
        cached = self.__dict__.get("_models")
        inertia = self.p.inertia
        if cached is not None and cached[0] is inertia:
            return cached[1]
        urdf_theta = rigid_body_model(*self.robot_description)[1]
        built, models = {}, []
        for row in np.atleast_2d(inertia):
            key = row.tobytes()
            if key not in built:
                if np.array_equal(row, urdf_theta):
                    built[key] = (self.model, self._data)
                else:
                    built[key] = _model_with_parameters(self.model, row, urdf_theta)
            models.append(built[key])
        self._models = (inertia, models)
        return models

    def derivative(self, t, x, u):
        """The kernel, or pinocchio's aba one variant at a time (``implementation``)."""
        tau, tau_star = u
        B = max(x.shape[0], tau.shape[0], tau_star.shape[0])
        if _uses_kernels(self.implementation, B):
            return Block.derivative(self, t, x, u)
        n = self._n
        p = self.p
        qdot = x[:, n:]
        torque = arm_torque(t, x, qdot, tau, tau_star, p.coulomb, p.viscous, p.velocity_scale,
                            *self.kernels.static)
        dx = np.empty((B, 2 * n))
        dx[:, :n] = qdot
        aba, models = self._pin.aba, self._pinocchio_models()
        if B == 1:
            model, data = models[0]
            dx[0, n:] = aba(model, data, x[0, :n], qdot[0], torque[0])
            return dx
        x = np.broadcast_to(x, (B, 2 * n))
        torque = np.broadcast_to(torque, (B, n))
        rows = zip(x[:, :n], x[:, n:], torque, dx[:, n:])
        if len(models) == 1:
            model, data = models[0]
            for q, qdot, tau, out in rows:
                out[:] = aba(model, data, q, qdot, tau)
        else:
            for (model, data), (q, qdot, tau, out) in zip(models, rows):
                out[:] = aba(model, data, q, qdot, tau)
        return dx


def _model_with_parameters(model, theta, urdf_theta):
    """(a copy of the pinocchio model whose bodies have the ten parameters of theta where
    they differ from the URDF's, urdf_theta; its data)."""
    import pinocchio as pin
    copy = model.copy()
    for j in range(1, copy.njoints):
        body = slice(10 * (j - 1), 10 * j)
        if not np.array_equal(theta[body], urdf_theta[body]):
            copy.inertias[j] = pin.Inertia.FromDynamicParameters(theta[body])
    return copy, copy.createData()


@register
class URDFRegressor(Block):
    """URDF-arm regressor Y(q, qdot, zeta, zetad) with H zetad + C(q, qdot) zeta + g = Y theta.

    Property 3 of the paper for ``URDFArm`` (same ``robot``/``urdf``, ``locked_joints``,
    ``gravity``), with C the Christoffel-symbol Coriolis matrix (so Hdot - 2C is
    skew-symmetric, Property 2; it equals pinocchio's computeCoriolisMatrix).  Computed by
    fwdstep's kernels (blocks/rigid_body.py: one Newton-Euler pass with the velocity products
    of qdot and zeta symmetrised; traced to straight-line code by the compiled backend) or
    from pinocchio's joint-torque regressor R(q, v, a) by polarization
    (docs/urdf-regressor.md, eq. (R); ``implementation``):

        Y = R_g(q, (qdot + zeta)/2, zetad) - R_0(q, (qdot - zeta)/2, 0),

    R_0 without gravity.  theta holds 10 parameters per moving body ([m, m c, inertia about
    the joint origin], ``URDFArm``'s ``theta`` output); many are not identifiable (columns of Y
    that vanish or are combinations of others): ``parameters: base`` keeps the independent
    columns and the plant's ``theta`` becomes the base parameters beta with Y_base beta = Y theta.

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
        implementation: 'auto' (native code of the kernels), 'pinocchio' or 'kernels' (the
        NumPy path's choice; see the module docstring).
    """

    params = _robot_params()
    example = {"robot": "ur5"}
    summary = classmethod(_summary_with_hint)
    compile_with = "traced"         # compiled: the kernels traced; NumPy: see output
    native_kernels = ("output",)   # NumPy path, ``auto``: natively compiled (_native_wanted)
    native_wanted = _native_wanted

    def setup(self, robot, urdf, locked_joints, gravity, parameters, implementation):
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
        self.implementation = implementation
        tree = rigid_body_model(*self.robot_description)[0]
        columns = np.arange(10 * n) if self._columns is None else self._columns
        self.set_param("tree", tree)
        self.set_param("gravity", [float(gravity)])
        self.set_param("columns", columns)
        self.set_kernels(output=regressor_output, params=("tree", "gravity", "columns"))

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
        """The kernel, or pinocchio's regressor one variant at a time (``implementation``)."""
        q, qdot, zeta, zetad = u
        B = max(q.shape[0], qdot.shape[0], zeta.shape[0], zetad.shape[0])
        if _uses_kernels(self.implementation, B):
            return Block.output(self, t, x, u)
        return (regressor_rows(self._pin, self.model, self._data, self.model0, self._data0,
                               *u, self._columns, B),)


def frame_output(t, x, q, qdot, tree, frame):
    """position, rotation, J, Jdot qdot of the block's frame (blocks/rigid_body.py)."""
    return frame_kinematics(tree, frame, q, qdot)


@register
class URDFFrame(Block):
    """Pose, Jacobian and Jdot qdot of a URDF frame: the task-space kinematics of a robot.

    For the frame ``frame`` (a link or joint name of the URDF, e.g. the UR5's ``tool0`` or
    the Panda's ``panda_hand``) of the robot described as for ``URDFArm``: its position p and
    rotation R in the base frame, the Jacobian J with [pdot; omega] = J(q) qdot (velocity of
    the frame's origin and angular velocity, base axes: pinocchio's LOCAL_WORLD_ALIGNED) and
    Jdot qdot, the acceleration [pddot; omegadot] at qddot = 0, so that
    [pddot; omegadot] = J qddot + Jdot qdot.  Computed by fwdstep's kernels
    (blocks/rigid_body.py ``frame_kinematics``; traced in compiled runs).

    Equation: p, R = FK(q); [pdot; omega] = J(q) qdot; [pddot; omegadot] = J qddot + Jdot qdot.

    Ports:
        | port      | direction | shape  | feedthrough |
        | q         | in        | (n,)   | -           |
        | qdot      | in        | (n,)   | -           |
        | position  | out       | (3,)   | q           |
        | rotation  | out       | (3, 3) | q           |
        | J         | out       | (6, n) | q           |
        | Jdot_qdot | out       | (6,)   | q, qdot     |

    Parameters:
        robot / urdf, locked_joints: the robot (see ``URDFArm``).
        frame: the frame's name (a URDF link or joint).
        implementation: 'auto' (native code of the kernels), 'pinocchio' or 'kernels' (the
        NumPy path's choice; see the module docstring).
    """

    params = {k: v for k, v in _robot_params().items()
              if k in ("robot", "urdf", "locked_joints", "implementation")}
    params["frame"] = Param("str", doc="a URDF link or joint name (e.g. tool0, panda_hand)")
    example = {"robot": "ur5", "frame": "tool0"}
    summary = classmethod(_summary_with_hint)
    compile_with = "traced"         # compiled: the kernels traced; NumPy: see output
    native_kernels = ("output",)   # NumPy path, ``auto``: natively compiled (_native_wanted)
    native_wanted = _native_wanted

    def setup(self, robot, urdf, locked_joints, frame, implementation):
        self._pin = _pinocchio(self.name, self.type_name)
        model, self._data = load_model(self, robot, urdf, locked_joints, 0.0)[:2]
        self.model = model
        self.implementation = implementation
        try:
            placement = rb.frame_from_pinocchio(model, frame)
        except KeyError:
            names = ", ".join(f.name for f in model.frames if f.name != "universe")
            raise ParameterError(f"block {self.name!r} parameter 'frame': the robot has no "
                                 f"frame {frame!r} on a moving body; frames are: {names}"[:400],
                                 block=self.name) from None
        n = model.nv
        self.declare_input("q", (n,))
        self.declare_input("qdot", (n,))
        self.declare_output("position", (3,), feedthrough=("q",), label="$p$", unit="m",
                            components=["x", "y", "z"])
        self.declare_output("rotation", (3, 3), feedthrough=("q",), label="$R$")
        self.declare_output("J", (6, n), feedthrough=("q",), label="$J$")
        self.declare_output("Jdot_qdot", (6,), feedthrough=("q", "qdot"),
                            label=r"$\dot J \dot q$")
        self._frame_id = model.getFrameId(frame)
        self.set_param("tree", rigid_body_model(*self.robot_description)[0])
        self.set_param("frame", placement)
        self.set_kernels(output=frame_output, params=("tree", "frame"))

    def output(self, t, x, u):
        """The kernel, or pinocchio one variant at a time (``implementation``): the frame's
        placement, getFrameJacobian and getFrameClassicalAcceleration at qddot = 0 (both in
        LOCAL_WORLD_ALIGNED)."""
        B = max(u[0].shape[0], u[1].shape[0])
        if _uses_kernels(self.implementation, B):
            return Block.output(self, t, x, u)
        pin, model, data, fid = self._pin, self.model, self._data, self._frame_id
        n = model.nv
        q, qdot = (np.broadcast_to(v, (B, n)) for v in u)
        position, rotation = np.empty((B, 3)), np.empty((B, 3, 3))
        J, bias = np.empty((B, 6, n)), np.empty((B, 6))
        zero = np.zeros(n)
        world = pin.LOCAL_WORLD_ALIGNED
        for b in range(B):
            pin.forwardKinematics(model, data, q[b], qdot[b], zero)
            placement = pin.updateFramePlacement(model, data, fid)
            position[b] = placement.translation
            rotation[b] = placement.rotation
            pin.computeJointJacobians(model, data, q[b])
            J[b] = pin.getFrameJacobian(model, data, fid, world)
            acc = pin.getFrameClassicalAcceleration(model, data, fid, world)
            bias[b, :3] = acc.linear
            bias[b, 3:] = acc.angular
        return position, rotation, J, bias
