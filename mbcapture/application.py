"""The applications' registry and data contract: what a reconstruction receives
(:class:`CaptureData`) and returns (:class:`AppOutput`), and the registry that maps an
application's name to it (:func:`register`, :func:`get`, :func:`names`).

It also holds the protocols' registry (:func:`register_protocol`): a protocol is a function of the
config that returns one period's slots, the reads and the buckets it uses, registered by the
application module that reads it by default (the HDR protocols and ``custom`` by :mod:`mbcapture.apps.hdr`);
:func:`mbcapture.timing.protocols.build` turns it into a timeline.

It sits low in the house (docs/architecture.md): a config validates ``app.name`` and ``capture.protocol`` against it, while the applications themselves
(:mod:`mbcapture.apps`) sit above the render plan and the sensor stage they use. Every module of
that package is imported on first use (:func:`load_all`), so a new application is one file that
calls :func:`register` (and, usually, :func:`register_protocol` for its schedule).
Reconstructions are pure numpy on ``CaptureData``, so that they can be tested on small synthetic
inputs with known answers, without Mitsuba.
"""

from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import BaseModel

from .strict import StrictModel
from .errors import ConfigError
from .sensor import dn_to_electrons
from .sensor.cfa import BAYER_PATTERNS, channel_map, demosaic


class NoParams(StrictModel):
    """An application without parameters of its own."""


@dataclass
class CaptureData:
    """What a reconstruction gets. Arrays are (read | bucket, row, column, channel).

    exposure_s          (R,) seconds each read integrated (its buckets' gated time)
    reads_dn            (R, H, W, C) simulated reads, DN; ``saturated`` (R, H, W, C) bool
    reads_e_expected    (R, H, W, C) noise-free, unclipped electrons of each read
    bucket_exposure     (K, H, W, C) noise-free radiant exposure, W m^-2 sr^-1 s (render units x s)
    group_exposure      (K, G, H, W, C) the same per rendered group (``plan.groups``), or None
                        when the application did not ask for it
    bucket_group_s      (K, S) seconds bucket k collected while switchable group
                        ``switchable[s]`` was on (from the timeline, exact)
    k_e                 (C,) electrons per render unit per second
    moving_mask         (H, W) pixels the moving parts cross during the capture
    renderer            the capture's Renderer (for reference renders), None in synthetic tests
    mosaic_dn           (R, H, W) a colour-filter-array sensor's photosite codes, and
    mosaic_saturated    (R, H, W) their flags (sensor.cfa); None without one. ``reads_dn`` are then
                        the demosaiced reads: an application that reconstructs before demosaicing
                        reads the mosaic and demosaics its result (:meth:`demosaic`)
    """

    cfg: Any
    scene: Any
    timeline: Any
    plan: Any
    read_names: list[str]
    exposure_s: np.ndarray
    reads_dn: np.ndarray
    saturated: np.ndarray
    reads_e_expected: np.ndarray
    bucket_exposure: np.ndarray
    k_e: np.ndarray
    moving_mask: np.ndarray
    switchable: tuple[str, ...] = ()
    bucket_group_s: np.ndarray | None = None
    group_exposure: np.ndarray | None = None
    renderer: Any = None
    seed: np.random.SeedSequence | None = None
    mosaic_dn: np.ndarray | None = None
    mosaic_saturated: np.ndarray | None = None

    @property
    def sequential(self) -> bool:
        return bool(self.timeline is not None and self.timeline.sequential)

    def reads_e(self) -> np.ndarray:
        """Reads in electrons (black level removed, gain undone), float64."""

        return dn_to_electrons(self.reads_dn, self.cfg.sensor)

    @property
    def bayer(self) -> bool:
        """True on a Bayer sensor (``sensor.cfa`` one of the Bayer phases) whose mosaic came with the reads."""
        return self.mosaic_dn is not None and self.cfg.sensor.cfa in BAYER_PATTERNS

    def demosaic(self, mosaic: np.ndarray) -> np.ndarray:
        """(..., H, W) values of this sensor's photosites -> (..., H, W, 3), with ``sensor.demosaic``."""
        return demosaic(mosaic, self.cfg.sensor.cfa, self.cfg.sensor.demosaic)

    def photosite_channels(self) -> np.ndarray:
        """(H, W) the channel each photosite of this Bayer sensor sees."""
        return channel_map(self.cfg.sensor.cfa, *self.mosaic_dn.shape[-2:])

    def group_index(self, name: str) -> int:
        return list(self.plan.groups).index(name)


