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

from fwdstep.core.errors import ConfigError, SimulationError
from fwdstep.core.instants import MAX_EVENTS, sample_instants  # noqa: F401  (blocks' helper)

#: events (and grid points) closer than SNAP * h are the same instant
SNAP = 1e-9
@dataclass
class Event:
    lo: float                        # the earliest of the merged times (left limits before it)
    hi: float                        # the latest (right limits from it on)
    updates: list = field(default_factory=list)   # compiled steps of discrete blocks
    #: ``updates`` in levels: a block's inputs depend (through feedthrough) only on blocks of
    #: lower levels; None when they form a loop (then: fixed-point iteration)
    levels: list | None = None


@dataclass
class SubStep:
    a: float                 # start time
    b: float                 # end time
    lo: float                # stage times >= lo (right limit of an event at a), else -inf
    hi: float                # stage times <= hi (left limit of an event at b), else +inf
    event: Event | None      # its discrete blocks are updated at a, before the first stage


@dataclass
class EventPlan:
    """``steps[n]``: the sub-steps replacing grid step n (only steps touched by an event);
    ``final``: the event at t_final (updates before the final record), or None;
    ``instants``: (time, event) in time order, the time being the grid point an event was
    snapped to or the event's own time (the breakpoints of ``fwdstep.run.ivp``)."""
    steps: dict
    final: Event | None
    events: list
    instants: list = field(default_factory=list)
    start: Event | None = None           # the event at t = 0 (if its blocks update there)

    @property
    def discrete(self) -> bool:
        return any(e.updates for e in self.events)

    @property
    def sampled_signals(self) -> list:
        """Signal indices read by the discrete blocks (what an update needs)."""
        return sorted({i for e in self.events for st in e.updates for i in st.inputs})


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
    _order_updates(d, events)
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
        upd = start if start and start.updates else None
        subs = []
        for ev in inside.get(n, []):
            subs.append(SubStep(a, ev.lo, lo, math.nextafter(ev.lo, -math.inf), upd))
            a, lo, upd = ev.lo, ev.hi, ev if ev.updates else None
        end = at_grid.get(n + 1)
        hi = math.nextafter(end.lo, -math.inf) if end else math.inf
        subs.append(SubStep(a, (n + 1) * h, lo, hi, upd))
        steps[n] = subs
    first = at_grid.get(0)
    return EventPlan(steps=steps, final=at_grid.get(n_steps), events=events, instants=instants,
                     start=first if first is not None and first.updates else None)


def _order_updates(d, events: list) -> None:
    """Sort each event's discrete blocks into levels: block D comes after block E when E's
    output reaches D's inputs through blocks with feedthrough (found once, from the
    schedule, which is topological for feedthrough)."""
    reach: dict = {}                 # signal index -> names of discrete blocks it depends on
    for st in d.schedule:
        blk = st.block
        names = list(blk.inputs)
        for port, idx in zip(blk.outputs, st.outputs):
            if blk.discrete:
                reach[idx] = frozenset((blk.name,))
            else:
                deps = [reach.get(st.inputs[names.index(i)], frozenset())
                        for i in blk.feedthrough(port)]
                reach[idx] = frozenset().union(*deps)
    cache: dict = {}
    for ev in events:
        if not ev.updates:
            continue
        key = tuple(st.block.name for st in ev.updates)
        if key not in cache:
            cache[key] = _levels(ev.updates, reach)
            if cache[key] is None:
                _refuse_algebraic_loop(ev, reach, getattr(d, "file", None))
        ev.levels = cache[key]


def _refuse_algebraic_loop(ev, reach: dict, file=None) -> None:
    """Refuse, before the run, a loop of discrete blocks that update at one instant and all
    pass their sample through (``Block.samples_through``): their new states would be a fixed
    point that no order of updates reaches.  Loops through a UnitDelay (or a block that
    does not say) are left to the run's fixed-point iteration."""
    import networkx as nx
    through = {st.block.name: st for st in ev.updates if st.block.samples_through is True}
    g = nx.DiGraph()
    for name, st in through.items():
        for i in st.inputs:
            for source in reach.get(i, frozenset()):
                if source in through:
                    g.add_edge(source, name)
    try:
        cycle = nx.find_cycle(g)
    except nx.NetworkXNoCycle:
        return
    names = [a for a, _ in cycle]
    raise ConfigError(f"discrete blocks {', '.join(repr(n) for n in names)} pass their inputs "
                      f"through to their outputs at the sample instant t = {ev.lo:.6g} in a "
                      f"loop ({' -> '.join(names + names[:1])}: a discrete algebraic loop); "
                      "put a UnitDelay in the loop", file=file, block=names[0])


def check_events(d) -> None:
    """What ``plan_events`` refuses (too many sample instants, a discrete algebraic loop),
    found without running: ``fwdstep validate`` never says ok to a run that cannot start."""
    cfg = d.spec.simulation
    plan_events(d, cfg.step, cfg.n_steps)


def _levels(updates: list, reach: dict) -> list | None:
    here = {st.block.name for st in updates}
    after = {st.block.name: set().union(*[reach.get(i, frozenset()) for i in st.inputs]) & here
             for st in updates}
    levels, placed = [], set()
    while len(placed) < len(updates):
        level = [st for st in updates if st.block.name not in placed
                 and after[st.block.name] <= placed]
        if not level:
            return None                  # a loop: fixed-point iteration decides
        levels.append(level)
        placed.update(st.block.name for st in level)
    return levels


def apply_updates(event: Event, t: float, x: np.ndarray, evaluate) -> None:
    """Update the discrete blocks of ``event`` at time t, in place in ``x`` (B, N).
    ``evaluate(t)`` evaluates every output at (t, x) and returns the signals (indexable by
    signal index).

    The new discrete states are the fixed point of ``x+ = update(x-, u(t, x+))``: each
    block's update reads its inputs at t evaluated with the *updated* states of the others
    (a ZeroOrderHold feeding a DiscreteStateSpace passes the sample of this instant, not the
    previous one).  Without a loop among the blocks this is one output pass per level
    (``Event.levels``); with one, passes are repeated until nothing changes, and a loop of
    blocks that pass their input through at the sample instant never settles: refused."""
    steps = event.updates
    if event.levels is not None:
        for level in event.levels:
            sig = evaluate(t)
            new = [st.block.update(t, x[:, st.state], tuple(sig[i] for i in st.inputs))
                   for st in level]
            for st, v in zip(level, new):
                x[:, st.state] = v
        return
    old = [x[:, st.state].copy() for st in steps]
    for _ in range(len(steps) + 2):
        sig = evaluate(t)
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
