"""The ``SceneModel.build`` payload: a scene as plain data that :mod:`mbcapture.render` turns
into a Mitsuba scene. No Mitsuba import here: scene modules use these classes.

Units: metres for geometry, W m^-2 sr^-1 for area and environment radiance (per RGB channel).
Transforms are numpy (4, 4) float64 homogeneous matrices acting on column vectors.

Canonical shapes (before ``to_world``), as in Mitsuba:

``rectangle``  [-1, 1]^2 in the z = 0 plane, normal +z (an area light emits towards +z)
``disk``       unit disk in the z = 0 plane, normal +z
``cube``       [-1, 1]^3
``sphere``     unit sphere at the origin (use uniform scales only)
``cylinder``   radius 1 from z = 0 to z = 1, open ends (close them with disks)

Moving geometry: a shape with ``part=<name>`` has its ``to_world`` relative to that part's
frame, and ``SceneBuild.parts[name](t_s)`` gives the part's world-from-part matrix at scene
time ``t_s`` (s). Non-emitting shapes of a part become one Mitsuba ``shapegroup`` + ``instance``;
emitting shapes of a part (``rectangle``, ``disk``, ``sphere``, ``cylinder`` only) are moved
through their own ``to_world``. Neither recompiles the render kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Literal, Mapping

import numpy as np

ShapeKind = Literal["rectangle", "disk", "cube", "sphere", "cylinder"]
RGB = tuple[float, float, float]
#: Shape kinds whose ``to_world`` Mitsuba exposes as an updatable parameter.
MOVABLE_EMITTER_KINDS: frozenset[str] = frozenset({"rectangle", "disk", "sphere", "cylinder"})


@dataclass(frozen=True)
class Material:
    """Lambertian reflector: ``reflectance`` (albedo per channel, 0..1)."""

    reflectance: RGB
    twosided: bool = False


@dataclass(frozen=True)
class Light:
    """Area emission of a shape's front side: ``radiance`` W m^-2 sr^-1, in emitter ``group``."""

    group: str
    radiance: RGB


@dataclass(frozen=True)
class Shape:
    """One primitive; ``name`` must be unique and a valid identifier."""

    name: str
    kind: ShapeKind
    to_world: np.ndarray
    material: Material | None = None  # None: black (e.g. the surface of a light)
    light: Light | None = None
    part: str | None = None


@dataclass(frozen=True)
class Environment:
    """Constant radiance ``radiance`` (W m^-2 sr^-1) from every direction, in ``group``."""

    group: str
    radiance: RGB


@dataclass(frozen=True)
class SceneBuild:
    """Everything :class:`mbcapture.render.Renderer` needs besides the camera.

    shapes
        All primitives.
    parts
        Moving part name -> ``f(t_s: float) -> (4, 4)`` world-from-part matrix.
    environment
        Optional constant environment light.
    """

    shapes: tuple[Shape, ...]
    parts: Mapping[str, Callable[[float], np.ndarray]] = field(default_factory=dict)
    environment: Environment | None = None

    def emitter_groups(self) -> tuple[str, ...]:
        """Groups that own at least one emitter, in first-appearance order."""
        seen: dict[str, None] = {}
        for s in self.shapes:
            if s.light is not None:
                seen.setdefault(s.light.group)
        if self.environment is not None:
            seen.setdefault(self.environment.group)
        return tuple(seen)


# -- small numpy transform helpers (column-vector convention, like Mitsuba) ---------------------
def translate(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def scale(x: float, y: float | None = None, z: float | None = None) -> np.ndarray:
    return np.diag([x, x if y is None else y, x if z is None else z, 1.0])


def rotate(axis: tuple[float, float, float], angle_rad: float) -> np.ndarray:
    """Right-handed rotation by ``angle_rad`` about the unit direction ``axis``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + s * k + (1 - c) * np.outer(a, a)
    return m


def frame_towards(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Matrix placing a canonical rectangle/disk at ``position`` with its normal (+z) aimed at
    ``target`` (the x axis is horizontal, perpendicular to ``up``)."""
    p = np.asarray(position, float)
    z = np.asarray(target, float) - p
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, p
    return m


def box(center, half_size) -> np.ndarray:
    """``to_world`` of an axis-aligned ``cube`` with the given centre and half sizes (m)."""
    return translate(*center) @ scale(*half_size)
