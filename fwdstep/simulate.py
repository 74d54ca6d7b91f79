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
    if recorded and any block output at t_n not finite: stop (diverged)   (fwdstep.finite)

The final time is recorded with one extra output pass.

Steps that touch a declared discontinuity time (``Block.discontinuities``: a Step, a pulse
edge, a sample instant) are split so that a (sub-)step ends exactly there, their stage
times are clamped to the correct side of it, and discrete blocks are updated there between
steps (``fwdstep.events``; docs/discrete-time.md).  Steps that touch none run exactly the
procedure above.

Nothing per-run is stored in the diagram or its blocks: all buffers live in this function's
frame.

``simulate`` runs this procedure through ``fwdstep.program``, which generates it once per
run as straight-line code over preallocated buffers and fuses the linear blocks (each
linear output still computed once per stage, as part of one matrix product); the
evaluator ``_make_evaluator`` below is the plain form, used for the initial state and to
locate a failing block.  docs/performance.md tells what was measured and changed.
"""
from __future__ import annotations

import time as _time

import numpy as np

from .compiler import CompiledDiagram
from .errors import BlockRuntimeError, ConfigError, DivergenceError, SimulationError
from .program import build_program
from .result import Result
from .events import apply_updates, plan_events
from . import finite, signals
from .solvers import IVP_METHODS, TABLEAUX, step_plan


class SimulationInterrupted(SimulationError):
    """The run was interrupted (Ctrl-C); ``result`` holds everything up to ``time``."""


def _make_evaluator(d: CompiledDiagram):
    """Build ``f(t, x, dx) -> None`` (fills dx), ``outputs(t, x)`` and the shared signal
    list: the procedure above, block by block, without the program's preparation."""
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    calls = []
    for step in d.schedule:
        outs = step.outputs
        calls.append((step.block.output, step.state, step.inputs, outs, len(outs)))
    ders = [(s.block.derivative, s.state, s.inputs) for s in d.stateful]
    empty = slice(0, 0)

    def outputs(t, x):
        for fn, sl, ins, outs, n_out in calls:
            y = fn(t, x[:, sl] if sl is not None else x[:, empty], tuple([sig[i] for i in ins]))
            if n_out == 1:
                sig[outs[0]] = y[0]
            else:
                for k in range(n_out):
                    sig[outs[k]] = y[k]

    def f(t, x, dx):
        outputs(t, x)
        for fn, sl, ins in ders:
            dx[:, sl] = fn(t, x[:, sl], tuple([sig[i] for i in ins]))

    return f, outputs, sig


def _locate_failure(d: CompiledDiagram, t: float, x: np.ndarray, exc) -> BlockRuntimeError:
    """Which block raised during the step from (t, x), at which stage time and with which
    inputs: the step is replayed with the reference evaluator, one block at a time."""
    tab = TABLEAUX[d.spec.simulation.solver]
    stages, _ = step_plan(tab, d.spec.simulation.step)
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    k = [np.zeros((d.batch, d.n_states)) for _ in range(tab.stages)]
    empty = slice(0, 0)
    with np.errstate(all="ignore"):
        for s, (ch, coeffs) in enumerate([(0.0, [])] + list(stages)):
            ts = t + ch if s else t
            xi = x.copy()
            for j, a in coeffs:
                xi += a * k[j]
            for what, steps in (("output", d.schedule), ("derivative", d.stateful)):
                for step in steps:
                    u = tuple(sig[i] for i in step.inputs)
                    xs = xi[:, step.state if step.state is not None else empty]
                    try:
                        if what == "output":
                            y = step.block.output(ts, xs, u)
                            for idx, val in zip(step.outputs, y):
                                sig[idx] = val
                                if (np.ndim(val) < 1 or np.shape(val)[0] not in (1, d.batch)
                                        or np.shape(val)[1:] != tuple(d.signal_shapes[idx])):
                                    return _shape_error(d, step, idx, val, ts)
                        else:
                            k[s][:, step.state] = step.block.derivative(ts, xs, u)
                    except Exception as inner:  # noqa: BLE001 - the user's block failed
                        return _block_error(step, inner, ts, u)
    return BlockRuntimeError(f"evaluation failed at t = {t:.6g}: {type(exc).__name__}: {exc}",
                             time=t)


