"""Per-pixel gate codes (coded two-bucket sensors): the code families, routing and its conservation,
the coded timeline, demultiplexing, photometric stereo, and captures through the whole pipeline:
the global schedule written as a code reproduces today's captures bit for bit."""

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.errors import ConfigError
from mbcapture.timing.gatecode import DRAIN, GateCode, default_tile, make_code
from mbcapture.reconstruct.demultiplex import (
    code_rank,
    demultiplex,
    demultiplex_guided,
    tent,
)
from mbcapture.reconstruct.photometric import angular_error_deg, near_light_normals

ROOT = Path(__file__).resolve().parents[1]
MULTI_FLASH = ROOT / "configs" / "multi_flash.yaml"
CODED = ROOT / "configs" / "coded_multi_flash.yaml"
FAMILIES = ("global", "one_hot", "hadamard", "random")


def _code(family, S=5, K=2, W=24, H=20):
    return make_code(family, S, S if family == "global" else K, width=W, height=H, seed=3)


# ---------------------------------------------------------------- codes and routing
@pytest.mark.parametrize("family", FAMILIES)
def test_routing_conserves_the_photodiode_light_for_every_code(family):
    code = _code(family)
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1e4, size=(5, 20, 24, 3))
    out = code.route(x)
    assert out.shape == (code.n_buckets, 20, 24, 3)
    np.testing.assert_allclose(out.sum(axis=0), x.sum(axis=0), rtol=1e-14)
    # each bucket holds exactly the sub-frames its pixel's code sends to it
    full = code.full(20, 24)
    for k in range(code.n_buckets):
        expect = sum(np.where((full[s] == k)[..., None], x[s], 0.0) for s in range(5))
        np.testing.assert_allclose(out[k], expect, rtol=1e-14)


def test_a_drained_sub_frame_is_in_no_bucket():
    tile = np.array([[[0, 1]], [[DRAIN, 0]], [[1, DRAIN]]], np.int8)  # (3 sub-frames, 1, 2)
    code = GateCode("file", tile, 2)
    x = np.stack([np.full((2, 4, 1), v) for v in (1.0, 10.0, 100.0)])
    out = code.route(x)
    np.testing.assert_array_equal(out[:, 0, 0, 0], [1.0, 100.0])  # even columns: 1 -> B1, 10 drained, 100 -> B2
    np.testing.assert_array_equal(out[:, 0, 1, 0], [10.0, 1.0])  # odd columns: 1 -> B2, 10 -> B1, 100 drained


def test_families_are_what_their_names_say():
    one_hot = _code("one_hot", S=4)
    assert one_hot.tile_shape == (2, 2)
    # position f sends sub-frame f to bucket 1, the others to bucket 2
    for f in range(4):
        y, x = divmod(f, 2)
        np.testing.assert_array_equal(one_hot.tile[:, y, x], [0 if s == f else 1 for s in range(4)])
    had = _code("hadamard", S=5)
    assert had.tile_shape == default_tile(7) == (3, 3)
    rows = had.tile.reshape(5, -1).T[:7]  # 7 positions of the order-8 S-matrix, 5 columns
    signs = np.where(rows == 0, 1, -1)
    h8 = np.array([[1]])
    for _ in range(3):
        h8 = np.block([[h8, h8], [h8, -h8]])
    np.testing.assert_array_equal(signs, h8[1:, 1:6])
    assert not any((r == r[0]).all() for r in rows)  # no position sends every sub-frame to one bucket
    rnd = _code("random")
    assert rnd.tile_shape == (20, 24) and 0.4 < rnd.tile.mean() < 0.6
    np.testing.assert_array_equal(rnd.tile, _code("random").tile)  # seeded
    assert _code("global").identity and not one_hot.uniform


def test_global_routing_returns_the_same_numbers_bit_for_bit():
    code = _code("global")
    x = np.random.default_rng(1).standard_normal((5, 6, 7, 3))
    out = code.route(x)
    assert out.dtype == x.dtype
    np.testing.assert_array_equal(out, x)


