"""User blocks: a plugin file (--plugin, load_diagram(plugins=...)) and an installed package's
``fwdstep.blocks`` entry point give blocks like the library's — validated, listed by
``fwdstep blocks``, batched, and right (the worked example of docs/writing-blocks.md against
the closed form of the logistic equation)."""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import fwdstep
from fwdstep.core.errors import ConfigError, ParameterError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PLUGIN = os.path.join(ROOT, "examples", "plugins", "logistic.py")
CLI = os.path.join(ROOT, "cli.py")

DIAGRAM = """
parameters: {r2: 2.0}
blocks:
  inflow: {type: Constant, value: [0.0, 0.0]}
  pop:    {type: Logistic, rate: [1.0, r2], capacity: 3.0, x0: [0.5, 1.0], n: 2}
connections:
  - inflow.y -> pop.u
simulation: {t_final: 2.0, step: 1.0e-3}
"""


@pytest.fixture
def diagram(tmp_path):
    path = tmp_path / "logistic.yaml"
    path.write_text(DIAGRAM)
    return str(path)


def _closed_form(t, r, x0, K=3.0):
    return K / (1.0 + (K / x0 - 1.0) * np.exp(-np.outer(t, r)))


def test_plugin_block_matches_the_closed_form(diagram):
    d = fwdstep.load_diagram(diagram, plugins=[PLUGIN])
    res = fwdstep.simulate(d)
    exact = _closed_form(res.t, np.array([1.0, 2.0]), np.array([0.5, 1.0]))
    assert np.max(np.abs(res["pop.y"] - exact)) < 1e-10      # RK4 at h = 1e-3


def test_plugin_block_batches_like_a_library_block(diagram):
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    fwdstep.load_diagram(diagram, plugins=[PLUGIN])
    specs = [load_spec(diagram, {"r2": v}) for v in (0.5, 2.0, 4.0)]
    res = fwdstep.simulate(compile_batch(specs))
    for b, r2 in enumerate((0.5, 2.0, 4.0)):
        exact = _closed_form(res.t, np.array([1.0, r2]), np.array([0.5, 1.0]))
        assert np.max(np.abs(res["pop.y"][:, b, :] - exact)) < 1e-10


def test_plugin_block_parameters_are_validated(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(DIAGRAM.replace("capacity: 3.0", "capacity: -1"))
    with pytest.raises(ParameterError, match="block 'pop' parameter 'capacity' must be "
                                             "positive"):
        fwdstep.load_diagram(str(path), plugins=[PLUGIN])


def test_missing_or_broken_plugin_is_one_line(tmp_path, diagram):
    with pytest.raises(ConfigError, match="plugin '.*nope.py' is not a file"):
        fwdstep.load_diagram(diagram, plugins=[str(tmp_path / "nope.py")])
    broken = tmp_path / "broken.py"
    broken.write_text("x = 1\nraise ValueError('boom')\n")
    with pytest.raises(ConfigError, match=r"plugin '.*broken.py:2' failed to load: "
                                          r"ValueError: boom"):
        fwdstep.load_diagram(diagram, plugins=[str(broken)])


def test_a_clash_with_a_library_block_is_refused(tmp_path, diagram):
    clash = tmp_path / "clash.py"
    clash.write_text(textwrap.dedent("""
        from fwdstep.core.block import Block
        from fwdstep.core.registry import register

        @register
        class Gain(Block):
            \"\"\"Another Gain.\"\"\"
    """))
    with pytest.raises(ConfigError, match="block type 'Gain' is defined twice"):
        fwdstep.load_diagram(diagram, plugins=[str(clash)])


def _cli(*args, env=None, cwd=None):
    full = dict(os.environ, MPLBACKEND="Agg", **(env or {}))
    full.pop("FWDSTEP_PLUGINS", None)
    return subprocess.run([sys.executable, CLI, *args], capture_output=True, text=True,
                          env=full, cwd=cwd, timeout=300)


def test_cli_plugin_option_on_validate_run_and_blocks(diagram, tmp_path):
    bare = _cli("validate", diagram)
    assert bare.returncode == 2 and "unknown block type 'Logistic'" in bare.stderr
    ok = _cli("validate", diagram, "--plugin", PLUGIN)
    assert ok.returncode == 0, ok.stderr
    listing = _cli("blocks", "--plugin", PLUGIN)
    assert listing.returncode == 0 and "Logistic" in listing.stdout
    doc = _cli("blocks", "Logistic", "--plugin", PLUGIN)
    assert doc.returncode == 0 and "dx_i/dt = r_i x_i (1 - x_i / K_i) + u_i" in doc.stdout
    out = tmp_path / "out"
    run = _cli("run", diagram, "-o", str(out), "--no-plots", "-q", "--plugin", PLUGIN)
    assert run.returncode == 0, run.stderr
    data = np.load(out / "result.npz")
    key = next(k for k in data.files if "pop.y" in k)
    t = data[next(k for k in data.files if k in ("t", "time"))]
    exact = _closed_form(t, np.array([1.0, 2.0]), np.array([0.5, 1.0]))
    assert np.max(np.abs(data[key].reshape(len(t), -1) - exact)) < 1e-10


def test_installed_entry_point_registers_blocks(tmp_path, diagram):
    """A tiny installed distribution (a dist-info with entry_points.txt on sys.path)."""
    site = tmp_path / "site"
    pkg = site / "logistic_pkg"
    pkg.mkdir(parents=True)
    with open(PLUGIN) as fh:
        (pkg / "__init__.py").write_text(fh.read())
    info = site / "logistic_pkg-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: logistic-pkg\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[fwdstep.blocks]\nlogistic = logistic_pkg\n")
    env = {"PYTHONPATH": os.pathsep.join([str(site), ROOT, os.environ.get("PYTHONPATH", "")])}
    listing = _cli("blocks", env=env)
    assert listing.returncode == 0, listing.stderr
    assert "Logistic" in listing.stdout
    ok = _cli("validate", diagram, env=env)
    assert ok.returncode == 0, ok.stderr


