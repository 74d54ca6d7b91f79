"""The compiled backend's side of ``simulate``: the same procedure, run in compiled chunks.

``fwdstep.run.simulate`` loads this module by name when a run asks for ``backend: compiled``
(the run layer never imports the compiled layer); divergence, interrupts and the final record
are ``fwdstep.run.outcome``'s.  Zero crossings are watched by the compiled loop and located
by ``fwdstep.run.crossings`` (one step on the NumPy path each time one happens).
"""
from __future__ import annotations

import time as _time

import numpy as np

from fwdstep.core import signals
from fwdstep.core.errors import ConfigError
from fwdstep.run import finite
from fwdstep.run import crossings
from fwdstep.run.backend import Backend
from fwdstep.run.crossings import crossing_steps
from fwdstep.run.evaluate import _make_evaluator
from fwdstep.run.events import apply_updates
from fwdstep.run.outcome import _divergence_message, _rows_recorded
from fwdstep.run.program import build_program
from fwdstep.structure.compiler import CompiledDiagram


#: False: run object-mode blocks inside the compiled loop even when compiling cannot help
#: (for tests of that machinery, fwdstep.run.python_blocks)
PICK_NUMPY_FOR_OBJECT_MODE = True


def numpy_instead(d: CompiledDiagram) -> str | None:
    """Why compiling cannot help ``d`` (its stage does not trace and the loop would call
    object-mode blocks, ``backend_numba.object_mode_only``): the run then takes the NumPy
    path; None to compile.  A block the compiled backend refuses is refused here."""
    try:
        from fwdstep.compiled import backend_numba
    except ImportError:
        raise ConfigError("backend 'compiled' needs numba: pip install 'fwdstep[fast]' (or use "
                          "backend 'numpy')", file=d.file) from None
    if not PICK_NUMPY_FOR_OBJECT_MODE:
        return None
    backend_numba.check_compilable(d)
    reason = backend_numba.object_mode_only(d)
    if reason is None and crossing_steps(d):
        reason = backend_numba.guards_unwatched(d)
    return reason


#: the shortest chunk of a batch whose crossings come close together
MIN_SPAN = 16


