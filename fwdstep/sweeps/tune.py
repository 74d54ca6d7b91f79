"""Gain tuning: gradient-based optimisation of a diagram's parameters.

    fwdstep tune D --vary K=10:200 --vary Lambda=1:50 --minimize rms_error_norm \\
                   --subject-to "max_abs(tau.y) <= 87" -o DIR

``tune`` minimises an objective (``fwdstep.results.objectives``: a metric such as
``rms_error_norm`` or ``FUNCTION(SIGNAL)``) over box bounds, subject to objectives bounded above
or below.  Every evaluation is one run with forward sensitivities
(``fwdstep.sensitivities``), which gives the objective, the constraints and their exact
gradients together.  The search:

1. *screening*: ``screen`` points of a space-filling design over the box (``--design``,
   scrambled Sobol by default: ``fwdstep.sweeps.sampling.unit_points``), plus the diagram's
   own values when they lie inside, each one plain run (no sensitivities); the tuned values
   are the best point evaluated inside the box (the diagram's own values outside it are
   the 'before', never the answer);
2. *local searches* from the ``starts`` best screened points (feasible first, then least
   violation): L-BFGS-B on the box without constraints, SLSQP with them, in coordinates
   scaled to [0, 1] per parameter and the objective scaled by its value at the start; each
   search stops after ``max_iterations`` iterations or when it converges.

A variable is a top-level parameter (``alpha``), one entry of an array parameter
(``K[0,0]``) or a block parameter path (``Ks.gain``), scalar each; several entries of one
array are set together.  A run that fails (diverges) is given a large objective and no
gradient, so the line search steps back.

Written to DIR: ``history.csv`` (every evaluation: phase, start, parameters, objective,
constraints, gradient norm, feasibility), ``history.png`` (objective per evaluation, best so
far, and the parameters' path), ``tune.json`` (bounds, settings, the best point, before and
after numbers, counts), ``best.yaml`` (the diagram file with the tuned parameter values
written in place of the old ones, comments kept; values the text edit cannot place are
listed in ``best_overrides.json`` as ``--set`` values), ``before_after.png`` (the
objective's and constraints' signals of the original and the tuned diagram) and
``report.html`` (``fwdstep.views.report``: before against after -- parameters, objective,
constraints -- the runs and both figures, one self-contained page; ``fwdstep report DIR``
writes it again).
"""
from __future__ import annotations

import csv
import json
import math
import os
import re
import time
from dataclasses import dataclass, field

import numpy as np

from fwdstep.core.errors import ConfigError, DiagramError, FwdstepError
from fwdstep.results.objectives import objective, parse_constraint, parse_objective

FILES = ("history.csv", "history.png", "tune.json", "best.yaml", "before_after.png",
         "report.html")
#: the objective given to the optimiser for a run that failed (times the scale)
FAILED_RUN_PENALTY = 1e3
_VARY = re.compile(r"^\s*(?P<name>[^=]+?)\s*=\s*(?P<lo>[-+0-9.eE]+)\s*:\s*(?P<hi>[-+0-9.eE]+)"
                   r"\s*$")


def parse_vary(items) -> dict:
    """['K=10:200', ...] -> {'K': (10.0, 200.0), ...}."""
    out = {}
    for text in items or []:
        m = _VARY.match(text)
        if not m:
            raise ConfigError(f"--vary '{text}' must read NAME=LOW:HIGH (e.g. K=10:200, "
                              "'K[0,0]=10:200', Ks.gain=1:5)")
        lo, hi = float(m.group("lo")), float(m.group("hi"))
        if not lo < hi:
            raise ConfigError(f"--vary '{text}': LOW must be below HIGH")
        if m.group("name") in out:      # (the last bounds won, silently)
            first = out[m.group("name")]
            raise ConfigError(f"--vary '{text}': {m.group('name')} is already varied over "
                              f"{first[0]:g}:{first[1]:g}; give each name once")
        out[m.group("name")] = (lo, hi)
    if not out:
        raise ConfigError("tune needs at least one --vary NAME=LOW:HIGH")
    return out


