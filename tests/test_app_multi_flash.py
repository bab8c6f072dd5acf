"""Multi-flash: protocol, epipoles, Raskar depth edges, ground-truth edges and metrics on small
synthetic inputs with known answers; one tiny render comparing interleaved and sequential."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.scene import scenes
from mbcapture.apps import multi_flash as mf
from mbcapture.reconstruct import depth_edges as de
from mbcapture.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "multi_flash.yaml"

# ---------------------------------------------------------------- synthetic scene with known edges
H, W = 40, 48
R0, R1, C0, C1 = 10, 19, 12, 21  # foreground square, inclusive rows/cols
SHADOW_PX = 3  # shadow width beside the square, px
INDIRECT = 0.05  # light left in a shadow, relative to direct


def _square_scene(seed=0):
    """Flash images (4, H, W, 3) in protocol order (top, bottom, left, right), an albedo map that
    varies per pixel, the epipoles of LEDs in the lens plane, and the true depth-edge map (the
    square's border pixels: the occluding side)."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 0.9, size=(H, W, 3))
    fg = np.zeros((H, W), bool)
    fg[R0 : R1 + 1, C0 : C1 + 1] = True
    shadows = {  # shadow cast on the wall on the side away from each LED
        "top": (slice(R1 + 1, R1 + 1 + SHADOW_PX), slice(C0, C1 + 1)),
        "bottom": (slice(R0 - SHADOW_PX, R0), slice(C0, C1 + 1)),
        "left": (slice(R0, R1 + 1), slice(C1 + 1, C1 + 1 + SHADOW_PX)),
        "right": (slice(R0, R1 + 1), slice(C0 - SHADOW_PX, C0)),
    }
    dirs = {"top": (0.0, -1.0), "bottom": (0.0, 1.0), "left": (-1.0, 0.0), "right": (1.0, 0.0)}
    images = []
    for name in ("top", "bottom", "left", "right"):
        light = np.ones((H, W))
        light[fg] = 1.6  # the foreground is nearer the LEDs: brighter
        light[shadows[name]] = INDIRECT
        images.append(albedo * light[..., None])
    truth = (
        fg & ~np.pad(fg, 1)[2:, 1:-1]
        | fg & ~np.pad(fg, 1)[:-2, 1:-1]
        | fg & ~np.pad(fg, 1)[1:-1, 2:]
        | fg & ~np.pad(fg, 1)[1:-1, :-2]
    )
    return np.stack(images), [de.Epipole(False, dirs[n]) for n in ("top", "bottom", "left", "right")], truth, fg


def test_raskar_finds_exactly_the_occluding_border_of_a_square():
    images, epipoles, truth, fg = _square_scene()
    det = de.raskar_depth_edges(images, epipoles, step_threshold=0.3)
    assert truth.sum() == 2 * (R1 - R0 + 1) + 2 * (C1 - C0 + 1) - 4
    np.testing.assert_array_equal(det.edges, truth)
    # each LED finds the side away from it: the left LED the square's right column, and so on
    np.testing.assert_array_equal(np.flatnonzero(det.per_flash[2].any(axis=0)), [C1])
    np.testing.assert_array_equal(np.flatnonzero(det.per_flash[0].any(axis=1)), [R1])
    # ratios are albedo-free: 1 on lit pixels, INDIRECT / 1 in shadows
    assert np.allclose(det.ratios[2][R0 : R1 + 1, C1 + 1 : C1 + 1 + SHADOW_PX], INDIRECT)
    assert np.allclose(det.ratios[2][fg], 1.0)
    # the max composite has no shadow left
    assert np.allclose(de.max_composite(images), images.max(axis=0))
    assert mf.luminance(de.max_composite(images)).min() > 0.1


def test_raskar_traversal_direction_matters():
    """Traversing towards the epipole instead sees the shadow's far end (a rise), not a depth edge."""
    images, epipoles, truth, _ = _square_scene()
    flipped = [de.Epipole(False, tuple(-v for v in e.xy)) for e in epipoles]
    det = de.raskar_depth_edges(images, flipped, step_threshold=0.3)
    assert not (det.edges & truth).any()  # every mark is at the shadow's far end, off the square


def test_raskar_with_noise_keeps_precision_and_recall():
    images, epipoles, truth, _ = _square_scene(seed=3)
    rng = np.random.default_rng(7)
    # 3 % Gaussian noise: a false step of 0.3 is a 7-sigma event for the ratio difference
    noisy = images * (1 + 0.03 * rng.standard_normal(images.shape))
    det = de.raskar_depth_edges(noisy, epipoles, step_threshold=0.3)
    s = de.edge_scores(det.edges, truth, 1.0)
    assert s["precision"] == 1.0 and s["recall"] == 1.0


def test_dark_or_saturated_pixels_carry_no_edges():
    images, epipoles, truth, _ = _square_scene()
    bad = np.zeros((H, W), bool)
    bad[:, C1] = True  # the square's right column saturated: the left LED's edge is lost there
    det = de.raskar_depth_edges(images, epipoles, step_threshold=0.3, bad=bad)
    assert not det.edges[:, C1].any() and (det.edges == (truth & ~bad)).all()
    dark = images.copy()
    dark[:, :, :5] = 0.0
    det = de.raskar_depth_edges(dark, epipoles, min_signal_fraction=0.05)
    assert not det.valid[:, :5].any() and det.valid[:, 5:].all()


def test_flash_images_subtract_the_ambient_read_in_radiance_units():
    rng = np.random.default_rng(1)
    k_e = np.array([1.0e6, 2.0e6, 1.5e6])
    flash = rng.uniform(0.5, 2.0, size=(4, 3, 5, 3))
    ambient = rng.uniform(0.0, 0.3, size=(3, 5, 3))
    exposure = np.array([1e-3, 1e-3, 1e-3, 1e-3, 2e-3])  # the ambient read may be longer
    reads = np.concatenate([(flash + ambient) * k_e * 1e-3, (ambient * k_e * 2e-3)[None]])
    got = mf.flash_images(reads, exposure, k_e, [0, 1, 2, 3], 4)
    np.testing.assert_allclose(got, flash, rtol=1e-12)
    kept = mf.flash_images(reads, exposure, k_e, [0, 1, 2, 3], None)
    np.testing.assert_allclose(kept, flash + ambient, rtol=1e-12)


def test_depth_discontinuities_mark_the_near_side_only():
    _, _, truth, fg = _square_scene()
    z = np.where(fg, 1.0, 2.0)
    np.testing.assert_array_equal(de.depth_discontinuities(z, 0.05), truth)
    # a slanted plane changes depth smoothly (1 % per pixel): no edge at a 5 % threshold
    slope = 1.0 + 0.01 * np.arange(W)[None, :] + np.zeros((H, 1))
    assert not de.depth_discontinuities(slope, 0.05).any()
    assert de.depth_discontinuities(slope, 0.005).sum() == H * (W - 1)  # each pixel nearer than its right neighbour
    # nothing behind (inf): the surface's border is an edge, the empty pixels are not
    z_inf = np.where(fg, 1.0, np.inf)
    np.testing.assert_array_equal(de.depth_discontinuities(z_inf, 0.05), truth)


def test_edge_scores_by_hand():
    truth = np.zeros((10, 10), bool)
    truth[5, 2:8] = True  # 6 true pixels
    det = np.zeros_like(truth)
    det[6, 2:6] = True  # 4 detections 1 px below the line
    det[0, 0] = True  # 1 far away
    s = de.edge_scores(det, truth, 1.0)
    assert s["precision"] == pytest.approx(4 / 5)
    # true pixels within 1 px of a detection: columns 1..6 (2..5 directly, 6 is sqrt(2) > 1 away from (6,5))
    assert s["recall"] == pytest.approx(4 / 6)
    assert s["f1"] == pytest.approx(2 * 0.8 * (4 / 6) / (0.8 + 4 / 6))
    s = de.edge_scores(det, truth, 1.5)
    assert s["recall"] == pytest.approx(5 / 6)  # (5,6) is sqrt(2) from (6,5)
    assert de.edge_scores(det, truth, 0.5)["precision"] == 0.0
    none = de.edge_scores(np.zeros_like(truth), truth, 1.0)
    assert none["precision"] is None and none["recall"] == 0.0
    masked = de.edge_scores(det, truth, 1.0, mask=np.arange(10)[None, :] >= 4 + np.zeros((10, 1)))
    assert masked["detected_px"] == 2 and masked["precision"] == 1.0


def test_shadow_metrics_find_a_kept_shadow():
    images, _, _, _ = _square_scene()
    m = mf.shadow_metrics(de.max_composite(images), images)
    assert m["residual_shadow_fraction"] == 0.0 and m["residual_shadow_mean"] == pytest.approx(0.0, abs=1e-12)
    # taking one flash image as "shadow-free" keeps that LED's shadow: 1/4 of the shadowed pixels
    m = mf.shadow_metrics(images[0], images)
    assert m["shadowed_px"] == 4 * SHADOW_PX * (R1 - R0 + 1)
    assert m["residual_shadow_fraction"] == pytest.approx(0.25)
    assert m["residual_shadow_mean"] == pytest.approx(0.25 * (1 - INDIRECT))


def test_canny_baseline_finds_texture_edges_too():
    images, epipoles, truth, _ = _square_scene()
    flat = np.ones_like(images)
    flat[:, :, : W // 2] *= 0.3  # an albedo edge on the wall: no depth edge, no shadow
    flat[:, R0 : R1 + 1, C0 : C1 + 1] *= 1.0
    p = mf.MultiFlashParams(method="canny_max_composite")
    det = mf.depth_edges(flat, epipoles, np.zeros((H, W), bool), p)
    assert det.ratios is None and det.edges[:, W // 2 - 1 : W // 2 + 1].any()
    assert not mf.depth_edges(flat, epipoles, np.zeros((H, W), bool), mf.MultiFlashParams()).edges.any()


def test_unknown_method_lists_the_registry():
    with pytest.raises(ConfigError, match=r"app.method: .*canny_max_composite.*raskar2004"):
        mf.depth_edges(np.ones((4, 3, 3, 3)), [], np.zeros((3, 3), bool), mf.MultiFlashParams(method="nope"))


# ---------------------------------------------------------------- epipoles
def test_epipoles_of_the_scene_leds_are_at_infinity_along_rows_and_columns():
    mod = scenes.load_module("multiflash")
    sc = mod.make(mod.Params())
    got = {g: de.epipole(sc.camera, p, 160, 128) for g, p in sc.extra["flash_positions_m"].items()}
    want = {"flash_top": (0, -1), "flash_bottom": (0, 1), "flash_left": (-1, 0), "flash_right": (1, 0)}
    for g, e in got.items():
        assert not e.finite
        np.testing.assert_allclose(e.xy, want[g], atol=1e-9)


@pytest.mark.parametrize("z_led", [0.3, -0.3])
def test_finite_epipole_points_shadows_the_right_way(z_led):
    """A light in front of (or behind) the lens: the image of a shadow point lies on the side of
    the occluder given by Epipole.away()."""
    cam = scenes.Camera(origin=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=40.0)
    light = np.array([0.15, -0.1, 2.0 - z_led])
    e = de.epipole(cam, light, 64, 48)
    assert e.finite and e.sign == (1 if z_led > 0 else -1)
    away = e.away(48, 64)
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(0.0, 0.8)])
        s = x + 0.2 * (x - light) / np.linalg.norm(x - light)  # further along the light's ray: in shadow
        px, ps = cam.project(np.stack([x, s]), 64, 48)
        if not (0 <= px[0] < 64 and 0 <= px[1] < 48):
            continue
        v = ps - px
        d = away[int(px[1]), int(px[0])]
        assert v @ d > 0.99 * np.linalg.norm(v)  # same direction (the pixel grid quantizes the start)


# ---------------------------------------------------------------- protocol
def test_protocol_buckets_reads_and_sequential_frames():
    tl = protocols.build(load_config(CONFIG, ["sensor.bucket_count=5"]))
    assert [r.name for r in tl.reads] == ["top", "bottom", "left", "right", "ambient"]
    assert [mf.read_groups(tl, r) for r in tl.reads] == [{g} for g in mf.FLASH_GROUPS] + [frozenset()]
    assert len({tl.read_exposure_ticks(r) for r in tl.reads}) == 1  # T each
    c = [tl.centroid_ticks(r.buckets) for r in tl.reads]
    assert float((max(c) - min(c)) * tl.tick_s) == pytest.approx(4 * 1e-3 / 16)  # 4 slots apart: within one period
    tl4 = protocols.build(load_config(CONFIG, ["sensor.bucket_count=4"]))
    assert [r.name for r in tl4.reads] == ["top", "bottom", "left", "right"]
    seq = protocols.build(load_config(CONFIG, ["capture.sequential=true"]))
    assert seq.sequential and [mf.read_groups(seq, r) for r in seq.reads] == [{g} for g in mf.FLASH_GROUPS] + [
        frozenset()
    ]
    c = [seq.centroid_ticks(r.buckets) for r in seq.reads]
    assert float((c[1] - c[0]) * seq.tick_s) == pytest.approx(1e-3 + 0.0333333)
    with pytest.raises(ConfigError, match="sensor.bucket_count"):
        protocols.build(load_config(CONFIG, ["sensor.bucket_count=3"]))


def test_config_keys_are_validated():
    with pytest.raises(ConfigError, match="app.step_threshold"):
        load_config(CONFIG, ["app.step_threshold=1.5"])
    with pytest.raises(ConfigError, match="app"):
        load_config(CONFIG, ["app.no_such_key=1"])


# ---------------------------------------------------------------- tiny renders
TINY = [
    "render.width=80",
    "render.height=64",
    "render.spp=4",
    "app.truth_spp=8",
    "render.max_motion_px=1.0",
    "render.min_strata=1",
]


@pytest.mark.render
def test_aov_depth_is_the_scene_geometry():
    from mbcapture.render import Renderer
    from mbcapture.render.aov import render_depth

    mod = scenes.load_module("multiflash")
    sc = mod.make(mod.Params())
    r = Renderer(sc, 80, 64)
    d = render_depth(r, 0.0)
    assert d.z_m[0, 0] == pytest.approx(1.0, abs=1e-5)  # the wall, camera 1 m away
    assert np.isfinite(d.distance_m).all() and (d.distance_m >= d.z_m).all()
    for t in (0.0, 0.05):  # the slider's front face (z = 0.40: 0.60 m) follows it
        px = sc.camera.project(sc.motion_points(np.array([t]))[0, -1], 80, 64)
        d = render_depth(r, t)
        assert d.z_m[int(px[1]), int(px[0])] == pytest.approx(0.60, abs=1e-5)
        assert d.time_s == t


@pytest.mark.render
def test_interleaved_beats_sequential_on_the_moving_scene():
    from mbcapture import run_capture

    inter = run_capture(load_config(CONFIG, TINY), progress=False)
    seq = run_capture(load_config(CONFIG, TINY + ["capture.sequential=true"]), progress=False)
    mi, ms = inter.report["metrics"], seq.report["metrics"]
    # each is scored against the scene at its own capture's mid-time: the same objects, the box elsewhere
    assert mi["truth"]["time_s"] == pytest.approx(inter.timeline.seconds(inter.timeline.end_tick) / 2)
    assert ms["truth"]["time_s"] == pytest.approx(seq.timeline.seconds(seq.timeline.end_tick) / 2)
    ti, ts = mi["depth_edges"]["all"]["true_px"], ms["depth_edges"]["all"]["true_px"]
    assert ti > 100 and abs(ti - ts) <= 0.05 * ti
    assert mi["depth_edges"]["all"]["f1"] > 0.85
    assert mi["depth_edges"]["all"]["f1"] > ms["depth_edges"]["all"]["f1"]
    assert mi["shadow_free"]["rel_mse"] < 0.5 * ms["shadow_free"]["rel_mse"]
    img = inter.images
    assert img["shadow_free"].shape == (64, 80, 3) and img["depth_edges"].shape == (64, 80)
    assert {"ratio_top", "ratio_left", "flash_right", "shadow_free_truth", "edges_overlay"} <= set(img)


def test_step_span_catches_a_two_pixel_shadow_onset():
    row = np.array([1.0, 1.0, 1.0, 0.5, 0.05, 0.05, 0.05, 1.0, 1.0, 0.05, 1.0, 1.0])  # onset at 2..4; 1-px shadow at 9
    img = np.repeat(np.tile(row, (3, 1))[None, ..., None], 3, -1)
    lit = np.ones_like(img)
    images = np.concatenate([img, lit])  # flash 0 from the left casts the shadows; flash 1 lights everything
    eps = [de.Epipole(False, (-1.0, 0.0)), de.Epipole(False, (1.0, 0.0))]
    one = de.raskar_depth_edges(images, eps, step_threshold=0.6, step_span_px=1).edges[1]
    two = de.raskar_depth_edges(images, eps, step_threshold=0.6, step_span_px=2).edges[1]
    assert not one[2:5].any() and one[8]  # each 1-px drop of the onset is below 0.6; the 1-px shadow is found
    # span 2: the onset's last fully lit pixel; the 1-px shadow is seen one pixel early (7 -> 9 skips it)
    assert np.flatnonzero(two).tolist() == [2, 7]


# ---------------------------------------------------------------- exact small cases
def _two_flash(ratio_profile, axis, light_xy):
    """Flash 0 lit uniformly (1.0), flash 1 with ``ratio_profile`` along ``axis`` (0: rows, 1:
    columns) of a 12 x 14 image; both lit from infinitely far in the direction ``light_xy``."""
    h, w = 12, 14
    r = np.asarray(ratio_profile, float)
    prof = r[:, None] * np.ones((1, w)) if axis == 0 else r[None, :] * np.ones((h, 1))
    images = np.stack([np.ones((h, w, 3)), prof[..., None] * np.ones(3)])
    return images, [de.Epipole(False, light_xy)] * 2


def test_epipole_away_is_the_exact_unit_direction_from_the_epipole():
    e = de.Epipole(True, (2.5, 1.5), 1)  # on pixel (x=2, y=1)'s centre
    a = e.away(4, 6)
    yy, xx = np.mgrid[0:4, 0:6]
    v = np.stack([xx + 0.5 - 2.5, yy + 0.5 - 1.5], -1)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    expect = np.where(n > 0, v / np.where(n > 0, n, 1), 0.0)
    np.testing.assert_allclose(a, expect, atol=1e-15)
    assert (a[1, 2] == 0).all() and a[1, 3].tolist() == [1.0, 0.0] and a[2, 2].tolist() == [0.0, 1.0]
    np.testing.assert_allclose(de.Epipole(True, (2.5, 1.5), -1).away(4, 6), -expect, atol=1e-15)
    inf = de.Epipole(False, (3.0, 4.0)).away(2, 3)  # towards the light (3, 4): away is -(0.6, 0.8) everywhere
    assert inf.shape == (2, 3, 2)
    np.testing.assert_allclose(inf, np.broadcast_to([-0.6, -0.8], (2, 3, 2)), atol=1e-15)


def test_epipole_at_unit_distance_and_barely_out_of_the_lens_plane():
    cam = scenes.Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0), fov_deg=60.0)
    e = de.epipole(cam, (0.0, 0.0, 1.0), 32, 24)  # 1 m straight ahead: the image centre
    assert e.finite is True and e.sign == 1 and e.xy == pytest.approx((16.0, 12.0))
    side = de.epipole(cam, (10.0, 0.0, 5e-9), 32, 24)  # z / dist = 5e-10: in the lens plane
    assert side.finite is False and side.xy == pytest.approx((-1.0, 0.0))  # +x world is left in the image
    with pytest.raises(ConfigError, match="scene: a flash at the lens centre"):
        de.epipole(cam, (0.0, 0.0, 0.0), 32, 24)


