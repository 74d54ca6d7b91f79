"""Simulation results: recorded signals, summary metrics, and safe writing to disk."""
from __future__ import annotations

import html
import json
import os
import tempfile
from dataclasses import dataclass

import numpy as np

from fwdstep.core.errors import DamagedFileError, OutputError, printable
from fwdstep.core.files import atomic_write, safe_path  # noqa: F401  (re-exported for readers of results)
from fwdstep.core.jsonable import jsonable as _jsonable

RESULT_FILE = "result.npz"
SUMMARY_FILE = "summary.json"


@dataclass(frozen=True)
class CrossingEvent:
    """One located state event (``fwdstep.run.crossings``): ``time`` (s), ``block`` (name),
    ``kind`` (guard name and direction, e.g. 'upper rising', or 'chattering'), ``variant``
    (of a batch).  Listed in ``Result.events`` and in summary.json's "events"."""
    time: float
    block: str
    kind: str
    variant: int = 0


def events_line(events) -> str:
    """One line about a run's located state events, e.g. "2 state events located (first:
    t = 2.37 s, block 'sat' upper falling)"."""
    first = events[0]
    where = f" in variant {first.variant}" if first.variant else ""
    return (f"{len(events)} state event{'s' if len(events) != 1 else ''} located (first: "
            f"t = {first.time:.9g} s, block '{first.block}' {first.kind}{where})")


#: what asking a Result without sensitivities for one says (a loaded Result never has
#: them: ``save`` / ``load_result`` keep the run's signals, not its sensitivities)
NO_SENSITIVITIES = ("this result has no sensitivities: run fwdstep.simulate(d, "
                    "sensitivities=[...]) to get them (they are not saved with a result: "
                    "one loaded from disk has none)")

