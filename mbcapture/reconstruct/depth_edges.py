"""Depth edges from multi-flash shadows (Raskar, Tan, Feris, Yu and Turk, "Non-photorealistic camera", SIGGRAPH
2004), arrays in and out: each flash's epipole in the image (:func:`epipole`), the shadow-free max composite, the
ratio images traversed away from each epipole for a negative step (:func:`raskar_depth_edges`), a Canny baseline
(OpenCV), the true depth discontinuities of a depth map and the edge scores (precision, recall, F1 within a
tolerance) of a detection against them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..metrics import luminance


@dataclass(frozen=True)
class Epipole:
    """Where a light's centre projects in the image, pixels (x right, y down).

    finite: ``xy`` is the epipole; ``sign`` +1 when the light is in front of the lens plane
    (shadows run away from the epipole), -1 behind it (they run towards it).
    infinite (light in the lens plane): ``xy`` is the unit image direction towards the light;
    shadows run the opposite way along parallel lines.
    """

    finite: bool
    xy: tuple[float, float]
    sign: int = 1

    def away(self, height: int, width: int) -> np.ndarray:
        """(H, W, 2) unit steps (dx, dy) per pixel along the epipolar line, away from the light."""
        if not self.finite:
            d = -np.asarray(self.xy, float)
            return np.broadcast_to(d / np.linalg.norm(d), (height, width, 2)).copy()
        yy, xx = np.mgrid[0:height, 0:width]
        v = np.stack([xx + 0.5 - self.xy[0], yy + 0.5 - self.xy[1]], axis=-1) * self.sign
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def epipole(camera, position, width: int, height: int) -> Epipole:
    """The epipole of a light at world ``position`` for ``camera`` (a :class:`~mbcapture.scene.projective.Camera`)."""
    o = np.asarray(camera.origin, float)
    fwd = np.asarray(camera.target, float) - o
    fwd /= np.linalg.norm(fwd)
    off = np.asarray(position, float) - o
    dist = float(np.linalg.norm(off))
    if dist == 0.0:
        raise ConfigError("scene: a flash at the lens centre has no epipole (no shadows to see)")
    z = float(off @ fwd)
    if abs(z) <= 1e-9 * dist:  # in the lens plane: the image direction of the offset, at infinity
        p0 = camera.project(o + fwd, width, height)
        p1 = camera.project(o + fwd + off / dist * 1e-3, width, height)
        d = p1 - p0
        return Epipole(False, tuple(float(v) for v in d / np.linalg.norm(d)))
    if z > 0:
        return Epipole(True, tuple(float(v) for v in camera.project(np.asarray(position, float), width, height)), 1)
    mirrored = o - off  # project() refuses points behind the camera: the mirror image has the same epipole
    return Epipole(True, tuple(float(v) for v in camera.project(mirrored, width, height)), -1)


# --------------------------------------------------------------------------------- images
def max_composite(images: np.ndarray) -> np.ndarray:
    """Raskar's shadow-free image: the per-pixel, per-channel maximum over flash images (F, H, W, C)."""
    return np.max(images, axis=0)


@dataclass
class DepthEdges:
    """edges (H, W) bool union; per_flash (F, H, W) bool; ratios (F, H, W) or None; valid (H, W) bool."""

    edges: np.ndarray
    per_flash: np.ndarray
    ratios: np.ndarray | None
    valid: np.ndarray


def _sample(img: np.ndarray, yy: np.ndarray, xx: np.ndarray) -> np.ndarray:
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, [yy, xx], order=1, mode="nearest")


def signal_valid(lum_max: np.ndarray, min_signal_fraction: float, bad: np.ndarray | None) -> np.ndarray:
    ref = float(np.percentile(lum_max, 99)) if lum_max.size else 0.0
    valid = lum_max > min_signal_fraction * ref if ref > 0 else np.zeros(lum_max.shape, bool)
    if bad is not None:
        valid &= ~bad
    return valid


