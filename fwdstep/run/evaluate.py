"""The plain evaluator of a compiled diagram: every block called in schedule order.

The run loop executes generated code (``fwdstep.run.program``); this plain form computes the
initial state's outputs and, when a generated stage fails, re-runs the stage block by block
to name the block, its inputs and the time (``_locate_failure``).
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.errors import BlockRuntimeError
from fwdstep.core.solvers import TABLEAUX, rk_step, step_plan
from fwdstep.run.events import apply_updates
from fwdstep.structure.compiler import CompiledDiagram


def _make_evaluator(d: CompiledDiagram):
    """Build ``f(t, x, dx) -> None`` (fills dx), ``outputs(t, x)`` and the shared signal
    list: the procedure above, block by block, without the program's preparation."""
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    calls = []
    for step in d.schedule:
        outs = step.outputs
        calls.append((step.block.output, step.state, step.inputs, outs, len(outs)))
    ders = [(s.block.derivative, s.state, s.inputs) for s in d.stateful]
    empty = slice(0, 0)

    def outputs(t, x):
        for fn, sl, ins, outs, n_out in calls:
            y = fn(t, x[:, sl] if sl is not None else x[:, empty], tuple([sig[i] for i in ins]))
            if n_out == 1:
                sig[outs[0]] = y[0]
            else:
                for k in range(n_out):
                    sig[outs[k]] = y[k]

    def f(t, x, dx):
        outputs(t, x)
        for fn, sl, ins in ders:
            dx[:, sl] = fn(t, x[:, sl], tuple([sig[i] for i in ins]))

    return f, outputs, sig


class _Found(Exception):
    """The located failure, out of the replayed step."""

    def __init__(self, error: BlockRuntimeError):
        super().__init__(str(error))
        self.error = error


def _locate_failure(d: CompiledDiagram, t: float, x: np.ndarray, exc) -> BlockRuntimeError:
    """Which block raised during the step from (t, x), at which stage time and with which
    inputs: the step (``rk_step``, the procedure itself) is replayed with every block called
    on its own (``checked_pass``)."""
    tab = TABLEAUX[d.spec.simulation.solver]
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr

    def f(ts, xi):
        dx = np.zeros((d.batch, d.n_states))
        error = checked_pass(d, ts, xi, sig, dx)
        if error is not None:
            raise _Found(error)
        return dx

    with np.errstate(all="ignore"):
        try:
            rk_step(f, t, x, step_plan(tab, d.spec.simulation.step), [None] * tab.stages)
        except _Found as found:
            return found.error
    return BlockRuntimeError(f"evaluation failed at t = {t:.6g}: {type(exc).__name__}: {exc}",
                             time=t)


def _locate_at(d: CompiledDiagram, t: float, x: np.ndarray, exc) -> BlockRuntimeError:
    """Which block raised when the outputs and derivatives at (t, x) were evaluated (the
    solve_ivp path's right-hand side), one block at a time."""
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    with np.errstate(all="ignore"):
        error = checked_pass(d, t, x, sig, np.zeros((d.batch, d.n_states)))
    return error or BlockRuntimeError(
        f"evaluation failed at t = {t:.6g}: {type(exc).__name__}: {exc}", time=t)


def check_shapes(d: CompiledDiagram, t: float, x: np.ndarray) -> None:
    """Every block's outputs and derivative evaluated once at (t, x), block by block, their
    shapes checked strictly against the declared ones: raises the ``BlockRuntimeError`` of
    the first block that raises or returns a wrong shape (chained to what it raised).

    Called by every backend once, at the initial state, before the first step.  The run
    loops themselves do not check shapes (a check per call would cost the hot path), and a
    result narrower than declared would be broadcast there without a word ((B, 1) for
    (B, 3): three equal columns).  Once is enough: a kernel is a pure function whose
    result's shape depends on its arguments' shapes only (docs/writing-blocks.md, the
    contract), and every argument's shape is fixed for the run -- the state slices and the
    parameters by construction, the constant and fused signals are views of fixed buffers,
    and every other input is an output of a block checked here, so by induction along the
    schedule each call of the run sees the argument shapes it sees here.  A block that
    breaks the contract (a shape that depends on values or time) is still caught when its
    result is too wide or of another rank (the assignment fails and ``_locate_failure``
    names it), not when it narrows later."""
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    with np.errstate(all="ignore"):
        error = checked_pass(d, t, x, sig, np.zeros((d.batch, d.n_states)))
    if error is not None:
        raise error


