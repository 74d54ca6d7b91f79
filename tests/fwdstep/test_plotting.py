"""Figures: labels/units/components from the diagram or the block, every trace drawn and
named, titles that fit, PDF/SVG output, a visible t = 0, missing folders, no backend switch."""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError, OutputError
from fwdstep.results.plotting import (figure_specs, headline, plot_result, result_figures, signal_info)

DIAGRAM = """
blocks:
  x: {type: Integrator, shape: [2], initial: [1.0, -2.0]}
  k: {type: Gain, gain: -1, shape: [2]}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {t_final: 1, step: 0.01}
plots:
  decay: [x.y, {signals: [x.y, k.y], scale: log}]
"""

LABELLED = """
description: Decay of two joints.
blocks:
  x: {type: Integrator, shape: [2], initial: [1.0, -2.0]}
  k: {type: Gain, gain: -1, shape: [2]}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {t_final: 1, step: 0.01}
log:
  - {signal: x.y, label: '$\\Delta q$', unit: rad, components: [joint 1, joint 2]}
plots:
  decay: [x.y, {signals: [x.y], scale: log}]
"""

MANY = """
description: "{description}"
parameters:
  rates: [0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0, 2.2, 2.4]
blocks:
  x: {{type: Integrator, shape: [12], initial: 1.0}}
  k: {{type: Gain, gain: "-diag(rates)", shape: [12]}}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {{t_final: 1, step: 0.05}}
plots:
  modes: [x.y]
"""


