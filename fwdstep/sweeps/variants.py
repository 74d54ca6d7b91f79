"""The specs of many variants of one diagram, each equal to its own ``load_spec``, cheaply.

A sweep needs ``load_spec(path, {**overrides, **values})`` for every variant.  Loading reads,
checks and flattens the whole file each time (~15 ms for slotine_li.yaml), which for 256
variants cost more than integrating them.  ``VariantSpecs`` loads the diagram once and
derives each variant's spec from that base by redoing only what the variant's values reach:

* the parameters that depend (transitively) on a swept parameter are evaluated again, the
  others are taken from the base (``resolve_parameters`` with the rest as ``preset``);
* a block entry is built again (``_Level._add_block``, the loader's own code) when one of its
  parameter values names such a parameter or a ``BLOCK.PARAMETER`` path sets it; the others
  are the base's entries;
* the simulation settings are evaluated again (cheap); connections, log, plots, aliases are
  the base's objects (they do not depend on parameter values);
* shapes the wiring fixed (``fwdstep.structure.shapes``) are the base's, after checking that every
  rebuilt block has the same port shapes as in the base: inference then reaches the same
  fixed point (each inferred shape is read from a port whose shape is unchanged).

Anything else -- a diagram with subsystems, a swept ``log``, a ``metrics.tail`` that depends
on a swept parameter, a rebuilt block whose ports change shape or which refuses its
parameters, any error -- falls back to the full ``load_spec``, which also produces the
error message.  The blocks built for the shape check are kept in ``made`` (the cache
``fwdstep.structure.compiler.instantiate_variants`` shares), so they are not built twice.
"""
from __future__ import annotations

import dataclasses
import os

from fwdstep.structure.compiler import _value_key
from fwdstep.core.errors import DiagramError
from fwdstep.core.expressions import names_in
from fwdstep.structure.graph import _instantiate_one
from fwdstep.core.search import SearchPath
from fwdstep.structure.spec import (Budget, LineDict, _Level, _line, _read_document, _simulation, _strings_in,
                   load_spec, resolve_parameters, split_overrides, unused_parameters)


