"""The lens (mbcapture.scene.optics): the diffraction OTF of a circular aperture and its application."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mbcapture.scene.optics import apply_diffraction, diffraction_otf


def test_the_otf_of_a_circular_aperture_by_hand():
    # nu = f lambda N: 1 at DC, (2/pi)(acos nu - nu sqrt(1 - nu^2)) below the cutoff, 0 beyond it
    lam_nm, N = 550.0, 4.0
    cutoff = 1.0 / (lam_nm * 1e-6 * N)  # cycles per mm
    f = np.array([0.0, 0.5 * cutoff, cutoff, 2 * cutoff])
    want = [1.0, (2 / math.pi) * (math.acos(0.5) - 0.5 * math.sqrt(0.75)), 0.0, 0.0]
    assert diffraction_otf(f, lam_nm, N) == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("f_number,cycles_per_px", [(2.8, 0.25), (8.0, 0.25), (8.0, 0.4)])
def test_a_sine_target_keeps_the_contrast_the_otf_says(f_number, cycles_per_px):
    """Vertical stripes at a known frequency: the contrast after the filter over the contrast before is
    the OTF at that frequency (fit of a sine of that frequency over the interior, away from the mirrored
    borders); per channel at its own wavelength. Measured agreement 3e-7; tolerance 1e-5 (a wrong
    frequency scale or OTF formula misses by orders of magnitude)."""
    W, H, pitch_um = 256, 32, 5.6
    x = np.arange(W)
    phase = 2 * np.pi * cycles_per_px * x
    img = np.broadcast_to((1.0 + 0.5 * np.cos(phase))[None, :, None], (H, W, 3)).copy()
    lam = [610.0, 540.0, 465.0]
    out = apply_diffraction(img, pitch_um, f_number, lam)
    inner = slice(48, W - 48)
    basis = np.stack([np.ones(W), np.cos(phase), np.sin(phase)], axis=1)[inner]
    f_mm = cycles_per_px / (pitch_um * 1e-3)
    for c in range(3):
        coef, *_ = np.linalg.lstsq(basis, out[H // 2, inner, c], rcond=None)
        contrast = math.hypot(coef[1], coef[2]) / 0.5
        assert coef[0] == pytest.approx(1.0, abs=1e-4)  # the mean is kept (measured within 1.4e-5)
        assert contrast == pytest.approx(float(diffraction_otf(f_mm, lam[c], f_number)), abs=1e-5)


def test_a_flat_field_stays_flat_and_the_wavelengths_must_match_the_channels():
    flat = np.full((2, 20, 24, 3), 3.0)
    assert np.allclose(apply_diffraction(flat, 5.6, 2.8, [600.0, 550.0, 450.0]), 3.0, rtol=1e-12)
    with pytest.raises(ValueError, match="wavelength_nm"):
        apply_diffraction(flat, 5.6, 2.8, [550.0])


@pytest.mark.render
def test_the_renderer_blurs_every_render_by_the_otf():
    """camera.diffraction: each render is the diffraction-free one filtered by apply_diffraction."""
    from mbcapture.scene import scenes
    from mbcapture.render import Renderer
    from mbcapture.sensor import SensorConfig

    scene = scenes.make_scene("colour_chart", scenes.load_module("colour_chart").Params(shake_amplitude_m=0.0))
    sensor = SensorConfig(f_number=11.0)
    sharp = Renderer(scene, 48, 36, sensor=sensor).render(0.0, 4, 1)
    blurred = Renderer(scene, 48, 36, sensor=sensor, diffraction=True).render(0.0, 4, 1)
    want = apply_diffraction(sharp, sensor.pixel_pitch_um, sensor.f_number, sensor.wavelength_nm)
    assert np.allclose(blurred, want, rtol=1e-5, atol=1e-6 * float(sharp.max()))
    assert np.abs(blurred - sharp).max() > 1e-3 * float(sharp.max())  # it did blur


# ----------------------------------------------------------------------------- depth of field
def _edge_scene(depth_m: float):
    """A lit half-plane x >= 0 at ``depth_m`` in front of a camera looking down -z: a vertical edge
    through the image centre, radiance 1."""
    from mbcapture.render.build import Light, SceneBuild, Shape, scale, translate
    from mbcapture.scene.scenes import Camera, SceneModel

    half = 10.0 * depth_m
    plane = Shape(
        "plane",
        "rectangle",
        translate(half, 0.0, -depth_m) @ scale(half, half, 1.0),
        None,
        Light("edge", (1.0, 1.0, 1.0)),
    )
    camera = Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=30.0)
    return SceneModel(
        name="edge",
        groups=("edge",),
        switchable=frozenset(),
        camera=camera,
        build=SceneBuild(shapes=(plane,)),
        params=None,
        motion_points=None,
    )


def _edge_model(width: int, radius_px: float) -> np.ndarray:
    """The edge's pixel values a defocus disk of ``radius_px`` gives: the lit share of a disk centred at
    each point, averaged over each pixel's box (the render's pixel filter), by quadrature."""
    x = (np.arange(width) + 0.5) - width / 2  # pixel centres; the edge is at 0
    sub = x[:, None] + (np.arange(64) + 0.5)[None, :] / 64 - 0.5  # points across each pixel
    if radius_px == 0:
        return (sub > 0).mean(axis=1)
    u = np.clip(sub / radius_px, -1.0, 1.0)  # lit share of a disk whose centre is u radii right of the edge
    share = 0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / np.pi
    return share.mean(axis=1)


@pytest.mark.render
@pytest.mark.parametrize("focus_m,radius_px", [(1.0, 0.0), (0.5, 5.0), (2.0, 2.5)])
def test_a_thin_lens_blurs_an_edge_by_the_analytic_defocus_disk(focus_m, radius_px):
    """Through focus: the edge at 1 m, the lens focused at 1 m (sharp), 0.5 m and 2 m. The aperture is
    chosen so that the disk is 5 px at focus 0.5 m; optics.blur_radius_px must say the radius, and the
    rendered edge (mean of its rows, 256 spp) must match the disk's lit share averaged over each pixel,
    within 0.02 everywhere (Monte Carlo noise ~0.004; a disk 20 % too small or large misses by 0.03+)."""
    from mbcapture.scene.optics import blur_radius_px
    from mbcapture.render import Renderer

    W, H = 96, 24
    scene = _edge_scene(1.0)
    px_tangent = 2 * math.tan(math.radians(30.0) / 2) / W
    aperture = 5.0 * px_tangent / abs(1 / 0.5 - 1 / 1.0)
    assert blur_radius_px(scene.camera, W, aperture, focus_m, 1.0) == pytest.approx(radius_px, rel=1e-9)
    img = Renderer(scene, W, H, max_depth=1, thin_lens=(aperture, focus_m)).render(0.0, 256, 3)[0, ..., 1]
    edge = img.mean(axis=0)
    assert np.abs(edge - _edge_model(W, radius_px)).max() < 0.02
    if radius_px:  # a wrong radius is caught
        assert np.abs(edge - _edge_model(W, 1.2 * radius_px)).max() > 0.02
        assert np.abs(edge - _edge_model(W, radius_px / 1.2)).max() > 0.02


def test_the_thin_lens_follows_the_config(tmp_path):
    """camera.lens thin: aperture f / 2N with f from the field of view and the sensor's width, focus at
    the look-at distance unless set; camera.focal_length_mm sets the field of view; the lens is part of
    the renderer's identity (its render-cache key)."""
    from pathlib import Path

    from mbcapture import load_config
    from mbcapture.config import scene_of
    from mbcapture.scene.optics import focal_length_m, focus_distance_m
    from mbcapture.render import Renderer
    from mbcapture.render.cache import RenderCache

    hdr = Path(__file__).resolve().parents[1] / "configs" / "metronome_hdr.yaml"
    small = ["render.width=64", "render.height=48"]
    cfg = load_config(hdr, [*small, "camera.lens=thin"])
    scene = scene_of(cfg)
    cache = RenderCache(tmp_path, max_bytes=1 << 30)
    r = Renderer.from_config(scene, cfg, cache=cache)
    f = focal_length_m(scene.camera, 64, cfg.sensor.pixel_pitch_um)
    assert f == pytest.approx(64 * 5.6e-6 / 2 / math.tan(math.radians(scene.camera.fov_deg) / 2))
    assert r.thin_lens == pytest.approx((f / (2 * 2.8), focus_distance_m(scene.camera)))
    focused = Renderer.from_config(
        scene, load_config(hdr, [*small, "camera.lens=thin", "camera.focus_distance_m=0.7"]), cache=cache
    )
    assert focused.thin_lens[1] == 0.7
    pinhole = Renderer.from_config(scene, load_config(hdr, small), cache=cache)
    assert pinhole.thin_lens is None
    assert len({pinhole.identity, r.identity, focused.identity}) == 3
    wide = scene_of(load_config(hdr, [*small, "camera.focal_length_mm=0.25"]))
    assert wide.camera.fov_deg == pytest.approx(math.degrees(2 * math.atan(64 * 5.6e-3 / 2 / 0.25)))


