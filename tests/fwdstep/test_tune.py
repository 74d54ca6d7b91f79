"""Gain tuning (issue 28): against an independent optimum on a dense grid.

The problem: a PI controller (Kp s + Ki)/s on the plant 1/(s+1)^3, unit step reference,
minimise the integral of e^2.  The reference cost is exact and independent of fwdstep: the
closed loop is linear, so ISE = C X C^T with X from the Lyapunov equation (scipy)."""
import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import fwdstep
from fwdstep.sweeps.tune import tune

PI = """
parameters:
  Kp: 0.5     # proportional gain
  Ki: 0.2     # integral gain
blocks:
  r: {type: Constant, value: 1.0}
  e: {type: Sum, signs: "+-"}
  pi: {type: TransferFunction, num: [Kp, Ki], den: [1, 0]}
  plant: {type: TransferFunction, num: [1], den: [1, 3, 3, 1]}
connections: [r.y -> e.u1, plant.y -> e.u2, e.y -> pi.u, pi.y -> plant.u]
simulation: {t_final: 30, step: 0.1, solver: rk4, log_every: 1}
log: [e.y, pi.y]
metrics: {error: e.y}
"""
BOUNDS = {"Kp": (0.05, 4.0), "Ki": (0.02, 1.5)}
GRID = 41          # a 41 x 41 grid: 1681 runs


def _exact_ise(kp, ki):
    from scipy import linalg, signal
    dl = np.polymul([1, 0], [1, 3, 3, 1])
    den = np.polyadd(dl, [kp, ki])
    A, B, C, _ = signal.tf2ss(dl[:-1], den)       # E(s) = den_L / (s (den_L + num_L))
    if np.max(np.linalg.eigvals(A).real) >= 0:
        return np.inf
    X = linalg.solve_continuous_lyapunov(A, -B @ B.T)
    return float((C @ X @ C.T).item())


@pytest.fixture
def pi_diagram(tmp_path):
    path = tmp_path / "pi.yaml"
    path.write_text(PI)
    return str(path)


def test_tuning_beats_a_dense_grid_with_a_tenth_of_its_runs(pi_diagram, tmp_path):
    kp = np.linspace(*BOUNDS["Kp"], GRID)
    ki = np.linspace(*BOUNDS["Ki"], GRID)
    grid_best = min(_exact_ise(a, b) for a in kp for b in ki)
    r = tune(pi_diagram, BOUNDS, "ise(e.y)", screen=8, starts=2, outdir=str(tmp_path / "t"))
    assert r.runs["total"] <= GRID * GRID / 10
    # the tuned point's exact cost, and fwdstep's own number for it
    assert _exact_ise(r.best["Kp"], r.best["Ki"]) <= 1.01 * grid_best
    assert r.best_cost <= 1.01 * grid_best
    assert r.initial_cost > 2 * r.best_cost
    rows = list(csv.DictReader(open(tmp_path / "t" / "history.csv")))
    assert len(rows) == r.runs["total"]
    summary = json.load(open(tmp_path / "t" / "tune.json"))
    assert summary["best"]["values"] == r.best
    tuned = fwdstep.load_diagram(str(tmp_path / "t" / "best.yaml"))
    assert tuned.spec.parameters["Kp"] == pytest.approx(r.best["Kp"], rel=1e-12)
    text = open(tmp_path / "t" / "best.yaml").read()
    line = next(x for x in text.splitlines() if x.startswith("  Kp:"))
    assert "tuned (was: 0.5)" in line and line.endswith("# proportional gain")


def test_a_torque_like_limit_is_respected(pi_diagram):
    r = tune(pi_diagram, BOUNDS, "ise(e.y)", ["max_abs(pi.y) <= 2"], screen=8, starts=1)
    run = fwdstep.simulate(fwdstep.load_diagram(pi_diagram, r.best))
    assert np.abs(run["pi.y"]).max() <= 2 + 1e-6
    assert r.best_constraints[0] == pytest.approx(2.0, abs=1e-3)     # the limit is active
    assert r.best_cost < 0.6 * r.initial_cost