@dataclass
class Evaluation:
    index: int
    phase: str                  # "start" (the diagram as given), "screen", "search"
    start: int                  # the local search's number (-1 outside searches)
    values: np.ndarray
    cost: float
    constraints: list           # objective values of the constraints
    gradient: np.ndarray | None
    status: str
    feasible: bool
    seconds: float
    backend: str = ""           # the backend that ran it (a fallback to numpy says so)


@dataclass
class TuneResult:
    """What ``tune`` found: ``best`` (name -> value), ``best_cost``, ``initial`` (the
    diagram's own values, name -> value) and its cost, every ``Evaluation`` in
    ``history``, ``runs`` (plain runs, runs with sensitivities), the files written;
    ``interrupted``: the signal that stopped the search early (its best point so far is
    reported and written; the CLI then exits 128 + that number)."""
    names: list
    bounds: list
    best: dict
    best_cost: float
    best_constraints: list
    initial: dict
    initial_cost: float
    initial_constraints: list
    history: list = field(default_factory=list)
    runs: dict = field(default_factory=dict)
    files: list = field(default_factory=list)
    message: str = ""
    #: the signal that stopped the search (2 for Ctrl-C), 0 if it ran to its end
    interrupted: int = 0


class _Problem:
    """The diagram at any point of the variables: loading, running, the objective."""

    def __init__(self, path, vary, minimize, subject_to, overrides, plugins, backend=None):
        from fwdstep.structure.compiler import load_diagram
        self.path = path
        self.base = dict(overrides or {})
        self.names = list(vary)
        self.bounds = np.array([vary[n] for n in self.names], dtype=float)
        parse_objective(minimize)
        self.minimize = minimize
        self.constraints = [parse_constraint(c) for c in (subject_to or [])]
        self.plugins = plugins
        self.backend = backend              # None: each diagram's own simulation.backend
        self.d0 = load_diagram(path, self.base, plugins=plugins)
        from fwdstep.analysis.sensitivity import resolve_parameter
        self.params = [resolve_parameter(self.d0, n) for n in self.names]
        for p in self.params:
            if len(p.elements) != 1:
                raise ConfigError(f"--vary {p.text}: the parameter has {p.value.size} values; "
                                  f"vary one entry, e.g. {p.text}[0" + ",0" * (p.value.ndim - 1)
                                  + "]", file=self.d0.file)
        self.x0 = np.array([p.value.reshape(-1)[p.elements[0]] for p in self.params])
        self.history: list = []
        self.plain_runs = 0
        self.sensitivity_runs = 0
        self.failures: list = []        # why evaluations failed (load or run errors)

    def overrides(self, x) -> dict:
        out = dict(self.base)
        arrays: dict = {}
        for p, v in zip(self.params, x):
            arr = arrays.setdefault(p.name, p.value.copy())
            arr.reshape(-1)[p.elements[0]] = float(v)
        for name, arr in arrays.items():
            out[name] = arr.tolist()
        return out

    def diagram(self, x):
        from fwdstep.structure.compiler import load_diagram
        return load_diagram(self.path, self.overrides(x), plugins=self.plugins)

    def evaluate(self, x, phase: str, start: int = -1, gradient: bool = True) -> Evaluation:
        from fwdstep.analysis.sensitivity import sensitivities
        from fwdstep.run.simulate import simulate
        wall = time.perf_counter()
        status, grad, cons = "ok", None, []
        try:
            # the diagram loaded at the start; a value of the box it refuses (an expression
            # such as sqrt(K - 1), a matrix that is no longer positive definite) is a failed
            # point of the search, as a diverging run is: it aborted the whole tuning and
            # lost every evaluation made so far
            d = self.diagram(x)
        except DiagramError as exc:
            d, status = None, "invalid"
            self.failures.append(f"at {self._point(x)}: {exc}")
        try:
            if d is None:
                r = None
            elif gradient:
                r = sensitivities(d, self.names, backend=self.backend)
                self.sensitivity_runs += 1
            else:
                r = simulate(d, backend=self.backend)
                self.plain_runs += 1
        except FwdstepError as exc:
            r, status = getattr(exc, "result", None), "error"
            self.failures.append(f"at {self._point(x)}: {exc}")
            if gradient:
                self.sensitivity_runs += 1
            else:
                self.plain_runs += 1
        if r is not None and r.status != "ok":
            status = r.status
        if status == "ok":
            cost, gcost = self._value(r, self.minimize, gradient)
            rows = [self._value(r, expr, gradient) for expr, _, _ in self.constraints]
            cons = [v for v, _ in rows]
            if gradient:
                grad = np.vstack([gcost] + [g for _, g in rows])
            if not np.isfinite(cost):
                status = "not finite"
        if status != "ok":
            cost, cons = math.inf, [math.nan] * len(self.constraints)
        feasible = status == "ok" and all(
            (v <= b if op == "<=" else v >= b) for v, (_, op, b) in zip(cons, self.constraints))
        ev = Evaluation(len(self.history), phase, start, np.array(x, dtype=float), float(cost),
                        cons, grad, status, feasible, time.perf_counter() - wall,
                        getattr(r, "backend", "") or "")
        self.history.append(ev)
        return ev

    def _point(self, x) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in zip(self.names, x))

    def _value(self, r, expr, gradient):
        if not gradient:
            return objective(r, expr), None
        v, g = objective(r, expr, gradient=True)
        return v, np.array([float(g[n]) for n in self.names])

    def violation(self, ev: Evaluation) -> float:
        if ev.status != "ok":
            return math.inf
        total = 0.0
        for v, (_, op, b) in zip(ev.constraints, self.constraints):
            if not np.isfinite(v):      # max(0.0, nan) is 0.0: a NaN constraint counted as met
                return math.inf
            gap = (v - b) if op == "<=" else (b - v)
            total += max(0.0, gap) / max(abs(b), 1e-12)
        return total


