"""Every config key is documented, and every shipped config loads, plans and (tiny) runs."""

import re
from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config, run_capture
from mbcapture.config import scene_of
from mbcapture.timing import protocols
from mbcapture.docgen import config_markdown
from mbcapture.exposure.plan import make_plan

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))
SLOW_CONFIGS = ("hdr_video.yaml", "rgb_illumination.yaml", "flash_matting.yaml")


def test_config_doc_is_up_to_date():
    doc = (ROOT / "docs" / "config.md").read_text()
    assert doc == config_markdown(), "docs/config.md is stale: run `python -m mbcapture.docgen > docs/config.md`"


def test_every_key_has_a_description():
    assert "|  |" not in config_markdown().replace("| (section) |  |", "")


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_shipped_config_loads_and_plans(path):
    cfg = load_config(path)
    scene = scene_of(cfg)  # the one scene of a config (a time-of-flight capture adds its phase groups)
    plan = make_plan(protocols.build(cfg), scene, cfg.render, np.random.default_rng(0))
    assert plan.passes >= 1


@pytest.mark.render
@pytest.mark.parametrize(
    "path",
    # a video: a capture per frame (15 s at this size): in make test-slow; tests/test_video.py runs a tiny one in make test.
    # rgb_illumination (a spectral render and a Bayer comparison capture, 9.5 s) and flash_matting (6 s): their
    # goldens run the same configs at 32x24 in make test
    [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_CONFIGS else p for p in CONFIGS],
    ids=lambda p: p.name,
)
def test_shipped_config_runs_at_tiny_size(path, tmp_path):
    """Each shipped config as it is (samples from render.noise_budget, every app with render.spp null),
    with its outputs and report.html."""
    from report_checks import check_report_folder, undocumented_keys

    cfg = load_config(path, ["render.width=16", "render.height=12", "render.max_motion_px=4", "render.min_strata=1"])
    assert cfg.render.spp is None or path.name == "tiny_hdr.yaml"
    result = run_capture(cfg, tmp_path, progress=False)
    if cfg.render.spp is None:
        assert result.plan.spp_source == "noise_budget"
    assert result.images and result.report["metrics"]
    # non-finite values only where the application flags the pixel invalid (HDR: sigma = inf
    # where every read saturated and the radiance is a lower bound)
    invalid = result.images["valid"] == 0 if "valid" in result.images else False
    for name, img in result.images.items():
        assert img.shape[:2] == (12, 16), name
        assert (np.isfinite(img) | invalid).all(), name
    for image, _ in result.app_output.png.values():  # every preview names an image that exists
        assert image in result.images
    # the application's declared outputs bound what it writes (the run's resource plan counts on them)
    from mbcapture import application

    app = application.get(result.app)
    layers = [
        *result.app_output.images.values(),
        *(v for d in result.app_output.extra_exr.values() for v in d.values()),
    ]
    channels = sum(np.asarray(v).shape[-1] if np.asarray(v).ndim == 3 else 1 for v in layers)
    assert channels <= app.output_channels and len(result.app_output.png) <= app.previews, (channels, app)
    # every application's run has a report.html that opens offline, shows each preview with what it is,
    # and a report.json whose every key docs/report.md explains
    refs = check_report_folder(tmp_path)
    assert {f"{stem}.png" for stem in result.app_output.png} <= set(refs.images)
    assert set(result.app_output.png) <= set(result.app_output.captions), "a preview without a caption"
    reads = [r.name for r in result.timeline.reads]
    assert undocumented_keys(result.report, reads) == [], "document these keys in docs/report.md"


