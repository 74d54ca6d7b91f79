"""Figures from a Result, as named in the diagram's ``plots:`` section.

Plotting lives here, in the runner's room, never in blocks.  matplotlib is imported lazily
(with the Agg backend) so loading and validating diagrams stays fast and headless.
"""
from __future__ import annotations

import io
import textwrap

import numpy as np

from .result import Result, atomic_write, safe_path


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def figure_specs(result: Result) -> dict:
    """figure name -> list of (signals, scale) panels."""
    spec = result.diagram.spec
    if spec.plots:
        return {name: list(zip(panels, spec.plot_scales.get(name, ["linear"] * len(panels))))
                for name, panels in spec.plots.items()}
    if "error" in spec.metrics:
        err = spec.metrics["error"]
        return {"tracking_error": [([err], "linear"), ([err], "log")]}
    return {}


def plot_result(result: Result, outdir: str, variants: list | None = None) -> list:
    """Write one PNG per figure into ``outdir``; returns the paths written."""
    figs = figure_specs(result)
    if not figs or len(result.t) == 0:
        return []
    plt = _pyplot()
    paths = []
    for name, panels in figs.items():
        fig, axes = plt.subplots(len(panels), 1, figsize=(8, 2.6 * len(panels) + 0.6),
                                 sharex=True, squeeze=False)
        for ax, (panel, scale) in zip(axes[:, 0], panels):
            for k, sig in enumerate(panel):
                _draw(ax, result, sig, variants, log=scale == "log", style=_STYLES[k % 4])
            if scale == "log":
                ax.set_yscale("log")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7, loc="best", ncol=2)
            ax.set_ylabel(", ".join(panel) if len(", ".join(panel)) < 40 else panel[0])
        axes[-1, 0].set_xlabel("t [s]")
        title = result.diagram.spec.description.strip().splitlines()
        axes[-1, 0].set_xlim(result.t[0], result.t[-1])
        headline = textwrap.shorten(title[0], 90, placeholder=" ...") if title else ""
        fig.suptitle(f"{name}" + (f" — {headline}" if headline else ""), fontsize=10)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110)
        plt.close(fig)
        path = safe_path(outdir, f"{name}.png")
        atomic_write(path, lambda fh: fh.write(buf.getvalue()), binary=True)
        paths.append(path)
    return paths


_STYLES = ("-", "--", ":", "-.")


def _draw(ax, result: Result, sig: str, variants, log: bool = False, style: str = "-"):
    """One line per component (|component| on a log panel); per variant |signal| for a batch.

    Component i has colour Ci whatever the signal, and each signal of a panel its own line
    style, so an estimate and its true value (theta_hat[2], theta[2]) share a colour."""
    data = result[sig]
    t = result.t
    if result.batch == 1:
        flat = data.reshape(len(t), -1)
        for i in range(flat.shape[1]):
            label = sig if flat.shape[1] == 1 else f"{sig}[{_index(data.shape[1:], i)}]"
            ax.plot(t, np.abs(flat[:, i]) if log else flat[:, i], lw=1.0, ls=style,
                    color=f"C{i % 10}", label=f"|{label}|" if log else label)
    else:
        chosen = variants if variants is not None else range(min(result.batch, 8))
        for b in chosen:
            flat = data[:, b].reshape(len(t), -1)
            norm = np.sqrt(np.sum(flat ** 2, axis=1))
            ax.plot(t, norm, lw=1.0, ls=style, color=f"C{b % 10}",
                    label=f"|{sig}| variant {b}")


def _index(shape, flat_index):
    idx = np.unravel_index(flat_index, shape)
    return ",".join(str(int(i)) for i in idx)
