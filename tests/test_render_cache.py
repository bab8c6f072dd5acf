"""The render cache: entries survive only whole and checked, eviction is least-recently-used,
concurrent writers are safe, and a capture re-renders exactly when something that determines a
render changed."""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import numpy as np
import pytest

from mbcapture.render.cache import RenderCache, digest

ROOT = Path(__file__).resolve().parents[1]


def _key(i: int) -> str:
    return digest({"entry": i})


def test_entries_round_trip_with_their_header(tmp_path):
    c = RenderCache(tmp_path, max_bytes=10**9)
    a = np.random.default_rng(0).random((2, 3, 4, 3)).astype(np.float32)
    assert c.get(_key(1)) is None
    c.put(_key(1), a, seconds=1.5, about={"kind": "test"})
    got, header = c.get(_key(1))
    np.testing.assert_array_equal(got, a)
    assert got.dtype == np.float32 and header["seconds"] == 1.5 and header["about"]["kind"] == "test"
    assert c.stats.hits == 1 and c.stats.misses == 1 and c.stats.saved_s == 1.5


@pytest.mark.parametrize("damage", ["truncate", "flip_byte", "garbage_header", "empty"])
def test_a_damaged_entry_is_never_used_and_is_removed(tmp_path, damage):
    c = RenderCache(tmp_path, max_bytes=10**9)
    a = np.arange(600, dtype=np.float32).reshape(10, 20, 3)
    c.put(_key(2), a)
    path = c._path(_key(2))
    raw = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(raw[:-100])
    elif damage == "flip_byte":
        path.write_bytes(raw[:-50] + bytes([raw[-50] ^ 0xFF]) + raw[-49:])
    elif damage == "garbage_header":
        path.write_bytes(b"{not json\n" + raw.split(b"\n", 1)[1])
    else:
        path.write_bytes(b"")
    assert c.get(_key(2)) is None
    assert c.stats.corrupt == 1 and not path.exists()
    c.put(_key(2), a)  # rendered again and stored whole
    np.testing.assert_array_equal(c.get(_key(2))[0], a)


def test_eviction_removes_the_least_recently_used(tmp_path):
    import os
    import time

    arr = np.zeros((64, 64, 3), np.float32)  # 49 kB each
    size = arr.nbytes
    c = RenderCache(tmp_path, max_bytes=int(3.5 * size))
    for i in range(3):
        c.put(_key(i), arr)
        p = c._path(_key(i))
        os.utime(p, (time.time() - 100 + i, time.time() - 100 + i))  # written in order 0, 1, 2
    assert c.get(_key(0)) is not None  # 0 is now the most recently used
    c.put(_key(3), arr)  # over the cap: the least recently used (1) goes
    assert c.get(_key(1)) is None
    assert all(c.get(_key(i)) is not None for i in (0, 2, 3))
    assert c.size_bytes() <= 3.5 * size


def test_writes_walk_the_folder_once_per_rescan_and_still_keep_the_cap(tmp_path, monkeypatch):
    """A write does not measure the whole cache (a stat per entry, per render): the folder is walked
    on the first write and every RESCAN_EVERY writes. Another process's entries (another
    RenderCache on the same folder) are counted at the next walk, and the cap then holds."""
    from mbcapture.render import cache as cache_mod

    arr = np.zeros((16, 16, 3), np.float32)
    walks = []
    real_entries = RenderCache.entries
    monkeypatch.setattr(RenderCache, "entries", lambda self: walks.append(1) or real_entries(self))
    n = 3 * cache_mod.RESCAN_EVERY
    mine = RenderCache(tmp_path, max_bytes=10**9)
    for i in range(n):
        mine.put(_key(i), arr)
    assert len(walks) == 3, len(walks)  # writes 1, 65 and 129; the old code walked on each of the 192
    assert mine._known_bytes == sum(p.stat().st_size for p in real_entries(mine))
    # another writer fills the folder past this object's cap: seen, and evicted, within RESCAN_EVERY writes
    entry = real_entries(mine)[0].stat().st_size
    mine.max_bytes = (n + 10) * entry
    other = RenderCache(tmp_path, max_bytes=10**9)
    for i in range(n, 2 * n):
        other.put(_key(i), arr)
    for i in range(cache_mod.RESCAN_EVERY + 1):
        mine.put(_key(2 * n + i), arr)
    assert sum(p.stat().st_size for p in real_entries(mine)) <= mine.max_bytes


def _hammer(root: str, worker: int, rounds: int) -> int:
    c = RenderCache(root, max_bytes=6 * 64 * 64 * 3 * 4)  # small cap: evictions race with reads
    bad = 0
    for r in range(rounds):
        i = (worker + r) % 8
        value = np.full((64, 64, 3), float(i), np.float32)
        got = c.get(_key(i))
        if got is not None and not np.array_equal(got[0], value):
            bad += 1
        c.put(_key(i), value)
    return bad


def test_concurrent_writers_readers_and_evictions_never_see_a_wrong_entry(tmp_path):
    ctx = mp.get_context("spawn")
    with ctx.Pool(3) as pool:
        bad = pool.starmap(_hammer, [(str(tmp_path), w, 60) for w in range(3)])
    assert bad == [0, 0, 0]
    c = RenderCache(tmp_path, max_bytes=10**9)
    for p in c.entries():  # everything left is whole
        assert c.get(p.name.split(".")[0]) is not None
    assert not list(tmp_path.glob("??/.tmp-*"))  # no temporary file left behind


