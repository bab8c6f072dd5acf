"""A sweep's results: one tidy table (Parquet and CSV), plots of each metric against each axis, index.html.

The table has one row per point: ``point`` (p0007), ``point_id``, ``render_group``, ``status``,
``error``, one column per axis (named by its key, e.g. ``sensor.read_noise_e``), then what the point
measured (:func:`mbcapture.sweep.execute.measurements`): ``metrics.*`` (every scalar metric of the
application), ``render_error.*``, ``passes``, ``spp_total``, ``renders_rendered`` and ``renders_reused``
(the render cache), ``render_shared`` (the point used its group's render stage), ``timings_s.*`` and
``seconds`` (the point's wall time), ``worker``.

Plots (:class:`mbcapture.output.plots.MetricGrid`): for every
numeric ``metrics.*`` column and ``render_error.to_shot_noise_variance_median`` (rendering noise
against the sensor's) where they vary, one figure with a row of panels per
axis, the metric against that axis; with one other axis its values are the lines, with more, the
first other axis makes the panels (facets) and the rest the lines. An axis with numbers spanning more than
a decade gets a log scale, text axes (protocols) are categories. Random samples, whose other axes
do not repeat, are a scatter plot.
"""

from __future__ import annotations

import html
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..output.io import staged_outputs
from ..output.plots import MetricGrid, png_bytes

#: Columns that say which point a row is, in this order, before the axes.
ID_COLUMNS = ("point", "point_id", "render_group", "status", "error")
#: Columns plotted against the axes: the application's metrics and the rendering noise against the sensor's.
PLOTTED = ("metrics.", "render_error.to_shot_noise_variance_median")


def _cell(value: Any) -> Any:
    """Axis values that are not scalars (lists) are kept as their JSON text."""
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value)
    return value


def table(sweep, plan, rows: dict[int, dict]):
    """The results as a pandas DataFrame, one row per point in sweep order."""
    import pandas as pd

    records = []
    for p in sweep.points:
        row = rows.get(p.index, {"status": "not run", "error": None})
        group = plan.group_of(p.index)
        rec = {
            "point": p.label,
            "point_id": p.id,
            "render_group": group.label if group else None,
            "status": row.get("status"),
            "error": row.get("error"),
        }
        rec.update({axis: _cell(p.values.get(axis)) for axis in sweep.axes})
        rec.update({k: v for k, v in row.items() if k not in rec and k not in ("traceback",)})
        records.append(rec)
    df = pd.DataFrame.from_records(records)
    fixed = [*ID_COLUMNS, *sweep.axes]
    rest = sorted(c for c in df.columns if c not in fixed)
    df = df[[*fixed, *rest]]
    for col in df.columns:  # a column mixing numbers and text (a metric that is sometimes a note) as text
        if df[col].dtype == object:
            kinds = {type(v) for v in df[col] if v is not None and not (isinstance(v, float) and math.isnan(v))}
            if kinds and kinds <= {int, float}:
                df[col] = pd.to_numeric(df[col])
            elif len(kinds) > 1 and not kinds <= {bool}:
                df[col] = df[col].map(lambda v: None if v is None else str(v))
    return df


def numeric_columns(df) -> list[str]:
    """Plotted columns: numeric ``metrics.*`` and the median Monte Carlo / shot-noise variance ratio,
    where a finite value varies."""
    from pandas.api.types import is_bool_dtype, is_numeric_dtype

    out = []
    for col in df.columns:
        if not col.startswith(PLOTTED) or not is_numeric_dtype(df[col]) or is_bool_dtype(df[col]):
            continue
        v = df[col].to_numpy(dtype=float, na_value=np.nan)
        finite = v[np.isfinite(v)]
        # varies, and is not rounding noise around zero (a difference of identical images: 1e-17)
        if finite.size and finite.max() > finite.min() and np.abs(finite).max() > 1e-12:
            out.append(col)
    return out


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


CSS = (
    "body{font-family:sans-serif;max-width:1200px;margin:auto;padding:0 1em}table{border-collapse:collapse;"
    "font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:left}td.num{text-align:right}"
    "img{max-width:100%}.muted{color:#666}"
    ".failed{color:#a00}"
)


def _esc(x: Any) -> str:
    return html.escape("" if x is None else str(x))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.4g}"
    return _esc(v)


def _html_table(df, columns: list[str], limit: int = 500) -> str:
    head = "".join(f"<th>{_esc(c)}</th>" for c in columns)
    body = []
    for rec in df[columns].head(limit).to_dict("records"):
        cells = "".join(
            f"<td class='num'>{_fmt(v)}</td>"
            if isinstance(v, (int, float)) and not isinstance(v, bool)
            else f"<td>{_fmt(v)}</td>"
            for v in rec.values()
        )
        body.append(f"<tr>{cells}</tr>")
    more = (
        f"<p class='muted'>First {limit} of {len(df)} rows; all of them in results.csv.</p>" if len(df) > limit else ""
    )
    return f"<table><tr>{head}</tr>{''.join(body)}</table>{more}"


