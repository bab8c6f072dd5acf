"""``report.html``: the page a person reads after a run, written beside ``report.json``.

One self-contained page (inline CSS, no scripts, no fonts or files from the network) that opens
offline from the output folder: the run's summary (scene, protocol, sensor, reads with exposure,
span and centroid), the gate schedule drawn as a timeline, every read twice (on one common DN
scale, so the exposure ratios show, and each on its own), the application's images with what
they show, the saturation and SNR maps, a histogram of each read in DN with the full well and the
ADC range marked, the metrics, the verdict on rendering noise against shot noise, and timings.

Every image it shows is a PNG in the same folder, written through the run's staging folder
(:class:`mbcapture.output.io.Staging`), so the page and its images appear together or not at all.
Plots are matplotlib (Agg, ``matplotlib.figure.Figure`` without pyplot, no timestamps); the
timeline is drawn by :func:`mbcapture.output.plots.draw_timeline`, the same code as the paper's
timing figures. The HTML is assembled by hand, one small function per section (:func:`write_report`
lists them), after the pictures are written (:func:`write_report_pictures`): it is a few tables and
images, which a templating library would not make shorter.
"""

from __future__ import annotations

import numpy as np

from ..budget import noise_verdict
from ..output.htmlparts import CSS, esc, figure, fmt, table
from ..metrics import flat_items, luminance
from ..scene.optics import diffraction_otf
from ..output.io import Staging
from .pipeline import CaptureResult
from ..output.plots import colour_map, gate_code_png, histograms_png, png8, summed_label, timeline_png

#: The common scale of the read previews: white is this percentile of the brightest read's luminance
#: (a percentile, not the maximum, so that one hot pixel does not make every read black).
COMMON_SCALE_PERCENTILE = 99.9

FILE_NOTES = {
    "buckets.exr": "noise-free expected electrons per bucket (B1.R, ...)",
    "reads_expected.exr": "noise-free, unclipped expected electrons of each read",
    "reads.exr": "simulated reads in DN, black level included",
    "config.yaml": "the resolved config (loads back as a config)",
    "report.json": "everything on this page as data (docs/report.md explains each key)",
    "report_timeline.png": "the gate schedule of this run",
    "report_histograms.png": "histogram of each read in DN",
    "map_saturation.png": "how many reads saturated, per pixel",
    "map_snr.png": "signal-to-noise ratio per pixel",
    "map_valid.png": "HDR valid flag per pixel",
}


# ----------------------------------------------------------------------------- read previews
#: The report's line for a sensor without a Bayer mosaic (sensor.cfa).
CFA_LINES = {
    "none": "none: R, G and B at every pixel (three stacked photosites)",
    "mono": "monochrome: one spectral response, the sum of the bands' (the reads' R, G, B are equal)",
}


def white_balanced(reads_dn: np.ndarray, black_level_dn: float, k_e: np.ndarray) -> np.ndarray:
    """Reads in DN above black, white-balanced: each channel times max(k_e) / k_e[c], the sensor's response to
    the render's linear sRGB channel c over the strongest (``k_e``: electrons per unit radiance and second), so
    that a white surface is grey, as in the previews of radiance (truth.png). The camera's raw values weigh the
    channels by the filters' response instead (the green one about twice the blue)."""
    above = np.asarray(reads_dn, dtype=np.float64) - black_level_dn
    k = np.asarray(k_e, dtype=np.float64)
    return above * (k.max() / k) if k.shape == (above.shape[-1],) and (k > 0).all() else above


def read_scales(balanced: np.ndarray) -> tuple[float, list[float]]:
    """White levels of the read previews, from the reads :func:`white_balanced`: the common one (the
    ``COMMON_SCALE_PERCENTILE`` of the brightest read's luminance) and each read's own maximum."""
    lum = luminance(balanced)  # (R, H, W)
    common = max(float(np.percentile(read, COMMON_SCALE_PERCENTILE)) for read in lum)
    own = [float(read.max()) for read in lum]
    return (common if common > 0 else 1.0), [o if o > 0 else 1.0 for o in own]


