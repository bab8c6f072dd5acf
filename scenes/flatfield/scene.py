"""Flat field: a uniform radiance fills every pixel exactly (sensor calibration, photon transfer).

The camera sits inside a constant environment light and there is no geometry, so every camera
ray escapes and returns ``radiance`` exactly, at any sample count.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from mbcapture.render.build import Environment, SceneBuild
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "uniform radiance over the whole image (static; group 'field')"


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    radiance: list[float] = Field(
        default=[1.0, 1.0, 1.0],
        description="radiance of the field per channel R, G, B, W m^-2 sr^-1 (>= 0)",
    )
    fov_deg: float = Field(
        default=40.0, gt=0.0, lt=170.0, description="horizontal field of view of the camera, degrees"
    )

    @field_validator("radiance")
    @classmethod
    def _three_non_negative(cls, v: list[float]) -> list[float]:
        if len(v) != 3 or any(x < 0 for x in v):
            raise ValueError("expected 3 non-negative values (R, G, B)")
        return v


def make(params: Params) -> SceneModel:
    """The flat-field scene for ``params``."""
    rad = tuple(float(x) for x in params.radiance)
    return SceneModel(
        name="flatfield",
        groups=("field",),
        switchable=frozenset(),
        camera=Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=params.fov_deg),
        build=SceneBuild(shapes=(), environment=Environment("field", rad)),
        params=params,
        motion_points=None,
        extra={"radiance": rad},
    )
