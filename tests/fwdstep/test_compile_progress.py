"""The compiled backend's progress news (simulate(on_compile=...)): a line before compiling
a never-seen structure with an estimate, one after; the NumPy path picked when compiling
cannot help (object-mode blocks in a stage that does not trace)."""
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.cli.commands import _compile_news

pytest.importorskip("numba")
pin = pytest.importorskip("pinocchio")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def robot(name, t_final):
    return fwdstep.load_diagram(os.path.join(ROOT, "diagrams", "robots", f"{name}.yaml"),
                                {"t_final": t_final})


@pytest.fixture
def nothing_compiled():
    """The process's compiled stages forgotten for the test, and remembered again after it
    (with the new ones: an LLVM engine is never destroyed while its code may be called)."""
    from fwdstep.compiled import llvm_stage
    saved = dict(llvm_stage._compiled)
    llvm_stage._compiled.clear()
    yield llvm_stage._compiled
    llvm_stage._compiled.update(saved)


def test_a_never_seen_stage_is_announced_with_an_estimate(nothing_compiled):
    from fwdstep.compiled import backend_numba
    news = []
    d = robot("ur5_task_space", 0.01)
    r = fwdstep.simulate(d, backend="compiled", on_compile=lambda e, i: news.append((e, i)))
    assert [e for e, _ in news] == ["compiling", "compiled"]
    info = news[0][1]
    assert info["what"] == "scalar stage" and info["diagram"] == d.file
    assert len(nothing_compiled) == 1 and 2000 < info["operations"] < 5000
    low = backend_numba.compile_estimate("stage", info["operations"])
    assert low <= info["estimate_s"] <= low + backend_numba.LOOP_SECONDS
    assert news[1][1]["seconds"] > 0
    # again in this process: nothing to compile, nothing said
    news.clear()
    again = fwdstep.simulate(robot("ur5_task_space", 0.01), backend="compiled",
                             on_compile=lambda e, i: news.append((e, i)))
    assert news == [] and np.array_equal(again["e.y"], r["e.y"])


def test_object_mode_only_runs_the_numpy_path_with_a_note():
    news = []
    d = robot("ur5_theorem6", 0.005)
    got = fwdstep.simulate(d, backend="compiled", on_compile=lambda e, i: news.append((e, i)))
    assert [e for e, _ in news] == ["numpy"]
    assert got.backend == "numpy"                          # the record says what ran
    assert "does not trace" in news[0][1]["reason"] and "arm" in news[0][1]["reason"]
    ref = fwdstep.simulate(robot("ur5_theorem6", 0.005), backend="numpy")
    for name in ref.names:
        assert np.array_equal(got[name], ref[name], equal_nan=True), name


def test_the_cli_lines(capsys):
    _compile_news("compiling", {"diagram": "/x/panda_slotine_li.yaml", "what": "scalar stage",
                                "operations": 4890, "estimate_s": 2.8})
    _compile_news("compiled", {"seconds": 3.04})
    _compile_news("numpy", {"reason": "its stage does not trace"})
    assert capsys.readouterr().err.splitlines() == [
        "fwdstep: compiling panda_slotine_li.yaml for the compiled backend (4890 scalar "
        "operations, about 3 s) ...",
        "fwdstep: compiled in 3.0 s",
        "fwdstep: note: running the NumPy path: its stage does not trace, which compiling "
        "would not make faster"]
