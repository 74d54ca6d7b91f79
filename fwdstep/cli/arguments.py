"""The ``fwdstep`` command: argument parsing only; all work happens in ``fwdstep.cli.commands``."""
from __future__ import annotations

import sys

from fwdstep.core.settings import BACKENDS


_DIAGRAM_HELP = "the diagram file (YAML; docs/diagram-format.md)"
_PLUGIN_HELP = ("a Python file defining more block types (repeatable; docs/writing-blocks.md); "
                "diagrams name block types, never Python files")
_SET_HELP = ("replace a value before building (repeatable): NAME (a parameter), BLOCK.PARAM, "
             "SUB.PARAM, SUB.BLOCK.PARAM, simulation.SETTING or log=[blk.port, ...]")


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("fwdstep")
    except Exception:  # noqa: BLE001 - not installed: the source tree's own number
        from fwdstep import __version__
        return __version__


def build_parser() -> argparse.ArgumentParser:
    import argparse                  # imported here: main() handles signals from its first line
    p = argparse.ArgumentParser(
        prog="fwdstep",
        description="Block-diagram simulation of forwardstepping control of robot manipulators.")
    p.add_argument("--version", action="version", version=f"fwdstep {_version()}",
                   help="print fwdstep's version and exit")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="simulate a diagram; write result.npz, summary.json, PNGs")
    run.add_argument("diagram", help=_DIAGRAM_HELP)
    run.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=_SET_HELP)
    run.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)
    run.add_argument("-o", "--outdir", default=None,
                     help="output directory (default: out/<diagram name>)")
    run.add_argument("--force", action="store_true", help="overwrite existing results")
    run.add_argument("--no-plots", action="store_true", help="skip the figures")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress or summary line")
    run.add_argument("--backend", choices=BACKENDS, default=None,
                     help="override simulation.backend (compiled needs numba: fwdstep[fast])")
    run.add_argument("--max-log-memory", default=None, metavar="SIZE",
                     help="largest log kept in memory, e.g. 8GB (default 2GiB); a larger log "
                          "is refused before the run starts")
    run.add_argument("--log-to-disk", action="store_true",
                     help="record into memory-mapped files beside OUTDIR instead of memory "
                          "(limited by free disk space)")

    rr = sub.add_parser("rerun", help="run again exactly what made a run directory (its copy "
                                      "of the diagram, --set values, backend, plugins)")
    rr.add_argument("run_dir", metavar="RUN_DIR", help="a directory written by fwdstep run")
    rr.add_argument("-o", "--outdir", default=None,
                    help="output directory (default: RUN_DIR_rerun)")
    rr.add_argument("--force", action="store_true", help="overwrite existing results")
    rr.add_argument("--no-plots", action="store_true", help="skip the figures")
    rr.add_argument("-q", "--quiet", action="store_true", help="no progress or summary line")
    rr.add_argument("--report", action="store_true", help="also write report.html")
    rr.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                    help=_PLUGIN_HELP + "; the run's own plugins are loaded (and checked "
                                        "against their recorded SHA-256) without it")

    val = sub.add_parser("validate", help="load and compile a diagram (exit 0 or 2)")
    val.add_argument("diagram", help=_DIAGRAM_HELP)
    val.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=_SET_HELP)
    val.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)

    blk = sub.add_parser("blocks", help="list the block library, or show one block's doc")
    blk.add_argument("name", nargs="?", help="a block type (e.g. Gain): show its documentation")
    blk.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)

    sch = sub.add_parser("schema", help="print the JSON Schema of the diagram format (from the "
                                        "block registry), for editors")
    sch.add_argument("-o", "--output", default=None,
                     help="write the schema to this file instead of standard output")
    sch.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP + "; their blocks are in the schema too")

    sw = sub.add_parser("sweep", help="run a diagram over a grid of parameter values")
    sw.add_argument("diagram")
    sw.add_argument("--grid", action="append", default=[], metavar="NAME=V1,V2,...",
                    help="values of NAME (a parameter, simulation.SETTING or BLOCK.PARAM); "
                         "the variants are the product of all grids (docs/sweeps.md)")
    sw.add_argument("--random", action="append", default=[], metavar="NAME=DIST",
                    help="draw NAME: LOW:HIGH (uniform), loguniform:LOW:HIGH or "
                         "normal:MEAN:SD; needs --samples")
    sw.add_argument("--samples", type=int, default=0, help="draws per grid cell")
    sw.add_argument("--seed", type=int, default=0, help="seed of the draws (and variant seeds)")
    sw.add_argument("--design", choices=("random", "lhs", "sobol"), default="random",
                    help="how the --samples points are placed: independent draws, Latin "
                         "hypercube or scrambled Sobol (scipy.stats.qmc)")
    sw.add_argument("--seed-parameter", default=None, metavar="NAME",
                    help="give each variant its own integer seed in diagram parameter NAME")
    sw.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    sw.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                    help=_PLUGIN_HELP)
    sw.add_argument("--sequential", action="store_true",
                    help="run variants one by one instead of in batches")
    sw.add_argument("--workers", type=int, default=None, metavar="N",
                    help="local worker processes (default: every core; 1: this process)")
    sw.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run the batches on this Dask scheduler (tcp://HOST:PORT); needs "
                         "fwdstep[distributed]")
    sw.add_argument("--backend", choices=BACKENDS, default=None,
                    help="override simulation.backend for every variant; compiled batches run "
                         "their variants in parallel threads (needs numba: fwdstep[fast])")
    sw.add_argument("--max-memory", default=None, metavar="SIZE",
                    help="memory for the batches running at once, e.g. 2GB (default 1GB)")
    sw.add_argument("--batch-size", type=int, default=None, metavar="N",
                    help="at most N variants per batch")
    sw.add_argument("--resume", action="store_true",
                    help="keep the finished batches in OUTDIR/parts and run only the rest")
    sw.add_argument("--no-signals", action="store_true",
                    help="keep only the table, not every variant's error signal")
    sw.add_argument("--netcdf", action="store_true",
                    help="also write sweep.nc: every variant's error as a labelled xarray "
                         "Dataset (needs xarray)")
    sw.add_argument("-o", "--outdir", default=None)
    sw.add_argument("--force", action="store_true")
    sw.add_argument("-q", "--quiet", action="store_true")
    _add_results_commands(sub, run)
    lin = sub.add_parser("linearize", help="linear model of a diagram at a time of its run: "
                                           "A, B, C, D, poles, zeros, Bode figure, margins")
    lin.add_argument("diagram", help=_DIAGRAM_HELP)
    lin.add_argument("--input", action="append", default=[], required=True, metavar="SIGNAL",
                     help="analysis point BLOCK.PORT or BLOCK.PORT[i]: the signal + u "
                          "(repeatable)")
    lin.add_argument("--output", action="append", default=[], required=True,
                     metavar="SIGNAL", help="measured signal (repeatable)")
    lin.add_argument("--at", type=float, default=0.0, metavar="T",
                     help="time of the run whose state is used (default 0: the initial state)")
    lin.add_argument("--open", action="append", default=None, metavar="SIGNAL",
                     help="cut the loop at this signal (loop transfer; margins for SISO)")
    lin.add_argument("--along", type=int, default=0, metavar="N",
                     help="also linearise at N times of one run: poles over time")
    lin.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=_SET_HELP)
    lin.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)
    lin.add_argument("-o", "--outdir", default=None,
                     help="output directory (default: out/<diagram name>/linear)")
    lin.add_argument("--force", action="store_true", help="overwrite existing results")
    tu = sub.add_parser("tune", help="gradient-based tuning of parameters (forward "
                                     "sensitivities): bounds, constraints from metrics, "
                                     "multi-start")
    tu.add_argument("diagram", help=_DIAGRAM_HELP)
    tu.add_argument("--vary", action="append", default=[], required=True,
                    metavar="NAME=LOW:HIGH", help="a parameter to tune and its bounds: "
                    "alpha=1:10, 'K[0,0]=10:200', Ks.gain=1:5 (repeatable)")
    tu.add_argument("--minimize", required=True, metavar="OBJECTIVE",
                    help="a metric (rms_error_norm, final_error_norm, ...) or FUNCTION(SIGNAL): "
                         "rms, mean_square, ise, max_abs, max_norm, final_norm, final_abs")
    tu.add_argument("--subject-to", action="append", default=[], metavar="CONSTRAINT",
                    help="'OBJECTIVE <= NUMBER' or '>=', e.g. \"max_abs(tau.y) <= 87\" "
                         "(repeatable)")
    tu.add_argument("--screen", type=int, default=16, metavar="N",
                    help="points of the design screened before the local searches (16)")
    tu.add_argument("--starts", type=int, default=3, metavar="N",
                    help="local searches, from the best screened points (3)")
    tu.add_argument("--design", default="sobol", choices=("sobol", "lhs", "random"),
                    help="screening design (sobol)")
    tu.add_argument("--seed", type=int, default=0, help="seed of the screening design (0)")
    tu.add_argument("--max-iterations", type=int, default=30, metavar="N",
                    help="iterations of each local search (30)")
    tu.add_argument("--backend", choices=BACKENDS, default=None,
                    help="backend of every evaluation (default: the diagram's "
                         "simulation.backend); compiled: sensitivities in compiled code")
    tu.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=_SET_HELP)
    tu.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                    help=_PLUGIN_HELP)
    tu.add_argument("-o", "--outdir", default=None,
                    help="output directory (default: out/<diagram name>/tune)")
    tu.add_argument("--force", action="store_true", help="overwrite existing results")
    tu.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    ident = sub.add_parser("identify", help="least-squares estimate of a robot's parameters "
                                            "from a saved run (filtered regressor, no qddot)")
    ident.add_argument("run", help="directory of a saved run (fwdstep run ... -o RUN)")
    ident.add_argument("--regressor", required=True, metavar="BLOCK",
                       help="the regressor block of the run's diagram (Y theta = H zetad + "
                            "C zeta + g)")
    ident.add_argument("--q", default=None, metavar="SIGNAL",
                       help="logged joint positions (default: what feeds the regressor's q)")
    ident.add_argument("--qdot", default=None, metavar="SIGNAL",
                       help="logged joint velocities (default: the regressor's qdot input)")
    ident.add_argument("--tau", default=None, metavar="SIGNAL",
                       help="logged torques (default: the input tau of the block producing q)")
    ident.add_argument("--bandwidth", type=float, default=None, metavar="LAMBDA",
                       help="filter lambda/(p + lambda), lambda in rad/s (default: "
                            "min(20, 0.05 / log interval))")
    ident.add_argument("--friction", choices=("none", "viscous"), default="none",
                       help="also estimate per-joint viscous friction F_v (tau_f = -F_v "
                            "qdot), appended after the regressor's parameters")
    ident.add_argument("--truth", default=None, metavar="SIGNAL",
                       help="a logged signal holding the true parameters, for comparison")
    ident.add_argument("--confidence", type=float, default=0.95,
                       help="confidence level of the intervals (0.95)")
    ident.add_argument("-o", "--outdir", default=None,
                       help="output directory (default: RUN/identify)")
    ident.add_argument("--force", action="store_true", help="overwrite existing results")
    ident.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                       help=_PLUGIN_HELP + "; a run's own plugin files are loaded from its "
                                           "record")
    return p


