"""Flash / no-flash: one bucket sees the scene lit by a pulsed flash, another by ambient light only.

Protocol ``flash_no_flash``: per period (2 ``unit_exposure_s / periods`` long) a slot into bucket 1 with
the ``flash`` group on, then one into bucket 2 with the flash off; ``app.flash_share`` (0.5) splits the period
between them and ``app.flash_duty`` (1) is the share of bucket 1's slot the flash is on. Both
buckets see the same motion, so their ambient components carry the same motion blur, and
``flash - noflash`` is the flash-only image even where things move. With
``capture.sequential: true`` the same two exposures are taken one after another (flash frame
first, ``sensor.frame_readout_s`` between them): the moving parts are elsewhere in the second
frame, and the difference shows ghosts.

Reconstruction (``app.method``, a small registry :data:`METHODS`), after Petschnigg et al.,
"Digital photography with flash and no-flash image pairs", SIGGRAPH 2004:

``petschnigg``       A_final = (1 - M) A_NR F_detail + M A_base: the ambient image denoised by a
                     joint bilateral filter whose range kernel looks at the flash image (A_NR),
                     times the flash image's detail layer F_detail = (F + eps) / (F_base + eps),
                     falling back to the plain bilateral A_base inside the mask M of flash
                     shadows and flash specularities (saturation).
``joint_bilateral``  A_NR alone (denoising guided by the flash, no detail transfer, no mask).
``bilateral``        A_base: the ambient image's own bilateral filter (the flash is not used).
``none``             the no-flash read as it is.

All images are radiance (W m^-2 sr^-1): reads in electrons divided by k_e and their exposure.
The filters' range kernels work on images scaled so that the ``app.white_percentile``
luminance percentile is 1, so ``app.sigma_range`` and ``app.detail_eps`` are fractions of white.

Ground truths come from the noise-free per-group exposures (``per_group``): the ambient image
(every group but the flash) seen by the no-flash read, the flash-only image seen by the flash
read, and the ambient component inside the flash read, which must match the no-flash read's
motion blur.
"""

from __future__ import annotations

import dataclasses
from fractions import Fraction
from typing import Callable, Literal

import numpy as np
from pydantic import Field

from ..strict import StrictModel
from ..scene.camera_motion import moving_region
from ..errors import ConfigError
from ..metrics import luminance, psnr, relative_mse
from ..timing.timeline import ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol
from .hdr import REL_MSE_EPS_RADIANCE

#: The switchable emitter group the protocol pulses.
FLASH_GROUP = "flash"


#: What each preview shows (report.html); mask.png's channels are (shadow, specular, M).
CAPTIONS = {
    "flash": "the flash read as radiance (ambient light plus the flash)",
    "noflash": "the no-flash read as radiance (ambient light only)",
    "flash_only": "flash minus no-flash: the scene lit by the flash alone",
    "enhanced": "the no-flash image enhanced with the flash image (app.method)",
    "truth_ambient": "reference: the noise-free ambient image the no-flash read saw",
    "truth_flash_only": "reference: the noise-free flash-only image the flash read saw",
    "mask": "Petschnigg's mask: red = flash shadow, green = flash specularity (saturation), blue = M, the "
    "dilated and feathered union of both, where the enhanced image falls back to the no-flash bilateral "
    "base; so magenta = shadow inside M, cyan = specularity inside M, pure blue = M's feathered rim, "
    "black = detail transfer applies",
}


# ----------------------------------------------------------------------------- protocol
@register_protocol("flash_no_flash", app="flash_no_flash")
def flash_no_flash_protocol(cfg):
    """One period of 2 T / N: bucket 1 (the flash on for ``app.flash_duty`` of its slot) for ``app.flash_share``
    of it, then bucket 2 ambient only; reads ``flash`` (bucket 1) and ``noflash`` (bucket 2); with the defaults
    each integrates T = unit_exposure_s."""
    if cfg.sensor.bucket_count < 2:
        raise ConfigError(
            f"capture.protocol: 'flash_no_flash' needs 2 buckets but sensor.bucket_count is {cfg.sensor.bucket_count}"
        )
    _, params = cfg.app.resolve(cfg.capture.protocol)
    # another application reconstructing this schedule (app.name) has no split keys: the defaults
    share = exact(getattr(params, "flash_share", FlashNoFlashParams().flash_share))
    duty = exact(getattr(params, "flash_duty", FlashNoFlashParams().flash_duty))
    period = 2 * exact(cfg.capture.unit_exposure_s) / Fraction(cfg.capture.periods)
    lit, dark = period * share * duty, period * share * (1 - duty)
    slots = [SlotSeconds(0, lit, frozenset({FLASH_GROUP}))] + ([SlotSeconds(0, dark)] if dark > 0 else [])
    slots.append(SlotSeconds(1, period * (1 - share)))
    reads = [ReadEvent("flash", (0,)), ReadEvent("noflash", (1,))]
    return slots, reads, 2


