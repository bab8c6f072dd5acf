"""Back-to-back burst: registration, averaging and blur fit with known answers (no Mitsuba), the
protocol, and why back-to-back frames are easier to align (from the camera trajectory alone)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from mbcapture import load_config
from mbcapture.timing import protocols
from mbcapture.apps import burst
from mbcapture.errors import ConfigError
from mbcapture.reconstruct import register as rg


def _texture(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return gaussian_filter(rng.random((h, w)), 1.5) * 4 + 1.0


def _views(shifts, h=48, w=64, seed=0, channels=None):
    """(K, h, w[, C]) windows of one larger texture whose content is moved by each (dx, dy) px
    (cubic spline shift of the large image, then the central crop: no border artefacts)."""
    from scipy.ndimage import shift

    big = _texture(h + 24, w + 24, seed)
    out = np.stack([shift(big, (dy, dx), order=3, mode="reflect")[12:-12, 12:-12] for dx, dy in shifts])
    return out if channels is None else np.repeat(out[..., None], channels, -1)


@pytest.mark.parametrize("method,tol_px", [("ecc_euclidean", 0.1), ("ecc_homography", 0.1), ("phase_correlation", 0.3)])
def test_registration_recovers_known_shifts(method, tol_px):
    """ECC is accurate to a few hundredths of a pixel here; OpenCV's phase correlation (its sub-pixel
    peak from a weighted centroid) to a few tenths."""
    shifts = [(0.0, 0.0), (1.3, -0.6), (-2.2, 0.9), (0.4, 2.1)]
    rng = np.random.default_rng(1)
    clean = _views(shifts)
    frames = clean + rng.normal(0, 0.01, clean.shape)
    # true mean positions of a 3x3 grid of points in each frame: the reference's points moved by the shift
    grid = np.array([[x, y] for x in (12.0, 32.0, 52.0) for y in (10.0, 24.0, 38.0)])
    true = np.stack([grid + np.array(s) for s in shifts])
    warps = np.stack([np.eye(3)] + [rg.register_frame(frames[0], frames[k], method) for k in range(1, 4)])
    err = rg.registration_errors(warps, true, 0)
    assert err[0] == 0 and np.all(err[1:] < tol_px), err
    none = rg.registration_errors(np.stack([np.eye(3)] * 4), true, 0)
    assert np.allclose(none, [np.hypot(*s) for s in shifts])  # no alignment: the error is the shift


def test_aligned_average_of_k_frames_has_1_over_sqrt_k_of_the_noise():
    """Integer shifts (no interpolation smoothing): the average of 4 aligned frames with independent
    noise sigma has noise sigma / 2 in the interior (standard error of a std over n samples:
    sigma / sqrt(2 n); tolerance 5 of them)."""
    sigma, shifts = 0.05, [(0, 0), (2, -1), (-1, 3), (3, 2)]
    rng = np.random.default_rng(2)
    clean = _views(shifts, 64, 80, channels=3)
    base = clean[0]
    frames = clean + rng.normal(0, sigma, clean.shape)
    sat = np.zeros(frames.shape, bool)
    out = rg.align_and_average(frames, sat, "phase_correlation", reference=0)
    assert out.coverage[8:-8, 8:-8].min() == 4
    resid = (out.average - base)[8:-8, 8:-8]
    n = resid.size
    assert resid.std() == pytest.approx(sigma / 2, abs=5 * (sigma / 2) / np.sqrt(2 * n) + 0.002)
    # a saturated sample of frame 2 (content moved by (2, -1)) is left out where it lands on the reference
    sat[1, 30, 40, :] = True
    out2 = rg.align_and_average(frames, sat, "phase_correlation", reference=0)
    assert out2.coverage[31, 38] == 3 and (out2.coverage[8:-8, 8:-8] < 4).sum() <= 4


def test_blur_fit_recovers_a_known_gaussian_blur():
    truth = _texture(64, 64, 3)
    rng = np.random.default_rng(4)
    for sigma in (0.0, 0.8, 1.7):
        blurred = gaussian_filter(truth, sigma) if sigma else truth
        got = rg.fit_blur_px(blurred + rng.normal(0, 0.005, truth.shape), truth)
        assert got == pytest.approx(sigma, abs=0.08)


def test_score_is_blind_to_a_global_shift_but_not_to_blur():
    truth, shifted = _views([(0, 0), (1.5, -0.7)], 60, 80, 5, channels=3)
    s = burst.score(shifted, truth)
    assert s["scoring_shift_px"] == pytest.approx(1.5, abs=0.1)  # the largest coordinate shift of a corner
    assert s["residual_blur_px"] < 0.35
    blurred = burst.score(gaussian_filter(truth, (1.5, 1.5, 0)), truth)
    assert blurred["residual_blur_px"] == pytest.approx(1.5, abs=0.15) and blurred["psnr_db"] < s["psnr_db"]


BURST = ["render.width=160", "render.height=128", "render.spp=2"]


def _scene_timeline(cfg):
    """The capture's scene (with its camera motion) and timeline, without planning its strata."""
    from mbcapture.scene import camera_motion, scenes

    return camera_motion.apply(scenes.make_scene(cfg.scene.name, cfg.scene.params()), cfg.camera), protocols.build(cfg)


