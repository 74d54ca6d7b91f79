"""YAML safety: diagrams are data, never code, and never a resource bomb.

fwdstep.core.yamlio must refuse Python and other non-standard tags with one line, refuse alias
bombs and deep nesting quickly, refuse oversized files before reading them, refuse duplicate
keys, and never be built on an unsafe PyYAML loader.
"""
from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
import yaml

import fwdstep
from fwdstep.core import yamlio
from fwdstep.core.errors import YamlError
from fwdstep.core.yamlio import parse_yaml_text, read_yaml_file

REPO = Path(__file__).resolve().parents[2]
PLAIN = "(mappings, lists, numbers, strings, booleans)"


@pytest.mark.parametrize("text, tag", [
    ("a: !!python/object:os.system {}\n", "!!python/object:os.system"),
    ("a: !!python/object/apply:os.system ['touch {marker}']\n",
     "!!python/object/apply:os.system"),
    ("a: !!python/object/new:os.system ['touch {marker}']\n", "!!python/object/new:os.system"),
    ("a: !!python/name:os.system\n", "!!python/name:os.system"),
    ("a: !!python/module:os\n", "!!python/module:os"),
    ("a: !!python/tuple [1, 2]\n", "!!python/tuple"),
    ("a: !<tag:yaml.org,2002:python/object/apply:os.system> ['touch {marker}']\n",
     "!!python/object/apply:os.system"),
    ("%TAG !p! tag:yaml.org,2002:python/\n---\na: !p!object/apply:os.system ['touch {marker}']\n",
     "!!python/object/apply:os.system"),
    ("a: !!binary aGVsbG8=\n", "!!binary"),
    ("a: !!set {x, y}\n", "!!set"),
    ("a: !!omap [{x: 1}]\n", "!!omap"),
    ("a: !!timestamp 2024-01-01\n", "!!timestamp"),
    ("a: !Gain {gain: 2}\n", "!Gain"),
    ("a: !!foo 1\n", "!!foo"),
])
def test_non_standard_tags_are_refused_with_one_line(text, tag, tmp_path):
    marker = tmp_path / "pwned"
    text = text.replace("{marker}", str(marker))
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, "d.yaml")
    line = text.count("\n", 0, text.index("a:")) + 1
    assert str(info.value) == (f"d.yaml:{line}: tag '{tag}' is not allowed: diagrams may "
                               f"contain only plain YAML {PLAIN}")
    assert not marker.exists()


def test_python_tag_in_a_diagram_file_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.yaml"
    path.write_text("blocks:\n  src: {type: Constant, value: 1}\n"
                    f"description: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(YamlError, match=r"evil\.yaml:3: tag '!!python/object/apply"):
        fwdstep.load_diagram(str(path))
    assert not marker.exists()


@pytest.mark.parametrize("text", ["a: !!str 12\n", "a: !!int '12'\n", "a: !!float '12'\n"])
def test_standard_scalar_tags_are_fine(text):
    value = parse_yaml_text(text)["a"]
    assert value == (12 if "int" in text else 12.0 if "float" in text else "12")


def billion_laughs(levels: int) -> str:
    rows = ['l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for k in range(1, levels):
        rows.append(f"l{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 10) + "]")
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("levels", [6, 9, 30])
def test_billion_laughs_is_refused_quickly(levels):
    text = billion_laughs(levels)        # 10**levels strings once expanded
    t0 = time.process_time()
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, "bomb.yaml")
    elapsed = time.process_time() - t0
    assert elapsed < 0.5, f"took {elapsed:.3f} s of CPU"
    # the line of the first top-level entry whose expansion passes the limit
    assert str(info.value) == ("bomb.yaml:6: the document expands to more than 200000 nodes "
                               "through aliases (&anchor/*alias); refused")


def test_aliases_within_the_limit_are_fine():
    doc = parse_yaml_text(billion_laughs(4))          # 10**4 strings
    assert len(doc["l3"]) == 10 and doc["l3"][0][0][0] == ["lol"] * 10


def test_recursive_alias_is_refused():
    with pytest.raises(YamlError, match="expands to more than"):
        parse_yaml_text("a: &a [1, *a]\n", "r.yaml")


@pytest.mark.parametrize("text, line", [
    ("x: " + "[" * 5000 + "]" * 5000 + "\n", 1),
    ("x: " + "{a: " * 5000 + "1" + "}" * 5000 + "\n", 1),
    ("".join("  " * i + "a:\n" for i in range(200)) + "  " * 200 + "1\n", 64),
], ids=["flow-list", "flow-map", "block-map"])
def test_deep_nesting_is_refused(text, line):
    t0 = time.process_time()
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, "deep.yaml")
    assert str(info.value) == f"deep.yaml:{line}: the document is nested more than 64 levels deep"
    assert time.process_time() - t0 < 0.5       # CPU seconds