# ----------------------------------------------------------------------------- distortion
def _forward_px(xu, yu, k, t, W, H):
    """Independent of the code: where the ray of normalized pinhole position (xu, yu) lands on the
    sensor, in pixels, under radial distortion k (Brown-Conrady), the field spanning [-t, t] across."""
    r2 = xu * xu + yu * yu
    s = 1 + sum(ki * r2 ** (i + 1) for i, ki in enumerate(k))
    return (xu * s / t + 1) * W / 2 - 0.5, (yu * s / (t * H / W) + 1) * H / 2 - 0.5


@pytest.mark.parametrize("k", [(-0.2, 0.05), (0.15,), (-0.1, 0.0, 0.02)])
def test_a_spot_lands_where_the_distortion_polynomial_sends_its_ray(k):
    """A small Gaussian spot rendered (pinhole) at a known ray ends up, after apply_distortion, with its
    centroid where the forward polynomial puts that ray, within 0.05 px."""
    from dataclasses import dataclass

    from mbcapture.scene.optics import apply_distortion, undistortion_maps

    @dataclass
    class Cam:
        fov_deg: float = 40.0

    W, H = 160, 120
    mx, my, t_r = undistortion_maps(Cam(), W, H, k)
    t = math.tan(math.radians(20.0))
    assert t_r >= t and (t_r > t) == (k[0] < 0)  # barrel needs a wider render, pincushion does not
    for xu, yu in [(0.2, 0.1), (-0.25, 0.15), (0.05, -0.2)]:
        cx, cy = (xu / t_r + 1) * W / 2 - 0.5, (yu / (t_r * H / W) + 1) * H / 2 - 0.5  # the spot in the render
        yy, xx = np.mgrid[0:H, 0:W]
        spot = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 1.5**2)).astype(np.float32)
        out = apply_distortion(np.repeat(spot[None, :, :, None], 3, -1), mx, my)[0, ..., 0].astype(np.float64)
        want = _forward_px(xu, yu, k, t, W, H)
        got = ((out * xx).sum() / out.sum(), (out * yy).sum() / out.sum())
        assert abs(got[0] - want[0]) < 0.05 and abs(got[1] - want[1]) < 0.05, (got, want)


