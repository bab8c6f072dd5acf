"""The planner: strata follow image motion, weights are exact, unused groups are left out."""

import numpy as np
import pytest

from mbcapture import protocols
from mbcapture.config import RenderSection, config_from_dict
from mbcapture.plan import make_plan
from mbcapture.scenes import Camera, SceneModel

CAM = Camera(origin=(0, 0, -10), target=(0, 0, 0), up=(0, 1, 0), fov_deg=40)


def point_scene(speed_m_per_s: float | None, groups=("ambient", "flash"), switchable=frozenset({"flash"})):
    motion = None
    if speed_m_per_s is not None:
        motion = lambda t: np.stack([np.asarray(t) * speed_m_per_s, 0 * np.asarray(t), 0 * np.asarray(t)], -1)[:, None, :]
    return SceneModel("test", groups, switchable, CAM, build=None, params=None, motion_points=motion)


def timeline(**capture):
    cfg = config_from_dict({"scene": {"name": "flatfield"}, "capture": capture})
    return protocols.build(cfg)


def plan(scene, tl, **render):
    return make_plan(tl, scene, RenderSection(width=160, height=128, **render), np.random.default_rng(0))


def test_camera_projects_centre_and_scale():
    W, H = 160, 128
    px = CAM.project(np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]), W, H)
    assert px[0] == pytest.approx([80, 64])
    f = W / 2 / np.tan(np.radians(20))  # focal length in pixels
    assert abs(px[1, 0] - 80) == pytest.approx(f / 10)  # 1 m at 10 m
    assert px[2, 1] == pytest.approx(64 - f / 10)  # up is up in the image (y grows downwards)


def test_static_scene_is_one_pass_whatever_the_periods():
    for periods in (1, 64, 10**5):
        p = plan(point_scene(None), timeline(periods=periods))
        assert p.passes == 1
        assert p.weights_s.sum() == pytest.approx(8e-3 * 1, rel=1e-12)  # 8T of ambient over 4 buckets


def test_doubling_speed_doubles_strata():
    tl = timeline(periods=16)
    n1 = plan(point_scene(50.0), tl).passes
    n2 = plan(point_scene(100.0), tl).passes
    assert n1 >= 5
    assert abs(n2 / n1 - 2) < 0.15


def test_strata_respect_max_motion():
    tl = timeline(periods=16)
    scene = point_scene(100.0)
    p = plan(scene, tl, max_motion_px=0.25)
    for a, b in zip(p.starts_ticks, p.ends_ticks):
        ts = np.linspace(float(tl.seconds(a)), float(tl.seconds(b)), 50)
        px = CAM.project(scene.motion_points(ts), 160, 128)[:, 0, 0]
        assert px.max() - px.min() <= 0.25 * 1.01
    # independent of the interleaving frequency: strata follow motion, not slots
    assert plan(scene, timeline(periods=1024), max_motion_px=0.25).passes == p.passes


def test_unused_emitter_group_is_never_rendered():
    p = plan(point_scene(None), timeline())
    assert p.groups == ("ambient",) and p.left_out_groups == ("flash",)
    assert p.weights_s.shape[-1] == 1


def test_sequential_gaps_are_not_rendered():
    tl = timeline(periods=4, sequential=True)
    p = plan(point_scene(100.0), tl, max_motion_px=1.0)
    intervals = tl.collecting_intervals()
    assert len(intervals) == 4
    for a, b in zip(p.starts_ticks, p.ends_ticks):  # every stratum inside one frame
        assert any(s <= a and b <= e for s, e in intervals)
    assert p.weights_s.sum(axis=(0, 2)) == pytest.approx([1e-3, 2e-3, 4e-3, 8e-3], rel=1e-12)


def test_render_times_are_inside_their_strata():
    tl = timeline(periods=16)
    p = plan(point_scene(100.0), tl)
    assert np.all(p.times_s >= tl.seconds(p.starts_ticks)) and np.all(p.times_s < tl.seconds(p.ends_ticks))


def test_max_strata_coarsens_and_says_so():
    p = plan(point_scene(500.0), timeline(periods=16), max_strata=8)
    assert p.passes == 8 and p.coarsened and "coarsened" in p.notes[0]
