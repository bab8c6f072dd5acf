"""Flutter shutter: codes, exposure kernels, least-squares deblurring and its noise on synthetic rows
with known answers (no Mitsuba); the protocol and the planner's strata against the chop length; one
tiny render comparing box, classic flutter and two-bucket flutter at equal exposure."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.scene import scenes
from mbcapture.apps import CaptureData
from mbcapture.apps import flutter_shutter as fs
from mbcapture.errors import ConfigError
from mbcapture.exposure.plan import make_plan
from mbcapture.reconstruct import deblur as db

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "flutter_shutter.yaml"
CODE = fs.code_bits("raskar2006")


def test_raskar_code_and_custom_codes():
    assert len(CODE) == 52 and CODE.sum() == 26 and CODE[0] == 1 and CODE[-1] == 1
    np.testing.assert_array_equal(fs.code_bits("1101"), [1, 1, 0, 1])
    for bad in ("", "0000", "10201", "gray"):
        with pytest.raises(ConfigError, match="app.code"):
            fs.code_bits(bad)
    with pytest.raises(ConfigError, match="app.code"):
        load_config(CONFIG, ["app.code=12"])
    with pytest.raises(ConfigError, match=r"app.deblur: .*fourier"):
        load_config(CONFIG, ["app.deblur=magic"])


def test_spread_kernel_keeps_weight_and_centroid():
    rng = np.random.default_rng(0)
    s, w = rng.uniform(-7.3, 9.1, 500), rng.uniform(0, 1, 500)
    first, h = db.spread_kernel(s, w)
    x = first + np.arange(len(h))
    assert h.sum() == pytest.approx(w.sum()) and (x * h).sum() == pytest.approx((s * w).sum())
    first, h = db.spread_kernel(np.array([2.25]), np.array([1.0]))
    assert first == 2 and h.tolist() == [0.75, 0.25]


def _rows(n_rows=40, n=120, support=(30, 80), seed=0):
    f = np.zeros((n_rows, n, 1))
    f[:, support[0] : support[1], 0] = np.random.default_rng(seed).uniform(0.1, 1.0, (n_rows, support[1] - support[0]))
    return f


def _blur(f, kernel):
    a = db.blur_matrix(*kernel, f.shape[1])
    return np.einsum("xy,ry->rx", a, f[..., 0])[..., None]


def test_blur_matrix_is_the_convolution():
    f = _rows(n_rows=1)[0, :, 0]
    k = (-3, np.array([0.2, 0.0, 0.5, 1.0, 0.3]))
    want = np.convolve(f, k[1])[np.arange(len(f)) - k[0]]
    np.testing.assert_allclose(db.blur_matrix(*k, len(f)) @ f, want, atol=1e-12)
    assert db.support([k], len(f)) == (3, len(f) - 1)  # f[x] reaches x - 3 .. x + 1
    np.testing.assert_allclose(db.blur_matrix(*k, len(f), (3, 119)) @ f[3:119], want, atol=1e-12)  # f is 0 outside
    with pytest.raises(ConfigError, match="wider than"):
        db.support([(-60, np.ones(121))], 120)


def test_least_squares_inverts_the_code_and_the_joint_solution_is_exact_too():
    f = _rows()
    chop = 1.0  # normal equations square the condition number: keep the numbers near 1
    k_open = (-26, CODE * chop)
    k_closed = (-26, (1 - CODE) * chop)
    b = np.stack([_blur(f, k_open), _blur(f, k_closed)])
    w = np.ones((2, 1))
    np.testing.assert_allclose(db.deblur_least_squares(b[:1], [k_open], w[:1], 0.0), f, atol=1e-6)
    np.testing.assert_allclose(db.deblur_least_squares(b, [k_open, k_closed], w, 0.0), f, atol=1e-6)
    # the box of the same length is exact too without noise, but far worse conditioned (next test)
    np.testing.assert_allclose(
        db.deblur_least_squares(_blur(f, (-26, np.ones(52)))[None], [(-26, np.ones(52))], w[:1], 0.0), f, atol=1e-4
    )


def _samples(code, first=-26, frac=0.0):
    """(shifts, seconds) of a code at one pixel per chop, chop k at shift first + k + frac."""
    return first + np.arange(len(code)) + frac, np.asarray(code, float)


def test_fourier_deblur_inverts_integer_and_fractional_shifts():
    """Integer shifts: the padded circular model is the linear convolution, so the sharp rows come back
    exactly. Fractional shifts: a band-limited row (a few low-frequency cosines) shifted by s - 0.37 px
    is exactly what the model describes, and comes back too."""
    f = _rows()
    k_open, k_closed = _samples(CODE), _samples(1 - CODE)
    b = np.stack([_blur(f, db.spread_kernel(*k_open)), _blur(f, db.spread_kernel(*k_closed))])
    w = np.ones((2, 1))
    np.testing.assert_allclose(db.deblur_fourier(b[:1], [k_open], w[:1], 0.0), f, atol=1e-8)
    np.testing.assert_allclose(db.deblur_fourier(b, [k_open, k_closed], w, 0.0), f, atol=1e-8)
    # band-limited (Gaussians of sigma 2.5 px: nothing left at the Nyquist frequency), shifted by
    # fractional amounts and zero at both ends of the row: the model is exact
    x = np.arange(120.0)
    g = lambda x: np.exp(-0.5 * ((x - 50) / 2.5) ** 2) + 0.6 * np.exp(-0.5 * ((x - 71.3) / 2.5) ** 2)  # noqa: E731
    # shifts on the 1/256 px grid the spectra are computed on: exact; off it, within the binning's
    # 1/512 px times the largest slope of g (0.24 / px)
    for frac, tol in ((-0.375, 1e-9), (-0.37, 0.24 / 512)):
        k_frac = _samples(CODE, frac=frac)
        blurred = sum(t * g(x - sh) for sh, t in zip(*k_frac))
        got = db.deblur_fourier(blurred[None, None, :, None], [k_frac], np.ones((1, 1)), 0.0)[0, :, 0]
        np.testing.assert_allclose(got, g(x), atol=tol)


def test_fourier_noise_gain_by_monte_carlo():
    """White noise over whole rows through the per-frequency least squares: the pixel variance is
    mean_w 1 / sum_r |H_r(w)|^2 (white_noise_gain), within 5 standard errors of the variance estimate."""
    samples = [_samples(CODE), _samples(1 - CODE)]
    n = db.fft_length(samples, 120)
    rows = 800
    noise = np.random.default_rng(2).standard_normal((2, rows, n, 1))
    out = db.deblur_fourier(noise, samples, np.ones((2, 1)), 0.0)  # rows of the FFT length: no padding
    var = out[..., 0].var(axis=0, ddof=1).mean()
    want = db.white_noise_gain(samples, np.ones(2), 120, 1.0) ** 2
    # the mean over n pixels of correlated variance estimates: bound by the single-pixel standard error
    assert abs(var / want - 1) < 5 * np.sqrt(2 / (rows - 1))
    single = db.white_noise_gain(samples[:1], np.ones(1), 120, 1.0)
    box = db.white_noise_gain([_samples(np.ones(52))], np.ones(1), 120, 1.0)
    assert box > 3 * single > 3 * db.white_noise_gain(samples, np.ones(2), 120, 1.0)


def test_linear_interpolation_of_one_pixel_chops_has_a_zero_at_nyquist():
    """Why 'fourier' is the default: a chop spanning exactly one pixel, spread linearly, is the code
    smoothed by [1/2, 1/2] (gain 0 at Nyquist); band-limited shifts keep the pixel's own sinc (0.64)."""
    fine = np.linspace(0, 1, 1001)[:-1] + 0.0005  # one chop's displacements, uniform over [0, 1) px
    first, h = db.spread_kernel(fine, np.full(fine.size, 1e-3))
    assert first == 0 and np.allclose(h, [0.5, 0.5], atol=1e-3)
    assert abs(np.sum(h * np.exp(-1j * np.pi * np.arange(2)))) < 1e-3
    n = 64
    hb = db.kernel_spectrum(fine, np.full(fine.size, 1e-3), n)
    assert abs(hb[-1]) == pytest.approx(2 / np.pi, rel=1e-3)


