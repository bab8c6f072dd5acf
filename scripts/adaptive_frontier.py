"""Adaptive sampling's rules for choosing pixels, each against what it costs, without rendering them.

What a rule leaves in the tail can be predicted from renders it does not need: two first passes of one
config that differ only in the run seed (their difference is Monte Carlo noise alone, as in
scripts/render_noise_reads.py) and a scout of its own (the one adaptive sampling chooses from,
:func:`mbcapture.budget.scout_ratio`). A rule gives each pixel a factor f of the first pass's samples;
where nothing moves a pixel's variance then falls as 1/f (an upper bound for the quasi-Monte Carlo
samplers), so the outside measurement after refinement is predicted by the same estimator on the two
first passes' squared differences divided by f: pooled over the alike of 3x3 pixels, over the
electrons. Where the moving parts cross, the refinement renders four times per half-stratum and the
time noise falls faster than 1/f: 1/f is kept there too (conservative).

Checked against real refinements on the default capture at 640x512 (seeds 1 and 2, 2026-11-27): the
3x3 box predicted J4's 99.9th percentile at 0.878 and render_noise_reads.py measured 0.877 from outside; the
four sides in place of the box (never run before then) predicted 0.915 and measured 0.906, the runs' own
0.918 and 0.910 (docs/noise.md, "The frontier"). The four sides are the rule in use.

The rules: a pixel is chosen where the scout's predicted ratio exceeds ``level`` x the tail target, its
factor the ratio over ``target`` x the tail target rounded up to a power of two in [2, max factor] (or,
with a fifth field ``int``, to an integer: adaptive sampling renders every factor in the same renders),
and the factors of the pixels at 2^``from`` or more (1: every chosen pixel, 2: those at 4x and up) spread
to their neighbours (``box``: 3x3, ``cross``: the four sides, ``none``). ``1,1,cross,1`` (level, target, dilation,
from) is :func:`mbcapture.budget.factor_tiers`, the rule in use (checked each run).

    python scripts/adaptive_frontier.py                       # the default capture at 640x512, a grid of rules
    python scripts/adaptive_frontier.py --size 160x128 --cache /tmp/f160.npz
    python scripts/adaptive_frontier.py --rule 1,1,cross,2 --rule 0.7,0.7,none,2

Renders three captures once (about 3 minutes at 640x512; ``--cache`` keeps them); each rule then takes
seconds. Prints, per rule, the samples it adds (over the first pass's, on the whole film, as report.json's
``adaptive.added_samples``), the pixels it refines and each read's predicted median, p95 and 99.9th
percentile.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
from scipy.ndimage import grey_dilation

from mbcapture import load_config
from mbcapture.budget import adaptive  # noqa: E402
from mbcapture.capture import pipeline
from mbcapture.budget import (
    ADAPTIVE_FOOTPRINT,
    ADAPTIVE_SELECT,
    budget_quantiles,
    effective_dof,
    factor_tiers,
    pooled_alike,
    scout_ratio,
    tail_pixels,
)
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus

sys.path.insert(0, str(Path(__file__).resolve().parent))  # render_noise_reads.py, a script beside this one
from render_noise_reads import FirstSamples, below_full_well, two_seeds  # noqa: E402

FOOTPRINTS = {"box": np.ones((3, 3), bool), "cross": np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool), "none": None}
#: The dilation of the rule in use (budget.ADAPTIVE_FOOTPRINT) by its name here.
IN_USE = next(name for name, f in FOOTPRINTS.items() if f is not None and np.array_equal(f, ADAPTIVE_FOOTPRINT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--set", action="append", default=[], dest="sets")
    ap.add_argument("--seeds", default="1,2", help="the two run seeds, comma-separated (the first one's scout chooses)")
    ap.add_argument("--cache", default=None, help="NPZ of the renders: read when it exists, written when not")
    ap.add_argument(
        "--rule",
        action="append",
        default=[],
        help="level,target,dilation,dilate-from[,steps] (e.g. 1,1,cross,1 or 1,1,box,1,int); "
        "default: a grid around the rule in use",
    )
    args = ap.parse_args()
    seeds = two_seeds(args.seeds)
    if args.cache and Path(args.cache).exists():
        data = dict(np.load(args.cache))
    else:
        data = render_inputs(args.config, args.size, seeds, args.sets)
        if args.cache:
            np.savez(args.cache, **data)
    rules = [parse_rule(r) for r in args.rule] or [
        (level, target, dil, start)
        for level, target, dil, start in itertools.product(
            (0.7, 1.0, 1.2), (0.7, 1.0), ("box", "cross", "none"), (1, 2)
        )
        if target <= level and not (dil == "none" and start == 2)
    ] + [
        (level, target, dil, 1, "int")
        for level, target, dil in itertools.product((0.7, 1.0), (0.7, 1.0), ("box", "cross"))
        if target <= level
    ]
    predicted = data["scout_worst"] * data["scale"]
    tail = float(data["tail_target"])
    in_use = factors(predicted, tail, ADAPTIVE_SELECT, ADAPTIVE_SELECT, IN_USE, 1, max_factor=int(data["max_factor"]))
    tiers = factor_tiers(predicted, ADAPTIVE_SELECT * tail, int(data["max_factor"]))
    expected = np.ones(predicted.size)
    for pixels, f in tiers:
        expected[pixels] = f
    if not np.array_equal(in_use.ravel(), expected):
        raise SystemExit(
            f"the rule {ADAPTIVE_SELECT:g},{ADAPTIVE_SELECT:g},{IN_USE},1 no longer reproduces "
            "budget.factor_tiers: update factors() here"
        )
    names = [str(n) for n in data["names"]]
    print(
        f"{args.config} at {args.size}: first passes of seeds {seeds[0]} and {seeds[1]}, the scout of seed {seeds[0]}; "
        f"the rule in use is level {ADAPTIVE_SELECT:g},target {ADAPTIVE_SELECT:g},{IN_USE},1"
    )
    print(
        f"{'level,target,dilation,from,steps':32s} {'added':>7s} {'pixels':>7s}   "
        + "   ".join(f"{n} median/p95/p99.9" for n in names)
    )
    rows = [("first pass alone", np.ones(predicted.shape))]
    rows += [
        (
            ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in rule),
            factors(predicted, tail, *rule, max_factor=int(data["max_factor"])),
        )
        for rule in rules
    ]
    for label, f in rows:
        figures = predict(data, f)
        added = float((f - 1.0).sum() / f.size)
        print(
            f"{label:32s} {added:7.3f} {int((f > 1).sum()):7d}   "
            + "   ".join(f"{m:.3f}/{p:.3f}/{t:.3f}" for m, p, t in figures)
        )


def parse_rule(text: str) -> tuple:
    """'level,target,dilation,from[,steps]' -> the rule's tuple; a clear error naming what is wrong."""
    parts = text.split(",")
    if len(parts) not in (4, 5) or parts[2] not in FOOTPRINTS or (len(parts) == 5 and parts[4] not in STEPS):
        raise SystemExit(
            f"--rule {text!r}: expected level,target,dilation,from[,steps] with dilation one of "
            f"{sorted(FOOTPRINTS)} and steps one of {list(STEPS)}, e.g. 1,1,box,1 or 1,1,cross,1,int"
        )
    level, target, start = float(parts[0]), float(parts[1]), int(parts[3])
    if not (0 < target <= level) or start < 1:
        raise SystemExit(f"--rule {text!r}: expected 0 < target <= level and from >= 1")
    return (level, target, parts[2], start) + ((parts[4],) if len(parts) == 5 else ())


