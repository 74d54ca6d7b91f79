"""fwdstep animate: the page is self-contained, what it embeds is the logged motion (against
pinocchio's forward kinematics and the two-link arm's geometry written out by hand), and a
real browser (headless chromium) draws the logged q at the slider's time."""
import base64
import json
import math
import os
import re
import shutil
import signal
import subprocess

import numpy as np
import pytest

import fwdstep
from fwdstep.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")

PANDA_DIAGRAM = """
description: the Panda falling from its ready pose under gravity (no torque), q_d held
parameters:
  q0: [0, -0.785, 0, -2.356, 0, 1.571, 0.785]
blocks:
  arm:  {type: URDFArm, robot: panda, q0: q0, damping: 2}
  zero: {type: Constant, value: [0, 0, 0, 0, 0, 0, 0]}
  qd:   {type: Constant, value: q0}
  e:    {type: Sum, signs: "+-"}
connections:
  - zero.y -> arm.tau
  - arm.q -> e.u1
  - qd.y -> e.u2
simulation: {t_final: 1.0, step: 0.002, solver: rk4, log_every: 4}
log: [arm.q, e.y]
metrics: {error: e.y}
"""


def page_data(page: str) -> dict:
    """The JSON the page embeds, its arrays decoded (written here, not fwdstep's reader)."""
    m = re.search(r'<script type="application/json" id="fwdstep-data">(.*?)</script>', page,
                  re.S)
    data = json.loads(m.group(1).replace("<\\/", "</"))

    def decode(obj):
        if isinstance(obj, dict) and set(obj) == {"dtype", "shape", "b64"}:
            dtype = {"f8": "<f8", "f4": "<f4", "u4": "<u4"}[obj["dtype"]]
            return np.frombuffer(base64.b64decode(obj["b64"]), dtype).reshape(obj["shape"])
        if isinstance(obj, dict):
            return {k: decode(v) for k, v in obj.items()}
        if isinstance(obj, list):
            return [decode(v) for v in obj]
        return obj
    return decode(data)


@pytest.fixture(scope="module")
def two_link_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("t1") / "run"
    assert main(["run", THEOREM1, "-o", str(out), "--no-plots", "-q",
                 "--set", "t_final=2"]) == 0
    return str(out)


@pytest.fixture(scope="module")
def panda_run(tmp_path_factory):
    pytest.importorskip("pinocchio", reason="URDF arms need pinocchio (fwdstep[robots])")
    folder = tmp_path_factory.mktemp("panda")
    path = folder / "panda_fall.yaml"
    path.write_text(PANDA_DIAGRAM)
    out = folder / "run"
    assert main(["run", str(path), "-o", str(out), "--no-plots", "-q"]) == 0
    return str(out)


