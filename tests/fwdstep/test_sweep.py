"""Sweeps (fwdstep.sweeps.sweep, ``fwdstep sweep``): batched variants give the one-by-one numbers.

The sweep groups variants by structure (``ell`` changes the state size: one batch per ell),
runs each group as one batch, and writes one CSV row per variant.  The batched table must
equal the ``--sequential`` table to 1e-12, including a variant that diverges (frozen in its
batch while the others continue) and one whose block raises (its batch is re-run variant by
variant, so the others still get their numbers).
"""
import csv
import os

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
from fwdstep.core.errors import ConfigError
from fwdstep.sweeps.sampling import Distribution
from fwdstep.sweeps.sweep import (METRICS, parse_grid, parse_random, run_sweep, split_values,
                           variant_values)

LOOP = """
parameters: {ell: 2, alpha: 4, gamma: 2, K: 20, q0: [0.1, -0.1]}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: q0}
  ref:   {type: ReferenceDynamics, variant: eq2, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  Ks:    {type: Gain, gain: K, shape: [2]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Yth.y -> tau.u1
  - Ks.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.5, step: 0.002, solver: rk4, log_every: 5, bound: 1e3}
log: [e.y]
metrics: {error: e.y}
"""


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "loop.yaml"
    p.write_text(LOOP)
    return str(p)


def _table(result):
    return {v.index: v for v in result.variants}


def test_batched_sweep_equals_sequential_sweep(path):
    grid = {"ell": [1, 2], "K": [20, -120, 50]}            # K = -120 diverges for ell = 2
    random = {"gamma": (0.5, 3.0)}
    batched = run_sweep(path, grid, random, samples=2, seed=7, workers=1)
    alone = run_sweep(path, grid, random, samples=2, seed=7, sequential=True, workers=1)
    assert len(batched.variants) == 12 and len(batched.batches) == 2      # one per ell
    assert len(alone.batches) == 12
    a, b = _table(batched), _table(alone)
    statuses = [v.status for v in batched.variants]
    assert statuses.count("diverged") == 2 and statuses.count("ok") == 10
    for i in a:
        assert a[i].values == b[i].values and a[i].status == b[i].status
        if a[i].status == "diverged":
            assert a[i].values["K"] == -120 and a[i].values["ell"] == 2
            assert a[i].diverged_at == pytest.approx(b[i].diverged_at, abs=1e-12)
            assert not a[i].metrics
            continue
        for m in METRICS:
            assert a[i].metrics[m] == pytest.approx(b[i].metrics[m], rel=1e-12, abs=1e-15)
    # the random samples are seeded: the same gamma pairs in every grid cell
    gammas = sorted({round(v.values["gamma"], 12) for v in batched.variants})
    assert len(gammas) == 2 and all(0.5 <= g <= 3.0 for g in gammas)


def test_cli_writes_table_and_figure(path, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["sweep", path, "--grid", "alpha=2,4", "--grid", "K=20,-300",
                     "--set", "gamma=1", "-o", str(out), "-q"])
    assert code == 3                               # a variant diverged
    with open(out / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["alpha"], r["K"]) for r in rows] == [("2", "20"), ("2", "-300"), ("4", "20"),
                                                    ("4", "-300")]
    assert [r["status"] for r in rows] == ["ok", "diverged", "ok", "diverged"]
    assert float(rows[0]["tail_error_norm_max"]) > 0 and rows[1]["tail_error_norm_max"] == ""
    assert float(rows[1]["diverged_at"]) > 0
    assert os.path.getsize(out / "sweep.png") > 10_000
    # an existing table is not overwritten without --force
    code = cli.main(["sweep", path, "--grid", "alpha=2,4", "-o", str(out), "-q"])
    assert code == 2 and "already exists" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=2,4", "-o", str(out), "-q",
                     "--force"]) == 0


def test_a_raising_variant_does_not_spoil_its_batch(path, monkeypatch):
    """A block that raises for one variant only: the batch is re-run variant by variant."""
    from fwdstep.blocks.adaptation import AdaptationLaw
    original = AdaptationLaw.derivative

    def fragile(self, t, x, u):
        if np.any(self.p.gamma == 5.0) and t > 0.1:
            raise ZeroDivisionError("broken adaptation")
        return original(self, t, x, u)

    monkeypatch.setattr(AdaptationLaw, "derivative", fragile)
    result = run_sweep(path, {"gamma": [2, 5, 3]}, workers=1)
    assert [v.status for v in result.variants] == ["ok", "error", "ok"]
    assert "broken adaptation" in result.variants[1].message
    assert all(result.variants[i].metrics for i in (0, 2))


