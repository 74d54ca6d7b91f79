"""Forward sensitivities: the derivative of the discrete solution of a run with respect to
parameters.

``r = fwdstep.sensitivities(d, ["alpha", "Ks.gain", "K[0,1]"])`` runs the diagram (the
ordinary ``fwdstep.simulate``, whose ``Result`` is returned) and integrates, alongside, the
variational equations of *the Runge-Kutta map itself*: for a step x_{n+1} = x_n + h sum b_i
k_i with stages k_i = f(t_n + c_i h, x_n + h sum_j a_ij k_j; p), the sensitivity S = dx/dp
follows

    S_i  = S_n + h sum_j a_ij K_j,       K_i = A_i S_i + B_i,      S_{n+1} = S_n + h sum b_i K_i

with A_i = df/dx and B_i = df/dp at each stage point: the exact derivative of the numbers
fwdstep computes (so it equals central differences of fwdstep runs to their own accuracy,
not just the sensitivity ODE to the solver's order).  A_i S_i + B_i is the chain rule over
the schedule with each block's Jacobian (``fwdstep.analysis.jacobian.BlockJacobian``: exact
forward-mode derivatives of the traced kernels, the linear form of linear blocks, Richardson
differences otherwise), applied to the columns of S instead of to the identity: the same
mechanism as ``fwdstep.linearize``.  A logged signal's sensitivity is its row of that chain
rule at the recorded stage.

Parameters (``resolve_parameter``):

* a top-level parameter ``alpha`` (the diagram's ``parameters:``), through every expression
  that uses it: several blocks' parameters, initial states, the initial state that
  ``ReferenceDynamics`` computes from its inputs;
* a block parameter path ``Ks.gain`` or ``ctrl.ref.alpha`` (a parameter of a block inside a
  subsystem), as ``--set`` writes it;
* one entry ``K[0,1]`` of either, or the whole array ``K`` (then the sensitivity has the
  array's shape appended).

How a parameter reaches the run-time arrays (``block.p``), the initial state and nothing
else is found by the loader itself: the diagram is evaluated again with the parameter moved
by +-h and +-h/2 (h = 1e-3 max(1, |value|)) and the Richardson derivative ``(4 D(h/2) -
D(h)) / 3`` of every ``p`` array and of the initial state is taken (exact for the affine and
polynomial expressions diagrams use, O(h^4) otherwise).  Each moved value takes the
loader's light path where it applies (``fwdstep.structure.spec.Reevaluation``: only the
parameters and top-level block entries that read it are evaluated again, by the loader's
own code, and only those blocks are built again; the moved initial states are one batch),
else the whole file is loaded again (a parameter passed into a subsystem, or read by the
simulation settings).  A parameter that changes anything else (a state size, a shape, a
sample period or a Step's time, a setting kept outside ``p``, the simulation settings) is
refused by name: its effect is not a derivative of the run-time arrays.  The derivative of
a block's outputs and state derivative with respect to its ``p`` arrays along those
directions is exact for traced blocks (columns "p.NAME" of
``BlockJacobian``); for the others (linear forms, pinocchio and complex-arithmetic blocks)
it is the Richardson central difference of the block along each direction, with the moved
blocks built once per run (a linear form is linear in its matrices: exact to round-off).

Discrete time: steps split at declared discontinuities (Step times, pulse edges, sample
instants) are differentiated as they are run (sub-steps, clamped stage times); a discrete
update x+ = update(x-, u) at an event is differentiated with the Richardson differences of
``Block.update`` in its state and inputs, the inputs' sensitivities coming from the chain
rule at the event (levels in order, as ``fwdstep.run.events.apply_updates``).  Event times
are fixed (declared, parameter-independent: a parameter that moves one is refused).

State events (zero crossings located by the run, ``fwdstep.run.crossings``) are replayed
from ``Result.events`` and differentiated as run: the sub-step of size tau to the crossing,
whose time follows from the guard that located it, g(s + tau, Phi_tau(x_s; p); p) = 0, so
dtau/dp = -(g_x (dPhi/dx S_s + dPhi/dp + dPhi/ds ds/dp) + g_p + g_t ds/dp) / (g_x dPhi/dtau
+ g_t), with the step map's tangents in its size and start time integrated as two extra
columns (a block's explicit time derivative by differences in t at fixed state and inputs,
carried by the chain rule); the state there moves by dPhi/dtau dtau/dp; the blocks'
``crossed`` (a reset x+ = R(t, x-, u)) is differentiated by Richardson differences in its
state, inputs, ``p`` and t; the rest of the step starts at the moving crossing.  The run's
tau is within ``CROSSING_TOL`` (1e-13 s) of the root, just past it: the exact root's map is
differentiated.  ``event_time_sensitivity(r, k, PARAM)`` gives d(time of r.events[k])/dp.
Not differentiated (NaN from there on, with a note in ``Result.notes``): a chattering block,
a Stop block's crossing, a guard touching zero without crossing; also discrete blocks in an
algebraic loop at an instant (fixed-point iteration), ``solve_ivp`` solvers, batches.
docs/design.md has the procedure and its measured accuracy.

Backends: with ``backend="compiled"`` (or ``simulation.backend: compiled``) the variational
equations are compiled into the stage and integrated by the compiled loop
(``fwdstep.analysis.compiled_sensitivity``: the same derivative, 1e-12 apart); diagrams it
cannot take (discrete updates, zero crossings, stages that do not trace) run here, on the
NumPy path (crossings differentiated as above), with a one-line note.
``fwdstep.simulate(d, sensitivities=[...])`` calls ``sensitivities`` (the run layer loads
this module by name).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from fwdstep.analysis.jacobian import DIFFERENCE_STEP, OFFSETS as _OFFSETS, BlockJacobian, \
    _call, moved_block, richardson as _richardson
from fwdstep.core.errors import ConfigError, DiagramError
from fwdstep.core.settings import BACKENDS
from fwdstep.core.solvers import IVP_METHODS, TABLEAUX
from fwdstep.results.result import NO_SENSITIVITIES

_ELEMENT = re.compile(r"^(?P<name>[A-Za-z_][A-Za-z0-9_./]*?)(?:\[(?P<index>[0-9,\s]+)\])?$")


# ---------------------------------------------------------------------- parameters
@dataclass
class Parameter:
    """One differentiated parameter: ``text`` as asked, ``name`` the ``--set`` key that
    moves it, ``value`` its current (whole) value, ``elements`` the flat indices
    differentiated, ``shape`` the parameter axes of its sensitivities, ``columns`` its
    columns among all parameters'."""
    text: str
    name: str
    value: np.ndarray
    elements: np.ndarray
    shape: tuple
    columns: slice = None


