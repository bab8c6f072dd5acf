"""Capture configuration: YAML -> validated, frozen pydantic models.

Every key is documented by its ``Field(description=...)``; ``docs/config.md`` is generated from
these descriptions (``mbcapture config-doc``). Unknown keys are rejected with their dotted path.
Units are in the names (``_s``, ``_e``, ``_px``).

Every error names where the offending key came from (the config file, or the ``--set`` that
set it) and, for an unknown key, suggests the nearest valid one. ``--set scene.name=...`` (or
``app.name=...``) that switches to another scene (application) drops the file's parameters of the
old one with a :class:`~mbcapture.errors.ConfigNotice`. A config is named by its path or, for the
shipped ones in ``configs/``, by its name (``metronome_hdr``).
"""

from __future__ import annotations

import copy
from abc import abstractmethod
import dataclasses
import difflib
import math
import warnings
from pathlib import Path
from typing import Any, Callable, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from . import strict
from .strict import StrictModel
from . import application as apps
from .scene import camera_motion, scenes
from .scene.camera_motion import CameraSection
from .errors import ConfigError, ConfigNotice
from .scene.optics import fov_deg_for
from .render.settings import RenderSection
from .sensor import demodulation
from .sensor.config import SensorConfig
from .sensor.spectral import EFFECTIVE_WAVELENGTH, is_spectral_variant

#: PyYAML's safe loader, on libyaml where PyYAML was built with it: the same documents (every shipped
#: config compared equal) in 0.19 ms instead of 2.3 ms; a sweep loads its base config once per point.
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

