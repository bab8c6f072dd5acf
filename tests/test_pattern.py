"""The pattern shared by the strata (render.pattern 'shared', mbcapture.render.pattern): what the
renderer relies on (nets in aligned blocks, uniform points, independent pairs), that a capture made
with it is unbiased and its reads less noisy at equal samples, and how its renders are keyed."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.budget import shared_pattern_gain
from mbcapture.exposure.integrate import render_patterns, render_requests

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def jit():
    from mbcapture.render import ensure_llvm

    ensure_llvm()
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return dr, mi


def points(jit, indices, key, dim):
    from mbcapture.render import pattern

    dr, mi = jit
    p = pattern.pair(
        dr, mi, mi.UInt32(np.asarray(indices, np.uint32)), mi.UInt32(np.asarray(key, np.uint32)), mi.UInt32(dim)
    )
    return np.asarray(p.x, np.float64), np.asarray(p.y, np.float64)


def is_net(x, y, m):
    """Whether the 2^m points (x, y) are a (0, m, 2)-net: one point in every elementary box of area 2^-m."""
    return all(len(set(zip((x * 2**a).astype(int), (y * 2 ** (m - a)).astype(int)))) == 2**m for a in range(m + 1))


@pytest.mark.render
def test_aligned_blocks_of_the_pattern_are_nets(jit):
    """Every aligned block of 2^m samples of a pixel's pattern is a (0, m, 2)-net in every pair of
    dimensions, so a stratum's own samples and the strata's union are both stratified; a plain
    uniform draw of 256 points is not (the check can fail)."""
    for key, dim in ((1, 0), (12345, 3), (2**31 + 7, 17)):
        x, y = points(jit, np.arange(4096), np.full(4096, key), dim)
        assert is_net(x, y, 12)
        assert all(is_net(x[s : s + 256], y[s : s + 256], 8) for s in range(0, 4096, 256))
    rng = np.random.default_rng(0)
    assert not is_net(rng.random(256), rng.random(256), 8)


@pytest.mark.render
def test_the_sequence_is_sobols_first_two_dimensions(jit):
    """sobol_pair's five-step transform gives what the direction numbers give (32 masked XORs)."""
    from mbcapture.render import pattern

    dr, mi = jit
    idx = np.concatenate([np.arange(512), np.random.default_rng(3).integers(0, 2**32, 4096)]).astype(np.uint32)
    x, y = pattern.sobol_pair(dr, mi.UInt32(idx))
    want = np.zeros_like(idx)
    v = 2**31  # the direction numbers of Sobol's second dimension (primitive polynomial x + 1)
    for b in range(32):
        if b:
            v ^= v >> 1
        want ^= np.where((idx >> np.uint32(b)) & 1, np.uint32(v), np.uint32(0)).astype(np.uint32)
    np.testing.assert_array_equal(np.asarray(y, np.uint32), want)
    np.testing.assert_array_equal(np.asarray(x, np.uint32)[:4], [0, 2**31, 2**30, 3 * 2**30])


@pytest.mark.render
def test_each_sample_is_uniform_over_keys_and_pairs_are_uncorrelated(jit):
    """One sample index over 2^18 keys (pixels): each coordinate uniform (16 bins, each within 5
    standard errors of 1/16), mean 1/2 within 5 standard errors; the pair jointly uniform (4 x 4 cells,
    the same bound); two pairs of dimensions of the same sample uncorrelated (|r| < 5 / sqrt(n)). (A
    bias far below these bounds would pass: exact uniformity rests on the construction, see
    mbcapture.render.pattern.)"""
    n = 1 << 18
    keys = (np.arange(n, dtype=np.uint64) * 2654435761 % 2**32).astype(np.uint32)
    for g in (0, 1, 131, 70000):
        x, y = points(jit, np.full(n, g), keys, 5)
        for u in (x, y):
            share = np.histogram(u, 16, (0.0, 1.0))[0] / n
            assert np.all(np.abs(share - 1 / 16) < 5 * np.sqrt(1 / 16 * 15 / 16 / n))
            assert abs(u.mean() - 0.5) < 5 * np.sqrt(1 / 12 / n)
        cells = np.histogram2d(x, y, 4, [[0.0, 1.0], [0.0, 1.0]])[0] / n
        assert np.all(np.abs(cells - 1 / 16) < 5 * np.sqrt(1 / 16 * 15 / 16 / n))
        x2, _ = points(jit, np.full(n, g), keys, 6)
        assert abs(np.corrcoef(x, x2)[0, 1]) < 5 / np.sqrt(n)


