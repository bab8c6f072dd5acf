"""A picture of where adaptive sampling treats a render's time as noise: the moving region (cyan) and the
moving parts' hard shadows (red, :func:`mbcapture.render.shadows.moving_shadows`) over a render of each config.

    python scripts/moving_shadows_map.py [CONFIG ...] [--size 160x128] [--out docs/images/moving_shadows.png]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from mbcapture import load_config
from mbcapture.scene.camera_motion import moving_region
from mbcapture.capture.pipeline import prepare
from mbcapture.render import Renderer, ensure_llvm
from mbcapture.render.shadows import moving_shadows

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="*", default=["multi_flash", "metronome_hdr"])
    ap.add_argument("--size", default="160x128")
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "moving_shadows.png"))
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    W, H = (int(v) for v in args.size.split("x"))
    fig, axes = plt.subplots(1, len(args.configs), figsize=(5.5 * len(args.configs), 4.6), squeeze=False)
    for ax, name in zip(axes[0], args.configs):
        cfg = load_config(
            ROOT / "configs" / f"{name}.yaml", [f"render.width={W}", f"render.height={H}", "render.cache=off"]
        )
        scene, timeline, _, _ = prepare(cfg)
        ensure_llvm()
        r = Renderer.from_config(scene, cfg)
        t0, t1 = (float(timeline.seconds(t)) for t in (timeline.start_tick, timeline.end_tick))
        start = time.perf_counter()
        shadows = moving_shadows(r, t0, t1, W, H)
        seconds = time.perf_counter() - start
        moving = moving_region(scene, t0, t1, W, H)
        img = r.render(0.5 * (t0 + t1), 16, 1).sum(axis=0).mean(axis=-1)
        ax.imshow(img / np.percentile(img, 99), cmap="gray", vmin=0, vmax=1)
        ax.contour(moving, [0.5], colors="cyan", linewidths=1)
        ax.contour(shadows & ~moving, [0.5], colors="red", linewidths=1)
        ax.set_title(f"{name} {W}x{H}: moving {int(moving.sum())} px, shadows +{int((shadows & ~moving).sum())} px")
        ax.set_axis_off()
        print(
            f"{name}: moving region {int(moving.sum())} px, its hard shadows {int((shadows & ~moving).sum())} more "
            f"({seconds:.2f} s)"
        )
    fig.tight_layout()
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
