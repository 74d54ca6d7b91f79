"""Parameter sweeps: many variants of one diagram, run in batches (``fwdstep sweep``).

::

    fwdstep sweep DIAGRAM --grid ell=1,2,3 --grid K=20,50
                  [--random NAME=DIST ... --samples N --seed S --design random|lhs|sobol]
                  [--seed-parameter NAME] [--set NAME=VALUE ...]
                  [--workers N | --scheduler ADDRESS] [--backend numpy|compiled]
                  [--max-memory SIZE] [--batch-size N]
                  [--sequential] [--resume] [--no-signals] [--netcdf] [-o OUTDIR] [--force]
                  [-q]

The variants are the Cartesian product of the ``--grid`` values (each value a number or an
expression, e.g. ``K=20*eye(2),50*eye(2)``; commas inside brackets do not split; a solver
setting is swept as ``simulation.step=0.001,0.002``), each combined with ``N`` draws of the
``--random`` parameters (``fwdstep.sweeps.sampling``: uniform, log-uniform or normal; random, Latin
hypercube or Sobol designs; seeded).  ``--seed-parameter NAME`` gives every variant its own
seed in the diagram parameter NAME (for noise blocks).  ``--set`` values apply to every
variant.

**Batches are exact.**  Variants run together in one batch (``fwdstep.compile_batch``) only
when everything that could change their numbers other than the stacked block parameters is
equal: the whole simulation settings object (``spec.simulation``, every field, including
ones added later), the rest of the diagram spec (log, metrics, connections) and the blocks'
structure signature (``fwdstep.structure.compiler.structure_signature``: shapes, state sizes,
non-numeric parameters, and everything a block computed in ``setup`` outside ``p``).
Fixed-step solvers batch, on the NumPy backend or the compiled one (``--backend compiled``:
``fwdstep.compiled.backend_numba`` runs a batch's variants in parallel threads; one process by
default); an adaptive solver, or a diagram with a Stop block (which ends a whole batch's
run), runs one variant per batch; a variant its Stop block ended says so in its message
(its metrics are at that time).  Zero crossings are located per variant in a batch
(``fwdstep.run.crossings``): each variant keeps the numbers of its run alone.  A variant that diverges is frozen and marked while the rest of its batch goes on;
if a block raises inside a batch, that batch is re-run variant by variant.

**Memory.**  A batch's size is bounded by what it really logs: the bytes of the logged error
signal times its rows, plus the state buffers, per variant; ``--max-memory`` (default 1 GB)
is shared by the batches running at once.  A sweep whose single variant needs more is refused
with the numbers.

**Parallel.**  Batches run on all local cores (``--workers N``, default: the cores this
process may use; ``--workers 1`` runs in this process), or on a Dask cluster
(``--scheduler tcp://HOST:PORT``; Python: ``client=``), see ``fwdstep.sweeps.distributed``.

**Nothing finished is lost.**  Each batch is written to ``OUTDIR/parts/`` atomically when it
finishes; Ctrl-C or SIGTERM stops the sweep and keeps them (exit 130), and ``--resume`` re-runs
only the variants that are not there yet.

Writes ``OUTDIR/sweep.csv`` (one row per variant: the swept parameters, the batch, the
status and the diagram's error metrics), ``OUTDIR/sweep.png`` (each metric against each
swept parameter, and |e|(t) of up to 8 variants) and, with ``--netcdf``, ``OUTDIR/sweep.nc``
(the error signal of every variant as a labelled xarray Dataset, ``fwdstep.results.labelled``;
``OUTDIR/parts/*.npz`` hold the same numbers unless ``--no-signals``).  Exit codes as
``fwdstep run``: 0 all variants ok, 2 bad input, 3 some diverged, 4 some raised, 130
interrupted.

Python: ``run_sweep(path, grid={"ell": [1, 2, 3]}, ...)`` returns a ``SweepResult``.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import gc
import glob
import io
import json
import math
import os
import pickle
import signal
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from fwdstep.structure.compiler import _value_key, compile_variants, instantiate_variants, structure_signature
from fwdstep.core import signals
from fwdstep.core.budgets import BudgetError
from fwdstep.sweeps.distributed import (WorkerLost, check_workers, dask_client, local_cores,
                                        run_jobs)
from fwdstep.core.errors import (BlockRuntimeError, ConfigError, DiagramError, DivergenceError,
                                 OutputError, printable)
from fwdstep.results.result import batch_error_metrics
from fwdstep.results.outputs import OutputDir, owned_files
from fwdstep.sweeps.sampling import (MAX_VARIANTS, parse_grid, parse_random, split_values,  # noqa: F401
                       variant_seeds, variant_values)
from fwdstep.run.simulate import SimulationInterrupted, simulate
from fwdstep.sweeps.variants import VariantSpecs
from fwdstep.results.sweep_format import (CSV_FILE, DATASET_FILE, FIGURE_FILE,  # noqa: F401
                                          IDENTITY_FILE, METRICS, PARTS_DIR, RECORD_FILE,
                                          part_name, read_part, cell_text as _text)
from fwdstep.sweeps.identity import check_identity, sweep_identity

#: No fixed largest batch: a group runs in as few batches as the memory allows
#: (``variant_bytes`` per variant, ``--max-memory`` shared by the batches running at once):
#: every batch pays the run loop's per-step Python cost again, so a 4096-variant sweep in
#: batches of 512 ran 2.45x the batched hand loop, in one batch 1.0x (docs/performance.md).
MAX_BATCH = None
#: Default bound on the memory of the batches running at once (bytes).
DEFAULT_MAX_MEMORY = 1_000_000_000
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
    signal_number: int = signal.SIGINT             # what interrupted it (exit 128 + this)
    settings: dict = field(default_factory=dict)   # simulation settings of the first variant
    parts: list = field(default_factory=list)      # in-memory batch outcomes (no outdir)
    outdir: str | None = None                      # where the parts were written
    keep_signals: bool = False                     # parts hold every variant's error signal
    signal_info: dict = field(default_factory=dict)  # the error signal's name, label, unit
    base_spec: object = None                       # the diagram as loaded (its record)
    lost: int = 0                                  # variants whose worker died
    write_failed: str = ""                         # a part could not be written (disk full)

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

    def to_pandas(self):
        """The table as a pandas DataFrame indexed by variant (numbers as numbers)."""
        import pandas as pd
        frame = pd.DataFrame(self.rows()).set_index("variant")
        for column in frame.columns:
            converted = pd.to_numeric(frame[column].replace("", np.nan), errors="coerce")
            if converted.notna().sum() == (frame[column] != "").sum():
                frame[column] = converted
        return frame

    def to_xarray(self):
        """The error signal of every variant as an xarray Dataset (``fwdstep.results.labelled``)."""
        from fwdstep.results.labelled import sweep_dataset
        return sweep_dataset(self)

    def write(self, outdir, plots: bool = True, dataset: bool = False,
              record: dict | None = None) -> list:
        """Write sweep.csv, sweep.png, (``dataset=True``, when signals were kept) sweep.nc,
        and sweep.json with the copy of the diagram as run (``diagram/``) and the record of
        what made the sweep (``fwdstep.results.provenance``; ``record``: what only the
        caller knows, e.g. the command line) into ``outdir`` (a directory name, or the
        ``OutputDir`` of ``open_sweep_output``) through the output transaction
        (``fwdstep.results.outputs``: locked, listed in the manifest, no link followed,
        nothing of the user's replaced); returns the paths written."""
        if not isinstance(outdir, OutputDir):
            with OutputDir.lock_only(outdir, force=True, expected=[
                    CSV_FILE, FIGURE_FILE, DATASET_FILE, RECORD_FILE]) as out:
                return self.write(out, plots, dataset, record)
        out = outdir
        written = self._write_record(out, record)
        rows = self.rows()
        buf = io.StringIO()
        columns = ["variant", *self.names, "batch", "status", "diverged_at", *METRICS,
                   "message"]
        writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in row.items()})
        written.append(out.put(CSV_FILE, lambda fh: fh.write(buf.getvalue())))
        if dataset and self.has_signals():
            ds = self.to_xarray()
            written.append(out.put_path(DATASET_FILE, ds.to_netcdf))
        if plots and self.metric_signal is not None and any(v.metrics for v in self.variants):
            from fwdstep.results.plotting import figure_bytes
            data = figure_bytes(sweep_figure(self), "png")
            written.append(out.put(FIGURE_FILE, lambda fh: fh.write(data), binary=True))
        return written

    def _write_record(self, out: OutputDir, record: dict | None) -> list:
        if self.base_spec is None:
            return []
        from fwdstep.results import provenance
        copied = []

        def put(name: str, data: bytes) -> None:         # diagram/...: the transaction too
            copied.append(out.put(name, lambda fh: fh.write(data), binary=True))
        copies = provenance.copy_sources(self.base_spec, out.target, write=put)
        prov = provenance.record_spec(self.base_spec, copies, record,
                                      backend=self.settings.get("backend"))
        doc = {"diagram": copies["diagram"], "provenance": prov,
               "sweep": {"parameters": list(self.names),
                         "variants": [_jsonable(v.values) for v in self.variants],
                         "counts": self.counts(), "wall_time_s": round(self.wall_time, 6)}}
        text = json.dumps(doc, indent=2)
        return [out.put(RECORD_FILE, lambda fh: fh.write(text))] + copied

    def has_signals(self) -> bool:
        return self.keep_signals and any(v.status in ("ok", "diverged") for v in self.variants)

    def iter_parts(self):
        """Every finished batch's outcome (dict of arrays), from memory or from disk."""
        yield from self.parts
        if self.outdir is not None:       # only the parts fwdstep's manifest lists
            for name in sorted(owned_files(self.outdir)):
                if name.startswith(PARTS_DIR + "/") and name.endswith(".npz"):
                    yield read_part(os.path.join(self.outdir, name))


