"""Render groups: the points of a sweep whose render stage is provably the same.

A capture's render stage (:class:`mbcapture.capture.pipeline.Rendered`: the pilot, the strata's renders and
their accumulation into bucket exposures) is a function of what the code hands it, and this module
computes exactly those arguments from each point's config, with the functions the capture itself
calls, instead of a list of "render keys" that could drift:

* the renderer: the scene and its parameters, the film, variant, path depth and sampler (the
  ``render`` section), the camera section, what of the lens and the sensor the images depend on
  (:func:`mbcapture.render.settings.image_settings`: field of view, thin lens, diffraction's
  f-number, pitch and wavelengths, a mono sensor's mixture), and in spectral mode the film's curves
  (``sensor.spectral_response`` and ``quantum_efficiency`` through
  :func:`mbcapture.sensor.spectral.film_sensitivity`);
* the plan (:func:`mbcapture.capture.pipeline.prepare`): strata, render times, weights, the groups rendered
  in each stratum, the buckets read, samples per pixel, estimator; so ``capture.*`` keys, and the
  ``sensor.*`` keys a protocol reads (``bucket_count``, ``frame_readout_s`` of a sequential capture),
  count exactly where they change the plan;
* the seed (render times and samples; ``sensor.noise_seed`` is not used by renders);
* with ``render.spp`` null, the pilot's inputs: electrons per render unit (optics, QE, pixel) and
  the full well, because the noise budget sets the samples against the sensor's shot noise;
* whether the application wants per-group exposures (the same renders, accumulated apart);
* a time-of-flight capture's demodulation (:class:`mbcapture.sensor.demodulation.Demodulation`): the waveform and
  harmonics decide the phasor channels rendered, the taps' duty and contrast how they make each tap's image,
  which happens before the accumulation.

Points with equal keys form one render group: the sweep renders its first point and hands that
render stage to the others, which only simulate their sensor and reconstruct. Everything else
(``sensor.*`` noise, full wells, ADC, ``hdr.*``, ``app.*``, ``output.*``) stays out of the key.
Renders shared between groups (e.g. an application's reference render, or the same strata under
another accumulation) still come from the render cache.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.pipeline import prepare
from ..config import CaptureConfig
from ..errors import MBCaptureError, one_line
from ..render.cache import digest
from ..render.settings import image_settings
from ..sensor import electrons_per_render_second
from ..sensor.spectral import film_sensitivity, is_spectral_variant
from .spec import Sweep


def _array(a: np.ndarray | None) -> Any:
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    return {"shape": list(a.shape), "dtype": a.dtype.str, "sha256": hashlib.sha256(a.tobytes()).hexdigest()}


def _camera(cfg: CaptureConfig) -> dict:
    out = cfg.camera.model_dump(mode="json")
    if cfg.camera.trajectory_file is not None:
        out["trajectory_sha256"] = hashlib.sha256(Path(cfg.camera.trajectory_file).read_bytes()).hexdigest()
    return out


def render_inputs(cfg: CaptureConfig, *, accumulation: bool = True) -> dict:
    """Everything the render stage of a capture of ``cfg`` receives, as plain data.

    ``accumulation=False``: only what decides the renders themselves (strata, render times, which
    groups each stratum renders, samples, seeds, the renderer), not how they are weighted into the
    buckets; with ``render.spp`` null the weights and buckets read stay in, because the pilot
    allocates samples by them."""

    scene, timeline, plan, _ = prepare(cfg)
    app, _ = cfg.app.resolve(cfg.capture.protocol)
    render = cfg.render.model_dump(mode="json")
    for where in ("cache", "cache_max_gb"):  # where renders are kept, not what they are
        render.pop(where)
    out: dict[str, Any] = {
        "seed": cfg.seed,
        "scene": {"name": cfg.scene.name, "params": cfg.scene.params().model_dump(mode="json")},
        "render": render,
        # the camera's pose at each render time: the trajectory's parameters, or its file's content
        "camera": _camera(cfg),
        # what of the lens and the sensor the images depend on (diffraction's f-number, a mono sensor's mixture)
        "images": image_settings(scene, cfg),
        "plan": {
            "starts_ticks": _array(plan.starts_ticks),
            "ends_ticks": _array(plan.ends_ticks),
            "times_s": _array(plan.render_times),
            "weights_s": _array(plan.weights_s),
            "groups": list(plan.groups),
            "buckets_read": list(plan.buckets_read),
            "spp": _array(plan.spp),
            "estimator": plan.estimator,
            "base_spp": plan.base_spp_setting,
            "base_time_s": repr(plan.base_time_s),
            "max_spp_per_render": plan.max_spp_per_render,
            "tick_s": str(timeline.tick_s),
        },
        "n_buckets": timeline.n_buckets,
        "per_group": app.per_group,
    }
    demod = scene.demodulation
    if demod is not None:  # a time-of-flight capture: its phase groups' images are combined before accumulation
        out["demodulation"] = {"waveform": demod.waveform, "harmonics": demod.harmonics}  # what is rendered
        if accumulation:  # and how the rendered channels make each tap's image
            out["demodulation"] |= {"duty": repr(demod.duty), "contrast": repr(demod.contrast)}
    if is_spectral_variant(cfg.render.variant):
        wl, curves = film_sensitivity(cfg.sensor)
        out["film_curves"] = [_array(np.asarray(wl, np.float64)), _array(np.asarray(curves, np.float64))]
    if cfg.render.spp is None:  # mbcapture.budget.resolve_spp: samples from the sensor's shot noise
        out["pilot"] = {
            "k_e": _array(np.asarray(electrons_per_render_second(cfg.sensor, cfg.render.variant))),
            "full_well_e": repr(float(cfg.sensor.full_well_e)),
        }
    elif not accumulation:  # integrate renders, per stratum, the groups with weight in it
        out["plan"]["weights_s"] = _array(plan.weights_s.sum(axis=1) > 0)
        for k in ("buckets_read",):
            out["plan"].pop(k)
        out.pop("n_buckets")
        out.pop("per_group")
    return out


def group_key(cfg: CaptureConfig) -> str:
    """SHA-256 of :func:`render_inputs`: equal for captures whose render stage is the same."""
    return digest(render_inputs(cfg))


def render_key(cfg: CaptureConfig) -> str:
    """SHA-256 of :func:`render_inputs` without the accumulation: equal for captures that render
    the same images (they may weigh them differently into their buckets)."""
    return digest(render_inputs(cfg, accumulation=False))


@dataclass(frozen=True)
class RenderGroup:
    """Points (indices into the sweep) that share one render stage; ``key``: their group key;
    ``renders``: their :func:`render_key` (groups with equal ones render the same images, so the
    later ones find them in the render cache)."""

    key: str
    points: tuple[int, ...]
    renders: str = ""

    @property
    def label(self) -> str:
        return f"g{self.key[:8]}"


@dataclass(frozen=True)
class SweepPlan:
    """The render groups (in order of their first point), the points that failed to plan (index ->
    one-line error), and which axes change the renders."""

    groups: tuple[RenderGroup, ...]
    failed: dict[int, str] = field(default_factory=dict)
    axes_changing_renders: tuple[str, ...] = ()

    def group_of(self, index: int) -> RenderGroup | None:
        for g in self.groups:
            if index in g.points:
                return g
        return None


def _hashable(value: Any) -> str:
    return digest(value)


def changing_axes(sweep: Sweep, keys: dict[int, str]) -> tuple[str, ...]:
    """Axes along which two points that agree on every other axis have different group keys."""
    out = []
    for axis in sweep.axes:
        seen: dict[str, str] = {}
        for p in sweep.points:
            if p.index not in keys:
                continue
            rest = _hashable({k: v for k, v in p.values.items() if k != axis})
            if seen.setdefault(rest, keys[p.index]) != keys[p.index]:
                out.append(axis)
                break
    return tuple(out)


def plan_sweep(sweep: Sweep) -> SweepPlan:
    """Group the sweep's points by :func:`group_key`. A point whose capture cannot be planned (e.g.
    a protocol that needs more buckets than its sensor has) is recorded as failed, not fatal."""

    keys: dict[int, str] = {}
    renders: dict[str, str] = {}
    failed: dict[int, str] = {}
    for p in sweep.points:
        try:
            keys[p.index] = group_key(p.config)
            if keys[p.index] not in renders:  # a group's renders are its first point's (computed once: a plan each)
                renders[keys[p.index]] = render_key(p.config)
        except (MBCaptureError, ValueError) as exc:
            failed[p.index] = one_line(exc)
    members: dict[str, list[int]] = {}
    for index, key in keys.items():
        members.setdefault(key, []).append(index)
    groups = tuple(RenderGroup(key, tuple(ix), renders[key]) for key, ix in members.items())
    return SweepPlan(groups, failed, changing_axes(sweep, keys))
