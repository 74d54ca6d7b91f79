import numpy as np

from fwdstep.block import Block, Param
from fwdstep.registry import register


def counter_output(t, x, u):
    """y = the count (the state)."""
    return (x[:, 0].copy(),)


def counter_derivative(t, x, u):
    """The count changes only at located crossings: x' = 0."""
    return np.zeros(x.shape)


@register
class CrossingCounter(Block):
    """CrossingCounter: counts the times u rises through a level.

    Equation: y = the number of rising crossings of u through level since t = 0.

    Ports:
        | port | direction | shape | feedthrough |
        | u    | in        | ()    | -           |
        | y    | out       | ()    | -           |

    Parameters:
        level: the level u rises through (default 0).
    """

    params = {"level": Param("float", 0.0, "the level u rises through")}
    example = {"level": 0.5}

    def setup(self, level):
        self.declare_input("u", ())
        self.declare_output("y", (), feedthrough=())
        self.declare_state(1, 0.0)
        self.set_param("level", [level])                    # (1, 1): one per variant
        self.set_kernels(output=counter_output, derivative=counter_derivative)
        self.declare_zero_crossings(("level",))             # one guard: u - level

    def zero_crossings(self, t, x, u):
        return u[0].reshape((-1, 1)) - self.p.level

    def crossed(self, t, x, u, which):
        rising = which & (self.zero_crossings(t, x, u) >= 0.0)   # just past: new sign
        return x + rising