class Result:
    """Time plus named signals of fixed shape.

    ``result.t`` is (T,); ``result["block.port"]`` is (T, *shape) for a single run and
    (T, B, *shape) for a batch of B variants.  Subsystem port names ('plant.q') work too.
    """

    def __init__(self, t, signals: dict, diagram=None, status: str = "ok", message: str = "",
                 wall_time: float = 0.0, steps: int = 0, diverged_at=None, reasons=None,
                 events=None, notes=None):
        self.t = t
        self._signals = signals
        self.diagram = diagram
        self.status = status
        self.message = message
        self.wall_time = wall_time
        self.steps = steps
        self.batch = diagram.batch if diagram is not None else 1
        self.diverged_at = diverged_at
        self.reasons = dict(reasons or {})    # batch: variant -> why it diverged (one line)
        #: forward sensitivities (``fwdstep.sensitivities``): {"signals": name -> (rows,
        #: size, P), "parameters": [(text, first column, end column, shape)]}, else None
        self.sensitivity_data = None
        #: located zero crossings: (time, block, kind, variant) (fwdstep.run.crossings)
        self.events = list(events or [])
        self.notes = list(notes or [])        # one line each (chattering, a fallback)
        self.limits = []     # operating limits reached (fwdstep.run.limits.limit_record)

    def __repr__(self) -> str:
        """One line: status (and why), time range, samples, signals with their shapes."""
        status = self.status + (f" ({self.message[:80]}{'…' if len(self.message) > 80 else ''})"
                                if self.message else "")
        span = (f"t = {self.t[0]:g} .. {self.t[-1]:g} s, {len(self.t)} samples"
                if len(self.t) else "nothing recorded")
        batch = f", {self.batch} variants" if self.batch > 1 else ""
        shown = [f"{k} {_shape_text(v.shape[2:])}" for k, v in list(self._signals.items())[:8]]
        more = len(self._signals) - len(shown)
        signals = ", ".join(shown) + (f", … ({more} more)" if more > 0 else "")
        return f"<Result {status}: {span}{batch}; signals: {signals or '(none)'}>"

    @property
    def names(self) -> list:
        return list(self._signals)

    def _key(self, name: str) -> str:
        if name in self._signals:
            return name
        real = (self.diagram.resolve(name) if self.diagram is not None
                else getattr(self, "aliases", {}).get(name, name))     # loaded: stored aliases
        if real in self._signals:
            return real
        raise KeyError(f"signal '{name}' was not recorded; recorded signals are: "
                       f"{', '.join(self._signals)}")

    def __getitem__(self, name: str) -> np.ndarray:
        arr = self._signals[self._key(name)]
        return arr[:, 0] if self.batch == 1 else arr

    def __contains__(self, name: str) -> bool:
        try:
            self._key(name)
            return True
        except KeyError:
            return False

    def variant(self, b: int) -> dict:
        return {k: v[:, b] for k, v in self._signals.items()}

    # ------------------------------------------------------------------ sensitivities
    @property
    def sensitivity_parameters(self) -> list:
        """The parameters differentiated (``fwdstep.sensitivities``), as asked."""
        return [p[0] for p in (self.sensitivity_data or {}).get("parameters", [])]

    def _parameter(self, param: str) -> tuple:
        if self.sensitivity_data is None:
            raise KeyError(NO_SENSITIVITIES)
        for p in self.sensitivity_data["parameters"]:
            if p[0] == param:
                return p
        raise KeyError(f"no sensitivity with respect to '{param}'; parameters: "
                       f"{', '.join(self.sensitivity_parameters)}")

    def sensitivity_matrix(self, signal: str) -> np.ndarray:
        """d signal / d (all parameters): (T, size of the signal, P columns)."""
        if self.sensitivity_data is None:
            self._parameter("")
        key = self._key(signal)
        got = self.sensitivity_data["signals"].get(key)
        if got is None:
            raise KeyError(f"signal '{signal}' has no sensitivity (it is not logged)")
        return got

    def sensitivity(self, signal: str, param: str) -> np.ndarray:
        """d signal / d param along the run: shape of ``self[signal]`` followed by the
        parameter's shape (a scalar parameter: exactly ``self[signal].shape``)."""
        text, a, b, shape = self._parameter(param)
        S = self.sensitivity_matrix(signal)[:, :, a:b]
        sig_shape = tuple(self.diagram.signal_shapes[self.diagram.signal_index[
            self._key(signal)]]) if self.diagram is not None else (S.shape[1],)
        return S.reshape((S.shape[0],) + sig_shape + tuple(shape))

    def split_parameters(self, g: np.ndarray) -> dict:
        """A gradient over all P columns -> {parameter: array of its shape}."""
        return {text: np.asarray(g[..., a:b]).reshape(np.shape(g)[:-1] + tuple(shape))
                for text, a, b, shape in self.sensitivity_data["parameters"]}

    def metric_gradient(self, metric: str, param: str | None = None):
        """The gradient of a metric (``rms_error_norm``, ... or ``FUNCTION(SIGNAL)``: see
        ``fwdstep.results.objectives``) with respect to every differentiated parameter
        ({param: array of its shape}), or to ``param`` alone."""
        from fwdstep.results.objectives import objective
        _, grads = objective(self, metric, gradient=True)
        return grads if param is None else grads[self._parameter(param)[0]]

    # ------------------------------------------------------------------ metrics
    def metrics(self) -> dict | list:
        """Summary metrics of the signal named by ``metrics: error:`` (per variant for a batch).

        |e|(t) is the Euclidean norm over the signal's components. Reported: final |e|,
        max |e| over the last ``tail`` fraction of the run (default 20%), RMS of |e| over
        the run, and max |e| over the run.
        """
        if self.diagram is None and getattr(self, "stored", None):    # from load_result
            return self.stored.get("metrics") or {}
        if self.diagram is None or "error" not in self.diagram.spec.metrics:
            return {} if self.batch == 1 else [{} for _ in range(self.batch)]
        e = self._signals[self._key(self.diagram.spec.metrics["error"])]
        tail = self.diagram.spec.metrics.get("tail", 0.2)
        out = batch_error_metrics(self.t, e, tail)
        return out[0] if self.batch == 1 else out

    # ------------------------------------------------------------------ writing
    def summary(self, provenance: dict | None = None) -> dict:
        """What summary.json holds.  ``parameters``: the diagram's parameters as evaluated
        after ``--set``; ``blocks``: every block's parameters as evaluated (a ``--set
        Ks.gain=...`` shows there); ``simulation``: every setting as run; ``provenance``
        (``fwdstep.results.provenance``) when written into an output directory; ``diagram``
        then names the copy of the diagram as run, relative to that directory."""
        d = self.diagram
        cfg = d.spec.simulation if d is not None else None
        params = [parameter_json(p) for p in d.variant_parameters] if d is not None else []
        diagram = None
        if provenance and provenance.get("diagram"):
            diagram = provenance["diagram"]
        elif d is not None:
            diagram = os.path.abspath(d.file)
        out = {
            "status": self.status,
            "message": self.message,
            "diagram": diagram,
            "parameters": params[0] if len(params) == 1 else params,
            "simulation": settings_json(cfg, getattr(self, "backend", None)) if cfg else None,
            "t_reached": float(self.t[-1]) if len(self.t) else None,
            "steps": int(self.steps),
            "batch": self.batch,
            "wall_time_s": round(self.wall_time, 6),
            "metrics": _jsonable(self.metrics()),
            **({"limits": _jsonable(self.limits)} if self.limits else {}),
            **({"events": [{"time": float(e.time), "block": e.block, "kind": e.kind,
                            "variant": int(e.variant)} for e in self.events]}
               if self.events else {}),
            **({"notes": list(self.notes)} if self.notes else {}),
            "signals": {k: list(v.shape[2:]) for k, v in self._signals.items()},
            **_figure_summary(self),
        }
        if d is not None:        # e.g. K after --set Ks.gain=..., t_final after simulation.t_final
            out["unused_parameters"] = list(d.spec.unused)
        if d is not None and self.batch == 1:
            out["blocks"] = {e.name: {"type": e.type_name,
                                      **{k: parameter_json(v) for k, v in e.params.items()}}
                             for e in d.spec.blocks}
        if provenance:
            out["provenance"] = provenance
        return out

    def save(self, outdir: str, force: bool = True) -> list:
        """Write ``result.npz``, ``summary.json``, the copy of the diagram as run (``diagram/``,
        see ``write_files``) and ``manifest.json`` into ``outdir`` as one
        transaction (``fwdstep.results.outputs.OutputDir``: locked, staged, one rename); replaces
        results fwdstep wrote there before (``force=False`` refuses to), never another file
        or a symbolic link.  Returns the paths written."""
        from fwdstep.results.outputs import OutputDir
        from fwdstep.results.provenance import COPY_DIR
        with OutputDir(outdir, force=force, expected=[RESULT_FILE, SUMMARY_FILE,
                                                      COPY_DIR]) as out:
            self.write_files(out.dir)
            return out.commit()

    def write_files(self, outdir: str, record: dict | None = None) -> list:
        """Write ``result.npz`` and ``summary.json`` atomically into the directory ``outdir``
        (the staging directory of an ``OutputDir``; ``save`` is the transaction), and, for a
        result of a loaded diagram, the copy of the diagram as run (``diagram/``) with the
        record of what made the run (``fwdstep.results.provenance``; ``record``: what only
        the caller knows, e.g. the command line and ``--set`` as typed)."""
        os.makedirs(outdir, exist_ok=True)
        arrays = {"t": self.t}
        for k, v in self._signals.items():
            arrays[k] = v[:, 0] if self.batch == 1 else v
        provenance = None
        copied = []
        if self.diagram is not None:
            from fwdstep.results import provenance as prov
            copies = prov.copy_sources(self.diagram.spec, outdir)
            provenance = prov.record(self, copies, record)
            copied = [os.path.join(outdir, *f["copy"].split("/")) for f in copies["files"]]
        paths = [safe_path(outdir, RESULT_FILE), safe_path(outdir, SUMMARY_FILE)]
        summary = json.dumps(self.summary(provenance), indent=2)
        # both files are complete on disk before either replaces an old one
        with atomic_write(paths[0], lambda fh: np.savez(fh, **arrays), binary=True,
                          commit=False) as commit_result:
            atomic_write(paths[1], lambda fh: fh.write(summary))
            commit_result()
        return paths + copied


    # ------------------------------------------------------------------ notebooks
    def plot(self, signals=None, figure: str | None = None, scale: str = "linear",
             variants: list | None = None):
        """matplotlib Figures, made without pyplot and without touching the backend.

        ``r.plot()``: dict figure name -> Figure for the diagram's ``plots:``;
        ``r.plot(figure="torque")``: that Figure; ``r.plot("e.y")`` or
        ``r.plot(["adapt.theta_hat", "truth.y"], scale="log")``: one panel of those signals."""
        from fwdstep.results.plotting import panel_figure, result_figures
        if signals is not None:
            sigs = [signals] if isinstance(signals, str) else list(signals)
            for s in sigs:
                self._key(s)
            from fwdstep.results.plotting import signal_info
            title = ", ".join(signal_info(self, s).label for s in sigs)
            return panel_figure(self, [(sigs, scale)], title, variants=variants)
        if figure is not None:
            return result_figures(self, variants, [figure])[figure]
        return result_figures(self, variants)

    def animate(self, fps: float = 30.0):
        """The robot of this run replayed: one self-contained HTML page (a str; shown inline
        in a notebook), the plant's q logged (``fwdstep.animate``)."""
        from fwdstep.results.animate import animation_html
        return animation_html([self], fps=fps)

    def _repr_html_(self) -> str:
        """A short summary for notebooks: status, time reached, metrics, signals."""
        m = self.metrics()
        rows = [("status", self.status + (f" — {self.message}" if self.message else "")),
                ("t reached", f"{self.t[-1]:g} s" if len(self.t) else "nothing recorded"),
                ("steps", str(self.steps)), ("variants", str(self.batch))]
        if isinstance(m, dict):
            rows += [(k.replace("_", " "), f"{v:.3e}" if isinstance(v, float) else str(v))
                     for k, v in m.items()]
        rows.append(("signals", ", ".join(self.names)))
        body = "".join(f"<tr><th style='text-align:left'>{html.escape(k)}</th>"
                       f"<td style='text-align:left'>{html.escape(v)}</td></tr>" for k, v in rows)
        return f"<div><b>fwdstep Result</b><table>{body}</table></div>"

    # ------------------------------------------------------------------ labelled data
    def to_xarray(self):
        """The signals as an xarray Dataset: dims time, [variant,] and each signal's own
        component axes; attrs: status, diagram, settings (``fwdstep.results.labelled``)."""
        from fwdstep.results.labelled import result_dataset
        return result_dataset(self)

    def to_pandas(self):
        """The signals as a pandas DataFrame indexed by time, one column per component."""
        from fwdstep.results.labelled import result_frame
        return result_frame(self)


