"""Camera shake: the trajectory model, projection through a moving camera, strata that follow the
frame's motion, the moving region, and the renderer (pose per render time, render cache keys)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mbcapture.scene import camera_motion as cm
from mbcapture import load_config
from mbcapture.scene import scenes
from mbcapture.scene.camera_motion import moving_region
from mbcapture.capture.pipeline import prepare
from mbcapture.errors import ConfigError


def _still_chart(**params):
    return scenes.make_scene("colour_chart", scenes.load_module("colour_chart").Params(shake_amplitude_m=0.0, **params))


def _constant_motion(ry_deg: float = 0.0, rx_deg: float = 0.0, tx_mm: float = 0.0) -> cm.CameraMotion:
    row = [math.radians(rx_deg), math.radians(ry_deg), 0.0, tx_mm * 1e-3, 0.0, 0.0]
    return cm.CameraMotion(cm.FileTrajectory("const", np.array([-100.0, 100.0]), np.array([row, row])), "constant")


def test_shake_has_the_configured_rms_and_a_tremor_peak():
    """Over 300 s the sampled offsets' RMS is the configured one. The drift (corner 1 Hz) decorrelates
    in ~1 / (2 pi) s, so 300 s hold ~900 independent samples and the variance's standard error is
    ~5 %; tolerance 5 SE on the variance, ~12 % on the RMS. The spectrum above 3 Hz peaks at the
    tremor frequency."""
    from scipy.signal import welch

    spec = cm.ShakeSpec(rotation_deg=0.1, roll_deg=0.03, translation_mm=0.4, tremor_hz=9.0, seed=4)
    traj = cm.ShakeTrajectory.from_spec(spec)
    t = np.arange(0.0, 300.0, 0.02)
    o = traj.offsets(t)
    expected = np.array([math.radians(0.1)] * 2 + [math.radians(0.03)] + [0.4e-3] * 3)
    assert np.allclose(o.std(axis=0), expected, rtol=0.12)
    f, p = welch(o[:, 1], fs=50.0, nperseg=2048)
    assert abs(f[f > 3][np.argmax(p[f > 3])] - 9.0) < 0.6
    # another seed is another hand; the same seed the same trajectory
    assert not np.allclose(cm.ShakeTrajectory.from_spec(spec.model_copy(update={"seed": 5})).offsets(t[:100]), o[:100])
    assert np.array_equal(cm.ShakeTrajectory.from_spec(spec).offsets(t[:100]), o[:100])


def test_still_pose_projects_like_the_scene_camera_and_a_yaw_shifts_the_image():
    scene = scenes.make_scene("metronome", scenes.load_module("metronome").Params())
    times = np.linspace(0.0, 0.01, 5)
    pts = np.asarray(scene.motion_points(times))
    zero = dataclasses.replace(scene, camera_motion=_constant_motion())
    assert np.allclose(zero.project(pts, times, 160, 128), scene.camera.project(pts, 160, 128), atol=1e-9)
    # a yaw of d about the camera's up axis moves the image centre by f tan(d) px, f = W / 2 / tan(fov / 2);
    # Mitsuba's camera x points to the image's left, so a positive yaw turns the view left: the image moves right
    d = 0.5
    yawed = dataclasses.replace(scene, camera_motion=_constant_motion(ry_deg=d))
    centre = np.asarray(scene.camera.target, float)[None, None]
    shift = yawed.project(centre, times[:1], 160, 128) - scene.camera.project(centre, 160, 128)
    f = 80 / math.tan(math.radians(scene.camera.fov_deg) / 2)
    assert shift[0, 0, 0] == pytest.approx(f * math.tan(math.radians(d)), rel=1e-6)
    assert abs(shift[0, 0, 1]) < 1e-9


def test_strata_follow_the_shake_of_a_static_scene():
    """A static scene is one stratum; shaken, the planner cuts it so that no reference point of the
    frame moves more than render.max_motion_px inside a stratum."""
    base = [
        "render.width=160",
        "render.height=128",
        "render.spp=2",
        "scene.name=colour_chart",
        "scene.shake_amplitude_m=0",
        "capture.protocol=burst",
        "capture.periods=1",
        "capture.unit_exposure_s=0.02",
        "app.name=burst",
    ]
    still = load_config(None, base)
    _, _, plan0, _ = prepare(still)
    assert plan0.passes == 1
    cfg = load_config(None, [*base, "camera.shake={rotation_deg: 0.3, seed: 1}"])
    scene, tl, plan, _ = prepare(cfg)
    assert scene.camera_motion is not None and not scene.is_static
    assert plan.passes > 4
    for a, b in zip(plan.starts_ticks, plan.ends_ticks):
        t = np.linspace(float(tl.seconds(a)), float(tl.seconds(b)), 200)
        px = scene.image_points(t, 160, 128)
        step = np.linalg.norm(np.diff(px, axis=0), axis=-1).sum(axis=0)  # path length of each point
        assert step.max() <= cfg.render.max_motion_px * 1.02
    assert plan.motion_px_total > 2.0


def test_moving_region_is_the_whole_frame_once_the_frame_moves():
    scene = _still_chart()
    assert not moving_region(scene, 0.0, 0.05, 32, 24).any()
    shaken = cm.apply(scene, cm.CameraSection(shake=cm.ShakeSpec(rotation_deg=0.5)))
    assert moving_region(shaken, 0.0, 0.05, 32, 24).all()
    tiny = cm.apply(scene, cm.CameraSection(shake=cm.ShakeSpec(rotation_deg=1e-5, roll_deg=0, translation_mm=0)))
    assert not moving_region(tiny, 0.0, 0.05, 32, 24).any()


def test_trajectory_file_is_read_interpolated_and_checked(tmp_path):
    good = tmp_path / "traj.csv"
    good.write_text("time_s,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm\n0,0,0,0,0,0,0\n0.1,1,2,3,4,5,6\n")
    motion = cm.from_config(cm.CameraSection(trajectory_file=str(good)))
    o = motion.offsets([0.05])[0]
    assert np.allclose(o, [math.radians(0.5), math.radians(1.0), math.radians(1.5), 2e-3, 2.5e-3, 3e-3])
    with pytest.raises(ConfigError, match="camera.trajectory_file: .* covers scene times 0..0.1 s"):
        motion.offsets([0.2])
    for text, msg in [
        ("t,a\n0,0\n", "expected the header"),
        ("time_s,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm\n0,0,0,0,0,0,0\n0,1,1,1,1,1,1\n", "must increase"),
        ("time_s,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm\n0,0,0,0,0,0,x\n1,0,0,0,0,0,0\n", "not numbers"),
    ]:
        bad = tmp_path / "bad.csv"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=f"camera.trajectory_file: .*{msg}"):
            cm.from_config(cm.CameraSection(trajectory_file=str(bad)))
    with pytest.raises(ConfigError, match="camera.shake and camera.trajectory_file are exclusive"):
        load_config(None, ["camera.shake={}", f"camera.trajectory_file={good}"])
    # a capture outside the file's times fails before anything renders
    with pytest.raises(ConfigError, match="covers scene times"):
        prepare(
            load_config(
                None, [f"camera.trajectory_file={good}", "capture.start_s=1", "render.width=16", "render.height=12"]
            )
        )


@pytest.mark.render
def test_renderer_moves_the_camera_and_keys_the_cache_by_its_pose(tmp_path):
    """A constant yaw shifts the rendered image as the projection says (phase correlation of a
    textured chart, 64x48); renders at another camera pose are never read back from the cache; a new
    pose recompiles nothing, the camera's transform being opaque (checked in a fresh process)."""
    import cv2

    from mbcapture.render import Renderer
    from mbcapture.render.cache import RenderCache

    cache = RenderCache(tmp_path / "cache", 10**9)
    still = _still_chart(ambient_irradiance_w_m2=1.0)
    yawed = dataclasses.replace(still, camera_motion=_constant_motion(ry_deg=0.4))
    W, H = 64, 48
    r0 = Renderer(still, W, H, cache=cache)
    r1 = Renderer(yawed, W, H, cache=cache)
    a = r0.render(0.0, 16, 1, ["ambient"])[0].mean(-1)
    b = r1.render(0.0, 16, 1, ["ambient"])[0].mean(-1)
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float32), b.astype(np.float32))
    centre = np.asarray(still.camera.target, float)[None, None]
    expected = yawed.project(centre, np.zeros(1), W, H)[0, 0] - still.camera.project(centre, W, H)[0, 0]
    assert dx == pytest.approx(expected[0], abs=0.1) and abs(dy) < 0.1
    assert expected[0] > 1.0  # a real shift, not a rounding of 0

    # the cache: the same scene, time, samples and seed with another camera pose is a miss
    def shake(seed):
        return cm.apply(still, cm.CameraSection(shake=cm.ShakeSpec(rotation_deg=0.3, seed=seed)))

    ra, rb = Renderer(shake(1), W, H, cache=cache), Renderer(shake(2), W, H, cache=cache)
    assert ra.state_at(0.01) != rb.state_at(0.01) and ra.state_at(0.01) != ra.state_at(0.02)
    misses = cache.stats.misses
    ia = ra.render(0.01, 4, 3, ["ambient"])
    ib = rb.render(0.01, 4, 3, ["ambient"])
    assert cache.stats.misses == misses + 2 and not np.array_equal(ia, ib)
    again = ra.render(0.01, 4, 3, ["ambient"])
    assert cache.stats.misses == misses + 2 and ra.last_cached and np.array_equal(again, ia)  # the same pose: read back
    assert _fresh_kernels_for_a_new_pose() == 0


