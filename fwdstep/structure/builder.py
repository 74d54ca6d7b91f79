"""Diagrams built in Python: ``fwdstep.Diagram``, for people who come from Drake or bdsim.

A builder writes the same YAML a person would, section by section, and loads it through
the same loader (``fwdstep.structure.spec``), so it gets the same validation and the same
one-line errors -- naming the line of ``to_yaml()`` where the mistake is::

    import fwdstep
    d = fwdstep.Diagram("PD control of a point", folder="diagrams")
    d.parameter("K", 20)
    d.add("ref", "Constant", value=[1.0])
    d.add("err", "Sum", signs="+-", shape=[1])
    d.add("ctrl", "Gain", gain="K", shape=[1])
    d.add("x", "Integrator", shape=[1])
    d.connect("ref.y", "err.u1")
    d.connect("x.y", "err.u2")
    d.connect("err.y", "ctrl.u")
    d.connect("ctrl.y", "x.u")
    d.simulation(t_final=2, step=0.01)
    d.log("err.y")
    d.metrics(error="err.y")
    compiled = d.load()                  # a CompiledDiagram, as fwdstep.load_diagram gives
    print(d.to_yaml())

Values are what YAML holds: numbers, lists (NumPy arrays become lists), strings
(expressions over the parameters, e.g. ``"50*eye(2)"``), booleans.  ``subsystem`` names a
diagram file, relative to ``folder`` (default: the working directory), as ``file:`` is
relative to the diagram that names it.  Each method returns the builder, so calls chain.
"""
from __future__ import annotations

import os
import re

from fwdstep.core.errors import ConfigError

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
#: the sections of a diagram file, in the order ``to_yaml`` writes them
SECTIONS = ("description", "parameters", "blocks", "connections", "ports", "simulation",
            "log", "plots", "metrics")


def _plain(value, what: str):
    """A value as YAML can hold it (arrays -> lists, NumPy numbers -> Python numbers)."""
    import numpy as np
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), what)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v, what) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v, what) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ConfigError(f"{what}: {type(value).__name__} is not a value a diagram can hold "
                      "(numbers, lists, strings, booleans)")


def _flow(value) -> str:
    """One YAML value on one line (flow style), as ``yaml.safe_dump`` writes it."""
    import yaml
    text = yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=1 << 30,
                          allow_unicode=True)
    if text.endswith("\n...\n"):          # a plain scalar is dumped as a whole document
        text = text[:-len("\n...\n")]
    return text.strip()


def _text_block(key: str, text: str) -> str:
    """``key: |`` and the text indented (as a person writes a description), or one line."""
    lines = text.split("\n")
    if "\n" in text.rstrip("\n") and not lines[0].startswith((" ", "\t")) and \
            all(not line.endswith((" ", "\t")) for line in lines) and \
            not text.endswith("\n\n"):
        chomp = "" if text.endswith("\n") else "-"
        body = "\n".join(f"  {line}" if line else "" for line in text.rstrip("\n").split("\n"))
        return f"{key}: |{chomp}\n{body}\n"
    return f"{key}: {_flow(text)}\n"


