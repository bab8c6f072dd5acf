"""Objects at several depths in front of a wall, lit by four LEDs around the lens (multi-flash).

The setting of Raskar et al. 2004 ("Non-photorealistic camera: depth edge detection and
stylized rendering using multi-flash imaging") and of the multi-bucket paper's section 5.3:
four small LEDs sit in the plane of the lens, ``led_offset_m`` above, below, left and right of
it, so each one casts a thin shadow beside every depth discontinuity, on the side away from
the LED. A box slides left and right in front of everything (the moving object).

Coordinates (m): y up, the wall is the plane z = 0, the camera sits at (0, 0, ``camera_distance_m``)
and looks along -z at the wall's centre, so image rows are world x and image columns world y
(image right = +x, image up = +y). Objects, nearest first (distance from the lens at the
default 1.0 m): the sliding box (front face ~0.60 m), a sphere (~0.68 m), a vertical cylinder
with a top cap (~0.80 m), a tilted box (~0.82 m), a flat box low on the wall (~0.90 m). No
floor: every object's outline is a depth discontinuity against the wall or another object.

Emitter groups (output order):

``ambient``        a weak, large soft box above the camera, outside the view (always on)
``flash_top``      1 x 1 cm LED ``led_offset_m`` above the lens, aimed at the wall's centre
``flash_bottom``   ... below the lens
``flash_left``     ... left of the lens (image left, world -x)
``flash_right``    ... right of the lens (image right, world +x)

The four flash groups are switchable; ``extra["flash_positions_m"]`` gives each LED's centre
(world, m) so that an application can find its epipole, ``extra["flash_directions"]`` the unit
direction each faces (photometric stereo's emitter cosine). Radiance scale at the default factors:
the wall under one LED about 1.1 W m^-2 sr^-1, under the ambient light about 0.1.

Motion: the sliding box's centre is at x(t) = ``slide_amplitude_m`` sin(2 pi f t) (f =
``slide_frequency_hz``, t scene time, s): at t = 0 it crosses the image centre line at its
fastest, 2 pi f A (0.30 m/s at the defaults: ~1.4 px/ms at 640x512).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.render.build import Light, Material, SceneBuild, Shape, box, frame_towards, rotate, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = (
    "boxes, a cylinder and a sphere before a wall, a sliding box, four LEDs around the lens "
    "(groups ambient, flash_top, flash_bottom, flash_left, flash_right)"
)

#: Radiance of each light at scale factor 1, W m^-2 sr^-1.
AMBIENT_RADIANCE = 1.0
LED_RADIANCE = 6.0e4
LED_HALF_SIZE_M = 0.005  # 1 x 1 cm emitting square

FLASH_GROUPS = ("flash_top", "flash_bottom", "flash_left", "flash_right")
#: LED offset direction from the lens per group, in the camera frame (image right, image up).
LED_DIRECTIONS = {
    "flash_top": (0.0, 1.0),
    "flash_bottom": (0.0, -1.0),
    "flash_left": (-1.0, 0.0),
    "flash_right": (1.0, 0.0),
}

SLIDER_HALF_M = (0.035, 0.035, 0.03)  # half sizes of the sliding box
SLIDER_Y_M = -0.02
SLIDER_Z_M = 0.37  # centre: its front face is at z = 0.40


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    slide_amplitude_m: float = Field(
        default=0.12, ge=0.0, le=0.2, description="sliding box: amplitude of its left-right motion, m (0: static scene)"
    )
    slide_frequency_hz: float = Field(
        default=0.4, gt=0.0, le=20.0, description="sliding box: oscillation frequency, Hz"
    )
    led_offset_m: float = Field(
        default=0.07, gt=0.005, le=0.3, description="distance of each LED's centre from the lens centre, m"
    )
    camera_distance_m: float = Field(default=1.0, ge=0.6, le=3.0, description="distance from the lens to the wall, m")
    ambient_scale: float = Field(default=1.0, ge=0.0, description="ambient light radiance factor, 1")
    flash_scale: float = Field(default=1.0, ge=0.0, description="radiance factor of every LED, 1")
    fov_deg: float = Field(
        default=40.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees"
    )


def _camera(p: Params) -> Camera:
    return Camera(origin=(0.0, 0.0, p.camera_distance_m), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)


def led_positions(p: Params) -> dict[str, tuple[float, float, float]]:
    """World centre of each LED (m): in the lens plane, ``led_offset_m`` from the lens centre."""
    o = _camera(p).origin
    return {g: (o[0] + p.led_offset_m * dx, o[1] + p.led_offset_m * dy, o[2]) for g, (dx, dy) in LED_DIRECTIONS.items()}


def led_directions(p: Params) -> dict[str, tuple[float, float, float]]:
    """The unit direction each LED faces (world): towards the camera's target, the wall's centre."""
    target = np.asarray(_camera(p).target, float)
    out = {}
    for g, pos in led_positions(p).items():
        d = target - np.asarray(pos, float)
        out[g] = tuple(float(v) for v in d / np.linalg.norm(d))
    return out


def _static_shapes(p: Params) -> list[Shape]:
    amb = AMBIENT_RADIANCE * p.ambient_scale
    led = LED_RADIANCE * p.flash_scale
    rot_x = rotate((1, 0, 0), -math.pi / 2)  # canonical +z -> +y (a cap facing up)
    shapes = [
        # Wall: 1.8 x 1.5 m, fills the view at any allowed camera distance and field of view <= ~60 deg.
        Shape(
            "wall",
            "rectangle",
            scale(0.9 * p.camera_distance_m + 0.3, 0.75 * p.camera_distance_m + 0.3, 1),
            Material((0.62, 0.60, 0.56)),
        ),
        # Tilted box, upper left (front corner ~0.18 m off the wall).
        Shape(
            "box_tilted",
            "cube",
            translate(-0.17, 0.11, 0.12)
            @ rotate((0, 1, 0), 0.45)
            @ rotate((1, 0, 0), 0.25)
            @ scale(0.055, 0.045, 0.04),
            Material((0.70, 0.25, 0.12)),
        ),
        # Flat box low on the wall, 0.1 m off it.
        Shape("box_flat", "cube", box((-0.02, -0.17, 0.07), (0.10, 0.035, 0.03)), Material((0.20, 0.35, 0.60))),
        # Vertical cylinder with a top cap, right, axis 0.15 m off the wall.
        Shape(
            "cylinder",
            "cylinder",
            translate(0.19, -0.20, 0.15) @ rotate((1, 0, 0), -math.pi / 2) @ scale(0.045, 0.045, 0.28),
            Material((0.25, 0.55, 0.25)),
        ),
        Shape("cylinder_cap", "disk", translate(0.19, 0.08, 0.15) @ rot_x @ scale(0.045), Material((0.25, 0.55, 0.25))),
        # Sphere, upper middle, 0.27 m off the wall.
        Shape("sphere", "sphere", translate(0.06, 0.13, 0.27) @ scale(0.05), Material((0.80, 0.78, 0.70))),
        # Ambient: a 0.8 x 0.5 m soft box above the camera, aimed at the wall.
        Shape(
            "ambient_softbox",
            "rectangle",
            frame_towards((0.0, 0.75, 0.8 * p.camera_distance_m), (0.0, 0.0, 0.0)) @ scale(0.4, 0.25, 1),
            None,
            Light("ambient", (amb, amb, amb * 0.9)),
        ),
    ]
    target = _camera(p).target
    for g, pos in led_positions(p).items():
        shapes.append(
            Shape(
                f"led_{g.removeprefix('flash_')}",
                "rectangle",
                frame_towards(pos, target) @ scale(LED_HALF_SIZE_M, LED_HALF_SIZE_M, 1),
                None,
                Light(g, (led, led, led)),
            )
        )
    return shapes


def make(params: Params) -> SceneModel:
    """The multi-flash scene for ``params``."""
    A, f = params.slide_amplitude_m, params.slide_frequency_hz

    def slider_x(t_s):
        return A * np.sin(2 * np.pi * f * np.asarray(t_s, float))

    def slider_to_world(t_s: float) -> np.ndarray:
        """World-from-slider matrix (4, 4) at scene time ``t_s`` (s)."""
        return translate(float(slider_x(t_s)), SLIDER_Y_M, SLIDER_Z_M)

    hx, hy, hz = SLIDER_HALF_M
    shapes = _static_shapes(params) + [
        Shape("slider_box", "cube", scale(hx, hy, hz), Material((0.85, 0.75, 0.15)), part="slider"),
    ]
    # the front face's corners and centre, and the back corners (what the camera sees of the box)
    corners = np.array(
        [[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)] + [[0.0, 0.0, hz]]
    )

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the sliding box's corners and front centre, m."""
        x = np.atleast_1d(slider_x(times_s))
        off = np.stack([x, np.full_like(x, SLIDER_Y_M), np.full_like(x, SLIDER_Z_M)], axis=-1)
        return corners[None, :, :] + off[:, None, :]

    return SceneModel(
        name="multiflash",
        groups=("ambient",) + FLASH_GROUPS,
        switchable=frozenset(FLASH_GROUPS),
        camera=_camera(params),
        build=SceneBuild(shapes=tuple(shapes), parts={"slider": slider_to_world}),
        params=params,
        motion_points=motion_points if A > 0 else None,
        default_film=(640, 512),
        extra={"flash_positions_m": led_positions(params), "flash_directions": led_directions(params)},
    )
