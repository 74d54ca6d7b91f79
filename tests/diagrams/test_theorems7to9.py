"""Shipped diagrams of Theorems 7, 8, 9 (diagrams/theorem7.yaml, theorem8.yaml, theorem9.yaml).

* (118): the realisation in the diagram (e_2 = chi_2 - chi_1 from psi_1 and v through one
  shared-denominator filter N_H p^(2n*)) against an independent second realisation by
  polynomial division A* = Q N_H + R, fed the same closed-loop signals: agree to 1e-9.
* the identity D_ell(p) (q - c) = p^(ell-1) (p + Lambda) s implied by (64)/(119)
  (c = q_d* in Theorem 7, c = chi_2 in Theorem 9): both sides through the same stable filter
  1/F(p) differ only by a homogeneous solution of F, which has died out after 1.5 s.
* theorem8.yaml is theorem9.yaml with n* = 2.
* short closed-loop runs stay bounded and the estimates move toward the true values
  (long-horizon numbers are in docs/theorems7-9.md; examples/study_theorems7to9.py).
"""
import copy
import os

import numpy as np
import pytest
import yaml

from fwdstep.structure.compiler import compile_spec
from fwdstep.run.simulate import simulate
from fwdstep.structure.spec import load_spec

HERE = os.path.dirname(os.path.abspath(__file__))
DIAGRAMS = os.path.normpath(os.path.join(HERE, "..", "..", "diagrams"))


def run_modified(tmp_path, name, overrides=None, params=None, blocks=None, connections=(),
                 log=None, t_final=1.5, step=0.005):
    """Run a shipped diagram with extra parameters, blocks and connections added."""
    with open(os.path.join(DIAGRAMS, name)) as f:
        doc = yaml.safe_load(f)
    doc = copy.deepcopy(doc)
    for entry in doc["blocks"].values():
        if entry.get("type") == "subsystem":
            entry["file"] = os.path.join(DIAGRAMS, entry["file"])
    doc["parameters"].update(params or {})
    doc["blocks"].update(blocks or {})
    doc["connections"].extend(connections)
    doc["simulation"].update(t_final=t_final, step=step, log_every=1)
    doc["log"] = log
    doc.pop("plots", None)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return simulate(compile_spec(load_spec(str(path), overrides)))


def padded(poly, length):
    poly = np.trim_zeros(np.asarray(poly, dtype=float), "f")
    return np.concatenate([np.zeros(length - poly.size), poly]).tolist()


@pytest.mark.parametrize("nstar,omegas", [(1, [3.0]), (3, [2.0, 3.0, 4.5])])
def test_e2_realisation_matches_polynomial_division_realisation(tmp_path, nstar, omegas):
    with open(os.path.join(DIAGRAMS, "theorem9.yaml")) as f:
        par = yaml.safe_load(f)["parameters"]
    a_star, kappa = float(par["a_star"]), float(par["kappa"])
    A_star = np.poly([-a_star] * (2 * nstar))
    N_H = np.poly([-kappa] * 2)
    Q, R = np.polydiv(A_star, N_H)              # A* = Q N_H + R, deg Q = 2n* - 2, deg R <= 1
    assert np.allclose(np.polyadd(np.polymul(Q, N_H), R), A_star)
    p2n = np.concatenate([[1.0], np.zeros(2 * nstar)])
    L = 2 * nstar + 1
    blocks = {
        # -[(A* - p^(2n*)) / p^(2n*)] psi_1 + [Q / p^(2n*)] v
        "r2a": {"type": "TransferFunctionSum", "den": p2n.tolist(),
                "nums": [padded(-np.polysub(A_star, p2n), L), padded(Q, L)], "shape": [2]},
        # [R / (N_H p^(2n*))] v
        "r2b": {"type": "TransferFunction", "num": np.trim_zeros(R, "f").tolist(),
                "den": np.polymul(N_H, p2n).tolist(), "shape": [2]},
        "e2alt": {"type": "Sum", "signs": "++", "shape": [2]},
    }
    conns = ["psi1.y -> r2a.u1", "v.y -> r2a.u2, r2b.u", "r2a.y -> e2alt.u1",
             "r2b.y -> e2alt.u2"]
    r = run_modified(tmp_path, "theorem9.yaml",
                     overrides={"nstar": nstar, "omegas": omegas, "gammas": 1e3},
                     blocks=blocks, connections=conns, log=["e2.y", "e2alt.y", "v.y"])
    e2, alt = r["e2.y"], r["e2alt.y"]
    assert np.max(np.abs(e2)) > 1e-4            # a non-trivial signal was compared
    assert np.max(np.abs(r["v.y"])) > 1e-6
    assert np.max(np.abs(e2 - alt)) <= 1e-9