def resolve_parameter(d, text: str) -> Parameter:
    """'alpha', 'Ks.gain', 'sub.blk.param', 'K[0,1]' -> ``Parameter`` (see the module
    docstring); a ``ConfigError`` naming what exists otherwise."""
    m = _ELEMENT.match(str(text).strip())
    if not m:
        raise ConfigError(f"sensitivity parameter '{text}' must read NAME, BLOCK.PARAMETER or "
                          "either with an element index, e.g. K[0,1]", file=d.file)
    name = m.group("name")
    if "." in name:
        *path, key = name.split(".")
        block = "/".join(path)
        entry = next((e for e in d.spec.blocks if e.name == block), None)
        if entry is None:
            raise ConfigError(f"sensitivity parameter '{text}': there is no block '{block}'; "
                              f"blocks are: {', '.join(e.name for e in d.spec.blocks)}",
                              file=d.file)
        decl = entry.cls.params.get(key)
        if decl is None:
            raise ConfigError(f"sensitivity parameter '{text}': block '{block}' "
                              f"({entry.type_name}) has no parameter '{key}'; parameters are: "
                              f"{', '.join(entry.cls.params)}", file=d.file, line=entry.line)
        if decl.kind not in ("float", "array", "any"):
            raise ConfigError(f"sensitivity parameter '{text}' is a {decl.kind} parameter; "
                              "only numbers and arrays have derivatives", file=d.file,
                              line=entry.key_lines.get(key, entry.line))
        value = entry.params.get(key, None if decl.required else decl.default)
    else:
        if name not in d.spec.parameters:
            raise ConfigError(f"sensitivity parameter '{text}': the diagram has no parameter "
                              f"'{name}'; parameters are: {', '.join(d.spec.parameters)} (a "
                              "block's parameter is written BLOCK.PARAMETER)", file=d.file)
        value = d.spec.parameters[name]
    if value is None or isinstance(value, (str, bool, np.bool_)):
        raise ConfigError(f"sensitivity parameter '{text}' is {value!r}, not a number or an "
                          "array of numbers", file=d.file)
    value = np.asarray(value, dtype=float)
    if m.group("index") is None:
        return Parameter(str(text), name, value, np.arange(value.size), value.shape)
    where = tuple(int(v) for v in m.group("index").split(","))
    if len(where) != value.ndim or any(not 0 <= i < s for i, s in zip(where, value.shape)):
        raise ConfigError(f"sensitivity parameter '{text}': index {list(where)} is outside "
                          f"the parameter's shape {list(value.shape)}", file=d.file)
    return Parameter(str(text), name, value,
                     np.array([np.ravel_multi_index(where, value.shape)]), ())


# ---------------------------------------------------------------------- the loader's derivative
@dataclass
class LoadedDerivative:
    """How the parameters reach the run: ``p[(block, name)]`` = d block.p.name / d columns,
    (size of the array, P); ``x0`` = d initial state / d columns, (N, P)."""
    p: dict
    x0: np.ndarray


def _moved_value(par: Parameter, element: int, delta: float):
    v = par.value.copy()
    v.reshape(-1)[element] += delta
    return v.tolist()


#: parsed diagram files, by (path, mtime, size, content hash) (``fwdstep.structure.spec._read_document``)
_PARSED: dict = {}


def loader_derivative(d, params: list, P: int) -> LoadedDerivative:
    """Richardson differences of the loaded diagram (module docstring) for every column;
    each moved value is found by the loader's light path where it applies
    (``_moved_blocks``)."""
    from fwdstep.structure.compiler import structure_signature
    from fwdstep.structure.spec import Reevaluation
    dp: dict = {}
    dx0 = np.zeros((d.n_states, P))
    cache = _PARSED                   # each file parsed once for all the moved loads
    while len(cache) > 16:            # (and for the next call: tuning calls again and again)
        cache.pop(next(iter(cache)))
    base = {}

    def base_signature():
        if not base:
            base["sig"] = structure_signature(d.blocks)
        return base["sig"]

    light: dict = {}
    columns = []                      # (column, h, [(moved blocks, x0 or None)] per offset)
    for par in params:
        if par.name not in light:
            try:
                light[par.name] = Reevaluation(d.spec, [par.name], cache)
            except (DiagramError, OSError):
                light[par.name] = None        # (the whole loads say what is wrong)
        for k, element in enumerate(par.elements):
            h = DIFFERENCE_STEP * max(1.0, abs(float(par.value.reshape(-1)[element])))
            columns.append((par.columns.start + k, h, [
                _moved_blocks(d, par, _moved_value(par, element, off * h), off * h, cache,
                              base_signature, light[par.name]) for off in _OFFSETS]))
    # the initial states of the light path's moved diagrams: one batched evaluation
    pending = [(q, i) for q, (_, _, moved) in enumerate(columns)
               for i, (_, x0) in enumerate(moved) if x0 is None]
    if pending:
        X0 = _start_states(d, [columns[q][2][i][0] for q, i in pending])
        for (q, i), x0 in zip(pending, X0):
            columns[q][2][i] = (columns[q][2][i][0], x0)
    for col, h, moved in columns:
        names = set().union(*(m for m, _ in moved))
        for blk in d.blocks:
            if blk.name not in names:
                continue
            for name, arr in vars(blk.p).items():
                vals = [np.asarray(getattr(m.get(blk.name, blk).p, name), dtype=float)
                        for m, _ in moved]
                if all(np.array_equal(v, arr) for v in vals):
                    continue
                g = _richardson(vals, h).reshape(-1)
                dp.setdefault((blk.name, name), np.zeros((g.size, P)))[:, col] = g
        with np.errstate(all="ignore"):
            dx0[:, col] = _richardson([x0 for _, x0 in moved], h)
    if not dp and not dx0.any():
        names = ", ".join(p.text for p in params)
        raise ConfigError(f"sensitivity parameters {names} reach no block parameter and no "
                          "initial state (nothing in the run depends on them)", file=d.file)
    return LoadedDerivative(dp, dx0)


