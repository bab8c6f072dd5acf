"""Multi-bucket video: ``capture.frames`` captures at ``capture.frame_rate_hz``, each read out before the next.

The paper: the approach "can be extended to the capture of HDR video"; its prototype's 3 frames/s
"can produce slight temporal aliasing in videography", which an on-chip ADC would fix.

Frame i is the configured capture (any protocol and application) started at
``capture.start_s + i / capture.frame_rate_hz``; after it, the sensor needs ``sensor.frame_readout_s``
to read out, so a frame period shorter than the capture's span plus the readout is refused (a
ConfigError naming ``capture.frame_rate_hz``). Every frame goes through the single-capture pipeline
(:func:`mbcapture.capture.pipeline.capture_in_memory`) with the run's renderer and render cache: renders that
frames share (a static scene, a pilot) are rendered once; frames at different times are different
renders. Frame i's config is the run's with ``capture.frames: 1``, its own ``capture.start_s`` and its
own ``sensor.noise_seed`` (a child of the run's), so one frame can be re-run alone; with
``render.spp: null`` the first frame's pilot chooses the samples per pixel and later frames take
its largest count (``render.spp``), without a pilot of their own.

Outputs (besides frame 0's single-capture outputs and report.html): ``frame_<i>.exr`` (the
application's layers of every frame), ``video.mp4`` (H.264 through imageio's ffmpeg plugin, the
ffmpeg binary of the imageio-ffmpeg package) and ``video.gif`` (an animated preview, imageio/Pillow),
both tone-mapped with one white level for the whole video (no exposure flicker), ``frames.csv``
(per-frame metrics) and report.json ``video`` (per frame, their summary, the comparisons).

Comparisons (``video.*``), for HDR applications:

Alternating-exposure HDR video (``video.compare_alternating``; Kang, Uyttendaele, Winder and
Szeliski, "High dynamic range video", SIGGRAPH 2003): a conventional sensor at the same frame rate
alternates a short exposure (the capture's shortest read, even frames) and a long one (its
longest, odd frames), each starting at the frame's start. Output frame i merges frame i with its
neighbours i-1 and i+1, each warped onto frame i by dense optical flow (OpenCV's DIS optical flow,
``video.flow``, on the exposure-normalized log luminance, neighbours' saturation flags warped
along) with the HDR merge of independent exposures (inverse variance,
:func:`mbcapture.reconstruct.hdr.merge_hdr`). Kang et al. refine the flow with a hierarchical
homography and use bidirectional interpolation; this is their scheme with an off-the-shelf flow.
Both videos are scored against the same truth per frame (the multi-bucket frame's: noise-free,
unclipped radiance over the frame's longest exposure).

Metrics: ghosting per frame (relMSE of the radiance against the truth inside the moving region,
and overall), and temporal consistency: sqrt(mean over consecutive frame pairs and pixels of
((L_i - L_(i-1)) - (T_i - T_(i-1)))^2) / mean T over the luminance L of the output and T of the
truth: frame-to-frame change that the scene did not have (noise, ghosts that pop in and out).

Temporal aliasing (``video.aliasing_rates_hz``, and the run's own rate): the needle's (the scene's
motion points') mean horizontal image position sampled at each frame's exposure centroid, over at
least ``ALIASING_PERIODS`` sampling periods of the slowest rate; its dominant frequency (zero-padded
FFT of the mean-removed samples) against the same motion sampled at 1 kHz. A rate below twice the
motion's frequency shows a slower, false swing (aliasing). At the run's own rate the position is
also measured from the rendered truth frames (the horizontal centroid of each truth frame's
difference from the frames' median luminance in the moving region) and correlated with the model's
track at the same times, which checks the model-based numbers.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field

import numpy as np

from ..timing import protocols
from ..apps.hdr import REL_MSE_EPS_RADIANCE
from ..config import scene_of
from ..output.io import encode_gif, encode_mp4, tonemapped_frames
from ..metrics import luminance, relative_mse
from .pipeline import capture_in_memory, frame_period_check, render_cache
from ..progress import StageStatus
from ..progress import bar as progress_bar
from ..reconstruct.hdr import merge_hdr
from ..render import Renderer, ensure_llvm
from ..sensor import dn_to_electrons
from ..exposure.simulate import capture_timeline
from ..timing.timeline import ReadEvent, SegmentSeconds, SlotSeconds, build_timeline, exact

#: Sampling periods of the slowest compared rate the aliasing analysis spans at least.
ALIASING_PERIODS = 24
#: Zero padding factor of the aliasing FFT.
FFT_PAD = 16


def frame_config(cfg, i: int, spp: int | None = None):
    """Frame ``i``'s config: one capture at start_s + i / frame_rate_hz with its own sensor noise seed."""
    c = cfg.capture
    start = c.start_s + i / c.frame_rate_hz
    noise = np.random.SeedSequence([cfg.seed if cfg.sensor.noise_seed is None else cfg.sensor.noise_seed, 0x71DE0, i])
    update = {
        "capture": c.model_copy(update={"frames": 1, "start_s": start}),
        "sensor": cfg.sensor.model_copy(update={"noise_seed": int(noise.generate_state(1)[0])}),
    }
    if spp is not None:
        update["render"] = cfg.render.model_copy(update={"spp": int(spp)})
    return cfg.model_copy(update=update)