#: The shipped configs, which ``load_config`` (and ``mbcapture run``) also finds by name.
SHIPPED_CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class _OwnKeysSection(StrictModel):
    """A section whose keys beside its name belong to what the name picks (a scene's, an
    application's own parameters): any key is taken, and an assignment is checked by :meth:`check`."""

    model_config = ConfigDict(extra="allow", validate_assignment=True)

    @abstractmethod
    def check(self) -> None:
        """Raise ConfigError if the section's keys are not those of what its name picks."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name.startswith("_"):
            super().__setattr__(name, value)
            return
        had = name in type(self).model_fields or name in (self.model_extra or {})
        old = getattr(self, name) if had else None
        super().__setattr__(name, value)
        try:
            self.check()
        except ConfigError:  # leave the section as it was
            if had:
                BaseModel.__setattr__(self, name, old)
            else:
                (self.model_extra or {}).pop(name, None)
            raise


class SceneSection(_OwnKeysSection):
    """``scene.name`` picks the scene; every other ``scene.*`` key is that scene's own parameter
    (``mbcapture scenes`` lists them)."""

    name: str = Field("metronome", description="Scene name: a folder scenes/<name>/ (see `mbcapture scenes`).")

    def params(self, origin: "Callable[[tuple], str] | None" = None) -> Any:
        """The scene's own validated ``Params`` (raises ConfigError naming ``scene.<key>``; an
        unknown key lists this scene's keys). ``origin``: where a key came from (see
        :func:`config_from_dict`)."""
        module = scenes.load_module(self.name)
        try:
            return module.Params(**(self.model_extra or {}))
        except ValidationError as exc:
            raise ConfigError(
                format_validation(exc, prefix="scene", origin=origin, model=module.Params, owner=f"scene {self.name!r}")
            ) from None

    def check(self) -> None:
        self.params()


class SlotSpec(StrictModel):
    bucket: int | Literal["drain"] = Field(
        description="1-based bucket that collects the photodiode's charge during this slot, or 'drain' (charge discarded)."
    )
    duration_s: float = Field(gt=0, description="Slot duration in seconds, within one period.")
    groups: tuple[str, ...] = Field(
        (), description="Switchable emitter groups (e.g. flash) that are on during this slot."
    )


class ReadSpec(StrictModel):
    name: str | None = Field(None, description="Read name in outputs (default J1, J2, ...).")
    buckets: tuple[int, ...] = Field(
        min_length=1, description="1-based buckets summed on the floating diffusion for this read (non-destructive)."
    )


class ScheduleSpec(StrictModel):
    slots: tuple[SlotSpec, ...] = Field(
        min_length=1, description="One period of the gate schedule; repeated capture.periods times."
    )
    reads: tuple[ReadSpec, ...] = Field(min_length=1, description="Read events at the end of the capture.")


class GateCodeSpec(StrictModel):
    family: Literal["global", "one_hot", "hadamard", "random", "file"] = Field(
        description="Per-pixel gate code (a coded two-bucket sensor): 'global' (every pixel sends sub-frame s to bucket s: "
        "global gates written as a code), 'one_hot' (tile position f sends sub-frame f to bucket 1, the rest to bucket 2), "
        "'hadamard' (bucket 1 where a Hadamard row is +1, bucket 2 where -1), 'random' (each pixel and sub-frame to "
        "bucket 1 or 2 with probability 1/2), 'file' (an array file). See docs/coded_gates.md."
    )
    subframes: int | None = Field(
        None,
        ge=1,
        le=32,
        description="Sub-frames the protocol schedules (what it would give as many buckets); the code "
        "routes each to a bucket per pixel. Required by every family but 'global' (whose default is sensor.bucket_count). "
        "multi_flash: 4 (one per LED) or 5 (and ambient).",
    )
    tile: tuple[int, int] | None = Field(
        None,
        description="one_hot, hadamard: the tile [height, width] of per-pixel codes repeated over the film "
        "(default: the near-square tile that holds one code per position: 2x2 for 4 sub-frames, 2x3 for 5, 2x4 for Hadamard's 8).",
    )
    file: str | None = Field(
        None,
        description="'file': a .npy array of shape (sub-frames, height, width) of 1-based buckets (0: drain), tiled "
        "over the film; a relative path is relative to the working directory.",
    )
    seed: int | None = Field(None, ge=0, description="'random': the code's seed (default: the run's seed).")

    @model_validator(mode="after")
    def _file_only_for_file(self) -> "GateCodeSpec":
        if (self.family == "file") != (self.file is not None):
            raise ValueError("capture.gate_code.file is required by family 'file' and read by no other family")
        if self.tile is not None and self.family not in ("one_hot", "hadamard"):
            raise ValueError(
                f"capture.gate_code.tile is read by the one_hot and hadamard families, not {self.family!r}"
            )
        if self.tile is not None and min(self.tile) < 1:
            raise ValueError("capture.gate_code.tile: height and width must be >= 1")
        return self


class TofSpec(StrictModel):
    """What an indirect time-of-flight capture measures with (``capture.tof``; the tof_* protocols)."""

    group: str = Field(
        "illuminator",
        description="The scene's switchable emitter group that is modulated (the ToF illuminator). Every other "
        "group is ambient light: it reaches every tap in proportion to its gated time.",
    )
    frequencies_mhz: list[float] = Field(
        [20.0],
        min_length=1,
        max_length=4,
        description="Modulation frequencies, MHz, each measured with capture.tof.phases phases. One frequency wraps "
        "every c / (2 f) (7.49 m at 20 MHz); two or more are unwrapped together (docs/tof.md).",
    )
    phases: int = Field(
        4,
        ge=3,
        le=16,
        description="Demodulation phases per frequency, evenly spaced from 0 (3, 4 or 8 are usual); a multiple of "
        "the pixel's taps.",
    )
    exposure_s: float = Field(
        1e-3,
        gt=0,
        description="Integration time per frequency, s: the illuminator's on-time for that frequency's phases, "
        "shared by every design (a 4-tap pixel takes all phases in it at once; a 2-tap pixel two sub-frames of "
        "half of it; a 1-tap pixel four of a quarter, draining half of each period).",
    )

    @field_validator("frequencies_mhz")
    @classmethod
    def _positive_distinct(cls, v: list[float]) -> list[float]:
        if not all(math.isfinite(f) and 0.0 < f <= 1000.0 for f in v) or len(set(v)) != len(v):
            raise ValueError(f"expected distinct frequencies in (0, 1000] MHz, got {v}")
        return v


#: The protocols that read capture.exposure_ratios (mbcapture.apps.hdr).
HDR_PROTOCOLS = ("photon_efficient_hdr", "interleaved_hdr")


class CaptureSection(StrictModel):
    protocol: str = Field(
        "photon_efficient_hdr",
        description="Gate schedule: photon_efficient_hdr, interleaved_hdr, custom, or an application's "
        "(flash_no_flash, ...); see docs/protocols.md and `mbcapture apps`.",
    )
    unit_exposure_s: float = Field(
        1e-3,
        gt=0,
        description="T: the shortest exposure of the HDR protocols (reads are T times capture.exposure_ratios). "
        "Unused by 'custom'.",
    )
    exposure_ratios: list[float] | None = Field(
        None,
        min_length=2,
        description="The HDR protocols' read exposures in units of T, ascending from 1 (e.g. [1, 8]: two reads, 8:1), one "
        "bucket per ratio, at most sensor.bucket_count. null: powers of two over every bucket (1, 2, 4, 8 with 4 "
        "buckets). Photon-efficient reads sum buckets, so its capture spans the largest ratio; interleaved, the sum.",
    )
    periods: int = Field(
        16, ge=1, le=10**7, description="N: how many times the slot pattern repeats within the exposure."
    )
    sequential: bool = Field(
        False,
        description="Capture the same exposures one after another on a conventional one-bucket sensor, "
        "with sensor.frame_readout_s between frames, instead of interleaving them.",
    )
    start_s: float = Field(
        0.0, ge=0, description="Scene time at which the capture starts (moves the metronome's phase)."
    )
    gate_code: GateCodeSpec | None = Field(
        None,
        description="Per-pixel gates: each pixel chooses its bucket for every sub-frame of the schedule (a coded "
        "two-bucket sensor). null: global gates, every pixel follows the schedule.",
    )
    schedule: ScheduleSpec | None = Field(
        None, description="The 'custom' protocol's schedule (required for it, refused otherwise)."
    )
    tof: TofSpec | None = Field(
        None,
        description="Indirect time of flight (required by the tof_* protocols, refused by others): the modulated "
        "group, frequencies, phases and integration time (docs/tof.md).",
    )
    frames: int = Field(
        1,
        ge=1,
        le=100_000,
        description="A video: this many captures, one per frame at capture.frame_rate_hz, each read out before the next "
        "(1: a single capture; see mbcapture/capture/video.py).",
    )
    frame_rate_hz: float | None = Field(
        None,
        gt=0,
        le=1e6,
        description="Frames per second of a video (capture.frames > 1); the frame period must hold the capture's span "
        "plus sensor.frame_readout_s.",
    )

    @field_validator("exposure_ratios")
    @classmethod
    def _ratios_ascend_from_one(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return v
        if not all(math.isfinite(r) for r in v) or v[0] != 1.0 or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"expected exposures in units of T ascending from 1 (e.g. [1, 8] or [1, 4, 16]), got {v}")
        return v

    @field_validator("protocol")
    @classmethod
    def _protocol_known(cls, v: str) -> str:
        if v not in apps.protocol_names():
            raise ValueError(f"unknown protocol; expected one of {apps.protocol_names()}")
        return v

    @model_validator(mode="after")
    def _video_needs_a_rate(self) -> "CaptureSection":
        if self.frames > 1 and self.frame_rate_hz is None:
            raise ValueError("capture.frame_rate_hz is required when capture.frames > 1 (a video)")
        return self

    @model_validator(mode="after")
    def _ratios_only_for_hdr(self) -> "CaptureSection":
        if self.exposure_ratios is not None and self.protocol not in HDR_PROTOCOLS:
            raise ValueError(
                f"capture.exposure_ratios is only read by {' and '.join(HDR_PROTOCOLS)}, not {self.protocol!r}"
            )
        return self

    @model_validator(mode="after")
    def _tof_only_for_tof(self) -> "CaptureSection":
        design = demodulation.DESIGNS.get(self.protocol)
        if design is not None and self.tof is None:
            raise ValueError(f"capture.tof is required by the time-of-flight protocol {self.protocol!r}")
        if design is None and self.tof is not None:
            raise ValueError(
                f"capture.tof is only read by the time-of-flight protocols {sorted(demodulation.DESIGNS)}, "
                f"not {self.protocol!r}"
            )
        if design is not None and self.tof.phases % design.taps:
            raise ValueError(
                f"capture.tof.phases: {self.tof.phases} phases do not split over the {design.taps} taps of "
                f"{self.protocol!r}; use a multiple of {design.taps}"
            )
        return self

    @model_validator(mode="after")
    def _schedule_only_for_custom(self) -> "CaptureSection":
        if self.protocol == "custom" and self.schedule is None:
            raise ValueError("capture.schedule is required when capture.protocol is 'custom'")
        if self.protocol != "custom" and self.schedule is not None:
            raise ValueError(f"capture.schedule is only read by the 'custom' protocol, not {self.protocol!r}")
        return self


class HDRSection(StrictModel):
    method: Literal["auto", "ramp_fit", "inverse_variance", "debevec"] = Field(
        "auto", description="HDR merge; 'auto' = ramp_fit for cumulative reads, inverse_variance for independent ones."
    )


class AppSection(_OwnKeysSection):
    """``app.name`` picks the reconstruction applied to the reads; every other ``app.*`` key is that
    application's own parameter (``mbcapture apps`` lists them)."""

    name: str | None = Field(
        None,
        description="Application that reconstructs the reads; default: the protocol's own (hdr for the HDR protocols).",
    )

    def resolve(self, protocol: str, origin: "Callable[[tuple], str] | None" = None) -> tuple[Any, Any]:
        """(App, its validated params) for a capture with ``protocol``; ConfigError names ``app.<key>``
        (an unknown key lists this application's keys)."""

        app = apps.get(self.name or apps.protocol_app(protocol))
        try:
            return app, app.params(**(self.model_extra or {}))
        except ValidationError as exc:
            raise ConfigError(
                format_validation(exc, prefix="app", origin=origin, model=app.params, owner=f"application {app.name!r}")
            ) from None

    def check(self) -> None:
        if self.name is not None:  # without a name, the protocol's application: checked when the run starts
            self.resolve("")