def _start_state(dd) -> np.ndarray:
    """x(0) of a loaded diagram's variants, (batch, N)."""
    from fwdstep.run.evaluate import initial_state
    from fwdstep.run.events import plan_events
    ev = plan_events(dd, dd.spec.simulation.step, dd.spec.simulation.n_steps)
    return initial_state(dd, event=ev.start if ev is not None else None)


def _start_states(d, variants: list) -> np.ndarray:
    """x(0) of ``d`` with each of ``variants`` (block name -> the block replacing ``d``'s,
    of the same structure), (len(variants), N): one batch
    (``fwdstep.structure.compiler.stack_blocks``, as a sweep stacks its variants), its
    initial state evaluated once."""
    import copy
    import dataclasses

    from fwdstep.structure.compiler import stack_blocks
    B = len(variants)
    stacked = stack_blocks([[v.get(blk.name, blk) for blk in d.blocks] for v in variants],
                           compared=True)     # (each rebuilt block's, by _moved_blocks)
    steps = [dataclasses.replace(st, block=blk) for st, blk in zip(d.schedule, stacked)]
    dd = copy.copy(d)
    dd.batch, dd.schedule = B, steps
    dd.stateful = [st for st in steps if st.state is not None]
    dd.x0 = np.zeros((B, d.n_states))
    for st in dd.stateful:
        dd.x0[:, st.state] = np.broadcast_to(st.block.x0, (B, st.block.n_states))
    return _start_state(dd)


def _moved_blocks(d, par, value, delta: float, cache: dict, base_signature,
                  light=None) -> tuple:
    """The diagram with parameter ``par`` set to ``value``: (block name -> its block, for
    the blocks that may differ from ``d``'s; the initial state, None from the light path:
    the caller evaluates those together, ``_start_states``).  The loader's light path
    (``light``, a ``fwdstep.structure.spec.Reevaluation``: the parameters and block
    entries that read the moved value, evaluated again by the loader's code; those blocks
    built anew,
    the rest of ``d`` shared) where it applies and the rebuilt blocks keep their
    structure; else the whole file loaded again (which says what the parameter changes
    beyond the run-time arrays)."""
    from fwdstep.structure.compiler import _block_signature, compile_spec, \
        structure_signature
    from fwdstep.structure.graph import _instantiate_one
    from fwdstep.structure.spec import load_spec
    try:
        entries = light.entries({par.name: value}) if light is not None and light.applies \
            else None
        rebuilt = {} if entries is None else {
            name: _instantiate_one(e) for name, e in entries.items()}
        by_name = {blk.name: blk for blk in d.blocks}
        if entries is not None and all(
                name in by_name and _block_signature(b) == _block_signature(by_name[name])
                for name, b in rebuilt.items()):
            return rebuilt, None      # (its initial state: _start_states, batched)
        overrides = dict(d.spec.overrides)
        overrides[par.name] = value
        dd = compile_spec(load_spec(d.spec.file, overrides, cache))
    except DiagramError as exc:
        raise ConfigError(f"sensitivity parameter '{par.text}' cannot be moved by "
                          f"{delta:.3g}: {exc}", file=d.file) from None
    _same_structure(d, dd, par, base_signature(), structure_signature)
    return {blk.name: blk for blk in dd.blocks}, _start_state(dd)[0]


def _same_structure(d, dd, par, base_signature, signature) -> None:
    if dd.spec.simulation != d.spec.simulation:
        raise ConfigError(f"sensitivity parameter '{par.text}' changes the simulation "
                          "settings (step, t_final, ...): the run has no derivative with "
                          "respect to it", file=d.file)
    moved = signature(dd.blocks)
    if moved == base_signature:
        return
    for blk, a, b in zip(d.blocks, base_signature, moved):
        if a != b:
            raise ConfigError(f"sensitivity parameter '{par.text}' changes block '{blk.name}' "
                              "beyond its run-time parameters (a size, a shape, an event time "
                              "or a setting kept outside p): not differentiable", file=d.file)
    raise ConfigError(f"sensitivity parameter '{par.text}' changes the diagram's blocks",
                      file=d.file)


# ---------------------------------------------------------------------- the chain rule
class _BlockTerm:
    """One block of the schedule: its Jacobian and how its parameters move."""

    def __init__(self, step, dp: dict, P: int):
        blk = step.block
        self.step = step
        names = _read_by_rows(blk, [name for (bname, name) in dp if bname == blk.name])
        self.jac = BlockJacobian(blk)
        self.Bp = None            # exact p columns: (size of those columns, P)
        self.probes = None        # moved copies of the block: [column][offset]
        self.dJ = None            # linear forms: d J / d column, (P, rows, x and u columns)
        if names:
            with_p = BlockJacobian(blk, names)
            if with_p.method.startswith("traced"):
                self.jac = with_p
                self.pcols = slice(with_p.columns[f"p.{names[0]}"].start, with_p.n_columns)
                self.Bp = np.vstack([dp[(blk.name, n)] for n in names])
            else:
                self.probes, self.steps = _probes(blk, {n: dp[(blk.name, n)] for n in names},
                                                  P)
                if self.jac.method == "linear form":
                    self.dJ = self._linear_derivative(P)
        j = self.jac
        self.x = j.columns["x"]
        out_rows = np.zeros(j.n_rows, dtype=bool)
        for port in blk.outputs:
            out_rows[j.rows[f"y.{port}"]] = True
        self.u_out, self.u_all = [], []
        for name, src in zip(blk.inputs, step.inputs):
            cols = j.columns[f"u.{name}"]
            self.u_all.append((cols, src))
            if j.mask[out_rows][:, cols].any():
                self.u_out.append((cols, src))
        self.n_out = int(out_rows.sum())
        self.outputs = [(j.rows[f"y.{port}"], idx) for port, idx in zip(blk.outputs,
                                                                        step.outputs)]
        self.dx = j.rows["dx"]
        self.n_rows = j.n_rows
        traced = getattr(j, "_traced", None) if j.method == "traced" else None
        self.fixed = None          # a Jacobian that reads no t, x or u: computed once
        if j.method == "linear form" or (traced is not None and traced.constant):
            self.fixed = j

    def _linear_derivative(self, P: int) -> np.ndarray:
        """A linear form is linear in its matrices: the derivative of its Jacobian along
        each column, once (Richardson over the moved blocks' forms; exact to round-off)."""
        n_xu = self.jac.n_columns
        dJ = np.zeros((P, self.jac.n_rows, n_xu))
        for c, (moved, h) in enumerate(zip(self.probes, self.steps)):
            if moved is not None:
                dJ[c] = _richardson([BlockJacobian(b)._linear(1)[0] for b in moved], h)
        return dJ

    def jacobian(self, t, x, u) -> np.ndarray:
        if self.fixed is not None:
            if not isinstance(self.fixed, np.ndarray):
                self.fixed = self.fixed.at(t, x, u).J[0]
            return self.fixed
        return self.jac.at(t, x, u).J[0]

    def parameter_rows(self, t, x, u, P) -> np.ndarray:
        """d (outputs, derivative) / d columns through this block's p: (rows, P)."""
        if self.dJ is not None:
            v = np.concatenate([x.reshape(-1)] + [np.reshape(a, -1) for a in u])
            return np.einsum("prc,c->rp", self.dJ, v)
        out = np.zeros((self.n_rows, P))
        if self.probes is None:
            return out
        for c, (moved, h) in enumerate(zip(self.probes, self.steps)):
            if moved is None:
                continue
            with np.errstate(all="ignore"):
                f = [_call(b, t, x, u, 1)[0] for b in moved]
            out[:, c] = _richardson(f, h)
        return out