def write_read_previews(st: "Staging", result: "CaptureResult") -> dict:
    """``read_<J>_common_scale.png`` (one white for every read: exposure ratios visible) and
    ``read_<J>_own_scale.png`` (each read's maximum is white), white-balanced (:func:`white_balanced`), with
    the sRGB curve; returns their scales for report.json."""
    names = [r.name for r in result.timeline.reads]
    balanced = white_balanced(result.reads_dn, result.config.sensor.black_level_dn, result.k_e)
    common, own = read_scales(balanced)
    for i, n in enumerate(names):
        st.write_png(f"read_{n}_common_scale.png", balanced[i] / common, None)
        st.write_png(f"read_{n}_own_scale.png", balanced[i] / own[i], None)
    how = "DN above black level, white-balanced by the sensor's response per channel (a white surface is grey)"
    return {
        "read_common_scale_white_dn": common,
        "read_common_scale": f"read_<name>_common_scale.png: {how}, / {common:.6g} (the "
        f"{COMMON_SCALE_PERCENTILE:g}th percentile luminance of the brightest read), "
        "clipped, sRGB curve: the same DN is the same grey in every read",
        "read_own_scale_white_dn": dict(zip(names, own)),
        "read_own_scale": f"read_<name>_own_scale.png: {how}, / that read's largest luminance, sRGB curve",
    }


def read_limits_dn(result: "CaptureResult") -> list[dict]:
    """Per read: the DN of its charge limit (its buckets' full wells, or the floating diffusion's,
    whichever is lower), of the black level, and of the ADC's top code."""
    s = result.config.sensor
    out = []
    for r in result.timeline.reads:
        limit_e = min(len(r.buckets) * s.full_well_e, s.fd_full_well_e)
        out.append(
            {
                "read": r.name,
                "charge_limit_e": limit_e,
                "charge_limit_dn": min(s.black_level_dn + s.gain_dn_per_e * limit_e, float(s.adc_max_dn)),
                "black_level_dn": s.black_level_dn,
                "adc_max_dn": float(s.adc_max_dn),
            }
        )
    return out


def snr_map(result: "CaptureResult") -> tuple[np.ndarray, str]:
    """(H, W) SNR and its description: of the HDR radiance's luminance where the application has
    ``radiance`` and ``sigma`` (NaN where not valid); otherwise of the read with the most light,
    expected from its noise-free electrons with photon shot noise and read noise (NaN where it
    saturated)."""
    img = result.images
    if "radiance" in img and "sigma" in img and img["radiance"].shape[-1] == 3:
        w = np.array([0.2126, 0.7152, 0.0722])  # the luminance weights of metrics.luminance (Rec. 709)
        lum = luminance(img["radiance"])
        sd = np.sqrt(((w * np.where(np.isfinite(img["sigma"]), img["sigma"], np.nan)) ** 2).sum(axis=-1))
        snr = np.where(sd > 0, lum / np.where(sd > 0, sd, 1.0), np.nan)
        if "valid" in img:
            snr = np.where(img["valid"].min(axis=-1) > 0, snr, np.nan)
        return snr, "HDR radiance: luminance / its 1-sigma uncertainty (grey: no valid read)"
    i = int(np.argmax(result.reads_expected_e.reshape(len(result.timeline.reads), -1).sum(axis=1)))
    e = result.reads_expected_e[i].mean(axis=-1)
    noise = np.sqrt(e + result.config.sensor.read_noise_e**2)
    snr = np.where(result.saturated[i].any(axis=-1), np.nan, e / noise)
    name = result.timeline.reads[i].name
    return snr, (
        f"read {name} (the one with the most light), expected: electrons / sqrt(electrons + read noise^2) "
        "(grey: saturated)"
    )


# ----------------------------------------------------------------------------- html


