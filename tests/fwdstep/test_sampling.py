"""Sampling designs (fwdstep.sweeps.sampling): each design has the property that defines it, the
distributions have their moments and bounds, the same seed gives the same variants, and
--seed-parameter gives each variant its own noise (equal to its own one-by-one run)."""
import numpy as np
import pytest
from scipy import stats

from fwdstep.cli import arguments as cli
from fwdstep.core.errors import ConfigError
from fwdstep.sweeps.sampling import Distribution, parse_random, unit_points, variant_values


def test_latin_hypercube_puts_one_point_in_every_stratum():
    n = 50
    u = unit_points(n, 3, "lhs", seed=4)
    for axis in range(3):
        strata = np.floor(u[:, axis] * n).astype(int)
        assert sorted(strata) == list(range(n))


def test_sobol_is_more_uniform_than_independent_draws():
    n = 256
    sobol = unit_points(n, 2, "sobol", seed=1)
    draws = unit_points(n, 2, "random", seed=1)
    from scipy.stats import qmc
    assert qmc.discrepancy(sobol) < 0.2 * qmc.discrepancy(draws)
    # a scrambled Sobol set of 2^8 points has exactly one point in every 1/16 x 1/16 cell
    cells = np.floor(sobol * 16).astype(int)
    assert len({tuple(c) for c in cells}) == 256


def test_distributions_have_their_moments_and_bounds():
    values = variant_values({}, parse_random(["m=normal:2:0.5", "k=loguniform:1:100",
                                              "a=3:4"]), samples=4000, seed=0, design="lhs")
    m = np.array([v["m"] for v in values])
    k = np.array([v["k"] for v in values])
    a = np.array([v["a"] for v in values])
    assert abs(m.mean() - 2) < 0.01 and abs(m.std() - 0.5) < 0.01
    assert stats.kstest(m, "norm", args=(2, 0.5)).pvalue > 0.05
    assert k.min() >= 1 and k.max() <= 100
    assert stats.kstest(np.log10(k), "uniform", args=(0, 2)).pvalue > 0.05   # log-uniform
    assert 3 <= a.min() and a.max() <= 4


def test_seeded_and_reproducible():
    random = {"a": Distribution("uniform", 0, 1), "b": (2.0, 3.0)}   # (low, high) also works
    for design in ("random", "lhs", "sobol"):
        one = variant_values({"g": [1, 2]}, random, samples=8, seed=5, design=design)
        assert one == variant_values({"g": [1, 2]}, random, samples=8, seed=5, design=design)
        assert one != variant_values({"g": [1, 2]}, random, samples=8, seed=6, design=design)
        assert [v["a"] for v in one[:8]] == [v["a"] for v in one[8:]]   # same draws per cell


def test_bad_distributions_are_one_line_errors():
    for text, message in (("a=normal:1:-1", "SD must not be negative"),
                          ("a=loguniform:0:1", "0 < LOW"),
                          ("a=beta:1:2", "NAME=loguniform:LOW:HIGH"),
                          ("a=1:2:3:4", "NAME=LOW:HIGH")):
        with pytest.raises(ConfigError, match=message):
            parse_random([text])
    with pytest.raises(ConfigError, match="designs are: random, lhs, sobol"):
        unit_points(4, 1, "halton", 0)


NOISY = """
parameters: {noise_seed: 0, K: 20}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5]}
  arm:   {type: TwoLinkArm}
  e:     {type: Sum, signs: "+-", shape: [2]}
  Ks:    {type: Gain, gain: K, shape: [2]}
  d:     {type: Gain, gain: 5, shape: [2]}
  noise: {type: WhiteNoise, n: 2, psd: [1e-3, 1e-3], sample_time: 0.01, seed: noise_seed}
  tau:   {type: Sum, signs: "--+", shape: [2]}
connections:
  - arm.q -> e.u1
  - qd.y -> e.u2
  - e.y -> Ks.u
  - arm.qdot -> d.u
  - Ks.y -> tau.u1
  - d.y -> tau.u2
  - noise.y -> tau.u3
  - tau.y -> arm.tau
simulation: {t_final: 0.3, step: 0.002, solver: rk4, log_every: 5}
log: [e.y]
metrics: {error: e.y}
"""


def test_each_variant_gets_its_own_seed(tmp_path):
    import fwdstep
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.structure.spec import load_spec
    from fwdstep.sweeps.sweep import run_sweep
    path = tmp_path / "noisy.yaml"
    path.write_text(NOISY)
    result = run_sweep(str(path), {"K": [20, 30]}, seed=9, seed_parameter="noise_seed",
                       workers=1)
    seeds = [v.values["noise_seed"] for v in result.variants]
    assert len(set(seeds)) == 2 and result.names == ["K", "noise_seed"]
    assert len(result.batches) == 1                  # the seed is stacked: still one batch
    part = result.parts[0]
    for k, i in enumerate(part["indices"]):
        values = result.variants[int(i)].values
        alone = fwdstep.simulate(compile_spec(load_spec(str(path), values)))
        np.testing.assert_allclose(part["e"][:, k], alone["e.y"], rtol=0, atol=1e-12)
    # the same seed gives the same variant seeds
    again = run_sweep(str(path), {"K": [20, 30]}, seed=9, seed_parameter="noise_seed",
                      workers=1)
    assert [v.values["noise_seed"] for v in again.variants] == seeds


def test_cli_design_options(tmp_path, capsys):
    path = tmp_path / "noisy.yaml"
    path.write_text(NOISY)
    out = tmp_path / "o"
    assert cli.main(["sweep", str(path), "--random", "K=loguniform:10:40", "--samples", "4",
                     "--design", "lhs", "--workers", "1", "-o", str(out), "-q"]) == 0
    text = (out / "sweep.csv").read_text().splitlines()
    ks = sorted(float(line.split(",")[1]) for line in text[1:])
    assert len(ks) == 4 and all(10 <= k <= 40 for k in ks)
    strata = [int(np.floor(4 * np.log(k / 10) / np.log(4))) for k in ks]   # LHS in log(K)
    assert strata == [0, 1, 2, 3]
    assert cli.main(["sweep", str(path), "--random", "K=1:2", "--samples", "2", "--design",
                     "grid", "-o", str(out)]) == 2
    assert "invalid choice: 'grid'" in capsys.readouterr().err
