"""Compare saved runs: the same signals overlaid, their differences, and a metrics table.

Python::

    c = fwdstep.compare(["out/theorem1", "out/theorem1_ell3"])     # dirs or Result objects
    c.table          # one row per run: status, t reached, metrics, max |difference| per signal
    c.figure         # matplotlib Figure (no pyplot): per signal an overlay and a difference panel
    c.save("out/cmp")                                              # compare.png/.csv

Command line: ``fwdstep compare RUN_A RUN_B [...] [-o DIR] [--signal S ...]``.
Differences are taken against the first run, on its time grid (linear interpolation when the
other run was recorded at other times; outside the other run's time span they are NaN, never
extrapolated).  A batch result counts as one run per variant: ``DIR@3`` is variant 3.
A sweep directory (``fwdstep sweep -o SWEEP``) counts as one run per variant whose signal was
saved; ``SWEEP@3`` is its variant 3 (the row ``variant = 3`` of sweep.csv), ``SWEEP@3,7``
variants 3 and 7.  A sweep keeps the diagram's error signal (``metrics: error:``) of each
variant, under its real name, label and unit, so it also compares with a run of the diagram.
"""
from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass, field

import numpy as np

from fwdstep.core.errors import OutputError
from fwdstep.results.plotting import (FORMATS, LineKey, check_formats, finish_figure, line_colors,
                                     new_figure, place_legend, save_figure, signal_info,
                                     time_axis)
from fwdstep.results.result import Result, load_result

CSV_FILE = "compare.csv"
#: how many variants of a sweep the report's comparison figure overlays
MAX_SWEEP_SHOWN = 8
FIGURE_NAME = "compare"
_STYLES = ("-", "--", ":", "-.")


@dataclass
class Run:
    label: str
    result: Result
    variant: int | None = None
    #: signal -> (factor, unit it was recorded in): its values converted into the first
    #: run's unit (``unit_conversions``)
    converted: dict = field(default_factory=dict)

    def data(self, name: str) -> np.ndarray:
        arr = self.result[name]
        arr = arr[:, self.variant] if self.variant is not None else arr
        if name in self.converted:
            arr = arr * self.converted[name][0]
        return arr

    def metrics(self) -> dict:
        m = self.result.metrics()
        if isinstance(m, list):
            return m[self.variant or 0] if m else {}
        return m or {}


class Table(list):
    """The metrics table: a list of rows (dict column -> value), one per run, that also
    turns into a pandas DataFrame (``to_pandas``) indexed by run label."""

    def to_pandas(self):
        import pandas as pd
        frame = pd.DataFrame(list(self))
        return frame.set_index("run") if "run" in frame.columns else frame


@dataclass(repr=False)
class Comparison:
    runs: list
    signals: list
    differences: dict            # signal -> list (one per run after the first) of (T, ...) arrays
    table: list                  # rows: dict column -> value (a ``Table``: ``.to_pandas()``)
    figure: object

    def __post_init__(self):
        if not isinstance(self.table, Table):
            self.table = Table(self.table)
        self.notes: list = []        # e.g. the runs come from different diagrams

    def __repr__(self) -> str:
        labels = ", ".join(r.label for r in self.runs)
        return (f"<Comparison of {len(self.runs)} runs ({labels}); signals: "
                f"{', '.join(self.signals)}; .table ({len(self.table)} rows, .to_pandas()), "
                ".differences, .figure>")

    def save(self, outdir: str, formats=("png",), force: bool = True) -> list:
        """Write compare.csv and compare.<fmt> into ``outdir`` through fwdstep.results.outputs."""
        from fwdstep.results.outputs import OutputDir
        formats = check_formats(formats)
        names = [CSV_FILE] + [f"{FIGURE_NAME}.{f}" for f in formats]
        with OutputDir(outdir, force=force, expected=names) as out:
            with open(os.path.join(out.dir, CSV_FILE), "w", newline="") as fh:
                fh.write(table_csv(self.table))
            save_figure(self.figure, out.dir, FIGURE_NAME, formats)
            return out.commit()


