"""Baseline diagrams from generic blocks: computed torque gives the linear error dynamics
Delta qddot + K_D Delta qdot + K_P Delta q = 0 (closed form for critical damping) on the
two-link and the 3-link arm; PD + gravity compensation uses g(q) = Y(q, 0, 0, 0) theta
(checked against the plant's g written out independently) and regulates a set point."""
import math
import os

import numpy as np
import pytest

import fwdstep

DIAGRAMS = os.path.join(os.path.dirname(__file__), "..", "..", "diagrams")


def run(name, **overrides):
    d = fwdstep.load_diagram(os.path.join(DIAGRAMS, name), overrides=overrides)
    r = fwdstep.simulate(d)
    assert r.status == "ok"
    return r


@pytest.mark.parametrize("name,n", [("computed_torque.yaml", 2),
                                    ("computed_torque_nlink.yaml", 3)])
def test_computed_torque_error_is_the_critically_damped_linear_response(name, n):
    """kP = w^2, kD = 2 w: Delta q(t) = (e0 + (edot0 + w e0) t) exp(-w t), with
    e0 = q0 - q_d(0) = q0 and edot0 = 0 - qdot_d(0) = -A w_d (q_d = A sin(w_d t))."""
    w = 10.0
    q0 = np.array([0.3, -0.2, 0.1][:n])
    A = np.array([0.5, 0.3, 0.4][:n])
    r = run(name, kP=w * w, kD=2 * w, dist_amplitude=[0.0] * n, t_final=1.5, step=0.002,
            log_every=5)
    t = r.t[:, None]
    edot0 = -A * 0.5
    exact = (q0 + (edot0 + w * q0) * t) * np.exp(-w * t)
    np.testing.assert_allclose(r["e.y"], exact, atol=1e-8)
    assert np.max(np.abs(r["e.y"][0])) > 0.1         # a real transient, not a trivial zero


def test_computed_torque_with_a_wrong_model_no_longer_decouples():
    exact = run("computed_torque.yaml", dist_amplitude=[0.0, 0.0], t_final=1.5, step=0.002)
    wrong = run("computed_torque.yaml", dist_amplitude=[0.0, 0.0], t_final=1.5, step=0.002,
                model_scale=0.8)
    assert np.max(np.abs(wrong["e.y"] - exact["e.y"])) > 1e-3


def _two_link_gravity(q, g=9.81, m1=1.0, l1=1.0, me=2.0, lc1=0.5, lce=0.6, delta_e=30.0):
    """g(q) of the TwoLinkArm docstring, written out again."""
    c = np.cos(q[:, 0] + q[:, 1] - math.radians(delta_e))
    return np.stack([(m1 * lc1 + me * l1) * g * np.cos(q[:, 0]) + me * lce * g * c,
                     me * lce * g * c], axis=1)


def test_pd_gravity_compensates_the_plant_gravity_and_regulates_a_set_point():
    setpoint = [0.5, -0.3]
    r = run("pd_gravity.yaml", qd_amplitude=[0.0, 0.0], qd_offset=setpoint,
            dist_amplitude=[0.0, 0.0], t_final=4.0, step=0.002, log_every=50)
    np.testing.assert_allclose(r["g.y"], _two_link_gravity(r["arm.q"]), rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(r["e.y"][-1])) < 1e-5
    # without the gravity term the arm sags: Delta q settles where K_P Delta q = g(q)
    sag = run("pd_gravity.yaml", qd_amplitude=[0.0, 0.0], qd_offset=setpoint,
              dist_amplitude=[0.0, 0.0], t_final=4.0, step=0.002, model_scale=0.0, log_every=50)
    e, q = sag["e.y"][-1], sag["arm.q"][-1:]
    np.testing.assert_allclose(400.0 * e, -_two_link_gravity(q)[0], rtol=1e-5)
    assert np.max(np.abs(e)) > 1e-2


def test_pd_gravity_nlink_regulates_a_set_point():
    r = run("pd_gravity_nlink.yaml", qd_amplitude=[0.0, 0.0, 0.0], qd_offset=[0.4, -0.2, 0.3],
            dist_amplitude=[0.0, 0.0, 0.0], t_final=5.0, step=0.002)
    err = np.max(np.abs(r["e.y"]), axis=1)
    late, early = err[r.t >= 4.0].max(), err[(r.t >= 1.0) & (r.t <= 2.0)].max()
    assert late < 2e-3 and late < 0.1 * early                # a decaying oscillation
    assert np.max(np.abs(r["g.y"][-1])) > 1.0            # gravity is really compensated


