"""Where a capture's rendering noise comes from: path length, emitter group and sampler.

Renders one stratum of a config (the plan's first render time, its groups) with SEEDS independent
seeds at --spp samples per pixel, and measures each pixel's Monte Carlo variance across the seeds.
The noise budget compares that variance with the shot noise, which grows with the signal, so
every figure here is per-sample variance over the full render's mean (the budget's ratio up to
the electrons per radiance unit, which is the same for every row), over the lit pixels:

* by path length: ``render.max_depth`` 2 (emitters seen directly and direct light) up to the
  config's own, so the step from one row to the next is what one more bounce adds;
* by emitter group, at the config's depth: each group's share of the mean and of the variance;
* by sampler, at the config's depth: multijitter, ldsampler and independent, each at the samples
  the sampler really takes for --spp (ldsampler rounds up to a power of 4);
* with ``--strata K``: the mean of K renders of --spp each (a static pixel's sum over K strata, each
  rendered with a pattern of its own) against one render of K x --spp (one pattern across the
  strata): how much a pattern shared by the strata could lower the variance, at most (equal weights).

    python scripts/render_noise_sources.py [CONFIG] [--size 160x128] [--spp 16] [--seeds 12] [--strata K] [--set KEY=VALUE ...]

Each row prints the median, 95th and 99.9th percentile and the mean over the lit pixels of
(variance x samples) / mean, relative to the median of the config's own render (1.00 is what the
budget pays for now), and the median pixel's share of the light.
"""

from __future__ import annotations

import argparse

import numpy as np

from mbcapture import load_config
from mbcapture.capture.pipeline import prepare
from mbcapture.render.renderer import Renderer


def per_sample_ratio(images: np.ndarray, spp: int, mean: np.ndarray) -> np.ndarray:
    """(H, W) per-sample variance over the reference mean: ``images`` (S, G, H, W, C) renders of S
    seeds, summed over groups and channels."""
    total = images.sum(axis=(1, -1), dtype=np.float64)
    return total.var(axis=0, ddof=1) * spp / mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="160x128")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument(
        "--strata", type=int, default=0, help="K: K patterns of --spp against one of K x --spp (0: not measured)"
    )
    ap.add_argument("--set", action="append", default=[], dest="sets")
    args = ap.parse_args()
    w, h = args.size.split("x")
    cfg = load_config(args.config, [f"render.width={w}", f"render.height={h}", "render.cache=off", *args.sets])
    scene, _, plan, _ = prepare(cfg)
    t, groups = float(plan.times_s[0]), plan.groups
    depth = cfg.render.max_depth

    def renders(**overrides) -> tuple[np.ndarray, int]:
        r = Renderer.from_config(scene, cfg, **overrides)
        n = r.sample_count(args.spp)
        return np.stack([r.render(t, n, 1000 + s, groups) for s in range(args.seeds)]), n

    own, n_own = renders()
    mean = own.sum(axis=(1, -1), dtype=np.float64).mean(axis=0)
    lit = mean > 1e-3 * np.median(mean[mean > 0])
    scale = np.median(per_sample_ratio(own, n_own, mean)[lit])

    def row(label: str, ratio: np.ndarray, share: float | None = None) -> None:
        q = np.percentile(ratio[lit], [50, 95, 99.9]) / scale
        s = "" if share is None else f"{share:10.3f}"
        print(f"{label:34s} {q[0]:9.3g} {q[1]:9.3g} {q[2]:9.3g} {ratio[lit].mean() / scale:9.3g} {s}")

    print(
        f"{args.config} at {args.size}, stratum at t = {t:.6f} s, groups {list(groups)}, {args.spp} spp, "
        f"{args.seeds} seeds, {int(lit.sum())} lit pixels; (variance x spp) / mean, relative to the median of "
        f"the config's own render (max_depth {depth}, sampler {cfg.render.sampler})"
    )
    print(f"{'':34s} {'median':>9s} {'p95':>9s} {'p99.9':>9s} {'mean':>9s} {'mean share':>10s}")
    for d in range(2, depth):
        imgs, n = renders(max_depth=d)
        share = float(np.median(imgs.sum(axis=(1, -1), dtype=np.float64).mean(axis=0)[lit] / mean[lit]))
        row(f"max_depth {d}", per_sample_ratio(imgs, n, mean), share)
    row(f"max_depth {depth} (the config's)", per_sample_ratio(own, n_own, mean), 1.0)
    for g, name in enumerate(groups):
        part = own[:, g : g + 1]
        share = float(np.median(part.sum(axis=(1, -1), dtype=np.float64).mean(axis=0)[lit] / mean[lit]))
        row(f"group {name}", per_sample_ratio(part, n_own, mean), share)
    for sampler in ("multijitter", "ldsampler", "independent"):
        imgs, n = (own, n_own) if sampler == cfg.render.sampler else renders(sampler=sampler)
        row(f"sampler {sampler} ({n} spp)", per_sample_ratio(imgs, n, mean))
    if args.strata > 1:
        k = args.strata
        r = Renderer.from_config(scene, cfg)
        many = np.stack(
            [
                np.mean([r.render(t, n_own, 5000 + k * s + i, groups) for i in range(k)], axis=0)
                for s in range(args.seeds)
            ]
        )
        n_one = r.sample_count(k * n_own)
        one = np.stack([r.render(t, n_one, 9000 + s, groups) for s in range(args.seeds)])
        row(f"{k} patterns of {n_own} spp, their mean", per_sample_ratio(many, k * n_own, mean))
        row(f"one pattern of {n_one} spp", per_sample_ratio(one, n_one, mean))


if __name__ == "__main__":
    main()
