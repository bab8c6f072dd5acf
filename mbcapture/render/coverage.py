"""Ground-truth coverage (alpha) of a set of shapes, motion-blurred over a capture's strata.

The coverage scene keeps only the named shapes, all black, inside a constant environment of
radiance 1 (group :data:`COVERAGE_GROUP`), rendered with ``max_depth`` 1: a camera ray sees 1
where it misses every kept shape and 0 where it hits one, so with the box pixel filter each
pixel's value is the fraction of the pixel the shapes leave uncovered, 1 - alpha. Moving parts
keep their motion, so integrating the strata with a bucket's weights gives the coverage as that
bucket saw it (motion blur included), exactly up to the Monte Carlo noise of the pixel samples:
per stratum the variance is alpha (1 - alpha) / spp.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable

import numpy as np

from ..errors import ConfigError
from ..scene.scenes import SceneModel
from .build import Environment, SceneBuild
from .renderer import Renderer

#: The one emitter group of a coverage scene (the environment).
COVERAGE_GROUP = "coverage"


def coverage_scene(scene: SceneModel, names: Iterable[str] | None = None) -> SceneModel:
    """A copy of ``scene`` holding only the shapes ``names`` (default: ``scene.extra['foreground']``),
    black and not emitting, in a constant environment of radiance 1."""
    if names is None:
        names = scene.extra.get("foreground")
        if not names:
            raise ConfigError(
                f"scene.name: scene {scene.name!r} does not name its foreground shapes "
                "(SceneModel.extra['foreground']), needed for a coverage ground truth"
            )
    names = set(names)
    build: SceneBuild = scene.build
    unknown = names - {s.name for s in build.shapes}
    if unknown:
        raise ConfigError(f"scene {scene.name!r}: foreground names unknown shapes {sorted(unknown)}")
    shapes = tuple(dataclasses.replace(s, material=None, light=None) for s in build.shapes if s.name in names)
    parts = {p: f for p, f in build.parts.items() if any(s.part == p for s in shapes)}
    return dataclasses.replace(
        scene,
        name=f"{scene.name}_coverage",
        groups=(COVERAGE_GROUP,),
        switchable=frozenset(),
        build=SceneBuild(shapes=shapes, parts=parts, environment=Environment(COVERAGE_GROUP, (1.0, 1.0, 1.0))),
    )


def rgb_variant(variant: str) -> str:
    """The RGB variant of the same backend (coverage is geometry, not colour)."""
    return variant[: -len("_spectral")] + "_rgb" if variant.endswith("_spectral") else variant


def coverage_alpha(
    scene: SceneModel,
    times_s: np.ndarray,
    weights_s: np.ndarray,
    width: int,
    height: int,
    spp: int,
    seed: np.random.SeedSequence,
    *,
    variant: str = "llvm_ad_rgb",
    names: Iterable[str] | None = None,
    cache=None,
) -> np.ndarray:
    """(H, W) float64 alpha: the weighted mean over time strata of the shapes' coverage.

    ``times_s`` (J,) the scene times at which the capture rendered its strata (``Plan.times_s``),
    ``weights_s`` (J,) how long the wanted bucket(s) collected in each stratum, s. Strata of weight
    0 are not rendered. Rendering at the capture's own times puts the parts exactly where the
    capture's renders saw them. ``cache``: a :class:`~mbcapture.render.cache.RenderCache` for the
    coverage renders (None: not kept).
    """

    t = np.asarray(times_s, dtype=np.float64)
    w = np.asarray(weights_s, dtype=np.float64)
    if t.ndim != 1 or w.shape != t.shape or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"coverage weights: expected {t.size} non-negative values with a positive sum")
    if spp < 1:
        raise ValueError("coverage spp must be >= 1")
    renderer = Renderer(
        coverage_scene(scene, names), width, height, variant=rgb_variant(variant), max_depth=1, cache=cache
    )
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=t.size)
    uncovered = np.zeros((height, width), dtype=np.float64)
    for j in np.flatnonzero(w > 0):
        img = renderer.render(float(t[j]), int(spp), int(seeds[j]), [COVERAGE_GROUP])[0]
        uncovered += w[j] * img.mean(axis=-1, dtype=np.float64)  # all channels equal
    return np.clip(1.0 - uncovered / w.sum(), 0.0, 1.0)
