"""Saved runs replayed: ``fwdstep.animate(RUN_DIR | Result | [...])`` and the report's
"Animation" section.  The page itself is ``fwdstep.results.animate``'s; this module loads the
runs (their Result and the diagram file summary.json names)."""
from __future__ import annotations

import html
import os

from fwdstep.core.errors import FwdstepError, OutputError, one_line
from fwdstep.results.animate import (DISPLAY_FPS, Animation, NoRobot, _diagram_file,
                                     animation_html, embed_html)
from fwdstep.results.result import load_result
from fwdstep.structure.compiler import load_diagram


def _load_run(outdir: str):
    """(Result, compiled diagram) of a saved run directory."""
    r = load_result(outdir)
    prov = r.stored.get("provenance")
    if isinstance(prov, dict) and prov.get("diagram"):    # the copy of the diagram as run
        from fwdstep.results.provenance import recorded_diagram
        return r, recorded_diagram(r.stored, outdir)
    path = _diagram_file(r.stored.get("diagram"), outdir)
    if path is None:
        raise OutputError(f"{outdir}: the run's diagram file {r.stored.get('diagram')} is not "
                          "here; animate needs it for the robot's geometry (run fwdstep animate "
                          "in the directory fwdstep run ran in)")
    params = r.stored.get("parameters")
    try:
        d = load_diagram(path, params if isinstance(params, dict) else None)
    except FwdstepError:
        d = load_diagram(path)
    return r, d


def _resolve(src):
    """(Result, diagram, where) of a run directory or a Result."""
    if isinstance(src, (str, os.PathLike)):
        r, d = _load_run(os.fspath(src))
        return r, d, os.fspath(src)
    d = getattr(src, "diagram", None)
    if d is None:
        outdir = getattr(src, "outdir", None)
        if outdir is None:
            raise OutputError("this Result has no diagram to take the robot from")
        r, d = _load_run(outdir)
        return r, d, outdir
    return src, d, None




def animate(sources, fps: float = DISPLAY_FPS, labels=None) -> Animation:
    """``fwdstep.animate(r)``: the page (a str, inline in notebooks) replaying a run's robot;
    ``r`` a Result, a run directory, or a list of them (overlaid in distinct colours)."""
    sources = list(sources) if isinstance(sources, (list, tuple)) else [sources]
    if not sources:
        raise OutputError("animate needs at least one run")
    return animation_html([_resolve(s) for s in sources], labels, fps)


def report_section(result, run_dir: str) -> list:
    """The report's "Animation" section (fwdstep.report): the page in an iframe, a one-line
    note when the run cannot be animated, nothing when its diagram has no robot."""
    try:
        page = animate([run_dir])
    except NoRobot:
        return []
    except FwdstepError as exc:
        return ["<h2>Animation</h2>", f"<p>{html.escape(one_line(str(exc)))}</p>"]
    except ImportError as exc:               # pinocchio missing for a URDF arm
        return ["<h2>Animation</h2>", f"<p>no animation: {html.escape(str(exc))}</p>"]
    return ["<h2>Animation</h2>", embed_html(page)]


