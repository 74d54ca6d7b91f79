"""Safe YAML reading for diagram files.

Built on ``yaml.SafeLoader`` (no Python tags, no code), plus what PyYAML does not do:
duplicate keys are refused (PyYAML silently keeps the last), every mapping and list remembers
the line it came from (for error messages), alias/anchor expansion is bounded ("billion
laughs" refused before anything is expanded), and files larger than ``MAX_FILE_BYTES`` are
refused before they are read.
"""
from __future__ import annotations

import os
import re

import yaml

from fwdstep.core.errors import YamlError, printable

MAX_FILE_BYTES = 1 << 20          # 1 MiB: a diagram is text written by a person
MAX_EXPANDED_NODES = 200_000      # nodes after alias expansion
MAX_DEPTH = 64                    # nesting of mappings and lists
MAX_INTEGER_DIGITS = 400          # a float holds at most ~309 decimal digits anyway
MAX_NODES = 50_000                # values written in the file (a theorem diagram has ~1 000)

#: characters YAML forbids (C0/C1 controls but tab/newline, DEL, U+FFFE/U+FFFF, surrogates)
_NOT_YAML = re.compile("[^\x09\x0A\x0D\x20-\x7E\x85\xA0-\uD7FF\uE000-\uFFFD"
                       "\U00010000-\U0010FFFF]")
_CONTROL_NAMES = {0x00: "NUL", 0x07: "BEL", 0x08: "backspace", 0x0B: "vertical tab",
                  0x0C: "form feed", 0x1B: "ESC", 0x7F: "DEL", 0xFFFE: "noncharacter U+FFFE",
                  0xFFFF: "noncharacter U+FFFF"}


class LineDict(dict):
    """A dict that remembers its own line and the line of each key (1-based)."""

    line: int | None = None
    key_lines: dict

    def line_of(self, key) -> int | None:
        return getattr(self, "key_lines", {}).get(key, self.line)


class LineList(list):
    """A list that remembers its own line and each item's line (1-based)."""

    line: int | None = None
    item_lines: list

    def line_of(self, index: int) -> int | None:
        lines = getattr(self, "item_lines", [])
        return lines[index] if index < len(lines) else self.line


class _DiagramLoader(yaml.SafeLoader):
    #: id() of the node under the top-level ``blocks:`` key (its keys are block names)
    blocks_node_id: int | None = None
    _current_scalar: yaml.Node | None = None
    _depth: int = 0

    def construct_scalar(self, node):
        self._current_scalar = node      # remembered for errors raised while converting it
        return super().construct_scalar(node)

    def compose_node(self, parent, index):
        # PyYAML composes recursively: bound the depth before Python's recursion limit (and
        # before the scanner's quadratic cost on thousands of open brackets) is reached
        self._nodes = getattr(self, "_nodes", 0) + 1
        if self._nodes > MAX_NODES:
            raise _too_many_values(self.peek_event().start_mark.line + 1)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                mark = self.peek_event().start_mark
                raise YamlError(f"the document is nested more than {MAX_DEPTH} levels deep",
                                line=mark.line + 1)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def fetch_flow_collection_start(self, TokenClass):
        # the scanner looks ahead over every open '[' or '{' (quadratic up to ~1000 of them):
        # stop at the depth limit here, before the composer ever sees them
        if self.flow_level >= MAX_DEPTH:
            raise YamlError(f"the document is nested more than {MAX_DEPTH} levels deep",
                            line=self.line + 1)
        super().fetch_flow_collection_start(TokenClass)

    def construct_yaml_int(self, node):
        if len(node.value) > MAX_INTEGER_DIGITS:
            raise YamlError(f"the integer on this line has {len(node.value)} digits; numbers "
                            f"are limited to {MAX_INTEGER_DIGITS}", line=node.start_mark.line + 1)
        return super().construct_yaml_int(node)


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode):
    seen: dict = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            kind = "a list" if isinstance(key, list) else "a mapping" if isinstance(key, dict) \
                else type(key).__name__
            raise YamlError(f"a mapping key must be a plain value, not {kind}",
                            line=key_node.start_mark.line + 1) from None
        if key in seen:
            what = "block name" if id(node) == loader.blocks_node_id else "key"
            raise YamlError(f"duplicate {what} '{key}' (first defined at line {seen[key]}); "
                            "YAML would silently keep only the last one",
                            line=key_node.start_mark.line + 1)
        seen[key] = key_node.start_mark.line + 1
    loader.flatten_mapping(node)
    out = LineDict()
    out.line = node.start_mark.line + 1
    out.key_lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        out[key] = loader.construct_object(value_node, deep=True)
        out.key_lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: yaml.SafeLoader, node: yaml.SequenceNode):
    out = LineList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.item_lines = [child.start_mark.line + 1 for child in node.value]
    return out


