"""Adaptive sampling (render.adaptive): pixels rendered alone (Renderer.render_pixels) are the full
render's estimator; the pixels are chosen from a scout of their own, so the first pass is unbiased
everywhere, and the refined capture's exposure at the chosen pixels (first and second pass combined)
matches a brute-force high-spp render within its standard error."""

from dataclasses import replace
from pathlib import Path

import re

import numpy as np
import pytest
from script_modules import load_script

from mbcapture import load_config
from mbcapture.budget import adaptive
from mbcapture.budget.adaptive import Passes
from mbcapture.exposure import integrate as integrate_module
from mbcapture.budget import ADAPTIVE_SELECT, tail_pixels
from mbcapture.config import scene_of
from mbcapture.exposure.integrate import integrate, integrate_tiles, refine
from mbcapture.capture.pipeline import prepare
from mbcapture.render import Renderer
from mbcapture.render.shadows import changing_region
from mbcapture.sensor import electrons_per_render_second

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["render.width=64", "render.height=48", "render.max_motion_px=4", "render.min_strata=1", "render.cache=off"]


@pytest.fixture(scope="module")
def setup():
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*SMALL, "render.spp=64"])
    _, timeline, plan, seeds = prepare(cfg)
    renderer = Renderer.from_config(scene_of(cfg), cfg)
    return cfg, timeline, plan, seeds, renderer


@pytest.mark.render
def test_pixels_rendered_alone_are_the_full_renders_estimator(setup):
    """Over every pixel, a 64-spp render_pixels differs from a 1024-spp full render by its noise only:
    per group, the mean difference is within 5 standard errors (from two seeds' spread)."""
    cfg, _, plan, _, r = setup
    groups = list(plan.groups)
    pix = np.arange(64 * 48)
    ref = r.render(0.003, 1024, 1, groups).reshape(len(groups), -1, 3).astype(np.float64)
    a, b = (r.render_pixels(0.003, 64, s, groups, pix).astype(np.float64) for s in (2, 3))
    for g in range(len(groups)):
        se = np.std(a[g] - b[g]) / np.sqrt(2) / np.sqrt(a[g].size)
        assert abs((a[g] - ref[g]).mean()) < 5 * se + 1e-6, groups[g]


