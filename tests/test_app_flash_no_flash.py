"""flash_no_flash: protocol, filters and reconstruction on small synthetic inputs with known
answers, and one tiny render (interleaved vs sequential).

Statistical tolerances: a mean over n independent samples of variance s^2 has standard error
s / sqrt(n); variances estimated from n samples have relative standard error sqrt(2 / (n - 1)).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.application import protocol_app
from mbcapture.timing import protocols
from mbcapture.apps import CaptureData, get
from mbcapture.apps.flash_no_flash import (
    METHODS,
    FlashNoFlashParams,
    blur_agreement,
    components,
    display_psnr,
    enhance,
    flash_mask,
    joint_bilateral,
    reconstruct,
    rel_rms,
    white_level,
)
from mbcapture.capture.pipeline import bucket_group_seconds
from mbcapture.config import config_from_dict
from mbcapture.errors import ConfigError
from mbcapture.sensor import electrons_per_render_second, simulate_reads

N_SIGMA = 5.0
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "flash_no_flash.yaml"


#: OpenCV's joint bilateral filter works in float32 with a tabulated range kernel: its results are
#: the definition's within a few float32 ulps of the weighted sums (measured up to 7e-7 relative).
F32 = 4e-6


def _mirror(q, n):
    return -q if q < 0 else (2 * (n - 1) - q if q >= n else q)


def _edge(q, n):
    return min(max(q, 0), n - 1)


def brute_joint_bilateral(img, guide, ss, sr, truncate=2.5, border=_mirror):
    """The filter's definition, one pixel at a time (mirrored borders, or ``border=_edge``): the oracle
    of OpenCV's ximgproc filter. Range distance: the sum of absolute differences over the guide's
    channels (OpenCV's rule for a colour guide)."""
    H, W = img.shape[:2]
    r = int(np.ceil(truncate * ss))
    out = np.zeros_like(img, dtype=float)
    for y in range(H):
        for x in range(W):
            num, den = 0.0, 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dy * dy + dx * dx > r * r:
                        continue
                    qy, qx = border(y + dy, H), border(x + dx, W)
                    w = np.exp(
                        -(dy * dy + dx * dx) / (2 * ss**2)
                        - np.sum(np.abs(guide[qy, qx] - guide[y, x])) ** 2 / (2 * sr**2)
                    )
                    num = num + w * img[qy, qx]
                    den += w
            out[y, x] = num / den
    return out


# ----------------------------------------------------------------------------- filters
def test_joint_bilateral_matches_its_definition():
    rng = np.random.default_rng(0)
    img, guide = rng.random((9, 11, 3)), rng.random((9, 11, 3))
    np.testing.assert_allclose(
        joint_bilateral(img, guide, 1.3, 0.4), brute_joint_bilateral(img, guide, 1.3, 0.4), rtol=0, atol=F32
    )
    one = guide[..., 0]
    np.testing.assert_allclose(
        joint_bilateral(img, one, 1.3, 0.1), brute_joint_bilateral(img, one[..., None], 1.3, 0.1), rtol=0, atol=F32
    )


def test_joint_bilateral_keeps_constants_and_the_guides_edges():
    const = np.full((16, 16, 3), 0.7)
    np.testing.assert_allclose(
        joint_bilateral(const, np.random.default_rng(1).random((16, 16)), 2.0, 0.1), 0.7, rtol=F32
    )
    # image = guide = a step: a range sigma far below the step keeps it exactly (weights e^-5000)
    step = np.zeros((16, 16, 1))
    step[:, 8:] = 1.0
    np.testing.assert_allclose(joint_bilateral(step, step, 2.0, 0.01), step, atol=1e-12)
    # a noisy image with a clean step guide: smoothed within each side, the edge stays sharp
    rng = np.random.default_rng(2)
    noisy = step + rng.normal(0, 0.05, step.shape)
    out = joint_bilateral(noisy, step, 2.0, 0.05)
    assert abs(out[:, 7].mean() - 0.0) < 0.02 and abs(out[:, 8].mean() - 1.0) < 0.02


def test_joint_bilateral_noise_reduction_is_the_spatial_kernels():
    """Guide constant: the range kernel is 1, so for interior pixels the output variance is
    sigma^2 sum w^2 / (sum w)^2 exactly (w the truncated spatial Gaussian)."""
    ss, sigma = 1.5, 1.0
    rng = np.random.default_rng(3)
    noise = rng.normal(0, sigma, (400, 400, 1))
    out = joint_bilateral(noise, np.zeros((400, 400)), ss, 0.1)
    r = int(np.ceil(2.5 * ss))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    w = np.exp(-(yy**2 + xx**2) / (2 * ss**2)) * (yy**2 + xx**2 <= r * r)
    expected = sigma**2 * (w**2).sum() / w.sum() ** 2
    # independent samples: pixels 2r + 1 apart
    sample = out[r : -r : 2 * r + 1, r : -r : 2 * r + 1].ravel()
    n = sample.size
    assert sample.var(ddof=1) == pytest.approx(expected, rel=N_SIGMA * np.sqrt(2 / (n - 1)))


def test_detail_transfer_recovers_an_ambient_image_proportional_to_the_flash():
    """A = c F, noise-free, no mask: A_NR = c F_base and F_detail = (F + eps) / (F_base + eps),
    so A_NR F_detail -> c F = A as eps -> 0 (the bilateral's smoothing is undone exactly)."""
    rng = np.random.default_rng(4)
    f = 0.2 + rng.random((20, 24, 3))
    a = 0.03 * f
    p = FlashNoFlashParams(sigma_range=0.5, detail_eps=1e-9, shadow_threshold=0.0, mask_feather_px=0.0)
    c = components(a, f, np.zeros((20, 24), bool), p)
    assert not c.mask.any()
    assert np.abs(c.a_nr - a).max() > 0.1 * a.max()  # the filter did smooth
    np.testing.assert_allclose(enhance(c, "petschnigg"), a, rtol=2 * F32)  # two float32 filters
    np.testing.assert_allclose(enhance(c, "none"), a)


def test_mask_marks_flash_shadows_and_specularities():
    fo = np.ones((30, 30, 3))
    fo[5:15, 5:15] = 0.01  # shadow
    fo[20, 20] = 0.0  # one dark noise pixel: removed by the opening
    spec = np.zeros((30, 30), bool)
    spec[25, 5] = True
    m, shadow, specular = flash_mask(fo, spec, 0.05, dilate_px=1, feather_px=0.0)
    assert shadow[5:15, 5:15].all() and shadow[4, 5:15].all() and not shadow[3, 10]
    assert not shadow[20, 20] and not shadow[25:, 25:].any()
    assert specular[24:27, 5].all() and specular[25, 4:7].all() and specular.sum() == 5
    np.testing.assert_array_equal(m, (shadow | specular).astype(float))
    m_soft, _, _ = flash_mask(fo, spec, 0.05, dilate_px=1, feather_px=1.0)
    assert 0 < m_soft[10, 16] < 1 and m_soft[10, 10] == pytest.approx(1.0, abs=1e-6)


def test_display_psnr_clips_to_white():
    t = np.full((4, 4, 3), 0.5)
    x = t + 0.1
    assert display_psnr(x, t, 1.0) == pytest.approx(20.0)
    # above white both clip: no error
    assert display_psnr(np.full((4, 4, 3), 3.0), np.full((4, 4, 3), 2.0), 1.0) == np.inf


# ----------------------------------------------------------------------------- protocol
def _cfg(**capture):
    return config_from_dict(
        {
            "scene": {"name": "metronome"},
            "render": {"width": 32, "height": 24, "spp": 2},
            "capture": {"protocol": "flash_no_flash", "unit_exposure_s": 0.01, "periods": 8, **capture},
        }
    )


def test_protocol_interleaves_flash_and_ambient_buckets():
    cfg = _cfg()
    tl = protocols.build(cfg)
    assert [r.name for r in tl.reads] == ["flash", "noflash"] and tl.n_buckets == 2
    bg = bucket_group_seconds(tl, ("flash",))
    np.testing.assert_allclose(bg[:, 0], [0.01, 0.0], atol=1e-15)
    np.testing.assert_allclose([float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads], [0.01, 0.01])
    assert float(tl.seconds(tl.end_tick - tl.start_tick)) == pytest.approx(0.02)
    assert protocol_app("flash_no_flash") == "flash_no_flash"
    assert get("flash_no_flash").per_group


def test_sequential_protocol_is_two_frames_flash_first():
    cfg = _cfg(sequential=True)
    tl = protocols.build(cfg)
    assert tl.sequential and [r.name for r in tl.reads] == ["flash", "noflash"]
    np.testing.assert_allclose(bucket_group_seconds(tl, ("flash",))[:, 0], [0.01, 0.0], atol=1e-15)
    s0, s1 = tl.span_ticks([0]), tl.span_ticks([1])
    assert s0[1] < s1[0]
    gap = float(tl.seconds(s1[0] - s0[1]))
    assert gap == pytest.approx(cfg.sensor.frame_readout_s, rel=1e-6)


def test_bad_keys_are_config_errors():
    with pytest.raises(ConfigError, match="app.sigma_spatial_px"):
        config_from_dict({"capture": {"protocol": "flash_no_flash"}, "app": {"sigma_spatial_px": -1}})
    with pytest.raises(ConfigError, match="app.method"):
        config_from_dict({"capture": {"protocol": "flash_no_flash"}, "app": {"method": "magic"}})
    with pytest.raises(ConfigError, match="app.bogus"):
        config_from_dict({"capture": {"protocol": "flash_no_flash"}, "app": {"bogus": 1}})
    with pytest.raises(ConfigError, match="sensor.bucket_count"):
        protocols.build(config_from_dict({"capture": {"protocol": "flash_no_flash"}, "sensor": {"bucket_count": 1}}))


# ----------------------------------------------------------------------------- reconstruction
H, W = 40, 48


def synthetic(sequential: bool, seed: int = 0):
    """A capture whose noise-free per-group exposures are known: groups (ambient, flash).

    Albedo: a ramp 0.1..0.2 (grey-ish colour) with a bar of 0.9, the 'needle', at columns
    20..24 while the flash read collects; while the no-flash read collects the bar is there too
    (interleaved) or at columns 30..34 (sequential). Radiance = albedo x 0.05 for the ambient
    light (0.005..0.01, i.e. a noisy ~100..200 e- in 10 ms at ~1.8e6 e- per unit and second) and
    albedo x 0.3 for the flash, which casts a shadow (rows 5..14, columns 5..14).
    """
    cfg = _cfg(sequential=sequential)
    tl = protocols.build(cfg)
    t = 0.01
    yy, xx = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    rho = (0.1 + 0.1 * xx)[..., None] * np.array([1.0, 0.9, 0.8])
    rho_f, rho_a = rho.copy(), rho.copy()
    rho_f[:, 20:25] = 0.9
    rho_a[:, slice(30, 35) if sequential else slice(20, 25)] = 0.9
    amb_f, amb_a = 0.05 * rho_f, 0.05 * rho_a
    fl = 0.3 * rho_f
    fl[5:15, 5:15] = 0.0
    ge = np.zeros((2, 2, H, W, 3))
    ge[0, 0], ge[0, 1], ge[1, 0] = amb_f * t, fl * t, amb_a * t
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    moving = np.zeros((H, W), bool)
    moving[:, 18:37] = True
    sens = simulate_reads(ge.sum(1) * k_e, [(0,), (1,)], cfg.sensor, np.random.default_rng(seed))
    data = CaptureData(
        cfg=cfg,
        scene=None,
        timeline=tl,
        plan=SimpleNamespace(groups=("ambient", "flash")),
        read_names=["flash", "noflash"],
        exposure_s=np.array([t, t]),
        reads_dn=sens.reads_dn,
        saturated=sens.saturated,
        reads_e_expected=sens.reads_e_expected,
        bucket_exposure=ge.sum(1),
        k_e=k_e,
        moving_mask=moving,
        switchable=("flash",),
        bucket_group_s=bucket_group_seconds(tl, ("flash",)),
        group_exposure=ge,
    )
    return data, dict(amb_f=amb_f, amb_a=amb_a, flash_only=fl, k_e=k_e, t=t)


def test_reconstruction_images_and_truths():
    data, tr = synthetic(sequential=False)
    out = reconstruct(data, FlashNoFlashParams())
    im = out.images
    np.testing.assert_allclose(im["truth_ambient"], tr["amb_a"], rtol=1e-12)
    np.testing.assert_allclose(im["truth_flash_only"], tr["flash_only"], rtol=1e-12)
    # flash and no-flash reads are unbiased radiance: mean over the image within shot + read noise
    e_per_px = tr["amb_a"] * tr["k_e"] * tr["t"]
    se = np.sqrt((e_per_px + data.cfg.sensor.read_noise_e**2).sum()) / e_per_px.size / (tr["k_e"].mean() * tr["t"])
    dsnu = data.cfg.sensor.dsnu_e / np.sqrt(e_per_px.size) / (tr["k_e"].min() * tr["t"])
    prnu = data.cfg.sensor.prnu / np.sqrt(e_per_px.size) * tr["amb_a"].mean()
    assert abs(im["noflash"].mean() - tr["amb_a"].mean()) < N_SIGMA * (se + dsnu + prnu) + 1e-12
    fo, sl = im["flash_only"], np.s_[20:, 26:]
    assert abs(fo[sl].mean() - tr["flash_only"][sl].mean()) < 0.01 * tr["flash_only"][sl].mean()  # PRNU 1 %
    m = out.metrics
    assert m["reads"] == {"flash": "flash", "noflash": "noflash"} and m["flash_groups"] == ["flash"]
    # interleaved: identical ambient components, so the noise-free difference is exact
    assert m["motion_blur_agreement"]["moving_region"]["rel_rms"] == 0.0
    assert m["flash_only"]["ghost_rel_mse_moving"] < 1e-25  # float rounding of x t / t only
    # the shadow rectangle is in the mask, the flash-lit area is not
    assert m["mask_fraction"]["shadow"] > 100 / (H * W)
    assert im["mask"][8, 8, 0] == 1.0 and im["mask"][30, 40, 0] == 0.0
    assert set(m["enhanced"]["by_method"]) == set(METHODS)
    for name in ("flash", "noflash", "flash_only", "enhanced", "truth_ambient", "truth_flash_only", "mask"):
        assert name in out.png


def test_flash_guided_denoising_beats_the_noisy_read_interleaved():
    data, _ = synthetic(sequential=False)
    m = reconstruct(data, FlashNoFlashParams(method="joint_bilateral")).metrics["enhanced"]
    assert m["gain_db"] > 3.0 and m["gain_db_moving"] > 3.0


def test_sequential_capture_shows_ghosts_the_interleaved_one_does_not():
    (di, _), (ds, tr) = synthetic(False, seed=5), synthetic(True, seed=5)
    p = FlashNoFlashParams(method="joint_bilateral")
    mi, ms = reconstruct(di, p).metrics, reconstruct(ds, p).metrics
    # known answer: the bar is at columns 20..24 in one read and 30..34 in the other
    base = tr["amb_a"]
    d = tr["amb_f"] - tr["amb_a"]
    mask = ds.moving_mask
    expected = np.sqrt(np.mean(d[mask] ** 2)) / base[mask].mean()
    got = ms["motion_blur_agreement"]["moving_region"]["rel_rms"]
    assert got == pytest.approx(expected, rel=1e-12) and got > 0.5
    assert mi["motion_blur_agreement"]["moving_region"]["rel_rms"] == 0.0
    # ghosts in the flash-only image: the ambient bar, +0.045 where it was and -0.045 where it went
    assert ms["flash_only"]["ghost_rel_mse_moving"] > 0.0
    assert ms["flash_only"]["rel_mse_moving"] > 2 * mi["flash_only"]["rel_mse_moving"]
    assert mi["enhanced"]["psnr_db_moving"] > ms["enhanced"]["psnr_db_moving"] + 3.0


def test_reconstruction_needs_one_flash_read():
    data, _ = synthetic(False)
    data.bucket_group_s = np.zeros_like(data.bucket_group_s)
    with pytest.raises(ConfigError, match="capture.protocol"):
        reconstruct(data, FlashNoFlashParams())


# ----------------------------------------------------------------------------- tiny render
@pytest.mark.render
def test_tiny_render_interleaved_beats_sequential():
    from mbcapture import run_capture

    over = ["render.width=64", "render.height=48", "render.spp=2", "render.max_motion_px=2.0", "render.min_strata=1"]
    res = {}
    for seq in (False, True):
        cfg = load_config(CONFIG, over + [f"capture.sequential={str(seq).lower()}"])
        res[seq] = run_capture(cfg, progress=False).report["metrics"]
    i, s = res[False], res[True]
    assert i["motion_blur_agreement"]["letter_s"]["pixels"] > 0
    assert i["motion_blur_agreement"]["letter_s"]["rel_rms"] < 0.05
    assert s["motion_blur_agreement"]["letter_s"]["rel_rms"] > 5 * i["motion_blur_agreement"]["letter_s"]["rel_rms"]
    assert s["flash_only"]["ghost_rel_mse_moving"] > 10 * i["flash_only"]["ghost_rel_mse_moving"]


def test_mask_threshold_opening_disc_and_feathered_border():
    """Shadow = luminance strictly below the threshold; the 3x3 opening keeps a 3x3 shadow and
    drops a 2x3 one; dilation is by a Euclidean disc of dilate_px; feathering treats the image
    as continued by its edge pixels."""
    from scipy import ndimage

    fo = np.ones((24, 24, 3))
    fo[3:6, 3:6] = 0.2  # a 3x3 shadow: kept by the 3x3 opening
    fo[3:5, 12:15] = 0.2  # 2x3: removed
    fo[14:19, 3:8] = 0.5  # exactly at the threshold: not a shadow
    fo[14:19, 12:17] = 0.4999  # just below: a shadow
    no_spec = np.zeros((24, 24), bool)
    m0, shadow0, spec0 = flash_mask(fo, no_spec, 0.5, dilate_px=0, feather_px=0.0)
    expect = np.zeros((24, 24), bool)
    expect[3:6, 3:6] = True
    expect[14:19, 12:17] = True
    np.testing.assert_array_equal(shadow0, expect)
    np.testing.assert_array_equal(m0, expect.astype(float))
    assert spec0.dtype == bool and not spec0.any()
    spec = np.zeros((24, 24), bool)
    spec[9, 20] = True
    _, shadow2, spec2 = flash_mask(fo, spec, 0.5, dilate_px=2, feather_px=0.0)
    np.testing.assert_array_equal(shadow2, ndimage.distance_transform_edt(~expect) <= 2)
    np.testing.assert_array_equal(spec2, ndimage.distance_transform_edt(~spec) <= 2)
    # a shadow band along the left edge, feathered: as if the band went on beyond the border
    fo_b = np.ones((12, 16, 3))
    fo_b[:, :4] = 0.0
    band = np.zeros((12, 16))
    band[:, :4] = 1.0
    m_soft, _, _ = flash_mask(fo_b, np.zeros((12, 16), bool), 0.5, dilate_px=0, feather_px=3.0)
    wide = np.pad(band, 20, mode="edge")
    np.testing.assert_allclose(m_soft, ndimage.gaussian_filter(wide, 3.0)[20:-20, 20:-20], atol=1e-9)


def test_letter_s_mask_is_the_region_its_points_sweep_over_the_capture():
    """The region swept by the motion points the scene names as the letter S, between the
    timeline's first and last tick; None without those points or without motion."""
    import dataclasses
    from fractions import Fraction

    from mbcapture.apps.flash_no_flash import _letter_s_mask
    from mbcapture.scene.camera_motion import moving_region
    from mbcapture.scene.scenes import Camera, SceneModel
    from mbcapture.timing.timeline import ReadEvent, SegmentSeconds, SlotSeconds, build_timeline

    def points(t):  # (T, 5, 3): 0-1 a pair moving right at 2 m/s, 2-4 a triangle ("the S") moving down at 2 m/s
        t = np.asarray(t, float)[:, None]
        pair = np.stack(
            [np.hstack([-0.6 + 2 * t, 0.3 + 0 * t, 2 + 0 * t]), np.hstack([-0.5 + 2 * t, 0.4 + 0 * t, 2 + 0 * t])],
            axis=1,
        )
        tri = np.stack(
            [
                np.hstack([0.3 + 0 * t, 0.5 - 2 * t, 2 + 0 * t]),
                np.hstack([0.5 + 0 * t, 0.5 - 2 * t, 2 + 0 * t]),
                np.hstack([0.4 + 0 * t, 0.3 - 2 * t, 2 + 0 * t]),
            ],
            axis=1,
        )
        return np.concatenate([pair, tri], axis=1)

    cam = Camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), 90.0)
    scene = SceneModel(
        "synthetic",
        ("ambient",),
        frozenset(),
        cam,
        None,
        None,
        motion_points=points,
        extra={"letter_s_points": (2, 3, 4)},
    )
    ms = Fraction(1, 1000)
    tl = build_timeline(
        [SegmentSeconds(50 * ms, (SlotSeconds(0, 20 * ms), SlotSeconds(1, 20 * ms)), 2)],
        [ReadEvent("F", (0,)), ReadEvent("A", (1,))],
        2,
        "two",
    )
    assert float(tl.seconds(tl.start_tick)) == pytest.approx(0.05) and float(tl.seconds(tl.end_tick)) == pytest.approx(
        0.13
    )
    W, H = 40, 30
    data = SimpleNamespace(scene=scene, timeline=tl, moving_mask=np.zeros((H, W), bool))
    got = _letter_s_mask(data)
    only_s = dataclasses.replace(scene, motion_points=lambda t: points(t)[:, 2:])
    np.testing.assert_array_equal(got, moving_region(only_s, 0.05, 0.13, W, H))
    everything = moving_region(scene, 0.05, 0.13, W, H)
    assert got.sum() > 20 and (got & ~everything).sum() < 5 and (everything & ~got).sum() > 20
    # the triangle moves 0.16 m down at 2 m away: ~3.2 px of 40; over a longer window it sweeps further
    assert not np.array_equal(got, moving_region(only_s, 0.0, 0.13, W, H))
    assert not np.array_equal(got, moving_region(only_s, 0.05, 0.2, W, H))
    assert _letter_s_mask(SimpleNamespace(scene=None, timeline=tl, moving_mask=data.moving_mask)) is None
    plain = dataclasses.replace(scene, extra={})
    assert _letter_s_mask(SimpleNamespace(scene=plain, timeline=tl, moving_mask=data.moving_mask)) is None
    still = dataclasses.replace(scene, motion_points=None)
    assert _letter_s_mask(SimpleNamespace(scene=still, timeline=tl, moving_mask=data.moving_mask)) is None


