"""Render the plan's strata and integrate them into bucket exposures.

    B_k = sum_j sum_g weights_s[j, k, g] * L_g(t_j)      (W m^-2 sr^-1 s, float64)

Each stratum is rendered as two independent half-sample passes accumulated apart, so a run
measures its own Monte Carlo error: Var[combined] ~ (A - B)^2 n_a n_b / n^2. Applications that
need the exposure of each emitter group separately (flash-only ground truths, per-LED colour
channels) ask for ``per_group``: the same renders, accumulated without summing over groups.

Estimators (``render.estimator``):

``independent``  L_j is a render of stratum j with its own seeds: unbiased; every stratum
                 carries its own Monte Carlo noise everywhere in the image.
``difference``   common random numbers against a base: L_j = L_j^crn + (B - B^crn), where
                 L_j^crn renders stratum j and B^crn the base time t_0 (the capture's start) with
                 the *same* seed and sample count for every stratum, and B renders t_0 at
                 ``plan.base_spp`` with seeds of its own. E[L_j] = L(t_j): unbiased. A pixel whose
                 paths never meet a moving part gets exactly L_j^crn = B^crn, hence L_j = B in every
                 stratum: static pixels carry only the base's error, identical in every bucket, and
                 the moving region carries the strata's differences. B and B^crn do not depend on
                 the protocol, so captures of the same scene, start and seed share them (cache).
                 Both halves of the error estimate have their own B, B^crn and seeds.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import blas

from .filmstore import IN_MEMORY, FilmStore
from .plan import Plan
from ..render.renderer import RenderRows
from ..progress import bar
from ..timing.timeline import Timeline


DIFF_DTYPE = np.float32  # what Integrated.mc_diff and Integrated.temporal_diff are kept in (see Integrated)


def render_seeds(plan: Plan, seed: np.random.SeedSequence) -> np.ndarray:
    """(J, 2) the seeds of each stratum's two half-sample renders."""
    return np.random.default_rng(seed).integers(0, 2**31 - 1, size=(plan.passes, 2))


