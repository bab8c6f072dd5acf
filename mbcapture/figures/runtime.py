"""Beyond the paper: rendering error against run time, the planner against naive per-slot rendering
(:mod:`mbcapture.studies.converge`, the same computation as ``mbcapture converge``)."""

from __future__ import annotations

from ..output.plots import convergence_figure
from ..studies import converge
from . import FigureContext, FigureOutput, figure


@figure("error_vs_runtime", "Rendering error against run time: motion planner vs naive per-slot", "beyond the paper")
def error_vs_runtime(ctx: FigureContext) -> FigureOutput:
    # 160x128 whatever the other figures' size: the figure is about convergence rates, and the naive
    # ladder renders every slot of 64 periods (256 renders per point). Quick: 16 periods (64 slot
    # renders), 80x64 and a 32-spp reference, a preview of the same comparison.
    periods = 16 if ctx.quick else 64
    width, height = (80, 64) if ctx.quick else (160, 128)
    cfg = ctx.config(
        "metronome_hdr", (f"capture.periods={periods}", f"render.width={width}", f"render.height={height}")
    )
    if ctx.quick:
        result = converge.run_converge(cfg, converge.QUICK_MOTION_LADDER, (1,), ref_spp=32)
    else:
        result = converge.run_converge(cfg)
    fig = convergence_figure(result)
    rows = [["method", "spp", "passes", "samples_per_pixel", "seconds", "error"]]
    rows += [
        [p["method"], p["spp"], p["passes"], p["samples_per_pixel_total"], p["seconds"], p["error"]]
        for p in result["points"]
    ]
    best = max((s["speedup"] for s in result["speedups"]), default=None)
    caption = (
        "Relative RMS error of the noise-free bucket exposures against a high-budget reference, metronome "
        f"photon-efficient HDR at {periods} periods, {width}x{height}. Planner: strata from motion; naive: one render per "
        f"slot. Fitted slopes: {result['slopes']}. "
        + (f"Largest equal-error speed-up: {best:.1f}x." if best else "")
        + " Run times are wall-clock on this machine and vary with its load."
    )
    return FigureOutput(fig, result, caption, rows)