def tune(path: str, vary: dict, minimize: str, subject_to=(), *, overrides=None,
         screen: int = 16, starts: int = 3, design: str = "sobol", seed: int = 0,
         max_iterations: int = 30, outdir: str | None = None, progress=None,
         plugins=None, figures: bool = True, backend: str | None = None) -> TuneResult:
    """Tune the parameters ``vary`` ({name: (low, high)}) of the diagram file ``path`` (see
    the module docstring).  ``progress(text)`` receives one line per evaluation.  With
    ``outdir``, the files of the module docstring are written there (``FILES``).
    ``backend`` ("numpy" or "compiled"; None: the diagram's own ``simulation.backend``) runs
    every evaluation, plain runs and runs with sensitivities alike."""
    prob = _Problem(path, vary, minimize, subject_to, overrides, plugins, backend)
    lo, hi = prob.bounds[:, 0], prob.bounds[:, 1]
    span = hi - lo
    n = len(prob.names)

    def say(ev: Evaluation, best: float):
        if progress is not None:
            shown = ", ".join(f"{k}={v:.5g}" for k, v in zip(prob.names, ev.values))
            cons = "".join(f"  {expr}={v:.4g}" for v, (expr, _, _) in
                           zip(ev.constraints, prob.constraints))
            progress(f"[{ev.index + 1:3d}] {ev.phase:6s} {shown}  {minimize}={ev.cost:.6g}"
                     f"{cons}{'' if ev.feasible else '  (infeasible)'}  best={best:.6g}")

    def best_so_far() -> float:
        ok = [e.cost for e in prob.history if e.feasible]
        return min(ok) if ok else math.inf

    # the diagram as given
    start_ev = prob.evaluate(prob.x0, "start", gradient=False)
    say(start_ev, best_so_far())
    interrupted = None
    try:
        _search(prob, lo, hi, span, n, screen, starts, design, seed, max_iterations, say,
                best_so_far)
    except KeyboardInterrupt as exc:        # Ctrl-C: keep what was evaluated
        interrupted = exc
    # the answer lies in the box asked for: the diagram's own values outside it (a start
    # better than every point inside was reported as the tuned one, out of bounds)
    inside = [e for e in prob.history if _inside(e, lo, hi)]
    feasible = [e for e in inside if e.feasible]
    pool = feasible or [e for e in inside if e.status == "ok"]
    if not pool:
        if interrupted is not None and not inside:
            raise interrupted                   # (nothing inside the bounds was run yet)
        first = f" (first: {prob.failures[0]})" if prob.failures else ""
        raise ConfigError(f"every tuning run failed; narrow the --vary ranges{first}",
                          file=path)
    best = min(pool, key=lambda e: (prob.violation(e), e.cost))
    result = TuneResult(
        names=prob.names, bounds=prob.bounds.tolist(),
        best=dict(zip(prob.names, best.values.tolist())), best_cost=best.cost,
        best_constraints=list(best.constraints),
        initial=dict(zip(prob.names, prob.x0.tolist())), initial_cost=start_ev.cost,
        initial_constraints=list(start_ev.constraints), history=prob.history,
        runs={"plain": prob.plain_runs, "with_sensitivities": prob.sensitivity_runs,
              "total": prob.plain_runs + prob.sensitivity_runs},
        message="; ".join(m for m in (
            "" if interrupted is None else
            f"{getattr(interrupted, 'reason', 'interrupted by the user')} after "
            f"{len(prob.history)} evaluations: the best point evaluated so far is reported",
            "" if feasible else "no evaluated point satisfies every constraint; the least "
                                "violating one is reported",
            "" if not prob.failures else
            f"{len(prob.failures)} evaluation(s) failed (first {prob.failures[0]})") if m),
        interrupted=0 if interrupted is None else int(getattr(interrupted, "signum", 2)))
    if outdir is not None:
        result.files = write_tune(prob, result, outdir, figures)
    return result