def _scale_html(scale: dict, label: str) -> str:
    """The colour scale of a :func:`colour_map` map, as HTML."""
    if "levels" in scale:
        sw = "".join(f"<span class='sw' style='background:{c}'></span>{k} " for k, c in enumerate(scale["levels"]))
        return f"<div class='scale'>{esc(label)}: {sw}<span class='sw' style='background:#d9d9d9'></span>none</div>"
    grad = ",".join(scale["stops"])
    lo, hi = scale["min"], scale["max"]
    mid = np.sqrt(lo * hi) if scale["log"] else (lo + hi) / 2
    return (
        f"<div class='scale'>{esc(label)}{' (log scale)' if scale['log'] else ''}<div class='bar' "
        f"style='background:linear-gradient(to right,{grad})'></div><div class='ticks'><span>{fmt(lo)}</span>"
        f"<span>{fmt(mid)}</span><span>{fmt(hi)}</span></div></div>"
    )


def _preview_scale(percentile: float | None) -> str:
    return (
        "linear, 1.0 is white"
        if percentile is None
        else f"tone-mapped: its {percentile:g}th percentile luminance is white"
    )


def write_report(st: Staging, result: CaptureResult) -> None:
    """Write the maps, the timeline, the histograms and ``report.html`` into the staging folder;
    call it last, so that the page can list every file of the run. The pictures are written first
    (:func:`write_report_pictures`), then the page is laid out from one function per section."""
    maps = write_report_pictures(st, result)
    rep = result.report
    sections = [summary_section(result), schedule_section()]
    if result.timeline.code is not None and not result.timeline.code.identity:  # a coded capture's gate code
        sections.append(gate_code_section(st, result))
    sections += [reads_section(result), app_section(result)]
    if result.video is not None:  # a video run's frames, previews and comparisons (mbcapture/capture/video.py)
        sections.append(video_section_html(result))
    sections += [
        maps_section(maps),
        histograms_section(),
        metrics_section(rep),
        render_noise_section(rep),
        timings_section(rep),
        files_section(st, result),
    ]
    title = f"mbcapture: {rep['app']} of {rep['scene']} ({rep['protocol']})"
    st.write_bytes("report.html", page_html(title, sections, video=result.video is not None).encode("utf-8"))


def write_report_pictures(st: Staging, result: CaptureResult) -> list[tuple[str, str]]:
    """The report's pictures (timeline, histograms, the saturation, SNR and HDR-valid maps) into the staging folder;
    returns each map's (file, caption)."""
    cfg, tl, rep = result.config, result.timeline, result.report
    names = [r.name for r in tl.reads]
    st.write_bytes("report_timeline.png", timeline_png(tl))
    st.write_bytes(
        "report_histograms.png",
        histograms_png(
            result.reads_dn,
            names,
            [r["exposure_s"] for r in rep["reads"]],
            read_limits_dn(result),
            cfg.sensor.adc_max_dn,
        ),
    )
    sat_count = result.saturated.any(axis=-1).sum(axis=0).astype(float)
    rgb, sat_scale = colour_map(sat_count, levels=len(names))
    st.write_bytes("map_saturation.png", png8(rgb))
    snr, snr_text = snr_map(result)
    rgb, snr_scale = colour_map(snr, log=True)
    st.write_bytes("map_snr.png", png8(rgb))
    maps = [
        (
            "map_saturation.png",
            f"<b>Saturation</b>: how many of the {len(names)} reads saturated (a bucket's or the "
            "floating diffusion's full well, or the ADC's top code) at each pixel."
            + _scale_html(sat_scale, "reads saturated"),
        ),
        ("map_snr.png", f"<b>SNR</b> of the {esc(snr_text)}." + _scale_html(snr_scale, "SNR")),
    ]
    if "valid" in result.images:
        rgb, valid_scale = colour_map(result.images["valid"].min(axis=-1).astype(float), levels=1)
        st.write_bytes("map_valid.png", png8(rgb))
        maps.append(
            (
                "map_valid.png",
                "<b>HDR valid</b>: 1 where the radiance is measured; 0 where every read "
                "saturated (the radiance there is a lower bound)." + _scale_html(valid_scale, "valid"),
            )
        )
    return maps


