"""The few HTML pieces report.html is assembled from, shared by the capture's report
(:mod:`mbcapture.report`) and a video's section of it (:mod:`mbcapture.video`). Written by hand:
a page of tables and images, which no templating library would make shorter.
"""

from __future__ import annotations

import html
import json


def esc(x) -> str:
    """Text made safe for HTML."""
    return html.escape(str(x))


def fmt(v) -> str:
    """A value as a report prints it: None as a dash, floats to 4 significant digits, short lists as JSON."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return json.dumps(v, default=lambda o: f"{o:.4g}" if isinstance(o, float) else str(o)) if len(str(v)) < 60 else \
            "[" + ", ".join(fmt(x) for x in v) + "]"
    return str(v)


def table(rows: list[list], header: list[str] | None = None) -> str:
    """An HTML table of ``rows`` (numbers right-aligned), with an optional header row."""
    out = ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        cells = []
        for c in row:
            num = isinstance(c, (int, float)) and not isinstance(c, bool)
            cells.append(f"<td class='num'>{esc(fmt(c))}</td>" if num else f"<td>{esc(fmt(c))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def figure(src: str, caption: str, plot: bool = False) -> str:
    """An image linked to itself, with its caption (HTML, not escaped); ``plot``: a chart, not a picture."""
    cls = " class='plot'" if plot else ""
    return (f"<figure{cls}><a href='{esc(src)}'><img src='{esc(src)}' alt='{esc(src)}'></a>"
            f"<figcaption>{caption}</figcaption></figure>")
