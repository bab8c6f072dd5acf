"""``mbcapture snr``: a design's analytic SNR against luminance, its dynamic range, and the simulated
flat field that checks it."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from mbcapture import load_config
from mbcapture.studies import dynamic_range as dr

DESIGNS = {
    "photon_efficient_4": [],
    "interleaved_4": ["capture.protocol=interleaved_hdr"],
    "photon_efficient_2_ratio_8": ["sensor.bucket_count=2", "capture.exposure_ratios=[1,8]"],
    "sequential_4": ["capture.sequential=true"],
}


def design(name: str) -> dr.Design:
    return dr.design_of(load_config("metronome_hdr", DESIGNS[name]), name)


@pytest.mark.parametrize("name", list(DESIGNS))
def test_simulated_flat_field_lies_on_the_analytic_curve(name):
    """24 levels of 4000 pixels each; a level's simulated SNR has standard error SNR / sqrt(2 (n - 1))
    (1.1 %). With the analytic curve right, each level falls outside its 95 % interval with
    probability 0.05: more than 4 of 24 has probability 0.008. A formula off by 3 % fails most levels."""
    d = design(name)
    levels = dr.check_levels(d, 24)
    sim = dr.simulated(d, levels, 4000, seed=11)
    want = dr.analytic(d, levels).merged
    z = (sim.snr - want) / sim.se
    assert np.all(np.isfinite(z)), "every check level is below saturation"
    assert np.sum(np.abs(z) > 1.96) <= 4, np.round(z, 1)
    # and the check has teeth: the same points against a curve 3 % lower fail
    z_off = (sim.snr - 0.97 * want) / sim.se
    assert np.sum(np.abs(z_off) > 1.96) > 12


def test_the_merge_dips_where_it_drops_a_read():
    d = design("photon_efficient_4")
    sat = dr.saturation_radiance(d)
    # J3 and J4 (J2's buckets fill as J1's does: bucket 3 is gated T like bucket 4): when one
    # saturates, the merge loses it and its photons
    inside = sat[sat < 0.98 * sat[0]]
    assert inside.size == 2
    for s in inside:
        below, above = dr.analytic(d, np.array([0.99 * s, 1.01 * s])).merged
        assert above < below
    assert np.all(np.isnan(dr.analytic(d, np.array([1.01 * sat[0]])).merged))  # J1 too: nothing left


def test_a_longer_longest_read_extends_the_dynamic_range_by_its_ratio():
    """The same shortest read (same saturation); a longest read 8x longer reaches SNR 1 at about 1/8 the
    radiance: the dynamic range grows by 20 log10(8) = 18.1 dB (within 0.5 dB: the short read's
    share of the merge at SNR 1 is small)."""
    base = ["sensor.bucket_count=2"]
    eight = dr.summary(d8 := dr.design_of(load_config("metronome_hdr", [*base, "capture.exposure_ratios=[1,8]"])),
                       dr.analytic(d8, dr.radiance_grid([d8], 4000)))  # fmt: skip
    d64 = dr.design_of(load_config("metronome_hdr", [*base, "capture.exposure_ratios=[1,64]"]))
    sixty_four = dr.summary(d64, dr.analytic(d64, dr.radiance_grid([d64], 4000)))
    assert sixty_four["saturation_radiance"] == pytest.approx(
        eight["saturation_radiance"], rel=1e-3
    )  # more dark charge in the longer span
    gain = sixty_four["dynamic_range_db"] - eight["dynamic_range_db"]
    assert abs(gain - 20 * math.log10(8)) < 0.5, gain


def test_a_single_read_is_shot_read_and_dark_noise():
    """A conventional one-frame capture: SNR = S / sqrt(S + dark + r^2), S = k L t."""
    cfg = load_config("metronome_hdr", ["capture.sequential=true"])
    d = dataclasses.replace(
        dr.design_of(cfg), reads=((0,),), read_s=np.array([4e-3]), bucket_s=np.array([4e-3]), storage_s=np.array([4e-3])
    )
    s = cfg.sensor
    radiance = np.array([1e-3, 1e-2, 1e-1])
    got = dr.analytic(d, radiance)
    signal = d.k_e * radiance * d.read_s[0]
    r2 = s.read_noise_e**2 + 1 / (12 * s.gain_dn_per_e**2) + s.read_noise_row_e**2
    want = signal / np.sqrt(signal + s.dark_current_e_per_s * d.storage_s[0] + r2)
    np.testing.assert_allclose(got.per_read[0], want, rtol=1e-12)
    np.testing.assert_allclose(got.merged, want, rtol=1e-9)


def test_the_command_writes_the_figure_table_and_summary(tmp_path):
    out = tmp_path / "snr"
    proc = subprocess.run(
        [sys.executable, "-m", "mbcapture", "snr", "metronome_hdr", "--vs", "sensor.bucket_count=2;capture.exposure_ratios=[1,8]",
         "--out", str(out), "--pixels", "500", "--levels", "6"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "dynamic range" in proc.stderr and "within the 95 % interval" in proc.stderr
    doc = json.loads((out / "snr.json").read_text())
    assert [d["label"] for d in doc["designs"]] == [
        "metronome_hdr",
        "sensor.bucket_count=2, capture.exposure_ratios=[1,8]",
    ]
    assert len(doc["designs"][1]["reads"]) == 2
    table = pd.read_parquet(out / "snr.parquet")
    assert set(table["curve"]) >= {"merged", "J1", "J4", "simulated"}
    assert (out / "snr.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_capture_that_is_not_merged_into_hdr_is_refused_in_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "mbcapture", "snr", "flash_no_flash", "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "capture.protocol 'flash_no_flash'" in proc.stderr
    assert not (tmp_path / "o").exists()
