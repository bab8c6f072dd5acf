"""Numerical stability on stiff and extreme cases, and bad input that must never lose data (issue 7).

Every case gives finite outputs, the right saturation/validity flags and the behaviour that
docs/stability.md documents; that file lists each case, what it produced and the limits found.
Cases already covered elsewhere are referenced there, not repeated here:
tests/test_hdr.py (every read saturated, negative reads at zero light, one usable cumulative
read), tests/test_timeline.py (10^6 periods of 1 us slots, closed-form gated time vs
enumeration), tests/test_config.py (malformed YAML, unknown keys, wrong types),
tests/test_end_to_end.py (an exception while writing keeps the previous outputs). The application
cases (flash_no_flash, multi_flash, flash_matting) call their public functions on synthetic arrays.

Sizes are CI-sized: renders at most 32x24, few strata; statistical tolerances are 5 standard
errors of the sample sizes used.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbcapture.timing import protocols
from mbcapture.config import config_from_dict, load_config
from mbcapture.errors import ConfigError
from mbcapture.exposure.integrate import accumulate
from mbcapture.scene.pendulum import OVERDAMPED_RATIO, STIFF_RATIO, Pendulum, nonlinear_period_s
from mbcapture.reconstruct.hdr import merge_hdr, quantization_read_variance_e2
from mbcapture.sensor import SensorConfig, dn_to_electrons, simulate_reads
from mbcapture.sensor.sampling import POISSON_EXACT_MAX
from mbcapture.timing.timeline import DRAIN, ReadEvent, SegmentSeconds, SlotSeconds, build_timeline

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny_hdr.yaml"
N_SIGMA = 5.0
IDEAL = SensorConfig(prnu=0.0, dsnu_e=0.0, dark_current_e_per_s=0.0)


def cfg(**capture):
    sensor = capture.pop("sensor", {})
    return config_from_dict({"scene": {"name": "flatfield"}, "capture": capture, "sensor": sensor})


# =============================================================================== motion
def upward_zero_crossings(p: Pendulum, t0: float, t1: float, n: int = 4001) -> np.ndarray:
    """Times in [t0, t1] where theta crosses 0 upwards, refined by Newton on the solution itself."""
    t = np.linspace(t0, t1, n)
    th = p.angle_rad(t)
    idx = np.flatnonzero((th[:-1] < 0) & (th[1:] >= 0))
    out = []
    for i in idx:
        x = t[i] - th[i] * (t[i + 1] - t[i]) / (th[i + 1] - th[i])
        for _ in range(8):
            a, w = p.state(x)
            x -= float(a) / float(w)
        out.append(x)
    return np.array(out)


# (tempo bpm, amplitude deg): the scene's fastest tempo (400) and near its largest amplitude (< 90),
# then the Pendulum class up to the closed form's limit near 180 deg
EXTREMES = [
    (400.0, 89.99),
    (400.0, 1e-4),
    (30.0, 89.99),
    (400.0, 170.0),
    (400.0, 179.0),
    (400.0, 179.99),
    (400.0, 179.996),
]


@pytest.mark.parametrize("tempo,amp_deg", EXTREMES)
def test_closed_form_period_and_energy_at_the_extremes(tempo, amp_deg):
    p = Pendulum.from_tempo(tempo, amp_deg)
    T = p.period_s
    assert nonlinear_period_s(p.omega0_rad_per_s, p.amplitude_rad) == pytest.approx(T, rel=1e-13)
    crossings = upward_zero_crossings(p, 0.5 * T, 20.5 * T)
    assert len(crossings) == 20
    # measured period (the closed form's own zero crossings) vs the elliptic 4 K / omega0: 1e-9
    np.testing.assert_allclose(np.diff(crossings), T, rtol=1e-9)
    t = np.linspace(0.0, 20 * T, 40001)
    th, om = p.state(t)
    assert np.all(np.isfinite(th)) and np.all(np.isfinite(om))
    assert np.max(np.abs(th)) == pytest.approx(p.amplitude_rad, rel=1e-6)
    e = p.energy_per_inertia(t) / p.target_energy_per_inertia
    assert np.max(np.abs(e - 1.0)) < 1e-12  # measured <= 1.5e-15


def test_amplitude_past_the_closed_form_limit_is_refused():
    # scipy's ellipj is wrong for 1 - m <= 1e-10 (energy off by 1e23 at 179.999 deg): refused
    with pytest.raises(ValueError, match=r"accurate only up to 179\.996"):
        Pendulum.from_tempo(400.0, 179.999)


def test_stiff_damped_needle_uses_an_implicit_solver():
    gamma = 1e4  # omega0 ~ 6.3 rad/s: (gamma / omega0) ~ 1600 > STIFF_RATIO
    p = Pendulum(math.radians(30.0), 1.0, damping_per_s=gamma)
    assert p.stiff and p.solver == "LSODA" and gamma / p.omega0_rad_per_s > STIFF_RATIO
    span = 0.5
    auto = p.solve(span)
    radau = p.solve(span, method="Radau")  # an independent implicit method (Radau IIA, order 5)
    explicit = p.solve(span, method="DOP853")
    t = np.linspace(0.0, span, 501)
    np.testing.assert_allclose(auto.sol(t)[0], radau.sol(t)[0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(auto.sol(t)[0], explicit.sol(t)[0], rtol=0, atol=1e-10)
    # the explicit method pays for the stiffness with tiny steps; the implicit one does not
    assert explicit.nfev > 10 * auto.nfev, (explicit.nfev, auto.nfev)
    th, om = p.state(t)
    e = 0.5 * om**2 + 2 * p.omega0_rad_per_s**2 * np.sin(th / 2) ** 2
    assert np.all(np.diff(e) <= 1e-12 * e[0])  # friction only removes energy
    # slow manifold: tan(theta/2) decays like exp(-omega0^2 t / gamma) once the speed has died
    late = np.array([0.2, 0.4])
    ratio = np.tan(p.angle_rad(late[1]) / 2) / np.tan(p.angle_rad(late[0]) / 2)
    assert ratio == pytest.approx(math.exp(-(p.omega0_rad_per_s**2) * 0.2 / gamma), rel=1e-6)


@pytest.mark.parametrize("gamma", [1e7, 1e12, 1e300])
def test_extreme_damping_uses_the_overdamped_closed_form(gamma):
    p = Pendulum(math.radians(30.0), 1.0, damping_per_s=gamma)
    assert p.overdamped_closed_form and gamma / p.omega0_rad_per_s > OVERDAMPED_RATIO
    t = np.array([0.0, 1.0 / gamma, 10.0 / gamma, 0.1, 1.0, 10.0])
    th, om = p.state(t)
    assert np.all(np.isfinite(th)) and np.all(np.isfinite(om))
    assert th[0] == 0.0 and om[0] == pytest.approx(p.max_angular_speed_rad_per_s())
    if gamma <= 1e7:  # against the ODE: (omega0 / gamma)^2 ~ 4e-13 relative
        ode = p.solve(10.0, t_eval=t[1:])
        np.testing.assert_allclose(th[1:], ode.y[0], rtol=1e-9)


def test_damped_motion_far_before_tau_zero_is_refused_not_overflowed():
    p = Pendulum(math.radians(30.0), 1.0, damping_per_s=1e4)
    assert np.isfinite(p.angle_rad(-0.02))  # 200 decay times back: huge but finite
    with pytest.raises(ValueError, match="decay times back"):
        p.angle_rad(-0.05)


def test_stiff_escapement_settles_on_the_exact_pendulum():
    """kappa = 1e4/s pulls the swing from 20 to 30 deg within milliseconds; afterwards the needle
    is the free pendulum of amplitude 30 deg: elliptic period and energy E_A."""
    T = 0.5
    p = Pendulum(math.radians(30.0), T, escapement_per_s=1e4, start_amplitude_rad=math.radians(20.0))
    assert p.stiff and p.solver == "LSODA"
    t = np.linspace(0.25, 1.25, 2001)
    e = p.energy_per_inertia(t) / p.target_energy_per_inertia
    assert np.max(np.abs(e - 1.0)) < 1e-8  # measured ~2e-9
    crossings = upward_zero_crossings(p, 0.25, 1.25)
    np.testing.assert_allclose(np.diff(crossings), T, rtol=1e-7)
    # started on the cycle, the driven needle is the closed form itself (same phase)
    on = Pendulum(math.radians(30.0), T, escapement_per_s=1e4)
    free = Pendulum(math.radians(30.0), T)
    t = np.linspace(0.0, 2 * T, 401)
    np.testing.assert_allclose(on.angle_rad(t), free.angle_rad(t), rtol=0, atol=1e-7)


def test_metronome_at_fastest_tempo_and_largest_amplitude_plans_finitely():
    from mbcapture.capture.pipeline import prepare

    c = load_config(
        TINY,
        [
            "render.width=32",
            "render.height=24",
            "scene.tempo_bpm=400",
            "scene.amplitude_deg=89.99",
            "render.max_motion_px=0.5",
            "render.spp=2",
        ],
    )
    scene, timeline, plan, _ = prepare(c)
    assert plan.passes > 1 and np.all(np.isfinite(plan.times_s)) and np.all(np.isfinite(plan.weights_s))
    # the strata cover the capture exactly: the always-on ambient weights (ticks) sum to every exposure
    ticks = np.rint(plan.weights_s[:, :, plan.groups.index("ambient")] / float(timeline.tick_s)).astype(np.int64)
    assert ticks.sum(axis=0).tolist() == [timeline.exposure_ticks(k) for k in range(timeline.n_buckets)]
    # the fastest needle point moves at most max_motion_px per stratum (0.5 px, 1 % slack for sampling)
    assert plan.motion_px_total / plan.passes <= 0.505
    pts = scene.motion_points(plan.times_s)
    assert np.all(np.isfinite(pts))


# =============================================================================== time
@pytest.mark.parametrize("periods", [10**6, 10**7])
def test_a_million_periods_partition_weights_exactly(periods):
    """Slots of T/N: 1 us (10^6 periods of T = 1 s) down to 0.1 us (10^7, the config's maximum)."""
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", unit_exposure_s=1.0, periods=periods))
    span = tl.end_tick - tl.start_tick
    assert span * tl.tick_s == 8  # an 8 s capture
    rng = np.random.default_rng(periods)
    inner = np.unique(rng.integers(tl.start_tick + 1, tl.end_tick, size=300))
    edges = np.concatenate([[tl.start_tick], inner, [tl.end_tick]]).astype(np.int64)
    w = tl.weights_ticks(edges, ("ambient",), frozenset())
    assert (w >= 0).all()
    assert w.sum(axis=0)[:, 0].tolist() == [tl.exposure_ticks(k) for k in range(4)]
    assert [tl.exposure_ticks(k) * tl.tick_s for k in range(4)] == [4, 2, 1, 1]
    # no drift: after n whole periods every bucket has gated exactly n slots, at any n
    period = tl.segments[0].period_ticks
    n = np.array([1, 12345, periods // 3, periods - 1, periods])
    for k, slot in enumerate(tl.segments[0].slots):
        assert tl.gated_ticks(tl.start_tick + n * period, k).tolist() == (n * slot.ticks).tolist()
    # the float seconds handed to the renderer: each stratum weight is ticks * tick, so the sum over
    # 301 strata is within a few ulps of the exact exposure
    ws = w[:, :, 0].astype(np.float64) * float(tl.tick_s)
    np.testing.assert_allclose(ws.sum(axis=0), [4.0, 2.0, 1.0, 1.0], rtol=64 * np.finfo(float).eps)


def test_long_capture_with_1us_slots_keeps_exact_centroids():
    """3 s of 1 us slots (three buckets, 10^6 periods): exposures 1 s each, centroids 1 us apart."""
    slots = tuple(SlotSeconds(b, Fraction(1, 10**6)) for b in range(3))
    reads = [ReadEvent(f"F{b}", (b,)) for b in range(3)]
    tl = build_timeline([SegmentSeconds(Fraction(0), slots, 10**6)], reads, 3, "custom")
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == 3
    assert [tl.read_exposure_ticks(r) * tl.tick_s for r in tl.reads] == [1, 1, 1]
    c = [tl.centroid_ticks((b,)) * tl.tick_s for b in range(3)]
    assert c[1] - c[0] == c[2] - c[1] == Fraction(1, 10**6)
    d = tl.describe_reads()
    assert [r["exposure_s"] for r in d] == [1.0, 1.0, 1.0]


def test_too_fine_a_common_time_unit_is_a_config_error():
    """Durations written with 16 significant digits force a 1e-16 s tick: 2^62 ticks then last
    461 s, so 10^7 periods of 1/3 s (3.3e6 s) cannot be represented and are refused."""
    slots = [{"bucket": 1, "duration_s": 1 / 3}, {"bucket": 2, "duration_s": 0.001}]
    c = cfg(protocol="custom", periods=10**7, schedule={"slots": slots, "reads": [{"buckets": [1]}]})
    with pytest.raises(ConfigError, match=r"more than 2\^62 ticks"):
        protocols.build(c)
    tl = protocols.build(cfg(protocol="custom", periods=1000, schedule={"slots": slots, "reads": [{"buckets": [1]}]}))
    assert tl.tick_s == Fraction(1, 10**16) and tl.exposure_ticks(0) * tl.tick_s == 1000 * Fraction(repr(1 / 3))


# =============================================================================== light
def flat(values, n_pix, channels=1):
    v = np.asarray(values, dtype=np.float64)
    return np.broadcast_to(v[:, None, None, None], (len(v), 1, n_pix, channels)).copy()


CUM_READS = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
CUM_T = 1e-3 * np.array([1.0, 2.0, 4.0, 8.0])
SLOTS_T = 1e-3 * np.array([4.0, 2.0, 1.0, 1.0])


@pytest.mark.parametrize("method", ["ramp_fit", "inverse_variance", "debevec"])
def test_zero_radiance_gives_black_unsaturated_valid_zero_rate(method):
    c = SensorConfig(prnu=0.0, dsnu_e=0.0, dark_current_e_per_s=0.0, read_noise_e=2.0)
    n = 20_000
    out = simulate_reads(flat([0.0] * 4, n), CUM_READS, c, np.random.default_rng(1))
    assert not out.saturated.any() and np.all(out.electrons == 0)
    res = merge_hdr(out.reads_dn, CUM_T, c, method=method, cumulative=True, saturated=out.saturated)
    assert res.valid.all() and np.all(np.isfinite(res.rate_e_per_s)) and np.all(np.isfinite(res.sigma_temporal_e_per_s))
    se = np.median(res.sigma_temporal_e_per_s) / math.sqrt(n)
    if method == "debevec":
        # the hat weight (code - black level) favours reads that noise pushed up: biased upwards at
        # zero light (measured: +770 e-/s = +0.77 e- in the 1 ms read, with 2 e- read noise)
        assert res.rate_e_per_s.mean() > N_SIGMA * se
    else:  # unbiased around zero: read noise only, sigma from the noise model
        assert abs(res.rate_e_per_s.mean()) < N_SIGMA * se


@pytest.mark.parametrize("times_full_well", [1e6, 1e12, 1e15, 1e30])
def test_radiance_far_above_the_full_well_saturates_finitely(times_full_well):
    """1e6 x the full well (a flash into the lens) up to 1e30 x, past numpy's Poisson limit (9.2e18)."""
    c = IDEAL
    mean = times_full_well * c.full_well_e * SLOTS_T / SLOTS_T.sum()
    out = simulate_reads(flat(mean, 50, 3), CUM_READS, c, np.random.default_rng(2))
    assert np.all(out.electrons == c.full_well_e) and out.bucket_saturated.all() and out.saturated.all()
    assert np.all(out.reads_dn <= c.adc_max_dn) and np.all(np.isfinite(out.reads_dn))
    res = merge_hdr(out.reads_dn, CUM_T, c, method="ramp_fit", cumulative=True, saturated=out.saturated)
    assert not res.valid.any() and np.all(np.isinf(res.sigma_temporal_e_per_s))
    assert np.all(np.isfinite(res.rate_e_per_s)) and np.all(res.rate_e_per_s > 0)


def test_poisson_draws_stay_integer_and_within_a_few_sd_up_to_1e30():
    """Means from 10 to 1e30 (numpy's own sampler refuses 9.2e18): exact inversion up to
    POISSON_EXACT_MAX, the rounded Cornish-Fisher quantile above; every draw an integer within
    6 sd of its mean (float64 resolution where the mean is beyond 2^53)."""
    c = IDEAL.model_copy(update={"full_well_e": 1e31, "fd_full_well_e": 1e31})
    means = np.array([10.0, 1e6, POISSON_EXACT_MAX / 2, POISSON_EXACT_MAX * 2, 5e18, 1e25, 1e30])
    mean = np.broadcast_to(means[None, :, None, None], (1, means.size, 200, 1)).copy()
    got = simulate_reads(mean, [(0,)], c, np.random.default_rng(3)).electrons[0, :, :, 0]
    assert np.all(np.isfinite(got))
    dev = (got - means[:, None]) / np.sqrt(means[:, None])
    assert np.all(np.abs(dev) < 6.0)
    exact = means < 2.0**53
    assert np.all(got[exact] == np.rint(got[exact]))
    assert np.all(dev.std(axis=1) > 0.7), "shot noise survives at every scale"


def test_exposure_ratio_2_to_the_20_in_a_custom_schedule():
    """Two independent reads, 1 us and 1.048576 s (ratio 2^20), exact in ticks; merged at rates where
    the short read sees 0.01 .. 9000 e-: finite, unbiased, the long read dropped once saturated."""
    c = cfg(
        protocol="custom",
        periods=1,
        schedule={
            "slots": [{"bucket": 1, "duration_s": 1e-6}, {"bucket": 2, "duration_s": 1.048576}],
            "reads": [{"name": "short", "buckets": [1]}, {"name": "long", "buckets": [2]}],
        },
    )
    tl = protocols.build(c)
    exp_ticks = [tl.read_exposure_ticks(r) for r in tl.reads]
    assert exp_ticks[1] == 2**20 * exp_ticks[0]
    t = np.array([float(e * tl.tick_s) for e in exp_ticks])
    sensor = IDEAL
    n = 4000
    fw = sensor.full_well_e
    for rate in (5e3, 5e6, 9e9):  # short read: 0.005, 5, 9000 e-; long read: 5200 e-, then saturated
        out = simulate_reads(flat(rate * t, n, 3), [(0,), (1,)], sensor, np.random.default_rng(int(np.log10(rate))))
        res = merge_hdr(out.reads_dn, t, sensor, method="inverse_variance", cumulative=False, saturated=out.saturated)
        assert np.all(np.isfinite(res.rate_e_per_s)) and res.valid.all()
        assert np.all(res.n_used == (2 if rate * t[1] < fw - 6 * math.sqrt(fw) else 1))
        se = np.sqrt(np.mean(res.sigma_temporal_e_per_s**2) / res.rate_e_per_s.size)
        assert abs(res.rate_e_per_s.mean() - rate) < N_SIGMA * se


def test_twenty_one_cumulative_reads_spanning_2_to_the_20():
    """photon_efficient_hdr on a 21-bucket sensor: cumulative reads T .. 2^20 T; the ramp fit's
    min(t_i, t_j) matrix (condition number ~4e6) still gives unbiased, efficient rates."""
    tl = protocols.build(
        cfg(protocol="photon_efficient_hdr", unit_exposure_s=1e-6, periods=1, sensor={"bucket_count": 21})
    )
    t = np.array([float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads])
    assert np.allclose(t / t[0], 2.0 ** np.arange(21), rtol=0)
    slot_t = np.array([float(tl.exposure_ticks(k) * tl.tick_s) for k in range(21)])
    sensor = IDEAL.model_copy(update={"bucket_count": 21, "fd_full_well_e": 1e9, "adc_bits": 24, "gain_dn_per_e": 0.01})
    n = 3000
    for rate in (5e3, 4e6, 4e9):
        # usable: the reads before the first one holding a bucket that fills its well
        full = rate * slot_t > sensor.full_well_e - 6 * math.sqrt(sensor.full_well_e)
        n_used = next((i for i, r in enumerate(tl.reads) if full[list(r.buckets)].any()), 21)
        assert n_used == {5e3: 21, 4e6: 13, 4e9: 3}[rate]
        out = simulate_reads(flat(rate * slot_t, n, 3), [r.buckets for r in tl.reads], sensor, np.random.default_rng(7))
        res = merge_hdr(out.reads_dn, t, sensor, method="ramp_fit", cumulative=True, saturated=out.saturated)
        assert np.all(np.isfinite(res.rate_e_per_s)) and np.all(np.isfinite(res.sigma_temporal_e_per_s))
        assert np.all(res.n_used == n_used), np.unique(res.n_used)
        x = res.rate_e_per_s.ravel()
        sig = np.median(res.sigma_temporal_e_per_s)
        assert abs(x.mean() - rate) < N_SIGMA * sig / math.sqrt(x.size)
        assert x.std() == pytest.approx(sig, rel=0.1)  # the returned sigma is the actual spread


# =============================================================================== reconstruction
def test_ramp_fit_with_one_unsaturated_read_has_its_single_read_sigma():
    # 8e6 e-/s: J1 = B4 holds 8000 e-; J2 = B4 + B3 = 16 000 e- overflows a 12 000 e- floating diffusion
    c = IDEAL.model_copy(update={"fd_full_well_e": 12_000.0})
    out = simulate_reads(flat(8e6 * SLOTS_T, 5000, 3), CUM_READS, c, np.random.default_rng(11))
    res = merge_hdr(out.reads_dn, CUM_T, c, method="ramp_fit", cumulative=True, saturated=out.saturated)
    one = res.n_used == 1
    assert one.mean() > 0.99
    x = dn_to_electrons(out.reads_dn[0], c)[one]
    np.testing.assert_allclose(res.rate_e_per_s[one], x / CUM_T[0], rtol=1e-12)
    lam = np.maximum(res.rate_e_per_s[one], 0)
    np.testing.assert_allclose(
        res.sigma_temporal_e_per_s[one],
        np.sqrt(lam * CUM_T[0] + quantization_read_variance_e2(c)) / CUM_T[0],
        rtol=1e-12,
    )


@pytest.mark.parametrize("method", ["ramp_fit", "inverse_variance", "debevec"])
def test_hdr_with_zero_read_noise(method):
    """read_noise_e = 0: only quantization (1/12 DN^2) is left in the read variance, never 0."""
    c = IDEAL.model_copy(update={"read_noise_e": 0.0})
    assert quantization_read_variance_e2(c) == pytest.approx(1 / (12 * 0.4**2))
    dark = simulate_reads(flat([0.0] * 4, 100, 3), CUM_READS, c, np.random.default_rng(12))
    res = merge_hdr(dark.reads_dn, CUM_T, c, method=method, cumulative=True, saturated=dark.saturated)
    assert (
        np.all(res.rate_e_per_s == 0.0)
        and np.all(np.isfinite(res.sigma_temporal_e_per_s))
        and np.all(res.sigma_temporal_e_per_s > 0)
    )
    n = 20_000
    out = simulate_reads(flat(1e5 * SLOTS_T, n, 1), CUM_READS, c, np.random.default_rng(13))
    res = merge_hdr(out.reads_dn, CUM_T, c, method=method, cumulative=True, saturated=out.saturated)
    se = np.sqrt(1e5 / CUM_T[-1] / n) * 3  # generous: debevec and inverse_variance are not efficient here
    assert abs(res.rate_e_per_s.mean() - 1e5) < N_SIGMA * se


# =============================================================================== accumulation
def test_many_strata_accumulate_like_a_compensated_sum():
    """20 000 strata, weights from 1e-9 s to 1 s, float32 radiance over 6 decades: the float64
    accumulation matches math.fsum (exactly rounded) to 1e-13 relative."""
    rng = np.random.default_rng(21)
    J, K, G = 20_000, 2, 2
    w = 10.0 ** rng.uniform(-9, 0, size=(J, K, G))
    rad = (10.0 ** rng.uniform(-3, 3, size=(J, G, 2, 2, 1))).astype(np.float32)
    out = np.zeros((K, 2, 2, 1))
    for j in range(J):
        accumulate(w[j], rad[j], out)
    terms = w[:, :, :, None, None, None] * rad.astype(np.float64)[:, None]  # (J, K, G, 2, 2, 1)
    ref = np.zeros_like(out)
    for idx in np.ndindex(out.shape):
        k = idx[0]
        ref[idx] = math.fsum(terms[(slice(None), k, slice(None), *idx[1:])].ravel())
    rel = np.abs(out - ref) / ref
    assert rel.max() < 1e-13, rel.max()


def test_accumulate_adds_into_its_output_as_the_product_made_apart_would():
    """accumulate's one BLAS call (dgemm, beta 1, into the output's memory) gives the bits of the
    product made apart and then added, for float32 radiance widened into a given array or a new one,
    and for float64 radiance; an output that is not C-contiguous is refused, not silently copied."""
    rng = np.random.default_rng(22)
    K, G, H, W, C = 4, 3, 5, 7, 3
    w = rng.uniform(0, 1e-3, size=(K, G))
    rad32 = rng.uniform(0, 50, size=(G, H, W, C)).astype(np.float32)
    start = rng.uniform(0, 1, size=(K, H, W, C))
    want = start + (w @ rad32.reshape(G, -1).astype(np.float64)).reshape(start.shape)
    for rad, buffer in ((rad32, None), (rad32, np.empty((G + 1, H, W, C))), (rad32.astype(np.float64), None)):
        out = start.copy()
        accumulate(w, rad, out, buffer)
        np.testing.assert_array_equal(out, want)
    with pytest.raises(ValueError, match="C-contiguous"):
        accumulate(w, rad32, np.zeros((W, H, K, C)).transpose(2, 1, 0, 3))


# =============================================================================== invariants
class ConstantRenderer:
    """Stands in for the Mitsuba renderer: radiance L_g of each group, the same at every time."""

    channels = ("R", "G", "B")
    width, height = 3, 2

    def __init__(self, radiance: dict[str, float]):
        self.radiance = radiance

    def render(self, t_s, spp, seed, groups, pattern=None):
        out = np.empty((len(groups), self.height, self.width, 3), np.float32)
        for i, g in enumerate(groups):
            out[i] = self.radiance[g]
        return out


@settings(max_examples=25, deadline=None)
@given(
    durs=st.lists(st.integers(1, 40), min_size=1, max_size=5),
    buckets=st.lists(st.integers(-1, 2), min_size=5, max_size=5),
    periods=st.integers(1, 100_000),
    level=st.floats(1e-3, 1e3).map(lambda x: float(np.float32(x))),  # what a float32 render holds
)
def test_electrons_over_all_buckets_equal_incident_times_gated_fraction(durs, buckets, periods, level):
    from mbcapture.exposure.integrate import integrate
    from mbcapture.exposure.plan import Plan

    slots = tuple(SlotSeconds(buckets[i], Fraction(d, 10**6)) for i, d in enumerate(durs))
    if all(s.bucket == DRAIN for s in slots):
        slots += (SlotSeconds(0, Fraction(1, 10**6)),)
    lit = tuple(sorted({s.bucket for s in slots if s.bucket != DRAIN}))
    tl = build_timeline([SegmentSeconds(Fraction(0), slots, periods)], [ReadEvent("J", lit)], 3, "custom")
    span = tl.end_tick - tl.start_tick
    edges = np.unique(np.linspace(tl.start_tick, tl.end_tick, 7).round().astype(np.int64))
    w = tl.weights_ticks(edges, ("field",), frozenset())
    plan = Plan(
        starts_ticks=edges[:-1],
        ends_ticks=edges[1:],
        times_s=np.zeros(len(edges) - 1),
        weights_s=w.astype(np.float64) * float(tl.tick_s),
        groups=("field",),
        buckets_read=(0, 1, 2),
        spp=np.full(len(edges) - 1, 2),
        max_motion_px=1.0,
        motion_px_total=0.0,
        coarsened=False,
        left_out_groups=(),
    )
    exposure = integrate(ConstantRenderer({"field": level}), plan, 3, np.random.SeedSequence(0)).exposure
    gated_ticks = sum(s.ticks for s in tl.segments[0].slots if s.bucket != DRAIN) * periods
    gated_fraction = Fraction(gated_ticks, span)
    incident = level * float(span * tl.tick_s)  # radiant exposure of an always-open pixel
    assert exposure.sum(axis=0) == pytest.approx(np.full((2, 3, 3), incident * float(gated_fraction)), rel=1e-12)
    # and each bucket holds its own gated share, exactly in ticks
    for k in range(3):
        assert exposure[k, 0, 0, 0] == pytest.approx(level * float(tl.exposure_ticks(k) * tl.tick_s), rel=1e-12, abs=0)


@settings(max_examples=40, deadline=None)
@given(
    rates=st.lists(st.floats(0.0, 3e4), min_size=4, max_size=4),
    parasitic=st.floats(0.0, 0.1),
    cti=st.floats(0.0, 0.01),
    fd_well=st.floats(5e3, 5e4),
    seed=st.integers(0, 2**32 - 1),
)
def test_cumulative_reads_never_decrease(rates, parasitic, cti, fd_well, seed):
    """Zero read noise: J_{i+1} >= J_i in every pixel, whatever saturates (buckets, FD, ADC)."""
    c = SensorConfig(read_noise_e=0.0, parasitic_light=parasitic, transfer_inefficiency=cti, fd_full_well_e=fd_well)
    out = simulate_reads(flat(rates, 64, 3), CUM_READS, c, np.random.default_rng(seed), storage_s=[1e-3] * 4)
    assert np.all(np.diff(out.reads_dn, axis=0) >= 0)
    assert np.all(np.diff(out.saturated.astype(int), axis=0) >= 0)  # once saturated, later reads are too


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**63 - 1), rate=st.floats(0.0, 1e8))
def test_same_seed_same_bits(seed, rate):
    c = SensorConfig(parasitic_light=0.01, transfer_inefficiency=1e-3)
    a = simulate_reads(flat(rate * SLOTS_T, 16, 3), CUM_READS, c, np.random.default_rng(seed), storage_s=[0.01] * 4)
    b = simulate_reads(flat(rate * SLOTS_T, 16, 3), CUM_READS, c, np.random.default_rng(seed), storage_s=[0.01] * 4)
    assert a.reads_dn.tobytes() == b.reads_dn.tobytes() and a.electrons.tobytes() == b.electrons.tobytes()
    ra = merge_hdr(a.reads_dn, CUM_T, c, method="ramp_fit", cumulative=True, saturated=a.saturated)
    rb = merge_hdr(b.reads_dn, CUM_T, c, method="ramp_fit", cumulative=True, saturated=b.saturated)
    assert ra.rate_e_per_s.tobytes() == rb.rate_e_per_s.tobytes()


# =============================================================================== bad input
BAD_INPUT = [
    # (case, config file text or None for tiny_hdr.yaml, --set overrides, text the message must contain)
    ("malformed YAML", "scene: {name: flatfield\nrender: [1, 2\n", [], "malformed YAML"),
    ("unknown key", "scene: {name: flatfield}\nrender: {widht: 32}\n", [], "render.widht: unknown key"),
    ("wrong type", None, ["capture.periods=many"], "capture.periods"),
    ("negative duration", None, ["capture.unit_exposure_s=-0.001"], "capture.unit_exposure_s"),
    (
        "zero duration",
        None,
        ["capture.protocol=custom", "capture.schedule={slots: [{bucket: 1, duration_s: 0}], reads: [{buckets: [1]}]}"],
        "capture.schedule.slots.0.duration_s",
    ),
    (
        "infinite duration",
        None,
        [
            "capture.protocol=custom",
            "capture.schedule={slots: [{bucket: 1, duration_s: .inf}], reads: [{buckets: [1]}]}",
        ],
        "capture.schedule.slots.0.duration_s: expected a finite number",
    ),
    ("nan phase", None, ["scene.phase_s=.nan"], "scene.phase_s: expected a finite number"),
    ("zero periods", None, ["capture.periods=0"], "capture.periods"),
    (
        "too many buckets",
        None,
        [
            "sensor.bucket_count=2",
            "capture.protocol=interleaved_hdr",
            "capture.protocol=custom",
            "capture.schedule={slots: [{bucket: 3, duration_s: 0.001}], reads: [{buckets: [3]}]}",
        ],
        "needs 3 buckets but sensor.bucket_count is 2",
    ),
    (
        "read never lit",
        None,
        [
            "capture.protocol=custom",
            "capture.schedule={slots: [{bucket: 1, duration_s: 0.001}], reads: [{buckets: [2]}]}",
        ],
        "never collect light",
    ),
    (
        "2^62 ticks",
        None,
        [
            "capture.protocol=custom",
            "capture.periods=10000000",
            "capture.schedule={slots: [{bucket: 1, duration_s: 0.3333333333333333}, {bucket: 2, duration_s: 0.001}], "
            "reads: [{buckets: [1]}]}",
        ],
        "2^62 ticks",
    ),
    ("missing scene", None, ["scene.name=atlantis"], "scene.name: unknown scene 'atlantis'"),
    ("missing config file", "MISSING", [], "config file not found"),
]


def run_cli(argv, capsys):
    from mbcapture.cli import main

    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return rc, err


@pytest.mark.parametrize("case,text,overrides,expect", BAD_INPUT, ids=[c[0] for c in BAD_INPUT])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, case, text, overrides, expect):
    if text is None:
        config = TINY
    elif text == "MISSING":
        config = tmp_path / "nope.yaml"
    else:
        config = tmp_path / "bad.yaml"
        config.write_text(text)
    out = tmp_path / "out"
    sets = [a for o in ["render.width=16", "render.height=12", "render.spp=2", *overrides] for a in ("--set", o)]
    rc, err = run_cli(["run", config, "--out", out, "--quiet", *sets], capsys)
    assert rc == 2, err
    assert err.strip().count("\n") == 0 and err.startswith("mbcapture: error: ")
    assert expect in err, err
    assert not out.exists()