def test_bad_codes_are_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match="capture.gate_code.tile: 1x2 holds 2 positions; this family needs 5"):
        make_code("one_hot", 5, 2, width=8, height=8, tile=(1, 2))
    with pytest.raises(ConfigError, match=r"capture.gate_code.file: expected an array of shape \(sub-frames=5"):
        make_code("file", 5, 2, width=8, height=8, array=np.ones((4, 2, 2), int))
    with pytest.raises(ConfigError, match="1-based buckets 1..2 or 0"):
        make_code("file", 2, 2, width=8, height=8, array=np.full((2, 2, 2), 3))
    with pytest.raises(ConfigError, match="'global' sends sub-frame s to bucket s"):
        make_code("global", 5, 2, width=8, height=8)
    missing = tmp_path / "nope.npy"
    with pytest.raises(ConfigError, match=f"capture.gate_code.file: {missing} does not exist"):
        protocols.build(
            load_config(
                MULTI_FLASH,
                [
                    "sensor.bucket_count=2",
                    "capture.gate_code.family=file",
                    "capture.gate_code.subframes=5",
                    f"capture.gate_code.file={missing}",
                ],
            )
        )
    with pytest.raises(ConfigError, match="capture.gate_code.subframes: required by family 'hadamard'"):
        protocols.build(load_config(MULTI_FLASH, ["sensor.bucket_count=2", "capture.gate_code.family=hadamard"]))


# ---------------------------------------------------------------- the coded timeline
def test_coded_timeline_channels_reads_exposures_and_storage():
    tl = protocols.build(load_config(CODED, ["render.width=32", "render.height=24"]))
    assert (tl.n_channels, tl.n_buckets) == (5, 2) and [r.name for r in tl.reads] == ["B1", "B2"]
    T = Fraction(1, 1000)  # each sub-frame collects T in all
    shares = tl.code.shares()
    for k in range(2):
        mean = sum(shares[s][k] for s in range(5)) * T
        assert tl.exposure_ticks(k) * tl.tick_s == mean  # exact: the mean over the code's pixels
    assert tl.exposure_ticks(0) + tl.exposure_ticks(1) == 5 * T / tl.tick_s  # every sub-frame lands somewhere
    # the reset is global: both buckets from the first slot any pixel's bucket collects to the end
    assert tl.storage_ticks(0) == tl.storage_ticks(1) == tl.end_tick - tl.start_tick
    names, sets = tl.channel_read_sets()
    vectors, _ = tl.code.vectors()
    assert len(sets) == 2 * len(vectors) and all(s for s in sets)
    assert sum(len(s) for s in sets) == 5 * len(vectors)  # each pixel code's two reads partition the sub-frames
    assert len(tl.describe_reads()) == 2


def test_the_global_code_keeps_the_protocol_reads_and_other_codes_read_each_bucket():
    glob = protocols.build(load_config(MULTI_FLASH, ["capture.gate_code.family=global"]))
    plain = protocols.build(load_config(MULTI_FLASH, []))
    assert glob.reads == plain.reads and glob.segments == plain.segments and glob.code.identity
    assert [glob.storage_ticks(k) for k in range(5)] == [plain.storage_ticks(k) for k in range(5)]
    with pytest.raises(ConfigError, match="capture.gate_code: a conventional sequential capture"):
        protocols.build(load_config(MULTI_FLASH, ["capture.gate_code.family=global", "capture.sequential=true"]))


def test_codes_need_an_application_that_demultiplexes():
    with pytest.raises(ConfigError, match="the hdr application reads global-gate reads; .* \\(multi_flash\\)"):
        load_config(
            None, ["capture.gate_code.family=hadamard", "capture.gate_code.subframes=4", "sensor.bucket_count=2"]
        )
    with pytest.raises(ConfigError, match="sensor.cfa 'RGGB' with capture.gate_code"):
        load_config(CODED, ["sensor.cfa=RGGB"])
    load_config(None, ["capture.gate_code.family=global"])  # global gates written as a code: any application


