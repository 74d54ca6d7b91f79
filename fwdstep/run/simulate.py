"""The run loop: fixed-step integration of a compiled diagram.

Procedure Step (one step of size h from (t_n, x_n), an s-stage explicit RK tableau)::

    for stage i = 1..s:
        x_i = x_n + h * sum_{j<i} a_ij k_j              (x_1 = x_n)
        for block in schedule (fixed at compile time):   # outputs, each block exactly once
            signals[block.outputs] = block.output(t_n + c_i h, x_i[block], signals[block.inputs])
        for block with states:                           # derivatives, after all outputs
            k_i[block] = block.derivative(t_n + c_i h, x_i[block], signals[block.inputs])
        if i == 1 and n % log_every == 0: record logged signals at t_n   (no extra evaluation)
    x_{n+1} = x_n + h * sum_i b_i k_i
    if any |x_{n+1}| > bound or not finite: stop (diverged), keep what was recorded
    if recorded and any block output at t_n not finite: stop (diverged)   (fwdstep.run.finite)

The final time is recorded with one extra output pass.

Steps that touch a declared discontinuity time (``Block.discontinuities``: a Step, a pulse
edge, a sample instant) are split so that a (sub-)step ends exactly there, their stage
times are clamped to the correct side of it, and discrete blocks are updated there between
steps (``fwdstep.run.events``; docs/discrete-time.md).  Steps that touch none run exactly the
procedure above.

Nothing per-run is stored in the diagram or its blocks: all buffers live in this function's
frame.

``simulate`` runs this procedure through ``fwdstep.run.program``, which generates it once per
run as straight-line code over preallocated buffers and fuses the linear blocks (each
linear output still computed once per stage, as part of one matrix product); the
evaluator ``_make_evaluator`` below is the plain form, used for the initial state and to
locate a failing block.  docs/performance.md tells what was measured and changed.
"""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.structure.compiler import CompiledDiagram
from fwdstep.core.errors import BlockRuntimeError, ConfigError, DivergenceError, SimulationError
from fwdstep.run.program import build_program
from fwdstep.results.result import Result
from fwdstep.run.events import apply_updates, plan_events
from fwdstep.run import finite
from fwdstep.core import signals
from fwdstep.core.settings import BACKENDS
from fwdstep.core.solvers import IVP_METHODS
from fwdstep.run.evaluate import _locate_failure, check_shapes, initial_state
from fwdstep.run.ivp import simulate_ivp
from fwdstep.run.outcome import SimulationInterrupted, _divergence_message, _finish, _reason

#: backends that plug into this loop from a higher layer, loaded by name on first use (as
#: block plugins are): the run layer never imports them.  With "numpy", BACKENDS.
PLUGGED_BACKENDS = {"compiled": "fwdstep.compiled.driver"}


def _plugged(name: str, d):
    import importlib
    try:
        return importlib.import_module(PLUGGED_BACKENDS[name])
    except ImportError as exc:
        if getattr(exc, "name", "") not in ("numba", "llvmlite"):
            raise
        raise ConfigError(f"backend '{name}' needs numba: pip install 'fwdstep[fast]' (or use "
                          "backend 'numpy')", file=d.file) from None


