"""Sweep files: a base config and axes over any of its keys, validated like configs.

A sweep file (YAML)::

    base: metronome_hdr            # a config path (relative to this file) or a shipped config's name
    set:                           # overrides of the base, for every point
      render.spp: 4
    axes:
      grid:                        # every combination (the first key varies slowest)
        capture.periods: [1, 4, 16]
        capture.protocol: [photon_efficient_hdr, interleaved_hdr]
      zip:                         # lists of equal length, varied together (one axis each mapping)
        - {sensor.read_noise_e: [1, 3, 10], sensor.adc_bits: [12, 12, 14]}
      random:                      # seeded samples, combined with every grid/zip point
        samples: 8
        seed: 0
        keys:
          sensor.full_well_e: {low: 2000, high: 40000, log: true}
    keep: report                   # per-point outputs: none | report | images | all

The points are the Cartesian product of the grid's axes, the zipped groups and the random
samples. Every point's config is the base, then ``set``, then the command line's ``--set``, then the
point's axis values, then ``$MBCAPTURE_SET`` (as for ``mbcapture run``), validated before anything
runs: an unknown or invalid key is one line naming the sweep file, the axis and the nearest valid
key. ``--set`` and ``set`` may not name an axis key (the axis would silently win).

Random samples come from scipy's Latin hypercube (``method: latin_hypercube``, each key's range cut
into ``samples`` equal strata, one sample in each) or independent uniform draws (``uniform``),
seeded; ``log: true`` samples the logarithm uniformly, ``integer: true`` rounds down to whole
numbers, ``choices`` picks among values.
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import (
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from ..strict import StrictModel
from ..config import (
    SHIPPED_CONFIG_DIR,
    CaptureConfig,
    format_validation,
    load_config,
    parse_override,
    resolve_config_path,
)
from ..errors import ConfigError, ConfigNotice
from ..render.cache import digest

#: The shipped sweeps (``mbcapture sweep interleaving`` finds configs/sweeps/interleaving.yaml).
SHIPPED_SWEEP_DIR = SHIPPED_CONFIG_DIR / "sweeps"
#: A sweep with more points than this is refused (a typo in a grid multiplies quickly).
MAX_POINTS = 100_000

Keep = Literal["none", "report", "images", "all"]


class RandomKey(StrictModel):
    """How one key is sampled: a range (``low``, ``high``; ``log``, ``integer``) or ``choices``."""

    low: float | None = Field(None, description="Smallest value of the range (with high).")
    high: float | None = Field(None, description="Largest value of the range (with low); included for integer keys.")
    log: bool = Field(
        False,
        description="Sample the logarithm of the value uniformly (low > 0): for scales such as full wells or light levels.",
    )
    integer: bool = Field(False, description="Round samples down to whole numbers (high included).")
    choices: list[Any] | None = Field(
        None, min_length=1, description="Pick among these values (each equally likely) instead of a range."
    )

    @model_validator(mode="after")
    def _range_or_choices(self) -> "RandomKey":
        if self.choices is not None:
            if self.low is not None or self.high is not None or self.log or self.integer:
                raise ValueError("give either choices or a range (low, high, log, integer), not both")
            return self
        if self.low is None or self.high is None:
            raise ValueError("expected low and high (a range) or choices")
        if not self.high >= self.low:
            raise ValueError(f"high ({self.high}) must be >= low ({self.low})")
        if self.log and not self.low > 0:
            raise ValueError(f"log: true needs low > 0 (got {self.low})")
        return self

    def values(self, u: np.ndarray) -> list[Any]:
        """The values at uniform variates ``u`` in [0, 1)."""
        if self.choices is not None:
            return [self.choices[min(int(x * len(self.choices)), len(self.choices) - 1)] for x in u]
        lo, hi = float(self.low), float(self.high)
        if self.integer:
            lo_i, hi_i = int(np.ceil(lo)), int(np.floor(hi))
            if self.log:
                v = np.exp(np.log(lo_i) + u * (np.log(hi_i + 1) - np.log(lo_i)))
            else:
                v = lo_i + u * (hi_i + 1 - lo_i)
            return [int(min(max(np.floor(x), lo_i), hi_i)) for x in v]
        v = np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))) if self.log else lo + u * (hi - lo)
        return [float(x) for x in v]


class RandomAxes(StrictModel):
    """Seeded random samples of some keys (one axis per key; the samples are combined with every grid point)."""

    samples: int = Field(ge=1, le=MAX_POINTS, description="How many samples to draw.")
    seed: int = Field(0, ge=0, description="Seed of the draws: the same seed gives the same samples.")
    method: Literal["latin_hypercube", "uniform"] = Field(
        "latin_hypercube",
        description="'latin_hypercube' (scipy.stats.qmc: each key's range cut into `samples` equal strata, one "
        "sample in each, so few samples still cover every range) or 'uniform' (independent draws).",
    )
    keys: dict[str, RandomKey] = Field(min_length=1, description="Dotted config key -> how it is sampled.")

    def draw(self) -> list[dict[str, Any]]:
        d = len(self.keys)
        if self.method == "latin_hypercube":
            from scipy.stats import qmc

            u = qmc.LatinHypercube(d=d, seed=np.random.default_rng(self.seed)).random(self.samples)
        else:
            u = np.random.default_rng(self.seed).random((self.samples, d))
        columns = {key: spec.values(u[:, i]) for i, (key, spec) in enumerate(self.keys.items())}
        return [{key: columns[key][n] for key in self.keys} for n in range(self.samples)]


class Axes(StrictModel):
    """What varies: a grid, zipped lists and random samples, combined as a product."""

    grid: dict[str, list[Any]] = Field(
        default_factory=dict,
        description="Dotted config key -> its values; the points are every combination (the first key varies slowest).",
    )
    zip: list[dict[str, list[Any]]] = Field(
        default_factory=list,
        description="Groups of keys varied together: in each mapping every list has the same length, and the i-th values go together.",
    )
    random: RandomAxes | None = Field(None, description="Seeded random samples of some keys.")

    @field_validator("grid")
    @classmethod
    def _non_empty(cls, grid: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in grid.items():
            if not values:
                raise ValueError(f"{key}: expected at least one value")
        return grid

    @field_validator("zip")
    @classmethod
    def _equal_lengths(cls, groups: list[dict[str, list[Any]]]) -> list[dict[str, list[Any]]]:
        for group in groups:
            lengths = {key: len(v) for key, v in group.items()}
            if not lengths:
                raise ValueError("a zip group needs at least one key")
            if len(set(lengths.values())) != 1 or 0 in lengths.values():
                raise ValueError(f"the lists of a zip group must have one, non-zero length; got {lengths}")
        return groups

    def keys(self) -> list[str]:
        out = list(self.grid)
        for group in self.zip:
            out += list(group)
        if self.random is not None:
            out += list(self.random.keys)
        return out

    def points(self) -> list[dict[str, Any]]:
        """Every point's axis values, in order."""
        factors: list[list[dict[str, Any]]] = [[{key: v} for v in values] for key, values in self.grid.items()]
        for group in self.zip:
            n = len(next(iter(group.values())))
            factors.append([{key: values[i] for key, values in group.items()} for i in range(n)])
        if self.random is not None:
            factors.append(self.random.draw())
        out = []
        for combo in itertools.product(*factors):
            point: dict[str, Any] = {}
            for part in combo:
                point.update(part)
            out.append(point)
        return out

    def size(self) -> int:
        n = 1
        for values in self.grid.values():
            n *= len(values)
        for group in self.zip:
            n *= len(next(iter(group.values())))
        if self.random is not None:
            n *= self.random.samples
        return n