def _refuse_tag(loader: yaml.SafeLoader, tag_suffix: str, node: yaml.Node):
    tag = node.tag.replace("tag:yaml.org,2002:", "!!")
    raise YamlError(f"tag '{tag}' is not allowed: diagrams may contain only plain YAML "
                    "(mappings, lists, numbers, strings, booleans)",
                    line=node.start_mark.line + 1)


_DiagramLoader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)
_DiagramLoader.add_constructor("tag:yaml.org,2002:seq", _construct_sequence)
_DiagramLoader.add_constructor("tag:yaml.org,2002:int", _DiagramLoader.construct_yaml_int)
_DiagramLoader.add_multi_constructor("", _refuse_tag)
_DiagramLoader.add_multi_constructor("!", _refuse_tag)
_DiagramLoader.add_multi_constructor("tag:yaml.org,2002:python/", _refuse_tag)
for _tag in ("binary", "timestamp", "set", "omap", "pairs"):
    _DiagramLoader.add_constructor(f"tag:yaml.org,2002:{_tag}",
                                   lambda loader, node: _refuse_tag(loader, "", node))
# dates like 2024-01-01 are plain strings here, not datetime objects; booleans are YAML
# 1.2's true/false only: YAML 1.1 also read yes/no/on/off as booleans, so a parameter or
# block named `off` became False (and `gain: no` a flag)
_DiagramLoader.yaml_implicit_resolvers = {
    k: [(tag, rx) for tag, rx in v
        if tag not in ("tag:yaml.org,2002:timestamp", "tag:yaml.org,2002:bool")]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_DiagramLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
    list("tTfF"))


def _expanded_size(node: yaml.Node, memo: dict, limit: int) -> int:
    key = id(node)
    if key in memo:
        return memo[key]
    memo[key] = limit + 1  # guards against recursive aliases
    if isinstance(node, yaml.ScalarNode):
        size = 1
    elif isinstance(node, yaml.SequenceNode):
        size = 1
        for child in node.value:
            size += _expanded_size(child, memo, limit)
            if size > limit:
                break
    else:
        size = 1
        for k, v in node.value:
            size += _expanded_size(k, memo, limit) + _expanded_size(v, memo, limit)
            if size > limit:
                break
    memo[key] = size
    return size


def _bomb_line(root: yaml.Node) -> int:
    """The line of the top-level entry at which alias expansion passes the limit."""
    children = []
    if isinstance(root, yaml.SequenceNode):
        children = [(c, c) for c in root.value]
    elif isinstance(root, yaml.MappingNode):
        children = list(root.value)
    total, memo = 1, {}
    for first, value in children:
        total += _expanded_size(value, memo, MAX_EXPANDED_NODES) + (first is not value)
        if total > MAX_EXPANDED_NODES:
            return first.start_mark.line + 1
    return root.start_mark.line + 1


def _blocks_node_id(root: yaml.Node) -> int | None:
    if isinstance(root, yaml.MappingNode):
        for key_node, value_node in root.value:
            if isinstance(key_node, yaml.ScalarNode) and key_node.value == "blocks":
                return id(value_node)
    return None


def _value_error_line(loader: yaml.SafeLoader) -> int | None:
    """Best effort: the line of the scalar being constructed when a ValueError escaped."""
    node = getattr(loader, "_current_scalar", None)
    return node.start_mark.line + 1 if node is not None else None


