"""Photometric stereo with calibrated near lights: surface normals from images lit one light at a time.

A Lambertian surface point X with albedo rho and normal n, lit by a small source at P of radiant
intensity I0 cos(theta_e) (a flat emitter facing n_e; theta_e the angle between n_e and the
direction to X), has radiance

    L_k = rho / pi * I0 * cos(theta_e,k) * (n . l_k) / r_k^2,   l_k = (P_k - X) / r_k,  r_k = |P_k - X|

so s_k = L_k r_k^2 / cos(theta_e,k) = (rho I0 / pi) (l_k . n): linear in g = rho I0 / pi n. With
three or more lights not in shadow, least squares gives g and n = g / |g| per pixel (Woodham
1980, with the near-light falloff of the sources). X comes from a depth map (here the scene's
true depth: the normals are judged on their photometry alone). A light is left out where its
image is below ``shadow_ratio`` of the brightest (cast or attached shadow). With every light
close to the lens (multi-flash LEDs a few cm from it) the l_k are nearly parallel: the fit is
ill-conditioned across the view direction and amplifies image noise into the normals, which is
what makes it a sensitive test of the images' noise and registration.

Written by hand (a 3x3 solve per pixel): the photometric-stereo packages on PyPI assume distant
lights.
"""

from __future__ import annotations

import numpy as np


def near_light_normals(
    images: np.ndarray,
    points: np.ndarray,
    light_pos: np.ndarray,
    light_dir: np.ndarray,
    *,
    shadow_ratio: float = 0.2,
    valid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) (unit, world frame; zero where not determined) and a bool mask (H, W).

    images     (F, H, W) radiance of each light's image (luminance), ambient removed
    points     (H, W, 3) world position seen by each pixel (non-finite: no surface)
    light_pos  (F, 3) each light's centre; light_dir (F, 3) the unit direction it faces
    valid      (H, W) pixels to solve (default: all with a finite point)
    """
    images = np.asarray(images, np.float64)
    F, H, W = images.shape
    X = np.asarray(points, np.float64)
    ok = np.isfinite(X).all(axis=-1) if valid is None else (np.asarray(valid, bool) & np.isfinite(X).all(axis=-1))
    Xs = np.where(ok[..., None], X, 0.0)
    d = np.asarray(light_pos, np.float64)[:, None, None, :] - Xs[None]  # (F, H, W, 3)
    r2 = (d**2).sum(axis=-1)
    to_light = d / np.sqrt(r2)[..., None]
    cos_e = np.einsum("fhwc,fc->fhw", -to_light, np.asarray(light_dir, np.float64))  # emitter cosine towards X
    s = np.where(cos_e > 0, images * r2 / np.maximum(cos_e, 1e-12), 0.0)
    lit = (images > shadow_ratio * images.max(axis=0)[None]) & (cos_e > 0)
    wl = lit.astype(np.float64)
    M = np.einsum("fhw,fhwi,fhwj->hwij", wl, to_light, to_light)  # sum over lit lights of l l^T
    b = np.einsum("fhw,fhwi,fhw->hwi", wl, to_light, s)
    solvable = ok & (lit.sum(axis=0) >= 3)
    det = np.linalg.det(np.where(solvable[..., None, None], M, np.eye(3)))
    solvable &= np.abs(det) > 1e-12
    g = np.zeros((H, W, 3))
    g[solvable] = np.linalg.solve(M[solvable], b[solvable][..., None])[..., 0]
    norm = np.linalg.norm(g, axis=-1)
    solvable &= norm > 0
    n = np.zeros((H, W, 3))
    n[solvable] = g[solvable] / norm[solvable][:, None]
    return n, solvable


def angular_error_deg(normals: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(H, W) angle between two unit-normal images, degrees."""
    c = np.clip((np.asarray(normals) * np.asarray(truth)).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(c))
