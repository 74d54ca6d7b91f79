"""Rigid-body algorithms of fixed-base robots (revolute and prismatic joints, chain or tree).

fwdstep's own forward kinematics, recursive Newton-Euler (inverse dynamics), composite
rigid-body algorithm (the inertia matrix H), forward dynamics (H and the Newton-Euler bias,
solved by an LDL^T factorisation) and the Slotine-Li regressor with the Christoffel C
(``Y theta = H zetad + C(q, qdot) zeta + g``), written once as kernels that

* run on the NumPy path batched over variants: every scalar of the algorithms is a column
  (B,) of the variants (or a shared (1,) column, or a plain number);
* trace in ``fwdstep.compiled.scalarize`` to straight-line code for the one robot: the robot's
  structure (``tree``: parents, joint kinds, placements, axes, and the gravitational
  acceleration) is read as plain numbers (``_structure``: a parameter the tracer folds in),
  the loops over joints unroll, and products with the structure's zeros and ones are left
  out at the Python level (``_mul``, ``_add``, ``_sub``) on both paths.

Conventions (pinocchio's, so pinocchio's model is the reference of the tests): joint i's
frame is placed in its parent's by ``E_i, p_i`` (rotation, translation) times the joint's
motion (a rotation by q_i about the unit axis a_i, or a translation by q_i along it); the
spatial velocity of body i is (w, v) in its own frame (v: velocity of the frame's origin);
the parameters of body i are pinocchio's ten [m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy,
I_xz, I_yz, I_zz] (first moment and inertia about the joint frame's origin, in that frame);
gravity is (0, 0, -g) in the base frame.  The derivations are in docs/urdf-regressor.md
(section "fwdstep's own algorithms").

The structure array (n, 17) per joint: [parent (-1: the base), kind (0 revolute,
1 prismatic), E (9, row-major), p (3), a (3)]; ``tree_from_pinocchio`` builds it.
"""
from __future__ import annotations

import numpy as np

#: columns of the structure array
STRUCTURE_WIDTH = 17
REVOLUTE, PRISMATIC = 0, 1


# --------------------------------------------------------------- scalars with structure
# A scalar is a column of variants (an array) or a plain Python float (the structure's
# numbers); products and sums with a plain 0, 1 or -1 are left out (exact).
def _mul(a, b):
    if a.__class__ is float:
        if a == 0.0:
            return 0.0
        if a == 1.0:
            return b
        if a == -1.0:
            return -b
    if b.__class__ is float:
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
        if b == -1.0:
            return -a
    return a * b


def _add(a, b):
    if a.__class__ is float and a == 0.0:
        return b
    if b.__class__ is float and b == 0.0:
        return a
    return a + b


def _sub(a, b):
    if b.__class__ is float and b == 0.0:
        return a
    if a.__class__ is float and a == 0.0:
        return -b
    return a - b


def _half(a):
    return _mul(0.5, a)


def _sum(*terms):
    acc = 0.0
    for t in terms:
        acc = _add(acc, t)
    return acc


def _dot(u, v):
    return _add(_add(_mul(u[0], v[0]), _mul(u[1], v[1])), _mul(u[2], v[2]))


def _cross(u, v):
    return (_sub(_mul(u[1], v[2]), _mul(u[2], v[1])),
            _sub(_mul(u[2], v[0]), _mul(u[0], v[2])),
            _sub(_mul(u[0], v[1]), _mul(u[1], v[0])))


def _vadd(u, v):
    return (_add(u[0], v[0]), _add(u[1], v[1]), _add(u[2], v[2]))


def _vsub(u, v):
    return (_sub(u[0], v[0]), _sub(u[1], v[1]), _sub(u[2], v[2]))


def _scale(s, u):
    return (_mul(s, u[0]), _mul(s, u[1]), _mul(s, u[2]))


def _rot(R, v):
    """R v, R a row-major 9-tuple."""
    return (_add(_add(_mul(R[0], v[0]), _mul(R[1], v[1])), _mul(R[2], v[2])),
            _add(_add(_mul(R[3], v[0]), _mul(R[4], v[1])), _mul(R[5], v[2])),
            _add(_add(_mul(R[6], v[0]), _mul(R[7], v[1])), _mul(R[8], v[2])))


