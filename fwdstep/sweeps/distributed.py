"""Where a sweep's batches run: in this process, on local cores, or on a Dask cluster.

``run_jobs(function, jobs, ...)`` calls ``function(job)`` for every job and yields
``(job, outcome)`` pairs **as they finish**, so the caller can write each batch to disk at
once.  Three executors, one interface:

* ``workers=1`` (or one job): in this process, one after the other;
* ``workers=N > 1``: N local processes, each sent one job at a time through its own pipe
  (no extra package);
* ``scheduler="tcp://HOST:PORT"`` or ``client=dask.distributed.Client(...)``: the jobs are
  submitted to that Dask cluster (``pip install 'fwdstep[distributed]'``).

Jobs carry everything they need (diagram specs are pickled, blocks rebuilt from them, plugin
files sent as text and loaded in the worker), so a worker on another machine needs fwdstep
installed but not the diagram or plugin files.  Local workers are forked with the jobs
already in memory and are sent only job numbers.  Ctrl-C / SIGTERM in the caller stop the
local workers (or cancel the Dask futures); whatever was yielded before is the caller's to
keep.

**A worker that dies is not waited for.**  A local worker killed (SIGKILL, the out-of-memory
killer) is seen through its process sentinel: its job is yielded as ``WorkerLost`` (the
sweep writes its variants as error rows "worker lost: ...", not as finished batches, so
``--resume`` runs them again) and a new worker takes the remaining jobs.  On Dask, a job
whose workers kept dying (``KilledWorker``) is yielded the same way; a cluster with no worker
is refused after ``WORKER_WAIT_S`` seconds, and one that loses all its workers during the
sweep gives up the remaining jobs after as long.
"""
from __future__ import annotations

import gc

import os
import signal

from fwdstep.core.errors import ConfigError

DISTRIBUTED_HINT = "pip install 'fwdstep[distributed]'"


def local_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:           # pragma: no cover - not Linux
        return os.cpu_count() or 1


#: how long a sweep waits for a Dask cluster to have a worker before it says so
WORKER_WAIT_S = 30.0


class WorkerLost:
    """What ``run_jobs`` yields for a job whose worker died (killed, out of memory) instead
    of its outcome; ``reason`` says how."""

    def __init__(self, reason: str):
        self.reason = reason

    def __repr__(self) -> str:
        return f"WorkerLost({self.reason!r})"


def dask_client(scheduler: str):
    """A ``dask.distributed.Client`` connected to ``scheduler`` (one-line error without dask
    or without a reachable scheduler, or with an address that is not one)."""
    try:
        from dask.distributed import Client
    except ImportError:
        raise ConfigError(f"--scheduler needs dask.distributed: {DISTRIBUTED_HINT}") from None
    try:
        return Client(scheduler, timeout="10s")
    except Exception as exc:  # noqa: BLE001 - ValueError, OSError, TimeoutError, ...
        text = " ".join(str(exc).split())[:200] or type(exc).__name__
    # the half-made Client is garbage whose __del__ stops its event loop: collected now, not
    # at some later allocation inside another Dask call (where distributed deadlocks)
    gc.collect()
    raise ConfigError(f"cannot reach the Dask scheduler at '{scheduler}': {text} (give "
                      "its address, e.g. tcp://HOST:8786)")


def check_workers(client, scheduler=None, wait: float | None = None) -> None:
    """Refuse, after ``wait`` seconds (``WORKER_WAIT_S``), a cluster with no worker: the
    sweep would wait for ever without a word."""
    wait = WORKER_WAIT_S if wait is None else wait
    try:
        client.wait_for_workers(1, timeout=wait)
    except Exception as exc:  # noqa: BLE001 - TimeoutError (its type differs by version)
        where = scheduler or getattr(getattr(client, "scheduler", None), "address", "")
        raise ConfigError(f"the Dask scheduler {where} has no worker (waited {wait:g} s): "
                          f"start some with 'dask worker {where}' and run again"
                          + ("" if "imeout" in type(exc).__name__ else
                             f" ({type(exc).__name__}: {exc})")) from None


def run_jobs(function, jobs: list, workers: int = 1, client=None):
    """Yield ``(job, function(job))`` for every job, in the order they finish; a job whose
    worker process died yields ``(job, WorkerLost(reason))`` and the others go on."""
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


#: (function, jobs) of the workers being started: forked workers inherit them, so a job is
#: sent as its number (no pickling of specs, no rebuilding of blocks in the worker)
_INHERITED: tuple | None = None


def _worker(conn, function, jobs) -> None:
    """A worker process: run the job numbers it is sent, one at a time, until None."""
    _ignore_interrupts()
    if jobs is None:
        function, jobs = _INHERITED
    while True:
        number = conn.recv()
        if number is None:
            return
        try:
            conn.send((number, True, function(jobs[number])))
        except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
            try:
                conn.send((number, False, exc))
            except Exception:  # noqa: BLE001 - an exception that does not pickle
                conn.send((number, False, RuntimeError(f"{type(exc).__name__}: {exc}")))