def test_joint_bilateral_on_an_image_narrower_than_its_radius_repeats_the_edge():
    """When the window is wider than the image (min(H, W) <= r) the border is the edge pixel
    repeated, not a mirror."""
    rng = np.random.default_rng(5)
    img = rng.uniform(0, 1, (7, 3, 2))  # r = ceil(2.5 * 1.2) = 3 = W
    out = joint_bilateral(img, img, 1.2, 0.3)
    expect = brute_joint_bilateral(img, img, 1.2, 0.3, border=_edge)
    np.testing.assert_allclose(out, expect, rtol=0, atol=F32)


def test_components_do_not_depend_on_the_units_of_radiance():
    """Filters, detail layer and mask work in fractions of each image's white: scaling both
    images by k scales the filtered ambient images by k and leaves the detail layer and the mask
    unchanged; the detail layer of a flat flash image is exactly 1; the shadow is where the flash
    adds nothing to the ambient light."""
    rng = np.random.default_rng(6)
    H, W = 20, 24
    ambient = rng.uniform(0.2, 0.4, (H, W, 3))
    flash = ambient + 0.8  # the flash adds 0.8 everywhere ...
    flash[6:12, 8:16] = ambient[6:12, 8:16]  # ... except in its shadow
    p = FlashNoFlashParams(mask_dilate_px=0, mask_feather_px=0.0)
    c1 = components(ambient, flash, np.zeros((H, W), bool), p)
    expect_shadow = np.zeros((H, W), bool)
    expect_shadow[6:12, 8:16] = True
    np.testing.assert_array_equal(c1.shadow, expect_shadow)
    k = 37.0
    ck = components(k * ambient, k * flash, np.zeros((H, W), bool), p)
    np.testing.assert_allclose(ck.a_nr, k * c1.a_nr, rtol=F32)
    np.testing.assert_allclose(ck.a_base, k * c1.a_base, rtol=F32)
    np.testing.assert_allclose(ck.f_detail, c1.f_detail, rtol=F32)
    np.testing.assert_array_equal(ck.mask, c1.mask)
    flat = components(ambient, np.full((H, W, 3), 5.0), np.zeros((H, W), bool), p)
    np.testing.assert_allclose(flat.f_detail, 1.0, rtol=F32)
    # a flat coloured scene comes out of both filters as it went in, in its own units
    colour_ = np.broadcast_to([0.2, 0.4, 0.6], (H, W, 3))
    c_flat = components(colour_, 3.0 * colour_, np.zeros((H, W), bool), p)
    np.testing.assert_allclose(c_flat.a_base, colour_, rtol=F32)
    np.testing.assert_allclose(c_flat.a_nr, colour_, rtol=F32)


