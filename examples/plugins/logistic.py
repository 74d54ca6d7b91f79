"""A user block outside the library, loaded with ``--plugin examples/plugins/logistic.py``
(or ``load_diagram(path, plugins=["examples/plugins/logistic.py"])``).  The worked example
of docs/writing-blocks.md."""
from __future__ import annotations

import numpy as np

from fwdstep.block import Block, Param
from fwdstep.errors import ParameterError
from fwdstep.registry import register


def logistic_output(t, x, u, rate, capacity):
    """y = x (the population), one array with the leading batch axis."""
    return (x,)


def logistic_derivative(t, x, u, rate, capacity):
    """dx/dt = r x (1 - x / K) + u, elementwise; rate and capacity are (B, n) or (1, n)."""
    return rate * x * (1.0 - x / capacity) + u


@register
class Logistic(Block):
    """Logistic growth with an inflow: dx/dt = r x (1 - x / K) + u, y = x (n independent
    populations).

    Equation: dx_i/dt = r_i x_i (1 - x_i / K_i) + u_i, y = x.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | (n,)  | -           |
        | y    | out       | (n,)  | -           |

    Parameters:
        rate: growth rate r (one number, or n numbers).
        capacity: carrying capacity K > 0 (one number, or n numbers).
        x0: initial population (one number, or n numbers).
        n: number of populations (default 1).
    """

    params = {
        "rate": Param("array", 1.0, "growth rate r, scalar or (n,)"),
        "capacity": Param("array", 1.0, "carrying capacity K > 0, scalar or (n,)"),
        "x0": Param("array", 0.1, "initial population, scalar or (n,)"),
        "n": Param("int", 1, "number of populations"),
    }
    example = {"rate": [1.0, 2.0], "capacity": 3.0, "x0": [0.5, 1.0], "n": 2}

    def setup(self, rate, capacity, x0, n):
        if n < 1:
            raise ParameterError(f"block '{self.name}' parameter 'n' must be at least 1, "
                                 f"got {n}", block=self.name)
        if np.any(np.asarray(capacity) <= 0.0):
            raise ParameterError(f"block '{self.name}' parameter 'capacity' must be positive",
                                 block=self.name)
        self.declare_input("u", (n,))
        self.declare_output("y", (n,), feedthrough=())      # y depends on the state only
        self.declare_state(n, np.broadcast_to(x0, (n,)))
        self.set_param("rate", np.broadcast_to(rate, (n,)))
        self.set_param("capacity", np.broadcast_to(capacity, (n,)))
        self.set_kernels(output=logistic_output, derivative=logistic_derivative,
                         params=("rate", "capacity"))
