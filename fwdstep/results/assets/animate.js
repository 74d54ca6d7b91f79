// fwdstep animate: the player of a page written by fwdstep/animate.py (fwdstep's own code).
// It reads the JSON in #fwdstep-data (arrays packed as little-endian base64), draws the
// robot of each run at the frame whose logged time is the latest <= the slider's time, and
// exposes what it drew in document.body.dataset (t, frames, q, points or ee).
const D = JSON.parse(document.getElementById("fwdstep-data").textContent);
const TYPES = {f8: Float64Array, f4: Float32Array, u4: Uint32Array};

function unpack(p) {
  const bin = atob(p.b64), bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  const a = new TYPES[p.dtype](bytes.buffer);
  a.shape = p.shape;
  return a;
}

const runs = D.runs.map((r) => {
  const out = Object.assign({}, r);
  for (const k of ["t", "q", "points", "ghost", "poses", "ee", "ee_desired"])
    if (r[k]) out[k] = unpack(r[k]);
  if (r.plot) out.plot = {name: r.plot.name, label: r.plot.label, unit: r.plot.unit,
                          components: r.plot.components,
                          t: unpack(r.plot.t), e: unpack(r.plot.e)};
  out.F = out.t.length;
  return out;
});
const T0 = Math.min(...runs.map((r) => r.t[0]));
const T1 = Math.max(...runs.map((r) => r.t[r.F - 1]));
const S = {t: T0, playing: true, speed: 1, loop: true, view: null, plot: null};

function frameAt(r, t) {                 // the latest frame with r.t[k] <= t (0 before the start)
  let lo = 0, hi = r.F - 1;
  if (t >= r.t[hi]) return hi;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (r.t[mid] <= t + 1e-12) lo = mid; else hi = mid - 1;
  }
  return lo;
}

function row(a, k) {                     // row k of a 2-D array
  const n = a.shape[1];
  return Array.from(a.subarray(k * n, (k + 1) * n));
}

// ------------------------------------------------------------------------------- legend
const legend = document.getElementById("fw-legend");
legend.innerHTML = runs.map((r) =>
  `<span class="sw" style="background:${r.color}"></span>${esc(r.label)} — ${esc(r.plant)}` +
  (r.status !== "ok" ? ` <b style="color:#c0392b">[${esc(r.status)}]</b>` : "")).join("") +
  (!runs.some((r) => r.desired) ? "" : runs.length === 1 ?
   '<span class="sw" style="background:#2ca02c;opacity:.45"></span>desired q<sub>d</sub> ' +
   "(ghost, end-effector path dashed)" :
   "<br>light and dashed: each run's desired q<sub>d</sub> (ghost, end-effector path)");
document.getElementById("fw-note").textContent = runs.map((r) =>
  `${r.label}: ${r.F} frames of the logged ${r.q_signal} (${r.kind === "urdf" ?
    r.robot + ", end effector " + r.ee_frame : r.plane})`).join("; ");

// the desired motion: green for one run, each run's own colour (light) for an overlay
const ghostColour = (r, alpha) => runs.length === 1 ? `rgba(44,160,44,${alpha})` :
  `rgba(${parseInt(r.color.slice(1, 3), 16)},${parseInt(r.color.slice(3, 5), 16)},` +
  `${parseInt(r.color.slice(5, 7), 16)},${alpha})`;

function esc(s) {
  return String(s).replace(/[&<>"]/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;",
                                               '"': "&quot;"}[c]));
}

