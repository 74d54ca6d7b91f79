"""A run records what made it (issue 24): fwdstep version, backend, solver settings, every
``--set`` as typed, the parameters as evaluated, plugin files with their SHA-256 and a copy
of every diagram file read; ``fwdstep rerun`` redoes exactly that, bit for bit, and
``report`` draws the copy, never the working tree."""
import hashlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import fwdstep
from fwdstep.cli import arguments as cli

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")
THEOREM6 = os.path.join(ROOT, "diagrams", "theorem6.yaml")
CLI = os.path.join(ROOT, "cli.py")


def _arrays(outdir) -> dict:
    with np.load(os.path.join(outdir, "result.npz")) as data:
        return {k: data[k] for k in data.files}


def _summary(outdir) -> dict:
    with open(os.path.join(outdir, "summary.json"), encoding="utf-8") as fh:
        return json.load(fh)


def _sha(path) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _same_arrays(a, b) -> bool:
    return sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def theorem1_run(tmp_path_factory):
    outdir = str(tmp_path_factory.mktemp("prov") / "theorem1")
    code = cli.main(["run", THEOREM1, "--set", "Ks.gain=80*eye(2)",
                     "--set", "simulation.t_final=2", "-o", outdir, "-q", "--no-plots"])
    assert code == 0
    return outdir


def test_summary_records_the_parameters_as_evaluated_after_every_set(theorem1_run):
    s = _summary(theorem1_run)
    assert s["blocks"]["Ks"]["gain"] == [[80, 0], [0, 80]]          # the block path --set
    assert s["blocks"]["Ks"]["type"] == "Gain"
    assert s["simulation"]["t_final"] == 2                           # simulation.t_final
    assert s["parameters"]["ell"] == 2 and isinstance(s["parameters"]["ell"], int)
    assert s["parameters"]["b1"] == 0.2
    # the diagram's K and t_final are what Ks.gain and simulation.t_final were: no longer read
    assert s["unused_parameters"] == ["K", "t_final"]
    prov = s["provenance"]
    assert prov["sets"] == ["Ks.gain=80*eye(2)", "simulation.t_final=2"]
    assert prov["overrides"] == {"Ks.gain": "80*eye(2)", "simulation.t_final": 2}
    assert prov["fwdstep_version"] == fwdstep.__version__
    assert prov["backend"] == "numpy" and prov["simulation"]["solver"] == "rk4"
    assert prov["simulation"]["t_final"] == 2 and prov["plugins"] == []
    assert prov["command"][:2] == ["fwdstep", "run"]


def test_the_diagram_as_run_is_copied_and_listed_in_the_manifest(theorem1_run):
    s = _summary(theorem1_run)
    assert s["diagram"] == "diagram/theorem1.yaml"                   # relative: any folder
    copy = os.path.join(theorem1_run, "diagram", "theorem1.yaml")
    with open(copy, "rb") as fh, open(THEOREM1, "rb") as original:
        assert fh.read() == original.read()
    (entry,) = s["provenance"]["files"]
    assert entry["copy"] == "diagram/theorem1.yaml" and entry["sha256"] == _sha(THEOREM1)
    assert entry["source"] == THEOREM1
    with open(os.path.join(theorem1_run, "manifest.json")) as fh:
        manifest = json.load(fh)["files"]
    assert manifest["diagram/theorem1.yaml"]["sha256"] == _sha(THEOREM1)


def test_rerun_from_another_folder_is_bit_identical(theorem1_run, tmp_path, monkeypatch,
                                                      capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["rerun", theorem1_run, "-o", "again", "-q", "--no-plots"]) == 0
    assert _same_arrays(_arrays(theorem1_run), _arrays("again"))
    again = _summary("again")
    assert again["provenance"]["sets"] == ["Ks.gain=80*eye(2)", "simulation.t_final=2"]
    assert again["provenance"]["rerun_of"] == theorem1_run
    assert again["provenance"]["diagram_source"] == THEOREM1
    assert again["blocks"]["Ks"]["gain"] == [[80, 0], [0, 80]]


def test_rerun_reads_the_copy_not_the_edited_file_and_report_draws_it(tmp_path, monkeypatch,
                                                                       capsys):
    """A diagram edited (and a subsystem file removed) after the run: the rerun and the
    report use the copy; the whole output directory may move."""
    work = tmp_path / "work"
    shutil.copytree(os.path.join(ROOT, "diagrams", "lib"), work / "lib")
    shutil.copy(THEOREM6, work / "t6.yaml")
    monkeypatch.chdir(work)
    assert cli.main(["run", "t6.yaml", "--set", "simulation.t_final=0.4", "--set",
                     "tq.lam=9", "-o", "out/t6", "-q", "--no-plots"]) == 0
    s = _summary("out/t6")
    assert sorted(f["copy"] for f in s["provenance"]["files"]) == sorted(
        ["diagram/t6.yaml"] + [f"diagram/lib/{n}.yaml" for n in
                               ("plant", "qd_star", "reference", "torque_passive",
                                "error_augmentation")])
    assert s["provenance"]["sets"][1] == "tq.lam=9"
    # edit the working tree: the gain changes, a block is renamed, a subsystem file goes
    text = (work / "t6.yaml").read_text()
    (work / "t6.yaml").write_text(text.replace("tq:", "tqq:").replace("tq.", "tqq."))
    os.remove(work / "lib" / "plant.yaml")
    shutil.move(str(work / "out" / "t6"), str(tmp_path / "moved"))
    monkeypatch.chdir(tmp_path)
    assert cli.main(["rerun", "moved", "-o", "again", "-q", "--no-plots"]) == 0
    assert _same_arrays(_arrays("moved"), _arrays("again"))
    other = tmp_path / "elsewhere"
    other.mkdir()
    monkeypatch.chdir(other)
    assert cli.main(["report", "../moved"]) == 0
    page = (tmp_path / "moved" / "report.html").read_text()
    assert "no picture" not in page and "image/svg+xml" in page
    assert "Set on the command line" in page and "tq.lam=9" in page
    from fwdstep.views.report import recorded_diagram
    d = recorded_diagram(_summary(tmp_path / "moved"), str(tmp_path / "moved"))
    assert any(b.name.startswith("tq/") for b in d.blocks)           # as run, not as edited
    assert not any(b.name.startswith("tqq/") for b in d.blocks)


