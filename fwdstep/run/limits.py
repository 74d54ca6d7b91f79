"""Operating limits (``Block.declare_limit``): how close a run came to them, and where it
crossed one.

A block declares, per element of a port, an interval [lower, upper] (``URDFArm``: the URDF's
joint effort on ``tau``, velocity on ``qdot`` and position on ``q``).  The port's signal is
recorded (fwdstep.structure.compiler adds it to the log), and after the run, for each limit
and element i, over the recorded samples (stage 1 of every ``log_every``-th step and the
final time):

* symmetric limit [-u_i, u_i]: usage_i = max_t |v_i(t)| / u_i;
* otherwise: usage_i = max_t |v_i(t) - c_i| / r_i with c_i, r_i the interval's centre and
  half-width (1 at either bound);

so usage_i > 1 exactly when element i left its interval.  The record (``Result.limits``,
``summary.json``'s ``limits``, the report's "Operating limits" table) also gives the joint
of the largest usage and the first recorded time beyond a limit.  Crossing a limit changes
nothing in the run unless the limit's ``stop`` is set (``URDFArm``'s ``stop_on_limits``):
then the run ends at that sample (``first_stop``), results up to it kept, status
``limit exceeded`` (a batch: that variant is frozen there, the others go on).
"""
from __future__ import annotations

import numpy as np

#: the status of a run stopped at a limit (``stop_on_limits``)
LIMIT_STATUS = "limit exceeded"


def _usage(limit, values: np.ndarray) -> tuple:
    """(usage (T, B, n), beyond (T, B, n)) of ``values`` (T, B, n) against ``limit``."""
    lo = np.asarray(limit.lower, dtype=float)
    hi = np.asarray(limit.upper, dtype=float)
    with np.errstate(all="ignore"):
        if limit.symmetric:
            usage = np.abs(values) / hi
        else:
            usage = np.abs(values - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
        beyond = (values > hi) | (values < lo)
    return usage, beyond


def first_stop(d, t: np.ndarray, signals: dict) -> np.ndarray | None:
    """Per variant, the first recorded row beyond a limit with ``stop`` (len(t) where none);
    None when no limit stops."""
    rows = None
    for _, limit, name in d.limits:
        if not limit.stop or name not in signals:
            continue
        values = signals[name].reshape(len(t), d.batch, -1)
        beyond = _usage(limit, values)[1].any(axis=2)                     # (T, B)
        first = np.where(beyond.any(axis=0), beyond.argmax(axis=0), len(t))
        rows = first if rows is None else np.minimum(rows, first)
    return rows


def stop_message(d, t: np.ndarray, signals: dict, row: int, b: int, alone: bool) -> str:
    """The one line of variant ``b`` crossing a stopping limit at recorded ``row``."""
    for block, limit, name in d.limits:
        if not limit.stop or name not in signals:
            continue
        v = signals[name][row].reshape(d.batch, -1)[b]
        usage, beyond = _usage(limit, v[None, None])
        if beyond.any():
            i = int(np.argmax(np.where(beyond[0, 0], usage[0, 0], -1.0)))
            joint = limit.components[i] if i < len(limit.components) else str(i)
            bound = limit.upper[i] if v[i] > limit.upper[i] else limit.lower[i]
            where = f" (variant {b})" if d.batch > 1 and not alone else ""
            unit = f" {limit.unit}" if limit.unit else ""
            return (f"block '{block}' {limit.what} limit exceeded at t = {t[row]:.6g}: "
                    f"{limit.port}[{joint}] = {v[i]:.6g}{unit}, limit {bound:.6g}{unit}"
                    f"{where} (stop_on_limits); results up to that time are kept")
    return "an operating limit was exceeded"


def limit_record(d, t: np.ndarray, signals: dict) -> list:
    """What summary.json's ``limits`` holds: one entry per declared limit whose signal was
    recorded (a sweep records only its metric: none).  Numbers per element (joint); for a
    batch, per variant a list."""
    out = []
    B = d.batch
    for block, limit, name in d.limits:
        if name not in signals or len(t) == 0:
            continue
        values = signals[name].reshape(len(t), B, -1)
        usage, beyond = _usage(limit, values)
        with np.errstate(all="ignore"):
            peak = np.nanmax(np.where(np.isnan(usage), -np.inf, usage), axis=0)      # (B, n)
        peak = np.where(np.isfinite(peak), peak, np.nan)
        crossed = beyond.any(axis=2)                                              # (T, B)
        first = [float(t[int(np.argmax(crossed[:, b]))]) if crossed[:, b].any() else None
                 for b in range(B)]
        worst = [int(np.nanargmax(peak[b])) if np.isfinite(peak[b]).any() else 0
                 for b in range(B)]
        names = list(limit.components) or [str(i) for i in range(values.shape[2])]
        per = {
            "usage": [[None if np.isnan(u) else float(u) for u in peak[b]] for b in range(B)],
            "max_usage": [None if np.isnan(peak[b, worst[b]]) else float(peak[b, worst[b]])
                          for b in range(B)],
            "worst_joint": [names[worst[b]] for b in range(B)],
            "exceeded": [bool(crossed[:, b].any()) for b in range(B)],
            "first_exceeded_t": first,
        }
        entry = {"block": block, "port": limit.port, "signal": name, "what": limit.what,
                 "unit": limit.unit, "joints": names,
                 "lower": list(limit.lower), "upper": list(limit.upper),
                 "usage_definition": ("max over recorded t of |v_i| / upper_i" if limit.symmetric
                                      else "max over recorded t of |v_i - centre_i| / "
                                           "half-width_i (1 at either bound)"),
                 "stop": limit.stop}
        for key, value in per.items():
            entry[key] = value[0] if B == 1 else value
        out.append(entry)
    return out


def describe(record: list) -> list:
    """One line per limit that a single run exceeded (the CLI prints them)."""
    lines = []
    for e in record:
        if e["exceeded"] is True:
            lines.append(f"block '{e['block']}' {e['what']} limit exceeded: {e['port']} reached "
                         f"{e['max_usage']:.3g} x its limit at joint {e['worst_joint']} "
                         f"(first beyond at t = {e['first_exceeded_t']:.6g} s)")
        elif isinstance(e["exceeded"], list) and any(e["exceeded"]):
            lines.append(f"block '{e['block']}' {e['what']} limit exceeded in "
                         f"{sum(e['exceeded'])} of {len(e['exceeded'])} variants")
    return lines
