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

Samples per pixel (``render.spp`` null): :func:`choose_spp` renders a pilot and allocates
samples so that, over the lit unsaturated samples of every read bucket, the ratio of the
Monte Carlo variance of the bucket's electrons to the photon shot-noise variance the sensor adds
there has its median at most ``render.noise_budget`` (0.1) and its 95th percentile at most
``render.noise_budget_p95`` (1.0). A median and a percentile rather than a mean: a handful of
hard pixels (the lamp's rim, speculars) would otherwise set the samples of the whole image
(measured on the metronome at 640x512: 7 x ~765 spp for a mean of 0.1, 7 x ~420 for the median
and p95 with independent samples).

The pilot, at up to ``PILOT_TIMES`` strata: two independent renders at each of ``PILOT_SPP``
(4 and 16). Each pair is the main render's two-halves estimator at twice the count, and its
squared difference over 4 that estimator's variance, per pixel; pooled over 3x3 pixels (9
degrees of freedom; :func:`budget_quantiles` corrects the median for the chi-square spread) and
divided by the pilot's expected electrons, this gives each bucket's ratios at the two counts. With
randomized quasi-Monte Carlo samplers (``render.sampler``) variance falls faster than 1/spp, so
the exponent between the two counts is measured (clipped to [1, 2]) and each target's quantile is
extrapolated to the count that meets it. Strata share that count in proportion to their Neyman
shape (sqrt of each stratum's summed variance: a stratum that weighs more in the buckets gets
more samples), but none gets fewer than the smaller pilot count (2 x 4), where the ratio was
measured rather than extrapolated; every stratum uses its nearest pilot. Counts are rounded up to what the sampler
takes for each half (ldsampler: powers of 4) within [2, ``render.max_spp``]. A dim scene gets
fewer samples: the variance scales with the square of the light, the shot noise with the light.

The pilot also times its renders: seconds per pass = c0 + c1 x spp (two-point fit, medians
over the pilot times) is the cost model behind ``Plan.estimate``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from .config import RenderSection
from .errors import ConfigError
from .scenes import SceneModel
from .timeline import Timeline

#: Motion is sampled this finely (per collecting interval) to bound image motion.
_MOTION_SAMPLES = 4096
#: Strata at which the pilot renders (spread evenly over the capture).
PILOT_TIMES = 3
#: The naive planner refuses captures with more slots than this.
MAX_NAIVE_PASSES = 200_000


