"""fwdstep speed benchmarks (not part of the test suite): medians and ratios, in one run.

    python benchmarks/run_benchmarks.py            # everything, medians of 5 (a few minutes)
    python benchmarks/run_benchmarks.py --quick    # 2 s runs, 3 repeats: a smoke check
    python benchmarks/run_benchmarks.py --only a,c --repeats 7 --json out.json

(a) diagrams/slotine_li.yaml (10 s, step 1e-3, rk4) vs a hand-written NumPy RK4 loop of the
    same closed loop (benchmarks/hand_loops.py), target <= 1.0;
(b) diagrams/theorem1.yaml with ell = 3 vs its hand-written loop;
(c) a 256-variant sweep of slotine_li.yaml (Lambda random in [2, 10]) vs one run (target
    <= 8) and vs 256 sequential runs (estimated as 256 x one run; --full runs them);
(d) run time of theorem1.yaml against ell = 1..10 (q_d constant), with its hand loop, and
    of an n-link arm (NLinkArm) loop against the number of joints n = 2..8;
(a) and (b) also time the optional compiled backend (numba) when it is installed, in the
process and in fresh processes that load the compiled code from the disk cache;
plus the other targets of issue 7: memory of a 10 s run logging every signal every step,
and the wall time of ``fwdstep validate`` in a fresh process (no matplotlib, no numba).

Each comparison interleaves its repeats (A, B, A, B, ...) so that a busy machine slows both
sides alike; wall and CPU (process) times are printed, ratios are of medians.  The hand
loops read their numbers from the diagrams, and their recorded tracking error is compared
with the diagram's to show that both integrate the same closed loop.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import tracemalloc

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

import fwdstep  # noqa: E402
import hand_loops  # noqa: E402
from fwdstep.structure.compiler import compile_spec  # noqa: E402
from fwdstep.structure.spec import load_spec  # noqa: E402
from fwdstep.sweeps.sweep import run_sweep  # noqa: E402

SLOTINE = os.path.join(ROOT, "diagrams", "slotine_li.yaml")
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w, time.process_time() - c, out


def interleaved(fns: dict, repeats: int) -> dict:
    """{name: fn} -> {name: {"wall": [...], "cpu": [...], "out": last result}}."""
    res = {k: {"wall": [], "cpu": []} for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            w, c, out = timed(fn)
            res[name]["wall"].append(w)
            res[name]["cpu"].append(c)
            res[name]["out"] = out
    for r in res.values():
        r["wall_median"] = statistics.median(r["wall"])
        r["cpu_median"] = statistics.median(r["cpu"])
    return res


def line(label, r, ref=None):
    text = f"  {label:42s} wall {r['wall_median']:8.3f} s   cpu {r['cpu_median']:8.3f} s"
    if ref is not None:
        text += (f"   ratio wall {r['wall_median'] / ref['wall_median']:6.3f}"
                 f"  cpu {r['cpu_median'] / ref['cpu_median']:6.3f}")
    print(text, flush=True)


def _entry(spec, name):
    return next(e for e in spec.blocks if e.name == name).params


def slotine_hand(spec):
    p, sim = spec.parameters, spec.simulation
    arm = _entry(spec, "arm")
    return lambda: hand_loops.slotine_li(sim.t_final, sim.step, sim.log_every, p["Lambda"],
                                         p["K"], p["Gamma"], p["theta0"], p["A"], p["w"],
                                         p["c"], arm.get("q0", 0.0))


def theorem1_hand(spec):
    p, sim = spec.parameters, spec.simulation
    arm, ref = _entry(spec, "arm"), _entry(spec, "ref")
    z0 = ref.get("z0")
    return lambda: hand_loops.theorem1(sim.t_final, sim.step, sim.log_every, int(p["ell"]),
                                       p["alpha"], p["K"], p["Gamma"], p["theta0"],
                                       p["qd_coefficients"], arm.get("q0", 0.0),
                                       0.0 if z0 is None else z0)


def agreement(result, hand_log) -> float:
    e = result["e.y"]
    return float(np.max(np.abs(e - hand_log[:len(e)])))


def bench_single(label, path, overrides, hand_factory, repeats, t_final, report):
    spec = load_spec(path, overrides)
    if t_final:
        spec.simulation.t_final = t_final
    d = compile_spec(spec)
    hand = hand_factory(spec)
    res = interleaved({"hand": hand, "fwdstep": lambda: fwdstep.simulate(d)}, repeats)
    diff = agreement(res["fwdstep"]["out"], res["hand"]["out"][1])
    sim = spec.simulation
    print(f"({label}) {os.path.relpath(path, ROOT)} {overrides or ''}: {sim.t_final:g} s, step "
          f"{sim.step:g}, {sim.solver}, log_every {sim.log_every}, {d.n_states} states; "
          f"max |e_fwdstep - e_hand| = {diff:.2e}")
    line("hand-written NumPy RK4 loop", res["hand"])
    line("fwdstep.simulate", res["fwdstep"], res["hand"])
    evals = sim.n_steps * 4
    print(f"  per evaluation of the closed loop: hand {1e6 * res['hand']['cpu_median'] / evals:.1f}"
          f" us, fwdstep {1e6 * res['fwdstep']['cpu_median'] / evals:.1f} us (cpu)")
    report[label] = {"hand": _strip(res["hand"]), "fwdstep": _strip(res["fwdstep"]),
                     "ratio_wall": res["fwdstep"]["wall_median"] / res["hand"]["wall_median"],
                     "ratio_cpu": res["fwdstep"]["cpu_median"] / res["hand"]["cpu_median"],
                     "agreement": diff}
    if compiled_available():
        bench_compiled(label, path, overrides, d, res["hand"], repeats, t_final, report)


def compiled_available() -> bool:
    import importlib.util
    return importlib.util.find_spec("numba") is not None


def bench_compiled(label, path, overrides, d, hand, repeats, t_final, report):
    """The numba backend: in this process once compiled, and in fresh processes that find
    the compiled code in the disk cache (import fwdstep and numba, load, run)."""
    fwdstep.simulate(d, backend="compiled")           # compile (or load) once
    res = interleaved({"compiled": lambda: fwdstep.simulate(d, backend="compiled")}, repeats)
    diff = float(np.max(np.abs(res["compiled"]["out"]["e.y"] - fwdstep.simulate(d)["e.y"])))
    line("compiled backend, in process", res["compiled"], hand)
    code = ("import sys, time; w = time.perf_counter(); import fwdstep; "
            "from fwdstep.structure.spec import load_spec; from fwdstep.structure.compiler import compile_spec; import json; "
            "spec = load_spec(sys.argv[1], json.loads(sys.argv[2])); "
            "spec.simulation.t_final = float(sys.argv[3]) or spec.simulation.t_final; "
            "d = compile_spec(spec); "
            "r = fwdstep.simulate(d, backend='compiled'); "
            "print(time.perf_counter() - w, r.wall_time)")
    walls, inner = [], []
    for _ in range(repeats):
        w = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", code, path, json.dumps(overrides),
                              str(t_final or 0)], capture_output=True, text=True, cwd=ROOT)
        walls.append(time.perf_counter() - w)
        inner.append(float(out.stdout.split()[1]))
    fresh = statistics.median(walls)
    print(f"  {'compiled backend, fresh process (cached)':42s} wall {fresh:8.3f} s "
          f"(simulate() alone {statistics.median(inner):.3f} s: numba import + cache load + "
          f"run)   ratio wall {fresh / hand['wall_median']:6.3f}; "
          f"max |e_compiled - e_numpy| = {diff:.1e}")
    report[label]["compiled"] = {
        "in_process": _strip(res["compiled"]),
        "ratio_in_process_wall": res["compiled"]["wall_median"] / hand["wall_median"],
        "ratio_in_process_cpu": res["compiled"]["cpu_median"] / hand["cpu_median"],
        "fresh_process_wall": fresh, "ratio_fresh_process_wall": fresh / hand["wall_median"],
        "agreement_with_numpy": diff}


def bench_sweep(repeats, samples, t_final, full, report):
    overrides = {}

    def single():
        spec = load_spec(SLOTINE, overrides)
        if t_final:
            spec.simulation.t_final = t_final
        return fwdstep.simulate(compile_spec(spec))

    def sweep(sequential=False):
        if t_final:                     # a shortened copy of the diagram for --quick
            import tempfile
            text = open(SLOTINE).read().replace("t_final: 10,", f"t_final: {t_final:g},")
            fd, path = tempfile.mkstemp(suffix=".yaml", dir=os.path.dirname(SLOTINE))
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            try:
                return run_sweep(path, random={"Lambda": (2.0, 10.0)}, samples=samples,
                                 seed=1, sequential=sequential)
            finally:
                os.unlink(path)
        return run_sweep(SLOTINE, random={"Lambda": (2.0, 10.0)}, samples=samples, seed=1,
                         sequential=sequential)

    res = interleaved({"single": single, "sweep": sweep}, repeats)
    counts = res["sweep"]["out"].counts()
    print(f"(c) {samples}-variant sweep of slotine_li.yaml (Lambda in [2, 10]) in "
          f"{len(res['sweep']['out'].batches)} batch(es), {counts}")
    line("one run (load, compile, simulate)", res["single"])
    line(f"sweep of {samples} variants (batched)", res["sweep"], res["single"])
    seq_wall = samples * res["single"]["wall_median"]
    seq_cpu = samples * res["single"]["cpu_median"]
    entry = {"single": _strip(res["single"]), "sweep": _strip(res["sweep"]),
             "ratio_to_single_wall": res["sweep"]["wall_median"] / res["single"]["wall_median"],
             "ratio_to_single_cpu": res["sweep"]["cpu_median"] / res["single"]["cpu_median"]}
    if full:
        w, c, _ = timed(lambda: sweep(sequential=True))
        seq_wall, seq_cpu = w, c
        print(f"  {samples} sequential runs (measured once)       wall {w:8.3f} s   cpu {c:8.3f} s")
    else:
        print(f"  {samples} sequential runs (= {samples} x one run)   wall {seq_wall:8.3f} s   "
              f"cpu {seq_cpu:8.3f} s")
    print(f"  throughput per variant, sweep vs sequential: "
          f"{seq_wall / res['sweep']['wall_median']:.1f}x (wall), "
          f"{seq_cpu / res['sweep']['cpu_median']:.1f}x (cpu)")
    entry["speedup_vs_sequential_wall"] = seq_wall / res["sweep"]["wall_median"]
    entry["speedup_vs_sequential_cpu"] = seq_cpu / res["sweep"]["cpu_median"]
    report["c"] = entry


def bench_ell(repeats, t_final, report):
    """theorem1.yaml for ell = 1..10 with a constant q_d (a1 = a2 = 0: the diagram's
    polynomial q_d of degree ell - 1 grows like 2^(ell-1) over 10 s and would make the arm
    spin ever faster), against the hand loop of the same closed loop."""
    print("(d) theorem1.yaml with q_d constant (a1 = a2 = 0), run time against ell")
    rows = {}
    first = None
    for ell in range(1, 11):
        spec = load_spec(THEOREM1, {"ell": ell, "a1": 0, "a2": 0})
        if t_final:
            spec.simulation.t_final = t_final
        d = compile_spec(spec)
        res = interleaved({"hand": theorem1_hand(spec),
                           "fwdstep": lambda d=d: fwdstep.simulate(d)}, repeats)
        first = first or res["fwdstep"]
        diff = agreement(res["fwdstep"]["out"], res["hand"]["out"][1])
        r = res["fwdstep"]
        print(f"  ell = {ell:2d} ({d.n_states:2d} states): fwdstep wall {r['wall_median']:6.3f} s "
              f"cpu {r['cpu_median']:6.3f} s = {r['cpu_median'] / first['cpu_median']:5.2f} x "
              f"ell 1; vs hand loop {r['cpu_median'] / res['hand']['cpu_median']:5.2f} (cpu) "
              f"{r['wall_median'] / res['hand']['wall_median']:5.2f} (wall); "
              f"max |e diff| {diff:.1e}", flush=True)
        rows[ell] = {"fwdstep": _strip(r), "hand": _strip(res["hand"]), "agreement": diff}
    report["d"] = rows


NLINK = """
parameters: {{ell: 2, alpha: 4, K: 30*eye({n}), Gamma: 2}}
blocks:
  qd:    {{type: Sine, amplitude: {amp}, frequency: {freq}, derivatives: 2}}
  arm:   {{type: NLinkArm, lengths: {lengths}}}
  ref:   {{type: ReferenceDynamics, variant: eq16, ell: ell, n: {n}, alpha: alpha}}
  e:     {{type: Sum, signs: "+-", shape: [{n}]}}
  s:     {{type: Sum, signs: "+-", shape: [{n}]}}
  Y:     {{type: NLinkRegressor, lengths: {lengths}}}
  Yth:   {{type: Product, a_shape: [{n}, {p}], b_shape: [{p}]}}
  Ks:    {{type: Gain, gain: K}}
  tau:   {{type: Sum, signs: "+-", shape: [{n}]}}
  adapt: {{type: AdaptationLaw, regressor_shape: [{n}, {p}], gamma: Gamma}}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - qd.y_d1 -> ref.qdot_d
  - qd.y_d2 -> ref.qddot_d
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Yth.y -> tau.u1
  - Ks.y -> tau.u2
  - tau.y -> arm.tau
