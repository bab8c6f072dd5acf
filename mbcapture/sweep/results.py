"""A sweep's results: one tidy table (Parquet and CSV), plots of each metric against each axis, index.html.

The table has one row per point: ``point`` (p0007), ``point_id``, ``render_group``, ``status``,
``error``, one column per axis (named by its key, e.g. ``sensor.read_noise_e``), then what the point
measured (:func:`mbcapture.sweep.execute.measurements`): ``metrics.*`` (every scalar metric of the
application), ``render_error.*``, ``passes``, ``spp_total``, ``renders_rendered`` and ``renders_reused``
(the render cache), ``render_shared`` (the point used its group's render stage), ``timings_s.*`` and
``seconds`` (the point's wall time), ``worker``.

Plots (matplotlib; the faceting is a few lines here rather than a plotting library's): for every
numeric ``metrics.*`` column and ``render_error.to_shot_noise_variance_median`` (rendering noise
against the sensor's) where they vary, one figure with a row of panels per
axis, the metric against that axis; with one other axis its values are the lines, with more, the
first other axis makes the panels (facets) and the rest the lines. An axis with numbers spanning more than
a decade gets a log scale, text axes (protocols) are categories. Random samples, whose other axes
do not repeat, are a scatter plot.
"""

from __future__ import annotations

import html
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..io import staged_outputs

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


def _numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _log_scale(values: np.ndarray) -> bool:
    v = values[np.isfinite(values)]
    return bool(v.size and v.min() > 0 and v.max() / v.min() > 10)


def _major_only(axis, values: np.ndarray) -> None:
    """No minor ticks on a log axis whose values span two decades or more, which always shows two
    labelled decades: the minor ticks' artists are most of a panel's drawing time."""
    from matplotlib.ticker import NullLocator

    v = values[np.isfinite(values) & (values > 0)]
    if v.size and v.max() / v.min() >= 100:
        axis.set_minor_locator(NullLocator())


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


def _facets(ok, axis: str, axes: list[str]) -> tuple[str | None, list, list[str], bool]:
    """How ``axis`` is drawn: (facet axis or None, its panel values, the axes that make the lines,
    whether the points form a grid; False for random samples: a scatter)."""
    others = [a for a in axes if a != axis]
    structured = not others or bool(ok.groupby(others, dropna=False).size().max() > 1)
    facet = others[0] if structured and len(others) >= 2 else None
    panels = list(dict.fromkeys(ok[facet].tolist())) if facet else [None]
    lines = [a for a in others if a != facet] if structured else []
    return facet, panels, lines, structured


