"""capture.exposure_ratios: the HDR protocols' read exposures for any bucket count (docs/protocols.md)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from mbcapture import load_config, run_capture
from mbcapture.errors import ConfigError
from mbcapture.timing import protocols


def _timeline(protocol: str, *sets: str):
    return protocols.build(load_config(None, [f"capture.protocol={protocol}", *sets]))


def _exposures_in_t(tl, unit_s: float = 1e-3) -> list[Fraction]:
    return [tl.read_exposure_ticks(r) * tl.tick_s / Fraction(repr(unit_s)) for r in tl.reads]


def _span_in_t(tl, unit_s: float = 1e-3) -> Fraction:
    return (tl.end_tick - tl.start_tick) * tl.tick_s / Fraction(repr(unit_s))


@pytest.mark.parametrize("protocol", ["photon_efficient_hdr", "interleaved_hdr"])
def test_the_default_is_powers_of_two_over_every_bucket(protocol):
    default = _timeline(protocol)
    given = _timeline(protocol, "capture.exposure_ratios=[1, 2, 4, 8]")
    assert _exposures_in_t(default) == [1, 2, 4, 8]
    assert default.segments == given.segments and default.reads == given.reads


def test_two_buckets_reach_eight_to_one_in_either_protocol():
    """[1, 8] on a 2-bucket sensor: reads T and 8T. Photon-efficient sums bucket 2 (T) into the second read, so the
    capture spans 8T; interleaved reads each bucket alone and spans 9T."""
    sets = ("capture.exposure_ratios=[1, 8]", "sensor.bucket_count=2")
    pe, il = _timeline("photon_efficient_hdr", *sets), _timeline("interleaved_hdr", *sets)
    assert _exposures_in_t(pe) == _exposures_in_t(il) == [1, 8]
    assert (_span_in_t(pe), _span_in_t(il)) == (8, 9)
    assert [r.buckets for r in pe.reads] == [(1,), (0, 1)] and [r.buckets for r in il.reads] == [(1,), (0,)]
    # the conventional sensor's twin takes the same two exposures one after the other
    seq = _timeline("photon_efficient_hdr", *sets, "capture.sequential=true")
    assert _exposures_in_t(seq) == [1, 8]


def test_ratios_that_are_not_powers_of_two_are_exact():
    """[1, 3, 10] on three buckets: photon-efficient slots 7 : 2 : 1 (each bucket the step between two reads)."""
    tl = _timeline("photon_efficient_hdr", "capture.exposure_ratios=[1, 3, 10]", "sensor.bucket_count=3")
    assert _exposures_in_t(tl) == [1, 3, 10]
    slots = tl.segments[0].slots
    ticks = {b: sum(s.ticks for s in slots if s.bucket == b) for b in range(3)}
    assert [Fraction(ticks[b], ticks[2]) for b in range(3)] == [7, 2, 1]


@pytest.mark.parametrize(
    "sets, names",
    [
        (["capture.exposure_ratios=[2, 8]"], "ascending from 1"),
        (["capture.exposure_ratios=[1, 4, 4]"], "ascending from 1"),
        (["capture.exposure_ratios=[1]"], "capture.exposure_ratios"),
        (["capture.protocol=flash_no_flash", "capture.exposure_ratios=[1, 8]"], "only read by"),
    ],
)
def test_a_bad_list_is_refused_where_the_config_loads(sets, names):
    with pytest.raises(ConfigError, match=names):
        load_config(None, sets)


def test_more_ratios_than_buckets_is_refused_naming_both_keys():
    with pytest.raises(
        ConfigError, match=r"capture.exposure_ratios: 3 reads need 3 buckets .* sensor.bucket_count is 2"
    ):
        _timeline("photon_efficient_hdr", "capture.exposure_ratios=[1, 4, 16]", "sensor.bucket_count=2")


@pytest.mark.render
def test_a_two_bucket_eight_to_one_capture_merges():
    """A tiny flat-field capture at [1, 8] on two buckets: reads of T and 8T whose HDR merge recovers the flat
    radiance (its relative error a few per cent at 1 spp: shot and render noise on 16x12 pixels)."""
    cfg = load_config(
        None,
        [
            "scene.name=flatfield",
            "render.width=16",
            "render.height=12",
            "render.spp=2",
            "sensor.bucket_count=2",
            "capture.exposure_ratios=[1, 8]",
        ],
    )
    res = run_capture(cfg, progress=False)
    assert [r["exposure_s"] for r in res.report["reads"]] == pytest.approx([1e-3, 8e-3])
    assert res.report["capture_span_s"] == pytest.approx(8e-3)
    assert np.isfinite(res.report["metrics"]["hdr_rel_mse"]) and res.report["metrics"]["hdr_rel_mse"] < 0.05
