"""The projector emitter (render/build.py Projector, Mitsuba's ``projector``): its pattern lands where
the projector's pinhole geometry says, with the documented irradiance, and it moves with its part."""

import numpy as np
import pytest

from mbcapture.scene import projective as pj
from mbcapture.errors import ConfigError
from mbcapture.render.build import (
    Material,
    Projector,
    SceneBuild,
    Shape,
    rotate,
    scale,
    translate,
)
from mbcapture.scene.scenes import Camera, SceneModel

pytestmark = pytest.mark.render

CAM = Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0)
W, H = 32, 24
ALBEDO = 0.8


def _scene(projector: Projector, wall_to_world: np.ndarray, parts=None) -> SceneModel:
    wall = Shape("wall", "rectangle", wall_to_world, Material((ALBEDO,) * 3))
    return SceneModel(
        name="projector_test",
        groups=(projector.group,),
        switchable=frozenset(),
        camera=CAM,
        build=SceneBuild(shapes=(wall,), parts=parts or {}, projectors=(projector,)),
        params=None,
    )


def test_look_at_frame_matches_mitsuba():
    from mbcapture.render import ensure_llvm

    ensure_llvm()
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    p = Projector("p", "g", (0.2, -0.1, 1.3), (0.0, 0.05, 0.0), (0.0, 1.0, 0.0), 30.0, np.ones((2, 2, 3)))
    want = np.asarray(
        mi.ScalarTransform4f().look_at(origin=list(p.origin), target=list(p.target), up=list(p.up)).matrix
    )
    np.testing.assert_allclose(p.to_world(), want, atol=1e-6)


def test_irradiance_on_a_perpendicular_wall_is_the_image_over_z_squared():
    """A uniform image E0 from 0.8 m onto a wall perpendicular to the axis: radiance rho E0 / (pi z^2)."""
    from mbcapture.render import Renderer

    e0 = 2.0
    proj = Projector(
        "proj", "pattern", (0.0, 0.0, 0.8), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 50.0, np.full((6, 8, 3), e0)
    )
    sc = _scene(proj, scale(2.0, 2.0, 1.0))
    img = Renderer(sc, W, H, max_depth=2).render(0.0, 4, 1)[0]
    # the projector's 50 deg field covers the camera's 40 deg one from closer: every pixel is lit
    np.testing.assert_allclose(img, ALBEDO * e0 / (np.pi * 0.8**2), rtol=2e-3)


def test_projected_stripe_lands_where_the_geometry_says():
    """A 3-texel bright stripe, projected from 15 cm beside the camera onto a wall turned by 25 deg: in
    every camera row the stripe's centroid is where the projector's column plane meets the camera ray."""
    from mbcapture.render import Renderer

    tw, th, col = 32, 24, 11  # stripe over texture columns 11..13, centre 12.5
    image = np.zeros((th, tw, 3))
    image[:, col : col + 3] = 3.0
    proj_cam = Camera((0.15, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0)
    proj = Projector("proj", "pattern", proj_cam.origin, proj_cam.target, proj_cam.up, proj_cam.fov_deg, image)
    wall = rotate((0, 1, 0), np.radians(25)) @ scale(1.5, 1.5, 1.0)
    img = Renderer(_scene(proj, wall), W, H, max_depth=2).render(0.0, 64, 3)[0].mean(-1)
    excess = img  # dark elsewhere (max_depth 2: no interreflection off the single wall)
    rows = [r for r in range(H) if excess[r].max() > 0.5 * excess.max()]
    assert len(rows) >= H // 2
    measured = np.array([(excess[r] * (np.arange(W) + 0.5)).sum() / excess[r].sum() for r in rows])
    # prediction: camera pixel-row centres; the wall's depth along each camera ray meets the
    # projector's column plane u = col + 1.5 (the stripe's centre)
    n_wall, o = rotate((0, 1, 0), np.radians(25))[:3, 2], np.zeros(3)
    xs = np.linspace(0, W, 2001)
    pred = []
    for r in rows:
        d = pj.pixel_rays(CAM, xs, np.full_like(xs, r + 0.5), W, H)
        z = ((o - np.asarray(CAM.origin)) @ n_wall) / (d @ n_wall)
        x = np.asarray(CAM.origin) + z[:, None] * d
        u = proj_cam.project(x, tw, th)[:, 0]
        pred.append(np.interp(col + 1.5, u, xs) if u[-1] > u[0] else np.interp(col + 1.5, u[::-1], xs[::-1]))
    # a texel is ~1.1 camera px here, so a half-texel error in the mapping would be ~0.55 px; the
    # bound leaves room for the box pixels' centroid bias (~0.06 px) and pixel-sampling noise
    err = measured - np.asarray(pred)
    assert abs(err.mean()) < 0.1 and np.abs(err).max() < 0.2, err


def test_projector_moves_with_its_part_and_rejects_spectral():
    from mbcapture.render import Renderer

    image = np.zeros((8, 8, 3))
    image[:, 3:5] = 4.0
    proj = Projector("proj", "pattern", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 20.0, image, part="rig")
    sc = _scene(proj, scale(1.5, 1.5, 1.0), parts={"rig": lambda t: translate(0.1 * t, 0.0, 0.0)})
    r = Renderer(sc, W, H, max_depth=2)
    a, b = (r.render(t, 4, 0)[0].mean(-1) for t in (0.0, 1.0))
    ca, cb = ((m.sum(0) * (np.arange(W) + 0.5)).sum() / m.sum() for m in (a, b))
    # 0.1 m sideways at 1 m: the camera's 40 deg field is 0.728 m over 32 px, so 4.40 px
    assert cb - ca == pytest.approx(0.1 / (2 * np.tan(np.radians(20)) / W), abs=0.15)
    with pytest.raises(ConfigError, match="RGB variants only"):
        Renderer(sc, W, H, variant="llvm_ad_spectral", film_curves=(np.array([400.0, 700.0]), np.ones((3, 2))))
