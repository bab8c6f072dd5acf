"""Command line: ``mbcapture run | plan | characterize | sweep | scenes | apps | figures | converge | cache``.

Input errors (config, files, environment) print one line and exit with status 2; notices
(:class:`~mbcapture.errors.ConfigNotice`) print one line ``mbcapture: note: ...`` and go on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import threading
import warnings
from pathlib import Path

from pydantic import ValidationError

from . import application as apps
from .studies import characterize, converge, dynamic_range
from . import figures
from .exposure import resources
from .scene import scenes
from .budget import probe_cost, resolve_spp
from .capture.run import render_summary, run_capture
from .capture.pipeline import describe, prepare, render_cache
from .exposure.cluster import start_client
from .config import load_config
from .errors import ConfigError, ConfigNotice, MBCaptureError
from .output.io import check_out_dir
from .render import Renderer
from .render import xmlscene
from .render.cache import RenderCache, default_cache_dir
from .sweep import load_sweep, resolve_sweep_path, run_sweep
from .design.results import run_design
from .design.spec import load_design

EXIT_INPUT = 2


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config",
        type=Path,
        help="YAML config: a path (configs/metronome_hdr.yaml) or a shipped config's name (metronome_hdr)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key by its dotted path; VALUE is YAML (e.g. render.spp=4, scene.amplitude_deg=45, "
        "scene.name=flatfield)",
    )


def _add_noise_args(p: argparse.ArgumentParser) -> None:
    """``--quiet`` and ``--silent``, the same for every command that runs for a while."""
    noise = p.add_mutually_exclusive_group()
    noise.add_argument("--quiet", action="store_true", help="no progress bar or status line; the summary at the end")
    noise.add_argument("--silent", action="store_true", help="nothing printed but errors")


def _shows_progress(args) -> bool:
    return not (args.quiet or args.silent)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mbcapture", description="Multi-bucket sensor capture simulator (Mitsuba 3).")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    _add_run_command(sub)
    _add_plan_command(sub)
    _add_converge_command(sub)
    _add_characterize_command(sub)
    _add_snr_command(sub)
    _add_design_command(sub)
    scn = sub.add_parser("scenes", help="list the scenes and their parameters, or the ids of a Mitsuba scene file")
    scn.add_argument(
        "file",
        nargs="?",
        type=Path,
        default=None,
        help="a Mitsuba 3 scene file (.xml): list what scene.groups and scene.motion can name in it",
    )
    scn.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a value of one of the file's $parameters (as scene.parameters gives it)",
    )
    _add_figures_command(sub)
    sub.add_parser("apps", help="list the applications (reconstructions), their protocols and parameters")
    _add_sweep_command(sub)
    _add_cache_command(sub)
    return p


def _add_run_command(sub) -> None:
    """``mbcapture run``."""

    run = sub.add_parser("run", help="render, simulate the sensor, reconstruct, write outputs")
    _add_config_args(run)
    run.add_argument("--out", type=Path, default=None, help="output folder (default: out/<config name>)")
    _add_noise_args(run)
    run_where = run.add_mutually_exclusive_group()
    run_where.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="render the capture's strata on a local Dask cluster of N worker processes",
    )
    run_where.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="render the capture's strata on an existing Dask cluster (tcp://host:port)",
    )


def _add_plan_command(sub) -> None:
    """``mbcapture plan``."""
    plan = sub.add_parser("plan", help="show what would be rendered, without rendering")
    _add_config_args(plan)
    plan.add_argument("--json", action="store_true", help="print the plan as JSON")
    plan.add_argument(
        "--no-probe",
        action="store_true",
        help="no pilot/probe render: no spp from render.noise_budget and no time estimate",
    )


def _add_converge_command(sub) -> None:
    """``mbcapture converge``."""
    conv = sub.add_parser("converge", help="rendering error vs run time: planner and naive per-slot ladders")
    _add_config_args(conv)
    conv.add_argument("--out", type=Path, default=None, help="output folder (default: out/converge_<config name>)")
    conv.add_argument("--quick", action="store_true", help="short ladders and a 64-spp reference")
    conv.add_argument(
        "--spp", type=str, default=None, help="planner ladder, comma-separated (default 1,2,4,8,16,32,64)"
    )
    conv.add_argument("--naive-spp", type=str, default=None, help="naive ladder, spp per slot (default 1,2,4,8)")
    conv.add_argument("--ref-spp", type=int, default=None, help="reference spp (default 256; --quick 64)")


def _add_characterize_command(sub) -> None:
    """``mbcapture characterize``."""
    char = sub.add_parser(
        "characterize",
        help="measure the configured sensor as EMVA 1288 Release 4.0 does; a "
        "datasheet (report.html, characterization.json)",
    )
    _add_config_args(char)
    char.add_argument("--out", type=Path, default=None, help="output folder (default: out/characterize_<config name>)")
    char.add_argument(
        "--size", type=_size, default=(128, 128), metavar="WxH", help="film of the flat-field frames (default 128x128)"
    )
    char.add_argument("--steps", type=int, default=50, help="exposure steps from dark to 1.25x saturation (default 50)")
    char.add_argument(
        "--dark-steps", type=int, default=10, help="exposure steps of the dark-current series (default 10)"
    )
    char.add_argument("--frames", type=int, default=16, help="frames averaged for DSNU and PRNU (default 16)")
    _add_noise_args(char)


def _add_design_command(sub) -> None:
    d = sub.add_parser(
        "design",
        help="find the schedule and sensor settings that optimise an application's metric (docs/design.md)",
        description="Search a design spec's variables (Optuna's TPE) for the best value of its objective, each "
        "design a capture on cached renders with several noise seeds; compare it with the default and with the "
        "grid at equal evaluations.",
    )
    d.add_argument("spec", type=Path, help="design spec: a path or a shipped spec's name (hdr_4bucket)")
    d.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a key of the base config for every design (e.g. render.width=160)",
    )
    d.add_argument("--out", type=Path, default=None, help="output folder (default: out/design_<spec name>)")
    d.add_argument("--evaluations", type=int, default=None, metavar="N", help="designs to evaluate (the spec's)")
    d.add_argument("--seeds", type=int, default=None, metavar="N", help="noise seeds per design (the spec's)")
    _add_noise_args(d)


def _add_snr_command(sub) -> None:
    """``mbcapture snr``."""
    snr = sub.add_parser(
        "snr",
        help="SNR against scene luminance of an HDR capture design, each read and the merge, and its dynamic "
        "range (analytic, checked on a simulated flat field; no rendering)",
    )
    _add_config_args(snr)
    snr.add_argument(
        "--vs",
        action="append",
        default=[],
        metavar="KEY=VALUE[;KEY=VALUE...]",
        help="another design on the same figure: the config with these overrides besides --set's "
        "(e.g. --vs 'sensor.bucket_count=2;capture.exposure_ratios=[1,8]'); repeatable",
    )
    snr.add_argument("--out", type=Path, default=None, help="output folder (default: out/snr_<config name>)")
    snr.add_argument(
        "--pixels", type=int, default=4000, help="pixels per level of the simulated check (default 4000; 0: none)"
    )
    snr.add_argument("--levels", type=int, default=16, help="radiance levels of the simulated check (default 16)")
    _add_noise_args(snr)


def _add_figures_command(sub) -> None:
    """``mbcapture figures``."""
    figs = sub.add_parser("figures", help="regenerate the paper's figures (PNG, PDF, data, index.html)")
    figs.add_argument("--out", type=Path, default=Path("out/figures"), help="output folder (default: out/figures)")
    figs.add_argument("--quick", action="store_true", help="small size (160x128, 4 spp): every figure in minutes")
    figs.add_argument("--only", nargs="+", metavar="NAME", default=None, help="only these figures (see --list)")
    figs.add_argument("--list", action="store_true", help="list the figures and exit")
    figs.add_argument("--seed", type=int, default=0, help="seed of every capture and simulation")
    _add_noise_args(figs)


def _add_sweep_command(sub) -> None:
    """``mbcapture sweep``."""
    sweep = sub.add_parser(
        "sweep", help="many captures varying some keys (renders shared), on Dask; a table, plots, index.html"
    )
    sweep.add_argument(
        "sweep",
        type=Path,
        help="sweep file: a path (configs/sweeps/sensor_noise.yaml) or a shipped sweep's name (sensor_noise)",
    )
    sweep.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a key of the base config for every point (not an axis), e.g. render.width=160",
    )
    sweep.add_argument("--out", type=Path, default=None, help="output folder (default: out/sweep_<sweep name>)")
    where = sweep.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="run on a local Dask cluster of N worker processes (default: one per core; a sweep whose "
        "points all share one set of renders runs in this process unless this is given)",
    )
    where.add_argument(
        "--in-process",
        dest="in_process",
        action="store_const",
        const=True,
        default=None,
        help="run every point in this process, without Dask",
    )
    where.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run on an existing Dask cluster (tcp://host:port) instead of a local one",
    )
    sweep.add_argument(
        "--resume", action="store_true", help="skip the points that finished in an earlier run into --out"
    )
    _add_noise_args(sweep)


def _add_cache_command(sub) -> None:
    """``mbcapture cache``."""
    cache = sub.add_parser("cache", help="the render cache: where it is and how big, or empty it")
    cache.add_argument(
        "action", choices=["info", "clear"], help="info: folder, entries, size; clear: remove every render"
    )
    cache.add_argument(
        "--dir",
        type=Path,
        default=None,
        help="cache folder (default: $MBCAPTURE_CACHE_DIR or the user cache folder, as render.cache: on)",
    )


def _cmd_cache(args) -> int:
    cache = RenderCache(args.dir or default_cache_dir(), max_bytes=0)
    if args.action == "clear":
        print(f"removed {cache.clear() if cache.root.is_dir() else 0} renders from {cache.root}")
        return 0
    info = cache.info()
    print(
        f"{info['folder']}: {info['entries']} renders, {info['size_bytes'] / 1e9:.3f} GB "
        "(cap: render.cache_max_gb, default 20 GB)"
    )
    return 0


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("mbcapture")
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 128x128, got {text!r}") from None
    return w, h


def _cmd_characterize(args) -> int:
    cfg = load_config(args.config, args.overrides)
    out = args.out or Path("out") / f"characterize_{args.config.stem}"
    check_out_dir(out)
    settings = characterize.Settings(
        width=args.size[0], height=args.size[1], steps=args.steps, dark_steps=args.dark_steps, frames=args.frames
    )
    characterize.characterize(
        cfg, out, source=str(args.config), settings=settings, progress=_shows_progress(args), summary=not args.silent
    )
    return 0


def _cmd_design(args) -> int:
    design = load_design(args.spec, args.overrides)
    update = {k: v for k, v in (("evaluations", args.evaluations), ("seeds", args.seeds)) if v is not None}
    if update:
        try:
            spec = design.spec.model_validate({**design.spec.model_dump(), **update})
        except ValidationError as exc:
            raise ConfigError(f"--evaluations/--seeds: {exc.errors()[0]['msg']}") from None
        design = dataclasses.replace(design, spec=spec)
    out = args.out or Path("out") / f"design_{design.name}"
    say = (lambda line: None) if args.silent else print
    run_design(design, out, progress=_shows_progress(args), say=say)
    return 0


def _cmd_snr(args) -> int:
    if args.pixels < 0 or args.pixels == 1:
        raise ConfigError(f"--pixels: expected 0 (no check) or at least 2, got {args.pixels}")
    if args.levels < 1:
        raise ConfigError(f"--levels: expected at least 1, got {args.levels}")
    designs = [dynamic_range.design_of(load_config(args.config, args.overrides), args.config.stem)]
    for text in args.vs:
        extra = [part.strip() for part in text.split(";") if part.strip()]
        designs.append(dynamic_range.design_of(load_config(args.config, [*args.overrides, *extra]), ", ".join(extra)))
    out = args.out or Path("out") / f"snr_{args.config.stem}"
    check_out_dir(out)
    doc = dynamic_range.study(designs, out, pixels=args.pixels, levels=args.levels)
    if not args.silent:
        for line in dynamic_range.summary_lines(doc):
            print(f"mbcapture: {line}", file=sys.stderr)
        print(f"mbcapture: wrote {out}/snr.png, snr.json, snr.parquet", file=sys.stderr)
    return 0


def _cmd_run(args) -> int:
    cfg = load_config(args.config, args.overrides)
    out = args.out or Path("out") / args.config.stem
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected a number of processes >= 1, got {args.workers}")
    client = None if args.workers is None and args.scheduler is None else start_client(args.workers, args.scheduler)
    try:
        result = run_capture(cfg, out, progress=_shows_progress(args), client=client)
    finally:
        if client is not None:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and args.scheduler is None:
                cluster.close()
    if not args.silent:
        r = result.report
        print(
            f"wrote {out}/  ({r['plan']['passes']} render passes x {result.plan.spp_label()} spp, "
            f"{r['timings_s']['total_before_write']:.1f} s)"
        )
        for line in [*result.app_output.summary, *render_summary(r)]:
            print(line)
    return 0


def _cmd_plan(args) -> int:
    cfg = load_config(args.config, args.overrides)
    scene, timeline, plan, seeds = prepare(cfg)
    if not args.no_probe and plan.passes:
        renderer = Renderer.from_config(scene, cfg, cache=render_cache(cfg.render))
        plan = resolve_spp(plan, renderer, cfg, seeds[2])  # the run's own pilot (render.spp null)
        if plan.cost is None:
            plan = probe_cost(plan, renderer, seeds[2])
    info = describe(cfg, timeline, plan)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(
        f"scene {info['scene']}, protocol {info['protocol']}{' (sequential, conventional sensor)' if timeline.sequential else ''}, "
        f"film {cfg.render.width}x{cfg.render.height}, capture span {info['capture_span_s'] * 1e3:.4g} ms"
    )
    print("reads:")
    for r in info["reads"]:
        print(
            f"  {r['name']}: buckets {r['buckets']}, exposure {r['exposure_s'] * 1e3:.4g} ms, "
            f"span {r['span_s'] * 1e3:.4g} ms, centroid {r['centroid_s'] * 1e3:.4g} ms"
        )
    s = info["plan"]
    print(
        f"render ({s['planner']} planner): {s['passes']} passes x {plan.spp_label()} spp ({s['spp_source']}), "
        f"groups {s['groups_rendered']}" + (f" (left out: {s['groups_left_out']})" if s["groups_left_out"] else "")
    )
    if s["pilot"]:
        need = [
            f"{name} {q['spp_for_median']:.0f}/{q['spp_for_p95']:.0f}"
            for name, q in s["pilot"]["per_read"].items()
            if q is not None
        ]
        t = s["pilot"]["targets"]
        print(
            f"pilot: {s['pilot']['renders']} renders, {s['pilot']['seconds']:.2f} s; spp each read needs for "
            f"Monte Carlo / shot-noise variance median <= {t['median']:g} / p95 <= {t['p95']:g}: {', '.join(need)}"
        )
    if s["estimate_s"]:
        c, e = s["cost_model"], s["estimate_s"]
        print(
            f"time estimate: render {e['render_s']:.2f} s + accumulate {e['accumulate_s']:.2f} s "
            f"({s['renders']} renders x {c['c0_s'] * 1e3:.1f} ms + {c['c1_s_per_spp'] * 1e3:.2f} ms per spp; "
            f"kernel compilation ~{c['compile_s']:.1f} s)"
        )
    print(
        f"image motion during the capture: {s['image_motion_px_total']:.2f} px (at most {s['max_motion_px']} px per stratum)"
    )
    r, (free, source) = info["resources"], resources.free_memory()
    tiles = (
        f" in {r['tiles']} tiles of rows (render.tiles; {r['render_bands']} render bands)"
        if r["tiles"] > 1
        else f" in one tile ({r['render_bands']} render band{'s' * (r['render_bands'] > 1)})"
    )
    if r["spill_gb"]:
        tiles += f", the film's results in {r['spill_gb']:.3g} GB of scratch files on disk (render.spill)"
    print(
        f"resources: peak memory about {r['peak_memory_gb']:.3g} GB{tiles} ({free / 2**30:.3g} GB free: {source}), outputs "
        f"about {r['outputs_mb']:.3g} MB"
        + (f", new render-cache entries about {r['render_cache_mb']:.3g} MB" if r["render_cache_mb"] else "")
    )
    for n in s["notes"]:
        print(f"note: {n}")
    return 0


def _cmd_converge(args) -> int:
    cfg = load_config(args.config, args.overrides)

    def ladder(text, default, key):
        if text is None:
            return default
        try:
            vals = tuple(int(v) for v in text.split(",") if v.strip())
        except ValueError:
            raise ConfigError(f"{key}: expected comma-separated integers, got {text!r}") from None
        if not vals or min(vals) < 1:
            raise ConfigError(f"{key}: expected integers >= 1, got {text!r}")
        return vals

    motion = ladder(args.spp, converge.QUICK_MOTION_LADDER if args.quick else converge.DEFAULT_MOTION_LADDER, "--spp")
    naive = ladder(
        args.naive_spp, converge.QUICK_NAIVE_LADDER if args.quick else converge.DEFAULT_NAIVE_LADDER, "--naive-spp"
    )
    ref_spp = args.ref_spp or (64 if args.quick else 256)
    out = args.out or Path("out") / f"converge_{args.config.stem}"

    check_out_dir(out)  # before the ladders run, not after
    result = converge.run_converge(
        cfg, motion, naive, ref_spp=ref_spp, ref_motion_div=4.0 if args.quick else 8.0, progress=print
    )
    converge.write_outputs(result, out)
    print(f"slopes of log error vs log time: {result['slopes']} (Monte Carlo: -0.5)")
    for s in result["speedups"]:
        print(
            f"equal error {s['error']:.3e}: naive {s['naive_s']:.2f} s (spp {s['naive_spp']}) vs planner "
            f"{s['planner_s']:.2f} s: {s['speedup']:.1f}x{' (extrapolated)' if s['extrapolated'] else ''}"
        )
    print(f"wrote {out}/converge.png, converge.csv, converge.json")
    return 0


def _cmd_sweep(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected a number of processes >= 1, got {args.workers}")
    sweep = load_sweep(args.sweep, args.overrides)
    out = args.out or Path("out") / f"sweep_{resolve_sweep_path(args.sweep).stem}"
    say = (lambda line: None) if args.silent else print
    try:
        outcome = run_sweep(
            sweep,
            out,
            workers=args.workers,
            scheduler=args.scheduler,
            resume=args.resume,
            progress=_shows_progress(args),
            in_process=args.in_process,
            say=say,
        )
    except KeyboardInterrupt:
        print(
            f"mbcapture: interrupted; the points that finished are kept in {out}/rows (--resume goes on from there)",
            file=sys.stderr,
        )
        return 130
    s = outcome.summary
    say(
        f"{s['ok']} of {s['points']} points ok, {s['failed']} failed; {s['render_groups']} render group"
        f"{'' if s['render_groups'] == 1 else 's'}; this run: "
        f"{s['ran']} points, {s['renders_rendered']} renders rendered, {s['renders_reused']} reused from the cache, "
        f"{s['points_sharing_renders']} points on their group's renders; {s['wall_s']:.1f} s"
    )
    for index, row in sorted(outcome.rows.items()):
        if row.get("status") != "ok":
            say(f"  {sweep.points[index].label} failed: {row.get('error')}")
    say(f"wrote {out}/index.html, results.parquet, results.csv")
    return 0


def _cmd_scenes(args) -> int:
    if args.file is not None:
        return _list_scene_file(args.file, args.param)
    for name in scenes.available():
        mod = scenes.load_module(name)
        print(f"{name}: {mod.DESCRIPTION}")
        _print_keys("scene", mod.Params)
    return 0


def _list_scene_file(path: Path, params: list[str]) -> int:
    """``mbcapture scenes FILE.xml``: the file's camera and the objects a config can name."""
    values = {}
    for text in params:
        name, sep, value = text.partition("=")
        if not sep or not name:
            raise ConfigError(f"--param {text!r}: expected NAME=VALUE")
        values[name] = value
    state, _ = xmlscene.parse(path, values)
    cam = xmlscene.file_camera(state)
    print(
        f"{path}: camera at {cam.origin} looking towards {cam.target}, horizontal field of view {cam.fov_deg:.2f} deg"
    )
    for o in xmlscene.file_objects(state):
        use = (
            "scene.groups (an emitter; a spot or a shape's light also scene.motion)"
            if o.kind == "Emitter" or o.emits
            else "scene.motion"
            if o.kind == "Shape"
            else "referenced by the shapes"
        )
        print(f"    {o.id:<24} {o.kind.lower():<9} {o.plugin:<18} {use}")
    print("files read: " + ", ".join(str(f) for f in xmlscene.referenced_files(state)))
    return 0


