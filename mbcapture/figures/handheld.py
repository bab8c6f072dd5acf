"""Figures of hand-held capture and video (beyond the paper's figures; the paper's section 5 and 6):
the camera-shake model and what it does to the render plan, the back-to-back burst against a
conventional burst and a long exposure, and multi-bucket HDR video against alternating exposures.
"""

from __future__ import annotations

import numpy as np

from ..scene import camera_motion as cm
from ..capture.pipeline import prepare
from ..config import scene_of
from ..output.io import tonemap
from ..capture.video import needle_track
from . import FigureContext, FigureOutput, figure


@figure(
    "camera_shake",
    "Hand shake: the trajectory model and the strata it costs",
    "beyond the paper (Fig. 13's shake)",
    renders=False,
)
def camera_shake(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt
    from scipy.signal import welch

    cfg = ctx.config("metronome_shake")
    spec = cfg.camera.shake
    traj = cm.ShakeTrajectory.from_spec(spec)
    t = np.arange(0.0, 2.0, 1e-3)
    o = traj.offsets(t)
    long_t = np.arange(0.0, 200.0, 0.02)
    f, p = welch(np.degrees(traj.offsets(long_t, axes=(0,))[:, 0]), fs=50.0, nperseg=2048)
    grid = np.linspace(cm.SHAKE_F_MIN_HZ, 25.0, 2000)
    model = cm.shake_psd(grid, spec) * spec.rotation_deg**2
    rows = [["rotation_deg (RMS)", "render passes", "image motion (px)"]]
    burst_cfg = ctx.config("burst")
    for rot in (0.0, 0.05, 0.1, 0.2, 0.4):  # the burst's static scene: every stratum is the shake's
        shake = "camera.shake=null" if rot == 0 else f"camera.shake.rotation_deg={rot}"
        _, _, plan, _ = prepare(ctx.config("burst", (shake,)))
        rows.append([rot, plan.passes, round(plan.motion_px_total, 3)])

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for a, name in zip(range(3), ("pitch", "yaw", "roll")):
        axes[0].plot(t, np.degrees(o[:, a]), lw=0.9, label=name)
    ax2 = axes[0].twinx()
    ax2.plot(t, o[:, 3] * 1e3, lw=0.6, color="0.5", label="x (mm)")
    axes[0].set_xlabel("time (s)"), axes[0].set_ylabel("rotation (deg)"), ax2.set_ylabel("translation x (mm)")
    axes[0].legend(fontsize=8, loc="upper left")
    axes[0].set_title("one hand (camera.shake.seed)", fontsize=10)
    axes[1].loglog(f[1:], p[1:], lw=0.8, label="pitch, Welch, 200 s")
    axes[1].loglog(grid, model, "k--", lw=1, label="model S(f) x RMS$^2$")
    axes[1].set_xlim(cm.SHAKE_F_MIN_HZ, 25.0)
    axes[1].set_ylim(model.min() / 30, model.max() * 10)
    axes[1].set_xlabel("frequency (Hz)"), axes[1].set_ylabel("deg$^2$/Hz"), axes[1].legend(fontsize=8)
    axes[1].set_title(f"drift + tremor at {spec.tremor_hz:g} Hz", fontsize=10)
    rots = [r[0] for r in rows[1:]]
    axes[2].plot(rots, [r[1] for r in rows[1:]], "o-")
    axes[2].set_xlabel("camera.shake.rotation_deg (RMS)"), axes[2].set_ylabel("render passes (strata)")
    axes[2].set_title(
        f"burst (a still scene), {ctx.film[0]}x{ctx.film[1]}, "
        f"{burst_cfg.capture.unit_exposure_s * burst_cfg.sensor.bucket_count * 1e3:g} ms",
        fontsize=10,
    )
    fig.tight_layout()
    caption = (
        "Left: the seeded hand-shake trajectory of configs/metronome_shake.yaml (pitch, yaw, roll and one "
        "translation) over 2 s. Middle: its spectrum against the model (slow drift plus the physiological "
        "tremor peak). Right: the planner's strata for configs/burst.yaml (a still scene) as the shake grows: "
        "the projected motion of the whole frame bounds them, as a moving part's does."
    )
    return FigureOutput(fig, {"shake": spec.model_dump(), "film": list(ctx.film), "strata": rows}, caption, rows)


@figure(
    "burst",
    "Back-to-back burst vs conventional burst vs one long exposure, hand-held in low light",
    "beyond the paper (section 5)",
)
def burst(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    res = ctx.capture("burst")
    img, m = res.images, res.report["metrics"]
    panels = [
        ("truth", "truth (still camera)"),
        ("reference_frame", f"one frame ({m['reference_frame']})"),
        ("unaligned_average", "frames averaged, not aligned"),
        ("average", f"back-to-back, aligned ({m['method']})"),
        ("other_burst", "conventional burst, aligned"),
        ("long_exposure", "one long exposure"),
    ]
    panels = [(k, t) for k, t in panels if k in img]
    white = float(np.percentile(img["truth"] @ np.array([0.2126, 0.7152, 0.0722]), 99.5)) or 1.0
    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.7))
    for ax, (k, title) in zip(np.atleast_1d(axes), panels):
        ax.imshow(tonemap(img[k] / white, None))
        ax.set_title(title, fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    keys = ["capture_span_s", "psnr_db", "rel_mse", "residual_blur_px", "motion_blur_px", "registration_error_px_mean"]
    comp = m.get("comparison", {})
    table = [["metric", *comp], *[[k, *[comp[c].get(k) for c in comp]] for k in keys]]
    caption = (
        f"configs/burst.yaml at {ctx.film[0]}x{ctx.film[1]}: {m['frames']} frames of "
        f"{m['frame_exposure_s'] * 1e3:g} ms, hand-held ({m['camera_motion']}). All at equal total exposure "
        f"{m['total_exposure_s'] * 1e3:g} ms, one white level. The table: PSNR against the still-camera truth, "
        "residual (Gaussian) blur, the frame's own motion during each exposure and the registration error."
    )
    return FigureOutput(fig, {"film": list(ctx.film), "metrics": m}, caption, table)


@figure(
    "hdr_video",
    "Multi-bucket HDR video vs alternating exposures, and temporal aliasing at 3 vs 30 frames/s",
    "beyond the paper (section 6)",
)
def hdr_video(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    res = ctx.capture("hdr_video", "capture.frames=8" if ctx.quick else "capture.frames=6")
    v, rep = res.video, res.report["video"]
    n = len(v.frames)
    picks = sorted({0, n // 2, n - 1})
    rows = [("truth", v.truth), ("multi-bucket", v.radiance)]
    if v.alternating_radiance is not None:
        rows.append(("alternating", v.alternating_radiance))
    fig = plt.figure(figsize=(12, 7))
    gs = fig.add_gridspec(len(rows) + 1, len(picks) + 1, height_ratios=[1] * len(rows) + [1.3])
    for r, (label, frames) in enumerate(rows):
        for c, i in enumerate(picks):
            ax = fig.add_subplot(gs[r, c])
            ax.imshow(tonemap(frames[i] / v.white, None))
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(f"frame {i}", fontsize=9)
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
    ax = fig.add_subplot(gs[: len(rows), len(picks)])
    for key, label in (("multi_bucket", "multi-bucket"), ("alternating_exposure", "alternating exposures")):
        if key in rep:
            vals = [np.nan if x is None else x for x in rep[key]["rel_mse_moving_per_frame"]]
            ax.semilogy(range(n), vals, "o-", label=label)
    ax.set_xlabel("frame"), ax.set_ylabel("relMSE, moving region"), ax.legend(fontsize=8)
    ax.set_title("ghosting per frame", fontsize=9)
    ax = fig.add_subplot(gs[len(rows), :])
    al = rep["aliasing"]
    if "rates" in al:
        cfg = res.config
        sc = scene_of(cfg)
        t0 = max(res.report["reads"], key=lambda r: r["exposure_s"])["centroid_s"]  # the longest read's centroid
        dense = t0 + np.arange(0.0, 3.0, 2e-3)
        W, H = cfg.render.width, cfg.render.height
        ax.plot(
            dense,
            needle_track(sc, dense, W, H),
            color="0.6",
            lw=1,
            label=f"needle, true ({al['true_frequency_hz']:.3g} Hz)",
        )
        for r in al["rates"].values():
            ts = t0 + np.arange(int(3.0 * r["frame_rate_hz"]) + 1) / r["frame_rate_hz"]
            ax.plot(
                ts,
                needle_track(sc, ts, W, H),
                "o-" if r["frame_rate_hz"] < 10 else ".",
                ms=4,
                label=f"{r['frame_rate_hz']:g} frames/s: appears at {r['apparent_frequency_hz']:.3g} Hz",
            )
        ax.set_xlabel("scene time (s)"), ax.set_ylabel("needle x (px)"), ax.legend(fontsize=8, loc="upper right")
        ax.set_title("temporal aliasing of the needle", fontsize=9)
    fig.tight_layout()
    table = [["video", "ghosting relMSE moving (mean)", "ghosting (max)", "temporal consistency"]]
    for key in ("multi_bucket", "alternating_exposure"):
        if key in rep:
            s = rep[key]
            table.append(
                [key, s["ghosting_rel_mse_moving_mean"], s["ghosting_rel_mse_moving_max"], s["temporal_consistency"]]
            )
    caption = (
        f"configs/hdr_video.yaml at {ctx.film[0]}x{ctx.film[1]}, {n} frames at {rep['frame_rate_hz']:g} frames/s. "
        "Top: frames of the truth, the multi-bucket HDR video and the alternating short/long-exposure video "
        "(Kang et al. 2003: neighbours warped by optical flow), one white level; right: ghosting per frame. "
        "Bottom: the needle's horizontal position, continuous and sampled at the compared frame rates."
    )
    return FigureOutput(
        fig, {"film": list(ctx.film), "video": {k: v2 for k, v2 in rep.items() if k != "per_frame"}}, caption, table
    )