def _shape_error(d, step, idx, val, t) -> BlockRuntimeError:
    """A block output whose shape is not the declared one (blamed on it, not downstream)."""
    port = d.signal_names[idx].rsplit(".", 1)[-1]
    got = tuple(np.shape(val))[1:] if np.ndim(val) else ()
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) output '{port}' has shape "
        f"{got} at t = {t:.6g}, but declares {tuple(d.signal_shapes[idx])}",
        time=t, block=step.block.name)


def _block_error(step, inner, t, u) -> BlockRuntimeError:
    names = list(step.block.inputs)
    shown = "; ".join(
        f"{n}={np.array2string(np.asarray(v)[0], precision=4, threshold=12)}"
        if v is not None else f"{n}=(not yet computed)" for n, v in zip(names, u))
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) raised "
        f"{type(inner).__name__}: {inner} at t = {t:.6g}; inputs: {shown or '(none)'}",
        time=t, block=step.block.name)


def initial_state(d: CompiledDiagram, t0: float = 0.0, event=None) -> np.ndarray:
    """x(0): declared initial values, then blocks that start from their inputs (reference
    dynamics: z(0) = qdot_d(0) - alpha_ell (q(0) - q_d(0))).  ``event``: discrete blocks
    that sample at t0 (``fwdstep.events``): those inputs are computed with their samples of
    t0 (a sampled controller's reference dynamics start from the sampled q(0), not from the
    hold's initial value); their own states are returned unchanged, the run updates them."""
    x = d.x0.copy()
    needing = [s for s in d.stateful if s.block.init_from_inputs]
    if not needing:
        return x
    _, outputs, sig = _make_evaluator(d)
    held = [(st.state, x[:, st.state].copy()) for st in event.updates] if event else []

    def evaluate(t):
        outputs(t, x)
        return sig

    with np.errstate(all="ignore"):
        for _ in range(len(needing) + 1):
            if held:
                for sl, v in held:
                    x[:, sl] = v
                apply_updates(event, t0, x, evaluate)
            outputs(t0, x)
            for s in needing:
                u = tuple(sig[i] for i in s.inputs)
                x[:, s.state] = np.broadcast_to(s.block.initial_state(t0, u),
                                                (d.batch, s.block.n_states))
    for sl, v in held:
        x[:, sl] = v
    return x
    _, outputs, sig = _make_evaluator(d)
    with np.errstate(all="ignore"):
        for _ in range(len(needing) + 1):
            outputs(t0, x)
            for s in needing:
                u = tuple(sig[i] for i in s.inputs)
                x[:, s.state] = np.broadcast_to(s.block.initial_state(t0, u),
                                                (d.batch, s.block.n_states))
    return x


