"""``fwdstep animate``: a run's robot replayed in one self-contained HTML page.

The page needs no network: the player (``assets/animate.js``, ``assets/animate.css``), three.js
for 3-D arms (``assets/three.module.min.js`` and ``OrbitControls.js``, MIT, vendored unmodified,
inlined as ``data:`` modules of an import map) and every mesh are inside it.

What is drawn is computed here, in Python, from the logged joint positions q of the plant block
(the block of a type in PLANT_TYPES; its ``q`` must be logged):

- URDF arms (``URDFArm``): the pose of every visual geometry (example-robot-data's meshes,
  loaded by pinocchio through coal/assimp, deduplicated and simplified by vertex clustering
  when large) from pinocchio's forward kinematics of q, 12 numbers per geometry and frame
  (the rows of [R p], float64, so they equal pinocchio's to the last bit);
- planar arms (``TwoLinkArm``, ``NLinkArm``) and point masses (``PointMass``): the joint
  points in the plane (two-link: the base, the elbow l1 E(q1) and the end-effector mass
  l1 E(q1) + lce E(q1 + q2 - delta_e), E(a) = (cos a, sin a); n-link: the partial sums of
  l_i E(q_1 + ... + q_i)).

Frames are the logged samples closest to a ``fps`` grid (decimated, never interpolated), so
the pose drawn at any slider time is the pose of a logged q.  The desired trajectory (found
through the error Sum q - q_d of the diagram) is drawn as a translucent ghost and as the
end-effector path; the time plots show the error signal of ``metrics: error:`` with a cursor
that follows the slider.  The page exposes what it draws: ``document.body.dataset`` holds the
time, the frame, q and the drawn points or end-effector position (tests read them through
headless chromium).
"""
from __future__ import annotations

import base64
import html
import json
import os
from importlib import resources

import numpy as np

from fwdstep.core.files import atomic_write

from fwdstep.core.errors import OutputError

PLANT_TYPES = ("URDFArm", "TwoLinkArm", "NLinkArm", "PointMass")
DISPLAY_FPS = 30
#: triangles kept per mesh (vertex clustering above this): the Panda's meshes (at most 21620)
#: pass whole; clustering shows at 6000 (facets, dark seams)
MAX_TRIANGLES = 25000
#: bytes of poses per run at most (a long URDF run keeps fewer frames): with three.js and the
#: Panda's meshes (3.3 MB in the page) a page stays under 20 MB
MAX_POSE_BYTES = 10_000_000
#: points per time-plot series (every k-th logged sample above this)
MAX_PLOT_POINTS = 1500
RUN_COLOURS = ("#1f6fb4", "#f07f0e", "#8e44ad", "#16a085")
ANIMATION_FILE = "animation.html"
_MARK = "<!-- written by fwdstep animate -->"


class NoRobot(OutputError):
    """The run's diagram has no plant block to draw (the report then shows no animation)."""


class Animation(str):
    """The page's HTML (a str); shown inline in a notebook (an iframe holding the page)."""

    def _repr_html_(self) -> str:
        return embed_html(self, height=720)

    def save(self, path: str) -> str:
        return write_page(self, path)


# ---------------------------------------------------------------------------- the runs
def _diagram_file(path, outdir: str):
    """The diagram file summary.json names (relative to where fwdstep run ran): as written,
    else under one of the run directory's parents; None when not found."""
    if not path:
        return None
    if os.path.isfile(path):
        return path
    if not os.path.isabs(path):
        folder = os.path.abspath(outdir)
        while os.path.dirname(folder) != folder:
            folder = os.path.dirname(folder)
            if os.path.isfile(os.path.join(folder, path)):
                return os.path.join(folder, path)
    return None


def find_plant(diagram, result, where: str = "the run"):
    """(plant block, name of its logged q signal).  The plant is the block of a type in
    PLANT_TYPES; OutputError (one line) when there is none or its q was not logged."""
    plants = [b for b in diagram.blocks if b.type_name in PLANT_TYPES]
    if not plants:
        raise NoRobot(f"{where}: no robot to animate: the diagram has no block of type "
                          f"{', '.join(PLANT_TYPES)}")
    for b in plants:
        if f"{b.name}.q" in result.names:
            return b, f"{b.name}.q"
    b = plants[0]
    raise OutputError(f"{where}: the plant {b.name!r} ({b.type_name}) has no logged q: add "
                      f"'{b.name}.q' to the diagram's log: list and run it again")


