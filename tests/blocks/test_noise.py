"""WhiteNoise: the variance of its integral is S t whatever the hold interval and the solver
step (the PSD scaling), Gaussian statistics, right-continuity at the declared sample
instants, determinism per seed, per-variant seeds in batches and sweeps, and a low-pass
filtered (band-limited) noise with the exact discrete variance."""
import math

import numpy as np
import pytest
from scipy import stats

import fwdstep
from fwdstep.blocks.noise import WhiteNoise
from fwdstep.structure.compiler import stack_blocks
from fwdstep.core.errors import ParameterError
from fwdstep.sweeps.sweep import run_sweep

NO_STATE = np.zeros((1, 0))


def samples(blk, times):
    return np.array([blk.output(t, NO_STATE, ())[0][0] for t in times])


def integrate(tmp_path, psd, sample_time, step, n, t_final=1.0, seed=5):
    path = tmp_path / "w.yaml"
    path.write_text(f"""
description: integral of white noise
blocks:
  w: {{type: WhiteNoise, n: {n}, psd: {psd}, sample_time: {sample_time}, seed: {seed}}}
  W: {{type: Integrator, shape: [{n}]}}
connections:
  - w.y -> W.u
simulation: {{t_final: {t_final}, step: {step}, solver: rk4, log_every: 1000000}}
log: [W.y]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    assert r.status == "ok"
    return r["W.y"][-1]


@pytest.mark.parametrize("sample_time,step", [(0.01, 0.01), (0.01, 0.0025), (0.01, 0.003),
                                              (0.05, 0.01)])
def test_integral_is_the_exact_sum_of_held_samples_for_any_step(tmp_path, sample_time, step):
    """With the sample instants declared as discontinuities, RK4 integrates the held samples
    exactly, also when the step does not divide Ts (0.003 vs 0.01)."""
    n, psd = 50, 0.3
    W = integrate(tmp_path, psd, sample_time, step, n, t_final=0.6)
    blk = WhiteNoise("w", n=n, psd=psd, sample_time=sample_time, seed=5)
    k = np.arange(round(0.6 / sample_time))
    exact = sample_time * samples(blk, k * sample_time).sum(axis=0)
    np.testing.assert_allclose(W, exact, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("sample_time", [0.005, 0.02, 0.1, 0.3])
def test_variance_of_the_integral_is_psd_times_time(sample_time):
    """Var(int_0^T w dt) = S T for every Ts (T = 0.9 s, also with Ts = 0.3 s: 3 samples):
    20000 independent channels, integral = Ts * sum of the held samples (the run above shows
    the solver computes exactly this).  The sample variance of 20000 normals is within 4.5
    standard errors (sqrt(2/20000) = 1 %)."""
    n, psd, T = 20000, 0.3, 0.9
    blk = WhiteNoise("w", n=n, psd=psd, sample_time=sample_time, seed=5)
    k = np.arange(round(T / sample_time))
    W = sample_time * samples(blk, k * sample_time).sum(axis=0)
    assert np.var(W) == pytest.approx(psd * T, rel=4.5 * math.sqrt(2 / n))
    assert abs(np.mean(W)) < 4.5 * math.sqrt(psd * T / n)


def test_samples_are_independent_standard_normals_scaled_by_sqrt_psd_over_ts():
    S, Ts = 2.0, 0.01
    blk = WhiteNoise("w", n=40, psd=S, sample_time=Ts, seed=11)
    y = samples(blk, np.arange(500) * Ts)                   # (500 times, 40 channels)
    z = y / math.sqrt(S / Ts)
    flat = z.reshape(-1)                                    # 20000 numbers
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    assert abs(flat.mean()) < 4.5 / math.sqrt(flat.size)
    assert flat.var() == pytest.approx(1.0, rel=4.5 * math.sqrt(2 / flat.size))
    lag_time = np.mean(z[1:] * z[:-1])                      # neighbouring samples
    lag_channel = np.mean(z[:, 1:] * z[:, :-1])             # neighbouring channels
    other_seed = samples(WhiteNoise("w", n=40, psd=S, sample_time=Ts, seed=12),
                         np.arange(500) * Ts) / math.sqrt(S / Ts)
    for corr in (lag_time, lag_channel, np.mean(z * other_seed)):
        assert abs(corr) < 4.5 / math.sqrt(flat.size)


def test_held_between_instants_and_right_continuous_at_them():
    Ts = 0.1
    blk = WhiteNoise("w", n=3, psd=1.0, sample_time=Ts, seed=2)
    for k in (1, 3, 7, 29):                                 # 0.7 / 0.1 = 6.999...
        T = k * Ts
        at, before = samples(blk, [T, math.nextafter(T, -math.inf)])
        inside = samples(blk, [T + 0.3 * Ts, T + 0.999 * Ts,
                                 math.nextafter((k + 1) * Ts, -math.inf)])
        assert not np.array_equal(at, before)
        for y in inside:
            np.testing.assert_array_equal(y, at)
    np.testing.assert_allclose(blk.discontinuities(1.0), np.arange(11) * Ts, rtol=0, atol=0)


def test_same_seed_same_signal_and_mean_is_added():
    a = WhiteNoise("w", n=2, psd=[1.0, 4.0], sample_time=0.01, seed=9)
    b = WhiteNoise("w", n=2, psd=[1.0, 4.0], sample_time=0.01, seed=9, mean=[1.0, -2.0])
    times = np.linspace(0.0, 3.0, 77)
    np.testing.assert_array_equal(samples(a, times) + [1.0, -2.0], samples(b, times))
    ratio = samples(a, times)[:, 1] / samples(a, times)[:, 0]
    assert not np.allclose(ratio, 2.0)                       # channels are not copies


def test_a_batch_mixes_seeds_and_each_variant_is_its_own_run():
    variants = [{"n": 2, "psd": 1.0, "sample_time": 0.01, "seed": s} for s in (1, 2, 3)]
    big = stack_blocks([[WhiteNoise("w", **v)] for v in variants])[0]
    for t in (0.0, 0.013, 0.5, 2.0):
        (yb,) = big.output(t, NO_STATE, ())
        for i, v in enumerate(variants):
            np.testing.assert_array_equal(yb[i], WhiteNoise("w", **v).output(t, NO_STATE, ())[0][0])
    assert not np.array_equal(yb[0], yb[1])


def test_sweep_gives_each_variant_its_own_seed(tmp_path):
    path = tmp_path / "sweep.yaml"
    path.write_text("""
description: filtered noise, swept over the gain, a seed per variant
parameters: {k: 1.0, noise_seed: 0}
blocks:
  w: {type: WhiteNoise, n: 1, psd: 1.0, sample_time: 0.01, seed: noise_seed}
  g: {type: Gain, gain: k, shape: [1]}
  f: {type: TransferFunction, num: [1], den: [1, 1], shape: [1]}
connections:
  - w.y -> g.u
  - g.y -> f.u
simulation: {t_final: 0.5, step: 0.01, solver: rk4}
log: [f.y]
metrics: {error: f.y}
""")
    batched = run_sweep(str(path), {"k": [1.0, 1.0, 1.0]}, seed_parameter="noise_seed",
                        seed=4, workers=1)
    alone = run_sweep(str(path), {"k": [1.0, 1.0, 1.0]}, seed_parameter="noise_seed",
                      seed=4, workers=1, sequential=True)
    seeds = [v.values["noise_seed"] for v in batched.variants]
    assert len(set(seeds)) == 3
    finals = {}
    for a, b in zip(sorted(batched.variants, key=lambda v: v.index),
                    sorted(alone.variants, key=lambda v: v.index)):
        assert a.values == b.values
        assert a.metrics == pytest.approx(b.metrics, rel=1e-12)
        finals[a.index] = a.metrics["final_error_norm"]
    assert len({round(v, 12) for v in finals.values()}) == 3   # three different signals


def test_low_pass_filtered_noise_has_the_exact_stationary_variance(tmp_path):
    """Band-limited noise: x' = wc (w - x) driven by the held samples is, at the sample
    instants, x_{k+1} = a x_k + (1 - a) w_k with a = exp(-wc Ts), so its stationary variance
    is (S / Ts) (1 - a) / (1 + a) (-> S wc / 2 as Ts -> 0).  Estimated from 40 channels x
    900 instants after the transient; the estimator of an AR(1) variance has relative
    standard error sqrt(2 (1 + a^2) / ((1 - a^2) N)) (1.7 % here), we allow 4.5 of them."""
    n, S, Ts, wc = 40, 0.5, 0.01, 20.0
    path = tmp_path / "lp.yaml"
    path.write_text(f"""
description: first-order low-pass filtered white noise
blocks:
  w: {{type: WhiteNoise, n: {n}, psd: {S}, sample_time: {Ts}, seed: 1}}
  f: {{type: TransferFunction, num: [{wc}], den: [1, {wc}], shape: [{n}]}}
connections:
  - w.y -> f.u
simulation: {{t_final: 10.0, step: {Ts / 2}, solver: rk4, log_every: 2}}
log: [f.y]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    a = math.exp(-wc * Ts)
    stationary = S / Ts * (1 - a) / (1 + a)
    x = r["f.y"][r.t >= 1.0]                        # 20 time constants: transient e^-20 gone
    se = math.sqrt(2 * (1 + a * a) / ((1 - a * a) * x.size))
    assert np.mean(x * x) == pytest.approx(stationary, rel=4.5 * se)
    assert stationary == pytest.approx(S * wc / 2, rel=0.01)


def test_bad_parameters_are_refused():
    with pytest.raises(ParameterError, match="'sample_time' must be positive"):
        WhiteNoise("w", psd=1.0, sample_time=0.0)
    with pytest.raises(ParameterError, match="'psd' must not be negative"):
        WhiteNoise("w", psd=-1.0, sample_time=0.1)
    with pytest.raises(ParameterError, match="'psd' must be a number or 2 numbers"):
        WhiteNoise("w", n=2, psd=[1.0, 2.0, 3.0], sample_time=0.1)


def test_shipped_measurement_noise_variant_without_noise_is_the_original_diagram():
    import os
    here = os.path.join(os.path.dirname(__file__), "..", "..", "diagrams")
    short = {"t_final": 0.1}
    plain = fwdstep.simulate(fwdstep.load_diagram(os.path.join(here, "theorem3.yaml"),
                                                  overrides=short))
    quiet = fwdstep.simulate(fwdstep.load_diagram(
        os.path.join(here, "theorem3_measurement_noise.yaml"),
        overrides={**short, "noise_psd_q": 0.0, "noise_psd_qdot": 0.0}))
    # the same up to rounding (q + 0 passes through one more Sum, fused with the others)
    np.testing.assert_allclose(quiet["e.y"], plain["e.y"], rtol=1e-13, atol=1e-15)
    noisy = fwdstep.simulate(fwdstep.load_diagram(
        os.path.join(here, "theorem3_measurement_noise.yaml"), overrides=short))
    w = noisy["w_q.y"]
    assert np.std(w) == pytest.approx(math.sqrt(1e-8 / 1e-3), rel=0.25)
    assert 0 < np.max(np.abs(noisy["e.y"] - plain["e.y"])) < 0.01   # felt, not dominant


def test_a_sweep_over_the_hold_interval_equals_its_one_by_one_runs(tmp_path):
    """Variants with another Ts have other sample instants (discontinuity times): they must never
    share a batch, whose step grid would then be the union of both (differences ~1e-8)."""
    path = tmp_path / "ts.yaml"
    path.write_text("""
description: filtered noise, swept over the hold interval
parameters: {ts: 0.01}
blocks:
  w: {type: WhiteNoise, n: 1, psd: 1.0, sample_time: ts, seed: 3}
  f: {type: TransferFunction, num: [1], den: [1, 1]}
connections:
  - w.y -> f.u
simulation: {t_final: 0.5, step: 0.004, solver: rk4}
log: [f.y]
metrics: {error: f.y}
""")
    grid = {"ts": [0.01, 0.03, 0.07]}
    batched = run_sweep(str(path), grid, workers=1)
    alone = run_sweep(str(path), grid, workers=1, sequential=True)
    for a, b in zip(sorted(batched.variants, key=lambda v: v.index),
                    sorted(alone.variants, key=lambda v: v.index)):
        assert a.values == b.values
        assert a.metrics["final_error_norm"] == b.metrics["final_error_norm"]
