"""Emitter drive that varies continuously in time, integrated exactly against the gate schedule.

An emitter group's radiance is scaled by its drive

    drive(t) = c0 + sum_m a_m cos(2 pi f_m t + phi_m)          (t: scene time, s; dimensionless)

(lamps on AC mains flicker at twice the mains frequency: |sin(2 pi 50 t)|^2 = 0.5 - 0.5 cos(2 pi 100 t)).
The render weights need  integral gate_k(t) * drive(t) dt  over each time stratum. A gate is a
slot of duration d repeated every period P, N times; the integral over n = 0..N-1 occurrences
starting at A is, per cosine term, in closed form (a geometric series of complex exponentials):

    a d sinc(w d / 2) * D_N(w P) * cos(phi + w (A + d/2 + (N - 1) P / 2)),
    D_N(theta) = sin(N theta / 2) / sin(theta / 2)      (the Dirichlet kernel; = +-N when theta/2 = k pi)

so its cost does not grow with the number of periods. Times are integer ticks of an exact
rational length; every phase is reduced modulo one cycle in exact rational arithmetic before
the float cosine, so a capture 10^5 periods long loses no phase accuracy, and frequencies
commensurate with the slot period (where the series resonates) are handled exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache

import numpy as np

from ..errors import ConfigError


def _exact(x: float | Fraction | int) -> Fraction:
    return Fraction(x) if isinstance(x, (Fraction, int)) else Fraction(repr(float(x)))


@dataclass(frozen=True)
class Drive:
    """``c0 + sum_m a_m cos(2 pi f_m t + phi_m)``; ``terms`` are ``(a_m, f_m in Hz, phi_m in rad)``.

    The drive multiplies the group's rendered radiance, so ``c0`` is its time average: with
    ``c0 = 1`` the scene's radiance values are the lamp's mean radiance. It must stay >= 0
    (``c0 >= sum |a_m|``): a lamp does not emit negative light.
    """

    c0: float = 1.0
    terms: tuple[tuple[float, float, float], ...] = ()

    def __post_init__(self) -> None:
        terms = tuple((float(a), float(f), float(p)) for a, f, p in self.terms)
        object.__setattr__(self, "terms", terms)
        vals = [self.c0, *(x for t in terms for x in t)]
        if not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"drive: every coefficient must be finite (got c0={self.c0}, terms={terms})")
        if any(f <= 0 for _, f, _ in terms):
            raise ConfigError(f"drive: frequencies must be > 0 Hz (got {[f for _, f, _ in terms]})")
        if self.c0 < sum(abs(a) for a, _, _ in terms) * (1 - 1e-12):
            raise ConfigError(
                f"drive: c0={self.c0} < sum |a_m| = {sum(abs(a) for a, _, _ in terms)}: the drive would go negative"
            )

    @classmethod
    def mains_flicker(cls, mains_hz: float = 50.0, depth: float = 1.0, phase_rad: float = 0.0) -> "Drive":
        """A lamp on AC mains: power follows sin^2 of the mains, i.e. flickers at 2 x mains_hz.

        ``1 - depth cos(2 pi (2 mains_hz) t + phase_rad)``, mean 1; ``depth = 1`` is
        ``2 |sin(2 pi mains_hz t + phase_rad / 2)|^2`` (full modulation, e.g. an LED or fluorescent
        tube without smoothing), small depths model an incandescent filament's thermal inertia.
        """
        if not 0.0 <= depth <= 1.0:
            raise ConfigError(f"drive: flicker depth must be in [0, 1] (got {depth})")
        if mains_hz <= 0:
            raise ConfigError(f"drive: mains_hz must be > 0 (got {mains_hz})")
        return cls(1.0, ((-depth, 2.0 * mains_hz, phase_rad),) if depth > 0 else ())

    @property
    def is_constant(self) -> bool:
        return not self.terms

    def __call__(self, t_s) -> np.ndarray:
        """drive(t) at scene times ``t_s`` (s), float64 (for plots and brute-force checks)."""
        t = np.asarray(t_s, dtype=np.float64)
        out = np.full(t.shape, self.c0, dtype=np.float64)
        for a, f, p in self.terms:
            out += a * np.cos(2 * np.pi * f * t + p)
        return out


def _sin_cos_cycles(num: int, den: int) -> tuple[float, float]:
    """(sin 2 pi x, cos 2 pi x) for the exact x = num / den cycles (Python ints): reduced exactly
    modulo one cycle and to within 1/8 cycle of a quarter turn first, so that values near zero
    keep their full relative accuracy however many cycles x holds."""
    num %= den
    quarter = (8 * num + den) // (2 * den)  # round(4 x)
    r = (4 * num - quarter * den) / (4 * den)  # in [-1/8, 1/8], one correctly rounded division
    s, c = math.sin(2 * math.pi * r), math.cos(2 * math.pi * r)
    return ((s, c), (c, -s), (-s, -c), (-c, s))[quarter % 4]


@lru_cache(maxsize=256)
def _cycles_per_tick(f_hz: float, tick_s: Fraction) -> tuple[int, int]:
    x = _exact(f_hz) * tick_s
    return x.numerator, x.denominator


def periodic_oscillation_ticks(
    drive: Drive, tick_s: Fraction, start: int, duration: int, period: int, count: int
) -> float:
    """sum_m a_m * integral of cos(2 pi f_m t + phi_m) over the ``count`` intervals
    [start + n period, start + n period + duration), n = 0..count-1 (all in ticks), in ticks.

    The oscillating part only; the constant part is ``c0 * count * duration`` ticks (exact).
    Closed form, O(1) in ``count``; phases in exact integer arithmetic (f t = num t / den cycles).
    """
    if count <= 0 or duration <= 0:
        return 0.0
    total = 0.0
    # twice the midpoint of the first and last occurrences, in ticks (an integer)
    mid2 = 2 * start + duration + (count - 1) * period
    for a, f, phi in drive.terms:
        num, den = _cycles_per_tick(f, tick_s)
        x = math.pi * (num * duration / den)  # w d / 2, radians
        sinc = 1.0 if x == 0 else math.sin(x) / x
        if count == 1:
            dirichlet = 1.0
        elif (num * period) % den == 0:  # resonance: theta / 2 = k pi, D = N cos(N k pi) / cos(k pi)
            dirichlet = (
                count * _sin_cos_cycles(num * period * count, 2 * den)[1] / _sin_cos_cycles(num * period, 2 * den)[1]
            )
        else:  # D = sin(N theta / 2) / sin(theta / 2), theta / 2 = num period / (2 den) cycles
            dirichlet = _sin_cos_cycles(num * period * count, 2 * den)[0] / _sin_cos_cycles(num * period, 2 * den)[0]
        sin_m, cos_m = _sin_cos_cycles(num * mid2, 2 * den)  # phase of the mean occurrence midpoint
        total += a * duration * sinc * dirichlet * (cos_m * math.cos(phi) - sin_m * math.sin(phi))
    return total