def stratum_halves(plan: Plan) -> list[tuple[int, ...]]:
    """Each stratum's samples as its two half-sample renders (n // 2, n - n // 2), or as one render of
    n when any stratum has fewer than 2 (then there are no halves to difference)."""
    spp = [int(n) for n in np.asarray(plan.spp, dtype=np.int64)]
    two = all(n >= 2 for n in spp)
    return [(n // 2, n - n // 2) if two else (n,) for n in spp]


def pattern_keys(seed: np.random.SeedSequence) -> np.ndarray:
    """The two shared patterns' keys (one per half) of the renders seeded by ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x5A7E))).integers(
        0, 2**32, size=2
    )


def sample_counter(renderer, plan: Plan) -> Callable[[int], int]:
    """What ``renderer``'s renders of ``plan`` take when asked for a count (``Renderer.counter``: the count
    itself where they draw from the shared pattern in an RGB variant, else the sampler's: multijitter takes
    132 for 128); every count as it is for a stand-in renderer without one."""
    counter = getattr(renderer, "counter", None)
    return counter(plan.shares_pattern) if counter is not None else (lambda n: n)


def render_patterns(
    plan: Plan, seed: np.random.SeedSequence, count: Callable[[int], int] | None = None, after: Plan | None = None
) -> list[list[tuple[int, int] | None]]:
    """The shared pattern (key, offset) of each stratum's half-sample renders, [j][h], or None
    (render.pattern 'own', or the ``difference`` estimator): half h of every stratum draws from one
    pattern of its own, stratum j taking the samples after those of strata 0 .. j - 1, so that the
    halves stay independent (the run's error estimate is their difference) and each is stratified
    over the strata together. ``count``: the samples the renderer's sampler takes for a request
    (:func:`sample_counter`), so that no two strata share samples.
    ``after``: a first pass rendered with the same ``seed``, whose patterns these continue: the same
    keys, each half's samples after all of that pass's (the budget's top-up)."""
    halves = stratum_halves(plan)
    if not plan.shares_pattern:
        return [[None] * len(h) for h in halves]
    taken = count if count is not None else (lambda n: n)
    keys = pattern_keys(seed)
    before = stratum_halves(after) if after is not None else []
    offset = [sum(int(taken(h_j[h])) for h_j in before if h < len(h_j)) for h in range(2)]
    out = []
    for h_j in halves:
        out.append([(int(keys[h]), offset[h]) for h in range(len(h_j))])
        for h, n_h in enumerate(h_j):
            offset[h] += int(taken(n_h))
    return out


def render_requests(
    plan: Plan, seed: np.random.SeedSequence, count: Callable[[int], int] | None = None
) -> list[tuple[float, int, int, tuple[str, ...], tuple[int, int] | None]]:
    """Every render :func:`integrate` makes for ``plan`` with the ``independent`` estimator, in its
    order: (scene time s, samples per pixel, seed, groups, shared pattern or None). What a cluster
    renders ahead of it (:mod:`mbcapture.exposure.cluster`); ``count`` as in :func:`render_patterns`."""
    seeds = render_seeds(plan, seed)
    patterns = render_patterns(plan, seed, count)
    used = plan.weights_s.sum(axis=1) > 0
    times = plan.render_times
    out = []
    for j, halves in enumerate(stratum_halves(plan)):
        groups_j = tuple(plan.groups[g] for g in np.flatnonzero(used[j]))
        for h, spp_h in enumerate(halves):
            out.append((float(times[j, h]), int(spp_h), int(seeds[j, h]), groups_j, patterns[j][h]))
    return out


@dataclass
class Integrated:
    """exposure (K, H, W, C); group_exposure (K, G, H, W, C) or None.

    mc_diff (K, H, W, C) float32 or None (spp = 1): the signed half-sample difference, scaled so that
    its square estimates the exposure's Monte Carlo variance (``mc_var``). Signed, because a read sums
    buckets whose Monte Carlo errors come from the same renders: the read's variance is the square
    of the summed differences, not the sum of the buckets' variances (:meth:`read_mc_var`).

    temporal_diff (K, H, W, C) float32 or None (one stratum): the exposure with strata merged in pairs
    (each pair rendered once, at its first stratum's render times, with both strata's weights) minus
    the exposure; its mean square, less its Monte Carlo part, measures the temporal error of
    strata twice as long as the plan's (:func:`temporal_error`).

    The two differences are accumulated in float64 and kept in float32 (:data:`DIFF_DTYPE`): they only
    estimate errors (a squared half-sample difference is itself a one-degree-of-freedom chi-square
    variable, 141 % uncertain), so float32's 6e-8 changes nothing a user reads, and a large film holds
    them at half the memory. Their squares and sums are taken in float64.
    """

    exposure: np.ndarray
    mc_diff: np.ndarray | None
    group_exposure: np.ndarray | None = None
    temporal_diff: np.ndarray | None = None

    @property
    def mc_var(self) -> np.ndarray | None:
        """(K, H, W, C) float64 estimated Monte Carlo variance of each bucket's exposure (one sample of it)."""
        return None if self.mc_diff is None else np.square(self.mc_diff, dtype=np.float64)

    def read_mc_var(self, buckets) -> np.ndarray | None:
        """(H, W, C) float64 estimated Monte Carlo variance of the exposure summed over ``buckets`` (a read)."""
        return None if self.mc_diff is None else self.mc_diff[list(buckets)].sum(axis=0, dtype=np.float64) ** 2

    def routed(self, timeline: Timeline) -> "Integrated":
        """The same renders per bucket: a coded timeline's sub-frame channels sent through its
        per-pixel gate code (:meth:`~mbcapture.timing.timeline.Timeline.route`; every array is linear in
        the renders, the signed differences too); itself with global gates."""
        if timeline.code is None:
            return self
        groups = None
        if self.group_exposure is not None:  # (S, G, H, W, C): route with the pixels on axes 1, 2
            groups = np.moveaxis(timeline.route(np.moveaxis(self.group_exposure, 1, 3)), 3, 1)
        return Integrated(
            exposure=timeline.route(self.exposure),
            mc_diff=timeline.route(self.mc_diff),
            group_exposure=groups,
            temporal_diff=timeline.route(self.temporal_diff),
        )


def accumulate(
    weights_s: np.ndarray, radiance: np.ndarray, out: np.ndarray, radiance64: np.ndarray | None = None
) -> None:
    """out[k] += sum_g weights_s[k, g] * radiance[g]  (float64, ``out`` C-contiguous; radiance (G, H, W, C)).

    One BLAS call does the product and the sum (dgemm with beta 1, into ``out``'s own memory): the
    same rounding as the product made apart and then added (one rounding of the dot product, one of
    the sum; checked equal bit for bit), without a product array of ``out``'s size to fill and read
    again. Written with scipy's BLAS because numpy's matmul has no "add into" (``out=`` overwrites).
    ``radiance64``: a float64 array of at least G radiance images that a float32 ``radiance`` is widened
    into (None: a new one); :func:`integrate` passes one made for the whole capture, as a new 24 MB
    array per render (640x512) is memory the system must map and zero first."""
    K, G = out.shape[0], radiance.shape[0]
    if G == 0 or out.size == 0:  # no group (or no pixel): nothing to add
        return
    if not out.flags.c_contiguous:
        raise ValueError("accumulate: out must be C-contiguous")
    n = out.size // K
    if radiance.dtype == np.float64 or radiance64 is None:
        wide = np.ascontiguousarray(radiance.reshape(G, n), dtype=np.float64)
    else:  # the same values (float32 -> float64 is exact), in the given array
        wide = radiance64.reshape(-1)[: G * n].reshape(G, n)
        np.copyto(wide, radiance.reshape(G, n))
    # column-major view of the row-major product: out^T (n, K) += wide^T (n, G) @ weights^T (G, K)
    target = out.reshape(K, n).T
    w = np.asarray(weights_s, np.float64)
    result = blas.dgemm(1.0, wide.T, w.T, 1.0, target, overwrite_c=1)
    if not np.shares_memory(result, out):  # BLAS worked on a copy (never for these layouts): keep its sum
        target[...] = result


def accumulate_groups(weights_s: np.ndarray, radiance: np.ndarray, out: np.ndarray) -> None:
    """out[k, g] += weights_s[k, g] * radiance[g]  (out (K, G, H, W, C) float64)."""
    out += weights_s[:, :, None, None, None] * radiance.astype(np.float64, copy=False)[None]


def _progress(total: int, enabled: bool, desc: str):
    return bar(total=total, desc=desc, unit="pass", enabled=enabled)


def integrate(
    renderer,
    plan: Plan,
    n_buckets: int,
    seed: np.random.SeedSequence,
    *,
    per_group: bool = False,
    timer=None,
    progress: bool = False,
    desc: str = "render",
    continues: tuple[Plan, np.random.SeedSequence] | None = None,
) -> Integrated:
    """Render every stratum of ``plan`` with ``renderer`` and accumulate the bucket exposures.

    Stratum j is rendered at ``plan.spp[j]`` samples as two halves (n//2, n - n//2), each at its
    own time (:attr:`Plan.render_times`), with only the groups that have weight in it. The halves
    give the Monte Carlo variance, the time sampling's included (exact when every stratum splits
    in the same ratio, as with even or uniform spp). Consecutive strata are paired to measure the
    temporal error (see :class:`Integrated`). ``continues``: a first pass (its plan and seed) whose
    shared patterns this pass's samples continue (:func:`render_patterns`); ``seed`` still seeds this
    pass's own renders (a spectral variant's camera rays).
    """
    if plan.spp is None:
        raise ValueError("plan.spp is not chosen yet: call mbcapture.budget.resolve_spp first")
    stage = timer if timer is not None else (lambda name: nullcontext())
    H, W, C = renderer.height, renderer.width, len(renderer.channels)
    G = len(plan.groups)
    spp = np.asarray(plan.spp, dtype=np.int64)
    halves_all = stratum_halves(plan)
    two = plan.passes > 0 and len(halves_all[0]) == 2
    # parts[h] = sum_j w_j (n_hj / n_j) L_hj: exposure = parts[0] + parts[1] exactly
    parts = [np.zeros((n_buckets, H, W, C), dtype=np.float64) for _ in range(2 if two else 1)]
    r = spp // 2 / np.maximum(spp, 1)  # share of the first half, per stratum
    groups_out = np.zeros((n_buckets, G, H, W, C), dtype=np.float64) if per_group else None
    temporal = np.zeros((n_buckets, H, W, C), dtype=np.float64) if plan.passes >= 2 else None
    seeds = render_seeds(plan, seed)
    first_plan, pattern_seed = continues if continues is not None else (None, seed)
    patterns = render_patterns(plan, pattern_seed, sample_counter(renderer, plan), after=first_plan)
    times = plan.render_times
    used = plan.weights_s.sum(axis=1) > 0  # (J, G): groups with weight in each stratum
    radiance64 = np.empty((G, H, W, C))  # each render widened to float64 for accumulate, made once
    # each stratum's radiance, its halves combined (the temporal pairs and the per-group sums), made once
    combined_all = np.empty((G, H, W, C)) if temporal is not None or groups_out is not None else None
    # the even stratum's combined radiance and the odd one's, (G, H, W, C), made once
    pair = [np.zeros((G, H, W, C)), np.zeros((G, H, W, C))] if temporal is not None else None
    control = _Control(renderer, plan, seed, stage) if plan.estimator == "difference" else None
    if control is not None and not two:
        raise ValueError("render.estimator 'difference' needs at least 2 samples per pixel per stratum")
    total = plan.passes + (control.renders_before() if control is not None else 0)
    with _progress(total, progress, desc) as bar:
        if control is not None:
            control.render_base(bar)
        for j in range(plan.passes):
            n = int(spp[j])
            halves = halves_all[j]
            gsel = np.flatnonzero(used[j])
            groups_j = tuple(plan.groups[g] for g in gsel)
            w_j = plan.weights_s[j][:, gsel]
            combined = None
            if combined_all is not None:
                combined = combined_all[: len(gsel)]
                combined.fill(0.0)
            for h, spp_h in enumerate(halves):
                with stage("render"):
                    if control is None:
                        radiance = renderer.render(
                            float(times[j, h]), spp_h, int(seeds[j, h]), groups_j, pattern=patterns[j][h]
                        )
                    else:
                        radiance = control.stratum(float(times[j, h]), h, spp_h, gsel)
                with stage("accumulate"):
                    accumulate(w_j * (spp_h / n), radiance, parts[h], radiance64)
                    if combined is not None:
                        combined += radiance * (spp_h / n)
            with stage("accumulate"):
                if groups_out is not None:
                    groups_out[:, gsel] += w_j[:, :, None, None, None] * combined[None]
                if temporal is not None:
                    full = pair[j % 2]
                    if len(gsel) == G:
                        np.copyto(full, combined)
                    else:  # the groups without weight here are zero
                        full.fill(0.0)
                        full[gsel] = combined
                    if j % 2 == 1:  # coarse (pair rendered once, at the even stratum) minus fine
                        np.subtract(pair[0], full, out=full)
                        accumulate(plan.weights_s[j], full, temporal)
            bar.update(1)
    if temporal is not None:
        temporal = temporal.astype(DIFF_DTYPE)
    exposure = parts[0] + parts[1] if two else parts[0]
    mc_diff = signed_difference(parts, r, plan.weights_s) if two else None
    return Integrated(exposure=exposure, mc_diff=mc_diff, group_exposure=groups_out, temporal_diff=temporal)


def signed_difference(parts: list[np.ndarray], r: np.ndarray, weights_s: np.ndarray) -> np.ndarray:
    """The signed half-sample error estimate (:attr:`Integrated.mc_diff`) from the two halves' sums ``parts``
    (spent: computed in place on them), ``r`` (J,) the first half's share of each stratum's samples.

    A = parts[0]/r, B = parts[1]/(1-r): Var[exposure] ~ (A - B)^2 r (1 - r) (r per stratum; exact when r is
    uniform, otherwise its weight-averaged value), kept signed: (A - B) sqrt(r (1 - r)), operation for operation."""
    rbar = float(np.average(r, weights=np.maximum(weights_s.sum(axis=(1, 2)), 1e-300)))
    a, b = parts
    a /= rbar
    b /= 1 - rbar
    a -= b
    a *= np.sqrt(rbar * (1 - rbar))
    return a.astype(DIFF_DTYPE)


def integrate_tiles(
    renderer,
    plan: Plan,
    n_buckets: int,
    seed: np.random.SeedSequence,
    tiles: tuple[tuple[int, int], ...],
    *,
    per_group: bool = False,
    timer=None,
    progress: bool = False,
    before_tile: Callable[[tuple[int, int]], None] | None = None,
    store: FilmStore = IN_MEMORY,
    desc: str = "render",
    continues: tuple[Plan, np.random.SeedSequence] | None = None,
) -> Integrated:
    """:func:`integrate` tile by tile: each tile (rows first, end; runs of whole render bands,
    :mod:`mbcapture.render.bands`) rendered through :class:`~mbcapture.render.renderer.RenderRows`
    and accumulated alone, so that the renders, the two halves, the pairs of strata and the
    per-group sums are held for one tile at a time; only the results are whole-film arrays. Every
    array is per pixel and a band renders the same pixels in a tile as in the whole film, so the
    result is :func:`integrate`'s on the whole film (tests/test_tiles.py): bit for bit at a few samples
    per pixel; at hundreds, as close as two renders of the whole film are to each other (the renderer's
    float32 sums across threads, about 3e-8 relative in a few samples).
    ``before_tile(rows)``: called before each tile is integrated (a cluster renders its bands then).
    ``store``: where the whole-film results of several tiles are made (in memory, or on disk:
    :mod:`mbcapture.exposure.filmstore`); ``desc`` and ``continues`` as for :func:`integrate`."""
    if len(tiles) == 1 and tuple(tiles[0]) == (0, renderer.height):
        if before_tile is not None:
            before_tile(tuple(tiles[0]))
        return integrate(
            renderer,
            plan,
            n_buckets,
            seed,
            per_group=per_group,
            timer=timer,
            progress=progress,
            desc=desc,
            continues=continues,
        )
    H = renderer.height
    out: dict[str, np.ndarray | None] = {}
    for i, (r0, r1) in enumerate(tiles):
        if before_tile is not None:
            before_tile((r0, r1))
        part = integrate(
            RenderRows(renderer, (r0, r1)),
            plan,
            n_buckets,
            seed,
            per_group=per_group,
            timer=timer,
            progress=progress,
            desc=f"{desc} tile {i + 1}/{len(tiles)}",
            continues=continues,
        )
        for name in ("exposure", "mc_diff", "group_exposure", "temporal_diff"):
            value = getattr(part, name)
            if value is None:
                out[name] = None
                continue
            if name not in out:  # (K, [G,] H, W, C): the film's rows on the axis before the last two
                shape = list(value.shape)
                shape[-3] = H
                out[name] = store.empty(shape, value.dtype)
            out[name][..., r0:r1, :, :] = value
    return Integrated(
        exposure=out["exposure"],
        mc_diff=out["mc_diff"],
        group_exposure=out["group_exposure"],
        temporal_diff=out["temporal_diff"],
    )


class _Control:
    """The ``difference`` estimator's base B and common-random-number base B^crn, per half."""

    def __init__(self, renderer, plan: Plan, seed: np.random.SeedSequence, stage):
        self.renderer, self.plan, self.stage = renderer, plan, stage
        # seeds of their own (not the strata's), fixed by the run's render seed alone, so that every
        # capture of the same scene, start and seed shares the base (render cache)
        rng = np.random.default_rng(np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0xBA5E)))
        self.crn_seeds = rng.integers(0, 2**31 - 1, size=2)
        n_base = int(plan.base_spp) // 2
        chunk = max(int(plan.max_spp_per_render) // 2, 1)
        count = sample_counter(renderer, plan)  # what the sampler takes
        self.base_chunks = [count(min(chunk, n_base - i)) for i in range(0, n_base, chunk)]
        self.base_seeds = rng.integers(0, 2**31 - 1, size=(2, len(self.base_chunks)))
        self.t0 = float(plan.base_time_s)
        self.delta: dict[tuple[int, int], np.ndarray] = {}  # (half, spp) -> B_h - B^crn_h, all groups
        self.base: list[np.ndarray] = []

    def renders_before(self) -> int:
        return 2 * len(self.base_chunks)

    def render_base(self, bar) -> None:
        groups = self.plan.groups
        for h in range(2):
            acc = None
            for c, n in enumerate(self.base_chunks):
                with self.stage("render"):
                    img = self.renderer.render(self.t0, n, int(self.base_seeds[h, c]), groups).astype(np.float64)
                acc = img * n if acc is None else acc + img * n
                bar.update(1)
            self.base.append(acc / sum(self.base_chunks))

    def stratum(self, t_s: float, h: int, spp_h: int, gsel: np.ndarray) -> np.ndarray:
        """Stratum radiance of half h: its common-random-number render plus B_h - B^crn_h."""
        groups = tuple(self.plan.groups[g] for g in gsel)
        key = (h, int(spp_h))
        if key not in self.delta:  # B^crn at this sample count (strata of one count share it)
            crn = self.renderer.render(self.t0, spp_h, int(self.crn_seeds[h]), self.plan.groups).astype(np.float64)
            self.delta[key] = self.base[h] - crn
        return self.renderer.render(t_s, spp_h, int(self.crn_seeds[h]), groups) + self.delta[key][gsel]


def temporal_error(integrated: Integrated, k_e: np.ndarray, buckets: list[int], full_well_e: float) -> dict:
    """The temporal (strata) part of the rendering error, from :attr:`Integrated.temporal_diff`.

    D = coarse - fine sums, per stratum pair, w_odd (L_even - L_odd): its mean square is the
    coarse plan's temporal error squared plus Monte Carlo noise of about 2 x the fine exposure's
    MC variance per pair (both strata's noise, weighted by one stratum's weight of the two), i.e.
    ~ mc_var overall. ``rel_rms_coarse``: sqrt(max(0, mean D^2 - mean mc_var)) / mean signal over
    the lit, unsaturated bucket samples; the fine plan's temporal error is smaller: about half
    of it where the error comes from moving edges (it scales with the motion per stratum), and
    it is reported as ``rel_rms_estimate`` = rel_rms_coarse / 2.
    """
    D = integrated.temporal_diff
    if D is None:
        return {
            "temporal_method": "one stratum: not measured (strata are compared in pairs); the image motion "
            "inside it is plan.image_motion_px_total",
            "temporal_rel_rms_estimate": None,
        }
    # bucket by bucket, one quantity at a time: the means of the samples of every bucket in order (the
    # same as over copies of all the buckets at once), holding one of them, not copies of the buckets
    exposure, mc_diff = integrated.exposure, integrated.mc_diff
    use = []
    for b in buckets:
        e = exposure[b] * k_e
        use.append((e > 1.0) & (e < full_well_e))
    if not any(u.any() for u in use):
        return {"temporal_method": "no unsaturated lit samples"}

    def mean_of(values) -> float:  # the samples of every bucket in one array, filled a bucket at a time
        samples, at = np.empty(sum(int(u.sum()) for u in use)), 0
        for b, u in zip(buckets, use):
            part = values(b)[u]
            samples[at : at + part.size], at = part, at + part.size
        return float(samples.mean())

    d2 = mean_of(lambda b: (D[b] * k_e) ** 2)
    mc = mean_of(lambda b: (mc_diff[b] * k_e) ** 2) if mc_diff is not None else 0.0
    signal = mean_of(lambda b: exposure[b] * k_e)
    resolved = bool(d2 > mc)
    coarse = float(np.sqrt(max(d2 - mc, 0.0)) / signal)
    out = {
        "temporal_method": "strata merged in pairs (coarse minus fine), Monte Carlo part subtracted",
        "temporal_rel_rms_coarse": coarse,
        "temporal_rel_rms_estimate": coarse / 2,
        "temporal_raw_rel_rms_coarse": float(np.sqrt(d2) / signal),
        "temporal_resolved": resolved,
    }
    if not resolved:
        out["temporal_note"] = (
            "the coarse-minus-fine difference is within the Monte Carlo noise: 0 means too small "
            "to measure at this spp, not exactly 0"
        )
    return out


def refine(
    renderer,
    plan: Plan,
    integrated: Integrated,
    pixels: np.ndarray,
    factor: "int | np.ndarray",
    seed: np.random.SeedSequence,
    *,
    points: int = 1,
    per_group: bool = False,
    timer=None,
    progress: bool = False,
    desc: str = "refine",
    have: "int | np.ndarray" = 1,
    store: FilmStore = IN_MEMORY,
) -> Integrated:
    """Adaptive sampling's second pass: every stratum again at ``pixels`` (flat indices) only, each with
    ``factor`` - 1 times its samples (one factor for all, or one per pixel; two halves, for the error
    estimate), through :meth:`mbcapture.render.Renderer.render_pixels`, added to the first pass there: each
    pixel ends with its ``factor`` times the first pass's samples.

    Unbiased where the pixels were chosen independently of the first pass (adaptive sampling chooses
    from a scout of its own, :func:`mbcapture.budget.scout_spp`): then the first pass at them is an
    unbiased estimate, so is the second pass, and so is their mean weighted by their samples, 1 : factor - 1
    (exposure, signed half-sample difference and per-group exposures alike: the combined difference's
    square estimates the combined variance, the passes being independent). Independent in time too:
    each half of each stratum is rendered at times of its own, drawn afresh inside the stratum:
    ``points`` times per half, one in each of ``points`` equal parts of the stratum, its samples shared
    among them (:meth:`Plan.draw_times`). Where a moving edge crosses a pixel, its value changes within a
    stratum, and one time per half leaves that change as noise that more samples do not lower; ``points``
    > 1 stratifies it. The halves' difference holds it too, so the error estimate covers it. The
    temporal-error estimate stays the first pass's.

    Where the first pass drew from shared patterns (``plan.shares_pattern``), so does this pass: from two
    patterns of its own (keys from ``seed``), each half of stratum j taking the samples after those of
    the strata before it, as the first pass did: a pixel's second pass is the first pass's estimator at
    ``factor`` - 1 times the samples, stratified over the strata together. Then every pixel, whatever its
    factor, is in one render per half-stratum and time (each takes its own count and offset of the pattern).
    Otherwise (render.pattern 'own': the sampler's sequences need one count a render) the pixels of each
    factor render together, each set with seeds of its own.

    ``have`` (one, or one per pixel): the factor of the first pass's samples ``integrated`` already holds at each
    pixel (a second round of adaptive sampling, :func:`mbcapture.budget.adaptive.refine_tail`): the pass then adds
    ``factor`` - ``have`` times the first pass's samples, weighed ``have`` : ``factor`` - ``have``. ``store``: where
    the refined whole-film arrays are made (a tiled capture's may be on disk, :mod:`mbcapture.exposure.filmstore`)."""
    pix = np.asarray(pixels, dtype=np.int64).ravel()
    fac = np.broadcast_to(np.asarray(factor, dtype=np.int64), pix.shape)
    held = np.broadcast_to(np.asarray(have, dtype=np.int64), pix.shape)
    if pix.size and (fac - held).min() < 1:
        raise ValueError(
            f"refine: factor {fac[np.argmin(fac - held)]} adds no samples to the "
            f"{held[np.argmin(fac - held)]} x the first pass's the pixel holds"
        )
    stage = timer if timer is not None else (lambda name: nullcontext())
    K, H, W, C = integrated.exposure.shape
    extra = fac - held  # (P,)
    first_spp = np.asarray(plan.spp, dtype=np.int64)
    halves = np.stack([first_spp // 2, first_spp - first_spp // 2], axis=1)  # (J, 2): the first pass's halves
    per_group = per_group and integrated.group_exposure is not None
    parts, groups_out = _refine_renders(
        renderer,
        plan,
        pix,
        extra,
        halves,
        seed,
        points,
        (K, C),
        per_group=per_group,
        progress=progress,
        desc=desc,
        stage=stage,
    )
    return _with_refined(integrated, parts, groups_out, pix, held, extra, halves, store)


def _refine_renders(
    renderer,
    plan: Plan,
    pix: np.ndarray,
    extra: np.ndarray,
    halves: np.ndarray,
    seed,
    points: int,
    shape: tuple[int, int],
    *,
    per_group: bool,
    progress: bool,
    desc: str,
    stage,
) -> tuple[list[np.ndarray], np.ndarray | None]:
    """:func:`refine`'s renders: each half of each stratum at ``points`` times of its own, each pixel of ``pix``
    with ``extra`` times its first-pass samples (``halves``: the first pass's, (J, 2)); returns each half's (K, P, C)
    sums (weights applied) and, with ``per_group``, the (K, G, P, C) per-group sums."""
    K, C = shape
    first_spp = halves.sum(axis=1)
    keys = pattern_keys(seed) if plan.shares_pattern else None
    # the pixels rendered together: all of them with a pattern (counts and offsets per pixel), else by factor
    batches = [np.arange(pix.size)] if keys is not None else [np.flatnonzero(extra == e) for e in np.unique(extra)]
    offset = [np.zeros(pix.size, np.int64), np.zeros(pix.size, np.int64)]  # per half: the pattern's samples taken
    points = max(1, min(int(points), int(halves.min() * (extra.min() if pix.size else 1))))  # a sample at each time
    # times of their own: the first pass's time draws (a moving edge's positions) made its noise too
    rng = np.random.default_rng(np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x71AE)))
    times = plan.draw_times(rng, points=points)
    seeds = [
        _refine_seeds(
            plan, seed if b == 0 else np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, b)), times.shape
        )
        for b in range(len(batches))
    ]
    used = plan.weights_s.sum(axis=1) > 0
    parts = [np.zeros((K, pix.size, C)) for _ in range(2)]
    groups_out = np.zeros((K, len(plan.groups), pix.size, C)) if per_group else None
    edges = np.arange(points + 1) / points
    with _progress(plan.passes, progress, desc) as bar:
        for j in range(plan.passes):
            gsel = np.flatnonzero(used[j])
            groups_j = [plan.groups[g] for g in gsel]
            w_j = plan.weights_s[j][:, gsel]
            for h in range(2):
                # each pixel's samples of this half, shared among its times (each time's render an unbiased
                # estimate at it, weighed alike)
                counts = np.diff(np.round(np.outer(extra * halves[j, h], edges)).astype(np.int64), axis=1)
                share = halves[j, h] / first_spp[j] / points
                for i in range(points):
                    for b, batch in enumerate(batches):
                        pattern = None if keys is None else (int(keys[h]), offset[h][batch])
                        with stage("refine"):
                            rad = renderer.render_pixels(
                                float(times[j, h, i]),
                                counts[batch, i],
                                int(seeds[b][j, h, i]),
                                groups_j,
                                pix[batch],
                                pattern=pattern,
                                cached=True,
                            ).astype(np.float64)
                            parts[h][:, batch] += np.einsum("kg,gpc->kpc", w_j * share, rad, optimize=True)
                            if groups_out is not None:
                                groups_out[:, gsel[:, None], batch[None, :]] += (
                                    w_j[:, :, None, None] * (rad * share)[None]
                                )
                    offset[h] += counts[:, i]
            bar.update(1)
    return parts, groups_out


