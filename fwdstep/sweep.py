"""Parameter sweeps: many variants of one diagram, run in batches (``fwdstep sweep``).

::

    fwdstep sweep DIAGRAM --grid ell=1,2,3 --grid K=20,50
                  [--random NAME=LOW:HIGH ... --samples N --seed S] [--set NAME=VALUE ...]
                  [--sequential] [-o OUTDIR] [--force] [-q]

The variants are the Cartesian product of the ``--grid`` values (each value a number or an
expression, e.g. ``K=20*eye(2),50*eye(2)``; commas inside brackets do not split), each
combined with ``N`` random samples of the ``--random`` parameters (uniform in
[LOW, HIGH], drawn with ``numpy.random.default_rng(S)``); ``--set`` values apply to every
variant.  Variants whose diagrams have the same structure (shapes and state sizes: every
``K`` for one ``ell``) run as one batch (``fwdstep.compile_batch``), a structure per batch;
``--sequential`` runs them one by one instead (the same numbers, slower).  A variant that
diverges is frozen and marked while the rest of its batch goes on; if a block raises inside
a batch, that batch is re-run variant by variant so the others still get their numbers.

Writes ``OUTDIR/sweep.csv`` (one row per variant: the swept parameters, the batch, the
status and the diagram's error metrics) and ``OUTDIR/sweep.png`` (each metric against
each swept parameter, and |e|(t) of up to 8 variants).  Exit codes as ``fwdstep run``: 0 all
variants ok, 2 bad input, 3 some diverged, 4 some raised, 130 interrupted (the rows run so
far are written).

Python: ``run_sweep(path, grid={"ell": [1, 2, 3]}, ...)`` returns a ``SweepResult``.
"""
from __future__ import annotations

import contextlib
import copy
import csv
import io
import itertools
import json
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from .compiler import compile_variants, instantiate_variants, structure_signature
from .errors import (BlockRuntimeError, ConfigError, DiagramError, DivergenceError,
                     OutputError)
from .result import atomic_write, error_metrics, safe_path
from .simulate import SimulationInterrupted, simulate

CSV_FILE = "sweep.csv"
FIGURE_FILE = "sweep.png"
METRICS = ("final_abs_error", "tail_max_abs_error", "rms_error", "max_abs_error")
#: Refuse sweeps with more variants than this (each variant is a diagram in memory).
MAX_VARIANTS = 100_000
#: Largest batch; a structure group with more variants runs in several batches.
MAX_BATCH = 512
#: Largest recorded error signal per batch (bytes); larger batches are split.
MAX_BATCH_LOG_BYTES = 400_000_000
#: How many variants' |e|(t) the figure overlays.
MAX_TRACES = 8


@dataclass
class Variant:
    """One row of the sweep table."""
    index: int
    values: dict                  # swept parameter -> value as given (number or expression)
    batch: int = -1
    status: str = "not run"
    message: str = ""
    diverged_at: float | None = None
    metrics: dict = field(default_factory=dict)


@dataclass
class SweepResult:
    diagram: str
    names: list                   # swept parameters, in column order
    variants: list
    batches: list                 # one (size, description) per batch run
    traces: dict                  # variant index -> (t, |e|(t)) for the plotted variants
    metric_signal: str | None
    wall_time: float = 0.0
    interrupted: bool = False

    def counts(self) -> dict:
        out: dict = {}
        for v in self.variants:
            out[v.status] = out.get(v.status, 0) + 1
        return out

    def rows(self) -> list:
        """The table as a list of dicts (column -> text or number)."""
        rows = []
        for v in self.variants:
            row = {"variant": v.index}
            row.update({name: _text(v.values.get(name)) for name in self.names})
            row.update(batch=v.batch, status=v.status,
                       diverged_at="" if v.diverged_at is None else v.diverged_at)
            row.update({m: ("" if v.metrics.get(m) is None else v.metrics[m]) for m in METRICS})
            row["message"] = v.message
            rows.append(row)
        return rows

    def write(self, outdir: str, plots: bool = True) -> list:
        """Write sweep.csv (and sweep.png) into ``outdir``; returns the paths written."""
        os.makedirs(outdir, exist_ok=True)
        rows = self.rows()
        buf = io.StringIO()
        columns = ["variant", *self.names, "batch", "status", "diverged_at", *METRICS,
                   "message"]
        writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in row.items()})
        path = safe_path(outdir, CSV_FILE)
        atomic_write(path, lambda fh: fh.write(buf.getvalue()))
        written = [path]
        if plots and self.metric_signal is not None and any(v.metrics for v in self.variants):
            written.append(plot_sweep(self, outdir))
        return written