def desired_q(diagram, result, plant, q: np.ndarray):
    """q_d (T, n) or None: the other input of a two-input Sum that subtracts it from (or adds
    it, negated, to) the plant's q, read from the log directly, or as q - e from the Sum's
    logged output e."""
    drivers = diagram.structure.drivers
    for b in diagram.blocks:
        if b.type_name != "Sum" or len(b.inputs) != 2:
            continue
        signs = str(b.values.get("signs", "++"))
        ports = list(b.inputs)
        src = [drivers.get((b.name, p)) for p in ports]
        if len(signs) != 2 or signs[0] == signs[1] or (plant.name, "q") not in src:
            continue
        k = src.index((plant.name, "q"))
        other = src[1 - k]
        if other is None:
            continue
        name = f"{other[0]}.{other[1]}"
        if name in result.names and result[name].shape == q.shape:
            return np.asarray(result[name], dtype=float)
        out = f"{b.name}.{next(iter(b.outputs))}"
        if out in result.names and result[out].shape == q.shape:
            e = np.asarray(result[out], dtype=float)        # e = +-(q - q_d)
            return q - (e if signs[k] == "+" else -e)
    return None


def frame_indices(t: np.ndarray, fps: float = DISPLAY_FPS) -> np.ndarray:
    """Indices of the logged samples nearest to the times t0, t0 + 1/fps, ... (unique,
    increasing, the last sample always included); every sample when the log is sparser."""
    t = np.asarray(t, dtype=float)
    if len(t) == 0:
        return np.zeros(0, dtype=int)
    grid = np.arange(t[0], t[-1] + 0.5 / fps, 1.0 / fps)
    right = np.clip(np.searchsorted(t, grid), 1, max(len(t) - 1, 1))
    left = right - 1
    nearest = np.where(np.abs(t[left] - grid) <= np.abs(t[np.minimum(right, len(t) - 1)] - grid),
                       left, right)
    return np.unique(np.append(np.clip(nearest, 0, len(t) - 1), len(t) - 1))


# ---------------------------------------------------------------------------- planar arms
def planar_points(plant, q: np.ndarray) -> np.ndarray:
    """(T, P, 2) points drawn for a planar plant at each q (T, n): the joints and the tip of
    an arm, or the positions of point masses."""
    q = np.asarray(q, dtype=float)
    v = plant.values
    if plant.type_name == "TwoLinkArm":
        l1, lce, de = float(v["l1"]), float(v["lce"]), np.radians(float(v["delta_e"]))
        elbow = l1 * np.stack([np.cos(q[:, 0]), np.sin(q[:, 0])], axis=1)
        a = q[:, 0] + q[:, 1] - de
        tip = elbow + lce * np.stack([np.cos(a), np.sin(a)], axis=1)
        return np.stack([np.zeros_like(elbow), elbow, tip], axis=1)
    if plant.type_name == "NLinkArm":
        lengths = np.atleast_1d(np.asarray(v["lengths"], dtype=float))
        phi = np.cumsum(q, axis=1)
        steps = lengths * np.stack([np.cos(phi), np.sin(phi)], axis=2).transpose(2, 0, 1)
        joints = np.concatenate([np.zeros((2, len(q), 1)), np.cumsum(steps, axis=2)], axis=2)
        return joints.transpose(1, 2, 0)
    # PointMass: one point in the plane for n <= 2, else one point per axis on its own track
    n = q.shape[1]
    if n <= 2:
        xy = np.zeros((len(q), 1, 2))
        xy[:, 0, :n] = q
        return xy
    pts = np.zeros((len(q), n, 2))
    pts[:, :, 0] = q
    pts[:, :, 1] = -np.arange(n)
    return pts


def _planar_run(plant, q, qd, idx) -> dict:
    pts = planar_points(plant, q[idx])
    out = {"points": _pack(pts), "links": plant.type_name != "PointMass"}
    if qd is not None:
        out["ghost"] = _pack(planar_points(plant, qd[idx]))
    gravity = float(plant.values.get("gravity", 0.0) or 0.0)
    out["plane"] = ("point masses: axis 1 right, axis 2 up" if plant.type_name == "PointMass"
                    else "vertical plane, gravity down" if gravity else
                    "horizontal plane (seen from above)")
    return out


