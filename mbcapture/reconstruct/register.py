"""Registration of frames: ECC or phase correlation (OpenCV), warping, aligning and averaging a
burst, and the blur that remains against a reference, arrays in, arrays out.

The burst application (:mod:`mbcapture.apps.burst`) takes and scores the bursts; the algorithms
live here. OpenCV loads inside the functions that use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..metrics import luminance

#: Alignment methods (``app.method`` of the burst application) and what each is.
ALIGN_METHODS: dict[str, str] = {
    "ecc_euclidean": "OpenCV findTransformECC, MOTION_EUCLIDEAN",
    "ecc_homography": "OpenCV findTransformECC, MOTION_HOMOGRAPHY",
    "phase_correlation": "OpenCV phaseCorrelate (translation)",
    "none": "no alignment",
}


#: Largest blur sigma the residual-blur fit considers, px.
MAX_BLUR_PX = 8.0


# --------------------------------------------------------------------------- pure functions
@dataclass(frozen=True)
class Aligned:
    """average (H, W, C); warps (K, 3, 3) mapping reference pixel coordinates to each frame's;
    coverage (H, W) how many frames contributed to each pixel."""

    average: np.ndarray
    warps: np.ndarray
    coverage: np.ndarray


def _prepared(lum: np.ndarray) -> np.ndarray:
    """Luminance scaled to [0, 1] for registration (float32)."""
    lo, hi = np.percentile(lum, [1, 99.5])
    return np.clip((lum - lo) / max(hi - lo, 1e-30), 0, 1).astype(np.float32)


def _ecc(template: np.ndarray, image: np.ndarray, motion: int, blur: int) -> np.ndarray:
    import cv2

    warp = np.eye(3 if motion == cv2.MOTION_HOMOGRAPHY else 2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    blur = blur if blur % 2 else blur + 1
    try:
        _, warp = cv2.findTransformECC(template, image, warp, motion, criteria, None, blur)
    except cv2.error:  # did not converge (flat or too noisy image): leave the frame where it is
        warp = np.eye(3 if motion == cv2.MOTION_HOMOGRAPHY else 2, 3, dtype=np.float32)
    out = np.eye(3)
    out[: warp.shape[0]] = warp
    return out


def _phase(template: np.ndarray, image: np.ndarray) -> np.ndarray:
    import cv2

    window = cv2.createHanningWindow(template.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(template.astype(np.float32), image.astype(np.float32), window)
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def register_frame(template: np.ndarray, image: np.ndarray, method: str, blur: int = 5) -> np.ndarray:
    """(3, 3) warp taking pixel coordinates (x right, y down, centres at half-integers are fine: the
    warp is affine or projective) of ``template`` (H, W) to the matching ones of ``image``."""
    import cv2

    if method == "none":
        return np.eye(3)
    a, b = _prepared(template), _prepared(image)
    if method == "ecc_euclidean":
        return _ecc(a, b, cv2.MOTION_EUCLIDEAN, blur)
    if method == "ecc_homography":
        return _ecc(a, b, cv2.MOTION_HOMOGRAPHY, blur)
    if method == "phase_correlation":
        return _phase(a, b)
    raise ConfigError(f"app.method: unknown alignment {method!r}; expected one of {sorted(ALIGN_METHODS)}")


def warp_onto(image: np.ndarray, warp: np.ndarray, cubic: bool = False) -> np.ndarray:
    """``image`` (H, W[, C]) resampled onto the template's grid: out(p) = image(warp(p)) (bilinear, or
    bicubic with ``cubic``); NaN where warp(p) falls outside the image."""
    import cv2

    H, W = image.shape[:2]
    flags = (cv2.INTER_CUBIC if cubic else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
    img = np.asarray(image, dtype=np.float32)
    inside = np.ones((H, W), np.float32)
    if np.allclose(warp[2], [0, 0, 1]):
        out = cv2.warpAffine(img, warp[:2].astype(np.float64), (W, H), flags=flags, borderValue=0)
        cover = cv2.warpAffine(inside, warp[:2].astype(np.float64), (W, H), flags=flags, borderValue=0)
    else:
        out = cv2.warpPerspective(img, warp.astype(np.float64), (W, H), flags=flags, borderValue=0)
        cover = cv2.warpPerspective(inside, warp.astype(np.float64), (W, H), flags=flags, borderValue=0)
    out = out.reshape(image.shape).astype(np.float64)
    bad = cover < 0.999
    out[bad] = np.nan
    return out


def align_and_average(rates: np.ndarray, saturated: np.ndarray, method: str, reference: int, blur: int = 5) -> Aligned:
    """Register every frame of ``rates`` (K, H, W, C) onto frame ``reference`` with ``method`` and
    average, per pixel, the warped frames that cover it and are not saturated there (the reference
    frame's value where none is)."""
    K = rates.shape[0]
    lum = luminance(rates)
    warps = np.stack(
        [np.eye(3) if k == reference else register_frame(lum[reference], lum[k], method, blur) for k in range(K)]
    )
    total = np.zeros(rates.shape[1:])
    count = np.zeros(rates.shape[1:])
    for k in range(K):
        img = rates[k] if k == reference else warp_onto(rates[k], warps[k])
        ok = np.isfinite(img) & ~(
            saturated[k] if k == reference else warp_onto(saturated[k].astype(float), warps[k]) > 0
        )
        total += np.where(ok, img, 0.0)
        count += ok
    avg = np.where(count > 0, total / np.maximum(count, 1), rates[reference])
    return Aligned(avg, warps, count.min(axis=-1).astype(int))


def apply_warp(warp: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) pixel points mapped by a (3, 3) warp."""
    p = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ warp.T
    return p[:, :2] / p[:, 2:]


def registration_errors(warps: np.ndarray, true_positions: np.ndarray, reference: int) -> np.ndarray:
    """(K,) RMS over points of |warp_k(p_ref) - p_k|: ``true_positions`` (K, N, 2) each frame's mean
    image position of N scene points."""
    ref = true_positions[reference]
    return np.array(
        [
            float(np.sqrt(np.mean(np.sum((apply_warp(w, ref) - true_positions[k]) ** 2, axis=-1))))
            for k, w in enumerate(warps)
        ]
    )


def fit_blur_px(result: np.ndarray, truth: np.ndarray, max_sigma: float = MAX_BLUR_PX) -> float:
    """Sigma (px) of the Gaussian blur of ``truth`` (H, W) closest to ``result`` (H, W) in least squares."""
    from scipy.ndimage import gaussian_filter
    from scipy.optimize import minimize_scalar

    t = np.asarray(truth, np.float64)
    r = np.asarray(result, np.float64)

    def cost(s: float) -> float:
        return (
            float(np.mean((gaussian_filter(t, s, mode="nearest") - r) ** 2))
            if s > 1e-3
            else float(np.mean((t - r) ** 2))
        )

    best = minimize_scalar(cost, bounds=(0.0, max_sigma), method="bounded", options={"xatol": 1e-3})
    return float(best.x) if cost(float(best.x)) < cost(0.0) else 0.0


def register_to_truth(result: np.ndarray, truth: np.ndarray, blur: int = 5) -> tuple[np.ndarray, float]:
    """``result`` (H, W, C) registered onto ``truth`` (ECC, euclidean) and resampled bicubically
    (bilinear resampling would itself blur ~0.3 px), and the largest coordinate shift of a corner (px)."""
    warp = register_frame(luminance(truth), luminance(result), "ecc_euclidean", blur)
    H, W = truth.shape[:2]
    corners = np.array([[0, 0], [W, 0], [0, H], [W, H]], float)
    return warp_onto(result, warp, cubic=True), float(np.abs(apply_warp(warp, corners) - corners).max())
