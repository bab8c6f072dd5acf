"""The two applications the paper's section 6 proposes and did not build: structured light with an
ambient bucket, and flutter shutter without light loss. Each figure shows the reconstructions next
to their baselines with the metrics from report.json."""

from __future__ import annotations

import numpy as np

from ..output.io import tonemap
from ..reconstruct.deblur import kernel_spectrum, read_samples, spread_kernel
from ..scene.scenes import make_scene
from . import FigureContext, FigureOutput, figure

GRAY = ("scene.pattern=gray_code", "sensor.bucket_count=10")


def _show(ax, img, pct, title):
    ax.imshow(tonemap(img, pct) if pct is not None else np.clip(img, 0, 1) ** (1 / 2.2))
    ax.set_xticks([]), ax.set_yticks([])
    ax.set_title(title, fontsize=8)


def _fmt(v):
    return None if v is None else round(float(v), 4)


@figure(
    "structured_light",
    "Structured light with an ambient bucket: interleaved vs sequential, with and without the ambient image",
    "Sec. 6 (proposed)",
)
def structured_light(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    runs = {
        "phase shift, interleaved": ctx.capture("structured_light"),
        "phase shift, sequential": ctx.capture("structured_light", "capture.sequential=true"),
        "Gray code, interleaved": ctx.capture("structured_light", *GRAY),
    }
    fig, axes = plt.subplots(len(runs), 4, figsize=(11, 2.3 * len(runs)), squeeze=False)
    table = [
        [
            "capture",
            "decoding",
            "region",
            "within_tolerance",
            "depth_rmse_mm",
            "depth_median_abs_mm",
            "phase_rmse_rad",
            "coverage",
        ]
    ]
    data = {}
    for row, (label, res) in enumerate(runs.items()):
        img, m = res.app_output.images, res.report["metrics"]
        first = res.timeline.reads[0].name
        _show(axes[row, 0], res.reads_dn[0] - res.config.sensor.black_level_dn, 99.5, f"read {first}")
        _show(axes[row, 1], img["depth_preview"], None, "depth, ambient subtracted")
        _show(
            axes[row, 2], img.get("depth_preview_ambient_ignored", img["depth_preview"]), None, "depth, ambient ignored"
        )
        _show(axes[row, 3], img["error_preview"], None, "|error| (white: 4x tol.; blue: lost)")
        axes[row, 0].set_ylabel(label, fontsize=9)
        data[label] = m
        for mode, regions in m["depth"].items():
            for region, s in regions.items():
                table.append(
                    [
                        label,
                        mode,
                        region,
                        _fmt(s.get("within_tolerance")),
                        _fmt(s.get("depth_rmse_mm")),
                        _fmt(s.get("depth_median_abs_mm")),
                        _fmt(s.get("phase_rmse_rad")),
                        _fmt(s.get("coverage")),
                    ]
                )
    tol = runs["phase shift, interleaved"].report["metrics"]["truth"]["tolerance_mm"]
    fig.suptitle(
        "Structured light, 3 phase-shifted sinusoids (or white + 8 Gray-code bits) + an ambient bucket, "
        "flickering lamp, sliding cube",
        fontsize=10,
    )
    fig.tight_layout()
    caption = (
        f"Depth by triangulation at {ctx.film[0]}x{ctx.film[1]}, scored against the depth AOV at the capture's "
        f"mid-time over the pixels the projector lights (within {tol:g} mm, RMSE, phase RMSE; overall and in the "
        "moving region). Interleaved: all patterns and the ambient image in the same 20 ms, so the 100 Hz "
        "flicker and the sliding cube are the same in each; sequential: four frames 33 ms apart. Phase "
        "shifting cancels an ambient level common to its patterns, so subtracting the ambient image changes "
        "nothing there; Gray-code thresholds fail wherever the lamp outshines the projector unless the "
        "ambient image is subtracted."
    )
    return FigureOutput(fig, {"film": list(ctx.film), "captures": data}, caption, table)


def _spectrum(samples, n=512):
    """|H(w)| of reads' (shifts, seconds), root-sum-square over reads (joint least squares sees sum |H_r|^2)."""

    return np.sqrt(sum(np.abs(kernel_spectrum(s, w, n)) ** 2 for s, w in samples))


@figure(
    "flutter_shutter",
    "Flutter shutter without light loss: box vs flutter vs two-bucket flutter at equal exposure",
    "Sec. 6 (proposed)",
)
def flutter_shutter(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    res = ctx.capture("flutter_shutter")
    seq = ctx.capture("flutter_shutter", "capture.sequential=true")
    img, m = res.app_output.images, res.report["metrics"]
    c = m["comparison"]
    pct = res.config.output.png_percentile
    panels = [
        ("blurred_box", "box exposure (blurred)"),
        ("blurred_open", "open bucket (flutter)"),
        ("deblurred_box", f"box deblurred\n{c['box']['psnr_db']:.1f} dB"),
        ("deblurred_flutter", f"flutter deblurred\n{c['flutter']['psnr_db']:.1f} dB"),
        ("deblurred", f"two-bucket deblurred\n{c['two_bucket_flutter']['psnr_db']:.1f} dB"),
        ("truth", "truth (sharp, mid-time)"),
    ]
    fig = plt.figure(figsize=(13, 5.2))
    grid = fig.add_gridspec(2, len(panels), height_ratios=[1.0, 0.8])
    for i, (name, title) in enumerate(panels):
        _show(fig.add_subplot(grid[0, i]), img[name], pct, title)
    tl = res.timeline
    W, H = res.config.render.width, res.config.render.height
    t_mid = float((tl.start_tick + tl.end_tick) / 2 * tl.tick_s)
    scene = make_scene(res.config.scene.name, res.config.scene.params())
    samples = [read_samples(tl, r, scene, t_mid, W, H) for r in tl.reads]
    box_samples = (np.concatenate([s for s, _ in samples]), np.concatenate([w for _, w in samples]))
    kernels = [spread_kernel(*sm) for sm in samples]
    box = spread_kernel(*box_samples)
    ax = fig.add_subplot(grid[1, : len(panels) // 2])
    for (first, h), label in ((box, "box"), (kernels[0], "open (bucket 1)"), (kernels[1], "closed (bucket 2)")):
        ax.step(first + np.arange(len(h)), h * 1e3, where="mid", label=label)
    ax.set_xlabel("displacement (px)"), ax.set_ylabel("ms per px"), ax.legend(fontsize=7)
    ax.set_title("exposure kernels", fontsize=9)
    ax = fig.add_subplot(grid[1, len(panels) // 2 :])
    freq = np.fft.rfftfreq(512)
    for ks, label in (([box_samples], "box"), ([samples[0]], "flutter (open only)"), (samples, "two-bucket (joint)")):
        ax.semilogy(freq, _spectrum(ks) * 1e3, label=label)
    ax.set_xlabel("cycles per px"), ax.set_ylabel("|H| (ms)"), ax.legend(fontsize=7)
    ax.set_title("kernel spectra: zeros make the box blur non-invertible", fontsize=9)
    fig.tight_layout()
    table = [
        [
            "shutter",
            "light_fraction",
            "psnr_db",
            "psnr_db_object",
            "ssim",
            "noise_amplification",
            "white_noise_gain",
            "noise_rms",
        ]
    ]
    for k, v in c.items():
        table.append(
            [
                k,
                _fmt(v["light_fraction"]),
                _fmt(v["psnr_db"]),
                _fmt(v.get("psnr_db_object")),
                _fmt(v["ssim"]),
                _fmt(v.get("noise_amplification")),
                _fmt(v.get("white_noise_gain")),
                _fmt(v.get("noise_rms")),
            ]
        )
    s = seq.report["metrics"]["deblurred"]["joint"]
    table.append(
        [
            "sequential (two box frames, joint)",
            1.0,
            _fmt(s["psnr_db"]),
            _fmt(s.get("psnr_db_object")),
            _fmt(s["ssim"]),
            _fmt(s.get("noise_amplification")),
            _fmt(s.get("white_noise_gain")),
            _fmt(s.get("noise_rms")),
        ]
    )
    caption = (
        f"A card crossing the view, {ctx.film[0]}x{ctx.film[1]}, {m['chops']} chops of Raskar et al.'s code over "
        f"{res.config.capture.unit_exposure_s * 1e3:g} ms, deblurred by least squares with the known motion. "
        "Box: one bucket open all the time (its kernel's spectral zeros amplify noise); flutter: the open chops "
        "only, the closed ones drained (half the light); two-bucket: open chops in bucket 1, closed in bucket 2, "
        "both deblurred jointly (all the light, and the code's spectrum); least squares per frequency "
        f"(app.deblur {m['deblur']}). Noise amplification is relative to "
        "the noise of the box read over its exposure. The last table row is the conventional sensor taking the "
        "two buckets' exposures as two frames one after another."
    )
    return FigureOutput(
        fig, {"film": list(ctx.film), "interleaved": m, "sequential": seq.report["metrics"]}, caption, table
    )
