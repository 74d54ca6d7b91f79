"""Labelled results (xarray): a run's or a sweep's signals with named dimensions.

A sweep becomes one ``xarray.Dataset``::

    error(variant, time, component)      the diagram's error signal (metrics: error:)
    status(variant), diverged_at(variant), final_error_norm(variant), ...
    coordinates: variant, time, component, and every swept parameter along 'variant'
    attributes: diagram, swept parameter names, simulation settings (JSON)

Variants run with different settings (``simulation.step``, ``t_final``, ``log_every``)
have different time grids: xarray aligns them on the union of times, NaN where a variant
has no sample (and after a divergence).  Saved as NetCDF (``sweep.nc``; any installed
engine, ``scipy`` needs nothing more).  xarray is optional: ``pip install 'fwdstep[labelled]'``.
"""
from __future__ import annotations

import json
import os

import numpy as np

from fwdstep.core.errors import ConfigError

HINT = "pip install 'fwdstep[labelled]'"


def _xarray():
    try:
        import xarray
    except ImportError:
        raise ConfigError(f"labelled results need xarray: {HINT}") from None
    return xarray


def sweep_dataset(result):
    """The Dataset of a ``SweepResult`` (see the module docstring)."""
    from fwdstep.results.sweep_format import METRICS, cell_text as _text
    xr = _xarray()
    pieces = []
    for part in result.iter_parts():
        if "e" not in part:
            continue
        keep = np.flatnonzero(part["has_signal"])
        e = part["e"][:, keep]
        e = e.reshape(e.shape[0], e.shape[1], -1)                   # (time, variant, comp)
        pieces.append(xr.Dataset(
            {"error": (("time", "variant", "component"), e)},
            coords={"time": part["t"], "variant": part["indices"][keep].astype(np.int32),
                    "component": np.arange(e.shape[2], dtype=np.int32)}))
    if not pieces:
        raise ConfigError("the sweep kept no signals (run without --no-signals, with a "
                          "'metrics: error:' signal in the diagram)")
    ds = xr.concat(pieces, dim="variant", join="outer", fill_value=np.nan)
    ds = ds.sortby("variant").transpose("variant", "time", "component")
    rows = {v.index: v for v in result.variants}
    chosen = [rows[int(i)] for i in ds["variant"].values]
    for name in result.names:
        values = [v.values.get(name) for v in chosen]
        try:
            column = np.array([float(x) for x in values])
        except (TypeError, ValueError):
            column = np.array([_text(x) for x in values], dtype=str)
        ds = ds.assign_coords({name: ("variant", column)})
    ds["status"] = ("variant", np.array([v.status for v in chosen], dtype=str))
    ds["diverged_at"] = ("variant", np.array([np.nan if v.diverged_at is None
                                              else v.diverged_at for v in chosen]))
    for m in METRICS:
        ds[m] = ("variant", np.array([v.metrics.get(m, np.nan) for v in chosen]))
    ds["error"].attrs["signal"] = result.metric_signal or ""
    ds.attrs.update(diagram=str(result.diagram), swept=json.dumps(result.names),
                    simulation=json.dumps(result.settings, default=str))
    return ds


def write_dataset(result, path: str) -> str:
    """Write ``sweep_dataset(result)`` to ``path`` (NetCDF) atomically; returns the path."""
    from fwdstep.core.files import atomic_write_path
    ds = sweep_dataset(result)
    return atomic_write_path(path, ds.to_netcdf)   # never through a link planted beside it


def load_sweep(outdir: str):
    """(table, dataset) of a sweep written to ``outdir``: the CSV as a pandas DataFrame and
    ``sweep.nc`` as an xarray Dataset (None when the sweep kept no signals)."""
    import pandas as pd
    from fwdstep.results.sweep_format import CSV_FILE, DATASET_FILE
    from fwdstep.core.errors import OutputError
    try:
        table = pd.read_csv(os.path.join(outdir, CSV_FILE), index_col="variant")
    except (OSError, ValueError) as exc:        # pandas' ParserError is a ValueError
        raise OutputError(f"{os.path.join(outdir, CSV_FILE)} cannot be read: "
                          f"{' '.join(str(exc).split())[:200]}") from None
    path = os.path.join(outdir, DATASET_FILE)
    dataset = _xarray().load_dataset(path) if os.path.exists(path) else None
    return table, dataset


