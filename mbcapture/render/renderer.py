"""Turn a :class:`~mbcapture.scenes.SceneModel` into a Mitsuba scene and render emitter groups.

Mitsuba is imported inside :class:`Renderer` only, after :func:`~mbcapture.render.llvm.ensure_llvm`
has pinned a libLLVM that does not crash.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from ..errors import ConfigError
from ..optics import (
    apply_diffraction,
    apply_distortion,
    bilinear_taps,
    diffraction_reach,
    focus_distance_m,
    natural_vignetting,
    thin_lens_aperture_m,
    undistortion_maps,
)
from ..scenes import SceneModel
from ..sensor.photons import mono_weights
from ..sensor.spectral import film_sensitivity
from .build import (
    MAX_GUIDE_SHARE,
    MOVABLE_EMITTER_KINDS,
    Guide,
    Material,
    PerTile,
    SceneBuild,
    Shape,
    Spectrum,
    Texture,
    spectrum_to_rgb_radiance,
    spectrum_to_rgb_reflectance,
)
from .bands import band_seed, film_bands
from .cache import RenderCache, digest
from .integrator import CAMERA_DIM, PLUGIN_NAME, integrator_class, is_lambertian
from .pattern import pair as pattern_pair, pixel_key
from .llvm import apply_target_from_env, ensure_llvm, llvm_target
from .tiles import materialize, tile_table, tiles_description

if TYPE_CHECKING:
    from ..sensor.config import SensorConfig

#: Mitsuba samplers a Renderer may use (render.sampler).
SAMPLERS = ("multijitter", "ldsampler", "independent")
#: The scene's second sensor (RGB variants): the first's camera and film with Mitsuba's independent sampler,
#: for the renders that draw from the shared pattern (mbcapture.render.pattern). Those draw every dimension,
#: the camera ray's included, from the pattern, so the sampler only lays out mi.render's lanes (spp
#: consecutive lanes a pixel) and places each sample in its pixel, which the box filter ignores; the
#: independent sampler takes any count, where multijitter takes 90 when asked for 85 (6 % more samples).
EXACT_SENSOR = "sensor_exact"
#: The scene's sensors, in their order in the scene (mi.render's ``sensor`` index).
_SENSORS = ("sensor", EXACT_SENSOR)

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
)


@lru_cache(maxsize=None)
def _file_sha256(path: str, mtime_ns: int, size: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's content (memoized by path, modification time and size)."""
    st = Path(path).stat()
    return _file_sha256(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)


def _canonical(obj: Any, mi: Any) -> Any:
    """A Mitsuba scene dict as plain JSON data for hashing: transforms as matrices, files by content."""
    if isinstance(obj, dict):
        return {
            str(k): ({"file": Path(v).name, "sha256": file_digest(v)} if k == "filename" else _canonical(v, mi))
            for k, v in obj.items()
        }
    if isinstance(obj, (list, tuple)):
        return [_canonical(v, mi) for v in obj]
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, float):
        return repr(obj)
    if isinstance(obj, mi.ScalarTransform4f):
        return [[repr(float(x)) for x in row] for row in np.asarray(obj.matrix, dtype=np.float64)]
    if isinstance(obj, mi.Bitmap):  # e.g. a projector's pattern: by content
        data = np.ascontiguousarray(np.asarray(obj))
        return {
            "bitmap": hashlib.sha256(data.tobytes()).hexdigest(),
            "shape": list(data.shape),
            "dtype": data.dtype.str,
        }
    if isinstance(obj, np.ndarray):
        return {"array": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(), "shape": list(obj.shape)}
    # anything else would be hashed by its repr, which need not show its content: refuse, so that
    # two different scenes can never share a cache key
    raise TypeError(f"render cache key: cannot hash a {type(obj).__name__} in the scene description")


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


