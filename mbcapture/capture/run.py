"""``run_capture``: one capture from config to outputs.

The capture itself is :func:`mbcapture.capture.pipeline.capture_in_memory` (a video's frames:
:func:`mbcapture.capture.video.run_video`); this module writes what it produced, atomically: EXR, PNG
previews, report.json and report.html.
"""

from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..exposure import resources
from ..budget import noise_verdict
from ..config import CaptureConfig, revalidated
from ..errors import ConfigError
from ..output.io import check_out_dir, staged_outputs
from .pipeline import (
    CaptureResult,
    Prepared,
    Rendered,
    capture_in_memory,
    prepare,
    render_cache,
)
from ..progress import StageStatus
from ..output.raw import white_level_dn, write_dng
from .report import read_limits_dn, write_read_previews, write_report
from ..sensor import electrons_per_render_second
from .video import run_video, write_video_files


def render_summary(report: dict) -> list[str]:
    """The lines a run prints about its rendering: noise against the budget, and the cache."""
    err = report.get("render_error", {})
    out = [err.get("verdict") or noise_verdict(err)]
    cache = report.get("render_cache", {})
    if cache.get("folder"):
        out.append(f"render cache: {cache['hits']} renders reused, {cache['rendered']} rendered ({cache['folder']})")
    return out


def check_resources(cfg: CaptureConfig, out_dir: Path | None) -> tuple[Prepared, resources.Resources, float]:
    """Plan the run's memory and disk and stop it, before any work, when it cannot fit
    (:func:`mbcapture.exposure.resources.check`: one line, exit 2). Returns what it planned with: the
    capture's :func:`prepare`, its resources, and the seconds the two took."""
    start = time.perf_counter()
    prepared = prepare(cfg)
    need = resources.plan_resources(cfg, prepared.timeline, prepared.plan, cfg.app.resolve(cfg.capture.protocol)[0])
    cache = render_cache(cfg.render)
    seconds = time.perf_counter() - start
    resources.check(need, cfg, out_dir, None if cache is None else cache.root)
    return prepared, need, seconds


def run_capture(
    cfg: CaptureConfig,
    out_dir: str | Path | None = None,
    *,
    progress: bool = True,
    rendered: Rendered | None = None,
    on_rendered: "Callable[[Rendered], None] | None" = None,
    client: Any = None,
) -> CaptureResult:
    """Run one capture. With ``out_dir``, write its outputs there (atomically). ``progress``: a
    status line for every stage and a bar for the render passes (stderr). ``rendered``: the render
    stage of another capture with the same renders (see :class:`Rendered`), used instead of
    rendering; ``on_rendered(Rendered)`` is called once this capture's render stage is done (before
    the sensor, so it is called even if a later stage fails). ``client``: a Dask client whose workers
    render the strata (mbcapture.exposure.cluster; not for videos)."""
    cfg = revalidated(cfg)  # what was assigned through the API, checked against the other sections
    if out_dir is not None:
        check_out_dir(Path(out_dir))
    planned = check_resources(cfg, None if out_dir is None else Path(out_dir))
    _, need, _ = planned
    if progress:
        print(f"mbcapture: this run {need.line()}", file=sys.stderr)
    if cfg.capture.frames > 1 and client is not None:
        raise ConfigError(
            "--workers/--scheduler: a video (capture.frames > 1) renders its frames here; "
            "use mbcapture sweep to spread captures over a cluster"
        )
    if cfg.capture.frames > 1:  # a video: a capture per frame (mbcapture/capture/video.py)
        result = run_video(cfg, progress=progress)
        if out_dir is not None:
            write_outputs(result, Path(out_dir), extra=lambda st: write_video_files(st, result))
            result.out_dir = Path(out_dir)
        return result
    own_render = rendered is None
    budget = cfg.render.spp is None  # a pilot, and adaptive sampling's second pass when it is on
    stages = 4 + own_render * (1 + budget + (budget and cfg.render.adaptive)) + (out_dir is not None)
    with StageStatus(progress, stages=stages) as status:
        result = capture_in_memory(
            cfg, status, progress=progress, rendered=rendered, on_rendered=on_rendered, client=client, planned=planned
        )
        if out_dir is not None:
            with status.stage("write outputs and report"):
                write_outputs(result, Path(out_dir))
            result.out_dir = Path(out_dir)
    return result


def write_outputs(result: CaptureResult, out: Path, extra=None, *, raw: bool = True) -> None:
    """Every output file of ``result`` into ``out``, atomically; ``extra(staging)`` writes more files
    (a video's) before report.html, which lists them; ``raw=False`` leaves out the bucket and read
    EXRs (buckets.exr, reads_expected.exr, reads.exr)."""
    cfg, tl = result.config, result.timeline
    names = [r.name for r in tl.reads]
    empty = result.film_store.empty  # a spilled film (render.spill) makes the EXRs' channels in scratch files too
    with staged_outputs(out) as st:
        if raw:
            st.write_exr(
                "buckets.exr",
                {f"B{k + 1}": partial(np.multiply, result.bucket_exposure[k], result.k_e) for k in range(tl.n_buckets)},
                empty=empty,
            )
            st.write_exr(
                "reads_expected.exr", {n: result.reads_expected_e[i] for i, n in enumerate(names)}, empty=empty
            )
            st.write_exr("reads.exr", {n: result.reads_dn[i] for i, n in enumerate(names)}, empty=empty)
        app_out = result.app_output
        st.write_exr(f"{result.app}.exr", app_out.images, empty=empty)
        for file, layers in app_out.extra_exr.items():
            st.write_exr(file, layers, empty=empty)
        for stem, (image, percentile) in app_out.png.items():
            st.write_png(f"{stem}.png", app_out.images[image], percentile)
        if cfg.output.dng:
            gain = electrons_per_render_second(cfg.sensor, cfg.render.variant) * cfg.sensor.gain_dn_per_e
            cfa = None if cfg.sensor.cfa == "none" else cfg.sensor.cfa
            codes = result.reads_dn if result.mosaic_dn is None else result.mosaic_dn  # a CFA sensor: its photosites
            limits = read_limits_dn(result)
            exposures = [r["exposure_s"] for r in result.report["reads"]]
            for i, n in enumerate(names):
                write_dng(
                    st.path(f"read_{n}.dng"),
                    codes[i],
                    black_level=cfg.sensor.black_level_dn,
                    white_level=white_level_dn(limits[i]["charge_limit_e"], cfg.sensor),
                    channel_gain=gain,
                    cfa=cfa,
                    exposure_s=exposures[i],
                    baseline_exposure_ev=float(np.log2(max(exposures) / exposures[i])) if exposures[i] > 0 else 0.0,
                )
        result.report["previews"] = write_read_previews(st, result)  # one common DN scale, and each its own
        st.write_yaml("config.yaml", cfg.to_yaml_dict())
        if extra is not None:
            extra(st)
        st.write_json("report.json", result.report)
        write_report(st, result)  # report.html and its plots, last: it lists every file
