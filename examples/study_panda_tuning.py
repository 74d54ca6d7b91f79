"""Tuning study (issue 28, item 4): Theorem 1 and Slotine-Li on the Franka Panda, gains
tuned by ``fwdstep.tune`` to the smallest tracking error under the URDF's torque limits,
max_t |tau_i(t)| <= effort_i for every joint.  docs/design.md shows and discusses the
results.

    MPLBACKEND=Agg python examples/study_panda_tuning.py --out results/panda_tuning
                 [--only theorem1|slotine_li] [--t-final 0.5] [--screen 6] [--iterations 15]

For each law the shipped diagram (diagrams/robots/panda_<law>.yaml) is derived, as data,
into OUT/<law>/panda_<law>_tuning.yaml (written there, so ``fwdstep tune`` can be run on it
alone):

* the gain matrix K = diag([k_arm x 4, k_wrist, k_wrist, k_wrist / 2]) -- the shipped
  diag([40, 40, 40, 40, 4, 4, 2]) at k_arm = 40, k_wrist = 4 -- so that two scalars scale
  the shoulder/elbow and the wrist gains;
* Slotine-Li's arm starts 0.1 rad below q_d(0) = q0 on every joint (``arm.q0: q0 - 0.1``),
  the initial offset panda_theorem1.yaml has (q_d(0) = q0 + 0.1, the arm at q0): both laws
  then start with the same error and the torque limit bounds how hard they may correct it;
* the effort limits read from the URDF (the plant block's ``effort`` parameter, which
  pinocchio reads from each joint's <limit effort=>) as the parameter ``effort``, and a Gain
  block ``usage`` = diag(1 / effort) tau, logged, so the one constraint
  ``max_abs(usage.y) <= 1`` is max_t |tau_i| <= effort_i for every joint i.

The sensitivities run on the compiled backend (``simulation: backend: compiled`` in the derived
diagram; ``--backend numpy`` for the NumPy path, ~30x slower here).

The variables: the reference dynamics' rate (Theorem 1: ``alpha``, every root of (2) at
-alpha; Slotine-Li: ``Lambda``), k_arm and k_wrist; the objective rms_error_norm (RMS over
the run of |q - q_d|).  Every step is logged (``log_every: 1``): objectives and constraints
are evaluated on the logged samples, and with the shipped 10 ms the torque peak of the
tuned Theorem 1 fell between two samples (1.098 x effort at t = 5 ms, while the logged
maximum read 1.000).  Results: OUT/<law>/ holds fwdstep tune's files (tune.json,
history.csv, history.png, before_after.png, best.yaml); OUT/summary.json the numbers of
docs/design.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

#: law -> (shipped diagram, its rate parameter and range, gain ranges)
LAWS = {
    "theorem1": ("panda_theorem1.yaml", {"alpha": (1.0, 25.0)}),
    "slotine_li": ("panda_slotine_li.yaml", {"Lambda": (1.0, 20.0)}),
}
GAINS = {"k_arm": (5.0, 200.0), "k_wrist": (0.5, 20.0)}
CONSTRAINT = "max_abs(usage.y) <= 1"


def derived_diagram(law: str, outdir: str, backend: str = "compiled") -> str:
    """Write OUT/<law>/panda_<law>_tuning.yaml (module docstring) and return its path."""
    import fwdstep
    shipped = os.path.join(ROOT, "diagrams", "robots", LAWS[law][0])
    plant = {b.name: b for b in fwdstep.load_diagram(shipped, {"t_final": 0.01}).blocks}["arm"]
    effort = np.asarray(plant.p.effort, dtype=float).reshape(-1).tolist()   # from the URDF
    with open(shipped) as fh:
        doc = yaml.safe_load(fh)
    doc["description"] = (f"{LAWS[law][0]} prepared for tuning under the URDF's torque limits "
                          "(examples/study_panda_tuning.py):\nK = diag([k_arm x 4, k_wrist, "
                          "k_wrist, k_wrist/2]); usage = tau / effort per joint.\n\n"
                          + doc["description"])
    params = doc["parameters"]
    assert params["K"] == "diag([40, 40, 40, 40, 4, 4, 2])", params["K"]
    params["k_arm"], params["k_wrist"] = 40.0, 4.0
    params["K"] = "diag([k_arm, k_arm, k_arm, k_arm, k_wrist, k_wrist, k_wrist/2])"
    params["effort"] = effort
    if law == "slotine_li":
        doc["blocks"]["arm"]["q0"] = "q0 - 0.1"
    doc["blocks"]["usage"] = {"type": "Gain", "gain": "diag(1/effort)"}
    doc["connections"] = [c + ", usage.u" if c.replace(" ", "").startswith("tau.y->") else c
                          for c in doc["connections"]]
    doc["log"].append({"signal": "usage.y", "label": "$\\tau_i / \\tau_{\\max,i}$",
                       "components": [f"joint {i + 1}" for i in range(7)]})
    doc["plots"]["torque_usage"] = ["usage.y"]
    doc["simulation"]["backend"] = backend      # where fwdstep.tune runs the sensitivities
    folder = os.path.join(outdir, law)
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, f"panda_{law}_tuning.yaml")
    with open(path, "w") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, width=100)
    return path


def study(law: str, outdir: str, t_final: float, screen: int, iterations: int,
          backend: str = "compiled") -> dict:
    import fwdstep
    path = derived_diagram(law, outdir, backend)
    vary = dict(LAWS[law][1], **GAINS)
    started, cpu = time.time(), time.process_time()
    result = fwdstep.tune(path, vary, "rms_error_norm", [CONSTRAINT],
                          overrides={"t_final": t_final, "log_every": 1}, screen=screen, starts=1,
                          max_iterations=iterations, outdir=os.path.join(outdir, law, "tune"),
                          progress=lambda line: print(f"{law}: {line}", flush=True))
    with_sens = [e.seconds for e in result.history if e.gradient is not None]
    plain = [e.seconds for e in result.history if e.gradient is None]
    return {"diagram": os.path.relpath(path, outdir), "t_final": t_final, "vary": vary,
            "backend": backend,
            "constraint": CONSTRAINT,
            "before": {"values": result.initial, "rms_error_norm": result.initial_cost,
                       "max_usage": result.initial_constraints[0]},
            "after": {"values": result.best, "rms_error_norm": result.best_cost,
                      "max_usage": result.best_constraints[0]},
            "runs": result.runs, "message": result.message,
            "seconds_per_plain_run": float(np.median(plain)) if plain else None,
            "seconds_per_run_with_sensitivities": float(np.median(with_sens)) if with_sens
            else None,
            "wall_seconds": round(time.time() - started, 1),
            "cpu_seconds": round(time.process_time() - cpu, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="results/panda_tuning")
    ap.add_argument("--only", choices=sorted(LAWS), action="append")
    ap.add_argument("--t-final", type=float, default=0.5)
    ap.add_argument("--screen", type=int, default=6)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--backend", choices=("compiled", "numpy"), default="compiled",
                    help="where the sensitivities run (the plain screening runs: NumPy)")
    args = ap.parse_args(argv)
    summary_path = os.path.join(args.out, "summary.json")
    summary = {}
    if os.path.exists(summary_path):
        with open(summary_path) as fh:
            summary = json.load(fh)
    for law in args.only or sorted(LAWS):
        summary[law] = study(law, args.out, args.t_final, args.screen, args.iterations,
                             args.backend)
        os.makedirs(args.out, exist_ok=True)
        with open(summary_path, "w") as fh:
            json.dump(summary, fh, indent=1)
        print(json.dumps(summary[law], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
