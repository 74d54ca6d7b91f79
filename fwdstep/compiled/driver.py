"""The compiled backend's side of ``simulate``: the same procedure, run in compiled chunks.

``fwdstep.run.simulate`` loads this module by name when a run asks for ``backend: compiled``
(the run layer never imports the compiled layer); divergence, interrupts and the final record
are ``fwdstep.run.outcome``'s.
"""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.core import signals
from fwdstep.core.errors import ConfigError, DiagramError, SimulationError
from fwdstep.results.result import Result
from fwdstep.run import finite
from fwdstep.run.evaluate import (_locate_failure, _make_evaluator, check_shapes,
                                  initial_state)
from fwdstep.run.events import apply_updates, plan_events
from fwdstep.run.outcome import (SimulationInterrupted, _divergence_message, _finish, _reason,
                                 _rows_recorded)
from fwdstep.structure.compiler import CompiledDiagram


#: False: run object-mode blocks inside the compiled loop even when compiling cannot help
#: (for tests of that machinery, fwdstep.run.python_blocks)
PICK_NUMPY_FOR_OBJECT_MODE = True


def simulate_compiled(d: CompiledDiagram, progress, x0, on_compile=None) -> Result:
    """``simulate`` with the numba backend: the same procedure, run in compiled chunks, on
    the same step grid (``plan_events``); discrete updates are applied here, between the
    chunks the loop ends at them (status 3, ``backend_numba.event_arrays``).

    ``on_compile(event, info)`` hears what compiling costs: ("compiling", {"diagram",
    "what", "operations", "estimate_s"}) before a structure never compiled before is compiled,
    ("compiled", {"seconds"}) after; ("numpy", {"reason"}) when compiling cannot help (the
    stage does not trace and the loop would call object-mode blocks,
    ``backend_numba.object_mode_only``): the run then takes the NumPy path."""
    try:
        from fwdstep.compiled import backend_numba
    except ImportError:
        raise ConfigError("backend 'compiled' needs numba: pip install 'fwdstep[fast]' (or use "
                          "backend 'numpy')", file=d.file) from None
    if PICK_NUMPY_FOR_OBJECT_MODE:
        backend_numba.check_compilable(d)
        reason = backend_numba.object_mode_only(d)
        if reason is not None:
            if on_compile is not None:
                on_compile("numpy", {"reason": reason})
            from fwdstep.run.simulate import simulate
            return simulate(d, progress, x0, backend="numpy")
    cfg = d.spec.simulation
    h, n_steps, every, bound = cfg.step, cfg.n_steps, cfg.log_every, cfg.bound
    wall0 = _time.perf_counter()
    n_rows = n_steps // every + 1 + (1 if n_steps % every else 0)
    events = plan_events(d, h, n_steps)   # the NumPy path's split steps, run in the loop
    announced = []

    def notify(what, operations, estimate):
        announced.append(_time.perf_counter())
        if on_compile is not None:
            on_compile("compiling", {"diagram": d.file, "what": what, "operations": operations,
                                     "estimate_s": estimate})
    prog = backend_numba.build_program(d, n_rows, events, notify=notify)
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
            x[...] = (initial_state(d, event=events.start if events is not None else None)
                      if x0 is None else np.asarray(x0, dtype=float))
            check_shapes(d, 0.0, x)           # on the NumPy path, before numba compiles:
            # a block that raises or returns a wrong shape is named, not left to numba
            with signals.deferred():          # a signal during numba's compile is acted on
                _compile(prog, d)             # after it (raised inside numba's callbacks it
            late = signals.pending()          # was swallowed and broke the function)
            if late is not None:
                raise late
            if announced and on_compile is not None:
                on_compile("compiled", {"seconds": _time.perf_counter() - announced[0]})
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
        except KeyboardInterrupt as exc:     # Ctrl-C, or SIGTERM/SIGHUP (fwdstep.core.signals)
            status, message = "interrupted", f"{_reason(exc)} at t = {t:.6g}"
            error = SimulationInterrupted(message, time=t)
            error.signum = getattr(exc, "signum", 2)
        except SimulationError as exc:    # an object-mode block's error: already says where
            status, message, error = "error", str(exc), exc
            row = _rows_recorded(prog.t_log, rows, row)
        except DiagramError:              # numba cannot compile a kernel: bad input
            raise
        except BaseException as exc:  # noqa: BLE001 - a SystemExit in a kernel too: the
            # block's error (status error, data kept), never the end of fwdstep with exit 0
            error = _locate_failure(d, t, x.copy(), exc)
            error.__cause__ = exc
            status, message = "error", str(error)
            row = _rows_recorded(prog.t_log, rows, row)
    prog.seal()
    return _finish(d, prog.t_log, prog.logs, row, status, message, error, alive, died_at,
                   x, n, t, wall0, reasons)


def _compile(prog, d: CompiledDiagram) -> None:
    """``prog.compile()``; numba's refusal of a kernel (a construct it cannot type) becomes
    one line naming the block, the kernel and numba's reason, with the way out."""
    try:
        prog.compile()
    except Exception as exc:
        if not type(exc).__module__.startswith("numba"):
            raise
        raise ConfigError(_numba_refusal(d, exc), file=d.file) from None


def _numba_refusal(d: CompiledDiagram, exc) -> str:
    import re
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc))
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    reason = next((ln for ln in lines if not ln.startswith(("Failed in", "During:", "File ",
                                                            "^", "- ", "Resolution failure"))
                   and "pipeline" not in ln), lines[0] if lines else type(exc).__name__)
    named = set(re.findall(r"<function ([\w.<>]+) at ", text))
    who = ""
    for step in d.schedule:
        k = step.block.kernels
        fns = [f for f in ((k.output, k.derivative) if k is not None else ()) if f is not None]
        hit = [f.__qualname__ for f in fns if f.__qualname__ in named]
        if hit:
            who = (f"block '{step.block.name}' ({step.block.type_name}): kernel "
                   f"{hit[0]} ")
            break
    return (f"{who or 'a kernel '}cannot be compiled by numba ({type(exc).__name__}: "
            f"{reason})"[:400] + "; run the diagram with backend numpy")


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
