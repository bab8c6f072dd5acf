"""moving_light: shadow-sweep region, read consistency and flicker gains on synthetic inputs with
known answers, the scene's shadow geometry, and a tiny capture interleaved vs sequential."""

from fractions import Fraction

import numpy as np
import pytest

from mbcapture import load_config, run_capture
from mbcapture.scene import scenes
from mbcapture.apps.moving_light import (
    consistency,
    drive_gains_exact,
    drive_gains_measured,
    rasterize_convex,
    read_spread_rel,
    sweep_region,
)
from mbcapture.timing.drive import Drive
from mbcapture.errors import ConfigError
from mbcapture.timing.timeline import ReadEvent, SegmentSeconds, SlotSeconds, build_timeline


def square(x0, y0, size):
    return np.array([[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size]], float)


def test_rasterize_counts_pixel_centres_inside():
    m = rasterize_convex([square(2, 3, 4)], 12, 10)  # x in [2, 6], y in [3, 7]: centres 2.5..5.5, 3.5..6.5
    assert m.sum() == 16 and m[3:7, 2:6].all()
    m2 = rasterize_convex([square(2.2, 3.2, 4)], 12, 10)  # centres 2.5..5.5 inside x in [2.2, 6.2]
    assert m2.sum() == 16
    assert not rasterize_convex([np.array([[0, 0], [5, 5], [9, 9]], float)], 12, 10).any()  # no area


def test_sweep_region_is_union_minus_intersection():
    # a 6 px square moving right by 1 px per step for 4 steps: swept by some but not all: 4 columns left + 4 right
    frames = [[square(5 + t, 2, 6)] for t in range(5)]
    m = sweep_region(frames, 24, 12)
    assert m.sum() == (4 + 4) * 6
    assert m[2:8, 5:9].all() and m[2:8, 11:15].all() and not m[2:8, 9:11].any()
    still = sweep_region([[square(5, 2, 6)]] * 5, 24, 12)
    assert not still.any()
    grown = sweep_region(frames, 24, 12, grow_px=1.0)  # a disk of radius 1 adds one pixel all round
    assert grown.sum() > m.sum() and grown[2:8, 4].all() and grown[1, 5:9].all()


def test_consistency_known_offsets():
    rng = np.random.default_rng(0)
    truth = np.full((8, 10, 3), 2.0)
    delta = np.array([0.1, -0.05, 0.0])
    normalized = truth[None] * (1 + delta[:, None, None, None])
    mask = np.zeros((8, 10), bool)
    mask[2:5, 3:9] = True
    normalized[:, ~mask] += rng.normal(size=(3, (~mask).sum(), 3))  # outside the mask: ignored
    c = consistency(normalized, ["J1", "J2", "J3"], truth, mask)
    assert c["rel_rms_vs_truth"] == pytest.approx({"J1": 0.1, "J2": 0.05, "J3": 0.0})
    assert c["pairwise_rel_rms"] == pytest.approx({"J1-J2": 0.15, "J1-J3": 0.1, "J2-J3": 0.05})
    assert c["max_pairwise_rel_rms"] == pytest.approx(0.15)
    assert c["moving_pixels"] == mask.sum()
    spread = read_spread_rel(normalized, truth)
    np.testing.assert_allclose(spread[mask], 0.1)


def sequential_frames(exposures_s, gap_s):
    segs, t = [], Fraction(0)
    for i, e in enumerate(exposures_s):
        segs.append(SegmentSeconds(t, (SlotSeconds(i, e),), 1))
        t += e + gap_s
    reads = [ReadEvent(f"J{i + 1}", (i,), True) for i in range(len(exposures_s))]
    return build_timeline(segs, reads, len(exposures_s), "seq", sequential=True)


