"""A room corner for indirect time of flight: multipath, a moving box across a depth edge, a bright window.

Coordinates (m): y up; the camera stands 1.2 m above the floor and looks along -z into the corner where two
walls meet at a right angle, ``corner_distance_m`` ahead (the walls make a V, each at 45 degrees to the view).
Light that bounces from one wall to the other before it returns travels farther than the direct path, so
near the corner the measured depth is too far (multipath interference), most where the walls see each other
best.

A box (``box_size_m`` on a side) on a thin post moves across the view at ``box_speed_m_s``, ``box_distance_m``
from the camera: its edges against the walls behind it are depth edges, where the taps of a sequential
capture see different surfaces (motion artefacts) and a pixel straddling the edge mixes two phases
(flying pixels).

Emitter groups (output order):

``ambient``      a window in the left wall (a bright emitting pane, seen by the camera and lighting the room;
                 ``ambient_scale``): light the illuminator's modulation does not carry (always on)
``illuminator``  the time-of-flight illuminator: a 2 x 2 cm emitter at the camera's centre aimed where it looks
                 (switchable: the tof_* protocols modulate it)

``layout: plane`` replaces the room by one wall perpendicular to the view ``plane_distance_m`` away and
nothing else (no window): the check that a plane at a known distance reconstructs at that distance.

``SceneModel.extra['corner']``: (a point on the corner's line, its direction), for the multipath region.
The walls are Lambertian (``wall_albedo``): what an iToF camera sees at 850 nm is grey.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.render.build import Light, Material, SceneBuild, Shape, box, frame_towards, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel
from mbcapture.timing.drive import Drive

DESCRIPTION = (
    "room corner with a moving box and a window, a ToF illuminator at the camera (groups ambient, illuminator)"
)

CAMERA_HEIGHT_M = 1.2
WALL_HEIGHT_M = 2.6
LED_HALF_M = 0.01


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    layout: Literal["room", "plane"] = Field("room", description="room: the corner, box and window; plane: one wall")
    corner_distance_m: float = Field(3.0, gt=0.5, le=20.0, description="camera to the corner's line, m")
    plane_distance_m: float = Field(1.0, gt=0.05, le=50.0, description="layout plane: camera to the wall, m")
    wall_albedo: float = Field(
        0.6, gt=0.0, le=1.0, description="the walls' and floor's reflectance at the illuminator's wavelength"
    )
    box_distance_m: float = Field(1.6, gt=0.3, le=10.0, description="camera to the box's front face, m")
    box_size_m: float = Field(0.35, gt=0.01, le=2.0, description="the box's side, m")
    box_speed_m_s: float = Field(
        1.5, ge=0.0, le=50.0, description="the box's speed across the view (+x), m/s; 0: still"
    )
    box_start_x_m: float = Field(-0.25, description="the box's centre at scene time 0, m from the view's axis")
    illuminator_radiance: float = Field(
        3.0e5, gt=0.0, description="the ToF illuminator's mean radiance, W m^-2 sr^-1 (2 x 2 cm at the camera)"
    )
    ambient_scale: float = Field(
        1.0,
        ge=0.0,
        description="the window's radiance factor (1: 40 W m^-2 sr^-1, an overcast sky's near infrared); applied "
        "as a gain on its rendered light, so every level shares the renders",
    )
    fov_deg: float = Field(60.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees")


WINDOW_RADIANCE = 40.0


def _camera(p: Params) -> Camera:
    if p.layout == "plane":
        return Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)
    return Camera(
        origin=(0.0, CAMERA_HEIGHT_M, 0.0),
        target=(0.0, CAMERA_HEIGHT_M - 0.25, -p.corner_distance_m),
        up=(0.0, 1.0, 0.0),
        fov_deg=p.fov_deg,
    )


def _illuminator(p: Params, cam: Camera) -> Shape:
    return Shape(
        "tof_led",
        "rectangle",
        frame_towards(cam.origin, cam.target) @ scale(LED_HALF_M, LED_HALF_M, 1),
        None,
        Light("illuminator", (p.illuminator_radiance,) * 3),
    )


def _wall(name: str, corner: np.ndarray, along: np.ndarray, length: float, p: Params) -> Shape:
    """A wall from the corner's line ``length`` m along ``along`` (horizontal unit), facing the camera."""
    centre = corner + along * length / 2 + np.array([0.0, WALL_HEIGHT_M / 2, 0.0])
    normal = np.array([-along[2], 0.0, along[0]])  # horizontal, perpendicular to the wall; turned to the camera
    normal *= np.sign(normal @ (np.array([0.0, CAMERA_HEIGHT_M, 0.0]) - centre))
    m = frame_towards(centre, centre + normal) @ scale(length / 2, WALL_HEIGHT_M / 2, 1)
    return Shape(name, "rectangle", m, Material((p.wall_albedo,) * 3))