class VariantSpecs:
    """``spec(values)`` == ``load_spec(path, {**overrides, **values})`` for every ``values``
    (a dict of parameter names, ``simulation.SETTING`` or ``BLOCK.PARAMETER`` paths)."""

    def __init__(self, path: str, overrides: dict | None = None, cache: dict | None = None):
        self.path = os.path.normpath(path)
        self.overrides = dict(overrides or {})
        self.cache = {} if cache is None else cache
        self.base = load_spec(self.path, self.overrides, cache=self.cache)
        self.made: dict = {}                      # instantiate_variants' cache of built blocks
        self._base_blocks: dict = {}
        self._base_keys: dict = {}
        self.derived = 0                          # how many specs were derived (not loaded)
        self._fast = False
        try:
            self._prepare()
        except DiagramError:                      # pragma: no cover - the base loaded
            self._fast = False

    # ------------------------------------------------------------------ preparation
    def _prepare(self) -> None:
        doc = _read_document(self.path, self.cache)
        blocks = doc.get("blocks")
        raw_params = doc.get("parameters") or {}
        if not (isinstance(blocks, dict) and isinstance(raw_params, dict)):
            return
        if any(not isinstance(b, dict) or b.get("type") == "subsystem" for b in blocks.values()):
            return                                # subsystems: the full loader flattens them
        if [e.name for e in self.base.blocks] != list(blocks):
            return
        self.doc, self.blocks_raw, self.raw_params = doc, blocks, raw_params
        params, sim, log, paths = split_overrides(self.overrides, raw_params)
        self.base_params, self.base_sim, self.base_paths = params, sim, paths
        if log is not None:
            return
        # who uses each parameter (with the --set expressions in place of the file's)
        effective = {**dict(raw_params), **params}
        self.users: dict = {name: set() for name in effective}
        for name, value in effective.items():
            for text in _strings_in(value):
                for dep in names_in(text):
                    if dep in self.users and dep != name:
                        self.users[dep].add(name)
        # names each block's values mention, and the keys the file/--set gave it
        self.block_names = {}
        for name, body in blocks.items():
            mentioned = set()
            for key, value in body.items():
                if key != "type":
                    for text in _strings_in(value):
                        mentioned |= names_in(text)
            self.block_names[name] = mentioned
        self.sim_names = set()
        for text in _strings_in(list((doc.get("simulation") or {}).values())):
            self.sim_names |= names_in(text)
        self.search = SearchPath(self.path)
        self.real_path = os.path.realpath(self.path)     # once: a _Level per variant needs it
        self.tail_names = set()
        metrics = doc.get("metrics")
        if isinstance(metrics, dict) and "tail" in metrics:
            for text in _strings_in(metrics["tail"]):
                self.tail_names |= names_in(text)
        level = self._level(self.base.parameters)
        self.raw_keys = {}
        self.block_uses = {}                      # block -> the parameters its values read
        for entry in self.base.blocks:
            level.used = set()
            rebuilt = self._build(level, entry.name, self.base_paths)
            self.raw_keys[entry.name] = list(rebuilt.params)
            self.block_uses[entry.name] = level.used
        self._fast = True

    def _level(self, namespace: dict) -> _Level:
        return _Level(self.doc, self.path, namespace, "", stack=(self.real_path,),
                      cache=self.cache, errors=[], budget=Budget(), search=self.search)

    def _build(self, level: _Level, name: str, paths: dict):
        sets = {tuple(path[1:]): value for path, value in paths.items() if path[0] == name}
        level._add_block(name, self.blocks_raw[name], _line(self.blocks_raw, name), sets)
        return level.blocks.pop()

    # ------------------------------------------------------------------ variants
    def spec(self, values: dict):
        """The spec of one variant (derived from the base when that is exact, else loaded)."""
        return self.load(values, blocks=False)[0]

    def load(self, values: dict, blocks: bool = True) -> tuple:
        """(spec, its blocks or None): the blocks are built once per distinct entry (the
        base's blocks for the entries a variant does not touch)."""
        if self._fast:
            try:
                derived = self._derive(values)
            except (DiagramError, ValueError, TypeError, KeyError, AttributeError):
                derived = None                   # the full loader decides (and says why)
            if derived is not None:
                self.derived += 1
                spec, rebuilt = derived
                if not blocks:
                    return spec, None
                return spec, [self.block(k, entry, rebuilt[k]) if k in rebuilt else
                              self._base_block(k) for k, entry in enumerate(spec.blocks)]
        spec = load_spec(self.path, {**self.overrides, **values}, cache=self.cache)
        if not blocks:
            return spec, None
        from fwdstep.structure.compiler import instantiate_variants
        return spec, instantiate_variants([spec], self.made)[0]

    def _base_block(self, k: int):
        if k not in self._base_blocks:
            self._base_blocks[k] = self.block(k, self.base.blocks[k], self._base_key(k))
        return self._base_blocks[k]

    def _derive(self, values: dict):
        base = self.base
        vparams, vsim, vlog, vpaths = split_overrides(values, self.raw_params)
        if vlog is not None or any(len(p) != 2 or p[0] not in self.blocks_raw for p in vpaths):
            return None
        if any(name not in self.users for name in vparams):
            return None
        affected, todo = set(), list(vparams)
        while todo:
            name = todo.pop()
            if name not in affected:
                affected.add(name)
                todo.extend(self.users[name])
        if affected & self.tail_names:
            return None
        preset = {k: v for k, v in base.parameters.items() if k not in affected}
        ns = resolve_parameters(self.raw_params, {**self.base_params, **vparams}, self.path,
                                preset=preset, line=_line(self.doc, "parameters"),
                                budget=Budget())
        ns = {k: ns[k] for k in base.parameters}     # the base's order
        if vsim or affected & self.sim_names:
            sim = _simulation(self._sim_doc({**self.base_sim, **vsim}), ns, self.path)
        else:                                  # the same settings, its own object
            sim = _shallow(base.simulation)
        paths = {**self.base_paths, **vpaths}
        touched = {p[0] for p in vpaths}
        level = self._level(ns)
        entries, rebuilt = [], {}                 # rebuilt: position -> its value key
        used = set()
        for k, entry in enumerate(base.blocks):
            if entry.name not in touched and not (self.block_names[entry.name] & affected):
                kept = _shallow(entry)
                kept.params = dict(entry.params)
                entries.append(kept)
                used |= self.block_uses[entry.name]
                continue
            new = self._build(level, entry.name, paths)
            open_shapes = set(getattr(entry.cls, "shape_from", {}))
            if open_shapes & set(new.params) != open_shapes & set(self.raw_keys[entry.name]):
                return None                      # a shape the wiring fixed is now given
            for key, value in entry.params.items():      # the shapes inference filled in
                if key not in self.raw_keys[entry.name]:
                    new.params[key] = value
            key = _value_key(new.params)
            if key != self._base_key(k) and not self._same_ports(k, entry, new, key):
                return None
            entries.append(new)
            rebuilt[k] = key
        used |= level.used                         # what the rebuilt blocks read
        for section, extra in (("simulation", {**self.base_sim, **vsim}), ("metrics", {})):
            raw = self.doc.get(section)
            for value in {**(raw if isinstance(raw, dict) else {}), **extra}.values():
                for text in _strings_in(value):
                    used |= names_in(text)
        unused = unused_parameters(self.raw_params, {**self.base_params, **vparams}, used)
        return dataclasses.replace(base, parameters=ns, blocks=entries, simulation=sim,
                                   overrides={**base.overrides, **values},
                                   unused=unused), rebuilt

    def _sim_doc(self, sim_overrides: dict):
        if not sim_overrides:
            return self.doc
        doc = LineDict(self.doc)
        doc.line, doc.key_lines = self.doc.line, dict(getattr(self.doc, "key_lines", {}))
        raw = self.doc.get("simulation") or LineDict()
        merged = LineDict(raw)
        merged.line = getattr(raw, "line", None)
        merged.key_lines = dict(getattr(raw, "key_lines", {}))
        merged.update(sim_overrides)
        doc["simulation"] = merged
        return doc

    def block(self, k: int, entry, value_key=None):
        """The built block of ``entry`` (position ``k``), shared through ``made``;
        ``value_key``: ``_value_key(entry.params)`` if the caller has it."""
        if value_key is None:
            value_key = _value_key(entry.params)
        key = (k, entry.name, entry.cls, value_key)
        blk = self.made.get(key)
        if blk is None:
            blk = self.made[key] = _instantiate_one(entry)
        return blk

    def _base_key(self, k: int):
        """``_value_key`` of the base's block ``k``'s parameters (computed once)."""
        key = self._base_keys.get(k)
        if key is None:
            key = self._base_keys[k] = _value_key(self.base.blocks[k].params)
        return key

    def _same_ports(self, k: int, old, new, new_key) -> bool:
        a, b = self.block(k, old, self._base_key(k)), self.block(k, new, new_key)
        return ({n: p.shape for n, p in a.inputs.items()} ==
                {n: p.shape for n, p in b.inputs.items()} and
                {n: p.shape for n, p in a.outputs.items()} ==
                {n: p.shape for n, p in b.outputs.items()})


def _shallow(obj):
    """A shallow copy of a plain object (``copy.copy`` is 5x slower, ``dataclasses.replace``
    runs ``__init__``)."""
    out = object.__new__(type(obj))
    out.__dict__.update(obj.__dict__)
    return out


__all__ = ["VariantSpecs"]
