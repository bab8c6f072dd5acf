"""Per-channel spectral response of the sensor for spectral rendering (``sensor.spectral_response``).

``"effective_wavelength"`` (default) is the RGB mode's model: one wavelength and one QE per
channel (:func:`mbcapture.sensor.photons.electrons_per_radiance_second`). Any other value names a
camera of colour-science's ``colour.MSDS_CAMERA_SENSITIVITIES`` dataset (e.g. ``"Nikon 5100
(NPL)"``); its relative R, G, B sensitivity curves are used as the spectral *shape* of each
channel's quantum efficiency.

``"monochrome:<camera>"`` (e.g. ``"monochrome:Nikon 5100 (NPL)"``) is a panchromatic sensor with
no colour filter array, as the multi-bucket sensor of the RGB-illumination application (its
colours come from the LEDs): all three channels get the same curve, the sum of the camera's R, G
and B curves (assumption: what the same silicon and IR-cut filter see without the colour filters,
up to the filters' peak transmissions), peak-scaled per channel to ``sensor.quantum_efficiency``.
Give the three ``quantum_efficiency`` values equal to make the channels identical; a
reconstruction then reads one channel as the monochrome pixel (:func:`is_monochrome`).

Assumption (documented in the config reference): each camera curve is scaled so that its peak
equals that channel's ``sensor.quantum_efficiency`` value, i.e. ``quantum_efficiency`` becomes the
peak QE (colour filter included) and the dataset supplies the shape only. The datasets are
relative responses (peak 1), not absolute QE, so some such scaling is unavoidable.

The spectral film then records, per channel c,

    F_c = integral S_c(lambda) L(lambda) d lambda,   S_c = QE_c(lambda) * lambda / (h c)

with L in W m^-2 sr^-1 nm^-1 and d lambda in nm: photo-electrons per (m^2 sr s) before the
optics (:func:`film_sensitivity`).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Protocol

import numpy as np


class SpectralSensor(Protocol):
    """What the spectral curves need of a sensor (:class:`mbcapture.sensor.config.SensorConfig` has it)."""

    spectral_response: str
    quantum_efficiency: tuple[float, float, float]


__all__ = [
    "EFFECTIVE_WAVELENGTH",
    "camera_names",
    "channel_quantum_efficiency",
    "check_spectral_response",
    "film_sensitivity",
    "is_monochrome",
    "is_spectral_variant",
    "MONOCHROME_PREFIX",
]

EFFECTIVE_WAVELENGTH = "effective_wavelength"
"""``sensor.spectral_response`` value meaning: one effective wavelength per channel (RGB mode)."""

MONOCHROME_PREFIX = "monochrome:"
"""``sensor.spectral_response`` prefix: a panchromatic (no colour filter) version of a camera."""

_PLANCK_J_S = 6.62607015e-34
_SPEED_OF_LIGHT_M_PER_S = 299_792_458.0


def is_spectral_variant(variant: str) -> bool:
    """True for Mitsuba's spectral variants (``llvm_ad_spectral``, ``cuda_ad_spectral``, ...)."""
    return variant.endswith("_spectral")


@lru_cache(maxsize=1)
def camera_names() -> tuple[str, ...]:
    """Names accepted by ``sensor.spectral_response`` besides ``effective_wavelength``."""
    import colour

    return tuple(sorted(colour.MSDS_CAMERA_SENSITIVITIES.keys()))


def check_spectral_response(name: str) -> str:
    """``name`` if it is ``effective_wavelength``, a known camera or ``monochrome:<known camera>``,
    else ValueError listing the names."""
    camera = name[len(MONOCHROME_PREFIX) :] if name.startswith(MONOCHROME_PREFIX) else name
    if name == EFFECTIVE_WAVELENGTH or camera in camera_names():
        return name
    valid = [EFFECTIVE_WAVELENGTH, *camera_names()]
    raise ValueError(
        f"spectral_response: unknown camera {camera!r}; expected one of {valid} "
        f"(colour.MSDS_CAMERA_SENSITIVITIES keys), optionally prefixed by {MONOCHROME_PREFIX!r}"
    )


def is_monochrome(name: str) -> bool:
    """True when ``sensor.spectral_response`` names a panchromatic (``monochrome:``) sensor."""
    return name.startswith(MONOCHROME_PREFIX)


def channel_quantum_efficiency(cfg: SpectralSensor) -> tuple[np.ndarray, np.ndarray]:
    """QE curves of the camera ``cfg.spectral_response``, peak-scaled to ``cfg.quantum_efficiency``.

    Returns (wavelengths_nm (n,), qe (3, n)) on the dataset's regular grid, float64, channels
    R, G, B, electrons per photon.
    """
    name = check_spectral_response(cfg.spectral_response)
    if name == EFFECTIVE_WAVELENGTH:
        raise ValueError("spectral_response 'effective_wavelength' has no spectral curves; name a camera")
    import colour

    mono = is_monochrome(name)
    msds = colour.MSDS_CAMERA_SENSITIVITIES[name[len(MONOCHROME_PREFIX) :] if mono else name]
    wl = np.asarray(msds.wavelengths, dtype=np.float64)
    rel = np.asarray(msds.values, dtype=np.float64).T.copy()  # (3, n): red, green, blue
    rel = np.clip(rel, 0.0, None)
    if mono:  # panchromatic: the same silicon without the colour filters
        rel = np.repeat(rel.sum(axis=0, keepdims=True), 3, axis=0)
    qe = rel / rel.max(axis=1, keepdims=True) * np.asarray(cfg.quantum_efficiency, np.float64)[:, None]
    return wl, qe


def film_sensitivity(cfg: SpectralSensor) -> tuple[np.ndarray, np.ndarray]:
    """Spectral film sensitivities S_c(lambda) = QE_c(lambda) * lambda / (h c).

    Returns (wavelengths_nm (n,), S (3, n)) in electrons per joule; with L in W m^-2 sr^-1 nm^-1
    the film value integral S_c L d lambda (nm) is in electrons per (m^2 sr s).
    """
    wl, qe = channel_quantum_efficiency(cfg)
    return wl, qe * (wl * 1e-9) / (_PLANCK_J_S * _SPEED_OF_LIGHT_M_PER_S)
