"""Figures of the camera beyond the paper: fixed-pattern noise split into pixel, row and column
components (EMVA 1288 Release 4.0) with temporal row noise, the lens (natural vignetting,
diffraction MTF, depth of field through focus) and a Bayer colour filter array and its demosaicing."""

from __future__ import annotations

import numpy as np

from ..config import load_config, scene_of
from ..metrics import row_column_pixel_variances
from ..scene.optics import (
    blur_radius_px,
    diffraction_otf,
    focal_length_m,
    focus_distance_m,
    natural_vignetting,
    thin_lens_aperture_m,
)
from ..render import Renderer
from ..sensor import SensorConfig, dn_to_electrons, simulate_reads
from ..sensor.cfa import DEMOSAIC_METHODS, channel_map, demosaic, to_mosaic
from . import CONFIG_DIR, FigureContext, FigureOutput, figure


@figure(
    "sensor_row_column_noise",
    "A dark frame with row and column fixed pattern and row noise",
    "beyond the paper",
    renders=False,
)
def sensor_row_column_noise(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    H, W = (96, 128) if ctx.quick else (384, 512)
    frames = 8 if ctx.quick else 32
    cfg = SensorConfig(
        dsnu_e=1.0,
        dsnu_row_e=0.5,
        dsnu_col_e=1.5,
        read_noise_e=2.0,
        read_noise_row_e=0.8,
        dark_current_e_per_s=0.0,
        fpn_seed=ctx.seed,
    )
    out = simulate_reads(
        np.zeros((frames, H, W, 1)),
        [(k,) for k in range(frames)],
        cfg,
        np.random.SeedSequence(ctx.seed).spawn(1)[0],
        shared_photodiode=False,
    )
    dark_e = dn_to_electrons(out.reads_dn[..., 0], cfg)  # (frames, H, W)
    mean = dark_e.mean(axis=0)
    rows, cols, pixel = row_column_pixel_variances(mean)
    q = (1.0 / cfg.gain_dn_per_e) ** 2 / 12.0
    want = {
        "row": cfg.dsnu_row_e**2 + cfg.read_noise_row_e**2 / frames,
        "column": cfg.dsnu_col_e**2,
        "pixel": cfg.dsnu_e**2 + (cfg.read_noise_e**2 + q) / frames,
    }
    got = {"row": rows, "column": cols, "pixel": pixel}

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), gridspec_kw={"width_ratios": [1.4, 1, 1]})
    lim = np.percentile(np.abs(dark_e[0]), 99)
    im = axes[0].imshow(dark_e[0], cmap="gray", vmin=-lim, vmax=lim)
    axes[0].set_title("one dark frame (e-): column stripes, row banding", fontsize=9)
    axes[0].set_xticks([]), axes[0].set_yticks([])
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    axes[1].plot(mean.mean(axis=0), lw=0.8, label="column means")
    axes[1].plot(mean.mean(axis=1), lw=0.8, label="row means")
    axes[1].set_xlabel("column / row", fontsize=8)
    axes[1].set_ylabel(f"mean of {frames} frames (e-)", fontsize=8)
    axes[1].legend(fontsize=7)
    names = list(want)
    x = np.arange(len(names))
    axes[2].bar(x - 0.2, [want[n] for n in names], 0.4, label="configured (+ temporal / frames)")
    axes[2].bar(x + 0.2, [got[n] for n in names], 0.4, label="recovered (EMVA 1288 split)")
    axes[2].set_xticks(x, names)
    axes[2].set_ylabel("variance (e-^2)", fontsize=8)
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    caption = (
        f"{frames} dark frames of {W}x{H} pixels with DSNU {cfg.dsnu_e:g} e- per pixel, {cfg.dsnu_row_e:g} e- per "
        f"row and {cfg.dsnu_col_e:g} e- per column, read noise {cfg.read_noise_e:g} e- and temporal row noise "
        f"{cfg.read_noise_row_e:g} e-. The row/column/pixel split of the frames' mean (EMVA 1288 R4.0) recovers "
        "the configured variances; the temporal parts enter divided by the number of frames."
    )
    table = [["component", "configured_e2", "recovered_e2"], *[[n, want[n], got[n]] for n in names]]
    return FigureOutput(
        fig, {"frames": frames, "width": W, "height": H, "configured_e2": want, "recovered_e2": got}, caption, table
    )