def simulate(d: CompiledDiagram, progress=None, x0: np.ndarray | None = None, *,
             fuse: bool = True, backend: str | None = None,
             log_dir: str | None = None, max_log_bytes: int | None = None,
             record_states: bool = False) -> Result:
    """Integrate the compiled diagram over ``simulation.t_final``.

    Returns a ``Result``.  A divergence, an exception inside a block, or Ctrl-C raise
    ``DivergenceError``, ``BlockRuntimeError`` or ``SimulationInterrupted`` whose ``result``
    attribute holds everything recorded up to that time (status 'diverged', 'error',
    'interrupted').  For a batch (B > 1) a diverging variant is frozen and marked, the
    others go on.
    ``progress(fraction)`` is called about once per second of wall time.
    ``fuse=False`` calls every linear block instead of fusing them (for comparisons).
    ``backend`` overrides ``simulation.backend``: 'numpy' (default) or 'compiled' (numba,
    ``fwdstep.backend_numba``; batches run their variants in parallel).
    ``log_dir``: record into memory-mapped files in that directory instead of memory
    (``fwdstep run --log-to-disk``; NumPy backend).
    ``record_states``: also keep the state at every recorded time as ``result.states``
    (rows, B, n_states) (NumPy backend, fixed-step solvers; ``fwdstep.linearize`` reads it).
    The log's size is checked before anything is allocated (``fwdstep.budgets.check_log``):
    at most ``max_log_bytes`` in memory (default ``budgets.DEFAULT_MAX_LOG_BYTES``, 2 GiB),
    or, with ``log_dir``, half the free space there; else ``ConfigError`` with the numbers.
    """
    from .budgets import check_log
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
        from .ivp import simulate_ivp
        return simulate_ivp(d, progress, x0)
    if (backend or cfg.backend) == "compiled":
        return _simulate_compiled(d, progress, x0)
    if (backend or cfg.backend) != "numpy":
        raise ConfigError(f"unknown backend '{backend}'; backends are: numpy, compiled")
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
        from .budgets import disk_allocator
        alloc = disk_allocator(log_dir)
    unlogged = finite.unlogged_signals(d)     # checked at every record (fwdstep.finite)
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
        except KeyboardInterrupt as exc:     # Ctrl-C, or SIGTERM/SIGHUP (fwdstep.signals)
            status, message = "interrupted", f"{_reason(exc)} at t = {t:.6g}"
            error = SimulationInterrupted(message, time=t)
            error.signum = getattr(exc, "signum", 2)
        except SimulationError as exc:    # a discrete algebraic loop: already says where
            status, message, error = "error", str(exc), exc
        except Exception as exc:  # noqa: BLE001 - wrapped with block, time and inputs
            error = _locate_failure(d, t, x, exc)
            error.__cause__ = exc
            status, message = "error", str(error)
    result = _finish(d, prog.t_log, prog.logs, row, status, message, error, alive, died_at, x,
                     n, t, wall0, reasons)
    if states is not None:
        result.states = states[:len(result.t)]
    return result


def _reason(exc) -> str:
    return getattr(exc, "reason", "interrupted by the user")