class Renderer:
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

    channels: tuple[str, ...] = ("R", "G", "B")

    def __init__(
        self,
        scene: SceneModel,
        width: int,
        height: int,
        *,
        variant: str = "llvm_ad_rgb",
        max_depth: int = 4,
        sensor: "SensorConfig | None" = None,
        film_curves: tuple[np.ndarray, np.ndarray] | None = None,
        cache: RenderCache | None = None,
        sampler: str = "multijitter",
        vignetting: str = "none",
        diffraction: bool = False,
        thin_lens: tuple[float, float] | None = None,
        mono: np.ndarray | None = None,
        distortion: Sequence[float] | None = None,
        band_rows: int | None = None,
        guide_fraction: float | None = 0.0,
    ) -> None:
        if thin_lens is not None and not (thin_lens[0] > 0 and thin_lens[1] > 0):
            raise ConfigError(f"thin lens: aperture radius and focus distance must be positive, got {thin_lens}")
        #: (aperture radius m, focus distance m) of Mitsuba's thinlens sensor; None: a pinhole
        self.thin_lens = None if thin_lens is None else (float(thin_lens[0]), float(thin_lens[1]))
        if vignetting not in ("none", "cos4"):
            raise ConfigError(f"camera.vignetting: expected 'none' or 'cos4', got {vignetting!r}")
        # radial distortion (mbcapture.optics): Mitsuba renders a pinhole of field render_fov_deg (wider than
        # the camera's for barrel distortion) and every render is resampled onto the sensor's pixels
        self.distortion = None if not distortion else tuple(float(k) for k in distortion)
        self.render_fov_deg = float(scene.camera.fov_deg)
        self._undistort = None
        if self.distortion is not None:
            try:
                map_x, map_y, t_render = undistortion_maps(scene.camera, width, height, self.distortion)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
            self._undistort = (map_x, map_y)
            self.render_fov_deg = float(np.degrees(2.0 * np.arctan(t_render)))
        # the falloff of each ray's field angle, on the grid Mitsuba renders (before any resampling)
        self._falloff = (
            None
            if vignetting == "none"
            else natural_vignetting(replace(scene.camera, fov_deg=self.render_fov_deg), width, height).astype(
                np.float32
            )[None, :, :, None]
        )
        if diffraction and sensor is None:
            raise ConfigError("camera.diffraction: needs the sensor (f-number, pixel pitch, wavelengths)")
        self._diffraction = sensor if diffraction else None  # the sensor's f-number, pitch and wavelengths
        # what render_pixels needs to reach every render pixel a sensor pixel reads: the four each is interpolated
        # from (distortion) and the log of how much its neighbours weigh in it (diffraction; mbcapture.optics)
        self._taps = None
        if self._undistort is not None:  # each tap's samples: its weight b over sum b^2 of the sensor pixel's count
            index, weight = bilinear_taps(*self._undistort)
            self._taps = (index.reshape(4, -1), (weight / (weight * weight).sum(axis=0)).reshape(4, -1))
        self._log_reach = None
        if diffraction:
            # a pixel's samples in proportion to its weight k in a sensor pixel, scaled by sum k / sum k^2: the sensor
            # pixel's variance is then what the first pass's would be at the count it asks for (every pinhole pixel at
            # it), at about sum k (sum k / sum k^2) = 1.46 times the count (f/2.8, 5.6 um) instead of the window's 289
            k = diffraction_reach(sensor.pixel_pitch_um, sensor.f_number, sensor.wavelength_nm)
            self._log_reach = np.log(np.maximum(k * (k.sum() / (k * k).sum()), 1e-300))
        #: renders made elsewhere (a cluster's workers, mbcapture.cluster), by (t, spp, seed, groups, band): used once
        self._given: dict[tuple[float, int, int, tuple[str, ...], int], np.ndarray] = {}
        # a monochrome sensor's mixture of the channels (mbcapture.sensor.mono_weights), or None
        self._mono = None if mono is None else np.asarray(mono, np.float64).reshape(3)
        if not isinstance(scene.build, SceneBuild):
            raise ConfigError(f"scene {scene.name!r}: build payload is not a SceneBuild")
        if width < 1 or height < 1:
            raise ConfigError(f"film size must be positive, got {width}x{height}")
        if max_depth < 1:
            raise ConfigError(f"render.max_depth must be >= 1, got {max_depth}")
        if not variant.endswith(("_rgb", "_spectral")) or variant.startswith("scalar"):
            raise ConfigError(f"render.variant: expected an llvm/cuda *_rgb or *_spectral variant, got {variant!r}")
        if sampler not in SAMPLERS:
            raise ConfigError(f"render.sampler: expected one of {list(SAMPLERS)}, got {sampler!r}")
        self.sampler = sampler
        self.spectral = variant.endswith("_spectral")
        self._sensitivity: tuple[np.ndarray, np.ndarray] | None = None
        if film_curves is not None:
            if not self.spectral:
                raise ConfigError(f"render.variant {variant!r}: film_curves need a spectral variant")
            wl, curves = (np.asarray(a, np.float64) for a in film_curves)
            if wl.ndim != 1 or curves.shape != (3, wl.size):
                raise ConfigError(
                    f"film_curves: expected wavelengths (n,) and curves (3, n), got {wl.shape}, {curves.shape}"
                )
            self._sensitivity = (wl, curves)
        elif self.spectral:
            if sensor is None:
                raise ConfigError(f"render.variant {variant!r}: a spectral render needs the sensor config")
            try:
                self._sensitivity = film_sensitivity(sensor)
            except ValueError as exc:
                raise ConfigError(f"sensor.{exc}") from None
        if variant.startswith("llvm"):
            ensure_llvm()
        import drjit as dr
        import mitsuba as mi

        if variant not in mi.variants():
            raise ConfigError(f"render.variant: {variant!r} not in {mi.variants()}")
        mi.set_variant(variant)
        if variant.startswith("llvm"):
            apply_target_from_env()  # MBCAPTURE_LLVM_TARGET: compile for another CPU (before any kernel)
        self._mi, self._dr = mi, dr
        self.variant = variant
        self.scene_model = scene
        self.width, self.height = int(width), int(height)
        self.max_depth = int(max_depth)
        #: the share of every diffuse bounce sent towards each of the scene's guides (SceneBuild.guides), in their
        #: order: their own shares (``guide_fraction`` None), or ``guide_fraction`` split in their proportions
        self.guide_shares = guide_shares(scene.build.guides, guide_fraction)
        #: the share of every diffuse bounce sent towards the scene's guides together (0: none)
        self.guide_fraction = float(sum(self.guide_shares))
        self.groups: tuple[str, ...] = tuple(scene.groups)
        build: SceneBuild = scene.build
        unknown = set(build.emitter_groups()) - set(self.groups)
        if unknown:
            raise ConfigError(f"scene {scene.name!r}: emitters in undeclared groups {sorted(unknown)}")

        self._build = build
        build.check_files(scene.name)
        self._python_objects: list[Any] = []  # Python Mitsuba objects its scenes hold (mbcapture.render.tiles)
        if build.projectors and self.spectral:
            raise ConfigError(
                f"scene {scene.name!r}: projector emitters are supported in RGB variants only, not {variant!r}"
            )
        self.cache = cache
        # the scene descriptions now; the Mitsuba scenes when something is rendered (a run whose
        # renders all come from the cache never loads them)
        self._dicts: dict[str | None, dict[str, Any]] = {None: self._scene_dict()}
        # spectral: a group whose emitters share one spectral shape f_g gets its own scene, with
        # flat emitters and film curves S_c f_g, so wavelengths are sampled where the group emits
        if self.spectral:
            for g in self.groups:
                shape = self._group_spectral_shape(g)
                if shape is not None:
                    self._dicts[g] = self._scene_dict(flat_group=g, film_shape=shape)
        whole = self.distortion is not None or diffraction  # the lens mixes neighbouring pixels
        if whole and band_rows is not None and band_rows < self.height:
            raise ConfigError(
                "render.band_rows: camera.distortion and camera.diffraction act on the whole film, "
                "which is then one band; set render.band_rows null"
            )
        #: (first row, end row) of each band of the film
        self.bands: tuple[tuple[int, int], ...] = film_bands(self.width, self.height, band_rows, whole)
        self._crop: dict[int, tuple[int, int]] = {}  # id(params) -> the rows its film renders now
        self._loaded = False
        self._scene: Any = None
        self._params: Any = None
        self._group_emitters: dict[str, list[Any]] = {}
        self._group_scenes: dict[str, tuple[Any, Any, list[Any]]] = {}
        integrator_class(variant)  # registers the plugin
        self._integrator = mi.load_dict({"type": PLUGIN_NAME, "max_depth": self.max_depth})
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
        self._group_emitters = self._collect_emitters(self._scene)
        for g, d in self._dicts.items():
            if g is not None:
                sc = self._load(d)
                self._group_scenes[g] = (sc, mi.traverse(sc), self._collect_emitters(sc)[g])
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
    def from_config(
        cls, scene: SceneModel, cfg: Any, *, cache: RenderCache | None = None, **overrides: Any
    ) -> "Renderer":
        """The renderer a capture config asks for (film, variant, depth, sampler, sensor), with
        ``overrides`` of any keyword of :class:`Renderer` (e.g. ``film_curves``, ``sensor``)."""
        r = cfg.render
        lens = thin_lens_of(scene, cfg)
        kw: dict[str, Any] = {
            "variant": r.variant,
            "max_depth": r.max_depth,
            "sampler": r.sampler,
            "sensor": cfg.sensor,
            "cache": cache,
            "vignetting": cfg.camera.vignetting,
            "diffraction": cfg.camera.diffraction,
            "thin_lens": lens,
            "mono": mono_weights(cfg.sensor, r.variant),
            "distortion": cfg.camera.distortion,
            "band_rows": r.band_rows,
            "guide_fraction": r.guide_fraction,
        }
        kw.update(overrides)
        return cls(scene, r.width, r.height, **kw)

    # -- scene construction -------------------------------------------------------------------
    def _load(self, d: dict[str, Any]) -> Any:
        try:
            return self._mi.load_dict(materialize(self._mi, d, self._python_objects))
        except RuntimeError as exc:  # Mitsuba's own loader errors (e.g. a file it cannot parse)
            msg = " ".join(str(exc).split())
            raise ConfigError(f"scene {self.scene_model.name!r}: Mitsuba cannot load the scene: {msg[:400]}") from None

    def _group_emission(self, group: str) -> list[Any]:
        out = [s.light.radiance for s in self._build.shapes if s.light is not None and s.light.group == group]
        env = self._build.environment
        if env is not None and env.group == group:
            out.append(env.radiance)
        return out

    def _group_spectral_shape(self, group: str) -> Spectrum | None:
        """The common spectral shape (integral 1) of a group's emitters, or None when they are not
        all Spectra proportional to one another."""
        rads = self._group_emission(group)
        if not rads or not all(isinstance(r, Spectrum) for r in rads):
            return None
        wl0, v0 = rads[0].arrays
        total = rads[0].integral()
        if not total > 0:
            return None
        f = v0 / total
        for r in rads[1:]:
            wl, v = r.arrays
            if (
                wl.shape != wl0.shape
                or not np.allclose(wl, wl0)
                or not np.allclose(v / max(r.integral(), 1e-300), f, rtol=1e-6, atol=1e-12 * f.max())
            ):
                return None
        return Spectrum(tuple(wl0), tuple(f))

    def _scene_dict(self, flat_group: str | None = None, film_shape: Spectrum | None = None) -> dict[str, Any]:
        self._flat_group = flat_group
        mi = self._mi
        cam = self.scene_model.camera
        T = mi.ScalarTransform4f
        d: dict[str, Any] = {
            "type": "scene",
            "sensor": {
                **(
                    {"type": "perspective"}
                    if self.thin_lens is None
                    else {"type": "thinlens", "aperture_radius": self.thin_lens[0], "focus_distance": self.thin_lens[1]}
                ),
                "fov": self.render_fov_deg,
                "fov_axis": "x",
                "near_clip": 1e-3,
                "to_world": T().look_at(origin=list(cam.origin), target=list(cam.target), up=list(cam.up)),
                "film": self._film_dict(film_shape),
                "sampler": {"type": self.sampler, "sample_count": 4},
            },
        }
        if not self.spectral:  # the same camera, for the renders that draw from the shared pattern (EXACT_SENSOR)
            d[EXACT_SENSOR] = {**d["sensor"], "sampler": {"type": "independent", "sample_count": 4}}
        parts = self._build.parts
        grouped: dict[str, dict[str, Any]] = {}
        for s in self._build.shapes:
            if s.name in d or s.name in parts or s.name in (*_SENSORS, "environment"):
                raise ConfigError(f"scene {self.scene_model.name!r}: duplicate shape name {s.name!r}")
            if s.part is not None and s.part not in parts:
                raise ConfigError(f"shape {s.name!r}: unknown part {s.part!r}")
            if s.part is None:
                d[s.name] = self._shape_dict(s, np.asarray(s.to_world, float))
            elif s.light is not None:
                if s.kind not in MOVABLE_EMITTER_KINDS:
                    raise ConfigError(
                        f"shape {s.name!r}: a moving light must be one of {sorted(MOVABLE_EMITTER_KINDS)}"
                    )
                d[s.name] = self._shape_dict(s, parts[s.part](0.0) @ s.to_world)
            else:
                grouped.setdefault(s.part, {"type": "shapegroup"})[s.name] = self._shape_dict(
                    s, np.asarray(s.to_world, float)
                )
        for part, group in grouped.items():
            d[f"{part}__group"] = group
            d[part] = {
                "type": "instance",
                "shapegroup": {"type": "ref", "id": f"{part}__group"},
                "to_world": T(np.asarray(parts[part](0.0), float)),
            }
        env = self._build.environment
        if env is not None:
            d["environment"] = {
                "type": "constant",
                "radiance": self._emission_dict(env.radiance, env.group == flat_group),
            }
        for p in self._build.projectors:
            if p.name in d or p.name in parts:
                raise ConfigError(f"scene {self.scene_model.name!r}: duplicate name {p.name!r} (projector)")
            if p.part is not None and p.part not in parts:
                raise ConfigError(f"projector {p.name!r}: unknown part {p.part!r}")
            d[p.name] = self._projector_dict(p)
        return d

    def _projector_world(self, p, t_s: float) -> np.ndarray:
        m = p.to_world()
        return m if p.part is None else np.asarray(self._build.parts[p.part](t_s), float) @ m

    def _projector_dict(self, p) -> dict[str, Any]:
        """Mitsuba's ``projector``: its texture value v lights a plane perpendicular to the axis at
        axial distance z with irradiance pi v scale / z^2 (measured), so scale = 1/pi makes the image
        the irradiance at 1 m (see :class:`~.build.Projector`)."""
        mi = self._mi
        return {
            "type": "projector",
            "to_world": mi.ScalarTransform4f(self._projector_world(p, 0.0)),
            "fov": float(p.fov_deg),
            "fov_axis": "x",
            "scale": 1.0 / np.pi,
            "irradiance": {
                "type": "bitmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(p.image)),
                "raw": True,
                "filter_type": "bilinear",
                "wrap_mode": "clamp",
            },
        }

    def _film_dict(self, shape: Spectrum | None = None) -> dict[str, Any]:
        film: dict[str, Any] = {"width": self.width, "height": self.height, "rfilter": {"type": "box"}}
        if self._sensitivity is None:
            return {"type": "hdrfilm", "pixel_format": "rgb", **film}
        wl, srf = self._sensitivity
        step = np.diff(wl)
        if not np.allclose(step, step[0]):
            raise ConfigError("sensor.spectral_response: the camera curves are not on a regular grid")
        if shape is not None:  # S_c(lambda) f_g(lambda) on a 1 nm grid over the overlap
            swl, sv = shape.arrays
            lo, hi = max(np.ceil(wl[0]), np.ceil(swl[0])), min(np.floor(wl[-1]), np.floor(swl[-1]))
            if hi - lo < 2:
                raise ConfigError("a spectral emitter lies outside the sensor's spectral range")
            grid = np.arange(lo, hi + 0.5, 1.0)
            f = np.interp(grid, swl, sv)
            srf = np.stack([np.interp(grid, wl, c) * f for c in srf])
            wl = grid
        film["type"] = "specfilm"
        for c, values in zip(self.channels, srf):
            film[c] = {
                "type": "regular",
                "wavelength_min": float(wl[0]),
                "wavelength_max": float(wl[-1]),
                "values": ", ".join(repr(float(v)) for v in values),
            }
        return film

    def _shape_dict(self, s: Shape, to_world: np.ndarray) -> dict[str, Any]:
        out = shape_description(self._mi, s, to_world, self._bsdf_dict(s))
        if s.light is not None and s.kind != "tiles":
            out["emitter"] = {
                "type": "area",
                "radiance": self._emission_dict(s.light.radiance, s.light.group == self._flat_group),
            }
        return out

    def _bsdf_dict(self, s: Shape) -> dict[str, Any]:
        """The shape's Lambertian BSDF (black without a material)."""
        mat = s.material or Material((0.0, 0.0, 0.0))
        if isinstance(mat.reflectance, PerTile):
            refl = tile_table(
                mat.reflectance.values, self.spectral, f"scene {self.scene_model.name!r}, shape {s.name!r}"
            )
        else:
            refl = self._reflectance_dict(mat.reflectance)
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": refl}
        return {"type": "twosided", "material": bsdf} if mat.twosided else bsdf

    def _emission_dict(self, value: Any, flat: bool) -> dict[str, Any]:
        """Emission; ``flat``: a Spectrum's integral as a constant (its shape is in the film)."""
        if flat:
            return {"type": "uniform", "value": float(value.integral())}
        return self._spectrum_dict(value, emission=True)

    def _spectrum_dict(self, value: Any, *, emission: bool) -> dict[str, Any]:
        """An RGB tuple or a Spectrum as a Mitsuba texture dict for this variant."""
        if isinstance(value, Spectrum):
            if self.spectral:
                wl, v = value.arrays
                return {
                    "type": "irregular",
                    "wavelengths": ", ".join(repr(float(x)) for x in wl),
                    "values": ", ".join(repr(float(x)) for x in v),
                }
            value = spectrum_to_rgb_radiance(value) if emission else spectrum_to_rgb_reflectance(value)
        return {"type": "rgb", "value": [float(x) for x in value]}

    def _reflectance_dict(self, value: Any) -> dict[str, Any]:
        if isinstance(value, Texture):
            return {"type": "bitmap", "filename": str(value.path), "filter_type": value.filter_type}
        return self._spectrum_dict(value, emission=False)

    def _collect_emitters(self, scene: Any) -> dict[str, list[Any]]:
        """Group name -> its Mitsuba emitter objects in ``scene``."""
        by_name = {sh.id(): sh.emitter() for sh in scene.shapes() if sh.emitter() is not None}
        out: dict[str, list[Any]] = {g: [] for g in self.groups}
        for s in self._build.shapes:
            if s.light is not None:
                out[s.light.group].append(by_name[s.name])
        if self._build.environment is not None:
            out[self._build.environment.group].append(scene.environment())
        if self._build.projectors:
            by_id = {e.id(): e for e in scene.emitters()}
            for p in self._build.projectors:
                out[p.group].append(by_id[p.name])
        return out

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
                "scene": [_canonical(d, self._mi) for d in dicts],
                "groups": list(self.groups),
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
        the shared pattern (``pattern``) in an RGB variant (:data:`EXACT_SENSOR`), else this renderer's
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
        """(4, 4) world-from-camera of the moving camera at ``t_s`` (:mod:`mbcapture.camera_motion`)."""
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
                for sensor in _SENSORS:
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
                    params[f"{p.name}.to_world"] = self._opaque_transform(self._projector_world(p, t_s))
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
        # the lens (mbcapture.optics): relative illumination, distortion, then diffraction (a blur in the sensor
        # plane), on every render alike (exposures, truths, the pilot), after the cache: a render is cached as
        # the pinhole sees it. Distortion and diffraction make the film one band (whole).
        return self._mono_mixed(self._lens(img, r0, r1))

    def _lens(self, img: np.ndarray, r0: int, r1: int) -> np.ndarray:
        """The lens on the pinhole's rows ``r0`` .. ``r1`` (group, row, col, channel): relative illumination, then
        (on the whole film) distortion and diffraction."""
        if self._falloff is not None:
            img = img * self._falloff[:, r0:r1]
        if self._undistort is not None:  # the lens bends each pixel's ray: resample the pinhole render
            img = apply_distortion(img, *self._undistort)
        if self._diffraction is not None:
            s = self._diffraction
            img = apply_diffraction(img, s.pixel_pitch_um, s.f_number, s.wavelength_nm).astype(np.float32)
        return img

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
        n = self.sample_count(spp, pattern is not None)
        params = self._cache_params(n, seed, req, pattern)
        if len(self.bands) == 1:  # the whole film: the key it has always had
            return self.cached(
                "radiance", t_s, params, lambda: self._render(t_s, int(n), int(seed), req, None, pattern)
            )
        rows = self.bands[band]
        params["rows"] = list(rows)
        return self.cached(
            "radiance", t_s, params, lambda: self._render(t_s, int(n), band_seed(seed, band), req, rows, pattern)
        )

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

    @property
    def renders_pixels_alone(self) -> bool:
        """Whether :meth:`render_pixels` renders the listed pixels alone, at a cost in proportion to them: a lens
        acting pixel by pixel. A lens that mixes neighbours (camera.distortion, camera.diffraction) makes it render
        the whole film, the listed pixels' neighbourhoods at their samples and the rest at one."""
        return self._undistort is None and self._diffraction is None

    def render_pixels(
        self,
        t_s: float,
        spp: "int | np.ndarray",
        seed: int,
        groups: Sequence[str],
        pixels: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None" = None,
        cached: bool = False,
    ) -> np.ndarray:
        """Radiance of each requested group at the film pixels ``pixels`` (flat indices y * W + x) only,
        ``spp`` samples each: float32 (len(groups), len(pixels), 3), the same estimator as :meth:`render`
        (box filter: the mean over each pixel's area; the lens and a mono mixture applied), at a
        cost in proportion to the pixels where the lens acts pixel by pixel (:attr:`renders_pixels_alone`).
        Written here because Mitsuba renders whole films
        (or crop rectangles): the camera rays of the listed pixels are generated as ``mi.render`` does
        (the sampler seeded over pixels x spp lanes, spp consecutive lanes per pixel, so its
        stratification is per pixel) and each lane's per-group AOVs (spectral: the film's channels of the
        sample, one pass a group) are summed into its pixel. A lens that mixes neighbours (distortion,
        diffraction) reads pinhole pixels around each listed one: the whole pinhole film is rendered, each
        pixel with the listed pixels' samples in proportion to its weight in them and the rest with one
        (:meth:`_lens_samples`), and put through the lens as a film is, so the value is unbiased and costs
        about one sample of the whole film more.
        ``pattern`` (key, offset): the samples drawn from the shared pattern as :meth:`render` draws them,
        so that a pixel's value is the one a whole-film render with that pattern gives it. With a pattern,
        ``spp`` and the offset may be one per pixel (arrays of the pixels' length): pixel i takes the pattern's
        samples offset[i] .. offset[i] + spp[i] - 1, all pixels in one render (adaptive sampling's tiers).
        ``cached``: kept in the render cache under the pixels' digest, as :meth:`render` keeps a film (the
        pilot's blocks and adaptive sampling's passes, which a run on a warm cache with the same choice of
        pixels reuses)."""
        req = list(groups)
        pix = np.ascontiguousarray(np.asarray(pixels, dtype=np.uint32).ravel())
        counts = np.broadcast_to(np.asarray(spp, np.int64), pix.shape)
        if pattern is None:
            if counts.size and counts.min() != counts.max():
                raise ValueError(
                    "render_pixels: samples per pixel that vary need a pattern (the sampler's "
                    "sequences are spp consecutive lanes a pixel)"
                )
            n = self.sample_count(int(counts.flat[0]) if counts.size else 1)
            counts, offsets = np.full(pix.shape, n, np.int64), None
        else:
            offsets = np.broadcast_to(np.asarray(pattern[1], np.int64), pix.shape)
            if counts.size and (counts.min() < 1 or offsets.min() < 0 or (offsets + counts).max() > 2**32):
                raise ValueError("render_pixels: expected samples >= 1 a pixel and pattern samples within 0 .. 2^32")

        def rendered(at: np.ndarray, n: np.ndarray, first: np.ndarray | None, s: int) -> np.ndarray:
            """``_render_pixels`` of pixels ``at`` (the pinhole's, before the lens), kept in the cache if asked."""
            pat = None if pattern is None else (pattern[0], first)
            if not cached:
                return self._render_pixels(t_s, n, s, req, at, pat, first)
            params = {
                **self._cache_params(n, s, req, pat),
                "pixels": hashlib.sha256(at.tobytes()).hexdigest(),
                "n_pixels": int(at.size),
            }
            return self.cached("pixels", t_s, params, lambda: self._render_pixels(t_s, n, s, req, at, pat, first))

        if self.renders_pixels_alone:
            out = rendered(pix, counts, offsets, seed)
            if self._falloff is not None:
                out = out * self._falloff.reshape(-1)[pix][None, :, None]
            return self._mono_mixed(out)
        # a lens that mixes neighbours: the whole pinhole film, each pixel with the samples that what reads it asks for
        # (its share of them), the rest with one, through the lens as :meth:`render`'s films are
        film = np.arange(self.width * self.height, dtype=np.uint32)
        asked, first = self._lens_samples(pix, counts, offsets)
        if pattern is not None:  # one render: a pixel nothing asks for takes one sample at a place of its own
            start = int(np.random.default_rng(int(seed) & 0xFFFFFFFF).integers(0, 2**31))
            img = rendered(film, np.maximum(asked, 1), np.where(asked > 0, first, start), seed)
        else:  # the sampler's sequences take one count a render: the reached pixels at it, the rest at one
            reached = asked > 0
            img = np.zeros((len(req), film.size, 3), np.float32)
            img[:, reached] = rendered(film[reached], np.full(int(reached.sum()), int(counts.flat[0])), None, seed)
            img[:, ~reached] = rendered(
                film[~reached], np.ones(int((~reached).sum()), np.int64), None, band_seed(seed, 0x5A)
            )
        img = self._lens(img.reshape(len(req), self.height, self.width, 3), 0, self.height)
        return self._mono_mixed(img.reshape(len(req), -1, 3)[:, pix])

    def _lens_samples(
        self, pix: np.ndarray, counts: np.ndarray, offsets: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(flat, per pinhole pixel) the samples :meth:`render_pixels` renders each pinhole pixel with (0: none asked;
        it then takes one) and the pattern offset they start at, where sensor pixels ``pix`` ask for ``counts`` from
        ``offsets``: through diffraction, each sensor pixel's count in proportion to how much each neighbour weighs in
        it (:func:`mbcapture.optics.diffraction_reach`; rounded, the most over what reaches a pixel), which for a
        given variance costs the fewest samples; through distortion, the four pixels it is interpolated from, its
        count over the sum of their squared weights times each one's weight (the same rule). Unbiased whatever they
        are (every pixel is rendered); they set the variance and the cost."""
        from scipy.ndimage import grey_dilation

        n = np.zeros(self.height * self.width)
        n[pix] = counts
        o = np.zeros(self.height * self.width, np.int64)
        if offsets is not None:
            o[pix] = offsets
        n, o = n.reshape(self.height, self.width), o.reshape(self.height, self.width)
        if self._log_reach is not None:
            none = -1e300
            log_n = grey_dilation(
                np.where(n > 0, np.log(np.maximum(n, 1.0)), none), structure=self._log_reach, mode="constant", cval=none
            )
            n = np.where(log_n > none / 2, np.rint(np.exp(np.minimum(log_n, 700.0))), 0.0)
            o = grey_dilation(o, size=self._log_reach.shape, mode="constant", cval=0)
        n, o = n.ravel(), o.ravel()
        if self._taps is not None:
            on = np.flatnonzero(n > 0)
            reach_n, reach_o = np.zeros_like(n), np.zeros_like(o)
            for taps, share in zip(*self._taps):
                np.maximum.at(reach_n, taps[on], np.rint(n[on] * share[on]))
                np.maximum.at(reach_o, taps[on], o[on])
            n, o = reach_n, reach_o
        return n.astype(np.int64), o

    def _render_pixels(
        self,
        t_s: float,
        counts: np.ndarray,
        seed: int,
        req: list[str],
        pix: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None",
        offsets: np.ndarray | None,
    ) -> np.ndarray:
        """:meth:`render_pixels` before the lens's falloff and a mono mixture: ``counts`` samples at each of
        ``pix``, from the pattern's samples ``offsets`` on (with a pattern) or the sampler's (equal counts).
        RGB: every group in one pass (its AOVs); spectral: one pass a group, in the scene whose film samples
        the group's wavelengths (as :meth:`_render`)."""
        out = np.zeros((len(req), pix.size, 3), np.float32)
        self._ensure_loaded()  # the emitters of each group are known once the scene is loaded
        lit = [g for g in req if self._group_emitters[g]]
        if not lit or pix.size == 0:
            return out
        self.set_time(t_s)
        passes = [[g] for g in lit] if self.spectral else [lit]
        for groups in passes:
            scene, params, emitters = (
                self._scene_of(groups[0])
                if self.spectral
                else (self._scene, self._params, [self._group_emitters[g] for g in groups])
            )
            self._set_rows(params, (0, self.height))  # the rays below address the whole film
            self._integrator.set_groups(groups, emitters)
            sums = self._pixel_sums(scene, groups[0] if self.spectral else None, counts, seed, pix, pattern, offsets)
            for i, g in enumerate(groups):
                out[req.index(g)] = sums[:, i]
        return out

    def _scene_of(self, group: str) -> tuple[Any, Any, list[list[Any]]]:
        """A spectral group's (scene, its parameters, [its emitters]): its own scene where its emitters share
        one spectral shape (:meth:`_group_spectral_shape`), else the main one."""
        if group in self._group_scenes:
            scene, params, emitters = self._group_scenes[group]
            return scene, params, [emitters]
        return self._scene, self._params, [self._group_emitters[group]]

    def _pixel_sums(
        self,
        scene: Any,
        group: str | None,
        counts: np.ndarray,
        seed: int,
        pix: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None",
        offsets: np.ndarray | None,
    ) -> np.ndarray:
        """One pass of :meth:`_render_pixels` in ``scene`` (the integrator's groups set): float64 (pixels,
        groups, 3), each pixel's mean over its samples. ``group``: the spectral group rendered (its scene's film
        curves weigh the wavelengths), None in RGB."""
        mi, dr = self._mi, self._dr
        lanes = int(counts.sum())
        sensor = scene.sensors()[self._sensor_index(pattern)]
        sampler = sensor.sampler().clone()
        key = index = None
        if pattern is None:  # the sampler's sequences: n consecutive lanes a pixel
            n = int(counts[0])
            sampler.set_sample_count(n)
            # the clone would keep the last mi.render's count, and the quasi-Monte Carlo samplers would then
            # stratify over the wrong sequences
            sampler.set_samples_per_wavefront(n)
            self._integrator.use_pattern(None)
            per_pixel = mi.UInt32(n)
            dr.make_opaque(per_pixel)  # a literal would compile a kernel for every count
            slot = dr.arange(mi.UInt32, lanes) // per_pixel
            pixel = dr.gather(mi.UInt32, mi.UInt32(_aligned(pix)), slot)
        else:  # the pattern draws every dimension: each lane is told its pixel and its sample of the pattern
            slots = np.repeat(np.arange(pix.size, dtype=np.uint32), counts)
            starts = np.cumsum(counts) - counts
            lane_index = (np.arange(lanes, dtype=np.int64) - np.repeat(starts - offsets, counts)).astype(np.uint32)
            slot, pixel, index = (
                mi.UInt32(_aligned(slots)),
                mi.UInt32(_aligned(pix[slots])),
                mi.UInt32(_aligned(lane_index)),
            )
            self._integrator.use_pattern(int(pattern[0]) & 0xFFFFFFFF, 0, 0, lanes=(pixel, index))
            key = mi.UInt32(int(pattern[0]) & 0xFFFFFFFF)
            dr.make_opaque(key)
        sampler.seed(int(seed) & 0xFFFFFFFF, lanes)
        y = pixel // self.width
        x = pixel - y * self.width
        if self.spectral and pattern is not None:
            # mi.render's spectral camera ray is its sampler's (the integrator cannot redraw its wavelengths and
            # their weight); these lanes have no sampler sequence of their own, so the ray's point in the pixel,
            # the aperture and the wavelengths are the pattern's: the same estimator, stratified across the strata
            draw = lambda d: pattern_pair(dr, mi, index, pixel_key(pixel, key), mi.UInt32(CAMERA_DIM + d))  # noqa: E731
            in_pixel, aperture = draw(0), (draw(1) if sensor.needs_aperture_sample() else mi.Point2f(0.5))
            wavelength = draw(2).x
        else:  # mi.render's order: the point in the pixel, the aperture, the wavelengths (spectral)
            in_pixel = sampler.next_2d()
            aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
            wavelength = sampler.next_1d() if self.spectral else mi.Float(0.0)
        pos = (mi.Point2f(mi.Float(x), mi.Float(y)) + in_pixel) * mi.ScalarVector2f(1.0 / self.width, 1.0 / self.height)
        ray, weight = sensor.sample_ray_differential(sensor.shutter_open(), wavelength, pos, aperture)
        spec, _, aovs = self._integrator.sample(scene, sampler, ray, None, mi.Bool(True))
        if self.spectral:
            values = self._film_values(sensor.film(), group, ray.wavelengths, weight * spec)
        else:
            values = [value * weight[0] for value in aovs]
        C = len(values)
        # the sums' array at a power of two of the pixels (at least 1024): a scatter's kernel holds its target's
        # size as a literal, so a size of its own for every choice of pixels compiled the render anew each call
        acc = dr.zeros(mi.Float, (1 << max(10, int(np.ceil(np.log2(pix.size))))) * C)
        for c, value in enumerate(values):
            dr.scatter_reduce(dr.ReduceOp.Add, acc, value, slot * C + c)
        dr.eval(acc)
        return np.asarray(acc, dtype=np.float64)[: pix.size * C].reshape(pix.size, C // 3, 3) / counts[:, None, None]

    def _film_values(self, film: Any, group: str, wavelengths: Any, spec: Any) -> list[Any]:
        """What ``specfilm`` stores of one sample (its channels), written here because Mitsuba 3.9.1's Python
        binding of ``Film.prepare_sample`` corrupts memory (measured: a segmentation fault). As the film
        does: the sample's value at each wavelength (``spec``, the ray's weight included) over the sum of the
        film's curves there (its wavelength-sampling density; 1 where that is 0), times each channel's
        curve, averaged over the wavelengths. The curves are the film's own (the scene's film description)."""
        mi, dr = self._mi, self._dr
        key = group if group in self._dicts else None  # the groups of the main scene share its film
        if key not in self._film_curves:
            film_dict = self._dicts[key]["sensor"]["film"]
            self._film_curves[key] = [mi.load_dict(film_dict[c]) for c in self.channels]
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wavelengths = wavelengths
        total = film.sensor_response_function().eval(si)
        scaled = spec * dr.select(total != 0.0, dr.rcp(total), 1.0)
        n = dr.size_v(mi.Spectrum)
        out = []
        for curve in self._film_curves[key]:
            weights = curve.eval(si)
            out.append(sum(weights[i] * scaled[i] for i in range(n)) * (1.0 / n))
        return out

    def _sensor_index(self, pattern: tuple[int, int] | None) -> int:
        """The scene's sensor a render uses: :data:`EXACT_SENSOR` (1) where it draws from the shared pattern in
        an RGB variant, else the user's sampler's (0)."""
        return 1 if pattern is not None and not self.spectral else 0

    def _set_rows(self, params: Any, rows: tuple[int, int]) -> None:
        """Make the film of the scene whose parameters are ``params`` render rows ``rows`` (a crop window)."""
        if self._crop.get(id(params), (0, self.height)) == tuple(rows):
            return
        mi = self._mi
        for sensor in _SENSORS:
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
        lit = [g for g in req if self._group_emitters[g]]
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
            self._integrator.set_groups(lit, [self._group_emitters[g] for g in lit])
            img = self._mi.render(
                self._scene,
                integrator=self._integrator,
                spp=int(spp),
                seed=int(seed) & 0xFFFFFFFF,
                sensor=self._sensor_index(pattern),
            )
            arr = np.asarray(img, dtype=np.float32)[..., 3:]
            arr = arr.reshape(h, self.width, len(lit), 3).transpose(2, 0, 1, 3)
            for i, g in enumerate(lit):
                out[req.index(g)] = arr[i]
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


def shape_description(mi: Any, s: Shape, to_world: np.ndarray, bsdf: dict[str, Any]) -> dict[str, Any]:
    """The scene-description entry of shape ``s``'s geometry at ``to_world`` with ``bsdf`` (no emitter): a tiles
    shape as one mesh (:func:`mbcapture.render.tiles.tiles_description`), a mesh from its .ply or .obj file, else
    Mitsuba's shape of its kind. The renderer's scenes and the moving shadows' static scene
    (:mod:`mbcapture.render.shadows`) are made of these."""
    if s.kind == "tiles":  # one mesh, one BSDF (mbcapture.render.tiles)
        return tiles_description(s.tiles, to_world, bsdf)
    out: dict[str, Any] = {"type": s.kind, "to_world": mi.ScalarTransform4f(np.asarray(to_world, float))}
    if s.kind == "mesh":
        out["type"] = "ply" if str(s.mesh).lower().endswith(".ply") else "obj"
        out["filename"] = str(s.mesh)
        out["face_normals"] = True
    out["bsdf"] = bsdf
    return out


def _aligned(a: np.ndarray) -> np.ndarray:
    """``a``'s values in memory aligned to 64 bytes. Dr.Jit reads a numpy array where it lies, and its kernel
    declares the loads aligned or not by the address: an array from wherever numpy put it compiled the same
    render again (0.19 s at 640x512) whenever its alignment differed from the last's (Dr.Jit's kernel log)."""
    a = np.ascontiguousarray(a)
    buf = np.empty(a.nbytes + 64, np.uint8)
    start = (-buf.ctypes.data) % 64
    out = buf[start : start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


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
    :func:`mbcapture.integrate.integrate` asks of a renderer (``render``, the film size, the channels,
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