#: How a chosen pixel's factor is rounded up from its ratio over the target: to a power of two, or to an integer.
STEPS = ("pow2", "int")


def factors(
    predicted: np.ndarray,
    tail_target: float,
    level: float,
    target: float,
    dilation: str,
    start: int,
    steps: str = "pow2",
    *,
    max_factor: int,
) -> np.ndarray:
    """(H, W) factor of each pixel under a rule (module doc): 1 where it is not refined. The factors at
    2^``start`` or more spread to the neighbours of ``dilation``."""
    chosen = predicted > level * tail_target
    fac = np.ones(predicted.shape)
    need = predicted[chosen] / (target * tail_target)
    if steps == "pow2":
        top = 2.0 ** int(np.log2(max_factor))
        fac[chosen] = np.clip(2.0 ** np.ceil(np.log2(need)), 2, top)
    else:
        fac[chosen] = np.clip(np.ceil(need), 2, max_factor)
    if FOOTPRINTS[dilation] is not None:
        spread = grey_dilation(
            np.where(fac >= 2**start, fac, 0), footprint=FOOTPRINTS[dilation], mode="constant", cval=0
        )
        fac = np.maximum(fac, spread)
    return fac


def predict(data: dict, f: np.ndarray) -> list[tuple[float, float, float]]:
    """Each read's predicted outside (median, p95, p99.9) after refining by the factors ``f`` (H, W): the two
    first passes' squared differences over 2, divided by f, pooled as the run's own estimate pools them
    (:func:`mbcapture.budget.pooled_alike`), over the mean electrons; the median deconvolved as
    render_noise_reads.py's (:func:`mbcapture.budget.budget_quantiles`)."""
    e1, e2 = data["e1"], data["e2"]
    out = []
    for r in range(e1.shape[0]):
        mean = (e1[r] + e2[r]) / 2
        use = (mean > 1.0) & data["below1"][r] & data["below2"][r] & (mean < float(data["fd_full_well_e"]))
        squared = (e1[r] - e2[r]) ** 2 / 2.0 / f[:, :, None]
        ratio = pooled_alike(squared, mean)[use] / mean[use]
        median, p95 = budget_quantiles(ratio, effective_dof(squared, use))
        out.append((median, p95, float(np.percentile(ratio, 99.9))))
    return out


