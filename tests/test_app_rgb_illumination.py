"""RGB illumination: protocol, ambient subtraction, colour matrices, masks and
CIEDE2000 on small synthetic inputs with known answers (no rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from mbcapture.timing import protocols
from mbcapture.scene import scenes
from mbcapture.apps import rgb_illumination as rgb
from mbcapture.capture.pipeline import bucket_group_seconds
from mbcapture.config import config_from_dict
from mbcapture.errors import ConfigError

CFG = {
    "scene": {"name": "colour_chart"},
    "render": {"width": 160, "height": 128, "variant": "llvm_ad_spectral"},
    "capture": {"protocol": "rgb_illumination", "unit_exposure_s": 0.004, "periods": 16},
    "sensor": {"spectral_response": "monochrome:Nikon 5100 (NPL)", "quantum_efficiency": [0.5, 0.5, 0.5]},
}


@pytest.fixture(scope="module")
def chart():
    mod = scenes.load_module("colour_chart")
    return mod.make(mod.Params())


# -- protocol ------------------------------------------------------------------------------------
def test_protocol_buckets_see_one_led_each(chart):
    cfg = config_from_dict(CFG)
    tl = protocols.build(cfg)
    assert [r.name for r in tl.reads] == ["R", "G", "B", "ambient"]
    secs = bucket_group_seconds(tl, ("led_r", "led_g", "led_b"))
    np.testing.assert_allclose(secs, np.vstack([np.eye(3) * 0.004, np.zeros((1, 3))]), atol=1e-12)
    assert float(tl.seconds(tl.end_tick - tl.start_tick)) == pytest.approx(0.016)
    seq = protocols.build(config_from_dict({**CFG, "capture": {**CFG["capture"], "sequential": True}}))
    np.testing.assert_allclose(bucket_group_seconds(seq, ("led_r", "led_g", "led_b")), secs, atol=1e-12)
    # four frames of 4 ms with the frame readout gap between them
    gap = config_from_dict(CFG).sensor.frame_readout_s
    assert float(seq.seconds(seq.end_tick - seq.start_tick)) == pytest.approx(0.016 + 3 * gap, rel=1e-9)


def test_protocol_needs_four_buckets():
    with pytest.raises(ConfigError, match="needs 4 buckets but sensor.bucket_count is 3"):
        protocols.build(config_from_dict({**CFG, "sensor": {**CFG["sensor"], "bucket_count": 3}}))


def test_monochrome_response_is_one_curve_for_all_channels():
    from mbcapture.sensor import SensorConfig
    from mbcapture.sensor.spectral import channel_quantum_efficiency

    wl, qe = channel_quantum_efficiency(
        SensorConfig(spectral_response="monochrome:Nikon 5100 (NPL)", quantum_efficiency=[0.5, 0.5, 0.5])
    )
    np.testing.assert_array_equal(qe[0], qe[1])
    np.testing.assert_array_equal(qe[0], qe[2])
    assert qe.max() == pytest.approx(0.5)
    _, cam = channel_quantum_efficiency(
        SensorConfig(spectral_response="Nikon 5100 (NPL)", quantum_efficiency=[1, 1, 1])
    )
    np.testing.assert_allclose(qe[0], cam.sum(0) / cam.sum(0).max() * 0.5)  # panchromatic: R + G + B
    with pytest.raises(ConfigError, match="unknown camera 'Nope'"):
        config_from_dict({**CFG, "sensor": {"spectral_response": "monochrome:Nope"}})


# -- signals -------------------------------------------------------------------------------------
def test_ambient_subtraction_recovers_led_rates():
    rng = np.random.default_rng(0)
    led = rng.uniform(0, 1e6, (3, 4, 5))  # e-/s of each LED
    amb = rng.uniform(0, 3e5, (4, 5))
    t = np.array([0.004, 0.004, 0.004, 0.002])  # a shorter ambient frame is scaled, not just subtracted
    mono = np.stack([(led[k] + amb) * t[k] for k in range(3)] + [amb * t[3]])
    np.testing.assert_allclose(rgb.led_signals(mono, t), led.transpose(1, 2, 0), rtol=1e-12)


def test_mono_signal_channel_or_sum():
    e = np.arange(2 * 2 * 3 * 3, dtype=float).reshape(2, 2, 3, 3)
    np.testing.assert_array_equal(rgb.mono_signal(e, True), e[..., 0])
    np.testing.assert_array_equal(rgb.mono_signal(e, False), e.sum(-1))


# -- colour matrices -----------------------------------------------------------------------------
def test_chart_fit_recovers_a_known_matrix():
    rng = np.random.default_rng(1)
    m_true = np.array([[0.5, 0.2, 0.01], [0.3, 0.7, 0.1], [0.15, 0.08, 0.9]])
    signals = rng.uniform(0.02, 1, (24, 3))
    np.testing.assert_allclose(rgb.fit_chart_matrix(signals, signals @ m_true), m_true, rtol=1e-10)


def test_analytic_matrix_is_exact_for_band_constant_reflectances():
    rng = np.random.default_rng(2)
    response = np.diag([2.0, 5.0, 3.0]) + 0.1  # with some cross-talk between channels
    led_xyz = rng.uniform(0.05, 1, (3, 3))
    rho = rng.uniform(0.03, 0.9, (24, 3))  # each surface's reflectance in the three LED bands
    geometry = 123.0
    signals = geometry * rho @ response.T
    white = np.array([0.9, 0.9, 0.9])
    white_xyz = led_xyz @ white
    m = rgb.analytic_matrix(response, led_xyz, geometry * response @ white, white_xyz[1])
    np.testing.assert_allclose(signals @ m, rho @ led_xyz.T, rtol=1e-10)


def test_analytic_matrix_from_the_scene_spectra_matches_true_colours(chart):
    """No rendering: the mono sensor's signals of the true reflectances under each LED, through the
    analytic matrix, land within a few CIEDE2000 of the true colours (the narrow-band assumption)."""
    import colour

    from mbcapture.sensor import SensorConfig
    from mbcapture.sensor.spectral import film_sensitivity

    wl, curves = film_sensitivity(SensorConfig(spectral_response="monochrome:Nikon 5100 (NPL)"))
    names, true_xyz, white_xy = rgb.true_colours(chart)
    grid = np.arange(360.0, 831.0, 1.0)
    s = np.interp(grid, wl, curves[0], left=0, right=0)
    e = [np.interp(grid, *chart.extra["led_spectra"][g].arrays, left=0, right=0) for g in rgb.LED_GROUPS]
    refl = [np.interp(grid, *chart.extra["reflectances"][n].arrays) for n in names]
    signals = np.array([[np.trapezoid(s * ek * r, grid) for ek in e] for r in refl])
    response, led_xyz = rgb.led_matrices(chart, wl, np.repeat(curves[:1], 3, 0), per_led_channel=True)
    white = names.index("white 9.5 (.05 D)")
    m = rgb.colour_matrix("analytic", signals, true_xyz, white, response, led_xyz)
    de = rgb.delta_e2000(signals @ m, true_xyz, white_xy)
    assert de[white] < 0.5 and de.mean() < 3.0, de
    # chart_fit on the same signals is at least as good on average (it is fitted to them)
    de_fit = rgb.delta_e2000(signals @ rgb.colour_matrix("chart_fit", signals, true_xyz, white), true_xyz, white_xy)
    assert de_fit.mean() <= de.mean() + 0.5
    # true colours: a perfect white has Y = 1; the white patch reflects ~90 %
    assert 0.8 < true_xyz[white, 1] < 0.95
    np.testing.assert_allclose(colour.xy_to_XYZ(white_xy)[1], 1.0)


def test_unknown_method_lists_valid_ones():
    with pytest.raises(ConfigError, match=r"app.method: unknown colour method 'magic'.*analytic.*chart_fit"):
        rgb.colour_matrix("magic", np.ones((24, 3)), np.ones((24, 3)), 18)
    with pytest.raises(ConfigError, match=r"app.method"):
        config_from_dict({**CFG, "app": {"method": "magic"}})


# -- CIEDE2000 -----------------------------------------------------------------------------------
def test_delta_e2000_known_pair():
    """Sharma, Wu and Dalal (2005), test pair 1: Lab (50, 2.6772, -79.7751) vs (50, 0, -82.7485): 2.0425."""
    import colour

    white_xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    a = colour.Lab_to_XYZ([50, 2.6772, -79.7751], white_xy)
    b = colour.Lab_to_XYZ([50, 0.0, -82.7485], white_xy)
    assert float(rgb.delta_e2000(a, b, white_xy)) == pytest.approx(2.0425, abs=1e-4)
    assert float(rgb.delta_e2000(a, a, white_xy)) == 0.0


# -- masks ---------------------------------------------------------------------------------------
def test_interior_masks_count_pixel_centres():
    boxes = np.array([[2.0, 3.0, 12.0, 11.0]])  # 10 x 8 px
    m = rgb.interior_masks(boxes, 20, 16, 0.5)  # central 5 x 4 px: centres x in [4.5, 9.5], y in [5, 9]
    assert m.shape == (1, 16, 20)
    ys, xs = np.nonzero(m[0])
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (4, 9, 5, 8)
    img = np.zeros((16, 20, 3))
    img[5:9, 4:10] = (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(rgb.patch_means(img, m), [[1.0, 2.0, 3.0]])


def test_patch_boxes_lie_in_the_image_in_chart_order(chart):
    boxes = rgb.patch_boxes_px(chart, 160, 128)
    assert boxes.shape == (24, 4)
    assert boxes[:, [0, 1]].min() > 0 and boxes[:, 2].max() < 160 and boxes[:, 3].max() < 128
    assert boxes[0, 0] < boxes[5, 0] and boxes[0, 1] < boxes[18, 1]  # row by row from the top left
    side = boxes[:, 2] - boxes[:, 0]
    np.testing.assert_allclose(side, side[0], rtol=1e-6)
    assert 10 < side[0] < 20  # 34 mm of a 0.39 m wide view on 160 px


# -- exact small cases ---------------------------------------------------------------------------
def test_interior_masks_boundary_and_patches_smaller_than_a_pixel():
    # fraction 1 of (1.5, 1.5)-(4.5, 4.5): the centres 1.5 and 4.5 lie on the border and count
    m = rgb.interior_masks(np.array([[1.5, 1.5, 4.5, 4.5]]), 8, 6, 1.0)[0]
    expect = np.zeros((6, 8), bool)
    expect[1:5, 1:5] = True
    np.testing.assert_array_equal(m, expect)
    # patches too small to hold a pixel centre get their nearest pixel, clamped to the image
    tiny = np.array([[2.1, 3.1, 2.3, 3.3], [-5.0, -5.0, -4.8, -4.8], [50.0, 40.0, 50.2, 40.2]])
    t = rgb.interior_masks(tiny, 8, 6, 0.5)
    for mask, (y, x) in zip(t, [(3, 2), (0, 0), (5, 7)]):
        assert mask.sum() == 1 and mask[y, x]


def test_patch_boxes_are_the_projected_patch_squares():
    from types import SimpleNamespace

    cam = scenes.Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0)
    sc = SimpleNamespace(camera=cam, extra={"patches": [("a", (0.1, 0.05, 0.0), 0.04), ("b", (-0.2, -0.1, 0.0), 0.02)]})
    boxes = rgb.patch_boxes_px(sc, 64, 48)
    for (_, (cx, cy, cz), h), box in zip(sc.extra["patches"], boxes):
        corners = np.array([[cx + sx * h, cy + sy * h, cz] for sx in (-1, 1) for sy in (-1, 1)])
        px = cam.project(corners, 64, 48)
        np.testing.assert_allclose(box, [px[:, 0].min(), px[:, 1].min(), px[:, 0].max(), px[:, 1].max()], rtol=1e-12)
        assert box[2] - box[0] == pytest.approx(box[3] - box[1], rel=1e-9)  # square patch, square pixels


def test_led_signals_of_a_two_row_image():
    mono = np.arange(4 * 2 * 3, dtype=float).reshape(4, 2, 3) + 10.0
    t = np.array([0.5, 1.0, 2.0, 4.0])
    s = rgb.led_signals(mono, t)
    assert s.shape == (2, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(s[..., k], mono[k] / t[k] - mono[3] / t[3])


def test_analytic_matrix_refuses_a_white_without_signal_and_scales_a_weak_one():
    response = np.diag([2.0, 5.0, 3.0])
    led_xyz = np.array([[0.4, 0.3, 0.2], [0.2, 0.7, 0.1], [0.01, 0.1, 0.9]])
    with pytest.raises(ValueError, match="analytic colour matrix: the white patch has no signal"):
        rgb.analytic_matrix(response, led_xyz, np.zeros(3), 1.0)
    white = 1e-3 * response @ np.ones(3)  # a faint white: Y of the mapped white is still white_y
    m = rgb.analytic_matrix(response, led_xyz, white, 0.9)
    assert float(white @ m[:, 1]) == pytest.approx(0.9)


def test_xyz_to_lab_uses_the_given_white():
    import colour

    a = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    white_xyz = colour.xy_to_XYZ(a)
    np.testing.assert_allclose(rgb.xyz_to_lab(white_xyz, a), [100.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(
        rgb.xyz_to_lab(np.array([-0.1, 0.5, 0.2]), a), rgb.xyz_to_lab(np.array([0.0, 0.5, 0.2]), a)
    )


def _box(lo, hi, v=1.0):
    """A spectrum of value v on [lo, hi] nm, sampled only there (1 nm): zero outside by definition."""
    from mbcapture.render.build import Spectrum

    wl = np.arange(lo, hi + 1.0)
    return Spectrum(tuple(wl), tuple(np.full(wl.size, v)))


def test_led_matrices_integrate_spectra_that_are_zero_outside_their_samples():
    """Box LEDs and box sensitivities, each sampled only over its support (non-zero at its ends):
    on the 1 nm grid a product of boxes integrates to (overlap in nm + 1) x the values."""
    from types import SimpleNamespace

    import colour

    leds = {"led_r": _box(690, 710), "led_g": _box(520, 540), "led_b": _box(440, 460)}
    sc = SimpleNamespace(extra={"led_spectra": leds})
    curves_wl = np.arange(450.0, 701.0)  # the red and blue LEDs stick out of the sensitivities' range
    ch0 = np.full(curves_wl.size, 0.5)  # 0.5 on 450..700
    ch1 = np.where((curves_wl >= 530) & (curves_wl <= 610), 2.0, 0.0)  # 2 on 530..610
    ch2 = np.ones(curves_wl.size)  # 1 on 450..700
    response, led_xyz = rgb.led_matrices(sc, curves_wl, np.stack([ch0, ch1, ch2]), per_led_channel=False)
    np.testing.assert_allclose(
        response, [[11 * 0.5, 21 * 0.5, 11 * 0.5], [0.0, 11 * 2.0, 0.0], [11.0, 21.0, 11.0]], rtol=1e-12
    )
    cmfs = colour.MSDS_CMFS[rgb.CMFS_NAME].copy().align(colour.SpectralShape(360, 830, 1)).values
    for k, (lo, hi) in enumerate([(690, 710), (520, 540), (440, 460)]):
        np.testing.assert_allclose(led_xyz[:, k], cmfs[lo - 360 : hi - 360 + 1].sum(axis=0), rtol=1e-12)
    diag, led_xyz2 = rgb.led_matrices(sc, curves_wl, np.stack([ch0, ch1, ch2]), per_led_channel=True)
    np.testing.assert_allclose(diag, np.diag(np.diag(response)), rtol=1e-15)
    np.testing.assert_array_equal(led_xyz2, led_xyz)


def test_true_colours_perfect_white_has_y_1_and_is_the_white_point(chart):
    from types import SimpleNamespace

    from mbcapture.render.build import Spectrum

    wl = tuple(np.arange(360.0, 831.0, 10.0))
    flat = {"white": Spectrum(wl, (1.0,) * len(wl)), "grey": Spectrum(wl, (0.5,) * len(wl))}
    sc = SimpleNamespace(extra={"led_spectra": chart.extra["led_spectra"], "reflectances": flat})
    names, xyz, white_xy = rgb.true_colours(sc)
    assert names == ["white", "grey"]
    assert xyz[0, 1] == pytest.approx(1.0, rel=1e-9) and xyz[1] == pytest.approx(0.5 * xyz[0], rel=1e-9)
    np.testing.assert_allclose(white_xy, xyz[0, :2] / xyz[0].sum(), rtol=1e-9)


def test_strata_split_the_window_so_no_point_moves_more_than_the_limit():
    """A point crossing 10 px of image during [t0, t1] at constant speed: ceil(10 / limit) equal
    strata (capped at max_strata); a static scene is one stratum at the middle."""
    import dataclasses

    from mbcapture.scene.scenes import Camera, SceneModel

    cam = Camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), 90.0)  # 1 m at 1 m depth = 20 px of 40

    def dot(t):  # (T, 2, 3): points 1 m ahead moving sideways at 2.5 and 1.5 m/s (10 and 6 px in the window)
        t = np.asarray(t, float)
        return np.stack(
            [np.stack([-2.5 * t, 0 * t, 1 + 0 * t], -1), np.stack([-1.5 * t, 0.1 + 0 * t, 1 + 0 * t], -1)], axis=1
        )

    moving = SceneModel("dot", ("ambient",), frozenset(), cam, None, None, motion_points=dot)
    mids = rgb._strata(moving, 0.1, 0.3, 40, 30, 3.0, 64)  # x from -0.25 to -0.75 m: 10 px (the other point: 6 px)
    np.testing.assert_allclose(mids, 0.1 + (np.arange(4) + 0.5) * 0.05)  # ceil(10 / 3) = 4 strata
    assert len(rgb._strata(moving, 0.1, 0.3, 40, 30, 2.5, 64)) == 4  # the longest path, not a sum or norm over points
    assert len(rgb._strata(moving, 0.1, 0.3, 40, 30, 2.0, 64)) == 5
    assert len(rgb._strata(moving, 0.1, 0.3, 40, 30, 0.5, 7)) == 7
    assert len(rgb._strata(moving, 0.1, 0.3, 40, 30, 100.0, 64)) == 1
    still = dataclasses.replace(moving, motion_points=None)
    np.testing.assert_array_equal(rgb._strata(still, 0.1, 0.3, 40, 30, 3.0, 64), [0.2])


def test_bayer_window_is_the_interleaved_span():
    from types import SimpleNamespace

    data = SimpleNamespace(cfg=SimpleNamespace(capture=SimpleNamespace(start_s=0.25, unit_exposure_s=0.004)))
    assert rgb.bayer_window(data) == (0.25, 0.25 + 0.016)


def test_cmf_curves_and_srgb_preview():
    import colour

    wl, curves = rgb._cmf_curves()
    np.testing.assert_array_equal(wl, np.arange(360.0, 831.0, 5.0))
    assert curves.shape == (3, wl.size) and curves.flags["C_CONTIGUOUS"]
    assert curves[1, wl.tolist().index(555.0)] == pytest.approx(1.0, abs=1e-4)  # y-bar peaks at 555 nm
    assert curves[2, wl.tolist().index(445.0)] == pytest.approx(1.78, abs=0.01)  # z-bar near its peak
    # the illuminant's own white maps to equal linear sRGB (chromatic adaptation to D65), at its Y
    a = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    rgb_white = rgb.xyz_to_linear_srgb(0.6 * colour.xy_to_XYZ(a), a)
    np.testing.assert_allclose(rgb_white, [0.6, 0.6, 0.6], atol=2e-3)
    # a colour: Bradford adaptation from the illuminant's white to D65, then the sRGB matrix, no encoding
    xyz = np.array([0.3, 0.2, 0.1])
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    adapted = colour.adaptation.chromatic_adaptation_VonKries(
        xyz, colour.xy_to_XYZ(a), colour.xy_to_XYZ(d65), "Bradford"
    )
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    np.testing.assert_allclose(rgb.xyz_to_linear_srgb(xyz, a), srgb.matrix_XYZ_to_RGB @ adapted, rtol=1e-6)


def test_true_colours_with_leds_sampled_on_different_grids():
    """Each LED spectrum given only over its own band: the illuminant is still the sum of all
    three (each zero outside its samples), the same as with all three on one full grid. The sum
    used to be taken on the first LED's grid only, which dropped the other two LEDs' light."""
    from types import SimpleNamespace

    import colour

    from mbcapture.render.build import Spectrum

    def led(peak, lo, hi):
        sd = colour.sd_single_led(peak, shape=colour.SpectralShape(lo, hi, 2), half_spectral_width=20)
        return Spectrum.from_sd(sd)

    wl = np.arange(360.0, 831.0, 10.0)
    refl = {
        "white": Spectrum(tuple(wl), (1.0,) * wl.size),
        "red": Spectrum(tuple(wl), tuple(np.where(wl > 580, 0.8, 0.05))),
    }
    own = {"led_r": led(630, 560, 700), "led_g": led(530, 460, 620), "led_b": led(450, 380, 520)}
    full = {"led_r": led(630, 360, 830), "led_g": led(530, 360, 830), "led_b": led(450, 360, 830)}
    _, xyz_own, white_own = rgb.true_colours(SimpleNamespace(extra={"led_spectra": own, "reflectances": refl}))
    _, xyz_full, white_full = rgb.true_colours(SimpleNamespace(extra={"led_spectra": full, "reflectances": refl}))
    np.testing.assert_allclose(xyz_own, xyz_full, atol=1e-6)
    np.testing.assert_allclose(white_own, white_full, atol=1e-6)
    assert white_full[0] < 0.3  # a bluish white: all three LEDs (the red one alone would be at x > 0.6)


def test_scores_aggregate_delta_e_over_the_image_and_the_patch_interiors():
    """Per-pixel CIEDE2000 against the reference, summarized over the image and over the patch
    interiors; and each patch's mean colour against its true colour."""
    import colour

    white_xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    rng = np.random.default_rng(15)
    ref = np.broadcast_to([0.3, 0.32, 0.35], (12, 16, 3)).copy()
    xyz = ref * rng.uniform(0.9, 1.1, (12, 16, 1))  # lightness errors everywhere
    xyz[0, 0] = [0.6, 0.3, 0.05]  # one very wrong pixel, outside the patches
    masks = np.zeros((2, 12, 16), bool)
    masks[0, 2:5, 2:6] = True
    masks[1, 7:10, 9:14] = True
    true_xyz = np.array([[0.3, 0.32, 0.35], [0.2, 0.2, 0.2]])
    scores, de = rgb._scores(xyz, ref, masks, true_xyz, white_xy)
    np.testing.assert_allclose(de, rgb.delta_e2000(xyz, ref, white_xy))
    inside = de[masks.any(axis=0)]
    patch = rgb.delta_e2000(rgb.patch_means(xyz, masks), true_xyz, white_xy)
    expect = {
        "delta_e2000_mean": de.mean(),
        "delta_e2000_max": de.max(),
        "delta_e2000_p99": np.percentile(de, 99),
        "delta_e2000_patch_interior_mean": inside.mean(),
        "delta_e2000_patch_interior_max": inside.max(),
        "delta_e2000_patch_colour_vs_true_mean": patch.mean(),
        "delta_e2000_patch_colour_vs_true_max": patch.max(),
    }
    assert scores == pytest.approx(expect, rel=1e-12)
    assert scores["delta_e2000_max"] == pytest.approx(float(de[0, 0]))  # the wrong pixel
    assert scores["delta_e2000_patch_interior_max"] < scores["delta_e2000_max"] / 5
    assert scores["delta_e2000_patch_colour_vs_true_max"] > 5  # the second patch is not grey 0.2