// ------------------------------------------------------------------------------- 2-D view
class PlanarView {
  constructor(host) {
    this.canvas = document.createElement("canvas");
    host.appendChild(this.canvas);
    let lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
    for (const r of runs) for (const a of [r.points, r.ghost]) {
      if (!a) continue;
      for (let i = 0; i < a.length; i += 2) {
        lo = [Math.min(lo[0], a[i]), Math.min(lo[1], a[i + 1])];
        hi = [Math.max(hi[0], a[i]), Math.max(hi[1], a[i + 1])];
      }
    }
    const reach = Math.max(hi[0] - lo[0], hi[1] - lo[1], 1e-3);
    this.lo = [lo[0] - 0.08 * reach, lo[1] - 0.08 * reach];
    this.hi = [hi[0] + 0.08 * reach, hi[1] + 0.08 * reach];
    this.resize();
  }
  resize() {
    const c = this.canvas, dpr = window.devicePixelRatio || 1;
    c.width = Math.max(1, c.clientWidth * dpr); c.height = Math.max(1, c.clientHeight * dpr);
    const sx = c.width / (this.hi[0] - this.lo[0]), sy = c.height / (this.hi[1] - this.lo[1]);
    this.s = Math.min(sx, sy);
    this.ox = (c.width - this.s * (this.hi[0] - this.lo[0])) / 2 - this.s * this.lo[0];
    this.oy = (c.height + this.s * (this.hi[1] - this.lo[1])) / 2 + this.s * this.lo[1];
    this.dpr = dpr;
  }
  X(x) { return this.ox + this.s * x; }
  Y(y) { return this.oy - this.s * y; }
  path(ctx, a, k, P, upto, from) {       // the tip's path: point P-1 of frames from..upto
    ctx.beginPath();
    for (let j = from; j <= upto; j++) {
      const i = (j * P + P - 1) * 2;
      if (j === from) ctx.moveTo(this.X(a[i]), this.Y(a[i + 1]));
      else ctx.lineTo(this.X(a[i]), this.Y(a[i + 1]));
    }
    ctx.stroke();
  }
  arm(ctx, a, k, P, links, colour, width, dash) {
    const pts = [];
    for (let p = 0; p < P; p++) pts.push([a[(k * P + p) * 2], a[(k * P + p) * 2 + 1]]);
    ctx.setLineDash(dash || []);
    if (links) {
      ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.lineCap = "round";
      ctx.lineJoin = "round";
      ctx.beginPath();
      pts.forEach((q, i) => (i ? ctx.lineTo : ctx.moveTo).call(ctx, this.X(q[0]), this.Y(q[1])));
      ctx.stroke();
    }
    ctx.setLineDash([]);
    for (let p = 0; p < P; p++) {
      ctx.beginPath();
      ctx.arc(this.X(pts[p][0]), this.Y(pts[p][1]), links ? width * 0.45 : width, 0, 2 * Math.PI);
      ctx.fillStyle = dash ? "rgba(255,255,255,0.5)" : "#fff";
      if (!links) ctx.fillStyle = colour;
      ctx.fill();
      ctx.lineWidth = 2 * this.dpr; ctx.strokeStyle = colour; ctx.stroke();
    }
    return pts;
  }
  grid(ctx) {
    const c = this.canvas, span = (this.hi[0] - this.lo[0]);
    const step = Math.pow(10, Math.floor(Math.log10(span / 4)));
    const nice = span / step > 20 ? 5 * step : span / step > 8 ? 2 * step : step;
    ctx.strokeStyle = "#e3e6ea"; ctx.lineWidth = 1;
    ctx.font = `${11 * this.dpr}px sans-serif`; ctx.fillStyle = "#999";
    for (let x = Math.ceil(this.lo[0] / nice) * nice; x <= this.hi[0]; x += nice) {
      ctx.beginPath(); ctx.moveTo(this.X(x), 0); ctx.lineTo(this.X(x), c.height); ctx.stroke();
    }
    const ylo = (this.oy - c.height) / this.s, yhi = this.oy / this.s;
    for (let y = Math.ceil(ylo / nice) * nice; y <= yhi; y += nice) {
      ctx.beginPath(); ctx.moveTo(0, this.Y(y)); ctx.lineTo(c.width, this.Y(y)); ctx.stroke();
    }
    ctx.fillText(`grid ${+nice.toPrecision(3)} m`, 8 * this.dpr, c.height - 8 * this.dpr);
    ctx.fillStyle = "#555";               // the base
    ctx.fillRect(this.X(0) - 9 * this.dpr, this.Y(0) - 4 * this.dpr, 18 * this.dpr, 8 * this.dpr);
  }
  draw(ks) {
    const c = this.canvas, ctx = c.getContext("2d");
    ctx.clearRect(0, 0, c.width, c.height);
    this.grid(ctx);
    const w = 9 * this.dpr;
    let drawn = null;
    runs.forEach((r, i) => {
      const P = r.points.shape[1], k = ks[i];
      const paths = r.links || P === 1;  // an arm's tip, or a single point mass
      if (r.ghost && paths) {            // the desired tip path, whole run, dashed
        ctx.strokeStyle = ghostColour(r, 0.7); ctx.lineWidth = 1.5 * this.dpr;
        ctx.setLineDash([6 * this.dpr, 5 * this.dpr]); this.path(ctx, r.ghost, k, P, r.F - 1, 0);
        ctx.setLineDash([]);
      }
      ctx.strokeStyle = r.color; ctx.globalAlpha = 0.55; ctx.lineWidth = 1.5 * this.dpr;
      if (paths) this.path(ctx, r.points, k, P, k, 0);     // the tip's trail up to now
      ctx.globalAlpha = 1;
      if (r.ghost) this.arm(ctx, r.ghost, k, P, r.links, ghostColour(r, 0.4), w,
                            [4 * this.dpr, 4 * this.dpr]);
    });
    runs.forEach((r, i) => {
      const pts = this.arm(ctx, r.points, ks[i], r.points.shape[1], r.links, r.color, w);
      if (i === 0) drawn = pts;
    });
    document.body.dataset.points = JSON.stringify(drawn);
  }
}

