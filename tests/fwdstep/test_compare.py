"""fwdstep compare: differences against the analytic solution, other time grids, batches,
the metrics table, and the command's files and refusals."""
import csv

import numpy as np
import pytest

import fwdstep
from fwdstep.cli.arguments import main
from fwdstep.views.compare import compare
from fwdstep.core.errors import OutputError
from fwdstep.results.result import load_result
from fwdstep.structure.spec import load_spec

DECAY = """
parameters: {{g: -1.0}}
blocks:
  x: {{type: Integrator, shape: [2], initial: [1.0, -2.0]}}
  k: {{type: Gain, gain: g, shape: [2]}}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {{t_final: {t_final}, step: {step}}}
log:
  - {{signal: x.y, label: '$x$', unit: m, components: [first, second]}}
plots:
  decay: [x.y]
metrics: {{error: x.y}}
"""
X0 = np.array([1.0, -2.0])


def _saved(tmp_path, name, g, t_final=2, step=0.01):
    path = tmp_path / f"{name}.yaml"
    path.write_text(DECAY.format(t_final=t_final, step=step))
    out = tmp_path / name
    assert main(["run", str(path), "--set", f"g={g}", "-o", str(out), "-q", "--no-plots"]) == 0
    return str(out), None


def test_difference_matches_the_analytic_solutions(tmp_path):
    a, _ = _saved(tmp_path, "a", -1.0)
    b, _ = _saved(tmp_path, "b", -2.0)
    c = compare([a, b])
    assert c.signals == ["x.y"]
    t = load_result(a).t
    exact = np.outer(np.exp(-2 * t) - np.exp(-t), X0)
    assert np.max(np.abs(c.differences["x.y"][0] - exact)) < 1e-8
    row_b = c.table[1]
    assert row_b["run"] == "b" and row_b["status"] == "ok"
    assert row_b["max |diff x.y|"] == pytest.approx(np.max(np.abs(exact)), rel=1e-6)
    assert row_b["final_error_norm"] == pytest.approx(np.linalg.norm(X0) * np.exp(-4), rel=1e-6)
    # the figure: overlay then difference, named by the labels of the diagram
    over, diff = c.figure.axes[:2]
    assert over.get_ylabel() == "$x$ [m]" and diff.get_ylabel() == "Δ $x$ [m]"
    assert [t.get_text() for t in diff.get_legend().get_texts()] == ["b − a, first",
                                                                   "b − a, second"]


def test_other_time_grids_are_interpolated_never_extrapolated(tmp_path):
    a, _ = _saved(tmp_path, "a", -1.0, t_final=2, step=0.01)
    b, _ = _saved(tmp_path, "b", -1.0, t_final=1, step=0.005)
    d = compare([a, b]).differences["x.y"][0]
    t = load_result(a).t
    inside = t <= 1.0 + 1e-12
    # same dynamics: only the interpolation error of a smooth curve (h = 0.005) is left
    assert np.max(np.abs(d[inside])) < 1e-4
    assert np.isnan(d[~inside]).all()


def test_batch_variants_compare_as_runs(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DECAY.format(t_final=1, step=0.01))
    specs = [load_spec(str(path), {"g": g}) for g in (-1.0, -3.0)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    out = tmp_path / "batch"
    out.mkdir()
    r.write_files(str(out))
    c = compare([str(out)])
    assert [run.label for run in c.runs] == ["batch@0", "batch@1"]
    t = r.t
    exact = np.outer(np.exp(-3 * t) - np.exp(-t), X0)
    assert np.max(np.abs(c.differences["x.y"][0] - exact)) < 1e-7
    one = compare([f"{out}@1", f"{out}@0"])
    assert np.allclose(one.differences["x.y"][0], -c.differences["x.y"][0])


def test_compare_command_writes_table_and_figure(tmp_path, capsys):
    a, _ = _saved(tmp_path, "a", -1.0)
    b, _ = _saved(tmp_path, "b", -2.0)
    out = tmp_path / "cmp"
    capsys.readouterr()
    assert main(["compare", a, b, "-o", str(out), "--figure-format", "svg"]) == 0
    rows = list(csv.DictReader(open(out / "compare.csv")))
    assert [r["run"] for r in rows] == ["a", "b"]
    assert float(rows[0]["max |diff x.y|"]) == 0.0
    assert b"<svg" in (out / "compare.svg").read_bytes()[:2000]
    assert "wrote" in capsys.readouterr().out
    # a compare.csv that fwdstep did not write is never replaced
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "compare.csv").write_text("mine")
    assert main(["compare", a, b, "-o", str(foreign)]) == 2
    assert (foreign / "compare.csv").read_text() == "mine"
    assert "fwdstep did not write" in capsys.readouterr().err