@dataclass(frozen=True)
class Plan:
    """What will be rendered.

    starts_ticks, ends_ticks   (J,) stratum bounds [start, end), int64 ticks.
    times_s       (J,) scene time at which each stratum is rendered (jittered inside it).
    weights_s     (J, K, G) seconds of stratum j in which bucket k collects while group g is on.
    groups        the emitter groups rendered (G), in the scene's order.
    spp           (J,) int64 samples per pixel of each stratum, or None until :func:`choose_spp`.
    spp_source    'render.spp', 'noise_budget' (pilot) or 'pending' (noise budget, no pilot yet).
    planner       'motion' or 'naive'.
    pilot         what the pilot measured (None without one).
    cost          the cost model {c0_s, c1_s_per_spp, compile_s, accumulate_s} (None without a pilot/probe).
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
    base_spp_setting: int | None = None
    base_time_s: float = 0.0
    max_spp_per_render: int = 1024

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
        samples = float(self.spp.sum()) + (self.base_spp + float(np.unique(self.spp).sum())
                                           if self.estimator == "difference" else 0.0)
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
                    "render_time_s": float(t),
                    "spp": None if spp is None else int(n),
                }
                for a, b, t, n in zip(
                    self.starts_ticks, self.ends_ticks, self.times_s, spp if spp is not None else [None] * self.passes
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


def _split_interval(scene, tl: Timeline, a: int, b: int, render: RenderSection) -> tuple[list[int], float]:
    """Boundaries inside [a, b] so that each piece moves at most max_motion_px.

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
    n = max(1, int(np.ceil(total / budget - 1e-9)))
    n = min(n, len(ticks) - 1)
    targets = np.linspace(0.0, total, n + 1)[1:-1]
    inner = np.interp(targets, s, ticks.astype(np.float64)) if n > 1 else np.array([])
    if snap is not None and inner.size:
        start, period = snap
        inner = start + np.round((inner - start) / period) * period
        inner = inner[(inner > a) & (inner < b)]
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
        for a, b in intervals:
            cuts, moved = _split_interval(scene, timeline, a, b, render)
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

    buckets_read = tuple(sorted({b for r in timeline.reads for b in r.buckets}))
    all_groups = scene.groups
    w = timeline.weights_ticks(edges, all_groups, scene.switchable, scene.drives)  # (J, K, G) ticks
    read_mask = np.zeros(timeline.n_buckets, dtype=bool)
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
    # jittered (stratified) render time inside each stratum: unbiased on average over seeds
    times = timeline.seconds(starts) + rng.random(len(starts)) * timeline.seconds(ends - starts)
    return Plan(
        starts_ticks=starts,
        ends_ticks=ends,
        times_s=np.asarray(times, dtype=np.float64),
        weights_s=w.astype(np.float64) * float(timeline.tick_s),
        groups=groups,
        buckets_read=buckets_read,
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


def _pilot_indices(plan: Plan) -> np.ndarray:
    """Strata the pilot renders at: up to PILOT_TIMES, spread evenly over the capture."""
    return np.unique(np.linspace(0, plan.passes - 1, min(PILOT_TIMES, plan.passes)).round().astype(int))


def _timed_render(renderer, t_s: float, spp: int, seed: int, groups) -> tuple[np.ndarray, float]:
    """One render and its seconds, the scene update included: every pass of a run moves the
    geometry (and rebuilds the acceleration structure) before it renders."""
    t0 = time.perf_counter()
    renderer.set_time(float(t_s), force=True)
    img = renderer.render(float(t_s), int(spp), int(seed), groups)
    seconds = time.perf_counter() - t0
    if getattr(renderer, "last_cached", False):  # from the render cache: the seconds it took when made
        seconds = renderer.last_render_s
    return img.astype(np.float64), seconds


def _cost_model(pairs: list[tuple[float, float]], first_s: float, accumulate_s: float,
                spp_pair: tuple[int, int] = (1, 4)) -> dict:
    """c0 + c1 x spp from (seconds at spp_pair[0], seconds at spp_pair[1]) pairs; medians over pairs."""
    lo, hi = spp_pair
    t1 = float(np.median([a for a, _ in pairs]))
    t4 = float(np.median([b for _, b in pairs]))
    c1 = max((t4 - t1) / (hi - lo), 1e-6)
    c0 = max(t1 - c1 * lo, 0.0)
    return {
        "c0_s": round(c0, 5),
        "c1_s_per_spp": round(c1, 6),
        "compile_s": round(max(first_s - (c0 + c1), 0.0), 3),
        "accumulate_s": round(accumulate_s, 5),
    }


def _timed_accumulate(weights_s: np.ndarray, radiance: np.ndarray, K: int) -> float:
    from .integrate import accumulate

    out = np.zeros((K, *radiance.shape[1:]), dtype=np.float64)
    t0 = time.perf_counter()
    accumulate(weights_s, radiance, out)
    return time.perf_counter() - t0


def probe_cost(plan: Plan, renderer, seed: np.random.SeedSequence) -> Plan:
    """Time a warm-up render (kernel compilation), one at 1 spp and one at 4 spp at the first
    stratum, and attach the cost model (``Plan.cost``) without changing the plan."""
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=3)
    t = float(plan.times_s[0])
    _, first = _timed_render(renderer, t, 1, seeds[0], plan.groups)
    a, ta = _timed_render(renderer, t, 1, seeds[1], plan.groups)
    _, tb = _timed_render(renderer, t, 4, seeds[2], plan.groups)
    acc = _timed_accumulate(plan.weights_s[0], a, plan.weights_s.shape[1])
    return replace(plan, cost=_cost_model([(ta, tb)], first, acc))


#: Pixels pooled (a box of this size) in per-pixel variance estimates: a single squared difference
#: is a chi-square variable with 1 degree of freedom per channel, far too noisy for a quantile;
#: pooling 3x3 neighbours gives 9.
POOL_PX = 3


def pooled(v: np.ndarray) -> np.ndarray:
    """Per-pixel variance estimates (..., H, W, C) averaged over POOL_PX x POOL_PX neighbours."""
    from scipy.ndimage import uniform_filter

    size = [1] * (v.ndim - 3) + [POOL_PX, POOL_PX, 1]
    return uniform_filter(np.asarray(v, dtype=np.float64), size=size, mode="nearest")


def chi2_median_factor(dof: float) -> float:
    """Median of chi^2_dof / dof (Wilson-Hilferty): how far below the mean the median of noisy
    variance estimates lies; 0.93 for 9 degrees of freedom."""
    return (1.0 - 2.0 / (9.0 * dof)) ** 3


def budget_quantiles(ratio: np.ndarray) -> tuple[float, float]:
    """(median, 95th percentile) of per-sample Monte Carlo / shot variance ratios estimated from
    pooled squared differences: the median is divided by :func:`chi2_median_factor` of the
    POOL_PX^2 degrees of freedom (unbiased for a uniform ratio); the 95th percentile is left as it
    is (the estimates' own spread only widens it: conservative)."""
    return float(np.median(ratio)) / chi2_median_factor(POOL_PX**2), float(np.percentile(ratio, 95))


