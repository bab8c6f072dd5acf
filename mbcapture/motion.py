"""Metronome needle dynamics: a physical (nonlinear) pendulum, optionally damped, or a sine.

Model
-----
The needle with its sliding weight is a compound pendulum; its angle from the vertical obeys

    theta'' + gamma * theta' + omega0**2 * sin(theta) = 0            (theta in rad, t in s)

with ``omega0 = sqrt(m g d / I)`` set by the weight's position. A metronome's tempo fixes the
*period*, not omega0, and the nonlinear period grows with the amplitude A:

    T = 4 K(m) / omega0,    m = k**2,  k = sin(A / 2)

(K: complete elliptic integral of the first kind, ``scipy.special.ellipk(m)``). Given the tempo
(one beat per half period: ``T = 2 * 60 / tempo_bpm``) and A, :class:`Pendulum` chooses omega0
so that the nonlinear period is exactly T.

Undamped motion uses the exact closed form (Jacobi elliptic functions, ``scipy.special.ellipj``)

    theta(t) = 2 asin(k sn(u, m)),   theta'(t) = 2 k omega0 cn(u, m),   u = omega0 * tau,

evaluated with tau reduced modulo T so that accuracy does not decay with time. A damped needle
(``gamma > 0``) is integrated with ``solve_ivp`` (DOP853, rtol 1e-10, atol 1e-12); its dense
solution is cached and extended when later times are asked for.

Phase convention
----------------
``tau = t_s + phase_s``. At tau = 0 the needle passes through the vertical (theta = 0) moving
towards positive theta with the speed it has at the bottom of an amplitude-A swing; it reaches
theta = +A at tau = T/4, crosses 0 again at T/2 and reaches -A at 3T/4. The ``"sine"`` model,
``theta = A sin(2 pi tau / T)``, has the same convention; it is the small-amplitude limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipj, ellipk

MotionModel = Literal["pendulum", "sine"]


def tempo_period_s(tempo_bpm: float) -> float:
    """Full swing period (s) of a metronome beating ``tempo_bpm`` (a beat = half a period)."""
    if tempo_bpm <= 0:
        raise ValueError("tempo_bpm must be > 0")
    return 2.0 * 60.0 / tempo_bpm


def nonlinear_period_s(omega0_rad_per_s: float, amplitude_rad: float) -> float:
    """Exact period (s) of an undamped pendulum: 4 K(sin^2(A/2)) / omega0."""
    k = math.sin(amplitude_rad / 2.0)
    return 4.0 * float(ellipk(k * k)) / omega0_rad_per_s


@dataclass(frozen=True)
class Pendulum:
    """Needle angle theta(t) in rad; see the module docstring for the model and phase.

    amplitude_rad
        Swing amplitude A (initial amplitude if damped), 0 < A < pi.
    period_s
        Period T of the undamped swing at amplitude A (the tempo's period).
    model
        ``"pendulum"`` (nonlinear, exact) or ``"sine"``.
    phase_s
        Pendulum time at scene time 0: tau = t_s + phase_s.
    damping_per_s
        gamma >= 0 in theta'' + gamma theta' + omega0^2 sin(theta) = 0 (pendulum model only).
    """

    amplitude_rad: float
    period_s: float
    model: MotionModel = "pendulum"
    phase_s: float = 0.0
    damping_per_s: float = 0.0
    _dense: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.amplitude_rad < math.pi:
            raise ValueError("amplitude_rad must be in (0, pi)")
        if self.period_s <= 0:
            raise ValueError("period_s must be > 0")
        if self.model not in ("pendulum", "sine"):
            raise ValueError(f"model must be 'pendulum' or 'sine', not {self.model!r}")
        if self.damping_per_s < 0:
            raise ValueError("damping_per_s must be >= 0")
        if self.damping_per_s > 0 and self.model != "pendulum":
            raise ValueError("damping needs model='pendulum'")

    @classmethod
    def from_tempo(cls, tempo_bpm: float, amplitude_deg: float, **kwargs) -> "Pendulum":
        """A metronome at ``tempo_bpm`` beats per minute swinging +-``amplitude_deg``."""
        return cls(math.radians(amplitude_deg), tempo_period_s(tempo_bpm), **kwargs)

    @property
    def k(self) -> float:
        """Elliptic modulus k = sin(A/2)."""
        return math.sin(self.amplitude_rad / 2.0)

    @property
    def omega0_rad_per_s(self) -> float:
        """Small-angle angular frequency sqrt(g_eff / L) giving the nonlinear period T at A."""
        if self.model == "sine":
            return 2.0 * math.pi / self.period_s
        return 4.0 * float(ellipk(self.k**2)) / self.period_s

    # -- evaluation ---------------------------------------------------------------------------
    def state(self, t_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(theta rad, theta' rad/s) at scene times ``t_s`` (any shape, same shape out)."""
        t = np.asarray(t_s, dtype=float)
        tau = t + self.phase_s
        A, T = self.amplitude_rad, self.period_s
        if self.model == "sine":
            w = 2.0 * math.pi / T
            phase = w * np.mod(tau, T)
            return A * np.sin(phase), A * w * np.cos(phase)
        if self.damping_per_s > 0:
            return self._damped_state(tau)
        k, w0 = self.k, self.omega0_rad_per_s
        sn, cn, _dn, _ph = ellipj(w0 * np.mod(tau, T), k * k)
        return 2.0 * np.arcsin(k * sn), 2.0 * k * w0 * cn

    def angle_rad(self, t_s: np.ndarray | float) -> np.ndarray:
        """Needle angle theta (rad) from the vertical at scene times ``t_s``."""
        return self.state(t_s)[0]

    def angular_velocity_rad_per_s(self, t_s: np.ndarray | float) -> np.ndarray:
        """theta' (rad/s) at scene times ``t_s``."""
        return self.state(t_s)[1]

    def energy_per_inertia(self, t_s: np.ndarray | float) -> np.ndarray:
        """E / I = theta'^2 / 2 + omega0^2 (1 - cos theta), rad^2/s^2 (constant if undamped)."""
        th, om = self.state(t_s)
        return 0.5 * om**2 + self.omega0_rad_per_s**2 * (1.0 - np.cos(th))

    def max_angular_speed_rad_per_s(self) -> float:
        """Largest |theta'| (at the bottom of the swing): 2 k omega0, or A w for the sine."""
        if self.model == "sine":
            return self.amplitude_rad * 2.0 * math.pi / self.period_s
        return 2.0 * self.k * self.omega0_rad_per_s

    # -- damped: ODE with a cached dense solution ---------------------------------------------
    def _damped_state(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = float(np.min(tau, initial=0.0)), float(np.max(tau, initial=0.0))
        theta = np.empty_like(tau)
        omega = np.empty_like(tau)
        for sign, end in ((1.0, hi), (-1.0, lo)):
            sel = tau >= 0 if sign > 0 else tau < 0
            if not np.any(sel):
                continue
            sol = self._dense_solution(sign, abs(end))
            y = sol(tau[sel])
            theta[sel], omega[sel] = y[0], y[1]
        return theta, omega

    def _dense_solution(self, sign: float, span_s: float):
        cached = self._dense.get(sign)
        if cached is not None and cached[0] >= span_s:
            return cached[1]
        span = max(span_s * 1.5, 4.0 * self.period_s)  # grow geometrically: few re-solves
        w0sq, gamma = self.omega0_rad_per_s**2, self.damping_per_s

        def rhs(_t, y):
            return (y[1], -gamma * y[1] - w0sq * math.sin(y[0]))

        y0 = (0.0, 2.0 * self.k * self.omega0_rad_per_s)
        sol = solve_ivp(rhs, (0.0, sign * span), y0, method="DOP853", rtol=1e-10, atol=1e-12,
                        dense_output=True)
        if not sol.success:
            raise RuntimeError(f"pendulum integration failed: {sol.message}")
        self._dense[sign] = (span, sol.sol)
        return sol.sol