def _add_results_commands(sub, run) -> None:
    """graph, report, compare and run's figure/report options (fwdstep.views.drawing/report/compare)."""
    run.add_argument("--figure-format", action="append", default=None,
                     choices=("png", "pdf", "svg"),
                     help="also write the figures in this format (repeatable); PNG is "
                          "always written")
    run.add_argument("--report", action="store_true",
                     help="also write report.html (self-contained) into the output directory")
    gr = sub.add_parser("graph", help="draw a diagram as a block diagram (SVG, PNG or PDF)")
    gr.add_argument("diagram", help=_DIAGRAM_HELP)
    gr.add_argument("-o", "--output", default=None,
                    help="picture file, .svg/.png/.pdf (default: out/<diagram name>/diagram.svg)")
    gr.add_argument("--depth", type=int, default=None,
                    help="draw subsystems nested deeper than this as one box (default: all)")
    gr.add_argument("--engine", choices=("auto", "dot", "matplotlib"), default="auto",
                    help="layout: graphviz dot (default when installed) or matplotlib")
    gr.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=_SET_HELP)
    gr.add_argument("--force", action="store_true",
                    help="replace the output file even when fwdstep did not write it")
    gr.add_argument("--tags", choices=("auto", "on", "off"), default="auto",
                    help="draw a signal that feeds 3 or more blocks as named tags instead of "
                         "wires (auto: in pictures of more than 30 boxes)")
    gr.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                    help=_PLUGIN_HELP)
    rep = sub.add_parser("report", help="one self-contained HTML page of a run or sweep "
                                        "directory: diagram, parameters, metrics, figures")
    rep.add_argument("run_dir", metavar="RUN_DIR",
                     help="a directory written by fwdstep run or fwdstep sweep")
    rep.add_argument("-o", "--output", default=None,
                     help="the HTML file (default: RUN_DIR/report.html)")
    rep.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP + "; a run's own plugin files are loaded from its record")
    ani = sub.add_parser("animate", help="replay the robot of a run (or two, overlaid) in one "
                                         "self-contained HTML page (3-D for URDF arms)")
    ani.add_argument("runs", nargs="+", metavar="RUN_DIR",
                     help="run directories written by fwdstep run (their plant's q logged)")
    ani.add_argument("-o", "--output", default=None,
                     help="the HTML file (default: RUN_DIR/animation.html)")
    ani.add_argument("--fps", type=float, default=30.0,
                     help="frames per second of simulated time kept (default 30)")
    ani.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)
    cmp = sub.add_parser("compare", help="overlay the same signals of saved runs, their "
                                         "differences and a metrics table")
    cmp.add_argument("runs", nargs="+", metavar="RUN_DIR",
                     help="run directories (of fwdstep run) or sweep directories (of "
                          "fwdstep sweep: every saved variant); DIR@K is variant K of a batch "
                          "or sweep, DIR@3,7 variants 3 and 7")
    cmp.add_argument("-o", "--outdir", default=None,
                     help="where compare.png and compare.csv go (default: out/compare)")
    cmp.add_argument("--signal", action="append", default=[], metavar="BLOCK.PORT",
                     help="signal to compare (repeatable; default: those of the figures)")
    cmp.add_argument("--figure-format", action="append", default=None,
                     choices=("png", "pdf", "svg"),
                     help="also write the figure in this format (repeatable); PNG is always "
                          "written")
    cmp.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help=_PLUGIN_HELP)
    cmp.add_argument("-q", "--quiet", action="store_true",
                     help="print nothing (the table is in compare.csv)")


