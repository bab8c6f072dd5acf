"""The package's layout in numbers: the places a reader visits at its top (root modules and folders), the import
arrows between those places, how many of them point up the wings contract of pyproject.toml, and the import circles
between modules (imports under TYPE_CHECKING counted). docs/architecture.md is the layout these numbers measure.

    python scripts/house_metrics.py            # this checkout
    python scripts/house_metrics.py --json     # the same as JSON
    python scripts/house_metrics.py --repo DIR # another checkout (an older commit's, say), imported from DIR
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

import grimp
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]


def place(module: str) -> str | None:
    """The top-level place of ``mbcapture.x.y``: ``x`` (a root module or a folder); None for the package itself."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module."""
    names = sorted(set(edges) | {t for ts in edges.values() for t in ts})
    at = {n: i for i, n in enumerate(names)}
    pairs = [(at[a], at[b]) for a, ts in edges.items() for b in ts]
    rows, cols = zip(*pairs) if pairs else ((), ())
    graph = csr_matrix((np.ones(len(pairs)), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(graph, directed=True, connection="strong")
    groups: dict[int, list[str]] = {}
    for name, lab in zip(names, label):
        groups.setdefault(int(lab), []).append(name)
    return sorted(g for g in groups.values() if len(g) > 1)


def measure(package: str = "mbcapture", root: Path = ROOT) -> dict:
    graph = grimp.build_graph(package, exclude_type_checking_imports=False, cache_dir=None)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    arrows = {
        (place(a), place(b)) for a, ts in edges.items() for b in ts if place(a) and place(b) and place(a) != place(b)
    }
    places = {place(m) for m in graph.modules} - {None}
    layers = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]["layers"]
    level = {m.strip().removeprefix(f"{package}."): -i for i, layer in enumerate(layers) for m in layer.split("|")}
    up = sorted(f"{a} -> {b}" for a, b in arrows if a in level and b in level and level[b] >= level[a])
    return {
        "places": len(places),
        "root_modules": sorted(p for p in places if (root / package / f"{p}.py").exists()),
        "folders": sorted(p for p in places if (root / package / p).is_dir()),
        "arrows_between_places": len(arrows),
        "arrows_up_or_across_the_wings": up,
        "circles": circles(edges),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON")
    parser.add_argument("--repo", type=Path, default=ROOT, help="the checkout to measure (default: this one)")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.repo.resolve()))
    m = measure(root=args.repo.resolve())
    if args.json:
        print(json.dumps(m, indent=2))
        return 0
    print(f"places at the top: {m['places']} ({len(m['root_modules'])} root modules, {len(m['folders'])} folders)")
    print(f"import arrows between them: {m['arrows_between_places']}")
    print(f"arrows up or across the wings contract: {len(m['arrows_up_or_across_the_wings'])}")
    print(f"import circles (TYPE_CHECKING counted): {len(m['circles'])}")
    for line in m["arrows_up_or_across_the_wings"] + [" <-> ".join(c) for c in m["circles"]]:
        print("  " + line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
