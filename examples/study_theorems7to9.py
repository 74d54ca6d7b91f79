"""Study of Theorems 7-9: learning 1, 2, 3 unknown disturbance frequencies over a long horizon.

One command:  python examples/study_theorems7to9.py [--t-final 60] [--jobs 2]
Writes docs/figures/theorem7-9_*.png and docs/figures/theorem7-9_results.json; the numbers
are quoted in docs/theorems7-9.md.  Cases (same arm, q_d and multi-sine disturbance of
amplitude 5 N m per frequency and joint):
  thm9_n1/n2/n3   diagrams/theorem9.yaml with n* = 1, 2, 3 (n* = 2 is Theorem 8)
  thm9_n*_fixed   the same with gamma_i = 1e-12 (theta_hat frozen at 0: no frequency learning)
  thm7            diagrams/theorem7.yaml (one frequency)
  thm6_n*         diagrams/theorem6.yaml on the same disturbance (no frequency learning)
  sl_n*           diagrams/slotine_li_disturbed.yaml on the same disturbance
  thm9_under      n* = 1 assumed, 2 frequencies present (more frequencies than n*)
"""
import argparse
import json
import os
import sys
from multiprocessing import Pool

import numpy as np

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, ROOT)

OMEGAS = {1: [3.0], 2: [2.0, 4.0], 3: [2.0, 3.0, 4.5]}
GAMMAS = {1: [2e3], 2: [1.6e5, 4.3e3], 3: [4.6e7, 1.7e6, 2.2e4]}   # as shipped (theorem8/9.yaml)
AMP = 5.0


def cases():
    out = {}
    for n in (1, 2, 3):
        common = {"nstar": n, "omegas": OMEGAS[n]}
        out[f"thm9_n{n}"] = ("theorem9.yaml", dict(common, gammas=GAMMAS[n]))
        out[f"thm9_n{n}_fixed"] = ("theorem9.yaml", dict(common, gammas=1e-12))
        sine = {"dist_amplitude": [[AMP] * n] * 2, "dist_frequency": [OMEGAS[n]] * 2,
                "dist_phase": 0, "q0": [0, 0], "qd_frequency": [0.5, 0.4],
                "theta0": [1, 0.5, 0.5, 0]}
        out[f"thm6_n{n}"] = ("theorem6.yaml", sine)
        out[f"sl_n{n}"] = ("slotine_li_disturbed.yaml", sine)
    out["thm7"] = ("theorem7.yaml", {"omega": 3.0, "gamma": 2e3})
    out["thm9_under"] = ("theorem9.yaml", {"nstar": 1, "omegas": [3.0], "gammas": [2e3],
                                           "dist_omegas": [2.0, 3.0], "n_dist": 2})
    return out


def run(item):
    name, (diagram, overrides), t_final = item
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.run.simulate import simulate
    from fwdstep.structure.spec import load_spec
    spec = load_spec(os.path.join(ROOT, "diagrams", diagram), overrides)
    spec.simulation.t_final = t_final
    spec.simulation.step = 0.005 if diagram.startswith(("theorem7", "theorem9")) else 0.002
    spec.simulation.log_every = 10 if spec.simulation.step == 0.005 else 25
    r = simulate(compile_spec(spec))
    try:
        err = np.asarray(r["qds.dq"])
    except KeyError:
        err = np.asarray(r["dq.y"])
    t = np.asarray(r.t)
    tail = t >= 0.8 * t[-1]
    out = {"diagram": diagram, "overrides": overrides, "t": t.tolist()[::4],
           "err_norm": np.linalg.norm(err, axis=1).tolist()[::4],
           "final_err": float(np.linalg.norm(err[-1])),
           "tail_max_err": float(np.max(np.linalg.norm(err[tail], axis=1))),
           "tail_rms_err": float(np.sqrt(np.mean(np.sum(err[tail] ** 2, axis=1))))}
    if "theta.theta_hat" in r.names:
        th = np.asarray(r["theta.theta_hat"]).reshape(len(t), -1)
        out["theta_hat"] = th.tolist()[::4]
        out["theta_final"] = th[-1].tolist()
        out["theta_true"] = np.atleast_1d(np.asarray(r["theta_true.theta"])[-1]).tolist()
    return name, out


def plots(results, outdir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for ax, n in zip(axes, (1, 2, 3)):
        for key, label in ((f"thm9_n{n}", "Theorem 9 (learning)"),
                           (f"thm9_n{n}_fixed", "Theorem 9, no learning"),
                           (f"thm6_n{n}", "Theorem 6"), (f"sl_n{n}", "Slotine-Li")):
            if key in results:
                ax.semilogy(results[key]["t"], results[key]["err_norm"], label=label, lw=0.8)
        ax.set_ylabel(f"|q - q_d|, n* = {n}")
        ax.legend(fontsize=7)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(os.path.join(outdir, "theorem7-9_tracking_error.png"), dpi=110)
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.5))
    for ax, key in zip(axes, ("thm7", "thm9_n1", "thm9_n2", "thm9_n3")):
        res = results.get(key)
        if not res or "theta_hat" not in res:
            continue
        th = np.asarray(res["theta_hat"])
        for i in range(th.shape[1]):
            line, = ax.plot(res["t"], th[:, i], lw=0.8, label=f"theta_hat_{i + 1}")
            ax.axhline(res["theta_true"][i], color=line.get_color(), ls="--", lw=0.6)
        ax.set_title(key)
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(outdir, "theorem7-9_theta_hat.png"), dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=60.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=None)
    args = ap.parse_args()
    todo = [(k, v, args.t_final) for k, v in cases().items()
            if args.only is None or k in args.only]
    outdir = os.path.join(ROOT, "docs", "figures")
    os.makedirs(outdir, exist_ok=True)
    with Pool(args.jobs) as pool:
        results = dict(pool.map(run, todo))
    path = os.path.join(outdir, "theorem7-9_results.json")
    old = json.load(open(path)) if os.path.exists(path) else {}
    old.update(results)
    with open(path, "w") as f:
        json.dump(old, f)
    plots(old, outdir)
    print(f"{'case':16s} {'final |e|':>10s} {'tail max':>10s} {'tail rms':>10s}  theta_hat vs theta")
    for k, v in old.items():
        th = ""
        if "theta_final" in v:
            th = (np.array2string(np.asarray(v["theta_final"]), precision=3) + " vs " +
                  np.array2string(np.asarray(v["theta_true"]), precision=3))
        print(f"{k:16s} {v['final_err']:10.2e} {v['tail_max_err']:10.2e} "
              f"{v['tail_rms_err']:10.2e}  {th}")


if __name__ == "__main__":
    main()
