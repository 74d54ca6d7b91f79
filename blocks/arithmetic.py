"""Memoryless arithmetic blocks: gains, sums and products of signals."""
from __future__ import annotations

import numpy as np

from fwdstep.block import Block, Param
from fwdstep.errors import ParameterError
from fwdstep.registry import register


@register
class Gain(Block):
    """Gain: y = K u, with K a scalar (any signal shape) or a matrix (vector signal).

    Equation: y = K u.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | shape | -           |
        | y    | out       | (m,) for matrix K, else shape of u | u |

    Parameters:
        gain: scalar, or (m, n) matrix applied to a vector input of size n.
        shape: shape of the input signal u (list; [] for a scalar).
    """

    params = {
        "gain": Param("array", doc="scalar or (m, n) matrix"),
        "shape": Param("array", default=None, doc="input shape, e.g. [2]; default: n of the "
                       "matrix gain, or scalar"),
    }
    example = {"gain": [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]}

    def setup(self, gain, shape):
        K = np.asarray(gain, dtype=float)
        if K.ndim == 0:
            in_shape = () if shape is None else tuple(int(s) for s in np.atleast_1d(shape))
            self.declare_input("u", in_shape)
            self.declare_output("y", in_shape)
            self._matrix = False
        elif K.ndim == 2:
            in_shape = (K.shape[1],)
            if shape is not None and tuple(int(s) for s in np.atleast_1d(shape)) != in_shape:
                raise ParameterError(
                    f"block '{self.name}' parameter 'gain' has shape {K.shape}, which does not "
                    f"fit an input of shape {tuple(int(s) for s in np.atleast_1d(shape))}",
                    block=self.name)
            self.declare_input("u", in_shape)
            self.declare_output("y", (K.shape[0],))
            self._matrix = True
        else:
            raise ParameterError(f"block '{self.name}' parameter 'gain' must be a scalar or a "
                                 f"matrix, got shape {K.shape}", block=self.name)
        self.set_param("K_T", K.T if self._matrix else K)

    def output(self, t, x, u):
        if self._matrix:
            return (np.matmul(u[0][:, None, :], self.p.K_T)[:, 0, :],)
        return (self.p.K_T.reshape((-1,) + (1,) * (u[0].ndim - 1)) * u[0],)