def _on_processes(function, jobs: list, workers: int):
    """N worker processes, each given one job at a time through its own pipe, watched
    through its sentinel: a worker that dies (SIGKILL, the out-of-memory killer) loses only
    its job (yielded as ``WorkerLost``) and is replaced; nothing waits for ever."""
    import multiprocessing
    from multiprocessing.connection import wait
    global _INHERITED
    fork = hasattr(os, "fork") and "fork" in multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if fork else "spawn")
    pending = list(range(len(jobs)))[::-1]
    running: dict = {}                   # process -> (conn, job number or None)

    def start():
        parent, child = context.Pipe()
        proc = context.Process(target=_worker, daemon=True,
                               args=(child, None, None) if fork else (child, function, jobs))
        proc.start()
        child.close()
        running[proc] = [parent, None]
        return proc

    def give(proc) -> None:
        conn = running[proc][0]
        number = pending.pop() if pending else None
        running[proc][1] = number
        try:
            conn.send(number)
        except OSError:                          # it died after its last result
            if number is not None:
                pending.append(number)
            proc.join()
            conn.close()
            del running[proc]
            if pending:
                give(start())

    if fork:
        _INHERITED = (function, jobs)
    try:
        for _ in range(workers):
            give(start())
        while any(number is not None for _, number in running.values()):
            busy = {p: v for p, v in running.items() if v[1] is not None}
            ready = wait([v[0] for v in busy.values()] + [p.sentinel for p in busy])
            for proc, (conn, number) in busy.items():
                if conn not in ready and proc.sentinel not in ready:
                    continue
                message = None
                try:
                    if conn.poll():
                        message = conn.recv()
                except (EOFError, OSError):
                    message = None
                if message is not None:
                    got, ok, outcome = message
                    if not ok:
                        if isinstance(outcome, KeyboardInterrupt):
                            raise outcome
                        outcome = WorkerLost(f"{type(outcome).__name__} in its worker: "
                                             f"{outcome}")
                    give(proc)
                    yield jobs[got], outcome
                elif not proc.is_alive():
                    proc.join()
                    conn.close()
                    del running[proc]
                    yield jobs[number], WorkerLost(_death(proc))
                    if pending:
                        give(start())
    finally:
        for proc, (conn, _) in running.items():
            if proc.is_alive():
                proc.terminate()             # interrupted or done: stop the workers at once
        for proc, (conn, _) in running.items():
            proc.join()
            conn.close()
        if fork:
            _INHERITED = None


def _death(proc) -> str:
    code = proc.exitcode
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        hint = " (the out-of-memory killer?)" if -code == signal.SIGKILL else ""
        return f"its worker process (pid {proc.pid}) was killed by {name}{hint}"
    return f"its worker process (pid {proc.pid}) exited with code {code}"


def _on_dask(function, jobs: list, client):
    """Futures on the cluster; a job whose workers died (``KilledWorker``: Dask gave up after
    its retries) or that raised on the worker is yielded as ``WorkerLost``; when the
    cluster has had no worker for ``WORKER_WAIT_S``, the jobs left are lost too."""
    import time
    from dask.distributed import wait
    futures = {}
    for k, job in enumerate(jobs):
        futures[client.submit(function, job, pure=False)] = k
    left = set(futures)
    alone_since = None
    try:
        while left:
            try:
                done = wait(list(left), timeout=min(5.0, WORKER_WAIT_S),
                            return_when="FIRST_COMPLETED").done
            except TimeoutError:                # distributed's wait raises on its timeout
                done = set()
            for future in done:
                left.discard(future)
                job = jobs[futures[future]]
                try:
                    outcome = future.result()
                except KeyboardInterrupt:
                    raise
                except Exception as exc:  # noqa: BLE001 - KilledWorker, an error on the worker
                    text = " ".join(str(exc).split()).split(". ")[0][:200]   # 1st sentence
                    outcome = WorkerLost(f"{type(exc).__name__} on the Dask cluster: {text}")
                yield job, outcome
            if done:
                alone_since = None
                continue
            if _client_has_workers(client):
                alone_since = None
            elif alone_since is None:
                alone_since = time.monotonic()
            elif time.monotonic() - alone_since > WORKER_WAIT_S:
                for future in list(left):
                    left.discard(future)
                    yield jobs[futures[future]], WorkerLost(
                        f"the Dask cluster had no worker for {WORKER_WAIT_S:g} s")
    except BaseException:
        client.cancel(list(futures))
        raise


def _client_has_workers(client) -> bool:
    try:
        return bool(client.scheduler_info().get("workers"))
    except Exception:  # noqa: BLE001 - the scheduler itself is gone
        return False


__all__ = ["run_jobs", "dask_client", "check_workers", "local_cores", "WorkerLost"]
