"""Measure the README's tables and write them between their marker comments.

    python scripts/readme_tables.py                 # run the captures (~2-3 min on 2 cores), rewrite README.md
    python scripts/readme_tables.py --from-data     # rewrite README.md from docs/measured.json, no runs
    python scripts/readme_tables.py --check         # exit 1 if README.md differs from docs/measured.json

Each row of a table is one ``mbcapture run <config> --quiet --out <tmp> [--set ...]`` in its own
process, read back from the run's ``report.json``, so a row says what a user's own run of that
command reports (wall time: ``timings_s.total_before_write``). The numbers go to
``docs/measured.json`` (with the machine) and into README.md between
``<!-- BEGIN readme_tables:<name> -->`` and ``<!-- END readme_tables:<name> -->``; nothing
else of the README changes. ``$MBCAPTURE_SET`` reaches the runs like any ``--set`` (a quick try at
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
    "hdr": ("configs/metronome_hdr.yaml", [
        ("default: photon-efficient, 640x512, N=16", []),
        ("`capture.protocol=interleaved_hdr`", ["capture.protocol=interleaved_hdr"]),
        ("`capture.sequential=true` (conventional sensor)", ["capture.sequential=true"]),
        ("default at `render.width=160 render.height=128`", ["render.width=160", "render.height=128"]),
    ]),
}


def run_in_own_process(args: list[str]) -> None:
    """``mbcapture <args>`` in a new Python process (what a user's command costs, kernel loading included)."""
    proc = subprocess.run([sys.executable, "-m", "mbcapture", *args], capture_output=True, text=True)
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
        "wall_s": rep["timings_s"]["total_before_write"],
        "hdr_rel_mse": m.get("hdr_rel_mse"),
        "hdr_rel_mse_moving": m.get("hdr_rel_mse_moving"),
        "reads_disagreement_moving": m.get("motion_check", {}).get("max_pairwise_rel_rms"),
        "llvm": rep["versions"].get("llvm"),
        "variant": rep["versions"].get("variant"),
    }


def _num(v: float | None, digits: int = 3) -> str:
    return "" if v is None else f"{v:.{digits}g}"


def _seconds(s: float) -> str:
    return f"{s:.1f} s" if s < 10 else f"{s:.0f} s"


def render_table(name: str, data: dict) -> str:
    """The markdown of table ``name`` from its measured rows (``data`` as in docs/measured.json)."""
    if name != "hdr":
        raise KeyError(name)
    rows = data["tables"][name]
    lines = [
        f"Measured on {data['machine']} with `python scripts/readme_tables.py` ({data['seconds']:.0f} s, load "
        f"average {data['load_average_5min']:g} over its last 5 minutes: other work on the machine stretches wall "
        "times)" + (f", with $MBCAPTURE_SET={data['mbcapture_set']!r} (not the sizes the rows name)"
                    if data.get("mbcapture_set") else "") + "; "
        "each row is the `mbcapture run` below, read from its `report.json` (`timings_s.total_before_write`, "
        "`metrics`):",
        "",
        "| run | passes × spp | wall time | HDR relMSE (all / moving region) | reads' disagreement in the moving region |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        mse = "" if r["hdr_rel_mse"] is None else f"{_num(r['hdr_rel_mse'])} / {_num(r['hdr_rel_mse_moving'])}"
        dis = r["reads_disagreement_moving"]
        dis = "" if dis is None else f"{100 * dis:.{1 if dis < 0.1 else 0}f} %"
        lines.append(f"| {r['label']} | {r['passes']} × {r['spp']} | {_seconds(r['wall_s'])} | {mse} | {dis} |")
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
    ap.add_argument("--data", type=Path, default=Path("docs/measured.json"),
                    help="measured numbers, written by a run and read by --from-data/--check")
    ap.add_argument("--only", nargs="+", default=None, metavar="TABLE", help=f"tables to measure ({', '.join(TABLES)})")
    ap.add_argument("--from-data", action="store_true", help="rewrite the README from --data without running anything")
    ap.add_argument("--check", action="store_true", help="exit 1 if the README's tables differ from --data")
    args = ap.parse_args(argv)

    if args.from_data or args.check:
        data = json.loads(args.data.read_text())
    else:
        t0 = time.perf_counter()
        data = {"machine": machine(), "tables": {}}
        for name in args.only or TABLES:
            config, rows = TABLES[name]
            data["tables"][name] = []
            for label, overrides in rows:
                print(f"{name}: {label} ...", flush=True)
                data["tables"][name].append({"label": label, **measure(config, overrides)})
        first = next(iter(data["tables"].values()))[0]
        data["machine"] += f", {first['variant']}, LLVM {first['llvm']}"
        data["seconds"] = round(time.perf_counter() - t0, 1)
        data["load_average_5min"] = round(os.getloadavg()[1], 2)  # other work on the machine stretches wall times
        if os.environ.get("MBCAPTURE_SET"):  # the rows are not what their labels say: make it visible
            data["mbcapture_set"] = os.environ["MBCAPTURE_SET"]
        args.data.parent.mkdir(parents=True, exist_ok=True)
        args.data.write_text(json.dumps(data, indent=2) + "\n")
    text = args.readme.read_text()
    new = text
    for name in data["tables"]:
        new = rewrite(new, name, render_table(name, data))
    if args.check:
        if new != text:
            print(f"{args.readme}: tables differ from {args.data}; run python scripts/readme_tables.py --from-data",
                  file=sys.stderr)
            return 1
        return 0
    tmp = args.readme.with_name(f".{args.readme.name}.tmp")
    tmp.write_text(new)
    os.replace(tmp, args.readme)  # whole or not at all
    print(f"wrote {', '.join(data['tables'])} into {args.readme} (data: {args.data})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