def index_html(sweep, summary: dict, df, plots: dict[str, str]) -> str:
    s = summary
    parts = [f"<h1>Sweep {_esc(sweep.name)}</h1>"]
    if sweep.spec.description:
        parts.append(f"<p>{_esc(sweep.spec.description)}</p>")
    facts = [
        ["sweep file", str(sweep.path)],
        ["base config", str(sweep.base)],
        ["overrides of every point", " ".join(sweep.overrides) or "none"],
        [
            "points",
            f"{s['points']} ({s['ok']} ok, {s['failed']} failed; {s['ran']} run now, {s['resumed']} from an earlier run)",
        ],
        [
            "render groups",
            f"{s['render_groups']} (points whose render stage is the same share it), rendering "
            f"{s['render_sets']} different sets of images (the others find them in the render cache)",
        ],
        ["axes that change the renders", ", ".join(s["axes_changing_renders"]) or "none"],
        [
            "renders this run",
            f"{s['renders_rendered']} rendered, {s['renders_reused']} read from the render cache, "
            f"{s['points_sharing_renders']} points used their group's render stage",
        ],
        ["ran on", s["executor"]],
        ["wall time", f"{s['wall_s']:.1f} s"],
    ]
    parts.append("<table>" + "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v)}</td></tr>" for k, v in facts) + "</table>")
    parts.append(
        "<p>Files: <a href='results.csv'>results.csv</a> · <a href='results.parquet'>results.parquet</a> · "
        "<a href='sweep.json'>sweep.json</a>"
        + (" · per-point outputs in <code>points/</code>" if sweep.spec.keep != "none" else "")
        + "</p>"
    )
    failed = df[df["status"] != "ok"]
    if len(failed):
        parts.append(
            "<h2 class='failed'>Failed points</h2>" + _html_table(failed, ["point", *sweep.axes, "status", "error"])
        )
    shown = [
        "point",
        "render_group",
        *sweep.axes,
        "status",
        *[c for c in df.columns if c.startswith(PLOTTED) and c in plots],
        "renders_rendered",
        "renders_reused",
        "seconds",
    ]
    shown = [c for c in dict.fromkeys(shown) if c in df.columns]
    parts.append("<h2>Results</h2>" + _html_table(df, shown))
    if plots:
        parts.append("<h2>Plots</h2>")
        parts.append(
            "<p class='muted'>Each metric against each axis (a row of panels per axis); the other axes "
            "are the lines and, with two or more of them, the panels.</p>"
        )
        for metric, file in plots.items():
            parts.append(
                f"<h3>{_esc(metric)}</h3><a href='{_esc(file)}'><img src='{_esc(file)}' "
                f"alt='{_esc(metric)} against the axes'></a>"
            )
    else:
        parts.append("<p class='muted'>No metric varies across the points: nothing to plot.</p>")
    return (
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>sweep {_esc(sweep.name)}</title>"
        f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>\n"
    )


def write_results(out: Path, sweep, plan, rows: dict[int, dict], summary: dict) -> Any:
    """Write the table, plots, sweep.json and index.html into ``out`` (atomically); returns the table."""
    df = table(sweep, plan, rows)
    plots: dict[str, str] = {}
    with staged_outputs(out) as st:
        df.to_parquet(st.path("results.parquet"), index=False)
        df.to_csv(st.path("results.csv"), index=False)
        metrics = numeric_columns(df) if (df["status"] == "ok").any() else []
        if metrics:
            grid = MetricGrid(df, sweep.axes)
            for metric in metrics:
                name = f"plot_{_slug(metric)}.png"
                st.write_bytes(name, png_bytes(grid.draw(metric), dpi=90))
                plots[metric] = name
        st.write_json(
            "sweep.json",
            {
                "sweep": str(sweep.path),
                "base": str(sweep.base),
                "overrides": list(sweep.overrides),
                "spec": sweep.spec.model_dump(mode="json"),
                "summary": summary,
                "groups": [
                    {
                        "group": g.label,
                        "key": g.key,
                        "renders": g.renders,
                        "points": [sweep.points[i].label for i in g.points],
                    }
                    for g in plan.groups
                ],
                "points": [{"point": p.label, "id": p.id, "values": p.values} for p in sweep.points],
            },
        )
        st.write_bytes("index.html", index_html(sweep, summary, df, plots).encode("utf-8"))
    for old in out.glob("plot_*.png"):  # an earlier sweep's plots of metrics this one does not have
        if old.name not in plots.values():
            old.unlink(missing_ok=True)
    return df
