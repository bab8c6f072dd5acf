"""The planner: strata follow image motion, weights are exact, unused groups are left out."""

from dataclasses import replace

import numpy as np
import pytest

from mbcapture.budget import adaptive
from mbcapture.budget.adaptive import Passes
from mbcapture.timing import protocols
from mbcapture.config import config_from_dict
from mbcapture.render.settings import RenderSection
from mbcapture.exposure.plan import make_plan
from mbcapture.scene.scenes import Camera, SceneModel

CAM = Camera(origin=(0, 0, -10), target=(0, 0, 0), up=(0, 1, 0), fov_deg=40)


def point_scene(speed_m_per_s: float | None, groups=("ambient", "flash"), switchable=frozenset({"flash"})):
    motion = None
    if speed_m_per_s is not None:

        def motion(t):
            return np.stack([np.asarray(t) * speed_m_per_s, 0 * np.asarray(t), 0 * np.asarray(t)], -1)[:, None, :]

    return SceneModel("test", groups, switchable, CAM, build=None, params=None, motion_points=motion)


def timeline(**capture):
    cfg = config_from_dict({"scene": {"name": "flatfield"}, "capture": capture})
    return protocols.build(cfg)


def plan(scene, tl, **render):
    return make_plan(tl, scene, RenderSection(width=160, height=128, **render), np.random.default_rng(0))


def test_camera_projects_centre_and_scale():
    W, H = 160, 128
    px = CAM.project(np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]), W, H)
    assert px[0] == pytest.approx([80, 64])
    f = W / 2 / np.tan(np.radians(20))  # focal length in pixels
    assert abs(px[1, 0] - 80) == pytest.approx(f / 10)  # 1 m at 10 m
    assert px[2, 1] == pytest.approx(64 - f / 10)  # up is up in the image (y grows downwards)


def test_static_scene_is_one_pass_whatever_the_periods():
    for periods in (1, 64, 10**5):
        p = plan(point_scene(None), timeline(periods=periods))
        assert p.passes == 1
        assert p.weights_s.sum() == pytest.approx(8e-3 * 1, rel=1e-12)  # 8T of ambient over 4 buckets


def test_doubling_speed_doubles_strata():
    tl = timeline(periods=16)
    n1 = plan(point_scene(50.0), tl).passes
    n2 = plan(point_scene(100.0), tl).passes
    assert n1 >= 5
    assert abs(n2 / n1 - 2) < 0.15


def test_a_moving_image_gets_at_least_min_strata():
    """render.min_strata: an image that moves less than render.max_motion_px is still cut into that many strata
    (each stratum's halves draw one time each, the same for every pixel), shared among the collecting intervals
    of a sequential capture; a static scene stays one stratum, and 1 restores the motion rule alone."""
    tl = timeline(periods=16)
    slow = point_scene(0.5)  # far under half a pixel over the capture
    assert plan(slow, tl, min_strata=1).passes == 1
    assert plan(slow, tl).passes == RenderSection().min_strata == 4
    assert plan(slow, tl, min_strata=7).passes == 7
    assert plan(point_scene(None), tl, min_strata=7).passes == 1
    fast = plan(point_scene(100.0), tl)  # motion asks for more than the minimum: the minimum changes nothing
    assert fast.passes == plan(point_scene(100.0), tl, min_strata=1).passes > 4
    seq = timeline(periods=4, sequential=True)  # four frames: at least one stratum each
    assert plan(slow, seq, min_strata=1).passes == 4 and plan(slow, seq, min_strata=8).passes == 8
    # two or three periods: too few boundaries to cut four strata on, so the cuts fall inside the periods
    assert plan(slow, timeline(periods=2)).passes == plan(slow, timeline(periods=3)).passes == 4


def test_strata_respect_max_motion():
    tl = timeline(periods=16)
    scene = point_scene(100.0)
    p = plan(scene, tl, max_motion_px=0.25)
    for a, b in zip(p.starts_ticks, p.ends_ticks):
        ts = np.linspace(float(tl.seconds(a)), float(tl.seconds(b)), 50)
        px = CAM.project(scene.motion_points(ts), 160, 128)[:, 0, 0]
        assert px.max() - px.min() <= 0.25 * 1.01
    # (nearly) independent of the interleaving frequency: strata follow motion, not slots; with
    # fine interleaving the cuts snap to period boundaries, planned for 0.25 px minus one period's motion
    fine = plan(scene, timeline(periods=1024), max_motion_px=0.25)
    assert p.passes <= fine.passes <= 1.1 * p.passes


def test_fine_interleaving_strata_hold_whole_periods():
    """Each stratum holds whole periods, so every bucket weighs it by its duty cycle exactly and
    the interleaved reads see identical motion sampling; the motion bound still holds."""
    tl = timeline(periods=1024)
    scene = point_scene(100.0)
    p = plan(scene, tl, max_motion_px=0.25)
    seg = tl.segments[0]
    assert np.all((p.starts_ticks - seg.start_tick) % seg.period_ticks == 0)
    assert np.all((p.ends_ticks - seg.start_tick) % seg.period_ticks == 0)
    exposure = np.array([tl.exposure_ticks(k) for k in range(tl.n_buckets)], float) * float(tl.tick_s)
    share = p.weights_s[:, :, 0] / exposure  # (J, K): fraction of each bucket's exposure in stratum j
    np.testing.assert_allclose(share, share[:, :1].repeat(tl.n_buckets, 1), rtol=1e-12)
    for a, b in zip(p.starts_ticks, p.ends_ticks):
        ts = np.linspace(float(tl.seconds(a)), float(tl.seconds(b)), 50)
        px = CAM.project(scene.motion_points(ts), 160, 128)[:, 0, 0]
        assert px.max() - px.min() <= 0.25 * 1.01
    # coarse interleaving (one period moves more than max_motion_px / 4) is not snapped
    coarse_tl = timeline(periods=2)
    coarse = plan(scene, coarse_tl, max_motion_px=0.25)
    cseg = coarse_tl.segments[0]
    assert np.any((coarse.starts_ticks[1:] - cseg.start_tick) % cseg.period_ticks != 0)


