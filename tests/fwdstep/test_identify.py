"""Parameter identification (issue 28) on a simulated two-link run: the plant's own
parameters are the reference (TwoLinkArm's theta), never the estimator's output."""
import os
import subprocess
import sys

import numpy as np
import pytest

import fwdstep
from fwdstep.analysis.identify import estimate, exponential_filter

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SLOTINE_LI = os.path.join(ROOT, "diagrams", "slotine_li.yaml")
DENSE = {"step": 0.0005, "t_final": 5, "log_every": 1, "log": ["arm.q", "arm.qdot", "tau.y"]}


@pytest.fixture(scope="module")
def run():
    d = fwdstep.load_diagram(SLOTINE_LI, DENSE)
    r = fwdstep.simulate(d)
    blocks = {b.name: b for b in d.blocks}
    return r, blocks["Y"], blocks["arm"].p.theta[0][:4]


def test_the_filter_is_the_ode_solution_and_its_adjoint_is_exact():
    from scipy.integrate import solve_ivp
    t = np.linspace(0, 2, 2001)
    z = exponential_filter(t, np.sin(3 * t), 20.0)
    ref = solve_ivp(lambda s, y: 20.0 * (np.sin(3 * s) - y), (0, 2), [0.0], t_eval=t,
                    rtol=1e-13, atol=1e-14).y[0]
    assert np.abs(z - ref).max() < 1e-10
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 57))
    tt = np.linspace(0, 1, 57)
    assert abs(exponential_filter(tt, a, 7.0) @ b
               - a @ exponential_filter(tt, b, 7.0, adjoint=True)) < 1e-13


def test_noiseless_run_gives_the_true_parameters(run):
    r, Y, truth = run
    ident = estimate(r.t, r["arm.q"], r["arm.qdot"], r["tau.y"], Y, bandwidth=10.0)
    assert ident.rank == 4
    assert np.abs(ident.theta - truth).max() < 1e-6


def test_with_torque_noise_the_intervals_hold_the_truth(run):
    r, Y, truth = run
    z = []
    for seed in range(12):
        noisy = r["tau.y"] + np.random.default_rng(seed).normal(0, 0.2, r["tau.y"].shape)
        ident = estimate(r.t, r["arm.q"], r["arm.qdot"], noisy, Y, bandwidth=10.0,
                         confidence=0.95)
        z.append((ident.theta - truth) / ident.std)
    z = np.array(z)
    assert np.mean(np.abs(z) < 1.96) >= 0.85          # 95 % intervals: calibrated
    assert 0.7 < z.std() < 1.4
    assert np.abs(z).max() < 4.5


