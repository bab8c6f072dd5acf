"""The paper's timing, HDR and SNR figures (1, 2, 3, 5, 6, 9, 11) and the HDR SNR curves.

Timing diagrams are drawn from the timelines the simulator actually uses
(:func:`mbcapture.timing.protocols.build`), and centroids/spans come from
:meth:`Timeline.centroid_ticks` / :meth:`Timeline.span_ticks` (exact fractions), checked
here against the paper's closed forms (equations 1-5).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from ..timing import protocols
from ..config import config_from_dict
from ..errors import MBCaptureError
from ..output.io import tonemap
from ..output.plots import BUCKET_COLOURS, draw_timeline
from ..sensor import SensorConfig, dn_to_electrons, simulate_reads
from ..studies.snr import radiance_range, snr_curves
from ..sweep import load_sweep, run_sweep
from . import CONFIG_DIR, FigureContext, FigureOutput, figure


def _timeline(capture: dict, sensor: dict | None = None):
    return protocols.build(config_from_dict({"capture": capture, "sensor": sensor or {}}, "figure"))


def _bucket_legend(ax, n: int) -> None:
    from matplotlib.patches import Patch

    handles = [Patch(color=BUCKET_COLOURS[k], label=f"bucket {k + 1}") for k in range(n)]
    handles.append(Patch(color="#dddddd", label="idle (readout)"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=n + 1, fontsize=8, frameon=False)


def _read_rows(tl, unit_s: float) -> list[dict]:
    rows = []
    for r in tl.describe_reads():
        rows.append(
            {
                **r,
                "exposure_T": r["exposure_s"] / unit_s,
                "span_T": r["span_s"] / unit_s,
                "centroid_T": r["centroid_s"] / unit_s,
            }
        )
    return rows


# ------------------------------------------------------------------------------------- figure 1a
@figure("fig01_timing", "HDR timing: non-interleaved, time-interleaved, photon-efficient", "Fig. 1a", renders=False)
def fig01_timing(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    T, N = 1e-3, 4
    rows = {
        "non-interleaved (sequential)": _timeline(
            {"protocol": "interleaved_hdr", "unit_exposure_s": T, "periods": N, "sequential": True},
            {"frame_readout_s": 0.0},
        ),
        "time-interleaved (8:4:2:1)": _timeline({"protocol": "interleaved_hdr", "unit_exposure_s": T, "periods": N}),
        "photon-efficient (4:2:1:1)": _timeline(
            {"protocol": "photon_efficient_hdr", "unit_exposure_s": T, "periods": N}
        ),
    }
    fig, ax = plt.subplots(figsize=(9, 3.2))
    data = {}
    for i, (label, tl) in enumerate(rows.items()):
        y = len(rows) - 1 - i
        draw_timeline(ax, tl, y, T, label)
        end = float((tl.end_tick - tl.start_tick) * tl.tick_s) / T
        reads = _read_rows(tl, T)
        ax.text(
            end + 0.2,
            y,
            "reads: "
            + ", ".join(f"{r['name']}={'+'.join(f'B{b}' for b in r['buckets'])} ({r['exposure_T']:g}T)" for r in reads),
            va="center",
            fontsize=7,
        )
        data[label] = {"capture_span_T": end, "reads": reads}
    ax.set_xlim(-0.5, 26)
    ax.set_ylim(-0.7, len(rows) - 0.3)
    ax.set_yticks([])
    ax.set_xlabel("time (units of T)")
    _bucket_legend(ax, 4)
    fig.tight_layout()
    pe, il = data["photon-efficient (4:2:1:1)"], data["time-interleaved (8:4:2:1)"]
    caption = (
        f"Exposures T, 2T, 4T, 8T with N = {N} periods. Capture span: photon-efficient "
        f"{pe['capture_span_T']:g}T, time-interleaved {il['capture_span_T']:g}T, sequential "
        f"{data['non-interleaved (sequential)']['capture_span_T']:g}T (no readout gaps drawn)."
    )
    return FigureOutput(fig, {"unit_exposure_s": T, "periods": N, "protocols": data}, caption)


# ------------------------------------------------------------------------------------- figure 1b
def _crop_box(result, pad: int = 6) -> tuple[slice, slice]:
    mask = result.moving_mask
    if not mask.any():
        h, w = mask.shape
        return slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4)
    ys, xs = np.nonzero(mask)
    return slice(max(ys.min() - pad, 0), ys.max() + pad + 1), slice(max(xs.min() - pad, 0), xs.max() + pad + 1)


@figure("fig01_hdr", "Photon-efficient HDR of the moving metronome: reads T..8T and the merge", "Fig. 1b")
def fig01_hdr(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    res = ctx.capture("metronome_hdr")
    cfg, tl = res.config, res.timeline
    full_scale = cfg.sensor.adc_max_dn - cfg.sensor.black_level_dn  # one white for all reads: J1 dark, J4 clipped
    reads = [(r.name, (res.reads_dn[i] - cfg.sensor.black_level_dn) / full_scale) for i, r in enumerate(tl.reads)]
    exps = [r["exposure_s"] for r in tl.describe_reads()]
    crop = _crop_box(res)
    fig, axes = plt.subplots(
        2, len(reads) + 1, figsize=(2.6 * (len(reads) + 1), 4.6), gridspec_kw={"height_ratios": [1.0, 0.8]}
    )
    panels = [(f"{n} ({e * 1e3:g} ms)", tonemap(img, None)) for (n, img), e in zip(reads, exps)]
    panels.append(("HDR (ramp fit)", tonemap(res.images["radiance"], cfg.output.png_percentile)))
    for j, (title, img) in enumerate(panels):
        axes[0, j].imshow(img)
        axes[0, j].set_title(title, fontsize=9)
        axes[1, j].imshow(img[crop])
        for a in axes[:, j]:
            a.set_xticks([]), a.set_yticks([])
    axes[1, 0].set_ylabel("crop: needle and S", fontsize=8)
    fig.tight_layout()
    m = res.report["metrics"]
    caption = (
        f"Reads as the sensor saw them (each at its own exposure) and the merged HDR image; the crops show "
        f"the swinging needle with the same blur in every read. HDR relMSE {m['hdr_rel_mse']:.3g}, "
        f"largest difference between exposure-normalized reads in the moving region "
        f"{100 * m['motion_check'].get('max_pairwise_rel_rms', 0):.2f}%."
    )
    return FigureOutput(
        fig,
        {"metrics": m, "plan": {k: res.report["plan"][k] for k in ("passes", "spp")}, "film": list(ctx.film)},
        caption,
    )


# ------------------------------------------------------------------------------------- figure 2
@figure("fig02_ghosting", "Ghosting of a sequential two-frame HDR capture", "Fig. 2")
def fig02_ghosting(ctx: FigureContext) -> FigureOutput:
    """A long (8T) and a short (T) frame one after another at 15 fps, against the same two
    exposures interleaved in two buckets."""
    import matplotlib.pyplot as plt

    T = 2e-3
    sched = [
        "capture.protocol=custom",
        "capture.periods=16",
        "capture.schedule={slots: [{bucket: 1, duration_s: %g}, {bucket: 2, duration_s: %g}], "
        "reads: [{name: long, buckets: [1]}, {name: short, buckets: [2]}]}" % (8 * T / 16, T / 16),
    ]
    seq = ctx.capture("metronome_hdr", *sched, "capture.sequential=true", "sensor.frame_readout_s=0.0666667")
    inter = ctx.capture("metronome_hdr", *sched)
    crop = _crop_box(seq)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8))
    for ax, (title, res) in zip(axes[:2], [("sequential, 15 fps: ghost", seq), ("interleaved in 2 buckets", inter)]):
        ax.imshow(tonemap(res.images["radiance"], res.config.output.png_percentile)[crop])
        ax.set_title(title, fontsize=10)
        ax.set_xticks([]), ax.set_yticks([])
    err = [np.abs(r.images["radiance"] - r.images["truth"]).mean(axis=-1)[crop] for r in (seq, inter)]
    im = axes[2].imshow(err[0], cmap="magma")
    axes[2].set_title("|HDR - truth|, sequential (W m$^{-2}$ sr$^{-1}$)", fontsize=9)
    axes[2].set_xticks([]), axes[2].set_yticks([])
    fig.colorbar(im, ax=axes[2], fraction=0.046)
    fig.tight_layout()
    data = {
        name: {
            "hdr_rel_mse": r.report["metrics"]["hdr_rel_mse"],
            "hdr_rel_mse_moving": r.report["metrics"].get("hdr_rel_mse_moving"),
            "max_pairwise_rel_rms": r.report["metrics"]["motion_check"].get("max_pairwise_rel_rms"),
        }
        for name, r in (("sequential", seq), ("interleaved", inter))
    }
    caption = (
        f"Long (8T) and short (T) exposures, T = {T * 1e3:g} ms. Sequentially, with 1/15 s between the frames, the "
        f"needle is in two places (relMSE in the moving region {data['sequential']['hdr_rel_mse_moving']:.3g}); "
        f"interleaved in two buckets it is not ({data['interleaved']['hdr_rel_mse_moving']:.3g})."
    )
    return FigureOutput(fig, data, caption)


# ------------------------------------------------------------------------------------- figures 3 and 5
def _three_frames(T123: tuple[float, float, float], periods: int, sequential: bool, gap_s: float):
    slots = ", ".join("{bucket: %d, duration_s: %r}" % (i + 1, t / periods) for i, t in enumerate(T123))
    reads = ", ".join("{name: F%d, buckets: [%d]}" % (i + 1, i + 1) for i in range(3))
    import yaml

    sched = yaml.safe_load("{slots: [%s], reads: [%s]}" % (slots, reads))
    return _timeline(
        {"protocol": "custom", "periods": periods, "sequential": sequential, "schedule": sched},
        {"bucket_count": 3, "frame_readout_s": gap_s},
    )


def _centroid_check(T123, N: int) -> dict:
    """Centroids and spans from the timelines vs equations (1)-(5), exactly (fractions of a second)."""
    seq = _three_frames(T123, 1, True, 0.0)
    mux = _three_frames(T123, N, False, 0.0)
    t1, t2, t3 = (Fraction(x).limit_denominator(10**9) for x in T123)

    def cents(tl):
        return [tl.centroid_ticks(r.buckets) * tl.tick_s for r in tl.reads]

    def spans(tl):
        return [(lambda a, b: (b - a) * tl.tick_s)(*tl.span_ticks(r.buckets)) for r in tl.reads]

    cs, cm = cents(seq), cents(mux)
    ss, sm = spans(seq), spans(mux)
    closed = {
        "sequential C2-C1 = (T1+T2)/2": ((t1 + t2) / 2, cs[1] - cs[0]),
        "sequential C3-C2 = (T2+T3)/2": ((t2 + t3) / 2, cs[2] - cs[1]),
        "multiplexed C2-C1 = (T1+T2)/2N (eq. 4)": ((t1 + t2) / (2 * N), cm[1] - cm[0]),
        "multiplexed C3-C2 = (T2+T3)/2N (eq. 5)": ((t2 + t3) / (2 * N), cm[2] - cm[1]),
        "multiplexed span2-span1 = (T2-T1)/N": ((t2 - t1) / N, sm[1] - sm[0]),
        "multiplexed span3-span2 = (T3-T2)/N": ((t3 - t2) / N, sm[2] - sm[1]),
    }
    rows = [[k, float(v[0]), float(v[1]), v[0] == v[1]] for k, v in closed.items()]
    bad = [r[0] for r in rows if not r[3]]
    if bad:
        raise MBCaptureError(f"timeline centroids/spans disagree with the paper's closed forms: {bad}")
    return {
        "rows": rows,
        "centroids_sequential_s": [float(c) for c in cs],
        "centroids_multiplexed_s": [float(c) for c in cm],
        "spans_sequential_s": [float(s) for s in ss],
        "spans_multiplexed_s": [float(s) for s in sm],
    }


@figure(
    "fig03_frame_rates",
    "Three exposures on conventional sensors of low, high and infinite frame rate",
    "Fig. 3",
    renders=False,
)
def fig03_frame_rates(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    T123 = (1 / 125, 1 / 250, 1 / 500)
    cases = {"low frame rate (30 fps)": 1 / 30, "high frame rate (500 fps)": 1 / 500, "infinite frame rate": 0.0}
    fig, ax = plt.subplots(figsize=(9, 2.8))
    data = {}
    unit = 1e-3
    for i, (label, gap) in enumerate(cases.items()):
        tl = _three_frames(T123, 1, True, gap)
        y = len(cases) - 1 - i
        draw_timeline(ax, tl, y, unit, label)
        for r in tl.describe_reads():
            ax.plot(r["centroid_s"] / unit, y, "k.", ms=5)
        data[label] = {
            "frame_readout_s": gap,
            "capture_span_s": float((tl.end_tick - tl.start_tick) * tl.tick_s),
            "reads": tl.describe_reads(),
        }
    ax.set_ylim(-0.6, len(cases) - 0.4)
    ax.set_xlim(-25, 90)
    ax.set_yticks([])
    ax.set_xlabel("time (ms)")
    _bucket_legend(ax, 3)
    fig.tight_layout()
    caption = (
        "Exposures 1/125, 1/250 and 1/500 s captured one after another; grey: idle time while the previous frame is "
        "read out (frame time = readout time). Dots: exposure centroids. Capture spans: "
        + ", ".join(f"{k} {v['capture_span_s'] * 1e3:.1f} ms" for k, v in data.items())
        + "."
    )
    return FigureOutput(fig, data, caption)


@figure(
    "fig05_centroids", "Sequential vs time-multiplexed exposure: centroids and spans (eq. 1-5)", "Fig. 5", renders=False
)
def fig05_centroids(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    T123, N, unit = (4e-3, 2e-3, 1e-3), 4, 1e-3
    check = _centroid_check(T123, N)
    fig, ax = plt.subplots(figsize=(9, 2.6))
    for y, (label, tl) in zip(
        (1, 0),
        (
            ("(a) sequential, infinite frame rate", _three_frames(T123, 1, True, 0.0)),
            (f"(b) time-multiplexed, N = {N}", _three_frames(T123, N, False, 0.0)),
        ),
    ):
        draw_timeline(ax, tl, y, unit, label)
        for r in tl.describe_reads():
            ax.plot(r["centroid_s"] / unit, y, "ko", ms=4)
    ax.set_ylim(-0.6, 1.6)
    ax.set_xlim(-3.5, 7.5)
    ax.set_yticks([])
    ax.set_xlabel("time (ms)")
    _bucket_legend(ax, 3)
    fig.tight_layout()
    table = [["quantity", "closed form (s)", "from timeline (s)", "equal"], *check["rows"]]
    caption = (
        f"Frames of T1, T2, T3 = 4, 2, 1 ms. Dots: centroids computed from the schedule. All six centroid and span "
        f"differences equal the paper's closed forms exactly (N = {N} times closer when multiplexed)."
    )
    return FigureOutput(fig, {"T_s": list(T123), "N": N, **check}, caption, table)


# ------------------------------------------------------------------------------------- figure 6
@figure("fig06_interleaving", "Ghosting as the interleaving gets coarser (periods N)", "Fig. 6")
def fig06_interleaving(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    # The photon-efficient slice of the shipped sweep configs/sweeps/interleaving.yaml (periods x
    # protocol): T = 4 ms, a 32 ms capture in which the needle tip sweeps several pixels; strata of
    # at most 0.1 px (4 spp: the metric compares noise-free reads of the same renders) resolve the
    # motion within one period down to vT = 0.025 px (below that the planner would hold whole
    # periods per stratum and the reads would agree by construction, see plan._split_interval).
    grid = {"capture.protocol": ["photon_efficient_hdr"]}
    if ctx.quick:
        grid["capture.periods"] = [1, 4, 16, 64]
    sweep = load_sweep(CONFIG_DIR / "sweeps" / "interleaving.yaml", ctx.size_overrides(), axes=grid)
    outcome = run_sweep(sweep, None, in_process=True, keep_results=True, progress=ctx.progress)
    failed = [
        f"{p.label}: {outcome.rows[p.index].get('error')}" for p in sweep.points if p.index not in outcome.results
    ]
    if failed:
        raise RuntimeError(f"fig06_interleaving: sweep points failed: {'; '.join(failed)}")
    periods = [p.values["capture.periods"] for p in sweep.points]
    runs = [outcome.results[p.index] for p in sweep.points]
    rows = [
        [
            "periods_N",
            "period_s",
            "needle_motion_per_period_px",
            "vT_over_p",
            "hdr_rel_mse_moving",
            "max_pairwise_rel_rms",
        ]
    ]
    for n, r in zip(periods, runs):
        span = r.report["capture_span_s"]
        motion = r.report["plan"]["image_motion_px_total"]
        per_period = motion / n
        m = r.report["metrics"]
        rows.append(
            [
                n,
                span / n,
                per_period,
                per_period,
                m.get("hdr_rel_mse_moving"),
                m["motion_check"].get("max_pairwise_rel_rms"),
            ]
        )
    show = [0, len(periods) // 2, len(periods) - 1]
    crop = _crop_box(runs[0])
    fig = plt.figure(figsize=(11, 4.2))
    gs = fig.add_gridspec(1, 4, width_ratios=[1, 1, 1, 1.6])
    for j, i in enumerate(show):
        ax = fig.add_subplot(gs[0, j])
        ax.imshow(tonemap(runs[i].images["radiance"], runs[i].config.output.png_percentile)[crop])
        ax.set_title(f"N = {periods[i]}, vT = {rows[i + 1][3]:.2g} px", fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    ax = fig.add_subplot(gs[0, 3])
    vt = np.array([r[3] for r in rows[1:]])
    pair = np.array([r[5] for r in rows[1:]], dtype=float)
    resolved = pair > 0
    ax.loglog(vt[resolved], pair[resolved], "o-", label="largest difference between reads")
    ax.axvline(1.0, color="k", ls="--", lw=1)
    ax.text(1.05, pair.max(), "vT = p (one pixel)", fontsize=8, va="top")
    ax.set_xlabel("image motion per interleaving period vT (pixels)")
    ax.set_ylabel("relative RMS, moving region (1)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    caption = (
        "Photon-efficient HDR (T = 4 ms) of the swinging metronome with the 4:2:1:1 pattern repeated N times. With few "
        "periods the needle moves more than a pixel per period (vT > p) and the reads disagree (ghosts in the "
        "merge); the difference between reads falls in proportion to vT. Strata of at most 0.1 px resolve the "
        "motion inside each period. The photon-efficient points of the sweep configs/sweeps/interleaving.yaml "
        "(`mbcapture sweep interleaving` runs all of it, the interleaved protocol too)."
    )
    return FigureOutput(fig, {"rows": rows}, caption, rows)


# ------------------------------------------------------------------------------------- figure 9
@figure("fig09_gates", "Time-interleaved quad-exposure HDR: gate signals", "Fig. 9", renders=False)
def fig09_gates(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    T, N = 1e-3, 3
    tl = _timeline({"protocol": "interleaved_hdr", "unit_exposure_s": T, "periods": N})
    end = tl.end_tick - tl.start_tick
    t = np.linspace(0, end, 4000).astype(np.int64)
    fig, ax = plt.subplots(figsize=(9, 3.2))
    data = {}
    for k in range(tl.n_buckets):
        g = np.diff(tl.gated_ticks(np.append(t, end), k)) > 0
        ax.step(t * float(tl.tick_s) / T, 1.2 * (tl.n_buckets - 1 - k) + g, where="post", color=BUCKET_COLOURS[k])
        ax.text(-0.3, 1.2 * (tl.n_buckets - 1 - k) + 0.4, f"SG{k + 1}", ha="right", fontsize=9)
        data[f"bucket_{k + 1}_exposure_T"] = float(tl.exposure_ticks(k) * tl.tick_s) / T
    ax.set_yticks([])
    ax.set_xlabel("time (units of T)")
    ax.set_title(f"storage-gate signals, exposures 8T:4T:2T:T interleaved over N = {N} periods", fontsize=10)
    fig.tight_layout()
    caption = "High = the photodiode's charge goes to that bucket. Duty cycles set the exposure ratio 8:4:2:1."
    return FigureOutput(fig, {"unit_exposure_s": T, "periods": N, **data}, caption)


# ------------------------------------------------------------------------------------- figure 11
@figure(
    "fig11_snr_table", "SNR of read-then-add vs in-pixel addition, analytic and simulated", "Fig. 11", renders=False
)
def fig11_snr_table(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    S, R = 100.0, 8.0
    n = 20_000 if ctx.quick else 200_000
    cfg = SensorConfig(
        read_noise_e=R,
        prnu=0.0,
        dsnu_e=0.0,
        dark_current_e_per_s=0.0,
        full_well_e=1e6,
        fd_full_well_e=4e6,
        adc_bits=20,
        gain_dn_per_e=4.0,
    )
    exp_e = np.broadcast_to(np.array([4 * S, 2 * S, S, S])[:, None, None, None], (4, n, 1, 1)).copy()
    rng = np.random.default_rng(np.random.SeedSequence(ctx.seed).spawn(1)[0])
    cumulative = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
    inpix = dn_to_electrons(simulate_reads(exp_e, cumulative, cfg, rng).reads_dn, cfg).reshape(4, -1)
    sep = dn_to_electrons(simulate_reads(exp_e, [(3,), (2,), (1,), (0,)], cfg, rng).reads_dn, cfg).reshape(4, -1)
    added = np.cumsum(sep, axis=0)
    s_k = S * np.array([1, 2, 4, 8])
    k = np.arange(1, 5)
    q = 1.0 / (12 * cfg.gain_dn_per_e**2)
    rows = [
        [
            "read",
            "signal_e",
            "SNR_read_then_add_analytic",
            "SNR_read_then_add_simulated",
            "SNR_in_pixel_analytic",
            "SNR_in_pixel_simulated",
        ]
    ]
    for i in range(4):
        rows.append(
            [
                f"J{i + 1}",
                s_k[i],
                s_k[i] / np.sqrt(s_k[i] + k[i] * (R**2 + q)),
                added[i].mean() / added[i].std(ddof=1),
                s_k[i] / np.sqrt(s_k[i] + R**2 + q),
                inpix[i].mean() / inpix[i].std(ddof=1),
            ]
        )
    fig, ax = plt.subplots(figsize=(9, 2.4))
    ax.axis("off")
    cells = [[r[0], f"{r[1]:g}", f"{r[2]:.2f}", f"{r[3]:.2f}", f"{r[4]:.2f}", f"{r[5]:.2f}"] for r in rows[1:]]
    tab = ax.table(
        cellText=cells,
        colLabels=[
            "read",
            "signal (e-)",
            "read-then-add\nanalytic",
            "read-then-add\nsimulated",
            "in-pixel\nanalytic",
            "in-pixel\nsimulated",
        ],
        loc="center",
    )
    tab.scale(1, 1.5)
    ax.set_title(f"Buckets hold S, S, 2S, 4S with S = {S:g} e-, read noise R = {R:g} e-; {n} pixels", fontsize=10)
    fig.tight_layout()
    caption = (
        "Figure 11's tables: J_k = sum of the first k buckets. Adding after readout pays the read noise k times "
        "(SNR = s/sqrt(s + kR^2)); adding on the floating diffusion pays it once (s/sqrt(s + R^2)). "
        "Simulated columns: the sensor model on flat fields (quantization included in the analytic values)."
    )
    return FigureOutput(fig, {"S_e": S, "read_noise_e": R, "pixels": n, "rows": rows}, caption, rows)


# ------------------------------------------------------------------------------------- beyond the paper
@figure(
    "hdr_snr_vs_radiance", "HDR SNR against radiance for the three HDR protocols", "beyond the paper", renders=False
)
def hdr_snr_vs_radiance(ctx: FigureContext) -> FigureOutput:
    import matplotlib.pyplot as plt

    cfg = SensorConfig(prnu=0.0, dsnu_e=0.0)
    T = 1e-3
    radiance = radiance_range(cfg, T, 25 if ctx.quick else 61)
    curves = snr_curves(cfg, radiance, T, 2000 if ctx.quick else 20_000, ctx.seed)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for name, snr in curves.items():
        ax.plot(radiance, snr, label=name, lw=1.6)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("scene radiance L, green channel (W m$^{-2}$ sr$^{-1}$)")
    ax.set_ylabel("HDR SNR, mean / std of merged rate (1)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    rows = [["radiance_w_m2_sr", *(f"snr_{n}" for n in curves)]]
    rows += [[float(L), *(float(curves[n][i]) for n in curves)] for i, L in enumerate(radiance)]
    caption = (
        "Exposures T, 2T, 4T, 8T (T = 1 ms) of a static flat field: photon-efficient (ramp fit over cumulative "
        "reads, 8T of capture) against interleaved and sequential (15T). See scripts/snr_curves.py."
    )
    return FigureOutput(fig, {"unit_exposure_s": T, "rows": rows}, caption, rows)
