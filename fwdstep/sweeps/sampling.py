"""Which variants a sweep runs: grids, distributions and sampling designs (seeded).

``--grid NAME=V1,V2,...`` lists values; ``--random NAME=DIST`` draws ``--samples N`` values
per grid cell, where DIST is

==========================  ====================================================
``LOW:HIGH``                uniform in [LOW, HIGH] (same as ``uniform:LOW:HIGH``)
``loguniform:LOW:HIGH``     log-uniform: log(value) uniform, 0 < LOW <= HIGH
``normal:MEAN:SD``          normal with mean MEAN and standard deviation SD >= 0
==========================  ====================================================

The N points of the unit hypercube (one axis per random parameter) come from ``--design``:
``random`` (independent uniform draws, ``numpy.random.default_rng(seed)``), ``lhs`` (Latin
hypercube, ``scipy.stats.qmc.LatinHypercube``: each axis cut in N strata, one point per
stratum) or ``sobol`` (scrambled Sobol sequence, ``scipy.stats.qmc.Sobol``: N should be a
power of 2); each point is mapped to the distributions by their inverse CDFs.  The same seed
gives the same variants.
"""
from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np

from fwdstep.core.errors import ConfigError

#: Refuse sweeps with more variants than this (each variant is a diagram in memory).
MAX_VARIANTS = 100_000
DESIGNS = ("random", "lhs", "sobol")
DISTRIBUTIONS = ("uniform", "loguniform", "normal")


class Distribution(NamedTuple):
    """One random parameter: ``kind`` in DISTRIBUTIONS and its two numbers (LOW, HIGH for
    uniform/loguniform; MEAN, SD for normal)."""
    kind: str
    a: float
    b: float

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Map points u in (0, 1) by the inverse CDF."""
        if self.kind == "uniform":
            return self.a + u * (self.b - self.a)
        if self.kind == "loguniform":
            return np.exp(np.log(self.a) + u * (np.log(self.b) - np.log(self.a)))
        from scipy.special import ndtri
        return self.a + self.b * ndtri(np.clip(u, 1e-16, 1 - 1e-16))


def split_values(text: str) -> list:
    """'1,2,[3, 4],f(5,6)' -> ['1', '2', '[3, 4]', 'f(5,6)']: commas at bracket depth 0."""
    parts, depth, current = [], 0, ""
    for ch in text:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    parts.append(current)
    return [p.strip() for p in parts]


def parse_grid(items: list) -> dict:
    """``["ell=1,2,3", "K=20,50"]`` -> {"ell": [1, 2, 3], "K": [20, 50]} (values read like
    ``--set`` values: numbers, lists, or expression strings)."""
    from fwdstep.structure.spec import parse_override
    grid: dict = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--grid '{item}' must have the form NAME=V1,V2,...")
        name, raw = item.split("=", 1)
        values = []
        for part in split_values(raw):
            if not part:
                raise ConfigError(f"--grid '{item}' has an empty value")
            values.append(parse_override(f"{name.strip()}={part}")[1])
        name = name.strip()
        if name in grid:
            raise ConfigError(f"--grid {name} is given twice")
        grid[name] = values
    return grid


def parse_random(items: list) -> dict:
    """``["alpha=1:5", "K=loguniform:1:100", "m=normal:2:0.1"]`` -> name -> Distribution."""
    out: dict = {}
    for item in items or []:
        name, sep, raw = item.partition("=")
        fields = raw.split(":")
        kind = "uniform" if len(fields) == 2 else fields[0].strip().lower()
        numbers = fields[-2:] if len(fields) in (2, 3) else []
        try:
            a, b = (float(x) for x in numbers)
        except ValueError:
            a = b = None
        form = (f"--random '{item}' must have the form NAME=LOW:HIGH, "
                "NAME=loguniform:LOW:HIGH or NAME=normal:MEAN:SD")
        if not sep or a is None or kind not in DISTRIBUTIONS or not (
                np.isfinite(a) and np.isfinite(b)):
            raise ConfigError(form)
        if kind == "normal" and b < 0:
            raise ConfigError(f"--random '{item}': SD must not be negative")
        if kind != "normal" and not a <= b:
            raise ConfigError(f"--random '{item}': LOW must not exceed HIGH")
        if kind == "loguniform" and a <= 0:
            raise ConfigError(f"--random '{item}': loguniform needs 0 < LOW")
        name = name.strip()
        if name in out:
            raise ConfigError(f"--random {name} is given twice")
        out[name] = Distribution(kind, a, b)
    return out


def as_distribution(value) -> Distribution:
    """A Distribution, or (low, high) for uniform (the Python API accepts both)."""
    if isinstance(value, Distribution):
        return value
    low, high = value
    return Distribution("uniform", float(low), float(high))


def unit_points(n: int, d: int, design: str, seed: int) -> np.ndarray:
    """n points of the d-dimensional unit hypercube by the named design."""
    if design not in DESIGNS:
        raise ConfigError(f"--design '{design}' is unknown; designs are: {', '.join(DESIGNS)}")
    if design == "random":
        return np.random.default_rng(seed).uniform(size=(n, d))
    from scipy.stats import qmc
    kind = qmc.LatinHypercube if design == "lhs" else qmc.Sobol
    try:                                   # scipy >= 1.15 names the generator 'rng'
        engine = kind(d=d, rng=np.random.default_rng(seed))
    except TypeError:                      # pragma: no cover - older scipy
        engine = kind(d=d, seed=np.random.default_rng(seed))
    if design == "sobol":
        import warnings
        with warnings.catch_warnings():    # n not a power of 2: still a valid design
            warnings.simplefilter("ignore")
            return engine.random(n)
    return engine.random(n)


def variant_values(grid: dict, random: dict, samples: int, seed: int,
                   design: str = "random") -> list:
    """The swept values of every variant: the grid product, each cell with ``samples``
    draws of the random parameters (the same draws in every cell)."""
    random = {k: as_distribution(v) for k, v in (random or {}).items()}
    both = set(grid) & set(random)
    if both:
        raise ConfigError(f"parameter '{sorted(both)[0]}' is both in --grid and --random")
    if random and samples < 1:
        raise ConfigError("--random needs --samples N (N >= 1)")
    if samples and not random:
        raise ConfigError("--samples needs at least one --random NAME=LOW:HIGH")
    if not grid and not random:
        raise ConfigError("nothing to sweep: give --grid NAME=V1,V2,... or --random "
                          "NAME=LOW:HIGH --samples N")
    n_grid = math.prod(len(v) for v in grid.values())      # Python ints: never overflow
    total = n_grid * max(int(samples), 1)
    if total > MAX_VARIANTS:
        raise ConfigError(f"the sweep has {total} variants; the limit is {MAX_VARIANTS}")
    draws = {}
    if random:
        u = unit_points(samples, len(random), design, seed)
        draws = {name: dist.from_unit(u[:, k]) for k, (name, dist) in enumerate(random.items())}
    out = []
    for combo in itertools.product(*grid.values()) if grid else [()]:
        base = dict(zip(grid, combo))
        for k in range(max(samples, 1)):
            values = dict(base)
            values.update({name: float(draws[name][k]) for name in random})
            out.append(values)
    return out


def variant_seeds(n: int, seed: int) -> list:
    """One independent integer seed per variant (``numpy.random.SeedSequence(seed).spawn``),
    for diagrams whose noise blocks take a ``seed`` parameter."""
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(n)]


__all__ = ["Distribution", "DESIGNS", "DISTRIBUTIONS", "parse_grid", "parse_random",
           "split_values", "unit_points", "variant_values", "variant_seeds"]