# ----------------------------------------------------------------------------- parameters
class FlashNoFlashParams(StrictModel):
    flash_share: float = Field(
        0.5,
        gt=0.0,
        lt=1.0,
        description="Bucket split: the share of each period the flash bucket collects (the no-flash bucket the "
        "rest); 0.5: T each. The capture spans 2 x capture.unit_exposure_s whatever the split.",
    )
    flash_duty: float = Field(
        1.0,
        gt=0.0,
        le=1.0,
        description="Flash duty: the share of the flash bucket's slot with the flash on (its start; the flash "
        "bucket collects ambient light for the rest). 1: on for the whole slot.",
    )
    method: Literal["petschnigg", "joint_bilateral", "bilateral", "none"] = Field(
        "petschnigg",
        description="Enhanced image: 'petschnigg' (joint bilateral + detail transfer + shadow/specular mask), "
        "'joint_bilateral' (flash-guided denoising only), 'bilateral' (no-flash image's own bilateral), "
        "'none' (the no-flash read). Metrics list every method.",
    )
    sigma_spatial_px: float = Field(
        1.5,
        gt=0,
        le=50,
        description="Spatial Gaussian sigma of the bilateral filters, pixels (window radius 2.5 sigma).",
    )
    sigma_range: float = Field(
        0.05,
        gt=0,
        description="Range sigma of the joint bilateral filter on the flash image, fraction of its white "
        "(the range distance is the sum of the absolute differences over R, G and B: OpenCV's ximgproc).",
    )
    ambient_sigma_range: float = Field(
        0.1,
        gt=0,
        description="Range sigma of the plain bilateral filter of the (noisy) no-flash image, fraction of its white.",
    )
    detail_eps: float = Field(
        0.02,
        gt=0,
        description="eps of the detail layer (F + eps) / (F_base + eps), fraction of the flash image's white.",
    )
    shadow_threshold: float = Field(
        0.05,
        ge=0,
        lt=1,
        description="Flash shadow: flash-only luminance below this fraction of its white (Petschnigg's tau_shad).",
    )
    specular_fraction: float = Field(
        0.95,
        gt=0,
        le=1,
        description="Flash specularity: flash read at or above this fraction of sensor.full_well_e, or saturated.",
    )
    mask_dilate_px: int = Field(1, ge=0, le=50, description="Dilation of the shadow/specular mask, pixels.")
    mask_feather_px: float = Field(1.0, ge=0, le=50, description="Gaussian sigma that feathers the mask, pixels.")
    white_percentile: float = Field(
        99.0,
        gt=0,
        le=100,
        description="Luminance percentile that is white (1.0) for the range kernels, detail eps, thresholds and PSNR peak.",
    )


# ----------------------------------------------------------------------------- filters
def white_level(rgb: np.ndarray, percentile: float) -> float:
    """The ``percentile`` of the image's luminance (1.0 if that is not positive)."""
    w = float(np.percentile(luminance(rgb), percentile))
    return w if w > 0 else 1.0


