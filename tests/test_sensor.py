"""Sensor physics: conversion factor, shot noise, full wells, figure 11, covariance, PTC.

Statistical tolerances come from the sample size: the standard error of a sample mean is
sqrt(var / n); of a sample variance sqrt(2 / (n - 1)) * var (Gaussian) plus the excess
kurtosis term var^2 * kappa / n (Poisson: kappa = 1 / lambda); of a sample covariance
sqrt((var_i var_j + cov_ij^2) / n). Assertions use 5 standard errors.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from mbcapture.sensor import (
    SensorConfig,
    dn_to_electrons,
    electrons_per_radiance_second,
    expected_electrons,
    fixed_pattern,
    simulate_reads,
)
from mbcapture.sensor.sampling import NoiseStreams

N_SIGMA = 5.0

# The paper's photon-efficient HDR protocol: buckets 4:2:1:1 of slot time, i.e. with the
# 0-based bucket index b = bucket number - 1, expected signal 4S, 2S, S, S in b = 0, 1, 2, 3,
# and cumulative reads J1 = B4, J2 = B4 + B3, J3 = B4 + B3 + B2, J4 = all.
CUMULATIVE_READS = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
SEPARATE_READS = [(3,), (2,), (1,), (0,)]


def ideal(**overrides) -> SensorConfig:
    """Default sensor without fixed-pattern noise (statistics over pixels = over captures)."""
    return SensorConfig(**{"prnu": 0.0, "dsnu_e": 0.0, **overrides})


def var_se(var: float, n: int, excess_kurtosis: float = 0.0) -> float:
    return var * np.sqrt(2.0 / (n - 1) + excess_kurtosis / n)


def flat(k_values: list[float], n_pix: int, channels: int = 1) -> np.ndarray:
    """(K, 1, n_pix, channels) flat expected electrons."""
    return np.broadcast_to(
        np.asarray(k_values, dtype=np.float64)[:, None, None, None], (len(k_values), 1, n_pix, channels)
    ).copy()


# --------------------------------------------------------------------------- conversion


def test_conversion_factor_matches_hand_computation():
    cfg = SensorConfig()
    # Green channel by hand: E/L = pi * 0.9 / (4 * 2.8^2) = 2.827433 / 31.36 = 0.0901605 sr;
    # A * ff = (5.6e-6)^2 * 0.5 = 1.568e-11 m^2; QE 0.5;
    # lambda / (h c) = 540e-9 / (6.62607015e-34 * 299792458) = 540e-9 / 1.98645e-25 = 2.718423e18 J^-1.
    # K_G = 0.0901605 * 1.568e-11 * 0.5 * 2.718423e18 = 1.92154e6 e- per (W m^-2 sr^-1 s).
    k = electrons_per_radiance_second(cfg)
    assert k.shape == (3,)
    assert k[1] == pytest.approx(1.92154e6, rel=1e-5)
    # Channels scale with QE * lambda.
    ratio = np.array([0.40 * 600, 0.50 * 540, 0.45 * 460]) / (0.50 * 540)
    np.testing.assert_allclose(k / k[1], ratio, rtol=1e-12)


def test_expected_electrons_needs_a_channel_axis_of_three():
    cfg = SensorConfig()
    k = electrons_per_radiance_second(cfg)
    np.testing.assert_allclose(
        expected_electrons([1.0, 2.0, 3.0], cfg), [k[0], 2 * k[1], 3 * k[2]], rtol=1e-15
    )  # 1-D is fine
    for bad in (np.float64(1.0), np.zeros(2), np.zeros((4, 2))):
        with pytest.raises(ValueError, match=r"radiant exposure must end in a channel axis of 3, got shape"):
            expected_electrons(bad, cfg)


def test_mid_grey_is_well_exposed_at_8ms():
    cfg = SensorConfig()
    e = expected_electrons(np.full((1, 1, 1, 3), 0.3 * 8e-3), cfg)[0, 0, 0]
    assert np.all(e > 0.3 * cfg.full_well_e) and np.all(e < 0.8 * cfg.full_well_e)


def test_config_rejects_nonsense_naming_the_key():
    with pytest.raises(ValidationError, match="full_well_e"):
        SensorConfig(full_well_e=0)
    with pytest.raises(ValidationError, match=r"quantum_efficiency: expected 3 values \(R, G, B\), got 2"):
        SensorConfig(quantum_efficiency=[0.5, 0.5])
    with pytest.raises(ValidationError, match="quantum_efficiency"):
        SensorConfig(quantum_efficiency=[0.5, 1.5, 0.5])
    with pytest.raises(ValidationError, match="black_level_dn"):
        SensorConfig(adc_bits=8, black_level_dn=300)
    with pytest.raises(ValidationError, match="no_such_key"):
        SensorConfig(no_such_key=1)


# --------------------------------------------------------------------------- shot noise, wells


def test_single_bucket_poisson_mean_and_variance():
    lam, n = 50.0, 200_000
    out = simulate_reads(flat([lam], n), [(0,)], ideal(), np.random.default_rng(1))
    e = out.electrons[0].ravel()
    assert np.all(e == np.rint(e))
    assert abs(e.mean() - lam) < N_SIGMA * np.sqrt(lam / n)
    assert abs(e.var(ddof=1) - lam) < N_SIGMA * var_se(lam, n, 1.0 / lam)
    assert not out.saturated.any()


def test_bucket_full_well_clips_and_flags():
    cfg = ideal()
    fw = cfg.full_well_e
    n = 20_000
    exp_e = flat([2.0 * fw, fw, 0.5 * fw], n)
    out = simulate_reads(exp_e, [(0,), (1,), (2,), (2, 0)], cfg, np.random.default_rng(2))
    assert np.all(out.electrons[0] == fw) and out.saturated[0].all()
    # A bucket expecting exactly its full well hits it about half of the time; flags follow the charge.
    np.testing.assert_array_equal(out.saturated[1], out.electrons[1] >= fw)
    assert 0.4 < out.saturated[1].mean() < 0.6
    assert not out.saturated[2].any()
    assert out.saturated[3].all(), "a read summing a clipped bucket is flagged"
    assert out.electrons.max() <= fw


def test_floating_diffusion_and_adc_clipping_flagged():
    cfg = ideal(fd_full_well_e=15_000.0)
    out = simulate_reads(flat([6000.0, 6000.0, 6000.0], 1000), [(0,), (0, 1), (0, 1, 2)], cfg, np.random.default_rng(3))
    assert not out.saturated[0].any() and not out.saturated[1].any()
    assert out.saturated[2].all()
    assert np.allclose(
        dn_to_electrons(out.reads_dn[2], cfg), 15_000.0, atol=6 * cfg.read_noise_e + 2 / cfg.gain_dn_per_e
    )
    cfg_adc = ideal(gain_dn_per_e=2.0)  # 9000 e- * 2 DN/e + 256 > 16383
    out = simulate_reads(flat([9000.0], 1000), [(0,)], cfg_adc, np.random.default_rng(4))
    assert out.saturated.all() and np.all(out.reads_dn == cfg_adc.adc_max_dn)


def test_fixed_pattern_is_per_sensor_and_identical_across_captures():
    cfg = SensorConfig(prnu=0.05, dsnu_e=2.0, fpn_seed=7)
    a = fixed_pattern((4, 5, 3), cfg)
    b = fixed_pattern((4, 5, 3), cfg)
    np.testing.assert_array_equal(a.prnu_gain, b.prnu_gain)
    np.testing.assert_array_equal(a.dsnu_offset_e, b.dsnu_offset_e)
    other = fixed_pattern((4, 5, 3), cfg.model_copy(update={"fpn_seed": 8}))
    assert not np.array_equal(a.prnu_gain, other.prnu_gain)


def test_dark_current_transfer_inefficiency_and_parasitic_light_means():
    n = 100_000
    cfg = ideal(dark_current_e_per_s=1000.0, transfer_inefficiency=0.1, parasitic_light=0.01, read_noise_e=0.0)
    exp_e = flat([1000.0, 0.0], n)
    out = simulate_reads(exp_e, [(0,), (1,)], cfg, np.random.default_rng(5), storage_s=[0.05, 0.1])
    # Bucket means: photo + parasitic share of the other bucket + dark.
    mean_b0 = 1000.0 + 0.0 + 50.0
    mean_b1 = 0.0 + 0.01 * 1000.0 + 100.0
    e = out.electrons.reshape(2, -1).mean(axis=1)
    assert abs(e[0] - mean_b0) < N_SIGMA * np.sqrt(mean_b0 / n)
    assert abs(e[1] - mean_b1) < N_SIGMA * np.sqrt(mean_b1 / n)
    # Reads see 90 % of the charge (binomial thinning keeps the Poisson law: var = mean).
    read_e = dn_to_electrons(out.reads_dn, cfg).reshape(2, -1)
    q = 1.0 / (12 * cfg.gain_dn_per_e**2)
    for r, m in enumerate([0.9 * mean_b0, 0.9 * mean_b1]):
        assert abs(read_e[r].mean() - m) < N_SIGMA * np.sqrt((m + q) / n)
    # Separate frames of a sequential capture do not couple.
    seq = simulate_reads(exp_e, [(0,), (1,)], cfg, np.random.default_rng(6), shared_photodiode=False)
    assert abs(seq.electrons[1].mean()) < N_SIGMA * np.sqrt(1.0 / n)


# --------------------------------------------------------------------------- figure 11


@pytest.mark.parametrize("signal_s", [20.0, 200.0])
def test_figure_11_in_pixel_addition_beats_read_then_add(signal_s):
    """Buckets 4, 3, 2, 1 hold S, S, 2S, 4S. J_k has signal s_k = S, 2S, 4S, 8S.

    In-pixel (figure 11b): Var(J_k) = s_k + R^2.  Read then add (11a): Var = s_k + k R^2.
    (Plus quantization 1/(12 g^2) per read, in electrons^2.)
    """
    cfg = ideal(read_noise_e=8.0)
    n = 100_000
    exp_e = flat([4 * signal_s, 2 * signal_s, signal_s, signal_s], n)
    q = 1.0 / (12 * cfg.gain_dn_per_e**2)
    r2 = cfg.read_noise_e**2
    s_k = signal_s * np.array([1.0, 2.0, 4.0, 8.0])

    inpix = simulate_reads(exp_e, CUMULATIVE_READS, cfg, np.random.default_rng(10))
    j_in = dn_to_electrons(inpix.reads_dn, cfg).reshape(4, -1)
    sep = simulate_reads(exp_e, SEPARATE_READS, cfg, np.random.default_rng(11))
    j_add = np.cumsum(dn_to_electrons(sep.reads_dn, cfg).reshape(4, -1), axis=0)

    k = np.arange(1, 5)
    var_in_model = s_k + r2 + q
    var_add_model = s_k + k * (r2 + q)
    for i in range(4):
        assert abs(j_in[i].mean() - s_k[i]) < N_SIGMA * np.sqrt(var_in_model[i] / n)
        assert abs(j_in[i].var(ddof=1) - var_in_model[i]) < N_SIGMA * var_se(
            var_in_model[i], n, s_k[i] / var_in_model[i] ** 2
        )
        assert abs(j_add[i].var(ddof=1) - var_add_model[i]) < N_SIGMA * var_se(
            var_add_model[i], n, s_k[i] / var_add_model[i] ** 2
        )
    snr_in = j_in.mean(axis=1) / j_in.std(axis=1)
    snr_add = j_add.mean(axis=1) / j_add.std(axis=1)
    assert np.all(snr_in[1:] > snr_add[1:])


def test_cumulative_reads_covariance_is_lambda_min_t():
    cfg = ideal(read_noise_e=5.0)
    n = 200_000
    s = 100.0  # electrons per unit time T in each slot of T
    exp_e = flat([4 * s, 2 * s, s, s], n)
    out = simulate_reads(exp_e, CUMULATIVE_READS, cfg, np.random.default_rng(12))
    j = dn_to_electrons(out.reads_dn, cfg).reshape(4, -1)
    t = np.array([1.0, 2.0, 4.0, 8.0])
    model = s * np.minimum.outer(t, t) + (cfg.read_noise_e**2 + 1 / (12 * cfg.gain_dn_per_e**2)) * np.eye(4)
    sample = np.cov(j)
    se = np.sqrt((np.outer(np.diag(model), np.diag(model)) + model**2) / n)
    assert np.all(np.abs(sample - model) < N_SIGMA * se), (sample, model)


# --------------------------------------------------------------------------- photon transfer curve


def test_photon_transfer_curve_recovers_gain_read_noise_and_full_well():
    """EMVA 1288 style: two captures of each flat level with the same sensor (same fixed
    pattern), temporal variance from their difference: var = Var(A - B) / 2 over pixels.
    Model: var_dn = g * (mu_dn - mu_dark) + (g R)^2 + 1/12.
    """
    cfg = SensorConfig(dark_current_e_per_s=0.0)  # default PRNU and DSNU on: the difference removes them
    n = 20_000
    levels_e = np.concatenate([[0.0], np.geomspace(20.0, 7000.0, 24), np.linspace(9000.0, 14000.0, 11)])
    exp_e = np.broadcast_to(levels_e[None, :, None, None], (1, levels_e.size, n, 1)).copy()
    a = simulate_reads(exp_e, [(0,)], cfg, np.random.default_rng(20)).reads_dn[0, :, :, 0]
    b = simulate_reads(exp_e, [(0,)], cfg, np.random.default_rng(21)).reads_dn[0, :, :, 0]
    mu = 0.5 * (a.mean(axis=1) + b.mean(axis=1)) - 0.5 * (a[0].mean() + b[0].mean())
    var = (a - b).var(axis=1, ddof=1) / 2.0

    # Linear range: below 70 % of the full well. Weighted least squares, weights 1 / SE(var)^2.
    lin = levels_e < 0.7 * cfg.full_well_e
    design = np.stack([mu[lin], np.ones(lin.sum())], axis=1)
    g_true = cfg.gain_dn_per_e
    var_model = g_true * mu[lin] + (g_true * cfg.read_noise_e) ** 2 + 1 / 12
    w = 1.0 / var_se(var_model, n) ** 2
    cov = np.linalg.inv(design.T @ (design * w[:, None]))
    slope, intercept = cov @ (design.T @ (w * var[lin]))
    se_slope, se_intercept = np.sqrt(np.diag(cov))
    print(
        f"PTC: gain {slope:.5f} DN/e (true {g_true}, SE {se_slope:.5f}); "
        f"intercept {intercept:.4f} DN^2 (SE {se_intercept:.4f})"
    )
    assert abs(slope - g_true) < N_SIGMA * se_slope
    read_noise_est = np.sqrt(max(intercept - 1 / 12, 0.0)) / slope
    # Propagated SE of R from the intercept: dR/dI = 1 / (2 g^2 R).
    se_r = se_intercept / (2 * g_true**2 * cfg.read_noise_e)
    print(f"PTC: read noise {read_noise_est:.4f} e- (true {cfg.read_noise_e}, SE {se_r:.4f})")
    assert abs(read_noise_est - cfg.read_noise_e) < N_SIGMA * se_r
    # Full well: EMVA saturation point = mean signal at the variance peak; above it the
    # variance collapses to the read noise and the mean plateaus at the full well. With
    # 1 % PRNU the pixels reach their well over a spread of a few percent of the light, so
    # the variance peaks some 5 % below the full well (at 9485 e- with these seeds).
    peak = int(np.argmax(var))
    sat_e = mu[peak] / slope
    plateau_e = mu[-1] / slope
    print(
        f"PTC: saturation (variance peak) {sat_e:.0f} e-, plateau {plateau_e:.0f} e- (full well {cfg.full_well_e:.0f})"
    )
    assert 0.9 * cfg.full_well_e < sat_e <= cfg.full_well_e
    assert plateau_e == pytest.approx(cfg.full_well_e, rel=0.01)
    assert var[-1] < 0.01 * var.max()


# --------------------------------------------------------------------------- each effect on its own


def _timeline(protocol: str, sequential: bool, periods: int = 4, unit_s: float = 1e-3):
    from mbcapture.timing import protocols
    from mbcapture.config import config_from_dict

    return protocols.build(
        config_from_dict(
            {
                "scene": {"name": "flatfield"},
                "capture": {
                    "protocol": protocol,
                    "unit_exposure_s": unit_s,
                    "periods": periods,
                    "sequential": sequential,
                },
            }
        )
    )


# storage time of each bucket, by hand, in units of T (N = 4 periods): from the bucket's first
# slot to its read. Interleaved 8:4:2:1 (bucket 1 first in each period, the capture spans 15T):
# bucket k starts after the earlier slots of the first period, 8T/N, (8+4)T/N, (8+4+2)T/N.
# Photon-efficient 4:2:1:1 over 8T: 4T/N, 6T/N, 7T/N. Sequential: each frame (T, 2T, 4T, 8T for
# the reads J1..J4, i.e. frames B1..B4) is read at the end of its own exposure.
STORAGE_T = {
    ("interleaved_hdr", False): [15.0, 15.0 - 8 / 4, 15.0 - 12 / 4, 15.0 - 14 / 4],
    ("photon_efficient_hdr", False): [8.0, 8.0 - 4 / 4, 8.0 - 6 / 4, 8.0 - 7 / 4],
    ("interleaved_hdr", True): [1.0, 2.0, 4.0, 8.0],
    ("photon_efficient_hdr", True): [1.0, 2.0, 4.0, 8.0],
}


@pytest.mark.parametrize("protocol,sequential", list(STORAGE_T))
def test_dark_current_accumulates_over_the_storage_time_of_every_bucket(protocol, sequential):
    """No light, a large dark current: each bucket's mean charge is dark current x the time from
    its first gated slot to its read (the timeline's storage time, what a capture passes to the
    sensor), not x its exposure. Interleaved buckets wait for the end of the capture; a sequential
    frame is read at the end of its own exposure, the readout gaps do not count."""
    tl = _timeline(protocol, sequential)
    unit_s = 1e-3
    want_s = np.array(STORAGE_T[(protocol, sequential)]) * unit_s
    np.testing.assert_allclose(tl.storage_s(), want_s, rtol=1e-12)
    exposure_s = np.array([tl.exposure_ticks(k) for k in range(tl.n_buckets)]) * float(tl.tick_s)
    dark = 2e5  # e-/s: 3000 e- over 15 ms, below the 10 000 e- full well
    cfg = ideal(dark_current_e_per_s=dark, read_noise_e=0.0)
    n = 5_000
    out = simulate_reads(
        np.zeros((4, 1, n, 1)),
        [r.buckets for r in tl.reads],
        cfg,
        np.random.SeedSequence(30),
        storage_s=tl.storage_s(),
        shared_photodiode=not sequential,
    )
    mean_e = out.electrons.reshape(4, -1).mean(axis=1)
    for k in range(4):
        m = dark * want_s[k]
        assert abs(mean_e[k] - m) < N_SIGMA * np.sqrt(m / n), (k, mean_e[k], m)
    # the storage differs from the exposure by far more than the tolerance (else this proves nothing)
    differs = np.abs(dark * (want_s - exposure_s)) > 10 * N_SIGMA * np.sqrt(dark * want_s / n)
    assert differs.any() if not sequential else not differs.any()
    # reads in electrons: the DN of a read is the sum of its buckets' dark charge (gain, black level)
    read_e = dn_to_electrons(out.reads_dn, cfg).reshape(4, -1).mean(axis=1)
    for r, read in enumerate(tl.reads):
        m = dark * want_s[list(read.buckets)].sum()
        assert abs(read_e[r] - m) < N_SIGMA * np.sqrt((m + 1 / (12 * cfg.gain_dn_per_e**2)) / n)


def test_prnu_is_one_fixed_pattern_shared_by_every_read():
    """Zero read noise, 20 % PRNU and so many electrons that shot noise is 1e-4: in every pixel the
    ratio of two reads equals the ratio of their exposures (4:1 for buckets of 4T and T; the
    cumulative read of both, 5:1), and each read divided by its expectation is the sensor's PRNU
    map, identical in a second capture with another noise seed. Per-pixel tolerance: 5 sd of the
    shot noise of that pixel's own expected charge."""
    cfg = ideal(
        prnu=0.2,
        read_noise_e=0.0,
        full_well_e=1e9,
        fd_full_well_e=4e9,
        adc_bits=24,
        gain_dn_per_e=1e-2,
        black_level_dn=0.0,
    )
    e = np.array([4e7, 1e7])  # buckets of 4T and T
    h, w = 8, 50
    exp_e = np.broadcast_to(e[:, None, None, None], (2, h, w, 3)).copy()
    gain = fixed_pattern((h, w, 3), cfg).prnu_gain  # the map of an (H, W, C) image, one value per pixel
    assert gain.std() > 0.15 and gain.min() > 0.2  # a real pattern, no pixel near zero sensitivity
    reads = [(0,), (1,), (0, 1)]
    for seed in (31, 32):
        out = simulate_reads(exp_e, reads, cfg, np.random.SeedSequence(seed))
        j = dn_to_electrons(out.reads_dn, cfg)  # (3, h, w, 3)
        quant = 0.5 / cfg.gain_dn_per_e  # rounding to DN, electrons
        for r, read in enumerate(reads):
            m = gain * e[list(read)].sum()
            assert np.all(np.abs(j[r] - m) < N_SIGMA * np.sqrt(m) + quant), r  # read = PRNU map x expectation
        ratio = j[0] / j[1]
        sd = 4.0 * np.sqrt(1 / (gain * e[0]) + 1 / (gain * e[1]))  # relative errors add in quadrature
        assert np.all(np.abs(ratio - 4.0) < N_SIGMA * sd)
        assert np.all(np.abs(j[2] / j[1] - 5.0) < N_SIGMA * 5.0 * np.sqrt(1 / (gain * e.sum()) + 1 / (gain * e[1])))


