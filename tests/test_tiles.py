"""Tiles of rows (render.tiles): render, accumulation and the sensor stage go through the film a
run of whole render bands at a time, and the capture is the untiled capture bit for bit (same
CPU); the noise fields cut to a band are the whole field's rows; the memory plan chooses tiles."""

import mmap
from pathlib import Path

import numpy as np
import pytest
from golden_cases import RENDER_REPEAT_RTOL, count_differences

from mbcapture import load_config, run_capture
from mbcapture.capture.run import check_resources
from mbcapture.errors import ResourceProblem
from mbcapture.capture.pipeline import prepare
from mbcapture.render.bands import band_seed, film_bands, group_bands
from mbcapture.exposure.resources import GB, choose_tiles, estimate
from mbcapture.sensor import SensorConfig, develop_reads, join_rows, simulate_reads
from mbcapture.sensor.sampling import BandedField, NoiseStreams, uniform_open

ROOT = Path(__file__).resolve().parents[1]
#: 4 render bands of 16 rows on a 48x64 film
SMALL = [
    "render.width=48",
    "render.height=64",
    "render.spp=4",
    "render.max_motion_px=0.05",
    "render.cache=off",
    "render.band_rows=16",
]


# ----------------------------------------------------------------------------- bands and fields
def test_film_bands_cover_the_film_in_even_bands_of_about_a_megapixel():
    assert film_bands(640, 512) == ((0, 512),)  # the paper's sensor: one band, rendered as it always was
    bands = film_bands(4096, 3072)
    assert len(bands) == 12 and all(b - a == 256 for a, b in bands)
    odd = film_bands(1000, 3001)
    assert odd[0] == (0, 1048) and odd[-1][1] == 3001 and all(a % 2 == 0 for a, _ in odd)
    assert all(b == c for (_, b), (c, _) in zip(odd[:-1], odd[1:]))  # contiguous
    assert film_bands(4096, 3072, whole=True) == ((0, 3072),)
    assert group_bands(film_bands(48, 64, 16), 3) == ((0, 16), (16, 48), (48, 64))
    assert group_bands(film_bands(48, 64, 16), 99) == film_bands(48, 64, 16)


def test_band_seeds_keep_the_render_seed_for_the_first_band_and_differ_elsewhere():
    assert band_seed(1234, 0) == 1234
    seeds = {band_seed(1234, b) for b in range(1, 50)}
    assert len(seeds) == 49 and 1234 not in seeds
    assert band_seed(1234, 3) == band_seed(1234, 3) and band_seed(1234, 3) != band_seed(1235, 3)


@pytest.mark.parametrize("kind", ["uniform", "normal"])
def test_a_banded_field_is_the_whole_fields_rows(kind):
    seed = np.random.SeedSequence(7)
    shape = (3, 50, 9, 3)
    rng = np.random.default_rng(seed)
    whole = uniform_open(rng, shape) if kind == "uniform" else rng.standard_normal(shape)
    field = BandedField(seed, shape, kind)
    for r0, r1 in [(0, 11), (11, 12), (12, 40), (40, 50)]:  # in order, as a tiled capture asks
        np.testing.assert_array_equal(field.rows(r0, r1), whole[:, r0:r1])
    np.testing.assert_array_equal(BandedField(seed, shape, kind).rows(30, 47), whole[:, 30:47])  # out of order
    np.testing.assert_array_equal(field.rows(5, 20), whole[:, 5:20])  # back again
    with pytest.raises(ValueError, match="rows"):
        field.rows(10, 51)


