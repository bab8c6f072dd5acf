"""RGB illumination: protocol, ambient subtraction, colour matrices, Bayer mosaic/demosaic, masks and
CIEDE2000 on small synthetic inputs with known answers (no rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from mbcapture import protocols, scenes
from mbcapture.apps import rgb_illumination as rgb
from mbcapture.capture import bucket_group_seconds
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

    wl, qe = channel_quantum_efficiency(SensorConfig(spectral_response="monochrome:Nikon 5100 (NPL)",
                                                     quantum_efficiency=[0.5, 0.5, 0.5]))
    np.testing.assert_array_equal(qe[0], qe[1])
    np.testing.assert_array_equal(qe[0], qe[2])
    assert qe.max() == pytest.approx(0.5)
    _, cam = channel_quantum_efficiency(SensorConfig(spectral_response="Nikon 5100 (NPL)", quantum_efficiency=[1, 1, 1]))
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


# -- Bayer ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("method", ["bilinear", "edge_aware"])
def test_mosaic_demosaic_flat_colour(pattern, method):
    img = np.broadcast_to(np.array([0.8, 0.3, 0.1]), (12, 16, 3)).copy()
    raw = rgb.mosaic(img, pattern)
    assert raw[0, 0] == img[0, 0, "RGB".index(pattern[0])] and raw[1, 1] == img[0, 0, "RGB".index(pattern[3])]
    out = rgb.demosaic(raw, pattern, method, peak=1.0)
    np.testing.assert_allclose(out[2:-2, 2:-2], img[2:-2, 2:-2], atol=2.0 / 65535)


def test_demosaic_edge_makes_colour_error_that_registered_channels_do_not():
    """A black/white vertical edge: a registered 3-channel image has no colour at the edge, the
    demosaiced mosaic does (the Bayer capture's cross-talk/demosaic error)."""
    img = np.zeros((16, 16, 3))
    img[:, 7:] = 1.0
    out = rgb.demosaic(rgb.mosaic(img, "RGGB"), "RGGB", "bilinear", peak=1.0)
    chroma = np.abs(out - out.mean(-1, keepdims=True)).max()
    assert chroma > 0.1
