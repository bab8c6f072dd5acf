"""Structured light with an ambient bucket: depth by triangulation from projected patterns (the
multi-bucket paper's section 6: "three of the buckets can be used to capture a scene illuminated
by three different patterns while the last bucket records the scene due to ambient light only").

Protocol ``structured_light``
    The scene's pattern groups (``SceneModel.extra['structured_light']['groups']``: the projector
    casting each pattern) in buckets 1..N, one per slot of T/N_p per period (T =
    ``capture.unit_exposure_s``, N_p = ``capture.periods``); when ``sensor.bucket_count`` > N, slot
    N+1 of T/N_p with the projector dark fills bucket N+1 (read ``ambient``). Each bucket is read
    directly; the reads are named after the groups. Every pattern and the ambient image are thus
    exposed through the same span of time, interleaved: the ambient light (a lamp flickering at
    twice the mains frequency) and the moving surfaces are the same in all of them. With a capture
    span of whole flicker cycles (the shipped config: 4 x 5 ms = two 100 Hz cycles, 20 periods)
    the flicker cancels in every bucket exactly (the Dirichlet kernel of the drive integral is 0).
    ``capture.sequential: true`` takes the same images one after another on a conventional sensor.

Reconstruction (pure numpy; radiance rate I_k = read electrons / (k_e t_k), Rec. 709 luminance)
    1. Ambient: ``app.ambient`` 'subtract' (default when there is an ambient read) removes the
       ambient read, scaled to each read's exposure, from every pattern image; 'none' keeps it.
       report.json scores both decodings of the same capture (with and without the ambient bucket).
    2. Decoding, by the scene's pattern kind (:data:`DECODERS`):
       ``phase_shift``: N-step phase shifting. With deltas d_k, S = sum_k I_k sin d_k,
       C = sum_k I_k cos d_k: wrapped phase phi = atan2(S, C) in [0, 2 pi), modulation
       B = 2 sqrt(S^2 + C^2) / N. A constant added to every I_k cancels in S and C: ambient that
       is equal in all pattern reads drops out even without the ambient bucket; ambient that
       differs between them (flicker between sequential frames) becomes phase error.
       Valid where B >= ``app.min_modulation_fraction`` x its 99th percentile.
       ``gray_code``: bit m is 1 where I_m - A > (I_white - A) / 2 (ambient subtracted) or
       I_m > I_white / 2 (without); the Gray code of the bits gives the stripe index s, the
       projector column u = (s + 1/2) W / 2^M. Valid where the white image's projector light
       (I_white - A, or I_white without the ambient bucket) is >= ``app.min_modulation_fraction``
       x its 99th percentile. Ambient light brighter than the projector flips 0 bits to 1.
    3. Phase unwrapping (phase_shift; ``app.unwrap``, :data:`UNWRAP_METHODS`):
       ``depth_range`` (default): per pixel, each candidate period k = 0..P-1 gives the projector
       column u_k = (phi / 2 pi + k) W / P and, by triangulation, a depth z_k; the pixel keeps the
       one candidate inside [``app.depth_min_m``, ``app.depth_max_m``] and is invalid when none or
       several are (pixel-wise, needs no extra patterns, unaffected by depth discontinuities; it
       needs the disparity range of the depth interval to be shorter than one fringe period, which
       :func:`period_ambiguity` reports: the shipped scene's 4 periods of 128 texels against ~90 texels
       of disparity over 0.7-1.6 m). ``spatial``: scikit-image's ``unwrap_phase`` (Herraez et al.
       2002, reliability-guided) over the valid pixels, then the one global offset of 2 pi that
       puts most pixels inside the depth interval; it fails where a depth discontinuity shifts
       the phase by more than pi between neighbours (the baseline that shows why).
       ``none``: u = phi W / (2 pi P), right for P = 1 only.
    4. Triangulation: the camera ray through each pixel centre meets the plane of the projector's
       column u (:func:`mbcapture.scene.projective.triangulate_columns`), giving the depth along the
       camera's optical axis.

Ground truth and metrics
    Depth: Mitsuba's depth AOV through each pixel centre at the capture's mid-time
    (:mod:`mbcapture.render.aov`), converted to depth along the optical axis. Truth projector column
    and phase: each truth point projected into the projector. Pixels that count: those whose truth
    point the projector lights (inside its field of view and visible from it: a depth map rendered
    from the projector's pose, a shadow map, with a 3x3 minimum so that silhouettes stay out).
    Over them, overall and in the moving region: ``depth_rmse_mm`` and ``column_rmse_px`` (texels)
    over the pixels decoded valid, ``phase_rmse_rad`` (phase_shift; wrapped difference), ``coverage``
    (fraction decoded valid) and ``within_tolerance`` (fraction with |depth error| <=
    ``app.depth_tolerance_mm``; invalid pixels count as misses). ``ambient_in_reads``: the
    flickering ambient group's exact drive-weighted exposure of each read over its exposure time
    (1 = the lamp's mean): equal for interleaved reads, different for sequential frames.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Callable, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from ..output.plots import depth_preview
from ..strict import StrictModel
from ..scene import scenes
from ..errors import ConfigError
from ..metrics import luminance
from ..scene.projective import frame, points_from_depth, triangulate_columns
from ..reconstruct.phase import UNWRAP_METHODS, decode_gray, period_ambiguity, wrapped_phase
from ..render.aov import NEAR_CLIP_M, pixel_cosines, render_depth
from ..timing.timeline import ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol

AMBIENT_READ = "ambient"
SCENE_KEY = "structured_light"


def scene_info(scene) -> dict:
    info = scene.extra.get(SCENE_KEY)
    if not info:
        raise ConfigError(
            f"scene.name: scene {scene.name!r} has no projector patterns "
            f"(SceneModel.extra[{SCENE_KEY!r}]); use a structured-light scene"
        )
    return info


# --------------------------------------------------------------------------------- protocol
@register_protocol("structured_light", app="structured_light")
def structured_light_protocol(cfg):
    """Buckets 1..N: the scene's pattern groups, T/N_p each per period; bucket N+1 (if any): ambient."""

    groups = list(scene_info(scenes.make_scene(cfg.scene.name, cfg.scene.params()))["groups"])
    n, have = len(groups), cfg.sensor.bucket_count
    if have < n:
        raise ConfigError(
            f"capture.protocol: 'structured_light' with {n} patterns needs {n} buckets (and one more for "
            f"the ambient image) but sensor.bucket_count is {have}"
        )
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    slots = [SlotSeconds(b, T / N, frozenset({g})) for b, g in enumerate(groups)]
    reads = [ReadEvent(g, (b,)) for b, g in enumerate(groups)]
    if have > n:
        slots.append(SlotSeconds(n, T / N))
        reads.append(ReadEvent(AMBIENT_READ, (n,)))
    return slots, reads, n + (1 if have > n else 0)