# ---------------------------------------------------------------- demultiplexing
def _piecewise(S, H, W, seed=0):
    """Sub-frame images constant on 8x8 blocks (so a tent window inside a block sees one value)."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(100, 1000, size=(S, -(-H // 8), -(-W // 8), 3))
    return np.repeat(np.repeat(blocks, 8, axis=1), 8, axis=2)[:, :H, :W]


@pytest.mark.parametrize("family", ["one_hot", "hadamard", "random"])
def test_demultiplexing_recovers_locally_constant_images_exactly(family):
    S, H, W = 5, 48, 64
    code = make_code(family, S, 2, width=W, height=H, seed=1)
    x = _piecewise(S, H, W)
    A = code.measurement([(0,), (1,)], H, W)
    radius = (2, 2) if family == "random" else code.tile_shape
    d = demultiplex(code.route(x), A, radius)
    # away from the block edges every window sees one value per sub-frame: exact
    ry, rx = radius
    inner = np.zeros((H, W), bool)
    for by in range(0, H, 8):
        for bx in range(0, W, 8):
            inner[by + ry - 1 : by + 8 - ry + 1, bx + rx - 1 : bx + 8 - rx + 1] = True
    inner &= d.valid
    assert inner.sum() > 0.05 * H * W
    np.testing.assert_allclose(d.images[:, inner], x[:, inner], rtol=1e-9)
    # at block edges it blurs: a demosaicing, not magic
    assert np.abs(d.images - x)[:, d.valid & ~inner].max() > 1.0


def test_demultiplexing_variance_matches_monte_carlo():
    S, H, W = 4, 16, 16
    code = make_code("one_hot", S, 2, width=W, height=H)
    A = code.measurement([(0,), (1,)], H, W)
    clean = code.route(np.full((S, H, W, 1), 500.0))
    rng = np.random.default_rng(2)
    n = 1000
    est = np.stack(
        [
            demultiplex(clean + rng.standard_normal((2, H, W, 1)), A, code.tile_shape).images[:, 6:8, 6:8, 0]
            for _ in range(n)
        ]
    )
    d = demultiplex(clean, A, code.tile_shape)
    var = est.var(axis=0, ddof=1)  # (S, 2, 2): one tile's four code positions
    # the sample variance of n normal draws has relative standard error sqrt(2 / (n - 1))
    np.testing.assert_allclose(var, d.variance[:, 6:8, 6:8], rtol=5 * np.sqrt(2 / (n - 1)))
    assert np.ptp(d.variance[:, 6:8, 6:8]) > 0.2 * d.variance.mean()  # it does depend on the position
    np.testing.assert_allclose(d.noise_gain, np.median(d.variance.reshape(S, -1), axis=1))


def test_guided_demultiplexing_is_the_plain_fit_with_flat_weights_and_keeps_an_edge():
    S, H, W = 5, 32, 40
    code = make_code("hadamard", S, 2, width=W, height=H)
    A = code.measurement([(0,), (1,)], H, W)
    rng = np.random.default_rng(5)
    x = rng.uniform(100, 1000, size=(S, H, W, 3))
    plain = demultiplex(code.route(x), A, code.tile_shape)
    flat = demultiplex_guided(code.route(x), A, code.tile_shape, sigma=1e9)  # every weight exp(0) = 1
    np.testing.assert_allclose(flat.images, plain.images, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(flat.variance, plain.variance, rtol=1e-9)
    # a vertical edge where every sub-frame image doubles: the plain fit mixes both sides, the guided one not
    step = (
        np.where(np.arange(W) < 20, 1.0, 2.0)[None, None, :, None]
        * np.array([300.0, 200, 500, 400, 100])[:, None, None, None]
    )
    step = np.broadcast_to(step, (S, H, W, 1)).copy()
    reads = code.route(step)
    cols = slice(17, 23)  # the columns the 3 x 3 tile's window straddles
    err_plain = np.abs(demultiplex(reads, A, code.tile_shape).images - step)[:, 4:-4, cols].max()
    err_guided = np.abs(demultiplex_guided(reads, A, code.tile_shape).images - step)[:, 4:-4, cols].max()
    assert err_plain > 50 and err_guided < 1e-4 * step.max()  # the far side weighs exp(-50); the rest is rounding


def test_a_uniform_two_bucket_code_cannot_separate_five_sub_frames():
    code = GateCode("file", np.array([0, 1, 0, 1, 0], np.int8)[:, None, None], 2)
    A = code.measurement([(0,), (1,)], 8, 8)
    assert code_rank(A) == 2
    d = demultiplex(code.route(np.ones((5, 8, 8, 1))), A, (2, 2))
    assert not d.valid.any()
    assert code_rank(make_code("hadamard", 5, 2, width=8, height=8).measurement([(0,), (1,)], 8, 8)) == 5


def test_saturated_samples_get_no_weight():
    S, H, W = 4, 32, 32
    code = make_code("one_hot", S, 2, width=W, height=H)
    x = _piecewise(S, H, W, seed=4)
    reads = code.route(x)
    bad = np.zeros((2, H, W), bool)
    bad[1, 10, 10] = True
    reads[1, 10, 10] = 1e9  # a clipped value that must not leak in
    A = code.measurement([(0,), (1,)], H, W)
    d = demultiplex(reads, A, code.tile_shape, bad=bad)
    assert np.abs(d.images[:, 8:13, 8:13]).max() < 2000
    assert np.allclose(tent(2), [0.25, 0.5, 0.25])


# ---------------------------------------------------------------- photometric stereo
def test_near_light_photometric_stereo_recovers_a_sphere_and_a_tilted_plane():
    H, W = 40, 40
    yy, xx = np.mgrid[0:H, 0:W]
    # a sphere of radius 0.2 m at 1 m, seen along -z; background: a tilted plane
    u, v = (xx - 19.5) / 40 * 0.6, (yy - 19.5) / 40 * 0.6
    r2 = u**2 + v**2
    inside = r2 < 0.2**2
    n_sphere = np.stack([u, v, np.sqrt(np.maximum(0.04 - r2, 0))], -1) / 0.2
    pts = np.stack([u, v, np.where(inside, np.sqrt(np.maximum(0.04 - r2, 0)), -0.1 * u)], -1)
    n_plane = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    normals = np.where(inside[..., None], n_sphere, n_plane)
    lights = np.array([[0.3, 0, 1.0], [-0.3, 0, 1.0], [0, 0.3, 1.0], [0, -0.3, 1.0]])
    facing = -lights / np.linalg.norm(lights, axis=1)[:, None]
    imgs = []
    for p, f in zip(lights, facing):
        d = p - pts
        r = np.linalg.norm(d, axis=-1)
        to_light = d / r[..., None]
        imgs.append(0.7 * np.maximum((to_light * normals).sum(-1), 0) * np.maximum((-to_light * f).sum(-1), 0) / r**2)
    n, ok = near_light_normals(np.stack(imgs), pts, lights, facing)
    assert ok.mean() > 0.9  # the sphere's rim, lit by fewer than three lights, is left out
    assert angular_error_deg(n, normals)[ok].max() < 1e-4  # arccos near 1: float64 resolves ~1e-6 deg
    # lights given in the wrong places: the normals are wrong (the falloff matters)
    n2, ok2 = near_light_normals(np.stack(imgs), pts, lights * [1, 1, 3], facing)
    assert np.median(angular_error_deg(n2, normals)[ok2]) > 1.0


# ---------------------------------------------------------------- whole captures
TINY = ["render.width=48", "render.height=40", "render.spp=4", "app.truth_spp=4", "render.cache=off"]


@pytest.mark.render
def test_global_gates_written_as_a_code_reproduce_the_capture_bit_for_bit():
    from mbcapture.capture.pipeline import capture_in_memory
    from mbcapture.progress import StageStatus

    plain = capture_in_memory(load_config(MULTI_FLASH, TINY), StageStatus(False))
    coded = capture_in_memory(load_config(MULTI_FLASH, TINY + ["capture.gate_code.family=global"]), StageStatus(False))
    assert coded.timeline.code is not None and plain.timeline.code is None
    for name in ("bucket_exposure", "buckets_e", "reads_expected_e", "reads_dn", "saturated", "render_var_exposure"):
        np.testing.assert_array_equal(getattr(coded, name), getattr(plain, name), err_msg=name)
    for name, img in plain.images.items():
        np.testing.assert_array_equal(coded.images[name], img, err_msg=name)
    hdr = capture_in_memory(load_config(None, TINY[:3] + ["render.cache=off"]), StageStatus(False))
    hdr_coded = capture_in_memory(
        load_config(None, TINY[:3] + ["render.cache=off", "capture.gate_code.family=global"]), StageStatus(False)
    )
    np.testing.assert_array_equal(hdr_coded.reads_dn, hdr.reads_dn)  # non-destructive reads of bucket sums too


@pytest.mark.render
@pytest.mark.parametrize("family", ["hadamard", "one_hot", "random", "file"])
def test_a_coded_capture_conserves_light_and_keeps_the_sensor_physics(family, tmp_path):
    """Every family that routes each sub-frame to a bucket (a file's code without drains) holds the global
    schedule's light, rerouted; 'global' is that schedule (multi_flash), which needs a bucket per sub-frame."""
    from mbcapture.capture.pipeline import capture_in_memory
    from mbcapture.progress import StageStatus

    quiet = [
        "sensor.dark_current_e_per_s=0",
        "sensor.prnu=0",
        "sensor.dsnu_e=0",
        "sensor.parasitic_light=0",
        "sensor.transfer_inefficiency=0",
    ]
    code = [f"capture.gate_code.family={family}", "capture.gate_code.subframes=5"]
    if family == "file":  # 1-based buckets, no 0 (drain): every sub-frame's light lands in a bucket
        np.save(tmp_path / "codes.npy", np.random.default_rng(3).integers(1, 3, size=(5, 40, 48)).astype(np.int8))
        code.append(f"capture.gate_code.file={tmp_path / 'codes.npy'}")
    res = capture_in_memory(load_config(CODED, TINY + quiet + code), StageStatus(False))
    glob = capture_in_memory(load_config(MULTI_FLASH, TINY + quiet), StageStatus(False))
    # the same renders (same strata, seeds, samples): the coded buckets hold the global buckets' light, rerouted
    assert res.plan.passes == glob.plan.passes
    np.testing.assert_allclose(res.buckets_e.sum(axis=0), glob.buckets_e.sum(axis=0), rtol=1e-12)
    np.testing.assert_allclose(res.bucket_exposure, res.timeline.route(glob.bucket_exposure), rtol=1e-12)
    # shot noise on each bucket: Var(electrons - expected) = expected (+ read noise), over all pixels
    from mbcapture.sensor import dn_to_electrons

    e = dn_to_electrons(res.reads_dn, res.config.sensor).astype(np.float64)
    mu = res.reads_expected_e
    ok = ~res.saturated & (mu > 50)
    z = (e - mu)[ok] ** 2 - (mu[ok] + res.config.sensor.read_noise_e**2 + 1 / (12 * res.config.sensor.gain_dn_per_e**2))
    scale = mu[ok] + res.config.sensor.read_noise_e**2
    # z has mean 0 and standard deviation about sqrt(2) x scale (a normal's squared deviation)
    assert abs(z.mean() / scale.mean()) < 5 * np.sqrt(2 / ok.sum()) * (scale.std() / scale.mean() + 1)
    m = res.report["metrics"]
    assert m["coded_gates"]["family"] == family and m["coded_gates"]["subframes"] == 5
    assert set(m["per_light"]["nrmse"]) == {"top", "bottom", "left", "right"}
    assert m["normals"]["judged_px"] > 0


@pytest.mark.render
def test_a_sweep_over_code_families_shares_one_render_stage():
    from mbcapture.sweep.groups import group_key

    keys = {
        group_key(load_config(CODED, TINY + [f"capture.gate_code.family={f}"]))
        for f in ("one_hot", "hadamard", "random")
    }
    assert len(keys) == 1