class MetricGrid:
    """One figure of panels for a sweep's table: a row of panels per axis, each against that axis,
    faceted by the other axes. :meth:`draw` puts one metric on it; the next call replaces it, so that
    the plots of every metric share one figure, whose axes and ticks are made once (making a panel's
    ticks anew is much of a plot's time: the six plots of the 64-point sensor_noise sweep took 2.6 s as
    fresh figures, 1.8 s redrawn)."""

    def __init__(self, df, axes: list[str]):
        import matplotlib.pyplot as plt
        from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

        self.ok = ok = df[df["status"] == "ok"]
        layout = {axis: _facets(ok, axis, axes) for axis in axes}
        ncols = min(max(len(panels) for _, panels, _, _ in layout.values()), 4)
        nrows = sum(-(-len(panels) // ncols) for _, panels, _, _ in layout.values())
        # one metric: every panel on one scale (labelled on the first column); each row one x axis
        self.fig, grid = plt.subplots(
            nrows, ncols, figsize=(3.4 * ncols + 0.6, 2.5 * nrows + 0.5), squeeze=False, sharex="row", sharey=True
        )
        #: per panel: (its axes, its rows of the table, the x axis, its position function, line keys, structured,
        #: whether it is the first of its row, which has the legend)
        self.panels: list[tuple] = []
        row = 0
        for axis, (facet, panels, line_keys, structured) in layout.items():
            xs = list(dict.fromkeys(ok[axis].tolist()))
            numeric_x = _numeric(xs)
            position = (lambda v: v) if numeric_x else {v: i for i, v in enumerate(xs)}.__getitem__
            for n, panel in enumerate(panels):
                ax = grid[row + n // ncols][n % ncols]
                sub = ok if facet is None else ok[ok[facet] == panel]
                self.panels.append((ax, sub, axis, position, line_keys, structured, n == 0))
                # a fixed title position: the automatic one measures every tick label of the panel (a third of the time)
                ax.set_title(f"{facet} = {panel}" if facet is not None else "", fontsize=8, y=1.0)
                if numeric_x and _log_scale(np.asarray(xs, dtype=float)):
                    ax.set_xscale("log")
                if numeric_x:  # the sweep's own values, labelled as they are
                    ax.xaxis.set_major_locator(FixedLocator(sorted(float(v) for v in xs)))
                    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                    ax.xaxis.set_minor_locator(NullLocator())
                else:
                    ax.set_xticks(range(len(xs)), [str(v) for v in xs], rotation=20, fontsize=7, ha="right")
                ax.set_xlabel(axis, fontsize=8)
                ax.tick_params(labelsize=7)
            for n in range(len(panels), -(-len(panels) // ncols) * ncols):
                grid[row + n // ncols][n % ncols].set_visible(False)
            row += -(-len(panels) // ncols)
        # fixed margins in inches (tight_layout measures every label: half of the plot's time)
        w, h = self.fig.get_size_inches()
        self.fig.subplots_adjust(
            left=0.85 / w, right=1 - 0.2 / w, bottom=0.5 / h, top=1 - 0.45 / h, wspace=0.3, hspace=0.45
        )

    def draw(self, metric: str):
        """The figure with ``metric`` on every panel (the metric drawn before it taken off)."""
        y_all = self.ok[metric].to_numpy(dtype=float, na_value=np.nan)
        log_y = _log_scale(y_all)
        for ax, sub, axis, position, line_keys, structured, first in self.panels:
            for artist in [*ax.lines, *ax.collections]:
                artist.remove()
            if ax.get_legend() is not None:
                ax.get_legend().remove()
            ax.set_prop_cycle(None)  # the lines' colours from the first again
            if structured:
                groups = sub.groupby(line_keys, dropna=False, sort=False) if line_keys else [((), sub)]
                for key, part in groups:
                    key = key if isinstance(key, tuple) else (key,)
                    order = np.argsort([position(v) for v in part[axis]], kind="stable")
                    label = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in zip(line_keys, key)) or None
                    ax.plot(
                        np.asarray([position(v) for v in part[axis]])[order],
                        part[metric].to_numpy(dtype=float, na_value=np.nan)[order],
                        "o-",
                        ms=3.5,
                        lw=1.2,
                        label=label,
                    )
            else:
                ax.scatter([position(v) for v in sub[axis]], sub[metric].to_numpy(dtype=float, na_value=np.nan), s=12)
            ax.set_yscale("log" if log_y else "linear")  # the scale's own locators, whatever the last metric set
            if log_y:
                _major_only(ax.yaxis, y_all)
            ax.grid(True, which="major", alpha=0.3)
            ax.relim()
            ax.autoscale_view()
            if line_keys and first:
                ax.legend(fontsize=6.5, frameon=False)
        self.fig.suptitle(metric, fontsize=9)
        return self.fig

    def close(self) -> None:
        import matplotlib.pyplot as plt

        plt.close(self.fig)


def plot(df, metric: str, axes: list[str]):
    """A figure of ``metric`` against each axis (one row of panels per axis), faceted by the other axes."""
    return MetricGrid(df, axes).draw(metric)


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, metadata={"Software": None})
    return buf.getvalue()


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
    import matplotlib

    matplotlib.use("Agg")

    df = table(sweep, plan, rows)
    plots: dict[str, str] = {}
    with staged_outputs(out) as st:
        df.to_parquet(st.path("results.parquet"), index=False)
        df.to_csv(st.path("results.csv"), index=False)
        metrics = numeric_columns(df) if (df["status"] == "ok").any() else []
        if metrics:
            grid = MetricGrid(df, sweep.axes)
            try:
                for metric in metrics:
                    name = f"plot_{_slug(metric)}.png"
                    st.write_bytes(name, _png(grid.draw(metric)))
                    plots[metric] = name
            finally:
                grid.close()
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