@figure(
    "camera_vignetting",
    "Natural vignetting of the metronome's camera (camera.vignetting: cos4)",
    "beyond the paper",
    renders=False,
)
def camera_vignetting(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    W, H = ctx.film
    camera = scene_of(load_config(CONFIG_DIR / "metronome_hdr.yaml")).camera
    v = natural_vignetting(camera, W, H)
    t = np.tan(np.radians(camera.fov_deg) / 2)
    x = 2.0 * (np.arange(W) + 0.5) / W - 1.0  # the middle row: field angle from the horizontal position only
    theta = np.degrees(np.arctan(np.abs(x) * t))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    im = axes[0].imshow(v, cmap="gray", vmin=0, vmax=1)
    axes[0].set_title(f"relative illumination, {W}x{H}, {camera.fov_deg:g} degree view", fontsize=9)
    axes[0].set_xticks([]), axes[0].set_yticks([])
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    axes[1].plot(theta[W // 2 :], v[H // 2, W // 2 :], lw=2, label="middle row of the map")
    axes[1].plot(theta[W // 2 :], np.cos(np.radians(theta[W // 2 :])) ** 4, "k:", label="cos^4(field angle)")
    axes[1].set_xlabel("field angle (degrees)", fontsize=8)
    axes[1].set_ylabel("relative illumination", fontsize=8)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    caption = (
        f"cos^4 natural vignetting of a thin lens over the metronome's {camera.fov_deg:g} degree horizontal view: "
        f"{v[H // 2, 0]:.2f} at the left and right edges, {v.min():.2f} in the corners. Every render of a capture "
        "with camera.vignetting: cos4 is multiplied by this map, truths included."
    )
    return FigureOutput(
        fig,
        {"fov_deg": camera.fov_deg, "edge": float(v[H // 2, 0]), "corner": float(v.min())},
        caption,
        [["field_angle_deg", "relative_illumination"], *[[a, b] for a, b in zip(theta[W // 2 :], v[H // 2, W // 2 :])]],
    )


@figure(
    "camera_mtf",
    "MTF of the default pixel with diffraction at f/2.8 and f/8 (camera.diffraction)",
    "beyond the paper",
    renders=False,
)
def camera_mtf(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    sensor = SensorConfig()
    pitch_mm = sensor.pixel_pitch_um * 1e-3
    f = np.linspace(0.0, 1.0 / pitch_mm, 400)  # to twice Nyquist, cycles per mm
    box = np.abs(np.sinc(f * pitch_mm))  # the pixel aperture (the render's box filter)
    fig, ax = plt.subplots(figsize=(7, 3.6))
    rows = [["f_number", "channel", "mtf_at_nyquist"]]
    colours = ["#d62728", "#2ca02c", "#1f77b4"]
    for n, style in ((sensor.f_number, "-"), (8.0, "--")):
        for c, lam in enumerate(sensor.wavelength_nm):
            mtf = box * diffraction_otf(f, lam, n)
            ax.plot(f, mtf, style, color=colours[c], lw=1, label=f"f/{n:g}, {lam:g} nm")
            rows.append([n, f"{lam:g} nm", float(np.interp(0.5 / pitch_mm, f, mtf))])
    ax.plot(f, box, "k:", lw=1, label="pixel aperture alone")
    ax.axvline(0.5 / pitch_mm, color="#777777", lw=0.8)
    ax.set_xlabel("spatial frequency (cycles per mm); grey: Nyquist", fontsize=8)
    ax.set_ylabel("MTF", fontsize=8)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    caption = (
        f"System MTF of a {sensor.pixel_pitch_um:g} um pixel (the render's box filter, sinc) times the diffraction "
        "OTF of a circular aperture per channel, at the default f-number and at f/8. camera.diffraction applies the "
        "OTF to every render."
    )
    return FigureOutput(fig, {"pixel_pitch_um": sensor.pixel_pitch_um, "rows": rows}, caption, rows)


@figure(
    "camera_depth_of_field",
    "Through focus: the metronome through a thin lens focused near, on the needle and far (camera.lens: thin)",
    "beyond the paper",
)
def camera_depth_of_field(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    # a large pixel (20 um: a 12.8 mm wide sensor at 640 px) and f/1.4 make the depth of field shallow
    # enough to see; the shipped configs' 5.6 um at f/2.8 blur the scene by under a pixel
    lens = ("camera.lens=thin", "sensor.pixel_pitch_um=20", "sensor.f_number=1.4")
    cfg = ctx.config("metronome_hdr", lens)
    scene = scene_of(cfg)
    W, H = ctx.film
    spp = 16 if ctx.quick else 64
    target = focus_distance_m(scene.camera)
    aperture = thin_lens_aperture_m(scene.camera, W, cfg.sensor.pixel_pitch_um, cfg.sensor.f_number)
    focus = {"near (0.7 m)": 0.7, f"on the needle ({target:.2f} m)": target, "far (1.6 m)": 1.6}
    images = []
    for s_f in focus.values():
        focused = ctx.config("metronome_hdr", (*lens, f"camera.focus_distance_m={s_f}"))
        images.append(Renderer.from_config(scene, focused).render(0.0, spp, ctx.seed).sum(axis=0))
    white = float(np.percentile(images[1].mean(axis=-1), 99.5))
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.4), gridspec_kw={"height_ratios": [1, 1.1]})
    rows = [["focus_m", "blur_radius_px_at_0.7m", "blur_radius_px_at_needle", "blur_radius_px_at_1.6m"]]
    crop = (slice(int(0.30 * H), int(0.80 * H)), slice(int(0.30 * W), int(0.70 * W)))  # the metronome and the ball
    for (top, bottom), (label, s_f), img in zip(axes.T, focus.items(), images):
        shown = np.clip(img / white, 0, 1) ** (1 / 2.2)
        top.imshow(shown)
        bottom.imshow(shown[crop], interpolation="nearest")
        radii = [blur_radius_px(scene.camera, W, aperture, s_f, z) for z in (0.7, target, 1.6)]
        rows.append([s_f, *radii])
        top.set_title(f"focused {label}", fontsize=9)
        bottom.set_title(f"crop; blur radius {radii[1]:.1f} px at the needle, {radii[2]:.1f} px at 1.6 m", fontsize=8)
        for ax in (top, bottom):
            ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    caption = (
        f"The metronome through a thin lens (Mitsuba's thinlens sensor) of f = "
        f"{focal_length_m(scene.camera, W, cfg.sensor.pixel_pitch_um) * 1e3:.1f} mm at f/{cfg.sensor.f_number:g} "
        f"(aperture radius {aperture * 1e3:.2f} mm) on {cfg.sensor.pixel_pitch_um:g} um pixels, focused at three "
        "distances. A point at depth z spreads over a disk of radius r |1/s_f - 1/z| in angle "
        "(optics.blur_radius_px; the table gives it in pixels), the law tests/test_optics.py checks on a rendered edge."
    )
    return FigureOutput(
        fig,
        {
            "focal_length_m": focal_length_m(scene.camera, W, cfg.sensor.pixel_pitch_um),
            "aperture_radius_m": aperture,
            "rows": rows,
        },
        caption,
        rows,
    )


@figure("camera_cfa", "A Bayer mosaic and its demosaicing (sensor.cfa: RGGB, sensor.demosaic)", "beyond the paper")
def camera_cfa(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    cfg = ctx.config("metronome_hdr", ())
    scene = scene_of(cfg)
    W, H = ctx.film
    img = Renderer.from_config(scene, cfg).render(0.0, 16 if ctx.quick else 64, ctx.seed).sum(axis=0).astype(np.float64)
    img /= float(np.percentile(img.mean(axis=-1), 99.5))  # white: the 99.5th percentile, noise-free
    pattern = "RGGB"
    mosaic = to_mosaic(img, pattern)[..., 0]
    shown_mosaic = np.zeros_like(img)  # each photosite in its filter's colour
    np.put_along_axis(shown_mosaic, channel_map(pattern, H, W)[..., None].astype(np.intp), mosaic[..., None], -1)
    crop = (
        slice(int(0.35 * H), int(0.35 * H) + max(H // 8, 16)),
        slice(int(0.45 * W), int(0.45 * W) + max(W // 8, 16)),
    )
    panels = {"the scene (three stacked photosites)": img, f"{pattern} mosaic: one channel per photosite": shown_mosaic}
    rows = [["demosaic", "psnr_db_vs_truth", "max_colour_error"]]
    for method in DEMOSAIC_METHODS:
        out = demosaic(mosaic, pattern, method)
        mse = float(np.mean((np.clip(out, 0, 1) - np.clip(img, 0, 1)) ** 2))
        psnr_db = 10 * np.log10(1.0 / mse)
        rows.append([method, psnr_db, float(np.abs(out - img).max())])
        panels[f"{method}: PSNR {psnr_db:.1f} dB"] = out
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4))
    for ax, (title, p) in zip(axes, panels.items()):
        ax.imshow(np.clip(p[crop], 0, 1) ** (1 / 2.2), interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    caption = (
        f"A crop of the metronome at {W}x{H}, noise-free, through an {pattern} colour filter array: each photosite "
        "keeps one channel, and colour-demosaicing's bilinear, Malvar (2004) and Menon (2007) methods bring back "
        "three. The PSNR (whole image, white = the 99.5th percentile) is the demosaicing's own error, which a "
        "capture on a Bayer sensor adds to its noise; edges show it as colour fringes."
    )
    return FigureOutput(fig, {"pattern": pattern, "rows": rows}, caption, rows)


@figure(
    "camera_distortion",
    "Radial lens distortion: the colour chart without, barrel and pincushion (camera.distortion)",
    "beyond the paper",
)
def camera_distortion(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    W, H = ctx.film
    spp = 4 if ctx.quick else 16
    cases = {
        "none": None,
        "barrel, k1 = -1.2": [-1.2],
        "pincushion, k1 = +1.2": [1.2],
    }  # the chart's view is 22 degrees
    fig, axes = plt.subplots(1, len(cases), figsize=(4 * len(cases), 3.6))
    rows = [["distortion", "render_fov_deg", "corner_shift_px"]]
    images = []
    for ax, (label, k) in zip(axes, cases.items()):
        cfg = ctx.config(
            "metronome_hdr", ("scene.name=colour_chart", f"camera.distortion={k}" if k else "camera.distortion=null")
        )
        r = Renderer.from_config(scene_of(cfg), cfg)
        img = r.render(0.0, spp, ctx.seed).sum(axis=0)
        images.append(img)
        ax.imshow(np.clip(img / float(np.percentile(images[0], 99.5)), 0, 1) ** (1 / 2.2))
        ax.set_title(f"{label}: Mitsuba renders {r.lens.render_fov_deg:.1f} degrees", fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
        t = np.tan(np.radians(r.scene_model.camera.fov_deg) / 2)
        corner = (t, t * H / W)  # where the sensor's corner ray would land without the lens's bending, in px
        shift = 0.0 if not k else float(np.hypot(*corner) * abs(k[0]) * (corner[0] ** 2 + corner[1] ** 2) * W / (2 * t))
        rows.append([label, r.lens.render_fov_deg, shift])
    fig.tight_layout()
    caption = (
        "The colour chart through a lens with radial (Brown-Conrady) distortion: the sensor pixel's ray is the "
        "pinhole ray that the polynomial r (1 + k1 r^2) sends onto it, found with OpenCV and resampled from a "
        "pinhole render wide enough for the corners (barrel needs a wider one). The straight patch rows bow "
        "outward (barrel) or inward (pincushion); the table gives the shift the polynomial makes at the corner."
    )
    return FigureOutput(fig, {"rows": rows}, caption, rows)
