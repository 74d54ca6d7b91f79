"""Study: linear analysis of the paper's loops (docs/linear-analysis.md).

One command:  python examples/study_linear_analysis.py
Writes docs/figures/linear_*.png and docs/figures/linear_results.json:
  1. Theorem 1 on two point masses (examples/theorem1_pointmass.yaml) at rest with
     theta_hat = theta, ell = 1..6: characteristic polynomial of each joint's loop against
     (p + alpha)^(ell+1) (p + K/m_i); Bode figure of joint 1's loop opened at its torque.
  2. Theorem 1 on the two-link arm (diagrams/theorem1.yaml), as shipped: closed-loop
     frozen-time poles at 60 times of its 10 s run.
  3. Theorem 7 (diagrams/theorem7.yaml) frozen at theta_hat = 0, 4, 9 (omega = 3): gain from
     the disturbance tau*_1 to q_1; the learned frequency is a notch.
  4. The Panda Slotine-Li diagram (57 states): time of the run to t = 1 s, of building the
     block Jacobians and of one linearisation.
"""
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, ROOT)
FIG = os.path.join(ROOT, "docs", "figures")


def theorem1_point_mass(results):
    import fwdstep
    from fwdstep.analysis.linearize import linearize
    from fwdstep.analysis.linear_outputs import bode_figure
    path = os.path.join(ROOT, "examples", "theorem1_pointmass.yaml")
    rows = []
    for ell in range(1, 7):
        d = fwdstep.load_diagram(path, {"ell": ell})
        m = linearize(d, inputs=["qd.y"], outputs=["e.y"], t=0.0)
        p = d.spec.parameters
        alpha, K, masses = float(p["alpha"]), float(p["K"]), np.asarray(p["m"], float)
        names = m.state_names
        adapt = [i for i, n in enumerate(names) if n.startswith("adapt.")]
        loop = [i for i in range(len(names)) if i not in adapt]
        worst = 0.0
        for j, mass in enumerate(masses):
            joint = [i for i in loop if names[i].endswith((f"[{j}]", f"q{j + 1}",
                                                           f"qdot{j + 1}"))]
            got = np.poly(m.A[np.ix_(joint, joint)])
            want = np.polymul(np.poly(np.full(ell + 1, -alpha)), [1.0, K / mass])
            worst = max(worst, float(np.max(np.abs(got - want) / np.abs(want))))
        poles = m.poles()
        rows.append({"ell": ell, "states": len(names), "adaptation_states": len(adapt),
                     "max_relative_coefficient_error": worst,
                     "adaptation_block_of_A_zero": bool(not m.A[adapt].any()
                                                        and not m.A[np.ix_(loop, adapt)].any()),
                     "pole_spread_around_minus_alpha": float(np.max(np.abs(
                         poles[np.abs(poles + alpha) < 0.5] + alpha)))})
        print(f"ell={ell}: {len(names)} states, coefficient error {worst:.1e}, "
              f"eigenvalues of the (ell+1)-fold root scattered by "
              f"{rows[-1]['pole_spread_around_minus_alpha']:.1e}")
    results["theorem1_point_mass"] = rows
    d = fwdstep.load_diagram(path, {"ell": 2})
    L = linearize(d, inputs=["tau.y[0]"], outputs=["tau.y[0]"], open="tau.y[0]")
    mg = L.margins()
    results["theorem1_point_mass_loop"] = {k: v for k, v in mg.items()}
    fig = bode_figure(L, margins=mg, title="Theorem 1, point mass 1 (m = 1.5, K = 50, "
                                           "alpha = 4, ell = 2): loop opened at tau_1")
    fig.savefig(os.path.join(FIG, "linear_theorem1_bode.png"), dpi=110)
    print(f"loop at tau_1: gain margin {mg['gain_margin_db']:.3g} dB, phase margin "
          f"{mg['phase_margin_deg']:.4g} deg at {mg['gain_crossover']:.4g} rad/s")


def theorem1_two_link_along(results):
    import fwdstep
    from fwdstep.analysis.linearize import linearize_along
    from fwdstep.analysis.linear_outputs import poles_figure
    d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", "theorem1.yaml"))
    start = time.perf_counter()
    models = linearize_along(d, inputs=["qd.y"], outputs=["e.y"], n=60)
    elapsed = time.perf_counter() - start
    fig = poles_figure(models, "Theorem 1, two-link arm (diagrams/theorem1.yaml): "
                               "closed-loop frozen-time poles at 60 times")
    fig.savefig(os.path.join(FIG, "linear_theorem1_poles_over_time.png"), dpi=110)
    right = [float(np.max(m.poles().real)) for m in models]
    results["theorem1_two_link_along"] = {
        "times": [m.t for m in models], "rightmost_real_part": right,
        "seconds_run_and_60_linearisations": elapsed}
    print(f"two-link along the run: rightmost real part {right[0]:.3g} at t=0, "
          f"{max(right[len(right) // 2:]):.3g} max over the second half ({elapsed:.2f} s)")


