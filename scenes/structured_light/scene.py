"""Surfaces at several depths, one sliding, lit by a pattern projector beside the camera and by a
flickering lamp (structured light; the multi-bucket paper's section 6).

Coordinates (m): y up, the camera at (0, 0, 1.2) looks along -z at the origin. A back wall at
z = -0.2 (1.4 m from the lens), a turned box (~1.0 m), a sphere (~1.06 m), a slanted board
(~1.1-1.3 m) and a cube sliding left and right in front of them (front face ~0.82 m).

Projector: a pinhole projector ``projector_baseline_m`` to the right of the camera (image right,
world +x), in the lens plane, aimed at the origin, horizontal field of view ``projector_fov_deg``,
``projector_width_px`` x 3/4 of it texels. Each pattern is its own emitter group (a projector at
the same pose casting that pattern), so the protocol can pulse them in different buckets:

``pattern: phase_shift``   groups ``fringe_1`` .. ``fringe_N`` (N = ``phase_steps``):
    E(u) = E0 (1 + cos(2 pi P u / W - delta_k)) / 2 with P = ``fringe_periods`` periods across the
    projector's width W (texels, u the continuous column, texel centres at j + 0.5) and
    delta_k = 2 pi (k - 1) / N.
``pattern: gray_code``     groups ``white`` (E0 everywhere) and ``gray_1`` .. ``gray_M``
    (M = ``gray_bits``): bit m (1 = most significant) of the reflected binary (Gray) code of the
    stripe index floor(u 2^M / W), E0 where it is 1 and 0 elsewhere.

E0 = ``projector_irradiance_w_m2``: the irradiance of a lit texel on a plane perpendicular to the
projector's axis 1 m away (falling off as 1 / z^2; :class:`mbcapture.render.build.Projector`).

``ambient``: a small spherical lamp up and to the left, outside the view (always on): its hard
shadows make the ambient light vary in space, and its drive flickers at twice ``mains_hz``
(:class:`mbcapture.timing.drive.Drive`), so it varies in time.

Motion: the sliding cube's centre is at x(t) = ``slide_amplitude_m`` sin(2 pi f t) (f =
``slide_frequency_hz``): 0.75 m/s at t = 0 at the defaults, about 0.8 px/ms at 640x512.

``extra["structured_light"]``: the pattern kind, the pattern groups in protocol order, the
projector's pinhole (a :class:`~mbcapture.scene.projective.Camera`) and image size, and the pattern
parameters, for the protocol and the reconstruction.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.timing.drive import Drive
from mbcapture.render.build import Light, Material, Projector, SceneBuild, Shape, rotate, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = (
    "wall, box, sphere, slanted board and a sliding cube; a pattern projector beside the lens "
    "(groups fringe_1..N or white, gray_1..M) and a flickering lamp (group ambient)"
)

CAMERA_ORIGIN = (0.0, 0.0, 1.2)
WALL_Z_M = -0.2
LAMP_POSITION = (-0.45, 0.38, 0.85)
LAMP_RADIUS_M = 0.02
LAMP_RADIANCE = 800.0  # W m^-2 sr^-1 of the bulb at lamp_scale 1 (time average)
LAMP_COLOUR = (1.0, 0.92, 0.8)
CUBE_HALF_M = 0.05
CUBE_Y_M, CUBE_Z_M = 0.02, 0.33  # the front face at z = 0.38, 0.82 m from the lens


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    pattern: str = Field(
        "phase_shift",
        pattern="^(phase_shift|gray_code)$",
        description="projected patterns: phase_shift (N sinusoids) or gray_code (white + M Gray-code bits)",
    )
    phase_steps: int = Field(3, ge=3, le=16, description="phase_shift: N, the number of phase-shifted sinusoids")
    fringe_periods: int = Field(
        4, ge=1, le=64, description="phase_shift: P, sinusoid periods across the projector's width"
    )
    gray_bits: int = Field(
        8, ge=1, le=10, description="gray_code: M, Gray-code bit patterns (2^M stripes across the width)"
    )
    projector_irradiance_w_m2: float = Field(
        1.6,
        gt=0.0,
        description="E0: irradiance of a fully lit texel 1 m from the "
        "projector on a plane perpendicular to its axis, W m^-2 per RGB channel",
    )
    projector_baseline_m: float = Field(
        0.2,
        gt=0.0,
        le=1.0,
        description="distance of the projector's centre to the right of the lens centre, in the lens plane, m",
    )
    projector_fov_deg: float = Field(
        50.0, gt=5.0, lt=120.0, description="horizontal field of view of the projector, degrees"
    )
    projector_width_px: int = Field(
        512, ge=16, le=4096, description="projector image width, texels (height: 3/4 of it)"
    )
    lamp_scale: float = Field(2.0, ge=0.0, description="ambient lamp radiance factor (time average), 1")
    mains_hz: float = Field(
        50.0, gt=0.0, le=1000.0, description="mains frequency of the lamp, Hz; it flickers at twice this"
    )
    flicker_depth: float = Field(
        1.0, ge=0.0, le=1.0, description="lamp drive 1 - depth cos(2 pi 2 mains_hz t + phase); 0 = steady"
    )
    flicker_phase_deg: float = Field(0.0, description="phase of the flicker at scene time 0, degrees of its cycle")
    slide_amplitude_m: float = Field(
        0.12, ge=0.0, le=0.2, description="sliding cube: amplitude of its left-right motion, m (0: static)"
    )
    slide_frequency_hz: float = Field(1.0, gt=0.0, le=20.0, description="sliding cube: oscillation frequency, Hz")
    fov_deg: float = Field(40.0, gt=5.0, lt=120.0, description="horizontal field of view of the camera, degrees")


def projector_camera(p: Params) -> Camera:
    """The projector's pinhole, aimed at the origin from ``projector_baseline_m`` right of the lens."""
    o = (CAMERA_ORIGIN[0] + p.projector_baseline_m, CAMERA_ORIGIN[1], CAMERA_ORIGIN[2])
    return Camera(origin=o, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=p.projector_fov_deg)


