"""Many flat rectangles with a reflectance each, as one Mitsuba mesh and one BSDF.

A scene with many small coloured patches (a ColorChecker's 24) could give each patch a shape and
a ``diffuse`` BSDF of its own. Mitsuba then traces every shape's intersection code and every
BSDF's evaluation into the render kernel (Dr.Jit records each instance of a virtual call), and
the kernel grows with the patch count. Measured on the colour-chart scene, one group-render,
llvm_ad_spectral, 2-core VM: 0.09 s with no patches, 0.21 s with 6, 0.72 s with 24 (the same
with regular or uniform spectra: the cost is the instances, not their data).

A ``kind="tiles"`` shape (:class:`~.build.Shape`) is one triangle mesh, two triangles per tile,
whose BSDF is one ``diffuse`` with a tile-table texture: every vertex of tile ``i`` carries the
texture coordinate u = i + 1/2, and the texture looks the reflectance up by ``floor(u)``.

* Spectral variants: the tiles' spectra (sharing one regular wavelength grid) are a (tiles,
  wavelengths) table interpolated linearly in wavelength and zero outside the grid, as Mitsuba's
  ``irregular`` spectrum evaluates each one. RGB tiles use Mitsuba's sRGB spectral upsampling
  (``srgb_model_fetch``), as its ``rgb`` texture does.
* RGB variants: a (tiles, 3) table of linear-sRGB albedos (spectra converted as
  :func:`~.build.spectrum_to_rgb_reflectance`).

Mitsuba has no such texture; it is written here (a Python ``mi.Texture``, created per variant
by :func:`tile_texture_class`). The scene description holds the tiles as plain arrays
(:func:`tiles_description`) so that the render cache can hash it; :func:`materialize` turns the
description into Mitsuba objects when the scene is loaded.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from .build import RGB, Spectrum, spectrum_to_rgb_reflectance

#: ``type`` of the scene-description entries :func:`materialize` replaces.
TILES_TYPE = "mbcapture_tiles"
TABLE_TYPE = "mbcapture_tile_table"

# the canonical rectangle's corners ([-1, 1]^2, z = 0) in counter-clockwise order seen from +z
_CORNERS = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])


def tile_geometry(matrices: Sequence[np.ndarray], to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (4n, 3), faces (2n, 3) and texture coordinates (4n, 2) of n tiles, tile i the
    canonical rectangle under ``to_world @ matrices[i]``. A tile's faces wind so that their normal
    is the rectangle's transformed normal (a mirroring matrix reverses the winding)."""
    verts, faces = [], []
    for i, m in enumerate(matrices):
        full = np.asarray(to_world, float) @ np.asarray(m, float)
        if full.shape != (4, 4):
            raise ConfigError(f"tile {i}: expected a (4, 4) matrix, got {full.shape}")
        verts.append(_CORNERS @ full[:3, :3].T + full[:3, 3])
        tri = [[0, 1, 2], [0, 2, 3]] if np.linalg.det(full[:3, :3]) > 0 else [[0, 2, 1], [0, 3, 2]]
        faces.append(np.asarray(tri) + 4 * i)
    n = len(verts)
    uv = np.repeat(np.stack([np.arange(n) + 0.5, np.full(n, 0.5)], -1), 4, axis=0)
    return np.concatenate(verts), np.concatenate(faces), uv


def tile_table(values: Sequence[RGB | Spectrum], spectral: bool, where: str) -> dict[str, Any]:
    """The description of a tile-table texture (``type`` :data:`TABLE_TYPE`) for the tiles'
    reflectances ``values``, for a spectral or an RGB variant; ConfigError naming ``where``
    for a table Mitsuba cannot evaluate this way."""
    if not values:
        raise ConfigError(f"{where}: a tiles shape needs at least one tile")
    spectra = [v for v in values if isinstance(v, Spectrum)]
    if spectra and len(spectra) != len(values):
        raise ConfigError(f"{where}: tile reflectances must be all spectra or all RGB, not a mix")
    if not spectral or not spectra:
        rgb = np.array([spectrum_to_rgb_reflectance(v) if isinstance(v, Spectrum) else v for v in values], float)
        if rgb.shape != (len(values), 3) or not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
            raise ConfigError(f"{where}: tile reflectances must be RGB triples >= 0 or spectra")
        return {"type": TABLE_TYPE, "table": rgb, "wavelengths": None, "upsample": bool(spectral)}
    wl = spectra[0].wavelengths_nm
    if any(s.wavelengths_nm != wl for s in spectra):
        raise ConfigError(f"{where}: the tiles' spectra must share one wavelength grid")
    step = np.diff(wl)
    if not np.allclose(step, step[0], rtol=1e-9, atol=0.0):
        raise ConfigError(f"{where}: the tiles' spectra must be sampled on a regular wavelength grid")
    table = np.array([s.values for s in spectra], float)
    return {"type": TABLE_TYPE, "table": table, "wavelengths": np.asarray(wl, float), "upsample": False}


