"""Identification (issue 28, item 3) on a simulated Franka Panda: the true BASE parameters
come from pinocchio alone (its joint-torque regressor at random states, the URDF inertias,
our own pivoted QR), never from fwdstep's regressor, plant or estimator."""
import os

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")
scipy_linalg = pytest.importorskip("scipy.linalg")

import fwdstep  # noqa: E402
from fwdstep.analysis.identify import (estimate, filtered_regressor, least_squares,  # noqa: E402
                                       parameter_names)
from fwdstep.blocks.urdf import NAMED_ROBOTS, _robots_folder  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DIAGRAM = os.path.join(ROOT, "diagrams", "robots", "panda_identification.yaml")
SHORT = {"t_final": 2}          # 4001 samples, 0.5 ms apart: a 1 s simulation
BANDWIDTH = 20.0


def reference():
    """(model, data) of the Panda loaded with pinocchio directly (fingers locked)."""
    relative, locked = NAMED_ROBOTS["panda"]
    model = pin.buildModelFromUrdf(str(_robots_folder("test") / relative))
    model = pin.buildReducedModel(model, [model.getJointId(j) for j in locked],
                                  pin.neutral(model))
    model.gravity.linear = np.array([0.0, 0.0, -9.81])
    return model, model.createData()


def true_base_parameters(Y_block):
    """beta with Y_base beta = R theta for every state (R pinocchio's regressor, theta the
    URDF inertias), on the columns of R that the block's base regressor holds.  Which
    columns those are is read by matching the block's output to R at one state (the
    parameterisation is a choice; its values are computed here)."""
    model, data = reference()
    n = model.nv
    theta = np.concatenate([model.inertias[j].toDynamicParameters()
                            for j in range(1, model.njoints)])
    rng = np.random.default_rng(7)
    W = np.vstack([pin.computeJointTorqueRegressor(model, data, pin.randomConfiguration(model),
                                                   rng.normal(size=n), rng.normal(size=n)).copy()
                   for _ in range(60)])
    R = scipy_linalg.qr(W, mode="r", pivoting=True)[0]
    rank = int(np.sum(np.abs(np.diag(R)) > 1e-8 * abs(R[0, 0])))
    q, v, a = pin.randomConfiguration(model), rng.normal(size=n), rng.normal(size=n)
    full = pin.computeJointTorqueRegressor(model, data, q, v, a).copy()
    mine = np.asarray(Y_block.output(0.0, np.zeros((1, 0)), (q[None], v[None], v[None],
                                                           a[None]))[0])[0]
    scale = np.abs(full).max()
    cols = [int(np.argmin(np.abs(full - mine[:, [c]]).max(axis=0)))
            for c in range(mine.shape[1])]
    assert np.abs(full[:, cols] - mine).max() < 1e-10 * scale
    beta, *_ = np.linalg.lstsq(W[:, cols], W @ theta, rcond=None)
    assert np.abs(W[:, cols] @ beta - W @ theta).max() < 1e-9 * np.abs(W @ theta).max()
    return beta, rank, np.array(model.damping, dtype=float)


@pytest.fixture(scope="module")
def panda_run():
    d = fwdstep.load_diagram(DIAGRAM, SHORT)
    r = fwdstep.simulate(d)
    Y = {b.name: b for b in d.blocks}["Y"]
    beta, rank, damping = true_base_parameters(Y)
    return r, Y, beta, rank, damping


def test_the_base_parameters_are_pinocchios(panda_run):
    r, Y, beta, rank, _ = panda_run
    assert rank == len(beta) == 43            # our QR of pinocchio's regressor: 43 of 70
    assert np.abs(r["arm.theta"][0] - beta).max() < 1e-9 * np.abs(beta).max()


def test_noiseless_panda_run_gives_the_true_base_parameters(panda_run):
    r, Y, beta, _, damping = panda_run
    truth = np.r_[beta, damping]               # 43 base parameters, 7 viscous frictions
    ident = estimate(r.t, r["arm.q"], r["arm.qdot"], r["tau.y"], Y, bandwidth=BANDWIDTH,
                     friction="viscous")
    assert ident.names == parameter_names(Y, "viscous") and len(ident.theta) == 50
    assert ident.rank == 50
    error = np.abs(ident.theta - truth)
    assert error.max() <= 1e-6 * np.abs(truth).max()        # measured 7e-11
    assert np.all(error <= 1e-6 * np.abs(truth))            # each one: measured 4e-8


def test_unmodelled_friction_biases_the_estimate(panda_run):
    """The Panda's URDF damping (0.003 N m s/rad) left out: the fit is visibly wrong."""
    r, Y, beta, _, _ = panda_run
    ident = estimate(r.t, r["arm.q"], r["arm.qdot"], r["tau.y"], Y, bandwidth=BANDWIDTH)
    assert np.abs(ident.theta - beta).max() > 1e-3 * np.abs(beta).max()


def test_with_torque_noise_the_intervals_hold_the_truth(panda_run):
    r, Y, beta, _, damping = panda_run
    truth = np.r_[beta, damping]
    Phi = filtered_regressor(r.t, r["arm.q"], r["arm.qdot"], Y, BANDWIDTH, "viscous")
    z = []
    for seed in range(8):
        noisy = r["tau.y"] + np.random.default_rng(seed).normal(0, 0.5, r["tau.y"].shape)
        ident = least_squares(r.t, Phi, noisy, BANDWIDTH, confidence=0.95, truth=truth)
        inside = ident.to_dict()["inside_interval"]
        assert len(inside) == 50
        z.append((ident.theta - truth) / ident.std)
    z = np.array(z)
    assert np.mean(np.abs(z) < 1.96) >= 0.85      # 95 % intervals: 8 seeds x 50 parameters
    assert 0.75 < z.std() < 1.3
    assert np.abs(z).max() < 4.5


@pytest.mark.slow
def test_the_shipped_run_long_version():
    """The diagram as shipped (4 s), 20 noise seeds: measured 94.9 % inside, z std 1.00."""
    d = fwdstep.load_diagram(DIAGRAM)
    r = fwdstep.simulate(d)
    Y = {b.name: b for b in d.blocks}["Y"]
    beta, _, damping = true_base_parameters(Y)
    truth = np.r_[beta, damping]
    Phi = filtered_regressor(r.t, r["arm.q"], r["arm.qdot"], Y, BANDWIDTH, "viscous")
    exact = least_squares(r.t, Phi, r["tau.y"], BANDWIDTH)
    assert np.all(np.abs(exact.theta - truth) <= 1e-6 * np.abs(truth))    # measured 1.4e-7
    z = []
    for seed in range(20):
        noisy = r["tau.y"] + np.random.default_rng(seed).normal(0, 0.5, r["tau.y"].shape)
        ident = least_squares(r.t, Phi, noisy, BANDWIDTH, truth=truth)
        z.append((ident.theta - truth) / ident.std)
    z = np.array(z)
    assert np.mean(np.abs(z) < 1.96) >= 0.9
    assert 0.85 < z.std() < 1.15
