"""Figures from a Result, as named in the diagram's ``plots:`` section, in one house style.

Plotting lives here, in the runner's room, never in blocks.  Figures are
``matplotlib.figure.Figure`` objects on an Agg canvas: pyplot is never imported and the
caller's backend (a notebook's inline backend, say) is never switched.

Signals are named as a reader of the paper names them: ``signal_info`` takes the label, unit
and component names from the diagram's ``log:``/``plots:`` entries
(``{signal: e.y, label: "$\\Delta q$", unit: rad, components: [joint 1, joint 2]}``), else from
the block's declaration (a plant's ``q`` is "$q$" in rad per joint), else the signal's name.

The style functions (``new_figure``, ``line_colors``, ``place_legend``, ``finish_figure``,
``save_figure``) are shared by run, sweep and compare figures.
"""
from __future__ import annotations

import io
import os
import re
import textwrap
from dataclasses import dataclass

import numpy as np

from fwdstep.core.errors import OutputError
from fwdstep.core.files import atomic_write, safe_path

FORMATS = ("png", "pdf", "svg")
WIDTH = 8.0          # inches; a figure fits a page or a slide at 100%
PANEL_HEIGHT = 2.6
DPI = 120
MAX_LEGEND_ROWS = 16
MAX_LEGEND_ENTRIES = 12   # more lines than this: a legend of colours and styles, or a colour bar


@dataclass(frozen=True)
class SignalInfo:
    """How figures name one signal: ``label`` (mathtext allowed), ``unit``, ``components``."""
    name: str
    label: str
    unit: str = ""
    components: tuple = ()

    def axis_label(self, absolute: bool = False) -> str:
        text = f"|{self.label}|" if absolute else self.label
        return f"{text} [{self.unit}]" if self.unit else text

    def component(self, index: tuple, shape: tuple) -> str:
        """The name of element ``index`` of a signal of ``shape`` (1-based like the paper)."""
        flat = int(np.ravel_multi_index(index, shape)) if shape else 0
        if len(self.components) == int(np.prod(shape, dtype=int)) and self.components:
            return str(self.components[flat])
        return subscript(self.label, ",".join(str(i + 1) for i in index))


def subscript(label: str, sub: str) -> str:
    """``label`` with a subscript: '$\\hat\\theta$' -> '$\\hat\\theta_{1}$', 'e.y' -> 'e.y$_{1}$'."""
    if not sub:
        return label
    if label.startswith("$") and label.endswith("$") and label.count("$") == 2:
        return f"${{{label[1:-1]}}}_{{{sub}}}$"
    return f"{label}$_{{{sub}}}$"


def literal_mathtext(fig) -> None:
    """Replace, in every Text artist of ``fig``, a text matplotlib's mathtext parser refuses
    by the same text with its dollar signs escaped (shown as written)."""
    from matplotlib.text import Text
    for artist in fig.findobj(Text):
        text = artist.get_text()
        if isinstance(text, str) and text.count("$") >= 2:
            fixed = safe_label(text)
            if fixed is not text:
                artist.set_text(fixed)


def safe_label(label: str) -> str:
    """``label`` if matplotlib can typeset it, else the same text with the dollar signs of
    each math part it cannot typeset escaped, so that part shows literally (a typo in a
    diagram's mathtext must not stop the figures); ``label`` itself when nothing changes."""
    if "\n" in label:                       # matplotlib typesets each line on its own
        lines = label.split("\n")
        fixed = [safe_label(line) for line in lines]
        return label if all(a is b for a, b in zip(fixed, lines)) else "\n".join(fixed)
    pieces = re.split(r"(?<!\\)\$", label)
    if len(pieces) < 3 or len(pieces) % 2 == 0:          # plain text for matplotlib
        return label
    from matplotlib.mathtext import MathTextParser
    parser = MathTextParser("path")

    def typesets(text: str) -> bool:
        try:
            parser.parse(text)
            return True
        except ValueError:
            return False

    if typesets(label):
        return label
    out = pieces[0]
    for math, after in zip(pieces[1::2], pieces[2::2]):
        out += (f"${math}$" if typesets(f"${math}$") else f"\\${math}\\$") + after
    return out if typesets(out) else label.replace("$", r"\$")


