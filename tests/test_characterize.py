"""EMVA 1288 characterization of the simulated sensor (mbcapture characterize), sensor presets and
their round trip through a datasheet.

Every tolerance is the figure's own standard uncertainty, which mbcapture.sensor.emva derives from the
number of pixels and frames behind it, times Z; the configured value a figure is compared with is
the ensemble value of the config, so the few figures that depend on this one sensor's fixed
pattern (the mean gain of its pixels, the variance of its rows) carry that sampling term too.
"""

from __future__ import annotations

import functools
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from mbcapture.studies import characterize as ch
from mbcapture import load_config
from mbcapture.errors import ConfigError
from mbcapture.sensor.presets import DATASHEET_SCHEMA, preset_names

ROOT = Path(__file__).resolve().parents[1]
#: Figures may lie this many of their standard uncertainties from the configured value (a miss has
#: probability ~6e-5 per figure for a normal error; about 60 figures are checked here).
Z = 4.0
SETTINGS = ch.Settings(width=96, height=96, steps=40, dark_steps=6, frames=12)
FPN = ["sensor.prnu_row=0.004", "sensor.prnu_col=0.003", "sensor.dsnu_row_e=0.6", "sensor.dsnu_col_e=0.8"]


def _measure(overrides, settings=SETTINGS) -> dict:
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", overrides)
    curves = ch.measure(cfg, settings, progress=False)
    return ch.datasheet(cfg, curves, settings, "test")


def _realization(cfg_sensor, name: str, H: int, W: int) -> float:
    """Std of this sensor's sampled value of a configured figure about its ensemble value: the mean
    PRNU gain of H x W pixels (quantum efficiency, responsivity)."""
    if name in ("quantum_efficiency", "responsivity_dn_per_photon"):
        return math.sqrt(cfg_sensor.prnu**2 / (H * W) + cfg_sensor.prnu_row**2 / H + cfg_sensor.prnu_col**2 / W)
    return 0.0


@pytest.fixture(scope="module")
def sheet():
    return _measure(FPN)


@pytest.mark.parametrize("mode", ["bucket", "sum"])
def test_every_figure_is_recovered_within_its_uncertainty(sheet, mode):
    data = sheet["reads"][mode]
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", FPN)
    checked = 0
    for name, configured in data["configured"].items():
        for c, ch_name in enumerate(ch.CHANNELS):
            f = data["channels"][ch_name][name]
            rel = _realization(cfg.sensor, name, SETTINGS.height, SETTINGS.width) * configured[c]
            tol = Z * math.hypot(f["uncertainty"], rel)
            if name == "linearity_error_percent":  # the model is linear: LE is the noise's spread alone
                assert 0 <= f["value"] <= Z * f["uncertainty"], (mode, ch_name, f)
            else:
                assert abs(f["value"] - configured[c]) <= tol, (mode, name, ch_name, f["value"], configured[c], tol)
            checked += 1
    assert checked == 3 * len(data["configured"]) >= 3 * 14
    # the standard's saturation capacity (variance maximum) lies just below the charge limit: within the
    # pixels' spread of saturation (PRNU, 3 sigma) and one step of the series
    for ch_name in ch.CHANNELS:
        sat = data["channels"][ch_name]["saturation_capacity_e"]["value"]
        limit = data["configured"]["charge_limit_e"][0]
        step = ch.SERIES_END * limit / SETTINGS.steps
        prnu = math.sqrt(cfg.sensor.prnu**2 + cfg.sensor.prnu_row**2 + cfg.sensor.prnu_col**2)
        assert limit * (1 - 3 * prnu) - step <= sat <= limit


def test_the_summed_read_has_every_buckets_dark_current_and_the_floating_diffusion_limit(sheet):
    b, s = sheet["reads"]["bucket"]["channels"]["G"], sheet["reads"]["sum"]["channels"]["G"]
    assert s["dark_current_e_per_s"]["value"] == pytest.approx(4 * b["dark_current_e_per_s"]["value"], rel=0.05)
    assert s["charge_limit_e"]["value"] == pytest.approx(40_000, rel=0.01)
    assert b["charge_limit_e"]["value"] == pytest.approx(10_000, rel=0.01)


