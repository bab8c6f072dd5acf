"""Capture configuration: YAML -> validated, frozen pydantic models.

Every key is documented by its ``Field(description=...)``; ``docs/config.md`` is generated from
these descriptions (``mbcapture config-doc``). Unknown keys are rejected with their dotted path.
Units are in the names (``_s``, ``_e``, ``_px``).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from . import scenes
from .errors import ConfigError
from .sensor.config import SensorConfig


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SceneSection(BaseModel):
    """``scene.name`` picks the scene; every other ``scene.*`` key is that scene's own parameter
    (``mbcapture scenes`` lists them)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    name: str = Field("metronome", description="Scene name: a folder scenes/<name>/ (see `mbcapture scenes`).")

    def params(self) -> Any:
        """The scene's own validated ``Params`` (raises ConfigError naming ``scene.<key>``)."""
        module = scenes.load_module(self.name)
        try:
            return module.Params(**(self.model_extra or {}))
        except ValidationError as exc:
            raise ConfigError(_format_validation(exc, prefix="scene")) from None


class RenderSection(_Model):
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
        description="With render.spp null: the median, over lit unsaturated bucket samples, of the Monte Carlo variance of the bucket electrons as a fraction of the photon shot-noise variance the sensor adds there (0.1 = rendering adds ~5% to the noise).",
    )
    noise_budget_p95: float = Field(
        1.0,
        gt=0,
        description="With render.spp null: the same ratio's 95th percentile (1.0: in 95% of the samples rendering adds at most as much variance as the photons).",
    )
    max_spp: int = Field(1024, ge=2, le=1 << 16, description="Upper bound on the samples per pixel render.noise_budget may choose for one stratum.")
    estimator: Literal["independent", "difference"] = Field(
        "independent",
        description="'independent': each stratum rendered with its own random numbers. 'difference': each stratum "
        "rendered with the same random numbers as a render of the capture's start, and added as a difference to a "
        "base render of the start at render.base_spp (control variate; unbiased): static pixels carry only the "
        "base's error, identically in every bucket (see mbcapture/integrate.py and scripts/benchmark.py [5]).",
    )
    base_spp: int | None = Field(
        None, ge=2, le=1 << 20,
        description="Samples per pixel of the 'difference' estimator's base render (rendered in chunks of at most "
        "render.max_spp); null: the strata's total samples per pixel.",
    )
    planner: Literal["motion", "naive"] = Field(
        "motion",
        description="'motion': time strata from image motion (one render per stratum); 'naive': one render per collecting slot of every period (the baseline of `mbcapture converge`).",
    )
    variant: str = Field("llvm_ad_rgb", description="Mitsuba variant: llvm_ad_rgb on CPU, cuda_ad_rgb where a GPU exists; llvm_ad_spectral / cuda_ad_spectral apply sensor.spectral_response exactly (spectral mode).")
    max_depth: int = Field(4, ge=1, le=64, description="Path length limit of the per-group path tracer (1 = emitters seen directly only).")
    sampler: Literal["multijitter", "ldsampler", "independent"] = Field(
        "multijitter",
        description="Mitsuba sample generator. 'multijitter' (correlated multi-jittered, Kensler 2013; any count) and "
        "'ldsampler' (a scrambled low-discrepancy sequence; counts rounded up to powers of 4) are randomized "
        "quasi-Monte Carlo: unbiased, independent between seeds, and on the metronome at 128 spp 4.6x and 10.6x lower "
        "in Monte Carlo variance than 'independent' (uniform random numbers).",
    )
    max_motion_px: float = Field(
        0.5, gt=0, description="Largest image motion, in pixels, of any moving point inside one time stratum (the paper's vT << p)."
    )
    max_strata: int = Field(
        2048, ge=1, description="Upper bound on render passes; a plan that needs more is coarsened with a warning in the report."
    )
    cache: str = Field(
        "on",
        description="Render cache: 'on' (the user cache folder, ~/.cache/mbcapture/renders on Linux, or "
        "$MBCAPTURE_CACHE_DIR), 'off', or a folder. Every render is stored under a key of everything that determines "
        "it, so a run that changes only sensor.*, hdr.*, app.*, output.* or sensor.noise_seed renders nothing "
        "(in spectral mode the sensor's spectral response and QE shape the film and do count). `mbcapture cache "
        "info | clear`.",
    )
    cache_max_gb: float = Field(
        20.0, gt=0, description="Size cap of the render cache in GB (10^9 bytes); beyond it the least recently used renders are removed."
    )

    @field_validator("cache", mode="before")
    @classmethod
    def _cache_setting(cls, v):
        if isinstance(v, bool):  # YAML reads a bare on / off as a boolean
            return "on" if v else "off"
        if not isinstance(v, str) or not v.strip():
            raise ValueError("expected 'on', 'off' or a folder path")
        return v.strip()


