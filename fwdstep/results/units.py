"""Units of recorded signals, as far as fwdstep can convert between them.

A unit is the text a diagram or a block gives (``rad``, ``deg``, ``rad/s``, ``N m``,
``m/s^2``, ``rad s$^{-1}$``).  ``factor(a, b)`` is the number that turns values in ``a`` into
values in ``b`` when both are products of powers of known units with the same dimensions
(``deg`` -> ``rad``: pi/180; ``mm/s`` -> ``m/s``: 1e-3), 1.0 when the two texts are equal,
and None otherwise: then the values cannot be put on one axis, and ``fwdstep compare``
refuses their difference instead of plotting it in one run's unit.
"""
from __future__ import annotations

import math
import re

#: unit -> (factor to the base unit, base dimension)
KNOWN = {
    "rad": (1.0, "rad"), "mrad": (1e-3, "rad"), "deg": (math.pi / 180, "rad"),
    "degree": (math.pi / 180, "rad"), "degrees": (math.pi / 180, "rad"),
    "°": (math.pi / 180, "rad"),
    "rev": (2 * math.pi, "rad"), "turn": (2 * math.pi, "rad"),
    "m": (1.0, "m"), "mm": (1e-3, "m"), "cm": (1e-2, "m"), "km": (1e3, "m"),
    "um": (1e-6, "m"), "µm": (1e-6, "m"),
    "s": (1.0, "s"), "ms": (1e-3, "s"), "us": (1e-6, "s"), "min": (60.0, "s"),
    "h": (3600.0, "s"), "hz": (1.0, "1/s"), "Hz": (1.0, "1/s"),
    "N": (1.0, "N"), "kN": (1e3, "N"), "mN": (1e-3, "N"),
    "kg": (1.0, "kg"), "g": (1e-3, "kg"),
    "rpm": (2 * math.pi / 60, "rad/s"),
}
_SUPERSCRIPTS = {"⁻¹": "^-1", "⁻²": "^-2", "²": "^2", "³": "^3"}
_TOKEN = re.compile(r"^(?P<name>[^\^]+)(?:\^(?P<power>[+-]?\d+))?$")


def parse(unit: str):
    """(factor, dimensions) of ``unit``: dimensions a sorted tuple of (base, power); None if
    some part is not a known unit.  Mathtext markup (``$``, braces, ``\\mathrm``) is ignored:
    ``rad s$^{-1}$`` is ``rad/s``."""
    text = unit.replace("$", "").replace("\\mathrm", "").replace("{", "").replace("}", "")
    for old, new in (("^\\circ", "°"), ("\\circ", "°"), ("\\cdot", " "), ("\\,", " "),
                     ("\\ ", " "), ("·", " "), ("*", " ")):
        text = text.replace(old, new)
    for sup, power in _SUPERSCRIPTS.items():
        text = text.replace(sup, power)
    text = re.sub(r"\s*\^\s*", "^", text).strip()
    if not text:
        return None
    num, _, den = text.partition("/")
    if "/" in den:
        return None
    factor, dims = 1.0, {}
    for side, sign in ((num, 1), (den, -1)):
        for token in side.replace("(", " ").replace(")", " ").split():
            if token == "1":
                continue
            m = _TOKEN.match(token)
            if m is None or m.group("name") not in KNOWN:
                return None
            power = int(m.group("power") or 1) * sign
            f, base = KNOWN[m.group("name")]
            factor *= f ** power
            for part, p in _base_parts(base):
                dims[part] = dims.get(part, 0) + p * power
    return factor, tuple(sorted((k, v) for k, v in dims.items() if v))


def _base_parts(base: str):
    if "/" in base:
        a, b = base.split("/")
        return ([(a, 1)] if a != "1" else []) + [(b, -1)]
    return [(base, 1)]


def factor(source: str, target: str) -> float | None:
    """The factor turning values in unit ``source`` into unit ``target``; 1.0 for equal
    texts (or when either is not given), None when they cannot be converted."""
    if source == target or not source or not target:
        return 1.0
    a, b = parse(source), parse(target)
    if a is None or b is None or a[1] != b[1]:
        return None
    return a[0] / b[0]
