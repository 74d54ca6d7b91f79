"""A URDF pinocchio cannot read is one line from fwdstep, with urdfdom's reason, and nothing
else on stderr: urdfdom's C++ log lines (with its build paths) printed before it."""
import pytest

from fwdstep.cli.arguments import main

pytest.importorskip("pinocchio")

BAD = """<robot name="r">
  <link name="a"/>
  <joint name="j" type="revolute"><parent link="a"/><child link="nope"/>
    <limit effort="1" velocity="1" lower="-1" upper="1"/></joint>
</robot>
"""


def test_a_broken_urdf_is_one_line_with_urdfdoms_reason(tmp_path, capfd):
    (tmp_path / "bad.urdf").write_text(BAD)
    path = tmp_path / "d.yaml"
    path.write_text(f"blocks:\n  arm: {{type: URDFArm, urdf: '{tmp_path / 'bad.urdf'}'}}\n"
                    "simulation: {t_final: 1, step: 0.01}\n")
    assert main(["validate", str(path)]) == 2
    out, err = capfd.readouterr()
    assert err == (f"fwdstep: {path}:2: block 'arm': the robot cannot read URDF "
                   f"'{tmp_path / 'bad.urdf'}': Failed to build tree: child link [nope] of "
                   "joint [j] not found\n")
    assert out == ""