def test_transfer_inefficiency_alone_loses_its_fraction_once_per_bucket():
    """Only transfer loss on (no read noise, dark current, PRNU, parasitic light): electrons are
    only ever lost, never gained (every read <= its buckets' charge); the mean read is (1 - eps)
    of the charge and, binomial thinning of Poisson charge being Poisson, so is its variance; the
    loss is drawn once per bucket, so the second cumulative read adds bucket 3's transferred
    charge to exactly the charge of the first read: J2 - J1 <= B3 in every pixel, and J2 - J1 is
    thinned Poisson, mean = variance = (1 - eps) lambda_3 (a loss drawn afresh for each read would
    add 2 eps (1 - eps) lambda_4 = 320 e-^2 to that variance of 480)."""
    eps = 0.2
    cfg = ideal(
        transfer_inefficiency=eps, read_noise_e=0.0, gain_dn_per_e=1.0, black_level_dn=0.0, dark_current_e_per_s=0.0
    )
    n = 40_000
    lam = np.array([0.0, 0.0, 600.0, 1000.0])
    out = simulate_reads(flat(list(lam), n), [(3,), (3, 2)], cfg, np.random.SeedSequence(33))
    j = out.reads_dn.reshape(2, -1)  # gain 1, black level 0, integer charge: DN = electrons exactly
    b = out.electrons.reshape(4, -1)
    assert np.all(j[0] <= b[3]) and np.all(j[1] <= b[3] + b[2])
    assert np.all(j[1] - j[0] <= b[2]) and np.all(j[1] - j[0] >= 0)
    for r, m in enumerate([(1 - eps) * lam[3], (1 - eps) * lam[2:].sum()]):
        assert abs(j[r].mean() - m) < N_SIGMA * np.sqrt(m / n)
        assert abs(j[r].var(ddof=1) - m) < N_SIGMA * var_se(m, n, 1.0 / m)
    d, m = j[1] - j[0], (1 - eps) * lam[2]
    assert abs(d.mean() - m) < N_SIGMA * np.sqrt(m / n)
    assert abs(d.var(ddof=1) - m) < N_SIGMA * var_se(m, n, 1.0 / m)
    lost = b[3] - j[0]  # binomial(B4, eps) given the bucket's charge
    assert abs(lost.mean() - eps * lam[3]) < N_SIGMA * np.sqrt(eps * lam[3] / n)


