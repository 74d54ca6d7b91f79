"""The broken-diagram corpus: every file in tests/diagrams/bad/ with its exact error.

Each row is (file stem, exception class, line, message); ``str(exc)`` must equal
``"<path>:<line>: <message>"``.  A message here is part of the user interface: when one
reads badly, improve it in the engine, not here.  ``fwdstep validate`` must answer every file
with exactly one line on stderr and exit code 2.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.core.errors import (AlgebraicLoopError, ConfigError, DiagramError, ExpressionError,
                            ParameterError, ShapeError, UnknownBlockTypeError, WiringError,
                            YamlError)

BAD = os.path.normpath(Path(__file__).resolve().parents[1] / "diagrams" / "bad")
REPO = Path(__file__).resolve().parents[2]

CASES = [
    ("algebraic_loop", AlgebraicLoopError, 4,
     'algebraic loop: sum.y -> g.u -> g.y -> sum.u2 -> sum.y; every port on it feeds '
     'straight through; break it with a block that has state (Integrator, a strictly proper '
     'TransferFunction)'),
    ("bad_choice", ParameterError, 2,
     "block 'ref' parameter 'variant' must be one of eq2, eq14, eq16, eq29, got 'eq99'"),
    ("billion_laughs", YamlError, 6,
     'the document expands to more than 200000 nodes through aliases (&anchor/*alias); '
     'refused'),
    ("block_feeds_itself", AlgebraicLoopError, 8,
     "block 'ref' feeds its output 'z' back into its input 'q', on which its output 'zdot' "
     "depends directly; fwdstep evaluates each block once per stage, so a block cannot drive "
     "its own direct-feedthrough input"),
    ("block_level_loop", AlgebraicLoopError, 4,
     "blocks ref -> g -> ref form a loop that is only broken inside a block whose outputs have "
     "different feedthrough; fwdstep evaluates each block once per stage, so split that block "
     "in two"),
    ("block_without_type", ConfigError, 2,
     "block 'src' has no 'type:' (the block type, e.g. 'type: Gain'; 'fwdstep blocks' lists "
     'them)'),
    ("blocks_not_mapping", ConfigError, 1,
     "'blocks' must be a mapping, got a list"),
    ("comments_only", YamlError, 1,
     "the file is empty; a diagram needs at least a 'blocks:' section"),
    ("control_character_bel", YamlError, 1,
     "column 21: the control character \\x07 (BEL) is not allowed; a diagram is printable "
     "text (tabs and newlines allowed)"),
    ("control_character_esc", YamlError, 3,
     "column 17: the control character \\x1b (ESC) is not allowed; a diagram is printable "
     "text (tabs and newlines allowed)"),
    ("control_character_form_feed", YamlError, 3,
     "column 1: the control character \\x0c (form feed) is not allowed; a diagram is "
     "printable text (tabs and newlines allowed)"),
    ("custom_tag", YamlError, 2,
     "tag '!Constant' is not allowed: diagrams may contain only plain YAML (mappings, lists, "
     'numbers, strings, booleans)'),
    ("duplicate_block_name", YamlError, 4,
     "duplicate block name 'int' (first defined at line 3); YAML would silently keep only "
     'the last one'),
    ("duplicate_block_parameter", YamlError, 2,
     "duplicate key 'value' (first defined at line 2); YAML would silently keep only the "
     'last one'),
    ("duplicate_key", YamlError, 6,
     "duplicate key 't_final' (first defined at line 4); YAML would silently keep only the "
     'last one'),
    ("empty_parameter", ExpressionError, 5,
     "block 'g' parameter 'gain': expression '-K' uses 'K', which is empty (null)"),
    ("empty", YamlError, 1,
     "the file is empty; a diagram needs at least a 'blocks:' section"),
    ("escape_in_block_type", UnknownBlockTypeError, 3,   # "\e" in YAML: shown, never sent
     "unknown block type 'Gain\\x1b[32m ok\\x1b[0m'; run 'fwdstep blocks' for the list; "
     "block types of your own are added with --plugin FILE.py (docs/writing-blocks.md)"),
    ("expression_overflow", ExpressionError, 5,
     "simulation.step: expression '1e400' is not finite"),
    ("forbidden_attribute", ExpressionError, 4,
     "block 'g' parameter 'gain': expression 'k.__class__' uses a forbidden construct "
     '(attribute access)'),
    ("forbidden_call", ExpressionError, 2,
     "parameter 'k': expression 'open('/etc/passwd')' calls 'open', which is not allowed; "
     'allowed functions are: abs, acos, asin, atan, atan2, binom, ceil, concat, cos, cosh, '
     'degrees, diag, exp, eye, floor, log, log10, max, min, ones, polyadd, polymul, polypow, '
     'radians, reshape, round, sin, sinh, size, sqrt, tan, tanh, transpose, zeros'),
    ("forbidden_comprehension", ExpressionError, 2,
     "parameter 'k': expression '[i for i in [1, 2]]' uses a forbidden construct "
     '(comprehensions)'),
    ("forbidden_import", ExpressionError, 2,
     "parameter 'k': expression '__import__('os').system('echo pwned')' uses the name "
     "'__import__'; names starting with '__' are never allowed"),
    ("forbidden_lambda", ExpressionError, 2,
     "parameter 'k': expression '(lambda: 2)()' uses a forbidden construct (lambdas)"),
    ("fractional_log_every", ConfigError, 3,
     'simulation.log_every must be a whole number of steps >= 1, got 2.5'),
    ("gain_wrong_shape", ParameterError, 6,
     "block 'g' parameter 'gain' has shape (2, 3), which does not fit an input of shape (2,)"),
    ("huge_eye", ExpressionError, 2,
     "parameter 'K': expression 'eye(10000)' cannot be evaluated: eye(): the identity matrix "
     'would have 100000000 numbers (limit 1000000)'),
    ("huge_integer_literal", YamlError, 2,
     'the integer on this line has 5000 digits; numbers are limited to 400'),
    ("huge_integrator", ParameterError, 4,
     "block 'int': number of elements of 'shape' = 1000000000 is larger than the limit 2000"),
    ("huge_power", ExpressionError, 2,
     "parameter 'k': expression '10**10**10' cannot be evaluated: overflow encountered in "
     'power (the result is too large or undefined)'),
    ("huge_reference_dynamics", ParameterError, 2,
     "block 'ref': ell = 1000000000 is larger than the limit 60"),
    ("huge_signal", ParameterError, 3,
     "block 'g': port 'u' would have 10000000000 elements (limit 1000000)"),
    ("improper_transfer_function", ParameterError, 3,
     "block 'tf' transfer function is improper: numerator degree 2 > denominator degree 1"),
    ("input_driven_twice", WiringError, 7,
     'input int.u is driven twice: by a.y (line 6) and by b.y'),
    ("input_used_as_source", WiringError, 5,
     "block 'int' has no output port 'u' ('u' is an input); output ports are: y"),
    ("list_with_null", ExpressionError, 2,
     "block 'src' parameter 'value': a list may contain only numbers, not null (an empty "
     "entry)"),
    ("log_missing_signal", ConfigError, 6,
     "signal 'int.x' (in log/plots/metrics) does not exist; block 'int' has outputs: y"),
    ("malformed_connection", WiringError, 5,
     "connection 'src.y => int.u' must have the form 'block.out -> block.in[, ...]'"),
    ("metrics_missing_signal", ConfigError, 6,
     "signal 'err.y' (in log/plots/metrics) does not exist; there is no block 'err'"),
    ("merge_key_bomb", YamlError, 10,                # <<: merge keys of aliases, doubling
     'the document expands to more than 200000 nodes through aliases (&anchor/*alias); '
     'refused'),
    ("missing_required_parameter", ParameterError, 3,
     "block 'g' (Gain) is missing required parameter 'gain' (scalar or (m, n) matrix)"),
    ("no_blocks", ConfigError, 1,
     "the diagram has no 'blocks:' section"),
    ("nonexistent_block", WiringError, 6,
     "connection names block 'intg', which does not exist; did you mean 'integ'?"),
    ("nonexistent_source_block", WiringError, 5,
     "connection names block 'source', which does not exist; did you mean 'src'?"),
    ("noncharacter_fffe", YamlError, 3,
     "column 20: the character \\ufffe (noncharacter U+FFFE) is not allowed; a diagram is "
     "printable text (tabs and newlines allowed)"),
    ("not_hurwitz", ParameterError, 3,
     "block 'ref': reference-dynamics polynomial w^2 + 1 w - 2 is not Hurwitz: root 1 has "
     'non-negative real part'),
    ("not_yaml", YamlError, 2,
     "not valid YAML: expected ',' or ']', but got ':'"),
    ("parameter_cycle", ExpressionError, 2,
     'parameters a, b refer to each other in a cycle'),
    ("parameter_mapping_value", ExpressionError, 2,
     "block 'src' parameter 'value' must be a number, a list or an expression, not a mapping "
     "({...} or indented 'key: value' lines)"),
    ("parameter_not_whole", ParameterError, 2,
     "block 'ref' parameter 'ell' must be a whole number, got 1.5"),
    ("parameter_wrong_type", ParameterError, 3,
     "block 'tf' parameter 'den' must be a number or array, got true"),
    ("plot_missing_signal", ConfigError, 7,
     "signal 'sink.y' (in log/plots/metrics) does not exist; there is no block 'sink'"),
    ("python_name_tag", YamlError, 2,
     "tag '!!python/name:os.system' is not allowed: diagrams may contain only plain YAML "
     '(mappings, lists, numbers, strings, booleans)'),
    ("python_object_tag", YamlError, 2,
     "tag '!!python/object/apply:os.system' is not allowed: diagrams may contain only plain "
     'YAML (mappings, lists, numbers, strings, booleans)'),
    ("ragged_array", ExpressionError, 2,
     "block 'src' parameter 'value': the list is not a rectangular array of numbers"),
    ("shape_mismatch", ShapeError, 5,
     'connection src.y -> int.u: shapes differ: src.y is (3,), int.u is (2,)'),
    # H15 (issue 15/16): budgets on the specification and confined includes
    ("spec_block_fanout", ConfigError, 2,
     "the diagram would have 160000 blocks after subsystem expansion; the limit is 10000"),
    ("spec_include_absolute", ConfigError, 2,
     "subsystem 'plant': file '/etc/passwd' leaves the diagram's folder; subsystems come from "
     "the diagram's folder tree, fwdstep's library (lib/NAME) or a folder in FWDSTEP_PATH"),
    ("spec_include_outside", ConfigError, 2,
     "subsystem 'plant': file '../../../../../../etc/passwd' leaves the diagram's folder; "
     "subsystems come from the diagram's folder tree, fwdstep's library (lib/NAME) or a folder "
     "in FWDSTEP_PATH"),
    ("spec_parameter_memory", ExpressionError, 23,
     "parameter 'p20': the diagram's evaluated parameters would hold 21000000 numbers; the "
     "limit is 20000000 (152 MiB)"),
    ("step_infinite", ConfigError, 5,
     'simulation.step must be a finite number, got inf'),
    ("step_larger_than_t_final", ConfigError, 3,
     'simulation.step (2) is larger than t_final (1)'),
    ("step_nan", ConfigError, 3,
     'simulation.step must be a finite number, got nan'),
    ("step_negative", ConfigError, 3,
     'simulation.step must be a positive finite number, got -0.01'),
    ("string_literal_expression", ExpressionError, 2,
     "block 'g' parameter 'gain': expression ''two'' contains a literal 'two' that is not a "
     'number'),
    ("subsystem_includes_itself", ConfigError, 2,
     "subsystem 'inner' includes itself: subsystem_includes_itself.yaml -> "
     'subsystem_includes_itself.yaml'),
    ("subsystem_missing_file", ConfigError, 2,
     "subsystem 'plant': file 'no_such_plant.yaml' not found; looked in: "
     '{dir}/no_such_plant.yaml'),
    ("subsystem_unknown_parameter", ParameterError, 3,
     "subsystem 'plant' (lib/plant.yaml) has no parameter 'gain'; parameters are: k"),
    ("subsystem_unknown_port", WiringError, 5,
     "subsystem 'plant' has no input port 'tau'; input ports are: u"),
    ("subscript_out_of_range", ExpressionError, 3,
     "parameter 'k': expression 'v[2]' cannot be evaluated: index 2 is out of bounds for axis 0 "
     "with size 2"),
    ("t_final_negative", ConfigError, 3,
     'simulation.t_final must be a positive number, got -5'),
    ("t_final_zero", ConfigError, 3,
     'simulation.t_final must be a positive number, got 0'),
    ("too_many_steps", ConfigError, 3,
     'simulation would take 1e+12 steps (t_final / step); the limit is 5e+07'),
    ("top_level_list", YamlError, 1,
     'the top level must be a mapping (blocks:, connections:, ...), got a list'),
    ("top_level_scalar", YamlError, 1,
     'the top level must be a mapping (blocks:, connections:, ...), got a string'),
    ("transfer_function_denormal_leading", ParameterError, 3,   # no RuntimeWarning lines
     "parameter 'den': the leading coefficient 9.99989e-321 is too small (dividing the other "
     "coefficients by it overflows); drop it or rescale the transfer function"),
    ("transfer_function_zero_denominator", ParameterError, 3,
     "block 'tf' parameter 'den' must not be zero"),
    ("unconnected_input", WiringError, 4,
     "block 'int' input port 'u' is not connected"),
    ("unquoted_comma", ExpressionError, 3,
     "block 'src' parameter 'value': cannot parse expression 'ones(2': '(' was never closed; "
     "in a YAML {...} or [...] a comma ends the value, so quote expressions that contain "
     "commas"),
    ("undefined_name", ExpressionError, 4,
     "block 'g' parameter 'gain': expression '2*alpah' refers to undefined name 'alpah'; did "
     "you mean 'alpha'? defined names are: alpha"),
    ("unknown_block_parameter", ParameterError, 5,
     "block 'g' (Gain) has no parameter 'gian'; valid parameters are: gain, shape"),
    ("unknown_block_type", UnknownBlockTypeError, 3,
     "unknown block type 'Intgrator'; did you mean 'Integrator'?"),
    ("unknown_block_type_case", UnknownBlockTypeError, 2,
     "unknown block type 'constant'; did you mean 'Constant'?"),
    ("unknown_destination_port", WiringError, 5,
     "block 'int' has no input port 'x'; input ports are: u"),
    ("unknown_simulation_setting", ConfigError, 3,
     "simulation has no setting 'dt'; settings are: t_final, step, solver, log_every, bound, "
     'backend, rtol, atol, stability_check'),
    ("unknown_solver", ConfigError, 3,
     "simulation.solver 'rk45' is unknown; solvers are: euler, heun, rk4, dop853, radau, lsoda"),
    ("unknown_source_port", WiringError, 5,
     "block 'src' has no output port 'out'; output ports are: y"),
    ("unknown_top_level_key", ConfigError, 3,
     "unknown top-level key 'connection'; did you mean 'connections'? (valid keys: "
     'description, parameters, blocks, connections, ports, simulation, log, plots, metrics)'),
]
CORPUS = sorted(p.stem for p in Path(BAD).glob("*.yaml"))


def bad_path(stem: str) -> str:
    return os.path.join(BAD, stem + ".yaml")


def test_corpus_is_complete():
    stems = [c[0] for c in CASES]
    assert len(stems) == len(set(stems)), "a file is listed twice"
    assert sorted(stems) == CORPUS, "every corpus file has exactly one row, and vice versa"
    assert len(CORPUS) >= 40


@pytest.mark.parametrize("stem, cls, line, message", CASES, ids=[c[0] for c in CASES])
def test_bad_diagram_message(stem, cls, line, message):
    path = bad_path(stem)
    t0 = time.process_time()        # CPU time: a loaded CI machine stretches wall time
    with pytest.raises(DiagramError) as info:
        fwdstep.load_diagram(path)
    elapsed = time.process_time() - t0
    assert type(info.value) is cls
    expected = message.replace("{dir}", BAD)
    assert str(info.value) == f"{path}:{line}: {expected}"
    assert "\n" not in str(info.value)
    # absurd sizes (10^9 states, eye(10000), 10**10**10, alias bombs) are refused at once
    assert elapsed < 1.0, f"{stem} took {elapsed:.2f} s of CPU to refuse"


@pytest.mark.parametrize("stem", CORPUS)
def test_validate_prints_one_line_and_exits_2(stem, capsys):
    code = cli.main(["validate", bad_path(stem)])
    out, err = capsys.readouterr()
    assert code == 2
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("fwdstep: " + bad_path(stem) + ":")
    assert "Traceback" not in err


@pytest.mark.parametrize("stem", ["not_yaml", "forbidden_import", "algebraic_loop"])
def test_validate_in_a_real_process(stem, tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "cli.py"), "validate", bad_path(stem)],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fwdstep: ") and "Traceback" not in proc.stderr


def test_run_refuses_a_bad_diagram_without_writing(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["run", bad_path("shape_mismatch"), "-o", str(out)]) == 2
    assert len(capsys.readouterr().err.splitlines()) == 1
    assert not out.exists()


# ------------------------------------------------------------------ --set of an unknown parameter
GOOD = """\
parameters:
  gain: 2
  alpha: 5
