"""A design spec (``mbcapture design SPEC.yaml``): the base config, the free variables and their bounds, the
objective(s), the constraints and the budget of evaluations (docs/design.md).

Variables are dotted config keys with a range (``low``, ``high``; ``log``, ``integer``), a list of ``choices``,
or, for ``capture.exposure_ratios``, ``ratios``: the count of reads (one value, or choices such as [2, 4];
``sensor.bucket_count`` is set to it) and the largest ratio ``max_ratio``; each read's ratio is
max_ratio^p with the positions p in (0, 1] drawn by the optimiser and sorted (the first read is always 1).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import Field, ValidationError, model_validator

from ..config import SHIPPED_CONFIG_DIR, CaptureConfig, format_validation, load_config, resolve_config_path
from ..errors import ConfigError, ConfigNotice
from ..strict import StrictModel
from ..sweep.spec import resolve_shipped, yaml_value

#: The shipped design specs (``mbcapture design hdr_4bucket`` finds configs/designs/hdr_4bucket.yaml).
SHIPPED_DESIGN_DIR = SHIPPED_CONFIG_DIR / "designs"
RATIOS_KEY = "capture.exposure_ratios"


class Ratios(StrictModel):
    """The HDR protocols' exposure ratios as a free variable."""

    count: int | list[int] = Field(
        description="Reads (one per bucket): a number, or choices (e.g. [2, 4]); sensor.bucket_count follows it."
    )
    max_ratio: float = Field(gt=1.0, le=1e6, description="The largest ratio a read may have, in units of T.")
    span_s: float | None = Field(
        None,
        gt=0,
        description="Hold the capture's span: capture.unit_exposure_s follows the ratios (the span over the largest "
        "ratio for photon-efficient reads, over their sum for interleaved or sequential ones). null: T is its own.",
    )

    @property
    def counts(self) -> list[int]:
        return [self.count] if isinstance(self.count, int) else list(self.count)

    @model_validator(mode="after")
    def _two_or_more(self) -> "Ratios":
        if not self.counts or min(self.counts) < 2:
            raise ValueError(f"count: expected 2 or more reads, got {self.count}")
        return self


class Variable(StrictModel):
    """One free variable: a range, choices, or ratios (``capture.exposure_ratios`` only)."""

    low: float | None = Field(None, description="Smallest value (with high).")
    high: float | None = Field(None, description="Largest value (with low), included.")
    log: bool = Field(False, description="Search the logarithm of the value (low > 0).")
    integer: bool = Field(False, description="Whole numbers only.")
    choices: list[Any] | None = Field(None, min_length=1, description="Pick among these values instead.")
    ratios: Ratios | None = Field(None, description="capture.exposure_ratios: the reads' ratios (module doc).")

    @model_validator(mode="after")
    def _one_kind(self) -> "Variable":
        kinds = [self.choices is not None, self.ratios is not None, self.low is not None or self.high is not None]
        if sum(kinds) != 1:
            raise ValueError("give exactly one of: low and high (a range), choices, or ratios")
        if kinds[2]:
            if self.low is None or self.high is None or not self.high > self.low:
                raise ValueError(f"expected low < high, got low={self.low}, high={self.high}")
            if self.log and not self.low > 0:
                raise ValueError(f"log: true needs low > 0 (got {self.low})")
        return self


class Objective(StrictModel):
    """What is scored: a column of the evaluation's row (a report.json metric as ``metrics.<dotted key>`` or
    its bare key, ``capture_span_s``; with ``evaluator: snr``, ``snr.worst_db``, ``snr.dynamic_range_db``)."""

    metric: str = Field(description="The measured value to optimise (see docs/design.md for the names).")
    direction: Literal["minimize", "maximize"] = Field("minimize", description="Which way is better.")


class Bound(StrictModel):
    min: float | None = Field(None, description="Smallest accepted value.")
    max: float | None = Field(None, description="Largest accepted value.")


class SnrEvaluator(StrictModel):
    """``evaluator: snr``: no capture, the analytic SNR of the HDR merge (mbcapture snr) over a luminance range."""

    luminance_cd_m2: tuple[float, float] = Field(description="The scene's luminance range [low, high], cd/m^2.")

    @model_validator(mode="after")
    def _range(self) -> "SnrEvaluator":
        lo, hi = self.luminance_cd_m2
        if not 0 < lo < hi:
            raise ValueError(f"luminance_cd_m2: expected 0 < low < high, got {list(self.luminance_cd_m2)}")
        return self


class DesignSpec(StrictModel):
    base: str = Field(description="The base config: a path (relative to the spec) or a shipped config's name.")
    set: dict[str, Any] = Field(default_factory=dict, description="Keys fixed for every evaluation.")
    variables: dict[str, Variable] = Field(min_length=1, description="Dotted config key -> its bounds.")
    objective: Objective
    second_objective: Objective | None = Field(
        None, description="A second objective: the search then finds the Pareto front of the two."
    )
    constraints: dict[str, Bound] = Field(
        default_factory=dict, description="Measured value -> the bounds a design must keep (e.g. capture_span_s)."
    )
    evaluations: int = Field(40, ge=2, le=10_000, description="Designs the optimiser evaluates.")
    seeds: int = Field(3, ge=1, le=100, description="Noise seeds per design: the objective is their mean.")
    seed: int = Field(0, ge=0, description="The optimiser's seed.")
    compare_grid: bool = Field(
        True, description="Also evaluate the grid over the same variables with as many designs (the sweep's way)."
    )
    evaluator: Literal["capture"] | SnrEvaluator = Field(
        "capture", description="'capture' (a whole capture on cached renders) or an SNR range (analytic)."
    )