# --------------------------------------------------------------------------------- params
class StructuredLightParams(StrictModel):
    ambient: Literal["auto", "subtract", "none"] = Field(
        "auto",
        description="Ambient light: 'auto' subtracts the ambient-only read when the capture has one, 'subtract' "
        "requires it, 'none' decodes the pattern reads as they are (report.json scores both decodings anyway).",
    )
    unwrap: str = Field(
        "depth_range",
        description="Phase unwrapping (phase_shift patterns): depth_range (per pixel, the one "
        "period whose triangulated depth lies in [depth_min_m, depth_max_m]), spatial (scikit-image "
        "unwrap_phase plus one global offset) or none (single-period patterns).",
    )
    depth_min_m: float = Field(
        0.7,
        gt=0.0,
        description="Nearest depth along the camera's axis the scene can have, m "
        "(depth_range unwrapping; decoded depths outside [depth_min_m, depth_max_m] are invalid).",
    )
    depth_max_m: float = Field(1.6, gt=0.0, description="Farthest depth along the camera's axis the scene can have, m.")
    min_modulation_fraction: float = Field(
        0.05,
        ge=0.0,
        lt=1.0,
        description="A pixel is decoded only where its "
        "pattern modulation (phase_shift: B; gray_code: the white image's projector "
        "light) is at least this fraction of its 99th percentile.",
    )
    depth_tolerance_mm: float = Field(
        10.0, gt=0.0, description="Metric within_tolerance: |depth error| at most this, mm."
    )

    @field_validator("unwrap")
    @classmethod
    def _unwrap(cls, v: str) -> str:
        if v not in UNWRAP_METHODS:
            raise ValueError(f"unknown phase unwrapping {v!r}; expected one of {sorted(UNWRAP_METHODS)}")
        return v

    @model_validator(mode="after")
    def _range(self) -> "StructuredLightParams":
        if self.depth_max_m <= self.depth_min_m:
            raise ValueError(f"depth_max_m ({self.depth_max_m}) must exceed depth_min_m ({self.depth_min_m})")
        return self