def _shape_text(shape: tuple) -> str:
    return "scalar" if not shape else "(" + ", ".join(map(str, shape)) + \
        ("," if len(shape) == 1 else "") + ")"


def load_result(outdir: str) -> Result:
    """A Result saved by ``fwdstep run`` (``result.npz`` + ``summary.json`` in ``outdir``).

    The loaded Result has no compiled diagram (``diagram`` is None): signals, status, metrics,
    labels and figures come from the files, so it plots and compares like a fresh one."""
    from fwdstep.core.errors import OutputError
    npz, summ = os.path.join(outdir, RESULT_FILE), os.path.join(outdir, SUMMARY_FILE)
    for path in (npz, summ):
        if not os.path.isfile(path):
            raise OutputError(f"{outdir} holds no saved run: {os.path.basename(path)} is missing "
                              "(write one with fwdstep run DIAGRAM -o DIR)")
    summary = read_summary(summ)
    arrays = read_arrays(npz)
    batch = int(summary.get("batch") or 1)
    problem = _arrays_problem(arrays, batch)
    if problem:
        raise DamagedFileError(f"{printable(npz)} does not fit {SUMMARY_FILE}: {problem}")
    t = arrays.pop("t")
    signals = {k: (v[:, None] if batch == 1 else v) for k, v in arrays.items()}
    r = Result(t, signals, status=summary.get("status", "ok"),
               message=summary.get("message", ""), wall_time=summary.get("wall_time_s", 0.0),
               steps=summary.get("steps", 0),
               events=[CrossingEvent(float(e["time"]), e["block"], e["kind"], e["variant"])
                       for e in summary.get("events") or []],
               notes=summary.get("notes") or [])
    r.batch = batch
    r.stored = summary
    r.limits = summary.get("limits") or []
    r.outdir = outdir
    r.signal_labels = summary.get("signal_labels") or {}
    r.figure_panels = {name: [(list(p["signals"]), p.get("scale", "linear")) for p in panels]
                       for name, panels in (summary.get("figures") or {}).items()}
    r.title = summary.get("title", "")
    r.aliases = summary.get("aliases") or {}
    return r


