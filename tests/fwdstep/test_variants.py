"""fwdstep.sweeps.variants: a variant's derived spec equals its own full ``load_spec``.

The sweep derives every variant's spec from one load of the diagram (only what the swept
values reach is evaluated again).  Each derived spec must equal what loading the diagram with
the variant's values gives, field by field and number by number, including variants that
change a state size (``ell``), a shape, a simulation setting, a block parameter by path and
a parameter other parameters depend on; where deriving would not be exact (subsystems, a
port that changes shape) the full loader is used instead.
"""
import dataclasses
import os

import numpy as np
import pytest

from fwdstep.structure.compiler import _value_key
from fwdstep.structure.spec import load_spec
from fwdstep.sweeps.variants import VariantSpecs

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _canonical(spec) -> dict:
    out = {}
    for f in dataclasses.fields(spec):
        value = getattr(spec, f.name)
        if f.name == "blocks":
            value = [(e.name, e.type_name, e.cls, _value_key(e.params), e.file, e.line,
                      e.key_lines) for e in value]
        elif f.name == "parameters":
            value = sorted((k, _value_key(v)) for k, v in value.items())
        elif f.name == "simulation":
            value = dataclasses.asdict(value)
        out[f.name] = value
    return out


def _check(path, overrides, variants, derived):
    loader = VariantSpecs(path, overrides)
    for values in variants:
        got = loader.spec(values)
        want = load_spec(path, {**overrides, **values})
        assert _canonical(got) == _canonical(want), values
    assert loader.derived == derived


def test_slotine_li_variants_equal_their_own_loads():
    path = os.path.join(ROOT, "diagrams", "slotine_li.yaml")
    variants = [{"Lambda": 3.0}, {"Lambda": "2*eye(2)"}, {"K": "30*eye(2)", "Gamma": 1.5},
                {"A": [0.1, 0.2]}, {"simulation.step": 0.002}, {"t_final": 1.0},
                {"Ks.gain": "10*eye(2)"}, {"theta0": [1, 1, 1, 1], "Lambda": 7}]
    _check(path, {"t_final": 2.0}, variants, derived=len(variants))


def test_theorem1_order_and_dependent_parameters():
    """ell changes the reference dynamics' state size and q_d's coefficients (a parameter
    computed from ell): derived specs still equal the loaded ones."""
    path = os.path.join(ROOT, "diagrams", "theorem1.yaml")
    variants = [{"ell": 1}, {"ell": 3}, {"T": 5, "a1": 0.1}, {"alpha": 2.5},
                {"simulation.log_every": 10}]
    loader = VariantSpecs(path, {"t_final": 1.0})
    for values in variants:
        assert _canonical(loader.spec(values)) == _canonical(
            load_spec(path, {"t_final": 1.0, **values}))
    assert loader.derived >= 3


def test_a_port_that_changes_shape_falls_back_to_the_loader(tmp_path):
    """A Gain whose shape the wiring fixes: sweeping the upstream amplitude to another length
    changes shapes, so that variant is loaded in full (and still equals its own load)."""
    p = tmp_path / "d.yaml"
    p.write_text("""
parameters: {A: [1.0, 2.0], k: 2}
blocks:
  src: {type: Constant, value: A}
  g:   {type: Gain, gain: k}
connections:
  - src.y -> g.u
simulation: {t_final: 0.1, step: 0.01}
log: [g.y]
""")
    _check(str(p), {}, [{"k": 3.0}, {"A": [1.0, 2.0, 3.0]}], derived=1)


def test_subsystems_and_errors_use_the_loader():
    path = os.path.join(ROOT, "diagrams", "slotine_li_disturbed.yaml")
    loader = VariantSpecs(path, {"t_final": 1.0})
    got = loader.spec({"t_final": 0.5})
    assert _canonical(got) == _canonical(load_spec(path, {"t_final": 0.5}))
    assert loader.derived == 0
    slotine = VariantSpecs(os.path.join(ROOT, "diagrams", "slotine_li.yaml"))
    with pytest.raises(Exception) as derived:
        slotine.spec({"simulation.step": -1})
    with pytest.raises(Exception) as loaded:
        load_spec(os.path.join(ROOT, "diagrams", "slotine_li.yaml"), {"simulation.step": -1})
    assert str(derived.value) == str(loaded.value)
    assert np.isfinite(slotine.base.simulation.step)