def _valid_fraction(signal: np.ndarray, fraction: float, bad: np.ndarray) -> np.ndarray:
    """Good pixels (not ``bad``, finite, > 0) whose signal is at least ``fraction`` of the 99th
    percentile over the good pixels (a NaN would otherwise make the percentile, and every pixel, NaN)."""
    good = ~bad & np.isfinite(signal)
    ref = float(np.percentile(signal[good], 99)) if good.any() else 0.0
    return good & (signal >= fraction * ref) & (signal > 0)


def decode_phase_shift(images, ambient, info, bad, tri, p: StructuredLightParams) -> dict:
    """images (N, H, W) pattern luminances, ambient (H, W) or None: phase, column, depth, valid."""
    imgs = images - ambient[None] if ambient is not None else images
    phase, mod, mean = wrapped_phase(imgs, info["phase_shifts_rad"])
    valid = _valid_fraction(mod, p.min_modulation_fraction, bad)
    w = info["projector_size_px"][0]
    u, z, ok = UNWRAP_METHODS[p.unwrap](phase, valid, tri, info["fringe_periods"], w, p.depth_min_m, p.depth_max_m)
    return {"phase": phase, "modulation": mod, "column": u, "depth": z, "valid": ok}


def decode_gray_code(images, ambient, info, bad, tri, p: StructuredLightParams) -> dict:
    """images (1 + M, H, W): the white pattern then the bits, most significant first."""
    white, bits = images[0], images[1:]
    stripe = decode_gray(white, bits, ambient)
    w = info["projector_size_px"][0]
    u = (stripe + 0.5) * w / 2 ** bits.shape[0]
    z = tri(u)
    light = white - ambient if ambient is not None else white
    with np.errstate(invalid="ignore"):
        ok = _valid_fraction(light, p.min_modulation_fraction, bad) & (z >= p.depth_min_m) & (z <= p.depth_max_m)
    return {
        "phase": None,
        "modulation": light,
        "column": np.where(ok, u, np.nan),
        "depth": np.where(ok, z, np.nan),
        "valid": ok,
    }


#: Pattern decoders by the scene's pattern kind: ``fn(images, ambient, info, bad, triangulate, params) -> dict``.
DECODERS: dict[str, Callable] = {"phase_shift": decode_phase_shift, "gray_code": decode_gray_code}


# --------------------------------------------------------------------------------- metrics
def depth_scores(
    z, valid, u, phase, truth: dict, lit: np.ndarray, tolerance_mm: float, periods: int | None, proj_width: int
) -> dict:
    """Depth and phase errors over the truly lit pixels ``lit`` (see module doc)."""
    n_lit = int(lit.sum())
    if n_lit == 0:
        return {"pixels": 0}
    both = lit & valid
    err_mm = (z - truth["z_m"]) * 1e3
    out = {
        "pixels": n_lit,
        "coverage": float(both.sum() / n_lit),
        "within_tolerance": float(np.sum(both & (np.abs(np.nan_to_num(err_mm, nan=np.inf)) <= tolerance_mm)) / n_lit),
    }
    if both.any():
        out["depth_rmse_mm"] = float(np.sqrt(np.mean(err_mm[both] ** 2)))
        out["depth_median_abs_mm"] = float(np.median(np.abs(err_mm[both])))
        out["column_rmse_px"] = float(np.sqrt(np.mean((u[both] - truth["u_px"][both]) ** 2)))
        if phase is not None and periods:
            dphi = np.angle(np.exp(1j * (phase[both] - 2 * np.pi * periods * truth["u_px"][both] / proj_width)))
            out["phase_rmse_rad"] = float(np.sqrt(np.mean(dphi**2)))
    return out