#: the keys of summary.json that readers use, and the JSON kinds each may have
_SUMMARY_KINDS = {
    "status": (str,), "message": (str,), "diagram": (str, type(None)), "title": (str,),
    "parameters": (dict, list, type(None)), "simulation": (dict, type(None)),
    "t_reached": (int, float, type(None)), "steps": (int,), "batch": (int,),
    "wall_time_s": (int, float), "metrics": (dict, list, type(None)),
    "signals": (dict, type(None)), "figures": (dict, type(None)),
    "signal_labels": (dict, type(None)), "aliases": (dict, type(None)),
    "events": (list, type(None)), "notes": (list, type(None)),
}
#: the fields of one entry of summary.json's "events" and their JSON kinds
_EVENT_KINDS = {"time": (int, float), "block": (str,), "kind": (str,), "variant": (int,)}


def read_summary(path: str) -> dict:
    """summary.json, checked: not JSON, or a key of the wrong kind (a hand edit) is one
    ``OutputError`` naming the file and the key."""
    from fwdstep.structure.model import kind_of
    shown = printable(path)
    try:
        with open(path, encoding="utf-8") as fh:
            summary = json.loads(fh.read(64 << 20))
    except (OSError, ValueError) as exc:        # JSONDecodeError, UnicodeDecodeError
        raise DamagedFileError(f"{shown} cannot be read: {printable(str(exc))[:200]}") from None
    if not isinstance(summary, dict):
        raise DamagedFileError(f"{shown} is not fwdstep's summary: the top level is "
                          f"{kind_of(summary)}, not a mapping")
    for key, kinds in _SUMMARY_KINDS.items():
        value = summary.get(key)
        if key in summary and (not isinstance(value, kinds) or isinstance(value, bool)):
            raise DamagedFileError(f"{shown}: '{key}' is {kind_of(value)}, which fwdstep never "
                              "writes there (was it edited by hand?)")
    if summary.get("batch", 1) < 1:
        raise DamagedFileError(f"{shown}: 'batch' must be 1 or more")
    for k, event in enumerate(summary.get("events") or []):
        if not isinstance(event, dict) or any(
                not isinstance(event.get(f), kinds) or isinstance(event.get(f), bool)
                for f, kinds in _EVENT_KINDS.items()):
            raise DamagedFileError(f"{shown}: event {k + 1} is not a mapping of time (number), "
                                   "block, kind (text) and variant (whole number)")
    if not all(isinstance(n, str) for n in summary.get("notes") or []):
        raise DamagedFileError(f"{shown}: 'notes' must be a list of text lines")
    for name, panels in (summary.get("figures") or {}).items():
        if not isinstance(panels, list) or not all(
                isinstance(p, dict) and isinstance(p.get("signals"), list)
                and all(isinstance(x, str) for x in p["signals"])
                and isinstance(p.get("scale", "linear"), str) for p in panels):
            raise DamagedFileError(f"{shown}: figure '{printable(str(name))}' is not a list of "
                              "panels {signals: [...], scale: ...}")
    for key in ("signal_labels", "aliases", "signals"):
        for name, value in (summary.get(key) or {}).items():
            if not isinstance(value, {"signal_labels": dict, "aliases": str,
                                      "signals": list}[key]):
                raise DamagedFileError(f"{shown}: '{key}' entry '{printable(str(name))}' is "
                                  f"{kind_of(value)} (was it edited by hand?)")
    return summary


