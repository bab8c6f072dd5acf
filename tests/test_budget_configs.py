"""Every shipped config whose samples the noise budget chooses (``render.spp: null``) meets the budget
at 160x128 (issue 26): the run's own estimate of its rendering noise, on every read, has its median
at most ``render.noise_budget`` and its 95th percentile at most ``render.noise_budget_p95``.

Marked ``budget`` and left out of ``make test``: its 16 captures take about 12 minutes one after
another on 2 cores (scripts/readme_tables.py: 718 s; hdr_video's 16 frames 225 s of it), 10 minutes
as ``make test-budget`` runs them, two at a time (2 min 20 s on the faster AMD EPYC of 2026-11-27), and the suite must stay under 6. ``python scripts/readme_tables.py --only
budget`` runs the same captures and writes their figures into the README's table. The
99.9th percentile target (``render.noise_budget_tail``) is not asserted: without adaptive sampling
no config meets it (docs/noise.md), and each capture's tail is printed instead.
"""

from pathlib import Path

import pytest
import yaml

from mbcapture import load_config
from mbcapture.capture import run_capture

ROOT = Path(__file__).resolve().parents[1]
FILM = ["render.width=160", "render.height=128", "render.cache=off"]  # cold: no reused renders


def budgeted_configs() -> list[str]:
    """The shipped configs whose samples the noise budget chooses."""
    return [p.stem for p in sorted((ROOT / "configs").glob("*.yaml"))
            if (yaml.safe_load(p.read_text()).get("render") or {}).get("spp") is None]


def test_the_budgeted_configs_are_found():
    """Not marked: the list the budget test runs over is the shipped configs' (a glob that found none
    would make that test pass vacuously)."""
    names = budgeted_configs()
    assert len(names) >= 10 and "metronome_hdr" in names and "flatfield_ptc" in names


@pytest.mark.budget
@pytest.mark.render
@pytest.mark.parametrize("name", budgeted_configs())
def test_every_budgeted_config_meets_the_noise_budget_at_160x128(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml", FILM)
    report = run_capture(cfg, None, progress=False).report
    error = report["render_error"]
    reads = error.get("reads", {})
    assert reads, f"{name}: no read estimate in report.json's render_error"
    budget = error["budget"]
    lines = [f"{n}: median {v['to_shot_noise_variance_median']:.3g}, p95 {v['to_shot_noise_variance_p95']:.3g}, "
             f"p99.9 {v['to_shot_noise_variance_p999']:.3g}" for n, v in reads.items()]
    print(f"{name} (top-up: {report.get('top_up')}):\n  " + "\n  ".join(lines))
    over = {n: v for n, v in reads.items()
            if v["to_shot_noise_variance_median"] > budget["median_target"]
            or v["to_shot_noise_variance_p95"] > budget["p95_target"]}
    assert not over and budget["met"], f"{name} misses the noise budget on {sorted(over)}: " + "; ".join(lines)
