"""Flash matting: a flash lights the near foreground far more than the distant background, so the
flash-only image (flash read minus no-flash read) separates them; a trimap from it and a matting
method turn that into an alpha matte (the paper's section 5.4 and figure 16; Sun, Kang and Shum,
"Flash matting", SIGGRAPH 2006).

Protocol ``flash_matting`` (4 buckets, each collecting ``capture.unit_exposure_s`` = T in total,
over ``capture.periods`` = N periods), ``app.flash_buckets``:

``2``    the 2:2 split: per period: bucket 1 (flash), bucket 3, bucket 4, bucket 2 (flash), each T / N; reads
         ``flash`` = buckets 1 + 2 (2T) and ``noflash`` = buckets 3 + 4 (2T). The slot order is a
         palindrome, so both reads have the same time centroid.
``3``    the 3:1 split: per period: bucket 4 for T / 2N, buckets 1, 2, 3 (flash) T / N each, bucket 4 for T / 2N;
         reads ``flash`` = buckets 1 + 2 + 3 (3T) and ``noflash`` = bucket 4 (T): the brighter flash
         image gets three buckets' full wells, the centroids still coincide.

``capture.sequential: true`` takes the two reads as two frames one after another (flash first):
the leaves move between them and the flash-only difference ghosts.

Reconstruction, in radiance (W m^-2 sr^-1; reads in electrons / k_e / exposure):

1. flash-only image  F = flash rate - no-flash rate (the ambient part cancels where both reads
   saw the same thing).
2. trimap from the flash-only luminance Y, scaled so that its ``app.trimap_reference_percentile``
   percentile is 1: Y >= ``app.trimap_fg_fraction`` is candidate foreground, Y <=
   ``app.trimap_bg_fraction`` candidate background; each is opened (disc of radius
   ``app.trimap_open_px``, removes noise specks) then eroded (radius ``app.trimap_erode_px``), so
   that mixed pixels (edges, motion blur) end up unknown (0.5).
3. alpha from a matting method (``app.matting``, registry :data:`MATTING_METHODS`; pymatting's
   solvers) applied to ``app.matting_image`` (by default the flash read, whose coverage the truth
   is), scaled to [0, 1] by the 99.9th percentile of its largest channel.
4. foreground colours: pymatting's multilevel foreground estimation on the no-flash image;
   ``extracted`` = alpha x foreground (the paper's figure 16c).

Ground truth: the alpha the flash read saw, i.e. the coverage of the scene's foreground shapes
(``SceneModel.extra['foreground']``) integrated over the capture's time strata with the flash
read's weights (:func:`mbcapture.render.coverage.coverage_alpha`), and the noise-free flash-only
image of the flash read (per-group exposures). Metrics: SAD (sum of |alpha - truth|, pixels) and
MSE, over the whole image, the trimap's unknown region and the moving region.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..strict import StrictModel
from ..errors import ConfigError
from ..metrics import luminance, relative_mse
from ..reconstruct.matting import estimate_alpha, make_trimap, reference_level, trimap_cue
from ..render.coverage import coverage_alpha
from ..timing.timeline import ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol
from .hdr import REL_MSE_EPS_RADIANCE

FLASH_READ, NOFLASH_READ = "flash", "noflash"
#: The matting image is divided by this percentile of its largest channel (then clipped to [0, 1]).
MATTING_WHITE_PERCENTILE = 99.9


class FlashMattingParams(StrictModel):
    flash_buckets: Literal[2, 3] = Field(
        2,
        description="How many of the 4 buckets collect with the flash on (read by the flash_matting protocol): 2 is the "
        "2:2 split (flash and no-flash reads of 2T each), 3 the 3:1 split (a flash read of 3T, a no-flash read of T).",
    )
    flash_group: str = Field("flash", description="The scene's switchable emitter group that the protocol pulses.")
    matting: Literal["closed_form", "knn", "lkm", "random_walk", "learning_based", "threshold"] = Field(
        "closed_form",
        description="Alpha matting method: 'closed_form' (Levin et al. 2008), 'knn' (Chen et al. 2013), 'lkm' (large "
        "kernel, He et al. 2010), 'random_walk' (Grady et al. 2005), 'learning_based' (Zheng and Kambhamettu 2009), "
        "all pymatting; 'threshold': alpha ramps linearly in the flash-only luminance between the two trimap fractions.",
    )
    matting_image: Literal["flash_only", "flash", "noflash"] = Field(
        "flash",
        description="Image the matting method sees: the flash read (default: the ground truth is its coverage), the "
        "flash-only difference (its shading falls off towards silhouettes, which reads as partial alpha) or the "
        "no-flash read. report.json scores the chosen method on all three (metrics.alpha_by_image).",
    )
    trimap_cue: Literal["flash_ratio", "flash_only"] = Field(
        "flash_ratio",
        description="What the trimap thresholds: 'flash_ratio' = flash-only luminance / (no-flash luminance + "
        "trimap_ratio_eps x its reference), which cancels the albedo and keeps only the flash's 1/d^2 falloff; "
        "'flash_only' = the flash-only luminance itself.",
    )
    trimap_ratio_eps: float = Field(
        0.05,
        gt=0,
        le=10,
        description="With trimap_cue 'flash_ratio': added to the no-flash luminance, as a fraction of its "
        "trimap_reference_percentile, so that dark, noisy pixels do not blow up the ratio.",
    )
    trimap_reference_percentile: float = Field(
        99.0,
        gt=0,
        le=100,
        description="Percentile of the trimap cue (and of the matting image) that is 1.0 for the trimap fractions.",
    )
    trimap_fg_fraction: float = Field(
        0.25, gt=0, le=1, description="Cue at or above this fraction of its reference: candidate foreground."
    )
    trimap_bg_fraction: float = Field(
        0.15, ge=0, lt=1, description="Cue at or below this fraction of its reference: candidate background."
    )
    trimap_open_px: int = Field(
        1, ge=0, le=20, description="Radius of the opening that removes specks from both candidates, pixels."
    )
    trimap_erode_px: int = Field(
        2,
        ge=0,
        le=50,
        description="Radius by which the definite foreground and background are eroded into unknown, pixels.",
    )
    truth_spp: int = Field(
        16,
        ge=1,
        le=4096,
        description="Samples per pixel per time stratum of the ground-truth coverage render (max_depth 1).",
    )

    @model_validator(mode="after")
    def _fractions_ordered(self) -> "FlashMattingParams":
        if self.trimap_bg_fraction >= self.trimap_fg_fraction:
            raise ValueError(
                f"trimap_bg_fraction ({self.trimap_bg_fraction}) must be below trimap_fg_fraction ({self.trimap_fg_fraction})"
            )
        return self


# ----------------------------------------------------------------------------- protocol
@register_protocol("flash_matting", app="flash_matting")
def flash_matting_protocol(cfg):
    """2:2 or 3:1 flash / no-flash buckets (``app.flash_buckets``); reads ``flash`` and ``noflash``."""
    if cfg.sensor.bucket_count < 4:
        raise ConfigError(
            f"capture.protocol: 'flash_matting' needs 4 buckets but sensor.bucket_count is {cfg.sensor.bucket_count}"
        )
    _, params = cfg.app.resolve(cfg.capture.protocol)
    # another application reconstructing this schedule (app.name) has no split keys: the defaults
    n_flash = getattr(params, "flash_buckets", FlashMattingParams().flash_buckets)
    on = frozenset({getattr(params, "flash_group", FlashMattingParams().flash_group)})
    slot = exact(cfg.capture.unit_exposure_s) / Fraction(cfg.capture.periods)
    if n_flash == 2:
        slots = [SlotSeconds(0, slot, on), SlotSeconds(2, slot), SlotSeconds(3, slot), SlotSeconds(1, slot, on)]
        reads = [ReadEvent(FLASH_READ, (0, 1)), ReadEvent(NOFLASH_READ, (2, 3))]
    else:
        slots = [
            SlotSeconds(3, slot / 2),
            SlotSeconds(0, slot, on),
            SlotSeconds(1, slot, on),
            SlotSeconds(2, slot, on),
            SlotSeconds(3, slot / 2),
        ]
        reads = [ReadEvent(FLASH_READ, (0, 1, 2)), ReadEvent(NOFLASH_READ, (3,))]
    return slots, reads, 4


# ----------------------------------------------------------------------------- pure functions
def read_radiance(read_e: np.ndarray, exposure_s: float, k_e: np.ndarray) -> np.ndarray:
    """A read as radiance (H, W, C) in render units: its electrons / its own exposure / k_e (C,)."""
    return np.asarray(read_e, np.float64) / exposure_s / np.asarray(k_e, np.float64)


def flash_only_image(
    flash_e: np.ndarray, flash_exposure_s: float, noflash_e: np.ndarray, noflash_exposure_s: float, k_e: np.ndarray
) -> np.ndarray:
    """Flash-only radiance (H, W, C): the flash read's radiance minus the no-flash read's, each read
    normalised by its own exposure (2T and 2T in the 2:2 split, 3T and T in the 3:1 split)."""
    return read_radiance(flash_e, flash_exposure_s, k_e) - read_radiance(noflash_e, noflash_exposure_s, k_e)


def matte_scores(alpha: np.ndarray, truth: np.ndarray, region: np.ndarray | None = None) -> dict:
    """SAD (sum of |alpha - truth| over the region, pixels) and MSE (mean squared error) of a matte."""
    a, t = np.asarray(alpha, np.float64), np.asarray(truth, np.float64)
    if region is not None:
        a, t = a[region], t[region]
    if a.size == 0:
        return {"pixels": 0, "sad": 0.0, "mse": None}
    d = a - t
    return {"pixels": int(a.size), "sad": float(np.abs(d).sum()), "mse": float(np.mean(d * d))}


def trimap_errors(trimap: np.ndarray, truth: np.ndarray, tol: float = 0.05) -> dict:
    """Definite trimap pixels that the truth contradicts: labelled foreground with truth alpha
    below ``tol``, labelled background with truth alpha above 1 - ``tol`` (pixels)."""
    return {
        "fg_on_background": int(((trimap == 1.0) & (truth < tol)).sum()),
        "bg_on_foreground": int(((trimap == 0.0) & (truth > 1 - tol)).sum()),
    }


# ----------------------------------------------------------------------------- application
def _read(data: CaptureData, name: str) -> int:
    if name not in data.read_names:
        raise ConfigError(
            f"app.name: flash_matting needs reads named {FLASH_READ!r} and {NOFLASH_READ!r} (capture.protocol "
            f"flash_matting, or a custom schedule with those read names); got {data.read_names}"
        )
    return data.read_names.index(name)


def alpha_truth(data: CaptureData, params: FlashMattingParams) -> np.ndarray | None:
    """Coverage of the scene's foreground as the flash read saw it (None without a renderer)."""
    if data.renderer is None:
        return None

    g = data.group_index(params.flash_group)
    buckets = list(data.timeline.reads[_read(data, FLASH_READ)].buckets)
    weights = data.plan.weights_s[:, buckets, g].sum(axis=1)  # (J,) seconds the flash read collected, flash on
    # at each render's time (both halves, and a top-up's), with its weight in the stratum's exposure: where
    # the capture saw the parts
    times, shares = data.plan.exposure_time_mix()
    weights = weights[:, None] * shares
    cfg = data.cfg
    seed = data.seed if data.seed is not None else np.random.SeedSequence(cfg.seed)
    return coverage_alpha(
        data.scene,
        times.ravel(),
        weights.ravel(),
        cfg.render.width,
        cfg.render.height,
        params.truth_spp,
        seed,
        variant=cfg.render.variant,
        cache=getattr(data.renderer, "cache", None),
    )