def _inside(ev: Evaluation, lo, hi) -> bool:
    return bool(np.all(ev.values >= lo) and np.all(ev.values <= hi))


def _search(prob, lo, hi, span, n, screen, starts, design, seed, max_iterations, say,
            best_so_far) -> None:
    """Screening, then local searches from the best screened points (module docstring)."""
    from scipy.optimize import minimize as scipy_minimize
    from fwdstep.sweeps.sampling import unit_points
    # 1. screening
    points = lo + unit_points(max(int(screen), 0), n, design, seed) * span if screen else \
        np.zeros((0, n))
    for x in points:
        ev = prob.evaluate(x, "screen", gradient=False)
        say(ev, best_so_far())
    candidates = [e for e in prob.history if _inside(e, lo, hi)]
    candidates.sort(key=lambda e: (prob.violation(e), e.cost))
    # 2. local searches (from the diagram's own values brought into the box when nothing
    # inside was screened)
    seeds = candidates[:max(1, int(starts))] or prob.history[:1]
    for k, first in enumerate(seeds):
        scale = abs(first.cost) if np.isfinite(first.cost) and first.cost != 0 else 1.0
        cache: dict = {}

        def at(u, k=k):
            key = tuple(np.round(u, 15))
            if key not in cache:
                x = lo + np.clip(u, 0.0, 1.0) * span
                ev = prob.evaluate(x, "search", k)
                say(ev, best_so_far())
                cache[key] = ev
            return cache[key]

        def fun(u):
            ev = at(u)
            if ev.status != "ok":
                return FAILED_RUN_PENALTY, np.zeros(n)
            return ev.cost / scale, ev.gradient[0] * span / scale

        cons = []
        for i, (_, op, b) in enumerate(prob.constraints):
            sign = 1.0 if op == ">=" else -1.0
            norm = max(abs(b), 1e-12)

            def c_fun(u, i=i, sign=sign, b=b, norm=norm):
                ev = at(u)
                if ev.status != "ok":
                    return -1.0
                return sign * (ev.constraints[i] - b) / norm

            def c_jac(u, i=i, sign=sign, norm=norm):
                ev = at(u)
                if ev.status != "ok":
                    return np.zeros(n)
                return sign * ev.gradient[1 + i] * span / norm

            cons.append({"type": "ineq", "fun": c_fun, "jac": c_jac})
        u0 = np.clip((first.values - lo) / span, 0.0, 1.0)
        box = [(0.0, 1.0)] * n
        with np.errstate(all="ignore"):
            if cons:
                scipy_minimize(fun, u0, jac=True, method="SLSQP", bounds=box, constraints=cons,
                               options={"maxiter": int(max_iterations), "ftol": 1e-10})
            else:
                scipy_minimize(fun, u0, jac=True, method="L-BFGS-B", bounds=box,
                               options={"maxiter": int(max_iterations), "ftol": 1e-12,
                                        "gtol": 1e-8})


