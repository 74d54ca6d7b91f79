"""Scalar objectives of a run and their gradients: what ``fwdstep tune`` minimises and
constrains, and what ``Result.metric_gradient`` differentiates.

An objective is written either as the name of one of the diagram's error metrics
(``rms_error_norm``, ``final_error_norm``, ... of ``fwdstep.results.result.METRIC_DEFINITIONS``,
computed from the signal named by ``metrics: error:``) or as ``FUNCTION(SIGNAL)`` of any
logged signal (``max_abs(tau.y)``), FUNCTION one of OBJECTIVE_FUNCTIONS.  Every objective is
a function of the logged samples y_k (k over the logged times, each flattened to n
components); its gradient with respect to parameters is the chain rule through the
sensitivities dy_k/dp (``fwdstep.analysis.sensitivity``).  Maxima (``max_abs``,
``max_norm``, the tail maxima) are differentiated at the sample and component that attain
them (a subgradient: exact wherever the maximum is attained once).
"""
from __future__ import annotations

import re

import numpy as np

from fwdstep.core.errors import ConfigError

#: FUNCTION(SIGNAL): what each computes from the logged samples y_k (n components each)
OBJECTIVE_FUNCTIONS = {
    "rms": "sqrt(mean over k of |y_k|_2^2)",
    "mean_square": "mean over k of |y_k|_2^2",
    "ise": "integral of |y(t)|_2^2 dt (trapezoidal rule over the logged times)",
    "max_abs": "max over k and components of |y_k,i|",
    "max_norm": "max over k of |y_k|_2",
    "final_norm": "|y_K|_2 at the last logged time",
    "final_abs": "max over components of |y_K,i| at the last logged time",
}
#: the diagram's error metrics as (function, over the tail only)
_NAMED = {
    "final_error_norm": ("final_norm", False),
    "final_error_max_abs": ("final_abs", False),
    "tail_error_norm_max": ("max_norm", True),
    "tail_error_max_abs": ("max_abs", True),
    "rms_error_norm": ("rms", False),
    "error_norm_max": ("max_norm", False),
}
_CALL = re.compile(r"^\s*(?P<fn>[A-Za-z_]+)\s*\(\s*(?P<sig>[^()]+?)\s*\)\s*$")
_CONSTRAINT = re.compile(r"^(?P<expr>.+?)\s*(?P<op><=|>=)\s*(?P<bound>[-+0-9.eE]+)\s*$")


def parse_objective(text: str) -> tuple:
    """'rms_error_norm' -> ('rms', None, False); 'max_abs(tau.y)' -> ('max_abs', 'tau.y', False);
    the signal None means the diagram's ``metrics: error:`` signal."""
    text = str(text).strip()
    if text in _NAMED:
        fn, tail = _NAMED[text]
        return fn, None, tail
    m = _CALL.match(text)
    if m and m.group("fn") in OBJECTIVE_FUNCTIONS:
        return m.group("fn"), m.group("sig"), False
    raise ConfigError(f"objective '{text}' is neither a metric ({', '.join(_NAMED)}) nor "
                      f"FUNCTION(SIGNAL) with FUNCTION one of "
                      f"{', '.join(OBJECTIVE_FUNCTIONS)}")


def parse_constraint(text: str) -> tuple:
    """'max_abs(tau.y) <= 87' -> ('max_abs(tau.y)', '<=', 87.0)."""
    m = _CONSTRAINT.match(str(text).strip())
    if not m:
        raise ConfigError(f"constraint '{text}' must read OBJECTIVE <= NUMBER or "
                          "OBJECTIVE >= NUMBER, e.g. \"max_abs(tau.y) <= 87\"")
    try:
        bound = float(m.group("bound"))
    except ValueError:
        raise ConfigError(f"constraint '{text}': '{m.group('bound')}' is not a number") from None
    parse_objective(m.group("expr"))
    return m.group("expr").strip(), m.group("op"), bound


def _signal_of(result, signal):
    if signal is None:
        d = result.diagram
        if d is None or "error" not in d.spec.metrics:
            raise ConfigError("the diagram names no error signal (metrics: error:), so its "
                              "error metrics are not defined; write FUNCTION(SIGNAL)")
        signal = d.spec.metrics["error"]
    if signal not in result:
        raise ConfigError(f"objective signal '{signal}' was not recorded; recorded signals "
                          f"are: {', '.join(result.names)} (add it to log:)")
    return signal


def objective(result, text: str, gradient: bool = False):
    """The value of objective ``text`` on ``result`` (a single run), and with
    ``gradient=True`` also its gradient: one array per differentiated parameter, in the
    order and shapes of ``result.sensitivity_parameters`` (a dict text -> array)."""
    fn, signal, tail = parse_objective(text)
    signal = _signal_of(result, signal)
    t = np.asarray(result.t, dtype=float)
    y = np.asarray(result[signal], dtype=float).reshape(len(t), -1)
    dy = None
    if gradient:
        dy = result.sensitivity_matrix(signal)             # (T, n, P)
    mask = np.ones(len(t), dtype=bool)
    if tail:
        frac = result.diagram.spec.metrics.get("tail", 0.2) if result.diagram else 0.2
        mask = t >= t[0] + (1 - frac) * (t[-1] - t[0])
    value, g = _FUNCTIONS[fn](t[mask], y[mask], None if dy is None else dy[mask])
    if not gradient:
        return float(value)
    return float(value), result.split_parameters(g)


def _rms(t, y, dy):
    ms = float(np.mean(np.sum(y * y, axis=1)))
    value = np.sqrt(ms)
    if dy is None:
        return value, None
    if value == 0:
        return value, np.zeros(dy.shape[2])
    return value, np.einsum("kn,knp->p", y, dy) / (len(t) * value)


def _mean_square(t, y, dy):
    value = float(np.mean(np.sum(y * y, axis=1)))
    return value, None if dy is None else 2.0 * np.einsum("kn,knp->p", y, dy) / len(t)


def _ise(t, y, dy):
    w = np.zeros(len(t))
    if len(t) > 1:
        dt = np.diff(t)
        w[:-1] += dt / 2
        w[1:] += dt / 2
    value = float(np.sum(w * np.sum(y * y, axis=1)))
    return value, None if dy is None else 2.0 * np.einsum("k,kn,knp->p", w, y, dy)


def _max_abs(t, y, dy):
    a = np.abs(y)
    k, i = np.unravel_index(int(np.argmax(a)), a.shape)
    value = float(a[k, i])
    return value, None if dy is None else np.sign(y[k, i]) * dy[k, i]


def _norm_at(y, dy, k):
    value = float(np.linalg.norm(y[k]))
    if dy is None:
        return value, None
    return value, (y[k] @ dy[k] / value if value > 0 else np.zeros(dy.shape[2]))


def _max_norm(t, y, dy):
    return _norm_at(y, dy, int(np.argmax(np.linalg.norm(y, axis=1))))


def _final_norm(t, y, dy):
    return _norm_at(y, dy, len(t) - 1)


def _final_abs(t, y, dy):
    return _max_abs(t[-1:], y[-1:], None if dy is None else dy[-1:])


_FUNCTIONS = {"rms": _rms, "mean_square": _mean_square, "ise": _ise, "max_abs": _max_abs,
              "max_norm": _max_norm, "final_norm": _final_norm, "final_abs": _final_abs}

__all__ = ["OBJECTIVE_FUNCTIONS", "objective", "parse_objective", "parse_constraint"]
