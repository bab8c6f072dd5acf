"""Capture protocols: each builds a :class:`~mbcapture.timeline.Timeline` from the config.

``photon_efficient_hdr``
    Slots 4:2:1:1 (for K buckets: 2^(K-2) : ... : 2 : 1 : 1) per period; non-destructive
    reads of bucket K, K+(K-1), ..., all: exposures T, 2T, 4T, ..., 2^(K-1) T in 2^(K-1) T
    (the paper's section 4).
``interleaved_hdr``
    Slots 8:4:2:1 (2^(K-1) : ... : 1), each bucket read directly: the same exposures in
    (2^K - 1) T (Wan et al. 2012; the paper's figure 9).
``custom``
    One period of slots from ``capture.schedule`` repeated ``capture.periods`` times.

``capture.sequential: true`` turns any of them into the conventional-sensor capture of the
same reads: one contiguous frame per read (its exposure, with the emitter groups its buckets
saw), one after another with ``sensor.frame_readout_s`` between frames, each frame read
destructively.

``capture.gate_code`` turns any of them into a coded capture (:mod:`mbcapture.gatecode`): the
protocol schedules ``capture.gate_code.subframes`` sub-frames as it would schedule that many
buckets, and the code sends each sub-frame to a bucket per pixel. The global identity code
keeps the protocol's reads; any other code reads every bucket once (``B1``, ``B2``, ...), since
what a read holds then differs from pixel to pixel and the application demultiplexes it.
"""

from __future__ import annotations

from fractions import Fraction
from typing import TYPE_CHECKING, Callable

from . import application as apps
from .errors import ConfigError
from .gatecode import GateCode, load_array, make_code
from .timeline import (
    DRAIN,
    ReadEvent,
    SegmentSeconds,
    SlotSeconds,
    Timeline,
    build_timeline,
    exact,
)

if TYPE_CHECKING:  # protocols sit below config: a config validates its protocol name against this registry
    from .config import CaptureConfig

Builder = Callable[["CaptureConfig"], tuple[list[SlotSeconds], list[ReadEvent], int]]
_REGISTRY: dict[str, Builder] = {}
_APP: dict[str, str] = {}


def register(name: str, app: str = "hdr") -> Callable[[Builder], Builder]:
    """Decorator: ``fn(cfg) -> (slots of one period, reads, buckets used)`` is protocol ``name``;
    ``app`` is the application (:mod:`mbcapture.apps`) that reconstructs its reads by default."""

    def deco(fn: Builder) -> Builder:
        _REGISTRY[name] = fn
        _APP[name] = app
        return fn

    return deco


def _load() -> None:
    apps.load_all()  # application modules register their own protocols


def names() -> list[str]:
    _load()
    return sorted(_REGISTRY)


def default_app(protocol: str) -> str:
    _check(protocol)
    return _APP[protocol]


def _check(name: str) -> None:
    _load()
    if name not in _REGISTRY:
        raise ConfigError(f"capture.protocol: unknown protocol {name!r}; expected one of {names()}")


def _need_buckets(cfg: CaptureConfig, needed: int) -> int:
    have = cfg.sensor.bucket_count
    if needed > have:
        raise ConfigError(
            f"capture.protocol: {cfg.capture.protocol!r} needs {needed} buckets but sensor.bucket_count is {have}"
        )
    return needed


@register("photon_efficient_hdr")
def photon_efficient_hdr(cfg: CaptureConfig):
    """One period: bucket 1 gets 2^(K-2) units, ..., bucket K-1 one unit, bucket K one unit."""
    k = _need_buckets(cfg, max(cfg.sensor.bucket_count, 2))
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    units = [2 ** (k - 2 - i) for i in range(k - 1)] + [1]
    slots = [SlotSeconds(b, T * u / N) for b, u in enumerate(units)]
    reads = [ReadEvent(f"J{i + 1}", tuple(range(k - 1 - i, k))) for i in range(k)]
    return slots, reads, k


@register("interleaved_hdr")
def interleaved_hdr(cfg: CaptureConfig):
    """One period: bucket 1 gets 2^(K-1) units, ..., bucket K one unit; each read directly."""
    k = _need_buckets(cfg, cfg.sensor.bucket_count)
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    slots = [SlotSeconds(b, T * 2 ** (k - 1 - b) / N) for b in range(k)]
    reads = [ReadEvent(f"J{i + 1}", (k - 1 - i,)) for i in range(k)]
    return slots, reads, k


