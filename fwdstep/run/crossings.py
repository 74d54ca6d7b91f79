"""Exact state events on a fixed step: zero crossings located in time.

Blocks declare guard functions next to their kernels (``Block.zero_crossings``; e.g. a
Saturation's ``u - lower`` and ``u - upper``): a regime changes where a guard changes sign.
Every stage 1 of the generated program writes the guards into ``Program.G``.  A (sub-)step
[a, b] of a diagram with guards runs as::

    stage 1 at (a, x_a): outputs, k_1, guards g(a)           (FSAL: the previous step's end pass)
    x_b = the step of size b - a;  stage 1 at (b, x_b): g(b)   (the next step's stage 1)
    if some g_j changed sign:
        tau = the earliest root in (0, b - a] of the guards that changed, found on the
              step itself: g(tau) is the guard after a step of size tau from (a, x_a) (the
              solver's own map, so the crossing lies exactly on the computed trajectory);
              secant proposals, bisection when one side stays twice, to CROSSING_TOL s
        x = the step of size tau (just past the root: the guard has its new sign)
        blocks whose guards changed: ``crossed(t, x, u, which)`` (a new mode, a reset);
        the event is listed (``Result.events``); a Stop block ends the run there
        go on from a + tau to b (a crossing is a step boundary: no stage straddles it)

so a piecewise-smooth right-hand side keeps the method's order.  A guard that crosses more
than ``CHATTER`` times within one grid step chatters (a sliding mode, stiction): that is
reported once, and its block's crossings are no longer located (its regime then follows its
guards at step boundaries).  Steps without a crossing cost one comparison of the guards'
signs; the end pass is the next step's stage 1 (and record), so nothing is evaluated twice.
"""
from __future__ import annotations

import math
import numpy as np

from fwdstep.results.result import CrossingEvent
from fwdstep.run.events import apply_updates

#: the located crossing time is within this of the exact root of the computed trajectory
CROSSING_TOL = 1e-13
#: more crossings of one block within one grid step than this: chattering
CHATTER = 8


def crossing_steps(d) -> tuple:
    """The compiled steps of blocks with zero-crossing functions, in schedule order."""
    return tuple(st for st in d.schedule if st.block.n_crossings)


class Crossings:
    """The guards of one run: columns of ``Program.G`` per block, which are still located
    (``active``), and the crossings of the current grid step (chattering)."""

    def __init__(self, d, steps):
        self.steps = steps
        self.cols = []
        c = 0
        for st in steps:
            self.cols.append(slice(c, c + st.block.n_crossings))
            c += st.block.n_crossings
        self.active = np.ones((d.batch, c), dtype=bool)
        self.count = np.zeros((d.batch, len(steps)), dtype=np.int64)   # this grid step
        self.quiet = [False] * len(steps)
        self.simple = True          # every guard located, no variant gone: the fast path
        self.counted = False        # count holds crossings of this grid step


