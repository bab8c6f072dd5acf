"""One capture in memory: prepare, render, accumulate, the sensor stage, reconstruct.

    config -> scene + timeline -> plan (strata, weights) -> render + accumulate
           -> sensor (noise, full wells, reads) -> application (HDR, ...) -> metrics

:func:`capture_in_memory` is the one orchestrator of a capture; :func:`mbcapture.capture.run_capture`
adds its outputs, a video (:mod:`mbcapture.video`) calls it once per frame, and a sweep's points
share a render stage through :class:`Rendered`. Nothing here writes a file.
"""

from __future__ import annotations

import copy
import platform
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import numpy as np

from . import camera_motion, protocols, resources, scenes
from .application import AppOutput, CaptureData
from .budget import (
    BucketElectrons,
    TailModel,
    noise_verdict,
    render_error,
    resolve_spp,
    scout_spp,
    tail_pixels,
)
from .cluster import render_on_cluster
from .config import CaptureConfig, scene_of
from .errors import ConfigError
from .filmstore import IN_MEMORY, FilmStore
from .integrate import Integrated, integrate_tiles, refine, sample_counter, temporal_error
from .plan import Plan, make_plan
from .progress import StageStatus
from .render import Renderer, ensure_llvm
from .render.bands import group_bands
from .render.cache import open_cache
from .render.llvm import llvm_target
from .render.shadows import changing_region
from .sensor import electrons_per_render_second
from .simulate import sense
from .timeline import Timeline

if TYPE_CHECKING:
    from .render.cache import RenderCache


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
                          mbcapture.integrate.Integrated.mc_diff)
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
    video: object = None  # a video run (capture.frames > 1): mbcapture.video.VideoFrames of every frame

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
    (:func:`mbcapture.integrate.temporal_error`). Besides the renders they depend on the electrons per
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
    #: (H, W) bool, the moving region of the capture's span (:func:`mbcapture.camera_motion.moving_region`): it depends on the
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


@dataclass(frozen=True)
class FilmLayout:
    """How a capture's render passes go through its film: in ``tiles`` of rows (None: the whole film at once),
    with whole-film results made by ``store`` (in memory, or scratch files on disk: render.spill). Every pass
    (the first, adaptive sampling's scout, the top-up) renders tile by tile as the first does, and a tile's
    renders are the whole film's rows (:func:`mbcapture.integrate.integrate_tiles`), so the budget's choices,
    made on the whole film's arrays, are those of an untiled run."""

    tiles: tuple[tuple[int, int], ...] | None = None
    store: FilmStore = IN_MEMORY

    def rows(self, height: int) -> tuple[tuple[int, int], ...]:
        """The tiles (first row, end) of a film of ``height`` rows."""
        return self.tiles or ((0, height),)

    def integrate(self, renderer, plan: Plan, n_buckets: int, seed: np.random.SeedSequence, **kw) -> Integrated:
        """:func:`mbcapture.integrate.integrate_tiles` over this layout's tiles (``kw`` passed on)."""
        return integrate_tiles(renderer, plan, n_buckets, seed, self.rows(renderer.height), store=self.store, **kw)

    def tile_share(self, height: int) -> float:
        """The largest tile's share of the film's ``height`` rows: what a pass holds of the film at once."""
        return max(r1 - r0 for r0, r1 in self.rows(height)) / height

    def mix(self, a: np.ndarray, b: np.ndarray, c: float) -> np.ndarray:
        """``(a + c b) / (1 + c)`` in ``a``'s dtype, made by the store a tile of rows at a time (the film's rows
        are the axis before the last two), so that no whole-film float64 temporary is held."""
        out = self.store.empty(a.shape, a.dtype)
        for r0, r1 in self.rows(a.shape[-3]):
            rows = (..., slice(r0, r1), slice(None), slice(None))
            out[rows] = ((a[rows].astype(np.float64) + c * b[rows]) / (1.0 + c)).astype(a.dtype)
        return out


#: The whole film at once, in memory.
WHOLE_FILM = FilmLayout()


#: The top-up aims this far under the budget (the run's own estimate scatters from seed to seed), and
#: sizes its pass for the less favourable of variance ~ 1/spp and ~ spp^-TOP_UP_EXPONENT (the steep
#: end of what the pilot sees): a pass with fewer samples than the first is dearer per sample with
#: quasi-Monte Carlo samplers, one with more gains less than their exponent promises.
TOP_UP_MARGIN = 1.1
TOP_UP_EXPONENT = 1.5