# ---------------------------------------------------------------------- outputs
def write_tune(prob: _Problem, result: TuneResult, outdir: str, figures: bool = True) -> list:
    os.makedirs(outdir, exist_ok=True)
    files = [_write_history(prob, os.path.join(outdir, "history.csv"))]
    summary = {
        "diagram": prob.path, "minimize": prob.minimize,
        "subject_to": [f"{e} {op} {b:g}" for e, op, b in prob.constraints],
        "bounds": dict(zip(prob.names, result.bounds)),
        "initial": {"values": result.initial, "cost": _finite(result.initial_cost),
                    "constraints": [_finite(v) for v in result.initial_constraints]},
        "best": {"values": result.best, "cost": _finite(result.best_cost),
                 "constraints": [_finite(v) for v in result.best_constraints]},
        "runs": result.runs, "message": result.message,
        "status": "interrupted" if result.interrupted else "finished",
        "evaluations": len(result.history),
        "wall_time_s": round(sum(e.seconds for e in result.history), 3)}
    path = os.path.join(outdir, "tune.json")
    with open(path, "w") as fh:
        json.dump(summary, fh, indent=1)
    files.append(path)
    files += write_best_yaml(prob, result.best, outdir)
    if figures:
        files.append(history_figure(prob, result, os.path.join(outdir, "history.png")))
        files.append(before_after_figure(prob, result, os.path.join(outdir,
                                                                    "before_after.png")))
    from fwdstep.core.files import atomic_write
    from fwdstep.views.report import report_html
    page = report_html(outdir)              # the page comparing before and after
    report = os.path.join(outdir, "report.html")
    atomic_write(report, lambda fh: fh.write(page.encode()), binary=True)
    files.append(report)
    return files


def _finite(v):
    return float(v) if v is not None and np.isfinite(v) else None


def _write_history(prob: _Problem, path: str) -> str:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["evaluation", "phase", "start"] + prob.names + [prob.minimize] +
                   [e for e, _, _ in prob.constraints] +
                   ["gradient_norm", "status", "feasible", "seconds"])
        for ev in prob.history:
            g = "" if ev.gradient is None else f"{np.linalg.norm(ev.gradient[0]):.6g}"
            w.writerow([ev.index, ev.phase, ev.start] + [f"{v:.10g}" for v in ev.values] +
                       [f"{ev.cost:.10g}"] + [f"{v:.10g}" for v in ev.constraints] +
                       [g, ev.status, int(ev.feasible), f"{ev.seconds:.3f}"])
    return path


