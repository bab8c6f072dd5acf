"""HDR merging: ramp_fit efficiency against the Cramer-Rao bound, comparisons, edge cases.

The bound for a known rate lambda is 1 / (t^T C^-1 t), C = lambda M + sigma_r^2 I, with
M = min(t_i, t_j) for cumulative reads and diag(t) for independent ones. With n samples the
sample variance has relative standard error sqrt(2 / (n - 1)); n = 60 000 makes it 0.58 %,
so the 5 % tolerance is more than 8 standard errors wide, and 5 % itself is the allowed
inefficiency of the two-pass weights.
"""

from __future__ import annotations

import numpy as np
import pytest

from mbcapture.errors import ConfigError
from mbcapture.reconstruct.hdr import (
    HDR_METHODS,
    merge_hdr,
    quantization_read_variance_e2,
)
from mbcapture.sensor import SensorConfig, simulate_reads

N_SIGMA = 5.0
T_S = 1e-3
CUM_T = T_S * np.array([1.0, 2.0, 4.0, 8.0])
CUMULATIVE_READS = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
CFG = SensorConfig(prnu=0.0, dsnu_e=0.0)
N_PIX = 20_000  # x 3 channels = 60 000 samples per level


def photon_efficient(rate_e_per_s: float, seed: int):
    """Buckets 1..4 (indices 0..3) gated 4T, 2T, T, T; cumulative reads T, 2T, 4T, 8T."""
    slots = T_S * np.array([4.0, 2.0, 1.0, 1.0])
    exp_e = np.broadcast_to((rate_e_per_s * slots)[:, None, None, None], (4, 1, N_PIX, 3)).copy()
    return simulate_reads(exp_e, CUMULATIVE_READS, CFG, np.random.default_rng(seed))


def crb(rate: float, t: np.ndarray, cumulative: bool) -> float:
    m = np.minimum.outer(t, t) if cumulative else np.diag(t)
    c = rate * m + quantization_read_variance_e2(CFG) * np.eye(t.size)
    return float(1.0 / (t @ np.linalg.solve(c, t)))


# Rates in electrons/s spanning the range: 1 e- per T up to where only J1, J2 are unsaturated
# (bucket full well 10 000 e-: bucket 1 saturates above 2.5e6 e-/s, bucket 2 above 5e6).
LEVELS = [(1e3, 4), (1e4, 4), (1e5, 4), (1e6, 4), (3e6, 3), (8e6, 2)]


@pytest.mark.parametrize("rate,n_usable", LEVELS)
def test_ramp_fit_unbiased_and_efficient(rate, n_usable):
    out = photon_efficient(rate, seed=int(np.log10(rate) * 10))
    res = {
        m: merge_hdr(out.reads_dn, CUM_T, CFG, method=m, cumulative=True, saturated=out.saturated) for m in HDR_METHODS
    }
    ramp = res["ramp_fit"]
    assert ramp.valid.all() and np.all(ramp.n_used == n_usable)
    bound = crb(rate, CUM_T[:n_usable], cumulative=True)
    x = ramp.rate_e_per_s.ravel()
    n = x.size
    assert abs(x.mean() - rate) < N_SIGMA * np.sqrt(bound / n)
    efficiency = x.var(ddof=1) / bound
    print(f"rate {rate:.0e} e-/s: ramp_fit var / CRB = {efficiency:.4f}")
    assert abs(efficiency - 1.0) < 0.05
    assert np.median(ramp.sigma_temporal_e_per_s) ** 2 / bound == pytest.approx(1.0, rel=0.05)

    mse = {m: float(np.mean((r.rate_e_per_s - rate) ** 2)) for m, r in res.items()}
    se_mse = {m: v * np.sqrt(2.0 / n) for m, v in mse.items()}
    print("  MSE / CRB:", {m: round(v / bound, 4) for m, v in mse.items()})
    assert mse["ramp_fit"] < mse["debevec"]
    assert mse["ramp_fit"] <= mse["inverse_variance"] + N_SIGMA * se_mse["inverse_variance"]