// ------------------------------------------------------------------------------- 3-D view
async function urdfView(host) {
  const THREE = await import("three");
  const {OrbitControls} = await import("three/addons/OrbitControls.js");
  const renderer = new THREE.WebGLRenderer({antialias: true, preserveDrawingBuffer: true});
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  host.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf6f7f9);
  const camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x8d8d8d, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  sun.position.set(2, -3, 4);
  scene.add(sun);
  const geometries = D.meshes.map((m) => {
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(unpack(m.positions), 3));
    g.setIndex(new THREE.BufferAttribute(unpack(m.index), 1));
    g.computeVertexNormals();
    return g;
  });
  // bounds of the motion: every geometry origin and end-effector position
  const box = new THREE.Box3();
  for (const r of runs) {
    for (let i = 0; i < r.poses.length; i += 12)
      box.expandByPoint(new THREE.Vector3(r.poses[i + 3], r.poses[i + 7], r.poses[i + 11]));
    for (let i = 0; i < r.ee.length; i += 3)
      box.expandByPoint(new THREE.Vector3(r.ee[i], r.ee[i + 1], r.ee[i + 2]));
  }
  box.expandByPoint(new THREE.Vector3(0, 0, 0));
  const centre = box.getCenter(new THREE.Vector3());
  const size = Math.max(box.getSize(new THREE.Vector3()).length(), 0.3);
  const grid = new THREE.GridHelper(Math.ceil(size * 2), Math.ceil(size * 2) * 5, 0xb0b4ba,
                                    0xdadde1);
  grid.rotation.x = Math.PI / 2;
  scene.add(grid);
  const axes = new THREE.AxesHelper(0.15);
  scene.add(axes);

  function setPose(meshes, a, k) {      // frame k's [R p] rows of every geometry
    const G = a.shape[1];
    meshes.forEach((m, g) => {
      if (!m) return;
      const o = (k * G + g) * 12;
      m.matrix.set(a[o], a[o + 1], a[o + 2], a[o + 3], a[o + 4], a[o + 5], a[o + 6], a[o + 7],
                   a[o + 8], a[o + 9], a[o + 10], a[o + 11], 0, 0, 0, 1);
      m.matrixWorldNeedsUpdate = true;
    });
  }
  const objects = runs.map((r, i) => {
    const solid = runs.length === 1 ?
      new THREE.MeshStandardMaterial({color: 0xe4e6ea, roughness: 0.55, metalness: 0.05}) :
      new THREE.MeshStandardMaterial({color: new THREE.Color(r.color), roughness: 0.6,
                                      metalness: 0.05, transparent: i > 0,
                                      opacity: i > 0 ? 0.6 : 1});
    const dark = solid.clone(); dark.color.multiplyScalar(0.35);
    // the ghost loses every depth tie to the arm (no green stains where they coincide)
    const ghost = new THREE.MeshLambertMaterial({color: 0x2ca02c, transparent: true,
                                                 opacity: 0.25, depthWrite: false,
                                                 polygonOffset: true, polygonOffsetFactor: 2,
                                                 polygonOffsetUnits: 8});
    const make = (material, useDark) => r.geoms.map((g) => {
      if (g.mesh === null) return null;
      const grey = g.color[0] + g.color[1] + g.color[2] < 1.0;   // dark parts stay dark
      const m = new THREE.Mesh(geometries[g.mesh], useDark && grey ? dark : material);
      m.matrixAutoUpdate = false;
      if (material === ghost) m.renderOrder = 1;
      scene.add(m);
      return m;
    });
    const line = (a, colour, dashed) => {
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.BufferAttribute(new Float32Array(a), 3));
      const mat = dashed ? new THREE.LineDashedMaterial({color: colour, dashSize: 0.02,
                                                         gapSize: 0.015})
                         : new THREE.LineBasicMaterial({color: colour});
      const l = new THREE.Line(g, mat);
      if (dashed) l.computeLineDistances();
      scene.add(l);
      return l;
    };
    const tip = new THREE.Mesh(new THREE.SphereGeometry(size * 0.008, 16, 12),
                               new THREE.MeshBasicMaterial({color: new THREE.Color(r.color)}));
    scene.add(tip);
    return {meshes: make(solid, true), ghost: r.ghost && runs.length === 1 ? make(ghost) : null,
            trail: line(r.ee, new THREE.Color(r.color), false),
            desired: r.ee_desired ? line(r.ee_desired, runs.length === 1 ? 0x2ca02c :
                                         new THREE.Color(r.color), true) : null, tip};
  });

  // the camera sees every mesh at the start, middle and end of each run
  runs.forEach((r, i) => {
    for (const k of [0, r.F >> 1, r.F - 1]) {
      setPose(objects[i].meshes, r.poses, k);
      for (const m of objects[i].meshes) if (m) box.expandByObject(m);
    }
  });
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const dir = new THREE.Vector3(1.45, -1.25, 0.75).normalize();
  const fit = sphere.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2));
  camera.position.copy(sphere.center).addScaledVector(dir, 0.68 * fit);   // the sphere is loose
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.copy(sphere.center);
  controls.update();
  const view = {
    ks: runs.map(() => 0),
    resize() {
      const w = host.clientWidth, h = host.clientHeight;
      renderer.setSize(w, h, true);
      camera.aspect = w / Math.max(h, 1);
      camera.updateProjectionMatrix();
      this.render();
    },
    pose: setPose,
    draw(ks) {
      this.ks = ks;
      runs.forEach((r, i) => {
        const o = objects[i], k = ks[i];
        this.pose(o.meshes, r.poses, k);
        if (o.ghost) this.pose(o.ghost, r.ghost, k);
        o.trail.geometry.setDrawRange(0, k + 1);
        o.tip.position.set(r.ee[3 * k], r.ee[3 * k + 1], r.ee[3 * k + 2]);
      });
      this.render();
      const r = runs[0], k = ks[0];
      const ee = [r.ee[3 * k], r.ee[3 * k + 1], r.ee[3 * k + 2]];
      const p = new THREE.Vector3(...ee).project(camera);
      document.body.dataset.ee = JSON.stringify(ee);
      document.body.dataset.eeScreen = JSON.stringify([
        Math.round((p.x + 1) / 2 * host.clientWidth), Math.round((1 - p.y) / 2 * host.clientHeight)]);
    },
    render() { renderer.render(scene, camera); },
  };
  controls.addEventListener("change", () => view.render());
  return view;
}

