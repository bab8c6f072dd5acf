"""Rigid motions set in a config (``scene.motion`` of a scene file): what moves an object of a Mitsuba scene
file over scene time, as a (4, 4) world-from-rest matrix ``M(t)`` (the identity where the object sits as
the file places it).

Kinds (``type``):

``keyframes``
    ``keyframes``: a list of poses at times ``t`` (s, ascending), each a ``translate`` (m), a ``rotate``
    (``axis``, ``angle_deg``, about the point ``about``) and a uniform ``scale`` about ``about``, applied
    in the order scale, rotate, translate; ``interpolation`` ``linear`` or ``smooth`` (a smoothstep in each
    interval: the object starts and stops without a jump in velocity). Held at the first and last poses
    outside their times.
``linear``
    a constant velocity ``velocity_m_s`` (m/s) from the rest pose at ``t = 0``.
``orbit``
    a rotation about ``axis`` through ``centre`` at one turn per ``period_s`` (negative: the other way).
``pendulum``
    a swing about ``axis`` through ``pivot``: angle ``amplitude_deg`` sin(2 pi t / ``period_s`` + phase).

Plain numpy: the planner bounds image motion with these matrices before anything is rendered.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

Vec3 = tuple[float, float, float]


def rotation(axis: Vec3, angle_deg: float, about: Vec3 = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) rotation by ``angle_deg`` about ``axis`` (right-handed) through the point ``about``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    th = math.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    r = np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * (k @ k)
    m = np.eye(4)
    m[:3, :3] = r
    p = np.asarray(about, dtype=np.float64)
    m[:3, 3] = p - r @ p
    return m


def translation(v: Vec3) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


class Pose(BaseModel):
    """One keyframe."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    t: float = Field(description="scene time of this pose, s")
    translate: Vec3 = Field((0.0, 0.0, 0.0), description="translation, m")
    axis: Vec3 = Field((0.0, 1.0, 0.0), description="rotation axis (any length but 0)")
    angle_deg: float = Field(0.0, description="rotation about axis, degrees (right-handed)")
    about: Vec3 = Field((0.0, 0.0, 0.0), description="the point the rotation and scale keep fixed, m")
    scale: float = Field(1.0, gt=0, description="uniform scale about 'about'")

    @model_validator(mode="after")
    def _axis(self) -> "Pose":
        if not np.linalg.norm(self.axis) > 0:
            raise ValueError("axis: expected a non-zero direction")
        return self


class Motion(BaseModel):
    """A rigid motion of one object of a scene file (see the module docstring for each kind's keys)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    type: Literal["keyframes", "linear", "orbit", "pendulum"] = Field(description="the kind of motion")
    keyframes: list[Pose] = Field(default_factory=list, description="keyframes: the poses, times ascending")
    interpolation: Literal["linear", "smooth"] = Field("linear", description="keyframes: between two poses")
    velocity_m_s: Vec3 = Field((0.0, 0.0, 0.0), description="linear: velocity, m/s")
    axis: Vec3 = Field((0.0, 1.0, 0.0), description="orbit, pendulum: the rotation axis")
    centre: Vec3 = Field((0.0, 0.0, 0.0), description="orbit: a point on the axis, m")
    pivot: Vec3 = Field((0.0, 0.0, 0.0), description="pendulum: a point on the axis, m")
    period_s: float = Field(1.0, description="orbit: seconds per turn (negative: the other way); pendulum: period")
    amplitude_deg: float = Field(10.0, description="pendulum: amplitude, degrees")
    phase_s: float = Field(0.0, description="pendulum: time offset, s")

    @model_validator(mode="after")
    def _complete(self) -> "Motion":
        if self.type == "keyframes":
            if not self.keyframes:
                raise ValueError("keyframes: a keyframes motion needs at least one pose")
            times = [p.t for p in self.keyframes]
            if any(b <= a for a, b in zip(times, times[1:])):
                raise ValueError(f"keyframes: times must ascend, got {times}")
            axes = {
                tuple(np.round(np.asarray(p.axis) / np.linalg.norm(p.axis), 9)) for p in self.keyframes if p.angle_deg
            }
            if len(axes) > 1:
                raise ValueError("keyframes: every rotating pose needs the same axis (angles interpolate about it)")
        if self.type in ("orbit", "pendulum"):
            if not np.linalg.norm(self.axis) > 0:
                raise ValueError("axis: expected a non-zero direction")
            if self.period_s == 0 or not math.isfinite(self.period_s):
                raise ValueError("period_s: expected a finite, non-zero period")
        return self

    def matrix(self, t_s: float) -> np.ndarray:
        """(4, 4) world-from-rest at scene time ``t_s``."""
        t = float(t_s)
        if self.type == "linear":
            return translation(tuple(t * np.asarray(self.velocity_m_s)))
        if self.type == "orbit":
            return rotation(self.axis, 360.0 * t / self.period_s, self.centre)
        if self.type == "pendulum":
            angle = self.amplitude_deg * math.sin(2 * math.pi * (t + self.phase_s) / abs(self.period_s))
            return rotation(self.axis, angle, self.pivot)
        return self._keyframe_matrix(t)

    def _keyframe_matrix(self, t: float) -> np.ndarray:
        poses = self.keyframes
        if t <= poses[0].t:
            return _pose_matrix(poses[0])
        if t >= poses[-1].t:
            return _pose_matrix(poses[-1])
        i = max(j for j, p in enumerate(poses) if p.t <= t)
        a, b = poses[i], poses[i + 1]
        u = (t - a.t) / (b.t - a.t)
        if self.interpolation == "smooth":
            u = u * u * (3 - 2 * u)
        # each parameter interpolated; the rotations share one axis (checked), so their angles interpolate
        axis = next((p.axis for p in poses if p.angle_deg), a.axis)
        mix = Pose(
            t=t,
            translate=tuple((1 - u) * np.asarray(a.translate) + u * np.asarray(b.translate)),
            axis=axis,
            angle_deg=(1 - u) * a.angle_deg + u * b.angle_deg,
            about=tuple((1 - u) * np.asarray(a.about) + u * np.asarray(b.about)),
            scale=(1 - u) * a.scale + u * b.scale,
        )
        return _pose_matrix(mix)


def _pose_matrix(p: Pose) -> np.ndarray:
    s = np.eye(4)
    s[:3, :3] *= p.scale
    s[:3, 3] = np.asarray(p.about) * (1 - p.scale)
    return translation(p.translate) @ rotation(p.axis, p.angle_deg, p.about) @ s
