"""Multi-flash photography: a shadow-free image and depth edges (Raskar et al. 2004; the paper's 5.3).

Protocol ``multi_flash``
    Four LED groups around the lens (``flash_top``, ``flash_bottom``, ``flash_left``,
    ``flash_right``), each synced with one bucket: per period, bucket 1 collects for T/N with the
    top LED on, bucket 2 with the bottom one, bucket 3 left, bucket 4 right (T =
    ``capture.unit_exposure_s``, N = ``capture.periods``); each bucket is read directly (reads
    ``top``, ``bottom``, ``left``, ``right``). When ``sensor.bucket_count`` >= 5 a fifth slot of
    T/N with every LED off fills bucket 5 (read ``ambient``): Raskar's ambient image I_0, taken
    interleaved with the flash images. ``capture.sequential: true`` takes the same 4 (5) images
    one after another on a conventional sensor.

Ambient handling (``app.ambient``)
    ``auto``: subtract the ambient read from every flash read when the capture has one, else
    keep the ambient light in the flash images. ``subtract``: require the ambient read.
    ``none``: never subtract (the paper's quad-bucket setup: a weak ambient only lifts the
    shadows' ratio from ~0 to A/(A+F)). A min composite is not used as the ambient estimate: it
    holds the dimmest flash's light wherever no LED is shadowed, so subtracting it would erase
    the ratios. All images are in radiance units, W m^-2 sr^-1 during the flash:
    read electrons / (k_e * exposure).

Reconstruction (``app.method``; :data:`DEPTH_EDGE_METHODS`)
    ``raskar2004``: the shadow-free image is the max composite I_max = max_k I_k (per channel).
    Each flash image's luminance is divided by I_max's (ratio R_k, ~1 where LED k lights the
    surface, ~0 in its shadow). R_k is traversed along epipolar lines away from LED k's epipole
    (the projection of the LED centre; for an LED in the lens plane it is at infinity in the LED's
    image direction, so the lines are rows or columns): a pixel p is a depth edge of flash k when
    the drop R_k(p) - R_k(p + s d) (d: one pixel further from the epipole, s =
    ``app.step_span_px``) exceeds ``app.step_threshold`` and is the largest drop of its three
    neighbours along the line (non-maximum suppression; on a sharp step it marks the last lit
    pixel, the occluding side), with both pixels valid (I_max above ``app.min_signal_fraction`` of its
    99th percentile, no read saturated). Depth edges are the union over flashes; they lie on the
    occluding (near) side of the discontinuity.
    ``canny_max_composite``: a baseline without the flashes' geometry: OpenCV Canny edges of the
    max composite (texture and shading edges included), to show what the ratios add.

    Fair comparisons: every interleaved bucket collects in every render stratum, so its image
    averages passes x ``render.spp`` samples; a sequential frame lies in one stratum and gets
    ``render.spp`` only. Give the sequential run ``render.spp`` x (the interleaved run's passes,
    ``mbcapture plan``) so both captures carry the same rendering noise and differ by motion only.

    Known limitation of the ratio test (seen in the shipped scene): a face lit at grazing incidence
    by one LED (the top face of a box seen from above, lit by the LED below the lens) has a low
    ratio too, so its crease with the front face is marked although its depth is continuous.

Ground truth and metrics
    Depth from Mitsuba's ``aov`` integrator (:mod:`mbcapture.render.aov`) at pixel centres:
    a pixel is a true depth edge when a 4-neighbour's depth differs by more than
    ``app.truth_depth_jump`` of the nearer depth and it is the nearer one. ``app.truth_time``:
    ``mid`` (default) takes the scene at the capture's mid-time, the instant the interleaved
    buckets are all centred on and the middle of the sequential frames: one answer for both
    captures, so the comparison is fair; ``strata_union`` is the union over the render strata's
    times (every position the moving edges held; lenient towards long captures). Precision: the
    fraction of detected pixels within ``app.tolerance_px`` of a true edge pixel; recall: the
    fraction of true edge pixels within that distance of a detected one (Euclidean distance
    transform); F1 their harmonic mean; over the image and over the capture's moving region.
    Shadow-free truth: the max composite of the flash groups rendered noise-free at the
    mid-time (plus the ambient group when it is not subtracted). Residual shadow: over pixels
    shadowed in some truth flash image (ratio below ``app.shadow_ratio``), the fraction where the
    shadow-free image is below half the truth, and the mean darkening max(0, 1 - I/I_truth).
    ``per_light``: each flash image's normalised RMS error (RMS error / mean truth) against its
    noise-free truth (``mean_nrmse``, and ``mean_nrmse_moving`` over the moving region).
    ``normals``: photometric-stereo normals from the flash images (near-light Lambertian fit at the
    true depth, :mod:`mbcapture.reconstruct.photometric`), their angular error against the normal
    AOV over pixels whose 3x3 neighbourhood is surface off the true depth edges (``median_deg``,
    ``mean_deg``, ``p90_deg``, ``median_deg_moving``).

Coded captures (``capture.gate_code``, docs/coded_gates.md)
    With per-pixel gates the reads ``B1``, ``B2`` hold each pixel's own mix of the sub-frames: the
    sub-frame images are demultiplexed first (:mod:`mbcapture.reconstruct.demultiplex`: local least
    squares over a tent window the size of the code's tile, ``app.demux_radius_px``; by default
    edge-aware, ``app.demux_method: guided``, neighbours weighted by how alike their total light is)
    and take the place of the reads; pixels whose window holds a saturated read are left out.
    ``coded_gates`` in the metrics says how (family, tile, window, per-sub-frame noise gain).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Callable, Literal

import numpy as np
from pydantic import Field

from ..strict import StrictModel
from ..errors import ConfigError
from ..metrics import luminance, nrmse, relative_mse
from ..scene.projective import points_from_depth
from ..reconstruct.depth_edges import (
    signal_valid,
    DepthEdges,
    canny_edges,
    depth_discontinuities,
    edge_scores,
    epipole,
    max_composite,
    raskar_depth_edges,
)
from ..reconstruct.demultiplex import code_rank, demultiplex, demultiplex_guided
from ..reconstruct.photometric import angular_error_deg, near_light_normals
from ..render.aov import render_depth, render_normals
from ..timing.timeline import ReadEvent, SlotSeconds, Timeline, exact
from . import AppOutput, CaptureData, register, register_protocol

#: Flash groups in bucket order, and the read names of the protocol.
FLASH_GROUPS = ("flash_top", "flash_bottom", "flash_left", "flash_right")
AMBIENT_READ = "ambient"

#: relMSE floor for radiance images (W m^-2 sr^-1)^2: about 0.1 x the darkest lit surfaces.
REL_MSE_EPS_RADIANCE = 1e-3


# --------------------------------------------------------------------------------- protocol
@register_protocol("multi_flash", app="multi_flash")
def multi_flash_protocol(cfg):
    """Buckets 1-4: one LED group each for T/N per period; bucket 5 (if any): ambient only."""
    have = cfg.sensor.bucket_count
    if have < 4:
        raise ConfigError(f"capture.protocol: 'multi_flash' needs 4 buckets but sensor.bucket_count is {have}")
    k = 5 if have >= 5 else 4
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    slots = [SlotSeconds(b, T / N, frozenset({g})) for b, g in enumerate(FLASH_GROUPS)]
    reads = [ReadEvent(g.removeprefix("flash_"), (b,)) for b, g in enumerate(FLASH_GROUPS)]
    if k == 5:
        slots.append(SlotSeconds(4, T / N))
        reads.append(ReadEvent(AMBIENT_READ, (4,)))
    return slots, reads, k


# --------------------------------------------------------------------------------- params
class MultiFlashParams(StrictModel):
    method: str = Field(
        "raskar2004",
        description="Depth-edge method: raskar2004 (ratio images traversed away from "
        "each flash's epipole) or canny_max_composite (baseline: Canny on the max composite).",
    )
    ambient: Literal["auto", "subtract", "none"] = Field(
        "auto",
        description="Ambient light: 'auto' subtracts the ambient-only read when the capture has one "
        "(sensor.bucket_count >= 5), 'subtract' requires it, 'none' keeps the ambient in the flash images.",
    )
    step_threshold: float = Field(
        0.35,
        gt=0.0,
        lt=1.0,
        description="raskar2004: smallest drop of a ratio image "
        "R(p) - R(p + s d) (dimensionless; s = step_span_px, d one pixel away from the "
        "epipole) that marks a depth edge.",
    )
    step_span_px: int = Field(
        2,
        ge=1,
        le=8,
        description="raskar2004: s, the distance (px) over which the ratio's drop "
        "is measured: 2 also catches shadows that begin over two pixels (curved silhouettes at "
        "grazing light); the edge of a shadow narrower than s is marked up to s - 1 px early.",
    )
    smooth_px: float = Field(
        0.0,
        ge=0.0,
        le=5.0,
        description="raskar2004: Gaussian sigma (px) applied to each "
        "flash image's luminance before the ratios (0: none).",
    )
    min_signal_fraction: float = Field(
        0.03,
        ge=0.0,
        lt=1.0,
        description="Pixels whose max-composite luminance is "
        "below this fraction of its 99th percentile carry no ratio (too dark).",
    )
    canny_low: float = Field(
        0.1,
        gt=0.0,
        lt=1.0,
        description="canny_max_composite: low hysteresis threshold as a "
        "fraction of the largest gradient of the tone-mapped luminance.",
    )
    canny_high: float = Field(
        0.25, gt=0.0, le=1.0, description="canny_max_composite: high hysteresis threshold, same units."
    )
    truth_depth_jump: float = Field(
        0.05,
        gt=0.0,
        lt=10.0,
        description="Ground truth: relative depth jump "
        "|z1 - z2| / min(z1, z2) between 4-neighbours that makes a depth edge.",
    )
    truth_time: Literal["mid", "strata_union"] = Field(
        "mid",
        description="Ground-truth depth edges at the capture's mid-time ('mid') or the union over the "
        "render strata's times ('strata_union').",
    )
    tolerance_px: float = Field(
        1.5,
        ge=0.0,
        le=10.0,
        description="Precision/recall: a detected and a true edge pixel match within this distance, px.",
    )
    shadow_ratio: float = Field(
        0.5,
        gt=0.0,
        lt=1.0,
        description="Residual-shadow metric: a pixel is shadowed in a "
        "truth flash image when its luminance is below this fraction of the truth max composite.",
    )
    truth_spp: int = Field(
        0,
        ge=0,
        le=4096,
        description="Samples per pixel of the noise-free shadow-free truth "
        "render (0: 4 x the capture's largest samples per pixel per stratum, render.spp or the noise budget's).",
    )
    demux_radius_px: int = Field(
        0,
        ge=0,
        le=16,
        description="Coded captures (capture.gate_code): half-width of the tent "
        "window over which the per-light images are demultiplexed, px (0: the code's tile height "
        "and width; a random code: 2).",
    )
    demux_method: Literal["lsq", "guided"] = Field(
        "guided",
        description="Coded captures: 'lsq' (least squares over "
        "a tent window) or 'guided' (the same with edge-aware weights: "
        "neighbours whose total light differs are left out).",
    )
    demux_guide_sigma: float = Field(
        0.1,
        gt=0.0,
        le=10.0,
        description="Coded captures, demux_method 'guided': the "
        "relative difference of two pixels' total light at which a neighbour's weight "
        "falls to exp(-1/2).",
    )
    normals_shadow_ratio: float = Field(
        0.2,
        gt=0.0,
        lt=1.0,
        description="Photometric-stereo normals: a light whose "
        "image is below this fraction of the brightest at a pixel is left out there (shadow).",
    )


# --------------------------------------------------------------------------------- geometry
def flash_images(
    reads_e: np.ndarray, exposure_s: np.ndarray, k_e: np.ndarray, flash_reads: list[int], ambient_read: int | None
) -> np.ndarray:
    """(F, H, W, C) radiance of each flash read (W m^-2 sr^-1 while the flash was on), with the
    ambient read's radiance subtracted when ``ambient_read`` is given (exposures may differ)."""
    rad = np.asarray(reads_e, np.float64) / (
        np.asarray(k_e)[None, None, None, :] * np.asarray(exposure_s, np.float64)[:, None, None, None]
    )
    out = rad[flash_reads]
    if ambient_read is not None:
        out = out - rad[ambient_read][None]
    return out


