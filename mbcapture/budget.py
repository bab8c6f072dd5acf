"""The noise budget: samples per pixel from a pilot, the render-error estimate and its verdict.

Samples per pixel (``render.spp`` null): :func:`choose_spp` renders a pilot and allocates
samples so that, over the lit unsaturated samples of every read the sensor outputs, the ratio of
the Monte Carlo variance of the read's electrons to the photon shot-noise variance the sensor adds
there has its median at most ``render.noise_budget`` (0.1) and its 95th percentile at most
``render.noise_budget_p95`` (1.0). Reads, not buckets: a read sums buckets whose Monte Carlo errors
come from the same renders, so they add coherently while shot noise adds in variance, and the ratio
grows with the read's exposure (the longest read of photon-efficient HDR decides). The tail (the
99.9th percentile, ``render.noise_budget_tail``) is estimated and judged on every run, but not
bought with samples everywhere. A median and a percentile rather than a mean: a handful of
hard pixels (the lamp's rim, speculars) would otherwise set the samples of the whole image
(measured on the metronome at 640x512: 7 x ~765 spp for a mean of 0.1, 7 x ~420 for the median
and p95 with independent samples).

The pilot, at up to ``PILOT_TIMES`` strata: two independent renders at each of ``PILOT_SPP``
(4 and 16). Each pair is the main render's two-halves estimator at twice the count, and its
squared difference over 4 that estimator's variance, per pixel; pooled over 3x3 pixels (about 9
degrees of freedom; :func:`budget_quantiles` takes the median of the true ratios behind these noisy
estimates, :func:`deconvolved_median`) and
divided by the pilot's expected electrons, this gives each read's ratios at the two counts. With
randomized quasi-Monte Carlo samplers (``render.sampler``) variance falls faster than 1/spp, so
the exponent between the two counts is measured (clipped to [1, 2]) and each target's quantile is
extrapolated to the count that meets it. Strata share that count in proportion to their Neyman
shape (sqrt of each stratum's summed variance: a stratum that weighs more in the buckets gets
more samples), but none gets fewer than the smaller pilot count (2 x 4), where the ratio was
measured rather than extrapolated; every stratum uses its nearest pilot. Counts are rounded up to what the sampler
takes for each half (ldsampler: powers of 4) within [2, ``render.max_spp``]. A dim scene gets
fewer samples: the variance scales with the square of the light, the shot noise with the light.

A film of more than 2 x ``PILOT_BLOCKS`` 3x3 blocks is piloted on ``PILOT_BLOCKS`` of them, drawn at
random (:func:`pilot_blocks`, rendered by ``Renderer.render_pixels``): every figure above is a quantile or
a ratio of sums over the film, which a random sample of its blocks estimates without bias, and each
block's centre pools exactly the 3x3 pixels it would pool in the film. At 640x512 that is a quarter of
the film, and the pilot's 7 s become 2 s (docs/noise.md, "The pilot on blocks").

The pilot also times its renders: seconds per pass = c0 + c1 x spp (two-point fit, medians
over the pilot times; c1 scaled to the film from a pilot on blocks) is the cost model behind
``Plan.estimate``.

The run's own estimate of its rendering error (:func:`render_error`, from the two half-sample
renders of every stratum) and its one-line verdict (:func:`noise_verdict`) are judged against the
same targets. It pools each sample's squared difference over the neighbours as bright as it
(:func:`pooled_alike`), not over all of them: across a silhouette the dark side would otherwise take
its edge's coverage noise, which put the tail several times too high. The pilot, which judges the
median and the p95 only, pools over all of them, electrons and variance alike.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from .integrate import accumulate, sample_counter
from .plan import Plan
from .sensor import electrons_per_render_second

#: Strata at which the pilot renders (spread evenly over the capture).
PILOT_TIMES = 3


def _pilot_indices(plan: Plan) -> np.ndarray:
    """Strata the pilot renders at: up to PILOT_TIMES, spread evenly over the capture."""
    return np.unique(np.linspace(0, plan.passes - 1, min(PILOT_TIMES, plan.passes)).round().astype(int))


def _timed(renderer, t_s: float, make: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
    """``make()`` (a render at ``t_s``) as float64 and its seconds, the scene update included: every pass
    of a run moves the geometry (and rebuilds the acceleration structure) before it renders."""
    t0 = time.perf_counter()
    renderer.set_time(float(t_s), force=True)
    img = make()
    seconds = time.perf_counter() - t0
    if getattr(renderer, "last_cached", False):  # from the render cache: the seconds it took when made
        seconds = renderer.last_render_s
    return img.astype(np.float64), seconds


def _timed_render(renderer, t_s: float, spp: int, seed: int, groups) -> tuple[np.ndarray, float]:
    """One render of the film and its seconds (:func:`_timed`)."""
    return _timed(renderer, t_s, lambda: renderer.render(float(t_s), int(spp), int(seed), groups))


#: The most of the film's 3x3 lattice blocks the pilot renders (:func:`pilot_blocks`): a film with more
#: than twice as many is piloted on this many of them, drawn at random, whole films below. The pilot
#: judges quantiles over the film, which a random sample of its blocks estimates without bias (the
#: deconvolved median's relative error at most DECONV_REL_SD / sqrt(blocks), 3 % here). At 640x512
#: (36 k blocks) this is a quarter of the film: the pilot took 7.5 s of the default capture's 64 s and
#: takes 1.6 s, and the samples it asks for scatter twice as far (sd 5 % against 2.5 %; docs/noise.md).
PILOT_BLOCKS = 8192


def pilot_blocks(height: int, width: int, rng: np.random.Generator) -> np.ndarray | None:
    """Centres (flat indices, sorted) of the POOL_PX x POOL_PX blocks of the film's lattice that the
    pilot renders: PILOT_BLOCKS of them drawn at random without replacement, or None (the whole film)
    where the film holds no more than twice as many."""
    rows, cols = np.arange(1, height - 1, POOL_PX), np.arange(1, width - 1, POOL_PX)
    if rows.size * cols.size <= 2 * PILOT_BLOCKS:
        return None
    centres = (rows[:, None] * width + cols[None, :]).ravel()
    return np.sort(rng.choice(centres, size=PILOT_BLOCKS, replace=False)).astype(np.int64)


def block_pixels(centres: np.ndarray, width: int) -> np.ndarray:
    """(blocks, POOL_PX^2) flat indices of the pixels of the POOL_PX x POOL_PX blocks centred on
    ``centres``, each block's row-major."""
    r = POOL_PX // 2
    offsets = (np.arange(-r, r + 1)[:, None] * width + np.arange(-r, r + 1)[None, :]).ravel()
    return np.asarray(centres, np.int64)[:, None] + offsets[None, :]


