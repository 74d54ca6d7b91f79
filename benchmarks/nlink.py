"""n-link arm speed against the number of joints (issue 10): the NumPy path and the compiled
backend against a hand-written NumPy RK4 loop of the same closed loop, in one run.

    python benchmarks/nlink.py                  # n = 2, 3, 4, 6, 8, 12, 16; medians of 5
    python benchmarks/nlink.py --n 2-16 --repeats 7 --t-final 2
    python benchmarks/nlink.py --quick          # n = 2, 16; 3 repeats of 0.5 s

The closed loop: the planar n-link arm (``NLinkArm``, vertical plane, gravity 9.81) under
PD feedback tau = -Kp (q - q_d) - Kd qdot (Kp = 100 H(q0), Kd = 20 H(q0)) with constant
q_d, step 1e-3,
rk4, q logged every 10 steps.  The hand loop integrates the same equations written for one
run on 1-d arrays (complex joint positions, cumulative sums, ``np.linalg.solve``), the way
one writes it without a framework; the largest difference of the logged q is printed to show
that both sides integrate the same dynamics.  Repeats are interleaved (hand, NumPy path,
compiled, hand, ...) so that a busy machine slows every side alike; ratios are of the
medians of CPU time.  The compiled runs are warm (the first run, which compiles, is not
timed); the compile of the first n is printed separately, and later n reuse it when the
structure is the same (n is a run-time size).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import fwdstep  # noqa: E402

DIAGRAM = """
parameters: {{Kp: {kp}, Kd: {kd}}}   # gain matrices
blocks:
  qd:   {{type: Constant, value: {qd}}}
  arm:  {{type: NLinkArm, lengths: {lengths}, masses: {masses}, gravity: 9.81, q0: {q0}}}
  e:    {{type: Sum, signs: "+-", shape: [{n}]}}
  P:    {{type: Gain, gain: Kp}}
  D:    {{type: Gain, gain: Kd}}
  tau:  {{type: Sum, signs: "--", shape: [{n}]}}
connections:
  - arm.q -> e.u1
  - qd.y -> e.u2
  - e.y -> P.u
  - arm.qdot -> D.u
  - P.y -> tau.u1
  - D.y -> tau.u2
  - tau.y -> arm.tau
