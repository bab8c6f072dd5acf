"""A ball rolling across a grey floor under a soft light: the smallest moving scene (docs/scenes.md)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.render.build import Light, Material, SceneBuild, Shape, frame_towards, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "a red ball rolling across a grey floor, lit by one soft light (group 'lamp')"


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")  # an unknown scene.* key is refused with its name

    speed_m_per_s: float = Field(1.0, ge=0.0, description="the ball's speed along the image's x axis, m/s")
    radius_m: float = Field(0.05, gt=0.0, le=0.2, description="the ball's radius, m")
    lamp_radiance: float = Field(20.0, ge=0.0, description="radiance of the soft light, W m^-2 sr^-1")


def make(params: Params) -> SceneModel:
    r, v = params.radius_m, params.speed_m_per_s

    def ball_to_world(t_s: float) -> np.ndarray:  # the moving part's pose at scene time t_s, (4, 4)
        return translate(v * t_s - 0.1, r, 0.0) @ scale(r)

    shapes = (
        Shape(
            "floor",
            "rectangle",
            frame_towards((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), up=(0.0, 0.0, -1.0)) @ scale(1.0),
            Material((0.5, 0.5, 0.5)),
        ),
        Shape("ball_surface", "sphere", np.eye(4), Material((0.7, 0.1, 0.1)), part="ball"),
        Shape(
            "light",
            "rectangle",
            frame_towards((0.0, 1.0, 0.3), (0.0, 0.0, 0.0)) @ scale(0.3),
            None,
            Light("lamp", (params.lamp_radiance,) * 3),
        ),
    )

    def motion_points(times_s: np.ndarray) -> np.ndarray:  # (T, M, 3): points on the moving part, world m
        centre = np.stack(
            [v * np.asarray(times_s, float) - 0.1, np.full(np.shape(times_s), r), np.zeros(np.shape(times_s))], axis=-1
        )
        offsets = np.array([[0, 0, 0], [r, 0, 0], [-r, 0, 0], [0, r, 0], [0, -r, 0]], float)
        return centre[:, None, :] + offsets[None]

    return SceneModel(
        name="rolling_ball",
        groups=("lamp",),
        switchable=frozenset(),
        camera=Camera(origin=(0.0, 0.4, 0.8), target=(0.0, 0.05, 0.0), up=(0.0, 1.0, 0.0), fov_deg=40.0),
        build=SceneBuild(shapes=shapes, parts={"ball": ball_to_world}),
        params=params,
        motion_points=motion_points if v > 0 else None,
    )
