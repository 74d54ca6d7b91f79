"""A reference-quality solver path: scipy's adaptive ``solve_ivp`` on a compiled diagram.

``simulation: {solver: dop853 | radau | lsoda, rtol: 1e-8, atol: 1e-10}`` runs the same
diagram through ``scipy.integrate.solve_ivp`` instead of the fixed-step Runge-Kutta loop,
for stiff diagrams (``radau``, ``lsoda``) and for checking a fixed-step run against a tight
tolerance (``dop853``).  What stays the same as the fixed-step path:

* the Result: same signals, same output grid (``t = n * step`` for every ``log_every``-th
  n, and t_final), same statuses and errors;
* the discontinuity times (``fwdstep.run.events``) are breakpoints: the integration is
  restarted at each, every evaluation of a segment ending at T is made at a time < T (left
  limit) and every evaluation of the next at a time >= T (right limit), and the discrete
  blocks are updated there exactly as in the fixed-step path (a record at an event time
  shows the updated values);
* ``step`` only sets the output grid here; the solver chooses its own steps.

The whole batch is one ODE system; if any variant exceeds ``bound`` the run stops
(diverged) with everything recorded so far.
"""
from __future__ import annotations

import math
import time as _time

import numpy as np

from fwdstep.structure.compiler import CompiledDiagram
from fwdstep.core.errors import SimulationError
from fwdstep.run.events import apply_updates, plan_events
from fwdstep.results.result import Result
from fwdstep.core.solvers import IVP_METHODS
from fwdstep.run.evaluate import _locate_at, check_shapes, initial_state
from fwdstep.run.outcome import SimulationInterrupted, _divergence_message, _finish

#: tolerances when a diagram gives none
DEFAULT_RTOL = 1e-8
DEFAULT_ATOL = 1e-10


