"""The ``SceneModel.build`` payload: a scene as plain data that :mod:`mbcapture.render` turns
into a Mitsuba scene. No Mitsuba import here: scene modules use these classes.

Units: metres for geometry, W m^-2 sr^-1 for area and environment radiance (per RGB channel).
Transforms are numpy (4, 4) float64 homogeneous matrices acting on column vectors.

Canonical shapes (before ``to_world``), as in Mitsuba:

``rectangle``  [-1, 1]^2 in the z = 0 plane, normal +z (an area light emits towards +z)
``disk``       unit disk in the z = 0 plane, normal +z
``cube``       [-1, 1]^3
``sphere``     unit sphere at the origin (use uniform scales only)
``cylinder``   radius 1 from z = 0 to z = 1, open ends (close them with disks)

Colours and textures: a ``reflectance`` is an RGB albedo tuple, a :class:`Spectrum` (e.g. a
ColorChecker patch's measured reflectance) or a :class:`Texture` (a PNG/JPEG/EXR bitmap on the
shape's uv); a ``radiance`` is an RGB tuple or a :class:`Spectrum` in W m^-2 sr^-1 nm^-1. Spectral
Mitsuba variants use spectra as they are (irregular spectra); RGB variants get their linear-sRGB
values (:func:`spectrum_to_rgb_reflectance`, :func:`spectrum_to_rgb_radiance`).

Meshes: ``kind="mesh"`` with ``mesh=<path>`` loads a PLY or OBJ file (``to_world`` applies on top).
Tiles: ``kind="tiles"`` with ``tiles=(matrix, ...)`` is a set of rectangles (tile i the canonical
rectangle under ``to_world @ tiles[i]``) rendered as one shape with one BSDF, its material's
reflectance a :class:`PerTile` (one RGB or Spectrum per tile): many small patches then cost one
shape in the render kernel, not one each (:mod:`mbcapture.render.tiles`).
Texture and mesh files are checked (:meth:`SceneBuild.check_files`) before Mitsuba sees them: a
missing, unreadable or corrupt file is a :class:`~mbcapture.errors.ConfigError` naming the file
and the shape.

Moving geometry: a shape with ``part=<name>`` has its ``to_world`` relative to that part's
frame, and ``SceneBuild.parts[name](t_s)`` gives the part's world-from-part matrix at scene
time ``t_s`` (s). Non-emitting shapes of a part become one Mitsuba ``shapegroup`` + ``instance``;
emitting shapes of a part (``rectangle``, ``disk``, ``sphere``, ``cylinder`` only) are moved
through their own ``to_world``. Neither recompiles the render kernel.

Guides: ``SceneBuild.guides`` are spheres (:class:`Guide`) around brightly lit patches that are not
lights, such as the top of a lamp's stand just under its bulb or the spots its bulb lights on the wall
behind it and the table under it; the path tracer sends each guide's share of every bounce towards it
(unbiased; ``render.guide_fraction`` scales the shares together), so their light stops arriving in rare
bounces that carry it all. A scene declares them where it knows such a patch, with the shares its
measurements chose.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Mapping, Union

import numpy as np

from ..errors import ConfigError

ShapeKind = Literal["rectangle", "disk", "cube", "sphere", "cylinder", "mesh", "tiles"]
RGB = tuple[float, float, float]
#: Shape kinds whose ``to_world`` Mitsuba exposes as an updatable parameter.
MOVABLE_EMITTER_KINDS: frozenset[str] = frozenset({"rectangle", "disk", "sphere", "cylinder"})


@dataclass(frozen=True, eq=False)
class Spectrum:
    """A sampled spectrum: ``values`` at ``wavelengths_nm`` (strictly increasing, >= 2 samples).

    As a reflectance: unitless, 0..1. As a radiance: W m^-2 sr^-1 nm^-1. Mitsuba's spectral
    variants interpolate it linearly and treat it as zero outside the sampled range.
    """

    wavelengths_nm: tuple[float, ...]
    values: tuple[float, ...]

    def __post_init__(self) -> None:
        wl = np.asarray(self.wavelengths_nm, float)
        v = np.asarray(self.values, float)
        if wl.ndim != 1 or wl.size < 2 or v.shape != wl.shape:
            raise ValueError(f"Spectrum: need matching 1-D wavelengths and values (>= 2), got {wl.shape} and {v.shape}")
        if not np.all(np.diff(wl) > 0) or not np.all(np.isfinite(v)) or np.any(v < 0):
            raise ValueError("Spectrum: wavelengths must increase and values be finite and >= 0")
        object.__setattr__(self, "wavelengths_nm", tuple(map(float, wl)))
        object.__setattr__(self, "values", tuple(map(float, v)))

    @classmethod
    def from_sd(cls, sd, scale: float = 1.0) -> "Spectrum":
        """From a ``colour.SpectralDistribution`` (values times ``scale``)."""
        return cls(tuple(np.asarray(sd.wavelengths, float)), tuple(np.asarray(sd.values, float) * scale))

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.wavelengths_nm), np.asarray(self.values)

    def integral(self) -> float:
        """Trapezoidal integral over wavelength (W m^-2 sr^-1 for a radiance)."""
        wl, v = self.arrays
        return float(np.trapezoid(v, wl))


@dataclass(frozen=True)
class Texture:
    """A bitmap (PNG, JPEG or OpenEXR file) mapped onto the shape's uv parameterization.

    8-bit files are sRGB-encoded albedo (decoded to linear by Mitsuba); EXR is linear. In
    spectral variants Mitsuba upsamples the texels' RGB to reflectance spectra.
    """

    path: str
    filter_type: Literal["bilinear", "nearest"] = "bilinear"


@dataclass(frozen=True, eq=False)
class PerTile:
    """One reflectance per tile of a ``kind="tiles"`` shape, in tile order: all RGB albedos or
    all spectra (sharing one regular wavelength grid)."""

    values: tuple[Union[RGB, Spectrum], ...]


@dataclass(frozen=True, eq=False)
class RadianceImage:
    """An emitter's radiance that varies over its surface: ``pixels`` (H, W, 3), linear RGB radiance in
    W m^-2 sr^-1, mapped onto the shape's uv (row 0 at the top, bilinear, clamped at the borders). RGB
    variants only. The ``image`` scene's plane emits a photograph this way."""

    pixels: np.ndarray

    def __post_init__(self) -> None:
        img = np.asarray(self.pixels, np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise ValueError(f"RadianceImage: pixels must be (H, W, 3), got {img.shape}")
        if not np.all(np.isfinite(img)) or np.any(img < 0):
            raise ValueError("RadianceImage: pixels must be finite and >= 0")
        object.__setattr__(self, "pixels", np.ascontiguousarray(img))


Reflectance = Union[RGB, Spectrum, Texture, PerTile]
Radiance = Union[RGB, Spectrum, RadianceImage]

TEXTURE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".exr"})
MESH_SUFFIXES = frozenset({".ply", ".obj"})


