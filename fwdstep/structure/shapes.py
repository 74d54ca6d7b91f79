"""Shapes inferred from the wiring: a block may leave out a shape parameter the connections fix.

A block class names its inferable shape parameters in ``shape_from``: parameter -> the ports
whose shape it is, e.g. ``Gain.shape_from = {"shape": ("u",)}``,
``Integrator.shape_from = {"shape": ("u", "y")}``.  When a diagram leaves such a parameter
out, it is taken from a port on the other side of a connection whose shape is already fixed:
the output driving one of those inputs, or an input driven by one of those outputs.  This is
repeated until nothing changes (so it travels along chains and around loops from wherever one
side is fixed); what stays open keeps the block's own default.  A shape written in the diagram
is never replaced, and connections are checked afterwards as always, so inference never hides
a mismatch.  Runs once per loaded diagram, before any block is built for the simulation.
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.errors import DiagramError
from fwdstep.structure.graph import _instantiate_one


def _open(entry) -> list:
    """The inferable shape parameters this block entry leaves out."""
    return [p for p in getattr(entry.cls, "shape_from", {}) if p not in entry.params]


def infer_shapes(spec) -> None:
    """Fill ``entry.params`` of ``spec.blocks`` with the shapes the connections fix."""
    entries = {e.name: e for e in spec.blocks}
    pending = {e.name for e in spec.blocks if _open(e)}
    if not pending:
        return
    drivers = {c.dst: c.src for c in spec.connections}
    driven: dict = {}
    for c in spec.connections:
        driven.setdefault(c.src, []).append(c.dst)
    built: dict = {}

    def block(name):
        """The built block when all its shapes are settled, else None."""
        if name in pending or name not in entries:
            return None
        if name not in built:
            try:
                built[name] = _instantiate_one(entries[name])
            except DiagramError:
                built[name] = None           # reported when the diagram is compiled
        return built[name]

    def shape_at(name: str, port: str):
        """The shape of the port across the connection(s) from ``name.port``, if fixed."""
        src = drivers.get((name, port))
        if src is not None:
            blk = block(src[0])
            if blk is not None and src[1] in blk.outputs:
                return blk.outputs[src[1]].shape
            return None
        for dst_name, dst_port in driven.get((name, port), ()):
            blk = block(dst_name)
            if blk is not None and dst_port in blk.inputs:
                return blk.inputs[dst_port].shape
        return None

    progress = True
    while progress and pending:
        progress = False
        for name in [n for n in entries if n in pending]:
            entry = entries[name]
            for param in _open(entry):
                for port in entry.cls.shape_from[param]:
                    shape = shape_at(name, port)
                    if shape is not None:
                        entry.params[param] = np.array(shape, dtype=float)
                        break
            if not _open(entry):
                pending.discard(name)
                progress = True
        if not progress and pending:
            # a loop with no fixed shape on it, or ports that are not connected: the first
            # such block keeps its default shape, which may fix the others
            pending.discard(next(n for n in entries if n in pending))
            progress = True