def signal_info(source, name: str, typeset: bool = True) -> SignalInfo:
    """Label, unit and component names of signal ``name`` of a Result or CompiledDiagram.
    ``typeset=False`` keeps the label as written (no mathtext check, which imports
    matplotlib): for what is saved, checked again when a figure is drawn."""
    diagram = getattr(source, "diagram", source)
    meta = {"label": None, "unit": "", "components": None}
    stored = getattr(source, "signal_labels", None) or {}
    if diagram is not None and hasattr(diagram, "spec"):
        real = diagram.resolve(name)
        blk_name, _, port = real.rpartition(".")
        for blk in diagram.blocks:
            if blk.name == blk_name:
                meta.update({k: v for k, v in getattr(blk, "output_info", {}).get(port, {}).items()
                             if v})
                break
        info = diagram.spec.signal_info
        for key in (real, name):
            meta.update({k: v for k, v in info.get(key, {}).items() if v})
    else:
        real = (getattr(source, "aliases", None) or {}).get(name, name)
        meta.update({k: v for k, v in stored.get(real, stored.get(name, {})).items() if v})
    label = meta["label"] or name
    return SignalInfo(name, safe_label(label) if typeset else label, meta["unit"] or "",
                      tuple(meta["components"] or ()))


class _SpecView:
    """A loaded spec and its built blocks, seen as ``signal_info`` sees a compiled diagram."""

    def __init__(self, spec, blocks):
        self.spec, self.blocks = spec, blocks

    def resolve(self, name: str) -> str:
        return self.spec.aliases.get(name, name)


def signal_record(spec, blocks, name: str) -> dict:
    """What a saved sweep keeps of signal ``name`` so that figures and ``fwdstep compare``
    name it as a run does: its name, the block port it resolves to, label, unit, components."""
    info = signal_info(_SpecView(spec, blocks), name, typeset=False)
    return {"name": name, "real": spec.aliases.get(name, name), "label": info.label,
            "unit": info.unit, "components": list(info.components) or None}


def signal_labels(result: Result) -> dict:
    """Every recorded signal's label/unit/components, as stored with a saved result."""
    out = {}
    for name in result.names:
        info = signal_info(result, name, typeset=False)
        out[name] = {"label": info.label, "unit": info.unit,
                     "components": list(info.components) or None}
    return out


