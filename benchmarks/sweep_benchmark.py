"""Sweep speed, as ratios measured in one run (issue 13).

(a) A 256-variant sweep of ``slotine_li.yaml`` (Lambda drawn in [2, 10]) on the NumPy path,
    one core (``workers=1``: one batch), against a hand-written NumPy RK4 loop of the same
    closed loop vectorised over the same 256 variants (``batched_slotine_li`` below: arrays
    with a leading batch axis, a closed-form 2x2 solve).  Target: sweep / hand <= 1.2.
    The two error logs are compared, so both sides integrate the same closed loop.
(b) The same sweep in >= 8 batches on 2 local worker processes against 1: throughput ratio
    (target >= 1.7).  The machine's load average is printed with it: other processes on the
    same cores take their share.  The CPU seconds spent in this process and in the workers
    are printed too, with the ratio they allow on two free cores (Amdahl).

Both run the diagram as shipped (t_final 10 s) unless ``--t-final`` says otherwise; a
shorter run weighs the sweep's fixed work (deriving and planning the 256 variants, ~0.1 s)
more: ``--t-final 2`` shows it.

    python benchmarks/sweep_benchmark.py [--t-final 10] [--samples 256] [--repeats 3]
"""
from __future__ import annotations

import argparse
import os
import sys
import shutil
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from hand_loops import A1, A2, A3, A4  # noqa: E402

from fwdstep.structure.compiler import compile_batch  # noqa: E402
from fwdstep.run.simulate import simulate  # noqa: E402
from fwdstep.structure.spec import load_spec  # noqa: E402
from fwdstep.sweeps.sweep import run_sweep  # noqa: E402

SLOTINE = os.path.join(os.path.dirname(HERE), "diagrams", "slotine_li.yaml")


def batched_slotine_li(t_final, h, log_every, Lambda, K, Gamma, theta0, A, w, c, q0):
    """The Slotine-Li closed loop of ``hand_loops.slotine_li`` for B gains Lambda at once:
    state (B, 8) = q, qdot, theta_hat; returns the log of e = q - q_d, (rows, B, 2)."""
    lam = np.asarray(Lambda, dtype=float)[:, None]          # (B, 1)
    B = lam.shape[0]
    A, w, c = (np.asarray(v, dtype=float) for v in (A, w, c))
    K = np.asarray(K, dtype=float) * (np.eye(2) if np.ndim(K) == 0 else 1.0)
    gam = float(Gamma)

    def f(t, x):
        q, qdot, th = x[:, 0:2], x[:, 2:4], x[:, 4:8]
        s_, c_ = np.sin(w * t), np.cos(w * t)
        qd, qd_d, qd_dd = c + A * s_, A * w * c_, -A * w * w * s_
        z = qd_d - lam * (q - qd)
        zd = qd_dd - lam * (qdot - qd_d)
        s = qdot - z
        c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
        v1 = qdot[:, 1] * z[:, 0] + (qdot[:, 0] + qdot[:, 1]) * z[:, 1]
        v2 = qdot[:, 0] * z[:, 0]
        w1 = 2 * zd[:, 0] + zd[:, 1]
        Y = np.empty((B, 2, 4))
        Y[:, 0, 0], Y[:, 0, 1] = zd[:, 0], zd[:, 1]
        Y[:, 0, 2], Y[:, 0, 3] = c2 * w1 - s2 * v1, s2 * w1 + c2 * v1
        Y[:, 1, 0], Y[:, 1, 1] = 0.0, zd[:, 0] + zd[:, 1]
        Y[:, 1, 2], Y[:, 1, 3] = c2 * zd[:, 0] + s2 * v2, s2 * zd[:, 0] - c2 * v2
        tau = np.einsum("bij,bj->bi", Y, th) - s @ K.T
        h12 = A2 + A3 * c2 + A4 * s2
        h11 = A1 + 2 * A3 * c2 + 2 * A4 * s2
        hh = A3 * s2 - A4 * c2
        r0 = tau[:, 0] + hh * qdot[:, 1] * qdot[:, 0] + hh * (qdot[:, 0] + qdot[:, 1]) * qdot[:, 1]
        r1 = tau[:, 1] - hh * qdot[:, 0] * qdot[:, 0]
        det = h11 * A2 - h12 * h12
        dx = np.empty_like(x)
        dx[:, 0:2] = qdot
        dx[:, 2] = (A2 * r0 - h12 * r1) / det
        dx[:, 3] = (h11 * r1 - h12 * r0) / det
        dx[:, 4:8] = -gam * np.einsum("bij,bi->bj", Y, s)
        return dx

    x = np.zeros((B, 8))
    x[:, 0:2] = q0
    x[:, 4:8] = theta0
    n = int(round(t_final / h))
    rows = n // log_every + 1 + (1 if n % log_every else 0)
    log = np.empty((rows, B, 2))
    r = 0
    for i in range(n):
        t = i * h
        if i % log_every == 0:
            log[r] = x[:, 0:2] - (c + A * np.sin(w * t))
            r += 1
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    log[r] = x[:, 0:2] - (c + A * np.sin(w * n * h))
    return log