@dataclass(frozen=True)
class Material:
    """Lambertian reflector: ``reflectance`` an albedo per channel (0..1), a :class:`Spectrum`
    or a :class:`Texture`."""

    reflectance: Reflectance
    twosided: bool = False


@dataclass(frozen=True)
class Light:
    """Area emission of a shape's front side: ``radiance`` W m^-2 sr^-1 per RGB channel, or a
    :class:`Spectrum` in W m^-2 sr^-1 nm^-1, in emitter ``group``."""

    group: str
    radiance: Radiance


@dataclass(frozen=True)
class Shape:
    """One primitive; ``name`` must be unique and a valid identifier."""

    name: str
    kind: ShapeKind
    to_world: np.ndarray
    material: Material | None = None  # None: black (e.g. the surface of a light)
    light: Light | None = None
    part: str | None = None
    mesh: str | None = None  # kind "mesh": a .ply or .obj file
    tiles: tuple[np.ndarray, ...] = ()  # kind "tiles": each tile's (4, 4) matrix, under to_world


@dataclass(frozen=True)
class Environment:
    """Constant radiance ``radiance`` (W m^-2 sr^-1) from every direction, in ``group``."""

    group: str
    radiance: Radiance


@dataclass(frozen=True, eq=False)
class Projector:
    """A pinhole projector (Mitsuba's ``projector`` emitter) casting ``image`` into the scene, in ``group``.

    It sits at ``origin`` and looks at ``target`` (``up`` fixes its roll) like
    :class:`mbcapture.scene.projective.Camera`, with the horizontal field of view ``fov_deg`` spanning the
    image's width; its height follows the image's aspect. Measured on Mitsuba 3.9.1 (tests/
    test_projector.py): texel (row i, column j) lights the points that a camera at the same pose,
    field of view and resolution sees in pixel (i, j), texel centres at half-integers, so
    ``Camera(origin, target, up, fov_deg).project(X, width, height)`` is the image position a world
    point X receives light from. ``image`` (H, W, 3) float is the irradiance, W m^-2 per RGB channel,
    on a plane perpendicular to the optical axis 1 m from the projector; on such a plane at axial
    distance z it is ``image / z^2`` (a Lambertian surface of albedo rho reflects rho image / (pi z^2)).
    Bilinear filtering, clamped at the borders; no light outside the field of view. A delta-position
    emitter: lit by next-event estimation only, never seen by the camera. RGB variants only.
    ``part``: the projector moves with that part (its pose relative to the part's frame).
    """

    name: str
    group: str
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float
    image: np.ndarray
    part: str | None = None

    def __post_init__(self) -> None:
        img = np.asarray(self.image, np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise ValueError(f"Projector {self.name!r}: image must be (H, W, 3), got {img.shape}")
        if not np.all(np.isfinite(img)) or np.any(img < 0):
            raise ValueError(f"Projector {self.name!r}: image values must be finite and >= 0")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"Projector {self.name!r}: fov_deg must be in (0, 180), got {self.fov_deg}")
        object.__setattr__(self, "image", img)

    def to_world(self) -> np.ndarray:
        """(4, 4) world-from-projector matrix of Mitsuba's ``look_at`` (x left, y up, z forward)."""
        o, t, u = (np.asarray(v, float) for v in (self.origin, self.target, self.up))
        d = (t - o) / np.linalg.norm(t - o)
        left = np.cross(u, d)
        left /= np.linalg.norm(left)
        new_up = np.cross(d, left)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
        return m