def test_flicker_gains_match_hand_integrals():
    """Frames of 1, 2, 4 ms with 3 ms gaps under 1 - cos(2 pi 100 t): mean drive of each frame by hand."""
    ms = Fraction(1, 1000)
    exp = [1 * ms, 2 * ms, 4 * ms]
    tl = sequential_frames(exp, 3 * ms)
    drive = Drive.mains_flicker(50.0)
    edges = np.array([tl.start_tick, tl.end_tick])
    w_s = tl.weights_ticks(edges, ["lamp", "ambient"], frozenset(), {"ambient": drive}) * float(tl.tick_s)
    exposure = np.array([float(e) for e in exp])
    gains = drive_gains_exact(w_s, 1, [r.buckets for r in tl.reads], exposure, drive.c0)
    starts = [0.0, 0.004, 0.009]
    w = 2 * np.pi * 100
    expect = [1 - (np.sin(w * (a + e)) - np.sin(w * a)) / (w * e) for a, e in zip(starts, exposure)]
    np.testing.assert_allclose(gains, expect, rtol=1e-12)
    lamp = drive_gains_exact(w_s, 0, [r.buckets for r in tl.reads], exposure, 1.0)
    np.testing.assert_allclose(lamp, 1.0, rtol=1e-15)  # the steady group: exactly its exposure
    # renders of a static ambient radiance (any image) give the same gains from the images
    L = np.random.default_rng(1).uniform(0.1, 2.0, size=(5, 6, 3))
    group_exposure = w_s.sum(axis=0)[:, :, None, None, None] * L[None, None]  # (K, G, H, W, C)
    measured = drive_gains_measured(group_exposure, w_s, 1, [r.buckets for r in tl.reads], exposure, drive.c0)
    np.testing.assert_allclose(measured, gains, rtol=1e-12)


def test_shadow_points_lie_on_the_table_along_rays_from_the_lamp():
    mod = scenes.load_module("moving_light")
    p = mod.Params()
    scene = scenes.make_scene("moving_light", p)
    times = np.array([0.0, 0.05, 0.1])
    lamp = mod.lamp_position(p, times)
    assert np.allclose(np.linalg.norm(lamp[:, [0, 2]], axis=1), p.arc_radius_m)
    ang = np.degrees(np.arctan2(lamp[:, 0], lamp[:, 2]))
    np.testing.assert_allclose(ang, p.lamp_start_deg + p.lamp_speed_deg_per_s * times)
    occ = mod.OCCLUDERS[0]
    shadow = scene.extra["shadow_polygons"](times)[0]  # (T, P, 3)
    top = occ.points[:, 1] > 0
    assert np.allclose(shadow[:, top, 1], 0.0)  # on the table plane
    for t in range(3):  # lamp, occluder point and its shadow are collinear, the point between them
        d1 = occ.points[top] - lamp[t]
        d2 = shadow[t, top] - lamp[t]
        assert np.allclose(np.cross(d1, d2), 0.0, atol=1e-12)
        assert np.all(np.linalg.norm(d2, axis=1) > np.linalg.norm(d1, axis=1))
    np.testing.assert_allclose(shadow[:, ~top], np.broadcast_to(occ.points[~top], shadow[:, ~top].shape))  # footprint
    mp = scene.motion_points(times)
    np.testing.assert_allclose(mp[:, 0], lamp)  # the lamp's centre leads the motion points
    assert "ambient" in scene.drives and scene.drives["ambient"].terms[0][1] == 100.0
    with pytest.raises(Exception, match="lamp_height_m"):
        mod.Params(lamp_height_m=0.2)


