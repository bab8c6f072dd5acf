"""mbcapture.render: LLVM selection (no Mitsuba), and rendering tests (marked ``render``).

Rendering tests use tiny films and few samples; statistical comparisons use independent
seed replicates, so their tolerances follow from the Monte Carlo error actually measured.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mbcapture.errors import EnvironmentProblem
from mbcapture.render import llvm
from mbcapture.render.build import (
    Light,
    Material,
    SceneBuild,
    Shape,
    frame_towards,
    rotate,
    scale,
    translate,
)
from mbcapture.scene.scenes import Camera, SceneModel, load_module, make_scene

REPO = Path(__file__).resolve().parents[1]


# -- LLVM selection: fake library directories ---------------------------------------------------
def _fake_libs(root: Path, names: dict[str, str | None]) -> Path:
    """Create files (value None) or symlinks (value = target name) in ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    for name, target in names.items():
        if target is None:
            (root / name).write_bytes(b"\x7fELF")
    for name, target in names.items():
        if target is not None:
            (root / name).symlink_to(target)
    return root


@pytest.mark.parametrize(
    "name, version",
    [
        ("libLLVM-19.so", 19),
        ("libLLVM-14.0.6.so.1", 14),
        ("libLLVM-15.so.1", 15),
        ("libLLVM.so.19.1", 19),
        ("libLLVM.so.18", 18),
        ("libLLVM.so", None),
        ("libLLVM.so.1", None),
        ("libLLVM-17git.so", 17),
        ("libLLVMCore.a", None),
    ],
)
def test_version_from_name(name, version):
    assert llvm.version_from_name(name) == version


def test_finder_picks_newest_at_least_16(tmp_path):
    a = _fake_libs(
        tmp_path / "x86_64-linux-gnu",
        {
            "libLLVM-14.so.1": None,
            "libLLVM-15.so.1": None,
            "libLLVM-15.so": "libLLVM-15.so.1",
            "libLLVM.so.19.1": None,
            "libLLVM-19.so": "libLLVM.so.19.1",
        },
    )
    b = _fake_libs(tmp_path / "llvm-17" / "lib", {"libLLVM-17.so": None, "libLLVM.so": "libLLVM-17.so"})
    env: dict[str, str] = {}
    v, path = llvm.select_llvm(env, dirs=[str(a), str(tmp_path / "llvm-*" / "lib")], use_ldconfig=False)
    assert v == 19 and Path(path).parent == a and env[llvm.ENV_VAR] == path
    v, path = llvm.select_llvm({}, dirs=[str(b)], use_ldconfig=False)
    assert v == 17


def test_finder_refuses_only_old_llvm(tmp_path):
    a = _fake_libs(
        tmp_path / "lib",
        {
            "libLLVM-14.so.1": None,
            "libLLVM-15.so.1": None,
            "libLLVM-15.so": "libLLVM-15.so.1",
            "libLLVM.so": "libLLVM-15.so",
        },
    )
    env: dict[str, str] = {}
    with pytest.raises(EnvironmentProblem) as err:
        llvm.select_llvm(env, dirs=[str(a)], use_ldconfig=False)
    msg = str(err.value)
    assert "\n" not in msg and "apt-get install libllvm19" in msg and llvm.ENV_VAR in msg
    assert "14, 15" in msg and llvm.ENV_VAR not in env
    with pytest.raises(EnvironmentProblem, match="no libLLVM found"):
        llvm.select_llvm({}, dirs=[str(tmp_path / "empty")], use_ldconfig=False)


