"""The fwdstep block library.

Importing this package registers every library block in ``fwdstep.core.registry.REGISTRY``.
Modules are listed explicitly: one module, one family of blocks.
"""
from fwdstep.core.registry import REGISTRY, register  # noqa: F401

from . import sources  # noqa: F401,E402  Constant, Step, Sine, Polynomial, disturbances
from . import arithmetic  # noqa: F401,E402 Gain, Sum, Product, ScalarProduct, ...
from . import linear  # noqa: F401,E402   Integrator, TransferFunction, StateSpace
from . import reference  # noqa: F401,E402 ReferenceDynamics
from . import robot  # noqa: F401,E402    TwoLinkArm, Regressor, PointMass, ...
from . import adaptation  # noqa: F401,E402 AdaptationLaw
from . import stacked  # noqa: F401,E402  FilterDerivatives, TransferFunctionSum, LinearCombination
from . import urdf  # noqa: F401,E402     URDFArm, URDFRegressor (pinocchio imported lazily)
from . import nonlinear  # noqa: F401,E402 Saturation, DeadZone, RateLimiter, Friction, Switch, Lookup1D
from . import noise  # noqa: F401,E402     WhiteNoise
from . import discrete  # noqa: F401,E402  ZeroOrderHold, UnitDelay, DiscreteStateSpace, ...