def _simulate_compiled(d: CompiledDiagram, progress, x0) -> Result:
    """``simulate`` with the numba backend: the same procedure, run in compiled chunks, on
    the same step grid (``plan_events``); discrete updates are applied here, between the
    chunks the loop ends at them (status 3, ``backend_numba.event_arrays``)."""
    try:
        from . import backend_numba
    except ImportError:
        raise ConfigError("backend 'compiled' needs numba: pip install 'fwdstep[fast]' (or use "
                          "backend 'numpy')", file=d.file) from None
    cfg = d.spec.simulation
    h, n_steps, every, bound = cfg.step, cfg.n_steps, cfg.log_every, cfg.bound
    wall0 = _time.perf_counter()
    n_rows = n_steps // every + 1 + (1 if n_steps % every else 0)
    events = plan_events(d, h, n_steps)   # the NumPy path's split steps, run in the loop
    prog = backend_numba.build_program(d, n_rows, events)
    with signals.deferred():                  # a signal during numba's compile is acted on
        prog.compile()                        # after it (raised inside numba's callbacks it
    late = signals.pending()                  # was swallowed and broke the function)
    B = d.batch
    x = prog.xn                               # (B, N); each variant runs on its own row
    x[...] = d.x0
    alive = np.ones(B, dtype=bool)
    died_at = np.full(B, np.nan)
    rows, codes, n_next = (np.zeros(B, dtype=np.int64) for _ in range(3))
    status, message, error = "ok", "", None
    reasons: dict = {}                        # variant of a batch -> why it diverged
    n, t, row = 0, 0.0, 0
    next_report = wall0 + 1.0
    with np.errstate(all="ignore"):
        try:
            if late is not None:
                raise late
            x[...] = (initial_state(d, event=events.start if events is not None else None)
                      if x0 is None else np.asarray(x0, dtype=float))
            sample = _sampler(d, events, x) if events is not None and events.discrete else None
            while n < n_steps:
                with signals.held():      # a signal during the chunk ends the run after
                    # its rows are counted (Python raised it the moment the chunk returned)
                    n1 = min(n + backend_numba.CHUNK, n_steps)
                    if B == 1:
                        codes[0], n_next[0], rows[0] = prog.run(n, n1, int(rows[0]))
                    else:                         # variants in parallel (numba prange)
                        prog.run_batch(n, n1, rows, codes, n_next, alive.copy())
                    paused = (codes == 3) & alive     # discrete blocks update before a sub-step:
                    if paused.any():                  # all alive variants stop at that row
                        q = int(prog.events[3][np.flatnonzero(paused)[0]])
                        a, lo = prog.events[2][q, 0], prog.events[2][q, 2]
                        apply_updates(prog.row_events[q], max(a, lo), x, sample)
                        codes[paused] = 0
                        n1 = int(n_next[paused][0])   # go on from that step (and row)
                    newly = (codes != 0) & alive
                    if newly.any():
                        died_at[newly] = n_next[newly] * h     # t + h of the failing step,
                        alive &= ~newly                        # status 2: t of the record
                        for b in np.flatnonzero(newly) if B > 1 else ():
                            reasons[int(b)] = (
                                _compiled_output_failure(d, died_at[b], x, b, alone=True)[0]
                                if codes[b] == 2
                                else _divergence_message(d, x, bound, died_at[b], b))
                        if not alive.any():
                            last = int(np.argmax(n_next))
                            n = int(n_next.max()) - 1
                            t = n * h
                            row = int(rows.max())
                            status = "diverged"
                            if codes[last] == 2:         # an unrecorded output not finite
                                t = float(n_next[last] * h)
                                message, x = _compiled_output_failure(d, t, x, last)
                                break
                            message = _divergence_message(d, x, bound, t + h)
                            break
                    n = n1
                    t = n * h
                    row = int(rows.max())
                    if progress is not None and _time.perf_counter() >= next_report:
                        progress(n / n_steps)
                        next_report = _time.perf_counter() + 1.0
            else:
                t = n_steps * h
                end = events.final if events is not None else None
                if end is not None and end.updates:   # an event at t_final: its right limit
                    apply_updates(end, max(t, end.hi), x, sample)
                for v in np.flatnonzero(alive):
                    if prog.final(t, int(rows[v]), int(v)) == 2:   # an output not finite
                        died_at[v], alive[v], last = t, False, int(v)
                        if B > 1:
                            reasons[last] = _compiled_output_failure(d, t, x, last, True)[0]
                row = int(rows.max()) + 1
                n = n_steps - 1
                if not alive.any():
                    status = "diverged"
                    message, x = _compiled_output_failure(d, t, x, last)
        except KeyboardInterrupt as exc:     # Ctrl-C, or SIGTERM/SIGHUP (fwdstep.signals)
            status, message = "interrupted", f"{_reason(exc)} at t = {t:.6g}"
            error = SimulationInterrupted(message, time=t)
            error.signum = getattr(exc, "signum", 2)
        except SimulationError as exc:    # an object-mode block's error: already says where
            status, message, error = "error", str(exc), exc
            row = _rows_recorded(prog.t_log, rows, row)
        except Exception as exc:  # noqa: BLE001 - wrapped with block, time and inputs
            error = _locate_failure(d, t, x.copy(), exc)
            error.__cause__ = exc
            status, message = "error", str(error)
            row = _rows_recorded(prog.t_log, rows, row)
    prog.seal()
    return _finish(d, prog.t_log, prog.logs, row, status, message, error, alive, died_at,
                   x, n, t, wall0, reasons)


def _rows_recorded(t_log, rows, row: int) -> int:
    """The rows a compiled chunk recorded before an exception left it: its loop could not
    return its row count, but each record wrote its time into t_log (NaN before), so the
    rows of the interrupted chunk are kept (a batch's loop updated ``rows`` itself)."""
    written = int(np.argmax(np.isnan(t_log))) if np.isnan(t_log).any() else len(t_log)
    return max(row, int(rows.max()), written)


def _sampler(d: CompiledDiagram, events, x):
    """``evaluate(ts)`` for ``apply_updates`` in a compiled run: the signals discrete blocks
    read, at (ts, x), from the NumPy path's generated output pass (``program.sample_signals``;
    updates are rare next to steps)."""
    numpy_prog = build_program(d, 1, sampled=tuple(events.sampled_signals))

    def evaluate(ts):
        numpy_prog.xn[...] = x
        return numpy_prog.sample_signals(ts)

    return evaluate


