"""Adaptive sampling (render.adaptive): pixels rendered alone (Renderer.render_pixels) are the full
render's estimator, and the refined capture's exposure at the pixels the first pass chose matches a
brute-force high-spp render within its standard error (the second pass replaces the first there, so
the choice, made from the first pass's noise, biases nothing)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.budget import tail_pixels
from mbcapture.config import scene_of
from mbcapture.integrate import integrate, refine
from mbcapture.pipeline import prepare
from mbcapture.render import Renderer
from mbcapture.sensor import electrons_per_render_second

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["render.width=64", "render.height=48", "render.max_motion_px=4", "render.cache=off"]


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
    with pytest.raises(Exception, match="render_pixels"):
        Renderer.from_config(scene_of(cfg), load_config(ROOT / "configs" / "metronome_hdr.yaml",
                                                        [*SMALL, "camera.diffraction=true"])).render_pixels(
            0.0, 4, 1, groups, pix)


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
def test_the_refined_pixels_match_a_brute_force_render_within_their_standard_error(setup):
    cfg, timeline, plan, seeds, r = setup
    first = integrate(r, plan, timeline.n_buckets, seeds[2])
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    pixels, factor = tail_pixels(first.mc_diff, first.exposure * k_e, k_e, [x.buckets for x in timeline.reads],
                                 cfg.sensor.full_well_e, cfg.sensor.fd_full_well_e, 40.0, 16)  # a tail target that
    # leaves most pixels alone at this small spp
    assert 0 < pixels.size < 64 * 48 and 2 <= factor <= 16
    refined = refine(r, plan, first, pixels, factor, np.random.SeedSequence(9))
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
    # the refined pixels are less noisy than the first pass made them: their estimated variance fell
    assert flat(refined.mc_var)[:, pixels].mean() < flat(first.mc_var)[:, pixels].mean() / 2