#: The pilot's two sample counts: at each, two independent renders (their mean is the main
#: render's two-halves estimator at twice the count, their difference its error).
PILOT_SPP = (4, 16)
#: Range of the fitted convergence exponent: Monte Carlo variance ~ spp^-exponent (1 for
#: independent samples, up to 2 for randomized quasi-Monte Carlo on smooth integrands).
EXPONENT_RANGE = (1.0, 2.0)


def _ladder(x: float) -> int:
    """x rounded up to the ladder round(2^(i/4)) (steps of at most 19 %): strata get few distinct
    sample counts, and Dr.Jit compiles one kernel per count."""
    if x <= 4:
        return max(int(np.ceil(x)), 1)
    i = int(np.ceil(4 * np.log2(x) - 1e-9))
    while round(2 ** (i / 4)) < x:
        i += 1
    return int(round(2 ** (i / 4)))


def _pilot_ratios(diffs: list[np.ndarray], owner: np.ndarray, w: np.ndarray, alpha: np.ndarray,
                  electrons: np.ndarray, lit: np.ndarray, k: int) -> np.ndarray:
    """Per-sample ratio of bucket k's Monte Carlo variance to its shot noise, for strata rendered
    at alpha_j times the pilot's count, over the lit samples: diffs[p] (G, H, W, C) are one pilot
    time's differences of two independent renders (electrons per second), whose square over 4
    estimates the variance of their mean; pooled over POOL_PX^2 pixels."""
    var_k = np.zeros(lit.shape[1:])
    for p, d in enumerate(diffs):
        sel = owner == p
        C = np.einsum("jg,jh->gh", w[sel, k] / alpha[sel, None], w[sel, k])  # (G, G)
        var_k += pooled(np.einsum("gh,gywc,hywc->ywc", C, d, d, optimize=True)) / 4.0
    return var_k[lit[k]] / electrons[k][lit[k]]


