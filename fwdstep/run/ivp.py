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

import numpy as np

from fwdstep.core.errors import SimulationError
from fwdstep.core.solvers import IVP_METHODS
from fwdstep.run import finite
from fwdstep.run.backend import Backend
from fwdstep.run.evaluate import _locate_at
from fwdstep.run.events import apply_updates
from fwdstep.run.outcome import _divergence_message
from fwdstep.run.program import build_program

#: tolerances when a diagram gives none
DEFAULT_RTOL = 1e-8
DEFAULT_ATOL = 1e-10


class IvpBackend(Backend):
    """``solve_ivp`` (method ``simulation.solver``) as a backend of the run loop
    (``fwdstep.run.simulate.run``): each ``advance`` integrates one segment between declared
    discontinuities and records the grid points in it; see the module docstring."""

    def __init__(self, d, plan):
        super().__init__(d, plan)
        cfg = d.spec.simulation
        self.method = IVP_METHODS[cfg.solver]
        self.rtol = getattr(cfg, "rtol", None) or DEFAULT_RTOL
        self.atol = getattr(cfg, "atol", None) or DEFAULT_ATOL
        h, n_steps, every = cfg.step, cfg.n_steps, cfg.log_every
        self.bound = cfg.bound
        self.t_final = t_final = n_steps * h
        self.grid = [n * h for n in range(0, n_steps, every)] + [t_final]
        # the fixed-step path's generated stage code: f(t, x) is its stage 1 at a given time
        unlogged = finite.unlogged_signals(d)     # checked at every record (fwdstep.run.finite)
        probe = (unlogged, finite.probe_buffer(d, unlogged)) if unlogged else None
        self.prog = build_program(d, len(self.grid),
                                  sampled=tuple(plan.sampled_signals) if plan else (),
                                  solver="euler", probe=probe)
        self.check = finite.OutputCheck(d, *probe) if probe else None
        self.t_log, self.logs = self.prog.t_log, self.prog.logs
        inner = [(t, ev) for t, ev in (plan.instants if plan else []) if 0 < t < t_final]
        start = (plan.instants[0][1] if plan and plan.instants and plan.instants[0][0] == 0
                 else None)
        end = plan.final if plan else None
        # segments [a, b]: (a, b, lo, hi, event at a whose discrete blocks update there)
        bounds = [(0.0, start)] + inner + [(t_final, end)]
        self.segments = []
        for (a, ev_a), (b, ev_b) in zip(bounds[:-1], bounds[1:]):
            self.segments.append((a, b, ev_a.hi if ev_a else -math.inf,
                                  math.nextafter(ev_b.lo, -math.inf) if ev_b else math.inf,
                                  ev_a if ev_a and ev_a.updates else None))
        self.x = np.empty((d.batch, d.n_states))  # the state; prog.xn is the program's scratch
        self.segment = 0                          # the next segment
        self.g = 0                                # the next grid row to record
        self.steps = 0                            # the solver's steps

    def _record(self, t_rec, ts, state, out) -> bool:
        """Outputs at (ts, state), recorded as time t_rec; False when the run must stop."""
        self.prog.xn[...] = state
        self.prog.final_ts(t_rec, ts, self.row)
        self.row += 1
        return self.check is None or not out.output_check(self.t_log, self.logs,
                                                          self.row - 1, self.check)

    def update(self, event, ts: float) -> None:
        xn = self.prog.xn
        xn[...] = self.x
        apply_updates(event, ts, xn, self.prog.sample_signals)
        self.x[...] = xn

    def advance(self, out) -> None:
        """The next segment: solve_ivp over [a, b], the grid points in it recorded from the
        dense output, the state checked against the bound at each."""
        from scipy.integrate import solve_ivp

        d, prog, x, grid = self.d, self.prog, self.x, self.grid
        B, N = x.shape
        xn, k0 = prog.xn, prog.k[0]
        a, b, lo, hi, event = self.segments[self.segment]
        self.segment += 1
        self.done = self.segment >= len(self.segments)
        self.t = a
        if event is not None:
            self.update(event, max(a, lo))
        tick, t_final = self.tick, self.t_final

        def rhs(tt, y):
            xn[...] = y.reshape(B, N)
            prog.first_ts(min(max(tt, lo), hi))
            if tick is not None:
                tick(tt / t_final)
            return k0.reshape(-1).copy()

        last = b >= t_final
        t_eval = []
        while self.g < len(grid) and (grid[self.g] < b or (last and grid[self.g] <= b)):
            t_eval.append(grid[self.g])
            self.g += 1
        if N == 0 or b <= a:
            states = [x.copy() for _ in t_eval]
            x_end = x.copy()
        else:
            sol = solve_ivp(rhs, (a, b), x.reshape(-1).copy(), method=self.method,
                            t_eval=None, dense_output=True, rtol=self.rtol, atol=self.atol)
            self.steps += max(len(sol.t) - 1, 0)
            self.n = max(self.steps - 1, 0)
            if sol.status < 0:
                self.t = float(sol.t[-1])
                raise SimulationError(f"solver {d.spec.simulation.solver} failed at t = "
                                      f"{self.t:.6g}: {sol.message}", time=self.t)
            states = [x.copy() if te == a else sol.sol(te).reshape(B, N) for te in t_eval]
            x_end = sol.y[:, -1].reshape(B, N)
        for te, xs in zip(t_eval, states):
            if last and te == b:
                continue                       # recorded after the final updates
            if not (np.abs(xs) <= self.bound).all():
                x_end, b = xs, te              # stop at the first record beyond it
                break
            if not self._record(te, max(te, lo), xs, out):
                return
        x[...] = x_end
        self.t = b
        self.fraction = b / t_final if t_final else 1.0
        if not (np.abs(x) <= self.bound).all():
            # the batch is one system: the run stops with its first variant beyond the bound
            beyond = out.beyond_bound(x)
            if not out.variants_failed(out.alive.copy(), b, lambda v: (
                    _divergence_message(d, x, self.bound, b, v) if beyond[v] else
                    f"stopped at t = {b:.6g} with its batch (solve_ivp integrates a batch as "
                    "one system)")):
                return
            out.stop("diverged", _divergence_message(d, x, self.bound, b), blamed=x, time=b)

    def final_record(self, t: float, ts: float, out) -> None:
        self._record(t, ts, self.x, out)

    def locate(self, exc):
        return _locate_at(self.d, self.t, self.x, exc)
