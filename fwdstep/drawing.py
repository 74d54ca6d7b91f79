"""A diagram as a picture: blocks as boxes with named ports, signals as arrows labelled with
their shapes, feedback drawn as feedback, subsystems as nested labelled frames.

Two layout engines:
  * graphviz ``dot`` (Debian package ``graphviz``) when it is on PATH: ``diagram_dot`` writes
    the DOT source, ``dot`` lays it out and renders SVG/PNG/PDF;
  * otherwise a layered layout computed here with networkx and drawn with matplotlib
    (``draw_layered``), so a plain ``pip install`` still draws.

Feedback: an edge is feedback when it goes against the forward order of the diagram
(a depth-first search from the sources; ``feedback_edges``).  It is drawn dashed in red and
does not constrain the layout, so the forward path reads left to right.  Each block shows
the equation number written in the YAML comment of its line (``# eq. (4)``, ``# (117)``).
"""
from __future__ import annotations

import html
import os
import re
import shutil
import subprocess
from dataclasses import dataclass, field

import networkx as nx

from .errors import OutputError

FORMATS = ("svg", "png", "pdf")
FEEDBACK_COLOR = "#c0392b"
TAG_COLOR = "#1a5276"
_EQ = re.compile(r"(?<![\w'])\((?:[1-9]\d*[a-z]?|[a-z]\d+)\)")


@dataclass
class Box:
    """One drawn block (or a collapsed subsystem)."""
    key: str                      # node id: full flattened name or the collapsed prefix
    title: str                    # name shown
    kind: str                     # block type, or "subsystem"
    inputs: list                  # port names, in order
    outputs: list
    equation: str = ""            # "(4)" / "(117), (119)"
    frame: tuple = ()             # enclosing subsystem prefixes, outermost first


@dataclass
class Picture:
    """Boxes, edges (src box, out port, dst box, in port, shape text, feedback) and frames."""
    boxes: dict
    edges: list
    frames: dict = field(default_factory=dict)     # prefix -> label
    title: str = ""


