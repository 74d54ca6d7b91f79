"""Shapes inferred from the wiring (fwdstep/structure/shapes.py).

A block may leave out a shape parameter (Gain/Sum/Integrator/TransferFunction ``shape``,
Product ``a_shape``/``b_shape``) when a connection fixes it.  Checked against analytic
solutions, against the same diagram with the shapes written out (bit for bit), and against
the shapes the shipped library declared by hand before (issue 15).
"""
from pathlib import Path

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ShapeError
from fwdstep.structure.spec import load_spec

REPO = Path(__file__).resolve().parents[2]


def _write(tmp_path, text, name="d.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_theorem1_takes_a_scalar_gain_for_K(tmp_path):
    """'--set K=50' used to fail with 'connection s.y -> Ks.u: shapes differ'."""
    shipped = str(REPO / "diagrams" / "theorem1.yaml")
    scalar = fwdstep.simulate(fwdstep.load_diagram(
        shipped, {"K": 50, "simulation.t_final": 0.3}))
    matrix = fwdstep.simulate(fwdstep.load_diagram(
        shipped, {"K": "50*eye(2)", "simulation.t_final": 0.3}))
    assert scalar.names == matrix.names
    for name in scalar.names:
        assert np.array_equal(scalar[name], matrix[name]), name


CHAIN = """
blocks:
  c:   {type: Constant, value: [1, 2, 3]}
  g:   {type: Gain, gain: 2}
  x:   {type: Integrator}
connections: [c.y -> g.u, g.y -> x.u]
simulation: {t_final: 1, step: 0.1}
log: [x.y]
"""


def test_a_chain_takes_its_shape_from_the_source(tmp_path):
    r = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, CHAIN)))
    t = r.t[:, None]
    np.testing.assert_allclose(r["x.y"], 2 * t * [1, 2, 3], rtol=1e-12, atol=1e-15)


# x' = -x + c around a loop where only the Constant fixes the shape: x = c (1 - exp(-t))
LOOP = """
blocks:
  c:   {type: Constant, value: [1, -2]}
  s:   {type: Sum, signs: "+-"}
  x:   {type: Integrator}
connections: [c.y -> s.u1, x.y -> s.u2, s.y -> x.u]
simulation: {t_final: 1, step: 0.01}
log: [x.y]
"""

# a loop x -> k -> x with no source at all, fixed only downstream by a declared Sum shape
DOWNSTREAM = """
blocks:
  x:   {type: Integrator, initial: 1}
  k:   {type: Gain, gain: -1}
  out: {type: Sum, signs: "+", shape: [2]}
connections: [x.y -> k.u, k.y -> x.u, x.y -> out.u1]
simulation: {t_final: 1, step: 0.01}
log: [out.y]
"""


def test_a_loop_takes_its_shape_from_either_side(tmp_path):
    r = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, LOOP)))
    expected = (1 - np.exp(-r.t))[:, None] * [1, -2]
    np.testing.assert_allclose(r["x.y"], expected, rtol=1e-9, atol=1e-12)
    r = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, DOWNSTREAM, "down.yaml")))
    assert r["out.y"].shape == (101, 2)
    np.testing.assert_allclose(r["out.y"], np.exp(-r.t)[:, None] * [1, 1], rtol=1e-9)


def test_written_shapes_are_kept_and_checked(tmp_path):
    explicit = CHAIN.replace("{type: Gain, gain: 2}", "{type: Gain, gain: 2, shape: [3]}") \
        .replace("{type: Integrator}", "{type: Integrator, shape: [3]}")
    a = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, CHAIN)))
    b = fwdstep.simulate(fwdstep.load_diagram(_write(tmp_path, explicit, "e.yaml")))
    assert np.array_equal(a["x.y"], b["x.y"])
    wrong = _write(tmp_path, CHAIN.replace("{type: Gain, gain: 2}",
                                           "{type: Gain, gain: 2, shape: [2]}"), "w.yaml")
    with pytest.raises(ShapeError) as info:
        fwdstep.load_diagram(wrong)
    assert str(info.value) == (f"{wrong}:6: connection c.y -> g.u: shapes differ: c.y is (3,), "
                               "g.u is (2,)")


