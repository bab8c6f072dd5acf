"""What each camera part costs in run time at 640x512, measured in one run (issue 23).

    python scripts/camera_cost.py [--spp 16] [--repeats 3]

Render stage: one 16-spp render of the metronome (all groups) with each lens part on, against the
pinhole, best of ``--repeats`` warm renders at new scene times. Sensor stage: one simulate_reads
of the default capture's four buckets and four cumulative reads, with the row and column fixed
pattern and temporal row noise on, and on a Bayer sensor with each demosaicing, against without. Prints seconds and the ratio to the baseline
(these machines are shared: compare ratios from one run, not seconds across runs).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mbcapture.config import load_config, scene_of
from mbcapture.render import Renderer
from mbcapture.sensor import simulate_reads

FILM = ["render.width=640", "render.height=512"]
LENS = {
    "pinhole": [],
    "thin lens": ["camera.lens=thin"],
    "cos4 vignetting": ["camera.vignetting=cos4"],
    "diffraction": ["camera.diffraction=true"],
    "distortion": ["camera.distortion=[-0.1]"],
    "mono sensor": ["sensor.cfa=mono"],
}
FPN = [
    "sensor.prnu_row=0.004",
    "sensor.prnu_col=0.003",
    "sensor.dsnu_row_e=0.6",
    "sensor.dsnu_col_e=0.8",
    "sensor.read_noise_row_e=0.5",
]


def best(fn, repeats: int) -> float:
    times = []
    for i in range(repeats):
        t = time.perf_counter()
        fn(i)
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    render = {}
    for name, extra in LENS.items():
        cfg = load_config("metronome_hdr", FILM + extra)
        r = Renderer.from_config(scene_of(cfg), cfg)
        r.render(0.0, args.spp, 1)  # compiles
        render[name] = best(lambda i: r.render(0.001 * (i + 1), args.spp, 2 + i), args.repeats)
    print(f"render stage, {args.spp} spp at 640x512:")
    for name, s in render.items():
        print(f"  {name:16s} {s:6.2f} s   x{s / render['pinhole']:.2f}")
    expected = np.random.default_rng(0).uniform(0, 4000, (4, 512, 640, 3))
    reads = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]
    sensor = {}
    stages = {
        "pixel fixed pattern": [],
        "+ row/column and row noise": FPN,
        **{
            f"Bayer RGGB, {m}": ["sensor.cfa=RGGB", f"sensor.demosaic={m}"]
            for m in ("bilinear", "malvar2004", "menon2007")
        },
    }
    for name, extra in stages.items():
        cfg = load_config("metronome_hdr", FILM + extra).sensor
        sensor[name] = best(lambda i: simulate_reads(expected, reads, cfg, 10 + i, storage_s=[0.008] * 4), args.repeats)
    print("sensor stage, 4 buckets and 4 reads at 640x512:")
    base = sensor["pixel fixed pattern"]
    for name, s in sensor.items():
        print(f"  {name:28s} {s:6.2f} s   x{s / base:.2f}")


if __name__ == "__main__":
    main()
