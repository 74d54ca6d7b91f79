"""From a notebook (or this script): load, run, sweep, plot, compare, report.

    python examples/notebook_walkthrough.py          # writes out/walkthrough/

Every cell below works as is in Jupyter: figures are matplotlib Figure objects made without
pyplot, so the notebook's backend is never switched (display one by leaving it last in a
cell), and a Result shows a short summary table (``_repr_html_``).
"""
import os

import numpy as np

import fwdstep
from fwdstep.views.drawing import draw_diagram
from fwdstep.views.report import write_report
from fwdstep.structure.spec import load_spec

OUT = os.path.join("out", "walkthrough")
DIAGRAM = "diagrams/theorem1.yaml"

# --- load: parse, validate and compile; --set is the overrides dict
d = fwdstep.load_diagram(DIAGRAM, overrides={"t_final": 6})
draw_diagram(d, os.path.join(OUT, "theorem1_diagram.svg"))        # the diagram as a picture

# --- run
r = fwdstep.simulate(d)
print(r.status, r.metrics())
html = r._repr_html_()                      # what a notebook shows for `r`
r.save(os.path.join(OUT, "alpha4"))           # result.npz + summary.json (+ manifest)

# --- plot: the diagram's figures, or any signals in one panel; no pyplot involved
figures = r.plot()                           # {"tracking_error": Figure, "torque": ..., ...}
figures["tracking_error"].savefig(os.path.join(OUT, "tracking_error.pdf"))
r.plot(["adapt.theta_hat", "truth.y"]).savefig(os.path.join(OUT, "estimates.png"), dpi=120)
r.plot("e.y", scale="log").savefig(os.path.join(OUT, "error_log.svg"))

# --- load a saved run back: it plots and compares like a fresh one
back = fwdstep.load_result(os.path.join(OUT, "alpha4"))
assert np.array_equal(back["e.y"], r["e.y"]) and back.metrics() == r.metrics()

# --- sweep: variants of one diagram run as one batch (fwdstep sweep does this from the CLI)
specs = [load_spec(DIAGRAM, {"t_final": 6, "alpha": a}) for a in (3, 4, 6)]
batch = fwdstep.simulate(fwdstep.compile_batch(specs))
for a, m in zip((3, 4, 6), batch.metrics()):
    print(f"alpha = {a}: final |e| = {m['final_error_norm']:.2e}")
batch.save(os.path.join(OUT, "alpha_sweep"))
batch.plot("e.y").savefig(os.path.join(OUT, "sweep_error.png"))   # |e| of every variant

# --- compare: saved runs or batch variants (DIR@k), differences against the first
c = fwdstep.compare([os.path.join(OUT, "alpha4"), os.path.join(OUT, "alpha_sweep@2")])
for row in c.table:
    print(row["run"], row["final_error_norm"], row["max |diff e.y|"])
c.save(os.path.join(OUT, "compare"))

# --- a saved sweep (fwdstep sweep -o DIR does the same): its variants compare as runs, SWEEP@k
sweep_dir = os.path.join(OUT, "ell_sweep")
sw = fwdstep.run_sweep(DIAGRAM, grid={"ell": [1, 3]}, overrides={"t_final": 6},
                       outdir=sweep_dir, workers=1, force=True)   # replaces an earlier run
sw.write(sweep_dir)                           # sweep.csv, sweep.png (|Δq| [rad] on its axes)
c = fwdstep.compare([f"{sweep_dir}@0,1", os.path.join(OUT, "alpha4")])
print([run.label for run in c.runs])          # ['ell_sweep@0 (ell=1)', 'ell_sweep@1 (ell=3)', ...]

# --- report: one self-contained HTML page per run directory
print("wrote", write_report(os.path.join(OUT, "alpha4")))
