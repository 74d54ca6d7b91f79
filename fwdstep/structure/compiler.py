"""Structure -> a frozen, compiled diagram: flat state layout, signal table, schedule.

Everything that can be decided once is decided here: the evaluation order, each block's
slice of the flat state vector, the integer index of every signal and of every block input,
the zero signals of unconnected optional inputs, and (for batches) the stacked parameters.
The simulator then only walks a prepared list.
"""
from __future__ import annotations

import copy
import dataclasses
import weakref
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from fwdstep.core.block import Block
from fwdstep.core.errors import ConfigError, DiagramError, WiringError
from fwdstep.structure.graph import Structure, build_structure, instantiate
from fwdstep.core.linear import fusable
from fwdstep.structure.spec import DiagramSpec, load_spec
from fwdstep.structure.stiffness import check_step

MAX_TOTAL_STATES = 2_000_000


@dataclass
class Step:
    """One block in the schedule."""
    block: Block
    state: slice | None
    inputs: tuple          # signal indices, in the block's input order
    outputs: tuple         # signal indices, in the block's output order


@dataclass
class CompiledDiagram:
    spec: DiagramSpec
    structure: Structure
    batch: int
    schedule: list                   # Step per block, evaluation order
    stateful: list                   # Steps of blocks with states
    n_states: int
    x0: np.ndarray                   # (batch, n_states), before input-dependent init
    signal_names: list               # index -> "block.port"
    signal_shapes: list
    signal_index: dict               # "block.port" -> index
    constant_signals: dict           # index -> array (zeros of unconnected optional inputs)
    logged: list                     # signal names to record
    variant_parameters: list = field(default_factory=list)   # one dict per batch member
    # compiled backend: keep sizes as run-time values (a sweep whose batches differ only in
    # sizes compiles one program) instead of unrolled scalar code for these sizes
    sizes_at_run_time: bool = False
    # operating limits the blocks declare (Block.declare_limit): (block name, Limit, the
    # name of the signal at the port); their signals are recorded (fwdstep.run.limits)
    limits: list = field(default_factory=list)

    @property
    def blocks(self) -> list:
        return [s.block for s in self.schedule]

    @property
    def file(self) -> str:
        return self.spec.file

    def resolve(self, name: str) -> str:
        """Signal name after subsystem aliases ('plant.q' -> 'plant/arm.q')."""
        return self.spec.aliases.get(name, name)

    def state_owner(self, index: int) -> tuple:
        for step in self.stateful:
            if step.state.start <= index < step.state.stop:
                return step.block, index - step.state.start
        return None, index


#: parameter kinds whose values may select code paths rather than numbers (never stacked)
STRUCTURAL_KINDS = ("str", "choice", "bool", "int", "names", "file")


def structure_signature(blocks: list) -> tuple:
    """What must be equal for variants to share one batched run: names, types, state sizes,
    port shapes, the shapes of the stacked ``p`` arrays, and the values of non-numeric
    parameters (a variant name or a flag may pick a different code path inside a block, which
    stacking numbers could not express)."""
    return tuple(_block_signature(b) for b in blocks)


#: block -> its signature; blocks are descriptions that never change after setup, and a
#: sweep shares one instance between the variants that agree on it
_signatures: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _block_signature(b) -> tuple:
    try:
        return _signatures[b]
    except (KeyError, TypeError):
        pass
    decls = type(b).params
    structural = tuple(sorted(
        (k, repr(v)) for k, v in getattr(b, "values", {}).items()
        if k in decls and decls[k].kind in STRUCTURAL_KINDS
        and k not in getattr(type(b), "stacked_params", ())))
    sig = (b.name, type(b).__name__, b.n_states,
           tuple((p.name, p.shape) for p in b.inputs.values()),
           tuple((p.name, p.shape) for p in b.outputs.values()),
           tuple(sorted((k, np.shape(v)) for k, v in vars(b.p).items())),
           structural, setup_state(b), _kernel_statics(b))
    try:
        _signatures[b] = sig
    except TypeError:                  # a block type that cannot be weakly referenced
        pass
    return sig