def read_arrays(path: str) -> dict:
    """The arrays of result.npz, never a pickle; a truncated or corrupt file is one
    ``OutputError`` naming it."""
    import zipfile
    try:
        with np.load(path, allow_pickle=False) as data:
            if not hasattr(data, "files"):
                raise ValueError("not an .npz archive")
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile,
            zipfile.LargeZipFile, NotImplementedError) as exc:
        raise DamagedFileError(f"{printable(path)} cannot be read ({type(exc).__name__}: "
                          f"{printable(str(exc))[:200]})") from None


def _arrays_problem(arrays: dict, batch: int) -> str:
    t = arrays.get("t")
    if t is None or t.ndim != 1 or t.dtype.kind not in "fi":
        return "no time column 't'"
    for name, v in arrays.items():
        if v.dtype.kind not in "fiub":
            return f"signal '{printable(name)}' holds {v.dtype} data"
        if name == "t":
            continue
        if v.ndim < 1 or v.shape[0] != len(t) or (batch > 1 and (v.ndim < 2 or
                                                                 v.shape[1] != batch)):
            return (f"signal '{printable(name)}' has shape {v.shape} for {len(t)} times and "
                    f"{batch} variant(s)")
    return ""


def _figure_summary(result: Result) -> dict:
    """Labels, figures and headline of a run, so a loaded result plots like a fresh one."""
    if result.diagram is None:
        return {}
    from fwdstep.results.plotting import figure_specs, headline, signal_labels
    return {"title": headline(result.diagram.spec.description),
            "figures": {name: [{"signals": list(sigs), "scale": scale} for sigs, scale in panels]
                        for name, panels in figure_specs(result).items()},
            "signal_labels": signal_labels(result),
            "aliases": {k: v for k, v in result.diagram.spec.aliases.items()
                        if v in result.names}}


