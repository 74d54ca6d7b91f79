"""Robot manipulator plants (eq. (1)) and their regressors (Property 3).

Every plant obeys eq. (1) of the paper, ``H(q) qddot + C(q, qdot) qdot + g(q) = tau + tau_star``
(the paper writes M for the inertia matrix H), with state ``(q, qdot)`` and outputs ``q`` and
``qdot`` that depend on the state only; ``qddot`` is not an output (it would feed through from
``tau`` and is not measured on a real arm).  Each plant comes with a regressor block whose
output ``Y`` satisfies ``H(q) zetad + C(q, qdot) zeta + g(q) = Y(q, qdot, zeta, zetad) theta``,
with the parameter vector ``theta`` documented on the plant (``parameter_vector``).
"""
from __future__ import annotations

import math

import numpy as np

from fwdstep.core import kernelops as ko
from fwdstep.core.block import MAX_BLOCK_STATES, Block, Param, as_written
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register

#: Physical parameters of the two-link arm (Slotine & Li, Applied Nonlinear Control,
#: Example 9.2) with their defaults.
TWO_LINK_DEFAULTS = {
    "m1": 1.0, "l1": 1.0, "me": 2.0, "delta_e": 30.0,
    "I1": 0.12, "lc1": 0.5, "Ie": 0.25, "lce": 0.6, "gravity": 0.0,
}


def two_link_theta(m1, l1, me, delta_e, I1, lc1, Ie, lce, gravity):
    """The 7 lumped parameters [a1, ..., a7] of the two-link arm (a5..a7 are 0 without
    gravity); ``delta_e`` in degrees."""
    de = math.radians(delta_e)
    return np.array([
        I1 + m1 * lc1 ** 2 + Ie + me * lce ** 2 + me * l1 ** 2,   # a1
        Ie + me * lce ** 2,                                        # a2
        me * l1 * lce * math.cos(de),                              # a3
        me * l1 * lce * math.sin(de),                              # a4
        (m1 * lc1 + me * l1) * gravity,                            # a5
        me * lce * gravity * math.cos(de),                         # a6
        me * lce * gravity * math.sin(de),                         # a7
    ])


def _two_link_params():
    docs = {
        "m1": "mass of link 1 (kg)",
        "l1": "length of link 1 (m)",
        "me": "mass of link 2 with its end effector (kg)",
        "delta_e": "angle of the link-2 centre of mass off the link axis, measured from the "
                   "centre of mass to the axis (degrees; the centre of mass is at absolute "
                   "angle q1 + q2 - delta_e)",
        "I1": "inertia of link 1 about its centre of mass (kg m^2)",
        "lc1": "distance from joint 1 to the centre of mass of link 1 (m)",
        "Ie": "inertia of link 2 about its centre of mass (kg m^2)",
        "lce": "distance from joint 2 to the centre of mass of link 2 (m)",
        "gravity": "gravitational acceleration in the plane of motion (m/s^2); 0 = horizontal "
                   "arm, 9.81 = vertical arm",
    }
    return {k: Param("float", TWO_LINK_DEFAULTS[k], docs[k]) for k in TWO_LINK_DEFAULTS}


#: The two-link regressor's parameter forms, by number of columns p (one definition: the
#: ``Regressor`` block's columns, ``TwoLinkArm``'s ``theta`` parameter and the load-time check
#: ``Regressor.check_source`` read it).
TWO_LINK_FORMS = {
    4: "[a1, a2, a3, a4]: horizontal arm, no gravity columns",
    5: "[a1, ..., a5]: gravity through a3, a4 and the known g / l1 (a6 = g a3 / l1, "
       "a7 = g a4 / l1)",
    7: "[a1, ..., a7]: a5..a7 carry the gravitational acceleration",
}


def two_link_theta_given(block_name: str, theta, physical: dict) -> np.ndarray:
    """The 7-vector [a1, ..., a7] from a ``theta`` parameter given in one of TWO_LINK_FORMS
    (4 numbers: a5..a7 = 0), refusing physical parameters given alongside it."""
    size = np.size(theta)
    known = ("gravity", "l1") if size == 5 else ()       # the 5-form's known kinematics
    changed = [k for k, v in physical.items() if v != TWO_LINK_DEFAULTS[k] and k not in known]
    if changed:
        raise ParameterError(f"block {block_name!r}: give either 'theta' or the physical "
                             f"parameters, not both ('theta' and {changed[0]!r} are set)",
                             block=block_name)
    theta = np.asarray(theta, dtype=float)
    if theta.ndim != 1 or theta.size not in TWO_LINK_FORMS:
        forms = "; ".join(f"{p} numbers {text}" for p, text in TWO_LINK_FORMS.items())
        raise ParameterError(f"block {block_name!r} parameter 'theta' must have {forms}; got "
                             f"shape {theta.shape}", block=block_name)
    if theta.size == 5:
        if physical["gravity"] == 0.0:
            raise ParameterError(f"block {block_name!r}: a 5-number 'theta' ({TWO_LINK_FORMS[5]}) "
                                 f"needs 'gravity' (and 'l1')", block=block_name)
        g_over_l1 = physical["gravity"] / physical["l1"]
        return np.concatenate([theta, [g_over_l1 * theta[2], g_over_l1 * theta[3]]])
    return np.concatenate([theta, np.zeros(7 - theta.size)])


