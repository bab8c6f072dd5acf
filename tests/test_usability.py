"""What a new user hits first (issue 15): where a bad key came from, switching scene on the command
line, an --out that cannot be made, --version, shipped configs by name. No renders."""

import json
import warnings
from importlib import metadata
from pathlib import Path

import pytest

from mbcapture.cli import main
from mbcapture.config import load_config
from mbcapture.errors import ConfigError, ConfigNotice

ROOT = Path(__file__).resolve().parents[1]
HDR = ROOT / "configs" / "metronome_hdr.yaml"


def run_cli(argv, capsys):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


# ----------------------------------------------------------------------------- where a key came from
def test_unknown_key_from_set_names_the_set_and_the_nearest_key():
    with pytest.raises(ConfigError) as e:
        load_config(HDR, ["render.sp=4"])
    msg = str(e.value)
    assert msg.startswith("--set render.sp=4: render.sp: unknown key") and "did you mean render.spp?" in msg
    assert "metronome_hdr.yaml" not in msg  # the file is not to blame


def test_unknown_key_from_the_file_names_the_file(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("render: {sp: 4}\n")
    with pytest.raises(ConfigError) as e:
        load_config(p, ["render.width=32"])  # an unrelated --set is not blamed
    assert str(e.value).startswith(f"{p}: render.sp: unknown key; did you mean render.spp?")


def test_key_of_another_section_is_suggested_and_bad_values_name_their_set():
    with pytest.raises(
        ConfigError, match=r"--set render\.periods=3: render\.periods: unknown key; did you mean capture\.periods\?"
    ):
        load_config(HDR, ["render.periods=3"])
    with pytest.raises(ConfigError, match=r"^--set render\.spp=-3: render\.spp: .*greater than or equal to 1"):
        load_config(HDR, ["render.spp=-3"])
    with pytest.raises(ConfigError, match=r"^--set scene\.phase_s=\.nan: scene\.phase_s: expected a finite number"):
        load_config(HDR, ["scene.phase_s=.nan"])


# ----------------------------------------------------------------------------- switching scene / app
def test_set_scene_name_drops_the_old_scenes_keys_with_a_notice():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cfg = load_config(HDR, ["scene.name=flatfield", "scene.radiance=[2,2,2]"])
    assert cfg.scene.name == "flatfield" and cfg.scene.params().radiance == [2.0, 2.0, 2.0]
    notes = [str(w.message) for w in caught if issubclass(w.category, ConfigNotice)]
    assert len(notes) == 1 and "scene.tempo_bpm" in notes[0] and "'metronome'" in notes[0]
    assert cfg.render.width == 640 and cfg.seed == 1  # the rest of the file is kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no notice when the scene does not change
        load_config(HDR, ["scene.name=metronome", "scene.tempo_bpm=90"])


def test_unknown_scene_key_says_which_scenes_keys_are_valid():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigNotice)
        with pytest.raises(ConfigError) as e:
            load_config(HDR, ["scene.name=flatfield", "scene.tempo_bpm=90"])
    msg = str(e.value)
    assert msg.startswith("--set scene.tempo_bpm=90: scene.tempo_bpm: unknown key for scene 'flatfield'")
    assert "its keys: radiance, fov_deg" in msg


def test_set_app_name_drops_the_old_applications_keys():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cfg = load_config(ROOT / "configs" / "flash_no_flash.yaml", ["app.name=hdr"])
    assert cfg.app.resolve(cfg.capture.protocol)[0].name == "hdr"
    assert any("app.method" in str(w.message) for w in caught)


def test_cli_switches_scene_and_prints_the_notice_on_one_line(capsys):
    rc, out, err = run_cli(["plan", HDR, "--set", "scene.name=flatfield", "--no-probe", "--json"], capsys)
    assert rc == 0, err
    assert json.loads(out)["scene"] == "flatfield"
    assert err.startswith("mbcapture: note: --set scene.name=flatfield") and err.count("\n") == 1


# ----------------------------------------------------------------------------- --out checked before any work
@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_out_that_cannot_be_created_fails_before_any_work(capsys, monkeypatch):
    import mbcapture.capture.pipeline as pipeline

    def no_work(*a, **k):
        raise AssertionError("the capture started before --out was checked")

    monkeypatch.setattr(pipeline, "prepare", no_work)
    rc, _, err = run_cli(["run", HDR, "--out", "/proc/nope", "--quiet"], capsys)
    assert rc == 2 and err.count("\n") == 1
    assert "--out /proc/nope: cannot create a folder in /proc" in err
    assert not Path("/proc/nope").exists()


def test_out_check_leaves_nothing_behind(tmp_path):
    from mbcapture.output.io import check_out_dir

    check_out_dir(tmp_path / "a" / "b" / "c")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- --version, configs by name
def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"mbcapture {metadata.version('mbcapture')}"


