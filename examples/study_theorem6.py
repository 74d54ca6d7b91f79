"""Study: parameter drift under a sustained disturbance, Slotine-Li against Theorem 6.

One command (from the repository root)::

    python examples/study_theorem6.py                # 120 s, ell = 1..5, about 10 min on 2 cores
    python examples/study_theorem6.py --t-final 60 --ells 1 3 5

runs diagrams/slotine_li_disturbed.yaml and diagrams/theorem6.yaml (ell = 1..5), each with
and without the disturbance (the two variants of one diagram run as one batch), and writes

* docs/figures/theorem6_study.png: |theta_hat(t)| and |Delta q(t)| for every controller,
  with and without the disturbance;
* the table between the markers in docs/theorem6.md (and on stdout).

Drift.  Each controller runs twice, with and without the disturbance, from the same initial
state; D(t) = |theta_hat_with(t) - theta_hat_without(t)| is the part of the estimate the
disturbance is responsible for.  A drifting estimate has a D(t) that keeps growing: the table
gives D(T/2), D(T) and the slope of D over the second half of the run, next to |theta_hat(T)|,
its change over the second half, and the tracking error over the last 20% of the run.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

THEOREM6 = os.path.join(ROOT, "diagrams", "theorem6.yaml")
SLOTINE_LI = os.path.join(ROOT, "diagrams", "slotine_li_disturbed.yaml")
DOC = os.path.join(ROOT, "docs", "theorem6.md")
FIGURE = os.path.join(ROOT, "docs", "figures", "theorem6_study.png")
TABLE_START = "<!-- study table: written by examples/study_theorem6.py -->"
TABLE_END = "<!-- end of study table -->"
NO_DISTURBANCE = [0.0, 0.0]
TAIL = 0.2          # tracking error over the last 20% of the run


def run_case(job):
    """Run one diagram with and without the disturbance (one batch of two variants)."""
    import fwdstep
    from fwdstep.structure.spec import load_spec

    label, path, overrides = job
    specs = [load_spec(path, dict(overrides, **extra))
             for extra in ({}, {"dist_amplitude": NO_DISTURBANCE})]
    wall = time.perf_counter()
    try:
        r = fwdstep.simulate(fwdstep.compile_batch(specs))
    except fwdstep.SimulationError as exc:     # keep what was computed
        r = exc.result
    error_name = "qds.dq" if "qds.dq" in r else "dq.y"
    return {"label": label, "t": r.t, "theta": r["adapt.theta_hat"], "dq": r[error_name],
            "status": r.status, "wall": time.perf_counter() - wall,
            "gamma": float(np.ravel(specs[0].parameters["gamma"])[0])}


def deviation(res):
    """D(t) = |theta_hat with the disturbance - theta_hat without|, (T,)."""
    return np.linalg.norm(res["theta"][:, 0] - res["theta"][:, 1], axis=1)


def metrics(res, theta_true):
    """The table's numbers for one controller (both variants)."""
    t = res["t"]
    half = t >= t[-1] / 2
    tail = t >= (1 - TAIL) * t[-1]
    i_half = int(np.argmax(half))
    D = deviation(res)
    out = {"D_half": D[i_half], "D_end": D[-1],
           "D_slope": np.polyfit(t[half], D[half], 1)[0] if np.all(np.isfinite(D)) else np.nan}
    for b, key in ((0, "with"), (1, "without")):
        theta = res["theta"][:, b]
        err = np.linalg.norm(res["dq"][:, b], axis=1)
        out[key] = {
            "theta_norm": np.linalg.norm(theta[-1]),
            "change": np.linalg.norm(theta[-1] - theta[i_half]),
            "theta_error": np.linalg.norm(theta[-1] - theta_true),
            "tail_max": np.max(err[tail]),
            "tail_rms": np.sqrt(np.mean(err[tail] ** 2)),
        }
    return out


