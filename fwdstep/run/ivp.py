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
* ``step`` only sets the output grid here; the solver chooses its own steps (the guards
  are checked at the grid times too: where one changed sign unseen by the solver's step
  ends, the piece is solved again with steps of at most ``step``);
* zero crossings (``Block.zero_crossings``; ``fwdstep.run.crossings``) are located: each
  guard of each variant is a terminal ``solve_ivp`` event (0 counts as positive; watched
  away from its sign at the start).  At an event the crossing is found again on the
  solver's own map tau -> the state after solving from the start of the last step (t_old)
  to t_old + tau, so no stage lies past it; just past it the blocks' ``crossed`` apply,
  the event is listed, a Stop ends the run, chattering is reported once -- all through
  ``fwdstep.run.crossings.act``, as on the fixed step -- and solve_ivp starts again there.
  A guard whose sign differs across a declared discontinuity acts there.

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
from fwdstep.run.crossings import (CROSSING_TOL, Crossings, act, crossing_steps, earliest,
                                   follow_quiet)
from fwdstep.run.evaluate import _locate_at
from fwdstep.run.events import apply_updates
from fwdstep.run.outcome import _divergence_message
from fwdstep.run.program import build_program

#: tolerances when a diagram gives none
DEFAULT_RTOL = 1e-8
DEFAULT_ATOL = 1e-10
#: a guard at exactly 0 counts as positive (``G >= 0``); solve_ivp sees this instead of 0
_TINY = 5e-324


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
        steps = crossing_steps(d)
        sampled = tuple(sorted(set(plan.sampled_signals if plan is not None else ())
                               | {i for st in steps for i in st.inputs}))
        self.prog = build_program(d, len(self.grid), sampled=sampled, solver="euler",
                                  probe=probe, crossings=steps)
        self.crossings = Crossings(d, steps) if steps else None
        self.last_signs = None       # the guards' signs at the end of the last segment
        self.quiet_signs = None      # the guards' signs at the last step boundary
        self.G0 = None               # the guards where the current solve started
        self.cell = -1               # the grid step of the last crossing (chattering)
        self.pending = []            # grid points of the segment still to record
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
        """The next segment: solve_ivp over [a, b] (restarted at every located crossing),
        the grid points in it recorded from the dense output, the state checked against
        the bound at each."""
        x, grid = self.x, self.grid
        B, N = x.shape
        a, b, lo, hi, event = self.segments[self.segment]
        self.segment += 1
        self.done = self.segment >= len(self.segments)
        self.t = a
        if event is not None:
            self.update(event, max(a, lo))
        last = b >= self.t_final
        pending = []                           # the grid points of this segment
        while self.g < len(grid) and (grid[self.g] < b or (last and grid[self.g] <= b)):
            pending.append(grid[self.g])
            self.g += 1
        self.pending = pending
        if self.crossings is not None and self._jumped(a, lo, hi, out):
            return                             # a Stop ended the run where a guard jumped
        ta = a
        while True:
            if N == 0 and self.crossings is None or b <= ta:
                sol, t_cut, crossed = None, b, False
            else:
                self.start_state = x.copy()
                sol, t_cut, crossed = self._solve(ta, b, lo, hi)
            if not self._record_until(sol, ta, t_cut, crossed, last, lo, out):
                return
            self.t = t_cut
            self.fraction = t_cut / self.t_final if self.t_final else 1.0
            if not out.running or not crossed:
                break
            if self._act(t_cut, lo, hi, out):
                return                             # a Stop: its record is made
            ta = t_cut
        if self.crossings is not None:             # the signs at the end (left limit)
            self._eval(b, x, lo, hi)
            self.last_signs = self.prog.G >= 0

    def _solve(self, ta, b, lo, hi):
        """solve_ivp from (ta, x) towards b (the next step boundary while a chattering
        block's regime follows there); with guards, each a terminal event (direction: away
        from its sign at ta) and the run cut just past the earliest crossing.  Returns the
        solution, the time reached and whether a guard crossed there (x is then the state
        just past it)."""
        from scipy.integrate import solve_ivp

        d, x, prog = self.d, self.x, self.prog
        B, N = x.shape
        zc = self.crossings
        end = b
        if zc is not None and any(zc.quiet):       # follow the quiet blocks at the grid
            h = d.spec.simulation.step
            end = min(b, (math.floor(ta / h + 1e-9) + 1) * h)
            if end <= ta:
                end = b
        events = None
        if zc is not None:
            self._eval(ta, x, lo, hi)
            G0 = prog.G.copy()
            if any(zc.quiet):
                self.quiet_signs = follow_quiet(prog, prog.xn, zc, self.quiet_signs,
                                                min(max(ta, lo), hi))
                x[...] = prog.xn
                G0 = prog.G.copy()
            self.ta = ta
            events = self._events(G0, lo, hi)
            self.G0 = G0
        y0 = x.reshape(-1).copy() if N else np.zeros(1)
        sol = solve_ivp(self._rhs(lo, hi), (ta, end), y0, method=self.method,
                        dense_output=True, rtol=self.rtol, atol=self.atol,
                        events=events or None)
        if events and self._unseen(sol, ta, G0, lo, hi):
            # solve_ivp looks for sign changes at its step ends only: a guard that moves
            # with time alone (a sine's level) crossed twice within one long step of a
            # state at rest.  Solved again with steps no longer than the grid's, the
            # fixed-step path's own guarantee
            self.steps += max(len(sol.t) - 1, 0)
            sol = solve_ivp(self._rhs(lo, hi), (ta, end), y0, method=self.method,
                            dense_output=True, rtol=self.rtol, atol=self.atol,
                            events=events, max_step=d.spec.simulation.step)
        self.steps += max(len(sol.t) - 1, 0)
        self.n = max(self.steps - 1, 0)
        if sol.status < 0:
            self.t = float(sol.t[-1])
            raise SimulationError(f"solver {d.spec.simulation.solver} failed at t = "
                                  f"{self.t:.6g}: {sol.message}", time=self.t)
        if sol.status != 1:
            if N:
                x[...] = sol.y[:, -1].reshape(B, N)
            return sol, end if end < b else b, False
        t_cut = self._past(sol, lo, hi)
        return sol, t_cut, True

    def _unseen(self, sol, ta, G0, lo, hi) -> bool:
        """Whether an active guard has left its sign at ta at a grid time (n * step)
        inside the solution (before its event, if it ended at one): a crossing the
        solver's step ends did not show."""
        zc, x = self.crossings, self.x
        B, N = x.shape
        h = self.d.spec.simulation.step
        t_end = float(sol.t[-1])
        times = np.arange(math.floor(ta / h) + 1, math.ceil(t_end / h)) * h
        times = times[(times > ta) & (times < t_end)]
        if not len(times):
            return False
        states = sol.sol(times)
        s0 = G0 >= 0
        for k, tt in enumerate(times):
            self._eval(tt, states[:, k].reshape(B, N) if N else x, lo, hi)
            if (((self.prog.G >= 0) != s0) & zc.active).any():
                return True
        return False

    def _rhs(self, lo, hi):
        """f(t, y): the program's stage 1 at t clamped to [lo, hi] (the side of the
        segment's discontinuities), the guards memoised for the event functions."""
        prog, tick, t_final = self.prog, self.tick, self.t_final
        xn, k0 = prog.xn, prog.k[0]
        B, N = xn.shape
        memo = self.memo = {}
        watch = self.crossings is not None

        def rhs(tt, y):
            if N:
                xn[...] = y.reshape(B, N)
            prog.first_ts(min(max(tt, lo), hi))
            if watch:
                if len(memo) > 16:
                    memo.clear()
                memo[(tt, y.tobytes())] = prog.G.copy()
            if tick is not None:
                tick(tt / t_final)
            return k0.reshape(-1).copy() if N else np.zeros(1)
        self.f = rhs
        return rhs

    def _events(self, G0, lo, hi):
        """One terminal event function per located guard (variant, column): the guard,
        with 0 counted as positive (the fixed-step path's sign, ``G >= 0``: a guard that
        stays at 0, e.g. an unconnected reset, never fires), watched in the direction
        away from its sign at the start."""
        zc = self.crossings

        by_time = {self.ta: G0}

        def guards(tt, y):
            """The guards at time tt, computed once per time: scipy asks again at a step's
            start from the step's interpolant, whose value can differ from the state there
            in the last digits (Radau), which must not flip a guard just past its root."""
            g = by_time.get(tt)
            if g is None:
                key = (tt, y.tobytes())
                g = self.memo.get(key)
                if g is None:
                    self.f(tt, y)
                    g = self.memo[key]
                if len(by_time) > 32:
                    for old in sorted(by_time)[:-2]:
                        del by_time[old]
                by_time[tt] = g
            return g

        events = []
        for v, c in zip(*np.nonzero(zc.active & np.isfinite(G0))):
            def event(tt, y, v=v, c=c):
                g = guards(tt, y)[v, c]
                return g if g != 0.0 else _TINY
            event.terminal = True
            event.direction = -1.0 if G0[v, c] >= 0 else 1.0
            events.append(event)
        return events

    def _eval(self, tt, state, lo, hi) -> None:
        """Outputs, guards and derivatives at (tt clamped to [lo, hi], state) (prog.xn)."""
        self.prog.xn[...] = state
        self.prog.first_ts(min(max(tt, lo), hi))

    def _past(self, sol, lo, hi) -> float:
        """Just past the earliest crossing in the solver's last step [t_old, t_new]; x is
        left there.  solve_ivp's root lies on that step's interpolant, which was fitted
        through stages on both sides of the kink; here the crossing is found again on
        the solver's own map tau -> the state after solving from (t_old, y_old) to
        t_old + tau (a step that ends at the crossing: no stage straddles it), so the
        state there is accurate to the tolerance (``fwdstep.run.crossings.earliest``)."""
        from scipy.integrate import solve_ivp

        zc, prog, x = self.crossings, self.prog, self.x
        B, N = x.shape
        interp = sol.sol.interpolants[-1]
        t_old = float(sol.t[-2])
        y_old = sol.y[:, -2].copy()
        H = max(interp.t_old, interp.t) - t_old
        rhs = self.f

        def at(tau):
            span = (t_old + tau) - t_old
            if N and span > 0:
                r = solve_ivp(rhs, (t_old, t_old + tau), y_old, method=self.method,
                              rtol=self.rtol, atol=self.atol, first_step=span)
                self.steps += max(len(r.t) - 1, 0)
                y = r.y[:, -1].reshape(B, N)
            else:
                y = y_old.reshape(B, N) if N else x
            self._eval(t_old + tau, y, lo, hi)
            return prog.G.copy(), y.copy()

        G_old, _ = at(0.0)
        self._eval(t_old + H, interp(t_old + H).reshape(B, N) if N else x, lo, hi)
        GH, xh = prog.G.copy(), (interp(t_old + H).reshape(B, N) if N else x.copy())
        guess = float(sol.t[-1]) - t_old
        tol = max(CROSSING_TOL, 4 * math.ulp(t_old + H))
        tau, xs = earliest(at, G_old, GH, xh, zc.active, H, tol, guess)
        x[...] = xs
        return t_old + tau

    def _act(self, te, lo, hi, out) -> bool:
        """At te, just past a crossing: ``fwdstep.run.crossings.act`` on the state (the
        blocks' ``crossed``, the events listed, chattering, Stop).  True: a Stop ended the
        run (its record made at te)."""
        zc, prog, x = self.crossings, self.prog, self.x
        h = self.d.spec.simulation.step
        cell = math.floor(te / h)
        if cell != self.cell:                      # chattering: crossings per grid step
            zc.count[:] = 0
            self.cell = cell
        ts = min(max(te, lo), hi)
        prog.xn[...] = x
        stop = act(prog, prog.xn, zc, out, te, ts, self.G0, zc.active)
        x[...] = prog.xn
        if stop:
            self._record(te, ts, x, out)
            return True
        return False

    def _jumped(self, a, lo, hi, out) -> bool:
        """At the start of a segment: guards whose sign differs from the end of the
        previous one jumped with a declared discontinuity (a Step, a discrete update):
        their blocks act at a (nothing to locate).  True: a Stop ended the run."""
        if self.last_signs is None:
            return False
        self._eval(a, self.x, lo, hi)
        if not (((self.prog.G >= 0) != self.last_signs) & self.crossings.active).any():
            return False
        self.G0 = np.where(self.last_signs, 1.0, -1.0)
        return self._act(a, lo, hi, out)

    def _record_until(self, sol, ta, t_cut, crossed, last, lo, out) -> bool:
        """Record the pending grid points before t_cut (through it at the end of the run,
        but t_final itself after the final updates) from the solution started at (ta, x);
        False: the run stopped (a record failed, or the state beyond the bound)."""
        d, x = self.d, self.x
        B, N = x.shape
        x_end = x.copy()
        beyond_at = None
        while self.pending and (self.pending[0] < t_cut or
                                (not crossed and self.pending[0] <= t_cut)):
            te = self.pending.pop(0)
            if last and te == self.t_final:
                continue                       # recorded after the final updates
            xs = (self.start_state if te == ta else
                  sol.sol(te).reshape(B, N)) if sol is not None and N else x
            if not (np.abs(xs) <= self.bound).all():
                x_end, beyond_at = xs, te      # stop at the first record beyond it
                break
            if not self._record(te, max(te, lo), xs, out):
                return False
        if beyond_at is None:
            if (np.abs(x) <= self.bound).all():
                return True
            beyond_at = t_cut
        else:
            x[...] = x_end
        # the batch is one system: the run stops with its first variant beyond the bound
        self.t = beyond_at
        beyond = out.beyond_bound(x)
        if not out.variants_failed(out.alive.copy(), beyond_at, lambda v: (
                _divergence_message(d, x, self.bound, beyond_at, v) if beyond[v] else
                f"stopped at t = {beyond_at:.6g} with its batch (solve_ivp integrates a batch "
                "as one system)")):
            return False
        out.stop("diverged", _divergence_message(d, x, self.bound, beyond_at), blamed=x,
                 time=beyond_at)
        return False

    def final_record(self, t: float, ts: float, out) -> None:
        self._record(t, ts, self.x, out)

    def locate(self, exc):
        return _locate_at(self.d, self.t, self.x, exc)
