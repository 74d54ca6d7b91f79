"""The plain evaluator of a compiled diagram: every block called in schedule order.

The run loop executes generated code (``fwdstep.run.program``); this plain form computes the
initial state's outputs and, when a generated stage fails, re-runs the stage block by block
to name the block, its inputs and the time (``_locate_failure``).
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.errors import BlockRuntimeError
from fwdstep.core.solvers import TABLEAUX, step_plan
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


def _locate_failure(d: CompiledDiagram, t: float, x: np.ndarray, exc) -> BlockRuntimeError:
    """Which block raised during the step from (t, x), at which stage time and with which
    inputs: the step is replayed with the reference evaluator, one block at a time."""
    tab = TABLEAUX[d.spec.simulation.solver]
    stages, _ = step_plan(tab, d.spec.simulation.step)
    sig: list = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr
    k = [np.zeros((d.batch, d.n_states)) for _ in range(tab.stages)]
    empty = slice(0, 0)
    with np.errstate(all="ignore"):
        for s, (ch, coeffs) in enumerate([(0.0, [])] + list(stages)):
            ts = t + ch if s else t
            xi = x.copy()
            for j, a in coeffs:
                xi += a * k[j]
            for what, steps in (("output", d.schedule), ("derivative", d.stateful)):
                for step in steps:
                    u = tuple(sig[i] for i in step.inputs)
                    xs = xi[:, step.state if step.state is not None else empty]
                    try:
                        if what == "output":
                            y = step.block.output(ts, xs, u)
                            for idx, val in zip(step.outputs, y):
                                sig[idx] = val
                                if (np.ndim(val) < 1 or np.shape(val)[0] not in (1, d.batch)
                                        or np.shape(val)[1:] != tuple(d.signal_shapes[idx])):
                                    return _shape_error(d, step, idx, val, ts)
                        else:
                            k[s][:, step.state] = step.block.derivative(ts, xs, u)
                    except Exception as inner:  # noqa: BLE001 - the user's block failed
                        return _block_error(step, inner, ts, u)
    return BlockRuntimeError(f"evaluation failed at t = {t:.6g}: {type(exc).__name__}: {exc}",
                             time=t)


def _shape_error(d, step, idx, val, t) -> BlockRuntimeError:
    """A block output whose shape is not the declared one (blamed on it, not downstream)."""
    port = d.signal_names[idx].rsplit(".", 1)[-1]
    got = tuple(np.shape(val))[1:] if np.ndim(val) else ()
    return BlockRuntimeError(
        f"block '{step.block.name}' ({step.block.type_name}) output '{port}' has shape "
        f"{got} at t = {t:.6g}, but declares {tuple(d.signal_shapes[idx])}",
        time=t, block=step.block.name)


def _block_error(step, inner, t, u) -> BlockRuntimeError:
    names = list(step.block.inputs)
    shown = "; ".join(
        f"{n}={np.array2string(np.asarray(v)[0], precision=4, threshold=12)}"
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
    _, outputs, sig = _make_evaluator(d)
    with np.errstate(all="ignore"):
        for _ in range(len(needing) + 1):
            outputs(t0, x)
            for s in needing:
                u = tuple(sig[i] for i in s.inputs)
                x[:, s.state] = np.broadcast_to(s.block.initial_state(t0, u),
                                                (d.batch, s.block.n_states))
    return x
