"""Adaptive sampling's choice of pixels: the scout's count (:func:`scout_spp`), the pixels over the
tail's target (:func:`tail_pixels`), their tiers of factors (:func:`factor_tiers`) and the rule judged
by what it leaves in the tail (:class:`TailModel`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .error import BucketElectrons, TAIL_QUANTILE, read_noise_ratio, read_squared_difference
from .pilot import ladder
from .quantiles import ALIKE_FACTOR, POOL_PX, pooled_alike


#: Adaptive sampling chooses its pixels from a scout: the capture's strata rendered again, with seeds of their
#: own, at about 1 / SCOUT_DIVISOR of the first pass's samples (:func:`scout_spp`), whose half-sample
#: differences are independent of the first pass's. A choice made from the first pass's own differences
#: conditions the pixels it leaves: where the errors are heavy-tailed, a pixel left alone is one whose first
#: pass drew no rare bright path, and its value sits low (scripts/adaptive_selection_bias.py: -0.26 shot-noise
#: sigma with 78 % of a small film chosen). Chosen from the scout, every pixel keeps its first pass, unbiased,
#: and the refined ones add a second pass to it. On the default capture at 640x512 the scout at 1/16 (12
#: samples per stratum) took 4.7 s of the first pass's 49 s; at 1/8 it chose a third as many pixels for
#: 8.1 s, at 1/32 three times as many for 2.8 s (docs/noise.md, "The scout").
SCOUT_DIVISOR = 16


def scout_spp(spp: np.ndarray, count: Callable[[int], int] | None = None) -> np.ndarray:
    """The scout's samples per stratum: each stratum's over :data:`SCOUT_DIVISOR`, as two halves of at
    least 2 on :func:`ladder` (``count``: what the sampler takes, ``Renderer.sample_count``)."""
    return np.array([2 * max(2, ladder(int(n) / SCOUT_DIVISOR / 2, count)) for n in np.asarray(spp)], np.int64)


#: Adaptive sampling refines the pixels whose predicted ratio exceeds this share of the tail target. The
#: prediction is the scout's ratio scaled to the first pass's samples as 1 / spp, which the quasi-Monte
#: Carlo samplers beat (the scout's 99th percentile fell as spp^-1.19 to the first pass's, its median as
#: spp^-1.24): an upper bound, so the level is the target itself. Where the moving parts cross, the ratio is
#: not scaled: both passes draw one time per half-stratum, so their time noise is alike. On the default
#: capture at 640x512 (the first pass's ratios after each choice, docs/noise.md "The scout") 1.0 chose 8.8 %
#: of the pixels and left the tail at 0.92, 0.7 chose 25 % for 0.78.
ADAPTIVE_SELECT = 1.0

#: The levels :func:`tail_pixels` chooses among (as shares of the tail target), each with every most factor
#: up to render.adaptive_max_factor: the cheapest rule whose planned factors bring the run's own estimate of the
#: tail under its target (:class:`TailModel`). One rule does not serve every film: the default capture met the
#: tail at level 1 and at most 8x at 640x512 (0.127 of the first pass's samples added in a run, J4 99.9th
#: percentile 0.931 from outside; four rules judged, the cheaper three missed), while at 160x128 the same rule left 1.22 and level 0.5 was needed, for 0.57 of the samples
#: (scripts/adaptive_frontier.py): a small film's pixel spans more of the scene's edges. The
#: rule is one choice for the whole film, from the whole film's estimate (as the top-up's size is), so it
#: conditions no pixel's value. The levels above 1 serve the pixels whose scout ratio
#: is not scaled to the first pass's samples (where a render's time is noise): there the scout over-predicts by
#: up to the first pass's samples over its own (16x) wherever sample noise dominates, and a shaken camera makes
#: every pixel such a pixel (:func:`mbcapture.render.shadows.changing_region`).
ADAPTIVE_LEVELS = (16.0, 8.0, 4.0, 2.0, 1.6, 1.25, ADAPTIVE_SELECT, 0.8, 0.64, 0.5, 0.4, 0.32, 0.25)

#: The neighbours a chosen pixel's factor spreads to (:func:`factor_tiers`): the four sides. On the default capture
#: at 640x512 (scripts/adaptive_frontier.py) the 3x3 box added 0.182 of the first pass's samples
#: for a predicted J4 99.9th percentile of 0.899, the four sides 0.143 for 0.931 (docs/noise.md, "The frontier").
ADAPTIVE_FOOTPRINT = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)


def scout_ratio(
    mc_diff_exposure: np.ndarray,
    buckets_e: "np.ndarray | BucketElectrons",
    k_e: np.ndarray,
    reads: list[tuple[int, ...]],
    full_well_e: float,
    fd_full_well_e: float,
) -> np.ndarray:
    """(H, W): the most any read's pooled Monte Carlo / shot-noise ratio (:func:`read_noise_ratio`), in any
    channel, reaches at each pixel, from a render's half-sample differences and electrons (0 where no read
    counts the pixel): what :func:`tail_pixels` chooses from, before its scale."""
    K, H, W, C = buckets_e.shape
    worst = np.zeros((H, W))
    for buckets in reads:
        var_e, signal, use = read_noise_ratio(mc_diff_exposure, buckets_e, k_e, buckets, full_well_e, fd_full_well_e)
        ratio = np.where(use, var_e / np.maximum(signal, 1e-300), 0.0)
        worst = np.maximum(worst, ratio.max(axis=-1))
    return worst


def tail_pixels(
    mc_diff_exposure: np.ndarray,
    buckets_e: "np.ndarray | BucketElectrons",
    k_e: np.ndarray,
    reads: list[tuple[int, ...]],
    full_well_e: float,
    fd_full_well_e: float,
    tail_target: float,
    max_factor: int,
    scale: "float | np.ndarray" = 1.0,
    *,
    meets: "Callable[[np.ndarray], bool] | None" = None,
    changing: "np.ndarray | None" = None,
) -> list[tuple[np.ndarray, int]]:
    """Adaptive sampling's choice, from a scout's half-sample differences and electrons: tiers of pixels
    (flat indices) and the factor of the first pass's samples each tier is to have in all, from
    :func:`scout_ratio` times ``scale`` (the ratio the first pass has over the one these renders measure,
    one or (H, W): the scout's samples over the first pass's where only samples differ; 1 where the moving
    parts cross, :func:`mbcapture.budget.adaptive.refine_tail`).

    ``changing`` (a flat mask): the pixels where a render's time within its stratum is noise (the moving parts and
    their shadows), which the second pass renders at several times per half-stratum: there the first pass's noise,
    mostly that of its time, keeps the share 1 / f of the combination, so its variance falls nearly as 1 / f^2
    (multi_flash at 160x128: the shadow's pixels given 4x fell from 40 to 2.4, 17-fold), and a
    pixel's factor is the square root of what its ratio over the level asks for (the factor the ratio itself asks
    for, capped at 4x, left those pixels over the tail). The rules are still judged with every pixel's
    variance as 1 / f (:class:`TailModel`): between the limits 1 / f (noise all of the samples) and 1 / f^2 (all of
    the render's time), the first is an upper bound; judged by the second, four of the shipped configs chose rules
    that left their tail at 1.04-1.78 and their median up to 0.112 (``make test-budget``).

    Without ``meets``: :func:`factor_tiers` at the level :data:`ADAPTIVE_SELECT` x the tail target. With
    ``meets(factors)`` (the flat factor of every pixel; whether they would bring the tail under its target,
    :meth:`TailModel.meets`): the cheapest rule that does, among every level of :data:`ADAPTIVE_LEVELS` with
    every most factor, a power of two up to ``max_factor``, and no refinement at all; the costliest when none does
    (the most the rules offer). Cost: the samples added, the sum of (factor - 1)."""
    worst = scout_ratio(mc_diff_exposure, buckets_e, k_e, reads, full_well_e, fd_full_well_e)
    worst *= scale
    on = np.zeros(worst.shape, bool) if changing is None else np.asarray(changing, bool).reshape(worst.shape)

    def asked(level: float) -> np.ndarray:  # the ratio whose power of two over the level is each pixel's factor
        return np.where(on, np.sqrt(np.maximum(worst, 0.0) * level), worst)

    if meets is None:
        return factor_tiers(asked(ADAPTIVE_SELECT * tail_target), ADAPTIVE_SELECT * tail_target, max_factor)
    top = int(np.log2(max_factor))
    rules = [np.zeros(worst.size, np.int64)]  # log2 of each pixel's factor; first, no refinement
    for level in ADAPTIVE_LEVELS:
        tier = tier_exponents(asked(level * tail_target), level * tail_target, top).ravel()
        rules += [np.minimum(tier, m) for m in range(1, top + 1)]
    cost = [int((np.left_shift(1, r) - 1).sum()) for r in rules]
    best = rules[int(np.argmax(cost))]
    for i in np.argsort(cost, kind="stable"):
        if meets(np.left_shift(1, rules[i])):
            best = rules[i]
            break
    return tiers_of(best)


def tier_exponents(predicted: np.ndarray, level: float, top: int) -> np.ndarray:
    """(H, W) int: log2 of the factor :func:`factor_tiers` gives each pixel (0: not refined), at most ``top``."""
    from scipy.ndimage import grey_dilation

    chosen = predicted > level
    tier = np.zeros(predicted.shape, np.int64)
    if chosen.any():
        tier[chosen] = np.clip(np.ceil(np.log2(predicted[chosen] / level)), 1, top).astype(np.int64)
        tier = grey_dilation(tier, footprint=ADAPTIVE_FOOTPRINT, mode="constant", cval=0)
    return tier


def tiers_of(tier: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """[(flat pixels, factor)] by increasing factor from an array of log2 factors (0: not refined)."""
    tier = tier.ravel()
    return [(np.flatnonzero(tier == t), 1 << int(t)) for t in np.unique(tier[tier > 0])]


def factor_tiers(predicted: np.ndarray, level: float, max_factor: int) -> list[tuple[np.ndarray, int]]:
    """The tiers of :func:`tail_pixels` from the predicted ratio of each pixel (H, W), at one level.

    A pixel is chosen where that ratio exceeds ``level``; its factor is the ratio over the level
    (variance ~ 1/spp: conservative for the quasi-Monte Carlo samplers), rounded up to a power of two in
    [2, ``max_factor``]. A pixel's four side neighbours get at least its factor (:data:`ADAPTIVE_FOOTPRINT`:
    the estimate is pooled over them). Chosen from the scout with the first pass kept, 2x meets the tail
    at the default capture (docs/noise.md, "The scout"). Other rules (a lower level, a smaller
    neighbourhood, factors to a lower target) cost more for the same tail or leave a higher tail for
    less (scripts/adaptive_frontier.py; docs/noise.md, "The frontier"); the four sides rather than the 3x3 box
    are a point of that frontier with a fifth fewer samples for a tail 0.03 higher.
    Returns [(pixels, factor)] by
    increasing factor, every pixel in one tier at most; [] when no pixel needs it."""
    return tiers_of(tier_exponents(predicted, level, int(np.log2(max_factor))))


class TailModel:
    """What a plan of per-pixel factors would leave in the tail of the run's own estimate, without rendering
    it: :func:`render_error`'s 99.9th percentile of each read's ratio (pooled by :func:`pooled_alike`) on the
    first pass, each pixel's squared half-sample differences over its factor f (variance ~ 1/spp, as
    :func:`mbcapture.budget.adaptive.with_planned_refinement` assumes). A factor only lowers a sample's ratio, so only the
    samples over the target can decide; for those it keeps the terms of their pooled sums (the alike neighbours'
    squared differences over the sample's own electrons and count, written here: pooled_alike's sums, term by
    term), and :meth:`meets` divides each term by its pixel's factor and counts the samples left over the target
    against what the quantile allows. Exact, to the last bits of the sums' order; thousands of plans cost what one
    pooled_alike does."""

    def __init__(
        self,
        mc_diff_exposure: np.ndarray,
        buckets_e: "np.ndarray | BucketElectrons",
        k_e: np.ndarray,
        reads: list[tuple[int, ...]],
        full_well_e: float,
        fd_full_well_e: float | None,
        tail_target: float,
        quantile: float = TAIL_QUANTILE,
    ):
        K, H, W, C = buckets_e.shape
        self.terms: list[np.ndarray] = []  # per read: (S, 9) the terms of each over-target sample's pooled ratio
        self.neighbours: list[np.ndarray] = []  # per read: (S, 9) the flat pixel of each term
        self.allowed: list[int] = []  # per read: how many samples may stay over the target
        self.target = float(tail_target)
        r = POOL_PX // 2
        offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        limit = np.log(ALIKE_FACTOR)
        for buckets in reads:
            squared, signal, use = read_squared_difference(
                mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e
            )
            n = int(use.sum())
            if n == 0:
                continue
            ratio = pooled_alike(squared, signal) * k_e**2 / np.maximum(signal, 1e-300)
            over = use & (ratio > self.target)
            del ratio
            y, x, c = np.nonzero(over)
            log_g = np.log(np.maximum(signal, 1e-300))
            centre = log_g[y, x, c]
            terms = np.zeros((y.size, len(offsets)))
            where = np.zeros((y.size, len(offsets)), np.int64)
            count = np.zeros(y.size)
            for i, (dy, dx) in enumerate(offsets):  # the film's border repeated, as pooled_alike pads
                yy, xx = np.clip(y + dy, 0, H - 1), np.clip(x + dx, 0, W - 1)
                alike = np.abs(log_g[yy, xx, c] - centre) <= limit
                terms[:, i] = np.where(alike, squared[yy, xx, c], 0.0)
                where[:, i] = yy * W + xx
                count += alike
            terms *= (k_e[c] ** 2 / (count * signal[y, x, c]))[:, None]
            self.terms.append(terms)
            self.neighbours.append(where)
            self.allowed.append(n - int(np.ceil(quantile / 100.0 * n)))

    def meets(self, factors: np.ndarray) -> bool:
        """Whether every read's tail would be at most the target with the flat per-pixel ``factors``
        (the p-quantile, the smallest value whose share reaches p, is at most the target where no more than
        n - ceil(p n) of the n samples exceed it)."""
        f = np.asarray(factors, np.float64).ravel()
        return all(
            int(((t / f[w]).sum(axis=1) > self.target).sum()) <= a
            for t, w, a in zip(self.terms, self.neighbours, self.allowed)
        )