def test_raskar_takes_the_local_maximum_of_the_drop_along_the_epipolar_line():
    """A shadow whose onset spreads over three rows (light above, traversal downwards): the edge is
    the row where the drop over step_span_px is largest, not the rows after it."""
    prof = [1.0] * 7 + [0.85, 0.45, 0.15, 0.1, 0.1]
    images, eps = _two_flash(prof, 0, (0.0, -1.0))
    det = de.raskar_depth_edges(images, eps, step_threshold=0.2, step_span_px=1)
    expect = np.zeros((12, 14), bool)
    expect[7] = True  # drops 0.15, 0.40, 0.30, 0.05 at rows 6..9: the maximum at row 7
    np.testing.assert_array_equal(det.edges, expect)
    np.testing.assert_array_equal(det.per_flash[0], np.zeros((12, 14), bool))


@pytest.mark.parametrize(
    "axis, light_xy, flip",
    [(1, (-1.0, 0.0), False), (1, (1.0, 0.0), True), (0, (0.0, -1.0), False), (0, (0.0, 1.0), True)],
)
def test_raskar_at_the_image_border(axis, light_xy, flip):
    """A shadow starting at the last pixel along the traversal: with step_span_px=1 the pixel
    before it is an edge (its sample point is the image's last pixel, inside); with
    step_span_px=2 no pixel is (the largest drop would need a sample beyond the border)."""
    n = 12 if axis == 0 else 14
    prof = np.ones(n)
    prof[-1] = 0.1
    if flip:
        prof = prof[::-1]
    images, eps = _two_flash(prof, axis, light_xy)
    one = de.raskar_depth_edges(images, eps, step_threshold=0.3, step_span_px=1).edges
    expect = np.zeros((12, 14), bool)
    idx = 1 if flip else n - 2
    if axis == 0:
        expect[idx] = True
    else:
        expect[:, idx] = True
    np.testing.assert_array_equal(one, expect)
    assert not de.raskar_depth_edges(images, eps, step_threshold=0.3, step_span_px=2).edges.any()


