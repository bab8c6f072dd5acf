"""How a :class:`~mbcapture.render.Renderer` renders: the config's ``render.*`` section (:class:`RenderSection`), the
renderer's settings read from a capture config (:class:`RenderSettings`), and Mitsuba loaded for a variant
(:func:`load_mitsuba`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Sequence

import numpy as np

from pydantic import Field, field_validator

from ..errors import ConfigError
from ..strict import StrictModel
from ..scene.optics import focus_distance_m, thin_lens_aperture_m
from ..scene.scenes import SceneModel
from ..sensor.config import SensorConfig
from ..sensor.photons import mono_weights
from ..sensor.spectral import film_sensitivity
from .build import MAX_GUIDE_SHARE, Guide
from .llvm import apply_target_from_env, ensure_llvm

#: Mitsuba samplers a Renderer may use (render.sampler).
SAMPLERS = ("multijitter", "ldsampler", "independent")


class RenderSection(StrictModel):
    width: int = Field(640, gt=0, le=16384, description="Film width in pixels (the paper's sensor: 640).")
    height: int = Field(512, gt=0, le=16384, description="Film height in pixels (the paper's sensor: 512).")
    spp: int | None = Field(
        None,
        ge=1,
        le=1 << 16,
        description="Samples per pixel of every time stratum; null (the default) = chosen per stratum by a pilot render so that the Monte Carlo noise stays within render.noise_budget / render.noise_budget_p95 of the photon shot noise.",
    )
    noise_budget: float = Field(
        0.1,
        gt=0,
        description="With render.spp null: the median, over the lit unsaturated samples of every read the sensor outputs (the worst read decides), of the Monte Carlo variance of the read's electrons as a fraction of the photon shot-noise variance the sensor adds there (0.1 = rendering adds ~5% to the noise).",
    )
    noise_budget_p95: float = Field(
        1.0,
        gt=0,
        description="With render.spp null: the same ratio's 95th percentile (1.0: in 95% of the samples rendering adds at most as much variance as the photons). With render.adaptive, the pilot chooses the first pass for at most half of render.noise_budget_tail here (budget.ADAPTIVE_FIRST_P95): adaptive sampling then refines a sixth of the default capture's film instead of more than half, for fewer samples in all (docs/noise.md).",
    )
    noise_budget_tail: float = Field(
        1.0,
        gt=0,
        description="The same ratio's 99.9th percentile on every read (1.0: no more than one sample in 1000 where "
        "rendering noise exceeds the photons'; a user would take such samples for hot pixels). Reported and judged "
        "on every run; the pilot does not raise spp for it (meeting a tail by more samples everywhere multiplies "
        "the cost).",
    )
    top_up: bool = Field(
        True,
        description="With render.spp null: when the run's own estimate of its rendering noise is over "
        "render.noise_budget or render.noise_budget_p95 on any read, render every stratum once more with the "
        "samples that close the gap (10 % margin, within render.max_spp) and combine the two passes without "
        "bias. true: on; report.json top_up says what it added. How and why: docs/noise.md.",
    )
    adaptive: bool = Field(
        True,
        description="With render.spp null: adaptive sampling, which renders again the pixels where rendering noise would "
        "otherwise exceed render.noise_budget_tail times the shot noise's variance at the 99.9th percentile "
        "(silhouettes, moving edges), chosen from a scout the image does not use, so unbiased. true: on; "
        "false: the tail is reported, not met. docs/noise.md explains the method and its cost; report.json "
        "adaptive says what it refined.",
    )
    adaptive_max_factor: int = Field(
        64,
        ge=2,
        le=256,
        description="Most samples a refined pixel may end with, as a multiple of its stratum's first-pass samples "
        "(rounded down to a power of two). Adaptive sampling keeps the cheapest rule that meets the tail, so "
        "a larger bound only adds choices; 64: the default capture chooses 8. report.json adaptive.tiers "
        "says how many pixels got what (docs/noise.md).",
    )
    max_spp: int = Field(
        1024,
        ge=2,
        le=1 << 16,
        description="Upper bound on the samples per pixel render.noise_budget may choose for one stratum.",
    )
    estimator: Literal["independent", "difference"] = Field(
        "independent",
        description="'independent': each stratum rendered with its own random numbers. 'difference': each stratum "
        "rendered with the same random numbers as a render of the capture's start, and added as a difference to a "
        "base render of the start at render.base_spp (control variate; unbiased): static pixels carry only the "
        "base's error, identically in every bucket (see mbcapture/exposure/integrate.py and scripts/benchmark.py [5]).",
    )
    base_spp: int | None = Field(
        None,
        ge=2,
        le=1 << 20,
        description="Samples per pixel of the 'difference' estimator's base render (rendered in chunks of at most "
        "render.max_spp); null: the strata's total samples per pixel.",
    )
    planner: Literal["motion", "naive"] = Field(
        "motion",
        description="'motion': time strata from image motion (one render per stratum); 'naive': one render per collecting slot of every period (the baseline of `mbcapture converge`).",
    )
    variant: str = Field(
        "llvm_ad_rgb",
        description="Mitsuba variant: llvm_ad_rgb on CPU, cuda_ad_rgb where a GPU exists; llvm_ad_spectral / cuda_ad_spectral apply sensor.spectral_response exactly (spectral mode).",
    )
    max_depth: int = Field(
        4,
        ge=1,
        le=64,
        description="Path length limit of the per-group path tracer, in segments (1 = emitters seen directly only, 2 adds direct light, each more one more bounce). In Lambertian scenes a path ends at the vertex that ends its segment max_depth - 1, whose light it estimates by light sampling alone: the bounce from there could only have "
        "collected emission (unbiased; 0.91x the time on the default capture, docs/noise.md).",
    )
    sampler: Literal["multijitter", "ldsampler", "independent"] = Field(
        "multijitter",
        description="Mitsuba's sample generator for the pilot, the truths and spectral camera rays: 'multijitter' "
        "(correlated multi-jittered; any count), 'ldsampler' (scrambled low-discrepancy; counts rounded up "
        "to powers of 4), 'independent' (uniform random numbers). The two quasi-Monte Carlo ones are "
        "unbiased and several times lower in variance; the strata draw from render.pattern instead "
        "(docs/noise.md).",
    )
    pattern: Literal["own", "shared"] = Field(
        "shared",
        description="Where the strata's samples come from. 'shared': one scrambled Sobol' pattern per pixel and half, "
        "each stratum taking the samples after the previous ones', so that a read, which sums strata, is "
        "stratified as a whole (the default capture's median 1.39x lower at equal samples). 'own': each "
        "render its own render.sampler pattern. Both unbiased (docs/noise.md).",
    )
    guide_fraction: float | None = Field(
        None,
        ge=0.0,
        le=MAX_GUIDE_SHARE,
        description="Share of every diffuse bounce sent towards the scene's guides (brightly lit patches that are not "
        "lights, declared by the scene), weighted by the mixture's density so the image's expectation is "
        "unchanged. null: each guide its scene's share; a number: that share in all, split in the scene's "
        "proportions; 0: off. Removes rare fireflies at about 3 % more time per sample (docs/noise.md).",
    )
    max_motion_px: float = Field(
        0.5,
        gt=0,
        description="Largest image motion, in pixels, of any moving point inside one time stratum (the paper's vT << p).",
    )
    min_strata: int = Field(
        4,
        ge=1,
        description="Fewest time strata of a capture whose image moves at all, however little. Each stratum's time "
        "noise, and the run's own estimate of it, rests on one pair of render times shared by every pixel, "
        "so one stratum makes that estimate unreliable. 4: at least four; 1: strata from motion alone "
        "(render.max_motion_px). docs/noise.md.",
    )
    max_strata: int = Field(
        2048,
        ge=1,
        description="Upper bound on render passes; a plan that needs more is coarsened with a warning in the report.",
    )
    cache: str = Field(
        "on",
        description="Render cache: 'on' (the user cache folder, ~/.cache/mbcapture/renders on Linux, or "
        "$MBCAPTURE_CACHE_DIR), 'off', or a folder. Every render is stored under a key of everything that determines "
        "it, so a run that changes only sensor.*, hdr.*, app.*, output.* or sensor.noise_seed renders nothing "
        "(in spectral mode the sensor's spectral response and QE shape the film and do count). `mbcapture cache "
        "info | clear`.",
    )
    max_memory_gb: float | None = Field(
        None,
        gt=0,
        description="Refuse, before any work, a run whose planned peak memory exceeds this many GB "
        "(mbcapture plan prints the plan); null: only the machine's free memory limits it.",
    )
    band_rows: int | None = Field(
        None,
        ge=2,
        le=16384,
        multiple_of=2,
        description="Rows of each render band (even). Every film renders as fixed row bands, each with a sampler seed of "
        "its own, so that tiles of whole bands hold exactly the untiled run's pixels. null: about a "
        "megapixel per band (640x512 is one band). Changing it changes the renders' random numbers, as a new "
        "seed would (docs/resources.md).",
    )
    tiles: int | None = Field(
        None,
        ge=1,
        description="Tiles (runs of whole render bands) in which render, accumulation, the noise budget's passes and the "
        "sensor stage go through the film, to bound memory; the result is the untiled run's "
        "(docs/resources.md says how close). null: one tile when the capture fits in memory, otherwise the "
        "fewest that fit.",
    )
    spill: bool | None = Field(
        None,
        description="Keep a tiled capture's whole-film results (exposures, reads, truths, flags) in memory-mapped "
        "scratch files, so that memory holds the working set and not the film; the same values. null: only "
        "when tiles alone do not fit in memory; true: whenever the film is in more than one tile; false: "
        "never. Not for a video's frames (docs/resources.md).",
    )
    spill_dir: str | None = Field(
        None,
        description="Folder of render.spill's scratch files, on a disk (each is unlinked as soon as it is made: "
        "nothing is left in the folder after a run, even a killed one). null: the user cache folder's 'scratch' "
        "(~/.cache/mbcapture/scratch on Linux), or $MBCAPTURE_SCRATCH_DIR.",
    )
    cache_max_gb: float = Field(
        20.0,
        gt=0,
        description="Size cap of the render cache in GB (10^9 bytes); beyond it the least recently used renders are removed.",
    )

    @field_validator("cache", mode="before")
    @classmethod
    def _cache_setting(cls, v):
        if isinstance(v, bool):  # YAML reads a bare on / off as a boolean
            return "on" if v else "off"
        if not isinstance(v, str) or not v.strip():
            raise ValueError("expected 'on', 'off' or a folder path")
        return v.strip()


def guide_shares(guides: Sequence[Guide], fraction: float | None) -> tuple[float, ...]:
    """The share of every diffuse bounce sent towards each of ``guides``: their own shares (``fraction``
    None), or ``fraction`` of every bounce split among them in proportion to their shares (0: none,
    all zeros). ConfigError (render.guide_fraction) outside 0 to :data:`~mbcapture.render.build.MAX_GUIDE_SHARE`."""
    if fraction is None:
        return tuple(g.share for g in guides)
    if not 0.0 <= fraction <= MAX_GUIDE_SHARE:
        raise ConfigError(f"render.guide_fraction: expected null or 0 to {MAX_GUIDE_SHARE}, got {fraction}")
    total = sum(g.share for g in guides)  # each share is positive (Guide)
    return tuple(float(fraction) * g.share / total for g in guides)


def thin_lens_of(scene: SceneModel, cfg: Any) -> tuple[float, float] | None:
    """(aperture radius m, focus distance m) of ``camera.lens: thin``, None for a pinhole."""
    if cfg.camera.lens != "thin":
        return None
    focus = cfg.camera.focus_distance_m or focus_distance_m(scene.camera)
    return thin_lens_aperture_m(scene.camera, cfg.render.width, cfg.sensor.pixel_pitch_um, cfg.sensor.f_number), focus


def image_settings(scene: SceneModel, cfg: Any) -> dict[str, Any]:
    """Everything of the camera and the sensor that :meth:`Renderer.from_config`'s images depend on,
    as plain data (a sweep's render groups compare them): the field of view, the thin lens, the
    falloff, distortion, diffraction (with the f-number, pixel pitch and wavelengths it uses) and a
    mono sensor's channel mixture. Noise, wells and the ADC are not in it."""
    s, cam = cfg.sensor, cfg.camera
    mono = mono_weights(s, cfg.render.variant)
    return {
        "fov_deg": repr(float(scene.camera.fov_deg)),
        "thin_lens": None if (lens := thin_lens_of(scene, cfg)) is None else [repr(float(x)) for x in lens],
        "vignetting": cam.vignetting,
        "distortion": cam.distortion,
        "diffraction": None
        if not cam.diffraction
        else {"f_number": s.f_number, "pixel_pitch_um": s.pixel_pitch_um, "wavelength_nm": list(s.wavelength_nm)},
        "mono": None if mono is None else [repr(float(w)) for w in mono],
    }


@dataclass(frozen=True, eq=False)
class RenderSettings:
    """How a :class:`Renderer` renders, besides its scene and film size (each field a keyword of ``Renderer`` too):
    the Mitsuba ``variant`` (an llvm/cuda ``*_rgb`` or ``*_spectral`` one), the path's ``max_depth``, Mitsuba's
    ``sampler``, the ``sensor`` section (a spectral film's curves, diffraction's aperture), ``film_curves``
    (wavelengths_nm (n,), curves (3, n)) that replace the sensor's in a spectral variant, the lens
    (``vignetting``, ``distortion``, ``diffraction``, ``thin_lens``: (aperture radius m, focus distance m) or None
    for a pinhole), a monochrome sensor's channel mixture ``mono``, the film's ``band_rows`` (None: the default)
    and ``guide_fraction`` (None: the scene's own guide shares; 0: none)."""

    variant: str = "llvm_ad_rgb"
    max_depth: int = 4
    sampler: str = "multijitter"
    sensor: SensorConfig | None = None
    film_curves: tuple[np.ndarray, np.ndarray] | None = None
    vignetting: str = "none"
    distortion: Sequence[float] | None = None
    diffraction: bool = False
    thin_lens: tuple[float, float] | None = None
    mono: np.ndarray | None = None
    band_rows: int | None = None
    guide_fraction: float | None = 0.0

    @classmethod
    def from_config(cls, scene: SceneModel, cfg: Any, **fields: Any) -> "RenderSettings":
        """The settings a capture config asks for (render.*, camera.*, sensor), with ``fields`` replacing any."""
        r = cfg.render
        return cls(
            **{
                "variant": r.variant,
                "max_depth": r.max_depth,
                "sampler": r.sampler,
                "sensor": cfg.sensor,
                "vignetting": cfg.camera.vignetting,
                "diffraction": cfg.camera.diffraction,
                "thin_lens": thin_lens_of(scene, cfg),
                "mono": mono_weights(cfg.sensor, r.variant),
                "distortion": cfg.camera.distortion,
                "band_rows": r.band_rows,
                "guide_fraction": r.guide_fraction,
                **fields,
            }
        )

    def check(self) -> None:
        """A ConfigError naming the key for a setting no renderer can take."""
        lens = self.thin_lens
        if lens is not None and not (lens[0] > 0 and lens[1] > 0):
            raise ConfigError(f"thin lens: aperture radius and focus distance must be positive, got {lens}")
        if self.max_depth < 1:
            raise ConfigError(f"render.max_depth must be >= 1, got {self.max_depth}")
        if not self.variant.endswith(("_rgb", "_spectral")) or self.variant.startswith("scalar"):
            raise ConfigError(
                f"render.variant: expected an llvm/cuda *_rgb or *_spectral variant, got {self.variant!r}"
            )
        if self.sampler not in SAMPLERS:
            raise ConfigError(f"render.sampler: expected one of {list(SAMPLERS)}, got {self.sampler!r}")

    def film_sensitivity(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A spectral film's (wavelengths_nm (n,), curves (3, n)): ``film_curves``, else the sensor's
        (:func:`mbcapture.sensor.spectral.film_sensitivity`); None in an RGB variant."""
        spectral = self.variant.endswith("_spectral")
        if self.film_curves is not None:
            if not spectral:
                raise ConfigError(f"render.variant {self.variant!r}: film_curves need a spectral variant")
            wl, curves = (np.asarray(a, np.float64) for a in self.film_curves)
            if wl.ndim != 1 or curves.shape != (3, wl.size):
                raise ConfigError(
                    f"film_curves: expected wavelengths (n,) and curves (3, n), got {wl.shape}, {curves.shape}"
                )
            return wl, curves
        if not spectral:
            return None
        if self.sensor is None:
            raise ConfigError(f"render.variant {self.variant!r}: a spectral render needs the sensor config")
        try:
            return film_sensitivity(self.sensor)
        except ValueError as exc:
            raise ConfigError(f"sensor.{exc}") from None


def load_mitsuba(variant: str) -> tuple[Any, Any]:
    """Mitsuba and Dr.Jit with ``variant`` set (an LLVM one after the libLLVM is picked, and compiling for
    ``$MBCAPTURE_LLVM_TARGET`` where set): the ``(mitsuba, drjit)`` modules."""
    if variant.startswith("llvm"):
        ensure_llvm()
    import drjit as dr
    import mitsuba as mi

    if variant not in mi.variants():
        raise ConfigError(f"render.variant: {variant!r} not in {mi.variants()}")
    mi.set_variant(variant)
    if variant.startswith("llvm"):
        apply_target_from_env()  # MBCAPTURE_LLVM_TARGET: compile for another CPU (before any kernel)
    return mi, dr