# --------------------------------------------------------------------------- pure functions
def optical_flow(reference: np.ndarray, moving: np.ndarray, method: str) -> np.ndarray:
    """(H, W, 2) flow from ``reference`` to ``moving`` (both (H, W) float, any scale): pixel p of the
    reference matches p + flow(p) in ``moving``."""
    import cv2

    def u8(x):
        lo, hi = np.percentile(np.concatenate([reference.ravel(), moving.ravel()]), [0.5, 99.5])
        return np.clip((x - lo) / max(hi - lo, 1e-30) * 255, 0, 255).astype(np.uint8)

    a, b = u8(reference), u8(moving)
    if method == "farneback":
        return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 9, 5, 5, 1.1, 0)
    preset = {
        "dis_medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
        "dis_fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
        "dis_ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    }[method]
    dis = cv2.DISOpticalFlow_create(preset)
    return dis.calc(a, b, None)


def warp_by_flow(image: np.ndarray, flow: np.ndarray, nearest: bool = False) -> np.ndarray:
    """``image`` (H, W[, C]) sampled at p + flow(p): the moving image brought onto the reference."""
    import cv2

    H, W = flow.shape[:2]
    xx, yy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    mx, my = xx + flow[..., 0].astype(np.float32), yy + flow[..., 1].astype(np.float32)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    img = np.asarray(image, dtype=np.float32)
    out = cv2.remap(img, mx, my, interp, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(image.shape)


def log_luminance(rate: np.ndarray) -> np.ndarray:
    lum = luminance(rate)
    return np.log(np.maximum(lum, 1e-3 * max(float(np.percentile(lum, 99)), 1e-30)))


def alternating_merge(
    dn: list[np.ndarray], saturated: list[np.ndarray], exposure_s: np.ndarray, sensor, flow: str, i: int
) -> np.ndarray:
    """Rate (electrons/s, (H, W, C)) of output frame ``i`` of an alternating-exposure video: frame i's
    read merged with its neighbours' reads warped onto it by optical flow (module docstring)."""

    n = len(dn)
    rate = [dn_to_electrons(d, sensor) / t for d, t in zip(dn, exposure_s)]
    reads, sats, exps = [dn[i]], [saturated[i]], [exposure_s[i]]
    for j in (i - 1, i + 1):
        if 0 <= j < n:
            f = optical_flow(log_luminance(rate[i]), log_luminance(rate[j]), flow)
            reads.append(warp_by_flow(dn[j], f).astype(np.float64))
            sats.append(warp_by_flow(saturated[j].astype(np.float32), f, nearest=True) > 0.5)
            exps.append(exposure_s[j])
    res = merge_hdr(
        np.stack(reads),
        np.asarray(exps, float),
        sensor,
        method="inverse_variance",
        cumulative=False,
        saturated=np.stack(sats),
    )
    return res.rate_e_per_s


def temporal_consistency(output: np.ndarray, truth: np.ndarray) -> float | None:
    """sqrt(mean over consecutive pairs and pixels of ((L_i - L_i-1) - (T_i - T_i-1))^2) / mean T, on the
    luminance of ``output`` and ``truth`` (F, H, W, C); None for fewer than 2 frames."""

    if output.shape[0] < 2:
        return None
    lo, lt = luminance(output), luminance(truth)
    d = np.diff(lo, axis=0) - np.diff(lt, axis=0)
    return float(np.sqrt(np.mean(d**2)) / max(float(lt.mean()), 1e-300))


def dominant_frequency_hz(samples: np.ndarray, rate_hz: float) -> float:
    """Frequency (Hz) of the largest peak of the zero-padded spectrum of the mean-removed ``samples``."""
    x = np.asarray(samples, float) - np.mean(samples)
    n = FFT_PAD * len(x)
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x)), n))
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    return float(f[1:][np.argmax(spec[1:])])