def open_run(source, label: str | None = None) -> list:
    """Runs from a Result, a run directory, ``DIR@k`` (variant k of a saved batch), a sweep
    directory (every variant whose signal was saved) or ``SWEEP@k`` / ``SWEEP@3,7``."""
    if isinstance(source, Result):
        r, name, variant = source, label or "run", None
    else:
        text = str(source)
        variant = None
        if "@" in text and not os.path.isdir(text):
            text, _, idx = text.rpartition("@")
            try:
                variant = [int(k) for k in idx.split(",")]
            except ValueError:
                raise OutputError(f"'{source}': after '@' come variant numbers, e.g. "
                                  f"{text}@3 or {text}@3,7") from None
        if is_sweep(text):
            return sweep_runs(text, variant, label)
        if variant is not None and len(variant) > 1:
            return [run for k in variant for run in open_run(f"{text}@{k}", label)]
        variant = variant[0] if variant else None
        r = load_result(text)
        name = label or _short(text)
        if variant is not None and not 0 <= variant < r.batch:
            raise OutputError(f"{text} has {r.batch} variant(s); there is no variant {variant}")
    if variant is None and r.batch > 1:
        return [Run(f"{name}@{b}", r, b) for b in range(r.batch)]
    return [Run(name if variant is None else f"{name}@{variant}", r, variant)]


def is_sweep(path: str) -> bool:
    """A directory written by ``fwdstep sweep`` (sweep.csv and parts/, no result.npz)."""
    from fwdstep.results.sweep_format import CSV_FILE as SWEEP_CSV, PARTS_DIR
    return (os.path.isdir(os.path.join(path, PARTS_DIR))
            or os.path.isfile(os.path.join(path, SWEEP_CSV))) \
        and not os.path.isfile(os.path.join(path, "result.npz"))


def sweep_runs(outdir: str, wanted: list | None = None, label: str | None = None) -> list:
    """The variants of a saved sweep as runs: the error signal under its real name, with the
    diagram's label, unit and components (stored in ``parts/*.npz``), the variant's status and
    metrics; legend entries say which parameter values each variant had.  ``wanted``: variant
    numbers (default: every variant whose signal was saved)."""
    import glob
    import json
    from fwdstep.results.sweep_format import METRICS, PARTS_DIR
    name = label or _short(outdir)
    found: dict = {}
    from fwdstep.results.outputs import owned_files
    from fwdstep.results.sweep_format import read_part
    listed = sorted(n for n in owned_files(outdir) if n.startswith(PARTS_DIR + "/"))
    paths = ([os.path.join(outdir, n) for n in listed] if os.path.lexists(
        os.path.join(outdir, "manifest.json")) else       # a sweep from before manifests
        sorted(glob.glob(os.path.join(glob.escape(outdir), PARTS_DIR, "*.npz"))))
    for path in paths:
        part = read_part(path)               # damaged: one line naming it
        for k, i in enumerate(part["indices"].tolist()):
            found[i] = (part, k)
    if not found:
        raise OutputError(f"{outdir} holds no finished variant (parts/ is empty or missing)")
    n = max(found) + 1
    if wanted is None:
        wanted = [i for i in sorted(found) if _has_signal(*found[i])]
        if not wanted:
            raise OutputError(f"{outdir}: no variant's signal was saved (the sweep ran with "
                              "--no-signals); run it again without --no-signals")
    runs = []
    for i in wanted:
        if i not in found:
            raise OutputError(f"{outdir} has no finished variant {i}" + (
                f" (its variants are 0..{n - 1}; resume the sweep to finish it)"
                if i < n else f"; its variants are 0..{n - 1}"))
        part, k = found[i]
        if not _has_signal(part, k):
            raise OutputError(f"{outdir}: the signal of variant {i} was not saved (the sweep "
                              "ran with --no-signals, which keeps only the plotted variants)")
        info = json.loads(str(part["signal_info"])) if "signal_info" in part else \
            {"name": "e", "real": "e"}                  # a sweep saved before names were kept
        t, e = part["t"], part["e"][:, k]
        rows = np.isfinite(e.reshape(len(t), -1)).any(axis=1)
        last = int(np.nonzero(rows)[0][-1]) + 1 if rows.any() else 0
        status = str(part["status"][k])
        r = Result(t[:last], {info["real"]: e[:last, None]}, status=status,
                   message=str(part["message"][k]))
        r.signal_labels = {info["real"]: {key: info.get(key) for key in
                                          ("label", "unit", "components")}}
        r.aliases = {info["name"]: info["real"]}
        metrics = ({m: float(x) for m, x in zip(METRICS, part["metrics"][k])}
                   if status == "ok" else {})
        r.stored = {"metrics": metrics, "metric_signal": info["name"]}
        r.figure_panels, r.title, r.outdir = {}, "", outdir
        r.diagram_file = str(part["diagram"]) if "diagram" in part else None
        values = json.loads(str(part["values"][k]))
        shown = ", ".join(f"{key}={_value_text(v)}" for key, v in values.items())
        runs.append(Run(f"{name}@{i}" + (f" ({shown})" if shown else ""), r))
    return runs


def _has_signal(part: dict, k: int) -> bool:
    return "e" in part and bool(part["has_signal"][k])


