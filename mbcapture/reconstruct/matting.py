"""Alpha matting from a flash / no-flash pair: the trimap from the flash-only cue, and alpha by
pymatting's closed-form, KNN or large-kernel methods (or a threshold ramp), arrays in, arrays out.

The flash-matting application (:mod:`mbcapture.apps.flash_matting`) captures the pair, renders
the true alpha and scores; the algorithms live here. pymatting and OpenCV load inside the
functions that use them.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..metrics import luminance


def reference_level(y: np.ndarray, percentile: float) -> float:
    """The ``percentile`` of ``y`` (1.0 where that is not positive)."""
    ref = float(np.percentile(y, percentile)) if np.size(y) else 1.0
    return ref if ref > 0 else 1.0


def trimap_cue(
    flash_only: np.ndarray,
    noflash: np.ndarray,
    kind: str = "flash_ratio",
    percentile: float = 99.0,
    ratio_eps: float = 0.05,
) -> np.ndarray:
    """The trimap's cue (H, W), scaled so that its ``percentile`` is 1.

    ``flash_only``: the flash-only luminance. ``flash_ratio``: flash-only luminance / (no-flash
    luminance + ``ratio_eps`` x the no-flash luminance's ``percentile``): albedo cancels, what is left
    is how much more the flash lights a point than the ambient light does, which falls off as 1/d^2."""
    y = luminance(flash_only)
    if kind == "flash_ratio":
        yn = luminance(noflash)
        y = y / (np.maximum(yn, 0.0) + ratio_eps * reference_level(yn, percentile))
    elif kind != "flash_only":
        raise ConfigError(f"app.trimap_cue: unknown cue {kind!r}; expected 'flash_ratio' or 'flash_only'")
    return y / reference_level(y, percentile)


def _disc(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def make_trimap(
    cue: np.ndarray, fg_fraction: float, bg_fraction: float, open_px: int = 1, erode_px: int = 2
) -> np.ndarray:
    """Trimap (H, W) float64: 1 foreground, 0 background, 0.5 unknown, from a cue scaled so that
    the foreground is about 1 (``cue >= fg_fraction``: candidate foreground, ``<= bg_fraction``:
    candidate background). Each candidate is opened by a disc of radius ``open_px`` and eroded by
    one of radius ``erode_px``; every other pixel is unknown."""
    import cv2

    if not 0 <= bg_fraction < fg_fraction:
        raise ValueError("make_trimap: need 0 <= bg_fraction < fg_fraction")
    cue = np.asarray(cue, np.float64)
    out = np.full(cue.shape, 0.5)
    for value, cand in ((1.0, cue >= fg_fraction), (0.0, cue <= bg_fraction)):
        m = cand.astype(np.uint8)
        if open_px > 0:
            m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disc(open_px), borderType=cv2.BORDER_REPLICATE)
        if erode_px > 0:
            m = cv2.erode(m, _disc(erode_px), borderType=cv2.BORDER_REPLICATE)
        out[m.astype(bool)] = value
    return out


def _pymatting(name: str) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    def solve(image: np.ndarray, trimap: np.ndarray, ramp: np.ndarray) -> np.ndarray:
        import pymatting

        return getattr(pymatting, name)(image, trimap)

    solve.__name__ = name
    return solve


def _threshold(image: np.ndarray, trimap: np.ndarray, ramp: np.ndarray) -> np.ndarray:
    return np.asarray(ramp, np.float64)


#: name -> f(image (H, W, 3) in [0, 1], trimap (H, W), ramp (H, W)) -> alpha (H, W).
#: ``ramp`` is the flash-only cue mapped linearly from the background fraction (0) to the
#: foreground fraction (1), clipped.
MATTING_METHODS: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = {
    "closed_form": _pymatting("estimate_alpha_cf"),
    "knn": _pymatting("estimate_alpha_knn"),
    "lkm": _pymatting("estimate_alpha_lkm"),
    "random_walk": _pymatting("estimate_alpha_rw"),
    "learning_based": _pymatting("estimate_alpha_lbdm"),
    "threshold": _threshold,
}


def estimate_alpha(
    image: np.ndarray, trimap: np.ndarray, method: str = "closed_form", ramp: np.ndarray | None = None
) -> np.ndarray:
    """Alpha (H, W) in [0, 1] by ``method``; the trimap's definite pixels are kept as they are.

    A trimap without foreground or without background has nothing to propagate: alpha is then
    the trimap's definite part (unknown pixels get the ramp, or 0)."""
    if method not in MATTING_METHODS:
        raise ConfigError(f"app.matting: unknown method {method!r}; expected one of {sorted(MATTING_METHODS)}")
    image = np.clip(np.ascontiguousarray(image, dtype=np.float64), 0.0, 1.0)
    trimap = np.asarray(trimap, np.float64)
    ramp = np.zeros(trimap.shape) if ramp is None else np.clip(np.asarray(ramp, np.float64), 0.0, 1.0)
    fg, bg = trimap == 1.0, trimap == 0.0
    unknown = ~(fg | bg)
    if not fg.any() or not bg.any() or not unknown.any():
        alpha = np.where(unknown, ramp, trimap)
    else:
        alpha = np.asarray(MATTING_METHODS[method](image, trimap, ramp), np.float64)
    alpha = np.clip(alpha, 0.0, 1.0)
    alpha[fg], alpha[bg] = 1.0, 0.0
    return alpha
