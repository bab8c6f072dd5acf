"""Benchmarks that print ratios measured within one run (the machines are shared and noisy).

    python scripts/benchmark.py [--width 160 --height 128 --spp 16]
    python scripts/benchmark.py --only 7 --sweep-film 640x512
    python scripts/benchmark.py --write-docs      # docs/benchmarks.md from docs/benchmarks.json, nothing run

Each measure's printed lines are also recorded in docs/benchmarks.json with the date, the CPU, its cores, the
commit and the command (a measure run again replaces its entry: older results are in git history), and
docs/benchmarks.md is written from that file (--no-record: print only).

1. Cost against interleaving frequency: the metronome HDR capture at capture.periods 4 and
   1024 (the ratio of wall times; a per-slot renderer would scale with the 256x more slots).
2. Overhead of the pipeline's rendering over raw ``mi.render`` ('path' integrator) of the same
   number of passes and samples (the per-group integrator splits 2 groups into their own
   channels, which 'path' cannot do), and the same at equal error: the per-pixel variance of
   each over 4 seeds (the per-group integrator estimates direct light from every emitter at each
   vertex, 'path' from one chosen at random); and what the scene's guides cost per sample
   (render.guide_fraction: the same render with and without them).
3. Sensor + reconstruction share of the total run time at the chosen film (4 buckets).
4. Equal-error speed-up over naive per-slot rendering at capture.periods 64: the naive
   baseline (one render per slot, spp per slot in --naive-spp) against the planner's ladder
   (--ladder), both measured against a high-spp fine-strata reference (mbcapture.studies.converge);
   the planner's time at the naive point's error is interpolated on its log-log ladder.
5. The noise budget and the render cache (`make capture`'s config at --budget-film, default
   640x512, with its adaptive sampling): the capture with an empty cache (targets: within the budget, at most 3 minutes on
   2 cores), the same again with a sensor change (target: at most 15 s, zero passes rendered),
   and the cost split of each (renders rendered / reused, render seconds / the rest). Against it,
   in the same run: the same capture by the code whose budget judged buckets (BUCKET_BUDGET_COMMIT,
   pilot included: issue 26's baseline, target: no more time; both with an empty render cache of their
   own; --budget-pairs N times N such pairs in alternating order and prints the ratio of the medians),
   and today's code at that budget's samples without a pilot (what the reads' extra samples cost).
6. What meeting the budget costs with each sampler and estimator (--compare-film, default
   160x128): samples chosen, wall time and the measured Monte Carlo / shot-noise ratio, then a
   second capture of the same scene with another protocol (interleaved_hdr) on the warm cache.
7. A 64-point sensor sweep against one capture (--sweep-film, default 320x256): `mbcapture sweep
   sensor_noise` (read noise x full well x f-number, one render group; where the sweep chooses to run it,
   or on a local Dask cluster of --sweep-workers processes) against `mbcapture run` of its first point, each in its own process with
   an empty render cache (target: at most 1.5x), and where the sweep's time goes.
8. 2 workers against 1 on a render-bound sweep (--sweep-film): 4 seeds of the default capture at
   render.spp 32, each its own render group, `mbcapture sweep --workers 1` and `--workers 2`, each
   with an empty render cache.
9. A sensor of real size: configs/sensor_12mp.yaml (4096x3072) at --big-spp samples per stratum and
   strata of --big-motion-px pixels of motion (2: about 11 strata instead of 41; memory does not
   depend on the strata, time does), render cache off, outputs written, each run in a fresh process: untiled (render.tiles 1), in
   --big-tiles tiles (default 12: one per render band), and so tiled on a local Dask cluster of 1
   and of 2 workers. Prints each run's peak resident memory (this process's; the workers' are
   their own) against the plan, its wall time, the render's samples per second per core, and the
   speed-ups of the workers over the tiled local run.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import re
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from mbcapture import load_config, run_capture

ROOT = Path(__file__).resolve().parents[1]
#: [5] The samples per stratum the noise budget chose for the default capture at 640x512 when it judged
#: buckets rather than reads (7 x 128-160 spp, README): their middle, for the same code at those samples.
BUCKET_BUDGET_SPP = 144
#: [5] The last commit whose noise budget judged buckets (the next, 0b8dee6, judges reads): issue 26's
#: "today's 117 s for the weaker bucket budget" is its default capture, pilot included, which [5] times
#: again beside today's (``git archive`` of it, run with this environment's packages).
BUCKET_BUDGET_COMMIT = "d6127d5990b92553280f8bfc9d3bb47f28523980"


def timed_capture(overrides: list[str]) -> tuple[float, dict]:
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", ["render.cache=off", *overrides])
    t0 = time.perf_counter()
    result = run_capture(cfg, progress=False)
    return time.perf_counter() - t0, result.report


def equal_error(args) -> None:
    from mbcapture.studies.converge import run_converge, write_outputs

    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml",
        [f"render.width={args.width}", f"render.height={args.height}", "capture.periods=64"],
    )
    res = run_converge(
        cfg,
        tuple(int(x) for x in args.ladder.split(",")),
        tuple(int(x) for x in args.naive_spp.split(",")),
        ref_spp=args.ref_spp,
    )
    out = ROOT / "out" / "benchmark_converge"
    write_outputs(res, out)
    for p in res["points"]:
        print(
            f"    {p['method']:6s} spp {p['spp']:4d}: {p['passes']:4d} passes {p['seconds']:8.2f} s  error {p['error']:.3e}"
        )
    for s in res["speedups"]:
        print(
            f"[4] equal error {s['error']:.3e}: naive {s['naive_s']:.2f} s ({s['naive_spp']} spp per slot) vs planner "
            f"{s['planner_s']:.2f} s: speed-up {s['speedup']:.1f}x{' (extrapolated)' if s['extrapolated'] else ''} "
            f"(target >= 20x); slopes {res['slopes']}; plot {out}/converge.png"
        )


def _budget_line(report: dict) -> str:
    e = report["render_error"]
    b = e.get("budget", {})
    adaptive = report.get("adaptive") or {}
    refined = f"; adaptive sampling refined {adaptive['pixels']} pixels" if adaptive.get("pixels") else ""
    return (
        f"Monte Carlo / shot variance median {e.get('to_shot_noise_variance_median', float('nan')):.3g}, "
        f"p95 {e.get('to_shot_noise_variance_p95', float('nan')):.3g}: {'within' if b.get('met') else 'NOT within'} "
        f"the budget ({b.get('median_target')} / {b.get('p95_target')}); tail (p99.9) "
        f"{e.get('to_shot_noise_variance_p999', float('nan')):.3g}: {'within' if b.get('tail_met') else 'NOT within'} "
        f"its target {b.get('tail_target')}{refined}"
    )


def _split(seconds: float, report: dict) -> str:
    c, t = report["render_cache"], report["timings_s"]
    render = t.get("render", 0.0) + t.get("pilot", 0.0)
    return (
        f"{c['rendered']} renders rendered, {c['hits']} reused; render + pilot {render:.1f} s, "
        f"the rest {seconds - render:.1f} s"
    )


def budget_and_cache(args) -> None:
    import tempfile

    w, h = (int(x) for x in args.budget_film.split("x"))
    with tempfile.TemporaryDirectory() as cache:
        film = [f"render.width={w}", f"render.height={h}", f"render.cache={cache}"]
        t_cold, cold = timed_capture(film)
        print(
            f"[5] {w}x{h}, empty cache: {t_cold:.1f} s (target <= 180 s), {cold['plan']['passes']} passes x "
            f"{cold['plan']['spp_range']} spp; {_budget_line(cold)}"
        )
        print(f"    cost split: {_split(t_cold, cold)}")
        # the baseline: the default capture of the code whose budget judged buckets, pilot included
        t_old = bucket_budget_capture(w, h)
        if t_old is not None:
            print(
                f"[5] the bucket budget's code ({BUCKET_BUDGET_COMMIT[:7]}), the same capture cold in this run: "
                f"{t_old[0]:.1f} s ({t_old[1]}); today's over it: {t_cold / t_old[0]:.2f}x (target <= 1)"
            )
            if args.budget_pairs > 1:
                budget_pairs(args.budget_pairs, w, h, (t_cold, t_old[0]))
        # the same code at the samples the bucket budget chose (their middle), without a pilot: what the reads'
        # extra samples cost
        with tempfile.TemporaryDirectory() as cache_b:
            t_bucket, bucket = timed_capture(
                [
                    f"render.width={w}",
                    f"render.height={h}",
                    f"render.cache={cache_b}",
                    f"render.spp={BUCKET_BUDGET_SPP}",
                ]
            )
        print(
            f"[5] today's code at the bucket budget's samples without a pilot (render.spp={BUCKET_BUDGET_SPP}, "
            f"empty cache): {t_bucket:.1f} s; the read budget over it: {t_cold / t_bucket:.2f}x"
        )
        t_warm, warm = timed_capture([*film, "sensor.read_noise_e=5"])
        print(
            f"[5] the same with sensor.read_noise_e=5: {t_warm:.1f} s (target <= 15 s), "
            f"{warm['render_cache']['rendered']} renders rendered (target 0); ratio warm / cold {t_warm / t_cold:.3f}"
        )
        print(f"    cost split: {_split(t_warm, warm)}")


def budget_pairs(n: int, w: int, h: int, first: tuple[float, float]) -> None:
    """[5] with --budget-pairs n: n pairs of (today's capture, the bucket budget's) cold, the first being the
    pair above, the order alternating (today's first in even pairs, the old code's first in odd ones: a
    machine that slows or speeds up during the run then tilts the pairs both ways); prints each pair's
    ratio and the ratio of the medians."""
    import tempfile

    pairs = [first]
    for i in range(1, n):
        with tempfile.TemporaryDirectory() as cache:

            def today() -> float:
                return timed_capture([f"render.width={w}", f"render.height={h}", f"render.cache={cache}"])[0]

            if i % 2:
                t_old = bucket_budget_capture(w, h)
                t_new = today()
            else:
                t_new = today()
                t_old = bucket_budget_capture(w, h)
        if t_old is None:
            return
        pairs.append((t_new, t_old[0]))
        print(
            f"[5] pair {i + 1} ({'old' if i % 2 else 'today'}'s first): today's {t_new:.1f} s, the bucket "
            f"budget's {t_old[0]:.1f} s: {t_new / t_old[0]:.2f}x"
        )
    new, old = np.median([p[0] for p in pairs]), np.median([p[1] for p in pairs])
    print(
        f"[5] {n} pairs, order alternating: today's median {new:.1f} s, the bucket budget's {old:.1f} s: "
        f"{new / old:.2f}x (target <= 1); the pairs' ratios {', '.join(f'{a / b:.2f}' for a, b in pairs)}"
    )


def bucket_budget_capture(w: int, h: int) -> tuple[float, str] | None:
    """The default capture at ``w`` x ``h`` by :data:`BUCKET_BUDGET_COMMIT`'s code, in a child process with
    this environment's packages, an empty render cache of its own like today's cold capture (both write their
    renders to it, as the default capture does): (wall seconds of ``run_capture``, its samples); None,
    with a line saying why, where the commit is not in this clone (a shallow one) or its capture fails."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryDirectory() as cache:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", BUCKET_BUDGET_COMMIT], capture_output=True)
        if archive.returncode != 0:
            print(
                f"[5] the bucket budget's code: not timed (git archive {BUCKET_BUDGET_COMMIT[:7]}: "
                f"{archive.stderr.decode(errors='replace').strip() or 'failed'})"
            )
            return None
        subprocess.run(["tar", "-x", "-C", tmp], input=archive.stdout, check=True)
        code = (
            "import json, time\n"
            "from mbcapture import load_config, run_capture\n"
            f"cfg = load_config('configs/metronome_hdr.yaml', ['render.width={w}', 'render.height={h}', "
            f"'render.cache={cache}'])\n"
            "t0 = time.perf_counter()\n"
            "r = run_capture(cfg, progress=False)\n"
            "plan = r.report['plan']\n"
            "print(json.dumps([time.perf_counter() - t0, plan['passes'], plan.get('spp_range', plan['spp'])]))\n"
        )
        env = {**os.environ, "PYTHONPATH": tmp}
        run = subprocess.run([sys.executable, "-c", code], cwd=tmp, env=env, capture_output=True, text=True)
        if run.returncode != 0:
            print(f"[5] the bucket budget's code: its capture failed ({run.stderr.strip().splitlines()[-1:]})")
            return None
        seconds, passes, spp = json.loads(run.stdout.strip().splitlines()[-1])
        spp = spp if isinstance(spp, list) else [spp]
        return seconds, f"{passes} passes x {min(spp)}-{max(spp)} spp"


