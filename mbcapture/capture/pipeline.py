"""One capture in memory: prepare, render, accumulate, the sensor stage, reconstruct.

    config -> scene + timeline -> plan (strata, weights) -> render + accumulate
           -> sensor (noise, full wells, reads) -> application (HDR, ...) -> metrics

:func:`capture_in_memory` is the one orchestrator of a capture; :func:`mbcapture.capture.run.run_capture`
adds its outputs, a video (:mod:`mbcapture.capture.video`) calls it once per frame, and a sweep's points
share a render stage through :class:`Rendered`. Nothing here writes a file.
"""

from __future__ import annotations

import copy
import platform
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from ..scene import camera_motion, scenes
from ..timing import protocols
from ..exposure import resources
from ..application import AppOutput, CaptureData
from ..budget import BucketElectrons, noise_verdict, render_error, resolve_spp
from ..budget.adaptive import Passes, after_first_pass
from ..exposure.cluster import render_on_cluster
from ..config import CaptureConfig, scene_of
from ..errors import ConfigError
from ..exposure.filmstore import IN_MEMORY, FilmStore
from ..exposure.integrate import FilmLayout, Integrated, temporal_error
from ..exposure.plan import Plan, make_plan
from ..progress import StageStatus
from ..render import Renderer, ensure_llvm
from ..render.bands import group_bands
from ..render.cache import open_cache
from ..render.llvm import llvm_target
from ..render.shadows import changing_region
from ..sensor import electrons_per_render_second
from ..exposure.simulate import sense
from ..timing.timeline import Timeline
from ..render.cache import RenderCache


@dataclass
class CaptureResult:
    """Everything a capture produced, as arrays (axes: read/bucket, row, column, channel).

    bucket_exposure       (K, H, W, C) noise-free radiant exposure per bucket, W m^-2 sr^-1 s
    k_e                   (C,) electrons per render unit and second
    buckets_e             (K, H, W, C) noise-free expected electrons per bucket (bucket_exposure x k_e, made
                          when asked for: a large film does not hold it twice)
    reads_expected_e      (R, H, W, C) noise-free, unclipped expected electrons of each read
    reads_dn              (R, H, W, C) simulated reads, DN
    saturated             (R, H, W, C) bool
    moving_mask           (H, W) pixels the moving parts cross during the capture
    render_mc_diff        (K, H, W, C) float32 signed half-sample difference of bucket_exposure (None if spp = 1;
                          mbcapture.exposure.integrate.Integrated.mc_diff)
    render_var_exposure   (K, H, W, C) estimated Monte Carlo variance of bucket_exposure, its square (made
                          when asked for; None if spp = 1)
    mosaic_dn             (R, H, W) a colour-filter-array sensor's photosite codes (sensor.cfa), else None;
                          reads_dn are then the demosaiced reads
    film_store            where the whole-film arrays were made: in memory, or scratch files (render.spill);
                          write_outputs makes the EXRs' channels there too
    app                   name of the application that reconstructed the reads
    images                its images by name (hdr: radiance, sigma, valid, truth, moving; see docs)
    """

    config: CaptureConfig
    timeline: Timeline
    plan: Plan
    bucket_exposure: np.ndarray
    k_e: np.ndarray
    reads_expected_e: np.ndarray
    reads_dn: np.ndarray
    saturated: np.ndarray
    moving_mask: np.ndarray
    app: str
    images: dict[str, np.ndarray]
    render_mc_diff: np.ndarray | None = None
    mosaic_dn: np.ndarray | None = None
    report: dict = field(default_factory=dict)
    out_dir: Path | None = None  # where run_capture wrote it
    film_store: FilmStore = IN_MEMORY  # where its whole-film arrays were made (render.spill: scratch files)
    app_output: AppOutput | None = None
    video: object = None  # a video run (capture.frames > 1): mbcapture.capture.video.VideoFrames of every frame

    @property
    def buckets_e(self) -> np.ndarray:
        return self.bucket_exposure * self.k_e

    @property
    def render_var_exposure(self) -> np.ndarray | None:
        return None if self.render_mc_diff is None else np.square(self.render_mc_diff, dtype=np.float64)


