"""DNG raw files of the simulated reads (``output.dng``), for the raw tools photographers already use.
LibRaw (through rawpy) is the reader the tests open and develop them with; other readers are not tested.

A DNG is a TIFF with the DNG tags; tifffile (well kept, already a dependency of scikit-image and
imageio) writes TIFF with any extra tags, so the DNG tags are written through it rather than with a
DNG-only package (PiDNG adds a compiled extension for the lossless JPEG this module does not need).
What is written, per read:

* the integer ADC codes, uncompressed 16-bit: a CFA mosaic (one sample per photosite,
  PhotometricInterpretation CFA, with CFARepeatPatternDim / CFAPattern) or, for a sensor whose
  every pixel sees R, G and B (mbcapture's sensor without a colour filter array), three samples per
  pixel as a linear DNG (PhotometricInterpretation LinearRaw); a monochrome sensor's one sample
  per pixel as a one-sample LinearRaw DNG;
* BlackLevel (the sensor's black level) and WhiteLevel, in DN: the code at which *this read* clips
  (:func:`white_level_dn`: its charge limit, the buckets' full wells summed or the floating diffusion's,
  through gain and black level, less four read-noise sigmas, so that every clipped sample lies at or above
  it; at most the ADC's top code), so that a raw developer knows where highlights clip and develops them white;
* ExposureTime (the read's exposure, s) and BaselineExposure (log2 of the longest read's exposure over this
  read's, EV): developed with it, every read of a capture comes out as bright as the longest;
* ColorMatrix1 (CIE XYZ to the camera's raw RGB under D65, CalibrationIlluminant1 = D65) and
  AsShotNeutral (the raw RGB of a D65 white), from the camera's response per channel: in an RGB
  render the raw value of channel c is g_c times the scene's linear-sRGB value c, with g_c the
  sensor's DN per unit radiance, so XYZ -> raw is diag(g / max g) times XYZ -> linear sRGB. A raw
  developer that applies them gives back the scene's sRGB colours. A monochrome DNG's one plane is
  given XYZ's Y (a 1x3 matrix) and a neutral of 1.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..sensor.cfa import BAYER_PATTERNS

#: XYZ (D65) -> linear sRGB (IEC 61966-2-1), the matrix every sRGB pipeline uses.
XYZ_TO_SRGB = np.array(
    [[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560], [0.0556434, -0.2040259, 1.0572252]]
)
#: CFA layouts by name: the colour (0 R, 1 G, 2 B) of each photosite of the 2x2 tile, row by row.
CFA_PATTERNS = BAYER_PATTERNS

# DNG / TIFF-EP tag numbers (DNG specification 1.4)
_CFA_REPEAT_PATTERN_DIM, _CFA_PATTERN = 33421, 33422
_DNG_VERSION, _DNG_BACKWARD_VERSION, _UNIQUE_CAMERA_MODEL = 50706, 50707, 50708
_CFA_PLANE_COLOR, _CFA_LAYOUT = 50710, 50711
_BLACK_LEVEL, _WHITE_LEVEL = 50714, 50717
_COLOR_MATRIX_1, _AS_SHOT_NEUTRAL, _CALIBRATION_ILLUMINANT_1 = 50721, 50728, 50778
_EXPOSURE_TIME, _BASELINE_EXPOSURE = 33434, 50730
_PHOTOMETRIC_CFA, _PHOTOMETRIC_LINEAR_RAW, _PHOTOMETRIC_BLACK_IS_ZERO = 32803, 34892, 1
_D65 = 21
#: The finest denominator of a written RATIONAL or SRATIONAL: six decimals, where the numerator fits.
_DENOMINATOR = 1_000_000


def _rational(values, signed: bool) -> tuple[int, ...]:
    """(numerator, denominator) pairs of ``values`` as TIFF (S)RATIONALs: 32-bit numerators, so each value's
    denominator is the largest power of ten up to 10^6 that keeps its numerator in range (a black level of
    5000 DN at 10^6 would be 5 x 10^9, over the 4.29 x 10^9 an unsigned 32-bit integer holds)."""
    top = 2**31 - 1 if signed else 2**32 - 1
    out = []
    for x in values:
        x = float(x)
        if not np.isfinite(x) or (x < 0 and not signed) or abs(x) > top:
            raise ValueError(f"DNG {'SRATIONAL' if signed else 'RATIONAL'}: {x} cannot be written")
        den = _DENOMINATOR
        while den > 1 and abs(round(x * den)) > top:
            den //= 10
        out += [int(round(x * den)), den]
    return tuple(out)


def _srational(values) -> tuple[int, ...]:
    return _rational(values, signed=True)


def _urational(values) -> tuple[int, ...]:
    return _rational(values, signed=False)


def colour_tags(channel_gain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ColorMatrix1 3x3, AsShotNeutral (3,)) of a camera whose raw channel c is ``channel_gain[c]``
    times the scene's linear sRGB channel c."""
    g = np.asarray(channel_gain, dtype=np.float64)
    if g.shape != (3,) or np.any(g <= 0) or not np.all(np.isfinite(g)):
        raise ValueError(f"channel_gain: expected 3 positive numbers, got {channel_gain!r}")
    neutral = g / g.max()
    return neutral[:, None] * XYZ_TO_SRGB, neutral


#: How many read-noise sigmas below a read's clip point its WhiteLevel lies: clipped samples carry the read noise
#: added after the clip, and at 4 sigma one in 30 000 of them would fall below the white level.
WHITE_LEVEL_SIGMAS = 4.0


