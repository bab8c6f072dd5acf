"""Samples per pixel from a pilot (``render.spp`` null): the pilot, its cost model, :func:`choose_spp`.

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
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from typing import Any

import numpy as np

from ..exposure.integrate import accumulate, sample_counter
from ..exposure.plan import Plan
from ..sensor import electrons_per_render_second
from .quantiles import POOL_PX, budget_quantiles, effective_dof, pooled


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


#: The pilot's two sample counts: at each, two independent renders (their mean is the main
#: render's two-halves estimator at twice the count, their difference its error).
PILOT_SPP = (4, 16)
#: Range of the fitted convergence exponent: Monte Carlo variance ~ spp^-exponent (1 for
#: independent samples, up to 2 for randomized quasi-Monte Carlo on smooth integrands).
EXPONENT_RANGE = (1.0, 2.0)


#: Steps per octave of the ladder of sample counts (:func:`ladder`): 2.2 % apart, so a stratum gets little
#: more than the pilot asked for (19 % or 9 % steps cost that much more), while the strata of a capture share
#: few counts. Distinct counts cost a kernel each where the sampler's count is a literal of it (multijitter:
#: about 0.25 s each at 640x512); the renders that draw from the shared pattern take their count opaque
#: and compile once for all counts.
LADDER_STEPS = 32


def ladder(x: float, count: Callable[[int], int] | None = None) -> int:
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


@dataclass
class PilotRenders:
    """The pilot's renders: at each pilot stratum ``idx`` (of the plan's), two independent renders at each count of
    :data:`PILOT_SPP`; ``diffs[spp]`` their differences in electrons per second, ``means`` every pilot sample of a
    stratum, ``seconds[spp]`` each render's time; ``only`` where the ratios count (the blocks' centres, or
    everywhere), ``film_share`` the share of the film rendered, ``centres`` the blocks' or None."""

    idx: np.ndarray
    diffs: dict[int, list[np.ndarray]]
    means: list[np.ndarray]
    seconds: dict[int, list[float]]
    only: Any
    film_share: float
    centres: np.ndarray | None


def render_pilot(plan: Plan, renderer, k_e: np.ndarray, rng: np.random.Generator) -> PilotRenders:
    """The pilot's renders (:class:`PilotRenders`): a large film's on a random sample of its 3x3 blocks."""
    idx = _pilot_indices(plan)
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
    return PilotRenders(idx, diffs, means, seconds, only, film_share, centres)


def neyman_shape(
    w: np.ndarray, hi: list[np.ndarray], owner: np.ndarray, lit: np.ndarray, electrons: np.ndarray
) -> np.ndarray:
    """(J,) each stratum's share of the samples, the largest 1: the Neyman shape, sqrt of each stratum's summed
    variance (``hi``: the pilot's differences at its larger count, nearest pilot ``owner``), max over reads."""
    J, K, _ = w.shape
    a_jk = np.zeros((J, K))
    for k in range(K):
        if lit[k].any():
            for p in range(len(hi)):
                d = hi[p][:, lit[k]]
                sel = owner == p
                a_jk[sel, k] = np.einsum("jg,gh,jh->j", w[sel, k], d @ d.T, w[sel, k])
    root = np.sqrt(np.maximum(a_jk, 0.0))
    # read k alone would take n_jk = sqrt(a_jk) sum_j sqrt(a_jk) / (f E_k), E_k its lit electrons: the
    # 1 / E_k keeps the reads' counts comparable, so that the max over k is the count every read needs
    e_k = np.array([electrons[k][lit[k]].sum() for k in range(K)])
    with np.errstate(divide="ignore", invalid="ignore"):
        shape = np.nan_to_num(root * root.sum(axis=0)[None, :] / np.maximum(e_k, 1e-300)[None, :]).max(axis=1)
    return np.maximum(shape / shape.max(), 1e-3) if shape.max() > 0 else np.ones(J)


def read_needs(
    pilot: PilotRenders, owner, w, alpha, electrons, lit, targets: tuple[float, float], shared: bool
) -> tuple[float, list[dict | None]]:
    """Per read: the median and p95 of the pooled ratios at both pilot counts (strata at alpha_j x the count), the
    exponent between them and the count each of ``targets`` (median, p95) needs; returns the largest count and what
    the report keeps of each read (None: a read with no lit sample)."""
    scale, per_read = 0.0, []
    n_lo, n_hi = 2 * PILOT_SPP[0], 2 * PILOT_SPP[-1]  # two halves: the main render's total count
    for k in range(w.shape[1]):
        if not lit[k].any():
            per_read.append(None)
            continue
        q = {
            n: budget_quantiles(*_pilot_ratios(pilot.diffs[s], owner, w, alpha, electrons, lit, k))
            for n, s in ((n_lo, PILOT_SPP[0]), (n_hi, PILOT_SPP[-1]))
        }
        need, gain = [], 1.0
        for i, target in enumerate(targets):
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
    return scale, per_read