# ---------------------------------------------------------------------------- planning
@dataclass
class BatchJob:
    """One batch, with everything a worker needs (picklable: specs and blocks travel)."""
    number: int
    indices: list
    specs: list
    blocks: list
    metric: str | None
    keep_signals: bool
    traces: frozenset
    values: list                  # the swept values of each variant (for the parts)
    max_log_bytes: int | None = None   # fwdstep.simulate refuses a larger log (--max-memory)
    # compiled backend: the batches differ in structure (sizes), so each runs the program
    # whose sizes are run-time values (one compile for them all), not its own scalar code
    sizes_at_run_time: bool = False
    #: plugin files of this process (real path -> source text), sent to Dask workers, which
    #: load them before the specs (which name plugin classes) are unpickled
    plugins: dict = field(default_factory=dict)

    def __getstate__(self) -> dict:
        """Sent to a worker without the blocks (they may hold unpicklable closures); the
        worker builds them again from the specs (``instantiate_variants``).  With plugins the
        specs travel as bytes, unpickled by ``ready`` once the plugins are loaded."""
        state = {**self.__dict__, "blocks": None}
        if self.plugins and not isinstance(self.specs, bytes):
            state["specs"] = pickle.dumps(self.specs, protocol=pickle.HIGHEST_PROTOCOL)
        return state

    def ready(self) -> None:
        """In the worker: load the plugin files it was sent, then the specs."""
        if isinstance(self.specs, bytes):
            from fwdstep.structure.library import load_plugin_sources
            load_plugin_sources(self.plugins)
            self.specs = pickle.loads(self.specs)

    def variant_blocks(self) -> list:
        self.ready()
        if self.blocks is None:
            self.blocks = instantiate_variants(self.specs, {})
        return self.blocks