def test_burst_protocol_takes_equal_frames_back_to_back():
    cfg = load_config("burst", BURST)
    tl = protocols.build(cfg)
    reads = tl.describe_reads()
    assert [r["name"] for r in reads] == ["F1", "F2", "F3", "F4"]
    assert all(r["exposure_s"] == pytest.approx(0.02) for r in reads)
    for a, b in zip(reads, reads[1:]):  # no gap: each frame starts when the previous one ends
        assert b["span_start_s"] == pytest.approx(a["span_end_s"])
    seq = protocols.build(load_config("burst", [*BURST, "capture.sequential=true"])).describe_reads()
    for a, b in zip(seq, seq[1:]):  # the conventional burst: a readout between frames
        assert b["span_start_s"] - a["span_end_s"] == pytest.approx(cfg.sensor.frame_readout_s)
    with pytest.raises(ConfigError, match="capture.periods: the 'burst' protocol"):
        protocols.build(load_config("burst", [*BURST, "capture.periods=4"]))


def test_back_to_back_frames_move_less_between_them_than_a_conventional_burst():
    """From the trajectories alone (no render): for 24 hands, the RMS displacement between consecutive
    frames' mean image positions, back to back and with a 33 ms readout between frames (same hand for
    both). The readout gap lets the drift grow and puts consecutive frames half a 10 Hz tremor period
    apart: the conventional burst's frames lie farther apart, by more than 4 standard errors of the
    paired difference; and a still camera has no shake at all."""
    diffs = []
    for seed in range(24):
        rms = []
        for seq in ("false", "true"):
            cfg = load_config("burst", [*BURST, f"camera.shake.seed={seed}", f"capture.sequential={seq}"])
            scene, tl = _scene_timeline(cfg)
            pos = burst.mean_positions(scene, tl, 160, 128)
            rms.append(np.sqrt(np.mean(np.sum(np.diff(pos, axis=0) ** 2, axis=-1))))
        diffs.append(rms[1] - rms[0])
    diffs = np.array(diffs)
    assert diffs.mean() > 4 * diffs.std(ddof=1) / np.sqrt(diffs.size)
    scene, tl = _scene_timeline(load_config("burst", [*BURST, "camera.shake=null"]))
    pos = burst.mean_positions(scene, tl, 160, 128)
    assert np.abs(pos - pos[0]).max() < 1e-9
    assert burst.frame_blur_px(scene, tl, 160, 128).max() == 0.0


