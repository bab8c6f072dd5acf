"""Measure the README's tables and write them between their marker comments.

    python scripts/readme_tables.py                 # run every table's captures, rewrite README.md
    python scripts/readme_tables.py --only budget   # one table's captures; the others keep their numbers
    python scripts/readme_tables.py --only budget --rows tof_4tap   # one new config's row; the rest kept
    python scripts/readme_tables.py --from-data     # rewrite README.md from docs/measured.json, no runs
    python scripts/readme_tables.py --check         # exit 1 if README.md differs from docs/measured.json

Each row of a table is one ``mbcapture run <config> --quiet --out <tmp> [--set ...]`` in its own
process, read back from the run's ``report.json``, so a row says what a user's own run of that
command reports (wall time: ``timings_s.total_before_write``; a video's: all its frames',
``timings_s.video_total_before_write``). The numbers go to
``docs/measured.json`` (each table with its machine and run time) and into README.md between
``<!-- BEGIN readme_tables:<name> -->`` and ``<!-- END readme_tables:<name> -->``; nothing
else of the README changes. Tables: ``hdr`` (the HDR protocols at 640x512, about 13 minutes on 2
cores) and ``budget`` (every shipped config whose samples the noise budget chooses, at 160x128: the
run's own estimate of its rendering noise on every read). ``$MBCAPTURE_SET`` reaches the runs like any ``--set`` (a quick try at
a tiny size; do not commit such numbers).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: name -> (config, [(row label, extra --set overrides)]): what each README table measures.
TABLES: dict[str, tuple[str, list[tuple[str, list[str]]]]] = {
    "hdr": (
        "configs/metronome_hdr.yaml",
        [
            ("default: photon-efficient, 640x512, N=16", []),
            ("`capture.protocol=interleaved_hdr`", ["capture.protocol=interleaved_hdr"]),
            ("`capture.sequential=true` (conventional sensor)", ["capture.sequential=true"]),
            ("default at `render.width=160 render.height=128`", ["render.width=160", "render.height=128"]),
        ],
    ),
}

#: The noise budget table: every shipped config whose samples the budget chooses, at this film.
BUDGET_FILM = ("render.width=160", "render.height=128")


def budget_rows(root: Path = Path(".")) -> list[tuple[str, str, list[str]]]:
    """(label, config, overrides) of the noise budget table: each shipped config with ``render.spp:
    null`` (the noise budget's), at :data:`BUDGET_FILM`."""
    import yaml

    rows = []
    for path in sorted((root / "configs").glob("*.yaml")):
        spp = (yaml.safe_load(path.read_text()).get("render") or {}).get("spp")
        if spp is None:
            rows.append((path.stem, f"configs/{path.name}", list(BUDGET_FILM)))
    return rows


def run_in_own_process(args: list[str]) -> None:
    """``mbcapture <args>`` in a new Python process with an empty render cache of its own (what a user's
    first run of the command costs, kernel loading included)."""
    with tempfile.TemporaryDirectory(prefix="readme-tables-cache-") as cache:
        proc = subprocess.run(
            [sys.executable, "-m", "mbcapture", *args],
            capture_output=True,
            text=True,
            env={**os.environ, "MBCAPTURE_CACHE_DIR": cache},
        )
    if proc.returncode != 0:
        raise SystemExit(f"readme_tables: mbcapture {' '.join(args)} failed: {proc.stderr.strip()}")


def measure(config: str, overrides: list[str], run=run_in_own_process) -> dict:
    """One ``mbcapture run`` (by ``run``, default in its own process); the numbers of its report.json
    that the table shows."""
    with tempfile.TemporaryDirectory(prefix="readme-tables-") as tmp:
        run(["run", config, "--quiet", "--out", tmp, *[a for o in overrides for a in ("--set", o)]])
        rep = json.loads((Path(tmp) / "report.json").read_text())
    m = rep["metrics"]
    plan = rep["plan"]
    return {
        "command": "mbcapture run " + " ".join([config, "--quiet", *[f"--set {o}" for o in overrides]]),
        "film": rep["film"],
        "passes": plan["passes"],
        "spp": plan["spp"],
        # a video's report is its first frame's, with every frame's time summed beside it
        "wall_s": rep["timings_s"].get("video_total_before_write", rep["timings_s"]["total_before_write"]),
        "hdr_rel_mse": m.get("hdr_rel_mse"),
        "hdr_rel_mse_moving": m.get("hdr_rel_mse_moving"),
        "reads_disagreement_moving": m.get("motion_check", {}).get("max_pairwise_rel_rms"),
        "llvm": rep["versions"].get("llvm"),
        "variant": rep["versions"].get("variant"),
        "render_error": render_error_summary(rep.get("render_error") or {}, rep.get("top_up")),
    }


def render_error_summary(err: dict, top_up: dict | None = None) -> dict | None:
    """What the budget table shows of a report's ``render_error`` (and ``top_up``): the highest median,
    95th and 99.9th percentiles of the Monte Carlo / shot-noise variance ratio over the reads, each with
    its read, the budget's verdicts and how far a top-up pass took it. None without an estimate."""
    reads = err.get("reads")
    if not reads:
        return None

    def worst(key: str) -> tuple[str, float]:
        name = max(reads, key=lambda n: reads[n][key])
        return name, reads[name][key]

    (median_read, median), (p95_read, p95), (tail_read, tail) = (
        worst(f"to_shot_noise_variance_{q}") for q in ("median", "p95", "p999")
    )
    return {
        "median": median,
        "median_read": median_read,
        "p95": p95,
        "p95_read": p95_read,
        "p999": tail,
        "p999_read": tail_read,
        "met": err["budget"]["met"],
        "tail_met": err["budget"].get("tail_met"),
        "top_up_before": (top_up or {}).get("before") if (top_up or {}).get("applied") else None,
    }


def _num(v: float | None, digits: int = 3) -> str:
    return "" if v is None else f"{v:.{digits}g}"


def _seconds(s: float) -> str:
    return f"{s:.1f} s" if s < 10 else f"{s:.0f} s"


def _measured_on(table: dict, what: str) -> str:
    """The sentence that opens a table: where, how long, how loaded, and what each row is."""
    return (
        f"Measured on {table['machine']} with `python scripts/readme_tables.py"
        f"{'' if table.get('only') is None else ' --only ' + table['only']}` ({table['seconds']:.0f} s, load "
        f"average {table['load_average_5min']:g} over its last 5 minutes: other work on the machine stretches wall "
        "times)"
        + (
            f", with $MBCAPTURE_SET={table['mbcapture_set']!r} (not the sizes the rows name)"
            if table.get("mbcapture_set")
            else ""
        )
        + "; each row is the `mbcapture run` below"
        + (", with an empty render cache" if table.get("empty_cache") else "")
        + f", {what}:"
    )


def render_table(name: str, data: dict) -> str:
    """The markdown of table ``name`` from its measured rows (``data`` as in docs/measured.json)."""
    table = data["tables"][name]
    rows = table["rows"]
    if name == "hdr":
        lines = [
            _measured_on(table, "read from its `report.json` (`timings_s.total_before_write`, `metrics`)"),
            "",
            "| run | passes × spp | wall time | HDR relMSE (all / moving region) | reads' disagreement in the moving region |",
            "| --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            mse = "" if r["hdr_rel_mse"] is None else f"{_num(r['hdr_rel_mse'])} / {_num(r['hdr_rel_mse_moving'])}"
            dis = r["reads_disagreement_moving"]
            dis = "" if dis is None else f"{100 * dis:.{1 if dis < 0.1 else 0}f} %"
            lines.append(f"| {r['label']} | {r['passes']} × {r['spp']} | {_seconds(r['wall_s'])} | {mse} | {dis} |")
    elif name == "budget":
        lines = [
            _measured_on(
                table,
                "read from its `report.json` (`render_error`: the run's own estimate, two "
                "half-sample renders per stratum, of the rendering-noise variance over the shot-noise "
                "variance of each lit, unsaturated sample of every read; each column the highest read's, "
                "named; `top_up`)",
            ),
            "",
            "| config | passes × spp | wall time | median (budget 0.1) | p95 (budget 1) | budget | top-up from | "
            "p99.9 (target 1) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            e = r["render_error"]
            head = f"| {r['label']} | {r['passes']} × {r['spp']} | {_seconds(r['wall_s'])} |"
            if e is None:
                lines.append(f"{head} not estimated | | | | |")
                continue
            top = "" if e["top_up_before"] is None else f"{e['top_up_before']:.2f}x"
            lines.append(
                f"{head} {_num(e['median'], 2)} ({e['median_read']}) | {_num(e['p95'], 2)} ({e['p95_read']}) | "
                f"{'met' if e['met'] else '**missed**'} | {top} | {_num(e['p999'], 2)} ({e['p999_read']}) |"
            )
    else:
        raise KeyError(name)
    lines.append("")
    lines.append("Commands: " + "; ".join(f"`{r['command']}`" for r in rows) + ".")
    return "\n".join(lines)


def markers(name: str) -> tuple[str, str]:
    return f"<!-- BEGIN readme_tables:{name} -->", f"<!-- END readme_tables:{name} -->"


def rewrite(text: str, name: str, table: str) -> str:
    """``text`` with everything between table ``name``'s markers replaced by ``table``."""
    begin, end = markers(name)
    pattern = re.compile(re.escape(begin) + r"\n.*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise SystemExit(f"readme_tables: no '{begin}' ... '{end}' in the README")
    return pattern.sub(lambda _: f"{begin}\n{table}\n{end}", text, count=1)


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--readme", type=Path, default=Path("README.md"), help="README to rewrite (default README.md)")
    ap.add_argument(
        "--data",
        type=Path,
        default=Path("docs/measured.json"),
        help="measured numbers, written by a run and read by --from-data/--check",
    )
    ap.add_argument(
        "--only",
        nargs="+",
        default=None,
        metavar="TABLE",
        help=f"tables to measure ({', '.join([*TABLES, 'budget'])}); the others keep their numbers",
    )
    ap.add_argument(
        "--rows",
        nargs="+",
        default=None,
        metavar="LABEL",
        help="measure only these rows of the tables measured (a config added to the budget table); the other rows "
        "keep their numbers, and the table records which rows were measured when",
    )
    ap.add_argument("--from-data", action="store_true", help="rewrite the README from --data without running anything")
    ap.add_argument("--check", action="store_true", help="exit 1 if the README's tables differ from --data")
    args = ap.parse_args(argv)

    if args.from_data or args.check:
        data = json.loads(args.data.read_text())
    else:
        # tables not measured now keep their numbers (each table carries its own machine and timing)
        data = json.loads(args.data.read_text()) if args.data.exists() else {"tables": {}}
        every = {
            **{n: [(label, config, over) for label, over in rows] for n, (config, rows) in TABLES.items()},
            "budget": budget_rows(),
        }
        for name in args.only or every:
            if name not in every:
                raise SystemExit(f"readme_tables: --only: no table {name!r} (tables: {', '.join(every)})")
            t0 = time.perf_counter()
            old = {r["label"]: r for r in data["tables"].get(name, {}).get("rows", [])}
            rows = []
            for label, config, overrides in every[name]:
                if args.rows is not None and label not in args.rows and label in old:
                    rows.append(old[label])  # measured before: kept
                    continue
                print(f"{name}: {label} ...", flush=True)
                rows.append({"label": label, **measure(config, overrides)})
            if args.rows is not None and name in data["tables"]:  # the table's own run, these rows added to it
                table = dict(data["tables"][name])
                table["rows"] = rows
                table.setdefault("rows_measured_later", []).append(
                    {"rows": list(args.rows), "machine": machine(), "date": time.strftime("%Y-%m-%d")}
                )
                data["tables"][name] = table
                tmp = args.data.with_name(f".{args.data.name}.tmp")
                tmp.write_text(json.dumps(data, indent=2) + "\n")
                os.replace(tmp, args.data)
                continue
            table = {
                "machine": f"{machine()}, {rows[0]['variant']}, LLVM {rows[0]['llvm']}",
                "seconds": round(time.perf_counter() - t0, 1),
                # other work on the machine stretches wall times
                "load_average_5min": round(os.getloadavg()[1], 2),
                "only": name,
                "empty_cache": True,
                "rows": rows,
            }
            if os.environ.get("MBCAPTURE_SET"):  # the rows are not what their labels say: make it visible
                table["mbcapture_set"] = os.environ["MBCAPTURE_SET"]
            data["tables"][name] = table
            tmp = args.data.with_name(f".{args.data.name}.tmp")
            tmp.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(data, indent=2) + "\n")
            os.replace(tmp, args.data)  # each table's numbers kept as soon as it is measured
    text = args.readme.read_text()
    new = text
    for name in data["tables"]:
        new = rewrite(new, name, render_table(name, data))
    if args.check:
        if new != text:
            print(
                f"{args.readme}: tables differ from {args.data}; run python scripts/readme_tables.py --from-data",
                file=sys.stderr,
            )
            return 1
        return 0
    tmp = args.readme.with_name(f".{args.readme.name}.tmp")
    tmp.write_text(new)
    os.replace(tmp, args.readme)  # whole or not at all
    print(f"wrote {', '.join(data['tables'])} into {args.readme} (data: {args.data})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
