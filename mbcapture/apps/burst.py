"""Back-to-back low-light burst: K equal exposures, one per bucket, aligned and averaged.

The paper (section 5): "A multi-bucket sensor can alternatively be used to capture multiple frames
of equal length back-to-back ... useful in low-light situation in which up to 4 handshake-free
images can be captured, and subsequently aligned-and-averaged ... Since the images are captured
back-to-back without losing time to image readout, image alignment is made much easier."

Protocol ``burst``: bucket k collects during [start + kT, start + (k+1)T), T =
``capture.unit_exposure_s``, for k = 0..K-1 (K = ``sensor.bucket_count``), once (``capture.periods``
must be 1: repeating the pattern would interleave the frames, and every frame would see the same
shake); each bucket is read directly (reads F1..FK). ``capture.sequential: true`` is the
conventional burst: the same K frames one after another with ``sensor.frame_readout_s`` between
them, so the camera shakes on during each readout gap.

Reconstruction (``app.method``, :data:`ALIGN_METHODS`): each frame's rate (electrons per second) is
registered to the reference frame (``app.reference``) on its luminance, warped onto it (bilinear)
and averaged over the frames that cover each pixel unsaturated:

``ecc_euclidean``   OpenCV's ``findTransformECC`` (enhanced correlation coefficient, Evangelidis &
                    Psarakis 2008), rotation + translation; the frames are smoothed by
                    ``app.ecc_blur_px`` first (they are noisy)
``ecc_homography``  the same with a homography (what a camera rotation does to the image exactly)
``phase_correlation`` OpenCV's ``phaseCorrelate`` (translation only, Hanning window)
``none``            no alignment: the plain mean (what shake does to an unaligned average)

Comparison at equal total exposure K T (``app.compare``, in report.json ``metrics.comparison``), all
simulated from the same scene, camera trajectory, sensor and samples per pixel, the run's own
capture being one of the first two:

``back_to_back``        the multi-bucket burst (this protocol)
``conventional_burst``  the K frames with readout gaps (``capture.sequential: true``)
``long_exposure``       one frame of K T on a conventional sensor (motion blur instead of noise)

Truth: the scene rendered with a still camera (the scene's nominal pose, no shake) at the capture's
middle time, ``app.reference_spp`` samples per pixel, in radiance (W m^-2 sr^-1). Each result is
radiance = rate / k_e; to score it, it is registered onto the truth with ECC (euclidean; a result
sits where its reference frame was, and that offset is not what is compared), resampled bicubically,
and a border of
``ceil(largest shift) + 2`` px is left out. Metrics per result:

``psnr_db``                 PSNR of the luminance, peak = the truth's 99.9th percentile luminance
``rel_mse``                 relative MSE of the RGB radiance (eps as the HDR application's)
``residual_blur_px``        sigma of the Gaussian blur that best maps the truth onto the result
                            (least squares over sigma in [0, 8] px, scipy ``minimize_scalar``)
``motion_blur_px``          mean over frames of how far the frame moved during its own exposure
                            (:func:`mbcapture.scene.camera_motion.frame_motion_px`, from the trajectory)
``registration_error_px``   per frame: RMS over a 3 x 3 grid of image points (at the camera's target
                            distance) of the estimated warp's position minus the true one, the true
                            correspondence being each point's mean image position over each frame's
                            exposure (from the trajectory); and their mean
``shake_between_frames_px`` per frame: RMS displacement of those mean positions from the reference
                            frame's: what the alignment has to undo
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..strict import StrictModel
from ..timing import protocols
from ..scene.camera_motion import frame_motion_px, reference_points, still
from ..errors import ConfigError
from ..metrics import luminance, psnr, relative_mse
from ..reconstruct.register import ALIGN_METHODS, align_and_average, fit_blur_px, register_to_truth, registration_errors
from ..render import Renderer
from ..exposure.simulate import capture_timeline
from ..timing.timeline import ReadEvent, SegmentSeconds, SlotSeconds, build_timeline, exact
from . import AppOutput, CaptureData, register, register_protocol
from .hdr import REL_MSE_EPS_RADIANCE

#: Points per axis of the grid on which registration error is measured.
GRID = 3
#: Times at which a frame's exposure is sampled for its mean image positions.
EXPOSURE_SAMPLES = 33

CAPTIONS = {
    "average": "the run's own burst, aligned (app.method) and averaged, radiance, tone-mapped",
    "truth": "truth: the scene through a still camera (no shake), noise-free",
    "reference_frame": "the reference frame alone (one exposure T): what averaging improves on",
    "unaligned_average": "the frames averaged without alignment: shake between frames blurs it",
    "long_exposure": "one long exposure of K T on a conventional sensor: shake during it blurs it",
    "other_burst": "the other burst (conventional if this run is back-to-back, and vice versa), aligned and averaged",
}


@register_protocol("burst", app="burst")
def burst_protocol(cfg):
    """K equal exposures T back to back, one per bucket, each read directly (F1..FK)."""
    if cfg.capture.periods != 1:
        raise ConfigError(
            f"capture.periods: the 'burst' protocol takes its frames back to back once (capture.periods "
            f"must be 1, got {cfg.capture.periods}: repeating the pattern would interleave the frames)"
        )
    k = cfg.sensor.bucket_count
    if k < 2:
        raise ConfigError(f"capture.protocol: 'burst' needs at least 2 buckets, sensor.bucket_count is {k}")
    T = exact(cfg.capture.unit_exposure_s)
    return [SlotSeconds(b, T) for b in range(k)], [ReadEvent(f"F{b + 1}", (b,)) for b in range(k)], k


class BurstParams(StrictModel):
    method: Literal["ecc_euclidean", "ecc_homography", "phase_correlation", "none"] = Field(
        "ecc_euclidean",
        description="Registration of each frame onto the reference: ecc_euclidean, ecc_homography "
        "(OpenCV findTransformECC), phase_correlation (OpenCV phaseCorrelate, translation) or none (plain mean).",
    )
    reference: Literal["first", "middle"] = Field(
        "middle", description="The frame the others are aligned to: the first, or the middle one (frame (K-1)//2 + 1)."
    )
    ecc_blur_px: int = Field(
        5, ge=1, le=31, description="Gaussian filter size (odd, px) ECC smooths the noisy frames with."
    )
    reference_spp: int = Field(128, ge=1, le=1 << 14, description="Samples per pixel of the still-camera truth render.")
    compare: bool = Field(
        True,
        description="Also simulate the other burst (conventional <-> back-to-back) and the long exposure at "
        "equal total exposure, and score all three (metrics.comparison).",
    )


def border_for(shift_px: float) -> int:
    """Pixels left out at each edge when scoring a result registered with a shift of ``shift_px``."""
    return int(np.ceil(shift_px)) + 2


def score_registered(on: np.ndarray, truth: np.ndarray, border: int) -> dict:
    """psnr_db, rel_mse, residual_blur_px of a registered result against ``truth`` without ``border`` px
    at each edge (the module docstring)."""
    H, W = truth.shape[:2]
    sl = (slice(border, H - border), slice(border, W - border))
    if H - 2 * border < 4 or W - 2 * border < 4:
        sl = (slice(None), slice(None))
    r, t = on[sl], truth[sl]
    ok = np.isfinite(r).all(axis=-1)
    lr, lt = luminance(np.where(ok[..., None], r, 0.0)), luminance(t)
    peak = float(np.percentile(lt, 99.9)) or 1.0
    return {
        "psnr_db": psnr(lr[ok], lt[ok], peak=peak),
        "rel_mse": relative_mse(r[ok], t[ok], eps=REL_MSE_EPS_RADIANCE),
        "residual_blur_px": fit_blur_px(np.where(ok, lr, lt), lt),
    }


def score(result: np.ndarray, truth: np.ndarray, blur: int = 5, border: int | None = None) -> dict:
    """Register ``result`` (H, W, C radiance) onto ``truth``, leave out ``border`` px at each edge (default:
    from its own shift) and return psnr_db, rel_mse, residual_blur_px, the scoring shift and border."""
    on, shift = register_to_truth(result, truth, blur)
    border = border_for(shift) if border is None else border
    return {**score_registered(on, truth, border), "scoring_shift_px": shift, "scoring_border_px": border}


# --------------------------------------------------------------------------- glue
def mean_positions(scene, timeline, width: int, height: int) -> np.ndarray:
    """(R, GRID^2, 2) each read's mean image position (over its exposure's collecting time) of the
    camera's GRID x GRID reference points at its target distance (from the camera trajectory)."""

    pts = reference_points(scene.camera, width, height)[1::3]  # the target-distance ones
    out = []
    for r in timeline.reads:
        a, b = timeline.span_ticks(r.buckets)
        t = np.linspace(float(timeline.seconds(a)), float(timeline.seconds(b)), EXPOSURE_SAMPLES)
        px = scene.project(np.broadcast_to(pts, (t.size, *pts.shape)), t, width, height)
        out.append(px.mean(axis=0))
    return np.stack(out)