def _run(tmp_path, text, name="d.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return fwdstep.simulate(fwdstep.load_diagram(str(path)))


def _legend(ax):
    return [t.get_text() for t in ax.get_legend().get_texts()]


def test_log_panel_is_parsed_and_drawn(tmp_path):
    r = _run(tmp_path, DIAGRAM)
    specs = figure_specs(r)
    assert specs == {"decay": [(["x.y"], "linear"), (["x.y", "k.y"], "log")]}
    written = plot_result(r, str(tmp_path))
    assert [p.rsplit("/", 1)[1] for p in written] == ["decay.png"]
    assert (tmp_path / "decay.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert np.allclose(r["x.y"][-1], [np.exp(-1), -2 * np.exp(-1)], atol=1e-8)


def test_bad_panel_scale_is_refused(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.replace("scale: log", "scale: loglog"))
    with pytest.raises(ConfigError) as info:
        fwdstep.load_diagram(str(path))
    assert str(info.value) == (f"{path}:10: plot 'decay': a panel mapping takes 'signals:' and "
                               "optionally 'scale: linear | log'")


def test_labels_units_and_components_from_the_diagram(tmp_path):
    r = _run(tmp_path, LABELLED)
    fig = result_figures(r)["decay"]
    lin, log = fig.axes[:2]
    assert lin.get_ylabel() == "$\\Delta q$ [rad]"
    assert log.get_ylabel() == "|$\\Delta q$| [rad]"
    assert _legend(lin) == ["joint 1", "joint 2"]
    # the log panel plots |x| and the data drawn are exactly |x.y|
    assert np.array_equal(log.lines[1].get_ydata(), np.abs(r["x.y"][:, 1]))
    assert fig._suptitle.get_text() == "Decay\nDecay of two joints."


def test_unknown_key_in_a_signal_entry_is_refused(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(LABELLED.replace("unit: rad", "units: rad"))
    with pytest.raises(ConfigError) as info:
        fwdstep.load_diagram(str(path))
    assert str(info.value) == (f"{path}:11: log: a signal mapping takes 'signal:' and optionally "
                               "'label:', 'unit:', 'components:'; 'units' is not one of them")


def test_a_plant_names_its_outputs_by_default():
    d = fwdstep.load_diagram("diagrams/slotine_li.yaml")
    q = next(n for n in d.signal_names if n.endswith(".q") and "arm" in n)
    info = signal_info(d, q)
    assert (info.label, info.unit, info.components) == ("$q$", "rad", ("joint 1", "joint 2"))
    # an undeclared signal keeps its name, and its components are numbered from 1
    plain = signal_info(d, q.replace(".q", ".qdot"))
    assert plain.unit == "rad/s"


def test_a_point_mass_position_is_in_metres_per_axis():
    d = fwdstep.load_diagram("diagrams/theorem2_pointmass.yaml")
    q, qdot = signal_info(d, "plant.q"), signal_info(d, "plant.qdot")
    assert (q.label, q.unit, q.components) == ("$q$", "m", ("axis 1", "axis 2"))
    assert (qdot.unit, qdot.components) == ("m/s", ("axis 1", "axis 2"))


def test_twelve_traces_are_all_drawn_in_distinct_colours_and_named(tmp_path):
    r = _run(tmp_path, MANY.format(description="Twelve modes."))
    ax = result_figures(r)["modes"].axes[0]
    assert len(ax.lines) == 12
    assert len({tuple(np.atleast_1d(np.asarray(ln.get_color(), dtype=object)))
                for ln in ax.lines}) == 12
    assert _legend(ax) == [f"x.y$_{{{i}}}$" for i in range(1, 13)]
    for i, line in enumerate(ax.lines):
        assert np.array_equal(line.get_ydata(), r["x.y"][:, i])


def test_a_batch_draws_every_variant(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.replace("gain: -1", "gain: g").replace(
        "blocks:", "parameters: {g: -1}\nblocks:"))
    from fwdstep.structure.spec import load_spec
    specs = [load_spec(str(path), {"g": -0.1 * (i + 1)}) for i in range(11)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    ax = result_figures(r)["decay"].axes[0]
    assert len(ax.lines) == 11
    assert _legend(ax)[-1] == "g = -1.1"
    assert ax.get_ylabel() == "|x.y|"
    assert np.allclose(ax.lines[3].get_ydata(), np.linalg.norm(r["x.y"][:, 3], axis=1))


def test_long_titles_wrap_at_words_and_fit_the_figure(tmp_path):
    words = ("Theorem 1: forwardstepping adaptive control with reference dynamics of order "
             "ell plus one from q, qdot and q_d only (Sec. 4.3) on the two-link arm.")
    assert headline(words).replace("\n", " ") == words
    r = _run(tmp_path, MANY.format(description=words))
    fig = result_figures(r)["modes"]
    fig.canvas.draw()
    box = fig._suptitle.get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width
    assert headline("First sentence. Second " + "word " * 80) == "First sentence."
    clauses = "A long one, " + ", ".join(f"clause number {i}" for i in range(40))
    short = headline(clauses, width=60, max_lines=2)
    lines = short.split("\n")
    assert len(lines) == 2 and all(len(ln) <= 60 for ln in lines) and short.endswith(" …")
    kept = " ".join(lines)[:-2]
    assert clauses.startswith(kept) and clauses[len(kept)] == ","   # ends at a clause
    assert headline("Indented lines end it:\n  (117) chi'' = x") == "Indented lines end it"   # its colon introduced the cut lines


def test_time_zero_is_inside_the_axes(tmp_path):
    r = _run(tmp_path, DIAGRAM)
    for ax in result_figures(r)["decay"].axes:
        lo, hi = ax.get_xlim()
        assert lo < r.t[0] and hi > r.t[-1]


def test_pdf_and_svg_and_a_missing_folder(tmp_path):
    r = _run(tmp_path, DIAGRAM)
    out = tmp_path / "new" / "deeper"
    paths = plot_result(r, str(out), formats=("pdf", "svg"))
    assert [p.rsplit("/", 1)[1] for p in paths] == ["decay.pdf", "decay.svg"]
    assert (out / "decay.pdf").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in (out / "decay.svg").read_bytes()[:2000]
    with pytest.raises(OutputError) as info:
        plot_result(r, str(out), formats=("jpg",))
    assert str(info.value) == "figure format 'jpg' is not supported; formats are: png, pdf, svg"
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError):
        plot_result(r, str(blocker / "sub"))


def test_plotting_never_switches_the_callers_backend(tmp_path):
    (tmp_path / "d.yaml").write_text(DIAGRAM)
    code = textwrap.dedent(f"""
        import sys, matplotlib
        matplotlib.use("svg")
        import fwdstep
        from fwdstep.results.plotting import plot_result
        r = fwdstep.simulate(fwdstep.load_diagram({str(tmp_path / 'd.yaml')!r}))
        r.plot()
        plot_result(r, {str(tmp_path / 'out')!r})
        print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={k: v for k, v in os.environ.items() if k != "MPLBACKEND"},
                         cwd=str(tmp_path))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["svg", "False"]


def test_a_label_matplotlib_cannot_typeset_is_shown_literally(tmp_path):
    r = _run(tmp_path, LABELLED.replace("'$\\Delta q$'", "'$\\Deltaq$'"))
    fig = result_figures(r)["decay"]
    fig.canvas.draw()                                  # typesetting would raise here
    assert fig.axes[0].get_ylabel() == "\\$\\Deltaq\\$ [rad]"


WIDE = """
parameters:
  rates: {rates}
blocks:
  x: {{type: Integrator, shape: [{n}], initial: 1.0}}
  k: {{type: Gain, gain: "-diag(rates)", shape: [{n}]}}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {{t_final: 0.5, step: 0.05}}
log:
  - {{signal: x.y, label: '$\\hat\\theta$'}}
  - {{signal: k.y, label: '$\\theta$'}}
plots:
  estimates: [[x.y, k.y], x.y]
"""


def _wide(n):
    return WIDE.format(n=n, rates=[round(0.1 * (i + 1), 2) for i in range(n)])


def test_43_components_get_a_colour_bar_not_an_86_entry_legend(tmp_path):
    from matplotlib.colors import to_rgba
    from fwdstep.results.plotting import MAX_LEGEND_ENTRIES
    r = _run(tmp_path, _wide(43))
    fig = result_figures(r)["estimates"]
    fig.canvas.draw()
    pair, single = fig.axes[0], fig.axes[1]
    assert len(pair.lines) == 86 and len(single.lines) == 43      # every component drawn
    for j in range(43):
        assert np.array_equal(pair.lines[j].get_ydata(), r["x.y"][:, j])
        assert np.array_equal(pair.lines[43 + j].get_ydata(), r["k.y"][:, j])
    # the legend names the two line styles only; the single-signal panel has none
    assert _legend(pair) == ["$\\hat\\theta$", "$\\theta$"]
    assert [ln.get_linestyle() for ln in pair.get_legend().get_lines()] == ["-", "--"]
    assert single.get_legend() is None
    for ax in (pair, single):
        legend = ax.get_legend()
        assert legend is None or len(legend.get_texts()) <= MAX_LEGEND_ENTRIES
    # a colour bar per panel whose band for component j is the colour of line j
    bars = [a._colorbar for a in fig.axes[2:]]
    assert len(bars) == 2
    for bar, ax in zip(bars, (pair, single)):
        ticks = bar.get_ticks()
        labels = [t.get_text() for t in bar.ax.get_yticklabels()]
        assert labels[0] == "1" and all(lab.isdigit() for lab in labels)
        assert all(1 <= int(lab) <= 43 for lab in labels)
        for j in (0, 17, 42):
            assert np.allclose(bar.cmap(bar.norm(j)), to_rgba(ax.lines[j].get_color()))
        assert list(ticks) == sorted(ticks)
    # the axes keep most of the width (an 86-entry legend left them a third)
    assert pair.get_position().width > 0.7


def test_seven_components_of_two_signals_list_colours_and_styles(tmp_path):
    r = _run(tmp_path, _wide(7))
    fig = result_figures(r)["estimates"]
    pair = fig.axes[0]
    assert len(pair.lines) == 14
    assert _legend(pair) == [str(j) for j in range(1, 8)] + ["$\\hat\\theta$", "$\\theta$"]
    assert pair.get_legend().get_title().get_text() == "component"
    assert len(fig.axes) == 2                          # no colour bar
    assert _legend(fig.axes[1]) == [f"${{\\hat\\theta}}_{{{j}}}$" for j in range(1, 8)]


def test_twenty_variants_are_numbered_on_a_colour_bar(tmp_path):
    from matplotlib.colors import to_rgba
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.replace("gain: -1", "gain: g").replace(
        "blocks:", "parameters: {g: -1}\nblocks:"))
    from fwdstep.structure.spec import load_spec
    specs = [load_spec(str(path), {"g": -0.2 * (i + 1)}) for i in range(20)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    fig = result_figures(r)["decay"]
    fig.canvas.draw()
    single, pair = fig.axes[:2]
    assert len(single.lines) == 20 and len(pair.lines) == 40
    assert single.get_legend() is None
    assert _legend(pair) == ["|x.y|", "|k.y|"]                   # the styles only
    bar = fig.axes[2]._colorbar
    labels = [t.get_text() for t in bar.ax.get_yticklabels()]
    assert labels[0] == "0" and all(0 <= int(lab) <= 19 for lab in labels)
    for b in (0, 7, 19):                       # the band of variant b is the colour of its line
        assert np.allclose(bar.cmap(bar.norm(b)), to_rgba(single.lines[b].get_color()))
        assert np.allclose(single.lines[b].get_ydata(), np.linalg.norm(r["x.y"][:, b], axis=1))
