"""Theorem 1 (eq. (2)-(5)) and the Slotine-Li baseline as shipped diagrams.

diagrams/theorem1.yaml chooses q_d as a polynomial of degree ell - 1 per joint, so
d^ell q_d = d^(ell+1) q_d = 0 (Theorem 1's assumption) for every ell; the theorem then
promises Delta q -> 0 and Delta qdot -> 0.  The Done-when of issue 2 asks for a final
tracking error below 1e-4 rad for ell = 1, 2, 3.  Measured with the shipped gains (10 s at
step 2e-3, rk4): 2.8e-13 (ell = 1), 1.0e-9 (ell = 2), 5.2e-9 (ell = 3); 5e-7 for ell = 4.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

import fwdstep
from fwdstep.structure.spec import load_spec

DIAGRAMS = os.path.join(os.path.dirname(__file__), "..", "..", "diagrams")
THEOREM1 = os.path.join(DIAGRAMS, "theorem1.yaml")
THEOREM1_SINE = os.path.join(DIAGRAMS, "theorem1_sine.yaml")
SLOTINE_LI = os.path.join(DIAGRAMS, "slotine_li.yaml")


def joint_norm(e: np.ndarray) -> np.ndarray:
    return np.linalg.norm(e, axis=-1)


@pytest.mark.parametrize("ell", [1, 2, 3])
def test_desired_position_meets_the_assumption_of_theorem_1(ell):
    """q_d is a polynomial of degree exactly ell - 1: d^ell q_d = d^(ell+1) q_d = 0."""
    spec = load_spec(THEOREM1, {"ell": ell})
    coefficients = spec.parameters["qd_coefficients"]
    assert coefficients.shape == (2, ell)            # ascending powers t^0 .. t^(ell-1)
    assert np.all(coefficients[:, -1] != 0)          # degree exactly ell - 1
    # and the q_d the diagram produces is that polynomial (checked on the logged signal)
    r = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, {"ell": ell, "t_final": 1}))
    t = r.t
    expected = np.stack([np.polyval(c[::-1], t) for c in coefficients], axis=1)
    np.testing.assert_allclose(r["qd.y"], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ell", [1, 2, 3])
def test_theorem1_tracking_error_converges(ell):
    r = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, {"ell": ell}))
    assert r.status == "ok"
    e = r["e.y"]
    assert e.shape == (len(r.t), 2)
    norm = joint_norm(e)
    assert norm[0] > 0.2                              # it starts off target ...
    assert norm[-1] < 1e-4                            # ... and converges (Done-when)
    assert r.metrics()["tail_error_norm_max"] < 1e-4   # and stays there over the last 20%
    # Delta qdot -> 0 too: the numerical derivative of the logged error is small at the end
    edot = np.gradient(e, r.t, axis=0)
    assert joint_norm(edot)[-5:].max() < 1e-3
    # the estimate started wrong and stayed bounded (V = s'Hs/2 + theta~' Gamma^-1 theta~/2)
    theta = r["adapt.theta_hat"]
    truth = r["truth.y"][0]
    assert np.linalg.norm(theta[0] - truth) > 1.0
    assert np.all(np.isfinite(theta)) and np.abs(theta).max() < 100


def test_theorem1_sine_error_is_bounded_but_does_not_vanish():
    """Remark 1: with d^ell q_d != 0 the error stays bounded, without converging to zero.

    Measured (ell = 2, first 10 s of the shipped 20 s): max |e| over the last 20% = 0.175 rad,
    initial 0.22 rad.  (For ell = 1, 2, 3, 4 it is 0.34, 0.17, 0.096, 0.054 rad.)"""
    r = fwdstep.simulate(fwdstep.load_diagram(THEOREM1_SINE, {"t_final": 10}))
    assert r.status == "ok"
    norm = joint_norm(r["e.y"])
    tail = norm[r.t >= 0.8 * r.t[-1]]
    assert tail.max() < 0.3                           # bounded
    assert tail.max() > 1e-2                          # but not convergent
    assert np.all(np.isfinite(r["adapt.theta_hat"]))


def test_slotine_li_tracks_its_sinusoid():
    """The classical controller, with qdot_d and qddot_d, drives Delta q from 0.22 rad to the
    mrad level.  Measured (10 s): max |e| over the last 20% = 5.0e-3 rad, final 1.3e-3 rad,
    max |e| after t = 1 s 6.6e-3 rad; asserted with a margin of about 2.  Run at step 2e-3
    instead of the shipped 1e-3 to halve the time: the metrics agree to 1e-8."""
    r = fwdstep.simulate(fwdstep.load_diagram(SLOTINE_LI, {"step": 0.002, "log_every": 5}))
    assert r.status == "ok"
    t, norm = r.t, joint_norm(r["e.y"])
    assert norm[0] > 0.2
    assert norm[t >= 1.0].max() < 1.5e-2
    assert r.metrics()["tail_error_norm_max"] < 1e-2
    assert norm[-1] < 3e-3