def test_the_taps_and_the_reach_are_the_lens_filters_own():
    """What render_pixels reaches through the lens: bilinear_taps' four pixels and weights give apply_distortion's
    value of every sensor pixel (to cv2.remap's 1/32 fixed-point weights); diffraction_reach is the linear filter's
    weight of each neighbour over the centre's (a delta through apply_diffraction without its clamp), symmetric."""
    from dataclasses import dataclass

    from mbcapture.scene.optics import apply_distortion, bilinear_taps, diffraction_reach, undistortion_maps

    @dataclass
    class Cam:
        fov_deg: float = 40.0

    mx, my, _ = undistortion_maps(Cam(), 40, 30, (-0.2, 0.05))
    img = np.random.default_rng(0).random((30, 40, 3)).astype(np.float32)
    index, weight = bilinear_taps(mx, my)
    np.testing.assert_allclose(weight.sum(axis=0), 1.0, atol=1e-6)
    by_taps = (img[..., 0].ravel()[index] * weight).sum(axis=0)
    np.testing.assert_allclose(apply_distortion(img, mx, my)[..., 0], by_taps, atol=1.0 / 32)
    k = diffraction_reach(5.6, 2.8, [610.0, 540.0, 465.0], radius=4)
    delta = np.zeros((129, 129, 3))
    delta[64, 64] = 1.0
    linear = np.abs(apply_diffraction(delta, 5.6, 2.8, [610.0, 540.0, 465.0], clamp=False))[60:69, 60:69]
    np.testing.assert_allclose(k, (linear / linear[4, 4]).max(axis=-1), rtol=0.05, atol=1e-4)
    assert k[4, 4] == 1.0 and k.max() == 1.0 and np.allclose(k, k.T) and np.allclose(k, k[::-1])


