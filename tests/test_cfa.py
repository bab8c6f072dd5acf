"""The colour filter array (mbcapture.sensor.cfa): the mosaic, demosaicing and its reach, and the
sensor stage behind a CFA: one channel per photosite, shot and read noise per photosite, saturation
spread over the demosaiced footprint, a monochrome sensor's one response. Every application on a
CFA sensor runs end to end in tests/test_docs_and_configs.py."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config, run_capture
from mbcapture.sensor import (
    SensorConfig,
    electrons_per_render_second,
    mono_weights,
    simulate_reads,
)
from mbcapture.sensor.cfa import (
    BAYER_PATTERNS,
    DEMOSAIC_METHODS,
    channel_map,
    demosaic,
    demosaic_hdr,
    footprint_radius,
    spread_to_footprint,
    to_mosaic,
)

ROOT = Path(__file__).resolve().parents[1]


def _ideal(**kw) -> SensorConfig:
    """A sensor whose reads are its photo-electrons: gain 1, no black level, no fixed pattern, no read noise."""
    base = dict(
        gain_dn_per_e=1.0,
        black_level_dn=0.0,
        read_noise_e=0.0,
        prnu=0.0,
        dsnu_e=0.0,
        adc_bits=20,
        full_well_e=1e6,
        fd_full_well_e=4e6,
        dark_current_e_per_s=0.0,
    )
    return SensorConfig(**{**base, **kw})


@pytest.mark.parametrize("pattern", sorted(BAYER_PATTERNS))
def test_each_photosite_keeps_its_own_channel(pattern):
    img = np.random.default_rng(1).uniform(0, 1, (2, 6, 8, 3))
    m = to_mosaic(img, pattern)
    assert m.shape == (2, 6, 8, 1)
    tile = np.array(BAYER_PATTERNS[pattern]).reshape(2, 2)
    for y in range(6):
        for x in range(8):
            assert m[1, y, x, 0] == img[1, y, x, tile[y % 2, x % 2]]
    assert (
        "RGB"[channel_map(pattern, 2, 2)[0, 0]] == pattern[0] and "RGB"[channel_map(pattern, 2, 2)[1, 1]] == pattern[3]
    )


@pytest.mark.parametrize("pattern", sorted(BAYER_PATTERNS))
@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
def test_a_flat_colour_comes_back_exactly_up_to_the_borders(pattern, method):
    """colour-demosaicing alone repeats the edge photosite (another colour) at the border: the mirrored
    margin keeps every border pixel right too."""
    img = np.broadcast_to(np.array([0.8, 0.3, 0.1]), (13, 17, 3)).copy()
    np.testing.assert_allclose(demosaic(to_mosaic(img, pattern), pattern, method), img, atol=1e-12)


def test_bilinear_green_at_a_red_photosite_is_its_four_neighbours_mean_and_offsets_pass_linear_methods():
    raw = np.random.default_rng(5).uniform(0, 1000, (12, 12))
    b = demosaic(raw, "RGGB", "bilinear")
    assert b[4, 6, 1] == pytest.approx((raw[4, 5] + raw[4, 7] + raw[3, 6] + raw[5, 6]) / 4, rel=1e-12)
    assert b[4, 6, 0] == raw[4, 6]
    for method in ("bilinear", "malvar2004"):  # linear: a black level passes through unchanged
        np.testing.assert_allclose(
            demosaic(raw + 64.0, "RGGB", method), demosaic(raw, "RGGB", method) + 64.0, atol=1e-9
        )


@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
def test_a_photosite_reaches_exactly_the_stated_footprint(method):
    """Changing one photosite changes demosaiced pixels up to footprint_radius away and no further
    (the radius that saturation flags are spread by)."""
    raw = np.random.default_rng(0).uniform(0, 1, (48, 48))
    base = demosaic(raw, "RGGB", method)
    reach = 0
    for y, x in [(20, 20), (20, 21), (21, 20), (21, 21), (24, 25), (22, 27)]:
        for amp in (0.5, -0.3, 5.0):
            r2 = raw.copy()
            r2[y, x] += amp
            changed = np.argwhere(np.abs(demosaic(r2, "RGGB", method) - base).max(-1) > 0)
            reach = max(reach, int(np.abs(changed - [y, x]).max()))
    assert reach == footprint_radius(method)


def test_an_edge_gives_colour_that_three_stacked_photosites_do_not():
    img = np.zeros((16, 16, 3))
    img[:, 7:] = 1.0
    out = demosaic(to_mosaic(img, "RGGB"), "RGGB", "bilinear")
    assert np.abs(out - out.mean(-1, keepdims=True)).max() > 0.1


def test_saturation_spreads_over_the_footprint_in_every_channel():
    flags = np.zeros((1, 20, 20), bool)
    flags[0, 9, 11] = True
    for method in DEMOSAIC_METHODS:
        r = footprint_radius(method)
        out = spread_to_footprint(flags, method)
        assert out.shape == (1, 20, 20, 3) and out.all(-1).sum() == (2 * r + 1) ** 2
        assert out[0, 9 - r, 11 + r].all() and not out[0, 9 - r - 1, 11].any()


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_each_photosite_collects_only_its_channel_with_its_own_shot_noise(pattern):
    """A field of red light only: the green and blue photosites stay dark; the red ones are Poisson
    with the red mean (variance = mean, within 5 standard errors of the sample variance)."""
    H, W, mean = 128, 128, 400.0
    e = np.zeros((1, H, W, 3))
    e[..., 0] = mean
    out = simulate_reads(e, [(0,)], _ideal(cfa=pattern), np.random.SeedSequence(3))
    cmap = channel_map(pattern, H, W)
    mos = out.mosaic_dn[0]
    assert np.all(mos[cmap != 0] == 0)
    red = mos[cmap == 0]
    n = red.size
    assert abs(red.mean() - mean) < 5 * np.sqrt(mean / n)
    assert abs(red.var(ddof=1) - mean) < 5 * mean * np.sqrt(2.0 / (n - 1))
    assert out.electrons.shape == (1, H, W, 1) and out.reads_dn.shape == (1, H, W, 3)
    # the truth stays the ideal three-channel sensor's, and the demosaiced red is the red mean on average
    np.testing.assert_array_equal(out.reads_e_expected[0], e[0])
    assert abs(out.reads_dn[0, ..., 0].mean() - mean) < 5 * np.sqrt(mean / n)


def test_a_saturated_photosite_flags_its_footprint_and_only_itself_in_the_mosaic():
    e = np.full((1, 24, 24, 3), 100.0)
    e[0, 10, 10, 0] = 5e6  # (10, 10) is a red photosite of RGGB
    s = _ideal(cfa="RGGB", demosaic="malvar2004", full_well_e=1e4, fd_full_well_e=4e4)
    out = simulate_reads(e, [(0,)], s, np.random.SeedSequence(4))
    assert out.mosaic_saturated.sum() == 1 and out.mosaic_saturated[0, 10, 10]
    assert out.saturated[0].all(-1).sum() == 25 and out.saturated[0, 8:13, 8:13].all()


def test_read_noise_is_per_photosite_and_demosaicing_keeps_the_black_level():
    s = _ideal(cfa="RGGB", read_noise_e=5.0, black_level_dn=200.0, gain_dn_per_e=1.0)
    out = simulate_reads(np.zeros((1, 128, 128, 3)), [(0,)], s, np.random.SeedSequence(6))
    n = 128 * 128
    mos = out.mosaic_dn[0]
    assert abs(mos.mean() - 200.0) < 5 * 5.0 / np.sqrt(n)
    assert abs(mos.var(ddof=1) - (25.0 + 1 / 12)) < 5 * 25.0 * np.sqrt(2.0 / (n - 1))  # + rounding
    assert abs(out.reads_dn[0].mean() - 200.0) < 5 * 5.0 / np.sqrt(n)


def test_a_mono_sensor_has_one_response_the_sum_of_the_bands():
    s = SensorConfig(cfa="mono")
    k = electrons_per_render_second(SensorConfig(), "llvm_ad_rgb")
    w = mono_weights(s, "llvm_ad_rgb")
    np.testing.assert_allclose(w.sum(), 1.0)
    np.testing.assert_allclose(electrons_per_render_second(s, "llvm_ad_rgb"), k.sum())
    radiance = np.array([0.3, 0.5, 0.2])  # the renderer's mixture times the mono factor: every band's electrons
    assert (radiance @ w) * electrons_per_render_second(s, "llvm_ad_rgb")[0] == pytest.approx(radiance @ k)
    assert mono_weights(SensorConfig(), "llvm_ad_rgb") is None
    e = np.full((1, 64, 64, 3), 300.0)
    out = simulate_reads(e, [(0,)], _ideal(cfa="mono"), np.random.SeedSequence(2))
    assert out.electrons.shape == (1, 64, 64, 1)
    np.testing.assert_array_equal(out.reads_dn[..., 0], out.reads_dn[..., 2])
    np.testing.assert_array_equal(out.mosaic_dn, out.reads_dn[..., 0])
    n = 64 * 64
    assert abs(out.mosaic_dn.var(ddof=1) - 300.0) < 5 * 300.0 * np.sqrt(2.0 / (n - 1))


def test_a_bad_cfa_or_method_names_the_key():
    with pytest.raises(ValueError, match="cfa"):
        SensorConfig(cfa="RGBW")
    with pytest.raises(ValueError, match="demosaic"):
        SensorConfig(demosaic="vng")


@pytest.mark.render
def test_the_hdr_app_merges_photosites_then_demosaics(tmp_path):
    """A Bayer capture end to end: the HDR merge runs on the mosaic (each photosite's own saturation),
    the raw files keep the mosaic, and the result is close to the three-channel sensor's."""
    over = ["render.width=48", "render.height=40", "render.spp=4", "output.dng=true", "sensor.demosaic=malvar2004"]
    plain = run_capture(load_config(ROOT / "configs" / "metronome_hdr.yaml", over), tmp_path / "rgb", progress=False)
    bayer = run_capture(
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [*over, "sensor.cfa=RGGB"]),
        tmp_path / "bayer",
        progress=False,
    )
    assert bayer.mosaic_dn.shape == (4, 40, 48) and plain.mosaic_dn is None
    # same renders, same truth (the ideal three-channel sensor's)
    np.testing.assert_array_equal(bayer.reads_expected_e, plain.reads_expected_e)
    m_b, m_p = bayer.report["metrics"], plain.report["metrics"]
    assert m_b["hdr_rel_mse"] > m_p["hdr_rel_mse"]  # a mosaic loses resolution at edges
    assert m_b["hdr_valid_fraction"] > 0.95  # all reads clip only at the lamp (and within reach of it)
    import tifffile

    with tifffile.TiffFile(tmp_path / "bayer" / "read_J1.dng") as t:
        assert t.pages[0].photometric == 32803 and t.pages[0].shape == (40, 48)


