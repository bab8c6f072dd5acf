"""HDR merging of several reads of one scene into one photo-electron rate.

Methods (registry :data:`HDR_METHODS`, dispatcher :func:`merge_hdr`):

``ramp_fit``
    Generalized least squares for the rate lambda (electrons/s) through the origin, with
    the read covariance in electrons^2

        C_ij = lambda * M_ij + sigma_r^2 * delta_ij,
        M_ij = min(t_i, t_j)  for cumulative non-destructive reads (they share photons),
        M_ij = t_i delta_ij   for independent exposures,

    over the usable reads (cumulative: the reads before the first saturated one;
    independent: every unsaturated read), as in up-the-ramp fitting of infrared detectors.
    Pass 0 is ordinary least squares through the origin; pass 1 is GLS with C(lambda_0);
    pass 2 iterates once more with C(lambda_1). The estimate is
    lambda = t^T C^-1 x / (t^T C^-1 t) with variance 1 / (t^T C^-1 t).
    sigma_r^2 = read_noise_e^2 + 1 / (12 gain^2) includes the quantization step.
    Vectorized: pixels are grouped by their set of usable reads; within a group M is
    shared, so with M = V diag(d) V^T every pixel's C^-1 is V diag(1/(lambda d + sigma_r^2)) V^T
    and no per-pixel matrix is ever solved.

``inverse_variance``
    Per-read rates x_i / t_i averaged with weights 1 / Var_i, Var_i = (lambda_0 t_i +
    sigma_r^2) / t_i^2, where lambda_0 = sum(x_i) / sum(t_i) over the usable reads is a
    first-pass estimate (weights from each noisy value would bias the merge low).
    Optimal for independent exposures. Given cumulative reads it treats them as
    independent (what a naive user does): the estimate stays unbiased but is not the
    minimum-variance one, and its reported sigma ignores the correlation.

``debevec``
    Debevec & Malik (1997) with a linear camera response: per-read rates x_i / t_i
    averaged with the hat weight of the read's code, w(z) = min(z - z_min, z_max - z),
    z_min = black level, z_max = top ADC code. Averaged in the linear domain, not in log
    radiance as in the paper, because log is undefined for the zero/negative reads of dark
    pixels and biased under noise. Cumulative reads are treated as independent, as above.
    sigma is propagated assuming independent reads.

Every method sees only usable reads. Where none is usable (all saturated) the result is
``valid = False``, the rate is the lower bound max_i x_i / t_i (finite, >= 0) and sigma is
+inf. Rates are not clipped at zero: around zero light they scatter around zero.

Every method's sigma is the temporal noise's (another capture of the same pixel); the fixed pattern
(PRNU, DSNU) adds an error that does not average over captures, :func:`fixed_pattern_sigma`.
:class:`HDRResult` keeps the two apart and gives their sum as ``sigma_e_per_s``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..sensor.config import SensorConfig
from ..sensor.readout import dn_to_electrons

__all__ = [
    "HDR_METHODS",
    "HDRResult",
    "MergeInput",
    "fixed_pattern_sigma",
    "merge_hdr",
    "quantization_read_variance_e2",
]


@dataclass(frozen=True)
class HDRResult:
    """Merged HDR estimate, all arrays (H, W, C) (the trailing shape of the reads).

    ``rate_e_per_s``: photo-electron rate, electrons/s, float64 (a lower bound where not valid).
    ``sigma_temporal_e_per_s``: 1-sigma uncertainty of the rate from the temporal noise (shot, read,
        quantization), electrons/s (+inf where not valid): what another capture of the same pixel
        would scatter by.
    ``sigma_fixed_e_per_s``: 1-sigma of the fixed pattern's error in the rate (PRNU and DSNU with their
        row and column parts, :func:`fixed_pattern_sigma`), electrons/s: what another pixel of the same
        sensor would differ by.
    ``sigma_e_per_s``: both together (their variances add: the fixed pattern is independent of the
        temporal noise), electrons/s: the error against the truth of an uncalibrated sensor.
    ``valid``: False where every read is saturated.
    ``n_used``: number of reads that entered the merge, int64.
    """

    rate_e_per_s: np.ndarray
    sigma_temporal_e_per_s: np.ndarray
    sigma_fixed_e_per_s: np.ndarray
    valid: np.ndarray
    n_used: np.ndarray

    @property
    def sigma_e_per_s(self) -> np.ndarray:
        return np.hypot(self.sigma_temporal_e_per_s, self.sigma_fixed_e_per_s)


@dataclass(frozen=True)
class MergeInput:
    """What every merge method receives, pixels flattened to P, only pixels with >= 1 usable read.

    ``x_e``: (R, P) reads in electrons (black level and gain removed).
    ``dn``: (R, P) the same reads in DN.
    ``exposures_s``: (R,) seconds.
    ``usable``: (R, P) bool, reads allowed into the merge.
    ``read_var_e2``: read-noise plus quantization variance per read, electrons^2.
    ``cumulative``: reads are nested non-destructive sums (share photons).
    ``cfg``: the sensor.
    """

    x_e: np.ndarray
    dn: np.ndarray
    exposures_s: np.ndarray
    usable: np.ndarray
    read_var_e2: float
    cumulative: bool
    cfg: SensorConfig


#: A merge: (rate, temporal sigma, offset gain), each (P,). The offset gain is the rate's change per
#: electron added to every usable read alike (a DSNU offset), 1/s: for a fit through the origin it is
#: not 1/t, and the fixed pattern's sigma needs it.
MergeMethod = Callable[[MergeInput], tuple[np.ndarray, np.ndarray, np.ndarray]]


def quantization_read_variance_e2(cfg: SensorConfig) -> float:
    """Per-read noise variance in electrons^2: read noise plus uniform quantization (1/12 DN^2)."""
    return cfg.read_noise_e**2 + 1.0 / (12.0 * cfg.gain_dn_per_e**2)


def _first_pass_rate(m: MergeInput) -> np.ndarray:
    """Pooled rate sum(x_i) / sum(t_i) over usable reads, (P,), electrons/s; >= 0 for use in variances."""
    t = m.exposures_s[:, None]
    rate = np.where(m.usable, m.x_e, 0.0).sum(axis=0) / np.where(m.usable, t, 0.0).sum(axis=0)
    return np.maximum(rate, 0.0)


def _read_sum(coef: np.ndarray, values: np.ndarray) -> np.ndarray:
    """sum_i coef[i] * values[i] over the reads (axis 0), added in read order, one sample at a time:
    the same value for a sample whatever the other samples (BLAS and einsum choose their summation
    order by the arrays' shapes, so a merge in chunks would differ in the last bits)."""
    out = coef[0] * values[0]
    for i in range(1, len(coef)):
        out = out + coef[i] * values[i]
    return out


def _ramp_fit(m: MergeInput) -> tuple[np.ndarray, np.ndarray]:
    n_reads, n_pix = m.x_e.shape
    rate, sigma, offset = np.empty(n_pix), np.empty(n_pix), np.empty(n_pix)
    codes = np.zeros(n_pix, np.int64)  # bit i: read i usable
    for i in range(n_reads):
        codes[m.usable[i]] |= 1 << i
    # the codes present: counted in a table of 2^R where that is small (np.unique sorts or hashes every sample)
    present = np.flatnonzero(np.bincount(codes, minlength=1 << n_reads)) if n_reads <= 16 else np.unique(codes)
    for code in present:
        pix = np.flatnonzero(codes == code) if present.size > 1 else None  # None: every sample
        reads = np.flatnonzero((int(code) >> np.arange(n_reads)) & 1)
        t = m.exposures_s[reads]
        x = m.x_e[reads] if pix is None else np.take(m.x_e[reads], pix, axis=1)  # (n, P_g)
        shared = np.minimum.outer(t, t) if m.cumulative else np.diag(t)
        d, v = np.linalg.eigh(shared)  # shared = v diag(d) v^T, d >= 0
        a = v.T @ t  # (n,)
        y = np.stack([_read_sum(v[:, i], x) for i in range(len(reads))])  # (n, P_g) = v^T x
        lam = _read_sum(t, x) / (t @ t)  # pass 0: ordinary least squares through the origin
        for _ in range(2):  # pass 1: GLS with C(lam_0); pass 2: iterate once with the fitted lam
            w = 1.0 / (np.maximum(lam, 0.0)[None, :] * d[:, None] + m.read_var_e2)  # (n, P_g)
            fisher = _read_sum(a**2, w)
            lam = _read_sum(a, w * y) / fisher
        w = 1.0 / (np.maximum(lam, 0.0)[None, :] * d[:, None] + m.read_var_e2)
        sel = slice(None) if pix is None else pix
        rate[sel] = lam
        fisher = _read_sum(a**2, w)
        sigma[sel] = 1.0 / np.sqrt(fisher)
        offset[sel] = _read_sum(a * v.sum(axis=0), w) / fisher  # the estimate with x = 1 in every read
    return rate, sigma, offset


def _per_read_variance(m: MergeInput, rate0: np.ndarray) -> np.ndarray:
    """(R, P) variance of x_i / t_i for independent reads at rate ``rate0``, (electrons/s)^2."""
    t = m.exposures_s[:, None]
    return (rate0[None, :] * t + m.read_var_e2) / t**2


def _inverse_variance(m: MergeInput) -> tuple[np.ndarray, np.ndarray]:
    rates = m.x_e / m.exposures_s[:, None]
    w = np.where(m.usable, 1.0 / _per_read_variance(m, _first_pass_rate(m)), 0.0)
    total = w.sum(axis=0)
    offset = (w / m.exposures_s[:, None]).sum(axis=0) / total
    return (w * rates).sum(axis=0) / total, 1.0 / np.sqrt(total), offset


_HAT_FLOOR = 1e-6
"""Smallest hat weight (relative to the peak), so that reads at the ends of the range still average."""


def _debevec(m: MergeInput) -> tuple[np.ndarray, np.ndarray]:
    z_min = m.cfg.black_level_dn
    z_max = float(m.cfg.adc_max_dn)
    hat = np.minimum(m.dn - z_min, z_max - m.dn) / (0.5 * (z_max - z_min))
    w = np.where(m.usable, np.maximum(hat, _HAT_FLOOR), 0.0)
    rates = m.x_e / m.exposures_s[:, None]
    total = w.sum(axis=0)
    rate = (w * rates).sum(axis=0) / total
    var = _per_read_variance(m, _first_pass_rate(m))
    sigma = np.sqrt((w**2 * var).sum(axis=0)) / total
    offset = (w / m.exposures_s[:, None]).sum(axis=0) / total
    return rate, sigma, offset


HDR_METHODS: dict[str, MergeMethod] = {
    "ramp_fit": _ramp_fit,
    "inverse_variance": _inverse_variance,
    "debevec": _debevec,
}
"""Registered merge methods by name; see the module docstring."""


def resolve_method(method: str, cumulative: bool) -> str:
    """``"auto"`` -> ``ramp_fit`` for cumulative reads, ``inverse_variance`` for independent ones."""
    if method == "auto":
        return "ramp_fit" if cumulative else "inverse_variance"
    return method


def merge_hdr(
    reads_dn: np.ndarray,
    exposures_s: np.ndarray,
    cfg: SensorConfig,
    *,
    method: str,
    cumulative: bool,
    saturated: np.ndarray | None = None,
) -> HDRResult:
    """Merge R reads of the same scene into one rate image.

    Parameters
    ----------
    reads_dn:
        (R, H, W, C) ADC codes (any trailing shape works), in DN.
    exposures_s:
        (R,) exposure time of each read in seconds (for cumulative reads: the summed
        exposure, e.g. T, 2T, 4T, 8T; must then be strictly increasing).
    cfg:
        The sensor (black level, gain, read noise, ADC range).
    method:
        A key of :data:`HDR_METHODS`, or ``"auto"``: ``ramp_fit`` for cumulative reads,
        ``inverse_variance`` for independent ones.
    cumulative:
        True if read i+1 contains the photons of read i (non-destructive sums).
    saturated:
        (R, H, W, C) bool saturation flags from the sensor; ``None`` = none saturated.

    Returns
    -------
    HDRResult with the trailing shape of ``reads_dn``.
    """
    method = resolve_method(method, cumulative)
    if method not in HDR_METHODS:
        valid = ", ".join(sorted([*HDR_METHODS, "auto"]))
        raise ConfigError(f"hdr.method: unknown method {method!r}; valid methods: {valid}")

    dn = np.asarray(reads_dn, dtype=np.float64)
    t = np.asarray(exposures_s, dtype=np.float64)
    if dn.ndim < 1 or t.shape != (dn.shape[0],):
        raise ValueError(f"exposures_s: expected one exposure per read ({dn.shape[:1]}), got shape {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError(f"exposures_s: must be finite and > 0, got {t}")
    if cumulative and np.any(np.diff(t) <= 0):
        raise ValueError(f"exposures_s: cumulative reads need strictly increasing exposures, got {t}")
    sat = np.zeros(dn.shape, dtype=bool) if saturated is None else np.asarray(saturated, dtype=bool)
    if sat.shape != dn.shape:
        raise ValueError(f"saturated: expected shape {dn.shape}, got {sat.shape}")

    n_reads = dn.shape[0]
    pixel_shape = dn.shape[1:]
    dn2 = dn.reshape(n_reads, -1)
    sat2 = sat.reshape(n_reads, -1)
    n = dn2.shape[1]
    rate, sigma, offset = np.empty(n), np.empty(n), np.empty(n)
    valid, n_used = np.empty(n, dtype=bool), np.empty(n, dtype=np.int64)
    # every method is per sample: MERGE_CHUNK samples at a time give the same values with the
    # temporaries (a dozen (R, chunk) arrays) of one chunk, whatever the film
    for a in range(0, n, MERGE_CHUNK):
        b = min(a + MERGE_CHUNK, n)
        rate[a:b], sigma[a:b], offset[a:b], valid[a:b], n_used[a:b] = _merge_samples(
            dn2[:, a:b], sat2[:, a:b], t, cfg, method, cumulative
        )
    return HDRResult(
        rate_e_per_s=rate.reshape(pixel_shape),
        sigma_temporal_e_per_s=sigma.reshape(pixel_shape),
        sigma_fixed_e_per_s=fixed_pattern_sigma(rate, offset, cfg).reshape(pixel_shape),
        valid=valid.reshape(pixel_shape),
        n_used=n_used.reshape(pixel_shape),
    )


#: Samples merged at a time by :func:`merge_hdr` (its methods are per sample).
MERGE_CHUNK = 1 << 18


def _merge_samples(
    dn2: np.ndarray, sat2: np.ndarray, t: np.ndarray, cfg: SensorConfig, method: str, cumulative: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`merge_hdr` on (R, P) codes and flags: rate, temporal sigma, offset gain (see
    :data:`MergeMethod`), valid, reads used, each (P,)."""
    x_e = dn_to_electrons(dn2, cfg)
    usable = ~sat2
    if cumulative:  # a read is usable while it and every read before it are unsaturated
        for i in range(1, usable.shape[0]):
            usable[i] &= usable[i - 1]
    n_used = usable.sum(axis=0)
    valid = n_used > 0

    # Lower bound where every read is saturated: each clipped read under-reports, so
    # rate >= x_i / t_i for every i.
    rate = np.maximum((x_e / t[:, None]).max(axis=0), 0.0)
    sigma = np.full(rate.shape, np.inf)
    offset = np.zeros(rate.shape)
    if np.any(valid):
        sel = slice(None) if valid.all() else valid  # every sample: no copies
        m = MergeInput(
            x_e=x_e[:, sel],
            dn=dn2[:, sel],
            exposures_s=t,
            usable=usable[:, sel],
            read_var_e2=quantization_read_variance_e2(cfg),
            cumulative=cumulative,
            cfg=cfg,
        )
        rate[sel], sigma[sel], offset[sel] = HDR_METHODS[method](m)
    return rate, sigma, offset, valid, n_used


def fixed_pattern_sigma(rate_e_per_s: np.ndarray, offset_gain_per_s: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """1-sigma of the fixed pattern's error in a merged rate, electrons/s.

    The sensor draws a relative sensitivity per pixel, per row and per column (PRNU: ``prnu``,
    ``prnu_row``, ``prnu_col``) that multiplies every bucket alike, and an offset per pixel, row and
    column (DSNU, electrons: ``dsnu_e``, ``dsnu_row_e``, ``dsnu_col_e``) added to every read alike. A
    merge is linear in its reads, so the sensitivity scales the merged rate (variance
    ``(prnu_total rate)^2``, the three parts' variances adding to first order) and the offset enters
    through the merge's offset gain ``g`` (variance ``(dsnu_total g)^2``). Over the pixels of a
    flat field these are the spread the pattern adds; at one pixel, the error an uncalibrated sensor
    makes there."""
    prnu2 = cfg.prnu**2 + cfg.prnu_row**2 + cfg.prnu_col**2
    dsnu2 = cfg.dsnu_e**2 + cfg.dsnu_row_e**2 + cfg.dsnu_col_e**2
    return np.sqrt(prnu2 * rate_e_per_s**2 + dsnu2 * offset_gain_per_s**2)