// ------------------------------------------------------------------------------- time plots
class Plots {
  constructor(canvas) {
    this.canvas = canvas;
    this.series = runs.filter((r) => r.plot);
    canvas.addEventListener("click", (ev) => {
      const b = canvas.getBoundingClientRect(), x = (ev.clientX - b.left) * this.dpr;
      if (this.boxes) setTime(this.T0 + (x - this.boxes[0].x) / this.boxes[0].w * (this.T1 - this.T0));
    });
  }
  resize() {
    const c = this.canvas, dpr = this.dpr = window.devicePixelRatio || 1;
    c.width = Math.max(1, c.clientWidth * dpr); c.height = Math.max(1, c.clientHeight * dpr);
    this.T0 = T0; this.T1 = T1 > T0 ? T1 : T0 + 1;
    this.back = document.createElement("canvas");
    this.back.width = c.width; this.back.height = c.height;
    const ctx = this.back.getContext("2d");
    ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, c.width, c.height);
    ctx.font = `${11 * dpr}px sans-serif`;
    if (!this.series.length) {
      ctx.fillStyle = "#888";
      ctx.fillText("no error signal logged (metrics: error:)", 10 * dpr, 20 * dpr);
      this.boxes = null;
      return;
    }
    const L = 62 * dpr, R = 12 * dpr, gap = 30 * dpr, top = 18 * dpr;
    const h = (c.height - top - gap - 22 * dpr) / 2, w = c.width - L - R;
    this.boxes = [{x: L, y: top, w, h}, {x: L, y: top + h + gap, w, h}];
    const first = this.series[0].plot;
    const unit = first.unit ? ` [${first.unit}]` : "";
    const m = first.e.shape[1];
    const palette = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                     "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
    // top: the components of the first run's error; bottom: |e|_2 of every run, log scale
    const comps = [];
    for (let j = 0; j < m; j++)
      comps.push({t: first.t, y: Array.from(first.t, (_, k) => first.e[k * m + j]),
                  colour: palette[j % palette.length]});
    const norms = this.series.map((r) => ({t: r.plot.t, colour: r.color,
      y: Array.from(r.plot.t, (_, k) => {
        let s = 0;
        for (let j = 0; j < r.plot.e.shape[1]; j++) s += r.plot.e[k * r.plot.e.shape[1] + j] ** 2;
        return Math.sqrt(s);
      })}));
    this.panel(ctx, this.boxes[0], comps, false,
               `${first.label}${unit} of ${this.series[0].label}, by component`);
    ctx.textAlign = "left";                // which colour is which component
    const names = first.components || comps.map((_, j) => `${j + 1}`);
    let x = this.boxes[0].x + this.boxes[0].w;
    for (let j = comps.length - 1; j >= 0; j--) {
      x -= ctx.measureText(names[j]).width + 22 * dpr;
      ctx.fillStyle = comps[j].colour; ctx.fillRect(x, top - 13 * dpr, 12 * dpr, 4 * dpr);
      ctx.fillStyle = "#555"; ctx.fillText(names[j], x + 15 * dpr, top - 8 * dpr);
    }
    this.panel(ctx, this.boxes[1], norms, true, `|${first.label}|₂${unit} (log scale)`);
  }
  panel(ctx, b, lines, log, title) {
    const f = (y) => (log ? Math.log10(Math.max(y, 1e-300)) : y);
    let lo = Infinity, hi = -Infinity;
    for (const s of lines) for (const y of s.y) if (isFinite(f(y))) {
      lo = Math.min(lo, f(y)); hi = Math.max(hi, f(y));
    }
    if (log) lo = Math.max(lo, hi - 12);
    if (!(hi > lo)) { hi = lo + 1; lo -= 1; }
    const pad = 0.05 * (hi - lo); lo -= pad; hi += pad;
    const X = (t) => b.x + (t - this.T0) / (this.T1 - this.T0) * b.w;
    const Y = (y) => b.y + b.h - (Math.min(Math.max(f(y), lo), hi) - lo) / (hi - lo) * b.h;
    ctx.strokeStyle = "#bbb"; ctx.lineWidth = 1; ctx.strokeRect(b.x, b.y, b.w, b.h);
    ctx.fillStyle = "#333"; ctx.textAlign = "left";
    ctx.fillText(title, b.x, b.y - 5 * this.dpr);
    ctx.fillStyle = "#777"; ctx.textAlign = "right";
    for (const v of [lo + pad, hi - pad]) {
      const text = log ? Math.pow(10, v).toExponential(1) : (+v.toPrecision(3)).toString();
      ctx.fillText(text, b.x - 4 * this.dpr, b.y + b.h - (v - lo) / (hi - lo) * b.h + 4 * this.dpr);
    }
    if (!log && lo < 0 && hi > 0) {
      ctx.strokeStyle = "#ddd"; ctx.beginPath(); ctx.moveTo(b.x, Y(0)); ctx.lineTo(b.x + b.w, Y(0));
      ctx.stroke();
    }
    ctx.textAlign = "center";
    for (let i = 0; i <= 5; i++) {
      const t = this.T0 + i / 5 * (this.T1 - this.T0);
      ctx.fillText(`${+t.toPrecision(3)} s`, X(t), b.y + b.h + 13 * this.dpr);
    }
    ctx.save();
    ctx.beginPath(); ctx.rect(b.x, b.y, b.w, b.h); ctx.clip();
    ctx.lineWidth = 1.3 * this.dpr;
    for (const s of lines) {
      ctx.strokeStyle = s.colour; ctx.beginPath();
      s.y.forEach((y, k) => (k ? ctx.lineTo : ctx.moveTo).call(ctx, X(s.t[k]), Y(y)));
      ctx.stroke();
    }
    ctx.restore();
  }
  draw(t) {
    const c = this.canvas, ctx = c.getContext("2d");
    ctx.clearRect(0, 0, c.width, c.height);
    ctx.drawImage(this.back, 0, 0);
    if (!this.boxes) return;
    ctx.strokeStyle = "#d62728"; ctx.lineWidth = 1.5 * this.dpr;
    for (const b of this.boxes) {
      const x = b.x + (t - this.T0) / (this.T1 - this.T0) * b.w;
      ctx.beginPath(); ctx.moveTo(x, b.y); ctx.lineTo(x, b.y + b.h); ctx.stroke();
    }
    this.cursor = t;
  }
}

