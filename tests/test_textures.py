"""Textures, meshes and spectra in scene builds: file checks (clear ConfigError before Mitsuba),
spectrum -> RGB conversion, and small renders against closed forms."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from mbcapture.errors import ConfigError
from mbcapture.render.build import (
    Environment,
    Material,
    SceneBuild,
    Shape,
    Spectrum,
    Texture,
    check_mesh_file,
    read_texture,
    scale,
    spectrum_to_rgb_radiance,
    spectrum_to_rgb_reflectance,
    translate,
)
from mbcapture.scene.scenes import Camera, SceneModel


def _png(path, rgb_u8):
    import cv2

    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb_u8[..., ::-1]))
    return path


def _two_colour(h=8, w=16):
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : w // 2] = (200, 30, 10)
    img[:, w // 2 :] = (10, 40, 220)
    return img


def _textured_build(path) -> SceneBuild:
    return SceneBuild(shapes=(Shape("poster", "rectangle", np.eye(4), Material(Texture(str(path)))),))


# -- file checks ---------------------------------------------------------------------------------
def test_read_texture_png_is_rgb_order_and_scaled(tmp_path):
    img = _two_colour()
    arr = read_texture(_png(tmp_path / "t.png", img))
    assert arr.shape == (8, 16, 3)
    np.testing.assert_allclose(arr[0, 0], np.array([200, 30, 10]) / 255.0)
    np.testing.assert_allclose(arr[0, -1], np.array([10, 40, 220]) / 255.0)


def test_read_texture_exr(tmp_path):
    import OpenEXR

    vals = np.arange(12, dtype=np.float32).reshape(2, 2, 3) / 10
    chans = {c: np.ascontiguousarray(vals[..., i]) for i, c in enumerate("RGB")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(tmp_path / "t.exr"))
    np.testing.assert_allclose(read_texture(tmp_path / "t.exr"), vals)


def test_missing_texture_names_file_and_shape(tmp_path):
    with pytest.raises(ConfigError, match=r"shape 'poster': texture .*nope\.png: file not found"):
        _textured_build(tmp_path / "nope.png").check_files("demo")


@pytest.mark.parametrize("kind", ["garbage", "truncated", "empty"])
def test_corrupt_texture_is_a_config_error(tmp_path, kind):
    good = _png(tmp_path / "good.png", _two_colour(64, 64)).read_bytes()
    data = {"garbage": b"\x89PNG not really an image" * 10, "truncated": good[: len(good) // 2], "empty": b""}[kind]
    bad = tmp_path / "bad.png"
    bad.write_bytes(data)
    with pytest.raises(ConfigError, match=r"scene 'demo', shape 'poster': texture .*bad\.png: (corrupt|.*truncated)"):
        _textured_build(bad).check_files("demo")


def test_texture_suffix_and_directory(tmp_path):
    (tmp_path / "t.gif").write_bytes(b"GIF89a")
    with pytest.raises(ConfigError, match=r"unsupported texture file type '\.gif'"):
        _textured_build(tmp_path / "t.gif").check_files()
    (tmp_path / "d.png").mkdir()
    with pytest.raises(ConfigError, match="not a regular file"):
        _textured_build(tmp_path / "d.png").check_files()


OBJ_QUAD = "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvt 0 0\nf 1 2 3\nf 1 3 4\n"


def _binary_ply(n_faces_written: int = 2) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    verts = struct.pack("<12f", -1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0)
    faces = [struct.pack("<B3i", 3, 0, 1, 2), struct.pack("<B3i", 3, 0, 2, 3)]
    return header + verts + b"".join(faces[:n_faces_written])


def test_mesh_checks(tmp_path):
    (tmp_path / "q.obj").write_text(OBJ_QUAD)
    check_mesh_file(tmp_path / "q.obj")
    (tmp_path / "q.ply").write_bytes(_binary_ply())
    check_mesh_file(tmp_path / "q.ply")
    (tmp_path / "cut.ply").write_bytes(_binary_ply(1))
    (tmp_path / "bad.obj").write_text(OBJ_QUAD + "f 1 2 9\n")
    for name, msg in [("cut.ply", "truncated PLY"), ("bad.obj", "corrupt OBJ: line 8"), ("none.ply", "file not found")]:
        build = SceneBuild(
            shapes=(Shape("statue", "mesh", np.eye(4), Material((0.5, 0.5, 0.5)), mesh=str(tmp_path / name)),)
        )
        with pytest.raises(ConfigError, match=rf"shape 'statue': mesh .*{name}: {msg}"):
            build.check_files("demo")
    with pytest.raises(ConfigError, match="kind 'mesh' needs a mesh file"):
        SceneBuild(shapes=(Shape("statue", "mesh", np.eye(4)),)).check_files()


# -- spectra -> RGB ------------------------------------------------------------------------------
def test_flat_reflectance_spectrum_is_grey():
    wl = tuple(np.arange(360.0, 831.0, 5.0))
    rgb = spectrum_to_rgb_reflectance(Spectrum(wl, (0.5,) * len(wl)))
    np.testing.assert_allclose(rgb, (0.5, 0.5, 0.5), atol=2e-3)


def test_d65_radiance_with_unit_luminance_is_rgb_white():
    import colour

    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(colour.SpectralShape(360, 830, 1))
    ybar = (
        colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
        .copy()
        .align(colour.SpectralShape(360, 830, 1))
        .values[:, 1]
    )
    k = 1.0 / np.trapezoid(ybar * d65.values, d65.wavelengths)
    rgb = spectrum_to_rgb_radiance(Spectrum.from_sd(d65, scale=2.0 * k))
    np.testing.assert_allclose(rgb, (2.0, 2.0, 2.0), rtol=3e-3)


def test_spectrum_validation():
    with pytest.raises(ValueError, match="wavelengths must increase"):
        Spectrum((500.0, 400.0), (1.0, 1.0))
    with pytest.raises(ValueError, match="matching"):
        Spectrum((400.0, 500.0), (1.0,))


# -- renders -------------------------------------------------------------------------------------
def _poster_scene(build: SceneBuild, groups=("sky",)) -> SceneModel:
    return SceneModel(
        name="poster",
        groups=groups,
        switchable=frozenset(),
        camera=Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0),
        build=build,
        params=None,
    )


@pytest.mark.render
def test_texture_renders_in_place_and_missing_file_fails_before_mitsuba(tmp_path):
    from mbcapture.render import Renderer

    path = _png(tmp_path / "poster.png", _two_colour())
    build = SceneBuild(
        shapes=(Shape("poster", "rectangle", scale(3.0), Material(Texture(str(path)))),),
        environment=Environment("sky", (1.0, 1.0, 1.0)),
    )
    img = Renderer(_poster_scene(build), 32, 16, max_depth=2).render(0.0, 16, 1)[0]
    # Lambertian under a uniform unit sky: radiance = linear albedo (sRGB-decoded texel)
    lin = lambda v: ((np.asarray(v) / 255 + 0.055) / 1.055) ** 2.4  # noqa: E731
    np.testing.assert_allclose(img[:, 4:12].mean(axis=(0, 1)), lin([200, 30, 10]), rtol=0.03, atol=2e-3)
    np.testing.assert_allclose(img[:, 20:28].mean(axis=(0, 1)), lin([10, 40, 220]), rtol=0.03, atol=2e-3)
    gone = SceneBuild(
        shapes=(Shape("poster", "rectangle", scale(3.0), Material(Texture(str(tmp_path / "x.png")))),),
        environment=Environment("sky", (1.0, 1.0, 1.0)),
    )
    with pytest.raises(ConfigError, match=r"scene 'poster', shape 'poster': texture .*x\.png: file not found"):
        Renderer(_poster_scene(gone), 32, 16)


@pytest.mark.render
def test_mesh_renders_like_the_rectangle(tmp_path):
    from mbcapture.render import Renderer

    (tmp_path / "q.obj").write_text(OBJ_QUAD)
    imgs = []
    for kind, mesh in (("rectangle", None), ("mesh", str(tmp_path / "q.obj"))):
        build = SceneBuild(
            shapes=(Shape("q", kind, translate(0.1, 0, 0) @ scale(0.5), Material((0.6, 0.3, 0.1)), mesh=mesh),),
            environment=Environment("sky", (1.0, 1.0, 1.0)),
        )
        imgs.append(Renderer(_poster_scene(build), 24, 24, max_depth=2).render(0.0, 8, 3)[0])
    covered = imgs[0][..., 1] < 0.6  # sky: 1, quad: 0.3
    assert 50 < covered.sum() < 24 * 24 - 50
    np.testing.assert_array_equal(covered, imgs[1][..., 1] < 0.6)
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(covered)  # fully covered pixels
    np.testing.assert_allclose(imgs[1][inner].mean(axis=0), (0.6, 0.3, 0.1), rtol=0.03)


@pytest.mark.render
def test_spectral_emitter_film_value_is_the_integral():
    """A sky of LED spectrum L(lambda) gives exactly integral S_c L d lambda on the spectral film
    (the group's shape is folded into the film: wavelengths sampled where the LED emits)."""
    import colour

    from mbcapture.render import Renderer
    from mbcapture.sensor import SensorConfig
    from mbcapture.sensor.spectral import film_sensitivity

    sd = colour.sd_single_led(530, shape=colour.SpectralShape(360, 830, 2), half_spectral_width=30)
    led = Spectrum.from_sd(sd, scale=0.02)
    sensor = SensorConfig(spectral_response="Nikon 5100 (NPL)")
    build = SceneBuild(shapes=(), environment=Environment("sky", led))
    img = Renderer(_poster_scene(build), 16, 16, variant="llvm_ad_spectral", sensor=sensor).render(0.0, 4, 1)[0]
    wl, s = film_sensitivity(sensor)
    grid = np.arange(360.0, 831.0, 0.5)
    lv = np.interp(grid, *led.arrays)
    expected = [np.trapezoid(np.interp(grid, wl, c, left=0, right=0) * lv, grid) for c in s]
    pix = img.reshape(-1, 3).astype(np.float64)
    sem = pix.std(axis=0) / np.sqrt(len(pix))  # Monte Carlo error of the mean (wavelength sampling)
    assert np.all(np.abs(pix.mean(axis=0) - expected) < 4 * sem + 3e-3 * np.asarray(expected))
    # the LED's own band (G) is sampled densely: per-pixel noise of a few percent at 4 spp
    assert pix[:, 1].std() / pix[:, 1].mean() < 0.05


# -- tiles: many rectangles as one shape and one BSDF (mbcapture.render.tiles) ---------------------
def _tile_matrices():
    """Four 0.4 m tiles in a 2 x 2 grid, the lower right one mirrored in x (it must face +z too)."""
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    return (
        translate(-0.5, 0.5, 0) @ scale(0.4),
        translate(0.5, 0.5, 0) @ scale(0.4),
        translate(-0.5, -0.5, 0) @ scale(0.4),
        translate(0.5, -0.5, 0) @ mirror @ scale(0.4),
    )


def _reflectance_spectra():
    wl = tuple(np.arange(380.0, 781.0, 10.0))
    x = (np.asarray(wl) - 380.0) / 400.0
    return (
        Spectrum(wl, tuple(0.1 + 0.8 * x)),
        Spectrum(wl, tuple(0.9 - 0.8 * x)),
        Spectrum(wl, tuple(0.5 + 0.4 * np.sin(6 * x))),
        Spectrum(wl, tuple(np.full_like(x, 0.3))),
    )


def _tiles_and_rectangles(values, twosided=False):
    from mbcapture.render.build import PerTile

    mats = _tile_matrices()
    tiles = SceneBuild(
        shapes=(Shape("grid", "tiles", translate(0, 0.05, 0), Material(PerTile(values), twosided), tiles=mats),),
        environment=Environment("sky", (1.0, 1.0, 1.0)),
    )
    rects = SceneBuild(
        shapes=tuple(
            Shape(f"r{i}", "rectangle", translate(0, 0.05, 0) @ m, Material(v, twosided))
            for i, (m, v) in enumerate(zip(mats, values))
        ),
        environment=Environment("sky", (1.0, 1.0, 1.0)),
    )
    return tiles, rects


def test_tile_geometry_faces_the_rectangles_normal_and_indexes_tiles():
    from mbcapture.render.tiles import tile_geometry

    v, f, uv = tile_geometry(_tile_matrices(), translate(0, 0.05, 0))
    assert v.shape == (16, 3) and f.shape == (8, 3) and uv.shape == (16, 2)
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(normals[:, 2] > 0) and np.allclose(normals[:, :2], 0)  # all face +z, the mirrored one too
    np.testing.assert_array_equal(np.floor(uv[:, 0]), np.repeat(np.arange(4), 4))  # vertex -> its tile
    np.testing.assert_allclose(v[:4].mean(axis=0), (-0.5, 0.55, 0.0))  # tile 0's centre under to_world
    assert np.allclose(np.abs(v[:4, :2] - (-0.5, 0.55)), 0.4)


def test_tile_tables_refuse_what_they_cannot_evaluate():
    from mbcapture.render.tiles import tile_table

    spectra = _reflectance_spectra()
    t = tile_table(spectra, True, "here")
    assert t["table"].shape == (4, 41) and t["wavelengths"][0] == 380.0 and not t["upsample"]
    rgb = tile_table(spectra, False, "here")  # RGB variant: each spectrum's linear sRGB albedo
    np.testing.assert_allclose(rgb["table"][3], spectrum_to_rgb_reflectance(spectra[3]))
    assert tile_table([(0.1, 0.2, 0.3)], True, "here")["upsample"]  # RGB tiles, spectral variant
    with pytest.raises(ConfigError, match="here: tile reflectances must be all spectra or all RGB"):
        tile_table([spectra[0], (0.1, 0.2, 0.3)], True, "here")
    other = Spectrum((380.0, 500.0, 780.0), (0.1, 0.2, 0.3))
    with pytest.raises(ConfigError, match="here: the tiles' spectra must share one wavelength grid"):
        tile_table([spectra[0], other], True, "here")
    with pytest.raises(ConfigError, match="here: .* regular wavelength grid"):
        tile_table([other, other], True, "here")
    with pytest.raises(ConfigError, match="here: a tiles shape needs at least one tile"):
        tile_table([], True, "here")


def test_tiles_shape_checks_name_the_shape():
    from mbcapture.render.build import Light, PerTile

    m = _tile_matrices()
    cases = [
        (
            Shape("g", "tiles", np.eye(4), Material(PerTile(((0.1, 0.1, 0.1),) * 3)), tiles=m),
            "4 tiles but 3 reflectances",
        ),
        (Shape("g", "tiles", np.eye(4), Material((0.5, 0.5, 0.5))), "needs at least one tile matrix"),
        (Shape("g", "tiles", np.eye(4), None, Light("sky", (1.0, 1.0, 1.0)), tiles=m), "cannot emit light"),
        (Shape("g", "rectangle", np.eye(4), Material(PerTile(((0.1, 0.1, 0.1),)))), "belong to kind 'tiles'"),
        (Shape("g", "rectangle", np.eye(4), Material((0.5, 0.5, 0.5)), tiles=m), "belong to kind 'tiles'"),
    ]
    for shape, message in cases:
        with pytest.raises(ConfigError, match=rf"scene 'x', shape 'g': .*{message}"):
            SceneBuild(shapes=(shape,)).check_files("x")


@pytest.mark.render
@pytest.mark.parametrize(
    "variant,kind", [("llvm_ad_rgb", "spectra"), ("llvm_ad_spectral", "spectra"), ("llvm_ad_spectral", "rgb")]
)
def test_tiles_render_as_the_rectangles_they_replace(variant, kind):
    """One tiles shape renders the image of its tiles as separate rectangles with their own BSDFs,
    to float rounding at the tiles' edges: the same paths, the same reflectances (spectra
    interpolated as Mitsuba's 'irregular' spectrum does, RGB upsampled as its 'rgb' texture does)."""
    from mbcapture.render import Renderer
    from mbcapture.sensor import SensorConfig

    values = (
        _reflectance_spectra()
        if kind == "spectra"
        else ((0.8, 0.2, 0.1), (0.1, 0.7, 0.2), (0.2, 0.3, 0.9), (0.5, 0.5, 0.5))
    )
    sensor = SensorConfig(spectral_response="Nikon 5100 (NPL)")
    imgs = [
        Renderer(_poster_scene(b), 32, 32, variant=variant, max_depth=2, sensor=sensor).render(0.0, 8, 5)[0]
        for b in _tiles_and_rectangles(values)
    ]
    tiles_img, rect_img = (i.astype(np.float64) for i in imgs)
    assert (
        np.ptp(rect_img[8:12, 8:12].mean(axis=(0, 1)) - rect_img[8:12, 20:24].mean(axis=(0, 1))) > 0.05 * rect_img.max()
    )
    same = np.isclose(tiles_img, rect_img, rtol=1e-5, atol=1e-6 * rect_img.max()).all(axis=-1)
    assert same.mean() > 0.99, f"only {same.mean():.3f} of the pixels agree"
