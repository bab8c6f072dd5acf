"""Still life lit by a moving lamp (its shadows sweep) and a flickering ambient light.

A table top against a back wall carries a white pillar, a red ball, a blue vase, a green
cube and a near-black ball. A small spherical lamp (group ``lamp``, steady: a DC-driven LED)
travels along a horizontal arc to the left of them, just outside the view, so the long
shadows they cast across the table swing during the capture. A large soft box overhead
(group ``ambient``, always on) is a fluorescent tube on AC mains: its power follows
sin^2 of the mains voltage, so it flickers at twice the mains frequency (100 or 120 Hz); the
drive is integrated exactly into the render weights (:class:`mbcapture.timing.drive.Drive`).

Coordinates (m): y up, the table top is y = 0, the wall is the plane z = WALL_Z_M, the camera
looks along -z. The lamp is at height ``lamp_height_m`` on a circle of radius ``arc_radius_m``
about the vertical axis through the origin; its angle, measured from +z (towards the camera)
towards +x (image right), is ``lamp_start_deg + lamp_speed_deg_per_s * t``.

Motion points (what the planner bounds): the lamp's centre and the shadow of every
silhouette point of the occluders, i.e. the points where the rays from the lamp's centre
through them meet the table (or the wall, where the table ends), so the render strata follow
the shadows' image motion, the fastest thing in the image. ``extra["shadow_polygons"](times)``
gives, per occluder, those shadow points plus its footprint: the convex hull of each is the
(umbra of the) occluder's shadow, used by the application for the shadow-sweep region.

Radiance at the default factors: lamp-lit white surfaces ~2-3 W m^-2 sr^-1, ambient-lit
surfaces in shadow ~0.05-0.15, the near-black ball in shadow ~0.003: about 1000:1 in view.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mbcapture.timing.drive import Drive
from mbcapture.render.build import Light, Material, SceneBuild, Shape, box, frame_towards, rotate, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = (
    "still life, lamp moving along an arc (sweeping shadows), ambient flickering at 2x mains (groups ambient, lamp)"
)

LAMP_RADIANCE = 4000.0  # W m^-2 sr^-1 of the bulb's surface, at lamp_scale 1 (warm white)
LAMP_COLOUR = (1.0, 0.9, 0.75)
LAMP_BULB_RADIUS_M = 0.015
AMBIENT_RADIANCE = 1.2  # time-averaged, at ambient_scale 1 (cool white)
AMBIENT_COLOUR = (0.92, 0.97, 1.0)
WALL_Z_M = -0.45
TABLE_FRONT_Z_M = 0.55
TABLE_HALF_WIDTH_M = 0.9
CAMERA_ORIGIN = (0.0, 0.34, 1.05)
CAMERA_TARGET = (0.0, 0.06, -0.05)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    lamp_height_m: float = Field(
        0.32, gt=0.25, le=1.0, description="height of the lamp's centre above the table, m (above every object)"
    )
    arc_radius_m: float = Field(
        0.55,
        gt=0.05,
        le=1.0,
        description="radius of the lamp's horizontal arc about the vertical axis through the still life, m",
    )
    lamp_start_deg: float = Field(
        -110.0,
        ge=-180.0,
        le=180.0,
        description="lamp's angle on the arc at scene time 0, degrees from +z (camera side) towards +x",
    )
    lamp_speed_deg_per_s: float = Field(
        60.0,
        ge=-3600.0,
        le=3600.0,
        description="angular speed of the lamp along the arc, degrees per second (0: still)",
    )
    lamp_scale: float = Field(1.0, ge=0.0, description="lamp radiance factor, 1")
    ambient_scale: float = Field(1.0, ge=0.0, description="ambient light radiance factor (time average), 1")
    mains_hz: float = Field(
        50.0,
        gt=0.0,
        le=1000.0,
        description="AC mains frequency of the ambient light, Hz (50 or 60); it flickers at twice this",
    )
    flicker_depth: float = Field(
        1.0,
        ge=0.0,
        le=1.0,
        description="ambient drive 1 - depth cos(2 pi 2 mains_hz t + phase): 1 = |sin|^2 (full), 0 = steady",
    )
    flicker_phase_deg: float = Field(
        0.0, description="phase of the ambient flicker at scene time 0, degrees of the flicker cycle"
    )
    fov_deg: float = Field(40.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees")

    @model_validator(mode="after")
    def _lamp_above_objects(self) -> "Params":
        top = max(o.top_m for o in OCCLUDERS)
        if self.lamp_height_m <= top + 0.05:
            raise ValueError(f"lamp_height_m must exceed the tallest object ({top} m) by 0.05 m")
        return self


class Occluder:
    """A convex object on the table: its Mitsuba shapes and silhouette sample points (world)."""

    def __init__(self, name: str, shapes: list[Shape], points: np.ndarray):
        self.name = name
        self.shapes = shapes
        self.points = np.asarray(points, float)
        self.top_m = float(self.points[:, 1].max())


def _box_occluder(name, center, half, colour) -> Occluder:
    c, h = np.asarray(center), np.asarray(half)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h + c
    return Occluder(name, [Shape(name, "cube", box(center, half), Material(colour))], corners)


def _ball_occluder(name, center, radius, colour, n=48) -> Occluder:
    # Fibonacci sphere: silhouette points in every direction the lamp can see it from
    i = np.arange(n) + 0.5
    y = 1 - 2 * i / n
    r = np.sqrt(1 - y * y)
    phi = math.pi * (3 - math.sqrt(5)) * i
    pts = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1) * radius + np.asarray(center)
    return Occluder(name, [Shape(name, "sphere", translate(*center) @ scale(radius), Material(colour))], pts)


def _vase_occluder(name, base, radius, height, colour, n=24) -> Occluder:
    a = 2 * math.pi * np.arange(n) / n
    rim = np.stack([radius * np.cos(a), np.zeros(n), radius * np.sin(a)], axis=1)
    pts = np.concatenate([rim, rim + [0, height, 0]]) + np.asarray(base)
    rot_x = rotate((1, 0, 0), -math.pi / 2)  # canonical +z axis -> +y
    shapes = [
        Shape(name, "cylinder", translate(*base) @ rot_x @ scale(radius, radius, height), Material(colour)),
        Shape(
            f"{name}_lid",
            "disk",
            translate(base[0], base[1] + height, base[2]) @ rot_x @ scale(radius),
            Material(colour),
        ),
    ]
    return Occluder(name, shapes, pts)


OCCLUDERS: tuple[Occluder, ...] = (
    _box_occluder("pillar_white", (-0.1, 0.09, 0.02), (0.025, 0.09, 0.025), (0.8, 0.8, 0.78)),
    _ball_occluder("ball_red", (0.1, 0.05, 0.08), 0.05, (0.65, 0.08, 0.06)),
    _vase_occluder("vase_blue", (0.03, 0.0, -0.14), 0.035, 0.15, (0.08, 0.15, 0.55)),
    _box_occluder("cube_green", (0.24, 0.03, -0.08), (0.03, 0.03, 0.03), (0.12, 0.45, 0.12)),
    _ball_occluder("ball_black", (-0.24, 0.025, 0.12), 0.025, (0.03, 0.03, 0.03)),
)


def lamp_position(p: Params, times_s) -> np.ndarray:
    """(T, 3) world position of the lamp's centre at scene times ``times_s`` (s)."""
    t = np.atleast_1d(np.asarray(times_s, float))
    ang = np.radians(p.lamp_start_deg + p.lamp_speed_deg_per_s * t)
    return np.stack(
        [p.arc_radius_m * np.sin(ang), np.full_like(ang, p.lamp_height_m), p.arc_radius_m * np.cos(ang)], -1
    )


