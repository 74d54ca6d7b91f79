"""How a run ends, stated once for every backend: which variants failed, when and why (a
state beyond the bound, an output not finite), interrupts (Ctrl-C, SIGTERM), errors, and the
Result with its status.  ``fwdstep.run.simulate.run`` keeps one ``Outcome`` per run; the
backends report what they detect to it and stop when it says the run is over."""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.core.errors import DivergenceError, LimitExceeded, SimulationError
from fwdstep.results.result import Result
from fwdstep.run import finite
from fwdstep.structure.compiler import CompiledDiagram


class SimulationInterrupted(SimulationError):
    """The run was interrupted (Ctrl-C); ``result`` holds everything up to ``time``."""


def _reason(exc) -> str:
    return getattr(exc, "reason", "interrupted by the user")


def _rows_recorded(t_log, rows, row: int) -> int:
    """The rows a compiled chunk recorded before an exception left it: its loop could not
    return its row count, but each record wrote its time into t_log (NaN before), so the
    rows of the interrupted chunk are kept (a batch's loop updated ``rows`` itself)."""
    written = int(np.argmax(np.isnan(t_log))) if np.isnan(t_log).any() else len(t_log)
    return max(row, int(rows.max()), written)


class Outcome:
    """The state of a run's ending: ``alive`` (per variant), ``died_at`` (time each variant
    failed, NaN while alive), ``reasons`` (a batch's variant -> its own one line), and the
    run's ``status``, ``message``, ``error``.  ``running`` is True until a failure stops the
    whole run (a single run's failure, or the last variant of a batch)."""

    def __init__(self, d: CompiledDiagram):
        self.d = d
        B = d.batch
        self.alive = np.ones(B, dtype=bool)
        self.died_at = np.full(B, np.nan)
        self.reasons: dict = {}
        self.status, self.message, self.error = "ok", "", None
        self.blamed = None          # the states (array) or the block name (str) at fault
        self.fail_time = None       # a state's divergence: the time its step ended
        self.rows = None            # rows to keep, when the failure decides them
        self.events: list = []      # located zero crossings (fwdstep.run.crossings)
        self.notes: list = []       # one line each: what the run did that a user should know

    @property
    def running(self) -> bool:
        return self.status == "ok"

    # ------------------------------------------------------------------ what backends report
    def beyond_bound(self, x) -> np.ndarray:
        """The alive variants whose state in ``x`` is beyond the bound or not finite."""
        bound = self.d.spec.simulation.bound
        if not x.shape[1]:
            return np.zeros(self.d.batch, dtype=bool)
        return ~(np.abs(x).max(axis=1) <= bound) & self.alive

    def states_diverged(self, x, t: float, bad=None) -> bool:
        """Variants ``bad`` (default: every alive one beyond the bound) diverged at time t
        (the end of their step).  Marks them, each with its own line in a batch; True (and
        the run is over) when none is left."""
        bound = self.d.spec.simulation.bound
        bad = self.beyond_bound(x) if bad is None else bad
        self.died_at[bad] = t
        if self.d.batch > 1:
            for b in np.flatnonzero(bad):
                self.reasons[int(b)] = _divergence_message(self.d, x, bound, t, int(b))
        self.alive &= ~bad
        if self.alive.any():
            return False
        self.stop("diverged", _divergence_message(self.d, x, bound, t), blamed=x, time=t)
        return True

    def variants_failed(self, bad, times, reason) -> bool:
        """Variants ``bad`` (mask or indices) failed at ``times``; ``reason(b)`` is variant
        b's own line (asked for in a batch only).  True when none is left alive (the caller
        then says why with ``stop``)."""
        self.died_at[bad] = times
        if self.d.batch > 1:
            for b in (np.flatnonzero(bad) if np.asarray(bad).dtype == bool else bad):
                self.reasons[int(b)] = reason(int(b))
        self.alive[bad] = False
        return not self.alive.any()

    def output_check(self, t_log, logs, r: int, check) -> bool:
        """After record ``r``: the unrecorded outputs (``finite.OutputCheck``) of the alive
        variants.  True when the run must stop (a single run, or every variant gone)."""
        bad = check.failed(self.alive)
        if bad is None:
            return False
        stop = finite.probe_failure(self.d, t_log, logs, r, check, bad, self.alive,
                                    self.died_at, self.reasons)
        if stop is None:
            return False
        rows, status, message, blamed = stop
        self.stop(status, message, blamed=blamed, rows=rows)
        return True

    def event(self, event) -> None:
        """A located state event (``fwdstep.run.crossings.CrossingEvent``)."""
        self.events.append(event)

    def note(self, line: str) -> None:
        """Something the user should know, said once (chattering, a fallback)."""
        if line not in self.notes:
            self.notes.append(line)

    def stop(self, status: str, message: str, blamed=None, time=None, rows=None,
             error=None) -> None:
        self.status, self.message, self.blamed = status, message, blamed
        self.fail_time, self.rows, self.error = time, rows, error

    def interrupted(self, exc, t: float) -> None:
        """Ctrl-C, or SIGTERM/SIGHUP (fwdstep.core.signals), at time t."""
        message = f"{_reason(exc)} at t = {t:.6g}"
        error = SimulationInterrupted(message, time=t)
        error.signum = getattr(exc, "signum", 2)
        self.stop("interrupted", message, error=error)

    def failed(self, error) -> None:
        """A block raised (``error`` names it) or the run cannot go on."""
        self.stop("error", str(error), error=error)

    # ------------------------------------------------------------------ the end
    def finish(self, t_log, logs, row: int, n: int, wall0: float) -> Result:
        """The Result of a run (partial after an error), or the error carrying it; ``row``
        rows recorded, ``n`` the last step taken (a finished run took n + 1)."""
        d = self.d
        B, N = d.batch, d.n_states
        bound = d.spec.simulation.bound
        if self.rows is not None:
            row = self.rows
        status, message, blamed = self.status, self.message, self.blamed
        alive, died_at = self.alive, self.died_at
        if status == "ok":                  # a diverged state stays the reported cause
            bad = finite.first_non_finite_output(d, t_log, logs, row, alive, died_at,
                                                 self.reasons)
            if bad is not None:
                row, status, message, blamed = bad
        if B > 1 and (~alive).any() and status == "ok":
            status = "partially diverged"
            message = f"{int((~alive).sum())} of {B} variants diverged"
        t_out = t_log[:row]
        signals = {name: L[:row] for name, L in zip(d.logged, logs)}
        if d.limits:
            row, status, message, self.error = _stop_at_limits(
                d, t_out, signals, row, status, message, self.error, alive, died_at,
                self.reasons)
            t_out = t_log[:row]
            signals = {name: L[:row] for name, L in zip(d.logged, logs)}
        if B > 1:
            for b in np.flatnonzero(~alive):          # NaN after a variant's divergence
                for L in signals.values():
                    L[t_out >= died_at[b], b] = np.nan
        result = Result(t=t_out, signals=signals, diagram=d, status=status, message=message,
                        wall_time=_time.perf_counter() - wall0, steps=n + (status == "ok"),
                        diverged_at=died_at, reasons=self.reasons, events=self.events,
                        notes=self.notes)
        if d.limits:
            from fwdstep.run.limits import limit_record
            result.limits = limit_record(d, t_out, signals)
        if status == "diverged" and isinstance(blamed, str):     # a block output, not a state
            raise DivergenceError(message, time=float(t_out[-1]), block=blamed or None,
                                  result=result)
        if status == "diverged":
            blk, _ = d.state_owner(int(np.argmax(~(np.abs(blamed) <= bound)) % max(N, 1)))
            raise DivergenceError(message, time=self.fail_time,
                                  block=blk.name if blk else None, result=result)
        if self.error is not None:
            self.error.result = result
            raise self.error
        return result