def test_cli_identify(tmp_path):
    env = dict(os.environ, PYTHONPATH=ROOT, MPLBACKEND="Agg")
    out = tmp_path / "run"
    sets = ["--set", "step=0.0005", "--set", "t_final=2", "--set", "log_every=1",
            "--set", "log=[arm.q, arm.qdot, tau.y]"]
    cli = [sys.executable, os.path.join(ROOT, "cli.py")]
    done = subprocess.run(cli + ["run", SLOTINE_LI, *sets, "-o", str(out), "--no-plots", "-q"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    done = subprocess.run(cli + ["identify", str(out), "--regressor", "Y"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "rank 4" in done.stdout and (out / "identify" / "identify.json").is_file()
    done = subprocess.run(cli + ["identify", str(out), "--regressor", "Z"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert "has no block 'Z'" in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_a_regressor_whose_C_breaks_property_2_is_refused(run):
    """C' = C + S with S = diag(q_1 qdot_1, 0) symmetric: (C' + C'^T) qdot != Hdot qdot, so
    the momentum form's N = g - C'^T qdot would be wrong; identification refuses it."""
    import copy
    from fwdstep.core.errors import ConfigError
    r, Y, _ = run

    class NotChristoffel(type(Y)):
        def output(self, t, x, u):
            out = np.array(np.broadcast_to(super().output(t, x, u)[0],
                                           (len(u[0]),) + self.outputs["Y"].shape))
            out[:, 0, 0] += u[0][:, 0] * u[1][:, 0] * u[2][:, 0]
            return (out,)

    bad = copy.copy(Y)
    bad.__class__ = NotChristoffel
    with pytest.raises(ConfigError, match="does not satisfy Property 2"):
        estimate(r.t, r["arm.q"], r["arm.qdot"], r["tau.y"], bad, bandwidth=10.0)


@pytest.mark.parametrize("settings, message", [
    ({"bandwidth": 0.0}, "finite lambda > 0"),        # was: silently the default lambda
    ({"bandwidth": -5.0}, "finite lambda > 0"),       # was: a growing 'filter', a result
    ({"bandwidth": float("nan")}, "finite lambda > 0"),   # was: a LAPACK traceback
    ({"confidence": 1.5}, "strictly between 0 and 1"),    # was: intervals [nan, nan]
    ({"confidence": 0.0}, "strictly between 0 and 1"),    # was: zero-width intervals
])
def test_settings_without_meaning_are_refused(run, settings, message):
    from fwdstep.core.errors import ConfigError
    r, Y, _ = run
    k = slice(0, 400)
    with pytest.raises(ConfigError, match=message):
        estimate(r.t[k], r["arm.q"][k], r["arm.qdot"][k], r["tau.y"][k], Y,
                 **{"bandwidth": 10.0, **settings})


def test_a_log_with_nan_is_refused_naming_the_signal_and_time(run):
    from fwdstep.core.errors import ConfigError
    r, Y, _ = run
    k = slice(0, 400)
    q = np.array(r["arm.q"][k])
    q[100, 1] = np.nan                                # was: LinAlgError from lstsq
    with pytest.raises(ConfigError, match=r"q \(arm.q\) is not finite at t = 0.05 s"):
        estimate(r.t[k], q, r["arm.qdot"][k], r["tau.y"][k], Y, bandwidth=10.0,
                 signals={"q": "arm.q"})


def test_a_run_too_short_for_the_filter_gives_no_intervals_not_huge_ones(run):
    """5 samples at 0.5 ms filtered at 20 rad/s are fewer than 4 parameters' worth of
    independent filtered residual: sigma is not estimable.  The intervals were +-1e144."""
    r, Y, truth = run
    k = slice(0, 5)
    ident = estimate(r.t[k], r["arm.q"][k], r["arm.qdot"][k], r["tau.y"][k], Y,
                     bandwidth=20.0)
    assert np.all(np.isnan(ident.std)) and np.all(np.isnan(ident.lower))
    assert ident.notes and "no intervals" in ident.notes[0]
    assert np.abs(ident.theta - truth).max() < 0.5   # the estimate itself is still given


def test_cli_identify_refusals_are_one_line(tmp_path):
    env = dict(os.environ, PYTHONPATH=ROOT, MPLBACKEND="Agg")
    out = tmp_path / "run"
    sets = ["--set", "step=0.001", "--set", "t_final=0.5", "--set", "log_every=1",
            "--set", "log=[arm.q, arm.qdot, tau.y, adapt.theta_hat]"]
    cli = [sys.executable, os.path.join(ROOT, "cli.py")]
    done = subprocess.run(cli + ["run", SLOTINE_LI, *sets, "-o", str(out), "--no-plots", "-q"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    for extra, message in [
            (["--regressor", "arm"], "'arm' (TwoLinkArm) is not a regressor"),
            (["--regressor", "Y", "--q", "tau.y"], "pass --tau SIGNAL"),
            (["--regressor", "Y", "--truth", "adapt.theta_hat"], "changes during the run"),
            (["--regressor", "Y", "--bandwidth", "0"], "finite lambda > 0")]:
        done = subprocess.run(cli + ["identify", str(out), *extra, "-o", str(tmp_path / "i")],
                              env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 2, (extra, done.stdout)
        assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1, extra
    assert not (tmp_path / "i").exists()
