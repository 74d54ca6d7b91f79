"""A 64-variant Panda sweep (payload mass and gains) in one batch, against 64 hand-loop runs
(issue 25 item 4; target: sweep <= 0.3x the 64 hand runs, one core).

    python benchmarks/robot_sweep_benchmark.py [--samples 64] [--t-final 1] [--repeats 3]
                                               [--backends numpy,compiled]

The variants of diagrams/robots/panda_slotine_li.yaml draw, from a seeded Latin hypercube,
``payload`` in [0, 2] kg (a point mass 0.1 m beyond the hand frame, URDFArm), ``Lambda`` in
[3, 8] and ``Gamma`` in [0.5, 2].  ``fwdstep.run_sweep(..., workers=1)`` runs them as one
batch, on the NumPy path (``implementation: auto``: the robot blocks' kernels as native code,
or pinocchio below 512 variants without llvmlite) and on the
compiled backend (``NUMBA_NUM_THREADS=1`` is set here: one core).  The hand loop is
``robots_benchmark.hand_loop_slotine_li``'s RK4 loop calling pinocchio directly, run once per
variant with that variant's gains and a pinocchio model with the payload appended by
pinocchio itself (``appendBodyToJoint``); its logged tracking errors are compared with the
sweep's, variant by variant (the same closed loops).  Repeats are interleaved; the ratios are
of CPU-time medians in this one run; the load average is printed.  The compiled backend's
first sweep (compiling the structure, or loading it from the cache) is untimed.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

from robots_benchmark import _rk4, slotine_li_by_hand  # noqa: E402

DIAGRAM = os.path.join(ROOT, "diagrams", "robots", "panda_slotine_li.yaml")
RANGES = {"payload": (0.0, 2.0), "Lambda": (3.0, 8.0), "Gamma": (0.5, 2.0)}


def hand_run(d, payload: float, lam: float, gamma: float, t_final: float):
    """One variant by hand: pinocchio's model with the payload appended, RK4; the log of
    e = q - q_d every log_every steps (rows, n)."""
    import pinocchio as pin

    arm = next(s.block for s in d.schedule if s.block.name == "arm")
    model = arm.model.copy()
    frame = model.frames[model.getFrameId("panda_hand")]
    model.appendBodyToJoint(frame.parentJoint, pin.Inertia(payload, np.array([0.0, 0.0, 0.1]),
                                                           np.zeros((3, 3))), frame.placement)
    data = model.createData()
    f, x, iq, q_d = slotine_li_by_hand(d, lam, gamma, model, data)
    step, log_every = d.spec.simulation.step, d.spec.simulation.log_every
    _, _, log = _rk4(f, x, t_final, step, log_every)
    t = np.arange(log.shape[0]) * (step * log_every)
    return log[:, iq] - q_d(t)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--t-final", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", default="numpy,compiled")
    args = parser.parse_args(argv)
    import fwdstep
    from fwdstep.sweeps.sweep import run_sweep

    backends = [b for b in args.backends.split(",") if b]
    fixed = {"t_final": args.t_final}
    random = dict(RANGES)                    # (low, high): uniform, as --random
    d = fwdstep.load_diagram(DIAGRAM, overrides=fixed)

    def sweep(backend, overrides=fixed):
        return run_sweep(DIAGRAM, random=random, samples=args.samples, seed=1, design="lhs",
                         overrides=overrides, workers=1, backend=backend)

    print(f"panda_slotine_li.yaml, {args.samples} variants (payload, Lambda, Gamma), "
          f"{args.t_final:g} s each; {args.repeats} interleaved repeats; load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    if "compiled" in backends:
        c0 = time.process_time()
        sweep("compiled", {"t_final": 10 * d.spec.simulation.step})
        print(f"compiled: compiling (or loading) the structure {time.process_time() - c0:.1f} s "
              f"CPU (untimed)", flush=True)
    cpu = {b: [] for b in backends + ["hand"]}
    results, hand_logs = {}, None
    for r in range(args.repeats):
        for b in backends:
            c0 = time.process_time()
            results[b] = sweep(b)
            cpu[b].append(time.process_time() - c0)
        c0 = time.process_time()
        logs = [hand_run(d, v.values["payload"], v.values["Lambda"], v.values["Gamma"],
                         args.t_final) for v in results[backends[0]].variants]
        cpu["hand"].append(time.process_time() - c0)
        hand_logs = logs
        print(f"repeat {r + 1}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in cpu.items())
              + f"; load average {os.getloadavg()[0]:.2f}", flush=True)
    med = {k: statistics.median(v) for k, v in cpu.items()}
    for b in backends:
        res = results[b]
        signals = {int(i): part["e"][:, k] for part in res.parts
                   for k, i in enumerate(part["indices"])}
        worst = max(float(np.abs(signals[v.index] - hand_logs[j]).max())
                    for j, v in enumerate(res.variants))
        print(f"{b:8s} sweep: {len(res.batches)} batch(es), counts {res.counts()}, median "
              f"{med[b]:.2f} s CPU; / {args.samples} hand runs = {med[b] / med['hand']:.3f} "
              f"(target <= 0.3); largest |e_sweep - e_hand| over the variants {worst:.1e} rad")
    print(f"hand loop, {args.samples} runs: median {med['hand']:.2f} s CPU "
          f"({med['hand'] / args.samples * 1e3:.1f} ms each); load average "
          f"{os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