def advance(bk, out) -> None:
    """``NumpyBackend.advance`` for a diagram with zero-crossing functions: steps
    ``bk.position`` .. up to ``bk.chunk`` more, each as in the module docstring."""
    prog, x, h, every, bound = bk.prog, bk.x, bk.h, bk.every, bk.bound
    zc: Crossings = bk.crossings
    special = bk.plan.steps if bk.plan is not None else {}
    check, alive = bk.check, out.alive
    B, N = x.shape
    n0 = bk.position
    n1 = min(n0 + bk.chunk, bk.n_steps)
    row, n, t = bk.row, bk.n, bk.t
    G = prog.G
    x0 = np.empty_like(x)
    first, first_record, rest, first_ts = prog.first, prog.first_record, prog.rest, prog.first_ts
    absx = np.empty_like(x)
    S0, S1, C = (np.empty(G.shape, dtype=bool) for _ in range(3))   # the guards' signs
    n_steps = bk.n_steps

    states = bk.states

    def failed(ts: float) -> bool:
        """After a kept record (row - 1) made at stage time ts: its state
        (``record_states``) and the unrecorded outputs; True: the run ends.  Variants that
        failed there are frozen (x = 0) and the stage 1 at ts made again for them (the
        record stands: it is not made twice)."""
        if states is not None:
            states[row - 1] = x
        if check is None:
            return False
        if out.output_check(prog.t_log, prog.logs, row - 1, check):
            return True
        if not alive.all():
            x[~alive] = 0.0
            zc.active[~alive] = False
            zc.simple = False
            prog.first_ts(ts)
        return False
    try:
        for n in range(n0, n1):
            t = n * h
            if zc.counted:
                zc.count[:] = 0
                zc.counted = False
            if n not in special and zc.simple:
                # the plain procedure (its numbers), with the guards' signs compared at the
                # end; a step that crossed is taken again, located (_unit)
                fresh = bk.fresh
                if n % every == 0:
                    if fresh is None or fresh[0] != t or fresh[1] != row - 1:
                        first_record(t, row)
                        row += 1
                        if failed(t):
                            return
                        np.greater_equal(G, 0.0, out=S0)
                elif fresh is None or fresh[0] != t:
                    first(t)
                    np.greater_equal(G, 0.0, out=S0)
                bk.fresh = None
                np.copyto(x0, x)
                rest(t)
                nxt = n + 1
                te = nxt * h
                rec_next = nxt % every == 0 and nxt < n_steps and nxt not in special
                if rec_next:
                    first_record(te, row)
                else:
                    first(te)
                np.greater_equal(G, 0.0, out=S1)
                np.not_equal(S1, S0, out=C)
                if C.any() and (C & np.isfinite(G)).any():   # (NaN/inf: divergence's)
                    np.copyto(x, x0)
                    first_ts(t)                   # stage 1 at t again: k_1, the guards
                    if _unit(bk, out, t, te, h, -math.inf, math.inf,
                             (te, row) if rec_next else None):
                        if not out.running:
                            row = _stopped(bk, prog, row)
                            return
                        bk.fresh = None           # the next step makes its stage 1
                        S1, S0 = S0, S1
                        continue_checks = True
                    else:
                        continue_checks = False
                else:
                    continue_checks = False
                if nxt in special:                # its first sub-step checks for jumps
                    bk.last_signs = G >= 0
                if not continue_checks:
                    S1, S0 = S0, S1               # the signs at te: the next step's start
                    if rec_next:
                        row += 1
                        bk.fresh = (te, row - 1)
                        if failed(te):
                            return
                    else:
                        bk.fresh = (te, -1)
                if N and not np.abs(x, out=absx).max() <= bound:     # (NaN fails it too)
                    if out.states_diverged(x, t + h):
                        row = _unrecord(bk, row)
                        return
                    _freeze(bk, alive)
                continue
            # (sub-)steps (a, b, size, lo, hi, event), sized as the plain loop sizes them
            units = ([(s.a, s.b, s.b - s.a, s.lo, s.hi, s.event) for s in special[n]]
                     if n in special else [(t, (n + 1) * h, h, -math.inf, math.inf, None)])
            for i, (a, b, H, lo, hi, event) in enumerate(units):
                if event is not None:
                    apply_updates(event, max(a, lo), x, prog.sample_signals)
                    bk.fresh = None
                ts = max(a, lo)
                rec = i == 0 and n % every == 0
                if rec:
                    if bk.fresh != (ts, row - 1):   # else: the previous end pass recorded
                        prog.first_record_ts(t, ts, row)
                        row += 1
                        if failed(ts):
                            return
                elif bk.fresh is None or bk.fresh[0] != ts:
                    prog.first_ts(ts)
                bk.fresh = None
                _follow_inactive(bk, ts)
                if bk.last_signs is not None:     # a guard that jumped between (sub-)steps
                    if _jumps(bk, out, t if rec else None, ts, row - 1):
                        row = _stopped(bk, prog, row)
                        return
                    bk.last_signs = None
                # the end pass: the next step's stage 1 (and record) when it starts here
                nxt = n + 1
                rec_next = (i == len(units) - 1 and nxt < bk.n_steps and nxt % every == 0
                            and nxt not in special)
                end = (nxt * h, row) if rec_next else None
                crossed = _unit(bk, out, a, b, H, lo, hi, end)
                if not out.running:
                    row = _stopped(bk, prog, row)
                    return
                if crossed:                       # the stage 1 at the end, made again
                    prog.first_ts(min(b, hi))
                    bk.fresh = (min(b, hi), -1)
                elif rec_next:
                    row += 1
                    bk.fresh = (min(b, hi), row - 1)
                    if failed(min(b, hi)):
                        return
                else:
                    bk.fresh = (min(b, hi), -1)
                bk.last_signs = G >= 0            # where the next (sub-)step starts from
            if bk.fresh is not None:              # the signs the next step starts from
                np.greater_equal(G, 0.0, out=S0)
            if N:
                if not np.abs(x).max() <= bound:                 # (NaN fails it too)
                    if out.states_diverged(x, t + h):
                        row = _unrecord(bk, row)
                        return
                    _freeze(bk, alive)
        bk.position = n1
        bk.done = n1 >= bk.n_steps
        bk.fraction = n1 / max(bk.n_steps, 1)
    finally:
        bk.row, bk.n, bk.t = row, n, t


