"""Indirect time of flight: phasors from tap values, phase unwrapping over several frequencies, depth, and the
error measures of a depth map (arrays in, arrays out; docs/tof.md).

A tap of demodulation phase phi_k collects ``B_k = o + a cos(theta - phi_k)`` (o: the light's common mode,
ambient included; a: the modulated amplitude; theta = 4 pi f d / c for a surface at distance d seen by an
illuminator at the camera). :func:`phasor_fit` solves the least-squares fit of (o, a cos theta, a sin theta)
to any number >= 3 of phases (for evenly spaced phases the classic N-bucket arctangent); the phase is
atan2 of the last two, the depth ``c theta / (4 pi f)`` modulo the unambiguous range ``c / (2 f)``.

Several frequencies are unwrapped by a lookup over the joint unambiguous range (:func:`unwrap`): every
wrap count of the first frequency inside the range is a candidate distance; each other frequency takes
its wrap count nearest to it, and the candidate whose frequencies agree best (least weighted squared
spread) wins; the depth is the frequencies' weighted mean (weights f^2, each frequency's depth noise
being proportional to 1 / f at equal phase noise). Written here: the search is a few lines of numpy.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from ..sensor.demodulation import C_M_PER_S, unambiguous_range_m


def phasor_fit(values: np.ndarray, phases_rad: np.ndarray, variances: np.ndarray | None = None) -> dict:
    """Least-squares fit of ``values[k] = o + I cos(phi_k) + Q sin(phi_k)`` over the first axis.

    values (P, ...) tap values (any unit); phases_rad (P,); variances (P, ...) of the values (optional):
    the fit's standard deviation of I and Q (``sigma``, the mean of the two) propagated from them.
    Returns offset, amplitude sqrt(I^2 + Q^2), phase atan2(Q, I) in [0, 2 pi), sigma (or None) and the
    residual's rms over the taps (0 for three phases; with more, taps that disagree with any one phasor: motion
    between them, or even harmonics)."""
    phi = np.asarray(phases_rad, dtype=np.float64)
    A = np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi)], axis=1)  # (P, 3)
    pinv = np.linalg.pinv(A)  # (3, P)
    v = np.asarray(values, dtype=np.float64)
    coef = np.tensordot(pinv, v, axes=(1, 0))  # (3, ...)
    offset, i, q = coef
    residual = np.sqrt(np.mean((v - np.tensordot(A, coef, axes=(1, 0))) ** 2, axis=0))
    sigma = None
    if variances is not None:
        var = np.asarray(variances, dtype=np.float64)
        var_i = np.tensordot(pinv[1] ** 2, var, axes=(0, 0))
        var_q = np.tensordot(pinv[2] ** 2, var, axes=(0, 0))
        sigma = np.sqrt(0.5 * (var_i + var_q))
    return {
        "offset": offset,
        "amplitude": np.hypot(i, q),
        "phase": np.mod(np.arctan2(q, i), 2 * math.pi),
        "sigma": sigma,
        "residual": residual,
    }


def wrapped_depth(phase: np.ndarray, frequency_hz: float) -> np.ndarray:
    """Distance (m) of a phase at one frequency, in [0, c / (2 f))."""
    return np.asarray(phase) / (2 * math.pi) * unambiguous_range_m(frequency_hz)


def joint_range_m(frequencies_hz: list[float]) -> float:
    """The frequencies' joint unambiguous range c / (2 gcd(f)) (exact rational gcd of the values as written)."""
    fr = [Fraction(repr(float(f))) for f in frequencies_hz]
    den = math.lcm(*(f.denominator for f in fr))
    g = Fraction(math.gcd(*(int(f * den) for f in fr)), den)
    return C_M_PER_S / (2.0 * float(g))


