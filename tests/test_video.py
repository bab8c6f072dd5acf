"""Multi-bucket video: the frame-rate check, per-frame configs, the comparison measures with known
answers (no Mitsuba), and a tiny video run with its files."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, shift

from mbcapture import load_config
from mbcapture.scene import scenes
from mbcapture.capture import video
from mbcapture.capture.pipeline import frame_period_check, prepare
from mbcapture.timing import protocols
from mbcapture.errors import ConfigError


def test_a_frame_period_shorter_than_capture_plus_readout_is_refused():
    ok = load_config("hdr_video", ["render.width=16", "render.height=12"])
    assert frame_period_check(ok, protocols.build(ok)) == pytest.approx(1 / 30)
    # 8 ms of capture + 10 ms of readout do not fit in 1/60 s
    with pytest.raises(ConfigError, match=r"capture.frame_rate_hz: 60 frames/s .* at most 55.56 frames/s"):
        prepare(load_config("hdr_video", ["capture.frame_rate_hz=60", "render.width=16", "render.height=12"]))
    with pytest.raises(ConfigError, match="capture.frame_rate_hz is required when capture.frames > 1"):
        load_config(None, ["capture.frames=3"])


def test_frame_configs_shift_the_start_and_draw_their_own_noise():
    cfg = load_config("hdr_video", ["render.width=16", "render.height=12"])
    frames = [video.frame_config(cfg, i) for i in range(3)]
    assert [f.capture.start_s for f in frames] == pytest.approx([0.0, 1 / 30, 2 / 30])
    assert all(f.capture.frames == 1 for f in frames)
    assert len({f.sensor.noise_seed for f in frames}) == 3
    assert video.frame_config(cfg, 1).sensor.noise_seed == frames[1].sensor.noise_seed  # reproducible
    assert video.frame_config(cfg, 2, spp=12).render.spp == 12


def test_aliasing_of_a_fast_needle_at_3_frames_per_second():
    """A 208 bpm metronome (sine motion) swings at 208/120 = 1.733 Hz: 30 frames/s see 1.733 Hz, 3 frames/s
    (Nyquist 1.5 Hz) a false 3 - 1.733 = 1.267 Hz swing, within the analysis' frequency resolution."""
    mod = scenes.load_module("metronome")
    scene = scenes.make_scene("metronome", mod.Params(tempo_bpm=208, motion_model="sine"))
    out = video.aliasing(scene, [30.0, 3.0], 0.0, 0.004, 0.5, 160, 128)
    res = out["frequency_resolution_hz"]
    assert out["true_frequency_hz"] == pytest.approx(208 / 120, abs=res)
    assert out["rates"]["30"]["apparent_frequency_hz"] == pytest.approx(208 / 120, abs=res)
    assert out["rates"]["3"]["apparent_frequency_hz"] == pytest.approx(3 - 208 / 120, abs=res)
    assert out["rates"]["3"]["aliased"] and not out["rates"]["30"]["aliased"]


def test_temporal_consistency_counts_only_changes_the_truth_does_not_have():
    rng = np.random.default_rng(0)
    truth = rng.random((5, 8, 10, 3)) + 1.0
    assert video.temporal_consistency(truth * 1.0 + 0.0, truth) == pytest.approx(0.0, abs=1e-12)
    assert video.temporal_consistency(truth + 0.3, truth) == pytest.approx(
        0.0, abs=1e-12
    )  # a constant offset: no change
    flicker = truth + 0.1 * (np.arange(5) % 2)[:, None, None, None]  # +0.1 on odd frames: every step changes by 0.1
    mean_lum = float(np.mean(truth @ np.array([0.2126, 0.7152, 0.0722])))
    assert video.temporal_consistency(flicker, truth) == pytest.approx(0.1 / mean_lum, rel=1e-9)
    assert video.temporal_consistency(truth[:1], truth[:1]) is None


def test_alternating_merge_undoes_the_motion_between_frames():
    """Three frames of a textured scene translating by 1.5 px per frame, exposures T, 8T, T (DN with
    shot-like noise): merged, the middle frame is closer to its noise-free value than alone, and the
    first frame (short, one long neighbour) gains most."""
    from mbcapture.sensor import SensorConfig

    sensor = SensorConfig(
        read_noise_e=3.0, gain_dn_per_e=1.0, black_level_dn=0.0, adc_bits=16, full_well_e=1e6, fd_full_well_e=1e6
    )
    rng = np.random.default_rng(3)
    big = gaussian_filter(rng.random((60, 84)), 2.0) * 3 + 0.5
    rate = np.stack([shift(big, (0, 1.5 * i), order=3, mode="reflect")[6:-6, 6:-6] for i in range(3)]) * 2e4  # e-/s
    rate = np.repeat(rate[..., None], 3, -1)
    exps = np.array([1e-3, 8e-3, 1e-3])
    clean = rate * exps[:, None, None, None]
    dn = [rng.poisson(c) + rng.normal(0, 3.0, c.shape) for c in clean]
    sat = [np.zeros(c.shape, bool) for c in clean]
    for i in (0, 2):
        merged = video.alternating_merge(dn, sat, exps, sensor, "dis_medium", i)
        alone = dn[i] / exps[i]
        core = (slice(8, -8), slice(8, -8))
        err_merged = np.sqrt(np.mean((merged[core] - rate[i][core]) ** 2))
        err_alone = np.sqrt(np.mean((alone[core] - rate[i][core]) ** 2))
        assert err_merged < 0.6 * err_alone


@pytest.mark.render
def test_tiny_video_writes_frames_movie_and_metrics(tmp_path):
    import csv
    import json

    import imageio.v3 as iio

    from mbcapture import run_capture
    from mbcapture.output.io import read_exr

    cfg = load_config(
        "hdr_video",
        ["render.width=16", "render.height=12", "capture.frames=4", "render.spp=4", "render.max_motion_px=4"],
    )
    res = run_capture(cfg, tmp_path, progress=False)
    assert len(res.video.frames) == 4
    for i in range(4):
        layers = read_exr(tmp_path / f"frame_{i:04d}.exr")
        assert np.allclose(layers["radiance"], res.video.frames[i].images["radiance"], rtol=1e-6)
    mp4 = iio.imread(tmp_path / "video.mp4", plugin="FFMPEG", index=None)
    gif = iio.imread(tmp_path / "video.gif", index=None)
    assert mp4.shape[:3] == (4, 12, 16) and gif.shape[:3] == (4, 12, 16)
    rows = list(csv.DictReader((tmp_path / "frames.csv").open()))
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3]
    rep = json.loads((tmp_path / "report.json").read_text())["video"]
    assert rep["frames"] == 4 and len(rep["multi_bucket"]["rel_mse_per_frame"]) == 4
    assert len(rep["alternating_exposure"]["rel_mse_per_frame"]) == 4
    assert "video.gif" in (tmp_path / "report.html").read_text()
    # a frame re-run alone from its own config gives the same reads as in the video
    alone = run_capture(video.frame_config(cfg, 2, spp=4), progress=False)
    assert np.array_equal(alone.reads_dn, res.video.frames[2].reads_dn)