class _Timer:
    def __init__(self):
        self.stages: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.stages[name] = self.stages.get(name, 0.0) + time.perf_counter() - t0


def _error_estimates(
    rendered: Rendered,
    integrated: Integrated,
    channels: Integrated,
    k_e: np.ndarray,
    timeline,
    plan: Plan,
    cfg: CaptureConfig,
) -> dict:
    """report.json's ``render_error``: the run's own estimate of its rendering error on every read
    (:func:`mbcapture.budget.render_error`) and its temporal part
    (:func:`mbcapture.exposure.integrate.temporal_error`). Besides the renders they depend on the electrons per
    render unit, the full wells, the reads and the budgets alone, and are kept on ``rendered`` under
    those, so the points of a sweep's render group that differ in anything else compute them once.
    A coded capture's reads route through its gate code: not kept."""
    reads = [r.buckets for r in timeline.reads]
    names = [r.name for r in timeline.reads]
    r, s = cfg.render, cfg.sensor
    key = (
        None
        if timeline.code is not None
        else (
            np.asarray(k_e, np.float64).tobytes(),
            s.full_well_e,
            s.fd_full_well_e,
            tuple(map(tuple, reads)),
            tuple(names),
            tuple(plan.buckets_read),
            r.noise_budget,
            r.noise_budget_p95,
            r.noise_budget_tail,
        )
    )
    if key in rendered.estimates:
        return copy.deepcopy(rendered.estimates[key])
    out = {
        **render_error(
            integrated.mc_diff,
            BucketElectrons(integrated.exposure, k_e),
            k_e,
            reads,
            names,
            s.full_well_e,
            s.fd_full_well_e,
            plan=plan,
            noise_budget=r.noise_budget,
            noise_budget_p95=r.noise_budget_p95,
            noise_budget_tail=r.noise_budget_tail,
        ),
        **temporal_error(channels, k_e, list(plan.buckets_read), s.full_well_e),
    }
    if key is not None:
        rendered.estimates[key] = copy.deepcopy(out)
    return out


@lru_cache(maxsize=1)
def _versions() -> dict:
    out = {"python": platform.python_version()}
    for pkg in ("mbcapture", "mitsuba", "drjit", "numpy", "scipy", "pydantic", "OpenEXR"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _llvm_target_label() -> str:
    """'znver4, vector width 16': the CPU target Dr.Jit compiled this run's kernels for."""
    t = llvm_target()
    return f"{t['cpu']}, vector width {t['vector_width']}"


def render_cache(render) -> "RenderCache | None":
    """The render cache ``render.cache`` names (None when 'off'); ConfigError if its folder cannot be made."""
    cache = open_cache(render.cache, render.cache_max_gb)
    if cache is not None:
        try:
            cache.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"render.cache: cannot create the cache folder {cache.root} ({exc.strerror})") from None
    return cache


def sensor_seed(cfg: CaptureConfig, seeds: list[np.random.SeedSequence]) -> np.random.SeedSequence:
    """The sensor's temporal-noise seed: ``sensor.noise_seed`` when set, else the run seed's stage 1."""
    return seeds[1] if cfg.sensor.noise_seed is None else np.random.SeedSequence(cfg.sensor.noise_seed)