def table(results, theta_true, t_final) -> str:
    bar = "\\|"
    lines = [
        "Drift: D(t) = |theta_hat with disturbance - theta_hat without|.",
        "",
        "| controller | Gamma | D(T/2) | D(T) | dD/dt, 2nd half (1/s) |",
        "|---|---|---|---|---|",
    ]
    rows = [(res, metrics(res, theta_true)) for res in results]
    for res, m in rows:
        lines.append(f"| {res['label']} | {res['gamma']:g} | {m['D_half']:.3f} | {m['D_end']:.3f} | "
                     f"{m['D_slope']:+.1e} |")
    lines += [
        "",
        f"| controller | disturbance | {bar}theta_hat(T){bar} | {bar}theta_hat(T) - theta_hat(T/2){bar} "
        f"| {bar}theta_hat(T) - theta{bar} | max {bar}Delta q{bar}, last 20% (rad) "
        f"| RMS {bar}Delta q{bar}, last 20% (rad) |",
        "|---|---|---|---|---|---|---|",
    ]
    for res, m in rows:
        for key, dist in (("with", "yes"), ("without", "no")):
            v = m[key]
            lines.append(f"| {res['label']} | {dist} | {v['theta_norm']:.3f} | {v['change']:.3f} | "
                         f"{v['theta_error']:.3f} | {v['tail_max']:.1e} | {v['tail_rms']:.1e} |")
    lines.append("")
    lines.append(f"T = {t_final:g} s; true theta = [{', '.join(f'{v:.3f}' for v in theta_true)}] "
                 f"(|theta| = {np.linalg.norm(theta_true):.3f}); theta_hat(0) = 0.")
    return "\n".join(lines)


def figure(results, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), sharex=True)
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, max(1, len(results) - 1)))
    for k, res in enumerate(results):
        sl = res["label"].startswith("Slotine")
        style = {"color": "black", "lw": 1.8, "ls": "--"} if sl else \
            {"color": colours[k - 1], "lw": 1.2}
        for b in range(2):
            axes[0, b].plot(res["t"], np.linalg.norm(res["theta"][:, b], axis=1),
                            label=res["label"], **style)
            axes[1, b].semilogy(res["t"], np.linalg.norm(res["dq"][:, b], axis=1), **style)
        axes[0, 2].plot(res["t"], deviation(res), **style)
        axes[1, 2].plot(res["t"], res["theta"][:, 0, 2], **style)
    axes[0, 0].set_title("|theta_hat|, with the sinusoidal disturbance")
    axes[0, 1].set_title("|theta_hat|, without disturbance")
    axes[0, 2].set_title("drift D = |theta_hat(with) - theta_hat(without)|")
    axes[1, 0].set_title("|Delta q| (rad), with the disturbance")
    axes[1, 1].set_title("|Delta q| (rad), without disturbance")
    axes[1, 2].set_title("theta_hat[2] with the disturbance (true a3 = 1.04)")
    for ax in axes.ravel():
        ax.grid(True, alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("t (s)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_table(text, path):
    with open(path) as fh:
        doc = fh.read()
    pattern = re.compile(re.escape(TABLE_START) + ".*?" + re.escape(TABLE_END), re.S)
    if not pattern.search(doc):
        raise SystemExit(f"{path} has no study-table markers; add\n{TABLE_START}\n{TABLE_END}")
    doc = pattern.sub(lambda _: f"{TABLE_START}\n{text}\n{TABLE_END}", doc)
    with open(path, "w") as fh:
        fh.write(doc)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=120.0, help="run length in s (>= 60)")
    ap.add_argument("--ells", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--dist-frequency", type=float, default=None,
                    help="disturbance frequency in rad/s (default: the diagrams' 0.8)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    ap.add_argument("--save", help="also keep the raw results in this .npz file")
    ap.add_argument("--load", help="redraw the figure and table from a --save file")
    args = ap.parse_args(argv)

    from fwdstep.blocks.robot import TwoLinkArm
    theta_true = TwoLinkArm.parameter_vector()
    common = {"t_final": args.t_final}
    if args.dist_frequency is not None:
        common["dist_frequency"] = args.dist_frequency
    jobs = [("Slotine-Li", SLOTINE_LI, common)]
    jobs += [(f"Theorem 6, ell = {ell}", THEOREM6, dict(common, ell=ell)) for ell in args.ells]
    started = time.perf_counter()
    if args.load:
        with np.load(args.load, allow_pickle=True) as data:
            results = list(data["results"])
            args.t_final = float(data["t_final"])
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            results = []
            for res in pool.map(run_case, jobs):
                print(f"{res['label']}: {res['status']}, {res['wall']:.0f} s", file=sys.stderr,
                      flush=True)
                results.append(res)
    if args.save:
        np.savez(args.save, results=np.array(results, dtype=object), t_final=args.t_final)
    text = table(results, theta_true, args.t_final)
    print(text)
    if not args.no_write:
        figure(results, FIGURE)
        write_table(text, DOC)
        print(f"wrote {os.path.relpath(FIGURE, ROOT)} and the table in "
              f"{os.path.relpath(DOC, ROOT)}", file=sys.stderr)
    print(f"total {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
