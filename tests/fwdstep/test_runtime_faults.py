"""Run-time faults: divergence, exceptions inside blocks and Ctrl-C stop the run with one clear
line, keep everything computed so far, and write it to disk with the right status."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep
from fwdstep.core.block import Block, Param
from fwdstep.core.errors import BlockRuntimeError, DivergenceError
from fwdstep.core.registry import REGISTRY, register

REPO = Path(__file__).resolve().parents[2]

# x' = rate x from x(0) = (1, -1): exp(rate t) passes any bound, then overflows
GROWTH = """\
parameters:
  rate: {rate}
blocks:
  g: {{type: Gain, gain: rate, shape: [2]}}
  int: {{type: Integrator, shape: [2], initial: [1, -1]}}
connections:
  - int.y -> g.u
  - g.y -> int.u
simulation: {{t_final: 20, step: 0.01, bound: {bound}}}
metrics: {{error: int.y}}
"""


def write(tmp_path, text: str, name: str = "d.yaml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def read_outputs(outdir) -> tuple:
    with np.load(os.path.join(outdir, "result.npz")) as data:
        arrays = {k: data[k] for k in data.files}
    with open(os.path.join(outdir, "summary.json")) as fh:
        summary = json.load(fh)
    return arrays, summary


# ------------------------------------------------------------------ divergence
NOT_FINITE = re.compile(r"simulation diverged at t = 0\.47: block 'int' \(Integrator\) "
                        r"state\[[01]\] = (nan|-?inf) is not finite; results up to that time "
                        r"are kept")


def test_non_finite_state_stops_and_keeps_data(tmp_path):
    # rk4 multiplies the state by ~4e6 per step at rate 1e4: from 1e305 straight to inf/NaN
    d = fwdstep.load_diagram(write(tmp_path, GROWTH.format(rate="1e4", bound="1e308")))
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(d)
    err = info.value
    assert NOT_FINITE.fullmatch(str(err)), str(err)
    assert err.block == "int" and err.time == pytest.approx(0.47)
    r = err.result
    assert r.status == "diverged" and r.message == str(err)
    assert len(r.t) == 47 and r.t[-1] == pytest.approx(0.46)
    assert np.all(np.isfinite(r["int.y"]))           # every recorded state is finite
    assert np.all(np.isfinite(r["g.y"][:-1]))          # g.y = 1e4 * 2e305 really overflows
    # the data are the run itself up to that time: x(t) = x0 * (rk4 growth factor)^n
    z = 1e4 * 0.01
    factor = 1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24
    np.testing.assert_allclose(r["int.y"][-1], [factor ** 46, -factor ** 46], rtol=1e-9)


def test_non_finite_state_cli(tmp_path, capsys):
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, GROWTH.format(rate="1e4", bound="1e308")),
                     "-o", str(outdir), "-q", "--no-plots"])
    err = capsys.readouterr().err
    assert code == 3
    assert err.count("\n") == 1 and NOT_FINITE.fullmatch(err[len("fwdstep: "):-1])
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "diverged" and summary["message"] == err[len("fwdstep: "):-1]
    assert summary["t_reached"] == pytest.approx(0.46) and summary["steps"] == 46
    assert arrays["t"].shape == (47,) and arrays["int.y"].shape == (47, 2)
    assert np.all(np.isfinite(arrays["int.y"]))
    # the metrics of a diverged run are finite numbers, not an overflow
    assert summary["metrics"]["final_error_norm"] == pytest.approx(
        np.hypot(*arrays["int.y"][-1]), rel=1e-12)


def test_bound_stops_the_run(tmp_path, capsys):
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, GROWTH.format(rate=50, bound="1e6")),
                     "-o", str(outdir), "-q", "--no-plots"])
    err = capsys.readouterr().err
    assert code == 3
    assert re.fullmatch(r"fwdstep: simulation diverged at t = 0\.28: block 'int' "
                        r"\(Integrator\) state\[0\] = 1\.19682e\+06 exceeds the bound 1e\+06; "
                        r"results up to that time are kept\n", err), err
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "diverged" and summary["simulation"]["bound"] == 1e6
    assert arrays["t"][-1] == pytest.approx(0.27)
    assert np.max(np.abs(arrays["int.y"])) <= 1e6 < 1.19682e6
    z = 50 * 0.01                                      # rk4's growth factor per step
    factor = 1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24
    np.testing.assert_allclose(arrays["int.y"][:, 0], factor ** np.arange(28), rtol=1e-12)


def test_a_run_within_the_bound_is_ok(tmp_path):
    r = fwdstep.simulate(fwdstep.load_diagram(
        write(tmp_path, GROWTH.format(rate=-1, bound="1e6"))))
    assert r.status == "ok" and r.t[-1] == pytest.approx(20.0)


# ------------------------------------------------------------------ exceptions inside blocks
class FragileTestBlock(Block):
    """Test block: passes its input through, raises once the input reaches a threshold."""

    params = {"threshold": Param("float", 1.0, "raise when u[0] >= threshold"),
              "where": Param("choice", "output", "which function raises",
                             choices=("output", "derivative"))}
    raised: list = []

    def setup(self, threshold, where):
        self.declare_input("u", (2,))
        self.declare_output("y", (2,), feedthrough=("u",) if where == "output" else ())
        if where == "derivative":
            self.declare_state(1)
        self.threshold, self.where = threshold, where

    def _check(self, u):
        if u[0][0, 0] >= self.threshold:
            exc = ZeroDivisionError("the fragile block broke")
            FragileTestBlock.raised.append(exc)
            raise exc

    def output(self, t, x, u):
        if self.where == "output":
            self._check(u)
            return (u[0],)
        return (np.zeros((1, 2)),)

    def derivative(self, t, x, u):
        self._check(u)
        return np.zeros((u[0].shape[0], 1))


@pytest.fixture
def fragile():
    register(FragileTestBlock)
    FragileTestBlock.raised = []
    yield FragileTestBlock
    REGISTRY.pop("FragileTestBlock", None)


FRAGILE = """\
blocks:
  src: {{type: Sine, amplitude: [1, 2], frequency: [1, 1]}}
  frag: {{type: FragileTestBlock, threshold: 0.5, where: {where}}}
  int: {{type: Integrator, shape: [2]}}