def test_cache_cli_info_and_clear(tmp_path, capsys):
    from mbcapture.cli import main

    c = RenderCache(tmp_path, max_bytes=10**9)
    c.put(_key(5), np.ones((4, 4, 3), np.float32))
    assert main(["cache", "info", "--dir", str(tmp_path)]) == 0
    assert "1 renders" in capsys.readouterr().out
    assert main(["cache", "clear", "--dir", str(tmp_path)]) == 0
    assert "removed 1 renders" in capsys.readouterr().out and not c.entries()


# --------------------------------------------------------------------------- captures


def _run(cache_dir: Path, *overrides: str, config: str = "metronome_hdr.yaml"):
    from mbcapture import load_config, run_capture

    cfg = load_config(
        ROOT / "configs" / config,
        [
            "render.width=16",
            "render.height=12",
            "render.spp=4",
            "render.max_motion_px=2.0",
            f"render.cache={cache_dir}",
            *overrides,
        ],
    )
    return run_capture(cfg, progress=False)


@pytest.mark.render
def test_changes_downstream_of_the_render_render_nothing_and_give_the_same_images(tmp_path):
    first = _run(tmp_path)
    assert first.report["render_cache"]["hits"] == 0 and first.report["render_cache"]["rendered"] > 0
    for change in [
        "sensor.read_noise_e=5",
        "sensor.noise_seed=7",
        "hdr.method=inverse_variance",
        "output.png_percentile=90",
        "sensor.full_well_e=5000",
    ]:
        again = _run(tmp_path, change)
        assert again.report["render_cache"]["rendered"] == 0, change
        np.testing.assert_array_equal(again.bucket_exposure, first.bucket_exposure)
    # a new noise seed: the same renders, other noise
    noisy = _run(tmp_path, "sensor.noise_seed=7")
    assert not np.array_equal(noisy.reads_dn, first.reads_dn)


@pytest.mark.render
def test_a_pilot_on_blocks_and_adaptive_sampling_are_cached_too(tmp_path, monkeypatch):
    """The renders of listed pixels (the pilot's blocks, adaptive sampling's passes) are kept under
    their pixels' digest: a sensor change on the warm cache renders nothing and gives the same exposure.
    The pilot is on blocks at this film (20 of them) with PILOT_BLOCKS at 8; a tail target of 0.01
    makes adaptive sampling refine pixels."""
    from mbcapture import budget
    from mbcapture.render import Renderer

    monkeypatch.setattr(budget.pilot, "PILOT_BLOCKS", 8)
    made = []  # every render of listed pixels this process makes, cached or not
    render_pixels = Renderer._render_pixels
    monkeypatch.setattr(Renderer, "_render_pixels", lambda self, *a: made.append(a) or render_pixels(self, *a))
    budgeted = ["render.spp=null", "render.max_spp=32", "render.adaptive=true", "render.noise_budget_tail=0.01"]
    first = _run(tmp_path, *budgeted)
    kinds = first.report["render_cache"]["by_kind"]
    assert first.report["plan"]["pilot"]["blocks"] == 8 and first.report["adaptive"]["pixels"] > 0
    assert kinds["pixels"]["rendered"] == len(made) > first.report["plan"]["pilot"]["renders"]
    made.clear()
    again = _run(tmp_path, *budgeted, "sensor.read_noise_e=5")
    assert again.report["render_cache"]["rendered"] == 0 and made == []
    assert again.report["render_cache"]["by_kind"]["pixels"]["hits"] == kinds["pixels"]["rendered"]
    np.testing.assert_array_equal(again.bucket_exposure, first.bucket_exposure)


@pytest.mark.render
@pytest.mark.parametrize(
    "change",
    [
        "seed=2",
        "render.spp=6",
        "render.max_depth=2",
        "render.sampler=independent",
        "scene.amplitude_deg=25",
        "render.width=18",
    ],
)
def test_changes_that_determine_a_render_render_again(tmp_path, change):
    _run(tmp_path)
    again = _run(tmp_path, change)
    assert again.report["render_cache"]["rendered"] > 0, change


@pytest.mark.render
def test_cache_off_writes_nothing_and_gives_the_same_images(tmp_path):
    on = _run(tmp_path / "c")
    off = _run(tmp_path / "unused", "render.cache=off")
    assert not (tmp_path / "unused").exists() and off.report["render_cache"] == {"folder": None}
    np.testing.assert_array_equal(on.reads_dn, off.reads_dn)
    cached = _run(tmp_path / "c")  # read back: bit-identical to rendering
    np.testing.assert_array_equal(cached.reads_dn, off.reads_dn)


def test_an_unusable_cache_folder_is_a_config_error(tmp_path):
    from mbcapture.capture.pipeline import render_cache
    from mbcapture.render.settings import RenderSection
    from mbcapture.errors import ConfigError

    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match="render.cache"):
        render_cache(RenderSection(cache=str(blocker / "sub")))
