"""Discrete-time refusals found before the run (issue 23): ``fwdstep validate`` refuses what
``fwdstep run`` cannot do -- a discrete algebraic loop, a sample period giving more
instants than the limit (5e-324 s: infinitely many) -- in one line, exit 2; a loop broken by a
UnitDelay (or a strictly proper DiscreteTransferFunction, D = 0) still validates and runs."""
import pytest

from fwdstep.cli import arguments as cli

LOOP = """
blocks:
  a: {type: ZeroOrderHold, period: 0.1}
  b: {type: %s}
  g: {type: Gain, gain: 0.5}
  c: {type: Constant, value: 1.0}
  s: {type: Sum, signs: "++"}
connections:
  - c.y -> s.u1
  - b.y -> s.u2
  - s.y -> a.u
  - a.y -> g.u
  - g.y -> b.u
simulation: {t_final: 1, step: 0.01, solver: rk4}
log: [a.y]
"""
HOLD = "ZeroOrderHold, period: 0.1"


def _write(tmp_path, text):
    p = tmp_path / "d.yaml"
    p.write_text(text)
    return str(p)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fwdstep: "), err
    return err


@pytest.mark.parametrize("b", [HOLD, "DiscreteTransferFunction, period: 0.1, "
                                     "num: [0.25, 0.1], den: [1, -0.5]"])
@pytest.mark.parametrize("verb", ["validate", "run"])
def test_a_discrete_algebraic_loop_is_refused_before_running(tmp_path, capsys, b, verb):
    path = _write(tmp_path, LOOP % b)
    args = [verb, path] + (["-o", str(tmp_path / "o"), "-q"] if verb == "run" else [])
    assert cli.main(args) == 2
    err = _one_line(capsys)
    assert "discrete algebraic loop" in err and "'a'" in err and "'b'" in err
    assert path in err


@pytest.mark.parametrize("b", ["UnitDelay, period: 0.1",
                               "DiscreteTransferFunction, period: 0.1, num: [1], den: [1, -0.5]"])
def test_a_loop_with_a_delay_runs(tmp_path, capsys, b):
    path = _write(tmp_path, LOOP % b)
    assert cli.main(["validate", path]) == 0
    assert cli.main(["run", path, "-o", str(tmp_path / "o"), "-q", "--no-plots"]) == 0


@pytest.mark.parametrize("period", ["5e-324", "1e-300", "1e-9"])
@pytest.mark.parametrize("verb", ["validate", "run"])
def test_a_tiny_period_is_one_line(tmp_path, capsys, period, verb):
    path = _write(tmp_path, LOOP.replace("a: {type: ZeroOrderHold, period: 0.1}",
                                         f"a: {{type: ZeroOrderHold, period: {period}}}")
                  % "UnitDelay, period: 0.1")
    args = [verb, path] + (["-o", str(tmp_path / "o"), "-q"] if verb == "run" else [])
    assert cli.main(args) == 2
    err = _one_line(capsys)
    assert "block 'a'" in err and "sample instants" in err and "limit 1e+07" in err
