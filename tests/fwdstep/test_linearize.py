"""fwdstep.linearize against independent references: analytic transfer functions and
margins, the paper's Theorem 1 (characteristic polynomial (p + alpha)^(ell+1) per joint),
central differences of the diagram's own closed-loop derivative, scipy/python-control."""
import json
import time

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError
from fwdstep.analysis.linearize import DiagramLinearizer, linearize, linearize_along
from fwdstep.run.evaluate import _make_evaluator, initial_state

LOOP = """
description: plant {num}/({den}) under negative feedback gain {k}
blocks:
  r: {{type: Constant, value: 1.0}}
  e: {{type: Sum, signs: "+-"}}
  plant: {{type: TransferFunction, num: {num}, den: {den}}}
  k: {{type: Gain, gain: {k}}}
connections:
  - r.y -> e.u1
  - e.y -> plant.u
  - plant.y -> k.u
  - k.y -> e.u2
simulation: {{t_final: 2, step: 0.01}}
"""

THEOREM1_POINT_MASS = "examples/theorem1_pointmass.yaml"   # also the study's


def _diagram(tmp_path, text, name="d.yaml", overrides=None):
    path = tmp_path / name
    path.write_text(text)
    return fwdstep.load_diagram(str(path), overrides)


def _loop(tmp_path, num, den, k):
    return _diagram(tmp_path, LOOP.format(num=num, den=den, k=k))


W40 = np.logspace(-2, 2, 40)


def test_closed_loop_from_reference_analysis_point(tmp_path):
    """1/(p^2+3p+2) with feedback gain 2, perturbation at the reference: 1/(p^2+3p+4)."""
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    m = linearize(d, inputs=["r.y"], outputs=["plant.y"], t=0.0)
    s = 1j * W40
    exact = 1.0 / (s ** 2 + 3 * s + 4)
    H = m.frequency_response(W40)[:, 0, 0]
    assert np.max(np.abs(H - exact) / np.abs(exact)) <= 1e-8
    np.testing.assert_allclose(np.sort_complex(m.poles()),
                               np.sort_complex(np.roots([1, 3, 4])), rtol=1e-12)
    assert m.input_names == ["r.y"] and m.output_names == ["plant.y"]
    assert m.state_names == ["plant.x0", "plant.x1"]


def test_sensitivity_and_opened_loop(tmp_path):
    """Input and output at the error: S = 1/(1 + L); opened there: G = -L, L = 2/(p^2+3p+2)."""
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    s = 1j * W40
    L = 2.0 / (s ** 2 + 3 * s + 2)
    S = linearize(d, inputs=["e.y"], outputs=["e.y"]).frequency_response(W40)[:, 0, 0]
    assert np.max(np.abs(S - 1 / (1 + L)) / np.abs(1 / (1 + L))) <= 1e-8
    G = linearize(d, inputs=["e.y"], outputs=["e.y"], open="e.y").frequency_response(W40)
    assert np.max(np.abs(G[:, 0, 0] + L) / np.abs(L)) <= 1e-8


def test_margins_of_a_third_order_loop(tmp_path):
    """L = 10/((p+1)(p+2)(p+3)): gain margin 6 at sqrt(11) rad/s; |L| = 1 at w = 1 where
    the phase margin is 180 - (atan 1 + atan 1/2 + atan 1/3) = 90 deg."""
    d = _loop(tmp_path, [10], [1, 6, 11, 6], 1)
    mg = linearize(d, inputs=["e.y"], outputs=["e.y"], open="e.y").margins()
    assert abs(mg["gain_margin"] - 6.0) <= 1e-9 * 6
    assert abs(mg["phase_crossover"] - np.sqrt(11.0)) <= 1e-9
    assert abs(mg["gain_crossover"] - 1.0) <= 1e-9
    pm = 180 - np.degrees(np.arctan(1) + np.arctan(0.5) + np.arctan(1 / 3))
    assert abs(mg["phase_margin_deg"] - pm) <= 1e-7


def test_conversions(tmp_path):
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    m = linearize(d, inputs=["r.y"], outputs=["plant.y", "e.y"])
    from scipy import signal
    ss = m.to_scipy()
    assert isinstance(ss, signal.StateSpace)
    np.testing.assert_array_equal(ss.A, m.A)
    control = pytest.importorskip("control", reason="python-control: pip install fwdstep[analysis]")
    sys = m.to_control()
    assert list(sys.input_labels) == ["r:y"]           # python-control reserves '.'
    assert list(sys.output_labels) == ["plant:y", "e:y"]
    ref = np.array([sys(1j * w) for w in W40])
    np.testing.assert_allclose(ref, m.frequency_response(W40), rtol=1e-12)
    assert control.ss2tf(sys[0, 0]).den[0][0][0] == pytest.approx(1.0)


