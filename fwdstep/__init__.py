"""fwdstep: block-diagram simulation of forwardstepping control of robot manipulators.

Python API::

    import fwdstep
    d = fwdstep.load_diagram("diagrams/theorem1.yaml", overrides={"ell": 3})
    r = fwdstep.simulate(d)
    r.t, r["err.y"], r.metrics()
"""
from fwdstep.structure.compiler import CompiledDiagram, compile_batch, load_diagram
from fwdstep.core.errors import (AlgebraicLoopError, BlockRuntimeError, ConfigError, DiagramError,
                     DivergenceError, ExpressionError, FwdstepError, OutputError, ParameterError,
                     ShapeError, SimulationError, UnknownBlockTypeError, WiringError, YamlError)
from fwdstep.results.result import Result, load_result
from fwdstep.run.simulate import SimulationInterrupted, simulate
from fwdstep.views.compare import compare  # noqa: E402 - after .result: fwdstep.compare(runs) is the function
from fwdstep.sweeps.sweep import SweepResult, run_sweep  # noqa: E402
from fwdstep.results.labelled import load_sweep  # noqa: E402

__all__ = [
    "load_diagram", "simulate", "compile_batch", "CompiledDiagram", "Result",
    "FwdstepError", "DiagramError", "YamlError", "ExpressionError", "ParameterError",
    "UnknownBlockTypeError", "WiringError", "ShapeError", "AlgebraicLoopError", "ConfigError",
    "OutputError", "SimulationError", "DivergenceError", "BlockRuntimeError",
    "SimulationInterrupted", "load_result", "compare", "run_sweep", "SweepResult", "load_sweep",
]
__version__ = "0.1.0"
