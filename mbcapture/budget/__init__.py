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

Where each part lives: the pilot and the samples it buys (:mod:`.pilot`); the pooled estimates and their
quantiles (:mod:`.quantiles`); the run's own estimate (:mod:`.error`); adaptive sampling's choice of
pixels (:mod:`.tiers`) and its passes (:mod:`.adaptive`); the verdict (:mod:`.verdict`). This module
gathers their public names.
"""

from .quantiles import (
    chi2_median_factor,
    effective_count,
    ALIKE_BAND_ROWS,
    DECONV_REL_SD,
    budget_quantiles,
    deconvolved_median,
    effective_dof,
    pooled,
    pooled_alike,
    quantiles_with_intervals,
)
from .pilot import (
    ADAPTIVE_FIRST_P95,
    LADDER_STEPS,
    PILOT_BLOCKS,
    PILOT_SPP,
    block_mosaic,
    block_pixels,
    choose_spp,
    first_pass_p95_target,
    ladder,
    mosaic_centres,
    pilot_blocks,
    probe_cost,
    resolve_spp,
    shared_pattern_gain,
)
from .error import BucketElectrons, render_error
from .tiers import (
    ADAPTIVE_FOOTPRINT,
    ADAPTIVE_LEVELS,
    ADAPTIVE_SELECT,
    TailModel,
    factor_tiers,
    scout_ratio,
    scout_spp,
    tail_pixels,
    tier_exponents,
    tiers_of,
)
from .verdict import noise_verdict

__all__ = [
    "chi2_median_factor",
    "effective_count",
    "ADAPTIVE_FIRST_P95",
    "ADAPTIVE_FOOTPRINT",
    "ADAPTIVE_LEVELS",
    "ADAPTIVE_SELECT",
    "ALIKE_BAND_ROWS",
    "BucketElectrons",
    "DECONV_REL_SD",
    "LADDER_STEPS",
    "PILOT_BLOCKS",
    "PILOT_SPP",
    "TailModel",
    "block_mosaic",
    "block_pixels",
    "budget_quantiles",
    "choose_spp",
    "deconvolved_median",
    "effective_dof",
    "factor_tiers",
    "first_pass_p95_target",
    "ladder",
    "mosaic_centres",
    "noise_verdict",
    "pilot_blocks",
    "pooled",
    "pooled_alike",
    "probe_cost",
    "quantiles_with_intervals",
    "render_error",
    "resolve_spp",
    "scout_ratio",
    "scout_spp",
    "shared_pattern_gain",
    "tail_pixels",
    "tier_exponents",
    "tiers_of",
]
