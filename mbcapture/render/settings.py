"""How a :class:`~mbcapture.render.Renderer` renders (:class:`RenderSettings`), read from a capture config, and
Mitsuba loaded for a variant (:func:`load_mitsuba`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from ..scene.optics import focus_distance_m, thin_lens_aperture_m
from ..scene.scenes import SceneModel
from ..sensor.config import SensorConfig
from ..sensor.photons import mono_weights
from ..sensor.spectral import film_sensitivity
from .build import MAX_GUIDE_SHARE, Guide
from .llvm import apply_target_from_env, ensure_llvm

#: Mitsuba samplers a Renderer may use (render.sampler).
SAMPLERS = ("multijitter", "ldsampler", "independent")


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