def write_best_yaml(prob: _Problem, best: dict, outdir: str) -> list:
    """The diagram file with the tuned values in place.  Top-level parameters written in
    block style are edited in the text (comments and layout stay); otherwise (flow style,
    block parameter paths) the document is written anew with the values replaced (its
    comments are lost).  ``--set`` overrides the tuning was given that are not tuned
    go to best_overrides.json."""
    import yaml
    with open(prob.path, encoding="utf-8") as fh:
        original = fh.read()
    values = prob.overrides([best[n] for n in prob.names])
    tuned = {p.name for p in prob.params}
    text, placed = original, True
    for name in sorted(tuned):
        if "." in name:
            placed = False
            break
        text, ok = _replace_parameter(text, name, values[name])
        if not ok:
            placed = False
            break
    note = ""
    if not placed:
        doc = yaml.safe_load(original)
        for name in tuned:
            value = values[name]
            if "." not in name:
                doc.setdefault("parameters", {})[name] = value
                continue
            *path, key = name.split(".")
            blocks = doc.get("blocks") or {}
            if len(path) == 1 and isinstance(blocks.get(path[0]), dict):
                blocks[path[0]][key] = value
            else:
                raise ConfigError(f"cannot write the tuned value of '{name}' (a block inside "
                                  "a subsystem) into best.yaml; it is in tune.json",
                                  file=prob.path)
        text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
        note = "# (written anew: the original's comments are not kept)\n"
    header = (f"# tuned by 'fwdstep tune' from {os.path.basename(prob.path)}: "
              + ", ".join(f"{n} = {best[n]:.8g}" for n in prob.names) + "\n" + note)
    path = os.path.join(outdir, "best.yaml")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(header + text)
    out = [path]
    rest = {k: v for k, v in prob.base.items() if k not in tuned}
    if rest:
        extra = os.path.join(outdir, "best_overrides.json")
        with open(extra, "w") as fh:
            json.dump({"set": rest}, fh, indent=1, default=str)
        out.append(extra)
    return out


def _yaml_value(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    return repr(float(value))


def _replace_parameter(text: str, name: str, value) -> tuple:
    """Replace ``NAME: ...`` in the top-level ``parameters:`` block mapping."""
    lines = text.split("\n")
    inside, indent = False, None
    for i, line in enumerate(lines):
        if re.match(r"^parameters\s*:\s*(#.*)?$", line):
            inside = True
            continue
        if inside:
            if line.strip() == "" or line.lstrip().startswith("#"):
                continue
            lead = len(line) - len(line.lstrip())
            if lead == 0:
                break
            indent = lead if indent is None else indent
            m = re.match(rf"^(\s+){re.escape(name)}\s*:\s*(?P<old>.*?)(?P<comment>\s+#.*)?$",
                         line)
            if m and lead == indent:
                old = m.group("old").strip()
                lines[i] = (f"{m.group(1)}{name}: {_yaml_value(value)}"
                            f"   # tuned (was: {old}){m.group('comment') or ''}")
                return "\n".join(lines), True
    return text, False


def _figure(rows: int, width: float = 7.5, height: float = 2.6):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width, height * rows), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, [fig.add_subplot(rows, 1, k + 1) for k in range(rows)]


def history_figure(prob: _Problem, result: TuneResult, path: str) -> str:
    """Objective per evaluation (screening, searches; best feasible so far) and each
    parameter's value scaled to its range."""
    fig, (ax, axp) = _figure(2)
    idx = np.array([e.index for e in prob.history])
    cost = np.array([e.cost if e.status == "ok" else np.nan for e in prob.history])
    feasible = np.array([e.feasible for e in prob.history])
    phases = np.array([e.phase for e in prob.history])
    positive = np.all(cost[np.isfinite(cost)] > 0)
    for phase, marker, colour in (("start", "s", "black"), ("screen", "o", "0.55"),
                                  ("search", ".", "tab:blue")):
        m = phases == phase
        ax.plot(idx[m & feasible], cost[m & feasible], marker, color=colour, ls="none",
                label=f"{phase}" if phase != "search" else "local search")
        ax.plot(idx[m & ~feasible], cost[m & ~feasible], marker, color=colour, ls="none",
                mfc="none", alpha=0.7)
    best = np.minimum.accumulate(np.where(feasible & np.isfinite(cost), cost, np.inf))
    ax.step(idx, np.where(np.isfinite(best), best, np.nan), where="post", color="tab:red",
            label="best feasible so far")
    if positive:
        ax.set_yscale("log")
        finite = cost[np.isfinite(cost)]
        if finite.size and finite.max() / finite.min() < 10:   # under a decade: label the
            from matplotlib.ticker import FuncFormatter         # minor ticks too
            ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
    ax.set_ylabel(prob.minimize)
    ax.set_title(f"tuning {', '.join(prob.names)}: {result.runs['total']} runs "
                 "(open markers: constraint violated)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", lw=0.3)
    lo, hi = prob.bounds[:, 0], prob.bounds[:, 1]
    for j, name in enumerate(prob.names):
        v = np.array([e.values[j] for e in prob.history])
        axp.plot(idx, (v - lo[j]) / (hi[j] - lo[j]), ".-", lw=0.6, ms=3,
                 label=f"{name} in [{lo[j]:g}, {hi[j]:g}]")
    axp.set_ylim(-0.05, 1.05)
    axp.set_xlabel("evaluation")
    axp.set_ylabel("value, scaled to its range")
    axp.legend(fontsize=7)
    axp.grid(True, lw=0.3)
    fig.savefig(path, dpi=110)
    return path


