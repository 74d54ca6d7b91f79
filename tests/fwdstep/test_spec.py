"""Command-line overrides of parameters and of simulation settings."""
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError
from fwdstep.structure.spec import load_spec, parse_override

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
    r = fwdstep.simulate(fwdstep.structure.compiler.compile_spec(spec))
    assert r.t[-1] == pytest.approx(3.0)
    assert r["x.y"][-1, 0] == pytest.approx(2.718281828459045 ** -1.5, rel=1e-5)


def test_bad_simulation_override_names_the_setting(path):
    with pytest.raises(ConfigError) as info:
        load_spec(path, dict([parse_override("simulation.stepp=0.1")]))
    assert str(info.value) == (f"{path}:10: simulation has no setting 'stepp'; settings are: "
                               "t_final, step, solver, log_every, bound, backend, rtol, atol, "
                               "stability_check")


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
    t0 = time.process_time()
    spec = load_spec(str(path))
    elapsed = time.process_time() - t0
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
  g: {type: Gainn, gain: 2, shape: [3]}
  h: {type: Gain, gain: 2, shapee: [2]}
  i: {type: Integrator, shape: [2]}
  j: {type: Gain, gain: 2, shape: [3]}
connections:
  - src.y -> g.u
  - src.y -> i.u
  - src.y -> j.u
  - i.yy -> h.u
  - i.y -> k.u
simulation: {t_final: -1, step: 0.1}
"""


def test_validate_reports_every_mistake_one_line_each(tmp_path, capsys):
    from fwdstep.cli import arguments as cli
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
        "(3,)",
        f"fwdstep: {path}:10: connection src.y -> j.u: shapes differ: src.y is (2,), j.u is "
        "(3,)",
        f"fwdstep: {path}:11: block 'i' has no output port 'yy'; output ports are: y"]
    # the run command still says only the first
    assert cli.main(["run", str(path), "-o", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_missing_simulation_section_is_stated(tmp_path):
    from fwdstep.structure.spec import defaults_note
    path = tmp_path / "nosim.yaml"
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\n")
    spec = load_spec(str(path))
    assert spec.simulation.defaulted == ("t_final", "step")
    assert (spec.simulation.t_final, spec.simulation.step) == (10.0, 1e-3)
    assert defaults_note(spec.simulation) == ("the diagram has no simulation: section; using "
                                              "the defaults t_final = 10 s, step = 0.001 s")
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\nsimulation: {t_final: 1}\n")
    assert defaults_note(load_spec(str(path)).simulation) == (
        "the diagram has no simulation.step; using the defaults step = 0.001 s")
    path.write_text("blocks:\n  c: {type: Constant, value: 1}\n"
                    "simulation: {t_final: 1, step: 0.5}\n")
    assert defaults_note(load_spec(str(path)).simulation) is None


def test_metrics_give_the_norm_and_the_largest_joint_separately(tmp_path):
    """e(t) = [t, -2 t] on [0, 1]: |e|_2 = sqrt(5) t, the largest joint error is 2 t."""
    import numpy as np
    path = tmp_path / "ramp.yaml"
    path.write_text("blocks:\n  c: {type: Constant, value: [1, -2]}\n"
                    "  x: {type: Integrator, shape: [2]}\nconnections: [c.y -> x.u]\n"
                    "simulation: {t_final: 1, step: 0.01}\nmetrics: {error: x.y, tail: 0.2}\n")
    m = fwdstep.simulate(fwdstep.load_diagram(str(path))).metrics()
    t = np.linspace(0, 1, 101)
    assert m["final_error_norm"] == pytest.approx(np.sqrt(5), rel=1e-12)
    assert m["final_error_max_abs"] == pytest.approx(2, rel=1e-12)
    assert m["tail_error_norm_max"] == pytest.approx(np.sqrt(5), rel=1e-12)
    assert m["tail_error_max_abs"] == pytest.approx(2, rel=1e-12)
    assert m["tail_error_max_abs_by_component"] == pytest.approx([1, 2], rel=1e-12)
    assert m["rms_error_norm"] == pytest.approx(np.sqrt(5 * np.mean(t ** 2)), rel=1e-12)


@pytest.mark.parametrize("gamma, what", [
    (0, "is 0, not positive"),
    ([1, -2], "entry 2 is -2, not positive"),
    ([1, 2, 3], "has 3 numbers, not 1 or 2"),
    ([[1, 2], [0, 1]], "is not symmetric"),
    ([[1, 2], [2, 1]], "is symmetric but not positive definite"),
    ([[1, 0, 0]], "is an array of shape 1x3, not 2x2"),
])
def test_adaptation_gain_messages_say_what_is_wrong_with_the_value(tmp_path, gamma, what):
    path = tmp_path / "adapt.yaml"
    path.write_text("blocks:\n  W: {type: Constant, value: [[1, 0], [0, 1]]}\n"
                    "  e: {type: Constant, value: [0, 0]}\n"
                    "  adapt: {type: AdaptationLaw, regressor_shape: [2, 2], gamma: 1}\n"
                    "connections: [W.y -> adapt.W, e.y -> adapt.e]\n"
                    "simulation: {t_final: 1, step: 0.5}\n")
    with pytest.raises(fwdstep.ParameterError) as info:
        fwdstep.load_diagram(str(path), {"adapt.gamma": gamma})
    assert str(info.value) == (f"{path}:4: block 'adapt' parameter 'gamma' {what} (it must be "
                               "a positive number, 2 positive numbers, or a symmetric positive "
                               "definite 2x2 matrix)")


def test_every_option_has_help_and_version_prints(capsys):
    import argparse
    from fwdstep.cli import arguments as cli
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = [f"{name} {a.option_strings or a.dest}" for name, sp in sub.choices.items()
               if name != "sweep"            # the sweep's options: H13 (issue 13)
               for a in sp._actions if not a.help]
    assert missing == []
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("fwdstep ")


def test_the_parse_cache_sees_an_edit_that_keeps_size_and_mtime(tmp_path):
    """A file edited in place to the same size, its mtime put back (an editor, a checkout
    within the clock's resolution), is parsed again: the cache is keyed by content too."""
    import os
    f = tmp_path / "d.yaml"
    text = ("parameters: {k: 1.5}\nblocks:\n  c: {type: Constant, value: k}\n"
            "connections: []\nsimulation: {t_final: 0.1, step: 0.01}\n")
    f.write_text(text)
    st = os.stat(f)
    cache = {}
    assert load_spec(str(f), {}, cache).parameters["k"] == 1.5
    f.write_text(text.replace("1.5", "2.5"))
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(f).st_size == st.st_size and os.stat(f).st_mtime_ns == st.st_mtime_ns
    assert load_spec(str(f), {}, cache).parameters["k"] == 2.5
