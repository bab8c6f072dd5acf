"""A Mitsuba 3 scene file (XML) as the content of a capture: ``scene.name: mitsuba`` with ``scene.file``.

The file is read by Mitsuba's own parser (``mitsuba.parser``: ``<include>``, ``<default>`` and
``$parameters``, references, every plugin Mitsuba has), so whatever Mitsuba loads, a capture loads: any
shape, BSDF (conductor, dielectric, plastic, principled, textures, normal maps), emitter (area, point,
spot, directional, constant, envmap). What a capture replaces: the file's integrator (the project's
per-group path tracer, :mod:`.integrator`), its film and sampler (``render.*``), and its sensor, which
becomes the capture's camera (:func:`file_camera`; ``camera.*`` moves it).

The parsed scene is turned into a Mitsuba scene *dictionary* (:func:`file_entries`) rather than loaded
as objects, so that it joins the project's own dictionaries: the capture's sensors are added, moving
shapes become instances whose ``to_world`` changes with time, and the render cache hashes the
description, every ``filename`` by its content (a changed texture or mesh renders again; an included
XML file is part of the description).

Hand-written, because no library converts a parsed Mitsuba scene into a dictionary: Mitsuba's parser
writes XML back, and its ``load_dict`` reads dictionaries, but nothing goes from the first to the second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..scene.projective import Camera
from .llvm import ensure_llvm

#: Object types of the file that a capture replaces with its own.
REPLACED = frozenset({"Integrator", "Sensor", "Film", "Sampler"})


def _mitsuba() -> Any:
    """Mitsuba, imported once the libLLVM is chosen; a variant set (the current one, or scalar_rgb)."""
    ensure_llvm()
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi


def parse(path: str | Path, parameters: dict[str, Any] | None = None) -> tuple[Any, Any]:
    """(the ``mitsuba.parser`` state of the file, references resolved, meshes *not* merged so every id stays; its
    config). ``parameters``: values of the file's ``$name`` parameters (as ``<default>`` would give them).
    A ConfigError names the file and Mitsuba's complaint."""
    mi = _mitsuba()
    import mitsuba.parser as mp

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"scene.file: {path}: no such file")
    config = mp.ParserConfig(mi.variant())
    try:
        state = mp.parse_file(config, str(path), **{k: str(v) for k, v in (parameters or {}).items()})
        mp.transform_upgrade(config, state)
        mp.transform_resolve(config, state)
    except Exception as exc:  # Mitsuba's parser raises RuntimeError and others with a message naming the line
        msg = " ".join(str(exc).split())
        raise ConfigError(f"scene.file: {path}: Mitsuba cannot parse it: {msg[:400]}") from None
    return state, config


def _type(node: Any) -> str:
    return str(node.type).rsplit(".", 1)[-1]


def _children(state: Any, node: Any) -> list[tuple[str, int]]:
    """(property name, node index) of every object below ``node``."""
    out = []
    for key in node.props.keys():
        value = node.props[key]
        if type(value).__name__ == "ResolvedReference":
            out.append((key, value.index()))
    return out


def _base_dir(state: Any, node: Any) -> Path:
    return Path(str(state.files[node.file_index])).parent


def _value(mi: Any, state: Any, node: Any, key: str, value: Any) -> Any:
    """One property as load_dict takes it."""
    kind = type(value).__name__
    if kind in ("AffineTransform4d", "AffineTransform4f", "ScalarAffineTransform4d", "ScalarAffineTransform4f"):
        return mi.ScalarTransform4f(np.asarray(value.matrix, dtype=np.float64))
    if kind in ("Color3d", "Color3f", "ScalarColor3d", "ScalarColor3f"):
        return {"type": "rgb", "value": [float(x) for x in value]}
    if kind == "Spectrum":
        if value.is_uniform:
            return {"type": "uniform", "value": float(np.asarray(value.values)[0])}
        return {
            "type": "irregular",
            "wavelengths": ", ".join(repr(float(x)) for x in np.asarray(value.wavelengths)),
            "values": ", ".join(repr(float(x)) for x in np.asarray(value.values)),
        }
    if kind.startswith("Array3") or kind.startswith("ScalarPoint3") or kind.startswith("ScalarVector3"):
        return [float(x) for x in value]
    if isinstance(value, str) and key == "filename":  # relative to the XML file that names it
        p = Path(value)
        return str(p if p.is_absolute() else (_base_dir(state, node) / p).resolve())
    if isinstance(value, (bool, int, float, str)):
        return value
    raise ConfigError(
        f"scene.file: {state.files[node.file_index]}: property {key!r} of a {node.props.plugin_name()!r} "
        f"({kind}) is not one a capture can pass on"
    )


