"""The few HTML pieces report.html is assembled from, shared by the capture's report
(:mod:`mbcapture.capture.report`) and a video's section of it (:mod:`mbcapture.capture.video`). Written by hand:
a page of tables and images, which no templating library would make shorter.
"""

from __future__ import annotations

import html
import json

#: The style of every page the package writes (report.html, the EMVA datasheet).
CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1280px;padding:0 1.2em 3em;
color:#222;line-height:1.4}
h1{font-size:1.5em;margin:.8em 0 .2em}h2{font-size:1.2em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0}td,th{border:1px solid #ddd;padding:.25em .6em;text-align:left;
vertical-align:top}th{background:#f5f5f5}td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(230px,1fr));gap:1em}
figure{margin:0}figure img{width:100%;image-rendering:pixelated;border:1px solid #ccc;background:#000}
figure.plot img{image-rendering:auto;background:#fff;border:none;width:auto;max-width:100%}figcaption{font-size:.82em;color:#444}
.lead{font-size:1.05em}.verdict{padding:.6em 1em;border-left:4px solid #888;background:#f7f7f7}
code{background:#f2f2f2;padding:0 .2em}.muted{color:#666;font-size:.85em}
.scale{font-size:.8em;margin:.3em 0}.bar{height:.8em;border:1px solid #aaa}.ticks{display:flex;justify-content:space-between}
.sw{display:inline-block;width:1em;height:.8em;border:1px solid #aaa;margin:0 .2em 0 .5em;vertical-align:middle}
"""


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
        return (
            json.dumps(v, default=lambda o: f"{o:.4g}" if isinstance(o, float) else str(o))
            if len(str(v)) < 60
            else "[" + ", ".join(fmt(x) for x in v) + "]"
        )
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
    return (
        f"<figure{cls}><a href='{esc(src)}'><img src='{esc(src)}' alt='{esc(src)}'></a>"
        f"<figcaption>{caption}</figcaption></figure>"
    )
