"""The camera's lens on a pinhole render (:class:`Lens`): relative illumination, radial distortion and diffraction
(:mod:`mbcapture.scene.optics`), applied to every render after the render cache (a render is cached as the
pinhole sees it), and the samples a listed-pixel render needs where the lens mixes neighbouring pixels."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from ..scene.optics import (
    apply_diffraction,
    apply_distortion,
    bilinear_taps,
    diffraction_reach,
    natural_vignetting,
    undistortion_maps,
)
from ..scene.projective import Camera


class Lens:
    """The lens of ``camera`` on a ``width`` x ``height`` film: ``vignetting`` ('none' or 'cos4': the natural
    falloff), radial ``distortion`` coefficients (None: none) and, with ``diffraction``, the diffraction of the
    aperture of ``sensor`` (its f-number, pixel pitch and wavelengths).

    Attributes: ``render_fov_deg``, the field Mitsuba renders (wider than the camera's under barrel distortion);
    ``mixes_pixels``, whether the lens mixes neighbouring pixels (distortion, diffraction: the film is then one
    render band)."""

    def __init__(
        self,
        camera: Camera,
        width: int,
        height: int,
        *,
        vignetting: str = "none",
        distortion: Sequence[float] | None = None,
        diffraction: bool = False,
        sensor: Any = None,
    ) -> None:
        if vignetting not in ("none", "cos4"):
            raise ConfigError(f"camera.vignetting: expected 'none' or 'cos4', got {vignetting!r}")
        self.width, self.height = int(width), int(height)
        # radial distortion (mbcapture.scene.optics): Mitsuba renders a pinhole of field render_fov_deg (wider than
        # the camera's for barrel distortion) and every render is resampled onto the sensor's pixels
        self.distortion = None if not distortion else tuple(float(k) for k in distortion)
        self.render_fov_deg = float(camera.fov_deg)
        self.undistort = None
        if self.distortion is not None:
            try:
                map_x, map_y, t_render = undistortion_maps(camera, width, height, self.distortion)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
            self.undistort = (map_x, map_y)
            self.render_fov_deg = float(np.degrees(2.0 * np.arctan(t_render)))
        # the falloff of each ray's field angle, on the grid Mitsuba renders (before any resampling)
        self.falloff = (
            None
            if vignetting == "none"
            else natural_vignetting(replace(camera, fov_deg=self.render_fov_deg), width, height).astype(np.float32)[
                None, :, :, None
            ]
        )
        if diffraction and sensor is None:
            raise ConfigError("camera.diffraction: needs the sensor (f-number, pixel pitch, wavelengths)")
        self.diffraction = sensor if diffraction else None  # the sensor's f-number, pitch and wavelengths
        # what render_pixels needs to reach every render pixel a sensor pixel reads: the four each is interpolated
        # from (distortion) and the log of how much its neighbours weigh in it (diffraction; mbcapture.scene.optics)
        self.taps = None
        if self.undistort is not None:  # each tap's samples: its weight b over sum b^2 of the sensor pixel's count
            index, weight = bilinear_taps(*self.undistort)
            self.taps = (index.reshape(4, -1), (weight / (weight * weight).sum(axis=0)).reshape(4, -1))
        self.log_reach = None
        if diffraction:
            # a pixel's samples in proportion to its weight k in a sensor pixel, scaled by sum k / sum k^2: the sensor
            # pixel's variance is then what the first pass's would be at the count it asks for (every pinhole pixel at
            # it), at about sum k (sum k / sum k^2) = 1.46 times the count (f/2.8, 5.6 um) instead of the window's 289
            k = diffraction_reach(sensor.pixel_pitch_um, sensor.f_number, sensor.wavelength_nm)
            self.log_reach = np.log(np.maximum(k * (k.sum() / (k * k).sum()), 1e-300))
        self.mixes_pixels = self.undistort is not None or self.diffraction is not None

    def apply(self, img: np.ndarray, r0: int, r1: int) -> np.ndarray:
        """The lens on the pinhole's rows ``r0`` .. ``r1`` (group, row, col, channel): relative illumination, then
        (on the whole film) distortion and diffraction."""
        if self.falloff is not None:
            img = img * self.falloff[:, r0:r1]
        if self.undistort is not None:  # the lens bends each pixel's ray: resample the pinhole render
            img = apply_distortion(img, *self.undistort)
        if self.diffraction is not None:
            s = self.diffraction
            img = apply_diffraction(img, s.pixel_pitch_um, s.f_number, s.wavelength_nm).astype(np.float32)
        return img

    def samples(self, pix: np.ndarray, counts: np.ndarray, offsets: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(flat, per pinhole pixel) the samples :meth:`mbcapture.render.Renderer.render_pixels` renders each pinhole pixel with (0: none asked;
        it then takes one) and the pattern offset they start at, where sensor pixels ``pix`` ask for ``counts`` from
        ``offsets``: through diffraction, each sensor pixel's count in proportion to how much each neighbour weighs in
        it (:func:`mbcapture.scene.optics.diffraction_reach`; rounded, the most over what reaches a pixel), which for a
        given variance costs the fewest samples; through distortion, the four pixels it is interpolated from, its
        count over the sum of their squared weights times each one's weight (the same rule). Unbiased whatever they
        are (every pixel is rendered); they set the variance and the cost."""
        from scipy.ndimage import grey_dilation

        n = np.zeros(self.height * self.width)
        n[pix] = counts
        o = np.zeros(self.height * self.width, np.int64)
        if offsets is not None:
            o[pix] = offsets
        n, o = n.reshape(self.height, self.width), o.reshape(self.height, self.width)
        if self.log_reach is not None:
            none = -1e300
            log_n = grey_dilation(
                np.where(n > 0, np.log(np.maximum(n, 1.0)), none), structure=self.log_reach, mode="constant", cval=none
            )
            n = np.where(log_n > none / 2, np.rint(np.exp(np.minimum(log_n, 700.0))), 0.0)
            o = grey_dilation(o, size=self.log_reach.shape, mode="constant", cval=0)
        n, o = n.ravel(), o.ravel()
        if self.taps is not None:
            on = np.flatnonzero(n > 0)
            reach_n, reach_o = np.zeros_like(n), np.zeros_like(o)
            for taps, share in zip(*self.taps):
                np.maximum.at(reach_n, taps[on], np.rint(n[on] * share[on]))
                np.maximum.at(reach_o, taps[on], o[on])
            n, o = reach_n, reach_o
        return n.astype(np.int64), o
