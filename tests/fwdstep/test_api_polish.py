"""The Python API reads well (issue 24, item 8): a Result and a Comparison print as a short
summary, a comparison's table becomes a DataFrame, ``to_xarray`` names component axes as
the diagram does (with coordinates and units), and every metric has one name everywhere."""
import csv
import os
import re

import numpy as np
import pytest

import fwdstep
from fwdstep.cli import arguments as cli
from fwdstep.results.result import METRIC_DEFINITIONS
from fwdstep.results.sweep_format import METRICS

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")


@pytest.fixture(scope="module")
def result():
    return fwdstep.simulate(fwdstep.load_diagram(THEOREM1, {"simulation.t_final": 0.5}))


def test_result_prints_its_status_time_range_and_signals(result):
    text = repr(result)
    assert str(result) == text and "object at 0x" not in text
    assert text == ("<Result ok: t = 0 .. 0.5 s, 51 samples; signals: e.y (2,), tau.y (2,), "
                    "adapt.theta_hat (4,), truth.y (4,), arm.q (2,), qd.y (2,)>")


def test_comparison_repr_is_short_and_its_table_is_a_dataframe(result):
    pd = pytest.importorskip("pandas")
    other = fwdstep.simulate(fwdstep.load_diagram(THEOREM1, {"simulation.t_final": 0.5,
                                                             "alpha": 5}))
    c = fwdstep.compare([result, other], labels=["a4", "a5"])
    text = repr(c)
    assert len(text) < 300 and "array(" not in text and text.startswith("<Comparison of 2 runs")
    frame = c.table.to_pandas()
    assert isinstance(frame, pd.DataFrame) and list(frame.index) == ["a4", "a5"]
    assert frame.loc["a5", "final_error_norm"] == pytest.approx(
        np.linalg.norm(other["e.y"][-1]), rel=1e-12)
    assert c.table[0]["run"] == "a4"                     # still the list of rows it was
    assert c.notes == []                                 # one diagram


def test_comparing_runs_of_different_diagrams_says_so(result, tmp_path, capsys):
    sine = os.path.join(ROOT, "diagrams", "theorem1_sine.yaml")
    other = fwdstep.simulate(fwdstep.load_diagram(sine, {"simulation.t_final": 0.5}))
    c = fwdstep.compare([result, other], labels=["t1", "sine"])
    (note,) = c.notes
    assert note.startswith("the runs come from different diagrams: t1 (theorem1.yaml, ")
    result.save(str(tmp_path / "a"))
    other.save(str(tmp_path / "b"))
    assert cli.main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "-o",
                     str(tmp_path / "c"), "-q"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("fwdstep: note: the runs come from different diagrams: a "
                          "(theorem1.yaml, ") and err.count("\n") == 1


def test_to_xarray_names_axes_from_the_components_with_coordinates_and_units(result):
    pytest.importorskip("xarray")
    ds = result.to_xarray()
    # theorem1.yaml: e.y, tau.y, qd.y have components [joint 1, joint 2]; arm.q from the block
    assert ds["e.y"].dims == ("time", "joint") and ds["tau.y"].dims == ("time", "joint")
    assert list(ds["joint"].values) == ["joint 1", "joint 2"]
    assert ds["e.y"].attrs["units"] == "rad" and ds["tau.y"].attrs["units"] == "N m"
    assert ds["time"].attrs["units"] == "s"
    assert ds["adapt.theta_hat"].dims == ("time", "adapt.theta_hat:0")   # unnamed components
    np.testing.assert_array_equal(ds["adapt.theta_hat:0"].values, np.arange(4))
    np.testing.assert_array_equal(ds["e.y"].sel(joint="joint 2").values, result["e.y"][:, 1])


LEGACY = ("final_abs_error", "tail_max_abs_error", "rms_error", "max_abs_error")


def test_metric_names_are_the_same_in_summary_sweep_csv_report_and_docs(result, tmp_path):
    assert set(result.metrics()) == set(METRIC_DEFINITIONS)
    assert set(METRICS) <= set(METRIC_DEFINITIONS)
    assert cli.main(["sweep", THEOREM1, "--grid", "alpha=3,4", "--set",
                     "simulation.t_final=0.2", "-o", str(tmp_path / "sw"), "-q",
                     "--workers", "1"]) == 0
    with open(tmp_path / "sw" / "sweep.csv") as fh:
        header = next(csv.reader(fh))
    assert [c for c in header if "error" in c] == list(METRICS)
    words = re.compile(r"\b(" + "|".join(LEGACY) + r")\b")
    for folder in ("docs", "examples", "fwdstep", "tests"):
        for here, _, files in os.walk(os.path.join(ROOT, folder)):
            for name in files:
                if not name.endswith((".py", ".md")) or name == "test_api_polish.py":
                    continue
                with open(os.path.join(here, name), encoding="utf-8") as fh:
                    text = fh.read()
                found = [m for m in words.findall(text)
                         if not (name == "study_robustness.py" and m == "rms_error")]
                if name == "diagram-format.md":        # names the old names once, as gone
                    found = [m for m in found if "are gone" not in text]
                assert not found, f"{name} still uses {found}"
