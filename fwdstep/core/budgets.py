"""Budgets checked before anything large is allocated, with the number in the message.

The log of a run is (rows x variants x logged values) float64 numbers, allocated whole before
the first step: ``check_log`` refuses a log larger than the budget (``fwdstep run
--max-log-memory``, default ``DEFAULT_MAX_LOG_BYTES``) before the allocation, and says how to
log less (``simulation.log_every``, fewer signals under ``log:``) or to stream the log to disk
(``fwdstep run --log-to-disk``, then the budget is the free disk space).  ``fwdstep validate``
applies the same check, so it never says ok to a run that cannot start.  ``fwdstep.simulate``
checks it too, whoever calls it (``max_log_bytes=``, ``log_dir=``; a sweep's batches are
checked against ``--max-memory``), so the Python API never allocates an unchecked log.
"""
from __future__ import annotations

import os
import re
import shutil

import numpy as np

from fwdstep.core.errors import ConfigError


class BudgetError(ConfigError):
    """A budget refused before the allocation (exit 2, like any bad setting)."""


DEFAULT_MAX_LOG_BYTES = 2 * 1024 ** 3          # 2 GiB of recorded signals in memory

_UNITS = {"": 1, "B": 1, "K": 1024, "KB": 1000, "KIB": 1024, "M": 1024 ** 2, "MB": 1000 ** 2,
          "MIB": 1024 ** 2, "G": 1024 ** 3, "GB": 1000 ** 3, "GIB": 1024 ** 3, "T": 1024 ** 4,
          "TB": 1000 ** 4, "TIB": 1024 ** 4}


def parse_size(text: str) -> int:
    """'2GB' -> 2e9, '512MiB' -> 512 * 2**20, '1e9' -> 1e9 bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*", str(text))
    unit = m.group(2).upper() if m else None
    if m is None or unit not in _UNITS:
        raise ConfigError(f"size '{text}' is not understood; write e.g. 512MB, 2GiB or 1e9")
    value = float(m.group(1)) * _UNITS[unit]
    if not np.isfinite(value) or value < 0:
        raise ConfigError(f"size '{text}' must be a finite number of bytes")
    return int(value)


def human(n: float) -> str:
    """Bytes in binary units: 745.1 GiB."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"


def log_rows(d) -> int:
    """Rows the run records (as ``fwdstep.simulate`` allocates them)."""
    cfg = d.spec.simulation
    return cfg.n_steps // cfg.log_every + 1 + (1 if cfg.n_steps % cfg.log_every else 0)


def log_values(d) -> int:
    """float64 numbers per recorded row, over every variant of the batch."""
    per_variant = sum(int(np.prod(d.signal_shapes[d.signal_index[name]], dtype=np.int64))
                      for name in d.logged)
    return per_variant * d.batch + 1              # + the time column


def log_bytes(d) -> int:
    return 8 * log_rows(d) * log_values(d)


def check_log(d, limit: int | None = None, to_disk: str | None = None,
              api: bool = False) -> int:
    """Refuse a log larger than ``limit`` bytes in memory (or, with ``to_disk`` a directory,
    larger than half its free space: the log and the result file written from it).
    ``api``: the message names ``fwdstep.simulate``'s arguments instead of the options of
    ``fwdstep run``.  Returns the log's size in bytes."""
    size = log_bytes(d)
    rows, values = log_rows(d), log_values(d)
    how = (f"{rows} rows x {values} values x 8 bytes" +
           (f" for {d.batch} variants" if d.batch > 1 else ""))
    if to_disk is not None:
        free = shutil.disk_usage(to_disk).free
        where = os.path.dirname(os.path.abspath(to_disk))
        if 2 * size > free:
            raise BudgetError(f"the log needs {human(size)} ({how}) on disk, and the result "
                              f"file as much again; {where} has "
                              f"{human(free)} free: log less (simulation.log_every, fewer "
                              "signals under log:) or choose another "
                              + ("log_dir" if api else "-o"), file=d.file)
        return size
    limit = DEFAULT_MAX_LOG_BYTES if limit is None else limit
    if size > limit:
        raise BudgetError(f"the log needs {human(size)} ({how}), more than the "
                          f"{human(limit)} allowed in memory: log less ("
                          + ("simulation.log_every" if api else "--set simulation.log_every=K")
                          + ", or fewer signals under log:), raise the limit ("
                          + ("max_log_bytes=" if api else "--max-log-memory")
                          + ") or stream it to disk ("
                          + ("log_dir=" if api else "--log-to-disk") + ")", file=d.file)
    return size


def disk_allocator(directory: str):
    """An allocator for ``fwdstep.run.program.build_program`` that puts each log array in a
    file under ``directory`` (a sparse, memory-mapped ``.npy``)."""
    counter = [0]

    def alloc(shape):
        counter[0] += 1
        path = os.path.join(directory, f"log{counter[0]}.npy")
        return np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=shape)
    return alloc