def projector_size(p: Params) -> tuple[int, int]:
    return p.projector_width_px, max(1, round(p.projector_width_px * 3 / 4))


def gray_code(n: np.ndarray) -> np.ndarray:
    """Reflected binary (Gray) code of non-negative integers."""
    n = np.asarray(n, np.int64)
    return n ^ (n >> 1)


def patterns(p: Params) -> tuple[list[str], list[np.ndarray], dict]:
    """(group names in protocol order, (H, W) patterns in 0..1, description for the reconstruction)."""
    w, h = projector_size(p)
    u = np.arange(w) + 0.5
    if p.pattern == "phase_shift":
        deltas = [2 * math.pi * k / p.phase_steps for k in range(p.phase_steps)]
        rows = [0.5 + 0.5 * np.cos(2 * math.pi * p.fringe_periods * u / w - d) for d in deltas]
        names = [f"fringe_{k + 1}" for k in range(p.phase_steps)]
        info = {"phase_shifts_rad": deltas, "fringe_periods": p.fringe_periods}
    else:
        stripe = np.floor(u * 2**p.gray_bits / w).astype(np.int64)
        g = gray_code(stripe)
        rows = [np.ones(w)] + [((g >> (p.gray_bits - 1 - m)) & 1).astype(float) for m in range(p.gray_bits)]
        names = ["white"] + [f"gray_{m + 1}" for m in range(p.gray_bits)]
        info = {"gray_bits": p.gray_bits, "white_group": "white"}
    return names, [np.broadcast_to(r[None, :], (h, w)) for r in rows], info


def make(params: Params) -> SceneModel:
    amb = LAMP_RADIANCE * params.lamp_scale
    shapes = [
        Shape("wall", "rectangle", translate(0.0, 0.0, WALL_Z_M) @ scale(1.2, 1.0, 1.0), Material((0.7, 0.7, 0.68))),
        Shape(
            "box",
            "cube",
            translate(-0.2, -0.1, 0.15) @ rotate((0, 1, 0), math.radians(30)) @ scale(0.08, 0.1, 0.08),
            Material((0.65, 0.45, 0.35)),
        ),
        Shape("sphere", "sphere", translate(0.2, 0.13, 0.05) @ scale(0.09), Material((0.8, 0.8, 0.78))),
        Shape(
            "board",
            "rectangle",
            translate(0.22, -0.16, -0.02) @ rotate((0, 1, 0), math.radians(-40)) @ scale(0.09, 0.07, 1.0),
            Material((0.45, 0.6, 0.4), twosided=True),
        ),
        Shape(
            "lamp",
            "sphere",
            translate(*LAMP_POSITION) @ scale(LAMP_RADIUS_M),
            None,
            Light("ambient", tuple(amb * c for c in LAMP_COLOUR)),
        ),
        Shape("cube", "cube", scale(CUBE_HALF_M), Material((0.8, 0.75, 0.5)), part="slider"),
    ]
    pc = projector_camera(params)
    names, pats, info = patterns(params)
    e0 = params.projector_irradiance_w_m2
    projectors = tuple(
        Projector(f"projector_{g}", g, pc.origin, pc.target, pc.up, pc.fov_deg, np.repeat((e0 * pat)[..., None], 3, -1))
        for g, pat in zip(names, pats)
    )
    A, f = params.slide_amplitude_m, params.slide_frequency_hz

    def slider_x(t_s):
        return A * np.sin(2 * np.pi * f * np.asarray(t_s, float))

    def slider_to_world(t_s: float) -> np.ndarray:
        return translate(float(slider_x(t_s)), CUBE_Y_M, CUBE_Z_M)

    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * CUBE_HALF_M

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        """World positions (time, point, xyz) of the sliding cube's corners, m."""
        x = np.atleast_1d(slider_x(times_s))
        off = np.stack([x, np.full_like(x, CUBE_Y_M), np.full_like(x, CUBE_Z_M)], -1)
        return corners[None] + off[:, None, :]

    w, h = projector_size(params)
    flicker = Drive.mains_flicker(params.mains_hz, params.flicker_depth, math.radians(params.flicker_phase_deg))
    return SceneModel(
        name="structured_light",
        groups=("ambient", *names),
        switchable=frozenset(names),
        camera=Camera(origin=CAMERA_ORIGIN, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=params.fov_deg),
        build=SceneBuild(shapes=tuple(shapes), parts={"slider": slider_to_world}, projectors=projectors),
        params=params,
        motion_points=motion_points if A > 0 else None,
        default_film=(640, 512),
        extra={
            "structured_light": {
                "kind": params.pattern,
                "groups": tuple(names),
                "projector": pc,
                "projector_size_px": (w, h),
                **info,
            }
        },
        drives={"ambient": flicker},
    )
