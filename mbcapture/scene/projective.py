"""Pinhole geometry shared by cameras and projectors: pixel rays, column planes, triangulation.

Conventions are those of :class:`Camera` (Mitsuba's ``perspective`` sensor with
``fov_axis='x'`` and a ``look_at`` frame): pixel coordinates (x right, y down) with pixel centres at
half-integers, the horizontal field of view spanning the width. A projector
(:class:`mbcapture.render.build.Projector`) maps its image onto the scene exactly like a camera
of the same pose, field of view and resolution sees it, so the same functions serve both.
Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole camera. ``fov_deg`` is the horizontal field of view."""

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float

    def project(self, points: np.ndarray, width: int, height: int) -> np.ndarray:
        """World points (..., 3) -> pixel coordinates (..., 2) as (x right, y down).

        Matches Mitsuba's ``perspective`` sensor with ``fov_axis='x'`` and a
        ``look_at`` transform, pixel centres at half-integers.
        """
        o, fwd, right, up = frame(self)
        d = np.asarray(points, float) - o
        z = d @ fwd
        if np.any(z <= 0):
            raise ValueError("a motion point lies behind the camera")
        x_cam = (d @ right) / z
        y_cam = (d @ up) / z
        tan_half = np.tan(np.radians(self.fov_deg) / 2)
        px = (x_cam / tan_half * 0.5 + 0.5) * width
        py = (0.5 - y_cam / tan_half * 0.5 * width / height) * height
        return np.stack([px, py], axis=-1)


def frame(camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(origin, forward, image right, image up) of a camera, world unit vectors: Mitsuba's
    ``look_at`` frame (its camera x axis, up x forward, points to image left). The one place the
    frame is built: projection (:meth:`Camera.project`), camera poses
    (:func:`mbcapture.scene.camera_motion.look_at_matrix`) and rays all use it."""
    o = np.asarray(camera.origin, float)
    fwd = np.asarray(camera.target, float) - o
    fwd /= np.linalg.norm(fwd)
    left = np.cross(np.asarray(camera.up, float), fwd)  # Mitsuba's look_at x axis points to image left
    left /= np.linalg.norm(left)
    up = np.cross(fwd, left)
    return o, fwd, -left, up


def tan_half(camera) -> float:
    return float(np.tan(np.radians(camera.fov_deg) / 2))


def pixel_rays(camera, px: np.ndarray, py: np.ndarray, width: int, height: int) -> np.ndarray:
    """World directions (..., 3) through image positions (px, py) (pixels, x right, y down),
    scaled so that their component along the optical axis is 1 (a point at depth z is origin + z d)."""
    o, fwd, right, up = frame(camera)
    th = tan_half(camera)
    xc = (np.asarray(px, float) / width - 0.5) * 2 * th
    yc = (0.5 - np.asarray(py, float) / height) * 2 * th * height / width
    return fwd + xc[..., None] * right + yc[..., None] * up


def column_planes(camera, px: np.ndarray, width: int) -> np.ndarray:
    """Normals (..., 3) of the planes through the optical centre holding every point that projects
    to image column ``px`` (pixels); not normalized."""
    o, fwd, right, up = frame(camera)
    xc = (np.asarray(px, float) / width - 0.5) * 2 * tan_half(camera)
    return right[None] * np.ones(np.shape(px) + (1,)) - xc[..., None] * fwd


def triangulate_columns(
    camera, projector, proj_col: np.ndarray, proj_width: int, width: int, height: int
) -> np.ndarray:
    """Depth along the camera's optical axis (H, W) of the point each camera pixel centre sees, given
    the projector column ``proj_col`` (H, W; pixels of a projector image ``proj_width`` wide) that lit
    it: the camera ray meets the projector's column plane. NaN where ``proj_col`` is NaN or the ray
    runs parallel to the plane; negative depths (behind the camera) are NaN too."""
    yy, xx = np.mgrid[0:height, 0:width].astype(float) + 0.5
    d = pixel_rays(camera, xx, yy, width, height)
    n = column_planes(projector, proj_col, proj_width)
    c = np.asarray(camera.origin, float)
    p = np.asarray(projector.origin, float)
    den = np.einsum("...i,...i->...", d, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = ((p - c) @ np.moveaxis(n, -1, 0).reshape(3, -1)).reshape(den.shape) / den
    return np.where(np.isfinite(z) & (z > 0), z, np.nan)


def points_from_depth(camera, z: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of a depth image (depth along the optical axis at pixel centres)."""
    h, w = z.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float) + 0.5
    return np.asarray(camera.origin, float) + z[..., None] * pixel_rays(camera, xx, yy, w, h)