def _results_command(args):
    """Exit code of graph/report/compare, or None for other commands."""
    if args.command == "graph":
        from fwdstep.cli.verbs import cmd_graph
        return cmd_graph(args.diagram, args.output, args.set, args.depth, args.engine,
                         args.force, args.tags)
    if args.command == "run" and (args.figure_format or args.report):
        from fwdstep.cli import commands
        code = commands.cmd_run(args.diagram, args.set, args.outdir, args.force,
                                plots=not args.no_plots, quiet=args.quiet, backend=args.backend,
                                formats=figure_formats(args.figure_format),
                                max_log_memory=args.max_log_memory,
                                log_to_disk=args.log_to_disk)
        if args.report and code != 2:            # partial results get a report too
            from fwdstep.cli.verbs import cmd_report
            code = cmd_report(args.outdir or commands.default_outdir(args.diagram)) or code
        return code
    if args.command == "report":
        from fwdstep.cli.verbs import cmd_report
        return cmd_report(args.run_dir, args.output)
    if args.command == "animate":
        from fwdstep.cli.verbs import cmd_animate
        return cmd_animate(args.runs, args.output, args.fps)
    if args.command == "compare":
        from fwdstep.cli.verbs import cmd_compare
        return cmd_compare(args.runs, args.outdir, args.signal,
                           figure_formats(args.figure_format), quiet=args.quiet)
    return None


