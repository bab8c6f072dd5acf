"""A ColorChecker chart and a picture on a board, shaken by hand, lit by red, green and blue LEDs.

The board (30 x 28 cm, dark grey) carries the 24 patches of an X-Rite ColorChecker Classic
(measured reflectance spectra, colour-science's ``'ColorChecker N Ohta'``; 34 mm patches on a
40 mm pitch, 6 columns x 4 rows) and below them a picture (``picture.png``, a bitmap texture with
saturated colours and sharp edges: hue wheel, stripes, a checkerboard). A grey wall stands 30 cm
behind. The camera looks along -z from 1 m.

Emitter groups (output order):

``ambient``  a 50 x 50 cm panel above the scene, out of view, with the spectrum of CIE
             illuminant A (incandescent; always on)
``led_r``, ``led_g``, ``led_b``
             8 x 8 cm LED panels beside the lens, aimed at the chart centre, with LED spectra of
             colour-science's Ohno (2005) model (peaks 630, 525, 460 nm by default). Switchable.

Light levels are given as irradiance at the chart centre, W m^-2 integrated over wavelength,
using the small-source approximation E = L A cos(theta) / d^2 for each panel.

Motion: the board (chart and picture) is shaken by hand: it translates by
dx(t) = A (1 - cos(2 pi f t)), dy(t) = 0.6 A (1 - cos(2 pi 1.3 f t)); at scene time 0 (``REST_TIME_S``) it is
at its rest position with zero velocity, the pose of the static reference.

``extra``: ``patches`` (name, centre (x, y, z) at rest, half size m), ``reflectances`` (name ->
Spectrum), ``led_spectra`` (group -> Spectrum in W m^-2 sr^-1 nm^-1 of the panel),
``ambient_spectrum``, ``rest_time_s``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mbcapture.render.build import (
    Light,
    Material,
    PerTile,
    SceneBuild,
    Shape,
    Spectrum,
    Texture,
    frame_towards,
    scale,
    translate,
)
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = (
    "ColorChecker chart and a picture shaken by hand, lit by R, G, B LED panels (groups ambient, led_r, led_g, led_b)"
)

HERE = Path(__file__).resolve().parent
PICTURE = HERE / "picture.png"
REST_TIME_S = 0.0

CAMERA_ORIGIN = (0.0, 0.0, 1.0)
CAMERA_TARGET = (0.0, 0.0, 0.0)
PATCH_PITCH_M = 0.040
PATCH_HALF_M = 0.017
CHART_CENTRE = (0.0, 0.045)  # centre of the 6 x 4 patch grid on the board, m
PICTURE_CENTRE = (0.0, -0.085)
PICTURE_HALF = (0.12, 0.045)  # 24 x 9 cm
PICTURE_PX = (320, 120)
BOARD_CENTRE = (0.0, -0.004)
BOARD_HALF = (0.15, 0.14)
LED_HALF_M = 0.04  # 8 x 8 cm panels
LED_POSITIONS = {"led_r": (-0.14, 0.08, 1.0), "led_g": (0.0, 0.16, 1.0), "led_b": (0.14, 0.08, 1.0)}
AMBIENT_POSITION = (0.0, 0.9, 0.6)
AMBIENT_HALF_M = 0.25
CHART_NAME = "ColorChecker N Ohta"


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    led_peak_nm: list[float] = Field(
        default=[630.0, 525.0, 460.0], description="peak wavelength of the red, green and blue LEDs, nm"
    )
    led_fwhm_nm: list[float] = Field(
        default=[20.0, 35.0, 25.0], description="spectral width (FWHM) of the red, green and blue LEDs, nm"
    )
    led_irradiance_w_m2: list[float] = Field(
        default=[3.0, 2.0, 2.4],
        description="irradiance of each LED (R, G, B) at the chart centre, W m^-2 over all wavelengths",
    )
    ambient_irradiance_w_m2: float = Field(
        default=1.0, ge=0.0, description="irradiance of the ambient panel (illuminant A) at the chart centre, W m^-2"
    )
    shake_amplitude_m: float = Field(
        default=0.004, ge=0.0, le=0.05, description="hand-shake amplitude A of the board, m (0: static)"
    )
    shake_frequency_hz: float = Field(default=4.0, gt=0.0, le=100.0, description="hand-shake frequency f, Hz")
    picture: str | None = Field(
        default=None, description="bitmap (PNG/JPEG/EXR) shown below the chart; default: the scene's picture.png"
    )
    fov_deg: float = Field(default=22.0, gt=5.0, lt=90.0, description="horizontal field of view of the camera, degrees")

    @field_validator("led_peak_nm", "led_fwhm_nm", "led_irradiance_w_m2")
    @classmethod
    def _three_positive(cls, v: list[float]) -> list[float]:
        if len(v) != 3 or any(not x > 0 for x in v):
            raise ValueError("expected 3 positive values (R, G, B)")
        return v


def make_picture(width: int = PICTURE_PX[0], height: int = PICTURE_PX[1]) -> np.ndarray:
    """The procedural picture, uint8 sRGB (height, width, 3): a hue wheel, saturated diagonal
    stripes and a black-and-white checkerboard, all with sharp edges."""
    import colour

    y, x = np.mgrid[0:height, 0:width].astype(float) + 0.5
    img = np.full((height, width, 3), 0.85)
    # hue wheel: 12 sectors, white centre
    cx, cy, r = height * 0.5, height * 0.5, height * 0.42
    ang = (np.arctan2(y - cy, x - cx) / (2 * np.pi)) % 1.0
    dist = np.hypot(x - cx, y - cy)
    hsv = np.stack([np.floor(ang * 12) / 12, np.ones_like(ang), np.ones_like(ang)], -1)
    wheel = colour.HSV_to_RGB(hsv)
    inside = (dist < r) & (dist > r * 0.25)
    img[inside] = wheel[inside]
    img[dist <= r * 0.25] = 1.0
    # diagonal stripes: red, green, blue, yellow, magenta, cyan
    stripes = np.array(
        [
            [0.9, 0.05, 0.05],
            [0.05, 0.7, 0.1],
            [0.1, 0.15, 0.9],
            [0.95, 0.85, 0.05],
            [0.85, 0.1, 0.75],
            [0.05, 0.75, 0.8],
        ]
    )
    x0, x1 = width * 0.36, width * 0.68
    band = (x >= x0) & (x < x1)
    k = np.floor((x + y) / (height / 6.0)).astype(int) % len(stripes)
    img[band] = stripes[k[band]]
    # checkerboard
    cb = (x >= width * 0.72) & (x < width * 0.97) & (y >= height * 0.1) & (y < height * 0.9)
    check = ((np.floor(x / 8) + np.floor(y / 8)) % 2).astype(bool)
    img[cb & check] = 0.03
    img[cb & ~check] = 0.95
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def write_picture(path: Path = PICTURE) -> None:
    """Write :func:`make_picture` to ``path`` (PNG)."""
    import cv2

    if not cv2.imwrite(str(path), make_picture()[..., ::-1]):
        raise OSError(f"cannot write {path}")


def led_spectrum(peak_nm: float, fwhm_nm: float) -> Spectrum:
    """LED spectral shape (Ohno 2005), normalized to integral 1 over wavelength (nm^-1)."""
    import colour

    sd = colour.sd_single_led(peak_nm, shape=colour.SpectralShape(360, 830, 2), half_spectral_width=fwhm_nm)
    spec = Spectrum.from_sd(sd)
    return Spectrum.from_sd(sd, scale=1.0 / spec.integral())


def ambient_spectrum_shape() -> Spectrum:
    """CIE illuminant A, 360..830 nm in 5 nm steps, normalized to integral 1 (nm^-1)."""
    import colour

    sd = colour.SDS_ILLUMINANTS["A"].copy().align(colour.SpectralShape(360, 830, 5))
    spec = Spectrum.from_sd(sd)
    return Spectrum.from_sd(sd, scale=1.0 / spec.integral())


def chart_reflectances() -> dict[str, Spectrum]:
    """The 24 patches' reflectance spectra, in chart order (row by row from top left)."""
    import colour

    return {name: Spectrum.from_sd(sd) for name, sd in colour.SDS_COLOURCHECKERS[CHART_NAME].items()}


