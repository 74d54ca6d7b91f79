"""A fixed step too large for a block's own dynamics is refused before anything runs.

One step of an explicit Runge-Kutta method multiplies a mode x' = lambda x by the stability
function R(h lambda) (``fwdstep.core.solvers.amplification``).  When a decaying mode
(Re lambda < 0) has |R(h lambda)| > 1, the numbers grow instead of decaying: a run that
reaches t_final anyway reports numbers with no relation to the diagram's (a RateLimiter with
its default time_constant 1e-3 under rk4 at h = 2.8e-3 settles at u - r h / 6, not at u).

Every block with states may say its own eigenvalues (``Block.state_eigenvalues``; a block
offering a ``linear_form`` gives its A's, ``RateLimiter`` -1/time_constant); for each
variant of a batch and each eigenvalue, h lambda is checked against the solver's stability
region.  The first block outside it is refused with one line: the block, its fastest
eigenvalue, the step, the largest stable step, and the ways out (a smaller step, solver
radau, or ``simulation.stability_check: false`` to run anyway).

This is a check of each block alone, inputs held: a loop through several blocks has other
eigenvalues (a slow integrator in a fast feedback loop), which only the whole system's
Jacobian would tell.  It catches the common case -- one fast filter, lag or pole written
into one block -- at no cost to the run.  Adaptive solvers (dop853, radau, lsoda) choose their
own steps and are not checked.
"""
from __future__ import annotations

import numpy as np

from fwdstep.core.errors import ConfigError
from fwdstep.core.linear import linear_form_of, matrix_eigenvalues
from fwdstep.core.solvers import TABLEAUX, amplification, stable_step

#: |R| may exceed 1 by this much (rounding) before a mode counts as growing
TOLERANCE = 1e-9


def block_eigenvalues(block) -> np.ndarray | None:
    """(1 or B, k) complex eigenvalues of ``block``'s own dynamics, or None if unknown."""
    if not block.n_states:
        return None
    ev = block.state_eigenvalues()
    if ev is None:
        form = linear_form_of(block)
        if form is None or form.A is None or not np.size(form.A):
            return None
        ev = matrix_eigenvalues(form.A)
    return np.atleast_2d(np.asarray(ev, dtype=complex))


def check_step(d) -> None:
    """Raise ``ConfigError`` if a block of compiled diagram ``d`` has a decaying mode that
    ``simulation.step`` makes grow under ``simulation.solver`` (see the module docstring)."""
    cfg = d.spec.simulation
    if cfg.solver not in TABLEAUX or not cfg.stability_check:
        return
    tab, h = TABLEAUX[cfg.solver], cfg.step
    for blk in d.blocks:
        ev = block_eigenvalues(blk)
        if ev is None:
            continue
        decaying = ev.real < 0
        gain = np.abs(amplification(tab, h * ev))
        grows = decaying & (gain > 1.0 + TOLERANCE)
        if not grows.any():
            slow = decaying & (gain > np.exp(0.5 * h * ev.real))
            if slow.any():
                _warn_unresolved(d, blk, ev, slow, gain, h, cfg.solver)
            continue
        # the largest step every decaying eigenvalue of the block allows, and which one
        # sets it (its fastest, in the solver's measure)
        limits = {lam: stable_step(tab, lam) for lam in np.unique(ev[decaying])}
        fastest = min(limits, key=limits.get)
        variant = int(np.flatnonzero((ev == fastest).any(axis=1))[0])
        raise ConfigError(_message(d, blk, fastest, limits[fastest], h, cfg.solver, variant,
                                   ev.shape[0]), file=_file(d, blk), line=_line(d, blk),
                          block=blk.name)


def _warn_unresolved(d, blk, ev, slow, gain, h, solver) -> None:
    """A decaying mode the step keeps stable but does not resolve: per step it shrinks by
    |R(h lambda)| instead of exp(h Re lambda), at less than half its true rate (rk4 from
    h*lambda = -2.06 on: 1/(p + 270) at h = 0.01 gives 0.275 after 0.1 s instead of
    1.9e-12).  A warning, not a refusal: the equilibrium is still exact (every consistent
    method keeps it), only the fast transient is wrong, which a lag much faster than its
    input may make harmless.  The step that resolves it: |R| <= exp(Re z / 2) up to it."""
    import warnings
    from fwdstep.core.errors import FwdstepWarning
    i = np.unravel_index(np.argmax(np.where(slow, np.abs(ev), -1.0)), ev.shape)
    lam = complex(ev[i])
    rate = -np.log(gain[i]) / h
    fine = _resolving_step(TABLEAUX[solver], lam, h)
    where = f"{_file(d, blk)}:{_line(d, blk)}: " if _line(d, blk) else f"{_file(d, blk)}: "
    warnings.warn(FwdstepWarning(
        f"{where}block '{blk.name}' ({blk.type_name}) has eigenvalue {_complex(lam)}: with "
        f"solver {solver} and step {h:g} (h*lambda = {_complex(h * lam)}) its mode decays "
        f"at {rate:.4g}/s instead of {-lam.real:.4g}/s, so its transients are wrong; a step "
        f"of at most {fine:.4g} resolves it (or use solver radau)"), stacklevel=2)


def _resolving_step(tab, lam: complex, h: float) -> float:
    """The largest step <= h at which the mode lam decays at least at half its rate."""
    lo, hi = 0.0, h
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        z = mid * lam
        if abs(complex(amplification(tab, z))) > np.exp(0.5 * z.real):
            hi = mid
        else:
            lo = mid
    return lo


def _message(d, blk, lam, h_max, h, solver, variant, rows) -> str:
    z = h * lam
    lam_text = f"{lam.real:.4g}" if lam.imag == 0 else f"{lam.real:.4g}{lam.imag:+.4g}j"
    where = ""
    if rows > 1 and d.batch > 1:
        where = f" (variant {variant}: {_variant_values(d, variant)})"
    return (f"block '{blk.name}' ({blk.type_name}) has eigenvalue {lam_text}{where}: with "
            f"solver {solver} and step {h:g}, h*lambda = {_complex(z)} is outside the "
            f"stability region (|R| = {abs(complex(amplification(TABLEAUX[solver], z))):.3g} "
            f"> 1: the mode would grow instead of decaying); the largest stable step is "
            f"{h_max:.4g}.  Use a smaller simulation.step, or solver radau, or set "
            f"simulation.stability_check: false to run anyway")


def _complex(z) -> str:
    z = complex(z)
    return f"{z.real:.4g}" if z.imag == 0 else f"{z.real:.4g}{z.imag:+.4g}j"


def _variant_values(d, variant: int) -> str:
    """The parameters that tell this variant of a batch from the others."""
    every = d.variant_parameters
    params = every[variant] if variant < len(every) else {}
    differ = [k for k in params if any(not _same(p.get(k), params[k]) for p in every)]
    return ", ".join(f"{k} = {_short(params[k])}" for k in differ[:4]) or "as given"


def _same(a, b) -> bool:
    try:
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    except (TypeError, ValueError):
        return a == b


def _short(value) -> str:
    text = np.array2string(np.asarray(value), precision=4, threshold=6) \
        if not isinstance(value, str) else value
    return text[:60]


def _entry(d, blk):
    return next((e for e in d.spec.blocks if e.name == blk.name), None)


def _file(d, blk):
    entry = _entry(d, blk)
    return entry.file if entry is not None and entry.file else d.spec.file


def _line(d, blk):
    entry = _entry(d, blk)
    return entry.line if entry is not None else None
