"""One capture across a Dask cluster: the strata's renders on the workers, everything else here.

``mbcapture run CONFIG --workers N`` (a LocalCluster of N processes on this machine) or
``--scheduler ADDRESS`` (an existing cluster: ``dask scheduler`` and ``dask worker`` processes, or
dask-jobqueue on a batch system; docs/resources.md) renders the time strata of one capture on the
cluster, the engine the sweeps use (:mod:`mbcapture.sweep`). Each worker builds the capture's
scene and renderer once (from the config, so every worker renders exactly what this process would)
and returns each render's raw radiance; this process hands them to its own renderer
(:meth:`mbcapture.render.Renderer.give`) and accumulates them in the plan's order, so the result
is the local run's: bit for bit on workers with this machine's CPU, within the renderer's last
bits on another CPU (the same tolerance as the goldens). Workers with the same render cache folder
(``render.cache`` a shared path) also fill it.

What stays here: the plan, the pilot that chooses spp (a few small renders), the sensor stage,
the reconstruction and the application's own comparison renders. The ``difference`` estimator's
base and control renders are not distributed (its strata depend on them): with it, everything
renders here.
"""

from __future__ import annotations

import socket
import time
from typing import Any, Callable

import numpy as np

from ..config import CaptureConfig, scene_of
from ..errors import ConfigError, one_line
from .integrate import render_requests, sample_counter
from .plan import Plan
from ..render import Renderer
from ..render.cache import open_cache
from ..render.llvm import set_render_threads
from ..sensor.sampling import set_threads as set_inversion_threads
from ..sensor.sampling import usable_cores

__all__ = [
    "drjit_threads",
    "host_cores",
    "prepare_worker",
    "render_on_cluster",
    "start_client",
    "topology",
    "usable_cores",
]


def host_cores() -> tuple[str, int]:
    """(host name, usable cores) of the process that runs it: asked of every worker."""
    return socket.gethostname(), usable_cores()


def drjit_threads(cores: int, workers_on_host: int, concurrent: int) -> int:
    """Dr.Jit threads for a task on a host with ``cores`` and ``workers_on_host`` worker processes
    when at most ``concurrent`` such tasks run there at once."""
    return max(1, cores // max(1, min(workers_on_host, concurrent)))


def start_client(workers: int | None, scheduler: str | None = None):
    """A Dask client: of a new LocalCluster of ``workers`` processes with one task thread each (its
    ``.cluster``), or of the scheduler at ``scheduler`` (tcp://host:port)."""
    import logging

    from dask.distributed import Client, LocalCluster

    if scheduler:
        from urllib.parse import urlsplit

        where = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
        try:  # a refused or unreachable address fails here at once, not after Dask's retries
            socket.create_connection((where.hostname, where.port or 8786), timeout=10).close()
            return Client(scheduler, timeout="30s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect ({one_line(exc)})") from None
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
        memory_limit=0,
    )
    try:
        return Client(cluster)
    except BaseException:
        cluster.close()
        raise


def topology(client) -> dict[str, tuple[int, int]]:
    """host -> (usable cores, worker processes on it), asked of every worker."""
    per_worker = client.run(host_cores)
    hosts: dict[str, list[int]] = {}
    for host, cores in per_worker.values():
        hosts.setdefault(host, []).append(cores)
    return {host: (min(c), len(c)) for host, c in hosts.items()}


# ------------------------------------------------------------------------------------ worker side
def prepare_worker(threads: dict[str, int] | None, variant: str) -> None:
    """In a worker process: its share of its host's cores (``threads``: by host name) for the sensor's
    inversions and, for an LLVM variant, Dr.Jit (after picking the libLLVM, before Mitsuba is imported)."""
    n = (threads or {}).get(socket.gethostname())
    set_inversion_threads(n)
    set_render_threads(variant, n)


#: The renderer of each capture config a worker has seen (by the config's JSON), built once.
_WORKER_RENDERERS: dict[str, Renderer] = {}


def _render_task(
    cfg: CaptureConfig,
    request: tuple[float, int, int, tuple[str, ...], tuple[int, int] | None, int],
    threads: dict[str, int],
) -> np.ndarray:
    """On a worker: the raw render of ``request`` (t, spp, seed, groups, shared pattern, render band) for the capture
    ``cfg`` (its own renderer, built once)."""
    prepare_worker(threads, cfg.render.variant)
    key = cfg.model_dump_json()
    renderer = _WORKER_RENDERERS.get(key)
    if renderer is None:
        renderer = _WORKER_RENDERERS[key] = Renderer.from_config(
            scene_of(cfg), cfg, cache=open_cache(cfg.render.cache, cfg.render.cache_max_gb)
        )
    t_s, spp, seed, groups, pattern, band = request
    return renderer.raw_render(t_s, spp, seed, groups, band=band, pattern=pattern)


# ------------------------------------------------------------------------------------ client side
def render_on_cluster(
    client,
    cfg: CaptureConfig,
    plan: Plan,
    seed: np.random.SeedSequence,
    renderer: Renderer,
    on_done: Callable[[], None] | None = None,
    rows: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """Render ``plan``'s strata (the renders :func:`mbcapture.exposure.integrate.integrate` will ask for, with
    ``seed``) on the cluster, each render band of ``rows`` (a tile; None: the whole film) a task of
    its own, and give them to ``renderer``. ``on_done``: called after each render arrives (a
    progress bar). Returns what report.json keeps (``cluster``)."""
    from dask.distributed import as_completed

    if plan.estimator != "independent":
        return {
            "renders": 0,
            "note": f"render.estimator {plan.estimator!r}: rendered here (its strata depend on its base render)",
        }
    bands = renderer.band_span((0, renderer.height) if rows is None else rows)
    requests = [(*req, b) for req in render_requests(plan, seed, sample_counter(renderer, plan)) for b in bands]
    hosts = topology(client)
    threads = {h: drjit_threads(c, w, w) for h, (c, w) in hosts.items()}
    start = time.perf_counter()
    futures = {
        client.submit(_render_task, cfg, req, threads, pure=False, key=f"render-{i}-{req[2]}-{req[5]}"): req
        for i, req in enumerate(requests)
    }
    for future in as_completed(list(futures)):
        req = futures.pop(future)
        try:
            t_s, spp, seed_r, groups, pattern, band = req
            renderer.give(t_s, spp, seed_r, groups, future.result(), band=band, pattern=pattern)
        except Exception as exc:  # a worker died, or its render failed: one line, not a Dask traceback
            raise ConfigError(f"cluster render at t = {req[0]:.6g} s failed: {one_line(exc)}") from None
        future.release()
        if on_done is not None:
            on_done()
    return {
        "workers": sum(w for _, w in hosts.values()),
        "hosts": len(hosts),
        "renders": len(requests),
        "seconds": round(time.perf_counter() - start, 3),
        "threads_per_worker": threads,
    }