def test_warp_onto_samples_at_the_warped_position_and_marks_what_falls_outside():
    """out(p) = image(warp(p)): on x^2 a half-pixel shift gives the bilinear average x^2 + x + 0.5,
    or with OpenCV's bicubic kernel (a = -0.75) x^2 + x + 0.125; pixels whose sample lies partly
    outside the image are NaN; a homography with warp[2] != (0, 0, 1) goes through the
    perspective path and, for the same transform, gives the same image."""
    h, w = 6, 10
    x = np.arange(w, dtype=float)
    img = np.broadcast_to((x / 4) ** 2, (h, w)).copy()  # small values: float32 keeps ~1e-7
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    lin = rg.warp_onto(img, shift)
    xs = x[:-1] / 4
    np.testing.assert_allclose(lin[:, :-1], np.broadcast_to(xs**2 + xs / 4 + 0.5 / 16, (h, w - 1)), rtol=1e-6)
    assert np.isnan(lin[:, -1]).all() and lin.dtype == np.float64
    cub = rg.warp_onto(img, shift, cubic=True)
    np.testing.assert_allclose(
        cub[:, 1:-2], np.broadcast_to(xs[1:-1] ** 2 + xs[1:-1] / 4 + 0.125 / 16, (h, w - 3)), rtol=1e-5
    )
    assert np.isnan(cub[:, -1]).all()
    np.testing.assert_allclose(rg.warp_onto(img, 2.0 * shift), lin, rtol=1e-6)  # the same transform, projective
    # (H, W, C) in, (H, W, C) out; an integer shift down by 2 rows: the last two rows are outside
    rgb = np.stack([img, 2 * img, 3 * img], -1)
    down = rg.warp_onto(rgb, np.array([[1.0, 0, 0], [0, 1.0, 2.0], [0, 0, 1.0]]))
    assert down.shape == (h, w, 3)
    np.testing.assert_allclose(down[:-2], rgb[2:], rtol=1e-6)
    assert np.isnan(down[-2:]).all()


def test_score_registered_leaves_out_the_border_and_unfilled_pixels():
    truth = np.repeat(_texture(24, 32, seed=4)[..., None], 3, -1)
    on = 1.1 * truth
    on[:2] = 50.0  # the border (2 px) is not scored
    on[10, 10] = np.nan  # nor are pixels the registration left unfilled
    s = burst.score_registered(on, truth, 2)
    inner = (slice(2, 22), slice(2, 30))
    ok = np.ones((20, 28), bool)
    ok[8, 8] = False
    t = truth[inner][ok]
    lt = t.mean(-1)  # luminance of a grey pixel
    from mbcapture.metrics import luminance

    lt_all = luminance(truth[inner])
    peak = np.percentile(lt_all, 99.9)
    assert s["psnr_db"] == pytest.approx(10 * np.log10(peak**2 / np.mean((0.1 * lt) ** 2)), rel=1e-9)
    assert s["rel_mse"] == pytest.approx(np.mean((0.1 * t) ** 2 / (t**2 + 1e-4)), rel=1e-9)
    assert s["residual_blur_px"] == 0.0  # a gain is not a blur
    exact = burst.score_registered(truth, truth, 2)
    assert exact["psnr_db"] == np.inf and exact["rel_mse"] == 0.0 and exact["residual_blur_px"] == 0.0
    # a blurred result inside the border: the blur is measured there
    blurred = truth.copy()
    blurred[2:22, 2:30] = np.repeat(gaussian_filter(truth[..., 0], 1.2, mode="nearest")[2:22, 2:30, None], 3, -1)
    blurred[10, 10] = np.nan  # an unfilled pixel takes the truth's value in the blur fit
    assert burst.score_registered(blurred, truth, 2)["residual_blur_px"] == pytest.approx(1.2, abs=0.1)
    # an image that would keep fewer than 4 rows or columns without its border is scored whole
    base = np.repeat(_texture(32, 32, seed=5)[..., None], 3, -1)
    gain = 1.0 + np.random.default_rng(5).uniform(0, 0.2, base.shape)  # a different error per pixel
    for h, w in ((6, 32), (32, 6), (7, 32), (8, 32), (32, 8), (9, 32), (32, 9)):
        t = base[:h, :w]
        whole = h - 4 < 4 or w - 4 < 4
        sl = (slice(None), slice(None)) if whole else (slice(2, h - 2), slice(2, w - 2))
        d, tt = (gain[:h, :w] - 1) * t, t
        expect = np.mean(d[sl] ** 2 / (tt[sl] ** 2 + 1e-4))
        assert burst.score_registered(gain[:h, :w] * t, t, 2)["rel_mse"] == pytest.approx(expect, rel=1e-9), (h, w)