def test_the_median_factor_of_the_pilot():
    """K equal strata and a per-sample exponent e: K^-(e - 1); one stratum, or e = 1 (variance ~ 1/spp:
    no stratification to share), gain nothing; unequal weights count as fewer strata."""
    assert shared_pattern_gain(np.ones(7), 1.2) == pytest.approx(7**-0.2)
    assert shared_pattern_gain(np.ones(1), 1.5) == 1.0
    assert shared_pattern_gain(np.ones(7), 1.0) == 1.0
    assert shared_pattern_gain(np.ones(7), 0.8) == 1.0
    assert shared_pattern_gain(np.array([1.0, 0.0, 0.0]), 1.5) == 1.0
    assert 7**-0.2 < shared_pattern_gain(np.array([3.0, 1, 1, 1, 1, 1, 1]), 1.2) < 1.0


def test_each_half_takes_the_samples_after_the_strata_before_it():
    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml",
        ["render.width=40", "render.height=32", "render.spp=6", "render.pattern=shared", "render.max_motion_px=0.05"],
    )
    from mbcapture.capture.pipeline import prepare

    _, _, plan, seeds = prepare(cfg)
    plan = replace(plan, spp=np.array([6, 10, 4, 8][: plan.passes] + [6] * max(plan.passes - 4, 0)))
    pats = render_patterns(plan, seeds[2])
    keys = {p[0] for row in pats for p in row}
    assert plan.passes >= 3 and len(keys) == 2 and pats[0][0][0] != pats[0][1][0]  # one pattern per half
    for h in range(2):
        halves = [n // 2 if h == 0 else n - n // 2 for n in plan.spp]
        np.testing.assert_array_equal([row[h][1] for row in pats], np.concatenate([[0], np.cumsum(halves)[:-1]]))
    assert [r[4] for r in render_requests(plan, seeds[2])] == [p for row in pats for p in row]
    # the offsets advance by what the sampler takes (multijitter takes 132 for 128): no shared samples
    taken = [[row[h][1] for row in render_patterns(plan, seeds[2], lambda n: n + 1)] for h in range(2)]
    for h in range(2):
        halves = [n // 2 if h == 0 else n - n // 2 for n in plan.spp]
        np.testing.assert_array_equal(taken[h], np.concatenate([[0], np.cumsum(np.add(halves, 1))[:-1]]))
    assert [r[4] for r in render_requests(plan, seeds[2], lambda n: n + 1)] == [
        p for row in render_patterns(plan, seeds[2], lambda n: n + 1) for p in row
    ]
    own = replace(plan, pattern="own")
    assert all(p is None for row in render_patterns(own, seeds[2]) for p in row)
    assert all(p is None for row in render_patterns(replace(plan, estimator="difference"), seeds[2]) for p in row)


@pytest.mark.render
def test_a_shared_pattern_render_is_keyed_by_its_pattern_and_bands_hold_the_film_rows(tmp_path):
    """The same render with another pattern offset differs, with another sampler seed it does not; the
    cache keys the pattern (a second renderer on the same cache gives the first's render, not an
    own-pattern one); a film rendered in bands keys each band's pattern by the image's pixels."""
    from mbcapture.capture.pipeline import prepare
    from mbcapture.render import Renderer
    from mbcapture.render.cache import open_cache

    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", ["render.width=40", "render.height=32"])
    scene, _, plan, _ = prepare(cfg)
    t = float(plan.times_s[0])
    r = Renderer.from_config(scene, cfg, cache=open_cache(str(tmp_path), 1.0))
    a = r.render(t, 8, 3, plan.groups, pattern=(99, 0))
    assert not np.array_equal(a, r.render(t, 8, 3, plan.groups, pattern=(99, 8)))
    assert not np.array_equal(a, r.render(t, 8, 3, plan.groups))
    # every dimension of an RGB render, the camera ray's position in the pixel too, is the pattern's:
    # the sampler's seed no longer matters
    np.testing.assert_array_equal(r.render(t, 8, 4, plan.groups, pattern=(99, 0)), a)
    again = Renderer.from_config(scene, cfg, cache=open_cache(str(tmp_path), 1.0))
    np.testing.assert_array_equal(again.render(t, 8, 3, plan.groups, pattern=(99, 0)), a)
    banded = Renderer.from_config(
        scene,
        load_config(
            ROOT / "configs" / "metronome_hdr.yaml", ["render.width=40", "render.height=32", "render.band_rows=8"]
        ),
    )
    banded.render(t, 8, 3, plan.groups)  # loads the scene and its integrator
    calls = []
    integrator = banded._integrator
    real = integrator.use_pattern
    integrator.use_pattern = lambda *args: (calls.append(args), real(*args))[1]
    try:
        b = banded.render(t, 8, 3, plan.groups, pattern=(99, 5))
        banded.render(t, 8, 3, plan.groups)
    finally:
        del integrator.use_pattern
    # each band's pixels are the image's (the key of a pixel's pattern), not the crop window's
    assert calls == [(99, 5, 40 * r0) for r0 in (0, 8, 16, 24)] + [(None,)] * 4
    assert b.shape == a.shape


@pytest.mark.render
def test_a_shared_pattern_render_is_the_same_through_either_sensor(monkeypatch):
    """The renders that draw from the shared pattern go through the scene's second sensor (EXACT_SENSOR, Mitsuba's
    independent sampler, which takes any count); through the first (the config's multijitter), at a count it takes
    as asked, they are the same image: the sampler only lays out the lanes and the box filter keeps each sample
    in its pixel. And a count multijitter would round (85 -> 90) is taken exactly."""
    from mbcapture.capture.pipeline import prepare
    from mbcapture.render import Renderer

    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml", ["render.width=40", "render.height=32", "render.cache=off"]
    )
    scene, _, plan, _ = prepare(cfg)
    t = float(plan.times_s[0])
    r = Renderer.from_config(scene, cfg)
    assert r.sampler == "multijitter" and r.sample_count(12) == 12 and r.sample_count(85) == 90
    assert r.sample_count(85, pattern=True) == 85
    exact = r.render(t, 12, 3, plan.groups, pattern=(7, 24))
    monkeypatch.setattr(r, "_sensor_index", lambda pattern: 0)
    through_first = r.render(t, 12, 3, plan.groups, pattern=(7, 24))
    np.testing.assert_allclose(through_first, exact, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
@pytest.mark.render
def test_a_shared_pattern_is_unbiased_and_lowers_a_static_reads_variance():
    """K = 4 strata of one static time, their mean, over 8 seeds at 80x64 and 64 spp: with the shared
    pattern (stratum k at offset k x 64) against each its own. Over 8x8-pixel blocks the means agree:
    the z-scores' mean within 4 standard errors of 0 (80 blocks) and their standard deviation below 1.5;
    and the median pixel's variance is lower with the shared pattern (measured here: 0.79x, 0.74x with
    K = 6 and 10 seeds; asserted: below 0.85x, while the median of ~4000 pixels' 7-degree-of-freedom
    variances scatters by about 1.5 per cent, so the ratio of two by about 2 per cent). With every stratum
    at offset 0 (the same samples K times) it is higher, not lower (measured: 4.19x). (K and the seeds were
    6 and 10 until 2026-11-28: 27 s, the suite's slowest test; now about 10 s.)"""
    from mbcapture.capture.pipeline import prepare
    from mbcapture.render import Renderer

    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml", ["render.width=80", "render.height=64", "render.cache=off"]
    )
    scene, _, plan, _ = prepare(cfg)
    t, groups = float(plan.times_s[0]), plan.groups
    r = Renderer.from_config(scene, cfg)
    K, n, S = 4, 64, 8

    def mean_of_strata(s: int, shared: bool) -> np.ndarray:
        imgs = [
            r.render(t, n, 1000 * s + k + (500 if shared else 0), groups, pattern=(77 + s, k * n) if shared else None)
            for k in range(K)
        ]
        return np.mean(imgs, axis=0).sum(axis=(0, -1), dtype=np.float64)

    own = np.stack([mean_of_strata(s, False) for s in range(S)])
    shared = np.stack([mean_of_strata(s, True) for s in range(S)])
    block = lambda a: a.reshape(S, 8, 8, 10, 8).sum(axis=(2, 4)).reshape(S, -1)  # noqa: E731
    bo, bs = block(own), block(shared)
    z = (bs.mean(0) - bo.mean(0)) / np.sqrt(bs.var(0, ddof=1) / S + bo.var(0, ddof=1) / S)
    assert abs(z.mean()) < 4 * max(z.std(), 1.0) / np.sqrt(z.size) and z.std() < 1.5
    mean = own.mean(0)
    lit = mean > 1e-3 * np.median(mean[mean > 0])
    ratio = np.median(shared.var(0, ddof=1)[lit] / mean[lit]) / np.median(own.var(0, ddof=1)[lit] / mean[lit])
    assert ratio < 0.85


def test_every_module_the_pixels_depend_on_keys_the_render_cache():
    """The render cache keys a renderer by the digests of the modules that make its pixels
    (renderer._PIXEL_CODE): each module of mbcapture/render that the renderer or the integrator
    imports is among them (pattern.py was missing at first: a change to the pattern would have
    served stale renders), but for the cache itself and the LLVM set-up (its target is keyed apart)."""
    import re

    from mbcapture.render import renderer

    render_dir = ROOT / "mbcapture" / "render"
    imported = set()
    for name in renderer._PIXEL_CODE:
        text = (render_dir / name).read_text()
        imported |= set(re.findall(r"^from \.(\w+) import", text, flags=re.M))
        imported |= {
            m for group in re.findall(r"^from \. import ([\w, ]+)$", text, flags=re.M) for m in re.split(r",\s*", group)
        }
    missing = {f"{m}.py" for m in imported} - set(renderer._PIXEL_CODE) - {"cache.py", "llvm.py"}
    assert not missing and "pattern.py" in renderer._PIXEL_CODE
