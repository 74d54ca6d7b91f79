"""Sources: outputs against independent formulas, analytic derivatives against exact formulas
and finite differences, batch stacking, and parameter errors."""
import math
import re

import numpy as np
import pytest
from numpy.polynomial import polynomial as P

from fwdstep.blocks.sources import Constant, MultiSine, Polynomial, RandomDisturbance, Sine, Step
from fwdstep.structure.compiler import stack_blocks
from fwdstep.core.errors import ConfigError, ParameterError

NO_STATE = np.zeros((1, 0))
TIMES = (0.0, 0.37, 1.9, -2.5, 13.0)


def out(block, t):
    return block.output(t, NO_STATE, ())


def stacked(cls, variants):
    """Separate blocks per variant, and one block stacked by the engine's batched-sweep code
    (parameters on which all variants agree keep a leading length of 1)."""
    singles = [cls("b", **v) for v in variants]
    big = stack_blocks([[cls("b", **v)] for v in variants])[0]
    return singles, big


def assert_batch_matches(cls, variants, times=TIMES):
    singles, big = stacked(cls, variants)
    for t in times:
        batched = out(big, t)
        for i, single in enumerate(singles):
            for yb, ys in zip(batched, out(single, t)):
                assert np.shape(yb)[0] == len(variants)
                np.testing.assert_allclose(yb[i], ys[0], rtol=1e-15, atol=1e-15)


def table_ports(cls):
    rows = re.findall(r"^\s*\|\s*(\w+)\s*\|\s*(in|out)\s*\|", cls.__doc__, re.M)
    return [name for name, _ in rows]


@pytest.mark.parametrize("cls", [Constant, Step, Sine, MultiSine, RandomDisturbance, Polynomial])
def test_example_matches_docstring_and_has_no_inputs(cls):
    blk = cls("ex", **cls.example)
    assert table_ports(cls) == list(blk.inputs) + list(blk.outputs)
    assert blk.inputs == {} and blk.n_states == 0
    ys = out(blk, 0.4)
    assert len(ys) == len(blk.outputs)
    for y, port in zip(ys, blk.outputs.values()):
        assert np.shape(y) == (1,) + port.shape
        assert blk.feedthrough(port.name) == ()


# --------------------------------------------------------------------------- Constant, Step
def test_constant_any_shape_and_batch():
    value = np.arange(6.0).reshape(2, 3)
    blk = Constant("c", value=value)
    assert blk.outputs["y"].shape == (2, 3)
    np.testing.assert_array_equal(out(blk, 5.0)[0], value[None])
    assert Constant("c", value=2.5).outputs["y"].shape == ()
    assert_batch_matches(Constant, [{"value": value}, {"value": -value}, {"value": value ** 2}])


def test_step_before_at_and_after_the_step_time():
    blk = Step("s", before=[1.0, 2.0], after=[3.0, -4.0], time=[0.5, 1.0])
    np.testing.assert_array_equal(out(blk, 0.0)[0], [[1.0, 2.0]])
    np.testing.assert_array_equal(out(blk, 0.5)[0], [[3.0, 2.0]])   # y = after at t = time
    np.testing.assert_array_equal(out(blk, 0.99)[0], [[3.0, 2.0]])
    np.testing.assert_array_equal(out(blk, 1.0)[0], [[3.0, -4.0]])
    scalar = Step("s", after=2.0, time=1.0)
    assert scalar.outputs["y"].shape == ()
    assert out(scalar, 0.9)[0].tolist() == [0.0] and out(scalar, 1.1)[0].tolist() == [2.0]


def test_step_batch():
    assert_batch_matches(Step, [{"after": [1.0, 2.0], "time": [0.3, 1.0]},
                                {"after": [5.0, 6.0], "before": [1.0, 1.0], "time": [0.3, 1.0]},
                                {"after": [0.0, 2.0], "before": [1.0, 0.5], "time": [0.3, 1.0]}],
                         times=(-4.0, 0.0, 0.3, 0.5, 1.0, 2.5))
    # steps that jump at different times never share a batch: a run splits its steps at
    # every jump (fwdstep.run.events), so batched variants would not equal their single runs
    with pytest.raises(ConfigError, match="differ in structure"):
        stacked(Step, [{"after": 1.0, "time": 0.3}, {"after": 1.0, "time": 1.0}])


# --------------------------------------------------------------------------- Sine
def sine_reference(A, w, phi, offset, t, order):
    """Independent evaluation with Python scalars: d^j/dt^j of offset + sum A sin(wt+phi)."""
    A, w, phi = (np.asarray(v, dtype=float) for v in (A, w, phi))
    A, w, phi = np.broadcast_arrays(*(v.reshape(v.shape + (1,) * (2 - v.ndim))
                                      for v in (A, w, phi)))
    y = []
    for i in range(A.shape[0]):
        total = float(np.broadcast_to(offset, (A.shape[0],))[i]) if order == 0 else 0.0
        for k in range(A.shape[1]):
            total += A[i, k] * w[i, k] ** order * math.sin(w[i, k] * t + phi[i, k]
                                                           + order * math.pi / 2)
        y.append(total)
    return np.array(y)


