"""The structure of a figure text's mathtext, checked without matplotlib.

Labels, units and component names of a diagram's ``log:``/``plots:`` entries and its
description reach the figures, where matplotlib typesets the parts between dollar signs
(only when the text holds an even, non-zero number of unescaped ``$``; otherwise it is
plain text).  A typo there (``rad/s$^{2$``) used to pass ``validate`` and fail at the end of
a run.  ``problem(text)`` finds the typos matplotlib's parser stops on -- a brace never
closed or closed twice, a ``^`` or ``_`` with nothing to raise or lower, a double
superscript or subscript -- at load time, with no import of matplotlib (``fwdstep
validate`` stays light).  What only the full parser knows (an unknown ``\\command``) is
shown literally when the figure is drawn (``fwdstep.results.plotting``), never lost.
"""
from __future__ import annotations

import re

_DOLLAR = re.compile(r"(?<!\\)\$")


def problem(text: str) -> str | None:
    """Why matplotlib would refuse ``text``'s mathtext, or None."""
    pieces = _DOLLAR.split(text)
    if len(pieces) < 3 or len(pieces) % 2 == 0:      # no $, or an odd number: plain text
        return None
    for math in pieces[1::2]:
        why = _segment_problem(math)
        if why is not None:
            return why
    return None


def _segment_problem(math: str) -> str | None:
    # one entry per open brace group: [the scripts its last atom already has, whether the
    # group is the argument of a ^ or _ (closing it then keeps the atom's scripts)]
    groups: list = [[set(), False]]
    argument = False                    # the next atom is the argument of a ^ or _
    i, n = 0, len(math)
    while i < n:
        c = math[i]
        if c.isspace():
            i += 1
            continue
        if c == "{":
            groups.append([set(), argument])
            argument = False
        elif c == "}":
            if len(groups) == 1:
                return "a '}' closes no '{'"
            _, was_argument = groups.pop()
            if not was_argument:
                groups[-1][0] = set()   # the group is a new atom
        elif c in "^_":
            rest = math[i + 1:].lstrip()
            if not rest or rest[0] in "}^_":
                return f"'{c}' has nothing after it to {'raise' if c == '^' else 'lower'}"
            if c in groups[-1][0]:
                return ("double " + ("superscript" if c == "^" else "subscript") +
                        " (group one of them in braces: x^{a^b})")
            groups[-1][0].add(c)
            argument = True
        else:
            if c == "\\":                 # an escaped character or a command
                i += 1
                while i + 1 < n and math[i].isalpha() and math[i + 1].isalpha():
                    i += 1
            if not argument:
                groups[-1][0] = set()   # a new atom
            argument = False
        i += 1
    if len(groups) > 1:
        return "a '{' is never closed"
    return None
