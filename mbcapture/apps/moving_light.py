"""Moving light: HDR of a still life whose lamp moves (shadows sweep) under flickering ambient light.

The reads of an HDR protocol are merged exactly as :mod:`mbcapture.apps.hdr` does (its
functions are called, not copied); this application adds how *consistent* the reads are, which
is what decides whether an HDR merge of them is a picture of one scene:

``consistency``
    relative RMS differences of the exposure-normalized, noise-free reads (radiance each read
    saw), pairwise and against the ground truth (the longest read's, as in ``hdr``), over the
    whole image and in the *shadow-sweep region*: the pixels that some occluder's shadow
    covers at some time of the capture but not at all times (computed from the scene's
    geometry over the span of both the interleaved and the sequential capture of the same
    reads, so both modes are scored on the same pixels).
``flicker``
    per read, the mean drive of the flickering group over its gated time relative to the
    drive's time average (``c0``): 1 when a read saw the flicker's mean. Exact from the render
    weights (gate x drive integrated in closed form), and measured from the per-group renders
    (mean ambient level per read over its exposure, relative to the drive-weighted mean).
    Interleaved reads sample the same flicker phases; sequential frames sample different ones.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..strict import StrictModel
from ..timing import protocols
from ..errors import ConfigError
from . import AppOutput, CaptureData, register
from . import hdr as hdr_app

#: scene times sampled to trace the shadows over a capture
SWEEP_TIME_SAMPLES = 96


class MovingLightParams(StrictModel):
    sweep_grow_px: float = Field(
        1.5,
        ge=0.0,
        le=50.0,
        description="Grow the shadow-sweep region by this many pixels (penumbrae, interreflections).",
    )
    flicker_group: str = Field(
        "ambient", description="Emitter group whose flicker phase is measured (must have a drive in the scene)."
    )


# --------------------------------------------------------------------------- pure functions
def rasterize_convex(polygons_px: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels whose centre lies in the convex hull of any of ``polygons_px``
    ((P, 2) pixel coordinates, x right, y down, pixel centres at half-integers): the centre is
    on the inner side of every hull edge (half-plane tests over the hull's bounding box)."""
    from scipy.spatial import ConvexHull, QhullError

    mask = np.zeros((height, width), dtype=bool)
    for pts in polygons_px:
        pts = np.asarray(pts, float)
        try:
            hull = pts[ConvexHull(pts).vertices]  # counter-clockwise in (x, y)
        except (QhullError, ValueError):  # degenerate (a line): nothing of area
            continue
        x0, y0 = np.maximum(np.floor(hull.min(axis=0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(hull.max(axis=0)).astype(int), [width, height])
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1] + 0.5
        inside = np.ones(xx.shape, dtype=bool)
        for a, b in zip(hull, np.roll(hull, -1, axis=0)):
            inside &= (b[0] - a[0]) * (yy - a[1]) - (b[1] - a[1]) * (xx - a[0]) >= 0
        mask[y0:y1, x0:x1] |= inside
    return mask


def sweep_region(
    shadows_px_over_time: list[list[np.ndarray]], width: int, height: int, grow_px: float = 0.0
) -> np.ndarray:
    """(H, W) bool: pixels inside some shadow at some time but not inside it at every time.

    ``shadows_px_over_time[t][o]`` is occluder o's shadow polygon at time t, (P, 2) pixels.
    Per occluder the union over times minus the intersection over times, then the union over
    occluders, grown by ``grow_px`` (a disk).
    """
    if not shadows_px_over_time:
        return np.zeros((height, width), dtype=bool)
    n_occ = len(shadows_px_over_time[0])
    out = np.zeros((height, width), dtype=bool)
    for o in range(n_occ):
        masks = np.stack([rasterize_convex([polys[o]], width, height) for polys in shadows_px_over_time])
        out |= masks.any(axis=0) & ~masks.all(axis=0)
    if grow_px > 0 and out.any():
        import cv2

        r = int(np.ceil(grow_px))
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        kernel = ((xx**2 + yy**2) <= grow_px**2).astype(np.uint8)
        out = cv2.dilate(out.astype(np.uint8), kernel).astype(bool)
    return out


def consistency(normalized: np.ndarray, names: list[str], truth: np.ndarray, mask: np.ndarray) -> dict:
    """Relative RMS differences of exposure-normalized reads (R, H, W, C) inside ``mask`` (H, W):
    :func:`mbcapture.apps.hdr.motion_check` (each read vs truth, the largest pairwise) plus every
    pair, all relative to the mean truth in the mask."""
    out = hdr_app.motion_check(normalized, names, truth, mask)
    if not mask.any():
        return out
    ref = float(truth[mask].mean()) or 1.0
    out["pairwise_rel_rms"] = {
        f"{names[i]}-{names[j]}": float(np.sqrt(np.mean((normalized[i][mask] - normalized[j][mask]) ** 2)) / ref)
        for i in range(len(names))
        for j in range(i + 1, len(names))
    }
    out["mean_rel_rms_vs_truth"] = float(np.mean(list(out["rel_rms_vs_truth"].values())))
    return out


#: What each preview shows (report.html), besides the HDR ones.
CAPTIONS = {
    "read_spread": "the largest departure of any exposure-normalized read from the reference, relative, linear: "
    "white = 100 %",
    "sweep": "white: the region the moving lamp's shadows sweep during the capture",
}


def read_spread_rel(normalized: np.ndarray, truth: np.ndarray, floor: float = 0.01) -> np.ndarray:
    """(H, W, C): the largest departure of any exposure-normalized read from the truth, relative
    to the truth (floored at ``floor`` render units so black pixels do not blow up)."""
    return np.abs(normalized - truth[None]).max(axis=0) / np.maximum(np.abs(truth), floor)


def drive_gains_exact(
    weights_s: np.ndarray, group: int, read_buckets: list[tuple[int, ...]], exposure_s: np.ndarray, c0: float
) -> np.ndarray:
    """(R,) mean drive of ``group`` over each read's gated time, relative to the time average c0:
    sum over strata and the read's buckets of the weights (seconds x drive), over exposure x c0.
    ``weights_s`` (J, K, G) from the plan."""
    per_bucket = weights_s[:, :, group].sum(axis=0)  # (K,)
    return np.array([per_bucket[list(b)].sum() for b in read_buckets]) / (np.asarray(exposure_s) * c0)


def drive_gains_measured(
    group_exposure: np.ndarray,
    weights_s: np.ndarray,
    group: int,
    read_buckets: list[tuple[int, ...]],
    exposure_s: np.ndarray,
    c0: float,
) -> np.ndarray:
    """(R,) the same measured on the rendered images: each read's mean level of ``group``
    (group_exposure (K, G, H, W, C), summed over its buckets) per second of exposure, over the
    group's drive-weighted mean radiance (all read buckets' exposure / their weights) x c0.
    Equals :func:`drive_gains_exact` when the group's radiance is static (up to render noise)."""
    level = group_exposure[:, group].mean(axis=(1, 2, 3))  # (K,) mean exposure of the group
    per_bucket = weights_s[:, :, group].sum(axis=0)
    used = sorted({k for b in read_buckets for k in b})
    mean_radiance = level[used].sum() / per_bucket[used].sum()
    return np.array([level[list(b)].sum() for b in read_buckets]) / (np.asarray(exposure_s) * mean_radiance * c0)


# --------------------------------------------------------------------------- glue
def _sweep_times(data: CaptureData) -> np.ndarray:
    """Scene times spanning both this capture and its twin (interleaved <-> sequential)."""

    cfg = data.cfg
    twin_cfg = cfg.model_copy(
        update={"capture": cfg.capture.model_copy(update={"sequential": not cfg.capture.sequential})}
    )
    spans = []
    for tl in (data.timeline, protocols.build(twin_cfg)):
        spans += [float(tl.seconds(tl.start_tick)), float(tl.seconds(tl.end_tick))]
    return np.linspace(min(spans), max(spans), SWEEP_TIME_SAMPLES)


def shadow_sweep_mask(data: CaptureData, grow_px: float) -> np.ndarray:
    scene = data.scene
    polys_fn = scene.extra.get("shadow_polygons")
    if polys_fn is None:
        raise ConfigError(
            f"app.name: moving_light needs a scene with extra['shadow_polygons'] (scene {scene.name!r} has none)"
        )
    H, W = data.reads_dn.shape[1:3]
    times = _sweep_times(data)
    per_occ = [scene.project(p, times, W, H) for p in polys_fn(times)]  # each (T, P, 2), through a shaking camera too
    return sweep_region([[occ[t] for occ in per_occ] for t in range(len(times))], W, H, grow_px)


def flicker_metrics(data: CaptureData, group_name: str) -> dict:
    drives = getattr(data.scene, "drives", {}) or {}
    if group_name not in drives:
        raise ConfigError(
            f"app.flicker_group: scene {data.scene.name!r} has no drive for group {group_name!r} "
            f"(driven groups: {sorted(drives)})"
        )
    drive = drives[group_name]
    if group_name not in data.plan.groups:
        return {"group": group_name, "note": "group not rendered (no weight in any read)"}
    gi = data.group_index(group_name)
    buckets = [r.buckets for r in data.timeline.reads]
    exact = drive_gains_exact(data.plan.weights_s, gi, buckets, data.exposure_s, drive.c0)
    out = {
        "group": group_name,
        "drive": {
            "c0": drive.c0,
            "terms": [{"amplitude": a, "frequency_hz": f, "phase_rad": p} for a, f, p in drive.terms],
        },
        "gain_vs_time_average": dict(zip(data.read_names, exact.tolist())),
        "gain_spread": float(exact.max() - exact.min()),
        "max_abs_gain_error": float(np.abs(exact - 1.0).max()),
    }
    if data.group_exposure is not None:
        measured = drive_gains_measured(
            data.group_exposure, data.plan.weights_s, gi, buckets, data.exposure_s, drive.c0
        )
        out["gain_measured_from_renders"] = dict(zip(data.read_names, measured.tolist()))
    return out


@register(
    "moving_light",
    renders=False,
    output_channels=24,
    previews=4,
    memory_scale=1.12,
    params=MovingLightParams,
    per_group=True,
    description="HDR of a moving-light scene plus read consistency (shadow sweep, flicker phase)",
)
def reconstruct(data: CaptureData, params: MovingLightParams) -> AppOutput:
    base = hdr_app.reconstruct(data, None)
    normalized = hdr_app.normalized_reads(data)
    ref = int(np.argmax(data.exposure_s))
    truth = normalized[ref]
    H, W = truth.shape[:2]
    sweep = shadow_sweep_mask(data, params.sweep_grow_px)
    metrics = dict(base.metrics)
    metrics["consistency"] = {
        "quantity": "relative RMS of exposure-normalized noise-free reads, over the mean truth in the region",
        "whole_image": consistency(normalized, data.read_names, truth, np.ones((H, W), dtype=bool)),
        "shadow_sweep": consistency(normalized, data.read_names, truth, sweep),
        "sweep_fraction_of_image": float(sweep.mean()),
    }
    metrics["flicker"] = flicker_metrics(data, params.flicker_group)

    c = metrics["consistency"]
    fl = metrics["flicker"]
    summary = list(base.summary) + [
        "consistency (largest pairwise rel. RMS of exposure-normalized reads): whole image "
        f"{100 * c['whole_image']['max_pairwise_rel_rms']:.2f}%, shadow sweep "
        f"{100 * c['shadow_sweep'].get('max_pairwise_rel_rms', float('nan')):.2f}% "
        f"({100 * c['sweep_fraction_of_image']:.1f}% of the image)",
    ]
    if "gain_vs_time_average" in fl:
        summary.append(
            f"flicker ({fl['group']}): mean drive per read / time average = "
            + ", ".join(f"{n} {g:.4f}" for n, g in fl["gain_vs_time_average"].items())
        )
    n_ch = truth.shape[-1]
    images = dict(base.images)
    images["sweep"] = np.repeat(sweep[..., None], n_ch, -1).astype(np.float32)
    images["read_spread_rel"] = read_spread_rel(normalized, truth).astype(np.float32)
    png = dict(base.png)
    png["read_spread"] = ("read_spread_rel", None)  # linear: white = 100 % departure, the same scale in every run
    png["sweep"] = ("sweep", None)
    return AppOutput(
        images=images,
        metrics=metrics,
        png=png,
        extra_exr=base.extra_exr,
        summary=summary,
        captions={**base.captions, **CAPTIONS},
    )