@pytest.mark.render
def test_pixels_rendered_alone_are_the_full_render_whatever_came_before(setup):
    """render_pixels of every pixel in order at (time, spp, seed) is the full render (to float32
    rounding: Dr.Jit's threads add a pixel's samples in no fixed order), on a fresh renderer and after
    renders at other times and sample counts: each pixel's samples are its own quasi-Monte Carlo
    sequence (a clone of the sensor's sampler kept the last render's samples
    per wavefront and stratified over the wrong sequences: the same mean, more noise). A subset of
    pixels is numbered in its own order, so its numbers differ; its estimator is the same (above)."""
    cfg = setup[0]
    groups = ["ambient", "lamp"]
    pix = np.arange(64 * 48)
    fresh = Renderer.from_config(scene_of(cfg), cfg).render_pixels(0.002, 24, 7, groups, pix)
    r = Renderer.from_config(scene_of(cfg), cfg)
    r.render(0.0005, 6, 3, groups)  # another time and sample count first
    after = r.render_pixels(0.002, 24, 7, groups, pix)
    full = r.render(0.002, 24, 7, groups).reshape(len(groups), -1, 3)
    np.testing.assert_allclose(fresh, full, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(after, full, rtol=1e-5, atol=1e-7)


@pytest.mark.render
def test_pixels_rendered_alone_from_a_shared_pattern_are_the_full_renders_pixels(setup):
    """With the shared pattern (key, offset), render_pixels of any pixels, in any order, gives each the
    value a whole-film render from that pattern gives it (to float32 rounding): the same samples, so
    adaptive sampling's passes and its audit are the first pass's estimator. Another key, other values."""
    cfg = setup[0]
    r = Renderer.from_config(scene_of(cfg), cfg)
    groups = ["ambient", "lamp"]
    full = r.render(0.002, 24, 7, groups, pattern=(12345, 48)).reshape(len(groups), -1, 3)
    pix = np.random.default_rng(0).permutation(64 * 48)[:500]
    alone = r.render_pixels(0.002, 24, 7, groups, pix, pattern=(12345, 48))
    np.testing.assert_allclose(alone, full[:, pix], rtol=1e-5, atol=1e-7)
    other = r.render_pixels(0.002, 24, 7, groups, pix, pattern=(12346, 48))
    assert np.abs(other - full[:, pix]).max() > 1e-3 * np.abs(full[:, pix]).max()
    # and a film render right after is the film's again (the listed pixels are not left in the integrator)
    np.testing.assert_allclose(
        r.render(0.002, 24, 7, groups, pattern=(12345, 48)).reshape(full.shape), full, rtol=1e-5, atol=1e-7
    )


@pytest.mark.render
def test_pixels_with_samples_and_offsets_of_their_own_are_the_full_renders_pixels(setup):
    """render_pixels with one count and one pattern offset per pixel (adaptive sampling's tiers in one render)
    gives each pixel the value of a whole-film render at its count and offset: pixel i takes the pattern's
    samples offset[i] .. offset[i] + spp[i] - 1 whatever its neighbours in the list take. Without a pattern
    the counts must be equal (the sampler's sequences are spp consecutive lanes a pixel)."""
    cfg = setup[0]
    r = Renderer.from_config(scene_of(cfg), cfg)
    groups = ["ambient", "lamp"]
    films = {
        (n, o): r.render(0.002, n, 7, groups, pattern=(12345, o)).reshape(len(groups), -1, 3)
        for n, o in ((24, 48), (12, 100), (5, 0))
    }
    rng = np.random.default_rng(1)
    pix = rng.permutation(64 * 48)[:600]
    which = rng.integers(0, 3, pix.size)
    choice = list(films)
    counts = np.array([choice[w][0] for w in which])
    offsets = np.array([choice[w][1] for w in which])
    alone = r.render_pixels(0.002, counts, 7, groups, pix, pattern=(12345, offsets))
    for w, key in enumerate(choice):
        sel = which == w
        np.testing.assert_allclose(alone[:, sel], films[key][:, pix[sel]], rtol=1e-5, atol=1e-7, err_msg=str(key))
    with pytest.raises(ValueError, match="need a pattern"):
        r.render_pixels(0.002, counts, 7, groups, pix)


@pytest.mark.render
@pytest.mark.parametrize("pattern", [True, False])
def test_pixels_through_a_lens_that_mixes_neighbours_are_the_full_renders_estimator(pattern):
    """camera.distortion and camera.diffraction make a sensor pixel read pinhole pixels around it: render_pixels then
    renders the whole pinhole film, the listed pixels' neighbourhoods with their samples in proportion to their
    weight and the rest with one, through the lens. Over 12 renders of 200 listed pixels each, against 12 full
    renders at the same count: the summed difference is within 5 standard errors per group (unbiased; a
    neighbourhood left out would bias the pixels by the weight it has, up to 15 % beside the lamp), and the listed
    pixels' variance is at most 2x the full render's (measured 1.0-1.7x: the allocation gives them about the count
    they ask for), for about 1.4x the listed pixels' samples where they lie apart."""
    cfg = load_config(
        ROOT / "configs" / "camera_full.yaml",
        ["render.width=48", "render.height=36", "render.cache=off", "render.spp=16"],
    )
    r = Renderer.from_config(scene_of(cfg), cfg)
    assert not r.renders_pixels_alone
    groups = list(r.groups)
    pix = np.random.default_rng(0).permutation(48 * 36)[:200]
    reps, n = 12, 24
    alone = np.array(
        [r.render_pixels(0.002, n, 5 + k, groups, pix, pattern=(100 + k, 0) if pattern else None) for k in range(reps)],
        np.float64,
    )
    full = np.array(
        [
            r.render(0.002, n, 70 + k, groups, pattern=(200 + k, 0)).reshape(len(groups), -1, 3)[:, pix]
            for k in range(reps)
        ],
        np.float64,
    )
    for g in range(len(groups)):
        d = alone[:, g].mean(axis=0) - full[:, g].mean(axis=0)
        var_alone, var_full = (x[:, g].var(axis=0, ddof=1) for x in (alone, full))
        assert abs(d.sum()) < 5 * np.sqrt((var_alone + var_full).sum() / reps), groups[g]
        assert var_alone.sum() < 2.0 * var_full.sum(), groups[g]
    asked, _ = r.lens.samples(pix.astype(np.uint32), np.full(pix.size, 1000), np.zeros(pix.size, np.int64))
    assert 1000 * pix.size < asked.sum() < 2.5 * 1000 * pix.size


@pytest.mark.render
def test_spectral_pixels_rendered_alone_are_the_full_render_and_its_estimator(setup):
    """A spectral variant: render_pixels renders one pass a group, each group in its own scene, and weighs each
    sample's wavelengths by the film's curves as Mitsuba's specfilm does (written in the renderer). Every pixel in
    order from the sampler is the full render at the same seed, to float32 rounding (the same camera rays,
    wavelengths and film weights: a wrong curve, density or wavelength order would not be); from a shared
    pattern, whose camera rays and wavelengths are the pattern's (the full render's stay the sampler's), the mean
    over the film is the 512-spp render's within 5 standard errors, per group. An RGB renderer made before still
    renders after them (each renderer makes its variant Mitsuba's current one: mi.render refused the RGB scene)."""
    cfg = load_config(
        ROOT / "configs" / "rgb_illumination.yaml",
        ["render.width=40", "render.height=30", "render.cache=off", "render.spp=16"],
    )
    r = Renderer.from_config(scene_of(cfg), cfg)
    groups = list(r.groups)
    assert r.spectral and r.renders_pixels_alone and len(groups) == 4
    pix = np.arange(40 * 30)
    full = r.render(0.002, 16, 7, groups).reshape(len(groups), -1, 3)
    np.testing.assert_allclose(r.render_pixels(0.002, 16, 7, groups, pix), full, rtol=1e-5, atol=1e-6 * full.max())
    ref = r.render(0.002, 512, 1, groups).reshape(len(groups), -1, 3).astype(np.float64)
    a, b = (r.render_pixels(0.002, 64, 7, groups, pix, pattern=(key, 0)).astype(np.float64) for key in (11, 12))
    for g in range(len(groups)):
        se = np.std(a[g] - b[g]) / np.sqrt(2) / np.sqrt(a[g].size)
        assert se > 0 and abs((a[g] - ref[g]).mean()) < 5 * se, groups[g]
    rgb = setup[4]
    assert rgb.render_pixels(0.002, 4, 1, ["lamp"], np.arange(10)).shape == (1, 10, 3)
    assert rgb.render(0.002, 4, 1, ["lamp"]).shape == (1, 48, 64, 3)


@pytest.mark.render
def test_the_refined_pixels_match_a_brute_force_render_within_their_standard_error(setup):
    cfg, timeline, plan, seeds, r = setup
    first = integrate(r, plan, timeline.n_buckets, seeds[2])
    scout = integrate(r, replace(plan, spp=plan.spp // 4), timeline.n_buckets, np.random.SeedSequence(8))
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    most = 2  # every chosen pixel at one factor
    tiers = tail_pixels(
        scout.mc_diff,
        scout.exposure * k_e,
        k_e,
        [x.buckets for x in timeline.reads],
        cfg.sensor.full_well_e,
        cfg.sensor.fd_full_well_e,
        40.0,
        most,
        0.25,
    )  # a tail target
    # that leaves most pixels alone at this small spp
    assert len(tiers) == 1
    pixels, factor = tiers[0]
    assert 0 < pixels.size < 64 * 48 and 2 <= factor <= most
    refined = refine(r, plan, first, pixels, factor, np.random.SeedSequence(9))
    with pytest.raises(ValueError, match="adds no samples"):
        refine(r, plan, first, pixels, 1, np.random.SeedSequence(9))
    brute = integrate(r, replace(plan, spp=plan.spp * 16), timeline.n_buckets, np.random.SeedSequence(10))
    K = first.exposure.shape[0]
    flat = lambda x: x.reshape(K, -1, 3)  # noqa: E731
    others = np.setdiff1d(np.arange(64 * 48), pixels)
    np.testing.assert_array_equal(flat(refined.exposure)[:, others], flat(first.exposure)[:, others])
    for k in range(K):  # per bucket, the chosen region's mean against brute force
        d = flat(refined.exposure)[k, pixels] - flat(brute.exposure)[k, pixels]
        var = flat(refined.mc_var)[k, pixels] + flat(brute.mc_var)[k, pixels]
        se = np.sqrt(var.sum()) / d.size
        assert abs(d.mean()) < 5 * se, (k, d.mean(), se)
    # the refined pixels are less noisy than the first pass made them: at factor 2 the second pass is the
    # first pass's estimator again, so their variance halved; its estimates' mean within 5 standard errors
    # of half the first pass's (the first pass there is a fair draw: the scout chose them; the two means'
    # relative errors added, a bound, as the refined estimates hold the first pass's)
    assert factor == 2
    after, before = flat(refined.mc_var)[:, pixels].ravel(), flat(first.mc_var)[:, pixels].ravel()
    rel_se = sum(v.std() / v.mean() / np.sqrt(v.size) for v in (after, before))
    assert abs(after.mean() / before.mean() * factor - 1) < 5 * rel_se, (after.mean() / before.mean(), rel_se)
    # a second round (adaptive.second_round): the same pixels to 4x from the 2x they hold, the passes weighed 2 : 2;
    # unbiased, and their variance a quarter of the first pass's
    again = refine(r, plan, refined, pixels, 2 * factor, np.random.SeedSequence(11), have=factor)
    with pytest.raises(ValueError, match="adds no samples"):
        refine(r, plan, refined, pixels, factor, np.random.SeedSequence(11), have=factor)
    np.testing.assert_array_equal(flat(again.exposure)[:, others], flat(first.exposure)[:, others])
    for k in range(K):
        d = flat(again.exposure)[k, pixels] - flat(brute.exposure)[k, pixels]
        se = np.sqrt((flat(again.mc_var)[k, pixels] + flat(brute.mc_var)[k, pixels]).sum()) / d.size
        assert abs(d.mean()) < 5 * se, (k, d.mean(), se)
    twice = flat(again.mc_var)[:, pixels].ravel()
    rel_se = sum(v.std() / v.mean() / np.sqrt(v.size) for v in (twice, before))
    assert abs(twice.mean() / before.mean() * 2 * factor - 1) < 5 * rel_se, (twice.mean() / before.mean(), rel_se)


def test_tail_pixels_gives_each_pixel_the_factor_its_estimate_asks_for():
    """Tiers of factors, from each pixel's estimated ratio over ADAPTIVE_SELECT x the tail target: a region far over
    the target gets more samples than one just over it, which gets 2x, each pixel in one tier, neighbours
    included; at render.adaptive_max_factor 2 one tier (every chosen pixel alike)."""
    H = W = 24
    signal = np.full((1, H, W, 1), 1000.0)  # electrons, one bucket, one channel, below the full well
    diff = np.zeros((1, H, W, 1))
    diff[0, 2:9, 2:9] = np.sqrt(1000 * 1.6)  # ratio 1.6: just over the level (ADAPTIVE_SELECT x tail target 1; pooled
    # over 3x3 its edge rows read 1.07)
    diff[0, 14:21, 14:21] = np.sqrt(1000 * 50.0)  # ratio 50: 70-100 x the level
    k_e = np.ones(1)
    args = (diff, signal, k_e, [(0,)], 1e9, 1e9, 1.0)
    tiers = tail_pixels(*args, 256)
    factors = [f for _, f in tiers]
    floor = 2  # the least factor: the first pass and as many samples again
    asks = lambda ratio: 2 ** int(np.ceil(np.log2(ratio / ADAPTIVE_SELECT)))  # noqa: E731  (the power of two a ratio asks)
    assert factors == sorted(set(factors)) and factors[0] == floor and factors[-1] == asks(50.0) >= 64
    given = np.zeros(H * W, int)
    for p, f in tiers:
        assert (given[p] == 0).all()  # each pixel in one tier
        given[p] = f
    given = given.reshape(H, W)
    assert given[5, 5] == asks(1.6) == floor and given[17, 17] == asks(50.0)  # the centres
    # outside each region, its side neighbours' factor (budget.ADAPTIVE_FOOTPRINT): (13, 14) has the high region's
    # corner below it (pooled over 3x3: 4 of 9 at 50) and (13, 15) beside it (3 of 9); the edge pixel (14, 15)
    # (6 of 9) is a diagonal neighbour, which the four sides leave out
    assert given[1, 5] == floor and given[13, 14] == asks(50.0 * 4 / 9) < asks(50.0 * 6 / 9)
    assert given[11, 11] == 0 and given[0, 23] == 0  # far from both: not refined
    low_high = set(np.flatnonzero(given).tolist())
    one = tail_pixels(*args, floor)
    assert len(one) == 1 and one[0][1] == floor and set(one[0][0].tolist()) == low_high
    assert tail_pixels(diff * 0, signal, k_e, [(0,)], 1e9, 1e9, 1.0, 256) == []
    # a scout's differences at a sixteenth of the samples (16x the variance), scaled back: the same choice
    scouted = tail_pixels(diff * 4, signal, k_e, [(0,)], 1e9, 1e9, 1.0, 256, 1 / 16)
    assert [(p.tolist(), f) for p, f in scouted] == [(p.tolist(), f) for p, f in tiers]
    # a scale per pixel: left unscaled, the low region (scout ratio 16 x 1.6) asks for the most
    per_pixel = np.full((H, W), 1 / 16)
    per_pixel[:12] = 1.0
    mixed = {f: set(p.tolist()) for p, f in tail_pixels(diff * 4, signal, k_e, [(0,)], 1e9, 1e9, 1.0, 256, per_pixel)}
    assert 5 * W + 5 in mixed[asks(16 * 1.6)] and 17 * W + 17 in mixed[asks(50.0)]


@pytest.mark.render
def test_a_capture_with_adaptive_sampling_reports_its_tiers(tmp_path, capsys):
    """`mbcapture run` with render.adaptive: report.json says which tiers were refined at what factor
    and what they added, every key documented in docs/report.md; the status lines count the stages
    against one total, fixed at the start, the refinement shown as a part of the stage before it."""
    from report_checks import undocumented_keys

    from mbcapture import run_capture

    # at most 32 spp and a tail target of 10: tiers of factors, chosen among the rules by what they leave in the
    # tail (at 32x24 one read's 0.1 % is two samples: the rule may refine most of the film)
    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml",
        [
            "render.width=32",
            "render.height=24",
            "render.max_motion_px=4",
            "render.min_strata=1",
            "render.cache=off",
            "render.max_spp=32",
            "render.adaptive=true",
            "render.adaptive_max_factor=64",
            "render.noise_budget_tail=10",
        ],
    )
    result = run_capture(cfg, tmp_path, progress=True)
    err = capsys.readouterr().err
    counts = [tuple(map(int, m)) for m in re.findall(r"\[(?:part of )?stage (\d+)/(\d+),", err)]
    assert len({n for _, n in counts}) == 1 and all(1 <= i <= n for i, n in counts), sorted(set(counts))
    assert "part of stage" in err and "adaptive sampling: refine" in err
    info = result.report["adaptive"]
    tiers = info["tiers"]
    assert len(tiers) >= 2 and info["pixels"] == sum(t["pixels"] for t in tiers) <= 32 * 24
    assert info["rules_judged"] >= 1 and isinstance(info["tail_met_by_rule"], bool) and info["predicted_tail"] > 0
    factors = [t["factor"] for t in tiers]
    assert factors == sorted(set(factors)) and all(2 <= f <= 64 and f & (f - 1) == 0 for f in factors)
    assert info["added_samples"] == pytest.approx(
        sum(t["pixels"] * (t["factor"] - 1) for t in tiers) / (32 * 24), abs=1e-4
    )
    assert undocumented_keys(result.report, [r.name for r in result.timeline.reads]) == []


@pytest.mark.render
def test_a_top_up_meets_the_budget_without_bias(setup, monkeypatch):
    """render.top_up: a first pass at about half the samples the budget needs is over it; the top-up's
    second pass, which continues the first pass's patterns (render.pattern 'shared', the default) and is
    weighed with it by their samples, brings the estimate under it, and the combination matches a
    brute-force render within its standard error."""
    from mbcapture.budget.adaptive import over_budget, top_up
    from mbcapture.progress import StageStatus

    _, timeline, plan, seeds, r = setup
    # a budget that 64 spp misses by about 1.7x at this film
    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml", [*SMALL, "render.noise_budget=1.5", "render.noise_budget_p95=100"]
    )
    low = plan  # 64 spp
    first = integrate(r, low, timeline.n_buckets, seeds[2])
    before = over_budget(first, timeline, cfg)[0]
    assert 1.3 < before < 4
    topped_plan, topped, info = top_up(
        Passes(cfg, r, timeline, seeds[2], StageStatus(False), per_group=False, progress=False),
        low,
        first,
        why_not=None,
    )
    assert info["applied"] and info["before"] == pytest.approx(before, rel=1e-3)
    assert info["weight"] == pytest.approx(sum(info["spp_added"]) / low.spp.sum())  # by their samples
    assert (topped_plan.spp == low.spp + np.array(info["spp_added"])).all()
    assert info["after"] < 1.0 and info["after"] == pytest.approx(over_budget(topped, timeline, cfg)[0], rel=1e-3)
    brute = integrate(r, replace(plan, spp=plan.spp * 4), timeline.n_buckets, np.random.SeedSequence(10))
    for k in range(topped.exposure.shape[0]):  # per bucket, the whole film's mean against brute force
        d = topped.exposure[k] - brute.exposure[k]
        se = np.sqrt((topped.mc_var[k] + brute.mc_var[k]).sum()) / d.size
        assert abs(d.mean()) < 5 * se, (k, d.mean(), se)
    # not applied where it cannot run, and says why
    same_plan, same, note = top_up(
        Passes(cfg, r, timeline, np.random.SeedSequence(4), StageStatus(False), per_group=False, progress=False),
        low,
        first,
        why_not="a reason",
    )
    assert same is first and same_plan is low and not note["applied"] and "a reason" in note["note"]
    # nor where its second set of the film's arrays would not fit in free memory
    from mbcapture.exposure import resources

    monkeypatch.setattr(resources, "free_memory", lambda: (resources.rss_bytes() + 1000, "a test"))
    _, same, note = top_up(
        Passes(cfg, r, timeline, np.random.SeedSequence(4), StageStatus(False), per_group=False, progress=False),
        low,
        first,
        why_not=None,
    )
    assert same is first and not note["applied"] and "free by a test" in note["note"]


def test_quantile_intervals_cover_the_true_quantile_at_their_stated_rate():
    """The stated 95 % intervals hold the population's quantile in 95 % of trials, within the binomial
    error of the trial count; with values that share their data (each repeated ``design`` times) too. Without the design factor the repeated values'
    interval is too narrow and misses far more often."""
    from scipy.stats import expon

    from mbcapture.budget import quantiles_with_intervals

    rng = np.random.default_rng(11)
    trials, n = 400, 3000
    tol = 4 * np.sqrt(0.95 * 0.05 / trials)  # four binomial standard errors of the coverage
    truth = {q: expon.ppf(q / 100) for q in (50.0, 95.0, 99.0)}

    def coverage(draw) -> dict:
        hits = {q: 0 for q in truth}
        for _ in range(trials):
            values, design = draw()
            for q, (_, lo, hi) in zip(truth, quantiles_with_intervals(values, list(truth), design)):
                hits[q] += lo <= truth[q] <= hi
        return {q: h / trials for q, h in hits.items()}

    plain = coverage(lambda: (rng.exponential(size=n), 1.0))
    shared = lambda d: (np.repeat(rng.exponential(size=n // 4), 4), d)  # noqa: E731
    with_design, without = coverage(lambda: shared(4.0)), coverage(lambda: shared(1.0))
    for q in truth:
        assert abs(plain[q] - 0.95) < tol, (q, plain[q])
        assert abs(with_design[q] - 0.95) < tol, (q, with_design[q])
    assert min(without.values()) < 0.95 - tol  # too narrow without the design factor


def _ratio_field(rng: np.random.Generator, H: int = 240, W: int = 320) -> np.ndarray:
    """(1, H, W, 1) known per-sample Monte Carlo / shot-noise ratios: a smooth field with a heavy tail
    (median 0.05, 7 % of the film over 0.5)."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(rng.standard_normal((H, W)), 6)
    return (0.05 * np.exp(1.5 * g / g.std()))[None, :, :, None]


@pytest.mark.parametrize("chooser", ["scout", "first pass"])
def test_a_choice_from_a_scout_leaves_the_runs_own_estimate_unbiased(chooser):
    """A film of known per-pixel ratios, half-sample differences drawn from it (heavy-tailed: Student's t
    with 3 degrees of freedom, scaled to the variance). Chosen from a scout of its own (a sixteenth of the
    samples: 16x the ratio, scale 1/16), the pixels adaptive sampling leaves keep first-pass estimates
    whose squared differences average their true variance, and the run's own quantiles, refined pixels
    combined with their first pass, hold the outside measurement (a second draw of the same estimator) in
    their intervals. Chosen from the first pass's own differences, the pixels left read low (why they were
    left): the bias the scout removes."""
    from mbcapture.budget import render_error

    rng = np.random.default_rng(5)
    ratio = _ratio_field(rng)
    H, W = ratio.shape[1:3]
    signal = np.full(ratio.shape, 5000.0)
    k_e = np.ones(1)

    def diff(r) -> np.ndarray:  # a half-sample difference whose square averages var = r x signal, heavy-tailed
        return np.sqrt(r * signal / 3.0) * rng.standard_t(3, size=r.shape)

    def err(d):
        return render_error(d, signal, k_e, [(0,)], ["J"], 1e12, None)["reads"]["J"]

    first = diff(ratio)
    scout, scale = (diff(16 * ratio), 1 / 16) if chooser == "scout" else (first, 1.0)
    tiers = tail_pixels(scout, signal, k_e, [(0,)], 1e12, 1e12, 1.0, 16, scale)
    factor = np.ones(H * W)
    for p, f in tiers:
        factor[p] = f
    factor = factor.reshape(ratio.shape)
    refined = factor > 1
    assert 0.02 < refined.mean() < 0.5
    left = ~refined
    # the pixels left: their first-pass squared differences against their true variance (mean 1 if unbiased)
    z = first[left] ** 2 / (ratio * signal)[left]
    se = z.std() / np.sqrt(z.size)
    if chooser == "first pass":
        assert z.mean() < 1 - 5 * se, (z.mean(), se)
        return
    assert abs(z.mean() - 1) < 5 * se, (z.mean(), se)
    # the refined pixels: the first pass and a second of factor - 1 times its samples, by their samples
    second = diff(ratio / np.maximum(factor - 1, 1))
    combined = np.where(refined, (first + (factor - 1) * second) / factor, first)
    own, outside = err(combined), err(diff(ratio / factor))
    for q in ("median", "p95", "p999"):
        lo, hi = own[f"to_shot_noise_variance_{q}_interval"]
        assert lo <= outside[f"to_shot_noise_variance_{q}"] <= hi, (q, lo, outside[f"to_shot_noise_variance_{q}"], hi)


@pytest.mark.render
def test_a_capture_chooses_its_pixels_from_a_scout_not_its_first_pass(monkeypatch):
    """The pixels adaptive sampling refines are chosen from the scout's renders (seeds of their own, a
    sixteenth of the samples), never from the first pass's differences."""
    from mbcapture.capture import pipeline
    from mbcapture.budget import scout_spp
    from mbcapture.progress import StageStatus

    made, seen = [], []

    def integrate_recorded(*args, **kwargs):  # every pass through the film, in its tiles (FilmLayout)
        made.append((kwargs.get("desc", "render"), args[1], integrate_tiles(*args, **kwargs)))
        return made[-1][2]

    def choose(mc_diff, *args, **kwargs):
        seen.append((mc_diff, args[-1]))
        return tail_pixels(mc_diff, *args, **kwargs)

    monkeypatch.setattr(integrate_module, "integrate_tiles", integrate_recorded)
    monkeypatch.setattr(adaptive, "tail_pixels", choose)
    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml",
        [
            "render.width=32",
            "render.height=24",
            "render.max_motion_px=4",
            "render.min_strata=1",
            "render.cache=off",
            "render.adaptive=true",
            "render.noise_budget_tail=10",
        ],
    )
    run = pipeline.capture_in_memory(cfg, StageStatus(False))
    ((desc, plan, scout),) = [m for m in made if m[0] == "scout"]
    assert len(seen) == 1 and seen[0][0] is scout.mc_diff
    top = run.report["top_up"] or {}  # the scout comes before a top-up: the first pass's samples alone
    first_spp = np.asarray(run.plan.spp) - (np.asarray(top["spp_added"]) if top.get("applied") else 0)
    assert run.plan.shares_pattern  # the scout draws from the pattern too: it takes the counts it asks for
    assert (plan.spp == scout_spp(first_spp, Renderer.from_config(scene_of(cfg), cfg).counter(True))).all()
    assert plan.spp.sum() * 8 < first_spp.sum()
    # its ratios scaled to the first pass's samples as 1/spp where nothing moves, not at all where the
    # moving parts cross or cast their hard shadows (both passes draw one time per half-stratum there: the time
    # noise stays)
    moving = run.moving_mask
    span = [float(run.timeline.seconds(t)) for t in (run.timeline.start_tick, run.timeline.end_tick)]
    changing = changing_region(Renderer.from_config(scene_of(cfg), cfg), *span, 32, 24)
    assert 0 < moving.mean() < changing.mean() < 1
    np.testing.assert_array_equal(seen[0][1], np.where(changing, 1.0, (plan.spp / first_spp).max()))
    assert run.report["adaptive"]["scout"]["spp"] == plan.spp.tolist()


@pytest.mark.slow
@pytest.mark.render
def test_the_outside_measurement_gives_the_second_run_the_first_runs_choice(monkeypatch):
    """scripts/render_noise_reads.py: with adaptive sampling both runs refine the pixels the first run
    chose and render the samples the first run's pilot chose (one estimator, the one whose error the first
    run's own figures estimate); --own-choices lets each choose both."""
    from mbcapture.capture import pipeline
    from mbcapture.capture.pipeline import capture_in_memory
    from mbcapture.progress import StageStatus

    script = load_script("render_noise_reads")
    sets = [
        "render.width=32",
        "render.height=24",
        "render.max_motion_px=4",
        "render.min_strata=1",
        "render.cache=off",
        "render.max_spp=32",
        "render.adaptive=true",
        "render.noise_budget_tail=10",
        "render.top_up=false",
    ]
    real_resolve = script.resolve_spp
    for share in (True, False):
        calls, pilots = [], []

        def choose(*args, **kwargs):
            calls.append(tail_pixels(*args, **kwargs))
            return calls[-1]

        def pilot(plan, *args, **kwargs):  # each run's pilot asks for other samples: 8 more per stratum each time
            out = real_resolve(plan, *args, **kwargs)
            pilots.append(out.spp + 8 * len(pilots))
            return replace(out, spp=pilots[-1])

        monkeypatch.setattr(script, "tail_pixels", choose)  # what FirstChoice calls to choose
        monkeypatch.setattr(script, "resolve_spp", pilot)  # what FirstSamples calls
        choice, samples = script.FirstChoice(share=share), script.FirstSamples(share=share)
        used, spp, rounds = [], [], []
        for seed in (1, 2):
            choice.start_run()
            monkeypatch.setattr(adaptive, "tail_pixels", choice)
            monkeypatch.setattr(pipeline, "resolve_spp", samples)
            run = capture_in_memory(
                load_config(ROOT / "configs" / "metronome_hdr.yaml", [*sets, f"seed={seed}"]), StageStatus(False)
            )
            used.append(choice.tiers)
            spp.append(np.asarray(run.plan.spp))
            assert run.report["adaptive"]["pixels"] == sum(p.size for p, _ in choice.tiers) > 0
            rounds.append(1 + ("second_round" in run.report["adaptive"]))
        # every round of the first run chooses; the second run's rounds choose only without sharing
        assert len(calls) == (rounds[0] if share else sum(rounds)) and len(pilots) == 2  # every run's pilot renders
        assert (used[1] is used[0]) == share
        assert np.array_equal(spp[1], pilots[0]) == share and np.array_equal(spp[0], pilots[0])


def test_the_outside_measurement_gives_each_round_of_the_second_run_the_first_runs_choice_for_it(monkeypatch):
    """scripts/render_noise_reads.FirstChoice: the first run's calls (adaptive sampling's first round, then a second)
    are kept, and a later run's calls get them in order; a round the first run did not need is chosen afresh; each
    run chooses all its own without sharing."""
    script = load_script("render_noise_reads")
    made = iter(range(100))
    monkeypatch.setattr(script, "tail_pixels", lambda *a, **k: f"choice {next(made)}")
    shared, own = script.FirstChoice(share=True), script.FirstChoice(share=False)
    assert shared.tiers is None
    got = []
    for calls in (2, 3):  # the second run needed a third round
        for c in (shared, own):
            c.start_run()
        got.append(([shared() for _ in range(calls)], [own() for _ in range(calls)]))
    assert got[0] == (["choice 0", "choice 1"], ["choice 2", "choice 3"])
    assert got[1] == (["choice 0", "choice 1", "choice 4"], ["choice 5", "choice 6", "choice 7"])
    assert shared.tiers == "choice 0" and own.tiers == "choice 5"


@pytest.mark.render
def test_adaptive_sampling_is_skipped_where_its_scout_would_not_fit_in_memory(setup, monkeypatch):
    """The scout renders the film again, holding a second set of its arrays: where free memory cannot
    take them, adaptive sampling is not applied and report.json's note says why (as the top-up does)."""
    from contextlib import nullcontext

    from mbcapture.exposure import resources
    from mbcapture.budget.adaptive import scout_tail
    from mbcapture.progress import StageStatus

    cfg, timeline, plan, seeds, r = setup
    first = integrate(r, plan, timeline.n_buckets, seeds[2])
    monkeypatch.setattr(resources, "free_memory", lambda: (resources.rss_bytes() + 1000, "a test"))
    tiers, info, _ = scout_tail(
        Passes(
            cfg,
            r,
            timeline,
            seeds[2],
            StageStatus(False),
            changing=np.zeros((48, 64), bool),
            timer=lambda name: nullcontext(),
            progress=False,
        ),
        plan,
        first,
    )
    assert tiers is None and info["pixels"] == 0 and "free by a test" in info["note"]


def test_the_frontier_scripts_rule_in_use_is_the_budgets():
    """scripts/adaptive_frontier.py: its rule 'level 1, target 1, cross, from 1' gives every pixel the factor
    budget.factor_tiers gives it (the script checks this on every run too), and the other rules differ from it
    the way they say: the 3x3 box spreads to more pixels, no spread to none, a lower level chooses more."""
    from mbcapture.budget import factor_tiers

    script = load_script("adaptive_frontier")
    rng = np.random.default_rng(3)
    predicted = rng.lognormal(-1.5, 1.5, (40, 56))
    expected = np.ones(predicted.size)
    for pixels, f in factor_tiers(predicted, ADAPTIVE_SELECT * 2.0, 8):
        expected[pixels] = f
    assert script.IN_USE == "cross"
    in_use = script.factors(predicted, 2.0, ADAPTIVE_SELECT, ADAPTIVE_SELECT, script.IN_USE, 1, max_factor=8)
    np.testing.assert_array_equal(in_use.ravel(), expected)
    chosen = predicted > 2.0
    none = script.factors(predicted, 2.0, 1.0, 1.0, "none", 1, max_factor=8)
    box = script.factors(predicted, 2.0, 1.0, 1.0, "box", 1, max_factor=8)
    assert np.array_equal(none > 1, chosen)
    assert (none <= in_use).all() and (in_use <= box).all() and (in_use > 1).sum() < (box > 1).sum()
    # integer factors: never above the power of two, the ratio over the target rounded up to an integer
    ints = script.factors(predicted, 2.0, 1.0, 1.0, "none", 1, "int", max_factor=8)
    assert (ints <= none).all() and (ints[chosen] == np.clip(np.ceil(predicted[chosen] / 2.0), 2, 8)).all()
    assert (script.factors(predicted, 2.0, 0.7, 0.7, "none", 1, max_factor=8) > 1).sum() > chosen.sum()
    # the factor: the predicted ratio over target x tail, up to a power of two in [2, 8]
    f = none[chosen]
    assert set(np.unique(f)) <= {2.0, 4.0, 8.0}
    assert (predicted[chosen] / f <= 2.0 + 1e-12)[f < 8].all()
    with pytest.raises(SystemExit, match="dilation one of"):
        script.parse_rule("1,1,star,1")
    with pytest.raises(SystemExit, match="target <= level"):
        script.parse_rule("0.7,1,box,1")


def test_the_frontier_script_predicts_a_refined_variance_as_the_first_passes_over_the_factor():
    """A factor f everywhere divides every predicted quantile by f (the variance falls as 1/f), and f = 1 is
    the two first passes' own outside figure, pooled as render_noise_reads.py pools it."""
    from mbcapture.budget import pooled_alike

    script = load_script("adaptive_frontier")
    rng = np.random.default_rng(5)
    mean = rng.uniform(50.0, 5000.0, (1, 24, 32, 3))
    e1, e2 = mean + rng.normal(0, 1, mean.shape) * np.sqrt(mean), mean + rng.normal(0, 1, mean.shape) * np.sqrt(mean)
    below = np.ones(mean.shape, bool)
    data = {"e1": e1, "e2": e2, "below1": below, "below2": below, "fd_full_well_e": 1e9}
    one = script.predict(data, np.ones((24, 32)))[0]
    four = script.predict(data, np.full((24, 32), 4.0))[0]
    np.testing.assert_allclose(np.array(four), np.array(one) / 4.0, rtol=1e-9)
    m = (e1[0] + e2[0]) / 2
    direct = pooled_alike((e1[0] - e2[0]) ** 2 / 2, m) / m
    assert one[2] == pytest.approx(float(np.percentile(direct, 99.9)), rel=1e-12)
    # shot-noise-sized differences: the ratio's middle near 1
    assert 0.6 < one[0] < 1.4


def test_the_top_up_judges_the_budget_on_the_image_adaptive_sampling_will_give(monkeypatch):
    """with_planned_refinement divides the half-sample differences of each tier's pixels by sqrt(factor) (their
    variance by the factor) and leaves the others and its input alone; top_up judges the budget on that."""
    from mbcapture.exposure.integrate import Integrated
    from mbcapture.progress import StageStatus

    rng = np.random.default_rng(5)
    diff = rng.normal(size=(2, 4, 5, 3)).astype(np.float32)
    first = Integrated(exposure=np.ones((2, 4, 5, 3)), mc_diff=diff.copy())
    tiers = [(np.array([0, 7]), 2), (np.array([19]), 8)]
    planned = adaptive.with_planned_refinement(first, tiers)
    np.testing.assert_array_equal(first.mc_diff, diff)
    want = diff.reshape(2, 20, 3).copy()
    want[:, [0, 7]] /= np.sqrt(2.0)
    want[:, 19] /= np.sqrt(8.0)
    np.testing.assert_allclose(planned.mc_diff, want.reshape(diff.shape), rtol=1e-6)
    assert adaptive.with_planned_refinement(first, []) is first

    judged = []

    def over(integrated, timeline, cfg, reads=None, *, tail=False, plan=None):
        judged.append((integrated.mc_diff, reads, tail))
        return 0.5, "J1", "to_shot_noise_variance_median", 0.05

    monkeypatch.setattr(adaptive, "over_budget", over)
    out = adaptive.top_up(
        Passes(None, None, None, None, StageStatus(False), per_group=False, progress=False),
        None,
        first,
        why_not=None,
        planned=tiers,
    )
    assert out == (None, first, None)
    np.testing.assert_array_equal(judged[0][0], planned.mc_diff)
    assert judged[0][1:] == (None, False)  # the tail is not judged unless asked: a rule met it
    figures = {"J1": {}}
    adaptive.top_up(
        Passes(None, None, None, None, StageStatus(False), per_group=False, progress=False),
        None,
        first,
        why_not=None,
        planned=tiers,
        planned_reads=figures,
        tail=True,
    )
    assert judged[1][1] is figures and judged[1][2] is True  # scout_tail's figures reused, the tail judged


def test_the_tail_model_agrees_with_the_runs_own_estimate_of_a_planned_refinement():
    """budget.TailModel.meets (what adaptive sampling's rules are judged by) says a plan of per-pixel factors
    meets the tail target exactly when render_error, on the first pass with each pixel's half-sample differences
    over sqrt(factor) (adaptive.with_planned_refinement), puts every read's 99.9th percentile at most at the
    target: on heavy-tailed noise, for plans from none to most of the film refined, at three targets."""
    from mbcapture.budget import TailModel, render_error

    rng = np.random.default_rng(3)
    K, H, W, C = 4, 40, 48, 3
    mc = (rng.standard_t(3, size=(K, H, W, C)) * 0.006).astype(np.float32)
    exposure = rng.uniform(0.2, 2.0, size=(K, H, W, C)).astype(np.float32)
    exposure[:, :, :8] *= 50  # a bright band: its neighbours are not alike
    k_e = np.array([300.0, 400.0, 500.0])
    reads = [(0,), (0, 1), (0, 1, 2, 3)]
    seen = set()
    for target in (0.3, 1.0, 3.0):
        model = TailModel(mc, exposure * k_e, k_e, reads, 1e9, None, target)
        for trial in range(16):
            f = np.where(rng.uniform(size=H * W) < trial / 16, 2.0 ** rng.integers(0, 6, size=H * W), 1.0)
            shrink = (1.0 / np.sqrt(f)).reshape(1, H, W, 1).astype(np.float32)
            e = render_error(mc * shrink, exposure * k_e, k_e, reads, ["a", "b", "c"], 1e9, None)
            truth = max(v["to_shot_noise_variance_p999"] for v in e["reads"].values()) <= target
            assert model.meets(f) == truth, (target, trial)
            seen.add(truth)
    assert seen == {True, False}  # both answers were asked for


def test_adaptive_sampling_renders_the_cheapest_rule_that_meets_the_tail():
    """tail_pixels with ``meets``: among no refinement and every level x most factor, the rule with the fewest added
    samples that meets is kept; where none meets, the costliest; where a render's time is noise, factors from the
    square root of the ratio."""
    from mbcapture.budget import ADAPTIVE_LEVELS, factor_tiers, scout_ratio, tier_exponents, tiers_of

    H, W = 24, 32
    rng = np.random.default_rng(5)
    signal = np.full((1, H, W, 1), 1000.0)
    ratio = np.exp(rng.normal(-1.0, 1.5, size=(H, W)))  # the scout's ratio, spread over the levels
    diff = np.sqrt(1000.0 * ratio)[None, :, :, None]
    args = (diff, signal, np.ones(1), [(0,)], 1e12, 1e12, 1.0, 16)
    pooled = scout_ratio(*args[:6])

    def cost(tiers):
        return sum(p.size * (f - 1) for p, f in tiers)

    every = [factor_tiers(pooled, level, m) for level in ADAPTIVE_LEVELS for m in (2, 4, 8, 16)]
    costs = sorted({cost(t) for t in every})
    # a judge that asks for a given number of added samples: the cheapest rule with as many is kept
    for need in (1, costs[len(costs) // 2], costs[-1]):
        kept = tail_pixels(*args, meets=lambda f: (f - 1).sum() >= need)
        assert cost(kept) == min(c for c in costs if c >= need)
    assert tail_pixels(*args, meets=lambda f: True) == []  # the first pass alone meets it: nothing refined
    costliest = tail_pixels(*args, meets=lambda f: False)
    assert cost(costliest) == costs[-1]
    # where a render's time is noise (the upper half), a pixel's factor is the power of two the square root of its
    # ratio over the level asks for: the costliest rule is the lowest level's at the most factor
    changing = np.zeros((H, W), bool)
    changing[: H // 2] = True
    level = min(ADAPTIVE_LEVELS) * 1.0
    asked = np.where(changing, np.sqrt(pooled * level), pooled)
    want = tiers_of(tier_exponents(asked, level, 4))
    got = tail_pixels(*args, meets=lambda f: False, changing=changing.ravel())
    assert [(p.tolist(), f) for p, f in got] == [(p.tolist(), f) for p, f in want]
    assert cost(got) < costs[-1]  # the changing pixels ask for less


def test_a_second_round_runs_only_where_the_refined_estimate_is_over_and_starts_from_what_each_pixel_holds(monkeypatch):
    """adaptive.second_round: nothing where the refined render stage's own estimate meets the tail target on every read
    (a median over its target is the top-up's); else a scout and a refinement again, from the factor each pixel holds (the first round's tiers), at most
    SECOND_ROUND_MAX_FACTOR more, reported under adaptive.second_round with how far over the stage was."""
    from types import SimpleNamespace

    from mbcapture.progress import StageStatus

    cfg = SimpleNamespace(render=SimpleNamespace(width=4, height=2, noise_budget_tail=1.0))
    tiers = [(np.array([1, 2]), 2), (np.array([5]), 8)]
    calls = []
    monkeypatch.setattr(
        adaptive,
        "scout_tail",
        lambda *a, **k: calls.append(("scout", k)) or ([(np.array([5]), 2)], {"pixels": 1}, None),
    )
    monkeypatch.setattr(
        adaptive,
        "refine_tail",
        lambda passes, plan, integrated, more, info, **k: (
            calls.append(("refine", more, k)) or ("refined", {**info, "seconds": 1.0})
        ),
    )
    for over, runs in ((0.99, False), (1.3, True)):
        calls.clear()
        monkeypatch.setattr(
            adaptive,
            "read_figures",
            lambda *a, **k: {
                "J1": {
                    "to_shot_noise_variance_p999": 0.5,
                    "to_shot_noise_variance_median": 7.0,
                },  # the median: the top-up's
                "J4": {"to_shot_noise_variance_p999": over, "to_shot_noise_variance_median": 0.0},
            },
        )
        out, info = adaptive.second_round(
            Passes(
                cfg,
                None,
                None,
                None,
                StageStatus(False),
                changing=np.zeros((2, 4), bool),
                per_group=False,
                progress=False,
            ),
            None,
            "first",
            tiers,
            {"pixels": 3},
        )
        if not runs:
            assert out == "first" and info == {"pixels": 3} and not calls
            continue
        assert out == "refined" and info["second_round"] == {"pixels": 1, "before": 1.3, "seconds": 1.0}
        (_, scout), (_, more, refine_kwargs) = calls
        np.testing.assert_array_equal(scout["have"], [1, 2, 2, 1, 1, 8, 1, 1])
        assert scout["max_factor"] == adaptive.SECOND_ROUND_MAX_FACTOR
        np.testing.assert_array_equal(refine_kwargs["have"], scout["have"])


def test_with_adaptive_sampling_the_pilot_aims_the_first_passes_p95_under_the_tail(monkeypatch):
    """The first pass's 95th percentile target: render.noise_budget_p95, lowered with adaptive sampling to
    ADAPTIVE_FIRST_P95 x render.noise_budget_tail (never raised), and that is what the pilot is given."""
    from mbcapture import budget
    from mbcapture.budget import ADAPTIVE_FIRST_P95, first_pass_p95_target, resolve_spp

    def render_cfg(*sets):
        return load_config("metronome_hdr", list(sets)).render

    assert first_pass_p95_target(render_cfg()) == pytest.approx(ADAPTIVE_FIRST_P95 * 1.0)
    assert first_pass_p95_target(render_cfg("render.noise_budget_tail=3")) == pytest.approx(1.0)  # the p95's own
    assert first_pass_p95_target(render_cfg("render.noise_budget_p95=0.2")) == pytest.approx(0.2)
    assert first_pass_p95_target(render_cfg("render.adaptive=false")) == pytest.approx(1.0)
    seen = {}
    monkeypatch.setattr(budget.pilot, "choose_spp", lambda plan, *a, **k: seen.update(k) or plan)
    cfg = load_config("metronome_hdr", [*SMALL, "render.noise_budget_tail=0.8"])
    plan = replace(prepare(cfg)[2], spp=None)
    resolve_spp(plan, None, cfg, np.random.SeedSequence(1))
    assert seen["noise_budget_p95"] == pytest.approx(ADAPTIVE_FIRST_P95 * 0.8)