@pytest.mark.render
class TestTinyCapture:
    """One interleaved and one sequential capture at 64 x 48, 2 spp."""

    SETS = ["render.width=64", "render.height=48", "render.spp=2", "render.max_motion_px=1.0", "render.min_strata=1"]

    @pytest.fixture(scope="class")
    @classmethod
    def runs(cls):
        from pathlib import Path

        path = Path(__file__).resolve().parents[1] / "configs" / "moving_light.yaml"
        out = {}
        for seq in (False, True):
            cfg = load_config(path, cls.SETS + [f"capture.sequential={str(seq).lower()}"])
            out[seq] = run_capture(cfg, progress=False)
        return out

    def test_interleaved_reads_are_consistent_sequential_are_not(self, runs):
        ci = runs[False].report["metrics"]["consistency"]
        cs = runs[True].report["metrics"]["consistency"]
        assert ci["sweep_fraction_of_image"] == cs["sweep_fraction_of_image"] > 0.0  # the same region in both
        for region in ("whole_image", "shadow_sweep"):
            assert ci[region]["max_pairwise_rel_rms"] < 0.2 * cs[region]["max_pairwise_rel_rms"]
        assert {"hdr_rel_mse", "hdr_pu21_psnr_db"} <= set(runs[False].report["metrics"])  # the HDR app's metrics

    def test_flicker_gains(self, runs):
        fi = runs[False].report["metrics"]["flicker"]
        fs = runs[True].report["metrics"]["flicker"]
        # interleaved: 16 periods of 0.625 ms span exactly one 100 Hz cycle, each bucket samples it evenly
        assert all(abs(g - 1) < 1e-12 for g in fi["gain_vs_time_average"].values())
        # sequential: frame i starts at sum of the earlier exposures + i x frame_readout_s
        cfg = runs[True].config
        T, gap = cfg.capture.unit_exposure_s, cfg.sensor.frame_readout_s
        w = 2 * np.pi * 100.0
        start, expect = 0.0, []
        for e in (T, 2 * T, 4 * T, 8 * T):
            expect.append(1 - (np.sin(w * (start + e)) - np.sin(w * start)) / (w * e))
            start += e + gap
        np.testing.assert_allclose(list(fs["gain_vs_time_average"].values()), expect, rtol=1e-9)
        assert fs["gain_spread"] > 0.5
        # the renders agree with the weights: the ambient light is static, only its drive varies;
        # tolerance: 8 x the run's own Monte Carlo error of an image mean (rel. RMS / sqrt(samples))
        rep = runs[True].report
        n = 64 * 48 * 3
        tol = 8 * rep["render_error"]["rel_rms"] / np.sqrt(n) * np.sqrt(2)
        for r, g in fs["gain_measured_from_renders"].items():
            assert g == pytest.approx(fs["gain_vs_time_average"][r], rel=tol)

    def test_outputs(self, runs):
        res = runs[False]
        imgs = res.images
        assert {"radiance", "truth", "sweep", "read_spread_rel"} <= set(imgs)
        assert imgs["sweep"].shape == (48, 64, 3) and imgs["sweep"].any()
        assert np.isfinite(imgs["radiance"]).all()
        assert res.plan.motion_px_total > 0  # the shadows move
        assert runs[True].plan.passes >= 4  # at least one stratum per sequential frame
        assert {"read_spread", "sweep", "hdr", "truth"} <= set(res.app_output.png)


def test_unknown_flicker_group_names_the_key():
    from mbcapture.apps import CaptureData
    from mbcapture.apps.moving_light import flicker_metrics

    scene = scenes.make_scene("moving_light", scenes.load_module("moving_light").Params())
    data = CaptureData(
        cfg=None,
        scene=scene,
        timeline=None,
        plan=None,
        read_names=[],
        exposure_s=np.zeros(0),
        reads_dn=np.zeros(0),
        saturated=np.zeros(0),
        reads_e_expected=np.zeros(0),
        bucket_exposure=np.zeros(0),
        k_e=np.ones(3),
        moving_mask=np.zeros((1, 1), bool),
    )
    with pytest.raises(ConfigError, match="app.flicker_group"):
        flicker_metrics(data, "lamp")


