"""One mistake, one line (issue 24, item 2): a block that fails does not drag the ports it
would have driven into "not connected" errors; a ``--set`` that breaks a parameter is
blamed, not the function it reached; ``urdf:`` is relative to the diagram that names it."""
import os
import shutil

import pytest

from fwdstep.cli import arguments as cli

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")
THEOREM6 = os.path.join(ROOT, "diagrams", "theorem6.yaml")
PLANT = os.path.join(ROOT, "diagrams", "lib", "plant.yaml")


def _lines(capsys) -> list:
    return capsys.readouterr().err.splitlines()


def test_a_failing_block_in_a_subsystem_gives_one_line(capsys):
    assert cli.main(["validate", THEOREM6, "--set", "plant.q0=[0.1,0.2,0.3]"]) == 2
    assert _lines(capsys) == [
        f"fwdstep: {PLANT}:15: "
        "block 'plant/arm' parameter 'q0' must be a number or a list of 2 numbers, got "
        "shape (3,)"]


def test_two_failing_blocks_give_two_lines_and_nothing_else(tmp_path, capsys):
    path = tmp_path / "two.yaml"
    path.write_text("blocks:\n"
                    "  a: {type: Integrator, x0: [1, 2], n: 3}\n"
                    "  b: {type: Integrator, x0: [1, 2], n: 3}\n"
                    "  g: {type: Gain, gain: 2}\n"
                    "  h: {type: Gain, gain: 3}\n"
                    "connections: [a.y -> g.u, b.y -> h.u, g.y -> a.u, h.y -> b.u]\n"
                    "simulation: {t_final: 1, step: 0.1}\n")
    assert cli.main(["validate", str(path)]) == 2
    lines = _lines(capsys)
    assert len(lines) == 2, lines
    assert "block 'a'" in lines[0] and "block 'b'" in lines[1]


def test_misspelt_parameter_gets_did_you_mean(capsys):
    assert cli.main(["validate", THEOREM1, "--set", "alpah=3"]) == 2
    (line,) = _lines(capsys)
    assert "no parameter 'alpah'; did you mean 'alpha'?" in line


def test_a_set_value_that_breaks_a_dependent_parameter_is_blamed(capsys):
    assert cli.main(["validate", THEOREM1, "--set", "ell=2.5"]) == 2
    (line,) = _lines(capsys)
    assert line.startswith(f"fwdstep: {THEOREM1}:17: --set ell=2.5: parameter "
                           "'qd_coefficients', which uses ell, cannot be evaluated: polypow()")


def test_urdf_is_relative_to_the_diagram_that_names_it(tmp_path, monkeypatch, capsys):
    pytest.importorskip("pinocchio", reason="URDF blocks need pinocchio (fwdstep[robots])")
    from fwdstep.blocks.urdf import NAMED_ROBOTS, _robots_folder
    try:
        folder = _robots_folder("arm")
    except Exception:  # noqa: BLE001 - example-robot-data missing
        pytest.skip("example-robot-data is not installed")
    robot = tmp_path / "robot"
    robot.mkdir()
    shutil.copy(folder / NAMED_ROBOTS["ur5"][0], robot / "arm.urdf")
    (robot / "arm.yaml").write_text(
        "blocks:\n"
        "  tau: {type: Constant, value: [0, 0, 0, 0, 0, 0]}\n"
        "  arm: {type: URDFArm, urdf: arm.urdf, gravity: 0}\n"
        "connections: [tau.y -> arm.tau]\n"
        "simulation: {t_final: 0.01, step: 0.001}\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert cli.main(["validate", "../robot/arm.yaml"]) == 0, capsys.readouterr().err
    # and a run keeps a copy of it, which rerun reads after the original is gone
    assert cli.main(["run", "../robot/arm.yaml", "-o", "one", "-q", "--no-plots"]) == 0
    assert os.path.isfile("one/diagram/arm.urdf")
    os.remove(robot / "arm.urdf")
    assert cli.main(["rerun", "one", "-o", "two", "-q", "--no-plots"]) == 0
