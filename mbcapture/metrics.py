"""Image error metrics against a noise-free ground truth.

All functions take a test image ``x`` and a reference ``y`` of the same shape (any axes,
e.g. (H, W, C)), linear values, and an optional boolean ``mask`` of the same shape (or
broadcastable to it) selecting the samples that count. They return a Python float.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

__all__ = [
    "PU21_L_MAX_CD_M2",
    "PU21_L_MIN_CD_M2",
    "PU21_PARAMETERS",
    "RELMSE_EPS",
    "flat_items",
    "psnr",
    "pu21_encode",
    "pu21_psnr",
    "REC709_LUMA",
    "luminance",
    "relative_mse",
]


def flat_items(data: Mapping, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """The leaves of nested dicts (a report's metrics) as ``("a.b.c", value)`` pairs, in order;
    every value that is not a dict is a leaf, lists included."""
    for k, v in data.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            yield from flat_items(v, key)
        else:
            yield key, v


#: Rec. 709 luminance weights of linear RGB.
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(..., C) -> (...): Rec. 709 luminance of linear RGB for 3 channels, the channel mean otherwise (float64)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return rgb @ REC709_LUMA if rgb.shape[-1] == 3 else rgb.mean(axis=-1)


RELMSE_EPS = 1e-2
"""Default eps of :func:`relative_mse`, in the squared units of the reference.

It keeps near-black reference pixels from dominating the mean; 1e-2 is the value common in
the rendering literature for images of order 1. For images in other units (electrons/s,
W m^-2 sr^-1) pass an eps of about (1e-1 x a typical dark level)^2.
"""


def _selected(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {x.shape} vs {y.shape}")
    if mask is None:
        return x.ravel(), y.ravel()
    m = np.broadcast_to(np.asarray(mask, dtype=bool), x.shape)
    if not m.any():
        raise ValueError("mask selects no samples")
    return x[m], y[m]


def relative_mse(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None, eps: float = RELMSE_EPS) -> float:
    """Relative mean squared error, mean over samples of (x - y)^2 / (y^2 + eps). Dimensionless."""
    xs, ys = _selected(x, y, mask)
    return float(np.mean((xs - ys) ** 2 / (ys**2 + eps)))


def nrmse(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Normalised RMS error, sqrt(mean (x - y)^2) / mean |y|. Dimensionless; unlike the relative MSE,
    dark reference samples (shadows) do not dominate it."""
    xs, ys = _selected(x, y, mask)
    scale = float(np.mean(np.abs(ys)))
    return float(np.sqrt(np.mean((xs - ys) ** 2)) / scale) if scale > 0 else float("inf")


def psnr(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None, peak: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(peak^2 / MSE).

    ``peak`` defaults to the largest reference value among the selected samples.
    Returns +inf for identical images.
    """
    xs, ys = _selected(x, y, mask)
    p = float(np.max(ys)) if peak is None else float(peak)
    mse = float(np.mean((xs - ys) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(p**2 / mse))


# PU21 encoding, Mantiuk & Azimi, "PU21: A novel perceptually uniform encoding for adapting
# existing quality metrics for HDR", Picture Coding Symposium 2021. The formula
#   V(Y) = p7 * (((p1 + p2 Y^p4) / (1 + p3 Y^p4))^p5 - p6),  Y in cd/m^2 clamped to [0.005, 10000],
# and the fitted parameters p1..p7 of each variant are the paper's published constants.
PU21_L_MIN_CD_M2 = 0.005
"""Lowest luminance of the PU21 fit, cd/m^2 (from the paper)."""
PU21_L_MAX_CD_M2 = 10_000.0
"""Highest luminance of the PU21 fit, cd/m^2 (from the paper)."""
PU21_PARAMETERS: dict[str, tuple[float, ...]] = {
    "banding": (1.070275272, 0.4088273932, 0.153224308, 0.2520326168, 1.063512885, 1.14115047, 521.4527484),
    "banding_glare": (
        0.353487901,
        0.3734658629,
        8.277049286e-05,
        0.9062562627,
        0.09150303166,
        0.9099517204,
        596.3148142,
    ),
    "peaks": (1.043882782, 0.6459495343, 0.3194584211, 0.374025247, 1.114783422, 1.095360363, 384.9217577),
    "peaks_glare": (816.885024, 1479.463946, 0.001253215609, 0.9329636822, 0.06746643971, 1.573435413, 419.6006374),
}
"""PU21 parameters p1..p7 per variant (constants from Mantiuk & Azimi 2021)."""


def pu21_encode(luminance_cd_m2: np.ndarray, variant: str = "banding_glare") -> np.ndarray:
    """PU21 perceptually uniform encoding of absolute luminance.

    ``luminance_cd_m2``: any shape, cd/m^2 (clamped to [0.005, 10000]). Returns the encoded
    values, same shape, float64, about 0 .. 600 (100 cd/m^2 maps to about 256), >= 0.
    """
    if variant not in PU21_PARAMETERS:
        raise ValueError(f"PU21 variant {variant!r} unknown; valid: {', '.join(PU21_PARAMETERS)}")
    p1, p2, p3, p4, p5, p6, p7 = PU21_PARAMETERS[variant]
    y = np.clip(np.asarray(luminance_cd_m2, dtype=np.float64), PU21_L_MIN_CD_M2, PU21_L_MAX_CD_M2)
    yp = y**p4
    v = p7 * (((p1 + p2 * yp) / (1.0 + p3 * yp)) ** p5 - p6)
    return np.maximum(v, 0.0)


def pu21_psnr(
    x_cd_m2: np.ndarray,
    y_cd_m2: np.ndarray,
    mask: np.ndarray | None = None,
    variant: str = "banding_glare",
) -> float:
    """PSNR in dB between PU21-encoded images, peak = encoded value of 10 000 cd/m^2.

    Inputs are absolute luminances (or per-channel absolute values) in cd/m^2; scale
    linear renders to a display or scene luminance before calling.
    """
    xs, ys = _selected(x_cd_m2, y_cd_m2, mask)
    peak = float(pu21_encode(np.array(PU21_L_MAX_CD_M2), variant))
    return psnr(pu21_encode(xs, variant), pu21_encode(ys, variant), peak=peak)


def row_column_pixel_variances(image: np.ndarray) -> tuple[float, float, float]:
    """EMVA 1288 Release 4.0's split of an image's spatial variance into row, column and pixel
    components, for (H, W) ``image`` = a_i + b_j + e_ij (row, column and pixel parts): the row means
    vary as s_r^2 + s_p^2 / W, the column means as s_c^2 + s_p^2 / H and the image as
    s_r^2 + s_c^2 + s_p^2; solved for (s_r^2, s_c^2, s_p^2). For a fixed-pattern map, take the mean
    of many frames (their temporal noise then adds its variance / frames to the components)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 2:
        raise ValueError(f"image: expected (H, W) with H, W >= 2, got {img.shape}")
    H, W = img.shape
    v_rows, v_cols, v_all = img.mean(axis=1).var(ddof=1), img.mean(axis=0).var(ddof=1), img.var(ddof=1)
    pixel = (v_all - v_rows - v_cols) / (1.0 - 1.0 / W - 1.0 / H)
    return float(v_rows - pixel / W), float(v_cols - pixel / H), float(pixel)
