"""The indirect time-of-flight pixel: taps that demodulate modulated light (docs/tof.md).

An illuminator whose power follows a periodic waveform ``m(t)`` of frequency f (mean 1) lights the scene;
light that travels a path of optical length l arrives delayed by l / c, so with theta = 2 pi f l / c its
radiance at the pixel is ``L_p m(t - l / c)``. A tap is a bucket whose gate opens for a fraction ``d`` (the
duty) of every modulation period, centred on the demodulation phase phi. What it collects per second of
gated time, over one modulation period (nanoseconds, far below any slot of the schedule), is

    G_phi = sum_p L_p [1 + eps sum_h s_h m_h cos(h (theta_p - phi))]
          = L + eps sum_h s_h m_h (cos(h phi) C_h + sin(h phi) S_h),

    C_h = sum_p L_p cos(h theta_p),  S_h = sum_p L_p sin(h theta_p),  s_h = sin(pi h d) / (pi h d),

with m_h the waveform's cosine coefficients (sine: m_1 = 1; square of 50 % duty: 4 / (pi h) sin(pi h / 2), odd
h only), s_h the gate's (a box of duty d, per unit of gated time) and eps the demodulation contrast (the share
of the charge the gates route to the right tap at this frequency; 1 is ideal). L, C_h and S_h are what the
renderer writes for the modulated group (the ``phasor channels``,
:class:`mbcapture.render.integrator.GroupPath`): light transport is linear, so every tap of every phase and
duty is a linear combination of them and nothing is rendered per tap. Ambient light (every other group)
reaches every tap in proportion to its gated time only.

A capture names its taps as switchable groups ("phase groups", :class:`PhaseGroup`), one per frequency and
phase; the timeline weighs them like any flash, and the renderer turns the rendered basis into their images
(:meth:`Demodulation.combine`).

Here: the pixel designs (:data:`DESIGNS`), the phase groups and their coefficients. No Mitsuba.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

#: Speed of light in vacuum, m/s (exact, SI).
C_M_PER_S = 299_792_458.0


@dataclass(frozen=True)
class TapDesign:
    """How a pixel collects the phases of one frequency.

    taps        storage nodes the photodiode's charge alternates between within a modulation period
    sequential  the phases that do not fit in one sub-frame are taken in sub-frames one after another,
                each read out (``sensor.frame_readout_s``) before the next; else the sub-frames
                alternate every ``capture.periods``-th of the exposure, each into its own buckets
    duty        the share of a modulation period each tap's gate is open (1 / taps; a one-tap pixel
                drains the other half of each period)
    """

    taps: int
    sequential: bool

    @property
    def duty(self) -> float:
        return 0.5 if self.taps == 1 else 1.0 / self.taps


#: The named iToF protocols (registered by :mod:`mbcapture.apps.tof`).
DESIGNS: dict[str, TapDesign] = {
    "tof_4tap": TapDesign(4, sequential=False),
    "tof_2tap": TapDesign(2, sequential=False),
    "tof_2tap_sequential": TapDesign(2, sequential=True),
    "tof_1tap": TapDesign(1, sequential=True),
}


@dataclass(frozen=True)
class PhaseGroup:
    """A tap's image: the light of emitter group ``source`` correlated with a gate of ``duty`` centred on
    phase ``phase_rad`` of frequency ``frequency_hz``, per second of gated time."""

    name: str
    source: str
    frequency_hz: float
    phase_rad: float


def phase_group_name(source: str, frequency_hz: float, phase_deg: float) -> str:
    return f"{source}@{frequency_hz / 1e6:g}MHz/{phase_deg:g}"


def waveform_coefficients(waveform: str, harmonics: int) -> dict[int, float]:
    """{h: m_h} of the illuminator's waveform (mean 1) up to harmonic ``harmonics``, zeros left out."""
    if waveform == "sine":
        return {1: 1.0}
    if waveform == "square":
        return {h: 4.0 / (math.pi * h) * math.sin(math.pi * h / 2) for h in range(1, harmonics + 1, 2)}
    raise ConfigError(f"sensor.tof.waveform: expected 'sine' or 'square', got {waveform!r}")


def gate_coefficient(h: int, duty: float) -> float:
    """s_h: harmonic h of a box gate of ``duty`` per unit of gated time, sin(pi h d) / (pi h d)."""
    x = math.pi * h * duty
    return math.sin(x) / x


