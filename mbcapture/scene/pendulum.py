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

evaluated with tau reduced modulo T so that accuracy does not decay with time. The angle is
computed as ``2 atan2(k sn, dn)`` (sin(theta/2) = k sn, cos(theta/2) = dn), which stays well
conditioned at the turning points where ``asin`` of a value near 1 would lose half the digits,
and K comes from ``ellipkm1(cos^2(A/2))`` so that amplitudes near pi keep the digits of 1 - m.
The argument of ``ellipj`` is reduced to [0, K] by the quarter-period symmetries (its error grows
with the argument).

Limit of the closed form: scipy's ``ellipj`` (Cephes) switches to a small-(1 - m) expansion for
m >= 1 - 1e-10, which is wrong over most of a period (measured: energy off by 1e23 at
A = 179.999 deg). Amplitudes with 1 - m = cos^2(A/2) < 1e-9, i.e. A > 179.9964 deg, are refused;
below that the closed form conserves energy to ~1e-15 (tests/test_stability.py).

Damping and escapement (integrated numerically)
-----------------------------------------------
With damping or an escapement the needle obeys

    theta'' = -omega0**2 sin(theta) - gamma theta' - kappa (E / E_A - 1) theta',
    E = theta'**2 / 2 + omega0**2 (1 - cos theta),   E_A = omega0**2 (1 - cos A)

(E is the energy per moment of inertia). ``kappa`` (``escapement_per_s``) models an ideal
escapement as energy regulation: dE/dt = -(gamma + kappa (E/E_A - 1)) theta'**2, so the swing
relaxes at a rate ~kappa towards the energy E_A (1 - gamma/kappa) and, without friction, onto
the exact free pendulum orbit of amplitude A, whose period is the elliptic 4 K / omega0: a
driven metronome keeps its tempo. ``start_amplitude_rad`` starts the needle (at the bottom, at
tau = 0) with the speed of a different amplitude, off that orbit.

These are integrated with ``solve_ivp`` and the dense solution is cached and extended when later
times are asked for. Large gamma (an overdamped needle: decay rates gamma and omega0^2/gamma) or
large kappa (a stiff escapement) make the equation stiff, and an explicit method would need
steps of ~1/(gamma + kappa) however slowly the needle moves. ``ode_method="auto"`` therefore
uses LSODA (ODEPACK: Adams while non-stiff, switching to the implicit BDF method with the
analytic Jacobian :meth:`Pendulum.jacobian` when it detects stiffness) when
(gamma + kappa) / omega0 > :data:`STIFF_RATIO`, and DOP853 otherwise; rtol 1e-10, atol 1e-12 rad
(rad/s). Measured on this machine (A = 30 deg, T = 0.5 s, 1 s of motion, against DOP853 at
rtol 1e-13): gamma = 1e4/s: DOP853 24155 right-hand-side calls, Radau 6805, LSODA 434 (error
1.3e-12 rad); escapement kappa = 1e4/s from 20 deg: DOP853 117362 calls (3.6 s), Radau 19955
(3.1 s, pure Python), LSODA 2118 (0.09 s, error 1.8e-9 rad). The explicit cost grows like
gamma * span; the implicit one does not. ``ode_method`` forces a method (e.g. ``"Radau"``).

Beyond gamma / omega0 > :data:`OVERDAMPED_RATIO` = 1e6 (no escapement) no ODE is solved: the
composite overdamped solution (fast decay of the initial speed, then the slow manifold
tan(theta/2) ~ exp(-omega0^2 tau / gamma)) is exact to O((omega0/gamma)^2). Without it LSODA
stalls at extreme gamma (measured: gamma = 1e300/s ran for > 5 min). Damped motion before
tau = 0 grows like exp(gamma |tau|); more than :data:`MAX_BACKWARD_DECAYS` decay times back is
refused with a ValueError (the energy e^(2 gamma |tau|) would overflow).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipj, ellipkm1

MotionModel = Literal["pendulum", "sine"]
OdeMethod = Literal["auto", "DOP853", "Radau", "BDF", "LSODA"]