def test_file_size_limit(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text("description: |\n" + ("  " + "x" * 98 + "\n") * 10486)
    size = path.stat().st_size
    assert size > yamlio.MAX_FILE_BYTES
    t0 = time.process_time()
    with pytest.raises(YamlError) as info:
        read_yaml_file(str(path))
    assert time.process_time() - t0 < 0.5       # CPU seconds
    assert str(info.value) == (f"{path}: the file is {size} bytes; diagrams are limited to "
                               "1048576 bytes")


def test_a_long_file_under_the_limit_is_read(tmp_path):
    path = tmp_path / "long.yaml"
    path.write_text("description: |\n" + ("  " + "x" * 98 + "\n") * 2000)
    assert len(read_yaml_file(str(path))["description"]) == 99 * 2000


@pytest.mark.parametrize("content, message", [
    (b"a: \xff\xfe\n", "the file is not UTF-8 text (byte 3)"),
    (b"a: 1\x00\n", "the file contains NUL bytes; it is not a text file"),
])
def test_binary_files_are_refused(tmp_path, content, message):
    path = tmp_path / "bin.yaml"
    path.write_bytes(content)
    with pytest.raises(YamlError) as info:
        read_yaml_file(str(path))
    assert str(info.value) == f"{path}: {message}"


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(YamlError) as info:
        read_yaml_file(str(tmp_path / "nope.yaml"))
    assert str(info.value) == f"{tmp_path / 'nope.yaml'}: cannot read the file: No such file or " \
                              "directory"
    with pytest.raises(YamlError) as info:
        read_yaml_file(str(tmp_path))
    assert str(info.value) == f"{tmp_path}: is a directory, not a diagram file"


@pytest.mark.parametrize("text, message", [
    ("a: 1\nb:\n  c: 2\n  c: 3\n", "4: duplicate key 'c' (first defined at line 3)"),
    ("1: a\n1.0: b\n", "2: duplicate key '1.0' (first defined at line 1)"),
    ("true: a\nTrue: b\n", "2: duplicate key 'True' (first defined at line 1)"),
    ("blocks:\n  g: {type: Gain}\n  g: {type: Sum}\n",
     "3: duplicate block name 'g' (first defined at line 2)"),
    ("parameters:\n  blocks: 1\nblocks:\n  g: 1\n  h: 2\n  h: 3\n",
     "6: duplicate block name 'h' (first defined at line 5)"),
    ("parameters:\n  g: 1\n  g: 2\nblocks: {}\n", "3: duplicate key 'g' (first defined at line 2)"),
])
def test_duplicate_keys_are_refused(text, message):
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, "dup.yaml")
    assert str(info.value) == (f"dup.yaml:{message}; YAML would silently keep only the last "
                               "one")


def test_merge_keys_may_override():
    doc = parse_yaml_text("base: &b {x: 1, y: 1}\nd:\n  <<: *b\n  x: 2\n")
    assert doc["d"] == {"x": 2, "y": 1}


@pytest.mark.parametrize("text, message", [
    ("a: " + "9" * 500 + "\n", "1: the integer on this line has 500 digits; numbers are "
                               "limited to 400"),
    ("a: 0x" + "f" * 5000 + "\n", "1: the integer on this line has 5002 digits; numbers are "
                                  "limited to 400"),
    ("? [1, 2]\n: 3\n", "1: a mapping key must be a plain value, not a list"),
    ("a: 1\n---\nb: 2\n", "2: not valid YAML: but found another document"),
    ("a:\t1\n", "1: not valid YAML: found character '\\t' that cannot start any token"),
], ids=["long-int", "long-hex", "list-key", "two-documents", "tab"])
def test_other_unreadable_documents(text, message):
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, "u.yaml")
    assert str(info.value) == f"u.yaml:{message}"