def test_raskar_threshold_is_strict_and_defaults_to_0_3():
    prof = np.ones(14)
    prof[7:] = 0.5  # a drop of exactly 0.5 (luminance scales exactly by a power of two)
    images, eps = _two_flash(prof, 1, (-1.0, 0.0))
    assert not de.raskar_depth_edges(images, eps, step_threshold=0.5, step_span_px=1).edges.any()
    assert de.raskar_depth_edges(images, eps, step_threshold=0.49, step_span_px=1).edges[:, 6].all()
    prof[7:] = 0.65  # a drop of 0.35: above the default 0.3
    images, eps = _two_flash(prof, 1, (-1.0, 0.0))
    assert de.raskar_depth_edges(images, eps, step_span_px=1).edges[:, 6].all()
    with pytest.raises(ValueError, match="one epipole per flash"):
        de.raskar_depth_edges(images[:, :, :, 0], eps)  # (F, H, W): no channel axis


def test_raskar_smoothing_is_a_gaussian_of_each_flash_image():
    """smooth_px filters each flash image (edges continued outward) before the ratios: the same as
    smoothing the images first (luminance is linear)."""
    from scipy.ndimage import gaussian_filter

    images, epipoles, _, _ = _square_scene(seed=4)
    for s in (0.7, 1.5):
        got = de.raskar_depth_edges(images, epipoles, smooth_px=s)
        pre = np.stack(
            [np.stack([gaussian_filter(im[..., c], s, mode="nearest") for c in range(3)], -1) for im in images]
        )
        ref = de.raskar_depth_edges(pre, epipoles)
        np.testing.assert_allclose(got.ratios, ref.ratios, atol=1e-12)
        np.testing.assert_array_equal(got.edges, ref.edges)
        assert not np.allclose(got.ratios, de.raskar_depth_edges(images, epipoles).ratios)