def joint_bilateral(
    image: np.ndarray, guide: np.ndarray, sigma_spatial_px: float, sigma_range: float, truncate: float = 2.5
) -> np.ndarray:
    """Joint (cross) bilateral filter: OpenCV's ``ximgproc.jointBilateralFilter`` (opencv-contrib).

    out(p) = sum_q w(p, q) image(q) / sum_q w(p, q),
    w(p, q) = exp(-|p - q|^2 / (2 sigma_s^2)) exp(-d(guide(p), guide(q))^2 / (2 sigma_r^2)),

    with d the sum of the absolute differences over the guide's channels (OpenCV's rule for a
    colour guide; for one channel, the absolute difference), q over the disc of radius
    ceil(truncate sigma_s), and the borders mirrored (edge-repeated when the image is narrower
    than the window: numpy pads, OpenCV filters the inside). ``guide = image`` is the plain
    bilateral filter. image (H, W, C), guide (H, W) or (H, W, C) with C <= 3. OpenCV computes in
    float32 and takes the range kernel from a table (relative error ~1e-6 against the definition,
    tests/test_app_flash_no_flash.py); returned as float64.
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    g = np.asarray(guide, dtype=np.float32)
    if g.ndim == 3 and g.shape[-1] == 1:
        g = g[..., 0]
    if g.ndim == 3 and g.shape[-1] == 2:  # OpenCV takes 1 or 3: a constant third channel adds nothing to d
        g = np.concatenate([g, np.zeros_like(g[..., :1])], axis=-1)
    if g.ndim not in (2, 3) or (g.ndim == 3 and g.shape[-1] != 3):
        raise ValueError(f"guide: expected (H, W) or (H, W, C) with C <= 3, got {g.shape}")
    if img.ndim != 3 or img.shape[:2] != g.shape[:2]:
        raise ValueError(f"image {img.shape} and guide {g.shape} differ in size")
    H, W = img.shape[:2]
    r = int(np.ceil(truncate * sigma_spatial_px))
    mode = "reflect" if min(H, W) > r else "edge"
    g_p = np.pad(g, ((r, r), (r, r)) + ((0, 0),) * (g.ndim - 2), mode=mode)
    img_p = np.pad(img, ((r, r), (r, r), (0, 0)), mode=mode)
    # OpenCV filters one or three channels at a time
    planes = [img_p] if img.shape[-1] == 3 else [np.ascontiguousarray(img_p[..., c]) for c in range(img.shape[-1])]
    out = [
        cv2.ximgproc.jointBilateralFilter(
            g_p, plane, 2 * r + 1, float(sigma_range), float(sigma_spatial_px), borderType=cv2.BORDER_REFLECT_101
        )
        for plane in planes
    ]
    filtered = out[0] if img.shape[-1] == 3 else np.stack(out, axis=-1)
    return np.asarray(filtered[r : r + H, r : r + W], dtype=np.float64)


def flash_mask(
    flash_only_n: np.ndarray, specular: np.ndarray, shadow_threshold: float, dilate_px: int, feather_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, shadow, specular): Petschnigg's mask of flash shadows and specularities.

    flash_only_n (H, W, C) flash-only image scaled to its white; specular (H, W) bool. Shadow:
    flash-only luminance below ``shadow_threshold``, opened by a 3x3 element (drops isolated
    noise pixels). Both masks are dilated by ``dilate_px``, joined, and feathered by a Gaussian
    of sigma ``feather_px``; M is in [0, 1].
    """
    from scipy import ndimage

    shadow = luminance(flash_only_n) < shadow_threshold
    shadow = ndimage.binary_opening(shadow, structure=np.ones((3, 3), bool))
    spec = np.asarray(specular, bool)
    if dilate_px > 0:
        disc = np.hypot(*np.mgrid[-dilate_px : dilate_px + 1, -dilate_px : dilate_px + 1]) <= dilate_px
        shadow = ndimage.binary_dilation(shadow, structure=disc)
        spec = ndimage.binary_dilation(spec, structure=disc)
    m = (shadow | spec).astype(np.float64)
    if feather_px > 0:
        m = ndimage.gaussian_filter(m, feather_px, mode="nearest")
    return np.clip(m, 0.0, 1.0), shadow, spec


@dataclasses.dataclass
class Components:
    """The pieces every method is made of (radiance unless noted)."""

    ambient: np.ndarray  # A, the no-flash image
    flash: np.ndarray  # F, the flash image
    a_nr: np.ndarray  # joint bilateral of A, range kernel on F
    a_base: np.ndarray  # bilateral of A
    f_detail: np.ndarray  # (F + eps) / (F_base + eps), dimensionless
    mask: np.ndarray  # (H, W) in [0, 1]
    shadow: np.ndarray  # (H, W) bool
    specular: np.ndarray  # (H, W) bool