STIFF_RATIO = 50.0
"""(gamma + kappa) / omega0 above which ``ode_method="auto"`` uses LSODA (implicit BDF when stiff)."""
ODE_RTOL = 1e-10
ODE_ATOL = 1e-12
OVERDAMPED_RATIO = 1e6
"""gamma / omega0 above which a damped needle (no escapement) uses the overdamped closed form."""
MAX_BACKWARD_DECAYS = 300.0
"""Largest gamma * |tau| before tau = 0 (damped motion grows like exp(gamma |tau|) backwards; its square, the energy, overflows near 354."""
MIN_ONE_MINUS_M = 1e-9
"""Smallest cos^2(A/2) = 1 - m accepted: scipy's ellipj is wrong for 1 - m <= 1e-10 (A > 179.9989 deg)."""


def tempo_period_s(tempo_bpm: float) -> float:
    """Full swing period (s) of a metronome beating ``tempo_bpm`` (a beat = half a period)."""
    if tempo_bpm <= 0:
        raise ValueError("tempo_bpm must be > 0")
    return 2.0 * 60.0 / tempo_bpm


def quarter_period_k(amplitude_rad: float) -> float:
    """K(m), m = sin^2(A/2), from the complementary parameter cos^2(A/2) (accurate as A -> pi)."""
    return float(ellipkm1(math.cos(amplitude_rad / 2.0) ** 2))


