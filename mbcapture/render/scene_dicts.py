"""The Mitsuba scene descriptions of a scene (:class:`SceneDicts`): what :class:`mbcapture.render.Renderer` loads.

A :class:`~mbcapture.render.build.SceneBuild` says what is in the scene in the project's own terms (shapes,
Lambertian materials, lights in groups, an environment, projectors); this module writes it as Mitsuba's
``load_dict`` dictionaries for one variant: the camera (pinhole or thin lens), the film (RGB, or a spectral film of
the sensor's curves), every shape with its BSDF and area emitter, the moving parts as instances of shape groups, the
environment and the projectors. It sits above :mod:`.tiles` (a colour chart's many patches, one mesh), which
:mod:`.build` is below, so it cannot live in build.py. No Mitsuba import: the module ``mi`` is handed in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..scene.projective import Camera
from .build import (
    RadianceImage,
    MOVABLE_EMITTER_KINDS,
    Material,
    PerTile,
    SceneBuild,
    Shape,
    Spectrum,
    Texture,
    spectrum_to_rgb_radiance,
    spectrum_to_rgb_reflectance,
)
from .tiles import tile_table, tiles_description
from . import xmlscene

#: The film's channels.
CHANNELS = ("R", "G", "B")
#: The second camera, for the renders that draw from the shared pattern (Mitsuba's independent sampler takes any
#: count; :mod:`mbcapture.render.pattern`).
EXACT_SENSOR = "sensor_exact"
#: The cameras' names in a scene dictionary.
SENSORS = ("sensor", EXACT_SENSOR)


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


@dataclass
class SceneDicts:
    """The Mitsuba dictionaries of ``build`` (scene ``scene_name``, its emitter ``groups``) seen by ``camera`` on a
    ``width`` x ``height`` film: ``mi`` the Mitsuba module of the variant, ``spectral`` whether it is spectral,
    ``sensitivity`` the spectral film's (wavelengths, curves) or None, ``thin_lens`` (aperture radius, focus
    distance) or None for a pinhole, ``render_fov_deg`` the field Mitsuba renders (wider than the camera's under
    barrel distortion), ``sampler`` Mitsuba's sampler."""

    mi: Any
    build: SceneBuild
    scene_name: str
    groups: tuple[str, ...]
    camera: Camera
    width: int
    height: int
    spectral: bool
    sensitivity: tuple[np.ndarray, np.ndarray] | None
    thin_lens: tuple[float, float] | None
    render_fov_deg: float
    sampler: str
    #: a scene file's moving lights: id -> their to_world as the file places them (filled by :meth:`scene_dict`)
    light_rest: dict = field(default_factory=dict)

    def group_emission(self, group: str) -> list[Any]:
        """The radiances of ``group``'s emitters (area lights and the environment)."""
        out = [s.light.radiance for s in self.build.shapes if s.light is not None and s.light.group == group]
        env = self.build.environment
        if env is not None and env.group == group:
            out.append(env.radiance)
        return out

    def group_spectral_shape(self, group: str) -> Spectrum | None:
        """The common spectral shape (integral 1) of a group's emitters, or None when they are not
        all Spectra proportional to one another."""
        rads = self.group_emission(group)
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

    def scene_dict(self, flat_group: str | None = None, film_shape: Spectrum | None = None) -> dict[str, Any]:
        """The scene: the camera (and, in RGB, its twin for the shared pattern: ``EXACT_SENSOR``), every shape (a
        moving part's as an instance of its shape group), the environment and the projectors. ``flat_group``: a
        spectral group rendered alone, whose emitters are flat (their shape, ``film_shape``, is in the film)."""
        mi = self.mi
        cam = self.camera
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
                "film": self.film_dict(film_shape),
                "sampler": {"type": self.sampler, "sample_count": 4},
            },
        }
        if not self.spectral:  # the same camera, for the renders that draw from the shared pattern (EXACT_SENSOR)
            d[EXACT_SENSOR] = {**d["sensor"], "sampler": {"type": "independent", "sample_count": 4}}
        parts = self.build.parts
        grouped: dict[str, dict[str, Any]] = {}
        for s in self.build.shapes:
            if s.name in d or s.name in parts or s.name in (*SENSORS, "environment"):
                raise ConfigError(f"scene {self.scene_name!r}: duplicate shape name {s.name!r}")
            if s.part is not None and s.part not in parts:
                raise ConfigError(f"shape {s.name!r}: unknown part {s.part!r}")
            if s.part is None:
                d[s.name] = self.shape_dict(s, np.asarray(s.to_world, float), flat_group)
            elif s.light is not None:
                if s.kind not in MOVABLE_EMITTER_KINDS:
                    raise ConfigError(
                        f"shape {s.name!r}: a moving light must be one of {sorted(MOVABLE_EMITTER_KINDS)}"
                    )
                d[s.name] = self.shape_dict(s, parts[s.part](0.0) @ s.to_world, flat_group)
            else:
                grouped.setdefault(s.part, {"type": "shapegroup"})[s.name] = self.shape_dict(
                    s, np.asarray(s.to_world, float), flat_group
                )
        if self.build.file is not None:
            self._add_file(d, grouped)
        for part, group in grouped.items():
            d[f"{part}__group"] = group
            d[part] = {
                "type": "instance",
                "shapegroup": {"type": "ref", "id": f"{part}__group"},
                "to_world": T(np.asarray(parts[part](0.0), float)),
            }
        env = self.build.environment
        if env is not None:
            d["environment"] = {
                "type": "constant",
                "radiance": self.emission_dict(env.radiance, env.group == flat_group),
            }
        for p in self.build.projectors:
            if p.name in d or p.name in parts:
                raise ConfigError(f"scene {self.scene_name!r}: duplicate name {p.name!r} (projector)")
            if p.part is not None and p.part not in parts:
                raise ConfigError(f"projector {p.name!r}: unknown part {p.part!r}")
            d[p.name] = self.projector_dict(p)
        return d

    def _add_file(self, d: dict[str, Any], grouped: dict[str, dict[str, Any]]) -> None:
        """The scene file's objects (its sensor, film, sampler and integrator left out), each under its id; a moving
        shape in its part's shape group, moved by the part's instance."""
        f = self.build.file
        state, _ = xmlscene.parse(f.path, dict(f.parameters))
        for key, entry in xmlscene.file_entries(self.mi, state).items():
            if key in d or key in self.build.parts:
                raise ConfigError(f"scene.file: {f.path}: id {key!r} is taken by the capture (rename it in the file)")
            if key in f.moving_lights:  # moved through its own to_world (light cannot be instanced)
                rest = xmlscene.rest_matrix(entry)
                self.light_rest[key] = rest
                entry = {k: v for k, v in entry.items() if k not in ("center", "radius", "position")}
                entry["to_world"] = self.mi.ScalarTransform4f(rest)
                d[key] = entry
            elif key in f.moving:
                grouped.setdefault(f.moving[key], {"type": "shapegroup"})[key] = entry
            else:
                d[key] = entry

    def projector_world(self, p, t_s: float) -> np.ndarray:
        """Projector ``p``'s to-world matrix at ``t_s`` (its part's motion applied)."""
        m = p.to_world()
        return m if p.part is None else np.asarray(self.build.parts[p.part](t_s), float) @ m

    def projector_dict(self, p) -> dict[str, Any]:
        """Mitsuba's ``projector``: its texture value v lights a plane perpendicular to the axis at
        axial distance z with irradiance pi v scale / z^2 (measured), so scale = 1/pi makes the image
        the irradiance at 1 m (see :class:`~.build.Projector`)."""
        mi = self.mi
        return {
            "type": "projector",
            "to_world": mi.ScalarTransform4f(self.projector_world(p, 0.0)),
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

    def film_dict(self, shape: Spectrum | None = None) -> dict[str, Any]:
        """The film: RGB, or a spectral film of the sensor's curves (times ``shape``, a group's spectral shape)."""
        film: dict[str, Any] = {"width": self.width, "height": self.height, "rfilter": {"type": "box"}}
        if self.sensitivity is None:
            return {"type": "hdrfilm", "pixel_format": "rgb", **film}
        wl, srf = self.sensitivity
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
        for c, values in zip(CHANNELS, srf):
            film[c] = {
                "type": "regular",
                "wavelength_min": float(wl[0]),
                "wavelength_max": float(wl[-1]),
                "values": ", ".join(repr(float(v)) for v in values),
            }
        return film

    def shape_dict(self, s: Shape, to_world: np.ndarray, flat_group: str | None = None) -> dict[str, Any]:
        """Shape ``s`` at ``to_world``: its geometry and BSDF, and its area emitter where it is a light."""
        out = shape_description(self.mi, s, to_world, self.bsdf_dict(s))
        if s.light is not None and s.kind != "tiles":
            out["emitter"] = {
                "type": "area",
                "radiance": self.emission_dict(s.light.radiance, s.light.group == flat_group),
            }
        return out

    def bsdf_dict(self, s: Shape) -> dict[str, Any]:
        """The shape's Lambertian BSDF (black without a material)."""
        mat = s.material or Material((0.0, 0.0, 0.0))
        if isinstance(mat.reflectance, PerTile):
            refl = tile_table(mat.reflectance.values, self.spectral, f"scene {self.scene_name!r}, shape {s.name!r}")
        else:
            refl = self.reflectance_dict(mat.reflectance)
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": refl}
        return {"type": "twosided", "material": bsdf} if mat.twosided else bsdf

    def emission_dict(self, value: Any, flat: bool) -> dict[str, Any]:
        """Emission; ``flat``: a Spectrum's integral as a constant (its shape is in the film)."""
        if flat:
            return {"type": "uniform", "value": float(value.integral())}
        if isinstance(value, RadianceImage):
            if self.spectral:
                raise ConfigError(f"scene {self.scene_name!r}: an image's radiance needs an RGB render.variant")
            return {
                "type": "bitmap",
                # the rectangle's v grows upwards, the image's rows downwards (measured: row 0 rendered at the bottom)
                "bitmap": self.mi.Bitmap(np.ascontiguousarray(value.pixels[::-1])),
                "raw": True,
                "filter_type": "bilinear",
                "wrap_mode": "clamp",
            }
        return self.spectrum_dict(value, emission=True)

    def spectrum_dict(self, value: Any, *, emission: bool) -> dict[str, Any]:
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

    def reflectance_dict(self, value: Any) -> dict[str, Any]:
        """A reflectance: a texture file, an RGB tuple or a Spectrum."""
        if isinstance(value, Texture):
            return {"type": "bitmap", "filename": str(value.path), "filter_type": value.filter_type}
        return self.spectrum_dict(value, emission=False)

    def collect_emitters(self, scene: Any) -> dict[str, list[Any]]:
        """Group name -> its Mitsuba emitter objects in ``scene``."""
        by_name = {sh.id(): sh.emitter() for sh in scene.shapes() if sh.emitter() is not None}
        out: dict[str, list[Any]] = {g: [] for g in self.groups}
        for s in self.build.shapes:
            if s.light is not None:
                out[s.light.group].append(by_name[s.name])
        if self.build.environment is not None:
            out[self.build.environment.group].append(scene.environment())
        by_id = {e.id(): e for e in scene.emitters()}
        for p in self.build.projectors:
            out[p.group].append(by_id[p.name])
        for name, group in self.build.file.emitters if self.build.file is not None else ():
            out[group].append(by_name[name] if name in by_name else by_id[name])
        return out

    def variant_dicts(self) -> dict[str | None, dict[str, Any]]:
        """The scene (key None) and, in a spectral variant, a scene of its own for each group whose emitters share
        one spectral shape f_g: flat emitters and film curves S_c f_g, so wavelengths are sampled where it emits."""
        dicts: dict[str | None, dict[str, Any]] = {None: self.scene_dict()}
        if self.spectral:
            for g in self.groups:
                shape = self.group_spectral_shape(g)
                if shape is not None:
                    dicts[g] = self.scene_dict(flat_group=g, film_shape=shape)
        return dicts
