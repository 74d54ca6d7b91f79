"""Blocks + connections -> a validated port-level graph and a block evaluation order.

Nodes are ports: ``("out", block, port)`` and ``("in", block, port)``.  Edges: each
connection (out -> in) and each declared feedthrough (in -> out of the same block).  A
cycle in this graph is a true algebraic loop and is refused with the whole cycle spelled out.
The evaluation order of blocks follows from the same graph, computed once here.
"""
from __future__ import annotations

from dataclasses import dataclass

import graphlib
import heapq

from fwdstep.core.block import Block, shape_str
from fwdstep.core.errors import AlgebraicLoopError, DiagramError, ParameterError, ShapeError, WiringError
from fwdstep.structure.model import DiagramSpec


@dataclass
class Structure:
    spec: DiagramSpec
    blocks: list          # Block instances in evaluation order
    drivers: dict         # (block, in_port) -> (block, out_port)


def instantiate(spec: DiagramSpec, errors: list | None = None) -> list:
    """The blocks of ``spec``.  With ``errors`` (a list), a block that refuses its parameters
    is recorded there and left out, so every such mistake can be reported at once."""
    blocks = []
    for entry in spec.blocks:
        try:
            blocks.append(_instantiate_one(entry))
        except DiagramError as exc:
            if errors is None:
                raise
            errors.append(exc)
    return blocks


def _instantiate_one(entry):
    try:
        blk = entry.cls(entry.name, **entry.params)
    except DiagramError as exc:
        line = entry.line
        # point at the parameter's own line when the message names it
        for key, kline in entry.key_lines.items():
            if f"parameter '{key}'" in exc.message:
                line = kline
                break
        exc.block = exc.block or entry.name
        raise exc.located(entry.file, line) from None
    except (ValueError, TypeError, ArithmeticError, IndexError, KeyError,
            MemoryError) as exc:
        # a block's own checks missed this; still one sentence, chained to the cause
        raise ParameterError(f"block '{entry.name}' ({entry.type_name}) rejected its "
                             f"parameters: {type(exc).__name__}: {exc}"[:400],
                             file=entry.file, line=entry.line, block=entry.name) from exc
    return blk


def _check_connection(conn, by_name: dict, drivers: dict, where: dict) -> None:
    (sb, sp), (db, dp) = conn.src, conn.dst
    for blk_name, port, kind in ((sb, sp, "output"), (db, dp, "input")):
        if blk_name not in by_name:
            raise WiringError(f"connection '{conn.text}' names block '{blk_name}', which does "
                              "not exist", file=conn.file, line=conn.line, block=blk_name)
        blk = by_name[blk_name]
        ports = blk.outputs if kind == "output" else blk.inputs
        if port not in ports:
            other = blk.inputs if kind == "output" else blk.outputs
            note = f" ('{port}' is an {'input' if kind == 'output' else 'output'})" \
                if port in other else ""
            raise WiringError(f"block '{blk_name}' has no {kind} port '{port}'{note}; "
                              f"{kind} ports are: {', '.join(ports) or '(none)'}",
                              file=conn.file, line=conn.line, block=blk_name, port=port)
    if (db, dp) in drivers:
        first = where[(db, dp)]
        raise WiringError(f"input {db}.{dp} is driven twice: by {drivers[(db, dp)][0]}."
                          f"{drivers[(db, dp)][1]} (line {first}) and by {sb}.{sp}",
                          file=conn.file, line=conn.line, block=db, port=dp)
    s_shape = by_name[sb].outputs[sp].shape
    d_shape = by_name[db].inputs[dp].shape
    if s_shape != d_shape:
        raise ShapeError(f"connection {sb}.{sp} -> {db}.{dp}: shapes differ: {sb}.{sp} is "
                         f"{shape_str(s_shape)}, {db}.{dp} is {shape_str(d_shape)}",
                         file=conn.file, line=conn.line, block=db, port=dp)