def test_signal_valid_against_the_99th_percentile():
    lum = np.ones((20, 10))
    lum[0, :1] = 1000.0  # 0.5 % hot pixels do not move the 99th percentile
    lum[5, :] = 0.25  # exactly min_signal_fraction x white: not valid
    lum[6, :] = 0.26
    v = de.signal_valid(4.0 * lum, 0.25, None)  # in other units: the same
    assert v[6].all() and not v[5].any() and v.sum() == 200 - 10
    bad = np.zeros((20, 10), bool)
    bad[0, 5] = True
    v2 = de.signal_valid(4.0 * lum, 0.25, bad)
    assert not v2[0, 5] and not v2[5].any() and v2.sum() == 200 - 11
    black = np.zeros((20, 10))
    black[0, 0] = 5.0  # a black image with one bright pixel: its white is 0, nothing is valid
    assert not de.signal_valid(black, 0.03, None).any()
    assert de.signal_valid(np.zeros((0, 0)), 0.03, None).shape == (0, 0)


def test_depth_discontinuities_match_a_pixel_by_pixel_definition():
    rng = np.random.default_rng(7)
    z = rng.choice([2.0, 2.5, 4.0, 4.5, np.inf], size=(9, 11))
    for rel in (0.1, 0.2, 0.25):
        expect = np.zeros(z.shape, bool)
        for y in range(9):
            for x in range(11):
                for qy, qx in ((y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1)):
                    if 0 <= qy < 9 and 0 <= qx < 11 and np.isfinite(z[y, x]) and z[qy, qx] - z[y, x] > rel * z[y, x]:
                        expect[y, x] = True
        np.testing.assert_array_equal(de.depth_discontinuities(z, rel), expect)
    # exactly rel_jump of the near depth is not a jump
    assert not de.depth_discontinuities(np.array([[2.0, 2.5]]), 0.25).any()