def _kernel_statics(block) -> tuple:
    """The static values of a block's kernels (``set_kernels(static=...)``): plain numbers
    and flags the kernels are written for.  ``setup_state`` leaves ``kernels`` out because a
    block's ``finalize`` may pick them anew from the stacked ``p``; a block that does not
    override ``finalize`` keeps the kernels of its setup, so ``stack_blocks`` would run every
    variant with the first one's statics: for those blocks they are part of the structure.
    A flag derived from a number (URDFArm's "has friction") then splits the batch."""
    kernels = getattr(block, "kernels", None)
    if kernels is None or type(block).finalize is not Block.finalize:
        return ()
    return tuple(_value_key(v) for v in kernels.static)


#: block attributes that stacking handles per variant (or that never change the numbers)
_STACKED_ATTRIBUTES = frozenset({"p", "x0", "values", "name"})


def setup_state(block) -> tuple:
    """A key of everything a block computed in ``setup`` outside ``p`` and ``x0``: private
    attributes (``self._gravity``, precomputed matrices, ...) that ``stack_blocks`` would take
    from the first variant.  Left out: what ``finalize`` recomputes from the stacked ``p``
    (the class's declared ``finalize_attributes``) and the names a block class lists in
    ``inspection_attributes`` (kept for users to read, never used at run time).  Variants
    batch together only when these are equal, so a block that keeps a number outside ``p``
    is never given another variant's number."""
    cls = type(block)
    skip = _STACKED_ATTRIBUTES | set(cls.finalize_attributes) | set(
        getattr(cls, "inspection_attributes", ()))
    return tuple(sorted((k, _value_key(v)) for k, v in vars(block).items() if k not in skip))


def stack_blocks(variants: list, compared: bool = False) -> list:
    """Stack the numeric parameters of structurally identical block lists along the batch axis.

    Returns copies of the first variant's blocks with ``p`` arrays of leading length B (or 1
    where all variants agree) and ``x0`` of shape (B, n); the variants' own blocks (which
    may be shared between variants and batches) are left as they were.  ``compared``: the
    caller has compared the variants' ``structure_signature`` already."""
    first = variants[0]
    B = len(variants)
    signature = None if compared else structure_signature(first)
    for blocks in variants[1:] if not compared else ():
        if blocks is not first and structure_signature(blocks) != signature:
            raise ConfigError("variants of a batch differ in structure (a parameter changes "
                              "a shape or a state size); run them in separate batches")
    stacked = []
    for k, original in enumerate(first):
        blk = copy.copy(original)
        blk.p = SimpleNamespace(**vars(original.p))
        column = [v[k] for v in variants]
        for name in list(vars(blk.p)):
            vals = [vars(c.p)[name] for c in column]
            if all(c is original for c in column) or all(
                    np.array_equal(vals[0], v) for v in vals[1:]):
                continue
            setattr(blk.p, name, np.concatenate(vals, axis=0))
        x0s = [c.x0 for c in column]
        blk.x0 = np.concatenate(x0s, axis=0) if B > 1 else x0s[0]
        blk.finalize(B)
        stacked.append(blk)
    return stacked


#: exact types whose key is (type name, value) (the last line of ``_value_key``), looked up
#: first: most values are these
_PLAIN_KEYS = frozenset({float, int, bool, str, type(None)})


def _value_key(value):
    """A hashable key equal for equal parameter values (type, shape and every number)."""
    kind = type(value)
    if kind in _PLAIN_KEYS:
        return (kind.__name__, value)
    if kind is tuple:
        return ("tuple", tuple(_value_key(v) for v in value))
    if kind is dict:
        return ("dict", tuple((k, _value_key(v)) for k, v in value.items()))
    if kind not in _OTHER_TYPES:
        if isinstance(value, (np.ndarray, dict, list, tuple, set, frozenset, slice)):
            return _container_key(value)
        _OTHER_TYPES.add(kind)          # none of the kinds above: straight to the last lines
    try:
        hash(value)
    except TypeError:
        return ("id", id(value))               # unhashable and unknown: never shared
    return (kind.__name__, value)