def _noise_std(kernels, n=120, regularization=0.0):
    """Per-pixel output noise std of the least-squares deblur for unit white noise in every read."""
    m = db.normal_matrix(kernels, np.ones(len(kernels)), n, regularization)
    return np.sqrt(np.diag(np.linalg.inv(m)))


def test_noise_of_box_flutter_and_two_bucket_flutter():
    """Raskar's point and the paper's: the box blur is nearly singular, the code is not; both buckets
    together beat the open bucket alone (the same code, twice the light)."""
    chop = 1.0
    box = _noise_std([(-26, np.ones(52) * chop)])
    flutter = _noise_std([(-26, CODE * chop)])
    both = _noise_std([(-26, CODE * chop), (-26, (1 - CODE) * chop)])
    rms = lambda s: float(np.sqrt(np.mean(s**2)))  # noqa: E731
    assert rms(box) > 3 * rms(flutter)
    assert rms(both) < rms(flutter) and (both <= flutter * (1 + 1e-9)).all()


def test_measured_deblur_noise_matches_the_normal_matrix():
    """Monte Carlo: 400 rows of white noise through the joint deblur; the per-pixel variance agrees with
    diag((sum A^T A)^-1) within 5 standard errors (the variance estimate's relative s.e. is sqrt(2/(n-1)))."""
    n_rows, n = 400, 120
    kernels = [(-26, CODE * 1.0), (-26, (1 - CODE) * 1.0)]
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((2, n_rows, n, 1))
    f = db.deblur_least_squares(noise, kernels, np.ones((2, 1)), 0.0)
    lo, hi = db.support(kernels, n)
    assert (f[:, :lo] == 0).all() and (f[:, hi:] == 0).all()
    var = f[:, lo:hi, 0].var(axis=0, ddof=1)
    want = _noise_std(kernels, n) ** 2
    rel = var / want - 1
    se = np.sqrt(2 / (n_rows - 1))
    assert np.abs(rel).max() < 5 * se


