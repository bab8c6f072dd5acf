"""Every shipped single-capture config on a Bayer sensor (sensor.cfa RGGB) and without a colour filter array,
at a small film: the application's relMSE and PSNR metrics side by side, and how many samples of each image
it returns are negative where they are valid (an HDR merge's ``valid`` layer, else everywhere).

    python scripts/cfa_apps.py [CONFIG ...] [--size 128x96] [--spp 8] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mbcapture import load_config
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = [
    "metronome_hdr",
    "moving_light",
    "flash_no_flash",
    "multi_flash",
    "flash_matting",
    "rgb_illumination",
    "structured_light",
    "flutter_shutter",
    "metronome_shake",
    "camera_full",
]  # a coded capture refuses a mosaic
#: The images that are not radiance (their sign means nothing here).
NOT_RADIANCE = ("sigma", "diff", "error", "delta_e", "alpha", "phase", "depth", "code", "valid", "moving", "mask")


def scores(metrics: dict, prefix: str = ""):
    """The report's error metrics, flattened: relMSE, PSNR, CIEDE2000, MAE and RMSE ones."""
    for key, value in metrics.items():
        if isinstance(value, dict):
            yield from scores(value, f"{prefix}{key}.")
        elif isinstance(value, (int, float)) and any(s in key for s in ("rel_mse", "psnr", "delta_e", "mae", "rmse")):
            yield prefix + key, float(value)


def negatives(images: dict) -> dict:
    valid = images.get("valid")
    out = {}
    for name, image in images.items():
        if image.ndim != 3 or image.dtype.kind != "f" or any(s in name for s in NOT_RADIANCE):
            continue
        where = valid > 0 if valid is not None and valid.shape == image.shape else np.ones(image.shape, bool)
        count = int(((image < 0) & where).sum())
        if count:
            out[name] = count
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("configs", nargs="*", default=CONFIGS)
    ap.add_argument("--size", default="128x96")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    args = ap.parse_args()
    w, h = args.size.split("x")
    table = {}
    for name in args.configs:
        row = {}
        for cfa in ("none", "RGGB"):
            cfg = load_config(
                ROOT / "configs" / f"{name}.yaml",
                [f"render.width={w}", f"render.height={h}", f"render.spp={args.spp}", f"sensor.cfa={cfa}"],
            )
            result = capture_in_memory(cfg, StageStatus(False))
            row[cfa] = {"metrics": dict(scores(result.report["metrics"])), "negative": negatives(result.images)}
        table[name] = row
        print(
            f"{name}  (negative valid samples: none {row['none']['negative'] or 0}, "
            f"RGGB {row['RGGB']['negative'] or 0})"
        )
        for key, plain in row["none"]["metrics"].items():
            bayer = row["RGGB"]["metrics"].get(key)
            print(f"    {key:<52} {plain:10.4g} {bayer if bayer is None else format(bayer, '10.4g')}")
    if args.json:
        args.json.write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
