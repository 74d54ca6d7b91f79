"""Non-finite block outputs: every block output is checked at every recorded sample.

A state that leaves the bound or stops being finite ends a run in ``fwdstep.simulate``; an
output can overflow with no state involved (a Gain of 1e308 on a large signal, a signal that
only reaches a Saturation or nothing at all).  Such a run is reported like a diverging state,
with the block and port named::

    simulation diverged at t = 0.18: block 'big' (Gain) output 'y'[0] = inf is not finite;
    results up to that time are kept

Two sources are looked at, together every block output at every recorded sample (stage 1 of
every ``log_every``-th step and the final time):

* recorded signals are in the log (``first_non_finite_output`` scans it, vectorised);
* the others (a ``log:`` list that leaves blocks out; a sweep records only its metric) are
  copied at each recorded sample into one probe buffer of shape (B, their total size) by
  the generated program (``fwdstep.run.program.build_program(probe=...)``), and
  ``OutputCheck.failed`` looks at it with one reduction (a sum is finite exactly when every
  term is, unless it overflows, which the exact check then clears).

The solve_ivp path (``fwdstep.run.ivp``) uses the same probe at its records; the compiled backend
(``fwdstep.compiled.backend_numba``) checks the unrecorded outputs inside ``run_one`` and returns status
2, and ``fwdstep.simulate`` names block and port by evaluating the outputs again.

In a batch the variant whose output is not finite is marked diverged at that sample, with its
own line in ``Result.reasons`` (what its run alone would print; a sweep's row shows it), and
the others go on, each equal to its run alone.
"""
from __future__ import annotations

import numpy as np


def unlogged_signals(d) -> tuple:
    """Indices of the signals a run of ``d`` computes but does not record (constant zero
    signals of unconnected optional inputs are neither)."""
    logged = {d.signal_index[name] for name in d.logged}
    return tuple(i for i in range(len(d.signal_names))
                 if i not in logged and i not in d.constant_signals)


def probe_buffer(d, indices) -> np.ndarray:
    """The (B, total size) buffer the program copies the ``indices`` signals into."""
    size = sum(int(np.prod(d.signal_shapes[i], dtype=np.int64)) for i in indices)
    return np.zeros((d.batch, size))


class OutputCheck:
    """The unrecorded outputs of the last recorded sample: ``failed(alive)`` after each."""

    def __init__(self, d, indices, buffer: np.ndarray):
        self.d, self.P = d, buffer
        self.views, c = [], 0
        for i in indices:
            n = int(np.prod(d.signal_shapes[i], dtype=np.int64))
            self.views.append((i, buffer[:, c:c + n]))
            c += n
        self.sums = np.empty(d.batch)

    def failed(self, alive: np.ndarray):
        """None when every unrecorded output of every live variant is finite (the usual case:
        one reduction); else the boolean mask of live variants with a non-finite one."""
        if self.d.batch == 1:
            s = np.add.reduce(self.P, axis=None)
            if s - s == 0.0:                  # inf - inf and nan are not 0
                return None
            bad = ~np.isfinite(self.P).all(axis=1)
        else:
            np.add.reduce(self.P, axis=1, out=self.sums)
            if np.isfinite(self.sums).all():
                return None
            bad = ~np.isfinite(self.P).all(axis=1)
        bad &= alive
        return bad if bad.any() else None

    def values(self, b: int) -> list:
        """(signal index, value) of variant ``b``'s unrecorded outputs at the last sample."""
        return [(i, v[b]) for i, v in self.views]


def blame(d, candidates) -> tuple:
    """The earliest signal in evaluation order among (signal index, value) pairs whose
    value is not finite: with every output looked at, the block that produced the first
    non-finite value (the later ones only inherit it).  Returns (name, value)."""
    order = {st.block.name: k for k, st in enumerate(d.schedule)}
    bad = [(order.get(d.signal_names[i].rsplit(".", 1)[0], len(order)), i, value)
           for i, value in candidates if not np.isfinite(value).all()]
    _, i, value = min(bad, key=lambda c: (c[0], c[1]))
    return d.signal_names[i], value


