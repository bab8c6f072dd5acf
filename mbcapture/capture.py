"""``run_capture``: one capture from config to outputs, in the order of the data flow.

    config -> scene + timeline -> plan (strata, weights) -> render + accumulate
           -> sensor (noise, full wells, reads) -> HDR -> metrics -> outputs
"""

from __future__ import annotations

import platform
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from . import camera_motion, protocols, scenes
from .config import CaptureConfig
from .errors import ConfigError
from .apps import AppOutput, CaptureData
from .integrate import Integrated, integrate, temporal_error
from .io import check_out_dir, staged_outputs
from .plan import Plan, make_plan, resolve_spp
from .progress import StageStatus
from .report import noise_verdict, write_read_previews, write_report
from .sensor import electrons_per_render_second, simulate_reads
from .timeline import Timeline

if TYPE_CHECKING:
    from .render.cache import RenderCache


@dataclass
class CaptureResult:
    """Everything a capture produced, as arrays (axes: read/bucket, row, column, channel).

    bucket_exposure       (K, H, W, C) noise-free radiant exposure per bucket, W m^-2 sr^-1 s
    buckets_e             (K, H, W, C) noise-free expected electrons per bucket
    reads_expected_e      (R, H, W, C) noise-free, unclipped expected electrons of each read
    reads_dn              (R, H, W, C) simulated reads, DN
    saturated             (R, H, W, C) bool
    moving_mask           (H, W) pixels the moving parts cross during the capture
    render_var_exposure   (K, H, W, C) estimated Monte Carlo variance of bucket_exposure (None if spp = 1)
    app                   name of the application that reconstructed the reads
    images                its images by name (hdr: radiance, sigma, valid, truth, moving; see docs)
    """

    config: CaptureConfig
    timeline: Timeline
    plan: Plan
    bucket_exposure: np.ndarray
    buckets_e: np.ndarray
    reads_expected_e: np.ndarray
    reads_dn: np.ndarray
    saturated: np.ndarray
    moving_mask: np.ndarray
    app: str
    images: dict[str, np.ndarray]
    render_var_exposure: np.ndarray | None = None
    report: dict = field(default_factory=dict)
    out_dir: Path | None = None
    app_output: AppOutput | None = None
    video: object = None  # a video run (capture.frames > 1): mbcapture.video.VideoFrames of every frame


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


