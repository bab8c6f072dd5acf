"""From scene radiance to expected photo-electrons (noise-free).

Derivation of the factor K (electrons per unit radiant exposure H = radiance x seconds):

1. A lens of f-number N and transmittance tau images a Lambertian-like patch of radiance
   L (W m^-2 sr^-1) onto the sensor with on-axis irradiance (the camera equation,
   cos^4 fall-off ignored, object far away)

       E = pi * L * tau / (4 N^2)                      [W m^-2]

2. The optically active part of one pixel, A_pixel * fill_factor (m^2), receives the power
   P = E * A_pixel * fill_factor (W); over t seconds the energy P * t (J).
3. A photon of wavelength lambda carries h c / lambda joules, so the photon count is
   P t lambda / (h c); a fraction QE of them becomes electrons.

Hence electrons = H * K with H = L * t and, per channel c,

       K_c = pi * tau / (4 N^2) * A_pixel * fill_factor * QE_c * lambda_c / (h c)
             [electrons per (W m^-2 sr^-1 s)].

In RGB mode lambda_c is one effective wavelength per channel (``sensor.wavelength_nm``).

In spectral mode (a ``*_spectral`` Mitsuba variant, :mod:`.spectral`) the film already integrates
QE_c(lambda) * lambda / (h c) against the spectral radiance, giving electrons per (m^2 sr s); what
is left is the optics and the pixel area (:func:`electrons_per_film_second`):

       K_c = pi * tau / (4 N^2) * A_pixel * fill_factor      [m^2 sr]
"""

from __future__ import annotations

import numpy as np

from .config import SensorConfig
from .spectral import is_spectral_variant

__all__ = [
    "PLANCK_J_S",
    "SPEED_OF_LIGHT_M_PER_S",
    "electrons_per_film_second",
    "electrons_per_radiance_second",
    "electrons_per_render_second",
    "expected_electrons",
    "mono_weights",
]

PLANCK_J_S = 6.62607015e-34
"""Planck constant h in J s (exact, SI 2019)."""
SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
"""Speed of light c in m/s (exact)."""


def electrons_per_radiance_second(cfg: SensorConfig) -> np.ndarray:
    """Expected photo-electrons per unit radiant exposure, per channel.

    Returns K, shape (C,) = (3,), float64, in electrons per (W m^-2 sr^-1 * s); see the
    module docstring for the derivation. Fixed-pattern PRNU is not included (it is applied
    in :func:`mbcapture.sensor.readout.simulate_reads`).
    """
    qe = np.asarray(cfg.quantum_efficiency, dtype=np.float64)
    wavelength_m = np.asarray(cfg.wavelength_nm, dtype=np.float64) * 1e-9
    irradiance_per_radiance = np.pi * cfg.lens_transmittance / (4.0 * cfg.f_number**2)  # sr
    photons_per_joule = wavelength_m / (PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S)
    return irradiance_per_radiance * cfg.pixel_area_m2 * cfg.fill_factor * qe * photons_per_joule


def electrons_per_film_second(cfg: SensorConfig) -> np.ndarray:
    """Spectral mode: electrons per second per unit spectral-film value, per channel.

    The spectral film (:func:`mbcapture.sensor.spectral.film_sensitivity`) records
    integral QE_c(lambda) lambda/(h c) L(lambda) d lambda in electrons per (m^2 sr s); this returns
    K, shape (3,), float64, in m^2 sr: pi tau / (4 N^2) * A_pixel * fill_factor, the same for
    every channel (QE and photon energy are in the film already).
    """
    etendue_m2_sr = np.pi * cfg.lens_transmittance / (4.0 * cfg.f_number**2) * cfg.pixel_area_m2 * cfg.fill_factor
    return np.full(3, etendue_m2_sr, dtype=np.float64)


def electrons_per_render_second(cfg: SensorConfig, variant: str) -> np.ndarray:
    """The factor from the renderer's output to electrons per second, for Mitsuba ``variant``:
    :func:`electrons_per_film_second` for spectral variants, :func:`electrons_per_radiance_second`
    otherwise. Shape (3,), float64."""

    k = _band_factors(cfg, variant)
    # a monochrome sensor (sensor.cfa: mono): the renderer gives the mixture of mono_weights, and the one
    # photosite collects every band's electrons: sum_c K_c x_c = (sum_c K_c) * (sum_c w_c x_c)
    return np.full(3, k.sum()) if cfg.cfa == "mono" else k


def mono_weights(cfg: SensorConfig, variant: str) -> np.ndarray | None:
    """A monochrome sensor's (``sensor.cfa: mono``) mixture of the renderer's channels, (3,) summing
    to 1: w_c = K_c / sum K, so that its photo-electrons, the mixture times
    :func:`electrons_per_render_second`, are the sum of each band's (the channels' quantum
    efficiencies sample the one spectral response over three bands). None for any other sensor."""
    if cfg.cfa != "mono":
        return None
    k = _band_factors(cfg, variant)
    return k / k.sum()


def _band_factors(cfg: SensorConfig, variant: str) -> np.ndarray:
    """Each channel's electrons per render unit and second, as three separate photosites see them."""
    return electrons_per_film_second(cfg) if is_spectral_variant(variant) else electrons_per_radiance_second(cfg)


def expected_electrons(radiant_exposure: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Expected (noise-free) photo-electrons from radiant exposure.

    ``radiant_exposure``: H, any shape ending in the channel axis C = 3, in
    W m^-2 sr^-1 s (e.g. (K, H, W, C) bucket exposures). Returns H * K with the same
    shape, float64, in electrons.
    """
    h = np.asarray(radiant_exposure, dtype=np.float64)
    if h.ndim == 0 or h.shape[-1] != 3:
        raise ValueError(f"radiant exposure must end in a channel axis of 3, got shape {h.shape}")
    return h * electrons_per_radiance_second(cfg)