def _read_by_rows(blk, names: list) -> list:
    """Of the moved p arrays ``names``, those the block's outputs and derivative can read:
    all of them, unless both are its declared kernels (``set_kernels``), which read their
    ``params`` alone (a Saturation's ``interval`` feeds its guards only: left in, it would
    keep the block from being traced, and differences in its limits straddle the kink)."""
    from fwdstep.core.block import Block
    k = getattr(blk, "kernels", None)
    if k is None or type(blk).output is not Block.output or \
            type(blk).derivative is not Block.derivative:
        return names
    return [n for n in names if n in k.params]


def _probes(blk, dp: dict, P: int):
    """For each column c: the block with its p arrays moved by off * h_c * dp[:, c] (the
    offsets of the Richardson difference), and h_c; None where nothing moves."""
    probes, steps = [], []
    for c in range(P):
        scale = max([np.max(np.abs(g[:, c])) for g in dp.values()] + [0.0])
        if scale == 0:
            probes.append(None)
            steps.append(1.0)
            continue
        size = max([np.max(np.abs(getattr(blk.p, n))) for n in dp] + [1.0])
        h = DIFFERENCE_STEP * size / scale
        probes.append([moved_block(blk, dp, c, off * h) for off in _OFFSETS])
        steps.append(h)
    return probes, steps


class SensitivityChain:
    """The variational right-hand side of a compiled diagram: ``stage(t, x, S, sig)`` gives
    every signal's sensitivity (signal -> (size, P)) and K = A S + B, (N, P)."""

    def __init__(self, d, dp: dict, P: int):
        self.d, self.P, self.dp = d, P, dp
        self.terms = [_BlockTerm(step, dp, P) for step in d.schedule]
        self.constant = {idx: np.zeros((int(np.prod(d.signal_shapes[idx], dtype=np.int64)),
                                        P)) for idx in d.constant_signals}

    def outputs(self, t, x, S, sig, time=None) -> tuple:
        """(signal sensitivities, [(block, its rows so far, J)]) at (t, x): the outputs'
        rows complete, the state derivative rows without the inputs' terms.  S may have
        more columns than the P parameters': those are directions of the state alone (no
        parameter term; a crossing's tangents).  ``time``: (seed, lo, hi): column c also
        moves t by seed[c] (each block's explicit time derivative at fixed state and
        inputs, ``_time_derivative`` within [lo, hi], carried by the chain rule: a kink
        of a block in its inputs is never straddled)."""
        P = self.P
        m = S.shape[1]
        G = dict(self.constant) if m == P else \
            {idx: np.zeros((g.shape[0], m)) for idx, g in self.constant.items()}
        kept = []
        for term in self.terms:
            step = term.step
            sl = step.state
            u = tuple(sig[i] for i in step.inputs)
            xs = x[None, sl] if sl is not None else np.zeros((1, 0))
            J = term.jacobian(t, xs, u)
            if term.Bp is not None:
                D = J[:, term.pcols] @ term.Bp
            elif term.probes is not None:
                D = term.parameter_rows(t, xs, u, P)
            else:
                D = np.zeros((term.n_rows, P))
            if m != P:
                D = np.concatenate((D, np.zeros((term.n_rows, m - P))), axis=1)
            if time is not None and term.n_rows:
                blk = step.block
                D += np.outer(_time_derivative(lambda tt: _call(blk, tt, xs, u, 1)[0], t,
                                               time[1], time[2]), time[0])
            if sl is not None:
                D += J[:, term.x] @ S[sl]
            if term.n_out:
                for cols, src in term.u_out:
                    g = G.get(src)
                    if g is None:
                        raise ConfigError(f"block '{step.block.name}' reads "
                                          f"'{self.d.signal_names[src]}' before it is computed "
                                          "(feedthrough declaration and kernel disagree)",
                                          file=self.d.file)
                    D[:term.n_out] += J[:term.n_out, cols] @ g
                for rows, idx in term.outputs:
                    G[idx] = D[rows]
            if sl is not None:
                kept.append((term, D, J))
        return G, kept

    def stage(self, t, x, S, sig, time=None) -> tuple:
        G, kept = self.outputs(t, x, S, sig, time)
        K = np.zeros((self.d.n_states, S.shape[1]))
        for term, D, J in kept:           # after every output, as in a stage
            dx = term.dx
            k = D[dx]
            for cols, src in term.u_all:
                k = k + J[dx, cols] @ G[src]
            K[term.step.state] = k
        return G, K


def _update_jacobian(step, t, x, u) -> tuple:
    """Richardson differences of ``block.update`` in its state and each input:
    (d x+/d x, [d x+/d u_j])."""
    blk = step.block
    return _difference_jacobian(lambda xs, us: blk.update(t, xs, us), x, u, blk.n_states)