class CompiledBackend(Backend):
    """The numba backend of the run loop (``fwdstep.run.simulate.run``): the same
    procedure, run in compiled chunks of ``backend_numba.CHUNK`` steps on the same step grid
    (``plan_events``); discrete updates are applied here, between the chunks the loop ends
    at them (status 3, ``backend_numba.event_arrays``).  A batch runs its variants in
    parallel, each on its own row of the state, each stopping where it fails.  Zero
    crossings: the loop returns each step that crosses (status 4), which the NumPy path's
    locating code takes (``_advance_watched``).  ``stage``:
    a scalar stage integrating more than x (``backend_numba.build_program``); ``x`` is then
    the view of the diagram's entries of the integrated state ``prog.xn``."""

    scan_log = False

    def __init__(self, d: CompiledDiagram, plan, on_compile=None, stage=None):
        super().__init__(d, plan)
        try:
            from fwdstep.compiled import backend_numba
        except ImportError:
            raise ConfigError("backend 'compiled' needs numba: pip install 'fwdstep[fast]' "
                              "(or use backend 'numpy')", file=d.file) from None
        self.numba = backend_numba
        cfg = d.spec.simulation
        self.h, self.n_steps, self.bound = cfg.step, cfg.n_steps, cfg.bound
        n_rows = self.n_steps // cfg.log_every + 1 + (1 if self.n_steps % cfg.log_every else 0)
        self.on_compile, self.announced = on_compile, []

        def notify(what, operations, estimate):
            self.announced.append(_time.perf_counter())
            if on_compile is not None:
                on_compile("compiling", {"diagram": d.file, "what": what,
                                         "operations": operations, "estimate_s": estimate})

        self.prog = prog = backend_numba.build_program(d, n_rows, plan, notify=notify,
                                                       stage=stage)
        B = d.batch
        self.x = prog.xn[:, :d.n_states]      # (B, N); each variant runs on its own row
        self.x[...] = d.x0
        self.t_log, self.logs = prog.t_log, prog.logs
        self.rows, self.codes, self.n_next = (np.zeros(B, dtype=np.int64) for _ in range(3))
        self.position = 0                     # the next step to take
        self.sample = None
        # zero crossings: the loop watches the guards and returns the steps that cross (or
        # touch a declared time) to the NumPy path's machinery, which takes them (one
        # definition of locating: fwdstep.run.crossings); ``whole``: every step there
        self.watched, self._numpy, self.whole = bool(crossing_steps(d)), None, False
        self.span = backend_numba.CHUNK       # steps of a batch's next chunk (watched)
        if self.watched and prog.guards is None:      # (an LLVM fault left the array code)
            self.whole = True
            self.t_log, self.logs = self.numpy.t_log, self.numpy.logs

    @property
    def numpy(self):
        """The NumPy path's backend that takes the steps which cross (made on first use:
        a run whose guards never cross does not generate its program)."""
        if self._numpy is None:
            from fwdstep.run.numpy_backend import NumpyBackend
            self._numpy = NumpyBackend(self.d, self.plan)
        return self._numpy

    def start(self, x0) -> None:
        """Compile (the run loop checked every block's shapes on the NumPy path first: a
        block that raises or returns a wrong shape is named, not left to numba)."""
        with signals.deferred():              # a signal during numba's compile is acted on
            _compile(self.prog, self.d)       # after it (raised inside numba's callbacks it
        late = signals.pending()              # was swallowed and broke the function)
        if late is not None:
            raise late
        if self.announced and self.on_compile is not None:
            self.on_compile("compiled", {"seconds": _time.perf_counter() - self.announced[0]})
        self.x[...] = x0
        if self.whole:
            self.numpy.x[...] = x0
        if self.plan is not None and self.plan.discrete:
            self.sample = _sampler(self.d, self.plan, self.x)

    def update(self, event, ts: float) -> None:
        if self.whole:                        # the NumPy path holds the state
            self.numpy.update(event, ts)
            return
        apply_updates(event, ts, self.x, self.sample)

    def advance(self, out) -> None:
        if self.whole:
            return self._numpy_whole(out)
        if self.watched:
            return self._advance_watched(out)
        self._advance(out, self.position, min(self.position + self.numba.CHUNK, self.n_steps))

    def _advance(self, out, n: int, n1: int) -> bool:
        """The compiled loop from step n to n1 (each variant; status 4: see
        ``_advance_watched``).  False: the run ended (every variant failed)."""
        prog, x, h, alive = self.prog, self.x, self.h, out.alive
        rows, codes, n_next = self.rows, self.codes, self.n_next
        B = self.d.batch
        self.cross_at = None
        with signals.held():      # a signal during the chunk ends the run after its rows
            if B == 1:            # are counted (Python raised it the moment the chunk returned)
                codes[0], n_next[0], rows[0] = prog.run(n, n1, int(rows[0]))
            else:                             # variants in parallel (numba prange)
                if self.watched:
                    kept = (prog.xn.copy(), rows.copy(), *(a.copy() for a in prog.guards))
                prog.run_batch(n, n1, rows, codes, n_next, alive.copy())
            four = (codes == 4) & alive
            if four.any():                    # a step to take on the NumPy path
                m = int(n_next[four].min())
                if B > 1 and ((n_next > m) & alive).any():
                    # others ran past it: every variant again from n to m (the same
                    # numbers; a failure after m is not one yet)
                    prog.xn[...], rows[...] = kept[0], kept[1]
                    for a, b in zip(prog.guards, kept[2:]):
                        a[...] = b
                    prog.run_batch(n, m, rows, codes, n_next, alive.copy())
                codes[four] = 0
                n1 = self.cross_at = m
            paused = (codes == 3) & alive     # discrete blocks update before a sub-step:
            if paused.any():                  # all alive variants stop at that row
                q = int(prog.events[3][np.flatnonzero(paused)[0]])
                a, lo = prog.events[2][q, 0], prog.events[2][q, 2]
                self.update(prog.row_events[q], max(a, lo))
                codes[paused] = 0
                n1 = int(n_next[paused][0])   # go on from that step (and row)
            newly = (codes != 0) & alive
            if newly.any():                   # status 1: t + h of the failing step,
                d, bound = self.d, self.bound     # status 2: t of the record
                if out.variants_failed(newly, n_next[newly] * h, lambda b: (
                        _compiled_output_failure(d, out.died_at[b], x, b, alone=True)[0]
                        if codes[b] == 2
                        else _divergence_message(d, x, bound, out.died_at[b], b))):
                    last = int(np.argmax(n_next))
                    self.n = int(n_next.max()) - 1
                    self.t = self.n * h
                    self.row = int(rows.max())
                    if codes[last] == 2:          # an unrecorded output not finite
                        self.t = float(n_next[last] * h)
                        message, blamed = _compiled_output_failure(d, self.t, x, last)
                        out.stop("diverged", message, blamed=blamed)
                    else:
                        out.stop("diverged", _divergence_message(d, x, bound, self.t + h),
                                 blamed=x, time=self.t + h)
                    return False
            self.position = self.n = n1
            self.t = n1 * h
            self.row = int(rows.max())
            self.done = n1 >= self.n_steps
            self.fraction = n1 / max(self.n_steps, 1)
        return True

    def _advance_watched(self, out) -> None:
        """A chunk of a diagram with zero crossings: the compiled loop up to the first step
        that crosses (status 4, the state back at its start), that step on the NumPy path
        (``fwdstep.run.crossings.advance``: located, ``crossed``, events, Stop, chattering,
        on the same state and record), then the loop again.  A batch's variants go in
        step: when one returns a step m the others ran past, every variant runs again
        from the chunk's start to m (the same numbers), and step m is taken for all."""
        alive = out.alive
        n0 = self.position
        span = self.span if self.d.batch > 1 else self.numba.CHUNK
        if not self._advance(out, n0, min(n0 + span, self.n_steps)):
            return
        # a batch's chunk follows the crossings' pace: the steps run past the earliest
        # crossing are run again, so at most about the distance between crossings
        m = self.cross_at
        self.span = (min(2 * span, self.numba.CHUNK) if m is None
                     else max(MIN_SPAN, 2 * (m - n0 + 1)))
        row = int(self.rows[alive].max())
        if not alive.all():                   # a variant failed: the NumPy path goes on
            self._to_numpy(out, self.position, row)
        elif self.cross_at is not None:
            self._numpy_step(out, self.cross_at, row)

    def _numpy_step(self, out, m: int, row: int) -> None:
        """Step m (state x_m, its record at ``row``) taken by the NumPy path's crossing
        machinery; its rows copied into the compiled record; the loop resumes after it."""
        nb, x = self.numpy, self.x
        nb.x[...] = x
        nb.position, nb.row, nb.fresh, nb.chunk = m, row, None, 1
        crossings.advance(nb, out)
        _copy_rows(nb, self, row, nb.row)
        x[...] = nb.x
        self.n, self.t = m, m * self.h
        if not out.running:                   # a Stop: its record is the last
            self.row = nb.row
            return
        if not nb.crossings.simple:           # chattering: its regime follows at steps
            self._to_numpy(out, m + 1, nb.row, keep=True)
            return
        # the end pass's record of step m + 1 (if any) is made again by the loop
        end = nb.row - (1 if nb.fresh is not None and nb.fresh[1] >= 0 else 0)
        self.rows[out.alive] = end
        self.row = end
        self.prog.guards[2][:, 0] = 0         # the loop's reference signs: from m + 1
        self.position = m + 1
        self.done = self.position >= self.n_steps
        self.fraction = self.position / max(self.n_steps, 1)

    def _to_numpy(self, out, position: int, row: int, keep: bool = False) -> None:
        """From step ``position`` on, the NumPy path runs every step (chattering, or a
        variant of a batch failed: its crossings then follow ``fwdstep.run.crossings``'s
        general procedure); the record so far moves to it.  ``keep``: it just took the
        step before (its end pass stands)."""
        nb = self.numpy
        alive = out.alive
        if not keep:
            nb.x[...] = self.x
            special = self.plan.steps if self.plan is not None else {}
            _, XS, GI = self.prog.guards
            if position in special and (GI[alive, 0] == 1).all():
                # it starts one step earlier (kept by the loop: XS, its row), so that
                # step's end leaves the signs the declared time's jumps are checked with
                position -= 1
                nb.x[alive] = XS[alive, :self.d.n_states]
                row = int(GI[alive, 1].max())
            _copy_rows(self, nb, 0, row)
            nb.position, nb.row, nb.fresh = position, row, None
        else:
            _copy_rows(self, nb, 0, row)
        nb.x[~alive] = 0.0
        nb.crossings.active[~alive] = False
        if not alive.all():
            nb.crossings.simple = False
        nb.chunk = type(nb).chunk
        self.t_log, self.logs = nb.t_log, nb.logs
        self.whole = True
        self.position = position
        self.done = position >= self.n_steps

    def _numpy_whole(self, out) -> None:
        nb = self.numpy
        nb.advance(out)
        self.row, self.n, self.t = nb.row, nb.n, nb.t
        self.done, self.fraction = nb.done, nb.fraction

    def final_record(self, t: float, ts: float, out) -> None:
        """Each alive variant's outputs at t and their record (the event rows of the
        compiled loop give its stage time ts)."""
        if self.whole:
            self.numpy.final_record(t, ts, out)
            self.row, self.n = self.numpy.row, self.numpy.n
            return
        d, x, alive = self.d, self.x, out.alive
        last = 0
        for v in np.flatnonzero(alive):
            if self.prog.final(t, int(self.rows[v]), int(v)) == 2:   # an output not finite
                last = int(v)
                out.variants_failed([last], t, lambda b: _compiled_output_failure(
                    d, t, x, b, True)[0])
        self.row = int(self.rows.max()) + 1
        self.n = self.n_steps - 1
        if not alive.any():
            message, blamed = _compiled_output_failure(d, t, x, last)
            out.stop("diverged", message, blamed=blamed)

    def after_error(self) -> None:
        if self.whole:
            self.row = self.numpy.row
            return
        self.row = _rows_recorded(self.prog.t_log, self.rows, self.row)

    def close(self) -> None:
        self.prog.seal()