class OutputSection(StrictModel):
    png_percentile: float = Field(
        99.5,
        gt=0,
        le=100,
        description="Tone mapping of PNG previews: this luminance percentile maps to white before the sRGB curve.",
    )
    dng: bool = Field(
        False,
        description="Also write each read as a DNG raw file, read_<name>.dng: its 16-bit ADC codes (a Bayer sensor's "
        "mosaic with its CFA pattern, a mono sensor's one sample, else R, G, B per pixel), black level, white "
        "level where that read clips, exposure, colour matrix and as-shot neutral. rawpy (LibRaw) opens and "
        "develops it (tested). Needs "
        "sensor.adc_bits <= 16 and an RGB render.variant unless mono (docs/characterize.md).",
    )


class VideoSection(StrictModel):
    """``video``: the comparisons and previews of a video run (``capture.frames`` > 1)."""

    compare_alternating: bool = Field(
        True,
        description="Also simulate the alternating short/long-exposure HDR video of a conventional sensor "
        "(Kang et al. 2003) at the same frame rate and score both (HDR applications only).",
    )
    flow: Literal["dis_medium", "dis_fast", "dis_ultrafast", "farneback"] = Field(
        "dis_medium",
        description="Optical flow that warps the alternating video's neighbours onto each frame: OpenCV's "
        "DIS optical flow at a preset, or Farneback's.",
    )
    aliasing_rates_hz: list[float] = Field(
        [3.0],
        description="Frame rates whose temporal aliasing of the scene's motion is reported beside the run's own "
        "(the paper's prototype: 3 frames/s).",
    )
    playback_fps: float | None = Field(
        None, gt=0, le=120, description="Frames per second of video.mp4 and video.gif; null: capture.frame_rate_hz."
    )


