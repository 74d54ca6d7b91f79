"""What the command-line verbs do (``cli.py`` only parses arguments and calls these).

Every verb returns an exit code:
  0 success; 2 the diagram, an option or the output directory is wrong (one line on stderr);
  3 the simulation diverged; 4 a block raised at run time; 5 the run stopped at an operating
  limit (``stop_on_limits``, fwdstep.run.limits); 128 + signal number when
  interrupted: 130 Ctrl-C (SIGINT), 143 SIGTERM, 129 SIGHUP (``fwdstep.core.signals``).
Partial results are written before a non-zero exit whenever anything was computed, as one
transaction into a locked output directory (``fwdstep.results.outputs``).
"""
from __future__ import annotations

import os
import sys

from fwdstep.core.errors import (BlockRuntimeError, DiagramError, DivergenceError, FwdstepError,
                     LimitExceeded, OutputError, SimulationError, one_line, printable)
from fwdstep.results.result import RESULT_FILE, SUMMARY_FILE

EXIT_OK, EXIT_INPUT, EXIT_DIVERGED, EXIT_BLOCK, EXIT_INTERRUPTED = 0, 2, 3, 4, 130
EXIT_LIMIT = 5


def _err(msg: str) -> None:
    print(f"fwdstep: {one_line(str(msg))}", file=sys.stderr)


def _overrides(pairs) -> dict:
    from fwdstep.structure.spec import parse_override
    out = {}
    for text in pairs or []:
        name, value = parse_override(text)
        out[name] = value
    return out


def default_outdir(path: str) -> str:
    return os.path.join("out", os.path.splitext(os.path.basename(path))[0])


def run_files(d, plots: bool, formats=("png",)) -> list:
    """Names of the files ``fwdstep run`` writes for compiled diagram ``d``."""
    from fwdstep.results.provenance import COPY_DIR
    names = [RESULT_FILE, SUMMARY_FILE, COPY_DIR]
    if plots:
        from fwdstep.results.plotting import figure_specs
        from fwdstep.results.result import Result
        import numpy as np
        names += [f"{fig}.{fmt}" for fig in figure_specs(Result(np.empty(0), {}, diagram=d))
                  for fmt in formats]
    return names


class Progress:
    """How far a run is, on stderr.  The simulation reports about once a second; on a
    terminal one line is rewritten in place, elsewhere (a log file, a pipe) a line is
    written at the first report (the run is going) and at each quarter after it.
    ``finish`` writes where the run ended (100 % when it reached t_final) once anything
    was shown."""

    QUARTERS = 4

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        try:
            self.live = self.stream.isatty()
        except (AttributeError, ValueError):
            self.live = False
        self.shown = -1                  # the last quarter written (not live)
        self.started = False

    def __call__(self, frac: float) -> None:
        frac = min(max(float(frac), 0.0), 1.0)
        if self.live:
            print(f"\r  {100 * frac:5.1f}% simulated", end="", file=self.stream, flush=True)
            self.started = True
            return
        quarter = int(frac * self.QUARTERS)
        if not self.started:
            self.started, self.shown = True, quarter
            print(f"  {100 * frac:5.1f}% simulated", file=self.stream, flush=True)
        elif 0 < quarter < self.QUARTERS and quarter > self.shown:
            self.shown = quarter
            self.started = True
            print(f"  {100 * quarter / self.QUARTERS:5.1f}% simulated", file=self.stream,
                  flush=True)

    def finish(self, frac: float) -> None:
        if not self.started:
            return
        frac = min(max(float(frac), 0.0), 1.0)
        print(f"{chr(13) if self.live else ''}  {100 * frac:5.1f}% simulated",
              file=self.stream, flush=True)


def _compile_news(event: str, info: dict) -> None:
    """The compiled backend's progress lines (``simulate(on_compile=...)``), on stderr."""
    if event == "compiling":
        name = os.path.basename(info["diagram"] or "") or "the diagram"
        unit = "scalar operations" if info["what"] == "scalar stage" else "block calls"
        print(f"fwdstep: compiling {name} for the compiled backend ({info['operations']} "
              f"{unit}, about {info['estimate_s']:.0f} s) ...", file=sys.stderr, flush=True)
    elif event == "compiled":
        print(f"fwdstep: compiled in {info['seconds']:.1f} s", file=sys.stderr, flush=True)
    elif event == "numpy":
        print(f"fwdstep: note: running the NumPy path: {info['reason']}, which compiling "
              "would not make faster", file=sys.stderr, flush=True)


def cmd_validate(path: str, sets=None) -> int:
    from fwdstep.core.budgets import check_log
    from fwdstep.structure.compiler import load_diagram
    try:
        d = load_diagram(path, _overrides(sets))
        check_log(d)                    # never ok for a run that cannot start
        from fwdstep.run.events import check_events
        check_events(d)                 # sample instants, discrete algebraic loops
    except DiagramError as exc:
        for each in [exc] + list(getattr(exc, "more", ())):   # every mistake found, one line each
            _err(str(each))
        return EXIT_INPUT
    print(f"{printable(path)}: ok — {len(d.schedule)} blocks, {d.n_states} states, "
          f"{len(d.signal_index)} signals, {d.spec.simulation.n_steps} steps of "
          f"{d.spec.simulation.step:g} s with {d.spec.simulation.solver}")
    _note_defaults(d)
    return EXIT_OK


