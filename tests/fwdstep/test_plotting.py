"""Figures named by ``plots:``: linear and log panels, refusals of malformed panels."""
import numpy as np
import pytest

import fwdstep
from fwdstep.errors import ConfigError
from fwdstep.plotting import figure_specs, plot_result

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


def test_log_panel_is_parsed_and_drawn(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM)
    r = fwdstep.simulate(fwdstep.load_diagram(str(path)))
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
