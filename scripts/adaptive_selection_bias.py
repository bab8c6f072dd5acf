"""Does adaptive sampling's choice bias the pixels it leaves unrefined?

Every pixel keeps its first pass, and the pixels adaptive sampling chooses add a second. Were the
choice made from the first pass's own noise (its half-sample differences), as it was until
2026-11-27, the pixels it leaves would be conditioned by it: where the errors are heavy-tailed (a
rare bright path raises a pixel's value and its difference together), a pixel left unrefined is one
whose first pass drew no such path, so its value may sit low. Adaptive sampling chooses from a scout
instead, renders of its own at a sixteenth of the samples (``budget.scout_spp``), which the first
pass does not see.

This renders the first pass of a config SEEDS times (render seeds differing, everything else fixed),
makes adaptive sampling's choice (``budget.tail_pixels``) in each, from the first pass itself
(``--chooser first``) or from a scout of its own (``--chooser scout``, what a capture does), and
compares, at the pixels chosen in some seed but not all, the longest read's expected electrons of the
seeds that left the pixel unrefined with the pixel's mean over all seeds, in units of its shot noise
(one estimate per sample: pixel and channel). The mean over all seeds is the pixel's unbiased
first-pass estimate, so the difference is the choice's doing alone. The selected share follows the
tail target: smaller targets choose more pixels.

    python scripts/adaptive_selection_bias.py [CONFIG] [--size 64x48] [--spp 32] [--seeds 40] [--tail-target 200]
                                              [--chooser first|scout]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from mbcapture import load_config
from mbcapture.budget import scout_spp, tail_pixels
from mbcapture.config import scene_of
from mbcapture.exposure.integrate import integrate
from mbcapture.capture.pipeline import prepare
from mbcapture.render import Renderer
from mbcapture.sensor import electrons_per_render_second


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="64x48")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument(
        "--tail-target",
        type=float,
        default=200.0,
        help="render.noise_budget_tail for the choice (the default capture's 1 chooses most of a "
        "small film at few samples; 200 chooses about 4 %% here, as the default capture does)",
    )
    ap.add_argument(
        "--chooser",
        choices=("first", "scout"),
        default="scout",
        help="choose from the first pass's own differences, or from a scout of its own (a capture's way)",
    )
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.split("x"))
    cfg = load_config(
        args.config,
        [
            f"render.width={w}",
            f"render.height={h}",
            f"render.spp={args.spp}",
            "render.max_motion_px=4",
            "render.cache=off",
        ],
    )
    _, timeline, plan, _ = prepare(cfg)
    renderer = Renderer.from_config(scene_of(cfg), cfg)
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    reads = [r.buckets for r in timeline.reads]
    longest = list(timeline.reads[-1].buckets)
    values, chosen = [], []
    for s in range(args.seeds):
        first = integrate(renderer, plan, timeline.n_buckets, np.random.SeedSequence(1000 + s))
        chooser, scale = first, 1.0
        if args.chooser == "scout":
            scout_plan = replace(plan, spp=scout_spp(plan.spp, renderer.sample_count))
            chooser = integrate(renderer, scout_plan, timeline.n_buckets, np.random.SeedSequence(5000 + s))
            scale = float((scout_plan.spp / plan.spp).max())
        tiers = tail_pixels(
            chooser.mc_diff,
            chooser.exposure * k_e,
            k_e,
            reads,
            cfg.sensor.full_well_e,
            cfg.sensor.fd_full_well_e,
            args.tail_target,
            cfg.render.adaptive_max_factor,
            scale,
        )
        mask = np.zeros(w * h, bool)
        for pixels, _ in tiers:
            mask[pixels] = True
        values.append(first.exposure[longest].sum(axis=0) * k_e)  # (H, W, C) electrons of the longest read
        chosen.append(mask.reshape(h, w))
    v, c = np.array(values), np.array(chosen)
    mean = v.mean(axis=0)
    z = (v - mean[None]) / np.sqrt(np.maximum(mean, 1.0))[None]  # each sample's deviation, in shot-noise sigmas
    some = c.any(axis=0) & ~c.all(axis=0)  # where the choice varied between seeds
    left = (~c & some[None])[..., None] & np.ones_like(z, bool)
    taken = (c & some[None])[..., None] & np.ones_like(z, bool)
    print(
        f"{args.config} at {args.size}, {args.spp} spp per stratum, {args.seeds} render seeds, chosen from "
        f"{'a scout' if args.chooser == 'scout' else 'the first pass'}, tail target "
        f"{args.tail_target}: {c.mean():.1%} of the pixels chosen on average, {some.mean():.1%} chosen in some "
        "seeds but not all"
    )
    for name, m in (("left unrefined", left), ("chosen", taken)):
        d = z[m]
        if d.size:
            print(
                f"  {name:15s} {d.size:7d} samples: {d.mean():+.3f} shot-noise sigma from their pixel's mean "
                f"(standard error {d.std() / np.sqrt(d.size):.3f})"
            )


if __name__ == "__main__":
    main()
