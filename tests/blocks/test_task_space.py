"""Task space: URDFFrame's two implementations, and diagrams/robots/ur5_task_space.yaml's
end-effector error against the closed form of its task-space reference dynamics."""
from pathlib import Path

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

import fwdstep  # noqa: E402
from fwdstep.blocks.urdf import URDFFrame  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DIAGRAM = ROOT / "diagrams" / "robots" / "ur5_task_space.yaml"


@pytest.mark.parametrize("robot, frame", [("ur5", "tool0"), ("panda", "panda_hand")])
def test_frame_pinocchio_path_equals_the_kernels(robot, frame):
    kernels = URDFFrame("f", robot=robot, frame=frame, implementation="kernels")
    pinocchio = URDFFrame("f", robot=robot, frame=frame, implementation="pinocchio")
    n = kernels.inputs["q"].shape[0]
    rng = np.random.default_rng(4)
    q, qdot = rng.uniform(-2, 2, (3, n)), rng.standard_normal((3, n))
    for a, b in zip(kernels.output(0.0, None, (q, qdot)), pinocchio.output(0.0, None, (q, qdot))):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(a).max()))


def test_end_effector_error_is_the_critically_damped_closed_form():
    """With the exact model, p_e = p - p_d obeys pddot_e + 2 w pdot_e + w^2 p_e = 0:
    p_e(t) = (p_e(0) + (pdot_e(0) + w p_e(0)) t) exp(-w t), pdot_e(0) = -pdot_d(0)."""
    d = fwdstep.load_diagram(str(DIAGRAM), overrides={"t_final": 2.0})
    r = fwdstep.simulate(d)
    w, radius, speed = (d.spec.parameters[k] for k in ("omega", "radius", "w"))
    e0 = r["e.y"][0]
    edot0 = -np.array([0.0, radius * speed, 0.0])        # the circle starts along +y
    t = r.t[:, None]
    closed = (e0 + (edot0 + w * e0) * t) * np.exp(-w * t)
    np.testing.assert_allclose(r["e.y"], closed, rtol=0, atol=1e-9)
    assert np.abs(e0).max() > 0.03                        # it starts off the circle
    # the tool's orientation held: its angular velocity stays zero (round-off)
    assert np.abs(r["omega_tool.y"]).max() < 1e-12
    # the torque stays within the URDF's effort limits the clip takes from the arm
    assert {e["what"]: e["exceeded"] for e in r.limits} == {
        "effort": False, "velocity": False, "position": False}