def test_no_distortion_is_the_identity_and_a_fold_is_refused():
    from dataclasses import dataclass

    from mbcapture.scene.optics import undistortion_maps

    @dataclass
    class Cam:
        fov_deg: float = 40.0

    mx, my, t_r = undistortion_maps(Cam(), 32, 24, (0.0,))
    assert t_r == pytest.approx(math.tan(math.radians(20.0)))
    np.testing.assert_allclose(mx, np.broadcast_to(np.arange(32.0), (24, 32)), atol=1e-4)
    np.testing.assert_allclose(my, np.broadcast_to(np.arange(24.0)[:, None], (24, 32)), atol=1e-4)
    with pytest.raises(ValueError, match="folds"):
        undistortion_maps(Cam(), 32, 24, (-1.5,))


@pytest.mark.render
def test_a_rendered_straight_edge_bends_as_the_distortion_says():
    """A vertical edge off the axis (x/z = 0.15 at 1 m): with barrel distortion its position in each row
    follows the polynomial (solved here by bisection, independently of OpenCV), within 0.1 px; the
    undistorted render keeps it straight."""
    from mbcapture.render import Renderer

    W, H, k = 96, 64, (-0.3,)
    scene = _edge_scene(1.0)
    # move the edge from x = 0 to x = 0.15 m: the plane is translated along x
    from dataclasses import replace as dc_replace

    from mbcapture.render.build import scale, translate

    plane = scene.build.shapes[0]
    shifted = dc_replace(plane, to_world=translate(0.15 + 10.0, 0.0, -1.0) @ scale(10.0, 10.0, 1.0))
    scene = dc_replace(scene, build=dc_replace(scene.build, shapes=(shifted,)))
    t = math.tan(math.radians(15.0))
    img = Renderer(scene, W, H, max_depth=1, distortion=k).render(0.0, 64, 5)[0, ..., 1]
    for row in (4, 20, 32, 50, 60):
        values = img[row]
        j = int(np.argmax(values > 0.5))  # first lit pixel; the edge crosses 0.5 between j - 1 and j
        edge_px = j - 1 + (0.5 - values[j - 1]) / (values[j] - values[j - 1]) + 0.5  # box pixels: value = lit share
        yd = ((row + 0.5) / H * 2 - 1) * t * H / W
        lo, hi = -1.0, 1.0  # the ray (0.15, yu) that lands on this row: yu (1 + k1 r^2) = yd
        for _ in range(80):
            mid = (lo + hi) / 2
            if mid * (1 + k[0] * (0.15**2 + mid**2)) < yd:
                lo = mid
            else:
                hi = mid
        want_x, _ = _forward_px(0.15, lo, k, t, W, H)
        assert abs(edge_px - (want_x + 0.5)) < 0.1, (row, edge_px, want_x + 0.5)


def test_distortion_keys_are_checked_and_pinhole_truth_applications_refuse_it():
    from pathlib import Path

    from mbcapture import load_config
    from mbcapture.errors import ConfigError

    configs = Path(__file__).resolve().parents[1] / "configs"
    assert load_config(configs / "metronome_hdr.yaml", ["camera.distortion=[-0.1, 0.01]"]).camera.distortion == [
        -0.1,
        0.01,
    ]
    with pytest.raises(ConfigError, match="distortion: expected 1 to 3"):
        load_config(configs / "metronome_hdr.yaml", ["camera.distortion=[0.1, 0.1, 0.1, 0.1]"])
    for name in ("multi_flash", "structured_light", "flash_matting"):
        with pytest.raises(ConfigError, match=f"camera.distortion: the {name} application"):
            load_config(configs / f"{name}.yaml", ["camera.distortion=[-0.1]"])
