"""The cost of watching zero crossings that never happen (issue 26: <= 5 %).

Slotine-Li (2-link arm, 8 states, RK4, h = 1e-3), four diagrams:

* as shipped (diagrams/slotine_li.yaml);
* with a unit ``Gain`` between ``tau`` and the arm (the same wiring, no guard);
* with ``UnguardedSaturation`` there (defined below: a ``Saturation`` that declares no
  zero-crossing functions), limits +-1e6 N m: the Saturation's own arithmetic (min, max)
  without guards;
* with a ``Saturation`` there whose limits (+-1e6 N m) are never reached: the same
  arithmetic and 4 guards watched at every step (``fwdstep.run.crossings``; the compiled
  stage compares their signs, ``fwdstep.compiled.backend_numba._guard_check``).

The cost of watching is Saturation / UnguardedSaturation.

CPU-time medians of interleaved repeats in one process, for the compiled backend (warm) and
the NumPy path; the runs with the Saturation must give the Gain's numbers and no event.
Run: ``python benchmarks/crossing_cost.py [--t-final 100] [--repeats 9] [--numpy]``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import fwdstep  # noqa: E402
from fwdstep.registry import register  # noqa: E402
from fwdstep.blocks.nonlinear import Saturation  # noqa: E402


@register
class UnguardedSaturation(Saturation):
    """UnguardedSaturation: a Saturation without zero-crossing functions (the baseline of
    this benchmark only: its kink is integrated through)."""

    def setup(self, lower, upper, shape):
        super().setup(lower, upper, shape)
        self.declare_zero_crossings(())


SLOTINE = os.path.join(ROOT, "diagrams", "slotine_li.yaml")


def variant(text: str, block: str, extra: str = "", wires: str = "") -> str:
    """Slotine-Li with ``block`` (YAML of a block named 'lim') between tau and the arm;
    ``extra`` blocks and ``wires`` (YAML lines) added."""
    text = text.replace("  - tau.y -> arm.tau",
                        "  - tau.y -> lim.u\n  - lim.y -> arm.tau" + wires, 1)
    return text.replace("\nconnections:", f"\n  lim:   {block}{extra}\nconnections:", 1)

KINDS = {
    "unit Gain": ("{type: Gain, gain: 1.0, shape: [2]}", "", ""),
    "unguarded": ("{type: UnguardedSaturation, lower: -1.0e6, upper: 1.0e6, shape: [2]}",
                  "", ""),
    "Saturation": ("{type: Saturation, lower: -1.0e6, upper: 1.0e6, shape: [2]}", "", ""),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--numpy", action="store_true",
                    help="also the NumPy path (about 1 s of CPU per simulated second)")
    args = ap.parse_args(argv)
    backends = ("compiled", "numpy") if args.numpy else ("compiled",)
    with open(SLOTINE, encoding="utf-8") as fh:
        text = fh.read()
    over = {"t_final": args.t_final}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {"shipped": SLOTINE}
        for name, (block, extra, wires) in KINDS.items():
            paths[name] = os.path.join(tmp, name.replace(" ", "_") + ".yaml")
            with open(paths[name], "w", encoding="utf-8") as fh:
                fh.write(variant(text, block, extra, wires))
        diagrams = {k: fwdstep.load_diagram(p, over) for k, p in paths.items()}
        fns = {}
        for name, d in diagrams.items():
            for backend in backends:
                fns[(name, backend)] = (lambda d=d, b=backend: fwdstep.simulate(d, backend=b))
        outs = {k: fn() for k, fn in fns.items()}          # compile (or load the cache)
        cpu = {k: [] for k in fns}
        for _ in range(args.repeats):
            for key, fn in fns.items():
                c0 = time.process_time()
                outs[key] = fn()
                cpu[key].append(time.process_time() - c0)
    med = {k: statistics.median(v) for k, v in cpu.items()}
    sat, gain = outs[("Saturation", "compiled")], outs[("unit Gain", "compiled")]
    assert sat.backend == "compiled" and sat.events == [], (sat.backend, sat.events)
    diff = max(np.max(np.abs(sat[n] - gain[n])) for n in ("e.y", "tau.y"))
    print(f"Slotine-Li, {args.t_final:g} s, RK4 h = 1e-3; CPU medians of {args.repeats} "
          f"interleaved repeats; load average {os.getloadavg()[0]:.1f}; max |Saturation - "
          f"Gain| (e, tau, compiled) = {diff:.1e}, events {len(sat.events)}")
    for backend in backends:
        base, bare = med[("shipped", backend)], med[("unguarded", backend)]
        for name in diagrams:
            t = med[(name, backend)]
            print(f"  {backend:8s} {name:10s} cpu {t:8.4f} s   / shipped {t / base:6.3f}   "
                  f"/ unguarded {t / bare:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