def shadow_metrics(
    shadow_free: np.ndarray, truth_flash: np.ndarray, *, shadow_ratio: float = 0.5, min_signal_fraction: float = 0.03
) -> dict:
    """How much shadow the shadow-free image keeps, against noise-free truth flash images (F, H, W, C).

    Over the pixels shadowed in some truth image (luminance below ``shadow_ratio`` x the truth
    max composite's) where the truth max composite is lit: ``residual_shadow_fraction`` the
    fraction where ``shadow_free`` is below half the truth max composite, ``residual_shadow_mean``
    the mean of max(0, 1 - I / I_truth) (luminance)."""
    truth_max = max_composite(truth_flash)
    lt, lf = luminance(truth_max), luminance(shadow_free)
    lit = signal_valid(lt, min_signal_fraction, None)
    shadowed = lit & (luminance(truth_flash).min(axis=0) < shadow_ratio * lt)
    if not shadowed.any():
        return {"shadowed_px": 0}
    rel = lf[shadowed] / lt[shadowed]
    return {
        "shadowed_px": int(shadowed.sum()),
        "residual_shadow_fraction": float((rel < 0.5).mean()),
        "residual_shadow_mean": float(np.maximum(0.0, 1.0 - rel).mean()),
    }


def edges_overlay(base: np.ndarray, detected: np.ndarray, truth: np.ndarray | None, tolerance_px: float) -> np.ndarray:
    """(H, W, 3) linear preview: the base image's luminance dimmed to 0..0.25, detected edges that
    match a true edge green, unmatched detections red, missed true edges blue (no truth: white)."""
    from scipy.ndimage import distance_transform_edt

    lum = luminance(base)
    white = float(np.percentile(lum, 99)) or 1.0
    out = np.repeat((0.25 * np.clip(lum / white, 0, 1))[..., None], 3, -1)
    if truth is None:
        out[detected] = 1.0
        return out
    d_truth = distance_transform_edt(~truth) if truth.any() else np.full(truth.shape, np.inf)
    d_det = distance_transform_edt(~detected) if detected.any() else np.full(truth.shape, np.inf)
    out[truth & (d_det > tolerance_px)] = (0.1, 0.3, 1.0)
    out[detected & (d_truth <= tolerance_px)] = (0.1, 1.0, 0.1)
    out[detected & (d_truth > tolerance_px)] = (1.0, 0.1, 0.1)
    return out


