"""Where a sweep's batches run: in this process, on local cores, or on a Dask cluster.

``run_jobs(function, jobs, ...)`` calls ``function(job)`` for every job and yields
``(job, outcome)`` pairs **as they finish**, so the caller can write each batch to disk at
once.  Three executors, one interface:

* ``workers=1`` (or one job): in this process, one after the other;
* ``workers=N > 1``: N local processes (``multiprocessing.Pool``; no extra package);
* ``scheduler="tcp://HOST:PORT"`` or ``client=dask.distributed.Client(...)``: the jobs are
  submitted to that Dask cluster (``pip install 'fwdstep[distributed]'``).

Jobs carry everything they need (diagram specs are pickled, blocks rebuilt from them), so a
worker on another machine needs fwdstep installed but not the diagram files.  Local workers
are forked with the jobs already in memory and are sent only job numbers.  Ctrl-C / SIGTERM in the
caller stop the local workers (or cancel the Dask futures); whatever was yielded before is
the caller's to keep.
"""
from __future__ import annotations

import os
import signal

from fwdstep.core.errors import ConfigError

DISTRIBUTED_HINT = "pip install 'fwdstep[distributed]'"


def local_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:           # pragma: no cover - not Linux
        return os.cpu_count() or 1


def dask_client(scheduler: str):
    """A ``dask.distributed.Client`` connected to ``scheduler`` (one-line error without dask
    or without a reachable scheduler)."""
    try:
        from dask.distributed import Client
    except ImportError:
        raise ConfigError(f"--scheduler needs dask.distributed: {DISTRIBUTED_HINT}") from None
    try:
        return Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None


def run_jobs(function, jobs: list, workers: int = 1, client=None):
    """Yield ``(job, function(job))`` for every job, in the order they finish."""
    if client is not None:
        yield from _on_dask(function, jobs, client)
    elif workers > 1 and len(jobs) > 1:
        yield from _on_processes(function, jobs, min(workers, len(jobs)))
    else:
        for job in jobs:
            yield job, function(job)


def _ignore_interrupts() -> None:
    """Workers leave Ctrl-C to the parent, which stops them."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _call(function_and_job):
    function, number, job = function_and_job
    return number, function(job)


#: (function, jobs) of the pool being started: forked workers inherit them, so a job is sent
#: as its number (no pickling of specs, no rebuilding of blocks in the worker)
_INHERITED: tuple | None = None


def _call_inherited(number: int):
    function, jobs = _INHERITED
    return number, function(jobs[number])


def _on_processes(function, jobs: list, workers: int):
    import multiprocessing
    global _INHERITED
    fork = hasattr(os, "fork") and "fork" in multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if fork else "spawn")
    if fork:                  # set while the pool lives (a replaced worker forks again)
        _INHERITED = (function, jobs)
        tasks, call = list(range(len(jobs))), _call_inherited
    else:
        tasks, call = [(function, k, job) for k, job in enumerate(jobs)], _call
    try:
        pool = context.Pool(workers, initializer=_ignore_interrupts)
        try:
            for number, outcome in pool.imap_unordered(call, tasks, chunksize=1):
                yield jobs[number], outcome
            pool.close()
        except BaseException:
            pool.terminate()             # interrupted: stop the workers at once
            raise
        finally:
            pool.join()
    finally:
        if fork:
            _INHERITED = None


def _on_dask(function, jobs: list, client):
    from dask.distributed import as_completed
    futures = {}
    for k, job in enumerate(jobs):
        futures[client.submit(function, job, pure=False)] = k
    try:
        for future in as_completed(list(futures)):
            yield jobs[futures[future]], future.result()
    except BaseException:
        client.cancel(list(futures))
        raise


__all__ = ["run_jobs", "dask_client", "local_cores"]