def build_structure(spec: DiagramSpec, blocks: list | None = None) -> Structure:
    errors: list = []
    blocks = instantiate(spec, errors) if blocks is None else blocks
    by_name = {b.name: b for b in blocks}
    entry_of = {e.name: e for e in spec.blocks}
    failed = {e.name for e in spec.blocks} - set(by_name)     # reported by instantiate
    drivers: dict = {}
    where: dict = {}
    where_file: dict = {}
    lost: set = set()       # inputs wired to a block that failed: connected, source unknown
    for conn in spec.connections:
        if conn.src[0] in failed or conn.dst[0] in failed:
            lost.add(conn.dst)      # its missing ports would only repeat that block's error
            continue
        try:
            _check_connection(conn, by_name, drivers, where)
        except DiagramError as exc:
            errors.append(exc)
            failed.add(conn.dst[0])     # its unconnected inputs would only repeat this mistake
            continue
        (sb, sp), (db, dp) = conn.src, conn.dst
        drivers[(db, dp)] = (sb, sp)
        where[(db, dp)] = conn.line
        where_file[(db, dp)] = conn.file
    for blk in blocks:
        for port in blk.inputs.values():
            if (blk.name, port.name) not in drivers and not port.optional:
                if blk.name in failed or (blk.name, port.name) in lost:
                    continue        # a connection into this block was wrong: reported already
                outer = spec.input_ports.get((blk.name, port.name))
                if outer is not None:     # name the subsystem's port, where the user can fix it
                    label, ofile, oline = outer
                    errors.append(WiringError(
                        f"subsystem input port '{label}' is not connected (it drives "
                        f"{blk.name}.{port.name})", file=ofile, line=oline,
                        block=label.rsplit(".", 1)[0], port=label.rsplit(".", 1)[1]))
                    continue
                entry = entry_of.get(blk.name)
                errors.append(WiringError(
                    f"block '{blk.name}' input port '{port.name}' is not connected",
                    file=entry.file if entry else spec.file,
                    line=entry.line if entry else None, block=blk.name, port=port.name))
    for (db, dp), (sb, sp) in drivers.items():
        # a block may check the block that drives one of its inputs (a regressor against its
        # plant: the same gravity, kinematics, parameter form); None means consistent
        check = getattr(by_name[db], "check_source", None)
        message = check(dp, by_name[sb], sp) if check is not None else None
        if message:
            errors.append(WiringError(f"connection {sb}.{sp} -> {db}.{dp}: {message}",
                                      file=where_file[(db, dp)], line=where[(db, dp)],
                                      block=db, port=dp))
    if errors:
        errors[0].more = errors[1:]
        raise errors[0]

    # port-level graph: connections plus each block's feedthrough edges
    succ: dict = {}
    for blk in blocks:
        for out in blk.outputs:
            succ.setdefault(("out", blk.name, out), [])
            for inp in blk.feedthrough(out):
                succ.setdefault(("in", blk.name, inp), []).append(("out", blk.name, out))
        for inp in blk.inputs:
            succ.setdefault(("in", blk.name, inp), [])
    for (db, dp), (sb, sp) in drivers.items():
        succ.setdefault(("out", sb, sp), []).append(("in", db, dp))
    cycle = _find_cycle(succ)
    if cycle:
        names = [f"{n[1]}.{n[2]}" for n, _ in cycle] + [f"{cycle[0][0][1]}.{cycle[0][0][2]}"]
        first_block = cycle[0][0][1]
        entry = entry_of.get(first_block)
        raise AlgebraicLoopError(
            "algebraic loop: " + " -> ".join(names) + "; every port on it feeds straight "
            "through; break it with a block that has state (Integrator, a strictly proper "
            "TransferFunction)", file=entry.file if entry else spec.file,
            line=entry.line if entry else None, block=first_block)

    # block-level order: A before B when an output of A reaches B through a feedthrough input
    index = {b.name: i for i, b in enumerate(blocks)}
    block_succ: dict = {name: [] for name in index}
    for (db, dp), (sb, sp) in drivers.items():
        direct = [o for o in by_name[db].outputs if dp in by_name[db].feedthrough(o)]
        if direct and sb == db:
            # not a port-level loop (sp has no feedthrough from dp), but the block would need
            # its own output before computing it: each block is evaluated once per stage
            raise AlgebraicLoopError(
                f"block '{db}' feeds its output '{sp}' back into its input '{dp}', on which "
                f"its output '{direct[0]}' depends directly; fwdstep evaluates each block once "
                "per stage, so a block cannot drive its own direct-feedthrough input",
                file=where_file.get((db, dp), spec.file), line=where.get((db, dp)), block=db,
                port=dp)
        if direct and db not in block_succ[sb]:
            block_succ[sb].append(db)
    order = _ordered(block_succ, index)
    if order is None:
        cyc = _find_cycle(block_succ)
        raise AlgebraicLoopError(
            "blocks " + " -> ".join(a for a, _ in cyc) + f" -> {cyc[0][0]} form a loop that is "
            "only broken inside a block whose outputs have different feedthrough; fwdstep "
            "evaluates each block once per stage, so split that block in two",
            file=entry_of[cyc[0][0]].file if cyc[0][0] in entry_of else spec.file,
            line=entry_of[cyc[0][0]].line if cyc[0][0] in entry_of else None) from None
    return Structure(spec=spec, blocks=[by_name[n] for n in order], drivers=drivers)


def _ordered(succ: dict, index: dict) -> list | None:
    """A topological order of ``succ`` (node -> successors) that takes, among the nodes ready
    at each point, the one of smallest ``index`` (the diagram's own block order), so the
    schedule is the same on every run; None if there is a cycle."""
    indegree = {n: 0 for n in succ}
    for n in succ:
        for m in succ[n]:
            indegree[m] += 1
    ready = [(index[n], n) for n, k in indegree.items() if k == 0]
    heapq.heapify(ready)
    order = []
    while ready:
        _, n = heapq.heappop(ready)
        order.append(n)
        for m in succ[n]:
            indegree[m] -= 1
            if indegree[m] == 0:
                heapq.heappush(ready, (index[m], m))
    return order if len(order) == len(succ) else None


def _find_cycle(succ: dict) -> list | None:
    """One cycle of ``succ`` as a list of edges (u, v), or None.  graphlib (standard
    library) checks for one; networkx, imported only then, names it the way it always has."""
    try:
        sorter = graphlib.TopologicalSorter()
        for n, ms in succ.items():
            sorter.add(n)
            for m in ms:
                sorter.add(m, n)
        sorter.prepare()
        return None
    except graphlib.CycleError:
        import networkx as nx
        g = nx.DiGraph()
        g.add_nodes_from(succ)
        g.add_edges_from((n, m) for n, ms in succ.items() for m in ms)
        return nx.find_cycle(g)
