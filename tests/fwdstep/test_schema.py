"""The JSON Schema of the diagram format (fwdstep/structure/schema.py, ``fwdstep schema``).

It is generated from the block registry, so these tests compare it with the registry itself
and run it, through the independent ``jsonschema`` validator, over every shipped diagram
(must pass) and over typical mistakes (must fail, at the right place).
"""
import json
from pathlib import Path

import pytest

from fwdstep.cli import arguments as cli
from fwdstep.structure.library import load_library
from fwdstep.structure.schema import diagram_schema, schema_text
from fwdstep.core.settings import SIMULATION_KEYS
from fwdstep.structure.spec import TOP_LEVEL_KEYS
from fwdstep.core.yamlio import read_yaml_file

jsonschema = pytest.importorskip("jsonschema")
REPO = Path(__file__).resolve().parents[2]
SHIPPED = sorted((REPO / "diagrams").glob("*.yaml")) + sorted((REPO / "diagrams" / "lib")
                                                              .glob("*.yaml"))


def plain(value):
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


@pytest.fixture(scope="module")
def validator():
    schema = diagram_schema()
    jsonschema.Draft7Validator.check_schema(schema)
    return jsonschema.Draft7Validator(schema)


def test_every_block_type_and_parameter_is_in_the_schema():
    schema = diagram_schema()
    registry = load_library()
    assert set(schema["properties"]) == set(TOP_LEVEL_KEYS)
    assert set(schema["properties"]["simulation"]["properties"]) == set(SIMULATION_KEYS)
    types = schema["definitions"]["block"]["properties"]["type"]["enum"]
    assert sorted(types) == sorted(list(registry) + ["subsystem"])
    for name, cls in registry.items():
        block = schema["definitions"][f"block.{name}"]
        assert set(block["properties"]) == {"type"} | set(cls.params), name
        assert set(block["required"]) == {"type"} | {k for k, d in cls.params.items()
                                                     if d.required and k not in cls.shape_from}, name


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_every_shipped_diagram_satisfies_the_schema(path, validator):
    errors = [e.message for e in validator.iter_errors(plain(read_yaml_file(str(path))))]
    assert errors == []


GOOD = {"blocks": {"g": {"type": "Gain", "gain": "2*k"}, "c": {"type": "Constant", "value": 1}},
        "connections": ["c.y -> g.u"], "simulation": {"t_final": 1, "step": 0.1}}


@pytest.mark.parametrize("change, where", [
    (lambda d: d["blocks"]["g"].update(gian=2), ["blocks", "g"]),                 # typo
    (lambda d: d["blocks"]["g"].update(type="Gainn"), ["blocks", "g", "type"]),
    (lambda d: d["blocks"]["c"].pop("value"), ["blocks", "c"]),                   # required
    (lambda d: d["blocks"].update(r={"type": "ReferenceDynamics", "variant": "eq99", "ell": 1,
                                     "n": 2}), ["blocks", "r", "variant"]),
    (lambda d: d["simulation"].update(solver="rk5"), ["simulation", "solver"]),
    (lambda d: d["simulation"].update(stepp=1), ["simulation"]),
    (lambda d: d.update(paramters={}), []),
    (lambda d: d["connections"].append("c.y => g.u"), ["connections", 1]),
    (lambda d: d.update(log=["cy"]), ["log", 0]),
])
def test_mistakes_are_caught_where_they_are(change, where, validator):
    assert list(validator.iter_errors(GOOD)) == []
    doc = json.loads(json.dumps(GOOD))
    change(doc)
    errors = list(validator.iter_errors(doc))
    assert errors
    assert any(list(e.absolute_path)[:len(where)] == where for e in errors), \
        [(list(e.absolute_path), e.message) for e in errors]


def test_the_command_prints_or_writes_the_schema(capsys, tmp_path):
    """No copy is kept in the repository (it would go stale as blocks change): editors point at
    the file 'fwdstep schema -o diagram.schema.json' writes."""
    assert cli.main(["schema"]) == 0
    assert capsys.readouterr().out == schema_text()
    out = tmp_path / "s.json"
    assert cli.main(["schema", "-o", str(out)]) == 0
    assert json.loads(out.read_text()) == diagram_schema()


def test_subsystem_keys_come_from_the_loader():
    from fwdstep.structure.spec import SUBSYSTEM_KEYS
    sub = diagram_schema()["definitions"]["block.subsystem"]
    assert set(sub["properties"]) == set(SUBSYSTEM_KEYS)


def test_the_reference_page_names_every_function_setting_section_and_metric():
    """docs/diagram-format.md is written by hand: it must not miss what the code offers."""
    import re
    from fwdstep.core.expressions import CONSTANTS, FUNCTIONS
    from fwdstep.results.result import METRIC_DEFINITIONS
    from fwdstep.core.settings import SOLVER_NAMES
    from fwdstep.structure.spec import SUBSYSTEM_KEYS
    text = (REPO / "docs" / "diagram-format.md").read_text()
    quoted = set(re.findall(r"`([A-Za-z_][A-Za-z0-9_]*)", text))
    named = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", text))
    missing = [n for n in list(FUNCTIONS) + list(CONSTANTS) if n not in named]
    missing += [n for n in list(TOP_LEVEL_KEYS) + list(SIMULATION_KEYS) + list(SOLVER_NAMES)
                + list(SUBSYSTEM_KEYS) + list(METRIC_DEFINITIONS) if n not in quoted]
    assert missing == []
