"""Scene modules metronome and flatfield fulfil the contract of mbcapture.scene.scenes (no Mitsuba)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from mbcapture.errors import ConfigError
from mbcapture.render.build import SceneBuild
from mbcapture.scene.scenes import SceneModel, available, load_module, make_scene

SCENES = ("metronome", "flatfield")
UNIT_WORDS = ("_bpm", "_deg", "_s", "_m", "scale", "radiance", "model")


@pytest.mark.parametrize("name", SCENES)
def test_contract(name):
    assert name in available()
    mod = load_module(name)
    assert isinstance(mod.DESCRIPTION, str) and "\n" not in mod.DESCRIPTION
    with pytest.raises(ValidationError):
        mod.Params(not_a_key=1)
    for key, f in mod.Params.model_fields.items():
        assert f.description, key
        assert not f.is_required(), key
        assert any(u in key for u in UNIT_WORDS), f"{key}: units belong in the name"
    sc = make_scene(name, mod.Params())
    assert isinstance(sc, SceneModel) and sc.name == name
    assert isinstance(sc.build, SceneBuild)
    assert set(sc.build.emitter_groups()) <= set(sc.groups)
    assert sc.switchable <= set(sc.groups)
    assert sc.default_film == (640, 512)


def test_unknown_scene_lists_valid_ones():
    with pytest.raises(ConfigError, match="metronome"):
        make_scene("no_such_scene", None)


def test_flatfield_is_static():
    mod = load_module("flatfield")
    sc = make_scene("flatfield", mod.Params(radiance=[2.0, 3.0, 4.0]))
    assert sc.is_static and sc.groups == ("field",) and sc.switchable == frozenset()
    assert sc.extra["radiance"] == (2.0, 3.0, 4.0)
    with pytest.raises(ValidationError):
        mod.Params(radiance=[1.0, 2.0])
    with pytest.raises(ValidationError):
        mod.Params(radiance=[1.0, -2.0, 1.0])


def test_metronome_groups_and_motion():
    mod = load_module("metronome")
    sc = make_scene("metronome", mod.Params())
    assert sc.groups == ("ambient", "lamp", "flash") and sc.switchable == frozenset({"flash"})
    t = np.linspace(0.0, 2.0, 4001)
    pts = sc.motion_points(t)
    assert pts.ndim == 3 and pts.shape[0] == t.size and pts.shape[2] == 3 and pts.shape[1] >= 4
    # the tracked points move rigidly about the pivot: distances between them are constant
    d = np.linalg.norm(pts[:, 1] - pts[:, -1], axis=-1)
    np.testing.assert_allclose(d, d[0], rtol=1e-12)
    # the needle's period is the tempo's: 120 bpm -> 1 s
    a, b = sc.motion_points(np.array([0.3, 1.3]))
    np.testing.assert_allclose(a, b, atol=1e-9)
    # everything stays in view, and the S moves ~100-400 px/s on the default film
    w, h = sc.default_film
    px = sc.camera.project(pts, w, h)
    assert np.all((px[..., 0] > 0) & (px[..., 0] < w) & (px[..., 1] > 0) & (px[..., 1] < h))
    speed = np.linalg.norm(np.diff(px, axis=0), axis=-1) / np.diff(t)[:, None]
    assert 100.0 <= speed.max() <= 400.0
    # tempo and amplitude change the motion; the sine model is close at 30 degrees
    slow = make_scene("metronome", mod.Params(tempo_bpm=60.0))
    assert np.linalg.norm(slow.motion_points(np.array([0.5]))[0, 1] - pts[0, 1]) > 1e-3
    sine = make_scene("metronome", mod.Params(motion_model="sine"))
    dev = np.abs(sine.motion_points(t) - pts).max()
    assert 0 < dev < 0.01


def test_metronome_needle_transform_matches_motion_points():
    mod = load_module("metronome")
    sc = make_scene("metronome", mod.Params(phase_s=0.17))
    f = sc.build.parts["needle"]
    times = np.array([0.0, 0.21, 0.77])
    pts = sc.motion_points(times)
    # recover the part-frame points at t=0 and map them with the part transform at other times
    local = np.linalg.solve(f(0.0), np.c_[pts[0], np.ones(len(pts[0]))].T)
    for i, t in enumerate(times):
        np.testing.assert_allclose((f(t) @ local)[:3].T, pts[i], atol=1e-12)


def test_radiance_scales():
    mod = load_module("metronome")
    sc = make_scene("metronome", mod.Params(lamp_scale=2.0, flash_scale=0.0))
    lights = {s.name: s.light for s in sc.build.shapes if s.light is not None}
    assert lights["lamp_bulb"].radiance[0] == pytest.approx(2 * mod.LAMP_RADIANCE)
    assert lights["flash_led"].radiance == (0.0, 0.0, 0.0)
    assert {light.group for light in lights.values()} == {"ambient", "lamp", "flash"}