def choose_spp(
    plan: Plan,
    renderer,
    k_e: np.ndarray,
    full_well_e: float,
    noise_budget: float,
    max_spp: int,
    seed: np.random.SeedSequence,
    noise_budget_p95: float | None = None,
) -> Plan:
    """Samples per pixel per stratum from a pilot (the rule is in the module docstring).

    ``k_e`` (C,): electrons per render unit and second. Returns the plan with ``spp``,
    ``pilot`` and ``cost`` filled in; the pilot's renders are not used in the image (their
    samples chose n_j: reusing them would bias the estimate).
    """
    if plan.passes == 0:
        return replace(plan, spp=np.zeros(0, np.int64), spp_source="noise_budget")
    p95_target = 10.0 * noise_budget if noise_budget_p95 is None else noise_budget_p95
    t_start = time.perf_counter()
    k_e = np.asarray(k_e, dtype=np.float64)
    idx = _pilot_indices(plan)
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=(len(idx), len(PILOT_SPP), 2))
    w = plan.weights_s  # (J, K, G)
    J, K, G = w.shape
    owner = np.abs(plan.times_s[:, None] - plan.times_s[idx][None, :]).argmin(axis=1)  # nearest pilot
    means: list[np.ndarray] = []
    diffs: dict[int, list[np.ndarray]] = {s: [] for s in PILOT_SPP}
    seconds: dict[int, list[float]] = {s: [] for s in PILOT_SPP}
    for p, j in enumerate(idx):
        total = 0.0
        for level, spp in enumerate(PILOT_SPP):
            (a, ta), (b, tb) = (_timed_render(renderer, plan.times_s[j], spp, seeds[p, level, h], plan.groups)
                                for h in range(2))
            diffs[spp].append((a - b) * k_e)  # (G, H, W, C), electrons per second
            seconds[spp] += [ta, tb]
            total = total + (a + b) * spp
        means.append(total / (2 * sum(PILOT_SPP)))  # every pilot sample of this time
    acc = _timed_accumulate(w[idx[0]], means[0], K)
    wp = np.stack([w[owner == p].sum(axis=0) for p in range(len(idx))])  # (P, K, G)
    # the ratios' denominator, pooled like their numerator so that its own noise does not scatter them
    electrons = pooled(np.einsum("pkg,pghwc->khwc", wp, np.stack(means), optimize=True) * k_e)
    lit = (electrons > 1.0) & (electrons < full_well_e)  # (K, H, W, C)
    # Neyman shape of n_j: sqrt of each stratum's summed variance, max over buckets
    hi = diffs[PILOT_SPP[-1]]
    a_jk = np.zeros((J, K))
    for k in range(K):
        if lit[k].any():
            for p in range(len(idx)):
                d = hi[p][:, lit[k]]
                sel = owner == p
                a_jk[sel, k] = np.einsum("jg,gh,jh->j", w[sel, k], d @ d.T, w[sel, k])
    root = np.sqrt(np.maximum(a_jk, 0.0))
    # bucket k alone would take n_jk = sqrt(a_jk) sum_j sqrt(a_jk) / (f E_k), E_k its lit electrons: the
    # 1 / E_k keeps the buckets' counts comparable, so that the max over k is the count every bucket needs
    e_k = np.array([electrons[k][lit[k]].sum() for k in range(K)])
    with np.errstate(divide="ignore", invalid="ignore"):
        shape = np.nan_to_num(root * root.sum(axis=0)[None, :] / np.maximum(e_k, 1e-300)[None, :]).max(axis=1)
    alpha = np.maximum(shape / shape.max(), 1e-3) if shape.max() > 0 else np.ones(J)
    # per bucket: median and p95 of the pooled ratios at both pilot counts (strata at alpha_j x the
    # count), the exponent between them, and the count each target needs
    scale, per_bucket = 0.0, []
    n_lo, n_hi = 2 * PILOT_SPP[0], 2 * PILOT_SPP[-1]  # two halves: the main render's total count
    for k in range(K):
        if not lit[k].any():
            per_bucket.append(None)
            continue
        q = {n: budget_quantiles(_pilot_ratios(diffs[s], owner, w, alpha, electrons, lit, k))
             for n, s in ((n_lo, PILOT_SPP[0]), (n_hi, PILOT_SPP[-1]))}
        need = []
        for i, target in enumerate((noise_budget, p95_target)):
            lo, hi_q = q[n_lo][i], q[n_hi][i]
            expo = float(np.clip(np.log(max(lo, 1e-300) / max(hi_q, 1e-300)) / np.log(n_hi / n_lo), *EXPONENT_RANGE))
            need.append(n_hi * (hi_q / target) ** (1.0 / expo) if hi_q > 0 else 0.0)
        per_bucket.append({"median_at": {n_lo: round(q[n_lo][0], 4), n_hi: round(q[n_hi][0], 4)},
                           "p95_at": {n_lo: round(q[n_lo][1], 4), n_hi: round(q[n_hi][1], 4)},
                           "spp_for_median": round(need[0], 1), "spp_for_p95": round(need[1], 1)})
        scale = max(scale, *need)
    # no stratum below the pilot's smaller count: there the ratio was measured, below it only extrapolated
    # (multijitter converges faster than spp^-2 on smooth scenes, so the clipped exponent under-predicts the
    # noise of fewer samples: flutter_shutter 640x512 was given 2 + 2 spp and measured 0.175 > 0.1)
    n = np.maximum(scale * alpha, float(n_lo)) if scale > 0 else scale * alpha
    count = getattr(renderer, "sample_count", lambda m: m)  # what the sampler takes
    half = np.array([count(_ladder(x / 2)) for x in n])
    cap = max(max_spp // 2, 1)
    spp = (2 * np.minimum(half, cap)).astype(np.int64)
    capped = int((n > 2 * cap).sum())
    notes = list(plan.notes)
    if capped:
        notes.append(f"render.max_spp={max_spp} capped {capped} strata: the noise budget is not met there")
    # the first render at each count compiled its kernel (Dr.Jit compiles one per sample count):
    # the cost model takes medians, and the compile time is what the first renders took beyond it
    pairs = list(zip(seconds[PILOT_SPP[0]], seconds[PILOT_SPP[-1]]))
    model = _cost_model(pairs, 0.0, acc, spp_pair=PILOT_SPP)
    model["compile_s"] = round(max(sum(seconds[s][0] - (model["c0_s"] + model["c1_s_per_spp"] * s) for s in PILOT_SPP),
                                   0.0), 3)
    pilot = {
        "times": len(idx),
        "renders": 2 * len(PILOT_SPP) * len(idx),
        "spp": list(PILOT_SPP),
        "seconds": round(time.perf_counter() - t_start, 3),
        "buckets_lit": [b + 1 for b in range(K) if lit[b].any()],
        "per_bucket": per_bucket,
        "targets": {"median": noise_budget, "p95": p95_target},
        "uncapped_spp_max": float(n.max()),
    }
    return replace(plan, spp=spp, spp_source="noise_budget", pilot=pilot, cost=model, notes=notes)


def resolve_spp(plan: Plan, renderer, cfg, seed: np.random.SeedSequence) -> Plan:
    """The plan ready to render: with ``render.spp`` null, run :func:`choose_spp` for this
    capture's sensor; otherwise return ``plan`` unchanged. ``seed``: the run's render seed (the
    pilot uses an independent child of it)."""
    if plan.spp is not None:
        return plan
    from .sensor import electrons_per_render_second

    pilot_seed = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x9117))
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    return choose_spp(plan, renderer, k_e, cfg.sensor.full_well_e, cfg.render.noise_budget, cfg.render.max_spp, pilot_seed,
                      noise_budget_p95=cfg.render.noise_budget_p95)
