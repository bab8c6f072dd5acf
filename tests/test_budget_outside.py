"""The noise budget measured from outside the run, in `make test`: two captures of the default config that
differ only in the run seed (scripts/render_noise_reads.py, the second rendering the first run's samples and
refining its pixels), their difference of noise-free expected electrons per read being Monte Carlo noise
alone. The run's own estimate is what the budget decides on; this checks it against what it estimates."""

from __future__ import annotations

from pathlib import Path

import pytest
from script_modules import load_script

ROOT = Path(__file__).resolve().parents[1]

#: How far over the tail target (render.noise_budget_tail) a read's p99.9 measured from outside may lie. The
#: 99.9th percentile of 61440 samples rests on about 60 of them, each a one-degree-of-freedom estimate pooled over
#: its neighbours alike: at 160x128 the outside J4 figure was 0.80 (and 0.95 at 640x512), where the capture
#: without adaptive sampling in its tiles measured 3.5.
TAIL_SLACK = 1.5

#: Of the 4 reads x 3 quantiles x 2 runs = 24 stated 95 % intervals, how many may miss the outside figure: each
#: misses with probability 0.05 (1.2 expected), and P(more than 5 misses) = 0.0007 for independent intervals;
#: measured 0 of 24.
MOST_MISSES = 5


@pytest.mark.render
@pytest.mark.slow
def test_the_default_capture_meets_its_budget_measured_from_outside():
    script = load_script("render_noise_reads")
    base = ["render.width=160", "render.height=128", "render.cache=off", "sensor.noise_seed=7"]
    runs, _, choice = script.two_runs(ROOT / "configs" / "metronome_hdr.yaml", base, [1, 2])
    assert choice.tiers is not None and runs[0].report["adaptive"]["pixels"] > 0
    render = runs[0].config.render
    misses = 0
    for name, row in script.outside_figures(runs).items():
        assert row["median"] <= render.noise_budget, (name, row["median"])
        assert row["p95"] <= render.noise_budget_p95, (name, row["p95"])
        assert row["p999"] <= TAIL_SLACK * render.noise_budget_tail, (name, row["p999"])
        for key in ("median", "p95", "p999"):
            for own in row["own"]:
                low, high = own[f"to_shot_noise_variance_{key}_interval"]
                misses += not low <= row[key] <= high
    assert misses <= MOST_MISSES, misses