def test_a_broken_installed_plugin_is_reported_once_and_not_blamed_on_the_diagram(tmp_path,
                                                                                   diagram):
    """An installed entry point whose import fails: one warning naming the plugin, and
    diagrams that do not use it still validate and run; a diagram that needs one of the
    missing block types is told which plugin failed (not 'line 3 of your diagram')."""
    site = tmp_path / "site"
    pkg = site / "broken_pkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("import numpy\nraise ImportError('libfoo.so missing')\n")
    info = site / "broken_pkg-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-pkg\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[fwdstep.blocks]\nbroken = broken_pkg\n")
    env = {"PYTHONPATH": os.pathsep.join([str(site), ROOT, os.environ.get("PYTHONPATH", "")])}
    plain = tmp_path / "plain.yaml"
    plain.write_text("blocks:\n  c: {type: Constant, value: 1.0}\n"
                     "simulation: {t_final: 1, step: 0.1}\n")
    warning = ("fwdstep: warning: the installed block plugin 'broken' (broken_pkg, entry point "
               "fwdstep.blocks) failed to load and is left out: ImportError: libfoo.so "
               "missing\n")
    ok = _cli("validate", str(plain), env=env)
    assert ok.returncode == 0, ok.stderr
    assert ok.stderr == warning
    run = _cli("run", str(plain), "-o", str(tmp_path / "out"), "-q", "--no-plots", env=env)
    assert run.returncode == 0 and run.stderr == warning
    needs = _cli("validate", diagram, env=env)
    assert needs.returncode == 2
    assert needs.stderr == warning + (
        f"fwdstep: {diagram}:5: unknown block type 'Logistic'; run 'fwdstep blocks' for the "
        "list; block types of your own are added with --plugin FILE.py "
        "(docs/writing-blocks.md); the installed block plugin 'broken' (ImportError: "
        "libfoo.so missing) failed to load\n")


