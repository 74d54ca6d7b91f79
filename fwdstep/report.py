"""Self-contained HTML: a Result's notebook summary and the ``fwdstep report`` page."""
from __future__ import annotations

import html


def result_summary_html(result) -> str:
    """A short summary of a Result for notebooks: status, time reached, metrics, signals."""
    m = result.metrics()
    rows = [("status", result.status + (f" — {result.message}" if result.message else "")),
            ("t reached", f"{result.t[-1]:g} s" if len(result.t) else "nothing recorded"),
            ("steps", str(result.steps)), ("variants", str(result.batch))]
    if isinstance(m, dict):
        rows += [(k.replace("_", " "), f"{v:.3e}" if isinstance(v, float) else str(v))
                 for k, v in m.items()]
    rows.append(("signals", ", ".join(result.names)))
    body = "".join(f"<tr><th style='text-align:left'>{html.escape(k)}</th>"
                   f"<td style='text-align:left'>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<div><b>fwdstep Result</b><table>{body}</table></div>"