def frame_period_check(cfg, timeline) -> float:
    """The frame period (s); ConfigError when it is shorter than the capture's span plus its readout."""
    c = cfg.capture
    if c.frame_rate_hz is None:
        raise ConfigError("capture.frame_rate_hz: a video (capture.frames > 1) needs a frame rate")
    period = 1.0 / c.frame_rate_hz
    span = float(timeline.seconds(timeline.end_tick - timeline.start_tick))
    readout = cfg.sensor.frame_readout_s
    if period < span + readout - 1e-12:
        raise ConfigError(
            f"capture.frame_rate_hz: {c.frame_rate_hz:g} frames/s gives a frame period of {period * 1e3:.4g} ms, shorter "
            f"than the capture ({span * 1e3:.4g} ms) plus its readout (sensor.frame_readout_s, {readout * 1e3:.4g} ms); "
            f"at most {1.0 / (span + readout):.4g} frames/s"
        )
    return period


class Prepared(NamedTuple):
    """What :func:`prepare` makes of a config (a tuple: ``scene, timeline, plan, seeds = prepare(cfg)``)."""

    scene: scenes.SceneModel
    timeline: Timeline
    plan: Plan
    seeds: list[np.random.SeedSequence]


def prepare(cfg: CaptureConfig) -> Prepared:
    """Scene, timeline and render plan of a capture, and the run's seeds split per stage
    (0: plan jitter, 1: sensor noise, 2: render seeds, 3: the application's reference renders).
    Shared by ``run`` and ``plan``."""
    seeds = np.random.SeedSequence(cfg.seed).spawn(4)
    scene = scene_of(cfg)
    timeline = protocols.build(cfg)
    if cfg.capture.frames > 1:
        frame_period_check(cfg, timeline)  # a frame period shorter than capture + readout: before anything renders
    plan = make_plan(timeline, scene, cfg.render, np.random.default_rng(seeds[0]))
    return Prepared(scene, timeline, plan, seeds)


def describe(cfg: CaptureConfig, timeline: Timeline, plan: Plan, need: resources.Resources | None = None) -> dict:
    """What is captured and how it is rendered: the head of report.json and of ``mbcapture plan``
    (``need``: the resources the run planned, else planned now)."""
    if need is None:
        need = resources.plan_resources(cfg, timeline, plan, cfg.app.resolve(cfg.capture.protocol)[0])
    return {
        "scene": cfg.scene.name,
        "protocol": timeline.protocol,
        "sequential": timeline.sequential,
        "sensor_type": "conventional (one bucket, destructive read per frame)"
        if timeline.sequential
        else f"{cfg.sensor.bucket_count}-bucket",
        "film": [cfg.render.width, cfg.render.height],
        "seed": cfg.seed,
        "capture_span_s": float(timeline.seconds(timeline.end_tick - timeline.start_tick)),
        "reads": timeline.describe_reads(),
        "plan": plan.summary(timeline),
        "resources": need.summary(),
    }


def bucket_group_seconds(timeline: Timeline, switchable: tuple[str, ...]) -> np.ndarray:
    """(K, S): seconds bucket k collected while switchable group ``switchable[s]`` was on (a coded
    capture: the mean over the code's pixels)."""
    out = np.zeros((timeline.n_buckets, len(switchable)))
    for k in range(timeline.n_buckets):
        for s, g in enumerate(switchable):
            out[k, s] = float(timeline.bucket_gated_ticks(k, g) * timeline.tick_s)
    return out


@dataclass(frozen=True)
class Rendered:
    """The render stage of a capture: its plan (samples chosen) and the integrated bucket exposures.

    A capture whose renders are provably the same (the points of a sweep's render group, see
    :mod:`mbcapture.sweep.groups`) takes it as ``run_capture(..., rendered=)`` and goes straight to
    the sensor: no pilot, renders or accumulation. Its own plan must have the same strata, render
    times, weights and groups (checked)."""

    plan: Plan
    integrated: Integrated
    #: (H, W) bool, the moving region of the capture's span (:func:`mbcapture.scene.camera_motion.moving_region`): it depends on the
    #: scene, the span and the film only, so the captures sharing these renders share it too
    moving: np.ndarray
    #: the run's estimates of its rendering error (render_error, temporal_error) by what they depend on
    #: besides these renders (:func:`_error_estimates`): the points of a sweep's render group that differ
    #: only in read noise, ADC or the application share them
    estimates: dict = field(default_factory=dict, compare=False, repr=False)

    def plan_for(self, own: Plan) -> Plan:
        same = (
            own.groups == self.plan.groups
            and np.array_equal(own.render_times, self.plan.render_times)
            and np.array_equal(own.weights_s, self.plan.weights_s)
            and (own.spp is None or np.array_equal(own.spp, self.plan.spp))
        )
        if not same:
            raise ValueError(
                "run_capture(rendered=...): the renders were made for another plan "
                "(strata, render times, weights, groups or samples differ)"
            )
        return self.plan