def test_bad_options_are_one_line_errors(path, tmp_path, capsys):
    out = str(tmp_path / "o")
    assert cli.main(["sweep", path, "--grid", "kappa=1,2", "-o", out]) == 2
    assert "no parameter 'kappa'" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--random", "alpha=1:x", "--samples", "2", "-o", out]) == 2
    assert "NAME=LOW:HIGH" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--random", "alpha=1:3", "-o", out]) == 2
    assert "--samples" in capsys.readouterr().err
    assert cli.main(["sweep", path, "-o", out]) == 2
    assert "nothing to sweep" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=1", "--set", "alpha=2", "-o", out]) == 2
    assert "both swept and set" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "alpha=-1", "-o", out]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fwdstep: ") and "variant alpha=-1" in err and "\n" == err[-1]
    assert not os.path.exists(out)


def test_value_parsing():
    assert split_values("1, 2,[3, 4],diag([1,2])") == ["1", "2", "[3, 4]", "diag([1,2])"]
    assert parse_grid(["ell=1,2", "K=20*eye(2),[[1,0],[0,1]]"]) == {
        "ell": [1, 2], "K": ["20*eye(2)", [[1, 0], [0, 1]]]}
    assert parse_random(["a=1:2.5"]) == {"a": Distribution("uniform", 1.0, 2.5)}
    with pytest.raises(ConfigError, match="LOW must not exceed HIGH"):
        parse_random(["a=3:1"])
    values = variant_values({"a": [1, 2, 3]}, {"b": (0.0, 1.0)}, samples=4, seed=3)
    assert len(values) == 12 and values == variant_values({"a": [1, 2, 3]}, {"b": (0.0, 1.0)},
                                                          samples=4, seed=3)
    assert [v["a"] for v in values[:5]] == [1, 1, 1, 1, 2]
    with pytest.raises(ConfigError, match="both in --grid and --random"):
        variant_values({"a": [1]}, {"a": (0.0, 1.0)}, samples=1, seed=0)


# ---------------------------------------------------------------------------- exactness
EVERY_KIND = """
parameters:
  ell: 2                   # int, changes the state size
  alpha: 4                 # float
  gamma: 2                 # float
  K: 20*eye(2)             # array
  q0: [0.1, -0.1]          # array (initial state)
  nseed: 3                 # int, stacked (noise seed per variant)
  npsd: 1e-6               # array
  lv: -0.5                 # array entry
  M: [[0.1, 0.3], [0.0, 0.2]]
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: q0}
  ref:   {type: ReferenceDynamics, variant: eq2, ell: ell, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  Ks:    {type: Gain, gain: K}
  lut:   {type: Lookup1D, breakpoints: [-0.2, 0, 0.2], values: [lv, 0, 0.4],
          extrapolation: clamp, n: 2}
  M:     {type: Constant, value: M}
  P:     {type: Product, a_shape: [2, 2], b_shape: [2], transpose_a: false}
  noise: {type: WhiteNoise, n: 2, psd: npsd, sample_time: 0.01, seed: nseed}
  tau:   {type: Sum, signs: "+-++", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
connections:
  - arm.q -> ref.q, Y.q, e.u1, lut.u
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - M.y -> P.a
  - lut.y -> P.b
  - Yth.y -> tau.u1
  - Ks.y -> tau.u2
  - P.y -> tau.u3
  - noise.y -> tau.u4
  - tau.y -> arm.tau
simulation: {t_final: 0.4, step: 0.002, solver: rk4, log_every: 2, bound: 1e3}
log: [e.y]
metrics: {error: e.y}
"""

