"""One capture across a Dask cluster (mbcapture.exposure.cluster): the strata render on a LocalCluster's
workers and the capture is the local one, bit for bit (same CPU); the CLI takes --workers."""

from pathlib import Path

import numpy as np
import pytest
from golden_cases import RENDER_REPEAT_RTOL, count_differences

from mbcapture import load_config, run_capture
from mbcapture.exposure.cluster import start_client
from mbcapture.exposure.integrate import render_requests

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["render.width=40", "render.height=32", "render.spp=4", "render.max_motion_px=0.05", "render.cache=off"]


@pytest.fixture(scope="module")
def client():
    c = start_client(2)
    yield c
    cluster = c.cluster
    c.close()
    cluster.close()


@pytest.mark.render
def test_a_capture_rendered_on_two_workers_is_the_local_capture(client):
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", SMALL)
    local = run_capture(cfg, progress=False)
    spread = run_capture(cfg, progress=False, client=client)
    assert local.plan.passes >= 3  # several strata, spread over both workers
    info = spread.report["cluster"]
    assert info["workers"] == 2 and info["renders"] == len(render_requests(spread.plan, np.random.SeedSequence(0)))
    assert local.report["cluster"] is None
    np.testing.assert_array_equal(spread.bucket_exposure, local.bucket_exposure)
    np.testing.assert_array_equal(spread.reads_dn, local.reads_dn)
    for name, img in local.images.items():
        np.testing.assert_array_equal(spread.images[name], img, err_msg=name)


@pytest.mark.render
def test_a_tiled_capture_on_two_workers_is_the_local_untiled_capture(client):
    """Each tile's render bands are tasks of their own; the tiles go one after another."""
    banded = [*SMALL, "render.band_rows=8"]  # 4 bands of the 32 rows
    local = run_capture(
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [*banded, "render.tiles=1"]), progress=False
    )
    spread = run_capture(
        load_config(ROOT / "configs" / "metronome_hdr.yaml", [*banded, "render.tiles=2"]), progress=False, client=client
    )
    info = spread.report["cluster"]
    assert info["tiles"] == 2 and info["renders"] == 4 * len(render_requests(spread.plan, np.random.SeedSequence(0)))
    np.testing.assert_array_equal(spread.bucket_exposure, local.bucket_exposure)
    np.testing.assert_array_equal(spread.reads_dn, local.reads_dn)
    for name, img in local.images.items():
        np.testing.assert_array_equal(spread.images[name], img, err_msg=name)


@pytest.mark.slow
@pytest.mark.render
def test_a_capture_with_the_noise_budget_on_two_workers_makes_the_local_choices(client):
    """render.spp null: the first pass renders on the workers; adaptive sampling's scout and refinement and the
    top-up render in this process. The choices (samples, refined pixels, the top-up's samples) are the local
    run's, and the values as close as two local runs are (RENDER_REPEAT_RTOL; the reads as counts)."""
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*SMALL, "render.spp=null", "render.noise_budget=0.02"])
    local = run_capture(cfg, progress=False)
    spread = run_capture(cfg, progress=False, client=client)
    assert spread.report["cluster"]["renders"] > 0
    adaptive, top_up = local.report["adaptive"], local.report["top_up"]
    assert adaptive["pixels"] > 0 and top_up is not None and top_up["applied"], (adaptive, top_up)
    assert spread.report["adaptive"]["tiers"] == adaptive["tiers"]
    assert spread.report["top_up"]["spp_added"] == top_up["spp_added"]
    np.testing.assert_array_equal(spread.plan.spp, local.plan.spp)
    np.testing.assert_allclose(spread.bucket_exposure, local.bucket_exposure, rtol=RENDER_REPEAT_RTOL, atol=0)
    reads = [r.buckets for r in local.timeline.reads]
    assert (
        count_differences(
            spread.reads_dn, local.reads_dn, spread.buckets_e, local.buckets_e, reads, cfg.sensor.gain_dn_per_e
        )
        == []
    )


@pytest.mark.render
def test_the_difference_estimator_renders_here_and_says_so(client):
    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [*SMALL, "render.estimator=difference"])
    spread = run_capture(cfg, progress=False, client=client)
    assert spread.report["cluster"]["renders"] == 0 and "rendered here" in spread.report["cluster"]["note"]
    np.testing.assert_array_equal(spread.reads_dn, run_capture(cfg, progress=False).reads_dn)


def test_render_requests_are_what_integrate_renders():
    """The list the cluster renders is exactly the renders integrate asks for, in its order."""
    from mbcapture.exposure.integrate import integrate
    from mbcapture.capture.pipeline import prepare

    cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", SMALL)
    _, timeline, plan, seeds = prepare(cfg)

    class Recorder:
        height, width, channels = 32, 40, ("R", "G", "B")

        def __init__(self):
            self.calls = []

        def render(self, t, spp, seed, groups, pattern=None):
            self.calls.append((float(t), int(spp), int(seed), tuple(groups), pattern))
            return np.zeros((len(groups), 32, 40, 3), np.float32)

    rec = Recorder()
    integrate(rec, plan, timeline.n_buckets, seeds[2])
    assert rec.calls == render_requests(plan, seeds[2])


@pytest.mark.slow
@pytest.mark.render
def test_mbcapture_run_takes_workers_and_refuses_a_bad_count(tmp_path, capsys):
    import json
    import subprocess
    import sys

    from mbcapture.cli import main

    def run(*extra):
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "mbcapture",
                "run",
                "metronome_hdr",
                "--quiet",
                "--out",
                str(tmp_path / "out"),
                *[a for s in SMALL for a in ("--set", s)],
                *extra,
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )

    ok = run("--workers", "1")
    assert ok.returncode == 0, ok.stderr
    assert json.loads((tmp_path / "out" / "report.json").read_text())["cluster"]["workers"] == 1
    # refused before anything starts: in this process (a second interpreter's start adds nothing to check)
    capsys.readouterr()
    assert main(["run", "metronome_hdr", "--quiet", "--out", str(tmp_path / "bad"), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "--workers" in err and "Traceback" not in err and not (tmp_path / "bad").exists()
