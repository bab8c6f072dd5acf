"""The sensor stage of every capture, and whole comparison captures of the same scene.

:func:`sense` is the one sensor stage: the main capture (:func:`mbcapture.capture.pipeline.capture_in_memory`),
a video's frames, a sweep's points and an application's comparison captures all read their
buckets through it, with one storage-time rule (:meth:`mbcapture.timing.timeline.Timeline.storage_ticks`:
a bucket is reset as its first slot opens and read after the capture's last slot, or at the end
of its own exposure when a conventional sensor reads it destructively; a bucket that never collects
holds no dark charge).

:func:`sense_frame` reads one conventional frame of given expected electrons through the same stage (the
flutter shutter's box exposure, the RGB-illumination app's Bayer frame).

:func:`capture_timeline` simulates another capture of the same scene inside an application or a
video: a timeline in, reads out.

Applications that compare their capture with other ways of taking the same picture (the burst's
conventional burst and long exposure, the video's alternating-exposure frames) need the same
pipeline as :func:`mbcapture.capture.pipeline.capture_in_memory`: plan the strata of the
timeline by image motion (camera shake included), render them with the run's renderer (render
cache shared), accumulate bucket electrons and simulate the sensor's reads. The samples per pixel
are given (usually the run's own, chosen by its noise budget): no second pilot.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .filmstore import IN_MEMORY, FilmStore
from .integrate import integrate
from .plan import Plan, make_plan
from ..sensor import SensorConfig, SensorReads, develop_reads, dn_to_electrons, join_rows, simulate_reads
from ..sensor.sampling import NoiseStreams
from ..timing.timeline import ReadEvent, SegmentSeconds, SlotSeconds, Timeline, build_timeline, exact


def sense(
    timeline: Timeline,
    buckets_e: np.ndarray,
    sensor: SensorConfig,
    seed: np.random.SeedSequence,
    tiles: tuple[tuple[int, int], ...] | None = None,
    per_unit: np.ndarray | None = None,
    store: FilmStore = IN_MEMORY,
) -> SensorReads:
    """The sensor stage: ``buckets_e`` (K, H, W, C) noise-free expected electrons of the buckets of
    ``timeline`` into its reads, with dark current over each bucket's storage time
    (:meth:`~mbcapture.timing.timeline.Timeline.storage_s`) and, on a multi-bucket sensor, the buckets
    sharing one photodiode (parasitic light); a sequential timeline's frames are separate exposures.

    ``tiles``: rows (first, end) covering the film in order; each is sensed alone (its noise fields
    the film's, cut to its rows) and the joined reads are developed once (a CFA's demosaicing), so
    the result is the untiled stage's reads bit for bit, without the buckets' charge (``electrons``
    None), and the noise fields and counts are held for one tile at a time.

    ``per_unit`` (C,): ``buckets_e`` is in render units (exposures) and each tile's expected electrons
    are ``buckets_e[tile] * per_unit``, made as the tile is sensed (the same values as multiplying first).
    ``store``: where a tiled stage's joined reads are made (in memory, or on disk: :mod:`mbcapture.exposure.filmstore`)."""
    reads = [r.buckets for r in timeline.reads]
    kw = {"storage_s": timeline.storage_s(), "shared_photodiode": not timeline.sequential}
    scale = (lambda a: a) if per_unit is None else (lambda a: a * per_unit)  # noqa: E731
    if tiles is None or len(tiles) == 1:
        return simulate_reads(scale(buckets_e), reads, sensor, seed, **kw)
    streams = NoiseStreams(seed)
    H = buckets_e.shape[1]
    # one tile at a time: its noise fields, counts and charge made, its reads copied into the film's, let go
    parts = (
        simulate_reads(scale(buckets_e[:, r0:r1]), reads, sensor, streams, band=(r0, H), develop=False, **kw)
        for r0, r1 in tiles
    )
    return develop_reads(join_rows(parts, height=H, reads_only=True, empty=store.empty), sensor)


@dataclass(frozen=True)
class SimulatedCapture:
    """Arrays are (read, row, column, channel).

    reads_dn          simulated reads, DN
    saturated         bool
    rate_e_per_s      each read in electrons per second of its exposure (black level removed, gain undone)
    expected_e        noise-free, unclipped expected electrons of each read
    exposure_s        (R,) seconds each read collected
    plan              the render plan (strata, spp)
    """

    timeline: Timeline
    reads_dn: np.ndarray
    saturated: np.ndarray
    rate_e_per_s: np.ndarray
    expected_e: np.ndarray
    exposure_s: np.ndarray
    plan: Plan


def frame_timeline(exposure_s: float) -> Timeline:
    """One conventional frame: one bucket open for ``exposure_s`` from time 0, read destructively at its end."""
    slot = SlotSeconds(0, exact(exposure_s))
    return build_timeline(
        [SegmentSeconds(exact(0.0), (slot,), 1)],
        [ReadEvent("frame", (0,), destructive=True)],
        1,
        "frame",
        sequential=True,
    )


def sense_frame(frame_e: np.ndarray, sensor: SensorConfig, seed, exposure_s: float) -> SensorReads:
    """One conventional frame through :func:`sense`: ``frame_e`` (H, W, C) noise-free expected electrons
    collected over ``exposure_s``, with dark current over that exposure (:func:`frame_timeline`'s storage
    time) and no parasitic light from other buckets."""
    return sense(frame_timeline(exposure_s), np.asarray(frame_e)[None], sensor, seed)


def capture_timeline(
    timeline: Timeline, scene, cfg, renderer, spp: int, seed: np.random.SeedSequence, k_e: np.ndarray
) -> SimulatedCapture:
    """Render, accumulate and read out ``timeline`` (the scene ``scene``, camera motion included) with
    ``spp`` samples per pixel per stratum. ``seed`` is split into the plan's jitter, the render seeds and
    the sensor noise; ``k_e`` (C,) electrons per render unit and second."""
    s_plan, s_render, s_noise = seed.spawn(3)
    plan = make_plan(timeline, scene, cfg.render, np.random.default_rng(s_plan))
    plan = replace(plan, spp=np.full(plan.passes, int(spp), dtype=np.int64), spp_source="given")
    integrated = integrate(renderer, plan, timeline.n_channels, s_render).routed(timeline)
    buckets_e = integrated.exposure * k_e
    out = sense(timeline, buckets_e, cfg.sensor, s_noise)
    exposure = np.array([float(timeline.read_exposure_ticks(r) * timeline.tick_s) for r in timeline.reads])
    rate = dn_to_electrons(out.reads_dn, cfg.sensor) / exposure[:, None, None, None]
    return SimulatedCapture(timeline, out.reads_dn, out.saturated, rate, out.reads_e_expected, exposure, plan)
