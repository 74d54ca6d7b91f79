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
else is found by the loader itself: the diagram is loaded again with the parameter moved by
+-h and +-h/2 (h = 1e-3 max(1, |value|)) and the Richardson derivative ``(4 D(h/2) - D(h))
/ 3`` of every ``p`` array and of the initial state is taken (exact for the affine and
polynomial expressions diagrams use, O(h^4) otherwise).  A parameter that changes anything
else (a state size, a shape, a sample period or a Step's time, a setting kept outside
``p``, the simulation settings) is refused by name: its effect is not a derivative of the
run-time arrays.  The derivative of a block's outputs and state derivative with respect to
its ``p`` arrays along those directions is exact for traced blocks (columns "p.NAME" of
``BlockJacobian``); for the others (linear forms, pinocchio and complex-arithmetic blocks)
it is the Richardson central difference of the block along each direction, with the moved
blocks built once per run (a linear form is linear in its matrices: exact to round-off).

Discrete time: steps split at declared discontinuities (Step times, pulse edges, sample
instants) are differentiated as they are run (sub-steps, clamped stage times); a discrete
update x+ = update(x-, u) at an event is differentiated with the Richardson differences of
``Block.update`` in its state and inputs, the inputs' sensitivities coming from the chain
rule at the event (levels in order, as ``fwdstep.run.events.apply_updates``).  Event times
are fixed (declared, parameter-independent: a parameter that moves one is refused).  Not
handled: state events (crossing times that depend on the state: the sensitivities from the
first located crossing on are NaN, with a note in ``Result.notes``), discrete blocks in an
algebraic loop at an instant (fixed-point iteration), ``solve_ivp`` solvers, batches.

Backends: with ``backend="compiled"`` (or ``simulation.backend: compiled``) the variational
equations are compiled into the stage and integrated by the compiled loop
(``fwdstep.analysis.compiled_sensitivity``: the same derivative, 1e-12 apart); diagrams it
cannot take (discrete updates, zero crossings, stages that do not trace) run here, on the
NumPy path, with a one-line note.  ``fwdstep.simulate(d, sensitivities=[...])`` calls
``sensitivities`` (the run layer loads this module by name).
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


#: parsed diagram files, by (path, mtime, size) (``fwdstep.structure.spec._read_document``)
_PARSED: dict = {}


def loader_derivative(d, params: list, P: int) -> LoadedDerivative:
    """Richardson differences of the loaded diagram (module docstring) for every column."""
    from fwdstep.run.evaluate import initial_state
    from fwdstep.run.events import plan_events
    from fwdstep.structure.compiler import compile_spec, structure_signature
    from fwdstep.structure.spec import load_spec
    base_signature = structure_signature(d.blocks)
    dp: dict = {}
    dx0 = np.zeros((d.n_states, P))
    cache = _PARSED                   # each file parsed once for all the moved loads
    while len(cache) > 16:            # (and for the next call: tuning calls again and again)
        cache.pop(next(iter(cache)))

    def start_state(dd):
        ev = plan_events(dd, dd.spec.simulation.step, dd.spec.simulation.n_steps)
        return initial_state(dd, event=ev.start if ev is not None else None)[0]

    for par in params:
        for k, element in enumerate(par.elements):
            col = par.columns.start + k
            h = DIFFERENCE_STEP * max(1.0, abs(float(par.value.reshape(-1)[element])))
            moved = []
            for off in _OFFSETS:
                overrides = dict(d.spec.overrides)
                overrides[par.name] = _moved_value(par, element, off * h)
                try:
                    dd = compile_spec(load_spec(d.spec.file, overrides, cache))
                except DiagramError as exc:
                    raise ConfigError(f"sensitivity parameter '{par.text}' cannot be moved by "
                                      f"{off * h:.3g}: {exc}", file=d.file) from None
                _same_structure(d, dd, par, base_signature, structure_signature)
                moved.append(dd)
            for j, blk in enumerate(d.blocks):
                for name, arr in vars(blk.p).items():
                    vals = [np.asarray(getattr(dd.blocks[j].p, name), dtype=float)
                            for dd in moved]
                    if all(np.array_equal(v, arr) for v in vals):
                        continue
                    g = _richardson(vals, h).reshape(-1)
                    dp.setdefault((blk.name, name), np.zeros((g.size, P)))[:, col] = g
            with np.errstate(all="ignore"):
                dx0[:, col] = _richardson([start_state(dd) for dd in moved], h)
    if not dp and not dx0.any():
        names = ", ".join(p.text for p in params)
        raise ConfigError(f"sensitivity parameters {names} reach no block parameter and no "
                          "initial state (nothing in the run depends on them)", file=d.file)
    return LoadedDerivative(dp, dx0)


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
        names = [name for (bname, name) in dp if bname == blk.name]
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
        self.d, self.P = d, P
        self.terms = [_BlockTerm(step, dp, P) for step in d.schedule]
        self.constant = {idx: np.zeros((int(np.prod(d.signal_shapes[idx], dtype=np.int64)),
                                        P)) for idx in d.constant_signals}

    def outputs(self, t, x, S, sig) -> tuple:
        """(signal sensitivities, [(block, its rows so far, J)]) at (t, x): the outputs'
        rows complete, the state derivative rows without the inputs' terms."""
        G = dict(self.constant)
        kept = []
        P = self.P
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

    def stage(self, t, x, S, sig) -> tuple:
        G, kept = self.outputs(t, x, S, sig)
        K = np.zeros((self.d.n_states, self.P))
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
    n = blk.n_states
    shapes = [np.shape(a)[1:] for a in u]
    base = np.concatenate([x.reshape(-1)] + [np.asarray(a, float).reshape(-1) for a in u])
    C = base.size
    out = np.zeros((n, C))
    for c in range(C):
        h = DIFFERENCE_STEP * max(1.0, abs(base[c]))
        f = []
        for off in _OFFSETS:
            v = base.copy()
            v[c] += off * h
            xs, us, k = v[:n].reshape(1, n), [], n
            for s in shapes:
                size = int(np.prod(s, dtype=np.int64))
                us.append(v[k:k + size].reshape((1,) + s))
                k += size
            with np.errstate(all="ignore"):
                f.append(np.broadcast_to(blk.update(t, xs, tuple(us)), (1, n))[0])
        out[:, c] = _richardson(f, h)
    parts, k = [], n
    for s in shapes:
        size = int(np.prod(s, dtype=np.int64))
        parts.append(out[:, k:k + size])
        k += size
    return out[:, :n], parts


