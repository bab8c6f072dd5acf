"""Measure how much each golden image differs between CPU targets; write tests/golden/cross_target.json.

    python scripts/golden_spread.py [--targets native,haswell,haswell-w4,skylake-avx512] [--cases A,B]
    python scripts/golden_spread.py --carry-over OLD.json

Every golden case (tests/golden_cases.py) is computed once per target, each in its own process
whose libraries compile and dispatch for that target (mbcapture.portability: Dr.Jit's vector
width and instruction set, numpy's SIMD loops, OpenBLAS's kernels, numba, OpenCV). For every
image the largest difference over all pairs of targets is kept (relative L2, samples that
differ, samples finite in one only, largest absolute difference); the golden tests allow
SAFETY times that (tests/golden_cases.py). Targets the host cannot run are left out.
Capture cases run as the golden tests run them: each sensor stage on the golden's stored input,
so the reconstruction's spread is measured on the same reads everywhere; each stage's end-to-end
reads (``sensor{i}_dn_fresh``: the sensor on that target's own renders) are measured too, for the
record (the tests compare those as counts, golden_cases.count_differences).

The file keeps the hosts the spreads were measured on: a run on another machine with the same
goldens adds its host and keeps the larger difference of each image. Takes about a minute per
target on 2 cores. Run it after ``pytest --regen-golden``; then ``--carry-over OLD`` (the committed
file before) keeps the hosts this machine is not, for the regenerated goldens too (see carry_over).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from conftest import GOLDEN_DIR, machine_description  # noqa: E402
from golden_cases import SPREAD_FILE, all_cases, compare  # noqa: E402

from mbcapture.portability import emulation_env, runnable_targets  # noqa: E402


def dump(out: Path, cases: list[str]) -> None:
    """Child process: compute the cases and save each as <out>/<case>.npz (float32, as stored)."""
    out.mkdir(parents=True, exist_ok=True)
    every = all_cases(GOLDEN_DIR)
    for name in cases:
        images = {k: np.asarray(v, np.float64 if k.endswith("_in") else np.float32) for k, v in every[name]().items()}
        np.savez(out / f"{name}.npz", **images)
        print(f"  {name}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", default="native," + ",".join(runnable_targets()))
    ap.add_argument("--cases", default=",".join(all_cases()))
    ap.add_argument("--out", type=Path, default=SPREAD_FILE)
    ap.add_argument("--dump", type=Path, help=argparse.SUPPRESS)
    ap.add_argument(
        "--carry-over",
        type=Path,
        metavar="EARLIER",
        help="measure nothing: keep EARLIER's hosts (another machine's spreads of the previous goldens) "
        "in --out, each image at the larger difference",
    )
    args = ap.parse_args()
    if args.carry_over:
        carry_over(args.out, args.carry_over)
        return
    cases = [c for c in args.cases.split(",") if c]
    if args.dump:
        dump(args.dump, cases)
        return

    targets = [t for t in args.targets.split(",") if t]
    runnable = set(runnable_targets()) | {"native"}
    skipped = [t for t in targets if t not in runnable]
    targets = [t for t in targets if t in runnable]
    if skipped:
        print(f"left out (this host cannot run them): {', '.join(skipped)}")
    with tempfile.TemporaryDirectory() as tmp:
        results: dict[str, Path] = {}
        described: dict[str, str] = {}
        for t in targets:
            env = dict(os.environ) if t == "native" else emulation_env(t)
            if t == "native":
                for k in (
                    "MBCAPTURE_LLVM_TARGET",
                    "NPY_DISABLE_CPU_FEATURES",
                    "OPENBLAS_CORETYPE",
                    "NUMBA_CPU_NAME",
                    "OPENCV_CPU_DISABLE",
                ):
                    env.pop(k, None)
            env["MBCAPTURE_CACHE_DIR"] = str(Path(tmp) / "render-cache")  # not the user's cache
            print(f"{t}:", flush=True)
            subprocess.run(
                [sys.executable, __file__, "--dump", str(Path(tmp) / t), "--cases", ",".join(cases)],
                env=env,
                cwd=ROOT,
                check=True,
            )
            probe = (
                "from mbcapture.render import ensure_llvm; ensure_llvm(); import mitsuba as mi; "
                "mi.set_variant('llvm_ad_rgb'); from mbcapture.render.llvm import apply_target_from_env, "
                "llvm_target; apply_target_from_env(); t = llvm_target(); print(t['cpu'], t['vector_width'])"
            )
            described[t] = subprocess.run(
                [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True
            ).stdout.strip()
            results[t] = Path(tmp) / t

        spread: dict[str, dict] = {}
        for case in cases:
            per_target = {t: dict(np.load(results[t] / f"{case}.npz")) for t in targets}
            names = sorted(per_target[targets[0]])
            spread[case] = {}
            for name in names:
                worst = {"rel_l2": 0.0, "flips": 0, "nonfinite": 0, "nonfinite_kind": 0, "max_abs": 0.0}
                for a, b in itertools.combinations(targets, 2):
                    d = compare(per_target[a][name], per_target[b][name])
                    worst = {k: max(worst[k], d[k]) for k in worst}
                spread[case][name] = worst

    made = {}
    for case in cases:
        path = ROOT / "tests" / "golden" / f"{case}.npz"
        if path.exists():
            with np.load(path) as data:
                made[case] = json.loads(str(data["__meta__"]))["made"] if "__meta__" in data.files else None
    host = machine_description()
    doc = {
        "about": "largest difference of each golden image between the CPU targets below, on every host "
        "listed (scripts/golden_spread.py); tests/golden_cases.py turns it into a tolerance",
        "measured": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "targets": {t: described[t] for t in targets},
        "hosts": [
            {
                "cpu": host["cpu"],
                "native_target": described.get("native"),
                "targets": targets,
                "measured": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                **({} if set(cases) == set(all_cases()) else {"cases": cases}),
            }
        ],
        "golden_made": made,
        "cases": spread,
    }
    old = json.loads(args.out.read_text()) if args.out.exists() else {"cases": {}}
    if set(cases) != set(all_cases()):  # a partial run updates its cases only
        doc["cases"] = {**old.get("cases", {}), **spread}
        doc["golden_made"] = {**old.get("golden_made", {}), **made}
    # the same goldens measured on another host: keep both, case by case
    same = [
        c
        for c in doc["cases"]
        if c in old.get("golden_made", {}) and old["golden_made"][c] == doc["golden_made"].get(c)
    ]
    merge(doc, old, same)
    write(doc, args.out)
    for case in cases:
        worst = max(spread[case].items(), key=lambda kv: kv[1]["rel_l2"])
        flips = sum(v["flips"] for v in spread[case].values())
        print(f"  {case:28s} largest relative L2 {worst[1]['rel_l2']:.2e} ({worst[0]}), samples differing {flips}")


def merge(doc: dict, old: dict, cases: list[str], *, carried: list[str] = ()) -> None:
    """Into ``doc``: ``old``'s spreads of ``cases``, each image at the larger difference of the two, and
    ``old``'s hosts for the cases ``doc`` does not measure on them; a host that counts for some cases only
    says which. ``carried``: the cases whose goldens ``old`` measured in an earlier version (the same code
    on images that have changed since), which its hosts then say."""
    if not cases:
        return
    for case in cases:
        for name, m in old.get("cases", {}).get(case, {}).items():
            cur = doc["cases"].setdefault(case, {}).setdefault(name, m)
            doc["cases"][case][name] = {k: max(cur.get(k, 0), m.get(k, 0)) for k in set(cur) | set(m)}
    # a host is its CPU and its native target: virtual machines name different CPUs alike
    # ("Intel(R) Xeon(R) Processor" was a Rocket Lake and a Sapphire Rapids). A host that measured every case
    # in doc replaces its old entry; one that measured some keeps its old entry for the others.
    measured: dict[tuple, set | None] = {}  # each host's cases in doc; None: every case
    for h in doc["hosts"]:
        key = (h.get("cpu"), h.get("native_target"))
        if "cases" not in h:
            measured[key] = None
        elif measured.get(key, set()) is not None:
            measured[key] = measured.get(key, set()) | set(h["cases"])
    for h in old.get("hosts", []):
        key = (h.get("cpu"), h.get("native_target"))
        theirs = set(h.get("cases") or old.get("cases", {})) | set(h.get("carried_over", {}).get("cases", ()))
        relevant = [c for c in cases if c in theirs]
        if key in measured:
            if measured[key] is None:
                continue
            relevant = [c for c in relevant if c not in measured[key]]
        if not relevant:
            continue
        # the cases it measured on earlier goldens than doc's: carried now, or carried before and not since measured
        before = h.get("carried_over", {}).get("their_goldens_made", {})
        made = {c: old.get("golden_made", {}).get(c) for c in relevant if c in carried}
        made.update({c: before[c] for c in relevant if c in before and before[c] != doc["golden_made"].get(c)})
        h = {k: v for k, v in h.items() if k not in ("cases", "carried_over")}
        if set(relevant) != set(doc["cases"]):
            h["cases"] = relevant
        if made:
            h["carried_over"] = {"cases": sorted(made), "their_goldens_made": made}
        doc["hosts"].append(h)
    doc["targets"] = {**old.get("targets", {}), **doc["targets"]}


def write(doc: dict, out: Path) -> None:
    tmp_out = out.with_suffix(".json.tmp")
    tmp_out.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    os.replace(tmp_out, out)
    print(f"wrote {out}")


def carry_over(out: Path, earlier: Path) -> None:
    """``--carry-over EARLIER``: keep an earlier file's hosts in ``out`` for goldens regenerated since.

    After ``pytest --regen-golden`` this host measures its own targets only. Another host's measurement
    of the previous goldens (the same code paths on images that changed, e.g. only in their render
    times) is the best evidence there is of that host's differences until it measures the new ones.
    Each image keeps the larger difference of the two, so no tolerance shrinks."""
    doc, old = json.loads(out.read_text()), json.loads(earlier.read_text())
    cases = sorted(c for c in old.get("cases", {}) if c in doc["cases"])
    changed = [c for c in cases if old.get("golden_made", {}).get(c) != doc["golden_made"].get(c)]
    merge(doc, old, cases, carried=changed)
    write(doc, out)


if __name__ == "__main__":
    main()
