"""All matplotlib drawing of a run's report.html (:mod:`mbcapture.capture.report`) and the paper's figures
(:mod:`mbcapture.figures`): a gate schedule as coloured slots on a time axis, the run's schedule
with each read's span and centroid, histograms of the reads, colour maps. Figures are
``matplotlib.figure.Figure`` without pyplot, written as PNG without timestamps. matplotlib is
imported where a drawing needs it, so importing this module costs nothing.
"""

from __future__ import annotations

import io

import numpy as np

from ..sensor.emva import spectrogram
from ..timing.timeline import Timeline

#: One colour per bucket (bucket k: ``BUCKET_COLOURS[k % 6]``), in figures and reports alike.
BUCKET_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]


def draw_timeline(
    ax,
    tl,
    y: float,
    unit_s: float,
    label: str,
    height: float = 0.6,
    *,
    colour=None,
    until_tick: int | None = None,
    background: str = "#dddddd",
) -> int:
    """Coloured slots on a horizontal bar at ``y`` over a ``background`` bar (idle time), x in units of
    ``unit_s`` from the capture's start. ``colour(slot)``: the slot's colour or None to leave it out
    (default: one colour per bucket, drained slots left out). ``until_tick``: draw only the slots
    that start before it (a long schedule's first periods). Returns the number of slots drawn.
    The paper's timing figures and every run's report.html draw their schedules with it."""
    colour = colour or (lambda s: BUCKET_COLOURS[s.bucket % len(BUCKET_COLOURS)] if s.bucket >= 0 else None)
    t0 = tl.start_tick
    stop = tl.end_tick if until_tick is None else min(until_tick, tl.end_tick)
    drawn = 0
    for seg in tl.segments:
        tick = seg.start_tick
        for _ in range(seg.repeats):
            if tick >= stop:
                break
            for s in seg.slots:
                c = colour(s) if tick < stop else None
                if c is not None:
                    x = float((tick - t0) * tl.tick_s) / unit_s
                    w = float(s.ticks * tl.tick_s) / unit_s
                    ax.add_patch(_rect(x, y - height / 2, w, height, c))
                    drawn += 1
                tick += s.ticks
    end = float((stop - t0) * tl.tick_s) / unit_s
    ax.add_patch(_rect(0, y - height / 2, end, height, background, zorder=0))
    if label:
        ax.text(-0.02 * end, y, label, ha="right", va="center", fontsize=9)
    return drawn


def _rect(x, y, w, h, colour, zorder=1):
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, facecolor=colour, edgecolor="none", zorder=zorder)


#: A schedule with more slots than this is drawn whole in outline, and its first periods in detail.
MAX_DETAIL_SLOTS = 480


