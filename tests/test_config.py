"""Config loading: validation errors name the key; --set overrides by dotted path."""

import pytest

from mbcapture.config import apply_overrides, load_config, parse_override
from mbcapture.errors import ConfigError


def write(tmp_path, text):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def test_defaults_are_the_paper_sensor():
    cfg = load_config(None, ["scene.name=flatfield"])
    assert (cfg.render.width, cfg.render.height) == (640, 512)
    assert cfg.sensor.bucket_count == 4 and cfg.sensor.pixel_pitch_um == 5.6
    assert cfg.render.variant == "llvm_ad_rgb"


def test_unknown_key_is_named_with_its_path(tmp_path):
    p = write(tmp_path, "scene: {name: flatfield}\nrender: {spp: 4, sppp: 3}\n")
    with pytest.raises(ConfigError, match=r"render\.sppp: unknown key"):
        load_config(p)


def test_unknown_scene_key_is_named(tmp_path):
    p = write(tmp_path, "scene: {name: flatfield, bogus: 1}\n")
    with pytest.raises(ConfigError, match=r"scene\.bogus: unknown key"):
        load_config(p)


def test_wrong_type_and_range(tmp_path):
    with pytest.raises(ConfigError, match=r"render\.spp: .*greater than or equal to 1 \(got 0\)"):
        load_config(None, ["scene.name=flatfield", "render.spp=0"])
    with pytest.raises(ConfigError, match=r"capture\.periods"):
        load_config(None, ["scene.name=flatfield", "capture.periods=many"])
    with pytest.raises(ConfigError, match=r"capture\.unit_exposure_s"):
        load_config(None, ["scene.name=flatfield", "capture.unit_exposure_s=-1"])


def test_malformed_yaml_names_file_and_line(tmp_path):
    p = write(tmp_path, "scene:\n  name: flatfield\nrender: [1, 2\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: line \d+, column \d+: malformed YAML"):
        load_config(p)


def test_missing_file_and_missing_scene(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: config file not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"scene\.name: unknown scene 'atlantis'; expected one of \["):
        load_config(None, ["scene.name=atlantis"])


def test_set_parses_yaml_values():
    assert parse_override("render.spp=4") == (["render", "spp"], 4)
    assert parse_override("scene.radiance=[1,1,1]") == (["scene", "radiance"], [1, 1, 1])
    assert parse_override("capture.sequential=true") == (["capture", "sequential"], True)
    assert apply_overrides({"render": {"spp": 1}}, ["render.width=32"]) == {"render": {"spp": 1, "width": 32}}
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        parse_override("render.spp")
    with pytest.raises(ConfigError, match="render.spp is a value, not a section"):
        apply_overrides({"render": {"spp": 1}}, ["render.spp.x=2"])


def test_custom_needs_schedule_and_others_refuse_it():
    with pytest.raises(ConfigError, match="capture.schedule is required"):
        load_config(None, ["scene.name=flatfield", "capture.protocol=custom"])
    with pytest.raises(ConfigError, match="only read by the 'custom' protocol"):
        load_config(
            None,
            ["scene.name=flatfield", "capture.schedule={slots: [{bucket: 1, duration_s: 1}], reads: [{buckets: [1]}]}"],
        )


def test_negative_slot_duration_is_refused():
    with pytest.raises(ConfigError, match=r"capture\.schedule\.slots\.0\.duration_s"):
        load_config(
            None,
            [
                "scene.name=flatfield",
                "capture.protocol=custom",
                "capture.schedule={slots: [{bucket: 1, duration_s: -1}], reads: [{buckets: [1]}]}",
            ],
        )


def test_resolved_config_round_trips(tmp_path):
    import yaml

    cfg = load_config(None, ["scene.name=flatfield", "render.spp=3"])
    p = write(tmp_path, yaml.safe_dump(cfg.to_yaml_dict()))
    assert load_config(p).to_yaml_dict() == cfg.to_yaml_dict()