# ---------------------------------------------------------------------------- URDF arms
class URDFScene:
    """The visual geometries of a URDFArm's robot (reduced like the plant: locked joints at
    the neutral configuration) and their poses at given q."""

    def __init__(self, plant):
        import pinocchio as pin
        self.pin = pin
        path, locked, _ = plant.robot_description
        full = pin.buildModelFromUrdf(path)
        dirs = _package_dirs(path)
        try:
            geom = pin.buildGeomFromUrdf(full, path, pin.GeometryType.VISUAL, package_dirs=dirs)
        except (RuntimeError, ValueError) as exc:
            raise OutputError(f"cannot load the visual meshes of {path}: "
                              f"{one_line(str(exc))}") from exc
        ids = [full.getJointId(j) for j in locked]
        if ids:
            self.model, self.geom = pin.buildReducedModel(full, geom, ids, pin.neutral(full))
        else:
            self.model, self.geom = full, geom
        if self.model.nq != plant.model.nq:
            raise OutputError(f"the visual model of {path} has {self.model.nq} joints, the "
                              f"plant {plant.name!r} {plant.model.nq}")
        self.data = self.model.createData()
        self.gdata = pin.GeometryData(self.geom)
        self.ee_frame = _end_effector_frame(self.model)

    def meshes(self, store: "MeshStore") -> list:
        """Per geometry {"mesh": index in store, "color": [r, g, b, a]} (None: not drawable)."""
        out = []
        for go in self.geom.geometryObjects:
            key = (go.meshPath or go.name, tuple(np.round(go.meshScale, 9)))
            out.append({"mesh": store.add(key, lambda g=go: _triangles(g)),
                        "name": go.name, "color": [float(c) for c in go.meshColor]})
        return out

    def poses(self, q: np.ndarray) -> tuple:
        """(T, G, 12) rows of [R p] of every geometry, (T, 3) the end effector's position."""
        pin, model, data = self.pin, self.model, self.data
        G = self.geom.ngeoms
        out = np.empty((len(q), G, 12))
        ee = np.empty((len(q), 3))
        for k, qk in enumerate(np.asarray(q, dtype=float)):
            pin.forwardKinematics(model, data, qk)
            pin.updateGeometryPlacements(model, data, self.geom, self.gdata)
            for g in range(G):
                out[k, g] = self.gdata.oMg[g].homogeneous[:3, :4].reshape(12)
            pin.updateFramePlacement(model, data, self.ee_frame)
            ee[k] = data.oMf[self.ee_frame].translation
        return out, ee


def _package_dirs(urdf_path: str) -> list:
    dirs = [os.path.dirname(os.path.abspath(urdf_path))]
    from importlib import metadata
    try:
        dist = metadata.distribution("example-robot-data")
        dirs.append(str(dist.locate_file("cmeel.prefix/share")))
    except metadata.PackageNotFoundError:
        pass
    # package://NAME/... resolves under a parent of the URDF's folder
    parent = os.path.dirname(dirs[0])
    return dirs + [parent, os.path.dirname(parent)]


def _end_effector_frame(model) -> int:
    names = [f.name for f in model.frames]
    for name in ("panda_hand_tcp", "tool0", "ee_link", "panda_hand"):
        if name in names:
            return names.index(name)
    import pinocchio as pin
    bodies = [i for i, f in enumerate(model.frames) if f.type == pin.FrameType.BODY]
    return bodies[-1] if bodies else len(names) - 1


def _triangles(go):
    """(vertices (V, 3), triangles (F, 3)) of a geometry object, or None."""
    geo = go.geometry
    kind = type(geo).__name__
    if hasattr(geo, "tri_indices") and hasattr(geo, "num_tris"):
        V = np.asarray(geo.vertices(), dtype=float).reshape(-1, 3)
        F = np.array([[t[0], t[1], t[2]] for t in map(geo.tri_indices, range(geo.num_tris))],
                     dtype=np.int64).reshape(-1, 3)
        return V, F
    if kind == "Box":
        return _box(np.asarray(geo.halfSide, dtype=float))
    if kind == "Sphere":
        return _revolution(np.full(13, float(geo.radius)) * np.sin(np.linspace(0, np.pi, 13)),
                           -float(geo.radius) * np.cos(np.linspace(0, np.pi, 13)))
    if kind in ("Cylinder", "Capsule"):           # a capsule drawn as its cylinder
        r, h = float(geo.radius), float(geo.halfLength)
        return _revolution(np.array([0.0, r, r, 0.0]), np.array([-h, -h, h, h]))
    return None


def _box(half):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]
    return corners.astype(float), np.array(tris)