def test_independent_exposures_inverse_variance_reaches_bound():
    """Interleaved 8:4:2:1 read directly: independent exposures 8T, 4T, 2T, T."""
    rate = 2e5
    t = T_S * np.array([8.0, 4.0, 2.0, 1.0])
    exp_e = np.broadcast_to((rate * t)[:, None, None, None], (4, 1, N_PIX, 3)).copy()
    out = simulate_reads(exp_e, [(0,), (1,), (2,), (3,)], CFG, np.random.default_rng(40))
    bound = crb(rate, t, cumulative=False)
    for method in ("inverse_variance", "ramp_fit"):
        res = merge_hdr(out.reads_dn, t, CFG, method=method, cumulative=False, saturated=out.saturated)
        x = res.rate_e_per_s.ravel()
        assert abs(x.mean() - rate) < N_SIGMA * np.sqrt(bound / x.size)
        assert x.var(ddof=1) / bound == pytest.approx(1.0, abs=0.05)


def test_all_saturated_gives_invalid_finite_lower_bound():
    rate = 1e9  # every bucket far above its full well
    out = photon_efficient(rate, seed=50)
    assert out.saturated.all()
    for method in HDR_METHODS:
        res = merge_hdr(out.reads_dn, CUM_T, CFG, method=method, cumulative=True, saturated=out.saturated)
        assert not res.valid.any() and np.all(res.n_used == 0)
        assert np.all(np.isfinite(res.rate_e_per_s))
        assert np.all(res.rate_e_per_s > 0) and np.all(res.rate_e_per_s <= rate)
        assert np.all(np.isinf(res.sigma_temporal_e_per_s))


@pytest.mark.parametrize("method", sorted(HDR_METHODS))
def test_zero_light_and_negative_reads_stay_finite(method):
    out = photon_efficient(0.0, seed=60)
    res = merge_hdr(out.reads_dn, CUM_T, CFG, method=method, cumulative=True, saturated=out.saturated)
    assert res.valid.all()
    assert np.all(np.isfinite(res.rate_e_per_s)) and np.all(np.isfinite(res.sigma_temporal_e_per_s))
    # Reads far below the black level (negative electrons) are finite too.
    dn = np.zeros((4, 2, 2, 3))
    res = merge_hdr(dn, CUM_T, CFG, method=method, cumulative=True)
    assert np.all(np.isfinite(res.rate_e_per_s)) and np.all(res.rate_e_per_s < 0)
    assert np.all(np.isfinite(res.sigma_temporal_e_per_s))


def test_cumulative_reads_used_only_before_first_saturated():
    dn = np.full((4, 1, 1, 3), 1000.0)
    sat = np.zeros(dn.shape, dtype=bool)
    sat[1] = True  # read 2 flagged: reads 3 and 4 contain its photons and are dropped too
    res = merge_hdr(dn, CUM_T, CFG, method="ramp_fit", cumulative=True, saturated=sat)
    assert np.all(res.n_used == 1)
    np.testing.assert_allclose(res.rate_e_per_s, (1000.0 - CFG.black_level_dn) / CFG.gain_dn_per_e / CUM_T[0])
    res = merge_hdr(dn, CUM_T, CFG, method="inverse_variance", cumulative=False, saturated=sat)
    assert np.all(res.n_used == 3)


def test_unknown_method_lists_valid_ones():
    with pytest.raises(ConfigError, match="debevec.*inverse_variance.*ramp_fit"):
        merge_hdr(np.zeros((4, 1, 1, 3)), CUM_T, CFG, method="robertson", cumulative=True)


def test_cumulative_exposures_must_increase():
    with pytest.raises(ValueError, match="exposures_s"):
        merge_hdr(np.zeros((4, 1, 1, 3)), CUM_T[::-1], CFG, method="ramp_fit", cumulative=True)


