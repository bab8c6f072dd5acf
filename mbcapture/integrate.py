"""Render the plan's strata and integrate them into bucket exposures.

    B_k = sum_j sum_g weights_s[j, k, g] * L_g(t_j)      (W m^-2 sr^-1 s, float64)

Each stratum is rendered as two independent half-sample passes accumulated apart, so a run
measures its own Monte Carlo error: Var[combined] ~ (A - B)^2 n_a n_b / n^2. Applications that
need the exposure of each emitter group separately (flash-only ground truths, per-LED colour
channels) ask for ``per_group``: the same renders, accumulated without summing over groups.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from .plan import Plan


@dataclass
class Integrated:
    """exposure (K, H, W, C); mc_var (K, H, W, C) or None (spp = 1); group_exposure (K, G, H, W, C) or None."""

    exposure: np.ndarray
    mc_var: np.ndarray | None
    group_exposure: np.ndarray | None = None


def accumulate(weights_s: np.ndarray, radiance: np.ndarray, out: np.ndarray) -> None:
    """out[k] += sum_g weights_s[k, g] * radiance[g]  (float64; radiance (G, H, W, C))."""
    out += np.einsum("kg,ghwc->khwc", weights_s, radiance.astype(np.float64, copy=False), optimize=True)


def accumulate_groups(weights_s: np.ndarray, radiance: np.ndarray, out: np.ndarray) -> None:
    """out[k, g] += weights_s[k, g] * radiance[g]  (out (K, G, H, W, C) float64)."""
    out += weights_s[:, :, None, None, None] * radiance.astype(np.float64, copy=False)[None]


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="pass", disable=not enabled, leave=False, dynamic_ncols=True)


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
) -> Integrated:
    """Render every stratum of ``plan`` with ``renderer`` and accumulate the bucket exposures."""
    stage = timer if timer is not None else (lambda name: nullcontext())
    H, W, C = renderer.height, renderer.width, len(renderer.channels)
    halves = (plan.spp // 2, plan.spp - plan.spp // 2) if plan.spp >= 2 else (plan.spp,)
    parts = [np.zeros((n_buckets, H, W, C), dtype=np.float64) for _ in halves]
    groups_out = np.zeros((n_buckets, len(plan.groups), H, W, C), dtype=np.float64) if per_group else None
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=(plan.passes, len(halves)))
    with _progress(plan.passes, progress, desc) as bar:
        for j in range(plan.passes):
            for h, spp_h in enumerate(halves):
                with stage("render"):
                    radiance = renderer.render(float(plan.times_s[j]), spp_h, int(seeds[j, h]), plan.groups)
                with stage("accumulate"):
                    accumulate(plan.weights_s[j], radiance, parts[h])
                    if groups_out is not None:
                        accumulate_groups(plan.weights_s[j] * (spp_h / plan.spp), radiance, groups_out)
            bar.update(1)
    exposure = sum(n * p for n, p in zip(halves, parts)) / plan.spp
    mc_var = (parts[0] - parts[1]) ** 2 * (halves[0] * halves[1] / plan.spp**2) if len(halves) == 2 else None
    return Integrated(exposure=exposure, mc_var=mc_var, group_exposure=groups_out)
