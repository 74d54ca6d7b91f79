"""The generated step functions (fwdstep.run.program): how a batch's signals are copied.

A (B, 2) signal written into columns of a wider buffer (a fused product's inputs, a block's
slice of k_i) is copied through a view of one 16-byte item per pair when the batch is large
(``_put_pairs``).  A copy cannot change a number, so the property checked is that it writes
exactly the bytes the plain assignment writes, and that every value the fast path does not
take (another dtype, a non-contiguous pair, broadcasting, a wrong shape) takes the plain
path, errors included.
"""
import sys

import numpy as np
import pytest

import fwdstep
import fwdstep.run.numpy_backend  # noqa: F401 - patched below
import fwdstep.run.program as program
from fwdstep.structure.compiler import compile_batch, compile_spec
from fwdstep.structure.spec import load_spec


def _target(B=300, width=7, at=3):
    buf = np.full((B, width), -1.0)
    dst = buf[:, at:at + 2]
    return buf, dst, dst.view(program._PAIR)


@pytest.mark.parametrize("make", [
    lambda rng, B: rng.standard_normal((B, 2)),                       # contiguous
    lambda rng, B: rng.standard_normal((B, 5))[:, 1:3],               # rows of a wider array
    lambda rng, B: rng.standard_normal((1, 2)),                       # broadcast over B
    lambda rng, B: rng.standard_normal((2, B)).T,                     # pair not contiguous
    lambda rng, B: rng.standard_normal((B, 1)),                       # broadcast along the pair
    lambda rng, B: rng.standard_normal((B, 2)).astype(np.float32),    # another dtype
    lambda rng, B: rng.integers(-5, 5, (B, 2)),                       # integers
    lambda rng, B: np.array([[np.nan, -0.0]] * B),                    # NaN and signed zero
    lambda rng, B: 2.5,                                               # a Python number
])
def test_put_pairs_writes_what_plain_assignment_writes(make):
    rng = np.random.default_rng(0)
    value = make(rng, 300)
    expected, dst_e, _ = _target()
    dst_e[...] = value
    got, dst, pairs = _target()
    program._put_pairs(pairs, dst, value)
    assert got.tobytes() == expected.tobytes()


def test_put_pairs_raises_the_plain_error():
    _, dst, pairs = _target()
    # float32 (300, 4) has the bytes of 300 pairs: only the dtype check keeps it from being
    # copied as raw bytes
    for bad in (np.zeros((299, 2)), np.zeros((300, 4)), np.zeros((300, 2, 1)),
                np.ones((300, 4), dtype=np.float32)):
        with pytest.raises(ValueError) as plain:
            dst[...] = bad
        with pytest.raises(ValueError) as fast:
            program._put_pairs(pairs, dst, bad)
        assert str(fast.value) == str(plain.value)


def test_a_large_batch_takes_the_pair_copies_and_keeps_every_bit(monkeypatch):
    """70 variants of slotine_li (the pair copies are used from 64 rows): the logs equal
    those of the same batch with plain copies only, byte for byte."""
    lam = np.linspace(2.0, 10.0, 70)
    specs = [load_spec("diagrams/slotine_li.yaml", {"t_final": 0.2, "Lambda": x}) for x in lam]
    runs = []
    for rows in (program.PAIR_COPY_MIN_ROWS, 10 ** 9):
        monkeypatch.setattr(program, "PAIR_COPY_MIN_ROWS", rows)
        seen = []
        build = program.build_program

        def spy(*args, **kwargs):
            prog = build(*args, **kwargs)
            seen.append(prog.source)
            return prog
        monkeypatch.setattr(sys.modules["fwdstep.run.numpy_backend"], "build_program", spy)
        d = compile_batch(specs)
        d.logged = [d.resolve("e.y"), d.resolve("tau.y")]
        runs.append((fwdstep.simulate(d), seen[0]))
    (fast, fast_source), (plain, plain_source) = runs
    assert fast_source.count("put_pairs(") >= 6 and "put_pairs(" not in plain_source
    for name in fast.names:
        assert fast[name].tobytes() == plain[name].tobytes(), name


def test_a_variant_in_a_batch_has_the_bits_of_its_run_alone():
    """The property the batch's code keeps (docs/performance.md, docs/discrete-time.md): with
    a gain per variant (one fused matrix per variant, the pair copies of a large batch) each
    variant's logs are byte for byte those of its run alone."""
    lam = np.linspace(2.0, 10.0, 70)
    specs = [load_spec("diagrams/slotine_li.yaml", {"t_final": 0.1, "Lambda": x}) for x in lam]
    d = compile_batch(specs)
    d.logged = [d.resolve(n) for n in ("e.y", "tau.y", "adapt.theta_hat")]
    batch = fwdstep.simulate(d)
    for b in (0, 33, 69):
        alone = compile_spec(specs[b])
        alone.logged = list(d.logged)
        one = fwdstep.simulate(alone)
        for name in d.logged:
            mine = np.ascontiguousarray(batch[name][:, b])
            assert mine.tobytes() == one[name].reshape(mine.shape).tobytes(), (b, name)


LOG_ONLY = """
blocks:
  src: {type: Sine, amplitude: 1.0, frequency: 1.0}
  x:   {type: Integrator}
  sat: {type: Saturation, lower: -1.0, upper: 0.5}
  err: {type: Sum, signs: "+-"}
connections:
  - src.y -> x.u, err.u2
  - x.y -> sat.u, err.u1
simulation: {t_final: 2.0, step: 0.001, solver: rk4, log_every: 10}
log: [x.y, sat.y, err.y]
"""


def test_a_block_only_the_log_reads_runs_at_the_records_only(tmp_path, monkeypatch):
    """``sat`` and ``err`` feed nothing but the log: the stages that record nothing do not
    call them (nor bind their outputs), the recorded stages do, and the logged values are
    the analytic ones (x = 1 - cos t, sat = min(x, 0.5), err = x - sin t)."""
    path = tmp_path / "log_only.yaml"
    path.write_text(LOG_ONLY)
    seen = []
    build = program.build_program

    def spy(*args, **kwargs):
        prog = build(*args, **kwargs)
        seen.append(prog.source)
        return prog
    monkeypatch.setattr(sys.modules["fwdstep.run.numpy_backend"], "build_program", spy)
    result = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    functions = {f.split("(", 1)[0]: f for f in seen[0].split("def ")[1:]}
    d = fwdstep.load_diagram(str(path))
    sat = d.signal_index["sat.y"]
    err = d.signal_index["err.y"]
    for idx in (sat, err):
        for fn in ("first", "rest", "first_ts", "rest_h"):
            assert f"s{idx} =" not in functions[fn], fn
        for fn in ("first_record", "final", "first_record_ts", "final_ts"):
            assert f"s{idx} =" in functions[fn], fn
    t = result.t
    x = 1.0 - np.cos(t)
    np.testing.assert_allclose(np.ravel(result["x.y"]), x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.ravel(result["sat.y"]), np.minimum(x, 0.5), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.ravel(result["err.y"]), x - np.sin(t), rtol=0, atol=1e-10)
