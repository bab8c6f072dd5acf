"""A Mitsuba 3 scene file (XML) as the scene: any shape, material and emitter Mitsuba loads, with its
objects moved and its emitters grouped from the config.

    scene:
      name: mitsuba
      file: scenes/examples/table.xml        # relative to the config file (to the working directory with --set)
      parameters: {lamp_w: 20}                # the file's $parameters
      groups: {flash_bulb: flash}             # emitter (or emitting shape) id -> group; the rest: default_group
      motion:                                 # shape id -> a motion (mbcapture.scene.keyframes)
        cup: {type: linear, velocity_m_s: [0.5, 0, 0]}

The file's sensor is the camera (``camera.*`` may move it or change its lens); its film, sampler and
integrator are replaced by the capture's (``render.*`` and the project's per-group path tracer).
``mbcapture scenes FILE.xml`` lists the ids a config can name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mbcapture.errors import ConfigError
from mbcapture.render import xmlscene
from mbcapture.render.build import SceneBuild, SceneFile
from mbcapture.scene.keyframes import Motion
from mbcapture.scene.scenes import Camera, SceneModel

DESCRIPTION = "a Mitsuba 3 scene file (scene.file): any material and emitter; motion and groups from the config"


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    file: str = Field(
        "", description="the Mitsuba 3 scene file (.xml); relative to the config file, or to the working directory"
    )
    parameters: dict[str, str | float | int | bool] = Field(
        default_factory=dict, description="values of the file's $parameters (as <default> gives them), by name"
    )
    groups: dict[str, str] = Field(
        default_factory=dict,
        description="emitter group of each emitter id (for an area light: its shape's id); a protocol switches "
        "groups (flash, led_top, ...). Emitters not named are in default_group",
    )
    default_group: str = Field("ambient", description="the group of every emitter not named in groups (always on)")
    motion: dict[str, Motion] = Field(
        default_factory=dict,
        description="shape id (or a spot light's, or an emitting rectangle's, disk's, sphere's or cylinder's) -> its "
        "motion over scene time: type keyframes, linear, orbit or pendulum (mbcapture/scene/keyframes.py lists "
        "their keys)",
    )


#: What scene.motion can move besides shapes without light: lights moved through their own to_world.
MOVABLE_LIGHTS = frozenset({"spot", "rectangle", "disk", "sphere", "cylinder"})


def _movable_light(o: xmlscene.FileObject) -> bool:
    return (o.kind == "Emitter" and o.plugin == "spot") or (
        o.kind == "Shape" and o.emits and o.plugin in MOVABLE_LIGHTS
    )


def _check_ids(params: Params, objects: list[xmlscene.FileObject], path: str) -> None:
    emitters = {o.id for o in objects if o.kind == "Emitter" or o.emits}
    movable = {o.id for o in objects if (o.kind == "Shape" and not o.emits) or _movable_light(o)}
    for key, pool, what in (
        ("groups", emitters, "an emitter"),
        ("motion", movable, "a shape, a spot light or a rectangle, disk, sphere or cylinder light"),
    ):
        for name in getattr(params, key):
            if name not in pool:
                raise ConfigError(
                    f"scene.{key}: {name!r} is not the id of {what} in {path} (those: {', '.join(sorted(pool)) or 'none'})"
                )


def shape_ids(objects: list[xmlscene.FileObject]) -> set[str]:
    return {o.id for o in objects if o.kind == "Shape"}


def make(params: Params) -> SceneModel:
    """The scene of ``params.file``."""
    if not params.file:
        raise ConfigError("scene.file: the mitsuba scene needs a Mitsuba 3 scene file (.xml)")
    path = str(Path(params.file).resolve())
    state, _ = xmlscene.parse(path, params.parameters)
    missing = [str(f) for f in xmlscene.referenced_files(state) if not f.is_file()]
    if missing:
        raise ConfigError(f"scene.file: {path} reads files that do not exist: {', '.join(missing)}")
    objects = xmlscene.file_objects(state)
    _check_ids(params, objects, path)
    emitters = tuple(
        (o.id, params.groups.get(o.id, params.default_group)) for o in objects if o.kind == "Emitter" or o.emits
    )
    if not emitters:
        raise ConfigError(f"scene.file: {path} has no emitter: a capture needs light")
    groups = tuple(dict.fromkeys(g for _, g in emitters))
    parts = {f"{shape}__moving": motion.matrix for shape, motion in params.motion.items()}
    entries = xmlscene.entries(state)  # converted once for every pose and box below
    lights = {o.id for o in objects if _movable_light(o)}
    corners = {
        key: (xmlscene.emitter_pose(entries, key)[0][None, :] if key in lights and key not in shape_ids(objects)
              else xmlscene.bounding_box(entries, key))
        for key in params.motion
    }  # fmt: skip

    def motion_points(times_s: np.ndarray) -> np.ndarray:
        out = []
        for t in np.atleast_1d(times_s):
            pts = [
                (params.motion[s].matrix(float(t)) @ np.c_[c, np.ones(len(c))].T).T[:, :3] for s, c in corners.items()
            ]
            out.append(np.concatenate(pts))
        return np.asarray(out)

    cam = xmlscene.file_camera(state)
    return SceneModel(
        name="mitsuba",
        groups=groups,
        switchable=frozenset(g for g in groups if g != params.default_group),
        camera=cam,
        build=SceneBuild(
            shapes=(),
            parts=parts,
            file=SceneFile(
                path,
                {k: str(v) for k, v in params.parameters.items()},
                emitters,
                {key: f"{key}__moving" for key in params.motion if key not in lights},
                {key: f"{key}__moving" for key in params.motion if key in lights},
            ),
        ),
        params=params,
        motion_points=motion_points if params.motion else None,
        extra=_flash_geometry(entries, emitters, cam),
    )


def _flash_geometry(entries: dict, emitters: tuple[tuple[str, str], ...], cam: Camera) -> dict:
    """Each group's light position (the mean of its emitters', world, m) and the unit direction it faces (a
    spot's axis, an emitting rectangle's normal; else towards the camera's view), as multi-flash reads them."""
    positions, directions = {}, {}
    for group in dict.fromkeys(g for _, g in emitters):
        poses = [xmlscene.emitter_pose(entries, key) for key, g in emitters if g == group]
        position = np.mean([p for p, _ in poses], axis=0)
        facing = [d for _, d in poses if d is not None]
        d = np.mean(facing, axis=0) if facing else np.asarray(cam.target) - position
        positions[group] = tuple(float(v) for v in position)
        directions[group] = tuple(float(v) for v in d / np.linalg.norm(d))
    return {"flash_positions_m": positions, "flash_directions": directions}