def test_parasitic_light_alone_adds_its_fraction_of_the_other_buckets_light():
    """Only parasitic light on: bucket k's mean charge is its own light plus ``parasitic_light``
    times the light of the other buckets of the same pixel (never less than its own light); the
    frames of a sequential capture (separate exposures, shared_photodiode=False) do not couple; the
    ground truth ``reads_e_expected`` stays the input light."""
    p = 0.05
    cfg = ideal(parasitic_light=p, read_noise_e=0.0, dark_current_e_per_s=0.0)
    n = 40_000
    lam = np.array([1000.0, 0.0, 300.0])
    want = lam + p * (lam.sum() - lam)  # 1015, 65, 350
    out = simulate_reads(flat(list(lam), n), [(0,), (1,), (2,)], cfg, np.random.SeedSequence(34))
    mean_e = out.electrons.reshape(3, -1).mean(axis=1)
    for k in range(3):
        assert abs(mean_e[k] - want[k]) < N_SIGMA * np.sqrt(want[k] / n), (k, mean_e[k], want[k])
    np.testing.assert_array_equal(out.reads_e_expected.reshape(3, -1), np.repeat(lam[:, None], n, axis=1))
    seq = simulate_reads(
        flat(list(lam), n), [(0,), (1,), (2,)], cfg, np.random.SeedSequence(34), shared_photodiode=False
    )
    assert np.all(seq.electrons[1] == 0.0)
    assert abs(seq.electrons[0].mean() - lam[0]) < N_SIGMA * np.sqrt(lam[0] / n)