class SlotSpec(_Model):
    bucket: int | Literal["drain"] = Field(
        description="1-based bucket that collects the photodiode's charge during this slot, or 'drain' (charge discarded)."
    )
    duration_s: float = Field(gt=0, description="Slot duration in seconds, within one period.")
    groups: tuple[str, ...] = Field((), description="Switchable emitter groups (e.g. flash) that are on during this slot.")


class ReadSpec(_Model):
    name: str | None = Field(None, description="Read name in outputs (default J1, J2, ...).")
    buckets: tuple[int, ...] = Field(
        min_length=1, description="1-based buckets summed on the floating diffusion for this read (non-destructive)."
    )


class ScheduleSpec(_Model):
    slots: tuple[SlotSpec, ...] = Field(min_length=1, description="One period of the gate schedule; repeated capture.periods times.")
    reads: tuple[ReadSpec, ...] = Field(min_length=1, description="Read events at the end of the capture.")


class CaptureSection(_Model):
    protocol: str = Field(
        "photon_efficient_hdr",
        description="Gate schedule: photon_efficient_hdr, interleaved_hdr, custom, or an application's "
        "(flash_no_flash, ...); see docs/protocols.md and `mbcapture apps`.",
    )
    unit_exposure_s: float = Field(
        1e-3, gt=0, description="T: the shortest exposure of the HDR protocols (reads are T, 2T, 4T, ...). Unused by 'custom'."
    )
    periods: int = Field(16, ge=1, le=10**7, description="N: how many times the slot pattern repeats within the exposure.")
    sequential: bool = Field(
        False,
        description="Capture the same exposures one after another on a conventional one-bucket sensor, "
        "with sensor.frame_readout_s between frames, instead of interleaving them.",
    )
    start_s: float = Field(0.0, ge=0, description="Scene time at which the capture starts (moves the metronome's phase).")
    schedule: ScheduleSpec | None = Field(None, description="The 'custom' protocol's schedule (required for it, refused otherwise).")

    @model_validator(mode="after")
    def _schedule_only_for_custom(self) -> "CaptureSection":
        if self.protocol == "custom" and self.schedule is None:
            raise ValueError("capture.schedule is required when capture.protocol is 'custom'")
        if self.protocol != "custom" and self.schedule is not None:
            raise ValueError(f"capture.schedule is only read by the 'custom' protocol, not {self.protocol!r}")
        return self


class HDRSection(_Model):
    method: Literal["auto", "ramp_fit", "inverse_variance", "debevec"] = Field(
        "auto", description="HDR merge; 'auto' = ramp_fit for cumulative reads, inverse_variance for independent ones."
    )


class AppSection(BaseModel):
    """``app.name`` picks the reconstruction applied to the reads; every other ``app.*`` key is that
    application's own parameter (``mbcapture apps`` lists them)."""

    model_config = ConfigDict(extra="allow", frozen=True)
    name: str | None = Field(
        None, description="Application that reconstructs the reads; default: the protocol's own (hdr for the HDR protocols)."
    )

    def resolve(self, protocol: str) -> tuple[Any, Any]:
        """(App, its validated params) for a capture with ``protocol``; ConfigError names ``app.<key>``."""
        from . import apps, protocols

        app = apps.get(self.name or protocols.default_app(protocol))
        try:
            return app, app.params(**(self.model_extra or {}))
        except ValidationError as exc:
            raise ConfigError(_format_validation(exc, prefix="app")) from None


class OutputSection(_Model):
    png_percentile: float = Field(
        99.5, gt=0, le=100, description="Tone mapping of PNG previews: this luminance percentile maps to white before the sRGB curve."
    )


