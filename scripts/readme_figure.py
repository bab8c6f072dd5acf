"""The README's picture (docs/images/overview.png): the default capture's gate schedule on a multi-bucket
sensor and on a conventional one, and the HDR image each gives of the swinging metronome.

    python scripts/readme_figure.py [--size 320x256] [--out docs/images/overview.png]

Two captures of configs/metronome_hdr.yaml (the second with capture.sequential=true), each with the samples
its noise budget chooses; about two minutes on 2 cores at 320x256.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mbcapture import load_config
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.output.plots import draw_timeline, time_unit
from mbcapture.progress import StageStatus

ROOT = Path(__file__).resolve().parents[1]


def tone_map(radiance: np.ndarray, white: float) -> np.ndarray:
    """Linear radiance over ``white``, clipped, with the sRGB curve's 1/2.2 power: an image to look at."""
    return np.clip(radiance / white, 0.0, 1.0) ** (1 / 2.2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "overview.png")
    args = ap.parse_args()
    w, h = args.size.split("x")
    runs = {}
    for label, extra in (
        ("multi-bucket, photon-efficient (reads T, 2T, 4T, 8T in 8T)", []),
        ("conventional sensor, the same exposures one after another (15T)", ["capture.sequential=true"]),
    ):
        cfg = load_config(ROOT / "configs" / "metronome_hdr.yaml", [f"render.width={w}", f"render.height={h}", *extra])
        runs[label] = capture_in_memory(cfg, StageStatus(False))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(10, 6.2))
    grid = fig.add_gridspec(2, 2, height_ratios=[1, 3.2], hspace=0.25, wspace=0.05)
    ax = fig.add_subplot(grid[0, :])
    longest = max(float((r.timeline.end_tick - r.timeline.start_tick) * r.timeline.tick_s) for r in runs.values())
    unit, name = time_unit(longest)
    for i, (label, run) in enumerate(runs.items()):
        draw_timeline(ax, run.timeline, 1 - i, unit, "")
        ax.text(0, 1 - i + 0.45, label, fontsize=8, va="bottom")
    ax.set_xlim(0, longest / unit * 1.01)
    ax.set_ylim(-0.5, 1.9)
    ax.set_yticks([])
    ax.set_xlabel(f"time ({name}); each colour is a bucket (a frame on the conventional sensor)", fontsize=8)
    white = float(np.percentile(next(iter(runs.values())).images["truth"].mean(axis=-1), 99))
    for i, (label, run) in enumerate(runs.items()):
        a = fig.add_subplot(grid[1, i])
        a.imshow(tone_map(run.images["radiance"], white))
        m = run.report["metrics"]
        a.set_title(f"HDR relMSE {m['hdr_rel_mse']:.3g}, moving region {m['hdr_rel_mse_moving']:.3g}", fontsize=8)
        a.set_xticks([]), a.set_yticks([])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110, bbox_inches="tight")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