// ------------------------------------------------------------------------------- the player
const slider = document.getElementById("fw-slider");
const readout = document.getElementById("fw-time");
const play = document.getElementById("fw-play");
slider.min = T0; slider.max = T1;

function setTime(t) {
  S.t = Math.min(Math.max(t, T0), T1);
  const ks = runs.map((r) => frameAt(r, S.t));
  slider.value = S.t;
  readout.textContent = `t = ${S.t.toFixed(3)} s / ${T1.toFixed(2)} s`;
  if (S.view) S.view.draw(ks);
  if (S.plot) S.plot.draw(S.t);
  const body = document.body.dataset;
  body.t = String(S.t);
  body.frames = JSON.stringify(ks);
  body.frameTimes = JSON.stringify(runs.map((r, i) => r.t[ks[i]]));
  body.q = JSON.stringify(runs.map((r, i) => row(r.q, ks[i])));
  document.title = `${D.title} — t = ${S.t.toFixed(3)} s`;
}

// frames are requested only while playing: a paused page is idle (and a headless browser
// taking its screenshot is not kept busy)
let last = null, ticking = false;
function setPlaying(on) {
  S.playing = on;
  play.innerHTML = on ? "&#10074;&#10074;" : "&#9654;";
  document.body.dataset.playing = on ? "1" : "0";
  if (on && !ticking && S.started) {
    ticking = true; last = null;
    requestAnimationFrame(tick);
  }
}