class SweepSpec(StrictModel):
    """A sweep file: many captures of one base config, varying a few keys."""

    base: str = Field(
        description="The base config: a path (relative to the sweep file) or a shipped config's name (metronome_hdr)."
    )
    description: str = Field("", description="What the sweep asks, shown on its index.html.")
    set: dict[str, Any] = Field(
        default_factory=dict,
        description="Overrides of the base config for every point: dotted key -> value (as --set, but YAML values).",
    )
    axes: Axes = Field(description="The keys that vary and their values: grid, zip and random (at least one key).")
    keep: Keep = Field(
        "report",
        description="Per-point outputs in points/<point>/: 'none' (only the sweep's table), 'report' (config.yaml and "
        "report.json), 'images' (also the application's images, EXR and PNG, the read previews and report.html), "
        "'all' (everything `mbcapture run` writes: also the bucket and read EXRs).",
    )

    @model_validator(mode="after")
    def _axes_distinct(self) -> "SweepSpec":
        keys = self.axes.keys()
        if not keys:
            raise ValueError("axes: no key varies; give axes.grid, axes.zip or axes.random")
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            raise ValueError(f"axes: {', '.join(twice)} appear(s) in more than one axis")
        fixed = sorted(set(keys) & set(self.set))
        if fixed:
            raise ValueError(f"set: {', '.join(fixed)} is also an axis (the axis values would replace it)")
        return self


@dataclass(frozen=True)
class Point:
    """One capture of a sweep: its index, axis values, validated config and identity.

    ``id``: SHA-256 of the resolved config and the outputs kept (the name under which a finished
    point is found again by ``--resume``); ``label``: ``p0007`` (its index), used in folder names."""

    index: int
    values: dict[str, Any]
    config: CaptureConfig
    id: str

    @property
    def label(self) -> str:
        return f"p{self.index:04d}"


@dataclass(frozen=True)
class Sweep:
    """A loaded sweep: its file, spec, base config path, the overrides every point got, and its points."""

    path: Path
    spec: SweepSpec
    base: Path
    overrides: tuple[str, ...]
    points: tuple[Point, ...]

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def axes(self) -> list[str]:
        return self.spec.axes.keys()


