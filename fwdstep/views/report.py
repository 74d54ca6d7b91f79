"""Self-contained HTML: a Result's notebook summary and the ``fwdstep report`` page."""
from __future__ import annotations

import html
import os

import numpy as np


# ---------------------------------------------------------------------------- the report page
REPORT_FILE = "report.html"
_MARK = "written by fwdstep report"

_CSS = """
body{font-family:Helvetica,Arial,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{font-size:1.5em;margin-bottom:.2em} h2{font-size:1.15em;border-bottom:1px solid #ccc;
margin-top:1.6em} table{border-collapse:collapse;font-size:.85em;margin:.4em 0}
td,th{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top}
th{background:#f4f6f7} .num{text-align:right;font-family:monospace}
.ok{color:#1e8449;font-weight:bold} .bad{color:#c0392b;font-weight:bold}
figure{margin:1em 0} figcaption{font-size:.85em;color:#555}
img{max-width:100%;height:auto;box-sizing:border-box;border:1px solid #eee}
.diagram img{cursor:zoom-in}

pre{background:#f8f9f9;padding:.6em;white-space:pre-wrap;font-size:.85em}
"""


# opens an inlined picture in a new tab: browsers refuse to navigate to a data: URL, so the
# picture is handed over as a blob (the page stays one self-contained file)
_OPEN_SCRIPT = """<script>function fwdstepOpen(img){var p=img.src.split(",");
var mime=p[0].slice(5).split(";")[0],bin=atob(p[1]),buf=new Uint8Array(bin.length);
for(var i=0;i<bin.length;i++)buf[i]=bin.charCodeAt(i);
window.open(URL.createObjectURL(new Blob([buf],{type:mime})),"_blank");}</script>"""


def _img(data: bytes, mime: str, alt: str) -> str:
    import base64
    return (f'<img alt="{html.escape(alt)}" src="data:{mime};base64,'
            f'{base64.b64encode(data).decode("ascii")}">')


def _value(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        text = "[" + ", ".join(_value(x) for x in v) + "]"
        return text if len(text) <= 300 else text[:300] + " …"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_value(x)}" for k, x in v.items()) + "}"
    text = "" if v is None else str(v)
    return text if len(text) <= 300 else text[:300] + " …"     # a matrix value's text