def test_unused_emitter_group_is_never_rendered():
    p = plan(point_scene(None), timeline())
    assert p.groups == ("ambient",) and p.left_out_groups == ("flash",)
    assert p.weights_s.shape[-1] == 1


def test_sequential_gaps_are_not_rendered():
    tl = timeline(periods=4, sequential=True)
    p = plan(point_scene(100.0), tl, max_motion_px=1.0)
    intervals = tl.collecting_intervals()
    assert len(intervals) == 4
    for a, b in zip(p.starts_ticks, p.ends_ticks):  # every stratum inside one frame
        assert any(s <= a and b <= e for s, e in intervals)
    assert p.weights_s.sum(axis=(0, 2)) == pytest.approx([1e-3, 2e-3, 4e-3, 8e-3], rel=1e-12)


def test_render_times_are_inside_their_strata():
    tl = timeline(periods=16)
    p = plan(point_scene(100.0), tl)
    start, end = tl.seconds(p.starts_ticks), tl.seconds(p.ends_ticks)
    assert np.all(p.times_s >= start) and np.all(p.times_s < end)
    np.testing.assert_array_equal(p.bounds_s, np.stack([start, end], axis=1))
    # fresh draws (adaptive sampling's second pass): inside their strata, independent of the plan's
    fresh = p.draw_times(np.random.default_rng(3))
    assert fresh.shape == (p.passes, 2, 1)
    fresh = fresh[..., 0]
    assert not np.any(fresh == p.times_s[:, None])
    assert np.all(fresh >= start[:, None]) and np.all(fresh < end[:, None])
    # uniform in the stratum: the two draws' difference over its length is triangular on (-1, 1), mean 0,
    # variance 1/6 (5 standard errors; Var[d^2] = E[d^4] - E[d^2]^2 = 1/15 - 1/36)
    d = (fresh[:, 1] - fresh[:, 0]) / (end - start)
    assert p.passes > 30 and abs(d.mean()) < 5 * np.sqrt(1 / 6 / p.passes)
    assert d.var() == pytest.approx(1 / 6, abs=5 * np.sqrt((1 / 15 - 1 / 36) / p.passes))


def test_each_half_sample_render_has_its_own_time():
    """The two halves of a stratum are rendered at independent times, each uniform in the stratum;
    the first is the stratum's time (the pilot's)."""
    from mbcapture.exposure.integrate import integrate, render_requests

    tl = timeline(periods=16)
    p = plan(point_scene(100.0), tl, spp=4)
    start, end = tl.seconds(p.starts_ticks), tl.seconds(p.ends_ticks)
    t = p.render_times
    assert t.shape == (p.passes, 2)
    np.testing.assert_array_equal(t[:, 0], p.times_s)
    assert np.all(t >= start[:, None]) and np.all(t < end[:, None]) and np.all(t[:, 0] != t[:, 1])
    d = (t[:, 1] - t[:, 0]) / (end - start)  # triangular on (-1, 1): mean 0, variance 1/6 (see above)
    assert p.passes > 30 and abs(d.mean()) < 5 * np.sqrt(1 / 6 / p.passes)
    assert d.var() == pytest.approx(1 / 6, abs=5 * np.sqrt((1 / 15 - 1 / 36) / p.passes))
    r = FakeRenderer(p.groups, {g: 1.0 for g in p.groups}, {g: 0.5 for g in p.groups}, height=4, width=8)
    integrate(r, p, tl.n_buckets, np.random.SeedSequence(1))
    np.testing.assert_array_equal([c[0] for c in r.calls], t.ravel())
    np.testing.assert_array_equal([q[0] for q in render_requests(p, np.random.SeedSequence(1))], t.ravel())
    np.testing.assert_array_equal(p.render_time_shares(), np.full((p.passes, 2), 0.5))
    one = replace(p, spp=np.ones(p.passes, np.int64))
    np.testing.assert_array_equal(one.render_time_shares(), np.tile([1.0, 0.0], (p.passes, 1)))


def test_the_half_sample_error_estimate_holds_the_time_sampling_noise():
    """A pixel whose value changes within a stratum (a moving edge) carries noise from where in the
    stratum its render times fell. With no Monte Carlo noise at all, the halves' difference must
    still estimate the exposure's variance over seeds: its mean square over many seeds equals the
    exposures' variance. (Rendered at one shared time, the difference was exactly 0.)"""
    from mbcapture.exposure.integrate import integrate

    tl = timeline(periods=16)
    scene = point_scene(10.0, groups=("ambient",), switchable=frozenset())  # a few strata (5), one group
    runs, est, expo = 400, [], []
    for s in range(runs):
        p = make_plan(tl, scene, RenderSection(width=160, height=128, spp=2), np.random.default_rng(s))
        r = FakeRenderer(p.groups, {g: 1.0 for g in p.groups}, {g: 0.0 for g in p.groups}, height=1, width=4, slope=1e3)
        out = integrate(r, p, tl.n_buckets, np.random.SeedSequence(s))
        expo.append(out.exposure[3, 0, -1, 0])
        est.append(float(out.mc_var[3, 0, -1, 0]))
    var = float(np.var(expo, ddof=1))
    assert var > 0
    # the mean of 400 one-degree-of-freedom estimates: relative standard error sqrt(2 / 400) = 7 %; 5 of them
    assert np.mean(est) == pytest.approx(var, rel=5 * np.sqrt(2 / runs))