@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
def test_hdr_demosaicing_keeps_a_dark_pixel_beside_a_bright_one_positive(method):
    """A lamp at 2000 on a wall at 0.01 (the metronome's contrast): demosaiced linearly, Malvar's and Menon's
    colour differences put the lamp's size on the wall with either sign (measured: RMS relative error in the
    ring of 2.5 px around it 9451 to 23722, bilinear included); in the logarithmic domain every value stays
    positive and that error is at most 1/100 of it (1.1 to 112). A flat colour comes back exactly, and values
    well within the floor of zero pass as the linear demosaicing's."""
    H, W = 24, 24
    wall, lamp = np.array([0.012, 0.010, 0.008]), np.array([2000.0, 1500.0, 900.0])
    yy, xx = np.mgrid[:H, :W]
    r = np.hypot(yy - 11.5, xx - 11.5)
    img = np.where((r < 4.5)[..., None], lamp, wall)
    ring = (r >= 4.5) & (r < 7)
    mosaic = to_mosaic(img, "RGGB")
    floor = np.full(3, 1e-4)
    log, linear = demosaic_hdr(mosaic, "RGGB", method, floor), demosaic(mosaic, "RGGB", method)
    assert (log > 0).all()
    if method != "bilinear":  # the linear methods' failure this replaces
        assert (linear < 0).any()

    def rms(a):
        return float(np.sqrt(np.mean((a[ring] / img[ring] - 1) ** 2)))

    assert rms(log) < rms(linear) / 100, (rms(log), rms(linear))
    flat = np.full((H, W, 3), [0.3, 0.5, 0.2])
    np.testing.assert_allclose(demosaic_hdr(to_mosaic(flat, "RGGB"), "RGGB", method, floor), flat, rtol=1e-9)
    small = np.random.default_rng(0).normal(0, 1e-7, (H, W, 3))  # far under the floor: asinh is linear there
    np.testing.assert_allclose(
        demosaic_hdr(to_mosaic(small, "RGGB"), "RGGB", method, 1.0),
        demosaic(to_mosaic(small, "RGGB"), "RGGB", method),
        atol=1e-12,
    )