def _difference_jacobian(fn, x, u, n: int) -> tuple:
    """Richardson differences of ``fn(x, u) -> (1, n)`` (a block's update, guards or
    crossed) in its state x (1, n_x) and each input: (d fn/d x, [d fn/d u_j])."""
    shapes = [np.shape(a)[1:] for a in u]
    n_x = x.shape[1]
    base = np.concatenate([x.reshape(-1)] + [np.asarray(a, float).reshape(-1) for a in u])
    C = base.size
    out = np.zeros((n, C))
    for c in range(C):
        h = DIFFERENCE_STEP * max(1.0, abs(base[c]))
        f = []
        for off in _OFFSETS:
            v = base.copy()
            v[c] += off * h
            xs, us, k = v[:n_x].reshape(1, n_x), [], n_x
            for s in shapes:
                size = int(np.prod(s, dtype=np.int64))
                us.append(v[k:k + size].reshape((1,) + s))
                k += size
            with np.errstate(all="ignore"):
                f.append(np.broadcast_to(np.asarray(fn(xs, tuple(us)), dtype=float),
                                         (1, n))[0])
        out[:, c] = _richardson(f, h)
    parts, k = [], n_x
    for s in shapes:
        size = int(np.prod(s, dtype=np.int64))
        parts.append(out[:, k:k + size])
        k += size
    return out[:, :n_x], parts


# ---------------------------------------------------------------------- state events
#: the step of the central differences in time (at fixed state) of a stage's right-hand
#: side, a guard or a reset, times max(1, |t|)
TIME_STEP = 1e-6


def _time_derivative(fn, t: float, lo: float, hi: float) -> np.ndarray:
    """d fn(t)/dt: Richardson central differences of step ``TIME_STEP``, or second-order
    one-sided ones into [lo, hi] where t is closer than that to a declared discontinuity
    (no difference straddles one)."""
    h = TIME_STEP * max(1.0, abs(t))
    with np.errstate(all="ignore"):
        if t - h >= lo and t + h <= hi:
            return _richardson([np.asarray(fn(t + off * h), dtype=float)
                                for off in _OFFSETS], h)
        up = hi - t >= t - lo
        h = min(h, 0.5 * ((hi - t) if up else (t - lo)))
        if not h > 0:
            return 0.0 * np.asarray(fn(t), dtype=float)
        sign = 1.0 if up else -1.0
        f0, f1, f2 = (np.asarray(fn(t + sign * k * h), dtype=float) for k in (0, 1, 2))
        return sign * (-3.0 * f0 + 4.0 * f1 - f2) / (2.0 * h)


class _NotDifferentiated(Exception):
    """A state event whose motion is not differentiated (chattering, a Stop, a crossing
    the replay does not meet): the sensitivities are NaN from ``time`` on."""

    def __init__(self, time: float, reason: str):
        super().__init__(reason)
        self.time, self.reason = time, reason


