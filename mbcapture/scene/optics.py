"""The lens between the scene and the pixels: its relative illumination (natural vignetting), its
radial distortion and its diffraction, applied to every render of a capture alike
(:class:`mbcapture.render.Renderer`), and the geometry of its depth of field (a thin lens:
Mitsuba's ``thinlens`` sensor renders it).

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


def apply_diffraction(
    image: np.ndarray,
    pixel_pitch_um: float,
    f_number: float,
    wavelength_nm: list[float] | np.ndarray,
    clamp: bool = True,
) -> np.ndarray:
    """``image`` (..., H, W, C) filtered by each channel's diffraction OTF (channel c at
    ``wavelength_nm[c]``), the borders mirrored; float64. A flat image stays flat (OTF(0) = 1).

    The filter treats the image as band-limited (the OTF is applied at the frequencies the pixel
    grid holds), which gives the right contrast at each of them; around a source sharper than a
    pixel (a lamp's rim), whose content the grid aliases, it rings below zero by a small fraction of
    the source: those samples are set to 0, as irradiance cannot be negative (``clamp``; off, the linear filter)."""
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
    out = out[..., PAD_PX : PAD_PX + H, PAD_PX : PAD_PX + W, :]
    return np.maximum(out, 0.0) if clamp else out


#: The half-width (pixels) of :func:`diffraction_reach`'s window.
REACH_PX = 8


def diffraction_reach(
    pixel_pitch_um: float, f_number: float, wavelength_nm: list[float] | np.ndarray, radius: int = REACH_PX
) -> np.ndarray:
    """(2 radius + 1, 2 radius + 1) how much a pixel at each offset weighs in :func:`apply_diffraction`'s value of
    the centre pixel, over the centre's own weight: the linear filter's absolute weights, the most over the
    channels (the filter is radially symmetric). Its weights fall slowly (about 2 % of the total beyond 4 pixels at
    f/2.8 and 5.6 um), so no window holds all of them: what reads a pixel's neighbours must reach them all
    (:meth:`mbcapture.render.Renderer.render_pixels` gives each render pixel samples in proportion to this)."""
    n = 2 * radius + 1
    delta = np.zeros((n + 2 * PAD_PX, n + 2 * PAD_PX, len(wavelength_nm)))
    c = delta.shape[0] // 2
    delta[c, c] = 1.0
    k = np.abs(apply_diffraction(delta, pixel_pitch_um, f_number, wavelength_nm, clamp=False))
    k = (k / k[c, c]).max(axis=-1)
    return k[c - radius : c + radius + 1, c - radius : c + radius + 1]


def bilinear_taps(map_x: np.ndarray, map_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four pixels of the (H', W') render that :func:`apply_distortion` interpolates each sensor pixel from,
    and their weights: ((4, H, W) flat indices, (4, H, W) bilinear weights), the indices clamped to the render as
    cv2.remap's BORDER_REPLICATE clamps them."""
    h, w = map_x.shape
    x0, y0 = np.floor(map_x).astype(np.int64), np.floor(map_y).astype(np.int64)
    fx, fy = map_x - x0, map_y - y0
    xs = [np.clip(x0 + d, 0, w - 1) for d in (0, 1)]
    ys = [np.clip(y0 + d, 0, h - 1) for d in (0, 1)]
    index = np.stack([y * w + x for y in ys for x in xs])
    weight = np.stack([wy * wx for wy in (1 - fy, fy) for wx in (1 - fx, fx)])
    return index, weight


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


def distort_normalized(x: np.ndarray, y: np.ndarray, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Radial Brown-Conrady distortion of normalized image coordinates (x/z, y/z of the undistorted,
    pinhole ray): each point moves along its radius r to r (1 + k1 r^2 + k2 r^4 + k3 r^6)."""
    r2 = x * x + y * y
    scale = 1.0
    for i, ki in enumerate(k):
        scale = scale + ki * r2 ** (i + 1)
    return x * scale, y * scale


def undistortion_maps(camera, width: int, height: int, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, float]:
    """Where each pixel of a distorting lens looks: ``(map_x, map_y, tan_half_render)``.

    A pixel centre of the sensor sits at distorted normalized coordinates (x_d, y_d) (the camera's
    horizontal field of view spans x_d in [-tan(fov/2), tan(fov/2)]); the ray that the lens bends onto
    it is the pinhole ray of (x_u, y_u) with distort(x_u, y_u) = (x_d, y_d). Barrel distortion (k1 < 0)
    sends the sensor's corners to rays outside the pinhole's field, so the pinhole render that is
    resampled must see wider: ``tan_half_render`` (>= tan(fov/2)) is the horizontal half-field it
    needs, and ``map_x``, ``map_y`` (H, W) float32 are the positions, in that render's pixels, of each
    sensor pixel's ray (for cv2.remap). ValueError when the distortion folds the image over (not
    invertible inside the frame). The inversion is OpenCV's (cv2.undistortPoints, iterated to
    convergence), checked against the forward model."""
    import cv2

    t = tan_half(camera)
    xd = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * t
    yd = (2.0 * (np.arange(height) + 0.5) / height - 1.0) * t * height / width
    gx, gy = np.meshgrid(xd, yd)
    coeffs = np.array([*(list(k) + [0.0] * 3)[:2], 0.0, 0.0, (list(k) + [0.0] * 3)[2]], np.float64)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=-1)[:, None, :]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    und = cv2.undistortPoints(pts, np.eye(3), coeffs, None, None, None, criteria)[:, 0, :]
    xu, yu = und[:, 0].reshape(height, width), und[:, 1].reshape(height, width)
    bx, by = distort_normalized(xu, yu, tuple(k))
    # the forward model must give the pixel back, and the radius must grow with the radius (no fold)
    r_u = np.hypot(xu, yu)
    r = np.linspace(0.0, float(r_u.max()), 2049)
    grows = np.all(np.diff(r * (1.0 + sum(ki * r ** (2 * (i + 1)) for i, ki in enumerate(k)))) > 0)
    if not grows or np.max(np.abs(bx - gx) + np.abs(by - gy)) > 1e-7 * max(t, 1.0):
        raise ValueError(
            f"camera.distortion {list(k)}: folds the image over inside the frame (the distorted radius "
            "must grow with the radius out to the corners); use smaller coefficients"
        )
    # a render of half-field t' puts x_u at pixel (x_u / t' + 1) W / 2 - 1/2, which must stay within
    # [0, W - 1] (and y likewise) for bilinear interpolation
    t_render = max(
        t,
        float(np.abs(xu).max()) * width / (width - 1) if width > 1 else t,
        float(np.abs(yu).max()) * width / (height - 1) if height > 1 else t,
    )
    map_x = ((xu / t_render + 1.0) * width / 2.0 - 0.5).astype(np.float32)
    map_y = ((yu / (t_render * height / width) + 1.0) * height / 2.0 - 0.5).astype(np.float32)
    return map_x, map_y, t_render


def apply_distortion(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """(..., H', W', C) pinhole render -> (..., H, W, C): each sensor pixel takes the radiance of the ray
    the lens bends onto it (:func:`undistortion_maps`), bilinearly interpolated (cv2.remap). Radiance is
    conserved along a ray, so resampling radiance keeps the photometry; the lens's relative
    illumination is :func:`natural_vignetting`'s, evaluated on the render's grid before this."""
    import cv2

    img = np.asarray(image, np.float32)
    flat = img.reshape(-1, *img.shape[-3:])
    out = np.empty((flat.shape[0], *map_x.shape, flat.shape[-1]), np.float32)
    for i, plane in enumerate(flat):
        out[i] = cv2.remap(plane, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(*img.shape[:-3], *map_x.shape, img.shape[-1])
