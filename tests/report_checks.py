"""Checks of a run's output folder shared by tests: report.html opens offline and references only
files that exist; every key of report.json is documented in docs/report.md."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images: list[str] = []
        self.links: list[str] = []
        self.tags: set[str] = set()
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.add(tag)
        if tag == "img":
            self.images.append(a.get("src", ""))
        if tag in ("a", "link") and a.get("href"):
            self.links.append(a["href"])
        if tag in ("script", "iframe", "object", "embed", "source", "video", "audio"):
            self.links.append(a.get("src", tag))

    def handle_data(self, data):
        self.text.append(data)


def parse_report(folder: Path) -> _Refs:
    refs = _Refs()
    refs.feed((folder / "report.html").read_text(encoding="utf-8"))
    return refs


def check_report_folder(folder: Path) -> _Refs:
    """report.html exists, loads nothing from elsewhere (no scripts, no URLs, no absolute paths),
    and every image and link it has names a file of the folder (or an anchor of the page)."""
    refs = parse_report(folder)
    assert refs.images, "report.html shows no image"
    assert not refs.tags & {"script", "iframe", "object", "embed"}, refs.tags
    for ref in refs.images + refs.links:
        if ref.startswith("#"):
            continue
        assert not re.match(r"^[a-z]+:|^/", ref), f"report.html refers outside its folder: {ref}"
        assert (folder / ref).is_file(), f"report.html refers to {ref}, which is not in {folder}"
    html = (folder / "report.html").read_text(encoding="utf-8")
    assert "url(" not in html and "@import" not in html, "report.html CSS loads something"
    return refs


def _documented() -> list[str]:
    """Key paths of docs/report.md: every `code` span in the first column of its tables."""
    keys = []
    for line in (ROOT / "docs" / "report.md").read_text().splitlines():
        if line.startswith("| `"):
            first = line.split("|")[1]
            keys.extend(re.findall(r"`([^`]+)`", first))
    return keys


def report_key_paths(report: dict, reads: list[str], channels: tuple[str, ...] = ("R", "G", "B")) -> set[str]:
    """Dotted paths of every leaf of report.json; list entries as ``[]``, read names as ``<read>``,
    channels as ``<channel>``."""
    out: set[str] = set()

    def walk(node, path):
        if isinstance(node, dict):
            if not node and path:
                out.add(path)
            for k, v in node.items():
                by_channel = path == "electrons_per_render_unit_second"
                name = "<channel>" if by_channel and k in channels else "<read>" if k in reads else str(k)
                walk(v, f"{path}.{name}" if path else name)
        elif isinstance(node, list) and node and all(isinstance(x, dict) for x in node):
            for x in node:
                walk(x, f"{path}[]")
        else:
            out.add(path)

    walk(report, "")
    return out


def undocumented_keys(report: dict, reads: list[str]) -> list[str]:
    """Keys of ``report`` that docs/report.md does not list (a documented ``a.*`` covers a.anything,
    a documented list ``a`` of entries explained in its row covers ``a[].anything``)."""
    doc = _documented()
    exact = set(doc)
    prefixes = tuple(d[:-1] for d in doc if d.endswith(".*")) + tuple(f"{d}[]." for d in doc)
    return sorted(k for k in report_key_paths(report, reads) if k not in exact and not k.startswith(prefixes))