#: The most of every diffuse bounce that a scene's guides may take together (the cosine lobe keeps the rest).
MAX_GUIDE_SHARE = 0.5


@dataclass(frozen=True)
class Guide:
    """A sphere around a brightly lit patch that is not an emitter (the top of a lamp's stand, millimetres
    under the bulb; the spot the bulb lights on the wall behind it): the path tracer sends ``share`` of every
    diffuse bounce into the cone of directions towards it, weighted by the mixture's density, so the light
    it reflects is found often and with small weights instead of by a rare bounce that carries it all
    (:func:`mbcapture.render.integrator.guided_lambertian`). ``render.guide_fraction`` may scale the shares
    of a scene's guides together. Static, in world coordinates (m). Guiding changes the noise, never the
    expected image.

    Keep the centre off every surface (a centimetre in front of the wall it guides to): from the vertices of a
    surface through the centre, half of the cone lies under their horizon, and a bounce drawn along it continues
    or ends by the last bit of its direction, which differs between CPUs (measured: a golden's sensor input
    differed between two CPU targets by 7.7e-4 relative, against 1e-6 with the centres 1 cm off)."""

    centre: tuple[float, float, float]
    radius: float
    share: float

    def __post_init__(self) -> None:
        c = np.asarray(self.centre, float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"Guide.centre: expected three finite coordinates (m), got {self.centre!r}")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Guide.radius: expected a positive radius (m), got {self.radius!r}")
        if not (math.isfinite(self.share) and 0 < self.share <= MAX_GUIDE_SHARE):
            raise ValueError(
                f"Guide.share: expected a share of the bounces above 0 and at most {MAX_GUIDE_SHARE}, "
                f"got {self.share!r}"
            )
        object.__setattr__(self, "centre", tuple(map(float, c)))
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "share", float(self.share))


