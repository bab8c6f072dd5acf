"""mbcapture converge: error falls with run time; equal-error interpolation; outputs."""

import csv

import numpy as np
import pytest

from mbcapture.studies.converge import Point, equal_error_speedups, fit_slope, planner_seconds_at, relative_error


def _mc_points(method, c0, c1, sigma, spps, passes):
    # error = sigma / sqrt(passes x spp), seconds = passes x (c0 + c1 spp)
    return [
        Point(method, s, passes, passes * s, passes * (c0 + c1 * s), sigma / np.sqrt(passes * s), 0.0) for s in spps
    ]


def test_slope_of_pure_monte_carlo_is_minus_half():
    pts = _mc_points("motion", 0.0, 0.01, 1.0, [1, 2, 4, 8, 16], 2)
    assert fit_slope(pts) == pytest.approx(-0.5, abs=1e-9)


def test_equal_error_speedup_interpolates_the_planner_ladder():
    motion = _mc_points("motion", 0.0, 0.01, 1.0, [1, 2, 4, 8, 16, 32, 64], 2)  # t = 0.02 spp, e = 1/sqrt(2 spp)
    naive = [Point("naive", 1, 64, 64, 10.0, 1 / np.sqrt(64), 0.0)]
    t, extrap = planner_seconds_at(motion + naive, 1 / np.sqrt(64))
    assert not extrap and t == pytest.approx(0.02 * 32)  # 2 x 32 samples reach the error of 64
    s = equal_error_speedups(motion + naive)
    assert s[0]["speedup"] == pytest.approx(10.0 / 0.64)
    # outside the ladder: extrapolated along the fitted -1/2 slope, and flagged
    t2, extrap2 = planner_seconds_at(motion + naive, 1 / np.sqrt(512))
    assert extrap2 and t2 == pytest.approx(0.02 * 256, rel=1e-6)


def test_relative_error_subtracts_the_reference_noise():
    rng = np.random.default_rng(0)
    truth = np.full((2, 40, 50, 3), 4.0)
    ref_sd, est_sd = 0.2, 0.4
    ref = truth + ref_sd * rng.standard_normal(truth.shape)
    est = truth + est_sd * rng.standard_normal(truth.shape)
    err, raw = relative_error(est, ref, np.full(truth.shape, ref_sd**2), [0, 1], trim=0.0)
    n = truth[0].size
    assert raw == pytest.approx(np.hypot(est_sd, ref_sd) / 4.0, rel=5 * np.sqrt(0.5 / n) + 0.01)
    assert err == pytest.approx(est_sd / 4.0, rel=0.05)
    # a few fireflies move the full RMS a lot and the trimmed one hardly at all
    est[0, :2, :2, 0] += 400.0
    full = relative_error(est, ref, np.full(truth.shape, ref_sd**2), [0, 1], trim=0.0)[0]
    trimmed = relative_error(est, ref, np.full(truth.shape, ref_sd**2), [0, 1])[0]
    assert full > 5 * err and trimmed == pytest.approx(err, rel=0.1)


@pytest.mark.render
@pytest.mark.slow  # 10 s; the documented `mbcapture converge` command runs at a tiny size in make test
def test_converge_on_a_tiny_capture(tmp_path):
    from mbcapture import load_config
    from mbcapture.studies.converge import run_converge, write_outputs

    cfg = load_config("configs/tiny_hdr.yaml", ["capture.periods=4"])
    res = run_converge(cfg, motion_ladder=(1, 4, 16), naive_ladder=(1,), ref_spp=512, ref_motion_div=2.0)
    motion = sorted((p for p in res["points"] if p["method"] == "motion"), key=lambda p: p["spp"])
    errs = [p["error"] for p in motion]
    # 16x the samples: the error falls by ~4x (MC; the 512-spp reference adds sqrt(1 + 16/512)),
    # at least 2.5x allowing for the spread of one ladder's errors
    assert errs[0] > errs[1] > errs[2] and errs[0] / errs[2] > 2.5
    naive = [p for p in res["points"] if p["method"] == "naive"][0]
    assert naive["passes"] == 4 * 4  # 4 periods x 4 slots
    write_outputs(res, tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "converge.csv")))
    assert len(rows) == 4 and {r["method"] for r in rows} == {"motion", "naive"}
    assert (tmp_path / "converge.png").stat().st_size > 10_000