def _lens_line(cfg) -> str:
    s = cfg.sensor
    if cfg.camera.lens == "pinhole":
        return "pinhole (everything in focus)"
    return (
        f"thin lens at f/{s.f_number:g}, focal length "
        + (f"{cfg.camera.focal_length_mm:g} mm" if cfg.camera.focal_length_mm else "from the field of view")
        + ", focused at "
        + (f"{cfg.camera.focus_distance_m:g} m" if cfg.camera.focus_distance_m else "the scene's subject")
        + (
            f"; radial distortion k = {', '.join(f'{k:g}' for k in cfg.camera.distortion)} (Brown-Conrady)"
            if cfg.camera.distortion
            else ""
        )
    )


def _film_line(cfg, film) -> str:
    diffraction = ""
    if cfg.camera.diffraction:
        mtf = diffraction_otf(
            500.0 / cfg.sensor.pixel_pitch_um, np.asarray(cfg.sensor.wavelength_nm), cfg.sensor.f_number
        )
        diffraction = (
            f", diffraction at f/{cfg.sensor.f_number:g} (MTF at Nyquist "
            + ", ".join(f"{m:.2f}" for m in mtf)
            + " for R, G, B)"
        )
    return (
        f"{film[0]} x {film[1]} px, variant {cfg.render.variant}"
        + (", natural vignetting (cos^4 of the field angle)" if cfg.camera.vignetting == "cos4" else "")
        + diffraction
    )


def summary_section(result: CaptureResult) -> str:
    """The run: scene, protocol, application, sensor, lens, film, span, rendering, seed, versions; the reads."""
    cfg, tl, rep = result.config, result.timeline, result.report
    scene_params = cfg.scene.params().model_dump(mode="json")
    s = cfg.sensor
    plan = rep["plan"]
    summary_rows = [
        ["scene", f"{rep['scene']}: " + ", ".join(f"{k}={fmt(v)}" for k, v in scene_params.items())],
        [
            "protocol",
            f"{rep['protocol']}"
            + (" (sequential: the same shots one after another on a conventional sensor)" if rep["sequential"] else ""),
        ],
        ["application", rep["app"]],
        [
            "sensor",
            f"{rep['sensor_type']}; {s.pixel_pitch_um:g} µm pixels, f/{s.f_number:g}, full well "
            f"{s.full_well_e:g} e- per bucket, floating diffusion {s.fd_full_well_e:g} e-, read noise "
            f"{s.read_noise_e:g} e-, gain {s.gain_dn_per_e:g} DN/e-, {s.adc_bits}-bit ADC, black level "
            f"{s.black_level_dn:g} DN",
        ],
        [
            "fixed pattern and row noise",
            f"PRNU {100 * s.prnu:g} % per pixel, {100 * s.prnu_row:g} % per row, "
            f"{100 * s.prnu_col:g} % per column; DSNU {s.dsnu_e:g} e- per pixel, "
            f"{s.dsnu_row_e:g} e- per row, {s.dsnu_col_e:g} e- per column; temporal row "
            f"noise {s.read_noise_row_e:g} e- (sensor.fpn_seed {s.fpn_seed})",
        ],
        [
            "colour filter array",
            CFA_LINES.get(
                s.cfa,
                f"Bayer {s.cfa}: one channel per photosite, each read demosaiced "
                f"({s.demosaic}, colour-demosaicing); raw files keep the mosaic",
            ),
        ],
        ["lens", _lens_line(cfg)],
        ["film", _film_line(cfg, rep["film"])],
        ["capture span", f"{rep['capture_span_s'] * 1e3:.6g} ms, {cfg.capture.periods} periods"],
        [
            "rendering",
            f"{plan['passes']} passes (time strata) x {result.plan.spp_label()} spp "
            f"({plan['spp_source']}); image motion {plan['image_motion_px_total']} px in all, at most "
            f"{plan['max_motion_px']} px per stratum",
        ],
        ["seed", rep["seed"]],
        ["versions", ", ".join(f"{k} {v}" for k, v in rep["versions"].items() if v is not None)],
    ]
    names = [r.name for r in tl.reads]
    sat = result.saturated.reshape(len(names), -1).mean(axis=1)
    read_rows = [
        [
            r["name"],
            summed_label(r["buckets"], tl.sequential),
            r["exposure_s"] * 1e3,
            f"{r['span_start_s'] * 1e3:.6g} – {r['span_end_s'] * 1e3:.6g}",
            r["span_s"] * 1e3,
            r["centroid_s"] * 1e3,
            f"{100 * sat[i]:.2f} %",
        ]
        for i, r in enumerate(rep["reads"])
    ]
    return (
        "<h2 id='summary'>The run</h2>"
        + "".join(f"<p class='lead'>{esc(line)}</p>" for line in result.app_output.summary)
        + table(summary_rows)
        + "<h3>Reads</h3>"
        + table(
            read_rows,
            [
                "read",
                "buckets summed",
                "exposure (ms)",
                "span (ms from start)",
                "span (ms)",
                "centroid (ms)",
                "saturated samples",
            ],
        )
        + "<p class='muted'>Exposure: the time the read's buckets collected. Span: from the first to the last moment "
        "any of them collected. Centroid: the mean time of the collected light (the paper's equations 1-5).</p>"
    )