def needle_track(scene, times_s: np.ndarray, width: int, height: int) -> np.ndarray:
    """(T,) the mean horizontal image position (px) of the scene's motion points at ``times_s``."""
    return scene.project(np.asarray(scene.motion_points(times_s)), times_s, width, height)[..., 0].mean(axis=1)


def aliasing(
    scene, rates_hz: list[float], t0_s: float, centroid_s: float, duration_s: float, width: int, height: int
) -> dict:
    """Per rate: the motion's apparent (sampled at the frames' centroids) and true dominant frequency."""
    if scene.motion_points is None:
        return {"note": "the scene has no moving parts"}
    span = max(duration_s, ALIASING_PERIODS / min(rates_hz))
    dense = t0_s + centroid_s + np.arange(0.0, span, 1e-3)
    true_f = dominant_frequency_hz(needle_track(scene, dense, width, height), 1e3)
    resolution = 1.0 / span
    out = {"true_frequency_hz": true_f, "analysis_span_s": span, "frequency_resolution_hz": resolution, "rates": {}}
    for r in sorted(set(rates_hz)):
        t = t0_s + centroid_s + np.arange(int(np.floor(span * r)) + 1) / r
        f = dominant_frequency_hz(needle_track(scene, t, width, height), r)
        out["rates"][f"{r:g}"] = {
            "frame_rate_hz": r,
            "samples": int(t.size),
            "apparent_frequency_hz": f,
            "aliased": bool(abs(f - true_f) > 2 * resolution),
            "nyquist_hz": r / 2,
        }
    return out