def simulate(d: CompiledDiagram, progress=None, x0: np.ndarray | None = None, *,
             fuse: bool = True, backend: str | None = None,
             log_dir: str | None = None, max_log_bytes: int | None = None,
             record_states: bool = False, on_compile=None) -> Result:
    """Integrate the compiled diagram over ``simulation.t_final``.

    Returns a ``Result``.  A divergence, an exception inside a block, or Ctrl-C raise
    ``DivergenceError``, ``BlockRuntimeError`` or ``SimulationInterrupted`` whose ``result``
    attribute holds everything recorded up to that time (status 'diverged', 'error',
    'interrupted').  For a batch (B > 1) a diverging variant is frozen and marked, the
    others go on.
    ``progress(fraction)`` is called about once per second of wall time.
    ``fuse=False`` calls every linear block instead of fusing them (for comparisons).
    ``backend`` overrides ``simulation.backend``: 'numpy' (default) or 'compiled' (numba,
    ``fwdstep.compiled.backend_numba``; batches run their variants in parallel).
    ``on_compile(event, info)``: the compiled backend's news, for a progress line
    (``fwdstep.compiled.driver.simulate_compiled``: compiling a never-seen structure, with
    an estimate; compiled; or taking the NumPy path because compiling cannot help).
    ``log_dir``: record into memory-mapped files in that directory instead of memory
    (``fwdstep run --log-to-disk``; NumPy backend).
    ``record_states``: also keep the state at every recorded time as ``result.states``
    (rows, B, n_states) (NumPy backend, fixed-step solvers; ``fwdstep.linearize`` reads it).
    The log's size is checked before anything is allocated (``fwdstep.core.budgets.check_log``):
    at most ``max_log_bytes`` in memory (default ``budgets.DEFAULT_MAX_LOG_BYTES``, 2 GiB),
    or, with ``log_dir``, half the free space there; else ``ConfigError`` with the numbers.
    """
    used = backend or d.spec.simulation.backend
    try:
        result = _simulate(d, progress, x0, fuse=fuse, backend=backend, log_dir=log_dir,
                           max_log_bytes=max_log_bytes, record_states=record_states,
                           on_compile=on_compile)
    except SimulationError as exc:
        if exc.result is not None:        # the record of the run (fwdstep.results.provenance);
            exc.result.backend = getattr(exc.result, "backend", None) or used   # the compiled
        raise                                 # backend may have taken the NumPy path
    result.backend = getattr(result, "backend", None) or used
    return result


