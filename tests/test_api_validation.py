"""The Python API validates what is assigned as the YAML and ``--set`` do, with the same one-line
error, and leaves the config as it was when it refuses."""

from __future__ import annotations

import pytest

from mbcapture import ConfigError, load_config, run_capture

SMALL = ["render.width=32", "render.height=24", "render.spp=2"]


def set_error(override: str) -> str:
    """The error ``--set`` gives, without its origin ('--set KEY=VALUE: ')."""
    with pytest.raises(ConfigError) as info:
        load_config("metronome_hdr", [override])
    return str(info.value).split(": ", 1)[1]


@pytest.mark.parametrize(
    "section,key,value,override",
    [
        ("sensor", "read_noise_e", "abc", "sensor.read_noise_e=abc"),
        ("sensor", "read_noise_e", -5, "sensor.read_noise_e=-5"),
        ("sensor", "read_noise_ee", 3, "sensor.read_noise_ee=3"),
        ("render", "width", 0, "render.width=0"),
        ("capture", "protocol", "nope", "capture.protocol=nope"),
        ("scene", "tempo_bpm", "fast", "scene.tempo_bpm=fast"),
        ("scene", "length_m", 2, "scene.length_m=2"),
    ],
)
def test_assignment_raises_the_set_error_and_keeps_the_old_value(section, key, value, override):
    cfg = load_config("metronome_hdr")
    part = getattr(cfg, section)
    before = part.model_dump()
    with pytest.raises(ConfigError) as info:
        setattr(part, key, value)
    assert str(info.value) == set_error(override)
    assert part.model_dump() == before


def test_a_valid_assignment_takes_and_nested_sections_name_their_key():
    cfg = load_config("metronome_hdr")
    cfg.sensor.read_noise_e = 5
    assert cfg.sensor.read_noise_e == 5.0
    cfg.scene.tempo_bpm = 90
    assert cfg.scene.params().tempo_bpm == 90
    cfg.capture.gate_code = {"family": "global"}
    with pytest.raises(ConfigError, match=r"^capture\.gate_code\.family: Input should be"):
        cfg.capture.gate_code.family = "zzz"


def test_a_run_checks_assignments_against_the_other_sections():
    """Each assignment is checked on its own; what joins two sections is checked when the run starts,
    before anything is rendered."""
    cfg = load_config("metronome_hdr", SMALL)
    cfg.sensor.spectral_response = "Nikon 5100 (NPL)"  # valid alone; needs a spectral variant
    with pytest.raises(ConfigError, match="needs a spectral render.variant"):
        run_capture(cfg, progress=False)
