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


def _chain(links: int) -> str:
    body = ['<robot name="chain">']
    for i in range(links):
        body.append(f'<link name="l{i}"><inertial><mass value="1"/><origin xyz="0 0 0.1"/>'
                    '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>'
                    '</inertial></link>')
    for i in range(1, links):
        body.append(f'<joint name="j{i}" type="revolute"><parent link="l{i - 1}"/>'
                    f'<child link="l{i}"/><origin xyz="0 0 0.2"/><axis xyz="0 1 0"/>'
                    '<limit effort="10" velocity="1" lower="-3" upper="3"/></joint>')
    return "\n".join(body + ["</robot>"]) + "\n"


def test_a_urdf_beyond_the_link_budget_is_one_line_before_it_is_built(tmp_path, capfd):
    """A 200-link chain took 2.8 GB (base parameters) before MemoryError: refused by its
    link count, in one line, before pinocchio builds anything."""
    import fwdstep.blocks.urdf as urdf
    (tmp_path / "long.urdf").write_text(_chain(urdf.MAX_URDF_LINKS + 72))
    path = tmp_path / "d.yaml"
    path.write_text(f"blocks:\n  arm: {{type: URDFArm, urdf: '{tmp_path / 'long.urdf'}', "
                    "parameters: base}\nsimulation: {t_final: 1, step: 0.01}\n")
    assert main(["validate", str(path)]) == 2
    out, err = capfd.readouterr()
    assert err == (f"fwdstep: {path}:2: block 'arm': the robot has "
                   f"{urdf.MAX_URDF_LINKS + 72} links; the limit is {urdf.MAX_URDF_LINKS}\n")


def test_a_urdf_within_the_link_budget_builds():
    from fwdstep.structure.library import lookup
    import tempfile, os
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "short.urdf")
        with open(path, "w") as fh:
            fh.write(_chain(6))
        arm = lookup("URDFArm")("arm", urdf=path)
    assert arm.n_states == 10                            # 5 revolute joints: q and qdot