def test_the_second_pass_renders_at_times_of_its_own():
    """Adaptive sampling's second pass draws times of its own: at the first pass's times it would repeat
    the first pass's time noise (a moving edge's positions), which adding the passes could then not lower."""
    from mbcapture.exposure.integrate import integrate, refine

    tl = timeline(periods=16)
    p = plan(point_scene(50.0), tl, spp=4)
    r = FakeRenderer(p.groups, {g: 1.0 for g in p.groups}, {g: 0.5 for g in p.groups}, height=4, width=8)
    first = integrate(r, p, tl.n_buckets, np.random.SeedSequence(1))
    times = []

    def render_pixels(t_s, spp, seed, groups, pixels, pattern=None, cached=False):
        times.append(t_s)
        return np.ones((len(groups), len(pixels), 3), np.float32)

    r.render_pixels = render_pixels
    out = refine(r, p, first, np.array([3, 9]), 2, np.random.SeedSequence(2))
    t = np.array(times).reshape(p.passes, 2)
    assert np.all(t >= p.bounds_s[:, :1]) and np.all(t < p.bounds_s[:, 1:])
    assert not np.any(t == p.times_s[:, None]) and np.all(t[:, 0] != t[:, 1])
    # the refined pixels hold the first pass and the second (radiance 1 everywhere: the weights' sum) by their
    # samples, 1 : factor - 1; the others the first pass alone
    K = tl.n_buckets
    flat, before = out.exposure.reshape(K, -1, 3), first.exposure.reshape(K, -1, 3)
    second = np.broadcast_to(p.weights_s.sum(axis=(0, 2))[:, None, None], (K, 2, 3))
    np.testing.assert_allclose(flat[:, [3, 9]], (before[:, [3, 9]] + second) / 2)
    np.testing.assert_array_equal(np.delete(flat, [3, 9], axis=1), np.delete(before, [3, 9], axis=1))

    # at several times per half (a moving pixel's second pass): one time in each quarter of the stratum,
    # the half's samples shared among them, each time's render weighted alike
    times.clear()
    counts, patterns = [], []

    def render_pixels_counted(t_s, spp, seed, groups, pixels, pattern=None, cached=False):
        # one count and one pattern offset per pixel: alike here (one factor)
        spp, offset = np.broadcast_to(spp, len(pixels)), np.broadcast_to(pattern[1], len(pixels))
        assert (spp == spp[0]).all() and (offset == offset[0]).all()
        counts.append(int(spp[0]))
        patterns.append((pattern[0], int(offset[0])))
        return render_pixels(t_s, spp, seed, groups, pixels)

    r.render_pixels = render_pixels_counted
    out = refine(r, p, first, np.array([3, 9]), 4, np.random.SeedSequence(3), points=4)
    t = np.array(times).reshape(p.passes, 2, 4)
    part = (t - p.bounds_s[:, :1, None]) / (p.bounds_s[:, 1:, None] - p.bounds_s[:, :1, None]) * 4
    np.testing.assert_array_equal(np.floor(part), np.broadcast_to(np.arange(4), part.shape))
    assert np.array(counts).reshape(p.passes, 2, 4).sum(axis=(1, 2)).tolist() == (p.spp * 3).tolist()  # factor - 1
    # from shared patterns as the first pass (one per half, of their own): each half's renders take the
    # pattern's samples one after another over the strata and their times, so they are one sequence
    assert p.shares_pattern
    keys = np.array([k for k, _ in patterns]).reshape(p.passes, 2, 4)
    offsets = np.array([o for _, o in patterns]).reshape(p.passes, 2, 4)
    c = np.array(counts).reshape(p.passes, 2, 4)
    assert (
        (keys[:, 0] == keys[0, 0, 0]).all() and (keys[:, 1] == keys[0, 1, 0]).all() and keys[0, 0, 0] != keys[0, 1, 0]
    )
    for h in range(2):
        seq_offsets, seq_counts = offsets[:, h].ravel(), c[:, h].ravel()
        assert seq_offsets[0] == 0 and (seq_offsets[1:] == np.cumsum(seq_counts)[:-1]).all()
    flat = out.exposure.reshape(K, -1, 3)
    np.testing.assert_allclose(flat[:, [3, 9]], (before[:, [3, 9]] + 3 * second) / 4)
    # jittered, not fixed: the same quarter's times differ between the strata's halves
    assert np.all(t[:, 0] != t[:, 1])

    # pixels of different factors in the same renders, each with its own count and its own run of the pattern
    calls = []

    def render_pixels_mixed(t_s, spp, seed, groups, pixels, pattern=None, cached=False):
        calls.append(
            (
                np.asarray(pixels).copy(),
                np.broadcast_to(spp, len(pixels)).copy(),
                np.broadcast_to(pattern[1], len(pixels)).copy(),
            )
        )
        return np.ones((len(groups), len(pixels), 3), np.float32)

    r.render_pixels = render_pixels_mixed
    out = refine(r, p, first, np.array([3, 9]), np.array([2, 8]), np.random.SeedSequence(4))
    assert len(calls) == p.passes * 2 and all(c[0].tolist() == [3, 9] for c in calls)
    c = np.array([c[1] for c in calls]).reshape(p.passes, 2, 2)
    assert c.sum(axis=(1,)).T.tolist() == [(p.spp * 1).tolist(), (p.spp * 7).tolist()]
    offsets = np.array([c[2] for c in calls]).reshape(p.passes, 2, 2)
    for h in range(2):
        assert (offsets[1:, h] == np.cumsum(c[:, h], axis=0)[:-1]).all() and (offsets[0, h] == 0).all()
    flat = out.exposure.reshape(K, -1, 3)
    np.testing.assert_allclose(flat[:, 3], (before[:, 3] + second[:, 0]) / 2)
    np.testing.assert_allclose(flat[:, 9], (before[:, 9] + 7 * second[:, 0]) / 8)