def test_simulate_reads_refuses_bad_input_naming_the_argument():
    cfg = ideal()
    ok = np.full((2, 1, 3, 3), 10.0)
    cases = [
        (np.full((2, 3, 3), 10.0), [(0,)], {}, r"^expected_bucket_e: expected shape \(K, H, W, C\), got \(2, 3, 3\)$"),
        (
            np.where(np.arange(3) == 1, -1.0, 10.0) * np.ones((2, 1, 3, 3)),
            [(0,)],
            {},
            r"^expected_bucket_e: values must be finite and >= 0$",
        ),
        (
            np.where(np.arange(3) == 1, np.nan, 10.0) * np.ones((2, 1, 3, 3)),
            [(0,)],
            {},
            r"^expected_bucket_e: values must be finite and >= 0$",
        ),
        (np.full((5, 1, 3, 3), 10.0), [(0,)], {}, r"^expected_bucket_e: 5 buckets but sensor.bucket_count is 4$"),
        (ok, [], {}, r"^reads: at least one read is needed$"),
        (ok, [(0,), ()], {}, r"^reads\[1\]: a read must sum at least one bucket$"),
        (ok, [(0, 0)], {}, r"^reads\[0\]: bucket listed twice in \(0, 0\)$"),
        (ok, [(0,), (2,)], {}, r"^reads\[1\]: bucket indices \(2,\) outside 0..1$"),
        (ok, [(-1,)], {}, r"^reads\[0\]: bucket indices \(-1,\) outside 0..1$"),
        (ok, [(0,)], {"storage_s": [1.0]}, r"^storage_s: expected 2 non-negative seconds, got"),
        (ok, [(0,)], {"storage_s": [1.0, -1.0]}, r"^storage_s: expected 2 non-negative seconds, got"),
    ]
    for expected, reads, kw, message in cases:
        with pytest.raises(ValueError, match=message):
            simulate_reads(expected, reads, cfg, 0, **kw)
    simulate_reads(ok, [(0,), (1,)], cfg, 0, storage_s=[0.0, 1.0])  # the valid neighbours pass