connections:
  - src.y -> frag.u
  - frag.y -> int.u
simulation: {{t_final: 2, step: 0.01}}
"""


@pytest.mark.parametrize("where", ["output", "derivative"])
def test_block_exception_names_block_time_inputs_and_is_chained(fragile, tmp_path, where):
    d = fwdstep.load_diagram(write(tmp_path, FRAGILE.format(where=where)))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d)
    err = info.value
    # sin(t) first reaches 0.5 at t = pi/6 = 0.5236, in the rk4 stage at 0.52 + 0.005
    assert str(err) == ("block 'frag' (FragileTestBlock) raised ZeroDivisionError: the fragile "
                        "block broke at t = 0.525; inputs: u=[0.5012 1.0024]")
    assert err.block == "frag" and err.time == pytest.approx(0.525)
    assert err.__cause__ is fragile.raised[0]
    assert err.result.status == "error" and err.result.t[-1] == pytest.approx(0.52)
    np.testing.assert_allclose(err.result["src.y"][:, 0], np.sin(err.result.t), atol=1e-12)


def test_block_exception_cli_exit_4_and_partial_results(fragile, tmp_path, capsys):
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, FRAGILE.format(where="output")), "-o", str(outdir)])
    out, err = capsys.readouterr()
    assert code == 4
    assert err == ("fwdstep: block 'frag' (FragileTestBlock) raised ZeroDivisionError: the "
                   "fragile block broke at t = 0.525; inputs: u=[0.5012 1.0024]\n")
    assert "Traceback" not in out + err
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "error" and arrays["t"][-1] == pytest.approx(0.52)


def test_block_exception_at_t0_has_nothing_recorded(fragile, tmp_path, capsys):
    text = FRAGILE.format(where="output").replace("Sine, amplitude: [1, 2], frequency: [1, 1]",
                                                  "Constant, value: [1, 2]")
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, text), "-o", str(outdir)])
    out, err = capsys.readouterr()
    assert code == 4
    assert err == ("fwdstep: block 'frag' (FragileTestBlock) raised ZeroDivisionError: the "
                   "fragile block broke at t = 0; inputs: u=[1. 2.]\n")
    assert out.startswith("error: nothing recorded in ")
    arrays, summary = read_outputs(outdir)
    assert arrays["t"].shape == (0,) and summary["t_reached"] is None


def test_block_exception_during_initialisation_is_wrapped(fragile, tmp_path):
    # reference dynamics take z(0) from their inputs: the block raises before step 0
    text = FRAGILE.format(where="output").replace(
        "Sine, amplitude: [1, 2], frequency: [1, 1]", "Constant, value: [1, 2]").replace(
        "  int: {type: Integrator, shape: [2]}",
        "  ref: {type: ReferenceDynamics, variant: eq2, ell: 1, n: 2, alpha: 1}").replace(
        "  - frag.y -> int.u", "  - frag.y -> ref.q\n  - src.y -> ref.qdot, ref.q_d")
    d = fwdstep.load_diagram(write(tmp_path, text))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d)
    assert str(info.value) == ("block 'frag' (FragileTestBlock) raised ZeroDivisionError: the "
                               "fragile block broke at t = 0; inputs: u=[1. 2.]")
    assert isinstance(info.value.__cause__, ZeroDivisionError)
    assert info.value.result.status == "error" and len(info.value.result.t) == 0


# ------------------------------------------------------------------ Ctrl-C
class InterruptAt(Block):
    """Test block: y = u; raises KeyboardInterrupt (as Ctrl-C would) at t >= at."""

    params = {"at": Param("float", 0.3, "")}

    def setup(self, at):
        self.declare_input("u", (2,))
        self.declare_output("y", (2,))
        self.at = at

    def output(self, t, x, u):
        if t >= self.at:
            raise KeyboardInterrupt
        return (u[0],)


@pytest.fixture
def interrupt_block():
    register(InterruptAt)
    yield InterruptAt
    REGISTRY.pop("InterruptAt", None)


def test_interrupt_in_process_writes_partial_results(interrupt_block, tmp_path, capsys):
    text = FRAGILE.format(where="output").replace(
        "{type: FragileTestBlock, threshold: 0.5, where: output}", "{type: InterruptAt}")
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, text), "-o", str(outdir), "-q", "--no-plots"])
    assert code == 130
    # the step from 0.29 reaches t = 0.3 in its last stage; 0.29 was recorded, nothing later
    assert capsys.readouterr().err == "fwdstep: interrupted by the user at t = 0.29\n"
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "interrupted"
    assert arrays["t"][-1] == pytest.approx(0.29)


LONG = """\
blocks:
  src: {type: Sine, amplitude: [1, 2], frequency: [1, 1]}
  int: {type: Integrator, shape: [2]}
