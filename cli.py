"""The ``fwdstep`` command: argument parsing only; all work happens in ``fwdstep.commands``."""
from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fwdstep",
        description="Block-diagram simulation of forwardstepping control of robot manipulators.")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="simulate a diagram; write result.npz, summary.json, PNGs")
    run.add_argument("diagram")
    run.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                     help="replace a diagram parameter before building (repeatable)")
    run.add_argument("-o", "--outdir", default=None,
                     help="output directory (default: out/<diagram name>)")
    run.add_argument("--force", action="store_true", help="overwrite existing results")
    run.add_argument("--no-plots", action="store_true", help="skip the figures")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress or summary line")
    run.add_argument("--backend", choices=("numpy", "compiled"), default=None,
                     help="override simulation.backend (compiled needs numba: fwdstep[fast])")

    val = sub.add_parser("validate", help="load and compile a diagram (exit 0 or 2)")
    val.add_argument("diagram")
    val.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")

    blk = sub.add_parser("blocks", help="list the block library, or show one block's doc")
    blk.add_argument("name", nargs="?")

    sw = sub.add_parser("sweep", help="run a diagram over a grid of parameter values")
    sw.add_argument("diagram")
    sw.add_argument("--grid", action="append", default=[], metavar="NAME=V1,V2,...")
    sw.add_argument("--random", action="append", default=[], metavar="NAME=LOW:HIGH")
    sw.add_argument("--samples", type=int, default=0)
    sw.add_argument("--seed", type=int, default=0)
    sw.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    sw.add_argument("--sequential", action="store_true",
                    help="run variants one by one instead of in batches")
    sw.add_argument("-o", "--outdir", default=None)
    sw.add_argument("--force", action="store_true")
    sw.add_argument("-q", "--quiet", action="store_true")
    return p




def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:       # argparse already printed a one-line usage error
        return 2 if exc.code not in (0, None) else 0
    from fwdstep import commands
    try:
        if args.command == "run":
            return commands.cmd_run(args.diagram, args.set, args.outdir, args.force,
                                    plots=not args.no_plots, quiet=args.quiet,
                                    backend=args.backend)
        if args.command == "validate":
            return commands.cmd_validate(args.diagram, args.set)
        if args.command == "blocks":
            return commands.cmd_blocks(args.name)
        if args.command == "sweep":
            from fwdstep.sweep import cmd_sweep
            return cmd_sweep(args)
    except KeyboardInterrupt:
        print("fwdstep: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:         # `fwdstep blocks | head`: the reader left; not an error
        import os
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except Exception as exc:  # noqa: BLE001 - the diagram errors are handled inside commands
        from fwdstep.errors import FwdstepError
        if isinstance(exc, FwdstepError):
            print(f"fwdstep: {exc}", file=sys.stderr)
            return 2
        raise
    return 2


if __name__ == "__main__":
    sys.exit(main())