def test_the_top_up_renders_at_times_of_its_own_and_says_which(monkeypatch):
    """render.top_up's second pass draws a time of its own for each half of each stratum: at the first
    pass's times it would repeat the first pass's time noise, which combining the passes could then
    not lower. The plan it returns lists every render's time with its weight in the combined
    exposure, and on a film that changes in time with no Monte Carlo noise those times and weights
    rebuild the combined exposure exactly (what flash matting's truth relies on)."""
    from types import SimpleNamespace

    from mbcapture.exposure.integrate import integrate
    from mbcapture.progress import StageStatus

    tl = timeline(periods=16)
    # render.pattern 'own': an independent second pass, weighed by inverse variance (the shared
    # pattern's, which continues the first pass, is the next test's)
    p = replace(plan(point_scene(100.0), tl, spp=4), pattern="own")
    mu = {g: 1.0 + i for i, g in enumerate(p.groups)}
    r = FakeRenderer(p.groups, mu, {g: 0.0 for g in p.groups}, height=2, width=8, slope=1e3)
    first = integrate(r, p, tl.n_buckets, np.random.SeedSequence(1))
    times, weights = p.exposure_time_mix()  # before a top-up: the two halves
    np.testing.assert_array_equal(times, p.render_times)
    np.testing.assert_array_equal(weights, p.render_time_shares())
    # the first pass 2x over the budget on J1, whose p95 ratio reads 2.0 there and 1.0 in the second (its
    # median 0.05 and 0.1): c = 2, from the figure that decided
    monkeypatch.setattr(
        adaptive,
        "over_budget",
        lambda integrated, timeline, cfg, *a, **k: (2.0, "J1", "to_shot_noise_variance_p95", 2.0),
    )
    monkeypatch.setattr(
        adaptive,
        "read_figures",
        lambda integrated, *a, **k: {
            "J1": {"to_shot_noise_variance_median": 0.05, "to_shot_noise_variance_p95": 2.0}
            if integrated is first
            else {"to_shot_noise_variance_median": 0.1, "to_shot_noise_variance_p95": 1.0}
        },
    )
    cfg = SimpleNamespace(render=SimpleNamespace(max_spp=1024))
    r.calls.clear()
    topped_plan, topped, info = adaptive.top_up(
        Passes(cfg, r, tl, np.random.SeedSequence(2), StageStatus(False), per_group=False, progress=False),
        p,
        first,
        why_not=None,
    )
    assert info["applied"] and info["weight"] == 2.0 and info["figure"] == "p95"
    t2 = np.array([c[0] for c in r.calls]).reshape(p.passes, 2)
    assert np.all(t2 >= p.bounds_s[:, :1]) and np.all(t2 < p.bounds_s[:, 1:])
    assert not np.isin(t2, p.render_times).any() and np.all(t2[:, 0] != t2[:, 1])
    times, weights = topped_plan.exposure_time_mix()
    np.testing.assert_array_equal(times, np.concatenate([p.render_times, t2], axis=1))
    # each pass's halves take half its samples: 1/3 of the weight to each first-pass half, 2/3 to each second's
    np.testing.assert_allclose(weights, np.tile([1 / 6, 1 / 6, 1 / 3, 1 / 3], (p.passes, 1)), rtol=1e-12)
    ramp = np.linspace(0, 1, 8) * 1e3
    radiance = np.array([[mu[g] + ramp * t for g in p.groups] for t in times.ravel()]).reshape(*times.shape, -1, 8)
    expected = np.einsum("jkg,jm,jmgx->kx", p.weights_s, weights, radiance)
    np.testing.assert_allclose(topped.exposure[:, 0, :, 0], expected, rtol=1e-6)
    strata = topped_plan.summary(tl)["strata"]
    assert [len(s["render_times_s"]) for s in strata] == [4] * p.passes
    assert sum(strata[0]["render_time_weights"]) == pytest.approx(1.0, abs=1e-5)
    # a stratum with no room under render.max_spp: not applied (the second pass must hold every stratum)
    cfg.render.max_spp = int(p.spp.max()) + 1
    same_plan, same, note = adaptive.top_up(
        Passes(cfg, r, tl, np.random.SeedSequence(2), StageStatus(False), per_group=False, progress=False),
        p,
        first,
        why_not=None,
    )
    assert same is first and same_plan is p and not note["applied"]
    assert note["note"] == f"render.max_spp={p.spp.max() + 1} reached in {p.passes} of {p.passes} strata"