def test_edge_scores_edge_cases():
    truth = np.zeros((8, 8), bool)
    det = np.zeros((8, 8), bool)
    det[0, 0] = True
    s = de.edge_scores(det, truth, 1.0)  # nothing true: every detection is wrong, recall undefined
    assert s == {"precision": 0.0, "recall": None, "f1": None, "detected_px": 1, "true_px": 0}
    s = de.edge_scores(truth, det, 1.0)  # nothing detected: recall 0, precision undefined
    assert s == {"precision": None, "recall": 0.0, "f1": None, "detected_px": 0, "true_px": 1}
    far = np.zeros((8, 8), bool)
    far[7, 7] = True
    assert de.edge_scores(det, far, 1.0)["f1"] == 0.0  # precision = recall = 0
    # precision 1/4 < recall 1/2
    truth = np.zeros((8, 8), bool)
    truth[0, 0] = truth[7, 7] = True
    det = np.zeros((8, 8), bool)
    det[0, 0] = det[0, 7] = det[7, 0] = det[4, 4] = True
    s = de.edge_scores(det, truth, 0.5)
    assert (s["precision"], s["recall"]) == (0.25, 0.5)
    assert s["f1"] == pytest.approx(2 * 0.25 * 0.5 / 0.75)
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    s = de.edge_scores(det, truth, 0.5, mask=mask)
    assert (s["detected_px"], s["true_px"], s["precision"], s["recall"]) == (2, 1, 0.5, 1.0)