def pilot_cost(pilot: PilotRenders, accumulate_s: float) -> dict:
    """The cost model from the pilot's render times (:func:`_cost_model`), its kernels' compile time, and scaled to
    the whole film from a pilot on blocks."""
    seconds = pilot.seconds
    # the first render at each count compiled its kernel (Dr.Jit compiles one per sample count):
    # the cost model takes medians, and the compile time is what the first renders took beyond it
    pairs = list(zip(seconds[PILOT_SPP[0]], seconds[PILOT_SPP[-1]]))
    model = _cost_model(pairs, 0.0, accumulate_s, spp_pair=PILOT_SPP)
    model["compile_s"] = round(
        max(sum(seconds[s][0] - (model["c0_s"] + model["c1_s_per_spp"] * s) for s in PILOT_SPP), 0.0), 3
    )
    if pilot.film_share < 1.0:  # a pass renders the film: its samples and its accumulation in proportion to the pixels
        model["c1_s_per_spp"] = round(model["c1_s_per_spp"] / pilot.film_share, 6)
        model["accumulate_s"] = round(model["accumulate_s"] / pilot.film_share, 5)
    return model


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
    pilot = render_pilot(plan, renderer, k_e, np.random.default_rng(seed))
    idx = pilot.idx
    # the budget is met on the reads the sensor outputs: a read's weights (and electrons) are its buckets'
    # sums, and its Monte Carlo errors add coherently (the same renders); one read per bucket without sets
    read_sets = plan.read_sets or tuple((b,) for b in plan.buckets_read)
    w_b = plan.weights_s  # (J, K, G)
    w = np.stack([w_b[:, list(r)].sum(axis=1) for r in read_sets], axis=1)  # (J, R, G)
    K = w.shape[1]  # reads from here on
    names = list(plan.read_names) if plan.read_sets else [f"B{b + 1}" for b in plan.buckets_read]
    owner = np.abs(plan.times_s[:, None] - plan.times_s[idx][None, :]).argmin(axis=1)  # nearest pilot
    acc = _timed_accumulate(w_b[idx[0]], pilot.means[0], w_b.shape[1])
    wp = np.stack([w_b[owner == p].sum(axis=0) for p in range(len(idx))])  # (P, K buckets, G)
    # the ratios' denominator, pooled like their numerator so that its own noise does not scatter them
    bucket_e = pooled(np.einsum("pkg,pghwc->khwc", wp, np.stack(pilot.means), optimize=True) * k_e)
    electrons = np.stack([bucket_e[list(r)].sum(axis=0) for r in read_sets])  # (R, H, W, C)
    # a read's sample counts where it holds light and none of its buckets (nor their sum) is full
    lit = (
        np.stack([(bucket_e[list(r)] < full_well_e).all(axis=0) for r in read_sets])
        & (electrons > 1.0)
        & (electrons < fd_full)
        & pilot.only
    )
    alpha = neyman_shape(w, pilot.diffs[PILOT_SPP[-1]], owner, lit, electrons)
    scale, per_read = read_needs(
        pilot, owner, w, alpha, electrons, lit, (noise_budget, p95_target), plan.shares_pattern
    )
    # no stratum below the pilot's smaller count: there the ratio was measured, below it only extrapolated
    # (multijitter converges faster than spp^-2 on smooth scenes, so the clipped exponent under-predicts the
    # noise of fewer samples: flutter_shutter 640x512 was given 2 + 2 spp and measured 0.175 > 0.1)
    n = np.maximum(scale * alpha, float(2 * PILOT_SPP[0])) if scale > 0 else scale * alpha
    count = sample_counter(renderer, plan)  # what the renders take
    half = np.array([ladder(x / 2, count) for x in n])
    cap = max(max_spp // 2, 1)
    spp = (2 * np.minimum(half, cap)).astype(np.int64)
    capped = int((n > 2 * cap).sum())
    notes = list(plan.notes)
    if capped:
        notes.append(f"render.max_spp={max_spp} capped {capped} strata: the noise budget is not met there")
    record = {
        "times": len(idx),
        "renders": 2 * len(PILOT_SPP) * len(idx),
        "spp": list(PILOT_SPP),
        "blocks": None if pilot.centres is None else int(pilot.centres.size),
        "film_share": round(pilot.film_share, 4),
        "seconds": round(time.perf_counter() - t_start, 3),
        "reads_lit": [names[i] for i in range(K) if lit[i].any()],
        "per_read": dict(zip(names, per_read)),
        "targets": {"median": noise_budget, "p95": p95_target},
        "uncapped_spp_max": float(n.max()),
    }
    return replace(plan, spp=spp, spp_source="noise_budget", pilot=record, cost=pilot_cost(pilot, acc), notes=notes)


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