@register("custom")
def custom(cfg: CaptureConfig):
    sched = cfg.capture.schedule
    used = {s.bucket for s in sched.slots if s.bucket != "drain"} | {b for r in sched.reads for b in r.buckets}
    bad = sorted(b for b in used if b < 1)
    if bad:
        raise ConfigError(f"capture.schedule: buckets are numbered from 1 (got {bad})")
    k = _need_buckets(cfg, max(used))
    slots = [
        SlotSeconds(DRAIN if s.bucket == "drain" else s.bucket - 1, exact(s.duration_s), frozenset(s.groups))
        for s in sched.slots
    ]
    reads = [ReadEvent(r.name or f"J{i + 1}", tuple(b - 1 for b in r.buckets)) for i, r in enumerate(sched.reads)]
    names_ = [r.name for r in reads]
    if len(set(names_)) != len(names_):
        raise ConfigError(f"capture.schedule.reads: read names must be unique (got {names_})")
    return slots, reads, k


def _sequential(slots: list[SlotSeconds], reads: list[ReadEvent], periods: int, cfg: CaptureConfig) -> Timeline:
    """The same reads captured one after another on a conventional sensor."""
    gap = exact(cfg.sensor.frame_readout_s)
    segments, frames = [], []
    t = exact(cfg.capture.start_s)
    for i, r in enumerate(reads):
        exposure = sum((s.duration_s for s in slots if s.bucket in r.buckets), Fraction(0)) * periods
        groups = {s.groups_on for s in slots if s.bucket in r.buckets}
        if len(groups) > 1:
            raise ConfigError(
                f"capture.sequential: read {r.name} sums buckets lit by different emitter groups; "
                "a single conventional frame cannot reproduce it"
            )
        segments.append(SegmentSeconds(t, (SlotSeconds(i, exposure, groups.pop()),), 1))
        frames.append(ReadEvent(r.name, (i,), destructive=True))
        t += exposure + gap
    return build_timeline(segments, frames, len(frames), cfg.capture.protocol, sequential=True)


def gate_code(cfg: CaptureConfig, subframes: int) -> GateCode:
    """The per-pixel gate code ``capture.gate_code`` describes, for ``subframes`` sub-frames."""
    spec = cfg.capture.gate_code
    return make_code(
        spec.family,
        subframes,
        cfg.sensor.bucket_count,
        width=cfg.render.width,
        height=cfg.render.height,
        tile=spec.tile,
        seed=cfg.seed if spec.seed is None else spec.seed,
        array=load_array(spec.file) if spec.file is not None else None,
    )


def _coded(cfg: CaptureConfig) -> Timeline:
    spec = cfg.capture.gate_code
    if cfg.capture.sequential:
        raise ConfigError(
            "capture.gate_code: a conventional sequential capture has one bucket and no per-pixel gates; "
            "set capture.sequential false or capture.gate_code null"
        )
    if spec.subframes is None and spec.family != "global":
        raise ConfigError(
            f"capture.gate_code.subframes: required by family {spec.family!r}: how many sub-frames the "
            f"protocol {cfg.capture.protocol!r} schedules (as it would schedule that many buckets)"
        )
    subframes = spec.subframes or cfg.sensor.bucket_count
    # the protocol schedules its sub-frames as it would schedule that many buckets
    as_buckets = cfg.model_copy(update={"sensor": cfg.sensor.model_copy(update={"bucket_count": subframes})})
    slots, reads, k = _REGISTRY[cfg.capture.protocol](as_buckets)
    code = gate_code(cfg, k)
    if not code.identity:
        reads = [ReadEvent(f"B{b + 1}", (b,)) for b in range(code.n_buckets)]
    elif k > cfg.sensor.bucket_count:
        raise ConfigError(
            f"capture.gate_code.subframes: {k} sub-frames sent to buckets 1..{k} by the global code, "
            f"but sensor.bucket_count is {cfg.sensor.bucket_count}"
        )
    segment = SegmentSeconds(exact(cfg.capture.start_s), tuple(slots), cfg.capture.periods)
    return build_timeline([segment], reads, code.n_buckets, cfg.capture.protocol, code=code)


def build(cfg: CaptureConfig) -> Timeline:
    """The capture's timeline (interleaved, or sequential when ``capture.sequential``, or coded per
    pixel when ``capture.gate_code``)."""
    name = cfg.capture.protocol
    _check(name)
    if cfg.capture.gate_code is not None:
        return _coded(cfg)
    slots, reads, k = _REGISTRY[name](cfg)
    if cfg.capture.sequential:
        return _sequential(slots, reads, cfg.capture.periods, cfg)
    segment = SegmentSeconds(exact(cfg.capture.start_s), tuple(slots), cfg.capture.periods)
    return build_timeline([segment], reads, k, name)