def _rot_t(R, v):
    """R^T v."""
    return (_add(_add(_mul(R[0], v[0]), _mul(R[3], v[1])), _mul(R[6], v[2])),
            _add(_add(_mul(R[1], v[0]), _mul(R[4], v[1])), _mul(R[7], v[2])),
            _add(_add(_mul(R[2], v[0]), _mul(R[5], v[1])), _mul(R[8], v[2])))


def _matmul3(A, B):
    return tuple(_add(_add(_mul(A[3 * i], B[j]), _mul(A[3 * i + 1], B[3 + j])),
                      _mul(A[3 * i + 2], B[6 + j])) for i in range(3) for j in range(3))


ZERO3 = (0.0, 0.0, 0.0)


# ------------------------------------------------------------------------- structure
def _structure(tree):
    """The robot's structure as plain numbers: a list of (parent, kind, E, p, a), and the
    gravitational acceleration, from the parameter arrays ``tree`` (Bp, n, 17) and
    ``gravity`` (Bp, 1) (the first variant: the structure is the same in every variant;
    traced, these are the constants the code is written for)."""
    rows = tree[0].astype("f8").tolist()
    return [(int(r[0]), int(r[1]), tuple(r[2:11]), tuple(r[11:14]), tuple(r[14:17]))
            for r in rows]


def _gravity(gravity):
    return gravity[0].astype("f8").tolist()[0]


def _joint_transforms(S, q):
    """[(R_i, p_i)]: joint i's frame in its parent's frame at q (R row-major)."""
    out = []
    for i, (parent, kind, E, p, a) in enumerate(S):
        qi = q[:, i]
        if kind == REVOLUTE:
            c, s = np.cos(qi), np.sin(qi)
            # Rot(a, q) = a a^T + c (I - a a^T) + s [a]x
            skew = (0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0)
            rot = []
            for r in range(3):
                for k in range(3):
                    aa = a[r] * a[k]
                    rot.append(_add(_add(aa, _mul(c, (1.0 if r == k else 0.0) - aa)),
                                    _mul(s, skew[3 * r + k])))
            out.append((_matmul3(E, tuple(rot)), p))
        else:
            out.append((E, _vadd(p, _scale(qi, _rot(E, a)))))
    return out


def _motion_to_child(X, w, v):
    """A motion (w, v) of the parent's frame seen in the child's frame X = (R, p)."""
    R, p = X
    return _rot_t(R, w), _rot_t(R, _vadd(v, _cross(w, p)))


def _force_to_parent(X, n, f):
    """A force (n, f) (moment about the child's origin, force) in the parent's frame."""
    R, p = X
    rf = _rot(R, f)
    return _vadd(_rot(R, n), _cross(p, rf)), rf


def _inertia_times(th, u):
    """I u, I the rotational inertia of the ten parameters th."""
    return (_add(_add(_mul(th[4], u[0]), _mul(th[5], u[1])), _mul(th[7], u[2])),
            _add(_add(_mul(th[5], u[0]), _mul(th[6], u[1])), _mul(th[8], u[2])),
            _add(_add(_mul(th[7], u[0]), _mul(th[8], u[1])), _mul(th[9], u[2])))


def _body_force(th, w, aw, alpha, wIw):
    """(n, f) of body parameters th with angular velocity w, angular acceleration aw,
    acceleration of the origin alpha (= a_v + w x v) and the gyroscopic term wIw
    (= w x I w): f = m alpha + aw x h + w x (w x h), n = I aw + wIw - alpha x h."""
    h = (th[1], th[2], th[3])
    f = _vadd(_vadd(_scale(th[0], alpha), _cross(aw, h)), _cross(w, _cross(w, h)))
    n = _vsub(_vadd(_inertia_times(th, aw), wIw), _cross(alpha, h))
    return n, f


def _subspace(kind, a):
    """The joint's motion subspace (angular, linear) in its own frame."""
    return (a, ZERO3) if kind == REVOLUTE else (ZERO3, a)