def test_preset_env_var_is_checked(tmp_path):
    a = _fake_libs(
        tmp_path / "lib",
        {
            "libLLVM-15.so.1": None,
            "libLLVM.so": "libLLVM-15.so.1",
            "libLLVM.so.19.1": None,
            "libLLVM-19.so": "libLLVM.so.19.1",
            "libfoo.so": None,
        },
    )
    for bad in ("libLLVM-15.so.1", "libLLVM.so"):  # the unversioned name resolves to 15
        with pytest.raises(EnvironmentProblem, match="LLVM 15"):
            llvm.select_llvm({llvm.ENV_VAR: str(a / bad)}, dirs=[], use_ldconfig=False)
    with pytest.raises(EnvironmentProblem, match="cannot tell"):
        llvm.select_llvm({llvm.ENV_VAR: str(a / "libfoo.so")}, dirs=[], use_ldconfig=False)
    with pytest.raises(EnvironmentProblem, match="does not exist"):
        llvm.select_llvm({llvm.ENV_VAR: str(a / "nope.so")}, dirs=[], use_ldconfig=False)
    good = str(a / "libLLVM-19.so")
    assert llvm.select_llvm({llvm.ENV_VAR: good}, dirs=[], use_ldconfig=False) == (19, good)


def test_import_render_does_not_import_mitsuba():
    code = (
        "import sys, mbcapture.render, mbcapture.scene.scenes; "
        "sys.exit(int('mitsuba' in sys.modules or 'drjit' in sys.modules))"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    assert subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO).returncode == 0


# -- rendering ----------------------------------------------------------------------------------
render = pytest.mark.render


def _metronome(**kw) -> SceneModel:
    mod = load_module("metronome")
    return make_scene("metronome", mod.Params(**kw))


