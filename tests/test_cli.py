"""The ``fwdstep`` command (cli.py parses, fwdstep.cli.commands works), run in-process through
``cli.main`` except one check that the installed console script is wired up."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
from fwdstep.structure.library import load_library

ROOT = os.path.normpath(os.path.join(os.path.dirname(__file__), ".."))
THEOREM1 = os.path.join(ROOT, "diagrams", "theorem1.yaml")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def theorem1_run(tmp_path_factory):
    """``fwdstep run diagrams/theorem1.yaml -o OUT`` once, shared by the tests below."""
    outdir = str(tmp_path_factory.mktemp("run") / "theorem1")
    code = cli.main(["run", THEOREM1, "-o", outdir, "--quiet"])
    return code, outdir


def test_run_exits_0_and_writes_results_summary_and_figures(theorem1_run):
    code, outdir = theorem1_run
    assert code == 0
    assert sorted(os.listdir(outdir)) == sorted(
        ["result.npz", "summary.json", "tracking_error.png", "torque.png",
         "parameter_estimates.png", "manifest.json", "diagram"])
    for name in ("tracking_error.png", "torque.png", "parameter_estimates.png"):
        with open(os.path.join(outdir, name), "rb") as fh:
            assert fh.read(8) == PNG_MAGIC


def test_result_npz_holds_time_and_every_logged_signal(theorem1_run):
    _, outdir = theorem1_run
    with np.load(os.path.join(outdir, "result.npz")) as data:
        arrays = {k: data[k] for k in data.files}
    t = arrays["t"]
    assert t[0] == 0 and t[-1] == pytest.approx(10.0)
    assert np.allclose(np.diff(t), 0.01)              # step 0.002, log_every 5
    expected = {"e.y": (2,), "tau.y": (2,), "adapt.theta_hat": (4,), "truth.y": (4,),
                "arm.q": (2,), "qd.y": (2,)}
    assert set(arrays) == {"t"} | set(expected)
    for name, shape in expected.items():
        assert arrays[name].shape == (len(t),) + shape
    np.testing.assert_allclose(arrays["e.y"], arrays["arm.q"] - arrays["qd.y"], atol=1e-15)


def test_summary_json_has_parameters_solver_step_wall_time_metrics(theorem1_run):
    _, outdir = theorem1_run
    with open(os.path.join(outdir, "summary.json")) as fh:
        summary = json.load(fh)
    assert summary["status"] == "ok"
    assert summary["parameters"]["ell"] == 2
    assert summary["parameters"]["K"] == [[50, 0], [0, 50]]
    assert summary["simulation"]["solver"] == "rk4"
    assert summary["simulation"]["step"] == 0.002
    assert summary["wall_time_s"] > 0
    metrics = summary["metrics"]
    assert set(metrics) >= {"final_error_norm", "tail_error_norm_max", "rms_error_norm"}
    assert metrics["final_error_norm"] < 1e-4
    assert metrics["tail_error_norm_max"] >= metrics["final_error_norm"]


def test_run_refuses_to_overwrite_without_force(theorem1_run, capsys):
    _, outdir = theorem1_run
    assert cli.main(["run", THEOREM1, "-o", outdir]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err and "Traceback" not in err


def test_run_set_overrides_parameters(tmp_path, capsys):
    outdir = str(tmp_path / "out")
    code = cli.main(["run", THEOREM1, "--set", "ell=3", "--set", "t_final=0.5",
                     "--set", "K=80*eye(2)", "-o", outdir, "--no-plots"])
    assert code == 0
    out = capsys.readouterr().out
    assert "final |e|" in out
    with open(os.path.join(outdir, "summary.json")) as fh:
        summary = json.load(fh)
    assert summary["parameters"]["ell"] == 3
    assert summary["parameters"]["K"] == [[80, 0], [0, 80]]
    assert summary["simulation"]["t_final"] == 0.5
    # ell = 3: the reference dynamics' state grows, q_d becomes a parabola (3 coefficients)
    assert np.shape(summary["parameters"]["qd_coefficients"]) == (2, 3)
    assert sorted(os.listdir(outdir)) == ["diagram", "manifest.json", "result.npz",
                                          "summary.json"]


def test_run_with_an_unknown_parameter_exits_2_with_one_line(tmp_path, capsys):
    code = cli.main(["run", THEOREM1, "--set", "elll=3", "-o", str(tmp_path / "x")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "elll" in err and "ell" in err
    assert not os.path.exists(tmp_path / "x" / "result.npz")


def test_validate_exits_0(capsys):
    assert cli.main(["validate", THEOREM1]) == 0
    out = capsys.readouterr().out
    assert out.startswith(THEOREM1) and ": ok" in out


@pytest.mark.skipif(shutil.which("fwdstep") is None, reason="console script not installed")
def test_installed_console_script_validates():
    proc = subprocess.run(["fwdstep", "validate", THEOREM1], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert ": ok" in proc.stdout and proc.stderr == ""


def test_cli_py_runs_from_a_checkout():
    """``python cli.py`` works from a checkout (cli.py is the whole command line)."""
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "cli.py"), "blocks", "Gain"],
                          capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "Gain" in proc.stdout


def test_blocks_lists_every_registered_block_with_its_summary(capsys):
    assert cli.main(["blocks"]) == 0
    out = capsys.readouterr().out
    for name, cls in load_library().items():
        assert f"{name} " in out
        assert cls.summary() in out
    for name in ("ReferenceDynamics", "TwoLinkArm", "Regressor", "AdaptationLaw", "Polynomial",
                 "Sine", "Sum", "Gain", "Product"):
        assert name in out


def test_blocks_name_prints_the_full_documentation(capsys):
    assert cli.main(["blocks", "ReferenceDynamics"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("ReferenceDynamics\n")
    assert "(2)" in out                                 # the equation number
    assert "Ports:" in out and "| zdot" in out          # the port table
    for param in ("variant", "ell", "alpha", "alphas", "z0"):
        assert f"\n  {param} " in out                   # the parameter list


def test_blocks_unknown_name_exits_2(capsys):
    assert cli.main(["blocks", "NoSuchBlock"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "NoSuchBlock" in err


def test_figure_format_writes_png_as_well(tmp_path):
    import yaml
    with open(THEOREM1, encoding="utf-8") as fh:
        figures = list(yaml.safe_load(fh)["plots"])               # what the diagram names
    out = tmp_path / "run"
    assert cli.main(["run", THEOREM1, "-o", str(out), "-q", "--set", "simulation.t_final=0.2",
                     "--figure-format", "pdf"]) == 0
    for name in figures:
        assert (out / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
        assert (out / f"{name}.pdf").read_bytes()[:5] == b"%PDF-"
    assert not list(out.glob("*.svg"))
    cmp = tmp_path / "cmp"
    assert cli.main(["compare", str(out), str(out), "-o", str(cmp), "--figure-format", "svg"]) == 0
    assert (cmp / "compare.png").read_bytes()[:8] == PNG_MAGIC
    assert b"<svg" in (cmp / "compare.svg").read_bytes()[:3000]


# ---------------------------------------------------------------------------- issue 24, item 9
def test_progress_off_a_terminal_writes_its_start_quarters_and_100():
    import io
    from fwdstep.cli.commands import Progress
    out = io.StringIO()
    p = Progress(out)
    for k in range(1, 15):                      # about once a second: every ~7 %
        p(k / 15)
    p.finish(1.0)
    assert out.getvalue().splitlines() == ["    6.7% simulated", "   25.0% simulated",
                                           "   50.0% simulated", "   75.0% simulated",
                                           "  100.0% simulated"]
    quiet = io.StringIO()
    Progress(quiet).finish(1.0)                 # a run shorter than a second: nothing
    assert quiet.getvalue() == ""


def test_compare_quiet_prints_nothing_and_schema_output_says_what_it_wrote(tmp_path, capsys):
    for name in ("a", "b"):
        assert cli.main(["run", THEOREM1, "--set", "simulation.t_final=0.1", "-o",
                         str(tmp_path / name), "-q", "--no-plots"]) == 0
    capsys.readouterr()
    assert cli.main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "-o",
                     str(tmp_path / "cmp"), "-q"]) == 0
    assert capsys.readouterr().out == ""
    assert os.path.isfile(tmp_path / "cmp" / "compare.csv")
    target = tmp_path / "schema.json"
    assert cli.main(["schema", "-o", str(target)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {target} ") and json.loads(target.read_text())
