"""Guides (render.guide_fraction, SceneBuild.guides): a share of the bounces sent towards a small, brightly
lit patch changes the noise, never the expected image, and lowers the noise of the light that patch
reflects (integrator.guided_lambertian)."""

import numpy as np
import pytest

from mbcapture.errors import ConfigError
from mbcapture.render.build import Guide, Light, Material, SceneBuild, Shape, frame_towards, rotate, scale, translate
from mbcapture.render.settings import guide_shares
from mbcapture.scene.scenes import Camera, SceneModel, load_module, make_scene

W, H = 24, 16


def _patch_scene(distance_m: float) -> SceneModel:
    """A grey wall the camera sees; in front of it a small bulb 1.5 cm above a white disk (the bright patch,
    lit some 100x brighter than the wall) and a guide around the disk. ``distance_m``: from the wall to the
    patch (far: the guide's cone at the wall is narrow, where a float32 cosine would misplace its samples)."""
    up = rotate((1, 0, 0), -np.pi / 2)  # canonical +z normal -> +y
    patch = np.array([0.0, -0.1, distance_m - 0.3])
    shapes = (
        Shape("wall", "rectangle", translate(0.0, 0.0, -0.3) @ scale(0.5), Material((0.6, 0.6, 0.6))),
        Shape("disk", "disk", translate(*patch) @ up @ scale(0.02), Material((0.8, 0.8, 0.8))),
        Shape(
            "bulb",
            "sphere",
            translate(*(patch + [0.0, 0.025, 0.0])) @ scale(0.008),
            None,
            Light("lamp", (2000.0, 2000.0, 2000.0)),
        ),
        Shape(
            "fill",
            "rectangle",
            frame_towards((0.0, 0.6, 0.6), (0.0, 0.0, -0.3)) @ scale(0.3),
            None,
            Light("fill", (0.2, 0.2, 0.2)),
        ),
    )
    camera = Camera(origin=(0.0, 0.0, 0.9), target=(0.0, 0.0, -0.3), up=(0.0, 1.0, 0.0), fov_deg=30.0)
    return SceneModel(
        name="patch",
        groups=("lamp", "fill"),
        switchable=frozenset(),
        camera=camera,
        build=SceneBuild(shapes=shapes, guides=(Guide(tuple(patch), 0.022, 0.02),)),
        params=None,
        motion_points=lambda t: np.zeros((len(t), 0, 3)),
    )