# --------------------------------------------------------------------------------- methods
def _method_raskar(images, epipoles, bad, p: MultiFlashParams) -> DepthEdges:
    return raskar_depth_edges(
        images,
        epipoles,
        step_threshold=p.step_threshold,
        step_span_px=p.step_span_px,
        smooth_px=p.smooth_px,
        min_signal_fraction=p.min_signal_fraction,
        bad=bad,
    )


def _method_canny(images, epipoles, bad, p: MultiFlashParams) -> DepthEdges:
    e = canny_edges(max_composite(images), low=p.canny_low, high=max(p.canny_high, p.canny_low))
    return DepthEdges(edges=e, per_flash=e[None], ratios=None, valid=~bad)


#: Depth-edge methods: ``fn(flash images (F, H, W, C), epipoles, bad (H, W), params) -> DepthEdges``
#: (``ratios`` None for methods that do not form ratio images).
DEPTH_EDGE_METHODS: dict[str, Callable] = {"raskar2004": _method_raskar, "canny_max_composite": _method_canny}


def depth_edges(images, epipoles, bad, params: MultiFlashParams) -> DepthEdges:
    if params.method not in DEPTH_EDGE_METHODS:
        raise ConfigError(
            f"app.method: unknown depth-edge method {params.method!r}; expected one of {sorted(DEPTH_EDGE_METHODS)}"
        )
    return DEPTH_EDGE_METHODS[params.method](images, epipoles, bad, params)