def _stop_at_limits(d, t_out, signals, row, status, message, error, alive, died_at, reasons):
    """Cut the run at the first recorded sample beyond a limit declared with ``stop``
    (fwdstep.run.limits): a single run ends there (status ``limit exceeded``, unless it
    failed earlier), a variant of a batch is frozen there (NaN after, its own line in
    ``reasons``).  Returns (rows to keep, status, message, error)."""
    from fwdstep.run.limits import LIMIT_STATUS, first_stop, stop_message
    stops = first_stop(d, t_out, signals)
    if stops is None or not (stops < row).any():
        return row, status, message, error
    if d.batch == 1:
        r = int(stops[0])
        message = stop_message(d, t_out, signals, r, 0, alone=True)
        return r + 1, LIMIT_STATUS, message, LimitExceeded(message, time=float(t_out[r]))
    stopped = 0
    for b in np.flatnonzero(stops < row):
        r = int(stops[b])
        if not np.isnan(died_at[b]) and died_at[b] <= t_out[r]:
            continue                              # diverged before
        stopped += 1
        reasons[int(b)] = stop_message(d, t_out, signals, r, int(b), alone=True)
        alive[b] = False
        died_at[b] = t_out[r + 1] if r + 1 < row else np.inf
    if stopped and status in ("ok", "partially diverged"):
        status = LIMIT_STATUS
        message = (f"{stopped} of {d.batch} variants stopped at an operating limit "
                   f"(stop_on_limits)")
    return row, status, message, error


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
