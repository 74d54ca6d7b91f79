"""Sweeps under hostile use (issue 23): --resume never mixes two studies, every output goes
through one transaction (no link followed, nothing of the user's replaced, --force removes
only what fwdstep listed), a lost worker is an error row that --resume runs again, budgets are
refused before the allocation, damaged result files are one line naming them.

Every CLI failure here must be exactly one line on stderr and exit 2 (bad input), and what
was finished before must still be on disk.
"""
import errno
import glob
import json
import os
import signal
import time

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
from fwdstep.core.errors import ConfigError
from fwdstep.results.outputs import MANIFEST_FILE, OutputDir, owned_files
from fwdstep.sweeps import sweep as sweep_module
from fwdstep.sweeps.sampling import MAX_VARIANTS, variant_values
from fwdstep.sweeps.sweep import run_sweep

# e' = -k e: the error of every variant is known in closed form, exp(-k t)
LOOP = """
parameters: {k: 2.0, a: 1.0}
blocks:
  r: {type: Constant, value: a}
  e: {type: Sum, signs: "+-"}
  g: {type: Gain, gain: k}
  p: {type: Integrator}
connections:
  - r.y -> e.u1
  - p.y -> e.u2
  - e.y -> g.u
  - g.y -> p.u
simulation: {t_final: 0.2, step: 0.01, solver: rk4}
log: [e.y]
metrics: {error: e.y}
"""
GRID = ["--grid", "a=1,2,3,4", "--batch-size", "1", "--workers", "1", "-q"]


@pytest.fixture
def diagram(tmp_path):
    p = tmp_path / "loop.yaml"
    p.write_text(LOOP)
    return str(p)


def sweep(diagram, out, *extra):
    return cli.main(["sweep", diagram, *GRID, "-o", str(out), *extra])


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fwdstep: "), err
    return err


def rows(out) -> list:
    import csv
    with open(os.path.join(out, "sweep.csv")) as fh:
        return list(csv.DictReader(fh))


def lose_two_parts(out) -> None:
    parts = sorted(glob.glob(os.path.join(out, "parts", "*.npz")))
    assert len(parts) == 4
    for path in parts[1:3]:
        os.unlink(path)


# ---------------------------------------------------------------------------- 1. identity
@pytest.mark.parametrize("change", ["set", "t_final", "diagram", "other_file", "grid_option"])
def test_resume_refuses_another_study(diagram, tmp_path, capsys, change):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    lose_two_parts(out)
    before = rows(out)
    extra, path = [], diagram
    if change == "set":
        extra = ["--set", "k=5"]
    elif change == "t_final":
        extra = ["--set", "simulation.t_final=0.3"]
    elif change == "diagram":                     # the same file, edited
        with open(diagram, "a") as fh:
            fh.write("# edited\n")
    elif change == "other_file":
        path = str(tmp_path / "other.yaml")
        with open(path, "w") as fh:
            fh.write(LOOP.replace("step: 0.01", "step: 0.005"))
    else:
        extra = ["--seed", "3"]
    code = cli.main(["sweep", path, *GRID, "-o", str(out), "--resume", *extra])
    err = one_line(capsys)
    assert code == 2 and "--resume refused" in err
    expected = {"set": "--set k", "t_final": "t_final", "diagram": "loop.yaml",
                "other_file": "other.yaml", "grid_option": "seed"}[change]
    assert expected in err
    assert rows(out) == before                     # nothing was run, nothing rewritten
    assert len(glob.glob(os.path.join(out, "parts", "*.npz"))) == 2