def _vector_param(block: Block, key: str, value, n: int) -> np.ndarray:
    """``value`` as a float vector of length ``n`` (a scalar is repeated)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ParameterError(f"block {block.name!r} parameter {key!r} must be a number or a "
                             f"list of {n} numbers, got shape {arr.shape}", block=block.name)
    return arr.copy()


class MechanicalPlant(Block):
    """Base of the plants of eq. (1): state (q, qdot), input tau and optional tau_star, and the
    measurable outputs q, qdot (state only).  Not registered; subclasses add the dynamics."""

    def declare_plant(self, n: int, q0, qdot0, unit: str = "rad", axis: str = "joint") -> None:
        """``unit`` of q ("rad" for revolute joints, "m" for a point mass's position) and the
        name of one coordinate ("joint", "axis"), the defaults figures use for q and qdot."""
        self._n = n
        self.declare_input("tau", (n,))
        self.declare_input("tau_star", (n,), optional=True)
        joints = [f"{axis} {i + 1}" for i in range(n)]
        self.declare_output("q", (n,), feedthrough=(), label="$q$", unit=unit, components=joints)
        self.declare_output("qdot", (n,), feedthrough=(), label=r"$\dot q$", unit=f"{unit}/s",
                            components=joints)
        self.declare_state(2 * n, np.concatenate([_vector_param(self, "q0", q0, n),
                                                  _vector_param(self, "qdot0", qdot0, n)]))
        self.state_labels = [f"q{i + 1}" for i in range(n)] + [f"qdot{i + 1}" for i in range(n)]



# ---------------------------------------------------------------- kernels (one definition)
def plant_state_outputs(x):
    """q, qdot: the two halves of a plant's state."""
    n = x.shape[1] // 2
    return (x[:, :n], x[:, n:])


def two_link_accel(a1, a2, a3, a4, a5, a6, a7, gravity, c1, c2, s2, c12, s12, qd1, qd2,
                   t1, t2):
    """qddot of the two-link arm (the equations in TwoLinkArm's docstring), on numbers or on
    arrays of variants alike (c1 = cos q1, c2, s2 of q2, c12, s12 of q1 + q2):
    H qddot = tau + tau_star - C qdot - g, solved in closed form."""
    h12 = a2 + a3 * c2 + a4 * s2
    h11 = a1 + 2.0 * a3 * c2 + 2.0 * a4 * s2
    hh = a3 * s2 - a4 * c2
    r1 = t1 + hh * (2.0 * qd1 + qd2) * qd2
    r2 = t2 - hh * qd1 * qd1
    if gravity:
        g2 = a6 * c12 + a7 * s12
        r1 = r1 - a5 * c1 - g2
        r2 = r2 - g2
    inv_det = 1.0 / (h11 * a2 - h12 * h12)
    return (a2 * r1 - h12 * r2) * inv_det, (h11 * r2 - h12 * r1) * inv_det


def two_link_output(t, x, tau, tau_star, theta, gravity):
    return plant_state_outputs(x)


def two_link_derivative(t, x, tau, tau_star, theta, gravity):
    """dx = [qdot, qddot], one variant at a time on plain numbers (the fast form for a
    single run and for compiled code)."""
    B = max(x.shape[0], tau.shape[0], tau_star.shape[0], theta.shape[0])
    dx = np.empty((B, 4))
    for b in range(B):
        bx = b if x.shape[0] > 1 else 0
        bu = b if tau.shape[0] > 1 else 0
        bs = b if tau_star.shape[0] > 1 else 0
        bt = b if theta.shape[0] > 1 else 0
        q1 = float(x[bx, 0])
        q2 = float(x[bx, 1])
        qd1 = float(x[bx, 2])
        qd2 = float(x[bx, 3])
        dd1, dd2 = two_link_accel(
            float(theta[bt, 0]), float(theta[bt, 1]), float(theta[bt, 2]), float(theta[bt, 3]),
            float(theta[bt, 4]), float(theta[bt, 5]), float(theta[bt, 6]), gravity,
            math.cos(q1), math.cos(q2), math.sin(q2), math.cos(q1 + q2), math.sin(q1 + q2),
            qd1, qd2, float(tau[bu, 0] + tau_star[bs, 0]), float(tau[bu, 1] + tau_star[bs, 1]))
        dx[b, 0] = qd1
        dx[b, 1] = qd2
        dx[b, 2] = dd1
        dx[b, 3] = dd2
    return dx


def two_link_derivative_batch(t, x, tau, tau_star, theta, gravity):
    """The same on columns of variants (vectorised NumPy for batches)."""
    torque = tau + tau_star
    q1 = x[:, 0]
    q2 = x[:, 1]
    c1 = c12 = s12 = q2                     # the cosines of q1, q1 + q2 only with gravity
    if gravity:
        c1, c12, s12 = np.cos(q1), np.cos(q1 + q2), np.sin(q1 + q2)
    c2, s2 = np.cos(q2), np.sin(q2)
    if theta.shape[0] == 1:                 # shared: numbers (an operation of a number with
        th = theta[0]                       # an array costs half that of a 1-element array)
        dd1, dd2 = two_link_accel(th[0], th[1], th[2], th[3], th[4], th[5], th[6], gravity,
                                  c1, c2, s2, c12, s12, x[:, 2], x[:, 3], torque[:, 0],
                                  torque[:, 1])
    else:
        dd1, dd2 = two_link_accel(theta[:, 0], theta[:, 1], theta[:, 2], theta[:, 3],
                                  theta[:, 4], theta[:, 5], theta[:, 6], gravity, c1, c2, s2,
                                  c12, s12, x[:, 2], x[:, 3], torque[:, 0], torque[:, 1])
    B = max(x.shape[0], dd1.shape[0])
    dx = np.empty((B, 4))
    dx[:, 0] = x[:, 2]
    dx[:, 1] = x[:, 3]
    dx[:, 2] = dd1
    dx[:, 3] = dd2
    return dx


def two_link_output_payload(t, x, tau, tau_star, theta, theta_after, payload_time, gravity):
    return plant_state_outputs(x)


def two_link_derivative_payload(t, x, tau, tau_star, theta, theta_after, payload_time,
                                gravity):
    """The same with a payload step: theta_after (link 2 with the payload) from payload_time
    on, per variant."""
    th = np.where(t >= payload_time, theta_after, theta)
    return two_link_derivative_batch(t, x, tau, tau_star, th, gravity)


def two_link_regressor_rows(c2, s2, qd1, qd2, z1, z2, zd1, zd2):
    """The entries of Y (Regressor's docstring) on numbers or arrays (c2 = cos q2,
    s2 = sin q2): row 1 and row 2 of the horizontal part; the gravity columns are cos q1,
    cos q12, sin q12."""
    v1 = qd2 * z1 + (qd1 + qd2) * z2                       # row-1 Coriolis factor
    v2 = qd1 * z1                                          # row-2 Coriolis factor
    w1 = 2.0 * zd1 + zd2
    return (zd1, zd2, c2 * w1 - s2 * v1, s2 * w1 + c2 * v1,
            zd1 + zd2, c2 * zd1 + s2 * v2, s2 * zd1 - c2 * v2)


def regressor_output(t, x, q, qdot, zeta, zetad, p):
    """Y (B, 2, p), one variant at a time on plain numbers."""
    B = max(q.shape[0], qdot.shape[0], zeta.shape[0], zetad.shape[0])
    Y = np.zeros((B, 2, p))
    for b in range(B):
        bq = b if q.shape[0] > 1 else 0
        bd = b if qdot.shape[0] > 1 else 0
        bz = b if zeta.shape[0] > 1 else 0
        bzd = b if zetad.shape[0] > 1 else 0
        q1 = float(q[bq, 0])
        q2 = float(q[bq, 1])
        r = two_link_regressor_rows(math.cos(q2), math.sin(q2), float(qdot[bd, 0]),
                                    float(qdot[bd, 1]), float(zeta[bz, 0]), float(zeta[bz, 1]),
                                    float(zetad[bzd, 0]), float(zetad[bzd, 1]))
        Y[b, 0, 0] = r[0]
        Y[b, 0, 1] = r[1]
        Y[b, 0, 2] = r[2]
        Y[b, 0, 3] = r[3]
        Y[b, 1, 1] = r[4]
        Y[b, 1, 2] = r[5]
        Y[b, 1, 3] = r[6]
        if p == 7:
            c12 = math.cos(q1 + q2)
            s12 = math.sin(q1 + q2)
            Y[b, 0, 4] = math.cos(q1)
            Y[b, 0, 5] = c12
            Y[b, 1, 5] = c12
            Y[b, 0, 6] = s12
            Y[b, 1, 6] = s12
    return (Y,)


def regressor_output_batch(t, x, q, qdot, zeta, zetad, p):
    """The same on columns of variants (vectorised NumPy for batches)."""
    r = two_link_regressor_rows(np.cos(q[:, 1]), np.sin(q[:, 1]), qdot[:, 0], qdot[:, 1],
                                zeta[:, 0],
                                zeta[:, 1], zetad[:, 0], zetad[:, 1])
    B = max(q.shape[0], qdot.shape[0], zeta.shape[0], zetad.shape[0])
    Y = np.zeros((B, 2, p))
    Y[:, 0, 0] = r[0]
    Y[:, 0, 1] = r[1]
    Y[:, 0, 2] = r[2]
    Y[:, 0, 3] = r[3]
    Y[:, 1, 1] = r[4]
    Y[:, 1, 2] = r[5]
    Y[:, 1, 3] = r[6]
    if p == 7:
        q12 = q[:, 0] + q[:, 1]
        Y[:, 0, 4] = np.cos(q[:, 0])
        Y[:, 0, 5] = np.cos(q12)
        Y[:, 1, 5] = Y[:, 0, 5]
        Y[:, 0, 6] = np.sin(q12)
        Y[:, 1, 6] = Y[:, 0, 6]
    return (Y,)


def regressor5_output(t, x, q, qdot, zeta, zetad, g_over_l1):
    """Y (B, 2, 5) of the 5-parameter form: the 7-column Y with the a6, a7 columns folded
    into a3, a4 (a6 = g a3 / l1, a7 = g a4 / l1); g_over_l1 (B, 1) or (1, 1)."""
    Y7 = regressor_output(t, x, q, qdot, zeta, zetad, 7)[0]
    Y = np.empty((Y7.shape[0], 2, 5))
    Y[:, :, 0] = Y7[:, :, 0]
    Y[:, :, 1] = Y7[:, :, 1]
    Y[:, :, 2] = Y7[:, :, 2] + g_over_l1 * Y7[:, :, 5]
    Y[:, :, 3] = Y7[:, :, 3] + g_over_l1 * Y7[:, :, 6]
    Y[:, :, 4] = Y7[:, :, 4]
    return (Y,)


def point_mass_output(t, x, tau, tau_star, inv_mass):
    return plant_state_outputs(x)


def point_mass_derivative(t, x, tau, tau_star, inv_mass):
    """dx = [qdot, (tau + tau_star) / m]."""
    n = x.shape[1] // 2
    qddot = (tau + tau_star) * inv_mass
    dx = np.empty((max(x.shape[0], qddot.shape[0]), 2 * n))
    dx[:, :n] = x[:, n:]
    dx[:, n:] = qddot
    return dx


def point_mass_regressor_output(t, x, q, qdot, zeta, zetad):
    """Y = diag(zetad)."""
    n = zetad.shape[1]
    Y = np.zeros((zetad.shape[0], n, n))
    for i in range(n):
        Y[:, i, i] = zetad[:, i]
    return (Y,)


def _native_in_batches(self, batch: int) -> tuple:
    """The two-link arm's and its regressor's kernels as native code on the NumPy path for a
    batch of variants (a sweep), not for one run.  Whole ``simulate`` of slotine_li.yaml with
    both native against their NumPy kernels, CPU medians of interleaved repeats in one
    process: 0.82 (256 variants, 10 s), 0.87 (4096, 1 s), 0.93 (one variant, 10 s); but a
    single run in a fresh process pays llvmlite's import and the trace first (~30 ms), and
    a whole ``fwdstep run`` of theorem1.yaml was no faster (1.05-1.09 of the hand script
    against 1.05 without; slotine_li.yaml 3 % faster): below the 5 % a fast path must pay."""
    return self.native_kernels if batch > 1 else ()


@register
class TwoLinkArm(MechanicalPlant):
    """Two-link planar arm (Slotine & Li): H(q) qddot + C(q, qdot) qdot + g(q) = tau + tau_star.

    Equation (1) of the paper with n = 2 (the paper writes M for H):

        a1 = I1 + m1 lc1^2 + Ie + me lce^2 + me l1^2,   a2 = Ie + me lce^2,
        a3 = me l1 lce cos(delta_e),                     a4 = me l1 lce sin(delta_e),
        H11 = a1 + 2 a3 cos q2 + 2 a4 sin q2,  H12 = H21 = a2 + a3 cos q2 + a4 sin q2,  H22 = a2,
        hh = a3 sin q2 - a4 cos q2,
        C = [[-hh qdot2, -hh (qdot1 + qdot2)], [hh qdot1, 0]],
        g = [(m1 lc1 + me l1) g cos q1 + me lce g cos(q1 + q2 - delta_e),
             me lce g cos(q1 + q2 - delta_e)]

    H is symmetric positive definite (Property 1), Hdot - 2C is skew-symmetric (Property 2),
    and g = dP/dq with P = (m1 lc1 + me l1) g sin q1 + me lce g sin(q1 + q2 - delta_e): the
    centre of mass of link 2 lies at absolute angle q1 + q2 - delta_e, which is where Slotine &
    Li's H puts it (H12 = a2 + me l1 lce cos(q2 - delta_e)), so the vertical arm is one rigid
    body (with "+ delta_e" in g, gravity would act on a mirrored link 2).  The
    2x2 system is solved in closed form.  ``tau_star`` (the paper's reference torque, e.g. a
    disturbance) is optional: unconnected, it is zero.  The lumped parameter vector theta of
    Property 3, matching the ``Regressor`` block, is ``TwoLinkArm.parameter_vector(**params)``.
    State order: q1, q2, qdot1, qdot2.

    Ports:
        | port     | direction | shape | feedthrough |
        | tau      | in        | (2,)  | -           |
        | tau_star | in        | (2,)  | -           |
        | q        | out       | (2,)  | -           |
        | qdot     | out       | (2,)  | -           |

    Parameters:
        m1, l1, me, delta_e, I1, lc1, Ie, lce: physical parameters (defaults: Slotine & Li,
            Example 9.2: 1, 1, 2, 30 deg, 0.12, 0.5, 0.25, 0.6); delta_e in degrees.
        gravity: gravitational acceleration g (default 0: horizontal plane).
        q0, qdot0: initial joint position and velocity (2 numbers each, or one number for both).
        payload, payload_time: from t = payload_time on, link 2 carries ``payload`` more kg at
            its centre of mass (me -> me + payload in a1..a7: a load picked up; default 0,
            none); the step time is declared as a discontinuity.
        theta: the plant in the paper's terms, instead of m1..lce and gravity: [a1, ..., a4]
            (horizontal arm) or [a1, ..., a7] (a5..a7 = the gravity terms above), used exactly
            as given (e.g. [3.34, 0.97, 1.0392305, 0.6]); not with physical parameters or a
            payload.
    """

    params = {
        **_two_link_params(),
        "theta": Param("array", None, "the lumped parameters instead of the physical ones: "
                                      "[a1, ..., a4] (horizontal) or [a1, ..., a7] (a5..a7 "
                                      "carry g)"),
        "payload": Param("float", 0.0, "mass added to link 2 at its centre of mass (kg)"),
        "payload_time": Param("float", 0.0, "time the payload is added (s)"),
        "q0": Param("array", 0.0, "initial joint position [q1, q2] (rad)"),
        "qdot0": Param("array", 0.0, "initial joint velocity [qdot1, qdot2] (rad/s)"),
    }
    example = {"q0": [0.1, -0.2], "qdot0": [0.0, 0.5], "gravity": 9.81}
    #: NumPy path, batches: the derivative as native code when llvmlite is installed
    #: (Block.native_kernels, ``_native_in_batches``; the same kernel, traced and compiled for
    #: the arm: the NumPy kernel makes ~40 array calls per stage)
    native_kernels = ("derivative",)
    native_wanted = _native_in_batches

    @staticmethod
    def parameter_vector(**params) -> np.ndarray:
        """The true theta for the ``Regressor`` block: [a1, a2, a3, a4] for a horizontal arm
        (gravity = 0), [a1, ..., a7] otherwise, with a5 = (m1 lc1 + me l1) g,
        a6 = me lce g cos(delta_e), a7 = me lce g sin(delta_e).  Missing keys take the
        block's defaults; q0 and qdot0 are accepted and ignored.  With ``theta`` given, that
        theta (4 or 7 numbers, as given)."""
        if params.get("p") == 5:
            rest = {k: v for k, v in params.items() if k != "p"}
            return TwoLinkArm.parameter_vector(**rest)[:5]
        if params.get("theta") is not None:
            physical = dict(TWO_LINK_DEFAULTS)
            physical.update({k: float(v) for k, v in params.items() if k in TWO_LINK_DEFAULTS})
            theta = two_link_theta_given("TwoLinkArm", params["theta"], physical)
            return theta[:np.asarray(params["theta"]).size]
        values = dict(TWO_LINK_DEFAULTS)
        for key, value in params.items():
            if key in ("q0", "qdot0", "theta"):
                continue
            if key not in values:
                raise ParameterError(f"TwoLinkArm has no parameter {key!r}; valid parameters "
                                     f"are: {', '.join(TWO_LINK_DEFAULTS)}")
            values[key] = float(value)
        theta = two_link_theta(**values)
        return theta if values["gravity"] != 0.0 else theta[:4]

    def setup(self, m1, l1, me, delta_e, I1, lc1, Ie, lce, gravity, theta, q0, qdot0, payload,
              payload_time):
        if theta is not None:
            if payload != 0.0:
                raise ParameterError(f"block {self.name!r}: a 'payload' needs the physical "
                                     f"parameters (me changes), not 'theta'", block=self.name)
            physical = dict(m1=m1, l1=l1, me=me, delta_e=delta_e, I1=I1, lc1=lc1, Ie=Ie,
                            lce=lce, gravity=gravity)
            theta = two_link_theta_given(self.name, theta, physical)
            self._declare_from_theta(theta, theta, payload_time, q0, qdot0)
            return
        for key, value in (("m1", m1), ("me", me), ("l1", l1), ("lce", lce)):
            if value <= 0.0:
                raise ParameterError(f"block {self.name!r} parameter {key!r} must be positive, "
                                     f"got {value}", block=self.name)
        for key, value in (("I1", I1), ("Ie", Ie), ("lc1", lc1)):
            if value < 0.0:
                raise ParameterError(f"block {self.name!r} parameter {key!r} must not be "
                                     f"negative, got {value}", block=self.name)
        if me + payload <= 0.0:
            raise ParameterError(f"block {self.name!r} parameter 'payload' would leave link 2 "
                                 f"with mass {me + payload} <= 0", block=self.name)
        theta = two_link_theta(m1, l1, me, delta_e, I1, lc1, Ie, lce, gravity)
        self._declare_from_theta(theta, two_link_theta(m1, l1, me + payload, delta_e, I1, lc1,
                                                       Ie, lce, gravity), payload_time, q0, qdot0)

    def _declare_from_theta(self, theta, theta_after, payload_time, q0, qdot0):
        a1, a2 = theta[0], theta[1]
        r2 = theta[2] ** 2 + theta[3] ** 2
        # det H = a2 (a1 - a2) - (a3 cos q2 + a4 sin q2)^2 >= a2 (a1 - a2) - (a3^2 + a4^2)
        if not a2 > 0.0 or a2 * (a1 - a2) - r2 <= 1e-12 * a1 * a1:
            raise ParameterError(f"block {self.name!r} parameters give an inertia matrix that is "
                                 f"not positive definite for every q2 (need a2 > 0 and "
                                 f"a2 (a1 - a2) > a3^2 + a4^2: I1, Ie or lc1 > 0)",
                                 block=self.name)
        self.declare_plant(2, q0, qdot0)
        self.set_param("theta", theta)
        self.set_param("theta_after", theta_after)
        self.set_param("payload_time", [payload_time])
        # the jump time, also kept outside p: variants picking up the payload at different
        # times never share a batch (one batch, one step grid), as Step and WhiteNoise do
        self.jumps = (float(payload_time),) if np.any(theta_after != theta) else ()
        self.finalize(1)

    def discontinuities(self, t_final: float) -> np.ndarray:
        """The payload time, when there is a payload."""
        return np.asarray(self.jumps, dtype=float)

    def finalize(self, batch: int) -> None:
        gravity = bool(np.any(self.p.theta[:, 4:] != 0.0))
        if np.any(self.p.theta_after != self.p.theta):
            self.set_kernels(output=two_link_output_payload,
                             derivative=two_link_derivative_payload,
                             params=("theta", "theta_after", "payload_time"), static=(gravity,))
            return
        self.set_kernels(output=two_link_output,
                         derivative=two_link_derivative if batch == 1
                         else two_link_derivative_batch,
                         params=("theta",), static=(gravity,))


@register
class Regressor(Block):
    """Two-link-arm regressor Y(q, qdot, zeta, zetad) with H zetad + C zeta + g = Y theta.

    Property 3 of the paper for the ``TwoLinkArm`` block, as used in eq. (4)-(5)
    (``zeta = z``, ``zetad = zdot``).  With c2 = cos q2, s2 = sin q2, q12 = q1 + q2 and the
    parameter vector theta = [a1, a2, a3, a4] (horizontal) or [a1, ..., a7] (gravity != 0),
    given by ``TwoLinkArm.parameter_vector``:

        Y[0] = [zd1, zd2, c2 (2 zd1 + zd2) - s2 (qd2 z1 + (qd1 + qd2) z2),
                s2 (2 zd1 + zd2) + c2 (qd2 z1 + (qd1 + qd2) z2), cos q1, cos q12, sin q12]
        Y[1] = [0, zd1 + zd2, c2 zd1 + s2 qd1 z1, s2 zd1 - c2 qd1 z1, 0, cos q12, sin q12]

    (the last three columns only with gravity).  The gravitational acceleration g is inside
    a5..a7, so only whether ``gravity`` is zero matters here: give it the same value as the
    plant's.  ``p: 5`` is the 5-parameter form theta = [a1, ..., a5] for a known g and l1:
    columns 3 and 4 gain (g / l1) cos q12 and (g / l1) sin q12 (a6 = g a3 / l1,
    a7 = g a4 / l1), the last two columns go.  The forms are listed once in TWO_LINK_FORMS;
    a plant whose gravity terms the form cannot express is refused when the diagram loads.

    Ports:
        | port  | direction | shape  | feedthrough            |
        | q     | in        | (2,)   | -                      |
        | qdot  | in        | (2,)   | -                      |
        | zeta  | in        | (2,)   | -                      |
        | zetad | in        | (2,)   | -                      |
        | Y     | out       | (2, p) | q, qdot, zeta, zetad   |

    Parameters:
        gravity: the plant's gravitational acceleration; 0 gives p = 4, anything else p = 7.
        p: 5 for the 5-parameter form (needs gravity != 0 and l1); 0 (default): 4 or 7 as
            above.
        l1: length of link 1 (m), for p = 5.
    """

    params = {
        "gravity": Param("float", 0.0, "the plant's gravitational acceleration (0: p = 4, "
                                       "else p = 7)"),
        "p": Param("int", 0, "5: the 5-parameter form [a1..a5] (needs gravity and l1); "
                             "0: 4 or 7 from gravity"),
        "l1": Param("float", 0.0, "length of link 1 (m), for p = 5"),
    }
    example = {"gravity": 9.81}
    #: NumPy path, batches: native code when llvmlite is installed (see TwoLinkArm)
    native_kernels = ("output",)
    native_wanted = _native_in_batches

    def setup(self, gravity, p, l1):
        self._gravity = gravity != 0.0
        self._p = 7 if self._gravity else 4
        if p not in (0, 5):
            raise ParameterError(f"block {self.name!r} parameter 'p' must be 0 (4 or 7 from "
                                 f"gravity) or 5, got {p}", block=self.name)
        if p == 5:
            if not self._gravity or l1 <= 0.0:
                raise ParameterError(f"block {self.name!r}: p = 5 ({TWO_LINK_FORMS[5]}) needs "
                                     f"gravity != 0 and l1 > 0", block=self.name)
            self._p = 5
            self.set_param("g_over_l1", [[gravity / l1]])
        for name in ("q", "qdot", "zeta", "zetad"):
            self.declare_input(name, (2,))
        self.declare_output("Y", (2, self._p), feedthrough=("q", "qdot", "zeta", "zetad"))
        self.finalize(1)

    def check_source(self, port, source, source_port):
        """At load time: a plant with gravity terms needs the gravity columns (p = 7); a
        horizontal plant with p = 7 is fine (a5..a7 = 0)."""
        if port != "q" or not isinstance(source, TwoLinkArm):
            return None
        if not self._gravity and np.any(source.p.theta[:, 4:] != 0.0):
            return ("the plant has gravity terms (a5..a7 != 0) but the regressor has none "
                    f"(gravity: 0, p = 4: {TWO_LINK_FORMS[4]}); give the Regressor the "
                    "plant's gravity")
        if self._p == 5:
            theta, k = source.p.theta[0], self.p.g_over_l1[0, 0, 0]
            if not np.allclose(theta[5:], k * theta[2:4], rtol=1e-12, atol=1e-12):
                return (f"the regressor's 5-parameter form needs a6 = (g/l1) a3 and "
                        f"a7 = (g/l1) a4 with its g/l1 = {k:g}, the plant has a3..a7 = "
                        f"{as_written(theta[2:])}; give both the same gravity and l1")
        return None

    def finalize(self, batch: int) -> None:
        if self._p == 5:
            self.set_kernels(output=regressor5_output, params=("g_over_l1",))
            return
        self.set_kernels(output=regressor_output if batch == 1 else regressor_output_batch,
                         static=(self._p,))


@register
class PointMass(MechanicalPlant):
    """n independent point masses: m qddot = tau + tau_star (eq. (1) with H = diag(m), C = g = 0).

    The simplest plant satisfying Properties 1-3; its regressor is ``PointMassRegressor``
    with theta = the n masses.  ``tau_star`` is optional: unconnected, it is zero.  State
    order: q (n values), then qdot (n values).

    Ports:
        | port     | direction | shape | feedthrough |
        | tau      | in        | (n,)  | -           |
        | tau_star | in        | (n,)  | -           |
        | q        | out       | (n,)  | -           |
        | qdot     | out       | (n,)  | -           |

    Parameters:
        mass: one mass shared by all axes, or n masses (positive).
        n: number of axes (default: the length of mass, q0 or qdot0, else 1).
        q0, qdot0: initial position and velocity (one number for all axes, or n numbers).
    """

    params = {
        "mass": Param("array", 1.0, "mass, scalar or one per axis (kg)"),
        "n": Param("int", None, "number of axes (default: inferred from mass, q0, qdot0)"),
        "q0": Param("array", 0.0, "initial position, scalar or (n,)"),
        "qdot0": Param("array", 0.0, "initial velocity, scalar or (n,)"),
    }
    example = {"mass": [1.0, 2.0], "q0": [0.5, -1.0]}

    @staticmethod
    def parameter_vector(mass=1.0, n=None, **ignored) -> np.ndarray:
        """The true theta for ``PointMassRegressor``: the n masses."""
        mass = np.asarray(mass, dtype=float)
        if n is None:
            n = mass.size if mass.ndim else 1
        return np.broadcast_to(mass, (int(n),)).copy()

    def setup(self, mass, n, q0, qdot0):
        if n is None:
            sizes = [np.asarray(v).size for v in (mass, q0, qdot0) if np.asarray(v).ndim > 0]
            n = sizes[0] if sizes else 1
        if n < 1:
            raise ParameterError(f"block {self.name!r} parameter 'n' must be at least 1, got {n}",
                                 block=self.name)
        n = self.require_size("n", n, MAX_BLOCK_STATES // 2)
        m = _vector_param(self, "mass", mass, n)
        if np.any(m <= 0.0):
            raise ParameterError(f"block {self.name!r} parameter 'mass' must be positive, "
                                 f"got {np.asarray(mass).tolist()}", block=self.name)
        self.declare_plant(n, q0, qdot0, unit="m", axis="axis")    # positions in metres
        self.set_param("inv_mass", 1.0 / m)
        self.set_kernels(output=point_mass_output, derivative=point_mass_derivative,
                         params=("inv_mass",))


@register
class PointMassRegressor(Block):
    """Point-mass regressor Y = diag(zetad), so that diag(m) zetad = Y theta with theta = m.

    Property 3 for the ``PointMass`` plant (C = 0, g = 0): one parameter per axis, the n
    masses (``PointMass.parameter_vector``), also when the plant's mass is a shared scalar.
    ``q`` and ``qdot`` are optional and unused; they make the ports those of ``Regressor``
    so a diagram can swap plants.

    Ports:
        | port  | direction | shape  | feedthrough |
        | q     | in        | (n,)   | -           |
        | qdot  | in        | (n,)   | -           |
        | zeta  | in        | (n,)   | -           |
        | zetad | in        | (n,)   | -           |
        | Y     | out       | (n, n) | zetad       |

    Parameters:
        n: number of axes.
    """

    params = {"n": Param("int", 1, "number of axes")}
    example = {"n": 3}

    def setup(self, n):
        if n < 1:
            raise ParameterError(f"block {self.name!r} parameter 'n' must be at least 1, got {n}",
                                 block=self.name)
        self._n = self.require_size("n", n, 1000)
        self._diag = np.arange(n)
        self.declare_input("q", (n,), optional=True)
        self.declare_input("qdot", (n,), optional=True)
        self.declare_input("zeta", (n,), optional=True)
        self.declare_input("zetad", (n,))
        self.declare_output("Y", (n, n), feedthrough=("zetad",))
        self.set_kernels(output=point_mass_regressor_output)


# --------------------------------------------------------------------------- n-link arm
MAX_LINKS = 100


def _n_link_values(block_name, lengths, masses, com, com_angle, inertias):
    """Validated per-link arrays (lengths, masses, com, com_angle in rad, inertias)."""
    def fail(message):
        return ParameterError(f"block {block_name!r} {message}", block=block_name)

    lengths = np.atleast_1d(np.asarray(lengths, dtype=float))
    if lengths.ndim != 1 or lengths.size < 1 or np.any(lengths <= 0.0):
        raise fail(f"parameter 'lengths' must be a list of positive link lengths, got "
                   f"{lengths.tolist()}")
    if lengths.size > MAX_LINKS:
        raise fail(f"has {lengths.size} links (limit {MAX_LINKS})")
    n = lengths.size

    def per_link(key, value, default):
        arr = np.asarray(default if value is None else value, dtype=float)
        if arr.ndim == 0:
            arr = np.full(n, float(arr))
        if arr.shape != (n,):
            raise fail(f"parameter {key!r} must be a number or {n} numbers (one per link), "
                       f"got shape {arr.shape}")
        return arr

    masses = per_link("masses", masses, 1.0)
    com = per_link("com", com, lengths / 2.0)
    angle = np.radians(per_link("com_angle", com_angle, 0.0))
    inertias = per_link("inertias", inertias, masses * lengths ** 2 / 12.0)
    if np.any(masses <= 0.0):
        raise fail(f"parameter 'masses' must be positive, got {masses.tolist()}")
    if np.any(com < 0.0) or np.any(inertias < 0.0):
        raise fail("parameters 'com' and 'inertias' must not be negative")
    if np.any(inertias + masses * com ** 2 <= 0.0):
        raise fail("has a link with no inertia about its joint (inertias + masses com^2 = 0): "
                   "the inertia matrix would be singular")
    return lengths, masses, com, angle, inertias


def n_link_theta(masses, com, angle, inertias) -> np.ndarray:
    """[m_i, m_i lc_i cos(angle_i), m_i lc_i sin(angle_i), I_i + m_i lc_i^2] for i = 1..n."""
    return np.stack([masses, masses * com * np.cos(angle), masses * com * np.sin(angle),
                     inertias + masses * com ** 2], axis=1).reshape(-1)


def n_link_theta_given(block_name, theta, lengths, masses, com, com_angle, inertias):
    """``theta`` given directly (4 per link, the order of n_link_theta), checked: no physical
    mass parameters alongside it, m_i > 0, inertia about each centre of mass >= 0 and about
    each joint > 0."""
    def fail(message):
        return ParameterError(f"block {block_name!r} {message}", block=block_name)

    lengths = _n_link_values(block_name, lengths, 1.0, None, 0.0, None)[0]
    given = [k for k, v, default in (("masses", masses, 1.0), ("com", com, None),
                                     ("com_angle", com_angle, 0.0), ("inertias", inertias, None))
             if (v is None) != (default is None) or (v is not None and np.any(
                 np.asarray(v, dtype=float) != default))]
    if given:
        raise fail(f"gets either 'theta' or the mass parameters, not both ('theta' and "
                   f"{given[0]!r} are set)")
    theta = np.asarray(theta, dtype=float)
    n = lengths.size
    if theta.shape != (4 * n,):
        raise fail(f"parameter 'theta' must have 4 numbers per link ({4 * n} for {n} links: "
                   f"[m, m lc cos, m lc sin, I + m lc^2] each), got shape {theta.shape}")
    m, sx, sy, J = theta.reshape(n, 4).T
    if np.any(m <= 0.0):
        raise fail(f"parameter 'theta' gives masses {m.tolist()}; they must be positive")
    if np.any(J - (sx ** 2 + sy ** 2) / m < -1e-12 * np.abs(J)) or np.any(J <= 0.0):
        raise fail("parameter 'theta' gives a link with negative inertia about its centre of "
                   "mass (need I + m lc^2 >= (m lc)^2 / m) or none about its joint")
    return theta.copy()


def n_link_output(t, x, tau, tau_star, lengths, theta, gravity):
    return plant_state_outputs(x)


def _suffix(a):
    """s[:, i] = a[:, i] + a[:, i + 1] + ... (sums over link i and the links beyond it)."""
    return ko.cumsum1(a[:, ::-1])[:, ::-1]


def n_link_derivative(t, x, tau, tau_star, lengths, theta, gravity):
    """dx = [qdot, H^-1 (tau + tau_star - C qdot - g)] with H, C, g of NLinkArm's docstring,
    in O(n^2) from sums over the outer links (points of the plane as complex numbers, a.b
    = Re(conj(a) b), a x b = Im(conj(a) b)).  With O_i the origin of joint i, w_i = s_i E_i the first moment of link i (theta's [sx, sy] rotated by
    phi_i = q_1 + ... + q_i) and S_b = sum_{i>=b} (m_i O_i + w_i), for a <= b:
    H_ab = sum_{i>=b} (m_i |O_i|^2 + 2 O_i.w_i + J_i) - (O_a + O_b).S_b
           + (sum_{i>=b} m_i) O_a.O_b;
    C qdot + g is the recursive Newton-Euler torque at qddot = 0: the force on link i is
    F_i = m_i A_i - phidot_i^2 w_i + j gravity m_i with A_i = -sum_{j<i} l_j phidot_j^2 E_j,
    and joint k carries sum_{i>=k} (O_i - O_k) x F_i + w_i x A_i + gravity w_i.x."""
    n = x.shape[1] // 2
    q = x[:, :n]
    qdot = x[:, n:]
    phid = ko.cumsum1(qdot)
    E = np.exp(1j * ko.cumsum1(q))                 # link directions, as complex numbers
    lE = lengths * E
    O = ko.cumsum1(lE) - lE                        # joint origins O_1 = 0, O_2, ..., O_n
    m = theta[:, 0::4]
    w = (theta[:, 1::4] + 1j * theta[:, 2::4]) * E  # first moments w_i = s_i E_i
    P = np.real(np.conj(O) * (m * O + 2.0 * w)) + theta[:, 3::4]
    S = _suffix(m * O + w)
    D = _suffix(m) * O - S
    # H_ab = row_b + O_a.D_b for a <= b: a product of (B, n, 3) and (B, 3, n), mirrored
    row = _suffix(P) - np.real(np.conj(O) * S)
    B = row.shape[0]
    L = np.ones((B, n, 3))
    L[:, :, 1] = np.real(O)
    L[:, :, 2] = np.imag(O)
    R = np.empty((B, 3, n))
    R[:, 0, :] = row
    R[:, 1, :] = np.real(D)
    R[:, 2, :] = np.imag(D)
    H = ko.symupper(ko.bmatmul(L, R))
    v2 = phid * phid
    lv = lE * v2
    A = lv - ko.cumsum1(lv)                        # A_i = -sum_{j<i} l_j phidot_j^2 E_j
    g = gravity[:, None]
    F = m * A - v2 * w + 1j * (g * m)
    T = np.imag(np.conj(O) * F + np.conj(w) * A) + g * np.real(w)
    bias = _suffix(T) - np.imag(np.conj(O) * _suffix(F))              # C qdot + g
    rhs = tau + tau_star - bias
    dx = np.empty((B, 2 * n))
    dx[:, :n] = qdot
    dx[:, n:] = ko.bsolve(H, rhs)
    return dx


def n_link_regressor_output(t, x, q, qdot, zeta, zetad, lengths, gravity, mask):
    """Y (B, n, 4n) of NLinkRegressor: H zetad + C zeta + g = Y theta with
    C = sum_i m_i Jv_i^T dJv_i/dt (so Hdot - 2C is skew-symmetric), theta ordered per link
    [m, sx, sy, J] as n_link_theta.  Points of the plane as complex numbers (a.b =
    Re(conj(a) b), a x b = Im(conj(a) b)); with E_i = exp(j phi_i),
    O_i the joint origins, Q_i = E_i (j psidot_i - phidot_i psi_i) (psi, psidot, phidot the
    cumulative sums of zeta, zetad, qdot) and A_i = sum_{j<i} l_j Q_j, every entry is
    Y[k, 4i + c] = alpha_ci + Ox_k beta_ci + Oy_k gamma_ci for k <= i (0 beyond; ``mask``):
    column m: alpha = O_i x A_i + gravity Ox_i, beta = -(Ay_i + gravity), gamma = Ax_i;
    column sx: alpha = (conj(E_i) A_i).y + gravity cos phi_i + O_i x Q_i, beta = -Qy_i,
    gamma = Qx_i; column sy: alpha = -gravity sin phi_i - (conj(E_i) A_i).x + O_i.Q_i,
    beta = -Qx_i, gamma = -Qy_i; column J: alpha = psidot_i, beta = gamma = 0."""
    B = max(q.shape[0], qdot.shape[0], zeta.shape[0], zetad.shape[0], gravity.shape[0])
    n = q.shape[1]
    zero = np.zeros((B, n))
    E = np.exp(1j * ko.cumsum1(q + zero))          # link directions, as complex numbers
    lE = lengths * E
    O = ko.cumsum1(lE) - lE                        # joint origins O_1 = 0, O_2, ..., O_n
    v = ko.cumsum1(zetad + zero)
    Q = E * (v * 1j - ko.cumsum1(qdot + zero) * ko.cumsum1(zeta + zero))
    lQ = lengths * Q
    A = ko.cumsum1(lQ) - lQ
    g = gravity[:, None] + zero
    EA = np.conj(E) * A
    OQ = np.conj(O) * Q
    L = np.ones((B, n, 3))
    L[:, :, 1] = np.real(O)
    L[:, :, 2] = np.imag(O)
    R = np.zeros((B, 3, 4 * n))
    R[:, 0, 0::4] = np.imag(np.conj(O) * A) + g * np.real(O)
    R[:, 1, 0::4] = -np.imag(A) - g
    R[:, 2, 0::4] = np.real(A)
    R[:, 0, 1::4] = np.imag(EA) + g * np.real(E) + np.imag(OQ)
    R[:, 1, 1::4] = -np.imag(Q)
    R[:, 2, 1::4] = np.real(Q)
    R[:, 0, 2::4] = np.real(OQ) - np.real(EA) - g * np.imag(E)
    R[:, 1, 2::4] = -np.real(Q)
    R[:, 2, 2::4] = -np.imag(Q)
    R[:, 0, 3::4] = v
    return (ko.bmatmul(L, R) * mask,)


@register
class NLinkArm(MechanicalPlant):
    """Planar n-link arm with revolute joints: H(q) qddot + C(q, qdot) qdot + g(q) = tau + tau_star.

    Equation (1) of the paper for a serial chain moving in a vertical (gravity != 0) or
    horizontal plane.  Link i has length l_i, mass m_i, its centre of mass at distance lc_i
    from joint i and at absolute angle q_1 + ... + q_i + com_angle_i, and inertia I_i about
    its centre of mass.  With Jv_i the Jacobian of that centre of mass,
    H = sum_i (m_i Jv_i^T Jv_i + I_i Jw_i^T Jw_i), C = sum_i m_i Jv_i^T dJv_i/dt (so Hdot - 2C
    is skew-symmetric, Property 2), g = dP/dq with P = gravity sum_i m_i y_i.  The lumped
    parameters of Property 3, matching ``NLinkRegressor``, are, per link,
    [m_i, m_i lc_i cos(com_angle_i), m_i lc_i sin(com_angle_i), I_i + m_i lc_i^2]
    (``NLinkArm.parameter_vector``).  ``TwoLinkArm`` is this arm with n = 2,
    com_angle = [0, -delta_e].  ``tau_star`` is optional: unconnected, it is zero.  The
    accelerations come from a batched linear solve.  State order: q (n), then qdot (n).

    Ports:
        | port     | direction | shape | feedthrough |
        | tau      | in        | (n,)  | -           |
        | tau_star | in        | (n,)  | -           |
        | q        | out       | (n,)  | -           |
        | qdot     | out       | (n,)  | -           |

    Parameters:
        lengths: the n link lengths (m); n is their number.
        masses: link masses (one number for all, or n; default 1).
        com: distances from each joint to its link's centre of mass (default: lengths / 2).
        com_angle: angle of each centre of mass off its link's axis (degrees; default 0).
        inertias: inertias about the centres of mass (default: uniform rods, m l^2 / 12).
        gravity: gravitational acceleration in the plane (default 0: horizontal plane).
        q0, qdot0: initial joint positions and velocities (one number or n numbers).
    """

    params = {
        "lengths": Param("array", [1.0, 1.0], "link lengths (m), one per link"),
        "masses": Param("array", 1.0, "link masses (kg): scalar or one per link"),
        "com": Param("array", None, "joint-to-centre-of-mass distances (default lengths / 2)"),
        "com_angle": Param("array", 0.0, "centre-of-mass angles off the link axes (degrees)"),
        "inertias": Param("array", None, "inertias about the centres of mass (default m l^2/12)"),
        "gravity": Param("float", 0.0, "gravitational acceleration (0: horizontal plane)"),
        "theta": Param("array", None, "the lumped parameters instead of masses, com, "
                                      "com_angle, inertias: 4 per link [m, m lc cos, m lc sin, "
                                      "I + m lc^2]"),
        "q0": Param("array", 0.0, "initial joint positions, scalar or (n,)"),
        "qdot0": Param("array", 0.0, "initial joint velocities, scalar or (n,)"),
    }
    example = {"lengths": [1.0, 0.8, 0.5], "masses": [2.0, 1.0, 0.5], "gravity": 9.81,
               "q0": [0.1, 0.2, -0.3]}

    @staticmethod
    def parameter_vector(lengths=(1.0, 1.0), masses=1.0, com=None, com_angle=0.0,
                         inertias=None, **ignored) -> np.ndarray:
        """The true theta (4n) for ``NLinkRegressor``; gravity, q0, qdot0 are ignored; with
        ``theta`` given, that theta."""
        if ignored.get("theta") is not None:
            return n_link_theta_given("NLinkArm", ignored["theta"], lengths, masses, com,
                                      com_angle, inertias)
        _, m, lc, angle, inertia = _n_link_values("NLinkArm", lengths, masses, com,
                                                  com_angle, inertias)
        return n_link_theta(m, lc, angle, inertia)

    def setup(self, lengths, masses, com, com_angle, inertias, gravity, theta, q0, qdot0):
        if theta is not None:
            theta = n_link_theta_given(self.name, theta, lengths, masses, com, com_angle,
                                       inertias)
            lengths = np.atleast_1d(np.asarray(lengths, dtype=float))
        else:
            lengths, m, lc, angle, inertia = _n_link_values(self.name, lengths, masses, com,
                                                            com_angle, inertias)
            theta = n_link_theta(m, lc, angle, inertia)
        n = lengths.size
        self.declare_plant(n, q0, qdot0)
        self.set_param("lengths", lengths)
        self.set_param("theta", theta)
        self.set_param("gravity", gravity)
        self.set_kernels(output=n_link_output, derivative=n_link_derivative,
                         params=("lengths", "theta", "gravity"))


@register
class NLinkRegressor(Block):
    """Planar n-link-arm regressor Y(q, qdot, zeta, zetad), H zetad + C zeta + g = Y theta.

    Property 3 for ``NLinkArm``, with theta = ``NLinkArm.parameter_vector`` ordered per link
    [m_i, m_i lc_i cos(com_angle_i), m_i lc_i sin(com_angle_i), I_i + m_i lc_i^2] (p = 4n;
    m_1 and, without gravity, other columns may be zero: the set is not minimal).  The link
    lengths (kinematics) and the gravitational acceleration are known, so they are
    parameters of this block; give them the plant's values.

    Ports:
        | port  | direction | shape   | feedthrough          |
        | q     | in        | (n,)    | -                    |
        | qdot  | in        | (n,)    | -                    |
        | zeta  | in        | (n,)    | -                    |
        | zetad | in        | (n,)    | -                    |
        | Y     | out       | (n, 4n) | q, qdot, zeta, zetad |

    Parameters:
        lengths: the n link lengths (m).
        gravity: gravitational acceleration in the plane (default 0).
    """

    params = {
        "lengths": Param("array", [1.0, 1.0], "link lengths (m), one per link"),
        "gravity": Param("float", 0.0, "gravitational acceleration (0: horizontal plane)"),
    }
    example = {"lengths": [1.0, 0.8, 0.5], "gravity": 9.81}

    def setup(self, lengths, gravity):
        lengths = _n_link_values(self.name, lengths, 1.0, None, 0.0, None)[0]
        n = self._n = lengths.size
        for name in ("q", "qdot", "zeta", "zetad"):
            self.declare_input(name, (n,))
        self.declare_output("Y", (n, 4 * n), feedthrough=("q", "qdot", "zeta", "zetad"))
        self.set_param("lengths", lengths)
        self.set_param("gravity", gravity)
        # [k, 4i + c] = (k <= i): joint k moves the links i >= k
        self.set_param("mask", np.repeat(np.triu(np.ones((n, n))), 4, axis=1))
        self.set_kernels(output=n_link_regressor_output, params=("lengths", "gravity", "mask"))

    def check_source(self, port, source, source_port):
        """At load time: the NLinkArm driving ``q`` must have these lengths and gravity."""
        if port != "q" or not isinstance(source, NLinkArm):
            return None
        for name in ("lengths", "gravity"):
            mine, theirs = getattr(self.p, name)[0], getattr(source.p, name)[0]
            if mine.shape != theirs.shape or np.any(mine != theirs):
                verb = "differ" if name == "lengths" else "differs"
                return (f"the regressor's {name} ({as_written(mine)}) {verb} from the plant's "
                        f"({as_written(theirs)}); give both blocks the same {name}")
        return None