#: The error metrics in summary.json (docs/diagram-format.md, "Metrics").  e(t) is the signal
#: named by ``metrics: error:``, flattened per time; |e|_2 its Euclidean norm over components,
#: max_i |e_i| its largest component; "tail" is the last ``metrics: tail`` fraction (20 %) of
#: the logged time span.
METRIC_DEFINITIONS = {
    "final_error_norm": "|e(T)|_2 at the last logged time T",
    "final_error_max_abs": "max_i |e_i(T)|: the largest component (joint) error at T",
    "tail_error_norm_max": "max over the tail of |e(t)|_2",
    "tail_error_max_abs": "max over the tail and the components of |e_i(t)| (largest joint)",
    "tail_error_max_abs_by_component": "per component i: max over the tail of |e_i(t)|",
    "rms_error_norm": "sqrt(mean over logged t of |e(t)|_2^2)",
    "error_norm_max": "max over all logged t of |e(t)|_2",
}


def error_metrics(t: np.ndarray, e: np.ndarray, tail: float = 0.2) -> dict:
    """The metrics of METRIC_DEFINITIONS for the error signal ``e`` (time first)."""
    return batch_error_metrics(t, e[:, None], tail)[0]


def batch_error_metrics(t: np.ndarray, e: np.ndarray, tail: float = 0.2) -> list:
    """``error_metrics`` of every variant of ``e`` (time, variant, ...), computed together (a
    sweep's batch: a few NumPy calls instead of a few per variant).  Each variant's numbers
    are those of its own call: the sum over time runs over one variant's contiguous row, as
    it does for a variant alone (sums over a component and maxima do not depend on the
    layout)."""
    B = e.shape[1]
    if len(t) == 0:
        return [{k: None for k in METRIC_DEFINITIONS} for _ in range(B)]
    flat = e.reshape(len(t), B, -1)                                        # (T, B, n)
    with np.errstate(all="ignore"):      # a diverged run has huge, inf or NaN errors
        norm = _scaled_norm(flat, axis=2)                                   # (T, B)
        rms = _scaled_norm(np.ascontiguousarray(norm.T), axis=1) / np.sqrt(len(t))
        absolute = np.abs(flat)
    t_end = t[-1]
    mask = t >= t[0] + (1 - tail) * (t_end - t[0])
    by_component = np.max(absolute[mask], axis=0)                            # (B, n)
    columns = {
        "final_error_norm": norm[-1],
        "final_error_max_abs": np.max(absolute[-1], axis=1),
        "tail_error_norm_max": np.max(norm[mask], axis=0),
        "tail_error_max_abs": np.max(by_component, axis=1),
        "rms_error_norm": rms,
        "error_norm_max": np.max(norm, axis=0),
    }
    columns = {k: v.tolist() for k, v in columns.items()}     # Python floats, same numbers
    components = by_component.tolist()
    out = []
    for b in range(B):
        m = {k: columns[k][b] for k in ("final_error_norm", "final_error_max_abs",
                                        "tail_error_norm_max", "tail_error_max_abs")}
        m["tail_error_max_abs_by_component"] = components[b]
        m["rms_error_norm"] = columns["rms_error_norm"][b]
        m["error_norm_max"] = columns["error_norm_max"][b]
        out.append(m)
    return out