class _StateEvents:
    """The run's located crossings (``Result.events``, variant 0) replayed on the
    sensitivities' own steps and differentiated (module docstring): the crossing blocks,
    the event times in order, d(event time)/d columns (``dtime``)."""

    def __init__(self, d, events, dp: dict, P: int, outputs, sig):
        from fwdstep.run.crossings import crossing_steps
        self.d, self.dp, self.P = d, dp, P
        self.outputs, self.sig = outputs, sig
        self.steps = crossing_steps(d)
        self.index = {st.block.name: k for k, st in enumerate(self.steps)}
        self.events = [e for e in events if e.variant == 0]
        self.times = sorted({e.time for e in self.events})
        self.k = 0
        self.dtime = np.full((len(self.events), P), np.nan)
        self.probes = {}

    def next_time(self) -> float:
        return self.times[self.k] if self.k < len(self.times) else math.inf

    def _which(self, te: float) -> dict:
        """The events at te -> {crossing step index: (1, n_crossings) bool} (the guards
        the run acted on), ``_NotDifferentiated`` for what is not differentiated; the next
        event time becomes the current one."""
        which, _ = self.acted(te)
        self.k += 1
        return which

    def acted(self, te: float) -> tuple:
        """({crossing step index: (1, n_crossings) bool}, {the same: (1, n_crossings) bool,
        True where the guard rose}) for the run's events at te."""
        which, rising = {}, {}
        for e in self.events:
            if e.time != te:
                continue
            k = self.index.get(e.block)
            blk = self.steps[k].block if k is not None else None
            if blk is None or e.kind == "chattering":
                raise _NotDifferentiated(te, f"block '{e.block}' chatters there (its "
                                             "crossings are no longer located)")
            if blk.stops_run:
                raise _NotDifferentiated(te, f"block '{e.block}' ({blk.type_name}) stops the "
                                             "run there at a crossing")
            label = e.kind.rsplit(" ", 1)[0]
            name, _, elem = label.partition("[")
            col = (blk.crossing_names.index(name) * blk.crossing_size
                   + (int(elem.rstrip("]")) if elem else 0))
            which.setdefault(k, np.zeros((1, blk.n_crossings), dtype=bool))[0, col] = True
            rising.setdefault(k, np.zeros((1, blk.n_crossings), dtype=bool))[0, col] = \
                e.kind.endswith("rising")
        return which, rising

    def past(self, te: float, hi: float, x) -> bool:
        """Whether every guard the run acted on at te has its new sign at (min(te, hi), x)
        (the run's state just past the root: ``crossed`` reads those signs)."""
        which, rising = self.acted(te)
        ts = min(te, hi)
        self.outputs(ts, x)
        for k, w in which.items():
            st = self.steps[k]
            xs, u = self._local(st, x)
            g = np.asarray(st.block.zero_crossings(ts, xs, u), dtype=float).reshape(1, -1)
            if ((g >= 0) != rising[k])[w].any():
                return False
        return True

    def _parameter(self, blk, fn, n: int) -> np.ndarray:
        """d fn(block) / d columns through the block's p arrays, (n, P) (Richardson over
        moved copies of the block, as for the blocks' right-hand sides)."""
        got = self.probes.get(blk.name)
        if got is None:
            names = {nm: g for (bn, nm), g in self.dp.items() if bn == blk.name}
            got = self.probes[blk.name] = _probes(blk, names, self.P) if names else ()
        out = np.zeros((n, self.P))
        for c, (moved, h) in enumerate(zip(*got) if got else ()):
            if moved is not None:
                with np.errstate(all="ignore"):
                    out[:, c] = _richardson([np.asarray(fn(b), dtype=float).reshape(-1)
                                             for b in moved], h)
        return out

    def _local(self, st, x):
        xs = x[:, st.state] if st.state is not None else x[:, 0:0]
        return xs, tuple(self.sig[i] for i in st.inputs)

    def act(self, which: dict, ts, dts, x, S, G, te_p, lo, hi) -> np.ndarray:
        """The blocks' ``crossed`` at ts (just past the crossing: signals and G, their
        sensitivities, at (ts, x)), x changed in place; returns the sensitivity after:
        x+ = R(t, x-, u) differentiated in x-, u (their sensitivities), p and t (te_p the
        event time's, dts = d ts / d te)."""
        S = S.copy()
        news = []
        for k, w in which.items():
            st = self.steps[k]
            if st.state is None:
                continue
            blk = st.block
            xs, u = self._local(st, x)
            new = blk.crossed(ts, xs, u, w)
            if new is None:
                continue
            n = blk.n_states

            def reset(xx, uu, b=blk, t=ts, w=w):
                got = b.crossed(t, xx, uu, w)
                return xx if got is None else got
            Rx, Ru = _difference_jacobian(reset, xs, u, n)
            dnew = Rx @ S[st.state] + self._parameter(blk, lambda b: reset(xs, u, b), n)
            for part, src in zip(Ru, st.inputs):
                dnew = dnew + part @ G[src]
            if dts:                      # its own explicit time (G holds the inputs')
                Rt = _time_derivative(lambda t: reset(xs, u, t=t).reshape(-1), ts, lo, hi)
                dnew = dnew + np.outer(Rt, dts * te_p)
            news.append((st, np.broadcast_to(new, (1, n)), dnew))
        for st, new, dnew in news:
            x[:, st.state] = new
            S[st.state] = dnew
        return S

    def crossing(self, te, lo, hi, x, S_m, V, s_p, chain):
        """Just past the located crossing at te, x = x- the sub-step of size tau from s
        (its sensitivity with tau fixed ``S_m``, d x-/d tau ``V``, d s/d columns ``s_p``):
        tau's derivative from the guard that located it, g(s + tau, x-(tau)) = 0, then the
        blocks' resets.  Returns (S after the crossing, d te / d columns); x is x+."""
        which = self._which(te)
        P = self.P
        ts = min(te, hi)
        dts = 1.0 if te < hi else 0.0
        self.outputs(ts, x)
        # columns: the parameters (tau fixed), d/d tau, d/d t at fixed x (the signals'
        # explicit time dependence, through the chain rule)
        cols = np.concatenate((S_m, V[:, None], np.zeros((len(V), 1))), axis=1)
        seed = np.zeros(P + 2)
        seed[P + 1] = dts
        Gs, _ = chain.outputs(ts, x[0], cols, self.sig, (seed, lo, hi))
        best = None
        for k, w in which.items():
            st = self.steps[k]
            blk = st.block
            xs, u = self._local(st, x)
            n = blk.n_crossings
            g = np.asarray(blk.zero_crossings(ts, xs, u), dtype=float).reshape(-1)
            Jx, Ju = _difference_jacobian(lambda xx, uu: blk.zero_crossings(ts, xx, uu),
                                          xs, u, n)
            rows = Jx @ cols[st.state] if st.state is not None else np.zeros((n, P + 2))
            for part, src in zip(Ju, st.inputs):
                rows = rows + part @ Gs[src]
            gp = self._parameter(blk, lambda b: b.zero_crossings(ts, xs, u), n)
            gt = rows[:, P + 1] + dts * _time_derivative(
                lambda t: np.asarray(blk.zero_crossings(t, xs, u), dtype=float).reshape(-1),
                ts, lo, hi)
            num = rows[:, :P] + gp + np.outer(gt, s_p)
            den = rows[:, P] + gt
            for j in np.flatnonzero(w[0]):
                back = g[j] / den[j] if den[j] != 0 else -math.inf
                if best is None or back > best[0]:    # the earliest root of those acted on
                    best = (back, num[j], den[j], blk.name)
        if best is None or not (np.isfinite(best[2]) and best[2] != 0):
            raise _NotDifferentiated(te, f"block '{best[3] if best else '?'}': its guard "
                                         "touches zero without crossing (tangent), so the "
                                         "crossing time has no derivative")
        tau_p = -best[1] / best[2]
        te_p = s_p + tau_p
        S = S_m + np.outer(V, tau_p)
        G = {idx: g[:, :P] + np.outer(g[:, P], tau_p) + np.outer(g[:, P + 1], te_p)
             for idx, g in Gs.items()}
        for e_i, e in enumerate(self.events):
            if e.time == te:
                self.dtime[e_i] = te_p
        return self.act(which, ts, dts, x, S, G, te_p, lo, hi), te_p

    def jump(self, ts, lo, hi, x, S, chain):
        """Guards that jumped at a declared time ts (a Step, a discrete update): the resets
        at a time that does not move (nothing located)."""
        which = self._which(ts)
        self.outputs(ts, x)
        G, _ = chain.outputs(ts, x[0], S, self.sig)
        for e_i, e in enumerate(self.events):
            if e.time == ts:
                self.dtime[e_i] = 0.0
        return self.act(which, ts, 0.0, x, S, G, np.zeros(self.P), lo, hi)


