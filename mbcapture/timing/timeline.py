"""Integer-tick time base, gate schedules, emitter drive and read events.

Time is counted in integer ticks of an exact rational length ``tick_s`` chosen so that every
duration of the schedule is a whole number of ticks (the greatest common divisor of the
durations, subdivided to at most 1 ns so that render strata can end between slot edges). Summing a million float slot durations drifts; integers do not. Every gated
time, weight, span and centroid below is exact.

A schedule is a sequence of :class:`Segment`: a pattern of slots (bucket or drain, duration,
switchable emitter groups on) repeated ``repeats`` times, starting at ``start_tick``. Time
between segments collects nothing (a conventional sensor's frame readout gap). Buckets are
0-based here and 1-based in configs and outputs, like the paper.

The central quantity is the cumulative gated time

    F[k, g](t) = integral_0^t gate_k(u) * drive_g(u) du        (ticks)

evaluated in closed form for any number of periods, so the weights of a time stratum
[t0, t1) are F(t1) - F(t0): the cost follows the number of strata, never the number of slots.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from math import gcd, lcm
from typing import Iterable, Mapping, Sequence

import numpy as np

from .drive import Drive, periodic_oscillation_ticks
from ..errors import ConfigError
from .gatecode import GateCode

DRAIN = -1
_MAX_TICKS = 1 << 62


def exact(seconds: float | Fraction | int) -> Fraction:
    """A float as the exact decimal it was written as (``0.001`` -> 1/1000, not the binary double)."""
    if isinstance(seconds, (Fraction, int)):
        return Fraction(seconds)
    return Fraction(repr(float(seconds)))


def common_tick(durations_s: Iterable[Fraction]) -> Fraction:
    """The largest tick that divides every duration exactly (a rational gcd)."""
    durs = [Fraction(d) for d in durations_s if d != 0]
    if not durs:
        raise ConfigError("capture: the schedule has no time in it")
    den = lcm(*(d.denominator for d in durs))
    num = gcd(*(d.numerator * (den // d.denominator) for d in durs))
    return Fraction(num, den)


@dataclass(frozen=True)
class Slot:
    bucket: int  #: 0-based bucket, or DRAIN
    ticks: int
    groups_on: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Segment:
    start_tick: int
    slots: tuple[Slot, ...]
    repeats: int

    @property
    def period_ticks(self) -> int:
        return sum(s.ticks for s in self.slots)

    @property
    def end_tick(self) -> int:
        return self.start_tick + self.repeats * self.period_ticks

    def _offsets(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum([s.ticks for s in self.slots])[:-1]]).astype(np.int64)

    def gated(self, t: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Ticks in [start, t) spent in the slots selected by ``mask`` (S,) bool, for each t."""
        period = self.period_ticks
        durs = np.array([s.ticks for s in self.slots], dtype=np.int64)
        rel = np.clip(np.asarray(t, dtype=np.int64) - self.start_tick, 0, self.repeats * period)
        n_full = np.minimum(rel // period, self.repeats)
        rem = rel - n_full * period
        per_period = int(durs[mask].sum())
        partial = np.clip(rem[:, None] - self._offsets()[None, :], 0, durs[None, :])[:, mask].sum(axis=1)
        return n_full * per_period + partial

    def drive_oscillation(self, t: np.ndarray, mask: np.ndarray, drive: "Drive", tick_s: Fraction) -> np.ndarray:
        """The oscillating part of integral_start^t gate(u) drive(u) du (ticks, float64) over the
        slots selected by ``mask``, for each t: the finished occurrences of each slot in closed
        form (:func:`mbcapture.timing.drive.periodic_oscillation_ticks`, O(1) in periods), plus the one
        that t cuts."""

        period = self.period_ticks
        out = np.zeros(len(t), dtype=np.float64)
        for off, s, on in zip(self._offsets().tolist(), self.slots, mask):
            if not on or s.ticks == 0:
                continue
            first = self.start_tick + off
            for i, ti in enumerate(np.asarray(t, dtype=np.int64).tolist()):
                done = min(max((ti - first - s.ticks) // period + 1, 0), self.repeats)  # occurrences ended by ti
                val = periodic_oscillation_ticks(drive, tick_s, first, s.ticks, period, done)
                a = first + done * period
                if done < self.repeats and ti > a:  # the occurrence in progress at ti
                    val += periodic_oscillation_ticks(drive, tick_s, a, ti - a, period, 1)
                out[i] += val
        return out


@dataclass(frozen=True)
class ReadEvent:
    """A read of the floating diffusion holding the sum of ``buckets`` (0-based)."""

    name: str
    buckets: tuple[int, ...]
    destructive: bool = False


@dataclass(frozen=True)
class Timeline:
    """A whole capture: segments, reads, and the exact tick length.

    ``n_buckets`` counts charge stores: the sensor's buckets for an interleaved capture, or the
    frames of a conventional sensor for a sequential one (each frame is read destructively, so
    a frame is equivalent to a bucket read once).

    ``code``: a per-pixel gate code (:class:`~mbcapture.timing.gatecode.GateCode`), or None for global
    gates. With a code, a slot's ``bucket`` names a *sub-frame* (0 .. ``n_channels`` - 1) and the
    code says which bucket of each pixel collects it; the reads still name buckets. Everything
    rendered and accumulated is per channel (a sub-frame, or a bucket without a code); the
    sensor routes channels to buckets (:meth:`route`). Per-bucket times of a coded timeline
    (exposure, centroid, gated time) are averages over the code's pixels, exact fractions.
    """

    tick_s: Fraction
    n_buckets: int
    segments: tuple[Segment, ...]
    reads: tuple[ReadEvent, ...]
    protocol: str
    sequential: bool = False
    code: GateCode | None = None

    # ----------------------------------------------------------------- basic quantities
    @property
    def n_channels(self) -> int:
        """What is accumulated: the sub-frames of a coded timeline, else the buckets."""
        return self.code.n_subframes if self.code is not None else self.n_buckets

    def route(self, channels: np.ndarray | None) -> np.ndarray | None:
        """Per-channel arrays (n_channels, H, W, ...) -> per-bucket (n_buckets, H, W, ...): the code's
        routing, or the arrays themselves with global gates."""
        return channels if self.code is None or channels is None else self.code.route(channels)

    def _shares(self, bucket: int) -> list[tuple[int, Fraction]]:
        """(channel, fraction of pixels whose ``bucket`` collects it) for every channel that some
        pixel's ``bucket`` collects; (bucket, 1) without a code."""
        if self.code is None:
            return [(bucket, Fraction(1))]
        sh = self.code.shares()
        return [(c, sh[c][bucket]) for c in range(self.n_channels) if sh[c][bucket] > 0]

    def channel_read_sets(self) -> tuple[tuple[str, ...], tuple[tuple[int, ...], ...]]:
        """The channels each read sums, per distinct pixel code: (names, channel sets). Without a
        code, the reads themselves. The noise budget is met on these (every pixel's read is one)."""
        if self.code is None:
            return tuple(r.name for r in self.reads), tuple(tuple(r.buckets) for r in self.reads)
        vectors, _ = self.code.vectors()
        names, sets = [], []
        for r in self.reads:
            for v in vectors:
                chans = tuple(int(c) for c in np.flatnonzero(np.isin(v, r.buckets)))
                if chans and chans not in sets:
                    names.append(r.name if len(vectors) == 1 else f"{r.name}@code{len(names)}")
                    sets.append(chans)
        return tuple(names), tuple(sets)

    @property
    def start_tick(self) -> int:
        return min(s.start_tick for s in self.segments)

    @property
    def end_tick(self) -> int:
        return max(s.end_tick for s in self.segments)

    def seconds(self, ticks) -> np.ndarray | float:
        """Ticks -> seconds (float64; exact values are kept in ticks)."""
        return np.asarray(ticks, dtype=np.float64) * float(self.tick_s)

    def switchable_groups(self) -> frozenset[str]:
        return frozenset(g for seg in self.segments for s in seg.slots for g in s.groups_on)

    def collecting_intervals(self) -> list[tuple[int, int]]:
        """[start, end) tick intervals of the segments that gate charge into some bucket."""
        out = []
        for seg in sorted(self.segments, key=lambda s: s.start_tick):
            if any(s.bucket != DRAIN for s in seg.slots):
                if out and out[-1][1] == seg.start_tick:
                    out[-1] = (out[-1][0], seg.end_tick)
                else:
                    out.append((seg.start_tick, seg.end_tick))
        return out

    # ----------------------------------------------------------------- gated time
    def gated_ticks(self, t: Sequence[int] | np.ndarray, bucket: int, group: str | None = None) -> np.ndarray:
        """F(t): ticks before each t during which ``bucket`` collects and ``group`` is on.

        ``group=None`` (or an always-on group) counts all the bucket's gated time.
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.int64))
        total = np.zeros(t.shape, dtype=np.int64)
        for seg in self.segments:
            mask = np.array(
                [s.bucket == bucket and (group is None or group in s.groups_on) for s in seg.slots], dtype=bool
            )
            if mask.any():
                total += seg.gated(t, mask)
        return total

    def drive_gated_ticks(
        self, t: Sequence[int] | np.ndarray, bucket: int, group: str | None, drive: "Drive"
    ) -> np.ndarray:
        """Oscillating part of integral_0^t gate_bucket(u) on_group(u) drive(u) du, ticks (float64);
        the constant part is ``drive.c0 * gated_ticks(t, bucket, group)``."""
        t = np.atleast_1d(np.asarray(t, dtype=np.int64))
        total = np.zeros(t.shape, dtype=np.float64)
        if drive.is_constant:
            return total
        for seg in self.segments:
            mask = np.array(
                [s.bucket == bucket and (group is None or group in s.groups_on) for s in seg.slots], dtype=bool
            )
            if mask.any():
                total += seg.drive_oscillation(t, mask, drive, self.tick_s)
        return total

    def weights_ticks(
        self,
        edges: np.ndarray,
        groups: Sequence[str],
        switchable: frozenset[str],
        drives: "Mapping[str, Drive] | None" = None,
    ) -> np.ndarray:
        """W[j, k, g] = ticks of stratum [edges[j], edges[j+1]) in which bucket k collects
        while group g is on (int64, exact). A group in ``switchable`` is on only in the slots
        that name it (a flash no slot names stays dark); every other group is always on.

        ``drives``: group -> :class:`~mbcapture.timing.drive.Drive`. A driven group's weight is the
        exact integral of gate x drive over the stratum (float64 ticks: ``c0`` x the integer
        ticks, plus the closed-form oscillating part), and the result is float64."""
        edges = np.asarray(edges, dtype=np.int64)
        drives = {g: d for g, d in (drives or {}).items() if g in groups}
        out = np.zeros((len(edges) - 1, self.n_channels, len(groups)), dtype=np.float64 if drives else np.int64)
        for k in range(self.n_channels):
            for gi, g in enumerate(groups):
                sel = g if g in switchable else None
                f = self.gated_ticks(edges, k, sel)
                if g in drives:
                    out[:, k, gi] = drives[g].c0 * np.diff(f) + np.diff(
                        self.drive_gated_ticks(edges, k, sel, drives[g])
                    )
                else:
                    out[:, k, gi] = np.diff(f)
        return out

    def exposure_ticks(self, bucket: int) -> int | Fraction:
        """Ticks ``bucket`` collects (a coded timeline: the mean over the code's pixels, exact)."""
        return self.bucket_gated_ticks(bucket, None)

    def bucket_gated_ticks(self, bucket: int, group: str | None) -> int | Fraction:
        """Ticks ``bucket`` collects while ``group`` is on (None: all its gated time); a coded
        timeline's mean over the code's pixels."""
        tot = sum(share * int(self.gated_ticks([self.end_tick], c, group)[0]) for c, share in self._shares(bucket))
        return int(tot) if Fraction(tot).denominator == 1 else Fraction(tot)

    def read_exposure_ticks(self, read: ReadEvent) -> int | Fraction:
        return sum(self.exposure_ticks(b) for b in read.buckets)

    # ----------------------------------------------------------------- spans and centroids
    def _bucket_slot_times(self, bucket: int) -> list[tuple[int, int, int | Fraction, int | Fraction]]:
        """(first start, last end, sum of durations, sum of duration*midpoint*2) per slot that
        ``bucket`` collects; a coded timeline's durations weighted by the share of pixels (spans:
        every slot some pixel's bucket collects)."""
        shares = dict(self._shares(bucket))
        rows = []
        for seg in self.segments:
            off = 0
            P, n = seg.period_ticks, seg.repeats
            for s in seg.slots:
                if s.bucket in shares and s.ticks > 0:
                    w = shares[s.bucket]
                    first = seg.start_tick + off
                    last_end = seg.start_tick + (n - 1) * P + off + s.ticks
                    dur = n * s.ticks
                    # sum over repeats of 2*midpoint*ticks, exact integers
                    mid2 = (2 * (seg.start_tick + off) + s.ticks) * n + 2 * P * (n * (n - 1) // 2)
                    rows.append((first, last_end, dur * w, mid2 * s.ticks * w))
                off += s.ticks
        return rows

    def span_ticks(self, buckets: Iterable[int]) -> tuple[int, int]:
        """First tick and last tick (exclusive) at which any of ``buckets`` collects."""
        rows = [r for b in buckets for r in self._bucket_slot_times(b)]
        if not rows:
            return (0, 0)
        return min(r[0] for r in rows), max(r[1] for r in rows)

    def centroid_ticks(self, buckets: Iterable[int]) -> Fraction:
        """Time centroid of the charge collection of the summed ``buckets`` (exact, in ticks)."""
        rows = [r for b in buckets for r in self._bucket_slot_times(b)]
        total = sum(r[2] for r in rows)
        if total == 0:
            raise ValueError("these buckets never collect")
        return Fraction(sum(r[3] for r in rows), 2 * total)

    def storage_ticks(self, bucket: int) -> int:
        """Ticks ``bucket`` holds charge before it is read, the time its dark current accumulates:
        from its reset to its read. The rule, the same for every capture (the sensor stage
        :func:`mbcapture.exposure.simulate.sense` is the only reader of it):

        * a bucket is reset as its first slot opens (the gate sequencer clears a storage node just
          before it first collects);
        * a conventional sequential frame is read destructively at the end of its own exposure;
          the buckets of an interleaved capture are all read after the capture's last slot;
        * a bucket that never collects is reset just before its read and holds no dark charge: 0;
        * with a per-pixel gate code, the reset is global: as the first slot that any pixel's
          bucket collects opens.

        Longer than the exposure wherever the bucket's slots are interleaved with others."""
        first, last = self.span_ticks([bucket])
        if first == last:
            return 0
        return (last if self.sequential else self.end_tick) - first

    def storage_s(self) -> np.ndarray:
        """(K,) seconds each bucket holds charge before its read (:meth:`storage_ticks`), float64."""
        return np.array([float(self.seconds(self.storage_ticks(k))) for k in range(self.n_buckets)])

    def describe_reads(self) -> list[dict]:
        """Per read: exposure, time span and centroid in seconds (for report.json and plan)."""
        out = []
        for r in self.reads:
            t0, t1 = self.span_ticks(r.buckets)
            out.append(
                {
                    "name": r.name,
                    "buckets": [b + 1 for b in r.buckets],
                    "exposure_s": float(self.read_exposure_ticks(r) * self.tick_s),  # coded: the pixels' mean
                    "span_start_s": float(t0 * self.tick_s),
                    "span_end_s": float(t1 * self.tick_s),
                    "span_s": float((t1 - t0) * self.tick_s),
                    "centroid_s": float(self.centroid_ticks(r.buckets) * self.tick_s),
                    "destructive": r.destructive,
                }
            )
        return out


# --------------------------------------------------------------------------- building
@dataclass(frozen=True)
class SlotSeconds:
    """A slot before the tick is chosen: duration as an exact fraction of a second."""

    bucket: int
    duration_s: Fraction
    groups_on: frozenset[str] = frozenset()


@dataclass(frozen=True)
class SegmentSeconds:
    start_s: Fraction
    slots: tuple[SlotSeconds, ...]
    repeats: int


def build_timeline(
    segments: Sequence[SegmentSeconds],
    reads: Sequence[ReadEvent],
    n_buckets: int,
    protocol: str,
    sequential: bool = False,
    code: GateCode | None = None,
) -> Timeline:
    """Choose the exact tick and convert seconds to integer ticks; check every bound. With a gate
    ``code``, the slots' buckets are its sub-frames and ``n_buckets`` the sensor's buckets."""
    durations = [s.duration_s for seg in segments for s in seg.slots] + [seg.start_s for seg in segments]
    for seg in segments:
        if seg.repeats < 1:
            raise ConfigError("capture.periods: must be >= 1")
        for s in seg.slots:
            if s.duration_s <= 0:
                raise ConfigError(f"capture: slot durations must be > 0 s (got {float(s.duration_s)})")
    # subdivide the common divisor down to <= 1 ns so that strata can end anywhere, not only
    # on slot boundaries (durations stay exact integers)
    tick = common_tick(durations)
    tick /= max(1, -(-tick.numerator * 10**9 // tick.denominator))
    out_segments = []
    for seg in segments:
        slots = tuple(Slot(s.bucket, int(s.duration_s / tick), s.groups_on) for s in seg.slots)
        segment = Segment(int(seg.start_s / tick), slots, seg.repeats)
        if segment.end_tick >= _MAX_TICKS:
            raise ConfigError(
                "capture: the schedule needs more than 2^62 ticks of the common time unit "
                f"({float(tick):.3g} s); use durations with a coarser common divisor"
            )
        out_segments.append(segment)
    for r in reads:
        bad = [b + 1 for b in r.buckets if not 0 <= b < n_buckets]
        if bad:
            raise ConfigError(
                f"capture.schedule.reads: read {r.name} names bucket(s) {bad}; the schedule has {n_buckets}"
            )
    if code is not None:
        used = {s.bucket for seg in segments for s in seg.slots if s.bucket != DRAIN}
        if max(used) >= code.n_subframes:
            raise ConfigError(
                f"capture.gate_code: the schedule has {max(used) + 1} sub-frames, the code {code.n_subframes}"
            )
    tl = Timeline(tick, n_buckets, tuple(out_segments), tuple(reads), protocol, sequential, code)
    for r in tl.reads:
        if tl.read_exposure_ticks(r) == 0:
            raise ConfigError(
                f"capture: read {r.name} sums buckets {[b + 1 for b in r.buckets]} that never collect light"
            )
    return tl
