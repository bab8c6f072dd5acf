"""Structured light: phase shifting, Gray code, unwrapping and triangulation on synthetic inputs with
known answers (no Mitsuba); the protocol; one tiny render comparing interleaved and sequential."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.scene import scenes
from mbcapture.scene import projective as pj
from mbcapture.apps import structured_light as sl
from mbcapture.errors import ConfigError
from mbcapture.reconstruct import phase as ph

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "structured_light.yaml"
MOD = scenes.load_module("structured_light")
W, H = 48, 36


def _geometry(**kw):
    p = MOD.Params(**kw)
    sc = MOD.make(p)
    return sc, sc.extra["structured_light"]


def _plane_depth(z0=1.1, slope=0.3):
    """A slanted plane seen by the camera: depth along the optical axis per pixel (H, W)."""
    return z0 + slope * (np.arange(W)[None, :] / W - 0.5) + 0.05 * (np.arange(H)[:, None] / H)


def _projector_columns(sc, info, z):
    pts = pj.points_from_depth(sc.camera, z)
    return info["projector"].project(pts, *info["projector_size_px"])[..., 0]


def test_phase_shifting_recovers_phase_and_cancels_equal_ambient():
    rng = np.random.default_rng(0)
    phi = rng.uniform(0, 2 * np.pi, (H, W))
    albedo = rng.uniform(0.2, 1.0, (H, W))
    for n in (3, 4, 7):
        d = 2 * np.pi * np.arange(n) / n
        imgs = albedo * 0.5 * (1 + np.cos(phi[None] - d[:, None, None]))
        amb = rng.uniform(0, 3, (H, W))  # spatially varying, equal in every pattern image
        got, mod, mean = ph.wrapped_phase(imgs + amb, d)
        np.testing.assert_allclose(np.angle(np.exp(1j * (got - phi))), 0, atol=1e-9)
        np.testing.assert_allclose(mod, albedo / 2, rtol=1e-9)
        np.testing.assert_allclose(mean, albedo / 2 + amb, rtol=1e-9)
    # ambient that differs between the images (flicker between sequential frames) is phase error
    imgs = 0.5 * (1 + np.cos(phi[None] - d[:, None, None]))
    got, _, _ = ph.wrapped_phase(imgs + np.arange(7)[:, None, None] * 0.05, d)
    assert np.abs(np.angle(np.exp(1j * (got - phi)))).max() > 0.05


def test_gray_code_round_trip_and_ambient_threshold():
    n = np.arange(1024)
    g = MOD.gray_code(n)
    assert (np.unpackbits((g[1:] ^ g[:-1]).astype(">u2").view(np.uint8)).reshape(-1, 16).sum(1) == 1).all()
    np.testing.assert_array_equal(ph.gray_to_binary(g), n)
    # decode 6-bit stripes under an ambient light that is brighter than the projector in the right half
    m = 6
    stripe = np.tile(np.arange(2**m), (4, 1))
    bits = np.stack([((MOD.gray_code(stripe) >> (m - 1 - i)) & 1).astype(float) for i in range(m)])
    proj = 0.8
    amb = np.zeros(stripe.shape)
    amb[:, 32:] = 1.5
    white = proj + amb
    images = proj * bits + amb[None]
    np.testing.assert_array_equal(ph.decode_gray(white, images, amb), stripe)
    wrong = ph.decode_gray(white, images, None)  # threshold white / 2: every 0 bit reads 1 where amb > proj
    np.testing.assert_array_equal(wrong[:, :32], stripe[:, :32])
    assert (wrong[:, 32:] != stripe[:, 32:]).mean() > 0.9


def test_triangulation_inverts_the_projection():
    sc, info = _geometry()
    z = _plane_depth()
    u = _projector_columns(sc, info, z)
    got = pj.triangulate_columns(sc.camera, info["projector"], u, info["projector_size_px"][0], W, H)
    np.testing.assert_allclose(got, z, rtol=1e-9)
    # a one-texel error in the column moves the depth by ~ z^2 / (f_p b): 9-14 mm here
    dz = pj.triangulate_columns(sc.camera, info["projector"], u + 1, info["projector_size_px"][0], W, H) - z
    assert 0.008 < np.abs(dz).min() and np.abs(dz).max() < 0.03


@pytest.mark.parametrize("method", ["depth_range", "spatial"])
def test_unwrapping_finds_the_fringe_period(method):
    sc, info = _geometry(fringe_periods=4)
    pw = info["projector_size_px"][0]
    z = _plane_depth()
    u = _projector_columns(sc, info, z)
    phase = np.mod(2 * np.pi * 4 * u / pw, 2 * np.pi)
    assert len(np.unique(np.floor(4 * u / pw))) >= 2  # the plane spans two fringe periods

    def tri(c):
        return pj.triangulate_columns(sc.camera, info["projector"], c, pw, W, H)

    col, depth, ok = ph.UNWRAP_METHODS[method](phase, np.ones((H, W), bool), tri, 4, pw, 0.7, 1.6)
    assert ok.all()
    np.testing.assert_allclose(col, u, atol=1e-6)
    np.testing.assert_allclose(depth, z, rtol=1e-9)
    # 'none' takes the first period: wrong wherever the plane lies in another one
    col0, _, ok0 = ph.unwrap_none(phase, np.ones((H, W), bool), tri, 4, pw, 0.0, 100.0)
    assert np.nanmax(np.abs(col0 - u)) > pw / 4 - 1


def test_depth_range_unwrapping_is_unique_for_the_shipped_geometry_and_rejects_out_of_range():
    sc, info = _geometry()
    pw = info["projector_size_px"][0]
    amb = ph.period_ambiguity(sc.camera, info["projector"], pw, 4, 160, 128, 0.7, 1.6)
    assert 0.5 < amb < 1.0  # unique everywhere, with margin; 8 periods would not be
    assert ph.period_ambiguity(sc.camera, info["projector"], pw, 8, 160, 128, 0.7, 1.6) > 1.0
    z = _plane_depth(z0=1.9, slope=0.0)  # beyond depth_max: no candidate lies in range
    u = _projector_columns(sc, info, z)

    def tri(c):
        return pj.triangulate_columns(sc.camera, info["projector"], c, pw, W, H)

    _, _, ok = ph.unwrap_depth_range(
        np.mod(2 * np.pi * 4 * u / pw, 2 * np.pi), np.ones((H, W), bool), tri, 4, pw, 0.7, 1.6
    )
    assert not ok.any()


def test_depth_scores_by_hand():
    truth = {"z_m": np.full((2, 5), 1.0), "u_px": np.full((2, 5), 100.0)}
    z = np.array([[1.001, 1.02, np.nan, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0, 1.0]])
    valid = np.isfinite(z)
    lit = np.ones((2, 5), bool)
    lit[1, 4] = False
    s = sl.depth_scores(z, valid, np.where(valid, 100.5, np.nan), None, truth, lit, 10.0, None, 512)
    assert s["pixels"] == 9 and s["coverage"] == pytest.approx(8 / 9)
    assert s["within_tolerance"] == pytest.approx(7 / 9)  # 20 mm off and the undecoded pixel miss
    assert s["depth_rmse_mm"] == pytest.approx(np.sqrt((1 + 400) / 8))
    assert s["column_rmse_px"] == pytest.approx(0.5)


def test_protocol_buckets_reads_and_sequential_frames():
    tl = protocols.build(load_config(CONFIG))
    assert [r.name for r in tl.reads] == ["fringe_1", "fringe_2", "fringe_3", "ambient"]
    assert [sorted(s.groups_on) for s in tl.segments[0].slots] == [["fringe_1"], ["fringe_2"], ["fringe_3"], []]
    assert len({tl.read_exposure_ticks(r) for r in tl.reads}) == 1
    tl3 = protocols.build(load_config(CONFIG, ["sensor.bucket_count=3"]))
    assert [r.name for r in tl3.reads] == ["fringe_1", "fringe_2", "fringe_3"]
    gray = protocols.build(load_config(CONFIG, ["scene.pattern=gray_code", "sensor.bucket_count=10"]))
    assert [r.name for r in gray.reads] == ["white"] + [f"gray_{i}" for i in range(1, 9)] + ["ambient"]
    with pytest.raises(ConfigError, match="sensor.bucket_count"):
        protocols.build(load_config(CONFIG, ["scene.pattern=gray_code"]))
    with pytest.raises(ConfigError, match="no projector patterns"):
        protocols.build(load_config(None, ["scene.name=multiflash", "capture.protocol=structured_light"]))
    seq = protocols.build(load_config(CONFIG, ["capture.sequential=true"]))
    assert seq.sequential and [r.name for r in seq.reads] == [r.name for r in tl.reads]


def test_interleaving_cancels_the_flicker_sequential_frames_do_not():
    from mbcapture.apps import CaptureData

    def ambient(over):
        cfg = load_config(CONFIG, over)
        sc = scenes.make_scene(cfg.scene.name, cfg.scene.params())
        data = CaptureData(
            cfg=cfg,
            scene=sc,
            timeline=protocols.build(cfg),
            plan=None,
            read_names=[],
            exposure_s=None,
            reads_dn=None,
            saturated=None,
            reads_e_expected=None,
            bucket_exposure=None,
            k_e=None,
            moving_mask=None,
        )
        return sl.ambient_in_reads(data)

    inter, seq = ambient([]), ambient(["capture.sequential=true"])
    assert inter["pattern_reads_spread"] < 1e-9  # 20 ms = two whole 100 Hz cycles, in every bucket
    assert seq["pattern_reads_spread"] > 0.3
    assert ambient(["capture.unit_exposure_s=0.004"])["pattern_reads_spread"] > 1e-3  # 16 ms: not whole cycles


def test_config_keys_are_validated():
    with pytest.raises(ConfigError, match="app.*depth_max_m"):
        load_config(CONFIG, ["app.depth_max_m=0.5"])
    with pytest.raises(ConfigError, match="scene.pattern"):
        load_config(CONFIG, ["scene.pattern=checkerboard"])
    with pytest.raises(ConfigError, match=r"app.unwrap: .*depth_range"):
        load_config(CONFIG, ["app.unwrap=magic"])


@pytest.mark.render
def test_interleaved_beats_sequential_and_the_ambient_bucket_helps_gray_code():
    from mbcapture import run_capture

    # 40x32 pixels average a lot of slanted surface: 30 mm is the tolerance of this size
    tiny = [
        "render.width=40",
        "render.height=32",
        "render.spp=4",
        "render.max_motion_px=1.0",
        "render.min_strata=1",
        "app.depth_tolerance_mm=30",
    ]
    inter = run_capture(load_config(CONFIG, tiny), progress=False).report["metrics"]
    seq = run_capture(load_config(CONFIG, tiny + ["capture.sequential=true"]), progress=False).report["metrics"]
    a, b = inter["depth"]["ambient_subtracted"]["all"], seq["depth"]["ambient_subtracted"]["all"]
    assert a["pixels"] > 800 and a["coverage"] > 0.95 and a["within_tolerance"] > 0.6
    assert a["within_tolerance"] > b["within_tolerance"] + 0.2 and a["phase_rmse_rad"] < 0.3 * b["phase_rmse_rad"]
    # phase shifting: subtracting the ambient read changes nothing (it cancels in the arctangent)
    assert inter["depth"]["ambient_ignored"]["all"] == pytest.approx(a)
    gray = run_capture(
        load_config(CONFIG, tiny + ["scene.pattern=gray_code", "sensor.bucket_count=10"]), progress=False
    ).report["metrics"]["depth"]
    g_sub, g_none = gray["ambient_subtracted"]["all"], gray["ambient_ignored"]["all"]
    assert g_sub["coverage"] > g_none["coverage"] + 0.2 and g_sub["column_rmse_px"] < 0.5 * g_none["column_rmse_px"]
    assert g_sub["within_tolerance"] > g_none["within_tolerance"] + 0.1


def _synthetic_capture(over, ambient_scale=1.0):
    """CaptureData of a slanted plane under the scene's projector, made without Mitsuba: per pixel an
    albedo, a spatially varying ambient radiance and the projector's patterns at the column that lights
    the plane's point; noise-free reads in DN."""
    from mbcapture.apps import CaptureData
    from mbcapture.sensor import electrons_per_render_second

    cfg = load_config(CONFIG, ["render.width=48", "render.height=36", *over])
    sc = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    info = sc.extra["structured_light"]
    tl = protocols.build(cfg)
    z = _plane_depth()
    u = _projector_columns(sc, info, z)
    pw = info["projector_size_px"][0]
    rng = np.random.default_rng(5)
    albedo = rng.uniform(0.3, 0.9, (H, W))
    ambient = ambient_scale * (0.05 + 0.4 * (np.arange(W)[None, :] > W // 2)) * np.ones((H, 1))  # a lit half
    _, pats, _ = MOD.patterns(
        MOD.Params(**{k.split(".", 1)[1]: v for k, v in (o.split("=") for o in over if o.startswith("scene."))})
    )
    rows = [np.interp(u, np.arange(pw) + 0.5, p[0]) for p in pats]  # the patterns along the plane
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    exposure = np.array([float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads])
    rate = [0.3 * albedo * row + ambient for row in rows]
    if len(tl.reads) > len(rows):
        rate.append(ambient)
    e = np.stack([np.repeat(r[..., None], 3, -1) for r in rate]) * k_e * exposure[:, None, None, None]
    dn = e * cfg.sensor.gain_dn_per_e + cfg.sensor.black_level_dn
    return z, CaptureData(
        cfg=cfg,
        scene=sc,
        timeline=tl,
        plan=None,
        read_names=[r.name for r in tl.reads],
        exposure_s=exposure,
        reads_dn=dn,
        saturated=np.zeros(dn.shape, bool),
        reads_e_expected=e,
        bucket_exposure=None,
        k_e=k_e,
        moving_mask=np.zeros((H, W), bool),
    )


@pytest.mark.parametrize("over", [[], ["scene.pattern=gray_code", "sensor.bucket_count=10"]], ids=["phase", "gray"])
def test_reconstruct_recovers_a_plane_without_mitsuba(over):
    """The whole reconstruction (reads in DN -> radiance -> ambient -> decode -> unwrap -> depth) on a
    synthetic capture of a known plane: exact for phase shifting, within half a Gray stripe's depth
    for the Gray code; without the ambient read the Gray code fails where the ambient outshines the
    projector (the right half), phase shifting does not care."""
    from mbcapture.apps import get

    z, data = _synthetic_capture(over)
    app = get("structured_light")
    out = app.reconstruct(data, app.params())
    decoded = out.images["decoded"] > 0
    assert decoded.mean() > 0.98
    err = np.abs(out.images["depth"] - z)[decoded]
    if over:
        # a stripe is 2 texels (256 over 512) and a texel 9-14 mm of depth on this plane (see the
        # triangulation test): the stripe centre is within half a stripe, < 15 mm
        assert np.percentile(err, 99) < 0.015
        ignored = app.reconstruct(data, app.params(ambient="none"))
        right = np.zeros((H, W), bool)
        right[:, W // 2 + 1 :] = True
        bad = np.abs(ignored.images["depth"] - z) > 0.03
        assert (bad | (ignored.images["decoded"] == 0))[right].mean() > 0.5
        assert (np.abs(ignored.images["depth"] - z) < 0.03)[~right].mean() > 0.9
    else:
        np.testing.assert_allclose(out.images["depth"][decoded], z[decoded], atol=2e-5)
        assert out.metrics["ambient_in_reads"]["pattern_reads_spread"] < 1e-9


def test_depth_scores_phase_median_and_edge_cases():
    """Phase error against the truth's column (2 pi periods u / projector width, wrapped), the
    median depth error, the tolerance's edge, a valid pixel without a depth, nothing or one lit."""
    truth = {"z_m": np.full((2, 4), 1.0), "u_px": np.array([[100.0, 200.0, 300.0, 400.0]] * 2)}
    z = np.array([[1.001, 1.003, 1.0078125, 1.0], [1.0, 1.0, 1.0, np.nan]])  # 7.8125 mm is exact in binary
    valid = np.ones((2, 4), bool)  # the NaN depth is "valid" by mistake: it is never within tolerance
    lit = np.ones((2, 4), bool)
    lit[1, :3] = False
    true_phase = 2 * np.pi * 4 * truth["u_px"] / 512
    phase = true_phase + np.array([[0.1, -0.2, 0.1 + 2 * np.pi, -0.2], [0.0, 0.0, 0.0, 0.3]])
    s = sl.depth_scores(z, valid, truth["u_px"] + 0.25, phase, truth, lit, 7.8125, 4, 512)
    assert s["pixels"] == 5 and s["coverage"] == 1.0
    assert s["within_tolerance"] == pytest.approx(4 / 5)  # 1, 3, 7.8125 (the edge, included) and 0 mm; not NaN
    assert s["phase_rmse_rad"] == pytest.approx(np.sqrt((0.01 + 0.04 + 0.01 + 0.04 + 0.09) / 5), rel=1e-9)
    assert s["column_rmse_px"] == pytest.approx(0.25)
    z2 = np.where(np.isfinite(z), z, 1.0)
    s2 = sl.depth_scores(z2, valid, truth["u_px"], None, truth, lit, 10.0, 4, 512)
    assert s2["depth_median_abs_mm"] == pytest.approx(1.0) and "phase_rmse_rad" not in s2  # |1, 3, 7.8, 0, 0| mm
    assert "phase_rmse_rad" not in sl.depth_scores(z2, valid, truth["u_px"], phase, truth, lit, 10.0, None, 512)
    assert sl.depth_scores(z2, valid, truth["u_px"], phase, truth, np.zeros((2, 4), bool), 10.0, 4, 512) == {
        "pixels": 0
    }
    one = np.zeros((2, 4), bool)
    one[0, 1] = True
    assert sl.depth_scores(z2, valid, truth["u_px"], phase, truth, one, 10.0, 4, 512)["pixels"] == 1


def _ramp(periods=4, pw=512, h=6, w=40):
    """Projector columns rising 10 -> 490 across the image, their wrapped phase, and a linear
    triangulation z = 1 + u / 1000 m."""
    u = np.broadcast_to(np.linspace(10.0, 490.0, w), (h, w)).copy()
    phase = np.mod(2 * np.pi * periods * u / pw, 2 * np.pi)
    return u, phase, (lambda c: 1.0 + np.asarray(c) / 1000.0)


def test_unwrap_none_reads_the_first_period_and_keeps_the_depth_range_inclusive():
    u, phase, tri = _ramp(periods=1)
    valid = np.ones(u.shape, bool)
    valid[0, 5] = False
    col = phase / (2 * np.pi) * 512 / 1  # the decoded column, as the function computes it
    z_lo, z_hi = float(tri(col[0, 3])), float(tri(col[0, 30]))  # two pixels exactly on the range's ends
    uu, zz, ok = ph.unwrap_none(phase, valid, tri, 1, 512, z_lo, z_hi)
    expect_ok = valid & (u >= u[0, 3]) & (u <= u[0, 30])
    np.testing.assert_array_equal(ok, expect_ok)
    np.testing.assert_allclose(uu[ok], u[ok], rtol=1e-12)
    np.testing.assert_allclose(zz[ok], tri(u[ok]), rtol=1e-12)
    assert np.isnan(uu[~ok]).all() and np.isnan(zz[~ok]).all()
    # with 4 periods, the first period only: u = phase W / (2 pi P) lies in [0, 128)
    _, phase4, _ = _ramp(periods=4)
    u4, _, ok4 = ph.unwrap_none(phase4, np.ones(u.shape, bool), tri, 4, 512, 0.0, 10.0)
    assert ok4.all() and u4.max() < 128 and u4.min() >= 0
    np.testing.assert_allclose(u4, np.mod(u, 128), rtol=1e-9, atol=1e-9)


def test_unwrap_spatial_recovers_a_smooth_ramp_within_the_depth_range():
    u, phase, tri = _ramp(periods=4)
    valid = np.ones(u.shape, bool)
    valid[2, 17] = False
    uu, zz, ok = ph.unwrap_spatial(phase, valid, tri, 4, 512, float(tri(u.min())) - 1e-9, float(tri(u.max())) + 1e-9)
    np.testing.assert_array_equal(ok, valid)
    np.testing.assert_allclose(uu[ok], u[ok], rtol=1e-9)
    np.testing.assert_allclose(zz[ok], tri(u[ok]), rtol=1e-12)
    assert np.isnan(uu[2, 17]) and np.isnan(zz[2, 17])
    # a range that holds only the left half: the same offset (most pixels in range), the rest not ok
    mid = float(tri((u[0, 19] + u[0, 20]) / 2))
    _, _, half = ph.unwrap_spatial(phase, valid, tri, 4, 512, float(tri(u.min())) - 1e-9, mid)
    np.testing.assert_array_equal(half, valid & (u <= u[0, 19]))


def test_valid_fraction_against_the_99th_percentile_of_the_good_pixels():
    """A pixel is valid when it is not bad, finite, > 0 and at least the fraction of the 99th
    percentile over such pixels. A NaN pixel is invalid and does not enter the percentile (it used
    to make the percentile NaN, and with it every pixel invalid)."""
    sig = np.ones((20, 10))
    sig[0, 0] = 1000.0  # 0.5 % hot pixels do not move the 99th percentile
    sig[1, :] = 0.25  # exactly the fraction: valid
    sig[2, :] = 0.2  # below: not valid
    sig[3, 0] = np.nan
    sig[3, 1] = 0.0
    bad = np.zeros((20, 10), bool)
    bad[4, :] = True
    sig[4, :] = 1e6  # bad pixels neither count nor set the reference
    v = sl._valid_fraction(4.0 * sig, 0.25, bad)
    expect = np.ones((20, 10), bool)
    expect[2, :] = expect[4, :] = False
    expect[3, :2] = False
    np.testing.assert_array_equal(v, expect)
    np.testing.assert_array_equal(sl._valid_fraction(sig, 0.25, np.zeros((20, 10), bool))[2], False)  # no bad pixel
    zero = sl._valid_fraction(sig, 0.0, bad)  # fraction 0: still not black, NaN or bad
    assert not zero[3, :2].any() and not zero[4].any() and zero[2].all()
    assert not sl._valid_fraction(sig, 0.25, np.ones((20, 10), bool)).any()  # all bad
