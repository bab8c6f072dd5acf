"""docs/benchmarks.md is written by scripts/benchmark.py from docs/benchmarks.json: each measure's latest run with
where and how it ran. The page agrees with the record, and a run's printed lines go to the measures they name."""

from __future__ import annotations

import json
from pathlib import Path

from script_modules import load_script

ROOT = Path(__file__).resolve().parents[1]


def test_the_page_is_the_record():
    bench = load_script("benchmark")
    data = json.loads((ROOT / "docs" / "benchmarks.json").read_text())
    assert (ROOT / "docs" / "benchmarks.md").read_text() == bench.page(data), (
        "docs/benchmarks.md is stale: run `python scripts/benchmark.py --write-docs`"
    )
    for entry in data.values():  # every entry says where, when and how it was measured
        assert {"date", "cpu", "cores", "commit", "command", "lines"} <= entry.keys()
        assert entry["command"].startswith("python scripts/benchmark.py")


def test_printed_lines_go_to_their_measures_and_a_new_run_replaces_only_its_own(tmp_path):
    bench = load_script("benchmark")
    text = (
        "[7] 320x256: run 9.1 s, sweep 13.2 s\n    in the sweep: the rest\nfilm 160x128, spp 16\n"
        "[1] periods 4: 1.0 s; ratio 1.01\n[2] ratio 1.18\n    and more\n"
    )
    lines = bench.by_measure(text)
    assert lines == {
        7: ["[7] 320x256: run 9.1 s, sweep 13.2 s", "    in the sweep: the rest"],
        1: ["[1] periods 4: 1.0 s; ratio 1.01"],
        2: ["[2] ratio 1.18", "    and more"],
    }
    path = tmp_path / "record.json"
    where = bench.machine()
    assert where["cores"] >= 1 and where["commit"] and where["date"][:2] == "20"
    bench.record(lines, "python scripts/benchmark.py --only 1,2,7", where, path)
    data = bench.record({2: ["[2] ratio 1.05"]}, "python scripts/benchmark.py --only 2", where, path)
    assert data["2"]["lines"] == ["[2] ratio 1.05"] and data["2"]["command"].endswith("--only 2")
    assert data["7"]["lines"][0].startswith("[7]") and list(data) == ["1", "2", "7"]
    md = bench.page(data)
    assert (
        "[2] ratio 1.05" in md
        and "ratio 1.18" not in md
        and "Not recorded yet: `python scripts/benchmark.py --only 4`" in md
    )