def test_result_save_from_python_records_the_overrides(tmp_path):
    d = fwdstep.load_diagram(THEOREM1, {"ell": 3, "simulation.t_final": 0.2})
    fwdstep.simulate(d).save(str(tmp_path / "api"))
    s = _summary(tmp_path / "api")
    assert s["provenance"]["overrides"] == {"ell": 3, "simulation.t_final": 0.2}
    assert "sets" not in s["provenance"]
    assert cli.main(["rerun", str(tmp_path / "api"), "-o", str(tmp_path / "api2"), "-q"]) == 0
    assert _same_arrays(_arrays(tmp_path / "api"), _arrays(tmp_path / "api2"))


PLUGIN = os.path.join(ROOT, "examples", "plugins", "logistic.py")


def test_rerun_refuses_in_one_line_when_a_plugin_changed(tmp_path):
    plugin = tmp_path / "decay_plugin.py"
    shutil.copy(PLUGIN, plugin)
    diagram = tmp_path / "d.yaml"
    diagram.write_text("blocks:\n  inflow: {type: Constant, value: [0.0]}\n"
                       "  pop: {type: Logistic, rate: 2, capacity: 3, x0: 0.5}\n"
                       "connections: [inflow.y -> pop.u]\n"
                       "simulation: {t_final: 1, step: 0.01}\n")
    env = {**os.environ, "PYTHONPATH": ROOT, "MPLBACKEND": "Agg"}
    env.pop("FWDSTEP_PLUGINS", None)

    def fwd(*args):
        return subprocess.run([sys.executable, CLI, *args], capture_output=True, text=True,
                              env=env, cwd=tmp_path, timeout=120)

    first = fwd("run", "d.yaml", "--plugin", "decay_plugin.py", "-o", "one", "-q",
                "--no-plots")
    assert first.returncode == 0, first.stderr
    (entry,) = _summary(tmp_path / "one")["provenance"]["plugins"]
    assert entry == {"file": str(plugin), "sha256": _sha(plugin)}
    same = fwd("rerun", "one", "-o", "two", "-q", "--no-plots")   # no --plugin needed
    assert same.returncode == 0, same.stderr
    assert _same_arrays(_arrays(tmp_path / "one"), _arrays(tmp_path / "two"))
    plugin.write_text(plugin.read_text() + "\n# edited after the run\n")
    changed = fwd("rerun", "one", "-o", "three", "-q", "--no-plots")
    assert changed.returncode == 2
    assert changed.stderr.count("\n") == 1 and "decay_plugin.py has changed" in changed.stderr
    assert not os.path.exists(tmp_path / "three")


def test_rerun_of_a_directory_without_a_record_is_refused_in_one_line(tmp_path, capsys):
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "summary.json").write_text(json.dumps({"status": "ok"}))
    assert cli.main(["rerun", str(tmp_path / "old"), "-o", str(tmp_path / "new")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "records no copy of the diagram" in err


def test_a_sweep_records_its_diagram_and_command(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["sweep", THEOREM1, "--grid", "alpha=3,4", "--set",
                     "simulation.t_final=0.2", "-o", "sw", "-q", "--workers", "1"]) == 0
    with open("sw/sweep.json") as fh:
        record = json.load(fh)
    assert record["diagram"] == "diagram/theorem1.yaml"
    assert os.path.isfile("sw/diagram/theorem1.yaml")
    assert record["provenance"]["sets"] == ["simulation.t_final=0.2"]
    assert record["provenance"]["grid"] == ["alpha=3,4"]
    assert record["sweep"]["variants"] == [{"alpha": 3}, {"alpha": 4}]


def test_the_record_names_the_optional_packages_that_computed(tmp_path):
    """A run in a fresh process records the versions of the optional numeric packages the
    process loaded (scipy, loaded here before the run) and none of those it did not."""
    scipy = pytest.importorskip("scipy")
    out = str(tmp_path / "run")
    code = ("import json, sys, scipy; from fwdstep.cli.arguments import main; "
            f"rc = main(['run', {THEOREM1!r}, '--set', 't_final=0.1', '-o', {out!r}, '-q', "
            "'--no-plots']); print(json.dumps({n: getattr(sys.modules.get(n), '__version__', "
            "None) for n in ('scipy', 'numba', 'llvmlite', 'pinocchio')})); sys.exit(rc)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout.strip().splitlines()[-1])
    prov = _summary(out)["provenance"]
    assert prov["scipy"] == scipy.__version__
    for name, version in loaded.items():
        assert prov.get(name) == version, name            # loaded: recorded; else absent