def _objective_signals(prob: _Problem) -> list:
    out = []
    for expr in [prob.minimize] + [e for e, _, _ in prob.constraints]:
        fn, sig, _ = parse_objective(expr)
        sig = sig or prob.d0.spec.metrics.get("error")
        if sig and sig not in out:
            out.append(sig)
    return out


def _line(colour, style, label):
    from matplotlib.lines import Line2D
    return Line2D([], [], color=colour, ls=style, lw=1.2, label=label)


def _style_handles(components: int, names=()) -> list:
    """Legend entries: before (dashed) and after (solid), then one colour per component
    (named as the result's figures name them, else by index)."""
    handles = [_line("0.3", "--", "before"), _line("0.3", "-", "after")]
    if components > 1:
        names = list(names) if len(names) == components else [f"[{c}]" for c in range(components)]
        handles += [_line(f"C{c % 10}", "-", names[c]) for c in range(components)]
    return handles


def before_after_figure(prob: _Problem, result: TuneResult, path: str) -> str:
    """The signals the objective and constraints read, for the diagram as given and tuned,
    the constraint bounds drawn on the signals they limit (max_abs constraints)."""
    from fwdstep.run.simulate import simulate
    runs = {}
    for label, x in (("before", [result.initial[n] for n in prob.names]),
                     ("after", [result.best[n] for n in prob.names])):
        try:
            runs[label] = simulate(prob.diagram(x), backend=prob.backend)
        except FwdstepError as exc:
            runs[label] = getattr(exc, "result", None)
    signals = _objective_signals(prob)
    fig, axes = _figure(max(1, len(signals)), width=8.5)
    for ax, sig in zip(axes, signals):
        components = 1
        for label, style in (("before", "--"), ("after", "-")):
            r = runs.get(label)
            if r is None or sig not in r:
                continue
            y = np.asarray(r[sig]).reshape(len(r.t), -1)
            components = max(components, y.shape[1])
            for c in range(y.shape[1]):     # one colour per component, before dashed
                ax.plot(r.t, y[:, c], color=f"C{c % 10}", ls=style,
                        lw=1.2 if label == "after" else 0.9)
        from fwdstep.results.plotting import signal_info
        shown = runs.get("after") or runs.get("before")
        info = signal_info(shown, sig) if shown is not None and sig in shown else None
        handles = _style_handles(components, info.components if info is not None else ())
        for expr, op, b in prob.constraints:
            fn, s, _ = parse_objective(expr)
            if s == sig and fn == "max_abs":
                ax.axhline(b, color="tab:red", lw=0.8, ls=":")
                ax.axhline(-b, color="tab:red", lw=0.8, ls=":")
                handles.append(_line("tab:red", ":", f"|{info.label if info else sig}| <= {b:g}"))
        ax.set_ylabel(info.axis_label() if info is not None else sig)
        ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        ax.grid(True, lw=0.3)
    axes[-1].set_xlabel("t (s)")
    before = ", ".join(f"{n}={v:.4g}" for n, v in result.initial.items())
    after = ", ".join(f"{n}={v:.4g}" for n, v in result.best.items())
    axes[0].set_title(f"before: {before}  ({prob.minimize} = {result.initial_cost:.4g})\n"
                      f"after: {after}  ({prob.minimize} = {result.best_cost:.4g})",
                      fontsize=8)
    fig.savefig(path, dpi=110)
    return path


__all__ = ["tune", "TuneResult", "Evaluation", "parse_vary", "write_tune", "FILES"]