#: types seen by ``_value_key`` that are none of the containers it takes apart
_OTHER_TYPES: set = set()


def _container_key(value):
    """The key of an array, dict, list, tuple, set or slice (or of a subclass of one)."""
    if isinstance(value, np.ndarray):
        return ("ndarray", value.shape, value.dtype.str, value.tobytes())
    if isinstance(value, dict):
        return ("dict", tuple((k, _value_key(v)) for k, v in value.items()))
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, tuple(_value_key(v) for v in value))
    if isinstance(value, (set, frozenset)):
        return ("set", tuple(sorted(repr(_value_key(v)) for v in value)))
    return ("slice", value.start, value.stop, value.step)


def instantiate_variants(specs: list, made: dict | None = None) -> list:
    """The blocks of every spec.  A block whose type and parameters equal those of the same
    block in an earlier spec is the same instance (a sweep over one gain builds one arm, one
    regressor, ... and only the gains anew).  ``made`` is the cache of built blocks, to share
    it between calls."""
    made = {} if made is None else made
    out = []
    for spec in specs:
        row = []
        for k, entry in enumerate(spec.blocks):
            key = (k, entry.name, entry.cls, _value_key(entry.params))
            blk = made.get(key)
            if blk is None:
                blk = made[key] = instantiate(dataclasses.replace(spec, blocks=[entry]))[0]
            row.append(blk)
        out.append(row)
    return out


def compile_spec(spec: DiagramSpec) -> CompiledDiagram:
    return compile_structure(build_structure(spec), 1, [spec.parameters])


def compile_batch(specs: list) -> CompiledDiagram:
    """One compiled diagram integrating ``len(specs)`` structurally identical variants."""
    return compile_variants(specs, instantiate_variants(specs))


def compile_variants(specs: list, variants: list) -> CompiledDiagram:
    """``compile_batch`` from already instantiated blocks (one list per spec)."""
    blocks = stack_blocks(variants)
    structure = build_structure(specs[0], blocks)
    return compile_structure(structure, len(specs), [s.parameters for s in specs])


def compile_structure(structure: Structure, batch: int, params: list) -> CompiledDiagram:
    spec = structure.spec
    names, shapes, index = [], [], {}
    for blk in structure.blocks:
        for port in blk.outputs.values():
            key = f"{blk.name}.{port.name}"
            index[key] = len(names)
            names.append(key)
            shapes.append(port.shape)
    constants = {}
    schedule, stateful = [], []
    # flat state layout: called blocks first, then the blocks the run loop can fuse into one
    # linear system (fwdstep.core.linear.plan_fusion), so that their states are one slice
    offsets, offset = {}, 0
    for fused in (False, True):
        for blk in structure.blocks:
            if blk.n_states and fusable(blk) == fused:
                offsets[blk.name] = offset
                offset += blk.n_states
                if offset > MAX_TOTAL_STATES:
                    raise ConfigError(f"the diagram has more than {MAX_TOTAL_STATES} states",
                                      file=spec.file)
    for blk in structure.blocks:
        ins = []
        for port in blk.inputs.values():
            drv = structure.drivers.get((blk.name, port.name))
            if drv is None:   # optional, unconnected: a zero signal of its own
                idx = len(names)
                names.append(f"{blk.name}.{port.name}(zero)")
                shapes.append(port.shape)
                constants[idx] = np.zeros((1,) + port.shape)
                ins.append(idx)
            else:
                ins.append(index[f"{drv[0]}.{drv[1]}"])
        outs = tuple(index[f"{blk.name}.{p}"] for p in blk.outputs)
        sl = None
        if blk.n_states:
            sl = slice(offsets[blk.name], offsets[blk.name] + blk.n_states)
        step = Step(blk, sl, tuple(ins), outs)
        schedule.append(step)
        if sl is not None:
            stateful.append(step)
    x0 = np.zeros((batch, offset))
    for step in stateful:
        x0[:, step.state] = np.broadcast_to(step.block.x0, (batch, step.block.n_states))
    logged = _logged_signals(spec, index)
    _check_declared_signals(spec, index)
    limits = _declared_limits(schedule, names)
    logged += [name for _, _, name in limits if name not in logged]
    d = CompiledDiagram(spec=spec, structure=structure, batch=batch, schedule=schedule,
                        stateful=stateful, n_states=offset, x0=x0, signal_names=names,
                        signal_shapes=shapes, signal_index=index, constant_signals=constants,
                        logged=logged, variant_parameters=params, limits=limits)
    check_step(d)                   # a step outside a block's stability region: refused
    return d