def test_shadow_metrics_strict_thresholds():
    rng = np.random.default_rng(8)
    lit = rng.uniform(0.5, 1.0, (6, 7, 3))
    half = np.stack([lit, 0.5 * lit])  # the second flash exactly half as bright: not shadowed (< 0.5 is)
    assert mf.shadow_metrics(lit, half) == {"shadowed_px": 0}
    quarter = np.stack([lit, 0.25 * lit])
    m = mf.shadow_metrics(0.5 * lit, quarter)  # a shadow-free image at exactly half the truth: not "residual"
    assert m["shadowed_px"] == 42 and m["residual_shadow_fraction"] == 0.0
    assert m["residual_shadow_mean"] == pytest.approx(0.5)


def test_depth_edge_methods_pass_their_parameters():
    images, epipoles, _, _ = _square_scene(seed=5)
    bad = np.zeros((H, W), bool)
    bad[R0 : R1 + 1, C1] = True
    p = mf.MultiFlashParams(
        method="raskar2004", step_threshold=0.5, step_span_px=1, smooth_px=0.8, min_signal_fraction=0.5
    )
    got = mf.depth_edges(images, epipoles, bad, p)
    ref = de.raskar_depth_edges(
        images, epipoles, step_threshold=0.5, step_span_px=1, smooth_px=0.8, min_signal_fraction=0.5, bad=bad
    )
    for a, b in ((got.edges, ref.edges), (got.valid, ref.valid), (got.ratios, ref.ratios)):
        np.testing.assert_array_equal(a, b)
    assert not got.valid[R0 : R1 + 1, C1].any() and (~got.valid).mean() > 0.03  # dim albedos fall below half the white
    for low, high in ((0.3, 0.6), (0.5, 0.2)):  # canny: a high threshold below the low one is raised to it
        c = mf.depth_edges(
            images, epipoles, bad, mf.MultiFlashParams(method="canny_max_composite", canny_low=low, canny_high=high)
        )
        e = de.canny_edges(de.max_composite(images), low=low, high=max(low, high))
        np.testing.assert_array_equal(c.edges, e)
        assert c.per_flash.shape == (1, H, W) and (c.per_flash[0] == e).all()
        np.testing.assert_array_equal(c.valid, ~bad)