def schedule_section() -> str:
    """The gate schedule's timeline."""
    return "<h2 id='schedule'>Gate schedule</h2>" + figure(
        "report_timeline.png",
        "Which bucket collects the photodiode's charge in each slot, which switchable "
        "emitter groups (flash, LEDs) are on, and each read's span and centroid.",
        plot=True,
    )


def reads_section(result: CaptureResult) -> str:
    """Every read twice: on one common DN scale, and each on its own."""
    rep = result.report
    names = [r.name for r in result.timeline.reads]
    scales = rep.get("previews", {})
    common_white = scales.get("read_common_scale_white_dn")
    own = scales.get("read_own_scale_white_dn", {})
    cells = []
    for i, n in enumerate(names):
        exp_ms = rep["reads"][i]["exposure_s"] * 1e3
        cells.append(
            figure(
                f"read_{n}_common_scale.png",
                f"<b>{esc(n)}</b>, {exp_ms:.4g} ms: common scale, white = {fmt(common_white)} DN",
            )
        )
    for i, n in enumerate(names):
        exp_ms = rep["reads"][i]["exposure_s"] * 1e3
        cells.append(
            figure(
                f"read_{n}_own_scale.png", f"<b>{esc(n)}</b>, {exp_ms:.4g} ms: own scale, white = {fmt(own.get(n))} DN"
            )
        )
    return (
        "<h2 id='reads'>Reads</h2><p>Top row: every read on one DN scale (black level removed; white = the "
        f"{COMMON_SCALE_PERCENTILE:g}th percentile luminance of the brightest read), so exposure ratios are visible. "
        "Bottom row: each read scaled to its own maximum. White-balanced DN above black, sRGB curve.</p>"
        f"<div class='grid' style='grid-template-columns:repeat({len(names)},minmax(0,300px))'>"
        + "".join(cells)
        + "</div>"
    )


def app_section(result: CaptureResult) -> str:
    """The application's previews, each with what it shows."""
    app_out, rep = result.app_output, result.report
    app_cells = []
    for stem, (image, pct) in app_out.png.items():
        text = app_out.captions.get(stem, "")
        app_cells.append(
            figure(
                f"{stem}.png", f"<b>{esc(stem)}</b> ({esc(_preview_scale(pct))})" + (f": {esc(text)}" if text else "")
            )
        )
    return (
        f"<h2 id='app'>Application: {esc(rep['app'])}</h2>"
        f"<p>Linear images as layers in <a href='{esc(result.app)}.exr'>{esc(result.app)}.exr</a>; "
        "previews:</p><div class='grid'>" + "".join(app_cells) + "</div>"
    )


