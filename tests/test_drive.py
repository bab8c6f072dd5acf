"""Emitter drive integrated exactly into the weights: closed form against brute-force integration."""

from fractions import Fraction

import numpy as np
import pytest

from mbcapture.timing.drive import Drive, periodic_oscillation_ticks
from mbcapture.errors import ConfigError
from mbcapture.timing.timeline import DRAIN, ReadEvent, SegmentSeconds, SlotSeconds, build_timeline

MS = Fraction(1, 1000)
#: one period: buckets 1..4 and a drain, 0.8 ms (1/P = 1250 Hz exactly: the resonant case is exact)
SLOTS = (
    SlotSeconds(0, 3 * MS / 10),
    SlotSeconds(1, 2 * MS / 10),
    SlotSeconds(DRAIN, MS / 10),
    SlotSeconds(2, MS / 10),
    SlotSeconds(3, MS / 10),
)
PERIOD_S = float(sum(s.duration_s for s in SLOTS))


def interleaved(periods: int, start_s=Fraction(37, 10**5)):
    reads = [ReadEvent(f"B{k + 1}", (k,)) for k in range(4)]
    return build_timeline([SegmentSeconds(start_s, SLOTS, periods)], reads, 4, "test")


def gate_intervals_s(tl, bucket):
    """Every [start, end) of ``bucket``'s gate, seconds (float), enumerated occurrence by occurrence."""
    out = []
    tick = float(tl.tick_s)
    for seg in tl.segments:
        off = 0
        for s in seg.slots:
            if s.bucket == bucket:
                n = np.arange(seg.repeats, dtype=np.float64)
                a = (seg.start_tick + off + n * seg.period_ticks) * tick
                out.append(np.stack([a, a + s.ticks * tick], axis=1))
            off += s.ticks
    return np.concatenate(out) if out else np.zeros((0, 2))