def settings_key(spec, memo: dict | None = None) -> tuple:
    """Everything in a diagram spec that may change a variant's numbers besides its blocks:
    every field of the spec (the simulation settings object whole, log, metrics, connections,
    ...) except the parameters and the ``--set`` overrides the spec was made with (which
    reach the numbers only through the blocks) and the blocks themselves
    (``structure_signature``).  Fields are read, never listed, so settings
    added later are included.  ``memo`` (kept by the caller while all the specs are alive)
    reuses the key of fields that are the very same objects as an earlier spec's (variants
    derived from one load share their connections, log, ...)."""
    rest = [(name, getattr(spec, name)) for name in _field_names(type(spec))
            if name not in _NOT_SETTINGS]
    if memo is not None:
        shared = tuple(id(value) for name, value in rest if name != "simulation")
        if shared not in memo:
            memo[shared] = settings_key(dataclasses.replace(
                spec, simulation=None, parameters={}, blocks=[], overrides={}, sources=[],
                unused=[]))
        return memo[shared] + settings_key(spec.simulation)
    try:            # equal bytes: equal content (unequal bytes only split a batch further)
        return (pickle.dumps(rest, protocol=pickle.HIGHEST_PROTOCOL),)
    except (pickle.PicklingError, TypeError, AttributeError):
        return tuple((name, _value_key(_plain(value))) for name, value in rest)


#: spec fields that never reach the numbers on their own: the parameters and overrides reach
#: them only through the blocks, the files read are a record of where they came from
_NOT_SETTINGS = ("parameters", "blocks", "overrides", "sources", "unused")


@functools.lru_cache(maxsize=None)
def _field_names(cls) -> tuple:
    return tuple(f.name for f in dataclasses.fields(cls))


def _plain(value):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def batchable(spec) -> bool:
    """Whether variants of this spec may share a batch: fixed-step Runge-Kutta solvers, on the
    NumPy backend (arrays with a batch axis) or the compiled one (``run_batch``: each variant
    on its own row, in parallel).  An adaptive solver would choose one step sequence for the
    whole batch, which is not each variant's own run."""
    from fwdstep.core.solvers import TABLEAUX
    cfg = spec.simulation
    return cfg.solver in TABLEAUX and getattr(cfg, "backend", "numpy") in ("numpy", "compiled")


def variant_bytes(spec, blocks, metric: str | None, logged_only: bool = False) -> tuple:
    """(bytes one variant needs in a batch, what they are for the message): the logged error
    signal (8 bytes x components x rows) plus the state buffers of the solver stages and the
    signal buffers of a stage with the kernels' temporaries (4 copies of every output)
    (``logged_only``: the signal alone)."""
    cfg = spec.simulation
    rows = cfg.n_steps // cfg.log_every + 2
    size = 0
    if metric is not None:
        owner, _, port = spec.aliases.get(metric, metric).rpartition(".")
        for b in blocks:
            if b.name == owner and port in b.outputs:
                size = b.outputs[port].size
    n_states = sum(b.n_states for b in blocks)
    signals = sum(port.size for b in blocks for port in b.outputs.values())
    logged = 8 * size * rows
    work = 0 if logged_only else 8 * (n_states * 12 + signals * 4)
    return logged + work, (f"{_mb(logged + work)} ({metric}: {size} value(s) x {rows} rows"
                           f" logged, plus {n_states} states and {signals} signal values)"
                           if metric else f"{_mb(work)} ({n_states} states, {signals} signal "
                                          "values)")


def parse_size(text) -> int:
    """``--max-memory``: a number of bytes or a size as ``fwdstep.core.budgets.parse_size`` reads
    it (2GB, 500MB, 1.5GiB, 1e9); more than zero."""
    from fwdstep.core.budgets import parse_size as size
    try:
        n = int(text) if isinstance(text, (int, float)) else size(text)
    except ConfigError as exc:
        raise ConfigError(f"--max-memory: {exc}") from None
    if n <= 0:
        raise ConfigError(f"--max-memory '{text}' must be more than zero bytes")
    return n


