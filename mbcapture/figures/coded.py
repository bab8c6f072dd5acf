"""Figures of per-pixel gates: a coded two-bucket capture's code, its reads and the per-light images
demultiplexed from them, beside the 5-bucket global-gate capture of the same moving scene."""

from __future__ import annotations

import numpy as np

from ..metrics import luminance
from ..output.plots import draw_gate_code
from ..capture.report import subframe_names
from . import FigureContext, FigureOutput, figure


@figure(
    "coded_gates",
    "One-shot multi-flash on a coded two-bucket sensor: the per-pixel code, the two reads, "
    "and the per-light images demultiplexed from them",
    "beyond the paper",
)
def coded_gates(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    coded = ctx.capture("coded_multi_flash")
    glob = ctx.capture("multi_flash")
    tl, code = coded.timeline, coded.timeline.code
    names = subframe_names(tl)
    H, W = coded.reads_dn.shape[1:3]
    crop = (
        slice(int(0.30 * H), int(0.30 * H) + max(H // 4, 24)),
        slice(int(0.40 * W), int(0.40 * W) + max(W // 4, 30)),
    )

    fig = plt.figure(figsize=(15, 7.2))
    grid = fig.add_gridspec(2, max(code.n_subframes, 5))
    for s in range(code.n_subframes):  # one period of the per-pixel patterns, an 8 x 8 corner
        draw_gate_code(
            fig.add_subplot(grid[0, s]), code, s, 8, f"sub-frame {s + 1}: {names[s]}\n(red: bucket 1, blue: bucket 2)"
        )

    def show(ax, img, title, white):
        ax.imshow(np.clip(img[crop] / white, 0, 1) ** (1 / 2.2), interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])

    reads = coded.reads_expected_e
    white_reads = float(np.percentile(luminance(reads[:, crop[0], crop[1]]), 99))
    truth = glob.images["shadow_free_truth"]
    white = float(np.percentile(luminance(truth[crop]), 99))
    row = [
        (reads[0], "read B1 (electrons): a mix per pixel", white_reads),
        (reads[1], "read B2", white_reads),
        (coded.images["flash_top"], "top LED, demultiplexed (2 buckets)", white),
        (glob.images["flash_top"], "top LED, its own bucket (5 buckets)", white),
        (truth, "shadow-free truth (noise-free)", white),
    ]
    for i, (img, title, w) in enumerate(row):
        show(fig.add_subplot(grid[1, i]), img, title, w)
    fig.tight_layout()
    mc, mg = coded.report["metrics"], glob.report["metrics"]
    rows = [
        ["capture", "per_light_nrmse", "depth_edge_f1", "normals_median_deg"],
        [
            "2 buckets, coded",
            mc["per_light"]["mean_nrmse"],
            mc["depth_edges"]["all"]["f1"],
            mc["normals"].get("median_deg"),
        ],
        [
            "5 buckets, global",
            mg["per_light"]["mean_nrmse"],
            mg["depth_edges"]["all"]["f1"],
            mg["normals"].get("median_deg"),
        ],
    ]
    caption = (
        f"The coded two-bucket capture (configs/coded_multi_flash.yaml, code '{code.family}', tile "
        f"{code.tile_shape[0]}x{code.tile_shape[1]}) at {W}x{H}: top, one period of the per-pixel patterns; "
        "bottom, a crop of its two reads, whose content changes from pixel to pixel with the code, the top LED's "
        "image demultiplexed from them, the same LED's image from the 5-bucket global-gate capture "
        "(configs/multi_flash.yaml), and the truth. Demultiplexing keeps every photon but fits over the code's "
        "tile: the edge-aware fit (app.demux_method: guided) keeps edges of the total light, and what is left "
        "blurs over the tile."
    )
    return FigureOutput(fig, {"code": code.family, "tile": list(code.tile_shape), "rows": rows}, caption, rows)