def block_mosaic(values: np.ndarray) -> np.ndarray:
    """Per-pixel values of blocks, (G, blocks x POOL_PX^2, C) in :func:`block_pixels`' order, laid side by
    side as a film (G, POOL_PX, blocks x POOL_PX, C): the POOL_PX x POOL_PX window of each block's centre
    (row POOL_PX // 2, columns POOL_PX i + POOL_PX // 2) is the block, so :func:`pooled` and
    :func:`effective_dof` see each block whole there (and a mix of neighbours elsewhere, which
    :func:`mosaic_centres` leaves out)."""
    G, n, C = values.shape
    nb = n // POOL_PX**2
    return values.reshape(G, nb, POOL_PX, POOL_PX, C).transpose(0, 2, 1, 3, 4).reshape(G, POOL_PX, nb * POOL_PX, C)


def mosaic_centres(blocks: int) -> np.ndarray:
    """(POOL_PX, blocks x POOL_PX) bool: the centres of a :func:`block_mosaic` of ``blocks`` blocks."""
    out = np.zeros((POOL_PX, blocks * POOL_PX), bool)
    out[POOL_PX // 2, POOL_PX // 2 :: POOL_PX] = True
    return out


def _timed_pixels(renderer, t_s: float, spp: int, seed: int, groups, pixels: np.ndarray) -> tuple[np.ndarray, float]:
    """:func:`_timed_render` of the pilot's blocks (``pixels`` from :func:`block_pixels`): their
    :func:`block_mosaic` and its seconds."""
    values, seconds = _timed(
        renderer,
        t_s,
        lambda: renderer.render_pixels(float(t_s), int(spp), int(seed), groups, pixels.ravel(), cached=True),
    )
    return block_mosaic(values), seconds


def _cost_model(
    pairs: list[tuple[float, float]], first_s: float, accumulate_s: float, spp_pair: tuple[int, int] = (1, 4)
) -> dict:
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


#: The neighbours :func:`pooled_alike` pools with a pixel: those whose expected electrons lie within this
#: factor of the pixel's own.
ALIKE_FACTOR = 1.5
#: Rows :func:`pooled_alike` works on at once (its temporaries are a band's, not the film's).
ALIKE_BAND_ROWS = 64


def pooled_alike(v: np.ndarray, guide: np.ndarray, factor: float = ALIKE_FACTOR) -> np.ndarray:
    """Per-pixel variance estimates ``v`` (H, W, C) averaged over the pixel and those of its POOL_PX x
    POOL_PX neighbours whose ``guide`` (H, W, C: the expected electrons) lies within ``factor`` of its
    own, channel by channel (the film's border repeated, as in :func:`pooled`).

    Written here: an edge-preserving box mean (a bilateral filter whose range kernel is a box around the
    centre's value), which scipy and OpenCV do not offer on float64 data. :func:`pooled` averages every
    neighbour, which assumes the variance is smooth over 3x3; across a silhouette it is not. There a
    pixel on the dark side took a share of its bright edge neighbour's variance (coverage noise, tens of
    times its own) and divided it by its own few electrons. Pooled with the neighbours of its own
    brightness, an edge pixel pools with the edge and a dark one with the dark: fewer neighbours at an
    edge, so a noisier estimate there, but not one biased by another pixel's noise."""
    v = np.asarray(v, np.float64)
    H, W = v.shape[:2]
    r = POOL_PX // 2
    limit = np.log(factor)
    out = np.empty_like(v)
    for y0 in range(0, H, ALIKE_BAND_ROWS):
        y1 = min(y0 + ALIKE_BAND_ROWS, H)
        a, b = max(y0 - r, 0), min(y1 + r, H)  # the band and its halo, within the film
        widths = ((r - (y0 - a), r - (b - y1)), (r, r), (0, 0))  # the rest of the halo: the border repeated
        vp = np.pad(v[a:b], widths, mode="edge")
        gp = np.log(np.maximum(np.pad(np.asarray(guide[a:b], np.float64), widths, mode="edge"), 1e-300))
        rows = y1 - y0
        centre = gp[r : r + rows, r : r + W]
        total, count = np.zeros((rows, W, v.shape[2])), np.zeros((rows, W, v.shape[2]))
        for dy in range(POOL_PX):
            for dx in range(POOL_PX):
                alike = np.abs(gp[dy : dy + rows, dx : dx + W] - centre) <= limit
                np.add(total, vp[dy : dy + rows, dx : dx + W], out=total, where=alike)
                count += alike
        out[y0:y1] = total / count  # the centre is always alike: count >= 1
    return out


def chi2_median_factor(dof: float) -> float:
    """Median of chi^2_dof / dof (Wilson-Hilferty): how far below the mean the median of noisy
    variance estimates of one uniform variance lies; 0.93 for 9 degrees of freedom."""
    return (1.0 - 2.0 / (9.0 * dof)) ** 3


#: Bounds of the effective degrees of freedom :func:`effective_dof` returns.
DOF_RANGE = (1.0, 4.0 * POOL_PX**2)
#: Fewer usable checkerboard pairs than this: :func:`effective_dof` returns POOL_PX^2 (Gaussian errors).
DOF_MIN_PAIRS = 100
#: :func:`effective_dof` measures bands of this many rows, on at most about this many values.
DOF_BAND_ROWS = 64
DOF_MAX_VALUES = 1 << 22


def effective_dof(unpooled: np.ndarray, use: np.ndarray) -> float:
    """The effective degrees of freedom of a POOL_PX x POOL_PX pooled variance estimate, measured on
    its own data: ``unpooled`` (..., H, W, C) the squared differences before pooling, ``use`` the
    samples that count (same shape).

    Each pool is split like a checkerboard into its cells of even and odd parity (for 3x3: the centre
    and corners, 5, against the edges, 4): two independent estimates A and B of nearly the same
    variance. Were each squared difference sigma^2 chi^2_1 (Gaussian errors), the mean of n of them is
    a gamma variable of shape n/2, and Var[log(A/B)] = psi'(n_A/2) + psi'(n_B/2). Rendering errors are
    heavier-tailed than Gaussian (rare bright paths) and neighbouring pixels' variances differ, which
    both widen it; with excess kurtosis kappa the shape of a mean of n is n/(2 + kappa). Solving for
    kappa from the measured variance of log(A/B) gives the whole pool's effective degrees of freedom,
    2 POOL_PX^2/(2 + kappa), within :data:`DOF_RANGE`. Measured on the metronome
    (scripts/render_noise_reads.py --truth): 7.2 at 160x128, 7.6 at 320x256, against 9 for Gaussian
    errors."""
    from scipy.ndimage import convolve
    from scipy.optimize import brentq
    from scipy.special import polygamma

    v = np.asarray(unpooled)
    use = np.broadcast_to(np.asarray(use, bool), v.shape)
    odd = (np.add.outer(np.arange(POOL_PX), np.arange(POOL_PX)) % 2).astype(np.float64)
    n_even, n_odd = float((1.0 - odd).sum()), float(odd.sum())
    n_pool = float(POOL_PX**2)
    shape = [1] * (v.ndim - 3) + [POOL_PX, POOL_PX, 1]
    H = v.shape[-3]
    # bands of rows, each split on its own; a large film is measured on every step-th band, so that
    # this holds a few bands' temporaries rather than the film's
    step = max(1, int(np.ceil(v.size / DOF_MAX_VALUES)))
    logs = []
    for r0 in range(0, H, DOF_BAND_ROWS * step):
        band = np.asarray(v[..., r0 : r0 + DOF_BAND_ROWS, :, :], dtype=np.float64)
        a = convolve(band, ((1.0 - odd) / n_even).reshape(shape), mode="nearest")
        b = convolve(band, (odd / n_odd).reshape(shape), mode="nearest")
        ok = use[..., r0 : r0 + DOF_BAND_ROWS, :, :] & (a > 0.0) & (b > 0.0)
        logs.append(np.log(a[ok] / b[ok]))
    ratios = np.concatenate(logs)
    if ratios.size < DOF_MIN_PAIRS:
        return n_pool
    spread = float(np.var(ratios))

    def excess(kappa: float) -> float:
        return float(polygamma(1, n_even / (2.0 + kappa)) + polygamma(1, n_odd / (2.0 + kappa))) - spread

    # kappa at the most and the fewest degrees of freedom
    lo, hi = 2.0 * n_pool / DOF_RANGE[1] - 2.0, 2.0 * n_pool / DOF_RANGE[0] - 2.0
    if excess(lo) >= 0.0:
        return DOF_RANGE[1]
    if excess(hi) <= 0.0:
        return DOF_RANGE[0]
    return 2.0 * n_pool / (2.0 + brentq(excess, lo, hi, xtol=1e-6))


#: The log-ratio histogram :func:`deconvolved_median` works on: bins per unit of log, and
#: Richardson-Lucy iterations.
DECONV_BINS_PER_UNIT = 10
DECONV_ITERATIONS = 200
#: :func:`deconvolved_median` bins its estimates this many at a time, and sets its histogram's range
#: from at most this many of them.
DECONV_RANGE_VALUES = 1 << 20
#: The relative standard deviation of :func:`deconvolved_median` times sqrt(effective count) of its
#: values (:func:`effective_count`): its scatter, the estimates' own sampling noise included. Measured
#: on lognormal fields (log sd 1.5) under chi^2_1 noise pooled over 3x3 on a 240x320 film: 2.1-2.3
#: (16 fields; 2000 and 20000 values drawn from the film), 1.5 on the whole film, 2.9 on adaptive
#: sampling's audited sample with its weights (20 fields, tests/test_adaptive.py's film; that audit no longer
#: exists and the constant is kept); on the metronome's own runs 0.7-0.8 (12 runs at
#: 320x256, 24 at 160x128). The largest, rounded up.
DECONV_REL_SD = 3.0


def deconvolved_median(ratio: np.ndarray, dof: float) -> float:
    """The median of the true ratios behind noisy pooled estimates ``ratio`` (1-D, >= 0), each the true
    ratio times an independent chi^2_dof / dof.

    Dividing the estimates' median by :func:`chi2_median_factor` is right only where every estimate
    has the same true ratio. Over a film the true ratios spread (walls, edges, shadows), and the
    estimates' distribution is theirs convolved with the noise's, in log space, whose mean lies below
    its median: measured on the metronome against 12 and 24 independent runs, that division read the
    median 13-15 % low. This removes the noise's kernel from a histogram of log estimates by
    Richardson-Lucy iteration (the maximum-likelihood deconvolution for counts) and returns the median
    of what is left; the estimates at 0 (no variance measured) count below it. Written here: scipy and
    scikit-image deconvolve images with a shift-invariant kernel, not one histogram with a kernel
    given by its cumulative distribution."""
    from scipy.stats import chi2

    r = np.asarray(ratio, dtype=np.float64).ravel()
    if r.size == 0:
        raise ValueError("deconvolved_median: no values")
    pos = r > 0.0
    zero_share = float((~pos).sum()) / r.size
    if zero_share >= 0.5 or not pos.any():
        return 0.0
    # the histogram spans the middle 99.8 % of the positive estimates (what lies beyond is put in its end
    # bins: it counts on the right side of the median, where it lies does not), so its size does not grow
    # with a few outliers; measured on at most DECONV_RANGE_VALUES of them, evenly strided
    stride = max(1, -(-r.size // DECONV_RANGE_VALUES))
    lo, hi = (float(x) for x in np.log(np.percentile(r[::stride][pos[::stride]], [0.1, 99.9])))
    step = 1.0 / DECONV_BINS_PER_UNIT
    # the noise's log reaches far below 0 (chi^2 near 0) and a little above: room on both sides
    edges = np.arange(lo - 4.0, hi + 2.0 + step, step)
    centres = 0.5 * (edges[1:] + edges[:-1])
    h = np.zeros(centres.size)
    for a in range(0, r.size, DECONV_RANGE_VALUES):  # in chunks: a 12 MP read holds 36 M estimates
        sel = pos[a : a + DECONV_RANGE_VALUES]
        lr = np.log(np.clip(r[a : a + DECONV_RANGE_VALUES][sel], np.exp(lo), np.exp(hi)))
        idx = np.clip(((lr - edges[0]) / step).astype(np.int64), 0, centres.size - 1)
        h += np.bincount(idx, minlength=centres.size)
    h /= h.sum()
    # kernel[i, j]: the chance that an estimate falls in bin i when its true ratio is at centre j
    kernel = np.diff(chi2.cdf(dof * np.exp(edges[:, None] - centres[None, :]), dof), axis=0)
    g = h.copy()
    for _ in range(DECONV_ITERATIONS):
        g *= kernel.T @ (h / np.maximum(kernel @ g, 1e-300))
        g /= g.sum()
    cdf = zero_share + (1.0 - zero_share) * np.cumsum(g)
    return float(np.exp(np.interp(0.5, cdf, edges[1:])))


def budget_quantiles(ratio: np.ndarray, dof: float = POOL_PX**2) -> tuple[float, float]:
    """(median, 95th percentile) of per-sample Monte Carlo / shot variance ratios estimated from
    pooled squared differences (``dof``: their effective degrees of freedom, :func:`effective_dof`):
    the median is :func:`deconvolved_median`'s; the 95th percentile is left as it is (the
    estimates' own spread only widens it: conservative)."""
    return deconvolved_median(ratio, dof), float(np.percentile(ratio, 95))


#: Coverage of the interval the run states for each of its quantiles (render_error's ``*_interval``).
INTERVAL_COVERAGE = 0.95


def interval_z() -> float:
    """The standard normal quantile of :data:`INTERVAL_COVERAGE`'s two-sided interval (1.96 for 95 %)."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + INTERVAL_COVERAGE / 2))


def effective_count(n: int, design: "np.ndarray | float" = 1.0) -> float:
    """Kish's effective count of ``n`` values with ``design`` d the number of values that share their
    data: n^2 / sum(d)."""
    d = np.broadcast_to(np.asarray(design, np.float64), (n,))
    return n**2 / float(d.sum())


def quantiles_with_intervals(
    values: np.ndarray, percents: "list[float]", design: "np.ndarray | float" = 1.0
) -> list[tuple[float, float, float]]:
    """(estimate, low, high) of each percentile in ``percents`` of ``values`` (1-D), with an
    :data:`INTERVAL_COVERAGE` interval from the order statistics.

    The share of the values below a point is a mean of indicators, so its standard error is
    sqrt(p (1 - p) / n_eff), with Kish's effective count n_eff = n^2 / sum(d) and ``design``
    d the number of values that share their data (a pooled 3x3 estimate shares its renders with its
    neighbours, a pixel's channels their paths): the interval is the values at p -/+ z x that error.
    The estimate is the inverted empirical CDF (the smallest value whose share reaches p). What it
    covers: the quantile's uncertainty over a finite set of noisy estimates, which an outside
    measurement with the same estimator (3x3 pooled squared differences) shares in kind. A high end
    at p + z se >= 1 is the largest value (the interval is then open above)."""
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        raise ValueError("quantiles_with_intervals: no values")
    z = interval_z()
    probs = np.asarray(percents, np.float64) / 100.0
    n_eff = effective_count(v.size, design)
    se = np.sqrt(probs * (1 - probs) / n_eff)
    wanted = np.clip(np.stack([probs, probs - z * se, probs + z * se], -1), 0.0, 1.0)  # (len(percents), 3)
    # rank of the inverted CDF: O(n) by partition (a 12 MP film's read is 36 M values)
    ranks = np.clip(np.ceil(wanted * v.size).astype(np.int64) - 1, 0, v.size - 1)
    picked = np.partition(v, np.unique(ranks))[ranks]
    return [(float(e), float(lo), float(hi)) for e, lo, hi in picked]


#: The pilot's two sample counts: at each, two independent renders (their mean is the main
#: render's two-halves estimator at twice the count, their difference its error).
PILOT_SPP = (4, 16)
#: Range of the fitted convergence exponent: Monte Carlo variance ~ spp^-exponent (1 for
#: independent samples, up to 2 for randomized quasi-Monte Carlo on smooth integrands).
EXPONENT_RANGE = (1.0, 2.0)


#: Steps per octave of the ladder of sample counts (:func:`_ladder`): 2.2 % apart, so a stratum gets little
#: more than the pilot asked for (19 % or 9 % steps cost that much more), while the strata of a capture share
#: few counts. Distinct counts cost a kernel each where the sampler's count is a literal of it (multijitter:
#: about 0.25 s each at 640x512); the renders that draw from the shared pattern take their count opaque
#: and compile once for all counts.
LADDER_STEPS = 32


def _ladder(x: float, count: Callable[[int], int] | None = None) -> int:
    """x rounded up to a count on the ladder round(2^(i / LADDER_STEPS)), each point moved down to the
    nearest count the sampler takes as it is (``count(m) == m``; multijitter takes 99 when asked for
    91, but 90 exactly), and not below x: strata get few distinct sample counts (Dr.Jit compiles one
    kernel per count), and no sample is taken that the ladder did not ask for. ``count`` (what the
    sampler takes when asked for m, ``Renderer.sample_count``) defaults to every count as it is."""
    count = count or (lambda m: m)
    if x <= 4:
        return count(max(int(np.ceil(x)), 1))
    low = int(np.ceil(x - 1e-9))
    i = int(np.ceil(LADDER_STEPS * np.log2(x) - 1e-9))
    while True:
        point = int(round(2 ** (i / LADDER_STEPS)))
        exact = next((m for m in range(point, low - 1, -1) if count(m) == m), None)
        if exact is not None:
            return exact
        i += 1


def _pilot_ratios(
    diffs: list[np.ndarray],
    owner: np.ndarray,
    w: np.ndarray,
    alpha: np.ndarray,
    electrons: np.ndarray,
    lit: np.ndarray,
    k: int,
) -> tuple[np.ndarray, float]:
    """Per-sample ratio of bucket k's Monte Carlo variance to its shot noise, for strata rendered
    at alpha_j times the pilot's count, over the lit samples: diffs[p] (G, H, W, C) are one pilot
    time's differences of two independent renders (electrons per second), whose square over 4
    estimates the variance of their mean; pooled over POOL_PX^2 pixels. With the pooled estimates'
    :func:`effective_dof`."""
    var_k = np.zeros(lit.shape[1:])
    for p, d in enumerate(diffs):
        sel = owner == p
        C = np.einsum("jg,jh->gh", w[sel, k] / alpha[sel, None], w[sel, k])  # (G, G)
        var_k += np.einsum("gh,gywc,hywc->ywc", C, d, d, optimize=True) / 4.0
    dof = effective_dof(var_k, lit[k])
    return pooled(var_k)[lit[k]] / electrons[k][lit[k]], dof


def shared_pattern_gain(weights: np.ndarray, exponent: float) -> float:
    """What a pattern shared by the strata (render.pattern 'shared') does to a read's variance at a
    static pixel, by the pilot's own model: the read sums its strata with ``weights`` (J,), the
    equivalent of K = (sum w)^2 / sum w^2 strata of equal weight, whose samples, drawn from one
    pattern, are stratified like one render of K times the samples; per-sample variance falls as
    spp^-(exponent - 1) (the exponent the pilot measured between its counts), so the read's variance is
    K^-(exponent - 1) times what independent patterns give. Applied to the median only: the median
    sample is a static pixel lit by indirect light, which gains that much (measured: 1.39x on J4 of
    the default capture); the 95th percentile gained 1.01-1.07x (docs/noise.md)."""
    w = np.abs(np.asarray(weights, dtype=np.float64))
    if w.sum() <= 0:
        return 1.0
    k_eff = w.sum() ** 2 / np.square(w).sum()
    return float(k_eff ** -(max(exponent, 1.0) - 1.0))


def choose_spp(
    plan: Plan,
    renderer,
    k_e: np.ndarray,
    full_well_e: float,
    noise_budget: float,
    max_spp: int,
    seed: np.random.SeedSequence,
    noise_budget_p95: float | None = None,
    fd_full_well_e: float | None = None,
) -> Plan:
    """Samples per pixel per stratum from a pilot (the rule is in the module docstring), so that every
    read of ``plan.read_sets`` meets the budget (``fd_full_well_e``: the floating diffusion's limit on a
    read's sum).

    ``k_e`` (C,): electrons per render unit and second. Returns the plan with ``spp``,
    ``pilot`` and ``cost`` filled in; the pilot's renders are not used in the image (their
    samples chose n_j: reusing them would bias the estimate).
    """
    if plan.passes == 0:
        return replace(plan, spp=np.zeros(0, np.int64), spp_source="noise_budget")
    fd_full = float("inf") if fd_full_well_e is None else fd_full_well_e
    p95_target = 10.0 * noise_budget if noise_budget_p95 is None else noise_budget_p95
    t_start = time.perf_counter()
    k_e = np.asarray(k_e, dtype=np.float64)
    idx = _pilot_indices(plan)
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, 2**31 - 1, size=(len(idx), len(PILOT_SPP), 2))
    # a large film: a random sample of its blocks, side by side (block_mosaic), whose centres alone count
    sparse = getattr(renderer, "renders_pixels_alone", False)
    centres = pilot_blocks(renderer.height, renderer.width, rng) if sparse else None
    if centres is None:
        only, film_share = True, 1.0
        render = lambda t, n, s: _timed_render(renderer, t, n, s, plan.groups)  # noqa: E731
    else:
        pixels = block_pixels(centres, renderer.width)
        only, film_share = mosaic_centres(centres.size)[:, :, None], pixels.size / (renderer.height * renderer.width)
        render = lambda t, n, s: _timed_pixels(renderer, t, n, s, plan.groups, pixels)  # noqa: E731
    # the budget is met on the reads the sensor outputs: a read's weights (and electrons) are its buckets'
    # sums, and its Monte Carlo errors add coherently (the same renders); one read per bucket without sets
    read_sets = plan.read_sets or tuple((b,) for b in plan.buckets_read)
    shared = plan.shares_pattern
    w_b = plan.weights_s  # (J, K, G)
    w = np.stack([w_b[:, list(r)].sum(axis=1) for r in read_sets], axis=1)  # (J, R, G)
    J, K, G = w.shape  # K: reads from here on
    names = list(plan.read_names) if plan.read_sets else [f"B{b + 1}" for b in plan.buckets_read]
    owner = np.abs(plan.times_s[:, None] - plan.times_s[idx][None, :]).argmin(axis=1)  # nearest pilot
    means: list[np.ndarray] = []
    diffs: dict[int, list[np.ndarray]] = {s: [] for s in PILOT_SPP}
    seconds: dict[int, list[float]] = {s: [] for s in PILOT_SPP}
    for p, j in enumerate(idx):
        total = 0.0
        for level, spp in enumerate(PILOT_SPP):
            (a, ta), (b, tb) = (render(plan.times_s[j], spp, seeds[p, level, h]) for h in range(2))
            diffs[spp].append((a - b) * k_e)  # (G, H, W, C), electrons per second
            seconds[spp] += [ta, tb]
            total = total + (a + b) * spp
        means.append(total / (2 * sum(PILOT_SPP)))  # every pilot sample of this time
    acc = _timed_accumulate(w_b[idx[0]], means[0], w_b.shape[1])
    wp = np.stack([w_b[owner == p].sum(axis=0) for p in range(len(idx))])  # (P, K buckets, G)
    # the ratios' denominator, pooled like their numerator so that its own noise does not scatter them
    bucket_e = pooled(np.einsum("pkg,pghwc->khwc", wp, np.stack(means), optimize=True) * k_e)
    electrons = np.stack([bucket_e[list(r)].sum(axis=0) for r in read_sets])  # (R, H, W, C)
    # a read's sample counts where it holds light and none of its buckets (nor their sum) is full
    lit = (
        np.stack([(bucket_e[list(r)] < full_well_e).all(axis=0) for r in read_sets])
        & (electrons > 1.0)
        & (electrons < fd_full)
        & only
    )
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
    scale, per_read = 0.0, []
    n_lo, n_hi = 2 * PILOT_SPP[0], 2 * PILOT_SPP[-1]  # two halves: the main render's total count
    for k in range(K):
        if not lit[k].any():
            per_read.append(None)
            continue
        q = {
            n: budget_quantiles(*_pilot_ratios(diffs[s], owner, w, alpha, electrons, lit, k))
            for n, s in ((n_lo, PILOT_SPP[0]), (n_hi, PILOT_SPP[-1]))
        }
        need, gain = [], 1.0
        for i, target in enumerate((noise_budget, p95_target)):
            lo, hi_q = q[n_lo][i], q[n_hi][i]
            expo = float(np.clip(np.log(max(lo, 1e-300) / max(hi_q, 1e-300)) / np.log(n_hi / n_lo), *EXPONENT_RANGE))
            if i == 0 and shared:
                gain = shared_pattern_gain(w[:, k].sum(axis=1), expo)
                hi_q = hi_q * gain
            need.append(n_hi * (hi_q / target) ** (1.0 / expo) if hi_q > 0 else 0.0)
        per_read.append(
            {
                **({"shared_pattern_median_factor": round(gain, 4)} if shared else {}),
                "median_at": {n_lo: round(q[n_lo][0], 4), n_hi: round(q[n_hi][0], 4)},
                "p95_at": {n_lo: round(q[n_lo][1], 4), n_hi: round(q[n_hi][1], 4)},
                "spp_for_median": round(need[0], 1),
                "spp_for_p95": round(need[1], 1),
            }
        )
        scale = max(scale, *need)
    # no stratum below the pilot's smaller count: there the ratio was measured, below it only extrapolated
    # (multijitter converges faster than spp^-2 on smooth scenes, so the clipped exponent under-predicts the
    # noise of fewer samples: flutter_shutter 640x512 was given 2 + 2 spp and measured 0.175 > 0.1)
    n = np.maximum(scale * alpha, float(n_lo)) if scale > 0 else scale * alpha
    count = sample_counter(renderer, plan)  # what the renders take
    half = np.array([_ladder(x / 2, count) for x in n])
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
    model["compile_s"] = round(
        max(sum(seconds[s][0] - (model["c0_s"] + model["c1_s_per_spp"] * s) for s in PILOT_SPP), 0.0), 3
    )
    if film_share < 1.0:  # a pass renders the film: its samples and its accumulation in proportion to the pixels
        model["c1_s_per_spp"] = round(model["c1_s_per_spp"] / film_share, 6)
        model["accumulate_s"] = round(model["accumulate_s"] / film_share, 5)
    pilot = {
        "times": len(idx),
        "renders": 2 * len(PILOT_SPP) * len(idx),
        "spp": list(PILOT_SPP),
        "blocks": None if centres is None else int(centres.size),
        "film_share": round(film_share, 4),
        "seconds": round(time.perf_counter() - t_start, 3),
        "reads_lit": [names[i] for i in range(K) if lit[i].any()],
        "per_read": dict(zip(names, per_read)),
        "targets": {"median": noise_budget, "p95": p95_target},
        "uncapped_spp_max": float(n.max()),
    }
    return replace(plan, spp=spp, spp_source="noise_budget", pilot=pilot, cost=model, notes=notes)


#: With adaptive sampling (``render.adaptive``), the first pass brings every read's 95th percentile to this share
#: of the tail target (``render.noise_budget_tail``) where ``render.noise_budget_p95`` asks for less: adaptive
#: sampling is cheap where the pixels it refines are few, and a first pass whose 95th percentile sits at the tail
#: target leaves some per cent of the samples over it, more than half of the film with their neighbours and the
#: scout's noise. Measured on the default capture at 640x512 (docs/noise.md, "The lamp's spots"): first passes of
#: 7 x 74 (the p95 at 1), 121 and 166 spp refined 56 %, 19 % and 4 % of the film, for 169, 164 and 189 samples a
#: pixel and stratum in all (first pass, scout and second pass, whose samples cost about 1.1x); 0.5 asks for about 121.
ADAPTIVE_FIRST_P95 = 0.5


def first_pass_p95_target(render_cfg) -> float:
    """The 95th percentile the pilot's first pass is chosen for: ``render.noise_budget_p95``, or with adaptive
    sampling at most :data:`ADAPTIVE_FIRST_P95` x ``render.noise_budget_tail``."""
    if render_cfg.adaptive:
        return min(render_cfg.noise_budget_p95, ADAPTIVE_FIRST_P95 * render_cfg.noise_budget_tail)
    return render_cfg.noise_budget_p95


def resolve_spp(plan: Plan, renderer, cfg, seed: np.random.SeedSequence) -> Plan:
    """The plan ready to render: with ``render.spp`` null, run :func:`choose_spp` for this
    capture's sensor (its 95th percentile at :func:`first_pass_p95_target`); otherwise return ``plan``
    unchanged. ``seed``: the run's render seed (the pilot uses an independent child of it)."""
    if plan.spp is not None:
        return plan
    pilot_seed = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x9117))
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    return choose_spp(
        plan,
        renderer,
        k_e,
        cfg.sensor.full_well_e,
        cfg.render.noise_budget,
        cfg.render.max_spp,
        pilot_seed,
        noise_budget_p95=first_pass_p95_target(cfg.render),
        fd_full_well_e=cfg.sensor.fd_full_well_e,
    )


# ----------------------------------------------------------------------------- the run's own estimate


#: The tail's quantile (render.noise_budget_tail): the 99.9th percentile, one sample in a thousand.
TAIL_QUANTILE = 99.9


def read_squared_difference(
    mc_diff_exposure: np.ndarray,
    buckets_e: "np.ndarray | BucketElectrons",
    buckets,
    full_well_e: float,
    fd_full_well_e: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One read's ``(squared, signal, use)``, each (H, W, C): the square of its buckets' summed half-sample
    differences (exposure units, not pooled), its expected electrons, and the samples that count: lit,
    every bucket below the full well, the sum below the floating diffusion's (``fd_full_well_e``; None:
    no limit)."""
    # bucket by bucket, in the read's order: the same sums as .sum(axis=0) over a copy of the read's
    # buckets, without the copy (a large film's noise report then holds a read, not its buckets)
    idx = [int(b) for b in buckets]
    diff = np.array(mc_diff_exposure[idx[0]], dtype=np.float64)
    e = buckets_e[idx[0]]
    signal, below = np.array(e, dtype=np.float64), e < full_well_e
    for b in idx[1:]:
        diff += mc_diff_exposure[b]
        e = buckets_e[b]
        signal += e
        below &= e < full_well_e
    fd_full = float("inf") if fd_full_well_e is None else fd_full_well_e
    np.square(diff, out=diff)
    return diff, signal, (signal > 1.0) & below & (signal < fd_full)


def read_noise_ratio(
    mc_diff_exposure: np.ndarray,
    buckets_e: "np.ndarray | BucketElectrons",
    k_e: np.ndarray,
    buckets,
    full_well_e: float,
    fd_full_well_e: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One read's ``(var_e, signal, use)``, each (H, W, C): its Monte Carlo variance in electrons^2 (the
    square of its buckets' summed half-sample differences, pooled over the alike of 3x3 pixels,
    :func:`pooled_alike`), its expected
    electrons, and the samples that count (:func:`read_squared_difference`)."""
    squared, signal, use = read_squared_difference(mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e)
    var_e = pooled_alike(squared, signal)
    del squared
    var_e *= k_e**2
    return var_e, signal, use


class BucketElectrons:
    """The expected electrons of each bucket, ``exposure[b] x k_e``, made when bucket ``b`` is asked
    for (``[b]``; ``shape`` as the exposures'): what the noise report reads, bucket by bucket, without
    holding every bucket's electrons beside the exposures."""

    def __init__(self, exposure: np.ndarray, k_e: np.ndarray):
        self.exposure, self.k_e = exposure, k_e

    @property
    def shape(self) -> tuple[int, ...]:
        return self.exposure.shape

    def __getitem__(self, b: int) -> np.ndarray:
        return self.exposure[b] * self.k_e


def render_error(
    mc_diff_exposure: np.ndarray | None,
    buckets_e: "np.ndarray | BucketElectrons",
    k_e: np.ndarray,
    reads: list[tuple[int, ...]],
    read_names: list[str],
    full_well_e: float,
    fd_full_well_e: float | None = None,
    *,
    plan: Plan | None = None,
    noise_budget: float = 0.1,
    noise_budget_p95: float = 1.0,
    noise_budget_tail: float = 1.0,
) -> dict:
    """The run's own estimate of its Monte Carlo rendering error on every read the sensor outputs,
    from two half-sample renders, and whether it is within the noise budget.

    A read sums buckets whose Monte Carlo errors come from the same renders: they add coherently
    (the read's signed half-sample difference is the sum of its buckets'), while their shot noise
    adds in variance; so the ratio grows with a read's exposure and the longest read usually decides.
    Per read, over its samples that hold light and whose buckets all stay below the full well (and
    the sum below the floating diffusion's): the ratio of Monte Carlo variance to photon shot-noise
    variance (electrons^2) per sample, from squared half differences pooled over the pixels of
    each 3x3 neighbourhood as bright as its centre (:func:`pooled_alike`; a single squared
    difference is a 1-degree-of-freedom chi-square variable; the median is
    :func:`deconvolved_median`'s, with the pooled estimates' :func:`effective_dof`, reported as
    ``estimate_dof``), its median, 95th and 99.9th percentiles (the tail: render.noise_budget_tail;
    pooled estimates are conservative there, as their own chi-square spread with 9 degrees of freedom
    alone puts the 99.9th percentile of a uniform ratio at 3.1 x its value) and the share of samples
    above 10. Each quantile comes with its :data:`INTERVAL_COVERAGE` interval
    (:func:`quantiles_with_intervals`; ``*_interval``). ``reads``: each read's figures; ``deciding_read``: the read furthest over (or
    closest to) its targets, whose figures are repeated at the top level. ``budget``: the targets,
    whether each is met on every read, and if the median or p95 is not, the samples per pixel that
    would meet them (scaled as 1/spp, which randomized quasi-Monte Carlo beats: an upper bound).
    """
    if mc_diff_exposure is None:
        return {"note": "render.spp = 1: no half-sample error estimate"}

    per_read, factors = {}, {}
    for name, buckets in zip(read_names, reads):
        squared, signal, use = read_squared_difference(
            mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e
        )
        if not use.any():
            continue
        dof = effective_dof(squared, use)  # measured before pooling
        var_e = pooled_alike(squared, signal)
        del squared
        var_e *= k_e**2
        samples = int(use.sum())
        channels = use.shape[-1]
        design = float(POOL_PX**2 * channels)  # a pooled estimate shares its renders with 3x3 x C
        var_e, signal = var_e[use], signal[use]  # the samples that count, the read's whole arrays let go
        ratio = var_e / signal
        (median, *median_iv), (p95, *p95_iv), (tail, *tail_iv) = quantiles_with_intervals(
            ratio, [50.0, 95.0, TAIL_QUANTILE], design
        )
        # the median of the true ratios behind the noisy estimates (deconvolved_median); its interval is
        # the estimates' median's, moved by the same factor
        true_median = deconvolved_median(ratio, dof)
        factor = median / true_median if median > 0 and true_median > 0 else chi2_median_factor(dof)
        median, median_iv = median / factor, [m / factor for m in median_iv]
        # the deconvolution's own scatter (DECONV_REL_SD), which the order statistics do not hold
        half = interval_z() * DECONV_REL_SD / np.sqrt(effective_count(ratio.size, design))
        median_iv = [min(median_iv[0], median * (1.0 - half)), max(median_iv[1], median * (1.0 + half))]
        per_read[name] = {
            "samples": samples,
            "rel_rms": float(np.sqrt(var_e.mean()) / signal.mean()),
            "to_shot_noise_variance_mean": float(var_e.mean() / signal.mean()),
            "to_shot_noise_variance_median": median,
            "to_shot_noise_variance_p95": p95,
            "to_shot_noise_variance_p999": tail,
            "to_shot_noise_variance_median_interval": median_iv,
            "to_shot_noise_variance_p95_interval": p95_iv,
            "to_shot_noise_variance_p999_interval": tail_iv,
            "share_above_10": float((ratio > 10.0).mean()),
            "estimate_dof": round(dof, 3),
        }
        factors[name] = (max(median / noise_budget, p95 / noise_budget_p95), tail / noise_budget_tail)
    if not per_read:
        return {"note": "no unsaturated lit samples"}
    deciding = max(per_read, key=lambda n: max(factors[n]))
    body = max(f[0] for f in factors.values())  # the median and p95 targets, on every read
    tail_met = all(f[1] <= 1.0 for f in factors.values())
    budget = {
        "median_target": noise_budget,
        "p95_target": noise_budget_p95,
        "tail_target": noise_budget_tail,
        "met": bool(body <= 1.0),
        "tail_met": tail_met,
    }
    if plan is not None:
        budget["spp_source"] = plan.spp_source
    if plan is not None and plan.spp is not None and body > 1.0:
        budget["spp_that_would_meet"] = int(2 * np.ceil(float(plan.spp.max()) * body / 2))
    return {
        "method": "two independent half-sample renders per stratum, summed over each read's buckets; squared "
        "differences pooled over 3x3 pixels",
        "interval": f"{INTERVAL_COVERAGE:.0%} interval of each quantile over the estimates it is taken from "
        "(order statistics, effective count with pooled neighbours and channels sharing renders)",
        **per_read[deciding],
        "deciding_read": deciding,
        "reads": per_read,
        "budget": budget,
    }


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
    least 2 on :func:`_ladder` (``count``: what the sampler takes, ``Renderer.sample_count``)."""
    return np.array([2 * max(2, _ladder(int(n) / SCOUT_DIVISOR / 2, count)) for n in np.asarray(spp)], np.int64)


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
    parts cross, :func:`mbcapture.pipeline.refine_tail`).

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
    :func:`mbcapture.pipeline.with_planned_refinement` assumes). A factor only lowers a sample's ratio, so only the
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


def noise_verdict(render_error: dict, *, adaptive_hint: bool = False) -> str:
    """One sentence: does the rendering's Monte Carlo noise matter next to the photon shot noise?
    Judged on the budget (``render_error.budget``: the median and 95th percentile of the per-sample
    Monte Carlo / shot-noise variance ratio of the deciding read against render.noise_budget and
    render.noise_budget_p95), with the tail (99.9th percentile) against render.noise_budget_tail.
    ``adaptive_hint``: a run that could have sampled adaptively and did not; a tail over its target
    then points to render.adaptive."""
    med, p95 = render_error.get("to_shot_noise_variance_median"), render_error.get("to_shot_noise_variance_p95")
    budget = render_error.get("budget")
    if med is None or budget is None:
        return f"Not estimated: {render_error.get('note', 'no half-sample estimate')}."
    extra = 100 * (np.sqrt(1 + med) - 1)  # added to the median sample's noise standard deviation
    where = f" of read {render_error['deciding_read']}" if "deciding_read" in render_error else ""
    level = (
        f"rendering noise variance is {med:.3g} x the shot-noise variance in the median sample{where} and "
        f"{p95:.3g} x in the 95th percentile (budget {budget['median_target']:g} / {budget['p95_target']:g})"
    )
    tail = render_error.get("to_shot_noise_variance_p999")
    tail_iv = render_error.get("to_shot_noise_variance_p999_interval")
    within = "" if tail_iv is None else f", {INTERVAL_COVERAGE:.0%} interval {tail_iv[0]:.3g}-{tail_iv[1]:.3g}"
    tail_text = ""
    if tail is not None and "tail_target" in budget:
        target = f"render.noise_budget_tail {budget['tail_target']:g}"
        # over by the estimate with an interval reaching below the target: the run cannot tell (after adaptive
        # sampling the unrefined film's tail rests on a few audit blocks; docs/noise.md)
        if budget.get("tail_met"):
            judged = f"within {target}"
        elif tail_iv is None or tail_iv[0] > budget["tail_target"]:
            judged = f"over {target}"
        else:
            judged = f"over {target} by this estimate, but its interval reaches below it: the run cannot tell"
        tail_text = f" Tail: {tail:.3g} x in the 99.9th percentile{within} ({judged})."
    if tail_text and adaptive_hint and not budget.get("tail_met"):
        tail_text += " render.adaptive: true renders the pixels over it again (docs/noise.md)."
    if budget["met"]:
        return f"Sensor noise dominates: {level}, adding {extra:.1f} % to the median sample's noise.{tail_text}"
    head = (
        f"Rendering noise is visible in the simulated images: {level}, adding {extra:.0f} % to the median "
        "sample's noise; "
    )
    spp = f"render.spp >= {budget['spp_that_would_meet']}" if "spp_that_would_meet" in budget else None
    if budget.get("spp_source") == "noise_budget":  # the pilot's estimate missed: more samples, not the budget again
        return (
            head
            + (
                f"the noise budget's pilot under-estimated it; {spp} would meet it."
                if spp
                else "the noise budget's pilot under-estimated it."
            )
            + tail_text
        )
    return head + (f"{spp} or " if spp else "") + "render.spp: null (the noise budget) would meet it." + tail_text