def test_cli_output_piped_into_head_ends_quietly():
    import subprocess
    import sys

    proc = subprocess.run(
        ["bash", "-o", "pipefail", "-c", f"'{sys.executable}' -m mbcapture apps | head -c 20"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert proc.returncode == 0 and len(proc.stdout) == 20
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr


#: One shipped config per application, on a Bayer sensor (and two on a monochrome one).
CFA_RUNS = [
    ("burst", "RGGB"),
    ("flash_matting", "GRBG"),
    ("flash_no_flash", "RGGB"),
    ("flutter_shutter", "BGGR"),
    ("metronome_hdr", "RGGB"),
    ("multi_flash", "GBRG"),
    ("rgb_illumination", "RGGB"),
    ("structured_light", "RGGB"),
    ("metronome_hdr", "mono"),
    ("rgb_illumination", "mono"),
]


@pytest.mark.render
@pytest.mark.parametrize("config,cfa", CFA_RUNS, ids=[f"{c}-{p}" for c, p in CFA_RUNS])
def test_every_application_runs_on_a_cfa_sensor(config, cfa, tmp_path):
    """Each application reconstructs from a mosaic (sensor.cfa) and writes the mosaic as its raw files."""
    over = [
        "render.width=16",
        "render.height=12",
        "render.spp=2",
        "render.max_motion_px=4",
        "render.min_strata=1",
        f"sensor.cfa={cfa}",
    ]
    if config == "rgb_illumination":
        # its separate ordinary Bayer camera (app.bayer) is not the sensor's mosaic under test, and costs
        # half of the run (a second spectral renderer); the shipped config runs it in the tests above
        over.append("app.bayer=false")
    spectral = load_config(ROOT / "configs" / f"{config}.yaml").render.variant.endswith("_spectral")
    dng = cfa == "mono" or not spectral  # a colour DNG's matrix is the RGB render's
    cfg = load_config(ROOT / "configs" / f"{config}.yaml", [*over, f"output.dng={str(dng).lower()}"])
    result = run_capture(cfg, tmp_path, progress=False)
    assert result.mosaic_dn.shape == (len(result.timeline.reads), 12, 16)
    np.testing.assert_array_equal(result.mosaic_dn, np.round(result.mosaic_dn))
    if cfa == "mono":  # one response: every channel of every read is the same
        np.testing.assert_array_equal(result.reads_dn[..., 0], result.reads_dn[..., 1])
    invalid = result.images["valid"] == 0 if "valid" in result.images else False
    for name, img in result.images.items():
        assert img.shape[:2] == (12, 16) and (np.isfinite(img) | invalid).all(), name
    assert len(list(tmp_path.glob("read_*.dng"))) == (len(result.timeline.reads) if dng else 0)


def test_the_scene_guide_shows_its_example_scene_as_it_is():
    """docs/scenes.md shows docs/examples/rolling_ball/scene.py, which its runnable example captures: the file
    and the page must not drift apart."""
    scene = (ROOT / "docs" / "examples" / "rolling_ball" / "scene.py").read_text().rstrip()
    assert f"```python\n{scene}\n```" in (ROOT / "docs" / "scenes.md").read_text()


#: Words that tell the project's history as a diary of working sessions; the project speaks of releases,
#: commits, machines and dates, and history goes in commit messages.
HISTORY = re.compile(r"\bsessions?\b", re.IGNORECASE)
#: Where users read: every text file of these.
PROSE = ["README.md", "docs", "configs", "mbcapture", "scripts"]


def test_no_session_history_in_what_users_read():
    found = []
    for top in PROSE:
        path = ROOT / top
        files = (
            [path] if path.is_file() else [p for p in path.rglob("*") if p.suffix in (".md", ".py", ".yaml", ".txt")]
        )
        for f in files:
            for n, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
                if HISTORY.search(line):
                    found.append(f"{f.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not found, "history in the docs or code (say it in a commit message):\n" + "\n".join(found)


def test_the_history_check_finds_what_it_looks_for():
    assert HISTORY.search("measured in the fifteenth session") and HISTORY.search("Sessions")
    assert not HISTORY.search("a sixteenth of the samples") and not HISTORY.search("obsession-free")


#: The longest a config key's description may be: it defines the key (what, unit, the default's meaning) and
#: links to the document that explains the mechanism.
MOST_DESCRIPTION_WORDS = 80


def test_every_config_description_is_a_definition_of_at_most_80_words():
    rows = [line for line in (ROOT / "docs" / "config.md").read_text().splitlines() if line.startswith("| `")]
    assert len(rows) > 200
    long = {row.split(" | ")[0]: len(row.strip("| ").split(" | ")[-1].split()) for row in rows}
    long = {key: n for key, n in long.items() if n > MOST_DESCRIPTION_WORDS}
    assert not long, long
