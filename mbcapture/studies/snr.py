"""HDR signal-to-noise ratio against scene radiance for three capture protocols.

All three capture the exposures T, 2T, 4T, 8T of a static flat scene on the same sensor:

``photon_efficient``
    Buckets 1..4 gated 4T, 2T, T, T (interleaved over 8T); non-destructive cumulative reads
    J1 = B4, J2 = B4 + B3, J3 = B4 + B3 + B2, J4 = all (exposures T, 2T, 4T, 8T), merged by
    ``ramp_fit``. Buckets hold charge for 8T (dark current).
``interleaved``
    Buckets gated 8T, 4T, 2T, T (interleaved over 15T), each read directly, merged by
    ``inverse_variance``. Buckets hold charge for 15T.
``sequential``
    A conventional sensor takes 4 frames 8T, 4T, 2T, T one after another (each a separate
    destructive read of its own exposure), merged by ``inverse_variance``.

Expected electrons K * L * exposure are fed to the sensor model directly (no rendering).
Used by ``scripts/snr_curves.py`` and ``mbcapture figures``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..reconstruct.hdr import merge_hdr
from ..sensor import SensorConfig, electrons_per_radiance_second, simulate_reads

GREEN = 1


@dataclass(frozen=True)
class Protocol:
    """A capture: per-bucket exposure in units of T, reads, merge method.

    ``bucket_t``: (K,) exposure of each bucket (or frame) in units of T.
    ``reads``: bucket indices summed per read.
    ``read_t``: (R,) exposure of each read in units of T.
    ``storage_t``: (K,) time each bucket holds charge before its read, units of T.
    """

    name: str
    bucket_t: tuple[float, ...]
    reads: tuple[tuple[int, ...], ...]
    read_t: tuple[float, ...]
    storage_t: tuple[float, ...]
    cumulative: bool
    method: str
    shared_photodiode: bool


PROTOCOLS = (
    Protocol(
        "photon_efficient",
        (4, 2, 1, 1),
        ((3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)),
        (1, 2, 4, 8),
        (8, 8, 8, 8),
        True,
        "ramp_fit",
        True,
    ),
    Protocol(
        "interleaved",
        (8, 4, 2, 1),
        ((0,), (1,), (2,), (3,)),
        (8, 4, 2, 1),
        (15, 15, 15, 15),
        False,
        "inverse_variance",
        True,
    ),
    Protocol(
        "sequential",
        (8, 4, 2, 1),
        ((0,), (1,), (2,), (3,)),
        (8, 4, 2, 1),
        (8, 4, 2, 1),
        False,
        "inverse_variance",
        False,
    ),
)

REPORT_RADIANCES = {"low": 1e-3, "mid": 1e-1, "high": 1.0}
"""Radiances (W m^-2 sr^-1) at which the SNR gains are printed: ~2, ~190 and ~1900 e- per T
at T = 1 ms (the high one saturates the 8T bucket of the interleaved/sequential captures)."""


def snr_curve(
    protocol: Protocol,
    radiance: np.ndarray,
    cfg: SensorConfig,
    unit_exposure_s: float,
    n_pixels: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """SNR of the merged green-channel rate at each radiance (L,), NaN where mostly saturated."""
    k_green = electrons_per_radiance_second(cfg)[GREEN]
    rate_e_per_s = k_green * radiance  # (L,)
    bucket_s = unit_exposure_s * np.asarray(protocol.bucket_t, dtype=np.float64)
    expected = rate_e_per_s[None, :, None, None] * bucket_s[:, None, None, None]
    expected = np.broadcast_to(expected, (bucket_s.size, radiance.size, n_pixels, 1)).copy()
    out = simulate_reads(
        expected,
        protocol.reads,
        cfg,
        rng,
        storage_s=unit_exposure_s * np.asarray(protocol.storage_t, dtype=np.float64),
        shared_photodiode=protocol.shared_photodiode,
    )
    res = merge_hdr(
        out.reads_dn,
        unit_exposure_s * np.asarray(protocol.read_t, dtype=np.float64),
        cfg,
        method=protocol.method,
        cumulative=protocol.cumulative,
        saturated=out.saturated,
    )
    snr = np.full(radiance.size, np.nan)
    for i in range(radiance.size):
        valid = res.valid[i, :, 0]
        if valid.mean() >= 0.5:
            x = res.rate_e_per_s[i, valid, 0]
            snr[i] = x.mean() / x.std(ddof=1)
    return snr


def radiance_range(cfg: SensorConfig, unit_exposure_s: float, levels: int) -> np.ndarray:
    """From ~0.05 e- per T up to where the shortest read (T) saturates, plus the report levels."""
    k_green = electrons_per_radiance_second(cfg)[GREEN]
    lo = 0.05 / (k_green * unit_exposure_s)
    hi = 2.0 * cfg.full_well_e / (k_green * unit_exposure_s)
    return np.unique(np.concatenate([np.geomspace(lo, hi, levels), list(REPORT_RADIANCES.values())]))


def snr_curves(
    cfg: SensorConfig, radiance: np.ndarray, unit_exposure_s: float, n_pixels: int, seed: int
) -> dict[str, np.ndarray]:
    """Protocol name -> SNR at each radiance."""
    seeds = np.random.SeedSequence(seed).spawn(len(PROTOCOLS))
    return {
        p.name: snr_curve(p, radiance, cfg, unit_exposure_s, n_pixels, np.random.default_rng(s))
        for p, s in zip(PROTOCOLS, seeds)
    }
