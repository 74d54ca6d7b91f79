"""fwdstep graph: boxes, ports, shapes, feedback, frames, equation numbers; dot and fallback."""
import glob
import os
import shutil
import subprocess
import sys

import pytest

import fwdstep
from fwdstep.cli.arguments import main
from fwdstep.views.drawing import (build_picture, diagram_dot, draw_diagram, equation_of,
                             feedback_edges, layered_positions)

needs_dot = pytest.mark.skipif(shutil.which("dot") is None, reason="graphviz dot not installed")


def test_feedback_edges_are_the_edges_that_close_a_loop():
    nodes = ["ref", "s", "tau", "arm", "e", "qd"]
    edges = [("qd", "ref"), ("ref", "s"), ("s", "tau"), ("tau", "arm"), ("arm", "ref"),
             ("arm", "s"), ("arm", "e"), ("qd", "e")]
    assert feedback_edges(nodes, edges) == {("arm", "ref"), ("arm", "s")}


def test_theorem1_picture():
    d = fwdstep.load_diagram("diagrams/theorem1.yaml")
    pic = build_picture(d)
    assert set(pic.boxes) == {b.name for b in d.blocks}
    arm = pic.boxes["arm"]
    assert (arm.kind, arm.inputs, arm.outputs, arm.equation) == (
        "TwoLinkArm", ["tau", "tau_star"], ["q", "qdot"], "(1)")
    assert pic.boxes["Ks"].equation == "(4)" and pic.boxes["truth"].equation == ""
    edges = {(e[0], e[1], e[2], e[3]): (e[4], e[5]) for e in pic.edges}
    assert len(edges) == len(d.spec.connections)
    assert edges[("Y", "Y", "adapt", "W")] == ("2×4", False)
    assert edges[("qd", "y", "ref", "q_d")] == ("2", False)
    assert edges[("arm", "q", "ref", "q")] == ("2", True)          # the loop is closed here
    # with the feedback removed the rest is a forward (acyclic) flow, left to right
    pos = layered_positions(pic)
    for src, _, dst, _, _, back in pic.edges:
        if not back:
            assert pos[src][0] < pos[dst][0]


def test_equation_numbers_come_from_the_yaml_comments():
    d = fwdstep.load_diagram("diagrams/theorem9.yaml")
    eq = {e.name: equation_of(e) for e in d.spec.blocks}
    assert eq["chi1dd"] == "(117)"          # its own comment
    assert eq["kpsi"] == "(120)"            # the '# (120)' heading its group
    assert eq["plant/arm"] == "(1)"         # inside lib/plant.yaml
    assert eq["qd"] == ""                   # '# q_d' names no equation


def test_subsystems_are_frames_or_one_box_at_a_chosen_depth():
    d = fwdstep.load_diagram("diagrams/theorem9.yaml")
    full = build_picture(d)
    assert set(full.frames) == {"plant", "qds", "torque"}
    assert full.boxes["plant/arm"].frame == ("plant",)
    top = build_picture(d, depth=0)
    assert top.frames == {}
    plant = top.boxes["plant"]
    assert (plant.kind, sorted(plant.outputs)) == ("subsystem plant.yaml", ["Y", "q", "qdot"])
    assert {"tau", "tau_star", "z", "zdot"} <= set(plant.inputs)
    assert not any(k.startswith("plant/") for k in top.boxes)
    assert ("torque", "tau", "plant", "tau") in {e[:4] for e in top.edges}


def test_frames_name_their_file_as_the_diagram_does_from_any_directory(monkeypatch, tmp_path):
    path = os.path.abspath("diagrams/theorem9.yaml")
    monkeypatch.chdir(tmp_path)              # was shown as ../../work/main/diagrams/lib/...
    frames = build_picture(fwdstep.load_diagram(path)).frames
    assert frames["plant"] == "plant  (lib/plant.yaml)"
    assert frames["qds"] == "qds  (lib/qd_star.yaml)"


def test_a_sampled_subsystem_shows_its_period_on_its_frame_and_its_box(tmp_path):
    import pathlib
    text = pathlib.Path("diagrams/slotine_li_disturbed.yaml").read_text()
    written = "file: lib/torque_passive.yaml,"
    assert written in text
    path = tmp_path / "sampled.yaml"
    path.write_text(text.replace(written, written + " sample_period: 0.002, sample_offset: 5e-4,"))
    d = fwdstep.load_diagram(str(path))
    frames = build_picture(d).frames
    assert frames["tq"] == "tq  (lib/torque_passive.yaml)  ·  sampled, T = 0.002 s (offset 0.0005 s)"
    assert frames["plant"] == "plant  (lib/plant.yaml)"             # not sampled: no period
    assert "T = 0.002 s" in diagram_dot(build_picture(d))
    box = build_picture(d, depth=0).boxes["tq"]
    assert box.kind == "subsystem torque_passive.yaml, sampled, T = 0.002 s (offset 0.0005 s)"
    assert build_picture(d, depth=0).boxes["plant"].kind == "subsystem plant.yaml"