connections:
  - src.y -> int.u
simulation: {t_final: 5000, step: 1e-4, log_every: 1000}
"""


def test_ctrl_c_in_a_real_process(tmp_path):
    outdir = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, str(REPO / "cli.py"), "run",
                             write(tmp_path, LONG), "-o", str(outdir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()      # the first progress line: the loop is running
        assert first.strip().endswith("% simulated"), first
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130
    assert re.fullmatch(r"fwdstep: interrupted by the user at t = [0-9.]+\n", err), err
    assert "Traceback" not in out + err
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "interrupted"
    n = len(arrays["t"])
    assert n >= 2 and arrays["int.y"].shape == (n, 2)
    np.testing.assert_allclose(arrays["int.y"][:, 0], 1 - np.cos(arrays["t"]), atol=1e-9)
    assert summary["t_reached"] == pytest.approx(arrays["t"][-1])
    assert not [f for f in os.listdir(outdir) if f.startswith(".tmp-")]


# ------------------------------------------------------------------ non-finite block outputs
OVERFLOW = """\
blocks:
  src: {type: Constant, value: [1.0e6, 1]}
  ramp: {type: Integrator, shape: [2], initial: [0, 0]}
  big: {type: Gain, gain: 1.0e303, shape: [2]}
  after: {type: Gain, gain: 0.5, shape: [2]}
connections:
  - src.y -> ramp.u
  - ramp.y -> big.u
  - big.y -> after.u