def flash_only_truth(data: CaptureData, params: FlashMattingParams) -> np.ndarray | None:
    """Noise-free flash-only radiance of the flash read: its flash-group exposure / its flash time."""
    if data.group_exposure is None or params.flash_group not in data.plan.groups:
        return None
    buckets = list(data.timeline.reads[_read(data, FLASH_READ)].buckets)
    g = data.group_index(params.flash_group)
    s = data.switchable.index(params.flash_group)
    return data.group_exposure[buckets, g].sum(axis=0) / data.bucket_group_s[buckets, s].sum()


#: What each preview shows (report.html).
CAPTIONS = {
    "flash": "the flash read as radiance (the near foreground lit by the flash, plus ambient)",
    "noflash": "the no-flash read as radiance (ambient only)",
    "flash_only": "flash minus no-flash: the flash falls off with distance, so the foreground stands out",
    "trimap": "white = foreground, black = background, grey = unknown (solved by the matting)",
    "alpha": "the matte: coverage of the foreground, 0 (black) to 1 (white)",
    "extracted": "alpha x the estimated foreground colour: the foreground cut out",
    "alpha_truth": "reference matte: the foreground's coverage as the flash read saw it, motion blur included",
    "alpha_error": "|alpha - reference|, linear: white = 1",
}