def _with_refined(integrated, parts, groups_out, pix, held, extra, halves, store: FilmStore) -> Integrated:
    """``integrated`` with the pixels ``pix`` the passes' mean by their samples (``held`` : ``extra``); the signed
    half-sample difference from the two halves' sums (``halves``: the first pass's, (J, 2))."""
    K, H, W, C = integrated.exposure.shape
    fac = held + extra
    first_spp = halves.sum(axis=1)
    r = float((halves[:, 0] / np.maximum(first_spp, 1)).mean())

    def combined(first: np.ndarray, second: np.ndarray, pixel_axis: int) -> np.ndarray:
        """``first`` with its pixels' values the passes' mean by their samples (have : extra)."""
        out = store.empty(first.shape, first.dtype)
        np.copyto(out, first)
        flat = out.reshape(*first.shape[:pixel_axis], H * W, C)
        at = (slice(None),) * pixel_axis + (pix,)
        flat[at] = (held[:, None] * flat[at] + extra[:, None] * second) / fac[:, None]
        return out

    exposure = combined(integrated.exposure, parts[0] + parts[1], 1)
    mc_diff = None
    if integrated.mc_diff is not None:
        mc_diff = combined(integrated.mc_diff, (parts[0] / r - parts[1] / (1 - r)) * np.sqrt(r * (1 - r)), 1)
    group_exposure = integrated.group_exposure
    if groups_out is not None:
        group_exposure = combined(group_exposure, groups_out, 2)
    return Integrated(
        exposure=exposure, mc_diff=mc_diff, group_exposure=group_exposure, temporal_diff=integrated.temporal_diff
    )


