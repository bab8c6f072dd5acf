"""Schedule arithmetic: exact ticks, the paper's spans (15T vs 8T) and equations 1-5."""

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbcapture.timing import protocols
from mbcapture.config import config_from_dict
from mbcapture.errors import ConfigError
from mbcapture.timing.timeline import DRAIN, ReadEvent, SegmentSeconds, SlotSeconds, build_timeline, common_tick, exact


def cfg(**capture):
    sensor = capture.pop("sensor", {})
    return config_from_dict({"scene": {"name": "flatfield"}, "capture": capture, "sensor": sensor})


def exposure_s(tl, read):
    return tl.read_exposure_ticks(read) * tl.tick_s


def span_s(tl, buckets):
    a, b = tl.span_ticks(buckets)
    return (b - a) * tl.tick_s


def test_common_tick_is_exact_gcd():
    assert common_tick([Fraction(1, 1000) / 1024 * 4, Fraction(1, 1000) / 1024]) == Fraction(1, 1024000)
    assert exact(0.001) == Fraction(1, 1000)  # the decimal as written, not the binary double
    assert common_tick([exact(1e-6), exact(0.5)]) == Fraction(1, 10**6)


@pytest.mark.parametrize("periods", [1, 3, 64, 1024, 10**6])
def test_photon_efficient_reads_T_2T_4T_8T_in_8T(periods):
    T = Fraction(1, 1000)
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", unit_exposure_s=0.001, periods=periods))
    assert [exposure_s(tl, r) for r in tl.reads] == [T, 2 * T, 4 * T, 8 * T]
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == 8 * T
    assert span_s(tl, tl.reads[-1].buckets) == 8 * T  # the longest exposure spans exactly 8T
    assert [r.buckets for r in tl.reads] == [(3,), (2, 3), (1, 2, 3), (0, 1, 2, 3)]  # J1 = bucket 4, ...


@pytest.mark.parametrize("periods", [1, 2, 16, 1000])
def test_interleaved_spans_follow_the_paper(periods):
    """Section 4: image i spans T_i + (N-1)/N * (sum of the other exposures); capture is 15T."""
    T, N = Fraction(1, 1000), periods
    tl = protocols.build(cfg(protocol="interleaved_hdr", unit_exposure_s=0.001, periods=N))
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == 15 * T
    exps = {r.buckets[0]: exposure_s(tl, r) for r in tl.reads}
    assert [exps[b] for b in range(4)] == [8 * T, 4 * T, 2 * T, T]
    # bucket 1 (first slot of each period): T1 + (N-1)/N (T2+T3+T4), as printed in the paper
    assert span_s(tl, (0,)) == 8 * T + Fraction(N - 1, N) * 7 * T
    # the last slot's bucket (4) starts after the other three slots of the first period
    assert span_s(tl, (3,)) == 15 * T - Fraction(14, N) * T


def three_frame_timeline(T1, T2, T3, N):
    slots = (SlotSeconds(0, T1 / N), SlotSeconds(1, T2 / N), SlotSeconds(2, T3 / N))
    reads = [ReadEvent(f"F{i + 1}", (i,)) for i in range(3)]
    return build_timeline([SegmentSeconds(Fraction(0), slots, N)], reads, 3, "custom")


@pytest.mark.parametrize("N", [1, 2, 5, 100])
def test_equations_1_to_5_centroids(N):
    T1, T2, T3 = Fraction(1, 125), Fraction(1, 250), Fraction(1, 500)
    tl = three_frame_timeline(T1, T2, T3, N)
    C = [tl.centroid_ticks((k,)) * tl.tick_s for k in range(3)]
    assert C[1] - C[0] == (T1 + T2) / (2 * N)  # eq. 4
    assert C[2] - C[1] == (T2 + T3) / (2 * N)  # eq. 5
    # duration (span) differences shrink to (T2 - T1)/N
    assert span_s(tl, (1,)) - span_s(tl, (0,)) == (T2 - T1) / N
    assert span_s(tl, (2,)) - span_s(tl, (1,)) == (T3 - T2) / N