class CaptureConfig(StrictModel):
    seed: int = Field(
        0,
        ge=0,
        description="One seed for the whole run, split per stage: render times and samples (the renders), and the "
        "sensor's temporal noise unless sensor.noise_seed is set; the fixed pattern has sensor.fpn_seed.",
    )
    scene: SceneSection = Field(
        default_factory=SceneSection, description="What is in front of the camera: scene.name and its parameters."
    )
    render: RenderSection = Field(
        default_factory=RenderSection, description="Film size, samples and the motion tolerance of the render plan."
    )
    capture: CaptureSection = Field(
        default_factory=CaptureSection, description="Protocol: gate schedule, exposures, interleaving periods."
    )
    camera: CameraSection = Field(
        default_factory=CameraSection,
        description="The camera: how it moves during the capture (camera.shake or camera.trajectory_file; default still) and its lens (camera.lens, focus, focal length, vignetting, diffraction).",
    )
    sensor: SensorConfig = Field(
        default_factory=SensorConfig, description="The multi-bucket pixel: optics, full wells, noise, ADC."
    )
    hdr: HDRSection = Field(default_factory=HDRSection, description="HDR reconstruction method.")
    app: AppSection = Field(
        default_factory=AppSection, description="Reconstruction applied to the reads and its parameters."
    )
    output: OutputSection = Field(default_factory=OutputSection, description="Preview images.")
    video: VideoSection = Field(
        default_factory=VideoSection, description="A video run's comparisons and previews (capture.frames > 1)."
    )

    @model_validator(mode="after")
    def _name_sections(self) -> "CaptureConfig":
        self.name_sections()  # each section's errors on assignment name its dotted key
        return self

    @field_validator("render")
    @classmethod
    def _variant_known(cls, render: RenderSection) -> RenderSection:
        if not any(render.variant.startswith(p) for p in ("llvm_", "scalar_", "cuda_")):
            raise ValueError(f"render.variant: {render.variant!r} is not a Mitsuba variant name")
        return render

    @model_validator(mode="after")
    def _spectral_response_needs_spectral_variant(self) -> "CaptureConfig":
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

    @model_validator(mode="after")
    def _dng_needs_16_bit_rgb(self) -> "CaptureConfig":
        if self.output.dng and self.sensor.adc_bits > 16:
            raise ValueError(
                f"output.dng: DNG samples are 16-bit here; needs sensor.adc_bits <= 16, got {self.sensor.adc_bits}"
            )
        if self.output.dng and is_spectral_variant(self.render.variant) and self.sensor.cfa != "mono":
            raise ValueError(
                f"output.dng: the colour matrix is the RGB render's (raw = per-channel gain x linear "
                f"sRGB); not available for render.variant {self.render.variant!r}"
            )
        return self

    def to_yaml_dict(self) -> dict:
        """The resolved config as plain data (scene parameters filled in with their defaults)."""
        data = self.model_dump(mode="json")
        data["scene"] = {"name": self.scene.name, **self.scene.params().model_dump(mode="json")}
        app, params = self.app.resolve(self.capture.protocol)
        data["app"] = {"name": app.name, **params.model_dump(mode="json")}
        return data


