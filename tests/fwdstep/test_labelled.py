"""Labelled results (fwdstep.results.labelled): a sweep as an xarray Dataset (variant x time x
component, swept parameters as coordinates) equal to each variant's own run, saved as
NetCDF and loaded back unchanged; a single Result as Dataset and DataFrame."""
import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.structure.compiler import compile_spec
from fwdstep.core.errors import DivergenceError
from fwdstep.structure.spec import load_spec
from fwdstep.sweeps.sweep import run_sweep

xr = pytest.importorskip("xarray")

LOOP = """
parameters: {K: 20, q0: [0.1, -0.1]}
blocks:
  qd:  {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5]}
  arm: {type: TwoLinkArm, q0: q0}
  e:   {type: Sum, signs: "+-", shape: [2]}
  Ks:  {type: Gain, gain: K, shape: [2]}
  d:   {type: Gain, gain: 5, shape: [2]}
  tau: {type: Sum, signs: "--", shape: [2]}
connections:
  - arm.q -> e.u1
  - qd.y -> e.u2
  - e.y -> Ks.u
  - arm.qdot -> d.u
  - Ks.y -> tau.u1
  - d.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.2, step: 0.002, solver: rk4, log_every: 5, bound: 1e3}
log: [e.y, tau.y]
metrics: {error: e.y}
"""


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "pd.yaml"
    p.write_text(LOOP)
    return str(p)


def _alone(path, values):
    try:
        return fwdstep.simulate(compile_spec(load_spec(path, values)))
    except DivergenceError as exc:
        return exc.result


def test_sweep_dataset_equals_each_variants_own_run(path, tmp_path):
    grid = {"K": [10.0, 40.0], "simulation.log_every": [5, 2]}
    result = run_sweep(path, grid, workers=1)
    ds = result.to_xarray()
    assert ds["error"].dims == ("variant", "time", "component")
    assert ds.sizes["variant"] == 4 and ds.sizes["component"] == 2
    assert list(ds["K"].values) == [10, 10, 40, 40]
    assert list(ds["simulation.log_every"].values) == [5, 2, 5, 2]
    # log_every 2 and 5: the union of both time grids
    assert ds.sizes["time"] == len(np.union1d(np.arange(0, 101, 5), np.arange(0, 101, 2)))
    assert ds.attrs["diagram"] == path
    for v in result.variants:
        alone = _alone(path, v.values)
        got = ds["error"].sel(variant=v.index).sel(time=alone.t)
        np.testing.assert_allclose(got.values, alone["e.y"], rtol=0, atol=1e-12)
        assert float(ds["final_error_norm"].sel(variant=v.index)) == pytest.approx(
            alone.metrics()["final_error_norm"], rel=1e-12)
        # the times this variant did not sample are missing, not zero
        others = np.setdiff1d(ds["time"].values, alone.t)
        assert np.isnan(ds["error"].sel(variant=v.index).sel(time=others).values).all()
    table = result.to_pandas()
    assert table.loc[3, "K"] == 40.0 and table.loc[3, "status"] == "ok"


def test_netcdf_round_trip_through_the_cli(path, tmp_path):
    from fwdstep.results.labelled import load_sweep
    out = tmp_path / "out"
    assert cli.main(["sweep", path, "--grid", "K=10,-2000", "--netcdf", "--workers", "1",
                     "-o", str(out), "-q"]) == 3
    table, ds = load_sweep(str(out))
    assert list(table["status"]) == ["ok", "diverged"]
    assert list(ds["status"].values) == ["ok", "diverged"]
    alone = _alone(path, {"K": 10})
    np.testing.assert_allclose(ds["error"].sel(variant=0).values, alone["e.y"], atol=1e-12)
    died = float(ds["diverged_at"].sel(variant=1))
    after = ds["error"].sel(variant=1).sel(time=slice(died, None)).values
    assert died < 0.2 and np.isnan(after).all()


def test_result_as_dataset_and_frame(path):
    r = fwdstep.simulate(compile_spec(load_spec(path)))
    ds = r.to_xarray()
    np.testing.assert_array_equal(ds["e.y"].values, r["e.y"])
    assert ds["e.y"].dims == ("time", "e.y:0") and ds.attrs["status"] == "ok"
    frame = r.to_pandas()
    np.testing.assert_array_equal(frame["tau.y[1]"].values, r["tau.y"][:, 1])
    np.testing.assert_array_equal(frame.index.values, r.t)