def _unrecord(bk, row: int) -> int:
    """The run diverged at the end of a step: the end pass's record of that state (the
    next step's stage 1) is not kept, as the plain procedure never makes it."""
    if bk.fresh is not None and bk.fresh[1] == row - 1:
        bk.fresh = None
        return row - 1
    return row


def _freeze(bk, alive) -> None:
    """Variants that failed at the end of a step: frozen (x = 0, their guards no longer
    watched), the stage 1 the next step starts from made again for them; a record made by
    that stage 1 stands (``fresh`` keeps its row: it is not made twice)."""
    bk.x[~alive] = 0.0
    bk.crossings.active[~alive] = False
    bk.crossings.simple = False
    if bk.fresh is not None:
        bk.prog.first_ts(bk.fresh[0])


def _stopped(bk, prog, row: int) -> int:
    """A Stop block ended the run: the last record, at its crossing; the rows."""
    if bk.stop_at is not None:
        te, tse = bk.stop_at
        prog.first_record_ts(te, tse, row)
        if bk.states is not None:
            bk.states[row] = bk.x
        bk.stop_at = None
        return row + 1
    return row


def _jumps(bk, out, t_rec, ts: float, rec_row: int) -> bool:
    """At the start (ts) of a (sub-)step: guards whose sign differs from the end of the
    previous one jumped there (a Step, a discrete update): their blocks' ``crossed`` is
    applied at ts (nothing to locate) and the stage 1 (and record) made again.  True: a
    Stop ended the run."""
    prog, zc = bk.prog, bk.crossings
    G = prog.G
    changed = ((G >= 0) != bk.last_signs) & zc.active
    if not changed.any():
        return False
    if _crossed(bk, out, ts, ts, np.where(bk.last_signs, 1.0, -1.0), zc.active):
        bk.stop_at = (ts, ts)
        return True
    if t_rec is not None:
        prog.first_record_ts(t_rec, ts, rec_row)
    else:
        prog.first_ts(ts)
    return False


def _after_crossing(bk, row: int) -> int:
    """After a (sub-)step that crossed: the stage 1 at its end is made again by the next
    step (a Stop's record aside, nothing was recorded for it)."""
    bk.fresh = None
    return row


def _unit(bk, out, a, b, H, lo, hi, end) -> bool:
    """The (sub-)step [a, b] of size H from the stage 1 just made at a; ``end``: (time,
    row) of the record the end pass makes, or None.  Returns whether a guard crossed (the
    stage 1 at b is then not the end pass's: the next step makes its own).

    In a batch each crossing variant is located on its own (the others' rows of those
    re-steps are dropped), so every variant has its own crossings and the numbers of its
    run alone; the variants that did not cross keep the full step."""
    prog, x, zc = bk.prog, bk.x, bk.crossings
    G, K0 = prog.G, prog.k[0]
    G0, K0a, x0 = G.copy(), K0.copy(), x.copy()
    if not H > 0:
        return False
    _step(prog, a, H, lo, hi, b, end)
    changed = ((G >= 0) != (G0 >= 0)) & zc.active & np.isfinite(G) & np.isfinite(G0)
    if not changed.any():
        return False
    B = x.shape[0]
    if B == 1:
        _located(bk, out, a, b, H, lo, hi, x0, K0a, G0, zc.active)
        return True
    x_full, G_full = x.copy(), G.copy()
    own = {}
    for v in np.flatnonzero(changed.any(axis=1)):
        x[...] = x_full
        G[...] = G_full
        mask = np.zeros_like(zc.active)
        mask[v] = True
        _located(bk, out, a, b, H, lo, hi, x0, K0a, G0, zc.active & mask)
        if not out.running:
            return True
        own[v] = x[v].copy()
    x[...] = x_full
    for v, xv in own.items():
        x[v] = xv
    return True