def scene_of(cfg: CaptureConfig) -> scenes.SceneModel:
    """The scene a config captures: ``scene.name`` with its parameters, seen through ``camera``
    (shake or a trajectory, :func:`mbcapture.scene.camera_motion.apply`; ``camera.focal_length_mm`` sets
    its field of view)."""
    scene = scenes.make_scene(cfg.scene.name, cfg.scene.params())
    if cfg.capture.tof is not None:
        scene = demodulated(scene, cfg)
    if cfg.camera.focal_length_mm is not None:
        fov = fov_deg_for(cfg.camera.focal_length_mm, cfg.render.width, cfg.sensor.pixel_pitch_um)
        scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, fov_deg=fov))
    return camera_motion.apply(scene, cfg.camera)


def demodulated(scene: scenes.SceneModel, cfg: CaptureConfig) -> scenes.SceneModel:
    """``scene`` with the phase groups of a time-of-flight capture added as switchable groups (the taps'
    images, :mod:`mbcapture.sensor.demodulation`), the modulated group checked."""
    tof, pixel = cfg.capture.tof, cfg.sensor.tof
    if tof.group not in scene.groups:
        raise ConfigError(
            f"capture.tof.group: {tof.group!r} is not an emitter group of scene {scene.name!r} "
            f"(its groups: {list(scene.groups)})"
        )
    if tof.group not in scene.switchable:
        raise ConfigError(
            f"capture.tof.group: {tof.group!r} of scene {scene.name!r} is always on; the modulated illuminator "
            f"must be switchable (switchable: {sorted(scene.switchable)})"
        )
    if is_spectral_variant(cfg.render.variant):
        raise ConfigError(
            "render.variant: time-of-flight captures render in RGB variants (the phasor channels are AOVs)"
        )
    demod = demodulation.make_demodulation(
        tof.group,
        [f * 1e6 for f in tof.frequencies_mhz],
        tof.phases,
        demodulation.DESIGNS[cfg.capture.protocol],
        pixel.demodulation_contrast,
        pixel.waveform,
        pixel.harmonics,
    )
    return dataclasses.replace(
        scene,
        groups=scene.groups + demod.names,
        switchable=scene.switchable | frozenset(demod.names),
        demodulation=demod,
    )


def format_validation(
    exc: ValidationError,
    prefix: str = "",
    origin: Callable[[tuple], str] | None = None,
    model: type[BaseModel] | None = None,
    owner: str | None = None,
) -> str:
    """:func:`mbcapture.strict.format_validation` with the whole :class:`CaptureConfig` as the root
    (a key unknown in its section is looked for in the others)."""
    return strict.format_validation(exc, prefix, origin, model, owner, root=CaptureConfig)


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