def trimap_of(flash_only: np.ndarray, noflash: np.ndarray, params: FlashMattingParams) -> tuple[np.ndarray, np.ndarray]:
    """The trimap (1 foreground, 0 background, 0.5 unknown) from the flash-only image's cue (``app.trimap_*``), and
    the cue's ramp from the background level (0) to the foreground level (1), which the matting may start from."""
    cue = trimap_cue(
        flash_only, noflash, params.trimap_cue, params.trimap_reference_percentile, params.trimap_ratio_eps
    )
    trimap = make_trimap(
        cue, params.trimap_fg_fraction, params.trimap_bg_fraction, params.trimap_open_px, params.trimap_erode_px
    )
    return trimap, (cue - params.trimap_bg_fraction) / (params.trimap_fg_fraction - params.trimap_bg_fraction)


def _score_alpha(
    truth, alpha, trimap, unknown, mask, by_image: dict, n_ch: int, truth_spp: int, images, metrics, png, summary
) -> None:
    """The matte against the ground-truth alpha ``truth`` (None: no renderer, none), into ``metrics``, ``images``,
    ``png`` and ``summary``: SAD and MSE over the image, the trimap's unknown region and the moving region, the
    trimap's errors, and each candidate image's matte (``by_image``)."""
    if truth is None:
        metrics["alpha_truth"] = None
        metrics["note"] = "no renderer: no ground-truth alpha"
    else:
        metrics["alpha_truth"] = (
            f"coverage of the scene's foreground shapes as the flash read saw it, {truth_spp} spp per stratum"
        )
        metrics["alpha"] = matte_scores(alpha, truth)
        metrics["alpha_unknown"] = matte_scores(alpha, truth, unknown)
        metrics["alpha_moving"] = matte_scores(alpha, truth, mask) if mask.any() else None
        metrics["trimap_errors"] = trimap_errors(trimap, truth)
        metrics["alpha_by_image"] = {name: matte_scores(a, truth) for name, a in by_image.items()}
        err = np.abs(alpha - truth)
        images["alpha_truth"] = np.repeat(truth[..., None], n_ch, -1)
        images["alpha_error"] = np.repeat(err[..., None], n_ch, -1)
        png["alpha_truth"] = ("alpha_truth", None)
        png["alpha_error"] = ("alpha_error", None)
        a = metrics["alpha"]
        summary.append(
            f"alpha vs truth: SAD {a['sad']:.1f} px, MSE {a['mse']:.3g}; in the unknown region "
            f"SAD {metrics['alpha_unknown']['sad']:.1f}, MSE {metrics['alpha_unknown']['mse'] or 0:.3g}"
        )