def _read_figures(
    integrated: Integrated,
    timeline: Timeline,
    cfg: CaptureConfig,
    names: list[str] | None = None,
    plan: Plan | None = None,
) -> dict:
    """The run's own estimate of each read's rendering noise (render_error's ``reads``), of the reads
    ``names`` (default: all); with ``plan``, of the channel sets it reads (:attr:`Plan.read_sets`: a coded
    capture's render stage holds sub-frames, not buckets), else of the timeline's reads' buckets."""
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    sets = (
        list(zip(plan.read_names, plan.read_sets))
        if plan is not None
        else [(r.name, r.buckets) for r in timeline.reads]
    )
    sets = [(n, b) for n, b in sets if names is None or n in names]
    return render_error(
        integrated.mc_diff,
        BucketElectrons(integrated.exposure, k_e),
        k_e,
        [b for _, b in sets],
        [n for n, _ in sets],
        cfg.sensor.full_well_e,
        cfg.sensor.fd_full_well_e,
    ).get("reads", {})


def over_budget(
    integrated: Integrated,
    timeline: Timeline,
    cfg: CaptureConfig,
    reads: dict | None = None,
    *,
    tail: bool = False,
    plan: Plan | None = None,
) -> tuple[float, str | None, str, float]:
    """How far the run's own estimate of its rendering noise is over the budget's median and p95 targets
    (render.noise_budget, render.noise_budget_p95), and with ``tail`` its tail target too
    (render.noise_budget_tail), on its worst read: (max over reads of each figure over its target, that
    read, the figure that decides it (render_error's ``to_shot_noise_variance_median``, ``_p95`` or
    ``_p999``), its value); (0, None, "", 0) without an estimate. ``reads``: :func:`_read_figures` of
    ``integrated`` where they are at hand, else made here (with ``plan``, on its channel sets: a coded capture's)."""
    reads = _read_figures(integrated, timeline, cfg, plan=plan) if reads is None else reads
    if not reads:
        return 0.0, None, "", 0.0
    targets = {
        "to_shot_noise_variance_median": cfg.render.noise_budget,
        "to_shot_noise_variance_p95": cfg.render.noise_budget_p95,
        **({"to_shot_noise_variance_p999": cfg.render.noise_budget_tail} if tail else {}),
    }
    over = {(n, k): v[k] / t for n, v in reads.items() for k, t in targets.items()}
    worst, key = max(over, key=over.get)
    return over[(worst, key)], worst, key, reads[worst][key]


def no_room_for_another_pass(integrated: Integrated, layout: FilmLayout = WHOLE_FILM) -> str | None:
    """Why another render pass over the film cannot run here, or None: it holds a second set of the
    film's arrays while it renders (two float64 halves of each, its per-group and temporal sums), which
    must fit in free memory beside what the run holds (the top-up's second pass, adaptive sampling's
    scout). In tiles (``layout``) the pass holds that for its largest tile, and its results are whole-film
    arrays beside them unless they go to scratch files."""
    arrays = [
        a
        for a in (integrated.exposure, integrated.mc_diff, integrated.group_exposure, integrated.temporal_diff)
        if a is not None
    ]
    share = layout.tile_share(integrated.exposure.shape[-3])
    results = 0.0 if share == 1.0 or layout.store.spills else 1.0
    need = int((3 * share + results) * sum(a.size * 8 for a in arrays))
    free, where = resources.free_memory()
    if need <= free - resources.rss_bytes():
        return None
    return (
        f"room for a second set of the film's arrays ({need / 1e9:.2f} GB; "
        f"{max(free - resources.rss_bytes(), 0) / 1e9:.2f} GB free by {where})"
    )


