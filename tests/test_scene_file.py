"""A Mitsuba scene file as the scene (scene.name: mitsuba): loaded as Mitsuba loads it, its emitters grouped and
its shapes moved from the config, rendered as Mitsuba renders it, and keyed in the render cache by every file
it reads."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mbcapture import ConfigError, load_config, run_capture
from mbcapture.config import scene_of
from mbcapture.scene.keyframes import Motion

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "scenes" / "examples" / "table.xml"
TINY = ["render.width=48", "render.height=36", "render.spp=4", "render.cache=off"]


def table(tmp_path: Path, extra: str = "", file: str | None = None) -> Path:
    """A config beside a copy of the example scene (its textures with it), the file named relative to it."""
    scene_dir = tmp_path / "scene"
    if not scene_dir.exists():
        shutil.copytree(TABLE.parent, scene_dir)
    cfg = tmp_path / "table.yaml"
    cfg.write_text(
        f"scene:\n  name: mitsuba\n  file: {file or 'scene/table.xml'}\n  groups: {{flash: flash}}\n{extra}"
        "render: {max_depth: 6}\n"
    )
    return cfg


@pytest.mark.render
def test_the_file_renders_as_mitsuba_renders_it():
    """The ambient and flash groups summed, against Mitsuba's own path tracer on the file (mi.load_file,
    max_depth 6, the same film): block means of 6x6 pixels agree to their Monte Carlo error. Measured at
    1024 spp x 4 seeds: median |relative difference| 0.11 %, median |z| 0.58. Here 512 spp x 2 seeds; the
    glass ball's caustics give the blocks heavy tails, so the bounds are on the median and the image mean."""
    import mitsuba as mi

    from mbcapture.render import Renderer

    w, h = 48, 36
    cfg = load_config(
        ROOT / "configs" / "table_hdr.yaml", [f"render.width={w}", f"render.height={h}", "scene.motion={}"]
    )
    renderer = Renderer.from_config(scene_of(cfg), cfg)
    ours = [renderer.render(0.0, 512, seed).sum(axis=0) for seed in (1, 2)]
    scene = mi.load_file(str(TABLE), width=w, height=h, ceiling=22)
    path = mi.load_dict({"type": "path", "max_depth": 6})
    theirs = [np.array(mi.render(scene, spp=512, integrator=path, seed=seed)) for seed in (1, 2)]

    def blocks(x):
        return np.asarray(x, np.float64).reshape(h // 6, 6, w // 6, 6, 3).mean(axis=(1, 3))

    a, b = np.mean([blocks(x) for x in ours], 0), np.mean([blocks(x) for x in theirs], 0)
    se = np.hypot(*(np.std([blocks(x) for x in runs], 0, ddof=1) / np.sqrt(2) for runs in (ours, theirs)))
    z = (a - b) / np.maximum(se, 1e-12)
    assert abs(a.mean() / b.mean() - 1) < 0.005
    assert np.median(np.abs(z)) < 1.2, np.median(np.abs(z))
    assert np.median(np.abs(a / b - 1)) < 0.01


@pytest.mark.render
def test_a_capture_of_the_file_moves_its_shape_and_switches_its_groups(tmp_path):
    motion = "  motion:\n    metal_ball: {type: linear, velocity_m_s: [-2.0, 0, 0]}\n"
    cfg = load_config(table(tmp_path, motion), [*TINY, "capture.protocol=flash_no_flash"])
    scene = scene_of(cfg)
    assert scene.groups == ("ambient", "flash") and scene.switchable == {"flash"}
    # the ball's box moves 2 cm in 10 ms: its image points shift left
    pts = scene.image_points(np.array([0.0, 0.01]), 48, 36)
    assert np.all(pts[1, :, 0] < pts[0, :, 0] - 0.5)
    result = run_capture(cfg, tmp_path / "out", progress=False)
    assert result.moving_mask.any() and not result.moving_mask.all()
    assert np.isfinite(result.reads_dn).all()
    flash, noflash = (result.reads_expected_e[i].mean() for i in range(2))
    assert flash > 1.2 * noflash  # the flash read saw the spot light as well


def test_ids_that_are_not_in_the_file_are_named_with_the_ones_that_are(tmp_path):
    with pytest.raises(
        ConfigError, match=r"scene.groups: 'bulb' is not the id of an emitter in .*table.xml \(those:.*flash"
    ):
        scene_of(load_config(table(tmp_path), ["scene.groups={bulb: flash}"]))
    with pytest.raises(ConfigError, match=r"scene.motion: 'wood' is not the id of a shape, a spot light or"):
        scene_of(load_config(table(tmp_path), ["scene.motion={wood: {type: linear}}"]))


def test_a_missing_or_broken_file_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"scene.file: .*nothere.xml: no such file"):
        scene_of(load_config(table(tmp_path, file="nothere.xml")))
    broken = tmp_path / "broken.xml"
    broken.write_text("<scene version='3.0.0'><shape type='sphere'>")
    with pytest.raises(ConfigError, match=r"broken.xml: Mitsuba cannot parse it"):
        scene_of(load_config(table(tmp_path, file="broken.xml")))


def test_the_file_is_relative_to_the_config_and_set_values_to_the_working_directory(tmp_path, monkeypatch):
    cfg = load_config(table(tmp_path))
    assert cfg.scene.model_extra["file"] == str(tmp_path / "scene" / "table.xml")
    monkeypatch.chdir(tmp_path / "scene")
    cfg = load_config(table(tmp_path), ["scene.file=table.xml"])
    assert scene_of(cfg).build.file.path == str(tmp_path / "scene" / "table.xml")


