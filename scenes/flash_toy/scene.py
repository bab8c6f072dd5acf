"""A potted toy plant with waving leaves in front of a distant, cluttered background (flash matting).

The paper's figure 16: a toy plant whose leaves wave up and down while a flash beside the lens
lights the near foreground much more than the distant background (the flash's irradiance falls
off as 1/d^2: at the default 1 m to the plant and 3 m to the back wall the background gets
1/9 of the plant's flash irradiance, the ambient light lights both about equally).

Coordinates (m): y up, the camera looks along -z at the plant, whose pot stands at the origin.
The pot reaches below the bottom of the image, so every foreground pixel is toy, never table.
Each leaf is a thin elliptical disk (two-sided) on its own moving part: it turns in the image
plane about its attachment point on the stem, angle(t) = base + A_i sin(2 pi f_i t + phi_i),
with its own amplitude, frequency and phase (so the leaves never move in step).

The background (a wall ``background_distance_m`` behind the plant, coloured posters on it,
boxes of different colours and sizes in front of it, a floor strip) is static.

Emitter groups (output order):

``ambient``  two large, soft panels outside the view: one above the plant, one lighting the
             background (always on)
``flash``    a 1 x 1 cm LED 4 cm beside the lens, aimed at the plant (switchable)

``SceneModel.extra['foreground']`` names the foreground shapes (pot, soil, stem, bud, leaves):
the matte's ground truth is their coverage (:mod:`mbcapture.render.coverage`).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.render.build import (
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

DESCRIPTION = "potted toy plant with waving leaves before a distant cluttered wall (groups ambient, flash)"

# Radiance of each light at scale factor 1, W m^-2 sr^-1.
AMBIENT_RADIANCE = 3.0
FLASH_RADIANCE = 4.0e4

CAMERA_ORIGIN = (0.0, 0.15, 1.0)
CAMERA_TARGET = (0.0, 0.15, 0.0)
FLASH_OFFSET_M = 0.04  # LED to the right of the lens, m

STEM_TOP_M = 0.30
LEAF_LENGTH_M = 0.085  # pivot to tip
LEAF_HALF_WIDTH_M = 0.016
LEAF_Z_M = 0.01  # leaves sit just in front of the stem
LEAF_TILT_RAD = 0.35  # each leaf's blade turned about its own axis (shading under the flash)
# (attachment height on the stem (m), side +1 right / -1 left as seen from the camera)
LEAF_ATTACH = [(0.10, 1), (0.13, -1), (0.17, 1), (0.20, -1), (0.24, 1), (0.27, -1), (0.29, 1), (0.115, -1)]
LEAF_COLOURS = [(0.10, 0.42, 0.08), (0.16, 0.50, 0.10), (0.08, 0.36, 0.12), (0.20, 0.55, 0.12)]


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    leaf_count: int = Field(default=6, ge=1, le=len(LEAF_ATTACH), description="number of waving leaves on the stem")
    wave_hz: float = Field(
        default=2.0,
        ge=0.0,
        le=50.0,
        description="mean leaf waving frequency, Hz (each leaf differs by up to +-15 %; 0 = still)",
    )
    wave_amplitude_deg: float = Field(
        default=20.0, ge=0.0, lt=60.0, description="mean leaf waving amplitude, degrees (each leaf 80..120 % of it)"
    )
    phase_s: float = Field(default=0.0, description="scene time offset of the waving, s")
    background_distance_m: float = Field(
        default=2.0,
        gt=0.3,
        le=20.0,
        description="distance from the plant to the back wall, m (flash falls off as 1/d^2)",
    )
    ambient_scale: float = Field(default=1.0, ge=0.0, description="ambient panels' radiance factor, 1")
    flash_scale: float = Field(default=1.0, ge=0.0, description="flash LED radiance factor, 1")
    fov_deg: float = Field(
        default=30.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees"
    )


def _leaf_motion(i: int, p: Params) -> tuple[float, float, float, float]:
    """(base angle rad, amplitude rad, frequency Hz, phase rad) of leaf i: fixed, varied per leaf."""
    side = LEAF_ATTACH[i][1]
    base = math.radians(28.0 + 6.0 * (i % 3)) if side > 0 else math.radians(180.0 - 28.0 - 6.0 * (i % 3))
    amp = math.radians(p.wave_amplitude_deg) * (0.8 + 0.4 * ((0.618 * i) % 1.0))
    freq = p.wave_hz * (1.0 + 0.15 * ((i % 3) - 1))
    phase = 2.0 * math.pi * ((0.37 * i) % 1.0)
    return base, amp, freq, phase


def _leaf_angle(i: int, p: Params, t_s):
    base, amp, freq, phase = _leaf_motion(i, p)
    return base + amp * np.sin(2.0 * math.pi * freq * (np.asarray(t_s, float) + p.phase_s) + phase)


def _leaf_pivot(i: int) -> np.ndarray:
    return np.array([0.0, LEAF_ATTACH[i][0], LEAF_Z_M])


def _leaf_shapes(i: int) -> list[Shape]:
    """Leaf i in its part frame: the blade lies along +x from the pivot, in the z = 0 plane."""
    mat = Material(LEAF_COLOURS[i % len(LEAF_COLOURS)], twosided=True)
    blade = (
        rotate((1, 0, 0), LEAF_TILT_RAD)
        @ translate(LEAF_LENGTH_M / 2, 0, 0)
        @ scale(LEAF_LENGTH_M / 2, LEAF_HALF_WIDTH_M, 1)
    )
    stalk = box((0.006, 0.0, 0.0), (0.006, 0.002, 0.002))
    return [
        Shape(f"leaf{i}_blade", "disk", blade, mat, part=f"leaf{i}"),
        Shape(f"leaf{i}_stalk", "cube", stalk, Material((0.25, 0.35, 0.12)), part=f"leaf{i}"),
    ]


def _leaf_points_part() -> np.ndarray:
    """Tracked points in a leaf's part frame (M, 3): tip, middle and the blade's widest edges."""
    c, s = math.cos(LEAF_TILT_RAD), math.sin(LEAF_TILT_RAD)
    h = LEAF_HALF_WIDTH_M
    return np.array(
        [
            [LEAF_LENGTH_M, 0, 0],
            [LEAF_LENGTH_M / 2, 0, 0],
            [LEAF_LENGTH_M / 2, h * c, h * s],
            [LEAF_LENGTH_M / 2, -h * c, -h * s],
        ]
    )


def _foreground_shapes() -> list[Shape]:
    up = rotate((1, 0, 0), -math.pi / 2)  # canonical +z -> +y
    return [
        Shape("pot", "cylinder", translate(0, -0.16, 0) @ up @ scale(0.05, 0.05, 0.23), Material((0.58, 0.28, 0.14))),
        Shape(
            "pot_rim", "cylinder", translate(0, 0.05, 0) @ up @ scale(0.056, 0.056, 0.022), Material((0.62, 0.31, 0.16))
        ),
        Shape("soil", "disk", translate(0, 0.07, 0) @ up @ scale(0.05), Material((0.12, 0.08, 0.05))),
        Shape(
            "stem",
            "cylinder",
            translate(0, 0.06, 0) @ up @ scale(0.0055, 0.0055, STEM_TOP_M - 0.06),
            Material((0.22, 0.40, 0.10)),
        ),
        Shape("bud", "sphere", translate(0, STEM_TOP_M + 0.012, 0) @ scale(0.02), Material((0.85, 0.70, 0.10))),
    ]


def _background_shapes(p: Params) -> list[Shape]:
    """Back wall, posters, boxes and a floor strip, all at least ``background_distance_m`` - 0.3 m away."""
    zw = -p.background_distance_m
    d = p.background_distance_m + 1.0  # camera to wall
    half_w = d * math.tan(math.radians(p.fov_deg) / 2) * 1.3 + 0.2
    floor_y = 0.15 - 0.6 * d * math.tan(math.radians(p.fov_deg) / 2)  # the floor's back edge is in view
    up = rotate((1, 0, 0), -math.pi / 2)
    shapes = [
        Shape("wall", "rectangle", translate(0, 0.15, zw) @ scale(half_w, half_w, 1), Material((0.55, 0.52, 0.46))),
        Shape(
            "floor",
            "rectangle",
            translate(0, floor_y, zw + 0.4) @ up @ scale(half_w, 0.4, 1),
            Material((0.35, 0.25, 0.18)),
        ),
    ]
    # posters: (x, y, half width, half height) as fractions of the visible half width; colour
    posters = [
        (-0.62, 0.35, 0.20, 0.26, (0.75, 0.12, 0.10)),
        (-0.18, 0.50, 0.16, 0.14, (0.10, 0.25, 0.70)),
        (0.30, 0.42, 0.22, 0.18, (0.85, 0.80, 0.70)),
        (0.70, 0.20, 0.14, 0.30, (0.08, 0.50, 0.45)),
        (0.05, 0.05, 0.10, 0.10, (0.90, 0.62, 0.10)),
        (-0.40, -0.05, 0.08, 0.16, (0.05, 0.05, 0.06)),
        (0.45, -0.02, 0.09, 0.06, (0.60, 0.20, 0.55)),
    ]
    s = half_w / 1.3
    for i, (x, y, hx, hy, col) in enumerate(posters):
        shapes.append(
            Shape(
                f"poster{i}",
                "rectangle",
                translate(x * s, 0.15 + y * s, zw + 0.005) @ scale(hx * s, hy * s, 1),
                Material(col),
            )
        )
    # boxes standing on the floor in front of the wall: (x, half width, half height, depth offset); colour
    boxes = [
        (-0.75, 0.12, 0.20, 0.15, (0.70, 0.55, 0.30)),
        (-0.35, 0.10, 0.12, 0.25, (0.15, 0.30, 0.60)),
        (0.10, 0.14, 0.08, 0.20, (0.80, 0.80, 0.78)),
        (0.55, 0.09, 0.22, 0.12, (0.55, 0.10, 0.12)),
        (0.85, 0.13, 0.10, 0.28, (0.20, 0.45, 0.20)),
    ]
    for i, (x, hx, hy, dz, col) in enumerate(boxes):
        shapes.append(
            Shape(
                f"box{i}",
                "cube",
                box((x * s, floor_y + hy * s, zw + dz * s + 0.05), (hx * s, hy * s, 0.08)),
                Material(col),
            )
        )
    return shapes


def _camera(p: Params) -> Camera:
    return Camera(origin=CAMERA_ORIGIN, target=CAMERA_TARGET, up=(0.0, 1.0, 0.0), fov_deg=p.fov_deg)


def _lights(p: Params) -> list[Shape]:
    amb = AMBIENT_RADIANCE * p.ambient_scale
    flash = FLASH_RADIANCE * p.flash_scale
    zw = -p.background_distance_m
    led = np.asarray(CAMERA_ORIGIN) + np.array([FLASH_OFFSET_M, 0.0, 0.0])
    return [
        # above and in front of the plant, 0.9 x 0.6 m
        Shape(
            "ambient_top",
            "rectangle",
            frame_towards((0.0, 1.0, 0.6), (0.0, 0.15, 0.0)) @ scale(0.45, 0.3, 1),
            None,
            Light("ambient", (amb, amb, 0.95 * amb)),
        ),
        # above the view, lighting the background (3 x 1 m): about the plant's ambient irradiance
        Shape(
            "ambient_back",
            "rectangle",
            frame_towards((0.0, 1.6, zw + 1.2), (0.0, 0.0, zw)) @ scale(1.5, 0.5, 1),
            None,
            Light("ambient", (amb, amb, 0.95 * amb)),
        ),
        Shape(
            "flash_led",
            "rectangle",
            frame_towards(led, (0.0, 0.17, 0.0)) @ scale(0.005, 0.005, 1),
            None,
            Light("flash", (flash, flash, flash)),
        ),
    ]


def make(params: Params) -> SceneModel:
    """The flash-matting toy scene for ``params``."""
    n = params.leaf_count
    pivots = [_leaf_pivot(i) for i in range(n)]

    def part_fn(i: int):
        def world_from_leaf(t_s: float) -> np.ndarray:
            """World-from-leaf matrix (4, 4) of leaf i at scene time ``t_s`` (s)."""
            return translate(*pivots[i]) @ rotate((0, 0, 1), float(_leaf_angle(i, params, t_s)))

        return world_from_leaf

    local = _leaf_points_part()

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the tracked points on every leaf, m."""
        t = np.atleast_1d(np.asarray(times_s, float))
        out = []
        for i in range(n):
            a = _leaf_angle(i, params, t)[:, None]
            c, s = np.cos(a), np.sin(a)
            x = c * local[None, :, 0] - s * local[None, :, 1]
            y = s * local[None, :, 0] + c * local[None, :, 1]
            z = np.broadcast_to(local[None, :, 2], x.shape)
            out.append(np.stack([x, y, z], axis=-1) + pivots[i])
        return np.concatenate(out, axis=1)

    fg = _foreground_shapes() + [s for i in range(n) for s in _leaf_shapes(i)]
    build = SceneBuild(
        shapes=tuple(_background_shapes(params) + fg + _lights(params)),
        parts={f"leaf{i}": part_fn(i) for i in range(n)},
    )
    still = params.wave_hz == 0.0 or params.wave_amplitude_deg == 0.0
    return SceneModel(
        name="flash_toy",
        groups=("ambient", "flash"),
        switchable=frozenset({"flash"}),
        camera=_camera(params),
        build=build,
        params=params,
        motion_points=None if still else motion_points,
        default_film=(640, 512),
        extra={"foreground": tuple(s.name for s in fg)},
    )
