"""Diagram files -> a flat, evaluated ``DiagramSpec`` (structure only, no numerics).

A diagram file has these top-level keys::

    description:  free text
    parameters:   name: value            # numbers, lists, or expressions over other parameters
    blocks:       name: {type: T, ...}   # parameters of the block; or type: subsystem
    connections:  - "src.out -> dst.in, other.in"
    ports:        {inputs: {name: blk.in | [blk.in, ...]}, outputs: {name: blk.out}}  # subsystems
    simulation:   {t_final, step, solver, log_every, bound}
    log:          [blk.port, ...]
    plots:        {figure_name: [panel, ...]}   # panel: "blk.port" or [blk.port, ...]
    metrics:      {error: blk.port}

Subsystems (``type: subsystem``, ``file:``, ``parameters:``) are flattened here, recursively:
their blocks are renamed ``<subsystem>/<block>`` and their declared ports are wired through.
"""
from __future__ import annotations

import copy
import hashlib
import math
import os
import re
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fwdstep.core.errors import (ConfigError, DiagramError, ExpressionError, ParameterError, WiringError,
                     YamlError)
from fwdstep.core.expressions import MAX_ARRAY_SIZE, evaluate, names_in
from fwdstep.structure.library import lookup
from fwdstep.core.mathtext import problem as mathtext_problem
from fwdstep.core.settings import BACKENDS, SIMULATION_KEYS, SOLVER_NAMES, SimulationConfig
from fwdstep.structure.sampled import sample_subsystem
from fwdstep.structure.shapes import infer_shapes
from fwdstep.structure.model import (BlockEntry, Connection, DiagramSpec, SourceFile, _line,
                                     evaluate_ragged, evaluate_value, kind_of)
from fwdstep.core.search import SearchPath, check_regular_file
from fwdstep.core.yamlio import LineDict, LineList, parse_yaml_text, read_yaml_file

TOP_LEVEL_KEYS = ("description", "parameters", "blocks", "connections", "ports", "simulation",
                  "log", "plots", "metrics")
SUBSYSTEM_KEYS = ("type", "file", "parameters", "sample_period", "sample_offset")
MAX_STEPS = 50_000_000
MAX_SUBSYSTEM_DEPTH = 16
MAX_BLOCKS = 10_000                     # blocks after subsystem expansion
MAX_PARAMETER_NUMBERS = 20_000_000      # numbers held by all evaluated parameters (160 MiB)
MAX_PARAMETER_SECONDS = 30              # time spent evaluating parameters
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_PATH = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+$")   # plant.arm.q0
_FIGURE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_-]{0,63}$")


# ---------------------------------------------------------------------------- helpers
class Budget:
    """Limits on what loading one diagram may cost, checked as it goes (before building more):
    blocks after subsystem expansion, numbers held by evaluated parameters, and the time spent
    evaluating them.  Errors raised here are marked ``fatal``: validation stops at once."""

    def __init__(self):
        self.blocks = 0
        self.numbers = 0
        self.start = time.monotonic()

    def _fail(self, exc: DiagramError) -> DiagramError:
        exc.fatal = True
        return exc

    def add_block(self, name: str, file: str, line) -> None:
        self.blocks += 1
        if self.blocks > MAX_BLOCKS:
            raise self._fail(ConfigError(
                f"the diagram has more than {MAX_BLOCKS} blocks after subsystem expansion "
                f"(reached at '{name}'); refused before building more", file=file, line=line,
                block=name))

    def charge(self, value, what: str) -> None:
        if isinstance(value, (np.ndarray, float, int)):
            self.numbers += int(np.size(value))
        if self.numbers > MAX_PARAMETER_NUMBERS:
            raise self._fail(ExpressionError(
                f"{what}: the diagram's evaluated parameters would hold {self.numbers} numbers; "
                f"the limit is {MAX_PARAMETER_NUMBERS} ({MAX_PARAMETER_NUMBERS * 8 >> 20} MiB)"))
        spent = time.monotonic() - self.start
        if spent > MAX_PARAMETER_SECONDS:
            raise self._fail(ExpressionError(
                f"{what}: evaluating the diagram's parameters has taken {spent:.0f} s; the limit "
                f"is {MAX_PARAMETER_SECONDS} s"))


def _mapping(value, what: str, file: str, line: int | None) -> LineDict:
    if value is None:
        out = LineDict()
        out.line, out.key_lines = line, {}
        return out
    if not isinstance(value, dict):
        raise ConfigError(f"'{what}' must be a mapping, got {kind_of(value)}", file=file,
                          line=line)
    return value


def parse_override(text: str) -> tuple[str, Any]:
    """``NAME=VALUE`` from the command line; VALUE is read as a YAML scalar/flow value."""
    if "=" not in text:
        raise ConfigError(f"--set '{text}' must have the form NAME=VALUE")
    name, raw = text.split("=", 1)
    name = name.strip()
    if not _NAME.match(name) and not _PATH.match(name):
        raise ConfigError(f"--set '{text}': '{name}' is not a parameter name, "
                          "simulation.SETTING, log, BLOCK.PARAMETER or SUBSYSTEM.BLOCK.PARAMETER")
    try:
        value = parse_yaml_text(raw) if raw.strip() else None
    except YamlError:
        value = raw
    if value is None:
        raise ConfigError(f"--set '{text}' has no value")
    return name, value