def _value_text(value, limit: int = 40) -> str:
    """A swept value in a legend entry: a matrix (a 200 x 200 one is 360 kB of text) is cut
    to ``limit`` characters, so drawing the legend stays cheap."""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        value = json.dumps(value)
    text = str(value)
    return text if len(text) <= limit else text[:limit - 1] + "\u2026"


def _short(path: str) -> str:
    return os.path.basename(os.path.normpath(path)) or path


def default_signals(runs: list) -> list:
    """The signals of the first run's figures (else its error signal) that every run has."""
    first = runs[0].result
    from fwdstep.results.plotting import figure_specs
    wanted = []
    for panels in figure_specs(first).values():
        for sigs, _ in panels:
            wanted += [s for s in sigs if s not in wanted]
    if not wanted:
        err = (getattr(first, "stored", None) or {}).get("metric_signal")
        if first.diagram is not None and "error" in first.diagram.spec.metrics:
            err = first.diagram.spec.metrics["error"]
        wanted = [err] if err else list(first.names)
    return [s for s in wanted if all(s in run.result for run in runs)]


def difference(ref: Run, other: Run, name: str) -> np.ndarray:
    """other - ref on ref's time grid (NaN outside other's time span)."""
    t0, t1 = ref.result.t, other.result.t
    a, b = ref.data(name), other.data(name)
    if a.shape[1:] != b.shape[1:]:
        raise OutputError(f"signal {name} has shape {a.shape[1:]} in {ref.label} but "
                          f"{b.shape[1:]} in {other.label}")
    if len(t0) == len(t1) and np.array_equal(t0, t1):
        return b - a
    flat = b.reshape(len(t1), -1)
    out = np.empty((len(t0), flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.interp(t0, t1, flat[:, j], left=np.nan, right=np.nan)
    return out.reshape((len(t0),) + a.shape[1:]) - a


def compare(sources, signals=None, labels=None) -> Comparison:
    """Compare runs (directories, ``DIR@k`` variants or Result objects); see the module doc."""
    runs = []
    for k, src in enumerate(sources):
        runs += open_run(src, labels[k] if labels else None)
    if len(runs) < 2:
        raise OutputError("compare needs at least two runs (or a batch with two variants)")
    seen: dict = {}
    for run in runs:                               # same directory names: keep them apart
        seen[run.label] = seen.get(run.label, 0) + 1
    for k, run in enumerate(runs):
        if seen[run.label] > 1:
            run.label = f"{run.label} ({k + 1})"
    if signals is None:
        signals = default_signals(runs)
    else:
        signals = [signals] if isinstance(signals, str) else list(signals)
        for s in signals:
            for run in runs:
                if s not in run.result:
                    raise OutputError(f"signal {s} is not in {run.label}; its signals are: "
                                      f"{', '.join(run.result.names)}")
    if not signals:
        raise OutputError("the runs have no signal in common to compare; name one with --signal")
    unit_conversions(runs, signals)
    diffs = {s: [difference(runs[0], other, s) for other in runs[1:]] for s in signals}
    table = metrics_table(runs, diffs)
    figure = comparison_figure(runs, signals, diffs)
    c = Comparison(runs, signals, diffs, table, figure)
    c.notes = diagram_notes(runs)
    return c


def _diagram_of(run) -> tuple | None:
    """(file name, SHA-256) of the diagram a run was made from, or None when unknown: a
    Result in memory knows its loaded files, a saved run its record
    (``fwdstep.results.provenance``)."""
    import hashlib
    r = run.result
    d = getattr(r, "diagram", None)
    if d is not None and d.spec.sources:
        top = d.spec.sources[0]
        try:
            if top.text is not None:
                data = top.text.encode("utf-8")
            else:
                with open(top.path, "rb") as fh:
                    data = fh.read()
        except OSError:
            return None
        return os.path.basename(top.path), hashlib.sha256(data).hexdigest()
    prov = (getattr(r, "stored", None) or {}).get("provenance")
    if isinstance(prov, dict) and prov.get("files"):
        top = prov["files"][0]
        return os.path.basename(str(prov.get("diagram_source") or top.get("copy"))), \
            top.get("sha256")
    return None


def diagram_notes(runs: list) -> list:
    """One line when the runs come from different diagrams (or different versions of one):
    their differences then say more about the diagrams than about the runs."""
    known = [(run.label, _diagram_of(run)) for run in runs]
    known = [(label, who) for label, who in known if who is not None]
    if len({who for _, who in known}) < 2:
        return []
    names = {who[0] for _, who in known}
    what = "different versions of " + names.pop() if len(names) == 1 else "different diagrams"
    return [f"the runs come from {what}: " + ", ".join(
        f"{label} ({who[0]}, {who[1][:8]})" for label, who in known)]


def unit_conversions(runs: list, signals: list) -> None:
    """Each run's signals in the first run's unit: a signal recorded in deg in one run and
    in rad in the other is converted (``fwdstep.results.units``: angles, lengths, times,
    forces and their products and quotients) before it is overlaid and subtracted; units
    fwdstep cannot convert (rad against N m, or a unit it does not know) refuse the
    comparison of that signal, never a difference in one run's unit."""
    from fwdstep.results.units import factor
    for name in signals:
        unit = signal_info(runs[0].result, name, typeset=False).unit
        for run in runs[1:]:
            other = signal_info(run.result, name, typeset=False).unit
            f = factor(other, unit)
            if f is None:
                raise OutputError(
                    f"signal {name} is in {other} in {run.label} but in {unit} in "
                    f"{runs[0].label}; fwdstep cannot convert {other} into {unit}, so it does "
                    "not take their difference (compare the runs' other signals with "
                    "--signal, or record this one in one unit)")
            if f != 1.0:
                run.converted[name] = (f, other)


def metrics_table(runs: list, diffs: dict) -> list:
    rows = []
    for k, run in enumerate(runs):
        r = run.result
        row = {"run": run.label, "status": r.status,
               "t_reached": float(r.t[-1]) if len(r.t) else None}
        row.update({key: val for key, val in run.metrics().items()})
        for s, ds in diffs.items():
            if k == 0:
                row[f"max |diff {s}|"] = 0.0
            else:
                d = np.abs(ds[k - 1])
                row[f"max |diff {s}|"] = float(np.nanmax(d)) if np.isfinite(d).any() else None
        rows.append(row)
    return rows


def table_csv(rows: list) -> str:
    columns = list(dict.fromkeys(c for row in rows for c in row))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow({c: ("" if row.get(c) is None else
                        repr(row[c]) if isinstance(row.get(c), float) else row[c])
                    for c in columns})
    return buf.getvalue()


def comparison_figure(runs: list, signals: list, diffs: dict):
    """Per signal: the runs overlaid (one colour per run; one line style per component when
    they are at most four, else all solid) and the differences to the first run."""
    fig, axes = new_figure(2 * len(signals), height=2.3 * 2 * len(signals) + 0.9)
    colors = line_colors(len(runs))
    labels = [r.label for r in runs]
    t_ref = runs[0].result.t
    for n, name in enumerate(signals):
        info = signal_info(runs[0].result, name)
        over, diff = axes[2 * n], axes[2 * n + 1]
        shape = runs[0].data(name).shape[1:]
        width = int(np.prod(shape, dtype=int))
        styled = 1 < width <= len(_STYLES)        # more components: styles would repeat
        comps = [_component(info, shape, j) if styled else "" for j in range(width)]
        styles = [_STYLES[j] if styled else "-" for j in range(width)]
        for k, run in enumerate(runs):
            flat = run.data(name).reshape(len(run.result.t), -1)
            for j in range(flat.shape[1]):
                note = (f" ({run.converted[name][1]} → {info.unit})"
                        if name in run.converted else "")
                over.plot(run.result.t, flat[:, j], color=colors[k], ls=styles[j], lw=1.1,
                          label=f"{run.label}{note}" + (f", {comps[j]}" if comps[j] else ""))
            if k:
                d = diffs[name][k - 1].reshape(len(t_ref), -1)
                for j in range(d.shape[1]):
                    diff.plot(t_ref, d[:, j], color=colors[k], ls=styles[j], lw=1.1,
                              label=f"{run.label} − {labels[0]}" + (f", {comps[j]}" if comps[j]
                                                                    else ""))
        over.set_ylabel(info.axis_label(), fontsize=9)
        diff.set_ylabel(f"Δ {info.label}" + (f" [{info.unit}]" if info.unit else ""), fontsize=9)
        style_key = (tuple(styles), tuple(comps)) if styled else (("-",), ("",))
        keys = (LineKey(tuple(colors), tuple(labels), "run", *style_key),
                LineKey(tuple(colors[1:]), tuple(f"{lab} − {labels[0]}" for lab in labels[1:]),
                        "run", *style_key))
        for ax, key in zip((over, diff), keys):
            time_axis(ax, t_ref)
            place_legend(ax, key=key)
    axes[-1].set_xlabel("$t$ [s]", fontsize=9)
    names = ", ".join(r.label for r in runs)
    finish_figure(fig, f"Comparison of {names}" if len(names) <= 90 else
                  f"Comparison of {len(runs)} runs", f"differences against {runs[0].label}")
    return fig


def _component(info, shape: tuple, j: int) -> str:
    if not shape:
        return ""
    return info.component(np.unravel_index(j, shape), shape)


__all__ = ["compare", "Comparison", "FORMATS"]