#: method -> (combine(components) -> enhanced image, description)
METHODS: dict[str, tuple[Callable[[Components], np.ndarray], str]] = {
    "petschnigg": (
        lambda c: (1.0 - c.mask[..., None]) * c.a_nr * c.f_detail + c.mask[..., None] * c.a_base,
        "(1 - M) A_NR F_detail + M A_base",
    ),
    "joint_bilateral": (lambda c: c.a_nr, "A_NR: joint bilateral of A guided by F"),
    "bilateral": (lambda c: c.a_base, "A_base: bilateral of A"),
    "none": (lambda c: c.ambient, "the no-flash image"),
}


def components(ambient: np.ndarray, flash: np.ndarray, specular: np.ndarray, p: FlashNoFlashParams) -> Components:
    """Filter the no-flash image ``ambient`` and the flash image ``flash`` (radiance, (H, W, C))."""
    a = np.asarray(ambient, dtype=np.float64)
    f = np.asarray(flash, dtype=np.float64)
    wa, wf = white_level(a, p.white_percentile), white_level(f, p.white_percentile)
    f_n = f / wf
    a_nr = joint_bilateral(a, f_n, p.sigma_spatial_px, p.sigma_range)
    a_base = wa * joint_bilateral(a / wa, a / wa, p.sigma_spatial_px, p.ambient_sigma_range)
    f_base_n = joint_bilateral(f_n, f_n, p.sigma_spatial_px, p.sigma_range)
    f_detail = (f_n + p.detail_eps) / (f_base_n + p.detail_eps)
    fo = f - a
    mask, shadow, spec = flash_mask(
        fo / white_level(fo, p.white_percentile), specular, p.shadow_threshold, p.mask_dilate_px, p.mask_feather_px
    )
    return Components(a, f, a_nr, a_base, f_detail, mask, shadow, spec)


def enhance(c: Components, method: str) -> np.ndarray:
    if method not in METHODS:
        raise ConfigError(f"app.method: unknown method {method!r}; expected one of {sorted(METHODS)}")
    return METHODS[method][0](c)