def test_unwritable_output_folder(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc, err = run_cli(["run", TINY, "--out", blocker / "sub", "--quiet"], capsys)
    assert rc == 2 and "is a file, not a folder" in err and err.strip().count("\n") == 0
    if os.geteuid() == 0:
        pytest.skip("root can write into a read-only folder: the permission case needs a normal user")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        rc, err = run_cli(["run", TINY, "--out", ro / "out", "--quiet"], capsys)
        assert rc == 2 and "is not writable" in err and not (ro / "out").exists()
    finally:
        ro.chmod(0o755)


def test_exit_status_is_2_from_a_real_process(tmp_path):
    out = tmp_path / "o"
    proc = subprocess.run(
        [sys.executable, "-m", "mbcapture", "run", TINY, "--out", out, "--set", "capture.periods=0"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "capture.periods" in proc.stderr
    assert not out.exists()


# =============================================================================== interrupted runs
def test_stale_staging_of_dead_processes_only_is_removed(tmp_path):
    from mbcapture.output.io import remove_stale_staging

    host = socket.gethostname()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    names = {
        "dead": f".staging-{host}-{dead.pid}-abc123",
        "alive": f".staging-{host}-{os.getppid()}-def456",
        "other_host": f".staging-elsewhere.example-{dead.pid}-ghi789",
        "old_format": ".staging-xyz_12",
    }
    for n in names.values():
        (tmp_path / n).mkdir()
        (tmp_path / n / "hdr.exr").write_bytes(b"partial")
    (tmp_path / "hdr.exr").write_bytes(b"previous run")
    assert remove_stale_staging(tmp_path) == [names["dead"]]
    left = {p.name for p in tmp_path.iterdir()}
    assert left == {names["alive"], names["other_host"], names["old_format"], "hdr.exr"}


SLOW_WRITER = textwrap.dedent("""
    import sys, time
    import mbcapture.output.io as mio
    real = mio.write_png
    def slow(*a, **k):
        real(*a, **k)
        open(sys.argv[1], "w").close()  # tells the test that a file is in the staging folder
        time.sleep(60)
    mio.write_png = slow
    from mbcapture.cli import main
    sys.exit(main(sys.argv[2:]))
""")


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def start_slow_run(tmp_path, out, seed):
    flag = tmp_path / f"flag{seed}"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            SLOW_WRITER,
            flag,
            "run",
            TINY,
            "--out",
            out,
            "--quiet",
            "--set",
            "render.width=16",
            "--set",
            "render.height=12",
            "--set",
            "render.spp=2",
            "--set",
            f"seed={seed}",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not flag.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the run never reached its output stage"
        time.sleep(0.05)
    return proc


@pytest.mark.slow
@pytest.mark.render
def test_killed_and_terminated_runs_keep_previous_outputs(tmp_path):
    from mbcapture import run_capture

    out = tmp_path / "out"
    run_capture(load_config(TINY, ["render.width=16", "render.height=12", "render.spp=2"]), out, progress=False)
    before = snapshot(out)
    assert "report.json" in before and "hdr.exr" in before

    # SIGKILL while the new run's files are being written: nothing of it reaches the folder
    proc = start_slow_run(tmp_path, out, seed=5)
    stale = [p.name for p in out.iterdir() if p.name.startswith(".staging-")]
    assert len(stale) == 1 and any((out / stale[0]).iterdir())  # its half-finished files are there, hidden
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert snapshot(out) == before
    assert [p.name for p in out.iterdir() if p.name.startswith(".staging-")] == stale  # nothing cleans up after SIGKILL

    # SIGTERM: the CLI treats it like Ctrl-C: exit 130, staging removed, outputs untouched
    proc = start_slow_run(tmp_path, out, seed=6)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err
    assert snapshot(out) == before
    # the killed run's folder is still there (this run ended before committing anything)...
    # ... and the next successful run removes it and replaces every file
    run_capture(
        load_config(TINY, ["render.width=16", "render.height=12", "render.spp=2", "seed=7"]), out, progress=False
    )
    after = snapshot(out)
    assert not any(p.name.startswith(".staging-") for p in out.iterdir())
    assert set(after) == set(before) and after["report.json"] != before["report.json"]


@pytest.mark.render
def test_same_seed_same_capture_bit_for_bit():
    from mbcapture import run_capture

    c = load_config(TINY, ["render.width=16", "render.height=12", "render.spp=2", "render.max_motion_px=4"])
    a, b = run_capture(c, progress=False), run_capture(c, progress=False)
    assert a.reads_dn.tobytes() == b.reads_dn.tobytes()
    assert a.bucket_exposure.tobytes() == b.bucket_exposure.tobytes()
    assert all(a.images[k].tobytes() == b.images[k].tobytes() for k in a.images)


@pytest.mark.render
@pytest.mark.parametrize("radiance,expect", [(0.0, "black"), (6.5e5, "saturated")])
def test_flat_field_at_zero_and_a_million_full_wells(tmp_path, radiance, expect):
    """End to end at 32x24: zero radiance and ~1e6 x the full well in the 8 ms read."""
    from mbcapture import run_capture
    from mbcapture.output.io import read_exr

    c = load_config(
        None,
        [
            "scene.name=flatfield",
            f"scene.radiance=[{radiance}, {radiance}, {radiance}]",
            "render.width=32",
            "render.height=24",
            "render.spp=2",
        ],
    )
    res = run_capture(c, tmp_path / "o", progress=False)
    img = read_exr(tmp_path / "o" / "hdr.exr")
    assert all(np.all(np.isfinite(v[np.isfinite(v)])) for v in img.values())
    assert np.all(np.isfinite(res.images["radiance"]))
    if expect == "black":
        assert not res.saturated.any() and res.images["valid"].all()
        assert abs(float(res.images["radiance"].mean())) < 1e-3
    else:
        e_full = res.buckets_e.sum(axis=0).mean()
        assert e_full > 1e5 * c.sensor.full_well_e
        assert res.saturated.all() and not res.images["valid"].any()
        assert np.all(res.images["radiance"] > 0)


# =============================================================================== applications
def test_flash_a_million_times_brighter_than_ambient():
    """flash_no_flash on synthetic radiance: flash-only = F - A stays exact to float64 rounding whichever
    dominates (relative error <= ratio x 1.1e-16; a float32 pipeline would lose ratio x 6e-8)."""
    from mbcapture.apps.flash_no_flash import FlashNoFlashParams, components, enhance

    rng = np.random.default_rng(31)
    a = rng.uniform(0.5, 1.0, (24, 32, 3))
    for ratio in (1e6, 1e-6):  # flash 1e6 x ambient, then ambient 1e6 x flash
        f_only = ratio * rng.uniform(0.5, 1.0, (24, 32, 3))
        f = a + f_only
        c = components(a, f, np.zeros((24, 32), bool), FlashNoFlashParams())
        got = c.flash - c.ambient
        rel = np.abs(got - f_only) / f_only
        assert rel.max() < max(1.0, 1.0 / ratio) * 4 * np.finfo(float).eps, rel.max()
        for name in ("a_nr", "a_base", "f_detail", "mask"):
            assert np.all(np.isfinite(getattr(c, name))), name
        assert 0.0 <= c.mask.min() and c.mask.max() <= 1.0
        assert a.min() - 1e-9 <= c.a_nr.min() and c.a_nr.max() <= a.max() + 1e-9  # a weighted mean of A
        assert np.all(np.isfinite(enhance(c, "petschnigg")))


def test_multi_flash_ratio_images_where_the_max_is_zero():
    """Pixels that no flash lights (max = 0) get ratio 0, are invalid and never edges; no NaN."""
    from mbcapture.apps.multi_flash import flash_images
    from mbcapture.reconstruct.depth_edges import Epipole, max_composite, raskar_depth_edges

    eps = [
        Epipole(False, (1.0, 0.0)),
        Epipole(False, (-1.0, 0.0)),
        Epipole(False, (0.0, 1.0)),
        Epipole(False, (0.0, -1.0)),
    ]
    d = raskar_depth_edges(np.zeros((4, 24, 32, 3)), eps)
    assert np.all(d.ratios == 0.0) and not d.valid.any() and not d.edges.any()
    rng = np.random.default_rng(32)
    imgs = rng.uniform(0.5, 1.0, (4, 24, 32, 3))
    imgs[:, :, :10] = 0.0  # a black region
    d = raskar_depth_edges(imgs, eps)
    assert np.all(np.isfinite(d.ratios)) and not d.valid[:, :10].any() and not d.edges[:, :10].any()
    assert np.all(d.ratios[:, :, 10:] <= 1.0) and np.allclose(d.ratios.max(axis=0)[:, 10:], 1.0)
    # reads with no light at all, ambient subtracted: zero images, a zero composite
    fi = flash_images(np.zeros((5, 24, 32, 3)), np.ones(5), np.ones(3), [0, 1, 2, 3], 4)
    assert np.all(fi == 0.0) and np.all(max_composite(fi) == 0.0)


@pytest.mark.parametrize("noise_e", [0.0, 30.0])
def test_matte_where_the_flash_adds_nothing(noise_e):
    """flash_matting with identical flash and no-flash light: no foreground is found, alpha = 0."""
    from mbcapture.apps.flash_matting import FlashMattingParams, flash_only_image
    from mbcapture.reconstruct.matting import estimate_alpha, make_trimap, trimap_cue

    rng = np.random.default_rng(33)
    p = FlashMattingParams()
    lit = np.full((24, 32, 3), 2.0)  # electrons in each 2 ms read
    fl = lit + noise_e * rng.standard_normal(lit.shape)
    nf = lit + noise_e * rng.standard_normal(lit.shape)
    fo = flash_only_image(fl, 2e-3, nf, 2e-3, np.ones(3))
    if noise_e == 0.0:
        assert np.all(fo == 0.0)
    for kind in ("flash_ratio", "flash_only"):
        cue = trimap_cue(fo, nf / 2e-3, kind, p.trimap_reference_percentile, p.trimap_ratio_eps)
        assert np.all(np.isfinite(cue))
        tri = make_trimap(cue, p.trimap_fg_fraction, p.trimap_bg_fraction, p.trimap_open_px, p.trimap_erode_px)
        assert not (tri == 1.0).any()
        alpha = estimate_alpha(np.clip(fl, 0, 1), tri, "closed_form")
        assert np.all(alpha == 0.0)
