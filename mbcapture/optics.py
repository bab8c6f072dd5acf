"""The lens between the scene and the pixels: its relative illumination (natural vignetting), its
diffraction, applied to every render of a capture alike (:class:`mbcapture.render.Renderer`), and
the geometry of its depth of field (a thin lens: Mitsuba's ``thinlens`` sensor renders it).

The render is already the mean radiance over each pixel (a box filter the size of the pixel: the
pixel aperture at 100 % fill factor), so the system MTF is that of the box times the lens's:
diffraction adds the optical transfer function of a circular aperture at the f-number, one per
channel at its effective wavelength (``sensor.wavelength_nm``). Written here with scipy's FFT:
the OTF of an aberration-free circular pupil is one closed form, which is all a simulated thin
lens needs (prysm, poppy or hcipy model whole pupils and wavefronts; none is needed for this).
"""

from __future__ import annotations

import numpy as np

from .projective import tan_half


def natural_vignetting(camera, width: int, height: int) -> np.ndarray:
    """(H, W) relative illumination of a thin lens's image plane, cos^4 of the field angle at each
    pixel centre (cos^2 from the oblique ray's longer path, cos from the tilted pupil, cos from the
    tilted pixel): 1 on the optical axis. The field angle theta of pixel (x, y) has
    tan(theta) = |(x_n, y_n)| tan(fov / 2), x_n = 2 (x + 1/2) / W - 1 and y_n scaled by H / W (the
    camera's fov is horizontal)."""
    th = tan_half(camera)
    xn = 2.0 * (np.arange(width) + 0.5) / width - 1.0
    yn = (2.0 * (np.arange(height) + 0.5) / height - 1.0) * height / width
    tan2 = (xn[None, :] ** 2 + yn[:, None] ** 2) * th * th
    return 1.0 / (1.0 + tan2) ** 2


def diffraction_otf(freq_cyc_per_mm: np.ndarray, wavelength_nm: float, f_number: float) -> np.ndarray:
    """The incoherent OTF of an aberration-free circular aperture (real, >= 0): with
    nu = f / f_c and f_c = 1 / (lambda N) the cutoff, (2 / pi) (acos nu - nu sqrt(1 - nu^2)) below
    the cutoff, 0 above."""
    nu = np.abs(np.asarray(freq_cyc_per_mm, dtype=np.float64)) * (wavelength_nm * 1e-6) * f_number
    nu = np.minimum(nu, 1.0)
    return (2.0 / np.pi) * (np.arccos(nu) - nu * np.sqrt(1.0 - nu * nu))


#: Pixels mirrored at each border before filtering (the PSF's first dark ring is at 1.22 lambda N,
#: a few micrometres: well inside this margin for any pixel pitch and f-number a camera uses).
PAD_PX = 16


def apply_diffraction(image: np.ndarray, pixel_pitch_um: float, f_number: float,
                      wavelength_nm: list[float] | np.ndarray) -> np.ndarray:
    """``image`` (..., H, W, C) filtered by each channel's diffraction OTF (channel c at
    ``wavelength_nm[c]``), the borders mirrored; float64. A flat image stays flat (OTF(0) = 1).

    The filter treats the image as band-limited (the OTF is applied at the frequencies the pixel
    grid holds), which gives the right contrast at each of them; around a source sharper than a
    pixel (a lamp's rim), whose content the grid aliases, it rings below zero by a small fraction of
    the source: those samples are set to 0, as irradiance cannot be negative."""
    from scipy import fft

    img = np.asarray(image, dtype=np.float64)
    H, W, C = img.shape[-3:]
    lam = np.asarray(wavelength_nm, dtype=np.float64)
    if lam.shape != (C,):
        raise ValueError(f"wavelength_nm: expected {C} values, one per channel, got {lam.shape}")
    pad = [(0, 0)] * (img.ndim - 3) + [(PAD_PX, PAD_PX), (PAD_PX, PAD_PX), (0, 0)]
    padded = np.pad(img, pad, mode="symmetric")
    Hp, Wp = padded.shape[-3], padded.shape[-2]
    pitch_mm = pixel_pitch_um * 1e-3
    fy = fft.fftfreq(Hp, d=pitch_mm)[:, None]
    fx = fft.rfftfreq(Wp, d=pitch_mm)[None, :]
    f = np.hypot(fx, fy)  # cycles per mm
    out = np.empty_like(padded)
    for c in range(C):
        spectrum = fft.rfft2(padded[..., c], axes=(-2, -1))
        out[..., c] = fft.irfft2(spectrum * diffraction_otf(f, lam[c], f_number), s=(Hp, Wp), axes=(-2, -1))
    return np.maximum(out[..., PAD_PX:PAD_PX + H, PAD_PX:PAD_PX + W, :], 0.0)


# ----------------------------------------------------------------------------- depth of field
def focal_length_m(camera, width: int, pitch_um: float) -> float:
    """The focal length that images the camera's horizontal field of view onto ``width`` pixels of
    ``pitch_um``: f = (W p / 2) / tan(fov / 2), in metres (scenes are in metres)."""
    return width * pitch_um * 1e-6 / 2.0 / tan_half(camera)


def fov_deg_for(focal_length_mm: float, width: int, pitch_um: float) -> float:
    """The horizontal field of view (degrees) of ``width`` pixels of ``pitch_um`` behind a lens of
    ``focal_length_mm``: 2 atan(W p / 2 f)."""
    return float(np.degrees(2.0 * np.arctan(width * pitch_um * 1e-3 / 2.0 / focal_length_mm)))


def focus_distance_m(camera) -> float:
    """The default focus: the distance from the camera to the point it looks at."""
    return float(np.linalg.norm(np.subtract(camera.target, camera.origin)))


def thin_lens_aperture_m(camera, width: int, pitch_um: float, f_number: float) -> float:
    """The entrance pupil's radius, f / (2 N), in metres."""
    return focal_length_m(camera, width, pitch_um) / (2.0 * f_number)


def blur_radius_px(camera, width: int, aperture_radius_m: float, focus_m: float, depth_m: float) -> float:
    """Radius in pixels of the disk a point at ``depth_m`` (along the optical axis, near the image
    centre) is spread over by Mitsuba's ``thinlens`` sensor focused at ``focus_m``: a ray from lens
    point a through the focus point of direction d meets depth z at a (1 - z / s_f) + d z, so the
    directions that see the point fill a disk of angular radius r |1/s_f - 1/z|; one pixel spans
    2 tan(fov / 2) / W of tangent. (The sensor keeps the field of view fixed while focusing: the
    thin lens's exact magnification differs by f / (s_f - f), under 1 % for the shipped scenes.)"""
    return aperture_radius_m * abs(1.0 / focus_m - 1.0 / depth_m) * width / (2.0 * tan_half(camera))