def test_still_lamp_is_one_pass_and_the_flicker_is_still_integrated():
    """A static scene renders once however many frames; the flicker lives in the weights only."""
    from pathlib import Path

    from mbcapture.capture.pipeline import prepare

    path = Path(__file__).resolve().parents[1] / "configs" / "moving_light.yaml"
    cfg = load_config(path, ["scene.lamp_speed_deg_per_s=0", "capture.sequential=true"])
    scene, tl, plan, _ = prepare(cfg)
    assert scene.is_static and plan.passes == 1
    gains = drive_gains_exact(
        plan.weights_s,
        plan.groups.index("ambient"),
        [r.buckets for r in tl.reads],
        np.array([float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads]),
        1.0,
    )
    assert gains.max() - gains.min() > 0.5  # four frames at four flicker phases, from one render


def _flicker_data(with_renders: bool):
    """A sequential capture of 1, 2, 4 ms frames (3 ms gaps) of a steady lamp and an ambient group
    driven by 2 + 1.5 cos(2 pi 100 t + 0.3), as CaptureData without Mitsuba."""
    from types import SimpleNamespace

    from mbcapture.apps import CaptureData

    ms = Fraction(1, 1000)
    exp = [1 * ms, 2 * ms, 4 * ms]
    tl = sequential_frames(exp, 3 * ms)
    drive = Drive(c0=2.0, terms=((1.5, 100.0, 0.3),))
    groups = ("lamp", "ambient")
    w_s = tl.weights_ticks(
        np.array([tl.start_tick, tl.end_tick]), list(groups), frozenset(), {"ambient": drive}
    ) * float(tl.tick_s)
    exposure = np.array([float(e) for e in exp])
    L = np.random.default_rng(2).uniform(0.1, 2.0, size=(4, 5, 3))  # a static radiance per group
    group_exposure = w_s.sum(axis=0)[:, :, None, None, None] * L[None, None] if with_renders else None
    scene = SimpleNamespace(name="synthetic", drives={"ambient": drive, "unrendered": Drive(c0=1.0)})
    plan = SimpleNamespace(groups=groups, weights_s=w_s)
    data = CaptureData(
        cfg=None,
        scene=scene,
        timeline=tl,
        plan=plan,
        read_names=["J1", "J2", "J3"],
        exposure_s=exposure,
        reads_dn=np.zeros(0),
        saturated=np.zeros(0),
        reads_e_expected=np.zeros(0),
        bucket_exposure=np.zeros(0),
        k_e=np.ones(3),
        moving_mask=np.zeros((4, 5), bool),
        group_exposure=group_exposure,
    )
    starts = np.array([0.0, 0.004, 0.009])
    w = 2 * np.pi * 100
    mean = 2.0 + 1.5 * (np.sin(w * (starts + exposure) + 0.3) - np.sin(w * starts + 0.3)) / (w * exposure)
    return data, mean / 2.0


def test_flicker_metrics_reports_each_reads_mean_drive_over_its_time_average():
    """flicker_metrics on a known drive: per read the mean drive over its frame / c0 (by hand),
    its spread and largest departure from 1, the same measured from static renders, and the
    drive's coefficients as given."""
    from mbcapture.apps.moving_light import flicker_metrics

    data, gains = _flicker_data(with_renders=True)
    assert gains.max() - gains.min() > 0.1  # three frames at clearly different flicker phases
    fl = flicker_metrics(data, "ambient")
    assert set(fl) == {
        "group",
        "drive",
        "gain_vs_time_average",
        "gain_spread",
        "max_abs_gain_error",
        "gain_measured_from_renders",
    }
    assert fl["group"] == "ambient"
    assert fl["drive"] == {"c0": 2.0, "terms": [{"amplitude": 1.5, "frequency_hz": 100.0, "phase_rad": 0.3}]}
    assert list(fl["gain_vs_time_average"]) == ["J1", "J2", "J3"]
    np.testing.assert_allclose(list(fl["gain_vs_time_average"].values()), gains, rtol=1e-12)
    assert fl["gain_spread"] == pytest.approx(gains.max() - gains.min(), rel=1e-12)
    assert fl["max_abs_gain_error"] == pytest.approx(np.abs(gains - 1).max(), rel=1e-12)
    assert list(fl["gain_measured_from_renders"]) == ["J1", "J2", "J3"]
    np.testing.assert_allclose(list(fl["gain_measured_from_renders"].values()), gains, rtol=1e-12)
    # without per-group renders only the exact gains are reported
    data_nr, _ = _flicker_data(with_renders=False)
    assert "gain_measured_from_renders" not in flicker_metrics(data_nr, "ambient")
    # a driven group that no read renders: named, with a note and nothing else
    assert flicker_metrics(data, "unrendered") == {
        "group": "unrendered",
        "note": "group not rendered (no weight in any read)",
    }