def _project(kind, a, n, f):
    """S^T (n, f)."""
    return _dot(a, n) if kind == REVOLUTE else _dot(a, f)


def _theta_columns(theta, i):
    return tuple(theta[:, 10 * i + c] for c in range(10))


def _batch(*arrays):
    return max(a.shape[0] for a in arrays)


def _fill(B, columns):
    """(B, len(columns)) from scalars."""
    out = np.empty((B, len(columns)))
    for i, c in enumerate(columns):
        out[:, i] = c
    return out


# ------------------------------------------------------------------------ algorithms
def _rnea(S, g, X, theta, qd, qdd, with_velocity=True):
    """Joint torques H qdd + C qd qd + g of the structure S (list of floats) at the joint
    transforms X; qd, qdd (B, n) arrays or None (zero)."""
    n = len(S)
    W, V, AW, AV, F = [None] * n, [None] * n, [None] * n, [None] * n, [None] * n
    for i, (parent, kind, E, p, a) in enumerate(S):
        if parent < 0:
            w0, v0, aw0, av0 = ZERO3, ZERO3, ZERO3, (0.0, 0.0, g)
        else:
            w0, v0, aw0, av0 = W[parent], V[parent], AW[parent], AV[parent]
        w, v = _motion_to_child(X[i], w0, v0)
        aw, av = _motion_to_child(X[i], aw0, av0)
        sw, sv = _subspace(kind, a)
        if qd is not None:
            qdi = qd[:, i]
            jw, jv = _scale(qdi, sw), _scale(qdi, sv)
            # a += v_i x S qd_i (w, v before the joint's own motion: S x S = 0)
            aw = _vadd(aw, _cross(w, jw))
            av = _vadd(av, _vadd(_cross(w, jv), _cross(v, jw)))
            w, v = _vadd(w, jw), _vadd(v, jv)
        if qdd is not None:
            aw = _vadd(aw, _scale(qdd[:, i], sw))
            av = _vadd(av, _scale(qdd[:, i], sv))
        W[i], V[i], AW[i], AV[i] = w, v, aw, av
        th = _theta_columns(theta, i)
        alpha = _vadd(av, _cross(w, v))
        F[i] = _body_force(th, w, aw, alpha, _cross(w, _inertia_times(th, w)))
    tau = [None] * n
    for i in range(n - 1, -1, -1):
        parent, kind, E, p, a = S[i]
        nf, ff = F[i]
        tau[i] = _project(kind, a, nf, ff)
        if parent >= 0:
            pn, pf = _force_to_parent(X[i], nf, ff)
            F[parent] = (_vadd(F[parent][0], pn), _vadd(F[parent][1], pf))
    return tau


def _transform_inertia(X, th):
    """Ten parameters of a body seen from its parent's frame (parallel axis theorem):
    h' = R h + m p, I' = R I R^T + m (|p|^2 1 - p p^T) - (h_r p^T + p h_r^T) + 2 (p.h_r) 1."""
    R, p = X
    m = th[0]
    hr = _rot(R, (th[1], th[2], th[3]))
    Ib = (th[4], th[5], th[7], th[5], th[6], th[8], th[7], th[8], th[9])
    T = _matmul3(R, Ib)
    Rt = (R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8])
    RIR = _matmul3(T, Rt)
    pp = _dot(p, p)
    ph2 = _mul(2.0, _dot(p, hr))

    def entry(i, j):
        e = _sub(RIR[3 * i + j], _add(_mul(hr[i], p[j]), _mul(p[i], hr[j])))
        mp = _sub(pp, p[i] * p[j]) if i == j else _mul(-1.0, p[i] * p[j])
        e = _add(e, _mul(m, mp))
        return _add(e, ph2) if i == j else e

    h = _vadd(hr, _scale(m, p))
    return (m, h[0], h[1], h[2], entry(0, 0), entry(0, 1), entry(1, 1), entry(0, 2),
            entry(1, 2), entry(2, 2))


