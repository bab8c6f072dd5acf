"""Measure what runs use of the machine against what `mbcapture plan` says they need.

    python scripts/resources.py [--configs metronome_hdr,flash_matting] [--sizes 320x256,640x512] [--spp 4]
                                [--band-rows 64 --tiles 8]

For each config and film size: the planned peak memory and output size (mbcapture.exposure.resources), and
a real `mbcapture run` in a child process (render cache off, fixed spp): its peak resident memory
(the child's VmHWM: getrusage's ru_maxrss carries the parent's across exec) and the bytes it wrote
to --out. Prints the ratio measured / planned for each, and the per-pixel slope of the memory between the first two sizes (what the constants of
mbcapture/exposure/resources.py were fitted to; docs/resources.md has the table). With ``--tiles N`` (and
``--band-rows``, so that a small film has several bands) the runs go through their films in N
tiles of rows, and the planned memory is the tiled plan's (what HELD_PER_BUCKET_SAMPLE was fitted to).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mbcapture import load_config  # noqa: E402
from mbcapture.exposure import resources  # noqa: E402
from mbcapture.capture.pipeline import prepare  # noqa: E402


def overrides(w: int, h: int, spp: int, tiles: int | None, band_rows: int | None) -> list[str]:
    out = [f"render.width={w}", f"render.height={h}", f"render.spp={spp}", "render.cache=off"]
    out += [] if tiles is None else [f"render.tiles={tiles}"]
    return out + ([] if band_rows is None else [f"render.band_rows={band_rows}"])


def planned(config: Path, sets: list[str]) -> resources.Resources:
    cfg = load_config(config, sets)
    _, timeline, plan, _ = prepare(cfg)
    return resources.plan_resources(cfg, timeline, plan, cfg.app.resolve(cfg.capture.protocol)[0])


def measured(config: Path, sets: list[str]) -> tuple[float, float]:
    """(peak RSS bytes, bytes written) of one run in a child process."""
    child = (
        "import resource, sys; from mbcapture import load_config, run_capture; "
        "cfg = load_config(sys.argv[1], sys.argv[3:]); run_capture(cfg, sys.argv[2], progress=False); "
        "from mbcapture.exposure.resources import peak_rss_bytes; print(peak_rss_bytes())"
    )
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        proc = subprocess.run(
            [sys.executable, "-c", child, str(config), str(out), *sets], capture_output=True, text=True, cwd=ROOT
        )
        if proc.returncode != 0:
            raise SystemExit(f"{config.name} {' '.join(sets)} failed:\n{proc.stderr[-2000:]}")
        written = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        shutil.rmtree(out, ignore_errors=True)
    return float(proc.stdout.strip().splitlines()[-1]), float(written)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--configs",
        default="metronome_hdr,flash_no_flash,flash_matting,multi_flash,structured_light,"
        "moving_light,rgb_illumination,flutter_shutter,burst",
    )
    ap.add_argument("--sizes", default="320x256,640x512")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--tiles", type=int, default=None, help="render.tiles of every run (default: as planned)")
    ap.add_argument("--band-rows", type=int, default=None, help="render.band_rows of every run")
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    print(
        f"{'config':20s} {'film':>9s} {'memory MB':>10s} {'planned':>8s} {'ratio':>6s} {'outputs MB':>11s} "
        f"{'planned':>8s} {'ratio':>6s} {'slope B/px':>10s}"
    )
    for name in args.configs.split(","):
        config = ROOT / "configs" / f"{name}.yaml"
        rows = []
        for w, h in sizes:
            sets = overrides(w, h, args.spp, args.tiles, args.band_rows)
            need = planned(config, sets)
            rss, written = measured(config, sets)
            rows.append((w * h, rss))
            slope = (rss - rows[0][1]) / (w * h - rows[0][0]) if len(rows) > 1 else float("nan")
            print(
                f"{name:20s} {f'{w}x{h}':>9s} {rss / 2**20:10.0f} {need.memory_bytes / 2**20:8.0f} "
                f"{rss / need.memory_bytes:6.2f} {written / 2**20:11.2f} {need.output_bytes / 2**20:8.2f} "
                f"{written / need.output_bytes:6.2f} {slope:10.0f}"
                + (f"  ({need.tiles} tiles)" if need.tiles > 1 else ""),
                flush=True,
            )
    print(f"(this process: {resources.peak_rss_bytes() / 2**20:.0f} MiB)")


if __name__ == "__main__":
    main()