def _note_defaults(d) -> None:
    """A diagram that leaves out simulation settings runs with stated defaults, never silently."""
    from fwdstep.structure.spec import defaults_note
    note = defaults_note(d.spec.simulation)
    if note:
        print(f"fwdstep: note: {note}", file=sys.stderr)


def cmd_run(path: str, sets=None, outdir: str | None = None, force: bool = False,
            plots: bool = True, quiet: bool = False, backend: str | None = None,
            formats=("png",), max_log_memory: str | None = None,
            log_to_disk: bool = False, redirects: dict | None = None,
            record: dict | None = None, overrides: dict | None = None) -> int:
    """``fwdstep run``: the output directory is claimed (locked, checked) and the log's size
    checked (``fwdstep.core.budgets``) before the simulation starts; results are written as one
    transaction (``fwdstep.results.outputs``) after it, partial when it diverged, failed or was
    interrupted (SIGINT/SIGTERM/SIGHUP).  ``log_to_disk`` records into memory-mapped files
    beside the output directory instead of memory.  The output directory also gets a copy of
    the diagram as run and the record of what made the run (``fwdstep.results.provenance``:
    ``sets`` as typed, the command line, plus ``record``); ``redirects``: read a recorded
    copy (``fwdstep rerun``)."""
    import shutil
    import tempfile
    from fwdstep.core.budgets import check_log, parse_size
    from fwdstep.structure.compiler import load_diagram
    from fwdstep.results.outputs import OutputDir
    outdir = outdir or default_outdir(path)
    log_dir = limit = None
    try:
        d = load_diagram(path, {**(overrides or {}), **_overrides(sets)},
                         redirects=redirects)
        limit = parse_size(max_log_memory) if max_log_memory else None
        if not log_to_disk:             # before the output directory is claimed
            check_log(d, limit)
        out = OutputDir(outdir, force, expected=run_files(d, plots, formats))
        out.__enter__()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    if not quiet:
        _note_defaults(d)
    try:
        if log_to_disk:
            log_dir = tempfile.mkdtemp(prefix=f".{out.name}.fwdstep-log-", dir=out.parent)
            check_log(d, to_disk=log_dir)   # the CLI's words; simulate checks it again
        record = {"command": _command_line(), "sets": list(sets or []), **(record or {}),
                  "figure_formats": list(formats) if plots else []}
        return _run_into(out, d, plots, quiet, backend, formats, log_dir, limit, record)
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    finally:
        out.__exit__(None, None, None)
        if log_dir is not None:
            shutil.rmtree(log_dir, ignore_errors=True)


#: the arguments of the command being run (``fwdstep.cli.arguments.main`` sets them)
_ARGUMENTS: list | None = None


def _reached(result, d) -> float:
    """The fraction of t_final a (possibly partial) result reached."""
    if result is None or not len(result.t):
        return 0.0
    return float(result.t[-1]) / d.spec.simulation.t_final


def _command_line() -> list:
    """The command as typed: 'fwdstep' and its arguments."""
    return ["fwdstep"] + list(sys.argv[1:] if _ARGUMENTS is None else _ARGUMENTS)


def _run_into(out, d, plots: bool, quiet: bool, backend, formats, log_dir=None,
              max_log_bytes=None, record=None) -> int:
    from fwdstep.run.simulate import simulate
    from fwdstep.core import signals
    code = EXIT_OK
    progress = None if quiet else Progress()
    result = None
    try:
        result = simulate(d, progress=progress, backend=backend, log_dir=log_dir,
                          max_log_bytes=max_log_bytes,   # checks the log's size (budgets)
                          on_compile=None if quiet else _compile_news)
    except SimulationError as exc:        # its line says where it stopped
        result = exc.result
        if progress is not None and progress.live and progress.started:
            print(file=sys.stderr)            # end the line the progress was rewriting
        _err(str(exc))
        code = (EXIT_DIVERGED if isinstance(exc, DivergenceError) else
                EXIT_BLOCK if isinstance(exc, BlockRuntimeError) else
                EXIT_LIMIT if isinstance(exc, LimitExceeded) else
                signals.exit_code(exc))
        if result is None:
            return code
    else:
        if progress is not None:
            progress.finish(_reached(result, d))
    for note in result.notes:
        _err(f"note: {note}")
    try:
        with signals.deferred():                  # a signal now: the results still land
            written = result.write_files(out.dir, record)
            if plots and len(result.t) and code != EXIT_BLOCK:
                code = _figures(result, out.dir, formats, code)
            written = out.commit()
    except OSError as exc:
        _err(f"cannot write results to {out.requested}: {exc}")
        return EXIT_INPUT
    late = signals.pending()
    if late is not None:
        _err(f"{late.reason} while the results were written; they are complete")
        code = code or signals.exit_code(late)
    if not quiet:
        from fwdstep.run.limits import describe
        from fwdstep.results.result import events_line
        for line in describe(result.limits):
            print(f"fwdstep: note: {line}", file=sys.stderr)
        m = result.metrics()
        reached = f"t = {result.t[-1]:g} s" if len(result.t) else "nothing recorded"
        line = f"{result.status}: {reached} in {result.wall_time:.2f} s wall"
        if result.status == "stopped":
            line += f" ({result.message})"
        if result.events:
            line += "; " + events_line(result.events)
        if m and m.get("final_error_norm") is not None:     # names: fwdstep.results.result
            line += (f"; final |e|_2 = {m['final_error_norm']:.3e}; over the last "
                     f"{int(100 * d.spec.metrics.get('tail', 0.2))}%: max |e|_2 = "
                     f"{m['tail_error_norm_max']:.3e}, largest joint max_i |e_i| = "
                     f"{m['tail_error_max_abs']:.3e}; RMS |e|_2 = {m['rms_error_norm']:.3e}")
        print(line)
        print(printable(f"wrote {', '.join(os.path.relpath(p) for p in written)}"))
    return code