@pytest.fixture(scope="module")
def two_link_page(two_link_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("pages") / "t1.html"
    assert main(["animate", two_link_run, "-o", str(out)]) == 0
    return str(out)


@pytest.fixture(scope="module")
def panda_page(panda_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("pages") / "panda.html"
    assert main(["animate", panda_run, "-o", str(out)]) == 0
    return str(out)


def _read(path):
    with open(path, encoding="utf-8") as fh:
        return fh.read()


# ------------------------------------------------------------------------------ the page
@pytest.mark.parametrize("which", ["two_link_page", "panda_page"])
def test_page_is_self_contained(which, request):
    page = _read(request.getfixturevalue(which))
    tags = re.findall(r"<(?:script|link|img|iframe)\b[^>]*>", page)
    assert not [t for t in tags if re.search(r"\b(?:src|href)\s*=", t)], tags
    assert not re.search(r"""(?:src|href)\s*=\s*["']?(?:https?:)?//""", page)
    for block in re.findall(r'<script type="importmap">(.*?)</script>', page, re.S):
        for url in json.loads(block)["imports"].values():
            assert url.startswith("data:text/javascript;base64,")
    assert "@import" not in page and "url(http" not in page


def test_panda_poses_are_pinocchio_fk_of_the_logged_q(panda_run, panda_page):
    pin = pytest.importorskip("pinocchio")
    from importlib import metadata
    r = fwdstep.load_result(panda_run)
    run = page_data(_read(panda_page))["runs"][0]
    robots = metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")
    urdf = str(robots / "panda_description/urdf/panda.urdf")
    full = pin.buildModelFromUrdf(urdf)
    geom = pin.buildGeomFromUrdf(full, urdf, pin.GeometryType.VISUAL,
                                 package_dirs=[str(robots.parent.parent)])
    locked = [full.getJointId(j) for j in ("panda_finger_joint1", "panda_finger_joint2")]
    model, geom = pin.buildReducedModel(full, geom, locked, pin.neutral(full))
    data = model.createData()
    tcp = model.getFrameId("panda_hand_tcp")
    t, q = r.t, r["arm.q"]
    frames = run["t"]
    assert np.all(np.isin(frames, t))                   # frames are logged samples
    assert len(frames) == pytest.approx(31, abs=1)       # 1 s at 30 frames per second
    assert run["poses"].shape == (len(frames), geom.ngeoms, 12)
    for k in (0, len(frames) // 3, len(frames) - 1):
        i = int(np.flatnonzero(t == frames[k])[0])
        assert np.array_equal(run["q"][k], q[i])
        pin.forwardKinematics(model, data, q[i])
        pin.updateFramePlacements(model, data)
        for g, go in enumerate(geom.geometryObjects):
            M = (data.oMi[go.parentJoint] * go.placement).homogeneous
            assert np.allclose(run["poses"][k, g].reshape(3, 4), M[:3], atol=1e-9, rtol=0)
        assert np.allclose(run["ee"][k], data.oMf[tcp].translation, atol=1e-9, rtol=0)
        # the ghost is the held q_d = q0
        pin.forwardKinematics(model, data, np.array(
            [0, -0.785, 0, -2.356, 0, 1.571, 0.785]))
        M = (data.oMi[7] * geom.geometryObjects[7].placement).homogeneous
        assert np.allclose(run["ghost"][k, 7].reshape(3, 4), M[:3], atol=1e-9, rtol=0)
    assert not np.allclose(run["poses"][0], run["poses"][-1])    # it fell
    meshes = page_data(_read(panda_page))["meshes"]
    used = {g["mesh"] for g in run["geoms"]}
    assert len(meshes) == len(used) == 10          # the two fingers share one mesh
    assert os.path.getsize(panda_page) < 8e6


def test_two_link_points_are_the_arm_geometry(two_link_run, two_link_page):
    r = fwdstep.load_result(two_link_run)
    run = page_data(_read(two_link_page))["runs"][0]
    l1, lce, de = 1.0, 0.6, math.radians(30.0)     # Slotine & Li, TwoLinkArm's defaults
    for k in range(0, len(run["t"]), 7):
        i = int(np.flatnonzero(r.t == run["t"][k])[0])
        q1, q2 = r["arm.q"][i]
        assert np.array_equal(run["q"][k], r["arm.q"][i])
        elbow = [l1 * math.cos(q1), l1 * math.sin(q1)]
        tip = [elbow[0] + lce * math.cos(q1 + q2 - de), elbow[1] + lce * math.sin(q1 + q2 - de)]
        assert np.allclose(run["points"][k], [[0, 0], elbow, tip], atol=1e-12, rtol=0)
        qd1, qd2 = r["qd.y"][i]
        assert np.allclose(run["ghost"][k][1], [l1 * math.cos(qd1), l1 * math.sin(qd1)],
                           atol=1e-12, rtol=0)
    grid = np.arange(len(run["t"])) / 30           # each frame: the sample nearest k/30 s
    assert np.allclose(run["t"], grid, atol=0.005 + 1e-12, rtol=0)   # log every 0.01 s


def test_two_runs_overlay_in_distinct_colours(two_link_run, tmp_path):
    other = tmp_path / "slower"
    assert main(["run", THEOREM1, "-o", str(other), "--no-plots", "-q", "--set", "t_final=2",
                 "--set", "alpha=2"]) == 0
    out = tmp_path / "both.html"
    assert main(["animate", two_link_run, str(other), "-o", str(out)]) == 0
    runs = page_data(_read(out))["runs"]
    assert [r["label"] for r in runs] == ["run (theorem1)", "slower (theorem1)"]
    assert runs[0]["color"] != runs[1]["color"]
    assert not np.allclose(runs[0]["q"][10], runs[1]["q"][10])


def test_q_not_logged_is_one_line_exit_2(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", THEOREM1, "-o", str(out), "--no-plots", "-q", "--set",
                 "t_final=0.1", "--set", "log=[e.y]"]) == 0
    capsys.readouterr()
    assert main(["animate", str(out), "-o", str(tmp_path / "a.html")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "arm.q" in err and "log" in err
    assert not (tmp_path / "a.html").exists()


def test_default_output_and_foreign_files(two_link_run, tmp_path, capsys):
    assert main(["animate", two_link_run]) == 0
    assert os.path.isfile(os.path.join(two_link_run, "animation.html"))
    with open(os.path.join(two_link_run, "manifest.json")) as fh:
        assert "animation.html" in json.load(fh)["files"]      # owned like the run's files
    foreign = tmp_path / "notes.html"
    foreign.write_text("mine")
    capsys.readouterr()
    assert main(["animate", two_link_run, "-o", str(foreign)]) == 2
    assert "refusing" in capsys.readouterr().err and foreign.read_text() == "mine"


def test_result_animate_and_report(two_link_run):
    d = fwdstep.load_diagram(THEOREM1, {"t_final": 0.5})
    page = fwdstep.simulate(d).animate()
    assert isinstance(page, str) and page.startswith("<!DOCTYPE html>")
    assert "<iframe" in page._repr_html_()
    assert page_data(page)["runs"][0]["plant"] == "arm (TwoLinkArm)"
    from fwdstep.views.report import report_html
    report = report_html(two_link_run)
    assert "<h2>Animation</h2>" in report and 'class="fw-animation"' in report


# ------------------------------------------------------------------------------ in a browser
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="headless chromium is not "
                                    "installed (apt-get install chromium)")


def _chromium(tmp_path, url: str, *what: str) -> str:
    profile = tmp_path / f"profile{len(list(tmp_path.iterdir()))}"
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", "--hide-scrollbars", "--window-size=1100,900",
            "--virtual-time-budget=3000", *what, url]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            start_new_session=True)      # its own group: ended whole
    try:
        return proc.communicate(timeout=60)[0]
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return ""


def _state(tmp_path, page: str, t: float) -> dict:
    dom = _chromium(tmp_path, f"file://{page}#t={t}", "--dump-dom")
    if 'data-ready="1"' not in dom:                     # a busy machine: once more
        dom = _chromium(tmp_path, f"file://{page}#t={t}", "--dump-dom")
    body = re.search(r"<body([^>]*)>", dom).group(1)
    attrs = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body))
    return {k: json.loads(v.replace("&quot;", '"')) for k, v in attrs.items()}


