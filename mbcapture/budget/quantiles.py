"""The budget's statistics: each sample's variance pooled over its neighbours, the median of the true
ratios behind those noisy estimates, and quantiles with their confidence intervals."""

from __future__ import annotations


import numpy as np


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