#: Sections whose other keys belong to what their ``name`` selects (a scene, an application).
_SELECTED_BY_NAME = {"scene": "scene", "app": "application"}


def _switch_selected(data: dict, overrides: list[str]) -> tuple[dict, list[str]]:
    """Drop the config file's ``scene.*`` (``app.*``) parameters when ``--set`` switches to another
    scene (application): they belong to the old one. Parameters that a ``--set`` gives are kept.
    Returns the data and one notice per switched section."""
    data = copy.deepcopy(data)
    parsed = [parse_override(t) for t in overrides]
    notices = []
    for section, what in _SELECTED_BY_NAME.items():
        names = [
            v.get("name") if p == [section] and isinstance(v, dict) else v
            for p, v in parsed
            if p in ([section, "name"], [section])
        ]
        old = data.get(section)
        if not names or not isinstance(old, dict) or names[-1] is None or names[-1] == _selected_name(data, section):
            continue
        dropped = [k for k in old if k != "name"]
        if dropped:
            data[section] = {k: v for k, v in old.items() if k == "name"}
            notices.append(
                f"--set {section}.name={names[-1]} replaces {what} {_selected_name(data, section)!r} of the "
                "config file: "
                f"dropped its keys {', '.join(f'{section}.{k}' for k in dropped)}"
            )
    return data, notices


def _selected_name(data: dict, section: str) -> str | None:
    """The scene (application) that raw config ``data`` selects, defaults included."""
    name = (data.get(section) or {}).get("name")
    if name is not None or section == "scene":
        return name or SceneSection.model_fields["name"].default

    capture = data.get("capture") if isinstance(data.get("capture"), dict) else {}
    try:
        return apps.protocol_app(capture.get("protocol", CaptureSection.model_fields["protocol"].default))
    except (ConfigError, KeyError, TypeError):
        return None


def _origin_of(overrides: list[str], source: str) -> Callable[[tuple], str]:
    """path -> '--set render.spp=4' for the last override that set the key at path (or a section
    holding it, or a key inside it), else ``source`` (the file, or 'defaults')."""
    parsed = [(tuple(parse_override(t)[0]), t) for t in overrides]

    def origin(path: tuple) -> str:
        path = tuple(map(str, path))
        if not path:  # a check across sections: no one key to blame
            return source
        for p, text in reversed(parsed):
            n = min(len(p), len(path))
            if p[:n] == path[:n]:
                return f"--set {text}"
        return source

    return origin


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


def config_from_dict(data: dict, source: str = "config", origin: Callable[[tuple], str] | None = None) -> CaptureConfig:
    """Validate raw config data. ``origin(path)`` says where the key at ``path`` came from (default:
    ``source`` for every key); every error names it."""
    origin = origin or (lambda path: source)
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of sections at the top level, got {type(data).__name__}")
    bad = _first_non_finite(data)
    if bad:  # YAML .inf / .nan: no key of any section accepts them (durations, radiances, noise, phases)
        raise ConfigError(f"{origin(tuple(bad[0].split('.')))}: {bad[0]}: expected a finite number (got {bad[1]!r})")
    try:
        cfg = CaptureConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation(exc, origin=origin)) from None
    cfg.scene.params(origin)  # validate the scene's and the application's own keys now, not halfway through a run
    app, _ = cfg.app.resolve(cfg.capture.protocol, origin)
    if cfg.camera.distortion and app.pinhole_truth:
        raise ConfigError(
            f"{origin(('camera', 'distortion'))}: camera.distortion: the {app.name} application's truth is "
            f"pinhole geometry ({app.pinhole_truth}); remove the distortion for this application"
        )
    code = cfg.capture.gate_code
    if code is not None and code.family != "global":
        if not app.coded_gates:
            coded = [n for n in apps.names() if apps.get(n).coded_gates]
            raise ConfigError(
                f"{origin(('capture', 'gate_code', 'family'))}: capture.gate_code.family {code.family!r}: "
                f"the {app.name} application reads global-gate reads; per-pixel codes need an application "
                f"that demultiplexes them ({', '.join(coded)})"
            )
        if cfg.sensor.cfa != "none":
            raise ConfigError(
                f"{origin(('sensor', 'cfa'))}: sensor.cfa {cfg.sensor.cfa!r} with capture.gate_code: "
                "demultiplexing per-pixel codes on a colour mosaic is not modelled; set sensor.cfa none"
            )
    return cfg


