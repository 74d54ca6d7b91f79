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

from fwdstep.core.errors import OutputError

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


def _as_written(file: str, top: str) -> str:
    """A subsystem's file as the diagram names it (lib/qd_star.yaml), not as seen from the
    current directory; the folder and name when it lies outside the diagram's folder."""
    rel = os.path.relpath(file, os.path.dirname(os.path.abspath(top)))
    if rel.startswith(".."):
        rel = os.path.join(os.path.basename(os.path.dirname(file)), os.path.basename(file))
    return rel


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
        label = prefix.split("/")[-1] + (f"  ({_as_written(file, spec.file)})" if file else "")
        note = sampling_note(getattr(spec, "sampled", {}).get(prefix))
        label += f"  ·  {note}" if note else ""
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
        note = sampling_note(getattr(spec, "sampled", {}).get(key))
        boxes[key] = Box(key, parts[-1], "subsystem" + (f" {os.path.basename(file)}"
                                                        if file else "")
                         + (f", {note}" if note else ""), ins, outs, "",
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
    from fwdstep.results.plotting import headline
    picture = Picture(boxes, [tuple(e) for e in edges], frames, headline(spec.description, 140))
    return with_tags(picture, spec.aliases) if tags else picture


def sampling_note(sampled: dict | None) -> str:
    """'sampled, T = 0.01 s (offset 0.002 s)' for a sampled subsystem, else ''."""
    if not sampled:
        return ""
    offset = sampled.get("offset") or 0.0
    return (f"sampled, T = {sampled['period']:g} s"
            + (f" (offset {offset:g} s)" if offset else ""))


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
    """A DOT identifier for a block or frame name, one per name (injective): letters and
    digits stay, '_' becomes '__' and any other character '_x<hex>_', so the subsystem
    block 'a/b' (n_a_x2f_b) and the top-level block 'a_b' (n_a__b) stay two nodes."""
    return "n_" + _escape_id(text)


def _escape_id(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]", lambda m: "__" if m.group() == "_"
                  else f"_x{ord(m.group()):x}_", text)


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
    return _escape_id(port)


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
    each source moved right up to its first consumer (a tag or a constant sits beside the
    block it feeds); rows ordered by barycentre sweeps (see ``_layout``)."""
    lay = _layout(picture)
    return {k: (lay.layer[k], float(r)) for k, r in lay.row.items() if k in picture.boxes}


@dataclass
class _Layout:
    layer: dict          # node -> layer (boxes and the dummy points of long wires)
    row: dict            # node -> position in its layer
    chains: dict         # edge index -> [dummy nodes], for wires spanning several layers


def _layout(picture: Picture) -> _Layout:
    g = nx.DiGraph()
    g.add_nodes_from(picture.boxes)
    forward = [(k, e) for k, e in enumerate(picture.edges) if not e[5] and e[0] != e[2]]
    g.add_edges_from((e[0], e[2]) for _, e in forward)
    while not nx.is_directed_acyclic_graph(g):      # a cycle the search did not break
        g.remove_edges_from(nx.find_cycle(g))
    layer = {}
    for n in nx.topological_sort(g):
        layer[n] = max((layer[p] + 1 for p in g.predecessors(n)), default=0)
    for n in reversed(list(nx.topological_sort(g))):   # sources next to their consumers
        if g.in_degree(n) == 0 and g.out_degree(n) > 0:
            layer[n] = max(layer[n], min(layer[s] for s in g.successors(n)) - 1)
    # long wires get one dummy point per layer they cross, so they never cross a box
    chains, nodes_in = {}, {}
    adj_up: dict = {}
    for k, e in forward:
        if (e[0], e[2]) not in g.edges:
            continue
        chain, prev = [], e[0]
        for lay in range(layer[e[0]] + 1, layer[e[2]]):
            d = f"\0{k}:{lay}"
            layer[d] = lay
            chain.append(d)
            adj_up.setdefault(d, []).append(prev)
            prev = d
        adj_up.setdefault(e[2], []).append(prev)
        chains[k] = chain
    for n, lay in layer.items():
        nodes_in.setdefault(lay, []).append(n)
    adj_down: dict = {}
    for n, ups in adj_up.items():
        for u in ups:
            adj_down.setdefault(u, []).append(n)
    order = {lay: sorted(ns, key=lambda n: list(picture.boxes).index(n)
                         if n in picture.boxes else 0) for lay, ns in nodes_in.items()}
    frame_of = {n: (picture.boxes[n].frame[:1] if n in picture.boxes else ()) for n in layer}
    for sweep in range(8):                            # barycentre, down then up
        layers = sorted(order) if sweep % 2 == 0 else sorted(order, reverse=True)
        adj = adj_up if sweep % 2 == 0 else adj_down
        for lay in layers:
            pos = {n: i for ln in order.values() for i, n in enumerate(ln)}
            def bary(n, pos=pos, adj=adj):
                nb = [pos[m] for m in adj.get(n, []) if m in pos]
                return sum(nb) / len(nb) if nb else pos[n]
            bc = {n: bary(n) for n in order[lay]}
            group = {}                                # a subsystem's boxes stay together
            for n in order[lay]:
                group.setdefault(frame_of[n], []).append(bc[n])
            gmean = {f: sum(v) / len(v) for f, v in group.items()}
            order[lay].sort(key=lambda n: (gmean[frame_of[n]] if frame_of[n] else bc[n],
                                           frame_of[n], bc[n]))
    row = {n: i for ln in order.values() for i, n in enumerate(ln)}
    return _Layout(layer, row, chains)


_FONT = 7.0          # points, the box titles; ports and shapes are smaller
_CHAR = 0.0078       # inches per point of font size and character (DejaVu Sans average)


def _box_size(box: Box) -> tuple:
    if box.kind.startswith("tag"):
        return (0.3 + _CHAR * 6.5 * len(box.title), 0.22)
    title = max(len(box.title) * _FONT, len(box.kind) * 5.5, len(f"eq. {box.equation}") * 5.5)
    ports = 2 * max([len(p) for p in box.inputs + box.outputs] or [0]) * 5.0  # text centred
    rows = max(len(box.inputs), len(box.outputs), 3 if box.equation else 2)
    return (0.3 + _CHAR * (title + ports), 0.16 * rows + 0.12)


def draw_layered(picture: Picture):
    """A matplotlib Figure (Agg canvas, no pyplot) of the picture in a layered layout: the
    forward path left to right, long wires routed through the gaps between boxes, feedback
    wires (dashed red) along lanes under the diagram, subsystems as labelled frames."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import FancyBboxPatch, PathPatch
    from matplotlib.path import Path
    lay = _layout(picture)
    size = {k: _box_size(b) for k, b in picture.boxes.items()}
    n_layers = max(lay.layer.values()) + 1
    width = [max([size[n][0] for n in lay.layer if lay.layer[n] == i and n in size] + [0.3])
             for i in range(n_layers)]
    gap = 0.75
    x_of = [sum(width[:i]) + gap * i for i in range(n_layers)]
    # vertical positions: stacked in row order, then pulled towards their neighbours
    height = {n: size[n][1] if n in size else 0.06 for n in lay.layer}
    by_layer: dict = {}
    for n in sorted(lay.layer, key=lambda n: lay.row[n]):
        by_layer.setdefault(lay.layer[n], []).append(n)
    y = {}
    for ns in by_layer.values():
        top = 0.0
        for n in ns:
            y[n] = top + height[n] / 2
            top += height[n] + 0.22
    nbrs: dict = {}
    for k, e in enumerate(picture.edges):
        if e[5]:
            continue
        path = [e[0], *lay.chains.get(k, []), e[2]]
        for a, b in zip(path, path[1:]):
            nbrs.setdefault(a, []).append(b)
            nbrs.setdefault(b, []).append(a)
    for _ in range(12):
        for ns in by_layer.values():
            want = [sum(y[m] for m in nbrs[n]) / len(nbrs[n]) if nbrs.get(n) else y[n]
                    for n in ns]
            for i, n in enumerate(ns):               # keep the order, no overlaps
                lo = (y[ns[i - 1]] + (height[ns[i - 1]] + height[n]) / 2 + 0.22) if i else -1e9
                y[n] = max(want[i], lo)
            for i in range(len(ns) - 2, -1, -1):
                hi = y[ns[i + 1]] - (height[ns[i + 1]] + height[ns[i]]) / 2 - 0.22
                y[ns[i]] = min(y[ns[i]], hi)
    shift, end = 0.0, None                  # close empty horizontal bands (> 0.5 in)
    for n in sorted(y, key=lambda n: y[n] - height[n] / 2):
        top = y[n] - height[n] / 2
        if end is not None and top - end > 0.5:
            shift += top - end - 0.5
        end = max(end if end is not None else top, y[n] + height[n] / 2)
        y[n] -= shift
    y0 = min(y[n] - height[n] / 2 for n in y)
    y = {n: v - y0 for n, v in y.items()}
    bottom = max(y[n] + height[n] / 2 for n in y)
    cx = {n: x_of[lay.layer[n]] + width[lay.layer[n]] / 2 for n in lay.layer}

    def port_y(key: str, port: str, side: str) -> float:
        ports = picture.boxes[key].inputs if side == "in" else picture.boxes[key].outputs
        if port not in ports or len(ports) == 1 or picture.boxes[key].kind.startswith("tag"):
            return y[key]
        h = height[key] - 0.12
        return y[key] - h / 2 + (ports.index(port) + 0.5) * h / len(ports)

    back = [e for e in picture.edges if e[5]]
    lanes = 0.16 * len(back)
    fig_w = max(6.0, x_of[-1] + width[-1] + 0.6)
    import textwrap
    title = "\n".join(textwrap.wrap(" ".join(picture.title.split()),
                                    max(40, int((fig_w - 0.5) / (_CHAR * (_FONT + 2))))))
    pad_top = 0.45 + 0.18 * (title.count("\n") + 1)
    fig_h = bottom + lanes + pad_top + 0.5
    fig = Figure(figsize=(fig_w, max(3.0, fig_h)))
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_axis_off()
    ax.set_xlim(-0.3, fig_w - 0.3)
    ax.set_ylim(bottom + lanes + 0.35, -pad_top)            # y grows downwards, in inches
    for key, label in sorted(picture.frames.items(), key=lambda kv: kv[0].count("/")):
        members = [k for k, b in picture.boxes.items() if key in b.frame]
        if not members:
            continue
        depth = key.count("/")
        pad = 0.16 - 0.04 * depth
        x0 = min(cx[k] - size[k][0] / 2 for k in members) - pad
        x1 = max(cx[k] + size[k][0] / 2 for k in members) + pad
        t0 = min(y[k] - height[k] / 2 for k in members) - pad - 0.16
        t1 = max(y[k] + height[k] / 2 for k in members) + pad
        ax.add_patch(FancyBboxPatch((x0, t0), x1 - x0, t1 - t0, boxstyle="round,pad=0.02",
                                    fc="#f4f6f7", ec="#7f8c8d", lw=0.8, zorder=0, alpha=0.9))
        ax.text(x0 + 0.05, t0 + 0.03, label, fontsize=_FONT - 0.5, va="top", color="#2c3e50",
                zorder=1)
    for key, box in picture.boxes.items():
        w, h = size[key]
        x, yy = cx[key], y[key]
        if box.kind.startswith("tag"):
            color = FEEDBACK_COLOR if box.kind == "tag back" else TAG_COLOR
            ax.add_patch(FancyBboxPatch((x - w / 2, yy - h / 2), w, h,
                                        boxstyle="round,pad=0.0,rounding_size=0.08",
                                        fc="white", ec=color, lw=0.8, zorder=2))
            text = f"▶ {box.title}" if box.inputs else f"{box.title} ▶"
            ax.text(x, yy, text, ha="center", va="center", fontsize=_FONT - 0.5, color=color,
                    zorder=3)
            continue
        ax.add_patch(FancyBboxPatch((x - w / 2, yy - h / 2), w, h, boxstyle="square,pad=0",
                                    fc="white", ec="#2c3e50", lw=0.9, zorder=2))
        lines = [(box.title, _FONT, "bold", "#000000"), (box.kind, _FONT - 1.5, "normal",
                                                         "#555555")]
        if box.equation:
            lines.append((f"eq. {box.equation}", _FONT - 1.5, "normal", "#1a5276"))
        for i, (text, fs, weight, color) in enumerate(lines):
            ax.text(x, yy + (i - (len(lines) - 1) / 2) * 0.13, text, ha="center",
                    va="center", fontsize=fs, fontweight=weight, color=color, zorder=3)
        for side, ports in ((-1, box.inputs), (1, box.outputs)):
            for port in ports:
                py = port_y(key, port, "in" if side < 0 else "out")
                ax.text(x + side * (w / 2 - 0.04), py, port, fontsize=_FONT - 2, zorder=3,
                        ha="left" if side < 0 else "right", va="center", color="#34495e")

    def curve(points: list, color: str, dashed: bool = False, arrow: bool = True) -> None:
        verts, codes = [points[0]], [Path.MOVETO]
        for (xa, ya), (xb, yb) in zip(points, points[1:]):
            dx = (xb - xa) / 2
            verts += [(xa + dx, ya), (xb - dx, yb), (xb, yb)]
            codes += [Path.CURVE4] * 3
        ax.add_patch(PathPatch(Path(verts, codes), fc="none", ec=color, lw=0.7, zorder=1,
                               ls=(0, (3, 2)) if dashed else "-"))
        if arrow:
            xb, yb = points[-1]
            ax.annotate("", (xb, yb), (xb - 0.09, yb), zorder=2,
                        arrowprops=dict(arrowstyle="-|>", color=color, lw=0.7,
                                        mutation_scale=6, shrinkA=0, shrinkB=0))

    lane = bottom + 0.25
    for k, (src, sp, dst, dp, shape, is_back) in enumerate(picture.edges):
        start = (cx[src] + size[src][0] / 2, port_y(src, sp, "out"))
        end = (cx[dst] - size[dst][0] / 2, port_y(dst, dp, "in"))
        if is_back or src == dst:                   # out to the right, under, back in
            off = 0.04 * (k % 5)                    # verticals in the gaps between layers
            xr = x_of[lay.layer[src]] + width[lay.layer[src]] + 0.12 + off
            xl = x_of[lay.layer[dst]] - 0.12 - off
            pts = [start, (xr, start[1]), (xr, lane), (xl, lane), (xl, end[1]), end]
            verts = pts[:-1]
            ax.add_patch(PathPatch(Path(verts, [Path.MOVETO] + [Path.LINETO] * 4), fc="none",
                                   ec=FEEDBACK_COLOR, lw=0.7, ls=(0, (3, 2)), zorder=1))
            ax.annotate("", end, (xl, end[1]), zorder=2,
                        arrowprops=dict(arrowstyle="-|>", color=FEEDBACK_COLOR, lw=0.7,
                                        mutation_scale=6, shrinkA=0, shrinkB=0))
            ax.text((xl + xr) / 2, lane - 0.03, shape, fontsize=_FONT - 2.5,
                    color=FEEDBACK_COLOR, ha="center", zorder=3)
            lane += 0.16
            continue
        pts = [start] + [(cx[d], y[d]) for d in lay.chains.get(k, [])] + [end]
        curve(pts, "#34495e")
        if shape:
            ax.text(start[0] + 0.06, start[1] - 0.03, shape, fontsize=_FONT - 2.5,
                    color="#34495e", ha="left", va="bottom", zorder=3)
    ax.text(fig_w / 2 - 0.3, -pad_top + 0.12, title, ha="center", va="top",
            fontsize=_FONT + 2)
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
    The matplotlib fallback draws subsystems as boxes unless ``depth`` is given (its frames
    would overlap: it has no cluster layout).  An existing file that fwdstep did not write is replaced only with ``force``.  ``tags``:
    "on" draws widely used signals as named tags (``with_tags``), "off" as wires, "auto"
    (default) tags them when the picture has more than TAG_BOXES boxes."""
    fmt = os.path.splitext(path)[1].lstrip(".").lower()
    if fmt not in FORMATS:
        raise OutputError(f"cannot draw to '{path}': the file name must end in "
                          f"{', '.join('.' + f for f in FORMATS)}")
    if os.path.isdir(path):
        raise OutputError(f"cannot write the picture to {path}: it is a directory")
    if engine == "auto":
        engine = "dot" if shutil.which("dot") else "matplotlib"
    used = engine
    if engine == "matplotlib" and depth is None and any("/" in b.name for b in diagram.blocks):
        depth, used = 0, "matplotlib, subsystems as boxes: --depth 1 opens them"
    picture = picture_for(diagram, depth, tags)
    if engine == "dot":
        data = render_dot(diagram_dot(picture), fmt)
    else:
        data = layered_bytes(picture, fmt)
    _write(path, data, force)
    return used


def layered_bytes(picture: Picture, fmt: str) -> bytes:
    """The fallback drawing as ``fmt`` bytes; large pictures at a lower resolution."""
    import io
    fig = draw_layered(picture)
    buf = io.BytesIO()
    inches = max(fig.get_size_inches())
    fig.savefig(buf, format=fmt, dpi=200 if inches <= 20 else 150)
    return buf.getvalue()


def _write(path: str, data: bytes, force: bool = False) -> None:
    """Put the picture in place as run outputs are (``fwdstep.results.outputs.OutputDir``: locked,
    staged, listed in the directory's manifest.json).  A picture fwdstep drew there before is
    replaced; any other file only with ``force``; a directory or a symbolic link never."""
    from fwdstep.core.errors import printable
    from fwdstep.results.outputs import MANIFEST_FILE, OutputDir, foreign_manifest, owned_files
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
    if foreign_manifest(directory):
        raise OutputError(f"cannot write the picture into {printable(directory)}: its "
                          f"{MANIFEST_FILE} was not written by fwdstep and would be replaced; "
                          "choose another directory with -o")
    import json
    from fwdstep.results.outputs import _describe
    from fwdstep.core.files import atomic_write
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
    from fwdstep.structure.compiler import load_diagram
    from fwdstep.core.errors import DiagramError
    try:
        return load_diagram(path, overrides)
    except DiagramError:
        from fwdstep.structure.spec import load_spec
        from fwdstep.core.yamlio import read_yaml_file
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
    from fwdstep.core.errors import DiagramError
    from fwdstep.structure.graph import _instantiate_one
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
    from fwdstep.core.yamlio import read_yaml_file
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