# --------------------------------------------------------------------------------- capture glue
def read_groups(timeline: Timeline, read: ReadEvent) -> frozenset[str]:
    """Switchable groups lit while the buckets of ``read`` collected."""
    return frozenset(g for seg in timeline.segments for s in seg.slots if s.bucket in read.buckets for g in s.groups_on)


@dataclass
class Sources:
    """The images the flash images come from: the reads of a global-gate (or sequential) capture,
    or the sub-frame images demultiplexed from a coded capture's reads.

    names (N,), groups (N,) the switchable groups lit in each, electrons (N, H, W, C), exposure_s
    (N,), bad (N, H, W) no usable value there (a saturated read; a coded capture: a saturated
    read in the window, or codes that do not separate the sub-frames); demux: how a coded capture
    was demultiplexed (None otherwise)."""

    names: list[str]
    groups: list[frozenset[str]]
    electrons: np.ndarray
    exposure_s: np.ndarray
    bad: np.ndarray
    demux: dict | None = None


def _sources(data: CaptureData, params: MultiFlashParams) -> Sources:
    tl = data.timeline
    if tl.code is None or tl.code.identity:
        return Sources(
            list(data.read_names),
            [read_groups(tl, r) for r in tl.reads],
            data.reads_e(),
            np.asarray(data.exposure_s, np.float64),
            data.saturated.any(axis=-1),
        )
    # a coded capture: every pixel's reads are its own mix of the sub-frames; demultiplex them
    code, W, H = tl.code, data.cfg.render.width, data.cfg.render.height
    A = code.measurement([r.buckets for r in tl.reads], H, W)
    rank = code_rank(A)
    if rank < code.n_subframes:
        raise ConfigError(
            f"capture.gate_code: the {code.family!r} code's reads separate at most {rank} of the "
            f"{code.n_subframes} sub-frames; use a code whose pixels differ (one_hot, hadamard, random)"
        )
    if params.demux_radius_px:
        radius = (params.demux_radius_px, params.demux_radius_px)
    else:
        radius = (2, 2) if code.family == "random" else code.tile_shape
    sat_samples = data.saturated.any(axis=-1)
    d = (
        demultiplex(data.reads_e(), A, radius, bad=sat_samples)
        if params.demux_method == "lsq"
        else demultiplex_guided(data.reads_e(), A, radius, params.demux_guide_sigma, bad=sat_samples)
    )
    from scipy.ndimage import binary_dilation

    sat = data.saturated.any(axis=(0, -1))
    near_sat = binary_dilation(sat, np.ones((2 * radius[0] - 1, 2 * radius[1] - 1), bool)) if sat.any() else sat
    bad = np.broadcast_to(~d.valid | near_sat, (code.n_subframes, H, W))
    groups, exposure = [], []
    for c in range(code.n_subframes):
        groups.append(frozenset(g for seg in tl.segments for sl in seg.slots if sl.bucket == c for g in sl.groups_on))
        exposure.append(float(tl.gated_ticks([tl.end_tick], c)[0] * tl.tick_s))
    names = [
        next(iter(g)).removeprefix("flash_") if len(g) == 1 else (AMBIENT_READ if not g else f"subframe{c + 1}")
        for c, g in enumerate(groups)
    ]
    info = {
        "family": code.family,
        "tile": list(code.tile_shape),
        "subframes": code.n_subframes,
        "buckets": code.n_buckets,
        "window_half_width_px": list(radius),
        "method": "local weighted least squares"
        + (
            f", edge-aware (guided by the total light, sigma {params.demux_guide_sigma:g})"
            if params.demux_method == "guided"
            else ""
        ),
        "noise_gain": dict(zip(names, [round(float(g), 4) for g in d.noise_gain])),
        "undetermined_px": int((~d.valid).sum()),
    }
    return Sources(names, groups, d.images, np.asarray(exposure), bad, info)


