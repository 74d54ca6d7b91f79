"""Monte Carlo study of Theorem 3 (diagrams/theorem3.yaml): how large does the tracking error
get under random sinusoidal disturbances and an unknown payload?

    python examples/monte_carlo_theorem3.py --out out/mc3                  # 10 000 variants
    python examples/monte_carlo_theorem3.py --out /tmp/mc3 --variants 500 --t-final 20
    python examples/monte_carlo_theorem3.py --out out/mc3 --resume         # after Ctrl-C
    python examples/monte_carlo_theorem3.py --out out/mc3 --scheduler tcp://HOST:8786

Each variant draws (seeded, Latin hypercube over the four uniform axes):

* the disturbance tau_star = A sin(w t + phi) of eq. (1): phases phi_1, phi_2 uniform in
  [0, 2 pi), frequency w log-uniform in [0.2, 3] rad/s (amplitudes as in the diagram);
* the payload: the end mass m_e of the arm uniform in [1.5, 3] kg, while the controller's
  feedforward Y theta keeps the nominal theta (m_e = 2): the payload is unknown to it.

Only the arm block's ``me`` is replaced (``arm.me``), so the diagram's ``theta`` stays
nominal.  Metric: max |Delta q| over the last 20% of the run.  The sweep runs on every local
core (or a Dask cluster), writes each finished batch to OUT/sweep/parts at once, and
``--resume`` finishes an interrupted study.  Figure OUT/monte_carlo_theorem3.png: the
error distribution, the error against w coloured by payload, and |Delta q|(t) of the five
worst variants.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import matplotlib  # noqa: E402
import matplotlib.ticker  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from fwdstep.sweeps.sampling import unit_points  # noqa: E402
from fwdstep.sweeps.sweep import run_sweep  # noqa: E402

DIAGRAM = os.path.join(ROOT, "diagrams", "theorem3.yaml")


def draw_variants(n: int, seed: int) -> list:
    u = unit_points(n, 4, "lhs", seed)
    phases = 2 * np.pi * u[:, 0:2]
    freq = np.exp(np.log(0.2) + u[:, 2] * (np.log(3.0) - np.log(0.2)))
    payload = 1.5 + 1.5 * u[:, 3]
    return [{"dist.phase": [float(p1), float(p2)], "dist.frequency": float(w),
             "arm.me": float(m)} for (p1, p2), w, m in zip(phases, freq, payload)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--variants", type=int, default=10_000)
    ap.add_argument("--t-final", type=float, default=30.0, help="run length (s)")
    ap.add_argument("--step", type=float, default=0.002)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--scheduler", default=None)
    ap.add_argument("--resume", action="store_true")
    args = ap.parse_args(argv)
    variants = draw_variants(args.variants, args.seed)
    sweep_dir = os.path.join(args.out, "sweep")
    os.makedirs(sweep_dir, exist_ok=True)
    result = run_sweep(DIAGRAM, variants=variants,
                       overrides={"t_final": args.t_final, "step": args.step, "log_every": 25},
                       workers=args.workers, scheduler=args.scheduler, outdir=sweep_dir,
                       resume=args.resume, force=not args.resume,   # a re-run starts again
                       progress=lambda text: print(" ", text, file=sys.stderr, flush=True))
    result.write(sweep_dir, plots=False)
    counts = result.counts()
    print(f"{len(variants)} variants in {len(result.batches)} batches, {counts}, "
          f"{result.wall_time:.1f} s wall")
    if result.interrupted:
        print("interrupted: run again with --resume")
        return 130
    ok = [v for v in result.variants if v.status == "ok"]
    err = np.array([v.metrics["tail_error_norm_max"] for v in ok])
    freq = np.array([v.values["dist.frequency"] for v in ok])
    mass = np.array([v.values["arm.me"] for v in ok])
    worst = [ok[k].index for k in np.argsort(err)[::-1][:5]]
    q = np.percentile(err, [50, 95, 99, 100])
    print(f"max |Delta q| over the last 20%: median {q[0]:.3g}, 95% {q[1]:.3g}, "
          f"99% {q[2]:.3g}, worst {q[3]:.3g} rad")
    for i in worst:
        v = result.variants[i]
        print(f"  variant {i}: w = {v.values['dist.frequency']:.3f} rad/s, "
              f"m_e = {v.values['arm.me']:.3f} kg, phases = "
              f"{np.round(v.values['dist.phase'], 3).tolist()}: {v.metrics['tail_error_norm_max']:.3g}")
    traces = {}
    for part in result.iter_parts():
        for k, i in enumerate(part["indices"].tolist()):
            if i in worst:
                traces[i] = (part["t"], np.linalg.norm(part["e"][:, k], axis=-1))

    fig, axes = plt.subplots(3, 1, figsize=(8, 10.5))
    ax = axes[0]
    bins = np.logspace(np.log10(err.min()), np.log10(err.max()), 50)
    ax.hist(err, bins=bins, color="tab:blue", alpha=0.8)
    for value, label, style in zip(q[:3], ("median", "95%", "99%"), (":", "--", "-.")):
        ax.axvline(value, color="k", ls=style, lw=1, label=f"{label}: {value:.3g} rad")
    ax.legend(fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel(r"max $|\Delta q|$ over the last 20% of the run [rad]")
    ax.set_ylabel("variants")
    ax.set_title(f"Theorem 3, {len(ok)} variants: random disturbance phases and frequency, "
                 "unknown payload", fontsize=10)
    ax = axes[1]
    sc = ax.scatter(freq, err, c=mass, s=4, cmap="viridis")
    fig.colorbar(sc, ax=ax, label=r"payload $m_e$ [kg] (controller assumes 2)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks([0.2, 0.5, 1, 2, 3], ["0.2", "0.5", "1", "2", "3"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(r"disturbance frequency $\omega$ [rad/s]")
    ax.set_ylabel(r"max $|\Delta q|$, last 20% [rad]")
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[2]
    for i in worst:
        t, norm = traces[i]
        v = result.variants[i]
        ax.semilogy(t, norm, lw=1, label=f"#{i}: $\\omega$ = {v.values['dist.frequency']:.2f}, "
                                         f"$m_e$ = {v.values['arm.me']:.2f}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(r"$|\Delta q|(t)$ [rad]")
    ax.set_title("the five worst variants", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(args.out, "monte_carlo_theorem3.png")
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