def unwrap(phases: np.ndarray, frequencies_hz: list[float], max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth from wrapped phases at several frequencies by lookup (module doc).

    phases (F, ...) in [0, 2 pi); returns (depth m, spread m: the weighted rms disagreement of the
    frequencies at the chosen candidate, large where unwrapping is unreliable). One frequency: its wrapped depth
    (``max_range_m`` is then at most its range) and zero spread."""
    freqs = [float(f) for f in frequencies_hz]
    wrapped = np.stack([wrapped_depth(p, f) for p, f in zip(phases, freqs)])
    if len(freqs) == 1:
        return wrapped[0], np.zeros_like(wrapped[0])
    ranges = np.array([unambiguous_range_m(f) for f in freqs])
    w = np.array(freqs) ** 2
    w = w / w.sum()
    best_cost = np.full(wrapped.shape[1:], np.inf)
    best_depth = np.zeros(wrapped.shape[1:])
    for n0 in range(int(math.ceil(max_range_m / ranges[0]))):
        cand0 = wrapped[0] + n0 * ranges[0]
        cands = [cand0]
        for f in range(1, len(freqs)):
            n = np.round((cand0 - wrapped[f]) / ranges[f])
            cands.append(wrapped[f] + n * ranges[f])
        cands = np.stack(cands)
        mean = np.tensordot(w, cands, axes=(0, 0))
        cost = np.tensordot(w, (cands - mean) ** 2, axes=(0, 0))
        better = (cost < best_cost) & (mean < max_range_m + ranges.min() / 2)
        best_cost = np.where(better, cost, best_cost)
        best_depth = np.where(better, mean, best_depth)
    return best_depth, np.sqrt(best_cost)


def depth_noise_m(amplitude: np.ndarray, sigma: np.ndarray, frequency_hz: float) -> np.ndarray:
    """The depth's standard deviation from a fit's phasor noise: c / (4 pi f) x sigma / amplitude."""
    return unambiguous_range_m(frequency_hz) / (2 * math.pi) * sigma / np.maximum(amplitude, 1e-30)


def edge_band(truth_m: np.ndarray, jump_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels within one pixel of a depth discontinuity of at least ``jump_m`` in the true depth: (band,
    nearest surface's depth, farthest surface's depth) over each pixel's 3x3 neighbourhood."""
    t = np.where(np.isfinite(truth_m), truth_m, np.nan)
    filled_lo = np.where(np.isfinite(t), t, np.inf)
    filled_hi = np.where(np.isfinite(t), t, -np.inf)
    lo = minimum_filter(filled_lo, size=3, mode="nearest")
    hi = maximum_filter(filled_hi, size=3, mode="nearest")
    band = np.isfinite(lo) & np.isfinite(hi) & (hi - lo >= jump_m)
    return band, lo, hi


def flying_pixels(depth_m: np.ndarray, valid: np.ndarray, truth_m: np.ndarray, jump_m: float, margin: float = 0.25):
    """Pixels at depth edges whose depth is neither surface's: between the nearest and the farthest true depth
    around them and more than ``margin`` of the jump from both (a pixel straddling the edge mixes the two
    phasors; motion between taps does too). A margin in proportion to the jump keeps a bias that shifts a
    whole surface (multipath) from counting. Returns (mask, number of valid edge pixels)."""
    band, lo, hi = edge_band(truth_m, jump_m)
    d = np.where(valid, depth_m, np.nan)
    gap = margin * (hi - lo)
    with np.errstate(invalid="ignore"):
        flying = band & valid & (d - lo > gap) & (hi - d > gap)
    return flying, int((band & valid).sum())


def depth_scores(depth_m: np.ndarray, truth_m: np.ndarray, mask: np.ndarray, tolerance_m: float) -> dict:
    """MAE, RMSE, mean signed error (bias) in mm and the fraction within ``tolerance_m`` over ``mask`` (pixels
    with a finite depth and truth)."""
    m = mask & np.isfinite(depth_m) & np.isfinite(truth_m)
    n = int(m.sum())
    if n == 0:
        return {"pixels": 0, "mae_mm": None, "rmse_mm": None, "bias_mm": None, "within_tolerance": None}
    e = (depth_m[m] - truth_m[m]) * 1e3
    return {
        "pixels": n,
        "mae_mm": float(np.mean(np.abs(e))),
        "rmse_mm": float(np.sqrt(np.mean(e**2))),
        "bias_mm": float(np.mean(e)),
        "median_abs_mm": float(np.median(np.abs(e))),
        "within_tolerance": float(np.mean(np.abs(e) <= tolerance_m * 1e3)),
    }