def _copy_rows(src, dst, r0: int, r1: int) -> None:
    """Rows r0..r1-1 of one backend's record into another's (times and logged signals)."""
    if r1 > r0:
        dst.t_log[r0:r1] = src.t_log[r0:r1]
        for a, b in zip(dst.logs, src.logs):
            a[r0:r1] = b[r0:r1]


def _compile(prog, d: CompiledDiagram) -> None:
    """``prog.compile()``; numba's refusal of a kernel (a construct it cannot type) becomes
    one line naming the block, the kernel and numba's reason, with the way out."""
    try:
        prog.compile()
    except Exception as exc:
        if not type(exc).__module__.startswith("numba"):
            raise
        raise ConfigError(_numba_refusal(d, exc), file=d.file) from None


def _numba_refusal(d: CompiledDiagram, exc) -> str:
    import re
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc))
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    reason = next((ln for ln in lines if not ln.startswith(("Failed in", "During:", "File ",
                                                            "^", "- ", "Resolution failure"))
                   and "pipeline" not in ln), lines[0] if lines else type(exc).__name__)
    named = set(re.findall(r"<function ([\w.<>]+) at ", text))
    who = ""
    for step in d.schedule:
        k = step.block.kernels
        fns = [f for f in ((k.output, k.derivative) if k is not None else ()) if f is not None]
        hit = [f.__qualname__ for f in fns if f.__qualname__ in named]
        if hit:
            who = (f"block '{step.block.name}' ({step.block.type_name}): kernel "
                   f"{hit[0]} ")
            break
    return (f"{who or 'a kernel '}cannot be compiled by numba ({type(exc).__name__}: "
            f"{reason})"[:400] + "; run the diagram with backend numpy")