def simulate_ivp(d: CompiledDiagram, progress=None, x0: np.ndarray | None = None) -> Result:
    """Integrate ``d`` with ``solve_ivp`` (method ``simulation.solver``); see the module
    docstring.  Raises like ``fwdstep.simulate`` (the error carries the partial Result)."""
    from scipy.integrate import solve_ivp

    from fwdstep.run import finite
    from fwdstep.run.program import build_program

    cfg = d.spec.simulation
    method = IVP_METHODS[cfg.solver]
    rtol = getattr(cfg, "rtol", None) or DEFAULT_RTOL
    atol = getattr(cfg, "atol", None) or DEFAULT_ATOL
    h, n_steps, every, bound = cfg.step, cfg.n_steps, cfg.log_every, cfg.bound
    t_final = n_steps * h
    B, N = d.batch, d.n_states
    wall0 = _time.perf_counter()

    grid = [n * h for n in range(0, n_steps, every)] + [t_final]
    plan = plan_events(d, h, n_steps)
    # the fixed-step path's generated stage code: f(t, x) is its stage 1 at an explicit time
    unlogged = finite.unlogged_signals(d)     # checked at every record (fwdstep.run.finite)
    probe = (unlogged, finite.probe_buffer(d, unlogged)) if unlogged else None
    prog = build_program(d, len(grid), sampled=tuple(plan.sampled_signals) if plan else (),
                         solver="euler", probe=probe)
    check = finite.OutputCheck(d, *probe) if probe else None
    xn, k0 = prog.xn, prog.k[0]
    inner = [(t, ev) for t, ev in (plan.instants if plan else []) if 0 < t < t_final]
    start = plan.instants[0][1] if plan and plan.instants and plan.instants[0][0] == 0 else None
    end = plan.final if plan else None
    # segments [a, b]: (a, b, lo, hi, event at a whose discrete blocks update there)
    bounds = [(0.0, start)] + inner + [(t_final, end)]
    segments = []
    for (a, ev_a), (b, ev_b) in zip(bounds[:-1], bounds[1:]):
        segments.append((a, b, ev_a.hi if ev_a else -math.inf,
                         math.nextafter(ev_b.lo, -math.inf) if ev_b else math.inf,
                         ev_a if ev_a and ev_a.updates else None))

    status, message, error = "ok", "", None
    alive = np.ones(B, dtype=bool)
    died_at = np.full(B, np.nan)
    row, steps, t = 0, 0, 0.0
    x = np.empty((B, N))                       # the state; xn is the program's scratch
    next_report = wall0 + 1.0

    def record(t_rec, ts, state):
        nonlocal row
        xn[...] = state
        prog.final_ts(t_rec, ts, row)
        row += 1
        bad = check.failed(alive) if check is not None else None
        if bad is not None:
            stop = finite.probe_failure(d, prog.t_log, prog.logs, row - 1, check, bad, alive,
                                        died_at)
            if stop is not None:
                raise finite.NonFiniteOutput(stop)

    def update(event, ts):
        xn[...] = x
        apply_updates(event, ts, xn, prog.sample_signals)
        x[...] = xn

    with np.errstate(all="ignore"):
        try:
            x[...] = (initial_state(d, event=plan.start if plan is not None else None)
                      if x0 is None else np.asarray(x0, dtype=float))
            check_shapes(d, 0.0, x)
            g = 0                                  # next grid row to record
            for a, b, lo, hi, event in segments:
                t = a
                if event is not None:
                    update(event, max(a, lo))

                def rhs(tt, y, lo=lo, hi=hi):
                    nonlocal next_report
                    xn[...] = y.reshape(B, N)
                    prog.first_ts(min(max(tt, lo), hi))
                    if progress is not None and _time.perf_counter() >= next_report:
                        progress(min(tt / t_final, 1.0))
                        next_report = _time.perf_counter() + 1.0
                    return k0.reshape(-1).copy()

                last = b >= t_final
                t_eval = []
                while g < len(grid) and (grid[g] < b or (last and grid[g] <= b)):
                    t_eval.append(grid[g])
                    g += 1
                if N == 0 or b <= a:
                    states = [x.copy() for _ in t_eval]
                    x_end = x.copy()
                else:
                    sol = solve_ivp(rhs, (a, b), x.reshape(-1).copy(), method=method,
                                    t_eval=None, dense_output=True, rtol=rtol, atol=atol)
                    steps += max(len(sol.t) - 1, 0)
                    if sol.status < 0:
                        t = float(sol.t[-1])
                        raise SimulationError(f"solver {cfg.solver} failed at t = {t:.6g}: "
                                              f"{sol.message}", time=t)
                    states = [x.copy() if te == a else sol.sol(te).reshape(B, N)
                              for te in t_eval]
                    x_end = sol.y[:, -1].reshape(B, N)
                for te, xs in zip(t_eval, states):
                    if last and te == b:
                        continue                   # recorded after the final updates
                    if not (np.abs(xs) <= bound).all():
                        x_end, b = xs, te          # stop at the first record beyond it
                        break
                    record(te, max(te, lo), xs)
                x[...] = x_end
                t = b
                if not (np.abs(x) <= bound).all():
                    status = "diverged"
                    message = _divergence_message(d, x, bound, t)
                    died_at[:] = t
                    alive[:] = False
                    break
            else:
                if end is not None and end.updates:
                    update(end, max(t_final, end.hi))
                record(t_final, max(t_final, end.hi) if end else t_final, x)
        except KeyboardInterrupt:
            status, message = "interrupted", f"interrupted by the user at t = {t:.6g}"
            error = SimulationInterrupted(message, time=t)
        except SimulationError as exc:
            status, message, error = "error", str(exc), exc
        except finite.NonFiniteOutput as exc:     # an unrecorded output: block and port
            row, status, message, x = exc.stop
        except BaseException as exc:  # noqa: BLE001 - wrapped with block, time and inputs
            error = _locate_at(d, t, x, exc)
            error.__cause__ = exc
            status, message = "error", str(error)
    # _finish reports a divergence at its t + step: pass the time it happened minus a step
    return _finish(d, prog.t_log, prog.logs, row, status, message, error, alive, died_at, x,
                   max(steps - 1, 0), t - h, wall0)
