"""The run's own estimate of its rendering error, read by read (:func:`render_error`): each read's
Monte Carlo variance against the shot noise the sensor adds there, from the two half-sample renders of
every stratum. Judged against the same targets as the pilot's. It pools each sample's squared
difference over the neighbours as bright as it (:func:`~mbcapture.budget.quantiles.pooled_alike`), not
over all of them: across a silhouette the dark side would otherwise take its edge's coverage noise,
which put the tail several times too high. The pilot, which judges the median and the p95 only,
pools over all of them, electrons and variance alike."""

from __future__ import annotations


import numpy as np

from ..exposure.plan import Plan
from .quantiles import (
    DECONV_REL_SD,
    INTERVAL_COVERAGE,
    POOL_PX,
    chi2_median_factor,
    deconvolved_median,
    effective_count,
    effective_dof,
    interval_z,
    pooled_alike,
    quantiles_with_intervals,
)


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
        f = read_figures(mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e, k_e)
        if f is None:
            continue
        per_read[name] = f
        median, p95, tail = (f[f"to_shot_noise_variance_{q}"] for q in ("median", "p95", "p999"))
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


def read_figures(mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e, k_e: np.ndarray) -> dict | None:
    """The figures of the read summing ``buckets`` (:func:`render_error`'s ``reads``), from its squared half-sample
    differences (:func:`read_squared_difference`, made here so that each array goes as soon as it is done with);
    None where no sample counts."""
    squared, signal, use = read_squared_difference(mc_diff_exposure, buckets_e, buckets, full_well_e, fd_full_well_e)
    if not use.any():
        return None
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
    return {
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