def _layout(src: Sources, params: MultiFlashParams) -> tuple[list[int], list[str], int | None]:
    """(flash source indices, their groups, ambient source index or None)."""
    flash_idx, groups, ambient = [], [], None
    for i, g in enumerate(src.groups):
        if len(g) == 1 and next(iter(g)) in FLASH_GROUPS:
            flash_idx.append(i)
            groups.append(next(iter(g)))
        elif not g:
            ambient = i
    if len(flash_idx) < 2:
        raise ConfigError(
            "capture.protocol: multi_flash needs reads lit by at least two of "
            f"{list(FLASH_GROUPS)}, one LED group each (got {src.names})"
        )
    if params.ambient == "subtract" and ambient is None:
        raise ConfigError(
            "app.ambient: 'subtract' needs an ambient-only read (sensor.bucket_count >= 5, or 5 "
            "sub-frames of a coded capture)"
        )
    return flash_idx, groups, (ambient if params.ambient != "none" else None)


def _mid_time_s(tl: Timeline) -> float:
    return float(Fraction(tl.start_tick + tl.end_tick, 2) * tl.tick_s)


#: What each preview shows (report.html).
CAPTIONS = {
    "shadow_free": "the per-pixel maximum of the flash images: no flash shadows",
    "shadow_free_truth": "reference: the noise-free shadow-free image",
    "depth_edges": "detected depth edges on the dimmed shadow-free image: green = matches a true depth edge "
    "(within app.tolerance_px), red = no true edge near, blue = true edge missed (without a "
    "reference: white = detected)",
    "normals": "photometric-stereo normals from the flash images at the true depth, (n + 1) / 2 as RGB (x right, "
    "y up, z towards the camera); black: fewer than three unshadowed lights",
}