def _screenshot(tmp_path, page: str, t: float) -> np.ndarray:
    from matplotlib.image import imread
    png = tmp_path / f"shot-{t}.png"
    for _ in range(2):                                  # a busy machine: once more
        _chromium(tmp_path, f"file://{page}#t={t}", f"--screenshot={png}")
        if png.exists():
            break
    return imread(str(png))


@needs_chromium
def test_browser_draws_the_logged_two_link_q(two_link_run, two_link_page, tmp_path):
    r = fwdstep.load_result(two_link_run)
    a, b = _screenshot(tmp_path, two_link_page, 0.3), _screenshot(tmp_path, two_link_page, 1.5)
    assert a.shape == b.shape and np.mean(np.any(a != b, axis=2)) > 0.001
    for t in (0.3, 1.5):
        s = _state(tmp_path, two_link_page, t)
        assert s["ready"] == 1 and s["playing"] == 0 and s["t"] == t
        i = int(np.flatnonzero(r.t <= t + 1e-12)[-1])     # the latest logged sample <= t
        assert s["frame-times"][0] == r.t[i]
        assert s["q"][0] == list(r["arm.q"][i])            # exactly the logged numbers
        q1, q2 = r["arm.q"][i]
        elbow = [math.cos(q1), math.sin(q1)]
        assert np.allclose(s["points"][1], elbow, atol=1e-12)


@needs_chromium
def test_browser_draws_the_logged_panda_pose(panda_run, panda_page, tmp_path):
    pin = pytest.importorskip("pinocchio")
    r = fwdstep.load_result(panda_run)
    a, b = _screenshot(tmp_path, panda_page, 0.0), _screenshot(tmp_path, panda_page, 0.9)
    view = (slice(80, 500), slice(50, 1050))               # the 3-D view: the arm moved
    assert np.mean(np.any(a[view] != b[view], axis=2)) > 0.002
    s = _state(tmp_path, panda_page, 0.9)
    assert "error" not in s and s["ready"] == 1
    i = int(np.flatnonzero(r.t <= 0.9 + 1e-12)[-1])
    assert s["q"][0] == list(r["arm.q"][i])
    from importlib import metadata
    robots = metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")
    full = pin.buildModelFromUrdf(str(robots / "panda_description/urdf/panda.urdf"))
    locked = [full.getJointId(j) for j in ("panda_finger_joint1", "panda_finger_joint2")]
    model = pin.buildReducedModel(full, locked, pin.neutral(full))
    data = model.createData()
    pin.framesForwardKinematics(model, data, r["arm.q"][i])
    assert np.allclose(s["ee"], data.oMf[model.getFrameId("panda_hand_tcp")].translation,
                       atol=1e-9, rtol=0)
    assert 0 < s["ee-screen"][0] < 1100 and 0 < s["ee-screen"][1] < 460
    assert s["ready-ms"] < 2000, "the page took more than 2 s to open"