# ---------------------------------------------------------------------------- single runs
def _component_dims(name: str, shape: tuple) -> tuple:
    return tuple(f"{name}:{k}" for k in range(len(shape)))


def _stem(components) -> str | None:
    """The word every component name shares ('joint' of 'joint 1', 'joint 2'), or None."""
    stems = {str(c).rstrip("0123456789").rstrip(" _-") for c in components}
    if len(stems) == 1:
        stem = stems.pop()
        return stem if stem and stem not in ("time", "variant") else None
    return None


def signal_axes(result, name: str, shape: tuple) -> list:
    """(dimension, coordinate values) of each component axis of signal ``name``: a vector
    whose components the diagram or block names gets the word they share as its dimension
    ('joint', with 'joint 1', 'joint 2' as coordinates; 'e.y:component' when they share
    none); other axes are 'SIGNAL:0', 'SIGNAL:1', ... with integer coordinates."""
    from fwdstep.results.plotting import signal_info
    info = signal_info(result, name, typeset=False)
    comps = tuple(info.components or ())
    if len(shape) == 1 and comps and len(comps) == shape[0]:
        return [(_stem(comps) or f"{name}:component", np.array(comps, dtype=str))]
    return [(dim, np.arange(n, dtype=np.int32))
            for dim, n in zip(_component_dims(name, shape), shape)]


def result_dataset(result):
    """A ``Result`` as a Dataset: one variable per signal, dims (time, [variant,] its own
    component axes (``signal_axes``: 'joint' where the diagram names the components 'joint
    1', 'joint 2', else 'SIGNAL:0', ...), each with coordinates; each variable's attrs give
    its ``long_name`` (label) and ``units``; the Dataset's attrs: status, message, diagram,
    settings."""
    from fwdstep.results.plotting import signal_info
    xr = _xarray()
    data = {}
    coords = {"time": ("time", np.asarray(result.t), {"units": "s"})}
    for name in result.names:
        arr = np.asarray(result[name])
        lead = ("time",) if result.batch == 1 else ("time", "variant")
        dims = []
        for dim, values in signal_axes(result, name, arr.shape[len(lead):]):
            have = coords.get(dim)
            if have is not None and not np.array_equal(have[1], values):
                dim = f"{name}:{dim}"              # same word, other components
            coords.setdefault(dim, (dim, values))
            dims.append(dim)
        info = signal_info(result, name, typeset=False)
        attrs = {"long_name": info.label}
        if info.unit:
            attrs["units"] = info.unit
        data[name] = (lead + tuple(dims), arr, attrs)
    if result.batch > 1:
        coords["variant"] = np.arange(result.batch, dtype=np.int32)
    ds = xr.Dataset(data, coords=coords)
    ds.attrs.update(status=result.status, message=result.message)
    d = result.diagram
    if d is not None:
        ds.attrs["diagram"] = str(d.file)
        ds.attrs["simulation"] = json.dumps(
            {k: getattr(d.spec.simulation, k) for k in vars(d.spec.simulation)}, default=str)
    return ds


def result_frame(result):
    """A ``Result`` as a pandas DataFrame indexed by time, one column per component
    ('e.y[0]', 'e.y[1]', ...; 'e.y[0]@v2' for variant 2 of a batch)."""
    import pandas as pd
    columns = {}
    for name in result.names:
        arr = np.asarray(result[name])
        if result.batch == 1:
            flat = arr.reshape(len(result.t), -1)
            for k in range(flat.shape[1]):
                columns[name if arr.ndim == 1 else f"{name}[{k}]"] = flat[:, k]
        else:
            flat = arr.reshape(len(result.t), result.batch, -1)
            for b in range(result.batch):
                for k in range(flat.shape[2]):
                    label = name if arr.ndim == 2 else f"{name}[{k}]"
                    columns[f"{label}@v{b}"] = flat[:, b, k]
    return pd.DataFrame(columns, index=pd.Index(result.t, name="time"))


__all__ = ["sweep_dataset", "write_dataset", "load_sweep", "result_dataset", "result_frame"]
