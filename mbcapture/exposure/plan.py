"""The render plan: time strata chosen by image motion, and exact gate x emitter weights.

The bucket images are  B_k = integral gate_k(t) * sum_g drive_g(t) * L_g(geometry(t)) dt.
Gates and flashes switch thousands of times, geometry moves slowly: the planner cuts the
collecting time into strata inside which no moving point travels more than
``render.max_motion_px`` pixels, renders each stratum once at a jittered time, and integrates
gate x drive analytically (:meth:`Timeline.weights_ticks`). A static scene is one stratum
however many buckets, flashes and periods there are.

Left out: emitter groups with no weight in any read bucket, buckets never read, strata with
no weight at all (and, per stratum, groups with no weight in it: see integrate).

``render.planner: naive`` is the baseline the planner is measured against: one render per
collecting slot of every period, at a jittered time inside the slot.

Samples per pixel (``render.spp`` null) are chosen by :mod:`mbcapture.budget` from a pilot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..render.settings import RenderSection
from ..errors import ConfigError
from ..scene.scenes import SceneModel
from ..timing.timeline import Timeline

#: Motion is sampled this finely (per collecting interval) to bound image motion.
_MOTION_SAMPLES = 4096
#: The naive planner refuses captures with more slots than this.
MAX_NAIVE_PASSES = 200_000


@dataclass(frozen=True)
class Plan:
    """What will be rendered.

    starts_ticks, ends_ticks   (J,) stratum bounds [start, end), int64 ticks.
    times_s       (J,) a scene time uniform in each stratum (jittered): the time of its first half-sample
                  render, and of the stratum where one time stands for it (the pilot, a truth render).
    half_times_s  (J, 2) the times of each stratum's two half-sample renders, drawn independently, each
                  uniform in the stratum (the first is ``times_s``): see :attr:`render_times`.
    bounds_s      (J, 2) each stratum's start and end, s (what :meth:`draw_times` jitters in).
    mix_times_s, mix_weights  (J, M) after a top-up (:func:`mbcapture.budget.adaptive.top_up`): every time whose
                  render makes up the stratum's exposure, and its weight in it; None before
                  (:meth:`exposure_time_mix`).
    weights_s     (J, K, G) seconds of stratum j in which channel k (a bucket, or a coded capture's
                  sub-frame) collects while group g is on.
    groups        the emitter groups rendered (G), in the scene's order.
    spp           (J,) int64 samples per pixel of each stratum, or None until :func:`choose_spp`.
    spp_source    'render.spp', 'noise_budget' (pilot) or 'pending' (noise budget, no pilot yet).
    planner       'motion' or 'naive'.
    pilot         what the pilot measured (None without one).
    cost          the cost model {c0_s, c1_s_per_spp, compile_s, accumulate_s} (None without a pilot/probe).
    read_sets     the channels each read of the timeline sums (the noise budget is met on reads; a coded
                  capture: one set per read and distinct pixel code), and
    read_names    their names.
    """

    starts_ticks: np.ndarray
    ends_ticks: np.ndarray
    times_s: np.ndarray
    weights_s: np.ndarray
    groups: tuple[str, ...]
    buckets_read: tuple[int, ...]
    spp: np.ndarray | None
    max_motion_px: float
    motion_px_total: float
    coarsened: bool
    left_out_groups: tuple[str, ...]
    notes: list[str] = field(default_factory=list)
    spp_source: str = "render.spp"
    planner: str = "motion"
    noise_budget: float | None = None
    pilot: dict | None = None
    cost: dict | None = None
    estimator: str = "independent"
    #: render.pattern: 'own' (each render its sampler's pattern) or 'shared' (mbcapture.render.pattern)
    pattern: str = "shared"
    base_spp_setting: int | None = None
    base_time_s: float = 0.0
    max_spp_per_render: int = 1024
    read_sets: tuple[tuple[int, ...], ...] = ()
    read_names: tuple[str, ...] = ()
    bounds_s: np.ndarray | None = None
    half_times_s: np.ndarray | None = None
    mix_times_s: np.ndarray | None = None
    mix_weights: np.ndarray | None = None

    @property
    def shares_pattern(self) -> bool:
        """Whether the strata draw their samples from one shared pattern (render.pattern 'shared' with the
        ``independent`` estimator; the ``difference`` estimator's strata reuse its base render's numbers)."""
        return self.pattern == "shared" and self.estimator == "independent"

    @property
    def render_times(self) -> np.ndarray:
        """(J, 2) the scene time of each stratum's two half-sample renders.

        Each half is rendered at its own time, uniform in the stratum and independent of the other's.
        A half's value then carries both its Monte Carlo noise and the noise of where in the stratum
        its time fell (a moving edge's position), so the halves' difference, which the run's own error
        estimate squares, holds both, as two captures with different seeds do. Rendered at one shared
        time, the halves agreed on the time noise and the estimate left it out (docs/noise.md).
        A plan built without half times (tests) renders both halves at ``times_s``."""
        if self.half_times_s is not None:
            return self.half_times_s
        return np.repeat(np.asarray(self.times_s, dtype=np.float64)[:, None], 2, axis=1)

    def render_time_shares(self) -> np.ndarray:
        """(J, 2) each half-sample render's share of its stratum's samples, as :func:`mbcapture.exposure.integrate.integrate`
        splits them (n // 2 and n - n // 2 when every stratum has 2 samples or more; else one render, at the
        first half's time): what a truth rendered at :attr:`render_times` weights each time with."""
        spp = np.asarray(self.spp, dtype=np.int64)
        if spp.size and np.all(spp >= 2):
            first = (spp // 2) / spp
            return np.stack([first, 1.0 - first], axis=1)
        return np.stack([np.ones(self.passes), np.zeros(self.passes)], axis=1)

    def exposure_time_mix(self) -> tuple[np.ndarray, np.ndarray]:
        """((J, M) times, (J, M) weights): the scene times whose renders make up each stratum's exposure,
        and each one's weight in it (each row sums to 1). What a truth of "what the capture saw"
        (flash matting's alpha, multi-flash's depth edges) renders at. The two half-sample renders
        (:attr:`render_times`, :meth:`render_time_shares`), or after a top-up both passes' four,
        weighted as the top-up combined them."""
        if self.mix_times_s is not None:
            return self.mix_times_s, self.mix_weights
        return self.render_times, self.render_time_shares()

    def draw_times(self, rng: np.random.Generator, per_stratum: int = 2, points: int = 1) -> np.ndarray:
        """(J, per_stratum, points) fresh render times, independent of each other and of ``times_s``
        (the second passes of adaptive sampling and the top-up draw their own:
        :func:`mbcapture.exposure.integrate.refine`, :func:`mbcapture.budget.adaptive.top_up`). Each of a stratum's
        ``per_stratum`` draws is ``points`` times, one uniform in each of ``points`` equal parts of
        the stratum (jittered: their mean is an unbiased, stratified estimate of the stratum's mean
        over time); with ``points`` 1, one time uniform in the stratum. A plan built
        without stratum bounds (tests) has nothing to draw in: its :attr:`render_times`, one point each."""
        if self.bounds_s is None:
            return self.render_times[:, :per_stratum, None]
        start, end = self.bounds_s[:, 0, None, None], self.bounds_s[:, 1, None, None]
        u = (np.arange(points) + rng.random((self.passes, per_stratum, points))) / points
        return np.minimum(start + u * (end - start), np.nextafter(end, start))

    @property
    def base_spp(self) -> int:
        """Samples per pixel of the ``difference`` estimator's base: render.base_spp, or as many as
        all strata together (the base then matches what the strata would give static pixels)."""
        if self.base_spp_setting is not None:
            return int(self.base_spp_setting)
        return int(2 * np.ceil(self.spp.sum() / 2)) if self.spp is not None else 0

    @property
    def passes(self) -> int:
        return len(self.times_s)

    @property
    def renders(self) -> int:
        """Mitsuba renders of the main pass: two halves per stratum with spp >= 2, else one; with the
        ``difference`` estimator also the base (in chunks of at most max_spp) and B^crn per count."""
        if self.spp is None:
            return 2 * self.passes
        n = int(np.where(self.spp >= 2, 2, 1).sum())
        if self.estimator == "difference":
            chunk = max(self.max_spp_per_render // 2, 1)
            n += 2 * int(np.ceil(self.base_spp / 2 / chunk)) + 2 * len(np.unique(self.spp))
        return n

    def spp_label(self) -> str:
        """'16' (uniform), '2-48 (mean 11.3)' (per stratum) or 'pending (noise budget)'."""
        if self.spp is None:
            return "chosen by the pilot (render.noise_budget)"
        lo, hi = int(self.spp.min()), int(self.spp.max())
        return str(lo) if lo == hi else f"{lo}-{hi} (mean {self.spp.mean():.1f})"

    def estimate(self) -> dict | None:
        """Seconds the main render (and accumulation) should take, from the cost model."""
        if self.cost is None or self.spp is None:
            return None
        c = self.cost
        samples = float(self.spp.sum()) + (
            self.base_spp + float(np.unique(self.spp).sum()) if self.estimator == "difference" else 0.0
        )
        render_s = self.renders * c["c0_s"] + c["c1_s_per_spp"] * samples
        acc_s = self.renders * c["accumulate_s"]
        return {
            "render_s": round(render_s, 3),
            "accumulate_s": round(acc_s, 3),
            "total_render_stages_s": round(render_s + acc_s, 3),
            "model": "renders x c0 + c1 x sum(spp) + renders x accumulate, constants timed by the pilot/probe renders",
        }

    def summary(self, timeline: Timeline) -> dict:
        spp = None if self.spp is None else self.spp
        # the times each stratum's exposure was rendered at, and their weights (none before the samples are chosen)
        mix = self.exposure_time_mix() if spp is not None else (self.render_times, [None] * self.passes)
        uniform = spp is not None and int(spp.min()) == int(spp.max())
        return {
            "planner": self.planner,
            "passes": self.passes,
            # an int when every stratum has the same spp; otherwise the (rounded) mean, with the
            # per-stratum values in "strata" and the range in "spp_range"
            "spp": None if spp is None else (int(spp[0]) if uniform else int(round(float(spp.mean())))),
            "spp_range": None if spp is None else [int(spp.min()), int(spp.max())],
            "spp_source": self.spp_source,
            "estimator": self.estimator,
            "pattern": self.pattern,
            "base_spp": self.base_spp if self.estimator == "difference" and self.spp is not None else None,
            "noise_budget": self.noise_budget,
            "samples_per_pixel_total": None if spp is None else int(spp.sum()),
            "renders": self.renders,
            "pilot": self.pilot,
            "cost_model": self.cost,
            "estimate_s": self.estimate(),
            "groups_rendered": list(self.groups),
            "groups_left_out": list(self.left_out_groups),
            "buckets_read": [b + 1 for b in self.buckets_read],
            "max_motion_px": self.max_motion_px,
            "image_motion_px_total": round(self.motion_px_total, 3),
            "coarsened": self.coarsened,
            "tick_s": float(timeline.tick_s),  # every time of the schedule is a whole number of ticks
            "tick_s_exact": str(timeline.tick_s),  # ... of exactly this fraction of a second
            "strata": [
                {
                    "start_s": float(timeline.seconds(a)),
                    "end_s": float(timeline.seconds(b)),
                    "render_times_s": [float(x) for x in t],
                    "render_time_weights": None if wt is None else [round(float(x), 6) for x in wt],
                    "spp": None if spp is None else int(n),
                }
                for a, b, t, wt, n in zip(
                    self.starts_ticks, self.ends_ticks, *mix, spp if spp is not None else [None] * self.passes
                )
            ],
            "notes": self.notes,
        }


def _image_path_length(scene: SceneModel, times_s: np.ndarray, width: int, height: int) -> np.ndarray:
    """Cumulative image-space path length (px) of the fastest moving point at ``times_s``; with a
    moving camera (``camera.shake``) the frame's reference points move too, so the bound covers the
    projected motion of the whole frame."""
    px = scene.image_points(times_s, width, height)  # (T, M, 2): moving parts, and the frame if the camera moves
    step = np.linalg.norm(np.diff(px, axis=0), axis=-1).max(axis=1)  # (T-1,)
    return np.concatenate([[0.0], np.cumsum(step)])


def _period_of(tl: Timeline, a: int, b: int) -> tuple[int, int] | None:
    """(start tick, period ticks) of the one repeating segment that spans [a, b], else None."""
    for seg in tl.segments:
        if seg.start_tick <= a and b <= seg.end_tick and seg.repeats > 1:
            return seg.start_tick, seg.period_ticks
    return None


def _split_interval(
    scene, tl: Timeline, a: int, b: int, render: RenderSection, fewest: int = 1
) -> tuple[list[int], float]:
    """Boundaries inside [a, b] so that each piece moves at most max_motion_px, and where the image moves at all,
    at least ``fewest`` pieces (render.min_strata, shared among the capture's intervals).

    Where the gate pattern repeats and one period moves the image by less than a quarter of
    max_motion_px, the cuts fall on period boundaries: every stratum then holds whole periods,
    so each bucket's weight in it is exactly proportional to its duty cycle and the interleaved
    reads mix the same renders in the same proportions (identical motion sampling, no
    stratum-to-bucket aliasing). The pieces are planned for max_motion_px minus one period's
    motion, so moving a cut by up to half a period on either side keeps the bound.
    """
    ticks = np.unique(np.linspace(a, b, _MOTION_SAMPLES + 1).round().astype(np.int64))
    s = _image_path_length(scene, tl.seconds(ticks), render.width, render.height)
    total = float(s[-1])
    budget = render.max_motion_px
    periodic = _period_of(tl, a, b)
    snap = None
    if periodic is not None:
        start, period = periodic
        # largest image motion within any window of one period (sampled path length)
        reach = np.interp(ticks + period, ticks, s, right=total) - s
        per_period = float(reach.max())
        if per_period < budget / 4:
            snap, budget = periodic, budget - per_period
    least = fewest if total > 0 else 1  # render.min_strata's share, where the image moves at all
    n = max(int(np.ceil(total / budget - 1e-9)), least)
    n = min(n, len(ticks) - 1)
    targets = np.linspace(0.0, total, n + 1)[1:-1]
    inner = np.interp(targets, s, ticks.astype(np.float64)) if n > 1 else np.array([])
    if snap is not None and inner.size:
        start, period = snap
        snapped = start + np.round((inner - start) / period) * period
        snapped = np.unique(snapped[(snapped > a) & (snapped < b)])
        # fewer periods than render.min_strata asks strata (a capture of two or three periods): cuts inside them
        if snapped.size + 1 >= min(n, least):  # n may be fewer: the interval's ticks
            inner = snapped
    inner = np.unique(np.round(inner).astype(np.int64))
    return [a, *inner.tolist(), b], total


def make_plan(
    timeline: Timeline,
    scene: SceneModel,
    render: RenderSection,
    rng: np.random.Generator,
) -> Plan:
    intervals = timeline.collecting_intervals()
    notes: list[str] = []
    motion_total = 0.0
    if render.planner == "naive":
        edges = _slot_edges(timeline)
        notes.append("naive planner: one render per collecting slot of every period")
    elif scene.is_static:
        edges = [intervals[0][0], intervals[-1][1]]
        notes.append("static scene: one stratum")
    else:
        edges = []
        # render.min_strata: each stratum's two halves draw a time each, so a stratum's time noise (a moving
        # edge's change) and the run's own estimate of it rest on one pair of times, the same for every pixel
        fewest = int(np.ceil(render.min_strata / len(intervals)))
        for a, b in intervals:
            cuts, moved = _split_interval(scene, timeline, a, b, render, fewest)
            motion_total += moved
            edges.extend(cuts if not edges or edges[-1] != cuts[0] else cuts[1:])
    edges = np.unique(np.asarray(edges, dtype=np.int64))

    coarsened = False
    if render.planner == "motion" and len(edges) - 1 > render.max_strata:
        keep = np.unique(np.linspace(0, len(edges) - 1, render.max_strata + 1).round().astype(int))
        edges = edges[keep]
        coarsened = True
        notes.append(
            f"coarsened to render.max_strata={render.max_strata} strata; image motion per stratum "
            f"now up to ~{motion_total / render.max_strata:.2f} px"
        )

    read_names, read_sets = timeline.channel_read_sets()  # channels: buckets, or a coded capture's sub-frames
    buckets_read = tuple(sorted({c for r in read_sets for c in r}))
    all_groups = scene.groups
    w = timeline.weights_ticks(edges, all_groups, scene.switchable, scene.drives)  # (J, K, G) ticks
    read_mask = np.zeros(timeline.n_channels, dtype=bool)
    read_mask[list(buckets_read)] = True
    w[:, ~read_mask, :] = 0
    used_g = w.sum(axis=(0, 1)) > 0
    groups = tuple(g for g, u in zip(all_groups, used_g) if u)
    left_out = tuple(g for g, u in zip(all_groups, used_g) if not u)
    unknown = timeline.switchable_groups() - set(all_groups)
    if unknown:
        raise ConfigError(
            f"capture.schedule: emitter group(s) {sorted(unknown)} are not in scene {scene.name!r} "
            f"(its groups: {list(all_groups)})"
        )
    not_switchable = timeline.switchable_groups() - set(scene.switchable)
    if not_switchable:
        raise ConfigError(
            f"capture.schedule: group(s) {sorted(not_switchable)} of scene {scene.name!r} are always on and cannot be "
            f"switched (switchable: {sorted(scene.switchable)})"
        )
    w = w[:, :, used_g]
    live = w.sum(axis=(1, 2)) > 0  # strata in idle gaps (sequential frames) carry no weight
    starts, ends, w = edges[:-1][live], edges[1:][live], w[live]
    # jittered (stratified) render times inside each stratum, one per half-sample render (Plan.render_times):
    # unbiased on average over seeds; the first halves' are drawn first and stay the strata's times
    halves = timeline.seconds(starts) + rng.random((2, len(starts))) * timeline.seconds(ends - starts)
    return Plan(
        starts_ticks=starts,
        ends_ticks=ends,
        times_s=np.asarray(halves[0], dtype=np.float64),
        half_times_s=np.ascontiguousarray(halves.T, dtype=np.float64),
        bounds_s=np.stack([timeline.seconds(starts), timeline.seconds(ends)], axis=1).astype(np.float64),
        weights_s=w.astype(np.float64) * float(timeline.tick_s),
        groups=groups,
        buckets_read=buckets_read,
        read_sets=read_sets,
        read_names=read_names,
        spp=None if render.spp is None else np.full(len(starts), render.spp, dtype=np.int64),
        max_motion_px=render.max_motion_px,
        motion_px_total=motion_total,
        coarsened=coarsened,
        left_out_groups=left_out,
        notes=notes,
        spp_source="render.spp" if render.spp is not None else "pending",
        planner=render.planner,
        noise_budget=None if render.spp is not None else render.noise_budget,
        estimator=render.estimator,
        pattern=render.pattern,
        base_spp_setting=render.base_spp,
        base_time_s=float(timeline.seconds(timeline.start_tick)),
        max_spp_per_render=render.max_spp,
    )


def _slot_edges(timeline: Timeline) -> np.ndarray:
    """Every slot boundary of every period of the collecting segments (the naive plan's strata)."""
    n = sum(seg.repeats * len(seg.slots) for seg in timeline.segments if any(s.bucket >= 0 for s in seg.slots))
    if n > MAX_NAIVE_PASSES:
        raise ConfigError(
            f"render.planner: 'naive' would render {n} slots (more than {MAX_NAIVE_PASSES}); use 'motion' "
            "or fewer capture.periods"
        )
    out = []
    for seg in timeline.segments:
        if not any(s.bucket >= 0 for s in seg.slots):
            continue
        offs = np.concatenate([[0], np.cumsum([s.ticks for s in seg.slots])[:-1]]).astype(np.int64)
        starts = seg.start_tick + np.arange(seg.repeats, dtype=np.int64)[:, None] * seg.period_ticks + offs[None, :]
        out.append(starts.ravel())
        out.append(np.array([seg.end_tick], dtype=np.int64))
    return np.unique(np.concatenate(out))
