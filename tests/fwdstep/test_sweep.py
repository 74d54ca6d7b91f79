"""Sweeps (fwdstep.sweep, ``fwdstep sweep``): batched variants give the one-by-one numbers.

The sweep groups variants by structure (``ell`` changes the state size: one batch per ell),
runs each group as one batch, and writes one CSV row per variant.  The batched table must
equal the ``--sequential`` table to 1e-12, including a variant that diverges (frozen in its
batch while the others continue) and one whose block raises (its batch is re-run variant by
variant, so the others still get their numbers).
"""
import csv
import os

import numpy as np
import pytest

import cli
from fwdstep.errors import ConfigError
from fwdstep.sweep import (METRICS, parse_grid, parse_random, run_sweep, split_values,
                           variant_values)

LOOP = """
parameters: {ell: 2, alpha: 4, gamma: 2, K: 20, q0: [0.1, -0.1]}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: q0}
  ref:   {type: ReferenceDynamics, variant: eq2, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  Ks:    {type: Gain, gain: K, shape: [2]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Yth.y -> tau.u1
  - Ks.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.5, step: 0.002, solver: rk4, log_every: 5, bound: 1e3}
log: [e.y]
metrics: {error: e.y}
"""


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "loop.yaml"
    p.write_text(LOOP)
    return str(p)


def _table(result):
    return {v.index: v for v in result.variants}


def test_batched_sweep_equals_sequential_sweep(path):
    grid = {"ell": [1, 2], "K": [20, -120, 50]}            # K = -120 diverges for ell = 2
    random = {"gamma": (0.5, 3.0)}
    batched = run_sweep(path, grid, random, samples=2, seed=7)
    alone = run_sweep(path, grid, random, samples=2, seed=7, sequential=True)
    assert len(batched.variants) == 12 and len(batched.batches) == 2      # one per ell
    assert len(alone.batches) == 12
    a, b = _table(batched), _table(alone)
    statuses = [v.status for v in batched.variants]
    assert statuses.count("diverged") == 2 and statuses.count("ok") == 10
    for i in a:
        assert a[i].values == b[i].values and a[i].status == b[i].status
        if a[i].status == "diverged":
            assert a[i].values["K"] == -120 and a[i].values["ell"] == 2
            assert a[i].diverged_at == pytest.approx(b[i].diverged_at, abs=1e-12)
            assert not a[i].metrics
            continue
        for m in METRICS:
            assert a[i].metrics[m] == pytest.approx(b[i].metrics[m], rel=1e-12, abs=1e-15)
    # the random samples are seeded: the same gamma pairs in every grid cell
    gammas = sorted({round(v.values["gamma"], 12) for v in batched.variants})
    assert len(gammas) == 2 and all(0.5 <= g <= 3.0 for g in gammas)


def test_cli_writes_table_and_figure(path, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["sweep", path, "--grid", "alpha=2,4", "--grid", "K=20,-300",
                     "--set", "gamma=1", "-o", str(out), "-q"])
    assert code == 3                               # a variant diverged
    with open(out / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["alpha"], r["K"]) for r in rows] == [("2", "20"), ("2", "-300"), ("4", "20"),
                                                    ("4", "-300")]
    assert [r["status"] for r in rows] == ["ok", "diverged", "ok", "diverged"]
    assert float(rows[0]["tail_max_abs_error"]) > 0 and rows[1]["tail_max_abs_error"] == ""
    assert float(rows[1]["diverged_at"]) > 0
    assert os.path.getsize(out / "sweep.png") > 10_000
    # an existing table is not overwritten without --force
    code = cli.main(["sweep", path, "--grid", "alpha=2,4", "-o", str(out), "-q"])
    assert code == 2 and "already exists" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=2,4", "-o", str(out), "-q",
                     "--force"]) == 0


def test_a_raising_variant_does_not_spoil_its_batch(path, monkeypatch):
    """A block that raises for one variant only: the batch is re-run variant by variant."""
    from blocks.adaptation import AdaptationLaw
    original = AdaptationLaw.derivative

    def fragile(self, t, x, u):
        if np.any(self.p.gamma == 5.0) and t > 0.1:
            raise ZeroDivisionError("broken adaptation")
        return original(self, t, x, u)

    monkeypatch.setattr(AdaptationLaw, "derivative", fragile)
    result = run_sweep(path, {"gamma": [2, 5, 3]})
    assert [v.status for v in result.variants] == ["ok", "error", "ok"]
    assert "broken adaptation" in result.variants[1].message
    assert all(result.variants[i].metrics for i in (0, 2))


def test_bad_options_are_one_line_errors(path, tmp_path, capsys):
    out = str(tmp_path / "o")
    assert cli.main(["sweep", path, "--grid", "kappa=1,2", "-o", out]) == 2
    assert "no parameter 'kappa'" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--random", "alpha=1:x", "--samples", "2", "-o", out]) == 2
    assert "NAME=LOW:HIGH" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--random", "alpha=1:3", "-o", out]) == 2
    assert "--samples" in capsys.readouterr().err
    assert cli.main(["sweep", path, "-o", out]) == 2
    assert "nothing to sweep" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=1", "--set", "alpha=2", "-o", out]) == 2
    assert "both swept and set" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=-1", "-o", out]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fwdstep: ") and "variant alpha=-1" in err and "\n" == err[-1]
    assert not os.path.exists(out)


def test_value_parsing():
    assert split_values("1, 2,[3, 4],diag([1,2])") == ["1", "2", "[3, 4]", "diag([1,2])"]
    assert parse_grid(["ell=1,2", "K=20*eye(2),[[1,0],[0,1]]"]) == {
        "ell": [1, 2], "K": ["20*eye(2)", [[1, 0], [0, 1]]]}
    assert parse_random(["a=1:2.5"]) == {"a": (1.0, 2.5)}
    with pytest.raises(ConfigError, match="LOW must not exceed HIGH"):
        parse_random(["a=3:1"])
    values = variant_values({"a": [1, 2, 3]}, {"b": (0.0, 1.0)}, samples=4, seed=3)
    assert len(values) == 12 and values == variant_values({"a": [1, 2, 3]}, {"b": (0.0, 1.0)},
                                                          samples=4, seed=3)
    assert [v["a"] for v in values[:5]] == [1, 1, 1, 1, 2]
    with pytest.raises(ConfigError, match="both in --grid and --random"):
        variant_values({"a": [1]}, {"a": (0.0, 1.0)}, samples=1, seed=0)