def _print_keys(prefix: str, model) -> None:
    for key, f in model.model_fields.items():
        print(f"    {prefix}.{key} = {f.get_default(call_default_factory=True)!r}    {f.description or ''}")


def _cmd_figures(args) -> int:
    if args.list:
        for name in figures.names():
            spec = figures.spec(name)
            print(f"{name}: {spec.title} ({spec.paper})")
        return 0
    entries = figures.make_figures(
        args.out, quick=args.quick, only=args.only, seed=args.seed, progress=_shows_progress(args)
    )
    if not args.silent:
        for e in entries:
            print(f"{e['name']:<24} {e['seconds']:7.1f} s  {e['title']}")
        print(f"wrote {args.out}/index.html")
    return 0


def _cmd_apps(args) -> int:
    by_app: dict[str, list[str]] = {}
    for p in apps.protocol_names():
        by_app.setdefault(apps.protocol_app(p), []).append(p)
    for name in apps.names():
        app = apps.get(name)
        print(
            f"{name}: {app.description}  (protocols: {', '.join(by_app.get(name, [])) or 'any, chosen with app.name'})"
        )
        _print_keys("app", app.params)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    handlers = {
        "run": _cmd_run,
        "plan": _cmd_plan,
        "scenes": _cmd_scenes,
        "apps": _cmd_apps,
        "figures": _cmd_figures,
        "converge": _cmd_converge,
        "cache": _cmd_cache,
        "sweep": _cmd_sweep,
        "characterize": _cmd_characterize,
        "snr": _cmd_snr,
        "design": _cmd_design,
    }
    # SIGTERM (kill, a batch system's time limit) ends a run like Ctrl-C: staging removed, outputs untouched
    previous = (
        signal.signal(signal.SIGTERM, _terminated) if threading.current_thread() is threading.main_thread() else None
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", ConfigNotice)
            shown = warnings.showwarning
            warnings.showwarning = lambda message, category, *a, **k: (
                print(f"mbcapture: note: {message}", file=sys.stderr)
                if issubclass(category, ConfigNotice)
                else shown(message, category, *a, **k)
            )
            return handlers[args.command](args)
    except MBCaptureError as exc:
        print(f"mbcapture: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except BrokenPipeError:  # output piped into e.g. `head`, which stopped reading
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("mbcapture: interrupted; no output was changed", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _terminated(signum, frame):
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