def test_white_level_rel_rms_blur_agreement_and_display_psnr():
    img = np.zeros((10, 10, 3))
    img[:, :5] = 0.5  # half the pixels at luminance 0.5
    assert white_level(img, 90.0) == pytest.approx(0.5)
    assert white_level(np.zeros((4, 4, 3)), 99.0) == 1.0  # black: white is 1 render unit
    mask = np.zeros((10, 10), bool)
    mask[2:4, 2:4] = True
    # over a black reference the RMS is absolute
    assert rel_rms(np.full_like(img, 0.3), np.zeros_like(img), mask) == pytest.approx(0.3)
    assert blur_agreement(img + 0.1, img, mask) == {"pixels": 4, "rel_rms": pytest.approx(0.2)}
    assert blur_agreement(img + 0.1, img, np.zeros((10, 10), bool)) == {"pixels": 0}
    # the mask selects the pixels scored; values below 0 display as black
    x = img.copy()
    x[8, 8] += 0.4  # outside the mask
    x[2, 2] += 0.1
    assert display_psnr(x, img, 1.0, mask) == pytest.approx(
        10 * np.log10(1 / (0.1**2 / 4))
    )  # one of 4 pixels off by 0.1
    assert display_psnr(img - 0.5, np.zeros_like(img), 1.0) == np.inf
    assert display_psnr(np.zeros_like(img), img - 0.5, 1.0) == np.inf