def cast_shadow(lamp: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Where the rays from ``lamp`` (T, 3) through ``points`` (P, 3) meet the table (y = 0) or,
    beyond its back edge, the wall (z = WALL_Z_M): (T, P, 3). Points below the lamp only."""
    L = lamp[:, None, :]
    d = points[None, :, :] - L
    s_table = L + d * (L[..., 1:2] / -d[..., 1:2])
    on_wall = s_table[..., 2] < WALL_Z_M
    with np.errstate(divide="ignore", invalid="ignore"):
        s_wall = L + d * ((WALL_Z_M - L[..., 2:3]) / d[..., 2:3])
    s = np.where(on_wall[..., None], s_wall, s_table)
    # beyond the table's front and side edges the shadow leaves the view (it falls to the floor):
    # hold it at the edge, where it stops moving in the image
    s[..., 0] = np.clip(s[..., 0], -TABLE_HALF_WIDTH_M, TABLE_HALF_WIDTH_M)
    s[..., 2] = np.minimum(s[..., 2], TABLE_FRONT_Z_M)
    return s


def _camera(p: Params) -> Camera:
    return Camera(origin=CAMERA_ORIGIN, target=CAMERA_TARGET, up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)


def make(params: Params) -> SceneModel:
    rot_x = rotate((1, 0, 0), -math.pi / 2)
    amb = AMBIENT_RADIANCE * params.ambient_scale
    lamp = LAMP_RADIANCE * params.lamp_scale
    shapes = [
        Shape(
            "table",
            "rectangle",
            translate(0, 0, (WALL_Z_M + TABLE_FRONT_Z_M) / 2)
            @ rot_x
            @ scale(TABLE_HALF_WIDTH_M, (TABLE_FRONT_Z_M - WALL_Z_M) / 2, 1),
            Material((0.55, 0.42, 0.28)),
        ),
        Shape("wall", "rectangle", translate(0, 0.5, WALL_Z_M) @ scale(1.2, 0.5, 1), Material((0.7, 0.7, 0.68))),
        Shape(
            "ambient_softbox",
            "rectangle",
            frame_towards((-0.1, 1.0, 0.7), (0.0, 0.0, -0.05)) @ scale(0.45, 0.3, 1),
            None,
            Light("ambient", tuple(amb * c for c in AMBIENT_COLOUR)),
        ),
        Shape(
            "lamp_bulb",
            "sphere",
            scale(LAMP_BULB_RADIUS_M),
            None,
            Light("lamp", tuple(lamp * c for c in LAMP_COLOUR)),
            part="lamp",
        ),
    ]
    for o in OCCLUDERS:
        shapes.extend(o.shapes)

    def lamp_to_world(t_s: float) -> np.ndarray:
        return translate(*lamp_position(params, t_s)[0])

    lit_points = np.concatenate([o.points[o.points[:, 1] > 1e-6] for o in OCCLUDERS])

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """(T, M, 3): the lamp's centre and the shadows of every occluder's silhouette points."""
        L = lamp_position(params, times_s)
        return np.concatenate([L[:, None, :], cast_shadow(L, lit_points)], axis=1)

    def shadow_polygons(times_s: np.ndarray) -> list[np.ndarray]:
        """Per occluder (T, P, 3): its shadow points and its footprint points (y = 0, static)."""
        L = lamp_position(params, times_s)
        return [cast_shadow(L, o.points) for o in OCCLUDERS]

    moving = params.lamp_speed_deg_per_s != 0.0
    flicker = Drive.mains_flicker(params.mains_hz, params.flicker_depth, math.radians(params.flicker_phase_deg))
    return SceneModel(
        name="moving_light",
        groups=("ambient", "lamp"),
        switchable=frozenset(),
        camera=_camera(params),
        build=SceneBuild(shapes=tuple(shapes), parts={"lamp": lamp_to_world}),
        params=params,
        motion_points=motion_points if moving else None,
        default_film=(640, 512),
        extra={
            "shadow_polygons": shadow_polygons,
            "occluders": tuple(o.name for o in OCCLUDERS),
            "lamp_position": lambda t: lamp_position(params, t),
        },
        drives={"ambient": flicker},
    )