# ---------------------------------------------------------------------- the run
def _integrate(d, chain: SensitivityChain, S0: np.ndarray, rows: int, events=()) -> tuple:
    """The run's steps with the sensitivities alongside (fwdstep.run.simulate's procedure:
    the same stages, event sub-steps, updates, record times and the run's located
    crossings, ``events``); returns (signal -> (rows, size, P) for every logged signal,
    d event time / d columns (len(events), P), the time from which nothing is computed and
    why, or None)."""
    from fwdstep.run.evaluate import _make_evaluator, initial_state
    from fwdstep.run.events import plan_events
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    h, n_steps, every = cfg.step, cfg.n_steps, cfg.log_every
    events_plan = plan_events(d, h, n_steps)
    special = events_plan.steps if events_plan is not None else {}
    f, outputs, sig = _make_evaluator(d)
    N, P = d.n_states, chain.P
    x = np.array(initial_state(d, event=events_plan.start if events_plan is not None
                               else None), dtype=float)
    S = S0.copy()
    logged = [(name, d.signal_index[name]) for name in d.logged]
    out = {name: np.full((rows, int(np.prod(d.signal_shapes[idx], dtype=np.int64)), P), np.nan)
           for name, idx in logged}
    row = 0
    located = _StateEvents(d, events, chain.dp, P, outputs, sig) if events else None

    def record(G):
        nonlocal row
        if row < rows:
            for name, idx in logged:
                out[name][row] = G[idx][:, :P]
        row += 1

    def event(ev, t):
        nonlocal S
        if ev.levels is None:
            raise ConfigError("sensitivities through discrete blocks in a loop at one instant "
                              "(fixed-point updates) are not computed", file=d.file)
        for level in ev.levels:
            with np.errstate(all="ignore"):
                outputs(t, x)
            G, _ = chain.outputs(t, x[0], S, sig)
            new, dnew = [], []
            for st in level:
                u = tuple(sig[i] for i in st.inputs)
                xs = x[:, st.state]
                Jx, Ju = _update_jacobian(st, t, xs, u)
                g = Jx @ S[st.state]
                for part, src in zip(Ju, st.inputs):
                    g = g + part @ G[src]
                new.append(st.block.update(t, xs, u))
                dnew.append(g)
            for st, v, g in zip(level, new, dnew):
                x[:, st.state] = v
                S[st.state] = g

    def step(a, hh, lo, hi, recorded, tangents=False):
        """One (sub-)step of size hh from (a, x); with ``tangents`` also the derivatives
        of its end with respect to its start time a and its size hh (at fixed x_a),
        returned as (N, 2): the stages' times move with them (unless clamped), so the
        blocks' explicit time derivatives enter (``SensitivityChain.outputs``' time)."""
        nonlocal S
        ks, Ks = [], []
        Sx = np.concatenate((S, np.zeros((N, 2))), axis=1) if tangents else S
        for i in range(tab.stages):
            raw = a + tab.c[i] * hh
            if i == 0:
                xi, Si, ti = x, Sx, max(a, lo)
            else:
                xi, Si = x.copy(), Sx.copy()
                for j, aij in enumerate(tab.a[i]):
                    if aij != 0.0:
                        xi += (hh * aij) * ks[j]
                        Si += (hh * aij) * Ks[j]
                        if tangents:
                            Si[:, P + 1] += aij * ks[j][0]
                ti = min(max(raw, lo), hi)
            dx = np.empty((1, N))
            with np.errstate(all="ignore"):
                f(ti, xi, dx)
            time = None
            if tangents and lo <= raw <= hi:      # (a clamped stage time does not move)
                seed = np.zeros(P + 2)
                seed[P], seed[P + 1] = 1.0, tab.c[i]
                time = (seed, lo, hi)
            G, K = chain.stage(ti, xi[0], Si, sig, time)
            if i == 0 and recorded:
                record(G)
            ks.append(dx)
            Ks.append(K)
        for j, bj in enumerate(tab.b):
            if bj != 0.0:
                x[...] += (hh * bj) * ks[j]
                Sx = Sx + (hh * bj) * Ks[j]
                if tangents:
                    Sx[:, P + 1] += bj * ks[j][0]
        S = Sx[:, :P]
        return Sx[:, P:] if tangents else None

    def unit(a, b, lo, hi, recorded):
        """A (sub-)step [a, b] in which the run located crossings (or at whose start
        guards jumped): sub-steps to each crossing, differentiated (module docstring)."""
        nonlocal S
        if located.next_time() == max(a, lo):
            S = located.jump(max(a, lo), lo, hi, x, S, chain)
        s, s_p = a, np.zeros(P)
        while True:
            te = located.next_time()
            if te <= s:
                raise _NotDifferentiated(te, "the sensitivities' replay of the run does not "
                                             "meet its crossing there")
            if te <= b:
                # the step to the run's crossing time; the run's own tau (te = s + tau
                # rounded) may be an ulp longer: a guard that is not yet past its root
                # here (a few 1e-16) is taken a few ulps further, as the run found it
                x_s, S_s, tau = x.copy(), S.copy(), te - s
                for more in range(12):
                    V = step(s, tau, lo, hi, recorded, tangents=True)
                    recorded = False
                    if located.past(te, hi, x):
                        break
                    x[...], S = x_s, S_s.copy()
                    tau += 2.0 ** more * math.ulp(te)
                else:
                    raise _NotDifferentiated(te, "the sensitivities' replay of the run does "
                                                 "not meet its crossing there")
                S_m = S + np.outer(V[:, 0], s_p)
                S, s_p = located.crossing(te, lo, hi, x, S_m, V[:, 1], s_p, chain)
                s = te
                recorded = False
                if not s < b:            # the rest has size 0 (the crossing at b): its
                    V = step(s, 0.0, lo, hi, False, tangents=True)   # tangents all the same
                    S = S + np.outer(V[:, 0] - V[:, 1], s_p)
                    return
            else:
                moving = bool(s_p.any())
                V = step(s, b - s, lo, hi, recorded, tangents=moving)
                if moving:               # starts at s (moving), ends at b (fixed)
                    S = S + np.outer(V[:, 0] - V[:, 1], s_p)
                return

    stopped = None
    with np.errstate(all="ignore"):   # S may overflow where x does not: a note says so
        try:
            for n in range(n_steps):
                t = n * h
                if not np.all(np.isfinite(x)):
                    break
                units = ([(sub.a, sub.b, sub.lo, sub.hi, sub.event) for sub in special[n]]
                         if n in special else [(t, (n + 1) * h, -math.inf, math.inf, None)])
                for i, (a, b, lo, hi, ev) in enumerate(units):
                    if ev is not None:
                        event(ev, max(a, lo))
                    rec = i == 0 and n % every == 0
                    if located is not None and located.next_time() <= b:
                        unit(a, b, lo, hi, rec)
                    else:
                        step(a, b - a, lo, hi, rec)
            else:
                t = n_steps * h
                end = events_plan.final if events_plan is not None else None
                ts = t
                if end is not None:
                    ts = max(t, end.hi)
                    if end.updates:
                        event(end, ts)
                if located is not None and located.next_time() <= ts:
                    raise _NotDifferentiated(located.next_time(), "the sensitivities' replay "
                                             "of the run does not meet its crossing there")
                outputs(ts, x)
                G, _ = chain.outputs(ts, x[0], S, sig)
                record(G)
        except _NotDifferentiated as exc:
            stopped = (exc.time, exc.reason)
    dtime = located.dtime if located is not None else np.zeros((0, P))
    return out, dtime, stopped