@register(
    "multi_flash",
    output_channels=34,
    previews=4,
    params=MultiFlashParams,
    coded_gates=True,
    pinhole_truth="depth edges of the aov depth through pixel centres; flash directions projected by the pinhole",
    description="multi-flash: shadow-free max composite and depth edges from ratio images (Raskar 2004)",
)
def reconstruct(data: CaptureData, params: MultiFlashParams) -> AppOutput:
    cfg = data.cfg
    W, H = cfg.render.width, cfg.render.height
    src = _sources(data, params)
    flash_idx, groups, ambient = _layout(src, params)
    positions = data.scene.extra.get("flash_positions_m")
    if not positions or any(g not in positions for g in groups):
        raise ConfigError(f"scene.name: {data.scene.name!r} does not give extra['flash_positions_m'] for {groups}")
    epipoles = [epipole(data.scene.camera, positions[g], W, H) for g in groups]
    images = flash_images(src.electrons, src.exposure_s, data.k_e, flash_idx, ambient)
    used = flash_idx + ([ambient] if ambient is not None else [])
    bad = src.bad[used].any(axis=0)
    shadow_free = max_composite(images)
    det = depth_edges(images, epipoles, bad, params)
    edges = det.edges
    names = [src.names[i] for i in flash_idx]

    out_images: dict[str, np.ndarray] = {"shadow_free": shadow_free, "depth_edges": edges.astype(np.float32)}
    if det.ratios is not None:
        for n, r in zip(names, det.ratios):
            out_images[f"ratio_{n}"] = r.astype(np.float32)
    for n, img in zip(names, images):
        out_images[f"flash_{n}"] = img
    metrics: dict = {
        "method": params.method,
        "ambient": "ambient read subtracted" if ambient is not None else "kept in the flash images",
        "flash_reads": dict(zip(names, groups)),
        "epipoles_px": {
            n: {"at_infinity": not e.finite, ("direction" if not e.finite else "xy"): list(e.xy)}
            for n, e in zip(names, epipoles)
        },
        "saturated_px": int(bad.sum()),
        "coded_gates": src.demux,
        "detected_edge_px": int(edges.sum()),
    }
    png = {"shadow_free": ("shadow_free", cfg.output.png_percentile)}
    summary = [f"multi-flash ({params.method}): {int(edges.sum())} depth-edge pixels, ambient {metrics['ambient']}"]

    if data.renderer is not None:
        truth = _truth(data, params, groups, ambient is None)
        metrics.update(_scores(data, params, edges, shadow_free, truth))
        metrics["per_light"] = _per_light(images, truth["flash"], names, data.moving_mask)
        normals, n_metrics = _normals(data, params, images, groups, truth)
        metrics["normals"] = n_metrics
        out_images["normals"] = 0.5 * (normals + 1.0) * (np.linalg.norm(normals, axis=-1, keepdims=True) > 0)
        out_images["normals_truth"] = 0.5 * (truth["normals"] + 1.0)
        png["normals"] = ("normals", None)
        out_images.update(
            {
                "shadow_free_truth": truth["shadow_free"],
                "depth_edges_truth": truth["edges"].astype(np.float32),
                "depth_truth_z": truth["z_m"].astype(np.float32),
                "edges_overlay": edges_overlay(shadow_free, edges, truth["edges"], params.tolerance_px),
            }
        )
        png["shadow_free_truth"] = ("shadow_free_truth", cfg.output.png_percentile)
        e = metrics["depth_edges"]["all"]
        fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
        summary.append(
            f"depth edges vs truth ({params.truth_time}): precision {fmt(e['precision'])}, "
            f"recall {fmt(e['recall'])}, F1 {fmt(e['f1'])} (tolerance {params.tolerance_px} px)"
        )
        s = metrics["shadow_free"]
        summary.append(
            f"shadow-free: relMSE {s['rel_mse']:.4g}, residual shadow "
            f"{100 * s.get('residual_shadow_fraction', 0.0):.2f}% of shadowed pixels"
        )
        summary.append(
            f"per-light images: NRMSE {metrics['per_light']['mean_nrmse']:.4g} (mean); photometric-stereo "
            f"normals: median error {fmt(metrics['normals'].get('median_deg'))} deg"
        )
    else:
        out_images["edges_overlay"] = edges_overlay(shadow_free, edges, None, params.tolerance_px)
    png["depth_edges"] = ("edges_overlay", None)
    return AppOutput(images=out_images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)


