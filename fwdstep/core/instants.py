"""Sample instants a block declares as its discontinuities (``Block.discontinuities``):
computed from their index, never accumulated, and bounded in number."""
from __future__ import annotations

import math

import numpy as np

from fwdstep.core.errors import ConfigError

#: the most event times one block may declare in a run
MAX_EVENTS = 10_000_000


def sample_instants(block, period: float, offset: float, t_final: float) -> np.ndarray:
    """``offset + k * period`` for k = 0, 1, ... up to t_final (each computed from k, never
    accumulated).  Refuses a period that would give more than MAX_EVENTS instants."""
    if not period > 0:
        raise ConfigError(f"block '{block.name}': sample period must be positive, got "
                          f"{period:g}", block=block.name)
    count = math.floor((t_final - offset) / period + 1e-9) + 1 if offset <= t_final else 0
    if count > MAX_EVENTS:
        raise ConfigError(f"block '{block.name}': sample period {period:g} s gives {count:.3g} "
                          f"sample instants up to t_final (limit {MAX_EVENTS:.0e})",
                          block=block.name)
    return offset + np.arange(max(count, 0)) * period