def _simulate(d: CompiledDiagram, progress=None, x0: np.ndarray | None = None, *,
              fuse: bool = True, backend: str | None = None,
              log_dir: str | None = None, max_log_bytes: int | None = None,
              record_states: bool = False, on_compile=None) -> Result:
    """``simulate`` without recording the backend used."""
    from fwdstep.core.budgets import check_log
    check_log(d, max_log_bytes, to_disk=log_dir, api=True)
    cfg = d.spec.simulation
    if record_states and (cfg.solver in IVP_METHODS or (backend or cfg.backend) != "numpy"):
        raise ConfigError("recording the states needs the numpy backend and a fixed-step "
                          "solver", file=d.file)
    if log_dir is not None and (cfg.solver in IVP_METHODS or (backend or cfg.backend) != "numpy"):
        raise ConfigError("--log-to-disk works with the numpy backend and the fixed-step "
                          "solvers only", file=d.file)
    if cfg.solver in IVP_METHODS:
        if (backend or cfg.backend) == "compiled":
            raise ConfigError(f"solver '{cfg.solver}' runs through scipy's solve_ivp; it has no "
                              "compiled backend (use backend numpy)", file=d.file)
        return simulate_ivp(d, progress, x0)
    if (backend or cfg.backend) == "compiled":
        return _plugged("compiled", d).simulate_compiled(d, progress, x0, on_compile)
    if (backend or cfg.backend) != "numpy":
        raise ConfigError(f"unknown backend '{backend}'; backends are: {', '.join(BACKENDS)}")
    h = cfg.step
    n_steps = cfg.n_steps
    events = plan_events(d, h, n_steps)
    special = events.steps if events is not None else {}
    sampled = tuple(events.sampled_signals) if events is not None else ()
    every = cfg.log_every
    B, N = d.batch, d.n_states
    bound = cfg.bound
    wall0 = _time.perf_counter()

    n_rows = n_steps // every + 1 + (1 if n_steps % every else 0)
    alloc = None
    if log_dir is not None:
        from fwdstep.core.budgets import disk_allocator
        alloc = disk_allocator(log_dir)
    unlogged = finite.unlogged_signals(d)     # checked at every record (fwdstep.run.finite)
    probe = (unlogged, finite.probe_buffer(d, unlogged)) if unlogged else None
    prog = build_program(d, n_rows, fuse=fuse, alloc=alloc, sampled=sampled, probe=probe)
    states = np.full((n_rows, B, N), np.nan) if record_states else None
    check = finite.OutputCheck(d, *probe) if probe else None
    reasons: dict = {}                        # variant of a batch -> why it diverged
    x = prog.xn
    x[...] = d.x0
    first, first_record, rest = prog.first, prog.first_record, prog.rest
    row = 0
    alive = np.ones(B, dtype=bool)
    died_at = np.full(B, np.nan)
    status, message, error = "ok", "", None
    n = 0
    t = 0.0
    next_report = wall0 + 1.0
    absx = np.empty((B, N))
    single = B == 1 and N > 0
    checked = 0                               # log rows already checked for NaN/inf

    with np.errstate(all="ignore"):
        try:
            x[...] = (initial_state(d, event=events.start if events is not None else None)
                      if x0 is None else np.asarray(x0, dtype=float))
            check_shapes(d, 0.0, x)
            for n in range(n_steps):
                t = n * h
                if n in special:              # a step that touches a discontinuity
                    for i, sub in enumerate(special[n]):
                        ts = max(sub.a, sub.lo)
                        if sub.event is not None:
                            apply_updates(sub.event, ts, x, prog.sample_signals)
                        if i == 0 and n % every == 0:
                            prog.first_record_ts(t, ts, row)
                            if states is not None:
                                states[row] = x
                            row += 1
                        else:
                            prog.first_ts(ts)
                        prog.rest_h(sub.a, sub.b - sub.a, sub.lo, sub.hi)
                else:
                    if n % every == 0:
                        first_record(t, row)
                        if states is not None:
                            states[row] = x
                        row += 1
                    else:
                        first(t)
                    rest(t)
                if single:
                    if np.abs(x, out=absx).max() <= bound:
                        pass
                    else:
                        status = "diverged"
                        message = _divergence_message(d, x, bound, t + h)
                        died_at[0] = t + h
                        alive[0] = False
                        break
                elif N:                       # one reduction; per variant only if it fails
                    if not np.abs(x, out=absx).max() <= bound:     # (NaN fails it too)
                        m = absx.max(axis=1)
                        bad = ~(m <= bound) & alive
                        died_at[bad] = t + h
                        for b in np.flatnonzero(bad):
                            reasons[int(b)] = _divergence_message(d, x, bound, t + h, b)
                        alive &= ~bad
                        if not alive.any():
                            status = "diverged"
                            message = _divergence_message(d, x, bound, t + h)
                            break
                        x[~alive] = 0.0      # frozen variants: keep the others finite, going
                if check is not None and n % every == 0:     # the outputs just recorded
                    bad = check.failed(alive)
                    if bad is not None:
                        stop = finite.probe_failure(d, prog.t_log, prog.logs, row - 1, check,
                                                    bad, alive, died_at, reasons)
                        if stop is not None:
                            row, status, message, x = stop
                            break
                        x[~alive] = 0.0
                if progress is not None and n % 2048 == 0:
                    now = _time.perf_counter()
                    if now >= next_report:
                        progress((n + 1) / n_steps)
                        next_report = now + 1.0
                if B == 1 and n % 8192 == 8191:    # an output gone NaN/inf: stop early,
                    if not finite.rows_finite(prog.logs, checked, row):  # _finish: where
                        break
                    checked = row
            else:
                t = n_steps * h
                end = events.final if events is not None else None
                if end is None:
                    prog.final(t, row)
                else:                         # an event at t_final: its right limit
                    if end.updates:
                        apply_updates(end, max(t, end.hi), x, prog.sample_signals)
                    prog.final_ts(t, max(t, end.hi), row)
                if states is not None:
                    states[row] = x
                row += 1
                bad = check.failed(alive) if check is not None else None
                if bad is not None:
                    stop = finite.probe_failure(d, prog.t_log, prog.logs, row - 1, check, bad,
                                                alive, died_at, reasons)
                    if stop is not None:
                        row, status, message, x = stop
        except KeyboardInterrupt as exc:     # Ctrl-C, or SIGTERM/SIGHUP (fwdstep.core.signals)
            status, message = "interrupted", f"{_reason(exc)} at t = {t:.6g}"
            error = SimulationInterrupted(message, time=t)
            error.signum = getattr(exc, "signum", 2)
        except SimulationError as exc:    # a discrete algebraic loop: already says where
            status, message, error = "error", str(exc), exc
        except BaseException as exc:  # noqa: BLE001 - a SystemExit in a kernel too: the
            # block's error (status error, data kept), never the end of fwdstep with exit 0
            error = _locate_failure(d, t, x, exc)
            error.__cause__ = exc
            status, message = "error", str(error)
    result = _finish(d, prog.t_log, prog.logs, row, status, message, error, alive, died_at, x,
                     n, t, wall0, reasons)
    if states is not None:
        result.states = states[:len(result.t)]
    return result