def top_up(
    cfg: CaptureConfig,
    renderer: Renderer,
    plan: Plan,
    timeline: Timeline,
    integrated: Integrated,
    seed: np.random.SeedSequence,
    status: StageStatus,
    *,
    per_group: bool,
    timer,
    progress: bool,
    why_not: str | None,
    planned: list[tuple[np.ndarray, int]] | None = None,
    planned_reads: dict | None = None,
    tail: bool = False,
    layout: FilmLayout = WHOLE_FILM,
) -> tuple[Plan, Integrated, dict | None]:
    """render.top_up: when the pilot's choice left the run's own estimate over the median or p95 target
    (:func:`over_budget` > 1; the pilot extrapolates from 8 and 32 samples, and its exponent can be
    too steep for the count it reaches), or, after adaptive sampling's choice, over the tail target (where
    none of its rules brings the tail under it: a first pass of few samples whose rare paths the scout,
    at fewer still, did not see), a second pass of every stratum, combined with the first.
    ``planned``: adaptive sampling's tiers (:func:`scout_tail`), still to be rendered: the budget is judged
    on the image they will give (:func:`with_planned_refinement`; ``planned_reads``: its :func:`_read_figures`,
    where :func:`scout_tail` made them), the one the run returns; ``tail``: the tail target judged too (where
    adaptive sampling judged its rules and none met it). (Judged before
    them, a first pass a hair over the median target, 1.008x, took a top-up of 12 % more samples on the
    default capture, which its refined pixels would have brought under the target anyway.)

    The second pass renders each half of each stratum at a time of its own, drawn afresh in the
    stratum (:meth:`Plan.draw_times`). Where a moving edge crosses a pixel, where in the stratum a
    render's time falls is noise too, and the first pass's estimate holds it (:attr:`Plan.render_times`);
    a second pass at the first pass's times would repeat that noise, so combining them would not
    lower it. The returned plan says which times make up the combined exposure, with which weights
    (:meth:`Plan.exposure_time_mix`: the applications' truths of what the capture saw render there).

    With render.pattern 'shared' the second pass continues the first pass's patterns: each half of
    each pixel draws the samples of its sequence after all of the first pass's (the same keys), so
    that the two passes, weighed by their samples (``c = n2 / n1``), are one pass of n1 + n2 samples,
    stratified as a whole; its samples are ``n2 / n1 = F x`` :data:`TOP_UP_MARGIN` ``- 1`` for the
    first pass's factor F over the budget (variance at least as 1 / spp). Otherwise (render.pattern
    'own') the second pass is independent, with a variance V2 that satisfies 1 / (1 / V1 + 1 / V2) <=
    V1 / (F x :data:`TOP_UP_MARGIN`) (see :data:`TOP_UP_EXPONENT`), and ``c = V1 / V2`` (in each pass,
    the worst read's figure that decided the top-up, its median or its p95 ratio: inverse-variance
    weights, one for the whole film, where the budget is judged; a p95's pixels gain less from a
    smaller second pass than the median's). At most render.max_spp per stratum in all. The
    combination ``(E1 + c E2) / (1 + c)`` is unbiased whatever ``c``: each pass is (every sample of a
    scrambled sequence is uniform, wherever it starts), and ``c`` and the second pass's size depend on
    the whole film's noise, not on any pixel's value. So is its half-sample difference ``(d1 + c d2) /
    (1 + c)`` as an error estimate. The second pass goes through the film as the first did (``layout``: its
    tiles, and where its results are made). Returns the plan with the summed samples, the combined render stage
    and what report.json keeps (None when the first pass met the budget)."""
    if integrated.mc_diff is None:
        return plan, integrated, None
    factor, worst, figure, _ = over_budget(
        with_planned_refinement(integrated, planned or []), timeline, cfg, planned_reads, tail=tail, plan=plan
    )
    if factor <= 1.0:
        return plan, integrated, None
    why_not = why_not or no_room_for_another_pass(integrated, layout)
    if why_not is not None:
        return (
            plan,
            integrated,
            {"applied": False, "before": round(factor, 4), "note": f"not applied: a top-up needs {why_not}"},
        )
    status.add_stage()
    with status.stage(f"top-up render (the estimate is {factor:.2f}x the noise budget)"):
        start = time.perf_counter()
        count = sample_counter(renderer, plan)
        # with the shared pattern the second pass continues each pixel's sequences after the first's, and
        # the two weighed by their samples are one pass of n1 + n2: variance at least as 1 / spp, so
        # (n1 + n2) / n1 = F x margin. An independent second pass needs V1 / V2 = F x margin - 1, and a
        # smaller pass is dearer per sample (TOP_UP_EXPONENT)
        extend = plan.shares_pattern
        gap = factor * TOP_UP_MARGIN - 1.0
        share = gap if extend else max(gap ** (1.0 / TOP_UP_EXPONENT), gap)  # n2 / n1
        extra = np.array([2 * count(max(int(np.ceil(share * n / 2)), 1)) for n in plan.spp], np.int64)
        room = np.maximum(cfg.render.max_spp - plan.spp, 0) // 2 * 2  # two halves of whole samples
        if (room < 2).any():
            # the second pass must render every stratum: its exposure is the combination's only where
            # it holds all of them (a stratum left out would be missing from it, not less noisy)
            return (
                plan,
                integrated,
                {
                    "applied": False,
                    "before": round(factor, 4),
                    "note": f"render.max_spp={cfg.render.max_spp} reached in "
                    f"{int((room < 2).sum())} of {plan.passes} strata",
                },
            )
        extra = np.minimum(extra, room)
        child = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x70F))
        rng = np.random.default_rng(np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x70F, 0x7)))
        times = plan.draw_times(rng)[:, :, 0]
        second_plan = replace(plan, spp=extra, times_s=times[:, 0], half_times_s=times)
        second = layout.integrate(
            renderer,
            second_plan,
            timeline.n_channels,
            child,
            per_group=per_group,
            timer=timer,
            progress=progress,
            desc="top-up",
            continues=(plan, seed) if extend else None,
        )
        c = float(extra.sum() / plan.spp.sum())  # by their samples: each sample alike when they continue
        if not extend:  # the two passes' figures as rendered (the planned refinement adds to both alike)
            v1, v2 = (
                _read_figures(x, timeline, cfg, [worst], plan=plan).get(worst, {}).get(figure, 0.0)
                for x in (integrated, second)
            )
            c = v1 / v2 if v2 > 0 else c

        def mix(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
            return None if a is None or b is None else layout.mix(a, b, c)

        integrated = Integrated(
            exposure=mix(integrated.exposure, second.exposure),
            mc_diff=mix(integrated.mc_diff, second.mc_diff),
            group_exposure=mix(integrated.group_exposure, second.group_exposure),
            temporal_diff=mix(integrated.temporal_diff, second.temporal_diff),
        )
        # the exposure's times: the first pass's at weight 1 / (1 + c), the second's at c / (1 + c)
        t1, w1 = plan.exposure_time_mix()
        plan = replace(
            plan,
            spp=plan.spp + extra,
            mix_times_s=np.concatenate([t1, times], axis=1),
            mix_weights=np.concatenate([w1, c * second_plan.render_time_shares()], axis=1) / (1.0 + c),
        )
        info = {
            "applied": True,
            "before": round(factor, 4),
            "read": worst,
            "figure": figure.removeprefix("to_shot_noise_variance_"),
            "spp_added": extra.tolist(),
            "weight": round(c, 4),
            "after": round(
                over_budget(with_planned_refinement(integrated, planned or []), timeline, cfg, tail=tail, plan=plan)[0],
                4,
            ),
            "judged_with_refinement": bool(planned),
            "seconds": round(time.perf_counter() - start, 3),
        }
    return plan, integrated, info


#: Adaptive sampling renders each half of a stratum at this many times (one in each equal part of the
#: stratum) where a render's time is noise (the moving parts, their shadows, a moving camera's film): the value
#: changes within a stratum there, and one time per half leaves that change as noise more samples do not lower (jittered, its variance falls
#: as 1 / points^3 for an edge moving at constant speed); elsewhere at one time, which keeps each
#: render's samples together (the quasi-Monte Carlo samplers stratify within a render).
REFINE_TIME_POINTS = 4


def scout_tail(
    cfg: CaptureConfig,
    renderer: Renderer,
    plan: Plan,
    timeline: Timeline,
    integrated: Integrated,
    seed: np.random.SeedSequence,
    status: StageStatus,
    *,
    moving: np.ndarray,
    timer,
    progress: bool,
    layout: FilmLayout = WHOLE_FILM,
    have: np.ndarray | None = None,
    max_factor: int | None = None,
) -> tuple[list[tuple[np.ndarray, int]] | None, dict, dict | None]:
    """Adaptive sampling's choice (render.adaptive): a scout, the strata rendered again with seeds of their own
    at about a sixteenth of the first pass's samples (:func:`mbcapture.budget.scout_spp`), chooses the pixels
    whose predicted ratio (the scout's, scaled as 1/spp except in ``moving``, where a render's time is noise:
    :func:`mbcapture.render.shadows.changing_region`) exceeds
    a level x the tail target (:func:`mbcapture.budget.tail_pixels`), each with the factor of the first pass's
    samples it is to have. The rule, a level of budget.ADAPTIVE_LEVELS and a most factor, is the cheapest whose
    factors bring the run's own estimate of the tail, on the first pass as they will leave it
    (:func:`with_planned_refinement`; :class:`mbcapture.budget.TailModel`), under render.noise_budget_tail.
    Which pixels are chosen is independent of the first pass, and the rule is one choice from the whole film's
    estimate, so every pixel's estimate, and the run's own estimate of its error, is unbiased. Made before the top-up, which judges the budget on the image these factors will give
    (:func:`top_up`), and rendered after it (:func:`refine_tail`). Returns the tiers (None where adaptive
    sampling cannot apply), what report.json keeps and the chosen tiers' :func:`_read_figures` (what the top-up
    judges on). The scout goes through the film as the first pass did (``layout``); the choice is made on the
    whole film's arrays.

    ``have`` (flat, per pixel): a second round (:data:`ADAPTIVE_ROUNDS`), on a render stage already refined to these
    factors of the first pass's samples: the scout (seeds of its own again) is scaled to them, the rule judged on
    that stage's own estimate, and the tiers are factors of what each pixel holds, at most ``max_factor`` (default
    render.adaptive_max_factor)."""
    why = (
        "render.estimator independent"
        if plan.estimator != "independent"
        else "two half-sample renders per stratum (spp >= 2)"
        if integrated.mc_diff is None
        else no_room_for_another_pass(integrated, layout)
    )  # the scout renders the film again
    if why is not None:
        return None, {"pixels": 0, "note": f"not applied: adaptive sampling needs {why}"}, None
    with status.stage("adaptive sampling: scout"):
        start = time.perf_counter()
        k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
        spp = np.asarray(plan.spp, np.int64)
        scout_plan = replace(plan, spp=scout_spp(spp, sample_counter(renderer, plan)))
        again = () if have is None else (0x2D,)  # a second round's scout: seeds of its own again
        with timer("scout"):
            scout = layout.integrate(
                renderer,
                scout_plan,
                timeline.n_channels,
                np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x5C0, *again)),
                progress=progress,
                desc="scout" if have is None else "scout again",
            )
        # the first pass's ratio over the scout's: as 1/spp where nothing moves; 1 where a render's time is noise,
        # as there both passes draw one time per half-stratum, and their time noise does not fall with samples
        scale = np.where(moving, 1.0, float((scout_plan.spp / np.maximum(spp, 1)).max()))
        if have is not None:  # and over the factors the pixels hold
            scale = scale / have.reshape(scale.shape)
        on_moving = moving.ravel()
        with timer("adaptive_rule"):  # the tail each rule would leave, from the first pass's own estimate
            model = TailModel(
                integrated.mc_diff,
                BucketElectrons(integrated.exposure, k_e),
                k_e,
                list(plan.read_sets),
                cfg.sensor.full_well_e,
                cfg.sensor.fd_full_well_e,
                cfg.render.noise_budget_tail,
            )
        tried = []

        def meets(factors: np.ndarray) -> bool:
            tried.append(model.meets(factors))
            return tried[-1]

        tiers = tail_pixels(
            scout.mc_diff,
            BucketElectrons(scout.exposure, k_e),
            k_e,
            list(plan.read_sets),
            cfg.sensor.full_well_e,
            cfg.sensor.fd_full_well_e,
            cfg.render.noise_budget_tail,
            max_factor or cfg.render.adaptive_max_factor,
            scale,
            meets=meets,
            changing=on_moving,
        )
        with timer("adaptive_rule"):  # the run's own estimate on the image the tiers will give: the top-up's too
            planned = _read_figures(with_planned_refinement(integrated, tiers), timeline, cfg, plan=plan)
        n_pix = sum(p.size for p, _ in tiers)
        film = cfg.render.width * cfg.render.height
        held = np.ones(film, np.int64) if have is None else have
        info = {
            "scout": {"spp": scout_plan.spp.tolist(), "seconds": round(time.perf_counter() - start, 3)},
            "pixels": int(n_pix),
            "share": round(n_pix / film, 6),
            "tiers": [{"factor": f, "pixels": int(p.size), "moving_pixels": int(on_moving[p].sum())} for p, f in tiers],
            # the second pass's samples over the first pass's, on the whole film
            "added_samples": round(sum(int(held[p].sum()) * (f - 1) for p, f in tiers) / film, 4),
        }
        # how many rules were judged, and the tail the run's own estimate predicts for the one kept
        info.update(
            rules_judged=len(tried),
            tail_met_by_rule=bool(tried and tried[-1]),
            predicted_tail=round(max((v["to_shot_noise_variance_p999"] for v in planned.values()), default=0.0), 4),
        )
    return tiers, info, planned


