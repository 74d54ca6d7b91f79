"""Subsystems (``type: subsystem``): flattening, names, parameters, and their errors.

A subsystem is a diagram file used as a block.  These tests write small diagrams into a
temporary folder, load them through ``fwdstep.structure.spec.load_spec`` / ``fwdstep.load_diagram``,
and check: the flattened block names ``outer/inner/block``; that logged signals and
``Result`` lookups accept both the internal name and the subsystem port name; that
parameters pass down (defaults, overrides, expressions over the parent's parameters,
dependent child parameters) through three levels; numbers through a run; and that every
mistake is refused with the right exception class, the file and line where it was written,
and the valid names.
"""
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError, ParameterError, ShapeError, WiringError
from fwdstep.structure.spec import load_spec

GAIN = """
parameters:
  k: 2
  k2: 3*k          # depends on k: an override of k must reach it
blocks:
  g: {type: Gain, gain: k2, shape: [1]}
ports:
  inputs: {u: g.u}
  outputs: {y: g.y}
"""

# level 2: two gains in series, the second one a subsystem of its own
MIDDLE = """
parameters:
  m: 1
blocks:
  first: {type: Gain, gain: m, shape: [1]}
  inner: {type: subsystem, file: gain.yaml, parameters: {k: m + 1}}
connections:
  - first.y -> inner.u
ports:
  inputs: {u: first.u}
  outputs: {y: inner.y, raw: first.y}
"""

# level 1: the middle level as a subsystem
OUTER = """
parameters:
  o: 1
blocks:
  mid: {type: subsystem, file: middle.yaml, parameters: {m: 2*o}}
ports:
  inputs: {u: mid.u}
  outputs: {y: mid.y}
"""

TOP = """
parameters:
  a: 1
blocks:
  c: {type: Constant, value: [1.0]}
  top: {type: subsystem, file: lib/outer.yaml, parameters: {o: a}}
connections:
  - c.y -> top.u
simulation: {t_final: 0.01, step: 0.001}
log: [top.y, top/mid.raw]
"""


def write(folder, name, text):
    path = os.path.join(str(folder), name)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        fh.write(text)
    return path


@pytest.fixture
def three_levels(tmp_path):
    """top.yaml -> lib/outer.yaml -> lib/middle.yaml -> lib/gain.yaml (depth 3)."""
    write(tmp_path, "lib/gain.yaml", GAIN)
    write(tmp_path, "lib/middle.yaml", MIDDLE)
    write(tmp_path, "lib/outer.yaml", OUTER)
    return write(tmp_path, "top.yaml", TOP)


def line_of(path, needle):
    with open(path) as fh:
        for i, text in enumerate(fh, start=1):
            if needle in text:
                return i
    raise AssertionError(f"{needle!r} not in {path}")


# ------------------------------------------------------------------------ flattening
def test_nesting_depth_three_prefixes_block_names(three_levels):
    spec = load_spec(three_levels)
    names = [b.name for b in spec.blocks]
    assert names == ["c", "top/mid/first", "top/mid/inner/g"]
    files = {b.name: os.path.basename(b.file) for b in spec.blocks}
    assert files == {"c": "top.yaml", "top/mid/first": "middle.yaml",
                     "top/mid/inner/g": "gain.yaml"}
    # a connection written inside a subsystem keeps the file and line it was written on
    inner = [c for c in spec.connections if c.dst == ("top/mid/inner/g", "u")]
    assert len(inner) == 1
    assert os.path.basename(inner[0].file) == "middle.yaml"
    assert inner[0].line == line_of(inner[0].file, "first.y -> inner.u")


def test_parameters_pass_down_three_levels_and_reach_numbers(three_levels):
    # a = 1 -> o = 1 -> m = 2 -> k = m + 1 = 3 -> k2 = 3 k = 9; y = m * k2 * 1 = 18
    r = fwdstep.simulate(fwdstep.load_diagram(three_levels))
    np.testing.assert_allclose(r["top.y"][-1], [18.0])
    np.testing.assert_allclose(r["top/mid.raw"][-1], [2.0])
    # the same signals under their internal (flattened) names
    np.testing.assert_allclose(r["top/mid/inner/g.y"][-1], [18.0])
    np.testing.assert_allclose(r["top/mid/first.y"][-1], [2.0])
    assert "top.y" in r and "top/mid/inner/g.y" in r
    # only the internal names are stored, once each
    assert sorted(r.names) == ["top/mid/first.y", "top/mid/inner/g.y"]