def test_dates_stay_strings_and_lines_are_kept():
    doc = parse_yaml_text("a: 2024-01-01\nb:\n  - x\n  - y\n")
    assert doc["a"] == "2024-01-01"
    assert doc.line_of("b") == 2 and doc["b"].line_of(1) == 4


def test_loader_is_safe_loader_subclass():
    assert issubclass(yamlio._DiagramLoader, yaml.SafeLoader)
    assert not issubclass(yamlio._DiagramLoader, (yaml.FullLoader, yaml.UnsafeLoader))


UNSAFE = re.compile(r"yaml\.(load|load_all|full_load|full_load_all|unsafe_load|unsafe_load_all)"
                    r"\s*\(|\b(Unsafe|Full)?Loader\b(?!\w)|yaml\.Loader|UnsafeLoader|FullLoader")


def test_no_unsafe_yaml_calls_anywhere():
    sources = list((REPO / "fwdstep").glob("*.py")) + list((REPO / "blocks").glob("*.py"))
    sources += [REPO / "cli.py"]
    offenders = []
    for path in sources:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if UNSAFE.search(code) and "SafeLoader" not in code:
                offenders.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert not offenders, "unsafe YAML loading:\n" + "\n".join(offenders)


# ------------------------------------------------------------------ hostile text
@pytest.mark.parametrize("char, name, kind", [
    ("\x07", "BEL", "control character"), ("\x1b", "ESC", "control character"),
    ("\x0c", "form feed", "control character"), ("\x7f", "DEL", "control character"),
    ("\x85\x9b", "U+009B", "control character"), ("\ufffe", "noncharacter U+FFFE", "character")])
def test_control_characters_are_reported_at_line_and_column(char, name, kind):
    text = f"a: 1\nb: [1, x{char}y]\n"
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text, file="f.yaml")
    shown = char[-1].encode("unicode_escape").decode() if char != "\ufffe" else "\\ufffe"
    column = 9 if char != "\x85\x9b" else 10          # U+0085 (NEL) is allowed by YAML
    assert str(info.value) == (f"f.yaml:2: column {column}: the {kind} {shown} ({name}) is not "
                               "allowed; a diagram is printable text (tabs and newlines allowed)")


def test_control_character_in_a_set_value_is_one_line(capsys, tmp_path):
    from fwdstep.cli import arguments as cli
    path = tmp_path / "d.yaml"
    path.write_text("parameters:\n  k: 1\nblocks:\n  c: {type: Constant, value: [1]}\n")
    assert cli.main(["validate", str(path), "--set", "k=[1, 2\x1b[2J]"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "\x1b" not in err and "\\x1b" in err, err


def test_a_megabyte_flow_list_is_refused_at_once_for_its_size_not_for_aliases(tmp_path):
    path = tmp_path / "flow.yaml"
    path.write_text("[" + ",".join(["1"] * 500_000) + "]\n")      # 1 000 002 bytes
    t0 = time.process_time()
    with pytest.raises(YamlError) as info:
        read_yaml_file(str(path))
    assert time.process_time() - t0 < 0.5
    assert str(info.value) == (
        f"{path}:1: the document has more than 50000 values (numbers, strings, lists, "
        "mappings); a diagram is limited to that: write large arrays as expressions such as "
        "ones(n) or eye(n)")


def test_values_are_counted_exactly_below_the_separator_estimate(monkeypatch):
    # 600 lines "kN: 1" pass the quick estimate; the composer counts 1 201 values
    monkeypatch.setattr(yamlio, "MAX_NODES", 1000)
    text = "".join(f"k{i}: 1\n" for i in range(600))
    assert sum(text.count(c) for c in ",\n[{") <= yamlio.MAX_NODES
    with pytest.raises(YamlError) as info:
        parse_yaml_text(text)
    assert "the document has more than 1000 values" in str(info.value)


def test_only_true_and_false_are_flags():
    """YAML 1.1 read yes/no/on/off as booleans: a parameter named `off` became False and
    failed as "parameter name 'False' is not a valid name"."""
    from fwdstep.core.yamlio import parse_yaml_text
    doc = parse_yaml_text("off: 1\non: [yes, no, Off]\nt: true\nf: FALSE\n", "x.yaml")
    assert doc == {"off": 1, "on": ["yes", "no", "Off"], "t": True, "f": False}