# ----------------------------------------------------------------------------- metrics
def rel_rms(x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> float:
    """RMS of x - y over ``mask`` (H, W), relative to the mean of y there."""
    ref = float(np.mean(y[mask])) or 1.0
    return float(np.sqrt(np.mean((x[mask] - y[mask]) ** 2)) / ref)


def display_psnr(x: np.ndarray, truth: np.ndarray, white: float, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of the images as displayed: both clipped to [0, white], peak = white."""
    m = None if mask is None else np.broadcast_to(mask[..., None], truth.shape)
    return psnr(np.clip(x, 0, white), np.clip(truth, 0, white), mask=m, peak=white)


def _read_roles(data: CaptureData) -> tuple[int, int, list[str]]:
    """(flash read, no-flash read, flash groups) from the timeline: the flash read's buckets saw a
    switchable group, the no-flash read's did not."""
    if len(data.read_names) != 2 or data.bucket_group_s is None:
        raise ConfigError(
            f"capture.protocol: flash_no_flash needs exactly two reads, one lit by a switchable group and one not "
            f"(got reads {data.read_names})"
        )
    lit = []
    for read in data.timeline.reads:
        seen = data.bucket_group_s[list(read.buckets)].sum(axis=0)
        lit.append([g for g, s in zip(data.switchable, seen) if s > 0])
    flash_reads = [i for i, g in enumerate(lit) if g]
    if len(flash_reads) != 1:
        raise ConfigError(
            "capture.protocol: flash_no_flash needs one read lit by a switchable group (the flash) and one "
            f"without; switchable groups seen per read: {dict(zip(data.read_names, lit))}"
        )
    i_f = flash_reads[0]
    return i_f, 1 - i_f, lit[i_f]


def _letter_s_mask(data: CaptureData) -> np.ndarray | None:
    """Pixels the letter S sweeps during the capture, where the scene says which motion points are
    on it (``scene.extra['letter_s_points']``); None otherwise."""
    idx = getattr(data.scene, "extra", {}).get("letter_s_points") if data.scene is not None else None
    if idx is None or data.scene.is_static:
        return None

    tl = data.timeline
    sub = dataclasses.replace(data.scene, motion_points=lambda t: data.scene.motion_points(t)[:, list(idx)])
    H, W = data.moving_mask.shape
    return moving_region(sub, float(tl.seconds(tl.start_tick)), float(tl.seconds(tl.end_tick)), W, H)


def blur_agreement(ambient_in_flash: np.ndarray, ambient_in_noflash: np.ndarray, mask: np.ndarray) -> dict:
    """How differently the two reads saw the ambient light where things move (noise-free, exposure-normalized)."""
    if not mask.any():
        return {"pixels": 0}
    return {"pixels": int(mask.sum()), "rel_rms": rel_rms(ambient_in_flash, ambient_in_noflash, mask)}


def enhancement_scores(comps, enhanced, truth_ambient, white: float, mask, p: FlashNoFlashParams) -> dict:
    """The enhanced image's display PSNR against the ambient truth, and every method's (``by_method``; "none" is
    the no-flash read), over the image and, with ``mask``, the moving region."""
    moving = mask is not None
    by_method = {}
    for name in METHODS:
        img = enhanced if name == p.method else enhance(comps, name)
        row = {"psnr_db": display_psnr(img, truth_ambient, white)}
        if moving:
            row["psnr_db_moving"] = display_psnr(img, truth_ambient, white, mask)
        by_method[name] = row
    enh = {
        "method": p.method,
        "formula": METHODS[p.method][1],
        "psnr_db": by_method[p.method]["psnr_db"],
        "noflash_psnr_db": by_method["none"]["psnr_db"],
        "gain_db": by_method[p.method]["psnr_db"] - by_method["none"]["psnr_db"],
        "peak": f"luminance percentile {p.white_percentile} of the ambient truth, {white:.4g} W m^-2 sr^-1",
    }
    if moving:
        enh["psnr_db_moving"] = by_method[p.method]["psnr_db_moving"]
        enh["noflash_psnr_db_moving"] = by_method["none"]["psnr_db_moving"]
        enh["gain_db_moving"] = enh["psnr_db_moving"] - enh["noflash_psnr_db_moving"]
    enh["by_method"] = by_method
    return enh


def _summary(blur: dict, fo: dict, enh: dict, method: str, moving: bool) -> list[str]:
    """The lines the CLI prints after a run."""
    summary = []
    if moving:
        mb = blur["letter_s" if "letter_s" in blur else "moving_region"]
        where = "letter S" if "letter_s" in blur else "moving region"
        summary.append(
            f"motion blur agreement ({where}): ambient in flash vs no-flash read, rel RMS {100 * mb['rel_rms']:.2f}%"
        )
        summary.append(f"flash-only relMSE {fo['rel_mse']:.4g} (moving region {fo['rel_mse_moving']:.4g})")
        summary.append(
            f"enhanced ({method}) PSNR {enh['psnr_db']:.2f} dB vs no-flash {enh['noflash_psnr_db']:.2f} dB; "
            f"moving region {enh['psnr_db_moving']:.2f} vs {enh['noflash_psnr_db_moving']:.2f} dB"
        )
    else:
        summary.append(
            f"flash-only relMSE {fo['rel_mse']:.4g}; enhanced ({method}) PSNR {enh['psnr_db']:.2f} dB "
            f"vs no-flash {enh['noflash_psnr_db']:.2f} dB"
        )

    return summary


@register(
    "flash_no_flash",
    renders=False,
    output_channels=33,
    previews=7,
    libraries_mb=90,
    params=FlashNoFlashParams,
    per_group=True,
    description="flash, no-flash, flash-only and Petschnigg-enhanced images (app.method), blur agreement",
)
def reconstruct(data: CaptureData, p: FlashNoFlashParams) -> AppOutput:
    if data.group_exposure is None:
        raise ConfigError("app.name: flash_no_flash needs per-group exposures (per_group)")
    i_f, i_a, flash_groups = _read_roles(data)
    groups = list(data.plan.groups)
    g_flash = [groups.index(g) for g in flash_groups if g in groups]
    g_amb = [i for i, g in enumerate(groups) if g not in flash_groups]
    b_f, b_a = list(data.timeline.reads[i_f].buckets), list(data.timeline.reads[i_a].buckets)
    t_f, t_a = float(data.exposure_s[i_f]), float(data.exposure_s[i_a])

    # reads -> radiance
    e = data.reads_e()
    flash = e[i_f] / (data.k_e * t_f)
    ambient = e[i_a] / (data.k_e * t_a)
    flash_only = flash - ambient

    # noise-free truths from the per-group exposures
    ge = data.group_exposure
    truth_ambient = ge[b_a][:, g_amb].sum(axis=(0, 1)) / t_a
    truth_flash_only = ge[b_f][:, g_flash].sum(axis=(0, 1)) / t_f
    ambient_in_flash = ge[b_f][:, g_amb].sum(axis=(0, 1)) / t_f

    full_well = data.cfg.sensor.full_well_e
    specular = data.saturated[i_f].any(-1) | (data.reads_e_expected[i_f] >= p.specular_fraction * full_well).any(-1)
    comps = components(ambient, flash, specular, p)
    enhanced = enhance(comps, p.method)

    # metrics
    mask = data.moving_mask
    s_mask = _letter_s_mask(data)
    white = white_level(truth_ambient, p.white_percentile)
    n_ch = flash.shape[-1]
    moving = mask.any()
    mmask = np.repeat(mask[..., None], n_ch, -1)
    blur = {"moving_region": blur_agreement(ambient_in_flash, truth_ambient, mask)}
    if s_mask is not None:
        blur["letter_s"] = blur_agreement(ambient_in_flash, truth_ambient, s_mask)
    fo = {"rel_mse": relative_mse(flash_only, truth_flash_only, eps=REL_MSE_EPS_RADIANCE)}
    if moving:
        fo["rel_mse_moving"] = relative_mse(flash_only, truth_flash_only, mask=mmask, eps=REL_MSE_EPS_RADIANCE)
        # the ghosts alone: noise-free flash read minus noise-free no-flash read, against the truth. Only in
        # the moving region: elsewhere a sequential capture's two frames differ by render noise only
        fo["ghost_rel_mse_moving"] = relative_mse(
            ambient_in_flash + truth_flash_only - truth_ambient, truth_flash_only, mask=mmask, eps=REL_MSE_EPS_RADIANCE
        )
    enh = enhancement_scores(comps, enhanced, truth_ambient, white, mask if moving else None, p)
    metrics = {
        "reads": {"flash": data.read_names[i_f], "noflash": data.read_names[i_a]},
        "flash_groups": flash_groups,
        "truth": "noise-free per-group exposures: ambient = all groups but the flash, seen by the no-flash read; "
        "flash-only = the flash group seen by the flash read",
        "motion_blur_agreement": blur,
        "flash_only": fo,
        "enhanced": enh,
        "mask_fraction": {
            "shadow": float(comps.shadow.mean()),
            "specular": float(comps.specular.mean()),
            "mean_M": float(comps.mask.mean()),
        },
    }

    summary = _summary(blur, fo, enh, p.method, moving)

    pct = data.cfg.output.png_percentile
    mask_img = (
        np.stack([comps.shadow.astype(float), comps.specular.astype(float), comps.mask], -1)[..., :n_ch]
        if n_ch >= 3
        else np.repeat(comps.mask[..., None], n_ch, -1)
    )
    return AppOutput(
        images={
            "flash": flash,
            "noflash": ambient,
            "flash_only": flash_only,
            "enhanced": enhanced,
            "denoised": comps.a_nr,
            "detail": comps.f_detail,
            "mask": mask_img,
            "truth_ambient": truth_ambient,
            "truth_flash_only": truth_flash_only,
            "ambient_in_flash": ambient_in_flash,
            "moving": mmask.astype(np.float32),
        },
        metrics=metrics,
        png={
            "flash": ("flash", pct),
            "noflash": ("noflash", pct),
            "flash_only": ("flash_only", pct),
            "enhanced": ("enhanced", pct),
            "truth_ambient": ("truth_ambient", pct),
            "truth_flash_only": ("truth_flash_only", pct),
            "mask": ("mask", None),
        },
        summary=summary,
        captions=CAPTIONS,
    )