def test_read_roles_from_the_switchable_groups_each_read_saw():
    from mbcapture.apps.flash_no_flash import _read_roles
    from mbcapture.timing.timeline import ReadEvent

    # buckets 0-1 make the no-flash read, bucket 2 the flash read; bucket 0 saw nothing switchable,
    # bucket 2 saw flash2 only (seconds per switchable group, columns flash, flash2)
    data = SimpleNamespace(
        read_names=["A", "F"],
        switchable=("flash", "flash2"),
        bucket_group_s=np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.01]]),
        timeline=SimpleNamespace(reads=[ReadEvent("A", (0, 1)), ReadEvent("F", (2,))]),
    )
    assert _read_roles(data) == (1, 0, ["flash2"])
    data.timeline = SimpleNamespace(reads=[ReadEvent("A", (2,)), ReadEvent("F", (0, 1))])
    data.bucket_group_s = np.array([[0.0, 0.02], [0.0, 0.0], [0.0, 0.0]])
    assert _read_roles(data) == (1, 0, ["flash2"])
    with pytest.raises(ConfigError, match="capture.protocol: flash_no_flash needs exactly two reads"):
        _read_roles(SimpleNamespace(read_names=["A", "F"], bucket_group_s=None))
    data.bucket_group_s = np.array([[0.0, 0.02], [0.0, 0.0], [0.01, 0.0]])  # both reads lit
    with pytest.raises(ConfigError, match="capture.protocol: flash_no_flash needs one read lit"):
        _read_roles(data)