def white_level_dn(charge_limit_e: float, sensor) -> int:
    """The DNG WhiteLevel of a read whose charge clips at ``charge_limit_e``: the code of that charge through the
    ``sensor``'s gain and black level, less :data:`WHITE_LEVEL_SIGMAS` of its read noise (pixel and row), at most the
    ADC's top code and above the black level."""
    noise_dn = sensor.gain_dn_per_e * float(np.hypot(sensor.read_noise_e, sensor.read_noise_row_e))
    level = sensor.black_level_dn + sensor.gain_dn_per_e * charge_limit_e - WHITE_LEVEL_SIGMAS * noise_dn
    return int(max(min(np.floor(level), sensor.adc_max_dn), np.floor(sensor.black_level_dn) + 1))


def write_dng(
    path: str | Path,
    codes: np.ndarray,
    *,
    black_level: float,
    white_level: int,
    channel_gain: np.ndarray,
    cfa: str | None = None,
    model: str = "mbcapture simulated sensor",
    exposure_s: float | None = None,
    baseline_exposure_ev: float = 0.0,
) -> None:
    """Write one read as a DNG. ``codes``: integer ADC codes, (H, W) for a ``cfa`` mosaic (one of
    :data:`CFA_PATTERNS`) or a ``cfa='mono'`` sensor, or (H, W, 3) without one; ``black_level`` and
    ``white_level`` in DN;
    ``channel_gain``: raw DN per unit of the scene's linear sRGB, per channel (:func:`colour_tags`);
    ``exposure_s``: the read's exposure (ExposureTime); ``baseline_exposure_ev``: BaselineExposure."""
    import tifffile

    data = np.asarray(codes)
    if not np.all(np.isfinite(data)) or np.any(data < 0) or np.any(data > 65535) or np.any(data != np.round(data)):
        raise ValueError("codes: expected integer ADC codes in 0 .. 65535")
    if not 0 < white_level <= 65535:
        raise ValueError(f"white_level: expected 1 .. 65535 (16-bit samples), got {white_level}")
    matrix, neutral = colour_tags(channel_gain)
    tags = [
        (_DNG_VERSION, "B", 4, (1, 4, 0, 0), True),
        (_DNG_BACKWARD_VERSION, "B", 4, (1, 1, 0, 0), True),
        (_UNIQUE_CAMERA_MODEL, "s", 0, model, True),
        (_WHITE_LEVEL, "I", 1, (int(white_level),), True),
        (_BASELINE_EXPOSURE, "2i", 1, _srational([baseline_exposure_ev]), True),
    ]
    if exposure_s is not None:
        tags.append((_EXPOSURE_TIME, "2I", 1, _urational([exposure_s]), True))
    if cfa != "mono":
        tags += [
            (_COLOR_MATRIX_1, "2i", 9, _srational(matrix.ravel()), True),
            (_AS_SHOT_NEUTRAL, "2I", 3, _urational(neutral), True),
            (_CALIBRATION_ILLUMINANT_1, "H", 1, (_D65,), True),
        ]
    else:  # one colour plane: XYZ -> its value is Y (a 1x3 matrix), its neutral 1
        tags += [
            (_COLOR_MATRIX_1, "2i", 3, _srational([0.0, 1.0, 0.0]), True),
            (_AS_SHOT_NEUTRAL, "2I", 1, _urational([1.0]), True),
            (_CALIBRATION_ILLUMINANT_1, "H", 1, (_D65,), True),
        ]
    if cfa == "mono":
        if data.ndim != 2:
            raise ValueError(f"codes: expected an (H, W) image of a monochrome sensor, got {data.shape}")
        photometric = _PHOTOMETRIC_BLACK_IS_ZERO  # written so, then made LinearRaw (below)
        tags.append((_BLACK_LEVEL, "2I", 1, _urational([black_level]), True))
    elif cfa is None:
        if data.ndim != 3 or data.shape[-1] != 3:
            raise ValueError(f"codes: expected (H, W, 3) without a CFA, got {data.shape}")
        photometric = _PHOTOMETRIC_LINEAR_RAW
        tags.append((_BLACK_LEVEL, "2I", 3, _urational([black_level] * 3), True))
    else:
        if cfa not in CFA_PATTERNS:
            raise ValueError(f"cfa: expected one of {sorted(CFA_PATTERNS)}, got {cfa!r}")
        if data.ndim != 2:
            raise ValueError(f"codes: expected an (H, W) mosaic with a CFA, got {data.shape}")
        photometric = _PHOTOMETRIC_CFA
        tags += [
            (_CFA_REPEAT_PATTERN_DIM, "H", 2, (2, 2), True),
            (_CFA_PATTERN, "B", 4, CFA_PATTERNS[cfa], True),
            (_CFA_PLANE_COLOR, "B", 3, (0, 1, 2), True),
            (_CFA_LAYOUT, "H", 1, (1,), True),
            (_BLACK_LEVEL, "2I", 1, _urational([black_level]), True),
        ]
    tifffile.imwrite(
        path,
        data.astype(np.uint16),
        photometric=photometric,
        planarconfig="contig",
        subfiletype=0,
        extratags=tags,
        metadata=None,
        software="mbcapture",
    )
    if cfa == "mono":
        # a monochrome DNG is LinearRaw with one sample (what LibRaw and Adobe's dng_validate read), which
        # tifffile will not write directly (it expects three samples for LinearRaw): rewrite the tag in place
        with tifffile.TiffFile(path, mode="r+b") as tif:
            tif.pages[0].tags["PhotometricInterpretation"].overwrite(_PHOTOMETRIC_LINEAR_RAW)
