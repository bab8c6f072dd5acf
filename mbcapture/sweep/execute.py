"""Running a sweep's points: on Dask (a LocalCluster here, or an existing cluster), or in this process.

Each render group (:mod:`.groups`) becomes a small task graph: its first pending point (the
leader) runs a whole capture, renders through the render cache and returns its render stage
(:class:`mbcapture.capture.pipeline.Rendered`); every other point of the group is a task that depends on
the leader and runs the capture from the leader's render stage (sensor, reconstruction, metrics).
Dask moves the leader's arrays to whichever worker runs a follower and frees them when the last
one is done. Render groups run in parallel on different workers.

Dr.Jit renders with its own thread pool (one thread per core by default), so a worker process per
core would oversubscribe the machine. Each task sets its process's Dr.Jit thread count: a leader
gets the cores of its host divided by the number of leaders that can run there at once (one
render group: all the cores), a follower (numpy) cores / workers, which the sensor's inversions
use too. Every worker picks its libLLVM (:func:`mbcapture.render.llvm.ensure_llvm`) before Mitsuba
is imported (:func:`mbcapture.exposure.cluster.prepare_worker`).

A point that fails (an exception in its capture, a worker lost) becomes a row with its error;
the sweep goes on. Finished points are written to ``rows/<point id>.json`` as they arrive, so an
interrupted sweep loses nothing, and ``--resume`` skips them.
"""

from __future__ import annotations

import os
import socket
import time
import traceback
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..capture.run import run_capture, write_outputs
from ..exposure.cluster import drjit_threads, prepare_worker, start_client, topology, usable_cores  # noqa: F401  (sweep API)
from ..config import config_from_dict
from ..errors import one_line
from ..output.io import staged_outputs
from ..metrics import flat_items
from ..sensor.sampling import keep_sensor_work
from .groups import SweepPlan
from .spec import Point, Sweep

#: Folder names inside the sweep's output folder.
ROWS_DIR = "rows"
POINTS_DIR = "points"


# ------------------------------------------------------------------------------------ worker side
def flatten(data: Any, prefix: str) -> dict[str, Any]:
    """Scalars (numbers, booleans, strings, None) of nested dicts as ``{'a.b.c': value}``; lists are left out."""
    out: dict[str, Any] = {}
    for key, v in flat_items(data, prefix):
        if isinstance(v, (bool, int, float, str)) or v is None:
            out[key] = v
        elif hasattr(v, "item") and getattr(v, "ndim", 1) == 0:  # a numpy scalar
            out[key] = v.item()
    return out


def measurements(report: dict) -> dict[str, Any]:
    """A row's measured columns from a capture's report.json: every scalar metric, the rendering
    error, the render plan's size, the render cache's reuse and the timings."""
    plan = report.get("plan", {})
    cache = report.get("render_cache", {})
    return {
        "capture_span_s": report.get("capture_span_s"),
        "passes": plan.get("passes"),
        "spp_total": plan.get("samples_per_pixel_total"),
        "renders_rendered": cache.get("rendered", 0),
        "renders_reused": cache.get("hits", 0),
        **flatten(report.get("metrics", {}), "metrics"),
        **{
            k: v
            for k, v in flatten(report.get("render_error", {}), "render_error").items()
            if not k.startswith("render_error.method")
        },
        **flatten(report.get("timings_s", {}), "timings_s"),
    }


def write_point(result, folder: Path, keep: str) -> None:
    """A point's own outputs (``keep``: report, images or all), atomically."""

    if keep == "report":
        with staged_outputs(folder) as st:
            st.write_yaml("config.yaml", result.config.to_yaml_dict())
            st.write_json("report.json", result.report)
    elif keep in ("images", "all"):
        write_outputs(result, folder, raw=keep == "all")


def run_point(task: dict, leader: dict | None = None, *after: Any, keep_result: bool = False) -> dict:
    """Run one sweep point in this process. ``task``: from :func:`make_task`; ``leader``: what the
    first point of its render group returned (its render stage is used instead of rendering);
    ``after``: ignored (tasks this one waits for: another group's that renders the same images).

    Returns ``{"row": {...}, "rendered": Rendered | None, "result": CaptureResult (keep_result)}``;
    an exception becomes ``row["status"] = "failed"`` with ``row["error"]``."""

    keep_sensor_work(4)  # a render group's points draw the same noise fields, and photons unless light or seed differ
    start = time.perf_counter()
    row: dict[str, Any] = {"status": "ok", "error": None, "worker": f"{socket.gethostname()}:{os.getpid()}"}
    kept: dict[str, Any] = {}
    result = None
    shared = leader.get("rendered") if leader else None
    try:
        cfg = config_from_dict(task["config"], source=f"sweep point {task['label']}")
        prepare_worker(task.get("threads"), cfg.render.variant)
        result = run_capture(
            cfg,
            progress=False,
            rendered=shared,
            on_rendered=(lambda r: kept.update(rendered=r)) if task.get("leader") else None,
        )
        if task.get("out_dir"):
            write_point(result, Path(task["out_dir"]), task["keep"])
        row.update(measurements(result.report))
        row["render_shared"] = shared is not None
    except Exception as exc:  # the point fails, the sweep goes on
        row.update(status="failed", error=one_line(exc), traceback=traceback.format_exc(limit=8))
    row["seconds"] = round(time.perf_counter() - start, 4)
    out = {"row": row, "rendered": kept.get("rendered")}
    if keep_result:
        out["result"] = result
    return out


def run_point_row(task: dict, leader: dict | None = None) -> dict:
    """:func:`run_point`'s row alone (what a follower sends back to the client)."""
    return run_point(task, leader)["row"]


def row_of(outcome: dict) -> dict:
    return outcome["row"]


