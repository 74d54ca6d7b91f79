"""fwdstep: block-diagram simulation of forwardstepping control of robot manipulators.

Python API::

    import fwdstep
    d = fwdstep.load_diagram("diagrams/theorem1.yaml", overrides={"ell": 3})
    r = fwdstep.simulate(d)
    r.t, r["err.y"], r.metrics()

    b = fwdstep.Diagram("built in Python")     # or build one: .add, .connect, ... .load()

The names below are imported on first use, so ``import fwdstep`` (and every command-line
verb) pays only for the layers it touches; docs/architecture.md shows the layers.
"""
import importlib

from fwdstep.core.version import __version__  # noqa: E402

#: public name -> the module that defines it
_PUBLIC = {
    "load_diagram": "fwdstep.structure.compiler",
    "compile_batch": "fwdstep.structure.compiler",
    "CompiledDiagram": "fwdstep.structure.compiler",
    "Diagram": "fwdstep.structure.builder",
    "simulate": "fwdstep.run.simulate",
    "SimulationInterrupted": "fwdstep.run.outcome",
    "Result": "fwdstep.results.result",
    "load_result": "fwdstep.results.result",
    "load_sweep": "fwdstep.results.labelled",
    "compare": "fwdstep.views.compare",
    "run_sweep": "fwdstep.sweeps.sweep",
    "SweepResult": "fwdstep.sweeps.sweep",
    "linearize": "fwdstep.analysis.linearize",
    "linearize_along": "fwdstep.analysis.linearize",
    "LinearModel": "fwdstep.analysis.linearize",
    "animate": "fwdstep.views.animate",
    "sensitivities": "fwdstep.analysis.sensitivity",
    "tune": "fwdstep.sweeps.tune",
    "identify_run": "fwdstep.analysis.identify",
}
_ERRORS = ("FwdstepError", "DiagramError", "YamlError", "ExpressionError", "ParameterError",
           "UnknownBlockTypeError", "WiringError", "ShapeError", "AlgebraicLoopError",
           "ConfigError", "OutputError", "SimulationError", "DivergenceError",
           "BlockRuntimeError")
_PUBLIC.update({name: "fwdstep.core.errors" for name in _ERRORS})

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'fwdstep' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
