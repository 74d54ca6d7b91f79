"""Texts figures show are checked when the diagram is loaded, and a figure never costs a run.

A typo in a unit (``rad/s$^{2$``) passed ``validate`` and lost the finished run with an
80-line traceback when the figures were drawn.  The reference for "valid" is matplotlib's
own mathtext parser."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.cli.arguments import main
from fwdstep.core.errors import ConfigError
from fwdstep.core.mathtext import problem

DIAGRAM = """\
description: {description}
blocks:
  x: {{type: Integrator, shape: [2], initial: [1.0, -2.0]}}
  k: {{type: Gain, gain: -1.0, shape: [2]}}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {{t_final: 1, step: 0.01}}
log:
  - {{signal: x.y, label: '{label}', unit: '{unit}', components: [{components}]}}
plots:
  decay: [x.y]
"""
GOOD = {"description": "decay of $x$", "label": "$q$", "unit": "rad/s$^{2}$",
        "components": "'$q_1$', joint 2"}


def _write(tmp_path, **changes) -> str:
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.format(**dict(GOOD, **changes)))
    return str(path)


@pytest.mark.parametrize("key, value, line, what", [
    ("unit", "rad/s$^{2$", 10, "log: the unit of x.y 'rad/s$^{2$'"),
    ("label", "$x^$", 10, "log: the label of x.y '$x^$'"),
    ("components", "'$q_{1$', joint 2", 10, "log: the component of x.y '$q_{1$'"),
    ("description", "'decay of $x}$'", 1, "the description 'decay of $x}$'")])
def test_validate_refuses_a_typo_with_file_and_line(tmp_path, capsys, key, value, line, what):
    path = _write(tmp_path, **{key: value})
    with pytest.raises(ConfigError, match=r"is not valid mathtext"):
        fwdstep.load_diagram(path)
    assert main(["validate", path]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fwdstep: {path}:{line}: {what} is not valid mathtext: ")
    assert err.count("\n") == 1


def test_the_good_texts_pass(tmp_path):
    fwdstep.load_diagram(_write(tmp_path))


CASES = ["rad/s$^{2$", "$x^2^3$", "$x^{2}^3$", "$x_1^2$", "$x^$", "$x}$", "$\\hat\\theta_{1}$",
         "costs $5", "$a$ and $b_{c}$", "$x^{a^b}$", "rad s$^{-1}$", "$x_{1,2}$", "$q_d$",
         "$\\dot{q}_d$", "$\\dot q^2$", "$\\mathrm{rad}/\\mathrm{s}^{2}$", "$a^b_c^d$",
         "$x_$", "${x$", "$\\Delta q$ [rad]", "N m", "plain", "$x ^2 ^3$"]


@pytest.mark.parametrize("text", CASES)
def test_the_load_time_check_agrees_with_matplotlib(text):
    """Whatever the light check refuses, matplotlib refuses; on these typos both agree."""
    from matplotlib.text import Text
    mathtext = pytest.importorskip("matplotlib.mathtext")
    is_math = Text(text=text)._preprocess_math(text)[1]
    try:
        if is_math:
            mathtext.MathTextParser("path").parse(text)
        refused = False
    except ValueError:
        refused = True
    assert (problem(text) is not None) == refused, text


def test_a_typo_only_matplotlib_knows_is_drawn_literally(tmp_path):
    """An unknown command passes the load-time check: the figure shows it as written."""
    out = tmp_path / "out"
    path = _write(tmp_path, unit="$\\alpah$")
    assert main(["run", path, "-o", str(out), "-q"]) == 0
    assert (out / "decay.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from fwdstep.results.plotting import figure_bytes, result_figures
    res = fwdstep.simulate(fwdstep.load_diagram(path))
    fig = result_figures(res)["decay"]
    figure_bytes(fig)
    assert fig.axes[0].get_ylabel() == "$q$ [\\$\\alpah\\$]"


def test_a_figure_that_fails_never_loses_the_run(tmp_path, capsys, monkeypatch):
    import fwdstep.results.plotting as plotting

    def broken(*args, **kwargs):
        raise ValueError("the figure broke\nover two lines")

    monkeypatch.setattr(plotting, "plot_result", broken)
    out = tmp_path / "out"
    assert main(["run", _write(tmp_path), "-o", str(out), "-q"]) == 2
    assert capsys.readouterr().err == (
        "fwdstep: the figures could not be drawn (ValueError: the figure broke over two "
        "lines); the run's data are written\n")
    with np.load(out / "result.npz") as data:
        t, x = data["t"], data[next(k for k in data.files if "x.y" in k)]
    np.testing.assert_allclose(x.reshape(len(t), -1)[:, 0], np.exp(-t), rtol=1e-8)
    with open(out / "summary.json") as fh:
        assert json.load(fh)["status"] == "ok"
    assert os.path.exists(out / "manifest.json")
