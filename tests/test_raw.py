"""DNG raw output (output.dng, mbcapture.output.raw): rawpy (LibRaw) opens every file with the simulated
codes, black and white levels exactly, and develops it to the scene's colours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rawpy  # a dependency (pyproject.toml): every test here runs, none is skipped for want of it

from mbcapture import load_config, run_capture
from mbcapture.errors import ConfigError
from mbcapture.output.io import read_exr
from mbcapture.output.raw import CFA_PATTERNS, colour_tags, write_dng

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("cfa", [None, *CFA_PATTERNS])
def test_rawpy_reads_back_the_codes_and_levels_exactly(tmp_path, cfa):
    rng = np.random.default_rng(1)
    shape = (24, 36) if cfa else (24, 36, 3)
    codes = rng.integers(0, 4096, shape)
    path = tmp_path / "a.dng"
    write_dng(path, codes, black_level=64, white_level=4095, channel_gain=np.array([2.0, 3.0, 1.5]), cfa=cfa)
    with rawpy.imread(str(path)) as raw:
        got = raw.raw_image if cfa else raw.raw_image[..., :3]
        assert np.array_equal(got, codes)
        assert raw.white_level == 4095
        assert list(raw.black_level_per_channel[: (4 if cfa else 3)]) == [64] * (4 if cfa else 3)
        if cfa:  # LibRaw's colour index per photosite of the 2x2 tile (its second green is 3)
            want = np.array(CFA_PATTERNS[cfa]).reshape(2, 2)
            pattern = np.where(raw.raw_pattern == 3, 1, raw.raw_pattern)
            assert np.array_equal(pattern, want)
        # white balance from AsShotNeutral: the reciprocal of the channel gains, green 1
        assert np.allclose(
            np.array(raw.camera_whitebalance[:3]) / raw.camera_whitebalance[1], [1.5, 1.0, 2.0], rtol=1e-5
        )


@pytest.mark.parametrize("black_level", [5000, 60000, 64.5])
def test_a_black_level_of_any_sixteen_bit_code_is_written(tmp_path, black_level):
    """A black level of 4295 DN or more over the finest denominator (10^6) would overflow the RATIONAL's 32-bit
    numerator: the denominator shrinks instead, and LibRaw reads the level back (it keeps whole DN)."""
    codes = np.random.default_rng(3).integers(int(black_level), 65535, (24, 36))
    path = tmp_path / "b.dng"
    write_dng(path, codes, black_level=black_level, white_level=65535, channel_gain=np.ones(3), cfa="RGGB")
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image, codes)
        assert list(raw.black_level_per_channel) == [int(black_level)] * 4


def test_a_run_with_a_high_black_level_writes_its_dngs(tmp_path):
    """The whole command: a 16-bit ADC with its black level at 5000 DN writes every read's DNG."""
    cfg = load_config(
        ROOT / "configs" / "metronome_hdr.yaml",
        [
            "render.width=32",
            "render.height=24",
            "render.spp=2",
            "render.cache=off",
            "sensor.adc_bits=16",
            "sensor.black_level_dn=5000",
            "output.dng=true",
        ],
    )
    run_capture(cfg, tmp_path / "run", progress=False)
    names = sorted(p.name for p in (tmp_path / "run").glob("*.dng"))
    assert names == ["read_J1.dng", "read_J2.dng", "read_J3.dng", "read_J4.dng"]
    with rawpy.imread(str(tmp_path / "run" / "read_J1.dng")) as raw:
        assert list(raw.black_level_per_channel[:3]) == [5000] * 3


def test_the_colour_matrix_maps_a_d65_white_to_the_as_shot_neutral():
    matrix, neutral = colour_tags(np.array([3.0, 6.0, 2.0]))
    d65_xyz = np.linalg.solve(matrix / neutral[:, None], np.ones(3))  # linear sRGB (1, 1, 1) in XYZ
    assert np.allclose(matrix @ d65_xyz, neutral)
    assert np.allclose(d65_xyz / d65_xyz[1], [0.95047, 1.0, 1.08883], atol=2e-4)  # D65 white point
    with pytest.raises(ValueError, match="3 positive"):
        colour_tags(np.array([1.0, 0.0, 1.0]))


def _chart_run(tmp_path_factory, name: str, extra: tuple[str, ...] = ()) -> Path:
    """The colour chart at 160x128, 4 spp, with every read written as a DNG (``extra``: more overrides)."""
    out = tmp_path_factory.mktemp(name) / "run"
    over = ["scene.name=colour_chart", "render.width=160", "render.height=128", "render.spp=4", "render.cache=off"]
    run_capture(load_config(None, [*over, "output.dng=true", *extra]), out, progress=False)
    return out


@pytest.fixture(scope="module")
def chart_run(tmp_path_factory):
    return _chart_run(tmp_path_factory, "dng")