def test_top_level_override_reaches_the_deepest_level(three_levels):
    # a = 2 -> o = 2 -> m = 4 -> k = 5 -> k2 = 15; y = 4 * 15 = 60
    r = fwdstep.simulate(fwdstep.load_diagram(three_levels, overrides={"a": 2}))
    np.testing.assert_allclose(r["top.y"][-1], [60.0])


def test_defaults_used_when_nothing_is_passed(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: gain.yaml}
connections:
  - c.y -> s.u
simulation: {t_final: 0.01, step: 0.001}
log: [s.y]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(top))
    np.testing.assert_allclose(r["s.y"][-1], [6.0])     # k = 2, k2 = 6


def test_same_file_twice_with_different_parameters(tmp_path):
    """Two instances of one file are two sets of blocks (not a self-inclusion)."""
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  one: {type: subsystem, file: gain.yaml, parameters: {k: 1}}
  two: {type: subsystem, file: gain.yaml, parameters: {k: 10}}
connections:
  - c.y -> one.u
  - one.y -> two.u                # subsystem output straight into a subsystem input
simulation: {t_final: 0.01, step: 0.001}
log: [one.y, two.y]
""")
    d = fwdstep.load_diagram(top)
    assert [b.name for b in d.blocks] == ["c", "one/g", "two/g"]
    r = fwdstep.simulate(d)
    np.testing.assert_allclose(r["one.y"][-1], [3.0])
    np.testing.assert_allclose(r["two.y"][-1], [90.0])


def test_input_port_fans_out_to_several_blocks(tmp_path):
    write(tmp_path, "fan.yaml", """
blocks:
  a: {type: Gain, gain: 2, shape: [1]}
  b: {type: Gain, gain: 3, shape: [1]}
  s: {type: Sum, signs: "++", shape: [1]}
connections:
  - a.y -> s.u1
  - b.y -> s.u2
ports:
  inputs: {u: [a.u, b.u]}
  outputs: {y: s.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  f: {type: subsystem, file: fan.yaml}
connections:
  - c.y -> f.u
simulation: {t_final: 0.01, step: 0.001}
log: [f.y]
""")
    r = fwdstep.simulate(fwdstep.load_diagram(top))
    np.testing.assert_allclose(r["f.y"][-1], [5.0])


def test_subsystem_with_state_runs_and_plots_by_port_name(tmp_path):
    """An integrator inside a subsystem; plots and metrics may name subsystem ports."""
    write(tmp_path, "integ.yaml", """
parameters:
  x0: 0
blocks:
  i: {type: Integrator, shape: [1], initial: [x0]}
ports:
  inputs: {u: i.u}
  outputs: {y: i.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [2.0]}
  s: {type: subsystem, file: integ.yaml, parameters: {x0: 1}}
connections:
  - c.y -> s.u
simulation: {t_final: 1, step: 0.01}
log: []
plots: {out: [s.y]}
metrics: {error: s.y}
""")
    r = fwdstep.simulate(fwdstep.load_diagram(top))
    np.testing.assert_allclose(r["s.y"][:, 0], 1.0 + 2.0 * r.t, atol=1e-12)
    assert r.metrics()["final_error_norm"] == pytest.approx(3.0)


def test_connection_inside_subsystem_to_undeclared_port_is_hidden(tmp_path):
    """Blocks inside a subsystem are reachable from outside only through its ports."""
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: gain.yaml}
connections:
  - c.y -> s/g.u
""")
    with pytest.raises(WiringError, match="does not exist"):
        load_spec(top)


# ------------------------------------------------------------------------ errors
def test_unknown_subsystem_input_port(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: gain.yaml}
connections:
  - c.y -> s.v
""")
    with pytest.raises(WiringError) as err:
        load_spec(top)
    msg = str(err.value)
    assert msg.startswith(f"{top}:{line_of(top, 'c.y -> s.v')}: ")
    assert "subsystem 's' has no input port 'v'; input ports are: u" in msg


def test_unknown_subsystem_output_port(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: gain.yaml}
  g: {type: Gain, gain: 1, shape: [1]}
connections:
  - c.y -> s.u
  - s.out -> g.u
""")
    with pytest.raises(WiringError) as err:
        load_spec(top)
    msg = str(err.value)
    assert msg.startswith(f"{top}:{line_of(top, 's.out -> g.u')}: ")
    assert "subsystem 's' has no output port 'out'; output ports are: y" in msg


