"""mbcapture.render.shadows: where the moving parts' hard shadows fall (adaptive sampling treats those pixels as
it treats the moving parts': a render's time within its stratum is noise there)."""

from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config
from mbcapture.scene.camera_motion import moving_region
from mbcapture.capture.pipeline import prepare
from mbcapture.render import Renderer
from mbcapture.render.shadows import changing_region, moving_shadows

ROOT = Path(__file__).resolve().parents[1]
W, H = 80, 64


def renderer_of(name: str, *extra: str, width: int = W, height: int = H):
    cfg = load_config(
        ROOT / "configs" / f"{name}.yaml",
        [f"render.width={width}", f"render.height={height}", "render.cache=off", *extra],
    )
    scene, timeline, _, _ = prepare(cfg)
    span = float(timeline.seconds(timeline.start_tick)), float(timeline.seconds(timeline.end_tick))
    return scene, Renderer.from_config(scene, cfg, max_depth=2), span


@pytest.mark.render
def test_the_light_that_changes_over_the_capture_lies_where_the_parts_move_or_cast_their_shadows():
    """multi_flash's LEDs alone (its soft ambient light left out), direct light only, rendered at the capture's
    first and last instants with the same samples: every pixel whose value changes by more than 2 % lies in the
    moving region or the moving shadows; the moving region alone misses many of them (the sliding box's shadows
    on the wall), and the shadows cover them without taking in the film."""
    scene, r, (t0, t1) = renderer_of("multi_flash", "scene.slide_frequency_hz=20")  # a long sweep: wide shadows
    flashes = [g for g in scene.groups if g.startswith("flash_")]
    a, b = (r.render(t, 64, 7, flashes).sum(axis=(0, 3)) for t in (t0, t1))
    changed = np.abs(b - a) > 0.02 * np.maximum(np.maximum(a, b), 1e-3 * a.max())
    moving = moving_region(scene, t0, t1, W, H)
    shadows = moving_shadows(r, t0, t1, W, H)
    assert changed.sum() > 50
    missed = changed & ~(moving | shadows)
    assert missed.sum() == 0, np.argwhere(missed)[:10]
    assert (changed & ~moving).sum() > 20  # what the moving region alone does not hold
    assert (shadows & ~moving).sum() < 0.25 * W * H


@pytest.mark.render
def test_a_still_scene_and_a_shaken_camera():
    """No moving part: no shadow moves. A camera shaken by more than camera_motion.FRAME_MOTION_PX (metronome_shake at
    640x512 moves its frame by about a pixel; at 160x128 by a quarter, under it): every pixel changes."""
    scene, r, (t0, t1) = renderer_of("multi_flash", "scene.slide_amplitude_m=0")
    assert scene.is_static and not moving_shadows(r, t0, t1, W, H).any()
    scene, r, (t0, t1) = renderer_of("metronome_shake", width=640, height=512)
    assert moving_shadows(r, t0, t1, 640, 512).all()


@pytest.mark.render
def test_where_the_time_is_noise():
    """changing_region: the moving region and the moving shadows together; every pixel where the camera moves at all,
    even by less than camera_motion.FRAME_MOTION_PX (metronome_shake at 160x128 moves its frame by 0.246 px: the
    applications' moving region is then the needle alone, but every edge in the image moves)."""
    from mbcapture.scene.camera_motion import FRAME_MOTION_PX, frame_motion_px

    scene, r, (t0, t1) = renderer_of("multi_flash")
    np.testing.assert_array_equal(
        changing_region(r, t0, t1, W, H), moving_region(scene, t0, t1, W, H) | moving_shadows(r, t0, t1, W, H)
    )
    scene, r, (t0, t1) = renderer_of("metronome_shake", width=160, height=128)
    assert 0 < frame_motion_px(scene, np.linspace(t0, t1, 64), 160, 128) < FRAME_MOTION_PX
    assert not moving_region(scene, t0, t1, 160, 128).all()
    assert changing_region(r, t0, t1, 160, 128).all()