class Diagram:
    """A diagram built by method calls; see the module docstring."""

    def __init__(self, description: str = "", *, folder: str | None = None,
                 name: str = "diagram"):
        if not _NAME.match(name):
            raise ConfigError(f"Diagram name '{name}' must be letters, digits and _ (it names "
                              "the diagram in messages and its file)")
        self.name = name
        self.folder = os.path.abspath(folder or os.getcwd())
        self.description = str(description or "")
        self._parameters: dict = {}
        self._blocks: dict = {}
        self._connections: list = []
        self._inputs: dict = {}
        self._outputs: dict = {}
        self._simulation: dict = {}
        self._log: list | None = None
        self._plots: dict = {}
        self._metrics: dict = {}

    # ------------------------------------------------------------------ building
    def parameter(self, name: str, value) -> "Diagram":
        """A diagram parameter (``parameters:``): a number, list or expression string."""
        self._check_name(name, "parameter", self._parameters)
        self._parameters[name] = _plain(value, f"parameter '{name}'")
        return self

    def add(self, name: str, type, **params) -> "Diagram":
        """A block of ``type`` (its registered name, or the Block class) with parameters."""
        type_name = type if isinstance(type, str) else getattr(type, "type_name", "") or \
            getattr(type, "__name__", str(type))
        if type_name == "subsystem":
            raise ConfigError(f"block '{name}': use .subsystem(name, file=...) for a subsystem")
        self._check_name(name, "block", self._blocks)
        body = {"type": type_name}
        body.update({k: _plain(v, f"block '{name}' parameter '{k}'") for k, v in params.items()})
        self._blocks[name] = body
        return self

    def subsystem(self, name: str, file: str, *, sample_period=None, sample_offset=None,
                  **params) -> "Diagram":
        """A subsystem: the diagram ``file`` (relative to ``folder``, or ``lib/NAME``), its
        ``params`` passed as its parameters; ``sample_period`` makes it a sampled
        controller (docs/discrete-time.md)."""
        self._check_name(name, "block", self._blocks)
        body = {"type": "subsystem", "file": str(file)}
        if params:
            body["parameters"] = {k: _plain(v, f"subsystem '{name}' parameter '{k}'")
                                  for k, v in params.items()}
        if sample_period is not None:
            body["sample_period"] = _plain(sample_period, f"subsystem '{name}'")
        if sample_offset is not None:
            body["sample_offset"] = _plain(sample_offset, f"subsystem '{name}'")
        self._blocks[name] = body
        return self

    def connect(self, source: str, *destinations: str) -> "Diagram":
        """``connect("a.y", "b.u", "c.u")``: output ``a.y`` drives inputs ``b.u`` and ``c.u``
        (the connection ``a.y -> b.u, c.u``)."""
        if not destinations:
            raise ConfigError(f"connect('{source}'): name at least one input it drives")
        for end in (source, *destinations):
            if not isinstance(end, str) or "." not in end or "->" in end or "," in end:
                raise ConfigError(f"connect: '{end}' is not a signal name of the form "
                                  "block.port")
        self._connections.append(f"{source} -> {', '.join(destinations)}")
        return self

    def input(self, name: str, *targets: str) -> "Diagram":
        """A port of a subsystem file (``ports: inputs:``): ``name`` drives ``targets``."""
        self._check_name(name, "input port", self._inputs)
        self._inputs[name] = targets[0] if len(targets) == 1 else list(targets)
        return self

    def output(self, name: str, source: str) -> "Diagram":
        """A port of a subsystem file (``ports: outputs:``): ``name`` is ``source``."""
        self._check_name(name, "output port", self._outputs)
        self._outputs[name] = source
        return self

    def simulation(self, **settings) -> "Diagram":
        """``simulation:`` settings (t_final, step, solver, log_every, bound, backend, ...)."""
        self._simulation.update({k: _plain(v, f"simulation.{k}") for k, v in settings.items()})
        return self

    def log(self, *signals) -> "Diagram":
        """Signals to record: ``"blk.port"`` or ``{"signal": ..., "label": ..., "unit": ...,
        "components": [...]}``; each call adds to the list."""
        self._log = (self._log or []) + [_plain(s, "log") for s in signals]
        return self

    def plot(self, name: str, *panels) -> "Diagram":
        """A figure ``name``: one panel per argument, a signal, a list of signals, or
        ``{"signals": [...], "scale": "log"}``."""
        if name in self._plots:
            raise ConfigError(f"plot '{name}' is already defined")
        self._plots[name] = [_plain(p, f"plot '{name}'") for p in panels]
        return self

    def metrics(self, error: str | None = None, tail=None) -> "Diagram":
        """``metrics:``: the error signal (and the tail fraction of the run)."""
        if error is not None:
            self._metrics["error"] = error
        if tail is not None:
            self._metrics["tail"] = _plain(tail, "metrics.tail")
        return self

    def _check_name(self, name, what: str, taken: dict) -> None:
        if not isinstance(name, str) or not _NAME.match(name):
            raise ConfigError(f"{what} name '{name}' is not valid (letters, digits and _, not "
                              "starting with a digit)")
        if name in taken:
            raise ConfigError(f"{what} '{name}' is already defined")

    # ------------------------------------------------------------------ output
    def to_dict(self) -> dict:
        """The diagram as the data of its YAML file (sections that are empty left out)."""
        out: dict = {}
        if self.description:
            out["description"] = self.description
        for key, value in (("parameters", self._parameters), ("blocks", self._blocks),
                           ("connections", self._connections)):
            if value:
                out[key] = value
        if self._inputs or self._outputs:
            out["ports"] = {k: v for k, v in (("inputs", self._inputs),
                                              ("outputs", self._outputs)) if v}
        for key, value in (("simulation", self._simulation), ("log", self._log),
                           ("plots", self._plots), ("metrics", self._metrics)):
            if value or (key == "log" and value is not None):
                out[key] = value
        return out

    def to_yaml(self) -> str:
        """The diagram file a person would write: one line per parameter, block,
        connection, logged signal and figure."""
        doc = self.to_dict()
        parts = []
        for key in SECTIONS:
            if key not in doc:
                continue
            value = doc[key]
            if key == "description":
                parts.append(_text_block(key, value))
            elif key in ("parameters", "blocks", "plots"):
                parts.append(f"{key}:\n" + "".join(f"  {k}: {_flow(v)}\n"
                                                   for k, v in value.items()))
            elif key == "ports":
                parts.append("ports:\n" + "".join(f"  {k}: {_flow(v)}\n"
                                                  for k, v in value.items()))
            elif key in ("connections", "log"):
                parts.append(f"{key}:\n" + "".join(f"  - {_flow(v)}\n" for v in value)
                             if value else f"{key}: []\n")
            else:
                parts.append(f"{key}: {_flow(value)}\n")
        return "".join(parts)

    @property
    def path(self) -> str:
        """Where the diagram stands in messages, and what its ``file:`` names are relative
        to: ``folder/name.yaml`` (nothing is written there unless you ``save``)."""
        return os.path.join(self.folder, f"{self.name}.yaml")

    def save(self, path: str | None = None) -> str:
        """Write ``to_yaml()`` to ``path`` (default ``self.path``); the path."""
        from fwdstep.core.files import atomic_write
        path = path or self.path
        text = self.to_yaml()
        atomic_write(os.path.abspath(path), lambda fh: fh.write(text))
        return path

    def spec(self, overrides: dict | None = None):
        """The loaded ``DiagramSpec`` (``fwdstep.structure.spec.load_spec`` of the YAML)."""
        from fwdstep.structure.spec import load_spec
        return load_spec(self.path, overrides, text=self.to_yaml())

    def load(self, overrides: dict | None = None, plugins: list | None = None):
        """Validate and compile, as ``fwdstep.load_diagram`` does a file: a
        ``CompiledDiagram``, or the loader's one-line ``DiagramError``."""
        from fwdstep.structure.compiler import compile_spec
        if plugins:
            from fwdstep.structure.library import load_plugins
            load_plugins(plugins)
        return compile_spec(self.spec(overrides))

    def __repr__(self) -> str:
        return (f"<Diagram {self.name}: {len(self._blocks)} blocks, "
                f"{len(self._connections)} connections, {len(self._parameters)} parameters>")


__all__ = ["Diagram"]