def test_the_render_cache_key_follows_the_file_its_texture_and_its_parameters(tmp_path):
    from mbcapture.render import Renderer
    from mbcapture.render.cache import RenderCache

    cache = RenderCache(tmp_path / "cache", 10**9)

    def identity(overrides=()):
        cfg = load_config(table(tmp_path), [*TINY, "render.cache=on", *overrides])
        return Renderer.from_config(scene_of(cfg), cfg, cache=cache).identity

    first = identity()
    assert identity() == first
    assert identity(["scene.parameters={ceiling: 30}"]) != first
    texture = tmp_path / "scene" / "textures" / "label.png"
    texture.write_bytes(texture.read_bytes() + b"\0")  # another file (PNG readers stop at IEND)
    changed = identity()
    assert changed != first
    xml = tmp_path / "scene" / "table.xml"
    xml.write_text(xml.read_text().replace('value="0.6, 0.6, 0.58"', 'value="0.5, 0.6, 0.58"'))
    assert identity() not in (first, changed)


def test_mbcapture_scenes_lists_the_ids_of_a_file():
    proc = subprocess.run(
        [sys.executable, "-m", "mbcapture", "scenes", str(TABLE), "--param", "ceiling=5"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = {line.split()[0]: line for line in proc.stdout.splitlines()[1:-1]}
    assert "scene.motion" in lines["metal_ball"] and "scene.groups" in lines["flash"]
    assert "scene.groups" in lines["ceiling_panel"]  # an area light: its shape's id
    assert "wood.png" in proc.stdout.splitlines()[-1]


def test_keyframes_pass_through_their_poses_and_named_motions_keep_their_period():
    m = Motion(
        type="keyframes",
        keyframes=[{"t": 0.0}, {"t": 1.0, "translate": [1, 0, 0], "angle_deg": 90, "axis": [0, 0, 1]}],
        interpolation="smooth",
    )
    np.testing.assert_allclose(m.matrix(0.0), np.eye(4), atol=1e-12)
    end = m.matrix(1.0)
    np.testing.assert_allclose(end[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 90 deg about z
    np.testing.assert_allclose(end[:3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(m.matrix(0.5)[:3, 3], [0.5, 0, 0], atol=1e-12)  # smoothstep(0.5) = 0.5
    assert m.matrix(0.25)[0, 3] == pytest.approx(0.15625)  # smoothstep(0.25), slower than linear at the start
    np.testing.assert_allclose(m.matrix(2.0), end)  # held after the last pose
    orbit = Motion(type="orbit", axis=[0, 1, 0], centre=[1, 0, 0], period_s=0.5)
    np.testing.assert_allclose(orbit.matrix(0.5), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(orbit.matrix(0.25) @ [0, 0, 0, 1], [2, 0, 0, 1], atol=1e-12)  # half a turn
    swing = Motion(type="pendulum", axis=[0, 0, 1], pivot=[0, 1, 0], amplitude_deg=30, period_s=2.0)
    tip = swing.matrix(0.5) @ [0, 0, 0, 1]  # a quarter period: the full amplitude
    assert np.degrees(np.arctan2(tip[0], 1 - tip[1])) == pytest.approx(30.0)
    with pytest.raises(ValueError, match="times must ascend"):
        Motion(type="keyframes", keyframes=[{"t": 1.0}, {"t": 0.5}])


@pytest.mark.render
def test_lights_of_the_file_move_through_their_own_transform(tmp_path):
    """The flash (a spot) swung about the camera's axis and the ceiling panel (an area light) lowered: each
    group's image changes over time as its light moves, and a moving light refused where it cannot move."""
    from mbcapture.render import Renderer

    motion = (
        "  motion:\n"
        "    flash: {type: orbit, axis: [0, 0, 1], centre: [0, 0.26, 0.62], period_s: 0.04}\n"
        "    ceiling_panel: {type: linear, velocity_m_s: [0, -30.0, 0]}\n"
    )
    cfg = load_config(table(tmp_path, motion), [*TINY, "render.spp=16"])
    scene = scene_of(cfg)
    assert set(scene.build.file.moving_lights) == {"flash", "ceiling_panel"} and not scene.build.file.moving
    renderer = Renderer.from_config(scene, cfg)
    at = {t: renderer.render(t, 64, 1) for t in (0.0, 0.01)}
    ambient, flash = scene.groups.index("ambient"), scene.groups.index("flash")
    # the panel 30 cm lower lights the table more (inverse square); the spot, turned a quarter, lights elsewhere
    assert at[0.01][ambient].mean() > 1.3 * at[0.0][ambient].mean()
    assert np.abs(at[0.01][flash] - at[0.0][flash]).mean() > 0.3 * at[0.0][flash].mean()
    np.testing.assert_array_equal(renderer.render(0.0, 64, 1), at[0.0])  # and back: a pose is a function of time
    with pytest.raises(ConfigError, match=r"scene.motion: 'sun' is not the id of a shape, a spot light or"):
        sun = tmp_path / "scene" / "sun.xml"
        sun.write_text(
            (tmp_path / "scene" / "table.xml")
            .read_text()
            .replace(
                "</scene>",
                '<emitter type="directional" id="sun"><vector name="direction" value="0,-1,0"/></emitter></scene>',
            )
        )
        scene_of(load_config(table(tmp_path, "  motion:\n    sun: {type: linear}\n", file="scene/sun.xml")))
