"""Command-line overrides of parameters and of simulation settings."""
import pytest

import fwdstep
from fwdstep.errors import ConfigError
from fwdstep.spec import load_spec, parse_override

DIAGRAM = """
parameters:
  k: 2
blocks:
  x: {type: Integrator, shape: [1], initial: [1.0]}
  g: {type: Gain, gain: -k, shape: [1]}
connections:
  - x.y -> g.u
  - g.y -> x.u
simulation: {t_final: 1, step: 0.01, solver: rk4}
"""


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "d.yaml"
    p.write_text(DIAGRAM)
    return str(p)


def test_simulation_settings_can_be_overridden(path):
    spec = load_spec(path, dict([parse_override("simulation.t_final=3"),
                                 parse_override("simulation.solver=heun"),
                                 parse_override("k=0.5")]))
    assert (spec.simulation.t_final, spec.simulation.solver) == (3.0, "heun")
    r = fwdstep.simulate(fwdstep.compiler.compile_spec(spec))
    assert r.t[-1] == pytest.approx(3.0)
    assert r["x.y"][-1, 0] == pytest.approx(2.718281828459045 ** -1.5, rel=1e-5)


def test_bad_simulation_override_names_the_setting(path):
    with pytest.raises(ConfigError) as info:
        load_spec(path, dict([parse_override("simulation.stepp=0.1")]))
    assert str(info.value) == (f"{path}:10: simulation has no setting 'stepp'; settings are: "
                               "t_final, step, solver, log_every, bound, backend, rtol, atol")


def test_override_name_must_be_a_name_or_a_dotted_path():
    with pytest.raises(ConfigError) as info:
        parse_override("plots..x=1")
    assert str(info.value) == ("--set 'plots..x=1': 'plots..x' is not a parameter name, "
                               "simulation.SETTING, log, BLOCK.PARAMETER or "
                               "SUBSYSTEM.BLOCK.PARAMETER")


# ------------------------------------------------------------- budgets and all errors (H15)
def test_a_chain_of_3000_parameters_resolves_in_linear_time(tmp_path):
    """p0 refers to p1, p1 to p2, ... written in the worst order (each after its user)."""
    import time
    n = 3000
    lines = [f"  p{i}: p{i + 1} + 1" for i in range(n - 1)] + [f"  p{n - 1}: 0"]
    path = tmp_path / "chain.yaml"
    path.write_text("parameters:\n" + "\n".join(lines) +
                    "\nblocks:\n  g: {type: Gain, gain: p0}\n")
    t0 = time.perf_counter()
    spec = load_spec(str(path))
    elapsed = time.perf_counter() - t0
    assert spec.parameters["p0"] == n - 1
    assert spec.blocks[0].params["gain"] == n - 1
    assert elapsed < 5.0, f"{elapsed:.1f} s (the quadratic resolver took minutes)"


def test_a_cycle_in_a_long_chain_names_its_members(tmp_path):
    path = tmp_path / "cycle.yaml"
    path.write_text("parameters:\n  a: b\n  b: c\n  c: a\n  d: 1\nblocks:\n"
                    "  g: {type: Gain, gain: d}\n")
    with pytest.raises(fwdstep.ExpressionError) as info:
        load_spec(str(path))
    assert str(info.value) == f"{path}:2: parameters a, b, c refer to each other in a cycle"


MANY_MISTAKES = """\
blocks:
  src: {type: Constant, value: [1, 2]}
  g: {type: Gainn, gain: 2}
  h: {type: Gain, gain: 2, shapee: [2]}
  i: {type: Integrator, shape: [2]}
  j: {type: Gain, gain: 2}
connections:
  - src.y -> g.u
  - src.y -> i.u
  - src.y -> j.u
  - i.yy -> h.u
  - i.y -> k.u
simulation: {t_final: -1, step: 0.1}
"""


def test_validate_reports_every_mistake_one_line_each(tmp_path, capsys):
    import cli
    path = tmp_path / "many.yaml"
    path.write_text(MANY_MISTAKES)
    assert cli.main(["validate", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.splitlines() == [f"fwdstep: {path}:{line}: {msg}" for line, msg in [
        (3, "unknown block type 'Gainn'; did you mean 'Gain'?"),
        (4, "block 'h' (Gain) has no parameter 'shapee'; valid parameters are: gain, shape"),
        (12, "connection names block 'k', which does not exist; blocks are: src, g, h, i, j"),
        (13, "simulation.t_final must be a positive number, got -1"),
    ]]
    # fixed at load level, the graph's mistakes are all reported next
    fixed = (MANY_MISTAKES.replace("Gainn", "Gain").replace("shapee", "shape")
             .replace("t_final: -1", "t_final: 1").replace("  - i.y -> k.u\n", ""))
    path.write_text(fixed)
    assert cli.main(["validate", str(path)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"fwdstep: {path}:8: connection src.y -> g.u: shapes differ: src.y is (2,), g.u is "
        "scalar ()",
        f"fwdstep: {path}:10: connection src.y -> j.u: shapes differ: src.y is (2,), j.u is "
        "scalar ()",
        f"fwdstep: {path}:11: block 'i' has no output port 'yy'; output ports are: y"]
    # the run command still says only the first
    assert cli.main(["run", str(path), "-o", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_missing_simulation_section_is_stated(tmp_path):
    path = tmp_path / "nosim.yaml"
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\n")
    spec = load_spec(str(path))
    assert spec.simulation.defaulted == ("t_final", "step", "solver")
    assert (spec.simulation.t_final, spec.simulation.step) == (10.0, 1e-3)
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\nsimulation: {t_final: 1}\n")
    assert load_spec(str(path)).simulation.defaulted == ("step", "solver")