@register(
    "flash_matting",
    output_channels=33,
    previews=8,
    libraries_mb=180,
    params=FlashMattingParams,
    per_group=True,
    pinhole_truth="the true matte is the foreground's coverage rendered through pixel centres",
    description="flash-only image, trimap and alpha matte (app.matting) scored against the rendered coverage",
)
def reconstruct(data: CaptureData, params: FlashMattingParams) -> AppOutput:
    if params.flash_group not in data.switchable:
        raise ConfigError(
            f"app.flash_group: {params.flash_group!r} is not a switchable group of scene "
            f"{data.scene.name!r} (switchable: {list(data.switchable)})"
        )
    i_f, i_n = _read(data, FLASH_READ), _read(data, NOFLASH_READ)
    reads_e = data.reads_e()
    t_f, t_n = float(data.exposure_s[i_f]), float(data.exposure_s[i_n])
    flash = read_radiance(reads_e[i_f], t_f, data.k_e)
    noflash = read_radiance(reads_e[i_n], t_n, data.k_e)
    flash_only = flash_only_image(reads_e[i_f], t_f, reads_e[i_n], t_n, data.k_e)
    y = luminance(flash_only)
    ref = reference_level(y, params.trimap_reference_percentile)
    trimap, ramp = trimap_of(flash_only, noflash, params)
    sources = {"flash_only": flash_only, "flash": flash, "noflash": noflash}

    def matte(name: str) -> np.ndarray:
        img = sources[name]  # to [0, 1] by its largest channel: clipping would break the colour-line model
        return estimate_alpha(
            img / reference_level(img.max(axis=-1), MATTING_WHITE_PERCENTILE), trimap, params.matting, ramp
        )

    alpha = matte(params.matting_image)

    from pymatting import estimate_foreground_ml

    white = reference_level(luminance(noflash), 99.5)
    fg_colour = estimate_foreground_ml(np.clip(noflash / white, 0.0, 1.0), alpha) * white
    extracted = alpha[..., None] * fg_colour

    n_ch = flash.shape[-1]
    unknown = trimap == 0.5
    mask = data.moving_mask
    metrics: dict = {
        "split": f"{params.flash_buckets}:{4 - params.flash_buckets}",
        "matting": params.matting,
        "matting_image": params.matting_image,
        "reads": {"flash_exposure_s": t_f, "noflash_exposure_s": t_n},
        "flash_read_saturated_fraction": float(data.saturated[i_f].any(axis=-1).mean()),
        "trimap": {
            "cue": params.trimap_cue,
            "flash_only_reference_luminance": ref,
            "foreground_fraction": float((trimap == 1.0).mean()),
            "background_fraction": float((trimap == 0.0).mean()),
            "unknown_fraction": float(unknown.mean()),
        },
    }
    images = {
        "flash": flash,
        "noflash": noflash,
        "flash_only": flash_only,
        "trimap": np.repeat(trimap[..., None], n_ch, -1),
        "alpha": np.repeat(alpha[..., None], n_ch, -1),
        "foreground": fg_colour,
        "extracted": extracted,
        "moving": np.repeat(mask[..., None], n_ch, -1).astype(np.float64),
    }
    png = {
        "flash": ("flash", 99.5),
        "noflash": ("noflash", 99.5),
        "flash_only": ("flash_only", 99.5),
        "trimap": ("trimap", None),
        "alpha": ("alpha", None),
        "extracted": ("extracted", 99.5),
    }
    summary = [
        f"flash matting ({params.flash_buckets}:{4 - params.flash_buckets}, {params.matting} on {params.matting_image}): trimap "
        f"{100 * unknown.mean():.1f}% unknown"
    ]

    fo_truth = flash_only_truth(data, params)
    if fo_truth is not None:
        images["flash_only_truth"] = fo_truth
        metrics["flash_only_rel_mse"] = relative_mse(flash_only, fo_truth, eps=REL_MSE_EPS_RADIANCE)
        if mask.any():
            metrics["flash_only_rel_mse_moving"] = relative_mse(
                flash_only, fo_truth, mask=np.repeat(mask[..., None], n_ch, -1), eps=REL_MSE_EPS_RADIANCE
            )
    by_image = {name: (alpha if name == params.matting_image else matte(name)) for name in sources}
    _score_alpha(
        alpha_truth(data, params),
        alpha,
        trimap,
        unknown,
        mask,
        by_image,
        n_ch,
        params.truth_spp,
        images,
        metrics,
        png,
        summary,
    )
    return AppOutput(images=images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)