@dataclass
class AppOutput:
    """images: name -> (H, W, C) float linear, written as the layers of ``<app>.exr``.
    png: file stem -> (image name, tone-map percentile; None = linear, 1.0 is white): previews.
    extra_exr: file name -> layers, written as they are. metrics go to report.json.
    summary: lines the CLI prints after a run.
    captions: png stem -> what the preview shows and how it is scaled (what each colour of a mask
    means); shown under it in report.html."""

    images: dict[str, np.ndarray]
    metrics: dict
    png: dict[str, tuple[str, float | None]] = field(default_factory=dict)
    extra_exr: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    summary: list[str] = field(default_factory=list)
    captions: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class App:
    name: str
    reconstruct: Callable[[CaptureData, Any], AppOutput]
    params: type[BaseModel] = NoParams
    per_group: bool = False
    description: str = ""
    #: At most this many float channels in the application's EXRs (3 per RGB image), this many PNG
    #: previews, and this much memory (MB) its own libraries add: the run's resource plan
    #: (mbcapture.exposure.resources); tests/test_docs_and_configs.py holds them to every shipped config.
    output_channels: int = 36
    previews: int = 8
    libraries_mb: float = 0.0
    #: The application's peak working set over a plain capture's (its own comparison captures).
    memory_scale: float = 1.0
    #: Where its truth or reconstruction is pinhole geometry (Mitsuba AOVs through pixel centres, a
    #: projective triangulation), what it is: such an application refuses camera.distortion. "" otherwise.
    pinhole_truth: str = ""
    #: It demultiplexes reads whose sub-frames differ from pixel to pixel (capture.gate_code other
    #: than 'global'); every other application refuses such a capture.
    coded_gates: bool = False
    #: Its reconstruction may render (reference, truth, AOV or comparison images through
    #: ``CaptureData.renderer``), so its captures are not run side by side in one process's threads
    #: (a sweep's points, :func:`mbcapture.sweep.execute.run_here`). False: it works on the capture's
    #: arrays alone.
    renders: bool = True


_REGISTRY: dict[str, App] = {}
#: The folder of the application modules (the package mbcapture.apps).
APPS_DIR = Path(__file__).resolve().parent / "apps"
_loaded = False


def register(
    name: str,
    *,
    params: type[BaseModel] = NoParams,
    per_group: bool = False,
    description: str = "",
    output_channels: int = 36,
    previews: int = 8,
    libraries_mb: float = 0.0,
    memory_scale: float = 1.0,
    pinhole_truth: str = "",
    coded_gates: bool = False,
    renders: bool = True,
):
    """Decorator: ``fn(data: CaptureData, params) -> AppOutput`` is application ``name``.
    ``per_group``: the reconstruction or its metrics need ``CaptureData.group_exposure``.
    ``output_channels``, ``previews``, ``libraries_mb``, ``memory_scale``: what its outputs, libraries
    and working set take; ``pinhole_truth``: why it needs a distortion-free camera; ``coded_gates``:
    it demultiplexes per-pixel coded reads; ``renders``: its reconstruction may render (see :class:`App`)."""

    def deco(fn):
        _REGISTRY[name] = App(
            name,
            fn,
            params,
            per_group,
            description or (fn.__doc__ or "").strip().split("\n")[0],
            output_channels,
            previews,
            libraries_mb,
            memory_scale,
            pinhole_truth,
            coded_gates,
            renders,
        )
        return fn

    return deco


def load_all() -> None:
    """Import every module of this package (each registers its application and protocols)."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    for mod in pkgutil.iter_modules([str(APPS_DIR)]):
        importlib.import_module(f"mbcapture.apps.{mod.name}")


def names() -> list[str]:
    load_all()
    return sorted(_REGISTRY)


def get(name: str) -> App:
    load_all()
    if name not in _REGISTRY:
        raise ConfigError(f"app.name: unknown application {name!r}; expected one of {names()}")
    return _REGISTRY[name]


ProtocolBuilder = Callable[[Any], Any]
"""``fn(cfg) -> (slots of one period, reads, buckets used)``: a protocol (timing.timeline's
``SlotSeconds`` and ``ReadEvent``); or ``fn(cfg) -> Timeline`` for one that lays out segments of its own."""

_PROTOCOLS: dict[str, tuple[ProtocolBuilder, str]] = {}


def register_protocol(name: str, app: str = "hdr") -> Callable[[ProtocolBuilder], ProtocolBuilder]:
    """Decorator: ``fn(cfg) -> (slots of one period, reads, buckets used)`` is protocol ``name``;
    ``app`` is the application that reconstructs its reads by default."""

    def deco(fn: ProtocolBuilder) -> ProtocolBuilder:
        _PROTOCOLS[name] = (fn, app)
        return fn

    return deco


def protocol_names() -> list[str]:
    """Every registered protocol, sorted."""
    load_all()  # application modules register their own protocols
    return sorted(_PROTOCOLS)


def _protocol(name: str) -> tuple[ProtocolBuilder, str]:
    load_all()
    if name not in _PROTOCOLS:
        raise ConfigError(f"capture.protocol: unknown protocol {name!r}; expected one of {protocol_names()}")
    return _PROTOCOLS[name]


def protocol_app(name: str) -> str:
    """The application that reconstructs protocol ``name``'s reads by default."""
    return _protocol(name)[1]


def protocol_builder(name: str) -> ProtocolBuilder:
    """Protocol ``name``'s function of the config (a ConfigError names the known ones)."""
    return _protocol(name)[0]