def revalidated(cfg: CaptureConfig) -> CaptureConfig:
    """``cfg`` validated again as a whole, as the YAML would be: what assignments through the API
    changed (each checked on its own when made) is checked against the other sections (ConfigError
    otherwise). A config that was not changed comes back equal."""
    return config_from_dict(cfg.model_dump(), source="config")


def shipped_configs() -> list[str]:
    """Names of the configs shipped in ``configs/`` (``mbcapture run <name>`` finds them)."""
    return sorted(p.stem for p in SHIPPED_CONFIG_DIR.glob("*.yaml"))


def resolve_config_path(path: str | Path) -> Path:
    """``path`` if it exists, else the shipped config of that name (``metronome_hdr`` or
    ``metronome_hdr.yaml``); a name that is neither fails naming the shipped ones."""
    p = Path(path)
    if p.exists():
        return p
    names = shipped_configs()
    close = difflib.get_close_matches(p.stem, names, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    if len(p.parts) != 1:
        raise ConfigError(f"{p}: config file not found (the shipped configs, by name: {', '.join(names)}){hint}")
    shipped = SHIPPED_CONFIG_DIR / (p.name if p.suffix in (".yaml", ".yml") else f"{p.name}.yaml")
    if shipped.is_file():
        return shipped
    raise ConfigError(f"{p}: config file not found, and not a shipped config ({', '.join(names)}){hint}")


#: Environment variable of extra ``--set`` overrides applied after the command line's to every
#: config loaded (shell words, e.g. ``"render.width=16 render.height=12"``): any command of the
#: README runs at a tiny size with it (the test suite does), a script's captures too.
ENV_OVERRIDES = "MBCAPTURE_SET"


def env_overrides() -> list[str]:
    """The overrides in ``$MBCAPTURE_SET`` (shell words), announced by a :class:`ConfigNotice`."""
    import os
    import shlex

    text = os.environ.get(ENV_OVERRIDES, "").strip()
    if not text:
        return []
    try:
        words = shlex.split(text)
    except ValueError as exc:
        raise ConfigError(f"${ENV_OVERRIDES}: {exc} in {text!r}") from None
    warnings.warn(f"${ENV_OVERRIDES} adds --set {' --set '.join(words)}", ConfigNotice, stacklevel=3)
    return words


#: Keys naming a file that a config file gives relative to itself (a --set gives it relative to the working
#: directory): scene.file of the ``mitsuba`` scene.
CONFIG_RELATIVE_KEYS = (("scene", "file"),)


def _file_relative_to(data: Any, folder: Path) -> None:
    """Make each of :data:`CONFIG_RELATIVE_KEYS` in the config file's ``data`` absolute, from ``folder``."""
    for section, key in CONFIG_RELATIVE_KEYS:
        part = data.get(section) if isinstance(data, dict) else None
        value = part.get(key) if isinstance(part, dict) else None
        if isinstance(value, str) and value and not Path(value).is_absolute():
            part[key] = str((folder / value).resolve())


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> CaptureConfig:
    """Load a YAML config (a path, or a shipped config's name; the defaults when ``path`` is None)
    and apply ``--set`` overrides, then those of ``$MBCAPTURE_SET``. Switching ``scene.name`` or ``app.name`` by an override drops the
    file's parameters of the old scene or application with a :class:`ConfigNotice` warning."""
    data: Any = {}
    source = "defaults"
    if path is not None:
        p = resolve_config_path(path)
        source = str(path) if Path(path) == p else f"{path} ({p})"
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read config file ({exc.strerror})") from None
        try:
            data = yaml.load(text, Loader=_YAML_LOADER)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            raise ConfigError(f"{p}:{where}: malformed YAML ({getattr(exc, 'problem', exc)})") from None
        if data is None:
            data = {}
        _file_relative_to(data, p.parent)
    overrides = [*overrides, *env_overrides()]
    if isinstance(data, dict):
        data, notices = _switch_selected(data, overrides)
        for n in notices:
            warnings.warn(n, ConfigNotice, stacklevel=2)
    data = apply_overrides(data, overrides)
    return config_from_dict(data, source, _origin_of(overrides, source))
