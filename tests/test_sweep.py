"""Sweeps (mbcapture sweep): sweep files validated like configs, points grouped by what their renders
receive, a tiny sweep on a LocalCluster of 2 processes sharing renders, resume, failures recorded,
and a point's outputs equal to `mbcapture run` of its config."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from mbcapture import load_config
from mbcapture.errors import ConfigError
from mbcapture.sweep import group_key, load_sweep, plan_sweep, render_key, run_sweep

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "configs" / "sweeps").glob("*.yaml"))


def write_sweep(folder: Path, data: dict, name: str = "s.yaml") -> Path:
    path = folder / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


TINY = {"render.width": 16, "render.height": 12, "render.spp": 4}


# ------------------------------------------------------------------------------ sweep files
@pytest.mark.parametrize(
    "data,message",
    [
        ({"base": "tiny_hdr", "axis": {"grid": {"seed": [0]}}}, "axis: unknown key; did you mean axes?"),
        (
            {"base": "tiny_hdr", "axes": {"grid": {"capture.perids": [1, 2]}}},
            "axes.grid capture.perids=1: capture.perids: unknown key; did you mean capture.periods?",
        ),
        (
            {"base": "tiny_hdr", "axes": {"grid": {"sensor.read_noise_e": [1, "loud"]}}},
            "axes.grid sensor.read_noise_e=loud: sensor.read_noise_e: Input should be a valid number",
        ),
        (
            {"base": "tiny_hdr", "axes": {"zip": [{"seed": [0, 1], "sensor.read_noise_e": [1]}]}},
            "the lists of a zip group must have one, non-zero length",
        ),
        ({"base": "tiny_hdr", "set": {"seed": 2}, "axes": {"grid": {"seed": [0, 1]}}}, "set: seed is also an axis"),
        ({"base": "nope", "axes": {"grid": {"seed": [0]}}}, "base: nope: config file not found"),
        (
            {
                "base": "tiny_hdr",
                "axes": {"random": {"samples": 4, "keys": {"sensor.full_well_e": {"low": 0, "high": 9, "log": True}}}},
            },
            "log: true needs low > 0",
        ),
        ({"base": "tiny_hdr", "axes": {}}, "no key varies"),
    ],
)
def test_sweep_file_errors_name_the_file_and_key(tmp_path, data, message):
    path = write_sweep(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_sweep(path)
    assert message in str(err.value) and str(path) in str(err.value) and "\n" not in str(err.value)


def test_cli_refuses_a_bad_sweep_with_one_line_and_writes_nothing(tmp_path, capsys):
    from mbcapture.cli import main

    path = write_sweep(tmp_path, {"base": "tiny_hdr", "axes": {"grid": {"sensor.read_noise_e": [1, 2]}}})
    out = tmp_path / "out"
    for args, message in (
        (["--set", "sensor.read_noise_e=3"], "sensor.read_noise_e is an axis of"),
        (["--set", "render.sp=4"], "render.sp: unknown key; did you mean render.spp?"),
        (["--workers", "0"], "--workers: expected a number of processes >= 1"),
        (["--scheduler", "tcp://127.0.0.1:9"], "--scheduler tcp://127.0.0.1:9: cannot connect"),
    ):
        assert main(["sweep", str(path), "--out", str(out), *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("mbcapture: error: ") and message in err and err.count("\n") == 1, err
    assert main(["sweep", str(tmp_path / "nope.yaml")]) == 2 and "sweep file not found" in capsys.readouterr().err
    assert not out.exists()


def test_points_are_the_product_of_grid_zip_and_random_samples(tmp_path):
    path = write_sweep(
        tmp_path,
        {
            "base": "tiny_hdr",
            "axes": {
                "grid": {"seed": [0, 1], "capture.periods": [2, 4, 8]},
                "zip": [{"sensor.read_noise_e": [1.0, 2.0], "sensor.adc_bits": [12, 14]}],
                "random": {
                    "samples": 5,
                    "seed": 7,
                    "keys": {
                        "sensor.full_well_e": {"low": 1000, "high": 100000, "log": True},
                        "sensor.fpn_seed": {"low": 0, "high": 4, "integer": True},
                        "hdr.method": {"choices": ["ramp_fit", "inverse_variance"]},
                    },
                },
            },
        },
    )
    sweep = load_sweep(path)
    assert len(sweep.points) == 2 * 3 * 2 * 5
    first, last = sweep.points[0].values, sweep.points[-1].values
    assert (first["seed"], first["capture.periods"], first["sensor.read_noise_e"]) == (0, 2, 1.0)
    assert (last["seed"], last["capture.periods"], last["sensor.adc_bits"]) == (1, 8, 14)
    assert (
        sweep.points[5].config.capture.periods == 2 and sweep.points[5].config.sensor.adc_bits == 14
    )  # random varies fastest
    # seeded: the same samples again; a Latin hypercube: one sample in each fifth of log(range)
    again = load_sweep(path)
    assert [p.values for p in again.points] == [p.values for p in sweep.points] and sweep.points[0].id == again.points[
        0
    ].id
    samples = [p.values for p in sweep.points[:5]]
    strata = sorted(int(np.log(s["sensor.full_well_e"] / 1000) / np.log(100) * 5) for s in samples)
    assert strata == [0, 1, 2, 3, 4]
    assert all(isinstance(s["sensor.fpn_seed"], int) and 0 <= s["sensor.fpn_seed"] <= 4 for s in samples)
    assert {s["hdr.method"] for s in samples} <= {"ramp_fit", "inverse_variance"}
    assert len({p.id for p in sweep.points}) == len(sweep.points)


# burst_hands plans its hand-held points' strata (8 s): in make test-slow
@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=pytest.mark.slow) if p.name == "burst_hands.yaml" else p for p in SHIPPED],
    ids=lambda p: p.name,
)
def test_shipped_sweep_loads_and_plans(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sweep = load_sweep(path.stem, ["render.width=32", "render.height=24"])
    plan = plan_sweep(sweep)
    assert not plan.failed and len(sweep.points) >= 12
    if path.stem == "sensor_noise":  # zero re-renders: one render group for all 64 points
        assert len(sweep.points) == 64 and len(plan.groups) == 1 and plan.axes_changing_renders == ()
    if path.stem == "coded_gates":  # the code only routes the same sub-frame renders: one render group
        assert len(plan.groups) == 1 and plan.axes_changing_renders == ()
    if path.stem == "interleaving":
        assert set(plan.axes_changing_renders) == {"capture.periods", "capture.protocol"}


# ------------------------------------------------------------------------------ render groups
def test_group_key_changes_exactly_with_what_the_renders_receive():
    """Keys that only the sensor, the reconstruction or the previews read leave the key alone; the
    seed, film, scene, schedule and (with the noise budget) the light per electron change it."""
    base = ["render.width=16", "render.height=12", "render.spp=4"]
    key = group_key(load_config("tiny_hdr", base))
    same = [
        "sensor.read_noise_e=9",
        "sensor.full_well_e=3000",
        "sensor.f_number=8",
        "sensor.noise_seed=5",
        "sensor.adc_bits=10",
        "sensor.prnu=0.05",
        "hdr.method=inverse_variance",
        "output.png_percentile=90",
        "render.cache=off",
        "sensor.frame_readout_s=0.1",
    ]
    for change in same:
        assert group_key(load_config("tiny_hdr", [*base, change])) == key, change
    # one stratum at this size (render.max_motion_px 2): N periods weigh it alike, the renders are the same;
    # with strata short enough to resolve the periods, N changes them
    assert group_key(load_config("tiny_hdr", [*base, "capture.periods=4"])) == key
    fine = [*base, "render.max_motion_px=0.01"]
    assert group_key(load_config("tiny_hdr", [*fine, "capture.periods=4"])) != group_key(load_config("tiny_hdr", fine))
    other = [
        "seed=4",
        "render.width=18",
        "render.spp=6",
        "scene.tempo_bpm=90",
        "capture.unit_exposure_s=0.002",
        "render.max_motion_px=0.01",
        "capture.protocol=interleaved_hdr",
        "capture.sequential=true",
        "render.max_depth=2",
    ]
    for change in other:
        assert group_key(load_config("tiny_hdr", [*base, change])) != key, change
    # a sequential capture reads sensor.frame_readout_s (the gap between frames): then it counts
    seq = [*base, "capture.sequential=true"]
    assert group_key(load_config("tiny_hdr", [*seq, "sensor.frame_readout_s=0.1"])) != group_key(
        load_config("tiny_hdr", seq)
    )
    # the noise budget chooses samples from the sensor's shot noise: light per electron and full well count
    budget = ["render.width=16", "render.height=12", "render.spp=null"]
    bkey = group_key(load_config("tiny_hdr", budget))
    assert group_key(load_config("tiny_hdr", [*budget, "sensor.read_noise_e=9"])) == bkey
    assert group_key(load_config("tiny_hdr", [*budget, "sensor.f_number=8"])) != bkey
    assert group_key(load_config("tiny_hdr", [*budget, "sensor.full_well_e=3000"])) != bkey
    # figure 6's strata at 1 and 2 periods: other weights (another render group), the same images
    fig6 = [
        "render.spp=4",
        "capture.unit_exposure_s=0.004",
        "render.max_motion_px=0.1",
        "render.width=160",
        "render.height=128",
    ]
    one, two = (load_config("metronome_hdr", [*fig6, f"capture.periods={n}"]) for n in (1, 2))
    assert group_key(one) != group_key(two) and render_key(one) == render_key(two)
    assert render_key(load_config("metronome_hdr", [*fig6, "capture.periods=1", "seed=5"])) != render_key(one)
    # the lens's images read the sensor: diffraction its f-number, a thin lens its aperture, a mono sensor its
    # mixture; a Bayer mosaic and the demosaicing read none of the renders
    diff = [*base, "camera.diffraction=true"]
    assert group_key(load_config("tiny_hdr", diff)) != key
    assert group_key(load_config("tiny_hdr", [*diff, "sensor.f_number=8"])) != group_key(load_config("tiny_hdr", diff))
    thin = [*base, "camera.lens=thin"]
    assert group_key(load_config("tiny_hdr", [*thin, "sensor.f_number=8"])) != group_key(load_config("tiny_hdr", thin))
    assert group_key(load_config("tiny_hdr", [*base, "sensor.cfa=mono"])) != key
    for same_images in ("sensor.cfa=RGGB", "sensor.demosaic=bilinear"):
        assert group_key(load_config("tiny_hdr", [*base, same_images])) == key, same_images
    assert group_key(load_config("tiny_hdr", [*base, "camera.distortion=[-0.1]"])) != key
    # a hand-held camera: its trajectory is rendered (another hand, other renders), its noise is not
    shake = ["render.width=16", "render.height=12", "render.spp=4"]
    hkey = group_key(load_config("metronome_shake", shake))
    assert group_key(load_config("metronome_shake", [*shake, "camera.shake.seed=99"])) != hkey
    assert group_key(load_config("metronome_shake", [*shake, "sensor.read_noise_e=9"])) == hkey
    # spectral mode: the camera's curves shape the film
    spec = ["render.width=16", "render.height=12", "render.spp=4"]
    skey = group_key(load_config("metronome_spectral", spec))
    assert group_key(load_config("metronome_spectral", [*spec, "sensor.quantum_efficiency=[0.3,0.5,0.45]"])) != skey
    assert group_key(load_config("metronome_spectral", [*spec, "sensor.read_noise_e=9"])) == skey


# ------------------------------------------------------------------------------ on a LocalCluster
@pytest.fixture(scope="session")
def client():
    """One LocalCluster of 2 worker processes for every sweep test (starting one costs seconds); for the
    session, so that a test of another module run in between does not close and start it again."""
    from mbcapture.sweep.execute import start_client

    c = start_client(2)
    yield c
    c.close()
    c.cluster.close()


@pytest.fixture(scope="session")
def tiny_sweep(tmp_path_factory, client):
    """3 points (seed, read noise: (0, 1), (0, 20), (1, 1); 16x12, 4 spp) in 2 render groups, run once
    on the cluster with a render cache of its own; keep: all. For the session: once per test process,
    even where another module's tests run between this module's."""
    folder = tmp_path_factory.mktemp("sweep")
    path = write_sweep(
        folder,
        {
            "base": "tiny_hdr",
            "set": {**TINY, "render.cache": str(folder / "cache")},
            "axes": {"zip": [{"seed": [0, 0, 1], "sensor.read_noise_e": [1.0, 20.0, 1.0]}]},
            "keep": "all",
        },
    )
    sweep = load_sweep(path)
    out = folder / "out"
    outcome = run_sweep(sweep, out, client=client, progress=False)
    return sweep, out, outcome


@pytest.mark.render
def test_tiny_sweep_renders_each_group_once(tiny_sweep):
    import pandas as pd

    sweep, out, outcome = tiny_sweep
    rows, s = outcome.rows, outcome.summary
    assert s["ok"] == 3 and s["failed"] == 0 and s["render_groups"] == 2
    assert s["axes_changing_renders"] == ["seed"]  # the zip varies seed and read noise together
    leaders, follower = [rows[0], rows[2]], rows[1]  # the first point of each seed renders, p0001 takes p0000's
    # a leader renders what one capture renders (2 halves per stratum), nothing comes from elsewhere
    passes = leaders[0]["passes"]
    assert all(
        r["renders_rendered"] == 2 * passes and r["renders_reused"] == 0 and not r["render_shared"] for r in leaders
    )
    assert follower["renders_rendered"] == 0 and follower["renders_reused"] == 0 and follower["render_shared"]
    assert s["renders_rendered"] == 4 * passes and s["points_sharing_renders"] == 1
    # the table: one row per point, in Parquet and CSV alike, with the axes and the metrics
    table = pd.read_parquet(out / "results.parquet")
    csv = pd.read_csv(out / "results.csv")
    assert list(table["point"]) == ["p0000", "p0001", "p0002"] and list(csv.columns) == list(table.columns)
    assert list(table["sensor.read_noise_e"]) == [1.0, 20.0, 1.0] and list(table["seed"]) == [0, 0, 1]
    np.testing.assert_allclose(csv["metrics.hdr_rel_mse"], table["metrics.hdr_rel_mse"], rtol=1e-12)
    assert table["render_group"].nunique() == 2 and (table["status"] == "ok").all()
    # more read noise, more HDR error, on the same renders
    assert table["metrics.hdr_rel_mse"][1] > table["metrics.hdr_rel_mse"][0]
    index = (out / "index.html").read_text()
    plots = sorted(p.name for p in out.glob("plot_*.png"))
    assert "plot_metrics.hdr_rel_mse.png" in plots and all(f"src='{p}'" in index for p in plots)
    assert json.loads((out / "sweep.json").read_text())["groups"][0]["points"] == ["p0000", "p0001"]


@pytest.mark.render
def test_a_sweep_point_equals_mbcapture_run_of_its_config(tiny_sweep, tmp_path):
    """p0001 took p0000's render stage; `mbcapture run` of its config.yaml renders (or reads) on its own."""
    from mbcapture.cli import main
    from mbcapture.output.io import read_exr

    sweep, out, outcome = tiny_sweep
    point = out / "points" / "p0001"
    assert outcome.rows[1]["render_shared"]
    assert main(["run", str(point / "config.yaml"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    for name in ("reads.exr", "buckets.exr", "hdr.exr"):
        a, b = read_exr(point / name), read_exr(tmp_path / "run" / name)
        assert a.keys() == b.keys()
        for layer in a:
            np.testing.assert_array_equal(a[layer], b[layer], err_msg=f"{name} {layer}")
    ours, theirs = (json.loads((d / "report.json").read_text()) for d in (point, tmp_path / "run"))
    assert ours["metrics"] == theirs["metrics"] and ours["render_error"] == theirs["render_error"]
    assert ours["plan"]["strata"] == theirs["plan"]["strata"]


@pytest.mark.render
def test_resume_skips_finished_points_and_renders_nothing(tiny_sweep, client):
    import pandas as pd

    sweep, out, outcome = tiny_sweep
    before = pd.read_parquet(out / "results.parquet")
    again = run_sweep(sweep, out, client=client, resume=True, progress=False)
    assert again.summary["ran"] == 0 and again.summary["resumed"] == 3
    # a point lost (its row removed), and a group's first point: run again from the render cache
    for p in (sweep.points[1], sweep.points[2]):
        (out / "rows" / f"{p.id}.json").unlink()
    again = run_sweep(sweep, out, client=client, resume=True, progress=False)
    s = again.summary
    assert s["ran"] == 2 and s["resumed"] == 1 and s["renders_rendered"] == 0 and s["renders_reused"] > 0
    after = pd.read_parquet(out / "results.parquet")
    np.testing.assert_array_equal(after["metrics.hdr_rel_mse"], before["metrics.hdr_rel_mse"])


@pytest.mark.render
def test_a_failing_point_is_recorded_and_the_others_finish(tmp_path, client):
    """Point 1's application cannot read an HDR capture (fails in its worker, after rendering); point 2
    asks for more buckets than its sensor has (fails while the sweep is planned)."""
    import pandas as pd

    path = write_sweep(
        tmp_path,
        {
            "base": "tiny_hdr",
            "set": TINY,
            "axes": {
                "zip": [
                    {
                        "app.name": ["hdr", "multi_flash", "flash_matting"],
                        "capture.protocol": ["photon_efficient_hdr", "photon_efficient_hdr", "flash_matting"],
                        "sensor.bucket_count": [4, 4, 2],
                    }
                ]
            },
            "keep": "none",
        },
    )
    outcome = run_sweep(load_sweep(path), tmp_path / "out", client=client, progress=False)
    rows = outcome.rows
    assert rows[0]["status"] == "ok" and rows[0]["metrics.hdr_rel_mse"] > 0
    assert rows[1]["status"] == "failed" and "multi_flash needs reads lit by at least two" in rows[1]["error"]
    assert rows[2]["status"] == "failed" and "needs 4 buckets but sensor.bucket_count is 2" in rows[2]["error"]
    table = pd.read_parquet(tmp_path / "out" / "results.parquet")
    assert list(table["status"]) == ["ok", "failed", "failed"]
    assert "multi_flash needs" in (tmp_path / "out" / "index.html").read_text()
    assert not (tmp_path / "out" / "points").exists()  # keep: none


# ------------------------------------------------------------------------------ in this process
def test_the_executor_is_this_process_for_one_set_of_renders_and_dask_otherwise():
    from types import SimpleNamespace

    from mbcapture.sweep import choose_executor

    one = SimpleNamespace(groups=(SimpleNamespace(points=(0, 1, 2), renders="a"),))
    two = SimpleNamespace(
        groups=(SimpleNamespace(points=(0, 1), renders="a"), SimpleNamespace(points=(2,), renders="b"))
    )
    shared = SimpleNamespace(
        groups=(SimpleNamespace(points=(0,), renders="a"), SimpleNamespace(points=(1,), renders="a"))
    )
    free = {"workers": None, "scheduler": None, "client": None, "in_process": None}
    assert choose_executor(one, {0, 1, 2}, **free)
    assert choose_executor(shared, {0, 1}, **free)  # two groups (e.g. per-group exposures) on the same images
    assert not choose_executor(two, {0, 1, 2}, **free)
    assert choose_executor(two, {0, 1}, **free)  # what is left to run renders one set
    for given in ({"workers": 2}, {"scheduler": "tcp://x:8786"}, {"client": object()}, {"in_process": False}):
        assert not choose_executor(one, {0, 1, 2}, **{**free, **given}), given
    assert choose_executor(two, {0, 1, 2}, **{**free, "in_process": True})


@pytest.mark.render
def test_a_sweep_of_one_render_set_runs_here_and_shares_its_error_estimates(tmp_path):
    """No Dask for points that all share one set of renders; the run's rendering-error estimate is
    computed once per full well and light level and equals a capture's own."""
    from mbcapture.capture.run import run_capture

    path = write_sweep(
        tmp_path,
        {
            "base": "tiny_hdr",
            "set": {**TINY, "render.cache": "off"},
            "axes": {"grid": {"sensor.full_well_e": [5000.0, 9000.0], "sensor.read_noise_e": [1.0, 20.0]}},
        },
    )
    sweep = load_sweep(path)
    outcome = run_sweep(sweep, tmp_path / "out", progress=False, keep_results=True)
    assert outcome.summary["executor"] == "this process (no Dask)" and outcome.summary["ok"] == 4
    assert outcome.summary["points_sharing_renders"] == 3
    for i, point in enumerate(sweep.points):
        own = run_capture(point.config, progress=False).report["render_error"]
        assert outcome.results[i].report["render_error"] == own, point.label


@pytest.mark.render
@pytest.mark.parametrize("config", ["metronome_hdr", "flash_no_flash", "moving_light"])
def test_an_application_that_says_it_renders_nothing_renders_nothing_on_shared_renders(config, monkeypatch):
    """App.renders False lets a sweep run its points side by side in threads: on another capture's
    renders, such an application's capture must not touch Mitsuba."""
    from mbcapture.capture.run import run_capture
    from mbcapture.render.renderer import Renderer

    cfg = load_config(config, ["render.width=16", "render.height=12", "render.spp=4", "render.cache=off"])
    app, _ = cfg.app.resolve(cfg.capture.protocol)
    assert not app.renders
    kept = {}
    run_capture(cfg, progress=False, on_rendered=lambda r: kept.update(rendered=r))

    def refuse(*args, **kwargs):
        raise AssertionError("rendered")

    for method in ("render", "render_rows", "render_pixels", "render_path", "raw_render", "_ensure_loaded", "set_time"):
        monkeypatch.setattr(Renderer, method, refuse)
    again = run_capture(
        load_config(
            config, ["render.width=16", "render.height=12", "render.spp=4", "render.cache=off", "sensor.read_noise_e=7"]
        ),
        progress=False,
        rendered=kept["rendered"],
    )
    assert again.images


def test_one_figure_redrawn_per_metric_is_the_figure_drawn_afresh():
    """write_results draws every metric on one MetricGrid: each plot is pixel for pixel the plot a fresh
    figure gives (no line, legend, colour or scale left from the metric before), log and linear alike."""
    import itertools

    import imageio.v3 as iio
    import pandas as pd

    from mbcapture.output.plots import MetricGrid, png_bytes, sweep_plot

    grid = list(itertools.product([1.0, 2.0, 5.0, 10.0], [2500, 5000, 10000], ["a", "b"]))
    df = pd.DataFrame(grid, columns=["sensor.read_noise_e", "sensor.full_well_e", "app.kind"])
    df["status"] = "ok"
    df["metrics.log"] = 1e-3 * df["sensor.read_noise_e"] ** 3 / df["sensor.full_well_e"] * 2500
    df["metrics.lin"] = 0.5 + 0.01 * df["sensor.read_noise_e"] - 1e-5 * df["sensor.full_well_e"]
    axes = ["sensor.read_noise_e", "sensor.full_well_e", "app.kind"]
    figure = MetricGrid(df, axes)
    redrawn = {m: png_bytes(figure.draw(m), dpi=90) for m in ("metrics.log", "metrics.lin", "metrics.log")}
    for metric, png in redrawn.items():
        fresh = sweep_plot(df, metric, axes)
        np.testing.assert_array_equal(iio.imread(png), iio.imread(png_bytes(fresh, dpi=90)), err_msg=metric)


def test_no_two_texts_of_a_sweep_figure_overlap():
    """The bucket-design sweep's layout (two categorical axes, rotated names, and a numeric one): no
    title, axis label or tick label overlaps another, and every one is inside the figure."""
    import itertools

    import pandas as pd
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from mbcapture.output.plots import sweep_plot

    rows = [
        {"status": "ok", "capture.protocol": p, "capture.sequential": s, "sensor.bucket_count": k, "m": 1e-3 * (1 + i)}
        for i, (p, s, k) in enumerate(
            itertools.product(["photon_efficient_hdr", "interleaved_hdr"], [False, True], [2, 3, 4])
        )
    ]
    fig = sweep_plot(pd.DataFrame(rows), "m", ["capture.protocol", "capture.sequential", "sensor.bucket_count"])
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)

    def drawn_ticks(axis, limits):
        low, high = sorted(limits)
        return [t for t, v in zip(axis.get_ticklabels(), axis.get_ticklocs()) if low <= v <= high]

    texts = [fig._suptitle]
    for ax in fig.axes:
        if ax.get_visible():
            texts += [
                ax.title,
                ax.xaxis.label,
                *drawn_ticks(ax.xaxis, ax.get_xlim()),
                *drawn_ticks(ax.yaxis, ax.get_ylim()),
            ]
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts if t.get_visible() and t.get_text()]
    whole = fig.bbox
    for name, box in boxes:
        assert whole.x0 <= box.x0 and box.x1 <= whole.x1 and whole.y0 <= box.y0 and box.y1 <= whole.y1, name
    for (a, box_a), (b, box_b) in itertools.combinations(boxes, 2):
        assert not box_a.overlaps(box_b), (a, b)