def test_unknown_port_of_a_nested_subsystem_names_the_full_path(three_levels, tmp_path):
    """A mistake two levels down names the subsystem by its full path and the file it is in."""
    middle = write(tmp_path, "lib/middle.yaml", MIDDLE.replace("first.y -> inner.u",
                                                               "first.y -> inner.w"))
    with pytest.raises(WiringError) as err:
        load_spec(three_levels)
    msg = str(err.value)
    assert msg.startswith(f"{middle}:{line_of(middle, 'first.y -> inner.w')}: ")
    assert "subsystem 'top/mid/inner' has no input port 'w'; input ports are: u" in msg


def test_unknown_parameter_passed_to_subsystem(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: gain.yaml, parameters: {gain: 3}}
connections:
  - c.y -> s.u
""")
    with pytest.raises(ParameterError) as err:
        load_spec(top)
    msg = str(err.value)
    assert msg.startswith(f"{top}:{line_of(top, 'gain: 3')}: ")
    assert "subsystem 's' (gain.yaml) has no parameter 'gain'; parameters are: k, k2" in msg


def test_parameter_passed_to_subsystem_without_parameters(tmp_path):
    write(tmp_path, "plain.yaml", """
blocks:
  g: {type: Gain, gain: 1, shape: [1]}
ports:
  inputs: {u: g.u}
  outputs: {y: g.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: plain.yaml, parameters: {k: 1}}
""")
    with pytest.raises(ParameterError, match=r"has no parameter 'k'; parameters are: \(none\)"):
        load_spec(top)


def test_parameter_expression_uses_the_parents_names_only(tmp_path):
    """A passed value is evaluated in the parent; the child's own names are not visible."""
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
parameters:
  a: 1
blocks:
  s: {type: subsystem, file: gain.yaml, parameters: {k: k2 + a}}
""")
    with pytest.raises(fwdstep.core.errors.ExpressionError) as err:
        load_spec(top)
    assert str(err.value).startswith(f"{top}:{line_of(top, 'k2 + a')}: ")
    assert "undefined name 'k2'" in str(err.value)


def test_error_inside_subsystem_names_block_path_and_child_file(tmp_path):
    child = write(tmp_path, "bad.yaml", """
blocks:
  g: {type: Gain, gain: 1, shape: [1], gian: 2}
ports:
  inputs: {u: g.u}
  outputs: {y: g.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: bad.yaml}
""")
    with pytest.raises(ParameterError) as err:
        load_spec(top)
    msg = str(err.value)
    assert msg.startswith(f"{child}:{line_of(child, 'gian')}: ")
    assert "block 's/g' (Gain) has no parameter 'gian'" in msg
    assert err.value.block == "s/g"


def test_block_constructor_error_inside_subsystem_names_path(tmp_path):
    """Errors raised when the block is built (graph phase) carry the flattened name too."""
    child = write(tmp_path, "bad.yaml", """
blocks:
  tf: {type: TransferFunction, num: [1, 0, 0], den: [1, 1], shape: [1]}
ports:
  inputs: {u: tf.u}
  outputs: {y: tf.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: bad.yaml}
connections:
  - c.y -> s.u
""")
    with pytest.raises(ParameterError) as err:
        fwdstep.load_diagram(top)
    msg = str(err.value)
    assert msg.startswith(f"{child}:")
    assert "'s/tf'" in msg and "improper" in msg


def test_unconnected_input_inside_subsystem_names_path(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: gain.yaml}
""")
    with pytest.raises(WiringError) as err:
        fwdstep.load_diagram(top)
    # the message names the subsystem's port, at the parent's line, where the user fixes it
    assert str(err.value) == (f"{top}:{line_of(top, 's: {type: subsystem')}: subsystem input "
                              "port 's.u' is not connected (it drives s/g.u)")