# ---------------------------------------------------------------------------- parsing
def split_values(text: str) -> list:
    """'1,2,[3, 4],f(5,6)' -> ['1', '2', '[3, 4]', 'f(5,6)']: commas at bracket depth 0."""
    parts, depth, current = [], 0, ""
    for ch in text:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    parts.append(current)
    return [p.strip() for p in parts]


def parse_grid(items: list) -> dict:
    """``["ell=1,2,3", "K=20,50"]`` -> {"ell": [1, 2, 3], "K": [20, 50]} (values read like
    ``--set`` values: numbers, lists, or expression strings)."""
    from .spec import parse_override
    grid: dict = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--grid '{item}' must have the form NAME=V1,V2,...")
        name, raw = item.split("=", 1)
        values = []
        for part in split_values(raw):
            if not part:
                raise ConfigError(f"--grid '{item}' has an empty value")
            values.append(parse_override(f"{name.strip()}={part}")[1])
        name = name.strip()
        if name in grid:
            raise ConfigError(f"--grid {name} is given twice")
        grid[name] = values
    return grid


def parse_random(items: list) -> dict:
    """``["alpha=1:5"]`` -> {"alpha": (1.0, 5.0)}."""
    out: dict = {}
    for item in items or []:
        name, sep, raw = item.partition("=")
        low, colon, high = raw.partition(":")
        try:
            bounds = (float(low), float(high))
        except ValueError:
            bounds = None
        if not sep or not colon or bounds is None or not all(map(np.isfinite, bounds)):
            raise ConfigError(f"--random '{item}' must have the form NAME=LOW:HIGH with two "
                              "numbers")
        if not bounds[0] <= bounds[1]:
            raise ConfigError(f"--random '{item}': LOW must not exceed HIGH")
        name = name.strip()
        if name in out:
            raise ConfigError(f"--random {name} is given twice")
        out[name] = bounds
    return out


def variant_values(grid: dict, random: dict, samples: int, seed: int) -> list:
    """The swept values of every variant: grid product x random samples."""
    both = set(grid) & set(random)
    if both:
        raise ConfigError(f"parameter '{sorted(both)[0]}' is both in --grid and --random")
    if random and samples < 1:
        raise ConfigError("--random needs --samples N (N >= 1)")
    if samples and not random:
        raise ConfigError("--samples needs at least one --random NAME=LOW:HIGH")
    if not grid and not random:
        raise ConfigError("nothing to sweep: give --grid NAME=V1,V2,... or --random "
                          "NAME=LOW:HIGH --samples N")
    n_grid = int(np.prod([len(v) for v in grid.values()], dtype=np.int64)) if grid else 1
    total = n_grid * max(samples, 1)
    if total > MAX_VARIANTS:
        raise ConfigError(f"the sweep has {total} variants; the limit is {MAX_VARIANTS}")
    rng = np.random.default_rng(seed)
    draws = {name: rng.uniform(low, high, size=max(samples, 1)) if random else None
             for name, (low, high) in random.items()}
    out = []
    for combo in itertools.product(*grid.values()) if grid else [()]:
        base = dict(zip(grid, combo))
        for k in range(max(samples, 1)):
            values = dict(base)
            values.update({name: float(draws[name][k]) for name in random})
            out.append(values)
    return out


# ---------------------------------------------------------------------------- running
def run_sweep(path: str, grid: dict | None = None, random: dict | None = None,
              samples: int = 0, seed: int = 0, overrides: dict | None = None,
              sequential: bool = False, progress=None) -> SweepResult:
    """Run every variant of the diagram at ``path``; see the module docstring.

    ``grid`` maps parameter names to lists of values; ``random`` maps names to (low, high);
    ``overrides`` are fixed for all variants.  ``progress(text)`` is told about each batch.
    Raises ``DiagramError`` for a bad diagram or bad sweep options (nothing is run then)."""
    from .spec import load_spec
    grid, random, overrides = dict(grid or {}), dict(random or {}), dict(overrides or {})
    wall0 = time.perf_counter()
    all_values = variant_values(grid, random, samples, seed)
    names = list(grid) + list(random)
    documents: dict = {}            # each YAML file parsed once for all variants
    base = load_spec(path, overrides, cache=documents)
    for name in names:
        if name not in base.parameters:
            raise ConfigError(f"--grid/--random {name}: the diagram has no parameter "
                              f"'{name}'; parameters are: {', '.join(base.parameters)}",
                              file=base.file)
        if name in overrides:
            raise ConfigError(f"parameter '{name}' is both swept and set with --set")
    specs, blocks, made = [], [], {}
    for values in all_values:
        try:
            specs.append(load_spec(path, {**overrides, **values}, cache=documents))
            blocks.extend(instantiate_variants(specs[-1:], made))
        except DiagramError as exc:
            shown = ", ".join(f"{k}={_text(v)}" for k, v in values.items())
            raise type(exc)(f"variant {shown}: {exc.message}", file=exc.file,
                            line=exc.line, block=exc.block, port=exc.port) from None
    metric = base.metrics.get("error")
    variants = [Variant(i, values) for i, values in enumerate(all_values)]
    groups: dict = {}
    for i, blks in enumerate(blocks):
        groups.setdefault(structure_signature(blks), []).append(i)
    batches = _batches(list(groups.values()), specs[0], metric, sequential)
    trace_ids = set(np.unique(np.linspace(0, len(variants) - 1,
                                          min(MAX_TRACES, len(variants))).astype(int)).tolist())
    result = SweepResult(diagram=path, names=names, variants=variants, batches=[],
                         traces={}, metric_signal=metric)
    try:
        for number, members in enumerate(batches):
            if progress is not None:
                shown = _describe(variants[members[0]].values, names)
                more = ("s", ", ...") if len(members) > 1 else ("", "")
                progress(f"batch {number + 1}/{len(batches)}: {len(members)} variant{more[0]} "
                         f"({shown}{more[1]})")
            result.batches.append((len(members), _describe(variants[members[0]].values, names)))
            _run_batch(number, members, specs, blocks, variants, metric, trace_ids, result)
    except KeyboardInterrupt:
        result.interrupted = True
        for v in variants:
            if v.status == "not run":
                v.status = "interrupted"
    result.wall_time = time.perf_counter() - wall0
    return result