def _scaled_norm(a: np.ndarray, axis: int):
    """Euclidean norm that does not overflow for entries near the float limit."""
    scale = np.max(np.abs(a), axis=axis, keepdims=True)
    safe = np.where((scale > 0) & np.isfinite(scale), scale, 1.0)
    norm = np.sqrt(np.sum((a / safe) ** 2, axis=axis, keepdims=True)) * safe
    norm = np.where(np.isfinite(scale), norm, scale)     # inf and NaN pass through
    return np.squeeze(norm, axis=axis)


def settings_json(cfg, backend: str | None = None) -> dict:
    """Every simulation setting as run (``--set simulation.X`` and ``--backend`` applied)."""
    import dataclasses
    out = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("defaulted", "given")}
    if backend:
        out["backend"] = backend
    return _jsonable(out)


#: arrays larger than this are recorded by shape and SHA-256 instead of every number
MAX_RECORDED_NUMBERS = 4096


def parameter_json(value):
    """A parameter value as JSON, as a person would write it: whole numbers as integers
    (``ell: 2`` stays 2, not 2.0), arrays as nested lists; a very large array as its shape
    and SHA-256."""
    if isinstance(value, dict):
        return {str(k): parameter_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [parameter_json(v) for v in value]
    if isinstance(value, np.ndarray) and value.dtype.kind in "fiub":
        if value.size > MAX_RECORDED_NUMBERS:
            import hashlib
            return {"shape": list(value.shape), "dtype": value.dtype.str,
                    "sha256": hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()}
        if value.dtype.kind == "f" and np.all(np.isfinite(value)) and \
                np.all(value == np.floor(value)) and np.all(np.abs(value) < 2.0 ** 53):
            return value.astype(np.int64).tolist()
        return _jsonable(value)
    if isinstance(value, (float, np.floating)) and not isinstance(value, bool):
        if np.isfinite(value) and float(value).is_integer() and abs(value) < 2.0 ** 53:
            return int(value)
    return _jsonable(value)