def _crba(S, X, theta):
    """H as a list of rows of scalars (plain 0.0 where two joints are on separate
    branches)."""
    n = len(S)
    Ic = [_theta_columns(theta, i) for i in range(n)]
    for i in range(n - 1, -1, -1):
        parent = S[i][0]
        if parent >= 0:
            t = _transform_inertia(X[i], Ic[i])
            Ic[parent] = tuple(_add(x, y) for x, y in zip(Ic[parent], t))
    H = [[0.0] * n for _ in range(n)]
    for j in range(n):
        parent, kind, E, p, a = S[j]
        th = Ic[j]
        h = (th[1], th[2], th[3])
        if kind == REVOLUTE:              # I (a, 0) = (I a, a x h)
            nf, ff = _inertia_times(th, a), _cross(a, h)
        else:                             # I (0, a) = (h x a, m a)
            nf, ff = _cross(h, a), _scale(th[0], a)
        H[j][j] = _project(kind, a, nf, ff)
        i = j
        while S[i][0] >= 0:
            nf, ff = _force_to_parent(X[i], nf, ff)
            i = S[i][0]
            H[i][j] = H[j][i] = _project(S[i][1], S[i][4], nf, ff)
    return H


def _ldl_solve(H, b):
    """x with H x = b, H symmetric positive definite (lists of scalars), by H = L D L^T
    (no pivoting: the same operations for every state, so it traces)."""
    n = len(b)
    L = [[0.0] * n for _ in range(n)]
    D = [0.0] * n
    for j in range(n):
        d = H[j][j]
        for k in range(j):
            d = _sub(d, _mul(_mul(L[j][k], L[j][k]), D[k]))
        D[j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            e = H[i][j]
            for k in range(j):
                e = _sub(e, _mul(_mul(L[i][k], L[j][k]), D[k]))
            L[i][j] = _mul(e, inv)
    y = list(b)
    for i in range(n):
        for k in range(i):
            y[i] = _sub(y[i], _mul(L[i][k], y[k]))
    x = [y[i] / D[i] for i in range(n)]
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, n):
            x[i] = _sub(x[i], _mul(L[k][i], x[k]))
    return x


# --------------------------------------------------------------------------- kernels
def rnea(tree, gravity, theta, q, qd, qdd):
    """tau = H(q) qdd + C(q, qd) qd + g(q) (B, n): inverse dynamics."""
    S, g = _structure(tree), _gravity(gravity)
    tau = _rnea(S, g, _joint_transforms(S, q), theta, qd, qdd)
    return _fill(_batch(theta, q, qd, qdd), tau)


def gravity_torque(tree, gravity, theta, q):
    """g(q) (B, n)."""
    S, g = _structure(tree), _gravity(gravity)
    tau = _rnea(S, g, _joint_transforms(S, q), theta, None, None)
    return _fill(_batch(theta, q), tau)


def mass_matrix(tree, theta, q):
    """H(q) (B, n, n) by the composite rigid-body algorithm."""
    S = _structure(tree)
    H = _crba(S, _joint_transforms(S, q), theta)
    n = len(S)
    out = np.empty((_batch(theta, q), n, n))
    for i in range(n):
        for j in range(n):
            out[:, i, j] = H[i][j]
    return out


def forward_dynamics(tree, gravity, theta, q, qd, tau):
    """qdd = H(q)^-1 (tau - C(q, qd) qd - g(q)) (B, n)."""
    S, g = _structure(tree), _gravity(gravity)
    X = _joint_transforms(S, q)
    bias = _rnea(S, g, X, theta, qd, None)
    rhs = [_sub(tau[:, i], bias[i]) for i in range(len(S))]
    return _fill(_batch(theta, q, qd, tau), _ldl_solve(_crba(S, X, theta), rhs))