# every simulation setting and every kind of block parameter, each next to variants that
# differ from it in that one setting only; K = -150 diverges (beside ones that do not)
EVERY_VARIANT = [
    {},
    {"K": "-150*eye(2)"},
    {"simulation.t_final": 0.3},
    {"simulation.step": 0.004},
    {"simulation.solver": "heun"},
    {"simulation.log_every": 5},
    {"simulation.bound": 0.3},
    {"ell": 1},
    {"ref.kappa": 2.0},              # a block parameter set by its path
    {"alpha": 3.0},
    {"gamma": 0.5},
    {"K": "35*eye(2)"},
    {"q0": [0.15, 0.05]},
    {"tau.signs": "+--+"},           # str, stacked (Sum keeps signs per variant)
    {"P.transpose_a": True},         # bool, stacked (Product keeps transposes per variant)
    {"lut.extrapolation": "linear"},  # choice, not stacked
    {"nseed": 11},
    {"npsd": 4e-6},
    {"lv": -0.1},
    {"M": [[0.0, 0.3], [0.2, 0.2]]},
    {"K": "-150*eye(2)", "simulation.bound": 50.0},
]


def _every_variant(path):
    """EVERY_VARIANT, plus an adaptive solver when this fwdstep has one."""
    from fwdstep.core.errors import ConfigError
    from fwdstep.structure.spec import load_spec
    out = list(EVERY_VARIANT)
    try:
        load_spec(path, {"simulation.solver": "dop853"})
        out.append({"simulation.solver": "dop853"})
    except ConfigError:
        pass
    return out


def _alone(path, values):
    import fwdstep
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.core.errors import DivergenceError
    from fwdstep.structure.spec import load_spec
    d = compile_spec(load_spec(path, values))
    d.logged = [d.resolve("e.y")]
    try:
        return fwdstep.simulate(d)
    except DivergenceError as exc:
        return exc.result


def test_every_variant_gets_its_own_numbers(tmp_path):
    """Item 1 of issue 13: a batch never mixes variants that differ in anything that changes
    the numbers.  Each variant's error signal and metrics equal its own one-by-one run."""
    path = tmp_path / "every.yaml"
    path.write_text(EVERY_KIND)
    every = _every_variant(str(path))
    result = run_sweep(str(path), variants=every, workers=1)
    signals = {}
    for part in result.parts:
        for k, i in enumerate(part["indices"]):
            signals[int(i)] = (part["t"], part["e"][:, k])
    assert len(result.batches) < len(every)          # some variants did share a batch
    statuses = {}
    for v in result.variants:
        alone = _alone(str(path), every[v.index])
        statuses[v.index] = v.status
        t, e = signals[v.index]
        rows = len(alone.t)
        np.testing.assert_array_equal(t[:rows], alone.t, err_msg=str(v.values))
        ref = alone["e.y"]
        scale = max(1.0, float(np.nanmax(np.abs(ref))))
        np.testing.assert_allclose(e[:rows], ref, rtol=0, atol=1e-12 * scale,
                                   err_msg=str(v.values))
        assert np.all(np.isnan(e[rows:])), v.values       # nothing after the end of its run
        if alone.status == "ok":
            assert v.status == "ok", v.values
            own = alone.metrics()
            for m in METRICS:
                assert v.metrics[m] == pytest.approx(own[m], rel=1e-12, abs=1e-15), (v.values, m)
        else:
            assert v.status == "diverged" and alone.status == "diverged", v.values
            assert v.diverged_at == pytest.approx(float(alone.diverged_at[0]), abs=1e-12)
    assert statuses[1] == "diverged" and statuses[0] == "ok" and statuses[6] == "diverged"
    assert statuses[20] == "diverged"
    # the settings really changed the runs (a sweep that ignored them would fail above)
    assert len(signals[2][0]) < len(signals[0][0]) and len(signals[5][0]) < len(signals[0][0])


