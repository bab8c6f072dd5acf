"""Indirect (continuous-wave) time of flight on a multi-tap pixel: the protocols, depth and its scores.

The protocols (``capture.protocol``; the pixel designs of :data:`mbcapture.sensor.demodulation.DESIGNS`):

``tof_4tap``             four taps, quarter-period gates: the four phases of a frequency in one exposure
``tof_2tap``             two complementary taps (phi, phi + 180) per sub-frame; the sub-frames (and the
                         frequencies) alternate ``capture.periods`` times within the exposure, each into
                         buckets of its own: a multi-bucket pixel used as a 2-tap demodulator (needs
                         frequencies x phases buckets)
``tof_2tap_sequential``  the same sub-frames one after another, each read out before the next
                         (``sensor.frame_readout_s``), as a plain 2-tap sensor takes them
``tof_1tap``             one tap, half-period gates (the other half drained), one phase per sub-frame, in
                         sequence

Every design gives each frequency the same illuminator on-time (``capture.tof.exposure_s``). A phase's
tap is a slot lit by its phase group (:class:`~mbcapture.sensor.demodulation.PhaseGroup`); inside a
sub-frame the taps alternate every ``capture.periods``-th of it (a model of their alternation at the
modulation frequency, exact in the light collected; the order inside a period shifts a tap's time centroid
by under one period). Reads: one per phase, ``f<i>_p<k>`` (frequency i, phase k).

The application: the phasor of each frequency (:func:`mbcapture.reconstruct.tof.phasor_fit`), its amplitude,
phase and wrapped depth, unwrapping over the frequencies, a confidence (amplitude over the fit's noise,
from the reads' own shot and read noise), the ambient image (the common mode less the modulated light's
share of it), and scores against the depth AOV at the capture's mid-time: overall, in the moving region,
at depth edges (flying pixels) and near the scene's corner (multipath). The same reconstruction on the
noise-free reads gives the systematic error alone (multipath, wiggling, motion between taps).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from pydantic import Field

from ..errors import ConfigError
from ..output.plots import depth_preview
from ..reconstruct.tof import depth_noise_m, depth_scores, flying_pixels, joint_range_m, phasor_fit, unwrap
from ..render.aov import pixel_cosines, render_depth
from ..scene.projective import points_from_depth
from ..sensor.demodulation import (
    DESIGNS,
    PhaseGroup,
    gate_coefficient,
    phase_group_name,
    phases_rad,
    unambiguous_range_m,
    waveform_coefficients,
)
from ..strict import StrictModel
from ..timing.timeline import DRAIN, ReadEvent, SegmentSeconds, SlotSeconds, Timeline, build_timeline, exact
from . import AppOutput, CaptureData, register, register_protocol


# --------------------------------------------------------------------------------- protocols
def tof_timeline(cfg) -> Timeline:
    """The timeline of the time-of-flight protocol ``cfg.capture.protocol`` (module doc)."""
    design = DESIGNS[cfg.capture.protocol]
    tof = cfg.capture.tof
    P, taps, N = tof.phases, design.taps, cfg.capture.periods
    n_sub = P // taps
    freqs = [f * 1e6 for f in tof.frequencies_mhz]
    phases = phases_rad(P)
    n_buckets = len(freqs) * P
    have = cfg.sensor.bucket_count
    need = taps if design.sequential else n_buckets
    if need > have:
        what = f"{taps} taps" if design.sequential else f"{len(freqs)} frequencies x {P} phases in buckets of their own"
        raise ConfigError(
            f"capture.protocol: {cfg.capture.protocol!r} needs {need} buckets ({what}) but sensor.bucket_count is {have}"
        )
    tap_s = exact(tof.exposure_s) / (P * N) / (2 if taps == 1 else 1)  # a tap's slot in one period

    def subframe(fi: int, s: int) -> list[SlotSeconds]:
        slots = []
        for j in range(taps):
            k = s + j * n_sub  # complementary taps: phases 360 / taps apart
            group = phase_group_name(tof.group, freqs[fi], math.degrees(phases[k]))
            slots.append(SlotSeconds(fi * P + k, tap_s, frozenset({group})))
        if taps == 1:
            slots.append(SlotSeconds(DRAIN, tap_s))
        return slots

    order = [(fi, s) for fi in range(len(freqs)) for s in range(n_sub)]
    start = exact(cfg.capture.start_s)
    if design.sequential:
        segments, t = [], start
        gap = exact(cfg.sensor.frame_readout_s)
        for fi, s in order:
            slots = tuple(subframe(fi, s))
            segments.append(SegmentSeconds(t, slots, N))
            t += N * sum((x.duration_s for x in slots), Fraction(0)) + gap
    else:
        segments = [SegmentSeconds(start, tuple(x for fi, s in order for x in subframe(fi, s)), N)]
    reads = [
        ReadEvent(f"f{fi + 1}_p{k}", (fi * P + k,), destructive=design.sequential)
        for fi in range(len(freqs))
        for k in range(P)
    ]
    return build_timeline(segments, reads, n_buckets, cfg.capture.protocol, sequential=design.sequential)


for _name in DESIGNS:
    register_protocol(_name, app="tof")(tof_timeline)


def tap_groups(data: CaptureData) -> list[PhaseGroup]:
    """The phase group each read of a time-of-flight capture collected (from its timeline)."""
    demod = data.scene.demodulation
    if demod is None:
        raise ConfigError("app.name: 'tof' reconstructs the time-of-flight protocols' reads (capture.protocol tof_*)")
    by_bucket: dict[int, str] = {}
    for seg in data.timeline.segments:
        for slot in seg.slots:
            for g in slot.groups_on:
                if g in demod.names:
                    by_bucket[slot.bucket] = g
    return [demod.by_name(by_bucket[r.buckets[0]]) for r in data.timeline.reads]


# --------------------------------------------------------------------------------- params
class TofParams(StrictModel):
    tolerance_mm: float = Field(
        10.0, gt=0, description="Metric within_tolerance and the motion test: |depth error| at most this, mm."
    )
    min_amplitude_snr: float = Field(
        3.0,
        ge=0,
        description="A pixel's depth is valid where every frequency's amplitude is at least this many times its noise "
        "(from the reads' shot and read noise) and no tap saturated.",
    )
    max_range_m: float | None = Field(
        None,
        gt=0,
        description="Farthest distance unwrapping considers, m. null: the frequencies' joint unambiguous range "
        "c / (2 gcd(f)).",
    )
    edge_jump_m: float = Field(
        0.1,
        gt=0,
        description="A depth edge: the true depth jumps at least this much within a pixel's 3x3 neighbours, m.",
    )
    corner_radius_m: float = Field(
        0.3,
        gt=0,
        description="Multipath region: points within this distance of the scene's corner line (SceneModel.extra "
        "'corner'), m.",
    )


# --------------------------------------------------------------------------------- app
def _error_preview(err_mm: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """(H, W, 3) signed depth error: red too far, blue too near, full at 4 x the tolerance; black 0 or invalid."""
    e = np.clip(np.nan_to_num(err_mm, nan=0.0) / (4 * tolerance_mm), -1, 1)
    out = np.zeros((*e.shape, 3), np.float32)
    out[..., 0] = np.maximum(e, 0)
    out[..., 2] = np.maximum(-e, 0)
    return out


CAPTIONS = {
    "depth": "measured depth (distance from the camera), turbo colour map from the nearest to the farthest true "
    "distance; black: not valid (low amplitude or saturated)",
    "amplitude": "modulated amplitude of the first frequency, electrons per second, tone-mapped",
    "ambient": "ambient light: the taps' common mode less the illuminator's share of it, render units, tone-mapped",
    "depth_truth": "reference: the depth AOV (distance) at the capture's mid-time, same colour scale",
    "depth_error": "measured - true depth: red too far, blue too near, full colour at 4 x app.tolerance_mm",
    "systematic_error": "the same reconstruction on the noise-free reads - true depth (multipath, wiggling, motion "
    "between taps), same scale",
}


def _corner_mask(data: CaptureData, distance_m: np.ndarray, radius_m: float) -> np.ndarray | None:
    corner = data.scene.extra.get("corner")
    if corner is None:
        return None
    cos = pixel_cosines(data.scene.camera, data.cfg.render.width, data.cfg.render.height)
    pts = points_from_depth(data.scene.camera, np.where(np.isfinite(distance_m), distance_m, 0.0) * cos)
    p0, direction = np.asarray(corner[0], float), np.asarray(corner[1], float)
    direction = direction / np.linalg.norm(direction)
    rel = pts - p0
    perp = rel - (rel @ direction)[..., None] * direction
    return np.isfinite(distance_m) & (np.linalg.norm(perp, axis=-1) <= radius_m)


def _reconstruct(values: np.ndarray, variances: np.ndarray | None, taps: list[PhaseGroup], freqs, max_range) -> dict:
    """Phasor per frequency and unwrapped depth of tap values (R, H, W)."""
    fits = []
    for f in freqs:
        idx = [i for i, g in enumerate(taps) if g.frequency_hz == f]
        fits.append(
            phasor_fit(
                values[idx],
                np.array([taps[i].phase_rad for i in idx]),
                None if variances is None else variances[idx],
            )
        )
    depth, spread = unwrap(np.stack([ft["phase"] for ft in fits]), freqs, max_range)
    return {"fits": fits, "depth": depth, "spread": spread}


def _against_truth(
    data: CaptureData,
    params: TofParams,
    got: dict,
    expected: dict,
    valid: np.ndarray,
    depth: np.ndarray,
    max_range: float,
    freqs: list[float],
) -> tuple[dict, dict, dict, list, list]:
    """Scores against the depth AOV: (metrics, images, previews, summary lines, warnings)."""
    metrics, images, png, summary, warnings = {}, {}, {}, [], []
    tl = data.timeline
    t_mid = float(Fraction(tl.start_tick + tl.end_tick, 2) * tl.tick_s)
    truth = render_depth(data.renderer, t_mid).distance_m
    finite = np.isfinite(truth)
    far = float(truth[finite].max()) if finite.any() else 0.0
    near = float(truth[finite].min()) if finite.any() else 0.0
    if far > max_range:
        warnings.append(
            f"the scene reaches {far:.2f} m but the unambiguous range is {max_range:.2f} m: farther surfaces wrap "
            "to near depths" + ("; add a second frequency (capture.tof.frequencies_mhz)" if len(freqs) == 1 else "")
        )
    tol = params.tolerance_mm * 1e-3
    systematic = expected["depth"]
    # noise-free depths where the illuminator's modulation reaches (not an emitter's own surface: the window)
    lit = np.all([ft["amplitude"] > 1e-3 * np.abs(ft["offset"]) for ft in expected["fits"]], axis=0)
    regions = {"all": finite}
    if data.moving_mask.any():
        regions["moving_region"] = finite & data.moving_mask
        regions["static_region"] = finite & ~data.moving_mask
    corner = _corner_mask(data, truth, params.corner_radius_m)
    if corner is not None and corner.any():
        regions["corner"] = corner
        regions["away_from_corner"] = finite & ~corner
    fly, edge_px = flying_pixels(got["depth"], valid, truth, params.edge_jump_m)
    fly0, _ = flying_pixels(systematic, finite & lit, truth, params.edge_jump_m)
    # the surface each pixel sees at the earliest and the latest tap's time centroid: where it changes by more
    # than the tolerance, the taps measured different surfaces (the design's exposure to motion artefacts)
    cents = [tl.centroid_ticks(r.buckets) for r in tl.reads]
    t_first, t_last = (float(c * tl.tick_s) for c in (min(cents), max(cents)))
    at_first, at_last = (render_depth(data.renderer, t).distance_m for t in (t_first, t_last))
    with np.errstate(invalid="ignore"):
        change = np.abs(np.where(np.isfinite(at_first), at_first, 1e9) - np.where(np.isfinite(at_last), at_last, 1e9))
    off = change > tol
    metrics["truth"] = {
        "time_s": t_mid,
        "what": "distance along each pixel's centre ray (depth aov) at the capture's mid-time",
        "near_m": near,
        "far_m": far,
        "tolerance_mm": params.tolerance_mm,
    }
    metrics["depth"] = {name: depth_scores(depth, truth, m & valid, tol) for name, m in regions.items()}
    metrics["systematic"] = {name: depth_scores(systematic, truth, m & lit, tol) for name, m in regions.items()}
    metrics["flying_pixels"] = {
        "edge_px": edge_px,
        "measured": int(fly.sum()),
        "noise_free": int(fly0.sum()),
        "fraction": float(fly.sum() / edge_px) if edge_px else 0.0,
    }
    moving_px = max(int(data.moving_mask.sum()), 1)
    metrics["motion_artefact"] = {
        "what": "pixels whose true distance changes by more than the tolerance between the earliest and the latest "
        "tap's time centroid: their taps measured different surfaces",
        "taps_apart_s": t_last - t_first,
        "px": int(off.sum()),
        "fraction_of_moving_region": float((off & data.moving_mask).sum() / moving_px),
        "error_there": depth_scores(depth, truth, off & valid, tol),
    }
    err = np.where(valid & finite, got["depth"] - truth, np.nan) * 1e3
    err0 = np.where(finite & lit, systematic - truth, np.nan) * 1e3
    images["taps_see_motion"] = off.astype(np.float32)
    images |= {
        "depth_truth": np.nan_to_num(truth, posinf=0.0).astype(np.float32),
        "depth_error_mm": np.nan_to_num(err, nan=0.0).astype(np.float32),
        "systematic_error_mm": np.nan_to_num(err0, nan=0.0).astype(np.float32),
        "depth_preview": depth_preview(depth, near, far).astype(np.float32),
        "depth_truth_preview": depth_preview(np.where(finite, truth, np.nan), near, far).astype(np.float32),
        "error_preview": _error_preview(err, params.tolerance_mm),
        "systematic_preview": _error_preview(err0, params.tolerance_mm),
    }
    png |= {
        "depth": ("depth_preview", None),
        "depth_truth": ("depth_truth_preview", None),
        "depth_error": ("error_preview", None),
        "systematic_error": ("systematic_preview", None),
    }
    a = metrics["depth"]["all"]
    fmt = lambda v: "n/a" if v is None else f"{v:.3g}"  # noqa: E731
    summary.append(
        f"depth MAE {fmt(a['mae_mm'])} mm, RMSE {fmt(a['rmse_mm'])} mm, "
        f"{100 * (a['within_tolerance'] or 0):.1f}% within {params.tolerance_mm:g} mm; "
        f"flying pixels {int(fly.sum())} of {edge_px} at edges"
    )
    if "moving_region" in metrics["depth"]:
        m = metrics["depth"]["moving_region"]
        summary.append(
            f"moving region: MAE {fmt(m['mae_mm'])} mm, {100 * (m['within_tolerance'] or 0):.1f}% within tolerance"
        )
    return metrics, images, png, summary, warnings


@register(
    "tof",
    output_channels=24,
    previews=6,
    params=TofParams,
    pinhole_truth="distance along each pixel's ray through the pinhole; truth from the depth aov",
    description="indirect time of flight: phasors, unwrapping over frequencies, depth, amplitude, ambient",
)
def reconstruct(data: CaptureData, params: TofParams) -> AppOutput:
    cfg = data.cfg
    taps = tap_groups(data)
    freqs = [f * 1e6 for f in cfg.capture.tof.frequencies_mhz]
    demod = data.scene.demodulation
    joint = joint_range_m(freqs)
    max_range = min(params.max_range_m or joint, joint)

    t = np.asarray(data.exposure_s, float)[:, None, None]
    e = data.reads_e().mean(axis=-1)  # (R, H, W): a mono sensor's channels are alike; else their mean
    rates = e / t
    var = (np.maximum(e, 0) + cfg.sensor.read_noise_e**2) / t**2
    sat = data.saturated.any(axis=(0, -1))
    got = _reconstruct(rates, var, taps, freqs, max_range)
    expected = _reconstruct(data.reads_e_expected.mean(axis=-1) / t, None, taps, freqs, max_range)

    snr = np.min([ft["amplitude"] / np.maximum(ft["sigma"], 1e-30) for ft in got["fits"]], axis=0)
    valid = ~sat & (snr >= params.min_amplitude_snr)
    depth = np.where(valid, got["depth"], np.nan)
    first = got["fits"][0]
    k_e = float(np.mean(data.k_e))
    # the illuminator's modulated amplitude over its common mode at the first frequency (its own DC): a tap's
    # correlation of contrast x gate x waveform coefficient
    share = demod.contrast * gate_coefficient(1, demod.duty) * waveform_coefficients(demod.waveform, demod.harmonics)[1]
    ambient = np.maximum(first["offset"] - first["amplitude"] / share, 0.0) / k_e
    sigma_d = depth_noise_m(first["amplitude"], first["sigma"], freqs[0])

    images = {
        "depth": np.nan_to_num(depth, nan=0.0).astype(np.float32),
        "depth_valid": valid.astype(np.float32),
        "amplitude": first["amplitude"].astype(np.float32),
        "intensity": (first["offset"] / k_e).astype(np.float32),
        "ambient": ambient.astype(np.float32),
        "confidence": snr.astype(np.float32),
        "depth_sigma_m": sigma_d.astype(np.float32),
    }
    for i, ft in enumerate(got["fits"]):
        images[f"phase_f{i + 1}"] = ft["phase"].astype(np.float32)
    if len(freqs) > 1:
        images["unwrap_spread_m"] = got["spread"].astype(np.float32)
    metrics: dict = {
        "design": cfg.capture.protocol,
        "frequencies_mhz": list(cfg.capture.tof.frequencies_mhz),
        "phases": cfg.capture.tof.phases,
        "unambiguous_range_m": [unambiguous_range_m(f) for f in freqs],
        "unwrap_range_m": max_range,
        "unwrap": "lookup over the joint range" if len(freqs) > 1 else "none (one frequency)",
        "valid_fraction": float(valid.mean()),
        "saturated_px": int(sat.sum()),
        "median_depth_sigma_mm": float(np.nanmedian(np.where(valid, sigma_d, np.nan)) * 1e3) if valid.any() else None,
    }
    png = {"amplitude": ("amplitude", 99.0), "ambient": ("ambient", 99.0)}
    summary = [
        f"time of flight ({cfg.capture.protocol}, {len(freqs)} frequenc{'y' if len(freqs) == 1 else 'ies'}): "
        f"{100 * valid.mean():.1f}% of pixels valid"
    ]
    warnings: list[str] = []
    if data.renderer is not None:
        m, im, pv, sm, warnings = _against_truth(data, params, got, expected, valid, depth, max_range, freqs)
        metrics |= m
        images |= im
        png |= pv
        summary += sm
    else:
        png |= {"depth": ("depth_preview", None)}
        images["depth_preview"] = depth_preview(
            depth, float(np.nanmin(depth)) if valid.any() else 0.0, max_range
        ).astype(np.float32)
    metrics["warnings"] = warnings
    summary += [f"warning: {w}" for w in warnings]
    return AppOutput(images=images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)