def test_every_verb_takes_plugin_and_a_plugin_runs_report_draws_it(diagram, tmp_path):
    """issue 24: graph, report, compare, sweep, validate and rerun take --plugin; report of
    a plugin run draws its diagram in a new process without --plugin (the record names the
    plugin file); without the plugin, the unknown type says where blocks come from."""
    env = {**os.environ, "PYTHONPATH": ROOT, "MPLBACKEND": "Agg"}
    env.pop("FWDSTEP_PLUGINS", None)         # set by the in-process tests above

    def fwd(*args):
        return subprocess.run([sys.executable, CLI, *args], capture_output=True, text=True,
                              env=env, cwd=tmp_path, timeout=180)

    missing = fwd("validate", diagram)
    assert missing.returncode == 2 and "--plugin FILE.py" in missing.stderr
    assert fwd("validate", diagram, "--plugin", PLUGIN).returncode == 0
    graph = fwd("graph", diagram, "--plugin", PLUGIN, "-o", "g.svg", "--engine", "matplotlib")
    assert graph.returncode == 0, graph.stderr
    for out in ("a", "b"):
        run = fwd("run", diagram, "--plugin", PLUGIN, "-o", out, "-q", "--no-plots")
        assert run.returncode == 0, run.stderr
    report = fwd("report", "a")
    assert report.returncode == 0, report.stderr
    page = (tmp_path / "a" / "report.html").read_text()
    assert "image/svg+xml" in page and "no picture" not in page
    assert fwd("report", "b", "--plugin", PLUGIN).returncode == 0
    compare = fwd("compare", "a", "b", "--plugin", PLUGIN, "-o", "cmp")
    assert compare.returncode == 0, compare.stderr
    sweep = fwd("sweep", diagram, "--plugin", PLUGIN, "--grid", "r2=1,2", "-o", "sw", "-q",
                "--workers", "1")
    assert sweep.returncode == 0, sweep.stderr
    assert fwd("rerun", "a", "-o", "c", "--plugin", PLUGIN, "-q").returncode == 0
    from fwdstep.cli.arguments import build_parser
    verbs = [a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction"]
    for name, parser in verbs[0].choices.items():          # every verb, also those to come
        assert "--plugin" in {o for a in parser._actions for o in a.option_strings}, name


COUNTER = os.path.join(ROOT, "examples", "plugins", "crossing_counter.py")


@pytest.mark.parametrize("solver", ["rk4", "dop853"])
def test_the_documented_crossing_counter_counts_at_the_exact_times(tmp_path, solver):
    """The zero-crossing example of docs/writing-blocks.md (shown there verbatim): u = sin t
    rises through 0 at 2 pi and 4 pi (falls at pi, 3 pi): the count steps exactly there."""
    with open(os.path.join(ROOT, "docs", "writing-blocks.md"), encoding="utf-8") as fh:
        doc = fh.read()
    with open(COUNTER, encoding="utf-8") as fh:
        assert fh.read() in doc
    path = tmp_path / "count.yaml"
    path.write_text(f"""
blocks:
  s: {{type: Sine, amplitude: 1.0, frequency: 1.0}}
  c: {{type: CrossingCounter}}
connections:
  - s.y -> c.u
simulation: {{t_final: 14.0, step: 0.1, solver: {solver}}}
""")
    r = fwdstep.simulate(fwdstep.load_diagram(str(path), plugins=[COUNTER]))
    pi = np.pi
    np.testing.assert_allclose([e.time for e in r.events], [pi, 2 * pi, 3 * pi, 4 * pi],
                               rtol=0, atol=1e-12)
    assert [e.kind for e in r.events] == ["level falling", "level rising"] * 2
    np.testing.assert_array_equal(r["c.y"], (r.t >= 2 * pi).astype(float)
                                  + (r.t >= 4 * pi))


def test_an_edited_plugin_runs_its_new_text_never_stale_bytecode(tmp_path):
    """A plugin edited within the same second to the same size (Python's bytecode check is
    the source's mtime and size) must run the new text, the text whose SHA-256 the run
    records: with a __pycache__ entry of the old text beside it, the import system ran the
    old code."""
    import hashlib
    import importlib.util
    import py_compile
    body = textwrap.dedent('''
        import numpy as np
        from fwdstep.core.block import Block
        from fwdstep.core.registry import register


        def scaled_output(t, x, u):
            return (2.0 * u,)


        @register
        class StaleCheck(Block):
            """y = c u.

            Equation: y = c u.
            """
            params = {}

            def setup(self):
                self.declare_input("u", ())
                self.declare_output("y", ())
                self.set_kernels(output=scaled_output)
        ''')
    plugin = tmp_path / "stale_check.py"
    plugin.write_text(body)
    py_compile.compile(str(plugin), cfile=importlib.util.cache_from_source(str(plugin)))
    stamp = os.stat(plugin)
    plugin.write_text(body.replace("2.0 * u", "3.0 * u"))           # same size
    os.utime(plugin, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))      # same second
    diagram = tmp_path / "d.yaml"
    diagram.write_text("blocks:\n  c: {type: Constant, value: 1.0}\n  g: {type: StaleCheck}\n"
                       "connections:\n  - c.y -> g.u\nsimulation: {t_final: 0.01}\n")
    code = ("import fwdstep, json, sys; "
            f"r = fwdstep.simulate(fwdstep.load_diagram({str(diagram)!r}, "
            f"plugins=[{str(plugin)!r}])); "
            "from fwdstep.structure.library import plugin_files; "
            "print(json.dumps([float(r['g.y'][-1]), "
            f"dict(plugin_files())[{os.path.realpath(plugin)!r}]]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env={k: v for k, v in os.environ.items()
                                            if k != "PYTHONDONTWRITEBYTECODE"})
    assert done.returncode == 0, done.stderr
    import json
    value, digest = json.loads(done.stdout.strip().splitlines()[-1])
    assert value == 3.0
    assert digest == hashlib.sha256(plugin.read_bytes()).hexdigest()


