"""Flash matting: protocol timing, flash-only image, trimap, matting methods and scores on small
synthetic inputs with known answers; the rendered coverage truth against the area of a disk; one
tiny end-to-end capture, interleaved against sequential."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.apps import CaptureData
from mbcapture.apps import flash_matting as fm
from mbcapture.errors import ConfigError
from mbcapture.reconstruct import matting as mt

T_S = 0.002


def _cfg(*extra):
    return load_config(
        None,
        [
            "capture.protocol=flash_matting",
            f"capture.unit_exposure_s={T_S}",
            "capture.periods=8",
            "scene.name=flash_toy",
            *extra,
        ],
    )


# ----------------------------------------------------------------------------- protocol
@pytest.mark.parametrize("n_flash, exposures", [(2, (2 * T_S, 2 * T_S)), (3, (3 * T_S, T_S))])
def test_protocol_exposures_flash_and_equal_centroids(n_flash, exposures):
    tl = protocols.build(_cfg(f"app.flash_buckets={n_flash}"))
    reads = {r.name: r for r in tl.reads}
    assert list(reads) == ["flash", "noflash"]
    for name, t in zip(("flash", "noflash"), exposures):
        assert float(tl.read_exposure_ticks(reads[name]) * tl.tick_s) == pytest.approx(t, rel=1e-12)
    # the slot order is symmetric: both reads have the same time centroid (exact rationals)
    assert tl.centroid_ticks(reads["flash"].buckets) == tl.centroid_ticks(reads["noflash"].buckets)
    # the flash is on in every flash slot and in no other
    for k in range(4):
        on = int(tl.gated_ticks([tl.end_tick], k, "flash")[0])
        assert on == (tl.exposure_ticks(k) if k in reads["flash"].buckets else 0)
    assert float((tl.end_tick - tl.start_tick) * tl.tick_s) == pytest.approx(4 * T_S)


def test_sequential_takes_two_frames_with_the_readout_gap():
    cfg = _cfg("capture.sequential=true", "sensor.frame_readout_s=0.03")
    tl = protocols.build(cfg)
    d = tl.describe_reads()
    assert [r["name"] for r in d] == ["flash", "noflash"] and all(r["destructive"] for r in d)
    assert d[1]["span_start_s"] - d[0]["span_end_s"] == pytest.approx(0.03)
    assert d[0]["exposure_s"] == pytest.approx(2 * T_S)


def test_protocol_needs_four_buckets_and_valid_keys():
    with pytest.raises(ConfigError, match="capture.protocol.*4 buckets"):
        protocols.build(_cfg("sensor.bucket_count=2"))
    with pytest.raises(ConfigError, match="app.flash_buckets"):
        _cfg("app.flash_buckets=1")
    with pytest.raises(ConfigError, match="trimap_bg_fraction"):
        _cfg("app.trimap_bg_fraction=0.5", "app.trimap_fg_fraction=0.4")


# ----------------------------------------------------------------------------- pure functions
def test_flash_only_cancels_ambient_at_different_exposures():
    rng = np.random.default_rng(0)
    ambient, flash = rng.uniform(0, 1, (5, 6, 3)), rng.uniform(0, 2, (5, 6, 3))
    k_e = np.array([1e6, 2e6, 1.5e6])
    t_f, t_n = 3e-3, 1e-3  # the 3:1 split
    got = fm.flash_only_image((ambient + flash) * k_e * t_f, t_f, ambient * k_e * t_n, t_n, k_e)
    np.testing.assert_allclose(got, flash, rtol=1e-12, atol=1e-12)


def test_flash_ratio_cue_cancels_albedo_and_keeps_distance():
    # two near surfaces of albedo 0.1 and 0.8, and one 3x farther (1/9 of the flash), albedo 0.8
    albedo = np.array([0.1, 0.8, 0.8])
    e_flash = np.array([1.0, 1.0, 1.0 / 9.0])
    e_amb = 0.5
    fo = (albedo * e_flash)[None, :, None].repeat(3, -1)
    nf = (albedo * e_amb)[None, :, None].repeat(3, -1)
    cue = mt.trimap_cue(fo, nf, "flash_ratio", percentile=100.0, ratio_eps=1e-9)
    np.testing.assert_allclose(cue[0], [1.0, 1.0, 1.0 / 9.0], rtol=1e-6)
    lum = mt.trimap_cue(fo, nf, "flash_only", percentile=100.0)
    np.testing.assert_allclose(lum[0], albedo * e_flash / 0.8, rtol=1e-12)


def test_trimap_thresholds_opening_and_erosion():
    h = w = 41
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(yy - 20, xx - 20)
    cue = np.where(r <= 10, 1.0, 0.0)
    cue[2, 2] = 1.0  # a one-pixel speck of noise in the background
    cue[(r > 10) & (r <= 11)] = 0.5  # a mixed ring: neither candidate
    tri = mt.make_trimap(cue, fg_fraction=0.8, bg_fraction=0.2, open_px=1, erode_px=2)
    assert set(np.unique(tri)) == {0.0, 0.5, 1.0}
    assert tri[20, 20] == 1.0 and tri[20, 40] == 0.0
    # the speck is opened away from the foreground; the hole it leaves in the background candidate
    # (eroded by 2 px) is unknown, for the matting to decide
    assert tri[2, 2] == 0.5 and tri[2, 6] == 0.0
    # erosion by a disc of radius 2: the definite regions end about 2 px inside the candidates
    assert np.all(r[tri == 1.0] <= 10 - 1) and np.all(tri[r <= 10 - 3] == 1.0)  # fg candidate: r <= 10
    far_from_speck = np.hypot(yy - 2, xx - 2) > 4
    assert np.all(r[(tri == 0.0)] > 11 + 1) and np.all(tri[(r > 11 + 3) & far_from_speck] == 0.0)  # bg: r > 11
    # no erosion, no opening: exactly the thresholds
    raw = mt.make_trimap(cue, 0.8, 0.2, open_px=0, erode_px=0)
    np.testing.assert_array_equal(raw, np.where(cue >= 0.8, 1.0, np.where(cue <= 0.2, 0.0, 0.5)))
    with pytest.raises(ValueError):
        mt.make_trimap(cue, 0.2, 0.8)


def _composite(h=40, w=48):
    """A soft vertical edge: alpha ramps 0 -> 1 over 8 px; constant foreground and background colours."""
    x = np.arange(w) + 0.5
    alpha = np.clip((x - 20) / 8.0, 0, 1)[None, :].repeat(h, 0)
    fg, bg = np.array([0.9, 0.6, 0.2]), np.array([0.1, 0.2, 0.4])
    image = alpha[..., None] * fg + (1 - alpha[..., None]) * bg
    tri = np.where(alpha >= 1, 1.0, np.where(alpha <= 0, 0.0, 0.5))
    tri[:, 16:32] = 0.5  # a wider unknown band than the ramp
    return image, tri, alpha


@pytest.mark.parametrize("method, max_err, mean_err", [("closed_form", 1e-3, 1e-4), ("knn", 0.2, 0.08)])
def test_matting_recovers_a_known_alpha(method, max_err, mean_err):
    image, tri, alpha = _composite()
    got = mt.estimate_alpha(image, tri, method)
    err = np.abs(got - alpha)[tri == 0.5]
    assert err.max() < max_err and err.mean() < mean_err  # knn is approximate (nearest neighbours in feature space)
    assert np.all(got[tri == 1.0] == 1.0) and np.all(got[tri == 0.0] == 0.0)


def test_matting_methods_registry_and_degenerate_trimaps():
    image, tri, alpha = _composite(8, 12)
    with pytest.raises(ConfigError, match="app.matting"):
        mt.estimate_alpha(image, tri, "magic")
    ramp = np.linspace(-0.5, 1.5, tri.size).reshape(tri.shape)
    np.testing.assert_allclose(
        mt.estimate_alpha(image, tri, "threshold", ramp)[tri == 0.5], np.clip(ramp, 0, 1)[tri == 0.5]
    )
    only_unknown_and_bg = np.where(tri == 1.0, 0.5, tri)  # no foreground: nothing to propagate
    got = mt.estimate_alpha(image, only_unknown_and_bg, "closed_form", ramp)
    np.testing.assert_allclose(got[only_unknown_and_bg == 0.5], np.clip(ramp, 0, 1)[only_unknown_and_bg == 0.5])


def test_matte_scores_and_trimap_errors_by_hand():
    a = np.array([[0.0, 0.5], [1.0, 1.0]])
    t = np.array([[0.0, 1.0], [0.5, 1.0]])
    s = fm.matte_scores(a, t)
    assert s == {"pixels": 4, "sad": 1.0, "mse": pytest.approx(0.125)}
    assert fm.matte_scores(a, t, np.array([[False, True], [False, False]]))["sad"] == 0.5
    tri = np.array([[1.0, 0.0], [0.5, 0.0]])
    assert fm.trimap_errors(tri, np.array([[0.0, 1.0], [0.3, 0.0]])) == {"fg_on_background": 1, "bg_on_foreground": 1}


@pytest.mark.parametrize("n_flash", [2, 3])
def test_reconstruct_on_synthetic_reads_recovers_the_matte(n_flash):
    """Noise-free synthetic reads of a soft-edged disc that the flash lights 10x more than the
    background: the trimap (eroded by more than the 3-px soft edge) and closed-form matte recover its alpha.
    At 2:2 and at 3:1 (reads of 3T and T, exposures from the timeline): the flash, no-flash and
    flash-only images are each read's own radiance, so a read normalised by the other's exposure fails."""
    cfg = _cfg("app.trimap_erode_px=3", f"app.flash_buckets={n_flash}")
    tl = protocols.build(cfg)
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    alpha = np.clip((14.0 - np.hypot(yy - 24, xx - 32)) / 3 + 0.5, 0, 1)  # 3-px soft edge
    fg_col, bg_col = np.array([0.2, 0.6, 0.1]), np.array([0.7, 0.5, 0.4])
    amb = alpha[..., None] * fg_col * 0.3 + (1 - alpha[..., None]) * bg_col * 0.3
    fl = alpha[..., None] * fg_col * 0.6 + (1 - alpha[..., None]) * bg_col * 0.6 / 10.0
    k_e = np.array([1e6, 1.5e6, 0.8e6])
    t_f, t_n = (float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads)
    assert (t_f, t_n) == pytest.approx((n_flash * T_S, (4 - n_flash) * T_S), rel=1e-12)
    reads_e = np.stack([(amb + fl) * k_e * t_f, amb * k_e * t_n])
    s = cfg.sensor
    data = CaptureData(
        cfg=cfg,
        scene=SimpleNamespace(name="synthetic"),
        timeline=tl,
        plan=SimpleNamespace(groups=("ambient", "flash")),
        read_names=["flash", "noflash"],
        exposure_s=np.array([t_f, t_n]),
        reads_dn=reads_e * s.gain_dn_per_e + s.black_level_dn,
        saturated=np.zeros(reads_e.shape, bool),
        reads_e_expected=reads_e,
        bucket_exposure=np.zeros((4, h, w, 3)),
        k_e=k_e,
        moving_mask=np.zeros((h, w), bool),
        switchable=("flash",),
        bucket_group_s=None,
        group_exposure=None,
    )
    out = fm.reconstruct(data, cfg.app.resolve(cfg.capture.protocol)[1])
    np.testing.assert_allclose(out.images["flash_only"], fl, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.images["flash"], amb + fl, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.images["noflash"], amb, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(
        out.images["flash_only"], fm.flash_only_image(data.reads_e()[0], t_f, data.reads_e()[1], t_n, k_e)
    )  # the tested function is the one used
    assert out.metrics["split"] == f"{n_flash}:{4 - n_flash}"
    assert out.metrics["reads"] == {"flash_exposure_s": t_f, "noflash_exposure_s": t_n}
    assert out.metrics["alpha_truth"] is None
    got = out.images["alpha"][..., 0]
    assert np.abs(got - alpha).sum() < 0.01 * alpha.sum()
    assert np.abs(got - alpha).max() < 0.05
    assert set(out.png) >= {"flash_only", "trimap", "alpha", "extracted"}


# ----------------------------------------------------------------------------- rendered
@pytest.mark.render
def test_coverage_of_a_disk_is_its_projected_area():
    from mbcapture.render.build import Material, SceneBuild, Shape, scale, translate
    from mbcapture.render.coverage import coverage_alpha
    from mbcapture.scene.scenes import Camera, SceneModel

    cam = Camera(origin=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=40.0)
    radius, w, h = 0.1, 64, 48
    disk = Shape("disk", "disk", translate(0, 0, 0) @ scale(radius), Material((0.5, 0.5, 0.5)))
    scene = SceneModel(
        "disk", ("light",), frozenset(), cam, SceneBuild(shapes=(disk,)), None, extra={"foreground": ("disk",)}
    )
    spp, strata = 16, 2
    alpha = coverage_alpha(scene, np.zeros(strata), np.ones(strata), w, h, spp, np.random.SeedSequence(1))
    px_per_m = w / (2 * np.tan(np.radians(20.0)))  # at distance 1 m
    area_px = np.pi * (radius * px_per_m) ** 2
    # only edge pixels are random: var alpha(1 - alpha) / (spp * strata) each, at most 1/4
    edge = (alpha > 0) & (alpha < 1)
    sigma = np.sqrt(edge.sum() * 0.25 / (spp * strata))
    assert abs(alpha.sum() - area_px) < 5 * sigma + 0.01 * area_px
    assert alpha[h // 2, w // 2] == 1.0 and alpha[0, 0] == 0.0


@pytest.mark.render
def test_tiny_capture_interleaved_beats_sequential():
    common = [
        "render.width=80",
        "render.height=64",
        "render.spp=4",
        "render.max_motion_px=1.0",
        "render.min_strata=1",
        "app.truth_spp=4",
        "scene.wave_hz=4",
    ]
    from mbcapture import run_capture

    cfg_path = __import__("pathlib").Path(__file__).resolve().parents[1] / "configs" / "flash_matting.yaml"
    inter = run_capture(load_config(cfg_path, common), progress=False)
    seq = run_capture(load_config(cfg_path, common + ["capture.sequential=true"]), progress=False)
    mi, ms = inter.report["metrics"], seq.report["metrics"]
    for m in (mi, ms):
        assert {"alpha", "alpha_unknown", "alpha_moving", "flash_only_rel_mse", "alpha_by_image"} <= set(m)
        assert 0 <= inter.images["alpha"].min() and inter.images["alpha"].max() <= 1
    truth = inter.images["alpha_truth"][..., 0]
    assert 0.05 < truth.mean() < 0.5  # the plant covers part of the frame
    assert mi["alpha_moving"]["sad"] < ms["alpha_moving"]["sad"]
    assert mi["flash_only_rel_mse_moving"] < ms["flash_only_rel_mse_moving"]


def test_matte_scores_of_an_empty_region_and_trimap_error_thresholds():
    assert fm.matte_scores(np.ones((2, 2)), np.zeros((2, 2)), np.zeros((2, 2), bool)) == {
        "pixels": 0,
        "sad": 0.0,
        "mse": None,
    }
    # truth exactly at the tolerance is not an error (strict inequalities); unknown pixels never are
    tri = np.array([[1.0, 1.0, 0.0, 0.0, 0.5, 0.5]])
    truth = np.array([[0.05, 0.0499, 0.95, 0.9501, 0.0, 1.0]])
    assert fm.trimap_errors(tri, truth, tol=0.05) == {"fg_on_background": 1, "bg_on_foreground": 1}


# ----------------------------------------------------------------------------- exact small cases
def test_reference_level_and_trimap_cue_by_hand():
    assert mt.reference_level(np.zeros(0), 99.0) == 1.0  # nothing to measure
    assert mt.reference_level(np.zeros((3, 3)), 99.0) == 1.0  # black: 1 render unit
    assert mt.reference_level(np.arange(101.0), 50.0) == 50.0
    rng = np.random.default_rng(11)
    n = rng.uniform(0.0, 3.0, (6, 7))
    n[0, :3] = -0.2  # a negative no-flash value (noise): counts as 0 in the denominator
    f = rng.uniform(0.0, 5.0, (6, 7))
    grey = lambda y: np.repeat(y[..., None], 3, -1)  # noqa: E731 (luminance of a grey pixel is its value)
    y = f / (np.maximum(n, 0.0) + 0.05 * np.percentile(n, 99))
    np.testing.assert_allclose(mt.trimap_cue(grey(f), grey(n)), y / np.percentile(y, 99), rtol=1e-12)
    y2 = f / (np.maximum(n, 0.0) + 0.2 * np.percentile(n, 80))
    np.testing.assert_allclose(
        mt.trimap_cue(grey(f), grey(n), "flash_ratio", 80.0, 0.2), y2 / np.percentile(y2, 80), rtol=1e-12
    )
    np.testing.assert_allclose(mt.trimap_cue(grey(f), grey(n), "flash_only"), f / np.percentile(f, 99), rtol=1e-12)


def test_make_trimap_exact_thresholds_structuring_discs_and_defaults():
    cue = np.array([[0.8, 0.2, 0.5]])
    np.testing.assert_array_equal(mt.make_trimap(cue, 0.8, 0.2, 0, 0), [[1.0, 0.0, 0.5]])  # at a threshold: definite
    np.testing.assert_array_equal(mt.make_trimap(cue, 0.8, 0.0, 0, 0), [[1.0, 0.5, 0.5]])  # bg_fraction 0 is allowed
    with pytest.raises(ValueError, match="make_trimap: need 0 <= bg_fraction < fg_fraction"):
        mt.make_trimap(cue, 0.5, 0.5)
    # a plus of 5 pixels survives opening by the radius-1 disc (a plus itself), a 2 x 2 block does not
    c = np.zeros((12, 12))
    c[3, 2:5] = c[2:5, 3] = 1.0
    c[8:10, 8:10] = 1.0
    t = mt.make_trimap(c, 0.8, 0.2, open_px=1, erode_px=0)
    assert (t[c == 1.0][:5] == 1.0).all() and t[3, 3] == 1.0 and not (t[8:10, 8:10] == 1.0).any()
    # erosion by radius 1 (a plus) vs radius 2; defaults open 1, erode 2
    sq = np.zeros((20, 20))
    sq[4:16, 4:16] = 1.0
    e1 = mt.make_trimap(sq, 0.8, 0.2, open_px=0, erode_px=1)
    assert (e1 == 1.0).sum() == 10 * 10 and e1[5, 5] == 1.0
    e2 = mt.make_trimap(sq, 0.8, 0.2, open_px=0, erode_px=2)
    assert (e2 == 1.0).sum() == 8 * 8
    # defaults on a smooth random cue, where every other radius changes some pixels
    from scipy import ndimage

    blob = ndimage.gaussian_filter(np.random.default_rng(14).uniform(0, 1, (40, 40)), 3)
    blob = (blob - blob.min()) / (blob.max() - blob.min())
    default = mt.make_trimap(blob, 0.6, 0.4)
    np.testing.assert_array_equal(default, mt.make_trimap(blob, 0.6, 0.4, open_px=1, erode_px=2))
    for other in ((2, 2), (1, 3), (0, 2)):
        assert not np.array_equal(default, mt.make_trimap(blob, 0.6, 0.4, *other))


def test_estimate_alpha_hands_the_method_clipped_inputs_and_keeps_definite_pixels(monkeypatch):
    """What every matting method gets (image and ramp clipped to [0, 1], the trimap as given) and
    what comes back (clipped, definite pixels forced); degenerate trimaps skip the method."""
    calls = []

    def spy(image, trimap, ramp):
        calls.append((image.copy(), trimap.copy(), ramp.copy()))
        return np.full(trimap.shape, 1.7) * (np.arange(trimap.shape[1]) % 2) - 0.3  # -0.3 and 1.4, alternating

    monkeypatch.setitem(mt.MATTING_METHODS, "spy", spy)
    rng = np.random.default_rng(12)
    image = rng.uniform(-0.5, 1.5, (4, 6, 3))
    tri = np.full((4, 6), 0.5)
    tri[0], tri[3] = 1.0, 0.0
    ramp = rng.uniform(-0.5, 1.5, (4, 6))
    alpha = mt.estimate_alpha(image, tri, "spy", ramp)
    ((img_in, tri_in, ramp_in),) = calls
    np.testing.assert_array_equal(img_in, np.clip(image, 0, 1))
    np.testing.assert_array_equal(tri_in, tri)
    np.testing.assert_array_equal(ramp_in, np.clip(ramp, 0, 1))
    expect = np.where(np.arange(6) % 2, 1.0, 0.0)[None].repeat(4, 0)
    expect[0], expect[3] = 1.0, 0.0
    np.testing.assert_array_equal(alpha, expect)
    # no background (or nothing unknown): the method is not called; unknown pixels get the clipped ramp
    calls.clear()
    no_bg = np.where(tri == 0.0, 0.5, tri)
    a = mt.estimate_alpha(image, no_bg, "spy", ramp)
    np.testing.assert_array_equal(a[1:], np.clip(ramp, 0, 1)[1:])
    assert (a[0] == 1.0).all()
    all_definite = np.where(tri == 0.5, 0.0, tri)
    np.testing.assert_array_equal(mt.estimate_alpha(image, all_definite, "spy", ramp), all_definite)
    assert not calls
    # without a method named, closed_form; a trimap with nothing to propagate does not need it to run
    np.testing.assert_array_equal(mt.estimate_alpha(image, all_definite), all_definite)


def _matting_data():
    """CaptureData of a flash read (buckets 0, 1) and a no-flash read (buckets 2, 3) with the flash
    on for 3 ms in bucket 0 and 1 ms in bucket 1; a static flash-lit radiance L."""
    from mbcapture.timing.timeline import ReadEvent

    L = np.random.default_rng(13).uniform(0.1, 2.0, (3, 4, 3))
    flash_s = np.array([0.003, 0.001, 0.0, 0.0])
    groups = ("ambient", "flash")
    group_exposure = np.zeros((4, 2, 3, 4, 3))
    group_exposure[:, 1] = flash_s[:, None, None, None] * L
    group_exposure[:, 0] = 0.004 * 0.5  # the ambient group, any value
    bucket_group_s = np.zeros((4, 2))
    bucket_group_s[:, 1] = flash_s  # switchable ("other", "flash"): the flash is the second
    bucket_group_s[:, 0] = [0.002, 0.0, 0.001, 0.0]  # another switchable group, on for part of the flash read
    tl = SimpleNamespace(reads=[ReadEvent("noflash", (2, 3)), ReadEvent("flash", (0, 1))])
    plan = SimpleNamespace(
        groups=groups,
        weights_s=np.stack(
            [
                np.array([[0.0, 0.002], [0.0, 0.0005], [0.0, 0.0], [0.0, 0.0]]),
                np.array([[0.0, 0.001], [0.0, 0.0005], [0.0, 0.0], [0.0, 0.0]]),
            ]
        ),
        times_s=np.array([0.001, 0.003]),
        # each stratum's two halves and a top-up's pass (Plan.exposure_time_mix)
        exposure_time_mix=lambda: (
            np.array([[0.001, 0.0015, 0.0012], [0.003, 0.0035, 0.0031]]),
            np.array([[0.25, 0.25, 0.5], [0.125, 0.375, 0.5]]),
        ),
    )
    data = CaptureData(
        cfg=None,
        scene=None,
        timeline=tl,
        plan=plan,
        read_names=["noflash", "flash"],
        exposure_s=np.array([0.004, 0.004]),
        reads_dn=np.zeros(0),
        saturated=np.zeros(0),
        reads_e_expected=np.zeros(0),
        bucket_exposure=np.zeros(0),
        k_e=np.ones(3),
        moving_mask=np.zeros((3, 4), bool),
        switchable=("other", "flash"),
        bucket_group_s=bucket_group_s,
        group_exposure=group_exposure,
    )
    return data, L


def test_flash_only_truth_is_the_flash_reads_flash_radiance():
    data, L = _matting_data()
    p = fm.FlashMattingParams()
    got = fm.flash_only_truth(data, p)
    assert got.shape == (3, 4, 3)
    np.testing.assert_allclose(got, L, rtol=1e-12)
    import dataclasses

    assert fm.flash_only_truth(dataclasses.replace(data, group_exposure=None), p) is None
    no_flash_rendered = dataclasses.replace(data, plan=SimpleNamespace(groups=("ambient",), weights_s=None))
    assert fm.flash_only_truth(no_flash_rendered, p) is None


def test_alpha_truth_weights_each_stratum_by_the_flash_reads_flash_time(monkeypatch):
    """The reference matte is the foreground's coverage averaged over the strata with the seconds
    the flash read collected while the flash was on (the plan's weights of its buckets), at each
    time a render of the stratum was made at (both halves, a top-up's too) with its weight in the
    stratum's exposure."""
    data, _ = _matting_data()
    got = {}

    def fake_coverage(scene, times_s, weights_s, width, height, spp, seed, variant, cache):
        got.update(
            scene=scene,
            times_s=times_s,
            weights_s=weights_s,
            size=(width, height),
            spp=spp,
            seed=seed,
            variant=variant,
            cache=cache,
        )
        return "coverage"

    monkeypatch.setattr(fm, "coverage_alpha", fake_coverage)  # the name the application calls
    seed = np.random.SeedSequence(5)
    cfg = SimpleNamespace(seed=1, render=SimpleNamespace(width=4, height=3, variant="scalar_rgb"))
    import dataclasses

    d = dataclasses.replace(data, cfg=cfg, scene="the scene", renderer=SimpleNamespace(cache="the cache"), seed=seed)
    assert fm.alpha_truth(d, fm.FlashMattingParams(truth_spp=7)) == "coverage"
    np.testing.assert_allclose(
        got["weights_s"],
        [0.0025 * 0.25, 0.0025 * 0.25, 0.0025 * 0.5, 0.0015 * 0.125, 0.0015 * 0.375, 0.0015 * 0.5],
        rtol=1e-15,
    )
    np.testing.assert_array_equal(got["times_s"], [0.001, 0.0015, 0.0012, 0.003, 0.0035, 0.0031])
    assert got["size"] == (4, 3) and got["spp"] == 7 and got["seed"] is seed and got["variant"] == "scalar_rgb"
    assert got["scene"] == "the scene" and got["cache"] == "the cache"
    assert fm.alpha_truth(dataclasses.replace(d, renderer=None), fm.FlashMattingParams()) is None
    d_noseed = dataclasses.replace(d, seed=None)
    fm.alpha_truth(d_noseed, fm.FlashMattingParams())
    assert got["seed"].entropy == 1  # the config's seed


def test_trimap_errors_and_read_names():
    tri = np.array([[1.0, 1.0, 0.0, 0.5], [0.0, 0.5, 1.0, 0.0]])
    truth = np.array([[0.0, 1.0, 1.0, 0.0], [0.97, 0.0, 0.04, 0.0]])
    # labelled fg with truth < 0.05: (0, 0) and (1, 2); labelled bg with truth > 0.95: (0, 2) and (1, 0)
    assert fm.trimap_errors(tri, truth) == {"fg_on_background": 2, "bg_on_foreground": 2}
    assert fm.trimap_errors(tri, truth, tol=0.02) == {"fg_on_background": 1, "bg_on_foreground": 1}
    data = SimpleNamespace(read_names=["noflash", "flash"])
    assert fm._read(data, "flash") == 1 and fm._read(data, "noflash") == 0
    with pytest.raises(ConfigError, match="app.name: flash_matting needs reads named 'flash' and 'noflash'"):
        fm._read(SimpleNamespace(read_names=["J1", "J2"]), "flash")
