"""Discontinuity times and discrete updates: where a fixed-step run splits its steps.

Blocks declare the times at which their outputs jump (``Block.discontinuities``; a Step's
time, a pulse's edges, the sample instants of a discrete block).  ``plan_events`` merges
them, once per run, into a plan over the fixed grid ``t_n = n h``:

* times closer than ``SNAP * h`` to each other are one *event*; an event closer than
  ``SNAP * h`` to a grid point happens *at* that grid point;
* a grid step with an event strictly inside is split into sub-steps that end and start
  exactly at the event;
* every stage of a (sub-)step that ends at an event is evaluated at a time clamped to
  ``nextafter(T, -inf)`` (the left limit); every stage of the (sub-)step that starts at it
  at a time ``>= T`` (the right limit);
* at an event, the discrete blocks that declared it apply ``update`` (``apply_updates``),
  before the first stage of the step that starts there (so the record at that time shows
  the updated, right-limit values).

Steps without events are run exactly as before (bit for bit).  docs/discrete-time.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError, SimulationError

#: events (and grid points) closer than SNAP * h are the same instant
SNAP = 1e-9
#: the most event times one block may declare in a run
MAX_EVENTS = 10_000_000


def sample_instants(block, period: float, offset: float, t_final: float) -> np.ndarray:
    """``offset + k * period`` for k = 0, 1, ... up to t_final (each computed from k, never
    accumulated).  Refuses a period that would give more than MAX_EVENTS instants."""
    if not period > 0:
        raise ConfigError(f"block '{block.name}': sample period must be positive, got "
                          f"{period:g}", block=block.name)
    count = math.floor((t_final - offset) / period + 1e-9) + 1 if offset <= t_final else 0
    if count > MAX_EVENTS:
        raise ConfigError(f"block '{block.name}': sample period {period:g} s gives {count:.3g} "
                          f"sample instants up to t_final (limit {MAX_EVENTS:.0e})",
                          block=block.name)
    return offset + np.arange(max(count, 0)) * period


@dataclass
class Event:
    lo: float                        # the earliest of the merged times (left limits before it)
    hi: float                        # the latest (right limits from it on)
    updates: list = field(default_factory=list)   # compiled steps of discrete blocks


@dataclass
class SubStep:
    a: float                 # start time
    b: float                 # end time
    lo: float                # stage times >= lo (right limit of an event at a), else -inf
    hi: float                # stage times <= hi (left limit of an event at b), else +inf
    updates: list            # discrete blocks updated at a, before the first stage


@dataclass
class EventPlan:
    """``steps[n]``: the sub-steps replacing grid step n (only steps touched by an event);
    ``final``: the event at t_final (updates before the final record), or None;
    ``instants``: (time, event) in time order, the time being the grid point an event was
    snapped to or the event's own time (the breakpoints of ``fwdstep.ivp``)."""
    steps: dict
    final: Event | None
    events: list
    instants: list = field(default_factory=list)

    @property
    def discrete(self) -> bool:
        return any(e.updates for e in self.events)


def collect(d, t_final: float) -> list:
    """(time, compiled step or None) for every declared time of every block."""
    out = []
    for st in d.schedule:
        blk = st.block
        times = np.asarray(blk.discontinuities(t_final), dtype=float).reshape(-1)
        if not len(times):
            continue
        if len(times) > MAX_EVENTS:
            raise ConfigError(f"block '{blk.name}' declares {len(times)} discontinuity times "
                              f"(limit {MAX_EVENTS:.0e})", block=blk.name)
        times = np.unique(times[np.isfinite(times)])
        disc = st if blk.discrete else None
        out.extend((float(t), disc) for t in times)
    return out


def plan_events(d, h: float, n_steps: int) -> EventPlan | None:
    """The event plan of compiled diagram ``d`` on the grid ``n h``, n = 0..n_steps; None
    when no block declares a time (the run is then exactly the plain fixed-step one)."""
    t_final = n_steps * h
    eps = SNAP * h
    times = [(t, st) for t, st in collect(d, t_final) if -eps <= t <= t_final + eps]
    if not times:
        return None
    times.sort(key=lambda p: p[0])
    events: list = []
    for t, st in times:
        if events and t - events[-1].hi <= eps:
            events[-1].hi = max(events[-1].hi, t)
        else:
            events.append(Event(lo=t, hi=t))
        if st is not None and all(u is not st for u in events[-1].updates):
            events[-1].updates.append(st)
    # events at grid points (index m) and inside steps (index n: t_n < T < t_{n+1})
    at_grid: dict = {}
    inside: dict = {}
    instants = []
    for ev in events:
        m = round(ev.lo / h)
        if abs(ev.lo - m * h) <= eps or abs(ev.hi - m * h) <= eps:
            m = min(max(m, 0), n_steps)
            at_grid[m] = ev
            instants.append((m * h, ev))
        else:
            inside.setdefault(math.floor(ev.lo / h), []).append(ev)
            instants.append((ev.lo, ev))
    steps = {}
    touched = set(inside) | {m for m in at_grid if m < n_steps} | {m - 1 for m in at_grid
                                                                  if m > 0}
    for n in sorted(touched):
        a = n * h
        start = at_grid.get(n)
        lo = start.hi if start else -math.inf
        upd = start.updates if start else []
        subs = []
        for ev in inside.get(n, []):
            subs.append(SubStep(a, ev.lo, lo, math.nextafter(ev.lo, -math.inf), upd))
            a, lo, upd = ev.lo, ev.hi, ev.updates
        end = at_grid.get(n + 1)
        hi = math.nextafter(end.lo, -math.inf) if end else math.inf
        subs.append(SubStep(a, (n + 1) * h, lo, hi, upd))
        steps[n] = subs
    return EventPlan(steps=steps, final=at_grid.get(n_steps), events=events, instants=instants)


def apply_updates(d, steps: list, t: float, x: np.ndarray, outputs, sig) -> None:
    """Update the discrete blocks ``steps`` at event time t, in place in ``x`` (B, N).

    The new discrete states are the fixed point of ``x+ = update(x-, u(t, x+))``: each
    block's update reads its inputs at t evaluated with the *updated* states of the others
    (a ZeroOrderHold feeding a DiscreteStateSpace passes the sample of this instant, not the
    previous one), found by repeated output passes (one per level of such chains, plus one
    to confirm).  A cycle of blocks that pass their input through at the sample instant has
    no such order and is refused."""
    old = [x[:, st.state].copy() for st in steps]
    for _ in range(len(steps) + 2):
        outputs(t, x)
        new = [np.broadcast_to(st.block.update(t, xo, tuple(sig[i] for i in st.inputs)),
                               xo.shape) for st, xo in zip(steps, old)]
        same = all(np.array_equal(x[:, st.state], v, equal_nan=True)
                   for st, v in zip(steps, new))
        for st, v in zip(steps, new):
            x[:, st.state] = v
        if same:
            return
    names = ", ".join(f"'{st.block.name}'" for st in steps)
    raise SimulationError(f"discrete blocks {names} pass their inputs through to their outputs "
                          f"at the sample instant t = {t:.6g} in a loop (a discrete algebraic "
                          "loop); put a UnitDelay in the loop", time=t,
                          block=steps[0].block.name)
