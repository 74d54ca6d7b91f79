"""Panda Theorem 1 (diagrams/robots/panda_theorem1.yaml: ell = 2, 10 s, step 1e-3, rk4) through
fwdstep against a hand-written RK4 loop that calls pinocchio directly for the same closed loop.

    python benchmarks/robots_benchmark.py               # 3 interleaved repeats of each
    python benchmarks/robots_benchmark.py --repeats 5 --t-final 2
    python benchmarks/robots_benchmark.py --compiled --diagram diagrams/robots/panda_theorem3.yaml

The hand loop integrates, with the diagram's numbers,

    zdot = -alpha_2 qdot - alpha_1 (q - q_d) - alpha_0 I,   I' = q - q_d        (eq. (2), ell = 2)
    s = qdot - z,  Y = R_g(q, (qdot + z)/2, zdot) - R_0(q, (qdot - z)/2, 0)[:, base columns]
    tau = Y theta_hat - K s,  qddot = aba(q, qdot, tau),  theta_hat' = -Gamma Y^T s

in one flat state vector, and its final tracking error is compared with the diagram's to show
that both integrate the same closed loop.  Both sides record every 10th step.  Repeats are
interleaved (A, B, A, B, ...) so that a busy machine slows both alike; the ratio is of medians
of CPU times (``time.process_time``) measured in this one run; the load average is printed.
Targets: issue 12, fwdstep <= 2x the hand loop; issue 25, <= 1.0 (Slotine-Li).

``--compiled`` also times ``--backend compiled`` (numba; URDFArm and URDFRegressor's kernels,
blocks/rigid_body.py, traced into the loop's straight-line scalar code), interleaved with the
others, after one untimed short run that compiles (or loads) the structure (its CPU time is
printed: the first compile of a never-seen robot when the numba cache is cold), and prints its
ratio to the NumPy path.  ``--diagram`` picks another robot diagram; the hand loops exist for
Theorem 1 (above) and for Slotine-Li (diagrams/robots/{panda,ur5}_slotine_li.yaml:
``tau = Y(q, qdot, z, zdot) theta_hat - K s``, ``theta_hat' = -Gamma Y^T s``, q_d a Sine,
with the plant's URDF damping), skipped for any other.

    python benchmarks/robots_benchmark.py --compiled --diagram diagrams/robots/panda_slotine_li.yaml
    python benchmarks/robots_benchmark.py --kernels      # per batch: kernels, pinocchio, native

The NumPy path runs the robot blocks as ``implementation: auto`` makes them run: their kernels
compiled to native code (fwdstep/compiled/native_block.py; "fwdstep simulate"), and, for
comparison, with ``implementation: pinocchio`` on every URDF block ("fwdstep, pinocchio"),
interleaved with the others; the native kernels' trace and compile happen in an untimed
first run.

``--kernels`` times, per batch size, one evaluation of the Panda's aba and Slotine-Li
regressor by fwdstep's kernels as NumPy arrays (every variant in one pass), by pinocchio one
variant at a time and by the native kernels (every variant in one call; blocks/urdf.py
``_native_wanted``, KERNELS_FROM_BATCH).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

DIAGRAM = os.path.join(ROOT, "diagrams", "robots", "panda_theorem1.yaml")
SLOTINE_LI = ("panda_slotine_li.yaml", "ur5_slotine_li.yaml")


def _rk4(f, x, t_final: float, step: float, log_every: int):
    """The hand loops' classical RK4, written out as a user would: (final x, final t, the
    state every ``log_every`` steps)."""
    steps = int(round(t_final / step))
    log = np.empty((steps // log_every + 1, x.size))
    log[0] = x
    t, h = 0.0, step
    for k in range(1, steps + 1):
        k1 = f(t, x)
        k2 = f(t + 0.5 * h, x + 0.5 * h * k1)
        k3 = f(t + 0.5 * h, x + 0.5 * h * k2)
        k4 = f(t + h, x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        t = k * h
        if k % log_every == 0:
            log[k // log_every] = x
    return x, t, log


def hand_loop(d, t_final: float, step: float, log_every: int):
    """The closed loop of panda_theorem1.yaml, integrated by hand with pinocchio calls."""
    import pinocchio as pin

    blocks = {s.block.name: s.block for s in d.schedule}
    Yb, adapt, ref, qd = blocks["Y"], blocks["adapt"], blocks["ref"], blocks["qd"]
    damping = blocks["arm"].p.viscous[0]          # the plant's URDF damping (URDFArm)
    model, data, model0, data0 = Yb.model, Yb._data, Yb.model0, Yb._data0
    cols = Yb._columns
    n, p = model.nv, Yb.outputs["Y"].shape[1]
    params = d.spec.parameters
    alpha, T = float(params["alpha"]), float(params["T"])
    a, b = np.asarray(params["a"], float), np.asarray(params["b"], float)
    K = np.asarray(params["K"], float)
    gamma = float(params["Gamma"])
    a0, a1, a2 = alpha ** 3, 3 * alpha ** 2, 3 * alpha              # (w + alpha)^3
    x = np.concatenate([np.asarray(params["q0"], float), np.zeros(n), np.zeros(n),
                        np.zeros(n), np.full(p, float(params["theta0"]))])
    iq, iv, iz, ii, ith = (slice(0, n), slice(n, 2 * n), slice(2 * n, 3 * n),
                           slice(3 * n, 4 * n), slice(4 * n, 4 * n + p))
    regressor, aba = pin.computeJointTorqueRegressor, pin.aba
    zeros = np.zeros(n)
    del ref, qd, adapt

    def f(t, x):
        q, v, z, integral, theta = x[iq], x[iv], x[iz], x[ii], x[ith]
        e = q - (b + a * (t / T))                                   # q - q_d (ell = 2: a ramp)
        zdot = -a2 * v - a1 * e - a0 * integral
        s = v - z
        Y = (regressor(model, data, q, 0.5 * (v + z), zdot)
             - regressor(model0, data0, q, 0.5 * (v - z), zeros))[:, cols]
        tau = Y @ theta - K @ s
        dx = np.empty_like(x)
        dx[iq] = v
        dx[iv] = aba(model, data, q, v, tau - damping * v)
        dx[iz] = zdot
        dx[ii] = e
        dx[ith] = -gamma * (Y.T @ s)
        return dx

    x, t, log = _rk4(f, x, t_final, step, log_every)
    e_final = x[iq] - (b + a * (t / T))
    return log, e_final


def slotine_li_by_hand(d, lam: float, gamma: float, model=None, data=None):
    """The right-hand side f(t, x) of {panda,ur5}_slotine_li.yaml's closed loop written by
    hand with pinocchio (``aba`` on ``model``, default the arm's own; two
    ``computeJointTorqueRegressor`` calls on the regressor block's models), its initial
    state and its slices (q, qdot, theta_hat); q_d = q0 + amp sin(w t)."""
    import pinocchio as pin

    blocks = {s.block.name: s.block for s in d.schedule}
    Yb, arm = blocks["Y"], blocks["arm"]
    model_r, data_r, model0, data0 = Yb.model, Yb._data, Yb.model0, Yb._data0
    if model is None:
        model, data = model_r, data_r
    cols = Yb._columns
    n, p = model.nv, Yb.outputs["Y"].shape[1]
    params = d.spec.parameters
    K = np.asarray(fwdstep_value(d, "Ks", "gain"), float)
    K = K if K.ndim == 2 else np.diag(np.broadcast_to(K, (n,)))
    q0 = np.asarray(params["q0"], float)
    amp = np.asarray(params["qd_amplitude"], float)
    w = float(params["qd_frequency"])
    damping = arm.p.viscous[0]
    x = np.concatenate([q0, np.zeros(n), np.full(p, float(params["theta0"]))])
    iq, iv, ith = slice(0, n), slice(n, 2 * n), slice(2 * n, 2 * n + p)
    regressor, aba = pin.computeJointTorqueRegressor, pin.aba
    zeros = np.zeros(n)

    def f(t, x):
        q, v, theta = x[iq], x[iv], x[ith]
        sn, cs = np.sin(w * t), np.cos(w * t)
        e = q - (q0 + amp * sn)
        z = amp * (w * cs) - lam * e
        zdot = -amp * (w * w * sn) - lam * (v - amp * (w * cs))
        s = v - z
        Y = (regressor(model_r, data_r, q, 0.5 * (v + z), zdot)
             - regressor(model0, data0, q, 0.5 * (v - z), zeros))[:, cols]
        tau = Y @ theta - K @ s
        dx = np.empty_like(x)
        dx[iq] = v
        dx[iv] = aba(model, data, q, v, tau - damping * v)
        dx[ith] = -gamma * (Y.T @ s)
        return dx

    def q_d(t):
        return q0 + amp * np.sin(w * np.asarray(t))[..., None]

    return f, x, iq, q_d


def hand_loop_slotine_li(d, t_final: float, step: float, log_every: int):
    """The closed loop of {panda,ur5}_slotine_li.yaml, integrated by hand with pinocchio."""
    params = d.spec.parameters
    f, x, iq, q_d = slotine_li_by_hand(d, float(params["Lambda"]), float(params["Gamma"]))
    x, t, log = _rk4(f, x, t_final, step, log_every)
    e_final = x[iq] - q_d(t)
    return log, e_final


def fwdstep_value(d, block: str, key: str):
    """A block's parameter as the diagram gave it (evaluated)."""
    blk = next(s.block for s in d.schedule if s.block.name == block)
    return blk.values[key]


def kernels_against_pinocchio(robot: str = "panda", batches=(1, 16, 64, 256, 1024, 4096)):
    """Seconds per evaluation of aba and of the Slotine-Li regressor, by fwdstep's kernels
    (NumPy, every variant at once) and by pinocchio (one variant at a time), per batch size."""
    from fwdstep.blocks.urdf import URDFArm, URDFRegressor
    rng = np.random.default_rng(0)
    from fwdstep.compiled.native_block import native_kernel
    rows = []
    for B in batches:
        timings = {}
        for impl in ("kernels", "pinocchio", "native"):
            kind = "kernels" if impl == "native" else impl
            arm = URDFArm("arm", robot=robot, implementation=kind)
            Y = URDFRegressor("Y", robot=robot, parameters="base", implementation=kind)
            n = arm._n
            x = rng.standard_normal((B, 2 * n))
            tau = rng.standard_normal((B, n))
            u = tuple(rng.standard_normal((4, B, n)))
            aba, regressor = arm.derivative, Y.output
            if impl == "native":
                aba, regressor = native_kernel(arm, "derivative", B), native_kernel(Y, "output", B)
            for what, call in (("aba", lambda: aba(0.0, x, (tau, np.zeros((1, n))))),
                               ("Y", lambda: regressor(0.0, None, u))):
                call()
                reps = max(3, int(2000 / B))
                t0 = time.perf_counter()
                for _ in range(reps):
                    call()
                timings[(what, impl)] = (time.perf_counter() - t0) / reps
        rows.append((B, timings))
        us = {key: value * 1e6 / B for key, value in timings.items()}
        print(f"B = {B:5d} (us/variant): aba kernels {us[('aba', 'kernels')]:8.2f}, pinocchio "
              f"{us[('aba', 'pinocchio')]:6.2f}, native {us[('aba', 'native')]:5.2f};  "
              f"Y kernels {us[('Y', 'kernels')]:8.2f}, pinocchio {us[('Y', 'pinocchio')]:6.2f}, "
              f"native {us[('Y', 'native')]:5.2f}", flush=True)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats of each")
    parser.add_argument("--t-final", type=float, default=10.0, help="simulated time (s)")
    parser.add_argument("--diagram", default=DIAGRAM, help="robot diagram (default: "
                        "panda_theorem1.yaml; the hand loop runs for that one only)")
    parser.add_argument("--compiled", action="store_true",
                        help="also time --backend compiled (the robot kernels traced)")
    parser.add_argument("--kernels", action="store_true",
                        help="only time the NumPy path's kernels against pinocchio per batch")
    args = parser.parse_args(argv)
    if args.kernels:
        kernels_against_pinocchio()
        return 0

    import fwdstep
    d = fwdstep.load_diagram(args.diagram, overrides={"t_final": args.t_final})
    step, log_every = d.spec.simulation.step, d.spec.simulation.log_every
    by_pinocchio = {f"{s.block.name}.implementation": "pinocchio" for s in d.schedule
                    if s.block.type_name.startswith("URDF")}
    d_pin = fwdstep.load_diagram(args.diagram, overrides={"t_final": args.t_final,
                                                          **by_pinocchio})
    c0 = time.process_time()
    fwdstep.simulate(fwdstep.load_diagram(args.diagram, overrides={"t_final": 10 * step}))
    print(f"native robot kernels traced and compiled (and a 10-step run): "
          f"{time.process_time() - c0:.2f} s CPU (not in the ratios)")
    slotine_li = os.path.basename(args.diagram) in SLOTINE_LI
    hand = os.path.samefile(args.diagram, DIAGRAM) or slotine_li
    loop = hand_loop_slotine_li if slotine_li else hand_loop
    print(f"{os.path.basename(args.diagram)}, {args.t_final:g} s at step {step:g}, "
          f"{d.spec.simulation.solver}, {d.n_states} states; {args.repeats} interleaved repeats "
          f"(CPU time); load average {os.getloadavg()[0]:.2f}")
    wall_f, wall_p, wall_h, wall_c = [], [], [], []
    if args.compiled:
        t0, c0 = time.perf_counter(), time.process_time()
        fwdstep.simulate(fwdstep.load_diagram(args.diagram, overrides={"t_final": 10 * step}),
                         backend="compiled")
        print(f"compile (or load from the cache) and a 10-step run: "
              f"{time.perf_counter() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU "
              f"(not in the ratios)")
    clock = time.process_time          # CPU time: a loaded machine slows both alike
    for _ in range(args.repeats):
        t0 = clock()
        result = fwdstep.simulate(d)
        wall_f.append(clock() - t0)
        t0 = clock()
        result_pin = fwdstep.simulate(d_pin)
        wall_p.append(clock() - t0)
        if args.compiled:
            t0 = clock()
            compiled = fwdstep.simulate(d, backend="compiled")
            wall_c.append(clock() - t0)
        if hand:
            t0 = clock()
            _, e_hand = loop(d, args.t_final, step, log_every)
            wall_h.append(clock() - t0)
    med_f, med_p = statistics.median(wall_f), statistics.median(wall_p)
    worst_pin = max(float(np.nanmax(np.abs(result_pin[n] - result[n]))
                          / max(1.0, float(np.nanmax(np.abs(result_pin[n])))))
                    for n in result.names)
    print(f"fwdstep simulate : median {med_f:.2f} s  ({', '.join(f'{w:.2f}' for w in wall_f)})")
    print(f"fwdstep, pinocchio: median {med_p:.2f} s  "
          f"({', '.join(f'{w:.2f}' for w in wall_p)}); native / pinocchio = "
          f"{med_f / med_p:.2f}; largest difference of a logged signal {worst_pin:.1e} of "
          f"its scale")
    if args.compiled:
        med_c = statistics.median(wall_c)
        worst = max(float(np.nanmax(np.abs(compiled[n] - result[n]))
                          / max(1.0, float(np.nanmax(np.abs(result[n]))))) for n in result.names)
        print(f"fwdstep compiled : median {med_c:.2f} s  "
              f"({', '.join(f'{w:.2f}' for w in wall_c)})")
        print(f"ratio compiled / NumPy path = {med_c / med_f:.2f}; largest difference of a "
              f"logged signal {worst:.1e} of its scale")
    if not hand:
        return 0
    e_diagram = result["e.y"][-1]
    agreement = float(np.abs(e_diagram - e_hand).max())
    med_h = statistics.median(wall_h)
    print(f"hand pinocchio   : median {med_h:.2f} s  ({', '.join(f'{w:.2f}' for w in wall_h)})")
    print(f"ratio fwdstep / hand = {med_f / med_h:.2f}  (issue 25 target <= 1.0; with "
          f"implementation: pinocchio {med_p / med_h:.2f}); load average "
          f"{os.getloadavg()[0]:.2f}")
    if args.compiled:
        print(f"ratio compiled / hand = {statistics.median(wall_c) / med_h:.3f}  "
              f"(issue 25 target <= 0.25)")
    print(f"final |Delta q| (largest joint): diagram {np.abs(e_diagram).max():.3e}, hand "
          f"{np.abs(e_hand).max():.3e}; they differ by {agreement:.1e} (same closed loop)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