def _room(p: Params) -> tuple[list[Shape], dict]:
    corner = np.array([0.0, 0.0, -p.corner_distance_m])
    left, right = np.array([-1.0, 0.0, 1.0]) / math.sqrt(2), np.array([1.0, 0.0, 1.0]) / math.sqrt(2)
    length = p.corner_distance_m * math.sqrt(2) + 1.0
    grey = Material((p.wall_albedo,) * 3)
    shapes = [
        _wall("left_wall", corner, left, length, p),
        _wall("right_wall", corner, right, length, p),
        Shape(
            "floor",
            "rectangle",
            translate(0.0, 0.0, -p.corner_distance_m / 2)
            @ frame_towards((0, 0, 0), (0, 1, 0), up=(0, 0, -1))
            @ scale(p.corner_distance_m + 1.0, p.corner_distance_m / 2 + 0.5, 1),
            grey,
        ),
    ]
    # a window pane in the left wall, 1 cm in front of it: 0.9 m wide, 1.2 m high, its centre 1.4 m up
    along = 0.45 * p.corner_distance_m * math.sqrt(2)
    centre = corner + left * along + np.array([0.0, 1.4, 0.0]) + np.array([1.0, 0.0, 1.0]) / math.sqrt(2) * 0.01
    pane = frame_towards(centre, centre + np.array([1.0, 0.0, 1.0])) @ scale(0.45, 0.6, 1)
    shapes.append(Shape("window", "rectangle", pane, None, Light("ambient", (WINDOW_RADIANCE,) * 3)))
    return shapes, {"corner": (tuple(corner), (0.0, 1.0, 0.0))}


def make(params: Params) -> SceneModel:
    """The time-of-flight room (or plane) for ``params``."""
    cam = _camera(params)
    if params.layout == "plane":
        d = params.plane_distance_m
        half = d * math.tan(math.radians(params.fov_deg)) + 1.0
        wall = Shape(
            "plane", "rectangle", translate(0.0, 0.0, -d) @ scale(half, half, 1), Material((params.wall_albedo,) * 3)
        )
        return SceneModel(
            name="tof_room",
            groups=("ambient", "illuminator"),
            switchable=frozenset({"illuminator"}),
            camera=cam,
            build=SceneBuild(shapes=(wall, _illuminator(params, cam))),
            params=params,
            default_film=(320, 240),
        )
    shapes, extra = _room(params)
    s = params.box_size_m
    z = -params.box_distance_m - s / 2
    y = CAMERA_HEIGHT_M - 0.25 * params.box_distance_m / params.corner_distance_m  # on the view's axis
    v = params.box_speed_m_s

    def box_pose(t_s: float) -> np.ndarray:
        """World-from-box matrix at scene time ``t_s``: the box slides along +x."""
        return translate(params.box_start_x_m + v * float(t_s), y, z)

    shapes += [
        Shape("box_body", "cube", box((0.0, 0.0, 0.0), (s / 2, s / 2, s / 2)), Material((0.7, 0.7, 0.7)), part="box"),
        Shape(
            "post",
            "cube",
            box((0.0, -(y + s / 2) / 2, 0.0), (0.02, (y - s / 2) / 2, 0.02)),
            Material((0.3,) * 3),
            part="box",
        ),
    ]
    corners = np.array([[x, yy, zz] for x in (-s / 2, s / 2) for yy in (-s / 2, s / 2) for zz in (-s / 2, s / 2)])

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the box's corners, m."""
        t = np.atleast_1d(np.asarray(times_s, float))
        centre = np.stack([params.box_start_x_m + v * t, np.full_like(t, y), np.full_like(t, z)], axis=-1)
        return centre[:, None, :] + corners[None]

    return SceneModel(
        name="tof_room",
        groups=("ambient", "illuminator"),
        switchable=frozenset({"illuminator"}),
        camera=cam,
        build=SceneBuild(shapes=tuple(shapes + [_illuminator(params, cam)]), parts={"box": box_pose}),
        params=params,
        motion_points=None if v == 0.0 else motion_points,
        default_film=(320, 240),
        extra=extra,
        # the window's level as a constant drive (a gain on its rendered light): every level shares the renders
        drives={"ambient": Drive(c0=params.ambient_scale)} if params.ambient_scale != 1.0 else {},
    )