def figure_formats(asked) -> tuple:
    """What ``--figure-format`` asks for, in addition to PNG (always written: the report
    and the README's examples read the PNG)."""
    return tuple(dict.fromkeys(["png"] + list(asked or [])))


def main(argv=None) -> int:
    """Run one command; its exit code.  SIGINT, SIGTERM and SIGHUP are handled from here on,
    also while fwdstep is still being imported: exit 128 + signal (130, 143, 129), one line,
    partial results kept (fwdstep.core.signals, fwdstep.results.outputs); never a traceback."""
    early = _hold_signals()                 # while numpy & co. import (they would turn an
    try:                                    # interrupt into an ImportError traceback)
        from fwdstep.core import signals
    finally:
        arrived = early()
    if arrived:
        from fwdstep.core.signals import Interrupted
        print(f"fwdstep: {Interrupted(arrived).reason}", file=sys.stderr)
        return 128 + arrived
    try:
        with signals.handled():
            return _main(argv)
    except KeyboardInterrupt as exc:        # also fwdstep.core.signals.Interrupted
        reason = getattr(exc, "reason", "interrupted by the user")
        print(f"fwdstep: {reason}", file=sys.stderr)
        return 128 + int(getattr(exc, "signum", 2))
    except MemoryError:
        print("fwdstep: out of memory; the diagram asks for more than this machine has "
              "(see 'When something is wrong' in the README)", file=sys.stderr)
        return 2