# ---------------------------------------------------------------------------- style
def new_figure(n_panels: int = 1, sharex: bool = True, height: float | None = None):
    """A Figure (Agg canvas, constrained layout) and its column of axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(WIDTH, height or PANEL_HEIGHT * n_panels + 0.9), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n_panels, 1, sharex=sharex, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, alpha=0.3, which="major")
        ax.tick_params(labelsize=8)
    return fig, list(axes)


def line_colors(n: int) -> list:
    """n distinct colours: the default cycle up to 10, tab20 up to 20, then viridis."""
    from matplotlib import colormaps
    if n <= 10:
        return [f"C{i}" for i in range(n)]
    if n <= 20:
        return [colormaps["tab20"](i) for i in range(n)]
    return [colormaps["viridis"](x) for x in np.linspace(0, 0.95, n)]


@dataclass(frozen=True)
class LineKey:
    """What colour and line style mean in one panel, for a legend that stays short.

    Lines are coloured by one thing (a signal's component, a variant of a batch, a run) and
    styled by another (the signal): ``colors``/``color_names`` and ``styles``/``style_names``
    pair each colour and style with its meaning.  ``color_kind`` names what the colours
    stand for ("component", "variant", "run"); ``color_values`` is what the colour bar shows
    for each colour (default 1 ... n)."""
    colors: tuple
    color_names: tuple
    color_kind: str = "component"
    styles: tuple = ("-",)
    style_names: tuple = ("",)
    color_values: tuple = ()


def _unique_entries(ax) -> tuple:
    """The panel's legend handles and labels, each label once (its first line)."""
    handles, labels = ax.get_legend_handles_labels()
    seen, out_h, out_l = set(), [], []
    for h, lab in zip(handles, labels):
        if lab not in seen:
            seen.add(lab)
            out_h.append(h)
            out_l.append(lab)
    return out_h, out_l


def place_legend(ax, title: str | None = None, key: LineKey | None = None) -> None:
    """A legend of at most ``MAX_LEGEND_ENTRIES`` entries, never one that crowds the axes.

    Up to that many labelled lines, one entry per line (inside the panel when few, beside it
    when more).  Beyond, with a ``key``: one entry per colour and one per line style, and when
    the colours alone are too many, a colour bar of them (by index) instead of their entries.
    Without a key the first entries are listed and the last says how many are not."""
    handles, labels = _unique_entries(ax)
    if len(handles) > MAX_LEGEND_ENTRIES and key is not None:
        handles, labels, bar = _key_entries(ax, key)
        if bar is not None:          # only the line styles are left: one row above the panel
            if handles:
                ax.legend(handles, labels, fontsize=7, loc="lower right", ncol=len(handles),
                          bbox_to_anchor=(1.0, 1.0), borderaxespad=0.2, frameon=False,
                          handlelength=2.5, title=title, title_fontsize=7)
            return
        title = title if title is not None else key.color_kind
    elif len(handles) > MAX_LEGEND_ENTRIES:
        from matplotlib.lines import Line2D
        more = len(handles) - MAX_LEGEND_ENTRIES + 1
        handles = handles[:MAX_LEGEND_ENTRIES - 1] + [Line2D([], [], lw=0)]
        labels = labels[:MAX_LEGEND_ENTRIES - 1] + [f"… {more} more not listed"]
    if not handles:
        return
    if len(handles) <= 6:
        ax.legend(handles, labels, fontsize=7, loc="best", ncol=2 if len(handles) > 3 else 1,
                  title=title, title_fontsize=7)
    else:
        ncol = -(-len(handles) // MAX_LEGEND_ROWS)
        ax.legend(handles, labels, fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  ncol=ncol, borderaxespad=0, title=title, title_fontsize=6)


def _key_entries(ax, key: LineKey) -> tuple:
    """Legend entries for a key: the colours if they fit beside the line styles (listed when
    more than one), else a colour bar of the colours on the panel (returned, else None)."""
    from matplotlib.lines import Line2D
    handles, labels, bar = [], [], None
    n_styles = len(key.styles) if len(key.styles) > 1 else 0
    if len(key.colors) + n_styles <= MAX_LEGEND_ENTRIES:
        handles += [Line2D([], [], color=c, lw=1.1) for c in key.colors]
        labels += [str(n) for n in key.color_names]
    else:
        bar = color_bar(ax, key)
    if n_styles:
        handles += [Line2D([], [], color="0.25", lw=1.1, ls=s) for s in key.styles]
        labels += [str(n) for n in key.style_names]
    return handles, labels, bar


def color_bar(ax, key: LineKey):
    """A discrete colour bar beside ``ax``: one band per colour of ``key``, integer ticks."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.ticker import MaxNLocator
    n = len(key.colors)
    values = list(key.color_values) or list(range(1, n + 1))
    mappable = ScalarMappable(BoundaryNorm(np.arange(n + 1) - 0.5, n), ListedColormap(key.colors))
    bar = ax.figure.colorbar(mappable, ax=ax, pad=0.01, fraction=0.05, aspect=20)
    at = {v: k for k, v in enumerate(values)}          # a value's band
    ticks = [at[int(v)] for v in MaxNLocator(nbins=8, steps=[1, 2, 5, 10], integer=True).tick_values(
        min(values), max(values)) if int(v) == v and int(v) in at]
    ticks = sorted({0, *ticks})                          # the first band is always named
    bar.set_ticks(ticks, labels=[str(values[t]) for t in ticks])
    bar.ax.tick_params(labelsize=7)
    bar.ax.minorticks_off()
    bar.set_label(f"{key.color_kind} ({n})", fontsize=8)
    return bar


def time_axis(ax, t: np.ndarray) -> None:
    """x from t0 to t_end with a small margin, so the t = 0 transient is not under the spine."""
    if len(t) == 0:
        return
    span = float(t[-1] - t[0]) or 1.0
    ax.set_xlim(float(t[0]) - 0.012 * span, float(t[-1]) + 0.012 * span)


def headline(description: str, width: int = 100, max_lines: int = 3) -> str:
    """The first sentence of the description's first paragraph, wrapped at words into at most
    ``max_lines`` lines (a longer sentence ends at its last clause that fits, then '…')."""
    lines = []
    for ln in (description or "").strip("\n").splitlines():
        if not ln.strip() or (lines and len(ln) - len(ln.lstrip()) > 0):
            break                     # a blank line or an indented (displayed) line ends it
        lines.append(ln.strip())
    text = " ".join(lines)
    text = re.split(r"(?<=[.!?])\s+(?=[A-Z])", text, maxsplit=1)[0]
    text = text.rstrip(",;:")         # it introduced the displayed lines that were cut
    wrapped = textwrap.wrap(text, width)
    if len(wrapped) > max_lines:
        clauses = re.split(r"(?<=[,;:])\s+", text)
        keep = clauses[0]
        for clause in clauses[1:]:
            if len(textwrap.wrap(f"{keep} {clause} …", width)) > max_lines:
                break
            keep = f"{keep} {clause}"
        wrapped = textwrap.wrap(keep.rstrip(",;:") + " …", width)
    return "\n".join(wrapped)


def finish_figure(fig, title: str, subtitle: str = "") -> None:
    fig.suptitle(title + (f"\n{subtitle}" if subtitle else ""), fontsize=9.5, ha="center")


def figure_bytes(fig, fmt: str = "png") -> bytes:
    """The figure drawn as ``fmt``.  Every figure fwdstep writes passes here, so here every
    text of it (titles, axis labels, legends) whose mathtext matplotlib cannot typeset is
    shown literally instead (``literal_mathtext``): a typo the load-time check cannot see
    (an unknown ``\\command``) costs its dollar signs, never the figure or the run."""
    literal_mathtext(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=DPI, metadata={"Software": "fwdstep"} if fmt == "png"
                else None)
    return buf.getvalue()


def save_figure(fig, outdir: str, name: str, formats=("png",)) -> list:
    """Write ``name.<fmt>`` for each format into ``outdir`` (created if missing); the paths.

    Commands pass the staging directory of a ``fwdstep.results.outputs.OutputDir`` (``out.dir``) as
    ``outdir`` and commit it afterwards: that is what keeps figures from replacing files
    fwdstep did not write, or being written through symbolic links, in the user's directory.
    """
    formats = check_formats(formats)
    try:
        os.makedirs(outdir, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the output directory {outdir}: "
                          f"{exc.strerror or exc}") from exc
    paths = []
    for fmt in formats:
        data = figure_bytes(fig, fmt)
        path = safe_path(outdir, f"{name}.{fmt}")
        atomic_write(path, lambda fh, data=data: fh.write(data), binary=True)
        paths.append(path)
    return paths


def check_formats(formats) -> tuple:
    formats = tuple(formats or ("png",))
    for fmt in formats:
        if fmt not in FORMATS:
            raise OutputError(f"figure format '{fmt}' is not supported; formats are: "
                              f"{', '.join(FORMATS)}")
    return formats


def pretty(name: str) -> str:
    """'tracking_error' -> 'Tracking error'."""
    text = name.replace("_", " ").replace("-", " ").strip()
    return text[:1].upper() + text[1:]


# ---------------------------------------------------------------------------- run figures
def figure_specs(result: Result) -> dict:
    """figure name -> list of (signals, scale) panels."""
    if result.diagram is None:                       # a loaded result: as saved
        return dict(getattr(result, "figure_panels", {}) or {})
    spec = result.diagram.spec
    if spec.plots:
        return {name: list(zip(panels, spec.plot_scales.get(name, ["linear"] * len(panels))))
                for name, panels in spec.plots.items()}
    if "error" in spec.metrics:
        err = spec.metrics["error"]
        return {"tracking_error": [([err], "linear"), ([err], "log")]}
    return {}


def result_figures(result: Result, variants: list | None = None, names=None) -> dict:
    """figure name -> Figure, for the figures the diagram names (or ``names`` of them)."""
    figs = figure_specs(result)
    if names is not None:
        unknown = [n for n in names if n not in figs]
        if unknown:
            raise KeyError(f"no figure '{unknown[0]}'; figures are: {', '.join(figs) or '(none)'}")
        figs = {n: figs[n] for n in names}
    if len(result.t) == 0:
        return {}
    subtitle = (headline(result.diagram.spec.description) if result.diagram is not None
                else getattr(result, "title", ""))
    return {name: panel_figure(result, panels, pretty(name), subtitle, variants)
            for name, panels in figs.items()}


def panel_figure(result: Result, panels: list, title: str = "", subtitle: str = "",
                 variants: list | None = None):
    """One Figure, one panel per (signals, scale)."""
    fig, axes = new_figure(len(panels))
    for ax, (panel, scale) in zip(axes, panels):
        infos = [signal_info(result, s) for s in panel]
        log = scale == "log"
        key = draw_panel(ax, result, infos, variants, log=log)
        if log:
            ax.set_yscale("log")
        absolute = log or result.batch > 1          # what is drawn: |component| or |signal|
        units = {i.unit for i in infos}
        if len(infos) == 1:
            ylabel = infos[0].axis_label(absolute)
        else:
            names = ", ".join(f"|{i.label}|" if absolute else i.label for i in infos)
            ylabel = names + (f" [{units.pop()}]" if len(units) == 1 and "" not in units else "")
        ax.set_ylabel(ylabel if len(ylabel) <= 45 else textwrap.fill(ylabel, 30), fontsize=9)
        time_axis(ax, result.t)
        place_legend(ax, key=key)
    axes[-1].set_xlabel("$t$ [s]", fontsize=9)
    finish_figure(fig, title, subtitle)
    return fig


_STYLES = ("-", "--", ":", "-.")


def draw_panel(ax, result: Result, infos: list, variants=None, log: bool = False) -> LineKey:
    """Draw every component of every signal (|component| on a log panel); for a batch, |signal|
    of every chosen variant.  Component i has one colour whatever the signal, each signal its
    own line style, so an estimate and its true value share a colour.  Every line is labelled;
    the returned key says what colours and styles mean, for ``place_legend`` when the lines
    are too many to list."""
    t = result.t
    styles = tuple(_STYLES[k % 4] for k in range(len(infos)))
    style_names = tuple(f"|{i.label}|" if log or result.batch > 1 else i.label for i in infos)
    if result.batch == 1:
        shapes = [result[i.name].shape[1:] for i in infos]
        widest = max(range(len(infos)), key=lambda k: int(np.prod(shapes[k], dtype=int)))
        colors = line_colors(int(np.prod(shapes[widest], dtype=int)))
        for k, info in enumerate(infos):
            data = result[info.name]
            shape = data.shape[1:]
            flat = data.reshape(len(t), -1)
            for j in range(flat.shape[1]):
                name = info.label if not shape else info.component(
                    np.unravel_index(j, shape), shape)
                if len(infos) > 1 and shape and info.components:
                    name = f"{info.label}: {name}"
                y = np.abs(flat[:, j]) if log else flat[:, j]
                ax.plot(t, y, lw=1.1, ls=styles[k], color=colors[j],
                        label=f"|{name}|" if log and not info.components else name)
        info, shape = infos[widest], shapes[widest]
        names = tuple(info.components) if len(info.components) == len(colors) else \
            tuple(str(j + 1) for j in range(len(colors)))
        return LineKey(tuple(colors), names, "component", styles, style_names)
    chosen = list(variants) if variants is not None else list(range(result.batch))
    colors = line_colors(len(chosen))
    names = variant_names(result)
    for k, info in enumerate(infos):
        data = result[info.name]
        for c, b in enumerate(chosen):
            flat = data[:, b].reshape(len(t), -1)
            norm = np.sqrt(np.sum(flat ** 2, axis=1))
            ax.plot(t, norm, lw=1.0, ls=styles[k], color=colors[c],
                    label=(f"{info.label}: " if len(infos) > 1 else "") + names[b])
    return LineKey(tuple(colors), tuple(names[b] for b in chosen), "variant", styles,
                   style_names, tuple(chosen))


def variant_names(result: Result) -> list:
    """'alpha = 3, K = 20' per variant of a batch: the parameters that differ between them."""
    params = getattr(result.diagram, "variant_parameters", None) or []
    if len(params) != result.batch:
        return [f"variant {b}" for b in range(result.batch)]
    keys = [k for k in params[0]
            if any(_differ(p.get(k), params[0].get(k)) for p in params[1:])]
    if not keys:
        return [f"variant {b}" for b in range(result.batch)]
    return [", ".join(f"{k} = {_short(p.get(k))}" for k in keys[:3]) for p in params]


def _differ(a, b) -> bool:
    try:
        return not np.array_equal(np.asarray(a), np.asarray(b))
    except (TypeError, ValueError):
        return a != b


def _short(value) -> str:
    arr = np.asarray(value)
    if arr.ndim == 0:
        return f"{float(arr):g}" if np.issubdtype(arr.dtype, np.number) else str(value)
    text = np.array2string(arr, precision=3, separator=", ")
    return text if len(text) <= 30 else text[:28] + "…"


def plot_result(result: Result, outdir: str, variants: list | None = None,
                formats=("png",)) -> list:
    """Write each figure of the diagram into ``outdir`` (created if missing) as
    ``name.png`` (and/or .pdf, .svg); returns the paths written."""
    formats = check_formats(formats)
    paths = []
    for name, fig in result_figures(result, variants).items():
        paths += save_figure(fig, outdir, name, formats)
    return paths