def test_rasterize_slanted_edges_image_borders_and_several_polygons():
    """Pixel centres on a slanted hull edge count as inside, the image's first row and column are
    reached, and every polygon adds its own pixels (a degenerate or off-image one skips only itself;
    a later polygon's bounding box does not clear an earlier one's pixels)."""
    tri = np.array(
        [[0, 0], [8, 0], [0, 8]], float
    )  # centres (x+.5, y+.5) with x + y + 1 <= 8 (the hypotenuse included)
    yy, xx = np.mgrid[0:10, 0:12]
    expect_tri = xx + yy <= 7
    m = rasterize_convex([tri], 12, 10)
    np.testing.assert_array_equal(m, expect_tri)
    assert m.sum() == 36 and m[0, 0]
    line = np.array([[0, 0], [5, 5], [9, 9]], float)
    off_image = square(20, 20, 3)
    np.testing.assert_array_equal(rasterize_convex([line, off_image, tri], 12, 10), expect_tri)
    # a triangle over y <= x whose bounding box covers square(0, 0, 4)'s corner (2..3, 2..3) but not all of it
    tri2 = np.array([[2, 2], [10, 2], [10, 10]], float)
    expect_tri2 = (xx >= 2) & (xx <= 9) & (yy >= 2) & (yy <= xx)
    np.testing.assert_array_equal(rasterize_convex([tri2], 12, 10), expect_tri2)
    both = rasterize_convex([square(0, 0, 4), tri2], 12, 10)
    np.testing.assert_array_equal(both, ((xx < 4) & (yy < 4)) | expect_tri2)
    assert both[3, 2]  # in the square, inside tri2's box, outside tri2


def test_sweep_region_unions_occluders_and_grows_by_a_disk():
    from scipy.ndimage import distance_transform_edt

    empty = sweep_region([], 6, 4)
    assert empty.shape == (4, 6) and empty.dtype == bool and not empty.any()
    # two occluders: one moves right, the other moves down; the region is the union of both sweeps
    frames = [[square(2 + t, 2, 4), square(14, 1 + t, 4)] for t in range(3)]
    a = sweep_region([[f[0]] for f in frames], 24, 14)
    b = sweep_region([[f[1]] for f in frames], 24, 14)
    assert a.sum() == 2 * 2 * 4 and b.sum() == 2 * 2 * 4 and not (a & b).any()
    m = sweep_region(frames, 24, 14)
    np.testing.assert_array_equal(m, a | b)
    for grow in (1.0, 2.0, 2.5):  # every pixel within grow_px (Euclidean) of the region
        grown = sweep_region(frames, 24, 14, grow_px=grow)
        assert grown.dtype == bool
        np.testing.assert_array_equal(grown, distance_transform_edt(~m) <= grow)


def test_consistency_mean_and_black_truth():
    """The mean of the per-read departures is reported; over a black truth the departures are
    absolute (relative to 1 render unit) and read_spread_rel divides by its floor, 0.01."""
    truth = np.zeros((4, 5, 3))
    normalized = np.stack([truth + 0.2, truth - 0.1, truth])
    mask = np.ones((4, 5), bool)
    c = consistency(normalized, ["J1", "J2", "J3"], truth, mask)
    assert c["rel_rms_vs_truth"] == pytest.approx({"J1": 0.2, "J2": 0.1, "J3": 0.0})
    assert c["pairwise_rel_rms"] == pytest.approx({"J1-J2": 0.3, "J1-J3": 0.2, "J2-J3": 0.1})
    assert c["mean_rel_rms_vs_truth"] == pytest.approx(0.1)
    np.testing.assert_allclose(read_spread_rel(normalized, truth), 0.2 / 0.01)