class _FixedFields(NoiseStreams):
    """Every uniform 1/2 (each Poisson draw is its median) and every normal +1: a capture with no
    randomness left, so each read's DN can be written down by hand."""

    def uniform(self, stage, shape):
        return np.full(shape, 0.5)

    def normal(self, stage, shape):
        return np.ones(shape)

    def normal_runs(self, stage, shape):  # the fields above, one leading index at a time (subclasses too)
        return iter(self.normal(stage, shape))


def test_readout_chain_by_hand_with_fixed_noise_fields():
    """Poisson(100) has median 100, so two buckets expecting 100 e- hold exactly 100 each. With the
    FD full well at 200 their sum reaches it: flagged (the sum clips *at* the well). DN =
    rint(gain (FD + DSNU map + R x 1) + black): the DSNU map and the read noise enter with their
    signs; a 10-bit ADC whose top code the sum reaches exactly is flagged too; a read far below
    the black level clips to code 0 (not flagged). The noise argument may be a NoiseStreams itself,
    and the result lists the reads as given."""
    cfg = SensorConfig(
        prnu=0.0,
        dsnu_e=2.0,
        read_noise_e=3.0,
        fd_full_well_e=200.0,
        gain_dn_per_e=4.0,
        black_level_dn=10.0,
        adc_bits=12,
        dark_current_e_per_s=0.0,
    )
    fpn = fixed_pattern((1, 4, 3), cfg)
    assert np.ptp(fpn.dsnu_offset_e) > 1.0  # a per-pixel map, not one offset
    exp_e = np.full((2, 1, 4, 3), 100.0)
    out = simulate_reads(exp_e, [[0], (0, 1)], cfg, _FixedFields(0))
    assert out.reads == ((0,), (0, 1))
    np.testing.assert_array_equal(out.electrons, 100.0)
    np.testing.assert_array_equal(out.reads_dn[0], np.rint(4.0 * (100.0 + fpn.dsnu_offset_e + 3.0) + 10.0))
    np.testing.assert_array_equal(out.reads_dn[1], np.rint(4.0 * (200.0 + fpn.dsnu_offset_e + 3.0) + 10.0))
    assert not out.saturated[0].any() and out.saturated[1].all()
    adc = cfg.model_copy(
        update={
            "fd_full_well_e": 1e6,
            "dsnu_e": 0.0,
            "read_noise_e": 0.0,
            "adc_bits": 10,
            "gain_dn_per_e": 5.0,
            "black_level_dn": 23.0,
        }
    )  # 5 x 200 + 23 = 1023, the top code
    top = simulate_reads(exp_e, [(0,), (0, 1)], adc, _FixedFields(0))
    np.testing.assert_array_equal(top.reads_dn, [np.full((1, 4, 3), 523.0), np.full((1, 4, 3), 1023.0)])
    assert not top.saturated[0].any() and top.saturated[1].all()
    low = cfg.model_copy(update={"dsnu_e": 0.0, "read_noise_e": 500.0, "black_level_dn": 0.0})
    dark = simulate_reads(np.zeros((1, 1, 4, 3)), [(0,)], low, _Negative(0))
    np.testing.assert_array_equal(dark.reads_dn, 0.0)
    assert not dark.saturated.any()