def test_shape_mismatch_across_the_boundary_points_at_the_parent_line(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  c: {type: Constant, value: [1.0, 2.0]}
  s: {type: subsystem, file: gain.yaml}
connections:
  - c.y -> s.u
""")
    with pytest.raises(ShapeError) as err:
        fwdstep.load_diagram(top)
    assert str(err.value).startswith(f"{top}:{line_of(top, 'c.y -> s.u')}: ")
    assert "s/g.u" in str(err.value)


def test_port_declaration_naming_a_missing_block(tmp_path):
    child = write(tmp_path, "bad.yaml", """
blocks:
  g: {type: Gain, gain: 1, shape: [1]}
ports:
  inputs: {u: gg.u}
  outputs: {y: g.y}
""")
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: bad.yaml}
""")
    with pytest.raises(WiringError) as err:
        load_spec(top)
    msg = str(err.value)
    assert msg.startswith(f"{child}:{line_of(child, 'gg.u')}: ")
    assert "subsystem input 'u' names block 'gg', which does not exist" in msg
    assert "did you mean 'g'?" in msg


def test_self_inclusion_is_refused(tmp_path):
    me = write(tmp_path, "me.yaml", """
blocks:
  again: {type: subsystem, file: me.yaml}
""")
    with pytest.raises(ConfigError) as err:
        load_spec(me)
    msg = str(err.value)
    assert msg.startswith(f"{me}:{line_of(me, 'file: me.yaml')}: ")
    assert "subsystem 'again' includes itself: me.yaml -> me.yaml" in msg


def test_mutual_inclusion_is_refused_with_the_chain(tmp_path):
    write(tmp_path, "a.yaml", """
blocks:
  b: {type: subsystem, file: sub/b.yaml}
""")
    b = write(tmp_path, "sub/b.yaml", """
blocks:
  a: {type: subsystem, file: ../a.yaml}
""")
    with pytest.raises(ConfigError) as err:
        load_spec(os.path.join(str(tmp_path), "a.yaml"))
    msg = str(err.value)
    assert msg.startswith(f"{b}:")
    assert "subsystem 'b/a' includes itself: a.yaml -> b.yaml -> a.yaml" in msg


def test_self_inclusion_through_a_differently_spelled_path(tmp_path):
    """'./x/../me.yaml' is the same file as 'me.yaml'."""
    os.makedirs(os.path.join(str(tmp_path), "x"))
    me = write(tmp_path, "me.yaml", """
blocks:
  again: {type: subsystem, file: ./x/../me.yaml}
""")
    with pytest.raises(ConfigError, match="includes itself"):
        load_spec(me)


def test_missing_subsystem_file(tmp_path):
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: nowhere.yaml}
""")
    with pytest.raises(fwdstep.core.errors.DiagramError, match="nowhere.yaml"):
        load_spec(top)


def test_unknown_subsystem_key(tmp_path):
    write(tmp_path, "gain.yaml", GAIN)
    top = write(tmp_path, "top.yaml", """
blocks:
  s: {type: subsystem, file: gain.yaml, params: {k: 1}}
""")
    with pytest.raises(ParameterError) as err:
        load_spec(top)
    assert "subsystem 's' has no key 'params'; keys are: type, file, parameters" \
        in str(err.value)


def test_batch_of_subsystem_variants(three_levels):
    """Variants differing only in a parameter passed down run as one batch."""
    specs = [load_spec(three_levels, {"a": a}) for a in (1.0, 2.0)]
    r = fwdstep.simulate(fwdstep.compile_batch(specs))
    np.testing.assert_allclose(r["top.y"][-1, :, 0], [18.0, 60.0])


def _chain(folder, levels):
    """level0.yaml includes level1.yaml ... includes level<levels>.yaml (a Gain)."""
    write(folder, f"level{levels}.yaml", GAIN.replace("k: 2", "k: 1"))
    for i in range(levels - 1, -1, -1):
        write(folder, f"level{i}.yaml", f"""
blocks:
  s: {{type: subsystem, file: level{i + 1}.yaml}}
ports:
  inputs: {{u: s.u}}
  outputs: {{y: s.y}}
""")
    return os.path.join(str(folder), "level0.yaml")


def test_depth_limit_is_exact(tmp_path):
    """MAX_SUBSYSTEM_DEPTH levels of subsystems load; one more is refused."""
    from fwdstep.structure.spec import MAX_SUBSYSTEM_DEPTH
    spec = load_spec(_chain(tmp_path / "ok", MAX_SUBSYSTEM_DEPTH))
    assert spec.blocks[0].name == "/".join(["s"] * MAX_SUBSYSTEM_DEPTH + ["g"])
    assert spec.aliases["s.y"] == spec.blocks[0].name + ".y"
    with pytest.raises(ConfigError, match=f"nested more than {MAX_SUBSYSTEM_DEPTH} deep"):
        load_spec(_chain(tmp_path / "deep", MAX_SUBSYSTEM_DEPTH + 1))


def test_self_inclusion_through_a_symbolic_link(tmp_path):
    me = write(tmp_path, "me.yaml", """