def test_every_read_is_a_dng_with_the_simulated_values(chart_run):
    reads = read_exr(chart_run / "reads.exr")
    assert sorted(p.name for p in chart_run.glob("*.dng")) == [f"read_{n}.dng" for n in sorted(reads)]
    # each read's white level: where it clips (its J buckets' full wells of 10 000 e- at 0.4 DN/e- above a black
    # level of 256 DN, less 4 read-noise sigmas of 3 e-), not the ADC's top code
    limit = {"J1": 4251, "J2": 8251, "J3": 12251, "J4": 16251}
    for name, dn in reads.items():
        with rawpy.imread(str(chart_run / f"read_{name}.dng")) as raw:
            assert np.array_equal(raw.raw_image[..., :3], dn.astype(np.uint16)), name
            assert raw.black_level_per_channel[:3] == [256] * 3 and raw.white_level == limit[name], name
    assert "read_J4.dng" in (chart_run / "report.html").read_text()


def _developed_colour_error(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """CIEDE2000 over 8x8 blocks of rawpy's develop (camera white balance, sRGB output, linear) of the longest
    read, against the run's noise-free truth, up to one exposure scale; and the same develop without the colour
    tags (white balance 1, 1, 1, raw colour), which must be visibly off for the comparison to mean anything."""
    import colour

    truth = read_exr(run / "hdr.exr")["truth"]
    reads = read_exr(run / "reads.exr")
    developed = _develop(run / "read_J4.dng")
    with rawpy.imread(str(run / "read_J4.dng")) as raw:
        plain = raw.postprocess(
            user_wb=[1, 1, 1, 1],
            no_auto_bright=True,
            output_color=rawpy.ColorSpace.raw,
            gamma=(1, 1),
            output_bps=16,
            user_flip=0,
        ).astype(np.float64)
    ok = (reads["J4"] < 16000).all(-1) & (truth.min(-1) > 0)
    H, W = ok.shape

    def blocks(a):
        return (
            a[: H // 8 * 8, : W // 8 * 8].reshape(H // 8, 8, W // 8, 8, -1).mean(axis=(1, 3)).reshape(-1, a.shape[-1])
        )

    keep = blocks(ok[..., None].astype(float))[:, 0] == 1
    assert keep.sum() > 100
    t = blocks(truth)[keep]
    lab = lambda x: colour.XYZ_to_Lab(colour.sRGB_to_XYZ(x / t.max(), apply_cctf_decoding=False))  # noqa: E731
    out = []
    for image in (developed, plain):
        d = blocks(image)[keep]
        d = d * (d * t).sum() / (d * d).sum()
        out.append(colour.delta_E(lab(d), lab(t), method="CIE 2000"))
    return out[0], out[1]


def test_a_developed_dng_has_the_scene_colours(chart_run):
    """The linear DNG of a sensor without a colour filter array (4 spp renders and one read's noise: measured
    median 0.27, max 1.8)."""
    de, plain = _developed_colour_error(chart_run)
    assert np.median(de) < 1.0 and de.max() < 4.0, (np.median(de), de.max())
    assert np.median(plain) > 2 * np.median(de)


@pytest.fixture(scope="module")
def bayer_chart_run(tmp_path_factory):
    return _chart_run(tmp_path_factory, "dng_bayer", ("sensor.cfa=RGGB",))


def test_a_developed_bayer_dng_has_the_scene_colours(bayer_chart_run):
    """A Bayer sensor's DNG is its photosites' mosaic with its CFA pattern: LibRaw demosaics it (its own
    method) and colours it from the same tags. Over 8x8 blocks, each colour from a quarter or half of the
    photosites with its own noise, and LibRaw's demosaicing at the patches' edges: measured median 1.06, max
    5.8 (the linear DNG's: 0.27, 1.8); without the tags the median is over twice that."""
    with rawpy.imread(str(bayer_chart_run / "read_J4.dng")) as raw:
        assert raw.raw_image.shape == (128, 160) and raw.num_colors == 3
    de, plain = _developed_colour_error(bayer_chart_run)
    assert np.median(de) < 1.5 and de.max() < 8.0, (np.median(de), de.max())
    assert np.median(plain) > 2 * np.median(de)


@pytest.mark.parametrize(
    "overrides,message",
    [
        (["output.dng=true", "sensor.adc_bits=18"], "needs sensor.adc_bits <= 16"),
    ],
)
def test_dng_needs_sixteen_bit_codes(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(ROOT / "configs" / "metronome_hdr.yaml", overrides)


def test_rawpy_default_develop_looks_like_the_runs_preview(chart_run):
    """rawpy's default postprocess (its auto-brightness, BT.709 curve, daylight = D65 white balance from
    the colour matrix) against the run's sRGB preview of the same scene (truth.png): the chromaticity
    of every 8x8 block that neither image clips, CIE 1931 xy (measured: median 0.002, max 0.010)."""
    import colour
    from PIL import Image

    with rawpy.imread(str(chart_run / "read_J4.dng")) as raw:
        developed = raw.postprocess(user_flip=0).astype(np.float64) / 255
    preview = np.asarray(Image.open(chart_run / "truth.png")).astype(np.float64) / 255
    H, W = preview.shape[:2]

    def blocks(a):
        return (
            a[: H // 8 * 8, : W // 8 * 8].reshape(H // 8, 8, W // 8, 8, -1).mean(axis=(1, 3)).reshape(-1, a.shape[-1])
        )

    unclipped = (developed.max(-1) < 0.98) & (preview.max(-1) < 0.98) & (preview.min(-1) > 0.02)
    keep = blocks(unclipped[..., None].astype(float))[:, 0] == 1
    assert keep.sum() >= 60
    xy = lambda rgb: colour.XYZ_to_xy(colour.sRGB_to_XYZ(rgb, apply_cctf_decoding=False))  # noqa: E731
    d = xy(blocks(colour.models.oetf_inverse_BT709(developed))[keep])
    p = xy(blocks(colour.cctf_decoding(preview, function="sRGB"))[keep])
    dist = np.linalg.norm(d - p, axis=1)
    assert np.median(dist) < 0.005 and dist.max() < 0.02, (np.median(dist), dist.max())


def test_a_mono_sensor_writes_a_one_sample_dng_that_rawpy_reads_back():
    import tempfile

    codes = np.random.default_rng(2).integers(0, 4096, (24, 36))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "m.dng"
        write_dng(path, codes, black_level=64, white_level=4095, channel_gain=np.ones(3), cfa="mono")
        with rawpy.imread(str(path)) as raw:
            assert np.array_equal(np.asarray(raw.raw_image).reshape(24, 36, -1)[..., 0], codes)
            assert raw.white_level == 4095 and raw.black_level_per_channel[0] == 64
        with pytest.raises(ValueError, match="monochrome"):
            write_dng(path, np.zeros((4, 4, 3)), black_level=0, white_level=4095, channel_gain=np.ones(3), cfa="mono")


def _develop(path: Path) -> np.ndarray:
    """rawpy's develop with the camera's white balance (AsShotNeutral), linear sRGB, no auto brightness."""
    with rawpy.imread(str(path)) as raw:
        return raw.postprocess(
            use_camera_wb=True,
            no_auto_bright=True,
            output_color=rawpy.ColorSpace.sRGB,
            gamma=(1, 1),
            output_bps=16,
            user_flip=0,
        ).astype(np.float64)


def test_a_clipped_highlight_develops_neutral(tmp_path):
    """A coloured flat field bright enough to clip every read in every channel: each read's DNG says where it clips
    (WhiteLevel: its charge limit through gain and black level, less four read-noise sigmas), so LibRaw develops
    the clipped field white (channels within 1 % of one another). With the ADC's top code as the white level, the
    same codes develop coloured: the white balance scales the clipped channels unequally."""
    import tifffile

    from mbcapture.output.raw import white_level_dn

    cfg = load_config(
        None,
        [
            "scene.name=flatfield",
            "scene.radiance=[20, 40, 10]",
            "render.width=64",
            "render.height=48",
            "render.spp=2",
            "render.cache=off",
            "output.dng=true",
        ],
    )
    res = run_capture(cfg, tmp_path / "run", progress=False)
    assert res.saturated.all()
    s = cfg.sensor
    for i, name in enumerate(["J1", "J2", "J3", "J4"]):
        path = tmp_path / "run" / f"read_{name}.dng"
        buckets = len(res.timeline.reads[i].buckets)
        with rawpy.imread(str(path)) as raw:
            assert raw.white_level == white_level_dn(min(buckets * s.full_well_e, s.fd_full_well_e), s) < s.adc_max_dn
        mean = _develop(path).reshape(-1, 3).mean(axis=0)
        assert mean.max() / mean.min() < 1.01, (name, mean)
        with tifffile.TiffFile(path) as tif:  # ExposureTime and BaselineExposure relate the reads
            tags = tif.pages[0].tags
            num, den = tags["ExposureTime"].value
            assert num / den == pytest.approx(res.report["reads"][i]["exposure_s"], rel=1e-6)
            num, den = tags[50730].value
            assert num / den == pytest.approx(np.log2(8e-3 / res.report["reads"][i]["exposure_s"]), abs=1e-6)
    # the first read's codes (clipped at a quarter of the ADC's range) with the ADC's top code as their white level: tinted
    old = tmp_path / "old.dng"
    k = np.array([res.report["electrons_per_render_unit_second"][c] for c in "RGB"]) * s.gain_dn_per_e
    write_dng(old, res.reads_dn[0], black_level=s.black_level_dn, white_level=s.adc_max_dn, channel_gain=k)
    mean = _develop(old).reshape(-1, 3).mean(axis=0)
    assert mean.max() / mean.min() > 1.1, mean