@needs_dot
def test_every_shipped_diagram_draws_with_dot(tmp_path):
    for path in sorted(glob.glob("diagrams/*.yaml")):
        pic = build_picture(fwdstep.load_diagram(path))
        source = diagram_dot(pic)
        proc = subprocess.run(["dot", "-Tsvg"], input=source.encode(), capture_output=True,
                              timeout=120)
        assert proc.returncode == 0, (path, proc.stderr[:300])
        svg = proc.stdout.decode()
        for box in pic.boxes.values():
            assert f">{box.title}<" in svg, (path, box.title)


@needs_dot
def test_graph_command_writes_svg_and_png(tmp_path, capsys):
    out = tmp_path / "t1.svg"
    assert main(["graph", "diagrams/theorem1.yaml", "-o", str(out)]) == 0
    svg = out.read_text()
    assert "eq. (4)" in svg and ">adapt<" in svg and "stroke-dasharray" in svg
    assert capsys.readouterr().out == f"wrote {out} (11 blocks, layout: dot)\n"
    assert main(["graph", "diagrams/theorem1.yaml", "-o", str(tmp_path / "t1.png")]) == 0
    assert (tmp_path / "t1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_matplotlib_fallback_draws_without_pyplot(tmp_path):
    code = ("import sys, fwdstep; from fwdstep.views.drawing import draw_diagram; "
            "d = fwdstep.load_diagram('diagrams/theorem1.yaml'); "
            f"print(draw_diagram(d, {str(tmp_path / 'f.png')!r}, engine='matplotlib'), "
            "'matplotlib.pyplot' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["matplotlib", "False"]
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_graph_errors_are_one_line(tmp_path, capsys):
    assert main(["graph", "diagrams/theorem1.yaml", "-o", str(tmp_path / "x.jpg")]) == 2
    err = capsys.readouterr().err
    assert err == (f"fwdstep: cannot draw to '{tmp_path / 'x.jpg'}': the file name must end in "
                   ".svg, .png, .pdf\n")
    assert main(["graph", str(tmp_path / "missing.yaml")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_draw_refuses_a_directory(tmp_path):
    d = fwdstep.load_diagram("diagrams/theorem2.yaml")
    (tmp_path / "pic.svg").mkdir()
    with pytest.raises(fwdstep.OutputError):
        draw_diagram(d, str(tmp_path / "pic.svg"), engine="matplotlib")


def test_a_subsystem_file_draws_with_its_ports_as_boxes(tmp_path):
    from fwdstep.views.drawing import diagram_for_drawing, subsystem_ports
    d = diagram_for_drawing("diagrams/lib/reference.yaml")       # does not compile alone
    pic = build_picture(d)
    subsystem_ports(pic, "diagrams/lib/reference.yaml", d)
    assert pic.boxes["inputs"].outputs == ["q", "qdot", "q_d", "qdot_d", "qddot_d"]
    assert pic.boxes["outputs"].inputs == ["z", "zdot", "s"]
    edges = {e[:4] for e in pic.edges}
    assert ("inputs", "q_d", "rd", "q_d") in edges and ("s", "y", "outputs", "s") in edges
    out = tmp_path / "ref.png"
    assert main(["graph", "diagrams/lib/reference.yaml", "-o", str(out),
                 "--engine", "matplotlib"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("name", ["qd_star", "torque_passive", "error_augmentation"])
def test_a_library_subsystem_with_open_shapes_draws_alone(tmp_path, capsys, name):
    """Its blocks take their shapes from the parent: drawn with their real port names, the
    file's ports as the inputs/outputs boxes, and no made-up shape on the open edges."""
    import yaml
    path = f"diagrams/lib/{name}.yaml"
    doc = yaml.safe_load(open(path))
    out = tmp_path / f"{name}.svg"
    assert main(["graph", path, "-o", str(out), "--engine", "matplotlib"]) == 0
    assert capsys.readouterr().out == (f"wrote {out} ({len(doc['blocks'])} blocks, "
                                       "layout: matplotlib)\n")
    from fwdstep.views.drawing import diagram_for_drawing, subsystem_ports
    d = diagram_for_drawing(path)
    pic = build_picture(d)
    subsystem_ports(pic, path, d)
    assert pic.boxes["inputs"].outputs == list(doc["ports"]["inputs"])
    assert pic.boxes["outputs"].inputs == list(doc["ports"]["outputs"])
    edges = {e[:4]: e[4] for e in pic.edges}
    for conn in doc["connections"]:                      # every connection, real port names
        (sb, sp), (db, dp) = (side.strip().rsplit(".", 1) for side in conn.split("->"))
        assert (sb, sp, db, dp) in edges, conn
    products = [b for b, spec in doc["blocks"].items() if spec["type"] == "Product"]
    assert products and all(pic.boxes[b].inputs == ["a", "b"] for b in products)
    assert all(e[4] == "" for e in pic.edges if e[0] in products or e[2] in products)


def test_graph_never_replaces_a_file_fwdstep_did_not_write(tmp_path, capsys):
    d = "diagrams/theorem2.yaml"
    pic = tmp_path / "pic.svg"
    args = ["graph", d, "--engine", "matplotlib", "-o"]
    assert main(args + [str(pic)]) == 0
    first = pic.read_bytes()
    assert main(args + [str(pic)]) == 0                  # its own picture: drawn again
    assert pic.read_bytes()[:5] == first[:5] == b"<?xml"
    user = tmp_path / "user.png"
    user.write_text("the user's figure")
    capsys.readouterr()
    assert main(args + [str(user)]) == 2
    assert capsys.readouterr().err == (f"fwdstep: refusing to replace {user}: fwdstep did not "
                                       "write it (pass --force to replace it, or choose "
                                       "another file with -o)\n")
    assert user.read_text() == "the user's figure"       # untouched
    assert main(args + [str(user), "--force"]) == 0
    assert user.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    link = tmp_path / "link.svg"
    link.symlink_to(pic)
    assert main(args + [str(link), "--force"]) == 2
    assert "it is a symbolic link" in capsys.readouterr().err
    other = tmp_path / "app"
    other.mkdir()
    (other / "manifest.json").write_text('{"name": "web app"}')
    assert main(args + [str(other / "x.svg")]) == 2
    assert capsys.readouterr().err.endswith("its manifest.json was not written by fwdstep and "
                                            "would be replaced; choose another directory "
                                            "with -o\n")
    assert (other / "manifest.json").read_text() == '{"name": "web app"}'
    assert not (other / "x.svg").exists()


def test_tags_replace_the_wires_of_widely_used_signals_and_keep_every_connection():
    from fwdstep.views.drawing import with_tags
    d = fwdstep.load_diagram("diagrams/theorem9.yaml")
    wired = build_picture(d)
    tagged = with_tags(wired, d.spec.aliases)
    fanout = {}
    for e in wired.edges:
        fanout[e[:2]] = fanout.get(e[:2], 0) + 1
    gotos = {k: b for k, b in tagged.boxes.items() if k.endswith(":goto")}
    assert {b.title for b in gotos.values()} >= {"plant.q", "plant.qdot", "plant.Y"}
    into = {(e[0], e[1]): e[2] for e in tagged.edges}
    direct = {e[:4] for e in tagged.edges}
    froms = {(tagged.boxes[e[0]].title, e[2], e[3]) for e in tagged.edges
             if tagged.boxes[e[0]].kind.startswith("tag")}
    for src, sp, dst, dp, _, back in wired.edges:       # every connection is still drawn
        if fanout[(src, sp)] < 3:
            assert (src, sp, dst, dp) in direct
        else:
            goto = tagged.boxes[into[(src, sp)]]
            assert (goto.title, dst, dp) in froms
            kind = next(tagged.boxes[e[0]].kind for e in tagged.edges
                        if e[2:4] == (dst, dp) and tagged.boxes[e[0]].title == goto.title)
            assert kind == ("tag back" if back else "tag")   # feedback keeps its colour
    # no block output feeds three or more blocks through wires any more
    wires = {}
    for e in tagged.edges:
        if not tagged.boxes[e[0]].kind.startswith("tag"):
            wires[e[:2]] = wires.get(e[:2], 0) + 1
    assert max(wires.values()) == 2


def test_small_diagrams_keep_their_wires_and_large_ones_get_tags():
    from fwdstep.views.drawing import picture_for
    small = fwdstep.load_diagram("diagrams/theorem1.yaml")
    large = fwdstep.load_diagram("diagrams/theorem6.yaml")
    def tags(d, mode):
        return sorted(b.title for k, b in picture_for(d, tags=mode).boxes.items()
                      if k.endswith(":goto"))
    assert tags(small, "auto") == [] and tags(small, "on") == ["arm.q", "arm.qdot"]
    assert tags(large, "auto") == tags(large, "on") != [] and tags(large, "off") == []


def test_the_fallback_layout_keeps_boxes_apart_and_collapses_subsystems(tmp_path, capsys,
                                                                         monkeypatch):
    """Theorem 9 without graphviz: subsystems drawn as boxes by default (said on stdout), no
    two boxes overlap, every forward wire runs left to right through the gaps between
    layers, and the text is drawn at a readable size."""
    import fwdstep.views.drawing
    from fwdstep.views.drawing import _box_size, _layout, draw_layered, picture_for
    drawn = []                                # the layout is checked below; skip rasterising
    monkeypatch.setattr(fwdstep.views.drawing, "layered_bytes",
                        lambda pic, fmt: drawn.append(pic) or b"\x89PNG\r\n\x1a\n")
    out = tmp_path / "t9.png"
    assert main(["graph", "diagrams/theorem9.yaml", "--engine", "matplotlib",
                 "-o", str(out)]) == 0
    assert capsys.readouterr().out == (f"wrote {out} (60 blocks, layout: matplotlib, "
                                       "subsystems as boxes: --depth 1 opens them)\n")
    d = fwdstep.load_diagram("diagrams/theorem9.yaml")
    pic = picture_for(d, depth=0)
    assert set(drawn[0].boxes) == set(pic.boxes)
    assert {"plant", "qds", "torque"} <= set(pic.boxes) and pic.frames == {}
    fig = draw_layered(pic)
    boxes = [p for p in fig.axes[0].patches if type(p).__name__ == "FancyBboxPatch"]
    rects = [(b.get_x(), b.get_y(), b.get_x() + b.get_width(), b.get_y() + b.get_height())
             for b in boxes]
    assert len(rects) == len(pic.boxes)
    for i, a in enumerate(rects):
        for b in rects[i + 1:]:
            assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1], (a, b)
    lay = _layout(pic)
    for k, e in enumerate(pic.edges):
        if not e[5]:
            path = [e[0], *lay.chains.get(k, []), e[2]]
            assert all(lay.layer[b] == lay.layer[a] + 1 for a, b in zip(path, path[1:]))
    sizes = [t.get_fontsize() for t in fig.axes[0].texts if t.get_text()]
    assert min(sizes) >= 4.5 and fig.get_size_inches()[0] < 40
    assert all(_box_size(b)[0] > 0.3 for b in pic.boxes.values())


def test_node_ids_are_one_per_block_and_frame(tmp_path):
    """A subsystem's block 'a/b' and a top-level block 'a_b' were one graphviz node (4 blocks
    reported, 3 drawn, their wires merged): the dot source must hold one node per block."""
    import re
    (tmp_path / "sub.yaml").write_text(
        "blocks:\n  b: {type: Gain, gain: 2.0}\n  c: {type: Gain, gain: 3.0}\n"
        "connections:\n  - b.y -> c.u\n"
        "ports:\n  inputs: {u: b.u}\n  outputs: {y: c.y}\n")
    (tmp_path / "top.yaml").write_text(
        "blocks:\n  src: {type: Constant, value: 1.0}\n  a: {type: subsystem, file: sub.yaml}\n"
        "  a_b: {type: Gain, gain: 5.0}\n"
        "connections:\n  - src.y -> a.u\n  - a.y -> a_b.u\n"
        "simulation: {t_final: 1, step: 0.1}\n")
    d = fwdstep.load_diagram(str(tmp_path / "top.yaml"))
    names = {b.name for b in d.blocks}
    assert names == {"src", "a/b", "a/c", "a_b"}
    source = diagram_dot(build_picture(d))
    nodes = re.findall(r"^\s*(n_\w+) \[label=<", source, flags=re.M)
    clusters = re.findall(r"subgraph (cluster_\w+) \{", source)
    assert len(nodes) == len(set(nodes)) == len(names)
    assert len(clusters) == 1
    edges = re.findall(r"^\s*(n_\w+):o_\w+:e -> (n_\w+):i_\w+:w", source, flags=re.M)
    assert len(set(edges)) == len(edges) == 3         # src -> a/b -> a/c -> a_b
