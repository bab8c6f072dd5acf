"""The noise budget: samples per pixel from a pilot, the render-error estimate and its verdict.

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

The run's own estimate of its rendering error (:func:`render_error`, from the two half-sample
renders of every stratum) and its one-line verdict (:func:`noise_verdict`) are judged against the
same targets.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .integrate import accumulate
from .plan import Plan
from .sensor import electrons_per_render_second

#: Strata at which the pilot renders (spread evenly over the capture).
PILOT_TIMES = 3


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
    pilot_seed = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0x9117))
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    return choose_spp(plan, renderer, k_e, cfg.sensor.full_well_e, cfg.render.noise_budget, cfg.render.max_spp, pilot_seed,
                      noise_budget_p95=cfg.render.noise_budget_p95)


# ----------------------------------------------------------------------------- the run's own estimate


def render_error(
    mc_var_exposure: np.ndarray | None, buckets_e: np.ndarray, k_e: np.ndarray, buckets: list[int], full_well_e: float,
    *, plan: Plan | None = None, noise_budget: float = 0.1, noise_budget_p95: float = 1.0,
) -> dict:
    """The run's own estimate of its Monte Carlo rendering error, from two half-sample renders,
    and whether it is within the noise budget.

    Over the bucket samples that hold light but stay below the full well (saturated samples
    carry no image information, and partly covered lamp pixels would dominate every mean):
    ``rel_rms``: RMS Monte Carlo error over the mean signal; ``to_shot_noise_variance_*``: the
    ratio of Monte Carlo variance to photon shot-noise variance (electrons^2) per sample, its
    median and 95th percentile computed from squared half differences pooled over 3x3 pixels
    (a single squared difference is a 1-degree-of-freedom chi-square variable whose median is 0.45
    of its mean; see :func:`budget_quantiles`). Below ~0.1 the sensor's own noise
    dominates and more samples are wasted; above 1 rendering noise is visible in the images.
    ``budget``: the targets (render.noise_budget for the median, render.noise_budget_p95 for the
    95th percentile), whether they are met, and if not, the samples per pixel that would meet them
    (scaled from this run's as 1/spp, which randomized quasi-Monte Carlo beats: an upper bound).
    """
    if mc_var_exposure is None:
        return {"note": "render.spp = 1: no half-sample error estimate"}
    var_e = pooled(mc_var_exposure[buckets]) * k_e**2
    signal = buckets_e[buckets]
    use = (signal > 1.0) & (signal < full_well_e)
    if not use.any():
        return {"note": "no unsaturated lit samples"}
    ratio = var_e[use] / signal[use]
    median, p95 = budget_quantiles(ratio)
    factor = max(median / noise_budget, p95 / noise_budget_p95)
    budget = {"median_target": noise_budget, "p95_target": noise_budget_p95, "met": bool(factor <= 1.0)}
    if plan is not None:
        budget["spp_source"] = plan.spp_source
    if plan is not None and plan.spp is not None and factor > 1.0:
        budget["spp_that_would_meet"] = int(2 * np.ceil(float(plan.spp.max()) * factor / 2))
    return {
        "method": "two independent half-sample renders per stratum; squared differences pooled over 3x3 pixels",
        "rel_rms": float(np.sqrt(var_e[use].mean()) / signal[use].mean()),
        "to_shot_noise_variance_mean": float(var_e[use].sum() / signal[use].sum()),
        "to_shot_noise_variance_median": median,
        "to_shot_noise_variance_p95": p95,
        "budget": budget,
    }


def noise_verdict(render_error: dict) -> str:
    """One sentence: does the rendering's Monte Carlo noise matter next to the photon shot noise?
    Judged on the budget (``render_error.budget``: the median and 95th percentile of the per-sample
    Monte Carlo / shot-noise variance ratio against render.noise_budget and render.noise_budget_p95)."""
    med, p95 = render_error.get("to_shot_noise_variance_median"), render_error.get("to_shot_noise_variance_p95")
    budget = render_error.get("budget")
    if med is None or budget is None:
        return f"Not estimated: {render_error.get('note', 'no half-sample estimate')}."
    extra = 100 * (np.sqrt(1 + med) - 1)  # added to the median sample's noise standard deviation
    level = (f"rendering noise variance is {med:.3g} x the shot-noise variance in the median sample and {p95:.3g} x "
             f"in the 95th percentile (budget {budget['median_target']:g} / {budget['p95_target']:g})")
    if budget["met"]:
        return f"Sensor noise dominates: {level}, adding {extra:.1f} % to the median sample's noise."
    head = (f"Rendering noise is visible in the simulated images: {level}, adding {extra:.0f} % to the median "
            "sample's noise; ")
    spp = f"render.spp >= {budget['spp_that_would_meet']}" if "spp_that_would_meet" in budget else None
    if budget.get("spp_source") == "noise_budget":  # the pilot's estimate missed: more samples, not the budget again
        return head + (f"the noise budget's pilot under-estimated it; {spp} would meet it." if spp else
                       "the noise budget's pilot under-estimated it.")
    return head + (f"{spp} or " if spp else "") + "render.spp: null (the noise budget) would meet it."
