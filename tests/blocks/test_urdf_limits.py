"""Joint limits from the URDF (URDFArm's limit outputs, the run's limit record,
stop_on_limits) against the URDF's own <limit> elements read with xml.etree, and the Clip
block against numpy.clip."""
import json
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

import fwdstep  # noqa: E402
from fwdstep.blocks.nonlinear import Clip  # noqa: E402
from fwdstep.blocks.urdf import NAMED_ROBOTS, URDFArm, _robots_folder  # noqa: E402
from fwdstep.core.errors import LimitExceeded  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def xml_limits(robot):
    """{joint: (effort, velocity, lower, upper)} read from the URDF text itself."""
    root = ElementTree.parse(str(_robots_folder("t") / NAMED_ROBOTS[robot][0])).getroot()
    out = {}
    for joint in root.iter("joint"):
        limit = joint.find("limit")
        if limit is not None:
            out[joint.get("name")] = tuple(float(limit.get(k, "nan")) for k in
                                           ("effort", "velocity", "lower", "upper"))
    return out


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_limit_outputs_are_the_urdf_limit_elements(robot):
    arm = URDFArm("arm", robot=robot)
    joints = list(arm.model.names[1:])
    expected = np.array([xml_limits(robot)[j] for j in joints])          # (n, 4)
    y = arm.output(0.0, arm.x0, (np.zeros((1, len(joints))),) * 2)
    names = list(arm.outputs)
    for k, port in enumerate(("effort_limit", "velocity_limit", "position_lower",
                              "position_upper")):
        assert np.array_equal(y[names.index(port)][0], expected[:, k]), port
    kinds = {limit.what: limit for limit in arm.limits}
    assert kinds["effort"].port == "tau" and kinds["effort"].upper == tuple(expected[:, 0])
    assert kinds["position"].lower == tuple(expected[:, 2])
    assert kinds["velocity"].components == tuple(joints)


def diagram(tmp_path, tau, stop=False, clip=False, t_final=0.4):
    text = textwrap.dedent(f"""\
        blocks:
          arm: {{type: URDFArm, robot: ur5, gravity: 0, q0: [0, -1.5, 1.5, 0, 0, 0],
                 stop_on_limits: {str(stop).lower()}}}
          torque: {{type: Constant, value: {tau}}}
        """)
    if clip:
        text += "  clip: {type: Clip}\n"
        wiring = ["torque.y -> clip.u", "arm.effort_limit -> clip.limit", "clip.y -> arm.tau"]
    else:
        wiring = ["torque.y -> arm.tau"]
    text += "connections:\n" + "".join(f"  - {w}\n" for w in wiring)
    text += (f"simulation: {{t_final: {t_final}, step: 0.001, solver: rk4, log_every: 5}}\n"
             "log: [arm.q, arm.qdot]\n")
    path = tmp_path / f"limits_{stop}_{clip}.yaml"
    path.write_text(text)
    return str(path)


def usage_by_hand(values, lower, upper):
    """max_t |v - centre| / half-width (= max_t |v| / upper for lower = -upper)."""
    centre, half = (upper + lower) / 2, (upper - lower) / 2
    return np.max(np.abs(values - centre) / half, axis=0)


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_a_run_beyond_the_limits_reports_them_and_goes_on(tmp_path, backend):
    if backend == "compiled":
        pytest.importorskip("numba")
    tau = [0, 0, 0, 40.0, 0, 5.0]          # wrist_1 above its 28 N m
    r = fwdstep.simulate(fwdstep.load_diagram(diagram(tmp_path, tau)), backend=backend)
    assert r.status == "ok" and r.t[-1] == pytest.approx(0.4)
    ref = xml_limits("ur5")
    joints = list(r.diagram.blocks[0].model.names[1:])
    effort, velocity, lower, upper = np.array([ref[j] for j in joints]).T
    record = {e["what"]: e for e in r.summary()["limits"]}
    assert record["effort"]["usage"] == pytest.approx(np.abs(tau) / effort, rel=1e-15)
    assert record["effort"]["exceeded"] and record["effort"]["first_exceeded_t"] == 0.0
    assert record["effort"]["worst_joint"] == "wrist_1_joint"
    assert record["velocity"]["usage"] == pytest.approx(
        usage_by_hand(r["arm.qdot"], -velocity, velocity), rel=1e-15)
    beyond = np.abs(r["arm.qdot"]) > velocity
    assert record["velocity"]["exceeded"] == bool(beyond.any())
    assert record["velocity"]["first_exceeded_t"] == r.t[np.argmax(beyond.any(axis=1))]
    assert record["position"]["usage"] == pytest.approx(
        usage_by_hand(r["arm.q"], lower, upper), rel=1e-15)
    q = r["arm.q"]
    assert record["position"]["exceeded"] == bool(((q > upper) | (q < lower)).any())


def test_stop_on_limits_ends_the_run_at_the_first_sample_beyond(tmp_path):
    tau = [0, 0, 0, 20.0, 0, 0]            # within the effort limit; the wrist speeds up
    free = fwdstep.simulate(fwdstep.load_diagram(diagram(tmp_path, tau)))
    ref = xml_limits("ur5")
    velocity = np.array([ref[j][1] for j in free.diagram.blocks[0].model.names[1:]])
    beyond = (np.abs(free["arm.qdot"]) > velocity).any(axis=1)
    assert beyond.any() and not beyond[0]
    first = int(np.argmax(beyond))
    with pytest.raises(LimitExceeded) as info:
        fwdstep.simulate(fwdstep.load_diagram(diagram(tmp_path, tau, stop=True)))
    stopped = info.value.result
    assert stopped.status == "limit exceeded"
    assert np.array_equal(stopped.t, free.t[:first + 1])
    assert np.array_equal(stopped["arm.qdot"], free["arm.qdot"][:first + 1])
    assert "velocity limit exceeded" in stopped.message and "wrist_1_joint" in stopped.message
    # the CLI: exit 5, the record and the partial results written
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(ROOT / "cli.py"), "run",
                           diagram(tmp_path, tau, stop=True), "-o", str(out), "--no-plots"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 5, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "limit exceeded"
    assert summary["t_reached"] == pytest.approx(free.t[first])


def test_clip_from_the_effort_limit_keeps_the_torque_at_the_limit(tmp_path):
    r = fwdstep.simulate(fwdstep.load_diagram(diagram(tmp_path, [0, 0, 0, 40.0, 0, -200.0],
                                                      clip=True, t_final=0.05)))
    record = {e["what"]: e for e in r.summary()["limits"]}
    assert record["effort"]["usage"] == [0, 0, 0, 1.0, 0, 1.0]
    assert not record["effort"]["exceeded"]


def test_clip_is_numpy_clip():
    rng = np.random.default_rng(3)
    u, a, b = rng.standard_normal((3, 4, 2, 3)) * 2
    limit = np.abs(a)
    sym = Clip("c", shape=[2, 3])
    assert np.array_equal(sym.output(0.0, None, (u, limit))[0], np.clip(u, -limit, limit))
    lower, upper = np.minimum(a, b), np.maximum(a, b)
    two = Clip("c", shape=[2, 3], symmetric=False)
    assert list(two.inputs) == ["u", "lower", "upper"]
    assert np.array_equal(two.output(0.0, None, (u, lower, upper))[0],
                          np.clip(u, lower, upper))
