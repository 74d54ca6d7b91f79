"""A block's results are taken as declared or refused, on every backend: a kernel returning
(B, 1) for a (B, 3) output or derivative is the block's error (it was broadcast into three
equal columns, status ok), and a kernel raising SystemExit (any exception but a signal's
KeyboardInterrupt) is the block's error too (it ended fwdstep with exit 0, nothing written).
The references are the declared shapes and the README's exit codes (4: a block's error)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import fwdstep
from fwdstep.core.block import Block
from fwdstep.core.errors import BlockRuntimeError
from fwdstep.core.registry import REGISTRY, register

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CLI = os.path.join(ROOT, "cli.py")


def _narrow_output(t, x, u):
    return (2.0 * u[:, :1],)                 # (B, 1) for a declared (3,)


def _narrow_derivative(t, x, u):
    return u[:, :1]                          # (B, 1) for 3 states


def _state(t, x, u):
    return (x,)


def _exit_output(t, x, u):
    raise SystemExit(0)


class NarrowOutputTestBlock(Block):
    """Test block: declares y (3,), its kernel returns (B, 1)."""

    params = {}

    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=("u",))
        self.set_kernels(output=_narrow_output)


class NarrowDerivativeTestBlock(Block):
    """Test block: 3 states, its derivative kernel returns (B, 1)."""

    params = {}

    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=())
        self.declare_state(3)
        self.set_kernels(output=_state, derivative=_narrow_derivative)


class ExitTestBlock(Block):
    """Test block: its output kernel raises SystemExit(0)."""

    params = {}

    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=("u",))
        self.set_kernels(output=_exit_output)


class NarrowLaterTestBlock(Block):
    """Test block called in object mode: y = u until t = 0.5, then (1, 1)."""

    params = {}
    compile_with = "objmode"

    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=("u",))

    def output(self, t, x, u):
        return (u[0] if t < 0.5 else u[0][:, :1],)


TEST_BLOCKS = (NarrowOutputTestBlock, NarrowDerivativeTestBlock, ExitTestBlock,
               NarrowLaterTestBlock)

DIAGRAM = """\
blocks:
  src: {{type: Constant, value: [1, 2, 3]}}
  b:   {{type: {block}}}
  int: {{type: Integrator, shape: [3]}}
connections:
  - src.y -> b.u
  - b.y -> int.u
simulation: {{t_final: 1, step: 0.01, solver: {solver}}}
"""


@pytest.fixture
def blocks():
    for cls in TEST_BLOCKS:
        register(cls)
    yield
    for cls in TEST_BLOCKS:
        REGISTRY.pop(cls.__name__, None)


def _diagram(tmp_path, block, solver="rk4"):
    path = tmp_path / "d.yaml"
    path.write_text(DIAGRAM.format(block=block, solver=solver))
    return str(path)


def _backends():
    try:
        import numba  # noqa: F401
    except ImportError:
        return ["numpy", pytest.param("compiled", marks=pytest.mark.skip("numba missing"))]
    return ["numpy", "compiled"]


@pytest.mark.parametrize("backend", _backends())
def test_a_narrow_output_is_the_blocks_error(blocks, tmp_path, backend, numba_cache):
    d = fwdstep.load_diagram(_diagram(tmp_path, "NarrowOutputTestBlock"))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d, backend=backend)
    assert str(info.value) == ("block 'b' (NarrowOutputTestBlock) output 'y' has shape (1,) "
                               "at t = 0, but declares (3,)")
    assert info.value.block == "b" and info.value.result.status == "error"


@pytest.mark.parametrize("backend", _backends())
def test_a_narrow_derivative_is_the_blocks_error(blocks, tmp_path, backend, numba_cache):
    d = fwdstep.load_diagram(_diagram(tmp_path, "NarrowDerivativeTestBlock"))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d, backend=backend)
    assert str(info.value) == ("block 'b' (NarrowDerivativeTestBlock) derivative has shape "
                               "(1,) at t = 0, but the block declares 3 states")


@pytest.mark.parametrize("solver", ["dop853", "radau"])
def test_a_narrow_result_under_solve_ivp(blocks, tmp_path, solver):
    d = fwdstep.load_diagram(_diagram(tmp_path, "NarrowDerivativeTestBlock", solver))
    with pytest.raises(BlockRuntimeError, match=r"derivative has shape \(1,\) at t = 0"):
        fwdstep.simulate(d)


def test_a_batch_axis_of_another_length_is_refused(tmp_path):
    """(2, 3) from a block of a batch of 3 is neither one row for all nor one per variant."""
    from fwdstep.run.evaluate import _fits
    assert _fits(np.zeros((3, 3)), 3, (3,)) and _fits(np.zeros((1, 3)), 3, (3,))
    assert not _fits(np.zeros((2, 3)), 3, (3,)) and not _fits(np.zeros((3, 1)), 3, (3,))
    assert not _fits(np.zeros(3), 3, (3,)) and not _fits(np.zeros((3, 3, 1)), 3, (3,))
    assert _fits(np.zeros(3), 3, ()) and not _fits(np.float64(1.0), 1, ())


def test_an_objmode_block_narrowing_mid_run_on_the_compiled_backend(blocks, tmp_path,
                                                                   numba_cache, monkeypatch):
    """Object mode inside the compiled loop (where compiling cannot help, runs take the
    NumPy path: switched off here to exercise the compiled loop's own check)."""
    pytest.importorskip("numba")
    from fwdstep.compiled import driver
    monkeypatch.setattr(driver, "PICK_NUMPY_FOR_OBJECT_MODE", False)
    d = fwdstep.load_diagram(_diagram(tmp_path, "NarrowLaterTestBlock"))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d, backend="compiled")
    assert str(info.value).startswith("block 'b' (NarrowLaterTestBlock) output 'y' has shape "
                                      "(1,) at t = 0.5")
    assert info.value.result.t[-1] == pytest.approx(0.49)
    np.testing.assert_allclose(info.value.result["int.y"][-1], 0.49 * np.array([1, 2, 3]))


