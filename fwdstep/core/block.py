"""The block contract.

A block is a *description*: it declares, once, in ``setup``:

* named input ports and output ports with fixed shapes (``()`` scalar, ``(n,)`` vector,
  ``(n, p)`` matrix);
* per output port, which inputs it depends on directly (*feedthrough*; default: all);
* its continuous state: a flat vector of ``n_states`` numbers and its initial value;
* its numeric parameters, stored in ``self.p`` as arrays whose **leading axis is the batch
  axis** (length 1 for a single run; stacked to length B by a batched sweep).

and implements two pure functions on arrays that all carry a leading batch axis ``B``:

``output(t, x, u) -> tuple``
    ``t`` float, ``x`` array ``(B, n_states)``, ``u`` tuple of input arrays in declared
    order, each ``(B, *shape)`` or ``(1, *shape)`` (broadcastable).  Returns one array per
    declared output, in declared order, each broadcastable to ``(B, *shape)``.
``derivative(t, x, u) -> array (B, n_states)``
    Only for blocks with state.

Neither may mutate ``self``, ``x`` or ``u``.  Per-run data (time, state, logs) live in the
simulator, never in the block, so a compiled diagram can be run any number of times.

One definition, two executions (docs/writing-blocks.md).  A block states its numerics once,
as module-level *kernels* declared in ``setup`` with ``set_kernels``::

    output_kernel(t, x, u_1, ..., u_k, p_1, ..., p_m, s_1, ..., s_r) -> (y_1, ..., y_j)
    derivative_kernel(t, x, u_1, ..., u_k, p_1, ..., p_m, s_1, ..., s_r) -> dx

where ``p_i`` are the arrays ``self.p.<name>`` named in ``params`` (leading batch axis) and
``s_i`` the plain numbers/flags in ``static``.  Kernels are pure functions written in the
subset of NumPy that numba compiles (plus ``math`` and the batched helpers of
``fwdstep.core.kernelops``).  The NumPy path calls them as they are (``Block.output`` /
``Block.derivative`` below do); the compiled backend jits the very same functions and calls
them from one generated loop.  A block whose numerics call a Python library numba cannot
compile (pinocchio) sets ``compile_with = "objmode"``: the compiled loop then calls its
ordinary ``output``/``derivative`` through numba's object mode.  ``compile_with = "traced"``:
kernels the compiled backend only traces into scalar code (``fwdstep.compiled.scalarize``; the robot
blocks of blocks/urdf.py), object mode when the diagram's stage does not trace.  A block
whose NumPy-path method is slow (a Python library called per variant) may name kernels in
``native_kernels``: the NumPy path then runs them as native code when it can.  A block
that cannot run compiled at all says why in ``cannot_compile``; the compiled backend then refuses it by name.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np

from fwdstep.core.errors import ParameterError

#: The largest state a single block may declare; larger requests are refused before any
#: allocation (a 10**9-state block would need 8 GB per copy of the state).
MAX_BLOCK_STATES = 200_000
#: The largest number of elements in one signal.
MAX_SIGNAL_SIZE = 1_000_000

REQUIRED = object()
_NO_TIMES = np.zeros(0)
_NO_TIMES.flags.writeable = False


@dataclass(frozen=True)
class Param:
    """Declaration of one block parameter.

    kind:
      ``float`` (scalar number), ``int`` (whole number), ``bool``, ``str`` (literal text),
      ``array`` (number, list or nested list -> float ndarray), ``choice`` (one of
      ``choices``), ``names`` (a list of literal names, e.g. joints: a tuple of str),
      ``file`` (a file name: the loader makes it absolute, relative to the diagram file
      that names it, as subsystem ``file:`` is; from ``--set``, relative to the working
      directory), ``any`` (passed through after expression evaluation).
    Numeric kinds accept expression strings, evaluated against the diagram's parameters.
    """

    kind: str
    default: Any = REQUIRED
    doc: str = ""
    choices: tuple = ()
    #: ``array`` only: a list of rows of different lengths is accepted and padded with zeros
    #: at the end (per-channel coefficient or harmonic lists)
    ragged: bool = False

    @property
    def required(self) -> bool:
        return self.default is REQUIRED


@dataclass(frozen=True)
class Port:
    name: str
    shape: tuple
    optional: bool = False   # inputs only: unconnected -> zeros (documented per block)

    @property
    def size(self) -> int:
        return math.prod(self.shape)            # Python ints: exact at any size


@dataclass(frozen=True)
class Kernels:
    """A block's numerics, declared with ``Block.set_kernels``."""
    output: Any
    derivative: Any
    params: tuple
    static: tuple
    packed: bool = False
    tuple_inputs: bool = False


