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

Blocks whose regime changes where a signal reaches a level (a limit, a switch, a reset)
declare zero-crossing functions; a step in which one changes sign is taken again up to the
crossing (located on the step itself, to 1e-13 s), the block acts there, and the step goes
on from it (``fwdstep.run.crossings``): no stage straddles the change, RK4 keeps order 4.
Steps without a crossing run exactly the procedure above.

One run loop (``run`` below) drives every backend through one interface (``Backend``): it
sets the initial state, asks the backend to advance, reports progress, applies the final
updates and record, and owns, through ``fwdstep.run.outcome.Outcome``, everything about how a
run ends (divergence, outputs not finite, errors, Ctrl-C) and the Result.  The backends:

* ``numpy`` (``fwdstep.run.numpy_backend``): this procedure as straight-line code generated
  once per run (``fwdstep.run.program``; linear blocks fused), advanced step by step;
* ``compiled`` (``fwdstep.compiled.driver``, loaded by name: the run layer never imports it):
  the same procedure in numba, advanced a chunk of steps at a time;
* solve_ivp (``fwdstep.run.ivp``): scipy's adaptive solvers, advanced one segment between
  declared discontinuities at a time (restarted at each located zero crossing).

The procedure itself is stated once as data (``fwdstep.core.solvers.step_plan``: the nonzero
coefficients in the order they are summed) and run by ``fwdstep.core.solvers.rk_step`` (the
plain form: ``integrate_ode``, the search for a failing block in ``fwdstep.run.evaluate``);
the generated program and the compiled loop are made from the same plan, sum in the same
order and give the same numbers.  docs/performance.md tells what was measured and changed.
"""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.core.errors import ConfigError, DiagramError, SimulationError
from fwdstep.core.settings import BACKENDS
from fwdstep.core.solvers import IVP_METHODS
from fwdstep.results.result import Result
from fwdstep.run import finite
from fwdstep.run.backend import Backend
from fwdstep.run.crossings import crossing_steps
from fwdstep.run.evaluate import check_shapes, initial_state
from fwdstep.run.events import plan_events
from fwdstep.run.outcome import Outcome, SimulationInterrupted  # noqa: F401 - SimulationInterrupted: public name
from fwdstep.structure.compiler import CompiledDiagram

#: backends that plug into this loop from a higher layer, loaded by name on first use (as
#: block plugins are): the run layer never imports them.  With "numpy", BACKENDS.
PLUGGED_BACKENDS = {"compiled": "fwdstep.compiled.driver"}
#: ``simulate(d, sensitivities=[...])`` hands the run to this module's ``sensitivities``
#: (the analysis layer, loaded by name: the run layer never imports it), which runs the
#: diagram through this module's ``simulate``/``run`` with the variational equations
PLUGGED_SENSITIVITIES = "fwdstep.analysis.sensitivity"


def _plugged(name: str, d):
    import importlib
    try:
        return importlib.import_module(PLUGGED_BACKENDS[name])
    except ImportError as exc:
        if getattr(exc, "name", "") not in ("numba", "llvmlite"):
            raise
        raise ConfigError(f"backend '{name}' needs numba: pip install 'fwdstep[fast]' (or use "
                          "backend 'numpy')", file=d.file) from None


class _Progress:
    """``progress(fraction)`` at most about once per second of wall time."""

    def __init__(self, progress, wall0: float):
        self.progress, self.next = progress, wall0 + 1.0

    def __call__(self, fraction: float) -> None:
        if self.progress is not None:
            now = _time.perf_counter()
            if now >= self.next:
                self.progress(min(fraction, 1.0))
                self.next = now + 1.0


def run(d: CompiledDiagram, backend: Backend, progress=None, x0=None,
        wall0: float | None = None, notes: tuple = ()) -> Result:
    """The run loop, for every backend: initial state, advance until t_final (progress about
    once a second; a single run whose recorded outputs went NaN/inf stops there), the
    updates and record at t_final; every ending decided by one ``Outcome``."""
    cfg = d.spec.simulation
    wall0 = _time.perf_counter() if wall0 is None else wall0
    out = Outcome(d)
    for line in notes:
        out.note(line)
    tick = backend.tick = _Progress(progress, wall0)
    plan = backend.plan
    scan = d.batch == 1 and backend.scan_log
    checked = 0                               # log rows already checked for NaN/inf
    with np.errstate(all="ignore"):
        try:
            x = (initial_state(d, event=plan.start if plan is not None else None)
                 if x0 is None else np.asarray(x0, dtype=float))
            check_shapes(d, 0.0, x)           # every block once, on the NumPy path: a block
            backend.start(x)                  # that raises or returns a wrong shape is named
            while out.running and not backend.done:
                backend.advance(out)
                tick(backend.fraction)
                if scan and out.running:      # an output gone NaN/inf: stop early
                    if not finite.rows_finite(backend.logs, checked, backend.row):
                        break                 # (Outcome.finish says where and what)
                    checked = backend.row
            if out.running and backend.done:
                t = cfg.n_steps * cfg.step
                end = plan.final if plan is not None else None
                ts = max(t, end.hi) if end is not None else t
                if end is not None and end.updates:   # an event at t_final: its right limit
                    backend.update(end, ts)
                backend.final_record(t, ts, out)
        except KeyboardInterrupt as exc:     # Ctrl-C, or SIGTERM/SIGHUP (fwdstep.core.signals)
            out.interrupted(exc, backend.t)
        except SimulationError as exc:    # a discrete algebraic loop, a solver's failure, an
            out.failed(exc)               # object-mode block's error: already says where
            backend.after_error()
        except DiagramError:              # bad input found late (numba refuses a kernel)
            raise
        except BaseException as exc:  # noqa: BLE001 - a SystemExit in a kernel too: the
            # block's error (status error, data kept), never the end of fwdstep with exit 0
            error = backend.locate(exc)
            error.__cause__ = exc
            out.failed(error)
            backend.after_error()
    backend.close()
    return out.finish(backend.t_log, backend.logs, backend.row, backend.n, wall0)


def simulate(d: CompiledDiagram, progress=None, x0: np.ndarray | None = None, *,
             fuse: bool = True, backend: str | None = None,
             log_dir: str | None = None, max_log_bytes: int | None = None,
             record_states: bool = False, on_compile=None,
             sensitivities: list | str | None = None) -> Result:
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
    (``fwdstep.compiled.driver.CompiledBackend``: compiling a never-seen structure, with
    an estimate; compiled; or taking the NumPy path because compiling cannot help).
    ``log_dir``: record into memory-mapped files in that directory instead of memory
    (``fwdstep run --log-to-disk``; NumPy backend).
    ``record_states``: also keep the state at every recorded time as ``result.states``
    (rows, B, n_states) (NumPy backend, fixed-step solvers; ``fwdstep.linearize`` reads it).
    The log's size is checked before anything is allocated (``fwdstep.core.budgets.check_log``):
    at most ``max_log_bytes`` in memory (default ``budgets.DEFAULT_MAX_LOG_BYTES``, 2 GiB),
    or, with ``log_dir``, half the free space there; else ``ConfigError`` with the numbers.
    ``sensitivities``: parameters ("alpha", "Ks.gain", "K[0,1]", ...) whose forward
    sensitivities are integrated along the run, on the NumPy path or (``backend``
    "compiled") in the compiled stage: ``r.sensitivity(SIGNAL, PARAM)``,
    ``r.metric_gradient(METRIC)`` (``fwdstep.analysis.sensitivity``, docs/design.md).
    """
    if sensitivities is not None:
        if x0 is not None or log_dir is not None or record_states or not fuse:
            raise ConfigError("sensitivities are integrated from the diagram's own initial "
                              "state, in memory: they take no x0, log_dir, record_states or "
                              "fuse=False", file=d.file)
        import importlib
        return importlib.import_module(PLUGGED_SENSITIVITIES).sensitivities(
            d, sensitivities, backend=backend, progress=progress, on_compile=on_compile,
            max_log_bytes=max_log_bytes)
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
    name = backend or cfg.backend
    if record_states and (cfg.solver in IVP_METHODS or name != "numpy"):
        raise ConfigError("recording the states needs the numpy backend and a fixed-step "
                          "solver", file=d.file)
    if log_dir is not None and (cfg.solver in IVP_METHODS or name != "numpy"):
        raise ConfigError("--log-to-disk works with the numpy backend and the fixed-step "
                          "solvers only", file=d.file)
    if cfg.solver in IVP_METHODS and name == "compiled":
        raise ConfigError(f"solver '{cfg.solver}' runs through scipy's solve_ivp; it has no "
                          "compiled backend (use backend numpy)", file=d.file)
    if name not in BACKENDS:
        raise ConfigError(f"unknown backend '{backend}'; backends are: {', '.join(BACKENDS)}")
    wall0 = _time.perf_counter()
    plan = plan_events(d, cfg.step, cfg.n_steps)
    notes = []
    located = crossing_steps(d)
    if cfg.solver in IVP_METHODS:
        from fwdstep.run.ivp import IvpBackend
        stepper = IvpBackend(d, plan)
    elif name == "numpy":
        from fwdstep.run.numpy_backend import NumpyBackend
        stepper = NumpyBackend(d, plan, fuse=fuse, log_dir=log_dir,
                               record_states=record_states)
    else:
        plugged = _plugged(name, d)
        reason = plugged.numpy_instead(d)
        if reason is None:
            stepper = plugged.CompiledBackend(d, plan, on_compile)
        else:                                 # compiling cannot help: the NumPy path
            if on_compile is not None:
                on_compile("numpy", {"reason": reason})
            if located:                       # (its crossings' numbers are located alike)
                blk = located[0].block
                notes.append(f"block '{blk.name}' ({blk.type_name}) has zero crossings; the "
                             f"compiled backend cannot run this diagram: {reason}; this "
                             "run uses the numpy backend")
            from fwdstep.run.numpy_backend import NumpyBackend
            name, stepper = "numpy", NumpyBackend(d, plan, fuse=fuse)
    result = run(d, stepper, progress, x0, wall0, notes)
    if record_states:
        result.states = stepper.states[:len(result.t)]
    result.backend = name                     # the one that ran (a fallback says numpy)
    return result