def _hold_signals():
    """Remember SIGINT/SIGTERM/SIGHUP instead of acting on them; returns a function that
    restores the previous handlers and gives the first signal that arrived (or 0)."""
    import signal
    import threading
    arrived: list = []
    if threading.current_thread() is not threading.main_thread():
        return lambda: 0
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        previous[signum] = signal.signal(signum, lambda n, frame: arrived.append(n))

    def release() -> int:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        return arrived[0] if arrived else 0
    return release


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """fwdstep's own warnings as one line on stderr; others as Python shows them."""
    import warnings
    from fwdstep.core.errors import FwdstepWarning, one_line
    if issubclass(category, FwdstepWarning):
        sys.stderr.write(f"fwdstep: warning: {one_line(str(message))}\n")
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _main(argv=None) -> int:
    import warnings
    with warnings.catch_warnings():      # restored when the command ends (tests call main)
        warnings.showwarning = _show_warning
        return _command(argv)


def _command(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:       # argparse already printed a one-line usage error
        return 2 if exc.code not in (0, None) else 0
    from fwdstep.cli import commands
    commands._ARGUMENTS = list(sys.argv[1:] if argv is None else argv)   # for the record
    try:
        if getattr(args, "plugin", None):        # user-chosen block files, before anything
            from fwdstep.structure.library import load_plugins
            load_plugins(args.plugin)
        code = _results_command(args)
        if code is not None:
            return code
        if args.command == "run":
            return commands.cmd_run(args.diagram, args.set, args.outdir, args.force,
                                    plots=not args.no_plots, quiet=args.quiet,
                                    backend=args.backend,
                                    max_log_memory=args.max_log_memory,
                                    log_to_disk=args.log_to_disk)
        if args.command == "rerun":
            return commands.cmd_rerun(args.run_dir, args.outdir, args.force,
                                      plots=not args.no_plots, quiet=args.quiet,
                                      report=args.report)
        if args.command == "validate":
            return commands.cmd_validate(args.diagram, args.set)
        if args.command == "blocks":
            return commands.cmd_blocks(args.name)
        if args.command == "schema":
            from fwdstep.cli.verbs import cmd_schema
            return cmd_schema(args.output)
        if args.command == "sweep":
            from fwdstep.cli.verbs import cmd_sweep
            return cmd_sweep(args)
        if args.command == "linearize":
            from fwdstep.cli.verbs import cmd_linearize
            return cmd_linearize(args.diagram, args.input, args.output, args.at, args.open,
                                 args.along, args.set, args.outdir, args.force)
        if args.command == "tune":
            from fwdstep.cli.verbs import cmd_tune
            return cmd_tune(args)
        if args.command == "identify":
            from fwdstep.cli.verbs import cmd_identify
            return cmd_identify(args)
    except KeyboardInterrupt as exc:
        reason = getattr(exc, "reason", "interrupted by the user")
        print(f"fwdstep: {reason}", file=sys.stderr)
        return 128 + int(getattr(exc, "signum", 2))
    except BrokenPipeError:         # `fwdstep blocks | head`: the reader left; not an error
        import os
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except Exception as exc:  # noqa: BLE001 - the diagram errors are handled inside commands
        from fwdstep.core.errors import FwdstepError
        if isinstance(exc, FwdstepError):
            from fwdstep.core.errors import one_line
            print(f"fwdstep: {one_line(str(exc))}", file=sys.stderr)
            return 2
        raise
    return 2


if __name__ == "__main__":
    sys.exit(main())