def test_state_from_a_run(tmp_path):
    """Without x the state is the run's at t: the logged output equals C x there."""
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    m = linearize(d, inputs=["r.y"], outputs=["plant.y"], t=0.7)
    r = fwdstep.simulate(d)
    k = int(np.argmin(np.abs(r.t - 0.7)))
    assert m.t == pytest.approx(0.7)
    assert float(m.x[0]) == pytest.approx(float(r["plant.y"][k]), abs=1e-12)


def test_theorem1_point_mass_poles(tmp_path):
    """Theorem 1 on two point masses at rest with theta_hat = theta, ell = 1..4.

    States in the loop: the plant (q, qdot) and the reference dynamics (z, I_1..I_{ell-1});
    at rest Y(q, 0, 0, 0) = 0 and s = 0, so the adaptation states neither move nor act
    (their rows and their columns in the loop's rows of A are zero: poles at 0, one per
    parameter).  The loop's characteristic polynomial is, per joint i,
    (p + alpha)^(ell+1) (p + K/m_i): ell+1 poles at -alpha (the Hurwitz polynomial of (2))
    and the s-dynamics m_i s' = -K s."""
    alpha, K, masses = 4.0, 50.0, (1.5, 0.7)
    for ell in (1, 2, 3, 4):
        d = fwdstep.load_diagram(THEOREM1_POINT_MASS, {"ell": ell})
        m = linearize(d, inputs=["qd.y"], outputs=["e.y"], t=0.0)
        names = m.state_names
        adapt = [i for i, n in enumerate(names) if n.startswith("adapt.")]
        loop = [i for i in range(len(names)) if i not in adapt]
        assert len(adapt) == 2 and len(loop) == 2 * (ell + 2)
        assert not m.A[adapt].any() and not m.A[np.ix_(loop, adapt)].any()
        for j, mass in enumerate(masses):        # the joints are decoupled: one at a time
            joint = [i for i in loop if names[i].endswith((f"[{j}]", f"q{j + 1}",
                                                           f"qdot{j + 1}"))]
            assert len(joint) == ell + 2, [names[i] for i in joint]
            other = [i for i in loop if i not in joint]
            assert not m.A[np.ix_(joint, other)].any()
            coefficients = np.poly(m.A[np.ix_(joint, joint)])
            expected = np.polymul(np.poly(np.full(ell + 1, -alpha)), [1.0, K / mass])
            assert np.max(np.abs(coefficients - expected) / np.abs(expected)) <= 1e-9, ell


def test_theorem1_two_link_at_rest(tmp_path):
    """diagrams/theorem1.yaml at rest on a constant target with theta_hat = theta: the loop's
    characteristic polynomial is (p + alpha)^(2 (ell+1)) det(p I + H(q)^-1 K), H from the
    arm's closed-form inertia (Slotine & Li) at q = q_d."""
    d = fwdstep.load_diagram("diagrams/theorem1.yaml", {
        "a1": 0, "a2": 0, "q0": "[b1, b2]", "theta0": "theta_true"})
    m = linearize(d, inputs=["qd.y"], outputs=["e.y"], t=0.0)
    p = d.spec.parameters
    a1, a2, a3, a4 = np.asarray(p["theta_true"], dtype=float)
    alpha, ell, Kg = float(p["alpha"]), int(p["ell"]), np.asarray(p["K"], dtype=float)
    q2 = float(p["b2"])
    H = np.array([[a1 + 2 * a3 * np.cos(q2) + 2 * a4 * np.sin(q2),
                   a2 + a3 * np.cos(q2) + a4 * np.sin(q2)],
                  [a2 + a3 * np.cos(q2) + a4 * np.sin(q2), a2]])
    names = m.state_names
    loop = [i for i, n in enumerate(names) if not n.startswith("adapt.")]
    expected = np.polymul(np.poly(np.full(2 * (ell + 1), -alpha)),
                          np.poly(-np.linalg.solve(H, Kg)))
    got = np.poly(m.A[np.ix_(loop, loop)])
    assert np.max(np.abs(got - expected) / np.abs(expected)) <= 1e-9


def test_state_matrix_is_the_derivative_of_the_closed_loop(tmp_path):
    """A of the closed loop (no opening) equals central differences of the diagram's own
    right-hand side f(t, x) (the reference evaluator of fwdstep.simulate), at a state of a
    run of diagrams/theorem1.yaml: the chain rule over the schedule is checked as a whole."""
    d = fwdstep.load_diagram("diagrams/theorem1.yaml")
    m = linearize(d, inputs=["qd.y"], outputs=["e.y"], t=1.0)
    f, _, _ = _make_evaluator(d)
    x = m.x[None].copy()
    N = d.n_states
    ref = np.zeros((N, N))
    for k in range(N):
        h = 1e-6 * max(1.0, abs(x[0, k]))
        dp, dm = np.zeros((1, N)), np.zeros((1, N))
        xp, xm = x.copy(), x.copy()
        xp[0, k] += h
        xm[0, k] -= h
        f(m.t, xp, dp)
        f(m.t, xm, dm)
        ref[:, k] = (dp - dm)[0] / (2 * h)
    assert np.max(np.abs(m.A - ref)) <= 1e-6 * max(1.0, np.abs(ref).max())