def theorem7_notch(results):
    import fwdstep
    from fwdstep.analysis.linearize import linearize
    from fwdstep.analysis.linear_outputs import _figure
    over = {"vartheta0": "[3.34, 0.97, 1.04, 0.6]", "qd_amp": [0, 0], "tau_amp": 0}
    w = np.logspace(-1, 1.5, 1500)
    fig, (ax,) = _figure(1, height=3.4)
    out = {}
    for theta in (0.0, 4.0, 9.0):
        d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", "theorem7.yaml"),
                                 dict(over, theta0=theta))
        m = linearize(d, inputs=["dist.y[0]"], outputs=["plant.q[0]"], t=0.0)
        H = np.abs(m.frequency_response(w)[:, 0, 0])
        at3 = float(np.abs(m.frequency_response([3.0])[0, 0, 0]))
        out[str(theta)] = {"gain_at_3": at3, "max_gain": float(H.max())}
        ax.loglog(w, H, label=rf"$\hat\theta$ = {theta:g} (notch at "
                              rf"$\sqrt{{\hat\theta}}$ = {np.sqrt(theta):.3g} rad/s)"
                  if theta else r"$\hat\theta$ = 0 (no internal model)")
    ax.axvline(3.0, color="0.5", ls="--", lw=0.8)
    ax.set_xlabel(r"$\omega$ (rad/s)")
    ax.set_ylabel(r"$|q_1 / \tau^*_1|(j\omega)$ (rad / N m)")
    ax.set_ylim(1e-6, None)
    ax.set_title("Theorem 7 (theorem7.yaml) frozen at rest: disturbance to position "
                 "(true frequency 3 rad/s)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", lw=0.3)
    fig.savefig(os.path.join(FIG, "linear_theorem7_notch.png"), dpi=110)
    results["theorem7_notch"] = out
    print("theorem 7: |H(j3)| = " + ", ".join(f"{v['gain_at_3']:.2e} (theta_hat={k})"
                                             for k, v in out.items()))


def theorems8_9_notches(results):
    """Theorems 8 and 9 frozen at rest with the learned theta_hat (the coefficients of
    prod (p^2 + omega_i^2)): a notch at every disturbance frequency; theta_hat = 0 for
    comparison."""
    import fwdstep
    from fwdstep.analysis.linearize import linearize
    from fwdstep.analysis.linear_outputs import _figure
    w = np.logspace(-0.3, 1.2, 2000)
    fig, axes = _figure(2, height=3.0)
    out = {}
    for ax, (name, omegas) in zip(axes, (("theorem8", [2.0, 4.0]),
                                         ("theorem9", [2.0, 3.0, 4.5]))):
        poly = np.real(np.poly(np.concatenate([1j * np.array(omegas), -1j * np.array(omegas)])))
        learned = [float(c) for c in poly[::-2][:len(omegas)]]
        out[name] = {}
        for label, theta0 in (("theta_hat = 0", 0), ("theta_hat learned", learned)):
            d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", f"{name}.yaml"), {
                "vartheta0": "[3.34, 0.97, 1.04, 0.6]", "qd_amp": [0, 0], "tau_amp": 0,
                "theta0": theta0})
            m = linearize(d, inputs=["dist.y[0]"], outputs=["plant.q[0]"], t=0.0)
            ax.loglog(w, np.abs(m.frequency_response(w)[:, 0, 0]),
                      label=rf"$\hat\theta$ = {learned}" if theta0 else r"$\hat\theta$ = 0")
            out[name][label] = [float(abs(m.frequency_response([om])[0, 0, 0]))
                                for om in omegas]
        for om in omegas:
            ax.axvline(om, color="0.5", ls="--", lw=0.8)
        ax.set_ylim(1e-7, None)
        ax.set_ylabel(r"$|q_1 / \tau^*_1|$ (rad / N m)")
        ax.set_title(f"{name}.yaml frozen at rest: notches at the learned frequencies "
                     f"{', '.join(f'{om:g}' for om in omegas)} rad/s", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(True, which="both", lw=0.3)
    axes[-1].set_xlabel(r"$\omega$ (rad/s)")
    fig.savefig(os.path.join(FIG, "linear_theorems8_9_notches.png"), dpi=110)
    results["theorems8_9_notches"] = out
    print("theorems 8, 9: |H(j omega_i)| learned", {k: v["theta_hat learned"]
                                                   for k, v in out.items()})


def panda_timing(results):
    try:
        import pinocchio  # noqa: F401
    except ImportError:
        print("panda: pinocchio missing, skipped")
        return
    import fwdstep
    from fwdstep.analysis.linearize import DiagramLinearizer, state_at
    d = fwdstep.load_diagram(os.path.join(ROOT, "diagrams", "robots",
                                          "panda_slotine_li.yaml"))
    start = time.perf_counter()
    t, x = state_at(d, 1.0)
    run = time.perf_counter() - start
    start = time.perf_counter()
    lin = DiagramLinearizer(d, inputs=["tau.y"], outputs=["e.y"])
    build = time.perf_counter() - start
    times = []
    for _ in range(5):
        start = time.perf_counter()
        m = lin.at(t, x)
        times.append(time.perf_counter() - start)
    poles = m.poles()
    results["panda_slotine_li"] = {
        "states": int(d.n_states), "run_to_1s_seconds": run,
        "build_jacobians_seconds": build, "linearise_seconds_median_of_5":
            float(np.median(times)), "rightmost_pole_real": float(poles.real.max()),
        "methods": m.methods}
    print(f"panda: {d.n_states} states; run to t = 1 s {run:.2f} s, block Jacobians built "
          f"in {build:.3f} s, one linearisation {np.median(times) * 1e3:.1f} ms; rightmost "
          f"closed-loop pole real part {poles.real.max():.3g}")


def main():
    os.makedirs(FIG, exist_ok=True)
    results = {}
    theorem1_point_mass(results)
    theorem1_two_link_along(results)
    theorem7_notch(results)
    theorems8_9_notches(results)
    panda_timing(results)

    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        if isinstance(v, float) and not np.isfinite(v):
            return str(v)
        return v
    with open(os.path.join(FIG, "linear_results.json"), "w") as f:
        json.dump(clean(results), f, indent=1)


if __name__ == "__main__":
    main()
