"""The files of a sweep's output directory, as every reader and writer names them.

``fwdstep sweep`` writes them (``fwdstep.sweeps``); ``compare``, ``report`` and
``load_sweep`` read them back.  docs/sweeps.md describes their contents.
"""
from __future__ import annotations

import json

import numpy as np

#: one row per variant: its values, status and metrics
CSV_FILE = "sweep.csv"
#: the metric of every variant against the swept values
FIGURE_FILE = "sweep.png"
#: the labelled results (``--netcdf``)
DATASET_FILE = "sweep.nc"
#: what made the sweep (``fwdstep.results.provenance``) and its variants
RECORD_FILE = "sweep.json"
#: finished batches, one file each, kept for ``--resume``
PARTS_DIR = "parts"
#: the error metrics of a sweep's rows, in column order
METRICS = ("final_error_norm", "tail_error_norm_max", "rms_error_norm", "error_norm_max")


def cell_text(value) -> str:
    """A value as written in a sweep.csv cell."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple, np.ndarray)):
        return json.dumps(np.asarray(value).tolist())
    return str(value)


#: what the sweep is (diagram files' hashes, settings, overrides, variants, plugins), written
#: when it starts and compared by ``--resume``
IDENTITY_FILE = "sweep-identity.json"
#: the keys of every part file, and the dtype kind each must have
PART_KEYS = {"indices": "i", "batch": "i", "status": "U", "message": "U", "diverged_at": "f",
             "metrics": "f", "values": "U"}


def part_name(first_index: int) -> str:
    """A finished batch's file, as listed in the output directory's manifest."""
    return f"{PARTS_DIR}/variants-{int(first_index):06d}.npz"


def read_part(path: str, signals: bool = True) -> dict:
    """The arrays of one finished batch (``parts/*.npz``), checked: a truncated, corrupt or
    hand-made file is one ``OutputError`` naming it (never a traceback, never a pickle)."""
    import zipfile
    from fwdstep.core.errors import DamagedFileError, printable
    shown = printable(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            if not hasattr(data, "files"):
                raise ValueError("not an .npz archive")
            part = {k: data[k] for k in data.files if signals or k != "e"}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile,
            zipfile.LargeZipFile, NotImplementedError) as exc:
        raise DamagedFileError(f"{shown} cannot be read ({type(exc).__name__}: "
                          f"{printable(str(exc))[:200]}); delete it to run its variants "
                          "again with --resume") from None
    problem = _part_problem(part)
    if problem:
        raise DamagedFileError(f"{shown} is not a batch fwdstep wrote: {problem}; delete it to run "
                          "its variants again with --resume")
    return part


def _part_problem(part: dict) -> str:
    for key, kind in PART_KEYS.items():
        if key not in part:
            return f"'{key}' is missing"
        if part[key].dtype.kind != kind and not (kind == "f" and part[key].dtype.kind == "i"):
            return f"'{key}' has dtype {part[key].dtype}"
    n = part["indices"].shape
    if len(n) != 1:
        return "'indices' is not a list"
    for key in PART_KEYS:
        if part[key].shape[:1] != n:
            return f"'{key}' has {part[key].shape[:1]} rows for {n[0]} variants"
    if part["metrics"].shape != (n[0], len(METRICS)):
        return f"'metrics' has shape {part['metrics'].shape}"
    if n[0] and part["indices"].min() < 0:
        return "a negative variant index"
    if "e" in part:
        t, e = part.get("t"), part["e"]
        flags = part.get("has_signal")
        if t is None or flags is None or t.ndim != 1 or e.ndim < 2 or e.shape[:2] != (
                len(t), n[0]) or flags.shape != n or t.dtype.kind != "f" or \
                e.dtype.kind != "f":
            return "its signals ('t', 'e', 'has_signal') do not fit together"
    for key in ("values", "status", "message"):
        for text in part[key].tolist():
            if not isinstance(text, str):
                return f"'{key}' holds no text"
    try:
        for text in part["values"].tolist():
            if not isinstance(json.loads(text), dict):
                raise ValueError
        if "signal_info" in part:
            info = json.loads(str(part["signal_info"]))
            if not (isinstance(info, dict) and isinstance(info.get("name"), str)
                    and isinstance(info.get("real"), str)):
                raise ValueError
    except ValueError:
        return "'values' or 'signal_info' is not fwdstep's JSON"
    return ""


def read_table(path: str) -> list:
    """The rows of a sweep.csv (dicts), with no limit on a cell's size (a 200 x 200 matrix
    value is one large cell); an unreadable file is one ``OutputError`` naming it."""
    import csv
    import sys
    from fwdstep.core.errors import DamagedFileError, printable
    previous = csv.field_size_limit()
    try:
        csv.field_size_limit(sys.maxsize)
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        raise DamagedFileError(f"{printable(path)} cannot be read: {exc}") from None
    finally:
        csv.field_size_limit(previous)
    if any(None in row for row in rows):
        raise DamagedFileError(f"{printable(path)} is not a table fwdstep wrote: a row has more "
                          "cells than the header")
    return rows