def test_workers_and_a_sweeps_identity_get_the_plugin_bytes_that_were_imported(tmp_path,
                                                                               monkeypatch):
    """A plugin written in Latin-1 (PEP 263 coding line) with CRLF line ends runs with
    'fwdstep run'; a sweep of it must too (its identity, and the dask workers, were given
    the file read again as UTF-8: 'cannot be read again to send it to the workers'), and
    what they get is the very bytes imported and hashed, even after the file was edited."""
    import hashlib
    import pickle

    from fwdstep.structure.library import load_plugins, plugin_files, plugin_sources
    from fwdstep.sweeps.sweep import run_sweep
    body = textwrap.dedent('''\
        # -*- coding: latin-1 -*-
        # y = 2 u (caf\xe9)
        from fwdstep.core.block import Block
        from fwdstep.core.registry import register


        def latin_output(t, x, u):
            return (2.0 * u,)


        @register
        class LatinScale(Block):
            """y = 2 u.

            Equation: y = 2 u.
            """
            params = {}

            def setup(self):
                self.declare_input("u", ())
                self.declare_output("y", ())
                self.set_kernels(output=latin_output)
        ''').replace("\n", "\r\n").encode("latin-1")
    plugin = tmp_path / "latin_scale.py"
    plugin.write_bytes(body)
    monkeypatch.setenv("FWDSTEP_PLUGINS", os.environ.get("FWDSTEP_PLUGINS", ""))  # restored
    load_plugins([str(plugin)])
    full = os.path.realpath(plugin)
    plugin.write_bytes(body.replace(b"2.0 * u", b"5.0 * u"))       # edited after the import
    sent = plugin_sources()[full]
    assert sent == body
    assert hashlib.sha256(sent).hexdigest() == dict(plugin_files())[full]
    diagram = tmp_path / "d.yaml"
    diagram.write_text("parameters: {a: 1.0}\nblocks:\n  c: {type: Constant, value: a}\n"
                       "  g: {type: LatinScale}\nconnections:\n  - c.y -> g.u\n"
                       "simulation: {t_final: 0.01}\nmetrics: {error: g.y}\n")
    result = run_sweep(str(diagram), {"a": [1.0, 3.0]}, workers=1,
                       outdir=str(tmp_path / "sweep"))
    assert [v.status for v in result.variants] == ["ok", "ok"]
    jobs = tmp_path / "sources.pickle"            # a worker on another machine: only the
    jobs.write_bytes(pickle.dumps(plugin_sources()))
    code = ("import pickle, sys; from fwdstep.structure import library as L; "
            f"L.load_plugin_sources(pickle.load(open({str(jobs)!r}, 'rb'))); "
            "from fwdstep.core.block import Block; import numpy as np; "
            "cls = L.lookup('LatinScale'); b = cls('g'); "
            f"print(float(b.output(0.0, None, (np.ones((1,)),))[0][0]), "
            f"dict(L.plugin_files())[{full!r}])")
    env = {k: v for k, v in os.environ.items() if k != "FWDSTEP_PLUGINS"}   # bytes sent
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    value, digest = done.stdout.split()
    assert float(value) == 2.0 and digest == dict(plugin_files())[full]