def identity_blocks(ell, alpha, lam, beta=10.0):
    """y = [D_ell / F](q - c) - [p^(ell-1)(p + lam) / F] s with F = (p + beta)^(ell+1)."""
    F = np.poly([-beta] * (ell + 1))
    D = np.poly([-alpha] * (ell + 1))
    N = np.polymul(np.concatenate([[1.0], np.zeros(ell - 1)]), [1.0, lam])
    return {"ident": {"type": "TransferFunctionSum", "den": F.tolist(),
                      "nums": [padded(D, ell + 2), padded(-N, ell + 2)], "shape": [2]},
            "scale": {"type": "TransferFunctionSum", "den": F.tolist(),
                      "nums": [padded(D, ell + 2)], "shape": [2]},
            "dqc": {"type": "Sum", "signs": "+-", "shape": [2]}}


def check_identity(r):
    tail = r.t > 1.5
    size = np.max(np.abs(r["scale.y"]))
    assert size > 1e-3
    assert np.max(np.abs(r["ident.y"][tail])) <= 1e-7 * size


@pytest.mark.parametrize("ell", [2, 3])
def test_identity_D_of_q_minus_chi2_equals_p_power_times_s_theorem9(tmp_path, ell):
    blocks = identity_blocks(ell, 4.0, 5.0)
    conns = ["plant.q -> dqc.u1", "chi2.y -> dqc.u2", "dqc.y -> ident.u1, scale.u1",
             "s.y -> ident.u2"]
    r = run_modified(tmp_path, "theorem9.yaml", overrides={"ell": ell}, blocks=blocks,
                     connections=conns, log=["ident.y", "scale.y"], t_final=2.5)
    check_identity(r)


def test_identity_D_of_q_minus_qdstar_equals_p_power_times_s_theorem7(tmp_path):
    blocks = identity_blocks(2, 4.0, 5.0)
    blocks["s"] = {"type": "Sum", "signs": "+-", "shape": [2]}       # s = qdot - z
    conns = ["plant.q -> dqc.u1", "qds.q_d_star -> dqc.u2", "dqc.y -> ident.u1, scale.u1",
             "plant.qdot -> s.u1", "ref.z -> s.u2", "s.y -> ident.u2"]
    r = run_modified(tmp_path, "theorem7.yaml", blocks=blocks, connections=conns,
                     log=["ident.y", "scale.y"], t_final=2.5)
    check_identity(r)


def test_theorem8_is_theorem9_with_two_frequencies():
    def body(name):
        with open(os.path.join(DIAGRAMS, name)) as f:
            doc = yaml.safe_load(f)
        doc.pop("description")
        return doc
    t8, t9 = body("theorem8.yaml"), body("theorem9.yaml")
    assert t8["parameters"]["nstar"] == 2
    assert len(t8["parameters"]["omegas"]) == 2
    for key in ("nstar", "omegas", "gammas"):
        t8["parameters"].pop(key), t9["parameters"].pop(key)
    assert t8 == t9


@pytest.mark.parametrize("name", ["theorem7.yaml", "theorem8.yaml", "theorem9.yaml"])
def test_shipped_diagram_runs_bounded_and_theta_hat_moves_toward_theta(tmp_path, name):
    r = run_modified(tmp_path, name, log=["qds.dq", "theta.theta_hat", "theta_true.theta"],
                     t_final=2.0)
    assert r.status == "ok"
    assert np.max(np.abs(r["qds.dq"])) < 0.2
    theta = np.atleast_2d(r["theta_true.theta"][-1])
    est = r["theta.theta_hat"].reshape(len(r.t), -1)
    assert np.all(np.isfinite(est))
    # from theta_hat(0) = 0 the largest-weight estimate theta_n* (the sum of omega_i^2)
    # must have started to move toward its true value within 2 s
    assert 0 < est[-1, -1] < 1.5 * theta[0, -1]
