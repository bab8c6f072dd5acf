"""A config's timeline (:func:`build`): its protocol's slots and reads as a
:class:`~mbcapture.timing.timeline.Timeline`.

Protocols are registered by the applications that read them (:func:`mbcapture.application.register_protocol`;
the HDR protocols and ``custom`` in :mod:`mbcapture.apps.hdr`); a protocol gives one period's slots,
repeated ``capture.periods`` times, or a whole :class:`~mbcapture.timing.timeline.Timeline` where it lays
out segments of its own (the time-of-flight sub-frames, :mod:`mbcapture.apps.tof`).

``capture.sequential: true`` turns any of them into the conventional-sensor capture of the
same reads: one contiguous frame per read (its exposure, with the emitter groups its buckets
saw), one after another with ``sensor.frame_readout_s`` between frames, each frame read
destructively.

``capture.gate_code`` turns any of them into a coded capture (:mod:`mbcapture.timing.gatecode`): the
protocol schedules ``capture.gate_code.subframes`` sub-frames as it would schedule that many
buckets, and the code sends each sub-frame to a bucket per pixel. The global identity code
keeps the protocol's reads; any other code reads every bucket once (``B1``, ``B2``, ...), since
what a read holds then differs from pixel to pixel and the application demultiplexes it.
"""

from __future__ import annotations

from fractions import Fraction

from ..application import protocol_builder
from ..config import CaptureConfig
from ..errors import ConfigError
from .gatecode import GateCode, load_array, make_code
from .timeline import ReadEvent, SegmentSeconds, SlotSeconds, Timeline, build_timeline, exact


def need_buckets(cfg: CaptureConfig, needed: int) -> int:
    """``needed``, or a ConfigError naming ``capture.protocol`` when the sensor has fewer buckets."""
    have = cfg.sensor.bucket_count
    if needed > have:
        raise ConfigError(
            f"capture.protocol: {cfg.capture.protocol!r} needs {needed} buckets but sensor.bucket_count is {have}"
        )
    return needed


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
    slots, reads, k = protocol_builder(cfg.capture.protocol)(as_buckets)
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
    if cfg.capture.gate_code is not None:
        if cfg.capture.tof is not None:
            raise ConfigError("capture.gate_code: the time-of-flight protocols use global gates; set it null")
        return _coded(cfg)
    built = protocol_builder(name)(cfg)
    if isinstance(built, Timeline):  # a protocol of several segments (the time-of-flight sub-frames)
        if cfg.capture.sequential:
            raise ConfigError(
                f"capture.sequential: protocol {name!r} lays out its own sub-frames; set capture.sequential false"
            )
        return built
    slots, reads, k = built
    if cfg.capture.sequential:
        return _sequential(slots, reads, cfg.capture.periods, cfg)
    segment = SegmentSeconds(exact(cfg.capture.start_s), tuple(slots), cfg.capture.periods)
    return build_timeline([segment], reads, k, name)
