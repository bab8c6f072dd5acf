"""report.html and what a run shows while it runs (issue 15): one tiny real run checked end to end,
and the pieces (verdict, scales, long schedules, the status line) on synthetic input."""

import io
import sys
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from report_checks import check_report_folder, undocumented_keys

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny_hdr.yaml"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny photon-efficient HDR run written with progress on; (folder, stderr)."""
    import sys

    from mbcapture import load_config, run_capture

    out = tmp_path_factory.mktemp("report")
    err = io.StringIO()
    real, sys.stderr = sys.stderr, err
    try:
        run_capture(load_config(TINY, ["render.width=32", "render.height=24", "render.spp=2"]), out, progress=True)
    finally:
        sys.stderr = real
    return out, err.getvalue()


@pytest.mark.render
def test_report_html_opens_offline_and_shows_every_part(tiny_run):
    out, _ = tiny_run
    refs = check_report_folder(out)
    shown = set(refs.images)
    reads = ["J1", "J2", "J3", "J4"]
    assert {f"read_{n}_common_scale.png" for n in reads} | {f"read_{n}_own_scale.png" for n in reads} <= shown
    assert {
        "report_timeline.png",
        "report_histograms.png",
        "map_saturation.png",
        "map_snr.png",
        "map_valid.png",
        "hdr.png",
        "truth.png",
    } <= shown
    text = " ".join(refs.text)
    rep = json.loads((out / "report.json").read_text())
    for part in (
        "Gate schedule",
        "Histograms",
        "Metrics",
        "Rendering noise against shot noise",
        "Timings",
        "hdr_rel_mse",
        rep["render_error"]["verdict"],
        "photon_efficient_hdr",
        "B1+B2+B3+B4",
    ):
        assert part in text, part
    listed = {h for h in refs.links if not h.startswith("#")}
    assert {p.name for p in out.iterdir() if not p.name.startswith(".")} <= listed  # every file is listed


@pytest.mark.render
def test_reads_on_a_common_scale_show_the_exposure_ratios(tiny_run):
    """read_J*_common_scale.png: one DN scale, so J1 (T) is ~1/8 of J4 (8T) in linear light; each
    read on its own scale hides that."""
    import colour

    out, _ = tiny_run
    rep = json.loads((out / "report.json").read_text())

    def linear(name):
        return colour.cctf_decoding(np.asarray(Image.open(out / name), dtype=np.float64) / 255, function="sRGB")

    common = [np.median(linear(f"read_{n}_common_scale.png")) for n in ("J1", "J4")]
    own = [np.median(linear(f"read_{n}_own_scale.png")) for n in ("J1", "J4")]
    assert 0.5 / 8 < common[0] / common[1] < 2.0 / 8
    assert own[0] / own[1] > 0.4  # own scales are close to each other: the ratio is not visible there
    w = rep["previews"]["read_common_scale_white_dn"]
    assert w > max(rep["previews"]["read_own_scale_white_dn"][n] for n in ("J1", "J2"))


@pytest.mark.render
def test_report_json_labels_its_numbers(tiny_run):
    out, _ = tiny_run
    rep = json.loads((out / "report.json").read_text())
    k_e = rep["electrons_per_render_unit_second"]
    assert list(k_e) == ["R", "G", "B"] and all(v > 0 for v in k_e.values())
    assert rep["plan"]["tick_s"] == pytest.approx(1e-9) and rep["plan"]["tick_s_exact"] == "1/1000000000"
    err = rep["render_error"]
    assert err["temporal_rel_rms_estimate"] is None or "temporal_resolved" in err  # never an unexplained 0.0
    assert undocumented_keys(rep, ["J1", "J2", "J3", "J4"]) == []


@pytest.mark.render
def test_every_stage_shows_progress(tiny_run):
    _, err = tiny_run
    for stage in ("plan", "render setup", "render (", "sensor", "reconstruct (hdr)", "write outputs"):
        assert stage in err, stage


def test_status_line_moves_during_a_silent_stage():
    """A stage with no progress of its own (a reconstruction, a write) is redrawn while it runs; into a file or a
    pipe each redraw is a line of its own."""
    from mbcapture.progress import StageStatus

    buf = io.StringIO()
    with StageStatus(True, stages=2, file=buf, interval_s=0.01) as status:
        with status.stage("reconstruct (x)"):
            start = status.refreshes
            deadline = time.monotonic() + 20
            while status.refreshes < start + 3 and time.monotonic() < deadline:
                time.sleep(0.005)  # the stage itself says nothing
            moved = status.refreshes - start
    assert moved >= 3
    assert "reconstruct (x)" in buf.getvalue() and "stage 1/2" in buf.getvalue()
    # into a file (not a terminal): plain lines, no carriage return or cursor escape
    assert "\r" not in buf.getvalue() and "\x1b" not in buf.getvalue()
    assert all(line.startswith("reconstruct (x)  ") for line in buf.getvalue().splitlines())
    assert not any(t.name == "mbcapture-status" for t in threading.enumerate())  # the ticker is stopped
    quiet = io.StringIO()
    with StageStatus(False, file=quiet) as status:
        with status.stage("x"):
            pass
    assert quiet.getvalue() == "" and status.refreshes == 0