def _node_dict(mi: Any, state: Any, index: int, top: set[int]) -> dict[str, Any]:
    """The node at ``index`` as a load_dict entry; objects defined at the top level (``top``) are referenced."""
    node = state.nodes[index]
    out: dict[str, Any] = {"type": node.props.plugin_name()}
    if node.props.id():
        out["id"] = node.props.id()
    for key in node.props.keys():
        value = node.props[key]
        if type(value).__name__ == "ResolvedReference":
            child = value.index()
            name = key if not key.startswith("_arg_") else (state.nodes[child].props.id() or f"{key.strip('_')}")
            if child in top and state.nodes[child].props.id():
                out[name] = {"type": "ref", "id": state.nodes[child].props.id()}
            else:
                out[name] = _node_dict(mi, state, child, top)
        else:
            out[key] = _value(mi, state, node, key, value)
    return out


def file_entries(mi: Any, state: Any) -> dict[str, dict[str, Any]]:
    """The file's top-level objects (shapes, emitters, BSDFs, textures, media) as load_dict entries by their id
    (``<type>_<n>`` for one without), in the file's order, without what a capture replaces."""
    root = state.nodes[0]
    top = {i for _, i in _children(state, root)}
    out: dict[str, dict[str, Any]] = {}
    for n, (_, index) in enumerate(_children(state, root)):
        node = state.nodes[index]
        if _type(node) in REPLACED:
            continue
        entry = _node_dict(mi, state, index, top)
        key = entry.pop("id", None) or f"{node.props.plugin_name()}_{n}"
        out[key] = entry
    return out


def _horizontal_fov(fov: float, axis: str, width: int, height: int) -> float:
    """Mitsuba's ``fov`` along ``fov_axis`` as the horizontal field of view of a ``width`` x ``height`` film."""
    aspect = width / height
    t = math.tan(math.radians(fov) / 2)
    if axis == "x":
        tx = t
    elif axis == "y":
        tx = t * aspect
    elif axis == "diagonal":
        tx = t * aspect / math.hypot(aspect, 1.0)
    elif axis == "smaller":
        tx = t * aspect if aspect > 1 else t
    elif axis == "larger":
        tx = t if aspect > 1 else t * aspect
    else:
        raise ConfigError(f"scene.file: sensor fov_axis {axis!r} is not one Mitsuba knows")
    return math.degrees(2 * math.atan(tx))


def file_camera(state: Any) -> Camera:
    """The file's first sensor (perspective or thinlens) as the capture's :class:`Camera` (its pose and horizontal
    field of view); a ConfigError without one."""
    for _, index in _children(state, state.nodes[0]):
        node = state.nodes[index]
        if _type(node) != "Sensor":
            continue
        props = node.props
        if props.plugin_name() not in ("perspective", "thinlens"):
            raise ConfigError(
                f"scene.file: {state.files[node.file_index]}: sensor {props.plugin_name()!r}: a capture needs a "
                "perspective or thinlens sensor"
            )
        m = np.asarray(props["to_world"].matrix, dtype=np.float64) if "to_world" in props else np.eye(4)
        width, height = 768, 576
        for _, child in _children(state, node):
            film = state.nodes[child].props
            if _type(state.nodes[child]) == "Film":
                width = int(film["width"]) if "width" in film else width
                height = int(film["height"]) if "height" in film else height
        fov = float(props["fov"]) if "fov" in props else 39.3077
        axis = str(props["fov_axis"]) if "fov_axis" in props else "x"
        origin = m[:3, 3]
        forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
        up = m[:3, 1] / np.linalg.norm(m[:3, 1])
        return Camera(
            tuple(map(float, origin)),
            tuple(map(float, origin + forward)),
            tuple(map(float, up)),
            _horizontal_fov(fov, axis, width, height),
        )
    raise ConfigError("scene.file: the file has no sensor; a capture needs one (its camera)")