@pytest.mark.parametrize("cumulative", [True, False])
def test_all_saturated_lower_bound_is_the_largest_read_rate(cumulative):
    """Documented value where every read saturated: max_i x_i / t_i over the reads (each clipped read
    under-reports its rate), clamped at 0. Hand-made DN put the largest rate in the second read
    (not the first, not the last, not the longest); a pixel below the black level gives 0."""
    t = CUM_T
    x_e = np.array([[5000.0, -40.0], [12000.0, -30.0], [15000.0, -20.0], [20000.0, -10.0]])  # (R, P) electrons
    dn = (x_e * CFG.gain_dn_per_e + CFG.black_level_dn).reshape(4, 1, 2, 1)
    rates = x_e / t[:, None]  # 5e6, 6e6, 3.75e6, 2.5e6 e-/s in pixel 0
    assert int(np.argmax(rates[:, 0])) == 1
    for method in HDR_METHODS:
        res = merge_hdr(dn, t, CFG, method=method, cumulative=cumulative, saturated=np.ones(dn.shape, bool))
        np.testing.assert_allclose(res.rate_e_per_s.ravel(), [12000.0 / t[1], 0.0], rtol=1e-12, atol=0)
        assert not res.valid.any() and np.all(np.isinf(res.sigma_temporal_e_per_s)) and np.all(res.n_used == 0)
    # a pixel with one usable read is merged from it, not bounded
    sat = np.ones(dn.shape, bool)
    sat[0] = False
    res = merge_hdr(dn, t, CFG, method="ramp_fit", cumulative=cumulative, saturated=sat)
    assert res.valid.all() and res.n_used.ravel().tolist() == [1, 1]
    np.testing.assert_allclose(res.rate_e_per_s.ravel(), x_e[0] / t[0], rtol=1e-12)


def test_debevec_and_inverse_variance_by_hand():
    """Both merges on hand-made independent reads (t = 1, 2, 4, 8 ms, the last one saturated and so
    left out), against their documented formulas written out here. Pixel 0: three well-exposed
    reads. Pixel 1: a read exactly at the black level (hat weight 0, raised to the 1e-6 floor) next
    to bright ones, where the floor and the hat's scale (1 at mid-range) matter to 1e-6."""
    t = CUM_T
    # pixel 2 sits at the black level: its pooled first-pass rate is negative and is used as 0
    dn = np.array(
        [[1256.0, 256.0, 250.0], [2100.0, 9000.0, 255.0], [4400.0, 12000.0, 258.0], [16383.0, 16383.0, 16383.0]]
    )
    sat = np.zeros(dn.shape, bool)
    sat[3] = True
    x = (dn - CFG.black_level_dn) / CFG.gain_dn_per_e
    use = ~sat
    r2 = CFG.read_noise_e**2 + 1.0 / (12.0 * CFG.gain_dn_per_e**2)
    rate0 = np.maximum(np.where(use, x, 0).sum(0) / np.where(use, t[:, None], 0).sum(0), 0.0)  # pooled first pass
    var = (rate0[None, :] * t[:, None] + r2) / t[:, None] ** 2  # variance of x_i / t_i
    # inverse variance: weights 1 / var_i, sigma = 1 / sqrt(sum of weights)
    w = np.where(use, 1.0 / var, 0.0)
    want_iv = (w * x / t[:, None]).sum(0) / w.sum(0), 1.0 / np.sqrt(w.sum(0))
    # Debevec with a linear response: hat weight min(z - z_min, z_max - z) / half the range, floor 1e-6
    z_min, z_max = CFG.black_level_dn, float(CFG.adc_max_dn)
    hat = np.minimum(dn - z_min, z_max - dn) / (0.5 * (z_max - z_min))
    h = np.where(use, np.maximum(hat, 1e-6), 0.0)
    want_db = (h * x / t[:, None]).sum(0) / h.sum(0), np.sqrt((h**2 * var).sum(0)) / h.sum(0)
    assert h[0, 1] == 1e-6 and 0.5 < h[1, 1] < 1.0  # the floor is in play in pixel 1
    for method, (rate, sigma) in (("inverse_variance", want_iv), ("debevec", want_db)):
        res = merge_hdr(dn[:, None, :, None], t, CFG, method=method, cumulative=False, saturated=sat[:, None, :, None])
        np.testing.assert_allclose(res.rate_e_per_s.ravel(), rate, rtol=1e-12, err_msg=method)
        np.testing.assert_allclose(res.sigma_temporal_e_per_s.ravel(), sigma, rtol=1e-12, err_msg=method)
        assert res.n_used.ravel().tolist() == [3, 3, 3]