def ambient_in_reads(data: CaptureData) -> dict | None:
    """Per read: the ambient group's drive-weighted exposure / the read's exposure (1 = the lamp's mean)."""
    tl, scene = data.timeline, data.scene
    amb = [g for g in scene.groups if g not in scene.switchable]
    if not amb:
        return None
    edges = np.array([tl.start_tick, tl.end_tick], dtype=np.int64)
    w = tl.weights_ticks(edges, amb, scene.switchable, scene.drives)[0]  # (K, G_amb) ticks
    out = {}
    for i, r in enumerate(tl.reads):
        ticks = tl.read_exposure_ticks(r)
        out[r.name] = float(w[list(r.buckets)].sum(axis=0).mean() / ticks) if ticks else None
    vals = [v for n, v in out.items() if n != AMBIENT_READ and v is not None]
    return {"per_read": out, "pattern_reads_spread": float(max(vals) - min(vals)) if vals else 0.0}


# --------------------------------------------------------------------------------- truth
def projector_depth(renderer, projector, width: int, height: int, t_s: float) -> np.ndarray:
    """(height, width) depth along the projector's axis of what each of its texel centres lights
    (a shadow map; inf where nothing), rendered with Mitsuba's aov integrator from its pose."""

    mi = renderer.mitsuba
    renderer.set_time(t_s)
    sensor = mi.load_dict(
        {
            "type": "perspective",
            "fov": float(projector.fov_deg),
            "fov_axis": "x",
            "near_clip": NEAR_CLIP_M,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=list(projector.origin), target=list(projector.target), up=list(projector.up)
            ),
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}},
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        }
    )
    integ = mi.load_dict({"type": "aov", "aovs": "dd.y:depth"})
    img = np.asarray(mi.render(renderer.mitsuba_scene, sensor=sensor, integrator=integ, spp=1, seed=0), np.float64)
    t = img[..., -1]
    cos = pixel_cosines(projector, width, height)
    return np.where(t > 0, (t + NEAR_CLIP_M / cos) * cos, np.inf)