SINE = {"amplitude": [[1.0, 0.3], [2.0, -0.5], [0.4, 0.0]], "frequency": [[1.0, 3.0]],
        "phase": [0.1, -0.7, 2.0], "offset": [0.5, 0.0, -1.0], "derivatives": 8}


def test_sine_and_all_derivatives_match_exact_formula():
    blk = Sine("s", **SINE)
    assert list(blk.outputs) == ["y"] + [f"y_d{j}" for j in range(1, 9)]
    for t in TIMES:
        ys = out(blk, t)
        for j, y in enumerate(ys):
            ref = sine_reference(SINE["amplitude"], SINE["frequency"], SINE["phase"],
                                 SINE["offset"], t, j)
            np.testing.assert_allclose(y[0], ref, rtol=1e-13, atol=1e-13 * 3.0 ** j)


def test_sine_derivatives_match_central_differences():
    """(f(t+h) - f(t-h)) / 2h has error h^2/6 max|f'''|; with h = 1e-5 and w <= 3 that is
    below 1e-9 |w|^(j+3); the tolerance is 1e-7 relative to 3^j."""
    blk = Sine("s", **SINE)
    h = 1e-5
    for t in (0.2, 4.1):
        plus, minus, mid = out(blk, t + h), out(blk, t - h), out(blk, t)
        for j in range(1, 9):
            fd = (plus[j - 1] - minus[j - 1]) / (2 * h)
            np.testing.assert_allclose(mid[j], fd, atol=1e-7 * 3.0 ** j)
        # second derivative straight from y: error h2^2/12 max|y''''| ~ 7e-7 for h2 = 1e-3
        h2 = 1e-3
        fd2 = (out(blk, t + h2)[0] - 2 * mid[0] + out(blk, t - h2)[0]) / h2 ** 2
        np.testing.assert_allclose(mid[2], fd2, atol=1e-5)


def test_sine_scalar_and_per_channel_forms():
    blk = Sine("s", amplitude=2.0, frequency=0.5, phase=0.25, derivatives=1)
    assert blk.outputs["y"].shape == ()
    y, yd = out(blk, 1.5)
    assert y.shape == (1,)
    assert y[0] == pytest.approx(2 * math.sin(0.75 + 0.25), abs=1e-15)
    assert yd[0] == pytest.approx(math.cos(0.75 + 0.25), abs=1e-15)
    # (n,) arrays are per channel, the offset alone can set n
    blk = Sine("s", amplitude=1.0, frequency=[1.0, 2.0])
    assert blk.outputs["y"].shape == (2,)
    np.testing.assert_allclose(out(blk, 0.3)[0][0], [math.sin(0.3), math.sin(0.6)], rtol=1e-15)
    blk = Sine("s", amplitude=1.0, frequency=1.0, offset=[0.0, 1.0, 2.0])
    np.testing.assert_allclose(out(blk, 0.3)[0][0], math.sin(0.3) + np.array([0.0, 1, 2]))


def test_sine_batch_with_swept_frequency_and_amplitude():
    variants = []
    for i in range(4):
        v = dict(SINE, derivatives=3)
        v["frequency"] = [[1.0 + 0.3 * i, 3.0 - 0.2 * i]]
        v["amplitude"] = (np.array(SINE["amplitude"]) * (1 + i)).tolist()
        variants.append(v)
    assert_batch_matches(Sine, variants)
    assert_batch_matches(Sine, [{"amplitude": a, "frequency": 2.0, "derivatives": 2}
                                for a in (1.0, -2.0, 0.5)])


# --------------------------------------------------------------------------- MultiSine
def test_multisine_matches_formula_and_sine():
    w = [1.0, 2.5, 4.0]
    A = [[1.0, 0.5, 0.2], [0.3, 0.0, 1.0]]
    phases = [[0.0, 0.1, 0.2], [1.0, 1.1, 1.2]]
    blk = MultiSine("m", frequencies=w, amplitudes=A, phases=phases, derivatives=2)
    twin = Sine("s", amplitude=A, frequency=[w], phase=phases, derivatives=2)
    for t in TIMES:
        ys = out(blk, t)
        for j in range(3):
            ref = [sum(A[i][k] * w[k] ** j * math.sin(w[k] * t + phases[i][k] + j * math.pi / 2)
                       for k in range(3)) for i in range(2)]
            np.testing.assert_allclose(ys[j][0], ref, rtol=1e-13, atol=1e-13)
            np.testing.assert_array_equal(ys[j], out(twin, t)[j])
    # a phase row (n*,) is shared by all channels (numpy broadcasting)
    row = MultiSine("m", frequencies=w, amplitudes=A, phases=[0.3, 0.2, 0.1])
    full = MultiSine("m", frequencies=w, amplitudes=A, phases=[[0.3, 0.2, 0.1]] * 2)
    np.testing.assert_array_equal(out(row, 0.7)[0], out(full, 0.7)[0])