def _truth(data: CaptureData, params: MultiFlashParams, groups: list[str], with_ambient: bool) -> dict:
    """Noise-free references rendered at the capture's mid-time (depth edges: per truth_time)."""

    renderer, tl = data.renderer, data.timeline
    t_mid = _mid_time_s(tl)
    spp = params.truth_spp or 4 * int(data.plan.spp.max())  # 4x the capture's samples per stratum
    seed = int(np.random.default_rng(data.seed).integers(0, 2**31 - 1))
    # the capture's own group set: its render kernel is compiled already
    render_groups = list(dict.fromkeys(list(data.plan.groups) + list(groups)))
    rad = renderer.render(t_mid, spp, seed, render_groups).astype(np.float64)
    flash = np.stack([rad[render_groups.index(g)] for g in groups])
    always_on = [i for i, g in enumerate(render_groups) if g not in data.scene.switchable]
    if with_ambient and always_on:  # the flash reads hold the always-on light too
        flash = flash + rad[always_on].sum(axis=0)[None]
    depth_mid = render_depth(renderer, t_mid)
    # strata_union: every time a render of the capture was made at (both halves, a top-up's pass)
    times = (
        [t_mid] if params.truth_time == "mid" else sorted({float(t) for t in data.plan.exposure_time_mix()[0].ravel()})
    )
    edges = np.zeros(depth_mid.z_m.shape, bool)
    for t in times:
        z = depth_mid.z_m if t == t_mid else render_depth(renderer, t).z_m
        edges |= depth_discontinuities(z, params.truth_depth_jump)
    return {
        "t_s": t_mid,
        "times_s": times,
        "flash": flash,
        "shadow_free": max_composite(flash),
        "edges": edges,
        "z_m": depth_mid.z_m,
        "spp": spp,
        "normals": render_normals(renderer, t_mid),
        "with_ambient": with_ambient and bool(always_on),
    }


