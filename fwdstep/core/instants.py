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
    ratio = (t_final - offset) / period if offset <= t_final else -1.0
    if not math.isfinite(ratio) or ratio > MAX_EVENTS:   # 5e-324: inf, never an OverflowError
        raise ConfigError(f"block '{block.name}': sample period {period:g} s gives "
                          f"{ratio + 1:.3g} sample instants up to t_final (limit "
                          f"{MAX_EVENTS:.0e})", block=block.name)
    count = math.floor(ratio + 1e-9) + 1 if ratio >= 0 else 0
    if count > MAX_EVENTS:
        raise ConfigError(f"block '{block.name}': sample period {period:g} s gives {count:.3g} "
                          f"sample instants up to t_final (limit {MAX_EVENTS:.0e})",
                          block=block.name)
    return offset + np.arange(max(count, 0)) * period