def test_sequential_centroids_and_gap():
    """N = 1 back-to-back frames with a readout gap: centroids (T1+T2)/2 + gap apart."""
    tl = protocols.build(
        cfg(
            protocol="interleaved_hdr",
            unit_exposure_s=0.001,
            periods=8,
            sequential=True,
            sensor={"frame_readout_s": 0.02},
        )
    )
    assert tl.sequential and all(r.destructive for r in tl.reads)
    T, gap = Fraction(1, 1000), Fraction(2, 100)
    exps = [exposure_s(tl, r) for r in tl.reads]
    assert exps == [T, 2 * T, 4 * T, 8 * T]  # same reads as the interleaved capture
    C = [tl.centroid_ticks(r.buckets) * tl.tick_s for r in tl.reads]
    assert C[1] - C[0] == (exps[0] + exps[1]) / 2 + gap
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == 15 * T + 3 * gap
    # each frame is one contiguous exposure
    assert all(span_s(tl, r.buckets) == e for r, e in zip(tl.reads, exps))


def brute_force_gated(tl, t, bucket, group=None):
    """Slot-by-slot enumeration (the naive way) of gated ticks before t."""
    total = 0
    for seg in tl.segments:
        start = seg.start_tick
        for _ in range(seg.repeats):
            for s in seg.slots:
                if s.bucket == bucket and (group is None or group in s.groups_on):
                    total += max(0, min(t, start + s.ticks) - start)
                start += s.ticks
    return total


