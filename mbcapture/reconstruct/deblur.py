"""Motion deblurring of coded exposures (the flutter shutter), arrays in, arrays out.

A read's blur kernel comes from the scene's motion sampled over the read's gated time
(:func:`read_samples`: where the image moved and for how long); :func:`deblur_fourier` inverts one
read, :func:`deblur_least_squares` several reads together (the two-bucket flutter shutter).
The flutter-shutter application (:mod:`mbcapture.apps.flutter_shutter`) and the section-6
figures use these.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError

#: Time steps over the capture for the exposure kernels.
KERNEL_TIME_STEPS = 40_000


# --------------------------------------------------------------------------------- kernels
def displacement_px(scene, times_s: np.ndarray, t_ref_s: float, width: int, height: int) -> np.ndarray:
    """(T, 2) image displacement (px) of the moving object at ``times_s`` relative to ``t_ref_s``:
    the mean over the scene's motion points (they move together for a rigid, fronto-parallel object)."""
    t = np.concatenate([[t_ref_s], np.asarray(times_s, float)])
    px = scene.camera.project(np.asarray(scene.motion_points(t)), width, height).mean(axis=1)
    return px[1:] - px[0]


def spread_kernel(shifts_px: np.ndarray, weights_s: np.ndarray) -> tuple[int, np.ndarray]:
    """(first integer shift, kernel (L,) seconds): each weight spread linearly onto the two integer shifts
    around its (fractional) shift; the kernel sums to the total weight."""
    s = np.asarray(shifts_px, float)
    w = np.asarray(weights_s, float)
    lo = np.floor(s).astype(np.int64)
    frac = s - lo
    first = int(lo.min())
    h = np.zeros(int(lo.max()) - first + 2)
    np.add.at(h, lo - first, w * (1 - frac))
    np.add.at(h, lo - first + 1, w * frac)
    while len(h) > 1 and h[-1] == 0:
        h = h[:-1]
    return first, h


def read_samples(
    timeline, read, scene, t_ref_s: float, width: int, height: int, steps: int = KERNEL_TIME_STEPS
) -> tuple[np.ndarray, np.ndarray]:
    """(shifts px, seconds) of ``read``: the exact gated seconds of its buckets in each of ``steps`` equal
    time steps over the capture (steps without gated time left out), at the object's displacement
    along the rows mid-step, relative to its position at ``t_ref_s``."""
    edges = np.unique(np.linspace(timeline.start_tick, timeline.end_tick, steps + 1).round().astype(np.int64))
    gated = sum(np.diff(timeline.gated_ticks(edges, b)).astype(float) for b in read.buckets) * float(timeline.tick_s)
    keep = gated > 0
    mid = timeline.seconds((edges[:-1] + edges[1:]) / 2)
    d = displacement_px(scene, np.asarray(mid, float)[keep], t_ref_s, width, height)
    if np.abs(d[:, 1]).max(initial=0.0) > 0.05 * max(1.0, np.abs(d[:, 0]).max(initial=0.0)):
        raise ConfigError(
            f"scene.name: {scene.name!r} moves vertically in the image; flutter_shutter deblurs motion "
            "along the image rows only"
        )
    return d[:, 0], gated[keep]


def read_kernel(
    timeline, read, scene, t_ref_s: float, width: int, height: int, steps: int = KERNEL_TIME_STEPS
) -> tuple[int, np.ndarray]:
    """Exposure kernel of ``read`` on integer shifts (:func:`spread_kernel` of :func:`read_samples`)."""
    return spread_kernel(*read_samples(timeline, read, scene, t_ref_s, width, height, steps))


def kernel_spectrum(shifts_px: np.ndarray, weights_s: np.ndarray, n_fft: int, full: bool = False) -> np.ndarray:
    """H(w) = sum_i w_i exp(-i w s_i) at the rfft frequencies of ``n_fft`` (``full``: all fft frequencies):
    band-limited fractional shifts; shifts binned to 1/256 px first."""
    q = np.round(np.asarray(shifts_px, float) * 256).astype(np.int64)
    u, inv = np.unique(q, return_inverse=True)
    w = np.bincount(inv, weights=np.asarray(weights_s, float))
    om = 2 * np.pi * (np.fft.fftfreq(n_fft) if full else np.fft.rfftfreq(n_fft))
    return np.exp(-1j * np.outer(om, u / 256.0)) @ w


def fft_length(samples, width: int) -> int:
    """Row length for the circular model: the row plus the blur's extent, rounded up to a fast size."""
    from scipy.fft import next_fast_len

    reach = max(float(np.abs(s).max(initial=0.0)) for s, _ in samples)
    return next_fast_len(int(width + 2 * np.ceil(reach) + 2), real=True)