@pytest.mark.parametrize("cfa", ["none", "RGGB", "mono"])
def test_sensing_a_film_band_by_band_gives_the_whole_films_reads(cfa):
    """Every noise source on (shot, transfer, read, row noise; pixel, row and column fixed pattern)."""
    e = np.random.default_rng(1).random((4, 30, 17, 3)) * 3000
    cfg = SensorConfig(
        cfa=cfa,
        transfer_inefficiency=1e-3,
        read_noise_row_e=0.7,
        prnu_row=0.01,
        dsnu_col_e=0.5,
        prnu=0.01,
        dsnu_e=1.0,
        full_well_e=2500,
    )
    reads = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
    whole = simulate_reads(e, reads, cfg, np.random.SeedSequence(9), storage_s=[1e-3] * 4)
    streams = NoiseStreams(np.random.SeedSequence(9))
    parts = [
        simulate_reads(e[:, a:b], reads, cfg, streams, storage_s=[1e-3] * 4, band=(a, 30), develop=False)
        for a, b in [(0, 8), (8, 10), (10, 24), (24, 30)]
    ]
    joined = develop_reads(join_rows(parts, height=30), cfg)
    assert whole.bucket_saturated.any() and not whole.bucket_saturated.all()  # wells reached in places
    for name in ("reads_dn", "saturated", "reads_e_expected", "electrons", "bucket_saturated", "mosaic_dn"):
        a, b = getattr(whole, name), getattr(joined, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(b, a, err_msg=name)
    if cfa == "RGGB":
        with pytest.raises(ValueError, match="even row"):
            simulate_reads(e[:, 3:9], reads, cfg, NoiseStreams(1), band=(3, 30))


# ----------------------------------------------------------------------------- whole captures
def _pair(config: str, extra: list[str], tiles: int):
    cfg = load_config(ROOT / "configs" / config, [*SMALL, *extra])
    untiled = run_capture(load_config(ROOT / "configs" / config, [*SMALL, *extra, "render.tiles=1"]), progress=False)
    tiled = run_capture(
        load_config(ROOT / "configs" / config, [*SMALL, *extra, f"render.tiles={tiles}"]), progress=False
    )
    return cfg, untiled, tiled


def _assert_same(untiled, tiled):
    for name in (
        "bucket_exposure",
        "buckets_e",
        "reads_expected_e",
        "reads_dn",
        "saturated",
        "render_var_exposure",
        "mosaic_dn",
    ):
        a, b = getattr(untiled, name), getattr(tiled, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(b, a, err_msg=name)
    assert untiled.images.keys() == tiled.images.keys()
    for name, img in untiled.images.items():
        np.testing.assert_array_equal(tiled.images[name], img, err_msg=name)
    assert tiled.report["render_error"] == untiled.report["render_error"]


@pytest.mark.render
@pytest.mark.parametrize(
    "config, extra, tiles",
    [
        ("metronome_hdr.yaml", [], 3),  # uneven tiles: 1 + 2 + 1 bands
        # a Bayer mosaic, row noise and transfer loss, with the film's results in scratch files on disk
        (
            "metronome_hdr.yaml",
            [
                "sensor.cfa=RGGB",
                "sensor.read_noise_row_e=1.0",
                "sensor.transfer_inefficiency=0.001",
                "render.spill=true",
            ],
            4,
        ),
        ("multi_flash.yaml", [], 2),  # per-group exposures
    ],
)
def test_a_tiled_capture_is_the_untiled_capture(config, extra, tiles, tmp_path):
    scratch = tmp_path / "scratch"
    _, untiled, tiled = _pair(config, [*extra, f"render.spill_dir={scratch}"], tiles)
    assert untiled.report["tiles"]["count"] == 1 and untiled.report["tiles"]["render_bands"] == 4
    assert tiled.report["tiles"]["count"] == tiles
    assert untiled.plan.passes >= 2
    _assert_same(untiled, tiled)
    spill = tiled.report["tiles"]["spill"]
    assert untiled.report["tiles"]["spill"] is None and (spill is not None) == ("render.spill=true" in extra)
    if spill is not None:  # mapped from scratch files, which leave no name behind
        assert spill["folder"] == str(scratch) and spill["gb"] > 0 and list(scratch.iterdir()) == []
        # the exposures and the joined photosite codes (the Bayer reads are demosaiced from them in memory)
        assert isinstance(_root(tiled.bucket_exposure), mmap.mmap) and isinstance(_root(tiled.mosaic_dn), mmap.mmap)
        # its outputs, whose float32 channels are made in scratch files too, are the untiled run's files
        from mbcapture.capture.run import write_outputs

        write_outputs(untiled, tmp_path / "untiled")
        write_outputs(tiled, tmp_path / "tiled")
        for name in ("buckets.exr", "reads_expected.exr", "reads.exr", "hdr.exr"):
            assert (tmp_path / "tiled" / name).read_bytes() == (tmp_path / "untiled" / name).read_bytes(), name
        assert list(scratch.iterdir()) == []
    else:
        assert not isinstance(_root(tiled.bucket_exposure), mmap.mmap)


@pytest.mark.slow
@pytest.mark.render
def test_a_tiled_capture_with_the_noise_budget_is_the_untiled_capture(tmp_path):
    """The default path, render.spp null: the pilot, adaptive sampling (scout, rule, refinement, second round)
    and the top-up each go through the film in the same tiles as the first pass and choose on the whole film's
    arrays, so the tiled capture makes the untiled one's choices, and its values are the untiled one's as far
    as two untiled runs agree (RENDER_REPEAT_RTOL), with its results in scratch files (render.spill). A tighter
    median target than the default makes the top-up run beside the refinement at this small film."""
    extra = [
        "render.spp=null",
        "render.noise_budget=0.05",
        "render.spill=true",
        f"render.spill_dir={tmp_path / 'scratch'}",
    ]
    _, untiled, tiled = _pair("metronome_hdr.yaml", extra, 3)
    assert tiled.report["tiles"]["count"] == 3 and tiled.report["tiles"]["spill"] is not None
    adaptive, top_up = untiled.report["adaptive"], untiled.report["top_up"]
    assert adaptive["pixels"] > 0 and "note" not in adaptive, adaptive
    assert top_up is not None and top_up["applied"], top_up
    assert tiled.report["adaptive"]["tiers"] == adaptive["tiers"]
    assert tiled.report["top_up"]["spp_added"] == top_up["spp_added"]
    np.testing.assert_array_equal(tiled.plan.spp, untiled.plan.spp)
    np.testing.assert_allclose(tiled.bucket_exposure, untiled.bucket_exposure, rtol=RENDER_REPEAT_RTOL, atol=0)
    # the reads as counts: a sample may move by one where its expected electrons moved (golden_cases says how many)
    reads = [r.buckets for r in untiled.timeline.reads]
    assert (
        count_differences(
            tiled.reads_dn,
            untiled.reads_dn,
            tiled.buckets_e,
            untiled.buckets_e,
            reads,
            tiled.config.sensor.gain_dn_per_e,
        )
        == []
    )
    for name, read in untiled.report["render_error"]["reads"].items():
        got = tiled.report["render_error"]["reads"][name]
        for key in ("to_shot_noise_variance_median", "to_shot_noise_variance_p95", "to_shot_noise_variance_p999"):
            assert got[key] == pytest.approx(read[key], rel=1e-4), (name, key)


def _root(a: np.ndarray):
    """What an array's memory finally belongs to (following views and buffers)."""
    while (isinstance(a, np.ndarray) and a.base is not None) or isinstance(a, memoryview):
        a = a.obj if isinstance(a, memoryview) else a.base
    return a


@pytest.mark.render
def test_the_difference_estimator_integrates_tiles_as_the_whole_film():
    """Its base and common-random-number renders are per tile too (the sensor is left out: at a few
    samples this control variate can give a negative exposure, which the sensor refuses)."""
    from mbcapture.config import scene_of
    from mbcapture.exposure.integrate import integrate, integrate_tiles
    from mbcapture.render import Renderer

    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*SMALL, "render.estimator=difference"])
    _, timeline, plan, seeds = prepare(cfg)
    renderer = Renderer.from_config(scene_of(cfg), cfg)
    whole = integrate(renderer, plan, timeline.n_channels, seeds[2])
    tiled = integrate_tiles(renderer, plan, timeline.n_channels, seeds[2], group_bands(renderer.bands, 3))
    for name in ("exposure", "mc_diff", "temporal_diff"):
        np.testing.assert_array_equal(getattr(tiled, name), getattr(whole, name), err_msg=name)


