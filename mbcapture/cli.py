"""Command line: ``mbcapture run | plan | scenes | apps``.

Input errors (config, files, environment) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .errors import MBCaptureError

EXIT_INPUT = 2


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, help="YAML config, e.g. configs/metronome_hdr.yaml")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key by its dotted path; VALUE is YAML (e.g. render.spp=4, scene.radiance=[1,1,1])",
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mbcapture", description="Multi-bucket sensor capture simulator (Mitsuba 3).")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="render, simulate the sensor, reconstruct, write outputs")
    _add_config_args(run)
    run.add_argument("--out", type=Path, default=None, help="output folder (default: out/<config name>)")
    run.add_argument("--quiet", action="store_true", help="no progress bar or summary")

    plan = sub.add_parser("plan", help="show what would be rendered, without rendering")
    _add_config_args(plan)
    plan.add_argument("--json", action="store_true", help="print the plan as JSON")

    sub.add_parser("scenes", help="list the scenes and their parameters")
    sub.add_parser("apps", help="list the applications (reconstructions), their protocols and parameters")
    return p


def _cmd_run(args) -> int:
    from .capture import run_capture
    from .config import load_config

    cfg = load_config(args.config, args.overrides)
    out = args.out or Path("out") / args.config.stem
    result = run_capture(cfg, out, progress=not args.quiet)
    if not args.quiet:
        r = result.report
        print(f"wrote {out}/  ({r['plan']['passes']} render passes x {r['plan']['spp']} spp, "
              f"{r['timings_s']['total_before_write']:.1f} s)")
        for line in result.app_output.summary:
            print(line)
    return 0


def _cmd_plan(args) -> int:
    from .capture import describe, prepare
    from .config import load_config

    cfg = load_config(args.config, args.overrides)
    _, timeline, plan, _ = prepare(cfg)
    info = describe(cfg, timeline, plan)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"scene {info['scene']}, protocol {info['protocol']}{' (sequential, conventional sensor)' if timeline.sequential else ''}, "
          f"film {cfg.render.width}x{cfg.render.height}, capture span {info['capture_span_s'] * 1e3:.4g} ms")
    print("reads:")
    for r in info["reads"]:
        print(f"  {r['name']}: buckets {r['buckets']}, exposure {r['exposure_s'] * 1e3:.4g} ms, "
              f"span {r['span_s'] * 1e3:.4g} ms, centroid {r['centroid_s'] * 1e3:.4g} ms")
    s = info["plan"]
    print(f"render: {s['passes']} passes x {s['spp']} spp, groups {s['groups_rendered']}"
          + (f" (left out: {s['groups_left_out']})" if s["groups_left_out"] else ""))
    print(f"image motion during the capture: {s['image_motion_px_total']:.2f} px (at most {s['max_motion_px']} px per stratum)")
    for n in s["notes"]:
        print(f"note: {n}")
    return 0


def _cmd_scenes(args) -> int:
    from . import scenes

    for name in scenes.available():
        mod = scenes.load_module(name)
        print(f"{name}: {mod.DESCRIPTION}")
        for key, f in mod.Params.model_fields.items():
            print(f"    scene.{key} = {f.default!r}    {f.description or ''}")
    return 0


def _cmd_apps(args) -> int:
    from . import apps, protocols

    by_app: dict[str, list[str]] = {}
    for p in protocols.names():
        by_app.setdefault(protocols.default_app(p), []).append(p)
    for name in apps.names():
        app = apps.get(name)
        print(f"{name}: {app.description}  (protocols: {', '.join(by_app.get(name, [])) or 'custom only'})")
        for key, f in app.params.model_fields.items():
            print(f"    app.{key} = {f.default!r}    {f.description or ''}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    handlers = {"run": _cmd_run, "plan": _cmd_plan, "scenes": _cmd_scenes, "apps": _cmd_apps}
    try:
        return handlers[args.command](args)
    except MBCaptureError as exc:
        print(f"mbcapture: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("mbcapture: interrupted; no output was changed", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
