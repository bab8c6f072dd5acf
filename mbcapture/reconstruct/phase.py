"""Structured light: phase shifting, Gray codes and phase unwrapping, arrays in, arrays out.

The structured-light application (:mod:`mbcapture.apps.structured_light`) projects the patterns,
renders the truth and scores; the decoding lives here. Triangulation is a callable ``tri(u) -> z``
(projector column to depth) built from :mod:`mbcapture.scene.projective`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..scene.projective import pixel_rays


# --------------------------------------------------------------------------------- decoding
def wrapped_phase(images: np.ndarray, deltas_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N-step phase shifting of images (N, H, W) taken under patterns (1 + cos(phi - d_k)) / 2:
    (phase in [0, 2 pi), modulation B = amplitude of the cosine, mean). Least squares for any N >= 3
    equally spaced shifts."""
    d = np.asarray(deltas_rad, float)
    imgs = np.asarray(images, float)
    s = np.tensordot(np.sin(d), imgs, axes=1)
    c = np.tensordot(np.cos(d), imgs, axes=1)
    n = len(d)
    return np.mod(np.arctan2(s, c), 2 * np.pi), 2.0 * np.hypot(s, c) / n, imgs.mean(axis=0)


def gray_to_binary(g: np.ndarray) -> np.ndarray:
    """Inverse of the reflected binary code n ^ (n >> 1)."""
    n = np.asarray(g, np.int64).copy()
    shift = np.right_shift(n, 1)
    while np.any(shift):
        n ^= shift
        shift = np.right_shift(shift, 1)
    return n


def decode_gray(white: np.ndarray, bits: np.ndarray, ambient: np.ndarray | None) -> np.ndarray:
    """Stripe index (H, W) from a white image and M bit images (M, H, W), most significant first.
    With an ambient image: bit = I_m - A > (I_white - A) / 2; without: I_m > I_white / 2."""
    bits = np.asarray(bits, float)
    if ambient is not None:
        on = (bits - ambient[None]) > 0.5 * (white - ambient)[None]
    else:
        on = bits > 0.5 * white[None]
    m = bits.shape[0]
    g = np.zeros(white.shape, np.int64)
    for i in range(m):
        g |= on[i].astype(np.int64) << (m - 1 - i)
    return gray_to_binary(g)


def period_ambiguity(
    camera, projector, proj_width: int, periods: int, width: int, height: int, z_min: float, z_max: float
) -> float:
    """Largest disparity range (projector texels) over the camera's pixels for depths in [z_min, z_max],
    as a fraction of one fringe period: below 1, depth_range unwrapping is unique everywhere."""

    yy, xx = np.mgrid[0:height, 0:width].astype(float) + 0.5
    d = pixel_rays(camera, xx, yy, width, height)
    o = np.asarray(camera.origin, float)
    u = [projector.project(o + z * d, proj_width, max(1, round(proj_width * 3 / 4)))[..., 0] for z in (z_min, z_max)]
    return float(np.abs(u[0] - u[1]).max() / (proj_width / periods))


def unwrap_depth_range(
    phase, valid, tri: Callable[[np.ndarray], np.ndarray], periods: int, proj_width: int, z_min: float, z_max: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(projector column, depth, valid): per pixel the one period whose depth lies in [z_min, z_max]."""
    lam = proj_width / periods
    cols, depths = [], []
    for k in range(periods):
        u = (phase / (2 * np.pi) + k) * lam
        cols.append(u)
        depths.append(tri(u))
    u_all, z_all = np.stack(cols), np.stack(depths)
    with np.errstate(invalid="ignore"):
        ok = (z_all >= z_min) & (z_all <= z_max)
    one = valid & (ok.sum(axis=0) == 1)
    pick = np.argmax(ok, axis=0)
    u = np.take_along_axis(u_all, pick[None], 0)[0]
    z = np.take_along_axis(z_all, pick[None], 0)[0]
    return np.where(one, u, np.nan), np.where(one, z, np.nan), one


def unwrap_spatial(phase, valid, tri, periods, proj_width, z_min, z_max):
    """scikit-image's unwrap_phase over the valid pixels, then the global 2 pi offset that puts the most
    pixels in [z_min, z_max]."""
    from skimage.restoration import unwrap_phase

    lam = proj_width / periods
    wrapped = np.where(valid, phase - np.pi, 0.0)  # unwrap_phase wants (-pi, pi]
    psi = np.asarray(unwrap_phase(np.ma.masked_array(wrapped, ~valid)).filled(np.nan)) + np.pi
    best = None
    for m in range(-periods, 2 * periods + 1):
        u = (psi / (2 * np.pi) + m) * lam
        z = tri(u)
        with np.errstate(invalid="ignore"):
            n_in = int(np.sum(valid & (z >= z_min) & (z <= z_max)))
        if best is None or n_in > best[0]:
            best = (n_in, u, z)
    _, u, z = best
    with np.errstate(invalid="ignore"):
        ok = valid & (z >= z_min) & (z <= z_max)
    return np.where(ok, u, np.nan), np.where(ok, z, np.nan), ok


def unwrap_none(phase, valid, tri, periods, proj_width, z_min, z_max):
    """u = phi W / (2 pi P): the first period only (right for single-period patterns)."""
    u = phase / (2 * np.pi) * proj_width / periods
    z = tri(u)
    with np.errstate(invalid="ignore"):
        ok = valid & (z >= z_min) & (z <= z_max)
    return np.where(ok, u, np.nan), np.where(ok, z, np.nan), ok


#: Phase unwrapping: ``fn(phase, valid, triangulate(u) -> z, periods, projector width, z_min, z_max)
#: -> (projector column, depth, valid)``.
UNWRAP_METHODS: dict[str, Callable] = {
    "depth_range": unwrap_depth_range,
    "spatial": unwrap_spatial,
    "none": unwrap_none,
}