def test_with_the_shared_pattern_the_top_up_continues_the_first_pass(monkeypatch):
    """With render.pattern 'shared' the top-up's second pass draws, in each half, the samples of the first
    pass's pattern after all of the first pass's (its keys, offsets from the first pass's totals on), so
    that the two passes weighed by their samples (c = n2 / n1) are one pass of n1 + n2; its size is
    n2 / n1 = F x margin - 1 (F: how far over the first pass was)."""
    from types import SimpleNamespace

    from mbcapture.exposure.integrate import integrate, render_patterns, stratum_halves
    from mbcapture.progress import StageStatus

    tl = timeline(periods=16)
    p = plan(point_scene(100.0), tl, spp=8)
    assert p.pattern == "shared"
    mu = {g: 1.0 + i for i, g in enumerate(p.groups)}
    r = FakeRenderer(p.groups, mu, {g: 1.0 for g in p.groups}, height=4, width=8)
    seed = np.random.SeedSequence(1)
    first = integrate(r, p, tl.n_buckets, seed)
    monkeypatch.setattr(
        adaptive,
        "over_budget",
        lambda integrated, timeline, cfg, *a, **k: (2.0, "J1", "to_shot_noise_variance_median", 0.2),
    )
    cfg = SimpleNamespace(render=SimpleNamespace(max_spp=1024))
    r.patterns.clear()
    topped_plan, topped, info = adaptive.top_up(
        Passes(cfg, r, tl, seed, StageStatus(False), per_group=False, progress=False), p, first, why_not=None
    )
    extra = np.array(info["spp_added"])
    assert info["applied"] and np.all(extra == 2 * int(np.ceil((2.0 * adaptive.TOP_UP_MARGIN - 1) * 8 / 2)))
    assert info["weight"] == pytest.approx(extra.sum() / p.spp.sum())
    firsts = render_patterns(p, seed)
    keys = [firsts[0][h][0] for h in range(2)]
    ends = [sum(n[h] for n in stratum_halves(p)) for h in range(2)]  # each half's samples in the first pass
    seconds = np.array(r.patterns).reshape(p.passes, 2, 2)  # (stratum, half, (key, offset))
    assert (seconds[:, :, 0] == keys).all()
    for h in range(2):
        assert list(seconds[:, h, 1]) == [ends[h] + j * extra[0] // 2 for j in range(p.passes)]


def test_max_strata_coarsens_and_says_so():
    p = plan(point_scene(500.0), timeline(periods=16), max_strata=8)
    assert p.passes == 8 and p.coarsened and "coarsened" in p.notes[0]


# --------------------------------------------------------------------------- naive planner, spp
class FakeRenderer:
    """Radiance mu_g(t) plus Gaussian noise of per-sample sigma_g: the mean of spp samples."""

    channels = ("R", "G", "B")

    def __init__(self, groups, mu, sigma, height=24, width=32, slope=0.0, sigma_map=None):
        self.groups, self.mu, self.sigma = tuple(groups), dict(mu), dict(sigma)
        self.height, self.width, self.slope = height, width, slope
        self.sigma_map = np.ones((height, width, 1)) if sigma_map is None else sigma_map[..., None]  # per-pixel factor
        self.calls, self.patterns = [], []

    def set_time(self, t_s, force=False):
        pass

    def render(self, t_s, spp, seed, groups=None, pattern=None):
        groups = tuple(self.groups if groups is None else groups)
        self.calls.append((t_s, spp, groups))
        self.patterns.append(pattern)
        rng = np.random.default_rng(seed)
        shape = (self.height, self.width, 3)
        ramp = np.linspace(0, 1, self.width)[None, :, None] * self.slope * t_s  # an image that changes in time
        return np.stack(
            [
                self.mu[g] + ramp + self.sigma[g] * self.sigma_map / np.sqrt(spp) * rng.standard_normal(shape)
                for g in groups
            ]
        ).astype(np.float32)


class BlockRenderer(FakeRenderer):
    """:class:`FakeRenderer` that also renders listed pixels (the pilot's blocks): the same pixels' values
    as its film, from the same seed."""

    renders_pixels_alone = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.pixel_calls = []

    def render_pixels(self, t_s, spp, seed, groups, pixels, pattern=None, cached=False):
        self.pixel_calls.append(np.asarray(pixels).copy())
        film = FakeRenderer.render(self, t_s, spp, seed, groups, pattern)
        self.calls.pop()  # counted as a render of pixels, not of the film
        return film.reshape(len(groups), -1, 3)[:, np.asarray(pixels)]


def test_the_block_mosaic_pools_each_block_at_its_centre():
    """The pilot on blocks lays them side by side: the 3x3 window of each block's centre in the mosaic is
    that block, so pooled() there is the block's mean, and the centres are the only samples it counts."""
    from mbcapture.budget import block_mosaic, block_pixels, mosaic_centres, pooled

    rng = np.random.default_rng(3)
    H, W = 30, 40
    film = rng.random((2, H, W, 3))
    centres = np.array([1 * W + 1, 4 * W + 10, 25 * W + 37, 13 * W + 19])
    px = block_pixels(centres, W)
    assert px.shape == (4, 9)
    mosaic = block_mosaic(film.reshape(2, -1, 3)[:, px.ravel()])
    assert mosaic.shape == (2, 3, 12, 3)
    centre = mosaic_centres(4)
    assert centre.sum() == 4 and centre[1, [1, 4, 7, 10]].all()
    for i, c in enumerate(centres):
        y, x = divmod(int(c), W)
        np.testing.assert_allclose(
            pooled(mosaic)[:, 1, 3 * i + 1], film[:, y - 1 : y + 2, x - 1 : x + 2].mean(axis=(1, 2))
        )


def test_a_large_film_is_piloted_on_a_random_sample_of_its_blocks(monkeypatch):
    """Above 2 x PILOT_BLOCKS lattice blocks the pilot renders PILOT_BLOCKS of them, whole, drawn at random
    (each at most once), and never the film; the samples it chooses still meet the closed form of
    test_noise_budget_spp_matches_the_closed_form. 600 blocks: the median of 600 pooled estimates of 9
    degrees of freedom has a spread of about DECONV_REL_SD / sqrt(600) = 12 % (the deconvolution's own
    scatter included); rounding up to the ladder adds up to 1.19x below."""
    from mbcapture import budget

    monkeypatch.setattr(budget.pilot, "PILOT_BLOCKS", 600)
    mu, sigma, k_e, f = 2.0, 3.0, 1e5, 0.1
    H, W = 72, 96  # 24 x 32 = 768 blocks: whole films up to 1200
    p0 = plan(point_scene(50.0), timeline(periods=16), spp=None)
    small = BlockRenderer(p0.groups, {g: mu for g in p0.groups}, {g: sigma for g in p0.groups}, H, W)
    whole = budget.choose_spp(p0, small, np.full(3, k_e), 1e12, f, 1 << 14, np.random.SeedSequence(5))
    assert small.pixel_calls == [] and whole.pilot["blocks"] is None and whole.pilot["film_share"] == 1.0

    H, W = 150, 192  # 50 x 64 = 3200 blocks
    r = BlockRenderer(p0.groups, {g: mu for g in p0.groups}, {g: sigma for g in p0.groups}, H, W)
    p = budget.choose_spp(p0, r, np.full(3, k_e), 1e12, f, 1 << 14, np.random.SeedSequence(5))
    assert r.calls == [] and len(r.pixel_calls) == p.pilot["renders"]
    px = r.pixel_calls[0].reshape(-1, 9)
    centres = px[:, 4]
    assert all(np.array_equal(c, r.pixel_calls[0]) for c in r.pixel_calls)  # the same blocks at every count
    assert p.pilot["blocks"] == 600 == np.unique(centres).size
    assert p.pilot["film_share"] == pytest.approx(600 * 9 / (H * W), abs=1e-4)
    y, x = np.divmod(centres, W)
    assert np.all(y % 3 == 1) and np.all(x % 3 == 1) and y.max() <= H - 2 and x.max() <= W - 2  # the lattice
    offsets = np.array([-W - 1, -W, -W + 1, -1, 0, 1, W - 1, W, W + 1])  # each block whole, row-major
    np.testing.assert_array_equal(px - centres[:, None], np.broadcast_to(offsets, px.shape))
    w = read_weights(p0)
    ratio = max((k_e**2 * w[:, k] ** 2 * sigma**2 / p.spp).sum() / (k_e * (w[:, k] * mu).sum()) for k in range(4))
    assert f * 0.88 / 1.19 <= ratio <= f * 1.12
    # the cost model stands for a pass over the film: a sample of a pixel costs what the film's does
    assert p.cost["c1_s_per_spp"] > 0

    # a region 20x noisier over 10 % of the film: the 95th percentile binds (as in
    # test_noise_budget_targets_the_median_and_the_95th_percentile), in the middle of the region's
    # estimates, which the blocks sample as the film holds them
    sigma_map = np.ones((H, W))
    side = int(round(np.sqrt(0.10 * H * W)))
    sigma_map[20 : 20 + side, 30 : 30 + side] = 20.0
    mu = 20.0
    r = BlockRenderer(p0.groups, {g: mu for g in p0.groups}, {g: sigma for g in p0.groups}, H, W, sigma_map=sigma_map)
    p = budget.choose_spp(p0, r, np.full(3, k_e), 1e12, f, 1 << 14, np.random.SeedSequence(5))
    assert r.calls == [] and p.pilot["blocks"] == 600
    calm = max((k_e**2 * w[:, k] ** 2 * sigma**2 / p.spp).sum() / (k_e * (w[:, k] * mu).sum()) for k in range(4))
    assert calm * 400 == pytest.approx(1.0, rel=0.3)


def test_naive_plan_renders_every_slot_of_every_period():
    tl = timeline(periods=8)  # photon-efficient HDR: 4 slots per period, each to its own bucket
    scene = point_scene(50.0)
    naive = plan(scene, tl, planner="naive", spp=2)
    motion = plan(scene, tl, spp=2)
    assert naive.passes == 8 * 4 and naive.planner == "naive"
    assert np.all((naive.weights_s.sum(axis=2) > 0).sum(axis=1) == 1)  # one bucket per slot
    assert naive.weights_s.sum(axis=0) == pytest.approx(motion.weights_s.sum(axis=0), rel=1e-12)
    assert naive.spp.tolist() == [2] * 32


def test_explicit_spp_wins_and_null_spp_waits_for_the_pilot():
    from mbcapture.budget import resolve_spp

    p = plan(point_scene(None), timeline(), spp=8)
    assert p.spp.tolist() == [8] and p.spp_source == "render.spp"
    cfg = config_from_dict({"scene": {"name": "flatfield"}, "render": {"spp": 8}})
    assert resolve_spp(p, renderer=None, cfg=cfg, seed=np.random.SeedSequence(0)) is p  # no pilot render
    q = plan(point_scene(None), timeline(), spp=None)
    assert q.spp is None and q.spp_source == "pending" and q.summary(timeline())["spp"] is None


def read_weights(p) -> np.ndarray:
    """(J, R) the one group's weights of each read: the sum of its buckets'."""
    return np.stack([p.weights_s[:, list(r), 0].sum(axis=1) for r in p.read_sets], axis=1)


def _budget_plan(
    mu,
    sigma,
    k_e=np.array([1e5, 1e5, 1e5]),
    budget=0.1,
    max_spp=1 << 14,
    speed=50.0,
    sigma_map=None,
    budget_p95=1.0,
    size=(24, 32),
):
    tl = timeline(periods=16)
    p = plan(point_scene(speed), tl, spp=None)
    r = FakeRenderer(p.groups, {g: mu for g in p.groups}, {g: sigma for g in p.groups}, *size, sigma_map=sigma_map)
    from mbcapture.budget import choose_spp

    return p, choose_spp(p, r, k_e, 1e12, budget, max_spp, np.random.SeedSequence(5), noise_budget_p95=budget_p95), r


def test_noise_budget_spp_matches_the_closed_form():
    # one always-on group (the unused flash is left out), Gaussian noise: per bucket k
    # MC variance (e-^2) = sum_j k_e^2 w_jk^2 sigma^2 / n_j,  shot variance = k_e sum_j w_jk mu, for each
    # READ k: its weights are its buckets' sums (the buckets' Monte Carlo errors come from the same renders)
    mu, sigma, k_e, f = 2.0, 3.0, 1e5, 0.1
    p0, p, r = _budget_plan(mu, sigma, budget=f)
    assert p.groups == ("ambient",)
    assert p.spp_source == "noise_budget" and p.spp.min() > 20 and np.all(p.spp % 2 == 0)  # well above the floor of 2
    w = read_weights(p0)  # (J, R)
    ratios = [(k_e**2 * w[:, k] ** 2 * sigma**2 / p.spp).sum() / (k_e * (w[:, k] * mu).sum()) for k in range(4)]
    # the longest read (J4, all four buckets) binds; its ratio is 8x that of the shortest
    assert int(np.argmax(ratios)) == 3
    # uniform noise: every pixel has this ratio, so the median target binds. The pilot's median
    # comes from 2304 pooled estimates of 9 degrees of freedom (their spread near the median is
    # ~sqrt(2/9) / sqrt(2304 / 9) = 3 %, 5 sd = 15 %); rounding n_j up (to a ladder of 19 % steps,
    # so that strata share few sample counts) only lowers it, by at most 1/1.19
    assert max(ratios) <= f * 1.15
    assert max(ratios) >= f * 0.85 / 1.19  # the binding bucket meets it, not far below
    # independent Gaussian samples: the measured convergence exponent is 1 (median 4x lower at 4x spp)
    k = int(np.argmax(ratios))
    at = list(p.pilot["per_read"].values())[k]["median_at"]
    lo, hi = sorted(at)
    assert at[lo] / at[hi] == pytest.approx(hi / lo, rel=0.15)
    assert p.pilot["renders"] == 4 * p.pilot["times"] and p.cost["c1_s_per_spp"] > 0
    assert len(r.calls) == p.pilot["renders"]  # the pilot renders nothing else


@pytest.mark.parametrize("noisy_fraction", [0.02, 0.15])
def test_noise_budget_targets_the_median_and_the_95th_percentile(noisy_fraction):
    """A region 20x noisier (a highlight, a lamp): below 5 % of the samples it does not raise the
    spp (a mean target would, ~8x); above 5 % the 95th percentile binds instead of the median.
    (The pilot pools variance over 3x3 pixels, so the noise is spatially coherent here, as it is
    in renders; salt-and-pepper noise of single pixels would be smeared by the pooling.)"""
    mu, sigma, k_e, f = 20.0, 3.0, 1e5, 0.1
    H, W = 48, 64
    sigma_map = np.ones((H, W))
    side = int(round(np.sqrt(noisy_fraction * H * W)))
    sigma_map[10 : 10 + side, 20 : 20 + side] = 20.0
    p0, p, _ = _budget_plan(mu, sigma, budget=f, sigma_map=sigma_map, size=(H, W))
    w = read_weights(p0)
    calm = max((k_e**2 * w[:, k] ** 2 * sigma**2 / p.spp).sum() / (k_e * (w[:, k] * mu).sum()) for k in range(4))
    if noisy_fraction < 0.05:
        assert calm == pytest.approx(f, rel=0.2)  # the median pixel meets the budget exactly
    else:
        # p95 binds: the noisy pixels (400x the variance) sit at the 1.0 target, the calm ones far below
        assert calm * 400 == pytest.approx(1.0, rel=0.3)
        assert calm < f / 2


def test_dim_scene_gets_fewer_samples_and_the_cap_holds():
    _, bright, _ = _budget_plan(2.0, 3.0)
    _, dim, _ = _budget_plan(0.2, 0.3)  # the same scene 10x dimmer: MC var /100, shot var /10
    assert dim.spp.sum() == pytest.approx(bright.spp.sum() / 10, rel=0.2)
    _, capped, _ = _budget_plan(2.0, 3.0, max_spp=64)
    assert capped.spp.max() == 64 and any("max_spp" in n for n in capped.notes)


def test_no_stratum_gets_fewer_samples_than_the_pilot_measured():
    """A scene so clean that the rule asks for ~1 sample: every stratum still gets the pilot's
    smaller count (2 x 4), where the ratio was measured (below it the convergence exponent is only
    extrapolated, and quasi-Monte Carlo samples converge differently at 1-2 samples)."""
    from mbcapture.budget import PILOT_SPP

    _, clean, _ = _budget_plan(2.0, 0.05)
    assert np.all(clean.spp == 2 * PILOT_SPP[0]), clean.spp
    assert clean.pilot["uncapped_spp_max"] == pytest.approx(2 * PILOT_SPP[0])


def test_sample_count_ladder_takes_counts_the_sampler_keeps():
    """The pilot's counts step along a ladder of 2.2 % steps, each point moved down to a count the sampler
    takes as asked: multijitter rounds 91 up to 99 (9 x 11), so asking it for the ladder's 91 would
    render 9 % more samples than the ladder meant; 90 (9 x 10) it takes as it is."""
    from mbcapture.budget import LADDER_STEPS, ladder

    def multijitter(m: int) -> int:  # Mitsuba's rule: floor(sqrt(m)) columns, as many rows as m needs
        cols = int(np.floor(np.sqrt(m)))
        return cols * -(-m // cols)

    assert multijitter(91) == 99 and multijitter(90) == 90 and multijitter(128) == 132  # the rule as Mitsuba has it
    assert ladder(86.3, multijitter) == 90
    step = 2 ** (1 / LADDER_STEPS)
    for x in np.geomspace(4.5, 5000, 400):
        n = ladder(x, multijitter)
        assert multijitter(n) == n and n >= x, (x, n)
        # at most two steps over x (the next ladder point, or the one after where no kept count lies
        # between), or one over the first count the sampler keeps, where those are sparse (12 after 9)
        first = next(m for m in range(int(np.ceil(x)), 10 * int(x)) if multijitter(m) == m)
        assert n <= max(x * step**2, first * step) + 1, (x, n)
    # few distinct counts: one per ladder point
    values = {ladder(x, multijitter) for x in np.geomspace(4.5, 5000, 4000)}
    assert len(values) <= LADDER_STEPS * np.log2(5000 / 4.5) + 2
    assert ladder(86.3) == 87  # every count as it is (the shared pattern's renders): the ladder's own point


def test_per_stratum_spp_follows_the_weights():
    """Neyman allocation per stratum. An accelerating point makes strata of very different lengths
    (the first, slow one ~7x the last), so their weights differ. With one group of per-sample
    sigma and mean mu everywhere, read k asks stratum j for n_jk = w_jk sigma^2 k_e / (f mu)
    samples, w_jk the read's weight (its buckets' sum) (the module's rule: sqrt(a_jk) sum_j sqrt(a_jk) / V_k,
    a_jk = w_jk^2 sigma^2 k_e^2 per sample, V_k = f k_e mu sum_j w_jk), and the stratum gets max_k n_jk, each half rounded up to the
    sampler's ladder of counts (steps of 9 %). The buckets' totals differ (T, 2T, 4T, 8T), so
    a rule that dropped V_k would over-sample the strata the short bucket weighs most. The
    pilot estimates sigma^2 from 2304 samples per pilot time: relative SE sqrt(2/2304) = 3 %, so
    5 SE = 15 %."""
    acc_m_per_s2 = 1e4

    def motion(t):
        t = np.asarray(t)
        return np.stack([0.5 * acc_m_per_s2 * t**2, 0 * t, 0 * t], -1)[:, None, :]

    scene = SceneModel(
        "test", ("ambient", "flash"), frozenset({"flash"}), CAM, build=None, params=None, motion_points=motion
    )
    tl = timeline(periods=16)
    p0 = plan(scene, tl, spp=None)
    mu, sigma, k_e, f = 2.0, 3.0, 1e5, 0.1
    r = FakeRenderer(p0.groups, {g: mu for g in p0.groups}, {g: sigma for g in p0.groups})
    from mbcapture.budget import choose_spp

    p = choose_spp(p0, r, np.full(3, k_e), 1e12, f, 1 << 14, np.random.SeedSequence(5))
    w_jk = read_weights(p0)  # each read's weights: its buckets' sums
    w = p0.weights_s[:, :, 0].sum(axis=1)
    assert p0.passes >= 10 and w.max() > 5 * w.min()  # strata of very different weight
    n_true = w_jk.max(axis=1) * sigma**2 * k_e / (f * mu)
    assert n_true.min() > 100  # far above the floor of 2 samples: the rule, not the floor, decides
    from mbcapture.budget import ladder

    upper = np.array([2 * ladder(1.15 * n / 2) for n in n_true])  # each half rounded up to the ladder (9 % steps)
    assert np.all(p.spp >= 0.85 * n_true) and np.all(p.spp <= upper), np.c_[p.spp, n_true]
    # the heaviest stratum gets several times the samples of the lightest
    assert p.spp[np.argmax(w)] > 3 * p.spp[np.argmin(w)]


def test_integrate_per_stratum_spp_is_unbiased_and_its_error_estimate_is_right():
    from mbcapture.exposure.integrate import integrate

    tl = timeline(periods=16)
    p = plan(point_scene(50.0), tl, spp=2)
    spp = np.array([2, 4, 8, 16, 32, 6, 10, 12][: p.passes] * (p.passes // 8 + 1))[: p.passes]
    p = replace(p, spp=spp)
    mu, sigma = 2.0, 3.0
    r = FakeRenderer(p.groups, {g: mu for g in p.groups}, {g: sigma for g in p.groups}, height=48, width=64)
    out = integrate(r, p, tl.n_buckets, np.random.SeedSequence(1))
    w = p.weights_s  # (J, K, G)
    expect = w.sum(axis=(0, 2)) * mu
    true_var = (w**2 * sigma**2 / spp[:, None, None]).sum(axis=(0, 2))  # (K,)
    n = 48 * 64 * 3
    for k in range(4):
        assert out.exposure[k].mean() == pytest.approx(expect[k], abs=5 * np.sqrt(true_var[k] / n))
        assert out.exposure[k].var() == pytest.approx(true_var[k], rel=5 * np.sqrt(2 / n))
        assert out.mc_var[k].mean() == pytest.approx(true_var[k], rel=5 * np.sqrt(2 / n))
    # renders: two halves per stratum, only the groups with weight
    assert len(r.calls) == 2 * p.passes
    # the two error estimates are kept in float32 (half a large film's memory for them), their squares in float64
    assert out.exposure.dtype == np.float64 and out.mc_var.dtype == np.float64
    assert out.mc_diff.dtype == out.temporal_diff.dtype == np.float32
    assert out.mc_diff.nbytes == out.temporal_diff.nbytes == out.exposure.nbytes // 2


def test_a_reads_monte_carlo_variance_adds_its_buckets_errors_coherently():
    """A read sums buckets rendered from the same strata: their Monte Carlo errors add as amplitudes,
    Var = sum_j (sum_k w_jk)^2 sigma^2 / n_j, not as variances (sum_j sum_k w_jk^2 sigma^2 / n_j); the
    half-sample estimate (Integrated.read_mc_var) must say the first, and render_error must judge reads."""
    from mbcapture.budget import render_error
    from mbcapture.exposure.integrate import integrate

    tl = timeline(periods=16)
    p = replace(plan(point_scene(50.0), tl, spp=2), spp=None)
    p = replace(p, spp=np.full(p.passes, 8))
    mu, sigma = 2.0, 3.0
    r = FakeRenderer(p.groups, {g: mu for g in p.groups}, {g: sigma for g in p.groups}, height=48, width=64)
    out = integrate(r, p, tl.n_buckets, np.random.SeedSequence(2))
    n = 48 * 64 * 3
    w = p.weights_s[:, :, 0]
    for read in p.read_sets:
        coherent = (w[:, list(read)].sum(axis=1) ** 2 * sigma**2 / p.spp).sum()
        incoherent = (w[:, list(read)] ** 2 * sigma**2 / p.spp[:, None]).sum()
        got = out.read_mc_var(read).mean()
        assert got == pytest.approx(coherent, rel=5 * np.sqrt(2 / n))
        if len(read) > 1:
            assert coherent > 1.5 * incoherent
    # render_error: one entry per read, the longest (J4, all buckets) decides, its ratio ~ its closed form
    k_e = np.full(3, 1e5)
    buckets_e = out.exposure * k_e
    rep = render_error(out.mc_diff, buckets_e, k_e, list(p.read_sets), list(p.read_names), 1e12, 4e12)
    assert list(rep["reads"]) == list(p.read_names) and rep["deciding_read"] == p.read_names[-1]
    longest = list(p.read_sets[-1])
    want = k_e[0] ** 2 * (w[:, longest].sum(axis=1) ** 2 * sigma**2 / p.spp).sum() / (k_e[0] * w[:, longest].sum() * mu)
    assert rep["to_shot_noise_variance_mean"] == pytest.approx(want, rel=0.1)
    ratios = [rep["reads"][n_]["to_shot_noise_variance_median"] for n_ in p.read_names]
    assert ratios == sorted(ratios)  # the ratio grows with the read's exposure


def test_temporal_error_sees_change_in_time_and_not_noise():
    from mbcapture.exposure.integrate import integrate, temporal_error

    tl = timeline(periods=16)
    p = plan(point_scene(50.0), tl, spp=16)
    k_e = np.array([1e4, 1e4, 1e4])
    still = FakeRenderer(p.groups, {g: 1.0 for g in p.groups}, {g: 0.5 for g in p.groups})
    moving = FakeRenderer(p.groups, {g: 1.0 for g in p.groups}, {g: 0.5 for g in p.groups}, slope=200.0)
    e_still = temporal_error(integrate(still, p, 4, np.random.SeedSequence(2)), k_e, [0, 1, 2, 3], 1e12)
    e_moving = temporal_error(integrate(moving, p, 4, np.random.SeedSequence(2)), k_e, [0, 1, 2, 3], 1e12)
    assert e_moving["temporal_rel_rms_coarse"] > 5 * e_still["temporal_rel_rms_coarse"]
    assert e_still["temporal_rel_rms_coarse"] < 0.3 * e_still["temporal_raw_rel_rms_coarse"]
    one = replace(plan(point_scene(None), tl, spp=4))
    single = temporal_error(integrate(still, one, 4, np.random.SeedSequence(3)), k_e, [0], 1e12)
    assert single["temporal_rel_rms_estimate"] is None and "not measured" in single["temporal_method"]
    assert e_moving["temporal_resolved"] and "temporal_note" not in e_moving