@dataclass(frozen=True)
class Limit:
    """An operating limit a block declares on one of its ports (``Block.declare_limit``):
    per element, the signal should stay in [lower, upper].  A run reports how close it came
    (``fwdstep.run.limits``) and stops at the first recorded sample beyond it when ``stop``.
    ``what`` names the quantity (effort, velocity, position), ``unit`` its unit,
    ``components`` the element names (joints)."""
    port: str
    what: str
    lower: tuple
    upper: tuple
    unit: str = ""
    components: tuple = ()
    stop: bool = False

    @property
    def symmetric(self) -> bool:
        return all(lo == -hi for lo, hi in zip(self.lower, self.upper))


def shape_str(shape: tuple) -> str:
    if shape == ():
        return "scalar ()"
    return "(" + ", ".join(str(s) for s in shape) + (",)" if len(shape) == 1 else ")")


class Block:
    """Base class of every library block. See the module docstring for the contract."""

    #: registry name (set by ``blocks.register``)
    type_name: ClassVar[str] = ""
    #: parameter declarations
    params: ClassVar[dict[str, Param]] = {}
    #: parameters that make a valid instance, used by the contract tests and ``fwdstep blocks``
    example: ClassVar[dict] = {}
    #: str/bool/choice/int parameters the block stores in ``p`` and handles per variant, so a
    #: batch may mix their values (all others of those kinds split batches)
    stacked_params: ClassVar[tuple] = ()
    #: shape parameters a diagram may leave out because the wiring fixes them: parameter ->
    #: the ports whose shape it is (fwdstep/structure/shapes.py), e.g. {"shape": ("u", "y")}
    shape_from: ClassVar[dict] = {}
    #: True when ``initial_state(t0, u)`` must be called with the inputs at t0
    init_from_inputs: ClassVar[bool] = False
    #: non-empty: why this block cannot run on the compiled backend (which then refuses the
    #: diagram with this reason and the block's name); empty: it must declare kernels
    cannot_compile: ClassVar[str] = ""
    #: how the compiled backend runs this block: "numba" (default) jits its kernels;
    #: "objmode" calls its ``output``/``derivative`` methods as they are (the NumPy path's
    #: code, e.g. a kernel calling pinocchio) from the compiled loop through numba's object
    #: mode, one variant per call, at the cost of a Python call (docs/writing-blocks.md)
    compile_with: ClassVar[str] = "numba"
    #: the kernels ("output", "derivative") worth running as native code on the NumPy path:
    #: when llvmlite is installed the generated program (``fwdstep.run.program``) calls a
    #: native compile of that kernel (``fwdstep.compiled.native_block``: the same equations,
    #: traced and compiled for the block's structure) instead of the method, for the batches
    #: ``native_wanted`` accepts; a kernel the tracer refuses keeps the method.  Worth it
    #: where the method makes several Python or library calls per stage (the robot blocks)
    native_kernels: ClassVar[tuple] = ()
    #: set by ``set_kernels``: (output kernel, derivative kernel, param names, static values)
    kernels: "Kernels | None" = None
    #: the attributes ``finalize`` may (re)compute from the stacked ``p`` and the batch size:
    #: everything else a block keeps outside ``p``, ``x0`` and ``values`` is part of its
    #: structure, and variants batch together only where it is equal
    #: (``fwdstep.structure.compiler.setup_state``); a subclass whose ``finalize`` sets more
    #: adds their names (tests/blocks/test_contract.py checks the declaration is complete)
    finalize_attributes: ClassVar[tuple] = ("kernels", "_unpack", "_kargs")
    #: operating limits on ports (``declare_limit``); none by default
    limits: tuple = ()

    def __init__(self, name: str, **params: Any):
        self.name = name
        self.inputs: dict[str, Port] = {}
        self.outputs: dict[str, Port] = {}
        self._feedthrough: dict[str, tuple | None] = {}
        self.output_info: dict[str, dict] = {}    # port -> label/unit/components for figures
        self.n_states = 0
        self.x0 = np.zeros((1, 0))
        self.state_labels: list[str] | None = None
        self.crossing_names: tuple = ()         # declare_zero_crossings
        self.n_crossings = 0
        self.p = SimpleNamespace()
        values = self._check_params(params)
        self.values = values
        self.setup(**values)
        for port in list(self.inputs.values()) + list(self.outputs.values()):
            if port.size > MAX_SIGNAL_SIZE:
                raise ParameterError(
                    f"block '{name}': port '{port.name}' would have {port.size} elements "
                    f"(limit {MAX_SIGNAL_SIZE})", block=name, port=port.name)

    def native_wanted(self, batch: int) -> tuple:
        """The ``native_kernels`` to run natively in a batch of ``batch`` variants (default:
        all of them; a block may keep its method for some batches or settings)."""
        return self.native_kernels

    # ------------------------------------------------------------------ declaration API
    def setup(self, **params: Any) -> None:  # pragma: no cover - overridden
        """Declare ports, states and parameters from the validated ``params``."""

    def declare_input(self, name: str, shape=(), optional: bool = False) -> None:
        self.inputs[name] = Port(name, _port_shape(shape), optional)

    def declare_output(self, name: str, shape=(), feedthrough=None, label: str | None = None,
                       unit: str = "", components=None) -> None:
        """``feedthrough``: None = depends on every input; a tuple of input names otherwise
        (``()`` = depends on state and time only).  ``label`` (mathtext allowed), ``unit`` and
        ``components`` (one name per element) are the defaults figures use for this output;
        a diagram's ``log:``/``plots:`` entries override them."""
        self.outputs[name] = Port(name, _port_shape(shape))
        self._feedthrough[name] = None if feedthrough is None else tuple(feedthrough)
        if label is not None or unit or components is not None:
            self.output_info[name] = {"label": label, "unit": unit,
                                      "components": list(components) if components else None}

    def declare_limit(self, port: str, what: str, upper, lower=None, unit: str = "",
                      components=None, stop: bool = False) -> None:
        """An operating limit on input or output ``port`` (a vector): each element should
        stay in [lower, upper] (``lower`` None: [-upper, upper]).  Not a constraint on the
        numerics: the run reports, per element, how far the signal went relative to the
        limit, and ends at the first recorded sample beyond it when ``stop``
        (``fwdstep.run.limits``; the port's signal is recorded)."""
        upper = np.asarray(upper, dtype=float).reshape(-1)
        lower = -upper if lower is None else np.asarray(lower, dtype=float).reshape(-1)
        self.limits = tuple(self.limits) + (Limit(
            port, what, tuple(lower.tolist()), tuple(upper.tolist()), unit,
            tuple(components or ()), bool(stop)),)

    def declare_state(self, n: int, initial=None) -> None:
        n = int(n)
        if n < 0 or n > MAX_BLOCK_STATES:
            raise ParameterError(
                f"block '{self.name}' would have {n} states (limit {MAX_BLOCK_STATES})",
                block=self.name)
        self.n_states = n
        x0 = np.zeros(n) if initial is None else np.asarray(initial, dtype=float)
        x0 = np.broadcast_to(x0, (n,)) if x0.ndim <= 1 and x0.size in (1, n) else x0
        if x0.size != n:
            raise ParameterError(f"block '{self.name}': initial state has {x0.size} values, "
                                 f"the block has {n} states", block=self.name)
        self.x0 = np.array(x0, dtype=float).reshape(1, n)

    def set_param(self, name: str, value) -> np.ndarray:
        """Store a numeric run-time parameter with a leading batch axis of length 1."""
        arr = np.asarray(value, dtype=float)[None]
        setattr(self.p, name, arr)
        return arr

    def require_size(self, what: str, value: int, maximum: int) -> int:
        """Refuse absurd sizes before anything is allocated."""
        if value > maximum:
            raise ParameterError(f"block '{self.name}': {what} = {value} is larger than the "
                                 f"limit {maximum}", block=self.name)
        return value

    def set_kernels(self, output=None, derivative=None, params: tuple = (),
                    static: tuple = (), packed: bool = False,
                    tuple_inputs: bool = False) -> None:
        """Declare the block's numerics: module-level kernel functions (see the module
        docstring and docs/writing-blocks.md).  ``params`` names arrays of ``self.p`` passed
        after the inputs, in this order; ``static`` are plain ints/floats/bools passed last
        (fixed by the structure, e.g. a size or a variant flag).  May be called again in
        ``finalize`` to pick another kernel for a batch.  ``packed``: the output kernel
        returns one array (B, total size) holding every output flattened, in declared order
        (for a number of outputs that depends on the parameters).  ``tuple_inputs``: the
        kernels receive the inputs as one tuple ``u`` (for a number of inputs that depends on
        the parameters; every input must then have the same rank)."""
        for name in params:
            if not hasattr(self.p, name):
                raise ValueError(f"{type(self).__name__}.set_kernels: self.p has no {name!r} "
                                 "(call set_param first)")
        for value in static:
            if not isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
                raise ValueError(f"{type(self).__name__}.set_kernels: static values must be "
                                 f"numbers or flags, got {type(value).__name__}")
        self.kernels = Kernels(output, derivative, tuple(params),
                               tuple(v.item() if isinstance(v, np.generic) else v
                                     for v in static), packed, tuple_inputs)
        if packed:
            self._unpack = []
            c = 0
            for port in self.outputs.values():
                # a vector output is the column slice itself (a view, no reshape)
                self._unpack.append((c, c + port.size, None if len(port.shape) == 1
                                     else port.shape))
                c += port.size

    def kernel_args(self) -> tuple:
        """The arguments after the inputs: the named ``p`` arrays, then the static values
        (built once per parameter namespace: a batch stacks ``p`` anew, then finalizes)."""
        cached = self.__dict__.get("_kargs")
        if cached is not None and cached[0] is self.p and cached[1] is self.kernels:
            return cached[2]
        k = self.kernels
        args = tuple(getattr(self.p, n) for n in k.params) + k.static
        self._kargs = (self.p, k, args)
        return args

    def feedthrough(self, output: str) -> tuple:
        ft = self._feedthrough[output]
        return tuple(self.inputs) if ft is None else ft

    # ------------------------------------------------------------------ run-time API
    def output(self, t: float, x: np.ndarray, u: tuple) -> tuple:
        k = self.kernels
        if k is None or k.output is None:
            return ()
        y = (k.output(t, x, u, *self.kernel_args()) if k.tuple_inputs
             else k.output(t, x, *u, *self.kernel_args()))
        if k.packed:
            return tuple(y[:, a:b] if shape is None else y[:, a:b].reshape((y.shape[0],) + shape)
                         for a, b, shape in self._unpack)
        return y

    def derivative(self, t: float, x: np.ndarray, u: tuple) -> np.ndarray:
        k = self.kernels
        if k is None or k.derivative is None:
            raise NotImplementedError(f"block type {type(self).__name__} declares states but "
                                      "no derivative kernel")
        if k.tuple_inputs:
            return k.derivative(t, x, u, *self.kernel_args())
        return k.derivative(t, x, *u, *self.kernel_args())

    # ------------------------------------------------------------------ time events
    #: True for blocks with discrete states: ``update`` is applied at their event times
    discrete: ClassVar[bool] = False
    #: discrete blocks: whether the output right after an update at t_k depends on the input
    #: sampled at t_k (a ZeroOrderHold, a DiscreteStateSpace with D != 0: True; a UnitDelay:
    #: False).  A loop of such blocks updating at one instant is a discrete algebraic loop,
    #: refused before the run (``fwdstep.run.events``); None: unknown, the run's fixed point
    #: decides.
    samples_through: bool | None = None

    def discontinuities(self, t_final: float) -> np.ndarray:
        """Times in [0, t_final] at which this block's outputs or derivatives jump (a Step's
        time, a pulse's edges, sample instants), as a 1-D float array, the union over the
        batch; default: none.  The simulator ends a step exactly at each such time; every
        stage of a step that ends at time T is evaluated at a time < T (left limit), every
        stage of the next step at a time >= T (right limit).  A block's output must
        therefore be right-continuous: use ``t >= T``, never ``t > T``.  For many regular
        instants use ``fwdstep.core.instants.sample_instants``.  Keep the times (or the period) in
        an attribute set in ``setup``, outside ``p``, so that variants with other times never
        share a batch (one batch, one grid).  docs/discrete-time.md."""
        return _NO_TIMES

    # ------------------------------------------------------------------ state events
    #: True for a block whose located crossing ends the run (``Stop``: status "stopped")
    stops_run: ClassVar[bool] = False

    def declare_zero_crossings(self, names, size: int = 1, kernel=None,
                               params: tuple = ()) -> None:
        """Declare zero-crossing functions (state events): ``names`` (one per function,
        e.g. ("lower", "upper")), each with ``size`` elements; ``zero_crossings`` returns
        them as (B, len(names) * size), name by name.  ``kernel``: optionally, the guards
        as a kernel ``kernel(out, t, x, u_1, ..., u_k, p_1, ...)`` writing them into
        ``out`` (B, n) (``params`` name arrays of ``self.p``); ``zero_crossings`` is then
        that kernel and the run calls it straight into its buffer (no allocation, no
        method call: the cost of watching guards that never cross).
        docs/writing-blocks.md."""
        self.crossing_names = tuple(names)
        self.crossing_size = int(size)
        self.n_crossings = len(self.crossing_names) * self.crossing_size
        self.crossing_kernel = (kernel, tuple(params)) if kernel is not None else None

    def zero_crossings(self, t: float, x: np.ndarray, u: tuple) -> np.ndarray:
        """The guard values g (B, n_crossings) at (t, x, u): a regime change (a limit
        reached, a switch flipping, a reset) happens where some g_j changes sign.  They
        must be continuous along a step (use the mode held in ``x``, never a regime
        recomputed from u).  A fixed-step run locates the crossing in time (to 1e-12 s),
        ends the step there, calls ``crossed`` and goes on (``fwdstep.run.crossings``).
        Default: the declared guard kernel, or no guards."""
        ck = getattr(self, "crossing_kernel", None)
        out = np.empty((x.shape[0], self.n_crossings))
        if ck is not None:
            ck[0](out, t, x, *u, *(getattr(self.p, n) for n in ck[1]))
        return out

    def crossed(self, t: float, x: np.ndarray, u: tuple, which: np.ndarray):
        """At a located crossing (t just past it): the block's new state (B, n_states) (a
        new mode, a reset, a clamp), or None when it keeps its state.  ``which`` (B,
        n_crossings, bool): the guards that changed sign."""
        return None

    def update(self, t: float, x: np.ndarray, u: tuple) -> np.ndarray:
        """Discrete blocks (``discrete = True``) only: the block's new state ``(B, n_states)``
        at one of its ``discontinuities`` times, from its state just before (``x``) and its
        inputs at t.  Applied between steps, never inside the Runge-Kutta stages; the
        block's ``derivative`` must be zero for its discrete states."""
        raise NotImplementedError

    def initial_state(self, t0: float, u: tuple) -> np.ndarray:
        """For ``init_from_inputs`` blocks: the initial state ``(B, n_states)`` from the
        inputs at t0."""
        return self.x0

    def state_eigenvalues(self) -> "np.ndarray | None":
        """The eigenvalues of this block's own dynamics (the Jacobian of ``derivative`` with
        respect to ``x``, inputs held), where the block knows them: a complex array
        (1 or B, k), one row per variant; None (the default) when it does not.  Before a
        fixed-step run every block's eigenvalues are checked against the solver's
        stability region (``fwdstep.structure.stiffness``).  A block offering a
        ``linear_form`` needs nothing more (its A is used); a nonlinear block may give the
        eigenvalues of its fastest regime (``RateLimiter``: -1/time_constant)."""
        return None

    def finalize(self, batch: int) -> None:
        """Called once after parameters are stacked for a batch of ``batch`` variants;
        blocks may pick fast paths here (never during a run)."""

    # ------------------------------------------------------------------ helpers
    @classmethod
    def summary(cls) -> str:
        doc = (cls.__doc__ or "").strip().splitlines()
        return doc[0] if doc else ""

    def _check_params(self, given: dict) -> dict:
        out = {}
        unknown = [k for k in given if k not in self.params]
        if unknown:
            valid = ", ".join(self.params) or "(none)"
            raise ParameterError(
                f"block '{self.name}' ({self.type_name}) has no parameter '{unknown[0]}'; "
                f"valid parameters are: {valid}", block=self.name, port=None)
        for key, decl in self.params.items():
            if key not in given:
                if decl.required:
                    raise ParameterError(
                        f"block '{self.name}' ({self.type_name}) is missing required parameter "
                        f"'{key}' ({decl.doc or decl.kind})", block=self.name)
                out[key] = decl.default
                continue
            out[key] = coerce(self.name, key, decl, given[key])
        return out