def _regressor_entries(S, g, X, qd, zeta, zetad, columns):
    """{column: [Y_0, ..., Y_{n-1}] scalars} for the wanted columns of the Slotine-Li
    regressor with the Christoffel C (the symmetric bilinear form of the Newton-Euler
    velocity terms: every product of two velocities v(qd) v(qd) is replaced by
    1/2 (v(qd) v(zeta) + v(zeta) v(qd)); docs/urdf-regressor.md)."""
    n = len(S)
    W1, V1, W2, V2, AW, AV = ([None] * n for _ in range(6))
    body = [None] * n
    for i, (parent, kind, E, p, a) in enumerate(S):
        if parent < 0:
            w1 = v1 = w2 = v2 = aw = ZERO3
            av = (0.0, 0.0, g)
        else:
            w1, v1, w2, v2 = W1[parent], V1[parent], W2[parent], V2[parent]
            aw, av = AW[parent], AV[parent]
        w1, v1 = _motion_to_child(X[i], w1, v1)
        w2, v2 = _motion_to_child(X[i], w2, v2)
        aw, av = _motion_to_child(X[i], aw, av)
        sw, sv = _subspace(kind, a)
        q1, q2 = qd[:, i], zeta[:, i]
        # a += 1/2 (v1 x S zeta_i + v2 x S qd_i) + S zetad_i
        u = _scale(0.5, _vadd(_scale(q2, w1), _scale(q1, w2)))
        if kind == REVOLUTE:
            aw = _vadd(aw, _cross(u, a))
            av = _vadd(av, _cross(_scale(0.5, _vadd(_scale(q2, v1), _scale(q1, v2))), a))
        else:
            av = _vadd(av, _cross(u, a))
        aw = _vadd(aw, _scale(zetad[:, i], sw))
        av = _vadd(av, _scale(zetad[:, i], sv))
        w1, v1 = _vadd(w1, _scale(q1, sw)), _vadd(v1, _scale(q1, sv))
        w2, v2 = _vadd(w2, _scale(q2, sw)), _vadd(v2, _scale(q2, sv))
        W1[i], V1[i], W2[i], V2[i], AW[i], AV[i] = w1, v1, w2, v2, aw, av
        alpha = _vadd(av, _scale(0.5, _vadd(_cross(w1, v2), _cross(w2, v1))))
        # h columns: s_v -> s_v x aw + P s_v, P = 1/2 (w1 w2^T + w2 w1^T) - (w1.w2) 1
        w12 = _dot(w1, w2)
        P = [[_sub(_half(_add(_mul(w1[r], w2[c]), _mul(w2[r], w1[c]))),
                   w12 if r == c else 0.0) for c in range(3)] for r in range(3)]
        # I columns: s_w^T N, N_c = L_c(aw) + 1/2 (w1 x L_c(w2) + w2 x L_c(w1)),
        # L_c(u) the column c of I u = L(u) [xx, xy, yy, xz, yz, zz]
        N = []
        for c in range(6):
            def L(u, c=c):
                return ((u[0], 0.0, 0.0), (u[1], u[0], 0.0), (0.0, u[1], 0.0),
                        (u[2], 0.0, u[0]), (0.0, u[2], u[1]), (0.0, 0.0, u[2]))[c]
            N.append(_vadd(L(aw), _scale(0.5, _vadd(_cross(w1, L(w2)), _cross(w2, L(w1))))))
        body[i] = (aw, alpha, P, N)
    Y = {}
    for k in range(n):
        aw, alpha, P, N = body[k]
        wanted = [c for c in range(10) if (10 * k + c) in columns]
        if not wanted:
            continue
        rows = [0.0] * n
        cols = {c: list(rows) for c in wanted}
        # joint j's subspace seen in body k's frame, for j = k and its ancestors
        chain = [k]
        while S[chain[-1]][0] >= 0:
            chain.append(S[chain[-1]][0])
        for j in chain:
            sw, sv = _subspace(S[j][1], S[j][4])
            path = []
            i = k
            while i != j:
                path.append(i)
                i = S[i][0]
            for i in reversed(path):
                sw, sv = _motion_to_child(X[i], sw, sv)
            for c in wanted:
                if c == 0:
                    e = _dot(sv, alpha)
                elif c < 4:
                    r = c - 1
                    e = _sum(_sub(_mul(sv[(r + 1) % 3], aw[(r + 2) % 3]),
                                  _mul(sv[(r + 2) % 3], aw[(r + 1) % 3])),
                             _dot(P[r], sv),
                             _sub(_mul(alpha[(r + 1) % 3], sw[(r + 2) % 3]),
                                  _mul(alpha[(r + 2) % 3], sw[(r + 1) % 3])))
                else:
                    e = _dot(sw, N[c - 4])
                cols[c][j] = e
        for c in wanted:
            Y[10 * k + c] = cols[c]
    return Y