simulation: {t_final: 1, step: 0.01}
metrics: {error: after.y}
"""


def test_overflowing_output_without_a_state_is_not_ok(tmp_path, capsys):
    # big.y = 1e303 * 1e6 t overflows once 1e309 t > 1.797e308, at t > 0.1797: the first
    # recorded row with inf is t = 0.18; no state is involved (ramp stays far below the bound)
    outdir = tmp_path / "out"
    code = cli.main(["run", write(tmp_path, OVERFLOW), "-o", str(outdir), "-q", "--no-plots"])
    assert code == 3
    assert capsys.readouterr().err == (
        "fwdstep: simulation diverged at t = 0.18: block 'big' (Gain) output 'y'[0] = inf is "
        "not finite; results up to that time are kept\n")
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "diverged"
    assert arrays["t"][-1] == pytest.approx(0.18) and np.isinf(arrays["big.y"][-1, 0])
    assert np.isfinite(arrays["big.y"][:-1]).all()


def test_overflowing_output_in_one_variant_of_a_batch(tmp_path):
    # g 1e150 t: finite for g = 1, inf from t = 0.01 for g = 1e200; only that variant diverges
    text = """\
parameters:
  g: 1
blocks:
  src: {type: Constant, value: [1.0e150, 1]}
  ramp: {type: Integrator, shape: [2]}
  big: {type: Gain, gain: g, shape: [2]}
  after: {type: Gain, gain: 0.5, shape: [2]}
connections:
  - src.y -> ramp.u
  - ramp.y -> big.u
  - big.y -> after.u
simulation: {t_final: 1, step: 0.01, bound: 1.0e300}
metrics: {error: after.y}
"""
    from fwdstep.sweeps.sweep import run_sweep
    res = run_sweep(write(tmp_path, text), grid={"g": [1.0, 1.0e200]})
    assert [(v.status, v.diverged_at) for v in res.variants] == [("ok", None), ("diverged", 0.01)]


# ------------------------------------------------------------------ output shape at run time
class ShapeshifterTestBlock(Block):
    """Test block: declares y of shape (2,), returns shape (3,) from t = 0.5 on."""

    params = {}

    def setup(self):
        self.declare_input("u", (2,))
        self.declare_output("y", (2,))

    def output(self, t, x, u):
        return (u[0] if t < 0.5 else np.zeros((u[0].shape[0], 3)),)


@pytest.mark.parametrize("downstream", ["Gain", "Integrator"])
def test_an_output_changing_shape_is_blamed_on_its_block_not_downstream(tmp_path, downstream):
    register(ShapeshifterTestBlock)
    try:
        text = FRAGILE.format(where="output").replace(
            "{type: FragileTestBlock, threshold: 0.5, where: output}",
            "{type: ShapeshifterTestBlock}").replace(
            "int: {type: Integrator, shape: [2]}",
            "int: {type: %s, shape: [2]%s}" % (downstream, ", gain: 2" * (downstream == "Gain")))
        d = fwdstep.load_diagram(write(tmp_path, text))
        with pytest.raises(BlockRuntimeError) as info:
            fwdstep.simulate(d)
    finally:
        REGISTRY.pop("ShapeshifterTestBlock", None)
    assert str(info.value) == ("block 'frag' (ShapeshifterTestBlock) output 'y' has shape (3,) "
                               "at t = 0.5, but declares (2,)")
    assert info.value.block == "frag" and info.value.result.t[-1] == pytest.approx(0.49)


def test_a_non_finite_output_stops_a_long_run_early(tmp_path):
    # 10^6 steps of 0.1 ms; big.y overflows at t = 0.1798: the run stops within 8192 steps
    text = OVERFLOW.replace("t_final: 1, step: 0.01", "t_final: 100, step: 0.0001")
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(fwdstep.load_diagram(write(tmp_path, text)))
    assert str(info.value).startswith("simulation diverged at t = 0.1798: block 'big' (Gain) "
                                      "output 'y'[0] = inf is not finite")
    assert info.value.result.steps < 1798 + 8192
    assert info.value.result.t[-1] == pytest.approx(0.1798)


# ------------------------------------------------------------------ outputs that are not recorded
# big.y = g * 1e150 t overflows for g = 1e200 from the first step (t = 0.01); it feeds a
# Saturation (inf -> 1), so the integrator behind it stays finite and bounded: no state check
# can see it, and neither big nor sat is recorded
UNLOGGED = """\
parameters:
  g: 1
