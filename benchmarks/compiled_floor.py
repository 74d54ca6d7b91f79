"""Slotine-Li (2-link arm, 8 states, RK4, h = 1e-3), four ways, CPU-time ratios measured in
one run (medians of --repeats, interleaved) against the hand-written NumPy loop:

* hand NumPy loop (benchmarks/hand_loops.py) — the 1.0;
* fwdstep NumPy path (``simulate(d)``);
* fwdstep compiled path, warm (``simulate(d, backend="compiled")`` after a first run);
* the floor: the same closed loop as allocation-free numba scalar code (below).

With ``--sweep``: a 256-variant compiled sweep (``fwdstep sweep --backend compiled``: a 16 x
16 grid of K = k I and Gamma) against 256 runs of the numba scalar floor, CPU and wall
(the sweep runs its variants on every core; the floor loop on one), target <= 5.

Also the cold start of the compiled path: a fresh process with an empty cache directory
(``fwdstep run --backend compiled``, CPU time of the child), and a fresh process that finds
the compiled code in the cache.  Run: ``python benchmarks/compiled_floor.py [--t-final 10]``.
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
sys.path.insert(0, ROOT)

import fwdstep  # noqa: E402
import hand_loops  # noqa: E402
from fwdstep.structure.compiler import compile_spec  # noqa: E402
from fwdstep.structure.spec import load_spec  # noqa: E402

SLOTINE = os.path.join(ROOT, "diagrams", "slotine_li.yaml")


def numba_floor():
    """The allocation-free scalar numba loop of hand_loops.slotine_li (scalar Lambda)."""
    from numba import njit

    @njit(cache=False)
    def rhs(t, x, dx, lam, K, G, A, w, c, a1, a2, a3, a4):
        q1, q2, v1, v2 = x[0], x[1], x[2], x[3]
        s0 = math.sin(w[0] * t)
        s1 = math.sin(w[1] * t)
        o0 = math.cos(w[0] * t)
        o1 = math.cos(w[1] * t)
        qd1, qd2 = c[0] + A[0] * s0, c[1] + A[1] * s1
        dd1, dd2 = A[0] * w[0] * o0, A[1] * w[1] * o1
        ad1, ad2 = -A[0] * w[0] * w[0] * s0, -A[1] * w[1] * w[1] * s1
        z1 = dd1 - lam * (q1 - qd1)
        z2 = dd2 - lam * (q2 - qd2)
        zd1 = ad1 - lam * (v1 - dd1)
        zd2 = ad2 - lam * (v2 - dd2)
        r1, r2 = v1 - z1, v2 - z2
        c2, s2 = math.cos(q2), math.sin(q2)
        u1 = v2 * z1 + (v1 + v2) * z2
        u2 = v1 * z1
        w1 = 2.0 * zd1 + zd2
        Y00, Y01, Y02, Y03 = zd1, zd2, c2 * w1 - s2 * u1, s2 * w1 + c2 * u1
        Y11, Y12, Y13 = zd1 + zd2, c2 * zd1 + s2 * u2, s2 * zd1 - c2 * u2
        th0, th1, th2, th3 = x[4], x[5], x[6], x[7]
        t1 = Y00 * th0 + Y01 * th1 + Y02 * th2 + Y03 * th3 - (K[0, 0] * r1 + K[0, 1] * r2)
        t2 = Y11 * th1 + Y12 * th2 + Y13 * th3 - (K[1, 0] * r1 + K[1, 1] * r2)
        h12 = a2 + a3 * c2 + a4 * s2
        h11 = a1 + 2.0 * a3 * c2 + 2.0 * a4 * s2
        hh = a3 * s2 - a4 * c2
        b1 = t1 + hh * (2.0 * v1 + v2) * v2
        b2 = t2 - hh * v1 * v1
        det = h11 * a2 - h12 * h12
        dx[0], dx[1] = v1, v2
        dx[2] = (a2 * b1 - h12 * b2) / det
        dx[3] = (h11 * b2 - h12 * b1) / det
        g0 = Y00 * r1
        g1 = Y01 * r1 + Y11 * r2
        g2 = Y02 * r1 + Y12 * r2
        g3 = Y03 * r1 + Y13 * r2
        for i in range(4):
            dx[4 + i] = -(G[i, 0] * g0 + G[i, 1] * g1 + G[i, 2] * g2 + G[i, 3] * g3)

    @njit(cache=False)
    def run(x, n, h, every, log, lam, K, G, A, w, c, a1, a2, a3, a4):
        k1 = np.empty(8)
        k2 = np.empty(8)
        k3 = np.empty(8)
        k4 = np.empty(8)
        xs = np.empty(8)
        r = 0
        for i in range(n):
            t = i * h
            if i % every == 0:
                log[r, 0] = x[0] - (c[0] + A[0] * math.sin(w[0] * t))
                log[r, 1] = x[1] - (c[1] + A[1] * math.sin(w[1] * t))
                r += 1
            rhs(t, x, k1, lam, K, G, A, w, c, a1, a2, a3, a4)
            for j in range(8):
                xs[j] = x[j] + h / 2 * k1[j]
            rhs(t + h / 2, xs, k2, lam, K, G, A, w, c, a1, a2, a3, a4)
            for j in range(8):
                xs[j] = x[j] + h / 2 * k2[j]
            rhs(t + h / 2, xs, k3, lam, K, G, A, w, c, a1, a2, a3, a4)
            for j in range(8):
                xs[j] = x[j] + h * k3[j]
            rhs(t + h, xs, k4, lam, K, G, A, w, c, a1, a2, a3, a4)
            for j in range(8):
                x[j] = x[j] + h / 6 * (k1[j] + 2 * k2[j] + 2 * k3[j] + k4[j])
        return r

    return run


def cpu_of_child(cmd, env) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, env=env, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def sweep_vs_floor(args) -> int:
    """256 variants (16 K_D x 16 Gamma) as one compiled sweep and as 256 floor runs."""
    from fwdstep.sweeps.sweep import run_sweep
    spec = load_spec(SLOTINE)
    sim, p = spec.simulation, spec.parameters
    arm = next(e for e in spec.blocks if e.name == "arm").params
    ks, gammas = np.linspace(20.0, 80.0, 16), np.linspace(0.5, 4.0, 16)
    grid = {"K": [[[k, 0.0], [0.0, k]] for k in ks], "Gamma": [float(g) for g in gammas]}
    over = {"t_final": args.t_final}
    run = numba_floor()
    A, w, c = (np.asarray(p[k], dtype=float) for k in ("A", "w", "c"))
    n = int(round(args.t_final / sim.step))
    rows = n // sim.log_every + 1 + (1 if n % sim.log_every else 0)

    def floors():
        out = []
        for k in ks:
            for g in gammas:
                x = np.concatenate([np.broadcast_to(arm.get("q0", 0.0), (2,)), [0.0, 0.0],
                                    np.asarray(p["theta0"], dtype=float)])
                log = np.empty((rows, 2))
                r = run(x, n, sim.step, sim.log_every, log, float(p["Lambda"]),
                        k * np.eye(2), g * np.eye(4), A, w, c, hand_loops.A1, hand_loops.A2,
                        hand_loops.A3, hand_loops.A4)
                out.append(log[:r])
        return out

    def sweep():
        return run_sweep(SLOTINE, grid=grid, overrides=over, backend="compiled")

    floors()
    sweep()                                            # compile (or load from the cache)
    times = {"sweep": [], "floor": []}
    for _ in range(args.repeats):
        for name, fn in (("sweep", sweep), ("floor", floors)):
            w0, c0 = time.perf_counter(), time.process_time()
            out = fn()
            times[name].append((time.perf_counter() - w0, time.process_time() - c0))
            if name == "sweep":
                result = out
            else:
                logs = out
    e = result.parts[0]["e"] if len(result.parts) == 1 else None
    agree = ""
    if e is not None:
        order = [v.values for v in result.variants]
        diffs = []
        for j, values in enumerate(order):
            kk, gg = values["K"][0][0], values["Gamma"]
            i = int(np.argmin(np.abs(ks - kk))) * 16 + int(np.argmin(np.abs(gammas - gg)))
            diffs.append(np.max(np.abs(e[:len(logs[i]), j] - logs[i])))
        agree = f"; max |e_sweep - e_floor| = {max(diffs):.1e}"
    wall = {k: statistics.median([a for a, _ in v]) for k, v in times.items()}
    cpu = {k: statistics.median([b for _, b in v]) for k, v in times.items()}
    print(f"256-variant compiled sweep of Slotine-Li ({args.t_final:g} s, 16 K x 16 Gamma, "
          f"{len(result.batches)} batch(es), {os.cpu_count()} cpus){agree}")
    print(f"  sweep / 256 numba floor runs: cpu {cpu['sweep'] / cpu['floor']:.2f}x, wall "
          f"{wall['sweep'] / wall['floor']:.2f}x (target <= 5)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-cold", action="store_true", help="skip the fresh-process timings")
    ap.add_argument("--sweep", action="store_true",
                    help="only the 256-variant compiled sweep against 256 floor runs")
    args = ap.parse_args(argv)
    if args.sweep:
        return sweep_vs_floor(args)
    spec = load_spec(SLOTINE)
    spec.simulation.t_final = args.t_final
    sim, p = spec.simulation, spec.parameters
    d = compile_spec(spec)
    arm = next(e for e in spec.blocks if e.name == "arm").params
    hand = lambda: hand_loops.slotine_li(sim.t_final, sim.step, sim.log_every, p["Lambda"],  # noqa: E731
                                         p["K"], p["Gamma"], p["theta0"], p["A"], p["w"],
                                         p["c"], arm.get("q0", 0.0))
    run = numba_floor()
    K, G = hand_loops._matrix(p["K"], 2), hand_loops._matrix(p["Gamma"], 4)
    A, w, c = (np.asarray(p[k], dtype=float) for k in ("A", "w", "c"))
    n = sim.n_steps
    rows = n // sim.log_every + 1 + (1 if n % sim.log_every else 0)

    def floor():
        x = np.concatenate([np.broadcast_to(arm.get("q0", 0.0), (2,)), [0.0, 0.0],
                            np.asarray(p["theta0"], dtype=float)])
        log = np.empty((rows, 2))
        r = run(x, n, sim.step, sim.log_every, log, float(p["Lambda"]), K, G, A, w, c,
                hand_loops.A1, hand_loops.A2, hand_loops.A3, hand_loops.A4)
        return x, log[:r]

    floor()                                            # compile
    fwdstep.simulate(d, backend="compiled")            # compile (or load from the cache)
    fns = {"hand NumPy loop": hand, "fwdstep NumPy path": lambda: fwdstep.simulate(d),
           "fwdstep compiled, warm": lambda: fwdstep.simulate(d, backend="compiled"),
           "numba scalar floor": floor}
    cpu = {k: [] for k in fns}
    outs = {}
    for _ in range(args.repeats):
        for name, fn in fns.items():
            c0 = time.process_time()
            outs[name] = fn()
            cpu[name].append(time.process_time() - c0)
    med = {k: statistics.median(v) for k, v in cpu.items()}
    e_hand = outs["hand NumPy loop"][1]
    e_np = outs["fwdstep NumPy path"]["e.y"]
    e_cp = outs["fwdstep compiled, warm"]["e.y"]
    print(f"Slotine-Li, {sim.t_final:g} s, RK4 h = {sim.step:g}, {d.n_states} states; CPU "
          f"medians of {args.repeats}; max |e - e_hand|: NumPy path "
          f"{np.max(np.abs(e_np - e_hand[:len(e_np)])):.1e}, compiled "
          f"{np.max(np.abs(e_cp - e_hand[:len(e_cp)])):.1e}, floor "
          f"{np.max(np.abs(outs['numba scalar floor'][1] - e_hand[:len(outs['numba scalar floor'][1])])):.1e}")
    ref, flo = med["hand NumPy loop"], med["numba scalar floor"]
    for name in fns:
        print(f"  {name:26s} cpu {med[name]:8.4f} s   / hand {med[name] / ref:7.4f}   "
              f"/ floor {med[name] / flo:8.2f}")
    if not args.no_cold:
        with tempfile.TemporaryDirectory() as tmp:
            env = dict(os.environ, FWDSTEP_CACHE_DIR=os.path.join(tmp, "cache"),
                       MPLBACKEND="Agg")
            cmd = [sys.executable, os.path.join(ROOT, "cli.py"), "run", SLOTINE, "--backend",
                   "compiled", "--no-plots", "-q", "--force", "--set",
                   f"simulation.t_final={args.t_final}"]
            cold = cpu_of_child(cmd + ["-o", os.path.join(tmp, "a")], env)
            warm = cpu_of_child(cmd + ["-o", os.path.join(tmp, "b")], env)
            # a never-seen structure whose kernels are cached: the same diagram logging
            # one more signal (another generated loop, the same block kernels)
            with open(SLOTINE, encoding="utf-8") as fh:
                text = fh.read().replace("\n  - adapt.theta_hat\n",
                                         "\n  - adapt.theta_hat\n  - s.y\n", 1)
            other = os.path.join(tmp, "slotine_li_other.yaml")
            with open(other, "w", encoding="utf-8") as fh:
                fh.write(text)
            new_structure = cpu_of_child([other if c == SLOTINE else c for c in cmd]
                                         + ["-o", os.path.join(tmp, "d")], env)
            numpy_run = cpu_of_child([c for c in cmd if c not in ("--backend", "compiled")]
                                     + ["-o", os.path.join(tmp, "c")], env)
        print(f"  fresh process, whole 'fwdstep run' CPU: compiled cold (empty cache) "
              f"{cold:.1f} s, compiled from the cache {warm:.1f} s, a new structure with "
              f"cached kernels {new_structure:.1f} s, NumPy path {numpy_run:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