@dataclass(frozen=True)
class FileObject:
    """An object of the file a config can name: its id, Mitsuba type (Shape, Emitter, ...) and plugin, and for a
    shape whether it carries an area emitter."""

    id: str
    kind: str
    plugin: str
    emits: bool = False


def file_objects(state: Any) -> list[FileObject]:
    """The file's top-level objects under the keys :func:`file_entries` gives them (their id, or ``<type>_<n>``
    for one without): what ``scene.groups`` and ``scene.motion`` name."""
    out = []
    for n, (_, index) in enumerate(_children(state, state.nodes[0])):
        node = state.nodes[index]
        if _type(node) in REPLACED:
            continue
        emits = any(_type(state.nodes[c]) == "Emitter" for _, c in _children(state, node))
        key = node.props.id() or f"{node.props.plugin_name()}_{n}"
        out.append(FileObject(key, _type(node), node.props.plugin_name(), emits))
    return out


def rest_matrix(entry: dict[str, Any]) -> np.ndarray:
    """(4, 4) to_world of a file's entry as the file places it: its ``to_world``, a sphere's centre and radius, or a
    point light's position."""
    m = np.asarray(entry["to_world"].matrix, dtype=np.float64) if "to_world" in entry else np.eye(4)
    if "center" in entry or "position" in entry:
        m = m.copy()
        m[:3, 3] += np.asarray(entry.get("center", entry.get("position")), dtype=np.float64)
    if "radius" in entry:
        m[:3, :3] *= float(entry["radius"])
    return m


def entries(state: Any) -> dict[str, dict[str, Any]]:
    """:func:`file_entries` in the current Mitsuba variant (scalar_rgb when none is set): what
    :func:`emitter_pose` and :func:`bounding_box` read, converted once for all of them."""
    return file_entries(_mitsuba(), state)


def emitter_pose(entries: dict[str, dict[str, Any]], key: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(position, unit direction it faces or None) of emitter ``key`` of :func:`entries` as the file places it: a
    point or spot light's position (a spot's axis), an emitting shape's bounding-box centre (a rectangle's or
    disk's normal)."""
    entry = entries[key]
    m = rest_matrix(entry)
    facing = entry["type"] in ("spot", "rectangle", "disk")
    axis = m[:3, 2] / np.linalg.norm(m[:3, 2]) if facing else None
    if entry["type"] in ("point", "spot"):
        return m[:3, 3], axis
    return bounding_box(entries, key).mean(axis=0), axis


def referenced_files(state: Any) -> list[Path]:
    """Every file the scene reads: its XML files (with ``<include>``s) and each ``filename`` (meshes, textures)."""
    files = [Path(str(f)).resolve() for f in state.files]
    for node in state.nodes:
        if "filename" in node.props:
            files.append(Path(_value(None, state, node, "filename", node.props["filename"])))
    return list(dict.fromkeys(files))


def bounding_box(entries: dict[str, dict[str, Any]], shape_id: str) -> np.ndarray:
    """(8, 3) corners of shape ``shape_id``'s (of :func:`entries`) world bounding box as the file places it (the
    shape loaded alone, its references to other objects, such as a shared BSDF, left out: they do not change its
    box)."""
    mi = _mitsuba()
    entry = {k: v for k, v in entries[shape_id].items() if not (isinstance(v, dict) and v.get("type") == "ref")}
    try:
        shape = mi.load_dict(entry)
    except Exception as exc:  # Mitsuba's loader: RuntimeError and others, with its message
        msg = " ".join(str(exc).split())
        raise ConfigError(f"scene.file: shape {shape_id!r}: Mitsuba cannot load it: {msg[:300]}") from None
    box = shape.bbox()
    lo, hi = np.asarray(box.min, dtype=np.float64), np.asarray(box.max, dtype=np.float64)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