simulation: {{t_final: {t_final}, step: 0.001, solver: rk4, log_every: 10}}
log: [arm.q]
"""


def problem(n):
    """The numbers of the n-joint closed loop (shared by the diagram and the hand loop)."""
    i = np.arange(n)
    return {"n": n, "lengths": (1.0 - 0.4 * i / max(n - 1, 1)) / n * 2.0,
            "masses": 2.0 - 1.5 * i / max(n - 1, 1), "q0": 0.3 * np.cos(i),
            "qd": 0.2 * np.sin(i + 1.0)}


def with_gains(pr):
    """Gain matrices from the inertia matrix at q0 (Kp = 100 H, Kd = 20 H: natural frequency
    10 rad/s in every direction near q0, so the light outer links stay inside RK4's
    stability region at step 1e-3)."""
    H = hand_dynamics(pr)(pr["q0"], np.zeros(pr["n"]))[0]
    pr["kp"] = 100.0 * H
    pr["kd"] = 20.0 * H
    return pr


# ---------------------------------------------------------------- the hand-written loop
def hand_dynamics(pr, gravity=9.81):
    """(H, C qdot + g) of the planar arm as a function of (q, qdot), one run, 1-d arrays."""
    lengths, masses = pr["lengths"], pr["masses"]
    lc = lengths / 2.0
    inertia = masses * lengths ** 2 / 12.0
    J = inertia + masses * lc ** 2                      # inertia of link i about joint i

    def suffix(a):
        return np.cumsum(a[::-1])[::-1]

    def dynamics(q, qdot):
        E = np.exp(1j * np.cumsum(q))                   # link directions
        phid = np.cumsum(qdot)
        O = np.cumsum(lengths * E) - lengths * E        # joint origins
        w = masses * lc * E                             # first moments about the joints
        # H_ab (a <= b) = sum_{i>=b} [m_i |O_i - O_a|^2 ... ] written with outer-link sums
        SM, SC = suffix(masses), suffix(masses * O + w)
        P = suffix(masses * np.abs(O) ** 2 + 2.0 * np.real(np.conj(O) * w) + J)
        U = (P - np.real(np.conj(O) * SC))[None, :] - np.real(np.conj(O)[:, None] * SC[None, :]) \
            + SM[None, :] * np.real(np.conj(O)[:, None] * O[None, :])
        H = np.triu(U) + np.triu(U, 1).T
        # C qdot + g: Newton-Euler with zero joint accelerations
        lv = lengths * phid ** 2 * E
        A = lv - np.cumsum(lv)
        F = masses * A - phid ** 2 * w + 1j * gravity * masses
        T = np.imag(np.conj(O) * F) + np.imag(np.conj(w) * A) + gravity * np.real(w)
        bias = suffix(T) - np.imag(np.conj(O) * suffix(F))
        return H, bias
    return dynamics


def hand_loop(pr, t_final, h=1e-3, every=10):
    n, kp, kd, qd = pr["n"], pr["kp"], pr["kd"], pr["qd"]
    dynamics = hand_dynamics(pr)

    def f(x):
        q, qdot = x[:n], x[n:]
        H, bias = dynamics(q, qdot)
        tau = -kp @ (q - qd) - kd @ qdot
        return np.concatenate([qdot, np.linalg.solve(H, tau - bias)])

    steps = int(round(t_final / h))
    x = np.concatenate([pr["q0"], np.zeros(n)])
    log = [x[:n].copy()]
    for i in range(steps):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if (i + 1) % every == 0:
            log.append(x[:n].copy())
    return np.array(log)


# ---------------------------------------------------------------- timing
def timed(fn):
    c = time.process_time()
    out = fn()
    return time.process_time() - c, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="2,3,4,6,8,12,16",
                    help="joint counts: a list 2,4,8 or a range 2-16")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--t-final", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-compiled", action="store_true")
    a = ap.parse_args(argv)
    if a.quick:
        a.n, a.repeats, a.t_final = "2,16", 3, 0.5
    if "-" in a.n:
        lo, hi = (int(v) for v in a.n.split("-"))
        ns = list(range(lo, hi + 1))
    else:
        ns = [int(v) for v in a.n.split(",")]
    compiled = not a.no_compiled
    if compiled:
        try:
            import numba  # noqa: F401
        except ImportError:
            print("numba not installed: NumPy path only (install fwdstep[fast])")
            compiled = False
    print(f"n-link arm, PD + gravity 9.81, {a.t_final:g} s at step 1e-3 (rk4), CPU-time "
          f"medians of {a.repeats}, ratios to the hand NumPy loop of the same run")
    print(f"{'n':>3} {'states':>6} {'hand s':>8} {'numpy s':>8} {'numpy/hand':>10} "
          f"{'compiled/hand':>13} {'max|dq| numpy':>13} {'max|dq| compiled':>16}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for n in ns:
            pr = with_gains(problem(n))
            fmt = lambda v: "[" + ", ".join(f"{float(s):.17g}" for s in v) + "]"  # noqa: E731
            mat = lambda v: "[" + ", ".join(fmt(row) for row in v) + "]"  # noqa: E731
            text = DIAGRAM.format(n=n, kp=mat(pr["kp"]), kd=mat(pr["kd"]), qd=fmt(pr["qd"]),
                                  lengths=fmt(pr["lengths"]), masses=fmt(pr["masses"]),
                                  q0=fmt(pr["q0"]), t_final=a.t_final)
            path = os.path.join(folder, f"nlink{n}.yaml")
            with open(path, "w") as fh:
                fh.write(text)
            d = fwdstep.load_diagram(path)
            sides = {"hand": lambda: hand_loop(pr, a.t_final),
                     "numpy": lambda: fwdstep.simulate(d, backend="numpy")}
            if compiled:
                c, _ = timed(lambda: fwdstep.simulate(d, backend="compiled"))
                if n == ns[0]:
                    print(f"    (first compiled run, n = {n}, compiles or loads: {c:.1f} s "
                          "CPU)", flush=True)
                sides["compiled"] = lambda: fwdstep.simulate(d, backend="compiled")
            cpu = {k: [] for k in sides}
            out = {}
            for _ in range(a.repeats):
                for k, fn in sides.items():
                    t, out[k] = timed(fn)
                    cpu[k].append(t)
            med = {k: statistics.median(v) for k, v in cpu.items()}
            hand = out["hand"]
            dq = {k: float(np.max(np.abs(out[k]["arm.q"] - hand))) for k in out if k != "hand"}
            row = {"n": n, **{f"{k}_cpu": v for k, v in med.items()},
                   "numpy_ratio": med["numpy"] / med["hand"],
                   "compiled_ratio": med["compiled"] / med["hand"] if "compiled" in med
                   else float("nan"), **{f"dq_{k}": v for k, v in dq.items()}}
            rows.append(row)
            print(f"{n:3d} {d.n_states:6d} {med['hand']:8.3f} {med['numpy']:8.3f} "
                  f"{row['numpy_ratio']:10.2f} {row['compiled_ratio']:13.3f} "
                  f"{dq['numpy']:13.1e} {dq.get('compiled', float('nan')):16.1e}", flush=True)
    worst = max(r["numpy_ratio"] for r in rows)
    print(f"worst NumPy-path ratio {worst:.2f} (target <= 1.0)")
    return rows


if __name__ == "__main__":
    main()