def merge_cluster_info(infos: list[dict]) -> dict:
    """What report.json keeps of a capture's cluster renders, one :func:`render_on_cluster` per tile."""
    out = dict(infos[0])
    if len(infos) > 1:
        out["renders"] = sum(i["renders"] for i in infos)
        if "seconds" in out:  # not with the difference estimator, which renders here
            out["seconds"] = round(sum(i["seconds"] for i in infos), 3)
        out["tiles"] = len(infos)
    return out


def capture_in_memory(
    cfg: CaptureConfig,
    status: StageStatus,
    *,
    progress: bool = False,
    rendered: Rendered | None = None,
    on_rendered: "Callable[[Rendered], None] | None" = None,
    renderer: Renderer | None = None,
    client: Any = None,
    planned: "tuple[Prepared, resources.Resources, float] | None" = None,
) -> CaptureResult:
    """One capture, in the order of the data flow, nothing written: plan, render (or take
    ``rendered``), accumulate, the sensor stage (:func:`mbcapture.exposure.simulate.sense`), reconstruct.
    ``status``: the stage lines; ``progress``: a bar for the render passes; ``renderer``: a Renderer
    of this capture's scene to reuse (a video's frames), else one is made; ``on_rendered``: called
    with the render stage once it is done; ``client``: a Dask client whose workers render the strata
    (:mod:`mbcapture.exposure.cluster`); ``planned``: :func:`prepare` and :func:`mbcapture.exposure.resources.plan_resources`
    of ``cfg`` made already, and the seconds they took (:func:`mbcapture.capture.run.check_resources`),
    else made here. BLAS runs on one thread throughout (:func:`mbcapture.exposure.resources.one_blas_thread`)."""
    with resources.one_blas_thread():
        return _capture_in_memory(
            cfg,
            status,
            progress=progress,
            rendered=rendered,
            on_rendered=on_rendered,
            renderer=renderer,
            client=client,
            planned=planned,
        )