def deblur_fourier(reads: np.ndarray, samples, weights: np.ndarray, regularization: float = 1e-6) -> np.ndarray:
    """Sharp image (H, W, C) from blurred reads (R, H, W, C) (radiance x seconds): least squares over a
    zero-padded row with band-limited (sinc) fractional shifts, solved per frequency:
    F = sum_r w_r conj(H_r) B_r / (sum_r w_r |H_r|^2 + lambda mean(.)). ``samples``: [(shifts, seconds)]."""
    r, hh, ww, cc = reads.shape
    n = fft_length(samples, ww)
    spectra = np.stack([kernel_spectrum(s, w, n) for s, w in samples])  # (R, F)
    out = np.empty((hh, ww, cc))
    for c in range(cc):
        den = np.einsum("r,rf->f", weights[:, c], np.abs(spectra) ** 2)
        den = den + regularization * float(den.mean())
        bf = np.fft.rfft(reads[..., c], n=n, axis=-1)  # (R, H, F)
        num = np.einsum("r,rf,rhf->hf", weights[:, c], np.conj(spectra), bf)
        out[..., c] = np.fft.irfft(num / den, n=n, axis=-1)[:, :ww]
    return out


def white_noise_gain(samples, weights: np.ndarray, width: int, exposure_s: float, regularization: float = 0.0) -> float:
    """RMS noise of :func:`deblur_fourier`'s result for white noise of variance 1 / w_r in read r, times the
    total exposure: 1 for an unblurred image taken with that exposure and unit noise (weights (R,))."""
    n = fft_length(samples, width)
    p = sum(w * np.abs(kernel_spectrum(s, t, n, full=True)) ** 2 for (s, t), w in zip(samples, weights))
    p = p + regularization * float(p.mean())
    return float(np.sqrt(np.mean(1.0 / p)) * exposure_s)


def blur_matrix(first: int, h: np.ndarray, n: int, cols: tuple[int, int] | None = None) -> np.ndarray:
    """(n, m) A with (A f)[x] = sum_s h[s - first] f[x - s] for the unknowns f[cols[0]:cols[1]] (default:
    all n pixels of the row; m = cols[1] - cols[0])."""
    c0, c1 = cols or (0, n)
    x, y = np.arange(n), np.arange(c0, c1)
    k = x[:, None] - y[None, :] - first
    ok = (k >= 0) & (k < len(h))
    return np.where(ok, h[np.clip(k, 0, len(h) - 1)], 0.0)


def support(kernels, n: int) -> tuple[int, int]:
    """Pixels [lo, hi) of a row whose blurred light stays inside the row under every kernel: the unknowns.
    Outside them the sharp image is taken as 0 (a black background, the object inside the frame all the
    time), which makes the system overdetermined by the kernels' lengths, as in Raskar et al.'s model;
    solving for all n pixels instead leaves the unknowns at the frame's edges nearly unconstrained."""
    lo = max(-first for first, _ in kernels)
    hi = min(n - (first + len(h) - 1) for first, h in kernels)
    lo, hi = max(lo, 0), min(hi, n)
    if hi - lo < 1:
        raise ConfigError(
            f"render.width: the motion blur ({max(len(h) for _, h in kernels)} px) is wider than the "
            f"{n}-pixel row; nothing left to deblur"
        )
    return lo, hi


def normal_matrix(kernels, weights: np.ndarray, n: int, regularization: float) -> np.ndarray:
    """sum_r w_r A_r^T A_r + lambda mean(diag) I for one channel (weights (R,)), over :func:`support`."""
    cols = support(kernels, n)
    m = np.zeros((cols[1] - cols[0],) * 2)
    for (first, h), w in zip(kernels, weights):
        a = blur_matrix(first, h, n, cols)
        m += w * a.T @ a
    return m + regularization * float(np.mean(np.diag(m))) * np.eye(len(m))


def deblur_least_squares(reads: np.ndarray, kernels, weights: np.ndarray, regularization: float = 1e-6) -> np.ndarray:
    """Sharp image (H, W, C) from blurred reads (R, H, W, C) (radiance x seconds), their integer-shift
    kernels [(first, h)] (:func:`spread_kernel`) and weights (R, C): weighted least squares along the rows
    over the unknowns of :func:`support` (0 elsewhere), all rows at once."""
    from scipy.linalg import cho_factor, cho_solve

    r, hh, ww, cc = reads.shape
    lo, hi = support(kernels, ww)
    out = np.zeros((hh, ww, cc))
    mats = [blur_matrix(f, h, ww, (lo, hi)) for f, h in kernels]
    for c in range(cc):
        m = sum(weights[i, c] * a.T @ a for i, a in enumerate(mats))
        m = m + regularization * float(np.mean(np.diag(m))) * np.eye(hi - lo)
        rhs = sum(weights[i, c] * a.T @ reads[i, :, :, c].T for i, a in enumerate(mats))  # (m, H)
        out[:, lo:hi, c] = cho_solve(cho_factor(m), rhs).T
    return out


def pixel_least_squares(reads, samples, weights, regularization):
    return deblur_least_squares(reads, [spread_kernel(s, w) for s, w in samples], weights, regularization)