def test_measured_gains_use_only_the_read_buckets():
    """The drive-weighted mean radiance comes from the buckets some read uses: a bucket no read
    uses (here with a radiance 10x the others) changes nothing."""
    w_s = np.array([[[1.0], [2.0], [0.5], [1.0]]])  # (J=1, K=4, G=1) seconds x drive
    level = np.array([1.0, 2.0, 0.5, 10.0]) * 3.0  # buckets 0-2 see radiance 3, bucket 3 radiance 30
    group_exposure = np.broadcast_to(level[:, None, None, None, None], (4, 1, 2, 2, 3)).copy()
    reads = [(0,), (1, 2)]
    exposure = np.array([0.5, 1.25])
    g = drive_gains_measured(group_exposure, w_s, 0, reads, exposure, 0.8)
    np.testing.assert_allclose(g, drive_gains_exact(w_s, 0, reads, exposure, 0.8), rtol=1e-12)
    np.testing.assert_allclose(g, [1.0 / (0.5 * 0.8), 2.5 / (1.25 * 0.8)], rtol=1e-12)


def test_shadow_sweep_mask_covers_both_capture_modes_over_their_joint_span():
    """The sweep region is traced over the span of the capture and of its twin (interleaved <->
    sequential), so both modes are scored on the same pixels; image size from the reads."""
    from pathlib import Path
    from types import SimpleNamespace

    from mbcapture.apps.moving_light import (
        SWEEP_TIME_SAMPLES,
        _sweep_times,
        shadow_sweep_mask,
    )
    from mbcapture.capture.pipeline import prepare

    path = Path(__file__).resolve().parents[1] / "configs" / "moving_light.yaml"
    W, H, grow = 40, 24, 1.5
    datas, spans = [], []
    for seq in (False, True):
        cfg = load_config(path, [f"capture.sequential={str(seq).lower()}", f"render.width={W}", f"render.height={H}"])
        scene, tl, _, _ = prepare(cfg)
        datas.append(SimpleNamespace(cfg=cfg, scene=scene, timeline=tl, reads_dn=np.zeros((len(tl.reads), H, W, 3))))
        spans += [float(tl.seconds(tl.start_tick)), float(tl.seconds(tl.end_tick))]
    times = _sweep_times(datas[0])
    np.testing.assert_allclose(times, np.linspace(min(spans), max(spans), SWEEP_TIME_SAMPLES), rtol=1e-12)
    np.testing.assert_allclose(_sweep_times(datas[1]), times, rtol=1e-12)
    assert max(spans) - min(spans) > spans[1] - spans[0]  # the sequential capture lasts longer
    masks = [shadow_sweep_mask(d, grow) for d in datas]
    np.testing.assert_array_equal(masks[0], masks[1])
    scene = datas[0].scene
    per_occ = [scene.project(p, times, W, H) for p in scene.extra["shadow_polygons"](times)]
    expect = sweep_region([[occ[t] for occ in per_occ] for t in range(len(times))], W, H, grow)
    assert masks[0].shape == (H, W) and 0 < expect.sum() < H * W
    np.testing.assert_array_equal(masks[0], expect)
    bare = SimpleNamespace(
        cfg=datas[0].cfg,
        scene=SimpleNamespace(name="plain", extra={}),
        timeline=datas[0].timeline,
        reads_dn=datas[0].reads_dn,
    )
    with pytest.raises(ConfigError, match="app.name: moving_light needs a scene with extra\\['shadow_polygons'\\]"):
        shadow_sweep_mask(bare, grow)