blocks:
  src: {type: Constant, value: [1, 2]}
  g: {type: Gain, gain: gain*alpha, shape: [2]}
  int: {type: Integrator, shape: [2]}
connections:
  - src.y -> g.u
  - g.y -> int.u
simulation: {t_final: 0.1, step: 0.01}
"""


@pytest.fixture
def good(tmp_path) -> str:
    path = tmp_path / "good.yaml"
    path.write_text(GOOD)
    return os.path.normpath(str(path))


SET_MESSAGE = ("{path}:1: --set alpah=...: the diagram has no parameter 'alpah'; did you mean "
               "'alpha'? parameters are: gain, alpha")


def test_set_unknown_parameter_api(good):
    with pytest.raises(ConfigError) as info:
        fwdstep.load_diagram(good, overrides={"alpah": 3})
    assert str(info.value) == SET_MESSAGE.format(path=good)


def test_set_unknown_parameter_cli(good, capsys):
    assert cli.main(["validate", good, "--set", "alpah=3"]) == 2
    err = capsys.readouterr().err
    assert err == "fwdstep: " + SET_MESSAGE.format(path=good) + "\n"
    assert cli.main(["run", good, "--set", "alpah=3", "-o", os.path.dirname(good) + "/o"]) == 2
    assert capsys.readouterr().err == err


@pytest.mark.parametrize("arg, message", [
    ("alpha", "--set 'alpha' must have the form NAME=VALUE"),
    ("alpha=", "--set 'alpha=' has no value"),
    ("2x=1", "--set '2x=1': '2x' is not a parameter name, simulation.SETTING, log, "
             "BLOCK.PARAMETER or SUBSYSTEM.BLOCK.PARAMETER"),
])
def test_set_malformed(good, capsys, arg, message):
    assert cli.main(["validate", good, "--set", arg]) == 2
    assert capsys.readouterr().err == f"fwdstep: {message}\n"


def test_set_known_parameter_still_checked(good, capsys):
    assert cli.main(["validate", good, "--set", "alpha=__import__('os')"]) == 2
    err = capsys.readouterr().err
    assert err == (f"fwdstep: {good}:3: --set alpha=__import__('os'): parameter 'alpha': "
                   "expression '__import__('os')' "
                   "uses the name '__import__'; names starting with '__' are never allowed\n")
