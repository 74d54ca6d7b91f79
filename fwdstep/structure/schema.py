"""A JSON Schema of the diagram format, generated from the block registry (never written by
hand, so it cannot drift from the blocks).

Editors use it for completion and checking (VS Code's YAML extension: put
``# yaml-language-server: $schema=PATH/diagram.schema.json`` on a diagram's first line).  The
schema checks what is knowable without evaluating anything: section names, block types, each
block's parameter names and required parameters, choices, simulation settings, the form of
connections and signal names.  Values may be expressions over parameters, so numbers are
accepted as numbers or strings; the loader still checks every value.
"""
from __future__ import annotations

import json
import sys

from fwdstep.core.settings import BACKENDS, SIMULATION_KEYS, SOLVER_NAMES
from fwdstep.structure.spec import SUBSYSTEM_KEYS, TOP_LEVEL_KEYS

SCHEMA_ID = "https://fwdstep.invalid/diagram.schema.json"
NAME = r"^[A-Za-z_][A-Za-z0-9_]*$"
SIGNAL = r"^\s*[A-Za-z_][A-Za-z0-9_]*([./][A-Za-z_][A-Za-z0-9_]*)*\.[A-Za-z_][A-Za-z0-9_]*\s*$"
CONNECTION = (r"^\s*[A-Za-z_][A-Za-z0-9_.]*\.[A-Za-z_][A-Za-z0-9_]*\s*->\s*"
              r"[A-Za-z_][A-Za-z0-9_.]*\.[A-Za-z_][A-Za-z0-9_]*"
              r"(\s*,\s*[A-Za-z_][A-Za-z0-9_.]*\.[A-Za-z_][A-Za-z0-9_]*)*\s*,?\s*$")

EXPRESSION = {"type": "string", "description": "an expression over the diagram's parameters"}
NUMBER = {"anyOf": [{"type": "number"}, EXPRESSION]}
ARRAY = {"anyOf": [{"type": "number"}, {"type": "array"}, EXPRESSION]}


def _param_schema(decl) -> dict:
    kind = decl.kind
    if kind in ("float", "int"):
        out = dict(NUMBER)
    elif kind == "array":
        out = dict(ARRAY)
    elif kind == "bool":
        out = {"anyOf": [{"type": "boolean"}, EXPRESSION]}
    elif kind in ("str", "file"):
        out = {"type": "string"}
    elif kind == "names":
        out = {"anyOf": [{"type": "array", "items": {"type": "string"}}, {"type": "string"}]}
    elif kind == "choice":
        out = {"enum": list(decl.choices)}
    else:
        out = {}
    doc = decl.doc or kind
    if not decl.required and decl.default is not None and not callable(decl.default):
        try:
            json.dumps(decl.default)
            out["default"] = decl.default
        except (TypeError, ValueError):
            pass
    out["description"] = doc
    return out


def block_schema(cls) -> dict:
    props = {"type": {"const": cls.type_name}}
    for key, decl in cls.params.items():
        props[key] = _param_schema(decl)
    return {
        "type": "object",
        "description": cls.summary(),
        "properties": props,
        # a required shape the wiring can fix (shape_from) may be left out
        "required": ["type"] + [k for k, d in cls.params.items()
                                if d.required and k not in getattr(cls, "shape_from", {})],
        "additionalProperties": False,
    }


def diagram_schema() -> dict:
    """The schema of a diagram file, built from the registry of block types."""
    from fwdstep.structure.library import load_library
    registry = load_library()
    types = sorted(registry)
    definitions = {f"block.{name}": block_schema(registry[name]) for name in types}
    subsystem = {key: NUMBER for key in SUBSYSTEM_KEYS}      # sample_period, sample_offset
    subsystem.update({"type": {"const": "subsystem"},
                      "file": {"type": "string", "pattern": r"^[^~\\]"},
                      "parameters": {"type": "object", "propertyNames": {"pattern": NAME},
                                     "additionalProperties": ARRAY}})
    definitions["block.subsystem"] = {
        "type": "object",
        "description": "another diagram used as a block (search path: next to this file, "
                       "fwdstep's library as lib/NAME.yaml, FWDSTEP_PATH)",
        "properties": subsystem,
        "required": ["type", "file"],
        "additionalProperties": False,
    }
    block = {
        "type": "object",
        "properties": {"type": {"enum": types + ["subsystem"],
                                "description": "a block type ('fwdstep blocks') or subsystem"}},
        "required": ["type"],
        "allOf": [{"if": {"properties": {"type": {"const": name}}, "required": ["type"]},
                   "then": {"$ref": f"#/definitions/block.{name}"}}
                  for name in types + ["subsystem"]],
    }
    definitions["block"] = block
    signal = {"type": "string", "pattern": SIGNAL, "description": "block.port"}
    signal_entry = {"anyOf": [signal, {
        "type": "object", "additionalProperties": False, "required": ["signal"],
        "properties": {"signal": signal, "label": {"type": "string"}, "unit": {"type": "string"},
                       "components": {"type": "array", "items": {"type": "string"}}}}]}
    panel = {"anyOf": [signal_entry, {"type": "array", "items": signal_entry}, {
        "type": "object", "additionalProperties": False, "required": ["signals"],
        "properties": {"signals": {"anyOf": [signal_entry,
                                             {"type": "array", "items": signal_entry}]},
                       "scale": {"enum": ["linear", "log"]}}}]}
    simulation = {key: NUMBER for key in SIMULATION_KEYS}
    simulation["solver"] = {"enum": list(SOLVER_NAMES)}
    simulation["backend"] = {"enum": list(BACKENDS)}
    simulation["stability_check"] = {"type": "boolean"}
    properties = {
        "description": {"type": "string"},
        "parameters": {"type": "object", "propertyNames": {"pattern": NAME},
                       "additionalProperties": ARRAY},
        "blocks": {"type": "object", "minProperties": 1, "propertyNames": {"pattern": NAME},
                   "additionalProperties": {"$ref": "#/definitions/block"}},
        "connections": {"type": "array", "items": {"type": "string", "pattern": CONNECTION}},
        "ports": {"type": "object", "additionalProperties": False, "properties": {
            "inputs": {"type": "object", "propertyNames": {"pattern": NAME},
                       "additionalProperties": {"anyOf": [
                           {"type": "string"}, {"type": "array", "items": {"type": "string"}}]}},
            "outputs": {"type": "object", "propertyNames": {"pattern": NAME},
                        "additionalProperties": {"type": "string"}}}},
        "simulation": {"type": "object", "additionalProperties": False,
                       "properties": simulation},
        "log": {"type": "array", "items": signal_entry},
        "plots": {"type": "object", "additionalProperties": {
            "anyOf": [signal, {"type": "array", "minItems": 1, "items": panel}]}},
        "metrics": {"type": "object", "additionalProperties": False,
                    "properties": {"error": signal, "tail": NUMBER}},
    }
    if set(properties) != set(TOP_LEVEL_KEYS):     # a programming error, caught by the tests
        raise RuntimeError("the schema and the loader disagree on the top-level sections")
    return {
        "$schema": "http://json-schema.org/draft-07/schema#",
        "$id": SCHEMA_ID,
        "title": "fwdstep diagram",
        "description": "A block diagram for fwdstep (docs/diagram-format.md). Generated by "
                       "'fwdstep schema' from the block registry.",
        "type": "object",
        "required": ["blocks"],
        "additionalProperties": False,
        "properties": properties,
        "definitions": definitions,
    }


def schema_text() -> str:
    return json.dumps(diagram_schema(), indent=1, sort_keys=False) + "\n"


