"""How well can adaptive sampling choose its pixels? Rules measured against a converged truth, offline.

Adaptive sampling (docs/noise.md) refines the pixels whose rendering noise it estimates to be over the
tail target. Its cost is set by how well that estimate finds them: an oracle would refine a few per
cent of the film, the pooled half-sample estimate with its 3x3 dilation refines far more. This study
renders the static film of a config at one time the way the first pass renders a static pixel:
--strata strata of --spp samples, each half of the samples continuing its own shared pattern
(mbcapture.render.pattern), for --seeds independent pairs of patterns. It sums the strata (a read
that weighs them alike, as J4 does), and for each of a few held-out seeds compares rules that see
only that seed's renders with the truth from all the other seeds:

* ``A``: the pooled half-sample estimate, (half 0 - half 1)^2 / 4 averaged over 3x3 pixels (as the
  run's own, but over every neighbour, not only the alike ones), with or without the 3x3 dilation;
* ``B``: the spread between the strata: at a static pixel every stratum renders the same value, so
  the variance of the 2 x --strata half-stratum renders about their mean, times their count / 4, is
  the variance the sum would have if the strata were independent (2 x --strata - 1 degrees of
  freedom per pixel); the shared pattern's stratification across strata only lowers the truth, so
  it reads high, not low;
* ``min(B, 4A)``: B capped by the half-sample estimate, for pixels where the strata differ in more
  than noise (motion, a moving light, a projector's patterns);
* the oracle: the truth itself.

Each rule refines the pixels it puts over tau (in units where the truth's median ratio is 0.1, the
budget's median target) by 4x, or by the power of two that brings its estimate to tau / 2 (2x-8x,
"tiers"); the table gives the truth's 99.9th percentile afterwards and the samples added, over the
first pass's. Static film only; the moving region is another matter. Built into the pipeline, B's
choice did not pay on the default capture (docs/noise.md, "A selection that pays for itself?").

    python scripts/selection_study.py [CONFIG] [--size 320x256] [--spp 180] [--strata 7] [--seeds 30]

About 26 s a seed at the defaults on 2 cores (13 minutes).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import grey_dilation, uniform_filter

from mbcapture import load_config
from mbcapture.capture.pipeline import prepare
from mbcapture.render.renderer import Renderer

#: Selection levels (tau) and the seeds held out, in turn, as "the run".
LEVELS = (0.3, 0.5, 0.7, 1.0, 1.4)
HELD_OUT = 4


def render_halves(config: str, width: int, height: int, spp: int, strata: int, seeds: int) -> np.ndarray:
    """(seeds, 2, strata, H, W, C) float32: each half-stratum's radiance, summed over the groups."""
    cfg = load_config(config, [f"render.width={width}", f"render.height={height}", "render.cache=off"])
    scene, _, plan, _ = prepare(cfg)
    t, groups = float(plan.times_s[0]), plan.groups
    renderer = Renderer.from_config(scene, cfg)
    n = renderer.sample_count(spp)
    out = np.zeros((seeds, 2, strata, height, width, len(renderer.channels)), np.float32)
    for s in range(seeds):
        for h in range(2):
            key = (2 * s + h + 1) * 2654435761 & 0xFFFFFFFF
            for j in range(strata):  # stratum j continues the half's pattern after strata 0 .. j - 1
                out[s, h, j] = renderer.render(t, n, 1000 + s, groups, pattern=(key, j * n)).sum(axis=0)
        print(f"  seed {s + 1} of {seeds}", flush=True)
    return out


def pool(x: np.ndarray) -> np.ndarray:
    return uniform_filter(x, size=(3, 3, 1), mode="nearest")


def factors(estimate: np.ndarray, tau: float, mode: str, dilate: bool) -> np.ndarray:
    """(H, W) samples factor per pixel (1: not refined) from (H, W) worst-channel estimates."""
    over = estimate > tau
    if mode == "x4":
        f = np.where(over, 4, 1)
    else:  # the power of two that brings the estimate to tau / 2, 2x-8x
        f = np.where(over, np.clip(2.0 ** np.ceil(np.log2(np.maximum(2 * estimate / tau, 2))), 2, 8), 1)
    return grey_dilation(f, size=(3, 3)) if dilate else f


def study(halves: np.ndarray, run: int) -> tuple[float, dict[str, list[tuple[float, str, float, float]]]]:
    """The truth's p99.9 before refinement, and per rule [(tau, mode, p99.9 after, samples added)]."""
    S, _, K, H, W, C = halves.shape
    sums = halves.sum(axis=2, dtype=np.float64)  # (S, 2, H, W, C): each half's sum over the strata
    others = sums[[s for s in range(S) if s != run]].reshape(-1, H, W, C)
    mean = others.mean(axis=0)
    lit = mean > 1e-3 * np.median(mean[mean > 0])
    truth = np.where(lit, others.var(axis=0, ddof=1) / 2 / np.maximum(mean, 1e-30), 0.0)  # the full sum's
    scale = 0.1 / np.median(truth[lit])
    truth *= scale
    full = sums[run].mean(axis=0)
    ratio_a = np.where(lit, pool((sums[run, 0] - sums[run, 1]) ** 2 / 4) / np.maximum(pool(full), 1e-30), 0) * scale
    spread = halves[run].astype(np.float64).reshape(2 * K, H, W, C).var(axis=0, ddof=1) * (2 * K) / 4
    ratio_b = np.where(lit, spread / np.maximum(full, 1e-30), 0) * scale
    rules = {
        "A, pooled, + 3x3 dilation": (ratio_a, True),
        "A, pooled": (ratio_a, False),
        "B": (ratio_b, False),
        "min(B, 4A)": (np.minimum(ratio_b, 4 * ratio_a), False),
        "oracle": (truth, False),
    }
    out = {}
    for name, (ratio, dilate) in rules.items():
        worst = ratio.max(axis=-1)
        rows = []
        for tau in LEVELS:
            for mode in ("x4", "tiers"):
                f = factors(worst, tau, mode, dilate)
                after = truth / f[..., None]
                rows.append((tau, mode, float(np.percentile(after[lit], 99.9)), float(f[f > 1].sum() / (H * W))))
        out[name] = rows
    return float(np.percentile(truth[lit], 99.9)), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--spp", type=int, default=180)
    ap.add_argument("--strata", type=int, default=7)
    ap.add_argument("--seeds", type=int, default=30)
    args = ap.parse_args()
    if args.seeds < HELD_OUT + 2:
        ap.error(f"--seeds: at least {HELD_OUT + 2}")
    w, h = (int(v) for v in args.size.split("x"))
    halves = render_halves(args.config, w, h, args.spp, args.strata, args.seeds)
    runs = [round(i * (args.seeds - 1) / (HELD_OUT - 1)) for i in range(HELD_OUT)]
    results = [study(halves, r) for r in runs]
    print(
        f"{args.config} at {args.size}, {args.strata} strata x {args.spp} spp, truth from {args.seeds - 1} seeds "
        f"(means over held-out seeds {runs}); ratios in units where the truth's median is 0.1"
    )
    print(f"the truth's p99.9 before refinement: {np.mean([r[0] for r in results]):.3f}")
    for name in results[0][1]:
        print(name)
        for i, (tau, mode, _, _) in enumerate(results[0][1][name]):
            p999 = np.mean([r[1][name][i][2] for r in results])
            added = np.mean([r[1][name][i][3] for r in results])
            print(f"  tau {tau:3.1f} {mode:5s}  p99.9 after {p999:6.3f}  samples added {added:6.3f}")


if __name__ == "__main__":
    main()
