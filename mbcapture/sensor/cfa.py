"""The colour filter array: which channel each photosite sees, and demosaicing back to RGB.

``sensor.cfa`` names the sensor's filters:

* ``none``: every pixel sees R, G and B (three stacked photosites, each with its own shot and read
  noise and fixed pattern). The default: the paper's sensor is treated channel by channel, and
  it keeps every earlier capture as it was.
* ``RGGB``, ``BGGR``, ``GRBG``, ``GBRG``: a Bayer mosaic, named by its 2x2 tile read row by row.
  Each photosite collects only its own channel's photo-electrons (the filter absorbs the rest),
  so shot noise, full well, fixed pattern and read noise are those of one photosite; the pixel
  model runs on the (K, H, W, 1) mosaic, and each read is demosaiced back to (H, W, 3) with
  colour-demosaicing (``sensor.demosaic``: bilinear, Malvar et al. 2004, Menon et al. 2007).
* ``mono``: a monochrome sensor with one spectral response, the band-wise sum of the three
  channels' responses (each channel's quantum efficiency over its band). The renderer mixes the
  channels into that response (:func:`mbcapture.sensor.photons.mono_weights`) so that exposures, truths and reference
  renders are all grey; the pixel model runs on one channel and its reads are repeated in R, G, B.

The mosaic selection and the footprint of each demosaicing method are written here; the
demosaicing itself is colour-demosaicing's.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BAYER_PATTERNS", "DEMOSAIC_METHODS", "channel_map", "demosaic", "footprint_radius", "spread_to_footprint",
           "to_mosaic"]

#: Bayer layouts by name: the channel (0 R, 1 G, 2 B) of each photosite of the 2x2 tile, row by row.
BAYER_PATTERNS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1), "GBRG": (1, 2, 0, 1)}

#: sensor.demosaic -> (colour-demosaicing function, the radius in photosites of the neighbourhood an
#: output pixel depends on). Bilinear: its 3x3 kernels. Malvar 2004: its 5x5 gradient-corrected
#: kernels. Menon 2007: its 5-tap directional filters, the differences and 5x5 window of the direction
#: decision and the refining step's filters, chained: 8 (tests/test_cfa.py measures each radius as the
#: reach of a single photosite's change).
DEMOSAIC_METHODS: dict[str, tuple[str, int]] = {
    "bilinear": ("demosaicing_CFA_Bayer_bilinear", 1),
    "malvar2004": ("demosaicing_CFA_Bayer_Malvar2004", 2),
    "menon2007": ("demosaicing_CFA_Bayer_Menon2007", 8),
}

#: The mirrored margin around a mosaic while it is demosaiced (even: the pattern keeps its name).
_MARGIN = 10


def channel_map(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) int: the channel each photosite of a ``pattern`` mosaic sees."""
    if pattern not in BAYER_PATTERNS:
        raise ValueError(f"cfa: expected one of {sorted(BAYER_PATTERNS)}, got {pattern!r}")
    tile = np.array(BAYER_PATTERNS[pattern], dtype=np.int8).reshape(2, 2)
    return np.tile(tile, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def to_mosaic(image: np.ndarray, pattern: str) -> np.ndarray:
    """(..., H, W, 3) -> (..., H, W, 1): each photosite keeps its own channel."""
    image = np.asarray(image)
    if image.ndim < 3 or image.shape[-1] != 3:
        raise ValueError(f"to_mosaic: expected (..., H, W, 3), got {image.shape}")
    cmap = channel_map(pattern, *image.shape[-3:-1])
    return np.take_along_axis(image, np.broadcast_to(cmap[..., None], (*image.shape[:-1], 1)).astype(np.intp), -1)


def demosaic(mosaic: np.ndarray, pattern: str, method: str) -> np.ndarray:
    """(..., H, W) or (..., H, W, 1) mosaic -> (..., H, W, 3) float64, each leading index alone, with
    colour-demosaicing's ``method`` (a key of :data:`DEMOSAIC_METHODS`). Linear in the values for
    bilinear and Malvar 2004 (so an offset such as the black level passes through them unchanged);
    Menon 2007 is not (its direction decision depends on the values)."""
    if method not in DEMOSAIC_METHODS:
        raise ValueError(f"demosaic: expected one of {sorted(DEMOSAIC_METHODS)}, got {method!r}")
    if pattern not in BAYER_PATTERNS:
        raise ValueError(f"cfa: expected one of {sorted(BAYER_PATTERNS)}, got {pattern!r}")
    import colour_demosaicing  # loads colour-science: only a CFA capture pays for it

    fn = getattr(colour_demosaicing, DEMOSAIC_METHODS[method][0])
    m = np.asarray(mosaic, dtype=np.float64)
    if m.ndim >= 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.ndim < 2:
        raise ValueError(f"demosaic: expected (..., H, W), got {np.shape(mosaic)}")
    flat = m.reshape(-1, *m.shape[-2:])
    out = np.empty((*flat.shape, 3), dtype=np.float64)
    # colour-demosaicing's convolutions repeat the edge photosite at the border, which puts a photosite of
    # another colour where the kernel expects this one (colour fringes along every edge of the image).
    # Mirroring about the edge photosite instead (numpy's 'reflect') keeps every photosite's colour, and an
    # even margin keeps the pattern's name; the margin is wider than any method's reach.
    pad = _MARGIN
    H, W = flat.shape[-2:]
    for i, plane in enumerate(flat):
        out[i] = fn(np.pad(plane, pad, mode="reflect"), pattern)[pad:pad + H, pad:pad + W]
    return out.reshape(*m.shape, 3)


def footprint_radius(method: str) -> int:
    """How far (in photosites) a demosaiced pixel reaches into the mosaic with ``method``."""
    return DEMOSAIC_METHODS[method][1]


def spread_to_footprint(flags: np.ndarray, method: str) -> np.ndarray:
    """(..., H, W) or (..., H, W, 1) bool photosite flags -> (..., H, W, 3): a demosaiced pixel is
    flagged (in every channel) when any photosite within ``method``'s footprint is: a saturated
    photosite biases every output pixel it feeds."""
    f = np.asarray(flags, dtype=bool)
    if f.ndim >= 3 and f.shape[-1] == 1:
        f = f[..., 0]
    from scipy.ndimage import maximum_filter

    side = 2 * footprint_radius(method) + 1  # the dilation by a side x side square, nothing beyond the border
    out = maximum_filter(f, size=(1,) * (f.ndim - 2) + (side, side), mode="constant", cval=False)
    return np.repeat(out[..., None], 3, axis=-1)
