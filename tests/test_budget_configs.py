"""Every shipped config whose samples the noise budget chooses (``render.spp: null``) meets the budget
at 160x128 (issue 26): the run's own estimate of its rendering noise, on every read, has its median
at most ``render.noise_budget`` and its 95th percentile at most ``render.noise_budget_p95``.

Marked ``budget`` and left out of ``make test``, which must stay under 6 minutes: with adaptive sampling
on, ``make test-budget`` runs its 16 captures two at a time in 8 min 25 s on the Intel Xeon of the sixteenth
session (2026-11-28; scripts/readme_tables.py, one after another in processes of their own: 527 s the session before). ``python
scripts/readme_tables.py --only budget`` runs the same captures and writes their figures into the README's
table.

The 99.9th percentile target (``render.noise_budget_tail``) is asserted too, on every config but those of
:data:`TAIL_NOT_MET` (none since the sixteenth session), where it is asserted to be missed (so that the list stays
the record of what is not yet met: a config that meets it fails here until it leaves the list). Adaptive sampling (on by default since
the fourteenth session) chooses the cheapest of its rules that brings the run's own estimate of the tail under
the target.
"""

from pathlib import Path

import pytest
import yaml

from mbcapture import load_config
from mbcapture.capture.run import run_capture

ROOT = Path(__file__).resolve().parents[1]
FILM = ["render.width=160", "render.height=128", "render.cache=off"]  # cold: no reused renders


#: The shipped configs whose tail the run does not yet bring under render.noise_budget_tail at 160x128, and why
#: (the run's own 99.9th percentile of the worst read in brackets). Empty since the sixteenth session, when adaptive
#: sampling came to spectral variants (metronome_spectral 3.2, rgb_illumination 6.5 before) and to a lens that mixes
#: neighbouring pixels (camera_full 4.8 before).
TAIL_NOT_MET: dict[str, str] = {}

#: Shipped configs that cap their samples below what the budget asks for, and why; asserted to miss it (the README's
#: budget table shows by how much), so that a config that comes to meet it leaves the list.
CAPPED: dict[str, str] = {
    name: "the glass ball's caustics (specular paths from a small light) ask for 1024 spp and for refining most "
    "pixels; the config caps render.max_spp at 128 with adaptive sampling off (docs/scenes.md)"
    for name in ("table_hdr", "table_flash_no_flash", "table_multi_flash")
} | {
    "tof_4tap": "a 15 um time-of-flight pixel's 100 000 e- wells keep its shot noise so low (SNR ~300 on the box) "
    "that the interreflections of the room's walls ask for more than render.max_spp = 1024 (median 0.17 x the "
    "shot noise's variance at 160x128; docs/tof.md)"
}


def budgeted_configs() -> list[str]:
    """The shipped configs whose samples the noise budget chooses."""
    return [
        p.stem
        for p in sorted((ROOT / "configs").glob("*.yaml"))
        if (yaml.safe_load(p.read_text()).get("render") or {}).get("spp") is None
    ]


def test_the_budgeted_configs_are_found():
    """Not marked: the list the budget test runs over is the shipped configs' (a glob that found none
    would make that test pass vacuously)."""
    names = budgeted_configs()
    assert len(names) >= 10 and "metronome_hdr" in names and "flatfield_ptc" in names
    assert set(TAIL_NOT_MET) | set(CAPPED) <= set(names)  # every config the lists excuse is one the test runs


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
    lines = [
        f"{n}: median {v['to_shot_noise_variance_median']:.3g}, p95 {v['to_shot_noise_variance_p95']:.3g}, "
        f"p99.9 {v['to_shot_noise_variance_p999']:.3g}"
        for n, v in reads.items()
    ]
    adaptive = {k: v for k, v in (report.get("adaptive") or {}).items() if k != "tiers"}
    adaptive["factors"] = [t["factor"] for t in (report.get("adaptive") or {}).get("tiers", [])]
    print(f"{name} (top-up: {report.get('top_up')}; adaptive: {adaptive}):\n  " + "\n  ".join(lines))
    if name in CAPPED:
        assert not budget["met"], f"{name} now meets the noise budget: take it out of CAPPED"
        return
    over = {
        n: v
        for n, v in reads.items()
        if v["to_shot_noise_variance_median"] > budget["median_target"]
        or v["to_shot_noise_variance_p95"] > budget["p95_target"]
    }
    assert not over and budget["met"], f"{name} misses the noise budget on {sorted(over)}: " + "; ".join(lines)
    if name in TAIL_NOT_MET:
        assert not budget["tail_met"], f"{name} now meets the tail target: take it out of TAIL_NOT_MET"
    else:
        tail = {
            n: v["to_shot_noise_variance_p999"]
            for n, v in reads.items()
            if v["to_shot_noise_variance_p999"] > budget["tail_target"]
        }
        assert not tail and budget["tail_met"], f"{name} misses the tail target on {tail}"