def resolve_parameters(raw: LineDict, overrides: dict, file: str,
                       preset: dict | None = None, line: int | None = None,
                       budget: "Budget | None" = None) -> dict:
    """Evaluate the ``parameters:`` section (any order; references resolved by dependency).

    ``overrides`` replace raw values (``--set``); ``preset`` supplies already-evaluated values
    (parameters passed into a subsystem by its parent)."""
    raw = _mapping(raw, "parameters", file, None)
    for key in raw:
        if not isinstance(key, str) or not _NAME.match(key):
            raise ParameterError(f"parameter name '{key}' is not a valid name (letters, digits, _)",
                                 file=file, line=_line(raw, key))
    values = dict(raw)
    for name, value in (overrides or {}).items():
        if name not in values:
            import difflib
            known = ", ".join(values) or "(none)"
            close = difflib.get_close_matches(name, list(values), n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise ConfigError(f"--set {name}=...: the diagram has no parameter '{name}'; "
                              f"{hint}parameters are: {known}", file=file,
                              line=line or getattr(raw, "line", None))
        values[name] = value
    namespace: dict = dict(preset or {})
    pending = {k: v for k, v in values.items() if k not in namespace}
    # dependency order in linear time: each expression is parsed once, then Kahn's algorithm
    needs: dict = {}
    users: dict = {name: [] for name in pending}
    for name, value in pending.items():
        deps = set()
        for text in _strings_in(value):
            deps |= names_in(text)
        needs[name] = {d for d in deps if d in pending and d != name}
        for d in needs[name]:
            users[d].append(name)
    uses = {name: set(deps) for name, deps in needs.items()}     # kept: needs is consumed
    ready = [name for name in pending if not needs[name]]
    done = 0
    while done < len(ready):
        name = ready[done]
        try:
            namespace[name] = evaluate_value(pending[name], namespace, f"parameter '{name}'")
            if budget is not None:
                budget.charge(namespace[name], f"parameter '{name}'")
        except DiagramError as exc:
            if getattr(exc, "fatal", False):
                raise exc.located(file, _line(raw, name)) from None
            raise _blame_override(exc, name, uses, overrides or {}, raw, file) from None
        done += 1
        for user in users[name]:
            needs[user].discard(name)
            if not needs[user]:
                ready.append(user)
    if len(ready) < len(pending):
        left = [name for name in pending if name not in namespace]
        raise ExpressionError(f"parameters {', '.join(left)} refer to each other in a cycle",
                              file=file, line=_line(raw, left[0]))
    return namespace


#: ``Reevaluation`` plans by (document, names, other overrides, blocks)
_PLANS: dict = {}


class Reevaluation:
    """The loader's light path for moving numbers (``fwdstep.analysis.sensitivity``): which
    top-level parameters and block entries of ``spec`` read the ``--set`` names ``names``
    (top-level parameters, ``BLOCK.PARAM`` paths; on top of ``spec.overrides``), found once;
    ``entries(changes)`` evaluates them again for values of those names with the loader's
    own code (``resolve_parameters`` for the parameters that depend on the moved ones, the
    others kept as loaded; ``_Level._add_block`` for the block parameters that read them),
    every other value as ``spec`` has it.  ``applies`` is False when the names reach
    anything else (a subsystem, the simulation settings, the metrics, the log, a block
    the spec does not have): the caller loads the whole file then.  The structure is not
    checked here (the caller compares the rebuilt blocks' signatures with the loaded
    ones)."""

    def __init__(self, spec: DiagramSpec, names, cache: dict | None = None):
        self.spec, self.applies = spec, False
        self.entries_of = {e.name: e for e in spec.blocks}
        path = spec.file
        text = spec.sources[0].text if spec.sources else None
        doc = (_read_document(path, cache, shared=True) if text is None else
               _check_document(parse_yaml_text(text, file=path), path))
        # the plan depends on the document (``cache``'s own object while the file does not
        # change), the other overrides and the names only: a tuning finds it once
        # (a number's value never changes which parameters read which: only its name)
        key = None
        others = sorted(((k, v if any(True for _ in _strings_in(v)) or not isinstance(
            v, (int, float, list)) else "<numbers>") for k, v in spec.overrides.items()
            if k not in names), key=lambda kv: str(kv[0]))
        if text is None and cache is not None and not any(
                isinstance(v, np.ndarray) for _, v in others):
            key = (id(doc), tuple(names), repr(others), tuple(self.entries_of))
            got = _PLANS.get(key)
            if got is not None and got[0] is doc:
                vars(self).update(got[1])
                return
        self._plan(spec, doc, names, cache)
        if key is not None:
            _PLANS[key] = (doc, {k: v for k, v in vars(self).items()
                                 if k not in ("spec", "entries_of")})
            while len(_PLANS) > 32:
                _PLANS.pop(next(iter(_PLANS)))

    def _plan(self, spec, doc, names, cache) -> None:
        path = spec.file
        raw = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
        moved, sim, log, paths = split_overrides({n: 0.0 for n in names}, raw)
        base, _, _, base_paths = split_overrides(spec.overrides, raw)
        if sim or log is not None:
            return
        values = dict(raw)
        values.update(base)
        changed = set(moved)
        grown = True
        while grown:                 # the parameters that read a moved one, transitively
            grown = False
            for name, value in values.items():
                if name not in changed and any(names_in(t) & changed
                                               for t in _strings_in(value)):
                    changed.add(name)
                    grown = True

        def reads(value) -> bool:
            if isinstance(value, dict):
                return any(reads(v) for v in value.values())
            return any(names_in(t) & changed for t in _strings_in(value))

        for section in ("simulation", "metrics", "log", "plots"):
            if reads(doc.get(section)):
                return
        sets = dict(base_paths)
        sets.update(paths)
        entries = self.entries_of
        blocks = doc.get("blocks") if isinstance(doc.get("blocks"), dict) else {}
        self.work = []               # (block name, its body reduced to the keys, line, sets)
        for name, body in blocks.items():
            if not isinstance(body, dict):
                continue
            mine = {k[1:]: v for k, v in sets.items() if k[0] == name}
            if body.get("type") == "subsystem":
                if reads(body.get("parameters")) or any(
                        (name,) + r in paths or reads(v) for r, v in mine.items()):
                    return
                continue
            keys = [k for k in body if k != "type" and (k,) not in mine and reads(body[k])]
            keys += [r[0] for r, v in mine.items() if (name,) + r in paths or reads(v)]
            if not keys:
                continue
            if name not in entries:
                return
            small = LineDict({k: v for k, v in body.items() if k == "type" or k in keys})
            small.line, small.key_lines = body.line, dict(getattr(body, "key_lines", {}))
            self.work.append((name, small, _line(blocks, name),
                              {r: v for r, v in mine.items() if r[0] in keys}))
        self.raw, self.changed = raw, changed
        self.level = _Level(doc, path, {}, "", stack=(os.path.realpath(path),), cache=cache)
        self.line = _line(doc, "parameters")
        self.applies = True

    def entries(self, changes: dict) -> dict:
        """{block name: BlockEntry} of the blocks that read ``changes`` ({name: value},
        the names given), evaluated again; the entry's other parameters (shapes the wiring
        fixed included) as loaded."""
        moved, _, _, paths = split_overrides(changes, self.raw)
        base, _, _, base_paths = split_overrides(self.spec.overrides, self.raw)
        given = {k: v for k, v in base.items() if k in self.changed}
        given.update(moved)           # (the --set values as given: a message blames them)
        ns = resolve_parameters(self.raw, given, self.spec.file,
                                preset={k: v for k, v in self.spec.parameters.items()
                                        if k not in self.changed}, line=self.line)
        level = self.level
        level.ns, level.blocks, level.budget = ns, [], Budget()
        out = {}
        for name, small, line, sets in self.work:
            sets = {r: paths.get((name,) + r, base_paths.get((name,) + r, v))
                    for r, v in sets.items()}
            level._add_block(name, small, line, sets)
            got = level.blocks.pop()
            old = self.entries_of[name]
            params = dict(old.params)
            params.update(got.params)
            out[name] = BlockEntry(old.name, old.type_name, old.cls, params, old.file,
                                   old.line, old.key_lines)
        return out


def _blame_override(exc: DiagramError, name: str, uses: dict, overrides: dict, raw,
                    file: str) -> DiagramError:
    """A parameter that fails only because a ``--set`` value reached it: the error names the
    ``--set`` (the user's mistake) first, at that parameter's line, then what it broke."""
    reached, todo = [], [name]
    seen = set()
    while todo:                      # the parameters ``name`` depends on, transitively
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        if current in overrides and current not in reached:
            reached.append(current)
        todo.extend(uses.get(current, ()))
    if not reached:
        return exc.located(file, _line(raw, name))
    culprit = reached[0] if name not in overrides else name
    shown = overrides[culprit]
    if culprit == name:
        why = exc.message
    else:
        inner = exc.message
        if "cannot be evaluated: " in inner:       # the expression itself is the file's
            inner = inner.split("cannot be evaluated: ", 1)[1]
        elif inner.startswith(f"parameter '{name}'"):
            inner = inner[len(f"parameter '{name}'"):].lstrip(": ")
        why = f"parameter '{name}', which uses {culprit}, cannot be evaluated: {inner}"
    out = type(exc)(f"--set {culprit}={shown}: {why}", file=file, line=_line(raw, culprit),
                    block=exc.block, port=exc.port)
    return out


def unused_parameters(raw, overrides: dict, used: set) -> list:
    """The top-level parameters no value of the run reads, directly or through another
    parameter: e.g. ``K`` after ``--set Ks.gain=80*eye(2)`` replaced the only use of it, or
    ``t_final`` after ``--set simulation.t_final=2``.  Shown as such in the record."""
    if not isinstance(raw, dict):
        return []
    values = {**raw, **(overrides or {})}
    reached, todo = set(), [n for n in used if n in values]
    while todo:
        name = todo.pop()
        if name in reached:
            continue
        reached.add(name)
        for text in _strings_in(values[name]):
            todo.extend(n for n in names_in(text) if n in values)
    return [name for name in values if name not in reached]


def _strings_in(value):
    if isinstance(value, str):
        yield value
    elif isinstance(value, list):
        for v in value:
            yield from _strings_in(v)


def parse_signal(text: Any, what: str, file: str, line: int | None) -> tuple[str, str]:
    if not isinstance(text, str) or "." not in text:
        raise ConfigError(f"{what}: '{text}' is not a signal name of the form block.port",
                          file=file, line=line)
    block, port = text.strip().rsplit(".", 1)
    if not block or not port:
        raise ConfigError(f"{what}: '{text}' is not a signal name of the form block.port",
                          file=file, line=line)
    return block, port


def _parse_connection(text: Any, file: str, line: int | None):
    if not isinstance(text, str) or "->" not in text:
        raise WiringError(f"connection {text!r} must have the form 'block.out -> block.in[, ...]'",
                          file=file, line=line)
    left, right = text.split("->", 1)
    src = parse_signal(left, f"connection '{text}'", file, line)
    dsts = [parse_signal(part, f"connection '{text}'", file, line)
            for part in right.split(",") if part.strip()]
    if not dsts:
        raise WiringError(f"connection '{text}' has no destination", file=file, line=line)
    return src, dsts


# ---------------------------------------------------------------------------- expansion
class _Failed(Exception):
    """A block or subsystem that was already reported: connections to it are skipped."""


def _suggest(name: str, names, what: str) -> str:
    import difflib
    names = list(names)
    close = difflib.get_close_matches(name, names, n=1)
    if close:
        return f"did you mean '{close[0]}'?"
    return f"{what} are: {', '.join(names) or '(none)'}"


class _Level:
    """One diagram file being expanded (the top level or a subsystem).

    ``sets`` holds the ``--set`` paths below this level, ``{("blk", "param"): value,
    ("sub", "param"): value, ("sub", "blk", "param"): value, ...}``.  ``errors`` is shared by
    all levels of one load: a bad block or connection is recorded and expansion goes on, so
    ``fwdstep validate`` can report every mistake at once."""

    def __init__(self, doc: LineDict, file: str, namespace: dict, prefix: str, stack: tuple,
                 cache: dict | None = None, sets: dict | None = None,
                 errors: list | None = None, budget: Budget | None = None,
                 search: SearchPath | None = None):
        self.doc, self.file, self.ns, self.prefix, self.stack = doc, file, namespace, prefix, stack
        self.cache = cache
        self.sets = sets or {}
        self.errors = [] if errors is None else errors
        self.budget = budget or Budget()
        self.search = search or SearchPath(file)
        self.blocks: list[BlockEntry] = []
        self.connections: list[Connection] = []
        self.local_blocks: dict[str, str] = {}  # local name -> "block" | "subsystem" | "failed"
        self.children: dict[str, "_Level"] = {}       # subsystem -> its expanded level
        self.sub_inputs: dict[str, dict] = {}         # subsystem -> input name -> [(blk, port)]
        self.sub_outputs: dict[str, dict] = {}        # subsystem -> output name -> (blk, port)
        self.aliases: dict[str, str] = {}
        self.input_ports: dict = {}     # (block, port) inside -> (outermost "sub.port", file, line)
        self.signal_info: dict = {}     # "sub/blk.port" -> {label, unit, components} declared below
        self.signal_lines: dict = {}    # "sub/blk.port" -> (file, line, as written) of those
        self.sampled: dict = {}         # sampled subsystem path -> {"period", "offset"}
        self.used: set = set()          # names of this level's parameters its values read

    def uses(self, value) -> None:
        """Note the parameters an expression (or list of them) of this level reads."""
        for text in _strings_in(value):
            self.used |= names_in(text)

    def full(self, local: str) -> str:
        return f"{self.prefix}{local}"

    def dotted(self, *parts) -> str:
        """A --set path as the user writes it: 'plant.arm.q0'."""
        return ".".join([p for p in self.prefix.split("/") if p] + list(parts))

    def _record(self, exc: DiagramError) -> None:
        if getattr(exc, "fatal", False):
            raise exc
        self.errors.append(exc)

    def expand(self):
        doc, file = self.doc, self.file
        blocks = doc.get("blocks")
        if blocks is None:
            raise ConfigError("the diagram has no 'blocks:' section", file=file, line=doc.line)
        blocks = _mapping(blocks, "blocks", file, _line(doc, "blocks"))
        if not blocks:
            raise ConfigError("'blocks:' is empty", file=file, line=_line(doc, "blocks"))
        sets: dict = {}
        for path, value in self.sets.items():
            sets.setdefault(path[0], {})[path[1:]] = value
        for first, below in sets.items():
            if first not in blocks:
                what = "the diagram" if not self.prefix else f"subsystem '{self.prefix[:-1]}'"
                names = [b for b in blocks if isinstance(b, str)]
                self._record(ConfigError(
                    f"--set {self.dotted(first, *next(iter(below)))}=...: {what} has no block "
                    f"'{first}'; "
                    f"{_suggest(first, names, 'blocks')}", file=file, line=_line(doc, "blocks")))
        for name, body in blocks.items():
            line = _line(blocks, name)
            try:
                if not isinstance(name, str) or not _NAME.match(name):
                    raise ConfigError(f"block name '{name}' is not valid (letters, digits and _, "
                                      "not starting with a digit)", file=file, line=line)
                if not isinstance(body, dict):
                    raise ConfigError(f"block '{name}' must be a mapping with a 'type:' key",
                                      file=file, line=line)
                if "type" not in body:
                    raise ConfigError(f"block '{name}' has no 'type:' (the block type, e.g. "
                                      "'type: Gain'; 'fwdstep blocks' lists them)", file=file,
                                      line=line)
                if body["type"] == "subsystem":
                    self._expand_subsystem(name, body, line, sets.get(name, {}))
                else:
                    self._add_block(name, body, line, sets.get(name, {}))
            except _Failed:         # its inner mistakes are recorded already
                self.local_blocks[name] = "failed"
            except DiagramError as exc:
                self._record(exc)
                if isinstance(name, str):
                    self.local_blocks[name] = "failed"
        self._connections()
        if self.prefix:             # the top level's log: is read by load_spec
            self._declared_labels()

    def _declared_labels(self):
        """A subsystem file's ``log:`` mappings name its signals (label, unit, components);
        recorded under the block port each resolves to, so that the names follow the signal
        out through the subsystem's ``ports: outputs:`` (an outer declaration wins)."""
        log = self.doc.get("log")
        if log is None:
            return
        file = self.file
        if not isinstance(log, list):
            self._record(ConfigError("'log:' must be a list of block.port names", file=file,
                                     line=_line(self.doc, "log")))
            return
        for i, entry in enumerate(log):
            line = _line(log, i)
            try:
                declared: dict = {}
                name = signal_entry(entry, declared, "log", file, line)
                blk, port = parse_signal(name, "log", file, line)
                src = self.resolve_src(blk, port, file, line, "log")
            except _Failed:
                continue
            except DiagramError as exc:
                self._record(exc)
                continue
            if declared:
                merge_signal_info(self.signal_info, f"{src[0]}.{src[1]}", declared[str(name)])
                self.signal_lines[f"{src[0]}.{src[1]}"] = (file, line, str(name))

    def _add_block(self, name: str, body: LineDict, line, sets: dict):
        file = self.file
        type_name = body["type"]
        try:
            cls = lookup(str(type_name))
        except DiagramError as exc:
            raise exc.located(file, _line(body, "type")) from None
        self.budget.add_block(self.full(name), file, line)
        items = [(key, value, _line(body, key), False) for key, value in body.items()
                 if key != "type"]
        for rest, value in sets.items():
            key = rest[0]
            if len(rest) != 1 or key not in cls.params:
                shown = self.dotted(name, *rest)
                if len(rest) != 1:
                    why = (f"block '{self.full(name)}' is a {type_name}, not a subsystem; write "
                           f"{self.dotted(name)}.PARAMETER")
                else:
                    why = (f"block '{self.full(name)}' ({type_name}) has no parameter '{key}'; "
                           f"{_suggest(key, cls.params, 'parameters')}")
                raise ParameterError(f"--set {shown}=...: {why}", file=file, line=line,
                                     block=self.full(name))
            items = [item for item in items if item[0] != key]
            items.append((key, value, _line(body, key) if key in body else line, True))
        params = {}
        key_lines = {}
        for key, value, kline, from_set in items:
            key_lines[key] = kline
            what = (f"--set {self.dotted(name, key)}" if from_set else
                    f"block '{self.full(name)}' parameter '{key}'")
            decl = cls.params.get(key)
            if decl is None:
                raise ParameterError(f"block '{self.full(name)}' ({type_name}) has no parameter "
                                     f"'{key}'; valid parameters are: "
                                     f"{', '.join(cls.params) or '(none)'}", file=file,
                                     line=kline, block=self.full(name))
            if decl.kind == "file" and isinstance(value, str) and value:
                params[key] = self.search.data_file(value, None if from_set else file)
                source = SourceFile(params[key], "file", value, "" if from_set else file)
                if os.path.isfile(params[key]) and source not in self.search.read:
                    self.search.read.append(source)
            elif decl.kind in ("str", "choice", "names", "file"):
                params[key] = value
            elif decl.kind == "bool" and isinstance(value, bool):
                params[key] = value
            else:
                try:
                    self.uses(value)
                    params[key] = (evaluate_ragged(value, self.ns, what) if decl.ragged else
                                   evaluate_value(value, self.ns, what))
                    if not (isinstance(value, str) and value.strip() in self.ns):
                        self.budget.charge(params[key], what)    # a bare name shares its array
                except DiagramError as exc:
                    raise exc.located(file, kline) from None
        self.local_blocks[name] = "block"
        self.blocks.append(BlockEntry(self.full(name), str(type_name), cls, params, file, line,
                                      key_lines))

    def _expand_subsystem(self, name: str, body: LineDict, line, sets: dict):
        file = self.file
        allowed = SUBSYSTEM_KEYS
        for key in body:
            if key not in allowed:
                raise ParameterError(f"subsystem '{self.full(name)}' has no key '{key}'; keys are: "
                                     f"{', '.join(allowed)}", file=file, line=_line(body, key))
        if "file" not in body or not isinstance(body["file"], str):
            raise ConfigError(f"subsystem '{self.full(name)}' needs 'file:' (a path to a diagram)",
                              file=file, line=line)
        if len(self.stack) > MAX_SUBSYSTEM_DEPTH:     # stack = this file and its parents
            raise ConfigError(f"subsystems are nested more than {MAX_SUBSYSTEM_DEPTH} deep",
                              file=file, line=line)
        path = self.search.resolve(body["file"], file, f"subsystem '{self.full(name)}'",
                                   _line(body, "file"))
        self.search.read.append(SourceFile(path, "subsystem", body["file"], file))
        if os.path.realpath(path) in self.stack:     # realpath: symbolic links too
            chain = " -> ".join(os.path.basename(p) for p in self.stack + (path,))
            raise ConfigError(f"subsystem '{self.full(name)}' includes itself: {chain}",
                              file=file, line=_line(body, "file"))
        child_doc = self.search.documents.get(os.path.realpath(path))
        if child_doc is None:       # each file parsed once per load; expansion never mutates it
            child_doc = self.search.documents[os.path.realpath(path)] = _read_document(
                path, self.cache)
        passed = _mapping(body.get("parameters"), "parameters", file, _line(body, "parameters"))
        child_params = child_doc.get("parameters") or {}
        child_blocks = child_doc.get("blocks") if isinstance(child_doc.get("blocks"), dict) else {}
        passed_items = [(key, value, _line(passed, key), f"subsystem '{self.full(name)}' "
                         f"parameter '{key}'") for key, value in passed.items()]
        child_sets = {}
        timing = {rest[0]: value for rest, value in sets.items()
                  if len(rest) == 1 and rest[0] in ("sample_period", "sample_offset")
                  and rest[0] not in child_params}
        if timing:                 # --set ctrl.sample_period=0: the body as if written so
            original, body = body, LineDict(body)
            body.line, body.key_lines = original.line, dict(getattr(original, "key_lines", {}))
            body.update(timing)
            sets = {rest: value for rest, value in sets.items() if rest[0] not in timing}
        for rest, value in sets.items():
            if len(rest) == 1 and rest[0] in child_params:
                passed_items = [item for item in passed_items if item[0] != rest[0]]
                passed_items.append((rest[0], value, _line(body, "parameters") or line,
                                     f"--set {self.dotted(name, rest[0])}"))
            elif len(rest) == 1:
                raise ParameterError(
                    f"--set {self.dotted(name, rest[0])}=...: subsystem '{self.full(name)}' "
                    f"({body['file']}) has no parameter '{rest[0]}'; "
                    f"{_suggest(rest[0], list(child_params), 'parameters')} (a block's "
                    f"parameter is {self.dotted(name)}.BLOCK.PARAMETER)", file=file, line=line)
            else:
                child_sets[rest] = value
        overrides = {}
        for key, value, kline, what in passed_items:
            try:
                self.uses(value)
                overrides[key] = evaluate_value(value, self.ns, what)
            except DiagramError as exc:
                raise exc.located(file, kline) from None
        for key, value, kline, what in passed_items:
            if key not in child_params:
                known = ", ".join(child_params) or "(none)"
                raise ParameterError(f"subsystem '{self.full(name)}' ({body['file']}) has no "
                                     f"parameter '{key}'; parameters are: {known}", file=file,
                                     line=kline)
        ns = resolve_parameters(child_params, {}, path, preset=overrides, budget=self.budget)
        child = _Level(child_doc, path, ns, f"{self.full(name)}/",
                       stack=self.stack + (os.path.realpath(path),), cache=self.cache,
                       sets=child_sets, errors=self.errors, budget=self.budget,
                       search=self.search)
        before = len(self.errors)
        child.expand()
        if len(self.errors) > before:
            raise _Failed()
        ports = _mapping(child_doc.get("ports"), "ports", path, _line(child_doc, "ports"))
        ins = _mapping(ports.get("inputs"), "ports.inputs", path, _line(ports, "inputs"))
        outs = _mapping(ports.get("outputs"), "ports.outputs", path, _line(ports, "outputs"))
        self.sub_inputs[name] = {}
        for pname, targets in ins.items():
            tl = targets if isinstance(targets, list) else [targets]
            resolved = []
            for tgt in tl:
                blk, port = parse_signal(tgt, f"subsystem input '{pname}'", path, _line(ins, pname))
                resolved.extend(child.resolve_dst(blk, port, path, _line(ins, pname),
                                                  f"subsystem input '{pname}'"))
            self.sub_inputs[name][pname] = resolved
            for target in resolved:
                self.input_ports[target] = (f"{self.full(name)}.{pname}", file, line)
        self.signal_info.update(child.signal_info)
        self.signal_lines.update(child.signal_lines)
        self.sampled.update(child.sampled)
        self.sub_outputs[name] = {}
        for pname, source in outs.items():
            blk, port = parse_signal(source, f"subsystem output '{pname}'", path, _line(outs, pname))
            src = child.resolve_src(blk, port, path, _line(outs, pname),
                                    f"subsystem output '{pname}'")
            self.sub_outputs[name][pname] = src
            self.aliases[f"{self.full(name)}.{pname}"] = f"{src[0]}.{src[1]}"
        self.aliases.update(child.aliases)
        for target, where in child.input_ports.items():
            self.input_ports.setdefault(target, where)
        self.blocks.extend(child.blocks)
        self.connections.extend(child.connections)
        if "sample_period" in body or "sample_offset" in body:   # a sampled controller
            inner = dict(self.sub_outputs[name])
            sample_subsystem(self, name, body, file, line)
            for pname, held in self.sub_outputs[name].items():   # a held output: same names
                known = self.signal_info.get(f"{inner[pname][0]}.{inner[pname][1]}")
                if known and held != inner[pname]:
                    merge_signal_info(self.signal_info, f"{held[0]}.{held[1]}", known)
        self.children[name] = child
        self.local_blocks[name] = "subsystem"

    def resolve_src(self, blk: str, port: str, file, line, what: str = "connection") -> tuple:
        """The (block, port) that drives ``blk.port`` at this level (through subsystems)."""
        return self._resolve(blk, port, "output", file, line, what)

    def resolve_dst(self, blk: str, port: str, file, line, what: str = "connection") -> list:
        """The inner (block, port) inputs that ``blk.port`` at this level stands for."""
        return self._resolve(blk, port, "input", file, line, what)

    def _resolve(self, blk, port, direction, file, line, what):
        head, dot, rest = blk.partition(".")
        kind = self.local_blocks.get(head)
        if kind is None:
            raise self._no_block(head, file, line, what)
        if kind == "failed":
            raise _Failed()
        if dot:             # sub.block.port: a port of a block inside a subsystem
            if kind != "subsystem":
                raise WiringError(f"{what} names '{blk}.{port}', but '{self.full(head)}' is a "
                                  "block, not a subsystem", file=file, line=line,
                                  block=self.full(head))
            return self.children[head]._resolve(rest, port, direction, file, line, what)
        if kind != "subsystem":
            own = (self.full(blk), port)
            return own if direction == "output" else [own]
        ports = self.sub_outputs[blk] if direction == "output" else self.sub_inputs[blk]
        if port not in ports:
            raise WiringError(f"subsystem '{self.full(blk)}' has no {direction} port '{port}'; "
                              f"{direction} ports are: {', '.join(ports) or '(none)'}", file=file,
                              line=line, block=self.full(blk), port=port)
        return ports[port]

    def _no_block(self, blk, file, line, what):
        import difflib
        names = list(self.local_blocks)
        close = difflib.get_close_matches(blk, names, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; blocks are: {', '.join(names)}"
        return WiringError(f"{what} names block '{blk}', which does not exist{hint}",
                           file=file, line=line, block=self.full(blk))

    def _connections(self):
        doc, file = self.doc, self.file
        conns = doc.get("connections")
        if conns is None:
            return
        if not isinstance(conns, list):
            self._record(ConfigError("'connections:' must be a list of 'src.out -> dst.in' "
                                     "strings", file=file, line=_line(doc, "connections")))
            return
        for i, text in enumerate(conns):
            line = _line(conns, i)
            try:
                (sb, sp), dsts = _parse_connection(text, file, line)
                src = self.resolve_src(sb, sp, file, line)
                for db, dp in dsts:
                    try:
                        for dst in self.resolve_dst(db, dp, file, line):
                            self.connections.append(Connection(src, dst, file, line, text))
                    except _Failed:
                        pass
            except _Failed:
                pass
            except DiagramError as exc:
                self._record(exc)


SIGNAL_ENTRY_KEYS = ("signal", "label", "unit", "components")


def signal_entry(entry, info: dict, where: str, file: str, line) -> Any:
    """A ``log:``/``plots:`` entry -> its signal name; ``{signal: e.y, label: "Δq", unit: rad,
    components: [joint 1, joint 2]}`` also records how figures name it in ``info``."""
    if not isinstance(entry, dict):
        return entry
    extra = [k for k in entry if k not in SIGNAL_ENTRY_KEYS]
    if extra or "signal" not in entry:
        raise ConfigError(f"{where}: a signal mapping takes 'signal:' and optionally 'label:', "
                          f"'unit:', 'components:'" + (f"; '{extra[0]}' is not one of them"
                                                       if extra else ""), file=file, line=line)
    comps = entry.get("components")
    if comps is not None and not (isinstance(comps, list) and comps):
        raise ConfigError(f"{where}: components of {entry['signal']} must be a list of names",
                          file=file, line=line)
    meta = {"label": None if entry.get("label") is None else str(entry["label"]),
            "unit": str(entry.get("unit") or ""),
            "components": None if comps is None else [str(c) for c in comps]}
    texts = [("label", meta["label"]), ("unit", meta["unit"])] + [
        ("components", c) for c in meta["components"] or ()]
    for key, text in texts:
        check_figure_text(text, f"{where}: the {key[:-1] if key == 'components' else key} "
                          f"of {entry['signal']}", file, _line(entry, key) or line)
    merge_signal_info(info, str(entry["signal"]), meta)
    return entry["signal"]


def merge_signal_info(info: dict, key: str, meta: dict) -> None:
    """``info[key]`` takes what ``meta`` declares (its non-empty label, unit, components)."""
    old = info.setdefault(key, {"label": None, "unit": "", "components": None})
    old.update({k: v for k, v in meta.items() if v})


def check_figure_text(text: str | None, what: str, file: str, line) -> None:
    """Refuse a text figures will show whose mathtext matplotlib could not typeset (a brace
    never closed, a ^ with nothing after it), at load time with file and line: a typo must
    not wait for the end of a run (fwdstep.core.mathtext; no matplotlib imported here)."""
    if not text:
        return
    why = mathtext_problem(text)
    if why is not None:
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise ConfigError(f"{what} {shown!r} is not valid mathtext: {why} (mathtext goes "
                          "between two $; write \\$ for a dollar sign)", file=file, line=line)


def _read_document(path: str, cache: dict | None = None, shared: bool = False) -> LineDict:
    """Parse and check a diagram file.  With ``cache`` (a dict kept by the caller, e.g. a
    sweep building many variants), each file is parsed once per (path, mtime, size) and every
    caller gets its own deep copy of the document (``shared``: the cache's own, for a
    caller that never changes it).  The key includes the SHA-256 of the
    file's bytes: a file edited in place within the clock's resolution, to the same size, is
    parsed again (its bytes are read on every call; parsing is what the cache saves)."""
    if cache is not None:
        try:
            check_regular_file(path)
            st = os.stat(path)
            with open(path, "rb") as fh:
                digest = hashlib.sha256(fh.read()).digest()
            key = (os.path.realpath(path), st.st_mtime_ns, st.st_size, digest)
        except OSError:
            key = None
        if key is not None:
            if key not in cache:
                cache[key] = _read_document(path)
            return cache[key] if shared else copy.deepcopy(cache[key])
    check_regular_file(path)        # never open a FIFO, a device or stdin
    return _check_document(read_yaml_file(path), path)


def _check_document(doc, path: str) -> LineDict:
    """A parsed diagram, checked as a whole: a mapping with diagram sections only."""
    if doc is None:
        raise YamlError("the file is empty; a diagram needs at least a 'blocks:' section",
                        file=path, line=1)
    if not isinstance(doc, dict):
        raise YamlError(f"the top level must be a mapping (blocks:, connections:, ...), got "
                        f"{kind_of(doc)}", file=path, line=getattr(doc, "line", 1))
    if not any(key in TOP_LEVEL_KEYS for key in doc):
        # not a diagram at all: say so without quoting any of its content
        raise ConfigError(f"not a diagram: none of its {len(doc)} top-level keys is a diagram "
                          f"section ({', '.join(TOP_LEVEL_KEYS)})", file=path, line=doc.line)
    for key in doc:
        if key not in TOP_LEVEL_KEYS:
            import difflib
            close = difflib.get_close_matches(str(key), TOP_LEVEL_KEYS, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise ConfigError(f"unknown top-level key '{key}'{hint} (valid keys: "
                              f"{', '.join(TOP_LEVEL_KEYS)})", file=path, line=_line(doc, key))
    return doc


def defaults_note(sim: SimulationConfig) -> str | None:
    """The run header's line for simulation settings a diagram did not give, or None."""
    if not sim.defaulted:
        return None
    values = {"t_final": f"t_final = {sim.t_final:g} s", "step": f"step = {sim.step:g} s"}
    given = "no simulation: section" if not sim.given else \
        f"no simulation.{', simulation.'.join(sim.defaulted)}"
    return f"the diagram has {given}; using the defaults " + \
        ", ".join(values[k] for k in sim.defaulted)


def _simulation(doc: LineDict, ns: dict, file: str) -> SimulationConfig:
    raw = _mapping(doc.get("simulation"), "simulation", file, _line(doc, "simulation"))
    cfg = SimulationConfig()
    cfg.defaulted = tuple(k for k in ("t_final", "step") if k not in raw)
    cfg.given = doc.get("simulation") is not None
    for key in raw:
        if key not in SIMULATION_KEYS:
            raise ConfigError(f"simulation has no setting '{key}'; settings are: "
                              f"{', '.join(SIMULATION_KEYS)}", file=file, line=_line(raw, key))

    def number(key):
        if isinstance(raw[key], float) and not math.isfinite(raw[key]):
            raise ConfigError(f"simulation.{key} must be a finite number, got {raw[key]}",
                              file=file, line=_line(raw, key))
        try:
            v = evaluate_value(raw[key], ns, f"simulation.{key}")
        except DiagramError as exc:
            raise exc.located(file, _line(raw, key)) from None
        if isinstance(v, bool) or not isinstance(v, float):
            raise ConfigError(f"simulation.{key} must be a number, got {raw[key]!r}", file=file,
                              line=_line(raw, key))
        return v

    if "solver" in raw:
        if raw["solver"] not in SOLVER_NAMES:
            raise ConfigError(f"simulation.solver '{raw['solver']}' is unknown; solvers are: "
                              f"{', '.join(SOLVER_NAMES)}", file=file, line=_line(raw, "solver"))
        cfg.solver = raw["solver"]
    if "backend" in raw:
        if raw["backend"] not in BACKENDS:
            raise ConfigError(f"simulation.backend '{raw['backend']}' is unknown; backends are: "
                              "numpy, compiled", file=file, line=_line(raw, "backend"))
        cfg.backend = raw["backend"]
    if "t_final" in raw:
        cfg.t_final = number("t_final")
        if not cfg.t_final > 0 or not math.isfinite(cfg.t_final):
            raise ConfigError(f"simulation.t_final must be a positive number, got {cfg.t_final:g}",
                              file=file, line=_line(raw, "t_final"))
    if "step" in raw:
        cfg.step = number("step")
        if not cfg.step > 0 or not math.isfinite(cfg.step):
            raise ConfigError(f"simulation.step must be a positive finite number, got "
                              f"{cfg.step:g}", file=file, line=_line(raw, "step"))
    if cfg.step > cfg.t_final:
        raise ConfigError(f"simulation.step ({cfg.step:g}) is larger than t_final "
                          f"({cfg.t_final:g})", file=file, line=_line(raw, "step"))
    steps = cfg.t_final / cfg.step
    if steps > MAX_STEPS:
        raise ConfigError(f"simulation would take {steps:.3g} steps (t_final / step); the limit "
                          f"is {MAX_STEPS:.0e}", file=file, line=_line(raw, "step"))
    if abs(steps - round(steps)) > 1e-6 * max(1.0, steps):
        raise ConfigError(f"simulation.t_final ({cfg.t_final:g}) is not a whole number of steps of "
                          f"{cfg.step:g}", file=file, line=_line(raw, "t_final"))
    if "log_every" in raw:
        v = number("log_every")
        if v != math.floor(v) or v < 1:
            raise ConfigError(f"simulation.log_every must be a whole number of steps >= 1, got "
                              f"{v:g}", file=file, line=_line(raw, "log_every"))
        cfg.log_every = int(v)
    for key in ("rtol", "atol"):
        if key in raw:
            setattr(cfg, key, number(key))
            if not getattr(cfg, key) > 0:
                raise ConfigError(f"simulation.{key} must be positive, got {raw[key]!r}",
                                  file=file, line=_line(raw, key))
    if "stability_check" in raw:
        if not isinstance(raw["stability_check"], bool):
            raise ConfigError(f"simulation.stability_check must be true or false, got "
                              f"{raw['stability_check']!r}", file=file,
                              line=_line(raw, "stability_check"))
        cfg.stability_check = raw["stability_check"]
    if "bound" in raw:
        cfg.bound = number("bound")
        if not cfg.bound > 0:
            raise ConfigError(f"simulation.bound must be positive, got {cfg.bound:g}", file=file,
                              line=_line(raw, "bound"))
    return cfg


def count_blocks(path: str, doc, search: SearchPath, cache: dict | None,
                 memo: dict | None = None, stack: tuple = ()) -> int:
    """Blocks of ``doc`` after subsystem expansion, counted from the files alone (each parsed
    once), so a fan-out of small files is refused before anything is built.  Files that cannot
    be found or read count 0 here: expansion reports them."""
    memo = {} if memo is None else memo
    blocks = doc.get("blocks") if isinstance(doc, dict) else None
    if not isinstance(blocks, dict):
        return 0
    total = 0
    for body in blocks.values():
        if not (isinstance(body, dict) and body.get("type") == "subsystem"
                and isinstance(body.get("file"), str)):
            total += 1
            continue
        try:
            child = search.resolve(body["file"], path, "subsystem", None)
        except DiagramError:
            continue
        key = os.path.realpath(child)
        if key in stack or len(stack) > MAX_SUBSYSTEM_DEPTH:
            continue
        if key not in memo:
            try:
                child_doc = search.documents.get(key)
                if child_doc is None:
                    child_doc = search.documents[key] = _read_document(child, cache)
            except DiagramError:
                memo[key] = 0
                continue
            memo[key] = count_blocks(child, child_doc, search, cache, memo, stack + (key,))
        total += memo[key]
    return total


def split_overrides(overrides: dict, parameters) -> tuple:
    """``--set`` names -> (top-level parameters, simulation settings, log list or None,
    block/subsystem paths ``{("plant", "arm", "q0"): value}``)."""
    params, sim, log, paths = {}, {}, None, {}
    for name, value in (overrides or {}).items():
        if name == "log" and "log" not in (parameters or {}):
            log = value if isinstance(value, list) else [value]
        elif name.startswith("simulation."):
            sim[name.split(".", 1)[1]] = value
        elif "." in name:
            paths[tuple(name.split("."))] = value
        else:
            params[name] = value
    return params, sim, log, paths


def load_spec(path: str, overrides: dict | None = None,
              cache: dict | None = None, redirects: dict | None = None,
              text: str | None = None) -> DiagramSpec:
    """Read, check and flatten a diagram file (and its subsystems).  ``cache``: see
    ``_read_document`` (parse each file once across many loads).

    ``overrides`` (``--set``): ``NAME`` a top-level parameter, ``simulation.SETTING``,
    ``log`` (the list of logged signals), ``BLOCK.PARAM`` a block's parameter,
    ``SUB.PARAM`` a subsystem's parameter, ``SUB.BLOCK.PARAM`` (any depth) a parameter of a
    block inside a subsystem.  Every mistake that can be found is collected; the first is
    raised with the others in its ``more`` attribute (``fwdstep validate`` prints them all).

    ``redirects`` ``{(including file, name as written): file}`` makes ``file:`` and
    ``Param("file")`` names read other files: a run's recorded copy
    (``fwdstep.results.provenance``).  The spec keeps the overrides as given and every file
    read (``spec.sources``), so a run can record what made it.

    ``text``: the diagram's YAML text, read instead of the file ``path`` (which then only
    names it in messages and places it: its ``file:`` names are relative to its folder);
    ``fwdstep.Diagram().load()`` passes what it built."""
    errors: list = []
    spec = None
    try:
        spec = _load(os.path.normpath(path), overrides, cache, errors, redirects, text)
    except DiagramError as exc:
        errors.append(exc)
    if errors:
        first = errors[0]
        first.more = errors[1:]
        raise first
    spec.overrides = dict(overrides or {})
    return spec


def _load(path: str, overrides: dict | None, cache: dict | None, errors: list,
          redirects: dict | None = None, text: str | None = None) -> DiagramSpec:
    cache = {} if cache is None else cache     # a subsystem used many times is parsed once
    if text is None:
        doc = _read_document(path, cache)
    else:
        doc = _check_document(parse_yaml_text(text, file=path), path)
    given = dict(overrides or {})
    budget = Budget()
    overrides, sim_overrides, log_override, paths = split_overrides(
        overrides, doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {})
    ns = resolve_parameters(doc.get("parameters"), overrides, path,
                            line=_line(doc, "parameters"), budget=budget)
    if sim_overrides or log_override is not None:  # --set simulation.t_final=20, --set log=[..]
        original, doc = doc, LineDict(doc)
        doc.line, doc.key_lines = original.line, dict(getattr(original, "key_lines", {}))
    if sim_overrides:
        sim_raw = _mapping(doc.get("simulation"), "simulation", path, _line(doc, "simulation"))
        merged = LineDict(sim_raw)
        merged.line, merged.key_lines = sim_raw.line, dict(getattr(sim_raw, "key_lines", {}))
        merged.update(sim_overrides)
        doc["simulation"] = merged
    if log_override is not None:
        doc["log"] = log_override
    search = SearchPath(path, redirects)
    search.read.append(SourceFile(os.path.abspath(path), "diagram", text=text))
    total = count_blocks(path, doc, search, cache)
    if total > MAX_BLOCKS:
        raise ConfigError(f"the diagram would have {total} blocks after subsystem expansion; the "
                          f"limit is {MAX_BLOCKS}", file=path, line=_line(doc, "blocks"))
    level = _Level(doc, path, ns, "", stack=(os.path.realpath(path),), cache=cache,
                   sets=paths, errors=errors, budget=budget, search=search)
    level.expand()
    sim = None
    try:
        sim = _simulation(doc, ns, path)
    except DiagramError as exc:
        errors.append(exc)
    lines, signal_info = {}, {}
    log = doc.get("log")
    if log is not None:
        if not isinstance(log, list):
            raise ConfigError("'log:' must be a list of block.port names", file=path,
                              line=_line(doc, "log"))
        log = [signal_entry(name, signal_info, "log", path, _line(log, i))
               for i, name in enumerate(log)]
        for i, name in enumerate(log):
            parse_signal(name, "log", path, _line(doc["log"], i))
            lines[name] = _line(doc["log"], i)
    plots_raw = _mapping(doc.get("plots"), "plots", path, _line(doc, "plots"))
    plots, plot_scales = {}, {}
    for fig, panels in plots_raw.items():
        fline = _line(plots_raw, fig)
        if not isinstance(fig, str) or not _FIGURE.match(fig):
            raise ConfigError(f"plot name '{fig}' must be letters, digits, '_' or '-' (it becomes "
                              "a file name)", file=path, line=fline)
        if isinstance(panels, str):
            panels = [panels]
        if not isinstance(panels, list) or not panels:
            raise ConfigError(f"plot '{fig}' must be a list of panels", file=path, line=fline)
        out, scales = [], []
        for panel in panels:
            scale = "linear"
            if isinstance(panel, dict) and "signal" not in panel:   # {signals: [...], scale: log}
                extra = [k for k in panel if k not in ("signals", "scale")]
                if extra or "signals" not in panel or panel.get("scale", "linear") not in (
                        "linear", "log"):
                    raise ConfigError(f"plot '{fig}': a panel mapping takes 'signals:' and "
                                      "optionally 'scale: linear | log'", file=path, line=fline)
                scale = panel.get("scale", "linear")
                panel = panel["signals"]
            sigs = panel if isinstance(panel, list) else [panel]
            sigs = [signal_entry(s, signal_info, f"plot '{fig}'", path, fline) for s in sigs]
            scales.append(scale)
            for s in sigs:
                parse_signal(s, f"plot '{fig}'", path, fline)
                lines.setdefault(s, fline)
            out.append([str(s) for s in sigs])
        plots[fig] = out
        plot_scales[fig] = scales
    metrics_raw = _mapping(doc.get("metrics"), "metrics", path, _line(doc, "metrics"))
    metrics = {}
    for key, value in metrics_raw.items():
        if key not in ("error", "tail"):
            raise ConfigError(f"metrics has no setting '{key}'; settings are: error, tail",
                              file=path, line=_line(metrics_raw, key))
        if key == "error":
            parse_signal(value, "metrics.error", path, _line(metrics_raw, key))
            lines.setdefault(value, _line(metrics_raw, key))
            metrics["error"] = value
        else:
            v = evaluate_value(value, ns, "metrics.tail")
            if not isinstance(v, float) or not 0 < v <= 1:
                raise ConfigError("metrics.tail must be a fraction in (0, 1]", file=path,
                                  line=_line(metrics_raw, key))
            metrics["tail"] = v
    declared = {key: dict(meta) for key, meta in level.signal_info.items()}
    for name, meta in signal_info.items():      # by the block port each name resolves to
        merge_signal_info(declared, level.aliases.get(name, name), meta)
    signal_info = declared
    check_figure_text(str(doc.get("description") or ""), "the description", path,
                      _line(doc, "description"))
    used = set(level.used)
    for section in ("simulation", "metrics"):
        if isinstance(doc.get(section), dict):
            for value in doc[section].values():
                for text in _strings_in(value):
                    used |= names_in(text)
    spec = DiagramSpec(file=path, description=str(doc.get("description") or ""), parameters=ns,
                       blocks=level.blocks, connections=level.connections, simulation=sim,
                       log=list(log) if log is not None else None, plots=plots, metrics=metrics,
                       aliases=level.aliases, lines=lines, plot_scales=plot_scales,
                       input_ports=level.input_ports, signal_info=signal_info,
                       signal_lines=level.signal_lines, sampled=level.sampled,
                       overrides=given, sources=list(search.read),
                       unused=unused_parameters(doc.get("parameters"), overrides, used))
    if not errors:
        infer_shapes(spec)      # shape parameters the wiring fixes (fwdstep/structure/shapes.py)
    return spec