def test_along_a_run(tmp_path):
    """An LTI loop has the same A at every time; the times are the run's recorded ones."""
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    models = linearize_along(d, inputs=["r.y"], outputs=["plant.y"], n=5)
    assert [m.t for m in models] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    for m in models:
        np.testing.assert_array_equal(m.A, models[0].A)
    assert not np.allclose(models[0].x, models[-1].x)


def test_unknown_signal_is_refused_with_the_valid_names(tmp_path):
    d = _loop(tmp_path, [1], [1, 3, 2], 2)
    with pytest.raises(ConfigError, match="block 'plant' has outputs: y"):
        linearize(d, inputs=["plant.u"], outputs=["plant.y"])
    with pytest.raises(ConfigError, match="outside the signal's shape"):
        linearize(d, inputs=["plant.y[3]"], outputs=["plant.y"])
    with pytest.raises(ConfigError, match="margins need one input and one output"):
        linearize(d, inputs=["r.y", "e.y"], outputs=["plant.y"]).margins()


def test_cli_writes_matrices_poles_and_bode(tmp_path, capsys):
    from fwdstep.cli import main
    path = tmp_path / "loop.yaml"
    path.write_text(LOOP.format(num=[10], den=[1, 6, 11, 6], k=1))
    out = tmp_path / "lin"
    code = main(["linearize", str(path), "--input", "e.y", "--output", "e.y",
                 "--open", "e.y", "--at", "0.5", "--along", "3", "-o", str(out)])
    assert code == 0
    data = json.loads((out / "linear.json").read_text())
    assert data["t"] == pytest.approx(0.5)
    assert abs(data["margins"]["gain_margin"] - 6.0) <= 1e-8
    npz = np.load(out / "linear.npz")
    assert npz["A"].shape == (3, 3)
    for name in ("bode.png", "poles_over_time.png", "poles_over_time.npz"):
        assert (out / name).stat().st_size > 0
    assert "gain margin 15.6 dB" in capsys.readouterr().out
    code = main(["linearize", str(path), "--input", "nope.y", "--output", "e.y",
                 "-o", str(tmp_path / "bad")])
    assert code == 2
    assert "'nope.y' is not a signal" in capsys.readouterr().err


def test_panda_slotine_li_at_one_time_within_a_second():
    """diagrams/robots/panda_slotine_li.yaml (57 states): Jacobians of every block built and
    the linearisation computed at one state in <= 1 s (the run to reach the state not
    counted); A checked against central differences of the diagram's right-hand side."""
    pytest.importorskip("pinocchio", reason="the Panda needs pinocchio (fwdstep[robots])")
    d = fwdstep.load_diagram("diagrams/robots/panda_slotine_li.yaml")
    x = initial_state(d)
    rng = np.random.default_rng(7)
    x = x + 0.05 * rng.standard_normal(x.shape)
    start = time.perf_counter()
    lin = DiagramLinearizer(d, inputs=["tau.y"], outputs=["e.y"])
    m = lin.at(0.3, x[0])
    elapsed = time.perf_counter() - start
    assert m.A.shape == (57, 57) and m.B.shape == (57, 7) and m.C.shape == (7, 57)
    assert elapsed <= 1.0, elapsed
    f, _, _ = _make_evaluator(d)
    N = d.n_states
    ref = np.zeros((N, N))
    for k in range(N):
        h = 1e-6 * max(1.0, abs(x[0, k]))
        dp, dm = np.zeros((1, N)), np.zeros((1, N))
        xp, xm = x.copy(), x.copy()
        xp[0, k] += h
        xm[0, k] -= h
        f(0.3, xp, dp)
        f(0.3, xm, dm)
        ref[:, k] = (dp - dm)[0] / (2 * h)
    assert np.max(np.abs(m.A - ref)) <= 1e-6 * max(1.0, np.abs(ref).max())


