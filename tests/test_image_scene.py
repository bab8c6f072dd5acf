"""A photograph as the scene (scene.name: image): its radiance as stored (EXR, .hdr) or linearised (PNG),
row 0 at the top, scaled to a stated luminance, and moving as the config says."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from mbcapture import ConfigError, load_config, run_capture
from mbcapture.config import scene_of

SIZE = ["render.width=32", "render.height=24", "render.spp=4", "render.cache=off"]


def write_exr(path: Path, img: np.ndarray) -> Path:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": img.astype(np.float32)}) as f:
        f.write(str(path))
    return path


def marked(h: int = 48, w: int = 64) -> np.ndarray:
    """Left half 0.5, right half 4, a red band over the top 6 rows."""
    img = np.full((h, w, 3), 0.5, np.float32)
    img[:, w // 2 :] = 4.0
    img[:6] = [8.0, 0.0, 0.0]
    return img


def render(overrides: list[str]) -> np.ndarray:
    from mbcapture.render import Renderer

    cfg = load_config(None, ["scene.name=image", *SIZE, *overrides])
    return Renderer.from_config(scene_of(cfg), cfg).render(0.0, 16, 1)[0]


@pytest.mark.render
def test_the_image_is_seen_as_stored_row_zero_at_the_top(tmp_path):
    """The plane fills a film of the image's aspect (overscan 1): each pixel averages 2 x 2 texels."""
    exr = write_exr(tmp_path / "m.exr", marked())
    got = render([f"scene.file={exr}", "scene.overscan=1.0", "scene.radiance_scale=2.0"])
    np.testing.assert_allclose(got[0, 4], [16.0, 0.0, 0.0], rtol=1e-5)  # the red band, at the top
    np.testing.assert_allclose(got[12, 2], [1.0, 1.0, 1.0], rtol=1e-5)  # left, dark
    np.testing.assert_allclose(got[12, 29], [8.0, 8.0, 8.0], rtol=1e-5)  # right, bright


@pytest.mark.render
def test_a_png_is_linearised_and_scaled_to_the_target_luminance(tmp_path):
    png = tmp_path / "grey.png"
    Image.fromarray(np.full((24, 32, 3), 128, np.uint8)).save(png)
    linear = ((128 / 255 + 0.055) / 1.055) ** 2.4  # 0.2158: the sRGB decoding
    got = render([f"scene.file={png}", "scene.overscan=1.0"])
    np.testing.assert_allclose(got, linear, rtol=1e-5)
    got = render([f"scene.file={png}", "scene.overscan=1.0", "scene.target_luminance_cd_m2=50"])
    np.testing.assert_allclose(683.0 * got.mean(), 50.0, rtol=1e-5)


@pytest.mark.render
def test_a_panning_image_is_a_moving_scene(tmp_path):
    exr = write_exr(tmp_path / "m.exr", marked())
    cfg = load_config(None, ["scene.name=image", f"scene.file={exr}", "scene.velocity=[2.0, 0.0]", *SIZE])
    scene = scene_of(cfg)
    pts = scene.image_points(np.array([0.0, 0.01]), 32, 24)
    np.testing.assert_allclose(pts[1, :, 0] - pts[0, :, 0], 0.02 * 32, rtol=1e-6)  # 2 view widths/s for 10 ms
    result = run_capture(cfg, progress=False)
    assert result.moving_mask.any() and np.isfinite(result.images["radiance"]).all()


def test_bad_image_input_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"scene.file: .*\.txt: expected .exr, .hdr, .png or .jpg"):
        scene_of(load_config(None, ["scene.name=image", f"scene.file={tmp_path / 'a.txt'}"]))
    broken = tmp_path / "b.exr"
    broken.write_bytes(b"not an exr")
    with pytest.raises(ConfigError, match=r"scene.file: .*b.exr: corrupt or unreadable OpenEXR"):
        scene_of(load_config(None, ["scene.name=image", f"scene.file={broken}"]))
    with pytest.raises(ConfigError, match="radiance_scale or target_luminance_cd_m2, not both"):
        load_config(
            None, ["scene.name=image", "scene.file=x.exr", "scene.radiance_scale=2", "scene.target_luminance_cd_m2=5"]
        )


@pytest.mark.render
def test_a_radiance_hdr_file_is_read_as_stored(tmp_path):
    import cv2

    img = marked()
    path = tmp_path / "m.hdr"
    assert cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]))  # OpenCV writes BGR
    got = render([f"scene.file={path}", "scene.overscan=1.0"])
    np.testing.assert_allclose(got[0, 4], [8.0, 0.0, 0.0], rtol=0.01)  # RGBE keeps 8 bits of mantissa
    np.testing.assert_allclose(got[12, 29], [4.0, 4.0, 4.0], rtol=0.01)