def lit_by_projector(
    points: np.ndarray, projector, shadow_map: np.ndarray, proj_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """(lit (H, W) bool, projector column u (H, W)) of world points (H, W, 3): inside the projector's field
    and no nearer than the 3x3 minimum of the shadow map around their texel (plus 2 mm + 0.2 %)."""
    from scipy.ndimage import minimum_filter

    w, h = proj_size
    finite = np.all(np.isfinite(points), axis=-1)
    pts = np.where(finite[..., None], points, 0.0)
    o, fwd, _, _ = frame(projector)
    zp = (pts - o) @ fwd
    uv = projector.project(np.where((zp > 1e-6)[..., None], pts, o + fwd), w, h)
    u, v = uv[..., 0], uv[..., 1]
    inside = finite & (zp > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    sm = minimum_filter(shadow_map, size=3, mode="nearest")
    iu = np.clip(np.floor(u).astype(int), 0, w - 1)
    iv = np.clip(np.floor(v).astype(int), 0, h - 1)
    lit = inside & (zp <= sm[iv, iu] * 1.002 + 0.002)
    return lit, np.where(finite, u, np.nan)


def _truth(data: CaptureData, info: dict) -> dict:
    tl = data.timeline
    t_mid = float(Fraction(tl.start_tick + tl.end_tick, 2) * tl.tick_s)
    cam = data.scene.camera
    d = render_depth(data.renderer, t_mid)
    z = np.where(np.isfinite(d.z_m), d.z_m, np.nan)
    pts = points_from_depth(cam, np.nan_to_num(z, nan=0.0))
    pts[~np.isfinite(z)] = np.nan
    pw, ph = info["projector_size_px"]
    sm = projector_depth(data.renderer, info["projector"], pw, ph, t_mid)
    lit, u = lit_by_projector(pts, info["projector"], sm, (pw, ph))
    return {"t_s": t_mid, "z_m": z, "u_px": u, "lit": lit}


# --------------------------------------------------------------------------------- app
def _roles(data: CaptureData, info: dict) -> tuple[list[int], int | None]:
    names = data.read_names
    missing = [g for g in info["groups"] if g not in names]
    if missing:
        raise ConfigError(
            f"capture.protocol: structured_light needs one read per pattern group {list(info['groups'])} "
            f"(missing {missing}; reads {names})"
        )
    return [names.index(g) for g in info["groups"]], (names.index(AMBIENT_READ) if AMBIENT_READ in names else None)


CAPTIONS = {
    "depth": "decoded depth, turbo colour map: app.depth_min_m (near) to app.depth_max_m (far); black = not decoded",
    "depth_truth": "reference: the depth AOV at the capture's mid-time where the projector lights the scene, same scale",
    "depth_error": "|decoded - true depth|: black = 0, white = 4 x app.depth_tolerance_mm or more; blue = lit but not "
    "decoded",
}


def _scores(dec: dict, truth: dict, lit: np.ndarray, mask: np.ndarray, tolerance_mm: float, periods, pw: int) -> dict:
    """One decoding's depth scores against the truth: over the lit pixels, and over those of the moving region."""
    args = (dec["depth"], dec["valid"], dec["column"], dec["phase"], truth)
    row = {"all": depth_scores(*args, lit, tolerance_mm, periods, pw)}
    if mask.any():
        row["moving_region"] = depth_scores(*args, lit & mask, tolerance_mm, periods, pw)
    return row


def _error_preview(err_mm: np.ndarray, undecoded: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """(H, W, 3) |depth error|: black 0, white 4 x the tolerance or more; blue where lit but not decoded."""
    e_rgb = np.repeat(np.clip(np.nan_to_num(err_mm, nan=0.0) / (4 * tolerance_mm), 0, 1)[..., None], 3, -1)
    e_rgb[undecoded] = (0.0, 0.0, 1.0)  # lit but not decoded: blue
    return e_rgb.astype(np.float32)


@register(
    "structured_light",
    output_channels=22,
    previews=3,
    libraries_mb=60,
    params=StructuredLightParams,
    pinhole_truth="triangulation through the pinhole camera and projector; truth depth from the aov",
    description="structured light: ambient-subtracted phase shifting or Gray code, unwrapping, triangulated depth",
)
def reconstruct(data: CaptureData, params: StructuredLightParams) -> AppOutput:
    cfg = data.cfg
    W, H = cfg.render.width, cfg.render.height
    info = scene_info(data.scene)
    kind = info["kind"]
    if kind not in DECODERS:
        raise ConfigError(f"scene: unknown pattern kind {kind!r}; expected one of {sorted(DECODERS)}")
    pat_idx, amb_idx = _roles(data, info)
    if params.ambient == "subtract" and amb_idx is None:
        raise ConfigError(
            "app.ambient: 'subtract' needs an ambient-only read (sensor.bucket_count > number of patterns)"
        )
    rate = data.reads_e() / (data.k_e * data.exposure_s[:, None, None, None])
    lum = luminance(rate)
    used = pat_idx + ([amb_idx] if amb_idx is not None else [])
    bad = data.saturated[used].any(axis=(0, -1))
    images = lum[pat_idx]
    ambient = lum[amb_idx] if amb_idx is not None else None
    proj, pw = info["projector"], info["projector_size_px"][0]

    def tri(u):
        return triangulate_columns(data.scene.camera, proj, u, pw, W, H)

    modes = {"ambient_ignored": None}
    if ambient is not None:
        modes = {"ambient_subtracted": ambient, **modes}
    chosen = "ambient_ignored" if params.ambient == "none" or ambient is None else "ambient_subtracted"
    decoded = {m: DECODERS[kind](images, a, info, bad, tri, params) for m, a in modes.items()}
    main = decoded[chosen]

    periods = info.get("fringe_periods")
    metrics: dict = {
        "patterns": kind,
        "pattern_reads": [data.read_names[i] for i in pat_idx],
        "ambient_read": amb_idx is not None,
        "decoding": chosen,
        "unwrap": params.unwrap if kind == "phase_shift" else "not needed (absolute Gray code)",
        "saturated_px": int(bad.sum()),
        "ambient_in_reads": ambient_in_reads(data),
    }
    if kind == "phase_shift":
        metrics["period_ambiguity"] = period_ambiguity(
            data.scene.camera, proj, pw, periods, W, H, params.depth_min_m, params.depth_max_m
        )
    out_images = {
        "depth": np.nan_to_num(main["depth"], nan=0.0).astype(np.float32),
        "decoded": main["valid"].astype(np.float32),
        "modulation": main["modulation"].astype(np.float32),
        "depth_preview": depth_preview(main["depth"], params.depth_min_m, params.depth_max_m),
    }
    if main["phase"] is not None:
        out_images["phase"] = main["phase"].astype(np.float32)
    if ambient is not None:
        out_images["ambient"] = rate[amb_idx]
    if "ambient_subtracted" in decoded:
        out_images["depth_preview_ambient_ignored"] = depth_preview(
            decoded["ambient_ignored"]["depth"], params.depth_min_m, params.depth_max_m
        )
    png = {"depth": ("depth_preview", None)}
    summary = [f"structured light ({kind}, {chosen}): {int(main['valid'].sum())} pixels decoded"]

    if data.renderer is not None:
        truth = _truth(data, info)
        lit, mask = truth["lit"], data.moving_mask
        scores = {
            m: _scores(dec, truth, lit, mask, params.depth_tolerance_mm, periods, pw) for m, dec in decoded.items()
        }
        metrics["truth"] = {
            "time_s": truth["t_s"],
            "lit_px": int(lit.sum()),
            "moving_px": int(mask.sum()),
            "tolerance_mm": params.depth_tolerance_mm,
            "what": "depth AOV at the capture's mid-time; pixels the projector lights (shadow map)",
        }
        metrics["depth"] = scores
        out_images["depth_truth"] = np.nan_to_num(truth["z_m"], nan=0.0).astype(np.float32)
        out_images["lit_truth"] = lit.astype(np.float32)
        err = np.where(lit & main["valid"], np.abs(main["depth"] - truth["z_m"]) * 1e3, np.nan)
        out_images["depth_error_mm"] = np.nan_to_num(err, nan=0.0).astype(np.float32)
        out_images["error_preview"] = _error_preview(err, lit & ~main["valid"], params.depth_tolerance_mm)
        out_images["depth_truth_preview"] = depth_preview(
            np.where(lit, truth["z_m"], np.nan), params.depth_min_m, params.depth_max_m
        )
        png |= {"depth_truth": ("depth_truth_preview", None), "depth_error": ("error_preview", None)}
        a = scores[chosen]["all"]
        fmt = lambda v: "n/a" if v is None else f"{v:.3g}"  # noqa: E731
        summary.append(
            f"depth RMSE {fmt(a.get('depth_rmse_mm'))} mm, {100 * a.get('within_tolerance', 0):.1f}% within "
            f"{params.depth_tolerance_mm:g} mm, coverage {100 * a.get('coverage', 0):.1f}%"
        )
        if "ambient_subtracted" in scores:
            b = scores["ambient_ignored"]["all"]
            summary.append(
                f"without the ambient bucket: RMSE {fmt(b.get('depth_rmse_mm'))} mm, "
                f"{100 * b.get('within_tolerance', 0):.1f}% within tolerance"
            )
    return AppOutput(images=out_images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)