class _Chunk:
    def __init__(self, variants):
        self.variants = variants


def _hand_batch(job):
    hand, chunk = job
    return hand(_Chunk(chunk)).shape


def _hand_batches(hand, chunks, workers):
    """The hand loop over ``chunks`` of variants, in this process or on forked workers
    (which inherit the jobs: only their numbers are sent)."""
    _JOBS[:] = [(hand, chunk) for chunk in chunks]
    if workers == 1:
        return [_hand_batch(job) for job in _JOBS]
    import multiprocessing
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        return pool.map(_hand_batch_inherited, range(len(_JOBS)), chunksize=1)


_JOBS: list = []


def _hand_batch_inherited(k):
    return _hand_batch(_JOBS[k])


def _timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w0, time.process_time() - c0, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-final", type=float, default=None,
                    help="run length (s; default: the diagram's, 10)")
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batches", type=int, default=8, help="batches for (b)")
    ap.add_argument("--only", default="a,b", help="which of (a), (b) to run: a, b or a,b")
    args = ap.parse_args(argv)
    text = open(SLOTINE).read()
    # a copy in a private folder, never next to the shipped diagrams (tests that list
    # diagrams/*.yaml while a benchmark runs would find it, then lose it)
    folder = tempfile.mkdtemp(prefix="fwdstep-sweep-benchmark-")
    path = os.path.join(folder, os.path.basename(SLOTINE))
    with open(path, "w") as fh:
        fh.write(text)
    try:
        over = {} if args.t_final is None else {"t_final": args.t_final}
        spec = load_spec(path, over)
        p = spec.parameters
        cfg = spec.simulation
        print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")

        def sweep(**kw):
            return run_sweep(path, random={"Lambda": (2.0, 10.0)}, samples=args.samples,
                             seed=1, overrides=over, keep_signals=True, **kw)

        def hand(result):
            lam = [v.values["Lambda"] for v in result.variants]
            return batched_slotine_li(cfg.t_final, cfg.step, cfg.log_every, lam, p["K"],
                                      p["Gamma"], p["theta0"], p["A"], p["w"], p["c"],
                                      p["q0"])

        def integrate(result):
            """The same batch compiled and integrated, nothing else (where the time goes)."""
            lam = [v.values["Lambda"] for v in result.variants]
            d = compile_batch([load_spec(path, {**over, "Lambda": x}) for x in lam])
            d.logged = [d.resolve("e.y")]
            return _timed(lambda: simulate(d))[:2]

        parts = set(args.only.split(","))
        probe = sweep(workers=1)
        log = hand(probe)
        order = np.concatenate([part["indices"] for part in probe.parts])
        e = np.concatenate([part["e"] for part in probe.parts], axis=1)[:, np.argsort(order)]
        diff = float(np.max(np.abs(e - log)))
        print(f"(a) {args.samples} variants, t_final {cfg.t_final:g} s, step {cfg.step:g}: "
              f"{len(probe.batches)} batch(es); max |e_sweep - e_hand| = {diff:.2e}")
        walls = {"sweep": [], "hand": []}
        cpus = {"sweep": [], "hand": []}
        runs = {"sweep": lambda: _timed(lambda: sweep(workers=1))[:2],
                "hand": lambda: _timed(lambda: hand(probe))[:2],
                "integrate": lambda: integrate(probe)}
        for i in range(args.repeats if "a" in parts else 0):     # interleaved, the order
            order = list(runs) if i % 2 == 0 else list(runs)[::-1]   # reversed every other
            for name in order:                                   # repeat (load drifts)
                w, c = runs[name]()
                walls.setdefault(name, []).append(w)
                cpus.setdefault(name, []).append(c)
        if "a" in parts:
            med = {k: float(np.median(v)) for k, v in walls.items()}
            cmed = {k: float(np.median(v)) for k, v in cpus.items()}
            print(f"    sweep (load + plan + one batch) / hand batched loop: "
                  f"{med['sweep'] / med['hand']:.2f}x wall, {cmed['sweep'] / cmed['hand']:.2f}x cpu "
                  f"(target <= 1.2)")
            print(f"    of which integrating the batch (fwdstep.simulate alone) / hand: "
                  f"{med['integrate'] / med['hand']:.2f}x wall, "
                  f"{cmed['integrate'] / cmed['hand']:.2f}x cpu")
            for name in ("sweep", "integrate"):   # each repeat against its own hand run
                paired = np.array(cpus[name]) / np.array(cpus["hand"])
                print(f"    {name} / hand, each repeat paired (cpu): median "
                      f"{np.median(paired):.2f}x, range {paired.min():.2f}-{paired.max():.2f}")
            print(f"    least disturbed repeats (minimum cpu of each): sweep / hand "
                  f"{min(cpus['sweep']) / min(cpus['hand']):.2f}x, integrate / hand "
                  f"{min(cpus['integrate']) / min(cpus['hand']):.2f}x; load average after: "
                  f"{os.getloadavg()[0]:.2f}")
        if "b" in parts:
            size = int(np.ceil(args.samples / args.batches))
            rates, split, machine = {}, [], {}
            chunks = [probe.variants[k:k + size] for k in range(0, args.samples, size)]
            for workers in (1, 2) * args.repeats:          # interleaved
                c0 = os.times()
                w, _, r = _timed(lambda: sweep(workers=workers, batch_size=size))
                c1 = os.times()
                rates.setdefault(workers, []).append(w)
                # the machine's own scaling: the hand batched loop on the same batches, in
                # this process and on 2 forked processes (no fwdstep involved)
                machine.setdefault(workers, []).append(_timed(lambda: _hand_batches(
                    hand, chunks, workers))[0])
                if workers == 2:     # CPU seconds of this process (serial) and of the workers
                    split.append((c1.user - c0.user + c1.system - c0.system,
                                  c1.children_user - c0.children_user
                                  + c1.children_system - c0.children_system))
            one, two = np.median(rates[1]), np.median(rates[2])
            serial, parallel = np.median([s for s, _ in split]), np.median([p for _, p in split])
            print(f"(b) {len(r.batches)} batches of <= {size}: 2 workers / 1 worker throughput "
                  f"{one / two:.2f}x (target >= 1.7); load average after: "
                  f"{os.getloadavg()[0]:.2f}")
            print(f"    the hand batched loop on the same {len(chunks)} batches, 2 processes / 1: "
                  f"{np.median(machine[1]) / np.median(machine[2]):.2f}x (what this machine "
                  f"gives this work)")
            # each repeat's pair (1 then 2 workers, minutes apart at most) on its own: the
            # VM's speed drifts between repeats, a pair shares its minutes
            mine = np.array(rates[1]) / np.array(rates[2])
            theirs = np.array(machine[1]) / np.array(machine[2])
            print(f"    each repeat's pair on its own: fwdstep {', '.join(f'{x:.2f}' for x in mine)}"
                  f" (median {np.median(mine):.2f}x); hand loop "
                  f"{', '.join(f'{x:.2f}' for x in theirs)} (median {np.median(theirs):.2f}x); "
                  f"fwdstep's scaling / the hand loop's, median of the repeats: "
                  f"{np.median(mine / theirs):.2f}")
            print(f"    with 2 workers: {serial:.2f} s CPU in this process (load, plan, collect), "
                  f"{parallel:.2f} s in the workers: on 2 free cores at most "
                  f"{(serial + parallel) / (serial + parallel / 2):.2f}x")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