def test_auto_method_validation_and_integer_flags():
    """``auto`` is ramp_fit for cumulative reads and inverse_variance for independent ones; bad
    exposures and flags are refused with a message naming the argument; 1-D reads (one pixel) and
    saturation flags given as 0/1 integers work."""
    rng = np.random.default_rng(3)
    dn = rng.uniform(300.0, 3000.0, (4, 2, 3, 3)).cumsum(axis=0)
    for cumulative, method in ((True, "ramp_fit"), (False, "inverse_variance")):
        a = merge_hdr(dn, CUM_T, CFG, method="auto", cumulative=cumulative)
        b = merge_hdr(dn, CUM_T, CFG, method=method, cumulative=cumulative)
        np.testing.assert_array_equal(a.rate_e_per_s, b.rate_e_per_s)
        np.testing.assert_array_equal(a.sigma_temporal_e_per_s, b.sigma_temporal_e_per_s)
    with pytest.raises(
        ConfigError,
        match=r"^hdr\.method: unknown method 'x'; valid methods: auto, debevec, inverse_variance, ramp_fit$",
    ):
        merge_hdr(dn, CUM_T, CFG, method="x", cumulative=True)
    with pytest.raises(ValueError, match=r"^exposures_s: expected one exposure per read \(\(4,\)\), got shape \(3,\)$"):
        merge_hdr(dn, CUM_T[:3], CFG, method="ramp_fit", cumulative=True)
    for bad in (np.array([1e-3, 2e-3, np.inf, 8e-3]), np.array([0.0, 2e-3, 4e-3, 8e-3])):
        with pytest.raises(ValueError, match=r"^exposures_s: must be finite and > 0, got"):
            merge_hdr(dn, bad, CFG, method="ramp_fit", cumulative=False)
    with pytest.raises(ValueError, match=r"^exposures_s: cumulative reads need strictly increasing exposures"):
        merge_hdr(dn, np.array([1e-3, 2e-3, 2e-3, 8e-3]), CFG, method="ramp_fit", cumulative=True)
    with pytest.raises(ValueError, match=r"^saturated: expected shape \(4, 2, 3, 3\), got \(4, 2, 3\)$"):
        merge_hdr(dn, CUM_T, CFG, method="ramp_fit", cumulative=True, saturated=np.zeros((4, 2, 3), bool))
    one = merge_hdr(dn[:, 0, 0, 0], CUM_T, CFG, method="ramp_fit", cumulative=True)  # reads of one pixel, shape (R,)
    assert (
        one.rate_e_per_s.shape == ()
        and one.rate_e_per_s == merge_hdr(dn, CUM_T, CFG, method="ramp_fit", cumulative=True).rate_e_per_s[0, 0, 0]
    )
    sat = np.zeros(dn.shape, bool)
    sat[2:, 0] = True
    flags = merge_hdr(dn, CUM_T, CFG, method="ramp_fit", cumulative=True, saturated=sat)
    ints = merge_hdr(dn, CUM_T, CFG, method="ramp_fit", cumulative=True, saturated=sat.astype(np.int64))
    np.testing.assert_array_equal(flags.rate_e_per_s, ints.rate_e_per_s)
    assert flags.n_used[0].max() == 2 and flags.n_used[1].min() == 4


