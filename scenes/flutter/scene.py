"""A textured card crossing the view fast in front of a black void (flutter-shutter motion deblurring).

The card (``card_width_m`` wide, 2:3 high, ``card.png`` on its face: blocks of colour, a checkerboard,
bars, rings and a frequency sweep, so that both edges and fine detail are blurred) translates along the
image's x axis at constant velocity ``speed_m_per_s``, 1 m in front of the camera, parallel to the
image plane, so every point of it moves by the same number of pixels: the blur is one 1-D kernel for
the whole image. Nothing is behind it (the void is black), so a blurred row is exactly the sharp row
convolved with the exposure's kernel: the linear model the deconvolution inverts. A large soft box
above the camera lights it (group ``ambient``, steady).

Coordinates (m): the camera at (0, 0, 1) looks along -z; the card lies in the plane z = 0 and its
centre is at x(t) = ``speed_m_per_s`` (t - ``centre_time_s``), y = 0. At the defaults (2.275 m/s,
40 deg field of view) that is 2.0 px/ms at 640x512: 52 px during a 26 ms exposure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.render.build import Light, Material, SceneBuild, Shape, Texture, frame_towards, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "textured card crossing the view fast before a black void, steady soft light (group ambient)"

HERE = Path(__file__).resolve().parent
CARD_TEXTURE = HERE / "card.png"
CARD_TEXTURE_PX = (240, 160)  # width, height


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    speed_m_per_s: float = Field(
        2.275, ge=0.0, le=50.0, description="card speed along the image's x axis, m/s (0: static)"
    )
    centre_time_s: float = Field(0.013, description="scene time at which the card's centre crosses the optical axis, s")
    card_width_m: float = Field(0.3, gt=0.01, le=0.6, description="card width, m (its height is 2/3 of it)")
    light_radiance: float = Field(2.5, ge=0.0, description="radiance of the soft box lighting the card, W m^-2 sr^-1")
    fov_deg: float = Field(40.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees")


def write_card(path: Path = CARD_TEXTURE) -> None:
    """Draw the card's face (sRGB PNG): colour blocks, a checkerboard, bars, rings and a chirp."""
    import cv2

    w, h = CARD_TEXTURE_PX
    rng = np.random.default_rng(13)
    img = np.full((h, w, 3), 200, np.uint8)
    for _ in range(14):  # colour blocks
        x0, y0 = rng.integers(0, w - 30), rng.integers(0, h // 2)
        cv2.rectangle(
            img,
            (int(x0), int(y0)),
            (int(x0 + rng.integers(12, 40)), int(y0 + rng.integers(8, 30))),
            tuple(int(c) for c in rng.integers(20, 255, 3)),
            -1,
        )
    yy, xx = np.mgrid[0:h, 0:w]
    check = ((xx // 6 + yy // 6) % 2).astype(bool) & (yy >= 90) & (yy < 126) & (xx < 80)
    img[check] = (30, 30, 30)
    for i, x in enumerate(range(90, 150, 5)):  # bars
        cv2.rectangle(img, (x, 92), (x + 1 + i % 3, 150), (40, 40, 160), -1)
    for r in range(4, 30, 5):  # rings
        cv2.circle(img, (195, 118), r, (160, 40, 40), 1)
    chirp = 0.5 + 0.5 * np.cos(2 * np.pi * (xx / w) ** 2 * 40)  # frequency sweep
    band = (yy >= 130) & (yy < 156)
    img[band] = (np.repeat(chirp[band][:, None], 3, -1) * 220 + 20).astype(np.uint8)
    cv2.imwrite(str(path), img[..., ::-1])


def make(params: Params) -> SceneModel:
    w = params.card_width_m
    v, tc = params.speed_m_per_s, params.centre_time_s

    def card_x(t_s):
        return v * (np.asarray(t_s, float) - tc)

    def card_to_world(t_s: float) -> np.ndarray:
        return translate(float(card_x(t_s)), 0.0, 0.0)

    shapes = (
        Shape("card_face", "rectangle", scale(w / 2, w / 3, 1.0), Material(Texture(str(CARD_TEXTURE))), part="card"),
        Shape(
            "softbox",
            "rectangle",
            frame_towards((0.0, 0.6, 0.9), (0.0, 0.0, 0.0)) @ scale(0.5, 0.3, 1.0),
            None,
            Light("ambient", (params.light_radiance,) * 3),
        ),
    )
    corners = np.array([[sx * w / 2, sy * w / 3, 0.0] for sx in (-1, 1) for sy in (-1, 1)] + [[0.0, 0.0, 0.0]])

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the card's corners and centre, m."""
        x = np.atleast_1d(card_x(times_s))
        return corners[None] + np.stack([x, np.zeros_like(x), np.zeros_like(x)], -1)[:, None, :]

    return SceneModel(
        name="flutter",
        groups=("ambient",),
        switchable=frozenset(),
        camera=Camera(origin=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=params.fov_deg),
        build=SceneBuild(shapes=shapes, parts={"card": card_to_world}),
        params=params,
        motion_points=motion_points if v > 0 else None,
        default_film=(640, 512),
        extra={"foreground": ("card_face",)},
    )


if __name__ == "__main__":  # regenerate card.png
    write_card()
    print(f"wrote {CARD_TEXTURE}")
