"""The applications' figures (12, 13, 15, 16, and the moving light): each application's preview
images from the interleaved capture next to the same shots taken one after another on a
conventional sensor, with the application's metrics for both.
"""

from __future__ import annotations

import numpy as np

from ..output.io import tonemap
from ..metrics import flat_items
from . import FigureContext, FigureOutput, figure


def _flat_metrics(metrics: dict) -> dict[str, float]:
    """Numeric leaves of a metrics dict, with dotted keys."""
    return {
        k: float(v)
        for k, v in flat_items(metrics)
        if isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool)
    }


def app_comparison(ctx: FigureContext, config: str, title: str, *overrides: str) -> FigureOutput:
    import matplotlib.pyplot as plt

    inter = ctx.capture(config, *overrides)
    seq = ctx.capture(config, *overrides, "capture.sequential=true")
    pngs = list(inter.app_output.png.items())
    fig, axes = plt.subplots(2, len(pngs), figsize=(2.9 * len(pngs), 5.4), squeeze=False)
    for row, (label, res) in enumerate((("interleaved", inter), ("sequential", seq))):
        for col, (stem, (image, pct)) in enumerate(pngs):
            ax = axes[row, col]
            ax.imshow(tonemap(res.app_output.images[image], pct))
            ax.set_xticks([]), ax.set_yticks([])
            if row == 0:
                ax.set_title(stem.replace("_", " "), fontsize=9)
        axes[row, 0].set_ylabel(label, fontsize=10)
    fig.suptitle(f"{title}: interleaved (top) vs sequential (bottom)", fontsize=11)
    fig.tight_layout()
    mi, ms = _flat_metrics(inter.report["metrics"]), _flat_metrics(seq.report["metrics"])
    keys = [k for k in mi if k in ms]
    table = [["metric", "interleaved", "sequential"], *[[k, mi[k], ms[k]] for k in keys]]
    caption = (
        f"{title} ({inter.app}), {ctx.film[0]}x{ctx.film[1]}. Top: the multi-bucket capture, every image from "
        "the same span of time; bottom: the same exposures one after another on a conventional sensor. "
        "The table (JSON/CSV) lists the application's metrics for both."
    )
    return FigureOutput(
        fig,
        {
            "app": inter.app,
            "config": config,
            "film": list(ctx.film),
            "interleaved": inter.report["metrics"],
            "sequential": seq.report["metrics"],
        },
        caption,
        table,
    )


@figure("fig12_flash_no_flash", "Flash/no-flash of the swinging metronome", "Fig. 12")
def fig12(ctx: FigureContext) -> FigureOutput:
    return app_comparison(ctx, "flash_no_flash", "Flash/no-flash")


@figure("fig13_rgb_illumination", "Colour from time-interleaved R, G, B illumination of a shaken chart", "Fig. 13")
def fig13(ctx: FigureContext) -> FigureOutput:
    return app_comparison(ctx, "rgb_illumination", "RGB active illumination")


@figure("fig15_multi_flash", "Multi-flash: shadow-free image and depth edges of a moving scene", "Fig. 15")
def fig15(ctx: FigureContext) -> FigureOutput:
    return app_comparison(ctx, "multi_flash", "Multi-flash")


@figure("fig16_flash_matting", "Flash matting of a waving toy", "Fig. 16")
def fig16(ctx: FigureContext) -> FigureOutput:
    return app_comparison(ctx, "flash_matting", "Flash matting")


@figure("moving_light", "HDR under a moving lamp and flickering mains light", "beyond the paper")
def moving_light(ctx: FigureContext) -> FigureOutput:
    return app_comparison(ctx, "moving_light", "Moving light and flicker")