def maps_section(maps: list[tuple[str, str]]) -> str:
    """The saturation, SNR (and HDR-valid) maps of :func:`write_report_pictures`."""
    return (
        "<h2 id='maps'>Saturation and SNR</h2><div class='grid' style='grid-template-columns:"
        f"repeat({len(maps)},minmax(0,400px))'>" + "".join(figure(f, t) for f, t in maps) + "</div>"
    )


def histograms_section() -> str:
    """Each read's histogram in DN with its clip points."""
    return "<h2 id='histograms'>Histograms</h2>" + figure(
        "report_histograms.png",
        "Each read in DN, per channel (pixels per bin, log scale). Dotted: black level; dashed: the "
        "read's full well (its buckets' full wells summed, or the floating diffusion's, whichever is lower); red: "
        "the ADC's top code. Pixels piled at a line are clipped there.",
        plot=True,
    )


def metrics_section(rep: dict) -> str:
    """The application's metrics, flattened."""
    metric_rows = [[k, v] for k, v in flat_items(rep["metrics"])]
    return (
        "<h2 id='metrics'>Metrics</h2>"
        + table(metric_rows, ["metric", "value"])
        + "<p class='muted'>Their meaning: <code>mbcapture apps</code> and docs/report.md.</p>"
    )


def render_noise_section(rep: dict) -> str:
    """The verdict on rendering noise against shot noise, and its figures."""
    err = rep.get("render_error", {})
    return (
        "<h2 id='render-noise'>Rendering noise against shot noise</h2>"
        f"<p class='verdict'>{esc(err.get('verdict') or noise_verdict(err))}</p>"
        + table([[k, v] for k, v in flat_items(err) if k != "verdict"], ["render_error", "value"])
    )


def timings_section(rep: dict) -> str:
    """Seconds per stage."""
    timings = rep.get("timings_s", {})
    return (
        "<h2 id='timings'>Timings</h2>"
        + table([[k, v] for k, v in timings.items()], ["stage", "seconds"])
        + "<p class='muted'>Seconds per stage of this run; writing the outputs is not included.</p>"
    )


def files_section(st: Staging, result: CaptureResult) -> str:
    """Every file of the run, with what it holds."""
    names = [r.name for r in result.timeline.reads]
    files = sorted(set(st.names) | {"report.html"})
    notes = {**FILE_NOTES, f"{result.app}.exr": "the application's images as linear layers", "report.html": "this page"}
    for n in names:
        notes[f"read_{n}_common_scale.png"] = f"read {n}, white-balanced, on the scale common to all reads"
        notes[f"read_{n}_own_scale.png"] = f"read {n}, white-balanced, its own maximum white"
        notes[f"read_{n}.dng"] = (
            f"read {n} as a DNG raw file (output.dng): ADC codes, black and white levels, colour matrix"
        )
    for stem, (image, pct) in result.app_output.png.items():
        notes.setdefault(f"{stem}.png", f"preview of {image} ({_preview_scale(pct)})")
    file_rows = "".join(
        f"<tr><td><a href='{esc(f)}'>{esc(f)}</a></td><td>{esc(notes.get(f, ''))}</td></tr>" for f in files
    )
    return f"<h2 id='files'>Files</h2><table><tr><th>file</th><th>content</th></tr>{file_rows}</table>"


def page_html(title: str, sections: list[str], *, video: bool = False) -> str:
    """The page: its title, the section links, the sections."""
    nav = " · ".join(
        f"<a href='#{a}'>{t}</a>"
        for a, t in [
            ("summary", "run"),
            ("schedule", "schedule"),
            ("reads", "reads"),
            ("app", "application"),
            *([("video", "video")] if video else []),
            ("maps", "maps"),
            ("histograms", "histograms"),
            ("metrics", "metrics"),
            ("render-noise", "rendering noise"),
            ("timings", "timings"),
            ("files", "files"),
        ]
    )
    return (
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
        f"<meta name='viewport' content='width=device-width, initial-scale=1'><style>{CSS}</style></head><body>"
        f"<h1>{esc(title)}</h1><p class='muted'>{nav}</p>" + "".join(sections) + "</body></html>\n"
    )


