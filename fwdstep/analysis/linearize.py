"""Linear analysis of a loaded diagram: linearisation at a point or along a run, analysis
points, loop opening, frequency response, poles, zeros and stability margins.

``linearize(d, inputs=[...], outputs=[...], t=T)`` returns the ``LinearModel``

    dx/dt = A dx + B w,    y = C dx + D w

of the diagram about its state at time T (taken from a run of the diagram up to T, or
given as ``x``), where

* each *input* names a signal ``BLOCK.PORT`` (or one element of it, ``BLOCK.PORT[i]``) that
  becomes ``signal + w`` for every block reading it: an additive perturbation at an analysis
  point, the loop is not cut;
* each *output* is a signal as its readers see it (with that perturbation, when it is also an
  input: input and output at the same point give the sensitivity (I + L)^-1);
* ``open=SIGNAL`` (or a list) cuts the loop there: the readers of the signal see its value at
  the operating point (plus ``w`` if it is an input), an output there measures the value the
  producing block computes.  With ``open=S, inputs=[S], outputs=[S]`` the model is the
  transfer from the cut's downstream side around the loop back to its upstream side,
  G = -L in the negative-feedback convention (closing the cut is y = w): ``margins()``
  uses L = -G by default.

The chain rule follows the compiled diagram's schedule: each signal's derivative with
respect to (x, w) is its producer's Jacobian (``fwdstep.analysis.jacobian``: from the block's one
definition) applied to the derivatives of the producer's inputs, in evaluation order;
the state derivative rows follow the same way.  Discrete states (sample-and-hold, unit
delays) are frozen: their rows of A are zero (poles at 0).  The time-varying robot loops are
linearised at frozen time (``linearize_along``: at N times of one run).
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field

import numpy as np

from fwdstep.core.errors import ConfigError
from fwdstep.analysis.jacobian import BlockJacobian


# ---------------------------------------------------------------------- the model
@dataclass
class LinearModel:
    """A, B, C, D of a diagram linearised at time ``t`` about state ``x``.

    ``state_names``: "BLOCK.LABEL" per state (the block's state labels, else x0, x1, ...);
    ``input_names`` / ``output_names``: "BLOCK.PORT" or "BLOCK.PORT[i]" per column / row.
    ``opened``: the signals where the loop was cut."""
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    state_names: list
    input_names: list
    output_names: list
    t: float = 0.0
    x: np.ndarray = field(default=None, repr=False)
    opened: list = field(default_factory=list)
    methods: dict = field(default_factory=dict, repr=False)   # block -> Jacobian method

    # conversions -------------------------------------------------------------------
    def to_scipy(self):
        """``scipy.signal.StateSpace``."""
        from scipy import signal
        return signal.StateSpace(self.A, self.B, self.C, self.D)

    def to_control(self):
        """python-control ``StateSpace`` with the signal and state names (optional extra
        ``fwdstep[analysis]``); python-control reserves '.' in names, so "BLOCK.PORT"
        becomes "BLOCK:PORT"."""
        try:
            import control
        except ImportError:
            raise ConfigError("to_control needs python-control: pip install "
                              "'fwdstep[analysis]' (or 'control>=0.10')") from None
        def names(v):
            return [n.replace(".", ":") for n in v]
        return control.ss(self.A, self.B, self.C, self.D, inputs=names(self.input_names),
                          outputs=names(self.output_names), states=names(self.state_names))

    # analysis ----------------------------------------------------------------------
    def poles(self) -> np.ndarray:
        """Eigenvalues of A (every state of the diagram: also those the chosen inputs or
        outputs do not see)."""
        return np.linalg.eigvals(self.A) if self.A.size else np.zeros(0, complex)

    def zeros(self) -> np.ndarray:
        """Invariant zeros of a square system: the finite generalized eigenvalues of the
        Rosenbrock pencil ([A B; C D], [I 0; 0 0]).  They include the decoupling zeros of
        states the inputs cannot move or the outputs cannot see (each cancels a pole)."""
        p, m = self.D.shape
        if p != m:
            raise ConfigError(f"zeros are computed for square systems; this one has {m} "
                              f"inputs and {p} outputs")
        from scipy.linalg import eigvals
        n = self.A.shape[0]
        M = np.block([[self.A, self.B], [self.C, self.D]])
        E = np.zeros_like(M)
        E[:n, :n] = np.eye(n)
        with np.errstate(all="ignore"):
            z = eigvals(M, E)
        finite = np.isfinite(z) & (np.abs(z) < 1e10 * max(1.0, np.abs(M).max()))
        return z[finite]

    def frequency_response(self, w) -> np.ndarray:
        """H(jw) = C (jw I - A)^-1 B + D at the angular frequencies ``w`` (rad/s):
        (len(w), outputs, inputs), complex."""
        w = np.atleast_1d(np.asarray(w, dtype=float))
        n = self.A.shape[0]
        out = np.empty((len(w),) + self.D.shape, dtype=complex)
        eye = np.eye(n)
        for k, wk in enumerate(w):
            if n:
                out[k] = self.C @ np.linalg.solve(1j * wk * eye - self.A, self.B) + self.D
            else:
                out[k] = self.D
        return out

    def margins(self, sign: float = -1.0, w=None) -> dict:
        """Gain and phase margins of the SISO loop L = sign * G (G this model; sign -1:
        the model is a loop opened at a signal, whose closing is positive feedback, so
        1 + L is the return difference).  Crossings are bracketed on a log grid
        (``frequency_grid``, or ``w``) and refined with Brent's method: a gain margin is
        1/|L| where L crosses the negative real axis (Im L = 0, Re L < 0), a phase margin
        180 deg + angle L (in (-180, 180]) where |L| = 1.  Every crossing is listed
        (``gain_margins``: [(w, margin in dB)], ``phase_margins``: [(w, deg)]); the headline
        values are the most critical ones (the gain margin closest to 0 dB, the phase margin
        smallest in magnitude), inf when there is no crossing."""
        if self.D.shape != (1, 1):
            raise ConfigError(f"margins need one input and one output; the model has "
                              f"{self.D.shape[1]} inputs and {self.D.shape[0]} outputs")
        from scipy.optimize import brentq
        w = self.frequency_grid() if w is None else np.asarray(w, dtype=float)

        def L(wk):
            return sign * self.frequency_response([wk])[0, 0, 0]

        values = np.array([L(wk) for wk in w])
        gains, phases = [], []
        im = values.imag
        for k in np.flatnonzero(np.sign(im[:-1]) * np.sign(im[1:]) < 0):
            wc = brentq(lambda v: L(v).imag, w[k], w[k + 1], xtol=1e-300, rtol=1e-13)
            Lc = L(wc)
            if Lc.real < 0:
                gains.append((float(wc), float(-20 * np.log10(abs(Lc)))))
        with np.errstate(divide="ignore"):
            mag = np.log(np.abs(values))
        for k in np.flatnonzero(np.sign(mag[:-1]) * np.sign(mag[1:]) < 0):
            wc = brentq(lambda v: np.log(abs(L(v))), w[k], w[k + 1], xtol=1e-300,
                        rtol=1e-13)
            phase = np.degrees(np.angle(L(wc)))
            phases.append((float(wc), float((phase + 360.0) % 360.0 - 180.0)))
        out = {"gain_margin": np.inf, "gain_margin_db": np.inf, "phase_crossover": np.nan,
               "phase_margin_deg": np.inf, "gain_crossover": np.nan, "sign": sign,
               "gain_margins": gains, "phase_margins": phases}
        if gains:
            wc, db = min(gains, key=lambda g: abs(g[1]))
            out.update(gain_margin=10 ** (db / 20), gain_margin_db=db, phase_crossover=wc)
        if phases:
            wc, pm = min(phases, key=lambda g: abs(g[1]))
            out.update(phase_margin_deg=pm, gain_crossover=wc)
        return out

    def frequency_grid(self, n: int = 2000, decades: float = 2.0) -> np.ndarray:
        """A log grid of angular frequencies spanning the poles and zeros (``decades``
        below the slowest nonzero one to ``decades`` above the fastest)."""
        marks = np.abs(self.poles())
        try:
            marks = np.concatenate([marks, np.abs(self.zeros())])
        except ConfigError:
            pass
        marks = marks[np.isfinite(marks)]
        if marks.size:      # near-zero poles (adaptation, integrators) set no range
            marks = marks[marks > 1e-5 * marks.max()]
        lo, hi = (marks.min(), marks.max()) if marks.size else (1.0, 1.0)
        return np.logspace(np.log10(lo) - decades, np.log10(hi) + decades, n)

    def to_dict(self) -> dict:
        """Everything as JSON-ready lists (complex numbers as [re, im])."""
        def cx(v):
            return [[float(z.real), float(z.imag)] for z in v]
        out = {"t": self.t, "A": self.A.tolist(), "B": self.B.tolist(), "C": self.C.tolist(),
               "D": self.D.tolist(), "states": list(self.state_names),
               "inputs": list(self.input_names), "outputs": list(self.output_names),
               "opened": list(self.opened), "x": np.asarray(self.x).reshape(-1).tolist(),
               "poles": cx(self.poles()), "jacobian_methods": dict(self.methods)}
        try:
            out["zeros"] = cx(self.zeros())
        except ConfigError:
            out["zeros"] = None
        return out


# ---------------------------------------------------------------------- signals
_ELEMENT = re.compile(r"^(?P<name>[^\[\]]+?)(?:\[(?P<index>[0-9,\s]+)\])?$")


@dataclass
class _Point:
    text: str
    index: int                 # signal index of the compiled diagram
    elements: np.ndarray       # flat element indices


def _point(d, text: str, what: str) -> _Point:
    """'BLOCK.PORT' or 'BLOCK.PORT[i]' / '[i, j]' -> signal index and elements."""
    m = _ELEMENT.match(text.strip())
    name = m.group("name").strip() if m else text
    real = d.resolve(name)
    if not m or real not in d.signal_index:
        blk = real.rsplit(".", 1)[0]
        ports = [n.rsplit(".", 1)[1] for n in d.signal_index if n.rsplit(".", 1)[0] == blk]
        hint = (f"; block '{blk}' has outputs: {', '.join(ports)}" if ports else
                f"; signals are: {', '.join(list(d.signal_index)[:40])}")
        raise ConfigError(f"{what} '{text}' is not a signal of the diagram{hint}",
                          file=d.file)
    idx = d.signal_index[real]
    shape = tuple(d.signal_shapes[idx])
    size = int(np.prod(shape, dtype=np.int64))
    if m.group("index") is None:
        return _Point(text, idx, np.arange(size))
    where = tuple(int(v) for v in m.group("index").split(","))
    if len(where) != len(shape) or any(not 0 <= i < s for i, s in zip(where, shape)):
        raise ConfigError(f"{what} '{text}': index {list(where)} is outside the signal's "
                          f"shape {list(shape)}", file=d.file)
    return _Point(text, idx, np.array([np.ravel_multi_index(where, shape)]))


def _element_names(d, p: _Point) -> list:
    shape = tuple(d.signal_shapes[p.index])
    name = d.signal_names[p.index]
    if len(p.elements) == 1 and shape == ():
        return [name]
    return [f"{name}[{','.join(str(i) for i in np.unravel_index(e, shape))}]"
            for e in p.elements]


def state_names(d) -> list:
    names = [""] * d.n_states
    for step in d.stateful:
        blk = step.block
        labels = blk.state_labels or []
        for i in range(blk.n_states):
            label = labels[i] if i < len(labels) else f"x{i}"
            names[step.state.start + i] = f"{blk.name}.{label}"
    return names


# ---------------------------------------------------------------------- the linearizer
class DiagramLinearizer:
    """The Jacobians of a compiled diagram's blocks (built once) and the chain rule over its
    schedule; ``at(t, x)`` gives a ``LinearModel``.  Reused by ``linearize_along`` (and by
    issue 28's sensitivities: ``jacobians`` holds each block's ``BlockJacobian``)."""

    def __init__(self, d, inputs=(), outputs=(), open=None):
        if d.batch != 1:
            raise ConfigError("linearize takes a single diagram, not a batch", file=d.file)
        self.d = d
        self.inputs = [_point(d, s, "input") for s in _as_list(inputs)]
        self.outputs = [_point(d, s, "output") for s in _as_list(outputs)]
        self.opened = [_point(d, s, "open") for s in _as_list(open)]
        self.jacobians = {step.block.name: BlockJacobian(step.block) for step in d.schedule}
        self.input_names = [n for p in self.inputs for n in _element_names(d, p)]
        self.output_names = [n for p in self.outputs for n in _element_names(d, p)]
        self.state_names = state_names(d)

    def at(self, t: float, x) -> LinearModel:
        from fwdstep.run.evaluate import _make_evaluator
        d = self.d
        N = d.n_states
        x = np.asarray(x, dtype=float).reshape(1, N)
        _, outputs, sig = _make_evaluator(d)
        with np.errstate(all="ignore"):
            outputs(t, x)
        m = len(self.input_names)
        width = N + m
        perturb: dict = {}          # signal -> [(element, column)]
        c = N
        for p in self.inputs:
            for e in p.elements:
                perturb.setdefault(p.index, []).append((int(e), c))
                c += 1
        cut = {}
        for p in self.opened:
            cut.setdefault(p.index, set()).update(int(e) for e in p.elements)
        G: dict = {idx: np.zeros((int(np.prod(d.signal_shapes[idx], dtype=np.int64)), width))
                   for idx in d.constant_signals}
        upstream: dict = {}
        rows = np.zeros((N, width))
        derivatives = []
        empty = slice(0, 0)
        for step in d.schedule:
            blk = step.block
            bj = self.jacobians[blk.name]
            sl = step.state if step.state is not None else empty
            u = tuple(sig[i] for i in step.inputs)
            J = bj.at(t, x[:, sl], u).J[0]
            in_names = list(blk.inputs)
            for k, (port, out) in enumerate(zip(blk.outputs, step.outputs)):
                r = bj.rows[f"y.{port}"]
                g = np.zeros((r.stop - r.start, width))
                if blk.n_states:
                    g[:, sl] = J[r, bj.columns["x"]]
                for j, src in enumerate(step.inputs):
                    part = J[r, bj.columns[f"u.{in_names[j]}"]]
                    if part.any():
                        g += part @ self._needed(G, src, blk, in_names[j])
                if out in cut:
                    upstream[out] = g.copy()
                    g[sorted(cut[out])] = 0.0
                for e, col in perturb.get(out, ()):
                    g[e, col] += 1.0
                G[out] = g
            if blk.n_states:
                derivatives.append((step, bj, J))
        for step, bj, J in derivatives:          # after every output, as in a stage
            blk, sl = step.block, step.state
            in_names = list(blk.inputs)
            r = bj.rows["dx"]
            rows[sl, sl] = J[r, bj.columns["x"]]
            for j, src in enumerate(step.inputs):
                part = J[r, bj.columns[f"u.{in_names[j]}"]]
                if part.any():
                    rows[sl] += part @ self._needed(G, src, blk, in_names[j])
        out_rows = []
        for p in self.outputs:
            g = G[p.index].copy()
            if p.index in upstream:
                cut_here = sorted(cut[p.index])
                g[cut_here] = upstream[p.index][cut_here]
            out_rows.append(g[p.elements])
        Y = np.vstack(out_rows) if out_rows else np.zeros((0, width))
        return LinearModel(A=rows[:, :N], B=rows[:, N:], C=Y[:, :N], D=Y[:, N:],
                           state_names=list(self.state_names),
                           input_names=list(self.input_names),
                           output_names=list(self.output_names), t=float(t), x=x[0].copy(),
                           opened=[p.text for p in self.opened],
                           methods={k: v.method for k, v in self.jacobians.items()})

    def _needed(self, G, src, blk, port):
        g = G.get(src)
        if g is None:           # read before it is computed: only outside feedthrough
            raise ConfigError(f"block '{blk.name}' input '{port}' is read before "
                              f"'{self.d.signal_names[src]}' is computed (feedthrough "
                              "declaration and kernel disagree)", file=self.d.file)
        return g


def _as_list(v) -> list:
    if v is None:
        return []
    return [v] if isinstance(v, str) else list(v)


# ---------------------------------------------------------------------- states from a run
def _until(d, t_final: float):
    """A copy of ``d`` whose run ends at ``t_final`` (on the step grid)."""
    cfg = d.spec.simulation
    spec = dataclasses.replace(d.spec, simulation=dataclasses.replace(cfg, t_final=t_final))
    return dataclasses.replace(d, spec=spec)


def run_states(d, t_final: float | None = None):
    """(times, states (rows, n_states)) of a run of ``d`` (numpy backend) up to ``t_final``
    (default: the diagram's), recorded at its log times."""
    from fwdstep.run.simulate import simulate
    if t_final is not None:
        if t_final < 0 or t_final > 1e9:
            raise ConfigError(f"linearisation time {t_final:g} is outside [0, 1e9]",
                              file=d.file)
        d = _until(d, t_final)
    r = simulate(d, backend="numpy", record_states=True)
    return r.t, r.states[:, 0, :]


def state_at(d, t: float) -> tuple:
    """(t actually reached, x) of a run of the diagram up to ``t`` (the step grid's nearest
    time; t = 0 needs no run: the initial state, with input-dependent blocks initialised)."""
    from fwdstep.run.evaluate import initial_state
    if t == 0:
        return 0.0, initial_state(d)[0]
    times, states = run_states(d, t)
    return float(times[-1]), states[-1]


def linearize(d, inputs=(), outputs=(), t: float = 0.0, x=None, open=None) -> LinearModel:
    """The ``LinearModel`` of compiled diagram ``d`` (``fwdstep.load_diagram``) at time
    ``t``: ``inputs`` and ``outputs`` are signals ("BLOCK.PORT" or "BLOCK.PORT[i]"), the
    state is ``x`` or that of a run of ``d`` up to ``t``; ``open``: signal(s) where the loop
    is cut.  See the module docstring."""
    lin = DiagramLinearizer(d, inputs, outputs, open)
    if x is None:
        t, x = state_at(d, float(t))
    else:
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.size != d.n_states:
            raise ConfigError(f"x has {x.size} values; the diagram has {d.n_states} states",
                              file=d.file)
    return lin.at(float(t), x)


def linearize_along(d, inputs=(), outputs=(), n: int = 20, times=None,
                    open=None) -> list:
    """Frozen-time linearisations at ``n`` evenly spaced recorded times of one run of ``d``
    (or at the recorded times nearest to ``times``): a list of ``LinearModel``."""
    lin = DiagramLinearizer(d, inputs, outputs, open)
    t_log, states = run_states(d)
    if times is None:
        rows = np.unique(np.linspace(0, len(t_log) - 1, max(1, int(n))).round().astype(int))
    else:
        rows = np.unique([int(np.argmin(np.abs(t_log - tk))) for tk in np.atleast_1d(times)])
    return [lin.at(float(t_log[k]), states[k]) for k in rows]


__all__ = ["LinearModel", "DiagramLinearizer", "linearize", "linearize_along", "state_at",
           "run_states", "state_names"]