# ---------------------------------------------------------------------- the run
def _integrate(d, chain: SensitivityChain, S0: np.ndarray, rows: int) -> dict:
    """The run's steps with the sensitivities alongside (fwdstep.run.simulate's procedure:
    the same stages, event sub-steps, updates and record times); returns signal ->
    (rows, size, P) for every logged signal."""
    from fwdstep.run.evaluate import _make_evaluator, initial_state
    from fwdstep.run.events import plan_events
    cfg = d.spec.simulation
    tab = TABLEAUX[cfg.solver]
    h, n_steps, every = cfg.step, cfg.n_steps, cfg.log_every
    events = plan_events(d, h, n_steps)
    special = events.steps if events is not None else {}
    f, outputs, sig = _make_evaluator(d)
    N, P = d.n_states, chain.P
    x = np.array(initial_state(d, event=events.start if events is not None else None),
                 dtype=float)
    S = S0.copy()
    logged = [(name, d.signal_index[name]) for name in d.logged]
    out = {name: np.full((rows, int(np.prod(d.signal_shapes[idx], dtype=np.int64)), P), np.nan)
           for name, idx in logged}
    row = 0

    def record(G):
        nonlocal row
        if row < rows:
            for name, idx in logged:
                out[name][row] = G[idx]
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

    def step(a, hh, lo, hi, recorded):
        nonlocal S
        ks, Ks = [], []
        for i in range(tab.stages):
            if i == 0:
                xi, Si, ti = x, S, max(a, lo)
            else:
                xi, Si = x.copy(), S.copy()
                for j, aij in enumerate(tab.a[i]):
                    if aij != 0.0:
                        xi += (hh * aij) * ks[j]
                        Si += (hh * aij) * Ks[j]
                ti = min(max(a + tab.c[i] * hh, lo), hi)
            dx = np.empty((1, N))
            with np.errstate(all="ignore"):
                f(ti, xi, dx)
            G, K = chain.stage(ti, xi[0], Si, sig)
            if i == 0 and recorded:
                record(G)
            ks.append(dx)
            Ks.append(K)
        for j, bj in enumerate(tab.b):
            if bj != 0.0:
                x[...] += (hh * bj) * ks[j]
                S = S + (hh * bj) * Ks[j]

    with np.errstate(all="ignore"):   # S may overflow where x does not: a note says so
        for n in range(n_steps):
            t = n * h
            if not np.all(np.isfinite(x)):
                break
            if n in special:
                for i, sub in enumerate(special[n]):
                    if sub.event is not None:
                        event(sub.event, max(sub.a, sub.lo))
                    step(sub.a, sub.b - sub.a, sub.lo, sub.hi, i == 0 and n % every == 0)
            else:
                step(t, h, -math.inf, math.inf, n % every == 0)
        else:
            t = n_steps * h
            end = events.final if events is not None else None
            ts = t
            if end is not None:
                ts = max(t, end.hi)
                if end.updates:
                    event(end, ts)
            outputs(ts, x)
            G, _ = chain.outputs(ts, x[0], S, sig)
            record(G)
    return out


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
    signals = _integrate(d, chain, S0, cfg.n_steps // cfg.log_every + 2)
    return _attach(r, {name: arr[:rows] for name, arr in signals.items()}, parameters)


def _attach(r, signals: dict, parameters: list):
    """The sensitivities onto the Result, with a note where they are not finite (the
    variational equations diverged: x is checked against the bound, S is not) and NaN from
    a zero crossing on (``_after_crossings``)."""
    r.sensitivity_data = {"signals": signals, "parameters": parameters}
    bad = [np.flatnonzero(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))
           for arr in signals.values()]
    first = min((int(b[0]) for b in bad if b.size), default=None)
    if first is not None:
        r.notes.append(f"sensitivities are not finite from t = {r.t[first]:.6g} s on")
    _after_crossings(r)
    return r


def _after_crossings(r) -> None:
    """A located zero crossing (a state event) moves with the parameters, and that motion
    is not differentiated here (the steps are integrated as if it were not there): the
    sensitivities from the first crossing on are NaN, with a note saying so, never a wrong
    number."""
    if not r.events:
        return
    first = min(r.events, key=lambda e: e.time)
    late = r.t >= first.time
    for arr in r.sensitivity_data["signals"].values():
        arr[late] = np.nan
    r.notes.append(f"sensitivities from t = {first.time:.6g} s on are not computed (NaN): "
                   f"block '{first.block}' crosses a zero there ({first.kind}), and how the "
                   "crossing time moves with the parameters is not differentiated")


__all__ = ["sensitivities", "resolve_parameter", "Parameter", "SensitivityChain",
           "loader_derivative", "LoadedDerivative"]