def _sampler(d: CompiledDiagram, events, x):
    """``evaluate(ts)`` for ``apply_updates`` in a compiled run: the signals discrete blocks
    read, at (ts, x), from the NumPy path's generated output pass (``program.sample_signals``;
    updates are rare next to steps)."""
    numpy_prog = build_program(d, 1, sampled=tuple(events.sampled_signals))

    def evaluate(ts):
        numpy_prog.xn[...] = x
        return numpy_prog.sample_signals(ts)

    return evaluate


def _compiled_output_failure(d: CompiledDiagram, t: float, x, b: int,
                             alone: bool = False) -> tuple:
    """(message, blamed block) for variant ``b`` whose compiled run found an unrecorded
    output not finite at its record of time ``t`` (state ``x``, before that step): the
    outputs are evaluated again at (t, x) on the NumPy path to name block and port."""
    _, outputs, sig = _make_evaluator(d)
    with np.errstate(all="ignore"):
        outputs(t, x)
    values = [(i, np.asarray(v)[min(b, np.shape(v)[0] - 1)]) for i, v in enumerate(sig)
              if v is not None and i not in d.constant_signals]
    if all(np.isfinite(v).all() for _, v in values):      # not reproduced: say so
        return (f"simulation diverged at t = {t:.6g}: a block output is not finite"
                + (f" (variant {b})" if d.batch > 1 and not alone else "")
                + "; results up to that time are kept"), ""
    name, value = finite.blame(d, values)
    return finite.message(d, t, name, value, b, alone), name.rsplit(".", 1)[0]