def regressor(tree, gravity, columns, q, qd, zeta, zetad):
    """Y (B, n, p): Y theta = H(q) zetad + C(q, qd) zeta + g(q) with C the Christoffel
    matrix, for the columns of the full regressor listed in ``columns`` (Bp, p) (all 10 n
    for theta of ten parameters per body; the independent ones for base parameters)."""
    S, g = _structure(tree), _gravity(gravity)
    wanted = [int(c) for c in columns[0].astype("f8").tolist()]
    entries = _regressor_entries(S, g, _joint_transforms(S, q), qd, zeta, zetad,
                                 set(wanted))
    n = len(S)
    Y = np.zeros((_batch(q, qd, zeta, zetad), n, len(wanted)))
    for col, c in enumerate(wanted):
        e = entries[c]
        for j in range(n):
            if e[j].__class__ is not float or e[j] != 0.0:
                Y[:, j, col] = e[j]
    return Y


def frame_placements(tree, q):
    """(positions (B, n, 3), rotations (B, n, 3, 3)) of every joint frame in the base
    frame: forward kinematics."""
    S = _structure(tree)
    X = _joint_transforms(S, q)
    n = len(S)
    Rw, pw = [None] * n, [None] * n
    for i, (parent, kind, E, p, a) in enumerate(S):
        R, t = X[i]
        if parent < 0:
            Rw[i], pw[i] = R, t
        else:
            Rw[i] = _matmul3(Rw[parent], R)
            pw[i] = _vadd(pw[parent], _rot(Rw[parent], t))
    B = q.shape[0]
    pos = np.empty((B, n, 3))
    rot = np.empty((B, n, 3, 3))
    for i in range(n):
        for r in range(3):
            pos[:, i, r] = pw[i][r]
            for c in range(3):
                rot[:, i, r, c] = Rw[i][3 * r + c]
    return pos, rot


def frame_kinematics(tree, frame, q, qd):
    """Pose, Jacobian and Jdot qdot of one frame fixed to a body: ``frame`` (Bp, 13) holds
    [joint index k (0-based), R (9, row-major), p (3)], the frame's placement in joint k's
    frame.  Returns position (B, 3) and rotation (B, 3, 3) in the base frame, J (B, 6, n)
    with [v; w] = J qdot (velocity of the frame's origin and angular velocity, base axes:
    pinocchio's LOCAL_WORLD_ALIGNED) and the acceleration of the origin and angular
    acceleration at qddot = 0, (B, 6) (so [a; alpha] = J qddot + Jdot qdot)."""
    S = _structure(tree)
    f = frame[0].astype("f8").tolist()
    k, Rf, pf = int(f[0]), tuple(f[1:10]), tuple(f[10:13])
    X = _joint_transforms(S, q)
    n = len(S)
    chain = [k]
    while S[chain[-1]][0] >= 0:
        chain.append(S[chain[-1]][0])
    chain.reverse()
    # world placements of the chain's joints, and body velocity / bias acceleration
    Rw, ow = {}, {}
    w, v, aw, av = ZERO3, ZERO3, ZERO3, ZERO3
    for i in chain:
        parent, kind, E, p, a = S[i]
        R, t = X[i]
        if parent < 0:
            Rw[i], ow[i] = R, t
        else:
            Rw[i], ow[i] = _matmul3(Rw[parent], R), _vadd(ow[parent], _rot(Rw[parent], t))
        w, v = _motion_to_child(X[i], w, v)
        aw, av = _motion_to_child(X[i], aw, av)
        sw, sv = _subspace(kind, a)
        jw, jv = _scale(qd[:, i], sw), _scale(qd[:, i], sv)
        aw = _vadd(aw, _cross(w, jw))
        av = _vadd(av, _vadd(_cross(w, jv), _cross(v, jw)))
        w, v = _vadd(w, jw), _vadd(v, jv)
    Rk = Rw[k]
    position = _vadd(ow[k], _rot(Rk, pf))
    rotation = _matmul3(Rk, Rf)
    B = max(q.shape[0], qd.shape[0])
    J = np.zeros((B, 6, n))
    for i in chain:
        kind, a = S[i][1], S[i][4]
        axis = _rot(Rw[i], a)
        lin = _cross(axis, _vsub(position, ow[i])) if kind == REVOLUTE else axis
        for r in range(3):
            J[:, r, i] = lin[r]
            if kind == REVOLUTE:
                J[:, 3 + r, i] = axis[r]
    # classical acceleration of the point pf: a_v + w x v + aw x pf + w x (w x pf)
    acc = _vadd(_vadd(av, _cross(w, v)), _vadd(_cross(aw, pf), _cross(w, _cross(w, pf))))
    bias = _fill(B, _rot(Rk, acc) + _rot(Rk, aw))
    pos = _fill(B, position)
    rot = np.empty((B, 3, 3))
    for r in range(3):
        for c in range(3):
            rot[:, r, c] = rotation[3 * r + c]
    return pos, rot, J, bias


