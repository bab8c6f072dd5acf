"""``report.html``: the page a person reads after a run, written beside ``report.json``.

One self-contained page (inline CSS, no scripts, no fonts or files from the network) that opens
offline from the output folder: the run's summary (scene, protocol, sensor, reads with exposure,
span and centroid), the gate schedule drawn as a timeline, every read twice (on one common DN
scale, so the exposure ratios show, and each on its own), the application's images with what
they show, the saturation and SNR maps, a histogram of each read in DN with the full well and the
ADC range marked, the metrics, the verdict on rendering noise against shot noise, and timings.

Every image it shows is a PNG in the same folder, written through the run's staging folder
(:class:`mbcapture.io.Staging`), so the page and its images appear together or not at all.
Plots are matplotlib (Agg, ``matplotlib.figure.Figure`` without pyplot, no timestamps); the
timeline is drawn by :func:`mbcapture.plots.draw_timeline`, the same code as the paper's
timing figures. The HTML is assembled by hand: it is a few tables and images, which no templating
library would make shorter.
"""

from __future__ import annotations

import io
from typing import TYPE_CHECKING

import numpy as np

from .budget import noise_verdict
from .htmlparts import esc, figure, fmt, table
from .metrics import flat_items, luminance
from .plots import BUCKET_COLOURS, draw_timeline
from .video import video_section_html

if TYPE_CHECKING:
    from .capture import CaptureResult
    from .io import Staging
    from .timeline import Timeline

#: The common scale of the read previews: white is this percentile of the brightest read's luminance
#: (a percentile, not the maximum, so that one hot pixel does not make every read black).
COMMON_SCALE_PERCENTILE = 99.9
#: A schedule with more slots than this is drawn whole in outline, and its first periods in detail.
MAX_DETAIL_SLOTS = 480

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
def read_scales(reads_dn: np.ndarray, black_level_dn: float) -> tuple[float, list[float]]:
    """White levels (DN above black) of the read previews: the common one (the
    ``COMMON_SCALE_PERCENTILE`` of the brightest read's luminance) and each read's own maximum."""
    lum = luminance(np.asarray(reads_dn, dtype=np.float64) - black_level_dn)  # (R, H, W)
    common = max(float(np.percentile(l, COMMON_SCALE_PERCENTILE)) for l in lum)
    own = [float(l.max()) for l in lum]
    return (common if common > 0 else 1.0), [o if o > 0 else 1.0 for o in own]


def write_read_previews(st: "Staging", result: "CaptureResult") -> dict:
    """``read_<J>_common_scale.png`` (one white for every read: exposure ratios visible) and
    ``read_<J>_own_scale.png`` (each read's maximum is white), sRGB; returns their scales for
    report.json."""
    black = result.config.sensor.black_level_dn
    names = [r.name for r in result.timeline.reads]
    common, own = read_scales(result.reads_dn, black)
    for i, n in enumerate(names):
        above = result.reads_dn[i] - black
        st.write_png(f"read_{n}_common_scale.png", above / common, None)
        st.write_png(f"read_{n}_own_scale.png", above / own[i], None)
    return {
        "read_common_scale_white_dn": common,
        "read_common_scale": f"read_<name>_common_scale.png: DN above black level / {common:.6g} (the "
                             f"{COMMON_SCALE_PERCENTILE:g}th percentile luminance of the brightest read), "
                             "clipped, sRGB: the same DN is the same grey in every read",
        "read_own_scale_white_dn": dict(zip(names, own)),
        "read_own_scale": "read_<name>_own_scale.png: DN above black level / that read's largest luminance, sRGB",
    }


# ----------------------------------------------------------------------------- plots
def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    return buf.getvalue()


def _margins(fig, *, left_in: float, right_in: float, bottom_in: float, top_in: float, hspace_in: float,
             wspace: float = 0.2) -> None:
    """Fixed margins in inches (tight_layout draws the figure twice: 3x slower for these plots)."""
    w, h = fig.get_size_inches()
    rows = fig.axes[0].get_subplotspec().get_gridspec().nrows if fig.axes else 1
    cell = (h - bottom_in - top_in - hspace_in * (rows - 1)) / rows
    fig.subplots_adjust(left=left_in / w, right=1 - right_in / w, bottom=bottom_in / h, top=1 - top_in / h,
                        hspace=hspace_in / max(cell, 0.1), wspace=wspace)