def brute_gauss(tl, edges, bucket, drive, nodes=8):
    """W[j] = integral over stratum j of gate x drive, by Gauss-Legendre on every clipped gate
    occurrence (numerical, occurrence by occurrence: cost grows with periods), in ticks."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    iv = gate_intervals_s(tl, bucket)
    tick = float(tl.tick_s)
    out = []
    for t0, t1 in zip(edges[:-1] * tick, edges[1:] * tick):
        a, b = np.maximum(iv[:, 0], t0), np.minimum(iv[:, 1], t1)
        keep = b > a
        a, b = a[keep], b[keep]
        mid, half = (a + b) / 2, (b - a) / 2
        vals = drive(mid[:, None] + half[:, None] * x[None, :])
        out.append(float((half * (vals @ w)).sum()) / tick)
    return np.array(out)


def brute_sampled(tl, edges, bucket, drive, cell_ticks=2000):
    """The same by fine sampling of gate(t) x drive(t): the midpoint rule on a 2 us grid aligned
    with the slot edges (so the gate is constant in every cell; strata cut the end cells)."""
    tick = float(tl.tick_s)
    seg = tl.segments[0]
    P = seg.period_ticks
    offs = np.concatenate([[0], np.cumsum([s.ticks for s in seg.slots])])
    assert seg.start_tick % cell_ticks == 0 and all(o % cell_ticks == 0 for o in offs)
    out = []
    for t0, t1 in zip(edges[:-1], edges[1:]):
        inner = np.arange(-(-t0 // cell_ticks) * cell_ticks, t1, cell_ticks)
        b = np.unique(np.concatenate([[t0], inner, [t1]])).astype(np.float64)
        mid, width = (b[:-1] + b[1:]) / 2, np.diff(b)
        rel = mid - seg.start_tick
        inside = (rel >= 0) & (rel < seg.repeats * P)
        slot = np.searchsorted(offs, np.mod(rel, P), side="right") - 1
        gate = inside & np.isin(slot, [i for i, s in enumerate(seg.slots) if s.bucket == bucket])
        out.append(float((gate * drive(mid * tick) * width).sum()))
    return np.array(out)


def midpoint_bound_ticks(drive, cell_s, length_ticks):
    """Midpoint-rule error bound: per cell width^3/24 max|drive''|, summed over the stratum."""
    return length_ticks * sum(abs(a) * (2 * np.pi * f * cell_s) ** 2 / 24 for a, f, _ in drive.terms)


def oscillating_weights(tl, edges, drive):
    """(J, K) oscillating part of the weights, ticks: the total minus c0 x the exact gated ticks."""
    w = tl.weights_ticks(edges, ["amb"], frozenset(), {"amb": drive})[:, :, 0]
    const = tl.weights_ticks(edges, ["amb"], frozenset())[:, :, 0]
    return w, const


FLICKERS = {
    "mains_100Hz": Drive.mains_flicker(50.0, 1.0, 0.3),
    "ntsc_119.88Hz": Drive.mains_flicker(59.94, 0.8, -1.1),
    "incommensurate_two_terms": Drive(1.0, ((0.4, 97.31, 0.7), (-0.25, 1234.567, 2.0))),
    "resonant_1/P": Drive(1.0, ((0.9, 1 / PERIOD_S, 0.2),)),  # f P = 1: every period adds in phase
    "half_resonant_1/(2P)": Drive(1.0, ((0.9, 0.5 / PERIOD_S, 0.2),)),  # theta/2 = pi/2 ... sign alternates
}


@pytest.mark.parametrize("name", list(FLICKERS))
@pytest.mark.parametrize("periods", [1, 7, 300])
def test_weights_match_fine_sampling(name, periods):
    drive = FLICKERS[name]
    tl = interleaved(periods)
    rng = np.random.default_rng(periods)
    inner = np.sort(rng.integers(tl.start_tick, tl.end_tick, size=4))
    edges = np.unique(np.concatenate([[tl.start_tick - 5], inner, [tl.end_tick + 3]]))
    w, const = oscillating_weights(tl, edges, drive)
    tol = midpoint_bound_ticks(drive, 2e-6, np.diff(edges)) + 1e-6 * np.diff(edges)  # + float summation
    for k in range(4):
        ref = brute_sampled(tl, edges, k, drive)
        assert np.all(np.abs(w[:, k] - ref) <= tol), (k, w[:, k] - ref, tol)
    # the drive matters: the exact weights are not c0 x gated ticks
    assert np.abs(w - drive.c0 * const).max() > 100 * tol.max()


@pytest.mark.parametrize("name", list(FLICKERS))
@pytest.mark.parametrize("periods", [3, 100_000])
def test_oscillating_part_matches_gauss_quadrature_over_many_periods(name, periods):
    """10^5 periods (80 s of capture): the closed form is O(1) per stratum; quadrature walks every period."""
    drive = FLICKERS[name]
    tl = interleaved(periods)
    rng = np.random.default_rng(7)
    edges = np.unique(np.concatenate([[tl.start_tick], rng.integers(tl.start_tick, tl.end_tick, 5), [tl.end_tick]]))
    w, const = oscillating_weights(tl, edges, drive)
    for k in range(4):
        ref = brute_gauss(tl, edges, k, drive)
        osc, osc_ref = w[:, k] - drive.c0 * const[:, k], ref - drive.c0 * const[:, k]
        scale = np.abs(const[:, k]).max()
        # float phases of a 75 s quadrature: ~1e-11 rad each, summed over 1e5 occurrences
        np.testing.assert_allclose(osc, osc_ref, rtol=1e-7, atol=1e-9 * scale)


def test_resonant_flicker_builds_up_with_periods():
    """f = 1/P: every period sees the same phase, so the oscillating part grows as N (no cancellation)."""
    drive = FLICKERS["resonant_1/P"]
    osc = []
    for n in (10, 10_000):
        tl = interleaved(n, start_s=Fraction(0))
        w, const = oscillating_weights(tl, np.array([tl.start_tick, tl.end_tick]), drive)
        osc.append(w[0] - const[0])
    np.testing.assert_allclose(osc[1], 1000 * osc[0], rtol=1e-9)
    assert np.abs(osc[0]).min() > 0.01 * const[0].min() / 1000  # not a vanishing quantity


def test_constant_part_stays_exact_integer_ticks():
    tl = interleaved(100_000)
    edges = np.array([tl.start_tick, tl.start_tick + 12345, tl.end_tick])
    plain = tl.weights_ticks(edges, ["lamp", "amb"], frozenset())
    assert plain.dtype == np.int64  # no drives: unchanged, exact
    driven = tl.weights_ticks(edges, ["lamp", "amb"], frozenset(), {"amb": Drive(2.5)})
    assert driven.dtype == np.float64
    np.testing.assert_array_equal(driven[:, :, 0], plain[:, :, 0])  # the undriven group: exact ticks
    np.testing.assert_array_equal(driven[:, :, 1], 2.5 * plain[:, :, 1])  # a constant drive: c0 x ticks


def test_closed_form_single_runs_against_sampling():
    """periodic_oscillation_ticks alone: count intervals, incommensurate frequency, against a grid."""
    tick = Fraction(1, 10**6)  # 1 us ticks
    drive = Drive(1.0, ((0.6, 97.31, 0.4),))
    for start, dur, period, count in [(123, 400, 750, 1), (0, 750, 750, 50), (5, 1, 3, 2000), (10**7, 333, 1000, 400)]:
        got = periodic_oscillation_ticks(drive, tick, start, dur, period, count)
        n = np.arange(count)[:, None]
        u = (np.arange(200) + 0.5) / 200 * dur
        t = (start + n * period + u[None, :]) * float(tick)
        ref = ((drive(t) - drive.c0).sum(axis=1) * dur / 200).sum()
        # midpoint rule: relative error (w dur/200)^2 / 24 per interval
        w_dur = 2 * np.pi * 97.31 * dur * float(tick)
        assert got == pytest.approx(ref, rel=1e-9 + (w_dur / 200) ** 2, abs=1e-9 * count * dur)


def test_cost_does_not_grow_with_periods():
    import time

    drive = FLICKERS["incommensurate_two_terms"]
    times = []
    for periods in (10, 10**7):
        tl = interleaved(periods)
        edges = np.linspace(tl.start_tick, tl.end_tick, 33).round().astype(np.int64)
        t0 = time.perf_counter()
        tl.weights_ticks(edges, ["amb"], frozenset(), {"amb": drive})
        times.append(time.perf_counter() - t0)
    assert times[1] < 20 * times[0] + 0.05  # closed form: same work for 10 and 10^7 periods


def test_sequential_frames_sample_different_flicker_phases():
    """Three contiguous 1/300 s frames of a 100 Hz flicker: each sees a different mean drive, and
    the three together see exactly one full cycle (mean 1)."""
    third = Fraction(1, 300)
    segs = [SegmentSeconds(i * third, (SlotSeconds(i, third),), 1) for i in range(3)]
    tl = build_timeline(segs, [ReadEvent(f"F{i}", (i,), True) for i in range(3)], 3, "seq", sequential=True)
    drive = Drive.mains_flicker(50.0)  # 1 - cos(2 pi 100 t)
    w = tl.weights_ticks(np.array([0, tl.end_tick]), ["amb"], frozenset(), {"amb": drive})[0, :, 0]
    gains = w / tl.weights_ticks(np.array([0, tl.end_tick]), ["amb"], frozenset())[0, :, 0]
    # by hand: mean of 1 - cos over [i/3, (i+1)/3) of a cycle = 1 - (sin(2 pi (i+1)/3) - sin(2 pi i/3)) / (2 pi / 3)
    expect = [1 - (np.sin(2 * np.pi * (i + 1) / 3) - np.sin(2 * np.pi * i / 3)) / (2 * np.pi / 3) for i in range(3)]
    np.testing.assert_allclose(gains, expect, rtol=1e-12)
    assert gains.mean() == pytest.approx(1.0, rel=1e-12)
    assert gains.max() - gains.min() > 0.8


def test_mains_flicker_is_sin_squared_and_bad_drives_are_refused():
    t = np.linspace(0, 0.05, 1001)
    np.testing.assert_allclose(Drive.mains_flicker(50.0)(t), 2 * np.sin(2 * np.pi * 50 * t) ** 2, atol=1e-12)
    np.testing.assert_allclose(Drive.mains_flicker(60.0, 0.5)(t), 1 - 0.5 * np.cos(2 * np.pi * 120 * t), atol=1e-12)
    with pytest.raises(ConfigError, match="negative"):
        Drive(0.5, ((0.6, 100.0, 0.0),))
    with pytest.raises(ConfigError, match="frequencies"):
        Drive(1.0, ((0.5, 0.0, 0.0),))
    with pytest.raises(ConfigError, match="depth"):
        Drive.mains_flicker(50.0, 1.5)


def test_driven_weights_of_switched_groups_over_segments_and_repeated_slots():
    """Two segments (a gap between them), a bucket gated twice per period, a switchable lamp on in
    some of its slots only, both groups driven: every weight equals Gauss quadrature over exactly the
    gate occurrences in which the bucket collects with the group on (a slot's contributions add
    up across slots, segments and groups are kept apart)."""
    lamp = frozenset({"lamp"})
    seg_a = SegmentSeconds(
        Fraction(0),
        (
            SlotSeconds(0, 2 * MS / 10, lamp),
            SlotSeconds(1, MS / 10),
            SlotSeconds(0, 15 * MS / 100),
            SlotSeconds(DRAIN, 5 * MS / 100),
        ),
        5,
    )
    seg_b = SegmentSeconds(4 * MS, (SlotSeconds(1, 3 * MS / 10, lamp), SlotSeconds(0, MS / 10, lamp)), 3)
    tl = build_timeline([seg_a, seg_b], [ReadEvent("A", (0,)), ReadEvent("B", (1,))], 2, "test")
    drives = {"amb": Drive(1.0, ((0.5, 997.0, 0.3),)), "lamp": Drive(2.0, ((-0.8, 1733.0, 1.1), (0.3, 211.0, 0.0)))}
    edges = np.array([tl.start_tick, tl.start_tick + (tl.end_tick - tl.start_tick) // 3, tl.end_tick], dtype=np.int64)
    w = tl.weights_ticks(edges, ["amb", "lamp"], lamp, drives)
    x, gw = np.polynomial.legendre.leggauss(8)
    tick = float(tl.tick_s)
    for k in range(2):
        for gi, g in enumerate(["amb", "lamp"]):
            iv = []
            for seg in tl.segments:
                off = 0
                for s in seg.slots:
                    if s.bucket == k and (g == "amb" or g in s.groups_on):
                        a = (seg.start_tick + off + np.arange(seg.repeats) * seg.period_ticks) * tick
                        iv.append(np.stack([a, a + s.ticks * tick], axis=1))
                    off += s.ticks
            iv = np.concatenate(iv)
            ref = []
            for t0, t1 in zip(edges[:-1] * tick, edges[1:] * tick):
                a, b = np.maximum(iv[:, 0], t0), np.minimum(iv[:, 1], t1)
                a, b = a[b > a], b[b > a]
                mid, half = (a + b) / 2, (b - a) / 2
                ref.append(float((half * (drives[g](mid[:, None] + half[:, None] * x[None, :]) @ gw)).sum()) / tick)
            np.testing.assert_allclose(w[:, k, gi], ref, rtol=1e-9, err_msg=f"bucket {k}, group {g}")