def _batches(groups: list, spec, metric, sequential: bool) -> list:
    if sequential:
        return [[i] for members in groups for i in members]
    n_rows = spec.simulation.n_steps // spec.simulation.log_every + 2
    per_variant = n_rows * 8 * 64          # a generous bound on the error signal's size
    limit = max(1, min(MAX_BATCH, MAX_BATCH_LOG_BYTES // per_variant))
    out = []
    for members in groups:
        out.extend(members[k:k + limit] for k in range(0, len(members), limit))
    return out


def _run_batch(number, members, specs, blocks, variants, metric, trace_ids, result) -> None:
    d = compile_variants([specs[i] for i in members], [blocks[i] for i in members])
    if metric is not None:
        d.logged = [d.resolve(metric)]
    else:
        d.logged = []
    try:
        r = simulate(d)
    except DivergenceError as exc:
        r = exc.result
    except SimulationInterrupted:
        raise KeyboardInterrupt from None
    except BlockRuntimeError as exc:
        if len(members) > 1:                 # find which variants fail: one by one
            for i in members:
                _run_batch(number, [i], specs, blocks, variants, metric, trace_ids, result)
            return
        v = variants[members[0]]
        v.batch, v.status, v.message = number, "error", str(exc)
        return
    tail = specs[members[0]].metrics.get("tail", 0.2)
    for b, i in enumerate(members):
        v = variants[i]
        v.batch = number
        died = r.diverged_at[b] if r.diverged_at is not None else np.nan
        if np.isfinite(died):
            v.status, v.diverged_at = "diverged", float(died)
            v.message = f"diverged at t = {died:.6g}"
        else:
            v.status = "ok"
        if metric is None:
            continue
        e = r.variant(b)[d.resolve(metric)]
        t = r.t
        if v.status == "diverged":
            keep = t < died
            t, e = t[keep], e[keep]
        else:
            v.metrics = error_metrics(t, e, tail)
        if i in trace_ids and len(t):
            result.traces[i] = (t.copy(), np.sqrt(np.sum(e.reshape(len(t), -1) ** 2, axis=1)))


def _describe(values: dict, names: list) -> str:
    return ", ".join(f"{k}={_text(values[k])}" for k in names if k in values)


def _text(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple, np.ndarray)):
        return json.dumps(np.asarray(value).tolist())
    return str(value)


# ---------------------------------------------------------------------------- figure
def _numeric(values: list):
    try:
        arr = np.array([float(v) for v in values])
        return arr
    except (TypeError, ValueError):
        return None


def plot_sweep(result: SweepResult, outdir: str) -> str:
    """sweep.png: the tail metric against each swept parameter, and |e|(t) traces."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [v for v in result.variants if v.metrics]
    n_panels = len(result.names) + 1
    fig, axes = plt.subplots(n_panels, 1, figsize=(8, 2.8 * n_panels + 0.6), squeeze=False)
    axes = axes[:, 0]
    for ax, name in zip(axes, result.names):
        raw = [v.values[name] for v in ok]
        x = _numeric(raw)
        if x is None:                                   # expressions: categories in order
            labels = list(dict.fromkeys(_text(r) for r in raw))
            x = np.array([labels.index(_text(r)) for r in raw], dtype=float)
            ax.set_xticks(range(len(labels)), labels, fontsize=7)
        others = [n for n in result.names if n != name]
        for key, (label, marker) in _series(ok, others).items():
            sel = [k for k, v in enumerate(ok) if _describe(v.values, others) == key]
            order = np.argsort(x[sel], kind="stable")
            color = None
            for metric, style in (("tail_max_abs_error", "-"), ("final_abs_error", ":")):
                y = np.array([ok[k].metrics[metric] for k in sel])
                line, = ax.plot(x[sel][order], y[order], style, marker=marker, ms=4, lw=1,
                                color=color,
                                label=f"{'max |e| over tail' if style == '-' else 'final |e|'}"
                                      f"{', ' + label if label else ''}")
                color = line.get_color()
        diverged = [v for v in result.variants if v.status == "diverged"]
        if diverged:
            xd = _numeric([v.values[name] for v in diverged])
            if xd is not None:
                top = max([max(v.metrics.values()) for v in ok] + [1.0])
                ax.plot(xd, np.full(len(xd), top), "rx", label="diverged")
        ax.set_yscale("log")
        ax.set_xlabel(name)
        ax.set_ylabel(f"|{result.metric_signal}|")
        ax.grid(True, alpha=0.3, which="both")
        if len(ax.get_legend_handles_labels()[0]) <= 12:
            ax.legend(fontsize=6, loc="best")
    ax = axes[-1]
    for i, (t, norm) in sorted(result.traces.items()):
        ax.semilogy(t, np.maximum(norm, 1e-300), lw=1,
                    label=_describe(result.variants[i].values, result.names))
    ax.set_xlabel("t [s]")
    ax.set_ylabel(f"|{result.metric_signal}|(t)")
    ax.grid(True, alpha=0.3, which="both")
    if result.traces:
        ax.legend(fontsize=6, loc="best")
    fig.suptitle(f"sweep of {os.path.basename(result.diagram)}: {len(result.variants)} "
                 f"variants", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    path = safe_path(outdir, FIGURE_FILE)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()), binary=True)
    return path


def _series(ok: list, others: list) -> dict:
    """One line per combination of the other swept parameters (at most 10 drawn as lines)."""
    keys = list(dict.fromkeys(_describe(v.values, others) for v in ok))
    markers = "os^vD<>ph*"
    if len(keys) > len(markers):
        return {k: ("", "o") for k in keys}
    return {k: (k, markers[n]) for n, k in enumerate(keys)}


# ---------------------------------------------------------------------------- command
def cmd_sweep(args) -> int:
    """``fwdstep sweep``: see the module docstring for the options and exit codes."""
    from .commands import (EXIT_BLOCK, EXIT_DIVERGED, EXIT_INPUT, EXIT_INTERRUPTED, EXIT_OK,
                           _overrides)
    outdir = args.outdir or os.path.join(
        "out", os.path.splitext(os.path.basename(args.diagram))[0] + "_sweep")
    quiet = getattr(args, "quiet", False)
    try:
        grid = parse_grid(args.grid)
        random = parse_random(args.random)
        overrides = _overrides(args.set)
        _check_outdir(outdir, args.force)
        progress = None if quiet else (lambda text: print(f"  {text}", file=sys.stderr,
                                                          flush=True))
        result = run_sweep(args.diagram, grid, random, args.samples, args.seed, overrides,
                           sequential=args.sequential, progress=progress)
    except (DiagramError, OutputError) as exc:
        print(f"fwdstep: {exc}", file=sys.stderr)
        return EXIT_INPUT
    try:
        written = result.write(outdir)
    except (OSError, OutputError) as exc:
        print(f"fwdstep: cannot write results to {outdir}: {exc}", file=sys.stderr)
        return EXIT_INPUT
    counts = result.counts()
    if not quiet:
        summary = ", ".join(f"{n} {status}" for status, n in counts.items())
        print(f"{len(result.variants)} variants in {len(result.batches)} batch"
              f"{'es' if len(result.batches) != 1 else ''}: {summary}; "
              f"{result.wall_time:.2f} s wall")
        print(f"wrote {', '.join(os.path.relpath(p) for p in written)}")
    if result.interrupted:
        return EXIT_INTERRUPTED
    if counts.get("error"):
        return EXIT_BLOCK
    if counts.get("diverged"):
        return EXIT_DIVERGED
    return EXIT_OK


def _check_outdir(outdir: str, force: bool) -> None:
    if os.path.exists(outdir) and not os.path.isdir(outdir):
        raise OutputError(f"output directory {outdir} exists and is not a directory")
    existing = os.path.join(outdir, CSV_FILE)
    if os.path.exists(existing) and not force:
        raise OutputError(f"{existing} already exists; pass --force to overwrite it or -o to "
                          "choose another directory")


__all__ = ["run_sweep", "SweepResult", "Variant", "cmd_sweep", "parse_grid", "parse_random",
           "variant_values"]
