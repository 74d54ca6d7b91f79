"""The NumPy backend of the run loop (``fwdstep.run.simulate.run``): the procedure of
``fwdstep.run.simulate`` as the generated program of ``fwdstep.run.program``, advanced step by
step (a chunk of ``CHUNK`` steps per call of ``advance``, between progress reports).

Steps that touch a declared discontinuity (``fwdstep.run.events``) run as their sub-steps,
with the discrete updates applied where they start; every other step runs the plain
procedure.  After each step the state is checked against the bound (one reduction; per
variant only when it fails), and after each record the outputs that are not recorded
(``fwdstep.run.finite``); what fails is reported to the run's ``Outcome``.
"""
from __future__ import annotations

import numpy as np

from fwdstep.run import finite
from fwdstep.run import crossings
from fwdstep.run.crossings import Crossings, crossing_steps
from fwdstep.run.events import apply_updates
from fwdstep.run.program import build_program
from fwdstep.run.backend import Backend

#: steps per ``advance`` (the loop reports progress and checks the log between chunks)
CHUNK = 2048


class NumpyBackend(Backend):
    chunk = CHUNK

    def __init__(self, d, plan, fuse: bool = True, log_dir: str | None = None,
                 record_states: bool = False):
        super().__init__(d, plan)
        cfg = d.spec.simulation
        self.h, self.n_steps, self.every, self.bound = (cfg.step, cfg.n_steps, cfg.log_every,
                                                        cfg.bound)
        n_rows = self.n_steps // self.every + 1 + (1 if self.n_steps % self.every else 0)
        alloc = None
        if log_dir is not None:
            from fwdstep.core.budgets import disk_allocator
            alloc = disk_allocator(log_dir)
        unlogged = finite.unlogged_signals(d)     # checked at every record (fwdstep.run.finite)
        probe = (unlogged, finite.probe_buffer(d, unlogged)) if unlogged else None
        steps = crossing_steps(d)
        sampled = tuple(sorted(set(plan.sampled_signals if plan is not None else ())
                               | {i for st in steps for i in st.inputs}))
        self.prog = build_program(d, n_rows, fuse=fuse, alloc=alloc, sampled=sampled,
                                  probe=probe, crossings=steps)
        self.crossings = Crossings(d, steps) if steps else None
        self.fresh = None            # (ts, row or -1): the stage 1 (and record) of the last end pass
        self.stop_at = None          # (t, stage time) where a Stop block ended the run
        self.last_signs = None       # the guards' signs at the end of the last (sub-)step
        self.check = finite.OutputCheck(d, *probe) if probe else None
        #: the state at every record (``simulate(record_states=True)``), else None
        self.states = (np.full((n_rows, d.batch, d.n_states), np.nan) if record_states
                       else None)
        self.x = self.prog.xn
        self.x[...] = d.x0
        self.t_log, self.logs = self.prog.t_log, self.prog.logs
        self.position = 0                         # the next step to take

    def advance(self, out) -> None:
        """Steps ``position`` .. up to CHUNK more, each the procedure of
        ``fwdstep.run.simulate`` (split where it touches a declared discontinuity; with
        zero-crossing functions, also where a guard changes sign: ``fwdstep.run.crossings``)."""
        if self.crossings is not None:
            return crossings.advance(self, out)
        prog, x, h, every, bound = self.prog, self.x, self.h, self.every, self.bound
        special = self.plan.steps if self.plan is not None else {}
        first, first_record, rest = prog.first, prog.first_record, prog.rest
        check, alive, states = self.check, out.alive, self.states
        B, N = x.shape
        absx = np.empty((B, N))
        single = B == 1 and N > 0
        n0 = self.position
        n1 = min(n0 + CHUNK, self.n_steps)
        row, n, t = self.row, self.n, self.t
        try:
            for n in range(n0, n1):
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
                    if not np.abs(x, out=absx).max() <= bound:     # (NaN fails it too)
                        out.states_diverged(x, t + h)
                        return
                elif N:                       # one reduction; per variant only if it fails
                    if not np.abs(x, out=absx).max() <= bound:
                        if out.states_diverged(x, t + h):
                            return
                        x[~alive] = 0.0      # frozen variants: keep the others finite, going
                if check is not None and n % every == 0:     # the outputs just recorded
                    if out.output_check(prog.t_log, prog.logs, row - 1, check):
                        return
                    x[~alive] = 0.0
            self.position = n1
            self.done = n1 >= self.n_steps
            self.fraction = n1 / max(self.n_steps, 1)
        finally:
            self.row, self.n, self.t = row, n, t

    def update(self, event, ts: float) -> None:
        apply_updates(event, ts, self.x, self.prog.sample_signals)

    def final_record(self, t: float, ts: float, out) -> None:
        if ts == t and (self.plan is None or self.plan.final is None):
            self.prog.final(t, self.row)
        else:
            self.prog.final_ts(t, ts, self.row)
        if self.states is not None:
            self.states[self.row] = self.x
        self.row += 1
        if self.check is not None:
            out.output_check(self.prog.t_log, self.prog.logs, self.row - 1, self.check)