@pytest.mark.render
def test_bands_render_the_rows_of_their_own_seeds():
    """A film of several bands is no copy of one band: each band has its own random numbers, and the
    first band is the one-band film's first rows."""
    from mbcapture.config import scene_of
    from mbcapture.render import Renderer

    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", SMALL)
    one = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*SMALL[:-1]])
    banded = Renderer.from_config(scene_of(cfg), cfg).render(0.0, 4, 11)
    whole = Renderer.from_config(scene_of(one), one).render(0.0, 4, 11)
    np.testing.assert_array_equal(banded[:, :16], whole[:, :16])
    assert not np.array_equal(banded[:, 16:], whole[:, 16:])
    # other bands: other numbers, the same scene (means agree within the Monte Carlo noise of 4 spp)
    rel = abs(banded[:, 16:].mean() - whole[:, 16:].mean()) / whole[:, 16:].mean()
    assert rel < 0.05


# ----------------------------------------------------------------------------- the memory plan
def test_tiles_are_chosen_from_the_memory_cap_and_shrink_the_estimate():
    cfg = load_config(ROOT / "configs" / "sensor_12mp.yaml", ["render.spp=4", "render.cache=off"])
    _, timeline, plan, _ = prepare(cfg)
    app = cfg.app.resolve(cfg.capture.protocol)[0]
    whole, tiled = estimate(cfg, timeline, plan, app, 1), estimate(cfg, timeline, plan, app, 12)
    assert whole.tiles == 1 and tiled.tiles == 12 and tiled.bands == 12
    # more tiles, less memory: the working set follows the largest tile, the whole-film results stay
    steps = [estimate(cfg, timeline, plan, app, n).memory_bytes for n in (1, 2, 3, 4, 6, 12)]
    assert all(a > b for a, b in zip(steps, steps[1:])), steps
    assert tiled.memory_bytes == steps[-1] and steps[-1] > 0.5 * steps[0]
    cap = (whole.memory_bytes + tiled.memory_bytes) / 2 / GB
    capped = load_config(
        ROOT / "configs" / "sensor_12mp.yaml", ["render.spp=4", "render.cache=off", f"render.max_memory_gb={cap}"]
    )
    n = choose_tiles(capped, timeline, plan, app)
    assert 1 < n <= 12
    assert estimate(capped, timeline, plan, app, n).memory_bytes <= cap * GB
    assert estimate(capped, timeline, plan, app, n - 1).memory_bytes > cap * GB  # the fewest that fit
    with pytest.raises(ResourceProblem, match="render.max_memory_gb"):  # below one band per tile: one line, exit 2
        check_resources(
            load_config(
                ROOT / "configs" / "sensor_12mp.yaml",
                [
                    "render.spp=4",
                    "render.cache=off",
                    "render.spill=false",
                    f"render.max_memory_gb={0.9 * tiled.memory_bytes / GB}",
                ],
            ),
            None,
        )