def _panel_radiance(irradiance_w_m2: float, position, half_m: float, target=(0.0, 0.0, 0.0)) -> float:
    """Band radiance (W m^-2 sr^-1) of a square panel that gives ``irradiance_w_m2`` at ``target``
    on a surface facing +z: E = L A cos(theta_surface) / d^2 (the panel faces the target)."""
    d = np.subtract(target, position)
    dist = float(np.linalg.norm(d))
    cos_surface = abs(d[2]) / dist
    area = (2 * half_m) ** 2
    return irradiance_w_m2 * dist**2 / (area * cos_surface)


def _camera(p: Params) -> Camera:
    return Camera(origin=CAMERA_ORIGIN, target=CAMERA_TARGET, up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)


def make(params: Params) -> SceneModel:
    """The colour-chart scene for ``params``."""
    picture = params.picture if params.picture is not None else str(PICTURE)
    refl = chart_reflectances()
    names = list(refl)
    shapes: list[Shape] = [
        Shape("wall", "rectangle", translate(0, 0, -0.3) @ scale(0.6, 0.5, 1), Material((0.5, 0.5, 0.5))),
        Shape(
            "board",
            "rectangle",
            translate(*BOARD_CENTRE, 0.0) @ scale(*BOARD_HALF, 1),
            Material((0.04, 0.04, 0.04)),
            part="chart",
        ),
        Shape(
            "picture",
            "rectangle",
            translate(*PICTURE_CENTRE, 0.0005) @ scale(*PICTURE_HALF, 1),
            Material(Texture(picture)),
            part="chart",
        ),
    ]
    patches = []
    for i, name in enumerate(names):
        row, col = divmod(i, 6)
        cx = CHART_CENTRE[0] + (col - 2.5) * PATCH_PITCH_M
        cy = CHART_CENTRE[1] + (1.5 - row) * PATCH_PITCH_M
        patches.append((name, (cx, cy, 0.0005), PATCH_HALF_M))
    # the 24 patches as one shape with one BSDF: as 24 shapes they were most of a render's time
    shapes.append(
        Shape(
            "patches",
            "tiles",
            np.eye(4),
            Material(PerTile(tuple(refl[n] for n in names))),
            part="chart",
            tiles=tuple(translate(*c) @ scale(h) for _, c, h in patches),
        )
    )

    led_spectra: dict[str, Spectrum] = {}
    for g, peak, fwhm, e in zip(
        ("led_r", "led_g", "led_b"), params.led_peak_nm, params.led_fwhm_nm, params.led_irradiance_w_m2
    ):
        pos = LED_POSITIONS[g]
        shape = led_spectrum(peak, fwhm)
        rad = _panel_radiance(e, pos, LED_HALF_M)
        spec = Spectrum(shape.wavelengths_nm, tuple(np.asarray(shape.values) * rad))
        led_spectra[g] = spec
        shapes.append(
            Shape(
                f"{g}_panel",
                "rectangle",
                frame_towards(pos, (0, 0, 0)) @ scale(LED_HALF_M, LED_HALF_M, 1),
                None,
                Light(g, spec),
            )
        )
    amb_shape = ambient_spectrum_shape()
    amb_rad = _panel_radiance(params.ambient_irradiance_w_m2, AMBIENT_POSITION, AMBIENT_HALF_M)
    ambient = Spectrum(amb_shape.wavelengths_nm, tuple(np.asarray(amb_shape.values) * max(amb_rad, 0.0)))
    shapes.append(
        Shape(
            "ambient_panel",
            "rectangle",
            frame_towards(AMBIENT_POSITION, (0, 0, 0), up=(0, 0, -1)) @ scale(AMBIENT_HALF_M, AMBIENT_HALF_M, 1),
            None,
            Light("ambient", ambient),
        )
    )

    amp, f = params.shake_amplitude_m, params.shake_frequency_hz

    def offset(t_s):
        t = np.asarray(t_s, float)
        return amp * (1 - np.cos(2 * math.pi * f * t)), 0.6 * amp * (1 - np.cos(2 * math.pi * 1.3 * f * t))

    def chart_to_world(t_s: float) -> np.ndarray:
        dx, dy = offset(t_s)
        return translate(float(dx), float(dy), 0.0)

    corners = np.array(
        [
            [BOARD_CENTRE[0] + sx * BOARD_HALF[0], BOARD_CENTRE[1] + sy * BOARD_HALF[1], 0.0]
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
        + [[*p[1][:2], 0.0] for p in patches[::5]]
    )

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the board corners and some patch centres, m."""
        dx, dy = offset(np.atleast_1d(times_s))
        shift = np.stack([dx, dy, np.zeros_like(dx)], -1)[:, None, :]
        return corners[None] + shift

    return SceneModel(
        name="colour_chart",
        groups=("ambient", "led_r", "led_g", "led_b"),
        switchable=frozenset({"led_r", "led_g", "led_b"}),
        camera=_camera(params),
        build=SceneBuild(shapes=tuple(shapes), parts={"chart": chart_to_world}),
        params=params,
        motion_points=None if amp == 0 else motion_points,
        default_film=(640, 512),
        extra={
            "patches": patches,
            "reflectances": refl,
            "led_spectra": led_spectra,
            "ambient_spectrum": ambient,
            "rest_time_s": REST_TIME_S,
            "picture": picture,
        },
    )


if __name__ == "__main__":  # regenerate picture.png
    write_picture()
    print(f"wrote {PICTURE}")