def message(d, t: float, name: str, value, b: int, alone: bool = False) -> str:
    """The one line of a non-finite output, as a diverging state's (``alone``: variant b's
    own line, without naming its place in the batch)."""
    block, port = name.rsplit(".", 1)
    step = next((st for st in d.schedule if st.block.name == block), None)
    flat = np.asarray(value, dtype=float).reshape(-1)
    k = int(np.argmax(~np.isfinite(flat)))
    where = f"[{k}]" if flat.size > 1 else ""
    who = f"block '{block}' ({step.block.type_name})" if step is not None else f"'{block}'"
    variant = f" (variant {b})" if d.batch > 1 and not alone else ""
    return (f"simulation diverged at t = {t:.6g}: {who} output '{port}'{where} = "
            f"{flat[k]:.6g} is not finite{variant}; results up to that time are kept")


def rows_finite(logs, lo: int, hi: int) -> bool:
    """Whether log rows lo..hi-1 are finite in every recorded signal."""
    return all(np.isfinite(L[lo:hi]).all() for L in logs)


def first_non_finite_output(d, t_log, logs, row, alive, died_at, reasons=None):
    """The first recorded row where a recorded output is NaN or inf while the states were
    finite.  One vectorised scan of the log, O(log size).  For a single run returns (rows
    to keep, "diverged", message, blamed block name) or None; in a batch the variant is
    marked diverged at that time (``alive``/``died_at`` updated in place) and None is
    returned unless every variant is gone.  Blamed is the earliest recorded signal in
    evaluation order that is not finite at that row.  ``reasons`` (a dict) receives each
    marked variant's own message."""
    if row == 0 or not logs:
        return None
    B = d.batch
    first = np.full(B, row)                   # first non-finite row per variant
    for L in logs:
        flat = L[:row].reshape(row, B, -1)
        bad = ~np.isfinite(flat).all(axis=2)  # (rows, B)
        hit = bad.any(axis=0)
        if hit.any():
            first = np.minimum(first, np.where(hit, bad.argmax(axis=0), row))
    if (first >= row).all():
        return None
    found = []
    for b in np.flatnonzero(first < row):
        r = int(first[b])
        if not np.isnan(died_at[b]) and t_log[r] >= died_at[b]:
            continue                          # after this variant's state diverged
        name, value = blame(d, [(d.signal_index[n], L[r, b]) for n, L in zip(d.logged, logs)])
        found.append((r, b, name, value))
    if not found:
        return None
    r, b, name, value = min(found, key=lambda f: (f[0], f[1]))
    text = message(d, t_log[r], name, value, b)
    for r_b, b_b, name_b, value_b in found:
        died_at[b_b] = t_log[r_b]
        alive[b_b] = False
        if reasons is not None:
            reasons[int(b_b)] = message(d, t_log[r_b], name_b, value_b, b_b, alone=True)
    if alive.any():
        return None
    return (r + 1 if B == 1 else row), "diverged", text, name.rsplit(".", 1)[0]


def probe_failure(d, t_log, logs, r, check: OutputCheck, bad, alive, died_at, reasons=None):
    """Variants ``bad`` have an unrecorded output that is not finite at recorded row ``r``:
    mark them diverged at that time (``alive``/``died_at`` updated in place).  Returns
    (rows to keep, "diverged", message, blamed block name) when the run must stop (a single
    run, or every variant gone), else None.  A single run's log is scanned first: a recorded
    output may have failed at an earlier row.  ``reasons`` as in first_non_finite_output."""
    if d.batch == 1:
        earlier = first_non_finite_output(d, t_log, logs, r, alive, died_at)
        if earlier is not None:
            return earlier
    found = []
    for b in np.flatnonzero(bad):
        recorded = [(d.signal_index[n], L[r, b]) for n, L in zip(d.logged, logs)]
        name, value = blame(d, recorded + check.values(b))
        died_at[b], alive[b] = t_log[r], False
        if reasons is not None:
            reasons[int(b)] = message(d, t_log[r], name, value, b, alone=True)
        found.append((b, name, value))
    if alive.any():
        return None
    b, name, value = found[0]
    return r + 1, "diverged", message(d, t_log[r], name, value, b), name.rsplit(".", 1)[0]
