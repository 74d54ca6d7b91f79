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
                               "t_final, step, solver, log_every, bound, backend")


def test_override_name_must_be_a_name_or_a_dotted_path():
    with pytest.raises(ConfigError) as info:
        parse_override("plots..x=1")
    assert str(info.value) == ("--set 'plots..x=1': 'plots..x' is not a parameter name, "
                               "simulation.SETTING, log, BLOCK.PARAMETER or "
                               "SUBSYSTEM.BLOCK.PARAMETER")
