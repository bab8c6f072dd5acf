"""Where the moving parts' shadows fall: the pixels whose light changes as a moving part passes between
a light and the static scene.

Adaptive sampling treats the pixels the moving parts cross apart (:func:`mbcapture.budget.adaptive.scout_tail`):
there a render's time within its stratum is noise that more samples at that time do not lower, so they are
refined at several times per half-stratum. A moving part's hard shadow is such a pixel too, though nothing
in it moves: measured on multi_flash at 160x128, the pixels beside the sliding box, where
the right LED's shadow of it sweeps over the wall, kept a run's own 99.9th percentile of 3.5 after 64 x the
first pass's samples at one time per half-stratum (their first pass's ratio about 4; 1/64 of it predicted).

No library does this: it casts rays from points of each light through the moving parts' motion points onto the
scene's static shapes (Mitsuba's ray tracer, in the renderer's variant) and rasterizes the convex hull of
where they land, per light and time (:func:`mbcapture.scene.camera_motion.hull_mask`). Hard shadows of convex parts
are covered; what is left out is said in :func:`moving_shadows`. :func:`changing_region`, what adaptive sampling
takes, adds the moving region and, where the camera moves at all, the whole film.
"""

from __future__ import annotations

import numpy as np

from ..scene.camera_motion import FRAME_MOTION_PX, MOVING_REGION_TIMES, frame_motion_px, hull_mask, moving_region
from ..scene.projective import frame
from .build import Shape
from .scene_dicts import shape_description