#: A change of one sensor key, and the figures (green channel, bucket read) it must move.
CHANGES = [
    ("sensor.gain_dn_per_e=0.3", {"system_gain_dn_per_e", "temporal_dark_noise_dn", "responsivity_dn_per_photon"}),
    (
        "sensor.read_noise_e=6",
        {
            "temporal_dark_noise_e",
            "temporal_dark_noise_dn",
            "absolute_sensitivity_threshold_e",
            "absolute_sensitivity_threshold_photons",
            "dynamic_range",
            "dynamic_range_db",
        },
    ),
    (
        "sensor.prnu=0.03",
        {
            "prnu_percent",
            "prnu_pixel_percent",
            "saturation_capacity_e",
            "saturation_photons",
            "snr_max",
            "snr_max_db",
            "dynamic_range",
            "dynamic_range_db",
        },
    ),
    (
        "sensor.full_well_e=6000",
        {
            "charge_limit_e",
            "saturation_capacity_e",
            "saturation_photons",
            "snr_max",
            "snr_max_db",
            "dynamic_range",
            "dynamic_range_db",
        },
    ),
    (
        "sensor.quantum_efficiency=[0.4,0.3,0.45]",
        {
            "quantum_efficiency",
            "responsivity_dn_per_photon",
            "absolute_sensitivity_threshold_photons",
            "saturation_photons",
        },
    ),
]
#: Compared: the figures a datasheet leads with (the others follow from them).
LEADING = [
    "system_gain_dn_per_e",
    "responsivity_dn_per_photon",
    "quantum_efficiency",
    "temporal_dark_noise_dn",
    "temporal_dark_noise_e",
    "charge_limit_e",
    "absolute_sensitivity_threshold_e",
    "dark_current_e_per_s",
    "dsnu_e",
    "prnu_percent",
]


CHANGE_SETTINGS = ch.Settings(width=64, height=64, steps=30, dark_steps=4, frames=8)


@functools.lru_cache(maxsize=1)
def _unchanged() -> dict:
    """The unchanged sensor's figures, measured once per test process for every change below."""
    return _measure([], CHANGE_SETTINGS)["reads"]["bucket"]["channels"]["G"]


@pytest.mark.parametrize("change,moved", CHANGES, ids=[c for c, _ in CHANGES])
def test_a_sensor_change_moves_exactly_the_figures_it_should(change, moved):
    base = _unchanged()
    new = _measure([change], CHANGE_SETTINGS)["reads"]["bucket"]["channels"]["G"]
    for name in LEADING:
        a, b = base[name], new[name]
        z = abs(a["value"] - b["value"]) / math.hypot(a["uncertainty"], b["uncertainty"])
        if name in moved:
            assert z > 2 * Z, (change, name, a["value"], b["value"], z)
        else:
            assert z < Z, (change, name, a["value"], b["value"], z)


# one preset in make test (the quad-bucket sensor the paper describes); the others, 5-6 s each, in make test-slow
@pytest.mark.parametrize(
    "preset", [p if p == "wan2012_quad_bucket" else pytest.param(p, marks=pytest.mark.slow) for p in preset_names()]
)
def test_a_preset_round_trips_through_its_datasheet(tmp_path, preset):
    """Characterize a preset, load the datasheet as a preset, characterize again: the same figures."""
    settings = ch.Settings(width=64, height=64, steps=40, dark_steps=5, frames=8)
    first = _measure([f"sensor.preset={preset}"], settings)
    path = tmp_path / "characterization.json"
    path.write_text(json.dumps(first))
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [f"sensor.preset={path}"])
    assert cfg.sensor.fill_factor == 1.0 and cfg.sensor.bucket_count == first["sensor"]["bucket_count"]
    second = _measure([f"sensor.preset={path}"], settings)
    assert set(second["reads"]) == set(first["reads"])
    sensors = [
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [f"sensor.preset={p}"]).sensor for p in (preset, path)
    ]
    for mode in first["reads"]:
        for c in ch.CHANNELS:
            a, b = first["reads"][mode]["channels"][c], second["reads"][mode]["channels"][c]
            for name in LEADING:
                if name.startswith(("dsnu", "prnu")):
                    continue  # a new sensor (new maps from the same seed and new std): compared below, in variance
                if name == "responsivity_dn_per_photon":
                    continue  # not a preset key: the preset's R is its gain (the channels' mean K) x its QE (R / K per
                    # channel), so it carries the channel's K error; K and QE themselves are compared
                # each sensor's own pixels: their mean gain differs from one sensor to the other
                own = [
                    _realization(s, name, settings.height, settings.width) * f[name]["value"]
                    for s, f in zip(sensors, (a, b))
                ]
                sd = math.sqrt(a[name]["uncertainty"] ** 2 + b[name]["uncertainty"] ** 2 + own[0] ** 2 + own[1] ** 2)
                z = abs(a[name]["value"] - b[name]["value"]) / sd
                assert z < Z, (preset, mode, c, name, a[name]["value"], b[name]["value"])
            for name in ("dsnu_e", "prnu_percent"):
                assert b[name]["value"] == pytest.approx(a[name]["value"], rel=0.15), (preset, mode, c, name)


