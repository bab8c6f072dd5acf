"""Pendulum model of the metronome needle (mbcapture.scene.pendulum): no Mitsuba needed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.special import ellipk

from mbcapture.scene.pendulum import Pendulum, nonlinear_period_s, tempo_period_s


def test_tempo_beats_are_half_periods():
    assert tempo_period_s(120) == pytest.approx(1.0)
    assert tempo_period_s(60) == pytest.approx(2.0)


@pytest.mark.parametrize("amp_deg", [5.0, 30.0, 60.0, 120.0])
def test_period_matches_elliptic_integral(amp_deg):
    p = Pendulum.from_tempo(100.0, amp_deg)
    A = math.radians(amp_deg)
    # omega0 was chosen so that the nonlinear period equals the tempo's period
    assert nonlinear_period_s(p.omega0_rad_per_s, A) == pytest.approx(p.period_s, rel=1e-12)
    assert p.omega0_rad_per_s == pytest.approx(4 * ellipk(math.sin(A / 2) ** 2) / p.period_s)
    # Measure the period of the closed-form solution: the upward zero crossing after one
    # period, found by Newton's method from a perturbed guess.
    t = 1.001 * p.period_s
    for _ in range(20):
        th, om = p.state(t)
        t -= float(th) / float(om)
    assert t == pytest.approx(p.period_s, rel=1e-8)
    # phase convention: 0 at t=0 going up, +A at T/4, 0 at T/2, -A at 3T/4
    T = p.period_s
    th = p.angle_rad(np.array([0.0, T / 4, T / 2, 3 * T / 4]))
    np.testing.assert_allclose(th, [0.0, A, 0.0, -A], atol=1e-10)
    assert p.angular_velocity_rad_per_s(0.0) > 0


def test_closed_form_solves_the_ode():
    p = Pendulum.from_tempo(120.0, 40.0)
    w0sq = p.omega0_rad_per_s**2
    times = np.linspace(0.0, 3 * p.period_s, 301)
    sol = solve_ivp(
        lambda t, y: (y[1], -w0sq * math.sin(y[0])),
        (0.0, times[-1]),
        (0.0, p.angular_velocity_rad_per_s(0.0)),
        method="DOP853",
        rtol=1e-12,
        atol=1e-13,
        t_eval=times,
    )
    np.testing.assert_allclose(p.angle_rad(times), sol.y[0], atol=1e-9)
    np.testing.assert_allclose(p.angular_velocity_rad_per_s(times), sol.y[1], atol=1e-8)


def test_energy_conserved_over_100_periods():
    p = Pendulum.from_tempo(120.0, 30.0)
    t = np.linspace(0.0, 100 * p.period_s, 20001)
    e = p.energy_per_inertia(t)
    e0 = p.omega0_rad_per_s**2 * (1 - math.cos(p.amplitude_rad))  # at rest at the turning point
    assert np.max(np.abs(e / e0 - 1.0)) < 1e-8


def test_small_amplitude_tends_to_sine():
    errs = []
    for amp_deg in (10.0, 1.0, 0.1):
        p = Pendulum.from_tempo(120.0, amp_deg)
        s = Pendulum.from_tempo(120.0, amp_deg, model="sine")
        t = np.linspace(0.0, 2.0, 501)
        errs.append(np.max(np.abs(p.angle_rad(t) - s.angle_rad(t))) / p.amplitude_rad)
    # relative deviation shrinks like A^2
    assert errs[0] < 3e-3 and errs[1] < errs[0] / 50 and errs[2] < errs[1] / 50


def test_phase_offset_shifts_time():
    p = Pendulum.from_tempo(90.0, 25.0)
    q = Pendulum.from_tempo(90.0, 25.0, phase_s=0.123)
    t = np.linspace(-1.0, 1.0, 11)
    np.testing.assert_allclose(q.angle_rad(t), p.angle_rad(t + 0.123), atol=1e-12)


def test_damped_decays_and_matches_undamped_when_light():
    light = Pendulum.from_tempo(120.0, 30.0, damping_per_s=1e-9)
    free = Pendulum.from_tempo(120.0, 30.0)
    t = np.linspace(-2.0, 2.0, 41)
    np.testing.assert_allclose(light.angle_rad(t), free.angle_rad(t), atol=1e-7)
    damped = Pendulum.from_tempo(120.0, 30.0, damping_per_s=0.5)
    e = damped.energy_per_inertia(np.array([0.0, 1.0, 2.0, 5.0]))
    assert np.all(np.diff(e) < 0)
    # energy of a lightly damped oscillator decays ~ exp(-gamma t)
    assert e[3] / e[0] == pytest.approx(math.exp(-0.5 * 5.0), rel=0.05)
    # later times extend the cached solution consistently
    assert damped.angle_rad(7.3) == pytest.approx(float(damped.angle_rad(np.array([0.0, 7.3]))[1]))


def test_vectorized_shapes_and_validation():
    p = Pendulum.from_tempo(120.0, 30.0)
    assert p.angle_rad(np.zeros((4, 5))).shape == (4, 5)
    with pytest.raises(ValueError):
        Pendulum(math.pi, 1.0)
    with pytest.raises(ValueError):
        Pendulum(0.5, 1.0, model="sine", damping_per_s=0.1)