def _capture_in_memory(
    cfg: CaptureConfig,
    status: StageStatus,
    *,
    progress: bool = False,
    rendered: Rendered | None = None,
    on_rendered: "Callable[[Rendered], None] | None" = None,
    renderer: Renderer | None = None,
    client: Any = None,
    planned: "tuple[Prepared, resources.Resources, float] | None" = None,
) -> CaptureResult:
    """:func:`capture_in_memory`'s work: a chain of named stages."""
    timer = _Timer()
    t_start = time.perf_counter()
    with timer("plan"), status.stage("plan"):
        app, app_params = cfg.app.resolve(cfg.capture.protocol)
        if planned is None:
            scene, timeline, plan, seeds = prepare(cfg)
            need = resources.plan_resources(cfg, timeline, plan, app)
        else:
            (scene, timeline, plan, seeds), need, seconds = planned
            timer.stages["plan"] = seconds  # and this stage's own time added
    with timer("render_setup"), status.stage("render setup (kernels, scene)"):
        llvm = ensure_llvm() if cfg.render.variant.startswith("llvm") else None
        cache = render_cache(cfg.render) if renderer is None else renderer.cache
        renderer = Renderer.from_config(scene, cfg, cache=cache) if renderer is None else renderer
    # tiles of rows (runs of whole render bands) for render, accumulation and the sensor: the same result
    # whatever their number (mbcapture.render.bands), so the memory plan alone chooses it; a tiled film's
    # whole-film results in scratch files on disk when the plan says so (render.spill)
    tiles = group_bands(renderer.bands, need.tiles)
    store = FilmStore(resources.spill_folder(cfg)) if need.spill_bytes and len(tiles) > 1 else IN_MEMORY
    layout = FilmLayout(tuple(tuple(t) for t in tiles), store)
    passes = Passes(cfg, renderer, timeline, seeds[2], status, timer, progress, app.per_group, layout)
    infos: dict = {"cluster": None, "adaptive": None, "top_up": None}
    if rendered is None:
        rendered = _render(passes, scene, plan, client, infos)
        if on_rendered is not None:
            on_rendered(rendered)
    else:  # another capture's render stage: it must have had the same renders
        rendered.plan_for(plan)
        if app.per_group and rendered.integrated.group_exposure is None:
            raise ValueError("run_capture(rendered=...): the application needs per-group exposures")
    plan = rendered.plan
    channels = rendered.integrated  # per channel: the buckets, or a coded capture's sub-frames
    with timer("accumulate"):
        integrated = channels.routed(timeline)  # per bucket, each pixel through its gate code
    k_e = electrons_per_render_second(
        cfg.sensor, cfg.render.variant
    )  # (C,) e- per render unit s (spectral: film units)
    with timer("sensor"), status.stage("sensor"):
        # the expected electrons exposure x k_e, made tile by tile inside the sensor stage
        sensor_out = sense(
            timeline, integrated.exposure, cfg.sensor, sensor_seed(cfg, seeds), tiles=tiles, per_unit=k_e, store=store
        )
    with timer("reconstruct"), status.stage(f"reconstruct ({app.name})"):
        data = _capture_data(cfg, scene, timeline, plan, integrated, sensor_out, k_e, rendered.moving, renderer, seeds)
        out = app.reconstruct(data, app_params)
    report = {
        **describe(cfg, timeline, plan, need),
        "tiles": _tiles_report(tiles, renderer, store),
        "app": app.name,
        "render_units": "camera-weighted film value, e- m^-2 sr^-1 s^-1 before optics"
        if cfg.render.variant.endswith("_spectral")
        else "W m^-2 sr^-1",
        "electrons_per_render_unit_second": dict(zip(renderer.channels, k_e.tolist())),  # per film channel
        "metrics": out.metrics,
        "render_error": _error_estimates(rendered, integrated, channels, k_e, timeline, plan, cfg),
        "render_cache": {"folder": str(cache.root), **cache.stats.as_dict()} if cache is not None else {"folder": None},
        **infos,
        "versions": {
            **_versions(),
            "llvm": ".".join(map(str, llvm)) if llvm else None,
            "variant": cfg.render.variant,
            "llvm_target": _llvm_target_label() if llvm else None,
        },
    }
    report["render_error"]["verdict"] = noise_verdict(
        report["render_error"], adaptive_hint=cfg.render.spp is None and not cfg.render.adaptive
    )
    report["timings_s"] = {k: round(v, 4) for k, v in timer.stages.items()}
    report["timings_s"]["total_before_write"] = round(time.perf_counter() - t_start, 4)
    return CaptureResult(
        config=cfg,
        timeline=timeline,
        plan=plan,
        bucket_exposure=integrated.exposure,
        k_e=k_e,
        reads_expected_e=sensor_out.reads_e_expected,
        reads_dn=sensor_out.reads_dn,
        saturated=sensor_out.saturated,
        moving_mask=rendered.moving,
        app=app.name,
        images=out.images,
        render_mc_diff=integrated.mc_diff,
        mosaic_dn=sensor_out.mosaic_dn,
        film_store=store,
        report=report,
        app_output=out,
    )