def _revolution(r: np.ndarray, z: np.ndarray, segments: int = 24):
    """A closed surface of revolution about z through the meridian points (r_i, z_i)."""
    a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    V = np.stack([np.outer(r, np.cos(a)), np.outer(r, np.sin(a)),
                  np.outer(z, np.ones_like(a))], axis=2).reshape(-1, 3)
    tris = []
    for i in range(len(r) - 1):
        for j in range(segments):
            p, q = i * segments + j, i * segments + (j + 1) % segments
            tris += [(p, q, q + segments), (p, q + segments, p + segments)]
    return V, np.array(tris)


def simplify(V: np.ndarray, F: np.ndarray, target: int | None = None) -> tuple:
    """Vertex clustering: vertices merged on a grid fine enough to keep at most ``target``
    (default MAX_TRIANGLES) triangles (coarsened step by step); degenerate and repeated
    triangles dropped."""
    target = MAX_TRIANGLES if target is None else target
    if len(F) <= target:
        return V, F
    lo = V.min(axis=0)
    size = float(np.linalg.norm(V.max(axis=0) - lo)) or 1.0
    cells = 256.0
    while True:
        h = size / cells
        key = np.floor((V - lo) / h).astype(np.int64)
        _, cluster, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.reshape(-1)
        W = np.zeros((len(counts), 3))
        np.add.at(W, cluster, V)
        W /= counts[:, None]
        G = cluster[F]
        keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 0] != G[:, 2])
        G = G[keep]
        _, first = np.unique(np.sort(G, axis=1), axis=0, return_index=True)
        G = G[np.sort(first)]
        if len(G) <= target or cells < 16:
            used, G = np.unique(G, return_inverse=True)
            return W[used], G.reshape(-1, 3)
        cells *= 0.8


class MeshStore:
    """Meshes shared by all geometries and runs of a page, each stored once."""

    def __init__(self):
        self.keys: dict = {}
        self.items: list = []

    def add(self, key, make):
        if key not in self.keys:
            tri = make()
            if tri is None:
                self.keys[key] = None
            else:
                V, F = simplify(*tri)
                self.keys[key] = len(self.items)
                self.items.append({"positions": _pack(V.astype(np.float32)),
                                   "index": _pack(F.astype(np.uint32)),
                                   "triangles": int(len(F))})
        return self.keys[key]


def _urdf_run(scene: URDFScene, plant, q, qd, idx, store: MeshStore) -> dict:
    poses, ee = scene.poses(q[idx])
    out = {"geoms": scene.meshes(store), "poses": _pack(poses), "ee": _pack(ee),
           "ee_frame": scene.model.frames[scene.ee_frame].name,
           "robot": os.path.basename(plant.robot_description[0])}
    if qd is not None:
        ghost, ee_d = scene.poses(qd[idx])
        out.update(ghost=_pack(ghost), ee_desired=_pack(ee_d))
    return out