def sensitivities(d, params, *, result=None, x0_sensitivity=None, backend=None,
                  progress=None, on_compile=None, max_log_bytes=None):
    """Run ``d`` and its forward sensitivities with respect to ``params`` (names as in the
    module docstring); ``fwdstep.simulate(d, sensitivities=params)`` is the same call.
    Returns that ``Result`` with ``r.sensitivity(SIGNAL, PARAM)`` (the shape of
    ``r[SIGNAL]`` followed by the parameter's shape), ``r.sensitivity_matrix(SIGNAL)``
    ((T, size, P)) and ``r.metric_gradient(METRIC)``.  ``backend`` (default
    ``simulation.backend``): "compiled" integrates the variational equations in the
    compiled stage (``fwdstep.analysis.compiled_sensitivity``; a diagram it cannot take runs
    on the NumPy path, with a one-line note in ``r.notes``), "numpy" block by block here.
    ``result``: a Result of this very diagram already run (skips the run; NumPy path)."""
    from fwdstep.run.simulate import simulate
    if d.batch != 1:
        raise ConfigError("sensitivities take a single diagram, not a batch", file=d.file)
    cfg = d.spec.simulation
    if cfg.solver in IVP_METHODS:
        raise ConfigError(f"sensitivities need a fixed-step solver (the Runge-Kutta map is "
                          f"differentiated); '{cfg.solver}' is scipy's solve_ivp", file=d.file)
    if isinstance(params, str):
        params = [params]
    resolved, P = [], 0
    for text in params:
        par = resolve_parameter(d, text)
        if any(p.text == par.text for p in resolved):
            raise ConfigError(f"sensitivity parameter '{text}' is asked twice", file=d.file)
        par.columns = slice(P, P + len(par.elements))
        P += len(par.elements)
        resolved.append(par)
    loaded = loader_derivative(d, resolved, P)
    S0 = loaded.x0 if x0_sensitivity is None else x0_sensitivity
    parameters = [(p.text, p.columns.start, p.columns.stop, p.shape) for p in resolved]
    if backend is not None and backend not in BACKENDS:
        raise ConfigError(f"unknown backend '{backend}'; backends are: {', '.join(BACKENDS)}",
                          file=d.file)
    if result is None and (backend or cfg.backend) == "compiled":
        from fwdstep.analysis.compiled_sensitivity import run_compiled
        got = run_compiled(d, loaded.p, P, S0, progress, on_compile, max_log_bytes)
        if not isinstance(got, str):
            return _attach(*got, parameters)
        note = f"sensitivities computed on the numpy path: {got}"
    else:
        note = None
    r = simulate(d, backend="numpy", progress=progress, max_log_bytes=max_log_bytes) \
        if result is None else result
    if note is not None:
        r.notes.append(note)
    rows = len(r.t)
    chain = SensitivityChain(d, loaded.p, P)
    signals, dtime, stopped = _integrate(d, chain, S0, cfg.n_steps // cfg.log_every + 2,
                                         r.events)
    return _attach(r, {name: arr[:rows] for name, arr in signals.items()}, parameters,
                   dtime, stopped)


def _attach(r, signals: dict, parameters: list, dtime=None, stopped=None):
    """The sensitivities onto the Result (``r.sensitivity_data``: "signals", "parameters"
    and "events", d event time / d columns per ``r.events`` entry), with a note where they
    are not finite (the variational equations diverged: x is checked against the bound, S
    is not) and one where a state event is not differentiated (``stopped``: (time,
    reason); NaN from there on)."""
    if dtime is None:
        dtime = np.zeros((len(r.events), parameters[-1][2] if parameters else 0))
    r.sensitivity_data = {"signals": signals, "parameters": parameters, "events": dtime}
    late = None
    if stopped is not None:
        late = r.t >= stopped[0]
        for arr in signals.values():
            arr[late] = np.nan
        r.notes.append(f"sensitivities from t = {stopped[0]:.6g} s on are not computed (NaN): "
                       f"{stopped[1]}")
    bad = [np.flatnonzero(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))
           for arr in signals.values()]
    first = min((int(b[0]) for b in bad if b.size), default=None)
    if first is not None and (late is None or not late[first]):
        r.notes.append(f"sensitivities are not finite from t = {r.t[first]:.6g} s on")
    return r


def event_time_sensitivity(r, index: int, param: str) -> np.ndarray:
    """d (the time of ``r.events[index]``) / d ``param`` (the parameter's shape): a located
    crossing's time moves with the parameters (a guard's root); declared times do not (0);
    NaN where the crossing is not differentiated (a note says why)."""
    if r.sensitivity_data is None:
        raise KeyError(NO_SENSITIVITIES)
    count = len(r.sensitivity_data["events"])
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) \
            or not 0 <= index < count:
        # (a bare IndexError, and -1 silently the last event, before)
        raise IndexError(f"event {index!r}: the run located {count} event(s), numbered "
                         f"0 to {count - 1} (r.events)" if count else
                         f"event {index!r}: the run has no events (r.events is empty)")
    for text, a, b, shape in r.sensitivity_data["parameters"]:
        if text == param:
            return np.asarray(r.sensitivity_data["events"][index, a:b]).reshape(shape)
    raise KeyError(f"no sensitivity with respect to '{param}'; parameters: "
                   f"{', '.join(r.sensitivity_parameters)}")


__all__ = ["sensitivities", "event_time_sensitivity", "resolve_parameter", "Parameter",
           "SensitivityChain", "loader_derivative", "LoadedDerivative"]