simulation: {{t_final: {t_final}, step: 0.001, solver: rk4, log_every: 10}}
log: [e.y]
"""


def bench_joints(repeats, t_final, report):
    """Run time against the number of joints: eq. (16) reference dynamics (ell = 2) and the
    adaptive law (4)-(5) on the planar n-link arm (NLinkArm, NLinkRegressor)."""
    import tempfile
    t_final = t_final or 2.0
    print(f"(d') n-link arm, eq. (16) + (4)-(5), {t_final:g} s at step 1e-3, against n")
    fns, states = {}, {}
    with tempfile.TemporaryDirectory() as folder:
        for n in (2, 3, 4, 6, 8):
            text = NLINK.format(n=n, p=4 * n, amp=[0.3] * n, freq=[1.0 + 0.1 * i for i in range(n)],
                                lengths=[1.0] * n, t_final=t_final)
            path = os.path.join(folder, f"nlink{n}.yaml")
            with open(path, "w") as fh:
                fh.write(text)
            d = fwdstep.load_diagram(path)
            states[n] = d.n_states
            fns[n] = (lambda d=d: fwdstep.simulate(d))
        res = interleaved(fns, repeats)
    for n, r in res.items():
        line(f"n = {n} joints ({states[n]} states)", r, res[2])
    report["joints"] = {n: _strip(r) for n, r in res.items()}


def bench_memory(t_final, report):
    spec = load_spec(SLOTINE)
    spec.simulation.t_final = t_final or 10.0
    spec.log = None                      # every output of every block
    spec.plots = {}
    out = {}
    for every in (1, 10):
        spec.simulation.log_every = every
        d = compile_spec(spec)
        tracemalloc.start()
        r = fwdstep.simulate(d)
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        size = sum(r[n].nbytes for n in r.names) / 1e6
        out[every] = {"peak_mb": peak, "log_mb": size, "signals": len(r.names)}
    print(f"(memory) slotine_li.yaml, {spec.simulation.t_final:g} s at step 1e-3, all "
          f"{out[1]['signals']} signals logged: peak {out[1]['peak_mb']:.1f} MB above the "
          f"baseline (logs {out[1]['log_mb']:.1f} MB) with log_every 1, "
          f"{out[10]['peak_mb']:.1f} MB with log_every 10")
    report["memory"] = out


def bench_startup(repeats, report):
    code = ("import sys, cli; code = cli.main(['validate', sys.argv[1]]); "
            "print('heavy imports:', [m for m in ('matplotlib', 'numba', 'scipy') "
            "if m in sys.modules])")
    walls = []
    for _ in range(repeats):
        w = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", code, SLOTINE], capture_output=True,
                              text=True, cwd=ROOT)
        walls.append(time.perf_counter() - w)
    print(f"(start-up) fwdstep validate slotine_li.yaml in a new process: median "
          f"{statistics.median(walls):.3f} s wall; {proc.stdout.strip().splitlines()[-1]}")
    report["startup_s"] = statistics.median(walls)


def _strip(r):
    return {k: v for k, v in r.items() if k != "out"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 s runs, 3 repeats, 64 variants")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--only", default="a,b,c,d,memory,startup")
    ap.add_argument("--full", action="store_true", help="(c): really run the variants one by one")
    ap.add_argument("--json", default=None, help="also write the numbers to this file")
    args = ap.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 5)
    t_final = 2.0 if args.quick else None
    only = set(args.only.split(","))
    report: dict = {"python": sys.version.split()[0], "numpy": np.__version__,
                    "cpus": os.cpu_count(), "repeats": repeats}
    print(f"fwdstep benchmarks: medians of {repeats}, numpy {np.__version__}, "
          f"{os.cpu_count()} cpus, load average {os.getloadavg()[0]:.1f}")
    if "a" in only:
        bench_single("a", SLOTINE, {}, slotine_hand, repeats, t_final, report)
    if "b" in only:
        bench_single("b", THEOREM1, {"ell": 3}, theorem1_hand, repeats, t_final, report)
    if "c" in only:
        bench_sweep(repeats, 64 if args.quick else 256, t_final, args.full, report)
    if "d" in only:
        bench_ell(repeats, t_final, report)
        bench_joints(repeats, t_final, report)
    if "memory" in only:
        bench_memory(t_final, report)
    if "startup" in only:
        bench_startup(repeats, report)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