def _compiled_output_failure(d: CompiledDiagram, t: float, x, b: int,
                             alone: bool = False) -> tuple:
    """(message, blamed block) for variant ``b`` whose compiled run found an unrecorded
    output not finite at its record of time ``t`` (state ``x``, before that step): the
    outputs are evaluated again at (t, x) on the NumPy path to name block and port."""
    _, outputs, sig = _make_evaluator(d)
    with np.errstate(all="ignore"):
        outputs(t, x)
    values = [(i, np.asarray(v)[min(b, np.shape(v)[0] - 1)]) for i, v in enumerate(sig)
              if v is not None and i not in d.constant_signals]
    if all(np.isfinite(v).all() for _, v in values):      # not reproduced: say so
        return (f"simulation diverged at t = {t:.6g}: a block output is not finite"
                + (f" (variant {b})" if d.batch > 1 and not alone else "")
                + "; results up to that time are kept"), ""
    name, value = finite.blame(d, values)
    return finite.message(d, t, name, value, b, alone), name.rsplit(".", 1)[0]


def _finish(d, t_log, logs, row, status, message, error, alive, died_at, x, n, t,
            wall0, reasons=None) -> Result:
    """The Result of a run (partial after an error), or the error carrying it.
    ``reasons``: each diverged variant of a batch -> its own message (``Result.reasons``)."""
    reasons = {} if reasons is None else reasons
    B, N = d.batch, d.n_states
    h, bound = d.spec.simulation.step, d.spec.simulation.bound
    if status == "ok":                  # a diverged state stays the reported cause
        bad = finite.first_non_finite_output(d, t_log, logs, row, alive, died_at, reasons)
        if bad is not None:
            row, status, message, x = bad
    if B > 1 and (~alive).any() and status == "ok":
        status = "partially diverged"
        message = f"{int((~alive).sum())} of {B} variants diverged"
    t_out = t_log[:row]
    signals = {name: L[:row] for name, L in zip(d.logged, logs)}
    if B > 1:
        for b in np.flatnonzero(~alive):          # NaN after a variant's divergence
            for L in signals.values():
                L[t_out >= died_at[b], b] = np.nan
    result = Result(t=t_out, signals=signals, diagram=d, status=status, message=message,
                    wall_time=_time.perf_counter() - wall0, steps=n + (status == "ok"),
                    diverged_at=died_at, reasons=reasons)
    if status == "diverged" and isinstance(x, str):          # a block output, not a state
        raise DivergenceError(message, time=float(t_out[-1]), block=x or None, result=result)
    if status == "diverged":
        blk, _ = d.state_owner(int(np.argmax(~(np.abs(x) <= bound)) % max(N, 1)))
        raise DivergenceError(message, time=t + h, block=blk.name if blk else None,
                              result=result)
    if error is not None:
        error.result = result
        raise error
    return result


def _divergence_message(d: CompiledDiagram, x, bound, t, variant=None) -> str:
    """The first state beyond the bound or not finite (of ``variant`` alone when given:
    its own line, without naming its place in the batch)."""
    bad = np.argwhere(~(np.abs(x) <= bound))
    if variant is not None:
        bad = bad[bad[:, 0] == variant]
    b, i = (int(bad[0][0]), int(bad[0][1])) if len(bad) else (variant or 0, 0)
    blk, local = d.state_owner(i)
    val = x[b, i]
    labels = getattr(blk, "state_labels", None) if blk is not None else None
    label = labels[local] if labels and local < len(labels) else f"state[{local}]"
    what = "is not finite" if not np.isfinite(val) else f"exceeds the bound {bound:g}"
    who = f"block '{blk.name}' ({blk.type_name})" if blk is not None else "the diagram"
    place = f" (variant {b})" if d.batch > 1 and variant is None else ""
    return (f"simulation diverged at t = {t:.6g}: {who} {label} = {val:.6g} {what}{place}; "
            "results up to that time are kept")