@dataclass(frozen=True)
class Design:
    path: Path
    spec: DesignSpec
    base: Path
    overrides: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.path.stem

    def base_values(self) -> dict[str, Any]:
        """The variables' values in the base config (with the fixed keys): what the default design has. The HDR
        protocols' exposure ratios null are their powers of two over the buckets."""
        cfg = self.config({})
        data = cfg.model_dump(mode="json")
        out = {}
        for key, var in self.spec.variables.items():
            if var.ratios is not None:
                n = cfg.sensor.bucket_count
                out[RATIOS_KEY] = cfg.capture.exposure_ratios or [float(2**i) for i in range(n)]
                out["sensor.bucket_count"] = n
            elif key.startswith("app."):  # the application's parameters with their defaults
                out[key] = getattr(cfg.app.resolve(cfg.capture.protocol)[1], key[4:], None)
            elif key.startswith("scene."):
                out[key] = getattr(cfg.scene.params(), key[6:], None)
            else:
                out[key] = _dotted(data, key)
        return out

    def config(self, values: dict[str, Any]) -> CaptureConfig:
        """The base config with the fixed keys, the command line's and ``values`` set (ConfigError if refused);
        with ratios that hold the span, T follows them."""
        var = self.spec.variables.get(RATIOS_KEY)
        if var is not None and var.ratios is not None and var.ratios.span_s is not None and RATIOS_KEY in values:
            base = self.config({k: v for k, v in values.items() if k != RATIOS_KEY})
            r = values[RATIOS_KEY]
            summed = base.capture.protocol == "interleaved_hdr" or base.capture.sequential
            unit = var.ratios.span_s / (sum(r) if summed else max(r))
            values = {**values, "capture.unit_exposure_s": float(f"{unit:.4g}")}  # a coarse exact tick
        own = [f"{k}={yaml_value(v)}" for k, v in values.items()]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConfigNotice)
            return load_config(self.base, [*self.overrides, *own])


def _dotted(data: dict, key: str) -> Any:
    for part in key.split("."):
        data = data.get(part) if isinstance(data, dict) else None
    return data


def resolve_design_path(path: str | Path) -> Path:
    """``path`` if it exists, else the shipped design spec of that name (``hdr_4bucket``)."""
    return resolve_shipped(path, SHIPPED_DESIGN_DIR, "design spec")


def ratios_of(positions: list[float], max_ratio: float) -> list[float]:
    """Exposure ratios 1, max_ratio^p (p sorted), rounded to 4 significant digits; None if two coincide."""
    r = [1.0] + [float(f"{max_ratio**p:.4g}") for p in sorted(positions)]
    return r if all(b > a for a, b in zip(r, r[1:])) else None


def extreme_values(key: str, var: Variable) -> list[dict[str, Any]]:
    """Config keys at the variable's bounds (each choice; for ratios, each count with ratios spread
    geometrically up to the largest), for checking that some config accepts them."""
    if var.ratios is not None:
        return [
            {RATIOS_KEY: ratios_of(list(np.linspace(0, 1, n)[1:]), var.ratios.max_ratio), "sensor.bucket_count": n}
            for n in var.ratios.counts
        ]
    if var.choices is not None:
        return [{key: c} for c in var.choices]
    lo, hi = (math.ceil(var.low), math.floor(var.high)) if var.integer else (var.low, var.high)
    return [{key: lo}, {key: hi}]


def load_design(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Design:
    """Read and validate a design spec; every variable's bounds tried on the base config (a bound no config
    accepts is one line naming it)."""
    path = resolve_design_path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the design spec ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: malformed YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with base, variables and objective")
    try:
        spec = DesignSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation(exc, origin=lambda p: str(path), model=DesignSpec)) from None
    local = path.parent / spec.base
    base = local if local.is_file() else resolve_config_path(spec.base)
    fixed = [f"{k}={yaml_value(v)}" for k, v in spec.set.items()]
    design = Design(path, spec, base, (*fixed, *overrides))
    for key, var in spec.variables.items():
        if var.ratios is not None and key != RATIOS_KEY:
            raise ConfigError(f"{path}: variables.{key}: 'ratios' is for {RATIOS_KEY} only")
        if var.ratios is None and key == RATIOS_KEY:
            raise ConfigError(f"{path}: variables.{key}: give it as ratios (count, max_ratio)")
        for values in extreme_values(key, var):
            try:
                design.config(values)
            except ConfigError as exc:
                shown = ", ".join(f"{k}={yaml_value(v)}" for k, v in values.items())
                raise ConfigError(f"{path}: variables.{key}: no config accepts {shown}: {exc}") from None
    return design