def raskar_depth_edges(
    images: np.ndarray,
    epipoles: list[Epipole],
    *,
    step_threshold: float = 0.3,
    step_span_px: int = 2,
    smooth_px: float = 0.0,
    min_signal_fraction: float = 0.03,
    bad: np.ndarray | None = None,
) -> DepthEdges:
    """Depth edges from flash images (F, H, W, C) lit from ``epipoles`` (Raskar et al. 2004).

    ``bad`` (H, W) bool: pixels with no usable value (e.g. a saturated read). See the module
    docstring for the steps.
    """
    images = np.asarray(images, np.float64)
    if images.ndim != 4 or len(epipoles) != images.shape[0]:
        raise ValueError(f"images (F, H, W, C) and one epipole per flash expected, got {images.shape}, {len(epipoles)}")
    F, H, W, _ = images.shape
    lum = np.maximum(luminance(images), 0.0)
    if smooth_px > 0:
        from scipy.ndimage import gaussian_filter

        lum = np.stack([gaussian_filter(x, smooth_px, mode="nearest") for x in lum])
    lum_max = lum.max(axis=0)
    valid = signal_valid(lum_max, min_signal_fraction, bad)
    ratios = np.divide(lum, lum_max[None], out=np.zeros_like(lum), where=valid[None])
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    per = np.zeros((F, H, W), bool)
    for k, ep in enumerate(epipoles):
        d = ep.away(H, W)
        dx, dy = d[..., 0], d[..., 1]
        r = ratios[k]
        ax, ay = xx + step_span_px * dx, yy + step_span_px * dy  # the pixel step_span_px further away
        step = r - _sample(r, ay, ax)  # drop into the shadow: positive
        step_prev = _sample(step, yy - dy, xx - dx)
        step_next = _sample(step, yy + dy, xx + dx)
        ok = valid & (_sample(valid.astype(float), ay, ax) > 0.999)
        inside = (ax >= 0) & (ax <= W - 1) & (ay >= 0) & (ay <= H - 1)
        per[k] = ok & inside & (step > step_threshold) & (step >= step_prev) & (step > step_next)
    return DepthEdges(edges=per.any(axis=0), per_flash=per, ratios=ratios, valid=valid)


def canny_edges(image: np.ndarray, *, low: float = 0.1, high: float = 0.25) -> np.ndarray:
    """(H, W) bool Canny edges of an image's luminance (tone-mapped to its 99th percentile, 8 bit);
    thresholds are fractions of the largest Sobel gradient magnitude (OpenCV's L1 norm)."""
    import cv2

    lum = luminance(image)
    white = float(np.percentile(lum, 99)) or 1.0
    u8 = np.round(np.clip(lum / white, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    gx = cv2.Sobel(u8, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(u8, cv2.CV_64F, 0, 1, ksize=3)
    gmax = float(np.max(np.abs(gx) + np.abs(gy))) or 1.0
    return cv2.Canny(u8, low * gmax, high * gmax, L2gradient=False) > 0


def depth_discontinuities(depth: np.ndarray, rel_jump: float) -> np.ndarray:
    """(H, W) bool: pixels whose depth is nearer than a 4-neighbour's by more than ``rel_jump``
    of their own depth (the occluding side of a depth edge). ``inf`` depth (no surface) counts
    as infinitely far."""
    z = np.asarray(depth, np.float64)
    out = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = np.swapaxes(z, 0, axis)
        near = np.minimum(a[:-1], a[1:])
        far = np.maximum(a[:-1], a[1:])
        with np.errstate(invalid="ignore"):
            jump = np.isfinite(near) & ((far - near) > rel_jump * near)
        o = np.swapaxes(out, 0, axis)
        o[:-1] |= jump & (a[:-1] <= a[1:])
        o[1:] |= jump & (a[1:] < a[:-1])
    return out


def edge_scores(detected: np.ndarray, truth: np.ndarray, tolerance_px: float, mask: np.ndarray | None = None) -> dict:
    """Precision, recall, F1 of a detected edge map against a true one, matching within
    ``tolerance_px`` (Euclidean distance transform). ``mask`` restricts the pixels counted (both
    maps are matched against the other's full extent). None where undefined (nothing to count)."""
    from scipy.ndimage import distance_transform_edt

    detected, truth = np.asarray(detected, bool), np.asarray(truth, bool)
    m = np.ones(detected.shape, bool) if mask is None else np.asarray(mask, bool)
    d_to_truth = distance_transform_edt(~truth) if truth.any() else np.full(truth.shape, np.inf)
    d_to_det = distance_transform_edt(~detected) if detected.any() else np.full(truth.shape, np.inf)
    n_det, n_true = int((detected & m).sum()), int((truth & m).sum())
    precision = float((d_to_truth[detected & m] <= tolerance_px).mean()) if n_det else None
    recall = float((d_to_det[truth & m] <= tolerance_px).mean()) if n_true else None
    f1 = (
        2 * precision * recall / (precision + recall)
        if precision is not None and recall is not None and precision + recall > 0
        else (0.0 if precision is not None and recall is not None else None)
    )
    return {"precision": precision, "recall": recall, "f1": f1, "detected_px": n_det, "true_px": n_true}
