"""Sweeps on many processes (fwdstep.sweeps.distributed): the numbers of the sequential run, every
finished batch on disk as it finishes, --resume runs only what is missing, --max-memory.

The Dask test starts a real scheduler and two workers as separate processes
(``distributed.LocalCluster(processes=True)``) and connects by the scheduler's address, as
``fwdstep sweep --scheduler ADDRESS`` does.
"""
import glob
import os

import numpy as np
import pytest

from fwdstep.cli import arguments as cli
import fwdstep.sweeps.sweep as sweep_module
from fwdstep.core.errors import ConfigError
from fwdstep.sweeps.sweep import METRICS, plan_batches, run_sweep

LOOP = """
parameters: {alpha: 4, gamma: 2, K: 20, q0: [0.1, -0.1]}
blocks:
  qd:    {type: Sine, amplitude: [0.3, 0.2], frequency: [1.0, 1.5], derivatives: 2}
  arm:   {type: TwoLinkArm, q0: q0}
  ref:   {type: ReferenceDynamics, variant: eq2, ell: 2, n: 2, alpha: alpha}
  e:     {type: Sum, signs: "+-", shape: [2]}
  s:     {type: Sum, signs: "+-", shape: [2]}
  Y:     {type: Regressor}
  Yth:   {type: Product, a_shape: [2, 4], b_shape: [4]}
  Ks:    {type: Gain, gain: K, shape: [2]}
  tau:   {type: Sum, signs: "+-", shape: [2]}
  adapt: {type: AdaptationLaw, regressor_shape: [2, 4], gamma: gamma}
connections:
  - arm.q -> ref.q, Y.q, e.u1
  - arm.qdot -> ref.qdot, Y.qdot, s.u1
  - qd.y -> ref.q_d, e.u2
  - ref.z -> s.u2, Y.zeta
  - ref.zdot -> Y.zetad
  - Y.Y -> Yth.a, adapt.W
  - adapt.theta_hat -> Yth.b
  - s.y -> Ks.u, adapt.e
  - Yth.y -> tau.u1
  - Ks.y -> tau.u2
  - tau.y -> arm.tau
simulation: {t_final: 0.3, step: 0.002, solver: rk4, log_every: 3, bound: 1e3}
log: [e.y]
metrics: {error: e.y}
"""
GRID = {"K": [20, -300, 50, 80], "alpha": [2.0, 3.0, 4.0]}      # 12 variants, K=-300 diverges


@pytest.fixture
def path(tmp_path):
    p = tmp_path / "loop.yaml"
    p.write_text(LOOP)
    return str(p)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    p = tmp_path_factory.mktemp("ref") / "loop.yaml"
    p.write_text(LOOP)
    return run_sweep(str(p), GRID, sequential=True, workers=1)


def _signals(result) -> dict:
    out = {}
    for part in result.iter_parts():
        for k, i in enumerate(part["indices"]):
            out[int(i)] = (part["t"], part["e"][:, k])
    return out


def assert_same(result, reference):
    assert [v.status for v in result.variants] == [v.status for v in reference.variants]
    assert [v.status for v in reference.variants].count("diverged") == 2   # alpha 3, 4
    for a, b in zip(result.variants, reference.variants):
        assert a.values == b.values
        if a.status == "diverged":
            assert a.diverged_at == pytest.approx(b.diverged_at, abs=1e-12)
        for m in METRICS if a.status == "ok" else ():
            assert a.metrics[m] == pytest.approx(b.metrics[m], rel=1e-12, abs=1e-15)
    mine, theirs = _signals(result), _signals(reference)
    assert sorted(mine) == sorted(theirs) == list(range(len(reference.variants)))
    for i, (t, e) in theirs.items():
        rows = min(len(t), len(mine[i][0]))
        np.testing.assert_array_equal(mine[i][0][:rows], t[:rows])
        np.testing.assert_allclose(mine[i][1][:rows], e[:rows], rtol=0, atol=1e-12,
                                   equal_nan=True)


def test_local_processes_give_the_sequential_numbers(path, reference, tmp_path):
    out = str(tmp_path / "out")
    result = run_sweep(path, GRID, workers=2, batch_size=3, outdir=out)
    assert len(result.batches) == 4
    assert len(glob.glob(os.path.join(out, "parts", "*.npz"))) == 4
    assert_same(result, reference)


def test_dask_cluster_of_separate_processes(path, reference):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None, silence_logs=40) as cluster:
        pids = {w.pid for w in cluster.workers.values()}
        assert len(pids) == 2 and os.getpid() not in pids         # really other processes
        result = run_sweep(path, GRID, scheduler=cluster.scheduler_address, batch_size=2)
    assert len(result.batches) == 6
    assert_same(result, reference)


