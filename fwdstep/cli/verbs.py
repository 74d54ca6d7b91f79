"""The verbs that show or sweep: ``fwdstep sweep``, ``report``, ``graph``, ``compare``, ``schema``.

Each parses nothing (``fwdstep.cli.arguments`` does), calls the library, prints what it wrote
and turns errors into one line on stderr and an exit code (``fwdstep.cli.commands``)."""
from __future__ import annotations

import contextlib
import os
import signal
import sys

import numpy as np

from fwdstep.analysis.linear_outputs import ALONG_FILES, FILES, write_along, write_linear
from fwdstep.analysis.linearize import linearize, linearize_along
from fwdstep.cli.commands import (EXIT_BLOCK, EXIT_DIVERGED, EXIT_INPUT, EXIT_INTERRUPTED,
                                  EXIT_OK, _err, _overrides, default_outdir)
from fwdstep.core.errors import (BlockRuntimeError, DiagramError, DivergenceError, FwdstepError,
                                 OutputError, SimulationError, one_line, printable)
from fwdstep.structure.compiler import load_diagram
from fwdstep.results.animate import ANIMATION_FILE, DISPLAY_FPS, write_page
from fwdstep.results.outputs import OutputDir
from fwdstep.results.sweep_format import CSV_FILE, PARTS_DIR
from fwdstep.structure.schema import schema_text
from fwdstep.structure.spec import parse_override
from fwdstep.sweeps.sweep import DEFAULT_MAX_MEMORY, parse_grid, parse_random, run_sweep
from fwdstep.views.animate import animate
from fwdstep.views.compare import compare
from fwdstep.views.drawing import diagram_for_drawing, draw_diagram
from fwdstep.views.report import write_report