# ---------------------------------------------------------------------------- one run's data
def run_data(result, diagram, label: str, fps: float = DISPLAY_FPS,
             store: MeshStore | None = None, where: str = "the run") -> dict:
    """Everything the page draws of one run (arrays packed as base64)."""
    if result.batch != 1:
        raise OutputError(f"{where}: a batch of {result.batch} variants; animate replays "
                          "single runs")
    plant, qname = find_plant(diagram, result, where)
    t = np.asarray(result.t, dtype=float)
    q = np.asarray(result[qname], dtype=float).reshape(len(t), -1)
    finite = np.all(np.isfinite(q), axis=1)
    if not finite.all():                     # a diverged run: up to its last finite pose
        stop = int(np.argmin(finite))
        t, q = t[:stop], q[:stop]
    if len(t) == 0:
        raise OutputError(f"{where}: no finite q was recorded")
    qd = desired_q(diagram, result, plant, q)
    if qd is not None:
        qd = qd[:len(t)]
        if not np.all(np.isfinite(qd)):
            qd = None
    idx = frame_indices(t, fps)
    scene = URDFScene(plant) if plant.type_name == "URDFArm" else None
    if scene is not None:            # 12 float64 per geometry and frame, twice with a ghost
        per_frame = 96 * scene.geom.ngeoms * (2 if qd is not None else 1)
        if len(idx) * per_frame > MAX_POSE_BYTES:          # a long run: fewer frames
            keep = np.linspace(0, len(idx) - 1, MAX_POSE_BYTES // per_frame).round()
            idx = idx[np.unique(keep.astype(int))]
    out = {"label": label, "plant": f"{plant.name} ({plant.type_name})", "q_signal": qname,
           "t": _pack(t[idx]), "q": _pack(q[idx]), "n": int(q.shape[1]),
           "desired": qd is not None, "status": getattr(result, "status", "ok")}
    if scene is not None:
        out["kind"] = "urdf"
        out.update(_urdf_run(scene, plant, q, qd, idx,
                             store if store is not None else MeshStore()))
    else:
        out["kind"] = "planar"
        out.update(_planar_run(plant, q, qd, idx))
    out["plot"] = _plot_data(result, diagram, len(t))
    return out


def _plot_data(result, diagram, stop: int):
    name = diagram.spec.metrics.get("error")
    if not name or name not in result:
        return None
    e = np.asarray(result[name], dtype=float)[:stop].reshape(stop, -1)
    t = np.asarray(result.t, dtype=float)[:stop]
    step = max(1, int(np.ceil(len(t) / MAX_PLOT_POINTS)))
    keep = np.unique(np.append(np.arange(0, len(t), step), len(t) - 1))
    labels = getattr(result, "signal_labels", None) or {}
    info = labels.get(diagram.resolve(name)) or labels.get(name) or {}
    if not info and result.diagram is not None:
        try:
            from .plotting import signal_info
            si = signal_info(result, name)
            info = {"label": si.label, "unit": si.unit,
                    "components": getattr(si, "components", None)}
        except Exception:  # noqa: BLE001 - labels are decoration
            info = {}
    comps = info.get("components")
    return {"name": name, "label": _plain_label(info.get("label") or name),
            "unit": info.get("unit") or "", "t": _pack(t[keep]), "e": _pack(e[keep]),
            "components": list(comps) if comps and len(comps) == e.shape[1] else None}


def _plain_label(label: str) -> str:
    """'$\\Delta q$' -> 'Δq': the plots' labels in plain text."""
    text = str(label).replace("$", "")
    for tex, plain in (("\\Delta ", "Δ"), ("\\Delta", "Δ"), ("\\tau", "τ"), ("\\theta", "θ"),
                       ("\\hat", ""), ("\\dot", ""), ("\\", "")):
        text = text.replace(tex, plain)
    return text.replace(" ", "") if len(text) < 8 else text


def _pack(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    code = {np.dtype(np.float64): "f8", np.dtype(np.float32): "f4",
            np.dtype(np.uint32): "u4"}[a.dtype]
    return {"dtype": code, "shape": list(a.shape),
            "b64": base64.b64encode(a.astype(a.dtype.newbyteorder("<")).tobytes())
            .decode("ascii")}


def unpack(packed: dict) -> np.ndarray:
    """An array packed into the page (for tests and tools)."""
    dtype = {"f8": "<f8", "f4": "<f4", "u4": "<u4"}[packed["dtype"]]
    return np.frombuffer(base64.b64decode(packed["b64"]), dtype=dtype).reshape(packed["shape"])


# ---------------------------------------------------------------------------- the page
def _asset(name: str) -> str:
    return resources.files("fwdstep.results").joinpath("assets", name).read_text(encoding="utf-8")


def _data_module(source: str) -> str:
    return "data:text/javascript;base64," + base64.b64encode(source.encode()).decode("ascii")


def page_html(runs: list, meshes: list, title: str) -> str:
    """The self-contained page of ``runs`` (run_data dicts)."""
    kinds = {r["kind"] for r in runs}
    if len(kinds) > 1:
        raise OutputError("cannot overlay a URDF arm and a planar arm in one page")
    for r, colour in zip(runs, RUN_COLOURS * 4):
        r["color"] = colour
    data = {"title": title, "kind": runs[0]["kind"], "runs": runs, "meshes": meshes,
            "fps": DISPLAY_FPS}
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    head = ""
    if data["kind"] == "urdf":
        imports = {"three": _data_module(_asset("three.module.min.js")),
                   "three/addons/OrbitControls.js": _data_module(_asset("OrbitControls.js"))}
        head = f'<script type="importmap">{json.dumps({"imports": imports})}</script>'
    licence = ("three.js r169 (MIT licence, © 2010-2024 three.js authors) is inlined for the "
               "3-D view." if data["kind"] == "urdf" else "")
    return ("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width,initial-scale=1\">"
            f"<title>{html.escape(title)}</title><style>{_asset('animate.css')}</style>{head}"
            "</head><body>"
            f"<div id=\"fw-app\"><h1>{html.escape(title)}</h1><div id=\"fw-legend\"></div>"
            "<div id=\"fw-view\"></div>"
            "<div id=\"fw-controls\"><button id=\"fw-play\" type=\"button\" "
            "title=\"play/pause (space)\">&#9654;</button>"
            "<input id=\"fw-slider\" type=\"range\" step=\"any\" aria-label=\"time\">"
            "<span id=\"fw-time\"></span><label>speed <select id=\"fw-speed\">"
            + "".join(f"<option value=\"{s}\"{' selected' if s == 1 else ''}>{s}&times;</option>"
                      for s in (0.1, 0.25, 0.5, 1, 2, 4)) +
            "</select></label><label><input id=\"fw-loop\" type=\"checkbox\" checked> loop"
            "</label></div><canvas id=\"fw-plot\"></canvas>"
            f"<p class=\"fw-note\" id=\"fw-note\"></p><p class=\"fw-note\">{licence} "
            + ("Drag to turn the view, scroll to zoom. " if data["kind"] == "urdf" else "")
            + "The slider, space and the arrow keys move in time; a "
            "click on a plot jumps there; #t=SECONDS in the address opens the page paused "
            "at that time.</p></div>"
            f"<script type=\"application/json\" id=\"fwdstep-data\">{payload}</script>"
            f"<script type=\"module\">{_asset('animate.js')}</script>{_MARK}</body></html>\n")


def animation_html(sources, labels=None, fps: float = DISPLAY_FPS) -> Animation:
    """The page replaying one or more runs: each source a Result with its compiled diagram
    (fresh from ``simulate``), or a (Result, diagram, where) triple (a saved run, loaded by
    ``fwdstep.views.animate``)."""
    sources = list(sources) if isinstance(sources, (list, tuple)) else [sources]
    if not sources:
        raise OutputError("animate needs at least one run")
    store = MeshStore()
    runs, names = [], []
    for i, src in enumerate(sources):
        result, diagram, where = src if isinstance(src, tuple) else _own(src)
        label = labels[i] if labels else _label(where, diagram)
        runs.append(run_data(result, diagram, label, fps, store,
                             where or os.path.basename(diagram.file or "the run")))
        names.append(label)
    title = "fwdstep animate: " + " vs ".join(names)
    return Animation(page_html(runs, store.items, title))


def _own(result):
    """(result, its diagram, a name for messages) of a Result fresh from ``simulate``."""
    d = getattr(result, "diagram", None)
    if d is None:
        raise OutputError("this Result has no diagram to take the robot from (a saved run: "
                          "use fwdstep.animate(RUN_DIR) or fwdstep animate RUN_DIR)")
    return result, d, None


def _label(where, diagram) -> str:
    """A run directory's name (with the diagram's when they differ), else the diagram's."""
    base = os.path.splitext(os.path.basename(diagram.file or ""))[0]
    if where is not None:
        name = os.path.basename(os.path.normpath(os.fspath(where)))
        return name if name == base or not base else f"{name} ({base})"
    return base or "run"


def embed_html(page: str, height: int = 760) -> str:
    """The page inside an iframe (srcdoc): for the report and notebooks.  Not sandboxed:
    in a sandbox's opaque origin chromium does not run the 3-D view (three.js's data:
    modules), and the page is fwdstep's own (every label escaped)."""
    return (f'<iframe class="fw-animation" title="animation" '
            f'style="width:100%;height:{height}px;border:1px solid #ccc" '
            f'srcdoc="{html.escape(page, quote=True)}"></iframe>')


# ---------------------------------------------------------------------------- writing
def write_page(page: str, output: str) -> str:
    """Write ``page`` to ``output``; only a page fwdstep animate wrote there is replaced."""
    if os.path.lexists(output):
        ours = False
        if os.path.isfile(output) and not os.path.islink(output):
            with open(output, "rb") as fh:
                fh.seek(max(0, os.path.getsize(output) - 200))
                ours = _MARK.encode() in fh.read()
        if not ours:
            raise OutputError(f"refusing to replace {output}: it is not a page fwdstep "
                              "animate wrote")
    os.makedirs(os.path.dirname(os.path.abspath(output)) or ".", exist_ok=True)
    atomic_write(os.path.abspath(output), lambda fh: fh.write(page.encode()), binary=True)
    return output


__all__ = ["animation_html", "Animation", "find_plant", "planar_points", "frame_indices",
           "unpack", "write_page", "embed_html"]