blocks:
  again: {type: subsystem, file: link.yaml}
""")
    os.symlink(me, os.path.join(str(tmp_path), "link.yaml"))
    with pytest.raises(ConfigError, match="includes itself: me.yaml -> link.yaml$"):
        load_spec(me)


# ----------------------------------------------------------------- --set paths (issue 15)
from pathlib import Path       # noqa: E402

from fwdstep.cli import arguments as cli  # noqa: E402
from fwdstep.core.errors import DiagramError  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _edited_copy(tmp_path, diagram: str, edits: list, plant_edits: list = ()) -> str:
    """A copy of a shipped diagram in a temporary folder, with text edits; lib/ comes from
    the shipped library except lib/plant.yaml when the plant itself is edited."""
    text = (REPO / "diagrams" / diagram).read_text()
    for old, new in edits:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    if plant_edits:
        plant = (REPO / "diagrams" / "lib" / "plant.yaml").read_text()
        for old, new in plant_edits:
            assert plant.count(old) == 1, old
            plant = plant.replace(old, new)
        (tmp_path / "lib").mkdir()
        (tmp_path / "lib" / "plant.yaml").write_text(plant)
    path = tmp_path / diagram
    path.write_text(text)
    return str(path)


SCENARIOS = {
    # Theorem 6: phase of q_d, disturbance phases, qdot(0), initial q_d*, a plant mass, theta_hat(0)
    "theorem6": (
        {"qd.phase": [0.3, -0.4], "dist.phase": [0.5, 2.0], "plant.qdot0": [0.1, -0.1],
         "qds.q_d0": [0.32, -0.18], "plant.arm.me": 2.2, "adapt.theta0": [1, 0.5, 0.5, 0.2],
         "simulation.t_final": 0.2},
        [("derivatives: 2}", "derivatives: 2, phase: [0.3, -0.4]}"),
         ("dist_phase: [0.0, 1.0]", "dist_phase: [0.5, 2.0]"),
         ("parameters: {q0: q0, gravity: gravity}}",
          "parameters: {q0: q0, gravity: gravity, qdot0: [0.1, -0.1]}}"),
         ("q_d0: q0,", "q_d0: [0.32, -0.18],"),
         ("theta0: [0, 0, 0, 0]", "theta0: [1, 0.5, 0.5, 0.2]"),
         ("t_final: 60", "t_final: 0.2")],
        [("qdot0: qdot0, gravity: gravity}", "qdot0: qdot0, gravity: gravity, me: 2.2}")]),
    # Theorem 9: chi_1'(0), the initial q_d* and qdot_d*, disturbance phases, a plant length
    "theorem9": (
        {"chi1dot.initial": [0.2, -0.1], "qds.q_d0": [0.1, 0.0], "qds.qdot_d0": [0.2, 0.1],
         "dist.phases": 0.7, "plant.arm.l1": 1.1, "simulation.t_final": 0.5},
        [("initial: 0}      # chi_1'(0)", "initial: [0.2, -0.1]}      # chi_1'(0)"),
         ("q_d0: [0, 0], qdot_d0: \"qd_amp*qd_freq\"", "q_d0: [0.1, 0.0], qdot_d0: [0.2, 0.1]"),
         ("amplitudes: \"tau_amp*ones(2, n_dist)\"}",
          "amplitudes: \"tau_amp*ones(2, n_dist)\", phases: 0.7}"),
         ("simulation: {t_final: 60,", "simulation: {t_final: 0.5,")],
        [("qdot0: qdot0, gravity: gravity}", "qdot0: qdot0, gravity: gravity, l1: 1.1}")]),
}


@pytest.mark.parametrize("diagram", sorted(SCENARIOS))
def test_a_scenario_is_one_run_with_set_only(diagram, tmp_path):
    """The clients' 71 edited copies: the same numbers, bit for bit, from --set paths."""
    sets, edits, plant_edits = SCENARIOS[diagram]
    shipped = str(REPO / "diagrams" / f"{diagram}.yaml")
    by_set = fwdstep.simulate(fwdstep.load_diagram(shipped, sets))
    edited = _edited_copy(tmp_path, f"{diagram}.yaml", edits, plant_edits)
    by_copy = fwdstep.simulate(fwdstep.load_diagram(edited))
    plain = fwdstep.simulate(fwdstep.load_diagram(shipped, {"simulation.t_final":
                                                            sets["simulation.t_final"]}))
    assert len(by_set.t) == len(by_copy.t) > 5
    names = list(by_copy.names)
    assert names and names == list(by_set.names)
    for name in names:
        assert np.array_equal(by_set[name], by_copy[name]), name
    assert any(not np.array_equal(by_set[n], plain[n]) for n in names)   # the sets did act