def plan_batches(specs, blocks, metric, *, sequential=False, workers=1,
                 max_memory=DEFAULT_MAX_MEMORY, batch_size=None) -> list:
    """Lists of variant indices, one per batch (see the module docstring)."""
    groups: dict = {}
    memo: dict = {}
    for i, (spec, blks) in enumerate(zip(specs, blocks)):
        # a Stop block ends a whole batch's run: those variants run one by one
        if sequential or not batchable(spec) or any(b.stops_run for b in blks):
            groups[("alone", i)] = [i]
            continue
        groups.setdefault((settings_key(spec, memo), structure_signature(blks)), []).append(i)
    per_batch = max_memory // max(1, workers)
    out = []
    for members in groups.values():
        need, what = variant_bytes(specs[members[0]], blocks[members[0]], metric)
        if need > per_batch:
            raise ConfigError(
                f"one variant needs {what}, more than the memory allowed per batch: "
                f"{_mb(per_batch)} (--max-memory {_mb(max_memory)} over {max(1, workers)} "
                f"worker(s)); raise --max-memory, use fewer --workers or log less often "
                f"(simulation.log_every)")
        limit = min(per_batch // max(need, 1), batch_size or len(members))
        if workers > 1 and batch_size is None:           # at least one batch per worker
            limit = min(limit, math.ceil(len(members) / workers))
        limit = max(1, limit)
        n = math.ceil(len(members) / limit)              # balanced sizes
        out.extend(list(chunk) for chunk in np.array_split(members, n))
    return [[int(i) for i in chunk] for chunk in out]


def _mb(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e9 else f"{n / 1e6:.3g} MB"


# ---------------------------------------------------------------------------- one batch
def run_job(job: BatchJob) -> dict:
    """Run one batch (in this process or a worker); returns its outcome as a dict of arrays
    (what ``OUTDIR/parts/*.npz`` holds)."""
    job.ready()
    outcomes = _run_members(job, list(range(len(job.indices))))
    n = len(job.indices)
    part = {"indices": np.asarray(job.indices, dtype=np.int64),
            "batch": np.full(n, job.number, dtype=np.int64),
            "status": np.array([o["status"] for o in outcomes], dtype=str),
            "message": np.array([o["message"] for o in outcomes], dtype=str),
            "diverged_at": np.array([np.nan if o["diverged_at"] is None else o["diverged_at"]
                                     for o in outcomes]),
            "metrics": np.array([[o["metrics"].get(m, np.nan) for m in METRICS]
                                 for o in outcomes], dtype=float).reshape(n, len(METRICS)),
            "values": np.array([json.dumps(_jsonable(v)) for v in job.values], dtype=str)}
    signals = [o for o in outcomes if o.get("e") is not None]
    if signals:
        longest = max(signals, key=lambda o: len(o["t"]))
        t = longest["t"]
        shape = longest["e"].shape[1:]
        e = np.full((len(t), n) + shape, np.nan)
        for k, o in enumerate(outcomes):
            if o.get("e") is not None:
                e[:len(o["t"]), k] = o["e"]
        part.update(t=t, e=e, has_signal=np.array([o.get("e") is not None for o in outcomes]))
    if job.metric is not None:     # e's real name, label and unit (figures, fwdstep compare)
        from fwdstep.results.plotting import signal_record
        record = signal_record(job.specs[0], job.variant_blocks()[0], job.metric)
        part.update(signal_info=np.array(json.dumps(record)),
                    diagram=np.array(str(job.specs[0].file or "")))
    return part


def _run_members(job: BatchJob, members: list) -> list:
    """Outcome dicts for ``members`` (positions in the job) run as one batch."""
    specs = [job.specs[k] for k in members]
    try:
        d = compile_variants(specs, [job.variant_blocks()[k] for k in members])
    except DiagramError as exc:        # a variant's wiring does not hold (e.g. a new port)
        if len(members) > 1:
            return [o for k in members for o in _run_members(job, [k])]
        return [{"status": "error", "message": str(exc), "diverged_at": None, "metrics": {}}]
    metric = job.metric
    d.logged = [d.resolve(metric)] if metric is not None else []
    d.sizes_at_run_time = job.sizes_at_run_time
    try:
        r = simulate(d, max_log_bytes=job.max_log_bytes)
    except DivergenceError as exc:
        r = exc.result
    except BudgetError as exc:           # over the log budget (plan_batches keeps it under)
        return [{"status": "error", "message": str(exc), "diverged_at": None,
                 "metrics": {}} for _ in members]
    except SimulationInterrupted:
        raise KeyboardInterrupt from None
    except BlockRuntimeError as exc:
        if len(members) > 1:                 # find which variants fail: one by one
            return [o for k in members for o in _run_members(job, [k])]
        return [{"status": "error", "message": str(exc), "diverged_at": None, "metrics": {}}]
    tail = specs[0].metrics.get("tail", 0.2)
    every = None                          # every variant's metrics, in a few NumPy calls
    if metric is not None:
        signal = r[d.resolve(metric)]
        every = batch_error_metrics(r.t, signal[:, None] if d.batch == 1 else signal, tail)
    out = []
    for b, k in enumerate(members):
        o = {"status": "ok", "message": "", "diverged_at": None, "metrics": {}}
        if r.status == "stopped" and d.batch == 1:
            # a Stop block ended this variant's run early (its metrics are at that time):
            # the sweep said only 'ok', as for a run to t_final
            o["message"] = r.message
        died = r.diverged_at[b] if r.diverged_at is not None else np.nan
        if np.isfinite(died):
            reason = r.reasons.get(b) or (r.message if d.batch == 1 else "")   # block, port
            o.update(status="diverged", diverged_at=float(died),
                     message=reason or f"diverged at t = {died:.6g}")
        if metric is not None:
            e, t = r.variant(b)[d.resolve(metric)], r.t
            if o["status"] == "diverged":
                keep = t < died
                t, e = t[keep], e[keep]
            else:                        # the same numbers as error_metrics(t, e, tail)
                o["metrics"] = every[b]
            if job.keep_signals or job.indices[k] in job.traces:
                o.update(t=np.array(t), e=np.array(e))
        out.append(o)
    return out


# ---------------------------------------------------------------------------- running
def run_sweep(path: str, grid: dict | None = None, random: dict | None = None,
              samples: int = 0, seed: int = 0, overrides: dict | None = None,
              sequential: bool = False, progress=None, *, design: str = "random",
              seed_parameter: str | None = None, workers: int | None = None,
              client=None, scheduler: str | None = None,
              max_memory=DEFAULT_MAX_MEMORY, batch_size: int | None = None,
              outdir: str | None = None, resume: bool = False,
              keep_signals: bool = True, variants: list | None = None,
              backend: str | None = None, force: bool = False,
              dataset: bool = False) -> SweepResult:
    """Run every variant of the diagram at ``path``; see the module docstring.

    ``grid`` maps parameter names to lists of values; ``random`` maps names to
    ``fwdstep.sweeps.sampling.Distribution`` or (low, high) for uniform; ``overrides`` are fixed for
    all variants.  ``workers`` local processes (default: every local core), or ``client`` (a
    ``dask.distributed.Client``) / ``scheduler`` (its address).  With ``outdir`` each
    finished batch is written to ``outdir/parts`` at once and ``resume=True`` skips the
    variants found there.  ``variants`` (instead of grid/random) lists the variants
    explicitly, one dict of parameter values each (a missing name keeps the diagram's
    value).  ``progress(text)`` is told about each finished batch.  ``backend`` ('numpy' or
    'compiled') sets ``simulation.backend`` for every variant; compiled sweeps run in one
    process unless ``workers`` is given (numba runs a batch's variants on every core).
    Raises ``DiagramError`` for a bad diagram or bad sweep options (nothing is run then)."""
    grid, random, overrides = dict(grid or {}), dict(random or {}), dict(overrides or {})
    wall0 = time.perf_counter()
    if variants is not None:
        if grid or random:
            raise ConfigError("give either variants or grid/random, not both")
        all_values = [dict(v) for v in variants]
        names = list(dict.fromkeys(k for v in all_values for k in v))
    else:
        all_values = variant_values(grid, random, samples, seed, design)
        names = list(grid) + list(random)
    if backend is not None:
        if "simulation.backend" in names:
            raise ConfigError("simulation.backend is both swept and set with --backend")
        overrides["simulation.backend"] = backend
    if seed_parameter is not None:
        if seed_parameter in names:
            raise ConfigError(f"--seed-parameter {seed_parameter} is also swept")
        for values, s in zip(all_values, variant_seeds(len(all_values), seed)):
            values[seed_parameter] = s
        names.append(seed_parameter)
    if not all_values:
        raise ConfigError("nothing to sweep: the list of variants is empty")
    if len(all_values) > MAX_VARIANTS:
        raise ConfigError(f"the sweep has {len(all_values)} variants; the limit is "
                          f"{MAX_VARIANTS}")
    with contextlib.ExitStack() as stack:
        out = outdir
        if outdir is not None and not isinstance(outdir, OutputDir):
            out = stack.enter_context(open_sweep_output(outdir, force=force, resume=resume))
        elif resume and outdir is None:
            raise ConfigError("--resume needs the output directory of the interrupted sweep "
                              "(-o)")
        loader = VariantSpecs(path, overrides)   # each variant's spec derived from one load
        base = loader.base
        for name in names:
            if name not in base.parameters and "." not in name:   # paths: load_spec checks
                raise ConfigError(f"--grid/--random {name}: the diagram has no parameter "
                                  f"'{name}'; parameters are: {', '.join(base.parameters)}",
                                  file=base.file)
            if name in overrides:
                raise ConfigError(f"parameter '{name}' is both swept and set with --set")
        identity = sweep_identity(
            path, loader, overrides, all_values,
            {"grid": grid, "random": random, "samples": samples, "seed": seed,
             "design": design, "seed_parameter": seed_parameter,
             "variants": variants is not None, "keep_signals": bool(keep_signals)})
        if out is not None and resume:
            check_identity(out, identity)       # before anything is built or run
        own_client = client is None and scheduler is not None
        if own_client:
            client = stack.enter_context(contextlib.closing(dask_client(scheduler)))
        if client is not None:
            check_workers(client, scheduler)     # a cluster without workers: say so
        specs, blocks = [], []
        collector = stack.enter_context(_CollectorSpared())
        for k, values in enumerate(all_values):
            try:
                spec, built = loader.load(values)
                blocks.append(built)
            except DiagramError as exc:
                shown = ", ".join(f"{key}={_text(v)}" for key, v in values.items())
                raise type(exc)(f"variant {shown}: {exc.message}", file=exc.file,
                                line=exc.line, block=exc.block, port=exc.port) from None
            specs.append(spec)
            if k == min(1, len(all_values) - 1):   # before the rest is built
                if workers is None and client is None:
                    workers = 1 if spec.simulation.backend == "compiled" else local_cores()
                concurrent = (_client_workers(client) if client is not None
                              else max(1, int(workers)))
                check_sweep_memory(specs, blocks, base.metrics.get("error"),
                                   len(all_values), concurrent, parse_size(max_memory),
                                   in_memory=out is None or dataset)
        collector.built()
        table = [Variant(i, values) for i, values in enumerate(all_values)]
        if any(s.simulation.backend == "compiled" for s in specs):
            _need_numba(path)
        if out is not None and not resume:       # a new sweep: the old one's files go
            out.discard(out.owned(PARTS_DIR + "/") + out.owned(IDENTITY_FILE))
            _refuse_foreign_parts(out)
            out.put(IDENTITY_FILE, lambda fh: json.dump(identity, fh, indent=1))
        return _run_planned(path, names, all_values, specs, blocks, base, table, client,
                            concurrent, sequential, max_memory, batch_size, out, resume,
                            keep_signals, progress, wall0)


class _CollectorSpared:
    """Python's cyclic garbage collector kept off the variants (thousands of specs and blocks
    alive for the whole sweep): paused while they are derived, which makes them at once and
    would have every collection of the older generations traverse them again and again, then
    frozen (``built``: ``gc.freeze`` moves what exists to the permanent generation) while the
    batches run.  At 4096 variants of slotine_li.yaml the collector took 12 % of a 2 s sweep's
    CPU time (docs/performance.md).  On the way out what was frozen here is unfrozen
    (collectable as usual) and the caller's collector state comes back; a process that had
    frozen objects of its own keeps them frozen, and nothing is frozen here then
    (``gc.unfreeze`` would release its objects too)."""

    def __enter__(self):
        self.was_enabled, self.mine = gc.isenabled(), gc.get_freeze_count() == 0
        gc.disable()
        return self

    def built(self) -> None:
        """The variants are built: freeze them, and collect again what the batches make."""
        if self.mine:
            gc.freeze()
        if self.was_enabled:
            gc.enable()

    def __exit__(self, *exc) -> None:
        if self.mine:
            gc.unfreeze()
        if self.was_enabled:
            gc.enable()


@contextlib.contextmanager
def open_sweep_output(outdir: str, force: bool = False, resume: bool = False):
    """The output directory of a sweep, locked for the whole sweep (``fwdstep.results.outputs``:
    one sweep per directory) and checked before anything runs: the user's own sweep.csv,
    sweep.png, sweep.nc or a link in place of ``parts/`` are never replaced (not even with
    ``force``); an earlier sweep's files need ``resume`` (finish it) or ``force`` (start again,
    removing only the files fwdstep's manifest lists).  Yields the ``OutputDir``."""
    with OutputDir.lock_only(outdir, force=True, expected=[CSV_FILE, FIGURE_FILE, DATASET_FILE,
                                                           IDENTITY_FILE, RECORD_FILE]) as out:
        out.check_subdir(PARTS_DIR)
        earlier = [n for n in (CSV_FILE, IDENTITY_FILE) if n in out.owned()] + \
            out.owned(PARTS_DIR + "/")
        if earlier and not (force or resume):
            raise OutputError(f"{os.path.join(outdir, earlier[0])} already exists; pass "
                              "--resume to finish that sweep, --force to overwrite it or -o "
                              "to choose another directory")
        yield out


def _refuse_foreign_parts(out: OutputDir) -> None:
    """After fwdstep's own parts are removed, a file named like one (the user's) would be
    taken for a finished batch by readers that look for them: refuse to start."""
    folder = os.path.join(out.target, PARTS_DIR)
    ours = set(out.owned(PARTS_DIR + "/"))
    for path in sorted(glob.glob(os.path.join(glob.escape(folder), "variants-*.npz"))):
        name = f"{PARTS_DIR}/{os.path.basename(path)}"
        if name not in ours:
            raise OutputError(f"refusing to start: {os.path.join(out.requested, name)} is a "
                              "file fwdstep did not write, named like a finished batch (move "
                              "it away or choose another directory with -o)")


def _parameter_bytes(block) -> int:
    """Bytes of the numeric arrays a built block holds (its run-time parameters and values)."""
    arrays = {id(v): v.nbytes for v in (*vars(block.p).values(), *block.values.values())
              if isinstance(v, np.ndarray)}
    return sum(arrays.values())


def check_sweep_memory(specs, blocks, metric, n: int, workers: int, max_memory: int,
                       in_memory: bool) -> None:
    """Refuse, from the first variants built and before the others are, a sweep whose memory
    exceeds ``max_memory``: one variant in a batch (``variant_bytes``: its logged signal and
    state buffers, per worker), and all ``n`` variants together -- the block parameters each
    variant holds for the whole sweep (measured: what the last variant built that the first
    does not share) and, when the signals are kept in memory (no output directory, or the
    NetCDF dataset), every variant's logged signal."""
    per_batch = max_memory // max(1, workers)
    need, what = variant_bytes(specs[-1], blocks[-1], metric)
    if need > per_batch:
        raise BudgetError(
            f"one variant needs {what}, more than the memory allowed per batch: "
            f"{_mb(per_batch)} (--max-memory {_mb(max_memory)} over {max(1, workers)} "
            f"worker(s)); raise --max-memory, use fewer --workers or log less often "
            f"(simulation.log_every)", file=specs[-1].file)
    shared = {id(b) for b in blocks[0]} if len(blocks) > 1 else set()
    own = sorted(((_parameter_bytes(b), b.name) for b in blocks[-1] if id(b) not in shared),
                 reverse=True)
    params = sum(size for size, _ in own)
    logged = variant_bytes(specs[-1], blocks[-1], metric, logged_only=True)[0] \
        if in_memory else 0
    total = n * (params + logged)
    if total > max_memory:
        pieces = [f"{_mb(params)} of block parameters ({own[0][1]}: {_mb(own[0][0])})"
                  ] if params else []
        if logged:
            pieces.append(f"{_mb(logged)} of {metric} kept in memory")
        raise BudgetError(
            f"the sweep needs {_mb(total)} in memory ({n} variants x "
            f"{' + '.join(pieces)}), more than --max-memory {_mb(max_memory)}: sweep fewer "
            "variants, log less (simulation.log_every), write to a directory (-o) without "
            "--netcdf, or raise --max-memory", file=specs[-1].file)


def _run_planned(path, names, all_values, specs, blocks, base, table, client, concurrent,
                 sequential, max_memory, batch_size, out, resume, keep_signals, progress,
                 wall0) -> SweepResult:
    from fwdstep.structure.library import plugin_sources
    metric = base.metrics.get("error")
    batches = plan_batches(specs, blocks, metric, sequential=sequential, workers=concurrent,
                           max_memory=parse_size(max_memory), batch_size=batch_size)
    trace_ids = _trace_set(len(table))
    result = SweepResult(diagram=path, names=names, variants=table, batches=[],
                         traces={}, metric_signal=metric,
                         settings=_plain(base.simulation),
                         outdir=None if out is None else out.target,
                         keep_signals=keep_signals and metric is not None,
                         base_spec=base)
    done = _resume(result, out) if resume else set()
    plugins = plugin_sources({e.cls for s in specs[:1] for e in s.blocks}) \
        if client is not None else {}
    jobs = []
    structures = {structure_signature(blocks[members[0]]) for members in batches} \
        if any(s.simulation.backend == "compiled" for s in specs) else set()
    for members in batches:
        todo = [i for i in members if i not in done]
        if todo:
            jobs.append(BatchJob(len(jobs), todo, [specs[i] for i in todo],
                                 [blocks[i] for i in todo], metric, keep_signals, trace_ids,
                                 [all_values[i] for i in todo], parse_size(max_memory),
                                 len(structures) > 1, plugins))
    if done:
        first = max((v.batch for v in table if v.index in done), default=-1) + 1
        for job in jobs:
            job.number += first
    stream = run_jobs(run_job, jobs, workers=concurrent, client=client)
    try:
        for finished, (job, part) in enumerate(stream, 1):
            # a finished batch is written and counted whole: a signal arriving meanwhile (a
            # batch system's SIGTERM inside np.savez broke the zip file being written and
            # ended the sweep with a traceback) acts once the batch is kept
            with signals.held():
                stop = _take(result, job, part, out, stream, table, names, finished,
                             len(jobs), progress)
            if stop:
                break
    except KeyboardInterrupt as exc:
        stream.close()
        result.interrupted = True
        result.signal_number = int(getattr(exc, "signum", signal.SIGINT))
        for v in table:
            if v.status == "not run":
                v.status = "interrupted"
    result.wall_time = time.perf_counter() - wall0
    return result


def _take(result, job, part, out, stream, table, names, finished: int, total: int,
          progress) -> bool:
    """A finished batch into the result (and to disk): True when the sweep must stop (the
    output could not be written: what is written is kept)."""
    description = _describe(table[job.indices[0]].values, names, short=True)
    if isinstance(part, WorkerLost):      # not written: --resume runs them again
        _absorb(result, lost_part(job, part.reason))
        result.lost += len(job.indices)
    else:
        try:
            _store(result, part, out)
        except OutputError as exc:        # a full disk: stop, keep what is written
            _absorb(result, part)
            result.write_failed = str(exc)
            stream.close()
            return True
    result.batches.append((len(job.indices), description))
    if progress is not None:
        more = ("s", ", ...") if len(job.indices) > 1 else ("", "")
        lost = f" LOST ({part.reason})" if isinstance(part, WorkerLost) else " done"
        progress(f"batch {finished}/{total}{lost}: {len(job.indices)} "
                 f"variant{more[0]} ({description}{more[1]})")
    return False


def lost_part(job: BatchJob, reason: str) -> dict:
    """The rows of a batch whose worker died: every variant an error 'worker lost: ...'."""
    n = len(job.indices)
    return {"indices": np.asarray(job.indices, dtype=np.int64),
            "batch": np.full(n, job.number, dtype=np.int64),
            "status": np.array(["error"] * n, dtype=str),
            "message": np.array([f"worker lost: {reason}; --resume runs it again"] * n,
                                dtype=str),
            "diverged_at": np.full(n, np.nan),
            "metrics": np.full((n, len(METRICS)), np.nan),
            "values": np.array([json.dumps(_jsonable(v)) for v in job.values], dtype=str)}


def _need_numba(path: str) -> None:
    try:
        import numba  # noqa: F401
    except ImportError:
        raise ConfigError("backend 'compiled' needs numba: pip install 'fwdstep[fast]' (or "
                          "use --backend numpy)", file=path) from None


def _client_workers(client) -> int:
    try:
        return max(1, sum(client.nthreads().values()))
    except Exception:  # noqa: BLE001 - an unusual client: assume one worker
        return 1


def _store(result: SweepResult, part: dict, out: OutputDir | None) -> None:
    """Take a finished batch into the table (and the traces); write it to disk first
    (``OutputDir.put``: listed in the manifest, then renamed into ``parts/``)."""
    if out is not None:
        out.put(part_name(part["indices"][0]), lambda fh: np.savez(fh, **part), binary=True)
    else:
        result.parts.append(part)
    _absorb(result, part)


def _absorb(result: SweepResult, part: dict) -> None:
    if "signal_info" in part and not result.signal_info:
        result.signal_info = json.loads(str(part["signal_info"]))
    traced = _trace_set(len(result.variants))
    batch, status = part["batch"].tolist(), part["status"].tolist()
    message, diverged = part["message"].tolist(), part["diverged_at"].tolist()
    metrics = part["metrics"].tolist()              # Python floats: the same numbers
    for k, i in enumerate(part["indices"].tolist()):
        v = result.variants[i]
        v.batch = batch[k]
        v.status = status[k]
        v.message = message[k]
        died = diverged[k]
        v.diverged_at = None if math.isnan(died) else died
        v.metrics = (dict(zip(METRICS, metrics[k]))
                     if v.status == "ok" and result.metric_signal is not None else {})
        if "e" in part and part["has_signal"][k] and i in traced:
            t = part["t"]
            e = part["e"][:, k]
            keep = np.isfinite(e.reshape(len(t), -1)).all(axis=1)
            t, e = t[keep], e[keep]
            if len(t):
                result.traces[i] = (t.copy(), np.sqrt(np.sum(e.reshape(len(t), -1) ** 2,
                                                             axis=1)))


@functools.lru_cache(maxsize=8)
def _trace_set(n: int) -> frozenset:
    """The variants (of ``n``) whose error traces are kept for the figure: MAX_TRACES spread
    evenly."""
    return frozenset(np.unique(np.linspace(0, n - 1, min(MAX_TRACES, n)).astype(int)).tolist())


def _resume(result: SweepResult, out: OutputDir) -> set:
    """Read the finished batches fwdstep wrote in ``parts/`` (those its manifest lists; the
    sweep's identity was checked by ``check_identity``); check they are this sweep's."""
    done: set = set()
    for name in out.owned(PARTS_DIR + "/"):
        path = os.path.join(out.requested, name)
        part = read_part(os.path.join(out.target, name), signals=False)
        for k, i in enumerate(part["indices"].tolist()):
            mine = json.dumps(_jsonable(result.variants[i].values)) \
                if i < len(result.variants) else None
            if mine != str(part["values"][k]):
                raise ConfigError(
                    f"{out.requested} holds a different sweep: {path} has variant {i} with "
                    f"{printable(str(part['values'][k]))[:200]}, this sweep's is {mine}; use "
                    "another -o or --force to start again")
        _absorb(result, part)
        done.update(part["indices"].tolist())
        result.batches.append((len(part["indices"]), "resumed"))
    return done


def _jsonable(values: dict) -> dict:
    return {k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, np.generic)) else v)
            for k, v in values.items()}