def test_resume_of_the_same_study_fills_in_the_lost_parts(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    lose_two_parts(out)
    assert sweep(diagram, out, "--resume", "--workers", "2") == 0   # how it runs: not identity
    table = rows(out)
    assert [r["status"] for r in table] == ["ok"] * 4
    for r in table:                    # e(t) = a exp(-k t): rk4 at h = 0.01 to 1e-9
        assert float(r["final_error_norm"]) == pytest.approx(float(r["a"]) * np.exp(-0.4),
                                                            rel=1e-8)


def test_subsystem_file_is_part_of_the_identity(tmp_path, capsys):
    lib = tmp_path / "gain.yaml"
    lib.write_text("""
parameters: {k: 2.0}
blocks:
  g: {type: Gain, gain: k}
ports:
  inputs: {u: g.u}
  outputs: {y: g.y}
""")
    top = tmp_path / "top.yaml"
    top.write_text(LOOP.replace("g: {type: Gain, gain: k}",
                                "g: {type: subsystem, file: gain.yaml, parameters: {k: k}}"))
    out = tmp_path / "o"
    assert cli.main(["sweep", str(top), *GRID, "-o", str(out)]) == 0
    lose_two_parts(out)
    lib.write_text(lib.read_text().replace("k: 2.0", "k: 2.5"))
    assert cli.main(["sweep", str(top), *GRID, "-o", str(out), "--resume"]) == 2
    assert "gain.yaml: content changed" in one_line(capsys)


def test_resume_without_a_recorded_identity_is_refused(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    os.unlink(out / "sweep-identity.json")
    assert sweep(diagram, out, "--resume") == 2
    assert "sweep-identity.json is missing" in one_line(capsys)


# ---------------------------------------------------------------------------- 2. outputs
def test_no_symbolic_link_is_followed(diagram, tmp_path, capsys):
    pytest.importorskip("xarray")
    out = tmp_path / "o"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    for name in ("sweep.nc.partial", "sweep.csv.partial", ".tmp-x", ".fwdstep-put-x"):
        os.symlink(victim, out / name)
    assert sweep(diagram, out, "--netcdf") == 0
    assert victim.read_text() == "precious"
    assert {"sweep.csv", "sweep.nc", "sweep.png", "sweep-identity.json"} <= owned_files(out)
    for name in ("sweep.nc", "sweep.png", "sweep.csv"):       # a planted link at the name
        (out / name).unlink()
        os.symlink(victim, out / name)
        assert sweep(diagram, out, "--netcdf", "--force") == 2
        assert "symbolic link" in one_line(capsys)
        assert victim.read_text() == "precious" and os.path.islink(out / name)
        (out / name).unlink()


@pytest.mark.parametrize("name", ["sweep.nc", "sweep.png"])
@pytest.mark.parametrize("force", [False, True])
def test_the_users_own_files_are_never_replaced(diagram, tmp_path, capsys, name, force):
    out = tmp_path / "o"
    out.mkdir()
    (out / name).write_text("mine")
    code = sweep(diagram, out, "--netcdf", *(["--force"] if force else []))
    assert code == 2 and "fwdstep did not write" in one_line(capsys)
    assert (out / name).read_text() == "mine"
    assert not (out / "parts").exists()                   # refused before anything ran


def test_the_users_report_html_is_never_replaced(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    (out / "report.html").write_text("my notes")
    assert cli.main(["report", str(out)]) == 2
    assert "report.html" in one_line(capsys)
    assert (out / "report.html").read_text() == "my notes"


def test_force_removes_only_what_fwdstep_listed(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    (out / "parts" / "notes.txt").write_text("mine")
    (out / "parts" / "data").mkdir()
    (out / "parts" / "data" / "x.npz").write_text("mine too")
    assert sweep(diagram, out) == 2 and "--resume" in one_line(capsys)   # no --force
    assert cli.main(["sweep", diagram, "--grid", "a=5,6", "--workers", "1", "-q", "-o",
                     str(out), "--force"]) == 0
    assert (out / "parts" / "notes.txt").read_text() == "mine"
    assert (out / "parts" / "data" / "x.npz").read_text() == "mine too"
    parts = sorted(n for n in owned_files(out) if n.startswith("parts/"))
    assert len(parts) == 1 and [r["a"] for r in rows(out)] == ["5", "6"]


def test_parts_that_is_a_link_is_one_line(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("keep")
    os.symlink(elsewhere, out / "parts")
    for extra in ([], ["--force"], ["--resume"]):
        assert sweep(diagram, out, *extra) == 2
        assert "parts" in one_line(capsys)
    assert os.listdir(elsewhere) == ["keep.txt"]


def test_a_file_named_like_a_part_is_not_taken_for_one(diagram, tmp_path, capsys):
    out = tmp_path / "o"
    (out / "parts").mkdir(parents=True)
    (out / "parts" / "variants-000000.npz").write_text("not a batch")
    assert sweep(diagram, out) == 2
    assert "named like a finished batch" in one_line(capsys)
    assert (out / "parts" / "variants-000000.npz").read_text() == "not a batch"


# ---------------------------------------------------------------------------- 3. workers
@pytest.fixture(scope="module")
def killer(tmp_path_factory):
    """(plugin file, diagram) of a block that kills its own process (as the out-of-memory
    killer would) when u == 3; one file per test module (a block type is registered once per
    process).  $FWDSTEP_PLUGINS is restored afterwards."""
    from fwdstep.structure.library import PLUGINS_ENV
    before = os.environ.get(PLUGINS_ENV)
    home = tmp_path_factory.mktemp("killer")
    path = home / "killer.yaml"
    path.write_text(KILLER)
    yield _killer_plugin(home), str(path)
    if before is None:
        os.environ.pop(PLUGINS_ENV, None)
    else:
        os.environ[PLUGINS_ENV] = before


def _killer_plugin(tmp_path) -> str:
    p = tmp_path / "killer.py"
    p.write_text('''
import os, signal
import numpy as np
from fwdstep.block import Block
from fwdstep.registry import register


def _out(t, x, u):
    if np.any(u == 3.0):
        os.kill(os.getpid(), signal.SIGKILL)
    return (u,)


@register
class KillerPass(Block):
    """y = u; the process dies when u == 3.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | ()    | y           |
        | y    | out       | ()    | -           |
    """
    params = {}

    def setup(self):
        self.declare_input("u", ())
        self.declare_output("y", (), feedthrough=("u",))
        self.set_kernels(output=_out)
''')
    return str(p)


KILLER = LOOP.replace("r: {type: Constant, value: a}",
                      "r0: {type: Constant, value: a}\n  r: {type: KillerPass}").replace(
    "connections:\n", "connections:\n  - r0.y -> r.u\n")


def test_a_killed_local_worker_is_an_error_row(tmp_path, capsys, killer):
    plugin, path = killer
    out = tmp_path / "o"
    args = ["sweep", path, "--plugin", plugin, "--grid", "a=1,2,3,4", "--batch-size",
            "1", "--workers", "2", "-o", str(out), "-q"]
    t0 = time.monotonic()
    assert cli.main(args) == 4                               # some variants errored
    assert time.monotonic() - t0 < 120                        # never hangs
    err = capsys.readouterr().err
    assert "1 variant(s) lost" in err and "--resume" in err
    table = rows(out)
    assert [r["status"] for r in table] == ["ok", "ok", "error", "ok"]
    assert table[2]["message"].startswith("worker lost:") and "SIGKILL" in table[2]["message"]
    assert len(glob.glob(os.path.join(out, "parts", "*.npz"))) == 3   # the lost one: not done


def test_resume_reruns_a_lost_variant(diagram, tmp_path, monkeypatch):
    """A variant lost with its worker is not kept as finished: --resume runs it (here it
    then succeeds)."""
    from fwdstep.sweeps import distributed
    out = str(tmp_path / "o")
    real = distributed.run_jobs

    def losing(function, jobs, workers=1, client=None):
        for job in jobs:
            if 2 in job.indices:
                yield job, distributed.WorkerLost("killed by SIGKILL (test)")
            else:
                yield job, function(job)
    monkeypatch.setattr(sweep_module, "run_jobs", losing)
    first = run_sweep(diagram, {"a": [1, 2, 3, 4]}, workers=1, batch_size=1, outdir=out)
    assert [v.status for v in first.variants] == ["ok", "ok", "error", "ok"]
    assert first.lost == 1
    monkeypatch.setattr(sweep_module, "run_jobs", real)
    ran = []
    second = run_sweep(diagram, {"a": [1, 2, 3, 4]}, workers=1, batch_size=1, outdir=out,
                       resume=True, progress=ran.append)
    assert len(ran) == 1 and [v.status for v in second.variants] == ["ok"] * 4


def test_scheduler_that_is_not_an_address_is_one_line(diagram, tmp_path, capsys):
    pytest.importorskip("distributed")
    assert sweep(diagram, tmp_path / "o", "--scheduler", "notanaddress") == 2
    assert "notanaddress" in one_line(capsys)


def test_dask_without_workers_says_so(diagram, tmp_path, capsys, monkeypatch):
    distributed = pytest.importorskip("distributed")
    from fwdstep.sweeps import distributed as fw_distributed
    monkeypatch.setattr(fw_distributed, "WORKER_WAIT_S", 1.0)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None,
                                  silence_logs=50) as cluster:
        t0 = time.monotonic()
        assert sweep(diagram, tmp_path / "o", "--scheduler", cluster.scheduler_address) == 2
        assert time.monotonic() - t0 < 30
    assert "has no worker" in one_line(capsys)


def test_plugin_sweep_on_dask_and_a_killed_worker(tmp_path, capsys, killer, monkeypatch):
    """The plugin file reaches workers in other processes (sent as text: the workers are
    started without $FWDSTEP_PLUGINS); a variant that kills its worker becomes a
    KilledWorker error row, the others are kept, sweep.csv is written."""
    distributed = pytest.importorskip("distributed")
    import dask
    from fwdstep.structure.library import PLUGINS_ENV
    monkeypatch.delenv(PLUGINS_ENV, raising=False)
    plugin, path = killer
    out = tmp_path / "o"
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                     dashboard_address=None, silence_logs=50) as cluster:
        code = cli.main(["sweep", path, "--plugin", plugin, "--grid", "a=1,2,3,4",
                         "--batch-size", "1", "--scheduler", cluster.scheduler_address,
                         "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 4, err
    table = rows(out)
    assert [r["status"] for r in table[:3]] == ["ok", "ok", "error"]
    # the variant queued on the same worker when it died may be lost with it (Dask's choice:
    # about 1 run in 3 here); then it is an error row saying so, never a wrong number
    assert table[3]["status"] in ("ok", "error")
    for r in table:
        if r["status"] == "error":
            assert "worker lost" in r["message"] and "KilledWorker" in r["message"], r
    for r in table:
        if r["status"] == "ok":
            assert float(r["final_error_norm"]) == pytest.approx(
                float(r["a"]) * np.exp(-0.4), rel=1e-8)


# ---------------------------------------------------------------------------- 4. budgets
def test_grid_count_is_exact_and_refused():
    grid = {f"p{k}": list(range(256)) for k in range(8)}      # 256**8 = 2**64: int64 wraps
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=f"{256 ** 8} variants; the limit is {MAX_VARIANTS}"):
        variant_values(grid, {}, 0, 0)
    assert time.monotonic() - t0 < 1


def test_sweep_memory_is_refused_before_allocating(tmp_path, capsys):
    path = tmp_path / "big.yaml"
    path.write_text("""
parameters: {k: 1.0}
blocks:
  c: {type: Constant, value: "k*ones(1000, 1000)"}
  g: {type: Gain, gain: 2.0, shape: [1000, 1000]}
connections:
  - c.y -> g.u
simulation: {t_final: 0.002, step: 0.001, solver: euler}
log: [g.y]
metrics: {error: g.y}
""")
    grid = "k=" + ",".join(str(k) for k in range(300))
    t0 = time.monotonic()
    code = cli.main(["sweep", str(path), "--grid", grid, "-o", str(tmp_path / "o"), "-q",
                     "--workers", "1"])
    assert time.monotonic() - t0 < 20
    err = one_line(capsys)
    # each variant holds its own 1e6-number value: 8 MB, times 300 variants
    assert code == 2 and "300 variants x" in err and "--max-memory 1 GB" in err
    import re
    total = float(re.search(r"needs ([0-9.]+) GB", err).group(1))
    assert total >= 300 * 8e6 / 1e9 and "block parameters (c:" in err


def test_disk_full_while_locking_is_one_line(diagram, tmp_path, capsys, monkeypatch):
    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "write", full)
    code = sweep(diagram, tmp_path / "o")
    monkeypatch.undo()
    assert code == 2 and "No space left on device" in one_line(capsys)


def test_disk_full_while_writing_parts_keeps_what_was_written(diagram, tmp_path, capsys,
                                                              monkeypatch):
    out = tmp_path / "o"
    real = OutputDir._put
    calls = []

    def put(self, name, produce):
        if name.startswith("parts/"):
            calls.append(name)
            if len(calls) == 3:
                def produce(tmp):
                    with open(tmp, "wb") as fh:
                        fh.write(b"half")
                    raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, name, produce)
    monkeypatch.setattr(OutputDir, "_put", put)
    assert sweep(diagram, out) == 2
    err = one_line(capsys)
    assert "No space left on device" in err and "--resume" in err
    monkeypatch.undo()
    parts = sorted(n for n in owned_files(out) if n.startswith("parts/"))
    assert len(parts) == 2                               # the two written before
    assert not glob.glob(os.path.join(out, ".fwdstep-put-*"))
    assert sweep(diagram, out, "--resume") == 0
    assert [r["status"] for r in rows(out)] == ["ok"] * 4


# ---------------------------------------------------------------------------- 5. damaged files
def _truncate(path) -> None:
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:
        fh.truncate(size // 2)


@pytest.mark.parametrize("verb", ["report", "compare", "resume"])
def test_a_truncated_part_is_one_line_naming_it(diagram, tmp_path, capsys, verb):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    victim = sorted(glob.glob(os.path.join(out, "parts", "*.npz")))[1]
    _truncate(victim)
    if verb == "report":
        code = cli.main(["report", str(out)])
    elif verb == "compare":
        code = cli.main(["compare", str(out), "-o", str(tmp_path / "c")])
    else:
        code = sweep(diagram, out, "--resume")
    err = one_line(capsys)
    assert code == 2 and os.path.basename(victim) in err


def _run(diagram, out) -> None:
    assert cli.main(["run", diagram, "-o", str(out), "-q", "--no-plots"]) == 0


@pytest.mark.parametrize("edit", [
    "[]", '{"batch": "x"}', '{"batch": 0}', '{"figures": 5}', '{"figures": {"f": [3]}}',
    '{"signals": 3}', '{"parameters": "x"}', '{"simulation": [1]}', '{"diagram": 5}',
    '{"signal_labels": {"e.y": 3}}', '{"aliases": {"e": 3}}', '{"status": 1}', "{",
])
def test_a_hand_edited_summary_is_one_line(diagram, tmp_path, capsys, edit):
    out = tmp_path / "r"
    _run(diagram, out)
    summary = out / "summary.json"
    if edit.startswith("{") and edit.endswith("}"):
        data = json.loads(summary.read_text())
        data.update(json.loads(edit))
        summary.write_text(json.dumps(data))
    else:
        summary.write_text(edit)
    capsys.readouterr()
    for args in (["report", str(out)], ["compare", str(out), "-o", str(tmp_path / "c")]):
        assert cli.main(args) == 2
        assert "summary.json" in one_line(capsys)


@pytest.mark.parametrize("verb", ["report", "compare"])
def test_a_truncated_result_is_one_line(diagram, tmp_path, capsys, verb):
    out = tmp_path / "r"
    _run(diagram, out)
    _truncate(out / "result.npz")
    capsys.readouterr()
    args = ["report", str(out)] if verb == "report" else ["compare", str(out), "-o",
                                                          str(tmp_path / "c")]
    assert cli.main(args) == 2
    assert "result.npz" in one_line(capsys)


def test_report_of_a_sweep_with_a_large_matrix_value(tmp_path, capsys):
    path = tmp_path / "m.yaml"
    path.write_text(LOOP.replace("parameters: {k: 2.0, a: 1.0}",
                                 "parameters: {k: 2.0, a: 1.0, M: 0}"))
    out = str(tmp_path / "o")
    big = np.full((200, 200), 0.123456)                 # 360 kB in one csv cell
    result = run_sweep(str(path), {"M": [big, 2 * big]}, workers=1, outdir=out)
    result.write(out)
    assert cli.main(["report", out]) == 0
    page = open(os.path.join(out, "report.html"), encoding="utf-8").read()
    assert "0.123456" in page and len(page) < 5_000_000


def test_manifest_lists_every_part(diagram, tmp_path):
    out = tmp_path / "o"
    assert sweep(diagram, out) == 0
    with open(out / MANIFEST_FILE) as fh:
        listed = json.load(fh)["files"]
    for path in glob.glob(os.path.join(out, "parts", "*.npz")):
        name = "parts/" + os.path.basename(path)
        import hashlib
        assert listed[name]["sha256"] == hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_sigkill_in_a_worker_never_hangs_run_jobs():
    """The executor alone: a job that kills its process is yielded as WorkerLost; the
    others' outcomes are all there."""
    from fwdstep.sweeps.distributed import WorkerLost, run_jobs

    def job(n):
        if n == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return n * n
    got = dict(run_jobs(job, [0, 1, 2, 3, 4], workers=2))
    assert {k: v for k, v in got.items() if k != 2} == {0: 0, 1: 1, 3: 9, 4: 16}
    assert isinstance(got[2], WorkerLost) and "SIGKILL" in got[2].reason