def frame_blur_px(scene, timeline, width: int, height: int) -> np.ndarray:
    """(R,) how far the frame moved during each read's own exposure (px)."""

    out = []
    for r in timeline.reads:
        a, b = timeline.span_ticks(r.buckets)
        out.append(
            frame_motion_px(
                scene,
                np.linspace(float(timeline.seconds(a)), float(timeline.seconds(b)), EXPOSURE_SAMPLES),
                width,
                height,
            )
        )
    return np.array(out)


def child_seed(seed: np.random.SeedSequence, i: int) -> np.random.SeedSequence:
    """The i-th independent child of ``seed``, the same whatever else was spawned from it."""
    return np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, 0xB0, i))


def reference_index(params: BurstParams, k: int) -> int:
    return 0 if params.reference == "first" else (k - 1) // 2


def still_truth(data: CaptureData, params: BurstParams) -> tuple[np.ndarray, float]:
    """(H, W, C) radiance through a still camera at the capture's middle time, and that time."""

    tl = data.timeline
    t_mid = float(tl.seconds((tl.start_tick + tl.end_tick) // 2))
    scene = still(data.scene)
    renderer = (
        data.renderer
        if scene is data.scene
        else Renderer.from_config(scene, data.cfg, cache=getattr(data.renderer, "cache", None))
    )
    seed = int(np.random.default_rng(child_seed(data.seed, 0)).integers(0, 2**31 - 1))
    img = renderer.render(t_mid, params.reference_spp, seed, list(data.plan.groups)).astype(np.float64)
    return img.sum(axis=0), t_mid


def _burst_result(
    name: str,
    rates: np.ndarray,
    saturated: np.ndarray,
    timeline,
    data: CaptureData,
    params: BurstParams,
    truth: np.ndarray,
) -> tuple[dict, dict[str, np.ndarray]]:
    W, H = data.cfg.render.width, data.cfg.render.height
    ref = reference_index(params, rates.shape[0])
    aligned = align_and_average(rates, saturated, params.method, ref, params.ecc_blur_px)
    radiance = aligned.average / data.k_e
    true_pos = mean_positions(data.scene, timeline, W, H)
    reg = registration_errors(aligned.warps, true_pos, ref)
    between = np.sqrt(np.mean(np.sum((true_pos - true_pos[ref]) ** 2, axis=-1), axis=-1))
    names = [r.name for r in timeline.reads]
    span = timeline.seconds(timeline.end_tick - timeline.start_tick)
    out = {
        "capture_span_s": float(span),
        "motion_blur_px": float(frame_blur_px(data.scene, timeline, W, H).mean()),
        "registration_error_px": dict(zip(names, reg.tolist())),
        "registration_error_px_mean": float(np.mean(np.delete(reg, ref))),
        "shake_between_frames_px": dict(zip(names, between.tolist())),
    }
    images = {
        "average": radiance,
        "unaligned_average": rates.mean(axis=0) / data.k_e,
        "reference_frame": rates[ref] / data.k_e,
    }
    return out, images


@register(
    "burst",
    output_channels=18,
    previews=6,
    libraries_mb=200,
    memory_scale=1.19,
    params=BurstParams,
    description="back-to-back burst aligned and averaged; vs a conventional burst and one long exposure",
)
def reconstruct(data: CaptureData, params: BurstParams) -> AppOutput:
    cfg = data.cfg
    if data.exposure_s.size < 2 or not np.allclose(data.exposure_s, data.exposure_s[0]):
        raise ConfigError(
            f"app.name: 'burst' aligns equal exposures (capture.protocol 'burst'), got exposures "
            f"{data.exposure_s.tolist()} s"
        )
    K, T = data.exposure_s.size, float(data.exposure_s[0])
    truth, t_mid = still_truth(data, params)
    own = "conventional_burst" if data.sequential else "back_to_back"
    rates = data.reads_e() / data.exposure_s[:, None, None, None]
    own_metrics, own_images = _burst_result(own, rates, data.saturated, data.timeline, data, params, truth)
    comparison = {own: own_metrics}
    images = {**own_images, "truth": truth}
    png = {
        "average": ("average", cfg.output.png_percentile),
        "truth": ("truth", cfg.output.png_percentile),
        "reference_frame": ("reference_frame", cfg.output.png_percentile),
        "unaligned_average": ("unaligned_average", cfg.output.png_percentile),
    }
    if params.compare:
        spp = int(data.plan.spp.max())
        seeds = [child_seed(data.seed, 1), child_seed(data.seed, 2)]
        twin_cfg = cfg.model_copy(
            update={"capture": cfg.capture.model_copy(update={"sequential": not data.sequential})}
        )
        twin = capture_timeline(protocols.build(twin_cfg), data.scene, cfg, data.renderer, spp, seeds[0], data.k_e)
        other = "back_to_back" if data.sequential else "conventional_burst"
        comparison[other], twin_images = _burst_result(
            other, twin.rate_e_per_s, twin.saturated, twin.timeline, data, params, truth
        )
        images["other_burst"] = twin_images["average"]
        start = exact(cfg.capture.start_s)
        long_tl = build_timeline(
            [SegmentSeconds(start, (SlotSeconds(0, exact(T) * K),), 1)],
            [ReadEvent("long", (0,), destructive=True)],
            1,
            "burst_long_exposure",
            sequential=True,
        )
        long = capture_timeline(long_tl, data.scene, cfg, data.renderer, spp, seeds[1], data.k_e)
        W, H = cfg.render.width, cfg.render.height
        long_rad = long.rate_e_per_s[0] / data.k_e
        comparison["long_exposure"] = {
            "capture_span_s": K * T,
            "motion_blur_px": float(frame_blur_px(data.scene, long_tl, W, H)[0]),
            "saturated_fraction": float(long.saturated.mean()),
        }
        images["long_exposure"] = long_rad
        png["long_exposure"] = ("long_exposure", cfg.output.png_percentile)
        png["other_burst"] = ("other_burst", cfg.output.png_percentile)
    # every result scored on the same pixels: registered onto the truth, then the largest border of all
    results = {own: images["average"]}
    if params.compare:
        results.update(
            {
                ("back_to_back" if data.sequential else "conventional_burst"): images["other_burst"],
                "long_exposure": images["long_exposure"],
            }
        )
    registered = {name: register_to_truth(img, truth, params.ecc_blur_px) for name, img in results.items()}
    border = max(border_for(shift) for _, shift in registered.values())
    for name, (on, shift) in registered.items():
        comparison[name].update(
            {**score_registered(on, truth, border), "scoring_shift_px": shift, "scoring_border_px": border}
        )
    metrics = {
        "method": params.method,
        "alignment": ALIGN_METHODS[params.method],
        "reference_frame": data.read_names[reference_index(params, K)],
        "capture": own,
        "frames": K,
        "frame_exposure_s": T,
        "total_exposure_s": K * T,
        "camera_motion": data.scene.camera_motion.label if data.scene.camera_motion is not None else "still",
        "truth": f"still camera (no shake) at scene time {t_mid:.6g} s, {params.reference_spp} spp",
        "comparison": comparison,
    }
    summary = [
        f"{name}: PSNR {m['psnr_db']:.2f} dB, residual blur {m['residual_blur_px']:.2f} px"
        + (
            f", registration error {m['registration_error_px_mean']:.2f} px"
            if "registration_error_px_mean" in m
            else ""
        )
        for name, m in comparison.items()
    ]
    return AppOutput(images=images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)