def _canny_reference(image, low, high):
    """The documented recipe with independent tools: luminance over its 99th percentile, clipped
    to [0, 1], gamma 1/2.2, 8 bit; thresholds = fractions of the largest |d/dx| + |d/dy| of the
    3x3 Sobel (scipy, OpenCV's mirrored border); Canny with the L1 gradient norm."""
    import cv2
    from scipy import ndimage

    from mbcapture.metrics import luminance

    lum = luminance(image)
    u8 = np.round(np.clip(lum / np.percentile(lum, 99), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    f = u8.astype(float)
    gmax = np.max(np.abs(ndimage.sobel(f, axis=1, mode="mirror")) + np.abs(ndimage.sobel(f, axis=0, mode="mirror")))
    return cv2.Canny(u8, low * gmax, high * gmax, L2gradient=False) > 0


def test_canny_edges_follow_the_documented_recipe():
    """Smooth random shading with a few hot pixels (above the 99th percentile) and negative
    values (an over-subtracted ambient): the edge map of the recipe, for several thresholds
    and at any scale of the input."""
    from scipy import ndimage

    rng = np.random.default_rng(9)
    base = ndimage.gaussian_filter(rng.uniform(0, 1, (48, 64)), 2.0)
    base = (base - base.min()) / (base.max() - base.min())
    base[np.arange(48) % 16 == 5] *= 0.35  # a few horizontal dark lines: strong y gradients
    img = np.stack([base, base**2, np.sqrt(base)], -1) * 3.0
    img[3, 7] = img[40, 50] = 30.0  # hot pixels
    img[20:23, 30:33] = -0.5  # negative pixels
    for low, high in ((0.1, 0.25), (0.05, 0.15), (0.2, 0.4), (0.3, 0.3)):
        ref = _canny_reference(img, low, high)
        assert ref.any() and not ref.all()
        np.testing.assert_array_equal(de.canny_edges(img, low=low, high=high), ref)
        np.testing.assert_array_equal(de.canny_edges(7.0 * img, low=low, high=high), ref)
    np.testing.assert_array_equal(de.canny_edges(img), _canny_reference(img, 0.1, 0.25))  # the defaults
    assert not de.canny_edges(np.zeros((8, 8, 3))).any()


def test_layout_finds_flash_and_ambient_reads():
    def sources(tl, reads=None):
        reads = tl.reads if reads is None else reads
        return mf.Sources([r.name for r in reads], [mf.read_groups(tl, r) for r in reads], None, None, None)

    five = protocols.build(load_config(CONFIG, ["sensor.bucket_count=5"]))
    assert mf._layout(sources(five), mf.MultiFlashParams()) == ([0, 1, 2, 3], list(mf.FLASH_GROUPS), 4)
    assert mf._layout(sources(five), mf.MultiFlashParams(ambient="subtract"))[2] == 4
    assert mf._layout(sources(five), mf.MultiFlashParams(ambient="none"))[2] is None
    four = protocols.build(load_config(CONFIG, ["sensor.bucket_count=4"]))
    assert mf._layout(sources(four), mf.MultiFlashParams()) == ([0, 1, 2, 3], list(mf.FLASH_GROUPS), None)
    with pytest.raises(ConfigError, match="app.ambient: 'subtract' needs an ambient-only read"):
        mf._layout(sources(four), mf.MultiFlashParams(ambient="subtract"))
    with pytest.raises(ConfigError, match="capture.protocol: multi_flash needs reads lit by at least two"):
        mf._layout(sources(five, five.reads[:1] + five.reads[4:]), mf.MultiFlashParams())
    two = sources(five, five.reads[:2] + five.reads[4:])
    assert mf._layout(two, mf.MultiFlashParams()) == ([0, 1], ["flash_top", "flash_bottom"], 2)


def test_mid_time_is_the_middle_of_the_timeline():
    from fractions import Fraction
    from types import SimpleNamespace

    tl = SimpleNamespace(start_tick=3, end_tick=10, tick_s=Fraction(1, 1000))
    assert mf._mid_time_s(tl) == 0.0065
    real = protocols.build(load_config(CONFIG, ["capture.sequential=true"]))
    assert mf._mid_time_s(real) == pytest.approx(
        (float(real.seconds(real.start_tick)) + float(real.seconds(real.end_tick))) / 2
    )


def test_edges_overlay_colours():
    """Base luminance dimmed to 0..0.25 of its 99th percentile; matched detections green, unmatched
    red, missed true edges blue; without a truth, detections white."""
    base = np.zeros((6, 8, 3))
    base[:, 4:] = 2.0  # half the image at luminance 2 (the 99th percentile)
    det = np.zeros((6, 8), bool)
    truth = np.zeros((6, 8), bool)
    det[1, 1] = truth[1, 2] = True  # 1 px apart: matched
    det[4, 6] = True  # nothing true near: unmatched
    truth[5, 0] = True  # nothing detected near: missed
    out = mf.edges_overlay(base, det, truth, 1.0)
    np.testing.assert_allclose(out[0, 0], 0.0)
    np.testing.assert_allclose(out[0, 7], 0.25)
    assert out[1, 1].tolist() == [0.1, 1.0, 0.1]
    assert out[4, 6].tolist() == [1.0, 0.1, 0.1]
    assert out[5, 0].tolist() == [0.1, 0.3, 1.0]
    np.testing.assert_allclose(out[1, 2], 0.0)  # a true edge with a detection near: not marked
    plain = mf.edges_overlay(base, det, None, 1.0)
    assert plain[1, 1].tolist() == plain[4, 6].tolist() == [1.0, 1.0, 1.0]
    np.testing.assert_allclose(plain[5, 0], 0.0)
    # nothing detected: every true edge is missed; nothing true: every detection unmatched
    assert mf.edges_overlay(base, np.zeros_like(det), truth, 1.0)[1, 2].tolist() == [0.1, 0.3, 1.0]
    assert mf.edges_overlay(base, det, np.zeros_like(truth), 1.0)[1, 1].tolist() == [1.0, 0.1, 0.1]
    black = mf.edges_overlay(np.zeros((6, 8, 3)), det, None, 1.0)  # a black base: white is 1, nothing divides by 0
    assert np.isfinite(black).all() and black[0, 0].tolist() == [0.0, 0.0, 0.0]
    # white is the 99th percentile, not the maximum: a hot pixel and values above white clip, below 0 too
    lum = np.zeros((10, 20))
    lum[:, 10:] = 2.0
    lum[0, 0] = 50.0  # 0.5 % of the pixels
    lum[5, 0] = 1.0  # half of white
    lum[6, 0] = -1.0
    out = mf.edges_overlay(np.repeat(lum[..., None], 3, -1), np.zeros((10, 20), bool), None, 1.0)
    np.testing.assert_allclose(out[..., 0][[0, 5, 6, 0], [0, 0, 0, 19]], [0.25, 0.125, 0.0, 0.25])
    # a detection (or true edge) in the image's corner with nothing on the other map: unmatched (missed)
    corner = np.zeros((6, 8), bool)
    corner[0, 0] = True
    assert mf.edges_overlay(base, corner, np.zeros_like(corner), 1.0)[0, 0].tolist() == [1.0, 0.1, 0.1]
    assert mf.edges_overlay(base, np.zeros_like(corner), corner, 1.0)[0, 0].tolist() == [0.1, 0.3, 1.0]


def test_scores_split_edges_and_shadow_free_error_by_the_moving_region():
    """The report's depth-edge scores over the whole image and, when something moves, inside and
    outside the moving region; the shadow-free image's relative MSE against the truth (whole and
    moving region, eps in radiance units) and its residual shadows."""
    from types import SimpleNamespace

    from mbcapture.metrics import relative_mse

    eps = 1e-3  # the relative MSE's eps for radiance, (render units)^2

    images, _, truth_edges, _ = _square_scene(seed=6)
    det = truth_edges.copy()
    det[0, :6] = True  # false detections in the top-left corner
    det[R0, C0 : C1 + 1] = False  # a missed true edge (the top row of the square)
    moving = np.zeros((H, W), bool)
    moving[:, :17] = True  # through the square: edges on both sides
    shadow_free = de.max_composite(images) * np.linspace(0.8, 1.2, W)[None, :, None]
    truth = {
        "t_s": 0.5,
        "times_s": [0.5],
        "flash": images,
        "shadow_free": de.max_composite(images),
        "edges": truth_edges,
        "spp": 16,
    }
    p = mf.MultiFlashParams(tolerance_px=1.5, min_signal_fraction=0.4)
    s = mf._scores(SimpleNamespace(moving_mask=moving), p, det, shadow_free, truth)
    assert s["moving_px"] == moving.sum()
    assert s["depth_edges"] == {
        "all": de.edge_scores(det, truth_edges, 1.5),
        "moving_region": de.edge_scores(det, truth_edges, 1.5, moving),
        "static_region": de.edge_scores(det, truth_edges, 1.5, ~moving),
    }
    edges = s["depth_edges"]
    assert edges["moving_region"] != edges["static_region"] and edges["all"] not in (
        edges["moving_region"],
        edges["static_region"],
    )
    sm = mf.shadow_metrics(shadow_free, images, shadow_ratio=p.shadow_ratio, min_signal_fraction=0.4)
    assert 0 < sm["shadowed_px"] < mf.shadow_metrics(shadow_free, images)["shadowed_px"]  # fewer pixels count as lit
    assert s["shadow_free"] == {
        "rel_mse": pytest.approx(relative_mse(shadow_free, truth["shadow_free"], eps=eps)),
        "rel_mse_moving": pytest.approx(
            relative_mse(shadow_free, truth["shadow_free"], mask=moving[..., None], eps=eps)
        ),
        **sm,
    }
    assert s["shadow_free"]["rel_mse"] != pytest.approx(s["shadow_free"]["rel_mse_moving"])
    t = s["truth"]
    assert (t["time_s"], t["edge_times_s"], t["mode"], t["depth_jump"], t["tolerance_px"], t["shadow_free_spp"]) == (
        0.5,
        [0.5],
        p.truth_time,
        p.truth_depth_jump,
        1.5,
        16,
    )
    # shadows at 5 % of the direct light are not below 4 % of it
    low = mf._scores(
        SimpleNamespace(moving_mask=moving), mf.MultiFlashParams(shadow_ratio=0.04), det, shadow_free, truth
    )
    assert low["shadow_free"]["shadowed_px"] == 0
    still = mf._scores(SimpleNamespace(moving_mask=np.zeros((H, W), bool)), p, det, shadow_free, truth)
    assert set(still["depth_edges"]) == {"all"} and "rel_mse_moving" not in still["shadow_free"]
    assert still["moving_px"] == 0