def test_set_reaches_block_subsystem_and_inner_block_parameters(three_levels):
    spec = load_spec(three_levels, {"top.o": 5, "top.mid.first.gain": 7, "top.mid.inner.k": 4})
    gains = {b.name: float(b.params["gain"]) for b in spec.blocks if b.name != "c"}
    # top.o = 5 -> m = 10 -> first's gain 10, inner's k 11; the two deeper sets win: 7, 3*4
    assert gains == {"top/mid/first": 7.0, "top/mid/inner/g": 12.0}
    spec = load_spec(three_levels, {"top.o": 5})
    gains = {b.name: float(b.params["gain"]) for b in spec.blocks if b.name != "c"}
    assert gains == {"top/mid/first": 10.0, "top/mid/inner/g": 33.0}


@pytest.mark.parametrize("name, message", [
    ("top.oo", "top.yaml:6: --set top.oo=...: subsystem 'top' (lib/outer.yaml) has no "
               "parameter 'oo'; did you mean 'o'? (a block's parameter is top.BLOCK.PARAMETER)"),
    ("tpo.o", "top.yaml:4: --set tpo.o=...: the diagram has no block 'tpo'; did you mean "
              "'top'?"),
    ("top.mid.frst.gain", "lib/middle.yaml:4: --set top.mid.frst.gain=...: subsystem "
                          "'top/mid' has no block 'frst'; did you mean 'first'?"),
    ("top.mid.first.gian", "lib/middle.yaml:5: --set top.mid.first.gian=...: block "
                           "'top/mid/first' (Gain) has no parameter 'gian'; did you mean "
                           "'gain'?"),
    ("top.mid.first.gain.x", "lib/middle.yaml:5: --set top.mid.first.gain.x=...: block "
                             "'top/mid/first' is a Gain, not a subsystem; write "
                             "top.mid.first.PARAMETER"),
])
def test_unknown_set_paths_are_refused_with_a_suggestion(three_levels, capsys, name, message):
    expected = os.path.join(os.path.dirname(three_levels), message)
    with pytest.raises(DiagramError) as info:
        load_spec(three_levels, {name: 1})
    assert str(info.value) == expected
    assert cli.main(["validate", three_levels, "--set", f"{name}=1"]) == 2
    assert capsys.readouterr().err == f"fwdstep: {expected}\n"


def test_set_log_replaces_the_logged_signals(three_levels):
    spec = load_spec(three_levels, {"log": ["top.y", "c.y"]})
    assert spec.log == ["top.y", "c.y"]
    r = fwdstep.simulate(fwdstep.load_diagram(three_levels, {"log": "c.y"}))
    assert list(r.names) == ["c.y"]


def test_a_diagram_without_ports_is_a_subsystem_reached_by_inner_port_names(tmp_path):
    (tmp_path / "pair.yaml").write_text(
        "parameters: {k: 2}\nblocks:\n  g: {type: Gain, gain: k, shape: [1]}\n"
        "  i: {type: Integrator, shape: [1]}\nconnections: [g.y -> i.u]\n"
        "simulation: {t_final: 5, step: 1}\n")      # a runnable diagram of its own, no ports:
    top = tmp_path / "top.yaml"
    top.write_text("blocks:\n  c: {type: Constant, value: [1]}\n"
                   "  p: {type: subsystem, file: pair.yaml, parameters: {k: 3}}\n"
                   "connections: [c.y -> p.g.u]\nlog: [p/i.y]\n"
                   "simulation: {t_final: 1, step: 0.5}\n")
    r = fwdstep.simulate(fwdstep.load_diagram(str(top)))
    assert r["p/i.y"][:, 0].tolist() == [0.0, 1.5, 3.0]      # x' = 3 * 1
    top.write_text(top.read_text().replace("p.g.u", "p.h.u"))
    with pytest.raises(WiringError) as info:
        load_spec(str(top))
    assert str(info.value) == (f"{top}:4: connection names block 'h', which does not exist; "
                               "blocks are: g, i")