class _Negative(_FixedFields):
    def normal(self, stage, shape):
        return -np.ones(shape)


def test_the_sensor_stage_hook_sees_each_input_and_can_simulate_another():
    """The seam of the stage goldens: inside sensor_stage_hook every simulate_reads call hands its input
    to the hook, whose simulate(e) is the same sensor (noise fields, reads, storage) on another input;
    outside it nothing changes."""
    from mbcapture.sensor import sensor_stage_hook

    cfg = SensorConfig(transfer_inefficiency=1e-3)
    e = np.full((4, 3, 5, 3), 800.0)
    reads = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
    kw = dict(storage_s=np.full(4, 1e-3))
    plain = simulate_reads(e, reads, cfg, np.random.SeedSequence(5), **kw)
    seen = []

    def hook(x, simulate):
        seen.append(x.copy())
        assert np.array_equal(simulate(x).reads_dn, simulate(x).reads_dn)  # the same fields on every call
        return simulate(2 * x)

    with sensor_stage_hook(hook):
        out = simulate_reads(e, reads, cfg, np.random.SeedSequence(5), **kw)
    assert len(seen) == 1 and np.array_equal(seen[0], e)
    doubled = simulate_reads(2 * e, reads, cfg, np.random.SeedSequence(5), **kw)
    assert np.array_equal(out.reads_dn, doubled.reads_dn) and not np.array_equal(out.reads_dn, plain.reads_dn)
    assert np.array_equal(simulate_reads(e, reads, cfg, np.random.SeedSequence(5), **kw).reads_dn, plain.reads_dn)
    with (
        sensor_stage_hook(lambda x, simulate: simulate(x[:, :2])),
        pytest.raises(ValueError, match="sensor stage input"),
    ):
        simulate_reads(e, reads, cfg, np.random.SeedSequence(5), **kw)