# ---------------------------------------------------------------------------- model
def equation_of(entry) -> str:
    """Equation numbers written in the comment of the block's YAML line, e.g. '(4)'; else those
    of the nearest comment line heading its group of blocks (``# (120)`` above a few blocks)."""
    try:
        with open(entry.file, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
        text = lines[entry.line - 1]
    except (OSError, IndexError, TypeError):
        return ""
    found = _EQ.findall(_comment(text))
    indent = len(text) - len(text.lstrip())
    k = entry.line - 2
    while not found and k >= 0 and indent > 0:
        line = lines[k]
        stripped = line.lstrip()
        if stripped and len(line) - len(stripped) < indent:
            break                                   # left the blocks: section
        if stripped.startswith("#") and len(line) - len(stripped) == indent:
            found = _EQ.findall(stripped[:60])       # the heading's leading equation numbers
            if found:
                break
        k -= 1
    return ", ".join(dict.fromkeys(found))


def _comment(line: str) -> str:
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[i + 1:]
    return ""


def shape_text(shape: tuple) -> str:
    return "1" if not shape else "×".join(str(s) for s in shape)


def build_picture(diagram, depth: int | None = None, tags: bool = False) -> Picture:
    """The picture of a CompiledDiagram; subsystems deeper than ``depth`` are one box;
    ``tags``: widely fed-back signals as named tags (``with_tags``)."""
    spec = diagram.spec
    blocks = {b.name: b for b in diagram.blocks}
    entries = {e.name: e for e in spec.blocks}

    def owner(name: str) -> str:
        parts = name.split("/")
        if depth is not None and len(parts) - 1 > depth:
            return "/".join(parts[:depth + 1])
        return name

    boxes, frames = {}, {}
    sub_files = {}
    for name, blk in blocks.items():
        parts = name.split("/")
        for k in range(1, len(parts)):
            prefix = "/".join(parts[:k])
            sub_files.setdefault(prefix, entries[name].file if k == len(parts) - 1 else None)
        key = owner(name)
        if key != name:
            continue
        entry = entries.get(name)
        boxes[name] = Box(name, parts[-1], entry.type_name if entry else type(blk).__name__,
                          list(blk.inputs), list(blk.outputs),
                          equation_of(entry) if entry else "", tuple(
                              "/".join(parts[:k]) for k in range(1, len(parts))))
    # frames, and collapsed subsystems with their own port names
    for prefix, file in sub_files.items():
        label = prefix.split("/")[-1] + (f"  ({os.path.relpath(file)})" if file else "")
        if owner(prefix + "/x") == prefix + "/x":
            frames[prefix] = label
    collapsed_in, collapsed_out = {}, {}
    for (blk, port), (alias, _f, _l) in spec.input_ports.items():
        if owner(blk) != blk:
            collapsed_in.setdefault(owner(blk), {})[(blk, port)] = alias.rsplit(".", 1)[1]
    for alias, real in spec.aliases.items():
        blk, port = real.rsplit(".", 1)
        if owner(blk) != blk and alias.rsplit(".", 1)[0] == owner(blk):
            collapsed_out.setdefault(owner(blk), {})[(blk, port)] = alias.rsplit(".", 1)[1]
    for key in {owner(n) for n in blocks if owner(n) != n}:
        parts = key.split("/")
        ins = list(dict.fromkeys(collapsed_in.get(key, {}).values()))
        outs = list(dict.fromkeys(collapsed_out.get(key, {}).values()))
        file = sub_files.get(key)
        boxes[key] = Box(key, parts[-1], "subsystem" + (f" {os.path.basename(file)}"
                                                        if file else ""), ins, outs, "",
                         tuple("/".join(parts[:k]) for k in range(1, len(parts))))
    edges, seen = [], set()
    for conn in spec.connections:
        (sb, sp), (db, dp) = conn.src, conn.dst
        so, do = owner(sb), owner(db)
        if so == do and so not in blocks:           # inside a collapsed subsystem
            continue
        if so != sb:
            sp = collapsed_out.get(so, {}).get((sb, sp), sp)
        if do != db:
            dp = collapsed_in.get(do, {}).get((db, dp), dp)
        shape = blocks[sb].outputs[sp if so == sb else conn.src[1]].shape
        key = (so, sp, do, dp)
        if key not in seen:
            seen.add(key)
            known = not ({sb, db} & getattr(diagram, "open_shapes", set()))
            edges.append([so, sp, do, dp, shape_text(shape) if known else "", False])
    back = feedback_edges(list(boxes), [(e[0], e[2]) for e in edges])
    for e in edges:
        e[5] = (e[0], e[2]) in back
    from .plotting import headline
    picture = Picture(boxes, [tuple(e) for e in edges], frames, headline(spec.description, 140))
    return with_tags(picture, spec.aliases) if tags else picture


#: a signal feeding this many blocks or more is drawn with tags (see ``with_tags``) ...
TAG_FANOUT = 3
#: ... in a picture with more boxes than this (Theorems 6-9); smaller ones keep every wire
TAG_BOXES = 30


def with_tags(picture: Picture, aliases: dict | None = None, fanout: int = TAG_FANOUT):
    """The wires of a widely used signal as named tags (Simulink's Goto/From): a signal
    feeding ``fanout`` or more blocks (the plant's q feeding every stage of the controller)
    goes into one tag "▶ plant.q" beside its source, and each block it feeds takes it from a
    tag "plant.q ▶" beside that block, drawn in the feedback colour where the wire was
    feedback.  The connections are the same, only their long routes become names."""
    by_source: dict = {}
    for e in picture.edges:
        by_source.setdefault((e[0], e[1]), []).append(e)
    named = {}
    for alias, real in (aliases or {}).items():
        if len(alias) < len(named.get(real, alias + "x")):
            named[real] = alias
    boxes, edges = dict(picture.boxes), []
    for (src, port), group in by_source.items():
        if len(group) < fanout:
            edges += group
            continue
        text = named.get(f"{src}.{port}", f"{picture.boxes[src].title}.{port}")
        goto = f"{src}.{port}:goto"
        boxes[goto] = Box(goto, text, "tag", [text], [], frame=picture.boxes[src].frame)
        edges.append((src, port, goto, text, group[0][4], False))
        for k, (_, _, dst, dp, shape, back) in enumerate(group):
            tag = f"{src}.{port}:from{k}"
            boxes[tag] = Box(tag, text, "tag" + (" back" if back else ""), [], [text],
                             frame=picture.boxes[dst].frame)
            edges.append((tag, text, dst, dp, shape, False))
    return Picture(boxes, edges, picture.frames, picture.title)


def feedback_edges(nodes: list, edges: list) -> set:
    """Edges that close a cycle in a depth-first search started from the sources (nodes with no
    incoming edge, in diagram order): the feedback paths of a block diagram."""
    g = nx.DiGraph()
    g.add_nodes_from(nodes)
    g.add_edges_from(edges)
    order = [n for n in nodes if g.in_degree(n) == 0] + nodes
    state, back = {}, set()
    for root in order:
        if root in state:
            continue
        stack = [(root, iter(g.successors(root)))]
        state[root] = "open"
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                state[node] = "done"
                stack.pop()
            elif state.get(nxt) == "open":
                back.add((node, nxt))
            elif nxt not in state:
                state[nxt] = "open"
                stack.append((nxt, iter(g.successors(nxt))))
    return back


# ---------------------------------------------------------------------------- graphviz
def _id(text: str) -> str:
    return "n_" + re.sub(r"[^A-Za-z0-9_]", "_", text)


def diagram_dot(picture: Picture) -> str:
    """DOT source: HTML-table boxes with input ports left, output ports right."""
    out = ["digraph fwdstep {",
           '  graph [rankdir=LR, splines=spline, nodesep=0.25, ranksep=0.55, fontname="Helvetica",'
           f' fontsize=13, labelloc=t, label="{_dot_escape(picture.title)}\\n"];',
           '  node [shape=plaintext, fontname="Helvetica", fontsize=10];',
           '  edge [fontname="Helvetica", fontsize=8, arrowsize=0.6, color="#34495e"];']
    children: dict = {}
    for key, box in picture.boxes.items():
        children.setdefault(box.frame[-1] if box.frame else "", []).append(("box", key))
    for prefix in picture.frames:
        parent = prefix.rsplit("/", 1)[0] if "/" in prefix else ""
        children.setdefault(parent, []).append(("frame", prefix))

    def emit(prefix: str, indent: str) -> None:
        for kind, key in children.get(prefix, []):
            if kind == "box":
                out.append(f"{indent}{_id(key)} [label=<{_box_html(picture.boxes[key])}>];")
            else:
                out.append(f"{indent}subgraph cluster_{_id(key)} {{")
                out.append(f'{indent}  label="{_dot_escape(picture.frames[key])}"; '
                           'style="rounded,filled"; fillcolor="#f4f6f7"; color="#7f8c8d"; '
                           "fontsize=11; labeljust=l;")
                emit(key, indent + "  ")
                out.append(f"{indent}}}")
    emit("", "  ")
    for src, sp, dst, dp, shape, back in picture.edges:
        attrs = [f'label="{shape}"']
        if back:
            attrs += [f'color="{FEEDBACK_COLOR}"', f'fontcolor="{FEEDBACK_COLOR}"',
                      "style=dashed"]
        out.append(f"  {_id(src)}:o_{_pid(sp)}:e -> {_id(dst)}:i_{_pid(dp)}:w "
                   f"[{', '.join(attrs)}];")
    out.append("}")
    return "\n".join(out) + "\n"


def _pid(port: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", port)


def _dot_escape(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"')


def _box_html(box: Box) -> str:
    e = html.escape
    if box.kind.startswith("tag"):         # a named wire end: "▶ q" (goto) or "q ▶" (from)
        port = (f'PORT="i_{_pid(box.inputs[0])}"' if box.inputs else
                f'PORT="o_{_pid(box.outputs[0])}"')
        text = f"▶ {e(box.title)}" if box.inputs else f"{e(box.title)} ▶"
        color = FEEDBACK_COLOR if box.kind == "tag back" else TAG_COLOR
        return (f'<TABLE BORDER="1" CELLBORDER="0" CELLSPACING="0" STYLE="ROUNDED" '
                f'COLOR="{color}"><TR><TD {port} CELLPADDING="2">'
                f'<FONT POINT-SIZE="9" COLOR="{color}">{text}</FONT></TD></TR></TABLE>')
    rows = max(len(box.inputs), len(box.outputs), 1)
    head = (f'<TD ROWSPAN="{rows}" BGCOLOR="#ffffff" CELLPADDING="4"><B>{e(box.title)}</B><BR/>'
            f'<FONT POINT-SIZE="8" COLOR="#555555">{e(box.kind)}</FONT>'
            + (f'<BR/><FONT POINT-SIZE="8" COLOR="#1a5276">eq. {e(box.equation)}</FONT>'
               if box.equation else "") + "</TD>")
    cells = []
    for r in range(rows):
        left = (f'<TD PORT="i_{_pid(box.inputs[r])}" ALIGN="LEFT" BGCOLOR="#eaf2f8">'
                f'<FONT POINT-SIZE="8">{e(box.inputs[r])}</FONT></TD>'
                if r < len(box.inputs) else ('<TD BORDER="0"></TD>' if box.inputs else ""))
        right = (f'<TD PORT="o_{_pid(box.outputs[r])}" ALIGN="RIGHT" BGCOLOR="#fdf2e9">'
                 f'<FONT POINT-SIZE="8">{e(box.outputs[r])}</FONT></TD>'
                 if r < len(box.outputs) else ('<TD BORDER="0"></TD>' if box.outputs else ""))
        cells.append(f"<TR>{left}{head if r == 0 else ''}{right}</TR>")
    return ('<TABLE BORDER="1" CELLBORDER="1" CELLSPACING="0" COLOR="#2c3e50">'
            + "".join(cells) + "</TABLE>")


def render_dot(source: str, fmt: str) -> bytes:
    exe = shutil.which("dot")
    if exe is None:
        raise OutputError("graphviz 'dot' is not on PATH (Debian/Ubuntu: apt install graphviz)")
    proc = subprocess.run([exe, f"-T{fmt}"], input=source.encode(), capture_output=True,
                          timeout=120)
    if proc.returncode != 0:
        raise OutputError(f"dot failed: {proc.stderr.decode(errors='replace').strip()[:300]}")
    return proc.stdout


# ---------------------------------------------------------------------------- fallback
def layered_positions(picture: Picture) -> dict:
    """Box -> (layer, row): longest-path layers of the diagram without its feedback edges,
    rows ordered by the barycentre of each box's predecessors (one sweep)."""
    g = nx.DiGraph()
    g.add_nodes_from(picture.boxes)
    g.add_edges_from((e[0], e[2]) for e in picture.edges if not e[5] and e[0] != e[2])
    if not nx.is_directed_acyclic_graph(g):         # a cycle the search did not break
        g.remove_edges_from(nx.find_cycle(g))
    layer = {}
    for n in nx.topological_sort(g):
        layer[n] = max((layer[p] + 1 for p in g.predecessors(n)), default=0)
    pos, rows = {}, {}
    for n in sorted(g, key=lambda n: layer[n]):
        preds = [pos[p][1] for p in g.predecessors(n) if p in pos]
        rows.setdefault(layer[n], []).append((sum(preds) / len(preds) if preds else 0.0, n))
    for lay, items in rows.items():
        for r, (_, n) in enumerate(sorted(items, key=lambda x: x[0])):
            pos[n] = (lay, float(r))
    return pos


def draw_layered(picture: Picture):
    """A matplotlib Figure (Agg canvas, no pyplot) of the picture in the layered layout."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch
    pos = layered_positions(picture)
    dx, dy = 3.2, 1.6
    n_layers = max(p[0] for p in pos.values()) + 1
    n_rows = max(p[1] for p in pos.values()) + 1
    back = [e for e in picture.edges if e[5]]
    sag = 0.15 * dx * max([abs(pos[e[0]][0] - pos[e[2]][0]) + 1 for e in back], default=0)
    fig = Figure(figsize=(max(6, 1.9 * n_layers), max(3, 1.0 * n_rows + 1 + sag / dy)))
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0, 0, 1, 0.94])
    ax.set_axis_off()
    centre = {k: (p[0] * dx, -p[1] * dy) for k, p in pos.items()}
    w, h = 2.2, 1.0
    for key, frame_label in picture.frames.items():        # frames behind their boxes
        members = [centre[k] for k, b in picture.boxes.items() if key in b.frame]
        if not members:
            continue
        xs, ys = [m[0] for m in members], [m[1] for m in members]
        depth = key.count("/")
        pad = 0.25 - 0.05 * depth
        ax.add_patch(FancyBboxPatch((min(xs) - w / 2 - pad, min(ys) - h / 2 - pad),
                                    max(xs) - min(xs) + w + 2 * pad,
                                    max(ys) - min(ys) + h + 2 * pad + 0.3,
                                    boxstyle="round,pad=0.05", fc="#f4f6f7", ec="#7f8c8d",
                                    lw=0.8, zorder=0))
        ax.text(min(xs) - w / 2 - pad + 0.05, max(ys) + h / 2 + pad + 0.25, frame_label,
                fontsize=6.5, va="top", color="#2c3e50", zorder=1)
    for key, box in picture.boxes.items():
        x, y = centre[key]
        ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.02",
                                    fc="white", ec="#2c3e50", lw=0.9, zorder=2))
        text = f"{box.title}\n{box.kind}" + (f"\neq. {box.equation}" if box.equation else "")
        ax.text(x, y, text, ha="center", va="center", fontsize=6.5, zorder=3)
        for side, ports in ((-1, box.inputs), (1, box.outputs)):
            for i, port in enumerate(ports):
                py = y + h / 2 - (i + 1) * h / (len(ports) + 1)
                ax.text(x + side * (w / 2 - 0.04), py, port, fontsize=4.5, zorder=3,
                        ha="left" if side < 0 else "right", va="center", color="#555555")
    for src, sp, dst, dp, shape, back in picture.edges:
        (x0, y0), (x1, y1) = centre[src], centre[dst]
        so, di = picture.boxes[src].outputs, picture.boxes[dst].inputs
        y0 += h / 2 - (so.index(sp) + 1) * h / (len(so) + 1) if sp in so else 0
        y1 += h / 2 - (di.index(dp) + 1) * h / (len(di) + 1) if dp in di else 0
        color = FEEDBACK_COLOR if back else "#34495e"
        arrow = FancyArrowPatch((x0 + w / 2, y0), (x1 - w / 2, y1), arrowstyle="-|>",
                                mutation_scale=7, lw=0.7, color=color, zorder=1,
                                linestyle="--" if back else "-",
                                connectionstyle="arc3,rad=-0.45" if back else "arc3,rad=0.0")
        ax.add_patch(arrow)
        ax.text((x0 + x1) / 2, (y0 + y1) / 2 + (0.35 if back else 0.08), shape, fontsize=5,
                color=color, ha="center", zorder=3)
    ax.set_xlim(-dx / 2 - 0.5, (n_layers - 1) * dx + dx / 2 + 0.5)
    ax.set_ylim(-(n_rows - 1) * dy - dy - sag, dy)
    fig.suptitle(picture.title, fontsize=9)
    return fig


# ---------------------------------------------------------------------------- entry points
def picture_for(diagram, depth: int | None = None, tags: str = "auto") -> Picture:
    """The picture ``draw_diagram`` draws: a subsystem file's ports as boxes, and tags on
    (``tags="on"``), off, or on for pictures of more than TAG_BOXES boxes (``"auto"``)."""
    picture = build_picture(diagram, depth)
    if isinstance(diagram, _Unwired):
        subsystem_ports(picture, diagram.spec.file, diagram)
    if tags not in ("auto", "on", "off"):
        raise OutputError(f"tags must be auto, on or off, not {tags!r}")
    if tags == "on" or (tags == "auto" and len(picture.boxes) > TAG_BOXES):
        picture = with_tags(picture, diagram.spec.aliases)
    return picture


def draw_diagram(diagram, path: str, depth: int | None = None, engine: str = "auto",
                 force: bool = False, tags: str = "auto") -> str:
    """Write the picture of ``diagram`` to ``path`` (.svg, .png or .pdf); the engine used.
    An existing file that fwdstep did not write is replaced only with ``force``.  ``tags``:
    "on" draws widely used signals as named tags (``with_tags``), "off" as wires, "auto"
    (default) tags them when the picture has more than TAG_BOXES boxes."""
    fmt = os.path.splitext(path)[1].lstrip(".").lower()
    if fmt not in FORMATS:
        raise OutputError(f"cannot draw to '{path}': the file name must end in "
                          f"{', '.join('.' + f for f in FORMATS)}")
    if os.path.isdir(path):
        raise OutputError(f"cannot write the picture to {path}: it is a directory")
    picture = picture_for(diagram, depth, tags)
    if engine == "auto":
        engine = "dot" if shutil.which("dot") else "matplotlib"
    if engine == "dot":
        data = render_dot(diagram_dot(picture), fmt)
    else:
        import io
        fig = draw_layered(picture)
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=200)
        data = buf.getvalue()
    _write(path, data, force)
    return engine


def _write(path: str, data: bytes, force: bool = False) -> None:
    """Put the picture in place as run outputs are (``fwdstep.outputs.OutputDir``: locked,
    staged, listed in the directory's manifest.json).  A picture fwdstep drew there before is
    replaced; any other file only with ``force``; a directory or a symbolic link never."""
    from .errors import printable
    from .outputs import MANIFEST_FILE, OutputDir, owned_files
    directory, name = os.path.split(os.path.abspath(path))
    if os.path.isdir(path) and not os.path.islink(path):
        raise OutputError(f"cannot write the picture to {path}: it is a directory")
    if name == MANIFEST_FILE:
        raise OutputError(f"cannot write the picture to {path}: fwdstep keeps its list of "
                          f"written files under that name; choose another -o")
    foreign = os.path.lexists(path) and name not in owned_files(directory)
    if foreign and (os.path.islink(path) or not os.path.isfile(path)):
        raise OutputError(f"refusing to replace {printable(path)}: it is "
                          f"{'a symbolic link' if os.path.islink(path) else 'not a file'}; "
                          "choose another file with -o")
    if foreign and not force:
        raise OutputError(f"refusing to replace {printable(path)}: fwdstep did not write it "
                          "(pass --force to replace it, or choose another file with -o)")
    manifest = os.path.join(directory, MANIFEST_FILE)
    if os.path.lexists(manifest) and not _fwdstep_manifest(manifest):
        raise OutputError(f"cannot write the picture into {printable(directory)}: its "
                          f"{MANIFEST_FILE} was not written by fwdstep and would be replaced; "
                          "choose another directory with -o")
    import json
    from .outputs import _describe
    from .result import atomic_write
    try:
        os.makedirs(directory, exist_ok=True)
        # the directory's lock (as a run holds it), then the picture and the manifest that
        # lists it, each replaced atomically; the user's directory itself is left in place
        with OutputDir.lock_only(directory, force=True):
            atomic_write(os.path.join(directory, name), lambda fh: fh.write(data),
                         binary=True)
            files = {}
            if os.path.lexists(manifest):
                with open(manifest, encoding="utf-8") as fh:
                    files = json.load(fh).get("files") or {}
            files[name] = _describe(os.path.join(directory, name))
            text = json.dumps({"written_by": "fwdstep", "files": files}, indent=2)
            atomic_write(manifest, lambda fh: fh.write(text))
    except (OSError, ValueError) as exc:
        raise OutputError(f"cannot write the picture to {path}: "
                          f"{getattr(exc, 'strerror', None) or exc}") from exc


def _fwdstep_manifest(path: str) -> bool:
    import json
    try:
        with open(path, encoding="utf-8") as fh:
            return json.loads(fh.read(1 << 20)).get("written_by") == "fwdstep"
    except (OSError, ValueError, AttributeError):
        return False


class _Unwired:
    """What ``build_picture`` needs of a diagram that does not compile on its own (a subsystem
    file of ``diagrams/lib``: its inputs are wired by the parent): spec and blocks."""

    def __init__(self, spec, blocks, open_shapes=()):
        self.spec, self.blocks, self.open_shapes = spec, blocks, set(open_shapes)

    def resolve(self, name: str) -> str:
        return self.spec.aliases.get(name, name)


def diagram_for_drawing(path: str, overrides: dict | None = None):
    """The compiled diagram; for a subsystem file (one with ``ports:``) that does not compile
    alone, its blocks and connections with its ports drawn as the frame's inputs/outputs."""
    from .compiler import load_diagram
    from .errors import DiagramError
    try:
        return load_diagram(path, overrides)
    except DiagramError:
        from .spec import load_spec
        from .yamlio import read_yaml_file
        doc = read_yaml_file(path)
        if not isinstance(doc, dict) or not doc.get("ports"):
            raise
        spec = load_spec(path, overrides)
        try:
            return _Unwired(spec, *_blocks_with_open_shapes(spec))
        except (DiagramError, ImportError) as exc:
            raise OutputError(f"{path} is a subsystem whose blocks take their shapes from the "
                              f"diagram that uses it ({exc.__class__.__name__}: "
                              f"{str(exc).split(': ', 1)[-1]}); draw a diagram that uses it"
                              ) from None


def _blocks_with_open_shapes(spec) -> tuple:
    """The blocks of a subsystem file drawn alone, and the names of those whose shapes only
    the parent diagram can fix.  Shapes the file fixes are inferred as for a run; a block
    whose shape stays open (a Product fed by the subsystem's inputs) is built with a
    stand-in shape, every size 2, so its port names can be drawn; the edges touching it are
    drawn without a shape, because the stand-in is not the diagram's."""
    import numpy as np
    from .errors import DiagramError
    from .graph import _instantiate_one
    blocks, open_ = [], set()                  # load_spec has inferred what the file fixes
    for entry in spec.blocks:
        inferred = set(getattr(entry.cls, "shape_from", {})) - set(entry.key_lines)
        if inferred:
            open_.add(entry.name)          # may hold a default or another block's stand-in
        try:
            blocks.append(_instantiate_one(entry))
            continue
        except DiagramError:
            if not inferred:
                raise
        example = getattr(entry.cls, "example", {}) or {}
        for param in inferred:             # every inferred shape: all sizes 2 compose
            rank = len(np.atleast_1d(example.get(param, [2])))
            entry.params[param] = np.full(rank, 2.0)
        blocks.append(_instantiate_one(entry))
    return blocks, open_


def subsystem_ports(picture: Picture, path: str, diagram) -> None:
    """Add the ``ports:`` of a subsystem file as two boxes, its inputs and its outputs."""
    from .yamlio import read_yaml_file
    ports = (read_yaml_file(path) or {}).get("ports") or {}
    ins, outs = ports.get("inputs") or {}, ports.get("outputs") or {}
    blocks = {b.name: b for b in diagram.blocks}
    if ins:
        picture.boxes["inputs"] = Box("inputs", "inputs", "subsystem ports", [], list(ins))
        for pname, targets in ins.items():
            for tgt in targets if isinstance(targets, list) else [targets]:
                blk, _, port = str(tgt).rpartition(".")
                if blk in blocks and port in blocks[blk].inputs:
                    shape = ("" if blk in getattr(diagram, "open_shapes", ()) else
                             shape_text(blocks[blk].inputs[port].shape))
                    picture.edges.append(("inputs", pname, blk, port, shape, False))
    if outs:
        picture.boxes["outputs"] = Box("outputs", "outputs", "subsystem ports", list(outs), [])
        for pname, src in outs.items():
            blk, _, port = str(src).rpartition(".")
            if blk in blocks and port in blocks[blk].outputs:
                shape = ("" if blk in getattr(diagram, "open_shapes", ()) else
                         shape_text(blocks[blk].outputs[port].shape))
                picture.edges.append((blk, port, "outputs", pname, shape, False))


def cmd_graph(path: str, output: str | None = None, sets=None, depth: int | None = None,
              engine: str = "auto", force: bool = False, tags: str = "auto") -> int:
    """``fwdstep graph DIAGRAM -o FILE.svg``: exit 0, or 2 with one line on stderr."""
    import sys
    from .errors import FwdstepError, one_line
    from .spec import parse_override
    try:
        overrides = dict(parse_override(s) for s in sets or [])
        diagram = diagram_for_drawing(path, overrides)
        output = output or os.path.join(
            "out", os.path.splitext(os.path.basename(path))[0], "diagram.svg")
        used = draw_diagram(diagram, output, depth, engine, force, tags)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return 2
    print(f"wrote {output} ({len(diagram.blocks)} blocks, layout: {used})")
    return 0
