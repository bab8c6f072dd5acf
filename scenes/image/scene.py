"""A photograph as the scene: an HDR image (OpenEXR, Radiance .hdr) or a PNG/JPEG (linearised from sRGB) on a
plane that fills the view and emits the image's radiance, moving by a 2D trajectory (translation, rotation,
zoom), so HDR data sets reach the sensor model with motion and buckets.

The plane is an area light whose radiance is the image (W m^-2 sr^-1 per channel, linear RGB): a pinhole
camera sees each pixel's radiance as the box average of the image over it (bilinear between texels).
``radiance_scale`` multiplies the file's values, or ``target_luminance_cd_m2`` sets the image's mean
luminance (683 lm/W times the Rec. 709 luma of the linear RGB). The image's aspect ratio is kept and its
width spans ``overscan`` times the view's, so a moving image does not uncover its edges at once; a film
taller than the image (render.width / render.height below the image's aspect) shows black bands.

Group ``image`` (always on). RGB render variants only.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mbcapture.errors import ConfigError
from mbcapture.render.build import Light, RadianceImage, SceneBuild, Shape, read_texture, scale
from mbcapture.scene.keyframes import rotation, translation
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "a photograph (EXR, .hdr, PNG/JPEG) on a plane filling the view, moving in 2D (group 'image')"

#: lm/W: luminance of linear-sRGB radiance is 683 times its Rec. 709 luma.
LUMINOUS_EFFICACY = 683.0
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    file: str = Field("", description="the image: .exr, .hdr (linear) or .png/.jpg (sRGB); relative to the config")
    radiance_scale: float = Field(1.0, gt=0, description="radiance per unit of the file's linear values, W m^-2 sr^-1")
    target_luminance_cd_m2: float | None = Field(
        None, gt=0, description="the image's mean luminance, cd/m^2, instead of radiance_scale (null: not used)"
    )
    fov_deg: float = Field(40.0, gt=0, lt=170, description="horizontal field of view of the camera, degrees")
    distance_m: float = Field(1.0, gt=0, description="distance from the camera to the plane, m")
    overscan: float = Field(1.2, ge=1.0, le=4.0, description="the image's width over the view's at the plane")
    velocity: tuple[float, float] = Field(
        (0.0, 0.0), description="the image's motion, view widths per second, (right, up)"
    )
    rotation_deg_s: float = Field(0.0, description="the image's rotation about the view's centre, degrees/s")
    zoom_per_s: float = Field(0.0, description="the image's growth rate: its scale is exp(zoom_per_s t)")

    @model_validator(mode="after")
    def _one_scale(self) -> "Params":
        if self.target_luminance_cd_m2 is not None and self.radiance_scale != 1.0:
            raise ValueError("give radiance_scale or target_luminance_cd_m2, not both")
        return self


def load_linear(path: Path) -> np.ndarray:
    """(H, W, 3) linear RGB of an image file: EXR and Radiance .hdr as stored, PNG/JPEG decoded from sRGB."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".hdr":
            import cv2

            img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
            if img is None:
                raise ValueError("corrupt or unreadable Radiance HDR file")
            arr = img[..., ::-1].astype(np.float32)
        else:
            arr = read_texture(path)
            if suffix != ".exr":  # 8- or 16-bit sRGB-encoded values in 0..1
                arr = np.where(arr <= 0.04045, arr / 12.92, ((arr + 0.055) / 1.055) ** 2.4)
    except ValueError as exc:
        raise ConfigError(f"scene.file: {path}: {exc}") from None
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return np.ascontiguousarray(np.maximum(arr[..., :3], 0.0), dtype=np.float32)


def make(params: Params) -> SceneModel:
    """The image scene of ``params``."""
    if not params.file:
        raise ConfigError("scene.file: the image scene needs an image file (.exr, .hdr, .png, .jpg)")
    path = Path(params.file).resolve()
    if path.suffix.lower() not in (".exr", ".hdr", ".png", ".jpg", ".jpeg"):
        raise ConfigError(f"scene.file: {path}: expected .exr, .hdr, .png or .jpg")
    linear = load_linear(path)
    mean_luminance = float(LUMINOUS_EFFICACY * (linear.reshape(-1, 3) @ REC709_LUMA).mean())
    if params.target_luminance_cd_m2 is not None:
        if not mean_luminance > 0:
            raise ConfigError(f"scene.target_luminance_cd_m2: {path} is black; nothing to scale")
        k = params.target_luminance_cd_m2 / mean_luminance
    else:
        k = params.radiance_scale
    h, w = linear.shape[:2]
    half_width = params.overscan * params.distance_m * math.tan(math.radians(params.fov_deg) / 2)
    half_height = half_width * h / w
    view_width = 2 * half_width / params.overscan
    at_rest = translation((0.0, 0.0, -params.distance_m)) @ scale(half_width, half_height, 1.0)
    centre = (0.0, 0.0, -params.distance_m)

    def motion(t_s: float) -> np.ndarray:
        shift = translation(tuple(view_width * t_s * np.array([params.velocity[0], params.velocity[1], 0.0])))
        turn = rotation((0.0, 0.0, 1.0), params.rotation_deg_s * t_s, centre)
        grow = math.exp(params.zoom_per_s * t_s)
        zoom = translation(centre) @ scale(grow, grow, 1.0) @ translation(tuple(-np.asarray(centre)))
        return shift @ turn @ zoom

    moving = any(params.velocity) or params.rotation_deg_s or params.zoom_per_s
    # points of the image within the view, for the planner: a 5 x 5 grid over the view's width
    u = np.linspace(-0.5, 0.5, 5) * view_width
    grid = np.array([[x, y, -params.distance_m, 1.0] for x in u for y in u * h / w])

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        return np.asarray([(motion(float(t)) @ grid.T).T[:, :3] for t in np.atleast_1d(times_s)])

    return SceneModel(
        name="image",
        groups=("image",),
        switchable=frozenset(),
        camera=Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=params.fov_deg),
        build=SceneBuild(
            shapes=(
                Shape(
                    "image_plane", "rectangle", at_rest, light=Light("image", RadianceImage(k * linear)), part="image"
                ),
            ),
            parts={"image": motion},
        ),
        params=params,
        motion_points=motion_points if moving else None,
        extra={"radiance_scale": k, "mean_luminance_cd_m2": mean_luminance * k},
    )
