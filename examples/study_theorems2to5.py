"""Study for docs/theorems2-5.md: does raising ell shrink the steady-state error (Sec. 4.2)?

    python examples/study_theorems2to5.py --out docs/figures            # ~20 min on 2 cores
    python examples/study_theorems2to5.py --out /tmp/quick --quick      # ~1 min smoke run
    python examples/study_theorems2to5.py --out docs/figures --parts 2  # one part only

Three parts, every number printed as a markdown table and written to CSV in --out:

1. Error against ell.  Theorems 2-5 (diagrams/theorem2..5.yaml, the horizontal two-link
   arm, critically damped coefficients) for ell = 1..6, against classical PID
   (diagrams/pid_classic.yaml) and Slotine-Li (diagrams/slotine_li_sine_disturbance.yaml) on
   the same q_d and disturbance; metric: max |Delta q| over the last 20% of a 60 s run.
   Three disturbance settings: frequency 0.8 rad/s; 2 rad/s (above Remark 4's "one");
   2 rad/s with kappa = 2 (Remark 4's time scale).  Also the vertical arm at 0.8 rad/s.
2. The point-mass closed forms |Delta q / tau_star|(j w) of Theorems 2 and 3 against ell,
   for several w and kappa (exact; tests/diagrams/test_theorems2to5.py checks them against
   simulation to 1e-4).
3. The smallest K keeping Theorem 2 stable on the point mass, ell = 1..6: from the exact
   Routh test of m p^(ell+2) + K P(p), from the eigenvalues of the diagram's own
   linearisation, and by simulation at 0.9 and 1.1 times that K.
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from math import comb

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import fwdstep  # noqa: E402
from fwdstep.structure.spec import load_spec  # noqa: E402

from fwdstep.blocks.reference import is_hurwitz  # noqa: E402


def diagram(name: str) -> str:
    return os.path.join(ROOT, "diagrams", f"{name}.yaml")


#: disturbance settings of part 1: label -> overrides (kappa only where the diagram has it)
SETTINGS = {
    "w=0.8": dict(dist_frequency=0.8),
    "w=2": dict(dist_frequency=2.0),
    "w=2, kappa=2": dict(dist_frequency=2.0, kappa=2.0),
}
THEOREMS = {"Theorem 2": "theorem2", "Theorem 3": "theorem3", "Theorem 4": "theorem4",
            "Theorem 5": "theorem5"}
VERTICAL = {"Theorem 2": ("theorem2", dict(gravity=9.81)),
            "Theorem 3": ("theorem3_vertical", {}), "Theorem 4": ("theorem4_vertical", {}),
            "Theorem 5": ("theorem5_vertical", {})}
ALPHA = 2.0                    # the diagrams' default alpha; PID gains below match it
BASELINES = {
    # K_D = K, K_P = K alpha_1, K_I = K alpha_0: Theorem 2's ell = 1 (K = 100) and the K of
    # Theorems 3-5 (K = 20)
    "PID, K_D = 100": ("pid_classic", dict(kD=[100.0] * 2, kP=[2 * ALPHA * 100] * 2,
                                           kI=[ALPHA ** 2 * 100] * 2)),
    "PID, K_D = 20": ("pid_classic", dict(kD=[20.0] * 2, kP=[2 * ALPHA * 20] * 2,
                                          kI=[ALPHA ** 2 * 20] * 2)),
    "Slotine-Li (adaptive)": ("slotine_li_sine_disturbance", dict(Lambda=ALPHA)),
}


# ----------------------------------------------------------------------------- running
def run_batch(name: str, variants: list, common: dict, refine: int = 2):
    """Simulate structurally identical variants of one diagram at once.

    Returns per variant the tail metric and the step that produced it, plus the time grid and
    the error-norm traces (T, B).  A variant that diverges is run again alone with the step
    divided by 4 (up to ``refine`` times): a divergence of a fixed-step solver on a stiff
    transient is not the controller's instability, and the table says which step was used.
    """
    specs = [load_spec(diagram(name), {**common, **v}) for v in variants]
    d = fwdstep.compile_batch(specs)
    try:
        r = fwdstep.simulate(d)
    except fwdstep.SimulationError as exc:        # every variant diverged
        r = exc.result
    metrics = r.metrics()
    metrics = metrics if isinstance(metrics, list) else [metrics]
    diverged = ~np.isnan(r.diverged_at) if r.diverged_at is not None else np.zeros(d.batch, bool)
    e = r["e.y"]
    e = e[:, None] if d.batch == 1 else e
    norms = np.linalg.norm(e, axis=-1)
    errs, steps = [], []
    for k, m in enumerate(metrics):
        err, step = m.get("tail_error_norm_max", np.nan), common["step"]
        if diverged[k] or not np.isfinite(err):
            err, step = np.nan, np.nan
            if refine:
                finer = {**common, "step": common["step"] / 4,
                         "log_every": common["log_every"] * 4}
                (err,), (step,), t_fine, n_fine = run_batch(name, [variants[k]], finer,
                                                            refine - 1)
                norms[:, k] = np.interp(r.t, t_fine, n_fine[:, 0])
        errs.append(err)
        steps.append(step)
    return errs, steps, r.t, norms


def part_error_vs_ell(ells, common, vertical: bool, log):
    rows, traces = [], {}
    for label, name in THEOREMS.items():
        for ell in ells:
            t0 = time.perf_counter()
            errs, steps, t, norms = run_batch(
                name, [{**v, "ell": ell} for v in SETTINGS.values()], common)
            for k, setting in enumerate(SETTINGS):
                rows.append(dict(controller=label, arm="horizontal", setting=setting, ell=ell,
                                 tail_max_error=errs[k], step=steps[k]))
                traces[(label, setting, ell)] = (t, norms[:, k])
            log(f"  {label} ell={ell}: " + ", ".join(
                f"{s}: {e:.3e}" + (f" (step {h:g})" if h != common["step"] else "")
                for s, e, h in zip(SETTINGS, errs, steps))
                + f"  ({time.perf_counter() - t0:.0f} s)")
    base_settings = {k: v for k, v in SETTINGS.items() if "kappa" not in v}
    for label, (name, extra) in BASELINES.items():
        errs, steps, t, norms = run_batch(
            name, [{**extra, **v} for v in base_settings.values()], common)
        for k, (setting, err) in enumerate(zip(base_settings, errs)):
            rows.append(dict(controller=label, arm="horizontal", setting=setting, ell="",
                             tail_max_error=err, step=steps[k]))
            traces[(label, setting, None)] = (t, norms[:, k])
        log(f"  {label}: " + ", ".join(f"{s}: {e:.3e}" for s, e in zip(base_settings, errs)))
    if vertical:
        for label, (name, extra) in VERTICAL.items():
            for ell in ells:
                errs, steps, _, _ = run_batch(
                    name, [{**extra, **SETTINGS["w=0.8"], "ell": ell}], common)
                rows.append(dict(controller=label, arm="vertical", setting="w=0.8", ell=ell,
                                 tail_max_error=errs[0], step=steps[0]))
            log(f"  {label} vertical: " + ", ".join(
                f"{r['tail_max_error']:.3e}" + (f" (step {r['step']:g})"
                                                if r["step"] != common["step"] else "")
                for r in rows if r["controller"] == label and r["arm"] == "vertical"))
    return rows, traces


# ----------------------------------------------------------------- point-mass closed forms
def gain_theorem2(w, ell, m, K, alpha, kappa):
    p = 1j * w
    P = np.polyval(np.poly([-alpha / kappa] * (ell + 1)), p)
    return abs(p ** ell / (m * p ** (ell + 2) + K * P))


def gain_theorem3(w, ell, m, K, alpha, kappa, Lambda):
    p = 1j * w
    P = np.polyval(np.poly([-alpha / kappa] * (ell + 1)), p)
    return abs(p ** (ell - 1) * (p + Lambda) / (P * (m * p + K)))


def part_closed_forms(ells):
    rows = []
    for w in (0.5, 0.8, 2.0, 4.0):
        for kappa in (1.0, 2.0):
            for ell in ells:
                rows.append(dict(w=w, kappa=kappa, ell=ell,
                                 theorem2=gain_theorem2(w, ell, 1.0, 100.0, ALPHA, kappa),
                                 theorem3=gain_theorem3(w, ell, 1.0, 20.0, ALPHA, kappa, 1.0)))
    return rows


# ----------------------------------------------------------------- Theorem 2's smallest K
def theorem2_polynomial_stable(K, ell, m=1.0, alpha=1.0, kappa=1.0) -> bool:
    """Routh test (exact in rationals) of p^(ell+2) + (K/m) (p + alpha/kappa)^(ell+1)."""
    a = alpha / kappa
    # coefficients of the monic polynomial, constant term first (blocks.reference order)
    coeffs = [K / m * comb(ell + 1, k) * a ** (ell + 1 - k) for k in range(ell + 2)]
    return is_hurwitz(np.array(coeffs))


def smallest_K(ell, m=1.0, alpha=1.0, kappa=1.0) -> float:
    lo, hi = 1e-6, 1e6
    for _ in range(200):
        mid = np.sqrt(lo * hi)
        if theorem2_polynomial_stable(mid, ell, m, alpha, kappa):
            hi = mid
        else:
            lo = mid
        if hi / lo < 1 + 1e-13:
            break
    return hi


def linearisation(d) -> np.ndarray:
    """Jacobian of the compiled diagram's state derivative at x = 0, t = 0 (central
    differences; exact up to round-off for a linear closed loop)."""
    sig = [None] * len(d.signal_names)
    for idx, arr in d.constant_signals.items():
        sig[idx] = arr

    def f(x):
        x = x[None, :]
        for step in d.schedule:
            xs = x[:, step.state] if step.state is not None else x[:, 0:0]
            for idx, val in zip(step.outputs, step.block.output(0.0, xs,
                                                                tuple(sig[i] for i in
                                                                      step.inputs))):
                sig[idx] = val
        dx = np.zeros_like(x)
        for step in d.stateful:
            dx[:, step.state] = step.block.derivative(0.0, x[:, step.state],
                                                      tuple(sig[i] for i in step.inputs))
        return dx[0]

    n = d.n_states
    J = np.empty((n, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1e-6
        J[:, i] = (f(e) - f(-e)) / 2e-6
    return J


def part_min_gain(ells, log, sim_t_final=120.0):
    m, alpha = 1.0, ALPHA
    quiet = dict(qd_amplitude=[0.0, 0.0], dist_amplitude=[0.0, 0.0], m=m, alpha=alpha)
    rows = []
    for ell in ells:
        K_min = smallest_K(ell, m, alpha)
        rightmost = {}
        for factor in (0.99, 1.01):
            d = fwdstep.load_diagram(diagram("theorem2_pointmass"),
                                     overrides={**quiet, "ell": ell, "K": factor * K_min})
            rightmost[factor] = np.max(np.linalg.eigvals(linearisation(d)).real)
        growth = {}
        for factor in (0.9, 1.1):
            d = fwdstep.load_diagram(diagram("theorem2_pointmass"),
                                     overrides={**quiet, "ell": ell, "K": factor * K_min,
                                                "t_final": sim_t_final, "step": 0.005,
                                                "log_every": 4})
            try:
                r = fwdstep.simulate(d)
            except fwdstep.DivergenceError:
                growth[factor] = np.inf           # |x| passed the diagram's bound, 1e8
                continue
            norm = np.linalg.norm(r["e.y"], axis=1)
            late = norm[r.t >= 0.8 * sim_t_final].max()
            early = norm[(r.t >= 0.1 * sim_t_final) & (r.t < 0.2 * sim_t_final)].max()
            growth[factor] = late / early
        rows.append(dict(ell=ell, c=K_min / (m * alpha), K_min=K_min,
                         K_min_kappa2=smallest_K(ell, m, alpha, 2.0),
                         eig_at_0_99=rightmost[0.99], eig_at_1_01=rightmost[1.01],
                         growth_at_0_9=growth[0.9], growth_at_1_1=growth[1.1]))
        log(f"  ell={ell}: K_min = {K_min:.6g} (c = {K_min / (m * alpha):.6g}); rightmost "
            f"eigenvalue {rightmost[0.99]:+.3e} / {rightmost[1.01]:+.3e} at 0.99/1.01 K_min; "
            f"|e| grows {growth_text(growth[0.9])} / {growth_text(growth[1.1])} at 0.9/1.1 "
            "K_min")
    return rows


# ----------------------------------------------------------------------------- output
def growth_text(g: float) -> str:
    return "diverged (|x| > 1e8)" if np.isinf(g) else f"x{g:.3g}"


def error_text(row: dict, default_step: float) -> str:
    text = f"{row['tail_max_error']:.2e}"
    if row["step"] != default_step:
        text += f" (h = {row['step']:g})"
    return text


def write_csv(path, rows):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def table_error(rows, ells, default_step, arm="horizontal"):
    lines = []
    settings = list(SETTINGS)
    head = "| controller | setting | " + " | ".join(f"ell = {e}" for e in ells) + " |"
    lines += [head, "|" + "---|" * (len(ells) + 2)]
    for label in THEOREMS:
        for s in settings:
            vals = {r["ell"]: r for r in rows if r["controller"] == label
                    and r["setting"] == s and r["arm"] == arm}
            if vals:
                lines.append(f"| {label} | {s} | " + " | ".join(
                    error_text(vals[e], default_step) for e in ells) + " |")
    if arm == "horizontal":
        for label in BASELINES:
            for s in settings:
                vals = [r for r in rows if r["controller"] == label and r["setting"] == s]
                if vals:
                    lines.append(f"| {label} | {s} | {error_text(vals[0], default_step)} "
                                 "(no ell) |" + " |" * (len(ells) - 1))
    return "\n".join(lines)


def figure_error(rows, ells, path):
    fig, axes = plt.subplots(1, len(SETTINGS), figsize=(5 * len(SETTINGS), 4), sharey=True)
    for ax, s in zip(axes, SETTINGS):
        for label in THEOREMS:
            vals = [next(r["tail_max_error"] for r in rows if r["controller"] == label
                         and r["setting"] == s and r["ell"] == e and r["arm"] == "horizontal")
                    for e in ells]
            ax.semilogy(ells, vals, "o-", label=label)
        for k, label in enumerate(BASELINES):
            vals = [r["tail_max_error"] for r in rows if r["controller"] == label
                    and r["setting"] == s]
            if vals:
                ax.axhline(vals[0], color=f"C{4 + k}", ls="--", label=label)
        ax.set_title(f"disturbance {s.replace('w=', 'w = ').replace('kappa=', 'kappa = ')}")
        ax.set_xlabel("ell")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("max |q - q_d| over the last 20% (rad)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_traces(traces, ells, path, setting="w=0.8"):
    fig, axes = plt.subplots(2, 2, figsize=(10, 7), sharex=True, sharey=True)
    for ax, label in zip(axes.flat, THEOREMS):
        for ell in ells:
            t, norm = traces[(label, setting, ell)]
            ax.semilogy(t, norm, lw=0.8, label=f"ell = {ell}")
        t, norm = traces[("PID, K_D = 100", setting, None)]
        ax.semilogy(t, norm, "k--", lw=0.8, label="PID, K_D = 100")
        ax.set_title(f"{label}, disturbance {setting}")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("t (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel("|q - q_d| (rad)")
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_closed_forms(rows, ells, path):
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, key, title in ((axes[0], "theorem2", "Theorem 2, K = 100"),
                           (axes[1], "theorem3", "Theorem 3, K = 20, Lambda = 1")):
        for k, w in enumerate(sorted({r["w"] for r in rows})):
            for kappa, ls in ((1.0, "-"), (2.0, ":")):
                vals = [next(r[key] for r in rows if r["w"] == w and r["kappa"] == kappa
                             and r["ell"] == e) for e in ells]
                ax.semilogy(ells, vals, ls, marker="o", color=f"C{k}",
                            label=f"w = {w:g}, kappa = {kappa:g}")
        ax.set_title(title)
        ax.set_xlabel("ell")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("|Delta q / tau_star| at w")
    axes[1].legend(fontsize=7)
    fig.suptitle(f"point mass m = 1, alpha = {ALPHA:g}: closed-form error gain")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_min_gain(rows, path):
    fig, ax = plt.subplots(figsize=(5, 4))
    ell = [r["ell"] for r in rows]
    ax.plot(ell, [r["K_min"] for r in rows], "o-", label="kappa = 1")
    ax.plot(ell, [r["K_min_kappa2"] for r in rows], "s--", label="kappa = 2")
    ax.set_xlabel("ell")
    ax.set_ylabel("smallest stabilising K")
    ax.set_title(f"Theorem 2, point mass m = 1, alpha = {ALPHA:g}")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="docs/figures", help="output directory")
    parser.add_argument("--quick", action="store_true",
                        help="ell = 1..2, 12 s runs, no vertical arm (a smoke run)")
    parser.add_argument("--parts", default="123",
                        help="which parts to run, e.g. 2 or 13 (default: 123)")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    ells = [1, 2] if args.quick else [1, 2, 3, 4, 5, 6]
    common = dict(t_final=12.0 if args.quick else 60.0, step=0.002, log_every=10)
    log = print

    if "1" in args.parts:
        log("1. steady-state error against ell (two-link arm)")
        rows, traces = part_error_vs_ell(ells, common, vertical=not args.quick, log=log)
        write_csv(os.path.join(args.out, "theorems2-5_error_vs_ell.csv"), rows)
        figure_error(rows, ells, os.path.join(args.out, "theorems2-5_error_vs_ell.png"))
        figure_traces(traces, ells, os.path.join(args.out, "theorems2-5_error_traces.png"))
        print("\n## Error against ell (horizontal arm)\n")
        print(table_error(rows, ells, common["step"]))
        if not args.quick:
            print("\n## Error against ell (vertical arm, w = 0.8)\n")
            print(table_error(rows, ells, common["step"], arm="vertical"))
    if "2" in args.parts:
        closed = part_closed_forms(ells)
        write_csv(os.path.join(args.out, "theorems2-3_pointmass_gain.csv"), closed)
        figure_closed_forms(closed, ells,
                            os.path.join(args.out, "theorems2-3_pointmass_gain.png"))
        print_closed_forms(closed, ells)
    if "3" in args.parts:
        log("3. Theorem 2: smallest stabilising K on the point mass")
        gains = part_min_gain(ells, log, sim_t_final=30.0 if args.quick else 60.0)
        write_csv(os.path.join(args.out, "theorem2_min_gain.csv"), gains)
        figure_min_gain(gains, os.path.join(args.out, "theorem2_min_gain.png"))
        print_min_gain(gains)
    return 0


def print_closed_forms(closed, ells):
    print("\n## Point mass, |Delta q / tau_star|(j w)\n")
    print("| w | kappa | " + " | ".join(f"ell = {e}" for e in ells) + " |")
    print("|" + "---|" * (len(ells) + 2))
    for key in ("theorem2", "theorem3"):
        for w in sorted({r["w"] for r in closed}):
            for kappa in (1.0, 2.0):
                vals = [next(r[key] for r in closed if r["w"] == w and r["kappa"] == kappa
                             and r["ell"] == e) for e in ells]
                print(f"| {key} {w:g} | {kappa:g} | " + " | ".join(f"{v:.2e}" for v in vals)
                      + " |")


def print_min_gain(gains):
    print("\n## Theorem 2: smallest K (point mass m = 1, alpha = 2)\n")
    print("| ell | K_min / (m alpha) | K_min | K_min, kappa = 2 | max Re eig at 0.99 / 1.01 "
          "K_min | growth of max abs e at 0.9 / 1.1 K_min |")
    print("|---|---|---|---|---|---|")
    for g in gains:
        print(f"| {g['ell']} | {g['c']:.6g} | {g['K_min']:.6g} | {g['K_min_kappa2']:.6g} | "
              f"{g['eig_at_0_99']:+.2e} / {g['eig_at_1_01']:+.2e} | "
              f"{growth_text(g['growth_at_0_9'])} / {growth_text(g['growth_at_1_1'])} |")


if __name__ == "__main__":
    sys.exit(main())