def test_row_and_column_fixed_pattern_and_row_noise_are_recovered_by_the_emva_split():
    """A dark series and a flat series of F frames (one read each): the mean image's row / column /
    pixel variance split recovers the configured DSNU and PRNU components, and the frames' row means
    the temporal row noise, each within 5 standard errors of its estimate (a variance from n
    independent values: relative standard error sqrt(2 / (n - 1)))."""
    from mbcapture.metrics import row_column_pixel_variances
    from mbcapture.sensor import dn_to_electrons

    H, W, F = 384, 320, 24
    cfg = SensorConfig(
        prnu=0.01,
        prnu_row=0.004,
        prnu_col=0.006,
        dsnu_e=1.0,
        dsnu_row_e=0.6,
        dsnu_col_e=0.8,
        read_noise_e=2.0,
        read_noise_row_e=0.5,
        dark_current_e_per_s=0.0,
        fpn_seed=3,
    )
    reads = [(k,) for k in range(F)]
    q_e2 = (1.0 / cfg.gain_dn_per_e) ** 2 / 12.0  # the ADC's rounding, in electrons^2
    t_pix = cfg.read_noise_e**2 + q_e2  # temporal variance per pixel and frame besides the row noise

    def series(level_e: float, seed: int) -> np.ndarray:
        out = simulate_reads(
            np.full((F, H, W, 1), level_e), reads, cfg, np.random.SeedSequence(seed), shared_photodiode=False
        )
        return dn_to_electrons(out.reads_dn[..., 0], cfg)  # (F, H, W) electrons

    def within(got, want, sd, what):
        assert abs(got - want) <= 5 * sd, f"{what}: {got:.4g} vs {want:.4g} +- {sd:.2g}"

    dark = series(0.0, 1)
    rows, cols, pix = row_column_pixel_variances(dark.mean(axis=0))
    want_rows = cfg.dsnu_row_e**2 + cfg.read_noise_row_e**2 / F
    want_cols, want_pix = cfg.dsnu_col_e**2, cfg.dsnu_e**2 + t_pix / F
    within(rows, want_rows, np.sqrt(2 / (H - 1)) * (want_rows + want_pix / W), "DSNU rows")
    within(cols, want_cols, np.sqrt(2 / (W - 1)) * (want_cols + want_pix / H), "DSNU columns")
    within(pix, want_pix, np.sqrt(2 / (H * W)) * want_pix * 1.5, "DSNU pixels")
    # temporal row noise: each frame's row means about the mean image vary as s_row^2 + t_pix / W
    resid_rows = (dark - dark.mean(axis=0)).mean(axis=2) * np.sqrt(F / (F - 1))
    n = resid_rows.size
    want_t = cfg.read_noise_row_e**2 + t_pix / W
    within(resid_rows.var(), want_t, np.sqrt(2 / (n - 1)) * want_t, "temporal row noise")

    level = 5000.0
    flat = series(level, 2)
    gain = (flat.mean(axis=0) - dark.mean(axis=0)) / level  # relative sensitivity: the DSNU cancels
    rows, cols, pix = row_column_pixel_variances(gain)
    t_rel = (level + 2 * t_pix) / F / level**2  # shot + both series' temporal noise, relative
    want_rows = cfg.prnu_row**2 + 2 * cfg.read_noise_row_e**2 / F / level**2
    want_cols, want_pix = cfg.prnu_col**2, cfg.prnu**2 + t_rel
    within(rows, want_rows, np.sqrt(2 / (H - 1)) * (want_rows + want_pix / W), "PRNU rows")
    within(cols, want_cols, np.sqrt(2 / (W - 1)) * (want_cols + want_pix / H), "PRNU columns")
    within(pix, want_pix, np.sqrt(2 / (H * W)) * want_pix * 1.5, "PRNU pixels")


def test_without_row_and_column_components_the_fixed_pattern_is_as_before():
    """The components default to 0, and the pixel maps of a given fpn_seed do not change when they are on."""
    from mbcapture.sensor import fixed_pattern

    base = fixed_pattern((8, 9, 3), SensorConfig(fpn_seed=4))
    rng = np.random.default_rng(np.random.SeedSequence(4))
    assert np.array_equal(base.prnu_gain, np.maximum(1.0 + 0.01 * rng.standard_normal((8, 9, 3)), 0.0))
    assert np.array_equal(base.dsnu_offset_e, 1.0 * rng.standard_normal((8, 9, 3)))
    lines = fixed_pattern((8, 9, 3), SensorConfig(fpn_seed=4, dsnu_col_e=0.5, prnu_row=0.01))
    d = lines.dsnu_offset_e - base.dsnu_offset_e  # a column offset: the same down each column, in every channel
    assert np.allclose(d, d[:1, :, :1]) and d[0, :, 0].std() > 0.1
    g = lines.prnu_gain - base.prnu_gain
    assert np.allclose(g, g[:, :1, :1]) and g[:, 0, 0].std() > 0.002