# ---------------------------------------------------------------------------- sweep
@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM (a batch system's kill) stops the sweep like Ctrl-C: finished batches kept.
    (``cli.main`` may have installed such a handler already; then it is left alone.)"""
    def handler(signum, frame):
        exc = KeyboardInterrupt()
        exc.signum = signum
        raise exc
    try:
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            yield
            return
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:                   # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def cmd_sweep(args) -> int:
    """``fwdstep sweep``: see ``fwdstep.sweeps.sweep`` for the options and exit codes.  One
    sweep per output directory: it is locked for the whole run and every file goes through
    its transaction (``fwdstep.sweeps.sweep.open_sweep_output``)."""
    from fwdstep.sweeps.sweep import open_sweep_output
    outdir = args.outdir or os.path.join(
        "out", os.path.splitext(os.path.basename(args.diagram))[0] + "_sweep")
    quiet = getattr(args, "quiet", False)
    resume = getattr(args, "resume", False)
    dataset = getattr(args, "netcdf", False)
    try:
        grid = parse_grid(args.grid)
        random = parse_random(args.random)
        overrides = _overrides(args.set)
        progress = None if quiet else (lambda text: print(f"  {text}", file=sys.stderr,
                                                          flush=True))
        with open_sweep_output(outdir, force=args.force, resume=resume) as out, \
                _terminate_as_interrupt():
            try:
                result = run_sweep(
                    args.diagram, grid, random, args.samples, args.seed, overrides,
                    sequential=args.sequential, progress=progress,
                    design=getattr(args, "design", "random"),
                    seed_parameter=getattr(args, "seed_parameter", None),
                    workers=getattr(args, "workers", None),
                    scheduler=getattr(args, "scheduler", None),
                    max_memory=getattr(args, "max_memory", None) or DEFAULT_MAX_MEMORY,
                    batch_size=getattr(args, "batch_size", None), outdir=out, resume=resume,
                    keep_signals=not getattr(args, "no_signals", False),
                    backend=getattr(args, "backend", None), dataset=dataset)
            except KeyboardInterrupt as exc:     # before any batch ran: nothing to keep
                print("fwdstep: interrupted", file=sys.stderr)
                return 128 + int(getattr(exc, "signum", signal.SIGINT))
            from fwdstep.cli.commands import _command_line
            record = {"command": _command_line(), "sets": list(args.set or []),
                      "grid": list(args.grid or []), "random": list(args.random or []),
                      "samples": args.samples, "seed": args.seed,
                      "design": getattr(args, "design", "random")}
            if result.write_failed:
                print(f"fwdstep: {one_line(result.write_failed)}; the finished batches "
                      f"written before are kept in {os.path.join(outdir, PARTS_DIR)}: free "
                      "space and run again with --resume", file=sys.stderr)
                with contextlib.suppress(FwdstepError):
                    result.write(out, plots=False, record=record)   # the table, if room
                return EXIT_INPUT
            written = result.write(out, dataset=dataset, record=record)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return EXIT_INPUT
    counts = result.counts()
    if not quiet:
        summary = ", ".join(f"{n} {status}" for status, n in counts.items())
        print(f"{len(result.variants)} variants in {len(result.batches)} batch"
              f"{'es' if len(result.batches) != 1 else ''}: {summary}; "
              f"{result.wall_time:.2f} s wall")
        print(f"wrote {', '.join(os.path.relpath(p) for p in written)}")
        if result.interrupted:
            print(f"interrupted: finished batches are in {os.path.join(outdir, PARTS_DIR)}; "
                  "run again with --resume to finish the rest")
    if result.lost:
        print(f"fwdstep: {result.lost} variant(s) lost with their worker process (see the "
              f"'message' column of {os.path.join(outdir, CSV_FILE)}); run again with "
              "--resume to run them", file=sys.stderr)
    if result.interrupted:
        return 128 + result.signal_number if result.signal_number else EXIT_INTERRUPTED
    if counts.get("error"):
        return EXIT_BLOCK
    if counts.get("diverged"):
        return EXIT_DIVERGED
    return EXIT_OK


# ---------------------------------------------------------------------------- report
def cmd_report(run_dir: str, output: str | None = None) -> int:
    """``fwdstep report RUN_DIR``: exit 0, or 2 with one line on stderr."""
    from fwdstep.core.errors import FwdstepError, one_line
    try:
        path = write_report(run_dir, output)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"fwdstep: cannot write the report: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0



# ---------------------------------------------------------------------------- graph
def cmd_graph(path: str, output: str | None = None, sets=None, depth: int | None = None,
              engine: str = "auto", force: bool = False, tags: str = "auto") -> int:
    """``fwdstep graph DIAGRAM -o FILE.svg``: exit 0, or 2 with one line on stderr."""
    from fwdstep.core.errors import FwdstepError, one_line
    try:
        overrides = dict(parse_override(s) for s in sets or [])
        diagram = diagram_for_drawing(path, overrides)
        output = output or os.path.join(
            "out", os.path.splitext(os.path.basename(path))[0], "diagram.svg")
        used = draw_diagram(diagram, output, depth, engine, force, tags)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return 2
    print(f"wrote {output} ({len(diagram.blocks)} blocks, layout: {used})")
    return 0



# ---------------------------------------------------------------------------- compare
def cmd_compare(sources: list, outdir: str | None = None, signals=None, formats=None,
                force: bool = True, quiet: bool = False) -> int:
    """``fwdstep compare``: exit 0, or 2 with one line on stderr."""
    from fwdstep.core.errors import FwdstepError, one_line
    try:
        c = compare(sources, signals or None)
        outdir = outdir or os.path.join("out", "compare")
        written = c.save(outdir, tuple(formats or ("png",)), force=force)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return 2
    for note in getattr(c, "notes", ()):
        print(f"fwdstep: note: {one_line(note)}", file=sys.stderr)
    if quiet:
        return 0
    cols = list(c.table[0])
    widths = {col: max([len(col), 10] + [len(_fmt(row.get(col))) for row in c.table])
              for col in cols}
    print("  ".join(f"{col:>{widths[col]}}" for col in cols))
    for row in c.table:
        print("  ".join(f"{_fmt(row.get(col)):>{widths[col]}}" for col in cols))
    print(f"wrote {', '.join(os.path.relpath(p) for p in written)}")
    return 0


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3e}"
    return str(v)



# ---------------------------------------------------------------------------- schema
def cmd_schema(output: str | None = None) -> int:
    text = schema_text()
    if output is None:
        sys.stdout.write(text)
        return 0
    try:
        with open(output, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as exc:
        print(f"fwdstep: cannot write {output}: {exc.strerror}", file=sys.stderr)
        return 2
    print(f"wrote {output} (JSON Schema of the diagram format, {len(text)} bytes)")
    return 0


# ---------------------------------------------------------------------------- linearize
def cmd_linearize(path: str, inputs, outputs, at: float = 0.0, open_=None, along: int = 0,
                  sets=None, outdir: str | None = None, force: bool = False) -> int:
    """``fwdstep linearize``; exit 0, or 2 with one line on a wrong diagram/option/signal,
    3/4 when the run to the linearisation time diverged/failed."""
    outdir = outdir or os.path.join(default_outdir(path), "linear")
    try:
        d = load_diagram(path, _overrides(sets))
        expected = list(FILES) + (list(ALONG_FILES) if along else [])
        out = OutputDir(outdir, force, expected=expected)
        out.__enter__()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    try:
        model = linearize(d, inputs=inputs, outputs=outputs, t=at, open=open_)
        siso = model.D.shape == (1, 1)
        margins = model.margins() if siso and open_ else None
        name = os.path.basename(path)
        title = (f"{name}: {', '.join(inputs)} -> {', '.join(outputs)}"
                 + (f", opened at {', '.join(model.opened)}" if model.opened else "")
                 + f", t = {model.t:g} s")
        written = write_linear(model, out.dir, margins, title)
        if along:            # the closed loop's poles (A does not depend on the points)
            models = linearize_along(d, inputs, outputs, n=along)
            written += write_along(models, out.dir, f"{name}: frozen-time poles of the "
                                                    f"closed loop at {len(models)} times")
        written = out.commit()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    except SimulationError as exc:
        _err(f"the run to t = {at:g} s stopped: {exc}")
        return EXIT_DIVERGED if isinstance(exc, DivergenceError) else (
            EXIT_BLOCK if isinstance(exc, BlockRuntimeError) else EXIT_INPUT)
    finally:
        out.__exit__(None, None, None)
    poles = model.poles()
    slowest = poles[np.argmax(poles.real)] if poles.size else None
    line = (f"linearised at t = {model.t:g} s: {model.A.shape[0]} states, "
            f"{len(model.input_names)} inputs, {len(model.output_names)} outputs")
    if slowest is not None:
        line += (f"; rightmost pole of the {'opened' if model.opened else 'closed'} loop "
                 f"{slowest.real:.4g}{slowest.imag:+.4g}j")
    if margins:
        line += (f"; gain margin {margins['gain_margin_db']:.3g} dB, phase margin "
                 f"{margins['phase_margin_deg']:.3g} deg")
    print(line)
    print(printable(f"wrote {', '.join(os.path.relpath(p) for p in written)}"))
    return 0


# ---------------------------------------------------------------------------- animate
def cmd_animate(run_dirs: list, output: str | None = None, fps: float = DISPLAY_FPS) -> int:
    """``fwdstep animate RUN_DIR [RUN_DIR2] [-o FILE.html]``: exit 0, or 2 with one line."""
    try:
        page = animate(list(run_dirs), fps=fps)
        if output is None:
            with OutputDir(run_dirs[0], force=True, expected=[ANIMATION_FILE]) as out:
                with open(os.path.join(out.dir, ANIMATION_FILE), "w", encoding="utf-8") as fh:
                    fh.write(page)
                out.commit()
            output = os.path.join(run_dirs[0], ANIMATION_FILE)
        else:
            write_page(page, output)
    except FwdstepError as exc:
        print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"fwdstep: cannot write the animation: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except ImportError as exc:
        print(f"fwdstep: animate needs {exc.name or exc} for this robot: install "
              "fwdstep[robots]", file=sys.stderr)
        return 2
    print(f"wrote {output} ({len(page.encode()) / 1e6:.1f} MB)")
    return 0


# ---------------------------------------------------------------------------- tune
def cmd_tune(args) -> int:
    """``fwdstep tune``; exit 0, or 2 with one line on a wrong diagram/option."""
    from fwdstep.sweeps.tune import FILES as TUNE_FILES, parse_vary, tune
    path = args.diagram
    outdir = args.outdir or os.path.join(default_outdir(path), "tune")
    try:
        vary = parse_vary(args.vary)
        overrides = _overrides(args.set)
        out = OutputDir(outdir, args.force, expected=list(TUNE_FILES))
        out.__enter__()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    try:
        result = tune(path, vary, args.minimize, args.subject_to, overrides=overrides,
                      screen=args.screen, starts=args.starts, design=args.design,
                      seed=args.seed, max_iterations=args.max_iterations, outdir=out.dir,
                      backend=args.backend,
                      progress=None if args.quiet else (lambda line: print(printable(line),
                                                                           flush=True)))
        written = out.commit()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    finally:
        out.__exit__(None, None, None)
    before = ", ".join(f"{k}={v:.6g}" for k, v in result.initial.items())
    after = ", ".join(f"{k}={v:.6g}" for k, v in result.best.items())
    print(f"before: {before}: {args.minimize} = {result.initial_cost:.6g}")
    print(f"after:  {after}: {args.minimize} = {result.best_cost:.6g} "
          f"({result.runs['total']} runs: {result.runs['plain']} plain, "
          f"{result.runs['with_sensitivities']} with sensitivities)")
    if result.message:
        print(f"note: {result.message}")
    print(printable(f"wrote {', '.join(os.path.relpath(p) for p in written)}"))
    # an interrupted search keeps its files but is not reported as finished
    return 128 + result.interrupted if result.interrupted else 0


# ---------------------------------------------------------------------------- identify
def cmd_identify(args) -> int:
    """``fwdstep identify RUN --regressor Y``: identify.json (estimate, standard errors,
    intervals, rank, the signals used); exit 0, or 2 with one line on bad input."""
    import json
    from fwdstep.analysis.identify import identify_run
    outdir = args.outdir or os.path.join(args.run, "identify")
    try:
        ident, names, _ = identify_run(args.run, args.regressor, args.q, args.qdot, args.tau,
                                       args.bandwidth, args.confidence, args.truth,
                                       args.friction)
        out = OutputDir(outdir, args.force, expected=["identify.json"])
        out.__enter__()
    except (DiagramError, OutputError) as exc:
        _err(str(exc))
        return EXIT_INPUT
    try:
        from fwdstep.core.jsonable import jsonable
        data = ident.to_dict()
        data["signals"] = names
        with open(os.path.join(out.dir, "identify.json"), "w") as fh:
            json.dump(jsonable(data), fh, indent=1)    # NaN (no interval) as null
        written = out.commit()
    finally:
        out.__exit__(None, None, None)
    print(f"identified {len(ident.theta)} parameters from {ident.rows} rows "
          f"(q={names['q']}, qdot={names['qdot']}, tau={names['tau']}, filter "
          f"lambda = {ident.bandwidth:g} rad/s), rank {ident.rank}:")
    known = 0 if ident.truth is None else len(ident.truth)
    for i, (v, lo, hi) in enumerate(zip(ident.theta, ident.lower, ident.upper)):
        extra = f"   (truth {ident.truth[i]:.8g})" if i < known else ""
        print(f"  {ident.names[i]} = {v:.8g}   {100 * ident.confidence:g}% interval "
              f"[{lo:.8g}, {hi:.8g}]{extra}")
    if known:
        error = np.abs(ident.theta[:known] - ident.truth)
        inside = int(np.sum(data["inside_interval"]))
        covered = (f"{inside} of {known} true values inside their intervals"
                   if np.all(np.isfinite(ident.std)) else "no intervals")
        print(f"against the truth: largest error {error.max():.3g} "
              f"({error.max() / max(np.abs(ident.truth).max(), 1e-300):.3g} of the largest "
              f"true value); {covered}")
    for note in ident.notes:
        print(f"note: {note}")
    if len(ident.unidentified):
        print(f"note: {len(ident.unidentified)} parameter direction(s) not excited by the "
              "run (see identify.json, 'unidentified')")
    print(printable(f"wrote {', '.join(os.path.relpath(p) for p in written)}"))
    return 0