def nonlinear_period_s(omega0_rad_per_s: float, amplitude_rad: float) -> float:
    """Exact period (s) of an undamped pendulum: 4 K(sin^2(A/2)) / omega0."""
    return 4.0 * quarter_period_k(amplitude_rad) / omega0_rad_per_s


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
    escapement_per_s
        kappa >= 0: rate at which an ideal escapement restores the energy of amplitude A (see
        the module docstring; pendulum model only).
    start_amplitude_rad
        Amplitude whose bottom speed the needle has at tau = 0 (default: A). Only meaningful
        with damping or an escapement (the free pendulum always swings at A).
    ode_method
        ``"auto"`` (LSODA when stiff, else DOP853) or a ``solve_ivp`` method name.
    """

    amplitude_rad: float
    period_s: float
    model: MotionModel = "pendulum"
    phase_s: float = 0.0
    damping_per_s: float = 0.0
    escapement_per_s: float = 0.0
    start_amplitude_rad: float | None = None
    ode_method: OdeMethod = "auto"
    _dense: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.amplitude_rad < math.pi:
            raise ValueError("amplitude_rad must be in (0, pi)")
        if self.model == "pendulum" and math.cos(self.amplitude_rad / 2.0) ** 2 < MIN_ONE_MINUS_M:
            limit = math.degrees(math.pi - 2.0 * math.asin(math.sqrt(MIN_ONE_MINUS_M)))
            raise ValueError(
                f"amplitude_rad: {self.amplitude_rad!r} is within {math.pi - self.amplitude_rad:.3g} rad of pi; "
                f"the elliptic closed form is accurate only up to {limit:.4f} deg"
            )
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError("period_s must be finite and > 0")
        if not math.isfinite(self.phase_s):
            raise ValueError("phase_s must be finite")
        if self.model not in ("pendulum", "sine"):
            raise ValueError(f"model must be 'pendulum' or 'sine', not {self.model!r}")
        for name in ("damping_per_s", "escapement_per_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0")
        if (self.damping_per_s > 0 or self.escapement_per_s > 0) and self.model != "pendulum":
            raise ValueError("damping and escapement need model='pendulum'")
        a0 = self.start_amplitude_rad
        if a0 is not None and not 0.0 < a0 < math.pi:
            raise ValueError("start_amplitude_rad must be in (0, pi)")
        if self.ode_method not in ("auto", "DOP853", "Radau", "BDF", "LSODA"):
            raise ValueError(f"ode_method: unknown solve_ivp method {self.ode_method!r}")

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
        return 4.0 * quarter_period_k(self.amplitude_rad) / self.period_s

    @property
    def integrated(self) -> bool:
        """True when the motion is integrated numerically (damping or escapement)."""
        return self.model == "pendulum" and (self.damping_per_s > 0 or self.escapement_per_s > 0)

    @property
    def stiff(self) -> bool:
        """(gamma + kappa) / omega0 > STIFF_RATIO: the fastest decay outruns the swing."""
        return (self.damping_per_s + self.escapement_per_s) / self.omega0_rad_per_s > STIFF_RATIO

    @property
    def solver(self) -> str:
        """The ``solve_ivp`` method used for the integrated motion."""
        if self.ode_method != "auto":
            return self.ode_method
        return "LSODA" if self.stiff else "DOP853"

    @property
    def target_energy_per_inertia(self) -> float:
        """E_A = omega0^2 (1 - cos A) = 2 omega0^2 sin^2(A/2), rad^2/s^2."""
        return 2.0 * (self.omega0_rad_per_s * self.k) ** 2

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
        if self.integrated:
            return self._damped_state(tau)
        k, w0 = self.k, self.omega0_rad_per_s
        K = quarter_period_k(A)
        u = w0 * np.mod(tau, T)
        # reduce u to [0, K] (sn(u + 2K) = -sn(u), sn(2K - u) = sn(u), cn(2K - u) = -cn(u)): ellipj's
        # error grows with u, e.g. theta(T) = 3e-7 rad instead of 1e-13 at A = 179.996 deg without it
        half = u >= 2.0 * K
        sign = np.where(half, -1.0, 1.0)
        u = np.where(half, u - 2.0 * K, u)
        upper = u > K
        sn, cn, dn, _ph = ellipj(np.where(upper, 2.0 * K - u, u), k * k)
        sn, cn = sign * sn, sign * np.where(upper, -cn, cn)
        return 2.0 * np.arctan2(k * sn, dn), 2.0 * k * w0 * cn

    def angle_rad(self, t_s: np.ndarray | float) -> np.ndarray:
        """Needle angle theta (rad) from the vertical at scene times ``t_s``."""
        return self.state(t_s)[0]

    def angular_velocity_rad_per_s(self, t_s: np.ndarray | float) -> np.ndarray:
        """theta' (rad/s) at scene times ``t_s``."""
        return self.state(t_s)[1]

    def energy_per_inertia(self, t_s: np.ndarray | float) -> np.ndarray:
        """E / I = theta'^2 / 2 + omega0^2 (1 - cos theta), rad^2/s^2 (constant if undamped)."""
        th, om = self.state(t_s)
        return 0.5 * om**2 + 2.0 * self.omega0_rad_per_s**2 * np.sin(0.5 * th) ** 2  # 1 - cos, without cancellation

    def max_angular_speed_rad_per_s(self) -> float:
        """Largest |theta'| (at the bottom of the swing): 2 k omega0, or A w for the sine."""
        if self.model == "sine":
            return self.amplitude_rad * 2.0 * math.pi / self.period_s
        k = self.k
        if self.integrated and self.start_amplitude_rad is not None:
            k = max(k, math.sin(self.start_amplitude_rad / 2.0))  # energy only relaxes towards E_A
        return 2.0 * k * self.omega0_rad_per_s

    # -- damped / escapement: ODE with a cached dense solution ------------------------------
    @property
    def overdamped_closed_form(self) -> bool:
        """gamma / omega0 > OVERDAMPED_RATIO without escapement: the composite asymptotic solution
        is exact to O((omega0/gamma)^2) (< 1e-12 relative) and no ODE is solved."""
        return self.escapement_per_s == 0 and self.damping_per_s / self.omega0_rad_per_s > OVERDAMPED_RATIO

    def _overdamped_state(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fast phase theta = theta1 (1 - e^(-gamma tau)), theta1 = v0 / gamma, then the slow manifold
        theta' = -(omega0^2 / gamma) sin(theta): tan(theta/2) = tan(theta1/2) e^(-omega0^2 tau / gamma)."""
        g, w0sq = self.damping_per_s, self.omega0_rad_per_s**2
        a0 = self.amplitude_rad if self.start_amplitude_rad is None else self.start_amplitude_rad
        v0 = 2.0 * math.sin(a0 / 2.0) * math.sqrt(w0sq)
        th1 = v0 / g
        fast = np.exp(-g * tau)
        slow = 2.0 * np.arctan(math.tan(th1 / 2.0) * np.exp(-w0sq * tau / g))
        return slow - th1 * fast, v0 * fast - (w0sq / g) * np.sin(slow)

    def _damped_state(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = float(np.min(tau, initial=0.0)), float(np.max(tau, initial=0.0))
        if self.damping_per_s * -lo > MAX_BACKWARD_DECAYS:
            raise ValueError(
                f"damped pendulum: time {lo:.6g} s before tau = 0 is {self.damping_per_s * -lo:.3g} decay times back "
                f"(at most {MAX_BACKWARD_DECAYS:g}: the swing grows like exp(gamma |tau|) backwards); use phase_s >= 0"
            )
        if self.overdamped_closed_form:
            return self._overdamped_state(tau)
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

    def rhs(self, _t: float, y) -> tuple[float, float]:
        """(theta', theta'') of the damped, escapement-driven pendulum (module docstring)."""
        th, om = y[0], y[1]
        w0sq = self.omega0_rad_per_s**2
        drag = self.damping_per_s
        if self.escapement_per_s > 0:
            energy = 0.5 * om * om + 2.0 * w0sq * math.sin(0.5 * th) ** 2
            drag += self.escapement_per_s * (energy / self.target_energy_per_inertia - 1.0)
        return (om, -w0sq * math.sin(th) - drag * om)

    def jacobian(self, _t: float, y) -> np.ndarray:
        """d(rhs)/d(theta, theta'), for the implicit solvers."""
        th, om = y[0], y[1]
        w0sq = self.omega0_rad_per_s**2
        j10 = -w0sq * math.cos(th)
        j11 = -self.damping_per_s
        if self.escapement_per_s > 0:
            kap, ea = self.escapement_per_s, self.target_energy_per_inertia
            energy = 0.5 * om * om + 2.0 * w0sq * math.sin(0.5 * th) ** 2
            j10 -= kap * om * w0sq * math.sin(th) / ea  # dE/dtheta = omega0^2 sin(theta)
            j11 -= kap * (energy / ea - 1.0) + kap * om * om / ea  # dE/dtheta' = theta'
        return np.array([[0.0, 1.0], [j10, j11]])

    def solve(self, t_end_s: float, method: str | None = None, **kwargs):
        """``solve_ivp`` result from tau = 0 to ``t_end_s`` (either sign) with this pendulum's method
        and tolerances (dense output); keyword arguments go to ``solve_ivp``."""
        method = method or self.solver
        a0 = self.amplitude_rad if self.start_amplitude_rad is None else self.start_amplitude_rad
        y0 = (0.0, 2.0 * math.sin(a0 / 2.0) * self.omega0_rad_per_s)
        opts = dict(method=method, rtol=ODE_RTOL, atol=ODE_ATOL, dense_output=True)
        if method in ("Radau", "BDF", "LSODA"):
            opts["jac"] = self.jacobian
        opts.update(kwargs)
        sol = solve_ivp(self.rhs, (0.0, t_end_s), y0, **opts)
        if not sol.success:
            raise RuntimeError(f"pendulum integration failed ({method}): {sol.message}")
        return sol

    def _dense_solution(self, sign: float, span_s: float):
        cached = self._dense.get(sign)
        if cached is not None and cached[0] >= span_s:
            return cached[1]
        span = max(span_s * 1.5, 4.0 * self.period_s)  # grow geometrically: few re-solves
        if sign < 0 and self.damping_per_s > 0:
            span = max(span_s, min(span, MAX_BACKWARD_DECAYS / self.damping_per_s))
        sol = self.solve(sign * span)
        self._dense[sign] = (span, sol.sol)
        return sol.sol
