"""Turn a :class:`~mbcapture.scene.scenes.SceneModel` into a Mitsuba scene and render emitter groups.

Mitsuba is imported inside :class:`Renderer` only, after :func:`~mbcapture.render.llvm.ensure_llvm`
has pinned a libLLVM that does not crash.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ConfigError
from ..scene.scenes import SceneModel
from .build import (
    SceneBuild,
)
from .bands import band_seed, film_bands
from .lens import Lens
from .pixels import PixelRendering
from .settings import RenderSettings, guide_shares, load_mitsuba
from .cache import RenderCache, canonical, digest, file_digest
from .integrator import PLUGIN_NAME, aov_layout, integrator_class, is_lambertian
from .llvm import llvm_target
from .scene_dicts import CHANNELS, SENSORS, SceneDicts
from .tiles import materialize

#: Modules whose code turns a scene description into pixels: part of every cache key.
_PIXEL_CODE = (
    "renderer.py",
    "integrator.py",
    "pattern.py",
    "build.py",
    "aov.py",
    "coverage.py",
    "bands.py",
    "tiles.py",
    "scene_dicts.py",
    "lens.py",
    "settings.py",
    "pixels.py",
    "xmlscene.py",
)


class Renderer(PixelRendering):
    """Radiance images of a scene's emitter groups at given scene times.

    One :meth:`render` is one Mitsuba pass of :mod:`.integrator`'s per-group path tracer: every
    requested group lands in its own channels, unrequested groups are neither sampled nor
    counted. Moving parts are updated through ``mi.traverse`` parameters wrapped in
    ``dr.make_opaque``, so changing the time does not compile a new kernel (a new *set* of
    requested groups compiles once, then is cached by Dr.Jit).

    Measured on the 2-core x86 VM (llvm_ad_rgb, LLVM 19.1, Mitsuba 3.9.1), metronome scene,
    max_depth 4, best of 3 warm renders, each at a new scene time (so the acceleration
    structure rebuild of ``params.update()`` is included)::

        film      spp   3 groups, one pass   flash only   mi.render 'path'   ratio 3 groups/path
        160x128     4        0.083 s           0.060 s         0.047 s             1.8
        160x128    16        0.22 s            0.14 s          0.13 s              1.7
        640x512     4        0.75 s            0.46 s          0.49 s              1.5
        640x512    16        2.9 s             2.0 s           2.3 s               1.3

    ``path`` gives only the summed image, choosing one emitter per vertex; separate renders
    per group would cost about 3x ``path``, so one pass is 1.7-2.4x cheaper, and it has no
    emitter-selection noise. The first render of a new film size or requested-group set adds
    about 1.5 s of kernel compilation (later renders hit Dr.Jit's kernel cache).

    Spectral mode (``llvm_ad_spectral`` / ``cuda_ad_spectral``): the film is a ``specfilm`` with
    channels R, G, B whose sensitivities are S_c(lambda) = QE_c(lambda) lambda/(h c) of
    ``sensor.spectral_response`` (:func:`mbcapture.sensor.spectral.film_sensitivity`), box filter.
    Measured on Mitsuba 3.9.1: ``specfilm`` does not normalize its curves; a flat field of
    spectral radiance L(lambda) gives exactly integral S_c L d lambda (lambda in nm), so the output
    is in photo-electrons per (m^2 sr s), not W m^-2 sr^-1. Scene RGB colours are upsampled by
    Mitsuba (emission: RGB times a D65-shaped illuminant spectrum, per nm). ``specfilm`` ignores the
    per-group AOVs' wavelengths, so each group is one pass with only that group requested (the
    others are neither sampled nor counted). Cost, metronome, 3 groups, max_depth 4, 160x128,
    16 spp, best of 3 warm renders on the (shared, noisy) 2-core VM: 1.1-1.2 s spectral against
    0.33-0.44 s for the one-pass RGB render, i.e. about 2.5-3.5x (3 passes x ~1.3x spectral);
    the first spectral render adds ~5 s of kernel compilation (one kernel per group).

    Spectra and textures (:mod:`.build`): a :class:`~.build.Spectrum` reflectance or radiance is an
    ``irregular`` spectrum in spectral variants and its linear-sRGB value in RGB variants; a
    :class:`~.build.Texture` is a ``bitmap``. Texture and mesh files are checked before Mitsuba
    loads them (:meth:`~.build.SceneBuild.check_files`), so a missing or corrupt file is a
    ConfigError naming the file and the shape.

    ``film_curves`` (spectral variants only): (wavelengths_nm (n,), curves (3, n)) replaces the
    sensor's film sensitivities, e.g. the CIE 1931 colour-matching functions for an XYZ reference.

    Attributes
    ----------
    groups
        ``scene.groups``: names of the emitter groups, in output order.
    channels
        ``("R", "G", "B")``.
    width, height
        Film size in pixels (columns, rows).
    bands
        The film's row bands (:mod:`.bands`): each is rendered as a crop window with a seed of its
        own (band 0: the render's seed), so that any run of whole bands (:meth:`render_rows`, a tile)
        holds the same pixels as the whole film. A lens that mixes neighbours (distortion,
        diffraction) renders one band, the whole film.
    """

    channels: tuple[str, ...] = CHANNELS

    def __init__(
        self,
        scene: SceneModel,
        width: int,
        height: int,
        settings: RenderSettings | None = None,
        *,
        cache: RenderCache | None = None,
        **settings_fields: Any,
    ) -> None:
        """A renderer of ``scene`` on a ``width`` x ``height`` film, rendering as ``settings`` says (default
        :class:`RenderSettings`; ``settings_fields``: any of its fields, replacing them), its renders kept in
        ``cache`` (None: none)."""
        settings = replace(settings or RenderSettings(), **settings_fields)
        settings.check()
        if not isinstance(scene.build, SceneBuild):
            raise ConfigError(f"scene {scene.name!r}: build payload is not a SceneBuild")
        if width < 1 or height < 1:
            raise ConfigError(f"film size must be positive, got {width}x{height}")
        self.settings = settings
        self.variant, self.sampler, self.max_depth = settings.variant, settings.sampler, int(settings.max_depth)
        self.spectral = self.variant.endswith("_spectral")
        #: (aperture radius m, focus distance m) of Mitsuba's thinlens sensor; None: a pinhole
        self.thin_lens = (
            None if settings.thin_lens is None else (float(settings.thin_lens[0]), float(settings.thin_lens[1]))
        )
        self.lens = Lens(
            scene.camera,
            width,
            height,
            vignetting=settings.vignetting,
            distortion=settings.distortion,
            diffraction=settings.diffraction,
            sensor=settings.sensor,
        )
        #: renders made elsewhere (a cluster's workers, mbcapture.exposure.cluster), by (t, spp, seed, groups, band): used once
        self._given: dict[tuple[float, int, int, tuple[str, ...], int], np.ndarray] = {}
        # a monochrome sensor's mixture of the channels (mbcapture.sensor.mono_weights), or None
        self._mono = None if settings.mono is None else np.asarray(settings.mono, np.float64).reshape(3)
        self._sensitivity = settings.film_sensitivity()
        self._mi, self._dr = load_mitsuba(self.variant)
        self.scene_model = scene
        self.width, self.height = int(width), int(height)
        #: the share of every diffuse bounce sent towards each of the scene's guides (SceneBuild.guides), in their
        #: order: their own shares (``guide_fraction`` None), or ``guide_fraction`` split in their proportions
        self.guide_shares = guide_shares(scene.build.guides, settings.guide_fraction)
        #: the share of every diffuse bounce sent towards the scene's guides together (0: none)
        self.guide_fraction = float(sum(self.guide_shares))
        self.groups: tuple[str, ...] = tuple(scene.groups)
        #: a time-of-flight capture's phase groups (:mod:`mbcapture.sensor.demodulation`): images made from the
        #: modulated group's phasor channels after a render (and after the cache), so that every design of the
        #: taps shares the renders
        self.demodulation = scene.demodulation
        phase = set(self.demodulation.names) if self.demodulation is not None else set()
        #: the groups that have emitters (every group but the phase groups)
        self.emitter_groups: tuple[str, ...] = tuple(g for g in self.groups if g not in phase)
        self._build = build = scene.build
        self._check_build(build)
        self._python_objects: list[Any] = []  # Python Mitsuba objects its scenes hold (mbcapture.render.tiles)
        self.cache = cache
        # the scene descriptions now; the Mitsuba scenes when something is rendered (a run whose
        # renders all come from the cache never loads them)
        self._describe = SceneDicts(
            self._mi,
            build,
            scene.name,
            self.emitter_groups,
            scene.camera,
            self.width,
            self.height,
            self.spectral,
            self._sensitivity,
            self.thin_lens,
            self.lens.render_fov_deg,
            self.sampler,
        )
        self._dicts = self._describe.variant_dicts()
        #: (first row, end row) of each band of the film
        self.bands: tuple[tuple[int, int], ...] = film_bands(
            self.width, self.height, settings.band_rows, self.lens.mixes_pixels
        )
        self._crop: dict[int, tuple[int, int]] = {}  # id(params) -> the rows its film renders now
        self._loaded = False
        self._scene: Any = None
        self._params: Any = None
        self._group_emitters: dict[str, list[Any]] = {}
        self._group_scenes: dict[str, tuple[Any, Any, list[Any]]] = {}
        integrator_class(self.variant)  # registers the plugin
        self._integrator = self._mi.load_dict({"type": PLUGIN_NAME, "max_depth": self.max_depth})
        self._time_s: float | None = None
        #: Seconds spent in the last :meth:`render` (scene update + Mitsuba pass; for a render read
        #: from the cache, the seconds it took when it was made).
        self.last_render_s = 0.0
        #: Whether the last :meth:`render` came from the cache.
        self.last_cached = False
        self.identity = self._identity(list(self._dicts.values())) if cache is not None else None
        self._sampler_probe = None
        self._sample_counts: dict[int, int] = {}
        #: each spectral film's channel curves, by group (None: the main scene's film), loaded when first needed
        self._film_curves: dict[str | None, list[Any]] = {}

    def _check_build(self, build: SceneBuild) -> None:
        """The scene's description against this renderer: its emitters in declared groups, its files readable, no
        projector in a spectral variant, and one band when the lens mixes pixels."""
        name = self.scene_model.name
        unknown = set(build.emitter_groups()) - set(self.groups)
        if unknown:
            raise ConfigError(f"scene {name!r}: emitters in undeclared groups {sorted(unknown)}")
        build.check_files(name)
        if build.projectors and self.spectral:
            raise ConfigError(
                f"scene {name!r}: projector emitters are supported in RGB variants only, not {self.variant!r}"
            )
        band_rows = self.settings.band_rows
        if self.lens.mixes_pixels and band_rows is not None and band_rows < self.height:
            raise ConfigError(
                "render.band_rows: camera.distortion and camera.diffraction act on the whole film, "
                "which is then one band; set render.band_rows null"
            )

    def _ensure_loaded(self) -> None:
        """Make this renderer's variant Mitsuba's current one (a process may hold renderers of several: ``mi.render``
        and the module's types are the current variant's), and load the Mitsuba scene(s) from their descriptions
        (once)."""
        if self._mi.variant() != self.variant:
            self._mi.set_variant(self.variant)
        if self._loaded:
            return
        mi = self._mi
        self._scene = self._load(self._dicts[None])
        self._params = mi.traverse(self._scene)
        self._group_emitters = self._describe.collect_emitters(self._scene)
        for g, d in self._dicts.items():
            if g is not None:
                sc = self._load(d)
                self._group_scenes[g] = (sc, mi.traverse(sc), self._describe.collect_emitters(sc)[g])
        self._integrator.lambertian = all(
            is_lambertian(sc) for sc in [self._scene, *(v[0] for v in self._group_scenes.values())]
        )
        self._integrator.light_alone_at_last = self._integrator.lambertian
        self._integrator.guides = self._guides()
        self._loaded = True

    def _guides(self) -> tuple:
        """The integrator's guides ((centre, radius, share), ...): the scene's spheres with
        :attr:`guide_shares`; none where those are 0."""
        if not self.guide_fraction:
            return ()
        if not self._integrator.lambertian:
            raise ConfigError(
                f"render.guide_fraction: scene {self.scene_model.name!r} has guides, which only "
                "Lambertian materials sample towards; set render.guide_fraction: 0"
            )
        return tuple((g.centre, g.radius, share) for g, share in zip(self._build.guides, self.guide_shares))

    @classmethod
    def from_config(cls, scene: SceneModel, cfg: Any, *, cache: RenderCache | None = None, **fields: Any) -> "Renderer":
        """The renderer a capture config asks for (:meth:`RenderSettings.from_config`), with ``fields`` of
        :class:`RenderSettings` replacing any (e.g. ``film_curves``, ``sensor``)."""
        return cls(
            scene, cfg.render.width, cfg.render.height, RenderSettings.from_config(scene, cfg, **fields), cache=cache
        )

    # -- scene construction -------------------------------------------------------------------
    def _load(self, d: dict[str, Any]) -> Any:
        try:
            return self._mi.load_dict(materialize(self._mi, d, self._python_objects))
        except RuntimeError as exc:  # Mitsuba's own loader errors (e.g. a file it cannot parse)
            msg = " ".join(str(exc).split())
            raise ConfigError(f"scene {self.scene_model.name!r}: Mitsuba cannot load the scene: {msg[:400]}") from None

    # -- state and rendering ------------------------------------------------------------------
    @property
    def mitsuba_scene(self) -> Any:
        """The loaded ``mi.Scene`` (at the last :meth:`set_time`), for AOV or reference renders, its
        film whole (not a band's crop window)."""
        self._ensure_loaded()
        self._set_rows(self._params, (0, self.height))
        return self._scene

    @property
    def mitsuba(self) -> Any:
        """The ``mitsuba`` module, with this renderer's variant set."""
        return self._mi

    def _identity(self, dicts: list[dict[str, Any]]) -> str:
        """Digest of everything but the time that determines this renderer's pixels: the scene
        description(s) with file contents, integrator, variant, the pixel code, library versions,
        and the CPU target the kernels are compiled for."""
        from importlib import metadata

        here = Path(__file__).resolve().parent
        code = {name: file_digest(here / name) for name in _PIXEL_CODE}
        target = llvm_target() if self.variant.startswith("llvm") else {"backend": "cuda"}
        return digest(
            {
                "scene": [canonical(d, self._mi) for d in dicts],
                "groups": list(self.emitter_groups),
                "variant": self.variant,
                "max_depth": self.max_depth,
                "guides": [[*g.centre, g.radius, share] for g, share in zip(self._build.guides, self.guide_shares)]
                if self.guide_fraction
                else [],
                "code": code,
                "versions": {p: metadata.version(p) for p in ("mitsuba", "drjit")},
                "target": target,
            }
        )

    def sample_count(self, spp: int, pattern: bool = False) -> int:
        """The samples per pixel a render takes when asked for ``spp``: exactly ``spp`` where it draws from
        the shared pattern (``pattern``) in an RGB variant (:data:`~.scene_dicts.EXACT_SENSOR`), else this renderer's
        sampler's count (ldsampler rounds up to a power of 4, multijitter to a product of two near-equal
        factors)."""
        key = int(spp)
        if pattern and not self.spectral:
            return key
        if key not in self._sample_counts:
            mi = self._mi
            if self._sampler_probe is None:
                self._sampler_probe = mi.load_dict({"type": self.sampler, "sample_count": 4})
            level = mi.log_level()
            mi.set_log_level(mi.LogLevel.Error)  # the sampler warns when it rounds: that is what we ask
            try:
                self._sampler_probe.set_sample_count(key)
                self._sample_counts[key] = int(self._sampler_probe.sample_count())
            finally:
                mi.set_log_level(level)
        return self._sample_counts[key]

    def counter(self, pattern: bool) -> Callable[[int], int]:
        """:meth:`sample_count` for renders that draw from the shared pattern (``pattern``) or not: what
        a plan's samples become (``plan.shares_pattern``)."""
        return lambda spp: self.sample_count(spp, pattern)

    def state_at(self, t_s: float) -> list:
        """The time-dependent part of the scene at ``t_s``: every moving part's and moving light's
        pose (4x4, as in :meth:`set_time`) and, with a moving camera, the camera's pose. Two times
        with equal states render equal images."""
        parts = self._build.parts
        out = []
        for s in self._build.shapes:
            if s.part is not None and s.light is not None:
                out.append([s.name, np.asarray(parts[s.part](t_s), float) @ s.to_world])
        for part, f in sorted(parts.items()):
            out.append([part, np.asarray(f(t_s), float)])
        if self.scene_model.camera_motion is not None:
            out.append(["camera (sensor.to_world)", self._camera_pose(t_s)])
        return [[name, [[repr(float(x)) for x in row] for row in m]] for name, m in out]

    def _camera_pose(self, t_s: float) -> np.ndarray:
        """(4, 4) world-from-camera of the moving camera at ``t_s`` (:mod:`mbcapture.scene.camera_motion`)."""
        sm = self.scene_model
        return sm.camera_motion.world_from_camera(sm.camera, [float(t_s)])[0]

    def cached(self, kind: str, t_s: float, params: dict, make: Callable[[], np.ndarray]) -> np.ndarray:
        """``make()`` (an image of the scene at ``t_s``), read from the cache when this renderer
        made it before with the same ``kind`` and ``params``, else computed and stored."""
        self.last_cached = False
        if self.cache is None:
            return make()
        key = digest({"renderer": self.identity, "kind": kind, "state": self.state_at(float(t_s)), **params})
        hit = self.cache.get(key, kind)
        if hit is not None:
            self.last_cached = True
            self.last_render_s = float(hit[1].get("seconds", 0.0))
            return hit[0]
        start = time.perf_counter()
        img = make()
        seconds = time.perf_counter() - start
        self.cache.put(
            key,
            img,
            seconds=seconds,
            about={"kind": kind, "scene": self.scene_model.name, "film": [self.width, self.height], **params},
        )
        self.last_render_s = seconds
        return img

    def set_time(self, t_s: float, force: bool = False) -> None:
        """Move every part (and a moving camera) to scene time ``t_s`` (s); no kernel is recompiled. ``force`` redoes the
        update (and the acceleration-structure rebuild) even at the current time, e.g. to time it."""
        t_s = float(t_s)
        self._ensure_loaded()
        camera = self.scene_model.camera_motion is not None
        if (t_s == self._time_s and not force) or not (self._build.parts or camera):
            self._time_s = t_s
            return
        parts = self._build.parts
        pose = self._camera_pose(t_s) if camera else None
        for params in [self._params, *(p for _, p, _ in self._group_scenes.values())]:
            moved = False
            if pose is not None:  # the handheld camera (camera.shake): opaque, so no kernel recompiles
                for sensor in SENSORS:
                    if f"{sensor}.to_world" in params:
                        params[f"{sensor}.to_world"] = self._opaque_transform(pose)
                moved = True
            for s in self._build.shapes:
                if s.part is not None and s.light is not None:
                    m = np.asarray(parts[s.part](t_s), float) @ s.to_world
                    params[f"{s.name}.to_world"] = self._opaque_transform(m)
                    moved = True
            for part, f in parts.items():
                key = f"{part}.to_world"
                if key in params:
                    params[key] = self._opaque_transform(f(t_s))
                    moved = True
            for p in self._build.projectors:
                if p.part is not None:
                    params[f"{p.name}.to_world"] = self._opaque_transform(self._describe.projector_world(p, t_s))
                    moved = True
            for key, part in self._build.file.moving_lights.items() if self._build.file is not None else ():
                m = np.asarray(parts[part](t_s), float) @ self._describe.light_rest[key]
                params[f"{key}.to_world"] = self._opaque_transform(m)
                moved = True
            if moved:
                params.update()
        self._time_s = t_s

    def _opaque_transform(self, matrix: np.ndarray) -> Any:
        """A ``mi.Transform4f`` made opaque: a literal would recompile the kernel every time."""
        tf = self._mi.Transform4f(np.asarray(matrix, float))
        self._dr.make_opaque(tf)
        return tf

    def render(
        self,
        t_s: float,
        spp: int,
        seed: int,
        groups: Sequence[str] | None = None,
        pattern: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """Radiance (W m^-2 sr^-1) of each requested emitter group at scene time ``t_s`` (s);
        in spectral mode the ``specfilm`` value, photo-electrons per (m^2 sr s).

        Returns float32 (group, row, col, channel) = (len(groups), height, width, 3), box pixel
        filter (the mean radiance over each pixel), ``spp`` samples per pixel, deterministic
        for a given ``seed``. ``groups`` defaults to all of :attr:`groups`, in any order given;
        groups not requested are not rendered at all. ``pattern`` (key, offset): the samples drawn
        from the shared pattern ``key``, this render's being its ``offset``, ``offset + 1``, ...
        (:mod:`mbcapture.render.pattern`; ``seed`` then matters only to a spectral variant's camera
        rays); None: all from render.sampler, seeded by ``seed``.
        """
        return self.render_rows(t_s, spp, seed, groups, (0, self.height), pattern)

    def band_span(self, rows: tuple[int, int]) -> range:
        """The indices of the bands that make up ``rows`` (first, end) exactly; ValueError otherwise."""
        r0, r1 = (int(r) for r in rows)
        idx = [i for i, (a, b) in enumerate(self.bands) if a >= r0 and b <= r1]
        if not idx or self.bands[idx[0]][0] != r0 or self.bands[idx[-1]][1] != r1:
            raise ValueError(f"rows {r0}..{r1}: not a run of whole bands of the film ({self.bands})")
        return range(idx[0], idx[-1] + 1)

    def render_rows(
        self,
        t_s: float,
        spp: int,
        seed: int,
        groups: Sequence[str] | None,
        rows: tuple[int, int],
        pattern: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """:meth:`render`'s rows ``rows`` (first, end; a run of whole :attr:`bands`), rendering only
        those: float32 (group, end - first, width, channel), equal to the whole film's rows."""
        req = list(self.groups if groups is None else groups)
        bad = [g for g in req if g not in self.groups]
        if bad or len(set(req)) != len(req):
            raise ConfigError(f"render groups {req}: expected distinct names from {list(self.groups)}")
        if spp < 1:
            raise ConfigError(f"render spp must be >= 1, got {spp}")
        span = self.band_span(rows)
        r0, r1 = int(rows[0]), int(rows[1])

        def band(b: int) -> np.ndarray:  # given by a cluster worker, or rendered here
            given = self._given.pop((float(t_s), int(spp), int(seed), tuple(req), b, _pattern_key(pattern)), None)
            return given if given is not None else self.raw_render(t_s, spp, seed, req, band=b, pattern=pattern)

        img = band(span[0]) if len(span) == 1 else np.concatenate([band(b) for b in span], axis=1)
        # the lens (mbcapture.scene.optics): relative illumination, distortion, then diffraction (a blur in the sensor
        # plane), on every render alike (exposures, truths, the pilot), after the cache: a render is cached as
        # the pinhole sees it. Distortion and diffraction make the film one band (whole).
        return self._mono_mixed(self.lens.apply(img, r0, r1))

    def _mono_mixed(self, img: np.ndarray) -> np.ndarray:
        """``img`` (..., 3) as a monochrome sensor sees it (its one response in every channel); as is otherwise."""
        if self._mono is None:
            return img
        return np.repeat((img @ self._mono.astype(np.float32))[..., None], 3, axis=-1)

    def give(
        self,
        t_s: float,
        spp: int,
        seed: int,
        groups: Sequence[str],
        radiance: np.ndarray,
        band: int = 0,
        pattern: tuple[int, int] | None = None,
    ) -> None:
        """Hand this renderer the raw render of band ``band`` of ``(t_s, spp, seed, groups)`` made by
        another process with the same renderer (a cluster worker, :meth:`raw_render`): :meth:`render`
        and :meth:`render_rows` use it (the lens applied as to their own) instead of rendering, once."""
        self._given[(float(t_s), int(spp), int(seed), tuple(groups), int(band), _pattern_key(pattern))] = np.asarray(
            radiance, np.float32
        )

    def raw_render(
        self,
        t_s: float,
        spp: int,
        seed: int,
        groups: Sequence[str],
        band: int = 0,
        pattern: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """What :meth:`render` caches: band ``band`` of the render before the lens's falloff, distortion,
        diffraction and mono mixture (what :meth:`give` takes)."""
        req = list(groups)
        basis = self.basis_of(req)
        n = self.sample_count(spp, pattern is not None)
        params = self._cache_params(n, seed, basis, pattern)
        if len(self.bands) == 1:  # the whole film: the key it has always had
            img = self.cached(
                "radiance", t_s, params, lambda: self._render(t_s, int(n), int(seed), basis, None, pattern)
            )
        else:
            rows = self.bands[band]
            params["rows"] = list(rows)
            img = self.cached(
                "radiance",
                t_s,
                params,
                lambda: self._render(t_s, int(n), band_seed(seed, band), basis, rows, pattern),
            )
        return self.combined(img, basis, req)

    def basis_of(self, req: list[str]) -> list[str]:
        """What is rendered for the groups ``req``: themselves, a phase group replaced by the modulated group's
        light and phasor channels (:meth:`mbcapture.sensor.demodulation.Demodulation.basis_of`)."""
        return req if self.demodulation is None else self.demodulation.basis_of(req)

    def combined(self, img: np.ndarray, basis: list[str], req: list[str]) -> np.ndarray:
        """Renders of ``basis`` (first axis) -> the images of ``req`` (the phase groups combined)."""
        if self.demodulation is None or basis == req:
            return img
        return self.demodulation.combine(img, basis, req).astype(np.float32)

    @staticmethod
    def _cache_params(
        n: "int | np.ndarray", seed: int, req: list[str], pattern: "tuple[int, int | np.ndarray] | None"
    ) -> dict[str, Any]:
        """The part of a render's cache key its call gives: samples taken, seed, groups and pattern. The
        samples and the pattern's offset may be one per pixel (:meth:`render_pixels`): one value where they
        are all alike (the key such a render has always had), else the digest of them all."""
        params: dict[str, Any] = {"spp": _one_or_digest(n), "seed": int(seed) & 0xFFFFFFFF, "groups": req}
        if pattern is not None:  # without one, the key renders have always had
            params["pattern"] = [int(pattern[0]) & 0xFFFFFFFF, _one_or_digest(pattern[1])]
        return params

    def _set_rows(self, params: Any, rows: tuple[int, int]) -> None:
        """Make the film of the scene whose parameters are ``params`` render rows ``rows`` (a crop window)."""
        if self._crop.get(id(params), (0, self.height)) == tuple(rows):
            return
        mi = self._mi
        for sensor in SENSORS:
            if f"{sensor}.film.crop_size" in params:
                params[f"{sensor}.film.crop_size"] = mi.ScalarVector2u(self.width, rows[1] - rows[0])
                params[f"{sensor}.film.crop_offset"] = mi.ScalarPoint2u(0, rows[0])
        params.update()
        self._crop[id(params)] = tuple(rows)

    def _render(
        self,
        t_s: float,
        spp: int,
        seed: int,
        req: list[str],
        rows: tuple[int, int] | None = None,
        pattern: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """The Mitsuba pass(es) of ``req`` at ``t_s``: the whole film, or its ``rows`` (a band)."""
        start = time.perf_counter()
        self._ensure_loaded()
        rows = (0, self.height) if rows is None else (int(rows[0]), int(rows[1]))
        if pattern is None:
            self._integrator.use_pattern(None)
        else:
            self._integrator.use_pattern(pattern[0], pattern[1], rows[0] * self.width)
        h = rows[1] - rows[0]
        out = np.zeros((len(req), h, self.width, 3), np.float32)
        lit, waves, slots = aov_layout(req, self._group_emitters)
        if lit and self.spectral:
            self.set_time(t_s)
            for g in lit:
                scene, params, emitters = self._scene_of(g)
                self._set_rows(params, rows)
                self._integrator.set_groups([g], emitters)
                img = self._mi.render(scene, integrator=self._integrator, spp=int(spp), seed=int(seed) & 0xFFFFFFFF)
                out[req.index(g)] = np.asarray(img, dtype=np.float32)[..., :3]
        elif lit:
            self.set_time(t_s)
            self._set_rows(self._params, rows)
            self._integrator.set_groups(lit, [self._group_emitters[g] for g in lit], waves)
            img = self._mi.render(
                self._scene,
                integrator=self._integrator,
                spp=int(spp),
                seed=int(seed) & 0xFFFFFFFF,
                sensor=self._sensor_index(pattern),
            )
            arr = np.asarray(img, dtype=np.float32)[..., 3:]
            arr = arr.reshape(h, self.width, -1, 3).transpose(2, 0, 1, 3)
            for name, i in slots.items():
                if name in req:
                    out[req.index(name)] = arr[i]
        self.last_render_s = time.perf_counter() - start
        return out

    def render_path(self, t_s: float, spp: int, seed: int) -> np.ndarray:
        """The whole scene (all groups on) with Mitsuba's built-in ``path`` integrator,
        float32 (row, col, channel): the reference the group images must sum to."""
        self._ensure_loaded()
        self.set_time(t_s)
        self._set_rows(self._params, (0, self.height))
        integ = self._mi.load_dict(
            {"type": "path", "max_depth": self.max_depth, "rr_depth": max(self.max_depth + 1, 5)}
        )
        img = self._mi.render(self._scene, integrator=integ, spp=int(spp), seed=int(seed))
        return np.asarray(img, dtype=np.float32)[..., :3]


def _one_or_digest(values: "int | np.ndarray") -> "int | str":
    """A cache key's value for a count or an offset: the int where all of ``values`` are alike (or it is one),
    else the SHA-256 of them all."""
    a = np.asarray(values, np.int64)
    if a.size and a.min() == a.max():
        return int(a.flat[0])
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def _pattern_key(pattern: tuple[int, int] | None) -> tuple[int, int] | None:
    """``pattern`` (key, offset) as plain ints, or None."""
    return None if pattern is None else (int(pattern[0]) & 0xFFFFFFFF, int(pattern[1]))


class RenderRows:
    """Rows (first, end) of a :class:`Renderer`'s film, a run of whole bands: what
    :func:`mbcapture.exposure.integrate.integrate` asks of a renderer (``render``, the film size, the channels,
    ``sample_count``), so that a tile integrates exactly as the whole film does on those rows."""

    def __init__(self, renderer: Renderer, rows: tuple[int, int]):
        renderer.band_span(rows)  # whole bands, or ValueError
        self.renderer, self.rows = renderer, (int(rows[0]), int(rows[1]))
        self.width, self.height = renderer.width, self.rows[1] - self.rows[0]
        self.channels, self.groups, self.cache = renderer.channels, renderer.groups, renderer.cache

    def render(
        self,
        t_s: float,
        spp: int,
        seed: int,
        groups: Sequence[str] | None = None,
        pattern: tuple[int, int] | None = None,
    ) -> np.ndarray:
        return self.renderer.render_rows(t_s, spp, seed, groups, self.rows, pattern)

    def sample_count(self, spp: int, pattern: bool = False) -> int:
        return self.renderer.sample_count(spp, pattern)

    def counter(self, pattern: bool) -> Callable[[int], int]:
        return self.renderer.counter(pattern)
