"""The interface between the run loop (``fwdstep.run.simulate.run``) and a backend that
advances a run: the NumPy program (``fwdstep.run.numpy_backend``), solve_ivp
(``fwdstep.run.ivp``) and the compiled backend (``fwdstep.compiled.driver``, which plugs in
from the layer above by name)."""
from __future__ import annotations

import numpy as np

from fwdstep.run.evaluate import _locate_failure
from fwdstep.structure.compiler import CompiledDiagram


class Backend:
    """What ``run`` drives: one object per run, holding the state and the record.

    Attributes the loop reads: ``x`` (B, N) the state; ``t_log``, ``logs`` the record and
    ``row`` the rows written; ``n`` the last step taken (``Result.steps``); ``t`` the time
    reached (for an interrupt's message); ``done`` once every step up to t_final is taken;
    ``fraction`` done (progress); ``scan_log`` below.  ``tick``: the loop's progress reporter, for a backend
    that advances a long way in one call (solve_ivp calls it from its right-hand side).

    Methods: ``start(x0)`` (the initial state, already computed); ``advance(out)``: take
    the next steps (a chunk: the backend chooses how many), report what fails to ``out``
    (``fwdstep.run.outcome.Outcome``) and return early when ``out.running`` turns False;
    ``update(event, ts)``: the discrete updates of an event (``fwdstep.run.events``);
    ``final_record(t, ts, out)``: outputs and record at the final time t (stage time ts);
    ``locate(exc)``: the error naming the block that raised; ``after_error()``: fix ``row``
    after an exception left a chunk; ``close()``: at the end, whatever happened."""

    x: np.ndarray
    t_log: np.ndarray
    logs: list
    row = 0
    n = 0
    t = 0.0
    done = False
    fraction = 0.0
    tick = None
    #: the loop scans the log of a single run between advances and stops at a recorded
    #: output gone NaN/inf (False: the backend's run goes on, the end finds it; measured on
    #: the compiled loop: the scan cost 6 %)
    scan_log = True

    def __init__(self, d: CompiledDiagram, plan):
        self.d, self.plan = d, plan

    def start(self, x0: np.ndarray) -> None:
        self.x[...] = x0

    def advance(self, out) -> None:
        raise NotImplementedError

    def update(self, event, ts: float) -> None:
        raise NotImplementedError

    def final_record(self, t: float, ts: float, out) -> None:
        raise NotImplementedError

    def locate(self, exc: Exception):
        return _locate_failure(self.d, self.t, self.x.copy(), exc)

    def after_error(self) -> None:
        pass

    def close(self) -> None:
        pass