def measured_track(truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(F,) horizontal centroid (px) of each truth frame's departure from the frames' median
    luminance inside ``mask`` (H, W): where the moving part is in each frame."""

    lum = luminance(truth)
    dev = np.abs(lum - np.median(lum, axis=0)[None]) * mask[None]
    xs = np.arange(lum.shape[2]) + 0.5
    w = dev.sum(axis=1)  # (F, W)
    return (w * xs).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-300)


# --------------------------------------------------------------------------- run
@dataclass
class VideoFrames:
    """What a video run adds to its first frame's :class:`~mbcapture.capture.pipeline.CaptureResult`."""

    frames: list = field(default_factory=list)  # CaptureResult per frame
    alternating_radiance: np.ndarray | None = None  # (F, H, W, C)
    truth: np.ndarray | None = None  # (F, H, W, C)
    radiance: np.ndarray | None = None  # (F, H, W, C)
    white: float = 1.0


def _hdr_like(result) -> bool:
    return {"radiance", "truth"} <= set(result.images)


def run_video(cfg, *, progress: bool = True):
    """Run a video (``capture.frames`` > 1); returns frame 0's CaptureResult with ``video`` (a
    :class:`VideoFrames`) and report.json's ``video`` section. Nothing is written: run_capture
    writes the outputs, with :func:`write_video_files`."""
    timeline = protocols.build(cfg)
    period = frame_period_check(cfg, timeline)
    n = cfg.capture.frames
    if cfg.render.variant.startswith("llvm"):
        ensure_llvm()
    scene = scene_of(cfg)
    cache = render_cache(cfg.render)
    renderer = Renderer.from_config(scene, cfg, cache=cache)
    frames = []
    spp = None
    with progress_bar(total=n, desc="frames", unit="frame", enabled=progress) as bar:
        for i in range(n):
            fcfg = frame_config(cfg, i, spp)
            with StageStatus(False) as status:
                res = capture_in_memory(fcfg, status, renderer=renderer)
            if spp is None and cfg.render.spp is None:
                spp = int(res.plan.spp.max())
            frames.append(res)
            bar.update(1)
    first = frames[0]
    video = VideoFrames(frames=frames)
    report = _video_report(cfg, frames, video, period, scene, renderer, progress)
    first.report["video"] = report
    if cache is not None:
        first.report["render_cache"] = {"folder": str(cache.root), **cache.stats.as_dict()}
    first.report["timings_s"]["video_total_before_write"] = round(
        sum(f.report["timings_s"]["total_before_write"] for f in frames), 4
    )
    first.video = video
    first.app_output.summary[:0] = _summary_lines(report)
    return first


def _video_report(cfg, frames, video: VideoFrames, period: float, scene, renderer, progress: bool) -> dict:
    n = len(frames)
    W, H = cfg.render.width, cfg.render.height
    per_frame = []
    for i, f in enumerate(frames):
        row = {"frame": i, "start_s": float(f.config.capture.start_s)}
        row.update(
            {k: v for k, v in f.report["metrics"].items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        )
        per_frame.append(row)
    rep: dict = {
        "frames": n,
        "frame_rate_hz": cfg.capture.frame_rate_hz,
        "frame_period_s": period,
        "capture_span_s": frames[0].report["capture_span_s"],
        "readout_s": cfg.sensor.frame_readout_s,
        "duty_cycle": frames[0].report["capture_span_s"] / period,
        "render_passes": int(sum(f.plan.passes for f in frames)),
        "per_frame": per_frame,
    }
    hdr = all(_hdr_like(f) for f in frames)
    if hdr:
        video.radiance = np.stack([f.images["radiance"] for f in frames])
        video.truth = np.stack([f.images["truth"] for f in frames])
        masks = np.stack([f.moving_mask for f in frames])
        rep["multi_bucket"] = _scores(video.radiance, video.truth, masks, REL_MSE_EPS_RADIANCE, relative_mse)
    vcfg = cfg.video
    if hdr and vcfg.compare_alternating and len(frames[0].timeline.reads) >= 2:
        exps = [r["exposure_s"] for r in frames[0].report["reads"]]
        short, long = min(exps), max(exps)
        k_e = np.asarray(list(frames[0].report["electrons_per_render_unit_second"].values()))

        dns, sats, ex = [], [], []
        for i, f in enumerate(frames):
            t_exp = short if i % 2 == 0 else long
            start = exact(f.config.capture.start_s)
            tl = build_timeline(
                [SegmentSeconds(start, (SlotSeconds(0, exact(t_exp)),), 1)],
                [ReadEvent("frame", (0,), destructive=True)],
                1,
                "alternating_exposure",
                sequential=True,
            )
            seed = np.random.SeedSequence([cfg.seed, 0xA17E, i])
            sim = capture_timeline(tl, renderer.scene_model, f.config, renderer, int(f.plan.spp.max()), seed, k_e)
            dns.append(sim.reads_dn[0])
            sats.append(sim.saturated[0])
            ex.append(sim.exposure_s[0])
        ex = np.asarray(ex)
        alt = np.stack([alternating_merge(dns, sats, ex, cfg.sensor, vcfg.flow, i) / k_e for i in range(n)])
        video.alternating_radiance = alt
        rep["alternating_exposure"] = {
            "short_exposure_s": short,
            "long_exposure_s": long,
            "flow": vcfg.flow,
            **_scores(alt, video.truth, masks, REL_MSE_EPS_RADIANCE, relative_mse),
        }
        for i, row in enumerate(per_frame):
            row["alternating_exposure_s"] = float(ex[i])
            row["alternating_rel_mse"] = rep["alternating_exposure"]["rel_mse_per_frame"][i]
            row["alternating_rel_mse_moving"] = rep["alternating_exposure"]["rel_mse_moving_per_frame"][i]
    reads = frames[0].report["reads"]
    longest = max(reads, key=lambda r: r["exposure_s"])
    centroid = longest["centroid_s"] - float(frames[0].config.capture.start_s)
    rates = [cfg.capture.frame_rate_hz, *vcfg.aliasing_rates_hz]
    al = aliasing(scene, rates, float(cfg.capture.start_s), centroid, n * period, W, H)
    if hdr and scene.motion_points is not None and n >= 4:
        mask = np.any(np.stack([f.moving_mask for f in frames]), axis=0)
        track = measured_track(video.truth, mask)
        times = np.array([float(f.config.capture.start_s) for f in frames]) + centroid - float(cfg.capture.start_s)
        model = needle_track(scene, float(cfg.capture.start_s) + times, W, H)
        corr = float(np.corrcoef(track, model)[0, 1]) if np.std(track) > 0 and np.std(model) > 0 else None
        al["measured_at_run_rate"] = {
            "frame_rate_hz": cfg.capture.frame_rate_hz,
            "track_px": track.tolist(),
            "model_track_px": model.tolist(),
            "correlation_with_model": corr,
        }
    rep["aliasing"] = al
    if video.truth is not None:
        video.white = float(np.percentile(luminance(video.truth), cfg.output.png_percentile)) or 1.0
    return rep


def _scores(radiance: np.ndarray, truth: np.ndarray, masks: np.ndarray, eps: float, relative_mse) -> dict:
    all_ = [relative_mse(radiance[i], truth[i], eps=eps) for i in range(len(radiance))]
    moving = [
        relative_mse(radiance[i], truth[i], mask=np.repeat(masks[i][..., None], radiance.shape[-1], -1), eps=eps)
        if masks[i].any()
        else None
        for i in range(len(radiance))
    ]
    mv = [m for m in moving if m is not None]
    return {
        "rel_mse_per_frame": all_,
        "rel_mse_moving_per_frame": moving,
        "rel_mse_mean": float(np.mean(all_)),
        "ghosting_rel_mse_moving_mean": float(np.mean(mv)) if mv else None,
        "ghosting_rel_mse_moving_max": float(np.max(mv)) if mv else None,
        "temporal_consistency": temporal_consistency(radiance, truth),
    }


def _summary_lines(rep: dict) -> list[str]:
    out = [
        f"video: {rep['frames']} frames at {rep['frame_rate_hz']:g} frames/s (capture {rep['capture_span_s'] * 1e3:.4g} ms "
        f"+ readout {rep['readout_s'] * 1e3:.4g} ms per {rep['frame_period_s'] * 1e3:.4g} ms frame)"
    ]
    for key, label in (
        ("multi_bucket", "multi-bucket HDR video"),
        ("alternating_exposure", "alternating-exposure video"),
    ):
        s = rep.get(key)
        if s and s["ghosting_rel_mse_moving_mean"] is not None:
            out.append(
                f"{label}: ghosting (relMSE in the moving region) mean {s['ghosting_rel_mse_moving_mean']:.4g}, "
                f"max {s['ghosting_rel_mse_moving_max']:.4g}; temporal consistency {s['temporal_consistency']:.4g}"
            )
    al = rep.get("aliasing", {})
    for r in al.get("rates", {}).values():
        out.append(
            f"{r['frame_rate_hz']:g} frames/s: the motion appears at {r['apparent_frequency_hz']:.3g} Hz (true "
            f"{al['true_frequency_hz']:.3g} Hz){': aliased' if r['aliased'] else ''}"
        )
    return out


# --------------------------------------------------------------------------- files
def write_video_files(st, result) -> None:
    """frame_<i>.exr, video.mp4, video.gif, compare.gif (truth | multi-bucket | alternating) and
    frames.csv into the staging folder ``st``."""
    video: VideoFrames = result.video
    cfg = result.config
    fps = cfg.video.playback_fps or cfg.capture.frame_rate_hz
    for i, f in enumerate(video.frames):
        st.write_exr(f"frame_{i:04d}.exr", f.app_output.images)
    rep = result.report["video"]
    if video.radiance is not None:
        frames_u8 = tonemapped_frames(video.radiance, video.white)
        st.write_bytes("video.mp4", encode_mp4(frames_u8, fps))
        st.write_bytes("video.gif", encode_gif(frames_u8, fps))
        panels = [tonemapped_frames(video.truth, video.white), frames_u8]
        if video.alternating_radiance is not None:
            panels.append(tonemapped_frames(video.alternating_radiance, video.white))
        st.write_bytes("compare.gif", encode_gif(np.concatenate(panels, axis=2), fps))
    buf = io.StringIO()
    keys = list(dict.fromkeys(k for row in rep["per_frame"] for k in row))
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for row in rep["per_frame"]:
        w.writerow(row)
    st.write_bytes("frames.csv", buf.getvalue().encode("utf-8"))
