"""How a run ends, stated once for every backend: the final record, divergence messages,
interrupts (Ctrl-C, SIGTERM), and the Result with its status."""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.core import signals
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
    if d.limits:
        row, status, message, error = _stop_at_limits(d, t_out, signals, row, status, message,
                                                      error, alive, died_at, reasons)
        t_out = t_log[:row]
        signals = {name: L[:row] for name, L in zip(d.logged, logs)}
    if B > 1:
        for b in np.flatnonzero(~alive):          # NaN after a variant's divergence
            for L in signals.values():
                L[t_out >= died_at[b], b] = np.nan
    result = Result(t=t_out, signals=signals, diagram=d, status=status, message=message,
                    wall_time=_time.perf_counter() - wall0, steps=n + (status == "ok"),
                    diverged_at=died_at, reasons=reasons)
    if d.limits:
        from fwdstep.run.limits import limit_record
        result.limits = limit_record(d, t_out, signals)
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
