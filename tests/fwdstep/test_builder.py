"""Diagrams built in Python (``fwdstep.Diagram``, issue 24): every shipped diagram, rebuilt
through the builder's calls from its parsed file, loads to the same spec as the file (same
blocks and parameters, connections, settings, log, plots, metrics, ports); a built diagram
runs and is refused with the loader's own one-line errors."""
import dataclasses
import glob
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError, ParameterError, WiringError
from fwdstep.core.yamlio import read_yaml_file
from fwdstep.structure.spec import load_spec

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SHIPPED = sorted(glob.glob(os.path.join(ROOT, "diagrams", "*.yaml")) +
                 glob.glob(os.path.join(ROOT, "diagrams", "lib", "*.yaml")) +
                 glob.glob(os.path.join(ROOT, "diagrams", "robots", "*.yaml")))


def rebuild(path: str) -> fwdstep.Diagram:
    """The diagram of ``path`` made by builder calls, section by section."""
    doc = read_yaml_file(path)
    name = os.path.splitext(os.path.basename(path))[0]
    b = fwdstep.Diagram(doc.get("description") or "", folder=os.path.dirname(path), name=name)
    for key, value in (doc.get("parameters") or {}).items():
        b.parameter(key, value)
    for block, body in doc["blocks"].items():
        body = dict(body)
        kind = body.pop("type")
        if kind == "subsystem":
            b.subsystem(block, body.pop("file"), **body.pop("parameters", {}), **body)
        else:
            b.add(block, kind, **body)
    for text in doc.get("connections") or []:
        source, destinations = text.split("->", 1)
        b.connect(source.strip(), *[d.strip() for d in destinations.split(",") if d.strip()])
    ports = doc.get("ports") or {}
    for port, targets in (ports.get("inputs") or {}).items():
        b.input(port, *(targets if isinstance(targets, list) else [targets]))
    for port, source in (ports.get("outputs") or {}).items():
        b.output(port, source)
    if doc.get("simulation") is not None:
        b.simulation(**doc["simulation"])
    if doc.get("log") is not None:
        b.log(*doc["log"])
    for figure, panels in (doc.get("plots") or {}).items():
        b.plot(figure, *(panels if isinstance(panels, list) else [panels]))
    if doc.get("metrics"):
        b.metrics(**doc["metrics"])
    return b


def _same(a, b) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and np.array_equal(a, b)
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: os.path.relpath(p, ROOT))
def test_every_shipped_diagram_builds_to_the_same_spec(path):
    built = rebuild(path)
    want = load_spec(path)
    got = built.spec()
    assert got.file == built.path and got.description == want.description
    assert [(e.name, e.type_name, e.cls) for e in got.blocks] == \
        [(e.name, e.type_name, e.cls) for e in want.blocks]
    for g, w in zip(got.blocks, want.blocks):
        assert _same(g.params, w.params), g.name
    assert [(c.src, c.dst) for c in got.connections] == \
        [(c.src, c.dst) for c in want.connections]
    assert _same(got.parameters, want.parameters)
    assert dataclasses.asdict(got.simulation) == dataclasses.asdict(want.simulation)
    for field in ("log", "plots", "plot_scales", "metrics", "aliases", "signal_info",
                  "input_ports"):
        g, w = getattr(got, field), getattr(want, field)
        if field == "input_ports":      # (outer port, file, line): the file is the built one
            g = {k: v[0] for k, v in g.items()}
            w = {k: v[0] for k, v in w.items()}
        assert _same(g, w), field


def test_the_yaml_of_a_built_diagram_is_the_file_a_person_writes(tmp_path):
    b = fwdstep.Diagram("first-order lag\nto 1", folder=str(tmp_path), name="lag")
    b.parameter("tau", 0.5).add("ref", "Constant", value=[1.0])
    b.add("err", "Sum", signs="+-", shape=[1]).add("gain", "Gain", gain="1/tau", shape=[1])
    b.add("x", "Integrator", shape=[1])
    b.connect("ref.y", "err.u1").connect("x.y", "err.u2").connect("err.y", "gain.u")
    b.connect("gain.y", "x.u")
    b.simulation(t_final=2, step=0.001, solver="rk4").log("x.y").metrics(error="err.y")
    assert b.to_yaml() == (
        "description: |-\n  first-order lag\n  to 1\n"
        "parameters:\n  tau: 0.5\n"
        "blocks:\n"
        "  ref: {type: Constant, value: [1.0]}\n"
        "  err: {type: Sum, signs: +-, shape: [1]}\n"
        "  gain: {type: Gain, gain: 1/tau, shape: [1]}\n"
        "  x: {type: Integrator, shape: [1]}\n"
        "connections:\n  - ref.y -> err.u1\n  - x.y -> err.u2\n  - err.y -> gain.u\n"
        "  - gain.y -> x.u\n"
        "simulation: {t_final: 2, step: 0.001, solver: rk4}\n"
        "log:\n  - x.y\n"
        "metrics: {error: err.y}\n")
    r = fwdstep.simulate(b.load())
    np.testing.assert_allclose(r["x.y"][:, 0], 1 - np.exp(-r.t / 0.5), atol=1e-9)
    saved = b.save()
    assert saved == str(tmp_path / "lag.yaml")
    assert fwdstep.simulate(fwdstep.load_diagram(saved))["x.y"].tolist() == r["x.y"].tolist()


def test_a_built_diagram_gets_the_loaders_errors():
    b = fwdstep.Diagram()
    b.add("g", "Gain", gian=2)
    with pytest.raises(ParameterError, match=r"diagram.yaml:2: block 'g' \(Gain\) has no "
                                             r"parameter 'gian'; valid parameters are: gain"):
        b.load()
    c = fwdstep.Diagram().add("k", "Constant", value=1.0).connect("k.y", "nothere.u")
    with pytest.raises(WiringError, match="names block 'nothere', which does not exist"):
        c.load()
    with pytest.raises(ConfigError, match="block 'k' is already defined"):
        c.add("k", "Gain", gain=1)
    with pytest.raises(ConfigError, match="not a signal name"):
        c.connect("k", "x.u")
