"""``fwdstep linearize``: the linear model of a diagram written to a directory.

    fwdstep linearize D --input SIG --output SIG [--at T] [--open SIG] [--along N]
                        [--set NAME=VALUE] -o DIR

writes ``linear.json`` (A, B, C, D, state/input/output names, the state, poles, zeros, the
margins of a SISO loop, how each block was differentiated), ``linear.npz`` (the same
arrays), ``bode.png`` (gain and phase of every input-output pair, the margins marked on a
SISO loop) and, with ``--along N``, ``poles_over_time.png`` and ``poles_over_time.npz``
(frozen-time poles at N times of one run).  The work is ``fwdstep.linearize``'s; figures are
matplotlib ``Figure`` objects on an Agg canvas (no pyplot), as in ``fwdstep.results.plotting``.
"""
from __future__ import annotations

import json
import os

import numpy as np

from fwdstep.core.errors import OutputError

FILES = ("linear.json", "linear.npz", "bode.png")
ALONG_FILES = ("poles_over_time.png", "poles_over_time.npz")


def _figure(rows: int, width: float = 7.0, height: float = 2.6):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width, height * rows), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, [fig.add_subplot(rows, 1, k + 1) for k in range(rows)]


def bode_figure(model, w=None, margins: dict | None = None, title: str = ""):
    """Gain (dB) and phase (deg) of every input-output pair of ``model`` against the
    angular frequency; with ``margins`` (a SISO loop) the crossovers and margins marked on
    the loop gain L = sign G."""
    w = model.frequency_grid(1000) if w is None else np.asarray(w, dtype=float)
    H = model.frequency_response(w)
    sign = margins["sign"] if margins else 1.0
    fig, (ax_mag, ax_ph) = _figure(2)
    for i, out in enumerate(model.output_names):
        for j, inp in enumerate(model.input_names):
            h = sign * H[:, i, j]
            label = f"{inp} -> {out}" if not margins else (
                f"L = {'-' if sign < 0 else ''}G, G: {inp} -> {out} (opened)")
            with np.errstate(divide="ignore"):
                ax_mag.semilogx(w, 20 * np.log10(np.abs(h)), label=label)
            phase = np.degrees(np.unwrap(np.angle(h)))
            phase -= 360.0 * np.round(phase[0] / 360.0)      # start in [-180, 180]
            ax_ph.semilogx(w, phase, label=label)
    ax_mag.set_ylabel("gain (dB)")
    ax_ph.set_ylabel("phase (deg)")
    ax_ph.set_xlabel(r"$\omega$ (rad/s)")
    ax_mag.axhline(0.0, color="0.6", lw=0.8)
    if margins:
        gm, pm = margins["gain_margin_db"], margins["phase_margin_deg"]
        wg, wp = margins["gain_crossover"], margins["phase_crossover"]
        if np.isfinite(wg):
            ax_mag.axvline(wg, color="tab:green", ls="--", lw=0.8)
            ax_ph.axvline(wg, color="tab:green", ls="--", lw=0.8)
        if np.isfinite(wp):
            ax_mag.axvline(wp, color="tab:red", ls="--", lw=0.8)
            ax_ph.axvline(wp, color="tab:red", ls="--", lw=0.8)
        text = (f"gain margin {gm:.3g} dB at {wp:.3g} rad/s" if np.isfinite(gm)
                else "gain margin: infinite (no -180 deg crossing)")
        text += "\n" + (f"phase margin {pm:.3g} deg at {wg:.3g} rad/s" if np.isfinite(pm)
                        else "phase margin: infinite (|L| never crosses 1)")
        ax_mag.text(0.02, 0.04, text, transform=ax_mag.transAxes, fontsize=8,
                    bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"})
    ax_mag.legend(fontsize=7, loc="upper right")
    ax_mag.grid(True, which="both", lw=0.3)
    ax_ph.grid(True, which="both", lw=0.3)
    ax_mag.set_title(title or f"linearised at t = {model.t:g} s", fontsize=9)
    return fig


def poles_figure(models, title: str = ""):
    """Real parts of the poles against time (top) and the pole map coloured by time
    (bottom), for frozen-time linearisations along a run."""
    times = np.array([m.t for m in models])
    poles = [np.sort_complex(m.poles()) for m in models]
    fig, (ax_re, ax_map) = _figure(2, height=3.0)
    for t, p in zip(times, poles):
        ax_re.plot(np.full(p.shape, t), p.real, ".", color="tab:blue", ms=3)
    ax_re.set_xlabel("t (s)")
    ax_re.set_ylabel("Re(pole)")
    ax_re.set_yscale("symlog", linthresh=1.0)
    ax_re.axhline(0.0, color="0.5", lw=0.8)
    ax_re.grid(True, lw=0.3)
    allp = np.concatenate(poles) if poles else np.zeros(0)
    colours = np.concatenate([np.full(p.shape, t) for t, p in zip(times, poles)]) \
        if poles else np.zeros(0)
    sc = ax_map.scatter(allp.real, allp.imag, c=colours, s=8, cmap="viridis")
    fig.colorbar(sc, ax=ax_map, label="t (s)")
    ax_map.set_xscale("symlog", linthresh=1.0)
    ax_map.axvline(0.0, color="0.5", lw=0.8)
    ax_map.set_xlabel("Re(pole)")
    ax_map.set_ylabel("Im(pole)")
    ax_map.grid(True, lw=0.3)
    ax_re.set_title(title or f"frozen-time poles at {len(models)} times", fontsize=9)
    return fig


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if np.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    if isinstance(v, np.integer):
        return int(v)
    return v


def write_linear(model, outdir: str, margins=None, title: str = "") -> list:
    """linear.json, linear.npz and bode.png of ``model`` into ``outdir``."""
    data = model.to_dict()
    data["margins"] = margins
    path = os.path.join(outdir, "linear.json")
    with open(path, "w") as f:
        json.dump(_jsonable(data), f, indent=1)
    zeros = data["zeros"]
    np.savez(os.path.join(outdir, "linear.npz"), A=model.A, B=model.B, C=model.C, D=model.D,
             x=np.asarray(model.x), t=model.t, poles=model.poles(),
             zeros=np.zeros(0, complex) if zeros is None else model.zeros(),
             states=np.array(model.state_names), inputs=np.array(model.input_names),
             outputs=np.array(model.output_names))
    fig = bode_figure(model, margins=margins, title=title)
    fig.savefig(os.path.join(outdir, "bode.png"), dpi=120)
    return [path, os.path.join(outdir, "linear.npz"), os.path.join(outdir, "bode.png")]


def write_along(models, outdir: str, title: str = "") -> list:
    fig = poles_figure(models, title)
    png = os.path.join(outdir, "poles_over_time.png")
    fig.savefig(png, dpi=120)
    n = max(len(m.poles()) for m in models)
    P = np.full((len(models), n), np.nan, dtype=complex)
    for k, m in enumerate(models):
        p = np.sort_complex(m.poles())
        P[k, :len(p)] = p
    npz = os.path.join(outdir, "poles_over_time.npz")
    np.savez(npz, t=np.array([m.t for m in models]), poles=P)
    return [png, npz]