def checked_pass(d: CompiledDiagram, t: float, x: np.ndarray, sig: list,
                 dx: np.ndarray) -> BlockRuntimeError | None:
    """One stage evaluated block by block at (t, x): outputs into ``sig``, derivatives into
    ``dx``; the error naming the first block that raised (any exception but a signal's
    KeyboardInterrupt: a SystemExit in a kernel is the block's error too) or whose result
    has another shape than declared: an output (1 or B, *declared shape), a derivative
    (1 or B, n_states), as many outputs as declared ports.  None when all is well."""
    empty = slice(0, 0)
    for what, steps in (("output", d.schedule), ("derivative", d.stateful)):
        for step in steps:
            u = tuple(sig[i] for i in step.inputs)
            xs = x[:, step.state if step.state is not None else empty]
            try:
                if what == "output":
                    y = step.block.output(t, xs, u)
                    if len(y) != len(step.outputs):
                        return _count_error(step, y, t)
                    for idx, val in zip(step.outputs, y):
                        sig[idx] = val
                        if not _fits(val, d.batch, tuple(d.signal_shapes[idx])):
                            return _shape_error(d, step, idx, val, t)
                else:
                    val = step.block.derivative(t, xs, u)
                    if not _fits(val, d.batch, (step.block.n_states,)):
                        return _derivative_shape_error(step, val, t)
                    dx[:, step.state] = val
            except KeyboardInterrupt:
                raise
            except BaseException as inner:  # noqa: BLE001 - the user's block failed
                error = _block_error(step, inner, t, u)
                error.__cause__ = inner
                return error
    return None


def _fits(val, batch: int, shape: tuple) -> bool:
    """``val`` is (1, *shape) or (batch, *shape), exactly (never broadcast to it)."""
    got = np.shape(val)
    return len(got) == len(shape) + 1 and got[0] in (1, batch) and got[1:] == shape


def _shape_error(d, step, idx, val, t) -> BlockRuntimeError:
    """A block output whose shape is not the declared one (blamed on it, not downstream)."""
    port = d.signal_names[idx].rsplit(".", 1)[-1]
    got = tuple(np.shape(val))[1:] if np.ndim(val) else ()
    if got == tuple(d.signal_shapes[idx]):             # the batch axis is what is wrong
        got = tuple(np.shape(val))
        return BlockRuntimeError(
            f"block '{step.block.name}' ({step.block.type_name}) output '{port}' has shape "
            f"{got} at t = {t:.6g}, but a batch of {d.batch} needs (1 or {d.batch}, "
            f"*{tuple(d.signal_shapes[idx])})", time=t, block=step.block.name)
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) output '{port}' has shape "
        f"{got} at t = {t:.6g}, but declares {tuple(d.signal_shapes[idx])}",
        time=t, block=step.block.name)


def _derivative_shape_error(step, val, t) -> BlockRuntimeError:
    got = tuple(np.shape(val))[1:] if np.ndim(val) else ()
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) derivative has shape {got} at "
        f"t = {t:.6g}, but the block declares {step.block.n_states} states",
        time=t, block=step.block.name)


def _count_error(step, y, t) -> BlockRuntimeError:
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) returned {len(y)} outputs at "
        f"t = {t:.6g}, but declares {len(step.outputs)}", time=t, block=step.block.name)


def _block_error(step, inner, t, u) -> BlockRuntimeError:
    names = list(step.block.inputs)
    shown = "; ".join(
        f"{n}={np.array2string(np.asarray(v)[0], precision=4, threshold=12, max_line_width=10**6).replace(chr(10), '')}"
        if v is not None else f"{n}=(not yet computed)" for n, v in zip(names, u))
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) raised "
        f"{type(inner).__name__}: {inner} at t = {t:.6g}; inputs: {shown or '(none)'}",
        time=t, block=step.block.name)


def initial_state(d: CompiledDiagram, t0: float = 0.0, event=None) -> np.ndarray:
    """x(0): declared initial values, then blocks that start from their inputs (reference
    dynamics: z(0) = qdot_d(0) - alpha_ell (q(0) - q_d(0))).  ``event``: discrete blocks
    that sample at t0 (``fwdstep.run.events``): those inputs are computed with their samples of
    t0 (a sampled controller's reference dynamics start from the sampled q(0), not from the
    hold's initial value); their own states are returned unchanged, the run updates them."""
    x = d.x0.copy()
    needing = [s for s in d.stateful if s.block.init_from_inputs]
    if not needing:
        return x
    _, outputs, sig = _make_evaluator(d)
    held = [(st.state, x[:, st.state].copy()) for st in event.updates] if event else []

    def evaluate(t):
        outputs(t, x)
        return sig

    with np.errstate(all="ignore"):
        for _ in range(len(needing) + 1):
            if held:
                for sl, v in held:
                    x[:, sl] = v
                apply_updates(event, t0, x, evaluate)
            outputs(t0, x)
            for s in needing:
                u = tuple(sig[i] for i in s.inputs)
                x[:, s.state] = np.broadcast_to(s.block.initial_state(t0, u),
                                                (d.batch, s.block.n_states))
    for sl, v in held:
        x[:, sl] = v
    return x