def _time_unit(seconds: float) -> tuple[float, str]:
    return (1e-3, "ms") if seconds >= 1e-3 else (1e-6, "µs")


def timeline_png(tl: "Timeline") -> bytes:
    """The gate schedule of a run: buckets (frames for a sequential capture) and switchable groups
    per slot, and each read's span with its centroid; a schedule of more than ``MAX_DETAIL_SLOTS``
    slots in outline (one block per segment) plus its first periods in detail."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch


    groups = sorted(tl.switchable_groups())
    n_slots = sum(seg.repeats * len(seg.slots) for seg in tl.segments)
    detail = n_slots <= MAX_DETAIL_SLOTS
    span_s = float((tl.end_tick - tl.start_tick) * tl.tick_s)
    unit, uname = _time_unit(span_s)
    reads = tl.describe_reads()
    rows = 1 + len(groups) + len(reads)
    panels = 1 if detail else 2
    fig = Figure(figsize=(10, 1.2 + 0.42 * rows * panels + 0.6 * (panels - 1)))
    axes = fig.subplots(panels, 1, squeeze=False)[:, 0]
    group_colour = "#222222"

    def schedule_rows(ax, until_tick=None, outline=False) -> None:
        y = rows - 1
        if outline:  # too many slots to draw: each segment as one block
            draw_timeline(ax, tl, y, unit, "", colour=lambda s: None)
            for seg in tl.segments:
                x0 = float((seg.start_tick - tl.start_tick) * tl.tick_s) / unit
                w = float((seg.end_tick - seg.start_tick) * tl.tick_s) / unit
                ax.add_patch(_hatched(x0, y, w))
                ax.text(x0 + w / 2, y, f"{seg.repeats} periods of {len(seg.slots)} slots", ha="center", va="center",
                        fontsize=7)
                for gi, g in enumerate(groups):
                    if any(g in s.groups_on for s in seg.slots):
                        ax.add_patch(_hatched(x0, y - 1 - gi, w))
        else:
            draw_timeline(ax, tl, y, unit, "", until_tick=until_tick)
            for gi, g in enumerate(groups):
                draw_timeline(ax, tl, y - 1 - gi, unit, "", height=0.35, until_tick=until_tick, background="#f2f2f2",
                              colour=lambda s, g=g: group_colour if g in s.groups_on else None)
        labels = {y: "frames" if tl.sequential else "buckets"}
        labels.update({y - 1 - gi: f"{g} on" for gi, g in enumerate(groups)})
        ax.set_yticks(list(labels), list(labels.values()), fontsize=8)

    ax = axes[0]
    schedule_rows(ax, outline=not detail)
    for i, r in enumerate(reads):  # spans and centroids
        y = len(reads) - 1 - i
        ax.plot([r["span_start_s"] / unit, r["span_end_s"] / unit], [y, y], color="#555555", lw=2)
        ax.plot([r["centroid_s"] / unit], [y], marker="|", ms=12, mew=2, color="#d62728")
        ax.text(r["span_end_s"] / unit, y, f"  {r['exposure_s'] * 1e3:.4g} ms", va="center", fontsize=7)
    ax.set_yticks([*ax.get_yticks(), *range(len(reads))],
                  [*[t.get_text() for t in ax.get_yticklabels()],
                   *[f"{r['name']} = {_summed(r['buckets'], tl.sequential)}" for r in reversed(reads)]], fontsize=8)
    ax.set_xlim(-0.01 * span_s / unit, 1.12 * span_s / unit)
    ax.set_ylim(-0.7, rows - 0.3)
    ax.set_xlabel(f"time from the start of the capture ({uname})")
    ax.set_title(f"{tl.protocol}{' (sequential, conventional sensor)' if tl.sequential else ''}: gate schedule; "
                 "reads: span (grey) and centroid (red)", fontsize=9)
    if not detail:  # the first periods in detail
        seg = tl.segments[0]
        periods = max(1, min(seg.repeats, MAX_DETAIL_SLOTS // max(len(seg.slots), 1), 2))
        until = seg.start_tick + periods * seg.period_ticks
        shown_s = float((until - tl.start_tick) * tl.tick_s)
        unit_d, uname_d = _time_unit(shown_s)
        ax = axes[1]
        y_top = rows - 1
        draw_timeline(ax, tl, y_top, unit_d, "", until_tick=until)
        for gi, g in enumerate(groups):
            draw_timeline(ax, tl, y_top - 1 - gi, unit_d, "", height=0.35, until_tick=until, background="#f2f2f2",
                          colour=lambda s, g=g: group_colour if g in s.groups_on else None)
        ax.set_yticks([y_top - k for k in range(1 + len(groups))],
                      ["frames" if tl.sequential else "buckets", *[f"{g} on" for g in groups]], fontsize=8)
        ax.set_xlim(0, shown_s / unit_d)
        ax.set_ylim(y_top - len(groups) - 0.7, y_top + 0.7)
        ax.set_xlabel(f"time ({uname_d})")
        ax.set_title(f"the first {periods} of {seg.repeats} periods", fontsize=9)
    used = sorted({s.bucket for seg in tl.segments for s in seg.slots if s.bucket >= 0})
    handles = [Patch(color=BUCKET_COLOURS[b % len(BUCKET_COLOURS)], label=f"{'frame' if tl.sequential else 'bucket'} {b + 1}")
               for b in used]
    handles.append(Patch(color="#dddddd", label="no bucket collects (drain, readout)"))
    if groups:
        handles.append(Patch(color=group_colour, label="switchable group on"))
    ncol = min(len(handles), 8)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=7, frameon=False)
    _margins(fig, left_in=1.45, right_in=0.15, bottom_in=0.7 + 0.2 * -(-len(handles) // ncol), top_in=0.3,
             hspace_in=0.75)
    return _png(fig)


def _summed(buckets: list[int], sequential: bool) -> str:
    """'B1+B2' (1-based buckets summed by a read), or 'frame 3' for a conventional sensor's frame."""
    return f"frame {buckets[0]}" if sequential else "+".join(f"B{b}" for b in buckets)