def test_shipped_presets_fill_the_sensor_and_keys_beside_them_win():
    hdr = ROOT / "configs" / "metronome_hdr.yaml"
    gs = load_config(hdr, ["sensor.preset=global_shutter_cmos"]).sensor
    assert (gs.bucket_count, gs.pixel_pitch_um, gs.adc_bits) == (1, 3.45, 12)
    assert load_config(hdr, ["sensor.preset=global_shutter_cmos", "sensor.read_noise_e=7"]).sensor.read_noise_e == 7
    assert load_config(hdr).sensor.preset == "wan2012_quad_bucket"


@pytest.mark.parametrize(
    "value,message",
    [
        ("nope", "unknown preset 'nope'"),
        ("missing/sheet.json", "file missing/sheet.json not found"),
        ("BAD_SCHEMA", "schema 'other/1'"),
        ("NO_READS", "expected 'sensor' and 'reads.bucket.channels'"),
    ],
)
def test_a_bad_preset_is_one_clear_error(tmp_path, value, message):
    if value == "BAD_SCHEMA":
        value = str(tmp_path / "a.json")
        Path(value).write_text(json.dumps({"schema": "other/1"}))
    if value == "NO_READS":
        value = str(tmp_path / "b.json")
        Path(value).write_text(json.dumps({"schema": DATASHEET_SCHEMA, "sensor": {}}))
    with pytest.raises(ConfigError, match="sensor.preset") as err:
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [f"sensor.preset={value}"])
    assert message in str(err.value)


def test_the_command_writes_a_datasheet_a_browser_shows(tmp_path):
    out = tmp_path / "sheet"
    cmd = [
        sys.executable,
        "-m",
        "mbcapture",
        "characterize",
        "metronome_hdr",
        "--out",
        str(out),
        "--size",
        "48x40",
        "--steps",
        "24",
        "--dark-steps",
        "3",
        "--frames",
        "4",
        "--quiet",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    sheet = json.loads((out / "characterization.json").read_text())
    assert sheet["schema"] == DATASHEET_SCHEMA and sheet["setup"]["film"] == [48, 40]
    html = (out / "report.html").read_text()
    for plot in ("photon_transfer", "snr", "linearity", "spectrograms"):
        for mode in ("bucket", "sum"):
            assert (out / f"{mode}_{plot}.png").stat().st_size > 5000
            assert f"{mode}_{plot}.png" in html
    assert "system gain K" in html and "characterization.json" in html
    bad = subprocess.run([*cmd[:7], "--size", "8x8"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--size must be at least 16x16" in bad.stderr


def test_a_spectral_sensor_is_measured_at_its_wavelengths():
    """The standard's light is monochromatic: a sensor with camera curves has, in each channel, the
    quantum efficiency of its curve at sensor.wavelength_nm (times the fill factor)."""
    import numpy as np

    from mbcapture.sensor.spectral import channel_quantum_efficiency

    settings = ch.Settings(width=48, height=48, steps=30, dark_steps=4, frames=4)
    cfg = load_config(ROOT / "configs" / "metronome_spectral.yaml")
    sheet = ch.datasheet(cfg, ch.measure(cfg, settings, progress=False), settings, "test")
    wl, qe = channel_quantum_efficiency(cfg.sensor)
    for c, name in enumerate(ch.CHANNELS):
        want = cfg.sensor.fill_factor * np.interp(cfg.sensor.wavelength_nm[c], wl, qe[c])
        f = sheet["reads"]["bucket"]["channels"][name]["quantum_efficiency"]
        assert abs(f["value"] - want) <= Z * math.hypot(f["uncertainty"], want * cfg.sensor.prnu / 48), (name, f, want)
    assert sheet["sensor"]["spectral_response"] == cfg.sensor.spectral_response
    with pytest.raises(ConfigError, match="no response at"):
        ch.measure(
            load_config(ROOT / "configs" / "metronome_spectral.yaml", ["sensor.wavelength_nm=[1900,540,460]"]),
            settings,
            progress=False,
        )