def test_shipped_config_by_name_from_any_folder(capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # outside the repository
    rc, out, err = run_cli(["plan", "metronome_hdr", "--no-probe", "--json"], capsys)
    assert rc == 0, err
    assert json.loads(out)["protocol"] == "photon_efficient_hdr"
    assert load_config("flash_no_flash.yaml").capture.protocol == "flash_no_flash"
    rc, _, err = run_cli(["plan", "metronome_hrd", "--no-probe"], capsys)
    assert rc == 2 and "not a shipped config" in err and "did you mean metronome_hdr?" in err


def test_mbcapture_set_applies_after_the_command_line_with_a_notice(monkeypatch):
    monkeypatch.setenv("MBCAPTURE_SET", "render.width=16 'scene.amplitude_deg=45'")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cfg = load_config(HDR, ["render.width=320"])
    assert cfg.render.width == 16 and cfg.scene.params().amplitude_deg == 45
    assert any("$MBCAPTURE_SET adds --set render.width=16" in str(w.message) for w in caught)
    monkeypatch.setenv("MBCAPTURE_SET", "render.sp=4")
    with warnings.catch_warnings(), pytest.raises(ConfigError, match="did you mean render.spp"):
        warnings.simplefilter("ignore", ConfigNotice)
        load_config(HDR)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_converge_checks_its_out_before_the_ladders(capsys, monkeypatch):
    import mbcapture.studies.converge as converge

    def no_work(*a, **k):
        raise AssertionError("the ladders started before --out was checked")

    monkeypatch.setattr(converge, "run_converge", no_work)
    rc, _, err = run_cli(["converge", HDR, "--quick", "--out", "/proc/nope"], capsys)
    assert rc == 2 and "cannot create a folder in /proc" in err


def test_an_unknown_scene_names_the_folders_searched():
    from mbcapture import load_config

    with pytest.raises(ConfigError, match=r"unknown scene 'nosuch'.*scene\.py in .*scenes.*MBCAPTURE_SCENE_PATH"):
        load_config("metronome_hdr", ["scene.name=nosuch"])


def test_a_scene_whose_make_returns_something_else_is_one_line(tmp_path, monkeypatch):
    from mbcapture.scene import scenes

    folder = tmp_path / "broken_make"
    folder.mkdir()
    (folder / "scene.py").write_text(
        "from pydantic import BaseModel\n"
        "DESCRIPTION = 'make returns a dict'\n"
        "class Params(BaseModel):\n    pass\n"
        "def make(params):\n    return {'not': 'a scene'}\n"
    )
    monkeypatch.setenv("MBCAPTURE_SCENE_PATH", str(tmp_path))
    scenes.load_module.cache_clear()
    try:
        with pytest.raises(
            ConfigError, match=r"broken_make/scene.py: make\(params\) must return .*SceneModel, got dict"
        ):
            scenes.make_scene("broken_make", scenes.load_module("broken_make").Params())
    finally:
        scenes.load_module.cache_clear()


def test_a_config_path_that_does_not_exist_names_the_shipped_configs():
    from mbcapture.config import resolve_config_path

    with pytest.raises(
        ConfigError, match=r"configs/metronome_hrd.yaml: config file not found .*metronome_hdr.*did you mean"
    ):
        resolve_config_path("configs/metronome_hrd.yaml")


@pytest.mark.render
def test_quiet_keeps_the_summary_and_silent_prints_nothing(tmp_path, capsys):
    """`mbcapture run --quiet`: no status line or bar, the final summary printed; `--silent`: nothing."""
    tiny = [
        "--set",
        "render.width=16",
        "--set",
        "render.height=12",
        "--set",
        "render.spp=1",
        "--set",
        "render.cache=off",
    ]
    assert main(["run", "metronome_hdr", "--out", str(tmp_path / "q"), "--quiet", *tiny]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"wrote {tmp_path / 'q'}/") and "HDR" in out and "stage" not in err
    assert main(["run", "metronome_hdr", "--out", str(tmp_path / "s"), "--silent", *tiny]) == 0
    out, err = capsys.readouterr()
    assert out == "" and "stage" not in err


def test_every_long_command_takes_quiet_and_silent():
    """run, characterize, snr, figures and sweep: the same two flags, refused together."""
    from mbcapture.cli import _parser

    parser = _parser()
    for argv in (
        ["run", "metronome_hdr"],
        ["characterize", "metronome_hdr"],
        ["snr", "metronome_hdr"],
        ["figures"],
        ["sweep", "bucket_designs"],
    ):
        for flag in ("--quiet", "--silent"):
            assert getattr(parser.parse_args([*argv, flag]), flag[2:]) is True, (argv, flag)
        with pytest.raises(SystemExit):
            parser.parse_args([*argv, "--quiet", "--silent"])


def test_snr_quiet_keeps_its_summary_and_silent_prints_nothing(tmp_path, capsys):
    assert main(["snr", "metronome_hdr", "--out", str(tmp_path / "q"), "--pixels", "0", "--quiet"]) == 0
    assert "dynamic range" in capsys.readouterr().err
    assert main(["snr", "metronome_hdr", "--out", str(tmp_path / "s"), "--pixels", "0", "--silent"]) == 0
    out, err = capsys.readouterr()
    assert out == "" and err == "" and (tmp_path / "s" / "snr.json").exists()
