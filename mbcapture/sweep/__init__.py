"""Design-space sweeps: many captures of one base config, renders shared, on Dask.

    sweep = load_sweep("configs/sweeps/sensor_noise.yaml", ["render.width=160", "render.height=128"])
    outcome = run_sweep(sweep, Path("out/sensor_noise"), workers=2)
    outcome.table            # pandas DataFrame, one row per point

The order of work (each step its own module):

1. :mod:`.spec`: the sweep file, its points, each point's config validated (ConfigError names the
   file and the axis before anything runs).
2. :mod:`.groups`: the points grouped by what their render stage receives (render groups).
3. :mod:`.execute`: each group's first point renders (through the render cache), the others take
   its render stage and simulate only their sensor; on a Dask LocalCluster, an existing cluster
   (``scheduler``), or in this process (``in_process``; what :func:`choose_executor` picks for a
   sweep that renders one set of images, and what ``mbcapture figures`` uses). Each finished
   point is written to ``rows/<id>.json`` as it arrives; ``resume`` skips the finished ones.
4. :mod:`.results`: results.parquet / .csv, plots of each metric against each axis, sweep.json,
   index.html, written atomically.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..output.io import check_out_dir, staged_outputs
from ..progress import bar as progress_bar
from ..render.cache import open_cache
from .execute import ROWS_DIR, run_here, run_on_dask, start_client, usable_cores
from .groups import SweepPlan, group_key, plan_sweep, render_inputs, render_key
from .results import write_results
from .spec import Point, Sweep, SweepSpec, load_sweep, resolve_sweep_path

__all__ = [
    "Point",
    "Sweep",
    "SweepOutcome",
    "SweepPlan",
    "SweepSpec",
    "choose_executor",
    "group_key",
    "load_sweep",
    "plan_sweep",
    "render_inputs",
    "render_key",
    "resolve_sweep_path",
    "run_sweep",
]


@dataclass
class SweepOutcome:
    """What a sweep produced: its plan, every point's row (by index), the summary, the table
    (None without an output folder) and, with ``keep_results``, the CaptureResults run here."""

    sweep: Sweep
    plan: SweepPlan
    rows: dict[int, dict]
    summary: dict
    table: Any = None
    results: dict[int, Any] = field(default_factory=dict)


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'' if n == 1 else 's'}"


def _read_row(path: Path) -> dict | None:
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return row if isinstance(row, dict) else None


def _write_row(out: Path, point: Point, row: dict) -> None:
    with staged_outputs(out / ROWS_DIR) as st:
        st.write_json(f"{point.id}.json", {"point": point.label, "values": point.values, **row})


def choose_executor(
    plan: SweepPlan,
    pending: set[int],
    *,
    workers: int | None,
    scheduler: str | None,
    client: Any,
    in_process: bool | None,
) -> bool:
    """Whether to run the pending points in this process rather than on Dask.

    ``in_process`` True or False decides; so do ``workers``, ``scheduler`` or ``client`` (Dask). Left
    to the sweep (all None): this process when the pending points render one set of images. Their
    first point then renders with every core (Dr.Jit's threads) while every other point waits for it,
    and the rest are numpy stages of a fraction of a second that a local cluster of the same cores only
    slows: measured on the 64-point ``sensor_noise`` sweep at 320x256 on 2 cores, 0.28 s a point here
    against 0.83 s on two worker processes beside their scheduler, and no cluster to start. Sweeps of
    several render sets keep the LocalCluster, whose workers render different sets at once."""
    if in_process is not None:
        return in_process
    if workers is not None or scheduler is not None or client is not None:
        return False
    return len({g.renders for g in plan.groups if any(i in pending for i in g.points)}) <= 1


def _rows_before(sweep: Sweep, plan, out: Path | None, resume: bool) -> tuple[dict[int, dict], set[int]]:
    """The rows known before anything runs: those an earlier run into ``out`` finished (with ``resume``), and those
    of points that cannot be planned (failed, written to ``out/rows``); and which were resumed."""
    rows: dict[int, dict] = {}
    resumed: set[int] = set()
    if resume and out is not None:
        for p in sweep.points:
            row = _read_row(out / ROWS_DIR / f"{p.id}.json")
            if row is not None and row.get("status") == "ok":
                rows[p.index] = row
                resumed.add(p.index)
    for index, error in plan.failed.items():
        rows[index] = {"status": "failed", "error": error}
        if out is not None:
            _write_row(out, sweep.points[index], rows[index])
    return rows, resumed


def _summary(sweep: Sweep, plan, rows: dict, ran: dict, resumed: set, executor: str, start: float, cache) -> dict:
    """sweep.json's summary: points, what ran and what was reused, the render groups, where it ran, its wall time."""
    done = [r for r in rows.values() if r.get("status") == "ok"]
    return {
        "points": len(sweep.points),
        "ok": len(done),
        "failed": len(rows) - len(done),
        "ran": len(ran),
        "resumed": len(resumed),
        "render_groups": len(plan.groups),
        "render_sets": len({g.renders for g in plan.groups}),
        "axes_changing_renders": list(plan.axes_changing_renders),
        "renders_rendered": int(sum(r.get("renders_rendered") or 0 for r in ran.values())),
        "renders_reused": int(sum(r.get("renders_reused") or 0 for r in ran.values())),
        "points_sharing_renders": int(sum(bool(r.get("render_shared")) for r in ran.values())),
        "executor": executor,
        "wall_s": round(time.perf_counter() - start, 3),  # before writing the results
        "render_cache": str(cache.root) if cache is not None else None,
    }


def run_sweep(
    sweep: Sweep,
    out: Path | None,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: bool = True,
    in_process: bool | None = None,
    keep_results: bool = False,
    client: Any = None,
    say: Callable[[str], None] | None = None,
) -> SweepOutcome:
    """Run ``sweep``; with ``out``, write rows as they finish and the results at the end.

    ``workers``: processes of the LocalCluster (default: one per usable core, at most one per point
    to run); ``scheduler``: run on the Dask cluster at that address instead; ``in_process``: True runs
    here, without Dask (``keep_results`` then keeps each point's CaptureResult), False on Dask, None
    (the default) as :func:`choose_executor` says; ``client``: a ``dask.distributed.Client`` to run on
    (left open). ``resume``: points whose row in ``out/rows`` says ok are not run again. ``say``: where
    to print a line about the plan."""

    say = say or (lambda line: None)
    if out is not None:
        check_out_dir(out)
    start = time.perf_counter()
    plan = plan_sweep(sweep)
    rows, resumed = _rows_before(sweep, plan, out, resume)
    pending = {p.index for p in sweep.points if p.index not in rows}
    ran: dict[int, dict] = {}
    n_groups = sum(1 for g in plan.groups if any(i in pending for i in g.points))
    say(
        f"sweep {sweep.name}: {len(sweep.points)} points in {_count(len(plan.groups), 'render group')}"
        + (
            f" (axes that change the renders: {', '.join(plan.axes_changing_renders)})"
            if plan.axes_changing_renders
            else " (no axis changes the renders)"
        )
        + (f"; {len(resumed)} finished before, {len(pending)} to run" if resume else "")
        + (f"; {len(plan.failed)} cannot be planned" if plan.failed else "")
    )
    cache = open_cache(sweep.points[0].config.render.cache, 1.0) if sweep.points else None
    if cache is None and len(pending) > n_groups:
        say("note: render.cache is off: a point run again (--resume, a lost worker) renders again")

    own_client = cluster = None
    in_process = choose_executor(
        plan, pending, workers=workers, scheduler=scheduler, client=client, in_process=in_process
    )
    executor = "nothing to run" if not pending else "this process (no Dask)"
    if pending and in_process:
        say("running in this process, without Dask (--workers N runs on a local Dask cluster)")
    if pending and not in_process:
        if client is None:
            client = own_client = start_client(workers or min(usable_cores(), len(pending)), scheduler)
            cluster = getattr(client, "cluster", None) if scheduler is None else None
        count = len(client.scheduler_info().get("workers", {}))
        executor = (
            f"Dask scheduler {scheduler}, {count} workers"
            if scheduler
            else f"Dask cluster {client.scheduler.address}, {count} workers"
            if own_client is None
            else f"Dask LocalCluster, {count} worker processes on {usable_cores()} cores"
        )
        say(f"running on {executor}")
    results: dict[int, Any] = {}
    try:
        with progress_bar(
            total=len(pending), desc=f"sweep {sweep.name}", unit="point", enabled=progress and bool(pending)
        ) as bar:

            def on_row(index: int, row: dict) -> None:
                rows[index] = ran[index] = row
                if out is not None:
                    _write_row(out, sweep.points[index], row)
                bar.update(1)
                failed = sum(r.get("status") != "ok" for r in ran.values())
                if failed:
                    bar.set_postfix_str(f"{failed} failed")

            if pending and not in_process:
                run_on_dask(client, sweep, plan, pending, out, on_row=on_row)
            elif pending:
                results = run_here(sweep, plan, pending, out, on_row=on_row, keep_results=keep_results)
    finally:
        if own_client is not None:
            own_client.close()
        if cluster is not None:
            cluster.close()
    summary = _summary(sweep, plan, rows, ran, resumed, executor, start, cache)
    outcome = SweepOutcome(sweep, plan, rows, summary, results=results)
    if out is not None:
        outcome.table = write_results(out, sweep, plan, rows, summary)
    return outcome