def test_a_film_that_tiles_cannot_fit_spills_its_results_to_disk(tmp_path):
    """render.spill null: below what tiles alone need, the whole-film results go to scratch files, and
    the plan counts them as disk (the exposures, both error estimates, the reads, truths and flags)."""
    from mbcapture.exposure.resources import choose_layout, plan_resources, spilled_per_bucket_sample

    sets = ["render.spp=4", "render.cache=off", f"render.spill_dir={tmp_path}"]
    cfg = load_config(ROOT / "configs" / "sensor_12mp.yaml", sets)
    _, timeline, plan, _ = prepare(cfg)
    app = cfg.app.resolve(cfg.capture.protocol)[0]
    tiled, spilled = estimate(cfg, timeline, plan, app, 12), estimate(cfg, timeline, plan, app, 12, spill=True)
    # HDR, 4 buckets and 4 reads: 2 (exposure, two float32 estimates) + 4 x 2.125 / 4 values per bucket sample
    assert spilled_per_bucket_sample(timeline, plan, app) == 2.0 + 2.125
    per_value = 8 * 4096 * 3072 * 3 * 4
    assert spilled.spill_bytes == int(per_value * 4.125) and tiled.spill_bytes == 0
    assert tiled.memory_bytes - spilled.memory_bytes == pytest.approx(spilled.spill_bytes, abs=2)
    assert estimate(cfg, timeline, plan, app, 1, spill=True).spill_bytes == 0  # one tile: nothing to spill
    cap = (tiled.memory_bytes + spilled.memory_bytes) / 2 / GB  # tiles alone cannot fit, spilled can
    capped = load_config(ROOT / "configs" / "sensor_12mp.yaml", [*sets, f"render.max_memory_gb={cap}"])
    n, spill = choose_layout(capped, timeline, plan, app)
    assert spill and 1 < n <= 12 and estimate(capped, timeline, plan, app, n, True).memory_bytes <= cap * GB
    need = plan_resources(capped, timeline, plan, app)  # what `mbcapture plan` and the run's first line say
    assert (need.tiles, need.spill_bytes > 0) == (n, True) and "scratch files on disk" in need.line()
    assert choose_layout(
        load_config(
            ROOT / "configs" / "sensor_12mp.yaml", [*sets, "render.spill=false", f"render.max_memory_gb={cap}"]
        ),
        timeline,
        plan,
        app,
    ) == (12, False)
    # a small film in tiles fits in memory: no spill unless asked for; never in one tile
    small = [*SMALL, f"render.spill_dir={tmp_path}"]
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*small, "render.tiles=2"])
    _, timeline, plan, _ = prepare(cfg)
    assert choose_layout(cfg, timeline, plan, app) == (2, False)
    assert choose_layout(
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [*small, "render.tiles=2", "render.spill=true"]),
        timeline,
        plan,
        app,
    ) == (2, True)
    assert choose_layout(
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [*small, "render.spill=true"]), timeline, plan, app
    ) == (1, False)