def test_noise_verdict_follows_the_budget():
    from mbcapture.budget import noise_verdict

    within = {
        "to_shot_noise_variance_median": 0.05,
        "to_shot_noise_variance_p95": 0.5,
        "budget": {"median_target": 0.1, "p95_target": 1.0, "met": True},
    }
    assert noise_verdict(within).startswith("Sensor noise dominates")
    assert "adding 2.5 %" in noise_verdict(within)  # sqrt(1.05) - 1
    over = {
        "to_shot_noise_variance_median": 3.0,
        "to_shot_noise_variance_p95": 30.0,
        "budget": {"median_target": 0.1, "p95_target": 1.0, "met": False, "spp_that_would_meet": 480},
    }
    assert noise_verdict(over).startswith("Rendering noise is visible") and "render.spp >= 480" in noise_verdict(over)
    assert "render.spp: null" in noise_verdict(over)
    # the budget chose the samples and missed: it does not suggest the budget again
    missed = {**over, "budget": {**over["budget"], "spp_source": "noise_budget"}}
    assert "pilot under-estimated" in noise_verdict(missed) and "render.spp >= 480" in noise_verdict(missed)
    assert "render.spp: null" not in noise_verdict(missed)
    assert "spp = 1" in noise_verdict({"note": "render.spp = 1: no half-sample error estimate"})
    # a tail over its target points to adaptive sampling where the run could have used it
    tail_over = {
        **within,
        "to_shot_noise_variance_p999": 4.7,
        "budget": {**within["budget"], "tail_target": 1.0, "tail_met": False},
    }
    assert "over render.noise_budget_tail 1" in noise_verdict(tail_over)
    assert "render.adaptive: true" in noise_verdict(tail_over, adaptive_hint=True)
    assert "render.adaptive" not in noise_verdict(tail_over)
    tail_within = {**tail_over, "budget": {**tail_over["budget"], "tail_met": True}}
    assert "render.adaptive" not in noise_verdict(tail_within, adaptive_hint=True)
    # over by the estimate, with an interval that reaches below the target: the run says it cannot tell
    clear = {**tail_over, "to_shot_noise_variance_p999_interval": [3.6, 6.6]}
    unclear = {**tail_over, "to_shot_noise_variance_p999": 1.18, "to_shot_noise_variance_p999_interval": [0.93, 10.2]}
    assert "(over render.noise_budget_tail 1)" in noise_verdict(clear) and "cannot tell" not in noise_verdict(clear)
    assert "(over render.noise_budget_tail 1 by this estimate, but its interval reaches below it" in noise_verdict(
        unclear
    )
    assert "cannot tell" not in noise_verdict({**unclear, "budget": tail_within["budget"]})


def test_long_schedule_is_drawn_in_outline_plus_its_first_periods(monkeypatch):
    """10^6 periods: the timeline draws a bounded number of slots, not one patch per slot."""
    import mbcapture.output.plots as plots
    from mbcapture.timing import protocols
    from mbcapture.config import load_config
    from mbcapture.output.plots import MAX_DETAIL_SLOTS, timeline_png

    tl = protocols.build(load_config(None, ["scene.name=flatfield", "capture.periods=1000000"]))
    drawn = []
    real = plots.draw_timeline
    monkeypatch.setattr(plots, "draw_timeline", lambda *a, **k: drawn.append(real(*a, **k)) or drawn[-1])
    png = timeline_png(tl)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert 0 < sum(drawn) <= MAX_DETAIL_SLOTS
    assert Image.open(io.BytesIO(png)).size[0] > 500


def test_colour_map_and_its_scale():
    from mbcapture.output.plots import MISSING_GREY, colour_map

    v = np.array([[0.0, 1.0], [2.0, np.nan]])
    rgb, scale = colour_map(v, levels=2)
    assert rgb.shape == (2, 2, 3) and tuple(rgb[1, 1]) == MISSING_GREY
    assert len(scale["levels"]) == 3 and len({tuple(rgb[0, 0]), tuple(rgb[0, 1]), tuple(rgb[1, 0])}) == 3
    rgb, scale = colour_map(np.array([[1.0, 10.0], [100.0, np.nan]]), log=True)
    assert scale == {**scale, "min": 1.0, "max": 100.0, "log": True}
    # 10 is half-way on a log scale from 1 to 100: its colour is the middle stop's
    assert "#%02x%02x%02x" % tuple(rgb[0, 1]) == scale["stops"][5]


def test_read_previews_are_white_balanced_so_a_white_surface_is_grey():
    """A read is camera DN: channel c of a white surface is black + g x k_e[c]. Its preview divides by the
    sensor's response per channel, so it is grey; the raw DN are not (the test can fail)."""
    from mbcapture.capture.report import white_balanced

    k_e = np.array([2.0, 4.0, 1.0])
    reads = 64.0 + 10.0 * np.ones((2, 3, 5, 3)) * k_e
    out = white_balanced(reads, 64.0, k_e)
    np.testing.assert_allclose(out, 40.0)
    assert not np.allclose(reads - 64.0, (reads - 64.0).mean(axis=-1, keepdims=True))


@pytest.mark.render
def test_the_page_prints_no_raw_python_dict(tiny_run):
    """Nested figures (render_error.reads.J4...., render_error.budget....) are rows of their own, not a dict's repr."""
    out, _ = tiny_run
    page = (out / "report.html").read_text()
    assert "render_error" in page and "reads.J4.to_shot_noise_variance_median" in page
    assert "{&#x27;" not in page and "{'" not in page


def test_a_progress_bar_into_a_file_is_plain_lines(monkeypatch):
    """Into a file or a pipe a pass bar writes plain lines (tqdm redraws in place with carriage returns)."""
    from mbcapture.progress import bar

    buf = io.StringIO()
    monkeypatch.setattr(sys, "stderr", buf)
    with bar(total=3, desc="render", unit="pass") as b:
        for _ in range(3):
            b.update(1)
    text = buf.getvalue()
    assert text.startswith("render:") and text.endswith("\n")
    assert "\r" not in text and "\x1b" not in text