blocks:
  src: {type: Constant, value: [1.0e150, 1]}
  ramp: {type: Integrator, shape: [2]}
  big: {type: Gain, gain: g, shape: [2]}
  sat: {type: Saturation, lower: -1, upper: 1, shape: [2]}
  held: {type: Integrator, shape: [2]}
  one: {type: Constant, value: [1, 2]}
  slope: {type: Gain, gain: g, shape: [2]}
  tracked: {type: Integrator, shape: [2]}
connections:
  - src.y -> ramp.u
  - ramp.y -> big.u
  - big.y -> sat.u
  - sat.y -> held.u
  - one.y -> slope.u
  - slope.y -> tracked.u
simulation: {t_final: 1, step: 0.01, bound: 1.0e300}
log: [tracked.y]
metrics: {error: tracked.y}
"""


def test_an_unrecorded_output_that_overflows_stops_the_run(tmp_path, capsys):
    path = write(tmp_path, UNLOGGED.replace("g: 1\n", "g: 1.0e200\n"))
    d = fwdstep.load_diagram(path)
    assert "big.y" not in d.logged and "sat.y" not in d.logged
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(d)
    assert str(info.value) == ("simulation diverged at t = 0.01: block 'big' (Gain) output "
                               "'y'[0] = inf is not finite; results up to that time are kept")
    assert info.value.block == "big" and info.value.result.status == "diverged"
    assert info.value.result.t[-1] == pytest.approx(0.01)
    outdir = tmp_path / "out"
    assert cli.main(["run", path, "-o", str(outdir), "-q", "--no-plots"]) == 3
    assert capsys.readouterr().err == f"fwdstep: {info.value}\n"
    arrays, summary = read_outputs(outdir)
    assert summary["status"] == "diverged" and arrays["t"][-1] == pytest.approx(0.01)


def test_an_unrecorded_output_that_stays_finite_is_ok(tmp_path):
    # the same diagram with g = 1: every output finite, tracked.y = g (1, 2) t exactly
    r = fwdstep.simulate(fwdstep.load_diagram(write(tmp_path, UNLOGGED)))
    assert r.status == "ok"
    np.testing.assert_allclose(r["tracked.y"][-1], [1.0, 2.0], rtol=1e-12)


def test_a_sweep_marks_only_the_variant_whose_unrecorded_output_overflows(tmp_path):
    from fwdstep.results.result import error_metrics
    from fwdstep.sweeps.sweep import run_sweep
    path = write(tmp_path, UNLOGGED)
    res = run_sweep(path, grid={"g": [1.0, 1.0e200, 3.0]}, workers=1)
    assert [size for size, _ in res.batches] == [3]                   # one batch of three
    assert [(v.status, v.diverged_at) for v in res.variants] == [
        ("ok", None), ("diverged", 0.01), ("ok", None)]
    for v in (res.variants[0], res.variants[2]):                      # as run one by one
        r = fwdstep.simulate(fwdstep.load_diagram(path, {"g": v.values["g"]}))
        alone = error_metrics(r.t, r["tracked.y"], 0.2)
        assert v.metrics == {m: alone[m] for m in v.metrics} and len(v.metrics) == 4
        # |tracked.y(1)| = |g (1, 2)| = sqrt(5) g
        assert alone["final_error_norm"] == pytest.approx(5 ** 0.5 * v.values["g"], rel=1e-12)
    with pytest.raises(DivergenceError) as info:                     # its row says why
        fwdstep.simulate(fwdstep.load_diagram(path, {"g": 1.0e200}))
    assert res.variants[1].message == str(info.value)
    assert "block 'big' (Gain) output 'y'[0] = inf" in str(info.value)


def test_a_sweep_row_names_the_state_that_diverged_as_its_run_alone(tmp_path):
    from fwdstep.sweeps.sweep import run_sweep
    path = write(tmp_path, GROWTH.format(rate="rate", bound="1e6").replace("rate: rate",
                                                                            "rate: 1"))
    res = run_sweep(path, grid={"rate": [0.01, 100.0]}, workers=1)
    assert [size for size, _ in res.batches] == [2]
    assert [v.status for v in res.variants] == ["ok", "diverged"]
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(fwdstep.load_diagram(path, {"rate": 100.0}))
    assert res.variants[1].message == str(info.value) == (
        "simulation diverged at t = 0.14: block 'int' (Integrator) state[0] = 1.14243e+06 "
        "exceeds the bound 1e+06; results up to that time are kept")   # e^(100 t) > 1e6


@pytest.mark.parametrize("solver", ["rk4", "dop853"])
def test_an_unrecorded_output_is_checked_with_fixed_and_adaptive_solvers(tmp_path, solver):
    # big.y = 1e308 t is finite up to t = 1.79 and inf from 1.8 (> 1.797e308) on; the
    # integrators see only sat(big.y) and a slope of 1 (finite for every solver)
    text = (UNLOGGED.replace("g: 1\n", "g: 1.0e308\n").replace("[1.0e150, 1]", "[1, 1]")
            .replace("slope: {type: Gain, gain: g", "slope: {type: Gain, gain: 1")
            .replace("t_final: 1, step: 0.01, bound: 1.0e300",
                     f"t_final: 3, step: 0.01, solver: {solver}"))
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(fwdstep.load_diagram(write(tmp_path, text)))
    assert str(info.value) == ("simulation diverged at t = 1.8: block 'big' (Gain) output "
                               "'y'[0] = inf is not finite; results up to that time are kept")
    assert info.value.result.t[-1] == pytest.approx(1.8)


@pytest.mark.slow
def test_an_unrecorded_output_is_checked_on_the_compiled_backend(tmp_path):
    # numba compiles this structure (~30 s CPU): a single run and a batch, as above
    pytest.importorskip("numba")
    path = write(tmp_path, UNLOGGED)
    with pytest.raises(DivergenceError) as info:
        fwdstep.simulate(fwdstep.load_diagram(path, {"g": 1.0e200}), backend="compiled")
    assert str(info.value) == ("simulation diverged at t = 0.01: block 'big' (Gain) output "
                               "'y'[0] = inf is not finite; results up to that time are kept")
    assert info.value.block == "big" and info.value.result.t[-1] == pytest.approx(0.01)
    # one batch of three variants, run in parallel by the compiled program
    from fwdstep.structure.spec import load_spec
    d = fwdstep.compile_batch([load_spec(path, {"g": g}) for g in (1.0, 1.0e200, 3.0)])
    r = fwdstep.simulate(d, backend="compiled")
    assert r.status == "partially diverged"
    assert list(np.isnan(r.diverged_at)) == [True, False, True] and r.diverged_at[1] == 0.01
    assert r.reasons == {1: str(info.value)}                          # its own line
    np.testing.assert_allclose(r["tracked.y"][-1], [[1, 2], [np.nan, np.nan], [3, 6]],
                               rtol=1e-12)                            # g (1, 2) t at t = 1


def test_a_block_error_with_matrix_inputs_is_one_line(tmp_path):
    """Found by the fuzz test: a Solve of a zero (3, 2) matrix raises inside numpy; the
    message shows its matrix input on one line (numpy prints matrices over several)."""
    path = tmp_path / "singular.yaml"
    path.write_text("blocks:\n"
                    "  A: {type: Constant, value: [[0, 0], [0, 0], [0, 0]]}\n"
                    "  b: {type: Constant, value: [0, 0, 0]}\n"
                    "  s: {type: Solve, shape: [3, 2]}\n"
                    "connections:\n  - A.y -> s.A\n  - b.y -> s.b\n"
                    "simulation: {t_final: 0.01, step: 0.001, solver: euler}\n")
    d = fwdstep.load_diagram(str(path))
    with pytest.raises(fwdstep.BlockRuntimeError) as info:
        fwdstep.simulate(d)
    text = str(info.value)
    assert "\n" not in text and "A=[[0. 0.] [0. 0.] [0. 0.]]" in text, text
