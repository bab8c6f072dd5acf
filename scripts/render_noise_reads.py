"""Rendering noise on every read, measured from outside the run: two captures of one config that
differ only in the run seed (render samples, strata jitter, pilot), with the sensor's noise seed
fixed and the render cache off. The difference of their noise-free expected electrons per read is
Monte Carlo noise alone: per unsaturated sample, its variance (the squared difference over 2, pooled
over the pixels of its 3x3 neighbourhood as bright as it, like the run's own estimate,
:func:`mbcapture.budget.pooled_alike`) over the shot-noise variance (the electrons). Prints
each read's median, p95, p99, p99.9 and max, the share above 10, and each run's own estimate, with
whether the outside figure falls in the interval each run states for its median, p95 and p99.9.

    python scripts/render_noise_reads.py [CONFIG] [--size 640x512] [--set KEY=VALUE ...] [--map tail.png]

``--truth N``: the converged median as well, from N runs (the two and N - 2 more seeds; the samples per
pixel must be fixed, ``--set render.spp=...``): each sample's variance over the N runs, pooled like the
run's (up to 9 (N - 1) degrees of freedom), its median over the samples unsaturated in every run, and each
estimate (outside and own) over it. And the tail from each sample's own variance over the N runs (N - 1
degrees of freedom, no neighbour's noise in it) against the two runs' pooled estimates, alike and over
every neighbour (a comparison: the runs pool over alike neighbours only).

The second run renders the samples per stratum the first run's pilot chose (every run's pilot still
renders), and with adaptive sampling (``render.adaptive``) it refines the pixels the first run chose
(its tiers, :func:`mbcapture.budget.tail_pixels`), so both runs are draws of one estimator: the first
run's, whose error its own figures estimate (were each run to render its own pilot's samples, the outside
figure would be the mean of two estimators' variances). Each run choosing
its own samples and pixels (``--own-choices``) measures
something else: at 640x512 the two choices share 10111
of about 27000 pixels, and the two-run difference then averages a field refined in one place with a
field refined in another, whose upper quantiles lie below either run's (J4's p99.9 0.85 that way,
0.93 with one choice; the runs' own 1.10-1.18).

``--map``: a picture of where the tail lies: the longest read's noise-free image with its samples
whose rendering noise exceeds 10x (red) and 1x (yellow) their shot noise marked.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from unittest import mock

import numpy as np

from mbcapture import load_config
from mbcapture.budget import adaptive  # noqa: E402
from mbcapture.capture import pipeline
from mbcapture.budget import (
    budget_quantiles,
    deconvolved_median,
    effective_dof,
    pooled,
    pooled_alike,
    resolve_spp,
    tail_pixels,
)
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--set", action="append", default=[], dest="sets")
    ap.add_argument("--seeds", default="1,2", help="the two run seeds, comma-separated")
    ap.add_argument("--map", default=None, help="PNG of where the longest read's tail lies")
    ap.add_argument(
        "--own-choices",
        action="store_true",
        help="each run renders its own pilot's samples and, with render.adaptive, refines its own choice of pixels "
        "(default: the first run's samples and choice)",
    )
    ap.add_argument("--truth", type=int, default=0, help="runs for the converged median (0: none; at least 3)")
    args = ap.parse_args()
    w, h = args.size.split("x")
    seeds = two_seeds(args.seeds)
    if args.truth and args.truth < 3:
        raise SystemExit(f"--truth: at least 3 runs, got {args.truth}")
    if args.truth and not any(sv.startswith("render.spp=") and sv != "render.spp=null" for sv in args.sets):
        raise SystemExit("--truth: fix the samples per pixel (--set render.spp=N): the runs must share them")
    base = [f"render.width={w}", f"render.height={h}", "render.cache=off", "sensor.noise_seed=7", *args.sets]
    runs, seconds, choice = two_runs(args.config, base, seeds, share=not args.own_choices)
    cfg = runs[0].config
    print(
        f"{args.config} at {args.size}: spp {runs[0].plan.spp_label()} and {runs[1].plan.spp_label()}; "
        f"{seconds[0]:.0f} s and {seconds[1]:.0f} s (render cache off)"
    )
    if choice.tiers is not None:
        print(
            f"adaptive sampling: {sum(p.size for p, _ in choice.tiers)} pixels refined, "
            + (
                "each run choosing its own (--own-choices)"
                if args.own_choices
                else "the second run refining the first run's choice"
            )
        )
    n = [float(np.asarray(r.plan.spp).sum()) for r in runs]
    if abs(n[0] - n[1]) > 1e-9 * max(n):
        # the outside variance is the mean of the two runs' (Var[e1 - e2] / 2): a run with more samples
        # reads its own figures below it, the other above, by about half the difference each
        print(
            f"the runs' samples per pixel differ by {100 * (n[1] / n[0] - 1):+.1f} % (seed {seeds[1]} against seed "
            f"{seeds[0]}); the outside figure is the mean of their variances, each run's own is its own"
        )
    print(
        f"{'read':6s} {'median':>8s} {'p95':>8s} {'p99':>8s} {'p99.9':>8s} {'max':>9s} {'>10x':>7s}   run's own "
        f"median / p95 / p99.9 (seed {seeds[0]}, seed {seeds[1]})"
    )
    below = [below_full_well(r, cfg.sensor.full_well_e) for r in runs]  # (R, H, W, C) each
    for name, row in outside_figures(runs).items():
        own = row["own"]
        own_text = ", ".join(
            f"{o.get('to_shot_noise_variance_median', float('nan')):.3g} / "
            f"{o.get('to_shot_noise_variance_p95', float('nan')):.3g} / "
            f"{o.get('to_shot_noise_variance_p999', float('nan')):.3g}"
            for o in own
        )
        print(
            f"{name:6s} {row['median']:8.3g} {row['p95']:8.3g} {row['p99']:8.3g} {row['p999']:8.3g} "
            f"{row['max']:9.3g} {100 * row['over_10']:6.2f}%   {own_text}"
        )
        # does the outside measurement fall in each run's stated 95 % interval?
        for q, key in (("median", "median"), ("p95", "p95"), ("p99.9", "p999")):
            outside = row[key]
            ivs = [o.get(f"to_shot_noise_variance_{key}_interval") for o in own]
            text = "; ".join(
                "no interval"
                if iv is None
                else f"[{iv[0]:.3g}, {iv[1]:.3g}] {'holds' if iv[0] <= outside <= iv[1] else 'MISSES'} it"
                for iv in ivs
            )
            print(f"{'':6s} {q:>6s}: outside {outside:.3g}; the runs' intervals {text}")
        mean, full_ratio = row["mean"], row["ratio_map"]
    if args.map:
        tail_map(args.map, mean, full_ratio, name)
    if args.truth:
        converged(args, base, runs, below, choice)


def two_runs(config, base: list[str], seeds: list[int], share: bool = True) -> tuple[list, list[float], "FirstChoice"]:
    """Two captures of ``config`` with ``base`` overrides at the run seeds ``seeds``, the second rendering the first
    run's samples and refining its choice of pixels (``share``; else each its own). Returns the runs, their
    seconds and the choice."""
    runs, seconds = [], []
    choice, samples = FirstChoice(share=share), FirstSamples(share=share)
    for s in seeds:
        t0 = time.perf_counter()
        choice.start_run()
        with mock.patch.object(adaptive, "tail_pixels", choice), mock.patch.object(pipeline, "resolve_spp", samples):
            runs.append(capture_in_memory(load_config(config, [*base, f"seed={s}"]), StageStatus(False)))
        seconds.append(time.perf_counter() - t0)
    return runs, seconds, choice


def outside_figures(runs: list) -> dict[str, dict]:
    """Per read of two :func:`two_runs`: the rendering noise measured from outside, its variance over the shot
    noise's in every sample below the full wells (median and p95 as the budget takes them, p99, p99.9, max, the
    share over 10), the runs' own figures (``own``, each run's render_error entry), and for a map the mean
    electrons and the ratio per sample (0 where not judged)."""
    cfg = runs[0].config
    below = [below_full_well(r, cfg.sensor.full_well_e) for r in runs]  # (R, H, W, C) each
    out = {}
    for i, read in enumerate(runs[0].timeline.reads):
        e1, e2 = (r.reads_expected_e[i] for r in runs)
        mean = (e1 + e2) / 2
        use = (mean > 1.0) & below[0][i] & below[1][i] & (mean < cfg.sensor.fd_full_well_e)
        squared = (e1 - e2) ** 2 / 2.0
        var = pooled_alike(squared, mean)
        ratio = var[use] / mean[use]
        med, p95 = budget_quantiles(ratio, effective_dof(squared, use))
        p99, p999 = np.percentile(ratio, [99, 99.9])
        out[read.name] = {
            "median": float(med),
            "p95": float(p95),
            "p99": float(p99),
            "p999": float(p999),
            "max": float(ratio.max()),
            "over_10": float((ratio > 10).mean()),
            "own": [r.report["render_error"].get("reads", {}).get(read.name, {}) for r in runs],
            "mean": mean,
            "ratio_map": np.where(use, var / np.maximum(mean, 1e-300), 0.0),
        }
    return out


class FirstChoice:
    """Stands in for :func:`mbcapture.budget.tail_pixels` in the runs: the first run's calls (adaptive sampling's
    first round, and a second where its own estimate of the tail was still over) choose as the run would, and
    later runs' calls return those in order (``share``) or choose afresh. A later run that calls more often than
    the first (a second round the first did not need) chooses its extra rounds itself."""

    def __init__(self, share: bool):
        self.share, self.choices, self.calls = share, [], 0

    def start_run(self) -> None:
        """Before each run: its calls count from the first round again (each run its own, without ``share``)."""
        self.calls = 0
        if not self.share:
            self.choices = []

    @property
    def tiers(self):
        """The first round's choice (the last run's without ``share``), None before any."""
        return self.choices[0] if self.choices else None

    def __call__(self, *args, **kwargs):
        i, self.calls = self.calls, self.calls + 1
        if i < len(self.choices):
            return self.choices[i]
        self.choices.append(tail_pixels(*args, **kwargs))
        return self.choices[-1]


class FirstSamples:
    """Stands in for :func:`mbcapture.budget.resolve_spp` in the runs: every run's pilot renders, and the
    first run's samples per stratum are kept; later runs render those (``share``) or their own pilot's."""

    def __init__(self, share: bool):
        self.share, self.spp = share, None

    def __call__(self, plan, *args, **kwargs):
        out = resolve_spp(plan, *args, **kwargs)
        if self.spp is None or not self.share:
            self.spp = None if out.spp is None else np.asarray(out.spp).copy()
        elif out.spp is not None:
            out = replace(out, spp=self.spp.copy())
        return out


def two_seeds(text: str) -> list[int]:
    """``--seeds``: two comma-separated run seeds, or a clear error."""
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        seeds = []
    if len(seeds) != 2:
        raise SystemExit(f"--seeds: two comma-separated run seeds expected, got {text!r}")
    return seeds


def below_full_well(run, full_well_e: float) -> np.ndarray:
    """(R, H, W, C) bool: for each read of ``run``, every one of its buckets below the full well."""
    return np.stack([(run.buckets_e[list(rd.buckets)] < full_well_e).all(axis=0) for rd in run.timeline.reads])


def converged(args, base: list[str], runs: list, below: list[np.ndarray], choice: "FirstChoice") -> None:
    """--truth: the median of each read's ratio from args.truth runs, against the two runs' estimates
    (``below``: each run's :func:`below_full_well`; ``choice``: the runs' pixels to refine)."""
    spp = [np.asarray(r.plan.spp) for r in runs]
    if not np.array_equal(*spp):
        raise SystemExit("--truth: the two runs rendered different samples per pixel")
    seeds = [int(s) for s in args.seeds.split(",")]
    more = [max(seeds) + 1 + i for i in range(args.truth - 2)]
    cfg = runs[0].config
    reads = [r.reads_expected_e for r in runs]
    full = list(below)
    t0 = time.perf_counter()
    for s in more:
        choice.start_run()
        with mock.patch.object(adaptive, "tail_pixels", choice):
            r = capture_in_memory(load_config(args.config, [*base, f"seed={s}"]), StageStatus(False))
        reads.append(r.reads_expected_e)
        full.append(below_full_well(r, cfg.sensor.full_well_e))
    print(
        f"converged median from {args.truth} runs (seeds {seeds + more}; {time.perf_counter() - t0:.0f} s for the "
        f"{len(more)} more): each estimate over it"
    )
    E = np.stack(reads)  # (N, R, H, W, C)
    ok = np.stack(full).all(axis=0)
    for i, read in enumerate(runs[0].timeline.reads):
        mean = E[:, i].mean(axis=0)
        use = (mean > 1.0) & ok[i] & (mean < cfg.sensor.fd_full_well_e)
        var_n = E[:, i].var(axis=0, ddof=1)
        ratio = pooled_alike(var_n, mean)[use] / mean[use]
        truth = deconvolved_median(ratio, 9.0 * (args.truth - 1))
        e1, e2 = E[0, i], E[1, i]  # the outside figure of the first two runs, on the samples unsaturated in all
        squared = (e1 - e2) ** 2 / 2.0
        pair_mean = (e1 + e2) / 2
        pair_ratio = pooled_alike(squared, pair_mean)[use] / pair_mean[use]
        outside = budget_quantiles(pair_ratio, effective_dof(squared, use))[0]
        own = [r.report["render_error"]["reads"][read.name]["to_shot_noise_variance_median"] for r in runs]
        print(
            f"{read.name:6s} converged median {truth:.4g}; outside {outside / truth:.3f} of it, the runs' own "
            f"{own[0] / truth:.3f} and {own[1] / truth:.3f}"
        )
        # the tail: each sample's own variance over the N runs (N - 1 degrees of freedom, not pooled: no
        # neighbour's noise in it), against the two runs' pooled estimates, alike (the run's) and box
        own_tail = np.percentile(var_n[use] / mean[use], [95, 99, 99.9])
        alike_tail = np.percentile(pair_ratio, [95, 99, 99.9])
        box_tail = np.percentile(pooled(squared[None])[0][use] / pair_mean[use], [95, 99, 99.9])
        print(
            f"{'':6s} p95 / p99 / p99.9: each sample's own over {args.truth} runs "
            f"{' / '.join(f'{x:.3g}' for x in own_tail)}; two runs pooled alike "
            f"{' / '.join(f'{x:.3g}' for x in alike_tail)}, pooled over every neighbour "
            f"{' / '.join(f'{x:.3g}' for x in box_tail)}"
        )


def tail_map(path: str, electrons: np.ndarray, ratio: np.ndarray, name: str) -> None:
    """The read's image (grey, gamma 1/2.2) with samples above 1x (yellow) and 10x (red) marked, any channel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grey = electrons.mean(axis=-1)
    grey = np.clip(grey / np.percentile(grey, 99.5), 0, 1) ** (1 / 2.2)
    rgb = np.repeat(grey[..., None], 3, -1) * 0.7
    worst = ratio.max(axis=-1)
    rgb[worst > 1] = (1.0, 0.85, 0.0)
    rgb[worst > 10] = (1.0, 0.0, 0.0)
    fig, ax = plt.subplots(figsize=(8, 6.6))
    ax.imshow(rgb, interpolation="nearest")
    ax.set_title(
        f"read {name}: rendering / shot-noise variance > 1 (yellow), > 10 (red); "
        f"{100 * (worst > 10).mean():.3f} % of pixels > 10",
        fontsize=9,
    )
    ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
