"""``mbcapture converge``: rendering error against run time, for the planner and the naive baseline.

For one capture config, a ladder of sample budgets is rendered twice:

``motion``   the planner (time strata from image motion), ``render.spp`` in the motion ladder;
``naive``    one render per collecting slot of every period, spp per slot in the naive ladder.

Each point's error is the relative RMS difference of the read buckets' noise-free exposures
(before the sensor) from a high-budget reference (the planner with strata ``ref_motion_div``
times finer and ``ref_spp`` samples), less the reference's own Monte Carlo variance (from its
averaged over buckets:

    e_k^2 = mean (B_k - R_k)^2 / mean(R_k)^2,     error = sqrt(mean_k e_k^2)

The reference's own error (from its half-sample variance) is reported beside it: the ladder's
errors are meaningful down to a few times that floor (``error_minus_ref`` subtracts it, but the
half-sample variance of a firefly-prone scene is itself noisy).

The largest 0.1 % of squared differences per bucket (fireflies) are left out (see
:func:`relative_error`). Each point's run time is the wall time of planning and rendering + accumulating (kernels are
compiled before the clock starts, as in a long run). Monte Carlo error falls as
seconds^(-1/2) once the per-render overhead is amortized; the plot has that slope as a guide.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..timing import protocols
from ..config import CaptureConfig, scene_of
from ..exposure.integrate import integrate
from ..output.io import staged_outputs
from ..output.plots import convergence_png
from ..exposure.plan import make_plan
from ..render import Renderer, ensure_llvm

DEFAULT_MOTION_LADDER = (1, 2, 4, 8, 16, 32, 64)
DEFAULT_NAIVE_LADDER = (1, 2, 4, 8)
QUICK_MOTION_LADDER = (1, 4, 16)
QUICK_NAIVE_LADDER = (1, 2)


@dataclass
class Point:
    method: str  #: 'motion' or 'naive'
    spp: int  #: samples per pixel per render pass (per stratum / per slot)
    passes: int
    samples_per_pixel_total: int
    seconds: float
    error: float  #: relative RMS error against the reference (fireflies trimmed)
    error_minus_ref: float  #: the same with the reference's half-sample MC variance subtracted (noisy)


def _setup(cfg: CaptureConfig):
    if cfg.render.variant.startswith("llvm"):
        ensure_llvm()
    scene = scene_of(cfg)
    timeline = protocols.build(cfg)
    renderer = Renderer.from_config(scene, cfg)  # no cache: converge measures rendering time
    return scene, timeline, renderer


def _warm(renderer, plan) -> None:
    """Compile the kernels of every group set the plan renders (outside the timed region)."""
    used = plan.weights_s.sum(axis=1) > 0
    for key in {tuple(np.flatnonzero(u)) for u in used}:
        renderer.render(float(plan.times_s[0]), 1, 0, tuple(plan.groups[g] for g in key))


def _seed(cfg: CaptureConfig, *key: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([cfg.seed, *key])


def render_point(
    cfg,
    scene,
    timeline,
    renderer,
    planner: str,
    spp: int,
    seed_key: tuple[int, ...],
    max_motion_px: float | None = None,
):
    """(integrated, plan, seconds) of one capture rendered with ``planner`` at ``spp``."""
    render = replace_render(cfg, planner=planner, spp=int(spp), max_motion_px=max_motion_px or cfg.render.max_motion_px)
    seeds = _seed(cfg, *seed_key).spawn(2)
    probe = make_plan(timeline, scene, render, np.random.default_rng(seeds[0]))
    _warm(renderer, probe)
    t0 = time.perf_counter()
    plan = make_plan(timeline, scene, render, np.random.default_rng(seeds[0]))
    out = integrate(renderer, plan, timeline.n_channels, seeds[1])
    return out, plan, time.perf_counter() - t0


def replace_render(cfg: CaptureConfig, **changes):
    return cfg.render.model_copy(update=changes)


#: Share of each bucket's samples left out of the error as fireflies (see :func:`relative_error`).
FIREFLY_SHARE = 1e-3


def relative_error(
    exposure: np.ndarray,
    reference: np.ndarray,
    ref_var: np.ndarray | None,
    buckets: list[int],
    trim: float = FIREFLY_SHARE,
) -> tuple[float, float]:
    """(error with the reference's MC variance subtracted, raw error): RMS over buckets of each
    bucket's RMS difference over its mean reference exposure.

    The largest ``trim`` share of squared differences per bucket is left out: a small bright
    lamp makes rare paths carry huge values (fireflies), and a handful of them make one ladder
    point's RMS jump by 2-3x; the trimmed RMS still falls as n^(-1/2) with the samples.
    """
    e2, raw2 = [], []
    for k in buckets:
        mean = reference[k].mean()
        if mean <= 0:
            continue
        d2 = ((exposure[k] - reference[k]) ** 2).ravel()
        v = ref_var[k].ravel() if ref_var is not None else np.zeros_like(d2)
        keep = d2 <= np.quantile(d2, 1.0 - trim) if trim > 0 else np.ones(d2.shape, bool)
        e2.append(max(d2[keep].mean() - v[keep].mean(), 0.0) / mean**2)
        raw2.append(d2[keep].mean() / mean**2)
    return float(np.sqrt(np.mean(e2))), float(np.sqrt(np.mean(raw2)))


def run_converge(
    cfg: CaptureConfig,
    motion_ladder=DEFAULT_MOTION_LADDER,
    naive_ladder=DEFAULT_NAIVE_LADDER,
    ref_spp: int = 256,
    ref_motion_div: float = 8.0,
    progress=None,
) -> dict:
    """Render the reference and both ladders; returns {'points': [...], 'reference': {...}, ...}."""
    say = progress or (lambda msg: None)
    scene, timeline, renderer = _setup(cfg)
    buckets = sorted({b for r in timeline.reads for b in r.buckets})
    say(f"reference: strata for {cfg.render.max_motion_px / ref_motion_div:g} px motion, {ref_spp} spp")
    ref, ref_plan, ref_s = render_point(
        cfg, scene, timeline, renderer, "motion", ref_spp, (99, ref_spp), cfg.render.max_motion_px / ref_motion_div
    )
    points: list[Point] = []
    for method, ladder, mid in (("motion", motion_ladder, 1), ("naive", naive_ladder, 2)):
        for spp in ladder:
            out, plan, secs = render_point(cfg, scene, timeline, renderer, method, spp, (mid, spp))
            sub, err = relative_error(out.exposure, ref.exposure, ref.mc_var, buckets)
            points.append(Point(method, int(spp), plan.passes, int(plan.spp.sum()), secs, err, sub))
            say(f"{method:6s} spp {spp:4d}: {plan.passes} passes, {secs:7.2f} s, error {err:.3e}")
    ref_err = (
        relative_error(ref.exposure + np.sqrt(ref.mc_var), ref.exposure, None, buckets, 0.0)[1]
        if ref.mc_var is not None
        else None
    )
    return {
        "film": [cfg.render.width, cfg.render.height],
        "periods": cfg.capture.periods,
        "protocol": cfg.capture.protocol,
        "scene": cfg.scene.name,
        "reference": {"passes": ref_plan.passes, "spp": ref_spp, "seconds": ref_s, "own_rel_rms_error": ref_err},
        "points": [asdict(p) for p in points],
        "slopes": {m: fit_slope([p for p in points if p.method == m]) for m in ("motion", "naive")},
        "speedups": equal_error_speedups(points),
    }


def fit_slope(points: list[Point]) -> float | None:
    """Least-squares slope of log(error) against log(seconds) (-1/2 for Monte Carlo)."""
    pts = [p for p in points if p.error > 0]
    if len(pts) < 2:
        return None
    return float(np.polyfit(np.log([p.seconds for p in pts]), np.log([p.error for p in pts]), 1)[0])


def planner_seconds_at(points: list[Point], error: float) -> tuple[float, bool]:
    """Seconds the motion planner needs for ``error``: log-log interpolation on its ladder
    (extrapolation with the fitted slope outside it; the bool says so)."""
    pts = sorted((p for p in points if p.method == "motion" and p.error > 0), key=lambda p: p.seconds)
    le = np.log([p.error for p in pts])
    lt = np.log([p.seconds for p in pts])
    if le.min() <= np.log(error) <= le.max():
        # errors fall along the ladder: interpolate time against error (error decreasing)
        order = np.argsort(le)
        return float(np.exp(np.interp(np.log(error), le[order], lt[order]))), False
    slope = fit_slope(pts)
    if slope is None or slope >= 0:
        raise ValueError("the planner's error does not fall with run time: cannot extrapolate")
    end = int(np.argmin(le)) if np.log(error) < le.min() else int(np.argmax(le))
    return float(np.exp(lt[end] + (np.log(error) - le[end]) / slope)), True


def equal_error_speedups(points: list[Point]) -> list[dict]:
    """For each naive point: naive seconds / planner seconds at the naive point's error."""
    out = []
    for p in (p for p in points if p.method == "naive"):
        try:
            t, extrap = planner_seconds_at(points, p.error)
        except ValueError:
            continue
        out.append(
            {
                "naive_spp": p.spp,
                "error": p.error,
                "naive_s": p.seconds,
                "planner_s": t,
                "speedup": p.seconds / t,
                "extrapolated": extrap,
            }
        )
    return out


def write_outputs(result: dict, out_dir: Path) -> None:
    """converge.csv, converge.json and converge.png (log-log error vs seconds)."""
    pts = result["points"]
    table = io.StringIO()
    w = csv.DictWriter(table, fieldnames=list(pts[0]))
    w.writeheader()
    w.writerows(pts)
    png = convergence_png(result)
    with staged_outputs(out_dir) as st:  # all three files or none (an interrupted run changes nothing)
        st.write_bytes("converge.csv", table.getvalue().encode())
        st.write_bytes("converge.json", (json.dumps(result, indent=2) + "\n").encode())
        st.write_bytes("converge.png", png)