def _step(prog, a, H, lo, hi, b, end) -> None:
    """x <- the step of size H from (a, x) (stage 1 made), then stage 1 at its end."""
    prog.rest_h(a, H, lo, hi)
    if end is not None:
        prog.first_record_ts(end[0], min(b, hi), end[1])
    else:
        prog.first_ts(min(b, hi))


def _located(bk, out, a, b, H, lo, hi, x0, K0a, G0, active) -> None:
    """From (a, x0) to b, every crossing of the ``active`` guards located and acted on;
    x and G hold the step of size H from (a, x0) (which crossed).

    A guard that crossed and was acted on (a reset reversing the motion: a bouncing ball)
    may cross back and return to its side again before b: its sign at b is then the one
    just after the crossing, and the rest of the step would run as if nothing happened (the
    ball fell through the floor once its bounces were shorter than a step).  So when no
    sign changed at b, those guards are looked at a little past the crossing (``_BACK``
    tolerances): a sign change there is located like any other."""
    prog, x = bk.prog, bk.x
    G, K0 = prog.G, prog.k[0]
    ta = a
    while True:
        tau = _locate(prog, x, K0, G, x0, K0a, G0, active, ta, H, lo, hi)
        ta = ta + tau
        just = ((G >= 0) != (G0 >= 0)) & active & np.isfinite(G)   # crossed here
        if _crossed(bk, out, ta, min(ta, hi), G0, active):
            bk.stop_at = (ta, min(ta, hi))
            return
        if not ta < b:
            return
        prog.first_ts(max(ta, lo))                 # go on from the crossing, new side
        _follow_inactive(bk, max(ta, lo))
        G0, K0a, x0 = G.copy(), K0.copy(), x.copy()
        H = b - ta
        _step(prog, ta, H, lo, hi, b, None)
        if (((G >= 0) != (G0 >= 0)) & active).any():
            continue
        just &= active                             # (a chattering block is no longer)
        if not just.any():
            return
        back = min(H, _BACK * max(CROSSING_TOL, 4 * math.ulp(ta + H)))
        xb = x.copy()                              # the state at b (its stage 1 is made
        x[...] = x0                                # again by the caller)
        K0[...] = K0a
        prog.rest_h(ta, back, lo, hi)
        prog.first_ts(min(ta + back, hi))
        if not (((G >= 0) != (G0 >= 0)) & just & np.isfinite(G)).any():
            x[...] = xb
            return
        H = back                                   # located in (0, back] next


#: how far past an acted-on crossing (in crossing tolerances) a guard is looked at again
#: when its sign at the end of the step is unchanged (``_located``)
_BACK = 64


def _locate(prog, x, K0, G, x0, K0a, G0, active, ta, H, lo, hi) -> float:
    """The step size tau in (0, H] just past the earliest sign change of an active guard
    along the computed trajectory from (ta, x0), where x and G hold the step of size H;
    leaves x at the step of size tau."""
    def at(tau):
        x[...] = x0
        K0[...] = K0a
        prog.rest_h(ta, tau, lo, hi)
        prog.first_ts(min(ta + tau, hi))
        return G.copy(), x.copy()

    tau, x[...] = earliest(at, G0, G.copy(), x.copy(), active, H,
                           max(CROSSING_TOL, 4 * math.ulp(ta + H)))
    return tau


def earliest(at, G0, GH, xh, active, H: float, tol: float, guess: float | None = None):
    """The least tau in (0, H] (within tol) at which an ``active`` guard has left its sign
    in G0 (the guards at 0), on the map ``at(tau)`` -> (guards, state) (the solver's step
    of size tau); GH, xh: ``at(H)``, where some guard has left it.  Secant proposals on the
    guards that changed (``guess`` first, if given), bisection when one end of the bracket
    stays twice.  Returns (tau, the state there)."""
    s0 = G0 >= 0
    tl, gl = 0.0, G0
    th, gh = H, GH
    kept = 0                                   # +k: the lower end moved k times in a row
    for _ in range(200):
        if th - tl <= tol:
            break
        ch = ((gl >= 0) != (gh >= 0)) & active
        if guess is not None and tl < guess < th:
            p, guess = guess, None
        elif abs(kept) >= 2 or not ch.any():
            p = 0.5 * (tl + th)
        else:
            a, b = gl[ch], gh[ch]
            p = float(np.min(tl + (th - tl) * (a / (a - b))))
        p = min(max(p, tl + 0.25 * tol), th - 0.25 * tol)
        gp, xp = at(p)
        if (((gp >= 0) != s0) & active).any():
            th, gh, xh = p, gp, xp
            kept = kept - 1 if kept < 0 else -1
        else:
            tl, gl = p, gp
            kept = kept + 1 if kept > 0 else 1
    return th, xh


