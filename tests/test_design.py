"""mbcapture design: the noise-optimal reference (Hasinoff et al. 2010), the search recovering it, the outputs of a
search on captures, and bad specs."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import yaml

from mbcapture import load_config
from mbcapture.cli import main
from mbcapture.design.results import run_design
from mbcapture.design.search import grid_values
from mbcapture.design.spec import load_design, ratios_of
from mbcapture.errors import ConfigError
from mbcapture.reconstruct.hdr import quantization_read_variance_e2
from mbcapture.sensor import electrons_per_radiance_second
from mbcapture.studies.dynamic_range import GREEN, LUMINOUS_EFFICACY_LM_PER_W
from mbcapture.studies.noise_optimal import NoiseModel, db, optimum, snr_at, worst_snr


def _reference_problem(spec_name: str):
    """The noise model and rate range of a shipped noise-optimal spec, as the reference sees them."""
    design = load_design(spec_name)
    s = design.config({}).sensor
    k = float(electrons_per_radiance_second(s)[GREEN])
    model = NoiseModel(
        quantization_read_variance_e2(s),
        min(s.full_well_e, s.fd_full_well_e, (s.adc_max_dn - s.black_level_dn) / s.gain_dn_per_e),
    )
    lo, hi = (x / LUMINOUS_EFFICACY_LM_PER_W * k for x in design.spec.evaluator.luminance_cd_m2)
    return design, model, lo, hi


def test_the_worst_snr_is_the_least_on_a_dense_grid():
    """worst_snr looks only at the range's low end and just past each shot's saturation: a dense grid finds no
    lower value (and one just past a cut is where it is)."""
    model = NoiseModel(9.5, 10_000.0)
    t = np.array([2e-6, 2.5e-4, 0.03])
    lo, hi = 2.8e3, 2.8e9
    dense = np.geomspace(lo, hi, 200_001)
    assert worst_snr(t, lo, hi, model) <= snr_at(dense, t, model).min() * (1 + 1e-9)
    assert worst_snr(t, lo, hi, model) == pytest.approx(snr_at(dense, t, model).min(), rel=2e-3)


def test_the_reference_optimum_balances_its_worst_points():
    """The minimax optimum of three shots makes the low end and the points past each saturation equally bad."""
    _, model, lo, hi = _reference_problem("noise_optimal_sequential")
    t, w = optimum(3, 0.03, lo, hi, model)
    assert t.sum() == pytest.approx(0.03, rel=1e-6)  # the whole budget spent
    corners = [lo] + list(model.full_well_e / t[1:] * (1 + 1e-9))
    np.testing.assert_allclose(snr_at(np.array(corners), t, model), w, rtol=1e-3)
    # two shots cannot cover 1 to 10^6 cd/m^2 as well: the range needs the third
    assert optimum(2, 0.03, lo, hi, model)[1] < w / 10


@pytest.mark.slow
def test_design_recovers_the_noise_optimal_sequence(tmp_path):
    """The issue's check: `mbcapture design` on the conventional sensor's sequential frames (the analytic SNR of
    its inverse-variance merge) finds Hasinoff et al.'s optimum: the worst SNR within 0.1 dB of the reference's,
    the longest exposure within 2 % and the middle one within 15 % (the shortest only has to keep the top of the
    range unsaturated and sets no corner, so it is not pinned)."""
    design, model, lo, hi = _reference_problem("noise_optimal_sequential")
    ref_t, ref_w = optimum(3, 0.03, lo, hi, model)
    doc = run_design(design, tmp_path / "out", progress=False, say=lambda s: None)
    found = doc["best"]
    assert abs(found["objective"] - db(ref_w)) < 0.1
    best = yaml.safe_load((tmp_path / "out" / "best.yaml").read_text())
    t = best["capture"]["unit_exposure_s"] * np.array(best["capture"]["exposure_ratios"])
    assert t[2] == pytest.approx(ref_t[2], rel=0.02)
    assert t[1] == pytest.approx(ref_t[1], rel=0.15)
    assert worst_snr(t, lo, hi, model) == pytest.approx(ref_w, rel=0.02)  # the reference agrees with the tool


def test_ratios_grid_and_extremes():
    assert ratios_of([1.0, 0.5], 64.0) == [1.0, 8.0, 64.0]
    assert ratios_of([0.5, 0.5], 64.0) is None  # two reads would coincide
    design = load_design("hdr_4bucket")
    grid = grid_values(design.spec.variables, 24)
    assert 1 < len(grid) <= 24
    assert all(g["sensor.bucket_count"] == 4 and g["capture.exposure_ratios"][0] == 1.0 for g in grid)
    # span_s holds the capture's span (T to 4 significant digits): T follows the ratios, for every design of the grid
    from mbcapture.timing import protocols

    for g in grid[:5]:
        tl = protocols.build(design.config(g))
        assert float((tl.end_tick - tl.start_tick) * tl.tick_s) == pytest.approx(0.008, rel=1e-3)


def test_a_search_on_captures_writes_a_runnable_best_design_and_its_history(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        yaml.safe_dump(
            {
                "base": "tiny_hdr",
                "set": {"render.width": 32, "render.height": 24},
                "variables": {
                    "capture.unit_exposure_s": {"low": 2e-4, "high": 2e-3, "log": True},
                    "sensor.gain_dn_per_e": {"choices": [0.2, 0.4]},
                },
                "objective": {"metric": "hdr_rel_mse", "direction": "minimize"},
                "constraints": {"capture_span_s": {"max": 0.0085}},
                "evaluations": 3,
                "seeds": 2,
            }
        )
    )
    out = tmp_path / "out"
    doc = run_design(load_design(spec), out, progress=False, say=lambda s: None)
    hist = pd.read_parquet(out / "history.parquet")
    assert list(hist["source"]).count("search") == 3 and (hist["source"] == "default").sum() == 1
    assert (hist["source"] == "grid").sum() == doc["evaluations"]["grid"] <= 3
    ok = hist[hist["feasible"]]
    assert (ok["objective_se"] > 0).all()  # two seeds: a standard error
    assert (ok["capture_span_s"] <= 0.0085 + 1e-12).all()  # the best is among designs that keep the constraint
    best = load_config(out / "best.yaml")  # a config mbcapture run takes
    assert best.render.width == 32
    assert doc["best"]["objective"] == pytest.approx(ok[ok["source"] == "search"]["objective"].min())
    assert (out / "objective.png").stat().st_size > 1000 and (out / "report.html").is_file()
    # every design on the same noise seeds: the margin over the default has its paired standard error too
    margin = doc["margins"]["vs_default"]
    assert margin is not None and np.isfinite(margin["paired_standard_errors"])


@pytest.mark.slow
def test_two_objectives_give_a_pareto_front(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        yaml.safe_dump(
            {
                "base": "metronome_hdr",
                "set": {"capture.exposure_ratios": [1, 4, 16], "sensor.bucket_count": 3},
                "variables": {"capture.unit_exposure_s": {"low": 1e-6, "high": 1e-3, "log": True}},
                "objective": {"metric": "snr.worst_db", "direction": "maximize"},
                "second_objective": {"metric": "capture_span_s", "direction": "minimize"},
                "evaluator": {"luminance_cd_m2": [1.0, 1000.0]},
                "evaluations": 12,
                "seeds": 1,
                "compare_grid": False,
            }
        )
    )
    out = tmp_path / "out"
    doc = run_design(load_design(spec), out, progress=False, say=lambda s: None)
    front = doc["pareto_front"]
    assert len(front) >= 2 and (out / "pareto.png").is_file()
    # along the front, a longer capture buys a better worst SNR
    pts = sorted((f["second_objective"], f["objective"]) for f in front)
    assert all(b[1] > a[1] for a, b in zip(pts, pts[1:]))


def test_bad_specs_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        yaml.safe_dump(
            {
                "base": "tiny_hdr",
                "variables": {"sensor.read_noise_e": {"low": -5.0, "high": -1.0}},
                "objective": {"metric": "hdr_rel_mse"},
            }
        )
    )
    with pytest.raises(ConfigError, match=r"variables\.sensor\.read_noise_e: no config accepts"):
        load_design(bad)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text(
        yaml.safe_dump(
            {
                "base": "tiny_hdr",
                "set": {"render.width": 32, "render.height": 24},
                "variables": {"capture.unit_exposure_s": {"low": 5e-4, "high": 1e-3}},
                "objective": {"metric": "no_such_metric"},
                "evaluations": 2,
                "seeds": 1,
            }
        )
    )
    rc = main(["design", str(unknown), "--out", str(tmp_path / "o"), "--quiet"])
    assert rc == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "objective 'no_such_metric' is not measured" in lines[0] and "hdr_rel_mse" in lines[0]
    assert not (tmp_path / "o").exists()  # nothing half-written
    with pytest.raises(ConfigError, match="not found"):
        load_design(tmp_path / "missing.yaml")


def test_continuous_values_keep_the_timeline_s_tick_coarse():
    """A share drawn as 0.4372918347 makes the flash slot's exact duration need more than 2^62 ticks; the search
    writes values to 4 significant digits, which build."""
    from mbcapture.design.search import sig4
    from mbcapture.timing import protocols

    design = load_design("flash_no_flash")
    with pytest.raises(ConfigError, match="2\\^62 ticks"):
        protocols.build(design.config({"app.flash_share": 0.4372918347, "app.flash_duty": 0.7129384712}))
    tl = protocols.build(design.config({"app.flash_share": sig4(0.4372918347), "app.flash_duty": sig4(0.7129384712)}))
    assert [r.name for r in tl.reads] == ["flash", "noflash"]
    flash, noflash = (float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads)
    assert flash / (flash + noflash) == pytest.approx(0.4373, rel=1e-9)


def test_a_space_that_fits_the_budget_is_searched_exhaustively(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        yaml.safe_dump(
            {
                "base": "metronome_hdr",
                "variables": {"capture.unit_exposure_s": {"choices": [1e-4, 2e-4, 4e-4]}},
                "objective": {"metric": "snr.worst_db", "direction": "maximize"},
                "evaluator": {"luminance_cd_m2": [1.0, 1000.0]},
                "evaluations": 5,
                "seeds": 1,
            }
        )
    )
    doc = run_design(load_design(spec), tmp_path / "out", progress=False, say=lambda s: None)
    hist = pd.read_parquet(tmp_path / "out" / "history.parquet")
    searched = hist[hist["source"] == "search"]["value.capture.unit_exposure_s"]
    assert sorted(searched) == ["0.0001", "0.0002", "0.0004"]  # each once, not five draws
    assert doc["best"]["objective"] == pytest.approx(hist[hist["source"] == "search"]["objective"].max())


def test_the_grid_s_counted_sizes_are_the_sizes_it_makes():
    """grid_values counts each axis before making it (the ratios' combinations are many): the count is the
    number of designs made, for ratios, log ranges, integer ranges and choices."""
    from mbcapture.design.search import axis_size
    from mbcapture.design.spec import Variable

    variables = {
        "capture.exposure_ratios": Variable(ratios={"count": [2, 3], "max_ratio": 1e5}),
        "capture.unit_exposure_s": Variable(low=1e-5, high=1e-3, log=True),
        "capture.periods": Variable(low=1, high=6, integer=True),
        "sensor.gain_dn_per_e": Variable(choices=[0.2, 0.4]),
    }
    for budget in (60, 300):
        grid = grid_values(variables, budget)
        levels = next(
            n for n in range(max(2, budget), 1, -1) if math.prod(axis_size(v, n) for v in variables.values()) <= budget
        )
        assert len(grid) == math.prod(axis_size(v, levels) for v in variables.values()) <= budget