def _table(rows: list, columns: list | None = None) -> str:
    if not rows:
        return "<p>(none)</p>"
    columns = columns or list(dict.fromkeys(c for r in rows for c in r))
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in columns)
    body = []
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c)
            cls = ' class="num"' if isinstance(v, (int, float)) and not isinstance(v, bool) else ""
            cells.append(f"<td{cls}>{html.escape(_value(v))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _pairs(d: dict) -> str:
    return _table([{"name": k, "value": v} for k, v in (d or {}).items()], ["name", "value"])


def _diagram_section(summary: dict, run_dir: str | None = None) -> list:
    """The "Diagram" heading, the picture of the run's diagram and any note about it."""
    svg, note = diagram_picture(summary, run_dir)
    out = ["<h2>Diagram</h2>"]
    if svg is not None:         # the whole picture at the page's width; a click opens it
        picture = _img(svg, "image/svg+xml", "block diagram").replace(
            "<img ", '<img title="open the picture at full size" '
                     'onclick="fwdstepOpen(this)" ', 1)
        out.append(f'<figure class="diagram">{picture}<figcaption>click the picture to open '
                   f'it at full size</figcaption></figure>{_OPEN_SCRIPT}')
    if note:
        out.append(f"<p>{html.escape(note)}</p>")
    return out


def recorded_diagram(summary: dict, run_dir: str | None):
    """The run's diagram as it was run (``fwdstep.results.provenance.recorded_diagram``)."""
    from fwdstep.results.provenance import recorded_diagram as recorded
    return recorded(summary, run_dir)


def diagram_picture(summary: dict, run_dir: str | None = None) -> tuple:
    """(SVG bytes or None, note) of the run's diagram, with the parameters as run."""
    import shutil
    from fwdstep.views.drawing import diagram_dot, layered_bytes, picture_for, render_dot
    from fwdstep.core.errors import FwdstepError
    try:
        d = recorded_diagram(summary, run_dir)
    except FileNotFoundError as exc:
        return None, str(exc)
    except FwdstepError as exc:
        return None, f"no picture: {exc}"
    try:
        if shutil.which("dot"):
            return render_dot(diagram_dot(picture_for(d)), "svg"), ""
        nested = any("/" in b.name for b in d.blocks)     # as fwdstep graph's fallback
        return (layered_bytes(picture_for(d, 0 if nested else None), "svg"),
                "drawn without graphviz (install graphviz for a better layout)"
                + ("; subsystems as boxes" if nested else ""))
    except FwdstepError as exc:
        return None, f"no picture: {exc}"


def _parameters_section(s: dict) -> list:
    """What the run was made of: the command-line values as typed, the diagram's parameters
    and every simulation setting as run, and each block's parameters as evaluated."""
    prov = s.get("provenance") if isinstance(s.get("provenance"), dict) else {}
    out = ["<h2>Parameters as run</h2>"]
    sets = prov.get("sets")
    if sets:
        out.append("<p>Set on the command line: " + ", ".join(
            f"<code>{html.escape(str(x))}</code>" for x in sets) + "</p>")
    elif prov.get("overrides"):
        out.append("<p>Overrides: " + html.escape(_value(prov["overrides"])) + "</p>")
    params = s.get("parameters")
    out.append("<h3>Diagram parameters</h3>")
    unused = set(s.get("unused_parameters") or [])
    if isinstance(params, list):
        out.append(_table(params))
    elif unused:
        out.append(_table([{"name": k, "value": v,
                            "note": "not used in this run (its uses were replaced by --set)"
                            if k in unused else ""} for k, v in (params or {}).items()],
                          ["name", "value", "note"]))
    else:
        out.append(_pairs(params or {}))
    out.append("<h3>Simulation settings</h3>" + _pairs(s.get("simulation") or {}))
    blocks = s.get("blocks")
    if blocks:
        set_paths = {str(x).split("=", 1)[0].strip() for x in sets or []}
        rows = []
        for name, values in blocks.items():
            dotted = name.replace("/", ".")
            for key, v in values.items():
                if key == "type":
                    continue
                rows.append({"block": name, "type": values.get("type"), "parameter": key,
                             "value": v, "set": "--set" if f"{dotted}.{key}" in set_paths
                             else ""})
        out.append("<h3>Block parameters</h3>")
        overridden = [r for r in rows if r["set"]]
        if overridden:
            out.append(_table(overridden, ["block", "parameter", "value", "set"]))
        out.append(f"<details><summary>every block ({len(blocks)})</summary>"
                   f"{_table(rows, ['block', 'type', 'parameter', 'value', 'set'])}</details>")
    if prov:
        facts = {k: prov.get(k) for k in ("fwdstep_version", "source_commit", "backend",
                                          "python", "numpy", "started", "diagram_source",
                                          "rerun_of") if prov.get(k)}
        if prov.get("command"):
            facts["command"] = " ".join(prov["command"])
        for entry in prov.get("plugins") or []:
            facts[f"plugin {entry.get('file')}"] = f"SHA-256 {entry.get('sha256')}"
        out.append("<h3>Provenance</h3>" + _pairs(facts))
        files = prov.get("files") or []
        if files:
            out.append(_table([{"copy": f.get("copy"), "kind": f.get("kind"),
                                "original": f.get("source"), "SHA-256": f.get("sha256")}
                               for f in files], ["copy", "kind", "original", "SHA-256"]))
    return out


def report_html(run_dir: str) -> str:
    """The self-contained page of a run (or sweep) directory: every image inlined."""
    import json
    from fwdstep.core.errors import OutputError
    from fwdstep.results.result import SUMMARY_FILE
    summ = os.path.join(run_dir, SUMMARY_FILE)
    sweep_csv = os.path.join(run_dir, "sweep.csv")
    tuned = os.path.join(run_dir, TUNE_FILE)
    if not any(os.path.isfile(f) for f in (summ, sweep_csv, tuned)):
        raise OutputError(f"{run_dir} holds no saved run, sweep or tuning (no summary.json, "
                          "sweep.csv or tune.json)")
    parts = []
    title = os.path.basename(os.path.normpath(run_dir))
    if os.path.isfile(tuned) and not os.path.isfile(summ):
        parts += _tuning(run_dir, tuned)
        title = f"tuning {os.path.basename(str(_tune_record(tuned).get('diagram') or title))}"
    if os.path.isfile(summ):
        from fwdstep.results.result import load_result
        r = load_result(run_dir)
        s = r.stored
        status_cls = "ok" if s.get("status") == "ok" else "bad"
        title = f"{os.path.basename(str(s.get('diagram') or title))}"
        parts.append(f"<h1>{html.escape(title)}</h1>")
        if s.get("title"):
            parts.append(f"<p>{html.escape(s['title'])}</p>")
        parts.append(f'<p>Status: <span class="{status_cls}">{html.escape(str(s.get("status")))}'
                     f"</span>" + (f" — {html.escape(str(s.get('message')))}"
                                   if s.get("message") else "") + "</p>")
        facts = {"diagram": s.get("diagram"), "t reached [s]": s.get("t_reached"),
                 "steps": s.get("steps"), "variants": s.get("batch"),
                 "wall time [s]": s.get("wall_time_s"), "run directory": run_dir}
        parts.append(_pairs(facts))
        parts.extend(_diagram_section(s, run_dir))
        parts.extend(_parameters_section(s))
        parts.append("<h2>Metrics</h2>")
        m = s.get("metrics")
        parts.append(_table(m) if isinstance(m, list) else _pairs(m or {}))
        parts += _limits(s.get("limits"))
        parts += _events(r)
        parts += _animation(r, run_dir)
        parts += _linear(run_dir)
        parts.append("<h2>Figures</h2>")
        parts += _figures(r, run_dir)
        parts.append("<h2>Signals recorded</h2>")
        parts.append(_table([{"signal": k, "shape": v} for k, v in
                             (s.get("signals") or {}).items()], ["signal", "shape"]))
    if os.path.isfile(sweep_csv):
        from fwdstep.results.sweep_format import read_table
        rows = read_table(sweep_csv)
        if not parts:
            parts.append(f"<h1>Sweep {html.escape(title)}</h1>")
        counts: dict = {}
        for row in rows:
            counts[row.get("status", "?")] = counts.get(row.get("status", "?"), 0) + 1
        parts.append("<h2>Sweep</h2><p>" + html.escape(", ".join(
            f"{v} {k}" for k, v in counts.items())) + "</p>")
        parts.append(_table([_numbers(row) for row in rows]))
        for name in sorted(os.listdir(run_dir)):
            if name.endswith(".png") and name.startswith("sweep"):
                with open(os.path.join(run_dir, name), "rb") as fh:
                    parts.append(f"<figure>{_img(fh.read(), 'image/png', name)}"
                                 f"<figcaption>{html.escape(name)}</figcaption></figure>")
        parts += _sweep_extras(run_dir, os.path.isfile(summ))
    return ("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>fwdstep report: {html.escape(title)}</title><style>{_CSS}</style></head>"
            f"<body>{''.join(parts)}<p style=\"color:#888;font-size:.8em\">{_MARK}</p>"
            "</body></html>\n")


TUNE_FILE = "tune.json"


def _tune_record(path: str) -> dict:
    import json
    from fwdstep.core.errors import DamagedFileError
    try:
        with open(path, encoding="utf-8") as fh:
            rec = json.load(fh)
    except (OSError, ValueError) as exc:
        raise DamagedFileError(f"{path}: not a tuning record ({exc})") from None
    if not isinstance(rec, dict) or not isinstance(rec.get("initial"), dict) \
            or not isinstance(rec.get("best"), dict):
        raise DamagedFileError(f"{path}: not a tuning record (no 'initial' and 'best')")
    problem = _tune_record_problem(rec)
    if problem:
        raise DamagedFileError(f"{path}: damaged tuning record: {problem}")
    return rec


def _tune_record_problem(rec: dict) -> str:
    """What in a tune.json does not have the shape ``write_tune`` gives it (every field the
    page reads: a damaged one was a bare traceback or a page of wrong rows), or ''."""
    def number(v, none_ok=True):
        return (v is None and none_ok) or (isinstance(v, (int, float))
                                          and not isinstance(v, bool))

    def strings(v):
        return isinstance(v, list) and all(isinstance(x, str) for x in v)

    subject_to = rec.get("subject_to", [])
    if not strings(subject_to):
        return "'subject_to' is not a list of constraints"
    bounds = rec.get("bounds", {})
    if not isinstance(bounds, dict) or not all(
            isinstance(b, list) and len(b) == 2 and all(number(x, False) for x in b)
            for b in bounds.values()):
        return "'bounds' is not {name: [low, high]}"
    for side in ("initial", "best"):
        values = rec[side].get("values", {})
        if not isinstance(values, dict) or not all(number(v) for v in values.values()):
            return f"'{side}.values' is not {{name: number}}"
        if not number(rec[side].get("cost")):
            return f"'{side}.cost' is not a number"
        cons = rec[side].get("constraints", [])
        if not isinstance(cons, list) or not all(number(v) for v in cons) \
                or len(cons) not in (0, len(subject_to)):
            return f"'{side}.constraints' is not one number per constraint"
    return ""


def _tuning(run_dir: str, path: str) -> list:
    """The page of ``fwdstep tune -o DIR``: the problem, before against after (parameters,
    objective, constraints), the runs, and the tuning's figures."""
    rec = _tune_record(path)
    parts = [f"<h1>Tuning {html.escape(os.path.basename(str(rec.get('diagram') or '')))}</h1>",
             _pairs({k: v for k, v in (
                 ("diagram", rec.get("diagram")), ("minimize", rec.get("minimize")),
                 ("subject to", "; ".join(rec.get("subject_to") or []) or "(nothing)"),
                 ("status", rec.get("status")),
                 ("runs", rec.get("runs")), ("time in the runs [s]", rec.get("wall_time_s")),
                 ("message", rec.get("message"))) if v not in (None, "")})]
    before, after = rec["initial"], rec["best"]
    rows = []
    bounds = rec.get("bounds") or {}
    for name, v in (before.get("values") or {}).items():
        b = bounds.get(name)
        rows.append({"quantity": name, "bounds": f"[{b[0]:g}, {b[1]:g}]" if b else "",
                     "before": v, "after": (after.get("values") or {}).get(name)})
    rows.append({"quantity": f"{rec.get('minimize')} (minimised)", "bounds": "",
                 "before": before.get("cost"), "after": after.get("cost")})
    for k, expr in enumerate(rec.get("subject_to") or []):
        pick = (lambda side: (side.get("constraints") or [None] * (k + 1))[k])
        rows.append({"quantity": f"constraint {expr}", "bounds": "",
                     "before": pick(before), "after": pick(after)})
    parts.append("<h2>Before and after</h2>")
    parts.append(_table(rows, ["quantity", "bounds", "before", "after"]))
    for name, caption in (("before_after.png", "the signals of the objective and the "
                           "constraints, before (dashed) and after (solid)"),
                          ("history.png", "every evaluation of the search")):
        fig = os.path.join(run_dir, name)
        if os.path.isfile(fig):
            with open(fig, "rb") as fh:
                parts.append(f"<figure>{_img(fh.read(), 'image/png', name)}"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    if os.path.isfile(os.path.join(run_dir, "best.yaml")):
        parts.append("<p>The tuned diagram: <code>best.yaml</code> (run it with "
                     "<code>fwdstep run best.yaml</code>); every evaluation: "
                     "<code>history.csv</code>.</p>")
    return parts


#: at most this many state events are listed on the page (all are in summary.json)
MAX_EVENTS_SHOWN = 200


def _events(r) -> list:
    """The "State events" section: the located zero crossings (time, block, kind, variant)
    and the run's notes (chattering), when there are any."""
    if not r.events and not r.notes:
        return []
    from fwdstep.results.result import events_line
    out = ["<h2>State events</h2>"]
    if r.events:
        out.append(f"<p>{html.escape(events_line(r.events))}.</p>")
        batch = any(e.variant for e in r.events)
        rows = [{"time [s]": e.time, "block": e.block, "event": e.kind,
                 **({"variant": e.variant} if batch else {})}
                for e in r.events[:MAX_EVENTS_SHOWN]]
        out.append(_table(rows))
        if len(r.events) > MAX_EVENTS_SHOWN:
            out.append(f"<p>… and {len(r.events) - MAX_EVENTS_SHOWN} more (all in "
                       "summary.json).</p>")
    for note in r.notes:
        out.append(f"<p>Note: {html.escape(note)}</p>")
    return out


def _limits(record) -> list:
    """The "Operating limits" table of a single run (fwdstep.run.limits): per limit and joint,
    the usage (max |signal| / limit; above 1: beyond it), in red where exceeded."""
    if not record or isinstance(record[0].get("exceeded"), list):
        return []
    head = ("<tr><th>block.port</th><th>limit</th><th>unit</th>" +
            "".join(f"<th>{html.escape(j)}</th>" for j in record[0]["joints"]) +
            "<th>first beyond [s]</th></tr>")
    rows = []
    for e in record:
        cells = []
        for u, lo, hi in zip(e["usage"], e["lower"], e["upper"]):
            bad = u is not None and u > 1.0
            text = "-" if u is None else f"{u:.3g}"
            bounds = f"[{lo:.4g}, {hi:.4g}]" if lo is not None else ""
            cells.append(f'<td class="num{" bad" if bad else ""}" title="{bounds}">{text}</td>')
        first = e["first_exceeded_t"]
        rows.append(f"<tr><td>{html.escape(e['block'])}.{html.escape(e['port'])}</td>"
                    f"<td>{html.escape(e['what'])}</td><td>{html.escape(e['unit'])}</td>"
                    + "".join(cells) + f"<td>{'-' if first is None else f'{first:.6g}'}</td></tr>")
    note = ("<p>Usage per joint: " + html.escape(record[0]["usage_definition"]) +
            " for symmetric limits, |q - centre| / half-range for positions; above 1 the "
            "joint went beyond its limit (red).</p>")
    return ["<h2>Operating limits</h2>", note, f"<table>{head}{''.join(rows)}</table>"]


def _numbers(row: dict) -> dict:
    """A sweep.csv row with its numeric cells as numbers (shown to 6 digits, right-aligned)."""
    out = {}
    for k, v in row.items():
        try:
            out[k] = int(v) if k in ("variant", "batch") else float(v) if v not in ("", None) \
                and k not in ("status", "message") else v
        except (TypeError, ValueError):
            out[k] = v
    return out


def _sweep_extras(run_dir: str, has_run: bool) -> list:
    """The diagram of a sweep and the comparison of up to 8 of its saved variants."""
    from fwdstep.views.compare import MAX_SWEEP_SHOWN, compare, sweep_runs
    from fwdstep.core.errors import FwdstepError
    from fwdstep.results.plotting import figure_bytes
    out = []
    from fwdstep.core.errors import DamagedFileError
    try:
        runs = sweep_runs(run_dir)
    except DamagedFileError:
        raise                          # a damaged part is said in one line, not hidden
    except FwdstepError as exc:
        return [f"<p>{html.escape(f'no comparison of variants: {exc}')}</p>"]
    diagram = getattr(runs[0].result, "diagram_file", None)
    if not has_run:
        try:
            import json
            with open(os.path.join(run_dir, "sweep.json"), encoding="utf-8") as fh:
                recorded = json.load(fh)
        except (OSError, ValueError):
            recorded = {"diagram": diagram} if diagram else None
        if recorded:
            out.extend(_diagram_section(recorded, run_dir))
    picked = runs if len(runs) <= MAX_SWEEP_SHOWN else [
        runs[int(k)] for k in np.unique(np.linspace(0, len(runs) - 1, MAX_SWEEP_SHOWN)
                                        .astype(int))]
    if len(picked) >= 2:
        c = compare([r.result for r in picked], labels=[r.label for r in picked])
        out.append(f"<h2>Variants compared</h2><figure>"
                   f"{_img(figure_bytes(c.figure, 'png'), 'image/png', 'variants compared')}"
                   f"<figcaption>{len(picked)} of {len(runs)} saved variants, differences "
                   f"against {html.escape(picked[0].label)}</figcaption></figure>")
    return out


def _linear(run_dir: str) -> list:
    """What ``fwdstep linearize`` wrote for this diagram (its default folder is the run's
    ``linear/``): the time, inputs and outputs, the poles, the margins and the Bode figure."""
    import json
    folder = os.path.join(run_dir, "linear")
    try:
        with open(os.path.join(folder, "linear.json"), encoding="utf-8") as fh:
            data = json.load(fh)
        poles = [complex(re_, im) for re_, im in data["poles"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    rows = [{"name": "linearised at t [s]", "value": data.get("t")},
            {"name": "inputs", "value": ", ".join(data.get("inputs", []))},
            {"name": "outputs", "value": ", ".join(data.get("outputs", []))},
            {"name": "opened at", "value": ", ".join(data.get("opened", [])) or "(closed loop)"},
            {"name": "states", "value": len(data.get("states", []))}]
    margins = data.get("margins") or {}
    for key in ("gain_margin_db", "phase_margin_deg"):
        if margins.get(key) is not None:
            rows.append({"name": key.replace("_", " "), "value": margins[key]})
    shown = sorted(poles, key=lambda z: -z.real)[:12]
    pole_rows = [{"pole": f"{z.real:.6g} {z.imag:+.6g}j"} for z in shown]
    out = ["<h2>Linear analysis</h2>", _table(rows, ["name", "value"]),
           f"<p>Rightmost {len(shown)} of {len(poles)} poles:</p>", _table(pole_rows, ["pole"])]
    bode = os.path.join(folder, "bode.png")
    if os.path.isfile(bode) and not os.path.islink(bode):
        with open(bode, "rb") as fh:
            out.append(f"<figure>{_img(fh.read(), 'image/png', 'Bode')}"
                       "<figcaption>fwdstep linearize: gain and phase</figcaption></figure>")
    return out


def _animation(result, run_dir: str) -> list:
    """The run's robot replayed beside the figures (fwdstep.animate): [] without a robot."""
    from fwdstep.views.animate import report_section
    return report_section(result, run_dir)


def _figures(result, run_dir: str) -> list:
    """Each figure of the run: its PNG in the directory if fwdstep wrote one, else drawn now."""
    from fwdstep.results.plotting import figure_bytes, result_figures
    from fwdstep.results.outputs import owned_files
    ours = owned_files(run_dir)
    out = []
    drawn = None
    for name in (getattr(result, "figure_panels", None) or {}):
        fname = f"{name}.png"
        if fname in ours:
            with open(os.path.join(run_dir, fname), "rb") as fh:
                data = fh.read()
        else:
            if drawn is None:
                drawn = result_figures(result)
            data = figure_bytes(drawn[name], "png")
        out.append(f"<figure>{_img(data, 'image/png', name)}"
                   f"<figcaption>{html.escape(name)}</figcaption></figure>")
    return out or ["<p>(the diagram names no figures)</p>"]


def write_report(run_dir: str, output: str | None = None) -> str:
    """Write report.html (into ``run_dir`` by default, through fwdstep.results.outputs); its path."""
    from fwdstep.results.outputs import OutputDir
    page = report_html(run_dir)
    if output is None:
        with OutputDir(run_dir, force=True, expected=[REPORT_FILE]) as out:
            with open(os.path.join(out.dir, REPORT_FILE), "w", encoding="utf-8") as fh:
                fh.write(page)
            out.commit()
        return os.path.join(run_dir, REPORT_FILE)
    from fwdstep.core.errors import OutputError
    from fwdstep.core.files import atomic_write
    if os.path.lexists(output):              # only an earlier fwdstep report is replaced
        ours = False
        if os.path.isfile(output) and not os.path.islink(output):
            with open(output, "rb") as fh:
                ours = _MARK.encode() in fh.read()[-400:]
        if not ours:
            raise OutputError(f"refusing to replace {output}: it is not a report fwdstep wrote")
    os.makedirs(os.path.dirname(os.path.abspath(output)), exist_ok=True)
    atomic_write(os.path.abspath(output), lambda fh: fh.write(page.encode()), binary=True)
    return output