@dataclass(frozen=True, eq=False)
class SceneFile:
    """A Mitsuba scene file in a scene (:mod:`mbcapture.render.xmlscene`): ``path`` (absolute), the values of
    its ``$parameters``, ``emitters``: each emitter's id (a shape's id for its area emitter) with its group,
    ``moving``: shape id -> the name of its part in :attr:`SceneBuild.parts` (its world-from-rest matrix over
    time), and ``moving_lights``: the same for lights (a spot, or a rectangle, disk, sphere or cylinder with an
    area emitter), moved through their own ``to_world``."""

    path: str
    parameters: Mapping[str, str]
    emitters: tuple[tuple[str, str], ...]
    moving: Mapping[str, str] = field(default_factory=dict)
    moving_lights: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class SceneBuild:
    """Everything :class:`mbcapture.render.Renderer` needs besides the camera.

    shapes
        All primitives.
    parts
        Moving part name -> ``f(t_s: float) -> (4, 4)`` world-from-part matrix.
    environment
        Optional constant environment light.
    projectors
        Pinhole projectors (:class:`Projector`), each in its own emitter group or sharing one.
    guides
        Spheres around bright patches that are not emitters (:class:`Guide`), towards which a share of
        the bounces is sampled; their shares add up to at most :data:`MAX_GUIDE_SHARE`.
    file
        A Mitsuba scene file whose objects join the shapes (:class:`SceneFile`), or None.
    """

    shapes: tuple[Shape, ...]
    parts: Mapping[str, Callable[[float], np.ndarray]] = field(default_factory=dict)
    environment: Environment | None = None
    projectors: tuple[Projector, ...] = ()
    guides: tuple[Guide, ...] = ()
    file: SceneFile | None = None

    def __post_init__(self) -> None:
        total = sum(g.share for g in self.guides)
        if total > MAX_GUIDE_SHARE:
            raise ValueError(
                f"SceneBuild.guides: their shares add up to {total:g}, above {MAX_GUIDE_SHARE}: the "
                "cosine lobe needs the rest of every bounce"
            )

    def emitter_groups(self) -> tuple[str, ...]:
        """Groups that own at least one emitter, in first-appearance order."""
        seen: dict[str, None] = {}
        for s in self.shapes:
            if s.light is not None:
                seen.setdefault(s.light.group)
        if self.environment is not None:
            seen.setdefault(self.environment.group)
        for p in self.projectors:
            seen.setdefault(p.group)
        for _, group in self.file.emitters if self.file is not None else ():
            seen.setdefault(group)
        return tuple(seen)

    def check_files(self, scene_name: str = "scene") -> None:
        """Every texture and mesh file exists and decodes and every tiles shape is well formed;
        else ConfigError naming the file and the shape."""
        for s in self.shapes:
            where = f"scene {scene_name!r}, shape {s.name!r}"
            if s.kind == "mesh":
                if not s.mesh:
                    raise ConfigError(f"{where}: kind 'mesh' needs a mesh file (.ply or .obj)")
                try:
                    check_mesh_file(s.mesh)
                except ValueError as exc:
                    raise ConfigError(f"{where}: mesh {s.mesh}: {exc}") from None
            elif s.mesh is not None:
                raise ConfigError(f"{where}: a mesh file is only read by kind 'mesh', not {s.kind!r}")
            per_tile = s.material is not None and isinstance(s.material.reflectance, PerTile)
            if s.kind == "tiles":
                if not s.tiles:
                    raise ConfigError(f"{where}: kind 'tiles' needs at least one tile matrix")
                if s.light is not None:
                    raise ConfigError(f"{where}: a tiles shape cannot emit light")
                if per_tile and len(s.material.reflectance.values) != len(s.tiles):
                    raise ConfigError(
                        f"{where}: {len(s.tiles)} tiles but {len(s.material.reflectance.values)} reflectances"
                    )
            elif s.tiles or per_tile:
                raise ConfigError(f"{where}: tiles and PerTile reflectances belong to kind 'tiles', not {s.kind!r}")
            if s.material is not None and isinstance(s.material.reflectance, Texture):
                tex = s.material.reflectance
                try:
                    check_texture_file(tex.path)
                except ValueError as exc:
                    raise ConfigError(f"{where}: texture {tex.path}: {exc}") from None
            if s.light is not None and isinstance(s.light.radiance, Texture):
                raise ConfigError(f"{where}: a light's radiance must be RGB or a Spectrum, not a texture")


# -- files -------------------------------------------------------------------------------------
def _readable(path: str | Path, suffixes: frozenset[str], what: str) -> Path:
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"unsupported {what} file type {p.suffix!r}; expected one of {sorted(suffixes)}")
    if not p.exists():
        raise ValueError("file not found")
    if not p.is_file():
        raise ValueError("not a regular file")
    try:
        with p.open("rb") as f:
            f.read(1)
    except OSError as exc:
        raise ValueError(f"cannot read file ({exc.strerror})") from None
    return p


