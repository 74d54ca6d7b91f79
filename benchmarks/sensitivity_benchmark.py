"""Forward sensitivities on the compiled backend (issue 28's cost target: p sensitivities
<= (1 + 0.5 p) x one compiled run, for the two-link diagrams).

For theorem1.yaml and slotine_li.yaml (10 s unless --t-final), CPU-time medians of
--repeats interleaved repeats in this one process, everything compiled beforehand, each
side measured alike:

* (a) integration: ``fwdstep.run.simulate.run`` of a prepared ``CompiledBackend`` (one
  run) against the same of a prepared ``SensitivityBackend`` integrating (x, S) with
  p = 1, 2, 4 parameters;
* (b) whole call, same values: ``simulate(d, backend="compiled")`` against
  ``simulate(d, backend="compiled", sensitivities=[...])`` on the same diagram every time;
* (c) whole call, a new value at every call (what a tuning's evaluations do): both sides
  get a diagram loaded beforehand with another value of the first parameter each call
  (neither the plain stage nor the sensitivities' set-up has seen it); the sensitivities'
  set-up finds how the parameters reach the blocks (the loader's light path, 4 moved
  evaluations per column) and rebinds the memoised variational stage;
* the NumPy path's sensitivities (``backend="numpy"``), once each for p = 1 and 4 (slow).

Run: ``python benchmarks/sensitivity_benchmark.py [--t-final 10] [--repeats 15]``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import fwdstep  # noqa: E402
from fwdstep.analysis import compiled_sensitivity as cs  # noqa: E402
from fwdstep.analysis.sensitivity import loader_derivative, resolve_parameter  # noqa: E402
from fwdstep.compiled.driver import CompiledBackend  # noqa: E402
from fwdstep.run.events import plan_events  # noqa: E402
from fwdstep.run.simulate import run  # noqa: E402

CASES = {
    "theorem1.yaml": ["alpha", "Gamma", "K[0,0]", "a1"],
    "slotine_li.yaml": ["Lambda", "Gamma", "K[0,0]", "A[0]"],
}


def _resolved(d, params):
    out, P = [], 0
    for text in params:
        p = resolve_parameter(d, text)
        p.columns = slice(P, P + len(p.elements))
        P += len(p.elements)
        out.append(p)
    return out, P


def _cpu(fn) -> float:
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


def measure(name: str, params: list, t_final: float, repeats: int, numpy_runs: bool) -> list:
    path = os.path.join(ROOT, "diagrams", name)
    d = fwdstep.load_diagram(path, {"t_final": t_final})
    cfg = d.spec.simulation
    counts = (1, 2, 4)
    prepared = {}
    for p in counts:
        res, P = _resolved(d, params[:p])
        loaded = loader_derivative(d, res, P)
        prepared[p] = (cs.variational_stage(d, loaded.p, P), loaded.x0)

    def plain_run():
        b = CompiledBackend(d, plan_events(d, cfg.step, cfg.n_steps))
        return _cpu(lambda: run(d, b))

    def sens_run(p):
        st, S0 = prepared[p]
        b = cs.SensitivityBackend(d, plan_events(d, cfg.step, cfg.n_steps), st, S0)
        return _cpu(lambda: run(d, b))

    def call(dd, p):
        if p == 0:
            return _cpu(lambda: fwdstep.simulate(dd, backend="compiled"))

        def go():
            r = fwdstep.simulate(dd, backend="compiled", sensitivities=params[:p])
            assert r.backend == "compiled" and not r.notes, r.notes
        return _cpu(go)

    # (c): another value of the first parameter at every call, loaded beforehand
    v0 = resolve_parameter(d, params[0]).value
    fresh = iter([fwdstep.load_diagram(path, {"t_final": t_final, params[0]: (
        v0 * (1 + 1e-3 * (i + 1))).tolist()}) for i in range(5 * (repeats + 1))])

    plain_run(), call(d, 0), call(next(fresh), 0)        # compile everything first
    for p in counts:
        sens_run(p), call(d, p), call(next(fresh), p)
    runs = {key: [] for key in ("run", "same0", "new0")}
    for p in counts:
        runs[f"run{p}"], runs[f"same{p}"], runs[f"new{p}"] = [], [], []
    for _ in range(repeats):                       # interleaved
        runs["run"].append(plain_run())
        runs["same0"].append(call(d, 0))
        runs["new0"].append(call(next(fresh), 0))
        for p in counts:
            runs[f"run{p}"].append(sens_run(p))
            runs[f"same{p}"].append(call(d, p))
            runs[f"new{p}"].append(call(next(fresh), p))
    med = {k: statistics.median(v) for k, v in runs.items()}
    rows = [(name, "compiled run (no sensitivities)", med["run"], 1.0, med["same0"], 1.0,
             med["new0"], 1.0, "")]
    for p in counts:
        rows.append((name, f"p = {p} ({', '.join(params[:p])})", med[f"run{p}"],
                     med[f"run{p}"] / med["run"], med[f"same{p}"],
                     med[f"same{p}"] / med["same0"], med[f"new{p}"],
                     med[f"new{p}"] / med["new0"], f"<= {1 + 0.5 * p:g}"))
    if numpy_runs:
        for p in (1, 4):
            t = _cpu(lambda: fwdstep.simulate(d, backend="numpy", sensitivities=params[:p]))
            rows.append((name, f"numpy path, p = {p}", float("nan"), float("nan"), t,
                         t / med["same0"], float("nan"), float("nan"), ""))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--no-numpy", action="store_true", help="skip the NumPy path (slow)")
    a = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    rows = []
    for name, params in CASES.items():
        rows += measure(name, params, a.t_final, a.repeats, not a.no_numpy)
    print(f"t_final {a.t_final:g} s, CPU-time medians of {a.repeats} interleaved repeats; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'diagram':16} {'what':36} {'(a) integration':>17} {'(b) same values':>17} "
          f"{'(c) new value':>17}  target")
    for name, what, ta, ra, tb, rb, tc, rc, target in rows:
        print(f"{name:16} {what:36} {ta * 1e3:7.2f}ms {ra:5.2f}x {tb * 1e3:7.2f}ms {rb:5.2f}x "
              f"{tc * 1e3:7.2f}ms {rc:5.2f}x  {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