def subframe_names(tl) -> list[str]:
    """Each sub-frame of a coded timeline named by the switchable groups lit in it ('dark': none)."""
    out = []
    for c in range(tl.n_channels):
        groups = sorted({g for seg in tl.segments for sl in seg.slots if sl.bucket == c for g in sl.groups_on})
        out.append(" + ".join(groups) if groups else "dark")
    return out


def gate_code_section(st: "Staging", result: "CaptureResult") -> str:
    """The report.html section of a coded capture: one period of its per-pixel patterns and how its
    reads were demultiplexed (the application's ``coded_gates`` metrics, when it reports them)."""
    tl = result.timeline
    code = tl.code
    st.write_bytes("gate_code.png", gate_code_png(code, subframe_names(tl)))
    rows = [
        ["family", code.family],
        ["sub-frames", code.n_subframes],
        ["buckets", code.n_buckets],
        ["tile", f"{code.tile_shape[0]} x {code.tile_shape[1]} px"],
        ["distinct pixel codes", len(code.vectors()[0])],
    ]
    demux = (result.report.get("metrics") or {}).get("coded_gates") or {}
    shown = {
        "method": fmt,
        "window_half_width_px": lambda v: " x ".join(map(str, v)),
        "noise_gain": lambda v: ", ".join(f"{k}: {fmt(g)}" for k, g in v.items()),
        "undetermined_px": fmt,
    }
    rows += [[key.replace("_", " "), show(demux[key])] for key, show in shown.items() if key in demux]
    return (
        "<h2 id='gate-code'>Per-pixel gate code</h2><p>Every pixel sends each sub-frame of the schedule to a bucket "
        "of its own choosing (capture.gate_code); the reads are demultiplexed into one image per sub-frame. "
        "Noise gain: each sub-frame image's variance per unit variance of a read.</p>"
        + figure(
            "gate_code.png",
            "One period of the per-pixel patterns: the bucket each pixel of the film's corner sends each sub-frame to.",
            plot=True,
        )
        + table(rows)
    )


def video_section_html(result) -> str:
    """The report.html section of a video run."""

    rep = result.report["video"]
    rows = [
        ["frames", rep["frames"]],
        ["frame rate (frames/s)", rep["frame_rate_hz"]],
        ["frame period (ms)", rep["frame_period_s"] * 1e3],
        ["capture + readout (ms)", (rep["capture_span_s"] + rep["readout_s"]) * 1e3],
    ]
    for key in ("multi_bucket", "alternating_exposure"):
        if key in rep:
            s = rep[key]
            rows += [
                [
                    f"{key}: ghosting relMSE in the moving region, mean / max",
                    f"{fmt(s['ghosting_rel_mse_moving_mean'])} / {fmt(s['ghosting_rel_mse_moving_max'])}",
                ],
                [f"{key}: temporal consistency", s["temporal_consistency"]],
            ]
    for r in rep.get("aliasing", {}).get("rates", {}).values():
        rows.append(
            [
                f"{r['frame_rate_hz']:g} frames/s: apparent motion frequency (Hz)",
                f"{r['apparent_frequency_hz']:.3g} (true {rep['aliasing']['true_frequency_hz']:.3g})"
                + (" aliased" if r["aliased"] else ""),
            ]
        )
    figs = ""
    if result.video.radiance is not None:
        figs = (
            "<div class='grid'>"
            + figure(
                "video.gif",
                "<b>video.gif</b>: the HDR video, one white level for every frame (<a href='video.mp4'>video.mp4</a>)",
            )
            + figure("compare.gif", "<b>compare.gif</b>: truth | multi-bucket | alternating exposures")
            + "</div>"
        )
    return (
        "<h2 id='video'>Video</h2><p>Frame 0 is shown in the other sections; every frame's layers are in "
        "frame_&lt;i&gt;.exr and its metrics in <a href='frames.csv'>frames.csv</a>.</p>"
        + figs
        + table(rows, ["", "value"])
        + f"<p class='muted'>{esc('report.json video: every number')}</p>"
    )
