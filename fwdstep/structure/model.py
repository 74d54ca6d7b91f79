"""The data a loaded diagram is made of: block entries, connections, the flat ``DiagramSpec``,
and the evaluation of YAML values.  The loader (``fwdstep.structure.spec``) builds them; the
later phases (sampled subsystems, shape inference, the graph) read them."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fwdstep.core.errors import ExpressionError
from fwdstep.core.expressions import MAX_ARRAY_SIZE, evaluate
from fwdstep.core.settings import SimulationConfig
from fwdstep.core.yamlio import LineDict, LineList


@dataclass
class BlockEntry:
    name: str
    type_name: str
    cls: type
    params: dict
    file: str
    line: int | None
    key_lines: dict = field(default_factory=dict)


@dataclass
class Connection:
    src: tuple
    dst: tuple
    file: str
    line: int | None
    text: str


@dataclass(frozen=True)
class SourceFile:
    """A file the loader read: the top-level diagram (``kind`` "diagram"), a subsystem
    ("subsystem") or a block's data file ("file", a ``Param("file")`` such as a URDF).
    ``named``: the name as written, by ``by`` (the including file; "" for the command line,
    None for the top-level diagram); ``text``: the diagram's text when it was given as text
    (``fwdstep.Diagram().load()``) rather than read from ``path``."""
    path: str
    kind: str
    named: str | None = None
    by: str | None = None
    text: str | None = None          # a diagram given as text (``fwdstep.Diagram``), no file


@dataclass
class DiagramSpec:
    file: str
    description: str
    parameters: dict
    blocks: list
    connections: list
    simulation: SimulationConfig
    log: list | None
    plots: dict
    metrics: dict
    aliases: dict
    lines: dict = field(default_factory=dict)   # where log/plots/metrics were written
    plot_scales: dict = field(default_factory=dict)   # figure -> ["linear" | "log"] per panel
    input_ports: dict = field(default_factory=dict)   # inner (block, port) -> subsystem port
    signal_info: dict = field(default_factory=dict)   # "sub/blk.port" -> {label, unit, components}
    signal_lines: dict = field(default_factory=dict)  # "sub/blk.port" -> (file, line, as written)
    sampled: dict = field(default_factory=dict)       # "sub/inner" -> {period, offset} (s)
    #: the ``--set`` overrides it was loaded with (a parameter's derivative reloads the file
    #: with these plus the perturbed value: fwdstep.analysis.sensitivity)
    overrides: dict = field(default_factory=dict)
    sources: list = field(default_factory=list)       # every file read, as SourceFile
    unused: list = field(default_factory=list)        # top-level parameters nothing reads


def kind_of(value) -> str:
    """What a YAML value is, in the words of the diagram format ('a list', 'a number')."""
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return f"a {type(value).__name__}"


def _line(container, key) -> int | None:
    if isinstance(container, (LineDict, LineList)):
        return container.line_of(key)
    return None


def evaluate_value(value: Any, namespace: dict, what: str):
    """Evaluate a YAML value: strings are expressions, lists are evaluated element-wise."""
    if isinstance(value, str):
        return evaluate(value, namespace, what)
    if isinstance(value, list):
        items, total = [], 0
        for v in value:
            items.append(evaluate_value(v, namespace, what))
            total += int(np.size(items[-1])) if items[-1] is not None else 1
            if total > MAX_ARRAY_SIZE:
                raise ExpressionError(f"{what}: the list has more than {MAX_ARRAY_SIZE} numbers")
        for v in items:
            if v is None or isinstance(v, (bool, np.bool_)):
                shown = "null (an empty entry)" if v is None else str(v).lower()
                raise ExpressionError(f"{what}: a list may contain only numbers, not {shown}")
        try:
            return np.array(items, dtype=float)
        except (ValueError, TypeError):
            raise ExpressionError(f"{what}: the list is not a rectangular array of numbers"
                                  ) from None
    if isinstance(value, dict):
        raise ExpressionError(f"{what} must be a number, a list or an expression, not a "
                              "mapping ({...} or indented 'key: value' lines)")
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, (int, float)):
        try:
            number = float(value)
        except OverflowError:
            raise ExpressionError(f"{what}: the integer is too large to be a number") from None
        if not math.isfinite(number):
            raise ExpressionError(f"{what}: value {value} is not finite")
        return number
    return value


def evaluate_ragged(value: Any, namespace: dict, what: str):
    """A list of rows of different lengths -> a matrix padded with zeros at the end of each
    row (``[[1, 0.5], [2]]`` -> ``[[1, 0.5], [2, 0]]``); anything else as ``evaluate_value``."""
    if not (isinstance(value, list) and value and all(isinstance(v, list) for v in value)):
        return evaluate_value(value, namespace, what)
    rows = [np.atleast_1d(evaluate_value(v, namespace, what)) for v in value]
    if any(r.ndim != 1 for r in rows):
        raise ExpressionError(f"{what}: each row must be a list of numbers")
    width = max(r.size for r in rows)
    if width * len(rows) > MAX_ARRAY_SIZE:
        raise ExpressionError(f"{what}: the list has more than {MAX_ARRAY_SIZE} numbers")
    out = np.zeros((len(rows), width))
    for i, r in enumerate(rows):
        out[i, :r.size] = r
    return out