def test_urdf_arm_jacobian_against_pinocchio_derivatives():
    """The Panda's central-difference Jacobian (pinocchio's aba cannot be traced) against
    pinocchio's analytic ABA derivatives (computeABADerivatives): an independent reference."""
    pin = pytest.importorskip("pinocchio", reason="needs pinocchio (fwdstep[robots])")
    from fwdstep.analysis.jacobian import BlockJacobian
    from fwdstep.structure.library import lookup
    arm = lookup("URDFArm")("arm", robot="panda", damping=0, coulomb=0)   # aba has no friction
    n = arm.model.nv
    rng = np.random.default_rng(3)
    q, v, tau = rng.uniform(-1, 1, n), rng.standard_normal(n), 5 * rng.standard_normal(n)
    jac = BlockJacobian(arm).at(0.0, np.concatenate([q, v])[None],
                                (tau[None], np.zeros((1, n))))
    data = arm.model.createData()
    pin.computeABADerivatives(arm.model, data, q, v, tau)
    dqdd_dq, dqdd_dv = np.array(data.ddq_dq), np.array(data.ddq_dv)
    Minv = np.array(data.Minv)
    Minv = np.triu(Minv) + np.triu(Minv, 1).T
    dx = jac.part("dx", "x")[0]
    scale = max(1.0, np.abs(dqdd_dq).max(), np.abs(Minv).max())
    assert np.max(np.abs(dx[n:, :n] - dqdd_dq)) <= 1e-7 * scale
    assert np.max(np.abs(dx[n:, n:] - dqdd_dv)) <= 1e-7 * scale
    assert np.max(np.abs(jac.part("dx", "u.tau")[0][n:] - Minv)) <= 1e-7 * scale


def test_theorem7_learned_frequency_is_a_notch():
    """diagrams/theorem7.yaml frozen with theta_hat = omega^2 (the learned value; omega = 3)
    and the true robot parameters, at rest: the disturbance tau* cannot reach q at omega
    (|H(j omega)| ~ 0, an internal model: zeros at +-j omega); with theta_hat = 0 it can."""
    over = {"vartheta0": "[3.34, 0.97, 1.04, 0.6]", "qd_amp": [0, 0], "tau_amp": 0}
    w = np.array([1.0, 2.0, 3.0, 4.0, 6.0])
    gains = {}
    for theta in (0.0, 9.0):
        d = fwdstep.load_diagram("diagrams/theorem7.yaml", dict(over, theta0=theta))
        m = linearize(d, inputs=["dist.y[0]"], outputs=["plant.q[0]"], t=0.0)
        gains[theta] = np.abs(m.frequency_response(w)[:, 0, 0])
    assert gains[9.0][2] <= 1e-12 * gains[9.0].max()
    assert gains[0.0][2] >= 0.5 * gains[0.0].max()


def test_the_report_shows_the_linearisation_written_into_the_run(tmp_path):
    """fwdstep linearize into the run's linear/ folder, then fwdstep report: the page lists
    the poles of linear.json (the rightmost first) and embeds the Bode figure."""
    from fwdstep.cli.arguments import main
    run = tmp_path / "run"
    assert main(["run", "diagrams/pid_classic.yaml", "-o", str(run), "-q", "--no-plots",
                 "--set", "simulation.t_final=0.2"]) == 0
    assert main(["linearize", "diagrams/pid_classic.yaml", "--input", "tau.y", "--output",
                 "e.y", "--at", "0.1", "-o", str(run / "linear")]) == 0
    data = json.loads((run / "linear" / "linear.json").read_text())
    assert main(["report", str(run)]) == 0
    page = (run / "report.html").read_text()
    assert "<h2>Linear analysis</h2>" in page and 'alt="Bode"' in page
    rightmost = max(complex(*p).real for p in data["poles"])
    assert f"{rightmost:.6g} " in page


@pytest.mark.parametrize("name,omegas", [("theorem8", [2.0, 4.0]), ("theorem9", [2.0, 3.0, 4.5])])
def test_theorems_8_and_9_learned_frequencies_are_notches(name, omegas):
    """Frozen at rest with theta_hat = the coefficients of prod (p^2 + omega_i^2) (computed
    here with numpy.poly, independently of FrequencyParameters), the disturbance cannot reach
    q at any omega_i (zeros at +-j omega_i); with theta_hat = 0 it can."""
    coefficients = np.real(np.poly(np.concatenate([1j * np.array(omegas),
                                                   -1j * np.array(omegas)])))
    learned = [float(c) for c in coefficients[::-2][:len(omegas)]]   # p^0, p^2, ... terms
    gains = {}
    for label, theta0 in (("none", 0), ("learned", learned)):
        d = fwdstep.load_diagram(f"diagrams/{name}.yaml", {
            "vartheta0": "[3.34, 0.97, 1.04, 0.6]", "qd_amp": [0, 0], "tau_amp": 0,
            "theta0": theta0})
        m = linearize(d, inputs=["dist.y[0]"], outputs=["plant.q[0]"], t=0.0)
        gains[label] = np.abs(m.frequency_response(omegas)[:, 0, 0])
    assert np.all(gains["none"] > 1e-4)
    assert np.all(gains["learned"] <= 1e-12 * gains["none"]), gains