def tiles_description(matrices: Sequence[np.ndarray], to_world: np.ndarray, bsdf: dict[str, Any]) -> dict[str, Any]:
    """The scene-description entry of a tiles shape (plain arrays, hashable by the render cache)."""
    vertices, faces, uv = tile_geometry(matrices, to_world)
    return {"type": TILES_TYPE, "vertices": vertices, "faces": faces, "texcoords": uv, "bsdf": bsdf}


@lru_cache(maxsize=None)
def tile_texture_class(variant: str) -> type:
    """The tile-table texture class for the active Mitsuba ``variant``."""
    import drjit as dr
    import mitsuba as mi

    class TileTableTexture(mi.Texture):
        """Reflectance of tile ``floor(u)``: a row of a table (see the module's description)."""

        def __init__(self, table: np.ndarray, wavelengths: np.ndarray | None, upsample: bool) -> None:
            super().__init__(mi.Properties())
            table = np.asarray(table, np.float64)
            self.n_tiles = table.shape[0]
            self.mean_value = float(table.mean())
            if upsample:  # RGB tiles in a spectral variant: sRGB upsampling coefficients per tile
                table = np.array([np.asarray(mi.srgb_model_fetch(mi.ScalarColor3f(*row))) for row in table])
            self.width = table.shape[1]
            self.upsample = upsample
            self.table = mi.Float(np.ascontiguousarray(table, np.float32).ravel())
            self.grid = None if wavelengths is None else (float(wavelengths[0]), float(wavelengths[1] - wavelengths[0]))

        def eval(self, si: Any, active: Any = True) -> Any:
            base = dr.clip(mi.UInt32(dr.floor(si.uv.x)), 0, self.n_tiles - 1) * self.width  # the tile's row
            if self.grid is None and not self.upsample:  # RGB variant: the tile's albedo
                return mi.Color3f(*(dr.gather(mi.Float, self.table, base + c, active) for c in range(3)))
            if self.upsample:  # spectral variant, RGB tile
                coeff = mi.Color3f(*(dr.gather(mi.Float, self.table, base + c, active) for c in range(3)))
                return mi.srgb_model_eval(coeff, si.wavelengths)
            wl0, step = self.grid
            last = self.width - 1
            out = []
            for k in range(len(si.wavelengths)):
                x = (si.wavelengths[k] - wl0) / step
                i0 = dr.clip(mi.UInt32(dr.floor(x)), 0, last - 1)
                f = x - mi.Float(i0)
                a = dr.gather(mi.Float, self.table, base + i0, active)
                b = dr.gather(mi.Float, self.table, base + i0 + 1, active)
                out.append(dr.select((x >= 0.0) & (x <= last), dr.lerp(a, b, f), 0.0))
            return mi.Spectrum(*out)

        def mean(self) -> float:
            """Mean of the table's entries (over tiles, and wavelengths or channels)."""
            return self.mean_value

        def is_spatially_varying(self) -> bool:
            return self.n_tiles > 1

        def to_string(self) -> str:
            return f"TileTableTexture[tiles={self.n_tiles}]"

    return TileTableTexture


def materialize(mi: Any, d: dict[str, Any], keep: list[Any]) -> dict[str, Any]:
    """``d`` with every tiles entry (:func:`tiles_description`) and tile table made Mitsuba
    objects (at any depth, e.g. inside a ``shapegroup``). The Python textures are appended to
    ``keep``: the caller holds them as long as the scene lives."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            if v.get("type") == TABLE_TYPE:
                tex = tile_texture_class(mi.variant())(v["table"], v["wavelengths"], v["upsample"])
                keep.append(tex)
                v = tex
            elif v.get("type") == TILES_TYPE:
                v = _mesh(mi, k, v, keep)
            else:
                v = materialize(mi, v, keep)
        out[k] = v
    return out


def _mesh(mi: Any, name: str, d: dict[str, Any], keep: list[Any]) -> Any:
    vertices, faces, uv = d["vertices"], d["faces"], d["texcoords"]
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(materialize(mi, {"bsdf": d["bsdf"]}, keep)["bsdf"])
    mesh = mi.Mesh(name, len(vertices), len(faces), props, has_vertex_normals=False, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.asarray(vertices, np.float32).ravel())
    p["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    p["vertex_texcoords"] = mi.Float(np.asarray(uv, np.float32).ravel())
    p.update()
    return mesh