def compare(args) -> None:
    import tempfile

    w, h = (int(x) for x in args.compare_film.split("x"))
    rows = [
        ("independent", "independent"),
        ("multijitter", "independent"),
        ("ldsampler", "independent"),
        ("multijitter", "difference"),
    ]
    for sampler, estimator in rows:
        with tempfile.TemporaryDirectory() as cache:
            film = [
                f"render.width={w}",
                f"render.height={h}",
                f"render.cache={cache}",
                f"render.sampler={sampler}",
                f"render.estimator={estimator}",
            ]
            t1, r1 = timed_capture(film)
            t2, r2 = timed_capture([*film, "capture.protocol=interleaved_hdr"])
            p = r1["plan"]
            print(
                f"[6] {sampler:11s} {estimator:11s}: spp {p['spp_range']}"
                f"{' + base ' + str(p['base_spp']) if p.get('base_spp') else ''}, {t1:.1f} s; {_budget_line(r1)}; "
                f"then interleaved_hdr on the warm cache {t2:.1f} s ({r2['render_cache']['hits']} renders reused, "
                f"{r2['render_cache']['rendered']} rendered)"
            )


def _timed_command(args: list[str]) -> float:
    import subprocess
    import sys

    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mbcapture", *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def sweep_cost(args) -> None:
    import tempfile

    import pandas as pd
    import yaml

    from mbcapture.sweep import load_sweep

    w, h = (int(x) for x in args.sweep_film.split("x"))
    film = ["--set", f"render.width={w}", "--set", f"render.height={h}"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        first = load_sweep("sensor_noise", [f"render.width={w}", f"render.height={h}"]).points[0]
        data = first.config.to_yaml_dict()
        data["render"]["cache"] = str(tmp / "cache_run")
        (tmp / "first.yaml").write_text(yaml.safe_dump(data))
        t_run = _timed_command(["run", str(tmp / "first.yaml"), "--quiet", "--out", str(tmp / "run")])
        where = ["--workers", str(args.sweep_workers)] if args.sweep_workers else []  # none: the sweep's own choice
        t_sweep = _timed_command(
            [
                "sweep",
                "sensor_noise",
                *film,
                "--set",
                f"render.cache={tmp / 'cache_sweep'}",
                *where,
                "--out",
                str(tmp / "sweep"),
                "--quiet",
            ]
        )
        table = pd.read_parquet(tmp / "sweep" / "results.parquet")
        summary = json.loads((tmp / "sweep" / "sweep.json").read_text())["summary"]
        report = json.loads((tmp / "run" / "report.json").read_text())
    lead = table[~table["render_shared"].astype(bool)]
    rest = table[table["render_shared"].astype(bool)]
    print(
        f"[7] {w}x{h}: `mbcapture run` of the sweep's first point {t_run:.1f} s ({report['plan']['passes']} passes x "
        f"{report['plan']['spp']} spp, capture {report['timings_s']['total_before_write']:.1f} s of it); "
        f"`mbcapture sweep sensor_noise` ({len(table)} points, {summary['render_groups']} render group, "
        f"{summary['executor']}) {t_sweep:.1f} s: ratio {t_sweep / t_run:.2f} (target <= 1.5)"
    )
    print(
        f"    in the sweep: the group's first point {lead['seconds'].sum():.1f} s ({summary['renders_rendered']} renders "
        f"rendered), the other {len(rest)} points {rest['seconds'].mean():.2f} s each (sensor "
        f"{rest['timings_s.sensor'].mean():.2f} s, reconstruct {rest['timings_s.reconstruct'].mean():.2f} s), "
        f"{rest['seconds'].sum():.1f} s in all over the workers; the rest (start, cluster, planning, results) "
        f"{t_sweep - summary['wall_s']:.1f} s outside the sweep's own {summary['wall_s']:.1f} s"
    )


def sweep_workers(args) -> None:
    import tempfile

    import yaml

    w, h = (int(x) for x in args.sweep_film.split("x"))
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        spec = {
            "base": "metronome_hdr",
            "set": {"render.width": w, "render.height": h, "render.spp": 32},
            "axes": {"grid": {"seed": [0, 1, 2, 3]}},
            "keep": "none",
        }
        (tmp / "seeds.yaml").write_text(yaml.safe_dump(spec))
        for n in (1, 2):
            times[n] = _timed_command(
                [
                    "sweep",
                    str(tmp / "seeds.yaml"),
                    "--set",
                    f"render.cache={tmp / f'cache{n}'}",
                    "--workers",
                    str(n),
                    "--out",
                    str(tmp / f"out{n}"),
                    "--quiet",
                ]
            )
    print(
        f"[8] {w}x{h}, 4 seeds at 32 spp (4 render groups): 1 worker {times[1]:.1f} s, 2 workers {times[2]:.1f} s: "
        f"speed-up {times[1] / times[2]:.2f}x"
    )


def _child_capture(sets: list[str], workers: int | None) -> dict:
    """One capture of configs/sensor_12mp.yaml in a fresh process, outputs written: wall seconds, peak
    resident memory (VmHWM), planned memory, tiles, render seconds and samples rendered."""
    import subprocess
    import sys
    import tempfile

    child = """
import json, sys, tempfile, time
from mbcapture import load_config, run_capture
from mbcapture.exposure.cluster import start_client
from mbcapture.exposure.resources import peak_rss_bytes
cfg = load_config(sys.argv[1], sys.argv[4:])
workers = int(sys.argv[3])
client = start_client(workers) if workers else None
t0 = time.perf_counter()
r = run_capture(cfg, sys.argv[2], progress=False, client=client)
wall = time.perf_counter() - t0
rep = r.report
print(json.dumps({"wall_s": wall, "peak_bytes": peak_rss_bytes(), "planned_gb": rep["resources"]["peak_memory_gb"],
                  "tiles": rep["tiles"]["count"], "render_s": rep["timings_s"].get("render", 0.0)
                  + rep["timings_s"].get("cluster", 0.0), "samples": cfg.render.width * cfg.render.height
                  * sum(s["spp"] for s in rep["plan"]["strata"])}))
"""
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run(
            [
                sys.executable,
                "-c",
                child,
                str(ROOT / "configs" / "sensor_12mp.yaml"),
                str(Path(tmp) / "out"),
                str(workers or 0),
                *sets,
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
    if proc.returncode != 0:
        raise SystemExit(f"[9] {' '.join(sets)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def big_sensor(args) -> None:
    from mbcapture.exposure.cluster import usable_cores

    base = [f"render.spp={args.big_spp}", "render.cache=off", f"render.max_motion_px={args.big_motion_px}"]
    tiled = [*base, f"render.tiles={args.big_tiles}"]
    runs = {"untiled": _child_capture([*base, "render.tiles=1"], None), "tiled": _child_capture(tiled, None)}
    for n in (1, 2):
        runs[f"tiled, {n} worker{'s' * (n > 1)}"] = _child_capture(tiled, n)
    cores = usable_cores()
    for name, r in runs.items():
        rate = r["samples"] / max(r["render_s"], 1e-9) / cores
        print(
            f"[9] 4096x3072, {args.big_spp} spp, strata of {args.big_motion_px} px, {name}: {r['tiles']} tiles, peak memory "
            f"{r['peak_bytes'] / 2**30:.2f} GiB (planned {r['planned_gb']:.2f} GB, ratio "
            f"{r['peak_bytes'] / 2**30 / r['planned_gb']:.2f}), {r['wall_s']:.0f} s, render "
            f"{rate / 1e6:.2f} M samples/s per core ({cores} cores)"
        )
    t = runs["tiled"]["wall_s"]
    print(
        f"[9] speed-up over the tiled run here: 1 worker {t / runs['tiled, 1 worker']['wall_s']:.2f}x, "
        f"2 workers {t / runs['tiled, 2 workers']['wall_s']:.2f}x; tiled / untiled peak memory "
        f"{runs['tiled']['peak_bytes'] / runs['untiled']['peak_bytes']:.2f}"
    )


#: Each measure's name in docs/benchmarks.md (the docstring above says what it does and its target).
TITLES = {
    1: "Cost against interleaving frequency (capture.periods 1024 over 4)",
    2: "The pipeline's rendering against Mitsuba's 'path', at equal samples and at equal error",
    3: "The sensor stage's and the reconstruction's share of a run",
    4: "Equal-error speed-up over naive per-slot rendering",
    5: "The noise budget and the render cache (the default capture, cold and warm)",
    6: "Meeting the budget with each sampler and estimator",
    7: "A 64-point sensor sweep against one capture",
    8: "2 sweep workers against 1 on a render-bound sweep",
    9: "A 4096x3072 sensor: memory and time, tiled and on a cluster",
}
RECORD = ROOT / "docs" / "benchmarks.json"
PAGE = ROOT / "docs" / "benchmarks.md"


class _Tee(io.TextIOBase):
    """Writes to the terminal and keeps a copy (the measures' printed lines)."""

    def __init__(self, out):
        self.out, self.kept = out, io.StringIO()

    def write(self, text: str) -> int:
        self.kept.write(text)
        return self.out.write(text)

    def flush(self) -> None:
        self.out.flush()


def by_measure(text: str) -> dict[int, list[str]]:
    """The printed lines of a run, per measure: a line starting ``[n]`` is measure n's, an indented line
    belongs to the measure before it, anything else (film and versions) to none."""
    out: dict[int, list[str]] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"\[(\d+)\]", line)
        if m:
            current = int(m.group(1))
        elif not line.startswith(" "):
            current = None
        if current is not None and line.strip():
            out.setdefault(current, []).append(line.rstrip())
    return out


def machine() -> dict:
    """Where a measure ran: the date (UTC), the CPU model, its cores and the commit (with a mark when the tree
    differs from it)."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        names = [
            ln.split(":", 1)[1].strip()
            for ln in Path("/proc/cpuinfo").read_text().splitlines()
            if ln.startswith("model name")
        ]
        cpu = names[0] if names else cpu

    def git(*args: str) -> str:
        run = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return run.stdout.strip() if run.returncode == 0 else ""

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    changed = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines()]
    if any(f not in ("docs/benchmarks.json", "docs/benchmarks.md") for f in changed):  # the record is output
        commit += " (with uncommitted changes)"
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "commit": commit,
    }


def record(lines: dict[int, list[str]], command: str, where: dict, path: Path = RECORD) -> dict:
    """Each measure's ``lines`` into the record at ``path`` (replacing that measure's older entry), with
    ``where`` (:func:`machine`, taken when the run started: the code it measured); returns the record."""
    data = json.loads(path.read_text()) if path.is_file() else {}
    for n, text in lines.items():
        data[str(n)] = {**where, "command": command, "lines": text}
    path.write_text(json.dumps(dict(sorted(data.items(), key=lambda kv: int(kv[0]))), indent=1) + "\n")
    return data


def page(data: dict) -> str:
    """docs/benchmarks.md from the record: each measure's latest run, where and how it ran, what it printed."""
    out = [
        "# Benchmarks",
        "",
        "Written by `python scripts/benchmark.py` from `docs/benchmarks.json`: the latest run of each measure,",
        "ratios measured within one run (the machines are shared and noisy). What each measure does and its",
        "target are in the script's docstring; older runs are in git history. Run a measure again to replace",
        "its entry; `--write-docs` rewrites this page from the record without running anything.",
        "",
    ]
    for n, title in TITLES.items():
        out += [f"## [{n}] {title}", ""]
        entry = data.get(str(n))
        if entry is None:
            out += [f"Not recorded yet: `python scripts/benchmark.py --only {n}`.", ""]
            continue
        out += [
            f"{entry['date']}, {entry['cpu']}, {entry['cores']} cores, commit {entry['commit']}: `{entry['command']}`",
            "",
            "```text",
            *entry["lines"],
            "```",
            "",
        ]
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each configuration; the fastest counts")
    ap.add_argument("--ladder", default="2,4,8,16,32,64,128", help="[4] planner spp ladder")
    ap.add_argument("--naive-spp", default="1,2", help="[4] naive spp per slot")
    ap.add_argument("--ref-spp", type=int, default=256, help="[4] reference spp")
    ap.add_argument("--budget-film", default="640x512", help="[5] film, WxH")
    ap.add_argument(
        "--budget-pairs",
        type=int,
        default=1,
        help="[5] pairs of (today's capture, the bucket budget's) in alternating order; their medians' ratio",
    )
    ap.add_argument("--compare-film", default="160x128", help="[6] film, WxH")
    ap.add_argument("--sweep-film", default="320x256", help="[7], [8] film, WxH")
    ap.add_argument(
        "--sweep-workers",
        type=int,
        default=None,
        help="[7] local Dask workers (default: none given, the sweep chooses: this process for one render set)",
    )
    ap.add_argument("--big-spp", type=int, default=2, help="[9] samples per stratum at 4096x3072")
    ap.add_argument("--big-motion-px", type=float, default=2.0, help="[9] render.max_motion_px at 4096x3072")
    ap.add_argument("--big-tiles", type=int, default=12, help="[9] render.tiles of the tiled runs")
    ap.add_argument("--only", default="1,2,3,4,5,6,7,8", help="which benchmarks to run, e.g. 4 ([9] only when named)")
    ap.add_argument("--no-record", action="store_true", help="print only: leave docs/benchmarks.json and .md alone")
    ap.add_argument(
        "--write-docs", action="store_true", help="write docs/benchmarks.md from docs/benchmarks.json, run nothing"
    )
    args = ap.parse_args()
    if args.write_docs:
        PAGE.write_text(page(json.loads(RECORD.read_text()) if RECORD.is_file() else {}))
        return
    where = machine()  # the code measured is the code at the start
    tee = _Tee(sys.stdout)
    try:
        with contextlib.redirect_stdout(tee):
            measure(args)
    finally:  # what finished is recorded even when a later measure fails
        if not args.no_record:
            lines = by_measure(tee.kept.getvalue())
            if lines:
                PAGE.write_text(page(record(lines, "python scripts/benchmark.py " + " ".join(sys.argv[1:]), where)))


def measure(args) -> None:
    """Run the measures ``args.only`` names, printing their results."""
    only = {int(x) for x in args.only.split(",")}
    if 9 in only:
        big_sensor(args)
    if 7 in only:
        sweep_cost(args)
    if 8 in only:
        sweep_workers(args)
    if 5 in only:
        budget_and_cache(args)
    if 6 in only:
        compare(args)
    if 4 in only:
        equal_error(args)
    if not only & {1, 2, 3}:
        return
    film = [f"render.width={args.width}", f"render.height={args.height}", f"render.spp={args.spp}"]
    timed_capture(film + ["capture.periods=4"])  # warm-up: kernel compilation, imports
    # alternate the two and keep the fastest of each: the machine is shared and noisy
    runs = {4: [], 1024: []}
    for _ in range(args.repeats):
        for periods in runs:
            runs[periods].append(timed_capture(film + [f"capture.periods={periods}"]))
    t4, r4 = min(runs[4], key=lambda x: x[0])
    t1024, r1024 = min(runs[1024], key=lambda x: x[0])
    print(
        f"[1] periods 4: {t4:.2f} s ({r4['plan']['passes']} passes); periods 1024: {t1024:.2f} s "
        f"({r1024['plan']['passes']} passes); ratio {t1024 / t4:.3f} (target <= 1.2; slots grew 256x)"
    )

    # [2] raw mi.render of the same passes x spp, through the same scene object
    from mbcapture.scene import scenes
    from mbcapture.render import Renderer

    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", film)
    scene = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    renderer = Renderer.from_config(scene, cfg)
    times = [s["render_times_s"][0] for s in r4["plan"]["strata"]]
    renderer.render_path(times[0], args.spp, 0)  # warm-up compile
    raw = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for i, t in enumerate(times):
            renderer.render_path(t, args.spp, i)
        raw.append(time.perf_counter() - t0)
    t_raw = min(raw)
    t_pipe = r4["timings_s"]["render"] + r4["timings_s"]["accumulate"]
    print(
        f"[2] pipeline render+accumulate {t_pipe:.2f} s (render {r4['timings_s']['render']:.2f} s, accumulate "
        f"{r4['timings_s']['accumulate']:.2f} s) vs raw mi.render 'path' {t_raw:.2f} s for "
        f"{len(times)} passes x {args.spp} spp: ratio {t_pipe / t_raw:.2f} (target <= 1.25)"
    )
    # the same samples buy different errors: the per-group integrator estimates direct light from every
    # emitter at each vertex, 'path' from one chosen at random. Per-pixel variance over 4 seeds of the same
    # image (every group summed, against 'path' with every group on), at the middle stratum's time
    t_mid = times[len(times) // 2]
    ours = np.stack([renderer.render(t_mid, args.spp, 1000 + s).sum(axis=0) for s in range(4)]).astype(np.float64)
    path = np.stack([renderer.render_path(t_mid, args.spp, 2000 + s) for s in range(4)]).astype(np.float64)
    lit = path.mean(axis=0) > 1e-3 * path.mean(axis=0).max()
    v_ours, v_path = ours.var(axis=0, ddof=1)[lit], path.var(axis=0, ddof=1)[lit]
    rel = lambda v, a: float(np.median(v / a.mean(axis=0)[lit] ** 2))  # noqa: E731
    mean_gain, median_gain = v_path.mean() / v_ours.mean(), rel(v_path, path) / rel(v_ours, ours)
    print(
        f"[2] at equal samples 'path' has {mean_gain:.2f}x the per-group integrator's variance over the lit samples "
        f"(mean) and {median_gain:.1f}x at the median sample (relative variance); the cost at equal error, "
        f"pipeline over 'path': {t_pipe / t_raw / mean_gain:.2f} (mean variance), "
        f"{t_pipe / t_raw / median_gain:.2f} (median)"
    )

    # what the guides cost per sample (render.guide_fraction, the scene's guides): the same render with and
    # without them, alternating, the fastest of each (the pipeline's figures above include them)
    if renderer.guide_fraction:
        guided = renderer._integrator.guides
        best = {"guided": float("inf"), "plain": float("inf")}
        for _ in range(max(args.repeats, 3)):
            for name, guides in (("plain", ()), ("guided", guided)):
                renderer._integrator.guides = guides
                t0 = time.perf_counter()
                renderer.render(t_mid, 4 * args.spp, 1)
                best[name] = min(best[name], time.perf_counter() - t0)
        renderer._integrator.guides = guided
        print(
            f"[2] guides (render.guide_fraction {renderer.guide_fraction:.3g}): a render {best['guided']:.2f} s with them, "
            f"{best['plain']:.2f} s without: {best['guided'] / best['plain']:.3f}x"
        )

    stages = r4["timings_s"]
    share = (stages["sensor"] + stages["reconstruct"]) / stages["total_before_write"]
    print(
        f"[3] sensor {stages['sensor']:.3f} s + reconstruct {stages['reconstruct']:.3f} s of "
        f"{stages['total_before_write']:.2f} s total: {100 * share:.1f} % (target <= 10 %)"
    )
    print(f"film {args.width}x{args.height}, spp {args.spp}, numpy {np.__version__}")


if __name__ == "__main__":
    main()