def _hatched(x: float, y: float, w: float):
    from matplotlib.patches import Rectangle

    return Rectangle((x, y - 0.3), w, 0.6, facecolor="#c6dbef", edgecolor="#6b8fb3", hatch="///", zorder=1)


def read_limits_dn(result: "CaptureResult") -> list[dict]:
    """Per read: the DN of its charge limit (its buckets' full wells, or the floating diffusion's,
    whichever is lower), of the black level, and of the ADC's top code."""
    s = result.config.sensor
    out = []
    for r in result.timeline.reads:
        limit_e = min(len(r.buckets) * s.full_well_e, s.fd_full_well_e)
        out.append({"read": r.name, "charge_limit_e": limit_e,
                    "charge_limit_dn": min(s.black_level_dn + s.gain_dn_per_e * limit_e, float(s.adc_max_dn)),
                    "black_level_dn": s.black_level_dn, "adc_max_dn": float(s.adc_max_dn)})
    return out


def histograms_png(result: "CaptureResult") -> bytes:
    """Histogram of each read in DN (per channel, log counts) with black level, charge limit and the
    ADC range marked."""
    from matplotlib.figure import Figure

    reads = result.reads_dn
    names = [r.name for r in result.timeline.reads]
    limits = read_limits_dn(result)
    adc_max = float(result.config.sensor.adc_max_dn)
    n = len(names)
    cols = min(n, 4)
    nrows = -(-n // cols)
    fig = Figure(figsize=(2.6 * cols + 0.4, 2.1 * nrows + 0.5))
    axes = fig.subplots(nrows, cols, squeeze=False).ravel()
    edges = np.linspace(0.0, adc_max + 1.0, 129)
    ch_colours = ["#d62728", "#2ca02c", "#1f77b4"] if reads.shape[-1] == 3 else ["#444444"] * reads.shape[-1]
    top = np.log10(max(reads[0, ..., 0].size, 10))
    decades = np.arange(0, int(np.ceil(top)) + 1)
    for i, name in enumerate(names):
        ax = axes[i]
        for c in range(reads.shape[-1]):  # log10(1 + count) on a linear axis: a log axis costs 4x in tick layout
            counts, _ = np.histogram(reads[i, ..., c], bins=edges)
            y = np.log10(1.0 + counts)
            ax.plot(edges, np.append(y, y[-1]), drawstyle="steps-post", color=ch_colours[c], lw=1)
        lim = limits[i]
        ax.axvline(lim["black_level_dn"], color="#777777", ls=":", lw=1, label="black level")
        ax.axvline(lim["charge_limit_dn"], color="#ff7f0e", ls="--", lw=1.2,
                   label="full well of the read (buckets or FD)")
        ax.axvspan(0, adc_max, color="#1f77b4", alpha=0.05, label="ADC range")
        ax.axvline(adc_max, color="#d62728", lw=1.2, label="ADC top code")
        ax.set_xlim(-0.02 * adc_max, 1.03 * adc_max)
        ax.set_ylim(0, top * 1.05)
        ax.set_yticks(decades, [str(10 ** d) if d < 3 else f"1e{d}" for d in decades])
        ax.set_xticks([0, adc_max / 2, adc_max], ["0", f"{adc_max / 2:.0f}", f"{adc_max:.0f}"])
        ax.set_title(f"{name}: {result.report['reads'][i]['exposure_s'] * 1e3:.4g} ms", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("DN", fontsize=8)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].set_ylabel("1 + pixels, per channel", fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=7, frameon=False)
    _margins(fig, left_in=0.75, right_in=0.15, bottom_in=0.75, top_in=0.3, hspace_in=0.75, wspace=0.28)
    return _png(fig)


MISSING_GREY = (217, 217, 217)


def colour_map(values: np.ndarray, *, log: bool = False, levels: int | None = None) -> tuple[np.ndarray, dict]:
    """A (H, W) map as (H, W, 3) uint8 viridis (NaN: light grey) and its colour scale for the page:
    ``levels``: integers 0..levels, one colour each; otherwise linear (or ``log``) from the finite
    minimum to the maximum. The scale is drawn in HTML (:func:`_scale_html`), so a map costs no plot."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    finite = values[np.isfinite(values)]
    if levels is not None:
        t = np.clip(np.nan_to_num(values, nan=0.0), 0, levels) / max(levels, 1)
        scale = {"levels": [_hex(cmap(k / max(levels, 1))) for k in range(levels + 1)]}
    else:
        if log:
            finite = finite[finite > 0]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        if log and lo > 0:
            v = np.log10(np.where(values > 0, values, np.nan))
            a, b = np.log10(lo), np.log10(hi)
        else:
            v, a, b, log = values, lo, hi, False
        t = np.clip((np.nan_to_num(v, nan=a) - a) / ((b - a) or 1.0), 0, 1)
        scale = {"min": lo, "max": hi, "log": log}
    rgb = (cmap(t)[..., :3] * 255).round().astype(np.uint8)
    rgb[~np.isfinite(values)] = MISSING_GREY
    scale["stops"] = [_hex(cmap(x)) for x in np.linspace(0, 1, 11)]
    return rgb, scale


def _hex(rgba) -> str:
    return "#" + "".join(f"{int(round(c * 255)):02x}" for c in rgba[:3])


def _png8(rgb: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb, mode="RGB").save(buf, format="PNG")
    return buf.getvalue()


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
    noise = np.sqrt(e + result.config.sensor.read_noise_e ** 2)
    snr = np.where(result.saturated[i].any(axis=-1), np.nan, e / noise)
    name = result.timeline.reads[i].name
    return snr, (f"read {name} (the one with the most light), expected: electrons / sqrt(electrons + read noise^2) "
                 "(grey: saturated)")


# ----------------------------------------------------------------------------- html
CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1280px;padding:0 1.2em 3em;
color:#222;line-height:1.4}
h1{font-size:1.5em;margin:.8em 0 .2em}h2{font-size:1.2em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0}td,th{border:1px solid #ddd;padding:.25em .6em;text-align:left;
vertical-align:top}th{background:#f5f5f5}td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(230px,1fr));gap:1em}
figure{margin:0}figure img{width:100%;image-rendering:pixelated;border:1px solid #ccc;background:#000}
figure.plot img{image-rendering:auto;background:#fff;border:none;width:auto;max-width:100%}figcaption{font-size:.82em;color:#444}
.lead{font-size:1.05em}.verdict{padding:.6em 1em;border-left:4px solid #888;background:#f7f7f7}
code{background:#f2f2f2;padding:0 .2em}.muted{color:#666;font-size:.85em}
.scale{font-size:.8em;margin:.3em 0}.bar{height:.8em;border:1px solid #aaa}.ticks{display:flex;justify-content:space-between}
.sw{display:inline-block;width:1em;height:.8em;border:1px solid #aaa;margin:0 .2em 0 .5em;vertical-align:middle}
"""


def _scale_html(scale: dict, label: str) -> str:
    """The colour scale of a :func:`colour_map` map, as HTML."""
    if "levels" in scale:
        sw = "".join(f"<span class='sw' style='background:{c}'></span>{k} " for k, c in enumerate(scale["levels"]))
        return f"<div class='scale'>{esc(label)}: {sw}<span class='sw' style='background:#d9d9d9'></span>none</div>"
    grad = ",".join(scale["stops"])
    lo, hi = scale["min"], scale["max"]
    mid = np.sqrt(lo * hi) if scale["log"] else (lo + hi) / 2
    return (f"<div class='scale'>{esc(label)}{' (log scale)' if scale['log'] else ''}<div class='bar' "
            f"style='background:linear-gradient(to right,{grad})'></div><div class='ticks'><span>{fmt(lo)}</span>"
            f"<span>{fmt(mid)}</span><span>{fmt(hi)}</span></div></div>")


def _preview_scale(percentile: float | None) -> str:
    return "linear, 1.0 is white" if percentile is None else f"tone-mapped: its {percentile:g}th percentile luminance is white"


def write_report(st: "Staging", result: "CaptureResult") -> None:
    """Write the maps, the timeline, the histograms and ``report.html`` into the staging folder;
    call it last, so that the page can list every file of the run."""
    cfg, tl, rep = result.config, result.timeline, result.report
    app_out = result.app_output
    names = [r.name for r in tl.reads]

    st.write_bytes("report_timeline.png", timeline_png(tl))
    st.write_bytes("report_histograms.png", histograms_png(result))
    sat_count = result.saturated.any(axis=-1).sum(axis=0).astype(float)
    rgb, sat_scale = colour_map(sat_count, levels=len(names))
    st.write_bytes("map_saturation.png", _png8(rgb))
    snr, snr_text = snr_map(result)
    rgb, snr_scale = colour_map(snr, log=True)
    st.write_bytes("map_snr.png", _png8(rgb))
    maps = [("map_saturation.png", f"<b>Saturation</b>: how many of the {len(names)} reads saturated (a bucket's or the "
                                   "floating diffusion's full well, or the ADC's top code) at each pixel."
                                   + _scale_html(sat_scale, "reads saturated")),
            ("map_snr.png", f"<b>SNR</b> of the {esc(snr_text)}." + _scale_html(snr_scale, "SNR"))]
    if "valid" in result.images:
        rgb, valid_scale = colour_map(result.images["valid"].min(axis=-1).astype(float), levels=1)
        st.write_bytes("map_valid.png", _png8(rgb))
        maps.append(("map_valid.png", "<b>HDR valid</b>: 1 where the radiance is measured; 0 where every read "
                                      "saturated (the radiance there is a lower bound)." + _scale_html(valid_scale, "valid")))

    scales = rep.get("previews", {})
    sections = []
    # ---- summary
    scene_params = cfg.scene.params().model_dump(mode="json")
    s = cfg.sensor
    plan = rep["plan"]
    summary_rows = [
        ["scene", f"{rep['scene']}: " + ", ".join(f"{k}={fmt(v)}" for k, v in scene_params.items())],
        ["protocol", f"{rep['protocol']}" + (" (sequential: the same shots one after another on a conventional sensor)"
                                              if rep["sequential"] else "")],
        ["application", rep["app"]],
        ["sensor", f"{rep['sensor_type']}; {s.pixel_pitch_um:g} µm pixels, f/{s.f_number:g}, full well "
                   f"{s.full_well_e:g} e- per bucket, floating diffusion {s.fd_full_well_e:g} e-, read noise "
                   f"{s.read_noise_e:g} e-, gain {s.gain_dn_per_e:g} DN/e-, {s.adc_bits}-bit ADC, black level "
                   f"{s.black_level_dn:g} DN"],
        ["film", f"{rep['film'][0]} x {rep['film'][1]} px, variant {cfg.render.variant}"],
        ["capture span", f"{rep['capture_span_s'] * 1e3:.6g} ms, {cfg.capture.periods} periods"],
        ["rendering", f"{plan['passes']} passes (time strata) x {result.plan.spp_label()} spp "
                      f"({plan['spp_source']}); image motion {plan['image_motion_px_total']} px in all, at most "
                      f"{plan['max_motion_px']} px per stratum"],
        ["seed", rep["seed"]],
        ["versions", ", ".join(f"{k} {v}" for k, v in rep["versions"].items() if v is not None)],
    ]
    sat = result.saturated.reshape(len(names), -1).mean(axis=1)
    read_rows = [[r["name"], _summed(r["buckets"], tl.sequential), r["exposure_s"] * 1e3,
                  f"{r['span_start_s'] * 1e3:.6g} – {r['span_end_s'] * 1e3:.6g}", r["span_s"] * 1e3,
                  r["centroid_s"] * 1e3, f"{100 * sat[i]:.2f} %"] for i, r in enumerate(rep["reads"])]
    sections.append(
        "<h2 id='summary'>The run</h2>"
        + "".join(f"<p class='lead'>{esc(line)}</p>" for line in app_out.summary)
        + table(summary_rows)
        + "<h3>Reads</h3>"
        + table(read_rows, ["read", "buckets summed", "exposure (ms)", "span (ms from start)", "span (ms)",
                             "centroid (ms)", "saturated samples"])
        + "<p class='muted'>Exposure: the time the read's buckets collected. Span: from the first to the last moment "
          "any of them collected. Centroid: the mean time of the collected light (the paper's equations 1-5).</p>")
    # ---- timeline
    sections.append("<h2 id='schedule'>Gate schedule</h2>" + figure(
        "report_timeline.png", "Which bucket collects the photodiode's charge in each slot, which switchable "
        "emitter groups (flash, LEDs) are on, and each read's span and centroid.", plot=True))
    # ---- reads
    common_white = scales.get("read_common_scale_white_dn")
    own = scales.get("read_own_scale_white_dn", {})
    cells = []
    for i, n in enumerate(names):
        exp_ms = rep["reads"][i]["exposure_s"] * 1e3
        cells.append(figure(f"read_{n}_common_scale.png",
                             f"<b>{esc(n)}</b>, {exp_ms:.4g} ms: common scale, white = {fmt(common_white)} DN"))
    for i, n in enumerate(names):
        exp_ms = rep["reads"][i]["exposure_s"] * 1e3
        cells.append(figure(f"read_{n}_own_scale.png",
                             f"<b>{esc(n)}</b>, {exp_ms:.4g} ms: own scale, white = {fmt(own.get(n))} DN"))
    sections.append(
        "<h2 id='reads'>Reads</h2><p>Top row: every read on one DN scale (black level removed; white = the "
        f"{COMMON_SCALE_PERCENTILE:g}th percentile luminance of the brightest read), so exposure ratios are visible. "
        "Bottom row: each read scaled to its own maximum. sRGB.</p>"
        f"<div class='grid' style='grid-template-columns:repeat({len(names)},minmax(0,300px))'>" + "".join(cells)
        + "</div>")
    # ---- application images
    app_cells = []
    for stem, (image, pct) in app_out.png.items():
        text = app_out.captions.get(stem, "")
        app_cells.append(figure(f"{stem}.png", f"<b>{esc(stem)}</b> ({esc(_preview_scale(pct))})"
                                 + (f": {esc(text)}" if text else "")))
    sections.append(f"<h2 id='app'>Application: {esc(rep['app'])}</h2>"
                    f"<p>Linear images as layers in <a href='{esc(result.app)}.exr'>{esc(result.app)}.exr</a>; "
                    "previews:</p><div class='grid'>" + "".join(app_cells) + "</div>")
    # ---- a video run's frames, previews and comparisons (mbcapture/video.py)
    if result.video is not None:

        sections.append(video_section_html(result))
    # ---- maps and histograms
    sections.append("<h2 id='maps'>Saturation and SNR</h2><div class='grid' style='grid-template-columns:"
                    f"repeat({len(maps)},minmax(0,400px))'>" + "".join(figure(f, t) for f, t in maps) + "</div>")
    sections.append("<h2 id='histograms'>Histograms</h2>" + figure(
        "report_histograms.png", "Each read in DN, per channel (pixels per bin, log scale). Dotted: black level; dashed: the "
        "read's full well (its buckets' full wells summed, or the floating diffusion's, whichever is lower); red: "
        "the ADC's top code. Pixels piled at a line are clipped there.", plot=True))
    # ---- metrics
    metric_rows = [[k, v] for k, v in flat_items(rep["metrics"])]
    sections.append("<h2 id='metrics'>Metrics</h2>" + table(metric_rows, ["metric", "value"])
                    + "<p class='muted'>Their meaning: <code>mbcapture apps</code> and docs/report.md.</p>")
    # ---- rendering noise
    err = rep.get("render_error", {})
    sections.append("<h2 id='render-noise'>Rendering noise against shot noise</h2>"
                    f"<p class='verdict'>{esc(err.get('verdict') or noise_verdict(err))}</p>"
                    + table([[k, v] for k, v in err.items() if k != "verdict"], ["render_error", "value"]))
    # ---- timings
    timings = rep.get("timings_s", {})
    sections.append("<h2 id='timings'>Timings</h2>" + table([[k, v] for k, v in timings.items()],
                                                             ["stage", "seconds"])
                    + "<p class='muted'>Seconds per stage of this run; writing the outputs is not included.</p>")
    # ---- files
    files = sorted(set(st.names) | {"report.html"})
    notes = {**FILE_NOTES, f"{result.app}.exr": "the application's images as linear layers",
             "report.html": "this page"}
    for n in names:
        notes[f"read_{n}_common_scale.png"] = f"read {n}, sRGB, on the scale common to all reads"
        notes[f"read_{n}_own_scale.png"] = f"read {n}, sRGB, its own maximum white"
    for stem, (image, pct) in app_out.png.items():
        notes.setdefault(f"{stem}.png", f"preview of {image} ({_preview_scale(pct)})")
    file_rows = "".join(f"<tr><td><a href='{esc(f)}'>{esc(f)}</a></td><td>{esc(notes.get(f, ''))}</td></tr>"
                        for f in files)
    sections.append(f"<h2 id='files'>Files</h2><table><tr><th>file</th><th>content</th></tr>{file_rows}</table>")

    title = f"mbcapture: {rep['app']} of {rep['scene']} ({rep['protocol']})"
    nav = " · ".join(f"<a href='#{a}'>{t}</a>" for a, t in [
        ("summary", "run"), ("schedule", "schedule"), ("reads", "reads"), ("app", "application"),
        *([("video", "video")] if result.video is not None else []), ("maps", "maps"),
        ("histograms", "histograms"), ("metrics", "metrics"), ("render-noise", "rendering noise"),
        ("timings", "timings"), ("files", "files")])
    page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'><style>{CSS}</style></head><body>"
            f"<h1>{esc(title)}</h1><p class='muted'>{nav}</p>" + "".join(sections) + "</body></html>\n")
    st.write_bytes("report.html", page.encode("utf-8"))
