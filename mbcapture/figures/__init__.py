"""``mbcapture figures``: the paper's figures, regenerated from the simulator.

Each figure is a function registered with :func:`figure`; it gets a :class:`FigureContext`
(output size, seed, a cache of captures shared between figures) and returns a
:class:`FigureOutput`: a matplotlib figure and the data behind it. The runner writes, for every
figure, ``<name>.png``, ``<name>.pdf`` and ``<name>.json`` (the data; ``<name>.csv`` too where
the data is a table), and ``index.html`` showing them all. Everything is written through a
staging folder and moved into place at the end, so an interrupted run changes nothing.

Figures are deterministic for a seed: captures use the config's seed, matplotlib writes no
timestamps (``metadata`` cleared) into PNG and PDF.
"""

from __future__ import annotations

import csv
import html
import io
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..capture.run import run_capture
from ..config import load_config
from ..errors import ConfigError
from ..progress import bar as progress_bar
from ..output.io import check_out_dir, staged_outputs

ROOT = Path(__file__).resolve().parents[2]
CONFIG_DIR = ROOT / "configs"


@dataclass
class FigureOutput:
    """fig: a matplotlib Figure; data: JSON-able dict; table: optional rows (first row = header)
    written as CSV; caption: one paragraph for the index page."""

    fig: Any
    data: dict
    caption: str
    table: list[list] | None = None


@dataclass(frozen=True)
class FigureSpec:
    name: str
    title: str
    paper: str
    fn: Callable[["FigureContext"], FigureOutput]
    renders: bool


_REGISTRY: dict[str, FigureSpec] = {}


def figure(name: str, title: str, paper: str, renders: bool = True):
    """Register ``fn(ctx) -> FigureOutput`` as figure ``name`` (``paper``: which figure of the paper,
    or 'beyond the paper'; ``renders``: whether it runs Mitsuba)."""

    def deco(fn):
        _REGISTRY[name] = FigureSpec(name, title, paper, fn, renders)
        return fn

    return deco


def _load() -> None:
    """Import every module of this package (each registers its figures)."""
    import importlib
    import pkgutil

    for mod in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{mod.name}")


def _order(name: str) -> tuple[int, str]:
    """The paper's figures in their order, then the ones beyond the paper."""
    return (0 if name.startswith("fig") else 1, name)


def names() -> list[str]:
    _load()
    return sorted(_REGISTRY, key=_order)


def spec(name: str) -> FigureSpec:
    _load()
    return _REGISTRY[name]


@dataclass
class FigureContext:
    """quick: small film and few samples; captures are cached by (config, overrides)."""

    quick: bool
    seed: int = 0
    progress: bool = True
    _cache: dict = field(default_factory=dict)

    @property
    def film(self) -> tuple[int, int]:
        return (160, 128) if self.quick else (640, 512)

    def size_overrides(self) -> list[str]:
        w, h = self.film
        out = [f"render.width={w}", f"render.height={h}", f"seed={self.seed}"]
        if self.quick:
            out.append("render.spp=4")
        return out

    def config(self, name: str, overrides: tuple[str, ...] = ()):
        return load_config(CONFIG_DIR / f"{name}.yaml", [*self.size_overrides(), *overrides])

    def capture(self, name: str, *overrides: str):
        """Run (once per run of ``mbcapture figures``) ``configs/<name>.yaml`` at the figure size."""

        key = (name, overrides)
        if key not in self._cache:
            self._cache[key] = run_capture(
                self.config(name, overrides), progress=self.progress
            )  # a status line per stage
        return self._cache[key]


def _save(spec: FigureSpec, out: FigureOutput, st, elapsed_s: float) -> dict:
    import matplotlib.pyplot as plt

    st.write_bytes(f"{spec.name}.png", _render(out.fig, "png"))
    st.write_bytes(f"{spec.name}.pdf", _render(out.fig, "pdf"))
    plt.close(out.fig)
    st.write_json(f"{spec.name}.json", {"figure": spec.name, "title": spec.title, "paper": spec.paper, **out.data})
    files = [f"{spec.name}.png", f"{spec.name}.pdf", f"{spec.name}.json"]
    if out.table:
        buf = io.StringIO()
        csv.writer(buf).writerows(out.table)
        st.write_bytes(f"{spec.name}.csv", buf.getvalue().encode())
        files.append(f"{spec.name}.csv")
    return {
        "name": spec.name,
        "title": spec.title,
        "paper": spec.paper,
        "caption": out.caption,
        "files": files,
        "seconds": round(elapsed_s, 2),
    }


def _render(fig, fmt: str) -> bytes:
    buf = io.BytesIO()
    meta = {"Software": None} if fmt == "png" else {"Creator": None, "Producer": None, "CreationDate": None}
    fig.savefig(buf, format=fmt, dpi=130, metadata=meta)
    return buf.getvalue()


def _index_html(entries: list[dict], quick: bool) -> str:
    rows = []
    for e in entries:
        links = " · ".join(
            f'<a href="{html.escape(f)}">{html.escape(f.rsplit(".", 1)[1].upper())}</a>' for f in e["files"]
        )
        rows.append(
            f'<section id="{e["name"]}"><h2>{html.escape(e["title"])} <small>({html.escape(e["paper"])})</small></h2>'
            f'<img src="{e["name"]}.png" alt="{html.escape(e["title"])}" style="max-width:100%">'
            f"<p>{html.escape(e['caption'])}</p><p>{links} · {e['seconds']} s</p></section>"
        )
    mode = "quick (160x128, 4 spp)" if quick else "full size (640x512)"
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>mbcapture figures</title>"
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}section{margin:2em 0}</style></head>"
        f"<body><h1>mbcapture: the paper's figures, regenerated</h1><p>Mode: {mode}. "
        "Regenerate with <code>mbcapture figures</code>.</p>" + "".join(rows) + "</body></html>\n"
    )


def make_figures(
    out_dir: Path, *, quick: bool = False, only: list[str] | None = None, seed: int = 0, progress: bool = True
) -> list[dict]:
    """Write the figures (all, or ``only``) and ``index.html`` into ``out_dir``; returns the index entries."""

    _load()
    unknown = sorted(set(only or []) - set(_REGISTRY))
    if unknown:
        raise ConfigError(f"--only: unknown figure(s) {unknown}; expected some of {names()}")
    chosen = [_REGISTRY[n] for n in names() if not only or n in only]
    check_out_dir(out_dir)
    ctx = FigureContext(quick=quick, seed=seed, progress=progress)
    import matplotlib

    matplotlib.use("Agg")

    entries = []
    with staged_outputs(out_dir) as st:
        for spec in progress_bar(chosen, desc="figures", unit="fig", enabled=progress):
            t0 = time.perf_counter()
            fig_out = spec.fn(ctx)
            entries.append(_save(spec, fig_out, st, time.perf_counter() - t0))
        previous = _previous_entries(out_dir, {e["name"] for e in entries})
        all_entries = sorted(previous + entries, key=lambda e: _order(e["name"]))
        st.write_json("index.json", {"quick": quick, "seed": seed, "figures": all_entries})
        st.write_bytes("index.html", _index_html(all_entries, quick).encode())
    return entries


def _previous_entries(out_dir: Path, replaced: set[str]) -> list[dict]:
    """Index entries of figures written by an earlier run into the same folder (``--only`` keeps them)."""
    try:
        old = json.loads((out_dir / "index.json").read_text())["figures"]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    return [
        e
        for e in old
        if e.get("name") in _REGISTRY
        and e["name"] not in replaced
        and all((out_dir / f).exists() for f in e.get("files", []))
    ]