def test_ramp_fit_is_the_documented_three_pass_gls():
    """ramp_fit written out with explicit covariance matrices: pass 0 ordinary least squares through
    the origin, then twice GLS with C(lambda) = max(lambda, 0) M + sigma_r^2 I, M = min(t_i, t_j);
    sigma = 1 / sqrt(t^T C(lambda_2)^-1 t). Pixels: bright, dim, and one below the black level
    (a negative lambda: its covariance uses lambda = 0); cumulative and independent reads."""
    r2 = CFG.read_noise_e**2 + 1.0 / (12.0 * CFG.gain_dn_per_e**2)
    x = np.array([[900.0, 30.0, -8.0], [1800.0, 55.0, -12.0], [3700.0, 120.0, -3.0], [7300.0, 230.0, -15.0]])
    dn = x * CFG.gain_dn_per_e + CFG.black_level_dn
    for cumulative in (True, False):
        m = np.minimum.outer(CUM_T, CUM_T) if cumulative else np.diag(CUM_T)
        want_rate, want_sigma = [], []
        for p in range(x.shape[1]):
            lam = CUM_T @ x[:, p] / (CUM_T @ CUM_T)
            for _ in range(2):
                c = max(lam, 0.0) * m + r2 * np.eye(4)
                lam = CUM_T @ np.linalg.solve(c, x[:, p]) / (CUM_T @ np.linalg.solve(c, CUM_T))
            c = max(lam, 0.0) * m + r2 * np.eye(4)
            want_rate.append(lam)
            want_sigma.append(1.0 / np.sqrt(CUM_T @ np.linalg.solve(c, CUM_T)))
        res = merge_hdr(dn[:, :, None], CUM_T, CFG, method="ramp_fit", cumulative=cumulative)
        np.testing.assert_allclose(res.rate_e_per_s.ravel(), want_rate, rtol=1e-10)
        np.testing.assert_allclose(res.sigma_temporal_e_per_s.ravel(), want_sigma, rtol=1e-10)
        assert want_rate[2] < 0


def test_motion_check_by_hand():
    """apps.hdr.motion_check: RMS of each normalised read against the truth and the largest pairwise
    RMS between reads, relative to the mean truth in the moving region (or absolute where that mean
    is 0); a static scene says so."""
    from mbcapture.apps.hdr import motion_check

    truth = np.full((2, 2, 1), 2.0)
    reads = np.stack([truth, truth + 1.0, truth - 1.0])  # off by 0, +1, -1 everywhere
    mask = np.array([[True, False], [True, True]])
    got = motion_check(reads, ["J1", "J2", "J3"], truth, mask)
    assert got == {
        "moving_pixels": 3,
        "rel_rms_vs_truth": {"J1": 0.0, "J2": 0.5, "J3": 0.5},
        "max_pairwise_rel_rms": 1.0,
    }
    assert motion_check(reads, ["J1", "J2", "J3"], 0 * truth, mask)["max_pairwise_rel_rms"] == 2.0  # truth 0: absolute
    assert motion_check(reads, ["J1", "J2", "J3"], truth, ~np.ones((2, 2), bool)) == {
        "moving_pixels": 0,
        "note": "static scene: nothing moves",
    }


@pytest.mark.parametrize("method, cumulative", [("ramp_fit", True), ("inverse_variance", False), ("debevec", False)])
def test_merging_in_chunks_gives_the_same_values(monkeypatch, method, cumulative):
    """merge_hdr goes through the samples MERGE_CHUNK at a time: every method is per sample, so
    any chunking gives the values of one pass (bit for bit), saturated and all-saturated samples too."""
    from mbcapture.reconstruct import hdr as module
    from mbcapture.sensor import SensorConfig

    cfg = SensorConfig()
    rng = np.random.default_rng(3)
    t = np.array([1e-3, 2e-3, 4e-3, 8e-3])
    dn = np.round(rng.uniform(cfg.black_level_dn, cfg.adc_max_dn, size=(4, 37, 23, 3)))
    sat = rng.random(dn.shape) < 0.2
    sat[:, 0, 0] = True  # every read saturated: the lower bound
    whole = module.merge_hdr(dn, t, cfg, method=method, cumulative=cumulative, saturated=sat)
    monkeypatch.setattr(module, "MERGE_CHUNK", 100)
    chunked = module.merge_hdr(dn, t, cfg, method=method, cumulative=cumulative, saturated=sat)
    for name in ("rate_e_per_s", "sigma_temporal_e_per_s", "valid", "n_used"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)
    assert not whole.valid[0, 0].any() and whole.valid.any()


