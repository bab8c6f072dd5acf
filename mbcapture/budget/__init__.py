"""The noise budget on every read: samples per pixel from a pilot so that rendering adds little noise next to
the photons' (the median of Monte Carlo over shot-noise variance at most ``render.noise_budget``, its 95th
percentile at most ``render.noise_budget_p95``), adaptive sampling for the tail (``render.noise_budget_tail``),
and the run's own estimate of its error with its verdict (docs/noise.md).

Where each part lives: the pilot and the samples it buys, with the rule (:mod:`.pilot`); the pooled estimates and
their quantiles (:mod:`.quantiles`); the run's own estimate (:mod:`.error`); adaptive sampling's choice of pixels
(:mod:`.tiers`) and the passes after the first (:mod:`.adaptive`); the verdict (:mod:`.verdict`). This module
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