def test_read_kernels_follow_the_code_at_one_pixel_per_chop():
    """At 640x512 the card moves 2.0 px/ms, 1.0 px per 0.5 ms chop: the open bucket's kernel is the code
    (each chop's second spread over the pixel it crosses), the two buckets' kernels sum to the box."""
    cfg = load_config(CONFIG)
    tl = protocols.build(cfg)
    sc = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    t_mid = float(tl.seconds((tl.start_tick + tl.end_tick) // 2))
    (f_o, h_o), (f_c, h_c) = (db.read_kernel(tl, r, sc, t_mid, 640, 512) for r in tl.reads)
    chop = 0.026 / 52
    assert h_o.sum() == pytest.approx(26 * chop, rel=1e-9) and h_c.sum() == pytest.approx(26 * chop, rel=1e-9)
    shifts, weights = fs._sum_kernels([(f_o, h_o), (f_c, h_c)])
    fb, hb = db.spread_kernel(shifts, weights)
    assert hb.sum() == pytest.approx(52 * chop) and np.count_nonzero(hb > 0.01 * chop) == 53  # a box of 52 px,
    assert np.all(hb[hb > 0.9 * chop] == pytest.approx(chop, rel=1e-3))  # half a pixel at each end
    # the open kernel, resampled per chop: chop k lies at shift k - 26 + 1/2 (its centre), so pixel
    # j gets half of chops j + 25 and j + 26
    x = f_o + np.arange(len(h_o))
    code_px = np.array(
        [0.5 * (CODE[j + 25] if 0 <= j + 25 < 52 else 0) + 0.5 * (CODE[j + 26] if 0 <= j + 26 < 52 else 0) for j in x]
    )
    np.testing.assert_allclose(h_o / chop, code_px, atol=0.02)


def test_protocol_for_each_shutter_and_sequential_frames():
    tl = protocols.build(load_config(CONFIG))
    seg = tl.segments[0]
    assert [s.bucket for s in seg.slots] == [0 if c else 1 for c in CODE] and [r.name for r in tl.reads] == [
        "open",
        "closed",
    ]
    assert float(tl.read_exposure_ticks(tl.reads[0]) * tl.tick_s) == pytest.approx(0.013)
    classic = protocols.build(load_config(CONFIG, ["app.shutter=flutter"]))
    assert [s.bucket for s in classic.segments[0].slots] == [0 if c else -1 for c in CODE]
    box = protocols.build(load_config(CONFIG, ["app.shutter=box"]))
    assert [r.name for r in box.reads] == ["box"] and box.read_exposure_ticks(
        box.reads[0]
    ) * box.tick_s == pytest.approx(0.026)
    seq = protocols.build(load_config(CONFIG, ["capture.sequential=true"]))
    assert seq.sequential and len(seq.segments) == 2
    with pytest.raises(ConfigError, match="sensor.bucket_count"):
        protocols.build(load_config(CONFIG, ["sensor.bucket_count=1"]))


@pytest.mark.parametrize(
    "width,height,max_motion,resolved", [(640, 512, 0.25, True), (160, 128, 0.25, True), (160, 128, 1.0, False)]
)
def test_planner_strata_resolve_one_chop(width, height, max_motion, resolved):
    """render.max_motion_px bounds the image motion inside a stratum; at the config's 0.25 px no stratum
    moves further than one chop's motion at either size (0.25 px at 160x128, 1 px at 640x512)."""
    cfg = load_config(
        CONFIG, [f"render.width={width}", f"render.height={height}", f"render.max_motion_px={max_motion}"]
    )
    sc = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    tl = protocols.build(cfg)
    plan = make_plan(tl, sc, cfg.render, np.random.default_rng(0))
    data = CaptureData(
        cfg=cfg,
        scene=sc,
        timeline=tl,
        plan=plan,
        read_names=[],
        exposure_s=None,
        reads_dn=None,
        saturated=None,
        reads_e_expected=None,
        bucket_exposure=None,
        k_e=None,
        moving_mask=None,
    )
    chk = fs.strata_check(data, 52)
    assert chk["resolved"] is resolved
    assert chk["max_stratum_motion_px"] <= max_motion * (1 + 1e-6)
    assert chk["chop_motion_px"] == pytest.approx(2.0 * 0.5 * width / 640, rel=1e-3)


@pytest.mark.render
def test_two_bucket_flutter_beats_flutter_beats_box_at_equal_exposure():
    from mbcapture import run_capture

    # 64x48 with the card 5x faster: 26 px of blur, half a pixel per chop (strata of at most one chop)
    tiny = [
        "render.width=64",
        "render.height=48",
        "render.spp=1",
        "scene.speed_m_per_s=11.375",
        "app.truth_spp=16",
        "render.max_motion_px=0.5",
    ]
    res = run_capture(load_config(CONFIG, tiny), progress=False)
    c = res.report["metrics"]["comparison"]
    assert res.report["metrics"]["strata"]["resolved"]
    assert c["two_bucket_flutter"]["psnr_db"] > c["flutter"]["psnr_db"] > c["box"]["psnr_db"] + 3
    assert c["box"]["noise_amplification"] > 2 * c["flutter"]["noise_amplification"]
    assert c["two_bucket_flutter"]["noise_amplification"] < c["flutter"]["noise_amplification"]
    assert c["flutter"]["light_fraction"] == pytest.approx(0.5) and c["two_bucket_flutter"]["light_fraction"] == 1.0
    # the box baseline is exactly what a box exposure collects: the same renders, one bucket
    box = run_capture(load_config(CONFIG, tiny + ["app.shutter=box"]), progress=False)
    np.testing.assert_allclose(box.reads_expected_e[0], res.reads_expected_e.sum(axis=0), rtol=1e-9)


def test_reconstruct_deblurs_a_known_row_without_mitsuba():
    """The whole reconstruction on a synthetic capture: a band-limited sharp image (Gaussian spots,
    sigma 2 px) moved along the shipped protocol's timeline at the scene's speed, integrated in time
    directly (not through the deconvolution's own model), reads in DN; both the single-code and the
    joint solution give the sharp image back, in radiance, at the capture's mid-time."""
    from mbcapture.apps import get
    from mbcapture.sensor import electrons_per_render_second

    w, h = 96, 8
    cfg = load_config(CONFIG, [f"render.width={w}", f"render.height={h}"])
    sc = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    tl = protocols.build(cfg)
    t_mid = float(tl.seconds(tl.start_tick + (tl.end_tick - tl.start_tick) / 2))
    x = np.arange(w) + 0.5
    centres = np.array([30.0, 41.5, 55.2, 63.0])
    amp = np.linspace(0.5, 1.0, h)[:, None, None] * np.array([0.2, 0.3, 0.25])[None, None, :]  # radiance

    def sharp(shift):
        prof = sum(np.exp(-0.5 * ((x - shift - c) / 2.0) ** 2) for c in centres)
        return amp * prof[None, :, None]

    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    e = []
    for r in tl.reads:  # time integral at the same 40 000 steps' displacements, but of the continuous image
        shifts, secs = db.read_samples(tl, r, sc, t_mid, w, h)
        idx = np.arange(0, len(secs), 20)
        e.append(sum(t * sharp(s) for s, t in zip(shifts[idx], np.add.reduceat(secs, idx))) * k_e)
    e = np.stack(e)
    dn = e * cfg.sensor.gain_dn_per_e + cfg.sensor.black_level_dn
    exposure = np.array([float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads])
    data = CaptureData(
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
        moving_mask=np.ones((h, w), bool),
    )
    app = get("flutter_shutter")
    peak = float(sharp(0.0).max())
    for method in ("joint", "single"):
        out = app.reconstruct(data, app.params(method=method))
        assert out.metrics["method"] == method
        # 20 steps of 0.65 us merged per sample: the image moves 0.003 px within one, far below 1 %
        np.testing.assert_allclose(out.images["deblurred"], sharp(0.0), atol=0.01 * peak)
    assert out.metrics["kernels_px"]["open"]["seconds"] == pytest.approx(0.013)


def test_read_weights_are_inverse_noise_variances_in_radiance_units():
    """w = k_e^2 / (mean electrons + read noise^2) per read and channel: the inverse variance of a
    radiance estimate e / k_e with Poisson and read noise, averaged over the region (the whole
    image when the region is empty)."""
    rng = np.random.default_rng(3)
    e = rng.uniform(100.0, 900.0, (3, 5, 6, 2))  # (R, H, W, C) expected electrons
    k_e = np.array([2.0, 3.0])
    region = np.zeros((5, 6), bool)
    region[1:3, 2:5] = True
    w = fs.read_weights(e, k_e, 4.0, region)
    assert w.shape == (3, 2)
    for r in range(3):
        for c in range(2):
            assert w[r, c] == pytest.approx(k_e[c] ** 2 / (e[r][region][:, c].mean() + 16.0), rel=1e-12)
    whole = fs.read_weights(e, k_e, 4.0, np.zeros((5, 6), bool))
    np.testing.assert_allclose(whole, k_e[None] ** 2 / (e.mean(axis=(1, 2)) + 16.0), rtol=1e-12)