@pytest.mark.parametrize("n_reads, cumulative", [(3, True), (20, False), (40, True)])
def test_ramp_fit_groups_of_usable_reads_whatever_their_number(n_reads, cumulative):
    """_ramp_fit fits each group of samples with the same usable reads on its own: merging the film
    gives each sample the value it gets merged alone (then one group, fitted without a gather), with
    up to 40 reads (their codes too many for a table of 2^R, so found by np.unique)."""
    from mbcapture.reconstruct import hdr as module

    cfg = SensorConfig()
    rng = np.random.default_rng(n_reads)
    t = 1e-3 * (np.arange(1, n_reads + 1) if cumulative else rng.uniform(0.5, 2.0, n_reads))
    dn = np.round(rng.uniform(cfg.black_level_dn, cfg.adc_max_dn, size=(n_reads, 9, 5)))
    sat = rng.random(dn.shape) < (0.02 if cumulative else 0.3)
    whole = module.merge_hdr(dn, t, cfg, method="ramp_fit", cumulative=cumulative, saturated=sat)
    assert len({tuple(col) for col in (~sat).reshape(n_reads, -1).T}) > 3  # several groups
    for y, x in np.ndindex(9, 5):
        alone = module.merge_hdr(
            dn[:, y : y + 1, x : x + 1],
            t,
            cfg,
            method="ramp_fit",
            cumulative=cumulative,
            saturated=sat[:, y : y + 1, x : x + 1],
        )
        assert alone.rate_e_per_s[0, 0] == whole.rate_e_per_s[y, x]
        assert alone.sigma_temporal_e_per_s[0, 0] == whole.sigma_temporal_e_per_s[y, x]


@pytest.mark.parametrize("rate", [2e4, 1e5, 1e6])
@pytest.mark.parametrize("cumulative", [True, False], ids=["ramp_fit-cumulative", "inverse_variance-independent"])
def test_sigma_covers_the_fixed_pattern_on_a_flat_field(rate, cumulative):
    """With PRNU and DSNU (pixel and column parts) on, a flat field's merged rates lie beyond 2 sigma
    in 4.55 % of pixels (a normal's two tails), and beyond 2 temporal sigmas in far more. Each merge
    on the reads its sigma is derived for (inverse_variance treats reads as independent); from 160
    electrons in the longest read up, where the shot noise is close to normal.

    One channel per pixel is counted (the pattern is drawn per pixel): n = 20 000 gives the
    fraction a binomial standard error of 0.15 %; the tolerance is 5 of them."""
    cfg = SensorConfig(prnu=0.01, prnu_col=0.005, dsnu_e=3.0, dsnu_col_e=2.0)
    slots = T_S * (np.array([4.0, 2.0, 1.0, 1.0]) if cumulative else np.array([1.0, 2.0, 4.0, 8.0]))
    reads = CUMULATIVE_READS if cumulative else [(0,), (1,), (2,), (3,)]
    exp_e = np.broadcast_to((rate * slots)[:, None, None, None], (4, 1, N_PIX, 3)).copy()
    out = simulate_reads(exp_e, reads, cfg, np.random.default_rng(int(rate)))
    method = "ramp_fit" if cumulative else "inverse_variance"
    res = merge_hdr(out.reads_dn, CUM_T, cfg, method=method, cumulative=cumulative, saturated=out.saturated)
    assert res.valid.all()
    err = (res.rate_e_per_s - rate)[..., 1].ravel()
    beyond = float(np.mean(np.abs(err) > 2 * res.sigma_e_per_s[..., 1].ravel()))
    p = 0.0455
    se = np.sqrt(p * (1 - p) / err.size)
    print(f"{method} at {rate:.0e} e-/s: {100 * beyond:.2f} % beyond 2 sigma")
    assert abs(beyond - p) < 5 * se
    temporal = float(np.mean(np.abs(err) > 2 * res.sigma_temporal_e_per_s[..., 1].ravel()))
    assert temporal >= beyond
    if rate >= 1e5:  # where the pattern is a large part of the error, the temporal sigma alone is too small
        assert temporal > p + 10 * se
    np.testing.assert_allclose(res.sigma_e_per_s**2, res.sigma_temporal_e_per_s**2 + res.sigma_fixed_e_per_s**2)