def test_scheduler_without_dask_is_one_line(path, monkeypatch, capsys, tmp_path):
    import builtins
    real = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name.startswith("dask") or name.startswith("distributed"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    code = cli.main(["sweep", path, "--grid", "K=1,2", "--scheduler", "tcp://127.0.0.1:1",
                     "-o", str(tmp_path / "o"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "fwdstep[distributed]" in err


def test_interrupted_sweep_keeps_finished_batches_and_resumes(path, reference, tmp_path,
                                                              monkeypatch):
    out = str(tmp_path / "out")
    real = sweep_module.run_job
    calls = []

    def interrupted_on_the_third(job):
        calls.append(job.indices)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(sweep_module, "run_job", interrupted_on_the_third)
    first = run_sweep(path, GRID, workers=1, batch_size=2, outdir=out)
    assert first.interrupted
    statuses = [v.status for v in first.variants]
    assert statuses.count("interrupted") == 8 and len(calls) == 3
    assert len(glob.glob(os.path.join(out, "parts", "*.npz"))) == 2
    monkeypatch.setattr(sweep_module, "run_job", real)
    calls.clear()
    ran = []
    second = run_sweep(path, GRID, workers=1, batch_size=2, outdir=out, resume=True,
                       progress=ran.append)
    assert len(ran) == 4 and not second.interrupted           # only the 8 missing variants
    assert_same(second, reference)
    # a different sweep in the same directory is refused, nothing is run
    with pytest.raises(ConfigError, match="holds a different sweep"):
        run_sweep(path, {"K": [1, 2]}, workers=1, outdir=out, resume=True)


def test_cli_resume_and_existing_outdir(path, tmp_path, capsys):
    out = str(tmp_path / "o")
    assert cli.main(["sweep", path, "--grid", "K=20,30", "-o", out, "-q", "--workers",
                     "1"]) == 0
    assert cli.main(["sweep", path, "--grid", "K=20,30", "-o", out, "-q"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert cli.main(["sweep", path, "--grid", "K=20,30", "-o", out, "-q", "--resume",
                     "--workers", "1"]) == 0
    with open(os.path.join(out, "sweep.csv")) as fh:
        assert [line.split(",")[3] for line in fh][1:] == ["ok", "ok"]


def test_memory_budget_counts_what_is_logged(path):
    from fwdstep.structure.compiler import instantiate_variants
    from fwdstep.structure.spec import load_spec
    specs = [load_spec(path, {"K": k}) for k in range(1, 17)]
    blocks = instantiate_variants(specs)
    # e.y: 2 numbers x (150 steps / 3 + 2) rows x 8 bytes = 832 B, plus 12 states x 8 bytes
    # x 12 solver buffers (arm 4, ref 4, adapt 4), plus 4 buffers of every block output
    signals = sum(port.size for b in blocks[0] for port in b.outputs.values())
    assert signals > 12
    per_variant = 2 * 52 * 8 + 12 * 8 * 12 + 4 * 8 * signals
    assert len(plan_batches(specs, blocks, "e.y", max_memory=16 * per_variant)) == 1
    assert len(plan_batches(specs, blocks, "e.y", max_memory=16 * per_variant - 1)) == 2
    assert len(plan_batches(specs, blocks, "e.y", max_memory=8 * per_variant,
                            workers=2)) == 4
    with pytest.raises(ConfigError) as info:
        plan_batches(specs, blocks, "e.y", max_memory=1000)
    message = str(info.value)
    assert f"{per_variant / 1e6:.3g} MB" in message and "--max-memory 0.001 MB" in message
    assert "832 B" not in message and "52 rows" in message
    assert f"{signals} signal values" in message


def test_cli_max_memory(path, tmp_path, capsys):
    code = cli.main(["sweep", path, "--grid", "K=1,2", "--max-memory", "1kB", "-o",
                     str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--max-memory 0.001 MB" in err
    code = cli.main(["sweep", path, "--grid", "K=1,2", "--max-memory", "lots", "-o",
                     str(tmp_path / "o")])
    assert code == 2 and capsys.readouterr().err == (
        "fwdstep: --max-memory: size 'lots' is not understood; write e.g. 512MB, 2GiB or 1e9\n")


def test_sigterm_keeps_finished_batches_and_resume_finishes(path, tmp_path):
    """A real SIGTERM (a batch system's kill) to a running ``fwdstep sweep``: exit 143, the
    finished batches stay in OUTDIR/parts and in the table; --resume runs only the rest."""
    import csv
    import signal
    import subprocess
    import sys
    import time
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = str(tmp_path / "o")
    args = ["sweep", path, "--grid", "K=" + ",".join(str(k) for k in range(20, 30)),
            "--set", "simulation.t_final=1", "--workers", "1", "--batch-size", "1",
            "-o", out, "-q"]
    code = f"import sys, cli; sys.exit(cli.main({args!r}))"
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=root)
    parts = os.path.join(out, "parts")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(glob.glob(os.path.join(parts, "*.npz"))) < 2:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(300) in (143, 130)
    with open(os.path.join(out, "sweep.csv")) as fh:
        rows = list(csv.DictReader(fh))
    done = [r for r in rows if r["status"] == "ok"]
    assert len(rows) == 10 and 2 <= len(done) < 10
    assert len(glob.glob(os.path.join(parts, "*.npz"))) == len(done)
    assert all(r["status"] == "interrupted" for r in rows if r not in done)
    assert cli.main(args[:-5] + ["-o", out, "-q", "--resume"]) == 0   # in one batch
    with open(os.path.join(out, "sweep.csv")) as fh:
        again = list(csv.DictReader(fh))
    assert [r["status"] for r in again] == ["ok"] * 10
    for r in done:                        # the finished variants were kept, not re-run
        assert again[int(r["variant"])]["final_error_norm"] == r["final_error_norm"]


def test_a_refused_scheduler_leaves_no_half_made_client_behind():
    """Client('notanaddress') fails half-made; its __del__, run by a later garbage
    collection inside another Dask call, broke that call (an AssertionError in
    LoopRunner.start, or a hang in the suite): fwdstep collects it when it refuses."""
    distributed = pytest.importorskip("distributed")
    from fwdstep.core.errors import ConfigError
    from fwdstep.sweeps.distributed import dask_client
    for _ in range(2):
        with pytest.raises(ConfigError, match="cannot reach the Dask scheduler at 'notanaddress'"):
            dask_client("notanaddress")
        with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None,
                                      silence_logs=50) as cluster:
            assert cluster.scheduler_address.startswith("inproc://")