class Scout:
    """Stands in for :func:`mbcapture.budget.tail_pixels` in the runs: the first call keeps the scout's predicted
    ratio, its scale and the rule's parameters, and every call returns the first one's choice by the rule in use
    (what the top-up judges the budget on, as a real run's does); the runs refine nothing
    (:func:`refine_nothing`), so their images are their first passes (and a top-up where a real run has one)."""

    def __init__(self):
        self.kept: dict | None = None
        self.tiers: list | None = None

    def __call__(
        self, mc_diff, buckets_e, k_e, reads, full_well_e, fd_full_well_e, tail_target, max_factor, scale=1.0, **kwargs
    ):
        if self.tiers is None:
            worst = scout_ratio(mc_diff, buckets_e, k_e, reads, full_well_e, fd_full_well_e)
            self.kept = {
                "scout_worst": worst,
                "scale": np.broadcast_to(np.asarray(scale, np.float64), worst.shape).copy(),
                "tail_target": float(tail_target),
                "max_factor": int(max_factor),
            }
            self.tiers = tail_pixels(
                mc_diff, buckets_e, k_e, reads, full_well_e, fd_full_well_e, tail_target, max_factor, scale, **kwargs
            )
        return self.tiers


def refine_nothing(passes, plan, integrated, tiers, info, **kwargs):
    """Stands in for :func:`mbcapture.budget.adaptive.refine_tail`: the first pass as it is."""
    return integrated, info


def render_inputs(config: str, size: str, seeds: list[int], sets: list[str]) -> dict:
    """The renders a rule is judged on: the first passes of two runs (the second at the first's samples per
    stratum) and the first run's scout."""
    w, h = size.split("x")
    base = [f"render.width={w}", f"render.height={h}", "render.cache=off", "sensor.noise_seed=7", *sets]
    samples, scout = FirstSamples(share=True), Scout()
    runs = []
    for i, s in enumerate(seeds):
        t0 = time.perf_counter()
        # both scout (the top-up judges the budget on the first run's choice, as a real run's does) and refine nothing
        overrides = [*base, f"seed={s}", "render.adaptive=true"]
        with (
            mock.patch.object(adaptive, "tail_pixels", scout),
            mock.patch.object(pipeline, "resolve_spp", samples),
            mock.patch.object(adaptive, "refine_tail", refine_nothing),
        ):
            runs.append(capture_in_memory(load_config(config, overrides), StageStatus(False)))
        print(f"seed {s}: {time.perf_counter() - t0:.0f} s, spp {runs[-1].plan.spp_label()}", flush=True)
    if scout.kept is None:
        raise SystemExit(
            f"{config}: the first run made no scout (render.spp must be null and adaptive sampling apply: "
            f"{runs[0].report.get('adaptive')})"
        )
    cfg = runs[0].config
    return {
        "e1": np.asarray(runs[0].reads_expected_e, np.float64),
        "e2": np.asarray(runs[1].reads_expected_e, np.float64),
        "below1": below_full_well(runs[0], cfg.sensor.full_well_e),
        "below2": below_full_well(runs[1], cfg.sensor.full_well_e),
        "fd_full_well_e": float(cfg.sensor.fd_full_well_e),
        "names": np.array([rd.name for rd in runs[0].timeline.reads]),
        **scout.kept,
    }


if __name__ == "__main__":
    main()
