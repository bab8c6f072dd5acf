"""HDR: the HDR protocols, and the merge of their reads into radiance with its uncertainty (``hdr.method``).

The protocols (each a function of the config returning one period's slots and the reads):

``photon_efficient_hdr``
    Slots 4:2:1:1 (for K buckets: 2^(K-2) : ... : 2 : 1 : 1) per period; non-destructive
    reads of bucket K, K+(K-1), ..., all: exposures T, 2T, 4T, ..., 2^(K-1) T in 2^(K-1) T
    (the paper's section 4).
``interleaved_hdr``
    Slots 8:4:2:1 (2^(K-1) : ... : 1), each bucket read directly: the same exposures in
    (2^K - 1) T (Wan et al. 2012; the paper's figure 9).
``custom``
    One period of slots from ``capture.schedule`` repeated ``capture.periods`` times (any
    application can read it: ``app.name``; the HDR merge by default).

On a Bayer sensor (``sensor.cfa``) the merge runs on each photosite's reads and the merged radiance
is demosaiced (:func:`merge_mosaic` says why).

Reference: the noise-free, unclipped radiance seen by the longest read. HDR extends that read's
dynamic range with the shorter ones; wherever they saw something else (motion), it shows as
error, and the motion check measures how far apart the exposure-normalized reads are.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from ..metrics import REC709_LUMA, pu21_psnr, relative_mse
from ..reconstruct.hdr import merge_hdr, quantization_read_variance_e2, resolve_method
from ..sensor.cfa import demosaic, demosaic_hdr, spread_to_footprint, to_mosaic
from ..config import CaptureConfig
from ..errors import ConfigError
from ..timing.protocols import need_buckets
from ..timing.timeline import DRAIN, ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol

#: lm/W at 555 nm: radiance (W m^-2 sr^-1) -> luminance (cd m^-2) for PU21, treating the RGB
#: channels' luminance weights (Rec. 709) as photometric. An approximation, used for the metric only.
LUMINOUS_EFFICACY_LM_PER_W = 683.0

#: relMSE floor for radiance images: (0.01 W m^-2 sr^-1)^2, about the darkest lit surfaces of the
#: shipped scenes, so black pixels do not dominate the mean.
REL_MSE_EPS_RADIANCE = 1e-4


def exposure_ratios(cfg: CaptureConfig, buckets: int) -> list[Fraction]:
    """The HDR protocols' read exposures in units of T, shortest first, as exact fractions: ``capture.exposure_ratios``
    (one bucket each, at most the sensor's; a ConfigError otherwise), else powers of two over ``buckets``."""
    ratios = cfg.capture.exposure_ratios
    if ratios is None:
        return [Fraction(2**i) for i in range(buckets)]
    if len(ratios) > cfg.sensor.bucket_count:
        raise ConfigError(
            f"capture.exposure_ratios: {len(ratios)} reads need {len(ratios)} buckets (one each) but "
            f"sensor.bucket_count is {cfg.sensor.bucket_count}"
        )
    return [exact(r) for r in ratios]


@register_protocol("photon_efficient_hdr")
def photon_efficient_hdr(cfg: CaptureConfig):
    """One period: bucket K (read first, alone) collects r1 units, bucket K-1 r2 - r1, ..., bucket 1 rK - r(K-1),
    for ratios r1 = 1 < r2 < ... < rK; read i sums buckets K-i+1..K: exposure ri T. Powers of two by default:
    2^(K-2) : ... : 2 : 1 : 1."""
    r = exposure_ratios(cfg, max(cfg.sensor.bucket_count, 2))
    k = len(r)
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    units = [r[k - 1 - b] - (r[k - 2 - b] if b < k - 1 else 0) for b in range(k)]
    slots = [SlotSeconds(b, T * u / N) for b, u in enumerate(units)]
    reads = [ReadEvent(f"J{i + 1}", tuple(range(k - 1 - i, k))) for i in range(k)]
    return slots, reads, k


@register_protocol("interleaved_hdr")
def interleaved_hdr(cfg: CaptureConfig):
    """One period: bucket b collects r(K-b+1) units (bucket K: r1 = 1), each read directly: read i is bucket
    K-i+1, exposure ri T. Powers of two by default: 2^(K-1) : ... : 1."""
    r = exposure_ratios(cfg, cfg.sensor.bucket_count)
    k = len(r)
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    slots = [SlotSeconds(b, T * r[k - 1 - b] / N) for b in range(k)]
    reads = [ReadEvent(f"J{i + 1}", (k - 1 - i,)) for i in range(k)]
    return slots, reads, k


@register_protocol("custom")
def custom(cfg: CaptureConfig):
    sched = cfg.capture.schedule
    used = {s.bucket for s in sched.slots if s.bucket != "drain"} | {b for r in sched.reads for b in r.buckets}
    bad = sorted(b for b in used if b < 1)
    if bad:
        raise ConfigError(f"capture.schedule: buckets are numbered from 1 (got {bad})")
    k = need_buckets(cfg, max(used))
    slots = [
        SlotSeconds(DRAIN if s.bucket == "drain" else s.bucket - 1, exact(s.duration_s), frozenset(s.groups))
        for s in sched.slots
    ]
    reads = [ReadEvent(r.name or f"J{i + 1}", tuple(b - 1 for b in r.buckets)) for i, r in enumerate(sched.reads)]
    names_ = [r.name for r in reads]
    if len(set(names_)) != len(names_):
        raise ConfigError(f"capture.schedule.reads: read names must be unique (got {names_})")
    return slots, reads, k


def luminance_cd_m2(rgb_radiance: np.ndarray) -> np.ndarray:
    return LUMINOUS_EFFICACY_LM_PER_W * (np.asarray(rgb_radiance) @ REC709_LUMA)


def normalized_reads(data: CaptureData) -> np.ndarray:
    """(R, H, W, C) radiance each read saw, noise-free: expected electrons / (k_e * exposure)."""
    return data.reads_e_expected / (data.k_e * data.exposure_s[:, None, None, None])


def motion_check(normalized: np.ndarray, names: list[str], truth: np.ndarray, mask: np.ndarray) -> dict:
    """How far apart the exposure-normalized, noise-free reads are inside the moving region.

    normalized (R, H, W, C) radiance of each read. Returns per read the RMS difference to the
    capture's ground truth and the largest pairwise RMS difference between reads, both relative
    to the mean truth in the region.
    """
    if not mask.any():
        return {"moving_pixels": 0, "note": "static scene: nothing moves"}
    ref = float(truth[mask].mean()) or 1.0
    per_read = {n: float(np.sqrt(np.mean((normalized[i][mask] - truth[mask]) ** 2)) / ref) for i, n in enumerate(names)}
    pair = 0.0
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            pair = max(pair, float(np.sqrt(np.mean((normalized[i][mask] - normalized[j][mask]) ** 2)) / ref))
    return {"moving_pixels": int(mask.sum()), "rel_rms_vs_truth": per_read, "max_pairwise_rel_rms": pair}


def demosaic_floor(sensor, k_e: np.ndarray, exposure_s: np.ndarray) -> np.ndarray:
    """(3,) radiance per channel below which a merge's radiance is demosaiced linearly (:func:`demosaic_hdr`):
    the merge's noise at zero light, one read's read and quantization noise (``sensor``) over the longest of
    the ``exposure_s``, through the electrons per unit radiance and second ``k_e``. Lower than the reads'
    floor (:data:`~mbcapture.sensor.cfa.LOG_DEMOSAIC_FLOOR_E`): a merge's darkest pixels sit beside its
    brightest, and within a linear range of 100 e- Menon's colour differences still pulled 6 of them below
    zero on the metronome at 128x96 (none with this floor; relMSE 0.0089 against 0.0092).
    ``python scripts/cfa_hdr_order.py --size 128x96 --spp 8`` measures the merge with it."""
    return np.sqrt(quantization_read_variance_e2(sensor)) / (np.asarray(k_e) * float(np.max(exposure_s)))


def merge_mosaic(data: CaptureData, method: str, cumulative: bool) -> tuple[np.ndarray, dict, np.ndarray]:
    """A Bayer sensor: merge each photosite's reads (with its own saturation flags), then demosaic the
    radiance. Returns radiance, {"sigma": ..., "sigma_temporal": ...} and valid, each (H, W, 3).

    Why merge first: saturation belongs to a photosite. Demosaicing the reads first mixes a clipped
    photosite into its neighbours, so every pixel within the demosaicing's reach of it must drop that
    read (the sensor stage flags them), and the merge falls back to shorter, noisier reads around
    every highlight. Merging each photosite first keeps its best reads, and demosaicing then works on
    unclipped radiance, in a logarithmic domain (:func:`mbcapture.sensor.cfa.demosaic_hdr` says why).
    Measured (``python scripts/cfa_hdr_order.py --size 128x96 --spp 8``: metronome_hdr, RGGB): relMSE 0.0089
    merging first against 0.0109 demosaicing first with menon2007, 0.0159 against 0.0171 with malvar2004,
    0.0685 against 0.0714 with bilinear (both in the logarithmic domain; demosaicing linearly, 0.26 to 0.53).
    Each sigma is the merged photosites' interpolated bilinearly, not the demosaiced value's own
    (averaging lowers it)."""
    hdr = merge_hdr(
        data.mosaic_dn,
        data.exposure_s,
        data.cfg.sensor,
        method=method,
        cumulative=cumulative,
        saturated=data.mosaic_saturated,
    )
    k = data.k_e[data.photosite_channels()]
    floor = demosaic_floor(data.cfg.sensor, data.k_e, data.exposure_s)
    radiance = demosaic_hdr(hdr.rate_e_per_s / k, data.cfg.sensor.cfa, data.cfg.sensor.demosaic, floor)
    valid = ~spread_to_footprint(~hdr.valid, data.cfg.sensor.demosaic)
    # an uncertainty interpolated with non-negative weights (Malvar's and Menon's negative ones made it < 0)
    sigmas = {
        name: np.where(valid, demosaic(np.where(hdr.valid, s / k, 0.0), data.cfg.sensor.cfa, "bilinear"), np.inf)
        for name, s in (("sigma", hdr.sigma_e_per_s), ("sigma_temporal", hdr.sigma_temporal_e_per_s))
    }
    return radiance, sigmas, valid


#: What each preview shows (report.html).
CAPTIONS = {
    "hdr": "the HDR radiance merged from the reads (hdr.method); where every read saturated, a lower bound",
    "truth": "the reference: noise-free, unclipped radiance that the longest read saw",
}


@register(
    "hdr",
    output_channels=18,
    previews=2,
    renders=False,
    description="HDR merge of the reads (hdr.method), with sigma (temporal noise and fixed pattern), "
    "sigma_temporal and valid layers",
)
def reconstruct(data: CaptureData, params) -> AppOutput:
    cfg, tl = data.cfg, data.timeline
    cumulative = not data.sequential and any(len(r.buckets) > 1 for r in tl.reads)
    method = resolve_method(cfg.hdr.method, cumulative)
    if data.bayer:
        radiance, sigmas, valid = merge_mosaic(data, method, cumulative)
    else:
        hdr = merge_hdr(
            data.reads_dn, data.exposure_s, cfg.sensor, method=method, cumulative=cumulative, saturated=data.saturated
        )
        radiance, valid = hdr.rate_e_per_s / data.k_e, hdr.valid
        sigmas = {"sigma": hdr.sigma_e_per_s / data.k_e, "sigma_temporal": hdr.sigma_temporal_e_per_s / data.k_e}
    normalized = normalized_reads(data)
    ref = int(np.argmax(data.exposure_s))
    truth = normalized[ref]
    mask = data.moving_mask
    n_ch = radiance.shape[-1]
    # PU21 needs luminance: defined for RGB radiance, not for a spectral camera's film units
    photometric = not cfg.render.variant.endswith("_spectral")
    metrics = {
        "hdr_method": method,
        "reference": f"noise-free radiance seen by the longest read, {data.read_names[ref]}",
        "hdr_rel_mse": relative_mse(radiance, truth, eps=REL_MSE_EPS_RADIANCE),
        "hdr_pu21_psnr_db": pu21_psnr(luminance_cd_m2(radiance), luminance_cd_m2(truth)) if photometric else None,
        "hdr_valid_fraction": float(valid.mean()),
        "motion_check": motion_check(normalized, data.read_names, truth, mask),
    }
    if data.bayer:  # the mosaic's own share: the noise-free truth through the same mosaic and demosaicing
        alone = demosaic_hdr(
            to_mosaic(truth, cfg.sensor.cfa),
            cfg.sensor.cfa,
            cfg.sensor.demosaic,
            demosaic_floor(cfg.sensor, data.k_e, data.exposure_s),
        )
        metrics["demosaic_rel_mse"] = relative_mse(alone, truth, eps=REL_MSE_EPS_RADIANCE)
        if mask.any():
            metrics["demosaic_rel_mse_moving"] = relative_mse(
                alone, truth, mask=mask[..., None].repeat(n_ch, -1), eps=REL_MSE_EPS_RADIANCE
            )
    if mask.any():
        metrics["hdr_rel_mse_moving"] = relative_mse(
            radiance, truth, mask=mask[..., None].repeat(n_ch, -1), eps=REL_MSE_EPS_RADIANCE
        )
        if photometric:
            metrics["hdr_pu21_psnr_db_moving"] = pu21_psnr(luminance_cd_m2(radiance), luminance_cd_m2(truth), mask=mask)
    pu21 = f", PU21-PSNR {metrics['hdr_pu21_psnr_db']:.2f} dB" if photometric else ""
    summary = [f"HDR ({method}): relMSE {metrics['hdr_rel_mse']:.4g}{pu21}"]
    mc = metrics["motion_check"]
    if mc.get("moving_pixels"):
        summary.append(
            "motion check: largest difference between exposure-normalized reads in the moving region "
            f"{100 * mc['max_pairwise_rel_rms']:.2f}% of its mean"
        )
    return AppOutput(
        images={
            "radiance": radiance,
            **sigmas,
            "valid": valid.astype(np.float32),
            "truth": truth,
            "moving": np.repeat(mask[..., None], n_ch, -1).astype(np.float32),
        },
        metrics=metrics,
        png={"hdr": ("radiance", cfg.output.png_percentile), "truth": ("truth", cfg.output.png_percentile)},
        summary=summary,
        captions=CAPTIONS,
    )
