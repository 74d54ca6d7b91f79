"""Robustness study: forwardstepping (Theorems 1, 3, 6) against Slotine-Li, PID and computed
torque, under torque saturation, a sampled controller (1 kHz, 200 Hz), sensor noise and a
payload step.  docs/robustness.md shows and discusses the results.

Reproduce every number and figure (about 30 minutes on 2 busy cores):

    MPLBACKEND=Agg python examples/study_robustness.py --out results/robustness

Every controller is a shipped diagram, run as it is shipped except for the shared task (all
are put on the task of diagrams/theorem3.yaml: horizontal two-link arm, q0 = [0.3, -0.2],
q_d = [0.5, 0.3] sin(0.5 t), disturbance tau* = [2, 1] sin(0.8 t + [0, 1])).  A scenario is a
data edit of the diagram (blocks inserted, connections rerouted; no Python inside a
diagram), and every edited diagram is written next to the results, so each run can be
repeated alone with ``fwdstep run OUT/diagrams/<controller>__<scenario>.yaml``:

* nominal: as shipped;
* saturation: a Saturation block between the controller's torque and the arm;
* sampled_1kHz, sampled_200Hz: ZeroOrderHold on q and qdot (the controller's inputs) and on
  tau (its output) -- a digital controller whose own filters run on held inputs, the
  semantics of a subsystem with ``sample_period`` (docs/discrete-time.md);
* noise: WhiteNoise added to the measured q and qdot (every block that reads q or qdot reads
  the noisy value; the error is measured on the true q);
* payload: the arm's link 2 gains ``payload`` kg at its centre of mass at t = 4 s (the
  TwoLinkArm options payload/payload_time); the controllers are not told;
* vertical, payload_vertical: the same task on the VERTICAL arm (gravity 9.81), without and
  with the payload, for the controllers that have a gravity form (``VERTICAL``).

The error reported is always e = q - q_d on the TRUE q (block ``e_true``), the torque the
one applied to the arm.  ``--smoke`` runs every scenario of two controllers for 0.2 s (the
test suite uses it); ``--only`` picks controllers or scenarios; ``--figures-only`` redraws
from OUT/results.json and OUT/*.npz.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

DIAGRAMS = os.path.join(ROOT, "diagrams")

#: the shared task (the one of theorem3.yaml, theorem6.yaml, pid_classic.yaml, ...)
TASK = {"q0": [0.3, -0.2], "qd_amplitude": [0.5, 0.3], "qd_frequency": 0.5,
        "dist_amplitude": [2.0, 1.0], "dist_frequency": 0.8, "dist_phase": [0.0, 1.0]}

#: controller -> (shipped diagram, parameter overrides putting it on the shared task)
CONTROLLERS = {
    "Theorem 1": ("theorem1_sine.yaml", {"A": [0.5, 0.3], "w": [0.5, 0.5], "c": [0.0, 0.0],
                                         "q0": [0.3, -0.2], "step": 0.001}),
    "Theorem 3": ("theorem3.yaml", {}),
    "Theorem 6": ("theorem6.yaml", {"step": 0.001}),
    "Slotine-Li": ("slotine_li_sine_disturbance.yaml", {}),
    "PID": ("pid_classic.yaml", {}),
    "computed torque": ("computed_torque.yaml", {"gravity": 0}),
}

#: the vertical arm (gravity 9.81), for the payload_vertical scenario: controllers with a
#: gravity form (Theorem 1's and Slotine-Li's diagrams are horizontal only)
VERTICAL = {
    "Theorem 3": ("theorem3_vertical.yaml", {}),
    "Theorem 6": ("theorem6.yaml", {"gravity": 9.81, "p": 7, "theta0": 0, "K": "100*eye(2)",
                                    "step": 0.001}),
    "PID": ("pid_classic.yaml", {"gravity": 9.81}),
    "computed torque": ("computed_torque.yaml", {}),
}

#: scenario settings
TORQUE_LIMIT = [5.0, 2.0]           # |tau_i| <= limit_i (N m); the task needs about [3, 1.2]
NOISE_PSD_Q = 1e-8                   # rad^2/Hz: std 3.2 mrad when held over 1 ms
NOISE_PSD_QDOT = 1e-6                # (rad/s)^2/Hz: std 0.032 rad/s over 1 ms
NOISE_SAMPLE = 0.001                 # s
PAYLOAD = 1.0                        # kg added to link 2 (me = 2 kg) at PAYLOAD_TIME
PAYLOAD_TIME = 4.0
SCENARIOS = ["nominal", "saturation", "sampled_1kHz", "sampled_200Hz", "noise", "payload",
             "vertical", "payload_vertical"]
T_FINAL = 10.0
WINDOW = (5.0, 10.0)                # metrics window (after the transients; after the payload)


# ------------------------------------------------------------------------- diagram edits
def _parse(doc):
    """connections as (source, [destinations]) pairs."""
    out = []
    for line in doc["connections"]:
        src, _, dsts = line.partition("->")
        out.append((src.strip(), [d.strip() for d in dsts.split(",")]))
    return out


def _write(doc, pairs):
    doc["connections"] = [f"{s} -> {', '.join(d)}" for s, d in pairs if d]


def reroute_source(doc, src, new_src):
    """Every port fed by ``src`` is fed by ``new_src`` instead."""
    pairs = _parse(doc)
    moved = []
    for s, dsts in pairs:
        if s == src:
            moved += dsts
            dsts.clear()
    pairs.append((new_src, moved))
    _write(doc, pairs)


def feeder_of(doc, dst):
    for s, dsts in _parse(doc):
        if dst in dsts:
            return s
    raise KeyError(dst)


def insert_before(doc, dst, block_in, block_out):
    """``X -> dst`` becomes ``X -> block_in`` and ``block_out -> dst``."""
    pairs = _parse(doc)
    for s, dsts in pairs:
        if dst in dsts:
            dsts[dsts.index(dst)] = block_in
    pairs.append((block_out, [dst]))
    _write(doc, pairs)


def flatten_plant(doc):
    """Theorem 6 uses the lib/plant.yaml subsystem (arm + regressor); inline it so the arm's
    q and qdot are visible to the edits below (the regressor then reads the measured q)."""
    if "plant" not in doc["blocks"]:
        return
    sub = doc["blocks"].pop("plant")
    par = sub.get("parameters", {})
    doc["blocks"]["arm"] = {"type": "TwoLinkArm", "q0": par.get("q0", [0, 0]),
                            "gravity": par.get("gravity", 0)}
    doc["blocks"]["reg"] = {"type": "Regressor", "gravity": par.get("gravity", 0)}
    names = {"plant.q": "arm.q", "plant.qdot": "arm.qdot", "plant.Y": "reg.Y",
             "plant.z": "reg.zeta", "plant.zdot": "reg.zetad", "plant.tau": "arm.tau",
             "plant.tau_star": "arm.tau_star"}
    pairs = [(names.get(s, s), [names.get(d, d) for d in dsts]) for s, dsts in _parse(doc)]
    pairs += [("arm.q", ["reg.q"]), ("arm.qdot", ["reg.qdot"])]
    _write(doc, pairs)


def ensure_disturbance(doc):
    """Theorem 1's sine diagram has no disturbance: add the task's."""
    if any("arm.tau_star" in d for _, d in _parse(doc)):
        return
    doc["blocks"]["dist"] = {"type": "Sine", "amplitude": TASK["dist_amplitude"],
                             "frequency": TASK["dist_frequency"], "phase": TASK["dist_phase"]}
    pairs = _parse(doc) + [("dist.y", ["arm.tau_star"])]
    _write(doc, pairs)


def merge_measurements(doc, prefix):
    """Route every reader of arm.q / arm.qdot through ``<prefix>q.y`` / ``<prefix>qd.y``
    (blocks added by the caller, fed from arm.q / arm.qdot)."""
    for port, name in (("arm.q", f"{prefix}q"), ("arm.qdot", f"{prefix}qd")):
        reroute_source(doc, port, f"{name}.y")
        pairs = _parse(doc) + [(port, [f"{name}.u1" if prefix == "n_" else f"{name}.u"])]
        _write(doc, pairs)


def scenario_doc(controller, scenario, t_final=T_FINAL):
    """The edited diagram (a dict) and its parameter overrides."""
    if scenario in ("vertical", "payload_vertical"):
        if controller not in VERTICAL:
            return None, None
        file, overrides = VERTICAL[controller]
    else:
        file, overrides = CONTROLLERS[controller]
    with open(os.path.join(DIAGRAMS, file)) as fh:
        doc = yaml.safe_load(fh)
    doc = copy.deepcopy(doc)
    params = doc["parameters"]
    for key, value in {**overrides, "t_final": t_final}.items():
        params[key] = value
    for key in ("qd_amplitude", "qd_frequency", "q0", "dist_amplitude", "dist_frequency",
                "dist_phase"):
        if key in params:
            params[key] = TASK[key]
    flatten_plant(doc)
    ensure_disturbance(doc)
    blocks = doc["blocks"]
    tau_src = feeder_of(doc, "arm.tau")
    if scenario == "saturation":
        blocks["sat"] = {"type": "Saturation", "lower": [-v for v in TORQUE_LIMIT],
                         "upper": TORQUE_LIMIT}
        insert_before(doc, "arm.tau", "sat.u", "sat.y")
    elif scenario.startswith("sampled"):
        period = 0.001 if scenario == "sampled_1kHz" else 0.005
        for name in ("z_q", "z_qd", "z_tau"):
            blocks[name] = {"type": "ZeroOrderHold", "period": period, "shape": [2]}
        blocks["z_q"]["initial"] = TASK["q0"]
        merge_measurements(doc, "z_")
        insert_before(doc, "arm.tau", "z_tau.u", "z_tau.y")
    elif scenario == "noise":
        blocks["w_q"] = {"type": "WhiteNoise", "n": 2, "psd": NOISE_PSD_Q,
                         "sample_time": NOISE_SAMPLE, "seed": 1}
        blocks["w_qd"] = {"type": "WhiteNoise", "n": 2, "psd": NOISE_PSD_QDOT,
                          "sample_time": NOISE_SAMPLE, "seed": 2}
        blocks["n_q"] = {"type": "Sum", "signs": "++", "shape": [2]}
        blocks["n_qd"] = {"type": "Sum", "signs": "++", "shape": [2]}
        merge_measurements(doc, "n_")
        _write(doc, _parse(doc) + [("w_q.y", ["n_q.u2"]), ("w_qd.y", ["n_qd.u2"])])
    elif scenario in ("payload", "payload_vertical"):
        blocks["arm"]["payload"] = PAYLOAD
        blocks["arm"]["payload_time"] = PAYLOAD_TIME
    # the true error and the applied torque, for every scenario alike
    blocks["e_true"] = {"type": "Sum", "signs": "+-", "shape": [2]}
    _write(doc, _parse(doc) + [("arm.q", ["e_true.u1"]), (_qd_source(doc), ["e_true.u2"])])
    applied = feeder_of(doc, "arm.tau")
    doc["log"] = [{"signal": "e_true.y", "label": "$\\Delta q$", "unit": "rad",
                   "components": ["joint 1", "joint 2"]},
                  {"signal": applied, "label": "$\\tau$", "unit": "N m",
                   "components": ["joint 1", "joint 2"]}]
    if tau_src != applied:
        doc["log"].append({"signal": tau_src, "label": "$\\tau_{cmd}$", "unit": "N m"})
    doc["plots"] = {"tracking_error": ["e_true.y", {"signals": ["e_true.y"], "scale": "log"}],
                    "torque": [applied]}
    doc["metrics"] = {"error": "e_true.y"}
    doc["description"] = (f"{controller}, scenario '{scenario}' (examples/study_robustness.py)"
                          f": an edit of diagrams/{file}.\n" + doc.get("description", ""))
    return doc, applied


def _qd_source(doc):
    """The q_d signal (Sine block 'qd', output y) every shipped controller has."""
    assert doc["blocks"]["qd"]["type"] == "Sine"
    return "qd.y"


# ------------------------------------------------------------------------- running
def run_one(args):
    controller, scenario, outdir, t_final = args
    import fwdstep
    doc, applied = scenario_doc(controller, scenario, t_final)
    if doc is None:                          # no such form of this controller
        return {"controller": controller, "scenario": scenario, "status": "n/a",
                "message": "", "wall": 0.0,
                **metrics(np.zeros(1), np.full((1, 2), np.nan), np.full((1, 2), np.nan),
                          t_final)}
    name = f"{controller.replace(' ', '_')}__{scenario}"
    path = os.path.join(outdir, "diagrams", name + ".yaml")
    with open(path, "w") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, width=100)
    wall = time.perf_counter()
    try:
        r = fwdstep.simulate(fwdstep.load_diagram(path))
        status, message = r.status, r.message
    except fwdstep.DivergenceError as exc:
        r, status, message = exc.result, "diverged", str(exc)
    except fwdstep.FwdstepError as exc:       # reported in the table, the study goes on
        return {"controller": controller, "scenario": scenario, "status": "error",
                "message": str(exc), "wall": time.perf_counter() - wall,
                **metrics(np.zeros(1), np.full((1, 2), np.nan), np.full((1, 2), np.nan),
                          t_final)}
    wall = time.perf_counter() - wall
    t = r.t
    e = r["e_true.y"]
    tau = r[applied]
    np.savez_compressed(os.path.join(outdir, name + ".npz"), t=t, e=e, tau=tau)
    return {"controller": controller, "scenario": scenario, "status": status,
            "message": message, "wall": wall, **metrics(t, e, tau, t_final)}


def _finite_max(values):
    finite = values[np.isfinite(values)]
    return float(np.max(finite)) if finite.size else float("nan")


def metrics(t, e, tau, t_final):
    lo, hi = WINDOW if t_final >= WINDOW[1] else (0.5 * t_final, t_final)
    w = (t >= lo) & (t <= hi) & np.all(np.isfinite(e), axis=1)
    norm = np.linalg.norm(e, axis=1)
    out = {"rms_error": float(np.sqrt(np.mean(norm[w] ** 2))) if w.any() else float("nan"),
           "max_error": float(np.max(norm[w])) if w.any() else float("nan"),
           "max_error_all": _finite_max(norm),
           "rms_torque": float(np.sqrt(np.mean(np.sum(tau[w] ** 2, axis=1))))
           if w.any() else float("nan"),
           "max_torque": _finite_max(np.abs(tau))}
    after = (t >= PAYLOAD_TIME) & np.isfinite(norm)
    out["max_error_after_payload"] = (float(np.max(norm[after])) if after.any()
                                      else float("nan"))
    return out


def saved(outdir, controller, scenario, t_final):
    """The result of a run from its saved signals (OUT/<name>.npz), or None: a run that
    stopped early or has non-finite values is 'diverged'."""
    f = os.path.join(outdir, f"{controller.replace(' ', '_')}__{scenario}.npz")
    if not os.path.exists(f):
        return None
    d = np.load(f)
    ok = d["t"][-1] >= t_final - 1e-9 and np.all(np.isfinite(d["e"]))
    return {"controller": controller, "scenario": scenario,
            "status": "ok" if ok else "diverged", "message": "", "wall": 0.0,
            **metrics(d["t"], d["e"], d["tau"], t_final)}


def collect(outdir, t_final):
    """Results rebuilt from the saved runs when results.json is missing (an interrupted
    study)."""
    return [r for c in CONTROLLERS for s in SCENARIOS
            if (r := saved(outdir, c, s, t_final)) is not None]


# ------------------------------------------------------------------------- figures
def figures(outdir, results, figdir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    controllers = list(dict.fromkeys(r["controller"] for r in results))
    scenarios = [s for s in SCENARIOS if any(r["scenario"] == s for r in results)]
    table = {(r["controller"], r["scenario"]): r for r in results}
    colours = dict(zip(controllers, plt.cm.tab10.colors))
    os.makedirs(figdir, exist_ok=True)
    written = []
    # 1. bar chart: RMS error per scenario and controller (log scale)
    fig, ax = plt.subplots(figsize=(11, 4.8))
    width = 0.8 / len(controllers)
    for i, c in enumerate(controllers):
        runs = [table.get((c, s), {}) for s in scenarios]
        vals = [r.get("rms_error", np.nan) if r.get("status") == "ok" else np.nan for r in runs]
        x = np.arange(len(scenarios)) + (i - (len(controllers) - 1) / 2) * width
        ax.bar(x, vals, width, label=c, color=colours[c])
        for xi, r in zip(x, runs):
            if r.get("status") == "diverged":
                ax.text(xi, 0.02, "diverged", rotation=90, ha="center", va="bottom",
                        fontsize=8, color=colours[c], transform=ax.get_xaxis_transform())
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(scenarios)), scenarios)
    ax.set_ylabel(r"RMS $|\Delta q|$ over t in [%g, %g] s [rad]" % WINDOW)
    ax.set_title("Tracking error by scenario (lower is better; no bar: diverged, or no "
                 "vertical form of that controller)")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(ncol=3, fontsize=9)
    fig.tight_layout()
    written.append(os.path.join(figdir, "robustness_rms_error.png"))
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)
    # 2. per scenario: |e|(t) of every controller, and the applied torque of joint 1
    for s in scenarios:
        fig, axes = plt.subplots(2, 1, figsize=(11, 7), sharex=True)
        torque_scale = 1.0
        for c in controllers:
            f = os.path.join(outdir, f"{c.replace(' ', '_')}__{s}.npz")
            if not os.path.exists(f):
                continue
            d = np.load(f)
            axes[0].semilogy(d["t"], np.linalg.norm(d["e"], axis=1), color=colours[c],
                             label=c, lw=1)
            axes[1].plot(d["t"], d["tau"][:, 0], color=colours[c], label=c, lw=0.8)
            late = (d["t"] >= 1.0) & np.isfinite(d["tau"][:, 0])
            if late.any():          # the scale of the torque after the first second
                torque_scale = max(torque_scale, float(np.max(np.abs(d["tau"][late, 0]))))
        axes[0].set_ylabel(r"$|\Delta q|$ [rad]")
        axes[0].set_ylim(1e-5, 2)
        axes[1].set_ylabel(r"applied $\tau_1$ [N m] (first-second peaks clipped)")
        axes[1].set_xlabel("t [s]")
        if s == "saturation":
            for v in (TORQUE_LIMIT[0], -TORQUE_LIMIT[0]):
                axes[1].axhline(v, color="k", ls=":", lw=0.8)
        if s == "payload":
            for a in axes:
                a.axvline(PAYLOAD_TIME, color="k", ls=":", lw=0.8)
        axes[1].set_ylim(-torque_scale * 1.1, torque_scale * 1.1)
        for a in axes:
            a.grid(True, which="both", alpha=0.3)
        axes[0].legend(ncol=3, fontsize=9, loc="upper right")
        axes[0].set_title(f"Scenario '{s}': tracking error of every controller (true q) and "
                          "the torque applied to joint 1")
        fig.tight_layout()
        written.append(os.path.join(figdir, f"robustness_{s}.png"))
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)
    return written


def markdown_table(results, key, fmt="{:.2e}"):
    controllers = list(dict.fromkeys(r["controller"] for r in results))
    scenarios = [s for s in SCENARIOS if any(r["scenario"] == s for r in results)]
    table = {(r["controller"], r["scenario"]): r for r in results}
    lines = ["| controller | " + " | ".join(scenarios) + " |",
             "|---|" + "---|" * len(scenarios)]
    for c in controllers:
        cells = []
        for s in scenarios:
            r = table.get((c, s))
            if r is None:
                cells.append("-")
            elif r["status"] != "ok":
                cells.append(r["status"])
            else:
                cells.append(fmt.format(r[key]))
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/robustness", help="output folder")
    ap.add_argument("--figures", default=None,
                    help="folder for the figures (default: OUT; docs use docs/figures)")
    ap.add_argument("--only", nargs="*", default=None,
                    help="controllers or scenarios to run (default: all)")
    ap.add_argument("--t-final", type=float, default=T_FINAL)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--smoke", action="store_true",
                    help="every scenario of two controllers for 0.2 s (for the tests)")
    ap.add_argument("--figures-only", action="store_true")
    ap.add_argument("--resume", action="store_true",
                    help="keep the runs already saved in OUT (their .npz) and run the rest")
    args = ap.parse_args(argv)
    out = args.out
    os.makedirs(os.path.join(out, "diagrams"), exist_ok=True)
    controllers = list(CONTROLLERS)
    scenarios = list(SCENARIOS)
    t_final = args.t_final
    if args.smoke:
        controllers, t_final = ["Theorem 1", "computed torque"], 0.2
    if args.only:
        picked_c = [c for c in controllers if c in args.only]
        picked_s = [s for s in scenarios if s in args.only]
        controllers = picked_c or controllers
        scenarios = picked_s or scenarios
    results_path = os.path.join(out, "results.json")
    if args.figures_only:
        results = collect(out, t_final) if not os.path.exists(results_path) else \
            json.load(open(results_path))
    else:
        # scenario by scenario (every controller), the costly sampled runs last
        order = ["nominal", "noise", "payload", "saturation", "sampled_200Hz", "sampled_1kHz",
                 "vertical", "payload_vertical"]
        jobs = [(c, s, out, t_final) for s in order if s in scenarios for c in controllers]
        results = []
        if args.resume:
            done = [saved(out, c, s, t_final) for c, s, _, _ in jobs]
            results = [r for r in done if r is not None]
            jobs = [j for j, r in zip(jobs, done) if r is None]
        if args.workers > 1:
            with ProcessPoolExecutor(args.workers) as pool:
                for r in pool.map(run_one, jobs):
                    results.append(r)
                    print(f"{r['controller']:>16} {r['scenario']:>14}: {r['status']:8} "
                          f"RMS |e| {r['rms_error']:.2e}  max |tau| {r['max_torque']:.3g}  "
                          f"({r['wall']:.0f} s)", flush=True)
        else:
            for job in jobs:
                results.append(run_one(job))
        old = []
        if os.path.exists(results_path) and (args.only or args.resume):
            with open(results_path) as fh:
                old = [r for r in json.load(fh)
                       if (r["controller"], r["scenario"]) not in
                       {(x["controller"], x["scenario"]) for x in results}]
        results = old + results
        order = {c: i for i, c in enumerate(CONTROLLERS)}
        results.sort(key=lambda r: (order[r["controller"]], SCENARIOS.index(r["scenario"])))
        with open(results_path, "w") as fh:
            json.dump(results, fh, indent=1)
    written = figures(out, results, args.figures or out)
    window = "[%g, %g] s" % WINDOW
    for key, title in (("rms_error", f"RMS |e| over {window} (rad)"),
                       ("max_error", f"max |e| over {window} (rad)"),
                       ("max_error_after_payload", f"max |e| from t = {PAYLOAD_TIME:g} s (rad)"),
                       ("rms_torque", f"RMS |tau| over {window} (N m)"),
                       ("max_torque", "max |tau_i| over the run (N m)")):
        print(f"\n{title}\n" + markdown_table(results, key,
                                               "{:.3g}" if "torque" in key else "{:.2e}"))
    print("\nfigures: " + ", ".join(written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