def read_texture(path: str | Path) -> np.ndarray:
    """Decode a texture file to float32 (H, W, C): 8/16-bit files scaled to 0..1 (still
    sRGB-encoded, channels R, G, B[, A]); EXR as stored. ValueError if missing or corrupt."""
    p = _readable(path, TEXTURE_SUFFIXES, "texture")
    if p.suffix.lower() == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(p), separate_channels=True) as f:
                chans = f.channels()
                names = [c for c in ("R", "G", "B", "A", "Y") if c in chans] or sorted(chans)
                arr = np.stack([np.asarray(chans[c].pixels, np.float32) for c in names], axis=-1)
        except Exception as exc:  # the OpenEXR binding raises plain RuntimeError/OSError
            raise ValueError(f"corrupt or unreadable OpenEXR file ({exc})") from None
    else:
        import cv2

        data = np.fromfile(str(p), np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            raise ValueError("corrupt or unreadable image (cannot be decoded)")
        if _truncated(p, data):
            raise ValueError("corrupt image: the file is truncated")
        peak = 65535.0 if img.dtype == np.uint16 else 255.0
        arr = img.astype(np.float32) / peak
        if arr.ndim == 3 and arr.shape[2] >= 3:  # OpenCV's BGR(A) -> RGB(A)
            arr = arr[..., [2, 1, 0, *range(3, arr.shape[2])]]
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.size == 0 or arr.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"unsupported image layout {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("the image holds NaN or infinite values")
    return arr


def _truncated(p: Path, data: np.ndarray) -> bool:
    """A PNG must end in its IEND chunk, a JPEG in the EOI marker (decoders may pad silently)."""
    raw = data.tobytes()
    if p.suffix.lower() == ".png":
        return not raw.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82")
    return not raw.rstrip(b"\x00").endswith(b"\xff\xd9")


def check_texture_file(path: str | Path) -> None:
    """ValueError (reason) unless ``path`` is a readable, decodable texture."""
    read_texture(path)


_PLY_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def check_mesh_file(path: str | Path) -> None:
    """ValueError (reason) unless ``path`` is a PLY or OBJ file with vertices and faces whose
    declared sizes fit the file."""
    p = _readable(path, MESH_SUFFIXES, "mesh")
    raw = p.read_bytes()
    if p.suffix.lower() == ".ply":
        _check_ply(raw)
    else:
        _check_obj(raw)


def _check_ply(raw: bytes) -> None:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError("corrupt PLY: no 'ply' magic or no end_header")
    try:
        header = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise ValueError("corrupt PLY: header is not ASCII") from None
    body = raw[raw.index(b"\n", end) + 1 :] if b"\n" in raw[end:] else b""
    fmt, elements = None, []  # elements: [name, count, [(kind, size | (count_size, item_size))]]
    for line in header[1:]:
        w = line.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        try:
            if w[0] == "format":
                fmt = w[1]
            elif w[0] == "element":
                elements.append([w[1], int(w[2]), []])
            elif w[0] == "property" and w[1] == "list":
                elements[-1][2].append((_PLY_SIZES[w[2]], _PLY_SIZES[w[3]]))
            elif w[0] == "property":
                elements[-1][2].append(_PLY_SIZES[w[1]])
        except (IndexError, KeyError, ValueError):
            raise ValueError(f"corrupt PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"corrupt PLY: unknown format {fmt!r}")
    counts = {name: n for name, n, _ in elements}
    if counts.get("vertex", 0) < 3 or counts.get("face", 0) < 1:
        raise ValueError("PLY without vertices or faces")
    if fmt == "ascii":
        lines = [ln for ln in body.splitlines() if ln.strip()]
        need = sum(n for _, n, _ in elements)
        if len(lines) < need:
            raise ValueError(f"truncated PLY: {len(lines)} data lines, the header declares {need}")
        return
    order = "<" if fmt == "binary_little_endian" else ">"
    pos = 0
    for name, n, props in elements:
        if all(isinstance(pr, int) for pr in props):
            pos += n * sum(props)
        else:  # walk the list properties (faces)
            for _ in range(n):
                for pr in props:
                    if isinstance(pr, int):
                        pos += pr
                        continue
                    cs, item = pr
                    if pos + cs > len(body):
                        raise ValueError(f"truncated PLY: element {name!r} runs past the end of the file")
                    code = {1: "B", 2: "H", 4: "I"}[cs]
                    pos += cs + item * struct.unpack_from(order + code, body, pos)[0]
        if pos > len(body):
            raise ValueError(f"truncated PLY: element {name!r} runs past the end of the file")


def _check_obj(raw: bytes) -> None:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("corrupt OBJ: not a text file") from None
    n_v, n_f = 0, 0
    for i, line in enumerate(text.splitlines(), 1):
        w = line.split()
        if not w:
            continue
        try:
            if w[0] == "v":
                if len(w) < 4:
                    raise ValueError
                [float(x) for x in w[1:4]]
                n_v += 1
            elif w[0] == "f":
                idx = [int(x.split("/")[0]) for x in w[1:]]
                if len(idx) < 3 or any(j == 0 or abs(j) > n_v for j in idx):
                    raise ValueError
                n_f += 1
        except ValueError:
            raise ValueError(f"corrupt OBJ: line {i}: {line.strip()[:60]!r}") from None
    if n_v < 3 or n_f < 1:
        raise ValueError("OBJ without vertices or faces")


# -- spectra -> linear sRGB (RGB variants) -------------------------------------------------------
def spectrum_to_rgb_reflectance(spec: Spectrum) -> RGB:
    """Linear-sRGB albedo of a reflectance spectrum under CIE D65 (the sRGB white): a perfect
    white reflector gives (1, 1, 1). Clipped to [0, 1]."""
    import colour

    sd = colour.SpectralDistribution(dict(zip(*spec.arrays)))
    xyz = colour.sd_to_XYZ(sd, illuminant=colour.SDS_ILLUMINANTS["D65"]) / 100.0
    rgb = colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=False)
    return tuple(float(v) for v in np.clip(rgb, 0.0, 1.0))


def spectrum_to_rgb_radiance(spec: Spectrum) -> RGB:
    """Linear-sRGB radiance of a spectral radiance L (W m^-2 sr^-1 nm^-1), in W m^-2 sr^-1:
    the sRGB primaries of (X, Y, Z) = integral (xbar, ybar, zbar)(lambda) L(lambda) d lambda (CIE 1931
    2-degree observer, peak of ybar = 1). This is the inverse of Mitsuba's RGB upsampling of emission
    (an RGB white (1, 1, 1) becomes D65 scaled to integral ybar L = 1), so a spectrum and its RGB have
    the same XYZ. Negative components (colours outside the sRGB gamut, e.g. narrow-band LEDs) are
    clipped to 0."""
    import colour

    wl, v = spec.arrays
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    grid = np.arange(max(360.0, np.floor(wl[0])), min(830.0, np.ceil(wl[-1])) + 1.0, 1.0)
    lv = np.interp(grid, wl, v, left=0.0, right=0.0)
    xyz = np.trapezoid(cmfs[grid] * lv[:, None], grid, axis=0)
    rgb = colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=False)
    return tuple(float(x) for x in np.clip(rgb, 0.0, None))


# -- small numpy transform helpers (column-vector convention, like Mitsuba) ---------------------
def translate(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def scale(x: float, y: float | None = None, z: float | None = None) -> np.ndarray:
    return np.diag([x, x if y is None else y, x if z is None else z, 1.0])


def rotate(axis: tuple[float, float, float], angle_rad: float) -> np.ndarray:
    """Right-handed rotation by ``angle_rad`` about the unit direction ``axis``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + s * k + (1 - c) * np.outer(a, a)
    return m


def frame_towards(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Matrix placing a canonical rectangle/disk at ``position`` with its normal (+z) aimed at
    ``target`` (the x axis is horizontal, perpendicular to ``up``)."""
    p = np.asarray(position, float)
    z = np.asarray(target, float) - p
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, p
    return m


def box(center, half_size) -> np.ndarray:
    """``to_world`` of an axis-aligned ``cube`` with the given centre and half sizes (m)."""
    return translate(*center) @ scale(*half_size)
