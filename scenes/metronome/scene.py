"""Still life with a swinging metronome (the paper's figures 1 and 12).

A table top against a back wall carries a few objects of different albedo and colour, a
small lamp whose bright bulb is in view, and a metronome whose needle swings about a pivot
near the base of the body with a letter "S" (five thin boxes) on its tip, facing the camera.

Coordinates (m): y up, the table top is y = 0, the camera looks along -z at the metronome,
which stands at the origin. At needle angle theta = 0 the needle points up; positive theta
turns it counter-clockwise as seen from the camera (tip towards -x, image left).

Emitter groups (output order):

``ambient``  a large, soft overhead light in front of the scene, outside the view (always on)
``lamp``     a small bulb in view, ~1e4..1e5 x brighter than the darkest lit surfaces (always on)
``flash``    a 1 cm LED beside the camera lens aimed at the metronome (switchable)

Radiance scale at the default factors: lit diffuse surfaces about 0.005..1 W m^-2 sr^-1,
the bulb 2000 W m^-2 sr^-1 (white).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.scene.pendulum import Pendulum
from mbcapture.render.build import (
    Guide,
    Light,
    Material,
    SceneBuild,
    Shape,
    box,
    frame_towards,
    rotate,
    scale,
    translate,
)
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "still life with a swinging metronome, letter S on the needle (groups ambient, lamp, flash)"

# Radiance of each light at scale factor 1, W m^-2 sr^-1.
AMBIENT_RADIANCE = 6.0
LAMP_RADIANCE = 2000.0
FLASH_RADIANCE = 4.0e4

BODY_DEPTH_M = 0.07
NEEDLE_Z_M = BODY_DEPTH_M / 2 + 0.006  # needle plane, in front of the body's front face
CAMERA_ORIGIN = (0.0, 0.23, 1.15)
CAMERA_TARGET = (0.02, 0.11, 0.0)
FLASH_OFFSET_M = (0.05, 0.0, 0.0)  # LED position relative to the lens (camera frame: right, up, back)
LAMP_X_M, LAMP_Z_M = 0.3, -0.2  # the lamp's stand (radius 4 mm, 0.2 m high) and bulb (radius 12 mm) above it
STAND_TOP_M, STAND_RADIUS_M = 0.2, 0.004
BULB_Y_M, BULB_RADIUS_M = 0.215, 0.012
WALL_Z_M = -0.4  # the back wall's plane; the table top is the plane y = 0
#: The stand's top centimetre lies 3-15 mm under the bulb: lit to a radiance of 2-12 W m^-2 sr^-1 (its rim
#: to 1 cm down), 20-100x the wall's left half, a patch 8 mm wide that a bounce from there finds about once in
#: 10^4. Those rare bounces were the wall's single-pixel fireflies (docs/noise.md, "The lamp's stand"), so
#: the path tracer samples towards it (:class:`~mbcapture.render.build.Guide`).
STAND_GUIDE = Guide((LAMP_X_M, STAND_TOP_M - 0.008, LAMP_Z_M), 0.01, 0.02)
#: The spots the bulb lights on the wall 0.2 m behind it and on the table 0.215 m under it (irradiance falling
#: as the cube of the distance from the bulb: within 0.2 m of the foot of the perpendicular lies 30 % of the
#: light the bulb sends to the wall's plane). A bounce from the rest of the scene finds them rarely, and the
#: bounces that do carry most of the image's rendering noise: in the median pixels of the default capture,
#: 1 % of the one-bounce samples (80 % of them on the table's spot) held 38 % of their second moment, and 1 %
#: of the two-bounce samples (90 % on the wall's spot) 73 %. Radii and shares chosen by measurement
#: (docs/noise.md, "The lamp's spots"): J4's median 0.60x and its p95 0.80x at equal samples. Their centres lie
#: 1 cm off the wall and the table (:class:`~mbcapture.render.build.Guide` says why).
WALL_SPOT_GUIDE = Guide((LAMP_X_M, BULB_Y_M, WALL_Z_M + 0.01), 0.25, 0.1)
TABLE_SPOT_GUIDE = Guide((LAMP_X_M, 0.01, LAMP_Z_M), 0.1, 0.03)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tempo_bpm: float = Field(
        default=120.0, gt=0.0, le=400.0, description="metronome tempo, beats per minute (a beat is half a swing period)"
    )
    amplitude_deg: float = Field(
        default=30.0, gt=0.0, lt=90.0, description="needle swing amplitude from the vertical, degrees"
    )
    motion_model: Literal["pendulum", "sine"] = Field(
        default="pendulum",
        description="'pendulum': nonlinear physical pendulum with the tempo's period; 'sine': harmonic",
    )
    phase_s: float = Field(
        default=0.0, description="pendulum time at scene time 0, s (0: needle vertical, moving to image left)"
    )
    damping_per_s: float = Field(
        default=0.0, ge=0.0, description="needle damping rate gamma, 1/s (0: the escapement keeps the swing)"
    )
    needle_length_m: float = Field(
        default=0.10, gt=0.02, le=0.2, description="needle length from the pivot to the base of the S, m"
    )
    ambient_scale: float = Field(default=1.0, ge=0.0, description="ambient light radiance factor, 1")
    lamp_scale: float = Field(default=1.0, ge=0.0, description="lamp bulb radiance factor, 1")
    flash_scale: float = Field(default=1.0, ge=0.0, description="flash LED radiance factor, 1")
    fov_deg: float = Field(
        default=40.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees"
    )


# Geometry of the needle's moving part, in the part frame (origin at the pivot, y along the needle).
NEEDLE_HALF_WIDTH_M = 0.0035
S_HEIGHT_M = 0.045
S_WIDTH_M = 0.034
S_STROKE_M = 0.008
S_GAP_M = 0.004  # between the needle tip and the bottom of the S


def _letter_s(base_y: float) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """The S as five strokes: (centre (x, y), half size (x, y)) in the needle plane, m."""
    w, h, st = S_WIDTH_M, S_HEIGHT_M, S_STROKE_M
    bar = (w / 2, st / 2)
    col = (st / 2, (h - 2 * st) / 4 + st / 2)  # vertical strokes overlap the bars
    return [
        ((0.0, base_y + h - st / 2), bar),  # top bar
        ((0.0, base_y + h / 2), bar),  # middle bar
        ((0.0, base_y + st / 2), bar),  # bottom bar
        ((-w / 2 + st / 2, base_y + 3 * h / 4), col),  # upper-left stroke
        ((w / 2 - st / 2, base_y + h / 4), col),  # lower-right stroke
    ]


def _needle_shapes(length_m: float) -> list[Shape]:
    needle_mat = Material((0.75, 0.72, 0.65))  # brushed metal-ish, Lambertian
    letter_mat = Material((0.9, 0.88, 0.2))  # yellow S
    weight_mat = Material((0.6, 0.55, 0.35))
    shapes = [
        Shape(
            "needle_rod",
            "cube",
            box((0.0, length_m / 2, 0.0), (NEEDLE_HALF_WIDTH_M, length_m / 2, 0.002)),
            needle_mat,
            part="needle",
        ),
        Shape(
            "needle_weight",
            "cube",
            box((0.0, 0.55 * length_m, 0.004), (0.009, 0.007, 0.004)),
            weight_mat,
            part="needle",
        ),
    ]
    for i, ((cx, cy), (hx, hy)) in enumerate(_letter_s(length_m + S_GAP_M)):
        shapes.append(Shape(f"letter_s{i}", "cube", box((cx, cy, 0.003), (hx, hy, 0.002)), letter_mat, part="needle"))
    return shapes


def _tracked_points_part(length_m: float) -> np.ndarray:
    """Points on the needle in its part frame, (M, 3): rod middle, rod tip, S corners, S centre."""
    y0 = length_m + S_GAP_M
    hw = S_WIDTH_M / 2
    z = 0.005
    return np.array(
        [
            [0.0, length_m / 2, z],
            [0.0, length_m, z],
            [-hw, y0, z],
            [hw, y0, z],
            [-hw, y0 + S_HEIGHT_M, z],
            [hw, y0 + S_HEIGHT_M, z],
            [0.0, y0 + S_HEIGHT_M / 2, z],
        ]
    )


def _static_shapes(p: Params) -> list[Shape]:
    amb = AMBIENT_RADIANCE * p.ambient_scale
    lamp = LAMP_RADIANCE * p.lamp_scale
    flash = FLASH_RADIANCE * p.flash_scale
    rot_x = rotate((1, 0, 0), -math.pi / 2)  # canonical +z normal -> +y
    body = Material((0.32, 0.16, 0.07))
    shapes = [
        # Table top (0.9 x 0.7 m) and back wall.
        Shape("table", "rectangle", translate(0, 0, 0.2) @ rot_x @ scale(0.9, 0.6, 1), Material((0.55, 0.40, 0.25))),
        Shape("wall", "rectangle", translate(0, 0.4, WALL_Z_M) @ scale(1.2, 0.6, 1), Material((0.62, 0.64, 0.66))),
        # Metronome body: a stepped wedge of three boxes, and a dark front plate behind the needle.
        Shape("body_base", "cube", box((0, 0.02, 0), (0.07, 0.02, BODY_DEPTH_M / 2)), body),
        Shape("body_mid", "cube", box((0, 0.09, -0.005), (0.055, 0.05, BODY_DEPTH_M / 2 - 0.005)), body),
        Shape("body_top", "cube", box((0, 0.165, -0.01), (0.035, 0.025, BODY_DEPTH_M / 2 - 0.01)), body),
        Shape(
            "body_plate",
            "rectangle",
            translate(0, 0.1, BODY_DEPTH_M / 2 + 0.001) @ scale(0.03, 0.07, 1),
            Material((0.04, 0.035, 0.03)),
        ),
        # Still life: red ball, blue can (with lid), green block, near-black ball, white cube.
        Shape("ball_red", "sphere", translate(0.2, 0.055, 0.08) @ scale(0.055), Material((0.65, 0.08, 0.06))),
        Shape(
            "can_blue",
            "cylinder",
            translate(-0.2, 0, 0.02) @ rotate((1, 0, 0), -math.pi / 2) @ scale(0.04, 0.04, 0.12),
            Material((0.08, 0.15, 0.55)),
        ),
        Shape("can_lid", "disk", translate(-0.2, 0.12, 0.02) @ rot_x @ scale(0.04), Material((0.08, 0.15, 0.55))),
        Shape(
            "block_green",
            "cube",
            translate(-0.09, 0.03, 0.14) @ rotate((0, 1, 0), 0.5) @ scale(0.03, 0.03, 0.03),
            Material((0.12, 0.45, 0.12)),
        ),
        Shape("ball_black", "sphere", translate(0.1, 0.025, 0.17) @ scale(0.025), Material((0.02, 0.02, 0.02))),
        Shape("cube_white", "cube", translate(-0.32, 0.035, -0.15) @ scale(0.035), Material((0.85, 0.85, 0.85))),
        # Lamp: a thin stand and a small spherical bulb, in view at the right.
        Shape(
            "lamp_stand",
            "cylinder",
            translate(LAMP_X_M, 0, LAMP_Z_M)
            @ rotate((1, 0, 0), -math.pi / 2)
            @ scale(STAND_RADIUS_M, STAND_RADIUS_M, STAND_TOP_M),
            Material((0.1, 0.1, 0.1)),
        ),
        Shape(
            "lamp_bulb",
            "sphere",
            translate(LAMP_X_M, BULB_Y_M, LAMP_Z_M) @ scale(BULB_RADIUS_M),
            None,
            Light("lamp", (lamp, lamp * 0.92, lamp * 0.8)),
        ),
        # Ambient: a 0.8 x 0.6 m soft box above and in front of the scene, aimed at it.
        Shape(
            "ambient_softbox",
            "rectangle",
            frame_towards((0.1, 0.9, 0.6), (0.0, 0.05, 0.0)) @ scale(0.4, 0.3, 1),
            None,
            Light("ambient", (amb, amb, amb * 0.95)),
        ),
    ]
    # Flash LED: 1 x 1 cm, beside the lens, aimed at the metronome.
    cam = _camera(p)
    fwd = np.subtract(cam.target, cam.origin)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    led = np.asarray(cam.origin) + FLASH_OFFSET_M[0] * right
    shapes.append(
        Shape(
            "flash_led",
            "rectangle",
            frame_towards(led, cam.target) @ scale(0.005, 0.005, 1),
            None,
            Light("flash", (flash, flash, flash)),
        )
    )
    return shapes


def _camera(p: Params) -> Camera:
    return Camera(origin=CAMERA_ORIGIN, target=CAMERA_TARGET, up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)


def make(params: Params) -> SceneModel:
    """The metronome scene for ``params``."""
    pendulum = Pendulum.from_tempo(
        params.tempo_bpm,
        params.amplitude_deg,
        model=params.motion_model,
        phase_s=params.phase_s,
        damping_per_s=params.damping_per_s,
    )
    pivot = translate(0.0, 0.03, NEEDLE_Z_M)

    def needle_to_world(t_s: float) -> np.ndarray:
        """World-from-needle matrix (4, 4) at scene time ``t_s`` (s)."""
        return pivot @ rotate((0, 0, 1), float(pendulum.angle_rad(t_s)))

    local = _tracked_points_part(params.needle_length_m)

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of needle and S points, m."""
        theta = np.atleast_1d(pendulum.angle_rad(np.asarray(times_s, float)))
        c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
        x = c * local[None, :, 0] - s * local[None, :, 1]
        y = s * local[None, :, 0] + c * local[None, :, 1]
        z = np.broadcast_to(local[None, :, 2], x.shape)
        return np.stack([x, y, z], axis=-1) + pivot[:3, 3]

    build = SceneBuild(
        shapes=tuple(_static_shapes(params) + _needle_shapes(params.needle_length_m)),
        parts={"needle": needle_to_world},
        guides=(STAND_GUIDE, WALL_SPOT_GUIDE, TABLE_SPOT_GUIDE),
    )
    return SceneModel(
        name="metronome",
        groups=("ambient", "lamp", "flash"),
        switchable=frozenset({"flash"}),
        camera=_camera(params),
        build=build,
        params=params,
        motion_points=motion_points,
        default_film=(640, 512),
        # letter_s_points: indices of motion_points on the letter S (corners, centre; see _tracked_points_part)
        extra={"pendulum": pendulum, "letter_s_points": (2, 3, 4, 5, 6)},
    )