#: How far a Bayer capture's HDR relMSE may lie above the sum of its two causes, the mosaic's (its noise-free
#: truth through the same demosaicing, ``demosaic_rel_mse``) and the noise's (the same capture without the
#: mosaic): measured 0.95x overall and 0.89x in the moving region on metronome_hdr at 128x96, 8 spp.
BAYER_HDR_FACTOR = 1.5


@pytest.mark.render
@pytest.mark.parametrize("config", ["metronome_hdr", "moving_light"])
def test_a_bayer_hdr_merge_has_no_negative_radiance_and_the_error_of_its_causes(config):
    over = ["render.width=96", "render.height=72", "render.spp=4", "render.cache=off"]
    plain = run_capture(load_config(ROOT / "configs" / f"{config}.yaml", over), progress=False)
    bayer = run_capture(load_config(ROOT / "configs" / f"{config}.yaml", [*over, "sensor.cfa=RGGB"]), progress=False)
    radiance, valid = bayer.images["radiance"], bayer.images["valid"] > 0
    assert not (radiance[valid] < 0).any() and (bayer.images["sigma"] >= 0).all()
    m_b, m_p = bayer.report["metrics"], plain.report["metrics"]
    for suffix in ("", "_moving"):
        bound = BAYER_HDR_FACTOR * (m_b["demosaic_rel_mse" + suffix] + m_p["hdr_rel_mse" + suffix])
        assert m_b["hdr_rel_mse" + suffix] <= bound, (suffix, m_b["hdr_rel_mse" + suffix], bound)


def test_characterize_measures_the_photosites_without_the_mosaic():
    """EMVA 1288 measures each colour's raw photosites; demosaiced frames would filter their noise."""
    from mbcapture.studies.characterize import monochromatic

    for cfa in ("RGGB", "mono"):
        cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [f"sensor.cfa={cfa}"])
        assert monochromatic(cfg).sensor.cfa == "none" and cfg.sensor.cfa == cfa