# ------------------------------------------------------------------------------------ client side
def make_task(sweep: Sweep, point: Point, out: Path | None, *, leader: bool, threads: dict[str, int] | None) -> dict:
    """What a worker needs to run ``point``: the resolved config as plain data, where to write."""
    keep = sweep.spec.keep
    return {
        "label": point.label,
        "id": point.id,
        "config": point.config.to_yaml_dict(),
        "out_dir": str(out / POINTS_DIR / point.label) if out is not None and keep != "none" else None,
        "keep": keep,
        "leader": leader,
        "threads": threads,
    }


@dataclass
class Progress:
    """Counts of what this invocation ran."""

    ran: int = 0
    failed: int = 0
    rows: dict[int, dict] = field(default_factory=dict)
    results: dict[int, Any] = field(default_factory=dict)


def groups_to_run(plan: SweepPlan, pending: set[int]) -> list[list[int]]:
    """Per render group, its pending points in order (the first is the leader)."""
    return [[i for i in g.points if i in pending] for g in plan.groups if any(i in pending for i in g.points)]


def run_here(
    sweep: Sweep,
    plan: SweepPlan,
    pending: set[int],
    out: Path | None,
    *,
    on_row: Callable[[int, dict], None],
    keep_results: bool = False,
) -> dict[int, Any]:
    """Run the pending points in this process, group by group (the leader's render stage handed to
    the others). Returns the CaptureResults by point index when ``keep_results``.

    The others of a group run on a pool of threads, one per usable core, where their stages are numpy
    alone: they write no images (``keep`` none or report: matplotlib's text rendering is not
    thread-safe) and their applications render nothing (``App.renders``: Mitsuba is driven from one
    thread). numpy runs outside the interpreter's lock, and each point's result is a function of its
    config and the shared renders alone, so the order they finish in changes nothing but the order of
    the rows."""
    results: dict[int, Any] = {}
    apps = {sweep.points[i].config.app.resolve(sweep.points[i].config.capture.protocol)[0] for i in pending}
    side_by_side = sweep.spec.keep in ("none", "report") and not any(app.renders for app in apps)
    threads = usable_cores() if side_by_side else 1
    for first, *rest in groups_to_run(plan, pending):
        leader = run_point(
            make_task(sweep, sweep.points[first], out, leader=True, threads=None), keep_result=keep_results
        )
        on_row(*_kept(results, first, leader, keep_results))
        shared = {"rendered": leader["rendered"]}
        tasks = {i: make_task(sweep, sweep.points[i], out, leader=False, threads=None) for i in rest}
        # threads only on the leader's renders: a point that renders for itself (its leader failed) runs alone
        if threads > 1 and len(tasks) > 1 and shared["rendered"] is not None:
            pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="sweep-point")
            try:
                futures = {
                    pool.submit(run_point, task, shared, keep_result=keep_results): i for i, task in tasks.items()
                }
                for future in as_completed(futures):
                    on_row(*_kept(results, futures[future], future.result(), keep_results))
            finally:  # an interrupt drops the points not started (--resume runs them)
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            for i, task in tasks.items():
                on_row(*_kept(results, i, run_point(task, shared, keep_result=keep_results), keep_results))
    return results


def _kept(results: dict[int, Any], index: int, outcome: dict, keep_results: bool) -> tuple[int, dict]:
    """(index, row) of a finished point, its CaptureResult kept in ``results`` when asked."""
    if keep_results and outcome.get("result") is not None:
        results[index] = outcome["result"]
    return index, outcome["row"]


def run_on_dask(
    client, sweep: Sweep, plan: SweepPlan, pending: set[int], out: Path | None, *, on_row: Callable[[int, dict], None]
) -> None:
    """Submit the pending points (leaders first) and hand each finished row to ``on_row`` as it comes."""
    from dask.distributed import as_completed

    todo = groups_to_run(plan, pending)
    renders_of = {i: g.renders for g in plan.groups for i in g.points}
    hosts = topology(client)
    concurrent = len({renders_of[m[0]] for m in todo})  # groups rendering different images
    leader_threads = {h: drjit_threads(c, w, concurrent) for h, (c, w) in hosts.items()}
    follower_threads = {h: drjit_threads(c, w, w) for h, (c, w) in hosts.items()}
    rows = {}
    first_rendering: dict[str, Any] = {}  # render key -> the row of the first group that renders those images
    for members in todo:
        first = sweep.points[members[0]]
        # a group that renders the same images as an earlier one waits for it and reads them from the cache
        after = [first_rendering[renders_of[members[0]]]] if renders_of[members[0]] in first_rendering else []
        lead = client.submit(
            run_point,
            make_task(sweep, first, out, leader=True, threads=leader_threads),
            None,
            *after,
            key=f"sweep-{first.label}-{first.id[:12]}",
            pure=False,
            priority=10,
        )
        row = client.submit(row_of, lead, key=f"row-{first.label}-{first.id[:12]}", pure=False, priority=10)
        rows[row] = members[0]
        first_rendering.setdefault(renders_of[members[0]], row)
        for index in members[1:]:
            p = sweep.points[index]
            rows[
                client.submit(
                    run_point_row,
                    make_task(sweep, p, out, leader=False, threads=follower_threads),
                    lead,
                    key=f"sweep-{p.label}-{p.id[:12]}",
                    pure=False,
                )
            ] = index
        del lead  # the followers hold it; Dask frees the leader's arrays after the last one
    for future in as_completed(list(rows)):
        index = rows.pop(future)
        try:
            row = future.result()
        except Exception as exc:  # the worker died, or its task could not run at all
            row = {"status": "failed", "error": f"the task was lost: {one_line(exc)}"}
        future.release()
        on_row(index, row)
