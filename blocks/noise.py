"""Seeded random signals for experiments: sampled white noise of a stated power spectral
density.

``WhiteNoise`` is a pure function of time: the sample of interval k of channel i is a
standard normal number computed from (seed, k, i) by a counter-based hash (splitmix64
mixing, Box-Muller), never from a generator advanced during the run.  So the signal does
not depend on the solver step, on the order in which stages are evaluated, on how often the
diagram is run or on the other variants of a batch; each variant keeps its own seed.
(Smooth band-limited noise: ``RandomDisturbance`` in blocks/sources.py, or this block
through a low-pass ``TransferFunction``; docs/robustness.md.)
"""
from __future__ import annotations

import math

import numpy as np

from fwdstep.core.block import Block, Param
from fwdstep.core.errors import ParameterError
from fwdstep.core.registry import register

#: The most sample instants one WhiteNoise declares per run (as discontinuity times).
MAX_SAMPLES = 10_000_000


def white_noise_output(t, x, seed, sigma, mean, sample_time, channel):
    """y_i(t) = mean_i + sigma_i N_{k,i}, sigma_i = sqrt(S_i / Ts), with k Ts <= t < (k + 1) Ts
    exactly against the float products k * Ts (the declared sample instants, so y is
    right-continuous there) and N_{k,i} standard normal from the counters (seed, k, i):
    splitmix64's finaliser (a bijection of uint64 with full avalanche) applied to the
    counters, two 53-bit uniforms, Box-Muller."""
    k = np.floor(t / sample_time)
    k = np.where((k + 1.0) * sample_time <= t, k + 1.0, k)
    k = np.where(k * sample_time > t, k - 1.0, k)
    golden = np.uint64(0x9E3779B97F4A7C15)
    m1 = np.uint64(0xBF58476D1CE4E5B9)
    m2 = np.uint64(0x94D049BB133111EB)
    s30 = np.uint64(30)
    s27 = np.uint64(27)
    s31 = np.uint64(31)
    # h = mix(mix(mix(seed + golden) + k) + channel + golden); mix(z) is written out each time
    z = seed.astype(np.uint64) + golden
    z = (z ^ (z >> s30)) * m1
    z = (z ^ (z >> s27)) * m2
    z = (z ^ (z >> s31)) + k.astype(np.int64).astype(np.uint64)
    z = (z ^ (z >> s30)) * m1
    z = (z ^ (z >> s27)) * m2
    z = (z ^ (z >> s31)) + channel.astype(np.uint64) + golden
    z = (z ^ (z >> s30)) * m1
    z = (z ^ (z >> s27)) * m2
    h = z ^ (z >> s31)
    # two draws: w1 = mix(h + golden), w2 = mix(h + 2 golden)
    w1 = h + golden
    w1 = (w1 ^ (w1 >> s30)) * m1
    w1 = (w1 ^ (w1 >> s27)) * m2
    w1 = w1 ^ (w1 >> s31)
    w2 = h + golden + golden
    w2 = (w2 ^ (w2 >> s30)) * m1
    w2 = (w2 ^ (w2 >> s27)) * m2
    w2 = w2 ^ (w2 >> s31)
    s11 = np.uint64(11)
    u1 = ((w1 >> s11).astype(np.float64) + 1.0) * (1.0 / 9007199254740992.0)    # (0, 1]
    u2 = (w2 >> s11).astype(np.float64) * (1.0 / 9007199254740992.0)            # [0, 1)
    return (mean + sigma * (np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * math.pi * u2)),)