function tick(now) {
  if (!S.playing) { ticking = false; return; }
  if (last !== null) {
    let t = S.t + (now - last) / 1000 * S.speed;
    if (t > T1) {
      if (S.loop) t = T0; else { t = T1; setPlaying(false); }
    }
    setTime(t);
  }
  last = now;
  requestAnimationFrame(tick);
}

play.addEventListener("click", () => {
  if (!S.playing && S.t >= T1) setTime(T0);
  setPlaying(!S.playing);
});
slider.addEventListener("input", () => { setPlaying(false); setTime(parseFloat(slider.value)); });
document.getElementById("fw-speed").addEventListener("change", (ev) => {
  S.speed = parseFloat(ev.target.value);
});
document.getElementById("fw-loop").addEventListener("change", (ev) => { S.loop = ev.target.checked; });
document.addEventListener("keydown", (ev) => {
  if (ev.target.tagName === "SELECT") return;
  if (ev.key === " ") { ev.preventDefault(); setPlaying(!S.playing); }
  const dt = 1 / D.fps * (ev.shiftKey ? 10 : 1);
  if (ev.key === "ArrowRight") { setPlaying(false); setTime(S.t + dt); }
  if (ev.key === "ArrowLeft") { setPlaying(false); setTime(S.t - dt); }
});

function fromHash() {                    // #t=1.5 (paused there), #t=1.5&play, #speed=2
  const h = new URLSearchParams(location.hash.replace(/^#/, ""));
  if (h.has("speed")) {
    S.speed = parseFloat(h.get("speed")) || 1;
    document.getElementById("fw-speed").value = String(S.speed);
  }
  if (h.has("t")) {
    setPlaying(h.has("play"));
    setTime(parseFloat(h.get("t")) || 0);
  }
}

async function main() {
  const host = document.getElementById("fw-view");
  try {
    S.view = D.kind === "urdf" ? await urdfView(host) : new PlanarView(host);
  } catch (err) {
    host.textContent = `cannot draw the robot here: ${err}`;
    document.body.dataset.error = String(err);
  }
  S.plot = new Plots(document.getElementById("fw-plot"));
  const resize = () => {
    if (S.view) S.view.resize();
    S.plot.resize();
    setTime(S.t);
  };
  window.addEventListener("resize", resize);
  setPlaying(true);
  resize();
  fromHash();
  window.addEventListener("hashchange", fromHash);
  document.body.dataset.ready = "1";
  document.body.dataset.readyMs = String(Math.round(performance.now()));
  S.started = true;
  setPlaying(S.playing);
}
main();
