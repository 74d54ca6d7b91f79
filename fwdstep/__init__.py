"""fwdstep: block-diagram simulation of forwardstepping control of robot manipulators.

Python API::

    import fwdstep
    d = fwdstep.load_diagram("diagrams/theorem1.yaml", overrides={"ell": 3})
    r = fwdstep.simulate(d)
    r.t, r["err.y"], r.metrics()
"""
from .compiler import CompiledDiagram, compile_batch, load_diagram
from .errors import (AlgebraicLoopError, BlockRuntimeError, ConfigError, DiagramError,
                     DivergenceError, ExpressionError, FwdstepError, OutputError, ParameterError,
                     ShapeError, SimulationError, UnknownBlockTypeError, WiringError, YamlError)
from .result import Result, load_result
from .simulate import SimulationInterrupted, simulate
from .compare import compare  # noqa: E402 - after .result: fwdstep.compare(runs) is the function
from .sweep import SweepResult, run_sweep  # noqa: E402
from .labelled import load_sweep  # noqa: E402
from .animate import animate  # noqa: E402 - fwdstep.animate(r) is the function

__all__ = [
    "load_diagram", "simulate", "compile_batch", "CompiledDiagram", "Result",
    "FwdstepError", "DiagramError", "YamlError", "ExpressionError", "ParameterError",
    "UnknownBlockTypeError", "WiringError", "ShapeError", "AlgebraicLoopError", "ConfigError",
    "OutputError", "SimulationError", "DivergenceError", "BlockRuntimeError",
    "SimulationInterrupted", "load_result", "compare", "run_sweep", "SweepResult", "load_sweep",
    "animate",
]
__version__ = "0.1.0"