def test_compare_refusals(tmp_path, capsys):
    a, _ = _saved(tmp_path, "a", -1.0)
    assert main(["compare", a]) == 2
    assert capsys.readouterr().err == ("fwdstep: compare needs at least two runs (or a batch "
                                       "with two variants)\n")
    assert main(["compare", a, str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fwdstep: {tmp_path / 'nothing'} holds no saved run") and \
        err.count("\n") == 1
    with pytest.raises(OutputError) as info:
        compare([a, a], signals=["k.z"])
    assert str(info.value).startswith("signal k.z is not in a (1); its signals are: ")


def test_a_loaded_result_plots_like_the_fresh_one(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DECAY.format(t_final=1, step=0.01))
    fresh = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    fresh.save(str(tmp_path / "run"))
    back = fwdstep.load_result(str(tmp_path / "run"))
    assert np.array_equal(back["x.y"], fresh["x.y"]) and np.array_equal(back.t, fresh.t)
    m_back, m_fresh = back.metrics(), fresh.metrics()
    assert sorted(m_back) == sorted(m_fresh)
    for key in m_fresh:                   # (approx() refuses lists inside a dict from pytest 9.2)
        np.testing.assert_allclose(m_back[key], m_fresh[key], rtol=1e-12, err_msg=key)
    a, b = fresh.plot(figure="decay"), back.plot(figure="decay")
    assert a.axes[0].get_ylabel() == b.axes[0].get_ylabel() == "$x$ [m]"
    assert [t.get_text() for t in b.axes[0].get_legend().get_texts()] == ["first", "second"]
    assert np.array_equal(b.axes[0].lines[1].get_ydata(), fresh["x.y"][:, 1])
    page = back._repr_html_()
    assert "<table>" in page and "ok" in page and f"{fresh.metrics()['final_error_norm']:.3e}" in page


def test_sweep_variants_compare_by_their_real_names_and_equal_a_run(tmp_path, capsys,
                                                                   monkeypatch):
    """A sweep directory's variants (SWEEP@k) overlay under the signal's real name, label and
    unit; variant g = -2 equals a separate run with g = -2; differences are analytic."""
    import fwdstep.results.plotting
    path = tmp_path / "decay.yaml"
    path.write_text(DECAY.format(t_final=2, step=0.01))
    sweep = tmp_path / "sweep"
    figures = []
    real_bytes = fwdstep.results.plotting.figure_bytes
    monkeypatch.setattr(fwdstep.results.plotting, "figure_bytes",
                        lambda fig, fmt="png": figures.append(fig) or real_bytes(fig, fmt))
    assert main(["sweep", str(path), "--grid", "g=-1,-2", "-o", str(sweep), "-q",
                 "--workers", "1"]) == 0
    # the sweep figure names the error by the diagram's label and unit, not |x.y|
    (metric_ax, trace_ax) = figures[-1].axes[:2]
    assert metric_ax.get_ylabel() == "|$x$| [m]" and trace_ax.get_ylabel() == "|$x$|(t) [m]"
    b, _ = _saved(tmp_path, "b", -2.0)
    c = compare([f"{sweep}@0,1", b])
    assert c.signals == ["x.y"]
    assert [r.label for r in c.runs] == ["sweep@0 (g=-1)", "sweep@1 (g=-2)", "b"]
    t = c.runs[0].result.t
    exact = np.outer(np.exp(-2 * t) - np.exp(-t), X0)
    assert np.max(np.abs(c.differences["x.y"][0] - exact)) < 1e-8
    assert np.max(np.abs(c.differences["x.y"][1] - exact)) < 1e-8
    assert np.array_equal(c.runs[1].data("x.y"), load_result(b)["x.y"])   # the same numbers
    over, diff = c.figure.axes[:2]
    assert over.get_ylabel() == "$x$ [m]"
    assert [t_.get_text() for t_ in diff.get_legend().get_texts()][:2] == [
        "sweep@1 (g=-2) − sweep@0 (g=-1), first", "sweep@1 (g=-2) − sweep@0 (g=-1), second"]
    assert c.table[1]["final_error_norm"] == pytest.approx(np.linalg.norm(X0) * np.exp(-4),
                                                          rel=1e-6)
    # the whole sweep directory: every variant; a variant that is not there: one line, exit 2
    assert [r.label for r in compare([str(sweep)]).runs] == ["sweep@0 (g=-1)", "sweep@1 (g=-2)"]
    capsys.readouterr()
    assert main(["compare", f"{sweep}@0,5", "-o", str(tmp_path / "cmp")]) == 2
    assert capsys.readouterr().err == (f"fwdstep: {sweep} has no finished variant 5; its "
                                       "variants are 0..1\n")
    assert main(["compare", f"{sweep}@0,x"]) == 2
    assert capsys.readouterr().err == (f"fwdstep: '{sweep}@0,x': after '@' come variant "
                                       f"numbers, e.g. {sweep}@3 or {sweep}@3,7\n")


# ------------------------------------------------------------------ units
def _in_unit(tmp_path, name, unit, scale):
    """The decay x(t) = exp(-t) x0 recorded in ``unit``, its values x0 * scale."""
    text = DECAY.format(t_final=2, step=0.01).replace("unit: m", f"unit: '{unit}'").replace(
        "initial: [1.0, -2.0]", f"initial: [{scale!r}, {-2 * scale!r}]")
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    out = tmp_path / name
    assert main(["run", str(path), "-o", str(out), "-q", "--no-plots"]) == 0
    return str(out)


@pytest.mark.parametrize("unit, scale", [("deg", 180 / np.pi), ("mrad", 1e3),
                                         ("rad s$^{-1}$ s", 1.0)])
def test_a_signal_in_another_unit_is_converted_before_the_difference(tmp_path, unit, scale):
    """The same motion in rad and in deg: their difference is zero, not 57 x the motion."""
    a = _in_unit(tmp_path, "rad_run", "rad", 1.0)
    b = _in_unit(tmp_path, "deg_run", unit, scale)
    c = compare([a, b])
    assert np.max(np.abs(c.differences["x.y"][0])) < 1e-12
    assert c.table[1]["max |diff x.y|"] < 1e-12
    over = c.figure.axes[0]
    assert over.get_ylabel() == "$x$ [rad]"
    if unit != "rad s$^{-1}$ s":
        assert any(f"({unit} → rad)" in t.get_text() for t in over.get_legend().get_texts())
    # the overlay shows the converted values: both runs' lines coincide
    lines = over.get_lines()
    np.testing.assert_allclose(lines[2].get_ydata(), lines[0].get_ydata(), atol=1e-12)


def test_units_that_cannot_be_converted_refuse_the_difference(tmp_path, capsys):
    a = _in_unit(tmp_path, "angle", "rad", 1.0)
    b = _in_unit(tmp_path, "torque", "N m", 1.0)
    with pytest.raises(OutputError, match=r"^signal x.y is in N m in torque but in rad in "
                                          r"angle; fwdstep cannot convert N m into rad"):
        compare([a, b])
    code = main(["compare", a, b, "-o", str(tmp_path / "cmp")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "cannot convert N m into rad" in err