def test_multisine_batch():
    assert_batch_matches(MultiSine, [
        {"frequencies": [1.0 + i, 2.0 * i + 3], "amplitudes": [[1.0, 0.5], [i, 1.0]],
         "phases": [0.1 * i, 0.0]} for i in range(3)])


# --------------------------------------------------------------------------- RandomDisturbance
def test_random_disturbance_is_seeded_band_limited_and_has_the_requested_rms():
    cfg = {"n": 2, "std": [0.5, 2.0], "cutoff": 8.0, "seed": 3, "components": 40}
    blk = RandomDisturbance("r", **cfg)
    again = RandomDisturbance("r", **cfg)
    other = RandomDisturbance("r", **dict(cfg, seed=4))
    assert out(blk, 1.3)[0].tolist() == out(again, 1.3)[0].tolist()
    assert not np.allclose(out(blk, 1.3)[0], out(other, 1.3)[0])
    # stored data: frequencies inside (0, cutoff), one per band; mean square exactly std^2
    w = blk.p.frequency[0]
    assert np.all(w > 0) and np.all(w < 8.0)
    np.testing.assert_array_equal(np.floor(w / (8.0 / 40)), np.tile(np.arange(40), (2, 1)))
    A = blk.p.even_coef[0, 0]
    np.testing.assert_allclose(np.sum(A ** 2, axis=1) / 2, [0.25, 4.0], rtol=1e-14)
    # the signal: sampled over 1000 s, zero mean, RMS within 5 %, no power above the cutoff
    t = np.arange(0.0, 1000.0, 0.05)
    y = np.array([out(blk, ti)[0][0] for ti in t[::10]])  # coarse check on a subsample
    assert np.all(np.abs(y.mean(axis=0)) < 0.1 * np.array([0.5, 2.0]))
    # dense sampling without the per-call loop: evaluate the stored sum directly
    ph = blk.p.phase[0]
    dense = np.einsum("ik,tik->ti", A, np.sin(w[None] * t[:, None, None] + ph[None]))
    np.testing.assert_allclose(dense[::10], y, atol=1e-12)
    rms = np.sqrt(np.mean(dense ** 2, axis=0))
    np.testing.assert_allclose(rms, [0.5, 2.0], rtol=0.05)
    spec = np.abs(np.fft.rfft(dense * np.hanning(t.size)[:, None], axis=0)) ** 2
    omega = 2 * np.pi * np.fft.rfftfreq(t.size, 0.05)
    above = spec[omega > 1.1 * 8.0].sum(axis=0) / spec.sum(axis=0)
    assert np.all(above < 1e-6)


def test_random_disturbance_batch_over_seeds():
    assert_batch_matches(RandomDisturbance, [
        {"n": 3, "std": 1.0 + s, "cutoff": 5.0, "seed": s, "components": 10} for s in range(4)])


# --------------------------------------------------------------------------- Polynomial
COEF = [[1.0, -2.0, 0.5, 0.25, -0.1], [0.0, 3.0, 0.0, 0.0, 0.0], [4.0, 0.0, 0.0, 0.0, 0.0]]


def test_polynomial_and_derivatives_match_numpy_polynomial():
    blk = Polynomial("p", coefficients=COEF, derivatives=6)
    assert list(blk.outputs) == ["y"] + [f"y_d{j}" for j in range(1, 7)]
    for t in TIMES:
        ys = out(blk, t)
        for j in range(7):
            ref = [P.polyval(t, P.polyder(row, j)) if j < len(row) else 0.0 for row in COEF]
            np.testing.assert_allclose(ys[j][0], ref, rtol=1e-13, atol=1e-12)


def test_polynomial_derivatives_match_central_differences():
    """Central differences are exact for degree <= 2 and err by h^2/6 |y'''| otherwise;
    h = 1e-5 gives < 1e-9 here; tolerance 1e-7 relative."""
    blk = Polynomial("p", coefficients=COEF, derivatives=4)
    h = 1e-5
    for t in (0.3, -1.7, 2.2):
        plus, minus, mid = out(blk, t + h), out(blk, t - h), out(blk, t)
        for j in range(1, 5):
            np.testing.assert_allclose(mid[j], (plus[j - 1] - minus[j - 1]) / (2 * h),
                                       rtol=1e-7, atol=1e-7)


