"""Demultiplexing coded per-pixel reads into full-resolution sub-frame images.

A coded two-bucket sensor (Wei et al., ECCV 2018) gives every pixel p a few reads m(p) (R), each
a known 0/1 combination of the S sub-frame images x(p): m(p) = A(p) x(p), A(p) (R, S) from the
pixel's gate code (:meth:`mbcapture.timing.gatecode.GateCode.measurement`). One pixel's reads cannot
determine S > R unknowns; neighbouring pixels carry other codes, so a neighbourhood can.

:func:`demultiplex` solves, at every pixel, the weighted least-squares problem over its
neighbourhood, assuming each sub-frame image locally constant:

    x(p) = argmin_x  sum_q w(q - p) || m(q) - A(q) x ||^2,   w a separable tent window

through its normal equations N(p) x = b(p), N = sum w A^T A (S x S), b = sum w A^T m: S(S+1)/2 + S
filtered product images and one batched S x S solve per pixel. For a tiled code this is the
least-squares counterpart of the C2B paper's "bucket demosaicing" (interpolate each code
position's samples to full resolution, then solve per pixel): the tent of half-width equal to
the tile's period interpolates each position's lattice bilinearly, and here the interpolation
and the solve are one weighted fit. It works as well for random codes, whose tile is the film.
Samples marked bad (a saturated read) get weight zero. Like any demosaicing it assumes the
images smooth over the window, so edges blur over about the tile's size.

:func:`demultiplex_guided` makes the window edge-aware (a joint-bilateral fit): neighbour q's
weight is also exp(-((g(q) - g(p)) / (sigma g(p)))^2 / 2), with g the pixel's total light, the sum of
its reads, which a two-bucket pixel measures at full resolution whatever its code. The fit then
stops at silhouettes and at shadow edges (where one of S sub-frames goes dark, the total drops by
about 1/S), instead of mixing both sides. The weights differ per pixel, so it sums the window's
offsets explicitly instead of filtering.

Written by hand: no library demultiplexes per-pixel coded reads; the filtering is OpenCV's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Pixels whose normal equations are worse conditioned than this carry no estimate.
MAX_CONDITION = 1e6


@dataclass(frozen=True)
class Demultiplexed:
    """images (S, H, W, C) float64 sub-frame images (units of the reads); valid (H, W) bool where
    the neighbourhood's codes determine every sub-frame; condition (H, W) the normal equations'
    condition number; variance (S, H, W) each estimate's variance for independent reads of unit
    variance (times the reads' noise variance: the estimate's; inf where not valid); noise_gain (S,)
    its median over the valid pixels."""

    images: np.ndarray
    valid: np.ndarray
    condition: np.ndarray
    variance: np.ndarray
    noise_gain: np.ndarray


def tent(radius: int) -> np.ndarray:
    """The normalised 1D tent of half-width ``radius`` (weights (radius - |d|) / radius, |d| < radius)."""
    d = np.arange(-radius + 1, radius)
    w = (radius - np.abs(d)).astype(np.float64)
    return w / w.sum()


def _filter(img: np.ndarray, ky: np.ndarray, kx: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.sepFilter2D(
        np.ascontiguousarray(img, dtype=np.float64), cv2.CV_64F, kx, ky, borderType=cv2.BORDER_REFLECT_101
    )


def code_rank(A: np.ndarray) -> int:
    """The rank of the stacked measurements of every distinct pixel code in ``A`` (R, S, H, W): the
    most sub-frames any neighbourhood of this code could separate."""
    R, S = A.shape[:2]
    rows = np.unique(A.reshape(R, S, -1).transpose(2, 0, 1).reshape(-1, R * S), axis=0).reshape(-1, S)
    return int(np.linalg.matrix_rank(rows))


def _solve(N: np.ndarray, N2: np.ndarray, b: np.ndarray) -> Demultiplexed:
    """Per-pixel solve of the normal equations N x = b (N (H, W, S, S), b (H, W, S, C)); N2: the
    normal matrix with squared weights (the fit's noise)."""
    H, W, S, C = b.shape
    ev = np.linalg.eigvalsh(N)  # symmetric, batched: the condition number per pixel
    condition = np.where(ev[..., 0] > 0, ev[..., -1] / np.maximum(ev[..., 0], 1e-300), np.inf)
    valid = condition < MAX_CONDITION
    x = np.zeros((H, W, S, C))
    variance = np.full((H, W, S), np.inf)
    gain = np.full(S, np.inf)
    if valid.any():
        inv = np.linalg.inv(N[valid])
        x[valid] = inv @ b[valid]
        # the weighted fit's variance for unit-variance independent reads: N^-1 N2 N^-1
        variance[valid] = np.diagonal(inv @ N2[valid] @ inv, axis1=-2, axis2=-1)
        gain = np.median(variance[valid], axis=0)
    return Demultiplexed(
        images=np.moveaxis(x, 2, 0),
        valid=valid,
        condition=condition,
        variance=np.moveaxis(variance, 2, 0),
        noise_gain=gain,
    )


def _products(reads: np.ndarray, A: np.ndarray, bad: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: P (H, W, S, S) = A^T diag(w) A and Q (H, W, S, C) = A^T diag(w) m, w = 0 on bad
    samples: what each pixel adds to the normal equations of a window holding it."""
    R, H, W, C = reads.shape
    if A.shape[0] != R or A.shape[2:] != (H, W):
        raise ValueError(f"A must be (reads={R}, sub-frames, {H}, {W}), got {A.shape}")
    w = np.ones((R, H, W)) if bad is None else (~np.asarray(bad, bool)).astype(np.float64)
    Aw = A * w[:, None]
    P = np.einsum("rihw,rjhw->hwij", Aw, A)
    Q = np.einsum("rihw,rhwc->hwic", Aw, reads)
    return P, Q


def demultiplex_guided(
    reads: np.ndarray, A: np.ndarray, radius: tuple[int, int], sigma: float = 0.1, bad: np.ndarray | None = None
) -> Demultiplexed:
    """:func:`demultiplex` with edge-aware weights: the tent times a Gaussian of the relative
    difference of the pixels' total light (the sum of their reads' channel means), width ``sigma``."""
    reads = np.asarray(reads, np.float64)
    H, W, C = reads.shape[1:]
    S = A.shape[1]
    P, Q = _products(reads, A, bad)
    guide = reads.mean(axis=-1).sum(axis=0)
    scale = sigma * np.maximum(guide, 1e-12 + 1e-6 * float(guide.max(initial=0.0)))
    ty, tx = tent(max(1, radius[0])), tent(max(1, radius[1]))
    ry, rx = len(ty) // 2, len(tx) // 2
    pad = ((ry, ry), (rx, rx))
    Pp = np.pad(P, pad + ((0, 0), (0, 0)), mode="reflect")
    Qp = np.pad(Q, pad + ((0, 0), (0, 0)), mode="reflect")
    gp = np.pad(guide, pad, mode="reflect")
    N, N2 = np.zeros((H, W, S, S)), np.zeros((H, W, S, S))
    b = np.zeros((H, W, S, C))
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            win = (slice(ry + dy, ry + dy + H), slice(rx + dx, rx + dx + W))
            wq = ty[dy + ry] * tx[dx + rx] * np.exp(-0.5 * ((gp[win] - guide) / scale) ** 2)
            N += wq[..., None, None] * Pp[win]
            N2 += (wq**2)[..., None, None] * Pp[win]
            b += wq[..., None, None] * Qp[win]
    return _solve(N, N2, b)


def demultiplex(
    reads: np.ndarray, A: np.ndarray, radius: tuple[int, int], bad: np.ndarray | None = None
) -> Demultiplexed:
    """Sub-frame images from coded reads.

    reads   (R, H, W, C) each pixel's reads (electrons, or any linear unit)
    A       (R, S, H, W) 0/1: read r of pixel p holds sub-frame s
    radius  (ry, rx) half-widths of the tent window, px (a tiled code: its tile's height and width)
    bad     (R, H, W) bool: samples to leave out (saturated), or None
    """
    reads = np.asarray(reads, np.float64)
    H, W, C = reads.shape[1:]
    S = A.shape[1]
    P, Q = _products(reads, A, bad)
    ky, kx = tent(max(1, radius[0])), tent(max(1, radius[1]))
    N = np.empty((H, W, S, S))
    N2 = np.empty((H, W, S, S))  # the same with squared weights: the fit's noise
    for i in range(S):
        for j in range(i, S):
            N[..., i, j] = N[..., j, i] = _filter(P[..., i, j], ky, kx)
            N2[..., i, j] = N2[..., j, i] = _filter(P[..., i, j], ky**2, kx**2)
    b = np.empty((H, W, S, C))
    for i in range(S):
        for c in range(C):
            b[..., i, c] = _filter(Q[..., i, c], ky, kx)
    return _solve(N, N2, b)