@pytest.mark.render
@pytest.mark.parametrize("distance_m", [0.25, 1.2])
def test_guided_bounces_keep_the_image_and_lower_the_patch_light_noise(mitsuba_ready, distance_m):
    """K seeds of guided (a high fraction, 0.3, so that a wrong density would show) and of plain renders:
    per 8x8-pixel block and channel a Welch t statistic of their means, bounded by Student's t quantile
    at a family-wise false-alarm rate of 1e-3 over the blocks (Bonferroni), and the whole-image means
    alike. Blocks of many samples: a plain wall pixel finds the disk's light in a rare sample, so its own
    mean is skewed and its spread over K seeds too, and a few samples per block would make the statistic
    meaningless. The wall's variance (over the seeds, the mean over its pixels) must fall at least 2x."""
    from scipy import stats

    from mbcapture.render import Renderer

    scene = _patch_scene(distance_m)
    k, spp = 16, 256
    renders = {}
    for fraction in (0.0, 0.3):
        r = Renderer(scene, W, H, guide_fraction=fraction)
        renders[fraction] = np.stack(
            [r.render(0.0, spp, seed=0, pattern=(1000 * (fraction > 0) + i, 0)).sum(axis=0) for i in range(k)]
        ).astype(np.float64)
    plain, guided = renders[0.0], renders[0.3]
    blocks = lambda x: x.reshape(k, H // 8, 8, W // 8, 8, 3).mean(axis=(2, 4))  # noqa: E731
    limit = lambda n: stats.t.ppf(1 - 1e-3 / (2 * n), 2 * (k - 1))  # noqa: E731
    se = lambda a, b: np.sqrt(a.var(axis=0, ddof=1) / k + b.var(axis=0, ddof=1) / k)  # noqa: E731
    z = (blocks(guided).mean(axis=0) - blocks(plain).mean(axis=0)) / np.maximum(
        se(blocks(guided), blocks(plain)), 1e-12
    )
    assert np.max(np.abs(z)) < limit(z.size), np.max(np.abs(z))
    whole = lambda x: x.mean(axis=(1, 2))  # noqa: E731
    z_all = (whole(guided).mean(axis=0) - whole(plain).mean(axis=0)) / se(whole(guided), whole(plain))
    assert np.all(np.abs(z_all) < limit(3)), z_all
    var_plain, var_guided = plain.var(axis=0).mean(axis=-1), guided.var(axis=0).mean(axis=-1)
    # not the disk or the bulb, chosen by the guided mean: the plain one is raised where a seed found the disk
    wall = guided.mean(axis=(0, 3)) < np.percentile(guided.mean(axis=(0, 3)), 80)
    gain = var_plain[wall].mean() / var_guided[wall].mean()
    assert gain > 2.0, gain


def test_a_guide_checks_its_sphere_and_share():
    with pytest.raises(ValueError, match="radius"):
        Guide((0.0, 0.0, 0.0), 0.0, 0.02)
    with pytest.raises(ValueError, match="centre"):
        Guide((0.0, np.nan, 0.0), 0.1, 0.02)
    for share in (0.0, -0.1, 0.6, np.nan):
        with pytest.raises(ValueError, match="Guide.share"):
            Guide((0.0, 0.0, 0.0), 0.1, share)
    assert Guide((0, 1, 2), 1, 0.5).centre == (0.0, 1.0, 2.0)
    with pytest.raises(ValueError, match="add up to 0.6"):
        SceneBuild(shapes=(), guides=(Guide((0, 0, 0), 0.1, 0.3), Guide((1, 0, 0), 0.1, 0.3)))


def test_the_fraction_scales_the_scenes_shares_together():
    guides = (Guide((0, 0, 0), 0.1, 0.02), Guide((1, 0, 0), 0.2, 0.1), Guide((2, 0, 0), 0.1, 0.03))
    assert guide_shares(guides, None) == (0.02, 0.1, 0.03)
    assert guide_shares(guides, 0.3) == pytest.approx((0.04, 0.2, 0.06))
    assert guide_shares(guides, 0.0) == (0.0, 0.0, 0.0)
    assert guide_shares((), None) == () and guide_shares((), 0.2) == ()
    for bad in (-0.01, 0.51):
        with pytest.raises(ConfigError, match="render.guide_fraction"):
            guide_shares(guides, bad)


@pytest.mark.render
def test_the_fraction_is_part_of_the_render_identity_and_needs_lambertian_materials(mitsuba_ready, tmp_path):
    from mbcapture.render import Renderer
    from mbcapture.render.cache import RenderCache

    scene = make_scene("metronome", load_module("metronome").Params())
    own = tuple(g.share for g in scene.build.guides)
    assert len(own) == 3, "the metronome declares its lamp stand's guide and the bulb's two spots"
    cache = RenderCache(tmp_path, 1 << 20)
    ids = {f: Renderer(scene, W, H, cache=cache, guide_fraction=f).identity for f in (0.0, 0.02, 0.05, None)}
    assert len(set(ids.values())) == 4
    assert Renderer(scene, W, H, cache=cache, guide_fraction=sum(own)).identity == ids[None]
    with pytest.raises(ConfigError, match="render.guide_fraction"):
        Renderer(scene, W, H, guide_fraction=0.6)
    r = Renderer(scene, W, H, guide_fraction=None)
    r._ensure_loaded()
    assert [g[2] for g in r._integrator.guides] == list(own)
    assert [g[:2] for g in r._integrator.guides] == [(g.centre, g.radius) for g in scene.build.guides]
    r._integrator.lambertian = False
    with pytest.raises(ConfigError, match="Lambertian"):
        r._guides()


@pytest.mark.render
@pytest.mark.parametrize("where", ["near", "far", "narrow", "too_narrow", "grazing", "inside", "below"])
def test_the_mixture_weights_integrate_the_lambertian_lobe(mitsuba_ready, where):
    """The guided bounce's weight is the BSDF value over the mixture's density, so over its own samples it
    averages to the integral of the value: the albedo over the hemisphere, and over the cone of the guide
    the albedo times the cone's projected solid angle / pi (by quadrature). N independent draws: each
    bound is 5 standard errors of the mean (the weights' own spread). A density off by 10 % in the cone,
    or a cosine lobe not scaled by its share, moves one of them by more than that; and a guide seen under
    less than 0.01 rad gets no share (the rule that keeps float32 rounding out of the cone's test)."""
    import drjit as dr
    import mitsuba as mi

    from mbcapture.render import Renderer
    from mbcapture.render.integrator import guided_lambertian

    Renderer(_patch_scene(0.25), 4, 4)  # sets the variant
    centre = {
        "near": (0.0, 0.0, 0.2),
        "far": (0.0, 0.3, 1.2),
        "grazing": (0.3, 0.0, 0.02),
        "narrow": (2.0, 1.0, 3.3),
        "too_narrow": (0.0, 6.0, 8.0),  # seen under 0.0125 and 0.005 rad
        "inside": (0.0, 0.0, 0.01),
        "below": (0.0, 0.0, -0.2),
    }[where]
    radius, share, albedo, n = 0.05, 0.3, 0.7, 1 << 20
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(0.0, 0.0, 0.0)
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    eval_pdf, sample = guided_lambertian(si, mi.Color3f(albedo), mi.Float(1.0), (((centre), radius, share),))
    rng = np.random.default_rng(7)
    u = mi.Point2f(*(mi.Float(rng.random(n, dtype=np.float32)) for _ in range(2)))
    wo, pdf, weight, _ = sample(mi.Float(0.0), u, mi.Bool(True))
    value, pdf_again = eval_pdf(wo, mi.Bool(True))
    w = np.asarray(weight[0], np.float64)
    d = np.array([np.asarray(wo.x), np.asarray(wo.y), np.asarray(wo.z)]).T.astype(np.float64)
    np.testing.assert_allclose(np.asarray(pdf_again), np.asarray(pdf), rtol=1e-5)
    se = lambda x: x.std() / np.sqrt(n)  # noqa: E731
    assert abs(w.mean() - albedo) < 5 * se(w) + 1e-6, (w.mean(), se(w))
    # the cone: directions within asin(radius / distance) of the centre, on the hemisphere
    c = np.asarray(centre) / np.linalg.norm(centre)
    sin2 = radius**2 / np.dot(centre, centre)
    in_cone = np.linalg.norm(np.cross(d, c), axis=1) ** 2 <= sin2
    in_cone &= d @ c > 0
    # the cone's projected solid angle by quadrature: (theta, phi) about the cone's axis
    t = np.linspace(0, np.arcsin(min(sin2, 1.0) ** 0.5), 801)
    p = np.linspace(0, 2 * np.pi, 1601)
    tt, pp = np.meshgrid(t, p, indexing="ij")
    e1 = np.cross(c, [1.0, 0.0, 0.0] if abs(c[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    dirs = np.cos(tt)[..., None] * c + np.sin(tt)[..., None] * (np.cos(pp)[..., None] * e1 + np.sin(pp)[..., None] * e2)
    integrand = np.clip(dirs[..., 2], 0, None) * np.sin(tt) / np.pi
    cone_share = np.trapezoid(np.trapezoid(integrand, p, axis=1), t)
    wc = np.where(in_cone, w, 0.0)
    assert abs(wc.mean() - albedo * cone_share) <= 5 * se(wc) + 1e-4 * albedo * cone_share, (
        wc.mean(),
        albedo * cone_share,
        se(wc),
    )
    # how often a direction lands in the cone: the cone's share where it applies, plus the cosine lobe's
    applies = where not in ("inside", "below", "too_narrow")  # inside its sphere, under the horizon, < 0.01 rad
    expected = (share if applies else 0.0) + (1.0 - (share if applies else 0.0)) * cone_share
    assert abs(np.mean(in_cone) - expected) <= 5 * np.sqrt(expected * (1 - expected) / n) + 1e-6, (
        np.mean(in_cone),
        expected,
    )