def with_planned_refinement(integrated: Integrated, tiers: list[tuple[np.ndarray, int]]) -> Integrated:
    """``integrated`` with the error estimate it will have once adaptive sampling has given each pixel of
    ``tiers`` its factor f of the samples: the half-sample differences over sqrt(f) there (variance ~ 1/spp,
    as :func:`mbcapture.budget.factor_tiers` assumes; scripts/adaptive_frontier.py measured the tail so
    predicted within 1 %). What the top-up judges the budget on, as the image the run returns will have it."""
    if not tiers or integrated.mc_diff is None:
        return integrated
    K, H, W, C = integrated.mc_diff.shape
    shrink = np.ones(H * W, np.float32)
    for pixels, factor in tiers:
        shrink[pixels] = 1.0 / np.sqrt(factor)
    return replace(integrated, mc_diff=integrated.mc_diff * shrink.reshape(1, H, W, 1))


def refine_tail(
    cfg: CaptureConfig,
    renderer: Renderer,
    plan: Plan,
    integrated: Integrated,
    tiers: list[tuple[np.ndarray, int]],
    info: dict,
    seed: np.random.SeedSequence,
    status: StageStatus,
    *,
    moving: np.ndarray,
    per_group: bool,
    timer,
    progress: bool,
    have: np.ndarray | None = None,
    layout: FilmLayout = WHOLE_FILM,
) -> tuple[Integrated, dict]:
    """Adaptive sampling's second pass (render.adaptive): the pixels of :func:`scout_tail`'s ``tiers`` rendered
    again with more samples and added to the first pass (:func:`mbcapture.integrate.refine`), those in
    ``moving`` (where a render's time is noise, :func:`mbcapture.render.shadows.changing_region`) at
    :data:`REFINE_TIME_POINTS` times per half-stratum. A
    top-up between the two keeps the tiers (chosen for the first pass's samples, they then give a little more
    than they need: the top-up lowered every pixel's ratio). Returns the refined render stage and what
    report.json keeps (``info``, the scout's, completed). ``have``: a second round's (:func:`scout_tail`), the
    tiers' factors then of what each pixel holds."""
    with status.stage("adaptive sampling: refine"):
        start = time.perf_counter()
        pixels = np.concatenate([p for p, _ in tiers])
        held = np.ones(pixels.size, np.int64) if have is None else have[pixels]
        factors = held * np.concatenate([np.full(p.size, f, np.int64) for p, f in tiers])
        on_moving = moving.ravel()[pixels]
        again = () if have is None else (0x2D,)
        for part, points in ((~on_moving, 1), (on_moving, REFINE_TIME_POINTS)):  # every tier at once
            if part.any():
                child = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0xADA, points, *again))
                integrated = refine(
                    renderer,
                    plan,
                    integrated,
                    pixels[part],
                    factors[part],
                    child,
                    points=points,
                    per_group=per_group,
                    timer=timer,
                    progress=progress,
                    have=held[part],
                    desc=f"refine {int(part.sum())} px" + (" moving" if points > 1 else ""),
                    store=layout.store,
                )
        info["seconds"] = round(info["scout"]["seconds"] + time.perf_counter() - start, 3)
    return integrated, info


