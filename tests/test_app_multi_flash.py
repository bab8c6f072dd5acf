"""Multi-flash: protocol, epipoles, Raskar depth edges, ground-truth edges and metrics on small
synthetic inputs with known answers; one tiny render comparing interleaved and sequential."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config, protocols, scenes
from mbcapture.apps import multi_flash as mf
from mbcapture.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "multi_flash.yaml"

# ---------------------------------------------------------------- synthetic scene with known edges
H, W = 40, 48
R0, R1, C0, C1 = 10, 19, 12, 21          # foreground square, inclusive rows/cols
SHADOW_PX = 3                             # shadow width beside the square, px
INDIRECT = 0.05                           # light left in a shadow, relative to direct


def _square_scene(seed=0):
    """Flash images (4, H, W, 3) in protocol order (top, bottom, left, right), an albedo map that
    varies per pixel, the epipoles of LEDs in the lens plane, and the true depth-edge map (the
    square's border pixels: the occluding side)."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 0.9, size=(H, W, 3))
    fg = np.zeros((H, W), bool)
    fg[R0:R1 + 1, C0:C1 + 1] = True
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
    truth = fg & ~np.pad(fg, 1)[2:, 1:-1] | fg & ~np.pad(fg, 1)[:-2, 1:-1] \
        | fg & ~np.pad(fg, 1)[1:-1, 2:] | fg & ~np.pad(fg, 1)[1:-1, :-2]
    return np.stack(images), [mf.Epipole(False, dirs[n]) for n in ("top", "bottom", "left", "right")], truth, fg


def test_raskar_finds_exactly_the_occluding_border_of_a_square():
    images, epipoles, truth, fg = _square_scene()
    det = mf.raskar_depth_edges(images, epipoles, step_threshold=0.3)
    assert truth.sum() == 2 * (R1 - R0 + 1) + 2 * (C1 - C0 + 1) - 4
    np.testing.assert_array_equal(det.edges, truth)
    # each LED finds the side away from it: the left LED the square's right column, and so on
    np.testing.assert_array_equal(np.flatnonzero(det.per_flash[2].any(axis=0)), [C1])
    np.testing.assert_array_equal(np.flatnonzero(det.per_flash[0].any(axis=1)), [R1])
    # ratios are albedo-free: 1 on lit pixels, INDIRECT / 1 in shadows
    assert np.allclose(det.ratios[2][R0:R1 + 1, C1 + 1:C1 + 1 + SHADOW_PX], INDIRECT)
    assert np.allclose(det.ratios[2][fg], 1.0)
    # the max composite has no shadow left
    assert np.allclose(mf.max_composite(images), images.max(axis=0))
    assert mf.luminance(mf.max_composite(images)).min() > 0.1


def test_raskar_traversal_direction_matters():
    """Traversing towards the epipole instead sees the shadow's far end (a rise), not a depth edge."""
    images, epipoles, truth, _ = _square_scene()
    flipped = [mf.Epipole(False, tuple(-v for v in e.xy)) for e in epipoles]
    det = mf.raskar_depth_edges(images, flipped, step_threshold=0.3)
    assert not (det.edges & truth).any()  # every mark is at the shadow's far end, off the square


def test_raskar_with_noise_keeps_precision_and_recall():
    images, epipoles, truth, _ = _square_scene(seed=3)
    rng = np.random.default_rng(7)
    # 3 % Gaussian noise: a false step of 0.3 is a 7-sigma event for the ratio difference
    noisy = images * (1 + 0.03 * rng.standard_normal(images.shape))
    det = mf.raskar_depth_edges(noisy, epipoles, step_threshold=0.3)
    s = mf.edge_scores(det.edges, truth, 1.0)
    assert s["precision"] == 1.0 and s["recall"] == 1.0


def test_dark_or_saturated_pixels_carry_no_edges():
    images, epipoles, truth, _ = _square_scene()
    bad = np.zeros((H, W), bool)
    bad[:, C1] = True  # the square's right column saturated: the left LED's edge is lost there
    det = mf.raskar_depth_edges(images, epipoles, step_threshold=0.3, bad=bad)
    assert not det.edges[:, C1].any() and (det.edges == (truth & ~bad)).all()
    dark = images.copy()
    dark[:, :, :5] = 0.0
    det = mf.raskar_depth_edges(dark, epipoles, min_signal_fraction=0.05)
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
    np.testing.assert_array_equal(mf.depth_discontinuities(z, 0.05), truth)
    # a slanted plane changes depth smoothly (1 % per pixel): no edge at a 5 % threshold
    slope = 1.0 + 0.01 * np.arange(W)[None, :] + np.zeros((H, 1))
    assert not mf.depth_discontinuities(slope, 0.05).any()
    assert mf.depth_discontinuities(slope, 0.005).sum() == H * (W - 1)  # each pixel nearer than its right neighbour
    # nothing behind (inf): the surface's border is an edge, the empty pixels are not
    z_inf = np.where(fg, 1.0, np.inf)
    np.testing.assert_array_equal(mf.depth_discontinuities(z_inf, 0.05), truth)


def test_edge_scores_by_hand():
    truth = np.zeros((10, 10), bool)
    truth[5, 2:8] = True                       # 6 true pixels
    det = np.zeros_like(truth)
    det[6, 2:6] = True                         # 4 detections 1 px below the line
    det[0, 0] = True                           # 1 far away
    s = mf.edge_scores(det, truth, 1.0)
    assert s["precision"] == pytest.approx(4 / 5)
    # true pixels within 1 px of a detection: columns 1..6 (2..5 directly, 6 is sqrt(2) > 1 away from (6,5))
    assert s["recall"] == pytest.approx(4 / 6)
    assert s["f1"] == pytest.approx(2 * 0.8 * (4 / 6) / (0.8 + 4 / 6))
    s = mf.edge_scores(det, truth, 1.5)
    assert s["recall"] == pytest.approx(5 / 6)  # (5,6) is sqrt(2) from (6,5)
    assert mf.edge_scores(det, truth, 0.5)["precision"] == 0.0
    none = mf.edge_scores(np.zeros_like(truth), truth, 1.0)
    assert none["precision"] is None and none["recall"] == 0.0
    masked = mf.edge_scores(det, truth, 1.0, mask=np.arange(10)[None, :] >= 4 + np.zeros((10, 1)))
    assert masked["detected_px"] == 2 and masked["precision"] == 1.0


def test_shadow_metrics_find_a_kept_shadow():
    images, _, _, _ = _square_scene()
    m = mf.shadow_metrics(mf.max_composite(images), images)
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
    flat[:, R0:R1 + 1, C0:C1 + 1] *= 1.0
    p = mf.MultiFlashParams(method="canny_max_composite")
    det = mf.depth_edges(flat, epipoles, np.zeros((H, W), bool), p)
    assert det.ratios is None and det.edges[:, W // 2 - 1: W // 2 + 1].any()
    assert not mf.depth_edges(flat, epipoles, np.zeros((H, W), bool), mf.MultiFlashParams()).edges.any()


def test_unknown_method_lists_the_registry():
    with pytest.raises(ConfigError, match=r"app.method: .*canny_max_composite.*raskar2004"):
        mf.depth_edges(np.ones((4, 3, 3, 3)), [], np.zeros((3, 3), bool), mf.MultiFlashParams(method="nope"))


# ---------------------------------------------------------------- epipoles
def test_epipoles_of_the_scene_leds_are_at_infinity_along_rows_and_columns():
    mod = scenes.load_module("multiflash")
    sc = mod.make(mod.Params())
    got = {g: mf.epipole(sc.camera, p, 160, 128) for g, p in sc.extra["flash_positions_m"].items()}
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
    e = mf.epipole(cam, light, 64, 48)
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
    assert seq.sequential and [mf.read_groups(seq, r) for r in seq.reads] == [{g} for g in mf.FLASH_GROUPS] + [frozenset()]
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
TINY = ["render.width=80", "render.height=64", "render.spp=4", "app.truth_spp=8", "render.max_motion_px=1.0"]


@pytest.mark.render
def test_aov_depth_is_the_scene_geometry():
    from mbcapture.render import Renderer
    from mbcapture.render.aov import render_depth

    mod = scenes.load_module("multiflash")
    sc = mod.make(mod.Params())
    r = Renderer(sc, 80, 64)
    d = render_depth(r, 0.0)
    assert d.z_m[0, 0] == pytest.approx(1.0, abs=1e-5)         # the wall, camera 1 m away
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
    eps = [mf.Epipole(False, (-1.0, 0.0)), mf.Epipole(False, (1.0, 0.0))]
    one = mf.raskar_depth_edges(images, eps, step_threshold=0.6, step_span_px=1).edges[1]
    two = mf.raskar_depth_edges(images, eps, step_threshold=0.6, step_span_px=2).edges[1]
    assert not one[2:5].any() and one[8]         # each 1-px drop of the onset is below 0.6; the 1-px shadow is found
    # span 2: the onset's last fully lit pixel; the 1-px shadow is seen one pixel early (7 -> 9 skips it)
    assert np.flatnonzero(two).tolist() == [2, 7]