def _refine_seeds(plan: Plan, seed: np.random.SeedSequence, shape: tuple[int, int, int]) -> np.ndarray:
    """(J, 2, points) seeds of a second pass's renders: the strata's seeds from ``seed`` at one time a half,
    seeds of their own per time otherwise."""
    if shape[2] == 1:
        return render_seeds(plan, seed)[:, :, None]
    child = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x5EED))
    return np.random.default_rng(child).integers(0, 2**31 - 1, shape)


@dataclass(frozen=True)
class FilmLayout:
    """How a capture's render passes go through its film: in ``tiles`` of rows (None: the whole film at once),
    with whole-film results made by ``store`` (in memory, or scratch files on disk: render.spill). Every pass
    (the first, adaptive sampling's scout, the top-up) renders tile by tile as the first does, and a tile's
    renders are the whole film's rows (:func:`mbcapture.exposure.integrate.integrate_tiles`), so the budget's choices,
    made on the whole film's arrays, are those of an untiled run."""

    tiles: tuple[tuple[int, int], ...] | None = None
    store: FilmStore = IN_MEMORY

    def rows(self, height: int) -> tuple[tuple[int, int], ...]:
        """The tiles (first row, end) of a film of ``height`` rows."""
        return self.tiles or ((0, height),)

    def integrate(self, renderer, plan: Plan, n_buckets: int, seed: np.random.SeedSequence, **kw) -> Integrated:
        """:func:`mbcapture.exposure.integrate.integrate_tiles` over this layout's tiles (``kw`` passed on)."""
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
