"""The simulation settings (the diagram's ``simulation:`` section), declared once.

``SIMULATION_KEYS`` (what a diagram may write), the JSON schema and the ``--set
simulation.X`` paths all derive from ``SimulationConfig``'s fields; the solver names from the
tableaux and the solve_ivp methods of ``fwdstep.core.solvers``; the backend names from
``BACKENDS``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from fwdstep.core.solvers import IVP_METHODS, TABLEAUX

#: the ways a run can be executed: the NumPy path, or the numba/LLVM compiled path
BACKENDS = ("numpy", "compiled")
#: every solver a diagram may name: the fixed-step tableaux, then scipy's adaptive methods
SOLVER_NAMES = tuple(TABLEAUX) + tuple(IVP_METHODS)


def _internal(default):
    return field(default=default, metadata={"setting": False})


@dataclass
class SimulationConfig:
    t_final: float = 10.0
    step: float = 1e-3
    solver: str = "rk4"
    log_every: int = 1
    bound: float = 1e8
    backend: str = "numpy"
    rtol: float = 1e-8           # dop853 / radau / lsoda only (fwdstep.run.ivp)
    atol: float = 1e-10
    stability_check: bool = True   # refuse a fixed step outside a block's stability region
    defaulted: tuple = _internal(())       # t_final/step the diagram did not give (the run's header says)
    given: bool = _internal(True)          # the diagram has a simulation: section

    @property
    def n_steps(self) -> int:
        return int(round(self.t_final / self.step))



#: the settings a diagram's ``simulation:`` section may give, in the documented order
SIMULATION_KEYS = tuple(f.name for f in fields(SimulationConfig) if f.metadata.get("setting", True))
