"""What the command-line verbs do (``cli.py`` only parses arguments and calls these).

Every verb returns an exit code:
  0 success; 2 the diagram, an option or the output directory is wrong (one line on stderr);
  3 the simulation diverged; 4 a block raised at run time; 130 interrupted (Ctrl-C).
Partial results are written before a non-zero exit whenever anything was computed.
"""
from __future__ import annotations

import os
import sys

from .errors import (BlockRuntimeError, DiagramError, DivergenceError, FwdstepError,
                     OutputError, SimulationError, one_line)
from .result import RESULT_FILE, SUMMARY_FILE

EXIT_OK, EXIT_INPUT, EXIT_DIVERGED, EXIT_BLOCK, EXIT_INTERRUPTED = 0, 2, 3, 4, 130


def _err(msg: str) -> None:
    print(f"fwdstep: {one_line(str(msg))}", file=sys.stderr)


def _overrides(pairs) -> dict:
    from .spec import parse_override
    out = {}
    for text in pairs or []:
        name, value = parse_override(text)
        out[name] = value
    return out


def default_outdir(path: str) -> str:
    return os.path.join("out", os.path.splitext(os.path.basename(path))[0])


def check_outdir(outdir: str, force: bool) -> None:
    if os.path.exists(outdir) and not os.path.isdir(outdir):
        raise OutputError(f"output directory {outdir} exists and is not a directory")
    existing = [f for f in (RESULT_FILE, SUMMARY_FILE)
                if os.path.exists(os.path.join(outdir, f))]
    if existing and not force:
        raise OutputError(f"{os.path.join(outdir, existing[0])} already exists; pass --force to "
                          "overwrite it or -o to choose another directory")


def _progress(frac: float) -> None:
    print(f"  {100 * frac:5.1f}% simulated", file=sys.stderr, flush=True)


def cmd_validate(path: str, sets=None) -> int:
    from .compiler import load_diagram
    try:
        d = load_diagram(path, _overrides(sets))
    except DiagramError as exc:
        _err(str(exc))
        return EXIT_INPUT
    print(f"{path}: ok — {len(d.schedule)} blocks, {d.n_states} states, "
          f"{len(d.signal_index)} signals, {d.spec.simulation.n_steps} steps of "
          f"{d.spec.simulation.step:g} s with {d.spec.simulation.solver}")
    return EXIT_OK


def cmd_run(path: str, sets=None, outdir: str | None = None, force: bool = False,
            plots: bool = True, quiet: bool = False, backend: str | None = None) -> int:
    from .compiler import load_diagram
    from .simulate import simulate
    outdir = outdir or default_outdir(path)
    try:
        d = load_diagram(path, _overrides(sets))
        check_outdir(outdir, force)
    except (DiagramError, OutputError) as exc:
        for each in [exc] + list(getattr(exc, "more", ())):   # every mistake found, one line each
            _err(str(each))
        return EXIT_INPUT
    code = EXIT_OK
    progress = None if quiet else _progress
    try:
        result = simulate(d, progress=progress, backend=backend)
    except SimulationError as exc:
        result = exc.result
        _err(str(exc))
        code = (EXIT_DIVERGED if isinstance(exc, DivergenceError) else
                EXIT_BLOCK if isinstance(exc, BlockRuntimeError) else EXIT_INTERRUPTED)
        if result is None:
            return code
    try:
        written = result.save(outdir, force=True)
        if plots and code in (EXIT_OK, EXIT_DIVERGED, EXIT_INTERRUPTED):
            from .plotting import plot_result
            written += plot_result(result, outdir)
    except (OSError, FwdstepError) as exc:
        _err(f"cannot write results to {outdir}: {exc}")
        return EXIT_INPUT
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    if not quiet:
        m = result.metrics()
        reached = f"t = {result.t[-1]:g} s" if len(result.t) else "nothing recorded"
        line = f"{result.status}: {reached} in {result.wall_time:.2f} s wall"
        if m and m.get("final_abs_error") is not None:
            line += (f"; final |e| = {m['final_abs_error']:.3e}, max |e| over last "
                     f"{int(100 * d.spec.metrics.get('tail', 0.2))}% = "
                     f"{m['tail_max_abs_error']:.3e}, RMS = {m['rms_error']:.3e}")
        print(line)
        print(f"wrote {', '.join(os.path.relpath(p) for p in written)}")
    return code


def cmd_blocks(name: str | None = None) -> int:
    from .registry import load_library
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
        from .registry import lookup
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