#: Points of each canonical shape (Mitsuba's: a rectangle and a disk span [-1, 1]^2 in z = 0, a sphere and a cube
#: [-1, 1]^3, a cylinder the unit circle from z = 0 to 1) from which a light's shadows are cast: its centre and
#: its extremes, so that a small source's penumbra is inside the hull of its corners' shadows.
LIGHT_POINTS = {
    "rectangle": [(0, 0, 0), (-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
    "disk": [(0, 0, 0), (-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0)],
    "sphere": [(0, 0, 0), (-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)],
    "cube": [(0, 0, 0)] + [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)],
    "cylinder": [(0, 0, 0.5)] + [(x, y, z) for z in (0, 1) for x, y in ((-1, 0), (1, 0), (0, -1), (0, 1))],
}


#: A light casts a hard shadow, one whose edge moves with the part, where it spans at most this many radians as
#: seen from the moving parts (its extent over its distance to them): the LEDs of multi_flash (1 cm at 0.6 m) and
#: the metronome's bulb do; a soft box (multi_flash's ambient light, 0.9 m across at 1 m) does not, and its shadow's
#: hull would take in a third of the film. A soft shadow's light changes across a wide penumbra, so the change a
#: render's time within its stratum makes is small.
HARD_SHADOW_MAX_ANGLE = 0.25


def _light_points(shape: Shape, part_to_world: np.ndarray | None) -> np.ndarray:
    """(P, 3) world points of an emitting shape (its mesh's: none)."""
    local = np.asarray(LIGHT_POINTS.get(shape.kind, []), float).reshape(-1, 3)
    m = shape.to_world if part_to_world is None else part_to_world @ shape.to_world
    return local @ m[:3, :3].T + m[:3, 3]


def _static_scene(mi, shapes: list[Shape]):
    """A Mitsuba scene of ``shapes`` alone (their geometry; what they look like does not matter here)."""
    return mi.load_dict(
        {
            "type": "scene",
            **{f"s{i}": shape_description(mi, s, s.to_world, {"type": "diffuse"}) for i, s in enumerate(shapes)},
        }
    )


def moving_shadows(renderer, t0_s: float, t1_s: float, width: int, height: int) -> np.ndarray:
    """(H, W) bool: the pixels where a moving part's shadow from one of the scene's lights (an emitting shape, or a
    projector's centre) falls on the static scene at some time in [t0, t1], at :data:`MOVING_REGION_TIMES` times:
    rays from each light's :data:`LIGHT_POINTS` through each of the scene's ``motion_points``, their first hits
    on the static, non-emitting shapes projected into the camera, one convex hull per light and time (a shadow
    over several surfaces: the hull spans them, more than the shadow); lights too large for a hard shadow
    (:data:`HARD_SHADOW_MAX_ANGLE`) are left out. All False for a static scene, all True
    where the frame itself moves (:func:`mbcapture.scene.camera_motion.moving_region` is then the whole film).
    :func:`changing_region` adds the moving region and a moving camera's. Left out: an environment light's soft shadows, a moving light's shadows of the static scene (the
    moving_light scene's lamp: its whole image changes), light the moving parts reflect onto the scene, and
    shadows on other moving parts."""
    scene = renderer.scene_model
    mask = np.zeros((height, width), dtype=bool)
    if scene.is_static or scene.motion_points is None:
        return mask
    times = np.linspace(t0_s, t1_s, MOVING_REGION_TIMES)
    if frame_motion_px(scene, times, width, height) > FRAME_MOTION_PX:
        return ~mask
    build = scene.build
    receivers = [s for s in build.shapes if s.part is None and s.light is None]
    lights = [s for s in build.shapes if s.light is not None]
    if not receivers or not (lights or build.projectors):
        return mask
    motion = np.asarray(scene.motion_points(times), float)  # (T, M, 3)
    starts, sets = [], []  # per (time, light): the light's points
    for ti, t in enumerate(times):
        for s in lights:
            pose = None if s.part is None else np.asarray(build.parts[s.part](float(t)), float)
            pts = _light_points(s, pose)
            if len(pts) == 0:
                continue
            extent = np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))
            if extent > HARD_SHADOW_MAX_ANGLE * np.linalg.norm(motion[ti] - pts[0], axis=-1).min():
                continue  # a soft shadow
            starts.append(pts)
            sets.append(ti)
        for p in build.projectors:
            world = p.to_world() if p.part is None else np.asarray(build.parts[p.part](float(t)), float) @ p.to_world()
            starts.append(world[:3, 3][None, :])
            sets.append(ti)
    if not starts:  # no light casts a hard shadow
        return mask
    # every ray of a (time, light): from each of its points through each motion point at that time, beyond it
    origins, directions, owner = [], [], []
    for k, (pts, ti) in enumerate(zip(starts, sets)):
        d = motion[ti][None, :, :] - pts[:, None, :]  # (P, M, 3)
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        ok = n[..., 0] > 1e-9
        origins.append(np.broadcast_to(motion[ti][None], d.shape)[ok])
        directions.append((d / np.maximum(n, 1e-12))[ok])
        owner.append(np.full(int(ok.sum()), k))
    o, dvec, owner = np.concatenate(origins), np.concatenate(directions), np.concatenate(owner)
    mi = renderer.mitsuba
    static = _static_scene(mi, receivers)
    ray = mi.Ray3f(
        mi.Point3f(*[np.ascontiguousarray(o[:, i], np.float32) for i in range(3)]),
        mi.Vector3f(*[np.ascontiguousarray(dvec[:, i], np.float32) for i in range(3)]),
    )
    si = static.ray_intersect(ray)
    hit = np.asarray(si.is_valid(), bool)
    p = np.stack([np.asarray(si.p[i], float) for i in range(3)], axis=1)
    # only what lies before the camera can be seen in it
    origin, forward, _, _ = frame(scene.camera)
    hit &= (p - origin) @ forward > 1e-6
    if not hit.any():
        return mask
    px = scene.camera.project(p[hit], width, height)
    owner = owner[hit]
    return hull_mask((px[owner == k] for k in np.unique(owner)), width, height)


def changing_region(
    renderer, t0_s: float, t1_s: float, width: int, height: int, moving: np.ndarray | None = None
) -> np.ndarray:
    """(H, W) bool: the pixels where a render's time within its stratum is noise, which adaptive sampling refines at
    several times per half-stratum (:func:`mbcapture.budget.adaptive.scout_tail`): the moving region
    (:func:`mbcapture.scene.camera_motion.moving_region`), the moving parts' hard shadows (:func:`moving_shadows`), and
    every pixel where the camera moves at all. The applications' moving region counts a moving camera only once its
    frame moves by :data:`mbcapture.scene.camera_motion.FRAME_MOTION_PX`, but every edge in the image moves with it:
    metronome_shake at 160x128, whose frame moves 0.246 px over the capture, kept its J4 ratio at 1.9 on the
    silhouettes of the balls, the cube and the lamp's stand after 8x the first pass's samples at one time per
    half-stratum. ``moving``: the moving region where the caller has it already."""
    scene = renderer.scene_model
    times = np.linspace(t0_s, t1_s, MOVING_REGION_TIMES)
    if frame_motion_px(scene, times, width, height) > 0.0:
        return np.ones((height, width), dtype=bool)
    moving = moving_region(scene, t0_s, t1_s, width, height) if moving is None else moving
    return moving | moving_shadows(renderer, t0_s, t1_s, width, height)