def test_polynomial_scalar_form_ramp():
    blk = Polynomial("p", coefficients=[0.5, 2.0], derivatives=2)
    assert blk.outputs["y"].shape == ()
    y, yd, ydd = out(blk, 3.0)
    assert (y.tolist(), yd.tolist(), ydd.tolist()) == ([6.5], [2.0], [0.0])


def test_polynomial_batch():
    assert_batch_matches(Polynomial, [
        {"coefficients": (np.array(COEF) * s).tolist(), "derivatives": 3} for s in (1, -2, 0.5)])


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize("cls, params, message", [
    (Sine, {"amplitude": 1.0, "frequency": 1.0, "derivatives": 9},
     "block 'b' parameter 'derivatives' must be between 0 and 8, got 9"),
    (Sine, {"amplitude": [1.0, 2.0], "frequency": [1.0, 2.0, 3.0]},
     "block 'b' parameters 'amplitude', 'frequency', 'phase' do not broadcast to one shape: "
     "'amplitude' (2, 1), 'frequency' (3, 1), 'phase' (1, 1); a 1-D array is one value per "
     "channel, write [[...]] for sinusoids shared by all channels"),
    (Sine, {"amplitude": [1.0, 2.0], "frequency": 1.0, "offset": [0.0, 1.0, 2.0]},
     "block 'b' parameter 'offset' has 3 values but amplitude, frequency and phase give 2 "
     "channels"),
    (MultiSine, {"frequencies": [1.0, 2.0], "amplitudes": [[1.0, 2.0, 3.0]]},
     "block 'b' parameter 'amplitudes' must be an (n, n*) matrix with n* = 2 columns (one per "
     "frequency), got shape (1, 3)"),
    (Polynomial, {"coefficients": [[[1.0]]]},
     "block 'b' parameter 'coefficients' must be a non-empty list c_0..c_d or an (n, d+1) "
     "matrix, got shape (1, 1, 1)"),
    (Polynomial, {"coefficients": [1.0], "derivatives": -1},
     "block 'b' parameter 'derivatives' must be between 0 and 8, got -1"),
    (RandomDisturbance, {"n": 2, "std": 1.0, "cutoff": 0.0},
     "block 'b' parameter 'cutoff' must be positive, got 0.0"),
    (RandomDisturbance, {"n": 2, "std": [1.0, 2.0, 3.0], "cutoff": 1.0},
     "block 'b' parameter 'std' must be a number or an (n,) vector with n = 2, all >= 0, got "
     "[1.0, 2.0, 3.0]"),
    (Step, {"after": [1.0, 2.0], "before": [1.0, 2.0, 3.0]},
     "block 'b' parameters 'before', 'after' and 'time' have shapes that do not broadcast: "
     "before (3,), after (2,), time scalar ()"),
    (Sine, {"amplitude": 1.0, "frequency": 1.0, "phase": "zero"},
     "block 'b' parameter 'phase' must be a number or array, got 'zero'"),
])
def test_bad_parameters_raise_with_exact_message(cls, params, message):
    with pytest.raises(ParameterError) as err:
        cls("b", **params)
    assert str(err.value) == message


def test_bad_sizes_are_refused_before_allocation():
    with pytest.raises(ParameterError, match="larger than the limit"):
        RandomDisturbance("b", n=10 ** 6, std=1.0, cutoff=1.0, components=10 ** 6)
    with pytest.raises(ParameterError, match="'amplitude' must be a number, an"):
        Sine("b", amplitude=np.ones((2, 2, 2)), frequency=1.0)


def test_a_frequency_whose_derivatives_overflow_is_refused_in_one_line():
    """Found by the fuzz test: w = 1.34e154 with two derivatives overflowed w^2 in setup (a
    RuntimeWarning, an error under the test settings, instead of a ParameterError)."""
    from fwdstep.blocks.sources import Sine
    from fwdstep.core.errors import ParameterError
    with pytest.raises(ParameterError) as info:
        Sine("s", amplitude=[1.0, 0.5], frequency=1.3407807929942597e+154, derivatives=2)
    assert str(info.value) == (
        "block 's': amplitude x frequency^2 (derivative 2) is larger than the largest float "
        "for frequency up to 1.34e+154 rad/s; use a smaller frequency or fewer derivatives")
    Sine("s", amplitude=[1.0, 0.5], frequency=1.3407807929942597e+154)    # no derivative: ok


def test_polynomial_derivative_coefficients_that_overflow_are_refused_in_one_line():
    with pytest.raises(ParameterError) as info:
        Polynomial("p", coefficients=[1e308] * 40, derivatives=8)
    assert str(info.value) == (
        "block 'p': the coefficients of derivative 1 (c_k k!/(k-1)!) are larger than the "
        "largest float; use smaller coefficients or fewer derivatives")