#: The most rounds of adaptive sampling: a second where the first's refined render stage still has its own estimate
#: of the tail over its target (the rule is judged on the first pass's estimate divided by the factors, and the pixels that draw
#: rare paths of their own in the second pass are not in it), with a scout of its own, at most
#: :data:`SECOND_ROUND_MAX_FACTOR` times what each pixel holds. Measured on multi_flash at 160x128: a rule judged to leave 0.95 left 1.13, the 68 samples over the target (61 allowed) at static
#: silhouettes given 16-32x and at the rim of the changing region.
ADAPTIVE_ROUNDS = 2
SECOND_ROUND_MAX_FACTOR = 4


def second_round(
    cfg: CaptureConfig,
    renderer: Renderer,
    plan: Plan,
    timeline: Timeline,
    integrated: Integrated,
    tiers: list[tuple[np.ndarray, int]],
    info: dict,
    seed: np.random.SeedSequence,
    status: StageStatus,
    *,
    moving: np.ndarray,
    per_group: bool,
    timer,
    progress: bool,
    layout: FilmLayout = WHOLE_FILM,
) -> tuple[Integrated, dict]:
    """Adaptive sampling's second round (:data:`ADAPTIVE_ROUNDS`), where the refined render stage's own estimate of
    the tail is still over render.noise_budget_tail on some read (the median and p95 are the top-up's):
    :func:`scout_tail` and :func:`refine_tail` again, from what each pixel holds. Unbiased as the first round is: its
    pixels come from a scout of its own, its rule from the whole film's estimate, and whether it runs from the whole
    film's. Returns the render stage and ``info``, with ``second_round`` where one ran."""
    reads = _read_figures(integrated, timeline, cfg, plan=plan)
    factor = max((v["to_shot_noise_variance_p999"] for v in reads.values()), default=0.0) / cfg.render.noise_budget_tail
    if ADAPTIVE_ROUNDS < 2 or factor <= 1.0:
        return integrated, info
    film = cfg.render.width * cfg.render.height
    have = np.ones(film, np.int64)
    for pixels, f in tiers:
        have[pixels] = f
    status.add_stage()
    more, round_info, _ = scout_tail(
        cfg,
        renderer,
        plan,
        timeline,
        integrated,
        seed,
        status,
        moving=moving,
        timer=timer,
        progress=progress,
        have=have,
        max_factor=SECOND_ROUND_MAX_FACTOR,
        layout=layout,
    )
    round_info["before"] = round(factor, 4)
    if more:
        status.add_stage()
        integrated, round_info = refine_tail(
            cfg,
            renderer,
            plan,
            integrated,
            more,
            round_info,
            seed,
            status,
            moving=moving,
            per_group=per_group,
            timer=timer,
            progress=progress,
            have=have,
            layout=layout,
        )
    info["second_round"] = round_info
    return integrated, info


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
    ``rendered``), accumulate, the sensor stage (:func:`mbcapture.simulate.sense`), reconstruct.
    ``status``: the stage lines; ``progress``: a bar for the render passes; ``renderer``: a Renderer
    of this capture's scene to reuse (a video's frames), else one is made; ``on_rendered``: called
    with the render stage once it is done; ``client``: a Dask client whose workers render the strata
    (:mod:`mbcapture.cluster`); ``planned``: :func:`prepare` and :func:`mbcapture.resources.plan_resources`
    of ``cfg`` made already, and the seconds they took (:func:`mbcapture.capture.check_resources`),
    else made here. BLAS runs on one thread throughout (:func:`mbcapture.resources.one_blas_thread`)."""
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
    """:func:`capture_in_memory`'s work."""
    timer = _Timer()
    t_start = time.perf_counter()
    cluster_info = None  # what the cluster rendered (report.json "cluster"), with a client
    adaptive_info = None  # what adaptive sampling refined (report.json "adaptive")
    top_up_info = None  # the budget's second pass (report.json "top_up")
    with timer("plan"), status.stage("plan"):
        app, app_params = cfg.app.resolve(cfg.capture.protocol)
        if planned is None:
            scene, timeline, plan, seeds = prepare(cfg)
            need = resources.plan_resources(cfg, timeline, plan, app)
        else:
            (scene, timeline, plan, seeds), need, seconds = planned
            timer.stages["plan"] = seconds  # and this stage's own time added
    W, H = cfg.render.width, cfg.render.height
    t0_s, t1_s = timeline.seconds(timeline.start_tick), timeline.seconds(timeline.end_tick)

    with timer("render_setup"), status.stage("render setup (kernels, scene)"):
        llvm = ensure_llvm() if cfg.render.variant.startswith("llvm") else None
        cache = render_cache(cfg.render) if renderer is None else renderer.cache
        renderer = Renderer.from_config(scene, cfg, cache=cache) if renderer is None else renderer
    # tiles of rows (runs of whole render bands) for render, accumulation and the sensor: the same result
    # whatever their number (mbcapture.render.bands), so the memory plan alone chooses it
    tiles = group_bands(renderer.bands, need.tiles)
    # a tiled film's whole-film results in scratch files on disk when the plan says so (render.spill)
    store = FilmStore(resources.spill_folder(cfg)) if need.spill_bytes and len(tiles) > 1 else IN_MEMORY
    # every render pass through the film in those tiles; on a cluster only the first pass renders on the workers,
    # adaptive sampling's scout, top-up and refinement in this process (the same renders: the same values)
    layout = FilmLayout(tuple(tuple(t) for t in tiles), store)
    if rendered is None:
        pilot = status.stage("pilot render (spp from render.noise_budget)") if cfg.render.spp is None else nullcontext()
        with timer("pilot"), pilot:
            plan = resolve_spp(plan, renderer, cfg, seeds[2])  # render.spp null: spp from render.noise_budget
        on_cluster = None
        if client is not None:  # each tile's renders on the workers first, then accumulated here
            infos: list[dict] = []

            def on_cluster(rows: tuple[int, int]) -> None:
                with timer("cluster"):
                    infos.append(render_on_cluster(client, cfg, plan, seeds[2], renderer, rows=rows))

        where = " on the cluster" if client is not None else ""
        in_tiles = f" x {len(tiles)} tiles" if len(tiles) > 1 else ""
        with status.stage(f"render{where} ({plan.passes} passes{in_tiles})"):
            integrated = integrate_tiles(
                renderer,
                plan,
                timeline.n_channels,
                seeds[2],
                tiles,
                per_group=app.per_group,
                timer=timer,
                progress=progress,
                before_tile=on_cluster,
                store=store,
            )
        if client is not None:
            cluster_info = merge_cluster_info(infos)
        moving = camera_motion.moving_region(scene, float(t0_s), float(t1_s), W, H)
        tiers = None  # adaptive sampling's choice of pixels, made before the top-up judges the budget
        planned_reads = None  # the run's own estimate on the image those tiers will give
        changing = moving  # where a render's time within its stratum is noise
        if cfg.render.spp is None and cfg.render.adaptive:
            with timer("adaptive_rule"):
                changing = changing_region(renderer, float(t0_s), float(t1_s), W, H, moving=moving)
            tiers, adaptive_info, planned_reads = scout_tail(
                cfg,
                renderer,
                plan,
                timeline,
                integrated,
                seeds[2],
                status,
                moving=changing,
                timer=timer,
                progress=progress,
                layout=layout,
            )
        if cfg.render.spp is None and cfg.render.top_up:
            why_not = "render.estimator independent" if plan.estimator != "independent" else None
            plan, integrated, top_up_info = top_up(
                cfg,
                renderer,
                plan,
                timeline,
                integrated,
                seeds[2],
                status,
                per_group=app.per_group,
                timer=timer,
                progress=progress,
                why_not=why_not,
                planned=tiers,
                planned_reads=planned_reads,
                tail=bool(
                    adaptive_info and adaptive_info.get("rules_judged") and not adaptive_info["tail_met_by_rule"]
                ),
                layout=layout,
            )
        if tiers:
            status.add_stage()  # the scout's stage was counted at the start, its second pass is one more
            integrated, adaptive_info = refine_tail(
                cfg,
                renderer,
                plan,
                integrated,
                tiers,
                adaptive_info,
                seeds[2],
                status,
                moving=changing,
                per_group=app.per_group,
                timer=timer,
                progress=progress,
                layout=layout,
            )
            integrated, adaptive_info = second_round(
                cfg,
                renderer,
                plan,
                timeline,
                integrated,
                tiers,
                adaptive_info,
                seeds[2],
                status,
                moving=changing,
                per_group=app.per_group,
                timer=timer,
                progress=progress,
                layout=layout,
            )
        rendered = Rendered(plan, integrated, moving)
        if on_rendered is not None:
            on_rendered(rendered)
    else:  # another capture's render stage, with the same renders
        plan, integrated, moving = rendered.plan_for(plan), rendered.integrated, rendered.moving
        if app.per_group and integrated.group_exposure is None:
            raise ValueError("run_capture(rendered=...): the application needs per-group exposures")
    channels = integrated  # per channel: the buckets, or a coded capture's sub-frames
    with timer("accumulate"):
        integrated = integrated.routed(timeline)  # per bucket, each pixel through its gate code
    exposure = integrated.exposure

    with timer("sensor"), status.stage("sensor"):
        spectral = cfg.render.variant.endswith("_spectral")
        k_e = electrons_per_render_second(
            cfg.sensor, cfg.render.variant
        )  # (C,) e- per render unit s (spectral: film units)
        # the expected electrons exposure x k_e, made tile by tile inside the sensor stage
        sensor_out = sense(
            timeline, exposure, cfg.sensor, sensor_seed(cfg, seeds), tiles=tiles, per_unit=k_e, store=store
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
            mosaic_dn=sensor_out.mosaic_dn,
            mosaic_saturated=sensor_out.mosaic_saturated,
        )
        out = app.reconstruct(data, app_params)

    report = {
        **describe(cfg, timeline, plan, need),
        "tiles": {
            "count": len(tiles),
            "rows": [list(t) for t in tiles],
            "render_bands": len(renderer.bands),
            "spill": {"folder": str(store.folder), "gb": round(store.spilled_bytes / resources.GB, 3)}
            if store.spills
            else None,
        },
        "app": app.name,
        "render_units": "camera-weighted film value, e- m^-2 sr^-1 s^-1 before optics" if spectral else "W m^-2 sr^-1",
        "electrons_per_render_unit_second": dict(zip(renderer.channels, k_e.tolist())),  # per film channel
        "metrics": out.metrics,
        "render_error": _error_estimates(rendered, integrated, channels, k_e, timeline, plan, cfg),
        "render_cache": {"folder": str(cache.root), **cache.stats.as_dict()} if cache is not None else {"folder": None},
        "cluster": cluster_info,
        "adaptive": adaptive_info,
        "top_up": top_up_info,
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
    result = CaptureResult(
        config=cfg,
        timeline=timeline,
        plan=plan,
        bucket_exposure=exposure,
        k_e=k_e,
        reads_expected_e=sensor_out.reads_e_expected,
        reads_dn=sensor_out.reads_dn,
        saturated=sensor_out.saturated,
        moving_mask=mask,
        app=app.name,
        images=out.images,
        render_mc_diff=integrated.mc_diff,
        mosaic_dn=sensor_out.mosaic_dn,
        film_store=store,
        report=report,
        app_output=out,
    )
    report["timings_s"] = {k: round(v, 4) for k, v in timer.stages.items()}
    report["timings_s"]["total_before_write"] = round(time.perf_counter() - t_start, 4)
    return result