def _crossed(bk, out, te: float, ts: float, G0, active) -> bool:
    """``act`` on the fixed-step backend's program and state.  True: the run ends."""
    stop = act(bk.prog, bk.x, bk.crossings, out, te, ts, G0, active)
    bk.fresh = None
    return stop


def act(prog, x, zc: Crossings, out, te: float, ts: float, G0, active) -> bool:
    """At te, just past a located crossing, the state ``x`` (B, N) (the program's ``xn``):
    the guards' new signs, each crossing block's ``crossed`` (x changed in place), the
    events listed, chattering and Stop handled; the same for every backend that locates
    crossings (fixed step here, solve_ivp in ``fwdstep.run.ivp``).  True: the run ends."""
    sig = prog.sample_signals(ts)              # outputs and guards at (ts, x)
    G = prog.G
    changed = ((G >= 0) != (G0 >= 0)) & active
    for k, (st, cols) in enumerate(zip(zc.steps, zc.cols)):
        which = changed[:, cols]
        rows = which.any(axis=1)
        if not rows.any():
            continue
        blk = st.block
        u = tuple(sig[i] for i in st.inputs)
        new = blk.crossed(ts, x[:, st.state] if st.state is not None else x[:, 0:0], u,
                          which)
        if new is not None and st.state is not None:
            x[rows, st.state] = np.broadcast_to(new, (x.shape[0], blk.n_states))[rows]
        size = blk.crossing_size
        for b in np.flatnonzero(rows):
            for j in np.flatnonzero(which[b]):
                kind = (f"{blk.crossing_names[j // size]}"
                        f"{'' if size == 1 else f'[{j % size}]'} "
                        f"{'rising' if G[b, cols][j] >= 0 else 'falling'}")
                out.event(CrossingEvent(te, blk.name, kind, int(b)))
        if blk.stops_run:
            out.stop("stopped", f"stopped by block '{blk.name}' ({blk.type_name}) at "
                                f"t = {te:.12g}")
            return True
        zc.count[rows, k] += 1
        zc.counted = True
        chatter = rows & (zc.count[:, k] > CHATTER)
        if chatter.any():
            zc.active[chatter, cols] = False
            zc.simple = False
            for b in np.flatnonzero(chatter):
                out.event(CrossingEvent(te, blk.name, "chattering", int(b)))
            out.note(f"block '{blk.name}' ({blk.type_name}): its zero crossing recurs more "
                     f"than {CHATTER} times within one step at t = {te:.6g} (chattering); "
                     "from there on its crossings are not located, its regime follows at "
                     "step boundaries")
            zc.quiet[k] = True
    return False


def _follow_inactive(bk, ts: float) -> None:
    """``follow_quiet`` on the fixed-step backend's program and state."""
    if any(bk.crossings.quiet):
        bk._quiet_signs = follow_quiet(bk.prog, bk.x, bk.crossings,
                                       getattr(bk, "_quiet_signs", None), ts)


def follow_quiet(prog, x, zc: Crossings, prev, ts: float):
    """Blocks whose crossings are no longer located (chattering): at a step boundary ts,
    their regime follows the guards' signs since ``prev`` (the signs at the previous
    boundary; None: the first) through ``crossed`` without location; the signs now."""
    now = prog.G >= 0
    if prev is None:
        return now.copy()
    changed = (now != prev) & ~zc.active
    if not changed.any():
        return now.copy()
    sig = prog.sample_signals(ts)
    for st, cols, quiet in zip(zc.steps, zc.cols, zc.quiet):
        which = changed[:, cols]
        if quiet and which.any() and st.state is not None:
            new = st.block.crossed(ts, x[:, st.state], tuple(sig[i] for i in st.inputs), which)
            if new is not None:
                rows = which.any(axis=1)
                x[rows, st.state] = np.broadcast_to(new, (x.shape[0], st.block.n_states))[rows]
    prog.first_ts(ts)
    return prog.G >= 0
