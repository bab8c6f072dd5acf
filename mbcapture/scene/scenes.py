"""Scene registry and the contract every ``scenes/<name>/scene.py`` fulfils.

A scene module is plain Python that never imports Mitsuba. It defines

``DESCRIPTION``
    one line for ``mbcapture scenes``.
``Params``
    a pydantic model (``extra="forbid"``) of the scene's own config keys (``scene.*``),
    every field with a default and a ``description``.
``make(params) -> SceneModel``
    the scene as data: camera, emitter groups, motion, and a builder that the render
    package turns into a Mitsuba scene.

Everything Mitsuba-specific (dict building, parameter updates) happens in
:mod:`mbcapture.render`; the planner only needs the camera and the motion points, so
``mbcapture plan`` works without Mitsuba.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

import numpy as np

from .camera_motion import project_through, reference_points
from ..errors import ConfigError
from .projective import Camera, frame  # noqa: F401  (Camera: a scene module builds its SceneModel with it)

#: Folder holding ``<name>/scene.py``; ``MBCAPTURE_SCENE_PATH`` (os.pathsep separated) adds more.
BUILTIN_SCENE_DIR = Path(__file__).resolve().parents[2] / "scenes"


@dataclass(frozen=True)
class SceneModel:
    """A scene as plain data, produced by a scene module's ``make(params)``.

    groups
        Emitter group names, in the order of the render output's group axis.
    switchable
        The groups a protocol may switch (flashes, LEDs). Every other group is always on.
    camera
        Used by the planner to project motion points to pixels.
    motion_points
        ``f(times_s: (T,) array) -> (T, M, 3)`` world-space points on the moving parts;
        ``None`` for a static scene. The planner bounds image motion with them.
    build
        Opaque payload for the render package (the scene's description); the scene module
        and :mod:`mbcapture.render` agree on its form.
    params
        The validated ``Params`` instance.
    drives
        Optional group -> :class:`~mbcapture.timing.drive.Drive`: emitter drive that varies
        continuously in time (mains flicker), integrated exactly into the render weights.
        Groups not named have a constant drive of 1.
    demodulation
        A time-of-flight capture's :class:`~mbcapture.sensor.demodulation.Demodulation` (set by the capture,
        :func:`mbcapture.config.demodulated`): its phase groups are among :attr:`groups`, and the renderer makes
        their images from the modulated group's phasor channels. None otherwise.
    camera_motion
        Optional :class:`~mbcapture.scene.camera_motion.CameraMotion` (``camera.shake`` or a trajectory
        file, set by the capture, not by scene modules): the camera's pose over time about
        ``camera``. Everything that projects to pixels goes through :meth:`project` and
        :meth:`image_points`, which follow it.
    """

    name: str
    groups: tuple[str, ...]
    switchable: frozenset[str]
    camera: Camera
    build: Any
    params: Any
    motion_points: Callable[[np.ndarray], np.ndarray] | None = None
    default_film: tuple[int, int] = (640, 512)
    extra: dict = field(default_factory=dict)
    drives: dict = field(default_factory=dict)
    camera_motion: Any = None
    demodulation: Any = None

    @property
    def is_static(self) -> bool:
        """Nothing in the image moves: no moving part and a still camera."""
        return self.motion_points is None and self.camera_motion is None

    def project(self, points: np.ndarray, times_s: np.ndarray, width: int, height: int) -> np.ndarray:
        """World points (T, M, 3) at scene times (T,) -> pixels (T, M, 2) as the camera saw them
        then: through :attr:`camera` if it is still, else through its pose at each time."""
        if self.camera_motion is None:
            return self.camera.project(points, width, height)

        poses = self.camera_motion.world_from_camera(self.camera, times_s)
        return project_through(poses, points, self.camera.fov_deg, width, height)

    def image_points(self, times_s: np.ndarray, width: int, height: int) -> np.ndarray:
        """(T, M, 2) pixel positions at ``times_s`` of the points whose image motion bounds the render
        strata: the moving parts' :attr:`motion_points` and, with a moving camera, the frame's
        reference points (:func:`mbcapture.scene.camera_motion.reference_points`, fixed in the world)."""
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        if self.camera_motion is None:
            return self.camera.project(np.asarray(self.motion_points(t), dtype=np.float64), width, height)

        ref = reference_points(self.camera, width, height)
        pts = np.broadcast_to(ref, (t.size, *ref.shape))
        if self.motion_points is not None:
            pts = np.concatenate([np.asarray(self.motion_points(t), dtype=np.float64), pts], axis=1)
        return self.project(pts, t, width, height)


def _scene_dirs() -> list[Path]:
    dirs = [BUILTIN_SCENE_DIR]
    for p in os.environ.get("MBCAPTURE_SCENE_PATH", "").split(os.pathsep):
        if p:
            dirs.append(Path(p))
    return dirs


def available() -> dict[str, Path]:
    """Scene name -> its ``scene.py``."""
    found: dict[str, Path] = {}
    for d in _scene_dirs():
        if d.is_dir():
            for sub in sorted(d.iterdir()):
                if (sub / "scene.py").is_file():
                    found.setdefault(sub.name, sub / "scene.py")
    return found


@lru_cache(maxsize=None)
def load_module(name: str) -> ModuleType:
    """Import ``scenes/<name>/scene.py``; an unknown name lists the valid ones."""
    scenes = available()
    if name not in scenes:
        searched = ", ".join(str(d) for d in _scene_dirs())
        raise ConfigError(
            f"scene.name: unknown scene {name!r}; expected one of {sorted(scenes)} (folders <name>/scene.py in "
            f"{searched}; $MBCAPTURE_SCENE_PATH adds folders)"
        )
    path = scenes[name]
    mod_name = f"mbcapture_scene_{name}"
    spec = importlib.util.spec_from_file_location(mod_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a broken scene file is the user's, name it
        del sys.modules[mod_name]
        raise ConfigError(f"{path}: cannot load scene module: {exc}") from exc
    for attr in ("DESCRIPTION", "Params", "make"):
        if not hasattr(module, attr):
            raise ConfigError(f"{path}: a scene module must define {attr}")
    return module


def make_scene(name: str, params: Any) -> SceneModel:
    """Scene ``name``'s model for its validated ``params``; a ``make()`` that returns something else than a
    SceneModel is one line naming the scene file."""
    module = load_module(name)
    scene = module.make(params)
    if not isinstance(scene, SceneModel):
        raise ConfigError(
            f"{available()[name]}: make(params) must return a mbcapture.scene.scenes.SceneModel, "
            f"got {type(scene).__name__}"
        )
    return scene