#: Run in a fresh process: a shaken camera renders at one pose (compiling its kernels), then at
#: another with the kernel history on; prints the kernels compiled for the second pose.
_NEW_POSE_PROBE = """
import drjit as dr
from mbcapture.scene import camera_motion as cm, scenes
from mbcapture.render import Renderer
chart = scenes.make_scene("colour_chart", scenes.load_module("colour_chart").Params(shake_amplitude_m=0.0,
                                                                                   ambient_irradiance_w_m2=1.0))
r = Renderer(cm.apply(chart, cm.CameraSection(shake=cm.ShakeSpec(rotation_deg=0.3, seed=1))), 64, 48, cache=None)
r.render(0.01, 4, 3, ["ambient"])
dr.set_flag(dr.JitFlag.KernelHistory, True)
dr.kernel_history()
r.render(0.03, 4, 3, ["ambient"])
print(sum(1 for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit")))
"""


def _fresh_kernels_for_a_new_pose() -> int:
    """Kernels compiled for a render at a new camera pose, after one render at another pose, in a
    process of its own: the precondition (this renderer's kernels compiled once, nothing else in the
    kernel cache) is then the same whatever ran before in the test process."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _NEW_POSE_PROBE], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return int(proc.stdout.strip().splitlines()[-1])


def test_natural_vignetting_is_cos4_of_the_field_angle():
    """By hand: the field angle of a pixel centre from the horizontal field of view; 1 on the axis,
    symmetric, cos^4 in the corners."""
    from mbcapture.scene.optics import natural_vignetting

    cam = _still_chart().camera
    W, H = 40, 30
    v = natural_vignetting(cam, W, H)
    assert v.shape == (H, W) and np.allclose(v, v[::-1]) and np.allclose(v, v[:, ::-1])
    t = math.tan(math.radians(cam.fov_deg) / 2)
    x, y = 1 - 1 / W, (1 - 1 / H) * H / W  # the corner pixel's centre, normalized
    assert v[0, 0] == pytest.approx(math.cos(math.atan(math.hypot(x, y) * t)) ** 4, rel=1e-12)
    assert v.max() == pytest.approx(1.0, abs=5e-3) and v.min() == v[0, 0]


@pytest.mark.render
def test_vignetting_darkens_every_render_by_the_analytic_falloff():
    """A flat field through the renderer with camera.vignetting cos4 is the pinhole's image times
    cos^4 of each pixel's field angle, to float32 precision; exposures and truths use the same
    renderer, so they agree."""
    from mbcapture.scene.optics import natural_vignetting
    from mbcapture.render import Renderer

    scene = scenes.make_scene("flatfield", scenes.load_module("flatfield").Params())
    W, H = 32, 24
    flat = Renderer(scene, W, H).render(0.0, 4, 1)
    dim = Renderer(scene, W, H, vignetting="cos4").render(0.0, 4, 1)
    want = natural_vignetting(scene.camera, W, H)[None, :, :, None]
    assert np.allclose(dim, flat * want, rtol=2e-7, atol=0) and dim.min() < 0.9 * flat.max()
    with pytest.raises(ConfigError, match="camera.vignetting"):
        Renderer(scene, W, H, vignetting="cos3")