# ----------------------------------------------------------------------------- plots
def png_bytes(fig, dpi: int = 110) -> bytes:
    """A figure as PNG bytes without a timestamp or software tag (the same figure, the same bytes)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return buf.getvalue()


def set_margins(
    fig, *, left_in: float, right_in: float, bottom_in: float, top_in: float, hspace_in: float, wspace: float = 0.2
) -> None:
    """Fixed margins in inches (tight_layout draws the figure twice: 3x slower for these plots)."""
    w, h = fig.get_size_inches()
    rows = fig.axes[0].get_subplotspec().get_gridspec().nrows if fig.axes else 1
    cell = (h - bottom_in - top_in - hspace_in * (rows - 1)) / rows
    fig.subplots_adjust(
        left=left_in / w,
        right=1 - right_in / w,
        bottom=bottom_in / h,
        top=1 - top_in / h,
        hspace=hspace_in / max(cell, 0.1),
        wspace=wspace,
    )


def time_unit(seconds: float) -> tuple[float, str]:
    return (1e-3, "ms") if seconds >= 1e-3 else (1e-6, "µs")


def _first_periods(ax, tl: Timeline, groups: list[str], y_top: int, group_colour: str) -> None:
    """The first periods of a long schedule in detail, on ``ax`` (:func:`timeline_png`'s second panel)."""
    seg = tl.segments[0]
    periods = max(1, min(seg.repeats, MAX_DETAIL_SLOTS // max(len(seg.slots), 1), 2))
    until = seg.start_tick + periods * seg.period_ticks
    shown_s = float((until - tl.start_tick) * tl.tick_s)
    unit_d, uname_d = time_unit(shown_s)
    draw_timeline(ax, tl, y_top, unit_d, "", until_tick=until)
    for gi, g in enumerate(groups):
        draw_timeline(
            ax,
            tl,
            y_top - 1 - gi,
            unit_d,
            "",
            height=0.35,
            until_tick=until,
            background="#f2f2f2",
            colour=lambda s, g=g: group_colour if g in s.groups_on else None,
        )
    ax.set_yticks(
        [y_top - k for k in range(1 + len(groups))],
        [
            "frames" if tl.sequential else ("sub-frames" if tl.code is not None else "buckets"),
            *[f"{g} on" for g in groups],
        ],
        fontsize=8,
    )
    ax.set_xlim(0, shown_s / unit_d)
    ax.set_ylim(y_top - len(groups) - 0.7, y_top + 0.7)
    ax.set_xlabel(f"time ({uname_d})")
    ax.set_title(f"the first {periods} of {seg.repeats} periods", fontsize=9)


def timeline_png(tl: Timeline) -> bytes:
    """The gate schedule of a run: buckets (frames for a sequential capture) and switchable groups
    per slot, and each read's span with its centroid; a schedule of more than ``MAX_DETAIL_SLOTS``
    slots in outline (one block per segment) plus its first periods in detail."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    groups = sorted(tl.switchable_groups())
    n_slots = sum(seg.repeats * len(seg.slots) for seg in tl.segments)
    detail = n_slots <= MAX_DETAIL_SLOTS
    span_s = float((tl.end_tick - tl.start_tick) * tl.tick_s)
    unit, uname = time_unit(span_s)
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
                ax.text(
                    x0 + w / 2,
                    y,
                    f"{seg.repeats} periods of {len(seg.slots)} slots",
                    ha="center",
                    va="center",
                    fontsize=7,
                )
                for gi, g in enumerate(groups):
                    if any(g in s.groups_on for s in seg.slots):
                        ax.add_patch(_hatched(x0, y - 1 - gi, w))
        else:
            draw_timeline(ax, tl, y, unit, "", until_tick=until_tick)
            for gi, g in enumerate(groups):
                draw_timeline(
                    ax,
                    tl,
                    y - 1 - gi,
                    unit,
                    "",
                    height=0.35,
                    until_tick=until_tick,
                    background="#f2f2f2",
                    colour=lambda s, g=g: group_colour if g in s.groups_on else None,
                )
        labels = {y: "frames" if tl.sequential else ("sub-frames" if tl.code is not None else "buckets")}
        labels.update({y - 1 - gi: f"{g} on" for gi, g in enumerate(groups)})
        ax.set_yticks(list(labels), list(labels.values()), fontsize=8)

    ax = axes[0]
    schedule_rows(ax, outline=not detail)
    for i, r in enumerate(reads):  # spans and centroids
        y = len(reads) - 1 - i
        ax.plot([r["span_start_s"] / unit, r["span_end_s"] / unit], [y, y], color="#555555", lw=2)
        ax.plot([r["centroid_s"] / unit], [y], marker="|", ms=12, mew=2, color="#d62728")
        ax.text(r["span_end_s"] / unit, y, f"  {r['exposure_s'] * 1e3:.4g} ms", va="center", fontsize=7)
    ax.set_yticks(
        [*ax.get_yticks(), *range(len(reads))],
        [
            *[t.get_text() for t in ax.get_yticklabels()],
            *[f"{r['name']} = {summed_label(r['buckets'], tl.sequential)}" for r in reversed(reads)],
        ],
        fontsize=8,
    )
    ax.set_xlim(-0.01 * span_s / unit, 1.12 * span_s / unit)
    ax.set_ylim(-0.7, rows - 0.3)
    ax.set_xlabel(f"time from the start of the capture ({uname})")
    ax.set_title(
        f"{tl.protocol}{' (sequential, conventional sensor)' if tl.sequential else ''}: gate schedule; "
        "reads: span (grey) and centroid (red)",
        fontsize=9,
    )
    if not detail:  # the first periods in detail
        _first_periods(axes[1], tl, groups, rows - 1, group_colour)
    used = sorted({s.bucket for seg in tl.segments for s in seg.slots if s.bucket >= 0})
    kind = "frame" if tl.sequential else ("sub-frame" if tl.code is not None else "bucket")
    handles = [Patch(color=BUCKET_COLOURS[b % len(BUCKET_COLOURS)], label=f"{kind} {b + 1}") for b in used]
    handles.append(Patch(color="#dddddd", label="no bucket collects (drain, readout)"))
    if groups:
        handles.append(Patch(color=group_colour, label="switchable group on"))
    ncol = min(len(handles), 8)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=7, frameon=False)
    set_margins(
        fig, left_in=1.45, right_in=0.15, bottom_in=0.7 + 0.2 * -(-len(handles) // ncol), top_in=0.3, hspace_in=0.75
    )
    return png_bytes(fig)


def draw_gate_code(ax, code, subframe: int, size_px: int, title: str) -> None:
    """Which bucket every pixel of a ``size_px`` square (the film's top-left corner) sends
    ``subframe`` to, in bucket colours (drain grey), the code's tile outlined. The report's
    gate-code plot and the coded_gates figure draw with it."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Rectangle

    K = code.n_buckets
    cmap = ListedColormap(["#bbbbbb", *[BUCKET_COLOURS[k % len(BUCKET_COLOURS)] for k in range(K)]])
    ax.imshow(code.full(size_px, size_px)[subframe] + 1, cmap=cmap, vmin=0, vmax=K, interpolation="nearest")
    h, w = code.tile_shape
    if h <= size_px and w <= size_px:
        ax.add_patch(Rectangle((-0.5, -0.5), w, h, fill=False, edgecolor="black", lw=1.5))
    ax.set_title(title, fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])


def gate_code_png(code, names: list[str], size_px: int = 12) -> bytes:
    """One period of a per-pixel gate code: for each sub-frame, which bucket every pixel of a
    ``size_px`` square (the film's top-left corner) sends it to (bucket colours; drain grey)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    S, K = code.n_subframes, code.n_buckets
    fig = Figure(figsize=(1.7 * S + 0.4, 2.6))
    axes = fig.subplots(1, S, squeeze=False)[0]
    h, w = code.tile_shape
    for s, ax in enumerate(axes):
        draw_gate_code(
            ax, code, s, size_px, f"sub-frame {s + 1}: {names[s]}" if s < len(names) else f"sub-frame {s + 1}"
        )
    handles = [Patch(color=BUCKET_COLOURS[k % len(BUCKET_COLOURS)], label=f"bucket {k + 1}") for k in range(K)]
    if (code.tile < 0).any():
        handles.append(Patch(color="#bbbbbb", label="drain"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    fig.suptitle(f"per-pixel gate code '{code.family}': {size_px} x {size_px} px, tile {h} x {w} outlined", fontsize=9)
    set_margins(fig, left_in=0.1, right_in=0.1, bottom_in=0.45, top_in=0.45, hspace_in=0.2)
    return png_bytes(fig)


def summed_label(buckets: list[int], sequential: bool) -> str:
    """'B1+B2' (1-based buckets summed by a read), or 'frame 3' for a conventional sensor's frame."""
    return f"frame {buckets[0]}" if sequential else "+".join(f"B{b}" for b in buckets)


def _hatched(x: float, y: float, w: float):
    from matplotlib.patches import Rectangle

    return Rectangle((x, y - 0.3), w, 0.6, facecolor="#c6dbef", edgecolor="#6b8fb3", hatch="///", zorder=1)


def histograms_png(
    reads: np.ndarray, names: list[str], exposure_s: list[float], limits: list[dict], adc_max: float
) -> bytes:
    """Histogram of each read (R, H, W, C) in DN (per channel, log counts) with black level, charge
    limit and the ADC range marked; ``limits``: per read ``black_level_dn`` and ``charge_limit_dn``
    (:func:`mbcapture.capture.report.read_limits_dn`)."""
    from matplotlib.figure import Figure

    adc_max = float(adc_max)
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
        ax.axvline(
            lim["charge_limit_dn"], color="#ff7f0e", ls="--", lw=1.2, label="full well of the read (buckets or FD)"
        )
        ax.axvspan(0, adc_max, color="#1f77b4", alpha=0.05, label="ADC range")
        ax.axvline(adc_max, color="#d62728", lw=1.2, label="ADC top code")
        ax.set_xlim(-0.02 * adc_max, 1.03 * adc_max)
        ax.set_ylim(0, top * 1.05)
        ax.set_yticks(decades, [str(10**d) if d < 3 else f"1e{d}" for d in decades])
        ax.set_xticks([0, adc_max / 2, adc_max], ["0", f"{adc_max / 2:.0f}", f"{adc_max:.0f}"])
        ax.set_title(f"{name}: {exposure_s[i] * 1e3:.4g} ms", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("DN", fontsize=8)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].set_ylabel("1 + pixels, per channel", fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=7, frameon=False)
    set_margins(fig, left_in=0.75, right_in=0.15, bottom_in=0.75, top_in=0.3, hspace_in=0.75, wspace=0.28)
    return png_bytes(fig)


MISSING_GREY = (217, 217, 217)


def colormap_rgb(t: np.ndarray, name: str = "turbo") -> np.ndarray:
    """(..., 3) float RGB in [0, 1] of matplotlib's colour map ``name`` at ``t`` in [0, 1] (the map's own values,
    sRGB-encoded)."""
    from matplotlib import colormaps

    return colormaps[name](t)[..., :3]


def depth_preview(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """(H, W, 3) linear preview of a depth map: near bright, far dark (turbo colour map), not finite black."""
    t = np.clip((far - np.nan_to_num(depth, nan=far)) / max(far - near, 1e-9), 0, 1)
    rgb = colormap_rgb(t, "turbo") ** 2.2  # the PNG writer applies the sRGB curve
    rgb[~np.isfinite(depth)] = 0.0
    return rgb


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


def png8(rgb: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb, mode="RGB").save(buf, format="PNG")
    return buf.getvalue()


# ----------------------------------------------------------------------------- EMVA 1288 datasheet
CHANNEL_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")


def _labelled_png(fig, ax, **labels) -> bytes:
    """PNG bytes of a one-axes figure once its axes are labelled (``ax.set(**labels)``) and it has a legend."""
    ax.set(**labels)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return png_bytes(fig)


def datasheet_pngs(curves, mode: str) -> dict[str, tuple[bytes, str]]:
    """The plots of an EMVA 1288 datasheet (:mod:`mbcapture.studies.characterize`) for one read mode, as
    {name: (PNG bytes, caption)}: photon transfer, SNR, linearity and the spectrograms of the averaged
    dark and 50 % frames. ``curves``: a :class:`mbcapture.studies.characterize.ReadCurves`."""
    from matplotlib.figure import Figure

    out: dict[str, tuple[bytes, str]] = {}
    y = curves.light.mean - curves.dark.mean  # (steps, C)
    s2 = curves.light.variance - curves.dark.variance
    names = ("R", "G", "B")

    fig = Figure(figsize=(5.2, 3.6))
    ax = fig.add_subplot()
    for c, name in enumerate(names):
        K = curves.figures[name]["system_gain_dn_per_e"].value
        ax.plot(y[:, c], s2[:, c], "o", ms=3, color=CHANNEL_COLOURS[c], label=f"{name}: K = {K:.4g} DN/e-")
        ax.plot(y[:, c], K * y[:, c], "-", lw=0.8, color=CHANNEL_COLOURS[c])
    out["photon_transfer"] = (
        _labelled_png(
            fig,
            ax,
            xlabel="μ_y − μ_y.dark (DN)",
            ylabel="σ²_y − σ²_y.dark (DN²)",
            title=f"photon transfer ({mode} read)",
        ),
        "photon transfer: temporal variance against mean, with the gain K fitted "
        "up to 70 % of saturation; the variance drops at saturation",
    )

    fig = Figure(figsize=(5.2, 3.6))
    ax = fig.add_subplot()
    for c, name in enumerate(names):
        f = curves.figures[name]
        snr = y[:, c] / np.sqrt(np.maximum(curves.light.variance[:, c], 1e-12))
        ax.loglog(curves.mu_p[:, c], np.maximum(snr, 1e-3), "o", ms=3, color=CHANNEL_COLOURS[c], label=name)
        mu_e = f["quantum_efficiency"].value * curves.mu_p[:, c]
        noise_e2 = (f["temporal_dark_noise_dn"].value / f["system_gain_dn_per_e"].value) ** 2
        ax.loglog(curves.mu_p[:, c], mu_e / np.sqrt(noise_e2 + mu_e), "-", lw=0.8, color=CHANNEL_COLOURS[c])
    out["snr"] = (
        _labelled_png(
            fig, ax, xlabel="photons per pixel μ_p", ylabel="SNR", title=f"signal-to-noise ratio ({mode} read)"
        ),
        "SNR against photons: measured (dots) and the linear model of the measured η, σ_d, K (lines)",
    )

    fig = Figure(figsize=(5.2, 5.0))
    ax, dev = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    for c, name in enumerate(names):
        R = curves.figures[name]["responsivity_dn_per_photon"].value
        ax.plot(curves.mu_p[:, c], y[:, c], "o", ms=3, color=CHANNEL_COLOURS[c], label=f"{name}: R = {R:.4g} DN/p")
        ok = (y[:, c] > 0.05 * y[:, c].max()) & (y[:, c] < 0.95 * y[:, c].max())
        dev.plot(
            curves.mu_p[ok, c],
            (y[ok, c] - R * curves.mu_p[ok, c]) / (R * curves.mu_p[ok, c]) * 100,
            "o-",
            ms=3,
            color=CHANNEL_COLOURS[c],
        )
    ax.set(ylabel="μ_y − μ_y.dark (DN)", title=f"linearity ({mode} read)")
    ax.legend(fontsize=8)
    dev.set(xlabel="photons per pixel μ_p", ylabel="deviation (%)")
    fig.tight_layout()
    out["linearity"] = (
        png_bytes(fig),
        "linearity: mean against photons and its relative deviation from the fitted line "
        "between 5 % and 95 % of saturation",
    )

    fig = Figure(figsize=(7.5, 5.0))
    axes = fig.subplots(2, 2)
    for c, name in enumerate(names):
        dark = curves.dark_frame[..., c]
        light = curves.light_frame[..., c] - dark
        for col, axis in enumerate((1, 0)):
            f, amp = spectrogram(dark, axis)
            axes[0, col].semilogy(f[1:], amp[1:], lw=0.8, color=CHANNEL_COLOURS[c], label=name)
            f, amp = spectrogram(light / light.mean() * 100, axis)
            axes[1, col].semilogy(f[1:], amp[1:], lw=0.8, color=CHANNEL_COLOURS[c], label=name)
    for col, which in enumerate(("horizontal", "vertical")):
        axes[0, col].set(title=f"DSNU, {which}", ylabel="amplitude (DN)")
        axes[1, col].set(title=f"PRNU, {which}", ylabel="amplitude (%)", xlabel="frequency (cycles/pixel)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    out["spectrograms"] = (
        png_bytes(fig),
        "spectrograms of the averaged dark frame (DSNU) and of the 50 % frame less "
        "the dark one (PRNU): row and column patterns show as peaks or a raised "
        "floor at low frequency, white pixel noise is flat",
    )
    return out


# ----------------------------------------------------------------------------- convergence studies
def convergence_figure(result: dict):
    """The log-log plot of error against run time for both methods of a convergence study
    (:func:`mbcapture.studies.converge.run_converge`'s result), as a matplotlib Figure."""
    from matplotlib.figure import Figure

    pts = result["points"]
    fig = Figure(figsize=(6, 4.5), dpi=120)
    ax = fig.add_subplot()
    styles = {"motion": ("o-", "C0", "planner (motion strata)"), "naive": ("s--", "C3", "naive (one render per slot)")}
    for m, (style, color, label) in styles.items():
        sel = sorted((p for p in pts if p["method"] == m), key=lambda p: p["seconds"])
        if not sel:
            continue
        slope = result["slopes"].get(m)
        ax.loglog(
            [p["seconds"] for p in sel],
            [p["error"] for p in sel],
            style,
            color=color,
            label=f"{label}, slope {slope:.2f}" if slope is not None else label,
        )
        for p in sel:
            ax.annotate(
                str(p["spp"]),
                (p["seconds"], p["error"]),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
                color=color,
            )
    motion = sorted((p for p in pts if p["method"] == "motion"), key=lambda p: p["seconds"])
    if motion:
        t = np.array([min(p["seconds"] for p in pts), max(p["seconds"] for p in pts)])
        anchor = motion[len(motion) // 2]
        ax.loglog(
            t, anchor["error"] * (t / anchor["seconds"]) ** -0.5, ":", color="gray", label="slope -1/2 (Monte Carlo)"
        )
    for s in result.get("speedups", [])[:1]:
        ax.annotate(
            f"{s['speedup']:.1f}x at equal error",
            (s["planner_s"], s["error"]),
            xytext=(s["planner_s"] * 1.3, s["error"] * 1.4),
            arrowprops={"arrowstyle": "->", "color": "gray"},
            fontsize=8,
        )
    ax.set_xlabel("run time: plan + render + accumulate (s)")
    ax.set_ylabel("relative RMS error of the bucket exposures")
    W, H = result["film"]
    ax.set_title(f"{result['scene']} {result['protocol']}, {result['periods']} periods, {W}x{H}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def convergence_png(result: dict) -> bytes:
    """:func:`convergence_figure` as PNG bytes (at the figure's own 120 dpi)."""
    buf = io.BytesIO()
    convergence_figure(result).savefig(buf, format="png")
    return buf.getvalue()


# ----------------------------------------------------------------------------- sweeps
def _numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _log_scale(values: np.ndarray) -> bool:
    v = values[np.isfinite(values)]
    return bool(v.size and v.min() > 0 and v.max() / v.min() > 10)


def _major_only(axis, values: np.ndarray) -> None:
    """No minor ticks on a log axis whose values span two decades or more, which always shows two
    labelled decades: the minor ticks' artists are most of a panel's drawing time."""
    from matplotlib.ticker import NullLocator

    v = values[np.isfinite(values) & (values > 0)]
    if v.size and v.max() / v.min() >= 100:
        axis.set_minor_locator(NullLocator())


def _facets(ok, axis: str, axes: list[str]) -> tuple[str | None, list, list[str], bool]:
    """How ``axis`` is drawn: (facet axis or None, its panel values, the axes that make the lines,
    whether the points form a grid; False for random samples: a scatter)."""
    others = [a for a in axes if a != axis]
    structured = not others or bool(ok.groupby(others, dropna=False).size().max() > 1)
    facet = others[0] if structured and len(others) >= 2 else None
    panels = list(dict.fromkeys(ok[facet].tolist())) if facet else [None]
    lines = [a for a in others if a != facet] if structured else []
    return facet, panels, lines, structured


class MetricGrid:
    """One figure of panels for a sweep's table (a pandas DataFrame, :mod:`mbcapture.sweep.results`; the faceting is a
    few lines here rather than a plotting library's): a row of panels per axis, each against that axis,
    faceted by the other axes. :meth:`draw` puts one metric on it; the next call replaces it, so that
    the plots of every metric share one figure, whose axes and ticks are made once (making a panel's
    ticks anew is much of a plot's time: the six plots of the 64-point sensor_noise sweep took 2.6 s as
    fresh figures, 1.8 s redrawn)."""

    def __init__(self, df, axes: list[str]):
        from matplotlib.figure import Figure
        from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

        self.ok = ok = df[df["status"] == "ok"]
        layout = {axis: _facets(ok, axis, axes) for axis in axes}
        ncols = min(max(len(panels) for _, panels, _, _ in layout.values()), 4)
        nrows = sum(-(-len(panels) // ncols) for _, panels, _, _ in layout.values())
        # one metric: every panel on one scale (labelled on the first column); each row one x axis. Sizes in
        # inches: a panel 2.2 high, and between rows the room for the row's tick labels (rotated names need
        # more), its x label and the next row's titles, so that no two texts overlap
        rotated = any(not _numeric(list(dict.fromkeys(ok[axis].tolist()))) for axis in axes)
        self.gap_in = 1.05 if rotated else 0.8
        self.left_in = 1.15 if rotated else 0.85
        self.fig = Figure(figsize=(3.4 * ncols + self.left_in - 0.25, (2.2 + self.gap_in) * nrows + 0.35))
        grid = self.fig.subplots(nrows, ncols, squeeze=False, sharex="row", sharey=True)
        #: per panel: (its axes, its rows of the table, the x axis, its position function, line keys, structured,
        #: whether it is the first of its row, which has the legend)
        self.panels: list[tuple] = []
        row = 0
        for axis, (facet, panels, line_keys, structured) in layout.items():
            xs = list(dict.fromkeys(ok[axis].tolist()))
            numeric_x = _numeric(xs)
            position = (lambda v: v) if numeric_x else {v: i for i, v in enumerate(xs)}.__getitem__
            for n, panel in enumerate(panels):
                ax = grid[row + n // ncols][n % ncols]
                sub = ok if facet is None else ok[ok[facet] == panel]
                self.panels.append((ax, sub, axis, position, line_keys, structured, n == 0))
                # a fixed title position: the automatic one measures every tick label of the panel (a third of the time)
                ax.set_title(f"{facet} = {panel}" if facet is not None else "", fontsize=8, y=1.0)
                if numeric_x and _log_scale(np.asarray(xs, dtype=float)):
                    ax.set_xscale("log")
                if numeric_x:  # the sweep's own values, labelled as they are
                    ax.xaxis.set_major_locator(FixedLocator(sorted(float(v) for v in xs)))
                    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                    ax.xaxis.set_minor_locator(NullLocator())
                else:
                    ax.set_xticks(range(len(xs)), [str(v) for v in xs], rotation=20, fontsize=7, ha="right")
                ax.set_xlabel(axis, fontsize=8)
                ax.tick_params(labelsize=7)
            for n in range(len(panels), -(-len(panels) // ncols) * ncols):
                grid[row + n // ncols][n % ncols].set_visible(False)
            row += -(-len(panels) // ncols)
        # fixed margins in inches (tight_layout measures every label: half of the plot's time); the top holds the
        # metric's title above the first row's panel titles
        set_margins(
            self.fig,
            left_in=self.left_in,
            right_in=0.2,
            bottom_in=self.gap_in - 0.3,
            top_in=0.65,
            hspace_in=self.gap_in,
            wspace=0.3,
        )

    def draw(self, metric: str):
        """The figure with ``metric`` on every panel (the metric drawn before it taken off)."""
        y_all = self.ok[metric].to_numpy(dtype=float, na_value=np.nan)
        log_y = _log_scale(y_all)
        for ax, sub, axis, position, line_keys, structured, first in self.panels:
            for artist in [*ax.lines, *ax.collections]:
                artist.remove()
            if ax.get_legend() is not None:
                ax.get_legend().remove()
            ax.set_prop_cycle(None)  # the lines' colours from the first again
            if structured:
                groups = sub.groupby(line_keys, dropna=False, sort=False) if line_keys else [((), sub)]
                for key, part in groups:
                    key = key if isinstance(key, tuple) else (key,)
                    order = np.argsort([position(v) for v in part[axis]], kind="stable")
                    label = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in zip(line_keys, key)) or None
                    ax.plot(
                        np.asarray([position(v) for v in part[axis]])[order],
                        part[metric].to_numpy(dtype=float, na_value=np.nan)[order],
                        "o-",
                        ms=3.5,
                        lw=1.2,
                        label=label,
                    )
            else:
                ax.scatter([position(v) for v in sub[axis]], sub[metric].to_numpy(dtype=float, na_value=np.nan), s=12)
            ax.set_yscale("log" if log_y else "linear")  # the scale's own locators, whatever the last metric set
            if log_y:
                _major_only(ax.yaxis, y_all)
            ax.grid(True, which="major", alpha=0.3)
            ax.relim()
            ax.autoscale_view()
            if line_keys and first:
                ax.legend(fontsize=6.5, frameon=False)
        self.fig.suptitle(metric, fontsize=9, y=1 - 0.12 / self.fig.get_size_inches()[1], va="top")
        return self.fig


def sweep_plot(df, metric: str, axes: list[str]):
    """A figure of a sweep's table's ``metric`` against each axis (one row of panels per axis), faceted by the other axes."""
    return MetricGrid(df, axes).draw(metric)


def snr_png(designs: list[dict]) -> bytes:
    """SNR (dB) against scene luminance (log) for one or more capture designs (``mbcapture snr``): the merged
    HDR's curve thick, each read's thin, each switch point a dotted line of its design's colour, the
    simulated flat-field points with their 95 % intervals. ``designs``: dicts with ``label``,
    ``luminance`` (L,), ``merged`` (L,), ``per_read`` {name: (L,)}, ``switch_luminances``, and
    optionally ``points`` (luminance, snr, half-width of the interval), SNR as a plain ratio."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=(8.0, 5.2))
    ax = fig.add_subplot()
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]

    def db(x):
        with np.errstate(divide="ignore", invalid="ignore"):
            return 20 * np.log10(np.asarray(x, dtype=np.float64))

    left, right = np.inf, 0.0
    for d, colour in zip(designs, colours * (1 + len(designs) // len(colours))):
        shown = np.flatnonzero(np.nan_to_num(db(d["merged"]), nan=-np.inf) >= -10)
        if shown.size:
            left, right = min(left, d["luminance"][shown[0]]), max(right, d["luminance"][shown[-1]])
        ax.plot(d["luminance"], db(d["merged"]), color=colour, lw=2.2, label=d["label"])
        # each read's curve thin, its name where it ends (where that read saturates)
        for name, snr in d["per_read"].items():
            ax.plot(d["luminance"], db(snr), color=colour, lw=0.7, alpha=0.55)
            last = np.flatnonzero(np.isfinite(snr))
            if last.size:
                j = int(last[-1])
                ax.annotate(name, (d["luminance"][j], db(snr[j])), fontsize=6, color=colour, alpha=0.8)
        for x in d["switch_luminances"]:
            ax.axvline(x, color=colour, lw=0.8, ls=":")
        if d.get("points") is not None:
            lum, snr, half = d["points"]
            lo, hi = db(np.maximum(snr - half, 1e-12)), db(snr + half)
            ax.errorbar(lum, db(snr), yerr=[db(snr) - lo, hi - db(snr)], fmt="o", ms=3, color=colour, lw=0.8)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xscale("log")
    if np.isfinite(left) and right > left:
        ax.set_xlim(left / 1.5, right * 1.5)
    ax.set_ylim(bottom=-10)
    ax.grid(True, which="major", alpha=0.3)
    ax.set(
        xlabel="scene luminance, cd/m² (grey scene; green channel)",
        ylabel="SNR, dB (20 log10)",
    )
    ax.set_title("thick: the HDR merge; thin: each read; dotted: switch points; dots: simulated (95 %)", fontsize=9)
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], marker="o", ls="", color="0.3", ms=3))
    labels.append("simulated flat field, 95 % interval")
    ax.legend(handles, labels, fontsize=7, loc="upper left")
    fig.tight_layout()
    return png_bytes(fig)


def _panel_axes(n: int, width: float, height: float):
    """A figure of ``n`` panels in up to three columns, and its axes."""
    from matplotlib.figure import Figure

    cols = min(max(n, 1), 3)
    rows = -(-max(n, 1) // cols)
    fig = Figure(figsize=(width * cols, height * rows))
    return fig, [fig.add_subplot(rows, cols, i + 1) for i in range(n)]


def grouped_bars_png(categories: list[str], panels: list[tuple[str, dict[str, list[float]]]], title: str = "") -> bytes:
    """Panels (y label, {series: a value per category}) of grouped bars (``scripts/tof_table.py``)."""
    fig, axes = _panel_axes(len(panels), 4.2, 3.8)
    x = np.arange(len(categories))
    for ax, (ylabel, series) in zip(axes, panels):
        width = 0.8 / max(len(series), 1)
        for j, (label, values) in enumerate(series.items()):
            ax.bar(x - 0.4 + width * (j + 0.5), np.asarray(values, dtype=np.float64), width, label=label)
        ax.set_xticks(x, categories, rotation=30, ha="right", fontsize=7)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return png_bytes(fig)


def design_png(panels: list[tuple[str, list[tuple[str, list, list]]]], ylabel: str, log_x: list[bool]) -> bytes:
    """The objective against each variable of ``mbcapture design`` (per panel: label, [(source, x, y)])."""
    fig, axes = _panel_axes(len(panels), 4.0, 3.3)
    style = {"search": {"marker": "o", "s": 14}, "grid": {"marker": "s", "s": 18}, "default": {"marker": "*", "s": 90}}
    for i, (ax, (label, sources)) in enumerate(zip(axes, panels)):
        for name, x, y in sources:
            ax.scatter(x, y, label=name, **style.get(name, style["search"]))
        ax.set_xscale("log" if log_x[i] else "linear")
        ax.xaxis.set_minor_formatter("")  # a log axis's minor labels overlap
        ax.set(xlabel=label, ylabel=ylabel)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return png_bytes(fig)


def pareto_png(points: list[tuple[str, list, list]], front: tuple[list, list], labels: tuple[str, str]) -> bytes:
    """Two objectives of every design (per source: label, first, second) and the Pareto front (a line)."""
    fig, (ax,) = _panel_axes(1, 6.0, 4.4)
    for name, x, y in points:
        ax.scatter(x, y, s=14, label=name, alpha=0.8)
    ax.plot(*np.asarray(front, dtype=np.float64)[:, np.argsort(front[0])], "k-", label="Pareto front")
    ax.set(xlabel=labels[0], ylabel=labels[1])
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return png_bytes(fig)