@dataclass(frozen=True)
class Demodulation:
    """The phase groups of a capture and how their images follow from the rendered basis.

    ``basis()`` names what the renderer must write: for each modulated group, its light (the group
    itself) and, for each frequency and harmonic, ``(group, wavenumber)`` pairs whose cosine and sine channels
    are named :func:`basis_name`. ``combine`` turns a stack of basis images into the phase groups' images."""

    groups: tuple[PhaseGroup, ...]
    duty: float
    contrast: float
    waveform: str
    harmonics: int

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(g.name for g in self.groups)

    def by_name(self, name: str) -> PhaseGroup:
        for g in self.groups:
            if g.name == name:
                return g
        raise KeyError(name)

    def terms(self, name: str) -> list[tuple[str, float]]:
        """(basis name, coefficient) whose sum is phase group ``name``'s image."""
        g = self.by_name(name)
        out = [(g.source, 1.0)]
        for h, m in waveform_coefficients(self.waveform, self.harmonics).items():
            a = self.contrast * gate_coefficient(h, self.duty) * m
            k = wavenumber(h * g.frequency_hz)
            out.append((basis_name(g.source, k, "cos"), a * math.cos(h * g.phase_rad)))
            out.append((basis_name(g.source, k, "sin"), a * math.sin(h * g.phase_rad)))
        return out

    def basis_of(self, requested: list[str]) -> list[str]:
        """The basis images the ``requested`` groups need (phase groups replaced by their terms), in order."""
        out: list[str] = []
        for r in requested:
            names = [b for b, _ in self.terms(r)] if r in self.names else [r]
            out.extend(b for b in names if b not in out)
        return out

    def combine(self, basis_img: np.ndarray, basis: list[str], requested: list[str]) -> np.ndarray:
        """(len(basis), ...) images -> (len(requested), ...): each phase group the sum of its terms, any
        other group as rendered."""
        out = np.empty((len(requested), *basis_img.shape[1:]), dtype=basis_img.dtype)
        for i, r in enumerate(requested):
            if r in self.names:
                acc = np.zeros(basis_img.shape[1:], np.float64)
                for b, a in self.terms(r):
                    acc += a * basis_img[basis.index(b)]
                out[i] = acc
            else:
                out[i] = basis_img[basis.index(r)]
        return out

    def lowest_correlation(self) -> float:
        """The least value of ``1 + eps sum_h s_h m_h cos(h x)`` over x: a tap's share of a path's light,
        which must not be negative (a truncated square wave's series can dip below 0 with eps near 1)."""
        x = np.linspace(0.0, 2 * math.pi, 4097)
        corr = np.ones_like(x)
        for h, m in waveform_coefficients(self.waveform, self.harmonics).items():
            corr += self.contrast * gate_coefficient(h, self.duty) * m * np.cos(h * x)
        return float(corr.min())


def wavenumber(frequency_hz: float) -> float:
    """k = 2 pi f / c, rad per metre of path: the phase a path of length l carries is k l."""
    return 2.0 * math.pi * frequency_hz / C_M_PER_S


def basis_name(source: str, k: float, part: str) -> str:
    """The rendered channel ``part`` ('cos' or 'sin') of group ``source`` at wavenumber ``k`` (rad/m)."""
    return f"{source}~{part}:{k!r}"


def parse_basis(name: str) -> tuple[str, float, str] | None:
    """(source, wavenumber, part) of a phasor basis name; None for a plain group."""
    if "~" not in name:
        return None
    source, _, rest = name.partition("~")
    part, _, k = rest.partition(":")
    return source, float(k), part


def phases_rad(n: int) -> list[float]:
    """n demodulation phases evenly spaced over one period, from 0."""
    return [2.0 * math.pi * i / n for i in range(n)]


def make_demodulation(
    source: str,
    frequencies_hz: list[float],
    phases: int,
    design: TapDesign,
    contrast: float,
    waveform: str,
    harmonics: int,
) -> Demodulation:
    """The phase groups of a capture: ``phases`` per frequency, in frequency then phase order."""
    groups = tuple(
        PhaseGroup(phase_group_name(source, f, math.degrees(p)), source, f, p)
        for f in frequencies_hz
        for p in phases_rad(phases)
    )
    demod = Demodulation(groups, design.duty, contrast, waveform, harmonics)
    low = demod.lowest_correlation()
    if low < 0:
        raise ConfigError(
            f"sensor.tof: with waveform {waveform!r} to harmonic {harmonics}, contrast {contrast} and gate duty "
            f"{design.duty:g}, a tap's correlation dips to {low:.3f} < 0 (the truncated series); lower "
            "sensor.tof.demodulation_contrast or raise sensor.tof.harmonics"
        )
    return demod


def unambiguous_range_m(frequency_hz: float) -> float:
    """c / (2 f): the distance over which one frequency's phase wraps once (the light goes there and back)."""
    return C_M_PER_S / (2.0 * frequency_hz)