@pytest.mark.parametrize("backend", _backends())
def test_system_exit_in_a_kernel_is_the_blocks_error(blocks, tmp_path, backend, numba_cache):
    d = fwdstep.load_diagram(_diagram(tmp_path, "ExitTestBlock"))
    with pytest.raises(BlockRuntimeError) as info:
        fwdstep.simulate(d, backend=backend)
    assert str(info.value) == ("block 'b' (ExitTestBlock) raised SystemExit: 0 at t = 0; "
                               "inputs: u=[1. 2. 3.]")
    assert isinstance(info.value.__cause__, SystemExit)


PLUGIN = '''
import numpy as np
from fwdstep.block import Block
from fwdstep.registry import register

def narrow(t, x, u):
    return (u[:, :1],)

def leave(t, x, u):
    if t >= 0.3:
        raise SystemExit(0)
    return (u,)

@register
class Narrow(Block):
    """(B, 1) for (3,)."""
    params = {}
    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=("u",))
        self.set_kernels(output=narrow)

@register
class Leave(Block):
    """SystemExit(0) from t = 0.3."""
    params = {}
    def setup(self):
        self.declare_input("u", (3,))
        self.declare_output("y", (3,), feedthrough=("u",))
        self.set_kernels(output=leave)
'''


@pytest.mark.parametrize("block, line", [
    ("Narrow", "fwdstep: block 'b' (Narrow) output 'y' has shape (1,) at t = 0, but declares "
               "(3,)\n"),
    ("Leave", "fwdstep: block 'b' (Leave) raised SystemExit: 0 at t = 0.3; inputs: "
              "u=[1. 2. 3.]\n")])
def test_cli_exit_4_one_line_and_data_kept(tmp_path, block, line):
    plugin = tmp_path / "plugin.py"
    plugin.write_text(textwrap.dedent(PLUGIN))
    out = tmp_path / "out"
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=ROOT)
    run = subprocess.run([sys.executable, CLI, "run", _diagram(tmp_path, block), "-o", str(out),
                          "--plugin", str(plugin), "-q", "--no-plots"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 4 and run.stderr == line
    with open(out / "summary.json") as fh:
        assert json.load(fh)["status"] == "error"
    with np.load(out / "result.npz") as data:
        t = data["t"]
    assert len(t) == (0 if block == "Narrow" else 30)      # 0, 0.01, ..., 0.29 kept
