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