def _port_shape(shape) -> tuple:
    """A declared shape as a tuple of ints: ``()``, a number or a sequence of numbers."""
    if type(shape) is tuple and all(type(s) is int for s in shape):
        return shape                                       # the common case, as given
    return tuple(int(s) for s in np.atleast_1d(shape)) if shape != () else ()


def as_written(value: Any):
    """A value as a user would have written it in YAML, for messages: whole numbers without
    '.0', lists as lists, None as null, booleans as true/false."""
    if value is None:
        return "null"
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value)
    try:
        arr = np.asarray(value, dtype=float)
    except (ValueError, TypeError):
        return repr(value)
    if (np.all(np.isfinite(arr)) and np.all(arr == np.floor(arr))
            and np.all(np.abs(arr) < 2.0 ** 53)):
        return str(arr.astype(np.int64).tolist())
    return str(arr.tolist())


def coerce(block: str, key: str, decl: Param, value: Any) -> Any:
    """Check and convert an (already expression-evaluated) parameter value."""
    def bad(expected: str):
        return ParameterError(
            f"block '{block}' parameter '{key}' must be {expected}, got {as_written(value)}"[:300],
            block=block)

    kind = decl.kind
    if kind == "any":
        return value
    if kind in ("str", "file"):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if kind == "names":
        if value is None:
            return None
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise bad("a list of names")
        return tuple(value)
    if kind == "choice":
        if value not in decl.choices:
            raise ParameterError(
                f"block '{block}' parameter '{key}' must be one of "
                f"{', '.join(map(str, decl.choices))}, got {as_written(value)}", block=block)
        return value
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise bad("true or false")
        return bool(value)
    if isinstance(value, (str, bool)) or value is None:
        raise bad("a number" if kind in ("float", "int") else "a number or array")
    try:
        arr = np.asarray(value, dtype=float)
    except (ValueError, TypeError):
        raise bad("a number or a rectangular array of numbers") from None
    if not (math.isfinite(arr) if arr.ndim == 0 else np.isfinite(arr).all()):
        raise bad("finite")
    if kind == "float":
        if arr.ndim != 0:
            raise bad("a single number")
        return float(arr)
    if kind == "int":
        if arr.ndim != 0 or arr != math.floor(arr):
            raise bad("a whole number")
        return int(arr)
    if kind == "array":
        return arr
    raise ValueError(f"unknown parameter kind {kind!r}")  # programming error