def resolve_shipped(path: str | Path, folder: Path, what: str) -> Path:
    """``path`` if it exists, else the YAML file of that name in ``folder`` (a shipped sweep or design spec);
    a ConfigError naming the shipped ones otherwise."""
    p = Path(path)
    if p.exists():
        return p
    if len(p.parts) == 1:
        shipped = folder / (p.name if p.suffix in (".yaml", ".yml") else f"{p.name}.yaml")
        if shipped.is_file():
            return shipped
        names = sorted(q.stem for q in folder.glob("*.yaml"))
        raise ConfigError(f"{p}: {what} not found, and not a shipped one ({', '.join(names)})")
    raise ConfigError(f"{p}: {what} not found")


def resolve_sweep_path(path: str | Path) -> Path:
    """``path`` if it exists, else the shipped sweep of that name (``interleaving``)."""
    return resolve_shipped(path, SHIPPED_SWEEP_DIR, "sweep file")


def yaml_value(value: Any) -> str:
    """A value as the YAML text of a ``--set`` (round-trips through ``yaml.safe_load``)."""
    if isinstance(value, (np.generic,)):
        value = value.item()
    text = yaml.safe_dump(value, default_flow_style=True, width=10**9).strip()
    return text[: -len("...")].strip() if text.endswith("...") else text


def _read_spec(path: Path) -> SweepSpec:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read sweep file ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{path}:{where}: malformed YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with base and axes, got {type(data).__name__}")
    try:
        return SweepSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation(exc, origin=lambda p: str(path), model=SweepSpec)) from None


def _base_path(spec: SweepSpec, path: Path) -> Path:
    local = path.parent / spec.base
    if local.is_file():
        return local
    try:
        return resolve_config_path(spec.base)
    except ConfigError as exc:
        raise ConfigError(f"{path}: base: {exc}") from None


def _axis_origin(spec: SweepSpec, key: str) -> str:
    if key in spec.axes.grid:
        return "axes.grid"
    if spec.axes.random is not None and key in spec.axes.random.keys:
        return "axes.random"
    return "axes.zip"


def load_sweep(
    path: str | Path, overrides: list[str] | tuple[str, ...] = (), *, axes: dict[str, list[Any]] | None = None
) -> Sweep:
    """Load and validate a sweep file and every point's config (ConfigError on the first bad one).

    ``overrides``: ``--set KEY=VALUE`` applied to the base for every point (an axis key is refused).
    ``axes``: replace the values of some grid axes (e.g. fewer for a quick look; each must be a grid
    axis of the file)."""

    path = resolve_sweep_path(path)
    spec = _read_spec(path)
    if axes:
        unknown = sorted(set(axes) - set(spec.axes.grid))
        if unknown:
            raise ConfigError(
                f"{path}: {', '.join(unknown)}: not a grid axis of this sweep ({', '.join(spec.axes.grid)})"
            )
        spec = spec.model_copy(update={"axes": spec.axes.model_copy(update={"grid": {**spec.axes.grid, **axes}})})
    n = spec.axes.size()
    if n > MAX_POINTS:
        raise ConfigError(f"{path}: axes: {n} points, more than the {MAX_POINTS} a sweep may have")
    base = _base_path(spec, path)
    axis_keys = set(spec.axes.keys())
    for text in overrides:
        key = ".".join(parse_override(text)[0])
        if key in axis_keys:
            raise ConfigError(f"--set {text}: {key} is an axis of {path} (its values would replace this)")
    fixed = [f"{key}={yaml_value(v)}" for key, v in spec.set.items()]
    labels = {f"--set {t}": f"{path}: set {t.partition('=')[0]}" for t in fixed}
    points = []
    notices: dict[str, None] = {}
    for index, values in enumerate(spec.axes.points()):
        own = [f"{key}={yaml_value(v)}" for key, v in values.items()]
        where = {f"--set {t}": f"{path}: {_axis_origin(spec, t.partition('=')[0])} {t}" for t in own}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConfigNotice)
            try:
                cfg = load_config(base, [*fixed, *overrides, *own])
            except ConfigError as exc:
                msg = str(exc)
                for origin, label in {**labels, **where}.items():
                    msg = msg.replace(origin + ":", label + ":")
                raise ConfigError(f"{msg} (point {index} of {n}: {', '.join(own)})") from None
        for w in caught:
            if issubclass(w.category, ConfigNotice):
                notices[str(w.message)] = None
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        points.append(Point(index, values, cfg, digest({"config": cfg.to_yaml_dict(), "keep": spec.keep})))
    for message in notices:  # once, not once per point
        warnings.warn(message, ConfigNotice, stacklevel=2)
    return Sweep(path, spec, base, (*fixed, *overrides), tuple(points))