def _shorten(text: str, limit: int = 40) -> str:
    """A label for a figure or a progress line: a matrix value's text (360 kB for a 200 x 200
    matrix) is cut, so drawing it stays cheap; equality is always decided on the full text."""
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _describe(values: dict, names: list, short: bool = False) -> str:
    """'K=20, ell=2'; ``short``: each value cut to 24 characters (labels, progress)."""
    if short:
        return ", ".join(f"{k}={_shorten(_text(values[k]), 24)}" for k in names if k in values)
    return ", ".join(f"{k}={_text(values[k])}" for k in names if k in values)


# ---------------------------------------------------------------------------- figure
def _numeric(values: list):
    try:
        arr = np.array([float(v) for v in values])
        return arr
    except (TypeError, ValueError):
        return None


def plot_sweep(result: SweepResult, outdir: str) -> str:
    """Write sweep.png into ``outdir`` (through its transaction); its path."""
    from fwdstep.results.plotting import figure_bytes
    data = figure_bytes(sweep_figure(result), "png")
    with OutputDir.lock_only(outdir, force=True, expected=[FIGURE_FILE]) as out:
        return out.put(FIGURE_FILE, lambda fh: fh.write(data), binary=True)


def sweep_figure(result: SweepResult):
    """The tail metric against each swept parameter (integer ticks when every swept value is
    a whole number), and |e|(t) traces."""
    from matplotlib.ticker import MaxNLocator
    from fwdstep.results.plotting import (LineKey, SignalInfo, finish_figure, line_colors,
                                          new_figure, place_legend, safe_label)

    rec = result.signal_info or {}     # the diagram's label and unit, as the run figures
    info = SignalInfo(str(result.metric_signal), safe_label(rec.get("label") or
                                                            str(result.metric_signal)),
                      rec.get("unit") or "")
    norm_label = f"|{info.label}|"
    ok = [v for v in result.variants if v.metrics]
    n_panels = len(result.names) + 1
    # the run figures' style (fwdstep.results.plotting): no pyplot, the caller's backend untouched
    fig, axes = new_figure(n_panels, sharex=False, height=2.8 * n_panels + 0.9)
    for ax, name in zip(axes, result.names):
        raw = [v.values[name] for v in ok]
        x = _numeric(raw)
        if x is None:                                   # expressions: categories in order
            labels = list(dict.fromkeys(_text(r) for r in raw))
            x = np.array([labels.index(_text(r)) for r in raw], dtype=float)
            ax.set_xticks(range(len(labels)), [_shorten(t) for t in labels], fontsize=7)
        others = [n for n in result.names if n != name]
        series = _series(ok, others)
        for key, (label, marker) in series.items():
            sel = [k for k, v in enumerate(ok) if _describe(v.values, others) == key]
            order = np.argsort(x[sel], kind="stable")
            color = None
            for metric, style in (("tail_error_norm_max", "-"), ("final_error_norm", ":")):
                y = np.array([ok[k].metrics[metric] for k in sel])
                line, = ax.plot(x[sel][order], y[order], style if len(series) <= 10 else "",
                                marker=marker, ms=4 if len(series) <= 10 else 2, lw=1,
                                color=color,
                                label=(f"max {norm_label} over tail" if style == "-" else
                                       f"final {norm_label}")
                                      + (f", {label}" if label else ""))
                color = line.get_color()
        diverged = [v for v in result.variants if v.status == "diverged"]
        if diverged:
            xd = _numeric([v.values[name] for v in diverged])
            if xd is not None:
                top = max([max(v.metrics.values()) for v in ok] + [1.0])
                ax.plot(xd, np.full(len(xd), top), "rx", label="diverged")
        ax.set_yscale("log")
        if _numeric(raw) is not None and np.all(x == np.round(x)):   # 1, 2, 3: never 1.25
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel(name)
        ax.set_ylabel(info.axis_label(absolute=True))
        ax.grid(True, alpha=0.3, which="both")
        place_legend(ax)
    ax = axes[-1]
    traces = sorted(result.traces.items())
    colors = line_colors(len(traces))
    names = [_describe(result.variants[i].values, result.names, short=True)
             for i, _ in traces]
    for color, name, (i, (t, norm)) in zip(colors, names, traces):       # one colour each
        ax.semilogy(t, np.maximum(norm, 1e-300), lw=1, color=color, label=name)
    ax.set_xlabel("$t$ [s]")
    ax.set_ylabel(f"{norm_label}(t)" + (f" [{info.unit}]" if info.unit else ""))
    ax.grid(True, alpha=0.3, which="both")
    place_legend(ax, key=LineKey(tuple(colors), tuple(names), "variant",
                                 color_values=tuple(i for i, _ in traces)))
    if 0 < len(traces) < len(result.variants):          # say so: never a silent selection
        ax.set_title(f"{len(traces)} of {len(result.variants)} variants drawn", fontsize=8)
    finish_figure(fig, f"Sweep of {os.path.basename(result.diagram)}: "
                       f"{len(result.variants)} variants")
    return fig


def _series(ok: list, others: list) -> dict:
    """One line per combination of the other swept parameters (at most 10 drawn as lines)."""
    keys = list(dict.fromkeys(_describe(v.values, others) for v in ok))
    markers = "os^vD<>ph*"
    if len(keys) > len(markers):
        return {k: ("", "o") for k in keys}
    short = {k: _describe(v.values, others, short=True) for v in ok
             for k in [_describe(v.values, others)]}
    return {k: (short[k], markers[n]) for n, k in enumerate(keys)}


# ---------------------------------------------------------------------------- command


__all__ = ["run_sweep", "SweepResult", "Variant", "parse_grid", "parse_random",
           "variant_values", "plan_batches", "settings_key", "parse_size"]