# ---------------------------------------------------------------- names that follow a signal out
def _declared(path: str) -> dict:
    """signal -> its log: mapping, read from the YAML file itself (not through fwdstep)."""
    import yaml
    with open(path, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    return {e["signal"]: e for e in doc.get("log") or [] if isinstance(e, dict)}


def test_labels_declared_in_a_library_file_follow_its_output_ports():
    from fwdstep.results.plotting import signal_info
    inner = _declared("diagrams/lib/qd_star.yaml")
    top = _declared("diagrams/theorem6.yaml")
    outs = {"e": "e.y", "q_d_star": "pos.y", "dq": "dq.y"}
    d = fwdstep.load_diagram("diagrams/theorem6.yaml")
    for port, inside in outs.items():
        info = signal_info(d, f"qds.{port}")
        real = signal_info(d, f"qds/{inside}")          # the flattened name: the same names
        outer = top.get(f"qds.{port}", {})
        want_label = outer.get("label") or inner[inside]["label"]      # the parent's wins
        want_unit = outer.get("unit") or inner[inside]["unit"]
        assert (info.label, info.unit) == (want_label, want_unit), port
        assert (real.label, real.unit) == (want_label, want_unit), port
    # Theorem 6 names qds.dq itself (with components): its declaration is the one kept
    assert signal_info(d, "qds.dq").components == tuple(top["qds.dq"]["components"])
    assert signal_info(d, "tq.tau").unit == _declared("diagrams/lib/torque_passive.yaml")[
        "tau.y"]["unit"]


def test_a_saved_run_keeps_a_subsystem_outputs_names(tmp_path):
    from fwdstep.results.plotting import signal_info
    from fwdstep.results.result import load_result
    d = fwdstep.load_diagram("diagrams/theorem6.yaml", {"simulation.t_final": 0.05})
    fwdstep.simulate(d).save(str(tmp_path / "run"))
    loaded = load_result(str(tmp_path / "run"))
    inner = _declared("diagrams/lib/qd_star.yaml")
    for name in ("qds.e", "qds/e.y"):              # the port name and the flattened name
        info = signal_info(loaded, name)
        assert (info.label, info.unit) == (inner["e.y"]["label"], inner["e.y"]["unit"])


HELD = """
blocks:
  g: {type: Gain, gain: 2, shape: [1]}
log:
  - {signal: g.y, label: "$y_g$", unit: V}
ports:
  inputs: {u: g.u}
  outputs: {y: g.y}
"""


def test_a_sampled_subsystem_output_keeps_its_names(tmp_path):
    from fwdstep.results.plotting import signal_info
    (tmp_path / "held.yaml").write_text(HELD)
    (tmp_path / "top.yaml").write_text("""
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: held.yaml, sample_period: 0.1}
connections:
  - c.y -> s.u
simulation: {t_final: 0.2, step: 0.01}
""")
    d = fwdstep.load_diagram(str(tmp_path / "top.yaml"))
    assert d.resolve("s.y") != "s/g.y"                 # the output is the hold's
    info = signal_info(d, "s.y")
    assert (info.label, info.unit) == ("$y_g$", "V")


def test_a_wrong_signal_in_a_subsystem_log_is_refused_where_it_is_written(tmp_path):
    (tmp_path / "held.yaml").write_text(HELD.replace("signal: g.y", "signal: g.z"))
    (tmp_path / "top.yaml").write_text("""
blocks:
  c: {type: Constant, value: [1.0]}
  s: {type: subsystem, file: held.yaml}
connections:
  - c.y -> s.u
""")
    with pytest.raises(WiringError) as info:
        fwdstep.load_diagram(str(tmp_path / "top.yaml"))
    assert str(info.value) == (f"{tmp_path / 'held.yaml'}:5: log: signal 'g.z' does not exist; "
                               "block 's/g' has outputs: y")