def moving_region(scene: scenes.SceneModel, t0_s: float, t1_s: float, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels the moving parts cover at some time in [t0, t1].

    At 64 times the convex hull of the projected motion points (grown by 1.5 px) is
    rasterized; the union over times is the region swept by the moving parts. With a moving
    camera the parts are projected through its pose at each time, and once the frame itself moves
    more than :data:`mbcapture.camera_motion.FRAME_MOTION_PX` during [t0, t1] every pixel moves: the
    mask is the whole image.
    """
    from matplotlib.path import Path as PolyPath
    from scipy.spatial import ConvexHull, QhullError

    from .camera_motion import FRAME_MOTION_PX, frame_motion_px

    mask = np.zeros((height, width), dtype=bool)
    if scene.is_static:
        return mask
    times = np.linspace(t0_s, t1_s, 64)
    if frame_motion_px(scene, times, width, height) > FRAME_MOTION_PX:
        return np.ones((height, width), dtype=bool)
    if scene.motion_points is None:
        return mask
    px = scene.project(np.asarray(scene.motion_points(times)), times, width, height)  # (T, M, 2)
    yy, xx = np.mgrid[0:height, 0:width]
    centres = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], axis=1)
    for pts in px:
        try:
            poly = pts[ConvexHull(pts).vertices]
        except (QhullError, ValueError):  # fewer than 3 points or collinear: use the points' bounding box
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            poly = np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]])
        lo, hi = poly.min(axis=0) - 2, poly.max(axis=0) + 2
        near = (centres[:, 0] >= lo[0]) & (centres[:, 0] <= hi[0]) & (centres[:, 1] >= lo[1]) & (centres[:, 1] <= hi[1])
        if near.any():
            inside = PolyPath(poly).contains_points(centres[near], radius=3.0) | PolyPath(poly[::-1]).contains_points(
                centres[near], radius=3.0
            )
            mask.ravel()[np.flatnonzero(near)[inside]] = True
    return mask


def render_error(
    mc_var_exposure: np.ndarray | None, buckets_e: np.ndarray, k_e: np.ndarray, buckets: list[int], full_well_e: float,
    *, plan: Plan | None = None, noise_budget: float = 0.1, noise_budget_p95: float = 1.0,
) -> dict:
    """The run's own estimate of its Monte Carlo rendering error, from two half-sample renders,
    and whether it is within the noise budget.

    Over the bucket samples that hold light but stay below the full well (saturated samples
    carry no image information, and partly covered lamp pixels would dominate every mean):
    ``rel_rms``: RMS Monte Carlo error over the mean signal; ``to_shot_noise_variance_*``: the
    ratio of Monte Carlo variance to photon shot-noise variance (electrons^2) per sample, its
    median and 95th percentile computed from squared half differences pooled over 3x3 pixels
    (a single squared difference is a 1-degree-of-freedom chi-square variable whose median is 0.45
    of its mean; see :func:`mbcapture.plan.budget_quantiles`). Below ~0.1 the sensor's own noise
    dominates and more samples are wasted; above 1 rendering noise is visible in the images.
    ``budget``: the targets (render.noise_budget for the median, render.noise_budget_p95 for the
    95th percentile), whether they are met, and if not, the samples per pixel that would meet them
    (scaled from this run's as 1/spp, which randomized quasi-Monte Carlo beats: an upper bound).
    """
    from .plan import budget_quantiles, pooled

    if mc_var_exposure is None:
        return {"note": "render.spp = 1: no half-sample error estimate"}
    var_e = pooled(mc_var_exposure[buckets]) * k_e**2
    signal = buckets_e[buckets]
    use = (signal > 1.0) & (signal < full_well_e)
    if not use.any():
        return {"note": "no unsaturated lit samples"}
    ratio = var_e[use] / signal[use]
    median, p95 = budget_quantiles(ratio)
    factor = max(median / noise_budget, p95 / noise_budget_p95)
    budget = {"median_target": noise_budget, "p95_target": noise_budget_p95, "met": bool(factor <= 1.0)}
    if plan is not None:
        budget["spp_source"] = plan.spp_source
    if plan is not None and plan.spp is not None and factor > 1.0:
        budget["spp_that_would_meet"] = int(2 * np.ceil(float(plan.spp.max()) * factor / 2))
    return {
        "method": "two independent half-sample renders per stratum; squared differences pooled over 3x3 pixels",
        "rel_rms": float(np.sqrt(var_e[use].mean()) / signal[use].mean()),
        "to_shot_noise_variance_mean": float(var_e[use].sum() / signal[use].sum()),
        "to_shot_noise_variance_median": median,
        "to_shot_noise_variance_p95": p95,
        "budget": budget,
    }


def render_summary(report: dict) -> list[str]:
    """The lines a run prints about its rendering: noise against the budget, and the cache."""
    out = [noise_verdict(report.get("render_error", {}))]
    cache = report.get("render_cache", {})
    if cache.get("folder"):
        out.append(f"render cache: {cache['hits']} renders reused, {cache['rendered']} rendered ({cache['folder']})")
    return out


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
    from .render.llvm import llvm_target

    t = llvm_target()
    return f"{t['cpu']}, vector width {t['vector_width']}"


def render_cache(render) -> "RenderCache | None":
    """The render cache ``render.cache`` names (None when 'off'); ConfigError if its folder cannot be made."""
    from .render.cache import open_cache

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


def prepare(cfg: CaptureConfig) -> tuple[scenes.SceneModel, Timeline, Plan, list[np.random.SeedSequence]]:
    """Scene, timeline and render plan of a capture, and the run's seeds split per stage
    (0: plan jitter, 1: sensor noise, 2: render seeds, 3: the application's reference renders).
    Shared by ``run`` and ``plan``."""
    seeds = np.random.SeedSequence(cfg.seed).spawn(4)
    scene = camera_motion.apply(scenes.make_scene(cfg.scene.name, cfg.scene.params()), cfg.camera)
    timeline = protocols.build(cfg)
    if cfg.capture.frames > 1:
        from .video import frame_period_check

        frame_period_check(cfg, timeline)  # a frame period shorter than capture + readout: before anything renders
    plan = make_plan(timeline, scene, cfg.render, np.random.default_rng(seeds[0]))
    return scene, timeline, plan, seeds


def describe(cfg: CaptureConfig, timeline: Timeline, plan: Plan) -> dict:
    """What is captured and how it is rendered: the head of report.json and of ``mbcapture plan``."""
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
    }


def bucket_group_seconds(timeline: Timeline, switchable: tuple[str, ...]) -> np.ndarray:
    """(K, S): seconds bucket k collected while switchable group ``switchable[s]`` was on."""
    out = np.zeros((timeline.n_buckets, len(switchable)))
    for k in range(timeline.n_buckets):
        for s, g in enumerate(switchable):
            out[k, s] = float(timeline.gated_ticks([timeline.end_tick], k, g)[0] * timeline.tick_s)
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
    #: (H, W) bool, the moving region of the capture's span (:func:`moving_region`): it depends on the
    #: scene, the span and the film only, so the captures sharing these renders share it too
    moving: np.ndarray

    def plan_for(self, own: Plan) -> Plan:
        same = (own.groups == self.plan.groups and np.array_equal(own.times_s, self.plan.times_s)
                and np.array_equal(own.weights_s, self.plan.weights_s)
                and (own.spp is None or np.array_equal(own.spp, self.plan.spp)))
        if not same:
            raise ValueError("run_capture(rendered=...): the renders were made for another plan "
                             "(strata, render times, weights, groups or samples differ)")
        return self.plan


def run_capture(cfg: CaptureConfig, out_dir: str | Path | None = None, *, progress: bool = True,
                rendered: Rendered | None = None,
                on_rendered: "Callable[[Rendered], None] | None" = None) -> CaptureResult:
    """Run one capture. With ``out_dir``, write its outputs there (atomically). ``progress``: a
    status line for every stage and a bar for the render passes (stderr). ``rendered``: the render
    stage of another capture with the same renders (see :class:`Rendered`), used instead of
    rendering; ``on_rendered(Rendered)`` is called once this capture's render stage is done (before
    the sensor, so it is called even if a later stage fails)."""
    if cfg.capture.frames > 1:  # a video: a capture per frame (mbcapture/video.py)
        from .video import run_video

        return run_video(cfg, out_dir, progress=progress)
    if out_dir is not None:
        check_out_dir(Path(out_dir))
    own_render = rendered is None
    with StageStatus(progress, stages=4 + own_render * (1 + (cfg.render.spp is None)) + (out_dir is not None)) as status:
        return _run(cfg, out_dir, progress, status, rendered, on_rendered)


def _run(cfg: CaptureConfig, out_dir: str | Path | None, progress: bool, status: StageStatus,
         rendered: Rendered | None = None, on_rendered: "Callable[[Rendered], None] | None" = None,
         renderer=None) -> CaptureResult:
    """One capture; ``renderer``: a Renderer of this capture's scene to reuse (a video's frames), else one is made."""
    from .render import Renderer, ensure_llvm

    timer = _Timer()
    t_start = time.perf_counter()
    with timer("plan"), status.stage("plan"):
        scene, timeline, plan, seeds = prepare(cfg)
        app, app_params = cfg.app.resolve(cfg.capture.protocol)
    W, H = cfg.render.width, cfg.render.height
    t0_s, t1_s = timeline.seconds(timeline.start_tick), timeline.seconds(timeline.end_tick)

    with timer("render_setup"), status.stage("render setup (kernels, scene)"):
        llvm = ensure_llvm() if cfg.render.variant.startswith("llvm") else None
        cache = render_cache(cfg.render) if renderer is None else renderer.cache
        renderer = Renderer.from_config(scene, cfg, cache=cache) if renderer is None else renderer
    if rendered is None:
        pilot = status.stage("pilot render (spp from render.noise_budget)") if cfg.render.spp is None else nullcontext()
        with timer("pilot"), pilot:
            plan = resolve_spp(plan, renderer, cfg, seeds[2])  # render.spp null: spp from render.noise_budget
        with status.stage(f"render ({plan.passes} passes)"):
            integrated = integrate(renderer, plan, timeline.n_buckets, seeds[2], per_group=app.per_group, timer=timer,
                                   progress=progress)
        moving = moving_region(scene, float(t0_s), float(t1_s), W, H)
        if on_rendered is not None:
            on_rendered(Rendered(plan, integrated, moving))
    else:  # another capture's render stage, with the same renders
        plan, integrated, moving = rendered.plan_for(plan), rendered.integrated, rendered.moving
        if app.per_group and integrated.group_exposure is None:
            raise ValueError("run_capture(rendered=...): the application needs per-group exposures")
    exposure = integrated.exposure

    with timer("sensor"), status.stage("sensor"):
        spectral = cfg.render.variant.endswith("_spectral")
        k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)  # (C,) e- per render unit s (spectral: film units)
        buckets_e = exposure * k_e
        sensor_out = simulate_reads(
            buckets_e,
            [r.buckets for r in timeline.reads],
            cfg.sensor,
            sensor_seed(cfg, seeds),
            storage_s=timeline.storage_s(),  # dark current from each bucket's first slot to its read
            shared_photodiode=not timeline.sequential,
        )

    with timer("reconstruct"), status.stage(f"reconstruct ({app.name})"):
        mask = moving
        switchable = tuple(g for g in scene.groups if g in scene.switchable)
        data = CaptureData(
            cfg=cfg,
            scene=scene,
            timeline=timeline,
            plan=plan,
            read_names=[r.name for r in timeline.reads],
            exposure_s=np.array([float(timeline.read_exposure_ticks(r) * timeline.tick_s) for r in timeline.reads]),
            reads_dn=sensor_out.reads_dn,
            saturated=sensor_out.saturated,
            reads_e_expected=sensor_out.reads_e_expected,
            bucket_exposure=exposure,
            k_e=k_e,
            moving_mask=mask,
            switchable=switchable,
            bucket_group_s=bucket_group_seconds(timeline, switchable),
            group_exposure=integrated.group_exposure,
            renderer=renderer,
            seed=seeds[3],
        )
        out = app.reconstruct(data, app_params)

    report = {
        **describe(cfg, timeline, plan),
        "app": app.name,
        "render_units": "camera-weighted film value, e- m^-2 sr^-1 s^-1 before optics" if spectral else "W m^-2 sr^-1",
        "electrons_per_render_unit_second": dict(zip(renderer.channels, k_e.tolist())),  # per film channel
        "metrics": out.metrics,
        "render_error": {
            **render_error(integrated.mc_var, buckets_e, k_e, list(plan.buckets_read), cfg.sensor.full_well_e,
                           plan=plan, noise_budget=cfg.render.noise_budget, noise_budget_p95=cfg.render.noise_budget_p95),
            **temporal_error(integrated, k_e, list(plan.buckets_read), cfg.sensor.full_well_e),
        },
        "render_cache": {"folder": str(cache.root), **cache.stats.as_dict()} if cache is not None else {"folder": None},
        "versions": {**_versions(), "llvm": ".".join(map(str, llvm)) if llvm else None, "variant": cfg.render.variant,
                     "llvm_target": _llvm_target_label() if llvm else None},
    }
    report["render_error"]["verdict"] = noise_verdict(report["render_error"])
    result = CaptureResult(
        config=cfg,
        timeline=timeline,
        plan=plan,
        bucket_exposure=exposure,
        buckets_e=buckets_e,
        reads_expected_e=sensor_out.reads_e_expected,
        reads_dn=sensor_out.reads_dn,
        saturated=sensor_out.saturated,
        moving_mask=mask,
        app=app.name,
        images=out.images,
        render_var_exposure=integrated.mc_var,
        report=report,
        app_output=out,
    )
    report["timings_s"] = {k: round(v, 4) for k, v in timer.stages.items()}
    report["timings_s"]["total_before_write"] = round(time.perf_counter() - t_start, 4)
    if out_dir is not None:
        with status.stage("write outputs and report"):
            write_outputs(result, Path(out_dir))
        result.out_dir = Path(out_dir)
    return result


def write_outputs(result: CaptureResult, out: Path, extra=None, *, raw: bool = True) -> None:
    """Every output file of ``result`` into ``out``, atomically; ``extra(staging)`` writes more files
    (a video's) before report.html, which lists them; ``raw=False`` leaves out the bucket and read
    EXRs (buckets.exr, reads_expected.exr, reads.exr)."""
    cfg, tl = result.config, result.timeline
    names = [r.name for r in tl.reads]
    with staged_outputs(out) as st:
        if raw:
            st.write_exr("buckets.exr", {f"B{k + 1}": result.buckets_e[k] for k in range(tl.n_buckets)})
            st.write_exr("reads_expected.exr", {n: result.reads_expected_e[i] for i, n in enumerate(names)})
            st.write_exr("reads.exr", {n: result.reads_dn[i] for i, n in enumerate(names)})
        app_out = result.app_output
        st.write_exr(f"{result.app}.exr", app_out.images)
        for file, layers in app_out.extra_exr.items():
            st.write_exr(file, layers)
        for stem, (image, percentile) in app_out.png.items():
            st.write_png(f"{stem}.png", app_out.images[image], percentile)
        result.report["previews"] = write_read_previews(st, result)  # one common DN scale, and each its own
        st.write_yaml("config.yaml", cfg.to_yaml_dict())
        if extra is not None:
            extra(st)
        st.write_json("report.json", result.report)
        write_report(st, result)  # report.html and its plots, last: it lists every file