class CaptureConfig(_Model):
    seed: int = Field(
        0, ge=0,
        description="One seed for the whole run, split per stage: render times and samples (the renders), and the "
        "sensor's temporal noise unless sensor.noise_seed is set; the fixed pattern has sensor.fpn_seed.",
    )
    scene: SceneSection = Field(default_factory=SceneSection, description="What is in front of the camera: scene.name and its parameters.")
    render: RenderSection = Field(default_factory=RenderSection, description="Film size, samples and the motion tolerance of the render plan.")
    capture: CaptureSection = Field(default_factory=CaptureSection, description="Protocol: gate schedule, exposures, interleaving periods.")
    sensor: SensorConfig = Field(default_factory=SensorConfig, description="The multi-bucket pixel: optics, full wells, noise, ADC.")
    hdr: HDRSection = Field(default_factory=HDRSection, description="HDR reconstruction method.")
    app: AppSection = Field(default_factory=AppSection, description="Reconstruction applied to the reads and its parameters.")
    output: OutputSection = Field(default_factory=OutputSection, description="Preview images.")

    @field_validator("render")
    @classmethod
    def _variant_known(cls, render: RenderSection) -> RenderSection:
        if not any(render.variant.startswith(p) for p in ("llvm_", "scalar_", "cuda_")):
            raise ValueError(f"render.variant: {render.variant!r} is not a Mitsuba variant name")
        return render

    @model_validator(mode="after")
    def _spectral_response_needs_spectral_variant(self) -> "CaptureConfig":
        from .sensor.spectral import EFFECTIVE_WAVELENGTH, is_spectral_variant

        spectral = is_spectral_variant(self.render.variant)
        if self.sensor.spectral_response != EFFECTIVE_WAVELENGTH and not spectral:
            raise ValueError(
                f"sensor.spectral_response {self.sensor.spectral_response!r} needs a spectral render.variant "
                f"(e.g. llvm_ad_spectral), got render.variant {self.render.variant!r}"
            )
        if spectral and self.sensor.spectral_response == EFFECTIVE_WAVELENGTH:
            raise ValueError(
                f"render.variant {self.render.variant!r} needs sensor.spectral_response to name a camera "
                "(e.g. 'Nikon 5100 (NPL)'), not 'effective_wavelength'"
            )
        return self

    def to_yaml_dict(self) -> dict:
        """The resolved config as plain data (scene parameters filled in with their defaults)."""
        data = self.model_dump(mode="json")
        data["scene"] = {"name": self.scene.name, **self.scene.params().model_dump(mode="json")}
        app, params = self.app.resolve(self.capture.protocol)
        data["app"] = {"name": app.name, **params.model_dump(mode="json")}
        return data


def _format_validation(exc: ValidationError, prefix: str = "") -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        if prefix:
            loc = f"{prefix}.{loc}" if loc else prefix
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif "input" in err and not isinstance(err["input"], (dict, list)):
            msg = f"{msg} (got {err['input']!r})"
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``'render.spp=4'`` -> (['render', 'spp'], 4); the value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE with a dotted key, e.g. render.spp=4")
    key, _, raw = text.partition("=")
    path = [p for p in key.strip().split(".")]
    if not all(path):
        raise ConfigError(f"--set {text!r}: empty part in key {key!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {key}: value {raw!r} is not valid YAML ({exc.problem})") from None
    return path, value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    data = copy.deepcopy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = data
        for i, part in enumerate(path[:-1]):
            nxt = node.get(part)
            if nxt is None:
                nxt = node[part] = {}
            if not isinstance(nxt, dict):
                raise ConfigError(f"--set {text}: {'.'.join(path[: i + 1])} is a value, not a section")
            node = nxt
        node[path[-1]] = value
    return data


def _first_non_finite(node: Any, path: tuple = ()) -> tuple[str, float] | None:
    """Dotted path and value of the first inf/nan number anywhere in raw config data, or None."""
    if isinstance(node, float) and not math.isfinite(node):
        return ".".join(map(str, path)), node
    if isinstance(node, dict):
        items = node.items()
    elif isinstance(node, (list, tuple)):
        items = enumerate(node)
    else:
        return None
    for key, value in items:
        found = _first_non_finite(value, (*path, key))
        if found:
            return found
    return None


def config_from_dict(data: dict, source: str = "config") -> CaptureConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of sections at the top level, got {type(data).__name__}")
    bad = _first_non_finite(data)
    if bad:  # YAML .inf / .nan: no key of any section accepts them (durations, radiances, noise, phases)
        raise ConfigError(f"{source}: {bad[0]}: expected a finite number (got {bad[1]!r})")
    try:
        cfg = CaptureConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {_format_validation(exc)}") from None
    cfg.scene.params()  # validate the scene's and the application's own keys now, not halfway through a run
    cfg.app.resolve(cfg.capture.protocol)
    return cfg


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> CaptureConfig:
    """Load a YAML config (or the defaults when ``path`` is None) and apply ``--set`` overrides."""
    data: Any = {}
    source = "defaults"
    if path is not None:
        p = Path(path)
        source = str(p)
        try:
            text = p.read_text()
        except FileNotFoundError:
            raise ConfigError(f"{p}: config file not found") from None
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read config file ({exc.strerror})") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            raise ConfigError(f"{p}:{where}: malformed YAML ({getattr(exc, 'problem', exc)})") from None
        if data is None:
            data = {}
    data = apply_overrides(data, list(overrides))
    return config_from_dict(data, source)