@settings(max_examples=60, deadline=None)
@given(
    durs=st.lists(st.integers(1, 50), min_size=1, max_size=5),
    buckets=st.lists(st.integers(-1, 2), min_size=5, max_size=5),
    flash=st.lists(st.booleans(), min_size=5, max_size=5),
    repeats=st.integers(1, 7),
    t=st.lists(st.integers(-5, 2000), min_size=1, max_size=8),
)
def test_closed_form_gated_time_matches_enumeration(durs, buckets, flash, repeats, t):
    slots = tuple(
        SlotSeconds(buckets[i], Fraction(d, 10**6), frozenset({"flash"}) if flash[i] else frozenset())
        for i, d in enumerate(durs)
    )
    if all(s.bucket == DRAIN for s in slots):
        slots = slots + (SlotSeconds(0, Fraction(1, 10**6)),)
    used = sorted({s.bucket for s in slots if s.bucket != DRAIN})
    tl = build_timeline(
        [SegmentSeconds(Fraction(3, 10**6), slots, repeats)], [ReadEvent("J1", (used[0],))], 3, "custom"
    )
    scale = int(Fraction(1, 10**6) / tl.tick_s)
    ts = np.array(t, dtype=np.int64) * scale
    for k in range(3):
        for g in (None, "flash"):
            got = tl.gated_ticks(ts, k, g)
            want = [brute_force_gated(tl, int(x), k, g) for x in ts]
            assert got.tolist() == want


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(0, 10**6), min_size=0, max_size=20), periods=st.integers(1, 5000))
def test_weights_of_any_partition_sum_exactly_to_exposures(cuts, periods):
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", unit_exposure_s=0.001, periods=periods))
    span = tl.end_tick - tl.start_tick
    inner = sorted({tl.start_tick + c * span // 10**6 for c in cuts} - {tl.start_tick, tl.end_tick})
    edges = np.array([tl.start_tick, *inner, tl.end_tick], dtype=np.int64)
    w = tl.weights_ticks(edges, ("ambient", "flash"), frozenset({"flash"}))
    assert (w >= 0).all()
    assert w[:, :, 0].sum(axis=0).tolist() == [tl.exposure_ticks(k) for k in range(4)]
    assert w[:, :, 1].sum() == 0  # no slot turns the flash on: it stays dark


def test_flash_weights_follow_the_slots():
    slots = (SlotSeconds(0, Fraction(1, 1000), frozenset({"flash"})), SlotSeconds(1, Fraction(1, 1000)))
    tl = build_timeline(
        [SegmentSeconds(Fraction(0), slots, 10)], [ReadEvent("F", (0,)), ReadEvent("A", (1,))], 2, "custom"
    )
    w = tl.weights_ticks(np.array([tl.start_tick, tl.end_tick]), ("ambient", "flash"), frozenset({"flash"}))[0]
    ms = int(Fraction(1, 1000) / tl.tick_s)
    assert w.tolist() == [[10 * ms, 10 * ms], [10 * ms, 0]]


def test_a_million_periods_of_1us_slots_are_exact():
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", unit_exposure_s=1.0, periods=10**6, sensor={}))
    assert Fraction(1, 10**6) / tl.tick_s == 1000  # T/N = 1 us slot for bucket 4, ticks of 1 ns
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == 8
    assert [tl.exposure_ticks(k) * tl.tick_s for k in range(4)] == [4, 2, 1, 1]


def test_protocol_needing_more_buckets_than_the_sensor_is_an_error():
    with pytest.raises(ConfigError, match=r"needs 4 buckets but sensor.bucket_count is 2"):
        protocols.build(
            cfg(
                protocol="custom",
                sensor={"bucket_count": 2},
                schedule={"slots": [{"bucket": 4, "duration_s": 1e-3}], "reads": [{"buckets": [4]}]},
            )
        )


def test_two_bucket_photon_efficient():
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", sensor={"bucket_count": 2}))
    assert [r.buckets for r in tl.reads] == [(1,), (0, 1)]
    assert [exposure_s(tl, r) for r in tl.reads] == [Fraction(1, 1000), Fraction(2, 1000)]


def test_custom_schedule_with_drain_and_flash():
    tl = protocols.build(
        cfg(
            protocol="custom",
            periods=4,
            schedule={
                "slots": [
                    {"bucket": 1, "duration_s": 2e-4, "groups": ["flash"]},
                    {"bucket": "drain", "duration_s": 1e-4},
                    {"bucket": 2, "duration_s": 2e-4},
                ],
                "reads": [{"name": "flash", "buckets": [1]}, {"name": "ambient", "buckets": [2]}],
            },
        )
    )
    assert [r.name for r in tl.reads] == ["flash", "ambient"]
    assert tl.switchable_groups() == {"flash"}
    assert (tl.end_tick - tl.start_tick) * tl.tick_s == Fraction(2, 1000)
    assert exposure_s(tl, tl.reads[0]) == Fraction(8, 10000)


def test_storage_time_runs_from_the_first_slot_to_the_read():
    """Dark current's clock (Timeline.storage_ticks): a drain slot before a bucket's first slot does not
    count, interleaved buckets are read at the end of the capture, and a bucket that never collects
    holds nothing. One period of 4 x 1 ms: drain, bucket 1, bucket 2, drain; 3 buckets, bucket 3 unused."""
    ms = Fraction(1, 1000)
    slots = (SlotSeconds(DRAIN, ms), SlotSeconds(0, ms), SlotSeconds(1, ms), SlotSeconds(DRAIN, ms))
    tl = build_timeline(
        [SegmentSeconds(Fraction(0), slots, 3)], [ReadEvent("A", (0,)), ReadEvent("B", (1,))], 3, "custom"
    )
    # the capture spans 12 ms; bucket 1 first collects at 1 ms, bucket 2 at 2 ms
    assert [tl.storage_ticks(k) * tl.tick_s for k in range(3)] == [11 * ms, 10 * ms, 0]
    np.testing.assert_allclose(tl.storage_s(), [11e-3, 10e-3, 0.0], rtol=1e-15, atol=0)
    seq = protocols.build(
        cfg(
            protocol="photon_efficient_hdr",
            unit_exposure_s=0.001,
            periods=8,
            sequential=True,
            sensor={"frame_readout_s": 0.5},
        )
    )
    assert [seq.storage_ticks(k) * seq.tick_s for k in range(4)] == [ms, 2 * ms, 4 * ms, 8 * ms]  # gaps do not count


def test_collecting_intervals_merge_touching_segments_and_skip_drain_only_ones():
    """Segments [0, 3) and [3, 5) ms touch: one interval; [6, 7) after a gap: another; a segment that
    only drains (8..9 ms) collects nothing and is left out (ticks of 1 us here)."""
    ms = Fraction(1, 1000)
    segs = [
        SegmentSeconds(Fraction(0), (SlotSeconds(0, ms),), 3),
        SegmentSeconds(3 * ms, (SlotSeconds(1, ms),), 2),
        SegmentSeconds(6 * ms, (SlotSeconds(0, ms / 2), SlotSeconds(DRAIN, ms / 2)), 1),
        SegmentSeconds(8 * ms, (SlotSeconds(DRAIN, ms),), 1),
    ]
    tl = build_timeline(segs, [ReadEvent("A", (0,)), ReadEvent("B", (1,))], 2, "custom")
    per_ms = int(ms / tl.tick_s)
    assert tl.collecting_intervals() == [(0, 5 * per_ms), (6 * per_ms, 7 * per_ms)]


def test_describe_reads_and_absolute_centroids_by_hand():
    """photon_efficient_hdr, N = 3 periods of 8 ms / 3 (slots 4:2:1:1 of T/3): bucket 4 (J1) is the
    last slot, at [7T/3, 8T/3) + k 8T/3; its centroid is the mean of those midpoints,
    (7.5 T/3) + (8T/3) (N - 1)/2 = 5.1666.. ms, its span [7T/3, 8T); the report names buckets from 1."""
    T = Fraction(1, 1000)
    tl = protocols.build(cfg(protocol="photon_efficient_hdr", unit_exposure_s=0.001, periods=3))
    d = tl.describe_reads()
    assert [r["buckets"] for r in d] == [[4], [3, 4], [2, 3, 4], [1, 2, 3, 4]]
    assert tl.centroid_ticks((3,)) * tl.tick_s == Fraction(15, 2) * T / 3 + 8 * T / 3
    assert tl.centroid_ticks((0,)) * tl.tick_s == 2 * T / 3 + 8 * T / 3  # bucket 1: [0, 4T/3) + k 8T/3
    assert d[0]["centroid_s"] == pytest.approx(float(Fraction(31, 6) * T), rel=1e-15)
    assert (d[0]["span_start_s"], d[0]["span_end_s"]) == pytest.approx((float(7 * T / 3), float(8 * T)), rel=1e-15)
    assert d[0]["span_s"] == pytest.approx(float(8 * T - 7 * T / 3), rel=1e-15)
    assert d[3]["exposure_s"] == pytest.approx(8e-3, rel=1e-15) and d[3]["span_s"] == pytest.approx(8e-3, rel=1e-15)
    # the summed buckets' centroid is the exposure-weighted mean of theirs (J4: all of 8T, centre 4T)
    assert tl.centroid_ticks((0, 1, 2, 3)) * tl.tick_s == 4 * T
    assert [r["destructive"] for r in d] == [False] * 4
    unused = build_timeline([SegmentSeconds(Fraction(0), (SlotSeconds(0, T),), 2)], [ReadEvent("A", (0,))], 2, "custom")
    with pytest.raises(ValueError, match="^these buckets never collect$"):
        unused.centroid_ticks((1,))
    assert unused.span_ticks((1,)) == (0, 0)


def test_exact_common_tick_and_build_checks():
    """exact() keeps exact inputs; common_tick ignores zero durations, counts a duration of exactly
    1 s (gcd(1, 2/3) = 1/3) and refuses a schedule with no time; build_timeline refuses zero-length
    slots and reads of buckets it does not have (1-based in the message), and keeps the protocol name."""
    assert exact(Fraction(1, 3)) == Fraction(1, 3) and exact(2) == 2
    assert common_tick([Fraction(0), Fraction(1, 2)]) == Fraction(1, 2)
    assert common_tick([Fraction(1), Fraction(2, 3)]) == Fraction(1, 3)
    with pytest.raises(ConfigError, match="^capture: the schedule has no time in it$"):
        common_tick([Fraction(0)])
    ms = Fraction(1, 1000)
    with pytest.raises(ConfigError, match=r"^capture: slot durations must be > 0 s \(got 0.0\)$"):
        build_timeline(
            [SegmentSeconds(Fraction(0), (SlotSeconds(0, ms), SlotSeconds(1, Fraction(0))), 1)],
            [ReadEvent("A", (0,))],
            2,
            "custom",
        )
    with pytest.raises(
        ConfigError, match=r"^capture.schedule.reads: read B names bucket\(s\) \[3\]; the schedule has 2$"
    ):
        build_timeline(
            [SegmentSeconds(Fraction(0), (SlotSeconds(0, ms),), 1)],
            [ReadEvent("A", (0,)), ReadEvent("B", (2,))],
            2,
            "custom",
        )
    with pytest.raises(ConfigError, match=r"^capture.periods: must be >= 1$"):
        build_timeline([SegmentSeconds(Fraction(0), (SlotSeconds(0, ms),), 0)], [ReadEvent("A", (0,))], 1, "custom")
    tl = build_timeline([SegmentSeconds(Fraction(0), (SlotSeconds(0, ms),), 1)], [ReadEvent("A", (0,))], 1, "mine")
    assert tl.protocol == "mine" and not tl.sequential