def test_payload_step_switches_the_arm_to_the_heavier_link_2_exactly(tmp_path):
    """TwoLinkArm payload: me -> me + payload at payload_time (a declared discontinuity, so
    RK4 keeps its order); reference: solve_ivp on the plain arm with me = 2, then me = 3."""
    from scipy.integrate import solve_ivp

    from fwdstep.blocks.robot import TwoLinkArm
    path = tmp_path / "payload.yaml"
    path.write_text("""
description: open-loop two-link arm picking up 1 kg at t = 0.35 (off the step grid)
blocks:
  tau: {type: Constant, value: [1.5, -0.5]}
  arm: {type: TwoLinkArm, q0: [0.3, -0.2], gravity: 9.81, payload: 1.0, payload_time: 0.35}
connections:
  - tau.y -> arm.tau
simulation: {t_final: 1.0, step: 0.002, solver: rk4}
log: [arm.q, arm.qdot]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    zero = np.zeros((1, 2))

    def f(arm):
        return lambda t, x: arm.derivative(t, x[None], (np.array([[1.5, -0.5]]), zero))[0]

    before = solve_ivp(f(TwoLinkArm("a", gravity=9.81)), (0, 0.35), [0.3, -0.2, 0, 0],
                       rtol=1e-12, atol=1e-12)
    after = solve_ivp(f(TwoLinkArm("a", gravity=9.81, me=3.0)), (0.35, 1.0), before.y[:, -1],
                      rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.r_[r["arm.q"][-1], r["arm.qdot"][-1]], after.y[:, -1],
                               atol=1e-8)


def test_a_sweep_over_the_payload_time_runs_each_variant_as_alone(tmp_path):
    """Variants picking up the payload at different times never share a batch (each batch
    has one step grid, split at its jump times); a batch of them used to end in a bare
    IndexError.  Each variant equals its own run, and one without payload runs too."""
    from fwdstep.sweeps.sweep import run_sweep
    path = tmp_path / "payload.yaml"
    path.write_text("""
parameters: {T: 0.35, load: 1.0}
blocks:
  tau: {type: Constant, value: [1.5, -0.5]}
  arm: {type: TwoLinkArm, q0: [0.3, -0.2], gravity: 9.81, payload: load, payload_time: T}
  e:   {type: Sum, signs: "+-", shape: [2]}
  z:   {type: Constant, value: [0.0, 0.0]}
connections:
  - tau.y -> arm.tau
  - arm.q -> e.u1
  - z.y -> e.u2
simulation: {t_final: 0.5, step: 0.002, solver: rk4}
metrics: {error: e.y}
""")
    variants = [{"T": 0.1234}, {"T": 0.35}, {"T": 0.35, "load": 2.0}, {"load": 0.0}]
    sweep = run_sweep(str(path), variants=variants, workers=1)
    assert [v.status for v in sweep.variants] == ["ok"] * 4
    assert len(sweep.batches) == 3                 # 0.1234 | 0.35 (two loads) | no payload
    for k, values in enumerate(variants):
        alone = fwdstep.simulate(fwdstep.load_diagram(str(path), values))
        e = sweep.parts[[k in p["indices"] for p in sweep.parts].index(True)]
        col = list(e["indices"]).index(k)
        np.testing.assert_allclose(e["e"][:, col], alone["e.y"], rtol=0, atol=1e-12)


def test_robustness_study_smoke(tmp_path):
    """examples/study_robustness.py builds and runs three scenarios (0.2 s, one controller):
    the edited diagrams load, the error is measured on the true q and torques are bounded
    by the saturation limits where there is one."""
    import importlib.util
    import json
    path = os.path.join(DIAGRAMS, "..", "examples", "study_robustness.py")
    spec = importlib.util.spec_from_file_location("study_robustness", path)
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    out = tmp_path / "out"
    assert study.main(["--smoke", "--out", str(out), "--workers", "1",
                       "--only", "computed torque", "nominal", "saturation", "noise"]) == 0
    results = {r["scenario"]: r for r in json.loads((out / "results.json").read_text())}
    assert set(results) == {"nominal", "saturation", "noise"}
    assert all(r["status"] == "ok" for r in results.values())
    assert results["saturation"]["max_torque"] <= max(study.TORQUE_LIMIT) + 1e-12
    assert results["nominal"]["max_torque"] > max(study.TORQUE_LIMIT)
    assert (out / "diagrams" / "computed_torque__noise.yaml").exists()