def _declared_limits(schedule: list, names: list) -> list:
    """(block name, Limit, signal name) of every limit a block declares on a port with a
    signal (an unconnected optional input has none: its zero is no operating point)."""
    out = []
    for step in schedule:
        blk = step.block
        for limit in blk.limits:
            if limit.port in blk.outputs:
                idx = step.outputs[list(blk.outputs).index(limit.port)]
            else:
                idx = step.inputs[list(blk.inputs).index(limit.port)]
                if names[idx].endswith("(zero)"):
                    continue
            out.append((blk.name, limit, names[idx]))
    return out


def _check_declared_signals(spec: DiagramSpec, index: dict) -> None:
    """A subsystem file's ``log:`` names signals for the figures: each must exist."""
    for real, (file, line, written) in spec.signal_lines.items():
        if real not in index:
            blk = real.rsplit(".", 1)[0]
            ports = [n.rsplit(".", 1)[1] for n in index if n.rsplit(".", 1)[0] == blk]
            hint = (f"; block '{blk}' has outputs: {', '.join(ports)}" if ports else
                    f"; there is no block '{blk}'")
            raise WiringError(f"log: signal '{written}' does not exist{hint}", file=file,
                              line=line, block=blk)


def _logged_signals(spec: DiagramSpec, index: dict) -> list:
    wanted = list(spec.log) if spec.log is not None else list(index)
    for panels in spec.plots.values():
        for panel in panels:
            wanted.extend(panel)
    if "error" in spec.metrics:
        wanted.append(spec.metrics["error"])
    out = []
    for name in wanted:
        real = spec.aliases.get(name, name)
        if real not in index:
            blk = real.rsplit(".", 1)[0]
            known = sorted({n.rsplit(".", 1)[0] for n in index})
            if blk in known:
                ports = [n.rsplit(".", 1)[1] for n in index if n.rsplit(".", 1)[0] == blk]
                hint = f"; block '{blk}' has outputs: {', '.join(ports)}"
            else:
                hint = f"; there is no block '{blk}'"
            raise ConfigError(f"signal '{name}' (in log/plots/metrics) does not exist{hint}",
                              file=spec.file, line=spec.lines.get(name))
        if real not in out:
            out.append(real)
    return out


def load_diagram(path: str, overrides: dict | None = None,
                 plugins: list | None = None, redirects: dict | None = None) -> CompiledDiagram:
    """Load, validate and compile a diagram file.  ``overrides`` maps parameter names to values
    (numbers, lists or expression strings) that replace the file's before anything is built.
    ``plugins``: Python files defining more blocks (docs/writing-blocks.md), imported first.
    ``redirects``: see ``fwdstep.structure.spec.load_spec`` (a run's recorded copy)."""
    if plugins:
        from fwdstep.structure.library import load_plugins
        load_plugins(plugins)
    return compile_spec(load_spec(path, overrides, redirects=redirects))


__all__ = ["CompiledDiagram", "load_diagram", "compile_batch", "compile_spec", "DiagramError"]