def test_cli_tune_writes_its_files_and_refuses_bad_options(pi_diagram, tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, PYTHONPATH=root, MPLBACKEND="Agg")
    out = tmp_path / "cli"
    cmd = [sys.executable, os.path.join(root, "cli.py"), "tune", pi_diagram,
           "--vary", "Kp=0.05:4", "--minimize", "ise(e.y)", "--screen", "2", "--starts", "1",
           "--max-iterations", "2", "-q", "-o", str(out)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "after:  Kp=" in done.stdout
    for name in ("history.csv", "history.png", "tune.json", "best.yaml", "before_after.png",
                 "report.html"):
        assert (out / name).is_file()
    # the report compares before and after with the numbers of tune.json, both figures inline
    rec = json.loads((out / "tune.json").read_text())
    page = (out / "report.html").read_text()
    assert "<h2>Before and after</h2>" in page and page.count("data:image/png;base64,") == 2
    row = page[page.index("<td>Kp</td>"):].split("</tr>")[0]
    assert f"{rec['initial']['values']['Kp']:.6g}" in row
    assert f"{rec['best']['values']['Kp']:.6g}" in row
    # fwdstep report DIR writes the same page again from the files
    os.remove(out / "report.html")
    again = subprocess.run([sys.executable, os.path.join(root, "cli.py"), "report", str(out)],
                           env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert (out / "report.html").read_text().split("written by")[0] == page.split("written by")[0]
    bad = cmd[:4] + ["--vary", "Kq=0:1", "--minimize", "ise(e.y)", "-o", str(tmp_path / "b")]
    done = subprocess.run(bad, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert "the diagram has no parameter 'Kq'" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_compiled_backend_tunes_the_same_search(pi_diagram):
    """`backend="compiled"` runs every evaluation (plain and with sensitivities) in compiled
    code; the search is the same one: the same points to the sensitivities' agreement."""
    pytest.importorskip("numba")
    kw = dict(screen=4, starts=1, max_iterations=4)
    a = tune(pi_diagram, BOUNDS, "ise(e.y)", ["max_abs(pi.y) <= 2"], backend="numpy", **kw)
    b = tune(pi_diagram, BOUNDS, "ise(e.y)", ["max_abs(pi.y) <= 2"], backend="compiled", **kw)
    assert {e.backend for e in a.history} == {"numpy"}
    assert {e.backend for e in b.history} == {"compiled"}
    assert len(b.history) == len(a.history) and b.runs == a.runs
    for k in BOUNDS:
        assert b.best[k] == pytest.approx(a.best[k], rel=1e-8)
    assert b.best_cost == pytest.approx(a.best_cost, rel=1e-9)


def test_the_tuned_values_lie_in_the_bounds_even_when_the_start_is_better(pi_diagram):
    """Kp = 0.5 as written, tuned over [0.05, 0.3] where every point is worse (exact ISE
    increasing as Kp falls): the answer is the best point of the box (Kp = 0.3, on its
    edge), not the diagram's own value outside it (which was reported as 'after')."""
    box = (0.05, 0.3)
    grid = np.linspace(*box, 201)
    exact = [_exact_ise(k, 0.2) for k in grid]
    assert _exact_ise(0.5, 0.2) < min(exact)              # the start beats the whole box
    r = tune(pi_diagram, {"Kp": box}, "ise(e.y)", screen=4, starts=1, max_iterations=10)
    assert box[0] <= r.best["Kp"] <= box[1]
    assert _exact_ise(r.best["Kp"], 0.2) <= 1.01 * min(exact)
    assert r.initial["Kp"] == 0.5                          # 'before' is still the diagram's
    # no screening: the search starts from the diagram's values brought into the box
    r = tune(pi_diagram, {"Kp": box}, "ise(e.y)", screen=0, starts=1, max_iterations=10)
    assert box[0] <= r.best["Kp"] <= box[1]
    assert _exact_ise(r.best["Kp"], 0.2) <= 1.01 * min(exact)


def test_a_name_varied_twice_is_refused():
    from fwdstep.core.errors import ConfigError
    from fwdstep.sweeps.tune import parse_vary
    with pytest.raises(ConfigError) as info:
        parse_vary(["Kp=0:3", "Kp=1:2"])
    assert str(info.value) == ("--vary 'Kp=1:2': Kp is already varied over 0:3; give each "
                               "name once")


def test_an_interrupted_search_keeps_its_points_and_says_so(pi_diagram, tmp_path,
                                                            monkeypatch, capsys):
    """A signal mid-search: what was evaluated is written (history.csv holds every
    evaluation), tune.json says 'interrupted', and the CLI exits 128 + the signal (it
    exited 0 with 'note: interrupted; ' as if the search had finished)."""
    import signal
    from fwdstep.cli.arguments import main
    from fwdstep.core.signals import Interrupted
    from fwdstep.sweeps import tune as tune_module
    real = tune_module._Problem.evaluate
    calls = []

    def evaluate(self, *a, **k):
        calls.append(1)
        if len(calls) == 7:
            raise Interrupted(signal.SIGTERM)
        return real(self, *a, **k)

    monkeypatch.setattr(tune_module._Problem, "evaluate", evaluate)
    out = tmp_path / "t"
    code = main(["tune", pi_diagram, "--vary", "Kp=0.05:4", "--vary", "Ki=0.02:1.5",
                 "--minimize", "ise(e.y)", "--screen", "16", "--starts", "2", "-o", str(out),
                 "-q"])
    assert code == 128 + signal.SIGTERM
    record = json.load(open(out / "tune.json"))
    assert record["status"] == "interrupted" and record["evaluations"] == 6
    assert record["message"].startswith("terminated (SIGTERM) after 6 evaluations")
    with open(out / "history.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 6
    assert "interrupted" in open(out / "report.html").read()


@pytest.mark.parametrize("damage, field", [
    (lambda rec: rec.update(bounds={"Kp": "x"}), "'bounds'"),
    (lambda rec: rec.update(bounds={"Kp": [1]}), "'bounds'"),
    (lambda rec: rec["initial"].update(values=[1, 2]), "'initial.values'"),
    (lambda rec: rec.update(subject_to="abc"), "'subject_to'"),
    (lambda rec: rec["best"].update(cost="low"), "'best.cost'"),
])
def test_report_of_a_damaged_tune_record_is_one_line(pi_diagram, tmp_path, damage, field):
    """Each of these was a bare traceback (ValueError, IndexError, AttributeError) or, for
    subject_to as a string, a page with one constraint row per character."""
    from fwdstep.core.errors import DamagedFileError
    from fwdstep.views.report import _tune_record
    out = tmp_path / "t"
    tune(pi_diagram, BOUNDS, "ise(e.y)", screen=2, starts=1, max_iterations=1,
         outdir=str(out), figures=False)
    path = out / "tune.json"
    rec = json.load(open(path))
    assert _tune_record(str(path)) == rec                 # as written: accepted
    damage(rec)
    json.dump(rec, open(path, "w"))
    with pytest.raises(DamagedFileError, match=f"damaged tuning record: {field}"):
        _tune_record(str(path))


def test_a_point_the_diagram_refuses_is_a_failed_evaluation_not_the_end(tmp_path):
    """The reference sqrt(Kp - 1) cannot be evaluated for Kp < 1: those points of the box
    fail (as a diverging run does) and the search goes on; the tuning aborted at the first
    one and lost every evaluation made so far.  The optimum is then Kp just above 1 (the
    reference ~0), which the exact ISE of a step of height sqrt(Kp - 1) confirms."""
    path = tmp_path / "pi_sqrt.yaml"
    path.write_text(PI.replace("value: 1.0", 'value: "sqrt(Kp - 1)"').replace("Kp: 0.5",
                                                                              "Kp: 2"))
    result = tune(str(path), {"Kp": (0.05, 4.0)}, "ise(e.y)", screen=8, starts=1,
                  max_iterations=10, outdir=str(tmp_path / "t"), figures=False)
    failed = [e for e in result.history if e.status == "invalid"]
    assert failed and all(e.values[0] < 1 for e in failed)
    assert all(e.status == "ok" for e in result.history if e.values[0] > 1)
    assert "evaluation(s) failed" in result.message and "sqrt(Kp - 1)" in result.message
    kp = result.best["Kp"]
    assert 1 <= kp < 1.05
    assert abs(result.best_cost - (kp - 1) * _exact_ise(kp, 0.2)) < 1e-3 * _exact_ise(kp, 0.2)


def test_a_nan_constraint_is_not_counted_as_met(pi_diagram):
    from fwdstep.sweeps.tune import Evaluation, _Problem
    prob = _Problem(pi_diagram, BOUNDS, "ise(e.y)", ["max_abs(pi.y) <= 2"], None, None)
    ev = lambda c: Evaluation(0, "screen", -1, np.zeros(2), 1.0, [c], None, "ok", False, 0.0)
    assert prob.violation(ev(1.0)) == 0 and prob.violation(ev(3.0)) == 0.5
    assert prob.violation(ev(float("nan"))) == float("inf")      # was 0: 'satisfied'
