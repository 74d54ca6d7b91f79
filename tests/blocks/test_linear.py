"""Integrator, TransferFunction and StateSpace against scipy.signal and analytic solutions.

Blocks are run standalone: a small fixed-step RK4 loop in this file calls ``derivative`` and
``output`` directly (the engine is not needed).  Inputs are smooth (sums of sinusoids), so
RK4 at h = 1e-3 is accurate to ~1e-12 (checked against solve_ivp when written); what remains
of the 1e-6 tolerance is ``scipy.signal.lsim``'s linear interpolation of the input between
samples, run on a 4x finer grid (measured: <= 4e-8).
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from fwdstep.blocks.linear import Integrator, StateSpace, TransferFunction
from fwdstep.core.errors import ParameterError

T_END = 4.0
STEP = 1e-3


class Smooth:
    """A different sum of two sinusoids plus a constant in every element of ``shape``."""

    def __init__(self, shape, seed=0):
        rng = np.random.default_rng(seed)
        self.shape = tuple(shape)
        size = int(np.prod(shape, dtype=int)) if shape else 1
        self.amp = rng.uniform(0.5, 2.0, (2, size))
        self.freq = rng.uniform(0.3, 2.0, (2, size))
        self.phase = rng.uniform(0, 2 * np.pi, (2, size))
        self.offset = rng.uniform(-1, 1, size)

    def __call__(self, t):
        """Value at a scalar t, shape ``shape``."""
        v = self.offset + (self.amp * np.sin(self.freq * t + self.phase)).sum(0)
        return v.reshape(self.shape)

    def samples(self, ts):
        """Values on a time grid, shape (len(ts), *shape)."""
        v = self.offset + (self.amp[:, None] * np.sin(self.freq[:, None] * ts[:, None]
                                                      + self.phase[:, None])).sum(0)
        return v.reshape((len(ts),) + self.shape)


def simulate(block, u_of_t, t_end=T_END, h=STEP, x0=None):
    """RK4 on one block with input u_of_t(t) -> (*shape) array; returns t, outputs[k]."""
    n_steps = int(round(t_end / h))
    x = block.x0.copy() if x0 is None else x0
    ts = np.linspace(0.0, n_steps * h, n_steps + 1)

    def u(t):
        return (u_of_t(t)[None],)

    def f(t, x):
        return block.derivative(t, x, u(t))

    outs = [block.output(0.0, x, u(0.0))]
    for i in range(n_steps):
        t = ts[i]
        k1 = f(t, x)
        k2 = f(t + h / 2, x + h / 2 * k1)
        k3 = f(t + h / 2, x + h / 2 * k2)
        k4 = f(t + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        outs.append(block.output(ts[i + 1], x, u(ts[i + 1])))
    return ts, [np.concatenate([o[k] for o in outs]) for k in range(len(outs[0]))]


def lsim(system, samples, ts, refine=4):
    """scipy.signal.lsim on a grid ``refine`` times finer than ``ts``, returned on ``ts``.

    lsim interpolates the input linearly between samples; its error (~ dt^2 u''/8 times the
    gain, 6.5e-7 for SS below at dt = 1e-3) drops 16-fold on the finer grid.  ``samples``
    maps a time grid to the input array lsim expects, (len,) or (len, n_u).
    """
    if isinstance(system, tuple):
        system = tuple(np.trim_zeros(np.asarray(c, dtype=float), "f") for c in system)
    fine = np.linspace(ts[0], ts[-1], refine * (len(ts) - 1) + 1)
    return scipy.signal.lsim(system, samples(fine), fine)[1][::refine]


def probe_matrices(block):
    """A, B, C, D of a one-input one-output block, read off through the run-time API."""
    n = block.n_states
    (name_in, port_in), = block.inputs.items()
    m = port_in.size
    zero_u = (np.zeros((1,) + port_in.shape),)
    eye_x = np.eye(n)
    A = np.stack([block.derivative(0.0, eye_x[i:i + 1], zero_u)[0] for i in range(n)], 1)
    C = np.stack([block.output(0.0, eye_x[i:i + 1], zero_u)[0].ravel() for i in range(n)], 1)
    B, D = [], []
    for j in range(m):
        e = np.zeros(m)
        e[j] = 1.0
        uj = (e.reshape((1,) + port_in.shape),)
        B.append(block.derivative(0.0, np.zeros((1, n)), uj)[0])
        D.append(block.output(0.0, np.zeros((1, n)), uj)[0].ravel())
    return A, np.stack(B, 1), C.reshape(-1, n), np.stack(D, 1)


def frequency_response(A, B, C, D, s):
    return C @ np.linalg.solve(s * np.eye(A.shape[0]) - A, B) + D


S_POINTS = [0.3j, 1.0 + 2.0j, -0.5 + 0.1j, 5.0j, 2.0]

TFS = [  # (num, den): strictly proper, biproper, non-monic, pure gain, first order
    ([1.0, 2.0], [1.0, 2.0, 3.0, 1.0]),
    ([2.0, 3.0, 1.0], [1.0, 0.8, 4.0]),
    ([0.0, 3.0, 1.0], [2.0, 1.0, 5.0]),
    ([1.0], [1.0, 1.0]),
]


# --------------------------------------------------------------------------- Integrator
def test_integrator_integrates_cosine_in_every_element():
    blk = Integrator("i", shape=[2, 2], initial=[[1.0, 2.0], [3.0, 4.0]])
    w = np.array([[1.0, 2.0], [0.5, 3.0]])
    ts, (y,) = simulate(blk, lambda t: np.cos(w * t), t_end=2.0)
    exact = np.sin(w * ts[:, None, None]) / w + blk.x0.reshape(2, 2)
    assert np.max(np.abs(y - exact)) < 1e-11
    assert blk.feedthrough("y") == ()


# --------------------------------------------------------------------------- TransferFunction
@pytest.mark.parametrize("num, den", TFS)
def test_transfer_function_matches_lsim(num, den):
    blk = TransferFunction("tf", num=num, den=den)
    u = Smooth(())
    ts, (y,) = simulate(blk, u)
    expected = lsim((num, den), u.samples, ts)
    assert np.max(np.abs(y - expected)) < 1e-6


@pytest.mark.parametrize("num, den", TFS)
def test_transfer_function_frequency_response(num, den):
    blk = TransferFunction("tf", num=num, den=den, shape=[2])
    A, B, C, D = probe_matrices(blk)
    for s in S_POINTS:
        H = frequency_response(A, B, C, D, s)
        h = np.polyval(num, s) / np.polyval(den, s)
        assert np.max(np.abs(H - h * np.eye(2))) < 1e-10 * max(1.0, abs(h))


def test_transfer_function_filters_each_element_of_a_matrix_signal():
    num, den = [1.0, 2.0], [1.0, 2.0, 3.0, 1.0]
    shape = (2, 3)
    blk = TransferFunction("tf", num=num, den=den, shape=list(shape))
    signal = Smooth(shape)
    ts, (y,) = simulate(blk, signal)
    scalar = TransferFunction("tf1", num=num, den=den)
    for i in range(shape[0]):
        for j in range(shape[1]):
            _, (yij,) = simulate(scalar, lambda t, i=i, j=j: signal(t)[i, j])
            assert np.max(np.abs(y[:, i, j] - yij)) < 1e-12
            expected = lsim((num, den), lambda g, i=i, j=j: signal.samples(g)[:, i, j], ts)
            assert np.max(np.abs(y[:, i, j] - expected)) < 1e-6


def test_transfer_function_initial_state_is_the_output_of_a_strictly_proper_lag():
    blk = TransferFunction("lag", num=[3.0], den=[1.0, 2.0], shape=[2], initial=[[1.0, -0.5]])
    ts, (y,) = simulate(blk, lambda t: np.zeros(2), t_end=1.0)
    assert np.max(np.abs(y - np.array([1.0, -0.5]) * np.exp(-2 * ts)[:, None])) < 1e-11


def test_transfer_function_feedthrough_only_when_biproper():
    assert TransferFunction("a", num=[1.0, 2.0], den=[1.0, 3.0]).feedthrough("y") == ("u",)
    assert TransferFunction("b", num=[0.0, 2.0], den=[1.0, 3.0]).feedthrough("y") == ()
    gain = TransferFunction("c", num=[3.0], den=[2.0])
    assert gain.n_states == 0
    assert gain.output(0.0, np.zeros((1, 0)), (np.array([4.0]),))[0][0] == 6.0


def test_improper_transfer_function_is_refused():
    with pytest.raises(ParameterError) as err:
        TransferFunction("tf", num=[1.0, 0.0, 0.0, 1.0], den=[1.0, 1.0, 1.0])
    assert str(err.value) == ("block 'tf' transfer function is improper: numerator degree 3 "
                              "> denominator degree 2")


def test_transfer_function_refuses_bad_shapes_and_sizes():
    with pytest.raises(ParameterError, match="must not be zero"):
        TransferFunction("tf", num=[1.0], den=[0.0, 0.0])
    with pytest.raises(ParameterError, match="larger than the limit"):
        TransferFunction("tf", num=[1.0], den=[1.0] + [0.0] * 10, shape=[1000])
    with pytest.raises(ParameterError, match="does not broadcast to"):
        TransferFunction("tf", num=[1.0], den=[1.0, 1.0, 1.0], shape=[2], initial=[1, 2, 3])
    with pytest.raises(ParameterError, match="positive whole numbers"):
        TransferFunction("tf", num=[1.0], den=[1.0, 1.0], shape=[2.5])


# --------------------------------------------------------------------------- StateSpace
SS = {
    "A": [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -3.0, -2.5]],
    "B": [[0.0, 1.0], [1.0, 0.0], [0.5, -1.0]],
    "C": [[1.0, 0.0, 2.0], [0.0, -1.0, 1.0]],
    "D": [[0.3, 0.0], [0.0, -0.7]],
}


def test_state_space_matches_lsim_on_a_vector_signal():
    blk = StateSpace("ss", **SS)
    signal = Smooth((2,))
    ts, (y,) = simulate(blk, signal)
    sys = scipy.signal.StateSpace(*(np.array(SS[k]) for k in "ABCD"))
    expected = lsim(sys, signal.samples, ts)
    assert np.max(np.abs(y - expected)) < 1e-6


def test_state_space_filters_a_matrix_signal_column_by_column():
    p = 3
    blk = StateSpace("ss", **SS, columns=p)
    assert blk.inputs["u"].shape == (2, p) and blk.outputs["y"].shape == (2, p)
    signal = Smooth((2, p))
    ts, (y,) = simulate(blk, signal)
    vector = StateSpace("ssv", **SS)
    sys = scipy.signal.StateSpace(*(np.array(SS[k]) for k in "ABCD"))
    for j in range(p):
        _, (yj,) = simulate(vector, lambda t, j=j: signal(t)[:, j])
        assert np.max(np.abs(y[:, :, j] - yj)) < 1e-12
        expected = lsim(sys, lambda g, j=j: signal.samples(g)[:, :, j], ts)
        assert np.max(np.abs(y[:, :, j] - expected)) < 1e-6


def test_state_space_frequency_response_is_kron_with_identity():
    p = 2
    blk = StateSpace("ss", **SS, columns=p)
    A, B, C, D = probe_matrices(blk)
    A0, B0, C0, D0 = (np.array(SS[k]) for k in "ABCD")
    for s in S_POINTS:
        G = frequency_response(A0, B0, C0, D0, s)
        H = frequency_response(A, B, C, D, s)
        assert np.max(np.abs(H - np.kron(G, np.eye(p)))) < 1e-10 * max(1.0, np.abs(G).max())


def test_state_space_initial_state_decays_by_the_matrix_exponential():
    from scipy.linalg import expm
    x0 = np.array([1.0, -1.0, 0.5])
    blk = StateSpace("ss", **SS, initial=x0)
    ts, (y,) = simulate(blk, lambda t: np.zeros(2), t_end=1.0)
    C = np.array(SS["C"])
    for i in (0, 500, 1000):
        assert np.allclose(y[i], C @ expm(np.array(SS["A"]) * ts[i]) @ x0, atol=1e-11)


@pytest.mark.parametrize("change, message", [
    ({"A": [[1.0, 2.0, 3.0]]}, "parameter 'A' has shape (1, 3), expected a non-empty square"),
    ({"B": [[1.0], [2.0]]}, "parameter 'B' has shape (2, 1), expected (3, n_u) with n_x = 3"),
    ({"C": [[1.0, 2.0]]}, "parameter 'C' has shape (1, 2), expected (n_y, 3) with n_x = 3"),
    ({"D": [[1.0, 2.0, 3.0]]}, "parameter 'D' has shape (1, 3), expected (2, 2) = (n_y from "
                               "C, n_u from B)"),
    ({"B": [1.0, 2.0, 3.0]}, "parameter 'B' must be a matrix ((3, n_u) with n_x = 3 from A), "
                             "got an array of shape (3,)"),
    ({"columns": 0}, "parameter 'columns' must be at least 1, got 0"),
])
def test_state_space_shape_errors_say_what_was_expected(change, message):
    with pytest.raises(ParameterError) as err:
        StateSpace("ss", **{**SS, **change})
    assert str(err.value).startswith(f"block 'ss' {message}")