def _per_light(images: np.ndarray, truth: np.ndarray, names: list[str], moving: np.ndarray) -> dict:
    """Normalised RMS error (:func:`~mbcapture.metrics.nrmse`) of each flash image against its
    noise-free truth, over the image and the moving region (the relative MSE would be ruled by the
    shadows' near-zero truth)."""
    out = {n: nrmse(img, t) for n, img, t in zip(names, images, truth)}
    res = {"nrmse": out, "mean_nrmse": float(np.mean(list(out.values())))}
    if moving.any():
        res["mean_nrmse_moving"] = float(
            np.mean([nrmse(img, t, mask=moving[..., None]) for img, t in zip(images, truth)])
        )
    return res


def _normals(
    data: CaptureData, params: MultiFlashParams, images: np.ndarray, groups: list[str], truth: dict
) -> tuple[np.ndarray, dict]:
    """Photometric-stereo normals of the flash images (:func:`~mbcapture.reconstruct.photometric.near_light_normals`)
    at the true depth, and their angular error against the normal AOV where every pixel of the 3x3
    neighbourhood is a surface off the true depth edges."""
    from scipy.ndimage import binary_dilation

    directions = data.scene.extra.get("flash_directions")
    if not directions or any(g not in directions for g in groups):
        return np.zeros(images.shape[1:3] + (3,)), {"note": f"scene {data.scene.name!r} gives no flash_directions"}
    positions = data.scene.extra["flash_positions_m"]
    lum = luminance(np.maximum(images, 0.0))
    note = (
        "ambient light kept in the flash images (no ambient read): it biases the normals"
        if truth["with_ambient"]
        else "flash images free of ambient light (subtracted, or none in the scene)"
    )
    pts = points_from_depth(data.scene.camera, truth["z_m"])
    n, ok = near_light_normals(
        lum,
        pts,
        np.array([positions[g] for g in groups]),
        np.array([directions[g] for g in groups]),
        shadow_ratio=params.normals_shadow_ratio,
    )
    tn = truth["normals"]
    judged = ok & ~binary_dilation(truth["edges"] | ~np.isfinite(truth["z_m"]), np.ones((3, 3), bool))
    judged &= np.linalg.norm(tn, axis=-1) > 0.5
    err = angular_error_deg(n, tn)
    out: dict = {
        "method": "near-light Lambertian photometric stereo at the true depth (3+ unshadowed lights)",
        "note": note,
        "solved_px": int(ok.sum()),
        "judged_px": int(judged.sum()),
    }
    if judged.any():
        e = err[judged]
        out.update(
            {"median_deg": float(np.median(e)), "mean_deg": float(e.mean()), "p90_deg": float(np.percentile(e, 90))}
        )
        mov = judged & data.moving_mask
        if mov.any():
            out["median_deg_moving"] = float(np.median(err[mov]))
    return n, out


def _scores(
    data: CaptureData, params: MultiFlashParams, edges: np.ndarray, shadow_free: np.ndarray, truth: dict
) -> dict:
    mask = data.moving_mask
    de = {"all": edge_scores(edges, truth["edges"], params.tolerance_px)}
    if mask.any():
        de["moving_region"] = edge_scores(edges, truth["edges"], params.tolerance_px, mask)
        de["static_region"] = edge_scores(edges, truth["edges"], params.tolerance_px, ~mask)
    sf = {
        "rel_mse": relative_mse(shadow_free, truth["shadow_free"], eps=REL_MSE_EPS_RADIANCE),
        **shadow_metrics(
            shadow_free,
            truth["flash"],
            shadow_ratio=params.shadow_ratio,
            min_signal_fraction=params.min_signal_fraction,
        ),
    }
    if mask.any():
        sf["rel_mse_moving"] = relative_mse(
            shadow_free, truth["shadow_free"], mask=mask[..., None], eps=REL_MSE_EPS_RADIANCE
        )
    return {
        "truth": {
            "time_s": truth["t_s"],
            "edge_times_s": truth["times_s"],
            "mode": params.truth_time,
            "depth_jump": params.truth_depth_jump,
            "tolerance_px": params.tolerance_px,
            "shadow_free_spp": truth["spp"],
            "what": "depth edges of the aov depth at pixel centres; shadow-free truth = max composite of "
            "the flash groups rendered noise-free at the capture's mid-time",
        },
        "moving_px": int(mask.sum()),
        "depth_edges": de,
        "shadow_free": sf,
    }
