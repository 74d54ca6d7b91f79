"""Whole-process cost of the main job: ``fwdstep run diagrams/theorem1.yaml`` against a
hand-written script of the same closed loop (issue 22, item 9).

Each repeat runs, in fresh processes and interleaved (so the machine's drift hits both):
  hand         python: import numpy, the RK4 loop of benchmarks/hand_loops.theorem1 with the
               diagram's numbers written out, np.savez of the logged error
  hand+plots   the same, then three matplotlib figures saved as PNG (what the run writes)
  run          fwdstep run diagrams/theorem1.yaml --no-plots -q
  run+plots    fwdstep run diagrams/theorem1.yaml -q (its three figures)
and reports the median CPU-time ratios (children's user+sys) run/hand and run+plots/hand+plots.
The children run without ``PYTHONDONTWRITEBYTECODE`` (set on some machines): a user's
installation keeps its compiled bytecode, and recompiling fwdstep's ~60 modules from source
in every process (~0.15 s) would measure that setting, not fwdstep.

    python benchmarks/whole_process.py [--repeats 7]
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

HAND = r'''
import sys, numpy as np
sys.path.insert(0, {bench!r})
import hand_loops
T, a1, a2, b1, b2 = 10.0, 0.5, -0.4, 0.2, -0.1
coef = [[b1, a1 / T], [b2, a2 / T]]            # ell = 2: q_d,i(t) = b_i + a_i t / T
x, log = hand_loops.theorem1(10.0, 0.002, 5, 2, 4.0, 50.0, 2.0, [1, 0.5, 0.5, 0], coef, 0.0)
t = np.arange(len(log)) * 0.01
np.savez({out!r} + "/hand.npz", t=t, e=np.asarray(log))
if {plots}:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    for name in ("tracking_error", "parameter_estimates", "torque"):
        fig, ax = plt.subplots(2, 1, figsize=(8, 6))
        ax[0].plot(t, np.asarray(log)); ax[1].semilogy(t, np.abs(np.asarray(log)) + 1e-300)
        ax[0].set_title(name); fig.savefig({out!r} + "/" + name + ".png", dpi=100)
        plt.close(fig)
'''


def cpu_of(cmd: list, cwd: str) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run(cmd, cwd=cwd, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, env={**env, "MPLBACKEND": "Agg"})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    out = tempfile.mkdtemp(prefix="fwdstep-whole-")
    bench = os.path.join(ROOT, "benchmarks")
    cmds = {
        "hand": [sys.executable, "-c", HAND.format(bench=bench, out=out, plots=False)],
        "hand+plots": [sys.executable, "-c", HAND.format(bench=bench, out=out, plots=True)],
        "run": [sys.executable, os.path.join(ROOT, "cli.py"), "run", "diagrams/theorem1.yaml",
                "--no-plots", "-q", "--force", "-o", os.path.join(out, "run")],
        "run+plots": [sys.executable, os.path.join(ROOT, "cli.py"), "run",
                      "diagrams/theorem1.yaml", "-q", "--force", "-o",
                      os.path.join(out, "plots")],
    }
    for cmd in cmds.values():                       # warm the file cache and numba's
        cpu_of(cmd, ROOT)
    times = {k: [] for k in cmds}
    for _ in range(args.repeats):
        for k, cmd in cmds.items():
            times[k].append(cpu_of(cmd, ROOT))
    med = {k: statistics.median(v) for k, v in times.items()}
    r1 = statistics.median(a / b for a, b in zip(times["run"], times["hand"]))
    r2 = statistics.median(a / b for a, b in zip(times["run+plots"], times["hand+plots"]))
    r3 = statistics.median(a / b for a, b in zip(times["run+plots"], times["hand"]))
    print("median CPU s: " + ", ".join(f"{k} {v:.2f}" for k, v in med.items()))
    print(f"run / hand (no plots): {r1:.2f}x   (target <= 1.05)")
    print(f"run+plots / hand+plots: {r2:.2f}x   (target <= 2); run+plots / hand: {r3:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