def _render(passes: Passes, scene, plan: Plan, client: Any, infos: dict) -> Rendered:
    """The render stage: the pilot (``render.spp`` null), the first pass (its renders on the Dask cluster of
    ``client`` when there is one), then the passes after it (:func:`mbcapture.budget.adaptive.after_first_pass`).
    Fills ``infos`` (what report.json keeps of the cluster, adaptive sampling and the top-up)."""
    cfg, renderer, timeline, timer, status = passes.cfg, passes.renderer, passes.timeline, passes.timer, passes.status
    W, H = cfg.render.width, cfg.render.height
    t0_s, t1_s = timeline.seconds(timeline.start_tick), timeline.seconds(timeline.end_tick)
    pilot = status.stage("pilot render (spp from render.noise_budget)") if cfg.render.spp is None else nullcontext()
    with timer("pilot"), pilot:
        plan = resolve_spp(plan, renderer, cfg, passes.seed)  # render.spp null: spp from render.noise_budget
    on_cluster, cluster = None, []
    if client is not None:  # each tile's renders on the workers first, then accumulated here

        def on_cluster(rows: tuple[int, int]) -> None:
            with timer("cluster"):
                cluster.append(render_on_cluster(client, cfg, plan, passes.seed, renderer, rows=rows))

    tiles = passes.layout.rows(H)
    where = " on the cluster" if client is not None else ""
    in_tiles = f" x {len(tiles)} tiles" if len(tiles) > 1 else ""
    with status.stage(f"render{where} ({plan.passes} passes{in_tiles})"):
        integrated = passes.layout.integrate(
            renderer,
            plan,
            timeline.n_channels,
            passes.seed,
            per_group=passes.per_group,
            timer=timer,
            progress=passes.progress,
            before_tile=on_cluster,
        )
    if cluster:
        infos["cluster"] = merge_cluster_info(cluster)
    moving = camera_motion.moving_region(scene, float(t0_s), float(t1_s), W, H)
    if cfg.render.spp is None:  # adaptive sampling (render.adaptive) and the top-up (render.top_up)
        passes.changing = moving  # where a render's time within its stratum is noise
        if cfg.render.adaptive:
            with timer("adaptive_rule"):
                passes.changing = changing_region(renderer, float(t0_s), float(t1_s), W, H, moving=moving)
        plan, integrated, infos["adaptive"], infos["top_up"] = after_first_pass(passes, plan, integrated)
    return Rendered(plan, integrated, moving)


def _capture_data(cfg, scene, timeline, plan, integrated, sensor_out, k_e, moving, renderer, seeds) -> CaptureData:
    """What the application reconstructs from (:class:`mbcapture.application.CaptureData`)."""
    switchable = tuple(g for g in scene.groups if g in scene.switchable)
    return CaptureData(
        cfg=cfg,
        scene=scene,
        timeline=timeline,
        plan=plan,
        read_names=[r.name for r in timeline.reads],
        exposure_s=np.array([float(timeline.read_exposure_ticks(r) * timeline.tick_s) for r in timeline.reads]),
        reads_dn=sensor_out.reads_dn,
        saturated=sensor_out.saturated,
        reads_e_expected=sensor_out.reads_e_expected,
        bucket_exposure=integrated.exposure,
        k_e=k_e,
        moving_mask=moving,
        switchable=switchable,
        bucket_group_s=bucket_group_seconds(timeline, switchable),
        group_exposure=integrated.group_exposure,
        renderer=renderer,
        seed=seeds[3],
        mosaic_dn=sensor_out.mosaic_dn,
        mosaic_saturated=sensor_out.mosaic_saturated,
    )


def _tiles_report(tiles, renderer, store: FilmStore) -> dict:
    """report.json's ``tiles``: the film's tiles of rows, its render bands and where a spilled film lives."""
    return {
        "count": len(tiles),
        "rows": [list(t) for t in tiles],
        "render_bands": len(renderer.bands),
        "spill": {"folder": str(store.folder), "gb": round(store.spilled_bytes / resources.GB, 3)}
        if store.spills
        else None,
    }