@register
class WhiteNoise(Block):
    """WhiteNoise: seeded Gaussian white noise of power spectral density S, held over Ts.

    Equation: y_i(t) = mean_i + sqrt(S_i / Ts) N_{k,i} for k Ts <= t < (k + 1) Ts, with
    N_{k,i} independent standard normal numbers fixed by (seed, k, i).  Its integral
    W_i(t) = int_0^t (y_i - mean_i) dt has variance S_i t at every sample instant, whatever
    Ts: y approximates white noise with autocorrelation S delta(tau), i.e. a two-sided power
    spectral density S (units^2 per Hz; the "noise power" of Simulink's Band-Limited White
    Noise), flat up to about 1 / (2 Ts).  The sample instants k Ts are declared as
    discontinuity times, so a fixed-step solver never straddles a jump.

    Ports:
        | port | direction | shape | feedthrough |
        | y    | out       | (n,)  | -           |

    Parameters:
        n: number of channels.
        psd: S, two-sided power spectral density per channel (>= 0; number or (n,)).
        sample_time: Ts, the hold interval (s, > 0); choose it a multiple of the step.
        seed: whole number >= 0; same seed, same signal (per variant in a batched sweep).
        mean: constant added per channel (default 0).
    """

    params = {
        "n": Param("int", 1, "number of channels"),
        "psd": Param("array", doc="two-sided power spectral density S per channel"),
        "sample_time": Param("float", doc="hold interval Ts (s)"),
        "seed": Param("int", 0, "random seed (whole number >= 0)"),
        "mean": Param("array", 0.0, "constant added per channel"),
    }
    #: the seed lives in ``p`` (as a float, exact below 2**53), so a batch may mix seeds
    stacked_params = ("seed",)
    example = {"n": 2, "psd": [1e-4, 4e-4], "sample_time": 0.01, "seed": 3}

    def setup(self, n, psd, sample_time, seed, mean):
        name = self.name
        if n < 1:
            raise ParameterError(f"block '{name}' parameter 'n' must be at least 1, got {n}",
                                 block=name)
        if not sample_time > 0:
            raise ParameterError(f"block '{name}' parameter 'sample_time' must be positive, "
                                 f"got {sample_time}", block=name)
        if not 0 <= seed < 2 ** 53:
            raise ParameterError(f"block '{name}' parameter 'seed' must be a whole number "
                                 f"from 0 to 2**53 - 1, got {seed}", block=name)
        psd = np.asarray(psd, dtype=float)
        mean = np.asarray(mean, dtype=float)
        for key, arr in (("psd", psd), ("mean", mean)):
            if arr.ndim > 1 or arr.size not in (1, n):
                raise ParameterError(f"block '{name}' parameter '{key}' must be a number or "
                                     f"{n} numbers, got shape {arr.shape}", block=name)
        if np.any(psd < 0):
            raise ParameterError(f"block '{name}' parameter 'psd' must not be negative, got "
                                 f"{psd.tolist()}", block=name)
        self.declare_output("y", (n,), feedthrough=())
        self.set_param("seed", [float(seed)])                       # (1, 1)
        self.set_param("sigma", np.broadcast_to(np.sqrt(psd / sample_time), (n,)))
        self.set_param("mean", np.broadcast_to(mean, (n,)))
        self.set_param("sample_time", [sample_time])                 # (1, 1)
        # the sample instants are discontinuity times: kept outside p as well, so variants with
        # another Ts never share a batch (one batch, one step grid; fwdstep.core.block.discontinuities)
        self.hold_interval = float(sample_time)
        self.set_param("channel", np.arange(n, dtype=float))
        self.set_kernels(output=white_noise_output,
                         params=("seed", "sigma", "mean", "sample_time", "channel"))

    def discontinuities(self, t_final: float) -> np.ndarray:
        """The sample instants k Ts, k = 0, 1, ..., up to t_final (each Ts of the batch); none
        when every variance is 0 (the signal is then the constant mean)."""
        if not np.any(self.p.sigma):
            return np.zeros(0)
        out = []
        for ts in (self.hold_interval,):
            count = math.floor(t_final / ts + 1e-9) + 1
            if count > MAX_SAMPLES:
                raise ParameterError(
                    f"block '{self.name}': sample_time {ts:g} s gives {count:.3g} samples up "
                    f"to t_final (limit {MAX_SAMPLES:.0e}); use a longer sample_time",
                    block=self.name)
            out.append(np.arange(count) * ts)
        return np.unique(np.concatenate(out)) if out else np.zeros(0)