def test_the_reported_examples(capsys, tmp_path):
    """The two commands of the issue: t_final and step now change the numbers."""
    out = tmp_path / "a"
    assert cli.main(["sweep", "diagrams/theorem1.yaml", "--grid", "t_final=1,2", "-o",
                     str(out), "-q", "--no-signals", "--set", "step=0.004"]) == 0
    with open(out / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rows[0]["final_error_norm"] != rows[1]["final_error_norm"]
    out = tmp_path / "b"
    assert cli.main(["sweep", "diagrams/theorem1.yaml", "--grid", "step=0.002,0.05", "-o",
                     str(out), "-q", "--set", "t_final=0.5"]) == 3
    with open(out / "sweep.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["ok", "diverged"]
    assert float(rows[1]["diverged_at"]) == pytest.approx(0.1)


def test_unbatchable_settings_run_one_variant_per_batch(path):
    """An adaptive solver picks one step sequence per run: such variants are never batched.
    The compiled backend batches (run_batch), but never with NumPy-backend variants."""
    from fwdstep.structure.compiler import instantiate_variants
    from fwdstep.structure.spec import load_spec
    from fwdstep.sweeps.sweep import plan_batches
    specs = [load_spec(path, {"K": k, "simulation.backend": b})
             for k in (10, 20, 30) for b in ("numpy", "compiled")]
    specs += [load_spec(path, {"K": k, "simulation.solver": "dop853"}) for k in (10, 20)]
    batches = plan_batches(specs, instantiate_variants(specs), "e.y")
    assert sorted(batches) == [[0, 2, 4], [1, 3, 5], [6], [7]]


@pytest.mark.slow
def test_compiled_sweep_equals_one_by_one_compiled_runs():
    """``--backend compiled``: a batch runs through the compiled backend's batched loop
    (``CompiledProgram.run_batch``); each variant equals its own compiled run (1e-12),
    including variants with another step (a separate batch).  Compiles numba code."""
    pytest.importorskip("numba")
    from fwdstep.structure.compiler import compile_spec
    from fwdstep.structure.spec import load_spec
    from fwdstep.run.simulate import simulate
    path = "diagrams/slotine_li.yaml"
    result = run_sweep(path, grid={"Lambda": [2.0, 5.0, 9.0],
                                   "simulation.step": [0.001, 0.002]},
                       overrides={"t_final": 0.5}, backend="compiled")
    assert len(result.batches) == 2 and result.counts() == {"ok": 6}
    signals = {}
    for part in result.parts:
        for k, i in enumerate(part["indices"]):
            signals[int(i)] = (part["t"], part["e"][:, k])
    for v in result.variants:
        alone = simulate(compile_spec(load_spec(path, {"t_final": 0.5, **v.values,
                                                       "simulation.backend": "compiled"})))
        t, e = signals[v.index]
        np.testing.assert_array_equal(t, alone.t)
        np.testing.assert_allclose(e, alone["e.y"], rtol=0, atol=1e-12, err_msg=str(v.values))
        own = alone.metrics()
        for m in METRICS:
            assert v.metrics[m] == pytest.approx(own[m], rel=1e-12, abs=1e-15), (v.values, m)


def test_backend_compiled_without_numba_is_one_line(path, tmp_path, monkeypatch, capsys):
    import sys
    monkeypatch.setitem(sys.modules, "numba", None)          # import numba -> ImportError
    code = cli.main(["sweep", path, "--grid", "K=10,20", "--backend", "compiled", "-q",
                     "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert err.endswith("backend 'compiled' needs numba: pip install 'fwdstep[fast]' (or use "
                        "--backend numpy)")
    with pytest.raises(ConfigError, match="both swept and set"):
        run_sweep(path, grid={"simulation.backend": ["numpy"]}, backend="numpy")


def test_batch_metrics_are_each_variants_own():
    """A sweep computes the metrics of a whole batch at once (fwdstep.results.result.
    batch_error_metrics): each variant's numbers are bit for bit those of its own
    error_metrics call (the sums run over its own row of the batch), and error_metrics
    agrees with the definitions computed plainly; NaN, inf and near-overflow errors too."""
    from fwdstep.results.result import batch_error_metrics, error_metrics
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.random(1001))
    e = rng.standard_normal((1001, 7, 2)) * 10.0 ** rng.integers(-5, 5, size=(1, 7, 1))
    e[400:, 1] = np.nan                          # diverged
    e[17, 2, 0] = np.inf
    e[:, 3] = 1e308                              # a naive sum of squares overflows
    batch = batch_error_metrics(t, e, 0.3)
    for b in range(7):
        alone = error_metrics(t, np.ascontiguousarray(e[:, b]), 0.3)
        assert repr(batch[b]) == repr(alone)     # bit for bit (floats repr exactly)
    norm = np.sqrt(np.sum(e[:, 0] ** 2, axis=1))
    tail = t >= t[0] + 0.7 * (t[-1] - t[0])
    np.testing.assert_allclose(
        [batch[0][k] for k in ("final_error_norm", "tail_error_norm_max", "rms_error_norm",
                               "error_norm_max", "tail_error_max_abs")],
        [norm[-1], norm[tail].max(), np.sqrt(np.mean(norm ** 2)), norm.max(),
         np.abs(e[tail, 0]).max()], rtol=1e-14)
    assert np.isnan(batch[1]["rms_error_norm"]) and batch[2]["error_norm_max"] == np.inf
    assert batch[3]["final_error_norm"] == pytest.approx(1e308 * np.sqrt(2), rel=1e-14)


def test_an_integer_axis_has_integer_ticks_and_many_traces_a_short_legend(path):
    from fwdstep.results.plotting import MAX_LEGEND_ENTRIES
    from fwdstep.sweeps.sweep import sweep_figure
    result = run_sweep(path, {"ell": [1, 2, 3, 4, 5], "gamma": [1.5, 2.5, 3, 4]}, workers=1)
    assert len(result.variants) == 20
    fig = sweep_figure(result)
    fig.canvas.draw()
    ell_ax, gamma_ax, traces = fig.axes[:3]
    assert ell_ax.get_xlabel() == "ell"
    lo, hi = ell_ax.get_xlim()
    shown = [v for v in ell_ax.get_xticks() if lo <= v <= hi]
    assert shown == [1, 2, 3, 4, 5]                  # not 1.0, 1.5, ..., 5.0
    # gamma takes 1.5: its axis is not forced to whole numbers
    lo, hi = gamma_ax.get_xlim()
    assert any(not float(v).is_integer() for v in gamma_ax.get_xticks() if lo <= v <= hi)
    for ax in fig.axes:
        legend = ax.get_legend()
        assert legend is None or len(legend.get_texts()) <= MAX_LEGEND_ENTRIES


def test_the_garbage_collector_is_left_as_it_was(path):
    """A sweep pauses Python's collector while it derives the variants and freezes them
    while the batches run (fwdstep.sweeps.sweep._CollectorSpared); afterwards, after a
    refused variant too, the collector is as the caller had it: on or off, and with the
    caller's own frozen objects still frozen."""
    import gc
    from fwdstep.errors import DiagramError
    assert gc.isenabled() and gc.get_freeze_count() == 0
    seen = []
    run_sweep(path, {"gamma": [1, 2]}, workers=1,
              progress=lambda *a, **k: seen.append((gc.isenabled(), gc.get_freeze_count())))
    assert seen and all(on and frozen > 0 for on, frozen in seen)   # frozen while running
    assert gc.isenabled() and gc.get_freeze_count() == 0
    with pytest.raises(DiagramError):
        run_sweep(path, {"ell": [2, -1]}, workers=1)                 # a refused variant
    assert gc.isenabled() and gc.get_freeze_count() == 0
    gc.disable()
    try:
        run_sweep(path, {"gamma": [1, 2]}, workers=1)
        assert not gc.isenabled()
    finally:
        gc.enable()
    gc.freeze()
    try:
        mine = gc.get_freeze_count()        # (a few frozen objects may be freed meanwhile)
        run_sweep(path, {"gamma": [1, 2]}, workers=1)
        assert gc.get_freeze_count() > mine // 2                     # not released
    finally:
        gc.unfreeze()


def test_a_signal_while_a_batch_is_written_keeps_that_batch(path, tmp_path, monkeypatch):
    """SIGTERM arriving while a finished batch's part is written (inside np.savez): the
    part is written whole and counted, then the sweep ends as interrupted (it broke the zip
    file being written and ended ``fwdstep sweep`` with a traceback, exit 1)."""
    import glob
    import os
    import signal
    from fwdstep.core import signals
    real, calls = np.savez, []

    def savez(fh, **part):
        calls.append(1)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)     # delivered here, mid-write
        return real(fh, **part)

    monkeypatch.setattr(np, "savez", savez)
    out = str(tmp_path / "o")
    with signals.handled():
        result = run_sweep(path, {"K": [20, 30, 40]}, workers=1, batch_size=1, outdir=out)
    assert result.interrupted and result.signal_number == signal.SIGTERM
    assert [v.status for v in result.variants] == ["ok", "interrupted", "interrupted"]
    assert len(result.batches) == 1
    assert len(glob.glob(os.path.join(out, "parts", "*.npz"))) == 1