def parse_yaml_text(text: str, file: str | None = None):
    """Parse YAML text into LineDict/LineList/scalars, with every safety check."""
    bad = _NOT_YAML.search(text)
    if bad is not None:
        raise _control_character(text, bad.start(), file)
    # PyYAML reads ~50 000 values a second: a 1 MB flow list ([1,1,1,...]) is refused from a
    # count of separators (C speed) before parsing; the exact count is in compose_node
    if sum(text.count(c) for c in ",\n[{") > MAX_NODES:
        n = 0
        for number, line in enumerate(text.split("\n"), start=1):
            n += 1 + sum(line.count(c) for c in ",[{")
            if n > MAX_NODES:
                break
        raise _too_many_values(number).located(file)
    loader = _DiagramLoader(text)
    try:
        try:
            node = loader.get_single_node()
        except YamlError as exc:
            raise exc.located(file) from None
        except RecursionError:
            raise YamlError("the document is nested too deeply", file=file) from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise YamlError(f"not valid YAML: {problem}", file=file,
                            line=mark.line + 1 if mark else None) from None
        if node is None:
            return None
        if _expanded_size(node, {}, MAX_EXPANDED_NODES) > MAX_EXPANDED_NODES:
            raise YamlError(f"the document expands to more than {MAX_EXPANDED_NODES} nodes "
                            "through aliases (&anchor/*alias); refused", file=file,
                            line=_bomb_line(node))
        loader.blocks_node_id = _blocks_node_id(node)
        try:
            return loader.construct_document(node)
        except YamlError as exc:
            raise exc.located(file) from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            raise YamlError(f"not valid YAML: {getattr(exc, 'problem', exc)}", file=file,
                            line=mark.line + 1 if mark else None) from None
        except RecursionError:
            raise YamlError("the document is nested too deeply", file=file) from None
        except (ValueError, OverflowError) as exc:
            # a scalar PyYAML's resolver accepted but Python cannot convert
            reason = str(exc).split(";")[0]
            raise YamlError(f"not valid YAML: a value cannot be read: {reason}"[:300], file=file,
                            line=_value_error_line(loader)) from None
    finally:
        loader.dispose()


def _too_many_values(line: int) -> YamlError:
    return YamlError(f"the document has more than {MAX_NODES} values (numbers, strings, lists, "
                     "mappings); a diagram is limited to that: write large arrays as "
                     "expressions such as ones(n) or eye(n)", line=line)


def _control_character(text: str, pos: int, file: str | None) -> YamlError:
    """The first character YAML does not allow, at its line and column (1-based)."""
    line = text.count("\n", 0, pos) + 1
    column = pos - (text.rfind("\n", 0, pos) + 1) + 1
    code = ord(text[pos])
    name = _CONTROL_NAMES.get(code, f"U+{code:04X}")
    kind = "control character" if code < 0x20 or 0x7F <= code < 0xA0 else "character"
    return YamlError(f"column {column}: the {kind} {printable(text[pos])} ({name}) is not "
                     "allowed; a diagram is printable text (tabs and newlines allowed)",
                     file=file, line=line)


def read_yaml_file(path: str):
    """Read and parse a diagram file; refuse what is too big before reading it."""
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise YamlError(f"cannot read the file: {exc.strerror}", file=path) from None
    if os.path.isdir(path):
        raise YamlError("is a directory, not a diagram file", file=path)
    if size > MAX_FILE_BYTES:
        raise YamlError(f"the file is {size} bytes; diagrams are limited to {MAX_FILE_BYTES} "
                        "bytes", file=path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise YamlError(f"the file is not UTF-8 text (byte {exc.start})", file=path) from None
    except OSError as exc:
        raise YamlError(f"cannot read the file: {exc.strerror}", file=path) from None
    if "\x00" in text:
        raise YamlError("the file contains NUL bytes; it is not a text file", file=path)
    return parse_yaml_text(text, file=path)
