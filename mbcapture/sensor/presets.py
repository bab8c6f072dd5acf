"""Sensor presets: ``sensor.preset`` fills the sensor keys from a shipped preset or from a datasheet.

* A **shipped preset** is a YAML file of sensor keys in ``mbcapture/sensor/presets/``, each value
  commented with where it comes from (:func:`preset_names`).
* A **file**: a YAML file of sensor keys in the same form, or a datasheet written by
  ``mbcapture characterize`` (characterization.json, schema :data:`DATASHEET_SCHEMA`), whose
  measured figures become the keys (:func:`sensor_keys_from_datasheet`). Relative paths are taken
  from the working directory.

Keys set next to ``preset`` in the config win over the preset's.
"""

from __future__ import annotations

import copy
import json
import math
from functools import lru_cache
from pathlib import Path

import yaml

PRESET_DIR = Path(__file__).with_name("presets")
#: The ``schema`` of characterization.json (mbcapture characterize) and of datasheets a preset loads.
DATASHEET_SCHEMA = "mbcapture.emva1288-datasheet/1"

__all__ = ["DATASHEET_SCHEMA", "PRESET_DIR", "load_preset", "preset_names", "sensor_keys_from_datasheet"]


def preset_names() -> list[str]:
    """Names of the shipped presets."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def load_preset(ref: str) -> dict:
    """The sensor keys of preset ``ref``: a shipped preset's name, or a path to a YAML file of sensor
    keys or to a datasheet (characterization.json). Raises ValueError naming the preset or file and
    what was expected."""
    path = PRESET_DIR / f"{ref}.yaml"
    if not path.is_file():
        path = Path(ref)
        if not (path.suffix or "/" in ref):
            raise ValueError(
                f"preset: unknown preset {ref!r}; expected one of {preset_names()} or a path to a "
                "datasheet (characterization.json) or a YAML file of sensor keys"
            )
        if not path.is_file():
            raise ValueError(f"preset: file {ref} not found")
    try:
        stat = path.stat()
        data = copy.deepcopy(_parsed(str(path.resolve()), stat.st_mtime_ns, stat.st_size))
    except (OSError, ValueError, yaml.YAMLError) as exc:
        raise ValueError(
            f"preset: {path}: cannot read it as {'JSON' if path.suffix == '.json' else 'YAML'} ({exc})"
        ) from None
    if not isinstance(data, dict):
        raise ValueError(f"preset: {path}: expected a mapping of sensor keys or a datasheet, got {type(data).__name__}")
    if "schema" in data:
        return sensor_keys_from_datasheet(data, str(path))
    if "preset" in data:
        raise ValueError(f"preset: {path}: a preset may not name another preset")
    return data


@lru_cache(maxsize=64)
def _parsed(path: str, mtime_ns: int, size: int) -> object:
    """The file ``path`` parsed (JSON or YAML by its suffix), once per version of it (its modification
    time and size): a sweep loads the same preset for every point's config."""
    text = Path(path).read_text()
    return json.loads(text) if path.endswith(".json") else yaml.safe_load(text)


def _figure(channels: dict, name: str, source: str, read: str = "bucket") -> list[float]:
    try:
        return [float(channels[c][name]["value"]) for c in ("R", "G", "B")]
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            f"preset: {source}: reads.{read}.channels.<R|G|B>.{name}.value missing or not a number"
        ) from None


def sensor_keys_from_datasheet(sheet: dict, source: str = "datasheet") -> dict:
    """Sensor keys from a datasheet in :data:`DATASHEET_SCHEMA` (``mbcapture characterize``'s
    characterization.json): the bucket read's figures (the full wells from the charge limits of the
    bucket read and of the summed read, where the standard's saturation capacity would lose the
    pixels' spread of saturation at every round trip), averaged over channels where the sensor has one
    value for all (gain, noise, full well, dark current), per channel for the quantum efficiency, and
    the rms over channels for the fixed-pattern components. The quantum efficiency is the pixel's
    (fill factor included), so ``fill_factor`` is 1. Not in an EMVA datasheet, hence left at their
    defaults: temporal row noise, transfer inefficiency, parasitic light."""
    if sheet.get("schema") != DATASHEET_SCHEMA:
        raise ValueError(f"preset: {source}: schema {sheet.get('schema')!r}; expected {DATASHEET_SCHEMA!r}")
    try:
        info = sheet["sensor"]
        reads = sheet["reads"]
        bucket = reads["bucket"]["channels"]
    except (KeyError, TypeError):
        raise ValueError(f"preset: {source}: expected 'sensor' and 'reads.bucket.channels' sections") from None

    def mean(name: str) -> float:
        return float(sum(_figure(bucket, name, source)) / 3)

    def rms(name: str) -> float:
        return math.sqrt(sum(v * v for v in _figure(bucket, name, source)) / 3)

    try:
        count = int(info.get("bucket_count", 1))
        setup = {
            "bucket_count": count,
            "pixel_pitch_um": float(info["pixel_pitch_um"]),
            "adc_bits": int(info["adc_bits"]),
            "black_level_dn": float(info["black_level_dn"]),
            "wavelength_nm": [float(w) for w in info["wavelength_nm"]],
        }
    except (KeyError, TypeError, ValueError) as exc:
        what = (
            exc.args[0]
            if isinstance(exc, KeyError)
            else "bucket_count, pixel_pitch_um, adc_bits, black_level_dn or wavelength_nm"
        )
        raise ValueError(f"preset: {source}: sensor.{what} missing or malformed") from None
    full_well = mean("charge_limit_e")
    summed = reads.get("sum")
    fd = (
        float(sum(_figure(summed.get("channels"), "charge_limit_e", source, "sum")) / 3)
        if isinstance(summed, dict)
        else max(count, 1) * full_well
    )
    return {
        **setup,
        "fill_factor": 1.0,
        "quantum_efficiency": [min(max(q, 1e-6), 1.0) for q in _figure(bucket, "quantum_efficiency", source)],
        "gain_dn_per_e": mean("system_gain_dn_per_e"),
        "read_noise_e": mean("temporal_dark_noise_e"),
        "full_well_e": full_well,
        "fd_full_well_e": max(fd, full_well),
        "dark_current_e_per_s": max(mean("dark_current_e_per_s"), 0.0),
        "dsnu_e": rms("dsnu_pixel_e"),
        "dsnu_row_e": rms("dsnu_row_e"),
        "dsnu_col_e": rms("dsnu_column_e"),
        "prnu": rms("prnu_pixel_percent") / 100,
        "prnu_row": rms("prnu_row_percent") / 100,
        "prnu_col": rms("prnu_column_percent") / 100,
    }