def _replicate_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z-scores of mean(a) - mean(b) over axis 0 (replicates), per remaining element."""
    k = a.shape[0]
    se = np.sqrt(a.var(axis=0, ddof=1) / k + b.var(axis=0, ddof=1) / k)
    return (a.mean(axis=0) - b.mean(axis=0)) / np.maximum(se, 1e-12)


@render
def test_flatfield_is_exact(mitsuba_ready):
    from mbcapture.render import Renderer

    mod = load_module("flatfield")
    radiance = [0.25, 1.0, 3.5]
    sc = make_scene("flatfield", mod.Params(radiance=radiance))
    assert sc.is_static and sc.groups == ("field",)
    r = Renderer(sc, 32, 24)
    img = r.render(0.0, spp=3, seed=7)
    assert img.shape == (1, 24, 32, 3) and img.dtype == np.float32
    np.testing.assert_allclose(img[0], np.broadcast_to(radiance, (24, 32, 3)), rtol=1e-5)
    np.testing.assert_allclose(img[0], np.broadcast_to(sc.extra["radiance"], (24, 32, 3)), rtol=1e-5)


@render
@pytest.mark.parametrize("guide_fraction, max_depth", [(0.0, 4), (0.3, 4), (0.0, 2)])
def test_group_images_sum_to_path_traced_image(mitsuba_ready, guide_fraction, max_depth):
    """Sum over groups of the one-pass integrator == Mitsuba's 'path' (unbiased, same depth), with and
    without the metronome's guide (render.guide_fraction; 0.3, well above the default, so that a wrong
    mixture density would show). At max_depth 2 every path ends at its first vertex, whose light the
    integrator then samples alone (the Lambertian scene's last vertex): there the soft box's light that
    the BSDF's samples would have found under MIS is a large share, and weighting the light samples by
    MIS without those BSDF samples would lose it.

    K seeds of each; per 4x4-pixel block and channel, the difference of the replicate means
    is compared with its standard error: a Welch t statistic with about 2 (K - 1) degrees of
    freedom, bounded by Student's t quantile at a family-wise false-alarm rate of 1e-3 over the
    3 x 48 blocks (Bonferroni); the whole-image means likewise over the 3 channels.
    """
    from scipy import stats

    from mbcapture.render import Renderer

    r = Renderer(_metronome(), 32, 24, guide_fraction=guide_fraction, max_depth=max_depth)
    k, spp = 12, 16
    mine = np.stack([r.render(0.05, spp, seed=100 + i).sum(axis=0) for i in range(k)])
    ref = np.stack([r.render_path(0.05, spp, seed=200 + i) for i in range(k)])
    blocks = lambda x: x.reshape(k, 6, 4, 8, 4, 3).mean(axis=(2, 4))  # noqa: E731
    limit = lambda n: stats.t.ppf(1 - 1e-3 / (2 * n), 2 * (k - 1))  # noqa: E731
    z_blocks = _replicate_z(blocks(mine), blocks(ref))
    assert np.max(np.abs(z_blocks)) < limit(z_blocks.size), np.max(np.abs(z_blocks))
    z_all = _replicate_z(mine.mean(axis=(1, 2)), ref.mean(axis=(1, 2)))
    assert np.all(np.abs(z_all) < limit(3)), z_all
    # and the mean agrees to a few percent (guards against a tiny-variance pass)
    np.testing.assert_allclose(mine.mean(axis=(0, 1, 2)), ref.mean(axis=(0, 1, 2)), rtol=0.05)


@render
def test_only_requested_groups_are_rendered(mitsuba_ready):
    import drjit as dr

    from mbcapture.render import Renderer

    r = Renderer(_metronome(), 32, 24)
    assert r.groups == ("ambient", "lamp", "flash") and r.channels == ("R", "G", "B")
    full = r.render(0.0, 4, seed=1)
    assert full.shape == (3, 24, 32, 3)
    flash = r.render(0.0, 4, seed=1, groups=["flash"])
    assert flash.shape == (1, 24, 32, 3)
    swapped = r.render(0.0, 4, seed=1, groups=["flash", "ambient"])
    assert swapped.shape == (2, 24, 32, 3)

    def ops(groups):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        r.render(0.0, 4, seed=2, groups=groups)
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        return max(h.get("operation_count", 0) for h in hist)

    # The render kernel for one group does less work than for all three.
    assert ops(["flash"]) < 0.8 * ops(None)

    # The flash-only output is the image under the flash alone: same expectation as the whole
    # scene rendered by 'path' with the other lights switched off (it would be ~2x brighter if
    # ambient and lamp leaked in), and exactly zero with the flash at zero radiance.
    dark = Renderer(_metronome(ambient_scale=0.0, lamp_scale=0.0), 32, 24)
    k = 6
    mine = np.stack([r.render(0.0, 8, seed=10 + i, groups=["flash"])[0].mean(axis=(0, 1)) for i in range(k)])
    ref = np.stack([dark.render_path(0.0, 8, seed=20 + i).mean(axis=(0, 1)) for i in range(k)])
    assert np.all(np.abs(_replicate_z(mine, ref)) < 4.0)
    off = Renderer(_metronome(flash_scale=0.0), 32, 24)
    assert np.all(off.render(0.0, 2, seed=3, groups=["flash"]) == 0.0)


@render
def test_time_change_does_not_recompile_and_moves_the_needle(mitsuba_ready):
    import drjit as dr

    from mbcapture.render import Renderer

    sc = _metronome()
    w, h = 64, 48
    r = Renderer(sc, w, h)
    r.render(0.0, 4, seed=6)  # compile (a new sample count is a new kernel; a new seed or time is not)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        a = r.render(0.0, 4, seed=5).sum(axis=0)
        t1 = 0.25  # a quarter period at 120 bpm: the needle at its extreme
        b = r.render(t1, 4, seed=5).sum(axis=0)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    compiled = [e for e in hist if e.get("type") == dr.KernelType.JIT and not e.get("cache_hit")]
    assert compiled == []
    # the image changes where the S is, at either time, and far less elsewhere
    diff = np.abs(a - b).mean(axis=-1)
    pts = sc.camera.project(sc.motion_points(np.array([0.0, t1])), w, h).reshape(-1, 2)
    near = np.zeros((h, w), bool)
    for x, y in pts[:, :]:
        near[max(int(y) - 1, 0) : int(y) + 2, max(int(x) - 1, 0) : int(x) + 2] = True
    assert diff[near].mean() > 10 * diff[~near].mean()


def _panels_scene() -> SceneModel:
    """Two panels the camera sees from behind, one one-sided and one two-sided, and one it sees from the
    front, on a floor; a light in front of the panels and one behind them (groups front, back)."""
    away = frame_towards((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))  # a rectangle facing -z, away from the camera
    shapes = (
        Shape(
            "one_sided_back", "rectangle", translate(-0.12, 0.0, 0.0) @ away @ scale(0.05), Material((0.8, 0.5, 0.3))
        ),
        Shape(
            "two_sided_back",
            "rectangle",
            translate(0.0, 0.0, 0.0) @ away @ scale(0.05),
            Material((0.3, 0.7, 0.6), twosided=True),
        ),
        Shape(
            "front",
            "rectangle",
            frame_towards((0.12, 0.0, 0.0), (0.12, 0.0, 1.0)) @ scale(0.05),
            Material((0.6, 0.6, 0.6)),
        ),
        Shape(
            "floor",
            "rectangle",
            translate(0.0, -0.06, 0.0) @ rotate((1, 0, 0), -np.pi / 2) @ scale(0.4),
            Material((0.5, 0.5, 0.5)),
        ),
        Shape(
            "light_front",
            "rectangle",
            frame_towards((0.0, 0.15, 0.3), (0.0, 0.0, 0.0)) @ scale(0.05),
            None,
            Light("front", (20.0, 20.0, 20.0)),
        ),
        Shape(
            "light_back", "sphere", translate(0.0, 0.1, -0.25) @ scale(0.03), None, Light("back", (30.0, 25.0, 20.0))
        ),
    )
    camera = Camera(origin=(0.0, 0.05, 0.6), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=40.0)
    return SceneModel(
        name="panels",
        groups=("front", "back"),
        switchable=frozenset(),
        camera=camera,
        build=SceneBuild(shapes=shapes, parts={}),
        params=None,
        motion_points=lambda t: np.zeros((len(t), 0, 3)),
    )


@render
@pytest.mark.parametrize("scene", ["panels", "metronome", "flash_toy"])
def test_lambertian_shading_is_mitsubas(mitsuba_ready, scene):
    """The integrator's own Lambertian evaluation and sampling (integrator.lambertian_shading) give the
    images Mitsuba's BSDF calls give (general_shading), with the sampler's numbers and the shared
    pattern's: a wrong side, cosine or pdf would move them by far more than float rounding. The panels
    are seen from behind (a one-sided one black there, a two-sided one lit from behind)."""
    from mbcapture.render import Renderer

    sc = _panels_scene() if scene == "panels" else make_scene(scene, load_module(scene).Params())
    r = Renderer(sc, 48, 36)
    r._ensure_loaded()
    assert r._integrator.lambertian
    for pattern in (None, (77, 0)):
        images = []
        for lambertian in (True, False):
            r._integrator.lambertian = lambertian
            images.append(r.render(0.0, 8, seed=3, pattern=pattern))
        fast, general = images
        assert general.max() > 0
        np.testing.assert_allclose(fast, general, rtol=2e-6, atol=2e-6 * float(general.max()))
    if scene == "panels":  # the backs: the one-sided panel reflects nothing there, the two-sided one does
        r._integrator.lambertian = True
        img = r.render(0.0, 16, seed=4).sum(axis=0)
        x_of = lambda wx: int(round(sc.camera.project(np.array([[wx, 0.0, 0.0]]), 48, 36)[0, 0]))  # noqa: E731
        y = int(round(sc.camera.project(np.array([[0.0, 0.0, 0.0]]), 48, 36)[0, 1]))
        assert img[y, x_of(-0.12)].max() == 0.0
        assert img[y, x_of(0.0)].min() > 0.0 and img[y, x_of(0.12)].min() > 0.0


def test_is_lambertian_knows_mitsubas_bsdfs(mitsuba_ready):
    import mitsuba as mi

    from mbcapture.render.integrator import is_lambertian

    mi.set_variant("llvm_ad_rgb")

    def scene(bsdf):
        return mi.load_dict(
            {
                "type": "scene",
                "a": {"type": "sphere", "bsdf": {"type": "diffuse"}},
                "b": {"type": "rectangle", "bsdf": bsdf},
            }
        )

    assert is_lambertian(scene({"type": "diffuse"}))
    assert is_lambertian(scene({"type": "twosided", "material": {"type": "diffuse"}}))
    assert not is_lambertian(scene({"type": "plastic"}))
    assert not is_lambertian(scene({"type": "roughconductor"}))
    assert not is_lambertian(scene({"type": "twosided", "material": {"type": "roughplastic"}}))


def _marker_scene(camera: Camera) -> SceneModel:
    """Three tiny markers, one group each: spheres m0, m1 and a square m2 facing the camera that
    circles about the y axis (a moving rectangle light: the case that recompiles every update
    unless its transform is opaque)."""
    radius = 0.004
    static = {"m0": (0.05, 0.02, -0.03), "m1": (-0.1, -0.06, 0.1)}
    shapes = [
        Shape(n, "sphere", translate(*p) @ scale(radius), None, Light(n, (100.0, 100.0, 100.0)))
        for n, p in static.items()
    ]
    shapes.append(
        Shape(
            "m2",
            "rectangle",
            frame_towards((0.12, 0.05, 0.0), camera.origin) @ scale(radius),
            None,
            Light("m2", (100.0, 100.0, 100.0)),
            part="spin",
        )
    )
    spin = lambda t: rotate((0, 1, 0), 0.5 * t)  # noqa: E731
    points = np.array(list(static.values()) + [(0.12, 0.05, 0.0)])

    def motion_points(times):
        out = np.repeat(points[None], len(times), axis=0)
        for i, t in enumerate(times):
            out[i, 2] = (spin(t) @ np.append(points[2], 1.0))[:3]
        return out

    return SceneModel(
        name="markers",
        groups=("m0", "m1", "m2"),
        switchable=frozenset(),
        camera=camera,
        build=SceneBuild(shapes=tuple(shapes), parts={"spin": spin}),
        params=None,
        motion_points=motion_points,
    )


@render
@pytest.mark.parametrize(
    "camera",
    [
        Camera(origin=(0.1, 0.3, 0.8), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=35.0),
        Camera(origin=(-0.5, 0.2, 0.4), target=(0.02, -0.01, 0.03), up=(0.1, 1.0, 0.2), fov_deg=50.0),
    ],
)
def test_camera_project_matches_rendered_marker_positions(mitsuba_ready, camera):
    import drjit as dr

    from mbcapture.render import Renderer

    sc = _marker_scene(camera)
    w, h = 64, 48
    r = Renderer(sc, w, h)
    r.render(0.3, 64, seed=3)  # compile
    for t in (0.0, 0.6):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        try:
            img = r.render(t, 64, seed=3).mean(axis=-1)  # (group, row, col)
            hist = dr.kernel_history()
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        # moving an area light (m2) does not compile a new kernel either
        assert not [e for e in hist if e.get("type") == dr.KernelType.JIT and not e.get("cache_hit")]
        expect = camera.project(sc.motion_points(np.array([t]))[0], w, h)
        xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        for g in range(3):
            wsum = img[g].sum()
            assert wsum > 0, f"marker {g} not visible"
            centroid = np.array([(img[g] * xs).sum() / wsum, (img[g] * ys).sum() / wsum])
            assert np.linalg.norm(centroid - expect[g]) < 1.0, (g, t, centroid, expect[g])


@render
def test_metronome_dynamic_range(mitsuba_ready):
    """The visible bulb is >= 1e4 x the darkest lit diffuse surfaces; lit surfaces ~0.005..1."""
    from mbcapture.render import Renderer

    r = Renderer(_metronome(), 80, 64)
    img = r.render(0.0, 16, seed=11, groups=["ambient", "lamp"]).sum(axis=0).mean(axis=-1)
    assert img.max() >= 50.0
    lit = img[img < 5.0]  # everything but the bulb and its immediate neighbourhood
    darkest = np.percentile(lit, 0.5)
    assert 0.003 < darkest and np.median(lit) < 1.0
    assert img.max() / darkest >= 1e4
