"""Ground-truth geometry images from Mitsuba's ``aov`` integrator: depth and normals at pixel centres.

Used by applications for truths that radiance cannot give (depth edges, mattes). Each render
is one sample per pixel at the pixel's centre (a ``stratified`` sampler without jitter and a
box filter), so a pixel's value is the surface seen through its centre, never a mix of two
surfaces across an edge.

Measured on Mitsuba 3.9.1: the ``depth`` AOV is the ray parameter ``t`` from the ray's origin,
which the perspective sensor places on the near-clip plane (``near_clip / cos(theta)`` along
the ray from the lens, theta the angle to the optical axis). :func:`render_depth` adds that
back, so ``distance_m`` is the Euclidean distance from the lens centre and ``z_m`` the depth
along the optical axis (``distance * cos(theta)``); pixels that see no surface are ``inf``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The renderer's perspective sensor uses this near clip (see :class:`~mbcapture.render.Renderer`).
NEAR_CLIP_M = 1e-3


@dataclass(frozen=True)
class DepthImage:
    """distance_m, z_m: (H, W) float64; inf where the pixel's centre ray hits nothing."""

    distance_m: np.ndarray
    z_m: np.ndarray
    time_s: float


def pixel_cosines(camera, width: int, height: int) -> np.ndarray:
    """(H, W) cosine of the angle between each pixel-centre ray and the optical axis
    (pinhole with horizontal field of view ``camera.fov_deg``, square pixels)."""
    tan_half = np.tan(np.radians(camera.fov_deg) / 2)
    x = ((np.arange(width) + 0.5) / width * 2 - 1) * tan_half
    y = ((np.arange(height) + 0.5) / height * 2 - 1) * tan_half * height / width
    return 1.0 / np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def _centre_sensor(renderer):
    mi = renderer.mitsuba
    cam = renderer.scene_model.camera
    return mi.load_dict(
        {
            "type": "perspective",
            "fov": float(cam.fov_deg),
            "fov_axis": "x",
            "near_clip": NEAR_CLIP_M,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=list(cam.origin), target=list(cam.target), up=list(cam.up)
            ),
            "film": {"type": "hdrfilm", "width": renderer.width, "height": renderer.height, "rfilter": {"type": "box"}},
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        }
    )


def _centre_aov(renderer, t_s: float, aovs: str, kind: str, channels: "int | slice") -> np.ndarray:
    """The ``aov`` integrator's channels ``aovs`` (the film's ``channels``) through every pixel's
    centre of ``renderer``'s scene at scene time ``t_s`` (cached by the renderer's cache under ``kind``)."""
    mi = renderer.mitsuba

    def make() -> np.ndarray:
        renderer.set_time(t_s)
        kernels = renderer.__dict__.setdefault("_aov_cache", {})
        key = (renderer.width, renderer.height, aovs)
        if key not in kernels:
            kernels[key] = (_centre_sensor(renderer), mi.load_dict({"type": "aov", "aovs": aovs}))
        sensor, integrator = kernels[key]
        model = renderer.scene_model
        if model.camera_motion is not None:  # the centre sensor follows the handheld camera too
            params = mi.traverse(sensor)
            import drjit as dr

            tf = mi.Transform4f(model.camera_motion.world_from_camera(model.camera, [float(t_s)])[0])
            dr.make_opaque(tf)
            params["to_world"] = tf
            params.update()
        return np.asarray(
            mi.render(renderer.mitsuba_scene, sensor=sensor, integrator=integrator, spp=1, seed=0), dtype=np.float32
        )[..., channels]

    # the renderer's cache (if any) keeps it: the key holds the scene, its pose at t_s and this kind
    return np.asarray(renderer.cached(kind, t_s, {}, make), dtype=np.float64)


def render_normals(renderer, t_s: float) -> np.ndarray:
    """(H, W, 3) world-space unit shading normals through every pixel's centre at scene time ``t_s``;
    zero where the centre ray hits nothing."""
    return _centre_aov(renderer, t_s, "nn:sh_normal", "normal_aov_centre", np.s_[-3:])


def render_depth(renderer, t_s: float) -> DepthImage:
    """Depth through every pixel's centre of ``renderer``'s scene at scene time ``t_s`` (s).

    Moves the scene with ``renderer.set_time(t_s)`` (no kernel recompile), then renders
    ``renderer.mitsuba_scene`` with ``aov`` (``depth``) from a sensor identical to the
    renderer's camera but sampling pixel centres.
    """
    t = _centre_aov(renderer, t_s, "dd.y:depth", "depth_aov_centre", np.s_[-1])
    cos = pixel_cosines(renderer.scene_model.camera, renderer.width, renderer.height)
    hit = t > 0
    distance = np.where(hit, t + NEAR_CLIP_M / cos, np.inf)
    return DepthImage(distance_m=distance, z_m=distance * cos, time_s=float(t_s))