# ------------------------------------------------------------------- model extraction
def _snap(v: float) -> float:
    """The structure's numbers with rounding noise of unit rotations (cos(pi/2) = 6e-17)
    removed, so the generated code leaves those products out."""
    for exact in (0.0, 1.0, -1.0):
        if abs(v - exact) < 1e-14:
            return exact
    return float(v)


def tree_from_pinocchio(model) -> np.ndarray:
    """The structure array (n, 17) of a pinocchio model of 1-degree-of-freedom revolute or
    prismatic joints (raises ValueError naming the first other joint)."""
    rows = []
    for i in range(1, model.njoints):
        joint = model.joints[i]
        short = joint.shortname()
        if short in ("JointModelRX", "JointModelRY", "JointModelRZ"):
            kind, axis = REVOLUTE, np.eye(3)["XYZ".index(short[-1])]
        elif short in ("JointModelPX", "JointModelPY", "JointModelPZ"):
            kind, axis = PRISMATIC, np.eye(3)["XYZ".index(short[-1])]
        elif short == "JointModelRevoluteUnaligned":
            kind, axis = REVOLUTE, np.asarray(joint.extract().axis, dtype=float)
        elif short == "JointModelPrismaticUnaligned":
            kind, axis = PRISMATIC, np.asarray(joint.extract().axis, dtype=float)
        else:
            raise ValueError(f"joint {model.names[i]!r} is a {short}: only revolute and "
                             f"prismatic joints are supported")
        placement = model.jointPlacements[i]
        row = [float(model.parents[i] - 1), float(kind)]
        row += [_snap(v) for v in np.asarray(placement.rotation).reshape(-1)]
        row += [_snap(v) for v in np.asarray(placement.translation)]
        row += [_snap(v) for v in axis / np.linalg.norm(axis)]
        rows.append(row)
    return np.array(rows, dtype=float)


def frame_from_pinocchio(model, name: str) -> np.ndarray:
    """[joint index (0-based), R (9), p (3)] of a pinocchio frame (a URDF link or joint);
    KeyError when the model has no such frame."""
    if not model.existFrame(name):
        raise KeyError(name)
    fr = model.frames[model.getFrameId(name)]
    joint = getattr(fr, "parentJoint", None)
    joint = fr.parent if joint is None else joint
    if joint < 1:
        raise KeyError(name)
    R = [_snap(v) for v in np.asarray(fr.placement.rotation).reshape(-1)]
    return np.array([float(joint - 1)] + R
                    + [_snap(v) for v in np.asarray(fr.placement.translation)])


def theta_from_pinocchio(model) -> np.ndarray:
    """theta (10 n): pinocchio's dynamic parameters of every moving body."""
    return np.concatenate([model.inertias[j].toDynamicParameters()
                           for j in range(1, model.njoints)])