def _figures(result, folder: str, formats, code: int) -> int:
    """Draw the run's figures into ``folder``, where its data already are: whatever goes
    wrong while drawing costs the figures, never the data (they are committed with what was
    drawn), and is one line; exit 2 if the run itself was ok."""
    from fwdstep.results.plotting import plot_result
    try:
        plot_result(result, folder, formats=formats)
    except Exception as exc:  # noqa: BLE001 - a figure must never lose a finished run
        _err(f"the figures could not be drawn ({type(exc).__name__}: "
             f"{' '.join(str(exc).split())[:200]}); the run's data are written")
        return code or EXIT_INPUT
    return code


def cmd_rerun(run_dir: str, outdir: str | None = None, force: bool = False,
              plots: bool = True, quiet: bool = False, report: bool = False) -> int:
    """``fwdstep rerun RUN_DIR -o NEW``: run again exactly what made RUN_DIR -- the copy of
    the diagram kept there, the same ``--set`` values, backend and solver settings, the same
    plugin files (refused in one line when one is missing or has changed) -- into NEW
    (default RUN_DIR_rerun).  Fixed-step runs give bit-identical result.npz arrays."""
    from fwdstep.results import provenance
    try:
        prov = provenance.read_record(run_dir)
        plugins = provenance.check_plugins(prov)
        if plugins:
            from fwdstep.structure.library import load_plugins
            load_plugins(plugins)
        top, overrides, redirects = provenance.load_recorded(run_dir, prov)
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    outdir = outdir or os.path.normpath(run_dir) + "_rerun"
    formats = tuple(prov.get("figure_formats") or ("png",))
    keep = {"rerun_of": os.path.abspath(run_dir),
            "diagram_source": prov.get("diagram_source"),
            "sets": prov.get("sets")}
    code = cmd_run(top, None, outdir, force, plots=plots and bool(prov.get("figure_formats")),
                   quiet=quiet, backend=prov.get("backend"), formats=formats,
                   redirects=redirects, overrides=overrides, record=keep)
    if report and code != EXIT_INPUT:
        from fwdstep.views.report import write_report
        try:
            print(f"wrote {write_report(outdir)}")
        except (FwdstepError, OSError) as exc:
            _err(f"cannot write the report: {exc}")
            code = code or EXIT_INPUT
    return code


def cmd_blocks(name: str | None = None) -> int:
    from fwdstep.structure.library import load_library
    reg = load_library()
    if name is None:
        for tname in sorted(reg):
            cls = reg[tname]
            try:
                blk = cls("example", **cls.example)
                ins = ", ".join(f"{p.name}{list(p.shape)}" for p in blk.inputs.values())
                outs = ", ".join(f"{p.name}{list(p.shape)}" for p in blk.outputs.values())
                ports = f"in: {ins or '-'}; out: {outs or '-'}"
            except FwdstepError:
                ports = ""
            params = ", ".join(cls.params)
            print(f"{tname:22s} {cls.summary()}")
            print(f"{'':22s}   {ports} (shapes of the example)")
            print(f"{'':22s}   parameters: {params or '-'}")
        return EXIT_OK
    if name not in reg:
        from fwdstep.structure.library import lookup
        try:
            lookup(name)
        except DiagramError as exc:
            _err(str(exc))
            return EXIT_INPUT
    cls = reg[name]
    print(f"{name}\n{'=' * len(name)}\n")
    import inspect
    print(inspect.cleandoc(cls.__doc__ or ""))
    print("\nParameters (kind, default):")
    for key, decl in cls.params.items():
        default = "required" if decl.required else repr(decl.default)
        print(f"  {key:16s} {decl.kind:7s} {default:12s} {decl.doc}")
    return EXIT_OK
