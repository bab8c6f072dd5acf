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

__all__ = [
    "BAYER_PATTERNS",
    "DEMOSAIC_METHODS",
    "LOG_DEMOSAIC_FLOOR_E",
    "channel_map",
    "demosaic",
    "demosaic_hdr",
    "footprint_radius",
    "spread_to_footprint",
    "to_mosaic",
]

#: Bayer layouts by name: the channel (0 R, 1 G, 2 B) of each photosite of the 2x2 tile, row by row.
BAYER_PATTERNS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2),
    "BGGR": (2, 1, 1, 0),
    "GRBG": (1, 0, 2, 1),
    "GBRG": (1, 2, 0, 1),
}

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

#: The photo-electrons below which :func:`demosaic_hdr` is linear, as a signal's floor. In the logarithm an
#: interpolated value is a weighted geometric mean, which lies under the arithmetic one by about half the
#: values' relative variance; a count of N electrons has a relative shot-noise variance of 1 / N, so above 100
#: electrons that bias is under 0.5 %, and below it the values are demosaiced as they are. Measured on
#: flash_no_flash at 128x96, RGGB (``python scripts/cfa_apps.py flash_no_flash``): with the floor at the read
#: noise (3 e-) the enhanced image's PSNR fell from 37.5 dB (linear) to 36.3, with 100 e- it rose to 38.1; both
#: cut the moving flash-only image's relMSE from 0.51 to 0.045.
LOG_DEMOSAIC_FLOOR_E = 100.0

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
        out[i] = fn(np.pad(plane, pad, mode="reflect"), pattern)[pad : pad + H, pad : pad + W]
    return out.reshape(*m.shape, 3)


def demosaic_hdr(mosaic: np.ndarray, pattern: str, method: str, floor: np.ndarray | float) -> np.ndarray:
    """Demosaic high-dynamic-range linear values (an HDR merge's radiance) in a logarithmic domain:
    ``floor * sinh(demosaic(asinh(mosaic / floor)))``, with ``floor`` the value of each photosite's channel
    (a scalar, or one per channel R, G, B) below which the transform is linear.

    Why: demosaicing methods interpolate a photosite's missing channels from its neighbours, Malvar's and
    Menon's from their colour differences. That assumption (a colour difference varies slowly) holds on
    images of a few hundred to one, the range the methods were designed on; an HDR merge spans 10^5 (a lamp
    at 2000 W m^-2 sr^-1 next to a wall at 0.01), where a bright neighbour's difference lands on a dark
    pixel as a value of the bright one's size and either sign: the metronome's merge at 128x96 had 206
    negative radiance samples and a relMSE of 0.26, as much as demosaicing its noise-free truth gave (0.37).
    In the logarithm a colour difference is a colour ratio (the constant-hue assumption of ratio-based
    demosaicing), which does vary slowly across such an edge, and an interpolated value is a weighted
    geometric mean, which a bright neighbour cannot pull below zero. Measured on that capture
    (``python scripts/cfa_hdr_order.py --size 128x96 --spp 8``): the merge's relMSE 0.258 -> 0.0089 with
    menon2007, 0.376 -> 0.016 with malvar2004, 0.395 -> 0.069 with bilinear, each now that of its
    noise-free truth demosaiced alike (0.0087, 0.018, 0.098). ``asinh`` rather than ``log`` keeps values at
    and below zero (noise around black) defined and unbiased: within ``floor`` of zero it is linear, where a
    logarithm would skew the noise (:data:`LOG_DEMOSAIC_FLOOR_E` and :func:`mbcapture.apps.hdr.demosaic_floor`
    choose it)."""
    floor = np.asarray(floor, dtype=np.float64)
    floor = floor.reshape(()) if floor.size == 1 else floor
    if np.any(~np.isfinite(floor)) or np.any(floor <= 0):
        raise ValueError(f"demosaic_hdr: floor must be positive and finite, got {floor!r}")
    if floor.ndim not in (0, 1) or floor.size not in (1, 3):
        raise ValueError(f"demosaic_hdr: floor must be one number or one per channel R, G, B, got {floor!r}")
    m = np.asarray(mosaic, dtype=np.float64)
    if m.ndim >= 3 and m.shape[-1] == 1:
        m = m[..., 0]
    per_site = floor[channel_map(pattern, *m.shape[-2:])] if floor.ndim == 1 else floor
    return np.sinh(demosaic(np.arcsinh(m / per_site), pattern, method)) * floor


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
