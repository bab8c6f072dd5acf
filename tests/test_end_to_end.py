"""A real capture at tiny size, through the CLI and the Python API."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mbcapture import load_config, run_capture
from mbcapture.output.io import read_exr

pytestmark = pytest.mark.render
ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny_hdr.yaml"


def cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "mbcapture", *map(str, args)], cwd=cwd, capture_output=True, text=True)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    proc = cli("run", TINY, "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    return out


def test_outputs_are_written_with_the_documented_layers(tiny_run):
    names = {p.name for p in tiny_run.iterdir()}
    assert {
        "buckets.exr",
        "reads_expected.exr",
        "reads.exr",
        "hdr.exr",
        "hdr.png",
        "config.yaml",
        "report.json",
    } <= names
    assert not any(n.startswith(".staging") for n in names)
    buckets = read_exr(tiny_run / "buckets.exr")
    assert sorted(buckets) == ["B1", "B2", "B3", "B4"] and buckets["B1"].shape == (48, 64, 3)
    reads = read_exr(tiny_run / "reads.exr")
    expected = read_exr(tiny_run / "reads_expected.exr")
    assert sorted(reads) == sorted(expected) == ["J1", "J2", "J3", "J4"]
    # the readout sums: J_i = sum of buckets 4 .. 5-i, noise-free
    np.testing.assert_allclose(expected["J2"], buckets["B4"] + buckets["B3"], rtol=1e-5)
    np.testing.assert_allclose(expected["J4"], sum(buckets[f"B{k}"] for k in range(1, 5)), rtol=1e-5)
    hdr = read_exr(tiny_run / "hdr.exr")
    assert {"radiance", "sigma", "valid", "truth"} <= set(hdr)
    assert np.isfinite(hdr["radiance"]).all()


def test_report_has_reads_timings_and_versions(tiny_run):
    rep = json.loads((tiny_run / "report.json").read_text())
    assert rep["protocol"] == "photon_efficient_hdr" and rep["seed"] == 3
    assert [round(r["exposure_s"], 9) for r in rep["reads"]] == [0.001, 0.002, 0.004, 0.008]
    assert rep["reads"][-1]["span_s"] == pytest.approx(0.008)
    assert rep["plan"]["passes"] >= 1 and rep["plan"]["spp"] == 2
    assert {"plan", "render", "sensor", "reconstruct"} <= set(rep["timings_s"])
    assert rep["versions"]["mitsuba"] == "3.9.1" and int(rep["versions"]["llvm"].split(".")[0]) >= 16
    cfg = load_config(tiny_run / "config.yaml")  # the resolved config loads back
    assert cfg.render.width == 64


@pytest.fixture(scope="module")
def moving_pair():
    """The same moving scene captured interleaved and sequentially (fast needle, small film)."""
    common = ["render.width=80", "render.height=64", "render.spp=2", "render.max_motion_px=1.0", "scene.tempo_bpm=200"]
    inter = run_capture(load_config(TINY, common), progress=False)
    seq = run_capture(load_config(TINY, common + ["capture.sequential=true"]), progress=False)
    return inter, seq


def test_interleaved_reads_agree_sequential_reads_ghost(moving_pair):
    inter, seq = moving_pair
    mi = inter.report["metrics"]["motion_check"]
    ms = seq.report["metrics"]["motion_check"]
    assert mi["moving_pixels"] > 20
    # the needle sits in the same place in every interleaved read; not in the sequential frames
    assert ms["max_pairwise_rel_rms"] > 5 * mi["max_pairwise_rel_rms"]
    assert ms["max_pairwise_rel_rms"] > 0.05
    assert seq.report["sensor_type"].startswith("conventional")


def test_hdr_matches_truth_within_its_own_uncertainty(moving_pair):
    inter, _ = moving_pair
    ok = inter.images["valid"].astype(bool) & ~inter.moving_mask[..., None] & (inter.images["sigma"] > 0)
    z = (inter.images["radiance"] - inter.images["truth"])[ok] / inter.images["sigma"][ok]
    # standardized errors: mean ~ 0 and spread ~ 1 (the truth's own Monte Carlo noise is not in sigma, so
    # allow a little more than unit spread)
    n = z.size
    assert abs(z.mean()) < 4 / np.sqrt(n) + 0.1
    assert 0.7 < z.std() < 1.5


def test_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "o"
    proc = cli("run", TINY, "--out", out, "--set", "render.spp=-3")
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "render.spp" in proc.stderr
    assert not out.exists()
    proc = cli(
        "run",
        TINY,
        "--set",
        "capture.protocol=custom",
        "--set",
        "capture.schedule={slots: [{bucket: 5, duration_s: 0.001}], reads: [{buckets: [5]}]}",
        "--out",
        out,
    )
    assert proc.returncode == 2 and "needs 5 buckets" in proc.stderr and not out.exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    proc = cli("run", TINY, "--out", blocker / "sub")
    assert proc.returncode == 2 and "is a file, not a folder" in proc.stderr and "render" not in proc.stderr


def test_failed_run_keeps_previous_outputs(tmp_path, monkeypatch):
    """A run that dies while writing leaves the earlier run's files as they were and no partial file."""
    import mbcapture.output.io as mio

    out = tmp_path / "o"
    cfg = load_config(TINY, ["render.width=16", "render.height=12"])
    run_capture(cfg, out, progress=False)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    calls = {"n": 0}
    real = mio.write_exr

    def dying(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(mio, "write_exr", dying)
    with pytest.raises(KeyboardInterrupt):
        run_capture(load_config(TINY, ["render.width=16", "render.height=12", "seed=99"]), out, progress=False)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after == before


def test_plan_and_scenes_commands():
    proc = cli("plan", TINY, "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["plan"]["groups_left_out"] == ["flash"]
    proc = cli("scenes")
    assert proc.returncode == 0 and "metronome" in proc.stdout and "flatfield" in proc.stdout
    assert "scene.tempo_bpm" in proc.stdout


def test_render_error_estimate_is_calibrated():
    """The half-sample variance estimate predicts the actual error against a high-spp render."""
    base = [
        "render.width=32",
        "render.height=24",
        "render.max_motion_px=50",
        "render.min_strata=1",
        "scene.lamp_scale=0",
    ]
    ref = run_capture(load_config(TINY, base + ["render.spp=512"]), progress=False)
    run = run_capture(load_config(TINY, base + ["render.spp=8", "seed=11"]), progress=False)
    assert ref.plan.passes == run.plan.passes == 1
    err2 = (run.bucket_exposure - ref.bucket_exposure) ** 2
    predicted = run.render_var_exposure + ref.render_var_exposure
    ratio = err2.mean() / predicted.mean()
    # the mean over 32*24*3*4 samples of a chi-square-like quantity: well within a factor 1.5
    assert 0.67 < ratio < 1.5, ratio
    assert "rel_rms" in run.report["render_error"]


@pytest.mark.parametrize("sequential", [False, True])
def test_dark_frame_capture_holds_dark_current_over_each_buckets_storage_time(sequential):
    """A capture of no light with a large dark current (no read noise, no DSNU): each read's mean is
    the dark current x its bucket's storage time, from the bucket's first slot to its read. By hand
    (interleaved 8:4:2:1, N = 4, T = 1 ms): reads J1..J4 hold buckets 4..1, which start 14T/4,
    12T/4, 8T/4 and 0 into the 15T capture and are all read at its end: 11.5, 12, 13 and 15 ms.
    Sequential frames are read at the end of their own exposures: 1, 2, 4, 8 ms (the gaps between
    frames do not count). 576 samples per read: the 5 sd tolerance is ~12 e- of 3000."""
    dark = 2e5
    cfg = load_config(
        None,
        [
            "scene.name=flatfield",
            "scene.radiance=[0,0,0]",
            "render.width=16",
            "render.height=12",
            "render.spp=1",
            "capture.protocol=interleaved_hdr",
            "capture.periods=4",
            "capture.unit_exposure_s=0.001",
            f"capture.sequential={str(sequential).lower()}",
            f"sensor.dark_current_e_per_s={dark}",
            "sensor.read_noise_e=0",
            "sensor.dsnu_e=0",
        ],
    )
    res = run_capture(cfg, progress=False)
    storage_ms = [1.0, 2.0, 4.0, 8.0] if sequential else [11.5, 12.0, 13.0, 15.0]
    from mbcapture.sensor import dn_to_electrons

    read_e = dn_to_electrons(res.reads_dn, cfg.sensor).reshape(4, -1)
    n = read_e.shape[1]
    q = 1 / (12 * cfg.sensor.gain_dn_per_e**2)
    for r, ms in enumerate(storage_ms):
        m = dark * ms * 1e-3
        assert abs(read_e[r].mean() - m) < 5 * np.sqrt((m + q) / n), (r, read_e[r].mean(), m)