# the shapes the shipped library wrote by hand before issue 15, for n = 2 joints, p parameters
DECLARED = [
    ("ea/W", "shape", ["n", "p"]), ("ea/Yth", "a_shape", ["n", "p"]), ("ea/Yth", "b_shape", ["p"]),
    ("ea/GYth", "shape", ["n"]), ("ea/Wth", "a_shape", ["n", "p"]), ("ea/Wth", "b_shape", ["p"]),
    ("ea/h", "shape", ["n"]), ("qds/dq", "shape", ["n"]), ("qds/dqdot", "shape", ["n"]),
    ("qds/a_dq", "shape", ["n"]), ("qds/e", "shape", ["n"]), ("qds/WTe", "a_shape", ["n", "p"]),
    ("qds/WTe", "b_shape", ["n"]), ("qds/WWTe", "a_shape", ["n", "p"]),
    ("qds/WWTe", "b_shape", ["p"]), ("qds/damp", "shape", ["n"]), ("qds/pos_err", "shape", ["n"]),
    ("qds/vel_err", "shape", ["n"]), ("qds/k0", "shape", ["n"]), ("qds/k1", "shape", ["n"]),
    ("qds/acc", "shape", ["n"]), ("qds/vel", "shape", ["n"]), ("qds/pos", "shape", ["n"]),
    ("ref/s", "shape", ["n"]), ("tq/YTs", "a_shape", ["n", "p"]), ("tq/YTs", "b_shape", ["n"]),
    ("tq/xi", "shape", ["p"]), ("tq/Yth", "a_shape", ["n", "p"]), ("tq/Yth", "b_shape", ["p"]),
    ("tq/Yxi", "a_shape", ["n", "p"]), ("tq/Yxi", "b_shape", ["p"]), ("tq/dYxi", "shape", ["n"]),
    ("tq/tau", "shape", ["n"]),
]


@pytest.mark.parametrize("sets, p", [({}, 4), ({"gravity": 9.81, "p": 7, "theta0": 0}, 7)])
def test_the_library_infers_what_it_used_to_declare(sets, p):
    text = "".join((REPO / "diagrams" / "lib" / f).read_text() for f in (
        "error_augmentation.yaml", "qd_star.yaml", "reference.yaml", "torque_passive.yaml"))
    assert "shape:" not in text            # nothing the wiring fixes is written by hand
    spec = load_spec(str(REPO / "diagrams" / "theorem6.yaml"), sets)
    params = {e.name: e.params for e in spec.blocks}
    size = {"n": 2, "p": p}
    for block, param, shape in DECLARED:
        assert params[block][param].tolist() == [size[s] for s in shape], (block, param)


def test_no_shipped_diagram_writes_a_shape_the_wiring_fixes():
    """Every shape parameter a block can infer is left out of the shipped diagrams (what is
    left: LinearCombination, whose input is (*shape, K), so no port carries its shape)."""
    import re
    from fwdstep.structure.library import load_library
    registry = load_library()
    found = []
    paths = sorted((REPO / "diagrams").glob("*.yaml")) + sorted((REPO / "diagrams" / "lib")
                                                                 .glob("*.yaml"))
    for path in [p for p in paths if not p.name.startswith("tmp")]:    # (robots/: not yet)
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            m = re.search(r"\{type: ([A-Za-z]+)", line)
            cls = registry.get(m.group(1)) if m else None
            if cls is None or cls.type_name == "LinearCombination":
                continue
            for param in cls.shape_from:
                if re.search(rf"[{{,]\s*{param}:", line):
                    found.append(f"{path.name}:{number}: {param}")
    assert found == []


def test_per_channel_lists_may_differ_in_length(tmp_path):
    """Polynomial coefficients and Sine harmonics per channel, without padding by hand."""
    path = _write(tmp_path, """
blocks:
  p: {type: Polynomial, coefficients: [[1, 2, 3], [4]], derivatives: 1}
  s: {type: Sine, amplitude: [[1, 0.5], [2]], frequency: [[1, 3], [2]], phase: [[0, 0.2], [1]]}
simulation: {t_final: 1, step: 0.25}
""")
    r = fwdstep.simulate(fwdstep.load_diagram(path))
    t = r.t
    np.testing.assert_allclose(r["p.y"], np.stack([1 + 2 * t + 3 * t ** 2, 4 + 0 * t], 1),
                               rtol=1e-14)
    np.testing.assert_allclose(r["p.y_d1"], np.stack([2 + 6 * t, 0 * t], 1), rtol=1e-14)
    np.testing.assert_allclose(r["s.y"], np.stack(
        [np.sin(t) + 0.5 * np.sin(3 * t + 0.2), 2 * np.sin(2 * t + 1)], 1), rtol=1e-12,
        atol=1e-15)
    # a block parameter that is not per-channel still refuses a ragged list
    bad = _write(tmp_path, "blocks:\n  c: {type: Constant, value: [[1, 2], [3]]}\n", "bad.yaml")
    with pytest.raises(fwdstep.ExpressionError) as info:
        load_spec(bad)
    assert str(info.value) == (f"{bad}:2: block 'c' parameter 'value': the list is not a "
                               "rectangular array of numbers")
